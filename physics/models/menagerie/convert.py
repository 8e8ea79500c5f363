"""Convert MuJoCo Menagerie robots into self-contained, mesh-free MJCF models.

    python -m physics.models.menagerie.convert            # rewrite go2.xml, h1.xml, panda_box.xml
    python -m physics.models.menagerie.convert --report   # and print the facts in docs/menagerie.md

Each robot's upstream scene.xml (which includes the robot XML) is read from original/ with
mujoco.MjSpec, edited, and written beside this file. The mesh files are not in this repository,
so every mesh geom goes: visual ones are dropped, colliding ones become primitives. Masses,
inertias, joints, actuators, keyframes and per-geom contact settings are kept as upstream wrote
them. docs/menagerie.md lists every step and why.
"""

from __future__ import annotations

import argparse
import ctypes
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

HERE = Path(__file__).resolve().parent
ORIGINAL = HERE / "original"

MESH = mujoco.mjtGeom.mjGEOM_MESH
CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
BOX = mujoco.mjtGeom.mjGEOM_BOX

# Panda link capsules (the only colliding meshes in these models). The link inertias cannot give
# a size (link1's 0.70 kg m² would make a 1.3 m box), so one radius for all links: about the
# link housings (~10 cm across), and thin enough that the arm folded to reach the floor (joint4
# -2.4, joint6 2.8 rad) has no false self-contact (5 cm has link4 touching link6 there).
LINK_RADIUS = 0.045
# Capsule ends stop this far short of the joints: with a zero-length link between them (link1,
# link5) the capsules of links i and i+2 would otherwise overlap at rest and push each other
# forever, which the upstream meshes do not do.
JOINT_CLEARANCE = LINK_RADIUS + 0.02

# Collision meshes whose primitive comes from upstream rather than a fit: Menagerie's own
# mjx_panda.xml replaces the hand mesh with this capsule (same body frame).
UPSTREAM_PRIMITIVES: dict[str, dict[str, list[float]]] = {
    "hand_c": {"size": [0.04, 0.06, 0.0], "pos": [0.0, 0.0, 0.03], "quat": [1.0, 1.0, 0.0, 0.0]},
}

BOX_HALF = 0.025  # 5 cm cube
BOX_MASS = 0.2  # kg
BOX_POS = (0.5, 0.0, BOX_HALF)  # on the floor, 0.5 m in front of the Panda (as mjx_single_cube)


@dataclass(frozen=True)
class Robot:
    name: str  # output file: <name>.xml
    scene: str  # upstream scene, relative to original/
    markers: dict[str, str] = field(default_factory=dict)  # new mocap site -> body
    timestep: float | None = None  # None: the model's own
    with_box: bool = False


ROBOTS = (
    Robot("go2", "unitree_go2/scene.xml", {"base_marker": "base"}),
    Robot("h1", "unitree_h1/scene.xml", {"pelvis_marker": "pelvis", "torso_marker": "torso_link"}),
    # Under the Euler integrator the Panda's position servos (kv up to 450 N m s/rad on ~0.1
    # kg m² joints) diverge at its 2 ms step (upstream runs them implicitfast); 0.5 ms holds.
    Robot("panda_box", "franka_emika_panda/scene.xml", timestep=0.0005, with_box=True),
)


def convert(robot: Robot) -> mujoco.MjSpec:
    """The edited spec of one robot (see the module docstring)."""
    spec = mujoco.MjSpec.from_file(str(ORIGINAL / robot.scene))
    drop_visual_meshes(spec)
    replace_collision_meshes(spec)
    drop_file_assets(spec)
    set_options(spec, robot.timestep)
    name_free_joints(spec)
    for site, body in robot.markers.items():
        spec.body(body).add_site(name=site, group=4)
    if robot.with_box:
        add_box(spec)
    return spec


def drop_visual_meshes(spec: mujoco.MjSpec) -> None:
    # Visual meshes (contype = conaffinity = 0) take part in nothing but rendering.
    for geom in list(spec.geoms):
        if geom.type == MESH and geom.contype == 0 and geom.conaffinity == 0:
            spec.delete(geom)


