"""Speed and memory of the estimator: wall time over log duration, overhead over the bare MuJoCo
linearization it needs, and peak memory, on two logs in one run.

    python benchmarks/estimator_speed.py [--minutes M] [--quadruped-seconds S]
        [--condition NAME] [--also-init INIT ...] [--out DIR]

Simulates (each in a separate process) an M-minute humanoid_push log (default 1; 100 Hz
knots) and an S-second log of MuJoCo Menagerie's Go2 quadruped (default 30; 500 Hz knots,
`physfuse simulate --model physics/models/menagerie/go2.xml`; 0: none), --condition as
`physfuse simulate --condition` (default the scenario as its sample recording, with mocap
dropouts), estimates each with the default settings, and measures in the same run the bare
cost of the MuJoCo work the solve needed: the same number of knot passes of mjd_inverseFD
(with Jacobians) and mj_inverse (without) — the MuJoCo calls alone, on the same 2 threads,
timed over every knot of the log before the estimate (at the interpolated measurements) and
after it (at the estimate), their mean; both are reported, since a shared machine's speed
drifts. --also-init: after the default estimate, the same log estimated again with each of
these starts (`init`), wall time and passes, in the same run. Prints a table and writes
DIR/estimator_speed.json. Peak memory is this process's maximum RSS up to that log's
estimate (reading the log, timing and estimating; the humanoid's first).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from estimator.batch import estimate
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import accelerations, build_problem, velocities
from estimator.run import initial_trajectory
from estimator.settings import CHOICES, Settings
from estimator.solver.linearize import THREADS
from physics.knots import KnotEngine


def bare_pass_seconds(
    config, measurements, settings: Settings, qpos: np.ndarray | None = None
) -> tuple[float, float]:
    """Wall seconds per knot of the MuJoCo calls of one pass over every knot of the log (at
    qpos, or the interpolated measurements), with and without Jacobians, on the estimator's
    THREADS threads. (Their cost varies along a log: on the 30 s humanoid_push log's first 400
    knots mjd_inverseFD cost 25% more than over the whole log.)"""
    h = float(config.load_model().opt.timestep)
    t_ns = knot_grid(measurements, h)
    problem = build_problem(config, measurements, settings, t_ns)
    model = problem.model
    if qpos is None:
        qpos = initial_trajectory(model, measurements, t_ns)
    v = velocities(model, qpos, h)
    a = accelerations(v, h)
    workers = [KnotEngine(model, eps=settings.fd_eps) for _ in range(THREADS)]
    nv, ns = model.nv, model.nsensordata
    out = [np.zeros((nv, nv)) for _ in range(3)] + [np.zeros((nv, ns)) for _ in range(3)]

    commanded = np.isfinite(problem.ctrl).any(axis=1) if problem.ctrl.shape[1] else []

    def work(chunk: range, worker: KnotEngine, jac: bool) -> None:
        outs = [o.copy() for o in out]
        for k in chunk:
            worker.inverse(qpos[k], v[k], a[k])
            if len(commanded) and commanded[k]:  # the commands' actuation (mj_fwdActuation)
                problem.actuation(worker.data, k)
            if jac:
                worker.derivatives(qpos[k], v[k], a[k], *outs)

    interior = range(1, len(t_ns) - 1)
    seconds = []
    with ThreadPoolExecutor(THREADS) as pool:
        for jac in (True, False):
            warm_up = [interior[:200][i::THREADS] for i in range(THREADS)]
            list(pool.map(work, warm_up, workers, [jac] * THREADS))
            chunks = [interior[i::THREADS] for i in range(THREADS)]
            start = time.perf_counter()
            list(pool.map(work, chunks, workers, [jac] * THREADS))
            seconds.append((time.perf_counter() - start) / len(interior))
    return seconds[0], seconds[1]


def starts_row(summary, wall: float) -> dict:
    """Wall time and passes of one estimate, and its windows solved from two starts."""
    return {
        "wall_s": wall,
        "linearizations": summary.linearizations,
        "evaluations": summary.evaluations,
        "windows_solved_from_two_starts": sum(len(t) > 1 for t in summary.starts_tried),
    }


LOGS = {  # name → `physfuse simulate` arguments (before --duration)
    "humanoid_push": ["humanoid_push"],
    "go2": [
        "--model",
        "physics/models/menagerie/go2.xml",
        "--excitation",
        "0.1",
        "--pushes",
        "base",
    ],
}


def measure(name: str, seconds: float, args: argparse.Namespace) -> tuple[dict, list]:
    """Simulate `name` for `seconds`, estimate it, time the bare MuJoCo work: (JSON, rows)."""
    stem = f"{name}_{seconds:g}s" + (f"_{args.condition}" if args.condition else "")
    log, config_path = args.out / f"{stem}.mcap", args.out / f"{stem}.toml"
    condition = ["--condition", args.condition] if args.condition else []
    subprocess.run(
        [
            sys.executable,
            "-m",
            "estimator.cli",
            "simulate",
            *LOGS[name],
            "--seed",
            "0",
            "--duration",
            str(seconds),
            "--out",
            str(log),
            "--config-out",
            str(config_path),
            "--quiet",
            *condition,
        ],
        check=True,
    )
    config = load_config(config_path)
    settings = Settings.from_config(config)
    start = time.perf_counter()
    measurements = read_log(log, config).measurements
    read_s = time.perf_counter() - start
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # the bare passes before and after the estimate: a shared machine's speed drifts by tens
    # of percent within minutes
    bare_before = np.array(bare_pass_seconds(config, measurements, settings))
    start = time.perf_counter()
    est, summary = estimate(config, measurements, settings)
    wall = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    bare_after = np.array(bare_pass_seconds(config, measurements, settings, est.qpos))
    per_jac, per_eval = (bare_before + bare_after) / 2
    bare = per_jac * summary.knots_linearized + per_eval * summary.knots_evaluated
    two_starts = sum(len(tried) > 1 for tried in summary.starts_tried)
    result = {
        "log": name,
        "condition": args.condition or "sample recording",
        "knot_rate_hz": 1.0 / float(summary.h),
        "log_duration_s": float(summary.duration_s),
        "knots": summary.knots,
        "windows": summary.windows,
        "windows_solved_from_two_starts": two_starts,
        "read_s": read_s,
        "estimate_wall_s": wall,
        "wall_over_duration": wall / float(summary.duration_s),
        "linearization_passes": summary.linearizations,
        "evaluation_passes": summary.evaluations,
        "bare_mujoco_s": bare,
        "overhead_over_bare_mujoco": wall / bare,
        "mjd_inverseFD_us_per_knot": 1e6 * per_jac,
        "mj_inverse_us_per_knot": 1e6 * per_eval,
        "mjd_inverseFD_us_per_knot_before_after": [1e6 * bare_before[0], 1e6 * bare_after[0]],
        "peak_rss_mb": peak_mb,
        "rss_before_estimate_mb": rss_before,
        "converged_windows": int(np.sum(summary.converged)),
    }
    rows = [
        (
            "log",
            f"{result['log_duration_s']:.0f} s at {result['knot_rate_hz']:.0f} Hz "
            f"({result['knots']} knots, {result['windows']} windows, {two_starts} of them "
            "solved from two starts)",
        ),
        ("estimate wall time", f"{wall:.1f} s = {result['wall_over_duration']:.2f}× the log"),
        (
            "bare MuJoCo work",
            f"{bare:.1f} s ({summary.linearizations} linearizations, "
            f"{summary.evaluations} evaluations)",
        ),
        (
            "bare pass per knot",
            f"{1e6 * bare_before[0]:.0f} µs before, {1e6 * bare_after[0]:.0f} µs after the "
            "estimate (mjd_inverseFD + mj_inverse; after: at the estimate)",
        ),
        ("overhead over bare MuJoCo", f"{result['overhead_over_bare_mujoco']:.2f}×"),
        ("peak memory (max RSS)", f"{peak_mb:.0f} MB"),
        ("reading the log", f"{read_s:.1f} s"),
    ]
    result["inits"] = {settings.init: starts_row(summary, wall)}
    for init in args.also_init:
        start = time.perf_counter()
        _, other = estimate(config, measurements, replace(settings, init=init))
        result["inits"][init] = starts_row(other, time.perf_counter() - start)
    for init, row in result["inits"].items():
        rows.append(
            (
                f"init = {init}",
                f"{row['wall_s']:.1f} s, {row['linearizations']} linearizations, "
                f"{row['windows_solved_from_two_starts']} windows from two starts",
            )
        )
    return result, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=1.0, help="the humanoid's log")
    parser.add_argument(
        "--quadruped-seconds", type=float, default=30.0, help="the Go2's log (0: none)"
    )
    parser.add_argument("--condition", help="simulate under this condition (physfuse simulate)")
    parser.add_argument(
        "--also-init", nargs="+", default=[], choices=CHOICES["init"], metavar="INIT"
    )
    parser.add_argument("--out", type=Path, default=Path("out/bench"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    logs = [("humanoid_push", 60 * args.minutes)]
    if args.quadruped_seconds > 0:
        logs.append(("go2", args.quadruped_seconds))
    results, tables = {}, []
    for name, seconds in logs:
        results[name], rows = measure(name, seconds, args)
        tables.append(rows)
    width = max(len(v) for rows in tables for _, v in rows)
    print(f"{'':28s} " + " | ".join(f"{name:{width}s}" for name, _ in logs))
    for i, (label, _) in enumerate(tables[0]):
        values = [rows[i][1] if i < len(rows) else "" for rows in tables]
        print(f"{label:28s} " + " | ".join(f"{v:{width}s}" for v in values))
    (args.out / "estimator_speed.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out / 'estimator_speed.json'}")


if __name__ == "__main__":
    main()
