"""Excerpts of one long log, each estimated on its slice of the log's own knots, against each
other and against whole-log estimates: how much the estimate at a knot depends on where the
estimate started and on where its windows lie (the question behind a chunked estimate
matching the single-process one within σ, docs/fleet.md).

    .venv/bin/python benchmarks/excerpts.py LOG --config CONFIG --excerpt 2830 2900 \
        --excerpt 2840.37 2882 [--against DIR ...] [--settings-from SUMMARY] [--out DIR] [--reuse]

Each excerpt (seconds from the log's first knot) is estimated as a chunk of `estimate
--chunk` is (`chunks.estimate_chunk`: its time slice of the file read, the estimate on its
knots), as Ray tasks on a local Ray; the softness is fitted on the log's start once (or taken
from SUMMARY, a whole-log run's summary.json, so as to compare with that run). Every pair —
excerpts, and each excerpt against each `--against` run's estimate.mcap — is compared over
the knots both have, less `--skip` seconds at each end of the shorter: the first free body's
position difference in units of the first one's reported σ (max and where, p99, knots beyond
1 σ) and in mm, and the window hand-overs they share. Prints a table and writes
DIR/excerpts.json; each excerpt's estimate is kept in DIR for `--reuse`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pickle
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.chunks import HEAD_S, _joined  # noqa: E402
from estimator.config import load_config  # noqa: E402
from estimator.io.logs import read_log  # noqa: E402
from estimator.io.logs.source import log_time_span  # noqa: E402
from estimator.knots import knot_grid  # noqa: E402
from estimator.run import softness_fitted  # noqa: E402
from estimator.settings import Settings  # noqa: E402

MARGIN_NS = 3_000_000_000  # log read around an excerpt's knots (stamps vs receipt, windows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument(
        "--excerpt", nargs=2, type=float, action="append", required=True, metavar=("FROM_S", "TO_S")
    )
    ap.add_argument(
        "--against",
        type=Path,
        action="append",
        default=[],
        help="a whole-log run's output folder (its estimate.mcap)",
    )
    ap.add_argument("--settings-from", type=Path, help="a whole-log run's summary.json")
    ap.add_argument("--skip", type=float, default=1.0, help="s left out at each end")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--reuse", action="store_true", help="the excerpts DIR holds, not re-run")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "excerpts")
    args = ap.parse_args(argv)
    import ray

    from estimator.fleet import as_task, ray_session

    config = load_config(args.config)
    h = float(config.load_model().opt.timestep)
    settings, t_ns = _settings_and_knots(args.log, config, args.settings_from)
    h = settings.h or h
    task = as_task(_excerpt)
    args.out.mkdir(parents=True, exist_ok=True)
    saved = {(a, b): args.out / f"excerpt_{a:g}_{b:g}.pkl" for a, b in args.excerpt}
    runs = {}
    with ray_session(args.workers):
        refs = {
            (a, b): task.remote(str(args.config), str(args.log), settings, _slice(t_ns, a, b))
            for (a, b), path in saved.items()
            if not (args.reuse and path.exists())
        }
        for (a, b), path in saved.items():  # each excerpt's estimate kept for --reuse
            if (a, b) in refs:
                path.write_bytes(pickle.dumps(ray.get(refs[(a, b)])))
            runs[f"{a:g}–{b:g} s"] = pickle.loads(path.read_bytes())
    for folder in args.against:
        runs[str(folder)] = _read_run(folder, t_ns, args.excerpt)
    skip = round(args.skip / h)
    pairs = [
        _compare(x, runs[x], y, runs[y], t_ns[0], skip) for x, y in itertools.combinations(runs, 2)
    ]
    rows = [r for r in pairs if r is not None]  # (pairs that share knots)
    report = {
        "log": str(args.log),
        "excerpts": {
            k: {"wall_s": v["wall_s"], "windows": len(v["starts"])}
            for k, v in runs.items()
            if "wall_s" in v
        },
        "pairs": rows,
        "machine": {
            "python": platform.python_version(),
            "cpu": platform.processor(),
            "workers": args.workers,
        },
    }
    (args.out / "excerpts.json").write_text(json.dumps(report, indent=1))
    print("| A | B | max σ | at s | p99 σ | knots > 1 σ | max mm | shared hand-overs |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['a']} | {r['b']} | {r['max_sigma']:.2f} | {r['at_s']:.2f} "
            f"| {r['p99_sigma']:.2f} | {r['beyond_1_sigma']} | {r['max_mm']:.4f} "
            f"| {r['shared_starts']} |"
        )
    return 0


def _settings_and_knots(
    log: Path, config: Any, summary: Path | None
) -> tuple[Settings, np.ndarray]:
    """The settings every excerpt takes (the softness fitted on the log's start, or SUMMARY's)
    and the log's knot grid, as `chunks.estimate_chunked` makes them."""
    span = log_time_span(log)
    head = read_log(log, config, log_time=(span[0], span[0] + round(HEAD_S * 1e9)), require=False)
    tail = read_log(
        log, config, log_time=(span[1] - round(HEAD_S * 1e9), span[1] + 1), require=False
    )
    settings = Settings.from_config(config) if summary is None else run_settings(summary)
    h = settings.h or float(config.load_model().opt.timestep)
    t_ns = knot_grid(_joined(head.measurements, tail.measurements), h)
    if summary is None:
        settings, _ = softness_fitted(config, head.measurements, settings, t_ns)
    settings = replace(settings, fit_softness="none")
    return settings, t_ns


