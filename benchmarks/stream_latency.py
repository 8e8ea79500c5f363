"""The streaming node's latency, backlog and accuracy: recordings replayed at their real rate
through a real TCP socket (`physfuse replay` → `physfuse stream`, two processes on loopback).

    .venv/bin/python benchmarks/stream_latency.py [--recordings humanoid_push quadruped_trot]
        [--newest filter smoother] [--rate 1] [--lag 0.5] [--iterations 2 ...]
        [--relinearize 0.04 0 ...] [--out DIR]

Per recording and node setting: the latency (from the arrival of the sample that made a knot
ready to the publication of its newest estimate) p50 / p99 / max; the backlog (knots ready
and not yet published when a knot is published — with `--newest smoother`, when a solve
starts) over the first and the last third of the run, and the smoother's own (its process's,
with `--newest filter`); the errors of the newest (`/estimate`) and of the smoothed
(`/estimate_smoothed`) estimate against the ground truth, next to the batch estimate's
(`physfuse estimate` with the same settings: the model's own contact softness); and the
throughput at `--rate 0` (the log as fast as the replay sends it), in knots per second.
Several values of an option give a row each, in one run. Prints a table and writes
DIR/stream_latency.json."""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.batch import estimate  # noqa: E402
from estimator.config import load_config  # noqa: E402
from estimator.evaluate import compare_states  # noqa: E402
from estimator.io.logs import read_log  # noqa: E402
from estimator.io.mcap_writer import EstimateWriter  # noqa: E402
from estimator.io.state_topics import read_state_topics  # noqa: E402
from estimator.settings import Settings  # noqa: E402
from estimator.solver.incremental import RELINEARIZE_S  # noqa: E402

PHYSFUSE = [sys.executable, "-m", "estimator.cli"]
METRICS = ("position_mm", "orientation_deg", "joint_deg", "linear_velocity_mps")


