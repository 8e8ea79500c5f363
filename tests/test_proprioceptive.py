"""Without motion capture: a trotting quadruped's base from its IMU, encoders and commands (the
`no_mocap` condition). Leg odometry starts it; the physics smoother holds the start pose and
reports what proprioception cannot see — x, y and yaw — as a σ that grows."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.batch import estimate
from estimator.cli import main
from estimator.config import MOCAP_KINDS, load_config
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.io.state_topics import read_state_topics
from estimator.knots import knot_grid
from estimator.leg_odometry import unanchored
from estimator.run import initial_trajectory
from estimator.settings import Settings


@pytest.fixture(scope="module")
def trot_files(tmp_path_factory):
    """quadruped_trot, 2 s without mocap: (log, config) paths."""
    folder = tmp_path_factory.mktemp("no_mocap")
    log, config = folder / "trot.mcap", folder / "trot.toml"
    argv = ["simulate", "quadruped_trot", "--condition", "no_mocap", "--seed", "0"]
    argv += ["--duration", "2", "--out", str(log), "--config-out", str(config), "--quiet"]
    assert main(argv) == 0
    return log, config


@pytest.fixture(scope="module")
def trot(trot_files):
    """(config, measurements, truth time, truth qpos) of `trot_files`."""
    log, config = trot_files
    cfg = load_config(config)
    t_true, q_true = read_state_topics(log, "/ground_truth").qpos(cfg.load_model())
    return cfg, read_log(log, cfg).measurements, t_true, q_true


def _truth_at(t_ns, t_true, q_true):
    return q_true[np.clip(np.searchsorted(t_true, t_ns), 0, len(t_true) - 1)]


def _tilt_and_yaw_deg(q, q_true):
    """(roll/pitch error RMS, yaw error per knot) of the base, degrees."""
    error = (
        Rotation.from_quat(q[:, 3:7], scalar_first=True)
        * Rotation.from_quat(q_true[:, 3:7], scalar_first=True).inv()
    )
    euler = error.as_euler("xyz", degrees=True)
    return float(np.sqrt(np.mean(euler[:, :2] ** 2))), euler[:, 2]


def test_no_mocap_leaves_only_proprioception_in_the_log_and_the_config(trot):
    config, measurements, _, _ = trot
    kinds = {s.kind for s in config.streams.values()}
    assert kinds == {"imu", "joint_state", "command"} and not kinds & set(MOCAP_KINDS)
    assert unanchored(config.load_model(), measurements)


def test_leg_odometry_starts_the_base_where_the_robot_trots(trot):
    """The initial trajectory follows the trot (≈ 0.5 m in 2 s) from the IMU's orientation and
    the stance feet: within 10% of the distance at the end, its height within 5 mm."""
    config, measurements, t_true, q_true = trot
    model = config.load_model()
    t_ns = knot_grid(measurements, model.opt.timestep)
    q = initial_trajectory(model, measurements, t_ns)
    truth = _truth_at(t_ns, t_true, q_true)
    travel = np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1))
    assert travel > 0.3
    drift = (q[-1, :2] - truth[-1, :2]) - (q[0, :2] - truth[0, :2])
    assert np.linalg.norm(drift) < 0.1 * travel
    assert np.sqrt(np.mean((q[:, 2] - truth[:, 2]) ** 2)) < 0.005
    tilt, _ = _tilt_and_yaw_deg(q, truth)
    assert tilt < 0.5


def test_the_estimate_holds_its_start_pose_and_reports_what_it_cannot_see(trot):
    """x, y and yaw stay at the start pose's at the first knot and their σ grows along the log
    (nothing absolute sees them), while z, roll and pitch (the floor and gravity see them)
    stay as certain as they start; the base follows the robot."""
    config, measurements, t_true, q_true = trot
    model = config.load_model()
    est, summary = estimate(config, measurements, Settings.from_config(config))
    truth = _truth_at(est.t_ns, t_true, q_true)
    home = model.key_qpos[0] if model.nkey else model.qpos0
    np.testing.assert_allclose(est.qpos[0, :2], home[:2], atol=1e-4)
    tilt, yaw = _tilt_and_yaw_deg(est.qpos, truth)
    assert abs(yaw[0]) < 0.01 and tilt < 0.2
    std = est.qpos_std  # free joint dofs: x y z, then rotation about the body's axes
    unseen, seen = std[:, [0, 1, 5]], std[:, [2, 3, 4]]
    assert np.all(unseen[-1] > 2.5 * unseen[0]) and unseen[-1, 2] > 0.005  # yaw: 0.3° in 2 s
    assert np.all(seen[-1] < 2 * seen[0] + 1e-4)
    travel = np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1))
    error = np.linalg.norm(est.qpos[:, :2] - truth[:, :2], axis=1)
    assert error.max() < 0.1 * travel  # it moved with the robot
    # in windows of window_s_no_mocap (0.5 s; the log is 2 s), not window_s (4 s)
    assert len(summary.window_starts) >= 4


@pytest.mark.parametrize("method", ["gtsam-legged-ekf", "gtsam-legged-smoother"])
def test_gtsams_legged_estimators_run_on_the_same_log_in_the_same_layout(trot, method):
    """gtsam's LeggedInvariantEKF and LeggedFixedLagSmoother, fed the IMU and the feet from
    the encoders (stance by the lowest feet: this log has no contact flags), follow the
    trot: the base within a third of the distance at the end, tilted under 2°."""
    config, measurements, t_true, q_true = trot
    settings = replace(Settings.from_config(config), method=method)
    est, summary = estimate(config, measurements, settings)
    assert f"{method}: stance from the feet within 15 mm of the lowest" in summary.warnings
    truth = _truth_at(est.t_ns, t_true, q_true)
    assert np.all(np.isfinite(est.qpos))
    travel = np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1))
    drift = (est.qpos[-1, :2] - truth[-1, :2]) - (est.qpos[0, :2] - truth[0, :2])
    assert np.linalg.norm(drift) < travel / 3
    assert np.linalg.norm(est.qpos[-1, :2] - est.qpos[0, :2]) > travel / 2  # it moved
    tilt, _ = _tilt_and_yaw_deg(est.qpos, truth)
    assert tilt < 2.0
    # the base's velocity is the estimator's own state, not its poses' finite differences
    # (those are 0.2 m/s off on this trot)
    h = 1e-9 * float(np.median(np.diff(t_true)))
    v_true = np.gradient(q_true[:, :3], h, axis=0)
    v_true = v_true[np.clip(np.searchsorted(t_true, est.t_ns), 0, len(t_true) - 1)]
    assert np.sqrt(np.mean((est.qvel[5:-5, :3] - v_true[5:-5]) ** 2)) < 0.12


def _assert_placed_at_1_m2_90(est, log, atol):
    """The base odometry `est` starts at x 1, y −2, yaw 90° (within atol m, 0.1°) and moves
    as the log's true base does, turned by 90° (within 10% of the distance)."""
    truth = read_state_topics(log, "/ground_truth").odometry["base"].values
    np.testing.assert_allclose(est[0, :2], [1.0, -2.0], atol=atol)
    _, yaw = _tilt_and_yaw_deg(est[:1], truth[:1])
    assert abs(yaw[0] - 90.0) < 0.1
    moved, moved_true = est[-1, :2] - est[0, :2], truth[-1, :2] - truth[0, :2]
    np.testing.assert_allclose(
        moved, [-moved_true[1], moved_true[0]], atol=0.1 * np.linalg.norm(moved_true)
    )


