"""What the sensor kinds added through the factor layer bring: encoder velocities (JointState
`use = [..., "velocity"]`) and foot-contact flags (`type = "contact_flags"`), with and without
the motion-capture stream, on simulated legged logs that carry both.

    .venv/bin/python benchmarks/sensor_kinds.py [--robots quadruped_trot go2] [--seconds 4]
                                                [--out DIR]

Each robot's scenario is simulated once with a `FootContacts` sensor (flags from the true
contact forces, 5 N threshold) and estimated by `physfuse estimate` under five configs:
everything but the new kinds (the scenario's own streams), + velocities, + flags, + both,
and both without the mocap stream; `physfuse evaluate` scores each against the ground truth.
Prints a table and writes DIR/sensor_kinds.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.simulate import simulate  # noqa: E402
from estimator.simulate.conditions import with_condition  # noqa: E402
from estimator.simulate.scenarios import get_scenario  # noqa: E402
from estimator.simulate.sensors import FootContacts  # noqa: E402
from estimator.simulate.simulation import scenario_config  # noqa: E402

FEET = {
    "quadruped_trot": ("front_left_shin", "front_right_shin", "rear_left_shin", "rear_right_shin"),
    "go2": ("FL_calf", "FR_calf", "RL_calf", "RR_calf"),
}
VARIANTS = ("base", "+velocity", "+flags", "+both", "+both -mocap")
METRICS = (
    "position_mm",
    "orientation_deg",
    "joint_deg",
    "linear_velocity_mps",
    "joint_velocity_dps",
    "contact_force_pct_weight",
)


def _scenario(robot: str):
    if robot == "go2":
        from estimator.simulate.model_scenario import model_scenario

        model = ROOT / "physics" / "models" / "menagerie" / "go2.xml"
        scenario = model_scenario(model, pushes="base", excitation_rad=0.1)  # as the suite's
    else:
        scenario = get_scenario(robot)
    scenario = with_condition(scenario, "nominal")
    return replace(scenario, sensors=(*scenario.sensors, FootContacts(FEET[robot])))


def _variant(text: str, variant: str) -> str:
    """The config text of a variant: streams' tables cut, or `use` added to the encoders'."""
    sections = re.split(r"(?m)^(?=\[)", text)  # the preamble, then one chunk per table
    drop = [] if "flags" in variant or "both" in variant else ["[streams.contacts]"]
    drop += ["[streams.mocap"] if "-mocap" in variant else []
    kept = [c for c in sections if not any(c.startswith(d) for d in drop)]
    if "velocity" in variant or "both" in variant:
        use = 'use = ["position", "velocity", "effort"]\n'
        kept = [c + use if c.startswith("[streams.joints]") else c for c in kept]
    return "".join(kept)


def _cli(*args: str) -> None:
    """`physfuse ARGS`; its last error line if it fails."""
    proc = subprocess.run(
        [sys.executable, "-m", "estimator.cli", *args], capture_output=True, text=True, cwd=ROOT
    )
    if proc.returncode:
        lines = proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"]
        raise SystemExit(f"physfuse {args[0]}: {lines[-1]}")


def run(robot: str, seconds: float, work: Path) -> dict:
    scenario = _scenario(robot)
    log = work / f"{robot}.mcap"
    simulate(scenario, log, seed=0, duration_s=seconds)
    text = scenario_config(scenario, work / "x.toml")
    rows = {}
    for variant in VARIANTS:
        name = f"{robot}_{variant.replace(' ', '').replace('+', 'with_').replace('-', 'no_')}"
        config = work / f"{name}.toml"
        config.write_text(_variant(text, variant))
        out = work / name
        started = time.perf_counter()
        _cli("estimate", str(log), "--config", str(config), "--out", str(out), "--quiet")
        wall = time.perf_counter() - started
        estimate = str(out / "estimate.mcap")
        _cli("evaluate", estimate, "--truth", str(log), "--config", str(config), "--out", str(out))
        metrics = json.loads((out / "metrics.json").read_text())["summary"]
        rows[variant] = {m: metrics.get(m) for m in METRICS} | {"wall_s": wall}
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", nargs="+", default=list(FEET), choices=list(FEET))
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "sensor_kinds")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = {robot: run(robot, args.seconds, args.out) for robot in args.robots}
    columns = (*METRICS, "wall_s")
    print(f"{'robot':<16} {'variant':<14}" + "".join(f"{m:>{len(m) + 2}}" for m in columns))
    for robot, rows in results.items():
        for variant, row in rows.items():
            cells = "".join(f"{row[m]:>{len(m) + 2}.4g}" for m in columns)
            print(f"{robot:<16} {variant:<14}{cells}")
    record = {
        "machine": f"{platform.machine()}, {platform.python_version()}",
        "seconds": args.seconds,
        "command": " ".join(sys.argv),
        "results": results,
    }
    (args.out / "sensor_kinds.json").write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
