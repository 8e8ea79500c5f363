"""The result of estimation: motion, forces, biases, uncertainty and residuals on a time grid."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from physics.result import Constraints


@dataclass(frozen=True)
class Estimate:
    """A smoothed trajectory on a uniform grid of T knots (step h).

    t_ns:          (T,) int64 knot times, ns
    qpos:          (T, nq) configuration (MuJoCo layout; quaternions w, x, y, z)
    qvel:          (T, nv) v_k = (q_k ⊖ q_{k−1})/h, the velocity the inverse dynamics see
                   (v_0 = v_1)
    qacc:          (T, nv) a_k = (v_{k+1} − v_k)/h (0 at the last knot)
    qfrc_inverse:  (T, nv) u of eq. 12 from the analytic inverse at (q_k, v_k, a_k)
    qfrc_known:    (T, nv) the generalized force the logged commands produce through the
                   actuators (NaN on dofs with no known force)
    qpos_std:      (T, nv) marginal standard deviation of q_k in MuJoCo's tangent space
                   (free joint: world position m, body-frame rotation rad; hinge rad; slide m)
    constraints:   T entries: every contact/constraint impulse at knot k (physics.result);
                   the contacts' balanced against the known forces (settings.contact_forces;
                   estimator.contact_forces), so qfrc_inverse is the model's u, before that
    imu_bias:      stream name → (T, 6) accelerometer bias (m/s²) then gyro bias (rad/s)
    model_error:   unactuated dof ("root_z") → (T,) the generalized force offset e_k that the
                   model needed to explain the motion (N or N·m; the setting model_error_std)
    residuals:     factor type ("physics", a stream name, …) → (T, k) whitened residuals
                   at each knot (NaN where the knot has no such factor)
    residual_labels: factor type → (k,) what each row is: "torso_site position z" (a
                   sensor's element and component), "root_z" (physics and priors: the dof)
    cost_by_type:  factor type → its robust cost at this trajectory
    model_name:    the model the estimate belongs to (bundled name or MJCF path)
    """

    t_ns: np.ndarray
    h: float
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    qfrc_inverse: np.ndarray
    qfrc_known: np.ndarray
    qpos_std: np.ndarray
    constraints: tuple[Constraints, ...]
    model_name: str
    imu_bias: dict[str, np.ndarray] = field(default_factory=dict)
    model_error: dict[str, np.ndarray] = field(default_factory=dict)
    residuals: dict[str, np.ndarray] = field(default_factory=dict)
    residual_labels: dict[str, list[str]] = field(default_factory=dict)
    cost_by_type: dict[str, float] = field(default_factory=dict)

    @property
    def T(self) -> int:
        return len(self.t_ns)

    def at(self, knots: slice) -> Estimate:
        """The estimate at some of its knots (its residual rows with them; costs as they were:
        over all its knots)."""
        return replace(
            self,
            t_ns=self.t_ns[knots],
            qpos=self.qpos[knots],
            qvel=self.qvel[knots],
            qacc=self.qacc[knots],
            qfrc_inverse=self.qfrc_inverse[knots],
            qfrc_known=self.qfrc_known[knots],
            qpos_std=self.qpos_std[knots],
            constraints=tuple(self.constraints[knots]),
            imu_bias={name: b[knots] for name, b in self.imu_bias.items()},
            model_error={name: e[knots] for name, e in self.model_error.items()},
            residuals={name: r[knots] for name, r in self.residuals.items()},
        )
