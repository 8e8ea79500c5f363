"""A force/torque sensor, predicted through the contact model: (s(q, v, a) + b − m̄) √n / σ
for force and torque, averaged over [t_k, t_k + h); b a random walk, as an F/T sensor
drifts off zero."""

from __future__ import annotations

import mujoco
import numpy as np

from estimator.config import StreamConfig
from estimator.factors.base import (
    Grid,
    Holdout,
    StreamFactors,
    add_element_sensors,
    biased_pair,
    vector_residuals,
)
from estimator.io.logs.measurements import Measurement
from estimator.knots import averaged_at_knots

_SENS = mujoco.mjtSensor


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    return add_element_sensors(
        spec, stream, ((_SENS.mjSENS_FORCE, "force"), (_SENS.mjSENS_TORQUE, "torque"))
    )


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    noise = stream.noise
    wrench, counts = averaged_at_knots(m, grid.t_ns, "acc", h_ns=grid.h_ns)
    blocks = biased_pair(
        stream.name,
        rows,
        (wrench[:, 0, :3], wrench[:, 0, 3:6]),
        (counts[:, 0, :3], counts[:, 0, 3:6]),
        (noise["force_std"], noise["torque_std"]),
        ("acc", "acc"),
        grid.nb,
        ("force", "torque"),
        kernel="force_sensor_kernel",
    )
    walk = np.r_[np.full(3, noise["force_bias_walk"]), np.full(3, noise["torque_bias_walk"])]
    prior = np.r_[np.full(3, noise["force_bias_std"]), np.full(3, noise["torque_bias_std"])]
    return StreamFactors(blocks, walk, prior)


def holdout(stream: StreamConfig) -> Holdout:
    names = tuple([f"force_{c}" for c in "xyz"] + [f"torque_{c}" for c in "xyz"])
    sigma = np.array([stream.noise["force_std"]] * 3 + [stream.noise["torque_std"]] * 3)
    return Holdout(names, sigma, ("N", "N·m"), vector_residuals(lambda m: m.values[:, 0, :6]))
