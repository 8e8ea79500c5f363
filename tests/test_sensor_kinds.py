"""The sensor kinds added through the factor layer: joint velocities from JointState and
binary foot-contact flags, on a simulated trot whose log carries both."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from factor_checks import jacobian_error

from estimator.cli import main
from estimator.config import load_config
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import build_problem
from estimator.run import residual_labels, residuals_by_type
from estimator.settings import Settings
from estimator.simulate import simulate
from estimator.simulate.scenarios import get_scenario
from estimator.simulate.sensors import FootContacts
from estimator.simulate.simulation import scenario_config

FEET = ("front_left_shin", "front_right_shin", "rear_left_shin", "rear_right_shin")
USE_VELOCITIES = 'joints = "model"\nuse = ["position", "velocity", "effort"]'


@pytest.fixture(scope="module")
def trot(tmp_path_factory):
    """A 1 s quadruped trot with foot-contact flags, its config fitting joint velocities too,
    and the true trajectory."""
    folder = tmp_path_factory.mktemp("trot")
    scenario = get_scenario("quadruped_trot")
    scenario = dataclasses.replace(scenario, sensors=(*scenario.sensors, FootContacts(FEET)))
    log, config = folder / "trot.mcap", folder / "trot.toml"
    result = simulate(scenario, log, seed=0, duration_s=1.0)
    text = scenario_config(scenario, config)
    assert 'joints = "model"' in text
    config.write_text(text.replace('joints = "model"', USE_VELOCITIES))
    return log, config, result


def _at_truth(trot, **settings):
    log, config_path, result = trot
    config = load_config(config_path)
    measurements = read_log(log, config).measurements
    h = float(config.load_model().opt.timestep)
    t_ns = knot_grid(measurements, h)
    problem = build_problem(config, measurements, Settings(**settings), t_ns)
    traj = result.trajectory
    step = np.round((t_ns - traj.t0_ns) / (traj.h * 1e9)).astype(int)
    qpos = traj.qpos[np.clip(step, 0, len(traj.qpos) - 1)]
    return problem, qpos, result


def _whitened(residuals, labels, factor, what):
    columns = [j for j, label in enumerate(labels[factor]) if what in label]
    r = residuals[factor][:, columns]
    return r[np.isfinite(r)], len(columns)


def test_joint_velocities_and_contact_flags_at_the_true_motion(trot):
    """At the true trajectory the new rows are noise-sized: encoder velocities against
    v_k = (q_k ⊖ q_{k−1})/h at their noise (median |r| of a unit Gaussian, 0.67), a swinging
    foot's contact force from the analytic inverse zero, a standing foot's sole nearly still."""
    problem, qpos, result = _at_truth(trot)
    residuals, _ = residuals_by_type(problem, qpos, np.zeros((problem.T, problem.nb)))
    labels = residual_labels(problem, residuals)
    velocity, n = _whitened(residuals, labels, "joints", "velocity")
    assert n == 12 and 0.55 < np.median(np.abs(velocity)) < 0.8
    force, n = _whitened(residuals, labels, "contacts", "contact force")
    assert n == 12 and len(force) > 1000  # swing phases of the trot
    assert np.percentile(np.abs(force), 95) < 0.1
    slip, _ = _whitened(residuals, labels, "contacts", "slip velocity")
    assert np.median(np.abs(slip)) < 0.5 and len(slip) > 1000
    assert labels["contacts"][:3] == [f"{FEET[0]} contact force {c}" for c in "xyz"]
    # the flags are the true contacts: the swing rows exist where the foot is in the air
    flags = result.sensors["contacts"]["flags"]
    assert 0.2 < flags.mean() < 0.8 and set(np.unique(flags)) == {0.0, 1.0}


def test_contact_force_rows_see_a_foot_pushed_into_the_ground(trot):
    """Lowering the body 1 cm presses the feet into the floor: the flagged-off feet that are
    low enough then carry force, so the factor measures contact and is not always zero."""
    problem, qpos, _ = _at_truth(trot)
    lowered = qpos.copy()
    lowered[:, 2] -= 0.01
    zeros = np.zeros((problem.T, problem.nb))
    r0, _ = residuals_by_type(problem, qpos, zeros)
    r1, _ = residuals_by_type(problem, lowered, zeros)
    labels = residual_labels(problem, r0)
    before, _ = _whitened(r0, labels, "contacts", "contact force")
    after, _ = _whitened(r1, labels, "contacts", "contact force")
    share_before, share_after = np.mean(np.abs(before) > 1.0), np.mean(np.abs(after) > 1.0)
    assert share_before < 0.05 and share_after > 4 * share_before + 0.1


def test_new_rows_have_jacobians_that_match_numerical_differentiation(trot):
    problem, qpos, _ = _at_truth(trot, huber_k=1e12)
    error, rows = jacobian_error(problem, qpos, np.zeros((problem.T, problem.nb)), k=40)
    assert error.max() < 2e-3, f"worst row {np.unravel_index(error.argmax(), error.shape)}"
    assert rows > 2 * problem.model.nv + 24


def test_estimate_runs_with_the_new_kinds_and_reports_them(trot, tmp_path):
    log, config, _ = trot
    out = tmp_path / "run"
    assert main(["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cost_by_type"]["contacts"] > 0
    assert all(not r["row"].startswith("row ") for r in summary["largest_residuals"])


@pytest.mark.parametrize(
    ("stream", "expected"),
    [
        ('type = "contact_flags"\ntopic = "/c"\n', "streams.c.bodies: give one of bodies"),
        (
            'type = "contact_flags"\ntopic = "/c"\nbodies = ["no_such_body"]\n',
            "streams.c.bodies[0]: unknown body 'no_such_body'",
        ),
        (
            'type = "contact_flags"\ntopic = "/c"\ngeoms = ["front_left_foot"]\nstamp = "header"\n',
            "a Float64MultiArray contact_flags stream has no header",
        ),
        (
            'type = "joint_state"\ntopic = "/j"\njoints = "model"\nuse = ["speed"]\n',
            "streams.c.use[0]: 'speed' (str) is not one of position, velocity, effort",
        ),
    ],
)
def test_new_kinds_config_errors_name_the_key(tmp_path, stream, expected):
    path = tmp_path / "robot.toml"
    path.write_text(f'model = "quadruped"\n[streams.c]\n{stream}')
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert expected in str(err.value)


def test_simulate_logs_contact_flags_and_maps_them(tmp_path, capsys):
    """`physfuse simulate --contact-flags BODY...`: the flags on /foot_contacts, a
    contact_flags stream in --config-out, read back as 0/1 per foot; a body the model lacks
    is one line naming the option."""
    log, config = tmp_path / "trot.mcap", tmp_path / "trot.toml"
    argv = ["simulate", "quadruped_trot", "--duration", "0.4", "--out", str(log), "--quiet"]
    assert main([*argv, "--config-out", str(config), "--contact-flags", *FEET]) == 0
    loaded = load_config(config)
    flags = read_log(log, loaded).measurements["contacts"]
    assert loaded.streams["contacts"].elements == FEET and flags.values.shape[1:] == (4, 1)
    assert set(np.unique(flags.values)) <= {0.0, 1.0} and 0 < flags.values.mean() < 1
    bad = tmp_path / "bad.mcap"
    assert main(["simulate", "quadruped_trot", "--out", str(bad), "--contact-flags", "wing"]) == 2
    assert "--contact-flags wing: quadruped has no (moving) body 'wing'" in capsys.readouterr().err
    assert not bad.exists()
