"""Checks shared by the factor tests."""

from __future__ import annotations

import numpy as np

from estimator.problem import Problem, retract
from estimator.solver.linearize import Linearizer


def jacobian_error(
    problem: Problem, qpos: np.ndarray, bias: np.ndarray, k: int = 6
) -> tuple[np.ndarray, int]:
    """Every row of knot k (physics, prior, sensors, …) against central differences of
    q ⊕ x and b + δ: the error of each Jacobian entry relative to its row's scale, and the
    number of rows compared. Run with robust reweighting off (huber_k huge)."""
    lin = Linearizer(problem)

    def rows_at_k(q: np.ndarray, b: np.ndarray, jacobian: bool) -> tuple[np.ndarray, ...]:
        if jacobian:
            r, J = lin.jacobian(q, b)
            return r[k - 1], J[k - 1]
        blocks = lin.blocks(lin.terms(q, False), b)
        return np.concatenate([block.r[k - 1] for block in blocks]), None

    try:
        r0, J = rows_at_k(qpos, bias, True)
        nv, nz = problem.model.nv, problem.nz
        numeric = np.zeros_like(J)
        eps = 1e-7
        for i, key in enumerate(range(k - 1, k - 1 + lin.span)):
            for c in range(nz):
                rows = []
                for sign in (1.0, -1.0):
                    dx = np.zeros((problem.T, nv))
                    db = np.zeros((problem.T, problem.nb))
                    if c < nv:
                        dx[key, c] = sign * eps
                    else:
                        db[key, c - nv] = sign * eps
                    rows.append(rows_at_k(retract(problem.model, qpos, dx), bias + db, False)[0])
                numeric[:, i * nz + c] = (rows[0] - rows[1]) / (2 * eps)
    finally:
        lin.close()
    # mjd_inverseFD differentiates forward in its own finite steps: compare each row to its
    # own scale; sensors and the prior are analytic up to the sensors' finite differences
    scale = np.maximum(np.max(np.abs(numeric), axis=1, keepdims=True), 1.0)
    error = np.abs(J - numeric) / scale
    return error, len(r0)
