"""The native path: the same interface backed by MuJoCo's C engine (mj_forward, mj_inverse).

Forward runs MuJoCo's configured solver (Newton by default; PGS for the paper's timing).
Inverse runs mj_inverse with mjENBL_INVDISCRETE, consistent with the discrete-time step.
"""

from __future__ import annotations

import mujoco
import numpy as np

from physics.dynamics import Dynamics, Path
from physics.errors import UnsupportedModelError
from physics.result import Constraints, Contacts, ForwardResult, InverseResult
from physics.softness import Softness


def use_discrete_inverse(model: mujoco.MjModel) -> None:
    """mj_inverse and mjd_inverseFD as the inverse of the Euler step, its implicit damping
    included (mjENBL_INVDISCRETE): the one place the flag is set, for this path and for the
    estimator's own calls at the knots."""
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_INVDISCRETE


class NativeDynamics(Dynamics):
    path: Path = "native"

    def __init__(self, model: mujoco.MjModel, softness: Softness | None = None) -> None:
        super().__init__(model, softness)
        if self.softness is not None and self.softness.r_min != mujoco.mjMINVAL:
            raise UnsupportedModelError(
                f"softness r_min={self.softness.r_min}: MuJoCo's C engine floors R at "
                f"mjMINVAL={mujoco.mjMINVAL} only; use the reference path for another r_min"
            )
        use_discrete_inverse(self.model)
        self._jar = np.zeros(0)

    def set_solver(self, solver: str, iterations: int, tolerance: float) -> None:
        """Choose MuJoCo's forward solver ("newton", "cg", "pgs") and its stopping rule."""
        names = {
            "newton": mujoco.mjtSolver.mjSOL_NEWTON,
            "cg": mujoco.mjtSolver.mjSOL_CG,
            "pgs": mujoco.mjtSolver.mjSOL_PGS,
        }
        if solver not in names:
            raise UnsupportedModelError(f"solver={solver!r}: expected one of {sorted(names)}")
        self.model.opt.solver = names[solver]
        self.model.opt.iterations = iterations
        self.model.opt.tolerance = tolerance
        self.data = mujoco.MjData(self.model)  # dual solvers need extra efc arrays

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
        """mj_forward with the solver chosen by `set_solver` (MuJoCo's Newton by default).

        warmstart: (nv,) initial guess for qacc (e.g. the previous step's or a previous
        solve's); MuJoCo's Newton can stop early from a poor guess, restarting it from its own
        answer converges it to machine precision. iterations, tolerance: override the model's
        opt.iterations / opt.tolerance for this and later calls.
        """
        m, d, h = self.model, self.data, self.h
        if iterations is not None:
            m.opt.iterations = iterations
        if tolerance is not None:
            m.opt.tolerance = tolerance
        self._set_state(qpos=qpos, qvel=qvel, ctrl=ctrl, qfrc_applied=qfrc_applied)
        d.qacc_warmstart[:] = 0.0 if warmstart is None else warmstart
        mujoco.mj_forward(m, d)
        iterations = int(d.solver_niter[0])
        converged = iterations < m.opt.iterations
        qacc = d.qacc.copy()
        return ForwardResult(
            qacc=qacc,
            qvel_next=d.qvel + h * qacc,
            constraints=self._constraints(states_from_qacc=True),
            iterations=iterations,
            converged=converged,
        )

    def inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> InverseResult:
        m, d = self.model, self.data
        self._set_state(qpos=qpos, qvel=qvel, qacc=qacc)
        mujoco.mj_inverse(m, d)
        return InverseResult(d.qfrc_inverse.copy(), self._constraints(states_from_qacc=False))

    def _constraints(self, states_from_qacc: bool) -> Constraints:
        """Copy MuJoCo's efc arrays. After a forward solve, classify each row at the solution
        with mj_constraintUpdate (the dual PGS solver leaves efc_state unset)."""
        m, d = self.model, self.data
        nefc = d.nefc
        efc_force = d.efc_force[:nefc].copy()
        if states_from_qacc and nefc:
            jar = np.zeros(nefc)
            mujoco.mj_mulJacVec(m, d, jar, d.qacc)
            jar -= d.efc_aref[:nefc]
            cost = np.zeros(1)
            mujoco.mj_constraintUpdate(m, d, jar, cost, 0)
            d.efc_force[:nefc] = efc_force  # keep the solver's forces
        return Constraints(
            efc_impulse=efc_force * self.h,
            efc_state=d.efc_state[:nefc].copy(),
            efc_type=d.efc_type[:nefc].copy(),
            efc_id=d.efc_id[:nefc].copy(),
            contacts=Contacts.from_data(d),
            h=self.h,
        )
