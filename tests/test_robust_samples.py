"""One bad stamp or value is an outlier of that sample: counted, skipped, the stream goes on."""

from __future__ import annotations

import numpy as np
import pytest
import ros2_logs as rl

from estimator.cli import main
from estimator.config import load_config
from estimator.io.logs import ByteStreamReader, read_log

DURATION = 0.5
IMU = "/imu"
MOCAP = "/mocap/torso"


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    folder = tmp_path_factory.mktemp("robot")
    return folder, load_config(rl.write_robot(folder))


def _with(replaced: dict[tuple[str, int], rl.Msg]) -> list[rl.Msg]:
    """The sample recording with messages (topic, k) replaced, in log-time order."""
    counts = rl.sample_counts(DURATION)
    msgs = [
        replaced.get((topic, k), rl.sample_message(topic, k))
        for topic in rl.SAMPLE_TOPICS
        for k in range(counts[topic])
    ]
    return sorted(msgs, key=lambda m: m.log_time_ns)


def _imu_at(k: int, stamp_ns: int, *, log_time_ns: int | None = None) -> rl.Msg:
    v = rl.value(IMU, k)
    fields = rl.imu(stamp_ns, v["gyro"], v["accel"], v["quat"])
    log_time = rl.sample_log_time(IMU, k) if log_time_ns is None else log_time_ns
    return rl.Msg(IMU, rl.SAMPLE_TOPICS[IMU][0], log_time, fields)


def _mocap_at(k: int, pos, quat) -> rl.Msg:
    fields = rl.pose_stamped(rl.sample_stamp(MOCAP, k), pos, quat)
    return rl.Msg(MOCAP, rl.SAMPLE_TOPICS[MOCAP][0], rl.sample_log_time(MOCAP, k), fields)


def _read(tmp_path, config, messages):
    path = tmp_path / "log.mcap"
    rl.write_mcap(path, messages, chunk_size=4096)
    return path, read_log(path, config)


def _stamps(topic: str, skipped: set[int]) -> np.ndarray:
    n = rl.sample_counts(DURATION)[topic]
    return np.array([rl.sample_stamp(topic, k) for k in range(n) if k not in skipped])


@pytest.mark.parametrize(
    ("k", "stamp_offset_s", "why"),
    [
        (50, 1000.0, "one stamp 1000 s late in the middle"),
        (0, -1000.0, "the first stamp far before the rest"),
        (None, 1000.0, "the last stamp 1000 s late"),
    ],
)
def test_one_jumped_stamp_loses_one_sample(robot, tmp_path, k, stamp_offset_s, why):
    _, config = robot
    n = rl.sample_counts(DURATION)[IMU]
    k = n - 1 if k is None else k
    bad = _imu_at(k, rl.sample_stamp(IMU, k) + int(stamp_offset_s * 1e9))
    _, log = _read(tmp_path, config, _with({(IMU, k): bad}))
    imu = log.measurements["imu"]
    assert imu.bad.time_jump == 1 and imu.bad.total == 1, why
    np.testing.assert_array_equal(imu.t_ns, _stamps(IMU, {k}))


def test_a_stamp_of_zero_first_does_not_stretch_the_log(robot, tmp_path):
    _, config = robot
    _, log = _read(tmp_path, config, _with({(IMU, 0): _imu_at(0, 0)}))
    imu = log.measurements["imu"]
    assert imu.bad.time_jump == 1
    assert imu.t_ns[0] == rl.sample_stamp(IMU, 1)


def test_a_log_time_beyond_int64_is_counted_and_inspect_reports_it(robot, tmp_path, capsys):
    folder, config = robot
    k = 40
    bad = _imu_at(k, rl.sample_stamp(IMU, k), log_time_ns=(1 << 64) - 1)
    path, log = _read(tmp_path, config, _with({(IMU, k): bad}))
    imu = log.measurements["imu"]
    assert imu.bad.bad_time == 1 and imu.bad.total == 1
    np.testing.assert_array_equal(imu.t_ns, _stamps(IMU, {k}))
    assert main(["inspect", str(path), "--config", str(folder / "config.toml")]) == 0
    assert "bad_time=1" in capsys.readouterr().out


