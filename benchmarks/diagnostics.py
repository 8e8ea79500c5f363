"""The contact diagnostics on simulated disturbances: recall, false alarms, isolation, force
error and detection delay per event kind.

    .venv/bin/python benchmarks/diagnostics.py [--scenarios humanoid_push quadruped_trot go2 h1]
        [--seeds 0 1 2] [--duration 10] [--online] [--jobs 2] [--out DIR]

Per scenario and seed: `physfuse simulate SCENARIO --condition disturbances` (go2 and h1:
the Menagerie models, `--model physics/models/menagerie/<name>.xml`), the batch physics
estimate with the config's defaults, `diagnose` with its defaults; events scored against the
log's truth (`estimator.diagnose.score`). Beside it the baseline, the generalized-momentum
observer on the kinematic smoother's estimate with the same isolation and detection
(`estimator.baselines.momentum_observer`, "MO" columns: pushes and collisions). Pushes and
collisions (with an obstacle not in the model, `estimator/simulate/obstacle.py`; their force
as the simulation measured it) of at least 30 N for at least 0.1 s are counted apart (the
target: recall ≥ 95%, isolation ≥ 90%, force error ≤ 20% at ≤ 1 false alarm per minute).
Slips (a foot on a low-friction patch, `estimator/simulate/patch.py`; as measured): recall,
isolation (the foot), the distance slid's error in the ‖F‖ columns, slips reported where
none happened per minute. A body's mass off ("mass error (reported)": n reported, the
isolation column the share right against the simulation's mismatch — the body or one of its
candidates off in that direction within 3σ —, false/min the wrong ones).
Prints a table and writes DIR/diagnostics.json.

--online: the same log also through the streaming estimator with its online detector
(`Stream(diagnose=...)`, the node's settings, solving every `ONLINE_STEP_S` of knots): its
recall, isolation and detection delay (the knot that reported the event − the true start,
in log time; the node's own latency comes on top) for the pushes and collisions after the
detector's calibration (`CALIBRATE_S`), and its false alarms per minute after it.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.baselines.momentum_observer import observer_diagnosis  # noqa: E402
from estimator.batch import estimate  # noqa: E402
from estimator.config import load_config  # noqa: E402
from estimator.diagnose import DetectorSettings, diagnose  # noqa: E402
from estimator.diagnose.online import CALIBRATE_S  # noqa: E402
from estimator.diagnose.score import KIND_OF, Matched, score, true_events  # noqa: E402
from estimator.io.logs import read_log  # noqa: E402
from estimator.io.logs.source import open_log  # noqa: E402
from estimator.settings import Settings  # noqa: E402
from estimator.simulate.simulation import T0_NS  # noqa: E402
from estimator.stream import Stream  # noqa: E402

PHYSFUSE = [sys.executable, "-m", "estimator.cli"]
MENAGERIE = {
    "go2": ["--model", "physics/models/menagerie/go2.xml", "--excitation", "0.1"],
    "h1": ["--model", "physics/models/menagerie/h1.xml", "--excitation", "0.05"],
}
STRONG_N, LONG_S = 30.0, 0.1
CONTACTS = ("push", "collision")  # the true events an unmodeled contact finds
ONLINE_STEP_S = 0.05


def simulated(name: str, seed: int, duration: float, work: Path) -> tuple[Path, Path]:
    log, config = work / f"{name}_{seed}.mcap", work / f"{name}_{seed}.toml"
    source = MENAGERIE.get(name, [name])
    subprocess.run(
        [
            *PHYSFUSE,
            "simulate",
            *source,
            "--condition",
            "disturbances",
            "--seed",
            str(seed),
            "--duration",
            str(duration),
            "--out",
            str(log),
            "--config-out",
            str(config),
        ],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    return log, config


def run(name: str, seed: int, duration: float, work: Path, online: bool = False) -> dict:
    log_path, config_path = simulated(name, seed, duration, work)
    config = load_config(config_path)
    log = read_log(log_path, config)
    settings = Settings.from_config(config)
    start = time.perf_counter()
    est, _ = estimate(config, log.measurements, settings)
    estimated = time.perf_counter()
    diagnosis = diagnose(config, log.measurements, est, settings)
    diagnosed = time.perf_counter()
    result = score(diagnosis.events, true_events(log_path), T0_NS, duration)
    out = {
        "scenario": name,
        "seed": seed,
        "minutes": result.minutes,
        "estimate_s": estimated - start,
        "diagnose_s": diagnosed - estimated,
        "events": [_matched(m) for m in result.matched],
        "false_alarms": [
            {
                "kind": e.kind,
                "start_s": (e.start_ns - T0_NS) / 1e9,
                "target": e.target,
                "component": e.component,
                "size": e.magnitude,
                "score": e.score,
            }
            for e in result.false_alarms
            if e.component != "mass"
        ],
        "masses": _masses(diagnosis.events, log_path),
    }
    start = time.perf_counter()
    _, _, observed = observer_diagnosis(config, log.measurements, settings)
    contacts = [t for t in true_events(log_path) if t["kind"] in CONTACTS]
    baseline = score(observed.events, contacts, T0_NS, duration)
    out["momentum_observer"] = {
        "seconds": time.perf_counter() - start,
        "events": [_matched(m) for m in baseline.matched],
        "false_alarms": [
            {"start_s": (e.start_ns - T0_NS) / 1e9, "target": e.target, "score": e.score}
            for e in baseline.false_alarms
        ],
    }
    if online:
        out["online"] = streamed(config, log_path, duration)
    return out


def streamed(config, log_path: Path, duration: float) -> dict:
    """The log through `Stream(diagnose=...)`: its final events scored against the pushes,
    collisions and slips that start after the calibration."""
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, diagnose=DetectorSettings())
    step = max(1, round(ONLINE_STEP_S / stream.h))
    events = []
    start = time.perf_counter()
    for raw in open_log(log_path):
        stream.push(raw)
        for update in stream.update(min_knots=step):
            events += update.events
    for update in stream.close():
        events += update.events
    final = [e for e in events if not e.ongoing]
    truth = [
        t
        for t in true_events(log_path)
        if t["kind"] in (*CONTACTS, "slip") and t["start_s"] >= CALIBRATE_S
    ]
    result = score(final, truth, T0_NS, duration - CALIBRATE_S)
    faults = [t["start_s"] for t in true_events(log_path) if KIND_OF[t["kind"]] == "sensor fault"]
    return {
        "minutes": result.minutes,
        "stream_s": time.perf_counter() - start,
        "events": [_matched(m) for m in result.matched],
        "false_alarms": [
            {
                "kind": e.kind,
                "start_s": (e.start_ns - T0_NS) / 1e9,
                "target": e.target,
                "size": e.magnitude,
                "score": e.score,
                # the online detector has no sensor-fault test: the physics residual after a
                # fault the estimate took in
                "after_sensor_fault": any(
                    0 <= (e.start_ns - T0_NS) / 1e9 - f <= 1.0 for f in faults
                ),
            }
            for e in result.false_alarms
            if e.start_ns >= T0_NS + CALIBRATE_S * 1e9
        ],
    }


def _masses(events: list, log_path: Path) -> list[dict]:
    """Each mass error reported against the simulation's (the `physfuse.mismatch` record):
    right when its target or one of its candidates is off in the same direction by an amount
    within 3σ of the one reported."""
    with open(log_path, "rb") as f:
        records = {r.name: r.metadata for r in make_reader(f).iter_metadata()}
    masses = json.loads(records.get("physfuse.mismatch", {}).get("body_mass", "{}"))
    true = {b: m[1] - m[0] for b, m in masses.items()}
    out = []
    for e in events:
        if e.component != "mass":
            continue
        kg, std = float(e.force[0]), float(np.sqrt(e.force_cov[0, 0]))
        bodies = [e.target, *(b for b in e.candidates if b != e.target)]
        out.append(
            {
                "body": e.target,
                "kg": kg,
                "std_kg": std,
                "true_kg": {b: true.get(b, 0.0) for b in bodies},
                "right": any(
                    true.get(b, 0.0) * kg > 0 and abs(true.get(b, 0.0) - kg) <= 3 * std
                    for b in bodies
                ),
            }
        )
    return out


def _matched(m: Matched) -> dict:
    t = m.truth
    force = float(np.linalg.norm(t["force_n"])) if "force_n" in t else None
    if t["kind"] == "slip":  # its size: the distance slid [m]
        force = t["distance_m"]
    out = {
        "kind": t["kind"],
        "start_s": t["start_s"],
        "end_s": t["end_s"],
        "target": t.get("body", t.get("stream")),
        "force_n": force,
        "found": m.found,
        "isolated": m.isolated,
        "force_error": None if np.isnan(m.force_error) else m.force_error,
        "delay_s": None if np.isnan(m.delay_s) else m.delay_s,
    }
    if m.detection is not None:
        out["detected"] = {"body": m.detection.target, "force_n": m.detection.magnitude}
        if "point_m" in t:  # a collision: where the obstacle touched, against the point found
            point = m.detection.point  # None: put at a centre of mass
            error = None if point is None else np.linalg.norm(np.subtract(point, t["point_m"]))
            out["point_error_m"] = None if error is None else float(error)
    return out


def summarize(runs: list[dict]) -> list[dict]:
    rows = []
    for name in dict.fromkeys(r["scenario"] for r in runs):
        mine = [r for r in runs if r["scenario"] == name]
        minutes = sum(r["minutes"] for r in mine)
        alarms = {
            kind: sum(a["kind"] == kind for r in mine for a in r["false_alarms"])
            for kind in ("unmodeled contact", "sensor fault", "model error", "slip")
        }
        events = [e for r in mine for e in r["events"]]
        baseline_alarms = sum(len(r["momentum_observer"]["false_alarms"]) for r in mine)
        for kind in CONTACTS:
            every = [e for e in events if e["kind"] == kind]
            for label, group in ((f"{kind} ≥30 N ≥0.1 s", _strong(every)), (f"{kind}, all", every)):
                rows.append(_row(name, label, group, alarms["unmodeled contact"], minutes))
                observed = [
                    e for r in mine for e in r["momentum_observer"]["events"] if e["kind"] == kind
                ]
                if group is not every:
                    observed = _strong(observed)
                rows[-1]["momentum_observer"] = _row(
                    name, label, observed, baseline_alarms, minutes
                )
                if all("online" in r for r in mine):
                    rows[-1]["online"] = _online_row(mine, kind, group is not every)
        slips = [e for e in events if e["kind"] == "slip"]
        rows.append(_row(name, "slip", slips, alarms["slip"], minutes))
        if all("online" in r for r in mine):
            rows[-1]["online"] = _online_row(mine, "slip", False)
        for kind in ("imu bias step", "encoder offset"):
            group = [e for e in events if e["kind"] == kind]
            rows.append(_row(name, kind, group, alarms["sensor fault"], minutes))
        # none is simulated (the logs' model errors are the condition's mismatch of masses,
        # inertias, friction and softness): what `diagnose` names a contact's model error
        rows.append(_row(name, "model error (reported)", [], alarms["model error"], minutes))
        # a body's mass: reported (n), right (isolation column), wrong per minute
        masses = [m for r in mine for m in r.get("masses", [])]
        wrong = sum(not m["right"] for m in masses)
        rows.append(_row(name, "mass error (reported)", [], wrong, minutes))
        rows[-1]["count"] = len(masses)
        rows[-1]["isolation"] = sum(m["right"] for m in masses) / len(masses) if masses else None
    return rows


def _row(name: str, label: str, group: list[dict], alarms: int | None, minutes: float) -> dict:
    found = [e for e in group if e["found"]]
    errors = [e["force_error"] for e in found if e["force_error"] is not None]
    delays = [e["delay_s"] for e in found]
    points = [e["point_error_m"] for e in found if e.get("point_error_m") is not None]
    return {
        "scenario": name,
        "events": label,
        "count": len(group),
        "recall": len(found) / len(group) if group else None,
        "isolation": sum(e["isolated"] for e in found) / len(found) if found else None,
        "force_error_median": float(np.median(errors)) if errors else None,
        "force_error_p90": float(np.quantile(errors, 0.9)) if errors else None,
        "delay_p50_ms": 1e3 * float(np.median(delays)) if delays else None,
        "false_alarms_per_min": alarms / minutes if alarms is not None and minutes else None,
        # collisions: how far the contact point found is from where the obstacle touched
        "point_error_p50_m": float(np.median(points)) if points else None,
        "points_found": len(points),
    }


def _baseline_cells(row: dict) -> list[str]:
    """The momentum observer's recall, isolation, force error and false alarms (contact rows)."""
    b = row.get("momentum_observer")
    if b is None:
        return ["—"] * 4
    return [
        _cell(b["recall"], ".0%"),
        _cell(b["isolation"], ".0%"),
        _cell(b["force_error_median"], ".0%"),
        _cell(b["false_alarms_per_min"], ".2f"),
    ]


