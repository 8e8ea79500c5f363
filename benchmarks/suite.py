"""The benchmark suite: the physics smoother against the baselines, scenario × condition.

    python benchmarks/suite.py [--out DIR] [--work DIR] [--scenarios NAME ...]
        [--conditions NAME ...] [--methods NAME ...] [--duration S] [--seed N]
        [--workers N | --ray-address ADDR]
        [--timeout S] [--no-mismatch] [--no-calibration]

For every scenario and condition (`physfuse simulate SCENARIO --condition CONDITION`,
estimator/simulate/conditions.py) it simulates a log with ground truth (cached in
WORK/logs by scenario, condition, seed and duration), then for every method runs

    physfuse estimate LOG --config CONFIG --out RUN --method METHOD --quiet
    physfuse evaluate RUN/estimate.mcap --truth LOG --config CONFIG --out RUN

each as a subprocess with a time limit. CONFIG is the log's own with its robot's contact
softness, fitted first by `physfuse calibrate` on the robot's nominal log (the `mismatch`
condition's robot on its own log; --no-calibration: the log's config as simulated). A step
that fails becomes a "failed: <its last error line>" entry instead of stopping the suite. It
prints one table (scenario × condition × method rows, the metrics of `metrics.json`'s
"summary" and wall time / log duration as columns), the same errors over the mocap
occlusions for the runs that had any, then the checklist of the targets:

    1. on every scenario and condition the physics smoother's position, orientation,
       joint-angle and velocity errors are lower than every baseline's;
    2. during mocap occlusions its position and orientation errors are at most a third of
       the kinematic smoother's;
    3. in nominal conditions its net contact force error is at most 10% of the robot's weight.

The public robots (`PUBLIC_ROBOTS`: MuJoCo Menagerie's Go2, H1 and Panda with a box) are
simulated with `physfuse simulate --model` and never calibrated: their runs take the default
settings and each model's own contact settings, as a new user's first run would.

--no-mismatch simulates every log with the robot exactly its model (`physfuse simulate
--no-mismatch`; the same seed draws the same noise, controller and pushes): what is left of a
miss then is the estimator's, not the model's. Its logs and runs are kept apart in WORK
(`-exact-model` in their names); the `mismatch` condition contradicts it.

It writes OUT/suite.json (settings, every run with its metrics and errors, the checklist),
OUT/suite.txt (the printed tables and checklist), OUT/suite.md (the tables in Markdown, for
the README) and one PNG per metric (OUT/<metric>.png:
grouped bars, method × (scenario, condition), log scale).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from estimator.calibrate import config_with  # noqa: E402
from estimator.evaluate import FORCE_KEYS, TRAJECTORY_KEYS  # noqa: E402
from estimator.fleet import as_task, ray_session  # noqa: E402
from estimator.simulate import SCENARIOS  # noqa: E402
from estimator.simulate.conditions import CONDITIONS  # noqa: E402

PHYSFUSE = [sys.executable, "-m", "estimator.cli"]
METHODS = ("physics", "kinematic", "ekf", "ukf", "raw")
# GTSAM's legged estimators: for legged robots without mocap (`--conditions no_mocap`)
LEGGED_METHODS = ("gtsam-legged-ekf", "gtsam-legged-smoother")
BASELINES = ("kinematic", "ekf", "ukf", "raw", *LEGGED_METHODS)
DURATION_S = 4.0  # ≥ 3 s: two occlusions; the whole suite in ~15 min on 2 cores (README)
TIMEOUT_S = 600.0

# metric key of metrics.json "summary" → (column header, lower is better)
METRICS: Mapping[str, tuple[str, bool]] = {
    "position_mm": ("pos mm", True),
    "orientation_deg": ("rot °", True),
    "joint_deg": ("joint °", True),
    "linear_velocity_mps": ("v m/s", True),
    "angular_velocity_dps": ("ω °/s", True),
    "joint_velocity_dps": ("q̇ °/s", True),
    "contact_force_N": ("F N", True),
    "contact_force_pct_weight": ("F %mg", True),
    "contact_precision": ("c.prec", False),
    "contact_recall": ("c.rec", False),
    "imu_accel_bias_mps2": ("ba m/s²", True),
    "imu_gyro_bias_dps": ("bg °/s", True),
    "position_anees": ("ANEES", True),  # eᵀΣ⁻¹e/3 of the position: 1 when honest
    "position_drift_pct": ("drift%", True),  # no mocap: what proprioception cannot hold
    "yaw_drift_deg_per_m": ("yaw°/m", True),
    "tilt_deg": ("tilt °", True),
    "wall_over_duration": ("wall/T", True),
}
# the same errors while mocap was occluded (`physfuse evaluate`: a body's pose and twist over
# its own occlusions, joints and contact forces over any body's); their own table
OCCLUDED_METRICS: Mapping[str, tuple[str, bool]] = {
    f"occluded_{key}": METRICS[key] for key in (*TRAJECTORY_KEYS, *FORCE_KEYS)
} | {"occluded_s": ("occ s", True)}
ALL_METRICS = {**METRICS, **OCCLUDED_METRICS}
BEATS_BASELINES = TRAJECTORY_KEYS
OCCLUSION_TARGET = ("occluded_position_mm", "occluded_orientation_deg")
OCCLUSION_RATIO = 1.0 / 3.0  # physics ≤ this × kinematic during occlusions
FORCE_PCT_WEIGHT = 10.0  # physics net contact force RMSE ≤ this % of m·g, nominal condition


@dataclass
class Run:
    """One method on one log: where it ran, its metrics summary, or why it failed."""

    scenario: str
    condition: str
    method: str
    metrics: dict[str, float | None] = field(default_factory=dict)
    error: str | None = None
    wall_time_s: float | None = None  # estimation alone (summary.json)
    duration_s: float | None = None  # the estimated log (summary.json)
    process_s: float = 0.0  # both subprocesses, start-up and writing included
    folder: str = ""
    reused: bool = False  # metrics from an earlier run (--reuse-runs)

    @property
    def key(self) -> tuple[str, str]:
        return self.scenario, self.condition


# -- running ----------------------------------------------------------------------------------
def call(argv: Sequence[str], timeout_s: float, transcript: Path) -> str | None:
    """Run `physfuse argv`; None when it succeeded, else one line saying why not.

    Its stdout and stderr go to `transcript`."""
    try:
        proc = subprocess.run(
            [*PHYSFUSE, *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout_s:g} s: physfuse {argv[0]}"
    except OSError as err:
        return f"cannot run physfuse {argv[0]}: {err}"
    with transcript.open("a") as f:
        f.write(f"$ physfuse {' '.join(argv)}\n{proc.stdout}{proc.stderr}\n")
    if proc.returncode == 0:
        return None
    lines = [line.strip() for line in (proc.stderr or proc.stdout).splitlines() if line.strip()]
    return lines[-1] if lines else f"physfuse {argv[0]} exited with status {proc.returncode}"


# public robots from MuJoCo Menagerie (physics/models/menagerie, docs/menagerie.md), simulated
# with `physfuse simulate --model`; estimated with default settings and the model's own
# contact settings: never calibrated
PUBLIC_ROBOTS: Mapping[str, tuple[str, ...]] = {
    "go2": ("--model", "physics/models/menagerie/go2.xml", "--excitation", "0.1",
            "--pushes", "base"),
    "h1": ("--model", "physics/models/menagerie/h1.xml", "--pushes", "pelvis"),
    "panda_box": ("--model", "physics/models/menagerie/panda_box.xml", "--excitation", "0.2",
                  "--markers", "box_marker0", "box_marker1", "box_marker2", "box_marker3"),
    "anymal_c": ("--model", "physics/models/menagerie/anymal_c.xml", "--excitation", "0.1",
                 "--pushes", "base"),
}  # fmt: skip
CALIBRATED_SETTING = "softness_eps"  # fitted per robot before the runs (--no-calibration)
EXACT_MODEL = "-exact-model"  # in the names of --no-mismatch logs and runs


def simulate_log(
    scenario: str,
    condition: str,
    seed: int,
    duration_s: float,
    logs: Path,
    timeout_s: float,
    mismatch: bool = True,
) -> tuple[Path, Path, str | None]:
    """The cached log and config of (scenario, condition, seed, duration, mismatch); simulated
    if absent. mismatch=False: the robot is exactly its model."""
    stem = f"{scenario}-{condition}-seed{seed}-{duration_s:g}s" + ("" if mismatch else EXACT_MODEL)
    log, config = logs / f"{stem}.mcap", logs / f"{stem}.toml"
    if log.exists() and config.exists():
        return log, config, None
    partial_log, partial_config = logs / f"{stem}.partial.mcap", logs / f"{stem}.partial.toml"
    what = list(PUBLIC_ROBOTS.get(scenario, (scenario,)))
    argv = [
        "simulate", *what, "--condition", condition, "--seed", str(seed),
        "--duration", f"{duration_s:g}", "--out", str(partial_log),
        "--config-out", str(partial_config), "--quiet",
    ] + ([] if mismatch else ["--no-mismatch"])  # fmt: skip
    error = call(argv, timeout_s, logs / f"{stem}.txt")
    if error is None:  # only a complete log enters the cache
        partial_config.replace(config)
        partial_log.replace(log)
    return log, config, error


@dataclass
class Calibration:
    """`physfuse calibrate` of one robot: the config its runs take, or why there is none."""

    scenario: str
    condition: str  # of the log it was fitted on
    setting: str
    value: float | None = None
    initial: float | None = None
    identified: bool = True  # False: the log does not show the setting; value = initial
    config: str = ""  # the calibrated config (empty: it failed)
    error: str | None = None
    process_s: float = 0.0


def calibration_condition(condition: str) -> str:
    """The log a condition's robot is calibrated on: the nominal one, which simulates the same
    robot (conditions.py), except under `mismatch` (another robot): its own."""
    return "mismatch" if condition == "mismatch" else "nominal"


def calibrate_robot(
    scenario: str,
    condition: str,
    setting: str,
    log: Path,
    config: Path,
    folder: Path,
    timeout_s: float,
    reuse: bool = False,
) -> Calibration:
    """`physfuse calibrate LOG --config CONFIG --setting SETTING` into `folder`, which then
    holds the calibrated config.toml. reuse: keep a calibration newer than the log."""
    result = Calibration(scenario, condition, setting)
    folder.mkdir(parents=True, exist_ok=True)
    report, calibrated = folder / "calibration.json", folder / "config.toml"
    start = time.perf_counter()
    if not (
        reuse
        and all(
            p.exists() and p.stat().st_mtime > log.stat().st_mtime for p in (report, calibrated)
        )
    ):
        report.unlink(missing_ok=True)
        calibrated.unlink(missing_ok=True)
        argv = [
            "calibrate", str(log), "--config", str(config), "--setting", setting,
            "--out", str(folder), "--config-out", str(calibrated), "--quiet",
        ]  # fmt: skip
        (folder / "transcript.txt").write_text("")
        result.error = call(argv, timeout_s, folder / "transcript.txt")
    result.process_s = time.perf_counter() - start
    if result.error is None:
        try:
            fitted = json.loads(report.read_text())
            result.value, result.initial = float(fitted["best"]), float(fitted["initial"])
            result.identified = bool(fitted["identified"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            result.error = f"cannot read {report}: {err}"
        else:
            result.config = str(calibrated)
    return result


def estimate_and_evaluate(
    run: Run,
    log: Path,
    config: Path,
    folder: Path,
    timeout_s: float,
    method_flag: bool,
    reuse: bool = False,
) -> Run:
    """`physfuse estimate` then `physfuse evaluate` into `folder`; fills `run`.

    reuse: keep the folder's summary.json and metrics.json when both are newer than the log
    and the config.
    """
    folder.mkdir(parents=True, exist_ok=True)
    run.folder = str(folder)
    summary_path, metrics_path = folder / "summary.json", folder / "metrics.json"
    start = time.perf_counter()
    inputs = max(log.stat().st_mtime, config.stat().st_mtime) if reuse else 0.0
    if reuse and all(
        p.exists() and p.stat().st_mtime > inputs for p in (summary_path, metrics_path)
    ):
        run.reused = True
    else:
        summary_path.unlink(missing_ok=True)
        metrics_path.unlink(missing_ok=True)
        transcript = folder / "transcript.txt"
        transcript.write_text("")
        argv = ["estimate", str(log), "--config", str(config), "--out", str(folder), "--quiet"]
        if method_flag:
            argv += ["--method", run.method]
        elif run.method != "physics":
            run.error = "physfuse estimate has no --method option (only the physics smoother)"
            return run
        run.error = call(argv, timeout_s, transcript)
        if run.error is None:
            argv = [
                "evaluate", str(folder / "estimate.mcap"), "--truth", str(log),
                "--config", str(config), "--out", str(folder),
            ]  # fmt: skip
            run.error = call(argv, timeout_s, transcript)
    run.process_s = time.perf_counter() - start
    if run.error is None:
        try:
            summary = json.loads(summary_path.read_text())
            metrics = json.loads(metrics_path.read_text())["summary"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            run.error = f"cannot read {folder}/summary.json or metrics.json: {err}"
            return run
        run.wall_time_s, run.duration_s = summary.get("wall_time_s"), summary.get("duration_s")
        run.metrics = {k: _number(metrics.get(k)) for k in ALL_METRICS if k in metrics}
        if run.wall_time_s is not None and run.duration_s:
            run.metrics["wall_over_duration"] = run.wall_time_s / run.duration_s
    return run


def _number(value: Any) -> float | None:
    """A finite float, or None (null, NaN)."""
    if value is None or isinstance(value, bool):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def estimate_has_method_option() -> bool:
    """Whether `physfuse estimate` takes --method (before it did, it ran physics only)."""
    proc = subprocess.run(
        [*PHYSFUSE, "estimate", "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    return "--method" in proc.stdout


def run_suite(
    scenarios: Sequence[str],
    conditions: Sequence[str],
    methods: Sequence[str],
    duration_s: float,
    seed: int,
    workers: int | None,
    timeout_s: float,
    work: Path,
    reuse: bool = False,
    say: Callable[[str], None] = print,
    mismatch: bool = True,
    calibrate: str | None = None,
    ray_address: str | None = None,
) -> tuple[list[Run], list[Calibration]]:
    """Simulate every (scenario, condition) log, calibrate each robot's `calibrate` setting
    (None: none) on its `calibration_condition` log, then estimate and evaluate every method
    with the calibrated config.

    Every step is a Ray task (`estimator/fleet.py`: a local Ray of `workers` CPUs, or the
    cluster at `ray_address`), started as soon as the steps it takes are done.
    mismatch=False: every log simulated with the robot exactly its model."""
    import ray

    # this file is no package's module: Ray's workers get its functions by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    logs = work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    suffix = "" if mismatch else EXACT_MODEL
    pairs = [(s, c) for s in scenarios for c in conditions]
    robots = list(
        dict.fromkeys((s, calibration_condition(c)) for s, c in pairs if s not in PUBLIC_ROBOTS)
    )
    to_simulate = list(dict.fromkeys(pairs + (robots if calibrate else [])))
    method_flag = estimate_has_method_option()
    with ray_session(workers, ray_address):
        simulate, fit, one = (as_task(f) for f in (simulate_log, fit_robot, run_one))
        simulated = {
            p: simulate.remote(p[0], p[1], seed, duration_s, logs, timeout_s, mismatch)
            for p in to_simulate
        }
        fitting = {
            robot: fit.remote(
                *robot,
                str(calibrate),
                simulated[robot],
                work / f"calibration{suffix}",
                timeout_s,
                reuse,
            )
            for robot in (robots if calibrate else [])
        }
        running = {
            (s, c, m): one.remote(
                Run(s, c, m),
                simulated[s, c],
                fitting.get((s, calibration_condition(c))),
                work / f"runs{suffix}",
                timeout_s,
                method_flag,
                reuse,
            )
            for s, c in pairs
            for m in methods
        }
        pending = [*fitting.values(), *running.values()]
        while pending:  # a line as each step is done
            ready, pending = ray.wait(pending, num_returns=1)
            say(_done_line(ray.get(ready[0])))
        calibrations = [ray.get(ref) for ref in fitting.values()]
        return [ray.get(ref) for ref in running.values()], calibrations


def fit_robot(
    scenario: str,
    condition: str,
    setting: str,
    simulated: tuple[Path, Path, str | None],
    calibrations: Path,
    timeout_s: float,
    reuse: bool,
) -> Calibration:
    """`calibrate_robot` on the robot's simulated log, into calibrations/scenario/condition."""
    log, config, error = simulated
    if error is not None:
        return Calibration(scenario, condition, setting, error=f"simulate: {error}")
    folder = calibrations / scenario / condition
    return calibrate_robot(scenario, condition, setting, log, config, folder, timeout_s, reuse)


