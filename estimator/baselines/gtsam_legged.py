"""GTSAM's legged estimators as baselines: `--method gtsam-legged-ekf` (`gtsam.LeggedInvariantEKF`)
and `--method gtsam-legged-smoother` (`gtsam.LeggedFixedLagSmoother`, lag 1 s), the gtsam
wheel's own classes, configured as its example (`gtsam/examples/LeggedEstimatorExample.py`)
configures them, and fed from the log:

- the IMU: each sample's gyro and specific force in the IMU site's frame (the reader's), held
  until the next (`predict`), `body_P_imu` the site's pose on the base; the noise densities
  from the config's per-sample σ at the stream's rate (σ² / rate);
- contacts: at each joint-encoder sample, every stance foot's sole in the base frame, through
  the encoders and the model's kinematics (`processContacts`); stance from the log's contact
  flags, else the feet within `leg_odometry.STANCE_M` of the lowest (the summary says which);
- the start: the model's home pose (as physfuse's), turned to the IMU's first orientation
  (`leg_odometry`), at rest; the footholds where the home pose puts the soles; the height
  prior on, the floor at the soles' home height.

The base's state is read at each knot: its pose, its velocity (the estimator's own velocity
state) and its angular velocity (the gyro less the estimated bias, turned to the base); the
joints are the encoders' (`initial_trajectory`): the same output layout as every method.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import mujoco
import numpy as np

from estimator.config import Config
from estimator.errors import ConfigError, PhysfuseError
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.knots import knot_grid
from estimator.leg_odometry import (
    base_orientations,
    body_in_base,
    feet_at,
    foot_points,
    free_base,
    orientations,
    stance,
)
from estimator.problem import build_problem, model_with_sensors, velocities
from estimator.rotations import quat_mul
from estimator.run import Summary, finish, initial_trajectory
from estimator.settings import Settings

METHODS = {
    "gtsam-legged-ekf": "LeggedInvariantEKF",
    "gtsam-legged-smoother": "LeggedFixedLagSmoother",
}
LAG_S = 1.0  # the example's DEFAULT_SMOOTHER_LAG_SECONDS
CONTACT_HZ = 50.0  # contact updates (every knot: the smoother's system turns indeterminate)
MIN_CONTACT_HZ = 10.0  # halved from CONTACT_HZ down to this while it does


def legged_estimate(
    config: Config, measurements: Mapping[str, Measurement], settings: Settings
) -> tuple[Estimate, Summary]:
    import gtsam

    start = time.perf_counter()
    compiled = model_with_sensors(config)
    model = compiled[0]
    h = settings.h or float(model.opt.timestep)
    problem = build_problem(config, measurements, settings, knot_grid(measurements, h), compiled)
    qpos = initial_trajectory(model, measurements, problem.t_ns)
    base, adr = free_base(model)
    imu = next((m for m in measurements.values() if m.kind == "imu" and len(m)), None)
    joints = next((m for m in measurements.values() if m.kind == "joint_state" and len(m)), None)
    if base < 0 or imu is None or joints is None or imu.element_type != "site":
        raise ConfigError(
            f"{config.path}: --method {settings.method} needs a legged robot's log: a free "
            "base with an IMU on it and joint encoders (joint_state)"
        )
    site = model.site(imu.elements[0])
    body = int(site.bodyid[0])  # the estimators' body: the IMU's (the base, or one on it)
    stream = config.streams[imu.stream]
    d = mujoco.MjData(model)
    home = qpos[0].copy()
    feet, soles_home = feet_at(model, d, home)
    if int(model.body_rootid[body]) != base or not feet:
        raise ConfigError(
            f"{config.path}: --method {settings.method} needs the IMU on the base "
            f"({model.body(base).name}) or on a body its joints carry, and feet touching the "
            "floor at the home pose"
        )
    rate = (len(imu) - 1) / ((imu.t_ns[-1] - imu.t_ns[0]) / 1e9)
    params = _params(gtsam, stream.noise, rate, site)
    # gtsam's full-contact initializer needs ≥ 3 feet: with it on, a biped's estimator never
    # starts (predict leaves the state as it was); the start pose is given below anyway
    params.useFullContactInitialization = len(feet) >= 3
    # the start: home, turned to the IMU's orientation, at rest
    p_rel, Q_rel = body_in_base(model, d, qpos, body)
    R0 = orientations(imu, site, quat_mul(home[adr + 3 : adr + 7], Q_rel[0]), imu.t_ns[:1])
    home[adr + 3 : adr + 7] = base_orientations(R0, Q_rel[:1])[0]
    d.qpos[:] = home
    mujoco.mj_kinematics(model, d)
    points, radii = foot_points(model, d, feet)
    footholds = (points - radii[:, None] * np.array([0.0, 0.0, 1.0])).T
    nav = gtsam.NavState(gtsam.Rot3.Quaternion(*R0[0]), d.xpos[body].copy(), np.zeros(3))
    names = [model.body(model.geom_bodyid[g]).name for g in feet]
    floor = float(np.mean(soles_home))
    body_points, stance, source = _contacts(model, d, qpos, problem.t_ns, feet, body, measurements)
    warnings = [f"{settings.method}: stance from {source}"]

    def replay(contact_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The IMU and the contacts (at contact_hz) in time order through a new estimator,
        after each knot: (T, 7) the body's pose, (T, 6) its velocity and rate, (T, 6) the IMU
        bias (accelerometer, gyro)."""
        if settings.method == "gtsam-legged-ekf":
            P0 = np.diag(
                [1e-2, 1e-2, 1e-6, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05] + [0.25] * 3 * len(feet)
            )
            estimator: Any = gtsam.LeggedInvariantEKF(nav, footholds, P0, params, names)
        else:
            P0 = np.diag([1e-2, 1e-2, 1e-6, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05])
            estimator = gtsam.LeggedFixedLagSmoother(nav, footholds, P0, params, LAG_S, names)
        estimator.turnHeightPriorOn(floor)
        t_imu = imu.t_ns
        events = sorted(
            [(int(t), 0, i) for i, t in enumerate(t_imu)]
            + [(int(t), 1, k) for k, t in enumerate(problem.t_ns)]
        )
        held = np.nan_to_num(imu.values[0, 0, 4:10])
        now = events[0][0]
        poses, twists, biases = [], [], []  # twists: the body's world velocity, its own rate
        R_site = np.empty(9)
        mujoco.mju_quat2Mat(R_site, site.quat)
        stride = max(1, round(1.0 / contact_hz / h))
        was: np.ndarray | None = None  # (the feet on the ground at the start: footholds0)
        for t, kind, i in events:
            if t > now:
                estimator.predict(held[:3], held[3:], (t - now) / 1e9)
                now = t
            if kind == 0:
                held = np.where(np.isfinite(imu.values[i, 0, 4:10]), imu.values[i, 0, 4:10], held)
                continue
            contacts = []
            for f in np.flatnonzero(stance[i]):
                c = gtsam.ContactMeasurement()
                c.foot, c.bodyPoint = int(f), body_points[i, f]
                c.touchdown = was is not None and not was[f]
                contacts.append(c)
            # (a state from the IMU first: the smoother's x1)
            if contacts and now > t_imu[0] and i % stride == 0:
                estimator.processContacts(contacts)
                was = stance[i]
            state = estimator.estimate()
            quat = state.rotation().toQuaternion()
            poses.append(np.r_[state.x(0), quat.w(), quat.x(), quat.y(), quat.z()])
            b = estimator.estimateBias()
            twists.append(np.r_[state.x(1), R_site.reshape(3, 3) @ (held[:3] - b.gyroscope())])
            biases.append(np.r_[b.accelerometer(), b.gyroscope()])
        return np.array(poses), np.array(twists), np.array(biases)

    contact_hz = CONTACT_HZ
    while True:
        try:
            pose, twist, imu_bias = replay(contact_hz)
            break
        except RuntimeError as err:  # gtsam's IndeterminantLinearSystemException
            if "Indeterminate" not in str(err) or contact_hz < MIN_CONTACT_HZ:
                raise PhysfuseError(
                    f"{config.path}: --method {settings.method}: gtsam stopped: "
                    + str(err).strip().splitlines()[0]
                ) from None
            contact_hz /= 2
    if contact_hz != CONTACT_HZ:
        warnings.append(
            f"{settings.method}: contacts at {contact_hz:g} Hz (at {2 * contact_hz:g} Hz gtsam's "
            "system turned indeterminate)"
        )
    # the base from the body's state through the encoders: R_b = R ⊗ Q_rel⁻¹, p_b = p − R_b p_rel
    R_base = base_orientations(pose[:, 3:7] / np.linalg.norm(pose[:, 3:7], axis=1)[:, None], Q_rel)
    qpos[:, adr + 3 : adr + 7] = R_base
    for k in range(problem.T):
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, R_base[k])
        qpos[k, adr : adr + 3] = pose[k, :3] - R.reshape(3, 3) @ p_rel[k]
    qvel = _base_velocity(model, d, qpos, body, twist, problem.h)
    bias = np.zeros((problem.T, problem.nb))
    bias[:, problem.bias_of[imu.stream]] = imu_bias
    std = np.full((problem.T, model.nv), np.nan)
    return finish(config, problem, qpos, bias, std, start, [], [], warnings, {}, qvel=qvel)


