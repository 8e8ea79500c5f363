"""`physfuse simulate`: realistic robot logs with ground truth, read back every way we read logs.

Each scenario is simulated briefly once per module; the tests read the logs back with our
reader and the scenario's config, decode the ground truth, check it against MuJoCo and the
paper's cone, check every sensor imperfection against the truth the simulator returns, and
open the logs in Rerun's MCAP importer.
"""

from __future__ import annotations

import io
import json
import math
import re
import shlex
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import rerun as rr
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.io.logs.ros2_types import (
    CONTACT_ARRAY_MSG,
    CONTACT_MSG,
    DIAGNOSTIC_EVENT_MSG,
    message_definition,
)
from estimator.io.mcap_writer import Ros2Writer
from estimator.rotations import quat_mul
from estimator.simulate import (
    SCENARIOS,
    SimulationError,
    SimulationResult,
    StateLayout,
    get_scenario,
    scenario_config,
    simulate,
    state_data,
    write_state,
)
from estimator.simulate.conditions import CONDITIONS, OUTLIER_PROBABILITY, with_condition
from estimator.simulate.controllers import Push
from estimator.simulate.mismatch import Mismatch
from estimator.simulate.sensors import (
    Commands,
    Encoders,
    Imu,
    ImuNoise,
    MocapNoise,
    MocapPoses,
)
from physics.dynamics import make_dynamics
from physics.model import load_model

ROOT = Path(__file__).resolve().parents[1]
NS = 1_000_000_000
SHORT_S = {
    "humanoid_push": 2.0,
    "humanoid_fall": 2.0,
    "quadruped_trot": 1.5,
    "arm_box": 2.0,
    "single_joint": 1.0,
}


@dataclass(frozen=True)
class Run:
    result: SimulationResult
    log: Path
    config: Path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Run]:
    folder = tmp_path_factory.mktemp("simulate")
    out = {}
    for name, duration in SHORT_S.items():
        log = folder / f"{name}.mcap"
        config = folder / f"{name}.toml"
        config.write_text(scenario_config(name))
        out[name] = Run(simulate(name, log, seed=0, duration_s=duration), log, config)
    return out


def _decoded(path: Path, topics: list[str] | None = None):
    """(topic, log_time_ns, message) of every message on `topics`, in file order."""
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(
            topics=topics, log_time_order=False
        ):
            yield channel.topic, message.log_time, decoded


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with path.open("rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def _stamp(header) -> int:
    return int(header.stamp.sec) * NS + int(header.stamp.nanosec)


def _world_force(contact) -> np.ndarray:
    """(3,) world-frame force of a decoded Contact on its geom2's body."""
    q = contact.orientation
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.array([q.w, q.x, q.y, q.z]))
    return rot.reshape(3, 3) @ np.array(contact.force[:3])


# -- the log as the estimator reads it ------------------------------------------------------------
def test_every_scenario_is_read_back_with_its_config_and_has_ground_truth(runs):
    for name, run in runs.items():
        config = load_config(run.config)
        log = read_log(run.log, config, decode_all=True)
        assert not log.warnings, name
        for stream, measurement in log.measurements.items():
            assert len(measurement) > 0, (name, stream)
            bad = measurement.bad
            if measurement.kind == "markers":
                # frames with some markers occluded: the reader may keep them (NaN entries) or
                # skip them as `nan`; either way every frame sent is accounted for
                assert bad.total == bad.nan, (name, stream, bad)
                assert len(measurement) + bad.nan == log.topics[measurement.topic].count
            else:
                assert bad.total == 0, (name, stream, bad)
        model = run.result.trajectory.model
        ground_truth = StateLayout.of(model).topics("/ground_truth")
        assert set(ground_truth) <= set(log.topics), name
        for topic, msg_type in ground_truth.items():
            stats = log.topics[topic]
            assert stats.msg_type == msg_type
            assert stats.count == run.result.trajectory.steps, (name, topic)
        assert set(run.result.topics) == set(log.topics)


def test_log_has_the_rosbag2_layout(runs):
    with runs["quadruped_trot"].log.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            assert "reliability:" in channel.metadata["offered_qos_profiles"]
            schema = summary.schemas[channel.schema_id]
            assert schema.encoding == "ros2msg"
    sensor_qos = _channel_metadata(runs["quadruped_trot"].log)["/imu"]
    assert "best_effort" in sensor_qos


def _channel_metadata(path: Path) -> dict[str, str]:
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {c.topic: c.metadata["offered_qos_profiles"] for c in summary.channels.values()}


