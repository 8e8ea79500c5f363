"""`physfuse evaluate`: an estimate against ground truth, or a held-out sensor predicted.

    physfuse evaluate ESTIMATE.mcap --truth LOG.mcap [--config CONFIG] [--out DIR]
    physfuse evaluate LOG.mcap --config CONFIG --holdout STREAM [--out DIR]

The first compares the `/estimate/...` topics of ESTIMATE.mcap with the `/ground_truth/...`
topics of LOG.mcap (`estimator/evaluate.py: compare_states`); with the log's config it also
evaluates the raw measurements (interpolated to the estimate's knots, where the smoother
starts) and the errors while each tracked body's mocap was occluded.

The second estimates the log without STREAM, then predicts STREAM's measurements from the
estimate through the model's own MuJoCo sensors (the estimator's: `model_with_sensors` on the
full config), at the stream's sample times, and reports the prediction error per channel. It
needs no ground truth.

Both write DIR/metrics.json and print a table.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import mujoco
import numpy as np
from tqdm import tqdm

from estimator.batch import estimate
from estimator.config import MOCAP_KINDS, Config, load_config
from estimator.errors import LogError, PhysfuseError
from estimator.evaluate import (
    SUMMARY_KEYS,
    channel_errors,
    compare_states,
    gap_intervals,
    intersect_intervals,
    json_ready,
)
from estimator.factors import UNITS
from estimator.io.logs import Measurement, read_log
from estimator.io.mcap_writer import body_twist, state_data
from estimator.io.outputs import OutputFile
from estimator.io.state_topics import PREFIX, Series, StateTopics, read_metadata, read_state_topics
from estimator.model_checks import check_for_estimate
from estimator.problem import (
    accelerations,
    build_problem,
    model_with_sensors,
    velocities,
)
from estimator.run import initial_trajectory
from estimator.settings import Settings
from physics.errors import PhysicsError
from physics.knots import KnotEngine
from physics.model import load_model

_OBJ = mujoco.mjtObj


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "input", type=Path, metavar="ESTIMATE|LOG", help="estimate.mcap (or the log: --holdout)"
    )
    parser.add_argument("--truth", type=Path, metavar="LOG", help="log with /ground_truth topics")
    parser.add_argument("--config", type=Path, help="the log's config (occlusions, raw, holdout)")
    parser.add_argument("--holdout", metavar="STREAM", help="estimate without STREAM, predict it")
    parser.add_argument(
        "--out",
        type=Path,
        help="output dir (default: the estimate's folder; holdout: out/evaluate)",
    )
    parser.add_argument(
        "--estimate-prefix",
        default="/estimate",
        help="topic prefix of the states to evaluate (default /estimate)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    out = _out(args)
    with OutputFile(out / "metrics.json") as tmp:  # checked and locked before the work
        if args.holdout is not None:
            report = holdout(args.input, args.config, args.holdout, quiet=args.quiet)
        else:
            config = _config(args.config) if args.config is not None else None
            report = against_truth(args.input, args.truth, config, args.estimate_prefix)
        tmp.write_text(json.dumps(json_ready(report), indent=2) + "\n")
    if args.holdout is not None:
        _print_holdout(report["holdout"])
    else:
        _print_truth(report)
    print(f"wrote {out / 'metrics.json'}")
    return 0


def _out(args: argparse.Namespace) -> Path:
    """The output folder, once the options are known to fit together."""
    if args.holdout is not None:
        if args.truth is not None:
            raise PhysfuseError("--holdout estimates the log itself: drop --truth")
        if args.config is None:
            raise PhysfuseError("--holdout needs the log's --config CONFIG")
        return args.out or Path("out/evaluate") / f"{args.input.stem}_holdout_{args.holdout}"
    if args.truth is None:
        raise PhysfuseError(
            "give --truth LOG (a log with ground truth), or --holdout STREAM with --config"
        )
    return args.out or args.input.parent


def _config(path: Path) -> Config:
    return load_config(path)


# -- against ground truth -------------------------------------------------------------------------
def against_truth(
    estimate_path: Path, truth_path: Path, config: Config | None, prefix: str = "/estimate"
) -> dict[str, Any]:
    """metrics.json of an estimate file against a log's ground truth (see module docstring)."""
    est = read_state_topics(estimate_path, prefix)
    truth = read_state_topics(truth_path, PREFIX)
    notes = shared_states(est, truth)  # (an error where they share nothing to compare)
    for note in notes:
        print(f"physfuse evaluate: warning: {note}", file=sys.stderr)
    model = config.load_model() if config is not None else _model_of(estimate_path, truth_path)
    est = _renamed_imus(est, truth, config, read_metadata(truth_path))
    occlusions = raw = None
    if config is not None:
        log = read_log(truth_path, config, require=False)
        t_ns = _knot_times(est)
        occlusions = mocap_occlusions(config, model, log.measurements, int(t_ns[0]), int(t_ns[-1]))
        qpos = initial_trajectory(model, log.measurements, t_ns)
        raw = compare_states(states_from_qpos(model, t_ns, qpos), truth, model, occlusions)
    else:
        notes.append("no --config: occlusion metrics and the raw measurements are skipped")
    if est.imu_bias and not truth.imu_bias:
        notes.append(
            f"{truth_path} has no {PREFIX}/imu_bias topics (simulated before they were "
            "written): IMU bias metrics skipped"
        )
    metrics = compare_states(est, truth, model, occlusions)
    return {
        "estimate": str(estimate_path),
        "truth": str(truth_path),
        "config": str(config.path) if config is not None else None,
        "summary": metrics.pop("summary"),
        "raw_summary": raw["summary"] if raw is not None else None,
        "details": metrics,
        "notes": notes,
    }


