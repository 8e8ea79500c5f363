"""Run a scenario and write the log a real robot could have produced, plus its ground truth.

    result = simulate("humanoid_push", "run.mcap", seed=0)

1. One `numpy.random.default_rng(seed)` feeds everything, in a fixed order: the model
   mismatch, the controller, the pushes, then each sensor in turn.
2. The mismatch-perturbed model (with its true softness written in by
   `physics.dynamics.make_dynamics`, or, for a scenario with `own_softness`, its own
   solref/solimp scaled by the mismatch) is stepped with `mj_step1` / control / `mj_step2`:
   MuJoCo's semi-implicit Euler step with elliptic cones at the model's timestep, its Newton
   solver run to convergence (tolerance 0), so that the inverse below reproduces the applied
   forces to ~1e-12.
3. Ground truth at every `ground_truth_decimation`-th step k: the state (q_k, v_k), and the
   native analytic inverse of (q_k, v_k, (v_{k+1} − v_k)/h) on the true model — its
   qfrc_inverse is the joints' effort, its impulses the contacts and contact wrenches
   (`writer.write_state` layout under `/ground_truth`). Its time is the true time; so is its
   log_time. Each IMU's true biases go to `/ground_truth/imu_bias/<site>` at its sample
   times. An IMU site without a gyro and an accelerometer in the model gets them (for
   the simulator to read; they change no dynamics).
4. Sensors sample the trajectory (`sensors.py`); all messages are written in receive-time
   order, like a recorder, with metadata records `physfuse.simulation`,
   `physfuse.mismatch`, `physfuse.sensors` and `physfuse.ground_truth` (and, under a
   condition, `physfuse.condition`: its name and the occlusion intervals it drew).
"""

from __future__ import annotations

import copy
import heapq
import json
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import IO, Any

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from estimator.io.mcap_writer import (
    EncodedMessage,
    Message,
    Ros2Writer,
    StateLayout,
    imu_bias_message,
    state_data,
    state_messages,
)
from estimator.simulate import disturbances
from estimator.simulate.conditions import CONDITIONS, with_condition
from estimator.simulate.controllers import Push, apply_pushes
from estimator.simulate.disturbances import push_events
from estimator.simulate.errors import SimulationError
from estimator.simulate.mismatch import Mismatch, MismatchRecord
from estimator.simulate.obstacle import Collision, Obstacle, add_obstacle
from estimator.simulate.patch import Patch, Patches
from estimator.simulate.scenarios import Controller, Scenario, get_scenario
from estimator.simulate.sensors import NS, Imu, Trajectory, site_ids
from physics.dynamics import Dynamics, make_dynamics
from physics.model import load_model, model_path
from physics.softness import Softness

T0_NS = 1_700_000_000 * NS  # the epoch of every simulated log: 2023-11-14T22:13:20Z
GROUND_TRUTH = "/ground_truth"

# What the ground-truth topics mean (the `physfuse.ground_truth` metadata record).
GROUND_TRUTH_DEFINITIONS = {
    "prefix": GROUND_TRUTH,
    "time": "header.stamp = log_time = the true time of the state (no clock offset, no latency)",
    "odometry": "nav_msgs/Odometry per free body: pose of the body frame in 'world'; twist = "
    "linear velocity of the body origin and angular velocity, in the body frame; covariances 0",
    "joint_states": "sensor_msgs/JointState of every hinge and slide joint: position = qpos, "
    "velocity = qvel at step k; effort = qfrc_inverse of the native analytic inverse of "
    "(q_k, v_k, (v_k+1 - v_k)/h) on the true model: actuator plus applied forces",
    "contact_wrench": "geometry_msgs/WrenchStamped per body that can collide: net force and "
    "torque of its contacts over step k (impulse / h), in the body frame, about the body origin",
    "contacts": "physfuse_msgs/ContactArray: every contact of step k from the same inverse "
    "(impulse in the contact frame, force = impulse / h, Algorithm 5 branch)",
    "imu_bias": "geometry_msgs/AccelStamped per IMU (topic .../imu_bias/<site>), at the "
    "IMU's true sample times: accel.linear = accelerometer bias [m/s^2], accel.angular = gyro "
    "bias [rad/s], in the frame of the IMU's model site (header.frame_id; the sensor axes "
    "turned by quat_site_sensor, as the estimator reads the IMU)",
}


