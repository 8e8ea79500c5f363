"""Motion priors on the finite-difference accelerations a_k = (v_{k+1} − v_k)/h.

    acceleration prior   a_k / σ_a                          weak, on every dof
    jerk prior           (a_{k+1} − a_k) / (h σ_j)          constant acceleration, on
                                                            (z_{k−1} … z_{k+2}); robust per
                                                            dof (`jerk_kernel`: impacts pass)

Their Jacobians are dofwise: a_k's row d reaches only d's group (itself; a rotation's 3).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimator.factors.base import Block, Terms
from estimator.factors.robust import weighted

if TYPE_CHECKING:
    from estimator.problem import Problem


def acceleration_prior(p: Problem, t: Terms) -> Block:
    sa = p.settings.accel_prior_std
    r = t.a / sa
    J = t.da / sa if t.da is not None else None
    cost = 0.5 * np.sum(r**2, axis=1)
    return Block("prior", r, J, cost, np.ones(r.shape, bool), dofwise=True)


def jerk_prior(p: Problem, t: Terms, robust: bool = True) -> Block:
    K = p.T - 2
    sj = p.h * p.settings.jerk_prior_std
    r = np.zeros_like(t.a)
    r[:-1] = (t.a[1:] - t.a[:-1]) / sj
    J = None
    if t.da is not None:  # by key and dof group, as da
        J = np.zeros((K, 4, *t.da.shape[2:]))
        J[:-1, :3] -= t.da[:-1] / sj
        J[:-1, 1:] += t.da[1:] / sj
    valid = np.ones(r.shape, bool)
    valid[-1] = False
    block = Block("jerk prior", r, J, np.zeros(K), valid, dofwise=True)
    kernel = p.settings.jerk_robust_kernel
    if kernel == "none":
        block.cost = 0.5 * np.sum(r**2, axis=1)
        return block
    return weighted(block, kernel, p.settings.huber_k, robust, group=1)  # per dof
