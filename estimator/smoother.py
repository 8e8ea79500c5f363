"""Smoothing a window of knots: Levenberg–Marquardt driven from Python.

Each iteration linearizes every interior knot (MuJoCo's mjd_inverseFD, threaded, the GIL
released), then whitens, robustly weights and chains the rows through the finite differences
for all knots at once (numpy, batched). Every factor sits on three consecutive keys
(z_{k−1}, z_k, z_{k+1}), so the normal equations JᵀJ are block-banded (bandwidth 2 keys): each
Levenberg–Marquardt trial is one banded Cholesky (LAPACK pbtrf through scipy), O(T). GTSAM
eliminates the same rows once per window, as JacobianFactors, for the marginal covariances.

Measured on the humanoid (27 dofs, 400 knots a window): GTSAM's elimination per trial cost
as much as the MuJoCo linearization itself (one JacobianFactor per knot built in Python, the
graph cloned per damping); the banded solve costs a tenth of it. Driving the loop from Python
also avoids GTSAM's CustomFactor path, which copies the whole Values on every callback
(../shared/DESIGN.md: 109× slower at 2000 variables).
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.linalg

from estimator.problem import (
    KnotModel,
    Problem,
    _RotationDofs,
    accelerations,
    difference_jacobians,
    quat_errors,
    retract,
    velocities,
)

THREADS = 2
SPAN = 3  # keys per factor: (z_{k−1}, z_k, z_{k+1})


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
    """One factor's whitened rows at every interior knot, robust weights applied.

    r: (K, m); J: (K, m, 3 nv) over (x_{k−1}, x_k, x_{k+1}) or None; J_bias: (K, m, nb) over
    b_k or None; cost: (K,) robust cost of the rows at each knot; valid: (K, m) rows that carry
    a factor (a measurement, a known force); the others are 0.
    """

    name: str
    r: np.ndarray
    J: np.ndarray | None
    cost: np.ndarray
    valid: np.ndarray
    J_bias: np.ndarray | None = None


def huber(norm: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's mEstimator.Huber, vectorized: loss ρ(n) (½n² within k, k(n − k/2) beyond) and
    weight w(n) = min(1, k/n), so that √w scales a block's rows."""
    inside = norm <= k
    loss = np.where(inside, 0.5 * norm**2, k * (norm - 0.5 * k))
    weight = np.where(inside, 1.0, k / np.where(inside, 1.0, norm))
    return loss, weight


