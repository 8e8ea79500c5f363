"""The contact-space problem (11) and its generalized projected Gauss–Seidel solver (GPGS).

    min_{f: φ(f) ≥ 0}  ½ fᵀ(A + R) f + fᵀ(v⁻ − v*)                                    (11)

Objects are visited in row order. A scalar object (friction loss: box, limit or frictionless
contact: f ≥ 0) is minimized exactly, as in classic PGS. A frictional contact takes one
projected-gradient step in the metric t·R_b, whose projection is Algorithm 5 (R_b satisfies
eq. 17 and the scale t does not move the projection):

    f_b ← ConeProject(f_b − (t R_b)⁻¹ g_b),   g_b = ((A + R) f + v⁻ − v*)_b,
    t = λ_max(R_b^-½ (A + R)_bb R_b^-½)      (so t·R_b ⪰ (A + R)_bb: every step lowers (11))

Each step decreases the strictly convex objective and the constraints separate by object, so
the sweeps converge to the unique minimizer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics.cone import cone_project
from physics.constraints import ConstraintObject, Kind


@dataclass(frozen=True)
class SolverStats:
    iterations: int
    converged: bool
    max_change: float  # ‖Δf‖∞ / max(‖f‖∞, tiny) in the last sweep


def solve_gpgs(
    A: np.ndarray,
    v_minus: np.ndarray,
    vstar: np.ndarray,
    R: np.ndarray,
    eta: np.ndarray,
    objects: tuple[ConstraintObject, ...],
    iterations: int,
    tolerance: float = 0.0,
    f0: np.ndarray | None = None,
) -> tuple[np.ndarray, SolverStats]:
    """Solve (11) for f (n,). A (n, n) = J M̂⁻¹ Jᵀ; v_minus, vstar, R, eta (n,).

    `objects` index rows of these arrays (no equality objects). Runs at most `iterations`
    sweeps and stops early once the relative change of f in a sweep is ≤ `tolerance`.
    """
    H = A + np.diag(R)
    b = v_minus - vstar
    f = np.zeros(len(b)) if f0 is None else f0.copy()
    blocks = [_Block(obj, H, R) for obj in objects]
    change = np.inf
    for sweep in range(1, iterations + 1):
        largest_step = 0.0
        for block in blocks:
            rows = block.rows
            g = H[rows] @ f + b[rows]
            old = f[rows].copy()
            if block.kind == Kind.CONTACT:
                y = old - g / (block.t * block.r)
                new, _ = cone_project(y, block.mu, block.r[0], block.rF)
            else:
                new = old - g / block.Hii
                if block.kind == Kind.FRICTION:
                    new = np.clip(new, -eta[rows], eta[rows])
                else:
                    new = np.maximum(new, 0.0)
            f[rows] = new
            largest_step = max(largest_step, float(np.max(np.abs(new - old))))
        scale = float(np.max(np.abs(f))) if len(f) else 0.0
        change = largest_step / scale if scale > 0 else largest_step
        if change <= tolerance:
            return f, SolverStats(sweep, True, change)
    return f, SolverStats(iterations, False, change)


class _Block:
    """Per-object constants of a GPGS sweep."""

    __slots__ = ("Hii", "kind", "mu", "r", "rF", "rows", "t")

    def __init__(self, obj: ConstraintObject, H: np.ndarray, R: np.ndarray) -> None:
        self.kind = obj.kind
        self.rows = obj.rows
        self.mu = obj.mu
        if obj.kind == Kind.CONTACT:
            self.r = R[obj.rows]
            self.rF = float(self.r[1:].mean())
            s = 1.0 / np.sqrt(self.r)
            self.t = float(np.linalg.eigvalsh(s[:, None] * H[obj.rows, obj.rows] * s)[-1])
        else:
            self.Hii = H[obj.start, obj.start]
