"""The ROS 2 message types physfuse reads and writes, by stream kind, and their definitions.

Schemas inside an MCAP file carry their own definition text, so reading needs only the type
names below. Writing an MCAP log needs the definitions: `message_definition(type_name)` gives
the rosbag2-style text (the type's `.msg`, then every nested type after a `===` separator)
from rosbags' ROS 2 Jazzy type store, with the mocap4r2 types registered.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
RIGID_BODIES = "mocap4r2_msgs/msg/RigidBodies"
MARKERS = "mocap4r2_msgs/msg/Markers"
IMU = "sensor_msgs/msg/Imu"
JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"

# Message types each stream kind accepts (see estimator.config.KINDS).
ACCEPTED_TYPES: Mapping[str, tuple[str, ...]] = {
    "pose": (POSE_STAMPED, TRANSFORM_STAMPED),
    "tf": (TF_MESSAGE, TRANSFORM_STAMPED),
    "rigid_bodies": (RIGID_BODIES,),
    "markers": (MARKERS,),
    "imu": (IMU,),
    "joint_state": (JOINT_STATE,),
    "command": (FLOAT64_MULTI_ARRAY, JOINT_TRAJECTORY),
    "wrench": (WRENCH_STAMPED,),
}

# mocap4r2_msgs (MOCAP4ROS2-Project/mocap4r2_msgs), which no standard type store ships.
_MOCAP4R2_MSGS = {
    "mocap4r2_msgs/msg/Marker": (
        "int8 USE_NAME=0\nint8 USE_INDEX=1\nint8 USE_BOTH=2\n"
        "int8 id_type\nint32 marker_index\nstring marker_name\n"
        "geometry_msgs/Point translation\n"
    ),
    "mocap4r2_msgs/msg/Markers": (
        "std_msgs/Header header\nuint32 frame_number\nmocap4r2_msgs/Marker[] markers\n"
    ),
    "mocap4r2_msgs/msg/RigidBody": (
        "string rigid_body_name\nmocap4r2_msgs/Marker[] markers\ngeometry_msgs/Pose pose\n"
    ),
    "mocap4r2_msgs/msg/RigidBodies": (
        "std_msgs/Header header\nuint32 frame_number\nmocap4r2_msgs/RigidBody[] rigidbodies\n"
    ),
}


def normalize_type(type_name: str) -> str:
    """`pkg/Type` (ROS 1 style, some writers) → `pkg/msg/Type`; other names unchanged."""
    parts = type_name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return type_name


@cache
def typestore() -> Typestore:
    """rosbags' ROS 2 Jazzy type store with the mocap4r2 messages registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in _MOCAP4R2_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@cache
def message_definition(type_name: str) -> str:
    """The rosbag2 schema text (`ros2msg` encoding) for a message type."""
    text, _ = typestore().generate_msgdef(type_name, ros_version=2)
    return text