class Linearizer:
    """Residuals and their Jacobians over all knots of a problem, vectorized across knots."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.knots = [KnotModel(problem, problem.settings.path) for _ in range(THREADS)]
        self.rotations = _RotationDofs.of(problem.model)
        rotation = {d + i for _, d in self.rotations.quat_dofs for i in range(3)}
        self.vector_dof = min(set(range(problem.model.nv)) - rotation, default=-1)
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
        F = np.zeros((3, n_jac, nv, nv))  # ∂u/∂(q, v, a), MuJoCo's transposed layout
        S = np.zeros((3, n_jac, nv, ns))  # ∂s/∂(q, v, a)

        def work(chunk: range, worker: KnotModel) -> None:
            for k in chunk:
                i = k - 1
                u[i], s[i] = worker.evaluate(qpos[k], v[k], a[k])
                if with_jacobians:
                    worker.jacobians(qpos[k], v[k], a[k], *F[:, i], *S[:, i])

        interior = range(1, p.T - 1)
        list(self.pool.map(work, [interior[i::THREADS] for i in range(THREADS)], self.knots))
        if not with_jacobians:
            return Terms(a[1:-1], u, s)
        # chain rule through v_k = (q_k ⊖ q_{k−1})/h and a_k = (v_{k+1} − v_k)/h
        d1, d2 = difference_jacobians(p.model, self.rotations, qpos[:-1], qpos[1:])
        dv = (d1[:-1] / h, d2[:-1] / h)  # ∂v_k/∂(x_{k−1}, x_k)
        da = (-d1[:-1] / h**2, (d1[1:] - d2[:-1]) / h**2, d2[1:] / h**2)  # ∂a_k/∂(x_{k−1…k+1})

        def chained(D: np.ndarray) -> np.ndarray:
            Dq, Dv, Da = (D[j].transpose(0, 2, 1) for j in range(3))
            times = self._times_difference
            return np.concatenate(
                [
                    times(Dv, dv[0]) + times(Da, da[0]),
                    Dq + times(Dv, dv[1]) + times(Da, da[1]),
                    times(Da, da[2]),
                ],
                axis=2,
            )

        return Terms(a[1:-1], u, s, chained(F), chained(S), np.concatenate(da, axis=2))

    def _times_difference(self, D: np.ndarray, M: np.ndarray) -> np.ndarray:
        """D @ M (K, m, nv) for M (K, nv, nv) = c I on vector dofs plus 3×3 rotation blocks
        (the difference Jacobians and their combinations): c D, rotation columns redone."""
        vector = self.vector_dof
        out = D * M[:, vector, vector][:, None, None] if vector >= 0 else np.zeros(D.shape)
        for _, dadr in self.rotations.quat_dofs:
            rot = slice(dadr, dadr + 3)
            out[:, :, rot] = D[:, :, rot] @ M[:, rot, rot]
        return out

    # -- whitened, robustly weighted rows of every factor --------------------------------------

    def blocks(self, t: Terms, bias: np.ndarray, robust: bool = True) -> list[Block]:
        """Physics, prior and sensor rows at every interior knot (one Block per factor; a pose
        stream has a position and a rotation block).

        robust=False leaves the rows unweighted (for reporting residuals)."""
        p = self.problem
        k_huber = p.settings.huber_k
        jac = t.Ju is not None
        K = p.T - 2
        out: list[Block] = []

        def weighted(block: Block, scale: np.ndarray | float = 1.0) -> Block:
            """Huber on the block's norm per knot; the threshold scales with `scale`."""
            norm = np.linalg.norm(block.r, axis=1) / scale
            loss, weight = huber(norm, k_huber)
            block.cost = loss * np.square(scale)
            if robust:
                root = np.sqrt(weight)
                block.r = block.r * root[:, None]
                for J in (block.J, block.J_bias):
                    if J is not None:
                        J *= root[:, None, None]
            return block

        # physics: W (u − u_known); rows with no known force are 0. Robust too, so that impacts
        # and unmodeled contacts do not bend the motion; the threshold scales with √(rows)
        # (a knot's norm over n consistent rows is ≈ √n)
        sigma = p.physics_sigma[1:-1]
        known = np.isfinite(sigma)
        w = np.where(known, 1.0 / np.where(known, sigma, 1.0), 0.0)
        r = np.nan_to_num((t.u - p.qfrc_known[1:-1]) * w)
        J = t.Ju * w[:, :, None] if t.Ju is not None else None
        physics = Block("physics", r, J, np.zeros(K), known)
        out.append(weighted(physics, np.sqrt(np.maximum(known.sum(axis=1), 1))))
        # smoothness prior: a_k / σ_a
        sa = p.settings.accel_prior_std
        r = t.a / sa
        J = t.da / sa if t.da is not None else None
        out.append(Block("prior", r, J, 0.5 * np.sum(r**2, axis=1), np.ones(r.shape, bool)))
        # sensors, robust
        for sensor in p.blocks:
            meas = sensor.values[1:-1]
            valid = np.all(np.isfinite(meas), axis=1)
            sig = sensor.sigma[1:-1] if sensor.sigma.ndim == 2 else np.tile(sensor.sigma, (K, 1))
            pred = t.s[:, sensor.rows]
            Js = t.Js[:, sensor.rows] if t.Js is not None else None
            J_bias = None
            if sensor.kind == "quat":
                e, de_dp = quat_errors(pred, np.where(valid[:, None], meas, pred))
                r = e / sig
                if Js is not None:
                    Js = np.einsum("kij,kjc->kic", de_dp, Js)
            else:
                b = bias[1:-1, sensor.bias] if sensor.bias is not None else 0.0
                r = (pred + b - np.where(valid[:, None], meas, 0.0)) / sig
                if jac and sensor.bias is not None:
                    J_bias = np.zeros((K, r.shape[1], p.nb))
                    rows = np.arange(r.shape[1])
                    J_bias[:, rows, sensor.bias.start + rows] = 1.0 / sig
            J = Js / sig[:, :, None] if Js is not None else None
            r[~valid] = 0.0
            for M in (J, J_bias):
                if M is not None:
                    M[~valid] = 0.0
            rows_valid = np.repeat(valid[:, None], r.shape[1], 1)
            out.append(weighted(Block(sensor.stream, r, J, np.zeros(K), rows_valid, J_bias)))
        return out

    def cost(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[float, dict[str, float]]:
        """Total robust cost and its split by factor type."""
        total: dict[str, float] = {}
        for b in self.blocks(self.terms(qpos, False), bias):
            total[b.name] = total.get(b.name, 0.0) + float(b.cost.sum())
        total.update(self._bias_cost(bias))
        return sum(total.values()), total

    def jacobian(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whitened, weighted rows of every knot: r (K, m) and J (K, m, 3 nz) over
        (z_{k−1}, z_k, z_{k+1}), z = (x, b)."""
        p = self.problem
        nv, nz = p.model.nv, p.nz
        blocks = self.blocks(self.terms(qpos, True), bias)
        r = np.concatenate([b.r for b in blocks], axis=1)
        J = np.zeros((p.T - 2, r.shape[1], SPAN * nz))
        row = 0
        for b in blocks:
            rows = slice(row, row + b.r.shape[1])
            assert b.J is not None
            for key in range(SPAN):
                J[:, rows, key * nz : key * nz + nv] = b.J[:, :, key * nv : (key + 1) * nv]
            if b.J_bias is not None:
                J[:, rows, nz + nv : 2 * nz] = b.J_bias
            row = rows.stop
        return r, J

    # -- IMU bias: prior on b_0 and random walk ------------------------------------------------

    def bias_rows(self, bias: np.ndarray) -> list[tuple[int, int | None, np.ndarray, np.ndarray]]:
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
        rows = self.bias_rows(bias)
        if not rows:
            return {}
        return {"imu_bias": float(sum(0.5 * np.sum((r / s) ** 2) for _, _, r, s in rows))}

    def close(self) -> None:
        self.pool.shutdown()


# ---------------------------------------------------------------------------------------------
# the normal equations, block-banded


@dataclass
class BandedSystem:
    """JᵀJ dx = −Jᵀr of a window, by blocks of keys: H_kk = diag[k] (T, nz, nz),
    H_{k+d, k} = lower[d − 1][k] for d = 1, 2; g = Jᵀr (T, nz)."""

    diag: np.ndarray
    lower: list[np.ndarray]
    g: np.ndarray

    @classmethod
    def of(cls, r: np.ndarray, J: np.ndarray, lin: Linearizer, bias: np.ndarray) -> BandedSystem:
        p = lin.problem
        T, nz, nv = p.T, p.nz, p.model.nv
        K = T - 2
        G = np.einsum("kmi,kmj->kij", J, J, optimize=True).reshape(K, SPAN, nz, SPAN, nz)
        gk = np.einsum("kmi,km->ki", J, r, optimize=True).reshape(K, SPAN, nz)
        diag = np.zeros((T, nz, nz))
        lower = [np.zeros((T - d, nz, nz)) for d in range(1, SPAN)]
        g = np.zeros((T, nz))
        for a in range(SPAN):  # knot k's factor adds to keys k−1+a, k−1+b
            g[a : a + K] += gk[:, a]
            diag[a : a + K] += G[:, a, :, a]
            for b in range(a):
                lower[a - b - 1][b : b + K] += G[:, a, :, b]
        if p.nb:  # bias prior on b_0, random walk (b_{k+1} − b_k)/(σ_walk √h)
            b_ = slice(nv, nz)
            s = p.settings
            prior = np.tile(
                np.r_[np.full(3, s.bias_prior_accel), np.full(3, s.bias_prior_gyro)], p.nb // 6
            )
            diag[0, b_, b_] += np.diag(prior**-2.0)
            g[0, b_] += bias[0] / prior**2
            W = np.diag((p.bias_walk * np.sqrt(p.h)) ** -2.0)
            step = (bias[1:] - bias[:-1]) @ W
            diag[:-1, b_, b_] += W
            diag[1:, b_, b_] += W
            lower[0][:, b_, b_] -= W
            g[:-1, b_] -= step
            g[1:, b_] += step
        return cls(diag, lower, g)

    def scaled_band(self) -> tuple[np.ndarray, np.ndarray]:
        """Marquardt scaling s = diag(H)^−½ and the lower band of S H S in LAPACK storage
        (ab[i − j, j] = (S H S)_ij), unit diagonal."""
        T, nz, _ = self.diag.shape
        d = np.einsum("kii->ki", self.diag).reshape(-1)
        s = 1.0 / np.sqrt(d + 1e-12 * max(float(d.max()), 1.0))
        S = s.reshape(T, nz)
        ab = np.zeros((SPAN * nz, T * nz))
        for offset, blocks in enumerate([self.diag, *self.lower]):
            n = len(blocks)
            scaled = S[offset : offset + n, :, None] * blocks * S[:n, None, :]
            band, col, keep = _band_indices(offset, n, nz)
            ab[band, col] = scaled.reshape(n, -1)[:, keep]
        return s, ab

    def damped_step(self, s: np.ndarray, ab: np.ndarray, lam: float) -> np.ndarray:
        """argmin ‖J dx + r‖² + λ Σ diag(JᵀJ) dx² → dx (T, nz); raises LinAlgError when the
        damped system is not positive definite."""
        damped = ab.copy()
        damped[0] += lam
        factor = scipy.linalg.cholesky_banded(damped, lower=True, check_finite=False)
        y = scipy.linalg.cho_solve_banded((factor, True), -s * self.g.reshape(-1))
        return (s * y).reshape(self.g.shape)


@functools.cache
def _band_indices(offset: int, n: int, nz: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the blocks H_{k+offset, k}, k < n, go in LAPACK lower band storage: row i − j and
    column j of each kept entry (i ≥ j), and which of a block's nz² entries are kept."""
    r, c = np.divmod(np.arange(nz * nz), nz)
    keep = offset * nz + r >= c
    band = np.broadcast_to(offset * nz + r[keep] - c[keep], (n, int(keep.sum())))
    col = np.arange(n)[:, None] * nz + c[keep][None, :]
    return band, col, keep


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
        r = J = None
        for it in range(1, p.settings.max_iterations + 1):  # noqa: B007
            r, J = lin.jacobian(qpos, bias)
            system = BandedSystem.of(r, J, lin, bias)
            s, ab = system.scaled_band()
            while True:
                try:
                    dx = system.damped_step(s, ab, lam)
                except np.linalg.LinAlgError:  # too ill-conditioned at this λ: a rejected step
                    lam *= 10.0
                    if lam > 1e10:
                        cost_new = cost
                        break
                    continue
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
        if covariance and r is not None and J is not None:
            # the last linearization: at the solution, or one step (< tolerance) before it
            std = _marginal_std(lin, r, J, bias, warnings)
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
    lin: Linearizer, r: np.ndarray, J: np.ndarray, bias: np.ndarray, warnings: list[str]
) -> np.ndarray:
    """(T, nv) marginal standard deviations from GTSAM's Marginals of the linearized rows.

    Contact directions make JᵀJ stiff (≈1e12) beside weakly observed ones, so the system is
    regularized by 1e-9·diag(JᵀJ), a prior far weaker than any measurement.
    """
    p = lin.problem
    T, nz, nv = p.T, p.nz, p.model.nv
    graph = gtsam.GaussianFactorGraph()
    unit = gtsam.noiseModel.Unit.Create(r.shape[1])
    for i in range(T - 2):
        blocks = [J[i, :, j * nz : (j + 1) * nz] for j in range(SPAN)]
        graph.add(
            gtsam.JacobianFactor(i, blocks[0], i + 1, blocks[1], i + 2, blocks[2], -r[i], unit)
        )
    select = np.zeros((p.nb, nz))
    select[:, nv:] = np.eye(p.nb)
    diag = np.zeros((T, nz))
    column_norms = np.sum(J**2, axis=1).reshape(T - 2, SPAN, nz)
    for j in range(SPAN):
        diag[j : T - 2 + j] += column_norms[:, j]
    for key_a, key_b, res, sigma in lin.bias_rows(bias):
        A = select / sigma[:, None]
        noise = gtsam.noiseModel.Unit.Create(p.nb)
        if key_b is None:
            graph.add(gtsam.JacobianFactor(key_a, A, -res / sigma, noise))
        else:
            graph.add(gtsam.JacobianFactor(key_a, -A, key_b, A, -res / sigma, noise))
            diag[key_b, nv:] += 1.0 / sigma**2
        diag[key_a, nv:] += 1.0 / sigma**2
    scale = diag + 1e-12 * max(float(diag.max()), 1.0)
    for k in range(T):  # the weak regularizer
        graph.add(
            gtsam.JacobianFactor(
                k, np.diag(np.sqrt(1e-9 * scale[k])), np.zeros(nz), gtsam.noiseModel.Unit.Create(nz)
            )
        )
    std = np.full((T, nv), np.nan)
    try:
        marginals = gtsam.Marginals(graph, graph.optimize())
        for k in range(T):
            cov = marginals.marginalCovariance(k)
            std[k] = np.sqrt(np.clip(np.diag(cov)[:nv], 0, None))
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else "ill-posed"
        warnings.append(f"covariances unavailable (GTSAM: {first}); qpos_std is NaN")
    return std
