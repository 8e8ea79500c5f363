"""The bundled MJCF models: they load, follow the rules the analytic inverse relies on, simulate
cleanly under random controls and produce the constraints each one exists to exercise."""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest

from physics.softness import Softness

MODEL_DIR = Path(__file__).resolve().parents[1] / "physics" / "models"

Cnstr = mujoco.mjtConstraint
Obj = mujoco.mjtObj


@dataclass(frozen=True)
class Spec:
    """What a bundled model must be: sizes, timestep and how hard to drive it."""

    nv: int
    nu: int
    timestep: float
    # Random control: home ctrl + N(0, ctrl_std · half ctrlrange), resampled every 20 ms.
    ctrl_std: float


SPECS = {
    "single_joint": Spec(nv=1, nu=1, timestep=0.002, ctrl_std=0.25),
    "humanoid": Spec(nv=27, nu=21, timestep=0.01, ctrl_std=0.2),
    "all_constraints": Spec(nv=25, nu=6, timestep=0.002, ctrl_std=0.6),
    "quadruped": Spec(nv=18, nu=12, timestep=0.005, ctrl_std=0.1),
    "arm_box": Spec(nv=13, nu=7, timestep=0.002, ctrl_std=0.1),
}
MODELS = sorted(SPECS)

ROLLOUT_S = 2.5
CTRL_PERIOD_S = 0.02
NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")


@functools.cache
def _model(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(MODEL_DIR / f"{name}.xml"))


def _home(m: mujoco.MjModel) -> tuple[mujoco.MjData, int]:
    """MjData reset to the "home" keyframe; returns it with the keyframe id."""
    d = mujoco.MjData(m)
    key = mujoco.mj_name2id(m, Obj.mjOBJ_KEY, "home")
    mujoco.mj_resetDataKeyframe(m, d, key)
    return d, key


@dataclass(frozen=True)
class Rollout:
    """Per-step records of a random-control simulation from the home keyframe."""

    finite: bool
    warnings: tuple[int, ...]  # d.warning[i].number at the end
    efc_types: tuple[frozenset[int], ...]  # constraint types present at each step
    contact_dims: tuple[frozenset[int], ...]  # d.contact.dim values at each step
    limited_joints: tuple[frozenset[int], ...]  # joint ids with a LIMIT_JOINT row
    contact_pairs: tuple[frozenset[tuple[str, str]], ...]  # geom name pairs in contact
    friction_force: np.ndarray  # (nstep,) sum of FRICTION_DOF forces
    friction_sticks: np.ndarray  # (nstep,) bool: a FRICTION_DOF force strictly inside ±η
    contact_normal_force: np.ndarray  # (nstep,) sum of contact normal forces
    nstep: int


@functools.cache
def _rollout(name: str, seed: int = 0) -> Rollout:
    m = _model(name)
    d, _ = _home(m)
    rng = np.random.default_rng(seed)
    ctrl_home = d.ctrl.copy()
    lo, hi = m.actuator_ctrlrange.T
    half_range = (hi - lo) / 2
    nsub = max(1, round(CTRL_PERIOD_S / m.opt.timestep))
    nstep = nsub * round(ROLLOUT_S / CTRL_PERIOD_S)
    efc_types, dims, limits, pairs = [], [], [], []
    friction_force = np.zeros(nstep)
    friction_sticks = np.zeros(nstep, dtype=bool)
    normal_force = np.zeros(nstep)
    finite = True
    for i in range(nstep):
        if i % nsub == 0:
            noise = rng.normal(0.0, SPECS[name].ctrl_std, m.nu) * half_range
            d.ctrl[:] = np.clip(ctrl_home + noise, lo, hi)
        mujoco.mj_step(m, d)
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            finite = False
            break
        efc_type = d.efc_type[: d.nefc]
        efc_force = d.efc_force[: d.nefc]
        efc_types.append(frozenset(efc_type.tolist()))
        dims.append(frozenset(d.contact.dim[: d.ncon].tolist()))
        limits.append(frozenset(d.efc_id[: d.nefc][efc_type == Cnstr.mjCNSTR_LIMIT_JOINT].tolist()))
        pairs.append(
            frozenset(
                tuple(sorted((m.geom(c.geom1).name, m.geom(c.geom2).name)))
                for c in d.contact[: d.ncon]
            )
        )
        friction = efc_type == Cnstr.mjCNSTR_FRICTION_DOF
        friction_force[i] = efc_force[friction].sum()
        # Sticking = the force is strictly inside [-η, η]. Read it from efc_force: after a
        # Newton solve that stops at one iteration, mujoco 4.0.0 leaves efc_state stale.
        eta = d.efc_frictionloss[: d.nefc][friction]
        friction_sticks[i] = bool(np.any(np.abs(efc_force[friction]) < (1 - 1e-3) * eta))
        # The first row of each contact (efc_address) is its normal.
        normal_force[i] = sum(
            d.efc_force[c.efc_address] for c in d.contact[: d.ncon] if c.efc_address >= 0
        )
    return Rollout(
        finite=finite,
        warnings=tuple(int(w.number) for w in d.warning),
        efc_types=tuple(efc_types),
        contact_dims=tuple(dims),
        limited_joints=tuple(limits),
        contact_pairs=tuple(pairs),
        friction_force=friction_force,
        friction_sticks=friction_sticks,
        contact_normal_force=normal_force,
        nstep=nstep,
    )


