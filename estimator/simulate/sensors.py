"""Simulated sensors: what a robot's drivers would publish, each with its imperfections.

Every sensor samples the true trajectory of the simulated robot (`Trajectory`, one state per
simulation step) at its own rate and phase, adds its imperfections, and returns ROS 2
messages timed as a recorder would see them:

    t            the true instant the sample describes (the simulation's clock)
    header.stamp t + clock offset + stamp jitter        (the sensor's clock; `Clock`)
    log_time     t + latency + latency jitter ≥ t       (when the recorder received it)

Between simulation steps, positions are interpolated linearly (orientations by slerp): the
semi-implicit Euler step q_{k+1} = q_k ⊕ h v_{k+1} moves q at the constant velocity v_{k+1}
through (t_k, t_{k+1}], so positions are exact and velocities are held at v_{k+1} there (a
gyro or encoder velocity then integrates to the motion); accelerations and forces are held
at the step's value over [t_k, t_{k+1}) (a_k = (v_{k+1} − v_k)/h, as the discrete-time
dynamics define them).

Imperfection models (each a frozen dataclass with documented defaults):

- `MocapNoise`: rate, white position/orientation noise, occlusion dropouts (a Poisson process
  of intervals, seconds long, per body or marker), outliers (jumps of centimetres), latency.
- `ImuNoise`: rate, white noise, bias = initial offset + random walk, saturation at the
  measurement range; specific force and angular rate come from the model's accelerometer and
  gyro sensors at the IMU site (MuJoCo: site frame, gravity included).
- `EncoderNoise`: position quantization (counts per turn), velocity and effort noise.
- `ForceTorqueNoise`: white noise and a constant bias on a force/torque sensor.
- `Clock`: per-stream clock offset, stamp jitter, latency and its jitter.

Sensors (`MocapPoses`, `MocapMarkers`, `Imu`, `Encoders`, `Commands`, `ForceTorque`) also
produce their config streams (estimator/config.py schema) and their settings for the log's
metadata. Randomness comes only from the generator passed to `sample`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import mujoco
import numpy as np

from estimator.io.logs import ros2_types
from estimator.io.mcap_writer import (
    RELIABLE_QOS,
    SENSOR_QOS,
    Message,
    header,
    pose,
    quaternion,
    vector3,
)
from estimator.rotations import quat_exp, quat_mul, quat_slerp, rotate_inverse
from estimator.simulate.errors import SimulationError

NS = 1_000_000_000
_IDENTITY_WXYZ = (1.0, 0.0, 0.0, 0.0)
_USE_NAME = 0  # mocap4r2_msgs/Marker.USE_NAME


# -- the true trajectory -------------------------------------------------------------------------
@dataclass(frozen=True)
class Trajectory:
    """The simulated robot's true motion, one row per step (N steps, N + 1 states).

    model: the simulated (true) model. t0_ns: epoch of step 0 [ns]. h: timestep [s].
    qpos (N+1, nq), qvel (N+1, nv): states at t0 + k h.
    site_xpos (N+1, nsite, 3) [m], site_xquat (N+1, nsite, 4) (w, x, y, z): world frame.
    sensordata_vel (N+1, nsensordata): the model's sensors at each state (position and velocity
        stages valid: gyro, framepos, jointpos, ...).
    sensordata_acc (N, nsensordata): after each step's constraint solve (acceleration stage
        valid too: accelerometer, force, torque, touch).
    ctrl (N, nu): controls applied during each step. qfrc_actuator (N, nv): their forces.
    body_xpos (N+1, nbody, 3) [m], body_xquat (N+1, nbody, 4) (w, x, y, z): body frames, world.
    """

    model: mujoco.MjModel
    t0_ns: int
    h: float
    qpos: np.ndarray
    qvel: np.ndarray
    site_xpos: np.ndarray
    site_xquat: np.ndarray
    sensordata_vel: np.ndarray
    sensordata_acc: np.ndarray
    ctrl: np.ndarray
    qfrc_actuator: np.ndarray
    body_xpos: np.ndarray
    body_xquat: np.ndarray

    @property
    def steps(self) -> int:
        return len(self.ctrl)

    @property
    def duration_ns(self) -> int:
        return round(self.steps * self.h * NS)

    def step_ns(self, k: np.ndarray | int) -> np.ndarray:
        """Time offset of step(s) k from t0 [ns], int64."""
        return np.round(np.asarray(k) * self.h * NS).astype(np.int64)

    def _locate(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step index k (n,) and fraction α (n,) in [0, 1] of times t_ns (offsets from t0)."""
        s = np.asarray(t_ns, dtype=np.float64) / NS / self.h
        k = np.clip(np.floor(s).astype(np.int64), 0, self.steps - 1)
        return k, np.clip(s - k, 0.0, 1.0)

    def interpolate(self, states: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Linear interpolation of a per-state array (N+1, ...) at times t_ns (n,) → (n, ...)."""
        k, a = self._locate(t_ns)
        a = a.reshape((-1,) + (1,) * (states.ndim - 1))
        return (1.0 - a) * states[k] + a * states[k + 1]

    def velocity(self, states: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """A per-state velocity-stage array (N+1, ...) at times t_ns (n,) → (n, ...): the
        value of state k + 1 through (t_k, t_{k+1}], the velocity q moves at in that step."""
        s = np.asarray(t_ns, dtype=np.float64) / NS / self.h
        return states[np.clip(np.ceil(s).astype(np.int64), 0, self.steps)]

    def slerp(self, quats: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Slerp of per-state unit quaternions (N+1, ..., 4) at times t_ns (n,) → (n, ..., 4)."""
        k, a = self._locate(t_ns)
        return quat_slerp(quats[k], quats[k + 1], a.reshape((-1,) + (1,) * (quats.ndim - 1)))

    def hold(self, steps: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """The value of the step containing each time, from a per-step array (N, ...)."""
        k, _ = self._locate(t_ns)
        return steps[k]


def random_unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) directions uniform on the sphere."""
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# -- timing --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Clock:
    """How one stream's samples are timed and delivered.

    offset_ns: the sensor clock minus true time: header.stamp = t + offset_ns (+ jitter).
        The scenario's config undoes it with `time_offset_ns = -offset_ns`.
    stamp_jitter_ns: standard deviation of per-sample stamp noise [ns] (clipped to ±3σ and to
        a quarter of the sample period, so stamps never go backwards).
    latency_ns: fixed delay from the sample to the recorder: log_time = t + latency (+ jitter).
    latency_jitter_ns: standard deviation of an extra, non-negative (half-normal) delay [ns].
    """

    offset_ns: int = 0
    stamp_jitter_ns: float = 0.0
    latency_ns: int = 1_000_000
    latency_jitter_ns: float = 0.0

    def stamps(self, t_ns: np.ndarray, period_ns: float, rng: np.random.Generator) -> np.ndarray:
        """Header stamps (n,) int64 of samples taken at true times t_ns (n,)."""
        bound = min(3.0 * self.stamp_jitter_ns, 0.25 * period_ns)
        jitter = np.clip(self.stamp_jitter_ns * rng.standard_normal(len(t_ns)), -bound, bound)
        return t_ns + self.offset_ns + np.round(jitter).astype(np.int64)

    def log_times(self, t_ns: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Receive times (n,) int64 of samples taken at true times t_ns (n,)."""
        extra = np.abs(self.latency_jitter_ns * rng.standard_normal(len(t_ns)))
        return t_ns + self.latency_ns + np.round(extra).astype(np.int64)


def sample_times(rate_hz: float, duration_ns: int, rng: np.random.Generator) -> np.ndarray:
    """True sample times (n,) int64 [ns from the start] of a free-running sensor.

    The first sample falls at a random phase within one period (sensors are not synchronized
    with the simulation); samples continue until the end of the trajectory.
    """
    period = NS / rate_hz
    phase = rng.uniform(0.0, period)
    n = int(np.floor((duration_ns - phase) / period)) + 1
    return np.round(phase + period * np.arange(max(n, 0))).astype(np.int64)


# -- imperfection models -------------------------------------------------------------------------
@dataclass(frozen=True)
class MocapNoise:
    """A motion-capture system (marker-based, like Vicon or OptiTrack).

    rate_hz: frame rate (typically 100–240 Hz).
    position_std_m, orientation_std_rad: white noise per frame and body (or marker).
    dropout_rate_hz: occlusions per second, per body or marker (Poisson); during one the body
        is not reported.
    dropout_s: (min, max) occlusion duration [s], uniform.
    outlier_probability: chance per frame and body that the fit jumps (a marker swap).
    outlier_m: (min, max) size of that jump [m], uniform, random direction; an outlier pose
        also turns by outlier_rad.
    outlier_rad: rotation of an outlier pose [rad] about a random axis.
    clock: timing (mocap frames are hardware-timed: little jitter, a few ms of latency).
    """

    rate_hz: float = 120.0
    position_std_m: float = 5e-4
    orientation_std_rad: float = 5e-3
    dropout_rate_hz: float = 0.2
    dropout_s: tuple[float, float] = (0.2, 2.0)
    outlier_probability: float = 0.005
    outlier_m: tuple[float, float] = (0.03, 0.15)
    outlier_rad: float = 0.5
    clock: Clock = Clock(
        offset_ns=-2_500_000,
        stamp_jitter_ns=20_000,
        latency_ns=4_000_000,
        latency_jitter_ns=500_000,
    )

    def dropouts(self, duration_s: float, rng: np.random.Generator) -> np.ndarray:
        """(n, 2) occlusion intervals [start, end) in seconds from the start."""
        count = int(rng.poisson(self.dropout_rate_hz * duration_s))
        start = rng.uniform(0.0, duration_s, count)
        length = rng.uniform(*self.dropout_s, count)
        order = np.argsort(start, kind="stable")
        return np.stack([start[order], (start + length)[order]], axis=1)


@dataclass(frozen=True)
class ImuNoise:
    """A MEMS IMU (defaults near a Bosch BMI088 at 500 Hz).

    rate_hz: output rate (typically 200–1000 Hz).
    gyro_std [rad/s], accel_std [m/s²]: white noise per sample.
    gyro_bias_std [rad/s], accel_bias_std [m/s²]: the initial (turn-on) bias, per axis.
    gyro_bias_walk [rad/s/√s], accel_bias_walk [m/s²/√s]: bias random walk.
    gyro_range [rad/s], accel_range [m/s²]: saturation (±2000 °/s, ±16 g).
    orientation_std_rad: noise of the orientation estimate (the IMU's own filter); None: the
        IMU reports no orientation (orientation_covariance[0] = -1, REP 145).
    quat_site_sensor: (w, x, y, z) the sensor axes in the model site's frame (the mounting).
    clock: timing.
    """

    rate_hz: float = 500.0
    gyro_std: float = 4e-3
    accel_std: float = 3e-2
    gyro_bias_std: float = 5e-3
    accel_bias_std: float = 5e-2
    gyro_bias_walk: float = 1e-4
    accel_bias_walk: float = 1e-3
    gyro_range: float = math.radians(2000.0)
    accel_range: float = 16 * 9.80665
    orientation_std_rad: float | None = 1e-2
    quat_site_sensor: tuple[float, float, float, float] = _IDENTITY_WXYZ
    clock: Clock = Clock(
        offset_ns=1_200_000, stamp_jitter_ns=50_000, latency_ns=800_000, latency_jitter_ns=200_000
    )


@dataclass(frozen=True)
class EncoderNoise:
    """Joint encoders and drive feedback (sensor_msgs/JointState).

    rate_hz: output rate; None: once per simulation step, at the step.
    counts_per_turn: hinge position quantization (resolution 2π / counts) [rad].
    slide_resolution_m: slide joint position quantization [m].
    velocity_std: white noise of the reported velocity [rad/s or m/s].
    effort_std: white noise of the reported effort (actuator force on the joint) [N·m or N].
    clock: timing.
    """

    rate_hz: float | None = None
    counts_per_turn: int = 2**14
    slide_resolution_m: float = 1e-5
    velocity_std: float = 1e-2
    effort_std: float = 0.05
    clock: Clock = Clock(
        offset_ns=0, stamp_jitter_ns=10_000, latency_ns=300_000, latency_jitter_ns=100_000
    )

    @property
    def hinge_resolution_rad(self) -> float:
        return 2.0 * math.pi / self.counts_per_turn


@dataclass(frozen=True)
class ForceTorqueNoise:
    """A six-axis force/torque sensor (geometry_msgs/WrenchStamped).

    rate_hz: output rate. force_std [N], torque_std [N·m]: white noise. force_bias_std,
    torque_bias_std: a constant offset per axis, drawn once. clock: timing.
    """

    rate_hz: float = 500.0
    force_std: float = 0.3
    torque_std: float = 0.01
    force_bias_std: float = 0.5
    torque_bias_std: float = 0.02
    clock: Clock = Clock(
        offset_ns=400_000, stamp_jitter_ns=20_000, latency_ns=500_000, latency_jitter_ns=100_000
    )


# -- sensors -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SensorOutput:
    """What a sensor produced: its messages, and the truth behind them (for tests and metrics).

    truth: per-sensor arrays, e.g. "t_ns" (n,) true sample times [ns from the start], the
    noiseless values, biases, which samples were dropped or are outliers.
    """

    messages: list[Message]
    truth: dict[str, Any]


class Sensor(Protocol):
    """One simulated sensor: a stream (or several) of messages, its config and settings."""

    @property
    def name(self) -> str:
        """The sensor's name (its truth in `SimulationResult.sensors`)."""
        ...

    def topics(self) -> dict[str, str]:
        """topic → message type."""
        ...

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        """Config stream tables (estimator/config.py schema), stream name → table."""
        ...

    def settings(self) -> dict[str, Any]:
        """The sensor's settings, JSON-serializable (the log's metadata)."""
        ...

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        """The sensor's messages over the trajectory."""
        ...


def site_ids(model: mujoco.MjModel, sites: Sequence[str], what: str) -> np.ndarray:
    ids = []
    for site in sites:
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if i < 0:
            valid = [
                mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in range(model.nsite)
            ]
            raise SimulationError(
                f"{what}: the model has no site {site!r}; its sites: {', '.join(map(str, valid))}"
            )
        ids.append(i)
    return np.array(ids, dtype=np.int64)


def _body_ids(model: mujoco.MjModel, bodies: Sequence[str], what: str) -> np.ndarray:
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body) for body in bodies]
    for body, i in zip(bodies, ids, strict=True):
        if i < 0:
            raise SimulationError(f"{what}: the model has no body {body!r}")
    return np.array(ids, dtype=np.int64)