def run_one(
    run: Run,
    simulated: tuple[Path, Path, str | None],
    robot: Calibration | None,
    runs: Path,
    timeout_s: float,
    method_flag: bool,
    reuse: bool,
) -> Run:
    """`estimate_and_evaluate` of the run on its log, with its robot's calibrated value (a
    failed or absent calibration: the log's config as it is)."""
    log, config, error = simulated
    if error is not None:
        run.error = f"simulate: {error}"
        return run
    folder = runs / run.scenario / run.condition / run.method
    if robot is not None and robot.value is not None:
        calibrated = folder.parent / "calibrated.toml"
        calibrated.parent.mkdir(parents=True, exist_ok=True)
        config_with(config, calibrated, robot.setting, robot.value)
        config = calibrated
    return estimate_and_evaluate(run, log, config, folder, timeout_s, method_flag, reuse)


def _done_line(step: Run | Calibration) -> str:
    if isinstance(step, Calibration):
        status = f"failed: {step.error}" if step.error else f"{step.value:.4g}"
        return f"  {step.scenario:15s} {step.condition:12s} calibrated {step.setting}: {status}"
    status = f"failed: {step.error}" if step.error else f"{step.process_s:.0f} s"
    status += " (reused)" if step.reused else ""
    return f"  {step.scenario:15s} {step.condition:12s} {step.method:10s} {status}"