def test_contact_message_definition_is_the_documented_msg_files():
    folder = ROOT / "msgs" / "physfuse_msgs" / "msg"
    assert (folder / "Contact.msg").read_text() == CONTACT_MSG
    assert (folder / "ContactArray.msg").read_text() == CONTACT_ARRAY_MSG
    text = message_definition("physfuse_msgs/msg/ContactArray")
    assert text.startswith(CONTACT_ARRAY_MSG)
    assert "MSG: physfuse_msgs/Contact\n" + CONTACT_MSG in text
    assert "MSG: geometry_msgs/Quaternion" in text
    assert (folder / "DiagnosticEvent.msg").read_text() == DIAGNOSTIC_EVENT_MSG
    assert message_definition("physfuse_msgs/msg/DiagnosticEvent").startswith(DIAGNOSTIC_EVENT_MSG)


# -- ground truth ----------------------------------------------------------------------------------
def test_ground_truth_odometry_is_what_mocap_measures_within_its_noise(runs):
    run = runs["humanoid_push"]
    times, positions, quats = [], [], []
    for _, _, msg in _decoded(run.log, ["/ground_truth/odometry/torso"]):
        times.append(_stamp(msg.header))
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        positions.append([p.x, p.y, p.z])
        quats.append([q.w, q.x, q.y, q.z])
        assert msg.child_frame_id == "torso"
        assert not any(msg.pose.covariance)
    times_rel = np.array(times) - run.result.trajectory.t0_ns
    assert np.array_equal(times_rel, run.result.trajectory.step_ns(np.arange(len(times))))
    config = load_config(run.config)
    mocap = read_log(run.log, config).measurements["mocap_torso"]
    truth = run.result.sensors["mocap"]
    visible = truth["visible"][:, 0]
    outlier = truth["outlier"][visible, 0]
    assert len(mocap) == visible.sum()
    # the config's time offset undoes the mocap clock: t is the true time up to the jitter
    t_true = truth["t_ns"][visible] + run.result.trajectory.t0_ns
    assert np.abs(mocap.t_ns - t_true).max() <= 3 * 20_000
    # ground truth at the mocap frame times (positions move linearly within a step)
    gt = np.stack(
        [np.interp(mocap.t_ns, np.array(times), np.array(positions)[:, i]) for i in range(3)], 1
    )
    error = np.linalg.norm(mocap.element("torso_marker")[:, :3] - gt, axis=1)
    noise = MocapNoise().position_std_m
    assert error[~outlier].max() < 6 * noise + 2e-4  # 6σ in 3D, plus 60 µs of motion
    assert (error[outlier] > MocapNoise().outlier_m[0] - 6 * noise).all()
    # orientation: the angle between measured and true within the noise
    q_meas = mocap.element("torso_marker")[~outlier, 3:]
    q_true = run.result.sensors["mocap"]["quat_wxyz"][visible][~outlier, 0]
    dot = np.abs(np.sum(q_meas * q_true, axis=1))
    angle = 2 * np.arccos(np.clip(dot, -1, 1))
    assert angle.max() < 6 * MocapNoise().orientation_std_rad


def test_contact_impulses_lie_in_the_friction_cone_by_branch(runs):
    branches = {0: 0, 1: 0, 4: 0}
    for name in ("arm_box", "quadruped_trot", "single_joint"):
        run = runs[name]
        model = run.result.trajectory.model
        h = run.result.trajectory.h
        for _, _, msg in _decoded(run.log, ["/ground_truth/contacts"]):
            assert msg.timestep == h
            for c in msg.contacts:
                impulse = np.array(c.impulse)
                assert impulse[0] >= 0.0
                assert np.allclose(np.array(c.force), impulse / h)
                assert not impulse[c.dim :].any()
                g1, g2 = (
                    mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, g)
                    for g in (c.geom1, c.geom2)
                )
                mu = max(model.geom_friction[g1, 0], model.geom_friction[g2, 0])
                tangent = math.hypot(impulse[1], impulse[2])
                branches[c.branch] += 1
                if c.branch == 0:  # separating: zero impulse
                    assert not impulse.any()
                elif c.branch == 1:  # sticking: inside the cone
                    assert tangent <= mu * impulse[0] * (1 + 1e-9)
                else:  # sliding: on the cone's surface
                    assert c.branch == 4
                    assert tangent == pytest.approx(mu * impulse[0], rel=1e-9)
    assert all(count > 0 for count in branches.values()), branches


def test_standing_humanoid_carries_its_weight_on_both_feet(runs):
    run = runs["humanoid_push"]
    weight = run.result.trajectory.model.body_subtreemass[0] * 9.81
    pushes = run.result.pushes
    vertical = []
    for _, _, msg in _decoded(run.log, ["/ground_truth/contacts"]):
        bodies = {c.body2 for c in msg.contacts}
        assert bodies == {"left_foot", "right_foot"}
        assert {c.body1 for c in msg.contacts} == {"world"}
        t = (_stamp(msg.header) - run.result.trajectory.t0_ns) / NS
        if not any(p.start_s - 0.05 <= t <= p.start_s + 0.6 for p in pushes):
            vertical.append(sum(_world_force(c)[2] for c in msg.contacts))
    assert np.mean(vertical) == pytest.approx(weight, rel=0.02)
    assert run.result.trajectory.qpos[:, 2].min() > 1.2  # still standing


