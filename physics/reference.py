"""The reference path: the paper's Phase II written in numpy on MuJoCo's Phase I.

Forward (Section II):  soft Gauss principle for equality constraints (eqs. 6-7), the
contact-space problem (8)-(11) solved by GPGS, next-step velocity by eq. 6, f_E by eq. 13.
Inverse (Section III): impulses by Theorems 2 and 4, control force by eq. 12 — no inertia
matrix, no factorization, no A.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.linalg import cho_factor, cho_solve

from physics.constraints import ConstraintSpace, constraint_space
from physics.dynamics import Dynamics, Path
from physics.inverse import impulses
from physics.result import Constraints, Contacts, ForwardResult, InverseResult
from physics.softness import Softness
from physics.solver import solve_gpgs


class ReferenceDynamics(Dynamics):
    path: Path = "reference"

    @property
    def paper_softness(self) -> Softness:
        """The one softness of the model (Dynamics takes the model's own when given none)."""
        assert self.softness is not None
        return self.softness

    def forward(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        ctrl: np.ndarray | None = None,
        qfrc_applied: np.ndarray | None = None,
        *,
        warmstart: np.ndarray | None = None,
        iterations: int | None = None,
        tolerance: float | None = None,
    ) -> ForwardResult:
        """Forward dynamics by at most `iterations` GPGS sweeps (default 1000), stopping once the
        inverse-consistency residual is ≤ `tolerance` (default 1e-12; 0 runs every sweep).
        A warm start qacc gives the first impulses by Theorem 4 at v' = v + h·qacc."""
        iterations = 1000 if iterations is None else iterations
        tolerance = 1e-12 if tolerance is None else tolerance
        m, d, h = self.model, self.data, self.h
        self._set_state(qpos=qpos, qvel=qvel, ctrl=ctrl, qfrc_applied=qfrc_applied)
        # Phase I (MuJoCo): kinematics, CRB + LDL, collision, Jacobians; RNE bias; actuation
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fwdVelocity(m, d)
        mujoco.mj_fwdActuation(m, d)
        space = constraint_space(m, d, self.paper_softness)
        v = d.qvel.copy()
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        tau = d.qfrc_passive + d.qfrc_actuator + d.qfrc_applied - d.qfrc_bias  # p + u − c

        # eq. 7: M̂ = M + J_Eᵀ R_E⁻¹ J_E,  v̂ = v + M̂⁻¹((p + u − c) h + J_Eᵀ R_E⁻¹ (v*_E − J_E v))
        E, C = slice(0, space.ne), slice(space.ne, space.nefc)
        J_E, R_E, vstar_E = space.J[E], space.R[E], space.vstar[E]
        Mhat = cho_factor(M + J_E.T @ (J_E / R_E[:, None]))
        vhat = v + cho_solve(Mhat, tau * h + J_E.T @ ((vstar_E - J_E @ v) / R_E))

        # eq. 8: A = J M̂⁻¹ Jᵀ, v⁻ = J v̂; eq. 11 by GPGS
        J = space.J[C]
        MinvJT = cho_solve(Mhat, J.T) if J.size else np.zeros((m.nv, 0))
        f0 = None
        if warmstart is not None:
            f0 = impulses(space, v + h * np.asarray(warmstart, dtype=float))[0][C]
        f, stats = solve_gpgs(
            J @ MinvJT,
            J @ vhat,
            space.vstar[C],
            space.R[C],
            space.eta[C],
            space.contact_objects(),
            iterations,
            tolerance,
            f0,
        )
        # eq. 6: v' = v̂ + M̂⁻¹ Jᵀ f;  eq. 13: f_E = R_E⁻¹ (v*_E − J_E v')
        v_next = vhat + MinvJT @ f
        efc_impulse = np.empty(space.nefc)
        efc_impulse[C] = f
        efc_impulse[E] = (vstar_E - J_E @ v_next) / R_E
        _, state = impulses(space, v_next)  # each object's branch at the solution
        return ForwardResult(
            qacc=(v_next - v) / h,
            qvel_next=v_next,
            constraints=self._constraints(space, efc_impulse, state),
            iterations=stats.iterations,
            converged=stats.converged,
        )

    def inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> InverseResult:
        m, d, h = self.model, self.data, self.h
        self._set_state(qpos=qpos, qvel=qvel, qacc=qacc)
        # Phase I without the inertia matrix: kinematics, collision, Jacobians, velocities
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_tendon(m, d)
        mujoco.mj_collision(m, d)
        mujoco.mj_makeConstraint(m, d)
        mujoco.mj_comVel(m, d)
        mujoco.mj_passive(m, d)
        space = constraint_space(m, d, self.paper_softness)

        # Theorems 2 and 4 at v' = v + h·qacc
        efc_impulse, state = impulses(space, d.qvel + h * d.qacc)

        # eq. 12: u = RNE(q, v, v̇) + D v̇ − p − (Jᵀ f + J_Eᵀ f_E)/h,  D = armature
        rne = np.zeros(m.nv)
        mujoco.mj_rne(m, d, 1, rne)
        qfrc = rne + m.dof_armature * d.qacc - d.qfrc_passive - space.J.T @ efc_impulse / h
        return InverseResult(qfrc, self._constraints(space, efc_impulse, state))

    def _constraints(
        self, space: ConstraintSpace, efc_impulse: np.ndarray, state: np.ndarray
    ) -> Constraints:
        return Constraints(
            efc_impulse=efc_impulse,
            efc_state=state,
            efc_type=space.efc_type,
            efc_id=space.efc_id,
            contacts=Contacts.from_data(self.data),
            h=space.h,
        )
