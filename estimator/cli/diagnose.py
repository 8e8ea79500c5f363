"""`physfuse diagnose LOG --config CONFIG --out DIR`: where and when the physics does not add up.

Estimates the log (the config's settings, as `physfuse estimate`), then finds unmodeled
contacts (pushes, collisions: body, interval, force ± σ), contact model errors, slips (a
contact sliding where the model's friction holds it: the distance slid) and sensor faults (a
stream's residual row that steps) in the estimate (estimator/diagnose). Prints the events as a
table and writes, whole or not at all:

    DIR/events.json       every event, the detector's settings and each body's calibration
    DIR/diagnostics.mcap  the estimate's topics (`physfuse estimate`'s layout) plus
                          /diagnostics (DiagnosticArray) and /diagnostics/unmodeled_force/<body>
                          (WrenchStamped): open it in Foxglove next to the log
    DIR/diagnostics.rrd   the estimate's Rerun recording with the events on its timeline, each
                          unmodeled contact's force as an arrow on its body and the detector's
                          statistic per body (estimator/io/rerun.py): `rerun DIR/diagnostics.rrd`
"""

from __future__ import annotations

import argparse
import json
import sys
import uuid
from dataclasses import replace
from pathlib import Path

from estimator.batch import estimate
from estimator.config import load_config
from estimator.diagnose import DetectorSettings, diagnose
from estimator.diagnose.report import events_json, table, write_mcap
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.io.mcap_writer import EstimateWriter
from estimator.io.outputs import OutputFolder
from estimator.io.rerun import write_recording
from estimator.model_checks import check_for_estimate
from estimator.settings import Settings

OUTPUTS = ("events.json", "diagnostics.mcap", "diagnostics.rrd")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, help="ROS 2 MCAP file or rosbag2 folder")
    parser.add_argument("--config", type=Path, required=True, help="TOML config (configs/)")
    parser.add_argument("--out", type=Path, default=Path("out/diagnose"), help="output dir")
    defaults = DetectorSettings()
    parser.add_argument(
        "--false-alarms-per-min",
        type=float,
        default=defaults.false_alarms_per_min,
        metavar="RATE",
        help="target false-alarm rate that sets every threshold "
        f"(default {defaults.false_alarms_per_min:g})",
    )
    parser.add_argument(
        "--window",
        type=float,
        default=defaults.window_s,
        metavar="S",
        help=f"length of the unmodeled-force fit's window, s (default {defaults.window_s:g})",
    )


def run(args: argparse.Namespace) -> int:
    for option, value in (
        ("--false-alarms-per-min", args.false_alarms_per_min),
        ("--window", args.window),
    ):
        if not value > 0:
            raise ConfigError(f"{option} {value:g}: expected a positive number")
    config = load_config(args.config)
    settings = Settings.from_config(config)
    if settings.method != "physics":
        settings = replace(settings, method="physics")  # the physics residual is the signal
    check_for_estimate(config, settings)
    detector = DetectorSettings(
        window_s=args.window, false_alarms_per_min=args.false_alarms_per_min
    )
    with OutputFolder(args.out, OUTPUTS) as tmp:
        log = read_log(args.log, config)
        for warning in log.warnings:
            print(f"physfuse diagnose: warning: {warning}", file=sys.stderr)
        est, _ = estimate(config, log.measurements, settings)
        diagnosis = diagnose(config, log.measurements, est, settings, detector)
        t0 = int(est.t_ns[0])
        model = config.load_model()
        imu_sites = {s.name: s.elements[0] for s in config.streams.values() if s.kind == "imu"}
        with EstimateWriter(
            tmp / "diagnostics.mcap", model, est.model_name, est.h, str(uuid.uuid4())
        ) as out:
            out.write(est, range(est.T), imu_sites)
            write_mcap(out.writer, diagnosis)
        (tmp / "events.json").write_text(json.dumps(events_json(diagnosis, t0), indent=2) + "\n")
        write_recording(
            est, model, log, path=tmp / "diagnostics.rrd", diagnosis=diagnosis,
            application_id="physfuse diagnose",
        )  # fmt: skip
    print(table(diagnosis, t0))
    print(f"outputs: {', '.join(str(args.out / n) for n in OUTPUTS)}")
    return 0
