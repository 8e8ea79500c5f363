"""Any MJCF model with a keyframe as a scenario: `physfuse simulate --model MODEL.xml`.

    scenario = model_scenario("physics/models/menagerie/h1.xml")
    simulate(scenario, "h1.mcap", seed=0)

The robot holds its keyframe through its own actuators under smooth random excitation
(`controllers.KeyframeHold`: motors get torques, position servos targets), optionally pushed
on a body (`controllers.random_pushes`), and is measured by the bundled scenarios' sensors
with their imperfections (sensors.py):

    mocap     /mocap/<label>/pose, 120 Hz: every free-joint body (at a site on it named
              <body>_marker, base_marker, pelvis_marker or torso_marker, else its body frame),
              or the bodies and sites named by `mocap`
    markers   /mocap/markers, 240 Hz: the sites named by `markers` (none by default)
    imu       /imu, 500 Hz: at site `imu` if the model has one, or at the site `imu` names
    encoders  /joint_states: every hinge and slide joint, every step (500 Hz if the step is
              shorter than 2 ms)
    commands  /joint_commands: every actuator's ctrl, every step

The mismatch scales the model's own contact softness (`Mismatch.apply(own_softness=True)`):
the model's per-geom solref/solimp and its impratio are what it simulates, perturbed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

from estimator.simulate.controllers import KeyframeHold, Push, actuator_kinds, random_pushes
from estimator.simulate.errors import SimulationError
from estimator.simulate.scenarios import Controller, Scenario
from estimator.simulate.sensors import (
    Commands,
    EncoderNoise,
    Encoders,
    Imu,
    MocapMarkers,
    MocapNoise,
    MocapPoses,
    Sensor,
)
from physics.dynamics import check_model
from physics.errors import PhysicsError
from physics.model import load_model

DURATION_S = 4.0
EXCITATION_RAD = 0.05
MARKER_SITES = ("{}_marker", "base_marker", "pelvis_marker", "torso_marker")


def model_scenario(
    model: str | Path,
    *,
    keyframe: str | None = None,
    mocap: Sequence[str] | None = None,
    markers: Sequence[str] = (),
    imu: str | None = None,
    pushes: str | None = None,
    excitation_rad: float = EXCITATION_RAD,
    duration_s: float = DURATION_S,
) -> Scenario:
    """The scenario of an MJCF file (see the module docstring); SimulationError naming the
    option (as on the command line) that does not fit the model.

    keyframe: its name (default: the model's first). mocap: bodies or sites tracked by mocap
    (None: the free-joint bodies). markers: marker sites. imu: the IMU site (None: `imu` if
    there is one). pushes: a body to push at random. excitation_rad: amplitude A of the
    joint targets' excitation [rad].
    """
    path = str(model)
    if not (Path(path).suffix == ".xml" and Path(path).is_file()):
        raise SimulationError(f"--model {path}: no such MJCF file (*.xml)")
    try:
        m = load_model(path)
        check_model(m, "native")
    except PhysicsError as err:
        raise SimulationError(f"--model {path}: {err}") from err
    try:
        actuator_kinds(m)
    except SimulationError as err:
        raise SimulationError(f"--model {path}: {err}") from err
    _check_names(m, path)
    key = _keyframe(m, path, keyframe)
    if not (math.isfinite(excitation_rad) and excitation_rad >= 0):
        raise SimulationError(f"--excitation {excitation_rad}: expected an amplitude >= 0 [rad]")
    if pushes is not None and _id(m, mujoco.mjtObj.mjOBJ_BODY, pushes) <= 0:
        raise SimulationError(f"--pushes {pushes}: {path} has no (moving) body {pushes!r}")
    sensors = _sensors(m, path, mocap, markers, imu)
    named = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, key)
    key_name = named or f"#{key}"

    def controller(nominal: mujoco.MjModel, rng: np.random.Generator, _: float) -> Controller:
        return KeyframeHold(nominal, key, rng, excitation_rad=excitation_rad)

    def push_factory(rng: np.random.Generator, duration: float) -> tuple[Push, ...]:
        return () if pushes is None else random_pushes(rng, pushes, duration)

    command = f"--model {path} --excitation {excitation_rad:g}"
    for flag, names in (
        ("--keyframe", named and [named]),
        ("--mocap", mocap),
        ("--markers", markers),
        ("--imu", imu and [imu]),
    ):
        if names:
            command += f" {flag} {' '.join(names)}"
    description = (
        f"{Path(path).name} holding keyframe {key_name} (PD + static feed-forward through its "
        f"actuators) under a {excitation_rad:g} rad random excitation"
    )
    if pushes is not None:
        command += f" --pushes {pushes}"
        description += f", pushed on {pushes}"
    return Scenario(
        name=Path(path).stem,
        model=path,
        description=description,
        duration_s=duration_s,
        controller=controller,
        sensors=sensors,
        pushes=push_factory,
        keyframe=named or key,
        own_softness=True,
        command=command,
        settings={
            "excitation_rad": repr(float(excitation_rad)),
            "controller": "KeyframeHold (estimator/simulate/controllers.py)",
        },
    )


def _check_names(m: mujoco.MjModel, path: str) -> None:
    """Actuators and hinge/slide joints need names: the logs and the config address them so."""
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for kind, obj, ids in (
        ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, range(m.nu)),
        ("joint", mujoco.mjtObj.mjOBJ_JOINT, [j for j in range(m.njnt) if m.jnt_type[j] in scalar]),
    ):
        for i in ids:
            if not mujoco.mj_id2name(m, obj, i):
                raise SimulationError(
                    f"--model {path}: {kind} #{i} has no name (the log and its config name "
                    f"every {kind})"
                )


def _keyframe(m: mujoco.MjModel, path: str, name: str | None) -> int:
    if m.nkey == 0:
        raise SimulationError(
            f"--model {path}: the model has no keyframe (the initial state and the pose to hold)"
        )
    if name is None:
        return 0
    key = _id(m, mujoco.mjtObj.mjOBJ_KEY, name)
    if key < 0:
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, k) or f"#{k}" for k in range(m.nkey)]
        raise SimulationError(
            f"--keyframe {name}: {path} has no such keyframe; its keyframes: {', '.join(names)}"
        )
    return key


def _sensors(
    m: mujoco.MjModel,
    path: str,
    mocap: Sequence[str] | None,
    markers: Sequence[str],
    imu: str | None,
) -> tuple[Sensor, ...]:
    """The model's sensors, in the order they draw random numbers."""
    sensors: list[Sensor] = []
    targets, bodies = _mocap_targets(m, path, mocap)
    if targets:
        sensors.append(MocapPoses(targets, MocapNoise(rate_hz=120.0), body_labels=bodies))
    for site in markers:
        if _id(m, mujoco.mjtObj.mjOBJ_SITE, site) < 0:
            raise SimulationError(f"--markers {site}: {path} has no site {site!r}")
    if markers:
        noise = MocapNoise(rate_hz=240.0, position_std_m=3e-4, dropout_rate_hz=0.3)
        sensors.append(MocapMarkers("/mocap/markers", tuple(markers), noise))
    if imu is not None and _id(m, mujoco.mjtObj.mjOBJ_SITE, imu) < 0:
        raise SimulationError(f"--imu {imu}: {path} has no site {imu!r}")
    if imu is None and _id(m, mujoco.mjtObj.mjOBJ_SITE, "imu") >= 0:
        imu = "imu"
    if imu is not None:
        sensors.append(Imu("/imu", imu))
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    if any(int(m.jnt_type[j]) in scalar for j in range(m.njnt)):
        # one JointState per step, up to 500 Hz (a 0.5 ms step would write 2 kHz)
        rate = None if m.opt.timestep >= 0.002 else 500.0
        sensors.append(Encoders("/joint_states", EncoderNoise(rate_hz=rate)))
    if m.nu:
        sensors.append(Commands("/joint_commands"))
    if not sensors:
        raise SimulationError(f"--model {path}: nothing to measure (no free body, joint or site)")
    return tuple(sensors)


def _mocap_targets(
    m: mujoco.MjModel, path: str, names: Sequence[str] | None
) -> tuple[dict[str, str], tuple[str, ...]]:
    """(label → site or body, the labels that name bodies) of the mocap poses."""
    targets: dict[str, str] = {}
    bodies: list[str] = []
    if names is None:  # every free-joint body, at its marker site if it has one
        for j in range(m.njnt):
            if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
                continue
            b = int(m.jnt_bodyid[j])
            body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
            if not body:
                raise SimulationError(f"--model {path}: free body #{b} has no name to track")
            site = _marker_site(m, b, body)
            targets[body] = site or body
            if site is None:
                bodies.append(body)
        return targets, tuple(bodies)
    for name in names:
        if _id(m, mujoco.mjtObj.mjOBJ_SITE, name) >= 0:
            targets[name] = name
        elif _id(m, mujoco.mjtObj.mjOBJ_BODY, name) > 0:
            targets[name] = name
            bodies.append(name)
        else:
            raise SimulationError(f"--mocap {name}: {path} has no (moving) body or site {name!r}")
    return targets, tuple(bodies)


def _marker_site(m: mujoco.MjModel, body: int, name: str) -> str | None:
    """The first of MARKER_SITES that is a site on `body`."""
    for pattern in MARKER_SITES:
        site = _id(m, mujoco.mjtObj.mjOBJ_SITE, pattern.format(name))
        if site >= 0 and m.site_bodyid[site] == body:
            return pattern.format(name)
    return None


def _id(m: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    return int(mujoco.mj_name2id(m, obj, name))
