"""Smoothing a window of knots: Levenberg–Marquardt driven from Python, GTSAM underneath.

Each iteration linearizes every interior knot (MuJoCo's mjd_inverseFD, threaded, the GIL
released), whitens and robustly weights the rows, and hands GTSAM one JacobianFactor per knot
on (z_{k−1}, z_k, z_{k+1}); GTSAM eliminates the banded system and returns the step, and its
Marginals the covariances. Driving the loop from Python avoids GTSAM's CustomFactor path, which
copies the whole Values on every callback (../shared/DESIGN.md: 109× slower at 2000 variables).
The cost grows linearly with the number of knots.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import gtsam
import numpy as np

from estimator.problem import (
    KnotModel,
    Problem,
    accelerations,
    difference_jacobians,
    quat_error_jacobian,
    retract,
    velocities,
)

THREADS = 2


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


class Knot(NamedTuple):
    """One interior knot at the current trajectory.

    v, a, u: (nv,) velocity, acceleration, inverse-dynamics force; s: (ns,) sensordata.
    Ju (nv, 3 nv), Js (ns, 3 nv), da_dx (nv, 3 nv): derivatives with respect to
    (x_{k−1}, x_k, x_{k+1}); None when only the residual is needed.
    """

    k: int
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    s: np.ndarray
    Ju: np.ndarray | None = None
    Js: np.ndarray | None = None
    da_dx: np.ndarray | None = None


class Linearizer:
    """Residuals and their Jacobians over all knots of a problem."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.knots = [KnotModel(problem, problem.settings.path) for _ in range(THREADS)]
        self.huber = gtsam.noiseModel.mEstimator.Huber.Create(problem.settings.huber_k)
        self.pool = ThreadPoolExecutor(THREADS)

    # -- per-knot rows ------------------------------------------------------------------------

    def rows(
        self, knot: Knot, bias: np.ndarray, with_jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray | None, dict[str, float]]:
        """Whitened residual rows of knot k and their Jacobian (rows, 3·nz) on z_{k−1..k+1}.

        Returns (r, J or None, cost per factor type). Robust (Huber) weights are folded into
        the sensor rows: r ← √w r, J ← √w J, with w from GTSAM's mEstimator at ‖r‖.
        """
        p = self.problem
        nv, nb, nz = p.model.nv, p.nb, p.nz
        k, a, u, s = knot.k, knot.a, knot.u, knot.s
        jac = with_jacobian
        empty = np.zeros((0, 0))
        Ju, Js, da_dx = (knot.Ju, knot.Js, knot.da_dx) if jac else (empty, empty, empty)
        assert Ju is not None and Js is not None and da_dx is not None
        r_parts: list[np.ndarray] = []
        j_parts: list[np.ndarray] = []
        cost: dict[str, float] = {}

        def add(name: str, r: np.ndarray, J: np.ndarray | None, robust: bool) -> None:
            norm = float(np.linalg.norm(r))
            if robust and norm > 0:
                w = self.huber.weight(norm)
                cost[name] = cost.get(name, 0.0) + float(self.huber.loss(norm))
                r, J = np.sqrt(w) * r, (None if J is None else np.sqrt(w) * J)
            else:
                cost[name] = cost.get(name, 0.0) + 0.5 * norm**2
            r_parts.append(r)
            if J is not None:
                j_parts.append(J)

        # physics: W (u − u_known) on dofs with a known force
        sigma = p.physics_sigma[k]
        known = np.isfinite(sigma)
        r = (u - p.qfrc_known[k])[known] / sigma[known]
        add(
            "physics",
            r,
            _expand(Ju[known] / sigma[known, None], nv, nz) if jac else None,
            robust=False,
        )
        # smoothness prior: a_k / σ_a
        sa = p.settings.accel_prior_std
        add("prior", a / sa, _expand(da_dx / sa, nv, nz) if jac else None, robust=False)
        # sensors
        for block in p.blocks:
            meas = block.values[k]
            if not np.all(np.isfinite(meas)):
                continue
            sig = block.sigma[k] if block.sigma.ndim == 2 else block.sigma
            pred = s[block.rows]
            if block.kind == "quat":
                e, de_dp = quat_error_jacobian(pred, meas)
                r = e / sig
                J = _expand(de_dp @ Js[block.rows] / sig[:, None], nv, nz) if jac else None
            else:
                b = bias[block.bias] if block.bias is not None else 0.0
                r = (pred + b - meas) / sig
                J = None
                if jac:
                    J = _expand(Js[block.rows] / sig[:, None], nv, nz)
                    if block.bias is not None:
                        cols = 2 * nz - nb + np.arange(block.bias.start, block.bias.stop)
                        J[np.arange(len(r)), cols] += 1.0 / sig
            add(block.stream, r, J, robust=True)
        r_all = np.concatenate(r_parts) if r_parts else np.zeros(0)
        J_all = np.vstack(j_parts) if (jac and j_parts) else None
        return r_all, J_all, cost

    # -- all knots ------------------------------------------------------------------------------

    def knot_terms(self, qpos: np.ndarray, with_jacobians: bool) -> list[Knot]:
        """Inverse dynamics, sensors and (optionally) their Jacobians at each interior knot."""
        p = self.problem
        nv, h = p.model.nv, p.h
        v = velocities(p.model, qpos, h)
        a = accelerations(v, h)

        def work(chunk: range, worker: KnotModel) -> list[Knot]:
            out = []
            zero = np.zeros((nv, nv))
            dq_dx = np.hstack([zero, np.eye(nv), zero])
            for k in chunk:
                u, s = worker.evaluate(qpos[k], v[k], a[k])
                if not with_jacobians:
                    out.append(Knot(k, v[k], a[k], u, s))
                    continue
                DfDq, DfDv, DfDa, DsDq, DsDv, DsDa = worker.jacobians(qpos[k], v[k], a[k])
                rot = worker.rotations
                d1_k, d2_k = difference_jacobians(p.model, rot, qpos[k - 1], qpos[k])
                d1_n, d2_n = difference_jacobians(p.model, rot, qpos[k], qpos[k + 1])
                # v_k = (q_k ⊖ q_{k−1})/h,  a_k = (v_{k+1} − v_k)/h
                dv_dx = np.hstack([d1_k, d2_k, zero]) / h
                da_dx = np.hstack([-d1_k, d1_n - d2_k, d2_n]) / h**2
                Ju = DfDq @ dq_dx + DfDv @ dv_dx + DfDa @ da_dx
                Js = DsDq @ dq_dx + DsDv @ dv_dx + DsDa @ da_dx
                out.append(Knot(k, v[k], a[k], u, s, Ju, Js, da_dx))
            return out

        interior = range(1, p.T - 1)
        chunks = [interior[i::THREADS] for i in range(THREADS)]
        parts = list(self.pool.map(work, chunks, self.knots))
        return sorted((knot for part in parts for knot in part), key=lambda knot: knot.k)

    def cost(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[float, dict[str, float]]:
        """Total robust cost and its split by factor type."""
        total: dict[str, float] = {}
        for knot in self.knot_terms(qpos, False):
            _, _, c = self.rows(knot, bias[knot.k], with_jacobian=False)
            for key, value in c.items():
                total[key] = total.get(key, 0.0) + value
        total.update(self._bias_cost(bias))
        return sum(total.values()), total

    def linearize(
        self, qpos: np.ndarray, bias: np.ndarray
    ) -> tuple[gtsam.GaussianFactorGraph, np.ndarray]:
        """The whitened linear system at (qpos, bias) and diag(JᵀJ) per key, (T, nz)."""
        p = self.problem
        graph = gtsam.GaussianFactorGraph()
        nz = p.nz
        diag = np.zeros((p.T, nz))
        for knot in self.knot_terms(qpos, True):
            k = knot.k
            r, J, _ = self.rows(knot, bias[k], with_jacobian=True)
            assert J is not None
            unit = gtsam.noiseModel.Unit.Create(len(r))
            graph.add(
                gtsam.JacobianFactor(
                    k - 1, J[:, :nz], k, J[:, nz : 2 * nz], k + 1, J[:, 2 * nz :], -r, unit
                )
            )
            diag[k - 1 : k + 2] += np.sum(J**2, axis=0).reshape(3, nz)
        self._add_bias_factors(graph, bias, diag)
        return graph, diag

    # -- IMU bias: prior on b_0 and random walk ------------------------------------------------

    def _bias_rows(self, bias: np.ndarray) -> list[tuple[int, int | None, np.ndarray, np.ndarray]]:
        """(key_a, key_b, residual, σ) for the bias prior (key_b None) and each walk step."""
        p = self.problem
        if not p.nb:
            return []
        s = p.settings
        prior_sigma = np.tile(
            np.r_[np.full(3, s.bias_prior_accel), np.full(3, s.bias_prior_gyro)], p.nb // 6
        )
        walk = p.bias_walk * np.sqrt(p.h)
        out: list[tuple[int, int | None, np.ndarray, np.ndarray]] = [
            (0, None, bias[0], prior_sigma)
        ]
        for k in range(p.T - 1):
            out.append((k, k + 1, bias[k + 1] - bias[k], walk))
        return out

    def _bias_cost(self, bias: np.ndarray) -> dict[str, float]:
        rows = self._bias_rows(bias)
        if not rows:
            return {}
        return {"imu_bias": float(sum(0.5 * np.sum((r / s) ** 2) for _, _, r, s in rows))}

    def _add_bias_factors(
        self, graph: gtsam.GaussianFactorGraph, bias: np.ndarray, diag: np.ndarray
    ) -> None:
        p = self.problem
        nv, nb, nz = p.model.nv, p.nb, p.nz
        select = np.zeros((nb, nz))
        select[:, nv:] = np.eye(nb)
        for key_a, key_b, r, sigma in self._bias_rows(bias):
            A = select / sigma[:, None]
            unit = gtsam.noiseModel.Unit.Create(nb)
            if key_b is None:
                graph.add(gtsam.JacobianFactor(key_a, A, -r / sigma, unit))
            else:
                graph.add(gtsam.JacobianFactor(key_a, -A, key_b, A, -r / sigma, unit))
                diag[key_b, nv:] += 1.0 / sigma**2
            diag[key_a, nv:] += 1.0 / sigma**2

    def close(self) -> None:
        self.pool.shutdown()


def _expand(J: np.ndarray, nv: int, nz: int) -> np.ndarray:
    """Jacobian over (x_{k−1}, x_k, x_{k+1}) (rows, 3 nv) → over (z_{k−1}, z_k, z_{k+1})."""
    out = np.zeros((J.shape[0], 3 * nz))
    for i in range(3):
        out[:, i * nz : i * nz + nv] = J[:, i * nv : (i + 1) * nv]
    return out


def solve_window(
    problem: Problem, qpos: np.ndarray, bias: np.ndarray, covariance: bool = True
) -> WindowResult:
    """Levenberg–Marquardt on one window from (qpos (T, nq), bias (T, nb))."""
    lin = Linearizer(problem)
    try:
        p = problem
        cost, _ = lin.cost(qpos, bias)
        cost0 = cost
        lam = 1e-3
        converged = False
        it = 0
        for it in range(1, p.settings.max_iterations + 1):  # noqa: B007
            graph, diag = lin.linearize(qpos, bias)
            scale = diag + 1e-12 * max(float(diag.max()), 1.0)  # Marquardt: λ diag(JᵀJ)
            while True:
                try:
                    step = _damped_step(graph, scale, lam)
                except RuntimeError:  # too ill-conditioned at this λ: a rejected step
                    lam *= 10.0
                    if lam > 1e10:
                        cost_new = cost
                        break
                    continue
                dx = np.array([step.at(k) for k in range(p.T)])
                q_new = retract(p.model, qpos, dx[:, : p.model.nv])
                b_new = bias + dx[:, p.model.nv :]
                cost_new, _ = lin.cost(q_new, b_new)
                if cost_new < cost or lam > 1e10:
                    break
                lam *= 10.0
            if cost_new >= cost:
                converged = True  # no step lowers the cost: a (local) minimum
                break
            decrease = (cost - cost_new) / max(cost, 1e-300)
            qpos, bias, cost = q_new, b_new, cost_new
            lam = max(lam / 10.0, 1e-9)
            if decrease < 1e-6:
                converged = True
                break
        _, by_type = lin.cost(qpos, bias)
        std = np.full((p.T, p.model.nv), np.nan)
        warnings: list[str] = []
        if covariance:
            std = _marginal_std(lin, qpos, bias, warnings)
        return WindowResult(qpos, bias, std, it, converged, cost0, cost, by_type, warnings)
    finally:
        lin.close()


def _marginal_std(
    lin: Linearizer, qpos: np.ndarray, bias: np.ndarray, warnings: list[str]
) -> np.ndarray:
    """(T, nv) marginal standard deviations from GTSAM's Marginals at the solution.

    Contact directions make JᵀJ stiff (≈1e12) beside weakly observed ones, so the system is
    regularized by 1e-9·diag(JᵀJ), a prior far weaker than any measurement.
    """
    p = lin.problem
    std = np.full((p.T, p.model.nv), np.nan)
    graph, diag = lin.linearize(qpos, bias)
    damped = _with_damping(graph, diag + 1e-12 * max(float(diag.max()), 1.0), 1e-9)
    try:
        marginals = gtsam.Marginals(damped, damped.optimize())
        for k in range(p.T):
            cov = marginals.marginalCovariance(k)
            std[k] = np.sqrt(np.clip(np.diag(cov)[: p.model.nv], 0, None))
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else "ill-posed"
        warnings.append(f"covariances unavailable (GTSAM: {first}); qpos_std is NaN")
    return std


def _damped_step(
    graph: gtsam.GaussianFactorGraph, scale: np.ndarray, lam: float
) -> gtsam.VectorValues:
    """argmin ‖J dx + r‖² + λ Σ_k dx_kᵀ diag(scale_k) dx_k (Levenberg–Marquardt)."""
    return _with_damping(graph, scale, lam).optimize()


def _with_damping(
    graph: gtsam.GaussianFactorGraph, scale: np.ndarray, lam: float
) -> gtsam.GaussianFactorGraph:
    damped = graph.clone()
    T, nz = scale.shape
    unit = gtsam.noiseModel.Unit.Create(nz)
    for k in range(T):
        damped.add(gtsam.JacobianFactor(k, np.diag(np.sqrt(lam * scale[k])), np.zeros(nz), unit))
    return damped
