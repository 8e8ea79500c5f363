"""Collisions with an obstacle that is not in the model (the `disturbances` condition).

The simulated world gets one more body, `OBSTACLE`: a mocap sphere of radius `RADIUS` parked
far below the floor. A `Collision` brings it against a robot body: at the collision's start
it is placed where, coming along the collision's direction on the line through the body's
centre of mass, it first touches the robot (that body, or whatever is in the way), then
pressed along that direction with its contact force Σ_b ‖F_b‖ held near the drawn magnitude
F* (each step the sphere follows the centre of mass of the body it touches along the path
and moves in by `RELAX` (F* − Σ_b ‖F_b‖) / K̂, at most `STEP`, K̂ the contact's stiffness
from the last step's ΔF/Δx: stable from a free hand to a leg on the ground, at 1 to 10 ms
steps; a padded sphere, its contact's time constant `SOLREF`), and parked again at the end.
The force the robot feels is the contact's (normal and friction, at the touching point: a
force and a moment about the centre of mass), and how long it lasts is how long the sphere
touches — the truth written to the log is what the simulation measured (`Obstacle.events`),
not the draw.

The obstacle touches only the robot (it is welded to the world, as the floor is, and MuJoCo
does not collide bodies welded together) and is invisible to everything the log holds: it has
no joint (no state), no sensor, and it is parked when the ground truth's inverse dynamics run,
so a collision's force there is, as a push's, part of the unexplained generalized force.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from estimator.simulate.controllers import Push

OBSTACLE = "physfuse/obstacle"
RADIUS = 0.04  # m
PARKED = (0.0, 0.0, -100.0)  # m, world
STIFFNESS = (2e4, 1e3, 1e7)  # N/m: the contact's ΔF/Δx at first, its least and most
RELAX = 0.5  # of the step a secant (Newton) iteration on the force would take
STEP = 1e-3  # m, the most the sphere moves into (out of) the robot in a step
FRICTION = 0.3  # sliding friction of the obstacle's contacts (it takes precedence)
SOLREF = (0.05, 1.0)  # a padded obstacle: time constant [s], damping ratio
TOUCHING_N = 1.0  # a contact force above this is a touch
REACH = 2.0  # m: the sphere comes from this far along its path


@dataclass(frozen=True)
class Collision(Push):
    """A push delivered through a contact: `force` is the drawn force (its direction the
    sphere's path, its norm the force it presses with)."""

    def as_dict(self) -> dict[str, object]:
        return super().as_dict() | {"kind": "collision"}


def add_obstacle(spec: mujoco.MjSpec, model: mujoco.MjModel) -> None:
    """Add the parked sphere to `spec` (of `model`): it collides with every robot geom that
    collides with anything (its contype and conaffinity the union of theirs)."""
    robot = np.flatnonzero(model.geom_bodyid > 0)
    contype = int(np.bitwise_or.reduce(model.geom_contype[robot], initial=0))
    conaffinity = int(np.bitwise_or.reduce(model.geom_conaffinity[robot], initial=0))
    body = spec.worldbody.add_body(name=OBSTACLE, mocap=True, pos=list(PARKED))
    body.add_geom(
        name=OBSTACLE,
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[RADIUS, 0.0, 0.0],
        contype=conaffinity,
        conaffinity=contype,
        condim=3,
        priority=1,
        friction=[FRICTION, 0.005, 0.0001],
        solref=list(SOLREF),
        rgba=[0.9, 0.4, 0.1, 0.5],
    )


def touchable(model: mujoco.MjModel, bodies: Sequence[str]) -> list[str]:
    """Of `bodies`, those with a geom that collides with something (the sphere can touch)."""
    out = []
    for name in bodies:
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        geoms = np.flatnonzero(model.geom_bodyid == b)
        if np.any((model.geom_contype[geoms] | model.geom_conaffinity[geoms]) > 0):
            out.append(name)
    return out


class Obstacle:
    """Drives the sphere through `collisions` during a run and records what it did.

    Call `move(d, t)` after `mj_step1` at every step (it sets where the sphere is for the
    next step) and `measure(d)` after `mj_step2` (the contact force of the step just solved).
    """

    def __init__(self, model: mujoco.MjModel, collisions: Sequence[Collision], steps: int):
        self.model = model
        self.collisions = list(collisions)
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, OBSTACLE)
        self.mocap = int(model.body_mocapid[body])
        self.geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, OBSTACLE)
        # (step, body, force on it [N], ‖force‖-weighted mean contact position [m]), world
        self.touches: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self.active: Collision | None = None
        self.k = 0
        self.pressed = 0.0  # the last step's force on the robot, Σ over bodies of ‖F_b‖ [N]
        self.touching = 0  # the body it pressed on most in the last step (0: none)
        self.before = 0.0  # the force of the step before [N]
        self.pushed = 0.0  # how far the last step moved the sphere into the robot [m]
        self.stiffness = STIFFNESS[0]  # the contact's ΔF/Δx, estimated [N/m]

    def move(self, d: mujoco.MjData, t: float) -> None:
        now = next((c for c in self.collisions if c.active(t)), None)
        if now is None:
            d.mocap_pos[self.mocap] = PARKED
        elif now is not self.active:
            d.mocap_pos[self.mocap] = self._touching(d, now)
            self.stiffness, self.pushed = STIFFNESS[0], 0.0
        else:
            path = _unit(now.force)
            b = self.touching or mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, now.body)
            velocity = np.zeros(6)
            mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_BODY, b, velocity, 0)
            follow = float(velocity[3:] @ path)  # the body's centre of mass, along the path
            if self.pushed and min(self.pressed, self.before) > TOUCHING_N:
                secant = (self.pressed - self.before) / self.pushed
                if secant > 0.0:  # ΔF/Δx of the last step, smoothed in log scale
                    stiffness = np.sqrt(self.stiffness * secant)
                    self.stiffness = float(np.clip(stiffness, *STIFFNESS[1:]))
            error = float(np.linalg.norm(now.force)) - self.pressed
            self.pushed = float(np.clip(RELAX * error / self.stiffness, -STEP, STEP))
            self.before = self.pressed
            d.mocap_pos[self.mocap] += path * (follow * self.model.opt.timestep + self.pushed)
        self.active = now

    def measure(self, d: mujoco.MjData, k: int) -> None:
        f6 = np.zeros(6)
        by_body: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # body → (force, Σ‖f‖ pos)
        for i in range(d.ncon):
            c = d.contact[i]
            if self.geom not in (c.geom1, c.geom2):
                continue
            mujoco.mj_contactForce(self.model, d, i, f6)
            on_geom2 = c.frame.reshape(3, 3).T @ f6[:3]  # from geom1 on geom2, world
            robot_geom, force = (
                (c.geom2, on_geom2) if c.geom1 == self.geom else (c.geom1, -on_geom2)
            )
            b = int(self.model.geom_bodyid[robot_geom])
            total, moment = by_body.get(b, (np.zeros(3), np.zeros(3)))
            by_body[b] = (total + force, moment + np.linalg.norm(force) * c.pos)
        for b, (force, moment) in by_body.items():
            point = moment / max(float(np.linalg.norm(force)), 1e-12)
            self.touches.append((k, b, force, point))
        self.pressed = sum(float(np.linalg.norm(f)) for f, _ in by_body.values())
        self.touching = max(by_body, key=lambda b: float(np.linalg.norm(by_body[b][0])), default=0)

    def _touching(self, d: mujoco.MjData, c: Collision) -> np.ndarray:
        """Where the sphere's centre first touches the robot coming along c.force on the
        line through c.body's centre of mass: rays parallel to the path, across the sphere's
        cross-section, against every robot geom that collides (what is in the way is hit)."""
        m = self.model
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, c.body)
        path = _unit(c.force)
        start = d.xipos[b] - REACH * path
        e1 = _unit(np.cross(path, [0.0, 0.0, 1.0] if abs(path[2]) < 0.9 else [1.0, 0.0, 0.0]))
        e2 = np.cross(path, e1)
        geoms = [
            g
            for g in np.flatnonzero(m.geom_bodyid > 0)
            if g != self.geom and m.geom_contype[g] | m.geom_conaffinity[g]
        ]
        travel = np.inf  # of the sphere's centre from `start` until it touches
        for rho in (0.0, 0.5 * RADIUS, 0.9 * RADIUS):
            ahead = np.sqrt(RADIUS**2 - rho**2)  # the sphere's front at that offset
            for angle in np.arange(8 if rho else 1) * np.pi / 4:
                ray = start + rho * (np.cos(angle) * e1 + np.sin(angle) * e2)
                for g in geoms:
                    x = mujoco.mju_rayGeom(
                        d.geom_xpos[g],
                        d.geom_xmat[g],
                        m.geom_size[g],
                        ray,
                        path,
                        int(m.geom_type[g]),
                    )
                    if x >= 0:
                        travel = min(travel, x - ahead)
        if not np.isfinite(travel):  # nothing in the way: a mesh, say; touch at the centre
            travel = REACH - RADIUS
        return start + travel * path

    def events(self, h: float, names: Sequence[str]) -> list[dict[str, Any]]:
        """One truth record per collision that touched the robot: kind "collision", the
        body that took most of its impulse and the mean force on it over the steps it was
        touched (world frame [N]) and where (`point_m`, world [m], the contacts' mean weighted
        by force), from the first to the last touching step [s]; every body
        touched with its share of the impulse (`touched`), the drawn force (`drawn_force_n`)."""
        out = []
        k = np.array([t[0] for t in self.touches], dtype=int)
        body = np.array([t[1] for t in self.touches], dtype=int)
        force = np.array([t[2] for t in self.touches]).reshape(-1, 3)
        point = np.array([t[3] for t in self.touches]).reshape(-1, 3)
        touching = np.linalg.norm(force, axis=1) > TOUCHING_N
        for c in self.collisions:
            k0, k1 = round(c.start_s / h), round((c.start_s + c.duration_s) / h)
            inside = touching & (k >= k0) & (k <= k1)
            if not inside.any():
                continue
            impulse = {
                int(b): float(np.linalg.norm(force[inside & (body == b)], axis=1).sum())
                for b in np.unique(body[inside])
            }
            main = max(impulse, key=impulse.__getitem__)
            on_main = inside & (body == main)
            out.append(
                {
                    "kind": "collision",
                    "body": names[main],
                    "start_s": round(float(k[inside].min() * h), 6),
                    "end_s": round(float((k[inside].max() + 1) * h), 6),
                    "force_n": force[on_main].mean(axis=0).tolist(),
                    "point_m": np.average(
                        point[on_main], axis=0, weights=np.linalg.norm(force[on_main], axis=1)
                    ).tolist(),
                    "touched": {
                        names[b]: round(i / sum(impulse.values()), 3) for b, i in impulse.items()
                    },
                    "drawn_force_n": list(c.force),
                }
            )
        return out


def _unit(v: Sequence[float] | np.ndarray) -> np.ndarray:
    u = np.asarray(v, dtype=float)
    return u / np.linalg.norm(u)