def shared_states(est: StateTopics, truth: StateTopics) -> list[str]:
    """Check that an estimate and a truth share bodies (odometry) or joints over a common
    time, which every metric needs: a PhysfuseError naming both files and what each has where
    they do not (its metrics would all be NaN); one warning per side with bodies or joints
    the other lacks (left out of the metrics)."""
    bodies = [b for b in est.odometry if b in truth.odometry]
    joints = [j for j in est.joint_names if j in truth.joint_names]
    if not bodies and not joints:
        raise PhysfuseError(
            f"{est.path} and {truth.path} share no body or joint to compare (an estimate of "
            f"another robot or model?): {est.path} ({est.prefix}) has {_contents(est)}; "
            f"{truth.path} ({truth.prefix}) has {_contents(truth)}"
        )
    spans = [(est.odometry[b].t_ns, truth.odometry[b].t_ns) for b in bodies]
    if joints and est.joints is not None and truth.joints is not None:
        spans.append((est.joints.t_ns, truth.joints.t_ns))
    if not any(e[0] <= t[-1] and t[0] <= e[-1] for e, t in spans):
        e, t = spans[0]
        raise PhysfuseError(
            f"{est.path} and {truth.path} share no time (an estimate of another log?): the "
            f"estimate's states span {e[0] / 1e9:.3f}–{e[-1] / 1e9:.3f} s, the truth's "
            f"{t[0] / 1e9:.3f}–{t[-1] / 1e9:.3f} s (header stamps)"
        )
    warnings = []
    for side, states, other in (("estimate", est, truth), ("truth", truth, est)):
        only_bodies = [b for b in states.odometry if b not in other.odometry]
        only_joints = [j for j in states.joint_names if j not in other.joint_names]
        if only_bodies or only_joints:
            what = "; ".join(
                f"{kind} {_listed(names)}"
                for kind, names in (("bodies", only_bodies), ("joints", only_joints))
                if names
            )
            warnings.append(
                f"only the {side} ({states.path}) has {what}: left out; the metrics compare the "
                f"{len(bodies)} bodies and {len(joints)} joints both have"
            )
    return warnings


def _contents(states: StateTopics) -> str:
    """'bodies a, b; joints c, d, … (12)' of a state file."""
    bodies = _listed(list(states.odometry)) if states.odometry else "none"
    joints = _listed(list(states.joint_names)) if states.joint_names else "none"
    return f"bodies {bodies}; joints {joints}"


def _listed(names: list[str], most: int = 6) -> str:
    """Up to `most` names, then how many there are."""
    if len(names) <= most:
        return ", ".join(names)
    return ", ".join(names[:most]) + f", … ({len(names)})"


def _model_of(*paths: Path) -> mujoco.MjModel:
    """The model named in an estimate's (`physfuse.estimate`) or a simulated log's metadata:
    the first that loads (an older estimate names its model as its config did, relative to
    the config's folder)."""
    failed = []
    for path in paths:
        meta = read_metadata(path)
        for record in ("physfuse.estimate", "physfuse.simulation"):
            name = meta.get(record, {}).get("model")
            if name:
                try:
                    return load_model(name)
                except PhysicsError as err:
                    failed.append(f"{path} names model {name!r}, which does not load ({err})")
    if failed:
        raise PhysfuseError(f"{'; '.join(failed)}; pass --config")
    raise PhysfuseError(f"{paths[0]}: no metadata names the model; pass --config CONFIG")


def _knot_times(states: StateTopics) -> np.ndarray:
    if states.joints is not None:
        return states.joints.t_ns
    return next(iter(states.odometry.values())).t_ns


