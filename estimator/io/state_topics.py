"""Robot states in a log's shared topic layout — the ground truth of `physfuse simulate`
(`/ground_truth/...`) or an estimate (`/estimate/...`) — and errors of a trajectory against it.
The layout is described in `estimator/io/mcap_writer.py`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from estimator.errors import LogError
from estimator.io.logs.source import RawMessage, open_log

PREFIX = "/ground_truth"


@dataclass(frozen=True)
class Series:
    """One topic's samples: t_ns (N,) int64 header stamps, increasing; values (N, K)."""

    t_ns: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class StateTopics:
    """Every state topic of one prefix in a log (the writer's layout; contacts not read).

    odometry:       body → (N, 22): position (3), quaternion w, x, y, z (4), then the twist
                    in the body frame: linear velocity of the body origin (3), angular (3),
                    then the position's covariance (3 × 3, row-major; NaN when the message
                    gives none: all zeros)
    joint_names:    the JointState's names, in its order (J)
    joints:         (N, J·3) per joint position, velocity, effort (NaN where not given)
    contact_wrench: body → (N, 6) net contact force (3) and torque (3), body frame
    imu_bias:       IMU site → (N, 6) accelerometer bias (m/s²) then gyro bias (rad/s); the
                    site is the header's frame_id (the topic's last part when empty, as in
                    logs written before topics were named by the site)
    """

    path: str
    prefix: str
    odometry: dict[str, Series]
    joint_names: tuple[str, ...]
    joints: Series | None
    contact_wrench: dict[str, Series]
    imu_bias: dict[str, Series]

    @property
    def empty(self) -> bool:
        return not (self.odometry or self.joints or self.contact_wrench or self.imu_bias)

    def joint(self, name: str) -> Series:
        """(N, 3) position, velocity, effort of one joint."""
        j = self.joint_names.index(name)
        assert self.joints is not None
        return Series(self.joints.t_ns, self.joints.values[:, 3 * j : 3 * j + 3])

    def qpos(self, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
        """(t_ns (N,), qpos (N, nq)) on the JointState's times (or the first odometry's);
        coordinates no topic gives keep the model's qpos0."""
        base = self.joints if self.joints is not None else next(iter(self.odometry.values()), None)
        if base is None:
            raise LogError(f"{self.path}: no {self.prefix}/odometry or joint_states topics")
        t_ns = base.t_ns
        qpos = np.tile(model.qpos0, (len(t_ns), 1))
        if self.joints is not None:
            positions = at_times(self.joints.t_ns, self.joints.values[:, 0::3], t_ns)
            for i, name in enumerate(self.joint_names):
                j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
                if j >= 0:
                    qpos[:, model.jnt_qposadr[j]] = positions[:, i]
        for body, series in self.odometry.items():
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
            if b >= 0 and model.body_jntnum[b] >= 1:
                adr = model.jnt_qposadr[model.body_jntadr[b]]
                qpos[:, adr : adr + 7] = at_times(series.t_ns, series.values, t_ns)[:, :7]
        return t_ns, qpos


def read_state_topics(
    path: str | Path, prefix: str = PREFIX, log_time: tuple[int, int] | None = None
) -> StateTopics:
    """The `{prefix}/...` state topics of a log (file or rosbag2 folder); log_time: (start,
    end) ns, only the messages received in [start, end).

    Raises LogError when the path is not a log, or has no topic under `prefix`.
    """
    source = open_log(path, log_time=log_time)
    decoders: dict[tuple[Any, ...], Callable[[bytes], Any]] = {}
    odometry: dict[str, dict[int, list[float]]] = {}
    joints: dict[int, dict[str, tuple[float, float, float]]] = {}
    wrench: dict[str, dict[int, list[float]]] = {}
    bias: dict[str, dict[int, list[float]]] = {}
    root = prefix.rstrip("/") + "/"
    for raw in source:
        topic = raw.topic
        if not topic.startswith(root) or topic == root + "contacts":
            continue
        m = _decode(raw, decoders)
        t = int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)
        name = topic.rsplit("/", 1)[1]
        if topic.startswith(root + "odometry/"):
            p, q = m.pose.pose.position, m.pose.pose.orientation
            lin, ang = m.twist.twist.linear, m.twist.twist.angular
            row = [p.x, p.y, p.z, q.w, q.x, q.y, q.z, lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]
            covariance = np.reshape(m.pose.covariance, (6, 6))[:3, :3].ravel()
            row += list(covariance) if np.any(covariance) else [np.nan] * 9
            odometry.setdefault(name, {})[t] = row
        elif topic == root + "joint_states":
            n = len(m.name)
            fields = [
                list(f) if len(f) == n else [np.nan] * n for f in (m.position, m.velocity, m.effort)
            ]
            joints[t] = {
                j: (fields[0][i], fields[1][i], fields[2][i]) for i, j in enumerate(m.name)
            }
        elif topic.startswith(root + "contact_wrench/"):
            f, tau = m.wrench.force, m.wrench.torque
            wrench.setdefault(name, {})[t] = [f.x, f.y, f.z, tau.x, tau.y, tau.z]
        elif topic.startswith(root + "imu_bias/"):
            a, w = m.accel.linear, m.accel.angular
            site = m.header.frame_id or name
            bias.setdefault(site, {})[t] = [a.x, a.y, a.z, w.x, w.y, w.z]
    names = tuple(dict.fromkeys(j for row in joints.values() for j in row))
    joint_series = None
    if joints:
        times = sorted(joints)
        nan3 = (np.nan, np.nan, np.nan)
        values = [[v for j in names for v in joints[t].get(j, nan3)] for t in times]
        joint_series = Series(np.array(times, dtype=np.int64), np.array(values, dtype=float))
    state = StateTopics(
        path=str(path),
        prefix=prefix,
        odometry=_series(odometry),
        joint_names=names,
        joints=joint_series,
        contact_wrench=_series(wrench),
        imu_bias=_series(bias),
    )
    if state.empty:
        why = " (this log has no ground truth)" if prefix == PREFIX else ""
        raise LogError(f"{path}: no {root}... topics{why}")
    return state


