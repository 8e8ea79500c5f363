"""The `disturbances` condition: what the contact diagnostics must find, its truth in the log.

    physfuse simulate humanoid_push --condition disturbances --out LOG.mcap

On top of `nominal` (the scenario's own pushes replaced):

    pushes        one every 1–2 s from 0.5 s to 70% of the log, each on a moving body
                  with mass drawn uniformly (`push_bodies`), 20–100 N for 0.05–0.3 s
                  (uniform), at the body's centre of mass, in a direction uniform in azimuth
                  and within ±30° of horizontal — never logged.
    collisions    each push on a body with a collision geom is, with probability ½, instead
                  delivered by an obstacle that is not in the model (`obstacle.py`): a
                  sphere that comes along the push's direction, touches the body's surface
                  and presses with about the push's force for its duration — a contact
                  force at a point of the surface, friction included.
    IMU bias step the first IMU's gyro (or, with probability ½, accelerometer) bias on one axis
                  steps by ±0.05 rad/s (±0.5 m/s²) at a uniform time in 70–80% of the log and
                  stays.
    slip          with feet (robot bodies touching the world at the keyframe), one low-friction
                  patch: for 0.3–0.8 s at a uniform time within the pushes' span, one foot's
                  (uniform) sliding friction is 0.01–0.08 (uniform; `patch.py`).
    encoder jump  one joint's encoder reading (uniform over the encoders' joints) jumps by
                  ±0.02 rad (±5 mm on a slide) at a uniform time in 85–95% of the log and
                  stays.

A push (or a patch) the robot cannot withstand is left out: the run is repeated without the
last one that started before the robot's root fell below `FALLEN` of its starting height,
until it stays up (a robot on the floor is all contact, and a fall is not what the
diagnostics are tested on).
The sensor faults come after the pushes: an estimate that takes in a faulty sensor is off
from then on, and the pushes are to be found on an estimate as good as the sensors allow.

The truth is the metadata record `physfuse.condition`, key `events`: a JSON list of
{"kind": "push" | "collision" | "slip" | "imu bias step" | "encoder offset", "start_s", "end_s", and
"body", "force_n" (world frame) for a push or a collision (as the simulation measured it:
the body that took most of it, its first and last touching step, its mean force on the
robot); "body", "distance_m" for a "slip" (a patch the foot slid on, from its first
to its last sliding step); "stream", "component", "step" for a sensor fault}, times
in seconds of simulated time from the start of the log (the log's stamps less their clock
offsets). The draws come after the scenario's own (controller, the sensors' noise), so a
disturbed log and its nominal twin differ only by them and by what they change.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from estimator.simulate.controllers import Push
from estimator.simulate.errors import SimulationError
from estimator.simulate.obstacle import Collision
from estimator.simulate.patch import Patch
from estimator.simulate.sensors import NS, Encoders, Imu, SensorOutput, Trajectory, Wrapping

PUSH_FORCE_N = (20.0, 100.0)
PUSH_S = (0.05, 0.3)
PUSH_EVERY_S = (1.0, 2.0)
PUSH_ELEVATION_RAD = np.deg2rad(30.0)
COLLISION_PROBABILITY = 0.5  # of a disturbance on a body the obstacle can touch
MARGIN_S = 0.5
FALLEN = 0.6  # of the root's starting height
PUSHES_UNTIL = 0.7  # of the log; the sensor faults come after
IMU_FAULT, ENCODER_FAULT = (0.70, 0.80), (0.85, 0.95)  # of the log
GYRO_STEP = 0.05  # rad/s
ACCEL_STEP = 0.5  # m/s²
ENCODER_JUMP = (0.02, 0.005)  # rad on a hinge, m on a slide
PATCH_S = (0.3, 0.8)
PATCH_FRICTION = (0.01, 0.08)


def push_bodies(model: mujoco.MjModel) -> list[str]:
    """The bodies a push may land on: every body with mass that moves (has dofs or is welded
    to one that has)."""
    out = []
    for b in range(1, model.nbody):
        root, moves = b, False
        while root and not moves:
            moves = bool(model.body_dofnum[root])
            root = int(model.body_parentid[root])
        if moves and model.body_mass[b] > 0:
            out.append(model.body(b).name or f"body {b}")
    return out


def random_body_pushes(
    bodies: list[str],
    touchable: Sequence[str] = (),
    feet: Sequence[tuple[str, tuple[int, ...]]] = (),
) -> Callable[[np.random.Generator, float], tuple[Push, ...]]:
    """A push factory (rng, duration) → pushes in time order, as the module docstring says;
    on a body in `touchable`, each is with probability `COLLISION_PROBABILITY` a `Collision`
    instead, and with `feet` ((body, geoms) pairs: `patch.feet`) one `Patch` is among them
    (both drawn from a generator spawned off rng: the pushes' own draws are those without
    collisions and patches)."""
    if not bodies:
        raise SimulationError("condition disturbances: the model has no moving body to push")

    def pushes(rng: np.random.Generator, duration_s: float) -> tuple[Push, ...]:
        (kinds,) = rng.spawn(1)
        out: list[Push] = []
        t = MARGIN_S
        while True:
            length = float(rng.uniform(*PUSH_S))
            if t + length > PUSHES_UNTIL * duration_s:
                return tuple(sorted(out + _patch(kinds, duration_s, feet), key=_start))
            body = bodies[int(rng.integers(len(bodies)))]
            magnitude = rng.uniform(*PUSH_FORCE_N)
            azimuth = rng.uniform(0.0, 2.0 * np.pi)
            elevation = rng.uniform(-PUSH_ELEVATION_RAD, PUSH_ELEVATION_RAD)
            horizontal = np.cos(elevation) * np.array([np.cos(azimuth), np.sin(azimuth)])
            direction = np.r_[horizontal, np.sin(elevation)]
            fx, fy, fz = (float(f) for f in magnitude * direction)
            collides = kinds.uniform() < COLLISION_PROBABILITY and body in touchable
            kind = Collision if collides else Push
            out.append(kind(body, round(t, 6), round(length, 6), (fx, fy, fz)))
            t += length + float(rng.uniform(*PUSH_EVERY_S))

    return pushes


def _patch(
    rng: np.random.Generator, duration_s: float, feet: Sequence[tuple[str, tuple[int, ...]]]
) -> list[Push]:
    length = float(rng.uniform(*PATCH_S))
    if not feet or MARGIN_S + length > PUSHES_UNTIL * duration_s:
        return []
    start = float(rng.uniform(MARGIN_S, PUSHES_UNTIL * duration_s - length))
    body, geoms = feet[int(rng.integers(len(feet)))]
    friction = round(float(rng.uniform(*PATCH_FRICTION)), 4)
    return [Patch(body, round(start, 6), round(length, 6), (0.0, 0.0, 0.0), geoms, friction)]


def _start(push: Push) -> float:
    return push.start_s


@dataclass(frozen=True)
class ImuBiasStep(Wrapping):
    """An IMU whose gyro or accelerometer bias on one axis steps at a random time."""

    sensor: Imu

    def settings(self) -> dict[str, Any]:
        return self.sensor.settings() | {"fault": "bias step"}

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        out = self.sensor.sample(traj, rng)
        gyro = bool(rng.uniform() < 0.5)
        axis = int(rng.integers(3))
        step = (GYRO_STEP if gyro else ACCEL_STEP) * float(rng.choice([-1.0, 1.0]))
        start_s = _fault_time(traj, rng, IMU_FAULT)
        field = "angular_velocity" if gyro else "linear_acceleration"
        key = "xyz"[axis]
        after = out.truth["t_ns"] >= start_s * NS
        messages = []
        for m, faulty in zip(out.messages, after, strict=True):
            if faulty:
                vector = dict(m.fields[field])
                vector[key] += step
                m = m._replace(fields=m.fields | {field: vector})
            messages.append(m)
        event = {
            "kind": "imu bias step",
            "stream": self.name,
            "component": f"{'gyro' if gyro else 'accel'} {key}",
            "start_s": start_s,
            "end_s": traj.duration_ns / NS,
            "step": step,
        }
        return SensorOutput(messages, out.truth | {"events": [event]})


@dataclass(frozen=True)
class EncoderJump(Wrapping):
    """Joint encoders of which one joint's reading jumps by an offset at a random time."""

    sensor: Encoders

    def settings(self) -> dict[str, Any]:
        return self.sensor.settings() | {"fault": "offset jump"}

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        out = self.sensor.sample(traj, rng)
        names = out.truth["names"]
        j = int(rng.integers(len(names)))
        joint = mujoco.mj_name2id(traj.model, mujoco.mjtObj.mjOBJ_JOINT, names[j])
        hinge = traj.model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_HINGE
        step = ENCODER_JUMP[0 if hinge else 1] * float(rng.choice([-1.0, 1.0]))
        start_s = _fault_time(traj, rng, ENCODER_FAULT)
        after = out.truth["t_ns"] >= start_s * NS
        messages = []
        for m, faulty in zip(out.messages, after, strict=True):
            if faulty:
                position = list(m.fields["position"])
                position[j] += step
                m = m._replace(fields=m.fields | {"position": position})
            messages.append(m)
        event = {
            "kind": "encoder offset",
            "stream": self.name,
            "component": f"{names[j]} position",
            "start_s": start_s,
            "end_s": traj.duration_ns / NS,
            "step": step,
        }
        return SensorOutput(messages, out.truth | {"events": [event]})


