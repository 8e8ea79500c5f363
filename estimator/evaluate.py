"""Metrics of an estimate against ground truth, and of predictions of a held-out sensor.

Pure functions on arrays (and on `StateTopics`, the arrays of one prefix of the shared topic
layout); `estimator/cli/evaluate.py` reads the files and prints the tables.

Conventions: an estimate sample at t is compared with the truth interpolated linearly to t
between the two truth samples around it (the truth may be sparser: `--ground-truth-every`);
`TRIM_KNOTS` knots at each end of the estimate are left out (no dynamics factor reaches the
outermost knots). RMSE of vectors is
sqrt(mean_n ‖e_n‖²); of scalars (joint angles) sqrt(mean e²) over every entry.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import mujoco
import numpy as np

from estimator.io.state_topics import Series, StateTopics, at_times
from estimator.rotations import heading, rotation_angles
from physics.model import weight as model_weight

TRIM_KNOTS = 2
CONTACT_WEIGHT_FRACTION = 0.01  # "in contact": net contact force above 1% of the weight
OCCLUSION_GAP_PERIODS = 2.5  # a mocap gap longer than this many sample periods: occluded

TRAJECTORY_KEYS = (  # the motion's errors: pose, joint angles, velocities
    "position_mm",
    "orientation_deg",
    "joint_deg",
    "linear_velocity_mps",
    "angular_velocity_dps",
    "joint_velocity_dps",
)
FORCE_KEYS = ("contact_force_N", "contact_force_pct_weight")
# what proprioception alone cannot hold (no mocap): of the body that travels farthest, the
# growth of its horizontal position error over the path it travelled, of its yaw error per
# metre, and its tilt error (the angle between the true and estimated up axes, RMS)
DRIFT_KEYS = ("position_drift_pct", "yaw_drift_deg_per_m", "tilt_deg")
# the same errors over the occlusions: a body's pose and twist over its own, the joints and
# contact forces over any body's
OCCLUDED_KEYS = tuple(f"occluded_{key}" for key in (*TRAJECTORY_KEYS, *FORCE_KEYS))
SUMMARY_KEYS = (
    *TRAJECTORY_KEYS,
    *FORCE_KEYS,
    "contact_precision",
    "contact_recall",
    "imu_accel_bias_mps2",
    "imu_gyro_bias_dps",
    *OCCLUDED_KEYS,
    "occluded_s",
    "position_anees",
    *DRIFT_KEYS,
)


# -- elementary metrics ---------------------------------------------------------------------------
def rmse(errors: np.ndarray) -> float:
    """sqrt(mean_n ‖e_n‖²) over the rows of errors (N,) or (N, k) that are finite; NaN if none."""
    e = np.asarray(errors, dtype=float)
    e = e.reshape(len(e), -1) if e.size else e.reshape(0, 1)
    ok = np.all(np.isfinite(e), axis=1)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.sum(e[ok] ** 2, axis=1))))


def in_contact(force: np.ndarray, threshold: float) -> np.ndarray:
    """(N,) whether the net contact force (N, 3) exceeds the threshold in norm."""
    return np.linalg.norm(force, axis=1) > threshold


def precision_recall(predicted: np.ndarray, actual: np.ndarray) -> tuple[float, float]:
    """Precision TP/(TP+FP) and recall TP/(TP+FN) of boolean sequences; NaN where undefined
    (nothing predicted, or nothing to find)."""
    predicted, actual = np.asarray(predicted, bool), np.asarray(actual, bool)
    tp = np.sum(predicted & actual)
    precision = tp / predicted.sum() if predicted.any() else float("nan")
    recall = tp / actual.sum() if actual.any() else float("nan")
    return float(precision), float(recall)


def gap_intervals(
    t_ns: np.ndarray, start_ns: int, end_ns: int, max_gap_ns: float | None = None
) -> np.ndarray:
    """(n, 2) int64 intervals within [start, end] with no sample for longer than max_gap_ns
    (default OCCLUSION_GAP_PERIODS median sample periods): between two samples (open), and
    before the first or after the last sample. No sample at all: the whole span."""
    t = np.sort(np.asarray(t_ns, dtype=np.int64))
    t = t[(t >= start_ns) & (t <= end_ns)]
    if len(t) == 0:
        return np.array([[start_ns, end_ns]], dtype=np.int64)
    if max_gap_ns is None:
        period = float(np.median(np.diff(t))) if len(t) > 1 else float(end_ns - start_ns)
        max_gap_ns = OCCLUSION_GAP_PERIODS * period
    edges = np.concatenate([[start_ns], t, [end_ns]])
    gaps = np.diff(edges) > max_gap_ns
    return np.stack([edges[:-1][gaps], edges[1:][gaps]], axis=1).astype(np.int64)


def intersect_intervals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, 2) the pairwise overlaps of two lists of intervals (m, 2) and (k, 2)."""
    out = []
    for a0, a1 in a:
        for b0, b1 in b:
            lo, hi = max(a0, b0), min(a1, b1)
            if lo < hi:
                out.append((lo, hi))
    return np.array(sorted(out), dtype=np.int64).reshape(-1, 2)


