"""The covariance of a window's estimate: the banded system's marginals with each factor's σ
made honest to its residuals (`honest`), plus what the model's uncertain parameters pass on
(Schmidt's consider covariance, `consider_variance`): S = −H⁻¹ Jᵀ ∂r/∂θ adds (S σ_θ)².
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from estimator.factors.base import Block
from estimator.problem import (
    Problem,
)
from estimator.solver.banded import LAMBDA_MIN, BandedSystem
from estimator.solver.linearize import Linearizer, z_columns
from physics.softness import scale as scale_softness

if TYPE_CHECKING:
    from estimator.solver.window import WindowResult


def honest(blocks: list[Block]) -> list[Block]:
    """The blocks with each residual row's σ scaled up by the RMS of its whitened residuals
    over the window where that exceeds 1 (a variance component per row, σ̂² = mean_k r_k²):
    where the model does not explain the motion as well as its σ says (a wrong mass, a
    contact softer than modeled), the covariance grows with what the residuals show instead
    of trusting the factor as exact. Rows that fit within their σ keep it."""
    out = []
    for b in blocks:
        r2 = np.where(b.valid, b.r**2, 0.0)
        count = np.maximum(b.valid.sum(axis=0), 1)
        scale = np.sqrt(np.maximum(r2.sum(axis=0) / count, 1.0))  # (m,) per row
        if np.all(scale == 1.0):
            out.append(b)
            continue
        if b.J is None:
            J = None
        elif b.dofwise:
            J = b.J / scale[None, None, :, None]
        else:
            J = b.J / scale[None, :, None]
        J_bias = None if b.J_bias is None else b.J_bias / scale[None, :, None]
        out.append(replace(b, r=b.r / scale, J=J, J_bias=J_bias))
    return out


def with_covariance(
    result: WindowResult, keys: range | None = None, problem: Problem | None = None
) -> WindowResult:
    """`result` with the marginal standard deviations of x_k at `keys` (None: every knot) from
    its last linearization, and their warnings; with the problem, also the variance of the
    model's uncertain parameters (`consider_variance`) and of where the solve stopped: the
    step still to the minimum (`remaining_step`). A solve stops on its relative tolerance, or
    on a step damped by rejected ones, short of the minimum, and where it stops depends on
    where it started (a window's overlap, a chunk's start): the estimate is uncertain by that
    much besides its marginal σ — small where the solve converged; large where the cost is
    flat (1e-3 of a window's cost is several σ along its flattest direction) or kinked (a
    contact arriving: 1% of the step raises the cost)."""
    if result.system is None:
        return result
    warnings = list(result.warnings)
    nv = result.qpos_std.shape[1]
    std = result.system.marginal_std(nv, warnings, keys)
    if problem is not None and result.solved_system is not None and result.blocks:
        # (the last linearization may be a step before the solution)
        at_solution = rows_at(problem, problem.model, result)
        variance = std**2 + consider_variance(problem, result, at_solution=at_solution)
        try:
            remaining = remaining_step(problem, result, at_solution)
            variance += remaining[:, :nv] ** 2
        except np.linalg.LinAlgError:  # no system positive definite at LAMBDA_MIN
            pass
        std = np.sqrt(variance)
    return replace(result, qpos_std=std, warnings=warnings)


def remaining_step(problem: Problem, result: WindowResult, rows: list[np.ndarray]) -> np.ndarray:
    """(T, nz) the Gauss–Newton step from the solution, −H⁻¹ Jᵀ r(x̂): H and J those of the
    last linearization, r the rows at the solution (`rows_at`) and the window's marginal
    prior at it. A solve stops when its last step lowered the cost by less than the
    tolerance, where the gradient is small in cost but not in the flat directions (zero only
    at the minimum)."""
    system = result.solved_system
    assert system is not None
    lin = Linearizer(problem, result.prior)
    try:
        at_solution = [replace(b, r=r) for b, r in zip(result.blocks, rows, strict=True)]
        g = BandedSystem.of(at_solution, lin, result.bias, result.qpos).g
    finally:
        lin.close()
    s, ab = system.scaled_band()
    return system.damped_steps(s, ab, LAMBDA_MIN, g[..., None])[..., 0]


CONSIDER_STEP = 0.01  # relative change of a parameter for its finite difference
MAX_SPREAD = 0.5  # the sigma points' half-width at most (a scale 1 − σ must stay positive)


def _scaled_softness(model: mujoco.MjModel, factor: float) -> None:
    scale_softness(model, eps_scale=factor)


def _scaled_timeconst(model: mujoco.MjModel, factor: float) -> None:
    scale_softness(model, kappa_scale=factor)


def _scaled_masses(model: mujoco.MjModel, scale: float) -> None:
    """Every body's mass and inertia times `scale`."""
    model.body_mass[:] *= scale
    model.body_inertia[:] *= scale


# the model's parameters the covariances consider: name → (relative change, its σ setting)
CONSIDERED = {
    "softness_eps": (_scaled_softness, "model_softness_std"),
    "softness_kappa": (_scaled_timeconst, "model_softness_std"),
    "masses": (_scaled_masses, "model_mass_std"),
}


