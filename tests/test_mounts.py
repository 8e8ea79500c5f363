"""Mountings in the config: a sensor's pose on a body or site, without editing the model."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import tomlkit

from estimator.cli import main
from estimator.config import load_config
from estimator.errors import ConfigError
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.problem import build_problem
from estimator.run import initial_trajectory
from estimator.settings import Settings
from estimator.solver.linearize import Linearizer

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "quadruped_trot.toml"
LOG = ROOT / "recordings" / "quadruped_trot.mcap"


def _mounted(folder: Path, shift_m: float = 0.0) -> Path:
    """The quadruped's config with its mocap marker and its IMU given as mounts on their
    bodies (the sites' poses, the IMU's axes folded into the mount) instead of model sites."""
    model = load_config(CONFIG).load_model()
    document = tomlkit.parse(CONFIG.read_text())
    document["model"] = str(ROOT / "physics" / "models" / "quadruped.xml")
    for stream, site in (("mocap_base", "base_marker"), ("imu", "imu")):
        table = document["streams"][stream]
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        quat = model.site_quat[i].copy()
        if "quat_site_sensor" in table:
            mujoco.mju_mulQuat(quat, model.site_quat[i], np.array(table["quat_site_sensor"]))
            del table["quat_site_sensor"]
        del table["site"]
        table["body"] = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.site_bodyid[i])
        pos = model.site_pos[i] + (shift_m if stream == "mocap_base" else 0.0)
        table["mount"] = {"pos": [float(v) for v in pos], "quat": [float(v) for v in quat]}
    path = folder / f"mounted{shift_m}.toml"
    path.write_text(tomlkit.dumps(document))
    return path


def _costs(config_path: Path) -> dict[str, float]:
    """Each factor's cost at one trajectory: the original config's start."""
    original = load_config(CONFIG)
    log = read_log(LOG, original)
    t_ns = knot_grid(log.measurements, 0.005)[100:160]
    qpos = initial_trajectory(original.load_model(), log.measurements, t_ns)
    config = load_config(config_path)
    log = read_log(LOG, config)
    problem = build_problem(config, log.measurements, Settings(), t_ns)
    lin = Linearizer(problem)
    try:
        return lin.cost(qpos, np.zeros((problem.T, problem.nb)))[1]
    finally:
        lin.close()


def test_a_mount_on_the_body_is_the_same_sensor_as_the_models_site(tmp_path):
    mounted = load_config(_mounted(tmp_path))
    assert mounted.streams["imu"].elements == ("physfuse/imu/mount",)
    assert mounted.streams["mocap_base"].mount is not None
    expected, got = _costs(CONFIG), _costs(_mounted(tmp_path))
    for name in ("mocap_base", "imu", "physics"):
        assert got[name] == pytest.approx(expected[name], rel=1e-9), name
    shifted = _costs(_mounted(tmp_path, shift_m=0.01))  # a marker 1 cm off is seen
    assert shifted["mocap_base"] > 10 * expected["mocap_base"]


def test_bad_mounts_are_one_line_errors(tmp_path, capsys):
    path = _mounted(tmp_path)
    text = path.read_text()
    for bad, expected in (
        ("pos = [", "pos = [1, "),  # 4 numbers
        ('body = "base"', 'body = "bsae"'),
    ):
        broken = tmp_path / "broken.toml"
        broken.write_text(text.replace(bad, expected, 1))
        with pytest.raises(ConfigError) as err:
            load_config(broken)
        assert "streams.mocap_base" in str(err.value)
    assert main(["inspect", str(LOG), "--config", str(path)]) == 0
    out = capsys.readouterr().out
    assert (
        "found              model body 'base' (mounted: 'physfuse/mocap_base/mount')  "
        "[streams.mocap_base.body]" in out
    )
