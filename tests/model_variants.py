"""Bundled models turned into what public robot models look like: other actuator types, their
own contact settings, rotated inertia frames (written with MjSpec, loaded from a temp folder)."""

from __future__ import annotations

from pathlib import Path

import mujoco
import tomlkit

ROOT = Path(__file__).resolve().parent.parent


def quadruped_with_actuators(folder: Path) -> Path:
    """The bundled quadruped with every kind of affine actuator, same names and joints:
    position (kp 30, kv 1) on the front-left leg, velocity (kv 2) on the front-right, general
    with an affine gain and bias on the rear-left, motors with a small forcerange (clamped) on
    the rear-right; gear 1. Returns the MJCF path."""
    spec = mujoco.MjSpec.from_file(str(ROOT / "physics" / "models" / "quadruped.xml"))
    for i, actuator in enumerate(spec.actuators):
        leg = i // 3
        actuator.gear[0] = 1.0  # joint units, as public models write them
        if leg == 0:
            actuator.set_to_position(kp=30.0, kv=1.0)
        elif leg == 1:
            actuator.set_to_velocity(kv=2.0)
        elif leg == 2:
            actuator.gaintype = mujoco.mjtGain.mjGAIN_AFFINE
            actuator.gainprm[:3] = [5.0, 1.0, 0.5]
            actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            actuator.biasprm[:3] = [0.2, -5.0, -0.3]
        else:
            actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
            actuator.forcerange[:] = [-0.3, 0.3]
    path = folder / "quadruped_actuators.xml"
    path.write_text(spec.to_xml())
    return path


def config_for_model(config: Path, model: Path, folder: Path) -> Path:
    """A copy of `config` in `folder` whose model is the MJCF file `model`."""
    document = tomlkit.parse(config.read_text())
    document["model"] = str(model)
    path = folder / config.name
    path.write_text(tomlkit.dumps(document))
    return path