def test_humanoid_falls_when_its_controller_switches_off(runs):
    run = runs["humanoid_fall"]
    qpos = run.result.trajectory.qpos
    assert qpos[0, 2] > 1.2
    assert qpos[-1, 2] < 0.6
    touched = set()
    for _, _, msg in _decoded(run.log, ["/ground_truth/contacts"]):
        touched |= {c.body2 for c in msg.contacts} | {c.body1 for c in msg.contacts}
    assert touched - {"world", "left_foot", "right_foot"}  # more than the feet hit something


def test_contact_wrenches_equal_mujocos_external_forces(runs):
    run = runs["quadruped_trot"]
    traj = run.result.trajectory
    model = traj.model
    layout = StateLayout.of(model)
    steps = {50, 150, 250}
    wrenches: dict[tuple[int, str], np.ndarray] = {}
    topics = [f"/ground_truth/contact_wrench/{b}" for b in layout.contact_bodies]
    for topic, _, msg in _decoded(run.log, topics):
        k = round((_stamp(msg.header) - traj.t0_ns) / (traj.h * NS))
        if k in steps:
            f, tau = msg.wrench.force, msg.wrench.torque
            wrenches[(k, topic.rsplit("/", 1)[1])] = np.array([f.x, f.y, f.z, tau.x, tau.y, tau.z])
            assert msg.header.frame_id == topic.rsplit("/", 1)[1]
    data = mujoco.MjData(model)
    touching = 0
    for k in steps:
        data.qpos[:], data.qvel[:], data.ctrl[:] = traj.qpos[k], traj.qvel[k], traj.ctrl[k]
        mujoco.mj_forward(model, data)
        mujoco.mj_rnePostConstraint(model, data)
        for name in layout.contact_bodies:
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            # cfrc_ext: [torque, force] at the subtree com, world axes → body origin, body axes
            torque_c, force = data.cfrc_ext[b, :3], data.cfrc_ext[b, 3:]
            arm = data.subtree_com[model.body_rootid[b]] - data.xpos[b]
            rot = data.xmat[b].reshape(3, 3)
            expected = np.concatenate([rot.T @ force, rot.T @ (torque_c + np.cross(arm, force))])
            np.testing.assert_allclose(
                wrenches[(k, name)], expected, atol=1e-6 * (1 + abs(expected).max())
            )
            touching += bool(np.abs(expected).max() > 1.0)
    assert touching >= len(steps) * 2  # at least two feet down at each step


def test_ground_truth_effort_is_the_actuator_force(runs):
    for name in ("quadruped_trot", "humanoid_push", "arm_box"):
        run = runs[name]
        traj = run.result.trajectory
        model = traj.model
        efforts = []
        for _, _, msg in _decoded(run.log, ["/ground_truth/joint_states"]):
            ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in msg.name]
            efforts.append(np.array(msg.effort))
            k = len(efforts) - 1
            np.testing.assert_allclose(
                np.array(msg.position), traj.qpos[k, model.jnt_qposadr[ids]], rtol=0, atol=0
            )
        dofs = model.jnt_dofadr[ids]
        np.testing.assert_allclose(np.array(efforts), traj.qfrc_actuator[:, dofs], atol=1e-6)


def test_write_state_writes_the_same_layout_under_estimate():
    model = load_model("quadruped")
    dyn = make_dynamics(model, "native")
    data = mujoco.MjData(dyn.model)
    mujoco.mj_resetDataKeyframe(dyn.model, data, 0)
    inverse = dyn.inverse(data.qpos, data.qvel, np.zeros(dyn.model.nv))
    cov = {"base": np.diag([1.0, 2, 3, 4, 5, 6]) * 1e-4}
    buffer = io.BytesIO()
    with Ros2Writer(buffer) as writer:
        count = write_state(
            writer,
            "/estimate",
            123 * NS,
            dyn.model,
            state_data(dyn.model, data.qpos, data.qvel),
            qfrc=inverse.qfrc_inverse,
            constraints=inverse.constraints,
            pose_covariance=cov,
        )
    layout = StateLayout.of(dyn.model)
    assert layout.free_bodies == ("base",)
    assert len(layout.joints) == 12
    assert "base" in layout.contact_bodies and "world" not in layout.contact_bodies
    buffer.seek(0)
    reader = make_reader(buffer, decoder_factories=[DecoderFactory()])
    got = {channel.topic: msg for _, channel, _, msg in reader.iter_decoded_messages()}
    assert set(got) == set(layout.topics("/estimate")) and count == len(got)
    odometry = got["/estimate/odometry/base"]
    assert _stamp(odometry.header) == 123 * NS
    assert odometry.pose.pose.position.z == data.qpos[2]
    assert list(odometry.pose.covariance) == list(cov["base"].reshape(-1))
    assert len(got["/estimate/contacts"].contacts) == 4