@dataclass(frozen=True)
class SimulationResult:
    """What `simulate` did: the true motion and the truth behind every sensor message.

    trajectory: the true motion (`Trajectory`). true_softness: the simulated contact softness
    (None: the model's own, scaled by the mismatch: `mismatch.softness`).
    mismatch: nominal vs true model values. pushes: the external pushes.
    sensors: sensor name → its `SensorOutput.truth` (true values, biases, dropouts, ...).
    topics: topic → message type of everything written. message_count: messages written.
    """

    scenario: Scenario
    seed: int
    duration_s: float
    trajectory: Trajectory
    true_softness: Softness | None
    mismatch: MismatchRecord
    pushes: tuple[Push, ...]
    sensors: dict[str, dict[str, Any]]
    topics: dict[str, str]
    message_count: int


def simulate(
    scenario: Scenario | str,
    out: str | Path | IO[bytes],
    *,
    seed: int = 0,
    duration_s: float | None = None,
    mismatch: bool = True,
    condition: str | None = None,
    progress: bool = False,
    compression: str = "zstd",
) -> SimulationResult:
    """Simulate `scenario` and write its MCAP log to `out` (a path or a binary file).

    seed: the only source of randomness; the same seed writes the same file.
    duration_s: simulated time [s] (default: the scenario's). mismatch: False simulates the
    nominal model. condition: simulate the scenario under one of `conditions.CONDITIONS`
    (None: as the scenario defines it). progress: show tqdm progress bars (on stderr).
    """
    scenario = get_scenario(scenario) if isinstance(scenario, str) else scenario
    if condition is not None:
        if condition == "mismatch" and not mismatch:
            raise SimulationError("condition 'mismatch' contradicts mismatch=False (--no-mismatch)")
        scenario = with_condition(scenario, condition)
    duration = scenario.duration_s if duration_s is None else float(duration_s)
    if not (math.isfinite(duration) and duration > 0):
        raise SimulationError(f"duration {duration_s!r} s: expected a positive number of seconds")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SimulationError(f"seed {seed!r}: expected a non-negative integer")
    if scenario.ground_truth_decimation < 1:
        raise SimulationError(
            f"ground truth every {scenario.ground_truth_decimation} steps: expected >= 1"
        )
    if not mismatch:
        scenario = replace(scenario, mismatch=Mismatch.none())
    rng = np.random.default_rng(seed)

    nominal = _simulation_model(scenario)
    true_model, true_softness, record = scenario.mismatch.apply(
        nominal, rng, own_softness=scenario.own_softness
    )
    dyn = make_dynamics(true_model, "native", softness=true_softness)
    # Newton to machine precision: the forward step and the analytic inverse then agree to
    # ~1e-12 in generalized force (at MuJoCo's default tolerance 1e-8 they can differ by 1e-4)
    dyn.model.opt.tolerance = 0.0
    start = copy.deepcopy(rng)  # a rerun draws the controller and pushes again from here
    controller = scenario.controller(load_model(scenario.model), rng, duration)
    pushes = scenario.pushes(rng, duration)

    trajectory, measured = _run(scenario, dyn.model, controller, pushes, duration, progress)
    while scenario.condition == "disturbances" and (
        (fall := disturbances.fall_time(trajectory)) is not None and pushes
    ):  # a push the robot cannot withstand is left out and the run repeated
        pushes = disturbances.without_culprit(pushes, fall)
        rng = copy.deepcopy(start)
        controller = scenario.controller(load_model(scenario.model), rng, duration)
        scenario.pushes(rng, duration)
        trajectory, measured = _run(scenario, dyn.model, controller, pushes, duration, progress)
    sensed: list[EncodedMessage] = []  # encoded: an hour of a robot's messages fits
    truths: dict[str, dict[str, Any]] = {}
    for sensor in scenario.sensors:
        output = sensor.sample(trajectory, rng)
        sensed.extend(m.encoded() for m in output.messages)
        truths[sensor.name] = output.truth
        if isinstance(imu := _wrapped(sensor), Imu):
            bias = _imu_bias_messages(imu, output.truth, trajectory.t0_ns)
            sensed.extend(m.encoded() for m in bias)
    sensed.sort(key=lambda m: m.log_time_ns)  # stable: a tie keeps the order made
    metadata = _metadata(scenario, seed, duration, trajectory, record, true_softness, pushes)
    if scenario.condition is not None:
        metadata["physfuse.condition"] = _condition_metadata(
            scenario.condition, truths, pushes, measured
        )
    try:
        writer = Ros2Writer(out, compression=compression)
    except OSError as err:
        raise SimulationError(f"cannot write {out}: {err.strerror or err}") from err
    topics: dict[str, str] = {}
    with writer:
        for name, data in metadata.items():
            writer.add_metadata(name, data)
        # the ground truth, made step by step in time order, merged with the sensors' messages
        # (a tie: the ground truth first); none of it is held
        truth = _ground_truth(scenario, dyn, trajectory, progress)
        for m in heapq.merge(truth, sensed, key=lambda m: m.log_time_ns):
            topics[m.topic] = m.msg_type
            writer.write_encoded(m.topic, m.msg_type, m.data, m.log_time_ns, qos=m.qos)
    return SimulationResult(
        scenario=scenario,
        seed=seed,
        duration_s=duration,
        trajectory=trajectory,
        true_softness=true_softness,
        mismatch=record,
        pushes=pushes,
        sensors=truths,
        topics=dict(sorted(topics.items())),
        message_count=writer.message_count,
    )


