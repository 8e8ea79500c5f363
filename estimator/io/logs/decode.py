"""Decoded ROS 2 messages → numpy `Record`s, one function per message type.

The CDR bytes are decoded by mcap_ros2 (from the schema text in the log); these functions
only read the decoded fields, so they accept any object with the ROS field names (mcap_ros2's
dynamic classes, rosbags' dataclasses). Conventions of the result:

- times are int64 nanoseconds: `header.stamp.sec * 1e9 + header.stamp.nanosec`;
- quaternions are (w, x, y, z) (ROS messages store x, y, z, w);
- a message that cannot be used raises `BadSampleError` with the counter it belongs to.

Every record has `names` (one per entry: a joint, a rigid body, a marker, a TF child frame,
an array index) and `values` of shape (n_entries, K), where K and the component order
depend on the message family (`COMPONENTS`). `present` marks the fields the message
actually carries (an empty JointState.velocity, an IMU orientation whose covariance[0] is
-1); the values of absent fields are NaN.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.io.logs import ros2_types as t

POSE = ("px", "py", "pz", "qw", "qx", "qy", "qz")
POINT = ("px", "py", "pz")
IMU = ("qw", "qx", "qy", "qz", "wx", "wy", "wz", "ax", "ay", "az")
JOINT = ("position", "velocity", "effort")
TRAJECTORY = ("positions", "velocities", "accelerations", "effort")
SCALAR = ("value",)
WRENCH = ("fx", "fy", "fz", "tx", "ty", "tz")

# Component names of each message type's record values (the K axis).
COMPONENTS: Mapping[str, tuple[str, ...]] = {
    t.POSE_STAMPED: POSE,
    t.TRANSFORM_STAMPED: POSE,
    t.TF_MESSAGE: POSE,
    t.RIGID_BODIES: POSE,
    t.MARKERS: POINT,
    t.IMU: IMU,
    t.JOINT_STATE: JOINT,
    t.FLOAT64_MULTI_ARRAY: SCALAR,
    t.JOINT_TRAJECTORY: TRAJECTORY,
    t.WRENCH_STAMPED: WRENCH,
}


class BadSampleError(Exception):
    """A message that cannot be used; `reason` is a `BadSampleCounts` field name."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(detail or reason)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Record:
    """One time-stamped group of entries from a message.

    stamp_ns: header.stamp in ns, None for a message type without a header.
    delay_ns: how long after the stamp the entries apply (JointTrajectory time_from_start).
    frame_id: header.frame_id, the frame the values are expressed in ('' without header).
    names: (n,) entry names.
    values: (n, K) float64, components as in `COMPONENTS[type]`.
    present: (n, K) bool, which fields the message carries; None means all.
    """

    stamp_ns: int | None
    frame_id: str
    names: tuple[str, ...]
    values: np.ndarray
    present: np.ndarray | None = None
    delay_ns: int = 0


