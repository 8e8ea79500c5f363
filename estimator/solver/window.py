"""One window solved: Levenberg–Marquardt from a start, its past marginalized into a prior on
the next window's first keys, and the backward step that lets the windows before follow.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import mujoco
import numpy as np
import scipy.linalg

from estimator.factors.base import Block
from estimator.factors.marginal_prior import MarginalPrior
from estimator.problem import (
    Problem,
    retract,
)
from estimator.solver.banded import (
    LAMBDA_MIN,
    LAMBDA_REJECTED,
    MARGINAL_REGULARIZER,
    BandedSystem,
)
from estimator.solver.covariance import honest, with_covariance
from estimator.solver.linearize import Derivatives, Linearizer


@dataclass(frozen=True)
class WindowResult:
    qpos: np.ndarray  # (T, nq)
    bias: np.ndarray  # (T, nb)
    qpos_std: np.ndarray  # (T, nv)
    iterations: int
    converged: bool
    cost_initial: float
    cost_final: float
    cost_by_type: dict[str, float]
    warnings: list[str]
    linearizations: int = 0  # MuJoCo passes with Jacobians (mjd_inverseFD at every knot)
    evaluations: int = 0  # passes without (mj_inverse at every knot)
    # the last linearization (at the solution, or one step below the tolerance before it),
    # its rows' σ scaled to what the residuals show (`honest`): the covariances' system
    system: BandedSystem | None = None
    # that linearization as solved (unscaled) and its factors' rows, for the sensitivity of
    # the estimate to the model's parameters (`consider_variance`)
    solved_system: BandedSystem | None = None
    blocks: list[Block] = field(default_factory=list)
    next_prior: MarginalPrior | None = None  # for the window that starts at `next_start`
    next_start: int | None = None  # the key where the next window starts (`marginalize`)
    prior: MarginalPrior | None = None  # the window's own (its rows' share of the gradient)


def solve_window(
    problem: Problem,
    qpos: np.ndarray,
    bias: np.ndarray,
    covariance: bool | range = True,
    prior: MarginalPrior | None = None,
    marginalize: int | range | None = None,
    derivatives: Derivatives | None = None,
    first: int = 0,
) -> WindowResult:
    """Levenberg–Marquardt on one window from (qpos (T, nq), bias (T, nb)); the marginal
    covariances at the knots `covariance` (True: all; False: none).

    prior: what the knots before the window say about its first keys (`MarginalPrior`).
    marginalize: the key where the next window starts: its prior (`WindowResult.next_prior`)
    is this window's past up to there, marginalized at the last linearization; a range: the
    quietest of those keys (`quietest_join`).
    derivatives, first: MuJoCo's derivatives kept across solves (a stream's window, which
    starts at the stream's knot `first`; `linearize.Derivatives`)."""
    lin = Linearizer(problem, prior, derivatives, first)
    try:
        p = problem
        blocks = lin.linearize(qpos, bias)  # (its rows give the start's cost too)
        cost, by_type = lin.cost_of(blocks, qpos, bias)
        cost0 = cost
        # damping λ on the unit diagonal: from LAMBDA_MIN (Gauss–Newton steps), raised only by
        # rejected steps (on the 1-minute humanoid_push log 120 linearizations against 157
        # from λ = 1e-3, and the lower cost)
        lam = LAMBDA_MIN
        converged = False
        it = 0
        system = None
        for it in range(1, p.settings.max_iterations + 1):
            if it > 1:
                blocks = lin.linearize(qpos, bias)
            at = (qpos, bias)
            system = BandedSystem.of(blocks, lin, bias, qpos)
            s, ab = system.scaled_band()
            while lam <= 1e10:
                try:
                    dx = system.damped_step(s, ab, lam)
                except np.linalg.LinAlgError:  # too ill-conditioned at this λ: a rejected step
                    lam *= 10.0
                    continue
                # a step the model says cannot lower the cost by the tolerance ends the window
                # unevaluated (more damping only shortens it)
                if system.predicted_decrease(s, lam, dx) < p.settings.tolerance * cost:
                    converged = True
                    break
                q_new = retract(p.model, qpos, dx[:, : p.model.nv])
                b_new = bias + dx[:, p.model.nv :]
                cost_new, by_type_new = lin.cost(q_new, b_new)
                if cost_new < cost:
                    break
                # rejected: below λ ≈ 1e-5 (on the unit diagonal) the step hardly changes
                lam = max(10.0 * lam, LAMBDA_REJECTED)
            else:  # no λ gives a step
                converged = True
            if converged:
                break
            decrease = (cost - cost_new) / max(cost, 1e-300)
            qpos, bias, cost, by_type = q_new, b_new, cost_new, by_type_new
            lam = max(lam / 10.0, LAMBDA_MIN)
            if decrease < p.settings.tolerance:
                converged = True
                break
        result = WindowResult(
            qpos,
            bias,
            np.full((p.T, p.model.nv), np.nan),
            it,
            converged,
            cost0,
            cost,
            by_type,
            [],
            lin.passes[True],
            lin.passes[False],
            BandedSystem.of(honest(blocks), lin, bias, qpos) if blocks else system,
            system,
            blocks,
            None,
            prior=prior,
        )
        if marginalize is not None and blocks:
            start = (
                quietest_join(blocks, p.settings.accel_prior_std, marginalize, lin.span)
                if isinstance(marginalize, range)
                else marginalize
            )
            result = replace(
                result,
                next_prior=marginal_prior(lin, blocks, *at, start),
                next_start=start,
            )
    finally:
        lin.close()
    if not covariance:
        return result
    return with_covariance(result, covariance if isinstance(covariance, range) else None, problem)


