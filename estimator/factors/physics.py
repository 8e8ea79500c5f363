"""The physics factor: the analytic inverse dynamics against the known generalized force.

    r_k = W (u(q_k, v_k, a_k) − u_known_k − e_k)     W = diag(1/σ), 0 where nothing is known

u: MuJoCo's inverse (`mj_inverse`, the paper's eq. 12); u_known: zero on unactuated dofs, the
commands through the model's actuators at the knot's state, or the measured efforts
(`Problem.u_known`); e_k: the model-error offset on the unactuated dofs (a bias random walk,
when `model_error_std` > 0). A knot's rows share one robust kernel (`physics_kernel`), its
threshold scaled by √(known rows): an impact or an unmodeled contact stops pulling the motion.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimator.factors.base import MODEL_ERROR, Block, Terms
from estimator.factors.robust import weighted

if TYPE_CHECKING:
    from estimator.problem import Problem


def rows(p: Problem, t: Terms, bias: np.ndarray, robust: bool = True) -> Block:
    K = p.T - 2
    sigma = p.physics_sigma[1:-1]
    known = np.isfinite(sigma)
    w = np.where(known, 1.0 / np.where(known, sigma, 1.0), 0.0)
    r = np.nan_to_num((t.u - t.known) * w)
    J = t.Ju * w[:, :, None] if t.Ju is not None else None
    J_offset = None
    if p.error_dofs.size:  # u − u_known − e_k on the unactuated dofs
        dofs, cols = p.error_dofs, p.bias_of[MODEL_ERROR]
        r[:, dofs] -= bias[1:-1, cols] * w[:, dofs]
        if t.Ju is not None:
            J_offset = np.zeros((K, p.model.nv, p.nb))
            J_offset[:, dofs, np.arange(cols.start, cols.stop)] = -w[:, dofs]
    block = Block("physics", r, J, np.zeros(K), known, J_offset)
    scale = np.sqrt(np.maximum(known.sum(axis=1), 1))  # a knot's norm over n rows is ≈ √n
    return weighted(block, p.settings.physics_kernel, p.settings.huber_k, robust, scale)