def _fraction(steps: tuple[frozenset, ...], item: object) -> float:
    return sum(item in s for s in steps) / len(steps)


def _names(m: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(m, obj, i) for i in range(count)]


def _sensors(m: mujoco.MjModel, sensor_type: mujoco.mjtSensor) -> list[tuple[str, str]]:
    """(sensor name, name of the object it reads) for every sensor of one type."""
    out = []
    for i in range(m.nsensor):
        if m.sensor_type[i] == sensor_type:
            obj = mujoco.mj_id2name(m, int(m.sensor_objtype[i]), int(m.sensor_objid[i]))
            out.append((m.sensor(i).name, obj))
    return out


# --- Every model ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MODELS)
def test_model_loads_with_expected_sizes_and_timestep(name):
    m = _model(name)
    spec = SPECS[name]
    assert (m.nv, m.nu) == (spec.nv, spec.nu)
    assert m.opt.timestep == pytest.approx(spec.timestep)


@pytest.mark.parametrize("name", MODELS)
def test_physics_load_model_resolves_bundled_name(name):
    from physics.model import load_model

    assert load_model(name).nv == SPECS[name].nv


@pytest.mark.parametrize("name", MODELS)
def test_cone_is_elliptic_and_integrator_is_euler(name):
    m = _model(name)
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER


@pytest.mark.parametrize("name", MODELS)
def test_no_damping_springs_margins_or_gaps(name):
    m = _model(name)
    assert not m.dof_damping.any()
    assert not m.jnt_stiffness.any()
    assert not m.tendon_damping.any()
    assert not m.tendon_stiffness.any()
    assert not m.geom_margin.any() and not m.geom_gap.any()
    assert not m.pair_margin.any() and not m.pair_gap.any()
    assert not m.jnt_margin.any() and not m.tendon_margin.any()


@pytest.mark.parametrize("name", MODELS)
def test_models_carry_the_papers_nominal_softness_on_every_constraint(name):
    """ε = 0.05, κ = 0.02 s in every element that can make a constraint, written into the model
    itself: the model's own softness is what the simulator and the estimator use by default."""
    m = _model(name)
    own = Softness.of_model(m)
    assert own.eps == pytest.approx(0.05, rel=1e-12) and own.kappa == 0.02
    assert own.impratio == 1.0


@pytest.mark.parametrize("name", MODELS)
def test_every_element_has_a_lower_snake_case_name(name):
    m = _model(name)
    counts = {
        Obj.mjOBJ_BODY: m.nbody,
        Obj.mjOBJ_JOINT: m.njnt,
        Obj.mjOBJ_GEOM: m.ngeom,
        Obj.mjOBJ_SITE: m.nsite,
        Obj.mjOBJ_ACTUATOR: m.nu,
        Obj.mjOBJ_SENSOR: m.nsensor,
        Obj.mjOBJ_EQUALITY: m.neq,
        Obj.mjOBJ_TENDON: m.ntendon,
        Obj.mjOBJ_PAIR: m.npair,
        Obj.mjOBJ_KEY: m.nkey,
    }
    for obj, count in counts.items():
        first = 1 if obj == Obj.mjOBJ_BODY else 0  # the world body is named by MuJoCo
        for i, element in enumerate(_names(m, obj, count)[first:], start=first):
            assert element and NAME_RE.match(element), f"{obj.name} {i} is named {element!r}"


