"""Every bad input is one clear line, found early: a model or setting `physfuse estimate`
cannot use fails `inspect --config` and `estimate` before the log is read, each [estimator]
and [simulate] key is checked when the config loads, and `evaluate` refuses states that share
nothing to compare."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import ros2_logs as rl

from estimator.calibrate import config_with
from estimator.cli import main
from estimator.cli.evaluate import shared_states
from estimator.config import load_config
from estimator.errors import ConfigError, PhysfuseError
from estimator.io.state_topics import Series, StateTopics

ROOT = Path(__file__).parents[1]
ELLIPTIC = '<option cone="elliptic"/>'  # (MuJoCo's default cone is pyramidal)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """A folder with the sample recording of the test walker (`ros2_logs`)."""
    folder = tmp_path_factory.mktemp("early")
    log = folder / "sample.mcap"
    rl.write_mcap(log, rl.sample_recording(0.5))
    return folder, log


def _config(folder: Path, name: str, options: str = "", table: str = "", xml: str = "") -> Path:
    """The sample config on a walker with the elliptic cone and then `options` (the later
    <option> wins), `table` added to the config, `xml` edits as "old -> new" lines."""
    model = rl.ROBOT_XML.replace("<worldbody>", f"{ELLIPTIC}\n  {options}\n  <worldbody>")
    for line in xml.splitlines():
        old, new = line.split(" -> ")
        model = model.replace(old, new)
    (folder / f"{name}.xml").write_text(model)
    config = folder / f"{name}.toml"
    text = rl.SAMPLE_CONFIG.replace('model = "walker.xml"', f'model = "{name}.xml"')
    top = not table.startswith("[")  # a top-level key goes before the first table
    config.write_text(table + text if top else text + "\n" + table)
    return config


def _error(capsys, argv: list[str]) -> str:
    """The one error line of a command that exits 2."""
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


# -- the model: what the engine supports, found before the log is read --------------------------
@pytest.mark.parametrize(
    ("option", "named"),
    [
        ('<option cone="pyramidal"/>', 'option cone="pyramidal"'),
        ('<option integrator="RK4"/>', 'option integrator="rk4"'),
        ('<option integrator="implicitfast"/>', 'option integrator="implicitfast"'),
        ('<option noslip_iterations="3"/>', "option noslip_iterations=3"),
    ],
)
def test_an_unsupported_model_option_fails_inspect_and_estimate_before_the_log(
    robot, tmp_path, capsys, option, named
):
    _, log = robot
    config = _config(tmp_path, "walker", option)
    err = _error(capsys, ["inspect", str(log), "--config", str(config)])
    assert f"{config}: model {tmp_path / 'walker.xml'}: {named}" in err
    assert "(set " in err  # how to fix it
    # a log that does not exist: the model is rejected before any log is read
    absent = tmp_path / "absent.mcap"
    for command in ("inspect", "estimate"):
        argv = [command, str(absent), "--config", str(config)]
        err = _error(
            capsys, [*argv, "--out", str(tmp_path / "o")] if command == "estimate" else argv
        )
        assert named in err and "absent.mcap" not in err, err


def test_the_walker_with_an_elliptic_cone_passes_inspect(robot, tmp_path, capsys):
    """(The options above are the only change that fails it.)"""
    _, log = robot
    assert main(["inspect", str(log), "--config", str(_config(tmp_path, "walker"))]) == 0
    assert capsys.readouterr().err == ""


def test_commands_to_an_actuator_they_cannot_drive_fail_inspect_before_the_log(tmp_path, capsys):
    edit = '<motor name="hip_motor" joint="hip"/> -> <general name="hip_motor" joint="hip" '
    edit += 'dyntype="filter" dynprm="0.05"/>'
    config = _config(tmp_path, "filtered", xml=edit)
    err = _error(capsys, ["inspect", str(tmp_path / "absent.mcap"), "--config", str(config)])
    assert f"{config}: streams.command: actuator 'hip_motor' cannot take commands" in err
    assert "dyntype=filter" in err


def test_a_mount_on_a_body_the_model_lacks_fails_inspect_in_one_line(tmp_path, capsys):
    """(inspect loads the config without check_names, to list the missing names.)"""
    config = _config(tmp_path, "walker")
    text = config.read_text().replace('body = "torso"\n', 'body = "torsoo"\nmount = {}\n', 1)
    config.write_text(text)
    err = _error(capsys, ["inspect", str(tmp_path / "absent.mcap"), "--config", str(config)])
    assert f"{config}: streams.mocap_torso.body: unknown body 'torsoo'; valid body names" in err


@pytest.mark.parametrize(
    ("table", "message"),
    [
        # MuJoCo would clamp κ below 2h: the knot step h, not the model's timestep
        ("softness_kappa = 0.005\nh = 0.004", "estimator.softness_kappa=0.005 s is below"),
        # the reference path takes one softness for the whole model
        ('path = "reference"', "estimator.path = 'reference' takes one flat contact softness"),
        # the softness fit divides by its prior's σ
        ("model_softness_std = 0", "estimator.model_softness_std = 0 gives fit_softness"),
    ],
)
def test_settings_the_model_cannot_take_fail_inspect_before_the_log(
    tmp_path, capsys, table, message
):
    edit = '<geom type="box" size=".1 .1 .1" mass="5"/> -> <geom type="box" size=".1 .1 .1" '
    edit += 'mass="5" solimp="0.8 0.8 0.001"/>'  # one geom softer than the others
    config = _config(tmp_path, "walker", table="[estimator]\n" + table + "\n", xml=edit)
    err = _error(capsys, ["inspect", str(tmp_path / "absent.mcap"), "--config", str(config)])
    assert str(config) in err and message in err, err


def test_the_same_settings_pass_where_the_engine_can_take_them(robot, tmp_path, capsys):
    _, log = robot
    table = (
        '[estimator]\nsoftness_kappa = 0.005\nsoftness_eps = 0.05\nh = 0.002\npath = "reference"\n'
    )
    table += 'model_softness_std = 0\nfit_softness = "none"\n'
    config = _config(tmp_path, "walker", table=table)
    assert main(["inspect", str(log), "--config", str(config)]) == 0, capsys.readouterr().err


# -- [estimator] and [simulate]: every key and value when the config loads ----------------------
@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("[estimator]\nwindow = 2", "estimator.window is not a setting (settings: method, "),
        ('[estimator]\nwindow_s = "2"', "estimator.window_s = '2'; expected a number > 0"),
        ("[estimator]\nmax_iterations = 2.5", "estimator.max_iterations = 2.5; expected an int"),
        ("[estimator]\nhuber_k = true", "estimator.huber_k = True; expected a number > 0"),
        ("[estimator]\nwindow_s = 0", "estimator.window_s = 0; expected a number > 0"),
        ("[estimator]\noverlap_s = -1", "estimator.overlap_s = -1; expected a number ≥ 0"),
        ("[estimator]\naccel_prior_std = nan", "estimator.accel_prior_std = nan; expected a"),
        ("[estimator]\nsoftness_eps_scale = 0", "estimator.softness_eps_scale = 0; expected a f"),
        ("[estimator]\nsoftness_eps = 1e6", "estimator.softness_eps=1000000.0 is outside"),
        ('[estimator]\nmethod = "smooth"', "estimator.method = 'smooth'; expected one of 'phy"),
        ("[estimator]\ninit = 1", "estimator.init = 1; expected one of 'measurements', "),
        ("estimator = 3", "estimator: expected a table, got 3 (int)"),
        ("[simulate]\nduration_s = 2.0", "simulate.duration_s: not a setting; physfuse reads"),
        ("simulate = 3", "simulate: expected a table, got 3 (int)"),
    ],
)
def test_each_bad_key_or_value_is_one_line_naming_file_table_and_key(tmp_path, table, message):
    config = _config(tmp_path, "walker", table=table + "\n")
    with pytest.raises(ConfigError) as err:
        load_config(config)
    assert len(str(err.value).splitlines()) == 1
    assert str(err.value).startswith(f"{config}: ") and message in str(err.value), err.value


def test_a_bad_setting_fails_inspect_before_the_log(tmp_path, capsys):
    config = _config(tmp_path, "walker", table='[estimator]\nmethod = "smooth"\n')
    err = _error(capsys, ["inspect", str(tmp_path / "absent.mcap"), "--config", str(config)])
    assert f"{config}: estimator.method = 'smooth'; expected one of" in err


def test_the_config_calibrate_writes_loads_and_passes_inspect(robot, tmp_path, capsys):
    """`physfuse calibrate --config-out` writes the config with [estimator] set
    (`estimator.calibrate.config_with`): plain load_config and inspect take it."""
    _, log = robot
    source = _config(tmp_path, "walker")
    written = tmp_path / "calibrated" / "walker.toml"
    for setting, value in (("softness_eps", 0.0523), ("softness_eps_scale", 1.7)):
        config_with(source, written, setting, value)
        config = load_config(written)
        assert config.sections["estimator"] == {setting: value}
        assert config.model_path.resolve() == (tmp_path / "walker.xml").resolve()
        assert main(["inspect", str(log), "--config", str(written)]) == 0
        assert capsys.readouterr().err == ""


# -- evaluate: states that share nothing -----------------------------------------------------------
def test_evaluate_refuses_another_robots_truth(tmp_path, capsys):
    """Go2's states (its log's ground truth, as the estimate) against H1's ground truth."""
    go2, h1 = ROOT / "recordings" / "go2.mcap", ROOT / "recordings" / "h1.mcap"
    argv = ["evaluate", str(go2), "--truth", str(h1), "--estimate-prefix", "/ground_truth"]
    err = _error(capsys, [*argv, "--out", str(tmp_path)])
    assert f"{go2} and {h1} share no body or joint to compare" in err
    assert "has bodies base; joints FL_hip_joint" in err and "has bodies pelvis" in err
    assert not (tmp_path / "metrics.json").exists()


