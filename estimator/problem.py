"""The estimation problem for a window of knots: variables, factors, residuals and Jacobians.

Variables. Knot k holds the configuration q_k on the model's own manifolds, perturbed as
q_k ⊕ x_k = mj_integratePos(q_k, x_k, 1): free joints as poses (world position, body-frame
rotation), ball joints as rotations, hinges and slides as vectors. Each IMU stream adds a
bias b_k = (accelerometer, gyro) per knot. The GTSAM key of knot k is z_k = (x_k, b_k).

Discrete-time kinematics (the Euler step of the paper's eq. 3):

    v_k = (q_k ⊖ q_{k−1}) / h,    a_k = (v_{k+1} − v_k) / h

Factors, all on (z_{k−1}, z_k, z_{k+1}) for the interior knots k = 1 … T−2:

    physics   W (u(q_k, v_k, a_k) − u_known_k)          u: the analytic inverse, eq. 12
    sensors   W (s(q_k, v_k, a_k) + b_k − s_measured_k)  MuJoCo's sensors at the same state
    prior     a_k / σ_a                                   a weak smoothness prior
    bias      (b_{k+1} − b_k) / (σ_walk √h)               random walk

and, optionally (the kinematic method), on (z_{k−1} … z_{k+2}):

    jerk      (a_{k+1} − a_k) / (h σ_j)                   constant-acceleration prior

Position-stage samples (poses, markers, encoders) are predicted at their own times: a
sample at t_{k−1} + α h as (1 − α) s(q_{k−1}) + α s(q_k), a factor of knot k; rates and
accelerations are averaged over the Euler step they belong to (gyro over (t_k − h, t_k], the
step v_k moves through; accelerometer and force/torque over [t_k, t_k + h), where a_k acts),
σ/√n; saturated IMU samples (at the configured range) left out. Rows are whitened here;
`estimator.factors` weights them robustly and `estimator.solver` solves.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from estimator.actuation import (
    actuation_at,
    check_commanded,
    commanded_force,
    commanded_forces,
    moment_dense,
)
from estimator.config import Config
from estimator.factors import UNITS, Grid, SensorBlock
from estimator.factors.base import MODEL_ERROR
from estimator.io.logs.measurements import Measurement
from estimator.knots import held_at_knots, knot_grid
from estimator.rotations import jr_inverse, quat_log_between
from estimator.settings import Settings, softness_error
from physics.errors import UnsupportedModelError
from physics.native import use_discrete_inverse

_OBJ = mujoco.mjtObj
_SENS = mujoco.mjtSensor


@dataclass
class Problem:
    """Everything fixed about one window: the model with sensors, the grid and measurements."""

    model: mujoco.MjModel
    h: float
    t_ns: np.ndarray  # (T,) knot times
    blocks: list[SensorBlock]
    # (T, nv) the known force that does not depend on the state (0 on unactuated dofs, logged
    # efforts; 0 on dofs the commands drive, whose force `u_known` adds), NaN where none is known
    qfrc_known: np.ndarray
    known_sigma: np.ndarray  # (T, nv) σ of u − qfrc_known whatever the method, inf where unknown
    physics_sigma: np.ndarray  # (T, nv) the physics factors' σ, inf where the dof is left free
    settings: Settings
    nb: int  # bias dimensions per knot (6 per IMU and per force/torque stream)
    imu_streams: list[str] = field(default_factory=list)
    bias_walk: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (nb,) per √s
    bias_prior: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (nb,) σ of b_0
    # stream → its 6 bias dims; MODEL_ERROR → the offset's dims (one per error_dofs entry)
    bias_of: dict[str, slice] = field(default_factory=dict)
    # unactuated dofs with a model-error offset, its bias dims bias_of[MODEL_ERROR]
    error_dofs: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    # (T, nu) the logged commands held at the knots, NaN where an actuator has none
    ctrl: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def u_known(
        self, data: mujoco.MjData, k: int, jacobians: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """u_known (nv,) at knot k and data's state (positions and velocities computed):
        qfrc_known[k] plus the force of the commands through the model's actuators
        (`estimator.actuation`), NaN where unknown; with jacobians, its ∂/∂q and ∂/∂v (nv, nv).
        """
        if not np.isfinite(self.ctrl[k]).any():
            return self.qfrc_known[k], None, None
        qfrc, dq, dv = commanded_force(self.model, data, self.ctrl[k], jacobians)
        return self.qfrc_known[k] + qfrc, dq, dv

    def actuation(self, data: mujoco.MjData, k: int) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo's actuation of knot k's commands at data's state (`actuation_at`), for
        `u_known_of`."""
        return actuation_at(self.model, data, self.ctrl[k])

    def u_known_of(
        self, knots: range, actuation: tuple[np.ndarray, np.ndarray], jacobians: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """`u_known` at many knots at once: (len, nv), with jacobians ∂/∂q and ∂/∂v (len, nv,
        nv), from each knot's `actuation` (moment arms and forces; zero at a knot without
        commands)."""
        ctrl = self.ctrl[knots.start : knots.stop]
        qfrc, dq, dv = commanded_forces(self.model, ctrl, *actuation, jacobians)
        return self.qfrc_known[knots.start : knots.stop] + qfrc, dq, dv

    @property
    def T(self) -> int:
        return len(self.t_ns)

    def keys(self, start: int, stop: int | None = None) -> Problem:
        """The same problem on its knots start … stop − 1 (its samples as they are here; the
        samples of its knot 1 are predicted from its knot 0, which the linearization does not
        evaluate: leave that knot's rows out)."""
        k = slice(start, stop)
        blocks = [
            replace(
                b,
                values=b.values[k],
                sigma=b.sigma[k] if b.sigma.ndim == 2 else b.sigma,  # (per knot, or per row)
                alpha=None if b.alpha is None else b.alpha[k],
            )
            for b in self.blocks
            if np.isfinite(b.values[k][1:-1]).any()  # (a block without a sample here: no rows)
        ]
        return replace(
            self,
            t_ns=self.t_ns[k],
            blocks=blocks,
            qfrc_known=self.qfrc_known[k],
            known_sigma=self.known_sigma[k],
            physics_sigma=self.physics_sigma[k],
            ctrl=self.ctrl[k] if len(self.ctrl) else self.ctrl,
        )

    @property
    def nz(self) -> int:
        return self.model.nv + self.nb


# ---------------------------------------------------------------------------------------------
# building the problem


def model_with_sensors(
    config: Config, base: mujoco.MjModel | None = None
) -> tuple[mujoco.MjModel, dict[str, list[str]]]:
    """The config's model with one MuJoCo sensor per measured quantity, named after the stream.

    Returns the compiled model and, per stream, the names of its sensors in measurement order.
    """
    spec = config.model_spec()
    names: dict[str, list[str]] = {}
    for stream in config.streams.values():
        unit = UNITS.get(stream.kind)
        names[stream.name] = unit.add_sensors(spec, stream) if unit else []
    model = spec.compile()
    if base is not None:  # keep the caller's options (e.g. solver settings)
        model.opt.timestep = base.opt.timestep
    use_discrete_inverse(model)  # the knots' mj_inverse inverts the Euler step, as the engine's
    return model, names


def build_problem(
    config: Config,
    measurements: Mapping[str, Measurement],
    settings: Settings,
    t_ns: np.ndarray | None = None,
    compiled: tuple[mujoco.MjModel, dict[str, list[str]]] | None = None,
    at_sample_times: bool = True,
) -> Problem:
    """Map the measurements onto the knots of `t_ns` (default: the whole log).

    compiled: the result of `model_with_sensors(config)`, to reuse across windows.
    at_sample_times: position-stage streams (poses, markers, encoders) as their samples, each
    predicted between its two knots (`SensorBlock.alpha`); False: interpolated to the knots
    (the filters, which step from knot to knot).
    """
    return ProblemBuilder(config, settings, compiled).build(measurements, t_ns, at_sample_times)


class ProblemBuilder:
    """What `build_problem` does that does not depend on the measurements, done once for
    problems built again and again (a stream's filter, one knot at a time): the model copied
    with the settings' timestep and softness, each stream's sensor rows, the actuators' moment
    arms at the model's reference configuration. The problems it builds share its model."""

    def __init__(
        self,
        config: Config,
        settings: Settings,
        compiled: tuple[mujoco.MjModel, dict[str, list[str]]] | None = None,
    ) -> None:
        model, sensor_names = compiled or model_with_sensors(config)
        model = copy.deepcopy(model)  # the softness settings scale it
        self.h = settings.h or float(model.opt.timestep)
        if abs(self.h - model.opt.timestep) > 1e-12:
            model.opt.timestep = self.h
        try:
            settings.apply_softness(model)
        except UnsupportedModelError as err:  # κ below 2h
            raise softness_error(config, err) from None
        self.config, self.settings, self.model = config, settings, model
        self.rows = {
            name: [_sensor_rows(model, s) for s in sensor_names[name]] for name in config.streams
        }
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        self.moment = moment_dense(model, data)  # (nu, nv)

    def build(
        self,
        measurements: Mapping[str, Measurement],
        t_ns: np.ndarray | None = None,
        at_sample_times: bool = True,
    ) -> Problem:
        """`build_problem` on this builder's model."""
        config, settings, model, h = self.config, self.settings, self.model, self.h
        if t_ns is None:
            t_ns = knot_grid(measurements, h)
        blocks: list[SensorBlock] = []
        walks: list[np.ndarray] = []  # per bias dim: random walk σ per √s, σ of b_0
        priors: list[np.ndarray] = []
        bias_of: dict[str, slice] = {}
        efforts: dict[int, np.ndarray] = {}
        nb = 0
        for name, stream in config.streams.items():
            m = measurements.get(name)
            unit = UNITS.get(stream.kind)
            if m is None or not len(m) or unit is None:
                continue
            out = unit.factors(
                stream, m, self.rows[name], Grid(model, t_ns, settings, nb, at_sample_times)
            )
            blocks += out.blocks
            efforts |= out.efforts
            if len(out.bias_walk):
                walks.append(out.bias_walk)
                priors.append(out.bias_prior)
                bias_of[name] = slice(nb, nb + len(out.bias_walk))
                nb += len(out.bias_walk)
        imu_streams = [n for n in bias_of if config.streams[n].kind == "imu"]
        qfrc_known, known_sigma, actuated, ctrl = _known_forces(
            model, self.moment, config, measurements, efforts, t_ns, settings
        )
        # the kinematic method: no physics factor anywhere
        sigma = np.full_like(known_sigma, np.inf) if settings.method == "kinematic" else known_sigma
        error_dofs = np.zeros(0, int)
        if settings.method == "physics" and settings.model_error_std > 0:
            error_dofs = np.flatnonzero(~actuated)
            walks.append(np.full(len(error_dofs), settings.model_error_walk))
            priors.append(np.full(len(error_dofs), settings.model_error_std))
            bias_of[MODEL_ERROR] = slice(nb, nb + len(error_dofs))
            nb += len(error_dofs)
        bias_walk = np.concatenate(walks) if walks else np.zeros(0)
        bias_prior = np.concatenate(priors) if priors else np.zeros(0)
        return Problem(
            model,
            h,
            t_ns,
            blocks,
            qfrc_known,
            known_sigma,
            sigma,
            settings,
            nb,
            imu_streams,
            bias_walk,
            bias_prior,
            bias_of,
            error_dofs,
            ctrl,
        )


def joint_name(model: mujoco.MjModel, j: int) -> str:
    """Joint j's name; an unnamed joint (a free joint often is) by its body: `<body>`, or
    `<body>_joint<k>` for the body's k-th unnamed joint after the first."""
    name = mujoco.mj_id2name(model, _OBJ.mjOBJ_JOINT, j)
    if name:
        return name
    body = int(model.jnt_bodyid[j])
    body_name = mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, body) or f"body{body}"
    k = j - int(model.body_jntadr[body])
    return body_name if k == 0 else f"{body_name}_joint{k}"


