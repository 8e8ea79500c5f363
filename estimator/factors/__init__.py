"""The factors of the estimation problem, one unit per sensor kind.

A sensor kind's unit (`pose`, `markers`, `imu`, `joint_state`, `wrench`, `contact_flags`)
adds the MuJoCo sensors that predict its measurements, maps a stream's samples onto the
knots as whitened residual rows (`SensorBlock`), and names its channels for held-out
validation; `base` says what each returns. Adding a kind: a unit here, its entry in `UNITS`,
its config keys (`estimator.config`) and its message type (`estimator.io.logs`).

The physics factor, the motion priors and the bias random walks are the smoother's own
(`estimator.solver.linearize.Linearizer`).
"""

from __future__ import annotations

from types import ModuleType

from estimator.factors import contact_flags, imu, joint_state, markers, pose, wrench
from estimator.factors.base import Grid, Holdout, SensorBlock, StreamFactors

# stream kind → its unit; commands have none: they enter the physics factor as known forces
UNITS: dict[str, ModuleType] = {
    "pose": pose,
    "tf": pose,
    "rigid_bodies": pose,
    "markers": markers,
    "imu": imu,
    "joint_state": joint_state,
    "wrench": wrench,
    "contact_flags": contact_flags,
}

__all__ = ["UNITS", "Grid", "Holdout", "SensorBlock", "StreamFactors"]