def replace_collision_meshes(spec: mujoco.MjSpec) -> None:
    """One primitive per body in place of its colliding meshes, with their contact settings."""
    for body in spec.bodies:
        meshes = [g for g in body.geoms if g.type == MESH]
        if not meshes:
            continue
        # link5's three convex pieces make one link: one primitive for all of them.
        for extra in meshes[1:]:
            spec.delete(extra)
        geom = meshes[0]  # edited in place, so solref, solimp, friction, condim, margin,
        #                   contype, conaffinity, priority and group stay as upstream set them
        mesh = geom.meshname
        geom.meshname = ""
        geom.name = geom.name or f"{body.name}_collision"
        others = [g for g in body.geoms if g.type != MESH and (g.contype or g.conaffinity)]
        if mesh in UPSTREAM_PRIMITIVES:
            geom.type = CAPSULE
            for key, value in UPSTREAM_PRIMITIVES[mesh].items():
                setattr(geom, key, value)
        elif others:
            # A finger: its mesh is the finger from the joint up to the upstream fingertip
            # pads, so a box bounding the pads and the body origin.
            geom.type = BOX
            lo, hi = _bounds(others)
            geom.pos = (lo + hi) / 2
            geom.size = (hi - lo) / 2
        else:
            # An arm link: a capsule along the kinematic chain, from this joint to the next.
            geom.type = CAPSULE
            geom.fromto = _chain_segment(body)
            geom.size = [LINK_RADIUS, 0.0, 0.0]


def _bounds(geoms: list[mujoco.MjsGeom]) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame bounding box of boxes and the body origin."""
    points = [np.zeros(3)]
    for g in geoms:
        assert g.type == BOX, f"bounding {g.type} is not implemented"
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, np.asarray(g.quat, dtype=float))
        for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            points.append(np.asarray(g.pos) + rot.reshape(3, 3) @ (corner * np.asarray(g.size)))
    return np.min(points, axis=0), np.max(points, axis=0)


def _chain_segment(body: mujoco.MjsBody) -> list[float]:
    """fromto of a link capsule: origin to the first child's origin (or, where the child shares
    the origin, through the COM to twice its offset), each end JOINT_CLEARANCE short."""
    children = list(body.bodies)
    end = np.asarray(children[0].pos, dtype=float) if children else np.zeros(3)
    if np.linalg.norm(end) < 1e-3:
        end = 2 * np.asarray(body.ipos, dtype=float)
    length = float(np.linalg.norm(end))
    # a link shorter than twice the clearance keeps a tenth of its segment
    inset = min(JOINT_CLEARANCE, 0.45 * length) * end / length
    return [*inset, *(end - inset)]


def drop_file_assets(spec: mujoco.MjSpec) -> None:
    # Mesh and texture files are not in this repository; nothing refers to the meshes any more.
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    for texture in list(spec.textures):
        if texture.file:
            spec.delete(texture)
    spec.compiler.meshdir = ""


def set_options(spec: mujoco.MjSpec, timestep: float | None) -> None:
    # What physics/dynamics.py check_model requires of a model for the analytic inverse.
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    spec.option.noslip_iterations = 0
    if timestep is not None:
        spec.option.timestep = timestep
    # Every body has an explicit <inertial>: the primitives above must not add mass or inertia.
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE


def name_free_joints(spec: mujoco.MjSpec) -> None:
    # A free joint needs a name to be addressed; the project's models call it <body>_root.
    for joint in spec.joints:
        if joint.type == mujoco.mjtJoint.mjJNT_FREE and not joint.name:
            joint.name = f"{joint.parent.name}_root"


def add_box(spec: mujoco.MjSpec) -> None:
    """A free 5 cm, 0.2 kg cube on the floor within the arm's reach, with mocap marker sites."""
    box = spec.worldbody.add_body(name="box", pos=list(BOX_POS))
    box.add_freejoint(name="box_root")
    # Explicit inertia of a uniform cube, like every other body here.
    box.explicitinertial = True
    box.mass = BOX_MASS
    box.inertia = [BOX_MASS * (2 * BOX_HALF) ** 2 / 6] * 3
    box.ipos = [0.0, 0.0, 0.0]  # without it to_xml leaves the <inertial> out
    box.add_geom(name="box", type=BOX, size=[BOX_HALF] * 3, condim=3, rgba=[0.9, 0.4, 0.1, 1])
    box.add_site(name="box_center", group=4)
    corners = [(1, 1), (-1, 1), (-1, -1), (1, -1)]
    for i, (x, y) in enumerate(corners):
        box.add_site(name=f"box_marker{i}", pos=[x * BOX_HALF, y * BOX_HALF, BOX_HALF], group=4)
    # Keyframes must cover the new qpos: the box resting where it was placed.
    for key in spec.keys:
        key.qpos = [*key.qpos, *BOX_POS, 1.0, 0.0, 0.0, 0.0]


def write(robot: Robot) -> Path:
    spec = convert(robot)
    spec.compile()  # fail here, not in a user's run
    path = HERE / f"{robot.name}.xml"
    header = (
        f"<!-- Generated by physics/models/menagerie/convert.py from MuJoCo Menagerie "
        f"{Path(robot.scene).parent}/ (see original/ and docs/menagerie.md); do not edit. -->\n"
    )
    path.write_text(header + to_xml(spec))
    return path


