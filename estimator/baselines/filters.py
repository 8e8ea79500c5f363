"""EKF and UKF with the physics forward dynamics as process model (MuJoCo MPC's
`estimator/kalman.cc` and `unscented.cc`), on filterpy: the causal baselines a user would
otherwise run on the smoother's knots, sensors and noise settings.

State at knot k: (q_k, v_k, b_k), the configuration on the model's manifolds, the velocity and
the IMU biases (6 per IMU stream, the problem's layout). The filters work in tangent
coordinates x = (δq, v, b) around a reference configuration q̄, q = q̄ ⊕ δq (TangentChart);
after each update δq is folded into q̄.

Start: q_0 the raw configuration, σ INITIAL_STD, or a coordinate's motion over the time it is
held back from its stream's first sample (`held_at_start`); v_0 from the first two.

Process: one semi-implicit Euler step of MuJoCo's forward dynamics (mj_step on the problem's
model, softness and timestep h, its actuation off) under the known generalized force u_k:

    a_k = forward(q_k, v_k, u_k),   v_{k+1} = v_k + h a_k,   q_{k+1} = q_k ⊕ h v_{k+1}

the smoother's v_{k+1} = (q_{k+1} ⊖ q_k)/h and a_k = (v_{k+1} − v_k)/h. The force is uncertain
by w_k ~ N(0, diag σ_f²): σ_f the physics σ of the settings per dof (a dof with no known force
takes 0 and σ from its actuators' force range). Q = G diag(σ_f²) Gᵀ with G = ∂x_{k+1}/∂u
(h² ∂a/∂u on δq, h ∂a/∂u on v, finite differences through the constraint solver, so contacts
absorb what they hold), plus the bias random walk σ_walk² h.

Measurements: the smoother's sensor blocks (a MuJoCo sensor per config stream, samples brought
to the knots), s(q_k, v_k, a_k) + b_k; a quaternion block as Log(m⁻¹ ⊗ s) against 0.
Acceleration-stage sensors (accelerometer, force/torque) also see the force noise:
R += D diag(σ_f²) Dᵀ, D = ∂s/∂u (its correlation with the same step's process noise is
dropped). A block whose innovation fails a chi-square test at GATE_PROBABILITY is left out at
that knot (mocap outliers), unless its stream has been rejected for more than GATE_LOCKOUT_S
(then the filter has drifted: accept it again rather than lose it for good).
"""

from __future__ import annotations

import copy
import functools
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import mujoco
import numpy as np
import scipy.linalg
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.stats import chi2

from estimator.actuation import moment_dense
from estimator.config import Config
from estimator.errors import ConfigError
from estimator.estimate import Estimate
from estimator.factors import SensorBlock
from estimator.io.logs.measurements import Measurement
from estimator.knots import knot_grid
from estimator.problem import Problem, build_problem, model_with_sensors, u_known_along
from estimator.rotations import quat_errors, quat_exp, quat_log_between, quat_mul
from estimator.run import Summary, finish, initial_trajectory
from estimator.settings import Settings

METHODS = ("ekf", "ukf")
GATE_PROBABILITY = 0.999  # a block is used when its Mahalanobis² < χ²(dim) at this quantile
GATE_LOCKOUT_S = 0.05  # s: a stream rejected for longer is accepted again (re-acquisition)
INITIAL_STD = 1.0  # m, rad, m/s, rad/s: the prior of q_0, v_0 before the first measurement
FORCE_STEP = 1e-3  # N or N·m: finite-difference step of ∂(a, s)/∂u
UNBOUNDED_FORCE_STD = 1000.0  # N or N·m: σ of an unknown force no actuator range bounds
# MuJoCo MPC's unscented.cc: sigma points at ±√n σ, no negative weights
UKF_ALPHA, UKF_BETA, UKF_KAPPA = 1.0, 2.0, 0.0
UKF_START_S = 0.05  # s: the UKF takes over from the EKF that starts both filters


# ---------------------------------------------------------------------------------------------
# the state's tangent coordinates


