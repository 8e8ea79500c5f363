"""The generalized-momentum observer (De Luca and Mattone, ICRA 2005; Haddadin et al., IEEE
T-RO 2017, §IV): the collision detector users know, as a baseline for `estimator.diagnose`.

With p = M(q) q̇ and the robot's dynamics M q̈ + c(q, q̇) = τ + τ_passive + τ_ext (c: Coriolis,
centrifugal and gravity, MuJoCo's qfrc_bias), ṗ = τ + τ_passive + Ṁq̇ − c + τ_ext, and the
residual

    r(t) = K_O ( p(t) − p(0) − ∫₀ᵗ (τ + τ_passive + Ṁq̇ − c + r) ds )

follows τ_ext through a first-order low pass, ṙ = K_O (τ_ext − r), without the
acceleration. Discretely at the knots (v_k = (q_k ⊖ q_{k−1})/h, as the estimate's), the
momentum's change splits exactly as p_{k+1} − p_k = M_k (v_{k+1} − v_k) + (M_{k+1} − M_k) v_{k+1},
so that with Ṁ_k v ≡ (M_{k+1} − M_k) v_{k+1} / h

    r_k = K_O (p_k − p_0 − S_k),   S_{k+1} = S_k + h (τ_k + τ_passive,k + Ṁ_k v − c_k + r_k)

τ: the logged commands through the actuators (`Estimate.qfrc_known`), q and q̇ from the
kinematic smoother (encoders, IMU and mocap without the physics): the observer's own inputs
on a floating base. On a legged robot r also holds the ground's reaction, which no sensor
here measures: `detect` takes it out as a contact force of unknown size (the residual's
component in the span of the contact Jacobians), as the humanoid observers do without foot
force sensors.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import mujoco
import numpy as np

from estimator.batch import estimate
from estimator.config import Config
from estimator.diagnose.contact_point import contact_points
from estimator.diagnose.detect import Detection, DetectorSettings, detect
from estimator.diagnose.unmodeled import UnmodeledForces, unmodeled_forces
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.problem import build_problem, model_with_sensors
from estimator.settings import Settings
from physics.model import weight

GAIN = 50.0  # K_O [1/s]: r follows τ_ext with a 20 ms time constant
UNKNOWN_CONTACT = 10.0  # σ of the ground's reaction, × the robot's weight: of any size


def momentum_residual(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    qvel: np.ndarray,
    tau: np.ndarray,
    h: float,
    gain: float = GAIN,
) -> np.ndarray:
    """(T, nv) r_k (module docstring) along a trajectory qpos (T, nq), qvel (T, nv) with the
    applied generalized force tau (T, nv)."""
    T, nv = qvel.shape
    data = mujoco.MjData(model)
    p = np.zeros((T, nv))  # M_k v_k
    M_v_next = np.zeros((T, nv))  # M_k v_{k+1}
    drift = np.zeros((T, nv))  # τ_passive − c at (q_k, v_k)
    for k in range(T):
        data.qpos[:], data.qvel[:] = qpos[k], qvel[k]
        mujoco.mj_fwdPosition(model, data)
        mujoco.mj_fwdVelocity(model, data)
        mujoco.mj_mulM(model, data, p[k], qvel[k])
        if k + 1 < T:
            mujoco.mj_mulM(model, data, M_v_next[k], qvel[k + 1])
        drift[k] = data.qfrc_passive - data.qfrc_bias
    r = np.zeros((T, nv))
    S = np.zeros(nv)
    for k in range(T):
        r[k] = gain * (p[k] - p[0] - S)
        if k + 1 < T:
            M_dot_v = (p[k + 1] - M_v_next[k]) / h
            S += h * (tau[k] + drift[k] + M_dot_v + r[k])
    return r


def observer_diagnosis(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    detector: DetectorSettings | None = None,
) -> tuple[Estimate, UnmodeledForces, Detection]:
    """Unmodeled contacts from the momentum observer: the kinematic smoother's estimate of the
    log, its r (`momentum_residual`, the commands through the actuators as τ), then the same
    isolation and detection as `estimator.diagnose` (`unmodeled_forces` with r in place of
    the physics residual and the ground's reaction of unknown size, `detect`,
    `contact_points`)."""
    kinematic = replace(settings, method="kinematic")
    est, _ = estimate(config, measurements, kinematic)
    compiled = model_with_sensors(config)
    problem = build_problem(config, measurements, kinematic, est.t_ns, compiled)
    model = problem.model
    r = momentum_residual(model, est.qpos, est.qvel, est.qfrc_known, est.h)
    forces = unmodeled_forces(
        model, est, problem.known_sigma, UNKNOWN_CONTACT * weight(model), residual=r
    )
    detection = detect(forces, detector)
    located = contact_points(
        model, est, problem.known_sigma, UNKNOWN_CONTACT * weight(model), detection, residual=r
    )
    return est, forces, replace(detection, events=located)