def calibration_text(calibrations: Sequence[Calibration]) -> str:
    """One line per calibrated robot: the value its runs took, or why they took the log's."""
    if not calibrations:
        return ""
    lines = ["calibrated (physfuse calibrate on the log named; every method's config):"]
    for c in calibrations:
        if c.error:
            shown = f"failed, the log's config used: {c.error}"
        elif not c.identified:
            shown = f"{c.setting} not identified by the mocap: the config's {c.initial:.4g} kept"
        else:
            shown = f"{c.setting} = {c.value:.4g} (config: {c.initial:.4g})"
        lines.append(f"  {c.scenario}/{c.condition}: {shown}")
    return "\n".join(lines) + "\n\n"


# -- the table ------------------------------------------------------------------------------------
def _format(value: float | None) -> str:
    """At most 7 characters: 3 significant digits, whole numbers from 100, e-notation
    outside [1e-3, 1e4)."""
    if value is None:
        return "—"
    size = abs(value)
    if value != 0 and not 1e-3 <= size < 1e4:
        return f"{value:.1e}"
    if size >= 100:
        return f"{value:.0f}"
    return f"{value:.3g}"


def _columns(runs: Sequence[Run], metrics: Mapping[str, tuple[str, bool]]) -> list[str]:
    """The metrics some run has a value of."""
    return [k for k in metrics if any(r.metrics.get(k) is not None for r in runs)]


