"""The controllers that drive the simulated robots, and the pushes that disturb them.

A controller is what runs on the robot: it knows only the nominal model (not the perturbed one
the simulator steps), reads the robot's state once per control step and returns `ctrl` (nu,)
in actuator units, clipped to each actuator's ctrlrange. All gains are per joint and scale
with the actuator's gear (a proxy for the joint's strength and reflected inertia), which keeps
the explicit Euler step stable at the models' timesteps.

- `StandingBalance` (humanoid): PD to a standing pose around a static feed-forward — the
  torques that, together with foot contact forces, hold the pose against gravity (least
  squares over contact forces and torques at the pose: qfrc_bias = B u + Jᵀ λ). Optionally
  switched off at a time, after which the robot falls.
- `TrotGait` (quadruped): phase-based joint trajectory of a trot (diagonal legs in phase,
  swing legs lifted by flexing the knee, stance legs sweeping back) around the standing pose,
  PD + the keyframe's holding torques.
- `PickAndPlace` (arm + box): scripted grasp-center waypoints solved to joint waypoints by
  damped least-squares IK on the nominal model, min-jerk interpolation, PD + gravity
  compensation (qfrc_bias of the nominal model via mj_rne); the gripper squeezes through a
  soft PD. The script pushes the box along the floor, grasps it, lifts, holds, lowers and
  releases it.
- `RandomTorque` (single joint, paper Fig. 1): ctrl ~ N(0, σ²) resampled every period.

`Push` schedules external forces (`xfrc_applied`) on a body: the disturbances of the
balancing scenario.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from estimator.actuation import moment_dense
from estimator.simulate.errors import SimulationError


@dataclass(frozen=True)
class Push:
    """A constant force on a body's center of mass for a while (an impulse of force·duration).

    body: model body name; start_s, duration_s: when [s from the start]; force: (3,) world
    frame [N].
    """

    body: str
    start_s: float
    duration_s: float
    force: tuple[float, float, float]

    def active(self, t: float) -> bool:
        return self.start_s <= t < self.start_s + self.duration_s

    def as_dict(self) -> dict[str, object]:
        return {
            "body": self.body,
            "start_s": self.start_s,
            "duration_s": self.duration_s,
            "force_n": list(self.force),
        }


def random_pushes(
    rng: np.random.Generator,
    body: str,
    duration_s: float,
    *,
    first_s: float = 1.0,
    interval_s: tuple[float, float] = (1.5, 2.5),
    force_n: tuple[float, float] = (25.0, 40.0),
    push_s: float = 0.1,
) -> tuple[Push, ...]:
    """Horizontal pushes in random directions, one every `interval_s` (uniform) seconds.

    force_n: range of the force magnitude [N]; push_s: how long each push lasts [s].
    """
    pushes = []
    t = first_s
    while t + push_s < duration_s:
        angle = rng.uniform(0.0, 2.0 * np.pi)
        magnitude = rng.uniform(*force_n)
        force = (float(magnitude * np.cos(angle)), float(magnitude * np.sin(angle)), 0.0)
        pushes.append(Push(body, round(t, 6), push_s, force))
        t += rng.uniform(*interval_s)
    return tuple(pushes)


def apply_pushes(
    model: mujoco.MjModel, data: mujoco.MjData, pushes: Sequence[Push], t: float
) -> None:
    """Set `data.xfrc_applied` to the pushes active at time t (zero elsewhere)."""
    data.xfrc_applied[:] = 0.0
    for push in pushes:
        if push.active(t):
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, push.body)
            data.xfrc_applied[body, :3] += push.force


class JointPD:
    """ctrl = clip(u_ff + (kp (q_ref − q) − kd v) / gear) for motors on hinge/slide joints.

    model: the nominal model. kp_per_gear, kd_per_gear: gains per unit gear [1/rad, s/rad]
    (kp = kp_per_gear · gear [N·m/rad], kd likewise).
    """

    def __init__(self, model: mujoco.MjModel, kp_per_gear: float, kd_per_gear: float) -> None:
        self.model = model
        joints = model.actuator_trnid[:, 0]
        self.qadr = model.jnt_qposadr[joints]
        self.dofadr = model.jnt_dofadr[joints]
        self.gear = model.actuator_gear[:, 0].copy()
        self.kp = kp_per_gear * self.gear
        self.kd = kd_per_gear * self.gear
        self.lo = model.actuator_ctrlrange[:, 0].copy()
        self.hi = model.actuator_ctrlrange[:, 1].copy()
        limited = model.actuator_ctrllimited.astype(bool)
        self.lo[~limited] = -np.inf
        self.hi[~limited] = np.inf

    def __call__(
        self, data: mujoco.MjData, q_ref: np.ndarray, u_ff: np.ndarray | float = 0.0
    ) -> np.ndarray:
        """(nu,) ctrl. q_ref: (nu,) joint targets of the actuated joints."""
        q = data.qpos[self.qadr]
        v = data.qvel[self.dofadr]
        tau = self.kp * (q_ref - q) - self.kd * v
        return np.clip(u_ff + tau / self.gear, self.lo, self.hi)


class StandingBalance:
    """Humanoid: PD to the keyframe pose around a static feed-forward; off after `off_s`.

    model: nominal model; keyframe: the standing pose; off_s: when the controller stops
    (ctrl = 0 from then on; None: never).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        keyframe: int = 0,
        *,
        kp_per_gear: float = 20.0,
        kd_per_gear: float = 0.05,
        off_s: float | None = None,
    ) -> None:
        self.pd = JointPD(model, kp_per_gear, kd_per_gear)
        self.off_s = off_s
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, keyframe)
        mujoco.mj_forward(model, data)
        self.q_ref = data.qpos[self.pd.qadr].copy()
        self.u_ff = static_feedforward(model, data)

    def __call__(self, t: float, data: mujoco.MjData) -> np.ndarray:
        if self.off_s is not None and t >= self.off_s:
            return np.zeros(self.pd.model.nu)
        return self.pd(data, self.q_ref, self.u_ff)