def stamp_ns(header: Any) -> int:
    """`std_msgs/Header.stamp` in int nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose_row(position: Any, orientation: Any) -> list[float]:
    """(x, y, z, qw, qx, qy, qz) from a Point/Vector3 and an (x, y, z, w) Quaternion."""
    q = orientation
    return [position.x, position.y, position.z, q.w, q.x, q.y, q.z]


def _array(row: list[float] | list[list[float]]) -> np.ndarray:
    return np.array(row, dtype=np.float64, ndmin=2)


def decode_pose_stamped(msg: Any) -> tuple[Record, ...]:
    """geometry_msgs/PoseStamped → one entry (''), values (1, 7) POSE."""
    row = _pose_row(msg.pose.position, msg.pose.orientation)
    return (Record(stamp_ns(msg.header), msg.header.frame_id, ("",), _array(row)),)


def decode_transform_stamped(msg: Any) -> tuple[Record, ...]:
    """geometry_msgs/TransformStamped → one entry named child_frame_id, values (1, 7) POSE."""
    tr = msg.transform
    row = _pose_row(tr.translation, tr.rotation)
    return (Record(stamp_ns(msg.header), msg.header.frame_id, (msg.child_frame_id,), _array(row)),)


def decode_tf_message(msg: Any) -> tuple[Record, ...]:
    """tf2_msgs/TFMessage → one record per transform (each has its own stamp)."""
    return tuple(r for tr in msg.transforms for r in decode_transform_stamped(tr))


def decode_rigid_bodies(msg: Any) -> tuple[Record, ...]:
    """mocap4r2_msgs/RigidBodies → entries named rigid_body_name, values (n, 7) POSE."""
    bodies = msg.rigidbodies
    names = tuple(b.rigid_body_name for b in bodies)
    rows = [_pose_row(b.pose.position, b.pose.orientation) for b in bodies]
    values = _array(rows) if rows else np.zeros((0, 7))
    return (Record(stamp_ns(msg.header), msg.header.frame_id, names, values),)


_USE_NAME, _USE_INDEX, _USE_BOTH = 0, 1, 2


def decode_markers(msg: Any) -> tuple[Record, ...]:
    """mocap4r2_msgs/Markers → entries named by marker, values (n, 3) POINT.

    A marker is named by `marker_name` (id_type USE_NAME), by its `marker_index` as a
    decimal string (USE_INDEX), or both (USE_BOTH: two entries with the same position).
    """
    names: list[str] = []
    rows: list[list[float]] = []
    for m in msg.markers:
        p = m.translation
        keys = {
            _USE_NAME: (m.marker_name,),
            _USE_INDEX: (str(m.marker_index),),
        }.get(int(m.id_type), (m.marker_name, str(m.marker_index)))
        for key in keys:
            names.append(key)
            rows.append([p.x, p.y, p.z])
    values = _array(rows) if rows else np.zeros((0, 3))
    return (Record(stamp_ns(msg.header), msg.header.frame_id, tuple(names), values),)


def decode_imu(msg: Any) -> tuple[Record, ...]:
    """sensor_msgs/Imu → one entry (''), values (1, 10) IMU: quat_wxyz, gyro, accel.

    REP 145: a covariance whose first element is -1 means the field is not provided.
    """
    q, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    row = [q.w, q.x, q.y, q.z, w.x, w.y, w.z, a.x, a.y, a.z]
    present = np.ones((1, 10), dtype=bool)
    for cols, cov in (
        (slice(0, 4), msg.orientation_covariance),
        (slice(4, 7), msg.angular_velocity_covariance),
        (slice(7, 10), msg.linear_acceleration_covariance),
    ):
        if len(cov) and cov[0] == -1.0:
            present[0, cols] = False
    values = _array(row)
    values[~present] = np.nan
    return (Record(stamp_ns(msg.header), msg.header.frame_id, ("",), values, present),)


def _columns(names: tuple[str, ...], fields: list[tuple[str, Any]]) -> tuple[np.ndarray, ...]:
    """Stack per-name arrays into (n, len(fields)) values + presence; empty = not provided."""
    n = len(names)
    values = np.full((n, len(fields)), np.nan)
    present = np.zeros((n, len(fields)), dtype=bool)
    for j, (label, data) in enumerate(fields):
        if len(data) == 0:
            continue
        if len(data) != n:
            raise BadSampleError("wrong_length", f"{n} names but {len(data)} {label}")
        values[:, j] = data
        present[:, j] = True
    return values, present


def decode_joint_state(msg: Any) -> tuple[Record, ...]:
    """sensor_msgs/JointState → entries named by joint, values (n, 3) JOINT.

    position/velocity/effort may each be empty (not provided); otherwise each must have one
    value per name (else `wrong_length`).
    """
    names = tuple(msg.name)
    values, present = _columns(
        names,
        [("positions", msg.position), ("velocities", msg.velocity), ("efforts", msg.effort)],
    )
    return (Record(stamp_ns(msg.header), msg.header.frame_id, names, values, present),)


def decode_float64_multi_array(msg: Any) -> tuple[Record, ...]:
    """std_msgs/Float64MultiArray → entries "0", "1", ..., values (n, 1); no header."""
    data = np.asarray(msg.data, dtype=np.float64).reshape(-1, 1)
    names = tuple(str(i) for i in range(len(data)))
    return (Record(None, "", names, data),)


def decode_joint_trajectory(msg: Any) -> tuple[Record, ...]:
    """trajectory_msgs/JointTrajectory → the first point, entries named by joint, (n, 4).

    The command applies `points[0].time_from_start` after the stamp (`delay_ns`).
    """
    if not msg.points:
        raise BadSampleError("wrong_length", "trajectory without points")
    names = tuple(msg.joint_names)
    p = msg.points[0]
    values, present = _columns(
        names,
        [
            ("positions", p.positions),
            ("velocities", p.velocities),
            ("accelerations", p.accelerations),
            ("efforts", p.effort),
        ],
    )
    delay = int(p.time_from_start.sec) * 1_000_000_000 + int(p.time_from_start.nanosec)
    return (
        Record(stamp_ns(msg.header), msg.header.frame_id, names, values, present, delay_ns=delay),
    )


def decode_wrench_stamped(msg: Any) -> tuple[Record, ...]:
    """geometry_msgs/WrenchStamped → one entry (''), values (1, 6) WRENCH: force, torque."""
    f, tau = msg.wrench.force, msg.wrench.torque
    row = [f.x, f.y, f.z, tau.x, tau.y, tau.z]
    return (Record(stamp_ns(msg.header), msg.header.frame_id, ("",), _array(row)),)


DECODERS: Mapping[str, Callable[[Any], tuple[Record, ...]]] = {
    t.POSE_STAMPED: decode_pose_stamped,
    t.TRANSFORM_STAMPED: decode_transform_stamped,
    t.TF_MESSAGE: decode_tf_message,
    t.RIGID_BODIES: decode_rigid_bodies,
    t.MARKERS: decode_markers,
    t.IMU: decode_imu,
    t.JOINT_STATE: decode_joint_state,
    t.FLOAT64_MULTI_ARRAY: decode_float64_multi_array,
    t.JOINT_TRAJECTORY: decode_joint_trajectory,
    t.WRENCH_STAMPED: decode_wrench_stamped,
}


def non_finite(record: Record) -> bool:
    """Whether any field the message carries is NaN or ±Inf."""
    finite = np.isfinite(record.values)
    if record.present is None:
        return not finite.all()
    return bool((record.present & ~finite).any())