# -- determinism and metadata ----------------------------------------------------------------------
def test_same_seed_same_bytes_other_seed_other_messages(tmp_path):
    paths = []
    for i, seed in enumerate((7, 7, 8)):
        path = tmp_path / f"{i}.mcap"
        argv = ["single_joint", "--out", str(path), "--seed", str(seed), "--duration", "0.4"]
        assert main(["simulate", *argv, "--quiet"]) == 0
        paths.append(path)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    first = [(t, lt, str(m)) for t, lt, m in _decoded(paths[0])]
    other = [(t, lt, str(m)) for t, lt, m in _decoded(paths[2])]
    assert first == [(t, lt, str(m)) for t, lt, m in _decoded(paths[1])]
    assert first != other
    differing = {t for (t, lt, m), (_, lt2, m2) in zip(first, other, strict=False) if m != m2}
    assert "/joint_states" in differing


def test_mismatch_is_seeded_and_recorded_in_metadata(runs, tmp_path):
    run = runs["humanoid_push"]
    meta = _metadata(run.log)
    sim = meta["physfuse.simulation"]
    assert sim["scenario"] == "humanoid_push" and sim["seed"] == "0"
    assert json.loads(sim["pushes"])[0]["body"] == "torso"
    mismatch = meta["physfuse.mismatch"]
    masses = json.loads(mismatch["body_mass"])
    nominal = load_model("humanoid")
    true = run.result.trajectory.model
    assert set(masses) == {mujoco.mj_id2name(nominal, 1, b) for b in range(1, nominal.nbody)}
    for body, (nom, tru) in masses.items():
        b = mujoco.mj_name2id(nominal, mujoco.mjtObj.mjOBJ_BODY, body)
        assert nom == nominal.body_mass[b] and tru == true.body_mass[b] and nom != tru
    friction = json.loads(mismatch["geom_friction"])
    assert friction["floor"][0] != friction["floor"][1]
    softness = json.loads(mismatch["true_softness"])
    assert softness["eps"] == run.result.true_softness.eps != 0.05
    assert json.loads(meta["physfuse.sensors"]["imu"])["noise"]["rate_hz"] == 500.0
    assert "qfrc_inverse" in meta["physfuse.ground_truth"]["joint_states"]
    # without mismatch the simulated robot is the model
    path = tmp_path / "nominal.mcap"
    result = simulate("humanoid_push", path, duration_s=0.05, mismatch=False)
    assert json.loads(_metadata(path)["physfuse.mismatch"]["body_mass"]) == {}
    np.testing.assert_array_equal(result.trajectory.model.body_mass, nominal.body_mass)
    # another seed, another robot
    other, _, _ = Mismatch().apply(nominal, np.random.default_rng(1))
    assert not np.array_equal(other.body_mass, true.body_mass)


# -- sensor imperfections --------------------------------------------------------------------------
def test_imu_bias_walks_and_noise_is_white(runs):
    run = runs["humanoid_push"]
    imu = read_log(run.log, load_config(run.config)).measurements["imu"]
    truth = run.result.sensors["imu"]
    noise = ImuNoise()
    assert len(imu) == len(truth["t_ns"])
    gyro = imu.values[:, 0, 4:7]
    accel = imu.values[:, 0, 7:10]
    gyro_error = gyro - truth["gyro"] - truth["gyro_bias"]
    accel_error = accel - truth["accel"] - truth["accel_bias"]
    assert np.std(gyro_error) == pytest.approx(noise.gyro_std, rel=0.1)
    assert np.std(accel_error) == pytest.approx(noise.accel_std, rel=0.1)
    assert abs(np.mean(gyro_error)) < 4 * noise.gyro_std / math.sqrt(gyro_error.size)
    # the bias walks: its increments have the walk's spread, and it ends somewhere else
    dt = 1 / noise.rate_hz
    steps = np.diff(truth["gyro_bias"], axis=0)
    assert np.std(steps) == pytest.approx(noise.gyro_bias_walk * math.sqrt(dt), rel=0.1)
    assert np.all(truth["gyro_bias"][-1] != truth["gyro_bias"][0])
    # standing upright: the accelerometer reads +g along the torso's z axis
    assert np.median(accel[:, 2]) == pytest.approx(9.81, abs=0.3)