def static_feedforward(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nu,) ctrl that holds the pose in `data` (zero velocity) with its current contacts.

    Least squares over ctrl u and constraint forces λ of qfrc_bias = B u + J_efcᵀ λ, with λ
    scaled to weigh like u (the feet carry the weight; the motors do the rest). B: (nv, nu),
    the actuators' moment arms times gear. `data` must hold mj_forward's results.
    """
    nv, nu = model.nv, model.nu
    moment = np.zeros((nu, nv))
    for i in range(nu):
        moment[i, model.jnt_dofadr[model.actuator_trnid[i, 0]]] = model.actuator_gear[i, 0]
    jac = constraint_jacobian(model, data)
    scale = 100.0  # N of contact force per unit of ctrl in the least-squares norm
    system = np.hstack([moment.T, scale * jac.T])
    solution = np.linalg.lstsq(system, data.qfrc_bias, rcond=None)[0]
    return solution[:nu]


def constraint_jacobian(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nefc, nv) dense efc_J of `data` (dense or sparse storage)."""
    nv, nefc = model.nv, data.nefc
    jac = np.zeros((nefc, nv))
    if nefc:
        if mujoco.mj_isSparse(model):
            mujoco.mju_sparse2dense(
                jac, data.efc_J, data.efc_J_rownnz, data.efc_J_rowadr, data.efc_J_colind
            )
        else:
            jac[:] = data.efc_J[: nefc * nv].reshape(nefc, nv)
    return jac