def test_the_largest_header_stamp_is_one_time_jump(robot, tmp_path):
    _, config = robot
    k = 30
    bad = _imu_at(k, (2**31 - 1) * rl.NS + 999_999_999)  # stamp.sec is an int32
    _, log = _read(tmp_path, config, _with({(IMU, k): bad}))
    imu = log.measurements["imu"]
    assert imu.bad.time_jump == 1 and imu.bad.total == 1
    np.testing.assert_array_equal(imu.t_ns, _stamps(IMU, {k}))


@pytest.mark.parametrize(
    ("pos", "quat", "why"),
    [
        ([1e300, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], "a position of 1e300 m"),
        ([0.1, 0.2, 1.0], [0.0, 0.0, 0.0, 0.0], "a zero quaternion"),
        ([0.1, 0.2, 1.0], [5.0, 0.0, 0.0, 0.0], "a quaternion of norm 5"),
    ],
)
def test_a_value_beyond_physics_is_out_of_bounds(robot, tmp_path, pos, quat, why):
    _, config = robot
    k = 12
    _, log = _read(tmp_path, config, _with({(MOCAP, k): _mocap_at(k, pos, quat)}))
    mocap = log.measurements["mocap_torso"]
    assert mocap.bad.out_of_bounds == 1 and mocap.bad.total == 1, why
    np.testing.assert_array_equal(mocap.t_ns, _stamps(MOCAP, {k}))
    assert np.abs(mocap.values).max() < 1e3


def test_the_byte_stream_reader_gives_the_same_samples(robot, tmp_path):
    _, config = robot
    k = 50
    bad = _imu_at(k, rl.sample_stamp(IMU, k) + 1000 * rl.NS)
    path, log = _read(tmp_path, config, _with({(IMU, k): bad}))
    with path.open("rb") as f:
        streamed = ByteStreamReader(f, config).read_all()
    for name, m in log.measurements.items():
        np.testing.assert_array_equal(streamed.measurements[name].t_ns, m.t_ns)
        assert streamed.measurements[name].bad == m.bad


def test_a_streams_max_abs_overrides_the_default_bound(tmp_path):
    text = rl.SAMPLE_CONFIG.replace(
        'body = "torso"\nnoise = { position_std_m = 0.0005 }',
        'body = "torso"\nnoise = { position_std_m = 0.0005 }\nmax_abs = { py = 0.1 }',
        1,
    )
    assert text != rl.SAMPLE_CONFIG
    config = load_config(rl.write_robot(tmp_path, text))
    _, log = _read(tmp_path, config, _with({}))
    mocap = log.measurements["mocap_torso"]
    n = rl.sample_counts(DURATION)[MOCAP]
    beyond = {k for k in range(n) if abs(rl.value(MOCAP, k)["pos"][1]) > 0.1}
    assert beyond and mocap.bad.out_of_bounds == len(beyond)
    np.testing.assert_array_equal(mocap.t_ns, _stamps(MOCAP, beyond))


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("{ nope = 1.0 }", "streams.mocap_torso.max_abs.nope: unknown key"),
        ("{ px = -1.0 }", "streams.mocap_torso.max_abs.px: expected a positive number"),
    ],
)
def test_a_bad_max_abs_is_one_line(tmp_path, table, message):
    from estimator.errors import ConfigError

    text = rl.SAMPLE_CONFIG.replace(
        'body = "torso"\nnoise = { position_std_m = 0.0005 }',
        f'body = "torso"\nnoise = {{ position_std_m = 0.0005 }}\nmax_abs = {table}',
        1,
    )
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        load_config(rl.write_robot(tmp_path, text))


