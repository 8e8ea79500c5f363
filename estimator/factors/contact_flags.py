"""Binary foot-contact flags: whether each foot touches the ground, from the robot's own
contact detection (a force threshold, a switch, the gait scheduler's stance).

    flag 0 (swing)    f_c(q, v, a) / σ_f     the foot's net contact force (MuJoCo's contact
                                            sensor, reduce = netforce) from the analytic
                                            inverse: a foot in the air carries none
    flag 1 (stance)   v_p(q, v) / σ_slip     the world velocity of the foot's contact point p:
                                            a foot on the ground does not slip

The flag of knot k is the last one at or before t_k. p is the foot geom's centre (`geoms`),
or, for a foot body (`bodies`), a site `physfuse/<stream>/<body>/sole` added at its sole
(`_sole_site`). A flag says nothing about how hard a foot presses:
that stays with the physics factor.
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
    labels,
)
from estimator.io.logs.measurements import Measurement
from estimator.knots import held_at_knots

_OBJ = mujoco.mjtObj
_SENS = mujoco.mjtSensor
# MuJoCo's contact sensor: intprm = (data fields as bits of mjtConDataField, reduce, num)
_NET_FORCE = (1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE), 3, 1)  # 3: netforce
_SOLE_BAND_M = 0.02


def add_sensors(spec: mujoco.MjSpec, stream: StreamConfig) -> list[str]:
    added = []
    compiled = spec.compile() if stream.element_type == "body" else None
    for foot in stream.elements:
        force = spec.add_sensor()
        force.name = f"physfuse/{stream.name}/{foot}/force"
        force.type = _SENS.mjSENS_CONTACT
        force.objtype = _OBJ.mjOBJ_BODY if stream.element_type == "body" else _OBJ.mjOBJ_GEOM
        force.objname = foot
        force.intprm[:3] = _NET_FORCE
        velocity = spec.add_sensor()
        velocity.name = f"physfuse/{stream.name}/{foot}/vel"
        velocity.type = _SENS.mjSENS_FRAMELINVEL
        if compiled is None:
            velocity.objtype, velocity.objname = _OBJ.mjOBJ_GEOM, foot
        else:
            velocity.objtype = _OBJ.mjOBJ_SITE
            velocity.objname = _sole_site(spec, compiled, stream, foot)
        added += [force.name, velocity.name]
    return added


def _sole_site(spec: mujoco.MjSpec, model: mujoco.MjModel, stream: StreamConfig, body: str) -> str:
    """A site at the foot's sole: the mean position, in the body's frame, of the body's
    colliding geoms within 2 cm of its lowest one in the model's reference pose (a foot
    sphere rather than the shin capsule above it; a flat foot's heel and toe together)."""
    b = model.body(body).id
    geoms = np.flatnonzero(
        (model.geom_bodyid == b) & ((model.geom_contype != 0) | (model.geom_conaffinity != 0))
    )
    site = spec.body(body).add_site()
    site.name = f"physfuse/{stream.name}/{body}/sole"
    if len(geoms):
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        z = data.geom_xpos[geoms, 2]
        site.pos = np.mean(model.geom_pos[geoms[z < z.min() + _SOLE_BAND_M]], axis=0)
    return site.name


def factors(
    stream: StreamConfig, m: Measurement, rows: list[np.ndarray], grid: Grid
) -> StreamFactors:
    flags = held_at_knots(m, grid.t_ns)  # (T, E), NaN before the first
    swing, stance = flags < 0.5, flags >= 0.5
    zeros = np.zeros((grid.T, len(stream.elements), 3))
    blocks = []
    for on, rows_of, std, stage, quantity in (
        (swing, rows[0::2], stream.noise["force_std"], "acc", "contact force"),
        (stance, rows[1::2], stream.noise["slip_std"], "vel", "slip velocity"),
    ):
        values = np.where(on[:, :, None], zeros, np.nan).reshape(grid.T, -1)
        blocks.append(
            SensorBlock(
                stream.name,
                "vector",
                np.concatenate(rows_of),
                values,
                np.full(values.shape[1], std),
                stage=stage,
                group=3,
                kernel="sensor_kernel",
                labels=tuple(label for foot in stream.elements for label in labels(foot, quantity)),
            )
        )
    return StreamFactors(blocks)


def holdout(stream: StreamConfig) -> Holdout:
    """Per foot: the contact force where flagged off and the slip velocity where on."""
    names = tuple(
        f"{foot}.{q}_{c}" for foot in stream.elements for q in ("force", "slip") for c in "xyz"
    )
    per_foot = [stream.noise["force_std"]] * 3 + [stream.noise["slip_std"]] * 3
    sigma = np.array(per_foot * len(stream.elements))

    def residuals(predicted: np.ndarray, m: Measurement) -> np.ndarray:
        flag = m.values[:, :, 0]  # (N, E)
        out = predicted.reshape(len(m), -1, 2, 3).copy()  # foot × (force, velocity) × xyz
        out[:, :, 0][~(flag < 0.5)] = np.nan
        out[:, :, 1][~(flag >= 0.5)] = np.nan
        return out.reshape(len(m), -1)

    return Holdout(names, sigma, ("N", "m/s"), residuals)