def test_imu_saturates_at_its_range(runs):
    run = runs["humanoid_fall"]
    sensor = Imu("/imu", "imu", ImuNoise(accel_range=12.0, gyro_range=1.0))
    output = sensor.sample(run.result.trajectory, np.random.default_rng(0))
    accel = np.array([[m.fields["linear_acceleration"][a] for a in "xyz"] for m in output.messages])
    gyro = np.array([[m.fields["angular_velocity"][a] for a in "xyz"] for m in output.messages])
    assert output.truth["saturated"].any()
    assert np.abs(accel).max() == 12.0 and np.abs(gyro).max() == 1.0
    assert np.isclose(np.abs(accel), 12.0).any(axis=1).sum() < len(accel)  # not always
    # an IMU without its own orientation filter says so (REP 145)
    plain = Imu("/imu", "imu", ImuNoise(orientation_std_rad=None))
    message = plain.sample(run.result.trajectory, np.random.default_rng(0)).messages[0]
    assert message.fields["orientation_covariance"][0] == -1.0


def test_quadruped_imu_mounting_is_undone_by_its_config(runs):
    run = runs["quadruped_trot"]
    traj = run.result.trajectory
    imu = read_log(run.log, load_config(run.config)).measurements["imu"]
    truth = run.result.sensors["imu"]
    scenario = get_scenario("quadruped_trot")
    (noise,) = [s.noise for s in scenario.sensors if isinstance(s, Imu)]
    assert noise.quat_site_sensor != (1.0, 0.0, 0.0, 0.0)
    # the reader turns the readings into the site frame: compare with the model's gyro
    gyro = mujoco.mj_name2id(traj.model, mujoco.mjtObj.mjOBJ_SENSOR, "imu_gyro")
    gyro_adr = int(traj.model.sensor_adr[gyro])
    gyro_site = traj.velocity(traj.sensordata_vel[:, gyro_adr : gyro_adr + 3], truth["t_ns"])
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.array(noise.quat_site_sensor))
    bias_site = truth["gyro_bias"] @ rot.reshape(3, 3).T
    error = imu.values[:, 0, 4:7] - gyro_site - bias_site
    assert np.abs(error).max() < 6 * noise.gyro_std
    # and the orientation into the site's orientation
    site = mujoco.mj_name2id(traj.model, mujoco.mjtObj.mjOBJ_SITE, "imu")
    q_site = traj.slerp(traj.site_xquat[:, site], truth["t_ns"])
    dot = np.abs(np.sum(imu.values[:, 0, 0:4] * q_site, axis=1))
    assert noise.orientation_std_rad is not None
    assert (2 * np.arccos(np.clip(dot, -1, 1))).max() < 6 * noise.orientation_std_rad
    assert np.allclose(quat_mul(q_site, np.array(noise.quat_site_sensor)), truth["quat_wxyz"])


def test_mocap_dropouts_are_gaps_and_outliers_are_jumps(tmp_path):
    noise = MocapNoise(
        rate_hz=100.0, dropout_rate_hz=2.0, dropout_s=(0.1, 0.3), outlier_probability=0.05
    )
    scenario = replace(
        get_scenario("single_joint"),
        sensors=(MocapPoses({"arm": "tip_site"}, noise), Commands()),
    )
    path, config = tmp_path / "occluded.mcap", tmp_path / "occluded.toml"
    config.write_text(scenario_config(scenario))
    result = simulate(scenario, path, seed=3, duration_s=3.0)
    truth = result.sensors["mocap"]
    intervals = truth["dropouts"]["arm"]
    assert len(intervals) >= 2
    mocap = read_log(path, load_config(config)).measurements["mocap_arm"]
    t = (mocap.t_ns - result.trajectory.t0_ns) / NS
    for start, end in intervals:  # no frame inside an occlusion
        assert not np.any((t >= start + 0.001) & (t < end - 0.001))
    gaps = np.diff(t)
    inside = [end - start for start, end in intervals if end < 2.9]
    assert gaps.max() >= max(inside) - 0.02 >= 0.08
    # outliers: exactly the flagged frames are off by centimetres
    visible = truth["visible"][:, 0]
    error = np.linalg.norm(mocap.values[:, 0, :3] - truth["position"][visible, 0], axis=1)
    flagged = truth["outlier"][visible, 0]
    assert flagged.sum() >= 3
    assert error[flagged].min() > noise.outlier_m[0] - 6 * noise.position_std_m
    assert error[~flagged].max() < 6 * noise.position_std_m


def test_encoder_positions_lie_on_the_quantization_grid(runs):
    for name in ("humanoid_push", "single_joint", "arm_box"):
        run = runs[name]
        joints = read_log(run.log, load_config(run.config)).measurements["joints"]
        truth = run.result.sensors["joints"]
        position = joints.component("position")
        counts = position / truth["resolution"]
        assert np.abs(counts - np.round(counts)).max() < 1e-6
        assert np.abs(position - truth["position"]).max() <= truth["resolution"].max() / 2 + 1e-12
        assert len(np.unique(np.round(counts), axis=0)) > len(counts) // 4  # the joints move


