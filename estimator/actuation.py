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
joint transmissions, is left out.)
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


def commanded_force(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    ctrl: np.ndarray,
    jacobians: bool = False,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """qfrc (nv,) of the commands ctrl (nu,) at data's state, NaN: no command (that actuator's
    force left out); with jacobians, ∂qfrc/∂q and ∂qfrc/∂v (nv, nv) in the tangent space.

    data must hold the state's positions and velocities (mj_inverse or mj_forward has run on
    it); its ctrl, actuator_force and qfrc_actuator are overwritten.
    """
    given = np.isfinite(ctrl)
    data.ctrl[:] = np.where(given, ctrl, 0.0)
    mujoco.mj_fwdActuation(model, data)
    force = np.where(given, data.actuator_force, 0.0)
    moment = moment_dense(model, data)
    qfrc = moment.T @ force
    if not jacobians:
        return qfrc, None, None
    c = data.ctrl.copy()  # as MuJoCo clamps it to ctrlrange
    if not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL:
        limited = model.actuator_ctrllimited.astype(bool)
        low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
        c = np.where(limited, np.clip(c, low, high), c)
    # (against the enum's int: an array compared with the enum object goes element by element
    # through Python, 70 µs for 21 actuators, a sixth of a knot's Jacobian pass)
    affine_gain = model.actuator_gaintype == _GAIN.mjGAIN_AFFINE.value
    affine_bias = model.actuator_biastype == _BIAS.mjBIAS_AFFINE.value
    gain, bias = model.actuator_gainprm, model.actuator_biasprm
    df_dl = np.where(affine_gain, gain[:, 1], 0.0) * c + np.where(affine_bias, bias[:, 1], 0.0)
    df_dv = np.where(affine_gain, gain[:, 2], 0.0) * c + np.where(affine_bias, bias[:, 2], 0.0)
    free = given & ~_at_forcerange(model, data)
    df_dl, df_dv = np.where(free, df_dl, 0.0), np.where(free, df_dv, 0.0)
    return qfrc, moment.T @ (df_dl[:, None] * moment), moment.T @ (df_dv[:, None] * moment)


def _at_forcerange(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nu,) actuators whose force MuJoCo clamped to their forcerange."""
    limited = model.actuator_forcelimited.astype(bool)
    low, high = model.actuator_forcerange[:, 0], model.actuator_forcerange[:, 1]
    f = data.actuator_force
    return limited & ((f <= low) | (f >= high))
