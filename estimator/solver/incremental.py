"""The fixed-lag smoother updated incrementally: at each update only the rows of the newest
keys are relinearized; the older rows stay in a kept linear system.

`fixed_lag.FixedLag` re-solves its whole window at every update, which costs about as much for
one new key as for fifty. Here the rows of the knots older than the newest `relinearize` keys
are kept linear — their normal equations summed once, at the state where they were last
relinearized — as iSAM2 relinearizes only the variables that moved (Kaess et al. 2012), and a
key that leaves the lag is eliminated from the kept system (the sliding-window filter's Schur
complement). With x̄ the kept rows' linearization point and d = x ⊖ x̄, per update:

    new keys             extrapolated at constant velocity, measured coordinates set (`_start`)
    tail rows            the rows reaching the newest `relinearize` keys, linearized at x
    step                 (H_kept + H_tail + λD) Δ = −(g_kept + H_kept d + g_tail),  x ← x ⊕ Δ
    rows leaving tail    H_kept += H_u,  g_kept += g_u − H_u d_u      (linearized at x_u)
    a key leaving lag    H_kept ← H_rr − H_r0 H_00⁻¹ H_0r,  g_kept ← g_r − H_r0 H_00⁻¹ g_0

The window starts as the batch fixed lag (whole solves from the measurements) and turns
incremental once its first key has left; a divergence goes back to that start.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import mujoco
import numpy as np
import scipy.linalg

from estimator.config import Config
from estimator.io.logs.measurements import Measurement
from estimator.problem import build_problem, retract
from estimator.run import collect_estimate
from estimator.settings import Settings
from estimator.solver.banded import (
    MARGINAL_REGULARIZER,
    BandedSystem,
    factor_std,
    front_std,
)
from estimator.solver.fixed_lag import FixedLag, LagStep, published_std
from estimator.solver.linearize import THREADS, Linearizer, row_span
from physics.dynamics import Dynamics, make_dynamics
from physics.knots import KnotBatch

# the newest knots whose rows each update relinearizes, s (the stream's default): 4 keys of
# humanoid_push, 8 of quadruped_trot (1 or 4 keys: the trot's smoothed joints 6× or 1.5×
# the batch estimate's; 8: 1.15×)
RELINEARIZE_S = 0.04


# a key whose last step moved a coordinate more than this (m or rad) keeps its rows in the
# tail, relinearized (iSAM2's relinearization threshold; the same 1 mm or mrad within which
# MuJoCo's derivatives are reused): a backlog worked off many keys at a time, or keys that
# start far off, are solved again before their rows are kept (Go2 replayed at --rate 0
# through its 1.28 s mocap dropout: base 0.42–0.47 mm smoothed, 0.58 without; at 0.1 mm
# the tail often reaches back to the leaving keys, and one of two runs ended 5.3 mm off)
RELINEARIZE_STEP = 1e-3

# the smoothed keys whose σ an update takes by a triangular solve across the window each
# (`front_std`); more (a backlog worked off): from the reversed system's own factorization
FRONT_SOLVES = 2


class IncrementalLag(FixedLag):
    """A stream's window whose past rows are kept linear (`FixedLag`'s interface).

    relinearize: the newest keys whose rows are relinearized at each update."""

    def __init__(
        self,
        config: Config,
        settings: Settings,
        compiled: tuple[mujoco.MjModel, dict[str, list[str]]],
        t0_ns: int,
        lag_knots: int,
        relinearize: int,
    ) -> None:
        super().__init__(config, settings, compiled, t0_ns, lag_knots)
        self.relinearize = max(relinearize, 1)
        self.span = row_span(settings)  # keys a knot's rows reach
        self.engines: KnotBatch | None = None  # (made once, on the windows' model)
        self.dynamics: Dynamics | None = None
        self.kept: BandedSystem | None = None  # over the window's keys, in x̄ coordinates
        self.anchor = (np.zeros((0, self.model.nq)), np.zeros((0, 0)))  # x̄: (qpos, bias)
        self.rows_kept = 0  # the rows of window knots < rows_kept are in `kept`
        self.walk_kept = 0  # and the bias walk steps k → k + 1 for k < walk_kept
        self.moved = np.zeros(0)  # per key, its largest coordinate's last step (m or rad)

    def advance(self, measurements: Mapping[str, Measurement], last_key: int) -> LagStep | None:
        if self.kept is None:
            step = super().advance(measurements, last_key)
            if step is not None and len(step.smoothed) and not step.diverged:
                self._begin(measurements)
            return step
        return self._update(measurements, last_key)

    def reset(self) -> None:
        super().reset()
        self.kept = None

    def retune(self, settings: Settings, iterations: int) -> None:
        super().retune(settings, iterations)
        self.kept = None  # (its rows are the old model's: whole solves until a key leaves)
        self.close()  # (the engines hold the old model)
        self.dynamics = None

    # -- the kept system ------------------------------------------------------------------------

    def _begin(self, measurements: Mapping[str, Measurement]) -> None:
        """From the whole solve's window: its rows but the tail's, and its marginal prior,
        linearized at its solution, kept."""
        W = len(self.qpos)
        tail = W - self.relinearize
        rows_lo = tail - self.span + 2  # the first knot whose rows reach the tail
        if rows_lo < 2:
            return  # (a lag shorter than the tail: stays whole)
        t_ns = self.t_ns(self.first, self.first + W)
        problem = build_problem(self.config, measurements, self.settings, t_ns, self.compiled)
        if self.engines is None:
            self.engines = KnotBatch(
                problem.model, THREADS, self.settings.path, self.settings.fd_eps
            )
        bias = self._bias(problem.nb)
        lin = Linearizer(problem, self.prior, self.derivatives, self.first, self.engines)
        try:
            blocks = lin.linearize(self.qpos, bias)
            self.kept = BandedSystem.of(
                blocks, lin, bias, self.qpos, rows=range(1, rows_lo), walk=range(0, tail - 1)
            )
        finally:
            lin.close()
        self.anchor = (self.qpos.copy(), bias.copy())
        self.rows_kept, self.walk_kept = rows_lo, tail - 1
        self.moved = np.zeros(W)  # (solved whole, to its tolerance)
        self.prior = None  # (in `kept` now)

    def _grow(self, W: int, qpos: np.ndarray, bias: np.ndarray) -> None:
        """The kept system and x̄ over W keys (the new keys: no kept rows, x̄ = x)."""
        assert self.kept is not None
        k = self.kept
        n = W - len(k.diag)
        if n <= 0:
            return
        nz = k.diag.shape[1]
        k.diag = np.concatenate([k.diag, np.zeros((n, nz, nz))])
        k.lower = [np.concatenate([lo, np.zeros((n, nz, nz))]) for lo in k.lower]
        k.g = np.concatenate([k.g, np.zeros((n, nz))])
        self.anchor = (
            np.concatenate([self.anchor[0], qpos[-n:]]),
            np.concatenate([self.anchor[1], bias[-n:]]),
        )

    def _offset(self, qpos: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """d = x ⊖ x̄ (W, nz)."""
        nv = self.model.nv
        d = np.zeros((len(qpos), nv + bias.shape[1]))
        for k in range(len(qpos)):
            mujoco.mj_differentiatePos(self.model, d[k, :nv], 1.0, self.anchor[0][k], qpos[k])
        d[:, nv:] = bias - self.anchor[1]
        return d

    def _keep(self, part: BandedSystem, at: int, d: np.ndarray) -> None:
        """Rows linearized at x (their system `part`, on the keys from `at`) into the kept
        system: H += H_u, g += g_u − H_u d_u."""
        assert self.kept is not None
        add_at(self.kept, part, at)
        self.kept.g[at : at + len(part.g)] -= times(part, d[at : at + len(part.g)])

    def _with_kept(self, fresh: BandedSystem, at: int, d: np.ndarray) -> BandedSystem:
        """The window's system at x: the kept rows through their linear model (g + H d) and
        the tail's rows `fresh` (on the keys from `at`)."""
        assert self.kept is not None
        k = self.kept
        total = BandedSystem(k.diag.copy(), [lo.copy() for lo in k.lower], k.g + times(k, d))
        add_at(total, fresh, at)
        return total

    def _eliminate(self) -> None:
        """Key 0 out of the kept system (all its rows are in it), and out of the window."""
        assert self.kept is not None
        self.kept = eliminate_first(self.kept)
        self.anchor = (self.anchor[0][1:], self.anchor[1][1:])
        self.moved = self.moved[1:]
        self.qpos, self.bias = self.qpos[1:], self._bias(self.anchor[1].shape[1])[1:]
        self.rows_kept -= 1
        self.walk_kept -= 1
        self.first += 1

    # -- an update ------------------------------------------------------------------------------

    def _update(self, measurements: Mapping[str, Measurement], last_key: int) -> LagStep | None:
        assert self.kept is not None
        stop = last_key + 1
        W = stop - self.first
        t_ns = self.t_ns(self.first, stop)
        nb = self.anchor[1].shape[1]
        # the tail: the newest `relinearize` keys, and every key not yet solved once or that
        # moved more than RELINEARIZE_STEP in the last update (rows leave it only once their
        # keys have settled)
        moving = np.flatnonzero(self.moved > RELINEARIZE_STEP)
        settled = min(len(self.qpos), moving[0] if len(moving) else len(self.qpos))
        qpos, bias = self._start(measurements, t_ns, nb)
        self._grow(W, qpos, bias)
        # (the rows of the keys that leave the lag with this update kept: they are eliminated;
        # and those of the next key, whose knot the next update's problem starts before)
        leave = max(W - self.lag_knots, 0)
        tail = max(min(W - self.relinearize, settled), self.walk_kept + 1, leave + self.span)
        rows_lo = max(tail - self.span + 2, self.rows_kept)
        # the rows leaving the tail and the tail's, in one problem on keys s … W − 1 (from
        # two keys before the first row's: a position-stage sample of a problem's knot 1 is
        # predicted from its knot 0, where the linearization has no sensor values)
        s = self.rows_kept - 2
        window = build_problem(self.config, measurements, self.settings, t_ns, self.compiled)
        if window.nb != nb:  # (a biased stream appeared or left: start over)
            self.reset()
            return super().advance(measurements, last_key)
        problem = window.keys(s)
        rows, walk = range(rows_lo - s, W - 1 - s), range(tail - 1 - s, W - 1 - s)  # the tail's
        lin = Linearizer(problem, None, self.derivatives, self.first + s, self.engines)
        try:
            blocks = lin.linearize(qpos[s:], bias[s:])
            leaving = BandedSystem.of(
                blocks,
                lin,
                bias[s:],
                rows=range(2, rows_lo - s),
                walk=range(self.walk_kept - s, tail - 1 - s),
                bias_prior=False,
            )
            d = self._offset(qpos, bias)
            self._keep(leaving, s, d)
            self.rows_kept, self.walk_kept = rows_lo, tail - 1
            tail_rows = slice(rows.start - 1, rows.stop - 1)  # (block row i: knot i + 1)
            cost = sum(float(b.cost[tail_rows].sum()) for b in blocks) / max(len(rows), 1)
            moved = np.full(W, np.inf)
            # Gauss–Newton on the tail, the kept rows through their linear model
            for it in range(max(self.settings.max_iterations, 1)):
                if it:
                    blocks = lin.linearize(qpos[s:], bias[s:])
                    d = self._offset(qpos, bias)
                fresh = BandedSystem.of(
                    blocks, lin, bias[s:], rows=rows, walk=walk, bias_prior=False
                )
                total = self._with_kept(fresh, s, d)
                sc, ab = total.scaled_band()
                L = _factor(ab)
                if L is None:
                    break
                dx = BandedSystem.solve(L, sc, total.g[..., None])[..., 0]
                moved = np.abs(dx[:, : self.model.nv]).max(axis=1)  # (the last step's)
                qpos = retract(self.model, qpos, dx[:, : self.model.nv])
                bias = bias + dx[:, self.model.nv :]
        finally:
            lin.close()
        if L is None:
            diverged = "the update's system is not positive definite"
        else:
            diverged = self._diverged(qpos, cost)
        if diverged:
            self.reset()
            self.derivatives.clear()
            step = super().advance(measurements, last_key)
            return None if step is None else replace(step, diverged=diverged)
        self.recent_cost.append(cost)
        self.qpos, self.bias = qpos.copy(), bias.copy()  # (the estimate keeps its own)
        self.moved = moved
        # publish: the newest knots, and those leaving the lag with the first that stays
        newest = range(max(self.published - self.first, 1), W - 1)
        smoothed = range(1, leave + 1) if leave else range(0)
        nz, nv = total.diag.shape[1], self.model.nv
        assert L is not None
        std = factor_std(L, sc, nz, nv, newest)
        if len(smoothed) <= FRONT_SOLVES:  # a triangular solve across the window each
            std[smoothed] = front_std(L, sc, nz, nv, smoothed)[smoothed]
        else:  # the system reversed, factored once more
            std[smoothed] = published_std(total, nv, W, range(0), smoothed)[smoothed]
        if self.dynamics is None:
            self.dynamics = make_dynamics(window.model, "native")
        estimate = collect_estimate(
            window,
            qpos,
            bias,
            std,
            self.config,
            sorted({*newest, *smoothed}),
            residuals=False,
            dynamics=self.dynamics,
        )
        step = LagStep(
            estimate, newest, smoothed, self.first, None, "", window.known_sigma, int(W - tail)
        )
        self.published = self.first + W - 1
        for _ in range(leave):
            self._eliminate()
        self.derivatives.forget_before(self.first)
        return step

    def finish(self, measurements: Mapping[str, Measurement]) -> LagStep | None:
        if self.kept is None:
            return super().finish(measurements)
        W = len(self.qpos)
        t_ns = self.t_ns(self.first, self.first + W)
        window = build_problem(self.config, measurements, self.settings, t_ns, self.compiled)
        k, bias = self.kept, self._bias(self.anchor[1].shape[1])
        d = self._offset(self.qpos, bias)
        total = BandedSystem(k.diag, k.lower, k.g + times(k, d))
        smoothed = range(1, W - 1)
        newest = range(max(self.published - self.first, 1), W - 1)
        std = published_std(total, self.model.nv, W, range(0), smoothed)
        estimate = collect_estimate(
            window, self.qpos, bias, std, self.config, smoothed, residuals=False
        )
        return LagStep(estimate, newest, smoothed, self.first, None, "", window.known_sigma, 0)

    def close(self) -> None:
        if self.engines is not None:
            self.engines.close()
            self.engines = None


