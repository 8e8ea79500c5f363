"""What the model says before estimating: actuators, contact settings, resting penetration,
commands against logged efforts (`physfuse inspect --config`, `estimator.model_checks`)."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import tomlkit
from model_variants import config_for_model, quadruped_with_actuators

from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import read_log
from estimator.knots import knot_grid
from estimator.model_checks import resting_penetration
from estimator.problem import build_problem, dof_names, joint_name, model_with_sensors
from estimator.settings import Settings

ROOT = Path(__file__).resolve().parent.parent
LOG = ROOT / "recordings" / "quadruped_trot.mcap"
CONFIG = ROOT / "configs" / "quadruped_trot.toml"

SOFT_BOX = """
<mujoco>
  <option timestep="0.001" integrator="Euler" cone="elliptic" impratio="10"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="box" pos="0 0 0.2">
      <freejoint/>
      <geom type="box" size="0.1 0.1 0.05" mass="10" solref="0.05 1" solimp="0.2 0.9 0.01 0.5 2"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_resting_penetration_is_where_a_simulated_body_comes_to_rest():
    """The bisection on mj_inverse's contact force gives the depth MuJoCo's own forward
    simulation settles at (a 10 kg box on soft contacts, solimp with a width)."""
    model = mujoco.MjModel.from_xml_string(SOFT_BOX)
    (rest,) = resting_penetration(model)
    data = mujoco.MjData(model)
    for _ in range(3000):
        mujoco.mj_step(model, data)
    settled = -min(data.contact[i].dist for i in range(data.ncon))
    assert rest.body == "box" and rest.contacts == data.ncon == 4
    assert rest.penetration_m == pytest.approx(settled, rel=1e-3)
    assert settled > 1e-3  # soft: millimetres, so the check is not trivially 0


def test_the_public_quadrupeds_soft_feet_rest_centimetres_deep():
    """Go2's own foot contacts (solimp 0.015 …, impratio 100) let it sink ≈ 17–18 mm."""
    model = mujoco.MjModel.from_xml_path(str(ROOT / "physics" / "models" / "menagerie" / "go2.xml"))
    (rest,) = resting_penetration(model, 0)
    assert 0.015 < rest.penetration_m < 0.02 and rest.contacts == 4


def _inspect(capsys, config: Path, tmp_path: Path) -> tuple[int, str, dict]:
    report = tmp_path / "report.json"
    code = main(["inspect", str(LOG), "--config", str(config), "--json", str(report)])
    out, _ = capsys.readouterr()
    return code, out, json.loads(report.read_text()) if report.is_file() else {}


def test_inspect_reports_actuator_kinds_and_the_contact_settings_in_use(capsys, tmp_path):
    model = quadruped_with_actuators(tmp_path)
    config = config_for_model(CONFIG, model, tmp_path)
    code, out, report = _inspect(capsys, config, tmp_path)
    assert code == 0
    kinds = {a["name"]: a["kind"] for a in report["model"]["actuators"]}
    assert kinds["front_left_knee"] == "position" and kinds["front_right_knee"] == "velocity"
    assert kinds["rear_left_knee"] == "general" and kinds["rear_right_knee"] == "motor"
    (knee,) = [a for a in report["model"]["actuators"] if a["name"] == "front_left_knee"]
    assert knee["kp"] == 30.0 and knee["kv"] == 1.0 and knee["commanded_by"] == "command"
    assert "contact settings in use (the model's own)" in out
    assert "resting penetration under its weight (keyframe 'home' posture" in out
    # an override in the config is what is reported, and said to be one
    document = tomlkit.parse(config.read_text())
    document.add("estimator", tomlkit.table())
    document["estimator"]["softness_eps"] = 0.2
    config.write_text(tomlkit.dumps(document))
    code, out, report = _inspect(capsys, config, tmp_path)
    assert "the config's softness_eps = 0.2 over the model's own" in out
    (setting,) = report["model"]["contact_settings"]
    assert setting["eps"] == pytest.approx([0.2, 0.2])
    softer = report["model"]["resting_penetration"][0]["penetration_m"]
    assert softer > 2 * 0.77e-3  # ε 4× the model's: deeper than its 0.77 mm


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ("swap", "disagree"),
        ("sign", "opposite sign"),
        ("units", "wrong units or gear"),
    ],
)
def test_commands_inconsistent_with_logged_efforts_are_flagged(capsys, tmp_path, change, expected):
    """A deliberately wrong actuator mapping (two actuators swapped in the command stream), a
    flipped gear and a gear ×10 each get a warning naming the actuator and what looks wrong;
    the recording's own mapping gets none."""
    code, out, _ = _inspect(capsys, CONFIG, tmp_path)
    assert code == 0 and "WARNING: commands to actuator" not in out
    if change == "swap":
        document = tomlkit.parse(CONFIG.read_text())
        names = document["streams"]["command"]["actuators"]
        names[1], names[2] = names[2], names[1]  # front left hip pitch ↔ knee
        config = tmp_path / "swapped.toml"
        document["model"] = str(ROOT / "physics" / "models" / "quadruped.xml")
        config.write_text(tomlkit.dumps(document))
    else:
        spec = mujoco.MjSpec.from_file(str(ROOT / "physics" / "models" / "quadruped.xml"))
        actuator = spec.actuator("front_left_knee")
        actuator.gear[0] *= -1.0 if change == "sign" else 10.0
        model = tmp_path / "geared.xml"
        model.write_text(spec.to_xml())
        config = config_for_model(CONFIG, model, tmp_path)
    code, out, report = _inspect(capsys, config, tmp_path)
    assert code == 0
    warned = [line for line in out.splitlines() if line.startswith("WARNING: commands to")]
    assert any("'front_left_knee'" in line and expected in line for line in warned), warned
    flagged = {c["actuator"] for c in report["model"]["commands_against_efforts"] if c["problem"]}
    assert "front_left_knee" in flagged and "rear_right_knee" not in flagged


