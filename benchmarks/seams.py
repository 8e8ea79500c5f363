"""Seams between windows: the estimate's acceleration error at the knots where consecutive
windows join, against the error inside the windows, on recordings with ground truth.

    .venv/bin/python benchmarks/seams.py [--recordings go2 humanoid_push] [--window 1] [--out DIR]

For each recording it estimates the log (the configured method, `--window` seconds a window
so that a short log has several joins), takes the truth's joint-space acceleration by the
same finite differences as the estimate's, and reports per recording: the median and the
95th percentile of ‖a_est − a_true‖ (over all dofs, rad/s² or m/s² mixed, as the solver
sees them) within ±2 knots of a join and elsewhere, and their ratio; and, for the same knots
near the joins, the error of the log solved as one window (no joins): where a join falls on
a hard stretch (an impact) both are large, and the difference is what the join adds. Prints a
table and writes DIR/seams.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.batch import estimate  # noqa: E402
from estimator.config import load_config  # noqa: E402
from estimator.io.logs import read_log  # noqa: E402
from estimator.io.state_topics import at_times, read_ground_truth  # noqa: E402
from estimator.problem import accelerations, velocities  # noqa: E402
from estimator.settings import Settings  # noqa: E402

NEAR = 2  # knots on each side of a join


def seams(name: str, window_s: float, method: str, **overrides: object) -> dict:
    config = load_config(ROOT / "configs" / f"{name}.toml")
    log_path = ROOT / "recordings" / f"{name}.mcap"
    log = read_log(log_path, config)
    settings = replace(Settings.from_config(config), window_s=window_s, method=method, **overrides)
    started = time.perf_counter()
    est, summary = estimate(config, log.measurements, settings)
    joins = summary.window_starts[1:]
    wall = time.perf_counter() - started
    whole, _ = estimate(config, log.measurements, replace(settings, window_s=1e6))
    model = config.load_model()
    truth = at_times(*read_ground_truth(log_path, model), est.t_ns)
    a_true = accelerations(velocities(model, truth, est.h), est.h)
    error = np.linalg.norm(est.qacc - a_true, axis=1)[2:-2]  # (ends: one-sided differences)
    near = np.zeros(len(est.t_ns), bool)
    for k in joins:
        near[max(0, k - NEAR) : k + NEAR + 1] = True
    near = near[2:-2]
    at_join, inside = error[near], error[~near]
    one_window = np.linalg.norm(whole.qacc - a_true, axis=1)[2:-2][near]
    return {
        "one_window_join_median": float(np.median(one_window)) if near.any() else None,
        "one_window_join_p95": float(np.percentile(one_window, 95)) if near.any() else None,
        "recording": name,
        "method": method,
        "windows": summary.windows,
        "joins": len(joins),
        "join_median": float(np.median(at_join)) if at_join.size else float("nan"),
        "join_p95": float(np.percentile(at_join, 95)) if at_join.size else float("nan"),
        "join_max": float(at_join.max()) if at_join.size else float("nan"),
        "interior_median": float(np.median(inside)),
        "interior_p95": float(np.percentile(inside, 95)),
        "ratio_median": float(np.median(at_join) / np.median(inside)) if at_join.size else 0.0,
        "ratio_p95": float(np.percentile(at_join, 95) / np.percentile(inside, 95))
        if at_join.size
        else 0.0,
        "wall_time_s": wall,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--recordings",
        nargs="+",
        default=["humanoid_push", "quadruped_trot", "arm_box", "go2", "h1", "panda_box"],
    )
    parser.add_argument("--window", type=float, default=1.0, help="window length, s")
    parser.add_argument("--methods", nargs="+", default=["physics"])
    parser.add_argument(
        "--join",
        nargs="+",
        default=["quiet", "fixed"],
        choices=["quiet", "fixed"],
        help="where windows hand over (the join setting); each in the same run",
    )
    parser.add_argument("--out", type=Path, default=Path("out/seams"))
    args = parser.parse_args(argv)
    rows = [
        seams(n, args.window, m, join=j) | {"join": j}
        for n in args.recordings
        for m in args.methods
        for j in args.join
    ]
    head = f"{'recording':16s} {'method':9s} {'join':6s} {'joins':>5s} {'join med':>9s} "
    head += f"{'inside med':>10s} "
    head += f"{'ratio':>6s} {'join p95':>9s} {'inside p95':>10s} {'ratio':>6s} {'max':>8s}"
    head += f" {'1-window: join med':>18s} {'p95':>6s}"
    print(head)
    for r in rows:
        print(
            f"{r['recording']:16s} {r['method']:9s} {r['join']:6s} {r['joins']:5d} "
            f"{r['join_median']:9.3g} "
            f"{r['interior_median']:10.3g} {r['ratio_median']:6.2f} {r['join_p95']:9.3g} "
            f"{r['interior_p95']:10.3g} {r['ratio_p95']:6.2f} {r['join_max']:8.3g}"
            f" {r['one_window_join_median']:18.3g} {r['one_window_join_p95']:6.3g}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    report = {
        "window_s": args.window,
        "near_knots": NEAR,
        "rows": rows,
        "machine": f"{platform.node()} {platform.machine()}, Python {platform.python_version()}",
    }
    (args.out / "seams.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out / 'seams.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
