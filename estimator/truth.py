"""Ground truth in a log (the `/ground_truth/...` topics of `physfuse simulate`) and errors
of a trajectory against it."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
from mcap_ros2.reader import read_ros2_messages

from estimator.errors import LogError

PREFIX = "/ground_truth"


def read_ground_truth(path: str | Path, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), qpos (N, nq)) from `/ground_truth/odometry/<body>` and `.../joint_states`.

    Raises LogError when the log has no ground truth (a real robot's log).
    """
    odometry: dict[str, dict[int, list[float]]] = {}
    joints: dict[int, dict[str, float]] = {}
    for msg in read_ros2_messages(str(path)):
        topic, m = msg.channel.topic, msg.ros_msg
        if not topic.startswith(PREFIX + "/"):
            continue
        if topic.startswith(f"{PREFIX}/odometry/"):
            t = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            p, q = m.pose.pose.position, m.pose.pose.orientation
            pose = [p.x, p.y, p.z, q.w, q.x, q.y, q.z]
            odometry.setdefault(topic.rsplit("/", 1)[1], {})[t] = pose
        elif topic == f"{PREFIX}/joint_states":
            t = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            joints[t] = dict(zip(m.name, m.position, strict=True))
    times = sorted(joints) if joints else sorted(next(iter(odometry.values()), {}))
    if not times:
        raise LogError(f"{path}: no {PREFIX}/... topics (this log has no ground truth)")
    t_ns = np.array(times, dtype=np.int64)
    qpos = np.tile(model.qpos0, (len(t_ns), 1))
    for i, t in enumerate(times):
        for name, value in joints.get(t, {}).items():
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j >= 0:
                qpos[i, model.jnt_qposadr[j]] = value
        for body, poses in odometry.items():
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
            if b >= 0 and t in poses:
                adr = model.jnt_qposadr[model.body_jntadr[b]]
                qpos[i, adr : adr + 7] = poses[t]
    return t_ns, qpos


def at_times(t_truth: np.ndarray, q_truth: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """(T, nq) the ground-truth state nearest in time to each of t_ns."""
    nearest = np.searchsorted(t_truth, t_ns).clip(1, len(t_truth) - 1)
    earlier = np.abs(t_truth[nearest - 1] - t_ns) <= np.abs(t_truth[nearest] - t_ns)
    return q_truth[nearest - earlier.astype(int)]


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
        for k in range(len(q)):
            e = np.zeros(3)
            mujoco.mju_subQuat(e, q[k, a + 3 : a + 7], g[k, a + 3 : a + 7])
            angle[k] = np.linalg.norm(e)
        out[f"{body}_rot_deg"] = float(np.degrees(np.sqrt(np.mean(angle**2))))
    return out
