"""The engine's public interface: forward and inverse dynamics on two paths.

    dyn = make_dynamics(model, path="native" | "reference", softness=None | Softness(...))
    fwd = dyn.forward(qpos, qvel, ctrl)        # (q, v, u) → v', impulses      (Section II)
    inv = dyn.inverse(qpos, qvel, qacc)        # (q, v, v') → u, impulses      (Section III)

qacc is the discrete acceleration (v' − v)/h of the Euler step. Each Dynamics object owns a
private copy of the model and one MjData, so use one object per thread. softness=None keeps the
model's own solref/solimp/impratio (the reference path then needs one softness for the whole
model: `Softness.of_model`); a Softness replaces them everywhere (paper Section V).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Literal

import mujoco
import numpy as np

from physics.errors import InvalidStateError, UnsupportedModelError
from physics.result import ForwardResult, InverseResult
from physics.softness import Softness

Path = Literal["native", "reference"]


class Dynamics(ABC):
    """State handling and model checks shared by both paths."""

    path: Path

    def __init__(self, model: mujoco.MjModel, softness: Softness | None = None) -> None:
        check_model(model, self.path)
        self.softness: Softness | None
        self.model = _copy_model(model)
        if softness is None:
            self.softness = Softness.of_model(self.model) if self.path == "reference" else None
        else:
            softness.apply(self.model)
            self.softness = softness
        self.data = mujoco.MjData(self.model)

    @property
    def h(self) -> float:
        return float(self.model.opt.timestep)

    @abstractmethod
    def forward(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        ctrl: np.ndarray | None = None,
        qfrc_applied: np.ndarray | None = None,
        *,
        warmstart: np.ndarray | None = None,
        iterations: int | None = None,
        tolerance: float | None = None,
    ) -> ForwardResult:
        """(q, v, u) → v' and the impulses of every constraint (Section II).

        warmstart: (nv,) a guess of qacc (e.g. the previous step's); iterations, tolerance:
        the solver's limits (None: the path's defaults).
        """

    @abstractmethod
    def inverse(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> InverseResult:
        """(q, v, qacc = (v' − v)/h) → u of eq. 12 and every impulse (Section III)."""

    def _set_state(self, **arrays: np.ndarray | None) -> None:
        """Copy validated arrays (qpos, qvel, qacc, ctrl, qfrc_applied) into MjData."""
        m, d = self.model, self.data
        sizes = {"qpos": m.nq, "qvel": m.nv, "qacc": m.nv, "ctrl": m.nu, "qfrc_applied": m.nv}
        for name, value in arrays.items():
            target = getattr(d, name)
            if value is None:
                target[:] = 0.0
                continue
            array = np.asarray(value, dtype=float)
            if array.shape != (sizes[name],):
                raise InvalidStateError(
                    f"{name} has shape {array.shape}, expected ({sizes[name]},) for this model"
                )
            bad = np.flatnonzero(~np.isfinite(array))
            if bad.size:
                raise InvalidStateError(
                    f"{name}[{bad[0]}] is {array[bad[0]]}: state must be finite "
                    f"({bad.size} non-finite entr{'y' if bad.size == 1 else 'ies'})"
                )
            target[:] = array


def check_model(m: mujoco.MjModel, path: Path) -> None:
    """Reject model options the analytic inverse (or parity with MuJoCo) cannot support."""
    opt = m.opt
    if opt.cone != mujoco.mjtCone.mjCONE_ELLIPTIC:
        raise UnsupportedModelError(
            'option cone="pyramidal": the analytic inverse needs elliptic friction cones '
            '(set <option cone="elliptic"/>)'
        )
    if opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        name = mujoco.mjtIntegrator(opt.integrator).name.removeprefix("mjINT_").lower()
        raise UnsupportedModelError(
            f'option integrator="{name}": the discrete-time dynamics of the paper are the '
            'semi-implicit Euler step (set <option integrator="Euler"/>)'
        )
    if opt.noslip_iterations > 0:
        raise UnsupportedModelError(
            f"option noslip_iterations={opt.noslip_iterations}: the noslip post-processing "
            "is not invertible (set it to 0)"
        )
    if opt.enableflags & mujoco.mjtEnableBit.mjENBL_OVERRIDE:
        raise UnsupportedModelError(
            "option flag override=enable replaces contact parameters; disable it"
        )
    if path == "reference":
        eulerdamp = not opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
        damped = np.flatnonzero(m.dof_damping > 0)
        if eulerdamp and damped.size:
            joint = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[damped[0]]))
            raise UnsupportedModelError(
                f"joint {joint!r} has damping {m.dof_damping[damped[0]]}: MuJoCo's Euler step "
                "applies implicit damping after the constraint solve, which the reference path "
                'does not model; use the native path or <flag eulerdamp="disable"/>'
            )


def _copy_model(m: mujoco.MjModel) -> mujoco.MjModel:
    import copy

    return copy.deepcopy(m)


def make_dynamics(
    model: mujoco.MjModel, path: Path = "native", softness: Softness | None = None
) -> Dynamics:
    """Forward/inverse dynamics of `model` on the native (MuJoCo C) or reference (paper) path."""
    from physics.native import NativeDynamics
    from physics.reference import ReferenceDynamics

    classes: dict[str, type[Dynamics]] = {
        "native": NativeDynamics,
        "reference": ReferenceDynamics,
    }
    if path not in classes:
        raise UnsupportedModelError(f"path={path!r}: expected one of {sorted(classes)}")
    return classes[path](model, softness)
