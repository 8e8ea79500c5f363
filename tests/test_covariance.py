"""Covariances that hold on an imperfect model: rows σ scaled to their residuals, and the
model's uncertain parameters considered (estimator.solver.covariance: honest, consider_variance)."""

from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from estimator.config import load_config
from estimator.factors.base import Block
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import build_problem
from estimator.run import initial_trajectory
from estimator.settings import Settings
from estimator.solver import covariance
from estimator.solver.banded import LAMBDA_MIN
from estimator.solver.covariance import honest
from estimator.solver.window import solve_window

ROOT = Path(__file__).resolve().parent.parent


def test_rows_whose_residuals_exceed_their_sigma_are_scaled_to_them():
    """A row with whitened residuals of RMS 3 gets σ × 3 (its r and J ÷ 3); a row that fits
    within its σ keeps it; invalid entries (no factor) do not count."""
    rng = np.random.default_rng(0)
    K = 400
    r = np.stack([3.0 * rng.standard_normal(K), 0.5 * rng.standard_normal(K)], axis=1)
    valid = np.ones((K, 2), bool)
    valid[:100, 0] = False
    r[:100, 0] = 0.0
    J = np.ones((K, 2, 6))
    (scaled,) = honest([Block("physics", r, J, np.zeros(K), valid)])
    rms = np.sqrt(np.mean(r[100:, 0] ** 2))
    np.testing.assert_allclose(scaled.r[:, 0], r[:, 0] / rms)
    np.testing.assert_allclose(scaled.J[:, 0], J[:, 0] / rms)
    np.testing.assert_array_equal(scaled.r[:, 1], r[:, 1])
    assert rms == pytest.approx(3.0, rel=0.1)


