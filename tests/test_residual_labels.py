"""Every residual row is named by its factor, element and component (terminal, summary, Rerun)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import build_problem, dof_names
from estimator.run import initial_trajectory, largest_residuals, residual_labels, residuals_by_type
from estimator.settings import Settings

ROOT = Path(__file__).resolve().parents[1]


def _labels(name: str, seconds: float = 0.3):
    config = load_config(ROOT / "configs" / f"{name}.toml")
    log = read_log(ROOT / "recordings" / f"{name}.mcap", config)
    t_ns = knot_grid(log.measurements, 0.002)
    t_ns = t_ns[t_ns < t_ns[0] + seconds * 1e9]
    problem = build_problem(config, log.measurements, Settings(), t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    residuals, _ = residuals_by_type(problem, qpos, np.zeros((len(t_ns), problem.nb)))
    return problem, residuals, residual_labels(problem, residuals)


@pytest.mark.parametrize("name", ["humanoid_push", "arm_box", "go2"])
def test_every_row_of_every_factor_has_its_own_label(name):
    problem, residuals, labels = _labels(name)
    assert set(labels) == set(residuals)
    for factor, r in residuals.items():
        assert len(labels[factor]) == r.shape[1], factor
        assert len(set(labels[factor])) == r.shape[1], factor  # no two rows alike
        assert not any(label.startswith("row ") for label in labels[factor]), factor
    assert labels["physics"] == dof_names(problem.model)


def test_labels_name_the_element_and_component():
    _, _, labels = _labels("humanoid_push")
    assert labels["mocap_torso"][:6] == [
        "torso_marker position x",
        "torso_marker position y",
        "torso_marker position z",
        "torso_marker rotation x",
        "torso_marker rotation y",
        "torso_marker rotation z",
    ]
    assert labels["imu"] == [f"{q} {a}" for q in ("accel", "gyro") for a in "xyz"]
    _, _, arm = _labels("arm_box")
    assert arm["ft"] == [f"{q} {a}" for q in ("force", "torque") for a in "xyz"]
    assert arm["markers"][:3] == [f"{arm['markers'][0][:-2]} {a}" for a in "xyz"]


def test_largest_residuals_report_the_label():
    from estimator.estimate import Estimate

    r = np.zeros((5, 2))
    r[3, 1] = -7.0
    est = Estimate(
        t_ns=np.arange(5) * 2_000_000,
        h=0.002,
        qpos=np.zeros((5, 1)),
        qvel=np.zeros((5, 1)),
        qacc=np.zeros((5, 1)),
        qfrc_inverse=np.zeros((5, 1)),
        qfrc_known=np.zeros((5, 1)),
        qpos_std=np.zeros((5, 1)),
        constraints=(),
        model_name="m",
        residuals={"joints": r},
        residual_labels={"joints": ["hip position", "knee position"]},
    )
    (top,) = largest_residuals(est)
    assert (top["factor"], top["row"], top["whitened"]) == ("joints", "knee position", -7.0)