def _strong(events: list[dict]) -> list[dict]:
    """The pushes (collisions) of at least `STRONG_N` for at least `LONG_S`."""
    return [
        e for e in events if e["force_n"] >= STRONG_N and e["end_s"] - e["start_s"] >= LONG_S - 1e-9
    ]


def _online_row(runs: list[dict], kind: str, strong_only: bool) -> dict:
    events = [e for r in runs for e in r["online"]["events"] if e["kind"] == kind]
    if strong_only:
        events = _strong(events)
    found = [e for e in events if e["found"]]
    delays = [1e3 * e["delay_s"] for e in found]
    alarms = [a for r in runs for a in r["online"]["false_alarms"] if a["kind"] == KIND_OF[kind]]
    minutes = sum(r["online"]["minutes"] for r in runs)
    return {
        "count": len(events),
        "recall": len(found) / len(events) if events else None,
        "isolation": sum(e["isolated"] for e in found) / len(found) if found else None,
        "delay_p50_ms": float(np.median(delays)) if delays else None,
        "delay_p95_ms": float(np.quantile(delays, 0.95)) if delays else None,
        "false_alarms_per_min": len(alarms) / minutes if minutes else None,
        "false_alarms_after_sensor_fault_per_min": (
            sum(a["after_sensor_fault"] for a in alarms) / minutes if minutes else None
        ),
    }


