"""`physfuse calibrate LOG --config CONFIG`: fit the model's contact softness to a log.

    physfuse calibrate LOG --config CONFIG [--setting softness_eps|softness_kappa]
        [--range LO HI] [--points N] [--duration S] [--out DIR] [--config-out PATH]
        [--workers N | --ray-address ADDR]

Profiles the mocap part of the physics estimate's cost over the setting
(`estimator/calibrate.py`), prints the profile and the best value, and writes
DIR/calibration.json and DIR/calibration.png; with --config-out, CONFIG with the value set in
its [estimator] table, ready for `physfuse estimate`. With --workers or --ray-address the
grid's estimates run in parallel as Ray tasks (a local Ray or a cluster, as `physfuse
estimate` runs many logs: estimator/fleet.py). DIR (and --config-out) are checked
before the first estimate, and the outputs put in place only when the run completes
(estimator/io/outputs.py).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from estimator.calibrate import (
    CALIBRATED,
    GRID_POINTS,
    IDENTIFIED_COST,
    Calibration,
    Point,
    calibrate,
    config_with,
)
from estimator.config import Config, load_config
from estimator.errors import PhysfuseError
from estimator.evaluate import json_ready
from estimator.fleet import ray_session
from estimator.io.logs import read_log
from estimator.io.outputs import OutputFile, OutputFolder
from estimator.model_checks import check_for_estimate
from estimator.run import samples_within
from estimator.settings import Settings

OUTPUTS = ("calibration.json", "calibration.png")  # one run's set, written whole


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log", type=Path, help="ROS 2 MCAP file, rosbag2 folder, FIFO, or - for standard input"
    )
    parser.add_argument("--config", type=Path, required=True, help="TOML config (configs/)")
    parser.add_argument(
        "--setting",
        choices=CALIBRATED,
        default="softness_eps",
        help="the setting to fit (default softness_eps: ε of paper Section V)",
    )
    parser.add_argument(
        "--range",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="grid from LO to HI, geometric (default: 7 values ×1.15 apart around the config's)",
    )
    parser.add_argument(
        "--points", type=int, default=GRID_POINTS, help=f"grid values (default {GRID_POINTS})"
    )
    parser.add_argument("--duration", type=float, help="use the first S s of the log only")
    parser.add_argument("--out", type=Path, default=Path("out/calibrate"), help="output dir")
    parser.add_argument(
        "--config-out", type=Path, help="write CONFIG with the fitted value in [estimator]"
    )
    parser.add_argument("--quiet", action="store_true", help="no line per evaluated value")
    ray = parser.add_mutually_exclusive_group()
    ray.add_argument(
        "--workers", type=int, help="the grid's estimates in parallel on a local Ray of N workers"
    )
    ray.add_argument(
        "--ray-address", help="the grid's estimates on an existing Ray cluster (HEAD_IP:6379)"
    )


def run(args: argparse.Namespace) -> int:
    if args.range is not None and not 0 < args.range[0] < args.range[1]:
        raise PhysfuseError(f"--range {args.range[0]:g} {args.range[1]:g}: expected 0 < LO < HI")
    if args.points < 3:
        raise PhysfuseError(f"--points {args.points}: expected 3 or more")
    if args.duration is not None and args.duration <= 0:
        raise PhysfuseError(f"--duration {args.duration:g}: expected a positive number of s")
    if args.workers is not None and args.workers < 1:
        raise PhysfuseError(f"--workers {args.workers}: expected 1 or more")
    config = load_config(args.config)
    settings = Settings.from_config(config)
    # what every estimate of the profile will meet, before the log is read
    check_for_estimate(config, replace(settings, method="physics", fit_softness="none"))
    out: Path = args.out
    with contextlib.ExitStack() as outputs:  # checked before the minutes of estimates
        tmp = outputs.enter_context(OutputFolder(out, OUTPUTS))
        config_out = None
        if args.config_out is not None:  # unchanged: left as it is, its time stamp too
            new_config = OutputFile(args.config_out, "--config-out", keep_unchanged=True)
            config_out = outputs.enter_context(new_config)
        result = _calibrate(args, config, settings)
        report = {
            "log": str(args.log),
            "config": str(args.config),
            "duration_s": args.duration,  # None: the whole log
            **asdict(result),
        }
        (tmp / "calibration.json").write_text(json.dumps(json_ready(report), indent=2) + "\n")
        plot(result, tmp / "calibration.png")
        if config_out is not None:
            config_with(args.config, config_out, args.setting, result.best)
    _print(result)
    if args.config_out is not None:
        print(f"wrote {args.config_out}: {args.config} with [estimator] {args.setting} set")
    print(f"outputs: {', '.join(str(out / n) for n in OUTPUTS)}")
    return 0


def _calibrate(args: argparse.Namespace, config: Config, settings: Settings) -> Calibration:
    """Read the log (its first --duration s) and profile the setting over the grid."""
    log = read_log(args.log, config)
    for warning in log.warnings:
        print(f"physfuse calibrate: warning: {warning}", file=sys.stderr)
    measurements = log.measurements
    if args.duration is not None:
        t0 = min(int(m.t_ns[0]) for m in measurements.values() if len(m.t_ns))
        t1 = t0 + round(args.duration * 1e9)
        measurements = {name: samples_within(m, t0, t1) for name, m in measurements.items()}
    grid = None
    if args.range is not None:
        grid = [float(v) for v in np.geomspace(args.range[0], args.range[1], args.points)]

    def progress(p: Point) -> None:
        if not args.quiet:
            print(f"  {args.setting} = {p.value:.5g}: mocap cost {p.mocap_cost:.1f} "
                  f"({p.wall_time_s:.1f} s)", flush=True)  # fmt: skip

    print(f"calibrating {args.setting} on {args.log} (each value: one physics estimate)")
    if not (args.workers or args.ray_address):
        return calibrate(config, measurements, settings, args.setting, grid, progress)
    with ray_session(args.workers, args.ray_address):
        return calibrate(config, measurements, settings, args.setting, grid, progress, True)


def _print(result: Calibration) -> None:
    initial = min(result.points, key=lambda p: abs(p.value - result.initial))
    print(f"\n{'value':>10} {'mocap cost':>12} {'whole cost':>12} {'time s':>7}")
    for p in sorted(result.points, key=lambda p: p.value):
        mark = "  ← best" if p.value == result.best and result.identified else ""
        print(f"{p.value:10.5g} {p.mocap_cost:12.1f} {p.cost:12.1f} {p.wall_time_s:7.1f}{mark}")
    if not result.identified:
        costs = [p.mocap_cost for p in result.points]
        print(
            f"\nnot identified: the mocap cost varies by {max(costs) - min(costs):.3g} over the "
            f"grid (< {IDENTIFIED_COST}): this log does not show {result.setting}; keeping the "
            f"config's {result.initial:.4g}"
        )
        return
    best = result.point(result.best)
    if math.isclose(initial.value, result.initial):
        against = f"the config's {result.initial:.4g}: {initial.mocap_cost:.1f}"
    else:
        against = f"nearest the config's {result.initial:.4g}, {initial.value:.4g}: "
        against += f"{initial.mocap_cost:.1f}"
    print(f"\nbest: {result.setting} = {result.best:.4g}, mocap cost {best.mocap_cost:.1f} "
          f"({against})")  # fmt: skip
    if result.sigma_log is not None:
        print(f"σ: ×/÷ {math.exp(result.sigma_log):.3f} (where the mocap cost rises by "
              f"{IDENTIFIED_COST} on the parabola)")  # fmt: skip
    if result.at_edge:
        print(
            "warning: the lowest mocap cost is at an end of the grid, extended as far as it "
            "spans (or at κ's 2h floor); the minimum may lie beyond it (widen --range)",
            file=sys.stderr,
        )
    print(f"to use it: [estimator] {result.setting} = {result.best:.4g} in the config")


def plot(result: Calibration, path: Path) -> None:
    """The mocap cost over the setting, the config's value and the best one marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    points = sorted(result.points, key=lambda p: p.value)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([p.value for p in points], [p.mocap_cost for p in points], "o-", color="C0")
    ax.axvline(result.initial, color="0.6", linestyle="--", label=f"config {result.initial:.4g}")
    ax.axvline(result.best, color="C3", label=f"best {result.best:.4g}")
    if result.sigma_log is not None:
        spread = math.exp(result.sigma_log)
        ax.axvspan(result.best / spread, result.best * spread, color="C3", alpha=0.15, label="±σ")
    if not result.identified:
        ax.set_title(f"not identified: {result.setting} stays at the config's")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(ScalarFormatter())
    ax.set_xlabel(result.setting)
    ax.set_ylabel("mocap cost of the estimate")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
