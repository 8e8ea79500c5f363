"""Joint encoders (sensor_msgs/JointState): positions, velocities and measured efforts.

    position   (q_j(t) − m_q) / σ_q        at the sample's time, between knots k−1 and k
    velocity   (v_j,k − m̄_v) √n / σ_v      the mean over (t_k − 0.9 h, t_k + 0.1 h], v_k's
                                           Euler step (a stamp jittering just past t_k its own)
    effort     the generalized force of dof j, known to the physics factor where no command
               drives it: W (u_j(q, v, a) − m_τ) with σ = physics_std_actuated

A stream uses the fields its config's `use` lists (default position and effort; a velocity
an encoder driver reports is often a filtered difference, delayed: opt in).
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
)
from estimator.io.logs.measurements import Measurement
from estimator.knots import averaged_at_knots, held_at_knots

_SENS = mujoco.mjtSensor
_LATE = 0.1  # of a knot step: how late a velocity sample may be stamped and still be its knot's


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    sensors = [(_SENS.mjSENS_JOINTPOS, "pos")]
    if "velocity" in stream.use:
        sensors.append((_SENS.mjSENS_JOINTVEL, "vel"))
    return add_element_sensors(spec, stream, sensors)


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    noise, per_joint = stream.noise, len(rows) // max(len(stream.elements), 1)
    out = StreamFactors()
    if "position" in stream.use:
        for slot, (values, alpha) in enumerate(grid.position_slots(m)):
            out.blocks.append(
                SensorBlock(
                    stream.name,
                    "vector",
                    np.concatenate(rows[::per_joint]),
                    values[:, :, 0],
                    np.full(values.shape[1], noise["position_std"]),
                    group=1,
                    alpha=alpha,
                    slot=slot,
                    labels=tuple(f"{element} position" for element in stream.elements),
                )
            )
    if "velocity" in stream.use:
        # an encoder often samples on the controller's clock, as the knots do: a stamp a
        # little after t_k is knot k's velocity, not the next step's
        late_ns = int(_LATE * (grid.t_ns[1] - grid.t_ns[0])) if grid.T > 1 else 0
        mean, counts = averaged_at_knots(m, grid.t_ns, "vel", late_ns, grid.h_ns)
        out.blocks.append(
            SensorBlock(
                stream.name,
                "vector",
                np.concatenate(rows[1::per_joint]),
                mean[:, :, 1],
                noise["velocity_std"] / np.sqrt(np.maximum(counts[:, :, 1], 1)),  # (T, E)
                stage="vel",
                group=1,
                labels=tuple(f"{element} velocity" for element in stream.elements),
            )
        )
    if "effort" in stream.use:
        effort = held_at_knots(m, grid.t_ns, component=2)
        for e, joint in enumerate(stream.elements):
            dof = int(grid.model.jnt_dofadr[grid.model.joint(joint).id])
            out.efforts[dof] = effort[:, e]
    return out


def holdout(stream: StreamConfig) -> Holdout:
    fields = [f for f in ("position", "velocity") if f in stream.use]
    names = tuple(
        element if f == "position" else f"{element}.velocity"
        for element in stream.elements
        for f in fields
    )
    sigma = np.array([stream.noise[f"{f}_std"] for _ in stream.elements for f in fields])
    component = [0 if f == "position" else 1 for f in fields]

    def residuals(predicted: np.ndarray, m: Measurement) -> np.ndarray:
        measured = m.values[:, :, component].reshape(len(m), -1)  # joints × fields, as sensors
        return predicted - measured

    return Holdout(names, sigma, ("rad or m", "rad/s or m/s"), residuals)
