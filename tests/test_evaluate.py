"""`physfuse evaluate`: metrics on constructed data with known answers, then end to end on a
short simulated log (against ground truth, against itself, and a held-out sensor on a log
without ground truth)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from scipy.spatial.transform import Rotation

from estimator.cli import main
from estimator.evaluate import (
    CONTACT_WEIGHT_FRACTION,
    SUMMARY_KEYS,
    compare_states,
    gap_intervals,
    intersect_intervals,
    position_nees,
    precision_recall,
    rmse,
    within,
)
from estimator.io.state_topics import Series, StateTopics
from estimator.rotations import heading, quat_conj, quat_mul, rotation_angles
from physics.model import load_model

MS = 1_000_000


# -- metrics on constructed data ------------------------------------------------------------------
def test_rmse_of_a_known_offset_ignores_rows_with_nan():
    errors = np.tile([3.0, 4.0, 0.0], (10, 1))
    errors[2] = np.nan
    assert rmse(errors) == pytest.approx(5.0)
    assert rmse(np.array([1.0, -1.0, 1.0, -1.0])) == pytest.approx(1.0)
    assert np.isnan(rmse(np.zeros((0, 3))))


def test_rotation_angle_is_the_short_way_and_ignores_the_quaternion_sign():
    half = 0.05  # a turn of 0.1 rad about z
    turned = np.array([[np.cos(half), 0.0, 0.0, np.sin(half)]])
    identity = np.array([[1.0, 0.0, 0.0, 0.0]])
    assert rotation_angles(turned, identity)[0] == pytest.approx(0.1)
    assert rotation_angles(-turned, identity)[0] == pytest.approx(0.1)
    assert rotation_angles(turned, turned)[0] == pytest.approx(0.0, abs=1e-12)


def test_a_turn_about_world_z_adds_to_the_heading_of_a_tilted_orientation():
    """heading(R_z(δ) ⊗ q) = heading(q) + δ (mod 2π), as scipy's ZYX yaw; q ⊗ q⁻¹ = 1."""
    q = Rotation.from_euler("ZYX", [0.3, 0.2, -0.4]).as_quat(scalar_first=True)
    assert heading(q) == pytest.approx(0.3)
    for delta in (0.5, 3.0, -2.0):
        turn = np.array([np.cos(delta / 2), 0.0, 0.0, np.sin(delta / 2)])
        expected = np.angle(np.exp(1j * (0.3 + delta)))
        assert heading(quat_mul(turn, q)) == pytest.approx(expected)
    np.testing.assert_allclose(quat_mul(q, quat_conj(q)), [1.0, 0.0, 0.0, 0.0], atol=1e-15)


def test_position_nees_of_known_errors_and_covariances():
    """eᵀ Σ⁻¹ e / 3 per knot; NaN without a covariance."""
    cov = np.diag([1e-6, 4e-6, 9e-6])
    errors = np.array([[1e-3, 0.0, 0.0], [0.0, 2e-3, 3e-3], [1e-3, 1e-3, 1e-3]])
    covariances = np.stack([cov, cov, np.full((3, 3), np.nan)])
    nees = position_nees(errors, covariances)
    np.testing.assert_allclose(nees[:2], [1 / 3, 2 / 3])
    assert np.isnan(nees[2])


def test_precision_and_recall_of_known_contact_intervals():
    knots = np.arange(100)
    actual = (knots >= 10) & (knots < 30)  # 20 knots in contact
    predicted = (knots >= 15) & (knots < 40)  # 25 predicted, 15 of them right
    precision, recall = precision_recall(predicted, actual)
    assert precision == pytest.approx(15 / 25) and recall == pytest.approx(15 / 20)
    precision, recall = precision_recall(np.zeros(100, bool), actual)
    assert np.isnan(precision) and recall == 0.0


def test_occlusion_intervals_from_a_known_gap_pattern():
    """Mocap at 100 Hz over [0, 1] s: a late start, one dropped frame (not an occlusion: a
    20 ms gap is under 2.5 periods), two dropped frames (30 ms: one) and a long dropout."""
    t = np.arange(50, 1001, 10) * MS  # starts at 50 ms
    dropped = (
        (t == 200 * MS) | (t == 600 * MS) | (t == 610 * MS) | ((t > 300 * MS) & (t < 500 * MS))
    )
    gaps = gap_intervals(t[~dropped], 0, 1000 * MS)
    expected = [[0, 50], [300, 500], [590, 620]]
    np.testing.assert_array_equal(gaps, np.array(expected) * MS)
    knots = np.array([20, 200, 400, 600, 800]) * MS
    np.testing.assert_array_equal(within(knots, gaps), [True, False, True, True, False])
    both = intersect_intervals(gaps, np.array([[400, 900]]) * MS)
    np.testing.assert_array_equal(both, np.array([[400, 500], [590, 620]]) * MS)
    np.testing.assert_array_equal(gap_intervals(np.zeros(0, np.int64), 0, 10), [[0, 10]])


