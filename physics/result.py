"""Result types shared by the reference and native paths (frozen; arrays are copies)."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from physics.cone import Branch

_T = mujoco.mjtConstraint
_OBJ = mujoco.mjtObj

_OWNER_OF_TYPE = {
    int(_T.mjCNSTR_EQUALITY): ("equality", _OBJ.mjOBJ_EQUALITY),
    int(_T.mjCNSTR_FRICTION_DOF): ("friction loss", _OBJ.mjOBJ_DOF),
    int(_T.mjCNSTR_FRICTION_TENDON): ("friction loss", _OBJ.mjOBJ_TENDON),
    int(_T.mjCNSTR_LIMIT_JOINT): ("limit", _OBJ.mjOBJ_JOINT),
    int(_T.mjCNSTR_LIMIT_TENDON): ("limit", _OBJ.mjOBJ_TENDON),
    int(_T.mjCNSTR_CONTACT_FRICTIONLESS): ("contact", None),
    int(_T.mjCNSTR_CONTACT_ELLIPTIC): ("contact", None),
}


@dataclass(frozen=True)
class Contacts:
    """The ncon contacts of a step (MuJoCo's d.contact, excluded ones included).

    pos:         (ncon, 3) contact point, world frame
    frame:       (ncon, 3, 3) rows: normal, tangent 1, tangent 2 (world frame)
    dim:         (ncon,) MuJoCo condim 1/3/4/6 (= 1 + d)
    geom:        (ncon, 2) geom ids of the pair
    efc_address: (ncon,) first constraint row of each contact, −1 if excluded
    friction:    (ncon, 5) μ: tangential 1, tangential 2, torsional, rolling 1, rolling 2
    """

    pos: np.ndarray
    frame: np.ndarray
    dim: np.ndarray
    geom: np.ndarray
    efc_address: np.ndarray
    friction: np.ndarray

    @classmethod
    def from_data(cls, d: mujoco.MjData) -> Contacts:
        c = d.contact
        return cls(
            pos=c.pos.copy(),
            frame=c.frame.reshape(-1, 3, 3).copy(),
            dim=c.dim.copy(),
            geom=c.geom.copy(),
            efc_address=c.efc_address.copy(),
            friction=c.friction.copy(),
        )


@dataclass(frozen=True)
class Constraints:
    """Every constraint impulse of one step, in MuJoCo's efc row order.

    efc_impulse: (nefc,) f and f_E of the paper — impulses, N·s (efc_force·h)
    efc_state:   (nefc,) mjtConstraintState: for contacts the Algorithm 5 branch
                 (QUADRATIC = sticking, CONE = sliding, SATISFIED = separating); friction loss
                 QUADRATIC inside the box, LINEARNEG/LINEARPOS at a bound; limits QUADRATIC
                 when pushing, SATISFIED otherwise; equality QUADRATIC
    efc_type:    (nefc,) mjtConstraint;  efc_id: (nefc,) owner (joint, dof, tendon, eq, contact)
    h:           the timestep the impulses accumulate over
    """

    efc_impulse: np.ndarray
    efc_state: np.ndarray
    efc_type: np.ndarray
    efc_id: np.ndarray
    contacts: Contacts
    h: float

    @property
    def efc_force(self) -> np.ndarray:
        """(nefc,) constraint forces in MuJoCo's units, N or N·m: impulse / h."""
        return self.efc_impulse / self.h

    def contact_impulse(self, i: int) -> np.ndarray:
        """(dim,) impulse of contact i in its frame: normal, tangential, torsional, rolling."""
        adr = self.contacts.efc_address[i]
        if adr < 0:
            return np.zeros(int(self.contacts.dim[i]))
        return self.efc_impulse[adr : adr + self.contacts.dim[i]]

    def contact_branch(self, i: int) -> Branch:
        """The Algorithm 5 branch of contact i (separating when excluded)."""
        adr = self.contacts.efc_address[i]
        return Branch.SEPARATING if adr < 0 else Branch(int(self.efc_state[adr]))

    def owner(self, m: mujoco.MjModel, row: int) -> str:
        """Human-readable owner of constraint row `row`, e.g. "limit joint 'knee'"."""
        what, obj = _OWNER_OF_TYPE[int(self.efc_type[row])]
        oid = int(self.efc_id[row])
        if obj is None:  # contact: the geom pair
            g1, g2 = self.contacts.geom[oid]
            names = [mujoco.mj_id2name(m, _OBJ.mjOBJ_GEOM, g) or f"#{g}" for g in (g1, g2)]
            return f"contact {names[0]!r}-{names[1]!r}"
        if obj == _OBJ.mjOBJ_DOF:
            oid, obj = int(m.dof_jntid[oid]), _OBJ.mjOBJ_JOINT
        name = mujoco.mj_id2name(m, obj, oid) or f"#{oid}"
        return f"{what} {obj.name.removeprefix('mjOBJ_').lower()} {name!r}"


@dataclass(frozen=True)
class ForwardResult:
    """Forward dynamics of one step: (q, v, u) → v' and the impulses that produced it.

    qacc: (nv,) discrete acceleration (v' − v)/h;  qvel_next: (nv,) v'
    iterations: solver iterations used;  converged: whether the solver met its tolerance
    """

    qacc: np.ndarray
    qvel_next: np.ndarray
    constraints: Constraints
    iterations: int
    converged: bool


@dataclass(frozen=True)
class InverseResult:
    """Inverse dynamics of one step: (q, v, v') → the forces that explain it.

    qfrc_inverse: (nv,) u of eq. 12 — every force that is not passive, bias or constraint
                  (actuators, applied forces), MuJoCo's qfrc_inverse
    """

    qfrc_inverse: np.ndarray
    constraints: Constraints