def _run(
    scenario: Scenario,
    m: mujoco.MjModel,
    controller: Controller,
    pushes: tuple[Push, ...],
    duration_s: float,
    progress: bool,
) -> tuple[Trajectory, list[dict[str, Any]]]:
    """Step the true model for `duration_s`; its trajectory and the truth of the collisions
    and slips (the pushes that are `Collision`s, as the obstacle delivered them:
    `obstacle.Obstacle.events`; the `Patch`es a foot slid on: `patch.Patches.events`)."""
    h = float(m.opt.timestep)
    steps = max(1, round(duration_s / h))
    d = mujoco.MjData(m)
    key = scenario.keyframe
    if isinstance(key, str):
        key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key)
    if key >= 0:
        mujoco.mj_resetDataKeyframe(m, d, key)
    qpos = np.zeros((steps + 1, m.nq))
    qvel = np.zeros((steps + 1, m.nv))
    site_xpos = np.zeros((steps + 1, m.nsite, 3))
    site_xmat = np.zeros((steps + 1, m.nsite, 9))
    sensordata_vel = np.zeros((steps + 1, m.nsensordata))
    sensordata_acc = np.zeros((steps, m.nsensordata))
    ctrl = np.zeros((steps, m.nu))
    qfrc_actuator = np.zeros((steps, m.nv))
    body_xpos = np.zeros((steps + 1, m.nbody, 3))
    body_xquat = np.zeros((steps + 1, m.nbody, 4))
    collisions = [p for p in pushes if isinstance(p, Collision)]
    patches = Patches(m, [p for p in pushes if isinstance(p, Patch)])
    forces = [p for p in pushes if not isinstance(p, Collision | Patch)]
    obstacle = Obstacle(m, collisions, steps) if collisions else None
    bar = tqdm(total=steps, desc=f"simulate {scenario.name}", unit="step", disable=not progress)
    with bar:
        for k in range(steps + 1):
            patches.apply(k * h)  # the contacts made in this step take its friction
            mujoco.mj_step1(m, d)  # positions, velocities and their sensors at state k
            if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                raise SimulationError(
                    f"scenario {scenario.name}: the simulation diverged at t = {k * h:.3f} s"
                )
            qpos[k], qvel[k] = d.qpos, d.qvel
            site_xpos[k], site_xmat[k] = d.site_xpos, d.site_xmat
            body_xpos[k], body_xquat[k] = d.xpos, d.xquat
            sensordata_vel[k] = d.sensordata
            if k == steps:
                break
            d.ctrl[:] = controller(k * h, d)
            apply_pushes(m, d, forces, k * h)
            if obstacle:
                obstacle.move(d, k * h)  # where it is from the next step on
            mujoco.mj_step2(m, d)  # forces, constraint solve, acceleration sensors, integrate
            if obstacle:
                obstacle.measure(d, k)
            patches.measure(d, k)
            ctrl[k], qfrc_actuator[k] = d.ctrl, d.qfrc_actuator
            sensordata_acc[k] = d.sensordata
            bar.update()
    patches.restore()
    rot = Rotation.from_matrix(site_xmat.reshape(-1, 3, 3))
    site_xquat = rot.as_quat(scalar_first=True).reshape(steps + 1, m.nsite, 4)
    trajectory = Trajectory(
        model=m,
        t0_ns=T0_NS,
        h=h,
        qpos=qpos,
        qvel=qvel,
        site_xpos=site_xpos,
        site_xquat=site_xquat,
        sensordata_vel=sensordata_vel,
        sensordata_acc=sensordata_acc,
        ctrl=ctrl,
        qfrc_actuator=qfrc_actuator,
        body_xpos=body_xpos,
        body_xquat=body_xquat,
    )
    names = [m.body(b).name for b in range(m.nbody)]
    measured = (obstacle.events(h, names) if obstacle else []) + patches.events(h, names)
    return trajectory, measured