def test_stamps_carry_clock_offsets_and_log_times_latency(runs):
    run = runs["humanoid_push"]
    t0 = run.result.trajectory.t0_ns
    log = read_log(run.log, load_config(run.config))
    scenario = get_scenario("humanoid_push")
    sensors = {s.name: s for s in scenario.sensors}
    for sensor, stream in (("imu", "imu"), ("joints", "joints")):
        truth = run.result.sensors[sensor]
        measurement = log.measurements[stream]
        device = sensors[sensor]
        assert isinstance(device, Imu | Encoders)
        clock = device.noise.clock
        stamps = truth["stamp_ns"] - truth["t_ns"]
        assert abs(np.median(stamps) - clock.offset_ns) <= clock.stamp_jitter_ns
        assert np.all(measurement.log_time_ns - t0 - truth["t_ns"] >= clock.latency_ns)
        # the config undoes the offset: the reader's times are true times up to the jitter
        assert np.abs(measurement.t_ns - t0 - truth["t_ns"]).max() <= 3 * clock.stamp_jitter_ns
    command = log.measurements["command"]
    np.testing.assert_array_equal(command.values[:, :, 0], run.result.trajectory.ctrl)
    # the recorder writes in receive order
    times = [lt for _, lt, _ in _decoded(run.log)]
    assert times == sorted(times)


# -- Rerun -----------------------------------------------------------------------------------------
def test_rerun_imports_the_log(runs):
    run = runs["humanoid_push"]
    reader = rr.chunk.McapReader(run.log)
    info = reader.info()
    assert info.profile == "ros2"
    assert info.message_count == run.result.message_count
    assert info.metadata_count == 4
    rows: dict[str, int] = {}
    columns: dict[str, set[str]] = {}
    for chunk in reader.stream().to_chunks():
        if chunk.is_static:
            continue
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        columns.setdefault(chunk.entity_path, set()).update(chunk.to_record_batch().schema.names)
    steps = run.result.trajectory.steps
    assert rows["/ground_truth/contacts"] == steps
    assert "physfuse_msgs.msg.ContactArray:message" in columns["/ground_truth/contacts"]
    assert rows["/ground_truth/odometry/torso"] == steps
    assert rows["/ground_truth/joint_states/effort"] == steps
    assert rows["/imu"] == len(run.result.sensors["imu"]["t_ns"])
    assert any("InstancePoses3D" in c for c in columns["/mocap/torso/pose"])


# -- conditions ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def humanoid_conditions(tmp_path_factory) -> dict[str, Run]:
    """humanoid_push, 3 s, seed 0, under the conditions that keep its true motion."""
    folder = tmp_path_factory.mktemp("conditions")
    out = {}
    for condition in ("nominal", "occlusion", "outliers", "no_commands"):
        log, config = folder / f"{condition}.mcap", folder / f"{condition}.toml"
        scenario = with_condition(get_scenario("humanoid_push"), condition)
        config.write_text(scenario_config(scenario))
        out[condition] = Run(simulate(scenario, log, seed=0, duration_s=3.0), log, config)
    return out


def _mocap_times_s(run: Run, stream: str) -> np.ndarray:
    measurement = read_log(run.log, load_config(run.config)).measurements[stream]
    return (measurement.t_ns - run.result.trajectory.t0_ns) / NS


def test_nominal_has_no_mocap_gaps_or_outliers_and_the_same_motion(humanoid_conditions):
    nominal = humanoid_conditions["nominal"]
    truth = nominal.result.sensors["mocap"]
    assert truth["visible"].all() and not truth["outlier"].any()
    for label in ("torso", "pelvis", "left_foot", "right_foot"):
        assert np.diff(_mocap_times_s(nominal, f"mocap_{label}")).max() < 1.5 / 120.0
    assert _metadata(nominal.log)["physfuse.condition"]["name"] == "nominal"
    for run in humanoid_conditions.values():  # the conditions change the sensors, not the robot
        np.testing.assert_array_equal(run.result.trajectory.qpos, nominal.result.trajectory.qpos)


def test_occlusion_hides_the_robot_for_02_to_1_s_several_times(humanoid_conditions):
    run = humanoid_conditions["occlusion"]
    intervals = run.result.sensors["mocap"]["occlusions"]
    assert len(intervals) == 2  # (3 s - 2 × 0.25 s margin) // 1.25 s
    lengths = intervals[:, 1] - intervals[:, 0]
    assert np.all((lengths >= 0.2) & (lengths <= 1.0))
    recorded = json.loads(_metadata(run.log)["physfuse.condition"]["occlusions_s"])
    np.testing.assert_allclose(recorded["mocap"], intervals)
    for label in ("torso", "pelvis", "left_foot", "right_foot"):  # every body, together
        times = _mocap_times_s(run, f"mocap_{label}")
        for start, end in intervals:  # a gap in the log spans each occlusion
            assert not np.any((times >= start + 0.001) & (times < end - 0.001))
            assert np.diff(times).max() >= end - start
        assert np.sum(np.diff(times) > 2.5 / 120.0) == len(intervals)


