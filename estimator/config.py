"""The config that maps a robot log's topics onto the MuJoCo model.

A config is a TOML file (`configs/<name>.toml`). It names the model and, for every stream the
estimator uses, the log topic, how its messages are timed, which model element (body, site,
joint, actuator) each entry belongs to, and the stream's noise. It is validated when loaded:
every error is a `ConfigError` whose message names the file, the key path
(`streams.mocap_torso.body`), the bad value and the allowed values or valid model names.

Schema (see `configs/README.md` for a worked example):

    model = "humanoid"        # bundled model name, or MJCF path (relative to the config file)
    description = "..."       # optional

    [streams.<name>]          # one table per stream; <name> is how results refer to it
    type = "pose"             # pose | tf | rigid_bodies | markers | imu | joint_state |
                              # command | wrench | contact_flags
    topic = "/mocap/torso"    # the log topic
    stamp = "header"          # "header" (header.stamp; default) or "log" (the recorder's
                              # receive time; the only choice for Float64MultiArray)
    time_offset_ns = 0        # t = stamp + time_offset_ns (int64 ns)
    required = true           # a missing required topic is an error (default true)
    noise = { ... }           # per-kind keys below; omitted keys take the defaults
    max_abs = { ax = 160.0 }  # optional: the largest plausible |value| per component (a
                              # sample beyond is skipped, counted `out_of_bounds`); defaults
                              # in estimator/io/logs/samples.py: BOUNDS (10 km, 1000 rad/s, …)

    type-specific keys:
      pose          body = "torso" | site = "torso_marker"   (PoseStamped, TransformStamped)
      tf            child_frame_id = "torso_link", body | site, parent_frame_id = "world"
                    (optional filter)                       (TFMessage, TransformStamped)
      rigid_bodies  bodies = { rigid_body_name = "body", ... }   (mocap4r2 RigidBodies)
      markers       markers = { marker_name_or_index = "site", ... }   (mocap4r2 Markers)
      imu           site = "imu", quat_site_sensor = [w, x, y, z]  (IMU axes in the site
                    frame; default identity), accel_range [m/s²], gyro_range [rad/s] (the
                    measurement range per sensor axis, optional: a sample at or beyond it
                    is saturated and left out)                (sensor_msgs/Imu)
      joint_state   joints = "model" (message names are model joint names) or
                    joints = { ros_name = "model_joint", ... }   (sensor_msgs/JointState);
                    use = ["position", "effort"] (default; "velocity" too to fit the
                    encoders' velocities; efforts are the known force where no command
                    drives the joint)
      command       actuators = ["a0", "a1", ...]  (Float64MultiArray: data[i] drives a_i), or
                    actuators = "model" (data[i] drives the model's actuator i; with field,
                    JointTrajectory joint names are the actuators' joints), or
                    actuators = { ros_joint = "actuator", ... } with
                    field = "positions" | "velocities" | "accelerations" | "effort"
                    (JointTrajectory: the first point's field)
      wrench        site = "ft_site", quat_site_sensor = [w, x, y, z]   (WrenchStamped)
      contact_flags bodies = ["foot_body", ...] or geoms = ["foot_geom", ...]: data[i] of a
                    Float64MultiArray says whether foot i touches (≥ 0.5) or not (stamp
                    "log"); a foot flagged off carries no contact force, one flagged on does
                    not slip (`estimator/factors/contact_flags.py`)

    Mountings without editing the model: pose, tf, imu and wrench streams take
    mount = { pos = [x, y, z], quat = [w, x, y, z] }, the sensor's (marker's, rigid body's)
    pose in the frame of its body or site; imu and wrench also take body = "<body>" instead of
    a site (mounted at the body's origin unless mount says otherwise). The model gets a site
    `physfuse/<stream>/mount` there.

Noise keys per kind (standard deviations per sample unless named a walk; SI units, joint
quantities in the joint's own units, rad or m):

    pose, tf, rigid_bodies   position_std_m, orientation_std_rad
    markers                  position_std_m
    imu                      gyro_std [rad/s], accel_std [m/s²], orientation_std_rad,
                             gyro_bias_walk [rad/s/√s], accel_bias_walk [m/s²/√s]
    joint_state              position_std, velocity_std, effort_std
    command                  std [actuator ctrl units]
    wrench                   force_std [N], torque_std [N·m], force_bias_std [N],
                             torque_bias_std [N·m] (the offset's prior), force_bias_walk
                             [N/√s], torque_bias_walk [N·m/√s]
    contact_flags            force_std [N] (a foot flagged off), slip_std [m/s] (on)

Each stream is resolved to `elements` (model names, the output column order) and `sources`
(the matching names in the messages), so the reader handles every kind the same way.

    [estimator]               # optional: the estimator's settings (estimator/settings.py:
                              # Settings), each key, type and range checked here
    [simulate]                # optional and empty: physfuse reads no settings from it (`physfuse
                              # simulate` takes its options on the command line)

Both come back in `Config.sections`. Other tools may keep their own top-level tables in the
same file: pass their names as `extra_sections` and they come back unvalidated there too.
Whether `physfuse estimate` can run the model and settings at all (friction cone,
integrator, actuators) is `estimator.model_checks.check_for_estimate`.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import mujoco
import numpy as np

from estimator.errors import ConfigError
from estimator.rotations import heading
from physics.errors import PhysicsError
from physics.model import MODEL_DIR, bundled_models, load_model

KINDS = (
    "pose",
    "tf",
    "rigid_bodies",
    "markers",
    "imu",
    "joint_state",
    "command",
    "wrench",
    "contact_flags",
)
MOCAP_KINDS = ("pose", "tf", "rigid_bodies", "markers")  # world-frame poses and positions
STAMPS = ("header", "log")
TRAJECTORY_FIELDS = ("positions", "velocities", "accelerations", "effort")
JOINT_FIELDS = ("position", "velocity", "effort")  # what a joint_state stream can `use`
ARRAY_KINDS = ("command", "contact_flags")  # read from Float64MultiArray, which has no header

# Noise keys and their defaults, per kind.
NOISE_DEFAULTS: Mapping[str, Mapping[str, float]] = {
    "pose": {"position_std_m": 1e-3, "orientation_std_rad": 1e-2},
    "tf": {"position_std_m": 1e-3, "orientation_std_rad": 1e-2},
    "rigid_bodies": {"position_std_m": 1e-3, "orientation_std_rad": 1e-2},
    "markers": {"position_std_m": 1e-3},
    "imu": {
        "gyro_std": 5e-3,
        "accel_std": 5e-2,
        "orientation_std_rad": 2e-2,
        "gyro_bias_walk": 1e-4,
        "accel_bias_walk": 1e-3,
    },
    "joint_state": {"position_std": 1e-3, "velocity_std": 1e-2, "effort_std": 1e-1},
    "command": {"std": 1e-2},
    "wrench": {
        "force_std": 1.0,
        "torque_std": 0.05,
        "force_bias_std": 2.0,  # F/T sensors drift off zero: a bias state, like the IMU's
        "torque_bias_std": 0.1,
        "force_bias_walk": 0.01,
        "torque_bias_walk": 5e-4,
    },
    "contact_flags": {"force_std": 5.0, "slip_std": 0.05},
}

_COMMON_KEYS = ("type", "topic", "stamp", "time_offset_ns", "required", "noise", "max_abs")
_KIND_KEYS: Mapping[str, tuple[str, ...]] = {
    "pose": ("body", "site", "mount"),
    "tf": ("child_frame_id", "parent_frame_id", "body", "site", "mount"),
    "rigid_bodies": ("bodies",),
    "markers": ("markers",),
    "imu": ("site", "body", "quat_site_sensor", "accel_range", "gyro_range", "mount"),
    "joint_state": ("joints", "use"),
    "command": ("actuators", "field"),
    "wrench": ("site", "body", "quat_site_sensor", "mount"),
    "contact_flags": ("bodies", "geoms"),
}
_TOP_KEYS = ("model", "description", "start_pose", "streams")
_START_POSE_KEYS = ("x", "y", "yaw_deg")
SECTIONS = ("estimator", "simulate")  # tables of physfuse's own, validated on loading
_IDENTITY_WXYZ = (1.0, 0.0, 0.0, 0.0)
_MAX_OFFSET_NS = 10**15

_OBJ_TYPES: Mapping[str, int] = {
    "body": mujoco.mjtObj.mjOBJ_BODY,
    "site": mujoco.mjtObj.mjOBJ_SITE,
    "joint": mujoco.mjtObj.mjOBJ_JOINT,
    "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR,
    "geom": mujoco.mjtObj.mjOBJ_GEOM,
}


@dataclass(frozen=True)
class Mount:
    """Where a sensor sits on the model without editing it: a site `site` added to the model at
    `pos`, `quat_wxyz` in the frame of the body or site `parent` (of `parent_type`)."""

    site: str
    parent_type: str  # "body" | "site"
    parent: str
    pos: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]

    def add_to(self, spec: mujoco.MjSpec, model: mujoco.MjModel) -> None:
        """Add the mount's site to `spec` (`model`: the same model compiled, for a site
        parent's resolved pose): on the parent body, at the parent's pose ∘ the mount's."""
        pos, quat = np.array(self.pos), np.array(self.quat_wxyz)
        if self.parent_type == "site":
            i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, self.parent)
            body = int(model.site_bodyid[i])
            rotated, composed = np.zeros(3), np.zeros(4)
            mujoco.mju_rotVecQuat(rotated, pos, model.site_quat[i])
            mujoco.mju_mulQuat(composed, model.site_quat[i], quat)
            pos, quat = model.site_pos[i] + rotated, composed
            parent = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or "world"
        else:
            parent = self.parent
        site = (spec.worldbody if parent == "world" else spec.body(parent)).add_site()
        site.name, site.pos, site.quat = self.site, pos, quat