def _site_sensor(model: mujoco.MjModel, site: str, kind: int, what: str) -> slice:
    """sensordata slice of the model sensor of type `kind` mounted at `site`."""
    site_id = site_ids(model, [site], what)[0]
    for s in range(model.nsensor):
        if (
            model.sensor_type[s] == kind
            and model.sensor_objtype[s] == mujoco.mjtObj.mjOBJ_SITE
            and model.sensor_objid[s] == site_id
        ):
            adr = int(model.sensor_adr[s])
            return slice(adr, adr + int(model.sensor_dim[s]))
    name = mujoco.mjtSensor(kind).name.removeprefix("mjSENS_").lower()
    raise SimulationError(f"{what}: the model has no {name} sensor at site {site!r}")


def _diagonal(variance: float) -> list[float]:
    """A 3×3 diagonal covariance, row-major (ROS message layout)."""
    v = float(variance)
    return [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]


def _noise_table(**values: float) -> dict[str, float]:
    return {k: float(v) for k, v in values.items()}


def _settings(obj: Any) -> dict[str, Any]:
    out = asdict(obj)
    out["type"] = type(obj).__name__
    return out


def _occluded(times_s: np.ndarray, intervals: np.ndarray) -> np.ndarray:
    """(n,) whether each time falls in one of the [start, end) intervals (m, 2)."""
    hidden = np.zeros(len(times_s), dtype=bool)
    for start, end in intervals:
        hidden |= (times_s >= start) & (times_s < end)
    return hidden


