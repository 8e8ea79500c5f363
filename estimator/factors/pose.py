"""Poses of a body or site (pose, tf, rigid_bodies): position and orientation per element.

position   (p(q) − m_p) / σ_p                 framepos, world frame
rotation   Log(m_R⁻¹ ⊗ R(q)) / σ_R            framequat
"""

from __future__ import annotations

import mujoco
import numpy as np

from estimator.config import StreamConfig
from estimator.factors.base import (
    Grid,
    Holdout,
    SensorBlock,
    StreamFactors,
    add_element_sensors,
    labels,
)
from estimator.io.logs.measurements import Measurement
from estimator.rotations import quat_errors

_SENS = mujoco.mjtSensor


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    return add_element_sensors(
        spec, stream, ((_SENS.mjSENS_FRAMEPOS, "pos"), (_SENS.mjSENS_FRAMEQUAT, "quat"))
    )


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    noise = stream.noise
    blocks = []
    for slot, (values, alpha) in enumerate(grid.position_slots(m)):  # values (T, E, 7)
        for e, element in enumerate(stream.elements):
            pos_rows, quat_rows = rows[2 * e], rows[2 * e + 1]
            for kind, element_rows, part, std, quantity in (
                ("vector", pos_rows, slice(0, 3), noise["position_std_m"], "position"),
                ("quat", quat_rows, slice(3, 7), noise["orientation_std_rad"], "rotation"),
            ):
                blocks.append(
                    SensorBlock(
                        stream.name,
                        kind,
                        element_rows,
                        values[:, e, part],
                        np.full(3, std),
                        alpha=alpha,
                        slot=slot,
                        labels=labels(element, quantity),
                    )
                )
    return StreamFactors(blocks)


def holdout(stream: StreamConfig) -> Holdout:
    noise = stream.noise
    names = [
        f"{element}.{c}"
        for element in stream.elements
        for c in ("x", "y", "z", "rot_x", "rot_y", "rot_z")
    ]
    sigma = [noise["position_std_m"]] * 3 + [noise["orientation_std_rad"]] * 3
    return Holdout(tuple(names), np.array(sigma * len(stream.elements)), ("m", "rad"), _residuals)


def _residuals(predicted: np.ndarray, m: Measurement) -> np.ndarray:
    values = m.values
    parts = []
    for e in range(values.shape[1]):
        pred = predicted[:, 7 * e : 7 * e + 7]
        parts.append(pred[:, :3] - values[:, e, :3])
        ok = np.all(np.isfinite(pred[:, 3:]), axis=1) & np.all(
            np.isfinite(values[:, e, 3:7]), axis=1
        )
        rot = np.full((len(values), 3), np.nan)
        rot[ok] = quat_errors(pred[ok, 3:], values[ok, e, 3:7])[0]
        parts.append(rot)
    return np.concatenate(parts, axis=1)
