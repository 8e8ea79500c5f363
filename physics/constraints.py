"""The constraint space of one time step: Phase I outputs in the paper's terms.

MuJoCo instantiates the constraint rows (mj_makeConstraint): Jacobians, violations, types and
owners. From them this module builds what Phase II needs — the objects of Section II-D, the
regularizer R (eq. 27, 22), the reference velocity v* (eq. 24) and the friction-loss bounds η —
from the project's own Softness settings, so that the reference path does not read MuJoCo's
efc_R / efc_aref (tests check that both agree).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from physics.softness import Softness

_T = mujoco.mjtConstraint


class Kind(enum.IntEnum):
    """The object types of Section II-D, plus equality constraints (Section II-C)."""

    EQUALITY = 0  # soft Gauss principle, f_E unconstrained
    FRICTION = 1  # dry friction loss: −η ≤ f ≤ η
    LIMIT = 2  # joint/tendon limit or frictionless contact: f ≥ 0
    CONTACT = 3  # frictional contact: f in the elliptic cone


_KIND_OF_TYPE = {
    int(_T.mjCNSTR_EQUALITY): Kind.EQUALITY,
    int(_T.mjCNSTR_FRICTION_DOF): Kind.FRICTION,
    int(_T.mjCNSTR_FRICTION_TENDON): Kind.FRICTION,
    int(_T.mjCNSTR_LIMIT_JOINT): Kind.LIMIT,
    int(_T.mjCNSTR_LIMIT_TENDON): Kind.LIMIT,
    int(_T.mjCNSTR_CONTACT_FRICTIONLESS): Kind.LIMIT,
    int(_T.mjCNSTR_CONTACT_ELLIPTIC): Kind.CONTACT,
}


@dataclass(frozen=True)
class ConstraintObject:
    """One object of the contact space: rows [start, start+size) of f."""

    kind: Kind
    start: int
    size: int
    mu: np.ndarray  # (d,) friction coefficients μ_1..μ_d (contacts only, else empty)

    @property
    def rows(self) -> slice:
        return slice(self.start, self.start + self.size)


@dataclass(frozen=True)
class ConstraintSpace:
    """Everything Phase II needs about the constraints at one (q, v). nefc rows, nv dofs.

    J:        (nefc, nv) stacked Jacobians [J_E; J] (MuJoCo's efc_J row order)
    R:        (nefc,) diagonal regularizer, eq. 27 with the friction adjustment of eq. 22
    vstar:    (nefc,) desired next-step constraint velocity v*, eq. 24
    eta:      (nefc,) friction-loss impulse bound η = h·frictionloss (0 on other rows)
    efc_type: (nefc,) MuJoCo mjtConstraint per row;  efc_id: (nefc,) owner id per row
    objects:  the paper's objects in row order;  ne: number of equality rows (they come first)
    """

    h: float
    J: np.ndarray
    R: np.ndarray
    vstar: np.ndarray
    eta: np.ndarray
    efc_type: np.ndarray
    efc_id: np.ndarray
    objects: tuple[ConstraintObject, ...]
    ne: int

    @property
    def nefc(self) -> int:
        return len(self.R)

    def contact_objects(self) -> tuple[ConstraintObject, ...]:
        """The objects of the contact space (all but equality), rows counted from row ne."""
        return tuple(
            replace(obj, start=obj.start - self.ne)
            for obj in self.objects
            if obj.kind != Kind.EQUALITY
        )


def constraint_space(m: mujoco.MjModel, d: mujoco.MjData, softness: Softness) -> ConstraintSpace:
    """Build the constraint space from MjData after mj_makeConstraint (positions) at qvel d.qvel.

    Reads efc_J, efc_pos, efc_margin, efc_frictionloss, efc_type, efc_id, contact friction, and
    MuJoCo's approximate diagonal of A (efc_diagA of the normal and scalar rows).
    """
    nefc, nv, h = d.nefc, m.nv, m.opt.timestep
    J = _dense_jacobian(m, d)
    efc_type = d.efc_type.copy()
    efc_id = d.efc_id.copy()
    eps = softness.eps

    # eq. 27: R_ii = max(ε A_ii, r_min); MuJoCo stores diagApprox re-derived from its own R,
    # which equals the original A_ii on every row but contact friction rows (set below).
    R = np.maximum(eps * d.efc_diagA, softness.r_min)
    B = np.full(nefc, softness.B)
    K = np.full(nefc, softness.K)
    eta = np.zeros(nefc)

    objects: list[ConstraintObject] = []
    no_mu = np.zeros(0)
    i = 0
    while i < nefc:
        kind = _KIND_OF_TYPE.get(int(efc_type[i]))
        if kind is None:
            raise ValueError(f"constraint row {i} has unsupported type {efc_type[i]}")
        if kind == Kind.CONTACT:
            con = d.contact[efc_id[i]]
            size = int(con.dim)
            mu = con.friction[: size - 1].copy()
            # eq. 22 with r_F = r_0 μ_1² ⟨μ_j⁻²⟩ / impratio (MuJoCo's R_1 = R_0 / impratio)
            r0 = R[i]
            rF = r0 * mu[0] ** 2 * np.mean(1.0 / mu**2) / softness.impratio
            R[i + 1 : i + size] = rF * mu**-2 / np.mean(mu**-2)
            K[i + 1 : i + size] = 0.0  # friction dimensions: velocity only
            objects.append(ConstraintObject(kind, i, size, mu))
        else:
            size = 1
            if kind == Kind.FRICTION:
                K[i] = 0.0
                eta[i] = h * d.efc_frictionloss[i]
            objects.append(ConstraintObject(kind, i, size, no_mu))
        i += size

    # eq. 24: v* = J v − h (B J v + K x), x the violation (distance minus margin)
    Jv = J @ d.qvel if nv else np.zeros(nefc)
    x = d.efc_pos - d.efc_margin
    vstar = Jv - h * (B * Jv + K * x)
    vstar -= h * _jdot_v(m, d, B, K, Jv, x)
    return ConstraintSpace(h, J, R, vstar, eta, efc_type, efc_id, tuple(objects), d.ne)


def _jdot_v(
    m: mujoco.MjModel, d: mujoco.MjData, B: np.ndarray, K: np.ndarray, Jv: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """(nefc,) J̇v on connect and weld rows, 0 elsewhere.

    MuJoCo (≥ 4.0) asks connect/weld constraints for J a + J̇ v = a_ref, a refinement of eq. 24
    that keeps anchors together on curved paths. J̇v is a Phase-I kinematic term like c(q, v);
    MuJoCo computes it in mj_referenceConstraint (mj_Jdotv, not in the Python API), so it is
    read back as the difference between eq. 24's a_ref and MuJoCo's efc_aref on those rows.
    """
    jdot_v = np.zeros(d.nefc)
    rows = np.flatnonzero(d.efc_type[: d.nefc] == _T.mjCNSTR_EQUALITY)
    rows = rows[np.isin(m.eq_type[d.efc_id[rows]], _CURVED_EQUALITIES)]
    if rows.size:
        mujoco.mj_referenceConstraint(m, d)
        imp = d.efc_KBIP[rows, 2]
        aref_eq24 = -d.efc_KBIP[rows, 1] * Jv[rows] - d.efc_KBIP[rows, 0] * imp * x[rows]
        jdot_v[rows] = aref_eq24 - d.efc_aref[rows]
    return jdot_v


_CURVED_EQUALITIES = [int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)]


def _dense_jacobian(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """efc_J as a dense (nefc, nv) array, whether MuJoCo stored it dense or sparse."""
    if not mujoco.mj_isSparse(m):
        return d.efc_J[: d.nefc * m.nv].reshape(d.nefc, m.nv).copy()
    J = np.zeros((d.nefc, m.nv))
    for r in range(d.nefc):
        adr, nnz = d.efc_J_rowadr[r], d.efc_J_rownnz[r]
        J[r, d.efc_J_colind[adr : adr + nnz]] = d.efc_J[adr : adr + nnz]
    return J
