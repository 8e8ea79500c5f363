"""Many logs on Ray (estimator/fleet.py): 1 against 2 local workers, a two-node cluster on this
machine, and a worker killed mid-task.

    .venv/bin/python benchmarks/scale.py --out out/scale [--method kinematic]

1. The 8 bundled recordings (recordings/*.mcap, configs/<name>.toml) through `physfuse
   estimate recordings/ --config configs/ --workers N` for N = 1 and 2, in one run: wall
   time of each fleet and their ratio.
2. A two-node Ray cluster on loopback (`ray.cluster_utils.Cluster`: a head and a second
   node, one CPU each) running the same fleet through `--ray-address`: the Ray node that
   ran each log (fleet.json's node_id).
3. A long simulated humanoid_push log (`--long-s`, default 60 s): one process, then `--chunk
   --workers 1` and `--workers 2`: wall times, and the chunked estimate against the
   single-process one in units of its reported σ.
4. A worker SIGKILLed mid-estimate (ray::estimate_one, after `--kill-after` s): its task is
   retried; the retried estimate against a single process's estimate of the same log.
5. `physfuse calibrate` of recordings/humanoid_push.mcap (its first `--calibrate-s` s) in one
   process, then with `--workers 2`: wall times and the two profiles against each other.
6. An hour-long humanoid_push log (`--hour-s`, default 3600 s; simulated once into OUT/hour):
   physics, one process, then `--chunk --workers 2`: wall time and peak memory of each (the
   sum over the process and every process it started — Ray's included — of their
   proportional set size, sampled every `MEMORY_EVERY_S`), and the chunked estimate against
   the single-process one in units of its reported σ. A run whose folder holds its estimate
   and memory record is not run again (`rm -r OUT/hour/<run>` to redo it).

`--parts` runs some of them (the others' results in OUT/scale.json are kept). Prints a table
and writes OUT/scale.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.fleet import task_processes  # noqa: E402

PHYSFUSE = [sys.executable, "-m", "estimator.cli"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/scale"))
    parser.add_argument(
        "--method",
        default="kinematic",
        help="estimate method of every log (kinematic: the fleet's scaling, not the "
        "physics' speed, is what is measured; physics takes ≈10 min on 1 worker)",
    )
    parser.add_argument("--long-s", type=float, default=60.0, help="the long log's length")
    parser.add_argument("--chunk-s", type=float, default=15.0, help="its chunks' length")
    parser.add_argument("--kill-log", default="humanoid_push", help="the log whose task is killed")
    parser.add_argument("--kill-after", type=float, default=3.0, help="s into its estimate")
    parser.add_argument("--calibrate-s", type=float, default=4.0, help="of the calibration log")
    parser.add_argument("--hour-s", type=float, default=3600.0, help="the hour-long log's length")
    parser.add_argument(
        "--hour-init", help="--init of both estimates of the hour-long log (default: the default)"
    )
    parser.add_argument(
        "--hour-work", type=Path, help="the hour-long log and its runs (default OUT/hour; 1 GB)"
    )
    parser.add_argument(
        "--parts", nargs="+", choices=PARTS, default=[p for p in PARTS if p != "hour"]
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    report = args.out / "scale.json"
    results: dict[str, Any] = {}
    if set(args.parts) != {p for p in PARTS if p != "hour"} and report.exists():
        results = json.loads(report.read_text())
    results |= {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
        "method": args.method,
    }
    if "fleet" in args.parts:
        logs = sorted((ROOT / "recordings").glob("*.mcap"))
        results["logs"] = [p.name for p in logs]
        walls = {}
        for workers in (1, 2):
            wall, rows = _fleet(
                ["--workers", str(workers)], args.out / f"workers{workers}", args.method
            )
            walls[workers] = wall
            results[f"workers_{workers}"] = {"wall_s": wall, "ok": _ok(rows), "rows": rows}
        results["speedup_2_over_1"] = walls[1] / walls[2]
    if "cluster" in args.parts:
        results["cluster"] = _two_nodes(args.out / "cluster", args.method)
    if "long" in args.parts:
        results["long_log"] = _long_log(args.out / "long", args.long_s, args.chunk_s)
    if "killed" in args.parts:
        results["killed_worker"] = _killed(args.out / "killed", args.kill_log, args.kill_after)
    if "calibrate" in args.parts:
        results["calibrate"] = _calibrate(args.out / "calibrate", args.calibrate_s)
    if "hour" in args.parts:
        results["hour_log"] = _hour_log(
            args.hour_work or args.out / "hour", args.hour_s, args.chunk_s * 4, args.hour_init
        )
    report.write_text(json.dumps(results, indent=2) + "\n")
    _print(results)
    print(f"wrote {report}")
    return 0


PARTS = ("fleet", "cluster", "long", "killed", "calibrate", "hour")
MEMORY_EVERY_S = 1.0


def _fleet(where: list[str], out: Path, method: str, **popen: Any) -> tuple[float, list]:
    """`physfuse estimate recordings/ --config configs/` on `where`: wall time and rows."""
    start = time.perf_counter()
    done = subprocess.run(
        [
            *(*PHYSFUSE, "estimate", "recordings/", "--config", "configs/", "--out", str(out)),
            *(*where, "--method", method, "--quiet"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        **popen,
    )
    wall = time.perf_counter() - start
    if done.returncode not in (0, 1):
        raise SystemExit(f"fleet {where} failed ({done.returncode}): {done.stderr[-2000:]}")
    return wall, json.loads((out / "fleet.json").read_text())


def _ok(rows: list[dict]) -> int:
    return sum(r["status"] == "ok" for r in rows)


def _two_nodes(out: Path, method: str) -> dict[str, Any]:
    """The fleet on a head and a second node started on this machine, one CPU each."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False}
    )
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        wall, rows = _fleet(["--ray-address", cluster.address], out, method)
        nodes = {r["node_id"] for r in rows if r["node_id"]}
        return {
            "address": cluster.address,
            "nodes_in_cluster": len(cluster.list_all_nodes()),
            "wall_s": wall,
            "ok": _ok(rows),
            "logs_per_node": {n[:12]: sum(r["node_id"] == n for r in rows) for n in sorted(nodes)},
        }
    finally:
        cluster.shutdown()


