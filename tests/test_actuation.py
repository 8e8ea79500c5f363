"""Commands through the model's own actuators, at each knot's state (estimator.actuation)."""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np
import pytest
from factor_checks import jacobian_error
from model_variants import config_for_model, quadruped_with_actuators

from estimator.actuation import actuator_kind, commanded_force
from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import Problem, build_problem, u_known_along
from estimator.run import initial_trajectory
from estimator.settings import Settings
from estimator.solver.linearize import Linearizer

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def variant(tmp_path_factory) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(
        str(quadruped_with_actuators(tmp_path_factory.mktemp("model")))
    )


def _random_state(model: mujoco.MjModel, seed: int) -> mujoco.MjData:
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    dq = rng.normal(0.0, 0.3, model.nv)
    mujoco.mj_integratePos(model, data.qpos, dq, 1.0)
    data.qvel[:] = rng.normal(0.0, 1.0, model.nv)
    mujoco.mj_forward(model, data)
    return data


def test_the_variant_has_every_affine_actuator_kind(variant):
    kinds = [actuator_kind(variant, i) for i in range(variant.nu)]
    assert kinds == ["position"] * 3 + ["velocity"] * 3 + ["general"] * 3 + ["motor"] * 3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_commanded_force_is_mujocos_actuation_at_the_state(variant, seed):
    """qfrc equals MuJoCo's qfrc_actuator at (q, v) with the same ctrl (position actuators:
    kp (ctrl − q) − kv v, not kp·ctrl), and a NaN command leaves its actuator's force out."""
    data = _random_state(variant, seed)
    ctrl = np.random.default_rng(seed).uniform(-1.0, 1.0, variant.nu)
    check = mujoco.MjData(variant)
    check.qpos[:], check.qvel[:], check.ctrl[:] = data.qpos, data.qvel, ctrl
    mujoco.mj_forward(variant, check)
    qfrc, _, _ = commanded_force(variant, data, ctrl)
    np.testing.assert_allclose(qfrc, check.qfrc_actuator, atol=1e-12)
    knee = mujoco.mj_name2id(variant, mujoco.mjtObj.mjOBJ_JOINT, "front_left_knee")
    dof, q = variant.jnt_dofadr[knee], data.qpos[variant.jnt_qposadr[knee]]
    assert qfrc[dof] == pytest.approx(30.0 * (ctrl[2] - q) - 1.0 * data.qvel[dof])
    without = ctrl.copy()
    without[2] = np.nan
    assert commanded_force(variant, data, without)[0][dof] == 0.0


@pytest.mark.parametrize("seed", [0, 1])
def test_commanded_force_jacobians_match_numerical_differentiation(variant, seed):
    """∂qfrc/∂q (tangent perturbations q ⊕ x) and ∂qfrc/∂v against central differences,
    including the motors clamped at their forcerange (derivative 0)."""
    data = _random_state(variant, seed)
    ctrl = np.random.default_rng(10 + seed).uniform(-1.0, 1.0, variant.nu)
    _, dq, dv = commanded_force(variant, data, ctrl, jacobians=True)
    q0, v0 = data.qpos.copy(), data.qvel.copy()
    eps = 1e-6
    numeric_q, numeric_v = np.zeros_like(dq), np.zeros_like(dv)
    for c in range(variant.nv):
        for sign in (1.0, -1.0):
            x = np.zeros(variant.nv)
            x[c] = sign * eps
            data.qpos[:] = q0
            mujoco.mj_integratePos(variant, data.qpos, x, 1.0)
            data.qvel[:] = v0
            mujoco.mj_forward(variant, data)
            numeric_q[:, c] += sign * commanded_force(variant, data, ctrl)[0] / (2 * eps)
            data.qpos[:], data.qvel[:] = q0, v0 + x
            mujoco.mj_forward(variant, data)
            numeric_v[:, c] += sign * commanded_force(variant, data, ctrl)[0] / (2 * eps)
    np.testing.assert_allclose(dq, numeric_q, atol=1e-5)
    np.testing.assert_allclose(dv, numeric_v, atol=1e-5)
    assert np.abs(dq).max() > 10.0 and np.abs(dv).max() > 0.5  # the position actuators' kp, kv


def test_a_joints_actuator_force_range_clamps_the_commanded_force_as_mujoco_does(variant):
    """A hinge with actuatorfrcrange (Menagerie's Berkeley Humanoid: ±5 N m on its ankles):
    MuJoCo clamps the actuators' sum on the joint's dof; so does the commanded force, whose
    derivatives there are then 0 (against central differences, as above)."""
    model = copy.deepcopy(variant)
    knee = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "front_left_knee")
    dof = model.jnt_dofadr[knee]
    model.jnt_actfrclimited[knee] = 1
    model.jnt_actfrcrange[knee] = (-0.5, 0.5)
    data = _random_state(model, 0)
    ctrl = np.random.default_rng(3).uniform(-1.0, 1.0, model.nu)
    check = mujoco.MjData(model)
    check.qpos[:], check.qvel[:], check.ctrl[:] = data.qpos, data.qvel, ctrl
    mujoco.mj_forward(model, check)
    qfrc, dq, dv = commanded_force(model, data, ctrl, jacobians=True)
    assert abs(check.qfrc_actuator[dof]) == pytest.approx(0.5)  # clamped, by MuJoCo
    np.testing.assert_allclose(qfrc, check.qfrc_actuator, atol=1e-12)
    assert dq is not None and dv is not None
    assert not dq[dof].any() and not dv[dof].any()
    unclamped = commanded_force(variant, data, ctrl, jacobians=True)
    assert np.abs(unclamped[1][dof]).max() > 10.0  # what the clamp holds at 0


