"""fit_softness: the physics and the mocap together fit factors on the model's own contact
softness (estimator.solver.softness_fit)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.io.state_topics import at_times, read_ground_truth, read_metadata
from estimator.knots import knot_grid
from estimator.problem import build_problem
from estimator.run import initial_trajectory
from estimator.settings import Settings
from estimator.solver.softness_fit import fit_softness
from estimator.solver.window import solve_window

ROOT = Path(__file__).resolve().parent.parent


def test_the_fit_brings_a_stiffer_robots_height_to_its_mocap():
    """Go2's recording simulates contacts stiffer than its model (κ × 0.94): held at the
    model's depth the base sits low; with the fitted factors (κ below 1, as simulated) the
    height error over the window shrinks to less than half."""
    config = load_config(ROOT / "configs" / "go2.toml")
    log_path = ROOT / "recordings" / "go2.mcap"
    log = read_log(log_path, config)
    softness = read_metadata(log_path)["physfuse.mismatch"]["softness"]
    assert '"kappa_scale": [1.0, 0.93' in softness
    t_ns = knot_grid(log.measurements, 0.002)[250:650]
    problem = build_problem(config, log.measurements, Settings(), t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    bias = np.zeros((problem.T, problem.nb))
    truth = at_times(*read_ground_truth(log_path, problem.model), t_ns)

    def height_error(q: np.ndarray) -> float:
        return float(np.mean(q[10:-10, 2] - truth[10:-10, 2]))

    plain = solve_window(problem, qpos, bias, covariance=False)
    fit, fitted = fit_softness(problem, qpos, bias)
    assert fit.rounds >= 1 and fit.kappa_scale < 1.0
    assert all(0 < s < 0.1 for s in fit.sigma)
    assert abs(height_error(fitted.qpos)) < 0.5 * abs(height_error(plain.qpos))
    assert abs(height_error(plain.qpos)) > 5e-5  # there is an error to remove