def within(t_ns: np.ndarray, intervals: np.ndarray) -> np.ndarray:
    """(N,) whether each time lies inside one of the intervals (n, 2) (ends excluded)."""
    inside = np.zeros(len(t_ns), dtype=bool)
    for start, end in intervals:
        inside |= (t_ns > start) & (t_ns < end)
    return inside


# -- an estimate against ground truth -------------------------------------------------------------
def _matched(
    est: Series, truth: Series, trim: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t_ns, estimate values, truth values) at the estimate's samples (trimmed) that lie
    between two truth samples at most 1.5 truth periods apart, the truth interpolated linearly
    there (`truth.at_times`); None if none does."""
    t, values = est.t_ns[trim : len(est.t_ns) - trim], est.values[trim : len(est.t_ns) - trim]
    if not len(t) or len(truth.t_ns) < 2:
        return None
    period = float(np.median(np.diff(truth.t_ns)))
    i = np.searchsorted(truth.t_ns, t).clip(1, len(truth.t_ns) - 1)
    inside = (t >= truth.t_ns[0]) & (t <= truth.t_ns[-1])
    ok = inside & (truth.t_ns[i] - truth.t_ns[i - 1] <= 1.5 * period)
    if not ok.any():
        return None
    return t[ok], values[ok], at_times(truth.t_ns, truth.values, t[ok])


def _matched_by_name(
    est: Mapping[str, Series], truth: Mapping[str, Series], trim: int
) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, t_ns, estimate values, truth values) of each name both hold, by `_matched`."""
    for name in sorted(set(est) & set(truth)):
        m = _matched(est[name], truth[name], trim)
        if m is not None:
            yield name, *m