def test_occlusion_hides_every_marker_of_the_box(tmp_path):
    scenario = with_condition(get_scenario("arm_box"), "occlusion")
    log, config = tmp_path / "box.mcap", tmp_path / "box.toml"
    config.write_text(scenario_config(scenario))
    result = simulate(scenario, log, seed=1, duration_s=1.5)
    ((start, end),) = result.sensors["markers"]["occlusions"]
    assert 0.2 <= end - start <= 1.0
    markers = read_log(log, load_config(config)).measurements["markers"]
    t = (markers.t_ns - result.trajectory.t0_ns) / NS
    assert not np.any((t >= start + 0.001) & (t < end - 0.001))
    assert np.isfinite(markers.values).all()  # outside the occlusion every marker is seen


def test_outliers_condition_jumps_2_percent_of_frames_by_centimetres(humanoid_conditions):
    run = humanoid_conditions["outliers"]
    truth = run.result.sensors["mocap"]
    rate = truth["outlier"].mean()  # 360 frames × 4 bodies: 2% ± 0.4% (1σ)
    assert abs(rate - OUTLIER_PROBABILITY) < 0.01
    torso = read_log(run.log, load_config(run.config)).measurements["mocap_torso"]
    error = np.linalg.norm(torso.values[:, 0, :3] - truth["position"][:, 0], axis=1)
    flagged = truth["outlier"][:, 0]
    assert flagged.any() and error[flagged].min() > 0.03 - 0.003
    assert error[~flagged].max() < 0.003
    assert truth["visible"].all()  # nominal's: no dropouts


def test_mismatch_condition_is_exactly_10_percent_mass_and_30_percent_friction(tmp_path):
    log = tmp_path / "mismatch.mcap"
    assert main(["simulate", "humanoid_push", "--condition", "mismatch", "--out", str(log),
                 "--duration", "0.1", "--quiet"]) == 0  # fmt: skip
    meta = _metadata(log)
    assert json.loads(meta["physfuse.simulation"]["mismatch"])["signed"] is True
    masses = json.loads(meta["physfuse.mismatch"]["body_mass"])
    ratios = np.array([true / nominal for nominal, true in masses.values()])
    np.testing.assert_allclose(np.abs(ratios - 1.0), 0.10, rtol=1e-12)
    assert (ratios > 1).any() and (ratios < 1).any()
    frictions = json.loads(meta["physfuse.mismatch"]["geom_friction"])
    ratios = np.array([true / nominal for nominal, true in frictions.values()])
    np.testing.assert_allclose(np.abs(ratios - 1.0), 0.30, rtol=1e-12)
    assert (ratios > 1).any() and (ratios < 1).any()


def test_no_commands_log_has_no_command_topic_and_its_config_no_command_stream(
    humanoid_conditions,
):
    run = humanoid_conditions["no_commands"]
    assert "/joint_commands" not in run.result.topics
    assert "/joint_commands" in humanoid_conditions["nominal"].result.topics
    config = load_config(run.config)
    assert "command" not in {stream.kind for stream in config.streams.values()}
    assert "--condition no_commands" in run.config.read_text()
    assert set(read_log(run.log, config).measurements) == {
        "mocap_torso", "mocap_pelvis", "mocap_left_foot", "mocap_right_foot", "imu", "joints"
    }  # fmt: skip


def test_every_condition_is_documented_on_the_command_line(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    out, _ = capsys.readouterr()
    for condition in CONDITIONS:
        assert condition in out


# -- the command line ------------------------------------------------------------------------------
def test_cli_writes_the_log_and_its_config(tmp_path, capsys):
    log, config = tmp_path / "sj.mcap", tmp_path / "sj.toml"
    options = ["--duration", "0.2", "--ground-truth-every", "5", "--no-mismatch"]
    code = main(
        ["simulate", "single_joint", "--out", str(log), "--config-out", str(config), *options]
    )
    out, _ = capsys.readouterr()
    assert code == 0
    assert f"{log}: single_joint, seed 0, 0.2 s simulated" in out
    assert config.read_text() == scenario_config("single_joint")
    counts = {t: s.count for t, s in read_log(log).topics.items()}
    assert counts["/ground_truth/joint_states"] == 20  # 100 steps, every 5th
    assert counts["/joint_commands"] == 100


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["nope"], "unknown scenario 'nope'; valid scenarios: " + ", ".join(SCENARIOS)),
        (["single_joint", "--duration", "-1"], "--duration -1.0: expected a positive"),
        (["single_joint", "--ground-truth-every", "0"], "--ground-truth-every 0: expected"),
        (["single_joint", "--seed", "-3"], "seed -3: expected a non-negative integer"),
        (["single_joint", "--condition", "rain"], "unknown condition 'rain'; valid conditions: "),
        (
            ["single_joint", "--condition", "mismatch", "--no-mismatch"],
            "--condition mismatch contradicts --no-mismatch",
        ),
    ],
)
def test_cli_rejects_bad_arguments_in_one_line(tmp_path, capsys, argv, message):
    log = tmp_path / "x.mcap"
    code = main(["simulate", *argv, "--out", str(log)])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("physfuse simulate: error: ")
    assert message in err
    assert not log.exists()