@dataclass(frozen=True)
class StreamConfig:
    """One stream: a topic, how it is timed, and the model elements its entries belong to.

    `elements[i]` (a model `element_type` name) is fed by the message entry named
    `sources[i]`: a joint name in a JointState, a rigid-body name, a marker name or index, a
    TF child frame, or the array index ("0", "1", ...) in a Float64MultiArray. `sources` is
    None for kinds whose message holds a single entry (pose, imu, wrench).
    """

    name: str
    kind: str
    topic: str
    stamp: str
    time_offset_ns: int
    required: bool
    element_type: str
    elements: tuple[str, ...]
    sources: tuple[str, ...] | None
    element_keys: tuple[str, ...]  # the config key path that names each element
    noise: Mapping[str, float]
    quat_site_sensor: tuple[float, float, float, float] = _IDENTITY_WXYZ
    field: str | None = None  # command from JointTrajectory: which point field
    use: tuple[str, ...] = ("position", "effort")  # joint_state: the JointState fields used
    # imu: the measurement range per sensor axis (a sample at or beyond it is saturated)
    accel_range: float = math.inf  # m/s²
    gyro_range: float = math.inf  # rad/s
    parent_frame_id: str | None = None  # tf: accept only transforms from this frame
    # where the sensor sits when the config mounts it: `elements` is then its added site
    mount: Mount | None = None
    # component → the largest plausible |value| (over the reader's defaults, `BOUNDS`)
    max_abs: Mapping[str, float] = dataclasses.field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True)
