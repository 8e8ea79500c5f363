"""The simulation scenarios: a model, a controller, disturbances and the robot's sensors.

    name             model         default  what happens
    humanoid_push    humanoid      6 s      stands (PD + static feed-forward) and is pushed on
                                            the torso every 1.5–2.5 s (25–40 N for 0.1 s): it
                                            rocks on its feet, heels and toes lift and land
    humanoid_fall    humanoid      3 s      stands, is pushed, and its controller switches off
                                            at 0.8 s: it collapses onto the floor
    quadruped_trot   quadruped     6 s      trots forward at ~0.25 m/s (phase-based gait + PD)
    arm_box          arm_box       6 s      pushes a free box ~4.5 cm along the floor, grasps
                                            it, lifts it 15 cm, holds, puts it down, lets go
    single_joint     single_joint  3 s      paper Fig. 1: random torques N(0, 5²) every 20 ms
                                            against dry joint friction and a floor contact

Sensors (rates are defaults; see `sensors.py` for every imperfection):

    humanoid_*      mocap poses of torso, pelvis and feet (120 Hz), IMU in the torso (500 Hz),
                    encoders (100 Hz), commands (100 Hz)
    quadruped_trot  mocap pose of the base (200 Hz), IMU mounted turned 90° about z (400 Hz),
                    encoders (200 Hz), commands (200 Hz)
    arm_box         mocap markers on the box (240 Hz), encoders (250 Hz), wrist force/torque
                    sensor (500 Hz), commands (500 Hz)
    single_joint    mocap pose of the arm's tip (100 Hz), encoder (500 Hz), commands (500 Hz)

Every scenario perturbs its model (`Mismatch()` defaults) unless asked not to.
`conditions.with_condition` turns a scenario into a variant (nominal, occlusion, outliers,
mismatch, no_commands).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from estimator.simulate.controllers import (
    PickAndPlace,
    Push,
    RandomTorque,
    StandingBalance,
    TrotGait,
    random_pushes,
)
from estimator.simulate.errors import SimulationError
from estimator.simulate.mismatch import Mismatch
from estimator.simulate.sensors import (
    Clock,
    Commands,
    EncoderNoise,
    Encoders,
    ForceTorque,
    Imu,
    ImuNoise,
    MocapMarkers,
    MocapNoise,
    MocapPoses,
    Sensor,
)

# (t [s], data) -> ctrl (nu,)
Controller = Callable[[float, mujoco.MjData], np.ndarray]
# (nominal model, rng, duration [s]) -> controller
ControllerFactory = Callable[[mujoco.MjModel, np.random.Generator, float], Controller]
# (rng, duration [s]) -> pushes
PushFactory = Callable[[np.random.Generator, float], tuple[Push, ...]]


def no_pushes(rng: np.random.Generator, duration_s: float) -> tuple[Push, ...]:
    return ()


@dataclass(frozen=True)
class Scenario:
    """Everything that defines a simulated recording except the seed.

    name: the CLI name. model: bundled model name or MJCF path. duration_s: default length [s].
    controller: builds the controller from the nominal model (it never sees the mismatch).
    pushes: draws the external pushes. sensors: in the order they draw random numbers.
    mismatch: how the simulated robot differs from the model. keyframe: the initial state
    (name, or index). ground_truth_decimation: write ground truth every this many steps
    (1: every step). condition: the `conditions.CONDITIONS` name this variant was made under
    (None: as defined). own_softness: the mismatch scales the model's own solref/solimp
    (False: the paper's one softness, `Softness()`, perturbed and written everywhere).
    command: the `physfuse simulate` arguments that make it ("": the name). settings: more
    `physfuse.simulation` metadata.
    """

    name: str
    model: str
    description: str
    duration_s: float
    controller: ControllerFactory
    sensors: tuple[Sensor, ...]
    pushes: PushFactory = no_pushes
    mismatch: Mismatch = field(default_factory=Mismatch)
    keyframe: str | int = "home"
    ground_truth_decimation: int = 1
    condition: str | None = None
    own_softness: bool = False
    command: str = ""
    settings: Mapping[str, str] = field(default_factory=dict)

    def topics(self) -> dict[str, str]:
        """Sensor topic → message type."""
        out: dict[str, str] = {}
        for sensor in self.sensors:
            out.update(sensor.topics())
        return out

    def config_streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        """The config's [streams.*] tables mapping the sensor topics onto the model."""
        out: dict[str, dict[str, Any]] = {}
        for sensor in self.sensors:
            out.update(sensor.streams(model))
        return out


# -- humanoid --------------------------------------------------------------------------------------
_HUMANOID_MOCAP = {
    "torso": "torso_marker",
    "pelvis": "pelvis_marker",
    "left_foot": "left_foot_marker",
    "right_foot": "right_foot_marker",
}


def _humanoid_sensors(imu: ImuNoise) -> tuple[Sensor, ...]:
    return (
        MocapPoses(_HUMANOID_MOCAP, MocapNoise(rate_hz=120.0)),
        Imu("/imu", "imu", imu),
        Encoders("/joint_states"),
        Commands("/joint_commands"),
    )


def _balance(off_s: float | None) -> ControllerFactory:
    def build(model: mujoco.MjModel, rng: np.random.Generator, duration_s: float) -> Controller:
        return StandingBalance(model, off_s=off_s)

    return build


def _humanoid_pushes(rng: np.random.Generator, duration_s: float) -> tuple[Push, ...]:
    return random_pushes(rng, "torso", duration_s)


def _fall_push(rng: np.random.Generator, duration_s: float) -> tuple[Push, ...]:
    angle = rng.uniform(0.0, 2.0 * np.pi)
    force = (35.0 * float(np.cos(angle)), 35.0 * float(np.sin(angle)), 0.0)
    return (Push("torso", 0.5, 0.1, force),)


def humanoid_push() -> Scenario:
    """The 27-dof humanoid balancing (PD + feed-forward) under random pushes on the torso."""
    return Scenario(
        name="humanoid_push",
        model="humanoid",
        description="27-dof humanoid standing under random pushes on the torso",
        duration_s=6.0,
        controller=_balance(None),
        sensors=_humanoid_sensors(ImuNoise(rate_hz=500.0)),
        pushes=_humanoid_pushes,
    )


def humanoid_fall() -> Scenario:
    """The humanoid pushed at 0.5 s; its controller switches off at 0.8 s and it falls."""
    return Scenario(
        name="humanoid_fall",
        model="humanoid",
        description="27-dof humanoid pushed, then its controller switches off: it falls",
        duration_s=3.0,
        controller=_balance(0.8),
        # an 8 g accelerometer range: the impacts saturate it
        sensors=_humanoid_sensors(ImuNoise(rate_hz=500.0, accel_range=8 * 9.80665)),
        pushes=_fall_push,
    )


# -- quadruped -------------------------------------------------------------------------------------
def _trot(model: mujoco.MjModel, rng: np.random.Generator, duration_s: float) -> Controller:
    return TrotGait(model)


def quadruped_trot() -> Scenario:
    """The 18-dof quadruped trotting forward."""
    c, s = float(np.cos(np.pi / 4)), float(np.sin(np.pi / 4))
    return Scenario(
        name="quadruped_trot",
        model="quadruped",
        description="18-dof quadruped trotting forward at about 0.25 m/s",
        duration_s=6.0,
        controller=_trot,
        sensors=(
            MocapPoses({"base": "base_marker"}, MocapNoise(rate_hz=200.0)),
            Imu("/imu", "imu", ImuNoise(rate_hz=400.0, quat_site_sensor=(c, 0.0, 0.0, s))),
            Encoders("/joint_states"),
            Commands("/joint_commands"),
        ),
    )


# -- arm and box -----------------------------------------------------------------------------------
def _pick_and_place(
    model: mujoco.MjModel, rng: np.random.Generator, duration_s: float
) -> Controller:
    return PickAndPlace(model)


def arm_box() -> Scenario:
    """The fixed-base arm pushing, grasping, lifting and placing a free box with markers."""
    return Scenario(
        name="arm_box",
        model="arm_box",
        description="fixed-base arm pushing, lifting and placing a free box with mocap markers",
        duration_s=6.0,
        controller=_pick_and_place,
        sensors=(
            MocapMarkers(
                "/mocap/markers",
                tuple(f"box_marker{i}" for i in range(6)),
                # markers on a small box are occluded by the gripper more often
                MocapNoise(rate_hz=240.0, position_std_m=3e-4, dropout_rate_hz=0.3),
            ),
            Encoders("/joint_states", EncoderNoise(rate_hz=250.0)),
            ForceTorque("/wrist_ft", "wrist_ft"),
            Commands("/joint_commands", Clock(latency_ns=100_000, latency_jitter_ns=20_000)),
        ),
    )


# -- single joint ----------------------------------------------------------------------------------
def _random_torque(
    model: mujoco.MjModel, rng: np.random.Generator, duration_s: float
) -> Controller:
    return RandomTorque(model, rng, std=5.0, period_s=0.02)


def single_joint() -> Scenario:
    """The paper's Fig. 1 mechanism under random torques: dry friction and a floor contact."""
    return Scenario(
        name="single_joint",
        model="single_joint",
        description="single hinge with dry friction and a floor contact, random torques "
        "(paper Fig. 1)",
        duration_s=3.0,
        controller=_random_torque,
        sensors=(
            MocapPoses({"arm": "tip_site"}, MocapNoise(rate_hz=100.0)),
            Encoders("/joint_states", EncoderNoise(counts_per_turn=2**16)),
            Commands("/joint_commands"),
        ),
    )


SCENARIOS: Mapping[str, Callable[[], Scenario]] = {
    "humanoid_push": humanoid_push,
    "humanoid_fall": humanoid_fall,
    "quadruped_trot": quadruped_trot,
    "arm_box": arm_box,
    "single_joint": single_joint,
}


def get_scenario(name: str) -> Scenario:
    """The scenario called `name`; `SimulationError` listing the valid names otherwise."""
    factory = SCENARIOS.get(name)
    if factory is None:
        raise SimulationError(f"unknown scenario {name!r}; valid scenarios: {', '.join(SCENARIOS)}")
    return factory()
