"""Twists in the documented convention: the body frame origin's velocity, in the body frame."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from estimator.io.mcap_writer import body_twist

ROOT = Path(__file__).resolve().parent.parent

# a free body whose centre of mass is off its origin and whose inertia frame is rotated, as on
# most public models
ROTATED_INERTIA = """
<mujoco>
  <option integrator="Euler" cone="elliptic"/>
  <worldbody>
    <body name="base" pos="0 0 1">
      <freejoint name="root"/>
      <inertial pos="0.05 -0.03 0.02" quat="0.8 0.2 0.5 0.2" mass="2" diaginertia="0.1 0.2 0.3"/>
      <geom type="box" size="0.1 0.05 0.02" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""


def _finite_difference_twist(model, data, body, dt=1e-6):
    """[ω, v] of the body frame origin in the body frame from poses at t ± dt."""
    q0 = data.qpos.copy()
    poses = []
    for sign in (-1.0, 1.0):
        data.qpos[:] = q0
        mujoco.mj_integratePos(model, data.qpos, sign * data.qvel, dt)
        mujoco.mj_kinematics(model, data)
        poses.append((data.xpos[body].copy(), data.xmat[body].reshape(3, 3).copy()))
    data.qpos[:] = q0
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_comVel(model, data)
    (p0, R0), (p1, R1) = poses
    R = data.xmat[body].reshape(3, 3)
    v = R.T @ (p1 - p0) / (2 * dt)
    dR = R0.T @ R1  # ≈ I + [ω]× 2dt
    w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (4 * dt)
    return np.r_[w, v]


def _models():
    yield "rotated_inertia", mujoco.MjModel.from_xml_string(ROTATED_INERTIA)
    for name in ("humanoid", "quadruped", "arm_box"):
        yield name, mujoco.MjModel.from_xml_path(str(ROOT / "physics" / "models" / f"{name}.xml"))


@pytest.mark.parametrize(
    ("name", "model"), list(_models()), ids=lambda x: x if isinstance(x, str) else ""
)
def test_body_twist_is_the_body_origins_velocity_in_the_body_frame(name, model):
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    data.qvel[:] = rng.normal(0.0, 1.0, model.nv)
    mujoco.mj_forward(model, data)
    free = [model.jnt_bodyid[j] for j in range(model.njnt) if model.jnt_type[j] == 0]
    assert free
    for body in free:
        expected = _finite_difference_twist(model, data, body)
        np.testing.assert_allclose(body_twist(model, data, body), expected, atol=1e-6)


def test_the_centre_of_mass_velocity_differs_there():
    """On the rotated-inertia body, MuJoCo's mjOBJ_BODY velocity (centre of mass, inertia
    frame) is not the documented twist: the test above would catch that call."""
    model = mujoco.MjModel.from_xml_string(ROTATED_INERTIA)
    data = mujoco.MjData(model)
    data.qvel[:] = [0.3, -0.2, 0.1, 1.0, -0.5, 0.8]
    mujoco.mj_forward(model, data)
    com = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, 1, com, 1)
    assert np.abs(com - body_twist(model, data, 1)).max() > 0.1