def _solved_and_moved(robot: str, h: float, knots: slice, step: float):
    """A window of a bundled recording (its knots of step h), solved tightly; and re-solved
    from there with every contact's κ × (1 + step)."""
    config = load_config(ROOT / "configs" / f"{robot}.toml")
    log = read_log(ROOT / "recordings" / f"{robot}.mcap", config)
    t_ns = knot_grid(log.measurements, h)[knots]
    settings = Settings(tolerance=1e-10, max_iterations=60, model_mass_std=0.0)
    problem = build_problem(config, log.measurements, settings, t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    solved = solve_window(problem, qpos, np.zeros((problem.T, problem.nb)), covariance=False)
    model = copy.deepcopy(problem.model)
    covariance._scaled_timeconst(model, 1.0 + step)
    moved = solve_window(replace(problem, model=model), solved.qpos, solved.bias, covariance=False)
    return problem, solved, moved


def test_considered_softness_predicts_how_far_a_re_solved_estimate_moves():
    """The linear sensitivity S_κ = −H⁻¹ Jᵀ ∂r/∂κ of the quadruped's height to its contacts'
    κ against re-solving the window with κ × 1.02, as RMS over the window: within 15% (the
    base sits on its feet's contacts, so a stiffer or softer contact moves it)."""
    step = 0.02
    problem, solved, moved = _solved_and_moved("quadruped_trot", 0.005, slice(100, 150), step)
    actual = np.sqrt(np.mean((moved.qpos[:, 2] - solved.qpos[:, 2]) ** 2))  # RMS over the window
    only_kappa = replace(problem, settings=replace(problem.settings, model_softness_std=step))
    variance = covariance.consider_variance(only_kappa, solved, ("softness_kappa",))
    predicted = np.sqrt(variance[:, 2])
    assert np.all(predicted == predicted[0])  # the window's RMS, at every knot
    assert actual > 2e-5  # it moves: tens of micrometres
    assert predicted[0] == pytest.approx(actual, rel=0.15)


def test_considered_softness_through_an_impact_uses_the_secants_to_its_sigma_points():
    """The humanoid falling onto the floor (knots 1.35–1.85 s of 10 ms), κ × (1 ± 0.1): the
    window's height re-solved moves by Δ₊ (softer) and hardly at all at κ × 0.9 (κ already at
    its floor 2h). The considered σ from the secants to κ ± σ comes within a factor 2 of
    √(½(Δ₊² + Δ₋²)), where the tangent at κ overstates it by more than 2.5×: the impact's
    force is far from linear in the softness."""
    step = 0.1
    problem, solved, softer = _solved_and_moved("humanoid_fall", 0.01, slice(135, 185), step)
    stiffer_model = copy.deepcopy(problem.model)
    covariance._scaled_timeconst(stiffer_model, 1.0 - step)
    stiffer = solve_window(
        replace(problem, model=stiffer_model), solved.qpos, solved.bias, covariance=False
    )
    shifts = [np.mean((m.qpos[:, 2] - solved.qpos[:, 2]) ** 2) for m in (softer, stiffer)]
    actual = np.sqrt(np.mean(shifts))
    only_kappa = replace(problem, settings=replace(problem.settings, model_softness_std=step))
    variance = covariance.consider_variance(only_kappa, solved, ("softness_kappa",))
    predicted = np.sqrt(variance[0, 2])
    at = covariance.rows_at(problem, problem.model, solved)
    ((_, _, tangent),) = covariance.parameter_sensitivities(
        problem, solved, solved.solved_system, [("softness_kappa", covariance.CONSIDER_STEP)], at
    )
    assert actual > 1e-4  # a tenth of a millimetre
    assert actual / 2 < predicted < actual
    assert step * np.sqrt(np.mean(tangent[:, 2] ** 2)) > 2.5 * actual


def test_a_force_sensor_predicted_through_the_contacts_enters_the_sensitivity():
    """The arm holding its box, κ × 1.02: the box moves by what S_κ predicts from every
    factor's rows (within a factor 1.5 of re-solving the window), where the physics rows
    alone predict a sixth of it — the wrist force/torque sensor, predicted through the
    fingers' contacts, is what the contact's softness moves most."""
    step, box = 0.02, slice(7, 10)
    problem, solved, moved = _solved_and_moved("arm_box", 0.002, slice(400, 500), step)
    actual = np.sqrt(np.mean(np.sum((moved.qpos[:, box] - solved.qpos[:, box]) ** 2, axis=1)))
    at = covariance.rows_at(problem, problem.model, solved)
    system = solved.solved_system
    ((dr, _, S),) = covariance.parameter_sensitivities(
        problem, solved, system, [("softness_kappa", covariance.CONSIDER_STEP)], at
    )
    predicted = step * np.sqrt(np.mean(np.sum(S[:, box] ** 2, axis=1)))
    physics_only = covariance.key_gradient(problem, solved.blocks[:1], dr[:1])
    s, ab = system.scaled_band()
    S_physics = replace(system, g=physics_only).damped_step(s, ab, LAMBDA_MIN)
    predicted_physics = step * np.sqrt(np.mean(np.sum(S_physics[:, box] ** 2, axis=1)))
    assert actual > 2e-6  # micrometres
    assert actual / 1.5 < predicted < 1.5 * actual
    assert predicted_physics < 0.3 * actual


def test_the_reversed_system_gives_the_first_keys_marginal_std():
    """`BandedSystem.reversed` (the keys in reverse order) has the same marginals: its last
    keys' σ are the first keys' σ of the system, computed from the dense inverse here."""
    from estimator.solver.banded import BandedSystem

    rng = np.random.default_rng(1)
    T, nz, span = 12, 4, 3
    rows = rng.standard_normal((T - span + 1, 6, span * nz))  # factors on span keys each
    H = sum(
        np.pad(J.T @ J, ((k * nz, (T - span - k) * nz),) * 2) for k, J in enumerate(rows)
    ) + 0.1 * np.eye(T * nz)
    blocks = H.reshape(T, nz, T, nz).transpose(0, 2, 1, 3)  # [i, j] = H_ij
    system = BandedSystem(
        np.stack([blocks[k, k] for k in range(T)]),
        [np.stack([blocks[k + d, k] for k in range(T - d)]) for d in range(1, span)],
        np.zeros((T, nz)),
    )
    expected = np.sqrt(np.diag(np.linalg.inv(H))).reshape(T, nz)[:, :3]
    first = system.reversed().marginal_std(3, [], range(T - 4, T))[::-1]
    np.testing.assert_allclose(first[:4], expected[:4], rtol=1e-9)
    np.testing.assert_allclose(system.marginal_std(3, [], range(0, T)), expected, rtol=1e-9)


def test_a_solve_stopped_short_is_as_uncertain_as_the_step_it_left():
    """humanoid_push's first 0.6 s, its solve stopped before its first step (a tolerance that
    the Gauss–Newton step's predicted decrease does not pass): the step left to the minimum
    (`remaining_step`) points at it (re-solved tightly, the minimum is much closer to the
    stop plus that step than to the stop), and the σ with the problem covers it at every
    knot."""
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    log = read_log(ROOT / "recordings" / "humanoid_push.mcap", config)
    t_ns = knot_grid(log.measurements, 0.01)[:60]
    settings = Settings(tolerance=0.9, fit_softness="none")
    problem = build_problem(config, log.measurements, settings, t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    short = solve_window(problem, qpos, np.zeros((problem.T, problem.nb)), covariance=False)
    assert np.array_equal(short.qpos, qpos)  # stopped at once
    tight = replace(problem, settings=replace(settings, tolerance=1e-12, max_iterations=60))
    best = solve_window(tight, short.qpos, short.bias, covariance=False)
    remaining = covariance.remaining_step(
        problem, short, covariance.rows_at(problem, problem.model, short)
    )
    left = best.qpos[:, :3] - short.qpos[:, :3]  # the base's position, m
    assert np.linalg.norm(left) > 1e-4  # it did stop short
    assert np.linalg.norm(left - remaining[:, :3]) < 0.5 * np.linalg.norm(left)  # (0.21)
    std = covariance.with_covariance(short, None, problem).qpos_std
    assert np.all(std >= np.abs(remaining[:, : problem.model.nv]) - 1e-15)


def test_the_step_left_counts_the_windows_prior():
    """A window after the first, solved to the default tolerance with the marginal prior its
    predecessor left: the remaining step from its solution is the Gauss–Newton step of the
    whole system there, the prior's rows included — solved again from the solution, the
    window's first linearization gives the same step (without the prior's share of the
    gradient it did not: 3.4e-6 m became 2.4e-5 m on the hour log's second window)."""
    config = load_config(ROOT / "configs" / "humanoid_push.toml")
    log = read_log(ROOT / "recordings" / "humanoid_push.mcap", config)
    t_ns = knot_grid(log.measurements, 0.01)[:120]
    settings = Settings(fit_softness="none")
    problem = build_problem(config, log.measurements, settings, t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    first = solve_window(problem, qpos, np.zeros((problem.T, problem.nb)), False, marginalize=60)
    assert first.next_prior is not None and first.next_start == 60
    second_problem = build_problem(config, log.measurements, settings, t_ns[60:])
    second = solve_window(
        second_problem, first.qpos[60:], first.bias[60:], False, prior=first.next_prior
    )
    assert second.prior is first.next_prior
    remaining = covariance.remaining_step(
        second_problem, second, covariance.rows_at(second_problem, second_problem.model, second)
    )
    # the step of a system linearized at the solution, the prior included
    again = replace(second_problem, settings=replace(settings, max_iterations=1, tolerance=1e300))
    at_solution = solve_window(again, second.qpos, second.bias, False, prior=first.next_prior)
    system = at_solution.solved_system
    assert system is not None
    s, ab = system.scaled_band()
    expected = system.damped_step(s, ab, covariance.LAMBDA_MIN)
    assert np.abs(expected).max() > 1e-9  # (the solve stopped short of the minimum)
    np.testing.assert_allclose(remaining, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
