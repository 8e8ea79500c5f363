"""The floating base from proprioception, for the initial trajectory of a log without mocap:
the IMU's orientation and kinematic leg odometry (Bloesch et al., "State Estimation for Legged
Robots", RSS 2013): a foot on the ground stays where it is, so between knots the base moves by
minus the stance feet's motion relative to it, through the encoders' forward kinematics.

    R_k     the IMU's orientation (q_ref_site ⊗ site_quat⁻¹), noisy per sample, fused with its
            gyro, precise over short times (a complementary filter, ORIENTATION_GAIN, run
            backward and then forward from where that ends), its yaw turned so that the first
            knot has the start pose's; without an orientation, the gyro integrated from the
            start pose with the accelerometer's tilt (a complementary filter, TILT_GAIN); an
            IMU on a body the joints carry (a humanoid's torso): that body's, turned to the
            base's through the encoders (R_body ⊗ Q_rel⁻¹, `body_in_base`)
    c_ik    foot i's point relative to the base origin, world axes: FK(R_k, joints_k); a round
            foot's centre (sphere, a capsule's end), which rolls: c moves by Δθ_i × r_i e_z
            over a stance foot (Δθ_i its rotation, r_i its radius); a flat foot's centre
    S_k     the stance feet: the contact flags where the log has them, else the feet within
            STANCE_M of the lowest
    p_k+1   = p_k + mean over i in S_k ∩ S_k+1 of (Δθ_i × r_i e_z − (c_i,k+1 − c_ik))   (x, y)
    z_k     = mean over i in S_k of (h_i − c_ik,z + r_i)     h_i: foot i's sole's height at home

The feet are the geoms that touch the world (within FOOT_GAP_M) at the start pose. The start
pose is the model's home keyframe (else qpos0), which the config's `start_pose` (or `physfuse
estimate --start-pose`) moves; x, y and yaw are not observable from proprioception and drift
from there.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import pairwise

import mujoco
import numpy as np

from estimator.config import MOCAP_KINDS, Config
from estimator.io.logs.measurements import Measurement
from estimator.knots import interpolated_at_knots
from estimator.rotations import heading, quat_conj, quat_mul

START_POSITION_STD_M = 1e-5  # the start pose's x, y and yaw: the reference the estimate
START_YAW_STD_RAD = 1e-5  # is relative to (`MarginalPrior.start_pose`)
FOOT_GAP_M = 0.01  # a geom this close to a world geom at the start pose is a foot
STANCE_M = 0.015  # a foot this close to the lowest one is on the ground (without flags)
TILT_GAIN = 1.0  # 1/s: how fast the accelerometer pulls roll and pitch (no IMU orientation)
# 1/s: how fast the IMU's own orientation pulls the gyro's integral: its noise averaged over
# ~1/G (H1, σ 0.57° per sample: a 0.76° pitch error at the start left 0.5 s windows 0.30° off
# in tilt; 0.14° with the orientation smoothed), a gyro bias b lagging it by b/G
ORIENTATION_GAIN = 10.0


def unanchored(model: mujoco.MjModel, measurements: Mapping[str, Measurement]) -> bool:
    """A free base and no mocap in the log: its x, y and yaw are seen by nothing absolute."""
    mocap = any(m.kind in MOCAP_KINDS and len(m) for m in measurements.values())
    return free_base(model)[0] >= 0 and not mocap


def base_from_legs(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    measurements: Mapping[str, Measurement],
    t_ns: np.ndarray,
) -> bool:
    """Write the free base's pose into qpos (T, nq) from the IMU and the stance feet, in
    place (the joints already in it). False, qpos untouched: the model has no free base with
    an IMU site on it or on a body its joints carry, or no foot touches the world at the start
    pose."""
    base, adr = free_base(model)
    imu = next((m for m in measurements.values() if m.kind == "imu" and len(m)), None)
    if base < 0 or imu is None or imu.element_type != "site":
        return False
    site = model.site(imu.elements[0])
    body = int(site.bodyid[0])  # the IMU's: the base or a body the encoders put on it
    if int(model.body_rootid[body]) != base:
        return False
    start = qpos[0].copy()
    d = mujoco.MjData(model)
    feet, heights = feet_at(model, d, start)
    if not feet:
        return False
    _, Q_rel = body_in_base(model, d, qpos, body)
    R_body = orientations(imu, site, quat_mul(start[adr + 3 : adr + 7], Q_rel[0]), t_ns)
    R = base_orientations(R_body, Q_rel)
    T = len(t_ns)
    rel = np.empty((T, len(feet), 3))  # c_ik: the feet's points, base origin at 0
    turn = np.empty((T, len(feet), 3, 3))  # the feet's orientations, world
    for k in range(T):
        d.qpos[:] = qpos[k]
        d.qpos[adr : adr + 3] = 0.0
        d.qpos[adr + 3 : adr + 7] = R[k]
        mujoco.mj_kinematics(model, d)
        rel[k], radii = foot_points(model, d, feet)
        turn[k] = d.geom_xmat[feet].reshape(-1, 3, 3)
    sole = rel[:, :, 2] - radii  # the feet's lowest points' heights, base origin at 0
    on_ground, _ = stance(model, feet, sole, measurements, t_ns)
    p = np.empty((T, 3))
    p[0] = start[adr : adr + 3]
    for k in range(T - 1):
        both = on_ground[k] & on_ground[k + 1]
        if both.any():
            # a foot that rolls without slipping: its point moves by Δθ × r e_z in the world
            rolled = np.array(
                [_rotation_vector(turn[k + 1, i] @ turn[k, i].T) for i in range(len(feet))]
            )
            roll = np.cross(rolled, radii[:, None] * np.array([0.0, 0.0, 1.0]))
            step = np.mean(roll[both] - (rel[k + 1, both] - rel[k, both]), axis=0)
        else:  # in flight: keep the last step
            step = p[k] - p[k - 1] if k else np.zeros(3)
        p[k + 1] = p[k] + step
    for k in range(T):
        if on_ground[k].any():
            p[k, 2] = np.mean(heights[on_ground[k]] - sole[k, on_ground[k]])
    qpos[:, adr : adr + 3] = p
    qpos[:, adr + 3 : adr + 7] = R
    return True


def body_in_base(
    model: mujoco.MjModel, d: mujoco.MjData, qpos: np.ndarray, body: int
) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3), (T, 4): `body`'s origin and orientation in the free base's frame at each knot,
    through the joints of qpos (T, nq) between them (the base's own: 0, identity)."""
    base, adr = free_base(model)
    T = len(qpos)
    p, Q = np.zeros((T, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    if body == base:
        return p, Q
    for k in range(T):
        d.qpos[:] = qpos[k]
        d.qpos[adr : adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
        mujoco.mj_kinematics(model, d)
        p[k], Q[k] = d.xpos[body], d.xquat[body]
    return p, Q


def base_orientations(body_quat: np.ndarray, rel_quat: np.ndarray) -> np.ndarray:
    """(T, 4) the base's orientation R_body ⊗ Q_rel⁻¹ from a body's, R_body (T, 4), and its
    orientation on the base, Q_rel (T, 4: `body_in_base`)."""
    return quat_mul(body_quat, quat_conj(rel_quat))


def unobserved_line(model: mujoco.MjModel, qpos: np.ndarray, std: np.ndarray, source: str) -> str:
    """What a log without mocap cannot see, for the summary: x, y and yaw relative to the start
    pose (from `source`), their σ at the first and the last knot (std: (T, nv) marginal σ)."""
    base, adr = free_base(model)
    dof = int(model.jnt_dofadr[model.body_jntadr[base]])
    yaw = np.degrees(heading(qpos[0, adr + 3 : adr + 7]))
    xy = np.hypot(std[:, dof], std[:, dof + 1])
    spin = np.degrees(std[:, dof + 5])  # about the base's z axis: ≈ the heading's
    return (
        f"no mocap: x, y and yaw are relative to the start pose (x {qpos[0, adr]:.3f} m, "
        f"y {qpos[0, adr + 1]:.3f} m, yaw {yaw:.1f}°: {source}) and unobservable: their σ "
        f"grows from {xy[0] * 1e3:.2g} mm, {spin[0]:.2g}° to {xy[-1] * 1e3:.2g} mm, "
        f"{spin[-1]:.2g}° (qpos_std); z, roll, pitch, the velocities, joints and contact "
        "forces are observed"
    )


def start_source(config: Config) -> str:
    """Where the start pose comes from, in words."""
    if config.start_pose is not None:
        return "the config's start_pose or --start-pose"
    model = config.load_model()
    has_home = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "home") >= 0
    return "the model's home keyframe" if has_home else "the model's qpos0"


def _rotation_vector(mat: np.ndarray) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, mat.reshape(9))
    out = np.zeros(3)
    mujoco.mju_quat2Vel(out, quat, 1.0)
    return out


def free_base(model: mujoco.MjModel) -> tuple[int, int]:
    """(body, qpos address) of the first free joint's body, or (-1, -1)."""
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            return int(model.jnt_bodyid[j]), int(model.jnt_qposadr[j])
    return -1, -1


def feet_at(
    model: mujoco.MjModel, d: mujoco.MjData, qpos: np.ndarray
) -> tuple[list[int], np.ndarray]:
    """Per moving body within FOOT_GAP_M of a world geom at qpos, its geom lowest there (a
    shin's capsule ends inside its foot's sphere), and their soles' heights."""
    d.qpos[:] = qpos
    mujoco.mj_kinematics(model, d)
    world = [g for g in range(model.ngeom) if model.geom_bodyid[g] == 0]
    fromto = np.zeros(6)
    feet = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == 0 or not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        gap = min(
            (mujoco.mj_geomDistance(model, d, w, g, FOOT_GAP_M, fromto) for w in world),
            default=np.inf,
        )
        if gap < FOOT_GAP_M:
            feet.append(g)
    points, radii = foot_points(model, d, feet)
    lowest: dict[int, int] = {}
    for i, g in enumerate(feet):  # the lowest sole; of two within a mm, the rounder
        b, j = int(model.geom_bodyid[g]), lowest.get(int(model.geom_bodyid[g]))
        key_i = (round((points[i, 2] - radii[i]) * 1e3), -radii[i])
        if j is None or key_i < (round((points[j, 2] - radii[j]) * 1e3), -radii[j]):
            lowest[b] = i
    keep = sorted(lowest.values())
    return [feet[i] for i in keep], points[keep, 2] - radii[keep]


def foot_points(
    model: mujoco.MjModel, d: mujoco.MjData, feet: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """(feet, 3) each foot's centre of curvature at its sole — a sphere's centre, a capsule's
    lower end — or a flat foot's centre, and (feet,) its rolling radius (0 if flat)."""
    points = d.geom_xpos[feet].copy()
    radii = np.zeros(len(feet))
    for i, g in enumerate(feet):
        kind, size = int(model.geom_type[g]), model.geom_size[g]
        if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            axis = d.geom_xmat[g].reshape(3, 3)[:, 2] * size[1]
            points[i] += -axis if axis[2] > 0 else axis
        if kind in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE):
            radii[i] = size[0]
    return points, radii


def orientations(
    imu: Measurement, site: object, start_quat: np.ndarray, t_ns: np.ndarray
) -> np.ndarray:
    """(T, 4) the orientation of the IMU site's body per knot, w x y z (module docstring);
    start_quat: that body's at the first knot."""
    site_quat = np.asarray(site.quat)  # type: ignore[attr-defined]  # body_from_site
    values = _filled(interpolated_at_knots(imu, t_ns)[:, 0])  # (T, 10): q, gyro, accel
    quat_ws = values[:, :4]
    T = len(t_ns)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, site_quat)
    R_bs = mat.reshape(3, 3)
    gyro = np.nan_to_num(values[:, 4:7]) @ R_bs.T  # body frame
    dt = np.diff(t_ns) / 1e9
    if np.isfinite(quat_ws).all():
        measured = quat_mul(
            quat_ws / np.linalg.norm(quat_ws, axis=1, keepdims=True), quat_conj(site_quat)
        )
        backward = _complementary(measured, gyro, dt, range(T - 1, -1, -1), measured[-1])
        return _with_start_yaw(
            _complementary(measured, gyro, dt, range(T), backward[0]), start_quat
        )
    accel = np.nan_to_num(values[:, 7:10]) @ R_bs.T
    out = np.empty((T, 4))
    out[0] = start_quat
    for k in range(T - 1):
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, out[k])
        up = R.reshape(3, 3) @ accel[k]  # the specific force, world axes: ≈ +g·z standing
        norm = np.linalg.norm(up)
        # the world rotation that turns `up` toward z, as a body-frame rate
        tilt = np.cross(up / norm, [0.0, 0.0, 1.0]) if norm > 1e-6 else np.zeros(3)
        omega = gyro[k] + TILT_GAIN * (R.reshape(3, 3).T @ tilt)
        out[k + 1] = out[k]
        mujoco.mju_quatIntegrate(out[k + 1], omega, dt[k])
    return out


