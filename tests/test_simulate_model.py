"""`physfuse simulate --model MODEL.xml`: any MJCF model with a keyframe, simulated holding it.

The converted Menagerie robots (Go2: motors, impratio 100; H1: a motor-driven humanoid;
Panda: position servos and a free box with markers; ANYmal C: position servos with force
limits, joint friction loss, cylinders, a base turned about z) and one bundled model are simulated
briefly once per module; the tests check the log, the controller's commands, that the robots
stay up, that the mismatch scales the model's own contact softness, the config, and the
command line's errors.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest

from estimator.cli import main
from estimator.config import load_config
from estimator.evaluate import compare_states
from estimator.io.mcap_writer import imu_bias_message
from estimator.io.state_topics import read_metadata, read_state_topics
from estimator.simulate import Ros2Writer, SimulationResult, simulate
from estimator.simulate.controllers import short_of_holding, unstable_under_euler
from estimator.simulate.mismatch import Mismatch
from estimator.simulate.model_scenario import model_scenario
from physics.model import load_model
from physics.native import NativeDynamics
from physics.softness import Softness

ROOT = Path(__file__).resolve().parents[1]
MENAGERIE = ROOT / "physics" / "models" / "menagerie"
GO2, H1, PANDA, ANYMAL = (
    MENAGERIE / f"{name}.xml" for name in ("go2", "h1", "panda_box", "anymal_c")
)
HUMANOID = ROOT / "physics" / "models" / "humanoid.xml"
BOX_MARKERS = [f"box_marker{i}" for i in range(4)]


@dataclass(frozen=True)
class Run:
    result: SimulationResult
    log: Path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Run]:
    folder = tmp_path_factory.mktemp("simulate_model")
    settings = {
        "go2": (GO2, {"excitation_rad": 0.1}, 1.0),
        "h1": (H1, {"pushes": "pelvis"}, 2.0),
        "panda_box": (PANDA, {"markers": BOX_MARKERS, "excitation_rad": 0.2}, 1.0),
        "anymal_c": (ANYMAL, {"excitation_rad": 0.1, "pushes": "base"}, 1.5),
        "humanoid": (HUMANOID, {}, 1.0),
    }
    out = {}
    for name, (path, options, duration) in settings.items():
        log = folder / f"{name}.mcap"
        scenario = model_scenario(str(path), **options)
        out[name] = Run(simulate(scenario, log, seed=0, duration_s=duration), log)
    return out


def _qadr(model: mujoco.MjModel, actuators: range) -> np.ndarray:
    return model.jnt_qposadr[model.actuator_trnid[actuators, 0]]


# -- the log -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "sensors"),
    [
        ("go2", {"/mocap/base/pose", "/imu", "/joint_states", "/joint_commands"}),
        ("h1", {"/mocap/pelvis/pose", "/imu", "/joint_states", "/joint_commands"}),
        ("panda_box", {"/mocap/box/pose", "/mocap/markers", "/joint_states", "/joint_commands"}),
        ("anymal_c", {"/mocap/base/pose", "/imu", "/joint_states", "/joint_commands"}),
        ("humanoid", {"/mocap/torso/pose", "/imu", "/joint_states", "/joint_commands"}),
    ],
)
def test_log_has_the_sensor_topics_ground_truth_and_metadata(runs, name, sensors):
    run = runs[name]
    truth = {t for t in run.result.topics if t.startswith("/ground_truth/")}
    assert set(run.result.topics) == sensors | truth
    free = {"h1": "pelvis", "panda_box": "box", "humanoid": "torso"}.get(name, "base")
    assert {f"/ground_truth/odometry/{free}", "/ground_truth/joint_states"} <= truth
    assert "/ground_truth/contacts" in truth
    assert ("/ground_truth/imu_bias/imu" in truth) == ("/imu" in sensors)
    states = read_state_topics(run.log)
    assert states.joints is not None and len(states.joints.t_ns) == run.result.trajectory.steps
    simulation = read_metadata(run.log)["physfuse.simulation"]
    model = {"go2": GO2, "h1": H1, "panda_box": PANDA, "anymal_c": ANYMAL}.get(name, HUMANOID)
    assert simulation["model"] == str(model) and simulation["seed"] == "0"
    assert simulation["keyframe"] == ("standing" if name == "anymal_c" else "home")  # upstream's


def test_ground_truth_imu_bias_is_named_by_its_site_as_the_estimates(runs, tmp_path):
    run = runs["go2"]
    truth = read_state_topics(run.log)
    assert list(truth.imu_bias) == ["imu"]  # the site, /ground_truth/imu_bias/imu
    # an estimate whose config calls the IMU stream differently still writes the site's name
    path = tmp_path / "estimate.mcap"
    series = truth.imu_bias["imu"]
    with Ros2Writer(path) as writer:
        for t, bias in zip(series.t_ns, series.values + 0.01, strict=True):
            m = imu_bias_message("/estimate", "base_imu", int(t), "imu", bias)
            assert m.topic == "/estimate/imu_bias/imu"
            writer.write(m.topic, m.msg_type, m.fields, m.log_time_ns)
    estimate = read_state_topics(path, "/estimate")
    metrics = compare_states(estimate, truth, load_model(GO2))
    assert metrics["imu_bias"]["imu"]["accel_mps2"] == pytest.approx(0.01 * np.sqrt(3), rel=1e-6)


# -- the controller ------------------------------------------------------------------------------
def test_position_servos_get_joint_targets_and_the_gripper_its_opening(runs):
    traj = runs["panda_box"].result.trajectory
    arm = range(7)
    targets, angles = traj.ctrl[:, arm], traj.qpos[:-1, _qadr(traj.model, arm)]
    # targets = the joint angles it tracks (the excitation swings them by tenths of a rad)
    assert np.abs(targets - angles).max() < 0.1
    assert np.ptp(angles, axis=0).max() > 0.1
    # actuator8 (split tendon, ctrl 0-255 for 0-0.08 m): the keyframe's open gripper
    assert traj.ctrl[:, 7] == pytest.approx(255.0)


@pytest.mark.parametrize("name", ["go2", "h1"])
def test_motors_get_torques(runs, name):
    traj = runs[name].result.trajectory
    dofs = traj.model.jnt_dofadr[traj.model.actuator_trnid[:, 0]]
    # gear 1: the commanded torque is the actuator force on the joint
    assert np.allclose(traj.qfrc_actuator[:, dofs], traj.ctrl, atol=1e-9)
    # holding the keyframe takes torque (knees: several N m)
    assert np.abs(traj.ctrl).max() > 5.0


@pytest.mark.parametrize(
    ("name", "low", "high"),
    [("go2", 0.22, 0.30), ("h1", 0.95, 1.0), ("anymal_c", 0.45, 0.57), ("humanoid", 1.2, 1.35)],
)
def test_floating_robots_stay_up(runs, name, low, high):
    run = runs[name]
    z = run.result.trajectory.qpos[:, 2]  # the base's free joint comes first
    assert low < z.min() and z.max() < high
    if name in ("h1", "anymal_c"):  # pushed and excited, and still up
        assert run.result.pushes and run.result.pushes[0].start_s == 1.0


@pytest.mark.parametrize("name", ["go2", "h1", "panda_box", "anymal_c"])
def test_the_inverse_at_a_simulated_trajectory_returns_its_actuator_forces(runs, name):
    """mj_inverse (the estimator's engine call) at the simulated states of each public robot,
    with the simulated (true) model, gives back the actuators' force of each step (pushes
    aside): contacts of condim 6 with their own solimp, elliptic cones at impratio 100, joint
    friction loss and damping are the forward step's, to rounding."""
    traj = runs[name].result.trajectory
    dynamics = NativeDynamics(traj.model)
    pushed = np.zeros(len(traj.qvel), bool)
    for push in runs[name].result.pushes:
        steps = np.arange(len(traj.qvel)) * traj.h
        pushed |= (steps >= push.start_s - traj.h) & (steps <= push.start_s + push.duration_s)
    steps = [k for k in range(0, len(traj.qvel) - 1, 9) if not pushed[k]]
    for k in steps:
        qacc = (traj.qvel[k + 1] - traj.qvel[k]) / traj.h
        u = dynamics.inverse(traj.qpos[k], traj.qvel[k], qacc).qfrc_inverse
        scale = max(np.abs(traj.qfrc_actuator[k]).max(), 1.0)
        assert np.abs(u - traj.qfrc_actuator[k]).max() / scale < 1e-6, (name, k)


