"""The mesh-free Menagerie models (physics/models/menagerie) against their upstream originals."""

from __future__ import annotations

from functools import cache

import mujoco
import numpy as np
import pytest
from numpy.typing import ArrayLike

from physics.dynamics import check_model
from physics.models.menagerie import convert
from physics.models.menagerie.convert import HERE, ORIGINAL, ROBOTS, Robot

MESH = mujoco.mjtGeom.mjGEOM_MESH
NAMES = [robot.name for robot in ROBOTS]
ROBOT = {robot.name: robot for robot in ROBOTS}
FREE_BODY = {"go2": "base", "h1": "pelvis"}

# contact settings a geom keeps through the conversion
CONTACT_FIELDS = (
    "friction",
    "solref",
    "solimp",
    "solmix",
    "condim",
    "margin",
    "gap",
    "priority",
    "contype",
    "conaffinity",
)


@cache
def converted(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(HERE / f"{name}.xml"))


@cache
def original_spec(name: str) -> mujoco.MjSpec:
    return mujoco.MjSpec.from_file(str(ORIGINAL / ROBOT[name].scene))


@cache
def original(name: str) -> mujoco.MjModel:
    """The upstream model compiled without its meshes (whose files are not here)."""
    spec = original_spec(name).copy()
    for geom in list(spec.geoms):
        if geom.type == MESH:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    return spec.compile()


def close(a: ArrayLike, b: ArrayLike) -> None:
    np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("robot", ROBOTS, ids=NAMES)
def test_converted_file_is_what_convert_writes(robot: Robot) -> None:
    written = (HERE / f"{robot.name}.xml").read_text()
    assert written.split("\n", 1)[1] == convert.to_xml(convert.convert(robot))


@pytest.mark.parametrize("name", NAMES)
def test_compiles_without_any_mesh_or_asset_file(name: str) -> None:
    m = converted(name)
    assert m.nmesh == 0
    assert int(MESH) not in m.geom_type
    spec = mujoco.MjSpec.from_file(str(HERE / f"{name}.xml"))
    assert not [t.file for t in spec.textures if t.file]


@pytest.mark.parametrize("name", NAMES)
def test_options_the_analytic_inverse_needs(name: str) -> None:
    m = converted(name)
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert m.opt.noslip_iterations == 0
    check_model(m, "native")  # joint damping keeps them off the reference path


@pytest.mark.parametrize("name", NAMES)
def test_timestep_and_impratio_are_upstream(name: str) -> None:
    m, o = converted(name), original(name)
    assert m.opt.impratio == o.opt.impratio
    assert m.opt.timestep == (ROBOT[name].timestep or o.opt.timestep)


@pytest.mark.parametrize("name", NAMES)
def test_masses_and_inertias_equal_upstream(name: str) -> None:
    m, o = converted(name), original(name)
    for b in range(o.nbody):
        c = m.body(o.body(b).name)
        for field in ("mass", "inertia", "ipos", "iquat", "pos", "quat"):
            close(getattr(c, field), getattr(o.body(b), field))
    robot = sum(m.body(o.body(b).name).mass[0] for b in range(o.nbody))
    close(robot, o.body_mass.sum())


@pytest.mark.parametrize("name", NAMES)
def test_joints_equal_upstream(name: str) -> None:
    m, o = converted(name), original(name)
    n, nv = o.njnt, o.nv  # added joints (the box) come after the robot's
    for field in ("jnt_type", "jnt_limited", "jnt_range", "jnt_pos", "jnt_axis", "jnt_solref"):
        close(getattr(m, field)[:n], getattr(o, field))
    for field in ("jnt_solimp", "jnt_stiffness", "jnt_margin", "jnt_bodyid"):
        close(getattr(m, field)[:n], getattr(o, field))
    for field in ("dof_armature", "dof_damping", "dof_frictionloss"):
        close(getattr(m, field)[:nv], getattr(o, field))
    close(m.qpos0[: o.nq], o.qpos0)