def eliminate_first(system: BandedSystem) -> BandedSystem:
    """The system of keys 1 … T − 1 with key 0 eliminated (the Schur complement on the keys
    its blocks reach, H_rr − H_r0 H_00⁻¹ H_0r and g_r − H_r0 H_00⁻¹ g_0: the minimum over
    x_0 of ½ xᵀHx + gᵀx), H_00 Jacobi-scaled (stiff contacts) and Cholesky-factored (its
    pseudo-inverse where it is only semidefinite). In place: the result is a view of the
    system's arrays, whose blocks next to key 0 it changes."""
    diag, lower, g = system.diag, system.lower, system.g
    nz = diag.shape[1]
    C = [lo[0] for lo in lower]  # H_{o, 0}, o = 1 … span − 1
    # X = H_00⁻¹ [H_{0,1} … H_{0,span−1}, g_0], scaled: S (S H_00 S)⁻¹ S
    s = 1.0 / np.sqrt(np.maximum(np.diag(diag[0]), 1e-300))
    A = s[:, None] * diag[0] * s[None, :]
    B = s[:, None] * np.hstack([*(c.T for c in C), g[0][:, None]])
    try:
        X = scipy.linalg.cho_solve(scipy.linalg.cho_factor(A, lower=True), B)
    except np.linalg.LinAlgError:  # (semidefinite: the pseudo-inverse)
        X = scipy.linalg.pinvh(0.5 * (A + A.T)) @ B
    X = s[:, None] * X
    for a in range(len(C)):
        g[a + 1] -= C[a] @ X[:, -1]
        for b in range(a + 1):
            block = C[a] @ X[:, b * nz : (b + 1) * nz]  # H_{a+1, 0} H_00⁻¹ H_{0, b+1}
            if a == b:
                diag[a + 1] -= block
            else:
                lower[a - b - 1][b + 1] -= block
    return BandedSystem(diag[1:], [lo[1:] for lo in lower], g[1:])


