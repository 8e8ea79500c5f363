"""Sensor biases (IMU, force/torque) and the model-error offset: each bias dim a random walk.

    prior   b_0 / σ_0                        (`Problem.bias_prior`; a marginal prior from the
                                              knots before the window replaces it)
    walk    (b_{k+1} − b_k) / (σ_walk √h)     (`Problem.bias_walk`, per √s)

Both are linear in b, so their normal equations are exact: `add_normal_equations`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from estimator.problem import Problem


def step_sigma(p: Problem) -> np.ndarray:
    """(nb,) σ of one knot step's change, σ_walk √h."""
    return p.bias_walk * np.sqrt(p.h)


def cost(p: Problem, bias: np.ndarray, with_prior: bool = True) -> float:
    """½ Σ of the whitened prior (with_prior) and walk rows."""
    walk = (bias[1:] - bias[:-1]) / step_sigma(p)
    first = np.sum((bias[0] / p.bias_prior) ** 2) if with_prior else 0.0
    return 0.5 * float(first + np.sum(walk**2))


def rows(p: Problem, bias: np.ndarray) -> list[tuple[int, int | None, np.ndarray, np.ndarray]]:
    """(key_a, key_b, residual, σ) for the prior (key_b None) and each walk step."""
    sigma = step_sigma(p)
    out: list[tuple[int, int | None, np.ndarray, np.ndarray]] = [(0, None, bias[0], p.bias_prior)]
    out += [(k, k + 1, bias[k + 1] - bias[k], sigma) for k in range(p.T - 1)]
    return out


def add_normal_equations(
    p: Problem,
    bias: np.ndarray,
    diag: np.ndarray,
    lower: np.ndarray,
    g: np.ndarray,
    with_prior: bool,
    steps: int,
    first_step: int = 0,
) -> None:
    """H += JᵀJ and g += Jᵀr of the prior (with_prior) and the walk steps k → k + 1 for
    first_step ≤ k < steps, on the bias columns (after nv) of the key blocks diag (T, nz,
    nz), lower (T, nz, nz: key k + 1 against key k) and g (T, nz)."""
    b_ = slice(p.model.nv, p.nz)
    if with_prior:
        diag[0, b_, b_] += np.diag(p.bias_prior**-2.0)
        g[0, b_] += bias[0] / p.bias_prior**2
    W = np.diag(step_sigma(p) ** -2.0)
    k, n = first_step, steps
    step = (bias[k + 1 : n + 1] - bias[k:n]) @ W
    diag[k:n, b_, b_] += W
    diag[k + 1 : n + 1, b_, b_] += W
    lower[k:n, b_, b_] -= W
    g[k:n, b_] -= step
    g[k + 1 : n + 1, b_] += step
