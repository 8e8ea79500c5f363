"""Where a window's solve stops: one window of a log solved from its measurements (no prior),
then, at the solution, the cost along 1% of each damped step the solver could take next, per
factor type, and the knots whose physics cost jumps, with the contacts that appear or vanish
there. A cost that rises for every small step in every direction is a kink (a contact
activating), not a minimum the quadratic model sees (docs/fleet.md).

    .venv/bin/python benchmarks/window_stop.py LOG --config CONFIG --at S [--window 4]
        [--settings-from SUMMARY] [--tolerance X] [--iterations N]

S: seconds from the log's first receive time; SUMMARY: a run's summary.json whose settings
and fitted softness the window takes (default: the config's, without the fit).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from excerpts import run_settings  # noqa: E402  (benchmarks/, the script's folder)

from estimator.config import load_config  # noqa: E402
from estimator.io.logs import read_log  # noqa: E402
from estimator.io.logs.source import log_time_span  # noqa: E402
from estimator.problem import build_problem, model_with_sensors, retract  # noqa: E402
from estimator.run import initial_trajectory, samples_within  # noqa: E402
from estimator.settings import Settings  # noqa: E402
from estimator.solver.banded import BandedSystem  # noqa: E402
from estimator.solver.linearize import Linearizer  # noqa: E402
from estimator.solver.window import solve_window  # noqa: E402

STEP = 0.01  # of a damped step, probed at the solution


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--at", type=float, required=True, help="window start, s into the log")
    ap.add_argument("--window", type=float, default=4.0, help="s")
    ap.add_argument("--settings-from", type=Path)
    ap.add_argument("--tolerance", type=float)
    ap.add_argument("--iterations", type=int)
    args = ap.parse_args(argv)
    config = load_config(args.config)
    settings = Settings.from_config(config)
    if args.settings_from:
        settings = run_settings(args.settings_from)
    settings = replace(settings, fit_softness="none")
    if args.tolerance is not None:
        settings = replace(settings, tolerance=args.tolerance)
    if args.iterations is not None:
        settings = replace(settings, max_iterations=args.iterations)
    compiled = model_with_sensors(config)
    model = compiled[0]
    h = settings.h or float(model.opt.timestep)
    t0 = log_time_span(args.log)[0] + round(args.at * 1e9)
    t_ns = np.arange(t0, t0 + round(args.window * 1e9), round(h * 1e9), dtype=np.int64)
    read = read_log(
        args.log,
        config,
        log_time=(t0 - 2_000_000_000, int(t_ns[-1]) + 2_000_000_000),
        require=False,
    )
    m = {k: samples_within(v, int(t_ns[0]), int(t_ns[-1])) for k, v in read.measurements.items()}
    problem = build_problem(config, m, settings, t_ns, compiled)
    result = solve_window(
        problem, initial_trajectory(model, m, t_ns), np.zeros((problem.T, problem.nb)), False
    )
    print(
        f"window {args.at:g}–{args.at + args.window:g} s: {result.iterations} iterations, "
        f"converged {result.converged}, cost {result.cost_final:.1f}"
    )
    lin = Linearizer(problem, None)
    q, b = result.qpos, result.bias
    blocks = lin.linearize(q, b)
    cost, by_type = lin.cost_of(blocks, q, b)
    system = BandedSystem.of(blocks, lin, b, q)
    scale, band = system.scaled_band()
    print(f"| λ | quadratic model's decrease (full step) | cost change at {STEP:.0%} of it |")
    print("|---|---|---|")
    moved: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    for lam in (1e-9, 1e-3, 1.0, 1e2):
        dx = STEP * system.damped_step(scale, band, lam)
        q1, b1 = retract(model, q, dx[:, : model.nv]), b + dx[:, model.nv :]
        cost1, by1 = lin.cost(q1, b1)
        rises = {
            k: round(by1[k] - by_type[k], 3) for k in by_type if abs(by1[k] - by_type[k]) > 1e-2
        }
        print(
            f"| {lam:.0e} | {system.predicted_decrease(scale, lam, dx / STEP):.4g} | "
            f"{cost1 - cost:+.4g} {rises} |"
        )
        moved[lam] = (q1, b1)
    worst = moved[1e-9]  # the Gauss–Newton step's direction
    jumps = _physics_jumps(lin, (q, b), worst)
    data = mujoco.MjData(model)
    for k, before, after in jumps:
        t = (t_ns[k] - log_time_span(args.log)[0]) / 1e9
        print(
            f"knot at {t:.2f} s: physics cost {before:.1f} → {after:.1f}; contacts "
            f"{_contacts(model, data, q[k])} → {_contacts(model, data, worst[0][k])}"
        )
    return 0


def _physics_jumps(lin: Linearizer, at: tuple, moved: tuple, n: int = 3) -> list[tuple]:
    """The knots whose physics cost changes most between the two points (knot, before, after)."""

    def per_knot(q: np.ndarray, b: np.ndarray) -> np.ndarray:
        blocks = lin.blocks(lin.terms(q, False), b)
        return np.sum([bl.cost for bl in blocks if bl.name == "physics"], axis=0)

    before, after = per_knot(*at), per_knot(*moved)
    order = np.argsort(-np.abs(after - before))[:n]
    # a physics row k is the inverse dynamics at knot k + 1 (three knots per row)
    return [
        (int(i) + 1, float(before[i]), float(after[i])) for i in order if after[i] - before[i] > 1.0
    ]


def _contacts(model: mujoco.MjModel, data: mujoco.MjData, qpos: np.ndarray) -> list[str]:
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    name = lambda g: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g)  # noqa: E731
    return [
        f"{name(c.geom1)}–{name(c.geom2)} {c.dist * 1e3:.4f} mm" for c in data.contact[: data.ncon]
    ]


if __name__ == "__main__":
    raise SystemExit(main())