def _long_log(out: Path, seconds: float, chunk_s: float) -> dict[str, Any]:
    """humanoid_push simulated for `seconds`, estimated (physics) by one process and in
    chunks on 1 and 2 workers; the 2-worker estimate against the one process's."""
    out.mkdir(parents=True, exist_ok=True)
    log, config = out / "humanoid_push_long.mcap", out / "humanoid_push_long.toml"
    _simulated(log, config, seconds)
    command = [*PHYSFUSE, "estimate", str(log), "--config", str(config), "--quiet"]
    runs: dict[str, Any] = {}
    for name, extra in (
        ("one_process", []),
        ("chunks_1_worker", ["--chunk", str(chunk_s), "--workers", "1"]),
        ("chunks_2_workers", ["--chunk", str(chunk_s), "--workers", "2"]),
    ):
        start = time.perf_counter()
        done = subprocess.run(
            [*command, "--out", str(out / name), *extra], cwd=ROOT, capture_output=True, text=True
        )
        runs[name] = {"wall_s": time.perf_counter() - start, "status": done.returncode}
        if done.returncode:
            runs[name]["error"] = done.stderr[-500:]
    return {
        "log_s": seconds,
        "chunk_s": chunk_s,
        "runs": runs,
        "speedup_chunks_2_over_1": runs["chunks_1_worker"]["wall_s"]
        / runs["chunks_2_workers"]["wall_s"],
        **_chunked_against_one(out / "one_process", out / "chunks_2_workers"),
    }