def _renamed_imus(
    est: StateTopics, truth: StateTopics, config: Config | None, metadata: Mapping[str, Any]
) -> StateTopics:
    """The estimate with its IMU streams named as the simulator's IMU sensors: the same name,
    else the sensor whose topic (log metadata `physfuse.sensors`) is the stream's topic, else
    the only IMU on each side."""
    sensors = metadata.get("physfuse.sensors", {})
    topic_of_sensor = {}
    for name, text in sensors.items():
        try:
            topic_of_sensor[name] = json.loads(text).get("topic")
        except (json.JSONDecodeError, AttributeError):
            continue
    renamed = {}
    for stream, series in est.imu_bias.items():
        name = stream
        if stream not in truth.imu_bias:
            topic = config.streams[stream].topic if config and stream in config.streams else None
            by_topic = [s for s, t in topic_of_sensor.items() if t == topic and topic is not None]
            if by_topic and by_topic[0] in truth.imu_bias:
                name = by_topic[0]
            elif len(est.imu_bias) == 1 and len(truth.imu_bias) == 1:
                name = next(iter(truth.imu_bias))
        renamed[name] = series
    return replace(est, imu_bias=renamed)


def mocap_occlusions(
    config: Config,
    model: mujoco.MjModel,
    measurements: Mapping[str, Measurement],
    start_ns: int,
    end_ns: int,
) -> dict[str, np.ndarray]:
    """Body → (n, 2) intervals within [start, end] in which no mocap stream saw the body.

    A pose sample sees its body; a markers sample sees a body when at least 3 of its markers
    (all of them, if it has fewer) are in it. Each stream's occlusions are its gaps longer than
    `OCCLUSION_GAP_PERIODS` sample periods; a body tracked by several streams is occluded
    where all of them are.
    """
    out: dict[str, np.ndarray] = {}
    for name, stream in config.streams.items():
        m = measurements.get(name)
        if stream.kind not in MOCAP_KINDS or m is None:
            continue
        for body, columns in _bodies_of(model, stream.element_type, m.elements).items():
            seen = np.isfinite(m.values[:, columns, 0])  # (N, columns)
            need = min(3, len(columns)) if stream.kind == "markers" else 1
            visible = m.t_ns[seen.sum(axis=1) >= need]
            gaps = gap_intervals(visible, start_ns, end_ns)
            out[body] = intersect_intervals(out[body], gaps) if body in out else gaps
    return out


def _bodies_of(
    model: mujoco.MjModel, element_type: str, elements: tuple[str, ...]
) -> dict[str, list[int]]:
    """Body name → the element columns (sites or bodies) on it."""
    out: dict[str, list[int]] = {}
    for i, element in enumerate(elements):
        if element_type == "site":
            body = int(model.site_bodyid[mujoco.mj_name2id(model, _OBJ.mjOBJ_SITE, element)])
        else:
            body = mujoco.mj_name2id(model, _OBJ.mjOBJ_BODY, element)
        out.setdefault(mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, body), []).append(i)
    return out


def states_from_qpos(model: mujoco.MjModel, t_ns: np.ndarray, qpos: np.ndarray) -> StateTopics:
    """A trajectory qpos (T, nq) on knots t_ns as state topics (odometry of the free bodies
    with v_k = (q_k ⊖ q_{k−1})/h, joint positions and velocities; no contacts)."""
    h = float(np.median(np.diff(t_ns))) / 1e9
    qvel = velocities(model, qpos, h)
    free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    scalar = [j for j in range(model.njnt) if model.jnt_type[j] in (2, 3)]  # slide, hinge
    odometry: dict[str, list[np.ndarray]] = {
        mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, model.jnt_bodyid[j]): [] for j in free
    }
    data = mujoco.MjData(model)
    for k in range(len(t_ns)):
        state_data(model, qpos[k], qvel[k], data)
        for j in free:
            body = int(model.jnt_bodyid[j])
            twist = body_twist(model, data, body)
            row = np.r_[data.xpos[body], data.xquat[body], twist[3:], twist[:3], np.full(9, np.nan)]
            odometry[mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, body)].append(row)
    joints = np.stack(
        [qpos[:, model.jnt_qposadr[scalar]], qvel[:, model.jnt_dofadr[scalar]]], axis=2
    )
    effort = np.full_like(joints[:, :, :1], np.nan)
    return StateTopics(
        path="raw",
        prefix="raw",
        odometry={b: Series(t_ns, np.array(rows)) for b, rows in odometry.items()},
        joint_names=tuple(mujoco.mj_id2name(model, _OBJ.mjOBJ_JOINT, j) for j in scalar),
        joints=Series(t_ns, np.concatenate([joints, effort], axis=2).reshape(len(t_ns), -1)),
        contact_wrench={},
        imu_bias={},
    )


