"""Writing robot logs as rosbag2 would: ROS 2 MCAP files, and the estimate/ground-truth layout.

`Ros2Writer` writes what `ros2 bag record -s mcap` writes: profile `ros2`, one `ros2msg`
schema per message type (the definition text, nested types after `===` separators), `cdr`
message encoding, and the `offered_qos_profiles` of each channel in its metadata. Messages are
plain dicts with the ROS field names; `log_time` is when the recorder received a message.

`write_state` writes one robot state in the topic layout that the simulator uses for its
ground truth (prefix `/ground_truth`) and the estimator for its estimates (prefix
`/estimate`), so the two can be compared topic by topic:

    topic                          type                            one per
    {prefix}/odometry/<body>       nav_msgs/msg/Odometry           free body
    {prefix}/joint_states          sensor_msgs/msg/JointState      (hinge and slide joints)
    {prefix}/contact_wrench/<body> geometry_msgs/msg/WrenchStamped body that can touch anything
    {prefix}/contacts              physfuse_msgs/msg/ContactArray  (every contact of the step)
    {prefix}/imu_bias/<site>       geometry_msgs/msg/AccelStamped  IMU, by its model site

- Odometry: header.frame_id "world", child_frame_id the body name; pose = the body frame in
  the world; twist = linear velocity of the body origin and angular velocity, both in the
  body frame (ROS: twist in child_frame_id); covariances 6×6 row-major over
  (x, y, z, rot x, rot y, rot z), zero when not given.
- JointState: every hinge and slide joint in model order; position and velocity are qpos and
  qvel; effort is the generalized force on the joint's dof that is neither passive, bias nor
  constraint force (the analytic inverse's `qfrc_inverse`: actuators plus applied forces);
  empty when not given.
- WrenchStamped: the net force and torque of all contacts on the body over the step
  (impulse / h), expressed in the body frame (header.frame_id = body name) about the body
  frame's origin; zero when the body touches nothing.
- ContactArray (`msgs/physfuse_msgs/msg/ContactArray.msg`): per contact the bodies and geoms,
  position, contact frame, impulse and force in the contact frame, condim and Algorithm 5
  branch.
- AccelStamped (IMU bias): accel.linear = accelerometer bias [m/s²], accel.angular = gyro
  bias [rad/s], in the frame of the IMU's model site (header.frame_id): the frame in which
  the estimator compares the IMU with MuJoCo's sensors (measured = true + bias). The
  simulator writes it at the IMU's sample times, the estimator at its knots. The topic is
  named by that site, which both know (the estimator's stream and the simulator's sensor
  may be named differently), so that estimate and truth share it.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, NamedTuple, Protocol, cast

import mujoco
import numpy as np
from mcap.records import Schema
from mcap.well_known import SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2._dynamic import EncoderFunction

from estimator.io import cdr
from estimator.io.logs import ros2_types
from estimator.io.logs.ros2_types import CONTACT_ARRAY
from physics.result import Constraints

if TYPE_CHECKING:
    from estimator.estimate import Estimate

NS = 1_000_000_000

ODOMETRY = "nav_msgs/msg/Odometry"
ACCEL_STAMPED = "geometry_msgs/msg/AccelStamped"
# rosbag2's QoS profiles (metadata version 9 spelling): sensor data is best effort, state and
# commands are reliable; both volatile, default deadline/lifespan/lease ("infinite").
_INFINITE = "{sec: 9223372036, nsec: 854775807}"


def qos_profile(reliability: str) -> str:
    """The `offered_qos_profiles` YAML of a channel ('reliable' or 'best_effort')."""
    return (
        "- history: keep_last\n"
        "  depth: 10\n"
        f"  reliability: {reliability}\n"
        "  durability: volatile\n"
        f"  deadline: {_INFINITE}\n"
        f"  lifespan: {_INFINITE}\n"
        "  liveliness: automatic\n"
        f"  liveliness_lease_duration: {_INFINITE}\n"
        "  avoid_ros_namespace_conventions: false"
    )


SENSOR_QOS = qos_profile("best_effort")
RELIABLE_QOS = qos_profile("reliable")


class MessageSink(Protocol):
    """Where state messages go: an MCAP file (`Ros2Writer`) or a live server
    (`estimator.io.foxglove.FoxgloveSink`)."""

    def write(
        self,
        topic: str,
        msg_type: str,
        fields: Mapping[str, Any],
        log_time_ns: int,
        *,
        qos: str = ...,
    ) -> None: ...

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None: ...

    def flush(self) -> None: ...

    def finish(self) -> None: ...


class Positioned:
    """A pipe or socket that tells its position (the bytes written), as the MCAP writer asks."""

    def __init__(self, out: IO[bytes]) -> None:
        self.out, self.position = out, 0

    def write(self, data: bytes) -> int:
        self.out.write(data)
        self.position += len(data)
        return len(data)

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        self.out.flush()


def _seekable(f: IO[bytes]) -> bool:
    try:
        return f.seekable()
    except (AttributeError, ValueError):
        return False


class Ros2Writer:
    """A rosbag2-layout MCAP writer (profile ros2, ros2msg schemas, cdr, QoS metadata).

    output: a path or a binary file object (left open). compression: "zstd", "lz4" or
    "none" chunk compression. The file's bytes depend only on what is written (no wall-clock
    times), so equal inputs give equal files. chunked=False writes each message as its own
    record (a live stream: what `flush` pushed out reads back even if the writer is killed).
    """

    def __init__(
        self,
        output: str | Path | IO[bytes],
        *,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        chunked: bool = True,
    ) -> None:
        codecs = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }
        self._own = isinstance(output, str | Path)
        self._file: IO[bytes] = (
            open(output, "wb")  # noqa: SIM115
            if isinstance(output, str | Path)
            else output
        )
        self._writer = McapWriter(
            self._file if _seekable(self._file) else cast(IO[bytes], Positioned(self._file)),
            chunk_size=chunk_size,
            compression=codecs[compression],
            use_chunking=chunked,
        )
        self._writer.start(profile="ros2", library="physfuse")
        self._schemas: dict[str, tuple[Schema, EncoderFunction]] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._finished = False
        self.message_count = 0

    def channel(self, topic: str, msg_type: str, qos: str = RELIABLE_QOS) -> int:
        """Register a topic (once) and its type's schema; returns the channel id."""
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msg_type:
                raise ValueError(f"topic {topic} is {known[1]}, cannot also carry {msg_type}")
            return known[0]
        schema, _ = self._schema(msg_type)
        channel_id = self._writer.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=schema.id,
            metadata={"offered_qos_profiles": qos},
        )
        self._channels[topic] = (channel_id, msg_type)
        return channel_id

    def write(
        self,
        topic: str,
        msg_type: str,
        fields: Mapping[str, Any],
        log_time_ns: int,
        *,
        publish_time_ns: int | None = None,
        qos: str = RELIABLE_QOS,
    ) -> None:
        """Encode one message (CDR) and write it, registering its channel on first use."""
        _, encode = cdr_encoder(msg_type)
        self.write_encoded(
            topic, msg_type, encode(fields), log_time_ns, publish_time_ns=publish_time_ns, qos=qos
        )

    def write_encoded(
        self,
        topic: str,
        msg_type: str,
        data: bytes,
        log_time_ns: int,
        *,
        publish_time_ns: int | None = None,
        qos: str = RELIABLE_QOS,
    ) -> None:
        """Write one message already CDR-encoded, registering its channel on first use."""
        channel_id = self.channel(topic, msg_type, qos)
        self._writer.add_message(
            channel_id=channel_id,
            log_time=int(log_time_ns),
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=0,
            data=data,
        )
        self.message_count += 1

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """A metadata record (name → string pairs), e.g. the simulation's settings."""
        self._writer.add_metadata(name, dict(data))

    def flush(self) -> None:
        """Push what was written to the file or stream (unchunked: every message so far)."""
        self._file.flush()

    def finish(self) -> None:
        """Write the summary and close the file (if this writer opened it)."""
        if self._finished:
            return
        self._finished = True
        self._writer.finish()
        if self._own:
            self._file.close()

    def __enter__(self) -> Ros2Writer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()

    def _schema(self, msg_type: str) -> tuple[Schema, EncoderFunction]:
        entry = self._schemas.get(msg_type)
        if entry is None:
            text, encode = cdr_encoder(msg_type)
            data = text.encode()
            schema_id = self._writer.register_schema(msg_type, SchemaEncoding.ROS2, data)
            schema = Schema(id=schema_id, name=msg_type, encoding=SchemaEncoding.ROS2, data=data)
            entry = self._schemas[msg_type] = (schema, encode)
        return entry