@pytest.mark.parametrize("name", MODELS)
def test_home_keyframe_is_valid(name):
    m = _model(name)
    d, key = _home(m)
    assert key >= 0
    mujoco.mj_forward(m, d)
    assert np.isfinite(d.qacc).all()
    assert all(w.number == 0 for w in d.warning)


@pytest.mark.parametrize("name", MODELS)
def test_random_controls_simulate_without_nan_or_warnings(name):
    rollout = _rollout(name)
    assert rollout.finite
    assert rollout.warnings == (0,) * len(rollout.warnings)


@pytest.mark.parametrize("name", MODELS)
def test_contacts_are_elliptic_never_pyramidal(name):
    rollout = _rollout(name)
    assert _fraction(rollout.efc_types, Cnstr.mjCNSTR_CONTACT_PYRAMIDAL) == 0
    assert _fraction(rollout.efc_types, Cnstr.mjCNSTR_CONTACT_ELLIPTIC) > 0


# --- single_joint -----------------------------------------------------------------------------


def test_single_joint_has_friction_loss_and_contact_impulses_that_vary():
    rollout = _rollout("single_joint")
    friction = _fraction(rollout.efc_types, Cnstr.mjCNSTR_FRICTION_DOF)
    contact = _fraction(rollout.efc_types, Cnstr.mjCNSTR_CONTACT_ELLIPTIC)
    assert friction == 1.0  # frictionloss rows are always present
    assert 0.2 < contact < 0.95  # the tip lifts off and lands again
    assert np.mean(np.abs(rollout.friction_force) > 0.1) > 0.5
    assert np.std(rollout.friction_force) > 0.3
    assert np.std(rollout.contact_normal_force) > 5.0


def test_single_joint_dry_friction_both_sticks_and_slips():
    rollout = _rollout("single_joint")
    sticks = rollout.friction_sticks
    in_contact = np.array([Cnstr.mjCNSTR_CONTACT_ELLIPTIC in t for t in rollout.efc_types])
    assert 0.2 < np.mean(sticks) < 0.8
    assert np.mean(sticks & ~in_contact) > 0.05  # held in the air by friction alone


# --- humanoid ---------------------------------------------------------------------------------

HUMANOID_HINGES = [
    "abdomen_z",
    "abdomen_y",
    "abdomen_x",
    *(
        f"{side}_{joint}"
        for side in ("right", "left")
        for joint in ("hip_x", "hip_z", "hip_y", "knee", "ankle_y", "ankle_x")
    ),
    *(
        f"{side}_{joint}"
        for side in ("right", "left")
        for joint in ("shoulder1", "shoulder2", "elbow")
    ),
]


def test_humanoid_has_free_root_and_21_limited_actuated_hinges():
    m = _model("humanoid")
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    hinges = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    assert sorted(m.joint(j).name for j in hinges) == sorted(HUMANOID_HINGES)
    assert all(m.jnt_limited[j] for j in hinges)
    actuated = {m.joint(int(m.actuator_trnid[a, 0])).name for a in range(m.nu)}
    assert actuated == set(HUMANOID_HINGES)


def test_humanoid_has_imu_mocap_joint_and_foot_touch_sensors():
    m = _model("humanoid")
    assert _sensors(m, mujoco.mjtSensor.mjSENS_ACCELEROMETER) == [("imu_acc", "imu")]
    assert _sensors(m, mujoco.mjtSensor.mjSENS_GYRO) == [("imu_gyro", "imu")]
    assert m.site("imu").bodyid == m.body("torso").id
    tracked = {"torso_marker", "pelvis_marker"}
    assert {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_FRAMEPOS)} == tracked
    assert {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_FRAMEQUAT)} == tracked
    assert {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_JOINTPOS)} == set(HUMANOID_HINGES)
    touch = {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_TOUCH)}
    assert touch == {"left_foot_touch", "right_foot_touch"}
    for side in ("left", "right"):
        # The touch site encloses the foot geom.
        site, geom = m.site(f"{side}_foot_touch"), m.geom(f"{side}_foot")
        assert site.bodyid == geom.bodyid
        assert np.all(site.size >= geom.size)
    for marker in ("torso", "pelvis", "head", "left_hand", "right_hand", "left_foot", "right_foot"):
        assert m.site(f"{marker}_marker").id >= 0


def test_humanoid_stands_on_both_feet_at_home():
    m = _model("humanoid")
    d, _ = _home(m)
    mujoco.mj_forward(m, d)
    feet = {m.geom("left_foot").id, m.geom("right_foot").id}
    in_contact = {g for c in d.contact[: d.ncon] for g in (c.geom1, c.geom2)}
    assert feet <= in_contact
    touch = {s for s, _ in _sensors(m, mujoco.mjtSensor.mjSENS_TOUCH)}
    assert all(d.sensor(s).data[0] > 0 for s in touch)