def streamed(
    name: str,
    rate: float,
    lag: float,
    iterations: int,
    relinearize: float,
    newest: str,
    work: Path,
) -> dict:
    """One replay → stream run: the node's --stats and its output file. The replay sends the
    config's topics (as a robot's foxglove_bridge sends the channels a client subscribed to;
    the recordings' ground truth is four fifths of their messages)."""
    log, config = ROOT / "recordings" / f"{name}.mcap", ROOT / "configs" / f"{name}.toml"
    tag = f"{name}_{rate:g}_{iterations}_{relinearize:g}_{newest}"
    out, stats = work / f"{tag}.mcap", work / f"{tag}.json"
    topics = sorted({s.topic for s in load_config(config).streams.values()})
    replay = subprocess.Popen(
        [
            *PHYSFUSE,
            "replay",
            str(log),
            "--to",
            "tcp://127.0.0.1:0",
            "--rate",
            str(rate),
            "--topics",
            *topics,
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert replay.stderr is not None
    port = int(replay.stderr.readline().rsplit(" ", 1)[1])
    node = subprocess.run(
        [
            *PHYSFUSE,
            "stream",
            "--config",
            str(config),
            "--source",
            f"tcp://127.0.0.1:{port}",
            "--out",
            str(out),
            "--stats",
            str(stats),
            "--lag",
            str(lag),
            "--iterations",
            str(iterations),
            "--relinearize",
            str(relinearize),
            "--newest",
            newest,
            "--fit-softness",  # (a 4 s log ends before the fit of its first 2 s is back)
            "none",
            "--quiet",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    replay.wait(timeout=60)
    if node.returncode != 0:
        raise SystemExit(f"physfuse stream on {name} failed: {node.stderr.strip()}")
    return {"stats": json.loads(stats.read_text()), "out": out}


def errors(path: Path, prefix: str, name: str) -> dict[str, float]:
    config = load_config(ROOT / "configs" / f"{name}.toml")
    truth = read_state_topics(ROOT / "recordings" / f"{name}.mcap")
    summary = compare_states(read_state_topics(path, prefix), truth, config.load_model())
    return {k: float(summary["summary"][k]) for k in METRICS}


def batch(name: str, work: Path) -> dict[str, float]:
    """The whole log at once, with the settings the node uses (the model's own softness)."""
    config = load_config(ROOT / "configs" / f"{name}.toml")
    settings = replace(Settings.from_config(config), fit_softness="none")
    est, _ = estimate(
        config, read_log(ROOT / "recordings" / f"{name}.mcap", config).measurements, settings
    )
    out = work / f"{name}_batch.mcap"
    with EstimateWriter(out, config.load_model(), est.model_name, est.h) as writer:
        writer.write(est, range(est.T))
    return errors(out, "/estimate", name)


def thirds(backlog: list[int]) -> tuple[float, float]:
    n = max(len(backlog) // 3, 1)
    return float(np.mean(backlog[:n])), float(np.mean(backlog[-n:]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--recordings", nargs="+", default=["humanoid_push", "quadruped_trot"])
    parser.add_argument("--lag", type=float, default=0.5)
    parser.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="the replay's pace for the latency rows (1: real time; 0.5: half, a node with "
        "spare CPU)",
    )
    parser.add_argument(
        "--iterations",
        type=int,
        nargs="+",
        default=[2],
        help="the node's Levenberg–Marquardt iterations per update; several: a row each",
    )
    parser.add_argument(
        "--relinearize",
        type=float,
        nargs="+",
        default=[RELINEARIZE_S],
        help="the node's --relinearize, s (0: whole-window updates); several: a row each",
    )
    parser.add_argument(
        "--newest",
        nargs="+",
        choices=("filter", "smoother"),
        default=["filter", "smoother"],
        help="the node's --newest; several: a row each",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "stream_latency")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    batches: dict[str, dict[str, float]] = {}  # one batch estimate per recording
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        runs = [
            (n, i, r, w)
            for n in args.recordings
            for i in args.iterations
            for r in args.relinearize
            for w in args.newest
        ]
        for name, iterations, relinearize, newest in runs:
            live = streamed(name, args.rate, args.lag, iterations, relinearize, newest, work)
            fast = streamed(name, 0.0, args.lag, iterations, relinearize, newest, work)
            s = live["stats"]
            lat = np.array(s["latency_s"]) * 1e3
            first, last = thirds(s["backlog"])
            # (--newest filter: the smoother's own updates, in its process)
            smoother_first, smoother_last = thirds(s["smoother_backlog"] or s["backlog"])
            f = fast["stats"]
            if name not in batches:
                batches[name] = batch(name, work)
            rows.append(
                {
                    "recording": name,
                    "newest_from": newest,
                    "iterations": iterations,
                    "relinearize_s": relinearize,
                    "knot_ms": s["knot_s"] * 1e3,
                    "knots": s["counts"]["knots_newest"],
                    "updates": s["counts"]["updates"],
                    "latency_p50_ms": float(np.percentile(lat, 50)),
                    "latency_p99_ms": float(np.percentile(lat, 99)),
                    "latency_max_ms": float(lat.max()),
                    "backlog_first_third": first,
                    "backlog_last_third": last,
                    "backlog_max": int(max(s["backlog"])),
                    "smoother_backlog_first_third": smoother_first,
                    "smoother_backlog_last_third": smoother_last,
                    "solve_p50_ms": float(np.median(s["solve_s"]) * 1e3),
                    "wall_s": s["wall_s"],
                    "throughput_knots_per_s": f["counts"]["knots_newest"] / f["wall_s"],
                    "throughput_smoothed_knots_per_s": f["counts"]["knots_smoothed"] / f["wall_s"],
                    "newest": errors(live["out"], "/estimate", name),
                    "smoothed": errors(live["out"], "/estimate_smoothed", name),
                    "batch": batches[name],
                    "divergences": s["counts"]["divergences"],
                    "late": s["counts"]["late"],
                }
            )
            print(
                f"{name}, newest from the {newest}, {iterations} iteration(s), relinearize "
                f"{relinearize:g} s: done",
                file=sys.stderr,
            )
    print(
        f"{'recording':15s} {'newest':>8s} {'it':>2s} {'relin':>5s} {'knot':>5s} {'p50 ms':>7s} "
        f"{'p99 ms':>7s} {'backlog 1st/last':>17s} {'smoother 1st/last':>17s} "
        f"{'thru k/s':>8s} | {'pos mm new / smooth / batch':>28s} | "
        f"{'joint ° new / smooth / batch':>30s}"
    )
    for r in rows:
        p = [r[k]["position_mm"] for k in ("newest", "smoothed", "batch")]
        j = [r[k]["joint_deg"] for k in ("newest", "smoothed", "batch")]
        print(
            f"{r['recording']:15s} {r['newest_from']:>8s} {r['iterations']:2d} "
            f"{r['relinearize_s']:5.2f} "
            f"{r['knot_ms']:5.1f} "
            f"{r['latency_p50_ms']:7.0f} "
            f"{r['latency_p99_ms']:7.0f} "
            f"{r['backlog_first_third']:8.1f}/{r['backlog_last_third']:<8.1f} "
            f"{r['smoother_backlog_first_third']:8.1f}/{r['smoother_backlog_last_third']:<8.1f} "
            f"{r['throughput_knots_per_s']:8.0f} | {p[0]:8.4f} {p[1]:8.4f} {p[2]:8.4f}   | "
            f"{j[0]:9.5f} {j[1]:9.5f} {j[2]:9.5f}"
        )
    report = {
        "rate": args.rate,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
        "lag_s": args.lag,
        "recordings": rows,
    }
    (args.out / "stream_latency.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out / 'stream_latency.json'}")


if __name__ == "__main__":
    main()