@pytest.mark.parametrize("name", NAMES)
def test_free_joints_are_named_after_their_body(name: str) -> None:
    m = converted(name)
    free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    assert free.size
    for j in free:
        assert m.joint(j).name == m.body(m.jnt_bodyid[j]).name + "_root"


@pytest.mark.parametrize("name", NAMES)
def test_actuators_equal_upstream(name: str) -> None:
    m, o = converted(name), original(name)
    assert m.nu == o.nu
    for field in (
        "actuator_trntype",
        "actuator_trnid",
        "actuator_gear",
        "actuator_dyntype",
        "actuator_dynprm",
        "actuator_gaintype",
        "actuator_gainprm",
        "actuator_biastype",
        "actuator_biasprm",
        "actuator_ctrllimited",
        "actuator_ctrlrange",
        "actuator_forcelimited",
        "actuator_forcerange",
    ):
        close(getattr(m, field), getattr(o, field))
    assert [m.actuator(i).name for i in range(m.nu)] == [o.actuator(i).name for i in range(o.nu)]


@pytest.mark.parametrize("name", NAMES)
def test_tendons_equalities_and_excludes_equal_upstream(name: str) -> None:
    m, o = converted(name), original(name)
    assert (m.ntendon, m.neq, m.nexclude) == (o.ntendon, o.neq, o.nexclude)
    close(m.wrap_prm, o.wrap_prm)
    for field in ("eq_type", "eq_obj1id", "eq_obj2id", "eq_data", "eq_solref", "eq_solimp"):
        close(getattr(m, field), getattr(o, field))


@pytest.mark.parametrize("name", NAMES)
def test_primitive_geoms_keep_upstream_shape_and_contact_settings(name: str) -> None:
    m, o = converted(name), original(name)
    for b in range(o.nbody):
        body = m.body(o.body(b).name).id
        kept = [
            g
            for g in range(m.ngeom)
            if m.geom_bodyid[g] == body and not m.geom(g).name.endswith("_collision")
        ]
        upstream = [g for g in range(o.ngeom) if o.geom_bodyid[g] == b]
        assert len(kept) == len(upstream), o.body(b).name
        for g, u in zip(kept, upstream, strict=True):
            for field in ("type", "size", "pos", "quat", *CONTACT_FIELDS):
                close(getattr(m.geom(g), field), getattr(o.geom(u), field))


@pytest.mark.parametrize("name", NAMES)
def test_replaced_meshes_keep_their_contact_settings(name: str) -> None:
    m = converted(name)
    replaced = [
        g for g in original_spec(name).geoms if g.type == MESH and g.contype | g.conaffinity
    ]
    for geom in replaced:
        primitive = m.geom(f"{geom.parent.name}_collision")
        assert primitive.type[0] in (
            mujoco.mjtGeom.mjGEOM_BOX.value,
            mujoco.mjtGeom.mjGEOM_CAPSULE.value,
        )
        for field in CONTACT_FIELDS:
            close(getattr(primitive, field), getattr(geom, field))
    assert (name == "panda_box") == bool(replaced)  # only the Panda collides through meshes


@pytest.mark.parametrize("name", NAMES)
def test_keyframe_is_upstream_and_valid(name: str) -> None:
    m, o = converted(name), original(name)
    close(m.key_qpos[0][: o.nq], o.key_qpos[0])
    close(m.key_ctrl[0], o.key_ctrl[0])
    qpos = m.key_qpos[0]
    for j in range(m.njnt):
        adr = m.jnt_qposadr[j]
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            assert np.linalg.norm(qpos[adr + 3 : adr + 7]) == pytest.approx(1.0)
        elif m.jnt_limited[j]:
            assert m.jnt_range[j][0] <= qpos[adr] <= m.jnt_range[j][1], m.joint(j).name
    lo, hi = m.actuator_ctrlrange.T
    assert np.all((lo <= m.key_ctrl[0]) & (m.key_ctrl[0] <= hi))
    # at the key nothing touches but the floor (no self-contact of the fitted primitives)
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_forward(m, d)
    floor = m.geom("floor").id
    assert d.ncon and all(floor in (c.geom1, c.geom2) for c in d.contact[: d.ncon])