def _print_truth(report: dict[str, Any]) -> None:
    raw = report["raw_summary"] or {}
    print(f"{report['estimate']} against the ground truth of {report['truth']} (RMSE):")
    print(f"  {'metric':34s} {'estimate':>10s} {'raw':>10s}")
    for key in SUMMARY_KEYS:
        value, raw_value = report["summary"][key], raw.get(key, float("nan"))
        print(f"  {key:34s} {value:10.4g} {raw_value:10.4g}")
    for body, d in report["details"]["contacts"].items():
        print(
            f"  contact {body:20s} force {d['force_N']:8.3g} N, precision "
            f"{d['precision']:.3f}, recall {d['recall']:.3f}"
        )
    for note in report["notes"]:
        print(f"  note: {note}")


# -- held-out sensor ------------------------------------------------------------------------------
def holdout(log_path: Path, config_path: Path, stream: str, quiet: bool = True) -> dict[str, Any]:
    """metrics.json of held-out-sensor validation (see the module docstring)."""
    config = _config(config_path)
    valid = [s.name for s in config.streams.values() if s.kind in UNITS]
    if stream not in valid:
        what = "is a command stream (no sensor measures it)" if stream in config.streams else ""
        raise PhysfuseError(
            f"--holdout {stream}: {what or 'no such stream'} in {config.path}; streams that can "
            f"be held out: {', '.join(valid)}"
        )
    reduced = replace(
        config, streams=MappingProxyType({k: v for k, v in config.streams.items() if k != stream})
    )
    settings = Settings.from_config(config)
    check_for_estimate(reduced, settings)
    log = read_log(log_path, config)
    held = log.measurements[stream]
    if not len(held):
        raise LogError(f"{log_path}: stream {stream} ({held.topic}) has no sample to predict")
    measurements = {k: v for k, v in log.measurements.items() if k != stream}
    bar = tqdm(total=0, unit="window", disable=quiet or not sys.stderr.isatty())

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    est, summary = estimate(reduced, measurements, settings, progress)
    bar.close()
    predictor = SensorPredictor(config, log.measurements, settings, est.t_ns)
    predicted = predictor.predict(stream, held.t_ns, est.qpos)
    raw_qpos = initial_trajectory(predictor.model, measurements, est.t_ns)
    raw_predicted = predictor.predict(stream, held.t_ns, raw_qpos)
    unit = UNITS[config.streams[stream].kind].holdout(config.streams[stream])
    channels, sigma = unit.names, unit.sigma
    residual = unit.residuals(predicted, held)
    raw_residual = unit.residuals(raw_predicted, held)
    acc_stage = predictor.acceleration_stage(stream, config.streams[stream].kind)
    raw_residual[:, acc_stage] = np.nan  # no raw acceleration: double differences of samples
    section: dict[str, Any] = {
        "stream": stream,
        "kind": held.kind,
        "topic": held.topic,
        "units": unit.units,
        "samples": len(held),
        "estimated_without_it": {
            "knots": summary.knots,
            "windows": summary.windows,
            "converged": all(summary.converged),
            "wall_time_s": summary.wall_time_s,
        },
        "estimate": channel_errors(residual, sigma, channels),
        "raw": channel_errors(raw_residual, sigma, channels),
        "overall_whitened_rmse": {
            "estimate": _overall(residual, sigma),
            "raw": _overall(raw_residual[:, ~acc_stage], sigma[~acc_stage]),
        },
    }
    if held.kind == "imu":
        # the held-out IMU's bias is not in an estimate made without it: one constant per
        # channel, the median residual, stands for it (6 numbers fitted to the held-out data)
        bias = np.nanmedian(residual, axis=0)
        section["estimate_with_fitted_bias"] = channel_errors(residual - bias, sigma, channels)
        section["fitted_bias"] = dict(zip(channels, bias.tolist(), strict=True))
        section["overall_whitened_rmse"]["estimate_with_fitted_bias"] = _overall(
            residual - bias, sigma
        )
    return {"log": str(log_path), "config": str(config.path), "holdout": section}


def _overall(residual: np.ndarray, sigma: np.ndarray) -> float:
    """sqrt(mean (e/σ)²) over every finite residual entry."""
    w = (residual / sigma).reshape(-1)
    w = w[np.isfinite(w)]
    return float(np.sqrt(np.mean(w**2))) if len(w) else float("nan")