def _rewritten(source, target, change) -> None:
    """`source` MCAP rewritten to `target` with change(topic, index on topic, log_time, data)
    → (log_time, data) applied to every message."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(source, "rb") as f, open(target, "wb") as out:
        writer = Writer(out)
        writer.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        seen: dict[str, int] = {}
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            k = seen[channel.topic] = seen.get(channel.topic, -1) + 1
            log_time, data = change(channel.topic, k, message.log_time, message.data)
            writer.add_message(channels[channel.id], log_time, data, log_time)
        writer.finish()


def test_estimate_uses_the_rest_of_a_log_with_bad_stamps_and_values(tmp_path, capsys):
    """One joint stamp 1000 s late, the first mocap stamp 0, a mocap position of 1e300 and a
    log time ≥ 2⁶³: the estimate runs on everything else and reports what it skipped."""
    import json
    import struct
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]

    def change(topic, k, log_time, data):
        data = bytearray(data)
        if topic == "/joint_states" and k == 100:
            sec = struct.unpack_from("<i", data, 4)[0]
            struct.pack_into("<i", data, 4, sec + 1000)  # header.stamp.sec (after CDR's 4 bytes)
        if topic == "/mocap/arm/pose" and k == 0:
            struct.pack_into("<ii", data, 4, 0, 0)
        if topic == "/mocap/arm/pose" and k == 50:  # pose.position.x: the last 7 float64
            struct.pack_into("<d", data, len(data) - 56, 1e300)
        if topic == "/joint_commands" and k == 200:
            log_time = (1 << 63) + 5
        return log_time, bytes(data)

    log = tmp_path / "damaged.mcap"
    _rewritten(root / "recordings" / "single_joint.mcap", log, change)
    out = tmp_path / "out"
    config = root / "configs" / "single_joint.toml"
    args = ["estimate", str(log), "--config", str(config), "--out", str(out), "--quiet"]
    assert main([*args, "--init", "measurements"]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    skipped = json.loads((out / "summary.json").read_text())["skipped_samples"]
    assert skipped["joints"]["by_reason"] == {"time_jump": 1}
    assert skipped["mocap_arm"]["by_reason"] == {"time_jump": 1, "out_of_bounds": 1}
    assert skipped["command"]["by_reason"] == {"bad_time": 1}
    assert "joints: skipped 1 of" in err


def test_streams_on_different_clocks_are_one_line_not_an_allocation():
    from estimator.errors import LogError
    from estimator.io.logs.measurements import BadSampleCounts, Measurement
    from estimator.knots import knot_grid

    def stream(name, t0_ns):
        t = t0_ns + np.arange(10) * 2_000_000
        values = np.zeros((10, 1, 3))
        return Measurement(
            name,
            "markers",
            "/m",
            "site",
            ("s",),
            ("px", "py", "pz"),
            t,
            t,
            values,
            BadSampleCounts(),
        )

    with pytest.raises(LogError, match=r"sim_clock 0\.000.*wall_clock .*different clocks"):
        knot_grid(
            {"sim_clock": stream("sim_clock", 0), "wall_clock": stream("wall_clock", 1 << 60)},
            0.002,
        )


def test_a_joint_name_with_damaged_bytes_is_undecodable_not_a_missing_joint(robot, tmp_path):
    _, config = robot
    topic, k = "/joint_states", 7
    v = rl.value(topic, k)
    names = ["hip_joint", "kn\x00e_joint", "extra"]  # the knee's name hit by damage
    fields = rl.joint_state(
        rl.sample_stamp(topic, k),
        names,
        [v["q"][0], v["q"][1], 0.5],
        [v["qd"][0], v["qd"][1], 0.0],
        [v["tau"][0], v["tau"][1], 0.0],
    )
    bad = rl.Msg(topic, rl.SAMPLE_TOPICS[topic][0], rl.sample_log_time(topic, k), fields)
    _, log = _read(tmp_path, config, _with({(topic, k): bad}))
    joints = log.measurements["joints"]
    assert joints.bad.undecodable == 1 and joints.bad.total == 1
    assert np.isfinite(joints.values).all()  # no sample with the knee missing


def test_an_array_length_damaged_to_zero_is_undecodable_not_a_missing_field(robot, tmp_path):
    """Damage that shortens an array leaves its values' bytes unread: the message is flagged
    (`undecodable`), not read as a JointState without velocities."""
    _, config = robot
    topic, k = "/joint_states", 7
    msgs = _with({})
    path = tmp_path / "log.mcap"
    rl.write_mcap(path, msgs, compression="none", enable_crcs=False)
    v = rl.value(topic, k)
    position = np.array([v["q"][1], 0.5, v["q"][0]], dtype="<f8").tobytes()  # as sample_message
    velocity = np.array([v["qd"][1], 0.0, v["qd"][0]], dtype="<f8").tobytes()
    data = path.read_bytes()
    clean = read_log(path, config).measurements["joints"]
    count = data.index(position) + len(position)  # velocity's element count follows position
    assert data[count : count + 4] == (3).to_bytes(4, "little") and velocity in data
    path.write_bytes(data[:count] + bytes(4) + data[count + 4 :])
    joints = read_log(path, config).measurements["joints"]
    assert joints.bad.undecodable == 1 and joints.bad.total == 1
    assert len(joints.t_ns) == len(clean.t_ns) - 1
