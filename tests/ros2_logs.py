"""Writing real ROS 2 logs for tests: MCAP files (mcap_ros2) and rosbag2 folders (rosbags).

Messages are plain dicts with the ROS field names (`Msg`); the builders below take numpy
conventions (int ns, quaternions w, x, y, z) and produce ROS ones (sec/nanosec, x, y, z, w).
`write_mcap` writes them with `mcap_ros2.writer.Writer` and the rosbag2 schema texts
(profile "ros2", schema encoding "ros2msg", message encoding "cdr"); `write_rosbag2` writes
the same messages with rosbags' own CDR encoder and MCAP writer, split over two files.
`sample_recording` is a small multi-rate recording of every supported type, and
`SAMPLE_CONFIG` the config that maps it onto `ROBOT_XML`.
"""

from __future__ import annotations

import io
import shutil
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.interfaces import Nodetype
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from ruamel.yaml import YAML

from estimator.io.logs import ros2_types as t
from estimator.io.logs.ros2_types import message_definition, typestore

NS = 1_000_000_000
T0 = 1_700_000_000 * NS  # a realistic epoch for header stamps and log times


@dataclass(frozen=True)
class Msg:
    """One message to write: ROS fields as a dict, logged (received) at log_time_ns."""

    topic: str
    msg_type: str
    log_time_ns: int
    fields: dict[str, Any]