def _states(path: str, bodies: tuple[str, ...], joints: tuple[str, ...], t0: int) -> StateTopics:
    t_ns = t0 + np.arange(10, dtype=np.int64) * 10_000_000
    return StateTopics(
        path=path,
        prefix="/x",
        odometry={b: Series(t_ns, np.zeros((10, 22))) for b in bodies},
        joint_names=joints,
        joints=Series(t_ns, np.zeros((10, 3 * len(joints)))) if joints else None,
        contact_wrench={},
        imu_bias={},
    )


def test_states_that_share_some_names_warn_and_none_or_no_time_fail():
    est = _states("est.mcap", ("torso", "box"), ("hip", "knee"), rl.T0)
    same = _states("truth.mcap", ("torso", "box"), ("hip", "knee"), rl.T0)
    assert shared_states(est, same) == []
    partial = _states("truth.mcap", ("torso",), ("hip", "knee", "ankle"), rl.T0)
    estimate_only, truth_only = shared_states(est, partial)
    assert "only the estimate (est.mcap) has bodies box: left out" in estimate_only
    assert "the 1 bodies and 2 joints both have" in estimate_only
    assert "only the truth (truth.mcap) has joints ankle" in truth_only
    other = _states("truth.mcap", ("pelvis",), ("elbow",), rl.T0)
    with pytest.raises(PhysfuseError, match=r"est.mcap and truth.mcap share no body or joint"):
        shared_states(est, other)
    later = _states("truth.mcap", ("torso",), (), rl.T0 + 60 * rl.NS)
    with pytest.raises(PhysfuseError, match=r"share no time \(an estimate of another log\?\)"):
        shared_states(est, later)
