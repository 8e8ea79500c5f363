"""`physfuse estimate LOG --config CONFIG --out DIR [--spawn | --serve]`: smooth a whole log.

Many logs (`LOG...`: files, globs, folders, list files) with `--workers N` or `--ray-address
ADDR` run as a fleet of Ray tasks, DIR/<log name> each (estimator/fleet.py).

Writes DIR/estimate.mcap (the `/estimate/...` topic layout), DIR/estimate.rrd (Rerun) and
DIR/summary.json, and prints a summary — with errors against ground truth when the log has
`/ground_truth/...` topics (a simulated log). DIR is checked before the log is read and the
three files are put in place together when the run completes (estimator/io/outputs.py): DIR
holds one run's set, never parts of two. A viewer that cannot open (--spawn without a
display, --serve on a busy port) is a warning: the files are written.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import sys
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import mujoco
from tqdm import tqdm

from estimator import chunks, fleet
from estimator.batch import estimate
from estimator.config import Config, load_config
from estimator.errors import ConfigError, LogError
from estimator.estimate import Estimate
from estimator.io.logs import Measurement, read_log
from estimator.io.mcap_writer import EstimateWriter
from estimator.io.outputs import OutputFolder
from estimator.io.state_topics import at_times, read_ground_truth, trajectory_errors
from estimator.model_checks import (
    check_for_estimate,
    command_warnings,
    commands_against_efforts,
)
from estimator.run import Summary, initial_trajectory
from estimator.settings import CHOICES, SETTINGS, Settings

OUTPUTS = ("estimate.mcap", "estimate.rrd", "summary.json")  # one run's set, written whole


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log",
        type=Path,
        nargs="+",
        help="ROS 2 MCAP file, rosbag2 folder, FIFO, or - for standard input; several (files, "
        "globs, folders of logs, .txt lists): one estimate each, as Ray tasks",
    )
    parser.add_argument(
        "--config",
        type=Path,
        required=True,
        help="TOML config (configs/); with several logs, a folder: FOLDER/<log name>.toml each",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/estimate"),
        help="output dir (several logs: DIR/<log name> each, DIR/fleet.csv and fleet.json)",
    )
    parser.add_argument(
        "--chunk",
        type=float,
        metavar="S",
        help="one long log in chunks of S s solved in parallel as Ray tasks and joined (with "
        "--workers or --ray-address; default a local Ray, a worker per core)",
    )
    parser.add_argument(
        "--chunk-overlap",
        type=float,
        default=chunks.OVERLAP_S,
        metavar="S",
        help=f"log each chunk sees past its ends, s (default {chunks.OVERLAP_S:g})",
    )
    fleet = parser.add_mutually_exclusive_group()
    fleet.add_argument(
        "--workers", type=int, help="several logs on a local Ray with N workers (default: cores)"
    )
    fleet.add_argument(
        "--ray-address", help="several logs on an existing Ray cluster (e.g. HEAD_IP:6379)"
    )
    view = parser.add_mutually_exclusive_group()
    view.add_argument("--spawn", action="store_true", help="open a Rerun viewer")
    view.add_argument("--serve", action="store_true", help="serve a Rerun web viewer")
    parser.add_argument(
        "--method",
        choices=CHOICES["method"],
        help="physics (default): the physics-prior smoother; baselines: kinematic (the same "
        "smoother without physics factors, constant-acceleration prior), ekf / ukf (filters "
        "with the forward dynamics as process model), raw (measurements interpolated)",
    )
    parser.add_argument(
        "--path", choices=CHOICES["path"], help="physics path (default: config/native)"
    )
    parser.add_argument(
        "--window", type=float, help="window length in s (default 4; 0.5 for a log without mocap)"
    )
    parser.add_argument(
        "--iterations", type=int, help="Levenberg–Marquardt iterations per solve (default 30)"
    )
    parser.add_argument(
        "--init",
        choices=CHOICES["init"],
        help="where each window's physics solve starts (default: config/best, from the "
        "kinematic smoother's solution and from the measurements, the lower cost kept; "
        "best_across_gaps: both only where the measurements have a gap or that solve does not "
        "converge; measurements: one solve)",
    )
    add_start_pose_argument(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def add_start_pose_argument(parser: argparse.ArgumentParser) -> None:
    """--start-pose X Y YAW_DEG (estimate, stream): `Config.starting_at`."""
    parser.add_argument(
        "--start-pose",
        nargs=3,
        type=float,
        metavar=("X", "Y", "YAW_DEG"),
        help="where a log without mocap starts: the free base's x, y (m) and heading (°), "
        "which the estimate is relative to (default: config start_pose, else the model's "
        "home keyframe)",
    )


def run(args: argparse.Namespace) -> int:
    parallel = args.workers or args.ray_address
    if len(args.log) > 1 or _names_many(args.log[0]) or (parallel and args.chunk is None):
        if args.chunk is not None:
            raise ConfigError("--chunk cuts one log: give one log")
        return _run_fleet(args)
    args.log = args.log[0]
    config = load_config(args.config)
    if args.start_pose is not None:
        config = config.starting_at(*args.start_pose)
    settings = Settings.from_config(config)
    overrides = {
        "method": args.method,
        "path": args.path,
        "window_s": args.window,
        "window_s_no_mocap": args.window,
        "max_iterations": args.iterations,
        "init": args.init,
    }
    settings = replace(settings, **{k: v for k, v in overrides.items() if v is not None})
    check_for_estimate(config, settings)  # the model and settings, before the log is read
    if args.chunk is not None:
        chunks.check(settings, args.chunk, args.chunk_overlap)
        chunks.check_log(args.log)
    out: Path = args.out
    run_id = str(uuid.uuid4())  # in summary.json, estimate.mcap and estimate.rrd: one run's set
    # --out checked and locked before the log is read; written whole when the run completes
    with OutputFolder(out, OUTPUTS) as tmp:
        if args.chunk is not None:
            report, summary, input_warnings, shown = _estimate_in_chunks(
                args, config, settings, tmp, run_id
            )
        else:
            report, summary, input_warnings, shown = _estimate_whole(
                args, config, settings, tmp, run_id
            )
    model = config.load_model()
    from estimator.io.rerun import ViewerError, serve_until_interrupted, show_recording

    _print(report, summary, input_warnings)
    print(f"outputs: {', '.join(str(out / n) for n in OUTPUTS)}")
    print(f"open the recording with: rerun {out / 'estimate.rrd'}")
    if args.spawn or args.serve:
        try:  # the outputs are complete: a viewer that cannot open is only a warning
            show_recording(shown, model, out / "estimate.rrd", spawn=args.spawn, serve=args.serve)
        except ViewerError as err:
            rrd = out / "estimate.rrd"
            print(f"physfuse estimate: warning: {err} (written: rerun {rrd})", file=sys.stderr)
            return 0
    if args.serve:
        serve_until_interrupted()
    return 0


def _estimate_whole(
    args: argparse.Namespace, config: Config, settings: Settings, tmp: Path, run_id: str
) -> tuple[dict[str, Any], Summary, list[str], Estimate]:
    """The log read whole, estimated, its three outputs written into `tmp`."""
    log = read_log(args.log, config)
    skipped = skipped_samples(log.measurements)
    # the log's, and commands that disagree with the logged efforts through the actuators
    input_warnings = list(log.warnings) + command_warnings(
        commands_against_efforts(config, config.load_model(), log.measurements)
    )
    for warning in input_warnings:
        print(f"physfuse estimate: warning: {warning}", file=sys.stderr)
    for line in skipped_lines(skipped):
        print(f"physfuse estimate: {line}", file=sys.stderr)
    with _progress_bar(args.quiet) as progress:
        est, summary = estimate(config, log.measurements, settings, progress)
    summary = replace(summary, warnings=input_warnings + summary.warnings)
    model = config.load_model()
    imu_sites = _imu_sites(config)
    with EstimateWriter(tmp / "estimate.mcap", model, est.model_name, est.h, run_id) as out_mcap:
        out_mcap.write(est, range(est.T), imu_sites)
    accuracy = _accuracy(args.log, model, log.measurements, est)
    lost = [asdict(x) for x in log.lost]
    report = _report(summary, settings, accuracy, args.out, run_id, skipped, lost)
    from estimator.io.rerun import write_recording

    write_recording(est, model, log, path=tmp / "estimate.rrd", recording_id=run_id)
    (tmp / "summary.json").write_text(json.dumps(report, indent=2) + "\n")
    return report, summary, input_warnings, est


def _estimate_in_chunks(
    args: argparse.Namespace, config: Config, settings: Settings, tmp: Path, run_id: str
) -> tuple[dict[str, Any], Summary, list[str], Estimate]:
    """The log in chunks on Ray (`estimator.chunks`), each part written to the outputs in
    `tmp` as it comes: memory holds a few chunks, not the log."""
    from estimator.io.rerun import RecordingWriter

    model = config.load_model()
    imu_sites = _imu_sites(config)
    h = settings.h or float(model.opt.timestep)
    shown: list[Estimate] = []
    command_lines: list[str] = []
    with (
        EstimateWriter(tmp / "estimate.mcap", model, config.model_ref, h, run_id) as out_mcap,
        RecordingWriter(tmp / "estimate.rrd", model, 0, run_id) as rrd,
        _progress_bar(args.quiet) as progress,
    ):

        def write(part: chunks.Part) -> None:
            if not shown:  # the recording's time origin: the first knot (a copy of it)
                shown.append(copy.deepcopy(part.estimate.at(slice(0, 1))))
                rrd.t0_ns = int(part.estimate.t_ns[0])
                # commands that disagree with the logged efforts, over the first chunk
                checks = commands_against_efforts(config, model, part.log.measurements)
                command_lines.extend(command_warnings(checks))
                for line in command_lines:
                    print(f"physfuse estimate: warning: {line}", file=sys.stderr)
            out_mcap.write(part.estimate, range(part.estimate.T), imu_sites)
            rrd.write(part.estimate, part.log)

        run = chunks.estimate_chunked(
            args.config,
            args.log,
            settings,
            args.chunk,
            write,
            args.chunk_overlap,
            args.workers,
            args.ray_address,
            progress,
        )
    for warning in run.warnings:
        print(f"physfuse estimate: warning: {warning}", file=sys.stderr)
    for line in skipped_lines(run.skipped):
        print(f"physfuse estimate: {line}", file=sys.stderr)
    input_warnings = run.warnings + command_lines
    summary = replace(run.summary, warnings=input_warnings + run.summary.warnings)
    lost = [asdict(x) for x in run.lost]
    report = _report(summary, settings, run.accuracy, args.out, run_id, run.skipped, lost)
    (tmp / "summary.json").write_text(json.dumps(report, indent=2) + "\n")
    return report, summary, input_warnings, shown[0]


@contextlib.contextmanager
def _progress_bar(quiet: bool) -> Iterator[Callable[[int, int], None]]:
    """progress(done, total) on a bar on stderr (none when quiet or not a terminal)."""
    bar = tqdm(total=0, unit="window", disable=quiet or not sys.stderr.isatty())

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        yield progress
    finally:
        bar.close()


def _imu_sites(config: Config) -> dict[str, str]:
    return {s.name: s.elements[0] for s in config.streams.values() if s.kind == "imu"}


def _names_many(log: Path) -> bool:
    """A glob, a list file or a folder of logs (not one rosbag2 folder)."""
    text = str(log)
    return (
        any(c in text for c in "*?[")
        or (log.suffix in fleet.LIST_SUFFIXES and log.is_file())
        or (log.is_dir() and not (log / "metadata.yaml").exists())
    )


def _run_fleet(args: argparse.Namespace) -> int:
    """Several logs: one estimate each as a Ray task; the fleet's table; status 1 when a log
    failed."""
    if args.spawn or args.serve:
        raise ConfigError("--spawn / --serve open one log's estimate: give one log")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: expected 1 or more")
    logs = fleet.expand_logs(args.log)
    options = []
    for flag, value in (
        ("--method", args.method),
        ("--path", args.path),
        ("--window", args.window),
        ("--iterations", args.iterations),
        ("--init", args.init),
    ):
        if value is not None:
            options += [flag, str(value)]
    if args.start_pose is not None:
        options += ["--start-pose", *map(str, args.start_pose)]
    workers = f"{args.workers} workers" if args.workers else "a worker per core"
    where = (
        f"the Ray cluster at {args.ray_address}" if args.ray_address else f"a local Ray, {workers}"
    )
    print(f"estimating {len(logs)} logs on {where}", file=sys.stderr)
    progress = None if args.quiet else fleet.Progress()
    try:
        rows = fleet.run_fleet(
            logs, args.config, args.out, options, args.workers, args.ray_address, progress
        )
    finally:
        if progress is not None:
            progress.close()
    print(fleet.table(rows))
    print(f"outputs: {args.out / 'fleet.csv'}, {args.out / 'fleet.json'}, {args.out}/<log name>/")
    return 0 if all(r.status == "ok" for r in rows) else 1


def skipped_samples(measurements: Mapping[str, Measurement]) -> dict[str, dict[str, Any]]:
    """Per stream: the samples kept, those skipped and why (the counts `inspect` shows)."""
    return {
        name: {
            "kept": len(m),
            "skipped": m.bad.total,
            "by_reason": {k: v for k, v in m.bad.as_dict().items() if v},
        }
        for name, m in measurements.items()
    }


def skipped_lines(skipped: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """One line per stream with skipped samples, e.g.
    `imu: skipped 3 of 2000 samples (backwards_time=2, nan=1)`."""
    return [
        f"{name}: skipped {s['skipped']} of {s['kept'] + s['skipped']} samples ("
        + ", ".join(f"{k}={v}" for k, v in s["by_reason"].items())
        + ")"
        for name, s in skipped.items()
        if s["skipped"]
    ]


def _accuracy(
    log_path: Path, model: mujoco.MjModel, measurements: Any, est: Estimate
) -> dict[str, dict[str, float]] | None:
    """Errors of the raw measurements and of the estimate against ground truth, if any (a
    stream — standard input, a FIFO — is read once: none)."""
    if not (log_path.is_file() or log_path.is_dir()):
        return None
    try:
        truth = at_times(*read_ground_truth(log_path, model), est.t_ns)
    except LogError:
        return None
    raw = initial_trajectory(model, measurements, est.t_ns)
    return {
        "raw": trajectory_errors(model, raw, truth),
        "estimate": trajectory_errors(model, est.qpos, truth),
    }


def _report(
    summary: Summary,
    settings: Settings,
    accuracy: dict | None,
    out: Path,
    run_id: str,
    skipped: dict[str, dict[str, Any]],
    lost: list[dict[str, Any]],
) -> dict[str, Any]:
    report = {"run_id": run_id, **asdict(summary)}
    report["settings"] = asdict(settings)
    report["setting_meanings"] = {k: v[1] for k, v in SETTINGS.items()}
    report["accuracy_vs_ground_truth"] = accuracy
    report["warnings"] = summary.warnings  # the log's first, then the estimate's
    report["skipped_samples"] = skipped
    report["lost"] = list(lost)  # damaged or missing stretches of the log (LostData)
    report["outputs"] = [str(out / n) for n in OUTPUTS]
    return report


def _stages(report: dict[str, Any]) -> str:
    """What the iteration count adds up for the physics smoother's starts (`init`)."""
    settings = report.get("settings", {})
    if settings.get("method") != "physics":
        return ""
    if settings.get("init") == "kinematic":
        return " (kinematic + physics from it)"
    if settings.get("init") not in ("best", "best_across_gaps"):
        return ""
    kept, tried = report.get("kept_starts", []), report.get("starts_tried", [])
    both = [k for k, t in zip(kept, tried, strict=True) if len(t) > 1]
    if not both:
        return " (physics from the measurements)"
    return (
        f" (physics from the measurements; in {len(both)} of {len(tried)} window(s) also "
        "kinematic + physics from it, whose solution had the lower cost in "
        f"{both.count('kinematic')})"
    )