@functools.cache
def cdr_encoder(msg_type: str) -> tuple[str, EncoderFunction]:
    """A ROS 2 message type's definition text (ros2msg) and its CDR encoder of field dicts
    (`estimator.io.cdr`: mcap_ros2's bytes, planned once per type)."""
    return ros2_types.message_definition(msg_type), cdr.encoder(msg_type)


# -- message builders (numpy conventions in, ROS conventions out) ------------------------------
def time_msg(t_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time of int nanoseconds."""
    return {"sec": int(t_ns) // NS, "nanosec": int(t_ns) % NS}


def header(t_ns: int, frame_id: str = "") -> dict[str, Any]:
    return {"stamp": time_msg(t_ns), "frame_id": frame_id}


def vector3(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def quaternion(quat_wxyz: np.ndarray) -> dict[str, float]:
    """geometry_msgs/Quaternion (x, y, z, w fields) of a (w, x, y, z) quaternion."""
    w, x, y, z = (float(c) for c in quat_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def pose(pos: np.ndarray, quat_wxyz: np.ndarray) -> dict[str, Any]:
    return {"position": vector3(pos), "orientation": quaternion(quat_wxyz)}


# -- the estimate / ground-truth layout --------------------------------------------------------
@dataclass(frozen=True)
class StateLayout:
    """Which topics a model's state is written to (see the module docstring).

    free_bodies: bodies whose joint is a free joint (one Odometry each), model order.
    joints: hinge and slide joints (the JointState's names), model order.
    contact_bodies: bodies that can collide (a geom with contype or conaffinity, or in an
        explicit pair) and are not welded to the world: one WrenchStamped each.
    """

    free_bodies: tuple[str, ...]
    joints: tuple[str, ...]
    contact_bodies: tuple[str, ...]

    @classmethod
    def of(cls, model: mujoco.MjModel) -> StateLayout:
        free = tuple(
            _name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[j]))
            for j in range(model.njnt)
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
        )
        scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        joints = tuple(
            _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            for j in range(model.njnt)
            if int(model.jnt_type[j]) in scalar
        )
        colliding = {
            int(model.geom_bodyid[g])
            for g in range(model.ngeom)
            if model.geom_contype[g] or model.geom_conaffinity[g]
        }
        for p in range(model.npair):
            colliding.add(int(model.geom_bodyid[model.pair_geom1[p]]))
            colliding.add(int(model.geom_bodyid[model.pair_geom2[p]]))
        bodies = tuple(
            _name(model, mujoco.mjtObj.mjOBJ_BODY, b)
            for b in sorted(colliding)
            if model.body_weldid[b] != 0
        )
        return cls(free, joints, bodies)

    def topics(self, prefix: str) -> dict[str, str]:
        """topic → message type of every topic the layout writes under `prefix`."""
        out = {f"{prefix}/odometry/{b}": ODOMETRY for b in self.free_bodies}
        if self.joints:
            out[f"{prefix}/joint_states"] = ros2_types.JOINT_STATE
        out.update(
            {f"{prefix}/contact_wrench/{b}": ros2_types.WRENCH_STAMPED for b in self.contact_bodies}
        )
        out[f"{prefix}/contacts"] = CONTACT_ARRAY
        return out


def _name(model: mujoco.MjModel, obj: int, index: int) -> str:
    name = mujoco.mj_id2name(model, obj, index)
    if name:
        return name
    return "world" if obj == mujoco.mjtObj.mjOBJ_BODY and index == 0 else f"#{index}"


def state_data(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    qvel: np.ndarray,
    data: mujoco.MjData | None = None,
) -> mujoco.MjData:
    """MjData with the positions and velocities of a state (kinematics, com, cvel) computed.

    qpos: (nq,), qvel: (nv,). `data` is reused when given.
    """
    data = data if data is not None else mujoco.MjData(model)
    data.qpos[:] = qpos
    data.qvel[:] = qvel
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_comVel(model, data)
    return data


def body_twist(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> np.ndarray:
    """(6,) [angular, linear] velocity of the body frame's origin, in the body frame.

    mjOBJ_XBODY: the body frame (xpos, xmat); mjOBJ_BODY would give the centre of mass in the
    principal-inertia frame (xipos, ximat), whose axes differ on most public models."""
    res = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, res, 1)
    return res


def contact_wrenches(
    model: mujoco.MjModel, data: mujoco.MjData, constraints: Constraints
) -> np.ndarray:
    """(nbody, 6) net contact [force, torque] on each body, in its frame, about its origin.

    Contact i pushes the body of geom2 with F = frameᵀ f[0:3] (and the torsional/rolling
    torques frameᵀ f[3:6] for condim ≥ 4) at the contact point, and the body of geom1 with
    the opposite wrench; f = impulse / h. `data` holds the step's kinematics.
    """
    contacts = constraints.contacts
    world = np.zeros((model.nbody, 6))  # force, torque about the body origin, world axes
    for i in range(len(contacts.dim)):
        if contacts.efc_address[i] < 0:
            continue
        f = np.zeros(6)
        dim = int(contacts.dim[i])
        f[:dim] = constraints.contact_impulse(i) / constraints.h
        axes = contacts.frame[i].T  # R_world_contact: columns normal, tangent1, tangent2
        force = axes @ f[:3]
        torque = axes @ f[3:6]  # torsional (about the normal), rolling (about the tangents)
        point = contacts.pos[i]
        for geom, sign in ((contacts.geom[i][1], 1.0), (contacts.geom[i][0], -1.0)):
            body = int(model.geom_bodyid[geom])
            a = point - data.xpos[body]  # arm × force, without np.cross's per-call overhead
            moment = [
                a[1] * force[2] - a[2] * force[1],
                a[2] * force[0] - a[0] * force[2],
                a[0] * force[1] - a[1] * force[0],
            ]
            world[body, :3] += sign * force
            world[body, 3:] += sign * (np.asarray(moment) + torque)
    rot = data.xmat.reshape(-1, 3, 3)  # R_world_body
    out = np.empty_like(world)
    out[:, :3] = np.einsum("bji,bj->bi", rot, world[:, :3])
    out[:, 3:] = np.einsum("bji,bj->bi", rot, world[:, 3:])
    return out


def contact_fields(model: mujoco.MjModel, constraints: Constraints, t_ns: int) -> dict[str, Any]:
    """physfuse_msgs/ContactArray fields of every contact in `constraints`."""
    contacts = constraints.contacts
    items = []
    for i in range(len(contacts.dim)):
        dim = int(contacts.dim[i])
        impulse = np.zeros(6)
        impulse[:dim] = constraints.contact_impulse(i)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, contacts.frame[i].T.reshape(-1))  # R_world_contact
        g1, g2 = (int(g) for g in contacts.geom[i])
        items.append(
            {
                "body1": _name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g1])),
                "body2": _name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g2])),
                "geom1": _name(model, mujoco.mjtObj.mjOBJ_GEOM, g1),
                "geom2": _name(model, mujoco.mjtObj.mjOBJ_GEOM, g2),
                "position": vector3(contacts.pos[i]),
                "orientation": quaternion(quat),
                "dim": dim,
                "impulse": [float(v) for v in impulse],
                "force": [float(v) for v in impulse / constraints.h],
                "branch": int(constraints.contact_branch(i)),
            }
        )
    return {
        "header": header(t_ns, "world"),
        "timestep": float(constraints.h),
        "contacts": items,
    }


class Message(NamedTuple):
    """One message to write: ROS fields as a dict, received by the recorder at log_time_ns."""

    topic: str
    msg_type: str
    log_time_ns: int
    fields: dict[str, Any]
    qos: str = RELIABLE_QOS

    def encoded(self) -> EncodedMessage:
        """The message with its fields CDR-encoded: a tenth of the memory (an hour of a
        simulated robot's messages is millions of them)."""
        _, encode = cdr_encoder(self.msg_type)
        data = encode(self.fields)
        return EncodedMessage(self.topic, self.msg_type, self.log_time_ns, data, self.qos)


class EncodedMessage(NamedTuple):
    """A `Message` whose fields are CDR bytes (`Ros2Writer.write_encoded`)."""

    topic: str
    msg_type: str
    log_time_ns: int
    data: bytes
    qos: str = RELIABLE_QOS


def state_messages(
    prefix: str,
    t_ns: int,
    model: mujoco.MjModel,
    data: mujoco.MjData,
    *,
    qfrc: np.ndarray | None = None,
    constraints: Constraints | None = None,
    pose_covariance: Mapping[str, np.ndarray] | None = None,
    twist_covariance: Mapping[str, np.ndarray] | None = None,
    log_time_ns: int | None = None,
    layout: StateLayout | None = None,
) -> list[Message]:
    """The messages of one robot state under `prefix` (arguments as for `write_state`)."""
    layout = layout or StateLayout.of(model)
    log_time = t_ns if log_time_ns is None else log_time_ns
    out = []
    for name in layout.free_bodies:
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        twist = body_twist(model, data, body)
        odometry: dict[str, Any] = {
            "header": header(t_ns, "world"),
            "child_frame_id": name,
            "pose": {
                "pose": pose(data.xpos[body], data.xquat[body]),
                "covariance": _covariance(pose_covariance, name),
            },
            "twist": {
                "twist": {"linear": vector3(twist[3:]), "angular": vector3(twist[:3])},
                "covariance": _covariance(twist_covariance, name),
            },
        }
        out.append(Message(f"{prefix}/odometry/{name}", ODOMETRY, log_time, odometry))
    if layout.joints:
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in layout.joints]
        fields: dict[str, Any] = {
            "header": header(t_ns),
            "name": list(layout.joints),
            "position": [float(data.qpos[model.jnt_qposadr[j]]) for j in ids],
            "velocity": [float(data.qvel[model.jnt_dofadr[j]]) for j in ids],
            "effort": [] if qfrc is None else [float(qfrc[model.jnt_dofadr[j]]) for j in ids],
        }
        out.append(Message(f"{prefix}/joint_states", ros2_types.JOINT_STATE, log_time, fields))
    if constraints is None:
        return out
    wrenches = contact_wrenches(model, data, constraints)
    for name in layout.contact_bodies:
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        fields = {
            "header": header(t_ns, name),
            "wrench": {
                "force": vector3(wrenches[body, :3]),
                "torque": vector3(wrenches[body, 3:]),
            },
        }
        topic = f"{prefix}/contact_wrench/{name}"
        out.append(Message(topic, ros2_types.WRENCH_STAMPED, log_time, fields))
    fields = contact_fields(model, constraints, t_ns)
    out.append(Message(f"{prefix}/contacts", CONTACT_ARRAY, log_time, fields))
    return out


def imu_bias_message(prefix: str, imu: str, t_ns: int, frame_id: str, bias: np.ndarray) -> Message:
    """`{prefix}/imu_bias/<site>` at t_ns: bias (6,) = accelerometer (m/s²) then gyro (rad/s)
    bias, in the frame of the IMU's site `frame_id`, which names the topic (the IMU's name
    `imu` when no site is given)."""
    fields = {
        "header": header(t_ns, frame_id),
        "accel": {"linear": vector3(bias[:3]), "angular": vector3(bias[3:6])},
    }
    return Message(f"{prefix}/imu_bias/{frame_id or imu}", ACCEL_STAMPED, t_ns, fields)


def write_state(
    writer: MessageSink,
    prefix: str,
    t_ns: int,
    model: mujoco.MjModel,
    data: mujoco.MjData,
    *,
    qfrc: np.ndarray | None = None,
    constraints: Constraints | None = None,
    pose_covariance: Mapping[str, np.ndarray] | None = None,
    twist_covariance: Mapping[str, np.ndarray] | None = None,
    log_time_ns: int | None = None,
    layout: StateLayout | None = None,
) -> int:
    """Write one robot state under `prefix` ("/ground_truth", "/estimate"); returns the count.

    t_ns: the state's time (header stamps), int ns.
    data: MjData holding qpos, qvel and their kinematics (`state_data`, or after mj_forward).
    qfrc: (nv,) generalized force, written as JointState.effort (None: no effort).
    constraints: the step's contacts and impulses (native or reference inverse, or a forward
        step); None writes no contact topics.
    pose_covariance, twist_covariance: body name → (6, 6) over (x, y, z, rot x, rot y, rot z)
        (missing bodies: zero).
    log_time_ns: the record time (default t_ns).
    layout: `StateLayout.of(model)`, precomputed to save time on long runs.
    """
    messages = state_messages(
        prefix,
        t_ns,
        model,
        data,
        qfrc=qfrc,
        constraints=constraints,
        pose_covariance=pose_covariance,
        twist_covariance=twist_covariance,
        log_time_ns=log_time_ns,
        layout=layout,
    )
    for m in messages:
        writer.write(m.topic, m.msg_type, m.fields, m.log_time_ns, qos=m.qos)
    return len(messages)


def _covariance(table: Mapping[str, np.ndarray] | None, body: str) -> list[float]:
    if table is None or body not in table:
        return [0.0] * 36
    cov = np.asarray(table[body], dtype=float)
    if cov.shape != (6, 6):
        raise ValueError(f"covariance of {body!r} has shape {cov.shape}, expected (6, 6)")
    return [float(v) for v in cov.reshape(-1)]


class EstimateWriter:
    """An estimate in the `/estimate/...` layout, knot by knot: a batch run writes every knot
    at once, a streaming run each as it is final (`chunked=False`, `flush` after each update;
    its smoothed knots under another prefix, `/estimate_smoothed`). Each IMU stream's bias
    goes to `<prefix>/imu_bias/<stream>` (frame: its site); metadata `physfuse.estimate` names
    the model, the knot spacing and the run (`run_id`, also in summary.json).

        with EstimateWriter(path, model, est.model_name, est.h, run_id) as out:
            out.write(est, range(est.T), {"imu": "imu_site"})
    """

    def __init__(
        self,
        output: str | Path | IO[bytes] | MessageSink,
        model: mujoco.MjModel,
        model_name: str,
        h: float,
        run_id: str = "",
        chunked: bool = True,
    ) -> None:
        """output: an MCAP file (a path or a binary file object) or a live `MessageSink`."""
        self.model = model
        self.layout = StateLayout.of(model)
        self.data = mujoco.MjData(model)
        self.free = [
            j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
        ]
        self.writer: MessageSink
        if isinstance(output, str | Path) or not hasattr(output, "add_metadata"):
            self.writer = Ros2Writer(output, chunked=chunked)
        else:  # a live sink
            self.writer = cast(MessageSink, output)
        self.writer.add_metadata(
            "physfuse.estimate", {"model": model_name, "h": repr(h), "run_id": run_id}
        )
        self.message_count = 0
        # the encoders planned now, not at the first knot (0.4 s: a stream's first knots
        # waited for it)
        for msg_type in {*self.layout.topics("").values(), ACCEL_STAMPED}:
            cdr_encoder(msg_type)

    def write(
        self,
        est: Estimate,
        knots: range,
        imu_sites: Mapping[str, str] | None = None,
        prefix: str = "/estimate",
    ) -> int:
        """Knots `knots` of an `Estimate` (qpos, qvel, qpos_std, qfrc_inverse, constraints,
        imu_bias) under `prefix`; returns the messages written."""
        model, data, sites = self.model, self.data, imu_sites or {}
        count = 0
        for k in knots:
            state_data(model, est.qpos[k], est.qvel[k], data)
            covariance = {}
            for j in self.free:
                body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[j]))
                std = est.qpos_std[k, model.jnt_dofadr[j] : model.jnt_dofadr[j] + 6]
                covariance[body] = np.diag(np.nan_to_num(std, nan=0.0) ** 2)
            t_ns = int(est.t_ns[k])
            count += write_state(
                self.writer,
                prefix,
                t_ns,
                model,
                data,
                qfrc=est.qfrc_inverse[k],
                constraints=est.constraints[k],
                pose_covariance=covariance,
                layout=self.layout,
            )
            for stream, bias in est.imu_bias.items():
                m = imu_bias_message(prefix, stream, t_ns, sites.get(stream, ""), bias[k])
                self.writer.write(m.topic, m.msg_type, m.fields, m.log_time_ns)
                count += 1
        self.message_count += count
        return count

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.finish()

    def __enter__(self) -> EstimateWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
