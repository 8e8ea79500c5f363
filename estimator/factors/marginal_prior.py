"""The marginal prior: what the knots before a window said about its first keys, the others
marginalized (a Schur complement of their normal equations; `estimator.solver.window`).

    ½ (δ − δ̂)ᵀ Λ (δ − δ̂)        δ = (q_k ⊖ q̄_k, b_k − b̄_k) over the first n keys
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


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

    @classmethod
    def start_pose(
        cls,
        model: mujoco.MjModel,
        qpos: np.ndarray,
        bias: np.ndarray,
        bias_prior: np.ndarray,
        position_std: float,
        yaw_std: float,
    ) -> MarginalPrior:
        """The start pose where proprioception cannot see it, as the first window's prior on
        its first key: the free base's x, y (σ position_std) and yaw (σ yaw_std) held at
        qpos[0], b_0 at its prior (σ bias_prior), every other direction free. The sweep's
        marginalization carries it on: what x, y and yaw are not observed, their σ grows.

        yaw: the rotation about world z; a free joint's rotation dofs are body axes, where z
        is Rᵀ e_z."""
        nv = model.nv
        nz = nv + len(bias_prior)
        j = next(j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
        dof, adr = int(model.jnt_dofadr[j]), int(model.jnt_qposadr[j])
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, qpos[0, adr + 3 : adr + 7])
        axis = R.reshape(3, 3).T @ np.array([0.0, 0.0, 1.0])
        info = np.zeros((nz, nz))
        info[dof, dof] = info[dof + 1, dof + 1] = position_std**-2
        info[dof + 3 : dof + 6, dof + 3 : dof + 6] = np.outer(axis, axis) * yaw_std**-2
        info[nv:, nv:] = np.diag(bias_prior**-2.0)
        return cls(qpos[:1].copy(), bias[:1].copy(), info, np.zeros(nz), np.zeros((0, nz)))
