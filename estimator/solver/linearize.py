"""Every factor's rows and Jacobians over all knots of a window, vectorized across knots.

The engine runs at every interior knot on its threads (`physics.knots`); the chain rule
through v_k = (q_k ⊖ q_{k−1})/h and a_k = (v_{k+1} − v_k)/h turns its derivatives by (q, v, a)
into derivatives by the keys (x_{k−1}, x_k, x_{k+1}); the factor units (`estimator.factors`)
whiten and robustly weight the rows.
"""

from __future__ import annotations

import os

import numpy as np

from estimator.factors import bias_walk, measurement, motion, physics
from estimator.factors.base import Block, Terms
from estimator.factors.marginal_prior import MarginalPrior
from estimator.problem import (
    Problem,
    RotationDofs,
    accelerations,
    difference_jacobians,
    velocities,
)
from estimator.settings import Settings
from physics.knots import INLINE_KNOTS, KnotBatch, KnotEngine

# MuJoCo threads of one estimate (a fleet task runs on its one CPU: 1)
THREADS = int(os.environ.get("PHYSFUSE_THREADS") or 2)


def row_span(settings: Settings) -> int:
    """The keys one knot's rows reach: (x_{k−1}, x_k, x_{k+1}), and x_{k+2} with the jerk
    prior."""
    return 4 if settings.jerk_prior_std > 0 else 3