class Config:
    """A loaded, validated config. `streams` keeps the file's order."""

    path: Path
    model: str
    model_path: Path
    description: str
    streams: Mapping[str, StreamConfig]
    sections: Mapping[str, Any] = field(default_factory=dict)
    # a free base's start x [m], y [m] and yaw [rad] (`start_pose`): its home keyframe's
    start_pose: tuple[float, float, float] | None = None

    @property
    def model_ref(self) -> str:
        """The model as a program without this config finds it (an estimate's metadata): a
        bundled model's name, or the MJCF file's absolute path (`model` is relative to the
        config's folder)."""
        if not self.model.endswith(".xml") and "/" not in self.model:
            return self.model
        return str(self.model_path.resolve())

    def load_model(self) -> mujoco.MjModel:
        """The MuJoCo model the config maps onto, with the sites of its mounts and its home
        keyframe at the start pose."""
        if not any(s.mount for s in self.streams.values()) and self.start_pose is None:
            return load_model(self.model_path)
        return self.model_spec().compile()

    def model_spec(self) -> mujoco.MjSpec:
        """The model as an MjSpec, with one site per mounted stream (`Mount`) and, with a
        start pose, the home keyframe's free base there (roll, pitch and height kept)."""
        spec = mujoco.MjSpec.from_file(str(self.model_path))
        if self.start_pose is not None:
            _set_start_pose(spec, load_model(self.model_path), self.start_pose)
        mounts = [(s.element_keys[0], s.mount) for s in self.streams.values() if s.mount]
        if mounts:
            model = load_model(self.model_path)
            for key, mount in mounts:
                # a parent the model lacks (loaded without check_names): one line, not a crash
                if mujoco.mj_name2id(model, _OBJ_TYPES[mount.parent_type], mount.parent) < 0:
                    valid = ", ".join(n for n in _names(model, mount.parent_type) if n)
                    raise ConfigError(
                        f"{self.path}: {key}: unknown {mount.parent_type} {mount.parent!r}; "
                        f"valid {mount.parent_type} names: {valid}"
                    )
                mount.add_to(spec, model)
        return spec

    def starting_at(self, x: float, y: float, yaw_deg: float) -> Config:
        """This config with start_pose = { x, y, yaw_deg } (`physfuse estimate --start-pose`)."""
        raw = {"x": x, "y": y, "yaw_deg": yaw_deg}
        parser = _Parser(self.path, (), False)
        start = parser.start_pose(raw, load_model(self.model_path))
        return dataclasses.replace(self, start_pose=start)

    def streams_on(self, topic: str) -> tuple[StreamConfig, ...]:
        """The streams fed by `topic` (several streams may share one, e.g. /tf)."""
        return tuple(s for s in self.streams.values() if s.topic == topic)

    @property
    def topics(self) -> tuple[str, ...]:
        """Every topic a stream reads, in stream order, without repeats."""
        return tuple(dict.fromkeys(s.topic for s in self.streams.values()))