def quietest_join(blocks: list[Block], sigma_a: float, keys: range, span: int) -> int:
    """Of the keys `keys`, the one where the motion is smoothest: the least of the largest
    jerk ‖a_{j+1} − a_j‖ over the knots whose rows the marginal prior summarizes around it
    (a_k from the acceleration prior's rows, a_k / σ_a). The prior is a Gaussian of the
    linearization there, which holds where the dynamics are smooth, not across an impact;
    ties go to the later key (longer windows)."""
    (prior,) = [b for b in blocks if b.name == "prior"]
    a = prior.r * sigma_a  # (K, nv): row i is knot i + 1
    jerk = np.r_[0.0, np.linalg.norm(np.diff(a, axis=0), axis=1), 0.0]  # at knot i + 1 ≈ k
    reach = span + 1  # knots on each side whose rows share keys with the join
    jerk = np.r_[jerk, np.zeros(reach + 1)]
    worst = [jerk[max(0, k - reach) : k + reach + 1].max() for k in keys]
    return keys[len(worst) - 1 - int(np.argmin(worst[::-1]))]


def marginal_prior(
    lin: Linearizer, blocks: list[Block], qpos: np.ndarray, bias: np.ndarray, start: int
) -> MarginalPrior:
    """The prior this window's past puts on keys start … start + span − 2, the first keys of
    the window that starts at `start` (they share rows with what follows): the factors on
    keys < start + span − 1 alone (`BandedSystem.of(until=…)`), linearized at (qpos, bias),
    the keys e < start eliminated, r the kept ones:

        Λ = H_rr − H_re H_ee⁻¹ H_er,   g̃ = g_r − H_re H_ee⁻¹ g_e,   δ̂ = −Λ⁺ g̃

    (the sliding-window smoother's Schur complement; H_ee is banded: one banded Cholesky)."""
    n = lin.span - 1
    part = BandedSystem.of(blocks, lin, bias, qpos, until=start + n - 1)
    nz = part.diag.shape[1]

    def H(i: int, j: int) -> np.ndarray:  # key block H_ij of the past's system (0 beyond)
        if i == j:
            return part.diag[i]
        if i > j:
            return part.lower[i - j - 1][j] if i - j <= n else np.zeros((nz, nz))
        return H(j, i).T

    kept = range(start, start + n)
    touching = range(max(0, start - n), start)  # eliminated keys coupled to the kept ones
    H_rr = np.block([[H(i, j) for j in kept] for i in kept])
    H_er = np.zeros((start * nz, n * nz))
    for k in touching:
        H_er[k * nz : (k + 1) * nz] = np.hstack([H(k, j) for j in kept])
    past = BandedSystem(
        part.diag[:start],
        [lo[: max(start - d, 0)] for d, lo in enumerate(part.lower, 1)],
        part.g[:start],
    )
    s, ab = past.scaled_band()
    ab[0] += MARGINAL_REGULARIZER  # (bias dims no factor of the past reaches yet)
    L = scipy.linalg.cholesky_banded(ab, lower=True, check_finite=False)
    rhs = np.hstack([H_er, part.g[:start].reshape(-1, 1)])
    X = s[:, None] * scipy.linalg.cho_solve_banded((L, True), s[:, None] * rhs)
    info = H_rr - H_er.T @ X[:, :-1]
    g = part.g[start : start + n].reshape(-1) - H_er.T @ X[:, -1]
    info = 0.5 * (info + info.T)
    d = 1.0 / np.sqrt(np.maximum(np.diag(info), 1e-300))  # Jacobi scaling: stiff contacts
    mean = -d * (scipy.linalg.pinvh(d[:, None] * info * d[None, :]) @ (d * g))
    return MarginalPrior(
        qpos[start : start + n].copy(), bias[start : start + n].copy(), info, mean, -X[:, :-1]
    )


def follow(
    model: mujoco.MjModel,
    prior: MarginalPrior,
    moved: tuple[np.ndarray, np.ndarray],
    now: tuple[np.ndarray, np.ndarray],
    past: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """The marginalized keys `past` (qpos (m, nq), bias (m, nb)) updated for the next
    window having moved the shared keys from `moved` to `now` ((n, nq), (n, nb) each):
    δ_e = −H_ee⁻¹ H_er δ_r, the minimum of the past's factors given the shared keys
    (a Rauch–Tung–Striebel backward step on the linearized system), so that the windows
    join without a seam."""
    delta = []
    for k in range(prior.keys):
        dq = np.zeros(model.nv)
        mujoco.mj_differentiatePos(model, dq, 1.0, moved[0][k], now[0][k])
        delta.append(np.r_[dq, now[1][k] - moved[1][k]])
    step = (prior.gain @ np.concatenate(delta)).reshape(len(past[0]), -1)
    return retract(model, past[0], step[:, : model.nv]), past[1] + step[:, model.nv :]
