"""Balanced contact forces: MuJoCo's contact Jacobian, the cone, the least-squares correction,
and on a recording: closer to the true contact forces than the model's own."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from estimator.batch import estimate
from estimator.config import load_config
from estimator.contact_forces import balanced_constraints, contact_jacobian, project_to_cone
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.io.mcap_writer import contact_wrenches
from estimator.io.state_topics import at_times, read_state_topics
from estimator.problem import build_problem
from estimator.run import collect_estimate
from estimator.settings import Settings
from physics.dynamics import make_dynamics

ROOT = Path(__file__).resolve().parent.parent


def _standing_quadruped() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The quadruped's home pose pressed 2 mm into the floor, one foot lifted off."""
    model = mujoco.MjModel.from_xml_path(str(ROOT / "physics" / "models" / "quadruped.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    lowest = min(data.geom_xpos[g][2] - model.geom_size[g][0] for g in range(1, model.ngeom))
    data.qpos[2] -= lowest + 0.002
    data.qpos[7] += 0.3  # the first leg's hip: its foot comes up
    mujoco.mj_forward(model, data)
    return model, data


def _dense_efc_jacobian(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    if mujoco.mj_isSparse(model):
        dense = np.zeros((data.nefc, model.nv))
        mujoco.mju_sparse2dense(
            dense, data.efc_J, data.efc_J_rownnz, data.efc_J_rowadr, data.efc_J_colind
        )
        return dense
    return data.efc_J.reshape(data.nefc, model.nv).copy()


def test_contact_jacobian_is_mujocos_constraint_jacobian():
    model, data = _standing_quadruped()
    efc_jac = _dense_efc_jacobian(model, data)
    contacts = make_dynamics(model).inverse(data.qpos, data.qvel, data.qacc).constraints.contacts
    assert 2 <= len(contacts.dim) < 4
    for i in range(len(contacts.dim)):
        adr = int(contacts.efc_address[i])
        np.testing.assert_allclose(
            contact_jacobian(model, data, contacts, i), efc_jac[adr : adr + 3], atol=1e-12
        )


def test_project_to_cone():
    mu = np.array([0.5, 1.0])
    np.testing.assert_array_equal(project_to_cone(np.array([10.0, 3.0, -4.0]), mu), [10, 3, -4])
    np.testing.assert_array_equal(project_to_cone(np.array([-1.0, 3.0, 4.0]), mu), [0, 0, 0])
    out = project_to_cone(np.array([2.0, 3.0, 4.0]), mu)  # ‖(6, 4)‖ > 2: onto the boundary
    assert np.hypot(out[1] / 0.5, out[2]) == pytest.approx(2.0)
    assert out[1] / out[2] == pytest.approx(3.0 / 4.0)
    np.testing.assert_array_equal(project_to_cone(np.array([-2.0]), mu), [0.0])


def test_balancing_recovers_the_contact_force_that_explains_a_residual():
    """r = J_cᵀ δ with δ inside the cones: the correction is δ (σ_f ≫ δ), the new residual
    r − J_cᵀ Δf vanishes; with no known force, or with σ_f → 0, nothing changes."""
    model, data = _standing_quadruped()
    constraints = make_dynamics(model).inverse(data.qpos, data.qvel, data.qacc).constraints
    contacts = constraints.contacts
    model_force = np.array([constraints.contact_impulse(i) for i in range(len(contacts.dim))])
    assert np.all(model_force[:, 0] > 0)
    delta = np.array([[5.0, 1.0, -2.0], [-3.0, 0.5, 0.5], [2.0, -1.0, 0.0]])[: len(contacts.dim)]
    jac = np.vstack([contact_jacobian(model, data, contacts, i) for i in range(len(delta))])
    residual = jac.T @ delta.ravel()
    sigma = np.full(model.nv, 2.0)
    balanced = balanced_constraints(model, data, constraints, residual, sigma, 1e6)
    for i in range(len(delta)):
        np.testing.assert_allclose(
            balanced.contact_impulse(i), model_force[i] + constraints.h * delta[i], atol=1e-6
        )
    unknown = np.full(model.nv, np.nan)
    assert balanced_constraints(model, data, constraints, unknown, sigma, 1e6) is constraints
    stiff = balanced_constraints(model, data, constraints, residual, sigma, 1e-9)
    np.testing.assert_allclose(stiff.efc_impulse, constraints.efc_impulse, atol=1e-9)


def test_balanced_forces_are_closer_to_the_truth_on_the_quadruped_recording():
    """The estimate of recordings/quadruped_trot: the balanced net contact force per foot is
    nearer the true one than the model's (at touch-down and lift-off the model's jump)."""
    config = load_config(ROOT / "configs" / "quadruped_trot.toml")
    log_path = ROOT / "recordings" / "quadruped_trot.mcap"
    log = read_log(log_path, config)
    est, _ = estimate(config, log.measurements, Settings())
    truth = read_state_topics(log_path)
    errors = {}
    for forces in ("model", "balanced"):
        settings = Settings(contact_forces=forces)
        problem = build_problem(config, log.measurements, settings, est.t_ns)
        model = problem.model
        bias = np.zeros((problem.T, problem.nb))
        again = collect_estimate(problem, est.qpos, bias, est.qpos_std, config)
        data = mujoco.MjData(model)
        wrench = np.zeros((problem.T, model.nbody, 3))
        for k in range(problem.T):
            data.qpos[:] = est.qpos[k]
            mujoco.mj_kinematics(model, data)
            wrench[k] = contact_wrenches(model, data, again.constraints[k])[:, :3]
        squared = []
        for body, series in truth.contact_wrench.items():
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
            true_force = at_times(series.t_ns, series.values, est.t_ns)[2:-2, :3]
            squared.append(np.sum((wrench[2:-2, b] - true_force) ** 2, axis=1))
        errors[forces] = float(np.sqrt(np.mean(np.concatenate(squared))))
    weight = float(np.sum(model.body_mass) * np.linalg.norm(model.opt.gravity))
    assert errors["balanced"] < 0.5 * errors["model"], errors
    assert errors["balanced"] < 0.2 * weight, (errors, weight)


def test_contact_forces_setting_is_checked(tmp_path):
    config = tmp_path / "typo.toml"
    text = (ROOT / "configs" / "quadruped_trot.toml").read_text()
    config.write_text(text + '\n[estimator]\ncontact_forces = "balance"\n')
    with pytest.raises(ConfigError, match=r"estimator.contact_forces = 'balance'; expected one of"):
        Settings.from_config(load_config(config))
