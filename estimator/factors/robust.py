"""Robust kernels (GTSAM's mEstimators, vectorized) and their weighting of a factor's rows.

A kernel acts on the norm n of each element's whitened rows at a knot (a marker's 3, a
joint's 1, a knot's physics rows together): the cost is ρ(n), and the rows are scaled by
√w(n), so that Gauss–Newton on the scaled rows is iteratively reweighted least squares.
"""

from __future__ import annotations

import numpy as np

from estimator.factors.base import Block


def huber(norm: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's mEstimator.Huber, vectorized: loss ρ(n) (½n² within k, k(n − k/2) beyond) and
    weight w(n) = min(1, k/n), so that √w scales a block's rows."""
    inside = norm <= k
    loss = np.where(inside, 0.5 * norm**2, k * (norm - 0.5 * k))
    weight = np.where(inside, 1.0, k / np.where(inside, 1.0, norm))
    return loss, weight


def cauchy(norm: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's mEstimator.Cauchy, vectorized: ρ(n) = ½k² log(1 + n²/k²), w(n) = k²/(k² + n²)
    (redescending: a residual far beyond k stops pulling)."""
    return 0.5 * k**2 * np.log1p((norm / k) ** 2), k**2 / (k**2 + norm**2)


KERNELS = {"huber": huber, "cauchy": cauchy}


def weighted(
    block: Block,
    kernel: str,
    k: float,
    robust: bool = True,
    scale: np.ndarray | float = 1.0,
    group: int = 0,
) -> Block:
    """`block` with its robust cost, and (robust) its rows and Jacobians scaled by √w: the
    kernel on the norm of each element's rows (`group` rows each; 0: the whole block) per
    knot, its threshold k scaled by `scale`."""
    K, m = block.r.shape
    g = group or m
    norm = np.linalg.norm(block.r.reshape(K, m // g, g), axis=2) / np.reshape(scale, (-1, 1))
    loss, weight = KERNELS[kernel](norm, k)
    block.cost = loss.sum(axis=1) * np.square(scale)
    if robust:
        root = np.repeat(np.sqrt(weight), g, axis=1)
        block.r = block.r * root
        if block.J is not None:
            block.J *= root[:, None, :, None] if block.dofwise else root[:, :, None]
        if block.J_bias is not None:
            block.J_bias *= root[:, :, None]
    return block