def test_panda_holds_its_arm_and_the_box_rests(runs):
    traj = runs["panda_box"].result.trajectory
    box = traj.model.jnt_qposadr[traj.model.joint("box_root").id]
    assert np.abs(traj.qpos[:, box + 2] - 0.025).max() < 1e-3
    arm = _qadr(traj.model, range(7))
    assert np.abs(traj.qpos[:, arm] - traj.qpos[0, arm]).max() < 0.3


# -- the mismatch: a scale of the model's own softness ------------------------------------------
def test_go2_solimp_solref_and_impratio_survive_scaled_into_the_true_model(runs):
    result = runs["go2"].result
    nominal, true = load_model(GO2), result.trajectory.model
    s_eps = result.mismatch.softness["eps_scale"][1]
    s_kappa = result.mismatch.softness["kappa_scale"][1]
    assert s_eps != 1.0 and s_kappa != 1.0 and result.true_softness is None
    assert true.opt.impratio == nominal.opt.impratio == 100.0
    d = nominal.geom_solimp[:, :2]
    assert len({tuple(row) for row in d}) > 1  # the feet's own solimp (0.015, 1) and others'
    eps = (1.0 - d) / d
    assert true.geom_solimp[:, :2] == pytest.approx(1.0 / (1.0 + s_eps * eps), rel=1e-12)
    assert np.array_equal(true.geom_solimp[:, 2:], nominal.geom_solimp[:, 2:])
    kappa = np.maximum(nominal.geom_solref[:, 0] * s_kappa, 2 * nominal.opt.timestep)
    assert true.geom_solref[:, 0] == pytest.approx(kappa, rel=1e-12)
    assert np.array_equal(true.geom_solref[:, 1], nominal.geom_solref[:, 1])
    assert np.array_equal(true.dof_frictionloss, nominal.dof_frictionloss)