@dataclass(frozen=True)
class NameCheck:
    """Whether one model name a config uses exists in the model."""

    key: str  # config key path, e.g. "streams.joints.joints.l_knee"
    element_type: str  # "body" | "site" | "joint" | "actuator"
    name: str
    found: bool
    valid: tuple[str, ...]  # the names the model has for that element type


def _set_start_pose(
    spec: mujoco.MjSpec, model: mujoco.MjModel, start: tuple[float, float, float]
) -> None:
    """The home keyframe (added from qpos0 where the model has none) with its first free
    joint at x, y and heading yaw: q ← R_z(yaw − yaw_home) ⊗ q_home."""
    j = next(j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
    adr = int(model.jnt_qposadr[j])
    key = next((k for k in spec.keys if k.name == "home"), None)
    qpos = np.array(key.qpos if key is not None and len(key.qpos) else model.qpos0, float)
    turn = start[2] - float(heading(qpos[adr + 3 : adr + 7]))
    quat = np.empty(4)
    mujoco.mju_mulQuat(
        quat, np.array([math.cos(turn / 2), 0, 0, math.sin(turn / 2)]), qpos[adr + 3 : adr + 7]
    )
    qpos[adr : adr + 2] = start[:2]
    qpos[adr + 3 : adr + 7] = quat
    if key is None:
        key = spec.add_key(name="home")
    key.qpos = qpos


def load_config(
    path: str | Path,
    *,
    extra_sections: Iterable[str] = (),
    check_names: bool = True,
) -> Config:
    """Load and validate a config file.

    `extra_sections`: top-level tables owned by other tools, returned raw in
    `Config.sections` (the [estimator] and [simulate] tables need not be named: they are
    always read, and validated). With `check_names` (the default) every body, site, joint and
    actuator name must exist in the model; `physfuse inspect` turns it off to list them with
    `check_model_names` instead.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from err
    return _Parser(path, tuple(extra_sections), check_names).parse(raw)


def check_model_names(config: Config, model: mujoco.MjModel) -> tuple[NameCheck, ...]:
    """One `NameCheck` per model name the config's streams use, in stream order."""
    valid = {kind: _names(model, kind) for kind in _OBJ_TYPES}
    valid["joint"] = _scalar_joints(model)  # a JointState reports hinge and slide joints
    checks = []
    for stream in config.streams.values():
        if stream.mount is not None:  # its site is added to the model: check what it is on
            mount = stream.mount
            names = valid[mount.parent_type]
            (key,) = stream.element_keys
            checks.append(
                NameCheck(key, mount.parent_type, mount.parent, mount.parent in names, names)
            )
            continue
        names = valid[stream.element_type]
        for key, name in zip(stream.element_keys, stream.elements, strict=True):
            checks.append(NameCheck(key, stream.element_type, name, name in names, names))
    return tuple(checks)


def _names(model: mujoco.MjModel, element_type: str) -> tuple[str, ...]:
    count = {
        "body": model.nbody,
        "site": model.nsite,
        "joint": model.njnt,
        "actuator": model.nu,
        "geom": model.ngeom,
    }[element_type]
    obj = _OBJ_TYPES[element_type]
    return tuple(mujoco.mj_id2name(model, obj, i) or "" for i in range(count))


def _scalar_joints(model: mujoco.MjModel) -> tuple[str, ...]:
    """Hinge and slide joints: the ones a JointState can report."""
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    return tuple(
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, i) or ""
        for i in range(model.njnt)
        if int(model.jnt_type[i]) in scalar
    )