def test_humanoid_falls_and_comes_to_rest_at_the_paper_timestep():
    m = _model("humanoid")
    d, _ = _home(m)
    d.ctrl[:] = 0
    for _ in range(round(4.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    assert all(w.number == 0 for w in d.warning)
    assert d.qpos[2] < 0.5  # lying on the floor
    assert d.ncon >= 4
    assert np.abs(d.qvel).max() < 0.1


def test_humanoid_has_frictional_floor_and_frictionless_self_contacts():
    rollout = _rollout("humanoid")
    dims = frozenset().union(*rollout.contact_dims)
    assert dims == {1, 3}  # body-body condim 1, body-floor condim 3
    assert _fraction(rollout.efc_types, Cnstr.mjCNSTR_LIMIT_JOINT) > 0.2


# --- all_constraints --------------------------------------------------------------------------


def test_all_constraints_has_connect_weld_and_joint_equalities_active():
    m = _model("all_constraints")
    eq = mujoco.mjtEq
    assert sorted(m.eq_type.tolist()) == sorted(
        [eq.mjEQ_CONNECT.value, eq.mjEQ_WELD.value, eq.mjEQ_JOINT.value]
    )
    assert m.eq_active0.all()


def test_all_constraints_limits_cover_hinge_slide_ball_and_tendon():
    m = _model("all_constraints")
    limited_types = {int(m.jnt_type[j]) for j in range(m.njnt) if m.jnt_limited[j]}
    jt = mujoco.mjtJoint
    assert {jt.mjJNT_HINGE, jt.mjJNT_SLIDE, jt.mjJNT_BALL} <= limited_types
    assert m.tendon_limited.any()
    assert np.count_nonzero(m.dof_frictionloss) >= 3


def test_all_constraints_every_constraint_type_is_active_at_home():
    m = _model("all_constraints")
    d, _ = _home(m)
    mujoco.mj_forward(m, d)
    types = set(d.efc_type[: d.nefc].tolist())
    assert types == {
        Cnstr.mjCNSTR_EQUALITY,
        Cnstr.mjCNSTR_FRICTION_DOF,
        Cnstr.mjCNSTR_LIMIT_JOINT,
        Cnstr.mjCNSTR_LIMIT_TENDON,
        Cnstr.mjCNSTR_CONTACT_FRICTIONLESS,
        Cnstr.mjCNSTR_CONTACT_ELLIPTIC,
    }
    assert sorted(d.contact.dim[: d.ncon].tolist()) == [1, 3, 4, 6]
    is_limit = d.efc_type[: d.nefc] == Cnstr.mjCNSTR_LIMIT_JOINT
    limited = {m.joint(int(i)).name for i in d.efc_id[: d.nefc][is_limit]}
    assert limited == {"flap_hinge", "lift_slide", "stick_ball"}


def test_all_constraints_every_constraint_type_stays_common_under_random_controls():
    m = _model("all_constraints")
    rollout = _rollout("all_constraints")
    for cnstr in (
        Cnstr.mjCNSTR_EQUALITY,
        Cnstr.mjCNSTR_FRICTION_DOF,
        Cnstr.mjCNSTR_LIMIT_JOINT,
        Cnstr.mjCNSTR_LIMIT_TENDON,
        Cnstr.mjCNSTR_CONTACT_FRICTIONLESS,
        Cnstr.mjCNSTR_CONTACT_ELLIPTIC,
    ):
        assert _fraction(rollout.efc_types, cnstr) > 0.5, cnstr.name
    for dim in (1, 3, 4, 6):
        assert _fraction(rollout.contact_dims, dim) > 0.5, dim
    for joint in ("flap_hinge", "lift_slide", "stick_ball"):
        # Limits are hit, and also released: the motion is not frozen against them.
        assert 0.3 < _fraction(rollout.limited_joints, m.joint(joint).id) < 1.0, joint


def test_all_constraints_frictional_cones_are_truly_elliptic():
    m = _model("all_constraints")
    for p in range(m.npair):
        if m.pair_dim[p] > 1:
            # Tangential, torsional and rolling coefficients differ.
            assert len(set(m.pair_friction[p, : m.pair_dim[p] - 1].tolist())) > 1


# --- quadruped --------------------------------------------------------------------------------


def test_quadruped_has_actuated_hinges_imu_mocap_and_foot_touch_sensors():
    m = _model("quadruped")
    hinges = {
        m.joint(j).name for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
    }
    assert len(hinges) == 12
    assert {m.joint(int(m.actuator_trnid[a, 0])).name for a in range(m.nu)} == hinges
    assert {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_JOINTPOS)} == hinges
    assert _sensors(m, mujoco.mjtSensor.mjSENS_ACCELEROMETER) == [("imu_acc", "imu")]
    assert _sensors(m, mujoco.mjtSensor.mjSENS_GYRO) == [("imu_gyro", "imu")]
    assert _sensors(m, mujoco.mjtSensor.mjSENS_FRAMEPOS) == [("base_pos", "base_marker")]
    assert _sensors(m, mujoco.mjtSensor.mjSENS_FRAMEQUAT) == [("base_quat", "base_marker")]
    assert len(_sensors(m, mujoco.mjtSensor.mjSENS_TOUCH)) == 4


def test_quadruped_home_stands_on_four_feet_with_its_holding_ctrl():
    m = _model("quadruped")
    d, _ = _home(m)
    for _ in range(round(0.5 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    feet = {
        m.geom(f"{leg}_foot").id for leg in ("front_left", "front_right", "rear_left", "rear_right")
    }
    in_contact = {g for c in d.contact[: d.ncon] for g in (c.geom1, c.geom2)}
    assert feet <= in_contact
    assert d.qpos[2] > 0.3
    assert set(d.contact.dim[: d.ncon].tolist()) == {3}


# --- arm_box ----------------------------------------------------------------------------------


def test_arm_box_has_marker_set_wrist_force_torque_and_joint_sensors():
    m = _model("arm_box")
    markers = [m.site(i).name for i in range(m.nsite) if m.site(i).name.startswith("box_marker")]
    assert len(markers) >= 4
    assert markers == [f"box_marker{i}" for i in range(len(markers))]
    assert all(m.site(s).bodyid == m.body("box").id for s in markers)
    assert m.jnt_type[m.body("box").jntadr] == mujoco.mjtJoint.mjJNT_FREE
    assert _sensors(m, mujoco.mjtSensor.mjSENS_FORCE) == [("wrist_force", "wrist_ft")]
    assert _sensors(m, mujoco.mjtSensor.mjSENS_TORQUE) == [("wrist_torque", "wrist_ft")]
    hinges = {
        m.joint(j).name for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
    }
    assert len(hinges) == 7
    assert {o for _, o in _sensors(m, mujoco.mjtSensor.mjSENS_JOINTPOS)} == hinges
    assert {m.joint(int(m.actuator_trnid[a, 0])).name for a in range(m.nu)} == hinges


def test_arm_box_can_grasp_and_lift_the_box():
    m = _model("arm_box")
    d, _ = _home(m)
    q_home = d.qpos[:7].copy()
    ctrl_gravity = d.ctrl.copy()
    gear = m.actuator_gear[:, 0]
    for _ in range(round(2.5 / m.opt.timestep)):
        target = q_home.copy()
        if d.time > 1.0:  # raise the shoulder, keep the tool pointing down
            target[1] -= 0.35 * min(1.0, (d.time - 1.0) / 1.0)
            target[3] = np.pi - target[1] - target[2]
        tau = 300.0 * (target - d.qpos[:7]) - 20.0 * d.qvel[:7]
        d.ctrl[:] = np.clip(ctrl_gravity + tau / gear, -1.0, 1.0)
        if d.time > 0.3:
            d.ctrl[m.actuator("gripper_jaw").id] = 1.0  # close the jaw
        mujoco.mj_step(m, d)
    assert d.sensor("box_pos").data[2] > 0.12  # lifted from 0.05
    floor, box = m.geom("floor").id, m.geom("box").id
    assert not any({c.geom1, c.geom2} == {floor, box} for c in d.contact[: d.ncon])
    assert np.linalg.norm(d.sensor("wrist_force").data) > 5.0  # carries hand and box


def test_arm_box_random_controls_touch_the_box_on_the_floor():
    rollout = _rollout("arm_box")
    assert _fraction(rollout.contact_pairs, ("box", "floor")) > 0.9
    gripper = [("box", "fixed_finger"), ("box", "jaw_finger"), ("box", "palm")]
    assert any(pair in pairs for pairs in rollout.contact_pairs for pair in gripper)
