"""Random but physically plausible states of the bundled models, for the physics tests."""

from __future__ import annotations

from collections.abc import Iterator

import mujoco
import numpy as np

from physics.model import load_model


def reset(m: mujoco.MjModel, d: mujoco.MjData) -> None:
    """Reset to the keyframe "home" when the model has one."""
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
    if key >= 0:
        mujoco.mj_resetDataKeyframe(m, d, key)
    else:
        mujoco.mj_resetData(m, d)


def random_states(
    name: str, n: int, seed: int, steps_between: int = 15
) -> Iterator[tuple[mujoco.MjModel, np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (model, qpos, qvel, ctrl) along a simulation under random controls."""
    m = load_model(name)
    d = mujoco.MjData(m)
    reset(m, d)
    rng = np.random.default_rng(seed)
    lo, hi = m.actuator_ctrlrange.T if m.nu else (np.zeros(0), np.zeros(0))
    limited = m.actuator_ctrllimited.astype(bool)
    for _ in range(n):
        for _ in range(steps_between):
            ctrl = rng.normal(0.0, 1.0, m.nu)
            ctrl[limited] = rng.uniform(lo[limited], hi[limited])
            d.ctrl[:] = ctrl
            mujoco.mj_step(m, d)
        yield m, d.qpos.copy(), d.qvel.copy(), d.ctrl.copy()