def _complementary(
    measured: np.ndarray, gyro: np.ndarray, dt: np.ndarray, order: range, first: np.ndarray
) -> np.ndarray:
    """(T, 4) the gyro (T, 3, body frame, held over each dt) integrated over the knots in
    `order` (forward or backward) from `first`, pulled toward the measured orientations:
    q_next = q ⊗ Exp((±ω + G Log(q⁻¹ ⊗ q_meas)) Δt)."""
    out = np.empty_like(measured)
    out[order[0]] = first
    error = np.zeros(3)
    sign = 1.0 if order.step > 0 else -1.0
    for a, b in pairwise(order):
        i = min(a, b)  # the interval between the two knots
        mujoco.mju_subQuat(error, measured[a], out[a])
        out[b] = out[a]
        mujoco.mju_quatIntegrate(out[b], sign * gyro[i] + ORIENTATION_GAIN * error, dt[i])
    return out


def _filled(values: np.ndarray) -> np.ndarray:
    """Each column's NaN knots (before the first sample, across a gap) from its nearest
    samples; a column without any stays NaN."""
    out = values.copy()
    k = np.arange(len(values))
    for c in range(values.shape[1]):
        ok = np.isfinite(values[:, c])
        if ok.any() and not ok.all():
            out[:, c] = np.interp(k, k[ok], values[ok, c])
    return out