def compare_states(
    est: StateTopics,
    truth: StateTopics,
    model: mujoco.MjModel,
    occlusions: Mapping[str, np.ndarray] | None = None,
    trim: int = TRIM_KNOTS,
) -> dict[str, Any]:
    """Errors of `est` against `truth`, topic by topic: {"summary": SUMMARY_KEYS → float or
    NaN, "bodies", "joints", "contacts", "imu_bias": details per body, joint, IMU;
    "contact_threshold_N"}. The pooled contact metrics cover the bodies that touch something
    (in the truth or the estimate) at some knot.

    model: the robot (hinge joints are compared in degrees; its weight sets the contact
        threshold). occlusions: body → (n, 2) int64 intervals in which its mocap was
        occluded (None: occlusion metrics NaN).
    """
    pooled: dict[str, list[np.ndarray]] = {k: [] for k in ("pos", "rot", "lin", "ang")}
    occluded: dict[str, list[np.ndarray]] = {k: [] for k in pooled}
    spans: list[np.ndarray] = []  # every body's occlusions within its matched knots
    pooled_nees: list[np.ndarray] = []
    bodies = {}
    for body, t, e, g in _matched_by_name(est.odometry, truth.odometry, trim):
        errors = {
            "pos": e[:, :3] - g[:, :3],
            "rot": rotation_angles(e[:, 3:7], g[:, 3:7]),
            "lin": e[:, 7:10] - g[:, 7:10],
            "ang": e[:, 10:13] - g[:, 10:13],
        }
        for key, value in errors.items():
            pooled[key].append(value)
        covariance = (  # the odometry's position covariance, when it carries one
            e[:, 13:22].reshape(-1, 3, 3) if e.shape[1] >= 22 else np.full((len(e), 3, 3), np.nan)
        )
        nees = position_nees(errors["pos"], covariance)
        pooled_nees.append(nees)
        bodies[body] = (
            _body_metrics(errors)
            | {"knots": len(t), "position_anees": _mean_or_nan(nees)}
            | drift(e, g)
        )
        if occlusions is not None and body in occlusions:
            span = intersect_intervals(occlusions[body], np.array([[t[0], t[-1]]]))
            hidden = within(t, span)
            for key, value in errors.items():
                occluded[key].append(value[hidden])
            spans.append(span)
            bodies[body] |= {
                "occluded_s": float(np.sum(span[:, 1] - span[:, 0]) / 1e9),
                "occluded_intervals_s": ((span - t[0]) / 1e9).tolist(),
                "occluded_knots": int(hidden.sum()),
            } | {
                f"occluded_{k}": v
                for k, v in _body_metrics({k: v[hidden] for k, v in errors.items()}).items()
            }
    joints, joint_errors = _joint_errors(est, truth, model, trim)
    weight = model_weight(model)
    contacts, contact_errors, flags = _contact_errors(est, truth, weight, trim)
    imu, bias_errors = _bias_errors(est, truth, trim)
    hidden_ns = np.concatenate(spans) if spans else np.zeros((0, 2), dtype=np.int64)

    def pool(parts: list[np.ndarray]) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros((0, 1))

    def while_occluded(parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """The errors (t, e) of each part at the times some body's mocap was occluded."""
        return pool([e[within(t, hidden_ns)] for t, e in parts])

    precision, recall = (
        precision_recall(pool(flags["est"]), pool(flags["truth"]))
        if flags["est"]
        else (float("nan"), float("nan"))
    )

    def errors_of(
        body_parts: Mapping[str, list[np.ndarray]],
        joint_part: Mapping[str, np.ndarray],
        force_part: np.ndarray,
    ) -> dict[str, float]:
        """TRAJECTORY_KEYS and FORCE_KEYS of pooled errors."""
        force = rmse(force_part)
        return _body_metrics({k: pool(v) for k, v in body_parts.items()}) | {
            "joint_deg": float(np.degrees(rmse(joint_part["pos"]))),
            "joint_velocity_dps": float(np.degrees(rmse(joint_part["vel"]))),
            "contact_force_N": force,
            "contact_force_pct_weight": 100.0 * force / weight,
        }

    all_errors = errors_of(
        pooled,
        {k: pool([e for _, e in parts]) for k, parts in joint_errors.items()},
        pool([e for _, e in contact_errors]),
    )
    occluded_errors = errors_of(
        occluded,
        {k: while_occluded(parts) for k, parts in joint_errors.items()},
        while_occluded(contact_errors),
    )
    summary = {
        **{k: all_errors[k] for k in (*TRAJECTORY_KEYS, *FORCE_KEYS)},
        "contact_precision": precision,
        "contact_recall": recall,
        "imu_accel_bias_mps2": rmse(pool(bias_errors["accel"])),
        "imu_gyro_bias_dps": float(np.degrees(rmse(pool(bias_errors["gyro"])))),
        **{f"occluded_{k}": occluded_errors[k] for k in (*TRAJECTORY_KEYS, *FORCE_KEYS)},
        "occluded_s": _total_s(spans) if occlusions is not None else float("nan"),
        "position_anees": _mean_or_nan(pool(pooled_nees)),
    }
    farthest = max(bodies.values(), key=lambda b: b["path_m"], default=None)
    for key in DRIFT_KEYS:
        summary[key] = farthest[key] if farthest else float("nan")
    return {
        "summary": summary,
        "bodies": bodies,
        "joints": joints,
        "contacts": contacts,
        "contact_threshold_N": CONTACT_WEIGHT_FRACTION * weight,
        "imu_bias": imu,
    }


def drift(e: np.ndarray, g: np.ndarray) -> dict[str, float]:
    """DRIFT_KEYS and "path_m" of a body's estimated poses e against the true g (n, ≥ 7:
    position, quaternion w x y z): the horizontal path g travelled; the growth of the
    horizontal position error over it (%) and of the yaw error per metre of it; the tilt."""
    path = float(np.sum(np.linalg.norm(np.diff(g[:, :2], axis=0), axis=1)))
    growth = (e[-1, :2] - g[-1, :2]) - (e[0, :2] - g[0, :2])
    yaw = heading(e[:, 3:7]) - heading(g[:, 3:7])
    yaw_growth = float(np.angle(np.exp(1j * (yaw[-1] - yaw[0]))))  # wrapped to ±π
    up_e, up_g = _up(e[:, 3:7]), _up(g[:, 3:7])
    tilt = np.arctan2(np.linalg.norm(np.cross(up_e, up_g), axis=1), np.sum(up_e * up_g, axis=1))
    return {
        "path_m": path,
        "position_drift_pct": 100.0 * float(np.linalg.norm(growth)) / path if path else np.nan,
        "yaw_drift_deg_per_m": float(np.degrees(abs(yaw_growth))) / path if path else np.nan,
        "tilt_deg": float(np.degrees(rmse(tilt))),
    }


def _up(quat: np.ndarray) -> np.ndarray:
    """(n, 3) the body's z axis in the world, from quaternions (n, 4) w x y z."""
    w, x, y, z = quat.T
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)


