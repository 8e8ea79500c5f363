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
    nv, nu, nefc = model.nv, model.nu, data.nefc
    moment = np.zeros((nu, nv))
    for i in range(nu):
        moment[i, model.jnt_dofadr[model.actuator_trnid[i, 0]]] = model.actuator_gear[i, 0]
    jac = np.zeros((nefc, nv))
    if nefc:
        if mujoco.mj_isSparse(model):
            mujoco.mju_sparse2dense(
                jac, data.efc_J, data.efc_J_rownnz, data.efc_J_rowadr, data.efc_J_colind
            )
        else:
            jac[:] = data.efc_J[: nefc * nv].reshape(nefc, nv)
    scale = 100.0  # N of contact force per unit of ctrl in the least-squares norm
    system = np.hstack([moment.T, scale * jac.T])
    solution = np.linalg.lstsq(system, data.qfrc_bias, rcond=None)[0]
    return solution[:nu]


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