def add_at(system: BandedSystem, part: BandedSystem, at: int) -> None:
    """system += part, part's key 0 on system's key `at`."""
    n = len(part.diag)
    system.diag[at : at + n] += part.diag
    for mine, theirs in zip(system.lower, part.lower, strict=True):
        mine[at : at + len(theirs)] += theirs
    system.g[at : at + n] += part.g


def times(system: BandedSystem, d: np.ndarray) -> np.ndarray:
    """H d of a block-banded symmetric H (T, nz) (H_{k+o, k} = lower[o − 1][k])."""
    out = np.einsum("kij,kj->ki", system.diag, d)
    for o, lo in enumerate(system.lower, 1):
        n = len(lo)
        out[o : o + n] += np.einsum("kij,kj->ki", lo, d[:n])
        out[:n] += np.einsum("kji,kj->ki", lo, d[o : o + n])
    return out


def _factor(ab: np.ndarray) -> np.ndarray | None:
    """The factor of the scaled system at the least regularizer that makes it positive
    definite (MARGINAL_REGULARIZER, ×100 up to 1e-3; None: none does): one factorization for
    the step and the published σ."""
    lam = MARGINAL_REGULARIZER
    while lam <= 1e-3:
        try:
            return BandedSystem.factor(ab, lam)
        except np.linalg.LinAlgError:
            lam *= 100.0
    return None