def dof_names(model: mujoco.MjModel) -> list[str]:
    """(nv,) one name per dof: `<joint>` for hinges and slides, `<joint>_{x,y,z,rx,ry,rz}`
    for free joints (world translation, body rotation), `<joint>_{rx,ry,rz}` for balls."""
    names = [""] * model.nv
    for j in range(model.njnt):
        joint = joint_name(model, j)
        kind = model.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            suffixes = ["_x", "_y", "_z", "_rx", "_ry", "_rz"]
        elif kind == mujoco.mjtJoint.mjJNT_BALL:
            suffixes = ["_rx", "_ry", "_rz"]
        else:
            suffixes = [""]
        adr = model.jnt_dofadr[j]
        for i, suffix in enumerate(suffixes):
            names[adr + i] = joint + suffix
    return names


def _sensor_rows(model: mujoco.MjModel, name: str) -> np.ndarray:
    i = mujoco.mj_name2id(model, _OBJ.mjOBJ_SENSOR, name)
    adr, dim = model.sensor_adr[i], model.sensor_dim[i]
    return np.arange(adr, adr + dim)


def _known_forces(
    model: mujoco.MjModel,
    moment: np.ndarray,
    config: Config,
    measurements: Mapping[str, Measurement],
    efforts: Mapping[int, np.ndarray],
    t_ns: np.ndarray,
    settings: Settings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """qfrc_known (T, nv), the physics factor's σ (T, nv), which dofs an actuator drives (nv,)
    and the commands held at the knots, ctrl (T, nu) (NaN: none). moment: the actuators'
    moment arms (nu, nv), which say which dofs they drive.

    Unactuated dofs: u_known = 0 with σ_unactuated. Actuated dofs: the force of the logged
    commands through the actuators at each knot's state (`Problem.u_known`; qfrc_known 0
    there), or the measured joint efforts, with σ_actuated; left free (σ = ∞) when neither
    is logged. Commands are held from sample to sample (zero-order hold, as a controller
    holds them), their stream's time offset applied by the reader.
    """
    T, nv = len(t_ns), model.nv
    actuated = np.any(moment != 0, axis=0)
    known = np.full((T, nv), np.nan)
    known[:, ~actuated] = 0.0
    sigma = np.full((T, nv), np.inf)
    sigma[:, ~actuated] = settings.physics_std_unactuated
    ctrl = np.full((T, model.nu), np.nan)
    commands = [(n, m) for n, m in measurements.items() if m.kind == "command" and len(m)]
    for name, m in commands:
        held = held_at_knots(m, t_ns)  # (T, E)
        ids = [mujoco.mj_name2id(model, _OBJ.mjOBJ_ACTUATOR, a) for a in m.elements]
        check_commanded(model, ids, f"{config.path}: streams.{name}")
        for e, a in enumerate(ids):
            ctrl[:, a] = held[:, e]
    if commands:
        for k in range(T):
            driven = np.any(moment[np.isfinite(ctrl[k])] != 0, axis=0)
            known[k, driven] = 0.0
            sigma[k, driven] = settings.physics_std_actuated
    else:
        for dof, effort in efforts.items():  # measured joint efforts (`factors.joint_state`)
            ok = np.isfinite(effort)
            known[ok, dof] = effort[ok]
            sigma[ok, dof] = settings.physics_std_actuated
    return known, sigma, actuated, ctrl


def u_known_along(
    problem: Problem, qpos: np.ndarray, knots: Iterable[int] | None = None
) -> np.ndarray:
    """(T, nv) u_known at every knot of a trajectory qpos (T, nq), v by finite differences
    (at `knots` only, NaN elsewhere, when given)."""
    model, data = problem.model, mujoco.MjData(problem.model)
    v = velocities(model, qpos, problem.h)
    out = np.full((problem.T, model.nv), np.nan)
    for k in range(problem.T) if knots is None else knots:
        data.qpos[:], data.qvel[:] = qpos[k], v[k]
        mujoco.mj_fwdPosition(model, data)
        mujoco.mj_fwdVelocity(model, data)
        out[k] = problem.u_known(data, k)[0]
    return out


# ---------------------------------------------------------------------------------------------
# kinematics on the knots


def velocities(model: mujoco.MjModel, qpos: np.ndarray, h: float) -> np.ndarray:
    """(T, nv) v_k = (q_k ⊖ q_{k−1})/h, with v_0 = v_1."""
    T = len(qpos)
    v = np.zeros((T, model.nv))
    for k in range(1, T):
        mujoco.mj_differentiatePos(model, v[k], h, qpos[k - 1], qpos[k])
    if T > 1:
        v[0] = v[1]
    return v


def accelerations(v: np.ndarray, h: float) -> np.ndarray:
    """(T, nv) a_k = (v_{k+1} − v_k)/h, with a_{T−1} = 0."""
    a = np.zeros_like(v)
    a[:-1] = (v[1:] - v[:-1]) / h
    return a


def retract(model: mujoco.MjModel, qpos: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """(T, nq) q_k ⊕ dx_k on each joint's manifold."""
    out = qpos.copy()
    for k in range(len(qpos)):
        mujoco.mj_integratePos(model, out[k], dx[k], 1.0)
    return out


@dataclass(frozen=True)
class RotationDofs:
    """Where rotations live in qpos/qvel: (qpos address of the quaternion, dof address)."""

    quat_dofs: tuple[tuple[int, int], ...]

    @classmethod
    def of(cls, model: mujoco.MjModel) -> RotationDofs:
        pairs = []
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                pairs.append((model.jnt_qposadr[j] + 3, model.jnt_dofadr[j] + 3))
            elif model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                pairs.append((model.jnt_qposadr[j], model.jnt_dofadr[j]))
        return cls(tuple(pairs))


def difference_jacobians(
    model: mujoco.MjModel, rotations: RotationDofs, q1: np.ndarray, q2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """∂(q2 ⊖ q1)/∂x1 and ∂(q2 ⊖ q1)/∂x2 for right perturbations q ⊕ x, for N pairs q1, q2
    (N, nq). Both are block-diagonal, so each is (N, nv, 3) by dof group: row d on the
    columns of its group (a vector dof: its own at index 0; a rotation: its 3).

    ∓1 on vector dofs; on a rotation φ = Log(R1ᵀ R2): ∂φ/∂x2 = J_r⁻¹(φ),
    ∂φ/∂x1 = −J_r⁻¹(φ) Exp(φ)ᵀ = −J_l⁻¹(φ) = −J_r⁻¹(−φ).
    """
    N, nv = len(q1), model.nv
    d1, d2 = np.zeros((N, nv, 3)), np.zeros((N, nv, 3))
    d1[:, :, 0], d2[:, :, 0] = -1.0, 1.0
    for qadr, dadr in rotations.quat_dofs:
        phi = quat_log_between(q1[:, qadr : qadr + 4], q2[:, qadr : qadr + 4])
        rot = slice(dadr, dadr + 3)
        d2[:, rot] = jr_inverse(phi)
        d1[:, rot] = -jr_inverse(-phi)
    return d1, d2