class TrotGait:
    """Quadruped trot: diagonal leg pairs alternate swing and stance around the standing pose.

    Legs in actuator order (hip abduction, hip pitch, knee) × (front left, front right, rear
    left, rear right). period_s: gait cycle; lift_rad: peak extra knee flexion in swing;
    stride_rad: hip pitch amplitude (swing forward, stance back); ramp_s: time to blend the
    gait in from standing.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        keyframe: int = 0,
        *,
        period_s: float = 0.4,
        lift_rad: float = 0.5,
        stride_rad: float = 0.1,
        ramp_s: float = 0.5,
        kp_per_gear: float = 5.0,
        kd_per_gear: float = 0.05,
    ) -> None:
        self.pd = JointPD(model, kp_per_gear, kd_per_gear)
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, keyframe)
        self.q_home = data.qpos[self.pd.qadr].copy()
        self.u_ff = model.key_ctrl[keyframe].copy() if model.nkey else np.zeros(model.nu)
        self.period_s, self.lift_rad, self.stride_rad, self.ramp_s = (
            period_s,
            lift_rad,
            stride_rad,
            ramp_s,
        )
        self.phase_offset = np.array([0.0, 0.5, 0.5, 0.0])  # FL+RR, then FR+RL

    def reference(self, t: float) -> np.ndarray:
        """(nu,) joint targets at time t [s]."""
        q = self.q_home.copy()
        ramp = min(1.0, t / self.ramp_s) if self.ramp_s > 0 else 1.0
        for leg, offset in enumerate(self.phase_offset):
            phase = (t / self.period_s + offset) % 1.0
            if phase < 0.5:  # swing: lift (knee flexes, hip helps) and move forward
                s = np.sin(np.pi * phase / 0.5)
                knee, hip = -self.lift_rad * s, 0.5 * self.lift_rad * s
                sweep = -self.stride_rad + 2.0 * self.stride_rad * phase / 0.5
            else:  # stance: the foot sweeps back under the body
                knee, hip = 0.0, 0.0
                sweep = self.stride_rad - 2.0 * self.stride_rad * (phase - 0.5) / 0.5
            q[3 * leg + 1] += ramp * (hip - sweep)
            q[3 * leg + 2] += ramp * knee
        return q

    def __call__(self, t: float, data: mujoco.MjData) -> np.ndarray:
        return self.pd(data, self.reference(t), self.u_ff)


@dataclass(frozen=True)
class Waypoint:
    """Where the grasp center should be at a time, and the gripper jaw's target.

    t_s: time [s]; offset_m: (3,) grasp-center displacement from its keyframe position,
    world frame [m]; jaw_rad: gripper jaw target [rad] (larger closes).
    """

    t_s: float
    offset_m: tuple[float, float, float]
    jaw_rad: float


# The pick-and-place script, for the bundled arm_box model (hand pointing down, the box between
# the fingers): move 6 cm along +x so that the fixed finger pushes the box ~4.5 cm along the
# floor, squeeze it with the jaw, lift it 15 cm, hold, put it down, open, retract.
PICK_AND_PLACE: tuple[Waypoint, ...] = (
    Waypoint(0.0, (0.0, 0.0, 0.0), 0.15),
    Waypoint(0.3, (0.0, 0.0, 0.0), 0.15),
    Waypoint(1.5, (0.06, 0.0, 0.0), 0.15),
    Waypoint(1.7, (0.06, 0.0, 0.0), 0.15),
    Waypoint(2.2, (0.06, 0.0, 0.0), 0.6),
    Waypoint(3.2, (0.06, 0.0, 0.15), 0.6),
    Waypoint(3.8, (0.06, 0.0, 0.15), 0.6),
    Waypoint(4.8, (0.06, 0.0, 0.0), 0.6),
    Waypoint(5.2, (0.06, 0.0, 0.0), 0.15),
    Waypoint(6.0, (0.06, 0.0, 0.15), 0.15),
)


class PickAndPlace:
    """Arm: scripted grasp-center waypoints → IK joint waypoints → min-jerk + PD + gravity comp.

    model: the nominal model (arm joints first, then the gripper jaw, then the box's free
    joint, as in arm_box); site: the grasp-center site the waypoints move; arm_joints: how
    many leading hinge joints the IK uses (the rest of the actuated joints is the jaw).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        keyframe: int = 0,
        *,
        waypoints: Sequence[Waypoint] = PICK_AND_PLACE,
        site: str = "grasp_center",
        arm_joints: int = 6,
        kp_per_gear: float = 20.0,
        kd_per_gear: float = 1.0,
        jaw_kp: float = 3.0,
        jaw_kd: float = 0.05,
    ) -> None:
        self.model = model
        self.pd = JointPD(model, kp_per_gear, kd_per_gear)
        self.pd.kp[arm_joints:] = jaw_kp
        self.pd.kd[arm_joints:] = jaw_kd
        self.data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, self.data, keyframe)
        mujoco.mj_forward(model, self.data)
        self.site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        self.arm_dofs = self.pd.dofadr[:arm_joints]
        home = self.data.site_xpos[self.site].copy()
        rot = self.data.site_xmat[self.site].reshape(3, 3).copy()
        q = self.data.qpos[self.pd.qadr].copy()
        self.times = np.array([w.t_s for w in waypoints])
        joints = []
        for w in waypoints:
            q = q.copy()
            q[:arm_joints] = self._ik(home + np.asarray(w.offset_m), rot, q)
            q[arm_joints:] = w.jaw_rad
            joints.append(q)
        self.joint_waypoints = np.array(joints)  # (n_waypoints, nu)

    def _ik(self, target: np.ndarray, rot: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Joint angles (arm_joints,) that put the site at `target` with orientation `rot`."""
        m, d = self.model, self.data
        d.qpos[self.pd.qadr] = q0
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        for _ in range(200):
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_jacSite(m, d, jacp, jacr, self.site)
            r = d.site_xmat[self.site].reshape(3, 3)
            e_rot = 0.5 * sum(np.cross(r[:, i], rot[:, i]) for i in range(3))
            err = np.concatenate([target - d.site_xpos[self.site], e_rot])
            if np.linalg.norm(err) < 1e-10:
                break
            jac = np.vstack([jacp, jacr])[:, self.arm_dofs]
            step = jac.T @ np.linalg.solve(jac @ jac.T + 1e-6 * np.eye(6), err)
            d.qpos[self.pd.qadr[: len(self.arm_dofs)]] += step
        return d.qpos[self.pd.qadr[: len(self.arm_dofs)]].copy()

    def reference(self, t: float) -> np.ndarray:
        """(nu,) joint targets at time t: min-jerk between waypoints, the last one held."""
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        if i >= len(self.times) - 1:
            return self.joint_waypoints[-1]
        i = max(i, 0)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        s = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        return self.joint_waypoints[i] + s * (self.joint_waypoints[i + 1] - self.joint_waypoints[i])

    def __call__(self, t: float, data: mujoco.MjData) -> np.ndarray:
        m, d = self.model, self.data
        d.qpos[:] = data.qpos
        d.qvel[:] = 0.0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        bias = np.zeros(m.nv)
        mujoco.mj_rne(m, d, 0, bias)  # gravity (velocity zero): the holding torques
        u_ff = bias[self.pd.dofadr] / self.pd.gear
        return self.pd(data, self.reference(t), u_ff)


class RandomTorque:
    """ctrl ~ N(0, std²) per actuator, resampled every `period_s` (the paper's Fig. 1 drive).

    rng: drawn once per period, in time order; clipped to the ctrlrange.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        rng: np.random.Generator,
        *,
        std: float = 5.0,
        period_s: float = 0.02,
    ) -> None:
        self.model = model
        self.rng = rng
        self.std = std
        self.period_s = period_s
        self.lo = model.actuator_ctrlrange[:, 0]
        self.hi = model.actuator_ctrlrange[:, 1]
        self.index = -1
        self.ctrl = np.zeros(model.nu)

    def __call__(self, t: float, data: mujoco.MjData) -> np.ndarray:
        index = int(np.floor(t / self.period_s + 1e-9))
        while self.index < index:
            self.ctrl = np.clip(
                self.std * self.rng.standard_normal(self.model.nu), self.lo, self.hi
            )
            self.index += 1
        return self.ctrl


# -- any model: hold its keyframe (`physfuse simulate --model`) ----------------------------------
MOTOR, SERVO = "motor", "servo"
_CONTACT_ROWS = (
    mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS,
    mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL,
    mujoco.mjtConstraint.mjCNSTR_CONTACT_ELLIPTIC,
    mujoco.mjtConstraint.mjCNSTR_EQUALITY,
)


def actuator_kinds(model: mujoco.MjModel) -> list[str]:
    """Per actuator MOTOR (fixed gain, no bias: ctrl is a force) or SERVO (fixed gain, affine
    bias with a stiffness biasprm[1] < 0: ctrl is a target, e.g. a position actuator with
    biasprm[1] = −gainprm[0] = −kp); SimulationError naming any other actuator."""
    kinds = []
    for i in range(model.nu):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
        if model.actuator_dyntype[i] != mujoco.mjtDyn.mjDYN_NONE:
            dyn = mujoco.mjtDyn(model.actuator_dyntype[i]).name.removeprefix("mjDYN_").lower()
            raise SimulationError(
                f"actuator {name!r} has activation dynamics (dyntype {dyn}): only actuators "
                "without them (motors, position servos) can be driven"
            )
        fixed = model.actuator_gaintype[i] == mujoco.mjtGain.mjGAIN_FIXED
        bias = model.actuator_biastype[i]
        if fixed and model.actuator_gainprm[i, 0] != 0 and bias == mujoco.mjtBias.mjBIAS_NONE:
            kinds.append(MOTOR)
        elif fixed and bias == mujoco.mjtBias.mjBIAS_AFFINE and model.actuator_biasprm[i, 1] < 0:
            kinds.append(SERVO)
        else:
            raise SimulationError(
                f"actuator {name!r} is neither a motor (fixed gain, no bias) nor a position "
                "servo (fixed gain, affine bias with biasprm[1] < 0)"
            )
    return kinds


def holding_forces(model: mujoco.MjModel, data: mujoco.MjData, clip: bool = True) -> np.ndarray:
    """(nu,) actuator forces that hold the state in `data` still, with its contacts.

    τ = qfrc_inverse + qfrc_constraint of mj_inverse at zero velocity and acceleration (gravity
    less passive forces), split by least squares over actuator forces F and the contact and
    equality constraint forces λ: τ = Mᵀ F + Jᵀ λ, λ weighted like `static_feedforward`.
    M: (nu, nv) actuator moments. Clipped to each actuator's force range (clip).
    """
    data.qvel[:] = 0.0
    data.qacc[:] = 0.0
    mujoco.mj_inverse(model, data)
    tau = data.qfrc_inverse + data.qfrc_constraint
    moment = moment_dense(model, data)
    rows = np.isin(data.efc_type[: data.nefc], _CONTACT_ROWS)
    jac = constraint_jacobian(model, data)[rows]
    scale = 100.0  # N of constraint force per N (N·m) of actuator force in the norm
    solution = np.linalg.lstsq(np.hstack([moment.T, scale * jac.T]), tau, rcond=None)[0]
    force = solution[: model.nu]
    if not clip:
        return force
    limited = model.actuator_forcelimited.astype(bool)
    lo, hi = model.actuator_forcerange.T
    return np.where(limited, np.clip(force, lo, hi), force)


def actuator_inertia(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """(nu,) the mass matrix M along each actuator's moment r at data's positions,
    r M rᵀ / |r|⁴ (a joint's M_jj / gear², armature included)."""
    moment = moment_dense(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    r2 = np.maximum(np.sum(moment**2, axis=1), 1e-300)
    return np.einsum("iu,uv,iv->i", moment, mass, moment) / r2**2


def unstable_under_euler(model: mujoco.MjModel, keyframe: int) -> dict[str, float]:
    """The actuators whose own feedback the semi-implicit Euler step cannot integrate at the
    model's timestep h, each with max(h kv/m, h √(kp/m)): a servo's velocity gain kv (its bias
    −kv l̇) on the inertia m it drives is stable only for h kv/m < 2, its stiffness kp only for
    h √(kp/m) < 2. Menagerie's Spot and Panda servos run with the implicit integrator
    upstream; under the Euler step the analytic inverse needs they shake and fall (the Panda
    at 2 ms; `physics/models/menagerie/convert.py` runs it at 0.5 ms)."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, keyframe)
    mujoco.mj_forward(model, data)
    m = actuator_inertia(model, data)
    h = float(model.opt.timestep)
    affine = model.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE
    kp = np.where(affine, -model.actuator_biasprm[:, 1], 0.0)
    kv = np.where(affine, -model.actuator_biasprm[:, 2], 0.0)
    ratio = np.maximum(h * kv / m, h * np.sqrt(np.maximum(kp, 0.0) / m))
    names = [
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"#{a}"
        for a in range(model.nu)
    ]
    return {names[a]: float(ratio[a]) for a in np.flatnonzero(ratio >= 2.0)}


def short_of_holding(model: mujoco.MjModel, keyframe: int) -> list[str]:
    """The actuators that cannot hold `keyframe` still, each as "name needs F (can give
    lo … hi)": the force that would (`holding_forces`) outside what their forcerange, their
    joint's actuatorfrcrange or their ctrlrange at the keyframe allows (a position servo's
    target past its range: Menagerie's Berkeley Humanoid, kp 1 N m/rad on its knees)."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, keyframe)
    force = holding_forces(model, data, clip=False)  # (leaves the keyframe's lengths in data)
    out = []
    for a in range(model.nu):
        lo, hi = -np.inf, np.inf
        if model.actuator_forcelimited[a]:
            lo, hi = (
                max(lo, model.actuator_forcerange[a, 0]),
                min(hi, model.actuator_forcerange[a, 1]),
            )
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            j = model.actuator_trnid[a, 0]
            gear = model.actuator_gear[a, 0]
            if model.jnt_actfrclimited[j] and gear:
                ends = np.sort(model.jnt_actfrcrange[j] / gear)
                lo, hi = max(lo, ends[0]), min(hi, ends[1])
        fixed = model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
        if model.actuator_ctrllimited[a] and fixed:  # F = g·ctrl + b₀ + b₁·L at rest
            bias = (
                model.actuator_biasprm[a, 0]
                + model.actuator_biasprm[a, 1] * data.actuator_length[a]
            )
            ends = np.sort(model.actuator_gainprm[a, 0] * model.actuator_ctrlrange[a] + bias)
            lo, hi = max(lo, ends[0]), min(hi, ends[1])
        if not lo - 1e-9 <= force[a] <= hi + 1e-9:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"#{a}"
            out.append(f"{name} needs {force[a]:.3g} (can give {lo:.3g} … {hi:.3g})")
    return out


class KeyframeHold:
    """Any model: hold a keyframe through the model's own actuators, with excitation.

    Each actuator's force is F = g·ctrl + b₀ + b₁·L + b₂·L̇ (gain g, affine bias b, length L):
      motor  ctrl = (F_ff + kp (L* − L) − kd L̇) / g         our PD on the length
      servo  ctrl = (F_ff − b₀ − b₁ L*) / g                  its own stiffness −b₁ and damping
             (a position actuator, b₁ = −g: ctrl = L* + F_ff / kp, a target)
    clipped to the ctrlrange. F_ff: `holding_forces` at the keyframe. L* = gear · q*: the
    keyframe's joint angle plus the excitation δ(t) on every actuated hinge (within its
    range); other transmissions hold the keyframe's length.
    δ(t) = A·r(t)·Σᵢ aᵢ sin(2π fᵢ t + φᵢ) / Σᵢ aᵢ, three sines per hinge, aᵢ ~ U(0.5, 1),
    fᵢ ~ U(0.2, 1) Hz, φᵢ ~ U(0, 2π), r a smoothstep from 0 to 1 over `ramp_s`: smooth,
    random, |δ| ≤ A.
    Motor gains: kp = m ω², kd = 2 m ω (critically damped), m = r M rᵀ / |r|⁴ the mass
    matrix M along the actuator's moment r at the keyframe (a joint's M_jj / gear²),
    ω = min(2π·bandwidth_hz, 0.5/h) to keep the explicit Euler step stable.
    Balance, for a floating base standing on one or two bodies (a biped): the actuated hinges
    of those bodies (the ankles) add lean_gain·(a·θ) + rate_gain·(a·θ̇) to their target, with
    a the joint's axis and θ = ẑ × (c − c_key) / H the lean of the centre of mass c away from
    the keyframe's, seen from the feet H below it (world frame): the feet move the centre of
    pressure under a leaning body (the ankle strategy of `hold_keyframe` in
    physics/models/menagerie/convert.py, on the centre of mass rather than the base's tilt,
    which the excitation of the legs moves too).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        keyframe: int,
        rng: np.random.Generator,
        *,
        excitation_rad: float = 0.1,
        ramp_s: float = 1.0,
        bandwidth_hz: float = 10.0,
        lean_gain: float = 10.0,
        rate_gain: float = 1.0,
    ) -> None:
        self.model = model
        self.motor = np.array([k == MOTOR for k in actuator_kinds(model)], dtype=bool)
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, keyframe)
        self.u_ff = holding_forces(model, data)  # leaves the keyframe's kinematics in data
        self.length = data.actuator_length.copy()
        self.gear = model.actuator_gear[:, 0].copy()
        self.gain = model.actuator_gainprm[:, 0].copy()
        self.b0, self.b1 = model.actuator_biasprm[:, 0].copy(), model.actuator_biasprm[:, 1].copy()
        limited = model.actuator_ctrllimited.astype(bool)
        self.lo = np.where(limited, model.actuator_ctrlrange[:, 0], -np.inf)
        self.hi = np.where(limited, model.actuator_ctrlrange[:, 1], np.inf)
        # actuated hinges: the excitation (and balance) act on their angles
        on_joint = model.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT
        joints = np.where(on_joint, model.actuator_trnid[:, 0], 0)  # 0: not a joint
        self.hinge = on_joint & (model.jnt_type[joints] == mujoco.mjtJoint.mjJNT_HINGE)
        self.qadr = model.jnt_qposadr[joints]
        self.q_key = data.qpos[self.qadr].copy()
        ranged = self.hinge & model.jnt_limited[joints].astype(bool)
        self.q_lo = np.where(ranged, model.jnt_range[joints, 0], -np.inf)
        self.q_hi = np.where(ranged, model.jnt_range[joints, 1], np.inf)
        # motor gains
        inertia = actuator_inertia(model, data)
        omega = min(2.0 * np.pi * bandwidth_hz, 0.5 / float(model.opt.timestep))
        self.kp, self.kd = inertia * omega**2, 2.0 * inertia * omega
        # excitation: three sines per actuated hinge
        shape = (model.nu, 3)
        self.amplitude, self.ramp_s = excitation_rad, ramp_s
        self.weights = rng.uniform(0.5, 1.0, shape)
        self.freqs = rng.uniform(0.2, 1.0, shape)
        self.phases = rng.uniform(0.0, 2.0 * np.pi, shape)
        # balance
        self.lean_gain, self.rate_gain = lean_gain, rate_gain
        self.root, self.ankles = _biped(model, data, joints, self.hinge)
        self.axes = data.xaxis[joints[self.ankles]].copy()  # (n, 3) world joint axes
        self.com_key = data.subtree_com[self.root].copy()
        floor = np.mean([c.pos[2] for c in data.contact[: data.ncon]]) if data.ncon else 0.0
        self.height = max(float(self.com_key[2] - floor), 1e-3)
        self.jac_com = np.zeros((3, model.nv))

    def excitation(self, t: float) -> np.ndarray:
        """(nu,) δ(t) [rad] (zero on actuators that are not on a hinge)."""
        s = min(max(t / self.ramp_s, 0.0), 1.0) if self.ramp_s > 0 else 1.0
        sines = np.sin(2.0 * np.pi * self.freqs * t + self.phases)
        wave = np.sum(self.weights * sines, axis=1) / np.sum(self.weights, axis=1)
        return np.where(self.hinge, self.amplitude * s * s * (3.0 - 2.0 * s) * wave, 0.0)

    def targets(self, t: float, data: mujoco.MjData) -> np.ndarray:
        """(nu,) joint targets q* of the actuated hinges (keyframe + excitation + balance)."""
        q = self.q_key + self.excitation(t)
        if self.ankles.any():
            theta, rate = self._lean(data)
            q[self.ankles] += self.lean_gain * self.axes @ theta + self.rate_gain * self.axes @ rate
        return np.clip(q, self.q_lo, self.q_hi)

    def __call__(self, t: float, data: mujoco.MjData) -> np.ndarray:
        target = np.where(self.hinge, self.gear * self.targets(t, data), self.length)
        error = target - data.actuator_length
        force = self.u_ff + self.kp * error - self.kd * data.actuator_velocity
        ctrl = np.where(self.motor, force, self.u_ff - self.b0 - self.b1 * target) / self.gain
        return np.clip(ctrl, self.lo, self.hi)

    def _lean(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """θ = ẑ × (c − c_key) / H and its rate (world frame) of the standing body's centre of
        mass c. `data`: after mj_step1 (subtree_com, its Jacobian)."""
        mujoco.mj_jacSubtreeCom(self.model, data, self.jac_com, self.root)
        up = np.array([0.0, 0.0, 1.0])
        offset = data.subtree_com[self.root] - self.com_key
        velocity = self.jac_com @ data.qvel
        return np.cross(up, offset) / self.height, np.cross(up, velocity) / self.height


def _biped(
    model: mujoco.MjModel, data: mujoco.MjData, joints: np.ndarray, hinge: np.ndarray
) -> tuple[int, np.ndarray]:
    """(the standing body's root, a mask (nu,) of its ankle actuators): the actuated hinges
    of the bodies touching the world at the keyframe when a floating base stands on one or
    two of them; (0, none) otherwise. `data`: the keyframe after collision detection;
    joints, hinge: each actuator's joint and whether it is an actuated hinge."""
    feet = set()
    for c in data.contact[: data.ncon]:
        b1, b2 = (int(model.geom_bodyid[g]) for g in (c.geom1, c.geom2))
        for foot, other in ((b1, b2), (b2, b1)):
            if model.body_weldid[other] == 0 and model.body_weldid[foot] != 0:
                feet.add(foot)
    roots = {int(model.body_rootid[b]) for b in feet}
    none = np.zeros(model.nu, dtype=bool)
    if not 1 <= len(feet) <= 2 or len(roots) != 1:
        return 0, none
    root = roots.pop()
    free = int(model.body_jntadr[root])
    if free < 0 or model.jnt_type[free] != mujoco.mjtJoint.mjJNT_FREE:
        return 0, none
    ankles = hinge & np.isin(model.jnt_bodyid[joints], list(feet))
    return (root, ankles) if ankles.any() else (0, none)
