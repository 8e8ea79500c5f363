"""The generalized force of the logged commands at a knot's state: MuJoCo's own actuation.

A position actuator pushes with kp (ctrl − q) − kv v, a velocity actuator with kv (ctrl − v):
the force of a command depends on the state, so it is computed at each knot's (q, v) by
`mj_fwdActuation` with the commands in `ctrl` (ctrlrange and forcerange clamping included).
Every actuator without activation dynamics (dyntype none) whose gain and bias are affine
(motor, position, velocity, general with gaintype fixed/affine and biastype none/affine) is
supported. Per actuator i, with length l_i = moment_i·q (locally) and velocity l̇_i = moment_i·v:

    force_i = gain_i ctrl_i + bias_i,   gain_i = g0 + g1 l + g2 l̇,   bias_i = b0 + b1 l + b2 l̇
    qfrc     = Σ_i moment_iᵀ force_i                   (over the actuators with a command)
    ∂qfrc/∂q = Σ_i moment_iᵀ (g1 ctrl_i + b1) moment_i
    ∂qfrc/∂v = Σ_i moment_iᵀ (g2 ctrl_i + b2) moment_i

(0 for an actuator clamped at its forcerange; the change of the moment arm with q, zero for
joint transmissions, is left out.) A joint with an actuatorfrcrange clamps the sum on its dof,
as MuJoCo clamps qfrc_actuator (a clamped dof's derivatives are 0).
"""

from __future__ import annotations

from collections.abc import Iterable

import mujoco
import numpy as np

from estimator.errors import ConfigError

_GAIN = mujoco.mjtGain
_BIAS = mujoco.mjtBias
_DYN = mujoco.mjtDyn


def actuator_kind(model: mujoco.MjModel, i: int) -> str:
    """A name for actuator i's kind as MJCF writes it: motor, position, velocity or general."""
    gain, bias = model.actuator_gaintype[i], model.actuator_biastype[i]
    g, b = model.actuator_gainprm[i, :3], model.actuator_biasprm[i, :3]
    if model.actuator_dyntype[i] != _DYN.mjDYN_NONE:
        return "general"
    if gain == _GAIN.mjGAIN_FIXED and bias == _BIAS.mjBIAS_NONE:
        return "motor"
    if gain == _GAIN.mjGAIN_FIXED and bias == _BIAS.mjBIAS_AFFINE and b[0] == 0:
        if b[1] == -g[0] and b[1] != 0:
            return "position"
        if b[1] == 0 and b[2] == -g[0] and b[2] != 0:
            return "velocity"
    return "general"


def unsupported_reason(model: mujoco.MjModel, i: int) -> str | None:
    """Why a command through actuator i cannot be turned into a force at a state (None: it can)."""
    if model.actuator_ctrlnum[i] != 1 or model.actuator_ctrladr[i] != i:
        return "it takes several controls (ctrlnum > 1), which a command stream does not give"
    if model.actuator_delay[i] > 0:
        return (
            f"MuJoCo delays its control by {model.actuator_delay[i]:g} s; give the command "
            "stream's time_offset_ns instead and remove the delay from the model"
        )
    dyn = int(model.actuator_dyntype[i])
    if dyn != _DYN.mjDYN_NONE.value:
        name = _DYN(dyn).name.removeprefix("mjDYN_").lower()
        return (
            f"it has activation dynamics (dyntype={name}): its force follows an activation "
            "state that the log does not carry and the estimator does not estimate"
        )
    gain, bias = int(model.actuator_gaintype[i]), int(model.actuator_biastype[i])
    if gain not in (_GAIN.mjGAIN_FIXED.value, _GAIN.mjGAIN_AFFINE.value):
        name = _GAIN(gain).name.removeprefix("mjGAIN_").lower()
        return f"its gain is {name}, not fixed or affine"
    if bias not in (_BIAS.mjBIAS_NONE.value, _BIAS.mjBIAS_AFFINE.value):
        name = _BIAS(bias).name.removeprefix("mjBIAS_").lower()
        return f"its bias is {name}, not none or affine"
    return None


def check_commanded(model: mujoco.MjModel, actuators: Iterable[int], where: str) -> None:
    """Reject commands to actuators whose force the estimator cannot compute (ConfigError)."""
    for i in actuators:
        reason = unsupported_reason(model, i)
        if reason is not None:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
            raise ConfigError(
                f"{where}: actuator {name!r} cannot take commands: {reason}; leave it out of "
                "the command stream (its dofs are then left free) or log its joint efforts"
            )


