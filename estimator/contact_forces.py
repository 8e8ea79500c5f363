"""Contact forces that close the physics residual.

At a knot the analytic inverse returns u = M a + c − J_cᵀ f − (the other constraint forces),
with f the soft contact model's forces at the estimated (q, v, a). Where the actuation is
known (u_known: commands through the actuators, zero on unactuated dofs) the residual
r = u − u_known is the generalized force the model's contacts leave unexplained. Within a
millimetre of touch-down or lift-off f jumps with q (a contact exists only below zero
distance), so there r is large and f is not to be trusted. The balanced forces

    f' = f + Δf,   Δf = argmin ‖Σ^{-1/2}(J_cᵀ Δf − r)‖² + ‖Δf‖² / σ_f²

are the forces of the active contacts that, with the known actuation, best explain the
estimated motion (u' − u_known = r − J_cᵀ Δf), each then scaled back into its friction cone.
Σ is the physics factors' σ²; dofs with no known force do not take part. The prior σ_f (of
the order of the robot's weight) keeps two contacts at nearly one point (a foot sphere and the
shin capsule above it) from trading large opposite forces that the cone would then cut apart.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from physics.result import Constraints, Contacts


def contact_jacobian(
    model: mujoco.MjModel, data: mujoco.MjData, contacts: Contacts, i: int
) -> np.ndarray:
    """(3, nv) rows normal, tangent 1, tangent 2 of contact i: the velocity of geom2's body
    relative to geom1's at the contact point, in the contact frame (MuJoCo's efc_J rows of an
    elliptic contact). `data` holds the knot's kinematics (mj_kinematics, mj_comPos)."""
    jac = np.zeros((3, model.nv))
    jacp = np.zeros((3, model.nv))
    for geom, sign in ((contacts.geom[i][1], 1.0), (contacts.geom[i][0], -1.0)):
        body = int(model.geom_bodyid[geom])
        if body:
            mujoco.mj_jac(model, data, jacp, None, contacts.pos[i], body)
            jac += sign * jacp
    return contacts.frame[i] @ jac


def project_to_cone(force: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """force (normal, tangent 1, tangent 2 | normal) with normal ≥ 0 and the tangential part
    scaled back to the elliptic cone ‖(f_t1/μ1, f_t2/μ2)‖ ≤ f_n."""
    out = force.copy()
    out[0] = max(out[0], 0.0)
    if len(out) > 1:
        scaled = np.hypot(out[1] / mu[0], out[2] / mu[1])
        if scaled > out[0]:
            out[1:] *= out[0] / scaled
    return out


def balanced_constraints(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    constraints: Constraints,
    residual: np.ndarray,
    sigma: np.ndarray,
    force_std: float,
) -> Constraints:
    """`constraints` with the active contacts' impulses balanced (module docstring).

    residual: (nv,) r = u − u_known (NaN where no force is known); sigma: (nv,) its σ (inf
    there); force_std: σ_f, N. Only the translational rows (normal, tangents) of a contact
    change.
    """
    contacts = constraints.contacts
    active = [int(i) for i in np.flatnonzero(contacts.efc_address >= 0)]
    known = np.isfinite(residual) & np.isfinite(sigma)
    if not active or not known.any():
        return constraints
    rows = [min(int(contacts.dim[i]), 3) for i in active]
    jac = np.vstack(
        [contact_jacobian(model, data, contacts, i)[:n] for i, n in zip(active, rows, strict=True)]
    )
    # whitened least squares: rows J_cᵀ/σ = r/σ on the known dofs, then Δf/σ_f = 0
    unknowns = jac.shape[0]
    lhs = np.vstack([(jac.T / sigma[:, None])[known], np.eye(unknowns) / force_std])
    rhs = np.r_[(residual / sigma)[known], np.zeros(unknowns)]
    delta = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    impulse = constraints.efc_impulse.copy()
    h = constraints.h
    start = 0
    for i, n in zip(active, rows, strict=True):
        adr = int(contacts.efc_address[i])
        force = impulse[adr : adr + n] / h + delta[start : start + n]
        impulse[adr : adr + n] = h * project_to_cone(force, contacts.friction[i, :2])
        start += n
    return dataclasses.replace(constraints, efc_impulse=impulse)