class Derivatives:
    """MuJoCo's derivatives at the knots of a stream, kept per knot and reused while the
    knot's (q, v, a) stays within `tol_q` (m or rad) of where they were taken (v within
    tol_q/h, a within tol_q/h²): a fixed-lag window re-solves mostly knots that barely
    move, and `mjd_inverseFD` is the linearization's cost (iSAM2 relinearizes only the
    variables that moved past a threshold, for the same reason). The residuals are always
    evaluated at the current state."""

    def __init__(self, h: float, tol_q: float = 1e-4) -> None:
        self.tol = np.array([tol_q, tol_q / h, tol_q / h**2])
        self.at: dict[int, tuple[np.ndarray, ...]] = {}  # knot → (q, v, a, F, S)
        self.reused = self.computed = 0

    def get(self, knot: int, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> tuple | None:
        """(F, S) taken near this state, or None."""
        kept = self.at.get(knot)
        if kept is None:
            return None
        for x, x0, tol in zip((q, v, a), kept[:3], self.tol, strict=True):
            if not np.max(np.abs(x - x0)) <= tol:  # (NaN: not near)
                return None
        self.reused += 1
        return kept[3], kept[4]

    def put(self, knot: int, q: np.ndarray, v: np.ndarray, a: np.ndarray, F, S) -> None:
        self.computed += 1
        self.at[knot] = (q.copy(), v.copy(), a.copy(), F.copy(), S.copy())

    def clear(self) -> None:
        self.at.clear()

    def forget_before(self, knot: int) -> None:
        for k in [k for k in self.at if k < knot]:
            del self.at[k]


class Linearizer:
    """Residuals and their Jacobians over all knots of a problem, vectorized across knots.

    derivatives, first: MuJoCo's derivatives kept across solves (a stream's window, whose
    knot k is the stream's knot first + k). engines: the engines of an earlier Linearizer on
    the same model (kept open by their owner; a stream's updates)."""

    def __init__(
        self,
        problem: Problem,
        prior: MarginalPrior | None = None,
        derivatives: Derivatives | None = None,
        first: int = 0,
        engines: KnotBatch | None = None,
    ) -> None:
        self.problem = problem
        self.prior = prior  # on the first keys, from the knots before the window
        self.derivatives, self.first = derivatives, first
        # the engine at the knots, one MjData per thread (`physics.knots`)
        self.own_engines = engines is None
        self.engines = engines or KnotBatch(
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
        self.span = row_span(problem.settings)  # keys a knot's rows reach
        # which of mjd_inverseFD's derivatives the rows use: u's where a physics row has a σ
        # (not in the kinematic smoother), the sensors' by v and a only for velocity- and
        # acceleration-stage sensors (a manipulator's mocap and encoders need ∂s/∂q alone)
        physics = bool(np.isfinite(problem.physics_sigma[1:-1]).any())
        stages = {block.stage for block in problem.blocks}
        self.wanted = (
            (physics, physics, physics),
            (True, bool(stages & {"vel", "acc"}), "acc" in stages),
        )
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
        Ju = np.empty((n_jac, nv, 3 * nv))  # and in the rows' layout (a sensor's rows contiguous)
        Js = np.empty((n_jac, ns, 3 * nv))
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

        keep = self.derivatives

        commanded = np.isfinite(p.ctrl).any(axis=1) if p.ctrl.shape[1] else np.zeros(p.T, bool)
        commands = bool(commanded[1:-1].any())
        nu = p.model.nu

        def work(engine: KnotEngine, chunk: range) -> None:
            rows = slice(chunk.start - 1, chunk.stop - 1)
            if commands:  # the commands' actuation at each knot, their forces after the loop
                moment = np.zeros((len(chunk), nu, nv))
                force = np.zeros((len(chunk), nu))
            for k in chunk:
                i = k - 1
                u[i], s[i] = engine.inverse(qpos[k], v[k], a[k])
                if commanded[k]:
                    j = k - chunk.start
                    moment[j], force[j] = p.actuation(engine.data, k)
                if with_jacobians:
                    kept = keep.get(self.first + k, qpos[k], v[k], a[k]) if keep else None
                    if kept is not None:
                        F[:, i], S[:, i] = kept
                    else:
                        outs = [
                            D[j, i] if wanted[j] else None
                            for D, wanted in zip((F, S), self.wanted, strict=True)
                            for j in range(3)
                        ]
                        engine.derivatives(qpos[k], v[k], a[k], *outs)
                        if keep is not None:
                            keep.put(self.first + k, qpos[k], v[k], a[k], F[:, i], S[:, i])
            if not commands:
                known[rows] = p.qfrc_known[chunk.start : chunk.stop]
            else:
                actuation = (moment, force)
                known[rows], known_dq, known_dv = p.u_known_of(chunk, actuation, with_jacobians)
                if known_dq is not None and known_dv is not None:  # of u − u_known
                    F[0, rows] -= known_dq.transpose(0, 2, 1)
                    F[1, rows] -= known_dv.transpose(0, 2, 1)
            if with_jacobians:  # numpy releases the GIL: the chain rule runs in parallel too
                chained(F[:, rows], rows, JuT[rows])
                chained(S[:, rows], rows, JsT[rows])
                Ju[rows] = JuT[rows].transpose(0, 2, 1)
                Js[rows] = JsT[rows].transpose(0, 2, 1)

        self.engines.map(work, 1, p.T - 1)
        if not with_jacobians:
            return Terms(a[1:-1], u, known, s)
        da = np.stack([-d1[:-1], d1[1:] - d2[:-1], d2[1:]], axis=1) / h**2
        return Terms(a[1:-1], u, known, s, Ju, Js, da)

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
        # the sensors' blocks on the engines' threads (numpy releases the GIL), in order
        each = map if p.T <= INLINE_KNOTS else self.pool.map
        out += each(lambda sensor: measurement.rows(p, t, bias, sensor, robust), p.blocks)
        return out

    def cost(self, qpos: np.ndarray, bias: np.ndarray) -> tuple[float, dict[str, float]]:
        """Total robust cost and its split by factor type."""
        return self.cost_of(self.blocks(self.terms(qpos, False), bias), qpos, bias)

    def cost_of(
        self, blocks: list[Block], qpos: np.ndarray, bias: np.ndarray
    ) -> tuple[float, dict[str, float]]:
        """The same from the blocks at (qpos, bias) (a linearization's: no second pass)."""
        total: dict[str, float] = {}
        for b in blocks:
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
        if self.own_engines:
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