def _simulated(log: Path, config: Path, seconds: float) -> None:
    """humanoid_push simulated for `seconds` into `log` and `config`, unless it is there."""
    if log.exists():
        return
    done = subprocess.run(
        [
            *(*PHYSFUSE, "simulate", "humanoid_push", "--out", str(log)),
            *("--duration", str(seconds), "--config-out", str(config), "--quiet"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if done.returncode:
        raise SystemExit(f"simulate: {done.stderr[-2000:]}")


def _chunked_against_one(one_dir: Path, chunked_dir: Path) -> dict[str, Any]:
    """The chunked estimate's first free body and joints against the one process's: the
    position difference in units of the one process's reported σ, and at most."""
    from estimator.io.state_topics import read_state_topics

    one = read_state_topics(one_dir / "estimate.mcap", prefix="/estimate")
    two = read_state_topics(chunked_dir / "estimate.mcap", prefix="/estimate")
    body = next(iter(one.odometry))
    a, b = one.odometry[body].values, two.odometry[body].values
    sigma = np.sqrt(np.stack([a[:, 13], a[:, 17], a[:, 21]], axis=1))  # σ x, y, z
    z = np.abs(a[:, :3] - b[:, :3]) / sigma
    return {
        "same_knots": bool(np.array_equal(one.odometry[body].t_ns, two.odometry[body].t_ns)),
        "body": body,
        "position_diff_over_sigma": {
            "max": float(np.max(z)),
            "p99": float(np.percentile(z, 99)),
            "within_1_sigma": float(np.mean(z <= 1)),
        },
        "position_diff_max_mm": float(np.max(np.abs(a[:, :3] - b[:, :3])) * 1e3),
        "joint_diff_max_deg": float(
            np.degrees(np.max(np.abs(one.joints.values[:, 0::3] - two.joints.values[:, 0::3])))
        ),
    }


def _hour_log(out: Path, seconds: float, chunk_s: float, init: str | None) -> dict[str, Any]:
    """humanoid_push simulated for `seconds`, estimated (physics) by one process and in
    chunks on 2 workers, each with its peak memory; the chunked estimate against the one."""
    out.mkdir(parents=True, exist_ok=True)
    log, config = out / "humanoid_push.mcap", out / "humanoid_push.toml"
    _simulated(log, config, seconds)
    command = [*PHYSFUSE, "estimate", str(log), "--config", str(config), "--quiet"]
    command += ["--init", init] if init else []
    runs: dict[str, Any] = {}
    for name, extra in (
        ("one_process", []),
        ("chunks_2_workers", ["--chunk", str(chunk_s), "--workers", "2"]),
    ):
        record = out / name / "memory.json"
        if not (record.exists() and (out / name / "summary.json").exists()):
            run = _with_peak_memory([*command, "--out", str(out / name), *extra])
            record.write_text(json.dumps(run, indent=2) + "\n")
        runs[name] = json.loads(record.read_text())
        summary = json.loads((out / name / "summary.json").read_text())
        runs[name]["estimate_rmse"] = (summary["accuracy_vs_ground_truth"] or {}).get("estimate")
        runs[name]["knots"] = summary["knots"]
    return {
        "log_s": seconds,
        "log_mb": log.stat().st_size / 2**20,
        "chunk_s": chunk_s,
        "init": init or "default",
        "runs": runs,
        **_chunked_against_one(out / "one_process", out / "chunks_2_workers"),
    }


def _with_peak_memory(command: list[str]) -> dict[str, Any]:
    """Run `command`; its wall time and peak memory: the most, over samples every
    `MEMORY_EVERY_S`, of the summed proportional set size (shared pages split among their
    sharers: Ray's object store counted once) of the process and all its descendants."""
    import psutil

    start = time.perf_counter()
    proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    root = psutil.Process(proc.pid)
    peak_pss, peak_rss, most = 0, 0, 0
    while proc.poll() is None:
        pss = rss = 0
        tree = [root, *root.children(recursive=True)]
        for p in tree:
            try:
                info = p.memory_full_info()
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            pss, rss = pss + info.pss, rss + info.rss
        peak_pss, peak_rss, most = max(peak_pss, pss), max(peak_rss, rss), max(most, len(tree))
        time.sleep(MEMORY_EVERY_S)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - start
    if proc.returncode:
        raise SystemExit(f"{' '.join(command)} failed: {stderr.decode()[-2000:]}")
    return {
        "wall_s": wall,
        "peak_pss_mb": peak_pss / 2**20,
        "peak_rss_sum_mb": peak_rss / 2**20,
        "processes_at_most": most,
        "said": stdout.decode().strip().splitlines()[:1],
    }


def _killed(out: Path, log: str, after_s: float) -> dict[str, Any]:
    """One log on 1 worker; its ray::estimate_one process SIGKILLed `after_s` into the task;
    the retried estimate against a single process's (both on one MuJoCo thread)."""
    recording = ROOT / "recordings" / f"{log}.mcap"
    config = ROOT / "configs" / f"{log}.toml"
    env = {**os.environ, "PHYSFUSE_THREADS": "1"}
    command = [*PHYSFUSE, "estimate", str(recording), "--config", str(config), "--quiet"]
    fleet = subprocess.Popen(
        [*command, "--out", str(out), "--workers", "1"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    victim = _wait_for(task_processes)
    time.sleep(after_s)
    os.kill(victim[0], signal.SIGKILL)
    killed_at = time.perf_counter()
    retried = _wait_for(lambda: [p for p in task_processes() if p not in victim])
    retried_after_s = time.perf_counter() - killed_at
    stdout, stderr = fleet.communicate(timeout=1800)
    finished_after_s = time.perf_counter() - killed_at
    single = out.parent / "killed_single"
    done = subprocess.run(
        [*command, "--out", str(single)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
    )
    from estimator.io.state_topics import read_state_topics

    a = read_state_topics(out / log / "estimate.mcap", prefix="/estimate")
    b = read_state_topics(single / "estimate.mcap", prefix="/estimate")
    joints = float(np.max(np.abs(a.joints.values - b.joints.values)))
    poses = [
        float(np.max(np.abs(a.odometry[body].values[:, :7] - b.odometry[body].values[:, :7])))
        for body in a.odometry
    ]
    rows = json.loads((out / "fleet.json").read_text())
    return {
        "log": log,
        "killed_pid": victim[0],
        "retried_pid": retried[0],
        "retried_after_s": retried_after_s,  # a new worker inside the task
        "finished_after_s": finished_after_s,  # the retried estimate done
        "fleet_status": fleet.returncode,
        "row_status": rows[0]["status"],
        "single_status": done.returncode,
        "max_abs_diff_joints": joints,
        "max_abs_diff_poses": max(poses, default=0.0),
        "raylet_said": [ln for ln in (stdout + stderr).splitlines() if "retried" in ln][:1],
    }


def _wait_for(find: Any, timeout_s: float = 300.0) -> list[int]:
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        found = find()
        if found:
            return found
        time.sleep(0.1)
    raise SystemExit(f"no Ray task worker in {timeout_s} s")


def _calibrate(out: Path, seconds: float) -> dict[str, Any]:
    """`physfuse calibrate` of humanoid_push's first `seconds` in one process (MuJoCo on the
    cores' threads), then its grid as Ray tasks on 2 local workers (one thread each)."""
    runs: dict[str, Any] = {}
    for name, more in (("one process", []), ("2 workers", ["--workers", "2"])):
        folder = out / name.replace(" ", "_")
        start = time.perf_counter()
        subprocess.run(
            [*PHYSFUSE, "calibrate", "recordings/humanoid_push.mcap", "--config",
             "configs/humanoid_push.toml", "--duration", f"{seconds:g}", "--out", str(folder),
             "--quiet", *more],
            cwd=ROOT, check=True, capture_output=True,
        )  # fmt: skip
        report = json.loads((folder / "calibration.json").read_text())
        runs[name] = {"wall_s": time.perf_counter() - start, "best": report["best"],
                      "points": report["points"]}  # fmt: skip
    one, two = (sorted(r["points"], key=lambda p: p["value"]) for r in runs.values())
    return {
        "log_s": seconds,
        "runs": runs,
        "speedup_2_workers": runs["one process"]["wall_s"] / runs["2 workers"]["wall_s"],
        "max_rel_diff_mocap_cost": max(
            abs(a["mocap_cost"] - b["mocap_cost"]) / abs(a["mocap_cost"])
            for a, b in zip(one, two, strict=True)
        ),
    }


def _print(r: dict[str, Any]) -> None:
    print(f"machine: {r['machine']}, Python {r['python']}; method {r['method']}")
    if "workers_1" in r:
        _print_fleet(r)
    if "hour_log" in r:
        _print_hour(r["hour_log"])
    if "calibrate" in r:
        c = r["calibrate"]
        for name, run in c["runs"].items():
            label = f"calibrate {c['log_s']:g} s, {name}"
            print(f"{label:34s} {run['wall_s']:8.1f}  best {run['best']:.4g}")
        print(f"{'speedup, calibrate on 2 workers':34s} {c['speedup_2_workers']:8.2f}")
        print(f"  profiles' mocap costs within {c['max_rel_diff_mocap_cost']:.1g} (relative)")


def _print_fleet(r: dict[str, Any]) -> None:
    print(f"{'fleet':34s} {'wall s':>8s} {'ok':>6s}")
    for w in (1, 2):
        f = r[f"workers_{w}"]
        print(f"{f'8 recordings, {w} local worker(s)':34s} {f['wall_s']:8.1f} {f['ok']:>4d}/8")
    print(f"{'speedup, 2 workers over 1':34s} {r['speedup_2_over_1']:8.2f}")
    c = r["cluster"]
    print(f"{'two-node cluster (1 CPU each)':34s} {c['wall_s']:8.1f} {c['ok']:>4d}/8")
    print(f"  logs per Ray node: {c['logs_per_node']}")
    g = r["long_log"]
    for name, run in g["runs"].items():
        label = f"{g['log_s']:.0f} s log, {name}"
        print(f"{label:34s} {run['wall_s']:8.1f}")
    print(f"{'speedup, chunks on 2 workers over 1':34s} {g['speedup_chunks_2_over_1']:8.2f}")
    d = g["position_diff_over_sigma"]
    print(
        f"  chunked vs one process, {g['body']} position: max {d['max']:.2f} σ, p99 "
        f"{d['p99']:.2f} σ, {d['within_1_sigma']:.3%} within 1 σ; max "
        f"{g['position_diff_max_mm']:.4f} mm, joints {g['joint_diff_max_deg']:.2g}°"
    )
    k = r["killed_worker"]
    print(
        f"killed worker: {k['log']} pid {k['killed_pid']} → retried on pid {k['retried_pid']} "
        f"{k['retried_after_s']:.1f} s later, done {k['finished_after_s']:.0f} s later; row "
        f"{k['row_status']}; against one process: "
        f"joints max |Δ| {k['max_abs_diff_joints']:.3g}, poses {k['max_abs_diff_poses']:.3g}"
    )


def _print_hour(g: dict[str, Any]) -> None:
    print(f"{'hour-long log':34s} {'wall s':>8s} {'peak MB':>8s}  (PSS over the process tree)")
    for name, run in g["runs"].items():
        label = f"{g['log_s']:.0f} s log, {name}"
        print(f"{label:34s} {run['wall_s']:8.1f} {run['peak_pss_mb']:8.0f}")
    d = g["position_diff_over_sigma"]
    print(
        f"  chunked vs one process, {g['body']} position: max {d['max']:.2f} σ, p99 "
        f"{d['p99']:.2f} σ, {d['within_1_sigma']:.3%} within 1 σ; max "
        f"{g['position_diff_max_mm']:.4f} mm, joints {g['joint_diff_max_deg']:.2g}°"
    )


if __name__ == "__main__":
    sys.exit(main())