def run_settings(summary: Path) -> Settings:
    """A run's settings (its summary.json) with the contact softness it fitted folded in, as
    every window of that run took them."""
    s = json.loads(summary.read_text())
    settings = Settings(**s["settings"])
    fit = s.get("softness_fit")
    if not fit:
        return settings
    return replace(
        settings,
        softness_eps_scale=settings.softness_eps_scale * fit["eps_scale"],
        softness_kappa_scale=settings.softness_kappa_scale * fit["kappa_scale"],
        model_softness_std=max(fit["eps_scale_sigma"], fit["kappa_scale_sigma"]),
    )


def _slice(t_ns: np.ndarray, a: float, b: float) -> np.ndarray:
    return t_ns[np.searchsorted(t_ns, t_ns[0] + a * 1e9) : np.searchsorted(t_ns, t_ns[0] + b * 1e9)]


def _excerpt(
    config_path: str, log_path: str, settings: Settings, knots: np.ndarray
) -> dict[str, Any]:
    """One excerpt, in a Ray worker: its slice of the log read, the estimate on `knots`."""
    from estimator.batch import estimate
    from estimator.run import samples_within

    config = load_config(config_path)
    log = read_log(
        log_path,
        config,
        log_time=(int(knots[0]) - MARGIN_NS, int(knots[-1]) + MARGIN_NS),
        require=False,
    )
    m = {k: samples_within(v, int(knots[0]), int(knots[-1])) for k, v in log.measurements.items()}
    start = time.perf_counter()
    est, summary = estimate(config, m, settings, knots=knots)
    body = est.qpos[:, :3]  # the free base's position (the first free joint's qpos)
    return {
        "t_ns": est.t_ns,
        "position": body,
        "sigma": est.qpos_std[:, :3],
        "starts": [int(knots[k]) for k in summary.window_starts],
        "wall_s": time.perf_counter() - start,
    }


def _read_run(folder: Path, t_ns: np.ndarray, excerpts: list[list[float]]) -> dict[str, Any]:
    """A whole-log run's first free body over the excerpts' span (its estimate.mcap), and its
    window hand-overs (its summary.json)."""
    from estimator.io.state_topics import read_state_topics

    lo = min(a for a, _ in excerpts) - 1.0
    hi = max(b for _, b in excerpts) + 1.0
    span = log_time_span(folder / "estimate.mcap")
    st = read_state_topics(
        folder / "estimate.mcap",
        prefix="/estimate",
        log_time=(span[0] + round(lo * 1e9), span[0] + round(hi * 1e9)),
    )
    odometry = next(iter(st.odometry.values()))
    summary = json.loads((folder / "summary.json").read_text())
    return {
        "t_ns": odometry.t_ns,
        "position": odometry.values[:, :3],
        "sigma": np.sqrt(odometry.values[:, [13, 17, 21]]),
        "starts": [int(t_ns[k]) for k in summary.get("window_starts", [])],
    }


def _compare(x: str, a: dict, y: str, b: dict, t0: int, skip: int) -> dict[str, Any] | None:
    common, ia, ib = np.intersect1d(a["t_ns"], b["t_ns"], return_indices=True)
    keep = slice(skip, max(skip, len(common) - skip))
    if not len(common[keep]):
        return None
    d = a["position"][ia][keep] - b["position"][ib][keep]
    z = np.abs(d) / a["sigma"][ia][keep]
    k = int(np.unravel_index(np.argmax(z), z.shape)[0])
    inside = set(int(t) for t in common[keep])
    starts_b = set(b["starts"]) & inside
    return {
        "a": x,
        "b": y,
        "knots": int(z.shape[0]),
        "max_sigma": float(z.max()),
        "at_s": float((common[keep][k] - t0) / 1e9),
        "p99_sigma": float(np.percentile(z, 99)),
        "beyond_1_sigma": int((z > 1).sum()),
        "max_mm": float(np.abs(d).max() * 1e3),
        "shared_starts": f"{len(set(a['starts']) & starts_b)} of {len(starts_b)}",
    }


if __name__ == "__main__":
    raise SystemExit(main())