def _base_velocity(
    model: mujoco.MjModel,
    d: mujoco.MjData,
    qpos: np.ndarray,
    body: int,
    twists: np.ndarray,
    h: float,
) -> np.ndarray:
    """(T, nv) the base's velocity (MuJoCo's free joint: linear in the world, angular in the
    base frame) from the estimator's own state of `body` (twists (T, 6): its origin's world
    velocity, its angular velocity in its frame), the joints' from the encoders' finite
    differences: the base's 6 dofs solve J_body v = (ω, v) of the body (mj_jacBody)."""
    qvel = velocities(model, qpos, h)
    dof = int(model.jnt_dofadr[model.body_jntadr[free_base(model)[0]]])
    base_dofs = np.arange(dof, dof + 6)
    others = np.setdiff1d(np.arange(model.nv), base_dofs)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for k in range(len(qpos)):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, d)
        mujoco.mj_comPos(model, d)
        mujoco.mj_jacBody(model, d, jacp, jacr, body)
        J = np.vstack([jacr, jacp])
        seen = np.r_[d.xmat[body].reshape(3, 3) @ twists[k, 3:], twists[k, :3]]
        qvel[k, base_dofs] = np.linalg.solve(J[:, base_dofs], seen - J[:, others] @ qvel[k, others])
    return qvel


