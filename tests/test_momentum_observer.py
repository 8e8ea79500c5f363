"""The momentum-observer baseline (estimator/baselines/momentum_observer.py): on a trajectory
MuJoCo integrates, its residual is zero without an external force and follows one through
its first-order filter, on a floating base."""

from __future__ import annotations

import mujoco
import numpy as np

from estimator.baselines.momentum_observer import GAIN, momentum_residual
from physics.model import load_model


def test_the_residual_follows_an_external_force_through_its_first_order_filter():
    """The humanoid in the air (contacts, limits and joint damping off, Euler steps as the knots'
    velocities are defined), random joint torques, a 40 N push on the torso from 0.2 s: r is
    zero before it to rounding, and Jᵀ F (1 − e^(−K_O t)) after."""
    model = load_model("humanoid")
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    model.dof_damping[:] = 0.0
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    h, T, onset = model.opt.timestep, 100, 20
    rng = np.random.default_rng(0)
    torso = model.body("torso").id
    force = np.array([40.0, -10.0, 5.0])
    qpos, qvel, tau = np.zeros((T, model.nq)), np.zeros((T, model.nv)), np.zeros((T, model.nv))
    jacp = np.zeros((3, model.nv))
    external = np.zeros((T, model.nv))
    for k in range(T):
        qpos[k], qvel[k] = data.qpos, data.qvel  # v_k = (q_k ⊖ q_{k−1}) / h
        tau[k, 6:] = rng.normal(0.0, 2.0, model.nv - 6)
        data.qfrc_applied[:] = tau[k]
        data.xfrc_applied[:] = 0.0
        if k >= onset:
            data.xfrc_applied[torso, :3] = force
            mujoco.mj_forward(model, data)
            mujoco.mj_jac(model, data, jacp, None, data.xipos[torso], torso)
            external[k] = jacp.T @ force
        mujoco.mj_step(model, data)
    r = momentum_residual(model, qpos, qvel, tau, h)
    scale = np.abs(external).max()
    assert np.abs(r[: onset + 1]).max() < 1e-8 * scale
    # r_{k+1} = r_k + K_O h (τ_ext,k − r_k): the step response, knot by knot
    expected = np.zeros_like(r)
    for k in range(T - 1):
        expected[k + 1] = expected[k] + GAIN * h * (external[k] - expected[k])
    assert np.abs(r - expected).max() < 1e-6 * scale
    assert np.abs(r[-1] - external[-2]).max() < 0.05 * scale  # settled to Jᵀ F