def _print(report: dict[str, Any], summary: Summary, printed: list[str]) -> None:
    status = "converged" if all(summary.converged) else "NOT converged in every window"
    print(
        f"estimated {summary.duration_s:.2f} s of log: {summary.knots} knots of "
        f"{summary.h * 1e3:g} ms in {summary.windows} window(s), "
        f"{sum(summary.iterations)} iterations{_stages(report)}, {status}; wall time "
        f"{summary.wall_time_s:.1f} s "
        f"({summary.wall_time_s / max(summary.duration_s, 1e-9):.1f}× the log)"
    )
    fit = summary.softness_fit
    if fit:
        print(
            f"contact softness fitted on the log's start ({fit['rounds']:.0f} rounds"
            f"{'' if fit.get('settled', 1.0) else ', still moving: σ at least its last step'}"
            f"): the model's ε × {fit['eps_scale']:.4g} ± {fit['eps_scale_sigma']:.2g}, κ × "
            f"{fit['kappa_scale']:.4g} ± {fit['kappa_scale_sigma']:.2g}"
        )
    print(
        "final cost by factor type: "
        + ", ".join(
            f"{k} {v:.4g}" for k, v in sorted(summary.cost_by_type.items(), key=lambda kv: -kv[1])
        )
    )
    for r in summary.largest_residuals[:3]:
        print(
            f"  largest residual: {r['factor']} {r['row']} at {r['time_s']:.2f} s: "
            f"{r['whitened']:+.1f}σ"
        )
    accuracy = report["accuracy_vs_ground_truth"]
    if accuracy:
        print("against ground truth (RMSE):      raw   estimate")
        for metric, raw in accuracy["raw"].items():
            print(f"  {metric:28s} {raw:9.3f} {accuracy['estimate'][metric]:9.3f}")
    for warning in summary.warnings[len(printed) :]:  # those not printed before the estimate
        print(f"physfuse estimate: warning: {warning}", file=sys.stderr)