def _contacts(
    model: mujoco.MjModel,
    d: mujoco.MjData,
    qpos: np.ndarray,
    t_ns: np.ndarray,
    feet: list[int],
    body: int,
    measurements: Mapping[str, Measurement],
) -> tuple[np.ndarray, np.ndarray, str]:
    """Per knot the feet's soles in `body`'s frame (T, feet, 3) from the encoders, which are
    on the ground (T, feet), and from what."""
    T = len(t_ns)
    body_points = np.empty((T, len(feet), 3))
    heights = np.empty((T, len(feet)))
    for k in range(T):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, d)
        points, radii = foot_points(model, d, feet)
        soles = points - radii[:, None] * np.array([0.0, 0.0, 1.0])
        R = d.xmat[body].reshape(3, 3)
        body_points[k] = (soles - d.xpos[body]) @ R  # Rᵀ (sole − x), row-wise
        heights[k] = soles[:, 2] - d.xpos[body, 2]
    on_ground, source = stance(model, feet, heights, measurements, t_ns)
    return body_points, on_ground, source


def _params(gtsam: Any, noise: Mapping[str, float], rate: float, site: Any) -> Any:
    """The example's parameters, with the config's IMU noise and the site's pose."""
    params = gtsam.LeggedEstimatorParams()
    params.preintegrationParams = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.preintegrationParams.setGyroscopeCovariance(np.eye(3) * noise["gyro_std"] ** 2 / rate)
    params.preintegrationParams.setIntegrationCovariance(np.eye(3) * 1e-3**2)
    params.preintegrationParams.setAccelerometerCovariance(
        np.eye(3) * noise["accel_std"] ** 2 / rate
    )
    params.body_P_imu = gtsam.Pose3(gtsam.Rot3.Quaternion(*site.quat), np.asarray(site.pos))
    params.footholdProcessSigma = 1e-4
    params.footholdInitSigma = 5e-1
    params.contactCovariance = np.diag([0.03**2, 0.03**2, 0.02**2])
    params.heightPriorSigma = 0.02
    params.useRobustContactNoise = False
    params.robustContactHuberK = 2.0
    params.imuBias = gtsam.imuBias.ConstantBias()
    params.biasAccRandomWalkSigma = 5e-3
    params.biasOmegaRandomWalkSigma = 1e-4
    params.useFullContactInitialization = True
    params.marginalizeLeavingFoot = True
    return params