def _with_start_yaw(quat: np.ndarray, start_quat: np.ndarray) -> np.ndarray:
    """quat (T, 4) turned about world z so that the first has start_quat's yaw."""
    delta = heading(start_quat) - heading(quat[0])
    return quat_mul(np.array([np.cos(delta / 2), 0.0, 0.0, np.sin(delta / 2)]), quat)


def stance(
    model: mujoco.MjModel,
    feet: list[int],
    sole: np.ndarray,
    measurements: Mapping[str, Measurement],
    t_ns: np.ndarray,
) -> tuple[np.ndarray, str]:
    """(T, feet) bool, which feet are on the ground — the contact flags of the feet's bodies
    where logged, else the feet whose soles (heights `sole` (T, feet), any common origin) are
    within STANCE_M of the lowest — and which of the two it is."""
    on_ground = sole <= sole.min(axis=1, keepdims=True) + STANCE_M
    flags = next((m for m in measurements.values() if m.kind == "contact_flags" and len(m)), None)
    if flags is None:
        return on_ground, f"the feet within {STANCE_M * 1e3:g} mm of the lowest"
    values = interpolated_at_knots(flags, t_ns)[:, :, 0]
    for e, name in enumerate(flags.elements):
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        for i, g in enumerate(feet):
            if model.geom_bodyid[g] == body:
                ok = np.isfinite(values[:, e])
                on_ground[ok, i] = values[ok, e] > 0.5
    return on_ground, f"the log's contact flags ({flags.stream})"
