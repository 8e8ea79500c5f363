"""Accuracy of the physics smoother against ground truth on the sample recordings.

    python benchmarks/estimator_accuracy.py [--out DIR] [--recordings NAME ...]

For each recording: RMSE of joint angles (deg), base position (mm) and base orientation (deg)
of the raw measurements (interpolated to the knots, as the smoother is initialized) and of the
estimate, against the `/ground_truth/...` topics; the wall time of estimation and its ratio
to the log's duration. Prints a table and writes DIR/estimator_accuracy.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mujoco
import numpy as np
from mcap_ros2.reader import read_ros2_messages

from estimator.config import load_config
from estimator.logs import read_log
from estimator.problem import Settings
from estimator.run import estimate, initial_trajectory

ROOT = Path(__file__).resolve().parent.parent
RECORDINGS = ("humanoid_push", "humanoid_fall", "quadruped_trot", "arm_box", "single_joint")


def ground_truth(path: Path, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), qpos (N, nq)) from /ground_truth/odometry/* and /ground_truth/joint_states."""
    odometry: dict[str, dict[int, list[float]]] = {}
    joints: dict[int, dict[str, float]] = {}
    for msg in read_ros2_messages(str(path)):
        topic, m = msg.channel.topic, msg.ros_msg
        if not topic.startswith("/ground_truth/"):
            continue
        t = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        if topic.startswith("/ground_truth/odometry/"):
            p, q = m.pose.pose.position, m.pose.pose.orientation
            odometry.setdefault(topic.rsplit("/", 1)[1], {})[t] = [
                p.x,
                p.y,
                p.z,
                q.w,
                q.x,
                q.y,
                q.z,
            ]
        elif topic == "/ground_truth/joint_states":
            joints[t] = dict(zip(m.name, m.position, strict=True))
    t_ns = np.array(sorted(joints), dtype=np.int64)
    qpos = np.tile(model.qpos0, (len(t_ns), 1))
    for i, t in enumerate(t_ns):
        for name, value in joints[t].items():
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            qpos[i, model.jnt_qposadr[j]] = value
        for body, poses in odometry.items():
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
            adr = model.jnt_qposadr[model.body_jntadr[b]]
            qpos[i, adr : adr + 7] = poses[t]
    return t_ns, qpos


def errors(model: mujoco.MjModel, qpos: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMSE over all knots but the two at each end (no dynamics factor reaches them)."""
    q, g = qpos[2:-2], truth[2:-2]
    out: dict[str, float] = {}
    scalar = [j for j in range(model.njnt) if model.jnt_type[j] in (2, 3)]
    if scalar:
        adr = model.jnt_qposadr[scalar]
        out["joint_deg"] = float(np.degrees(np.sqrt(np.mean((q[:, adr] - g[:, adr]) ** 2))))
    free = [j for j in range(model.njnt) if model.jnt_type[j] == 0]
    if free:
        a = model.jnt_qposadr[free[0]]
        out["base_pos_mm"] = float(
            1e3 * np.sqrt(np.mean(np.sum((q[:, a : a + 3] - g[:, a : a + 3]) ** 2, axis=1)))
        )
        angle = np.zeros(len(q))
        for k in range(len(q)):
            e = np.zeros(3)
            mujoco.mju_subQuat(e, q[k, a + 3 : a + 7], g[k, a + 3 : a + 7])
            angle[k] = np.linalg.norm(e)
        out["base_rot_deg"] = float(np.degrees(np.sqrt(np.mean(angle**2))))
    return out


def run(name: str) -> dict:
    config = load_config(
        ROOT / "configs" / f"{name}.toml", extra_sections=("estimator", "simulate")
    )
    path = ROOT / "recordings" / f"{name}.mcap"
    log = read_log(path, config)
    settings = Settings.from_config(config)
    start = time.perf_counter()
    est, summary = estimate(config, log.measurements, settings)
    wall = time.perf_counter() - start
    model = config.load_model()
    t_truth, q_truth = ground_truth(path, model)
    nearest = np.abs(t_truth[None, :] - est.t_ns[:, None]).argmin(axis=1)
    truth = q_truth[nearest]
    raw = initial_trajectory(model, log.measurements, est.t_ns)
    return {
        "duration_s": float(summary.duration_s),
        "knots": summary.knots,
        "iterations": summary.iterations,
        "wall_s": wall,
        "wall_over_duration": wall / float(summary.duration_s),
        "raw": errors(model, raw, truth),
        "estimate": errors(model, est.qpos, truth),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench"))
    parser.add_argument("--recordings", nargs="*", default=list(RECORDINGS))
    args = parser.parse_args()
    results = {name: run(name) for name in args.recordings}
    print(f"{'recording':16s} {'metric':14s} {'raw':>9s} {'estimate':>9s}   wall/duration")
    for name, r in results.items():
        for i, metric in enumerate(r["raw"]):
            ratio = f"{r['wall_over_duration']:.1f}×" if i == 0 else ""
            raw, est = r["raw"][metric], r["estimate"][metric]
            print(f"{name:16s} {metric:14s} {raw:9.3f} {est:9.3f}   {ratio}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "estimator_accuracy.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out / 'estimator_accuracy.json'}")


if __name__ == "__main__":
    main()
