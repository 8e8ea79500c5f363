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
    "contact_flags": (FLOAT64_MULTI_ARRAY,),
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


CONTACT = "physfuse_msgs/msg/Contact"
CONTACT_ARRAY = "physfuse_msgs/msg/ContactArray"

# The definitions in msgs/physfuse_msgs/msg/ (tests check that they match the files).
CONTACT_MSG = """\
# One contact between two geoms over one timestep, from physfuse's ground truth (the
# simulator) or its estimate (the smoother). Impulses follow Todorov 2014 and MuJoCo: they
# are expressed in the contact frame, whose first axis is the contact normal (pointing from
# geom1 toward geom2) and whose other two axes span the tangent plane.

# Algorithm 5 branch of the impulse (the same values as MuJoCo's mjtConstraintState).
uint8 SEPARATING=0   # impulse 0: the contact is opening (tip of the friction cone)
uint8 STICKING=1     # impulse strictly inside the friction cone: no slip
uint8 SLIDING=4      # impulse on the surface of the friction cone: slipping

string body1                            # body of geom1 ("world" for the floor)
string body2                            # body of geom2
string geom1                            # geom names; "#<id>" for an unnamed geom
string geom2
geometry_msgs/Point position            # contact point, world frame [m]
geometry_msgs/Quaternion orientation    # R_world_contact: columns normal, tangent1, tangent2
uint8 dim                               # MuJoCo condim: 1 frictionless, 3 sliding, 4 +torsional,
                                        # 6 +rolling friction
float64[6] impulse                      # contact-frame impulse over the step [N*s, N*m*s]:
                                        # normal, tangent1, tangent2, torsional, rolling1,
                                        # rolling2; entries past dim are 0
float64[6] force                        # impulse / timestep [N, N*m], the same layout
uint8 branch                            # SEPARATING, STICKING or SLIDING
"""

CONTACT_ARRAY_MSG = """\
# Every contact of one timestep. On the body of geom2 the contact applies
#   F_world = R_world_contact * force[0:3]
#   M_world = R_world_contact * (force[3], force[4], force[5])   (torsional, rolling; condim >= 4)
# at `position`, and the opposite wrench on the body of geom1.

std_msgs/Header header                  # stamp: the start of the step; frame_id: "world"
float64 timestep                        # h [s]: impulse = force * timestep
physfuse_msgs/Contact[] contacts
"""

DIAGNOSTIC_EVENT = "physfuse_msgs/msg/DiagnosticEvent"
DIAGNOSTIC_EVENT_MSG = """\
# One event of `physfuse diagnose` (docs/diagnostics.md): where and when the physics does not
# add up. Written on /diagnostics/events beside its DiagnosticArray status on /diagnostics:
# at the event's start (diagnose), at the knot that reported it (stream --diagnose).

# kind
uint8 UNMODELED_CONTACT=0   # a force on `target` (a body) that actuation and the modeled
                            # contacts do not explain: a push, a collision
uint8 MODEL_ERROR=1         # a modeled contact's force off: its normal force (softness,
                            # stiffness or the surface's height; size 1 value) or its whole
                            # force (timing, friction; size 3); target "contact <body>–<geom>";
                            # or a body's mass (component "mass", target the body, size 1)
uint8 SENSOR_FAULT=2        # a stream's residual row that steps; target the stream,
                            # component the row ("gyro z", "FR_hip_joint position")
uint8 SLIP=3                # a modeled contact sliding where the model would hold it (less
                            # friction than the model's); target the body, component
                            # "contact <body>–<what it touches>"

std_msgs/Header header                  # stamp: the event's start; frame_id: "world"
uint8 kind
builtin_interfaces/Time end             # the event's end
builtin_interfaces/Time detected        # when the detector first alarmed
string target
string component
float64[] size                          # UNMODELED_CONTACT: the force on the target, world
                                        # frame [N] (3 values); MODEL_ERROR: the
                                        # normal force error [N] (1), the contact force's,
                                        # world frame (3), or the mass error [kg] (1);
                                        # SENSOR_FAULT: the step in σ of its row (1);
                                        # SLIP: the distance its contact slid [m] (1)
float64[] size_covariance               # of size, row-major (len(size)² values)
float64 score                           # the peak statistic over its threshold (> 1)
string explained_by                     # the sensor fault or slip that explains it
                                        # ("": none)
string[] candidates                     # UNMODELED_CONTACT: the best-fitting bodies, best first
float64[] candidate_likelihood_ratios   # their likelihood ratios
bool ongoing                            # `physfuse stream --diagnose`: the first report, its
                                        # alarm still on (interval and size so far); the final
                                        # report of the same event follows
float64[] point                         # UNMODELED_CONTACT: where on the target the force acts,
                                        # world frame at the event's middle [m] (3 values; none:
                                        # at the target's centre of mass)
"""

PHYSFUSE_MSGS: Mapping[str, str] = {
    CONTACT: CONTACT_MSG,
    CONTACT_ARRAY: CONTACT_ARRAY_MSG,
    DIAGNOSTIC_EVENT: DIAGNOSTIC_EVENT_MSG,
}

_SEPARATOR = "=" * 80


@cache
def typestore() -> Typestore:
    """rosbags' ROS 2 Jazzy type store with the mocap4r2 and physfuse_msgs types registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in {**_MOCAP4R2_MSGS, **PHYSFUSE_MSGS}.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@cache
def message_definition(msg_type: str) -> str:
    """The `ros2msg` schema text of a type, as rosbag2 stores it.

    physfuse_msgs types keep their documented text (comments included); their nested standard
    types follow after `===` separators.
    """
    generated, _ = typestore().generate_msgdef(msg_type, ros_version=2)
    if msg_type not in PHYSFUSE_MSGS:
        return generated
    blocks = generated.split(_SEPARATOR + "\n")
    out = [PHYSFUSE_MSGS[msg_type]]
    for block in blocks[1:]:
        first_line, _, _ = block.partition("\n")
        name = first_line.removeprefix("MSG: ")
        full = normalize_type(name)
        out.append(f"MSG: {name}\n{PHYSFUSE_MSGS[full]}" if full in PHYSFUSE_MSGS else block)
    return f"{_SEPARATOR}\n".join(part if part.endswith("\n") else part + "\n" for part in out)