class Wrapping:
    """A condition's wrapper of a sensor (an occlusion, a fault): the wrapped sensor's name,
    topics and config streams; the wrapper changes what it samples."""

    sensor: Sensor

    @property
    def name(self) -> str:
        return self.sensor.name

    def topics(self) -> dict[str, str]:
        return self.sensor.topics()

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        return self.sensor.streams(model)


@dataclass(frozen=True)
class MocapPoses:
    """Rigid-body poses from motion capture, one PoseStamped topic per body (vrpn_mocap style).

    bodies: rigid-body label → model site whose frame the mocap system tracks (for the labels
    in `body_labels`: model body, its frame). Topics are `topic_format.format(label)`. All
    bodies share the frame times, stamps and delivery of one mocap system; dropouts and
    outliers are per body.
    """

    bodies: Mapping[str, str]
    noise: MocapNoise = MocapNoise()
    topic_format: str = "/mocap/{}/pose"
    name: str = "mocap"
    body_labels: tuple[str, ...] = ()

    def topic(self, label: str) -> str:
        return self.topic_format.format(label)

    def topics(self) -> dict[str, str]:
        return {self.topic(label): ros2_types.POSE_STAMPED for label in self.bodies}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        n = self.noise
        return {
            f"{self.name}_{label}": {
                "type": "pose",
                "topic": self.topic(label),
                ("body" if label in self.body_labels else "site"): site,
                "time_offset_ns": -n.clock.offset_ns,
                "noise": _noise_table(
                    position_std_m=n.position_std_m, orientation_std_rad=n.orientation_std_rad
                ),
            }
            for label, site in self.bodies.items()
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        n = self.noise
        labels = list(self.bodies)
        frames = []  # per label: (N+1, 3) positions and (N+1, 4) orientations
        for label, target in self.bodies.items():
            if label in self.body_labels:
                b = _body_ids(traj.model, [target], self.name)[0]
                frames.append((traj.body_xpos[:, b], traj.body_xquat[:, b]))
            else:
                i = site_ids(traj.model, [target], self.name)[0]
                frames.append((traj.site_xpos[:, i], traj.site_xquat[:, i]))
        xpos = np.stack([p for p, _ in frames], axis=1)
        xquat = np.stack([q for _, q in frames], axis=1)
        t = sample_times(n.rate_hz, traj.duration_ns, rng)
        stamps = n.clock.stamps(t, NS / n.rate_hz, rng)
        log_times = n.clock.log_times(t, rng)
        true_pos = traj.interpolate(xpos, t)  # (n, B, 3)
        true_quat = traj.slerp(xquat, t)  # (n, B, 4)
        shape = (len(t), len(labels))
        pos = true_pos + n.position_std_m * rng.standard_normal((*shape, 3))
        quat = quat_mul(
            true_quat, quat_exp(n.orientation_std_rad * rng.standard_normal((*shape, 3)))
        )
        # outliers: a jump of outlier_m in a random direction, a turn of outlier_rad
        outlier = rng.random(shape) < n.outlier_probability
        jump = random_unit_vectors(rng, shape[0] * shape[1]).reshape(*shape, 3)
        jump *= rng.uniform(*n.outlier_m, shape)[..., None]
        turn = n.outlier_rad * random_unit_vectors(rng, shape[0] * shape[1]).reshape(*shape, 3)
        pos = np.where(outlier[..., None], pos + jump, pos)
        quat = np.where(outlier[..., None], quat_mul(quat, quat_exp(turn)), quat)
        # occlusions, per body
        duration_s = traj.duration_ns / NS
        dropouts = {label: n.dropouts(duration_s, rng) for label in labels}
        visible = np.stack([~_occluded(t / NS, dropouts[label]) for label in labels], axis=1)
        messages = []
        for b, label in enumerate(labels):
            topic = self.topic(label)
            for j in np.flatnonzero(visible[:, b]):
                fields = {
                    "header": header(traj.t0_ns + int(stamps[j]), "world"),
                    "pose": pose(pos[j, b], quat[j, b]),
                }
                messages.append(
                    Message(
                        topic,
                        ros2_types.POSE_STAMPED,
                        traj.t0_ns + int(log_times[j]),
                        fields,
                        SENSOR_QOS,
                    )
                )
        truth = {
            "t_ns": t,
            "stamp_ns": stamps,
            "labels": labels,
            "position": true_pos,
            "quat_wxyz": true_quat,
            "visible": visible,
            "outlier": outlier & visible,
            "dropouts": dropouts,
        }
        return SensorOutput(messages, truth)


@dataclass(frozen=True)
class MocapMarkers:
    """Individual mocap markers (mocap4r2_msgs/Markers), named by their model sites.

    markers: model sites, reported with id_type USE_NAME and marker_name = the site name.
    Occluded markers are left out of a frame; a frame with no visible marker is not sent.
    """

    topic: str
    markers: tuple[str, ...]
    noise: MocapNoise = MocapNoise()
    name: str = "markers"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.MARKERS}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        return {
            self.name: {
                "type": "markers",
                "topic": self.topic,
                "markers": {site: site for site in self.markers},
                "time_offset_ns": -self.noise.clock.offset_ns,
                "noise": _noise_table(position_std_m=self.noise.position_std_m),
            }
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        n = self.noise
        sites = site_ids(traj.model, self.markers, self.name)
        t = sample_times(n.rate_hz, traj.duration_ns, rng)
        stamps = n.clock.stamps(t, NS / n.rate_hz, rng)
        log_times = n.clock.log_times(t, rng)
        true_pos = traj.interpolate(traj.site_xpos[:, sites], t)  # (n, M, 3)
        shape = (len(t), len(sites))
        pos = true_pos + n.position_std_m * rng.standard_normal((*shape, 3))
        outlier = rng.random(shape) < n.outlier_probability
        jump = random_unit_vectors(rng, shape[0] * shape[1]).reshape(*shape, 3)
        jump *= rng.uniform(*n.outlier_m, shape)[..., None]
        pos = np.where(outlier[..., None], pos + jump, pos)
        duration_s = traj.duration_ns / NS
        dropouts = {site: n.dropouts(duration_s, rng) for site in self.markers}
        visible = np.stack([~_occluded(t / NS, dropouts[s]) for s in self.markers], axis=1)
        messages = []
        for j in range(len(t)):
            shown = np.flatnonzero(visible[j])
            if not len(shown):
                continue
            fields = {
                "header": header(traj.t0_ns + int(stamps[j]), "world"),
                "frame_number": j,
                "markers": [
                    {
                        "id_type": _USE_NAME,
                        "marker_index": int(i),
                        "marker_name": self.markers[i],
                        "translation": vector3(pos[j, i]),
                    }
                    for i in shown
                ],
            }
            messages.append(
                Message(
                    self.topic,
                    ros2_types.MARKERS,
                    traj.t0_ns + int(log_times[j]),
                    fields,
                    SENSOR_QOS,
                )
            )
        truth = {
            "t_ns": t,
            "stamp_ns": stamps,
            "position": true_pos,
            "visible": visible,
            "outlier": outlier & visible,
            "dropouts": dropouts,
        }
        return SensorOutput(messages, truth)


@dataclass(frozen=True)
class Imu:
    """An IMU at a model site (sensor_msgs/Imu): angular rate, specific force, orientation.

    The model must have a gyro and an accelerometer sensor at `site`; their values (site
    frame) are turned into the sensor frame by `noise.quat_site_sensor`.
    """

    topic: str
    site: str
    noise: ImuNoise = ImuNoise()
    frame_id: str = "imu_link"
    name: str = "imu"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.IMU}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        n = self.noise
        table: dict[str, Any] = {
            "type": "imu",
            "topic": self.topic,
            "site": self.site,
            "time_offset_ns": -n.clock.offset_ns,
        }
        if n.quat_site_sensor != _IDENTITY_WXYZ:
            table["quat_site_sensor"] = list(n.quat_site_sensor)
        # the range per axis: the estimator leaves out saturated samples
        table["accel_range"] = float(n.accel_range)
        table["gyro_range"] = float(n.gyro_range)
        noise = _noise_table(
            gyro_std=n.gyro_std,
            accel_std=n.accel_std,
            gyro_bias_walk=n.gyro_bias_walk,
            accel_bias_walk=n.accel_bias_walk,
        )
        if n.orientation_std_rad is not None:
            noise["orientation_std_rad"] = float(n.orientation_std_rad)
        table["noise"] = noise
        return {self.name: table}

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        n = self.noise
        m = traj.model
        gyro_adr = _site_sensor(m, self.site, mujoco.mjtSensor.mjSENS_GYRO, self.name)
        accel_adr = _site_sensor(m, self.site, mujoco.mjtSensor.mjSENS_ACCELEROMETER, self.name)
        site = site_ids(m, [self.site], self.name)[0]
        t = sample_times(n.rate_hz, traj.duration_ns, rng)
        stamps = n.clock.stamps(t, NS / n.rate_hz, rng)
        log_times = n.clock.log_times(t, rng)
        count = len(t)
        # true signals in the sensor frame
        gyro_true = rotate_inverse(
            n.quat_site_sensor, traj.velocity(traj.sensordata_vel[:, gyro_adr], t)
        )
        accel_true = rotate_inverse(
            n.quat_site_sensor, traj.hold(traj.sensordata_acc[:, accel_adr], t)
        )
        quat_true = quat_mul(
            traj.slerp(traj.site_xquat[:, site], t), np.asarray(n.quat_site_sensor)
        )
        # biases: turn-on offset + random walk
        dt = 1.0 / n.rate_hz
        gyro_bias = n.gyro_bias_std * rng.standard_normal(3) + np.cumsum(
            n.gyro_bias_walk * math.sqrt(dt) * rng.standard_normal((count, 3)), axis=0
        )
        accel_bias = n.accel_bias_std * rng.standard_normal(3) + np.cumsum(
            n.accel_bias_walk * math.sqrt(dt) * rng.standard_normal((count, 3)), axis=0
        )
        gyro_raw = gyro_true + gyro_bias + n.gyro_std * rng.standard_normal((count, 3))
        accel_raw = accel_true + accel_bias + n.accel_std * rng.standard_normal((count, 3))
        gyro = np.clip(gyro_raw, -n.gyro_range, n.gyro_range)
        accel = np.clip(accel_raw, -n.accel_range, n.accel_range)
        orientation_noise = rng.standard_normal((count, 3))
        if n.orientation_std_rad is not None:
            quat = quat_mul(quat_true, quat_exp(n.orientation_std_rad * orientation_noise))
            orientation_cov = _diagonal(n.orientation_std_rad**2)
        else:
            quat = np.tile([1.0, 0.0, 0.0, 0.0], (count, 1))
            orientation_cov = [-1.0] + [0.0] * 8  # REP 145: no orientation
        gyro_cov = _diagonal(n.gyro_std**2)
        accel_cov = _diagonal(n.accel_std**2)
        messages = []
        for j in range(count):
            fields = {
                "header": header(traj.t0_ns + int(stamps[j]), self.frame_id),
                "orientation": quaternion(quat[j]),
                "orientation_covariance": orientation_cov,
                "angular_velocity": vector3(gyro[j]),
                "angular_velocity_covariance": gyro_cov,
                "linear_acceleration": vector3(accel[j]),
                "linear_acceleration_covariance": accel_cov,
            }
            messages.append(
                Message(
                    self.topic, ros2_types.IMU, traj.t0_ns + int(log_times[j]), fields, SENSOR_QOS
                )
            )
        truth = {
            "t_ns": t,
            "stamp_ns": stamps,
            "gyro": gyro_true,
            "accel": accel_true,
            "quat_wxyz": quat_true,
            "gyro_bias": gyro_bias,
            "accel_bias": accel_bias,
            "saturated": np.any(np.abs(gyro_raw) > n.gyro_range, axis=1)
            | np.any(np.abs(accel_raw) > n.accel_range, axis=1),
        }
        return SensorOutput(messages, truth)


