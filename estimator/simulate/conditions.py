"""Conditions: the same scenario under the circumstances that break estimators.

    scenario = with_condition(get_scenario("humanoid_push"), "occlusion")
    physfuse simulate humanoid_push --condition occlusion --out LOG.mcap

Without a condition a scenario is simulated as its sample recording was (sparse mocap
dropouts and outliers mixed in). With one:

    nominal      the scenario's sensors with all their imperfections except two: no mocap
                 dropouts and no mocap outliers. White noise, IMU biases (turn-on offset and
                 random walk), saturation, encoder quantization, clock offsets, stamp jitter
                 and latency stay. The model mismatch is the scenario's default `Mismatch()`
                 (log-normal: σ 5% mass, 5% inertia, 10% friction, 10% contact softness):
                 a robot is never exactly its model.
    occlusion    nominal + the mocap system loses the robot (every body of its mocap
                 sensor; a marker sensor: every marker) for 0.2–1 s, once in each 1.25 s
                 slot of the log after a 0.25 s margin at either end. (Hiding one body of an
                 articulated robot whose other bodies stay in view hides nothing: the
                 encoders carry their pose over to it.)
    outliers     nominal + mocap outliers: each frame of each body (each marker) is, with
                 probability 2%, off by 3–15 cm in a random direction (a pose also turned
                 by 0.5 rad) — a marker swap.
    mismatch     nominal, but the model off by exactly ±10% in every body's mass (inertia
                 scaled with it, then ±5% per principal moment), ±30% in every geom's sliding
                 friction and ±10% in the contact softness ε and κ; each sign drawn per
                 body, moment, geom and parameter (`SignedMismatch`).
    no_commands  nominal, but the commands are not logged: no command topic in the log and
                 no command stream in the config.
    disturbances nominal + unlogged pushes on random bodies (half of them, where the body has
                 a collision geom, collisions with an obstacle not in the model), a
                 low-friction patch under a foot (a slip), an IMU bias step and an encoder
                 offset jump, their truth in the log (`disturbances`: what the contact
                 diagnostics must find).

Under every condition but disturbances the seed draws the same model mismatch (up to
`mismatch`'s signed factors), controller and pushes, so nominal, occlusion, outliers and
no_commands simulate the same true motion.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from estimator.io.mcap_writer import Message
from estimator.simulate import disturbances
from estimator.simulate.errors import SimulationError
from estimator.simulate.mismatch import SignedMismatch
from estimator.simulate.obstacle import touchable
from estimator.simulate.patch import feet
from estimator.simulate.scenarios import Scenario
from estimator.simulate.sensors import (
    NS,
    Commands,
    Encoders,
    Imu,
    MocapMarkers,
    MocapPoses,
    Sensor,
    SensorOutput,
    Trajectory,
    Wrapping,
)
from physics.model import load_model

CONDITIONS: Mapping[str, str] = {
    "nominal": "sensor noise, biases and latency, default model mismatch; no mocap dropouts "
    "or outliers",
    "occlusion": "nominal + every mocap body occluded 0.2-1 s once per 1.25 s",
    "outliers": "nominal + 2% of mocap frames per body (marker) off by 3-15 cm",
    "mismatch": "nominal with the model off by exactly ±10% mass, ±30% friction",
    "no_commands": "nominal without the command topic (no command stream in the config)",
    "no_mocap": "nominal without motion capture (no mocap stream in the log or the config): "
    "IMU, encoders and commands, as a legged robot in the field",
    "disturbances": "nominal + pushes on random bodies (20-100 N, 0.05-0.3 s), half of them "
    "collisions with an obstacle not in the model, a low-friction patch under a foot, an IMU bias "
    "step, an encoder offset jump",
}

OUTLIER_PROBABILITY = 0.02  # per frame and body (or marker), the `outliers` condition
MISMATCH = SignedMismatch(
    mass_rel_std=0.10, inertia_rel_std=0.05, friction_rel_std=0.30, softness_rel_std=0.10
)


@dataclass(frozen=True)
class Occluded(Wrapping):
    """A mocap sensor whose `targets` (pose labels, or marker sites of one body) all vanish
    together for stretches of `duration_s` (min, max) [s], uniform.

    The log, less `margin_s` at either end, is cut into equal slots of at least `every_s`
    (at least one slot); each slot holds one occlusion at a uniform position within it.
    The intervals are drawn after the sensor's own samples, so they leave its draws alone.
    """

    sensor: MocapPoses | MocapMarkers
    targets: tuple[str, ...]
    duration_s: tuple[float, float] = (0.2, 1.0)
    every_s: float = 1.25
    margin_s: float = 0.25

    def settings(self) -> dict[str, Any]:
        occlusion = {
            "targets": list(self.targets),
            "duration_s": list(self.duration_s),
            "every_s": self.every_s,
            "margin_s": self.margin_s,
        }
        return self.sensor.settings() | {"occlusion": occlusion}

    def intervals(self, log_s: float, rng: np.random.Generator) -> np.ndarray:
        """(n, 2) occlusion intervals [start, end) in seconds from the start of the log."""
        span = log_s - 2.0 * self.margin_s
        if span < self.duration_s[0]:
            raise SimulationError(
                f"{self.name}: a {log_s:g} s log is too short for occlusions of "
                f"{self.duration_s[0]:g} s or more ({self.margin_s:g} s margins)"
            )
        count = max(1, int(span // self.every_s))
        slot = span / count
        length = np.minimum(rng.uniform(*self.duration_s, count), slot)
        start = (
            self.margin_s + slot * np.arange(count) + rng.uniform(0.0, 1.0, count) * (slot - length)
        )
        return np.stack([start, start + length], axis=1)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        out = self.sensor.sample(traj, rng)
        intervals = self.intervals(traj.duration_ns / NS, rng)
        t_s = out.truth["t_ns"] / NS
        hidden = np.zeros(len(t_s), dtype=bool)  # frames inside an occlusion
        for start, end in intervals:
            hidden |= (t_s >= start) & (t_s < end)
        frame = {traj.t0_ns + int(s): j for j, s in enumerate(out.truth["stamp_ns"])}
        messages = [m for m in map(self._occlude(frame, hidden), out.messages) if m is not None]
        truth = dict(out.truth)
        columns = truth["labels"] if isinstance(self.sensor, MocapPoses) else self.sensor.markers
        visible = truth["visible"].copy()
        dropouts = dict(truth["dropouts"])
        for target in self.targets:
            c = list(columns).index(target)
            visible[:, c] &= ~hidden
            both = np.concatenate([dropouts[target], intervals])
            dropouts[target] = both[np.argsort(both[:, 0], kind="stable")]
        truth.update(
            visible=visible,
            outlier=truth["outlier"] & visible,
            dropouts=dropouts,
            occlusions=intervals,
        )
        return SensorOutput(messages, truth)

    def _occlude(self, frame: Mapping[int, int], hidden: np.ndarray):
        """Message → the message with the targets removed from hidden frames (None: empty)."""
        if isinstance(self.sensor, MocapPoses):
            topics = {self.sensor.topic(label) for label in self.targets}
        targets = set(self.targets)

        def occlude(m: Message) -> Message | None:
            stamp = m.fields["header"]["stamp"]
            if not hidden[frame[stamp["sec"] * NS + stamp["nanosec"]]]:
                return m
            if isinstance(self.sensor, MocapPoses):
                return None if m.topic in topics else m
            shown = [k for k in m.fields["markers"] if k["marker_name"] not in targets]
            return m._replace(fields=m.fields | {"markers": shown}) if shown else None

        return occlude


def with_condition(scenario: Scenario, condition: str) -> Scenario:
    """`scenario` under `condition` (one of `CONDITIONS`); `SimulationError` otherwise."""
    if condition not in CONDITIONS:
        raise SimulationError(
            f"unknown condition {condition!r}; valid conditions: {', '.join(CONDITIONS)}"
        )
    sensors = tuple(_without_dropouts_or_outliers(s) for s in scenario.sensors)
    mismatch = scenario.mismatch
    if condition == "occlusion":
        sensors = _occlude_mocap(sensors, scenario.name)
    elif condition == "outliers":
        sensors = tuple(_with_outliers(s) for s in sensors)
    elif condition == "mismatch":
        mismatch = MISMATCH
    elif condition == "no_commands":
        sensors = tuple(s for s in sensors if not isinstance(s, Commands))
    elif condition == "no_mocap":
        if not any(isinstance(s, Imu) for s in sensors):
            raise SimulationError(
                f"scenario {scenario.name}: the no_mocap condition needs an IMU (a floating "
                "base estimated from proprioception); this scenario has none"
            )
        sensors = tuple(s for s in sensors if not isinstance(s, MocapPoses | MocapMarkers))
    elif condition == "disturbances":
        model = load_model(scenario.model)
        bodies = disturbances.push_bodies(model)
        faulty = _first(sensors, Imu, disturbances.ImuBiasStep)
        faulty = _first(faulty, Encoders, disturbances.EncoderJump)
        return replace(
            scenario,
            sensors=faulty,
            pushes=disturbances.random_body_pushes(
                bodies, touchable(model, bodies), feet(model, scenario.keyframe)
            ),
            condition=condition,
        )
    return replace(scenario, sensors=sensors, mismatch=mismatch, condition=condition)


def _first(sensors: tuple[Sensor, ...], kind: type, wrap: Any) -> tuple[Sensor, ...]:
    """The sensors with the first one of `kind` wrapped in `wrap` (unchanged if none)."""
    for i, sensor in enumerate(sensors):
        if isinstance(sensor, kind):
            return (*sensors[:i], wrap(sensor), *sensors[i + 1 :])
    return sensors


def _without_dropouts_or_outliers(sensor: Sensor) -> Sensor:
    if isinstance(sensor, MocapPoses | MocapMarkers):
        noise = replace(sensor.noise, dropout_rate_hz=0.0, outlier_probability=0.0)
        return replace(sensor, noise=noise)
    return sensor


def _with_outliers(sensor: Sensor) -> Sensor:
    if isinstance(sensor, MocapPoses | MocapMarkers):
        return replace(sensor, noise=replace(sensor.noise, outlier_probability=OUTLIER_PROBABILITY))
    return sensor


def _occlude_mocap(sensors: tuple[Sensor, ...], scenario: str) -> tuple[Sensor, ...]:
    """The sensors with every body (every marker) of the first mocap sensor occluded."""
    for i, sensor in enumerate(sensors):
        if isinstance(sensor, MocapPoses):
            occluded: Sensor = Occluded(sensor, tuple(sensor.bodies))
        elif isinstance(sensor, MocapMarkers):
            occluded = Occluded(sensor, tuple(sensor.markers))
        else:
            continue
        return (*sensors[:i], occluded, *sensors[i + 1 :])
    raise SimulationError(f"scenario {scenario}: no mocap sensor to occlude")
