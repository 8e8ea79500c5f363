"""Config loading: the sample config resolves to the right elements; every error names the key."""

from __future__ import annotations

from pathlib import Path

import pytest
from ros2_logs import ROBOT_XML, SAMPLE_CONFIG, write_robot

from estimator.config import NOISE_DEFAULTS, check_model_names, load_config
from estimator.errors import ConfigError
from physics.model import MODEL_DIR

HEAD = 'model = "walker.xml"\n'


def _load(tmp_path: Path, text: str, **kwargs):
    return load_config(write_robot(tmp_path, text), **kwargs)


def test_sample_config_resolves_every_stream(tmp_path):
    config = _load(tmp_path, SAMPLE_CONFIG)
    assert config.model_path == tmp_path / "walker.xml"
    assert config.load_model().nu == 2
    s = config.streams
    assert list(s) == [
        "mocap_torso",
        "tf_torso",
        "tf_shin",
        "rigid",
        "markers",
        "imu",
        "joints",
        "command",
        "trajectory",
        "foot_ft",
    ]
    assert (s["mocap_torso"].element_type, s["mocap_torso"].elements) == ("body", ("torso",))
    assert s["mocap_torso"].sources is None
    assert s["mocap_torso"].noise == {"position_std_m": 0.0005, "orientation_std_rad": 0.01}
    assert s["tf_shin"].sources == ("shin_link",) and not s["tf_shin"].required
    assert s["rigid"].sources == ("Torso", "Shin") and s["rigid"].elements == ("torso", "shin")
    assert s["markers"].sources == ("7", "knee")
    assert s["markers"].elements == ("torso_marker", "knee_marker")
    assert s["imu"].quat_site_sensor == (1.0, 0.0, 0.0, 0.0)
    assert s["imu"].noise == NOISE_DEFAULTS["imu"]
    assert s["joints"].sources == ("knee_joint", "hip_joint")
    assert s["joints"].elements == ("knee", "hip")
    assert s["command"].sources == ("0", "1") and s["command"].field is None
    assert (s["command"].stamp, s["mocap_torso"].stamp) == ("log", "header")
    assert s["trajectory"].field == "effort"
    assert s["trajectory"].elements == ("knee_motor", "hip_motor")
    assert s["foot_ft"].element_keys == ("streams.foot_ft.site",)
    assert config.topics[:2] == ("/mocap/torso", "/tf")
    assert [x.name for x in config.streams_on("/tf")] == ["tf_torso", "tf_shin"]


def test_joints_model_maps_the_hinge_and_slide_joints(tmp_path):
    text = HEAD + '[streams.j]\ntype = "joint_state"\ntopic = "/js"\njoints = "model"\n'
    stream = _load(tmp_path, text).streams["j"]
    assert stream.elements == ("hip", "knee") and stream.sources == ("hip", "knee")


def test_actuators_model_maps_the_models_actuators_in_order(tmp_path):
    """A Float64MultiArray's data[i] drives actuator i; a JointTrajectory by each actuator's
    joint name."""
    text = HEAD + '[streams.c]\ntype = "command"\ntopic = "/c"\nactuators = "model"\n'
    stream = _load(tmp_path, text).streams["c"]
    assert stream.elements == ("hip_motor", "knee_motor") and stream.sources == ("0", "1")
    text += '[streams.t]\ntype = "command"\ntopic = "/t"\nactuators = "model"\nfield = "effort"\n'
    stream = _load(tmp_path, text).streams["t"]
    assert stream.elements == ("hip_motor", "knee_motor") and stream.sources == ("hip", "knee")
    assert stream.field == "effort"


def test_bundled_model_by_name(tmp_path):
    text = 'model = "humanoid"\n[streams.imu]\ntype = "imu"\ntopic = "/imu"\nsite = "imu"\n'
    config = _load(tmp_path, text)
    assert config.model_path == MODEL_DIR / "humanoid.xml"


def test_the_readme_example_is_a_valid_config(tmp_path):
    readme = (Path(__file__).parents[1] / "configs" / "README.md").read_text()
    (tmp_path / "example.toml").write_text(readme.split("```toml\n")[1].split("```")[0])
    config = load_config(tmp_path / "example.toml")
    assert len(config.streams) == 10
    assert len(config.streams["joints"].elements) == 21 == len(config.streams["command"].elements)
    feet = config.streams["feet"]
    assert feet.kind == "contact_flags" and feet.elements == ("right_foot", "left_foot")
    assert feet.sources == ("0", "1") and feet.stamp == "log"


