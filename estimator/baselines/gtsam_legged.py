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

The base's pose between IMU samples is interpolated onto the knots; the joints are the
encoders' (`initial_trajectory`): the same output layout as every method.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import mujoco
import numpy as np

from estimator.config import Config
from estimator.errors import ConfigError
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.knots import knot_grid
from estimator.leg_odometry import feet_at, foot_points, free_base, orientations, stance
from estimator.problem import build_problem, model_with_sensors
from estimator.run import Summary, finish, initial_trajectory
from estimator.settings import Settings

METHODS = {
    "gtsam-legged-ekf": "LeggedInvariantEKF",
    "gtsam-legged-smoother": "LeggedFixedLagSmoother",
}
LAG_S = 1.0  # the example's DEFAULT_SMOOTHER_LAG_SECONDS
CONTACT_HZ = 50.0  # contact updates (every knot: the smoother's system turns indeterminate)


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
    stream = config.streams[imu.stream]
    d = mujoco.MjData(model)
    home = qpos[0].copy()
    feet, soles_home = feet_at(model, d, home)
    if int(site.bodyid[0]) != base or not feet:
        raise ConfigError(
            f"{config.path}: --method {settings.method} needs the IMU on the base "
            f"({model.body(base).name}) and feet touching the floor at the home pose"
        )
    rate = (len(imu) - 1) / ((imu.t_ns[-1] - imu.t_ns[0]) / 1e9)
    params = _params(gtsam, stream.noise, rate, site)
    # the start: home, turned to the IMU's orientation, at rest
    R0 = orientations(imu, site, home[adr + 3 : adr + 7], imu.t_ns[:1])[0]
    home[adr + 3 : adr + 7] = R0
    d.qpos[:] = home
    mujoco.mj_kinematics(model, d)
    points, radii = foot_points(model, d, feet)
    footholds = (points - radii[:, None] * np.array([0.0, 0.0, 1.0])).T
    nav = gtsam.NavState(gtsam.Rot3.Quaternion(*R0), home[adr : adr + 3], np.zeros(3))
    names = [model.body(model.geom_bodyid[g]).name for g in feet]
    if settings.method == "gtsam-legged-ekf":
        P0 = np.diag(
            [1e-2, 1e-2, 1e-6, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05] + [0.25] * 3 * len(feet)
        )
        estimator: Any = gtsam.LeggedInvariantEKF(nav, footholds, P0, params, names)
    else:
        P0 = np.diag([1e-2, 1e-2, 1e-6, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05])
        estimator = gtsam.LeggedFixedLagSmoother(nav, footholds, P0, params, LAG_S, names)
    floor = float(np.mean(soles_home))
    estimator.turnHeightPriorOn(floor)
    body_points, stance, source = _contacts(model, d, qpos, problem.t_ns, feet, measurements)
    # the IMU and the contact events in time order; the state after each
    t_imu = imu.t_ns
    events = sorted(
        [(int(t), 0, i) for i, t in enumerate(t_imu)]
        + [(int(t), 1, k) for k, t in enumerate(problem.t_ns)]
    )
    held = np.nan_to_num(imu.values[0, 0, 4:10])
    now = events[0][0]
    times, poses = [], []
    stride = max(1, round(1.0 / CONTACT_HZ / h))
    was: np.ndarray | None = None  # (the feet on the ground at the start: their footholds0)
    for t, kind, i in events:
        if t > now:
            estimator.predict(held[:3], held[3:], (t - now) / 1e9)
            now = t
        if kind == 0:
            held = np.where(np.isfinite(imu.values[i, 0, 4:10]), imu.values[i, 0, 4:10], held)
        else:
            contacts = []
            for f in np.flatnonzero(stance[i]):
                c = gtsam.ContactMeasurement()
                c.foot, c.bodyPoint = int(f), body_points[i, f]
                c.touchdown = was is not None and not was[f]
                contacts.append(c)
            # (a state from the IMU first: the smoother's x1; contacts at CONTACT_HZ)
            if contacts and now > t_imu[0] and i % stride == 0:
                estimator.processContacts(contacts)
                was = stance[i]
            state = estimator.estimate()
            times.append(t)
            quat = state.rotation().toQuaternion()
            poses.append(np.r_[state.x(0), quat.w(), quat.x(), quat.y(), quat.z()])
    pose = np.array(poses)
    qpos[:, adr : adr + 3] = pose[:, :3]
    qpos[:, adr + 3 : adr + 7] = pose[:, 3:7] / np.linalg.norm(pose[:, 3:7], axis=1, keepdims=True)
    bias = np.zeros((problem.T, problem.nb))
    std = np.full((problem.T, model.nv), np.nan)
    warnings = [f"{settings.method}: stance from {source}"]
    return finish(config, problem, qpos, bias, std, start, [], [], warnings, {})


def _contacts(
    model: mujoco.MjModel,
    d: mujoco.MjData,
    qpos: np.ndarray,
    t_ns: np.ndarray,
    feet: list[int],
    measurements: Mapping[str, Measurement],
) -> tuple[np.ndarray, np.ndarray, str]:
    """Per knot the feet's soles in the base frame (T, feet, 3) from the encoders, which are
    on the ground (T, feet), and from what."""
    base, _ = free_base(model)
    T = len(t_ns)
    body_points = np.empty((T, len(feet), 3))
    heights = np.empty((T, len(feet)))
    for k in range(T):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, d)
        points, radii = foot_points(model, d, feet)
        soles = points - radii[:, None] * np.array([0.0, 0.0, 1.0])
        R = d.xmat[base].reshape(3, 3)
        body_points[k] = (soles - d.xpos[base]) @ R  # R_bᵀ (sole − x_b), row-wise
        heights[k] = soles[:, 2] - d.xpos[base, 2]
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