@pytest.mark.parametrize("name", NAMES)
def test_upstream_sites_kept_and_sensor_sites_added(name: str) -> None:
    m, o = converted(name), original(name)
    for s in range(o.nsite):
        close(m.site(o.site(s).name).pos, o.site(s).pos)
    wanted = {
        "go2": {"imu": "base", "base_marker": "base"},
        "h1": {"imu": "torso_link", "pelvis_marker": "pelvis", "torso_marker": "torso_link"},
        "panda_box": {"box_center": "box", **{f"box_marker{i}": "box" for i in range(4)}},
    }[name]
    for site, body in wanted.items():
        assert m.body(m.site_bodyid[m.site(site).id]).name == body


@pytest.mark.parametrize("name", ["go2", "h1"])
def test_legged_robot_stands_for_1s_holding_the_keyframe(name: str) -> None:
    m = converted(name)
    d = convert.hold_keyframe(m, name, 1.0)
    assert np.all(np.isfinite(d.qpos))
    base = m.body(FREE_BODY[name]).id
    assert abs(d.xpos[base][2] - m.key_qpos[0][2]) < 0.03
    assert d.xmat[base][8] > np.cos(0.1)  # upright within 0.1 rad
    assert np.linalg.norm(d.xpos[base][:2]) < 0.03


def test_panda_holds_home_and_box_rests_for_1s() -> None:
    m = converted("panda_box")
    d = convert.hold_keyframe(m, "panda_box", 1.0)
    assert np.all(np.isfinite(d.qpos))
    np.testing.assert_allclose(d.qpos[:7], m.key_qpos[0][:7], atol=0.02)
    box = m.body("box").id
    np.testing.assert_allclose(d.xpos[box], convert.BOX_POS, atol=1e-3)
    assert np.abs(d.qvel).max() < 1e-2


def test_panda_fingers_can_grasp_the_box() -> None:
    """Reach over the box (damped least squares on the hand pose, from a folded guess), close
    the gripper: the fingertip pads of both fingers press on the box."""
    m = converted("panda_box")
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_forward(m, d)
    hand = m.body("hand").id
    down = d.xquat[hand].copy()  # the home pose points the hand down
    # the pads' lower half beside the box: hand origin 12.5 cm above the box centre
    target = np.add(convert.BOX_POS, [0.0, 0.0, 0.125])
    d.qpos[:7] = [0.0, 0.4, 0.0, -2.2, 0.0, 2.6, -0.785]
    lo, hi = m.jnt_range[:7].T
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for _ in range(100):
        mujoco.mj_forward(m, d)
        twist = np.zeros(3)  # the rotation still to go, in the hand frame
        mujoco.mju_subQuat(twist, down, d.xquat[hand])
        error = np.concatenate([target - d.xpos[hand], d.xmat[hand].reshape(3, 3) @ twist])
        mujoco.mj_jacBody(m, d, jacp, jacr, hand)
        J = np.vstack([jacp, jacr])[:, :7]
        step = J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(6), error)
        d.qpos[:7] = np.clip(d.qpos[:7] + step, lo, hi)
    assert np.linalg.norm(error) < 1e-6
    d.qvel[:] = 0
    d.ctrl[:7] = d.qpos[:7]
    d.ctrl[7] = 0.0  # close
    for _ in range(round(1.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    box = m.geom("box").id
    pads = {  # the upstream fingertip pads, not the box fitted to the finger mesh
        m.body(m.geom_bodyid[c.geom1 + c.geom2 - box]).name
        for c in d.contact[: d.ncon]
        if box in (c.geom1, c.geom2) and not m.geom(c.geom1 + c.geom2 - box).name
    }
    assert pads == {"left_finger", "right_finger"}
    np.testing.assert_allclose(d.ten_length[0], convert.BOX_HALF, atol=1e-3)  # closed on it