@dataclass(frozen=True)
class TangentChart:
    """Vector coordinates x = (δq, v, b) of a filter state around a reference q̄, q = q̄ ⊕ δq.

    The rotation triples of δq (free-joint and ball-joint rotations, body frame) combine on
    SO(3): x ⊖ y = Log(Exp(y)⁻¹ Exp(x)) and x ⊕ d = Log(Exp(x) Exp(d)), independent of q̄
    (q̄ Exp(x) ⊖ q̄ Exp(y) = Log(Exp(y)⁻¹ Exp(x))); every other coordinate is a vector.
    """

    model: mujoco.MjModel
    rotations: tuple[np.ndarray, ...]  # indices of each rotation's three δq coordinates

    @classmethod
    def of(cls, model: mujoco.MjModel) -> TangentChart:
        triples = []
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                triples.append(model.jnt_dofadr[j] + 3 + np.arange(3))
            elif model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                triples.append(model.jnt_dofadr[j] + np.arange(3))
        return cls(model, tuple(triples))

    def qpos(self, reference: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(nq,) q̄ ⊕ δq."""
        q = reference.copy()
        mujoco.mj_integratePos(self.model, q, x[: self.model.nv], 1.0)
        return q

    def coordinates(self, reference: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """(nv,) δq = q ⊖ q̄."""
        dq = np.zeros(self.model.nv)
        mujoco.mj_differentiatePos(self.model, dq, 1.0, reference, qpos)
        return dq

    def residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a ⊖ b (filterpy's residual_x)."""
        out = a - b
        for i in self.rotations:
            out[i] = quat_log_between(quat_exp(b[i])[None], quat_exp(a[i])[None])[0]
        return out

    def add(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """x ⊕ dx (filterpy's state_add)."""
        out = x + dx
        for i in self.rotations:
            q = quat_mul(quat_exp(x[i]), quat_exp(dx[i]))  # Exp(x) Exp(dx)
            out[i] = quat_log_between(_IDENTITY[None], q[None])[0]
        return out

    def mean(self, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Weighted mean of points (N, n): Σ w_i (x_i ⊖ m) = 0, the Karcher mean on each
        rotation (Gauss–Newton from the coordinate mean), the plain mean elsewhere."""
        m = weights @ points
        for i in self.rotations:
            R = quat_exp(points[:, i])  # (N, 4)
            for _ in range(20):
                mean = np.tile(quat_exp(m[i]), (len(R), 1))
                step = weights @ quat_errors(R, mean)[0]  # Σ w_i Log(m⁻¹ R_i)
                m[i] = self.add(m, _on(i, step, len(m)))[i]
                if np.linalg.norm(step) < 1e-13:
                    break
        return m


_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _on(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n,) zeros with values at index."""
    out = np.zeros(n)
    out[index] = values
    return out


def _psd_sqrt(P: np.ndarray) -> np.ndarray:
    """U with UᵀU = P (Cholesky; eigen-decomposition when P is only semi-definite)."""
    try:
        return scipy.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (P + P.T))
        return np.sqrt(np.clip(w, 0.0, None))[:, None] * V.T


# ---------------------------------------------------------------------------------------------
# MuJoCo at a state


class _Physics:
    """The Euler step, the sensors and their derivatives on the problem's model (owns MjData)."""

    def __init__(self, problem: Problem) -> None:
        # the commands' force comes in as u (qfrc_applied): the model's own actuation off, or a
        # position servo's bias (−kp q − kv v at ctrl 0) would be applied on top of it
        self.model = copy.deepcopy(problem.model)
        self.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
        self.data = mujoco.MjData(self.model)
        self.h = problem.h
        self.fd_eps = problem.settings.fd_eps
        self.warmstart = np.zeros(self.model.nv)  # the solver's start: the last nominal qacc

    def _set(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> None:
        d = self.data
        d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, u
        d.qacc_warmstart[:] = self.warmstart

    def step(
        self, q: np.ndarray, v: np.ndarray, u: np.ndarray, nominal: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q_{k+1}, v_{k+1}): mj_step (semi-implicit Euler). nominal: the mean state, whose
        qacc warm-starts the solver for the states around it (sigma points)."""
        self._set(q, v, u)
        mujoco.mj_step(self.model, self.data)
        if nominal:
            self.warmstart = self.data.qacc.copy()
        return self.data.qpos.copy(), self.data.qvel.copy()

    def sensors(
        self, q: np.ndarray, v: np.ndarray, u: np.ndarray, nominal: bool = False
    ) -> np.ndarray:
        """(ns,) sensordata at (q, v, a = forward(q, v, u))."""
        self._set(q, v, u)
        mujoco.mj_forward(self.model, self.data)
        if nominal:
            self.warmstart = self.data.qacc.copy()
        return self.data.sensordata.copy()

    def transition(
        self, q: np.ndarray, v: np.ndarray, u: np.ndarray, want_A: bool, want_C: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """mjd_transitionFD: A = ∂x_{k+1}/∂x_k (2nv, 2nv), C = ∂s/∂x_k (ns, 2nv); x = (δq, v)."""
        m, nv = self.model, self.model.nv
        A = np.zeros((2 * nv, 2 * nv)) if want_A else np.zeros((0, 0))
        C = np.zeros((m.nsensordata, 2 * nv)) if want_C else np.zeros((0, 0))
        self._set(q, v, u)
        mujoco.mj_forward(m, self.data)
        self.data.qacc_warmstart[:] = self.data.qacc
        mujoco.mjd_transitionFD(
            m,
            self.data,
            self.fd_eps,
            False,
            A if want_A else None,
            None,
            C if want_C else None,
            None,
        )
        return A, C

    def linearize(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> Linearization:
        """Everything an EKF step needs at one state, each derivative once."""
        s = self.sensors(q, v, u, nominal=True)
        A, C = self.transition(q, v, u, want_A=True, want_C=True)
        da, ds = self.force_response(q, v, u)
        return Linearization(s, A, C, da, ds)

    def force_response(
        self, q: np.ndarray, v: np.ndarray, u: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """∂a/∂u (nv, nv) and ∂s/∂u (ns, nv) by forward differences of the acceleration stage
        (the constraint solver included), warm-started from the nominal solution."""
        m, d = self.model, self.data
        self._set(q, v, u)
        mujoco.mj_forward(m, d)
        a0, s0 = d.qacc.copy(), d.sensordata.copy()
        da = np.zeros((m.nv, m.nv))
        ds = np.zeros((m.nsensordata, m.nv))
        for i in range(m.nv):
            d.qacc_warmstart[:] = a0
            d.qfrc_applied[i] = u[i] + FORCE_STEP
            mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 0)
            da[:, i] = (d.qacc - a0) / FORCE_STEP
            ds[:, i] = (d.sensordata - s0) / FORCE_STEP
            d.qfrc_applied[i] = u[i]
        return da, ds


@dataclass(frozen=True)
class Linearization:
    """The physics at one state: sensordata s (ns,), A = ∂x'/∂x and C = ∂s/∂x
    (`_Physics.transition`), ∂a/∂u and ∂s/∂u (`_Physics.force_response`)."""

    s: np.ndarray
    A: np.ndarray
    C: np.ndarray
    da: np.ndarray
    ds: np.ndarray


@dataclass(frozen=True)
class Force:
    """The known generalized force of a step, u (nv,), and its variance σ_f² (nv,)."""

    u: np.ndarray
    var: np.ndarray


# ---------------------------------------------------------------------------------------------
# the measurement of one knot


@dataclass(frozen=True)
class Knot:
    """The sensor blocks measured at knot k of their problem: z (m,), σ (m,), and each block's
    rows; key: the knot's index in the whole run (a stream's filter steps through problems of
    a few knots each). The blocks' rows as index arrays, each kind at once: vector rows
    (`vec_*`: residual row, sensordata row, bias index or −1) and quaternion blocks (`quat_*`:
    (B, 3) residual rows, (B, 4) sensordata rows, (B, 4) measured quaternions)."""

    k: int
    blocks: list[SensorBlock]
    rows: list[slice]
    z: np.ndarray
    sigma: np.ndarray
    key: int
    vec_out: np.ndarray
    vec_src: np.ndarray
    vec_bias: np.ndarray
    quat_out: np.ndarray
    quat_src: np.ndarray
    quat_meas: np.ndarray

    @classmethod
    def at(cls, problem: Problem, k: int, key: int | None = None) -> Knot:
        blocks, rows, z, sigma = [], [], [], []
        vec_out: list[int] = []
        vec_src: list[int] = []
        vec_bias: list[int] = []
        quat_out, quat_src, quat_meas = [], [], []
        start = 0
        for b in (e for block in problem.blocks for e in block.elements()):
            meas = b.values[k]
            if not np.all(np.isfinite(meas)):
                continue
            n = 3 if b.kind == "quat" else len(b.rows)
            blocks.append(b)
            rows.append(slice(start, start + n))
            sigma.append(b.sigma[k] if b.sigma.ndim == 2 else b.sigma)
            if b.kind == "quat":
                z.append(np.zeros(3))
                quat_out.append(np.arange(start, start + 3))
                quat_src.append(b.rows)
                quat_meas.append(meas)
            else:
                z.append(meas)
                vec_out.extend(range(start, start + n))
                vec_src.extend(b.rows)
                bias = range(b.bias.start, b.bias.stop) if b.bias is not None else [-1] * n
                vec_bias.extend(bias)
            start += n
        ints = lambda v, shape: np.array(v, dtype=int).reshape(shape)  # noqa: E731
        return cls(
            k,
            blocks,
            rows,
            np.concatenate(z) if z else np.zeros(0),
            np.concatenate(sigma) if sigma else np.zeros(0),
            k if key is None else key,
            ints(vec_out, -1),
            ints(vec_src, -1),
            ints(vec_bias, -1),
            ints(quat_out, (-1, 3)),
            ints(quat_src, (-1, 4)),
            np.array(quat_meas, dtype=float).reshape(-1, 4),
        )

    def predict(self, s: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """(N, m) predicted rows for sensordata s (N, ns) and biases (N, nb)."""
        N, B = len(s), len(self.quat_out)
        out = np.zeros((N, len(self.z)))
        if len(self.vec_out):
            biased = self.vec_bias >= 0
            pred = s[:, self.vec_src]
            pred[:, biased] += bias[:, self.vec_bias[biased]]
            out[:, self.vec_out] = pred
        if B:
            pred = s[:, self.quat_src].reshape(N * B, 4)
            meas = np.broadcast_to(self.quat_meas, (N, B, 4)).reshape(N * B, 4)
            out[:, self.quat_out] = quat_errors(pred, meas)[0].reshape(N, B, 3)
        return out

    def jacobian(self, s: np.ndarray, ds: np.ndarray) -> np.ndarray:
        """(m, c) ∂rows/∂y from sensordata s (ns,) and ∂s/∂y (ns, c) (biases not included)."""
        out = np.zeros((len(self.z), ds.shape[1]))
        out[self.vec_out] = ds[self.vec_src]
        if len(self.quat_out):
            _, de_dp = quat_errors(s[self.quat_src], self.quat_meas)  # (B, 3, 4)
            out[self.quat_out] = np.einsum("bij,bjc->bic", de_dp, ds[self.quat_src])
        return out

    def bias_jacobian(self, nb: int) -> np.ndarray:
        """(m, nb) ∂rows/∂b."""
        out = np.zeros((len(self.z), nb))
        biased = self.vec_bias >= 0
        out[self.vec_out[biased], self.vec_bias[biased]] = 1.0
        return out

    def gate(self, y: np.ndarray, S: np.ndarray, accept: set[str]) -> tuple[np.ndarray, set[str]]:
        """Rows of the blocks whose innovation y (m,) with covariance S (m, m) passes the
        chi-square test (or whose stream is in `accept`), and the streams rejected. Blocks of
        one size at once: d² = yᵀ S_bb⁻¹ y per block."""
        passed = np.zeros(len(self.blocks), dtype=bool)
        sizes = np.array([r.stop - r.start for r in self.rows], dtype=int)
        starts = np.array([r.start for r in self.rows], dtype=int)
        for n in np.unique(sizes):
            which = np.flatnonzero(sizes == n)
            idx = starts[which, None] + np.arange(n)  # (Bn, n)
            yb = y[idx]
            d2 = np.einsum(
                "bi,bi->b",
                yb,
                np.linalg.solve(S[idx[:, :, None], idx[:, None, :]], yb[..., None])[..., 0],
            )
            passed[which] = d2 <= _gate_threshold(int(n))
        keep: list[int] = []
        rejected: set[str] = set()
        for b, r, ok in zip(self.blocks, self.rows, passed, strict=True):
            if b.stream in accept or ok:
                keep.extend(range(r.start, r.stop))
            else:
                rejected.add(b.stream)
        return np.array(keep, dtype=int), rejected


# ---------------------------------------------------------------------------------------------
# the filters


@functools.cache
def _gate_threshold(dim: int) -> float:
    return float(chi2.ppf(GATE_PROBABILITY, dim))


class _ManifoldEKF(ExtendedKalmanFilter):
    """filterpy's EKF whose prediction of x is the physics step (set `step` before predict)."""

    step: Callable[[], np.ndarray]

    def predict_x(self, u: object = 0) -> None:
        self.x = self.step()


class _ManifoldUKF(UnscentedKalmanFilter):
    """filterpy's UKF with its sums over sigma points as matrix products (same formulas)."""

    def cross_variance(
        self, x: np.ndarray, z: np.ndarray, sigmas_f: np.ndarray, sigmas_h: np.ndarray
    ) -> np.ndarray:
        """Pxz = Σ Wc_i (χ_i ⊖ x)(ζ_i − z)ᵀ."""
        dx = np.array([self.residual_x(s, x) for s in sigmas_f])
        return (dx.T * self.Wc) @ (sigmas_h - z)


def _unscented_transform(
    sigmas: np.ndarray,
    Wm: np.ndarray,
    Wc: np.ndarray,
    noise_cov: np.ndarray | None = None,
    mean_fn: Callable | None = None,
    residual_fn: Callable | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """filterpy's unscented_transform, P = Σ Wc_i (χ_i ⊖ x)(χ_i ⊖ x)ᵀ + noise as one product."""
    x = mean_fn(sigmas, Wm) if mean_fn is not None else Wm @ sigmas
    if residual_fn is None or residual_fn is np.subtract:
        y = sigmas - x
    else:
        y = np.array([residual_fn(s, x) for s in sigmas])
    P = (y.T * Wc) @ y
    return x, P if noise_cov is None else P + noise_cov


class Filter:
    """One pass over the knots: predict with the physics step, update with the knot's sensors."""

    def __init__(
        self, problem: Problem, qpos0: np.ndarray, method: str, held_s: np.ndarray | None = None
    ) -> None:
        self.p = problem
        self.method = method
        self.physics = _Physics(problem)
        self.chart = TangentChart.of(problem.model)
        nv, nb = problem.model.nv, problem.nb
        self.nv, self.nb, self.n = nv, nb, 2 * nv + nb
        self.rejected: dict[str, int] = {}  # stream → knots with a block rejected
        self.rejected_since: dict[str, int] = {}  # stream → first knot of its rejections
        self.reference = qpos0[0].copy()
        bias_std = problem.bias_prior
        self.ekf = _ManifoldEKF(self.n, 1)
        self.ekf.x = np.zeros(self.n)
        if len(qpos0) > 1:  # v_0 from the first two raw configurations
            self.ekf.x[nv : 2 * nv] = self.chart.coordinates(qpos0[0], qpos0[1]) / problem.h
        # q_0's prior: INITIAL_STD, but a coordinate held from a measurement t later (a stream
        # that starts after the log) is off by its motion over t, INITIAL_STD (as a speed) · t
        q_std = np.full(nv, INITIAL_STD)
        if held_s is not None:
            held = (held_s > 0) & np.isfinite(held_s)
            q_std[held] = np.minimum(INITIAL_STD, INITIAL_STD * held_s[held])
        self.ekf.P = np.diag(np.r_[q_std**2, np.full(nv, INITIAL_STD**2), bias_std**2])
        self.ukf: UnscentedKalmanFilter | None = None
        if method == "ukf":
            points = MerweScaledSigmaPoints(
                self.n, UKF_ALPHA, UKF_BETA, UKF_KAPPA, sqrt_method=_psd_sqrt
            )
            self.ukf = _ManifoldUKF(
                self.n,
                1,
                problem.h,
                hx=None,
                fx=self._fx,
                points=points,
                x_mean_fn=self.chart.mean,
                residual_x=self.chart.residual,
                state_add=self.chart.add,
            )

    # -- shared pieces -------------------------------------------------------------------------

    def _recenter(self, x: np.ndarray) -> None:
        """Fold δq into the reference: q̄ ← q̄ ⊕ δq, δq ← 0."""
        self.reference = self.chart.qpos(self.reference, x)
        x[: self.nv] = 0.0

    def _process_noise(self, da: np.ndarray, force: Force) -> np.ndarray:
        """Q of a step with ∂a/∂u = da: G diag(σ_f²) Gᵀ, and the bias walk."""
        h, nv = self.p.h, self.nv
        G = np.vstack([h * h * da, h * da])
        Q = np.zeros((self.n, self.n))
        Q[: 2 * nv, : 2 * nv] = (G * force.var) @ G.T
        Q[2 * nv :, 2 * nv :] = np.diag(self.p.bias_walk**2 * h)
        return Q

    def _sensor_force_noise(
        self, knot: Knot, q: np.ndarray, v: np.ndarray, force: Force
    ) -> np.ndarray:
        """(m, m) D diag(σ_f²) Dᵀ: the force noise seen by acceleration-stage sensors."""
        _, ds = self.physics.force_response(q, v, force.u)
        s = self.physics.sensors(q, v, force.u)
        D = knot.jacobian(s, ds)
        return (D * force.var) @ D.T

    def _gate(self, knot: Knot, y: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The rows to update with: the chi-square gate, except for a stream rejected for
        longer than GATE_LOCKOUT_S (then the filter, not the stream, has drifted)."""
        accept = {
            stream
            for stream, first in self.rejected_since.items()
            if (knot.key - first) * self.p.h > GATE_LOCKOUT_S
        }
        keep, rejected = knot.gate(y, S, accept)
        for stream in {b.stream for b in knot.blocks}:
            if stream in rejected:
                self.rejected[stream] = self.rejected.get(stream, 0) + 1
                self.rejected_since.setdefault(stream, knot.key)
            else:
                self.rejected_since.pop(stream, None)
        return keep

    # -- EKF -------------------------------------------------------------------------------------

    def ekf_update(self, knot: Knot, force: Force, at: Linearization | None = None) -> None:
        """The knot's sensors, at the force applied there; at: the physics linearized at the
        prior (else here)."""
        if not knot.blocks:
            return
        x, nv = self.ekf.x, self.nv
        q, v, b = self.chart.qpos(self.reference, x), x[nv : 2 * nv], x[2 * nv :]
        if at is None:
            s = self.physics.sensors(q, v, force.u)
            _, C = self.physics.transition(q, v, force.u, want_A=False, want_C=True)
            H = knot.jacobian(s, C)
            R = np.diag(knot.sigma**2) + self._sensor_force_noise(knot, q, v, force)
        else:  # (∂rows/∂x and ∂rows/∂u in one pass over the blocks)
            s = at.s
            HD = knot.jacobian(s, np.hstack([at.C, at.ds]))
            H, D = HD[:, : 2 * nv], HD[:, 2 * nv :]
            R = np.diag(knot.sigma**2) + (D * force.var) @ D.T
        H = np.hstack([H, knot.bias_jacobian(self.nb)])
        predicted = knot.predict(s[None], b[None])[0]
        y = knot.z - predicted
        keep = self._gate(knot, y, H @ self.ekf.P @ H.T + R)
        if keep.size:
            self.ekf.update(
                knot.z[keep],
                HJacobian=lambda _x: H[keep],
                Hx=lambda _x: predicted[keep],
                R=R[np.ix_(keep, keep)],
            )
        self._recenter(self.ekf.x)

    def ekf_predict(self, force: Force, at: Linearization | None = None) -> None:
        """One step from the posterior under the force: x = step(x), P = F P Fᵀ + Q (F from A,
        at the posterior, or from `at`: the same step's prior, linearized once for both)."""
        x, nv = self.ekf.x, self.nv
        q, v = self.chart.qpos(self.reference, x), x[nv : 2 * nv].copy()
        if at is None:
            A, _ = self.physics.transition(q, v, force.u, want_A=True, want_C=False)
            da, _ = self.physics.force_response(q, v, force.u)
        else:
            A, da = at.A, at.da
        F = np.eye(self.n)
        F[: 2 * nv, : 2 * nv] = A
        self.ekf.F = F
        self.ekf.Q = self._process_noise(da, force)
        q_next, v_next = self.physics.step(q, v, force.u)

        def step() -> np.ndarray:
            self.reference = q_next
            return np.r_[np.zeros(nv), v_next, x[2 * nv :]]

        self.ekf.step = step
        self.ekf.predict()
        self.ekf.P = 0.5 * (self.ekf.P + self.ekf.P.T)

    # -- UKF -------------------------------------------------------------------------------------

    def _fx(
        self, x: np.ndarray, dt: float, q_from: np.ndarray, q_to: np.ndarray, u: np.ndarray
    ) -> np.ndarray:
        """A sigma point through the physics step, in coordinates around q_to."""
        nv = self.nv
        q_next, v_next = self.physics.step(self.chart.qpos(q_from, x), x[nv : 2 * nv], u)
        return np.concatenate([self.chart.coordinates(q_to, q_next), v_next, x[2 * nv :]])

    def ukf_predict(self, force: Force) -> None:
        assert self.ukf is not None
        x, nv = self.ukf.x, self.nv
        q, v = self.chart.qpos(self.reference, x), x[nv : 2 * nv]
        q_to, _ = self.physics.step(q, v, force.u, nominal=True)  # the next reference
        self.ukf.Q = self._process_noise(self.physics.force_response(q, v, force.u)[0], force)
        q_from, self.reference = self.reference, q_to
        self.ukf.predict(UT=_unscented_transform, q_from=q_from, q_to=q_to, u=force.u)

    def ukf_update(self, knot: Knot, force: Force) -> None:
        """Sigma points of the prior through the sensors; gate per block; filterpy's update."""
        assert self.ukf is not None
        ukf, nv = self.ukf, self.nv
        if knot.blocks:
            q, v = self.chart.qpos(self.reference, ukf.x), ukf.x[nv : 2 * nv]
            R = np.diag(knot.sigma**2) + self._sensor_force_noise(knot, q, v, force)
            self.physics.sensors(q, v, force.u, nominal=True)
            sigmas = ukf.sigmas_f
            s = np.array(
                [
                    self.physics.sensors(
                        self.chart.qpos(self.reference, x), x[nv : 2 * nv], force.u
                    )
                    for x in sigmas
                ]
            )
            predicted = knot.predict(s, sigmas[:, 2 * nv :])  # (N, m)
            # filterpy's update calls hx on the same sigma points: reuse the evaluations
            cache = {x.tobytes(): row for x, row in zip(sigmas, predicted, strict=True)}
            z_mean = ukf.Wm @ predicted
            dz = predicted - z_mean
            S = (dz.T * ukf.Wc) @ dz + R
            keep = self._gate(knot, knot.z - z_mean, S)
            if keep.size:
                ukf.update(
                    knot.z[keep],
                    R=R[np.ix_(keep, keep)],
                    UT=_unscented_transform,
                    hx=lambda x: cache[x.tobytes()][keep],
                )
                ukf.P = 0.5 * (ukf.P + ukf.P.T)
        self._recenter(ukf.x)

    # -- the pass --------------------------------------------------------------------------------

    def run(
        self, qpos0: np.ndarray, progress: Callable[[int, int], None] | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qpos (T, nq), bias (T, nb) and the q block's standard deviations (T, nv) over the
        problem's knots; qpos0: the raw trajectory, at which the commands' force is taken."""
        T, nv = self.p.T, self.nv
        # the commands' force at the measured motion (the filters step with a known force)
        u = np.nan_to_num(u_known_along(self.p, qpos0))
        var = _force_variance(self.p)
        force = [Force(u[k], var[k]) for k in range(T)]
        qpos = np.zeros((T, self.p.model.nq))
        bias = np.zeros((T, self.nb))
        std = np.zeros((T, nv))
        # both filters start with the EKF from a broad prior (sigma points of a broad prior
        # would sit metres away); the UKF takes over after UKF_START_S
        handover = T if self.ukf is None else min(T, max(1, round(UKF_START_S / self.p.h)))
        self.ekf_update(Knot.at(self.p, 0), force[0])
        self.tighten_initial_velocity()
        current: ExtendedKalmanFilter | UnscentedKalmanFilter = self.ekf
        for k in range(T):
            if 0 < k < handover:
                self.ekf_predict(force[k - 1])
                self.ekf_update(Knot.at(self.p, k), force[k])
            elif k >= handover and self.ukf is not None:
                if k == handover:
                    self.ukf.x, self.ukf.P = self.ekf.x.copy(), self.ekf.P.copy()
                    current = self.ukf
                self.ukf_predict(force[k - 1])
                self.ukf_update(Knot.at(self.p, k), force[k])
            qpos[k] = self.reference
            bias[k] = current.x[2 * nv :]
            std[k] = np.sqrt(np.clip(np.diag(current.P)[:nv], 0.0, None))
            if progress and ((k + 1) % 50 == 0 or k + 1 == T):
                progress(k + 1, T)
        return qpos, bias, std

    def tighten_initial_velocity(self) -> None:
        """v_0 came from two raw configurations: its σ is √2 σ_q / h (capped by INITIAL_STD)."""
        P, nv, h = self.ekf.P, self.nv, self.p.h
        var_v = np.minimum(2.0 * np.diag(P)[:nv] / h**2, INITIAL_STD**2)
        var_v = np.minimum(var_v, np.diag(P)[nv : 2 * nv])
        v = slice(nv, 2 * nv)
        P[v, :] = 0.0
        P[:, v] = 0.0
        P[v, v] = np.diag(var_v)


def held_at_start(model: mujoco.MjModel, measured: np.ndarray, h: float) -> np.ndarray:
    """(nv,) how long each dof's coordinate at the first knot is held back from a later
    measurement, s (`initial_trajectory` holds a stream's first sample at the log's start):
    0 where it is measured there, inf where it never is. ANYmal C's first mocap frame comes
    11 ms into its log; under the 1 m prior the first update (joints and IMU) put its base 13
    cm high until then."""
    first = np.where(measured.any(axis=0), measured.argmax(axis=0), -1)  # (nq,) first knot
    out = np.full(model.nv, np.inf)
    for j in range(model.njnt):
        q, d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        kind = model.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_FREE:  # position, then orientation
            groups = [(q, q + 3, d, d + 3), (q + 3, q + 7, d + 3, d + 6)]
        elif kind == mujoco.mjtJoint.mjJNT_BALL:
            groups = [(q, q + 4, d, d + 3)]
        else:
            groups = [(q, q + 1, d, d + 1)]
        for qa, qb, da, db in groups:
            knots = first[qa:qb]
            out[da:db] = np.inf if (knots < 0).any() else float(knots.max()) * h
    return out


def _force_variance(problem: Problem) -> np.ndarray:
    """(T, nv) σ_f² of the force on each dof: the physics σ of the settings; where no force
    is known, `force_bound`."""
    sigma = problem.physics_sigma
    return np.where(np.isfinite(sigma), sigma, force_bound(problem.model)) ** 2


def force_bound(model: mujoco.MjModel) -> np.ndarray:
    """(nv,) the largest force the actuators can apply on each dof (Σ_a |moment| ·
    max|force_a|, from the force range, or gain · max|ctrl| for a fixed-gain actuator), else
    UNBOUNDED_FORCE_STD."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    moment = np.abs(moment_dense(model, data))  # (nu, nv)
    largest = np.full(model.nu, np.inf)
    for a in range(model.nu):
        if model.actuator_forcelimited[a]:
            largest[a] = np.max(np.abs(model.actuator_forcerange[a]))
        elif (
            model.actuator_ctrllimited[a]
            and model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
            and model.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
        ):
            largest[a] = abs(model.actuator_gainprm[a, 0]) * np.max(
                np.abs(model.actuator_ctrlrange[a])
            )
    contribution = np.where(moment > 0, moment * np.where(moment > 0, largest[:, None], 0.0), 0.0)
    bound = contribution.sum(axis=0)
    return np.where(np.isfinite(bound) & (bound > 0), bound, UNBOUNDED_FORCE_STD)


# ---------------------------------------------------------------------------------------------
# a whole log


def filter_estimate(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    method: str,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Estimate, Summary]:
    """Filter the whole log causally with an EKF or a UKF (`method` "ekf" | "ukf") on the
    smoother's knots; `progress(done, total)` is called every 50 knots."""
    if method not in METHODS:
        raise ConfigError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    start = time.perf_counter()
    compiled = model_with_sensors(config)
    h = settings.h or float(compiled[0].opt.timestep)
    problem = build_problem(
        config, measurements, settings, knot_grid(measurements, h), compiled, at_sample_times=False
    )
    measured = np.zeros((problem.T, problem.model.nq), dtype=bool)
    qpos0 = initial_trajectory(problem.model, measurements, problem.t_ns, measured_out=measured)
    run = Filter(problem, qpos0, method, held_at_start(problem.model, measured, problem.h))
    qpos, bias, std = run.run(qpos0, progress)
    finite = bool(np.all(np.isfinite(qpos)))
    warnings = [
        f"{stream}: measurements rejected by the chi-square gate (p = {GATE_PROBABILITY}) at "
        f"{n} of {problem.T} knots"
        for stream, n in sorted(run.rejected.items())
    ]
    if not finite:
        warnings.append(f"the {method.upper()} diverged: non-finite states")
    return finish(config, problem, qpos, bias, std, start, [problem.T], [finite], warnings, {})
