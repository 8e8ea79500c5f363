"""The estimator's sensor model agrees with the simulator's sensors.

At the true trajectory of a simulation of the nominal model (no mismatch), the MuJoCo sensors
the estimator adds per stream (`model_with_sensors`), evaluated at the knot state it uses
(q_k, v_k = (q_k ⊖ q_{k−1})/h, a_k = (v_{k+1} − v_k)/h, through mj_inverse), reproduce the
noiseless values the simulator's sensors sample: framepos, framequat, accelerometer, gyro,
jointpos, force and torque. And the samples each knot stands for are taken from the step its
quantity belongs to, with saturated IMU samples left out, and position-stage samples are
predicted at their own times, between their two knots.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from estimator.config import load_config
from estimator.factors.imu import without_saturated
from estimator.io.logs import read_log
from estimator.io.logs.measurements import Measurement
from estimator.knots import averaged_at_knots, samples_between_knots
from estimator.problem import accelerations, build_problem, velocities
from estimator.settings import Settings
from estimator.simulate.sensors import Trajectory
from estimator.simulate.simulation import scenario_config, simulate
from physics.knots import KnotEngine

_SENS = mujoco.mjtSensor


def _sim_sensor(traj: Trajectory, site: str, kind: mujoco.mjtSensor) -> slice:
    """sensordata slice of the simulated model's own sensor of `kind` at `site`."""
    m = traj.model
    site_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    for s in range(m.nsensor):
        if m.sensor_type[s] == kind and m.sensor_objid[s] == site_id:
            return slice(int(m.sensor_adr[s]), int(m.sensor_adr[s] + m.sensor_dim[s]))
    raise AssertionError(f"the simulated model has no {kind} sensor at {site}")


@pytest.mark.parametrize(
    ("scenario", "duration_s"),
    [("humanoid_fall", 1.6), ("arm_box", 2.0)],  # the fall's impacts; the arm's grasp
)
def test_sensor_model_reproduces_the_simulated_sensors_at_the_true_trajectory(
    scenario, duration_s, tmp_path
):
    log = tmp_path / "log.mcap"
    result = simulate(scenario, log, seed=0, duration_s=duration_s, mismatch=False)
    traj = result.trajectory
    config_path = tmp_path / "config.toml"
    config_path.write_text(scenario_config(scenario))
    config = load_config(config_path)
    t_ns = traj.t0_ns + traj.step_ns(np.arange(traj.steps + 1))
    measurements = read_log(log, config).measurements
    problem = build_problem(config, measurements, Settings(), t_ns)
    assert problem.h == pytest.approx(traj.h)
    engine = KnotEngine(problem.model)
    v = velocities(problem.model, traj.qpos, traj.h)
    a = accelerations(v, traj.h)
    # the knot state is the simulator's state: v_k = qvel_k, a_k = (qvel_{k+1} − qvel_k)/h
    assert np.allclose(v[1:], traj.qvel[1:], atol=1e-9)
    m = problem.model
    checked: set[str] = set()
    for k in range(1, traj.steps):
        _, s = engine.inverse(traj.qpos[k], v[k], a[k])
        for name, stream in config.streams.items():
            for element in stream.elements:
                prefix = f"physfuse/{name}/{element}/"
                for tag in ("pos", "quat", "accel", "gyro", "force", "torque"):
                    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, prefix + tag)
                    if i < 0:
                        continue
                    rows = slice(int(m.sensor_adr[i]), int(m.sensor_adr[i] + m.sensor_dim[i]))
                    kind = _SENS(m.sensor_type[i])
                    expected = _simulated(traj, k, kind, element)
                    if kind == _SENS.mjSENS_FRAMEQUAT:  # q and −q are one rotation
                        expected = expected * np.sign(expected @ s[rows])
                    scale = max(1.0, float(np.abs(expected).max()))
                    error = np.abs(s[rows] - expected).max()
                    assert error < 1e-6 * scale, (name, element, kind.name, k, error)
                    checked.add(kind.name)
    expected_kinds = {
        "humanoid_fall": {
            "mjSENS_FRAMEPOS",
            "mjSENS_FRAMEQUAT",
            "mjSENS_ACCELEROMETER",
            "mjSENS_GYRO",
            "mjSENS_JOINTPOS",
        },
        "arm_box": {"mjSENS_FRAMEPOS", "mjSENS_FORCE", "mjSENS_TORQUE", "mjSENS_JOINTPOS"},
    }[scenario]
    assert expected_kinds <= checked