def _scalar_joints(model: mujoco.MjModel) -> list[int]:
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    return [j for j in range(model.njnt) if int(model.jnt_type[j]) in scalar]


@dataclass(frozen=True)
class Encoders:
    """Joint encoders of every hinge and slide joint (sensor_msgs/JointState, model names).

    position: quantized to the encoder resolution (no other noise); velocity: true + noise;
    effort: the actuator force on the joint's dof during the step + noise.
    """

    topic: str = "/joint_states"
    noise: EncoderNoise = EncoderNoise()
    name: str = "joints"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.JOINT_STATE}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        n = self.noise
        # quantization error is uniform over one step: std = resolution / √12
        return {
            self.name: {
                "type": "joint_state",
                "topic": self.topic,
                "joints": "model",
                "time_offset_ns": -n.clock.offset_ns,
                "noise": _noise_table(
                    position_std=n.hinge_resolution_rad / math.sqrt(12.0),
                    velocity_std=n.velocity_std,
                    effort_std=n.effort_std,
                ),
            }
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def resolution(self, model: mujoco.MjModel) -> np.ndarray:
        """(n_joints,) position quantum of each hinge [rad] and slide [m] joint."""
        return np.array(
            [
                self.noise.hinge_resolution_rad
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
                else self.noise.slide_resolution_m
                for j in _scalar_joints(model)
            ]
        )

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        n = self.noise
        m = traj.model
        joints = _scalar_joints(m)
        if not joints:
            raise SimulationError(f"{self.name}: the model has no hinge or slide joints")
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}" for j in joints]
        qadr = m.jnt_qposadr[joints]
        dofadr = m.jnt_dofadr[joints]
        if n.rate_hz is None:
            t = traj.step_ns(np.arange(traj.steps))
            period = traj.h * NS
        else:
            t = sample_times(n.rate_hz, traj.duration_ns, rng)
            period = NS / n.rate_hz
        stamps = n.clock.stamps(t, period, rng)
        log_times = n.clock.log_times(t, rng)
        resolution = self.resolution(m)
        q_true = traj.interpolate(traj.qpos[:, qadr], t)
        v_true = traj.velocity(traj.qvel[:, dofadr], t)
        effort_true = traj.hold(traj.qfrc_actuator[:, dofadr], t)
        position = np.round(q_true / resolution) * resolution
        velocity = v_true + n.velocity_std * rng.standard_normal(v_true.shape)
        effort = effort_true + n.effort_std * rng.standard_normal(effort_true.shape)
        messages = []
        for j in range(len(t)):
            fields = {
                "header": header(traj.t0_ns + int(stamps[j])),
                "name": names,
                "position": [float(v) for v in position[j]],
                "velocity": [float(v) for v in velocity[j]],
                "effort": [float(v) for v in effort[j]],
            }
            messages.append(
                Message(
                    self.topic,
                    ros2_types.JOINT_STATE,
                    traj.t0_ns + int(log_times[j]),
                    fields,
                    SENSOR_QOS,
                )
            )
        truth = {
            "t_ns": t,
            "stamp_ns": stamps,
            "names": names,
            "position": q_true,
            "velocity": v_true,
            "effort": effort_true,
            "resolution": resolution,
        }
        return SensorOutput(messages, truth)