def test_scaling_a_bundled_models_softness_is_the_papers_mismatch():
    # the bundled models carry the paper's one softness: a scale of it is the uniform mismatch
    nominal = load_model(HUMANOID)
    _, paper, _ = Mismatch().apply(nominal, np.random.default_rng(3))
    scaled, none, record = Mismatch().apply(nominal, np.random.default_rng(3), own_softness=True)
    assert none is None and isinstance(paper, Softness)
    assert record.softness["eps_scale"][1] * 0.05 == pytest.approx(paper.eps, rel=1e-12)
    assert scaled.geom_solimp[:, :2] == pytest.approx(paper.d, rel=1e-12)
    assert scaled.geom_solref[:, 0] == pytest.approx(paper.kappa, rel=1e-12)


def test_no_mismatch_simulates_the_model_itself():
    scenario = model_scenario(str(GO2))
    result = simulate(scenario, io.BytesIO(), duration_s=0.02, mismatch=False)
    nominal, true = load_model(GO2), result.trajectory.model
    for field in ("geom_solimp", "geom_solref", "body_mass", "geom_friction"):
        assert np.array_equal(getattr(true, field), getattr(nominal, field)), field


# -- the command line ----------------------------------------------------------------------------
def test_cli_writes_a_log_and_a_config_that_inspect_reads(tmp_path, capsys, monkeypatch):
    (tmp_path / "configs").mkdir()
    log, config = tmp_path / "panda.mcap", tmp_path / "configs" / "panda.toml"
    argv = ["simulate", "--model", str(PANDA), "--markers", *BOX_MARKERS, "--duration", "0.2"]
    assert main([*argv, "--out", str(log), "--config-out", str(config)]) == 0
    out, _ = capsys.readouterr()
    assert f"{log}: panda_box, seed 0, 0.2 s simulated" in out
    text = config.read_text()
    assert 'model = "../' in text  # relative to the config's folder
    loaded = load_config(config)
    assert loaded.model_path.resolve() == PANDA.resolve()
    assert {s.kind for s in loaded.streams.values()} == {
        "pose",
        "markers",
        "joint_state",
        "command",
    }
    assert main(["inspect", str(log), "--config", str(config)]) == 0
    # the estimate names its model so that it loads without the config, from anywhere
    out_dir = tmp_path / "estimate"
    argv = ["estimate", str(log), "--config", str(config), "--out", str(out_dir), "--method", "raw"]
    assert main([*argv, "--quiet"]) == 0
    monkeypatch.chdir(tmp_path / "configs")
    named = read_metadata(out_dir / "estimate.mcap")["physfuse.estimate"]["model"]
    assert Path(named) == PANDA.resolve()
    assert load_model(named).nq == load_model(PANDA).nq
    capsys.readouterr()


def _model_file(tmp_path: Path, actuator: str, option: str = "", key: bool = True) -> Path:
    path = tmp_path / "robot.xml"
    path.write_text(
        f"""<mujoco><option cone="elliptic" {option}/><worldbody>
        <body name="arm"><joint name="hinge"/><geom size="0.1" mass="1"/></body></worldbody>
        <actuator>{actuator}</actuator>
        {'<keyframe><key name="home"/></keyframe>' if key else ""}</mujoco>"""
    )
    return path