def rows_at(problem: Problem, model: mujoco.MjModel, result: WindowResult) -> list[np.ndarray]:
    """Every factor's rows (robust weights applied) at the result's solution with `model`,
    block by block as `result.blocks`."""
    lin = Linearizer(replace(problem, model=model))
    try:
        return [b.r for b in lin.blocks(lin.terms(result.qpos, False), result.bias)]
    finally:
        lin.close()


def key_gradient(problem: Problem, blocks: list[Block], rows: list[np.ndarray]) -> np.ndarray:
    """Jᵀ r by key (T, nz): the blocks' Jacobians on `rows` (one (K, m) per block) — those of
    the physics and the sensors; the priors', on the motion alone, left out."""
    nz, K = problem.nz, problem.T - 2
    out = np.zeros((problem.T, nz))
    for block, r in zip(blocks, rows, strict=True):
        if block.dofwise or block.J is None:
            continue
        J, cols = z_columns(problem, block)
        flat = np.einsum("kmc,km->kc", J, r)
        for a in range(int(cols.max(initial=-1)) // nz + 1):  # knot row i reaches key i + a
            at = cols // nz == a
            out[a : a + K, cols[at] % nz] += flat[:, at]
    return out


def parameter_sensitivities(
    problem: Problem,
    result: WindowResult,
    system: BandedSystem,
    perturbations: list[tuple[str, float]],
    at: list[np.ndarray],
) -> list[tuple[list[np.ndarray], np.ndarray, np.ndarray]]:
    """For each CONSIDERED parameter θ (a relative change) and step: ∂r/∂θ of every factor's
    rows (one (K, m) per block: the physics, and the sensors the model predicts through θ — a
    force/torque sensor through the contacts) as the difference quotient over θ → θ + step,
    C = Jᵀ ∂r/∂θ by key (T, nz) and the estimate's sensitivity S = −H⁻¹ C (T, nz) with H
    that of `system` (one factorization for all); `at`: the rows at the result's solution
    (`rows_at`)."""
    parts = []
    for name, step in perturbations:
        perturb, _ = CONSIDERED[name]
        model = copy.deepcopy(problem.model)
        perturb(model, 1.0 + step)
        moved = rows_at(problem, model, result)
        dr = [(r - r0) / step for r, r0 in zip(moved, at, strict=True)]
        parts.append((dr, key_gradient(problem, result.blocks, dr)))
    s, ab = system.scaled_band()
    S = system.damped_steps(s, ab, LAMBDA_MIN, np.stack([C for _, C in parts], axis=-1))
    return [(dr, C, S[..., i]) for i, (dr, C) in enumerate(parts)]


def consider_variance(
    problem: Problem,
    result: WindowResult,
    parameters: tuple[str, ...] = tuple(CONSIDERED),
    at_solution: list[np.ndarray] | None = None,
) -> np.ndarray:
    """(T, nv) the variance the estimate inherits from the model's uncertain parameters,
    which it does not estimate (Schmidt's consider covariance): per parameter θ — the contact
    softness ε and κ and the masses, each as a relative scale with σ_θ from the settings
    (model_softness_std, model_mass_std) — the estimate's sensitivity S_θ = −H⁻¹ Jᵀ ∂r/∂θ
    (H, J of the solved system; ∂r/∂θ of every factor's rows by a finite difference at the
    solution: the physics, and the sensors predicted through θ — a force/torque sensor
    through the contacts; secants to θ ± σ_θ) adds (S_θ σ_θ)², as its mean over the window
    per dof. A contact softer than modeled lets the robot sit lower: the height's variance
    grows by that much. `at_solution`: the rows at the solution (`rows_at`), if computed."""
    system = result.solved_system
    nv = problem.model.nv
    variance = np.zeros((problem.T, nv))
    if system is None or not result.blocks:
        return variance
    sides: list[tuple[str, float]] = []  # (parameter, ±its spread)
    for name in parameters:
        sigma = getattr(problem.settings, CONSIDERED[name][1])
        if sigma <= 0:
            continue
        # the two points θ ± σ_θ (the unscented transform's, in one parameter): the
        # estimate's variance ½ (Δ₊² + Δ₋²) with Δ± = S± σ_θ from the secants to each —
        # a contact's force is far from linear in its softness (the tangent at θ overstated a
        # humanoid's fall by 4.6×), and one side may be cut off (κ ≥ 2h)
        spread = min(sigma, MAX_SPREAD)
        sides.append((name, spread))
        sides.append((name, -spread))
    if not sides:
        return variance
    if at_solution is None:  # (the linearization may be a step before the solution)
        at_solution = rows_at(problem, problem.model, result)
    try:
        S = [S for _, _, S in parameter_sensitivities(problem, result, system, sides, at_solution)]
    except np.linalg.LinAlgError:
        return variance
    for (name, _), S_plus, S_minus in zip(sides[::2], S[::2], S[1::2], strict=True):
        sigma = getattr(problem.settings, CONSIDERED[name][1])
        # its RMS over the window, per dof: a constant parameter moves the estimate by about
        # this much throughout, where the linear sensitivity may pass through zero (a load
        # moving from foot to foot)
        variance += np.mean((S_plus[:, :nv] ** 2 + S_minus[:, :nv] ** 2) * (sigma**2 / 2.0), axis=0)
    return variance