class SensorPredictor:
    """A stream's sensor values predicted from a trajectory on knots t_ns: MuJoCo's sensors of
    the estimator's model (`model_with_sensors`, softness and timestep as in `build_problem`)
    evaluated by the analytic inverse at (q_k, v_k, a_k), then brought to the sample times:
    position- and velocity-stage values interpolated linearly between knots (quaternions
    renormalized), acceleration-stage values (accelerometer, force, torque) held over the step
    [t_k, t_k + h), the interval over which the Euler step applies a_k."""

    def __init__(
        self,
        config: Config,
        measurements: Mapping[str, Measurement],
        settings: Settings,
        t_ns: np.ndarray,
    ):
        self.config = config
        self.t_ns = t_ns
        model, self.sensor_names = model_with_sensors(config)
        self.problem = build_problem(
            config, measurements, settings, t_ns, (model, self.sensor_names)
        )
        self.model = self.problem.model

    def rows(self, stream: str) -> np.ndarray:
        """sensordata indices of the stream's sensors, in measurement order."""
        out = []
        for name in self.sensor_names[stream]:
            i = mujoco.mj_name2id(self.model, _OBJ.mjOBJ_SENSOR, name)
            out.append(
                np.arange(
                    self.model.sensor_adr[i], self.model.sensor_adr[i] + self.model.sensor_dim[i]
                )
            )
        return np.concatenate(out)

    def acceleration_stage(self, stream: str, kind: str) -> np.ndarray:
        """(C,) per residual channel: whether its sensor needs accelerations."""
        flags = []
        for name in self.sensor_names[stream]:
            i = mujoco.mj_name2id(self.model, _OBJ.mjOBJ_SENSOR, name)
            acc = self.model.sensor_needstage[i] == mujoco.mjtStage.mjSTAGE_ACC
            channels = (
                3
                if self.model.sensor_type[i] == mujoco.mjtSensor.mjSENS_FRAMEQUAT
                else int(self.model.sensor_dim[i])
            )
            flags += [bool(acc)] * channels
        return np.array(flags)

    def predict(self, stream: str, t_ns: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """(N, rows) the stream's sensordata at the sample times t_ns (NaN outside the knots)."""
        model, h = self.model, self.problem.h
        v = velocities(model, qpos, h)
        a = accelerations(v, h)
        engine = KnotEngine(model, self.problem.settings.path)
        rows = self.rows(stream)
        s = np.array([engine.inverse(qpos[k], v[k], a[k])[1][rows] for k in range(len(qpos))])
        k = np.clip(np.searchsorted(self.t_ns, t_ns, side="right") - 1, 0, len(self.t_ns) - 2)
        alpha = ((t_ns - self.t_ns[k]) / (self.t_ns[k + 1] - self.t_ns[k]))[:, None]
        out = (1.0 - alpha) * s[k] + alpha * s[k + 1]
        column = 0
        for name in self.sensor_names[stream]:
            i = mujoco.mj_name2id(model, _OBJ.mjOBJ_SENSOR, name)
            dim = int(model.sensor_dim[i])
            cols = slice(column, column + dim)
            if model.sensor_needstage[i] == mujoco.mjtStage.mjSTAGE_ACC:
                out[:, cols] = s[k, cols]
            if model.sensor_type[i] == mujoco.mjtSensor.mjSENS_FRAMEQUAT:
                out[:, cols] /= np.linalg.norm(out[:, cols], axis=1, keepdims=True)
            column += dim
        outside = (t_ns < self.t_ns[0]) | (t_ns > self.t_ns[-1])
        out[outside] = np.nan
        return out


def _print_holdout(section: dict[str, Any]) -> None:
    print(
        f"held out {section['stream']} ({section['kind']}, {section['samples']} samples): "
        "prediction − measurement per channel"
    )
    fitted = "estimate_with_fitted_bias" in section
    header = f"  {'channel':28s} {'RMSE':>10s} {'median|e|':>10s} {'RMSE/σ':>8s} {'raw RMSE':>10s}"
    print(header + (f" {'fitted-bias RMSE':>17s}" if fitted else ""))
    for channel, e in section["estimate"].items():
        raw = section["raw"][channel]
        line = (
            f"  {channel:28s} {e['rmse']:10.4g} {e['median_abs']:10.4g} "
            f"{e['whitened_rmse']:8.3g} {raw['rmse']:10.4g}"
        )
        if fitted:
            line += f" {section['estimate_with_fitted_bias'][channel]['rmse']:17.4g}"
        print(line)
    overall = ", ".join(f"{k} {v:.3g}" for k, v in section["overall_whitened_rmse"].items())
    print(f"  whitened RMSE over all channels: {overall}")