def _simulation_model(scenario: Scenario) -> mujoco.MjModel:
    """The scenario's model, with a gyro and an accelerometer added at each IMU site that
    lacks them (the IMU reads them; sensors change no dynamics) and, under `disturbances`,
    the obstacle its collisions bring against the robot (`obstacle.py`; parked, it changes
    no dynamics either)."""
    model = load_model(scenario.model)
    imus = [s for s in map(_wrapped, scenario.sensors) if isinstance(s, Imu)]
    for imu in imus:
        site_ids(model, [imu.site], imu.name)  # SimulationError naming the model's sites
    kinds = (mujoco.mjtSensor.mjSENS_GYRO, mujoco.mjtSensor.mjSENS_ACCELEROMETER)
    missing = [
        (imu.site, kind)
        for imu in imus
        for kind in kinds
        if not _has_site_sensor(model, imu.site, kind)
    ]
    collides = scenario.condition == "disturbances"
    if not (missing or collides):
        return model
    spec = mujoco.MjSpec.from_file(str(model_path(scenario.model)))
    for site, kind in missing:
        sensor = spec.add_sensor()
        sensor.name = f"physfuse/{site}/{mujoco.mjtSensor(kind).name}"
        sensor.type = kind
        sensor.objtype = mujoco.mjtObj.mjOBJ_SITE
        sensor.objname = site
    if collides:
        add_obstacle(spec, model)
    try:
        return spec.compile()
    except ValueError as err:
        raise SimulationError(
            f"{scenario.model}: cannot add the IMU sensors or the obstacle: {err}"
        ) from err


def _wrapped(sensor: Any) -> Any:
    """The sensor a condition's wrapper (an occlusion, a fault) wraps; itself if none."""
    while hasattr(sensor, "sensor"):
        sensor = sensor.sensor
    return sensor


def _has_site_sensor(model: mujoco.MjModel, site: str, kind: int) -> bool:
    site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    return any(
        model.sensor_type[s] == kind
        and model.sensor_objtype[s] == mujoco.mjtObj.mjOBJ_SITE
        and model.sensor_objid[s] == site_id
        for s in range(model.nsensor)
    )


def _ground_truth(
    scenario: Scenario, dyn: Dynamics, traj: Trajectory, progress: bool
) -> Iterator[EncodedMessage]:
    """The `/ground_truth` messages, step by step: state, inverse-dynamics effort and
    contacts."""
    m = dyn.model
    layout = StateLayout.of(m)
    data = mujoco.MjData(m)
    steps = range(0, traj.steps, scenario.ground_truth_decimation)
    for k in tqdm(steps, desc="ground truth", unit="step", disable=not progress, leave=False):
        qacc = (traj.qvel[k + 1] - traj.qvel[k]) / traj.h
        inverse = dyn.inverse(traj.qpos[k], traj.qvel[k], qacc)
        state_data(m, traj.qpos[k], traj.qvel[k], data)
        t_ns = traj.t0_ns + int(traj.step_ns(k))
        state = state_messages(
            GROUND_TRUTH,
            t_ns,
            m,
            data,
            qfrc=inverse.qfrc_inverse,
            constraints=inverse.constraints,
            layout=layout,
        )
        yield from (each.encoded() for each in state)


def _imu_bias_messages(imu: Imu, truth: dict[str, Any], t0_ns: int) -> list[Message]:
    """`/ground_truth/imu_bias/<site>`: the true biases at each sample, in the site frame."""
    site_from_sensor = Rotation.from_quat(imu.noise.quat_site_sensor, scalar_first=True)
    bias = np.hstack(
        [site_from_sensor.apply(truth["accel_bias"]), site_from_sensor.apply(truth["gyro_bias"])]
    )
    return [
        imu_bias_message(GROUND_TRUTH, imu.name, t0_ns + int(t), imu.site, bias[j])
        for j, t in enumerate(truth["t_ns"])
    ]


