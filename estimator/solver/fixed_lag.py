"""The fixed-lag smoother: the batch sweep's window (`window.solve_window`) advanced as knots
become ready, its keys older than the lag marginalized into the prior on the ones that stay
(`window.marginal_prior`, the same Schur complement the batch sweep hands from window to
window).

    lag = FixedLag(config, settings, compiled, t0_ns, lag_knots=50)
    step = lag.advance(measurements, last_key=k)   # keys first … k solved
    step.estimate, step.newest, step.smoothed       # knots to publish (window indices)

Each advance solves the window [first, last_key] once (Levenberg–Marquardt, at most
`settings.max_iterations` steps) from the previous solution, the new keys extrapolated at
constant velocity and set to their measured coordinates; then the keys more than `lag_knots`
behind the newest leave: their estimate is final (smoothed) and their factors become the
prior of the next window's first keys.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from estimator.config import Config
from estimator.estimate import Estimate
from estimator.factors.marginal_prior import MarginalPrior
from estimator.io.logs.measurements import Measurement
from estimator.leg_odometry import START_POSITION_STD_M, START_YAW_STD_RAD, unanchored
from estimator.problem import build_problem
from estimator.run import collect_estimate, initial_trajectory
from estimator.settings import Settings
from estimator.solver.banded import BandedSystem
from estimator.solver.linearize import Derivatives, row_span
from estimator.solver.window import WindowResult, solve_window

MIN_KEYS = 8  # a window solves once it has this many keys (the marginal prior needs 3 + 3)
BLOWUP = 1e3  # a solve whose cost per knot exceeds this many times the recent median diverged


@dataclass(frozen=True)
class LagStep:
    """One advance of the fixed-lag smoother.

    estimate: the window's knots (forces and contacts at `newest` and `smoothed` only).
    newest: window indices of the knots published for the first time (the newest estimate:
        each knot once its rows are all in, i.e. up to the key before the last).
    smoothed: window indices of the knots that left the lag, and of the first key that
        stays (its rows are all in the next window's prior): their final estimate.
    first: the global index of the window's first knot.
    diverged: why the solve was rejected and the window reset ("" if it was not).
    known_sigma: (W, nv) the physics residual's σ per knot (`Problem.known_sigma`).
    """

    estimate: Estimate
    newest: range
    smoothed: range
    first: int
    result: WindowResult | None  # the window's solve (None: an incremental update's)
    diverged: str = ""
    known_sigma: np.ndarray | None = None
    relinearized: int = 0  # the keys whose rows the solve relinearized (a whole solve: all)


class FixedLag:
    """The sliding window of a live stream: its keys, their solution and the prior that the
    marginalized knots left on the first of them."""

    def __init__(
        self,
        config: Config,
        settings: Settings,
        compiled: tuple[mujoco.MjModel, dict[str, list[str]]],
        t0_ns: int,
        lag_knots: int,
    ) -> None:
        self.config, self.settings, self.compiled = config, settings, compiled
        self.model = compiled[0]
        self.h = settings.h or float(self.model.opt.timestep)
        self.step_ns = round(self.h * 1e9)
        self.t0_ns = t0_ns
        self.lag_knots = max(lag_knots, MIN_KEYS // 2)
        self.first = 0  # global index of the window's first key
        self.qpos = np.zeros((0, self.model.nq))  # the window's keys as last solved
        self.bias: np.ndarray | None = None
        self.prior: MarginalPrior | None = None
        self.published = 0  # the next knot (global) whose newest estimate is due
        self.recent_cost: deque[float] = deque(maxlen=50)  # cost per knot of recent solves
        self.converge = 0  # the iterations of the next solve, if more than an update's
        # MuJoCo's derivatives, reused where a knot moved less than 1 mm or mrad since they
        # were taken (trot in half-lag steps: 182 against 165 knots/s at 0.1 mm, smoothed
        # base 0.153 and 0.154 mm; at 1 cm humanoid_push's torso 0.124 against 0.089 mm)
        self.derivatives = Derivatives(self.h, 1e-3)

    def t_ns(self, first: int, stop: int) -> np.ndarray:
        """Global knot times of keys first … stop − 1."""
        return self.t0_ns + self.step_ns * np.arange(first, stop, dtype=np.int64)

    def advance(self, measurements: Mapping[str, Measurement], last_key: int) -> LagStep | None:
        """Solve keys first … last_key from the measurements buffered around them; None while
        the window has fewer than MIN_KEYS keys."""
        stop = last_key + 1
        if stop - self.first < MIN_KEYS:
            return None
        t_ns = self.t_ns(self.first, stop)
        settings = self.settings
        if self.converge:  # (`retune`)
            settings, self.converge = replace(settings, max_iterations=self.converge), 0
        problem = build_problem(self.config, measurements, settings, t_ns, self.compiled)
        qpos, bias = self._start(measurements, t_ns, problem.nb)
        if not len(self.qpos) and unanchored(self.model, measurements):
            # no mocap: the first window holds the start pose's x, y, yaw (as `run.smooth`)
            self.prior = MarginalPrior.start_pose(
                self.model, qpos, bias, problem.bias_prior, START_POSITION_STD_M, START_YAW_STD_RAD
            )
        W = len(t_ns)
        n_shared = row_span(self.settings) - 1
        leave = W - self.lag_knots  # keys that leave the lag with this solve
        marginalize = leave if leave >= 1 and leave + n_shared <= W else None
        diverged = ""
        try:
            result = solve_window(
                problem,
                qpos,
                bias,
                covariance=False,
                prior=self.prior,
                marginalize=marginalize,
                derivatives=self.derivatives,
                first=self.first,
            )
            diverged = self._diverged(result.qpos, result.cost_final / max(W - 2, 1))
        except (np.linalg.LinAlgError, FloatingPointError, ValueError) as err:
            diverged, result = f"the solve failed ({err})", None
        if diverged:  # start over from the measurements alone, without the prior
            self.prior = None
            self.derivatives.clear()
            qpos, bias = self._start(measurements, t_ns, problem.nb, reset=True)
            result = solve_window(problem, qpos, bias, covariance=False, marginalize=marginalize)
        assert result is not None
        self.recent_cost.append(result.cost_final / max(W - 2, 1))
        # the keys that leave, and the first that stays (the next window's key 0, whose rows
        # are then in its prior): final now
        cut = result.next_start or 0
        smoothed = range(1, cut + 1) if cut else range(0)
        newest = range(max(self.published - self.first, 1), W - 1)
        publish = sorted({*newest, *smoothed})
        std = published_std(result.system, self.model.nv, W, newest, smoothed)
        estimate = collect_estimate(
            problem, result.qpos, result.bias, std, self.config, publish, residuals=False
        )
        step = LagStep(
            estimate, newest, smoothed, self.first, result, diverged, problem.known_sigma, W
        )
        self.published = self.first + W - 1
        self.qpos, self.bias = result.qpos[cut:].copy(), result.bias[cut:].copy()
        self.first += cut
        self.prior = result.next_prior if cut else self.prior
        self.derivatives.forget_before(self.first)
        return step

    def finish(self, measurements: Mapping[str, Measurement]) -> LagStep | None:
        """The end of the stream: the remaining keys solved once more and all published as
        smoothed (None if the window never reached MIN_KEYS keys)."""
        stop = self.first + len(self.qpos)
        if stop - self.first < MIN_KEYS:
            return None
        t_ns = self.t_ns(self.first, stop)
        problem = build_problem(self.config, measurements, self.settings, t_ns, self.compiled)
        result = solve_window(problem, self.qpos, self._bias(problem.nb), False, self.prior)
        W = len(t_ns)
        smoothed = range(1, W - 1)
        std = np.full((W, self.model.nv), np.nan)
        if result.system is not None:
            std = result.system.marginal_std(self.model.nv, [], range(1, W))
        estimate = collect_estimate(
            problem, result.qpos, result.bias, std, self.config, smoothed, residuals=False
        )
        newest = range(max(self.published - self.first, 1), W - 1)
        return LagStep(estimate, newest, smoothed, self.first, result, "", problem.known_sigma, W)

    def close(self) -> None:
        """Let go of what the window holds open (the incremental update's engines)."""

    def reset(self) -> None:
        """Drop the window's solution and prior: the next advance starts from the
        measurements."""
        self.qpos = np.zeros((0, self.model.nq))
        self.prior = None

    def retune(self, settings: Settings, iterations: int) -> None:
        """Take new settings (a contact softness fitted while the stream ran): the next
        advance re-solves the whole window with them, up to `iterations` iterations, from its
        solution so far (not from the measurements: through a mocap dropout they do not hold
        the base; nor in an update's few iterations: H1's pelvis stayed near the old depth,
        0.20 mm off against 0.11), MuJoCo's derivatives retaken."""
        self.settings = settings
        self.converge = iterations
        self.derivatives.clear()
        self.recent_cost.clear()

    # -- the start of a solve ------------------------------------------------------------------

    def _bias(self, nb: int) -> np.ndarray:
        if self.bias is None or self.bias.shape[1] != nb:
            self.bias = np.zeros((len(self.qpos), nb))
        return self.bias

    def _start(
        self,
        measurements: Mapping[str, Measurement],
        t_ns: np.ndarray,
        nb: int,
        reset: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The window's start: the previous solution on the keys it had; the new keys at
        constant velocity from the last two, their measured coordinates set to the
        measurements (the whole window from the measurements at the start or a reset)."""
        model, W = self.model, len(t_ns)
        have = 0 if reset else len(self.qpos)
        bias = np.zeros((W, nb))
        if have < 2:
            qpos = initial_trajectory(model, measurements, t_ns)
            if have:
                bias[:have] = self._bias(nb)[:have]
            return qpos, bias
        measured = np.zeros((W - have, model.nq), dtype=bool)
        at_knots = initial_trajectory(model, measurements, t_ns[have:], measured_out=measured)
        qpos = np.empty((W, model.nq))
        qpos[:have] = self.qpos
        v = np.zeros(model.nv)
        mujoco.mj_differentiatePos(model, v, self.h, self.qpos[-2], self.qpos[-1])
        for k in range(have, W):
            qpos[k] = qpos[k - 1]
            mujoco.mj_integratePos(model, qpos[k], v, self.h)
        new = slice(have, W)
        qpos[new] = np.where(measured, at_knots, qpos[new])
        for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
            quat = model.jnt_qposadr[j] + 3  # a free joint's quaternion, renormalized
            qpos[new, quat : quat + 4] /= np.linalg.norm(
                qpos[new, quat : quat + 4], axis=1, keepdims=True
            )
        old = self._bias(nb)
        bias[:have] = old
        bias[have:] = old[-1]
        return qpos, bias

    def _diverged(self, qpos: np.ndarray, per_knot: float) -> str:
        """Why a solve is not to be trusted ("" if it is): NaN, or a cost per knot BLOWUP
        times the recent median."""
        if not (np.all(np.isfinite(qpos)) and np.isfinite(per_knot)):
            return "the solution is not finite"
        if len(self.recent_cost) >= 5:
            median = float(np.median(self.recent_cost))
            if per_knot > BLOWUP * max(median, 1e-12):
                return f"its cost per knot {per_knot:.3g} is {per_knot / median:.3g}× the recent"
        return ""


def published_std(
    system: BandedSystem | None, nv: int, W: int, newest: range, smoothed: range
) -> np.ndarray:
    """(W, nv) marginal σ at the knots to publish (NaN at the others): the newest from the
    last key down, the smoothed from the first key up (the system reversed), so that neither
    costs the whole window."""
    std = np.full((W, nv), np.nan)
    if system is None:
        return std
    warnings: list[str] = []
    if len(newest):
        std[newest] = system.marginal_std(nv, warnings, range(newest.start, W))[newest]
    if len(smoothed):
        back = system.reversed().marginal_std(nv, warnings, range(W - smoothed.stop, W))
        std[smoothed] = back[::-1][smoothed]
    return std