def position_nees(errors: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """(N,) normalized estimation error squared per dof, eᵀ Σ⁻¹ e / 3, of position errors
    (N, 3) with the estimate's covariances (N, 3, 3); NaN where there is none (a method
    without covariances, an unmeasured knot). 1 on average when the covariance is honest."""
    out = np.full(len(errors), np.nan)
    ok = np.all(np.isfinite(covariance), axis=(1, 2)) & np.all(np.isfinite(errors), axis=1)
    ok[ok] = np.linalg.det(covariance[ok]) > 0
    if ok.any():
        solved = np.linalg.solve(covariance[ok], errors[ok][:, :, None])[:, :, 0]
        out[ok] = np.sum(errors[ok] * solved, axis=1) / 3.0
    return out


def _mean_or_nan(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)] if values.size else values
    return float(np.mean(finite)) if finite.size else float("nan")


def _body_metrics(errors: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Position (mm), orientation (deg), linear (m/s) and angular (deg/s) velocity RMSE of a
    body's errors {"pos", "rot", "lin", "ang"} (m, rad, m/s, rad/s)."""
    return {
        "position_mm": 1e3 * rmse(errors["pos"]),
        "orientation_deg": float(np.degrees(rmse(errors["rot"]))),
        "linear_velocity_mps": rmse(errors["lin"]),
        "angular_velocity_dps": float(np.degrees(rmse(errors["ang"]))),
    }


def _total_s(spans: list[np.ndarray]) -> float:
    """The summed length [s] of interval lists (n, 2) in ns."""
    return float(sum(np.sum(s[:, 1] - s[:, 0]) for s in spans) / 1e9)


def _joint_errors(
    est: StateTopics, truth: StateTopics, model: mujoco.MjModel, trim: int
) -> tuple[dict[str, Any], dict[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """Per hinge joint angle and velocity RMSE (deg, deg/s), and each joint's errors (rad) with
    their times (t_ns, e)."""
    details: dict[str, Any] = {}
    errors: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"pos": [], "vel": []}
    if est.joints is None or truth.joints is None:
        return details, errors
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    for name in est.joint_names:
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if name not in truth.joint_names or j < 0 or int(model.jnt_type[j]) != hinge:
            continue
        m = _matched(est.joint(name), truth.joint(name), trim)
        if m is None:
            continue
        t, e, g = m
        d = e[:, :2] - g[:, :2]
        errors["pos"].append((t, d[:, 0]))
        errors["vel"].append((t, d[:, 1]))
        details[name] = {
            "angle_deg": float(np.degrees(rmse(d[:, 0]))),
            "velocity_dps": float(np.degrees(rmse(d[:, 1]))),
        }
    return details, errors


def _contact_errors(
    est: StateTopics, truth: StateTopics, weight: float, trim: int
) -> tuple[dict[str, Any], list[tuple[np.ndarray, np.ndarray]], dict[str, list[np.ndarray]]]:
    """Per body net contact force RMSE (N) and contact precision/recall; the force errors (with
    their times: t_ns, e) of the bodies that touch something (in the truth or the estimate) and
    their in-contact flags."""
    threshold = CONTACT_WEIGHT_FRACTION * weight
    details: dict[str, Any] = {}
    errors: list[tuple[np.ndarray, np.ndarray]] = []
    flags: dict[str, list[np.ndarray]] = {"est": [], "truth": []}
    for body, t, e, g in _matched_by_name(est.contact_wrench, truth.contact_wrench, trim):
        touching_est, touching_truth = (
            in_contact(e[:, :3], threshold),
            in_contact(g[:, :3], threshold),
        )
        if not (touching_est.any() or touching_truth.any()):
            continue
        precision, recall = precision_recall(touching_est, touching_truth)
        errors.append((t, e[:, :3] - g[:, :3]))
        flags["est"].append(touching_est)
        flags["truth"].append(touching_truth)
        details[body] = {
            "force_N": rmse(e[:, :3] - g[:, :3]),
            "precision": precision,
            "recall": recall,
            "in_contact_truth": float(touching_truth.mean()),
            "in_contact_estimate": float(touching_est.mean()),
        }
    return details, errors, flags


def _bias_errors(
    est: StateTopics, truth: StateTopics, trim: int
) -> tuple[dict[str, Any], dict[str, list[np.ndarray]]]:
    """Per IMU bias RMSE (accelerometer m/s², gyro deg/s), matched by name."""
    details: dict[str, Any] = {}
    errors: dict[str, list[np.ndarray]] = {"accel": [], "gyro": []}
    for name, _, e, g in _matched_by_name(est.imu_bias, truth.imu_bias, trim):
        errors["accel"].append(e[:, :3] - g[:, :3])
        errors["gyro"].append(e[:, 3:] - g[:, 3:])
        details[name] = {
            "accel_mps2": rmse(e[:, :3] - g[:, :3]),
            "gyro_dps": float(np.degrees(rmse(e[:, 3:] - g[:, 3:]))),
            "true_accel_mps2": rmse(g[:, :3]),
            "true_gyro_dps": float(np.degrees(rmse(g[:, 3:]))),
        }
    return details, errors


# -- predictions of a held-out stream -------------------------------------------------------------
def channel_errors(
    residuals: np.ndarray, sigma: np.ndarray, channels: tuple[str, ...]
) -> dict[str, dict[str, float]]:
    """Per channel: RMSE and median |e| (the stream's units) and the whitened RMSE (e/σ),
    of residuals (N, C) (NaN where not measured); sigma (C,) the config's noise."""
    out = {}
    for c, name in enumerate(channels):
        e = residuals[:, c]
        e = e[np.isfinite(e)]
        out[name] = {
            "rmse": rmse(e),
            "median_abs": float(np.median(np.abs(e))) if len(e) else float("nan"),
            "whitened_rmse": rmse(e / sigma[c]),
            "samples": len(e),
        }
    return out


def json_ready(value: Any) -> Any:
    """A JSON-safe copy: NaN/Inf → None, numpy scalars and arrays → Python numbers and lists."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [json_ready(v) for v in value]
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    return value