def test_known_force_follows_the_estimate_not_the_rest_pose(variant, tmp_path):
    """u_known of a position actuator at a knot is kp (ctrl − q_k) − kv v_k at that knot."""
    problem, qpos = _trot_window(tmp_path, slice(100, 140))
    known = u_known_along(problem, qpos)
    m = problem.model
    knee = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "front_left_knee")
    dof, adr = m.jnt_dofadr[knee], m.jnt_qposadr[knee]
    v = (qpos[1:, adr] - qpos[:-1, adr]) / problem.h
    expected = 30.0 * (problem.ctrl[1:, 2] - qpos[1:, adr]) - v
    np.testing.assert_allclose(known[1:, dof], expected, atol=1e-9)
    assert np.all(problem.qfrc_known[:, dof] == 0.0)  # the state-independent part
    assert np.isfinite(problem.physics_sigma[:, dof]).all()


def test_commands_to_an_actuator_with_activation_dynamics_are_one_line_errors(tmp_path, capsys):
    spec = mujoco.MjSpec.from_file(str(ROOT / "physics" / "models" / "quadruped.xml"))
    spec.actuators[4].dyntype = mujoco.mjtDyn.mjDYN_FILTER
    spec.actuators[4].dynprm[0] = 0.05
    model_path = tmp_path / "filtered.xml"
    model_path.write_text(spec.to_xml())
    config = config_for_model(ROOT / "configs" / "quadruped_trot.toml", model_path, tmp_path)
    log = ROOT / "recordings" / "quadruped_trot.mcap"
    assert main(["estimate", str(log), "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "streams.command: actuator 'front_right_hip_pitch' cannot take commands" in err
    assert "dyntype=filter" in err


def test_physics_factor_jacobian_with_state_dependent_actuation(tmp_path):
    """The physics rows W (u − u_known(q, v)) on the variant quadruped (position, velocity,
    affine and clamped actuators) against central differences on the manifold."""
    model_path = quadruped_with_actuators(tmp_path)
    config = load_config(
        config_for_model(ROOT / "configs" / "quadruped_trot.toml", model_path, tmp_path)
    )
    log = read_log(ROOT / "recordings" / "quadruped_trot.mcap", config)
    t_ns = knot_grid(log.measurements, 0.005)[200:212]
    problem = build_problem(config, log.measurements, Settings(huber_k=1e12), t_ns)
    qpos = initial_trajectory(problem.model, log.measurements, t_ns)
    bias = np.random.default_rng(0).normal(0.0, 0.01, (problem.T, problem.nb))
    error, _ = jacobian_error(problem, qpos, bias)
    nv = problem.model.nv
    physics = error[:nv]  # the physics rows come first
    assert physics.max() < 2e-3, (
        f"worst physics row {np.unravel_index(physics.argmax(), physics.shape)}"
    )
    assert error.max() < 2e-3


def test_the_linearizer_batches_the_commands_forces_as_knot_by_knot(tmp_path):
    """u_known over a window's knots in one batch (`Problem.u_known_of`, each chunk of the
    linearization's threads) equals `Problem.u_known` knot by knot, clamped actuators and
    knots and actuators without a command included."""
    problem, qpos = _trot_window(tmp_path, slice(100, 160))
    problem.ctrl[20:25] = np.nan  # knots without commands
    problem.ctrl[30, :3] = 1e3  # beyond ctrlrange: clamped
    problem.ctrl[40, 3:6] = np.nan  # some actuators without a command
    lin = Linearizer(problem)
    try:
        batched = lin.terms(qpos, True).known
    finally:
        lin.close()
    knot_by_knot = u_known_along(problem, qpos)[1:-1]
    assert np.isfinite(problem.ctrl[1:-1]).any(axis=1).sum() < problem.T - 2
    np.testing.assert_allclose(batched, knot_by_knot, rtol=1e-12, atol=1e-9)


def _trot_window(tmp_path: Path, knots: slice) -> tuple[Problem, np.ndarray]:
    """The quadruped_trot recording's problem on `knots` of its grid with the variant
    quadruped's actuators, and the measurements' start there."""
    model_path = quadruped_with_actuators(tmp_path)
    config = load_config(
        config_for_model(ROOT / "configs" / "quadruped_trot.toml", model_path, tmp_path)
    )
    log = read_log(ROOT / "recordings" / "quadruped_trot.mcap", config)
    t_ns = knot_grid(log.measurements, 0.005)[knots]
    problem = build_problem(config, log.measurements, Settings(), t_ns)
    return problem, initial_trajectory(problem.model, log.measurements, t_ns)