def to_xml(spec: mujoco.MjSpec, digits: int = 15) -> str:
    """spec.to_xml() with `digits` significant digits instead of MuJoCo's 6, which would round
    upstream numbers (Panda link1's mass 4.970684 to 4.97068). The writer's precision is only
    settable through a private, exported C function of libmujoco."""
    library = ctypes.CDLL(str(next(Path(mujoco.__file__).parent.glob("libmujoco*"))))
    before = library._mjPRIVATE__get_xml_precision()
    library._mjPRIVATE__set_xml_precision(digits)
    try:
        return spec.to_xml()
    finally:
        library._mjPRIVATE__set_xml_precision(before)


@dataclass(frozen=True)
class Hold:
    """A joint PD servo to the keyframe through torque motors (for robots without servos)."""

    kp: float  # N m/rad
    kd: float  # N m s/rad
    # H1 only: its home pose has the centre of mass 2.4 cm in front of the heel edge and rolls
    # back onto the heels even with every joint welded, so the ankles flex toes-up as the
    # pelvis leans back (centre of pressure behind the centre of mass):
    # ankle target += lean_gain * sin(forward lean) + rate_gain * pitch rate.
    lean_gain: float = 0.0
    rate_gain: float = 0.0


# Go2 and H1 drive their joints with torque motors, so their keys' ctrl holds nothing (Go2's
# equals the key's joint angles, a position target read as N m; H1's key has none): a PD servo
# in Python holds them.
HOLDS = {
    "go2": Hold(kp=100.0, kd=3.0),
    "h1": Hold(kp=2000.0, kd=40.0, lean_gain=3.0, rate_gain=0.1),
}


def hold_keyframe(model: mujoco.MjModel, name: str, seconds: float) -> mujoco.MjData:
    """Simulate `seconds` from the first keyframe, holding it."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    steps = round(seconds / model.opt.timestep)
    hold = HOLDS.get(name)
    if hold is None:  # the Panda: its position servos hold the key's ctrl
        mujoco.mj_step(model, data, nstep=steps)
        return data
    joints = model.actuator_trnid[:, 0]  # each Go2/H1 motor drives one hinge
    qadr, dofs = model.jnt_qposadr[joints], model.jnt_dofadr[joints]
    key = model.key_qpos[0][qadr]
    ankles = np.array(["ankle" in model.actuator(i).name for i in range(model.nu)])
    for _ in range(steps):
        tilt = data.xmat[1][2]  # sine of the base's (body 1) forward lean
        target = key + ankles * (hold.lean_gain * tilt + hold.rate_gain * data.qvel[4])
        torque = hold.kp * (target - data.qpos[qadr]) - hold.kd * data.qvel[dofs]
        data.ctrl[:] = np.clip(torque, *model.actuator_ctrlrange.T)
        mujoco.mj_step(model, data)
    return data


def report(name: str) -> str:
    """The facts docs/menagerie.md quotes, measured after holding the keyframe for 1 s."""
    model = mujoco.MjModel.from_xml_path(str(HERE / f"{name}.xml"))
    start = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, start, 0)
    mujoco.mj_forward(model, start)
    data = hold_keyframe(model, name, 1.0)
    floor = model.geom("floor").id
    contacts = [c for c in data.contact[: data.ncon] if floor in (c.geom1, c.geom2)]
    deepest = min(contacts, key=lambda c: c.dist)
    other = deepest.geom2 if deepest.geom1 == floor else deepest.geom1
    gains = sorted({mujoco.mjtGain(g).name for g in model.actuator_gaintype})
    biases = sorted({mujoco.mjtBias(b).name for b in model.actuator_biastype})
    free = model.body("box" if name == "panda_box" else 1).id  # the floating body
    robot = sum(model.body_mass[b] for b in range(model.nbody) if model.body(b).name != "box")
    return (
        f"{name}: robot mass {robot:.6g} kg, nq {model.nq}, nv {model.nv}, "
        f"nu {model.nu}, gain {gains}, bias {biases}, timestep {model.opt.timestep}, "
        f"impratio {model.opt.impratio:g}, {len(contacts)} floor contacts, deepest "
        f"{-1000 * deepest.dist:.2f} mm ({model.geom(other).name or other}), "
        f"{model.body(free).name} z {start.xpos[free][2]:.4f} -> {data.xpos[free][2]:.4f} m"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="print the measured facts")
    args = parser.parse_args()
    for robot in ROBOTS:
        print(f"wrote {write(robot).relative_to(HERE.parents[2])}")
    if args.report:
        for robot in ROBOTS:
            print(report(robot.name))


if __name__ == "__main__":
    main()