def _states(t_ns, *, pos, quat, joints, force, bias) -> StateTopics:
    """StateTopics of a humanoid (torso odometry, one joint, the left foot's contact, an IMU)."""
    n = len(t_ns)
    odometry = np.hstack([pos, quat, np.zeros((n, 6))])
    return StateTopics(
        path="constructed",
        prefix="/x",
        odometry={"torso": Series(t_ns, odometry)},
        joint_names=("right_knee",),
        joints=Series(t_ns, np.hstack([joints, np.zeros((n, 2))])),
        contact_wrench={"left_foot": Series(t_ns, np.hstack([force, np.zeros((n, 3))]))},
        imu_bias={"imu": Series(t_ns, bias)},
    )


def test_compare_states_recovers_known_offsets_against_a_sparser_truth():
    """The estimate every 10 ms, the truth every 40 ms (ground truth every 4th step): each
    knot is compared with the truth interpolated to it; the offsets come back as the errors."""
    model = load_model("humanoid")
    weight = float(np.sum(model.body_mass) * 9.81)
    t_est = np.arange(0, 2000, 10) * MS
    t_truth = np.arange(0, 2000, 40) * MS
    n, m = len(t_est), len(t_truth)
    stance = (t_truth >= 500 * MS) & (t_truth < 1500 * MS)
    identity = np.tile([1.0, 0, 0, 0], (m, 1))
    truth = _states(
        t_truth,
        pos=np.tile([0.0, 0.0, 1.0], (m, 1)),
        quat=identity,
        joints=np.full((m, 1), 0.3),
        force=np.outer(stance, [0.0, 0.0, weight / 2]),
        bias=np.tile([0.1, 0.0, 0.0, 0.01, 0.0, 0.0], (m, 1)),
    )
    half = np.radians(0.5) / 2  # 0.5° about x
    in_stance_est = (t_est >= 500 * MS) & (t_est < 1500 * MS)
    est = _states(
        t_est,
        pos=np.tile([0.001, 0.0, 1.0], (n, 1)),  # 1 mm off
        quat=np.tile([np.cos(half), np.sin(half), 0, 0], (n, 1)),
        joints=np.full((n, 1), 0.3 + np.radians(0.2)),
        force=np.outer(in_stance_est, [3.0, 0.0, weight / 2 + 4.0]),  # (3, 0, 4): 5 N off
        bias=np.tile([0.1, 0.02, 0.0, 0.01, 0.0, 0.0], (n, 1)),
    )
    occluded = {"torso": np.array([[1000, 1200]]) * MS}
    metrics = compare_states(est, truth, model, occluded)
    s = metrics["summary"]
    assert set(s) == set(SUMMARY_KEYS)
    assert s["position_mm"] == pytest.approx(1.0)
    assert s["orientation_deg"] == pytest.approx(0.5)
    assert s["joint_deg"] == pytest.approx(0.2)
    assert s["linear_velocity_mps"] == 0.0 and s["joint_velocity_dps"] == 0.0
    # stance [500, 1500) ms: the truth's samples in it are 520 … 1480 ms; interpolated, the
    # truth is in contact on (480, 1520) ms, the knots 490 … 1510 (103), the estimate on the
    # 100 knots 500 … 1490: no false positive, three false negatives
    in_contact = metrics["contacts"]["left_foot"]
    assert in_contact["precision"] == pytest.approx(1.0)
    assert in_contact["recall"] == pytest.approx(100 / 103)
    assert s["contact_precision"] == in_contact["precision"]
    assert 4.5 < s["contact_force_N"] < weight / 2
    assert s["contact_force_pct_weight"] == pytest.approx(100 * s["contact_force_N"] / weight)
    assert metrics["contact_threshold_N"] == pytest.approx(CONTACT_WEIGHT_FRACTION * weight)
    assert s["imu_accel_bias_mps2"] == pytest.approx(0.02) and s["imu_gyro_bias_dps"] == 0.0
    assert s["occluded_s"] == pytest.approx(0.2)
    assert s["occluded_position_mm"] == pytest.approx(1.0)
    assert metrics["bodies"]["torso"]["occluded_knots"] == 19
    # every error again over the occlusion: the joints and forces over any body's occlusion
    assert s["occluded_orientation_deg"] == pytest.approx(0.5)
    assert s["occluded_joint_deg"] == pytest.approx(0.2)
    assert s["occluded_linear_velocity_mps"] == 0.0 and s["occluded_joint_velocity_dps"] == 0.0
    assert s["occluded_contact_force_N"] == pytest.approx(5.0)  # mid-stance: (3, 0, 4) N off
    assert s["occluded_contact_force_pct_weight"] == pytest.approx(500.0 / weight)
    assert metrics["bodies"]["torso"]["occluded_angular_velocity_dps"] == 0.0