def _simulated(traj: Trajectory, k: int, kind: mujoco.mjtSensor, element: str) -> np.ndarray:
    """The simulator's noiseless value of a sensor of `kind` on `element` at step k."""
    m = traj.model
    if kind == _SENS.mjSENS_JOINTPOS:
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, element)
        return traj.qpos[k, m.jnt_qposadr[j] : m.jnt_qposadr[j] + 1]
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, element)
    if kind == _SENS.mjSENS_FRAMEPOS:
        return traj.site_xpos[k, site]
    if kind == _SENS.mjSENS_FRAMEQUAT:
        return traj.site_xquat[k, site]
    if kind == _SENS.mjSENS_GYRO:
        return traj.sensordata_vel[k, _sim_sensor(traj, element, kind)]
    return traj.sensordata_acc[k, _sim_sensor(traj, element, kind)]


def _imu_measurement(t_ns: np.ndarray, values: np.ndarray) -> Measurement:
    from estimator.io.logs.decode import IMU
    from estimator.io.logs.measurements import BadSampleCounts

    return Measurement(
        "imu", "imu", "/imu", "site", ("imu",), IMU, t_ns, t_ns, values, BadSampleCounts()
    )


def test_knots_average_the_samples_of_the_step_their_quantity_belongs_to():
    knots = np.array([0, 10, 20, 30], dtype=np.int64)
    t = np.array([1, 5, 10, 11, 19, 20, 25], dtype=np.int64)
    values = np.tile(t.astype(float)[:, None, None], (1, 1, 10))
    values[3, 0, 7] = np.nan  # a component left out is not counted
    m = _imu_measurement(t, values)
    # velocity stage: knot k averages (t_k − h, t_k]
    mean, n = averaged_at_knots(m, knots, "vel")
    assert n[:, 0, 4].tolist() == [0, 3, 3, 1]
    assert mean[1, 0, 4] == pytest.approx((1 + 5 + 10) / 3)
    assert mean[3, 0, 4] == 25
    assert np.isnan(mean[0, 0, 4])
    # acceleration stage: knot k averages [t_k, t_k + h)
    mean, n = averaged_at_knots(m, knots, "acc")
    assert n[:, 0, 4].tolist() == [2, 3, 2, 0]
    assert n[1, 0, 7] == 2 and mean[1, 0, 7] == pytest.approx((10 + 19) / 2)


def test_saturated_imu_samples_are_left_out_per_sensor_axis(tmp_path):
    path = tmp_path / "c.toml"
    quat = [float(np.cos(np.pi / 4)), 0.0, 0.0, float(np.sin(np.pi / 4))]  # sensor x = site y
    path.write_text(
        'model = "humanoid"\n[streams.imu]\ntype = "imu"\ntopic = "/imu"\nsite = "imu"\n'
        f"quat_site_sensor = {quat}\naccel_range = 80.0\ngyro_range = 30.0\n"
    )
    stream = load_config(path).streams["imu"]
    values = np.zeros((3, 1, 10))
    values[:, 0, 0] = 1.0
    values[0, 0, 7:10] = [0.0, 80.0, 0.0]  # site y = sensor x at the rail
    values[1, 0, 7:10] = [79.0, -79.0, 79.0]  # within range on every axis
    values[2, 0, 4:7] = [0.0, -30.0, 0.0]  # gyro at the rail
    m = without_saturated(_imu_measurement(np.arange(3, dtype=np.int64), values), stream)
    assert np.isnan(m.values[0, 0, 7:10]).all() and np.isfinite(m.values[0, 0, 4:7]).all()
    assert np.isfinite(m.values[1]).all()
    assert np.isnan(m.values[2, 0, 4:7]).all() and np.isfinite(m.values[2, 0, 7:10]).all()
    # without a range nothing is left out
    unlimited = replace(stream, accel_range=np.inf, gyro_range=np.inf)
    assert without_saturated(m, unlimited) is m