def table(runs: Sequence[Run], metrics: Mapping[str, tuple[str, bool]] = METRICS) -> str:
    """One row per run (scenario, condition, method); a column per metric with any value."""
    columns = _columns(runs, metrics)
    width = 8
    head = f"{'scenario':15s} {'condition':12s} {'method':10s}"
    lines = [head + "".join(f"{metrics[k][0]:>{width}s}" for k in columns)]
    lines.append("-" * len(lines[0]))
    previous: tuple[str, str] | None = None
    for r in runs:
        if previous is not None and r.key != previous:
            lines.append("")
        previous = r.key
        row = f"{r.scenario:15s} {r.condition:12s} {r.method:10s}"
        if r.error:
            row += "  failed: " + r.error
        else:
            row += "".join(f"{_format(r.metrics.get(k)):>{width}s}" for k in columns)
        lines.append(row)
    return "\n".join(lines)


def markdown_table(runs: Sequence[Run], metrics: Mapping[str, tuple[str, bool]] = METRICS) -> str:
    """`table` as a Markdown table (the physics smoother's rows in bold), for the README."""
    columns = _columns(runs, metrics)
    lines = [
        "| scenario | condition | method | " + " | ".join(metrics[k][0] for k in columns) + " |",
        "|---" * (3 + len(columns)) + "|",
    ]
    for r in runs:
        method = f"**{r.method}**" if r.method == "physics" else r.method
        cells = (
            [f"failed: {r.error}"] + [""] * (len(columns) - 1)
            if r.error
            else [_format(r.metrics.get(k)) for k in columns]
        )
        lines.append(f"| {r.scenario} | {r.condition} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def occlusion_runs(runs: Sequence[Run]) -> list[Run]:
    """The runs whose log had mocap occlusions."""
    return [r for r in runs if (r.metrics.get("occluded_s") or 0.0) > 0]


def occlusion_table(runs: Sequence[Run]) -> str:
    """`table` of the runs with occlusions, over the occlusions; empty if none had any."""
    occluded = occlusion_runs(runs)
    if not occluded:
        return ""
    return f"over the mocap occlusions:\n{table(occluded, OCCLUDED_METRICS)}\n\n"


def markdown(runs: Sequence[Run]) -> str:
    """suite.md: both tables in Markdown (the README's copy)."""
    text = f"{markdown_table(runs)}\n"
    if occluded := occlusion_runs(runs):
        text += f"\nOver the mocap occlusions:\n\n{markdown_table(occluded, OCCLUDED_METRICS)}\n"
    return text


# -- the targets ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Check:
    """One target on one (scenario, condition): PASS, MISS or N/A (not measurable), and why."""

    target: str
    scenario: str
    condition: str
    status: str
    detail: str
    items: tuple[dict[str, Any], ...] = ()


def _by_method(runs: Iterable[Run]) -> dict[tuple[str, str], dict[str, Run]]:
    out: dict[tuple[str, str], dict[str, Run]] = {}
    for r in runs:
        out.setdefault(r.key, {})[r.method] = r
    return out


def _aggregate(target: str, key: tuple[str, str], items: list[dict[str, Any]]) -> Check | None:
    """The worst status of the items; the detail names the misses (or the closest pass, or
    what could not be measured)."""
    if not items:
        return None
    statuses = [i["status"] for i in items]
    status = "MISS" if "MISS" in statuses else "N/A" if "N/A" in statuses else "PASS"
    shown = [i for i in items if i["status"] == status]
    if status == "PASS":  # the closest call
        shown = [max(shown, key=lambda i: i["ratio"] or 0.0)]
    if status == "N/A":  # one line per reason: "joint_deg, joint_velocity_dps: ekf failed"
        reasons = dict.fromkeys(i["detail"] for i in shown)
        metrics = {r: ", ".join(i["metric"] for i in shown if i["detail"] == r) for r in reasons}
        detail = "; ".join(f"{metrics[r]}: {r}" for r in reasons)
    else:
        detail = "; ".join(i["detail"] for i in shown)
    return Check(target, key[0], key[1], status, detail, tuple(items))


def check_beats_baselines(runs: Sequence[Run]) -> list[Check]:
    """Target 1: physics < every baseline's error on each metric of BEATS_BASELINES."""
    target = "physics beats every baseline (position, orientation, joints, velocities)"
    checks = []
    for key, by in _by_method(runs).items():
        physics = by.get("physics")
        baselines = [by[m] for m in BASELINES if m in by]
        if physics is None or not baselines:
            continue
        items = []
        for metric in BEATS_BASELINES:
            if physics.error:
                items.append(_item(metric, "N/A", f"physics failed: {physics.error}"))
                continue
            p = physics.metrics.get(metric)
            values: dict[str, float] = {
                b.method: v
                for b in baselines
                if not b.error and (v := b.metrics.get(metric)) is not None
            }
            failed = [b.method for b in baselines if b.error]
            if p is None:
                if values:
                    items.append(_item(metric, "N/A", "physics has no value"))
                continue
            if not values and not failed:
                continue  # no baseline measures it: not applicable
            best = min(values, key=lambda m: values[m]) if values else None
            if best is not None and p >= values[best]:
                ratio = p / values[best] if values[best] > 0 else None
                shown = f"{ratio:.2f}×" if ratio is not None else f"{best} exact"
                detail = f"{metric} {_format(p)} vs {best} {_format(values[best])} ({shown})"
                items.append(_item(metric, "MISS", detail, p, best, values[best], ratio))
            elif failed:
                items.append(_item(metric, "N/A", f"{', '.join(failed)} failed", p))
            else:
                assert best is not None
                ratio = p / values[best]
                detail = f"{metric} {_format(p)} vs {best} {_format(values[best])} ({ratio:.2f}×)"
                items.append(_item(metric, "PASS", detail, p, best, values[best], ratio))
        check = _aggregate(target, key, items)
        if check is not None:
            checks.append(check)
    return checks


def check_occlusion(runs: Sequence[Run]) -> list[Check]:
    """Target 2: during occlusions physics ≤ OCCLUSION_RATIO × the kinematic smoother."""
    target = "occluded error ≤ 1/3 of the kinematic smoother's"
    checks = []
    for key, by in _by_method(runs).items():
        physics, kinematic = by.get("physics"), by.get("kinematic")
        if physics is None or kinematic is None:
            continue
        occluded = [(r.metrics.get("occluded_s") or 0.0) for r in (physics, kinematic)]
        if not physics.error and not kinematic.error and max(occluded) <= 0:
            continue  # no occlusion in this log
        if key[1] != "occlusion" and (physics.error or kinematic.error):
            continue  # cannot tell whether it had occlusions; the occlusion condition does
        items = []
        for metric in OCCLUSION_TARGET:
            if physics.error or kinematic.error:
                who = "physics" if physics.error else "kinematic"
                items.append(_item(metric, "N/A", f"{who} failed"))
                continue
            p, k = physics.metrics.get(metric), kinematic.metrics.get(metric)
            if p is None or k is None:
                continue
            ratio = p / k if k > 0 else None
            status = "PASS" if p <= OCCLUSION_RATIO * k else "MISS"
            shown = f"{ratio:.2f}×" if ratio is not None else "kinematic exact"
            detail = f"{metric} {_format(p)} vs kinematic {_format(k)} ({shown}, target ≤ 0.33×)"
            items.append(_item(metric, status, detail, p, "kinematic", k, ratio))
        check = _aggregate(target, key, items)
        if check is not None:
            checks.append(check)
    return checks


def check_contact_force(runs: Sequence[Run]) -> list[Check]:
    """Target 3: nominal condition, physics net contact force RMSE ≤ FORCE_PCT_WEIGHT % of m·g."""
    target = f"net contact force error ≤ {FORCE_PCT_WEIGHT:g}% of the weight (nominal)"
    checks = []
    for r in runs:
        if r.method != "physics" or r.condition != "nominal":
            continue
        metric = "contact_force_pct_weight"
        if r.error:
            items = [_item(metric, "N/A", f"physics failed: {r.error}")]
        elif (value := r.metrics.get(metric)) is None:
            continue  # no contacts to estimate
        else:
            ratio = value / FORCE_PCT_WEIGHT
            status = "PASS" if value <= FORCE_PCT_WEIGHT else "MISS"
            detail = f"{_format(value)}% of m·g ({ratio:.2f}× the limit)"
            items = [_item(metric, status, detail, value, None, FORCE_PCT_WEIGHT, ratio)]
        check = _aggregate(target, r.key, items)
        if check is not None:
            checks.append(check)
    return checks


def _item(
    metric: str,
    status: str,
    detail: str,
    physics: float | None = None,
    against: str | None = None,
    reference: float | None = None,
    ratio: float | None = None,
) -> dict[str, Any]:
    return {
        "metric": metric,
        "status": status,
        "detail": detail,
        "physics": physics,
        "against": against,
        "reference": reference,
        "ratio": ratio,
    }


def checklist(runs: Sequence[Run]) -> list[Check]:
    return check_beats_baselines(runs) + check_occlusion(runs) + check_contact_force(runs)


def checklist_text(checks: Sequence[Check]) -> str:
    lines = ["targets:"]
    target = None
    for c in checks:
        if c.target != target:
            target = c.target
            lines.append(f"  {target}")
        lines.append(f"    [{c.status:4s}] {c.scenario}/{c.condition}: {c.detail}")
    counts = {s: sum(c.status == s for c in checks) for s in ("PASS", "MISS", "N/A")}
    lines.append("  " + ", ".join(f"{s} {n}" for s, n in counts.items()))
    return "\n".join(lines)


# -- plots ----------------------------------------------------------------------------------------
def plot(runs: Sequence[Run], out: Path) -> list[Path]:
    """One PNG per metric: a panel per scenario, a group of bars per condition, a bar per
    method (log scale; precision and recall linear). × marks a method that failed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    scenarios = list(dict.fromkeys(r.scenario for r in runs))
    conditions = list(dict.fromkeys(r.condition for r in runs))
    methods = list(dict.fromkeys(r.method for r in runs))
    by_key = {(r.scenario, r.condition, r.method): r for r in runs}
    palette = plt.get_cmap("tab10")
    colors = {m: palette(i % 10) for i, m in enumerate(methods)}
    width = 0.8 / len(methods)
    paths = []
    for metric, (label, lower_is_better) in ALL_METRICS.items():
        values = [r.metrics.get(metric) for r in runs if not r.error]
        if not any(v is not None and v > 0 for v in values):
            continue
        bars = len(scenarios) * len(conditions) * len(methods)
        fig, axes = plt.subplots(
            1,
            len(scenarios),
            sharey=True,
            squeeze=False,
            figsize=(max(8.0, 2.0 + 0.18 * bars), 4.5),
        )
        for ax, scenario in zip(axes[0], scenarios, strict=True):
            for i, method in enumerate(methods):
                for j, condition in enumerate(conditions):
                    run = by_key.get((scenario, condition, method))
                    x = j + (i - (len(methods) - 1) / 2) * width
                    if run is not None and run.error:
                        ax.text(x, 0.01, "×", transform=ax.get_xaxis_transform(),
                                ha="center", color=colors[method], fontsize=8)  # fmt: skip
                        continue
                    y = run.metrics.get(metric) if run is not None else None
                    if y is not None and y > 0:
                        ax.bar(x, y, width, color=colors[method])
            ax.set_title(scenario, fontsize=9)
            ax.set_xlim(-0.5, len(conditions) - 0.5)
            ax.set_xticks(range(len(conditions)))
            ax.set_xticklabels(conditions, fontsize=7, rotation=30, ha="right")
            ax.grid(axis="y", alpha=0.3)
        if metric in ("contact_precision", "contact_recall"):
            axes[0, 0].set_ylim(0.0, 1.05)
        else:  # bars start well below the smallest, so their heights compare by ratio
            axes[0, 0].set_yscale("log")
            smallest = min(v for v in values if v is not None and v > 0)
            largest = max(v for v in values if v is not None)
            axes[0, 0].set_ylim(min(smallest / 3.0, largest / 30.0), largest * 1.5)
        axes[0, 0].set_ylabel(label)
        handles = [Patch(color=colors[m], label=m) for m in methods]
        better = "lower" if lower_is_better else "higher"
        better = "1 is honest" if metric == "position_anees" else f"{better} is better"
        fig.suptitle(f"{metric} ({better}; × failed)", fontsize=10)
        fig.legend(handles=handles, loc="lower center", ncols=len(methods), fontsize=8)
        fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
        path = out / f"{metric}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


# -- main -----------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/suite"), help="results folder")
    parser.add_argument(
        "--work",
        type=Path,
        default=Path("out/suite/work"),
        help="where the logs (cached) and the runs' outputs go",
    )
    every = [*SCENARIOS, *PUBLIC_ROBOTS]
    parser.add_argument("--scenarios", nargs="+", default=every, choices=every)
    # disturbances is the diagnostics' condition (benchmarks/diagnostics.py), not the
    # estimator's; no_mocap the legged robots' (`--conditions no_mocap --scenarios …`)
    estimator_conditions = [c for c in CONDITIONS if c not in ("disturbances", "no_mocap")]
    parser.add_argument("--conditions", nargs="+", default=estimator_conditions, choices=CONDITIONS)
    parser.add_argument(
        "--methods", nargs="+", default=list(METHODS), choices=[*METHODS, *LEGGED_METHODS]
    )
    parser.add_argument("--duration", type=float, default=DURATION_S, help="log length, s")
    parser.add_argument("--seed", type=int, default=0)
    ray = parser.add_mutually_exclusive_group()
    ray.add_argument(
        "--workers", type=int, help="steps in parallel on a local Ray (default: a worker per core)"
    )
    ray.add_argument("--ray-address", help="the steps on an existing Ray cluster (HEAD_IP:6379)")
    parser.add_argument("--timeout", type=float, default=TIMEOUT_S, help="per step, s")
    parser.add_argument(
        "--reuse-runs",
        action="store_true",
        help="keep the metrics of runs already in WORK (newer than their log): re-tabulate",
    )
    parser.add_argument(
        "--no-mismatch",
        action="store_true",
        help="simulate the robot exactly as its model (not with the `mismatch` condition)",
    )
    parser.add_argument(
        "--no-calibration",
        action="store_true",
        help="run every method on the log's config as simulated, without first fitting "
        "each robot's contact softness (softness_eps) by `physfuse calibrate`",
    )
    args = parser.parse_args(argv)
    if (
        not args.duration > 0
        or (args.workers is not None and args.workers < 1)
        or args.timeout <= 0
    ):
        parser.error("--duration and --timeout must be positive, --workers at least 1")
    if args.no_mismatch and "mismatch" in args.conditions:
        parser.error(
            "--no-mismatch contradicts the `mismatch` condition: pass --conditions without it"
        )
    work = args.work.resolve()  # the subprocesses run in the repository root
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    exact = ", the robot exactly its model" if args.no_mismatch else ""
    engine = f"the Ray cluster at {args.ray_address}" if args.ray_address else "a local Ray, "
    engine += "" if args.ray_address else f"{args.workers or os.cpu_count()} worker(s)"
    print(
        f"suite: {len(args.scenarios)} scenarios × {len(args.conditions)} conditions × "
        f"{len(args.methods)} methods, {args.duration:g} s logs{exact}, on {engine}; {work}"
    )
    calibrate = None if args.no_calibration else CALIBRATED_SETTING
    runs, calibrations = run_suite(
        args.scenarios,
        args.conditions,
        args.methods,
        args.duration,
        args.seed,
        args.workers,
        args.timeout,
        work,
        args.reuse_runs,
        mismatch=not args.no_mismatch,
        calibrate=calibrate,
        ray_address=args.ray_address,
    )
    wall = time.perf_counter() - start
    checks = checklist(runs)
    text = (
        f"{calibration_text(calibrations)}{table(runs)}\n\n{occlusion_table(runs)}"
        f"{checklist_text(checks)}\n\nsuite wall time {wall:.0f} s\n"
    )
    print("\n" + text, end="")
    report = {
        "settings": {
            "scenarios": args.scenarios,
            "conditions": {c: CONDITIONS[c] for c in args.conditions},
            "methods": args.methods,
            "duration_s": args.duration,
            "seed": args.seed,
            "model_mismatch": not args.no_mismatch,
            "calibrated": calibrate,
            "workers": args.workers,
            "ray_address": args.ray_address,
            "timeout_s": args.timeout,
            "work": str(work),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
            "python": platform.python_version(),
        },
        "wall_s": wall,
        "calibrations": [asdict(c) for c in calibrations],
        "runs": [asdict(r) for r in runs],
        "targets": [asdict(c) for c in checks],
        "target_counts": {s: sum(c.status == s for c in checks) for s in ("PASS", "MISS", "N/A")},
    }
    (args.out / "suite.json").write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
    (args.out / "suite.txt").write_text(text)
    (args.out / "suite.md").write_text(markdown(runs))
    paths = plot(runs, args.out)
    print(f"wrote {args.out / 'suite.json'}, {args.out / 'suite.txt'} and {len(paths)} plots")
    return 0


if __name__ == "__main__":
    sys.exit(main())
