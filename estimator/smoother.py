"""Smoothing a window of knots: Levenberg–Marquardt driven from Python.

Each iteration linearizes every interior knot (MuJoCo's mjd_inverseFD, threaded, the GIL
released), then whitens, robustly weights and chains the rows through the finite differences
for all knots at once (numpy, batched). Every factor sits on three consecutive keys
(z_{k−1}, z_k, z_{k+1}), the constant-acceleration prior on four (dof to dof), so the normal
equations JᵀJ are block-banded (bandwidth 2 or 3 keys), summed straight into key blocks over
the columns each factor reaches: each Levenberg–Marquardt trial is one banded Cholesky
(LAPACK pbtrf through scipy), O(T). GTSAM eliminates the same system once per window, as
HessianFactors, for the marginal covariances.

Measured on the humanoid (27 dofs, 400 knots a window): GTSAM's elimination per trial cost
as much as the MuJoCo linearization itself (one JacobianFactor per knot built in Python, the
graph cloned per damping); the banded solve costs a tenth of it. Driving the loop from Python
also avoids GTSAM's CustomFactor path, which copies the whole Values on every callback
(../shared/DESIGN.md: 109× slower at 2000 variables).
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np
import scipy.linalg

from estimator.factors import bias_walk, measurement, motion, physics
from estimator.factors.base import Block, Terms
from estimator.problem import (
    Problem,
    RotationDofs,
    accelerations,
    difference_jacobians,
    retract,
    velocities,
)
from physics.knots import KnotBatch, KnotEngine, chunks
from physics.softness import scale as scale_softness

# MuJoCo threads of one estimate (a fleet task runs on its one CPU: 1)
THREADS = int(os.environ.get("PHYSFUSE_THREADS") or 2)
LAMBDA_MIN = 1e-9  # Levenberg–Marquardt's least damping, and its first
LAMBDA_REJECTED = 1e-5  # the least damping after a rejected step
MARGINAL_REGULARIZER = 1e-14  # on the unit diagonal of S H S (`BandedSystem.marginal_std`)


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
    next_prior: MarginalPrior | None = None  # for the window that starts at `marginalize`


@dataclass(frozen=True)
class MarginalPrior:
    """What the knots before a window said about its first n keys, the others marginalized
    (a Schur complement of their normal equations): ½ (δ − δ̂)ᵀ Λ (δ − δ̂), δ = (q_k ⊖ q̄_k,
    b_k − b̄_k) stacked over keys 0 … n − 1 (n = span − 1: every key the next rows share).

    qpos (n, nq), bias (n, nb): its linearization point q̄, b̄ (the previous window's
    solution); info Λ (n nz, n nz); mean δ̂ (n nz): where the marginal puts those keys.
    gain: (m nz, n nz) −H_ee⁻¹ H_er, how the m marginalized keys before follow when the next
    window moves these keys (the smoother's backward pass, linearized: `follow`).
    """

    qpos: np.ndarray
    bias: np.ndarray
    info: np.ndarray
    mean: np.ndarray
    gain: np.ndarray

    @property
    def keys(self) -> int:
        return len(self.qpos)

    def error(self, model: mujoco.MjModel, qpos: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """δ − δ̂ (n nz) at the window's first n keys of (qpos, bias)."""
        delta = []
        for k in range(self.keys):
            dq = np.zeros(model.nv)
            mujoco.mj_differentiatePos(model, dq, 1.0, self.qpos[k], qpos[k])  # q ⊖ q̄
            delta.append(np.r_[dq, bias[k] - self.bias[k]])
        return np.concatenate(delta) - self.mean

    def cost(self, model: mujoco.MjModel, qpos: np.ndarray, bias: np.ndarray) -> float:
        e = self.error(model, qpos, bias)
        return 0.5 * float(e @ self.info @ e)


class Linearizer:
    """Residuals and their Jacobians over all knots of a problem, vectorized across knots."""

    def __init__(self, problem: Problem, prior: MarginalPrior | None = None) -> None:
        self.problem = problem
        self.prior = prior  # on the first keys, from the knots before the window
        # the engine at the knots, one MjData per thread (`physics.knots`)
        self.engines = KnotBatch(
            problem.model, THREADS, problem.settings.path, problem.settings.fd_eps
        )
        self.pool = self.engines.pool  # the same threads run the numpy products
        self.rotations = RotationDofs.of(problem.model)
        self.rotation_dofs = [d for _, d in self.rotations.quat_dofs]  # first of each 3
        rotation = {d + i for d in self.rotation_dofs for i in range(3)}
        self.vector_dofs = np.array(sorted(set(range(problem.model.nv)) - rotation), dtype=int)
        # the columns of each dof's group (nv, 3), where group_mask (a vector dof: its own)
        self.group_cols = np.tile(np.arange(problem.model.nv)[:, None], (1, 3))
        self.group_mask = np.zeros((problem.model.nv, 3), bool)
        self.group_mask[:, 0] = True
        for d in self.rotation_dofs:
            self.group_cols[d : d + 3] = d + np.arange(3)
            self.group_mask[d : d + 3] = True
        self.span = 4 if problem.settings.jerk_prior_std > 0 else 3  # keys a knot's rows reach
        self.passes = {True: 0, False: 0}  # MuJoCo passes over all knots, with/without Jacobians

    # -- MuJoCo at every knot (threads; MuJoCo releases the GIL) ------------------------------

    def terms(self, qpos: np.ndarray, with_jacobians: bool) -> Terms:
        p = self.problem
        self.passes[with_jacobians] += 1
        nv, ns, h = p.model.nv, p.model.nsensordata, p.h
        v = velocities(p.model, qpos, h)
        a = accelerations(v, h)
        K = p.T - 2
        u, known, s = np.zeros((K, nv)), np.zeros((K, nv)), np.zeros((K, ns))
        n_jac = K if with_jacobians else 0
        F = np.zeros((3, n_jac, nv, nv))  # ∂u/∂(q, v, a), MuJoCo's transposed layout
        S = np.zeros((3, n_jac, nv, ns))  # ∂s/∂(q, v, a)
        JuT = np.empty((n_jac, 3 * nv, nv))  # the chained Jacobians, transposed
        JsT = np.empty((n_jac, 3 * nv, ns))
        if with_jacobians:
            # chain rule through v_k = (q_k ⊖ q_{k−1})/h and a_k = (v_{k+1} − v_k)/h:
            # ∂v_k/∂(x_{k−1}, x_k) = (d1_k, d2_k)/h, ∂a_k/∂(x_{k−1}, x_k, x_{k+1}) =
            # (−d1_k, d1_{k+1} − d2_k, d2_{k+1})/h², with d1, d2 of the pair (q_{k−1}, q_k)
            d1, d2 = difference_jacobians(p.model, self.rotations, qpos[:-1], qpos[1:])

        def chained(D: np.ndarray, i: slice, out: np.ndarray) -> None:
            """out = [d1_kᵀ P,  D_q + d2_kᵀ P + d1_{k+1}ᵀ Q,  d2_{k+1}ᵀ Q] over (x_{k−1}, x_k,
            x_{k+1}), P = D_v/h − D_a/h², Q = D_a/h², computed transposed in MuJoCo's layout
            D (3, n, nv, m), where every product is contiguous. On vector dofs d1 = −1 and
            d2 = 1: [−P, D_q + P − Q, Q]; the rotations' rows are redone by their blocks."""
            Q = D[2] * h**-2
            P = D[1] * (1.0 / h)
            P -= Q
            x0, x1, x2 = out[:, :nv], out[:, nv : 2 * nv], out[:, 2 * nv :]
            np.negative(P, out=x0)
            np.subtract(P, Q, out=x1)
            x1 += D[0]
            x2[...] = Q
            for d in self.rotation_dofs:
                rot = slice(d, d + 3)

                def times(dk: np.ndarray, M: np.ndarray, rot: slice = rot) -> np.ndarray:
                    return dk[i, rot].transpose(0, 2, 1) @ M[:, rot]  # dᵀ M on the 3 rows

                x0[:, rot] = times(d1[:-1], P)
                x1[:, rot] = D[0][:, rot] + times(d2[:-1], P) + times(d1[1:], Q)
                x2[:, rot] = times(d2[1:], Q)

        def work(engine: KnotEngine, chunk: range) -> None:
            for k in chunk:
                i = k - 1
                u[i], s[i] = engine.inverse(qpos[k], v[k], a[k])
                known[i], known_dq, known_dv = p.u_known(engine.data, k, with_jacobians)
                if with_jacobians:
                    engine.derivatives(qpos[k], v[k], a[k], *F[:, i], *S[:, i])
                    if known_dq is not None and known_dv is not None:  # of u − u_known
                        F[0, i] -= known_dq.T
                        F[1, i] -= known_dv.T
            if with_jacobians:  # numpy releases the GIL: the chain rule runs in parallel too
                rows = slice(chunk.start - 1, chunk.stop - 1)
                chained(F[:, rows], rows, JuT[rows])
                chained(S[:, rows], rows, JsT[rows])

        self.engines.map(work, 1, p.T - 1)
        if not with_jacobians:
            return Terms(a[1:-1], u, known, s)
        da = np.stack([-d1[:-1], d1[1:] - d2[:-1], d2[1:]], axis=1) / h**2
        return Terms(a[1:-1], u, known, s, JuT.transpose(0, 2, 1), JsT.transpose(0, 2, 1), da)

    def dense(self, C: np.ndarray) -> np.ndarray:
        """A dofwise Jacobian (K, keys, nv, 3) by key and dof group as (K, nv, keys·nv)."""
        K, keys, nv, _ = C.shape
        d, j = np.nonzero(self.group_mask)
        out = np.zeros((K, nv, keys * nv))
        for a in range(keys):
            out[:, d, a * nv + self.group_cols[d, j]] = C[:, a, d, j]
        return out

    # -- whitened, robustly weighted rows of every factor --------------------------------------

    def blocks(self, t: Terms, bias: np.ndarray, robust: bool = True) -> list[Block]:
        """Every factor's whitened, robustly weighted rows at every interior knot, one Block
        per factor (`estimator.factors`: physics, the motion priors, each sensor block).

        robust=False leaves the rows unweighted (for reporting residuals)."""
        p = self.problem
        out = [physics.rows(p, t, bias, robust), motion.acceleration_prior(p, t)]
        if self.span == 4:
            out.append(motion.jerk_prior(p, t, robust))
        out += [measurement.rows(p, t, bias, sensor, robust) for sensor in p.blocks]
        return out

    def cost(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[float, dict[str, float]]:
        """Total robust cost and its split by factor type."""
        total: dict[str, float] = {}
        for b in self.blocks(self.terms(qpos, False), bias):
            total[b.name] = total.get(b.name, 0.0) + float(b.cost.sum())
        total.update(self.bias_cost(bias))
        if self.prior is not None:
            total["marginal prior"] = self.prior.cost(self.problem.model, qpos, bias)
        return sum(total.values()), total

    def linearize(self, qpos: np.ndarray, bias: np.ndarray) -> list[Block]:
        """Every factor's whitened, weighted rows at every knot, with their Jacobians."""
        return self.blocks(self.terms(qpos, True), bias)

    def jacobian(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The same rows dense: r (K, m) and J (K, m, span·nz) over (z_{k−1}, z_k, z_{k+1}[,
        z_{k+2}]), z = (x, b) (for checks; the solve uses the blocks)."""
        p = self.problem
        nz = p.nz
        blocks = self.linearize(qpos, bias)
        r = np.concatenate([b.r for b in blocks], axis=1)
        J = np.zeros((p.T - 2, r.shape[1], self.span * nz))
        row = 0
        for b in blocks:
            rows = slice(row, row + b.r.shape[1])
            if b.dofwise and b.J is not None:
                b = Block(b.name, b.r, self.dense(b.J), b.cost, b.valid)
            J_z, cols = z_columns(p, b)
            J[:, rows, cols] = J_z
            row = rows.stop
        return r, J

    # -- sensor biases (IMU, force/torque): prior on b_0 and random walk ---------------------

    def bias_rows(self, bias: np.ndarray) -> list[tuple[int, int | None, np.ndarray, np.ndarray]]:
        """The bias prior's and walk's rows (for the dense checks; `bias_walk`)."""
        return bias_walk.rows(self.problem, bias) if self.problem.nb else []

    def bias_cost(self, bias: np.ndarray) -> dict[str, float]:
        """{"bias": cost of the bias prior (unless a marginal prior holds b_0) and random walk}
        ({} without biased sensors)."""
        if not self.problem.nb:
            return {}
        return {"bias": bias_walk.cost(self.problem, bias, with_prior=self.prior is None)}

    def close(self) -> None:
        self.engines.close()


# ---------------------------------------------------------------------------------------------
def z_columns(problem: Problem, block: Block) -> tuple[np.ndarray, np.ndarray]:
    """A block's Jacobian on the columns of (z_{k−1}, z_k, …) its rows reach (nonzero at some
    knot; a mocap row reaches a few of x_k's): (K, m, n) and their n column indices (x of key
    a: a·nz + dof; the bias b_k: nz + nv + i)."""
    nv, nz = problem.model.nv, problem.nz
    assert block.J is not None
    x_cols = np.arange(block.J.shape[2])
    x_cols = x_cols // nv * nz + x_cols % nv
    reach = np.flatnonzero(np.any(block.J, axis=(0, 1)))
    J = block.J if len(reach) == len(x_cols) else block.J[:, :, reach]
    cols = x_cols[reach]
    if block.J_bias is not None:
        J = np.concatenate([J, block.J_bias], axis=2)
        cols = np.r_[cols, nz + nv + np.arange(problem.nb)]
    return J, cols


def _dot(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """Σ aᵢ·bᵢ over blocks of rows."""
    return float(sum(np.sum(x * y) for x, y in zip(a, b, strict=True)))


# the normal equations, block-banded


@dataclass
class BandedSystem:
    """JᵀJ dx = −Jᵀr of a window, by blocks of keys: H_kk = diag[k] (T, nz, nz),
    H_{k+d, k} = lower[d − 1][k] for d = 1 … span − 1; g = Jᵀr (T, nz)."""

    diag: np.ndarray
    lower: list[np.ndarray]
    g: np.ndarray

    @classmethod
    def of(
        cls,
        blocks: list[Block],
        lin: Linearizer,
        bias: np.ndarray,
        qpos: np.ndarray | None = None,
        until: int | None = None,
    ) -> BandedSystem:
        """The system of `lin.linearize`'s blocks (and the bias prior and walk, and the
        marginal prior at qpos). until: only the factors on keys ≤ until — the rows of knots
        k ≤ until − span + 2 and the walk steps to keys ≤ until — what a window's past says
        before its keys ≤ until are marginalized (`marginal_prior`)."""
        p = lin.problem
        if until is not None:
            last_row = until - lin.span + 2  # knot of the last row kept: it reaches key `until`
            keep = (np.arange(p.T - 2) + 1 <= last_row)[:, None]
            blocks = [
                replace(
                    b,
                    r=b.r * keep,
                    J=None if b.J is None else b.J * keep.reshape(-1, *[1] * (b.J.ndim - 1)),
                    J_bias=None if b.J_bias is None else b.J_bias * keep[:, :, None],
                )
                for b in blocks
            ]
        T, nz, span = p.T, p.nz, lin.span
        K = T - 2
        # Knot row i (knot k = i + 1) reaches keys i + a, a = 0 … span − 1. Each factor's
        # Jacobian is split by key into runs of consecutive columns, (a, columns in J,
        # columns in z_{i+a}) (slices: fancy indexing is 5× slower). The sensors' blocks, a
        # few rows each, are stacked into one over the union of their columns.
        dofwise = [(b.r, b.J) for b in blocks if b.dofwise and b.J is not None]
        groups = [[b] for b in blocks if not (b.dofwise or b.sensor)]
        groups.append([b for b in blocks if b.sensor])
        parts = []  # (r, [(J, its columns in the union)], number of columns, runs)
        for group in groups:
            reach = [z_columns(p, b) for b in group]
            if len(reach) == 1:  # its own columns, in their order
                cols = reach[0][1]
            else:
                cols = np.unique(np.concatenate([c for _, c in reach] or [np.zeros(0, int)]))
            if not len(cols):  # (rows with no measurement in this window)
                continue
            starts = np.flatnonzero((np.diff(cols, prepend=-2) != 1) | (cols % nz == 0))
            runs = [
                (cols[i] // nz, slice(i, j), slice(cols[i] % nz, cols[i] % nz + j - i))
                for i, j in zip(starts, [*starts[1:], len(cols)], strict=True)
            ]
            r = np.concatenate([b.r for b in group], axis=1)
            parts.append((r, [(J, np.searchsorted(cols, c)) for J, c in reach], len(cols), runs))
        # the priors' rows reach one dof (or one rotation's 3) per key: JᵀJ by dof groups
        vec = lin.vector_dofs

        def products(c: range) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
            """This chunk of knots' share of (diag, lower, g), in its own arrays (threads)."""
            diag = np.zeros((T, nz, nz))
            lower = [np.zeros((T - d, nz, nz)) for d in range(1, span)]
            g = np.zeros((T, nz))
            H = [diag, *lower]  # H[a − b][key of b]: H_{k+a−b, k}
            i0, i1 = c.start, c.stop
            for r, reach, n_cols, runs in parts:
                rc = r[i0:i1]
                if len(reach) == 1:
                    Jc = reach[0][0][i0:i1]
                else:
                    Jc = np.zeros((i1 - i0, r.shape[1], n_cols))
                    row = 0
                    for J, at in reach:
                        Jc[:, row : row + J.shape[1], at] = J[i0:i1]
                        row += J.shape[1]
                for a, in_a, z_a in runs:
                    Ja = Jc[:, :, in_a]
                    g[i0 + a : i1 + a, z_a] += np.einsum("kmc,km->kc", Ja, rc)
                    for b, in_b, z_b in runs:
                        if b <= a:
                            H[a - b][i0 + b : i1 + b, z_a, z_b] += (
                                Ja.transpose(0, 2, 1) @ Jc[:, :, in_b]
                            )
            for r, C in dofwise:
                n = C.shape[1]  # keys reached (the prior 3, the jerk prior 4)
                # rows reaching key i + a ≤ T − 1 (the jerk prior's last row, zero, reaches T)
                rows = [slice(i0, min(i1, T - a)) for a in range(n)]
                Jv = [C[rows[a], a, vec, 0] for a in range(n)]  # (knots, vector dofs)
                for a in range(n):
                    m = rows[a].stop - i0
                    g[i0 + a : i0 + a + m, vec] += Jv[a] * r[rows[a], vec]
                    for b in range(a + 1):
                        diagonal = H[a - b].reshape(-1, nz * nz)[:, :: nz + 1]  # a view
                        diagonal[i0 + b : i0 + b + m, vec] += Jv[a] * Jv[b][:m]
                for d in lin.rotation_dofs:  # the 3 rows of a rotation on its 3 columns
                    rot = slice(d, d + 3)
                    Jr = [C[rows[a], a, rot] for a in range(n)]  # (knots, 3, 3)
                    for a in range(n):
                        m = rows[a].stop - i0
                        JrT = Jr[a].transpose(0, 2, 1)
                        g[i0 + a : i0 + a + m, rot] += (JrT @ r[rows[a], rot, None])[:, :, 0]
                        for b in range(a + 1):
                            H[a - b][i0 + b : i0 + b + m, rot, rot] += JrT @ Jr[b][:m]
            return diag, lower, g

        shares = list(lin.pool.map(products, chunks(0, K, THREADS)))
        diag, lower, g = shares[0]
        for more_diag, more_lower, more_g in shares[1:]:
            diag += more_diag
            g += more_g
            for mine, more in zip(lower, more_lower, strict=True):
                mine += more
        if p.nb:  # (a marginal prior holds b_0 already) the steps k → k + 1 to keys ≤ the
            # last kept row's knot, with `until`
            n = T - 1 if until is None else min(T - 1, until - lin.span + 2)
            bias_walk.add_normal_equations(p, bias, diag, lower[0], g, lin.prior is None, n)
        if lin.prior is not None:  # ½ eᵀΛe on the first keys: H += Λ, g += Λe
            assert qpos is not None, "a marginal prior needs the window's qpos"
            prior = lin.prior
            Lam = prior.info.reshape(prior.keys, nz, prior.keys, nz)
            Le = (prior.info @ prior.error(p.model, qpos, bias)).reshape(prior.keys, nz)
            for i in range(prior.keys):
                g[i] += Le[i]
                diag[i] += Lam[i, :, i]
                for j in range(i):
                    lower[i - j - 1][j] += Lam[i, :, j]
        return cls(diag, lower, g)

    def marginal_std(self, nv: int, warnings: list[str], keys: range | None = None) -> np.ndarray:
        """(T, nv) marginal standard deviations of x_k at `keys` (default: all; NaN at the
        others): the diagonal of H⁻¹ = S (S H S)⁻¹ S (S = diag(H)^−½) by a banded Cholesky
        of the scaled system and the selected inverse of its band (`banded_inverse_blocks`).

        Contact directions make JᵀJ stiff (≈1e12–1e17) beside weakly observed ones (1e6), and
        S H S has eigenvalues far below 1: an accelerometer at every knot puts ≈4e14 on the
        diagonal where the mocap knows the position as a whole to ≈1e6 (an eigenvalue ≈2e-9);
        a free object's tilt in a gripper at h = 0.5 ms reaches ≈5e-12. GTSAM's Marginals
        declared that system indeterminate below a regularizer of 1e-8 on the unit diagonal,
        which halved the position σ of every floating base. MARGINAL_REGULARIZER only keeps
        the directions nothing observes finite (there σ comes out huge, as it should)."""
        T, nz, _ = self.diag.shape
        std = np.full((T, nv), np.nan)
        s, ab = self.scaled_band()
        ab = ab.copy(order="F")
        ab[0] += MARGINAL_REGULARIZER
        try:
            L = scipy.linalg.cholesky_banded(ab, overwrite_ab=True, lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            warnings.append(f"covariances unavailable ({err}); qpos_std is NaN")
            return std
        first = 0 if keys is None or len(keys) == 0 else keys.start
        Z = banded_inverse_blocks(L, nz, first)
        variance = np.einsum("kii->ki", Z)[:, :nv] * s.reshape(T, nz)[first:, :nv] ** 2
        chosen = np.arange(first, T) if keys is None else np.asarray(keys, dtype=int)
        std[chosen] = np.sqrt(np.clip(variance[chosen - first], 0.0, None))
        return std

    def scaled_band(self) -> tuple[np.ndarray, np.ndarray]:
        """Marquardt scaling s = diag(H)^−½ and the lower band of S H S in LAPACK storage
        (ab[i − j, j] = (S H S)_ij), unit diagonal.

        The band is as wide as the farthest coupling: keys span − 1 apart couple only through
        the jerk prior, dof to dof (a rotation's 3 to its 3), so its rows end there: 3 nz + 3
        rows instead of 4 nz (the banded Cholesky's cost goes with the band's square)."""
        T, nz, _ = self.diag.shape
        d = np.einsum("kii->ki", self.diag).reshape(-1)
        s = 1.0 / np.sqrt(d + 1e-12 * max(float(d.max()), 1.0))
        S = s.reshape(T, nz)
        span = len(self.lower) + 1
        rows, cols = np.nonzero(np.any(self.lower[-1] != 0, axis=0))
        kd = (span - 1) * nz + int(np.max(rows - cols, initial=-1))  # the farthest nonzero
        # LAPACK's ab[i − j, j] = H_ij: key k's column c holds H_{k+o, k}[r, c] at
        # i − j = o nz + r − c, written through a skewed view of M[k, c, nz + (i − j)] (the
        # padding nz on each side takes the diagonal block's upper half and the zeros past kd)
        M = np.zeros((T, nz, nz + kd + 1 + nz))
        st = M.strides
        for offset, blocks in enumerate([self.diag, *self.lower]):
            n = len(blocks)
            skewed = np.lib.stride_tricks.as_strided(
                M[:n, :, (offset + 1) * nz :],
                shape=(n, nz, nz),
                strides=(st[0], st[1] - st[2], st[2]),
            )  # skewed[k, c, r] = M[k, c, nz + offset·nz + r − c]
            skewed[...] = (S[offset : offset + n, :, None] * blocks * S[:n, None, :]).transpose(
                0, 2, 1
            )
        # in Fortran order, as LAPACK reads it (scipy would copy it otherwise)
        ab = M[:, :, nz : nz + kd + 1].reshape(T * nz, kd + 1).T
        return s, ab

    def predicted_decrease(self, s: np.ndarray, lam: float, dx: np.ndarray) -> float:
        """The quadratic model's cost decrease −gᵀdx − ½dxᵀH dx at the damped step dx, which
        solves (H + λD) dx = −g with D = s⁻²: ½(−gᵀdx + λ dxᵀD dx)."""
        d = dx.reshape(-1)
        return 0.5 * float(-self.g.reshape(-1) @ d + lam * np.sum(np.square(d / s)))

    def damped_step(self, s: np.ndarray, ab: np.ndarray, lam: float) -> np.ndarray:
        """argmin ‖J dx + r‖² + λ Σ diag(JᵀJ) dx² → dx (T, nz); raises LinAlgError when the
        damped system is not positive definite."""
        damped = ab.copy(order="F")
        damped[0] += lam
        factor = scipy.linalg.cholesky_banded(
            damped, overwrite_ab=True, lower=True, check_finite=False
        )
        y = scipy.linalg.cho_solve_banded((factor, True), -s * self.g.reshape(-1))
        return (s * y).reshape(self.g.shape)


def banded_inverse_blocks(L: np.ndarray, nz: int, first: int = 0) -> np.ndarray:
    """The diagonal blocks Z_kk (T − first, nz, nz) of A⁻¹ for A = L Lᵀ, L lower banded in
    LAPACK storage (L[d, j] = L_{j+d, j}), keys of nz unknowns, without forming A⁻¹: the
    selected inversion (Takahashi's recurrence) from Lᵀ Z = L⁻¹, key k from the last down,

        Z_{k, k+1:k+m} = −L_kk⁻ᵀ B_kᵀ Z_{k+1:k+m, k+1:k+m},
        Z_kk = L_kk⁻ᵀ (L_kk⁻¹ − B_kᵀ Z_{k, k+1:k+m}ᵀ),

    with B_k the rows of L below L_kk in key k's columns and m keys its band reaches; Z is
    needed only within the band, held as a rolling window of m + 1 keys."""
    kd, N = L.shape[0] - 1, L.shape[1]
    T = N // nz
    m = -(-kd // nz)  # keys below the diagonal block a column reaches
    w = (m + 1) * nz
    # C[k, t, c] = L[k nz + t, k nz + c]: key k's columns, rows k nz … k nz + w − 1
    t, c = np.arange(w)[:, None], np.arange(nz)[None, :]
    d = t - c
    inside = (d >= 0) & (d <= kd)
    cols = np.arange(T)[:, None, None] * nz + c[None]
    rows = cols + d[None]
    C = np.where(
        inside[None] & (rows < N), L[np.clip(d, 0, kd)[None], np.minimum(cols, N - 1)], 0.0
    )
    out = np.empty((T - first, nz, nz))
    W = np.zeros((w, w))  # Z over keys k … k + m (rows beyond the last key stay 0)
    for k in range(T - 1, first - 1, -1):
        Lkk, B = C[k, :nz], C[k, nz:]
        sub = W[: w - nz, : w - nz]  # keys k + 1 … k + m, the previous window's first m
        X = scipy.linalg.solve_triangular(Lkk, B.T @ sub, lower=True, trans="T")
        inv_Lkk = scipy.linalg.solve_triangular(Lkk, np.eye(nz), lower=True)
        Zkk = scipy.linalg.solve_triangular(Lkk, inv_Lkk + B.T @ X.T, lower=True, trans="T")
        Zkk = 0.5 * (Zkk + Zkk.T)
        new = np.empty((w, w))
        new[nz:, nz:] = sub
        new[:nz, nz:] = -X
        new[nz:, :nz] = -X.T
        new[:nz, :nz] = Zkk
        W = new
        out[k - first] = Zkk
    return out


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


def solve_window(
    problem: Problem,
    qpos: np.ndarray,
    bias: np.ndarray,
    covariance: bool | range = True,
    prior: MarginalPrior | None = None,
    marginalize: int | None = None,
) -> WindowResult:
    """Levenberg–Marquardt on one window from (qpos (T, nq), bias (T, nb)); the marginal
    covariances at the knots `covariance` (True: all; False: none).

    prior: what the knots before the window say about its first keys (`MarginalPrior`).
    marginalize: the key where the next window starts: its prior (`WindowResult.next_prior`)
    is this window's past up to there, marginalized at the last linearization."""
    lin = Linearizer(problem, prior)
    try:
        p = problem
        cost, by_type = lin.cost(qpos, bias)
        cost0 = cost
        # damping λ on the unit diagonal: from LAMBDA_MIN (Gauss–Newton steps), raised only by
        # rejected steps (on the 1-minute humanoid_push log 120 linearizations against 157
        # from λ = 1e-3, and the lower cost)
        lam = LAMBDA_MIN
        converged = False
        it = 0
        system = None
        blocks: list[Block] = []
        for it in range(1, p.settings.max_iterations + 1):  # noqa: B007
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
            marginal_prior(lin, blocks, *at, marginalize) if marginalize and blocks else None,
        )
    finally:
        lin.close()
    if not covariance:
        return result
    return with_covariance(result, covariance if isinstance(covariance, range) else None, problem)


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


def with_covariance(
    result: WindowResult, keys: range | None = None, problem: Problem | None = None
) -> WindowResult:
    """`result` with the marginal standard deviations of x_k at `keys` (None: every knot) from
    its last linearization (GTSAM), and their warnings; with the problem, also the variance
    of the model's uncertain parameters (`consider_variance`)."""
    if result.system is None:
        return result
    warnings = list(result.warnings)
    std = result.system.marginal_std(result.qpos_std.shape[1], warnings, keys)
    if problem is not None:  # and the model's uncertain parameters' share
        std = np.sqrt(std**2 + consider_variance(problem, result))
    return replace(result, qpos_std=std, warnings=warnings)


CONSIDER_STEP = 0.01  # relative change of a parameter for its finite difference


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


@dataclass(frozen=True)
class SoftnessFit:
    """The contact softness fitted by the physics (`fit_softness`): factors on the model's own
    ε and κ, their posterior σ (relative), and the rounds taken."""

    eps_scale: float
    kappa_scale: float
    sigma: tuple[float, float]
    rounds: int


FIT_ROUNDS = 6
FIT_STOP = 0.005  # a round that changes both factors by less than this ends the fit


def fit_softness(
    problem: Problem, qpos: np.ndarray, bias: np.ndarray
) -> tuple[SoftnessFit, WindowResult]:
    """Fit factors θ = (s_ε, s_κ) on the window's model's own contact softness together with
    the window's motion: maximum a posteriori with the prior log-normal around 1 (σ =
    model_softness_std). Each round takes one Gauss–Newton step over (x, θ) through the
    Schur complement of the solved system — (D − Cᵀ H⁻¹ C) Δθ = −(Jθᵀ r + θ/σ²), with
    Jθ = ∂r/∂θ of the physics rows (finite differences), C = Jᵀ Jθ, D = Jθᵀ Jθ + 1/σ² —
    then re-solves the window with the model scaled by exp(θ) from x + S Δθ (S = −H⁻¹ C).
    The mocap sees how deep the robot sits; the physics says how deep the model lets it."""
    sigma = problem.settings.model_softness_std
    names = ("softness_eps", "softness_kappa")
    theta = np.zeros(2)
    base = problem.model
    result = solve_window(problem, qpos, bias, covariance=False)
    M = np.diag(np.full(2, 1.0 / sigma**2))
    rounds = 0
    for rounds in range(1, FIT_ROUNDS + 1):  # noqa: B007
        system = result.solved_system
        if system is None or not result.blocks:
            break
        r = _rows_at(problem, problem.model, result)
        parts = [_parameter_sensitivity(problem, result, system, name, r) for name in names]
        D = np.array([[_dot(a[0], b[0]) for b in parts] for a in parts])
        D += np.eye(2) / sigma**2
        CS = np.array([[np.sum(a[1] * b[2]) for b in parts] for a in parts])  # Cᵀ S = −Cᵀ H⁻¹ C
        M = D + CS
        g = np.array([_dot(dr, r) for dr, _, _ in parts]) + theta / sigma**2
        step = -np.linalg.solve(M, g)
        theta += step
        model = copy.deepcopy(base)
        scale_softness(model, float(np.exp(theta[0])), float(np.exp(theta[1])))
        dx = sum(S * d for (_, _, S), d in zip(parts, step, strict=True))
        nv = problem.model.nv
        problem = replace(problem, model=model)
        start_q = retract(model, result.qpos, dx[:, :nv])
        result = solve_window(problem, start_q, result.bias + dx[:, nv:], covariance=False)
        if np.max(np.abs(step)) < FIT_STOP:
            break
    posterior = np.sqrt(np.clip(np.diag(np.linalg.inv(M)), 0.0, None))
    fit = SoftnessFit(
        float(np.exp(theta[0])), float(np.exp(theta[1])), (posterior[0], posterior[1]), rounds
    )
    return fit, result


def _rows_at(problem: Problem, model: mujoco.MjModel, result: WindowResult) -> list[np.ndarray]:
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


def _parameter_sensitivity(
    problem: Problem,
    result: WindowResult,
    system: BandedSystem,
    name: str,
    at: list[np.ndarray],
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """For one CONSIDERED parameter θ (a relative change): ∂r/∂θ of every factor's rows (one
    (K, m) per block: the physics, and the sensors the model predicts through θ — a
    force/torque sensor through the contacts), C = Jᵀ ∂r/∂θ by key (T, nz) and the
    estimate's sensitivity S = −H⁻¹ C (T, nz) with H that of `system`; `at`: the rows at the
    result's solution (`_rows_at`)."""
    perturb, _ = CONSIDERED[name]
    model = copy.deepcopy(problem.model)
    perturb(model, 1.0 + CONSIDER_STEP)
    moved = _rows_at(problem, model, result)
    dr = [(r - r0) / CONSIDER_STEP for r, r0 in zip(moved, at, strict=True)]
    C = key_gradient(problem, result.blocks, dr)
    s, ab = system.scaled_band()
    return dr, C, replace(system, g=C).damped_step(s, ab, LAMBDA_MIN)


def consider_variance(
    problem: Problem, result: WindowResult, parameters: tuple[str, ...] = tuple(CONSIDERED)
) -> np.ndarray:
    """(T, nv) the variance the estimate inherits from the model's uncertain parameters,
    which it does not estimate (Schmidt's consider covariance): per parameter θ — the contact
    softness ε and κ and the masses, each as a relative scale with σ_θ from the settings
    (model_softness_std, model_mass_std) — the estimate's sensitivity S_θ = −H⁻¹ Jᵀ ∂r/∂θ
    (H, J of the solved system; ∂r/∂θ of every factor's rows by a finite difference at the
    solution: the physics, and the sensors predicted through θ — a force/torque sensor
    through the contacts) adds (S_θ σ_θ)², as its mean over the window per dof. A contact
    softer than modeled lets the robot sit lower: the height's variance grows by that much."""
    system = result.solved_system
    nv = problem.model.nv
    variance = np.zeros((problem.T, nv))
    if system is None or not result.blocks:
        return variance
    at_solution = None
    for name in parameters:
        sigma = getattr(problem.settings, CONSIDERED[name][1])
        if sigma <= 0:
            continue
        if at_solution is None:  # (the linearization may be a step before the solution)
            at_solution = _rows_at(problem, problem.model, result)
        try:
            _, _, S = _parameter_sensitivity(problem, result, system, name, at_solution)
        except np.linalg.LinAlgError:
            continue
        # its RMS over the window, per dof: a constant parameter moves the estimate by about
        # this much throughout, where the linear sensitivity may pass through zero (a load
        # moving from foot to foot)
        variance += np.mean((S[:, :nv] * sigma) ** 2, axis=0)
    return variance
