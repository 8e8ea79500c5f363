"""The unmodeled force on each body, knot by knot, from the physics residual of an estimate.

At knot k the analytic inverse returns u_k (eq. 12) with the model's contact forces f at the
estimated motion; the known actuation is u_known. A force F on body b's centre of mass that the
model does not have appears in the residual as

    r_k = u_k − u_known_k = J_bᵀ F + J_cᵀ Δf + noise

J_b (3, nv): the translational Jacobian of b's centre of mass; J_c: the contact Jacobians
(normal, tangents) of the knot's contacts and near-contacts (geoms within `contact_margin`);
Δf: how far the model's contact forces are off, which soft contacts leave uncertain (a foot's
millimetre of slide buys newtons of friction), given a prior Δf ~ N(0, σ_f²). Whitened by
the physics σ (W = diag(1/σ) on the dofs with a known force) and with Δf marginalized, the
noise covariance is S = I + σ_f² A_c A_cᵀ, A_c = W J_cᵀ, and F's information and gradient
at the knot are

    I_kb = A_bᵀ S⁻¹ A_b,   g_kb = A_bᵀ S⁻¹ W r_k,   A_b = W J_bᵀ

so that over any set of knots the constant force that best explains the residual is
F̂ = (Σ I)⁻¹ Σ g, with the likelihood-ratio statistic χ² = Σgᵀ (Σ I)⁻¹ Σg (`detect`).
Without the contact term a push on a standing robot's trunk reads as a tenth of itself: the
estimate's feet take up the rest as friction.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from estimator.contact_forces import contact_jacobian
from estimator.estimate import Estimate
from physics.model import weight
from physics.result import Contacts

CONTACT_MARGIN_M = 0.01
FORCE_PRIOR = 10.0  # × the robot's weight


@dataclass(frozen=True)
class UnmodeledForces:
    """Per knot and body, what the physics residual says about an unmodeled force.

    t_ns:   (T,) knot times
    bodies: (B,) names of the candidate bodies (every moving body)
    body_ids: (B,) their MuJoCo ids
    info:   (T, B, 3, 3) I_kb (module docstring), 0 where the knot has no physics residual
    grad:   (T, B, 3) g_kb
    misfit: (T,) rᵀ S⁻¹ r, the knot's whitened residual with the contact forces' error
            marginalized (NaN where the knot has none); what a force on body b explains of it
            is g_kbᵀ I_kb⁻¹ g_kb (`detect.unexplained`)
    """

    t_ns: np.ndarray
    bodies: tuple[str, ...]
    body_ids: np.ndarray
    info: np.ndarray
    grad: np.ndarray
    misfit: np.ndarray

    @property
    def h(self) -> float:
        return float(np.median(np.diff(self.t_ns))) / 1e9


def unmodeled_forces(
    model: mujoco.MjModel,
    est: Estimate,
    sigma: np.ndarray,
    contact_force_std: float,
    contact_margin: float = CONTACT_MARGIN_M,
    force_prior: float | None = None,
    knots: Sequence[int] | None = None,
    residual: np.ndarray | None = None,
) -> UnmodeledForces:
    """The `UnmodeledForces` of an estimate.

    model: the estimate's model (kinematics only); sigma: (T, nv) the physics residual's σ on
    each dof (inf or NaN where no force is known: those rows drop out); contact_force_std:
    σ_f [N], the prior on how far a contact force of the model may be off; contact_margin [m]:
    geoms this close count as touching (a foot lands a knot earlier than its estimate does);
    force_prior [N]: F ~ N(0, force_prior²) at each knot (default `FORCE_PRIOR` × the
    robot's weight): what the residual cannot see of a force (a hinge's axial direction) is
    0, not arbitrary. knots: the knots to compute (default all; the others' info is 0).
    residual: (T, nv) another generalized force residual in place of the physics one
    (default est.qfrc_inverse − est.qfrc_known; the momentum observer's, a baseline).
    """
    if force_prior is None:
        force_prior = FORCE_PRIOR * weight(model)
    model = with_margin(model, contact_margin)
    bodies = np.array(
        [b for b in range(1, model.nbody) if _moves(model, b) and model.body_mass[b] > 0]
    )
    info = np.zeros((est.T, len(bodies), 3, 3))
    grad = np.zeros((est.T, len(bodies), 3))
    misfit = np.full(est.T, np.nan)
    data = mujoco.MjData(model)
    jacp = np.zeros((3, model.nv))
    J_b = np.zeros((len(bodies), model.nv, 3))
    if residual is None:
        residual = est.qfrc_inverse - est.qfrc_known
    for k in range(est.T) if knots is None else knots:
        knot = knot_residual(model, data, est, sigma, k, contact_force_std, residual[k])
        if knot is None:
            continue
        for i, b in enumerate(bodies):
            mujoco.mj_jac(model, data, jacp, None, data.xipos[b], b)
            J_b[i] = jacp.T
        A_b = J_b[:, knot.known] * knot.w[None, :, None]  # (B, m, 3)
        m = len(knot.w)
        S_inv_A = np.linalg.solve(knot.S, A_b.transpose(1, 0, 2).reshape(m, -1))
        S_inv_A = S_inv_A.reshape(m, len(bodies), 3).transpose(1, 0, 2)
        info[k] = np.einsum("bmi,bmj->bij", A_b, S_inv_A) + np.eye(3) / force_prior**2
        grad[k] = np.einsum("bmi,m->bi", S_inv_A, knot.r)
        misfit[k] = knot.r @ np.linalg.solve(knot.S, knot.r)
    names = tuple(model.body(int(b)).name or f"body {b}" for b in bodies)
    return UnmodeledForces(est.t_ns, names, bodies, info, grad, misfit)


@dataclass(frozen=True)
class KnotResidual:
    """Knot k's physics residual whitened on the dofs with a known force, with its noise.

    known: (nv,) those dofs; w: (m,) 1/σ on them; r: (m,) W r_k; contacts: the knot's
    contacts and near-contacts; J_c: their Jacobian rows (normal, tangents; `contact_jacobian`)
    on the known dofs, one (d, m) per contact; S: (m, m) I + σ_f² A_c A_cᵀ, A_c = W J_cᵀ.
    `data` holds the knot's kinematics and collisions afterwards.
    """

    known: np.ndarray
    w: np.ndarray
    r: np.ndarray
    contacts: Contacts
    J_c: list[np.ndarray]
    S: np.ndarray


def knot_residual(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    est: Estimate,
    sigma: np.ndarray,
    k: int,
    contact_force_std: float,
    residual: np.ndarray | None = None,
) -> KnotResidual | None:
    """`KnotResidual` of knot k (None: no dof has a known force there); `model` with the
    contact margin (`with_margin`). residual: (nv,) (default the physics residual)."""
    if residual is None:
        residual = est.qfrc_inverse[k] - est.qfrc_known[k]
    known = np.isfinite(residual) & np.isfinite(sigma[k]) & (sigma[k] > 0)
    if not known.any():
        return None
    w = 1.0 / sigma[k, known]
    data.qpos[:] = est.qpos[k]
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_collision(model, data)
    contacts = Contacts.from_data(data)
    J_c = [
        contact_jacobian(model, data, contacts, i)[: min(int(contacts.dim[i]), 3), known]
        for i in range(len(contacts.dim))
    ]
    A_c = np.vstack(J_c).T * w[:, None] if J_c else np.zeros((len(w), 0))
    S = np.eye(len(w)) + contact_force_std**2 * (A_c @ A_c.T)
    return KnotResidual(known, w, residual[known] * w, contacts, J_c, S)


def with_margin(model: mujoco.MjModel, contact_margin: float) -> mujoco.MjModel:
    """A copy of `model` whose geoms count as touching `contact_margin` [m] apart (0: the
    model itself, e.g. one that has its margin already)."""
    if contact_margin == 0:
        return model
    model = copy.deepcopy(model)
    model.geom_margin += contact_margin
    return model


def _moves(model: mujoco.MjModel, body: int) -> bool:
    """Whether a body or one it is welded to has dofs."""
    while body:
        if model.body_dofnum[body]:
            return True
        body = int(model.body_parentid[body])
    return False