@dataclass(frozen=True)
class Commands:
    """The controller's commands (std_msgs/Float64MultiArray: ctrl of every actuator).

    Published once per control step (every simulation step), exactly as applied; the message
    has no header, so its time is the recorder's receive time (config stamp = "log").
    """

    topic: str = "/joint_commands"
    clock: Clock = Clock(offset_ns=0, latency_ns=150_000, latency_jitter_ns=50_000)
    std: float = 1e-3  # the config's command noise: how well ctrl turns into actuator force
    name: str = "command"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.FLOAT64_MULTI_ARRAY}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        names = [
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
            for i in range(model.nu)
        ]
        return {
            self.name: {
                "type": "command",
                "topic": self.topic,
                "actuators": names,
                "stamp": "log",
                "time_offset_ns": -self.clock.latency_ns,
                "noise": _noise_table(std=self.std),
            }
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        t = traj.step_ns(np.arange(traj.steps))
        log_times = self.clock.log_times(t, rng)
        messages = [
            Message(
                self.topic,
                ros2_types.FLOAT64_MULTI_ARRAY,
                traj.t0_ns + int(log_times[k]),
                {
                    "layout": {"dim": [], "data_offset": 0},
                    "data": [float(v) for v in traj.ctrl[k]],
                },
                RELIABLE_QOS,
            )
            for k in range(traj.steps)
        ]
        return SensorOutput(messages, {"t_ns": t, "ctrl": traj.ctrl})


@dataclass(frozen=True)
class ForceTorque:
    """A force/torque sensor at a model site (geometry_msgs/WrenchStamped, site frame).

    The model must have a force and a torque sensor at `site` (MuJoCo: the interaction
    between the site's body and its parent, in the site frame).
    """

    topic: str
    site: str
    noise: ForceTorqueNoise = ForceTorqueNoise()
    name: str = "ft"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.WRENCH_STAMPED}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        n = self.noise
        return {
            self.name: {
                "type": "wrench",
                "topic": self.topic,
                "site": self.site,
                "time_offset_ns": -n.clock.offset_ns,
                "noise": _noise_table(force_std=n.force_std, torque_std=n.torque_std),
            }
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        n = self.noise
        m = traj.model
        force_adr = _site_sensor(m, self.site, mujoco.mjtSensor.mjSENS_FORCE, self.name)
        torque_adr = _site_sensor(m, self.site, mujoco.mjtSensor.mjSENS_TORQUE, self.name)
        t = sample_times(n.rate_hz, traj.duration_ns, rng)
        stamps = n.clock.stamps(t, NS / n.rate_hz, rng)
        log_times = n.clock.log_times(t, rng)
        force_true = traj.hold(traj.sensordata_acc[:, force_adr], t)
        torque_true = traj.hold(traj.sensordata_acc[:, torque_adr], t)
        force_bias = n.force_bias_std * rng.standard_normal(3)
        torque_bias = n.torque_bias_std * rng.standard_normal(3)
        force = force_true + force_bias + n.force_std * rng.standard_normal(force_true.shape)
        torque = torque_true + torque_bias + n.torque_std * rng.standard_normal(torque_true.shape)
        messages = [
            Message(
                self.topic,
                ros2_types.WRENCH_STAMPED,
                traj.t0_ns + int(log_times[j]),
                {
                    "header": header(traj.t0_ns + int(stamps[j]), self.site),
                    "wrench": {"force": vector3(force[j]), "torque": vector3(torque[j])},
                },
                SENSOR_QOS,
            )
            for j in range(len(t))
        ]
        truth = {
            "t_ns": t,
            "stamp_ns": stamps,
            "force": force_true,
            "torque": torque_true,
            "force_bias": force_bias,
            "torque_bias": torque_bias,
        }
        return SensorOutput(messages, truth)


@dataclass(frozen=True)
class FootContacts:
    """Binary foot-contact flags (std_msgs/Float64MultiArray: data[i] = 1.0 when foot i
    touches, else 0.0), as a legged robot's contact estimator publishes them: a foot body is
    in contact when the normal force of its contacts exceeds `threshold_n`, evaluated at each
    control step's state and controls (pushes left out), published every step, after
    `clock`'s latency, with no header (config stamp = "log").
    """

    feet: tuple[str, ...]
    topic: str = "/foot_contacts"
    threshold_n: float = 5.0
    clock: Clock = Clock(offset_ns=0, latency_ns=500_000, latency_jitter_ns=100_000)
    name: str = "contacts"

    def topics(self) -> dict[str, str]:
        return {self.topic: ros2_types.FLOAT64_MULTI_ARRAY}

    def streams(self, model: mujoco.MjModel) -> dict[str, dict[str, Any]]:
        return {
            self.name: {
                "type": "contact_flags",
                "topic": self.topic,
                "bodies": list(self.feet),
                "stamp": "log",
                "time_offset_ns": -self.clock.latency_ns,
            }
        }

    def settings(self) -> dict[str, Any]:
        return _settings(self)

    def normal_forces(self, traj: Trajectory) -> np.ndarray:
        """(N, feet) the summed normal contact force on each foot body at each step [N]."""
        m = traj.model
        feet = _body_ids(m, self.feet, self.name)
        d = mujoco.MjData(m)
        force = np.zeros(6)
        out = np.zeros((traj.steps, len(feet)))
        for k in range(traj.steps):
            d.qpos[:], d.qvel[:], d.ctrl[:] = traj.qpos[k], traj.qvel[k], traj.ctrl[k]
            mujoco.mj_forward(m, d)
            for i in range(d.ncon):
                c = d.contact[i]
                bodies = m.geom_bodyid[[c.geom1, c.geom2]]
                for f, body in enumerate(feet):
                    if body in bodies:
                        mujoco.mj_contactForce(m, d, i, force)
                        out[k, f] += force[0]
        return out

    def sample(self, traj: Trajectory, rng: np.random.Generator) -> SensorOutput:
        t = traj.step_ns(np.arange(traj.steps))
        log_times = self.clock.log_times(t, rng)
        normal = self.normal_forces(traj)
        flags = (normal > self.threshold_n).astype(float)
        messages = [
            Message(
                self.topic,
                ros2_types.FLOAT64_MULTI_ARRAY,
                traj.t0_ns + int(log_times[k]),
                {"layout": {"dim": [], "data_offset": 0}, "data": flags[k].tolist()},
                RELIABLE_QOS,
            )
            for k in range(traj.steps)
        ]
        return SensorOutput(messages, {"t_ns": t, "flags": flags, "normal_force": normal})
