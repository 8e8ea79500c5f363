"""The EKF and UKF baselines: the manifold coordinates their sigma points live in, and each
filter on short slices of the sample recordings against ground truth."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from functools import cache
from pathlib import Path

import mujoco
import numpy as np
import pytest

from estimator.baselines.filters import TangentChart, filter_estimate
from estimator.cli import main
from estimator.config import Config, load_config
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.io.logs.measurements import Measurement
from estimator.io.state_topics import at_times, read_ground_truth, trajectory_errors
from estimator.run import initial_trajectory
from estimator.settings import Settings

ROOT = Path(__file__).resolve().parent.parent

_FREE_BODY = """
<mujoco><worldbody><body><freejoint/><geom size=".1"/></body>
<body pos="1 0 0"><joint type="ball"/><geom size=".1"/></body></worldbody></mujoco>
"""


def _chart() -> TangentChart:
    return TangentChart.of(mujoco.MjModel.from_xml_string(_FREE_BODY))


def test_chart_mean_of_rotations_about_one_axis_is_the_mean_angle():
    """Rotations by θ_i about one axis average to the rotation by Σ w_i θ_i about it, also
    where the coordinate (rotation-vector) mean of a mix of axes would not be a fixed point."""
    chart = _chart()
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    theta = np.array([0.3, 1.2, -0.4, 2.5, 0.9])
    weights = np.array([0.1, 0.3, 0.2, 0.25, 0.15])
    points = np.zeros((5, chart.model.nv))
    points[:, 3:6] = theta[:, None] * axis  # the free joint's rotation
    points[:, 6:9] = theta[:, None] * axis[::-1]  # the ball joint
    points[:, :3] = np.arange(15.0).reshape(5, 3)  # positions: a plain mean
    mean = chart.mean(points, weights)
    np.testing.assert_allclose(mean[3:6], (weights @ theta) * axis, atol=1e-12)
    np.testing.assert_allclose(mean[6:9], (weights @ theta) * axis[::-1], atol=1e-12)
    np.testing.assert_allclose(mean[:3], weights @ points[:, :3], atol=1e-12)


def test_chart_mean_satisfies_its_defining_equation_and_residual_inverts_add():
    """Σ w_i (x_i ⊖ m) = 0 for rotations about different axes; (x ⊕ d) ⊖ x = d."""
    chart = _chart()
    rng = np.random.default_rng(0)
    points = rng.normal(0.0, 0.6, (9, chart.model.nv))
    weights = rng.dirichlet(np.ones(9))
    mean = chart.mean(points, weights)
    balance = sum(w * chart.residual(p, mean) for w, p in zip(weights, points, strict=True))
    np.testing.assert_allclose(balance, 0.0, atol=1e-12)
    assert np.abs(mean[3:6] - weights @ points[:, 3:6]).max() > 1e-3  # not the plain mean
    x, d = rng.normal(0.0, 1.0, (2, chart.model.nv))
    np.testing.assert_allclose(chart.residual(chart.add(x, d), x), d, atol=1e-12)


def test_chart_coordinates_are_mujoco_tangent_space():
    """q̄ ⊕ δq and q ⊖ q̄ are mj_integratePos / mj_differentiatePos."""
    chart = _chart()
    model = chart.model
    reference = model.qpos0.copy()
    reference[3:7] = [0.6, 0.0, 0.8, 0.0]
    dq = np.random.default_rng(1).normal(0.0, 0.3, model.nv)
    q = chart.qpos(reference, dq)
    expected = reference.copy()
    mujoco.mj_integratePos(model, expected, dq, 1.0)
    np.testing.assert_allclose(q, expected)
    np.testing.assert_allclose(chart.coordinates(reference, q), dq, atol=1e-12)


@cache
def _slice(name: str, seconds: float) -> tuple[Config, dict[str, Measurement]]:
    config = load_config(ROOT / "configs" / f"{name}.toml")
    measurements = read_log(ROOT / "recordings" / f"{name}.mcap", config).measurements
    t0 = min(int(m.t_ns[0]) for m in measurements.values() if len(m))
    end = t0 + int(seconds * 1e9)
    sliced = {}
    for key, m in measurements.items():
        keep = m.t_ns < end
        sliced[key] = replace(
            m, t_ns=m.t_ns[keep], log_time_ns=m.log_time_ns[keep], values=m.values[keep]
        )
    return config, sliced


@pytest.mark.parametrize("method", ["ekf", "ukf"])
@pytest.mark.parametrize(
    ("name", "seconds"), [("humanoid_push", 2.0), ("quadruped_trot", 1.5), ("single_joint", 1.5)]
)
def test_filter_beats_the_raw_measurements(name, seconds, method):
    """Finite states; the free body's position and orientation better than the raw
    measurements (mocap with outliers, dropouts, latency); hinge angles no worse than 1.25×
    the encoders (16384 counts per turn, which a causal filter cannot improve much)."""
    config, measurements = _slice(name, seconds)
    est, summary = filter_estimate(config, measurements, Settings.from_config(config), method)
    assert np.all(np.isfinite(est.qpos)) and np.all(np.isfinite(est.qpos_std))
    assert summary.converged == [True] and summary.iterations == [est.T]
    model = config.load_model()
    truth = at_times(*read_ground_truth(ROOT / "recordings" / f"{name}.mcap", model), est.t_ns)
    raw = trajectory_errors(model, initial_trajectory(model, measurements, est.t_ns), truth)
    filtered = trajectory_errors(model, est.qpos, truth)
    for metric, error in filtered.items():
        if metric == "joint_deg":
            assert error < 1.25 * raw[metric], (metric, error, raw[metric])
        else:
            assert error < 0.5 * raw[metric], (metric, error, raw[metric])


def test_unknown_method_is_one_clear_error():
    config, measurements = _slice("single_joint", 0.1)
    with pytest.raises(ConfigError, match=r"'kf'.*ekf, ukf"):
        filter_estimate(config, measurements, Settings(), "kf")


MENAGERIE = ROOT / "physics" / "models" / "menagerie"


def _ekf_on_simulated(
    tmp_path: Path, argv: list[str]
) -> tuple[dict[str, float], dict[str, float], Mapping[str, Measurement]]:
    """`physfuse simulate ARGV` for 1 s and the EKF's estimate of it: its errors, the raw
    measurements' errors and the measurements."""
    log, config_path = tmp_path / "log.mcap", tmp_path / "log.toml"
    out = ["--duration", "1", "--out", str(log), "--config-out", str(config_path), "--quiet"]
    main(["simulate", *argv, *out])
    config = load_config(config_path)
    measurements = read_log(log, config).measurements
    est, _ = filter_estimate(config, measurements, Settings.from_config(config), "ekf")
    model = config.load_model()
    truth = at_times(*read_ground_truth(log, model), est.t_ns)
    raw = trajectory_errors(model, initial_trajectory(model, measurements, est.t_ns), truth)
    return trajectory_errors(model, est.qpos, truth), raw, measurements