def test_cli_rejects_an_unwritable_output_before_simulating(tmp_path, capsys):
    for out, why in (
        (tmp_path / "missing" / "x.mcap", "does not exist"),
        (tmp_path, "is a directory"),
    ):
        code = main(["simulate", "arm_box", "--out", str(out)])
        _, err = capsys.readouterr()
        assert code == 2 and err.count("\n") == 1 and why in err


def test_simulate_rejects_bad_settings(tmp_path):
    with pytest.raises(SimulationError, match="positive number of seconds"):
        simulate("single_joint", tmp_path / "x.mcap", duration_s=float("nan"))
    bad = replace(get_scenario("single_joint"), sensors=(Imu("/imu", "imu"),))
    with pytest.raises(SimulationError, match="no site 'imu'"):
        simulate(bad, io.BytesIO(), duration_s=0.01)


def test_pushes_move_the_humanoid(runs):
    run = runs["humanoid_push"]
    (push, *_) = run.result.pushes
    assert isinstance(push, Push) and push.start_s == 1.0
    qvel = run.result.trajectory.qvel
    k = round(push.start_s / run.result.trajectory.h)
    before, after = np.abs(qvel[k - 5, :2]).max(), np.abs(qvel[k + 10, :2]).max()
    assert after > 5 * before


# -- the committed configs and sample recordings ---------------------------------------------------
def test_committed_configs_are_the_scenarios_configs():
    for name in SCENARIOS:
        path = ROOT / "configs" / f"{name}.toml"
        assert path.read_text() == scenario_config(name), name
        load_config(path)


def _readme_commands() -> dict[str, list[str]]:
    text = (ROOT / "recordings" / "README.md").read_text()
    commands = {}
    for line in re.findall(r"^physfuse simulate .*$", text, flags=re.MULTILINE):
        argv = shlex.split(line)[1:]
        commands[Path(argv[argv.index("--out") + 1]).stem] = argv
    return commands


PUBLIC_RECORDINGS = ("go2", "h1", "panda_box")  # `simulate --model` of physics/models/menagerie


def test_sample_recordings_are_read_with_their_configs(capsys):
    commands = _readme_commands()
    assert set(commands) == {*SCENARIOS, *PUBLIC_RECORDINGS}
    total = 0
    for name, argv in commands.items():
        log = ROOT / "recordings" / f"{name}.mcap"
        config = ROOT / "configs" / f"{name}.toml"
        assert argv[argv.index("--out") + 1] == f"recordings/{name}.mcap"
        assert argv[argv.index("--config-out") + 1] == f"configs/{name}.toml"
        assert argv[argv.index("--seed") + 1] == "0"
        total += log.stat().st_size
        result = read_log(log, load_config(config))
        assert not result.warnings
        for m in result.measurements.values():
            assert len(m) > 0 and m.bad.total == (m.bad.nan if m.kind == "markers" else 0), name
        assert _metadata(log)["physfuse.simulation"]["scenario"] == name
        assert main(["inspect", str(log), "--config", str(config)]) == 0
    capsys.readouterr()
    assert total < 14_000_000


def test_sample_recording_is_regenerated_by_its_readme_command(tmp_path):
    argv = _readme_commands()["single_joint"]
    argv[argv.index("--out") + 1] = str(tmp_path / "single_joint.mcap")
    argv[argv.index("--config-out") + 1] = str(tmp_path / "single_joint.toml")
    assert main([*argv, "--quiet"]) == 0
    fresh = list(_decoded(tmp_path / "single_joint.mcap"))
    committed = list(_decoded(ROOT / "recordings" / "single_joint.mcap"))
    assert len(fresh) == len(committed)
    for (topic, log_time, msg), (topic0, log_time0, msg0) in zip(fresh, committed, strict=True):
        assert topic == topic0 and abs(log_time - log_time0) <= 2
        assert _numbers(msg) == pytest.approx(_numbers(msg0), rel=1e-6, abs=1e-9)


def _numbers(msg) -> list[float]:
    """Every number in a decoded message, depth first (strings dropped)."""
    if isinstance(msg, int | float):
        return [float(msg)]
    if isinstance(msg, str):
        return []
    if isinstance(msg, list | tuple):
        return [v for item in msg for v in _numbers(item)]
    return [v for slot in msg.__slots__ for v in _numbers(getattr(msg, slot))]