def moment_dense(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nu, nv) actuator moment arms at data's positions (after mj_fwdPosition / mj_inverse)."""
    moment = np.zeros((model.nu, model.nv))
    mujoco.mju_sparse2dense(
        moment, data.actuator_moment, data.moment_rownnz, data.moment_rowadr, data.moment_colind
    )
    return moment


def actuation_at(
    model: mujoco.MjModel, data: mujoco.MjData, ctrl: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's actuation of the commands ctrl (nu,) at data's state (mj_inverse or mj_forward
    has run on it; its ctrl, actuator_force and qfrc_actuator are overwritten): the moment
    arms (nu, nv) and the actuator forces (nu,), what `commanded_forces` turns into forces
    and Jacobians (at many knots at once)."""
    data.ctrl[:] = np.where(np.isfinite(ctrl), ctrl, 0.0)
    mujoco.mj_fwdActuation(model, data)
    return moment_dense(model, data), data.actuator_force.copy()


def commanded_forces(
    model: mujoco.MjModel,
    ctrl: np.ndarray,
    moment: np.ndarray,
    force: np.ndarray,
    jacobians: bool = False,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """qfrc (K, nv) of the commands ctrl (K, nu) at K states, NaN: no command (that actuator's
    force left out), from `actuation_at`'s moment (K, nu, nv) and force (K, nu); with
    jacobians, ∂qfrc/∂q and ∂qfrc/∂v (K, nv, nv) in the tangent space (the module's
    formulas)."""
    given = np.isfinite(ctrl)
    f = np.where(given, force, 0.0)
    qfrc = np.einsum("kun,ku->kn", moment, f)
    dofs, low, high = _joint_force_ranges(model)
    clamped = (qfrc[:, dofs] < low) | (qfrc[:, dofs] > high)  # (K, limited dofs)
    qfrc[:, dofs] = np.clip(qfrc[:, dofs], low, high)
    if not jacobians:
        return qfrc, None, None
    c = np.where(given, ctrl, 0.0)  # as MuJoCo clamps it to ctrlrange
    if not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL:
        limited = model.actuator_ctrllimited.astype(bool)
        low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
        c = np.where(limited, np.clip(c, low, high), c)
    # (against the enum's int: an array compared with the enum object goes element by element
    # through Python, 70 µs for 21 actuators)
    affine_gain = model.actuator_gaintype == _GAIN.mjGAIN_AFFINE.value
    affine_bias = model.actuator_biastype == _BIAS.mjBIAS_AFFINE.value
    gain, bias = model.actuator_gainprm, model.actuator_biasprm
    df_dl = np.where(affine_gain, gain[:, 1], 0.0) * c + np.where(affine_bias, bias[:, 1], 0.0)
    df_dv = np.where(affine_gain, gain[:, 2], 0.0) * c + np.where(affine_bias, bias[:, 2], 0.0)
    free = given & ~_at_forcerange(model, force)
    df_dl, df_dv = np.where(free, df_dl, 0.0), np.where(free, df_dv, 0.0)
    moment_t = moment.transpose(0, 2, 1)
    dq, dv = moment_t @ (df_dl[:, :, None] * moment), moment_t @ (df_dv[:, :, None] * moment)
    for i, d in enumerate(dofs):
        dq[clamped[:, i], d] = 0.0
        dv[clamped[:, i], d] = 0.0
    return qfrc, dq, dv


def commanded_force(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    ctrl: np.ndarray,
    jacobians: bool = False,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """`commanded_forces` at data's one state: qfrc (nv,), with jacobians ∂qfrc/∂q and
    ∂qfrc/∂v (nv, nv)."""
    moment, force = actuation_at(model, data, ctrl)
    qfrc, dq, dv = commanded_forces(model, ctrl[None], moment[None], force[None], jacobians)
    return qfrc[0], None if dq is None else dq[0], None if dv is None else dv[0]


def _joint_force_ranges(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The dofs of the hinge and slide joints with an actuatorfrcrange, and its ends."""
    # (against the enums' ints: `commanded_forces`)
    scalar = (model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE.value) | (
        model.jnt_type == mujoco.mjtJoint.mjJNT_SLIDE.value
    )
    joints = np.flatnonzero(model.jnt_actfrclimited.astype(bool) & scalar)
    return (
        model.jnt_dofadr[joints],
        model.jnt_actfrcrange[joints, 0],
        model.jnt_actfrcrange[joints, 1],
    )


def _at_forcerange(model: mujoco.MjModel, force: np.ndarray) -> np.ndarray:
    """(..., nu) actuators whose force (..., nu) MuJoCo clamped to their forcerange."""
    limited = model.actuator_forcelimited.astype(bool)
    low, high = model.actuator_forcerange[:, 0], model.actuator_forcerange[:, 1]
    return limited & ((force <= low) | (force >= high))
