"""The contact-space problem (11) and its generalized projected Gauss–Seidel solver (GPGS).

    min_{f: φ(f) ≥ 0}  ½ fᵀ(A + R) f + fᵀ(v⁻ − v*)                                    (11)

Objects are visited in row order; each update minimizes (11) over one object's rows with the
others fixed. With H = A + R and c_b = (H f + v⁻ − v*)_b − H_bb f_b the rest of the gradient:

- scalar objects (friction loss: box; limit, frictionless contact: f ≥ 0) as in classic PGS:
  f_i ← clamp(−c_i / H_ii);
- a frictional contact, exactly when the block minimizer is sticking or separating:
  x = −H_bb⁻¹ c_b if x lies inside the cone, else 0 if c_b lies in the dual cone
  {s: s_0 ≥ ‖(μ_j s_j)‖}; otherwise (sliding) projected-gradient steps in the metric t·R_b,
  whose projection is Algorithm 5 (R_b satisfies eq. 17; the scale t does not move it):
      f_b ← ConeProject(f_b − (t R_b)⁻¹ g_b),   t = λ_max(R_b^-½ H_bb R_b^-½),
  so that t·R_b ⪰ H_bb and every step lowers (11).

Every update lowers the strictly convex objective and the constraints separate by object, so
the sweeps converge to the unique minimizer.

Stopping rule, from Theorems 3-4: f solves (11) exactly when the analytic inverse of the step it
produces returns f, i.e. when f = Π(R⁻¹(v* − v⁻ − A f)). The relative size of that difference is
the residual checked against `tolerance` after every sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physics.cone import cone_project
from physics.constraints import ConstraintObject, Kind
from physics.inverse import project


@dataclass(frozen=True)
class SolverStats:
    iterations: int
    converged: bool
    residual: float  # ‖f − Π(R⁻¹(v* − v⁻ − A f))‖∞ / ‖f‖∞ after the last sweep


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
    residual = np.inf
    for sweep in range(1, iterations + 1):
        for block in blocks:
            rows = block.rows
            g = H[rows] @ f + b[rows]
            if block.kind == Kind.CONTACT:
                f[rows] = block.minimize(g - block.H @ f[rows], f[rows].copy())
            elif block.kind == Kind.FRICTION:
                f[rows] = np.clip(f[rows] - g / block.Hii, -eta[rows], eta[rows])
            else:
                f[rows] = np.maximum(f[rows] - g / block.Hii, 0.0)
        if tolerance > 0:
            f_inverse, _ = project(-(A @ f + b) / R, R, eta, objects)
            scale = float(np.max(np.abs(f))) if len(f) else 0.0
            residual = float(np.max(np.abs(f - f_inverse), initial=0.0)) / max(scale, 1e-300)
            if residual <= tolerance:
                return f, SolverStats(sweep, True, residual)
    return f, SolverStats(iterations, False, residual)


class _Block:
    """Per-object constants of a GPGS sweep and the contact block update."""

    __slots__ = ("H", "H_inv", "Hii", "kind", "mu", "r", "rF", "rows", "t")

    SLIDING_STEPS = 4  # projected-gradient steps per sweep for a sliding contact

    def __init__(self, obj: ConstraintObject, H: np.ndarray, R: np.ndarray) -> None:
        self.kind = obj.kind
        self.rows = obj.rows
        self.mu = obj.mu
        if obj.kind == Kind.CONTACT:
            self.H = H[obj.rows, obj.rows]
            self.H_inv = np.linalg.inv(self.H)
            self.r = R[obj.rows]
            self.rF = float(self.r[1:].mean())
            s = 1.0 / np.sqrt(self.r)
            self.t = float(np.linalg.eigvalsh(s[:, None] * self.H * s)[-1])
        else:
            self.Hii = H[obj.start, obj.start]

    def minimize(self, c: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Lower ½ xᵀ H_bb x + xᵀ c over the cone, starting from x (exact unless sliding)."""
        mu = self.mu
        x_free = -self.H_inv @ c
        if x_free[0] >= 0 and x_free[0] ** 2 >= np.sum((x_free[1:] / mu) ** 2):
            return x_free  # sticking
        if c[0] >= 0 and c[0] ** 2 >= np.sum((mu * c[1:]) ** 2):
            return np.zeros_like(x)  # separating: 0 satisfies the KKT conditions
        step = 1.0 / (self.t * self.r)
        for _ in range(self.SLIDING_STEPS):
            x, _ = cone_project(x - step * (self.H @ x + c), mu, self.r[0], self.rF)
        return x
