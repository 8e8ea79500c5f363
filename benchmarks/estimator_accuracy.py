"""Accuracy of the physics smoother against ground truth on the sample recordings.

    python benchmarks/estimator_accuracy.py [--out DIR] [--recordings NAME ...]

For each recording: RMSE of hinge angles (deg) and of each free body's position (mm) and
orientation (deg)
of the raw measurements (interpolated to the knots, as the smoother is initialized) and of the
estimate, against the `/ground_truth/...` topics; the wall time of estimation and its ratio
to the log's duration. Prints a table and writes DIR/estimator_accuracy.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from estimator.config import load_config
from estimator.logs import read_log
from estimator.problem import Settings
from estimator.run import estimate, initial_trajectory
from estimator.truth import at_times, read_ground_truth, trajectory_errors

ROOT = Path(__file__).resolve().parent.parent
RECORDINGS = ("humanoid_push", "humanoid_fall", "quadruped_trot", "arm_box", "single_joint")


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
    truth = at_times(*read_ground_truth(path, model), est.t_ns)
    raw = initial_trajectory(model, log.measurements, est.t_ns)
    return {
        "duration_s": float(summary.duration_s),
        "knots": summary.knots,
        "iterations": summary.iterations,
        "wall_s": wall,
        "wall_over_duration": wall / float(summary.duration_s),
        "raw": trajectory_errors(model, raw, truth),
        "estimate": trajectory_errors(model, est.qpos, truth),
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
