"""Projection on a friction cone: the paper's Algorithm 5 (Section III-E).

Finds the x in the elliptic cone C = {x ∈ R^{d+1}: x_0 ≥ 0, x_0² ≥ Σ_j μ_j⁻² x_j²} that minimizes
Σ_k r_k (x_k − y_k)², where the weights r satisfy eq. 17 (μ_j² r_j = μ̂² r_0) because they are
built from (μ, r_0, r_F) by eq. 22.
"""

from __future__ import annotations

import enum

import numpy as np


class Branch(enum.IntEnum):
    """Which branch of Algorithm 5 produced x; values are MuJoCo's mjtConstraintState."""

    SEPARATING = 0  # x = 0, the tip of the cone          (mjCNSTRSTATE_SATISFIED)
    STICKING = 1  # x = y, strictly inside the cone         (mjCNSTRSTATE_QUADRATIC)
    SLIDING = 4  # x on the surface of the cone             (mjCNSTRSTATE_CONE)


def cone_weights(mu: np.ndarray, r0: float, rF: float) -> tuple[np.ndarray, float]:
    """Eq. 22: weights r = (r_0, r_1..r_d) and μ̂² from (μ_1..μ_d, r_0, r_F)."""
    inv_mu2 = 1.0 / (mu * mu)
    mean_inv_mu2 = inv_mu2.mean()
    r = np.empty(len(mu) + 1)
    r[0] = r0
    r[1:] = rF * inv_mu2 / mean_inv_mu2
    return r, rF / (r0 * mean_inv_mu2)


def cone_project(y: np.ndarray, mu: np.ndarray, r0: float, rF: float) -> tuple[np.ndarray, Branch]:
    """Algorithm 5: the R-weighted projection of y (d+1,) on the friction cone of μ (d,).

    Returns x (d+1,) and the branch taken. d = len(mu) ∈ {2, 3, 5} for MuJoCo condim 3, 4, 6
    (any d ≥ 1 works).
    """
    y0, yt = y[0], y[1:]
    # 1) y inside the friction cone: x = y
    if y0 >= 0 and y0 * y0 >= np.sum((yt / mu) ** 2):
        return y.copy(), Branch.STICKING
    # 2) no friction component: the nearest point is the tip
    if not np.any(yt):
        return np.zeros_like(y), Branch.SEPARATING
    # 3) r_j and μ̂² from eq. 22
    r, mu_hat2 = cone_weights(mu, r0, rF)
    # 4) ŷ_k = r_k^½ y_k, eq. 16
    sqrt_r = np.sqrt(r)
    yh = sqrt_r * y
    yh0, yht = yh[0], yh[1:]
    yht_norm2 = float(np.dot(yht, yht))
    if yh0 == 0:
        # 5) special case of eq. 20
        xh = np.empty_like(yh)
        xh[0] = np.sqrt(mu_hat2) / (1 + mu_hat2) * np.sqrt(yht_norm2)
        xh[1:] = mu_hat2 / (1 + mu_hat2) * yht
    else:
        # 6) the two surface points x̂± of eqs. 18-19
        beta = np.sqrt(yht_norm2 / (mu_hat2 * yh0 * yh0))
        candidates = []
        for s in (1.0, -1.0):
            denominator = 1 + s * mu_hat2 * beta
            if denominator == 0:  # λ⁻ → ∞: x̂⁻ → 0, already the tip candidate
                continue
            lam = (1 - s * beta) / denominator
            xh_s = np.empty_like(yh)
            xh_s[0] = yh0 / (1 + mu_hat2 * lam)
            xh_s[1:] = yht / (1 - lam)
            if xh_s[0] >= 0:
                candidates.append(xh_s)
        # 7) the optimal x̂ among {x̂+, x̂−, 0}: the feasible one closest to ŷ
        if not candidates:
            return np.zeros_like(y), Branch.SEPARATING
        xh = min(candidates, key=lambda c: float(np.sum((c - yh) ** 2)))
    # 8) invert eq. 16
    x = xh / sqrt_r
    return x, (Branch.SLIDING if np.any(x) else Branch.SEPARATING)