def _point_cell(row: dict) -> str:
    if row["point_error_p50_m"] is None:
        return "—"
    return f"{100 * row['point_error_p50_m']:.1f} ({row['points_found']})"


def _cell(v: object, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--scenarios", nargs="+", default=["humanoid_push", "quadruped_trot", "go2", "h1"]
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "diagnostics")
    parser.add_argument("--online", action="store_true", help="also the streaming detector")
    parser.add_argument("--jobs", type=int, default=1, help="runs at once (processes)")
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.jobs) as pool:
        jobs = [
            pool.submit(run, name, seed, args.duration, Path(tmp), args.online)
            for name in args.scenarios
            for seed in args.seeds
        ]
        for job in jobs:
            r = job.result()
            runs.append(r)
            found = sum(e["found"] for e in r["events"])
            print(
                f"{r['scenario']} seed {r['seed']}: {found}/{len(r['events'])} events found, "
                f"{len(r['false_alarms'])} false alarms "
                f"(estimate {r['estimate_s']:.0f} s, diagnose {r['diagnose_s']:.1f} s)",
                file=sys.stderr,
            )
    rows = summarize(runs)
    header = (
        "scenario",
        "events",
        "n",
        "recall",
        "isolation",
        "‖F‖ err p50",
        "p90",
        "delay p50 ms",
        "false/min",
        "point err cm p50 (n)",
        "MO recall",
        "MO isolation",
        "MO ‖F‖ err p50",
        "MO false/min",
    )
    print(" | ".join(header))
    for r in rows:
        print(
            " | ".join(
                [
                    r["scenario"],
                    r["events"],
                    str(r["count"]),
                    _cell(r["recall"], ".0%"),
                    _cell(r["isolation"], ".0%"),
                    _cell(r["force_error_median"], ".0%"),
                    _cell(r["force_error_p90"], ".0%"),
                    _cell(r["delay_p50_ms"], ".0f"),
                    _cell(r["false_alarms_per_min"], ".2f"),
                    _point_cell(r),
                    *_baseline_cells(r),
                ]
            )
        )
    online = [r for r in rows if "online" in r]
    if online:
        print("\nonline (stream --diagnose), pushes, collisions and slips after the calibration:")
        print("scenario | events | n | recall | isolation | delay p50 ms | p95 | false/min")
        for r in online:
            o = r["online"]
            cells = [
                r["scenario"],
                r["events"],
                str(o["count"]),
                _cell(o["recall"], ".0%"),
                _cell(o["isolation"], ".0%"),
                _cell(o["delay_p50_ms"], ".0f"),
                _cell(o["delay_p95_ms"], ".0f"),
                _cell(o["false_alarms_per_min"], ".2f"),
            ]
            print(" | ".join(cells))
    args.out.mkdir(parents=True, exist_ok=True)
    report = {
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "seeds": args.seeds,
        "duration_s": args.duration,
        "online_step_s": ONLINE_STEP_S if args.online else None,
        "rows": rows,
        "runs": runs,
    }
    (args.out / "diagnostics.json").write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
