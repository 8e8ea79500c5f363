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

import gtsam
import numpy as np

from estimator.problem import (
    KnotModel,
    Problem,
    accelerations,
    difference_jacobians,
    quat_errors,
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
    linearizations: int = 0  # MuJoCo passes with Jacobians (mjd_inverseFD at every knot)
    evaluations: int = 0  # passes without (mj_inverse at every knot)


@dataclass
class Terms:
    """Inverse dynamics and sensors at the interior knots k = 1 … T−2, stacked (row i ↔ knot
    i + 1). a, u: (K, nv); s: (K, ns). With Jacobians, derivatives with respect to
    (x_{k−1}, x_k, x_{k+1}): Ju (K, nv, 3 nv), Js (K, ns, 3 nv), da (K, nv, 3 nv)."""

    a: np.ndarray
    u: np.ndarray
    s: np.ndarray
    Ju: np.ndarray | None = None
    Js: np.ndarray | None = None
    da: np.ndarray | None = None


@dataclass
class Block:
    """One factor type's whitened rows at every interior knot, robust weights applied.

    r: (K, m); J: (K, m, 3 nz) or None; cost: (K,) robust cost of the rows at each knot;
    valid: (K, m) rows that carry a factor (a measurement, a known force); the others are 0.
    """

    name: str
    r: np.ndarray
    J: np.ndarray | None
    cost: np.ndarray
    valid: np.ndarray


class Linearizer:
    """Residuals and their Jacobians over all knots of a problem, vectorized across knots."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.knots = [KnotModel(problem, problem.settings.path) for _ in range(THREADS)]
        self.huber = gtsam.noiseModel.mEstimator.Huber.Create(problem.settings.huber_k)
        self.pool = ThreadPoolExecutor(THREADS)
        self.passes = {True: 0, False: 0}  # MuJoCo passes over all knots, with/without Jacobians

    # -- MuJoCo at every knot (threads; MuJoCo releases the GIL) ------------------------------

    def terms(self, qpos: np.ndarray, with_jacobians: bool) -> Terms:
        p = self.problem
        self.passes[with_jacobians] += 1
        nv, ns, h = p.model.nv, p.model.nsensordata, p.h
        v = velocities(p.model, qpos, h)
        a = accelerations(v, h)
        K = p.T - 2
        u, s = np.zeros((K, nv)), np.zeros((K, ns))
        n_jac = K if with_jacobians else 0
        Ju, Js, da = (np.zeros((n_jac, n, 3 * nv)) for n in (nv, ns, nv))
        zero = np.zeros((nv, nv))
        dq_dx = np.hstack([zero, np.eye(nv), zero])

        def work(chunk: range, worker: KnotModel) -> None:
            for k in chunk:
                i = k - 1
                u[i], s[i] = worker.evaluate(qpos[k], v[k], a[k])
                if not with_jacobians:
                    continue
                DfDq, DfDv, DfDa, DsDq, DsDv, DsDa = worker.jacobians(qpos[k], v[k], a[k])
                rot = worker.rotations
                d1_k, d2_k = difference_jacobians(p.model, rot, qpos[k - 1], qpos[k])
                d1_n, d2_n = difference_jacobians(p.model, rot, qpos[k], qpos[k + 1])
                # v_k = (q_k ⊖ q_{k−1})/h,  a_k = (v_{k+1} − v_k)/h
                dv_dx = np.hstack([d1_k, d2_k, zero]) / h
                da_dx = np.hstack([-d1_k, d1_n - d2_k, d2_n]) / h**2
                Ju[i] = DfDq @ dq_dx + DfDv @ dv_dx + DfDa @ da_dx
                Js[i] = DsDq @ dq_dx + DsDv @ dv_dx + DsDa @ da_dx
                da[i] = da_dx

        interior = range(1, p.T - 1)
        list(self.pool.map(work, [interior[i::THREADS] for i in range(THREADS)], self.knots))
        if with_jacobians:
            return Terms(a[1:-1], u, s, Ju, Js, da)
        return Terms(a[1:-1], u, s)

    # -- whitened, robustly weighted rows of every factor type --------------------------------

    def blocks(self, t: Terms, bias: np.ndarray, robust: bool = True) -> list[Block]:
        """Physics, prior and sensor rows at every interior knot (one Block per factor type).

        robust=False leaves the sensor rows unweighted (for reporting residuals)."""
        p = self.problem
        nv, nb, nz = p.model.nv, p.nb, p.nz
        if t.Ju is not None and t.Js is not None and t.da is not None:
            jac, Ju, Js_all, da = True, t.Ju, t.Js, t.da
        else:
            jac, Ju, Js_all, da = False, np.zeros(0), np.zeros(0), np.zeros(0)
        K = p.T - 2
        out: list[Block] = []

        # physics: W (u − u_known); rows with no known force are 0
        sigma = p.physics_sigma[1:-1]
        known = np.isfinite(sigma)
        w = np.where(known, 1.0 / np.where(known, sigma, 1.0), 0.0)
        r = np.nan_to_num((t.u - p.qfrc_known[1:-1]) * w)
        J = _expand(Ju * w[:, :, None], nv, nz) if jac else None
        # robust too, so that impacts and unmodeled contacts do not bend the motion; the
        # threshold scales with √(rows) (a knot's norm over n consistent rows is ≈ √n)
        scale = np.sqrt(np.maximum(known.sum(axis=1), 1))
        norm = np.linalg.norm(r, axis=1) / scale
        cost = np.array([self.huber.loss(n) for n in norm]) * scale**2
        if robust:
            root = np.sqrt([self.huber.weight(n) for n in norm])
            r = r * root[:, None]
            if J is not None:
                J *= root[:, None, None]
        out.append(Block("physics", r, J, cost, known))
        # smoothness prior: a_k / σ_a
        sa = p.settings.accel_prior_std
        r = t.a / sa
        J = _expand(da / sa, nv, nz) if jac else None
        out.append(Block("prior", r, J, 0.5 * np.sum(r**2, axis=1), np.ones(r.shape, bool)))
        # sensors, robust
        b_k = bias[1:-1]
        for block in p.blocks:
            meas = block.values[1:-1]
            valid = np.all(np.isfinite(meas), axis=1)
            sig = block.sigma[1:-1] if block.sigma.ndim == 2 else np.tile(block.sigma, (K, 1))
            pred = t.s[:, block.rows]
            Js = Js_all[:, block.rows] if jac else Js_all
            if block.kind == "quat":
                e, de_dp = quat_errors(pred, np.where(valid[:, None], meas, pred))
                r = e / sig
                J = (
                    _expand(np.einsum("kij,kjc->kic", de_dp, Js) / sig[:, :, None], nv, nz)
                    if jac
                    else None
                )
            else:
                b = b_k[:, block.bias] if block.bias is not None else np.zeros(1)
                r = (pred + b - np.where(valid[:, None], meas, 0.0)) / sig
                J = _expand(Js / sig[:, :, None], nv, nz) if jac else None
                if J is not None and block.bias is not None:
                    cols = 2 * nz - nb + np.arange(block.bias.start, block.bias.stop)
                    J[:, np.arange(r.shape[1]), cols] += 1.0 / sig
            r[~valid] = 0.0
            if J is not None:
                J[~valid] = 0.0
            norm = np.linalg.norm(r, axis=1)
            cost = np.array([self.huber.loss(n) for n in norm])
            if robust:
                root = np.sqrt([self.huber.weight(n) for n in norm])
                r = r * root[:, None]
                if J is not None:
                    J *= root[:, None, None]
            out.append(Block(block.stream, r, J, cost, np.repeat(valid[:, None], r.shape[1], 1)))
        return _merge_by_name(out)

    def cost(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[float, dict[str, float]]:
        """Total robust cost and its split by factor type."""
        total = {b.name: float(b.cost.sum()) for b in self.blocks(self.terms(qpos, False), bias)}
        total.update(self._bias_cost(bias))
        return sum(total.values()), total

    def linearize(
        self, qpos: np.ndarray, bias: np.ndarray
    ) -> tuple[gtsam.GaussianFactorGraph, np.ndarray]:
        """The whitened linear system at (qpos, bias) and diag(JᵀJ) per key, (T, nz)."""
        p = self.problem
        nz = p.nz
        blocks = self.blocks(self.terms(qpos, True), bias)
        R = np.concatenate([b.r for b in blocks], axis=1)  # (K, m)
        J = np.concatenate([b.J for b in blocks if b.J is not None], axis=1)
        graph = gtsam.GaussianFactorGraph()
        unit = gtsam.noiseModel.Unit.Create(R.shape[1])
        for i in range(p.T - 2):
            k = i + 1
            graph.add(
                gtsam.JacobianFactor(
                    k - 1,
                    J[i, :, :nz],
                    k,
                    J[i, :, nz : 2 * nz],
                    k + 1,
                    J[i, :, 2 * nz :],
                    -R[i],
                    unit,
                )
            )
        diag = np.zeros((p.T, nz))
        column_norms = np.sum(J**2, axis=1).reshape(p.T - 2, 3, nz)
        for j in range(3):
            diag[j : p.T - 2 + j] += column_norms[:, j]
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
    """Jacobians over (x_{k−1}, x_k, x_{k+1}) (K, m, 3 nv) → over (z_{k−1}, z_k, z_{k+1})."""
    out = np.zeros((*J.shape[:2], 3 * nz))
    for i in range(3):
        out[:, :, i * nz : i * nz + nv] = J[:, :, i * nv : (i + 1) * nv]
    return out


def _merge_by_name(blocks: list[Block]) -> list[Block]:
    """One Block per factor type (a stream's position and rotation blocks together)."""
    merged: dict[str, list[Block]] = {}
    for b in blocks:
        merged.setdefault(b.name, []).append(b)
    out = []
    for name, parts in merged.items():
        r = np.concatenate([b.r for b in parts], axis=1)
        jacobians = [b.J for b in parts if b.J is not None]
        J = np.concatenate(jacobians, axis=1) if jacobians else None
        valid = np.concatenate([b.valid for b in parts], axis=1)
        cost = np.sum([b.cost for b in parts], axis=0)
        out.append(Block(name, r, J, cost, valid))
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
            if decrease < p.settings.tolerance:
                converged = True
                break
        _, by_type = lin.cost(qpos, bias)
        std = np.full((p.T, p.model.nv), np.nan)
        warnings: list[str] = []
        if covariance:
            std = _marginal_std(lin, qpos, bias, warnings)
        return WindowResult(
            qpos,
            bias,
            std,
            it,
            converged,
            cost0,
            cost,
            by_type,
            warnings,
            lin.passes[True],
            lin.passes[False],
        )
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