def test_a_position_servo_is_not_applied_twice(tmp_path):
    """The filters step with the commands' force as u: the model's own actuation is off there.
    Menagerie's Panda drives its arm with position servos (force kp (ctrl − q) − kv q̇), whose
    bias −kp q − kv q̇ would otherwise pull every joint towards zero on top of u (the EKF's
    joints were 1.9° off, 400× the encoders)."""
    markers = [f"box_marker{i}" for i in range(4)]
    argv = ["--model", str(MENAGERIE / "panda_box.xml"), "--excitation", "0.2", "--markers"]
    filtered, raw, _ = _ekf_on_simulated(tmp_path, [*argv, *markers])
    assert filtered["joint_deg"] < 1.25 * raw["joint_deg"], (filtered, raw)


def test_a_pose_held_back_from_mocap_that_starts_late_stays_near_it(tmp_path):
    """ANYmal C's first mocap frame comes a few ms into its log, its base's start held back
    from it: the filter's prior there is the base's motion over those ms, not 1 m, which the
    first updates (encoders and IMU, through the feet's contacts) moved by 13 cm."""
    argv = ["--model", str(MENAGERIE / "anymal_c.xml"), "--excitation", "0.1"]
    filtered, raw, measurements = _ekf_on_simulated(tmp_path, [*argv, "--condition", "nominal"])
    assert measurements["mocap_base"].t_ns[0] > min(m.t_ns[0] for m in measurements.values())
    assert filtered["base_pos_mm"] < 0.5 * raw["base_pos_mm"], (filtered, raw)
