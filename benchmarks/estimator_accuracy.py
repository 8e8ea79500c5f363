"""Accuracy of the estimator (and, by --methods, its baselines) on the sample recordings.

    python benchmarks/estimator_accuracy.py [--out DIR] [--recordings NAME ...] [--methods M ...]

For each recording: RMSE of hinge angles (deg) and of each free body's position (mm) and
orientation (deg) of the raw measurements (interpolated to the knots, where the smoother
starts) and of each method's estimate (`physfuse estimate --method M`, default settings),
against the `/ground_truth/...` topics; each method's wall time and its ratio to the log's
duration. Prints a table and writes DIR/estimator_accuracy.json:

    {recording: {"duration_s", "knots", "raw": {metric: RMSE},
                 method: {"errors": {metric: RMSE}, "iterations", "wall_s",
                          "wall_over_duration", "warnings"}}}
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from estimator.batch import estimate
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.io.state_topics import at_times, read_ground_truth, trajectory_errors
from estimator.run import initial_trajectory
from estimator.settings import CHOICES, Settings

ROOT = Path(__file__).resolve().parent.parent
RECORDINGS = ("humanoid_push", "humanoid_fall", "quadruped_trot", "arm_box", "single_joint")
METHODS = tuple(m for m in CHOICES["method"] if m != "raw")  # raw is every table's first column


def run(name: str, methods: list[str]) -> dict:
    config = load_config(ROOT / "configs" / f"{name}.toml")
    path = ROOT / "recordings" / f"{name}.mcap"
    log = read_log(path, config)
    settings = Settings.from_config(config)
    model = config.load_model()
    result: dict = {}
    for method in methods:
        start = time.perf_counter()
        est, summary = estimate(config, log.measurements, replace(settings, method=method))
        wall = time.perf_counter() - start
        if "raw" not in result:  # every method estimates on the same knots
            truth = at_times(*read_ground_truth(path, model), est.t_ns)
            raw = initial_trajectory(model, log.measurements, est.t_ns)
            result.update(
                duration_s=float(summary.duration_s),
                knots=summary.knots,
                raw=trajectory_errors(model, raw, truth),
            )
        result[method] = {
            "errors": trajectory_errors(model, est.qpos, truth),
            "iterations": summary.iterations,
            "wall_s": wall,
            "wall_over_duration": wall / float(summary.duration_s),
            "warnings": summary.warnings,
        }
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench"))
    parser.add_argument("--recordings", nargs="*", default=list(RECORDINGS), choices=RECORDINGS)
    parser.add_argument(
        "--methods", nargs="+", default=["physics"], choices=METHODS, help="default: physics"
    )
    args = parser.parse_args()
    results = {name: run(name, args.methods) for name in args.recordings}
    header = "".join(f" {m:>9s}" for m in args.methods)
    walls = "".join(f" {m[:4] + ' wall/T':>11s}" for m in args.methods)
    print(f"{'recording':16s} {'metric':14s} {'raw':>9s}{header}  {walls}")
    for name, r in results.items():
        for i, metric in enumerate(r["raw"]):
            errors = "".join(f" {r[m]['errors'][metric]:9.4f}" for m in args.methods)
            ratio = "".join(f" {r[m]['wall_over_duration']:10.2f}×" for m in args.methods)
            ratio = ratio if i == 0 else ""
            print(f"{name:16s} {metric:14s} {r['raw'][metric]:9.4f}{errors}  {ratio}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "estimator_accuracy.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out / 'estimator_accuracy.json'}")


if __name__ == "__main__":
    main()