def test_cli_warns_when_the_actuators_cannot_hold_the_keyframe_and_the_robot_falls(
    tmp_path, capsys
):
    """A pole standing on the floor, tilted 5°, a weak position servo at its top holding 1 kg
    0.1 m out (kp 1, targets within ±0.1 rad: at most 0.1 N m of the 0.98 N m it takes): both
    are one line each, and the log is written (it records the fall)."""
    model = tmp_path / "pole.xml"
    model.write_text(
        """<mujoco><option cone="elliptic"/><worldbody><geom type="plane" size="0 0 1"/>
        <body name="pole" pos="0 0 0.5"><freejoint name="pole_root"/>
        <geom type="capsule" size="0.05" fromto="0 0 -0.45 0 0 0.45" mass="1"/>
        <body name="tip" pos="0 0 0.45"><joint name="wrist" axis="0 1 0"/>
        <geom size="0.05" pos="0.1 0 0" mass="1"/></body></body></worldbody>
        <actuator><position name="wrist" joint="wrist" kp="1" ctrlrange="-0.1 0.1"/></actuator>
        <keyframe><key name="home" qpos="0 0 0.5 0.9990482 0 0.0436194 0 0"/></keyframe>
        </mujoco>"""
    )
    log = tmp_path / "pole.mcap"
    assert main(["simulate", "--model", str(model), "--duration", "2", "--out", str(log)]) == 0
    _, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 2, err
    assert "keyframe 'home' takes more than the model's actuators give" in lines[0]
    assert "wrist needs -0.977" in lines[0] and "(can give -0.1 … 0.1)" in lines[0]
    assert "the robot fell" in lines[1] and log.is_file()
    stout = tmp_path / "stout.xml"  # the same servo, strong enough: no warning about it
    stout.write_text(model.read_text().replace('kp="1" ctrlrange="-0.1 0.1"', 'kp="100"'))
    assert short_of_holding(load_model(stout), 0) == []


def test_cli_warns_when_a_servo_is_too_stiff_for_the_euler_step(tmp_path, capsys):
    """A position servo with kv 10 N m s/rad on a 0.004 kg m² link: h kv/m = 5 at the 2 ms
    step, where explicit damping is stable below 2 (Menagerie's Spot knees: 5.2); the line
    names it and the timestep that would do (2 ms · 2/5). With kv 1 nothing is said."""
    servo = '<position joint="hinge" name="servo" kp="10" kv="{kv}"/>'
    model = _model_file(tmp_path, servo.format(kv=10))
    assert unstable_under_euler(load_model(model), 0) == {"servo": pytest.approx(5.0)}
    log = tmp_path / "servo.mcap"
    assert main(["simulate", "--model", str(model), "--duration", "0.1", "--out", str(log)]) == 0
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "cannot integrate the servo feedback of servo" in line
    assert '<option timestep="0.0008"/>' in line
    assert unstable_under_euler(load_model(_model_file(tmp_path, servo.format(kv=1))), 0) == {}


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "give a SCENARIO (humanoid_push, "),
        (["humanoid_push", "--model", str(GO2)], "give SCENARIO (humanoid_push) or --model"),
        (["single_joint", "--imu", "imu"], "--imu applies to --model MODEL.xml, not to a SCEN"),
        (["--model", "nope.xml"], "--model nope.xml: no such MJCF file (*.xml)"),
        (["--model", str(GO2), "--keyframe", "sit"], "has no such keyframe; its keyframes: home"),
        (["--model", str(GO2), "--mocap", "tail"], f"--mocap tail: {GO2} has no (moving) body"),
        (["--model", str(PANDA), "--markers", "x"], f"--markers x: {PANDA} has no site 'x'"),
        (["--model", str(GO2), "--imu", "chest"], f"--imu chest: {GO2} has no site 'chest'"),
        (["--model", str(GO2), "--pushes", "head"], f"--pushes head: {GO2} has no (moving) body"),
        (["--model", str(GO2), "--excitation", "-1"], "--excitation -1.0: expected an amplitude"),
        (["--model", str(GO2), "--duration", "0"], "--duration 0.0: expected a positive"),
    ],
)
def test_cli_rejects_bad_flags_in_one_line(tmp_path, capsys, argv, message):
    log = tmp_path / "x.mcap"
    code = main(["simulate", *argv, "--out", str(log)])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("physfuse simulate: error: ")
    assert message in err
    assert not log.exists()


@pytest.mark.parametrize(
    ("actuator", "option", "key", "message"),
    [
        ('<general name="a" joint="hinge" dyntype="filter"/>', "", True, "has activation dynamics"),
        ('<velocity name="a" joint="hinge" kv="1"/>', "", True, "neither a motor"),
        ('<motor name="a" joint="hinge"/>', "", False, "the model has no keyframe"),
        ('<motor name="a" joint="hinge"/>', 'integrator="RK4"', True, 'option integrator="rk4"'),
        ('<motor joint="hinge"/>', "", True, "actuator #0 has no name"),
    ],
)
def test_cli_rejects_models_it_cannot_drive_in_one_line(
    tmp_path, capsys, actuator, option, key, message
):
    path = _model_file(tmp_path, actuator, option, key)
    code = main(["simulate", "--model", str(path), "--out", str(tmp_path / "x.mcap")])
    _, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1
    assert f"--model {path}: " in err and message in err
