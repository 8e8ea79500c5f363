"""An IMU: accelerometer and gyro with a bias each, b_k a random walk.

    accel   (s_acc(q, v, a) + b_acc − m̄_acc) √n / σ_acc     over [t_k, t_k + h), where a_k acts
    gyro    (s_gyro(q, v) + b_gyro − m̄_gyro) √n / σ_gyro    over (t_k − h, t_k], v_k's step
    walk    (b_{k+1} − b_k) / (σ_walk √h);  prior b_0 / σ_b0

m̄ is the mean of the n samples of the step; saturated samples (at the configured range) are
left out, as a reading on the rail only bounds the truth.
"""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np

from estimator.config import StreamConfig
from estimator.factors.base import (
    Grid,
    Holdout,
    StreamFactors,
    add_element_sensors,
    biased_pair,
)
from estimator.io.logs.measurements import Measurement
from estimator.knots import averaged_at_knots

_SENS = mujoco.mjtSensor


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    return add_element_sensors(
        spec, stream, ((_SENS.mjSENS_ACCELEROMETER, "accel"), (_SENS.mjSENS_GYRO, "gyro"))
    )


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    noise, settings = stream.noise, grid.settings
    m = without_saturated(m, stream)
    accel, accel_counts = averaged_at_knots(m, grid.t_ns, "acc", h_ns=grid.h_ns)
    gyro, gyro_counts = averaged_at_knots(m, grid.t_ns, "vel", h_ns=grid.h_ns)
    blocks = biased_pair(
        stream.name,
        rows,
        (accel[:, 0, 7:10], gyro[:, 0, 4:7]),
        (accel_counts[:, 0, 7:10], gyro_counts[:, 0, 4:7]),
        (noise["accel_std"], noise["gyro_std"]),
        ("acc", "vel"),
        grid.nb,
        ("accel", "gyro"),
    )
    walk = np.r_[np.full(3, noise["accel_bias_walk"]), np.full(3, noise["gyro_bias_walk"])]
    prior = np.r_[np.full(3, settings.bias_prior_accel), np.full(3, settings.bias_prior_gyro)]
    return StreamFactors(blocks, walk, prior)


def without_saturated(m: Measurement, stream: StreamConfig) -> Measurement:
    """The IMU samples with their accelerometer (gyro) left out (NaN) where a sensor axis is
    at or beyond `accel_range` (`gyro_range`): a saturated reading only bounds the truth.

    The reader has turned the vectors into the site frame; the range is per sensor axis,
    v_sensor = R_site_sensorᵀ v_site.
    """
    if not len(m) or (math.isinf(stream.accel_range) and math.isinf(stream.gyro_range)):
        return m
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.array(stream.quat_site_sensor))
    R_site_sensor = mat.reshape(3, 3)
    values = m.values.copy()
    for part, limit in ((slice(7, 10), stream.accel_range), (slice(4, 7), stream.gyro_range)):
        v_sensor = values[:, 0, part] @ R_site_sensor  # rows: (R_site_sensorᵀ v_site)ᵀ
        # the rail within rounding of the frame change
        saturated = np.any(np.abs(v_sensor) >= limit * (1.0 - 1e-9), axis=1)
        values[saturated, 0, part] = np.nan
    return replace(m, values=values)


def holdout(stream: StreamConfig) -> Holdout:
    names = tuple([f"accel_{c}" for c in "xyz"] + [f"gyro_{c}" for c in "xyz"])
    sigma = np.array([stream.noise["accel_std"]] * 3 + [stream.noise["gyro_std"]] * 3)
    return Holdout(names, sigma, ("m/s²", "rad/s"), _residuals)


def _residuals(predicted: np.ndarray, m: Measurement) -> np.ndarray:
    # components: q (4), gyro (3), accel (3); sensors: accel, gyro
    return np.concatenate(
        [predicted[:, :3] - m.values[:, 0, 7:10], predicted[:, 3:6] - m.values[:, 0, 4:7]], axis=1
    )