def test_position_samples_belong_to_the_knot_interval_they_fall_in():
    knots = np.arange(0, 70, 10, dtype=np.int64)  # T = 7: interior knots 1 … 5
    t = np.array([3, 10, 14, 17, 26, 45, 52, 58], dtype=np.int64)
    m = _imu_measurement(t, np.tile(t.astype(float)[:, None, None], (1, 1, 10)))
    (first, alpha0), (second, alpha1) = samples_between_knots(m, knots)

    def carried(values: np.ndarray) -> dict[int, float]:
        return {
            k: float(values[k, 0, 0]) for k in range(len(knots)) if np.isfinite(values[k, 0, 0])
        }

    # t ∈ (t_{k−1}, t_k] → knot k with α = (t − t_{k−1})/h; 3 comes before t_1 and 52, 58 need
    # the end knot 6, so none of them is used; a second sample in an interval → slot 1
    assert carried(first) == {1: 10, 2: 14, 3: 26, 5: 45}
    assert alpha0[[1, 2, 3, 5]] == pytest.approx([1.0, 0.4, 0.6, 0.5])
    assert carried(second) == {2: 17} and alpha1[2] == pytest.approx(0.7)
    assert np.isfinite(second[2]).all()


def test_samples_between_knots_are_predicted_by_blending_their_two_knots():
    """(1 − α) s_{k−1} + α s_k for vectors; for quaternions q_{k−1} taken to q_k's side (q and
    −q are one rotation) and the blend normalized."""
    from estimator.factors.measurement import between_knots

    root = Path(__file__).resolve().parent.parent
    config = load_config(root / "configs" / "humanoid_push.toml")
    measurements = read_log(root / "recordings" / "humanoid_push.mcap", config).measurements
    t_ns = np.arange(5) * 10_000_000 + measurements["mocap_torso"].t_ns[0]
    problem = build_problem(config, measurements, Settings(), t_ns)
    vector = replace(problem.blocks[0], alpha=np.array([1.0, 1.0, 0.25, 0.5, 1.0]))
    s = np.array([[1.0, 0.0, 0.0], [3.0, 4.0, 0.0], [5.0, 4.0, 2.0]])  # knots 1, 2, 3
    blend, _ = between_knots(vector, s, None, problem.model.nv)
    assert blend == pytest.approx(np.array([[1, 0, 0], [1.5, 1, 0], [4, 4, 1]]))
    half = np.sqrt(0.5)
    q = np.array([[1.0, 0, 0, 0], [-half, 0, 0, -half], [0, 0, 0, 1.0]])  # 0°, 90°, 180° on z
    blend, _ = between_knots(replace(vector, kind="quat"), q, None, problem.model.nv)
    assert np.linalg.norm(blend, axis=1) == pytest.approx(1.0)
    # knot 2: α = 0.25 of the way from 0° to 90°, on q_2's side (−q_1)
    expected = 0.75 * -q[0] + 0.25 * q[1]
    assert blend[1] == pytest.approx(expected / np.linalg.norm(expected))
    # knot 3: halfway from 90° to 180°: 135°
    assert np.degrees(2 * np.arctan2(abs(blend[2, 3]), abs(blend[2, 0]))) == pytest.approx(135)