def test_an_unnamed_free_joint_is_named_by_its_body():
    model = mujoco.MjModel.from_xml_string(SOFT_BOX)
    assert joint_name(model, 0) == "box"
    assert dof_names(model)[:3] == ["box_x", "box_y", "box_z"]


def test_a_softness_scale_keeps_the_models_per_geom_values():
    """softness_eps_scale multiplies each element's own ε = (1 − d)/d (Go2's feet and its
    other geoms differ, and stay different); softness_kappa_scale each time constant."""
    model = mujoco.MjModel.from_xml_path(str(ROOT / "physics" / "models" / "menagerie" / "go2.xml"))
    eps = (1 - model.geom_solimp[:, :2]) / model.geom_solimp[:, :2]
    kappa = model.geom_solref[:, 0].copy()
    assert len(np.unique(np.round(eps[:, 0], 9))) > 1  # per-geom values to keep
    Settings(softness_eps_scale=1.2, softness_kappa_scale=0.9).apply_softness(model)
    scaled = (1 - model.geom_solimp[:, :2]) / model.geom_solimp[:, :2]
    np.testing.assert_allclose(scaled, 1.2 * eps, rtol=1e-12)
    np.testing.assert_allclose(model.geom_solref[:, 0], 0.9 * kappa, rtol=1e-12)


def test_calibrate_fits_a_scale_of_the_models_own_softness(tmp_path, capsys):
    log, config = ROOT / "recordings" / "go2.mcap", ROOT / "configs" / "go2.toml"
    argv = ["calibrate", str(log), "--config", str(config), "--setting", "softness_eps_scale"]
    argv += ["--duration", "0.25", "--range", "0.8", "1.25", "--points", "3"]
    assert main([*argv, "--out", str(tmp_path), "--config-out", str(tmp_path / "c.toml")]) == 0
    report = json.loads((tmp_path / "calibration.json").read_text())
    assert report["setting"] == "softness_eps_scale" and report["initial"] == 1.0
    assert "softness_eps_scale = " in (tmp_path / "c.toml").read_text()


def test_a_physics_residual_over_the_whole_log_names_the_likely_setting(tmp_path, capsys):
    """Knee motors 30× too strong: the estimate warns on the knee's dof and points at the
    commands' force through the actuators (type, gains, units, mapping)."""
    spec = mujoco.MjSpec.from_file(str(ROOT / "physics" / "models" / "quadruped.xml"))
    for name in ("front_left_knee", "front_right_knee", "rear_left_knee", "rear_right_knee"):
        spec.actuator(name).gear[0] *= 30.0
    model = tmp_path / "strong_knees.xml"
    model.write_text(spec.to_xml())
    config = config_for_model(CONFIG, model, tmp_path)
    out = tmp_path / "out"
    assert main(["estimate", str(LOG), "--config", str(config), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    (line,) = [w for w in err.splitlines() if "does not explain the motion" in w]
    assert "_knee (largest" in line and "the commands' force through the actuators" in line


def test_a_softness_scale_that_is_not_a_factor_is_a_one_line_error(tmp_path, capsys):
    config = tmp_path / "zero.toml"
    config.write_text(
        (ROOT / "configs" / "go2.toml").read_text().replace("../physics", str(ROOT / "physics"))
        + "\n[estimator]\nsoftness_eps_scale = 0\n"
    )
    log = ROOT / "recordings" / "go2.mcap"
    assert main(["estimate", str(log), "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        len(err.splitlines()) == 1
        and "estimator.softness_eps_scale = 0; expected a factor > 0" in err
    )


def test_a_softness_scale_is_applied_once_per_problem_not_once_per_window():
    """build_problem on the same compiled model twice (two windows) scales it once."""
    config = load_config(ROOT / "configs" / "go2.toml")
    log = read_log(ROOT / "recordings" / "go2.mcap", config)
    t_ns = knot_grid(log.measurements, 0.002)
    compiled = model_with_sensors(config)
    settings = Settings(softness_eps_scale=1.2)
    first = build_problem(config, log.measurements, settings, t_ns[10:30], compiled)
    second = build_problem(config, log.measurements, settings, t_ns[30:50], compiled)
    np.testing.assert_array_equal(first.model.geom_solimp, second.model.geom_solimp)
    own = compiled[0].geom_solimp
    eps = (1 - own[:, :2]) / own[:, :2]
    scaled = (1 - first.model.geom_solimp[:, :2]) / first.model.geom_solimp[:, :2]
    np.testing.assert_allclose(scaled, 1.2 * eps, rtol=1e-12)
