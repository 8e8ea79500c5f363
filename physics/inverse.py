"""The analytic inverse of Section III: impulses from Theorems 2 and 4.

Given the next-step constraint velocity J v', every object's impulse follows from its own rows:

    y = R⁻¹ (v* − J v')                                              (15)
    equality:  f_E = y                                               (13)
    friction:  f = max(−η, min(η, y))                                (Theorem 4)
    limit:     f = max(0, y)
    contact:   f = ConeProject(y)                                    (Algorithm 5)
"""

from __future__ import annotations

import mujoco
import numpy as np

from physics.cone import Branch, cone_project
from physics.constraints import ConstraintObject, ConstraintSpace, Kind

_S = mujoco.mjtConstraintState


def impulses(space: ConstraintSpace, qvel_next: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Impulses f (nefc,) that explain next-step velocity v' (nv,), and each row's state.

    States are mjtConstraintState values; for contacts the Algorithm 5 branch.
    """
    y = (space.vstar - space.J @ qvel_next) / space.R
    return project(y, space.R, space.eta, space.objects)


def project(
    y: np.ndarray, R: np.ndarray, eta: np.ndarray, objects: tuple[ConstraintObject, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Theorem 4 object by object: the R-weighted projection of y (n,) on {f: φ(f) ≥ 0}."""
    f = np.empty_like(y)
    state = np.empty(len(y), dtype=np.int32)
    for obj in objects:
        i, rows = obj.start, obj.rows
        if obj.kind == Kind.EQUALITY:
            f[i] = y[i]
            state[i] = _S.mjCNSTRSTATE_QUADRATIC
        elif obj.kind == Kind.FRICTION:
            bound = eta[i]
            f[i] = max(-bound, min(bound, y[i]))
            # MuJoCo names the bound by the sign of J a − a_ref = −R y / h
            state[i] = (
                _S.mjCNSTRSTATE_LINEARNEG
                if y[i] >= bound
                else _S.mjCNSTRSTATE_LINEARPOS
                if y[i] <= -bound
                else _S.mjCNSTRSTATE_QUADRATIC
            )
        elif obj.kind == Kind.LIMIT:
            f[i] = max(0.0, y[i])
            state[i] = _S.mjCNSTRSTATE_QUADRATIC if y[i] > 0 else _S.mjCNSTRSTATE_SATISFIED
        else:
            r = R[rows]
            f[rows], branch = cone_project(y[rows], obj.mu, r[0], float(r[1:].mean()))
            state[rows] = int(branch)
    return f, state


__all__ = ["Branch", "impulses", "project"]
