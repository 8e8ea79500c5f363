"""A low-friction patch under a foot (the `disturbances` condition): a slip the model does not
expect.

A `Patch` lowers, from `start_s` for `duration_s`, the sliding friction of one foot's
contacts (its geoms that touch the world at the keyframe) to `friction` (it takes
precedence over the floor's: MuJoCo's geom priority) — the foot stands or lands on
something slippery. The estimator's model keeps the friction it
has, so where the foot slides its contact asks for a friction force that the floor did not
give. A standing robot cannot walk onto a patch, so the patch comes to the foot; a walking
one meets it at every stance of that foot within the interval.

The feet are the robot bodies with geoms that touch the world at the scenario's keyframe
(`feet`). The truth is what the simulation measured (`Patches.events`): a patch under which
the foot slid — a contact point faster than `SLIDING_MPS` over the world while its contact
pressed with more than `TOUCHING_N` — by at least `SLID_M` is an event "slip" from the first
to the last sliding step, with the foot's body, the distance slid and the peak speed; a
patch under which the foot held is no event.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from estimator.simulate.controllers import Push

SLIDING_MPS = 0.03  # a contact point faster than this over the world slides
SLID_M = 0.005  # a slip shorter than this is none
TOUCHING_N = 5.0  # a contact pressing with more than this touches


@dataclass(frozen=True)
class Patch(Push):
    """A push schedule's entry that pushes nothing: for its interval, the foot `body`'s geoms
    `geoms` (ids of the model) have sliding friction `friction`; `force` is 0."""

    geoms: tuple[int, ...]
    friction: float

    def as_dict(self) -> dict[str, object]:
        return {
            "kind": "patch",
            "body": self.body,
            "geoms": list(self.geoms),
            "start_s": self.start_s,
            "duration_s": self.duration_s,
            "friction": self.friction,
        }


def feet(model: mujoco.MjModel, keyframe: str | int) -> list[tuple[str, tuple[int, ...]]]:
    """(body name, geom ids) of the robot bodies with geoms touching a world geom at
    `keyframe`, those geoms (none for a fixed base in the air)."""
    data = mujoco.MjData(model)
    key = keyframe
    if isinstance(key, str):
        key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
    if key >= 0:
        mujoco.mj_resetDataKeyframe(model, data, key)
    mujoco.mj_forward(model, data)
    touching: dict[int, set[int]] = {}
    for c in data.contact[: data.ncon]:
        bodies = model.geom_bodyid[c.geom]
        if min(bodies) == 0 < max(bodies) and c.dist <= 0.0:
            touching.setdefault(int(max(bodies)), set()).add(int(c.geom[int(np.argmax(bodies))]))
    return [(model.body(b).name, tuple(sorted(g))) for b, g in sorted(touching.items())]


class Patches:
    """Applies `patches` during a run and measures the slips they cause.

    Call `apply(t)` before `mj_step1` of every step (contacts take their friction when they
    are made), `measure(d, k)` after `mj_step2`, and `restore()` once the run ends (the
    model is left as it was).
    """

    def __init__(self, model: mujoco.MjModel, patches: Sequence[Patch]):
        self.model = model
        self.patches = list(patches)
        self.friction = model.geom_friction[:, 0].copy()
        self.priority = model.geom_priority.copy()
        self.on = max(int(model.geom_priority.max()), 0) + 1  # above every geom's
        # (step, patch index, sliding speed [m/s]) of the steps a patched foot touched
        self.touches: list[tuple[int, int, float]] = []
        self.active: Patch | None = None

    def apply(self, t: float) -> None:
        now = next((p for p in self.patches if p.active(t)), None)
        if now is self.active:
            return
        self.restore()
        if now is not None:
            geoms = list(now.geoms)
            self.model.geom_friction[geoms, 0] = now.friction
            self.model.geom_priority[geoms] = self.on
        self.active = now

    def restore(self) -> None:
        self.model.geom_friction[:, 0] = self.friction
        self.model.geom_priority[:] = self.priority

    def measure(self, d: mujoco.MjData, k: int) -> None:
        """The patched foot's contacts with the world at step k: the fastest contact point's
        speed along the floor (d.qvel: the velocity the step integrated with)."""
        if self.active is None:
            return
        m, geoms = self.model, self.active.geoms
        f6, jacp = np.zeros(6), np.zeros((3, m.nv))
        speed, touching = 0.0, False
        for i in range(d.ncon):
            c = d.contact[i]
            mine = [int(g) for g in c.geom if g in geoms]
            if not mine or min(m.geom_bodyid[c.geom]) != 0:
                continue
            mujoco.mj_contactForce(m, d, i, f6)
            if f6[0] <= TOUCHING_N:
                continue
            touching = True
            mujoco.mj_jac(m, d, jacp, None, c.pos, int(m.geom_bodyid[mine[0]]))
            v = jacp @ d.qvel
            normal = c.frame[:3]
            speed = max(speed, float(np.linalg.norm(v - (v @ normal) * normal)))
        if touching:
            self.touches.append((k, self.patches.index(self.active), speed))

    def events(self, h: float, names: Sequence[str]) -> list[dict[str, Any]]:
        """One truth record per patch the foot slid on (module docstring): kind "slip",
        body, start_s/end_s (first sliding step, after the last), distance_m (the fastest
        contact point's path from the one to the other, every touching step), peak_mps,
        friction (the patch's), and the patch's own interval (`patch_s`)."""
        out = []
        steps = np.array([t[0] for t in self.touches], dtype=int)
        which = np.array([t[1] for t in self.touches], dtype=int)
        speed = np.array([t[2] for t in self.touches], dtype=float)
        for i, p in enumerate(self.patches):
            sliding = (which == i) & (speed > SLIDING_MPS)
            if not sliding.any():
                continue
            first, last = steps[sliding].min(), steps[sliding].max()
            during = (which == i) & (steps >= first) & (steps <= last)
            if speed[during].sum() * h < SLID_M:
                continue
            out.append(
                {
                    "kind": "slip",
                    "body": p.body,
                    "start_s": round(float(first * h), 6),
                    "end_s": round(float((last + 1) * h), 6),
                    "distance_m": float(speed[during].sum() * h),
                    "peak_mps": float(speed[sliding].max()),
                    "friction": p.friction,
                    "patch_s": [p.start_s, round(p.start_s + p.duration_s, 6)],
                }
            )
        return out
