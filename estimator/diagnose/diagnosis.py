"""One log's diagnosis: its estimate's physics residual through `unmodeled` and `detect`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import mujoco

from estimator.config import Config
from estimator.diagnose.contact_model import contact_force_errors, contact_model_errors
from estimator.diagnose.contact_point import contact_points
from estimator.diagnose.detect import Detection, DetectorSettings, Event, detect
from estimator.diagnose.model_errors import mass_errors
from estimator.diagnose.sensor_faults import ONE_FAULT_S, sensor_faults
from estimator.diagnose.slip import slips
from estimator.diagnose.unmodeled import UnmodeledForces, unmodeled_forces
from estimator.estimate import Estimate
from estimator.io.logs.measurements import Measurement
from estimator.problem import build_problem, model_with_sensors
from estimator.settings import Settings
from physics.model import weight


@dataclass(frozen=True)
class Diagnosis:
    """forces, detection: the unmodeled-contact stages; events: every event in time order —
    the unmodeled contacts (on the body and point that best explain them, `contact_point`),
    those a modeled contact explains as its "model error" (its normal force off, or its
    whole force where the event acts at it: `contact_model`), the slips (`slip`), the sensor
    faults, a body's mass off (`model_errors`) —, the contacts a sensor fault or a slip
    explains marked `explained_by` it."""

    forces: UnmodeledForces
    detection: Detection
    events: list[Event]


def diagnose(
    config: Config,
    measurements: Mapping[str, Measurement],
    est: Estimate,
    settings: Settings,
    detector: DetectorSettings | None = None,
) -> Diagnosis:
    """Events in an estimate of the log `measurements` (made with `settings`): the physics
    residual's σ and the contact-force prior σ_f (`contact_force_std` × the robot's weight)
    are the estimator's."""
    compiled = model_with_sensors(config)
    problem = build_problem(config, measurements, settings, est.t_ns, compiled)
    model = problem.model
    sigma_f = settings.contact_force_std * weight(model)
    forces = unmodeled_forces(model, est, problem.known_sigma, sigma_f)
    detection = detect(forces, detector)
    # the simpler explanation first: a modeled contact's normal force; the rest located
    errors = contact_model_errors(model, est, problem.known_sigma, sigma_f, detection)
    with_errors = replace(detection, events=errors)
    located = contact_points(model, est, problem.known_sigma, sigma_f, with_errors)
    contacts = contact_force_errors(model, est, located)
    slid = slips(model, est, weight(model), detector)
    faults = sensor_faults(est, detector)
    events = explained(on_slips(model, contacts, slid) + slid, faults)
    masses = mass_errors(model, est, forces, events, detector)
    return Diagnosis(forces, detection, sorted(masses + events, key=lambda e: e.start_ns))


def on_slips(model: mujoco.MjModel, contacts: list[Event], slid: list[Event]) -> list[Event]:
    """`contacts` with each unmodeled contact or contact model error on a slipping body, or on
    the body next to it across a joint (its parent or child: the ankle between a foot and its
    shin hardly tells them apart), and overlapping its slip, explained by the slip: the
    model's friction, which the surface did not give, is what the physics residual shows
    there (humanoid, held-out seed 11: 4900 N on the shin above a slipping foot)."""
    out = []
    for event in contacts:
        body = event.target.removeprefix("contact ").split("–")[0]
        for s in slid:
            overlaps = event.start_ns <= s.end_ns and event.end_ns >= s.start_ns
            if overlaps and not event.explained_by and _adjacent(model, body, s.target):
                event = replace(event, explained_by=f"slip {s.target}")
                break
        out.append(event)
    return out


def _adjacent(model: mujoco.MjModel, a: str, b: str) -> bool:
    """Whether bodies `a` and `b` are one body or parent and child."""
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, a)
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b)
    if i < 0 or j < 0:
        return a == b
    return i == j or model.body_parentid[i] == j or model.body_parentid[j] == i


def explained(contacts: list[Event], faults: list[Event]) -> list[Event]:
    """All events in time order; a contact event (an unmodeled contact, a model error, a
    slip) that starts within `ONE_FAULT_S` of a sensor fault's start explained by it: the
    estimate took the faulty reading in, and its physics does not add up there — before the
    fault's start too, since a smoother spreads the reading both ways and the change point is
    known to a few tenths of a second
    (quadruped_trot, an accelerometer's step: the base's unmodeled force 0.12 and 0.27 s
    before it)."""
    out = list(faults)
    causes = [f for f in faults if not f.explained_by]
    for event in contacts:
        for f in causes:
            if abs(event.start_ns - f.start_ns) <= ONE_FAULT_S * 1e9:
                event = replace(event, explained_by=f"{f.target} {f.component}")
                break
        out.append(event)
    return sorted(out, key=lambda e: e.start_ns)