def _series(table: dict[str, dict[int, list[float]]]) -> dict[str, Series]:
    out = {}
    for name, rows in sorted(table.items()):
        times = sorted(rows)
        out[name] = Series(
            np.array(times, dtype=np.int64), np.array([rows[t] for t in times], dtype=float)
        )
    return out


def _decode(raw: RawMessage, decoders: dict[tuple[Any, ...], Callable[[bytes], Any]]) -> Any:
    schema = raw.schema
    if schema is None:
        raise LogError(f"topic {raw.topic}: no schema, cannot decode its messages")
    key = (schema.name, schema.data, raw.message_encoding)
    if key not in decoders:
        try:
            decoder = DecoderFactory().decoder_for(raw.message_encoding, schema)
        except Exception as err:  # a schema text mcap_ros2 cannot parse
            raise LogError(f"topic {raw.topic}: cannot decode {schema.name} ({err})") from err
        if decoder is None:
            raise LogError(f"topic {raw.topic}: no decoder for {raw.message_encoding} messages")
        decoders[key] = decoder
    return decoders[key](raw.data)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """An MCAP file's metadata records (name → string pairs); {} for anything else."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        with path.open("rb") as f:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception:  # no readable summary (a cut file): no metadata
        return {}


def read_ground_truth(
    path: str | Path, model: mujoco.MjModel, log_time: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), qpos (N, nq)) from `/ground_truth/odometry/<body>` and `.../joint_states`
    (log_time: of the messages received in [start, end) ns only).

    Raises LogError when the log has no ground truth (a real robot's log).
    """
    return read_state_topics(path, PREFIX, log_time).qpos(model)


def at_times(t_truth: np.ndarray, values: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """(T, n) the truth (N, n) at each of t_ns: linear interpolation between the samples that
    bracket it, held beyond the ends. (Quaternion columns come out a hair off unit norm:
    normalize them.)"""
    if len(t_truth) == 1:
        return np.repeat(values, len(t_ns), axis=0)
    i = np.searchsorted(t_truth, t_ns).clip(1, len(t_truth) - 1)
    t0, t1 = t_truth[i - 1], t_truth[i]
    w = ((t_ns - t0) / np.maximum(t1 - t0, 1)).clip(0.0, 1.0)[:, None]
    return (1.0 - w) * values[i - 1] + w * values[i]


def trajectory_errors(
    model: mujoco.MjModel, qpos: np.ndarray, truth: np.ndarray, trim: int = 2
) -> dict[str, float]:
    """RMSE of hinge angles (deg), and of each free body's position (mm) and orientation (deg).

    qpos, truth: (T, nq) on the same times; `trim` knots at each end are left out (no
    dynamics factor reaches the outermost knots).
    """
    q, g = qpos[trim : len(qpos) - trim], truth[trim : len(truth) - trim]
    out: dict[str, float] = {}
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    if hinges:
        adr = model.jnt_qposadr[hinges]
        out["joint_deg"] = float(np.degrees(np.sqrt(np.mean((q[:, adr] - g[:, adr]) ** 2))))
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[j]))
        a = model.jnt_qposadr[j]
        dp = q[:, a : a + 3] - g[:, a : a + 3]
        out[f"{body}_pos_mm"] = float(1e3 * np.sqrt(np.mean(np.sum(dp**2, axis=1))))
        angle = np.zeros(len(q))
        g_quat = g[:, a + 3 : a + 7] / np.linalg.norm(g[:, a + 3 : a + 7], axis=1, keepdims=True)
        for k in range(len(q)):
            e = np.zeros(3)
            mujoco.mju_subQuat(e, q[k, a + 3 : a + 7], g_quat[k])
            angle[k] = np.linalg.norm(e)
        out[f"{body}_rot_deg"] = float(np.degrees(np.sqrt(np.mean(angle**2))))
    return out