def test_other_sections_pass_through_when_declared(tmp_path):
    text = SAMPLE_CONFIG + "\n[my_tool]\nduration_s = 2.0\n"
    config = _load(tmp_path, text, extra_sections=("my_tool",))
    assert config.sections == {"my_tool": {"duration_s": 2.0}}
    with pytest.raises(ConfigError, match=r"my_tool: unknown key; allowed keys: model, "):
        _load(tmp_path, text)


def test_the_estimator_and_simulate_tables_need_no_extra_sections(tmp_path):
    """physfuse's own tables are read (and validated) whether or not a caller names them."""
    text = SAMPLE_CONFIG + "\n[estimator]\nwindow_s = 2\n\n[simulate]\n"
    for kwargs in ({}, {"extra_sections": ("estimator", "simulate")}):
        config = _load(tmp_path, text, **kwargs)
        assert config.sections == {"estimator": {"window_s": 2}, "simulate": {}}
    bad = SAMPLE_CONFIG + "\n[estimator]\nwindow_s = -2\n"
    with pytest.raises(ConfigError, match=r"config.toml: estimator.window_s = -2; expected a"):
        _load(tmp_path, bad, extra_sections=("estimator",))


STREAM = '[streams.s]\ntype = "pose"\ntopic = "/p"\n'


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            HEAD + 'modle = "x"\n',
            "modle: unknown key; allowed keys: model, description, start_pose, streams",
        ),
        ('[streams.s]\ntype = "pose"\n', "model: missing"),
        (
            'model = "robot"\n' + STREAM + 'body = "torso"\n',
            "model: 'robot' is neither an MJCF file (*.xml) nor a bundled model; bundled models: ",
        ),
        ('model = "nothere.xml"\n' + STREAM + 'body = "torso"\n', "model: MJCF file"),
        (HEAD, "streams: no streams"),
        (
            HEAD + STREAM + 'bdy = "torso"\n',
            "streams.s.bdy: unknown key; allowed keys: type, topic, stamp, time_offset_ns, "
            "required, noise, max_abs, body, site",
        ),
        (
            HEAD + '[streams.s]\ntype = "camera"\ntopic = "/c"\n',
            "streams.s.type: 'camera' (str) is not one of pose, tf, rigid_bodies, markers, imu, "
            "joint_state, command, wrench",
        ),
        (HEAD + '[streams.s]\ntopic = "/c"\n', "streams.s.type: missing; one of pose, tf"),
        (HEAD + '[streams.s]\ntype = "pose"\nbody = "torso"\n', "streams.s.topic: missing"),
        (
            HEAD + STREAM + 'body = "torso"\nstamp = "recv"\n',
            "streams.s.stamp: 'recv' (str) is not one of header, log",
        ),
        (
            HEAD + STREAM + 'body = "torso"\ntime_offset_ns = 1.5\n',
            "streams.s.time_offset_ns: expected an integer number of ns within ±1e15 (11 days), "
            "got 1.5 (float)",
        ),
        (
            HEAD + STREAM + 'body = "torso"\ntime_offset_ns = 9_000_000_000_000_000_000\n',
            "streams.s.time_offset_ns: expected an integer number of ns within ±1e15",
        ),
        (
            HEAD + STREAM + 'body = "torso"\nrequired = "yes"\n',
            "streams.s.required: expected true or false, got 'yes' (str)",
        ),
        (
            HEAD + STREAM + 'body = "torso"\nnoise = { gyro_std = 0.1 }\n',
            "streams.s.noise.gyro_std: unknown key; allowed keys: position_std_m, "
            "orientation_std_rad",
        ),
        (
            HEAD + STREAM + 'body = "torso"\nnoise = { position_std_m = -1 }\n',
            "streams.s.noise.position_std_m: expected a positive finite number, got -1 (int)",
        ),
        (
            HEAD + STREAM + 'body = "torso"\nsite = "imu"\n',
            'streams.s.body: give exactly one of body = "<model body>" or site',
        ),
        (
            HEAD + STREAM + 'body = "torsoo"\n',
            "streams.s.body: unknown body 'torsoo'; valid body names: world, torso, thigh, shin",
        ),
        (
            HEAD + '[streams.s]\ntype = "imu"\ntopic = "/i"\nsite = "imu_site"\n',
            "streams.s.site: unknown site 'imu_site'; valid site names: imu, torso_marker, "
            "knee_marker, foot_ft",
        ),
        (
            HEAD + '[streams.s]\ntype = "imu"\ntopic = "/i"\nsite = "imu"\n'
            "quat_site_sensor = [1, 1, 0, 0]\n",
            "streams.s.quat_site_sensor: expected a unit quaternion [w, x, y, z], "
            "got [1, 1, 0, 0] (list)",
        ),
        (
            HEAD + '[streams.s]\ntype = "joint_state"\ntopic = "/j"\njoints = { l_knee = "kne" }\n',
            "streams.s.joints.l_knee: unknown joint 'kne'; valid joint names: hip, knee",
        ),
        (
            HEAD + '[streams.s]\ntype = "joint_state"\ntopic = "/j"\njoints = { r = "root" }\n',
            "streams.s.joints.r: unknown joint 'root'; valid joint names: hip, knee",
        ),
        (
            HEAD + '[streams.s]\ntype = "joint_state"\ntopic = "/j"\njoints = "all"\n',
            'streams.s.joints: expected "model" or a table',
        ),
        (
            HEAD + '[streams.s]\ntype = "command"\ntopic = "/c"\n'
            'actuators = ["hip_motor", "ankle_motor"]\n',
            "streams.s.actuators[1]: unknown actuator 'ankle_motor'; valid actuator names: "
            "hip_motor, knee_motor",
        ),
        (
            HEAD + '[streams.s]\ntype = "command"\ntopic = "/c"\n'
            'actuators = { hip = "hip_mot" }\nfield = "effort"\n',
            "streams.s.actuators.hip: unknown actuator 'hip_mot'",
        ),
        (
            HEAD
            + '[streams.s]\ntype = "command"\ntopic = "/c"\nactuators = { hip = "hip_motor" }\n',
            "streams.s.field: missing; a JointTrajectory command needs the point field that "
            "drives the actuators: one of positions, velocities, accelerations, effort",
        ),
        (
            HEAD + '[streams.s]\ntype = "command"\ntopic = "/c"\nactuators = ["hip_motor"]\n'
            'stamp = "header"\n',
            "streams.s.stamp: 'header' is not possible: a Float64MultiArray command stream has no "
            "header; use 'log'",
        ),
        (
            HEAD + '[streams.s]\ntype = "rigid_bodies"\ntopic = "/r"\nbodies = {}\n',
            "streams.s.bodies: empty; map at least one rigid body name to a model body",
        ),
        (
            HEAD + '[streams.s]\ntype = "tf"\ntopic = "/tf"\nbody = "torso"\n',
            "streams.s.child_frame_id: missing",
        ),
        (HEAD + "[streams]\ns = 3\n", "streams.s: expected a table, got 3 (int)"),
        (
            HEAD + '[streams.s]\ntype = "command"\ntopic = "/c"\nactuators = "all"\n',
            'streams.s.actuators: expected "model", a list of actuator names or a table',
        ),
    ],
)
def test_config_errors_name_the_key_and_the_allowed_values(tmp_path, text, expected):
    path = write_robot(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ")
    assert expected in message


def test_every_unknown_name_is_listed_in_one_message(tmp_path):
    text = HEAD + STREAM + 'body = "torsoo"\n[streams.t]\ntype = "imu"\ntopic = "/i"\nsite = "x"\n'
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, text)
    assert "streams.s.body: unknown body 'torsoo'" in str(err.value)
    assert "streams.t.site: unknown site 'x'" in str(err.value)
    assert "\n" not in str(err.value)


def test_unchecked_names_are_listed_by_check_model_names(tmp_path):
    text = HEAD + STREAM + 'body = "torsoo"\n'
    config = _load(tmp_path, text, check_names=False)
    (check,) = check_model_names(config, config.load_model())
    assert (check.key, check.name, check.found) == ("streams.s.body", "torsoo", False)
    assert check.valid == ("world", "torso", "thigh", "shin")


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "absent.toml")
    (tmp_path / "walker.xml").write_text(ROBOT_XML)
    bad = tmp_path / "bad.toml"
    bad.write_text('model = "walker.xml"\n[streams.s\n')
    with pytest.raises(ConfigError, match=r"bad.toml: not valid TOML: .*line 2"):
        load_config(bad)