def _metadata(
    scenario: Scenario,
    seed: int,
    duration_s: float,
    traj: Trajectory,
    record: MismatchRecord,
    softness: Softness | None,
    pushes: Iterable[Push],
) -> dict[str, dict[str, str]]:
    """The MCAP metadata records (name → string pairs; structured values as JSON)."""
    simulation = {
        "scenario": scenario.name,
        "description": scenario.description,
        "model": scenario.model,
        "seed": str(seed),
        "duration_s": repr(duration_s),
        "timestep_s": repr(traj.h),
        "steps": str(traj.steps),
        "start_time_ns": str(traj.t0_ns),
        "keyframe": str(scenario.keyframe),
        "ground_truth_decimation": str(scenario.ground_truth_decimation),
        "pushes": json.dumps([p.as_dict() for p in pushes]),
        "mismatch": json.dumps(asdict(scenario.mismatch)),
        "solver": "newton, tolerance 0 (converged), elliptic cones, Euler",
        **scenario.settings,
    }
    true_softness = (
        json.dumps({"eps": softness.eps, "kappa": softness.kappa})
        if softness is not None
        else "the model's own solref/solimp, scaled (softness: eps_scale, kappa_scale)"
    )
    mismatch = record.metadata() | {"true_softness": true_softness}
    sensors = {s.name: json.dumps(s.settings()) for s in scenario.sensors}
    return {
        "physfuse.simulation": simulation,
        "physfuse.mismatch": mismatch,
        "physfuse.sensors": sensors,
        "physfuse.ground_truth": dict(GROUND_TRUTH_DEFINITIONS),
    }


def _condition_metadata(
    condition: str,
    truths: dict[str, dict[str, Any]],
    pushes: tuple[Push, ...],
    measured: list[dict[str, Any]],
) -> dict[str, str]:
    """The `physfuse.condition` record: the condition, and the occlusions it drew (if any);
    under `disturbances`, its `events` (disturbances.py; collisions and slips as measured)."""
    record = {"name": condition, "description": CONDITIONS[condition]}
    if condition == "disturbances":
        events = push_events([p for p in pushes if not isinstance(p, Collision | Patch)])
        events += measured
        events += [e for truth in truths.values() for e in truth.get("events", [])]
        record["events"] = json.dumps(sorted(events, key=lambda e: e["start_s"]))
    occlusions = {
        name: truth["occlusions"].tolist()
        for name, truth in truths.items()
        if "occlusions" in truth
    }
    if occlusions:
        record["occlusions_s"] = json.dumps(occlusions)
    return record


# -- the scenario's config -----------------------------------------------------------------------
def scenario_config(scenario: Scenario | str, path: str | Path | None = None) -> str:
    """The config TOML (estimator/config.py schema) that maps the scenario's sensor topics
    onto its model, with the sensors' noise levels and the clock offsets to undo.

    path: where the config will be written; a model file is then named relative to its
    folder (as the config is read), else as the scenario names it."""
    scenario = get_scenario(scenario) if isinstance(scenario, str) else scenario
    model = load_model(scenario.model)
    model_value = scenario.model
    if path is not None and scenario.model.endswith(".xml"):
        folder = Path(path).resolve().parent
        model_value = os.path.relpath(Path(scenario.model).resolve(), folder)
    command = scenario.command or scenario.name
    if scenario.condition is not None:
        command += f" --condition {scenario.condition}"
    lines = [
        f"# Generated by `physfuse simulate {command} --config-out ...`: the sensor",
        "# topics of the simulated log mapped onto the model. time_offset_ns undoes each",
        "# sensor's clock offset (commands: the transport latency).",
        f"model = {_toml(Path(model_value).as_posix())}",
        f"description = {_toml(f'simulated: {scenario.description}')}",
    ]
    for name, table in scenario.config_streams(model).items():
        lines += ["", f"[streams.{name}]"]
        lines += [f"{key} = {_toml(value)}" for key, value in table.items()]
    return "\n".join(lines) + "\n"


def _toml(value: Any) -> str:
    """A TOML value: strings, numbers, booleans, lists and (inline) tables."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"TOML has no {value}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        items = ", ".join(f"{_toml_key(k)} = {_toml(v)}" for k, v in value.items())
        return "{ " + items + " }" if items else "{}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def _toml_key(key: str) -> str:
    bare = key and all(c.isalnum() or c in "_-" for c in key)
    return key if bare else json.dumps(key)