class _Parser:
    """Validates the raw TOML tree; every error names the file and the key path."""

    def __init__(self, path: Path, extra_sections: tuple[str, ...], check_names: bool):
        self.path = path
        self.extra_sections = extra_sections
        self.check_names = check_names

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.path}: {key}: {message}")

    # -- top level -------------------------------------------------------------------------
    def parse(self, raw: dict[str, Any]) -> Config:
        extra = tuple(name for name in self.extra_sections if name not in SECTIONS)
        self.unknown_keys(raw, "", (*_TOP_KEYS, *SECTIONS, *extra))
        if "model" not in raw:
            raise self.error("model", "missing; name a bundled model or an MJCF file")
        model_value = self.string(raw["model"], "model")
        model_path = self.resolve_model(model_value)
        try:
            model = load_model(model_path)
        except PhysicsError as err:
            raise self.error("model", str(err)) from err
        description = self.string(raw.get("description", ""), "description")
        start_pose = self.start_pose(raw["start_pose"], model) if "start_pose" in raw else None
        streams_raw = self.table(raw.get("streams", {}), "streams")
        if not streams_raw:
            raise self.error("streams", "no streams; add at least one [streams.<name>] table")
        streams = {
            name: self.stream(name, self.table(table, f"streams.{name}"), model)
            for name, table in streams_raw.items()
        }
        sections = {name: raw[name] for name in (*SECTIONS, *extra) if name in raw}
        self.table(sections.get("estimator", {}), "estimator")  # its keys: below
        self.simulate(sections.get("simulate", {}))
        config = Config(
            path=self.path,
            model=model_value,
            model_path=model_path,
            description=description,
            streams=MappingProxyType(streams),
            sections=MappingProxyType(sections),
            start_pose=start_pose,
        )
        if self.check_names:
            bad = [c for c in check_model_names(config, model) if not c.found]
            if bad:
                raise ConfigError(
                    f"{self.path}: "
                    + "; ".join(
                        f"{c.key}: unknown {c.element_type} {c.name!r}; valid "
                        f"{c.element_type} names: {', '.join(n for n in c.valid if n)}"
                        for c in bad
                    )
                )
        # every [estimator] key, type and range, now rather than when an estimate starts
        # (estimator.problem imports this module: imported here)
        from estimator.settings import Settings

        Settings.from_config(config)
        return config

    def simulate(self, table: Any) -> None:
        """[simulate]: no physfuse command reads settings from it, so that any key there
        would be ignored without a word; each is an error instead."""
        for key in self.table(table, "simulate"):
            raise self.error(
                f"simulate.{key}",
                "not a setting; physfuse reads no settings from [simulate] (`physfuse "
                "simulate` takes its options on the command line: see physfuse simulate --help): "
                "remove it",
            )

    def resolve_model(self, value: str) -> Path:
        candidate = Path(value)
        if not candidate.is_absolute():
            candidate = self.path.parent / candidate
        if candidate.suffix == ".xml":
            if not candidate.is_file():
                raise self.error("model", f"MJCF file {str(candidate)!r} not found")
            return candidate
        if value in bundled_models():
            return MODEL_DIR / f"{value}.xml"
        raise self.error(
            "model",
            f"{value!r} is neither an MJCF file (*.xml) nor a bundled model; "
            f"bundled models: {', '.join(bundled_models())}",
        )

    # -- one stream ------------------------------------------------------------------------
    def stream(self, name: str, raw: dict[str, Any], model: mujoco.MjModel) -> StreamConfig:
        key = f"streams.{name}"
        if "type" not in raw:
            raise self.error(f"{key}.type", f"missing; one of {', '.join(KINDS)}")
        kind = self.choice(raw["type"], f"{key}.type", KINDS)
        self.unknown_keys(raw, key, (*_COMMON_KEYS, *_KIND_KEYS[kind]))
        if "topic" not in raw:
            raise self.error(f"{key}.topic", "missing; the log topic this stream reads")
        topic = self.string(raw["topic"], f"{key}.topic")
        if not topic:
            raise self.error(f"{key}.topic", "empty topic name")
        offset = raw.get("time_offset_ns", 0)
        if isinstance(offset, bool) or not isinstance(offset, int) or abs(offset) > _MAX_OFFSET_NS:
            raise self.error(
                f"{key}.time_offset_ns",
                f"expected an integer number of ns within ±1e15 (11 days), got {self.show(offset)}",
            )
        required = raw.get("required", True)
        if not isinstance(required, bool):
            raise self.error(
                f"{key}.required", f"expected true or false, got {self.show(required)}"
            )
        noise = self.noise(raw.get("noise", {}), f"{key}.noise", kind)
        max_abs = self.max_abs(raw.get("max_abs", {}), f"{key}.max_abs", kind, raw.get("field"))
        mapping = getattr(self, f"map_{kind}")(raw, key, model)
        mount = self.mount(raw, key, name, kind, mapping)
        if mount is not None:
            mapping |= {"element_type": "site", "elements": (mount.site,), "mount": mount}
        has_header = not (kind in ARRAY_KINDS and mapping.get("field") is None)
        stamp = self.choice(
            raw.get("stamp", "header" if has_header else "log"), f"{key}.stamp", STAMPS
        )
        if stamp == "header" and not has_header:
            raise self.error(
                f"{key}.stamp",
                f"'header' is not possible: a Float64MultiArray {kind} stream has no header; use "
                "'log'",
            )
        return StreamConfig(
            name=name,
            kind=kind,
            topic=topic,
            stamp=stamp,
            time_offset_ns=offset,
            required=required,
            noise=MappingProxyType(noise),
            max_abs=MappingProxyType(max_abs),
            **mapping,
        )

    def map_pose(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        return self.body_or_site(raw, key) | {"sources": None}

    def map_tf(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        if "child_frame_id" not in raw:
            raise self.error(f"{key}.child_frame_id", "missing; the TF frame that tracks the body")
        child = self.string(raw["child_frame_id"], f"{key}.child_frame_id")
        parent = raw.get("parent_frame_id")
        if parent is not None:
            parent = self.string(parent, f"{key}.parent_frame_id")
        return self.body_or_site(raw, key) | {"sources": (child,), "parent_frame_id": parent}

    def map_rigid_bodies(
        self, raw: dict[str, Any], key: str, model: mujoco.MjModel
    ) -> dict[str, Any]:
        return self.name_table(raw, key, "bodies", "body", "rigid body name")

    def map_markers(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        return self.name_table(raw, key, "markers", "site", "marker name or index")

    def map_imu(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        ranges = {}
        for name in ("accel_range", "gyro_range"):
            value = raw.get(name, math.inf)
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or math.isnan(value) or value <= 0:
                raise self.error(
                    f"{key}.{name}", f"expected a positive number, got {self.show(value)}"
                )
            ranges[name] = float(value)
        return self.sensor_site(raw, key) | ranges

    def map_wrench(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        return self.sensor_site(raw, key)

    def map_joint_state(
        self, raw: dict[str, Any], key: str, model: mujoco.MjModel
    ) -> dict[str, Any]:
        joints = raw.get("joints")
        if joints == "model":
            names = _scalar_joints(model)
            if not names:
                raise self.error(f"{key}.joints", "the model has no hinge or slide joints")
            return {
                "element_type": "joint",
                "elements": names,
                "sources": names,
                "element_keys": tuple(f"{key}.joints" for _ in names),
            } | self.use(raw, key)
        if isinstance(joints, str):
            raise self.error(
                f"{key}.joints",
                f'expected "model" or a table {{ ros_name = "model_joint" }}, got {joints!r}',
            )
        return self.name_table(raw, key, "joints", "joint", "JointState name") | self.use(raw, key)

    def use(self, raw: dict[str, Any], key: str) -> dict[str, Any]:
        """joint_state `use`: the JointState fields the estimator fits, a list of JOINT_FIELDS."""
        value = raw.get("use", ["position", "effort"])
        if not isinstance(value, list) or not value:
            raise self.error(
                f"{key}.use",
                f"expected a non-empty list of {', '.join(JOINT_FIELDS)}, got {self.show(value)}",
            )
        fields = tuple(self.choice(v, f"{key}.use[{i}]", JOINT_FIELDS) for i, v in enumerate(value))
        return {"use": fields}

    def map_contact_flags(
        self, raw: dict[str, Any], key: str, model: mujoco.MjModel
    ) -> dict[str, Any]:
        given = [k for k in ("bodies", "geoms") if k in raw]
        if len(given) != 1:
            raise self.error(
                f"{key}.bodies",
                'give one of bodies = ["foot_body", ...] or geoms = ["foot_geom", ...]: '
                "data[i] of the flags' Float64MultiArray is foot i",
            )
        (table_key,) = given
        feet = raw[table_key]
        if not isinstance(feet, list) or not feet:
            raise self.error(
                f"{key}.{table_key}", f"expected a non-empty list of names, got {self.show(feet)}"
            )
        names = tuple(self.string(f, f"{key}.{table_key}[{i}]") for i, f in enumerate(feet))
        return {
            "element_type": "body" if table_key == "bodies" else "geom",
            "elements": names,
            "sources": tuple(str(i) for i in range(len(names))),
            "element_keys": tuple(f"{key}.{table_key}[{i}]" for i in range(len(names))),
        }

    def map_command(self, raw: dict[str, Any], key: str, model: mujoco.MjModel) -> dict[str, Any]:
        actuators = raw.get("actuators")
        if actuators is None:
            raise self.error(
                f"{key}.actuators",
                "missing; a list of actuator names (Float64MultiArray) or a table "
                '{ ros_joint = "actuator" } (JointTrajectory)',
            )
        if actuators == "model":
            return self.model_actuators(raw, key, model)
        if isinstance(actuators, str):
            raise self.error(
                f"{key}.actuators",
                f'expected "model", a list of actuator names or a table {{ ros_joint = '
                f'"actuator" }}, got {actuators!r}',
            )
        if isinstance(actuators, list):
            if "field" in raw:
                raise self.error(
                    f"{key}.field",
                    "only for JointTrajectory commands (actuators given as a table); "
                    "a Float64MultiArray's data drives the actuators directly",
                )
            if not actuators:
                raise self.error(f"{key}.actuators", "empty list")
            names = tuple(self.string(a, f"{key}.actuators[{i}]") for i, a in enumerate(actuators))
            return {
                "element_type": "actuator",
                "elements": names,
                "sources": tuple(str(i) for i in range(len(names))),
                "element_keys": tuple(f"{key}.actuators[{i}]" for i in range(len(names))),
                "field": None,
            }
        if "field" not in raw:
            raise self.error(
                f"{key}.field",
                "missing; a JointTrajectory command needs the point field that drives the "
                f"actuators: one of {', '.join(TRAJECTORY_FIELDS)}",
            )
        trajectory_field = self.choice(raw["field"], f"{key}.field", TRAJECTORY_FIELDS)
        return self.name_table(raw, key, "actuators", "actuator", "JointTrajectory joint name") | {
            "field": trajectory_field
        }

    def model_actuators(
        self, raw: dict[str, Any], key: str, model: mujoco.MjModel
    ) -> dict[str, Any]:
        """actuators = "model": a Float64MultiArray's data[i] drives the model's actuator i; a
        JointTrajectory (with field) drives each actuator through its joint's name."""
        names = tuple(
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or "" for i in range(model.nu)
        )
        if not names:
            raise self.error(f"{key}.actuators", "the model has no actuators")
        if "" in names:
            raise self.error(
                f"{key}.actuators",
                f'"model" needs named actuators; actuator #{names.index("")} has no name',
            )
        keys = tuple(f"{key}.actuators" for _ in names)
        if "field" not in raw:
            sources = tuple(str(i) for i in range(len(names)))
            return {
                "element_type": "actuator",
                "elements": names,
                "sources": sources,
                "element_keys": keys,
                "field": None,
            }
        joints = []
        for i, name in enumerate(names):
            joint = None
            if int(model.actuator_trntype[i]) == mujoco.mjtTrn.mjTRN_JOINT.value:
                joint = mujoco.mj_id2name(
                    model, mujoco.mjtObj.mjOBJ_JOINT, int(model.actuator_trnid[i, 0])
                )
            if not joint:
                raise self.error(
                    f"{key}.actuators",
                    f'"model" with a JointTrajectory maps actuators by their joint; {name!r} '
                    'drives no named joint: give the table { ros_joint = "actuator" }',
                )
            joints.append(joint)
        trajectory_field = self.choice(raw["field"], f"{key}.field", TRAJECTORY_FIELDS)
        return {
            "element_type": "actuator",
            "elements": names,
            "sources": tuple(joints),
            "element_keys": keys,
            "field": trajectory_field,
        }

    # -- shared pieces ---------------------------------------------------------------------
    def body_or_site(self, raw: dict[str, Any], key: str) -> dict[str, Any]:
        given = [k for k in ("body", "site") if k in raw]
        if len(given) != 1:
            raise self.error(
                f"{key}.body",
                'give exactly one of body = "<model body>" or site = "<model site>"',
            )
        element_type = given[0]
        name = self.string(raw[element_type], f"{key}.{element_type}")
        return {
            "element_type": element_type,
            "elements": (name,),
            "element_keys": (f"{key}.{element_type}",),
        }

    def sensor_site(self, raw: dict[str, Any], key: str) -> dict[str, Any]:
        """The site an IMU or F/T sensor is at, or a body it is mounted on (`mount`)."""
        if "site" not in raw and "body" not in raw:
            raise self.error(
                f"{key}.site",
                'missing; the model site the sensor is at, or body = "<body>" with '
                "mount = { pos = [x, y, z], quat = [w, x, y, z] }",
            )
        quat = self.quaternion(
            raw.get("quat_site_sensor", _IDENTITY_WXYZ), f"{key}.quat_site_sensor"
        )
        return self.body_or_site(raw, key) | {"sources": None, "quat_site_sensor": quat}

    def mount(
        self, raw: dict[str, Any], key: str, name: str, kind: str, mapping: dict[str, Any]
    ) -> Mount | None:
        """mount = { pos = [x, y, z], quat = [w, x, y, z] }: the sensor's pose in its body's
        or site's frame (m; default 0 and identity). An IMU or F/T sensor on a body is mounted
        at the body's origin when no mount is given (MuJoCo's sensors sit at sites)."""
        on_body = kind in ("imu", "wrench") and mapping["element_type"] == "body"
        if "mount" not in raw and not on_body:
            return None
        table = self.table(raw.get("mount", {}), f"{key}.mount")
        self.unknown_keys(table, f"{key}.mount", ("pos", "quat"))
        pos = table.get("pos", [0.0, 0.0, 0.0])
        ok = (
            isinstance(pos, list)
            and len(pos) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in pos)
            and all(math.isfinite(v) for v in pos)
        )
        if not ok:
            raise self.error(f"{key}.mount.pos", f"expected [x, y, z] in m, got {self.show(pos)}")
        quat = self.quaternion(table.get("quat", list(_IDENTITY_WXYZ)), f"{key}.mount.quat")
        x, y, z = (float(v) for v in pos)
        (parent,) = mapping["elements"]
        return Mount(f"physfuse/{name}/mount", mapping["element_type"], parent, (x, y, z), quat)

    def name_table(
        self, raw: dict[str, Any], key: str, table_key: str, element_type: str, what: str
    ) -> dict[str, Any]:
        full = f"{key}.{table_key}"
        if table_key not in raw:
            raise self.error(full, f'missing; a table {{ <{what}> = "<model {element_type}>" }}')
        table = self.table(raw[table_key], full)
        if not table:
            raise self.error(full, f"empty; map at least one {what} to a model {element_type}")
        sources = tuple(table)
        elements = tuple(self.string(v, f"{full}.{k}") for k, v in table.items())
        return {
            "element_type": element_type,
            "elements": elements,
            "sources": sources,
            "element_keys": tuple(f"{full}.{k}" for k in sources),
        }

    def noise(self, raw: Any, key: str, kind: str) -> dict[str, float]:
        table = self.table(raw, key)
        defaults = NOISE_DEFAULTS[kind]
        self.unknown_keys(table, key, tuple(defaults))
        noise = dict(defaults)
        for name, value in table.items():
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or not math.isfinite(value) or value <= 0:
                raise self.error(
                    f"{key}.{name}", f"expected a positive finite number, got {self.show(value)}"
                )
            noise[name] = float(value)
        return noise

    def max_abs(self, raw: Any, key: str, kind: str, field: Any) -> dict[str, float]:
        """{component: bound} of a stream's `max_abs` table (components of its kind)."""
        # (imported here: the reader's modules import this one)
        from estimator.io.logs.measurements import STREAM_COMPONENTS

        table = self.table(raw, key)
        components = (field,) if kind == "command" and isinstance(field, str) else None
        self.unknown_keys(table, key, components or STREAM_COMPONENTS[kind])
        bounds = {}
        for name, value in table.items():
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or math.isnan(value) or value <= 0:
                raise self.error(
                    f"{key}.{name}", f"expected a positive number, got {self.show(value)}"
                )
            bounds[name] = float(value)
        return bounds

    def quaternion(self, value: Any, key: str) -> tuple[float, float, float, float]:
        ok = (
            isinstance(value, list | tuple)
            and len(value) == 4
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        )
        if not ok or abs(math.hypot(*value) - 1.0) > 1e-6:
            raise self.error(
                key, f"expected a unit quaternion [w, x, y, z], got {self.show(value)}"
            )
        w, x, y, z = (float(v) for v in value)
        return (w, x, y, z)

    def start_pose(self, raw: Any, model: mujoco.MjModel) -> tuple[float, float, float]:
        """start_pose = { x = …, y = …, yaw_deg = … } (each optional, 0) → (x, y, yaw rad)."""
        table = self.table(raw, "start_pose")
        self.unknown_keys(table, "start_pose", _START_POSE_KEYS)
        if not any(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
            raise self.error("start_pose", "the model has no free joint (a floating base) to place")
        x, y, yaw = (table.get(k, 0.0) for k in _START_POSE_KEYS)
        for k, v in zip(_START_POSE_KEYS, (x, y, yaw), strict=True):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise self.error(f"start_pose.{k}", f"expected a number, got {self.show(v)}")
        return float(x), float(y), math.radians(yaw)

    def unknown_keys(self, raw: dict[str, Any], key: str, allowed: tuple[str, ...]) -> None:
        for name in raw:
            if name not in allowed:
                full = f"{key}.{name}" if key else name
                raise self.error(full, f"unknown key; allowed keys: {', '.join(allowed)}")

    def table(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.error(key, f"expected a table, got {self.show(value)}")
        return value

    def string(self, value: Any, key: str) -> str:
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {self.show(value)}")
        return value

    def choice(self, value: Any, key: str, allowed: tuple[str, ...]) -> str:
        if value not in allowed:
            raise self.error(key, f"{self.show(value)} is not one of {', '.join(allowed)}")
        return str(value)

    @staticmethod
    def show(value: Any) -> str:
        return f"{value!r} ({type(value).__name__})"
