"""Marker positions (mocap4r2 Markers): (p(q) − m) / σ per marker, framepos in the world."""

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
    vector_residuals,
)
from estimator.io.logs.measurements import Measurement


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    return add_element_sensors(spec, stream, ((mujoco.mjtSensor.mjSENS_FRAMEPOS, "pos"),))


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    blocks = [
        SensorBlock(
            stream.name,
            "vector",
            np.concatenate(rows),
            values[:, :, :3].reshape(grid.T, -1),
            np.full(values.shape[1] * 3, stream.noise["position_std_m"]),
            group=3,
            alpha=alpha,
            slot=slot,
            labels=tuple(label for element in stream.elements for label in labels(element, "")),
        )
        for slot, (values, alpha) in enumerate(grid.position_slots(m))
    ]
    return StreamFactors(blocks)


def holdout(stream: StreamConfig) -> Holdout:
    names = tuple(f"{element}.{c}" for element in stream.elements for c in "xyz")
    sigma = np.full(len(names), stream.noise["position_std_m"])
    return Holdout(
        names, sigma, ("m",), vector_residuals(lambda m: m.values[:, :, :3].reshape(len(m), -1))
    )