# -- end to end -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def estimated(tmp_path_factory):
    """A 2 s humanoid_push log, its config, and `physfuse estimate` of it."""
    folder = tmp_path_factory.mktemp("evaluate")
    log, config, out = folder / "push.mcap", folder / "push.toml", folder / "out"
    argv = ["simulate", "humanoid_push", "--seed", "3", "--duration", "2"]
    assert main([*argv, "--out", str(log), "--config-out", str(config), "--quiet"]) == 0
    assert main(["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]) == 0
    return folder, log, config, out


def test_evaluate_against_ground_truth_beats_the_raw_measurements(estimated, capsys):
    _, log, config, out = estimated
    argv = ["evaluate", str(out / "estimate.mcap"), "--truth", str(log), "--config", str(config)]
    assert main(argv) == 0
    assert "position_mm" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    summary, raw = metrics["summary"], metrics["raw_summary"]
    assert list(summary) == list(SUMMARY_KEYS)
    assert all(np.isfinite(v) for v in summary.values()), summary
    assert summary["position_mm"] < raw["position_mm"] / 10
    assert summary["orientation_deg"] < raw["orientation_deg"] / 10
    assert summary["occluded_s"] > 0 and summary["occluded_position_mm"] < 1.0
    assert summary["contact_precision"] > 0.9 and summary["contact_recall"] > 0.9
    # the covariance is written and scored: eᵀΣ⁻¹e/3 per knot, averaged per body
    assert 0.1 < metrics["details"]["bodies"]["torso"]["position_anees"] < 10
    # the biases were estimated: closer to the truth than zero is
    imu = metrics["details"]["imu_bias"]["imu"]
    assert imu["accel_mps2"] < imu["true_accel_mps2"] / 2
    assert imu["gyro_dps"] < imu["true_gyro_dps"] / 2


def test_the_ground_truth_against_itself_has_no_error(estimated, tmp_path):
    log = estimated[1]
    argv = ["evaluate", str(log), "--truth", str(log), "--estimate-prefix", "/ground_truth"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    summary = metrics["summary"]
    for key in SUMMARY_KEYS:
        if key.startswith("occluded"):  # no --config: no occlusions
            assert summary[key] is None, key
        elif key.startswith("contact_precision") or key.startswith("contact_recall"):
            assert summary[key] == 1.0
        elif key == "position_anees":  # the truth has no covariance
            assert summary[key] is None
        else:
            assert summary[key] == 0.0, key
    assert metrics["notes"]


def _strip_ground_truth(source: Path, target: Path) -> None:
    """Copy a log without its /ground_truth topics (schemas, channels, metadata kept)."""
    with source.open("rb") as f, target.open("wb") as out:
        reader = make_reader(f)
        writer = Writer(out)
        writer.start(profile="ros2", library="test")
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, dict(meta.metadata))
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.topic.startswith("/ground_truth/"):
                continue
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
        writer.finish()


def test_holdout_predicts_a_sensor_on_a_log_without_ground_truth(estimated, capsys):
    folder, log, config, estimate_dir = estimated
    bare = folder / "bare.mcap"
    _strip_ground_truth(log, bare)
    # no ground truth: --truth is a one-line error
    assert main(["evaluate", str(estimate_dir / "estimate.mcap"), "--truth", str(bare)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no ground truth" in err
    out = folder / "holdout_imu"
    argv = ["evaluate", str(bare), "--config", str(config), "--holdout", "imu", "--out", str(out)]
    assert main([*argv, "--quiet"]) == 0
    assert "gyro_x" in capsys.readouterr().out
    section = json.loads((out / "metrics.json").read_text())["holdout"]
    assert section["stream"] == "imu" and section["estimated_without_it"]["converged"]
    noise = {"accel": 0.03, "gyro": 0.004}  # the config's σ
    for axis in "xyz":
        gyro, raw_gyro = section["estimate"][f"gyro_{axis}"], section["raw"][f"gyro_{axis}"]
        # the estimate predicts the gyro within a few σ; mocap differences do not
        assert gyro["median_abs"] < 3 * noise["gyro"] and gyro["rmse"] < raw_gyro["rmse"] / 10
        accel = section["estimate"][f"accel_{axis}"]
        assert accel["median_abs"] < 10 * noise["accel"]
        assert section["raw"][f"accel_{axis}"]["rmse"] is None  # no raw accelerations
        assert section["estimate_with_fitted_bias"][f"accel_{axis}"]["rmse"] is not None


def test_bad_arguments_are_one_line_errors(estimated, tmp_path, capsys):
    _, log, config, out = estimated
    cases = [
        (["evaluate", str(tmp_path / "none.mcap"), "--truth", str(log)], "none.mcap"),
        (["evaluate", str(out / "estimate.mcap")], "--truth"),
        (
            ["evaluate", str(log), "--config", str(config), "--holdout", "lidar"],
            "streams that can be held out: mocap_torso",
        ),
        (
            ["evaluate", str(log), "--config", str(config), "--holdout", "command"],
            "command stream",
        ),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err