def test_a_start_pose_places_the_estimate_and_the_summary_names_what_is_unobserved(
    trot_files, tmp_path
):
    """--start-pose X Y YAW_DEG: the estimate starts there (its first knot), moves as the robot
    does, turned by the yaw; summary.json says x, y and yaw are unobservable from there."""
    log, config = trot_files
    out = tmp_path / "est"
    argv = ["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]
    assert main([*argv, "--start-pose", "1", "-2", "90"]) == 0
    est = read_state_topics(out / "estimate.mcap", "/estimate").odometry["base"].values
    _assert_placed_at_1_m2_90(est, log, atol=1e-4)
    warnings = json.loads((out / "summary.json").read_text())["warnings"]
    line = next(w for w in warnings if w.startswith("no mocap:"))
    assert "(x 1.000 m, y -2.000 m, yaw 90.0°: the config's start_pose or --start-pose)" in line


def test_the_stream_holds_its_start_pose_too(trot_files, tmp_path):
    """`physfuse stream --start-pose`: the live estimate's first smoothed knot is there and the
    base moves as the robot does, turned by the yaw (the first window holds x, y, yaw)."""
    log, config = trot_files
    out = tmp_path / "live.mcap"
    argv = [sys.executable, "-m", "estimator.cli", "stream", "--config", str(config)]
    argv += ["--source", str(log), "--out", str(out), "--start-pose", "1", "-2", "90", "--quiet"]
    assert subprocess.run(argv, capture_output=True, timeout=600).returncode == 0
    est = read_state_topics(out, "/estimate_smoothed").odometry["base"].values
    _assert_placed_at_1_m2_90(est, log, atol=1e-3)


def test_chunks_without_mocap_continue_each_other(trot_files, tmp_path):
    """--chunk 1 on 2 Ray workers: every chunk starts at the start pose and is then turned and
    shifted to continue the one before: the base follows the robot across the joins without a
    jump there (left at the start pose, it jumped 17 mm back at the first join)."""
    log, config = trot_files
    out = tmp_path / "chunked"
    argv = ["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]
    assert main([*argv, "--chunk", "1", "--chunk-overlap", "0.5", "--workers", "2"]) == 0
    est = read_state_topics(out / "estimate.mcap", "/estimate").odometry["base"]
    truth = read_state_topics(log, "/ground_truth").odometry["base"]
    at = np.clip(np.searchsorted(truth.t_ns, est.t_ns), 0, len(truth.t_ns) - 1)
    p, p_true = est.values[:, :2], truth.values[at, :2]
    travel = np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=1))
    assert np.linalg.norm(p - p_true, axis=1).max() < 0.1 * travel
    steps, true_steps = np.diff(p, axis=0), np.diff(p_true, axis=0)
    assert np.abs(steps - true_steps).max() < 0.002  # no jump of the base between two knots
    _, yaw = _tilt_and_yaw_deg(est.values, truth.values[at])
    assert np.abs(yaw).max() < 2.0


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ('start_pose = { x = "one" }', "start_pose.x: expected a number, got 'one' (str)"),
        ("start_pose = { z = 1.0 }", "start_pose.z: unknown key; allowed keys: x, y, yaw_deg"),
    ],
)
def test_a_bad_start_pose_is_one_line_naming_the_key(trot_files, tmp_path, entry, message):
    _, config = trot_files
    bad = tmp_path / "bad.toml"
    text = config.read_text()
    bad.write_text(text.replace("[streams.", entry + "\n\n[streams.", 1))
    with pytest.raises(ConfigError, match=re.escape(f"{bad}: {message}")):
        load_config(bad)


def test_a_start_pose_on_a_fixed_base_says_there_is_none(tmp_path):
    config = tmp_path / "hinge.toml"
    config.write_text(
        'model = "single_joint"\nstart_pose = { x = 1.0 }\n'
        '[streams.joints]\ntype = "joint_state"\ntopic = "/joint_states"\njoints = "model"\n'
    )
    with pytest.raises(ConfigError, match="start_pose: the model has no free joint"):
        load_config(config)