def fall_time(traj: Trajectory) -> float | None:
    """When the first free joint's height first drops below `FALLEN` of its start [s from
    the start]; None if it never does or the model has no free joint."""
    free = np.flatnonzero(traj.model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if not free.size:
        return None
    z = traj.qpos[:, traj.model.jnt_qposadr[free[0]] + 2]
    low = np.flatnonzero(z < FALLEN * z[0])
    return float(low[0] * traj.h) if low.size else None


def without_culprit(pushes: tuple[Push, ...], fall_s: float) -> tuple[Push, ...]:
    """The pushes less the last one that started before the fall (the first if none did)."""
    before = [i for i, p in enumerate(pushes) if p.start_s < fall_s]
    culprit = before[-1] if before else 0
    return pushes[:culprit] + pushes[culprit + 1 :]


def push_events(pushes: Sequence[Push]) -> list[dict[str, Any]]:
    return [
        {
            "kind": "push",
            "body": p.body,
            "start_s": p.start_s,
            "end_s": p.start_s + p.duration_s,
            "force_n": list(p.force),
        }
        for p in pushes
    ]


def _fault_time(traj: Trajectory, rng: np.random.Generator, span: tuple[float, float]) -> float:
    duration = traj.duration_ns / NS
    return round(float(rng.uniform(span[0] * duration, span[1] * duration)), 6)