# -- message builders (numpy conventions in, ROS conventions out) -------------------------------
def time_msg(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // NS, "nanosec": t_ns % NS}


def header(t_ns: int, frame_id: str = "") -> dict[str, Any]:
    return {"stamp": time_msg(t_ns), "frame_id": frame_id}


def _xyz(v: Sequence[float]) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(q_wxyz: Sequence[float]) -> dict[str, float]:
    w, x, y, z = (float(c) for c in q_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def pose(pos: Sequence[float], quat_wxyz: Sequence[float]) -> dict[str, Any]:
    return {"position": _xyz(pos), "orientation": _quat(quat_wxyz)}


def pose_stamped(t_ns: int, pos, quat_wxyz, frame_id: str = "world") -> dict[str, Any]:
    return {"header": header(t_ns, frame_id), "pose": pose(pos, quat_wxyz)}


def transform_stamped(
    t_ns: int, child: str, pos, quat_wxyz, frame_id: str = "world"
) -> dict[str, Any]:
    return {
        "header": header(t_ns, frame_id),
        "child_frame_id": child,
        "transform": {"translation": _xyz(pos), "rotation": _quat(quat_wxyz)},
    }


def tf_message(transforms: list[dict[str, Any]]) -> dict[str, Any]:
    return {"transforms": transforms}


def rigid_bodies(t_ns: int, bodies: dict[str, tuple], frame_id: str = "world") -> dict[str, Any]:
    """bodies: rigid_body_name → (pos, quat_wxyz)."""
    return {
        "header": header(t_ns, frame_id),
        "frame_number": 0,
        "rigidbodies": [
            {"rigid_body_name": name, "markers": [], "pose": pose(p, q)}
            for name, (p, q) in bodies.items()
        ],
    }


USE_NAME, USE_INDEX, USE_BOTH = 0, 1, 2


def markers(t_ns: int, entries: list[tuple[int, int, str, Sequence[float]]]) -> dict[str, Any]:
    """entries: (id_type, marker_index, marker_name, position)."""
    return {
        "header": header(t_ns, "world"),
        "frame_number": 0,
        "markers": [
            {"id_type": k, "marker_index": i, "marker_name": n, "translation": _xyz(p)}
            for k, i, n, p in entries
        ],
    }


def imu(t_ns: int, gyro, accel, quat_wxyz=None, frame_id: str = "imu_link") -> dict[str, Any]:
    """quat_wxyz None: no orientation (orientation_covariance[0] = -1, REP 145)."""
    cov = [0.0] * 9
    return {
        "header": header(t_ns, frame_id),
        "orientation": _quat(quat_wxyz if quat_wxyz is not None else (1, 0, 0, 0)),
        "orientation_covariance": [-1.0] + [0.0] * 8 if quat_wxyz is None else cov,
        "angular_velocity": _xyz(gyro),
        "angular_velocity_covariance": cov,
        "linear_acceleration": _xyz(accel),
        "linear_acceleration_covariance": cov,
    }


def joint_state(t_ns: int, names, position=(), velocity=(), effort=()) -> dict[str, Any]:
    return {
        "header": header(t_ns),
        "name": list(names),
        "position": [float(v) for v in position],
        "velocity": [float(v) for v in velocity],
        "effort": [float(v) for v in effort],
    }


def float64_multi_array(data) -> dict[str, Any]:
    return {"layout": {"dim": [], "data_offset": 0}, "data": [float(v) for v in data]}


def joint_trajectory(
    t_ns: int, names, *, positions=(), velocities=(), effort=(), time_from_start_ns: int = 0
) -> dict[str, Any]:
    return {
        "header": header(t_ns),
        "joint_names": list(names),
        "points": [
            {
                "positions": [float(v) for v in positions],
                "velocities": [float(v) for v in velocities],
                "accelerations": [],
                "effort": [float(v) for v in effort],
                "time_from_start": time_msg(time_from_start_ns),
            }
        ],
    }


def wrench_stamped(t_ns: int, force, torque, frame_id: str = "ft_link") -> dict[str, Any]:
    return {
        "header": header(t_ns, frame_id),
        "wrench": {"force": _xyz(force), "torque": _xyz(torque)},
    }


# -- writers ----------------------------------------------------------------------------------
def write_mcap(
    target: str | Path | IO[bytes],
    messages: Iterable[Msg],
    *,
    chunk_size: int = 1024 * 1024,
    compression: str = "zstd",
    enable_crcs: bool = True,
) -> None:
    """Write messages (in the given order) as a ROS 2 MCAP file with mcap_ros2's writer.

    enable_crcs: False writes no chunk and summary CRCs (as some writers do).
    """
    own = isinstance(target, str | Path)
    out: Any = open(target, "wb") if own else target  # noqa: SIM115
    try:
        writer = Ros2Writer(
            out,
            chunk_size=chunk_size,
            compression=CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE,
            enable_crcs=enable_crcs,
        )
        schemas = {}
        for m in messages:
            if m.msg_type not in schemas:
                schemas[m.msg_type] = writer.register_msgdef(
                    m.msg_type, message_definition(m.msg_type)
                )
            writer.write_message(
                m.topic,
                schemas[m.msg_type],
                m.fields,
                log_time=m.log_time_ns,
                publish_time=m.log_time_ns,
            )
        writer.finish()
    finally:
        if own:
            out.close()


def mcap_bytes(messages: Iterable[Msg], **kwargs: Any) -> bytes:
    buf = io.BytesIO()
    write_mcap(buf, messages, **kwargs)
    return buf.getvalue()


def write_rosbag2(folder: Path, messages: Sequence[Msg], *, split_at: int | None = None) -> Path:
    """A rosbag2 folder written by rosbags (CDR encoding, MCAP storage, metadata.yaml).

    split_at: the first `split_at` messages go to `<name>_0.mcap`, the rest to
    `<name>_1.mcap`, as rosbag2 splits a long recording.
    """
    parts = [messages] if split_at is None else [messages[:split_at], messages[split_at:]]
    folder = Path(folder)
    metas = []
    for i, part in enumerate(parts):
        bag = folder.parent / f"{folder.name}.part{i}"
        _write_one_bag(bag, part)
        metas.append((bag, YAML(typ="safe").load((bag / "metadata.yaml").read_text())))
    folder.mkdir(parents=True)
    files, merged = [], metas[0][1]
    info = merged["rosbag2_bagfile_information"]
    for i, (bag, meta) in enumerate(metas):
        name = f"{folder.name}_{i}.mcap"
        shutil.move(bag / f"{bag.name}.mcap", folder / name)
        entry = meta["rosbag2_bagfile_information"]["files"][0]
        files.append(entry | {"path": name})
        shutil.rmtree(bag)
    info["relative_file_paths"] = [f["path"] for f in files]
    info["files"] = files
    info["message_count"] = len(messages)
    counts: dict[str, int] = {}
    for m in messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
    for entry in info["topics_with_message_count"]:
        entry["message_count"] = counts[entry["topic_metadata"]["name"]]
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    with (folder / "metadata.yaml").open("w") as f:
        yaml.dump(merged, f)
    return folder


def _write_one_bag(bag: Path, messages: Sequence[Msg]) -> None:
    store = typestore()
    with Rosbag2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for m in messages:
            if m.topic not in connections:
                connections[m.topic] = writer.add_connection(m.topic, m.msg_type, typestore=store)
            data = store.serialize_cdr(_to_rosbags(m.msg_type, m.fields), m.msg_type)
            writer.write(connections[m.topic], m.log_time_ns, data)


_DTYPES = {
    "float64": np.float64,
    "float32": np.float32,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "bool": np.bool_,
}


def _to_rosbags(msg_type: str, value: dict[str, Any]) -> Any:
    """A dict message → rosbags' dataclass instance (missing fields take ROS defaults)."""
    store = typestore()
    _, fields = store.fielddefs[msg_type]
    kwargs = {name: _field(node, value.get(name)) for name, node in fields}
    return store.types[msg_type](**kwargs)


def _field(node: tuple, value: Any) -> Any:
    kind, detail = node
    if kind == Nodetype.NAME:
        return _to_rosbags(detail, value or {})
    if kind == Nodetype.BASE:
        base = detail[0]
        if base == "string":
            return value or ""
        return _DTYPES[base](value or 0).item()
    (sub_kind, sub_detail), length = detail
    items = list(value) if value is not None else []
    if kind == Nodetype.ARRAY and not items:
        items = [None] * length
    if sub_kind == Nodetype.BASE and sub_detail[0] in _DTYPES:
        return np.array([v or 0 for v in items], dtype=_DTYPES[sub_detail[0]])
    return [_field((sub_kind, sub_detail), v) for v in items]


# -- the test robot and a sample recording ------------------------------------------------------
ROBOT_XML = """\
<mujoco model="walker">
  <option cone="elliptic"/>
  <worldbody>
    <body name="torso" pos="0 0 1">
      <freejoint name="root"/>
      <geom type="box" size=".1 .1 .1" mass="5"/>
      <site name="imu" pos="0 0 0.05"/>
      <site name="torso_marker" pos="0.1 0 0"/>
      <body name="thigh" pos="0 0 -0.1">
        <joint name="hip" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03"/>
        <site name="knee_marker" pos="0 0 -0.3"/>
        <body name="shin" pos="0 0 -0.3">
          <joint name="knee" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03"/>
          <site name="foot_ft" pos="0 0 -0.3"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="hip_motor" joint="hip"/>
    <motor name="knee_motor" joint="knee"/>
  </actuator>
</mujoco>
"""

SAMPLE_CONFIG = """\
model = "walker.xml"
description = "the test walker in a mocap room"

[streams.mocap_torso]
type = "pose"
topic = "/mocap/torso"
body = "torso"
noise = { position_std_m = 0.0005 }

[streams.tf_torso]
type = "tf"
topic = "/tf"
child_frame_id = "torso_link"
body = "torso"

[streams.tf_shin]
type = "tf"
topic = "/tf"
child_frame_id = "shin_link"
body = "shin"
required = false

[streams.rigid]
type = "rigid_bodies"
topic = "/mocap/rigid_bodies"
bodies = { Torso = "torso", Shin = "shin" }

[streams.markers]
type = "markers"
topic = "/mocap/markers"
markers = { "7" = "torso_marker", knee = "knee_marker" }

[streams.imu]
type = "imu"
topic = "/imu"
site = "imu"

[streams.joints]
type = "joint_state"
topic = "/joint_states"
joints = { knee_joint = "knee", hip_joint = "hip" }

[streams.command]
type = "command"
topic = "/joint_commands"
actuators = ["hip_motor", "knee_motor"]

[streams.trajectory]
type = "command"
topic = "/joint_trajectory"
actuators = { knee_joint = "knee_motor", hip_joint = "hip_motor" }
field = "effort"
required = false

[streams.foot_ft]
type = "wrench"
topic = "/ft/foot"
site = "foot_ft"
"""

# topic → (type, rate Hz, receive latency ns) of the sample recording
SAMPLE_TOPICS: dict[str, tuple[str, float, int]] = {
    "/mocap/torso": (t.POSE_STAMPED, 200.0, 3_000_000),
    "/tf": (t.TF_MESSAGE, 100.0, 1_000_000),
    "/mocap/rigid_bodies": (t.RIGID_BODIES, 100.0, 3_000_000),
    "/mocap/markers": (t.MARKERS, 100.0, 3_000_000),
    "/imu": (t.IMU, 500.0, 500_000),
    "/joint_states": (t.JOINT_STATE, 500.0, 250_000),
    "/joint_commands": (t.FLOAT64_MULTI_ARRAY, 100.0, 100_000),
    "/joint_trajectory": (t.JOINT_TRAJECTORY, 50.0, 100_000),
    "/ft/foot": (t.WRENCH_STAMPED, 250.0, 400_000),
}


def jitter_ns(k: int) -> int:
    """A deterministic stamp jitter in [-50, 50] µs."""
    return ((k * 7919) % 11 - 5) * 10_000


def unit_quat(a: float) -> np.ndarray:
    """A unit quaternion (w, x, y, z) that turns with a."""
    q = np.array([np.cos(a), 0.3 * np.sin(a), 0.5 * np.sin(a), 0.81 * np.sin(a)])
    return q / np.linalg.norm(q)


def value(topic: str, k: int) -> dict[str, Any]:
    """The k-th message's numbers on each sample topic (what the reader must return)."""
    x = 0.001 * k
    t = k / SAMPLE_TOPICS[topic][1] if topic in SAMPLE_TOPICS else x  # s
    return {
        "pos": np.array([x, 2 * x, 1 + 0.5 * x]),
        "quat": unit_quat(0.01 * k + len(topic)),
        "gyro": np.array([0.1 + x, -0.2, 0.3 * x]),
        "accel": np.array([0.0, 0.1 * x, 9.81]),
        "q": np.array([0.1 + x, -0.2 - x]),  # hip, knee
        "qd": np.array([1.0 + x, -1.0]),
        "tau": np.array([2.0 * t, -2.0]),  # in time: commands and efforts agree
        "force": np.array([1.0, 2.0 + x, 300.0]),
        "torque": np.array([0.1, -0.1 * x, 0.0]),
    }


def sample_stamp(topic: str, k: int) -> int:
    _, rate, _ = SAMPLE_TOPICS[topic]
    return T0 + round(k * NS / rate) + jitter_ns(k)


def sample_log_time(topic: str, k: int) -> int:
    return sample_stamp(topic, k) + SAMPLE_TOPICS[topic][2]


def sample_message(topic: str, k: int) -> Msg:
    """The k-th message of a sample topic."""
    msg_type = SAMPLE_TOPICS[topic][0]
    s, v = sample_stamp(topic, k), value(topic, k)
    if topic == "/mocap/torso":
        fields = pose_stamped(s, v["pos"], v["quat"])
    elif topic == "/tf":
        fields = tf_message(
            [
                transform_stamped(s, "torso_link", v["pos"], v["quat"]),
                transform_stamped(s, "shin_link", v["pos"] + 1.0, v["quat"]),
                transform_stamped(s, "camera_link", v["pos"] - 1.0, v["quat"]),
            ]
        )
    elif topic == "/mocap/rigid_bodies":
        fields = rigid_bodies(
            s, {"Shin": (v["pos"] + 1.0, v["quat"]), "Torso": (v["pos"], v["quat"])}
        )
    elif topic == "/mocap/markers":
        fields = markers(
            s,
            [
                (USE_NAME, 0, "knee", v["pos"] + 2.0),
                (USE_INDEX, 7, "", v["pos"]),
                (USE_INDEX, 9, "", v["pos"] - 2.0),
            ],
        )
    elif topic == "/imu":
        fields = imu(s, v["gyro"], v["accel"], v["quat"])
    elif topic == "/joint_states":  # other order than the config, plus a joint it does not map
        fields = joint_state(
            s,
            ["knee_joint", "finger", "hip_joint"],
            [v["q"][1], 0.5, v["q"][0]],
            [v["qd"][1], 0.0, v["qd"][0]],
            [v["tau"][1], 0.0, v["tau"][0]],
        )
    elif topic == "/joint_commands":
        fields = float64_multi_array(v["tau"])
    elif topic == "/joint_trajectory":
        fields = joint_trajectory(
            s, ["hip_joint", "knee_joint"], effort=v["tau"], time_from_start_ns=1_000_000
        )
    else:
        fields = wrench_stamped(s, v["force"], v["torque"])
    return Msg(topic, msg_type, sample_log_time(topic, k), fields)


def sample_counts(duration_s: float) -> dict[str, int]:
    return {topic: int(rate * duration_s) for topic, (_, rate, _) in SAMPLE_TOPICS.items()}


def sample_recording(duration_s: float = 0.5, topics: Iterable[str] | None = None) -> list[Msg]:
    """Every sample topic for `duration_s`, in receive (log time) order like a recorder."""
    counts = sample_counts(duration_s)
    chosen = list(topics) if topics is not None else list(SAMPLE_TOPICS)
    msgs = [sample_message(topic, k) for topic in chosen for k in range(counts[topic])]
    return sorted(msgs, key=lambda m: m.log_time_ns)


def write_robot(folder: Path, config_text: str = SAMPLE_CONFIG) -> Path:
    """`walker.xml` and `config.toml` in folder; returns the config path."""
    (folder / "walker.xml").write_text(ROBOT_XML)
    path = folder / "config.toml"
    path.write_text(config_text)
    return path


# -- a recording with injected bad samples ------------------------------------------------------
def _replace(msg: Msg, fields: dict[str, Any]) -> Msg:
    return Msg(msg.topic, msg.msg_type, msg.log_time_ns, fields)


def bad_sample_recording(duration_s: float = 0.5) -> list[Msg]:
    """The sample recording with bad messages injected at fixed places (see BAD_COUNTS)."""
    counts = sample_counts(duration_s)
    out = []
    for topic in SAMPLE_TOPICS:
        for k in range(counts[topic]):
            m = sample_message(topic, k)
            v = value(topic, k)
            if topic == "/mocap/torso" and k == 10:  # NaN position
                m = _replace(m, pose_stamped(sample_stamp(topic, k), [np.nan, 0, 0], v["quat"]))
            elif topic == "/mocap/torso" and k == 20:  # the stamp of message 19 again
                m = _replace(m, pose_stamped(sample_stamp(topic, 19), v["pos"], v["quat"]))
            elif topic == "/mocap/torso" and k == 30:  # a stamp before message 29's
                m = _replace(m, pose_stamped(sample_stamp(topic, 28), v["pos"], v["quat"]))
            elif topic == "/imu" and k == 5:  # Inf acceleration
                m = _replace(m, imu(sample_stamp(topic, k), v["gyro"], [0, np.inf, 0], v["quat"]))
            elif topic == "/joint_states" and k == 3:  # 3 names, 2 velocities
                f = dict(m.fields, velocity=[1.0, 2.0])
                m = _replace(m, f)
            elif topic == "/joint_states" and k == 4:  # none of the mapped joints
                m = _replace(m, joint_state(sample_stamp(topic, k), ["a", "b"], [1.0, 2.0]))
            elif topic == "/joint_states" and k == 6:  # NaN in a joint the config does not map
                f = dict(m.fields, position=[v["q"][1], np.nan, v["q"][0]])
                m = _replace(m, f)
            elif topic == "/joint_commands" and k == 7:  # 3 values for 2 actuators
                m = _replace(m, float64_multi_array([1.0, 2.0, 3.0]))
            out.append(m)
    return sorted(out, key=lambda m: m.log_time_ns)


# (stream, reason) → count of the injected bad samples, per config stream
BAD_STREAM_COUNTS = {
    "mocap_torso": {"nan": 1, "duplicate_time": 1, "backwards_time": 1},
    "imu": {"nan": 1},
    "joints": {"wrong_length": 1, "unknown_name": 1},
    "command": {"wrong_length": 1},
}
# per topic, from the messages alone (no config): the NaN in the unmapped joint counts, the
# unmapped names and the array length of a Float64MultiArray do not
BAD_TOPIC_COUNTS = {
    "/mocap/torso": {"nan": 1, "duplicate_time": 1, "backwards_time": 1},
    "/imu": {"nan": 1},
    "/joint_states": {"wrong_length": 1, "nan": 1},
}
# (topic, k) of the messages a stream skips
BAD_SKIPPED = {
    "mocap_torso": {10, 20, 30},
    "imu": {5},
    "joints": {3, 4},
    "command": {7},
}


def corrupt_string_length(data: bytes, marker: str) -> bytes:
    """Overwrite the CDR length in front of the string `marker` (an uncompressed log).

    The chunk's CRC is computed anew, as if the writer had serialized a bad message: the
    damage is in the message, for the decoder to find, not in the file.
    """
    raw = marker.encode() + b"\x00"
    at = data.index(raw)
    assert data.count(raw) == 1, "marker must occur once"
    out = bytearray(data[: at - 4] + b"\xff\xff\xff\x7f" + data[at:])
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    (chunk,) = [
        c
        for c in summary.chunk_indexes
        if c.chunk_start_offset < at < c.chunk_start_offset + c.chunk_length
    ]
    assert chunk.compression == ""
    # chunk record: opcode, length, start, end, uncompressed size, CRC, "" (4), data length, data
    crc_at, data_at = chunk.chunk_start_offset + 33, chunk.chunk_start_offset + 49
    out[crc_at : crc_at + 4] = struct.pack(
        "<I", zlib.crc32(out[data_at : data_at + chunk.compressed_size])
    )
    return bytes(out)
