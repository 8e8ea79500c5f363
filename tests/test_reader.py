"""The file reader: exact arrays for every message type, time bases, bad input, truncation."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import ros2_logs as rl
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter

from estimator.config import load_config
from estimator.errors import LogError, MissingTopicError
from estimator.io.logs import read_log, resample, time_grid
from estimator.io.logs import ros2_types as t
from estimator.io.logs.source import log_time_span

DURATION = 0.5
COUNTS = rl.sample_counts(DURATION)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """(folder, log path, config) of the sample recording."""
    folder = tmp_path_factory.mktemp("sample")
    config = load_config(rl.write_robot(folder))
    path = folder / "sample.mcap"
    rl.write_mcap(path, rl.sample_recording(DURATION))
    return folder, path, config


@pytest.fixture(scope="module")
def sample_log(sample):
    _, path, config = sample
    return read_log(path, config)


def _pose(v, offset=0.0):
    return np.concatenate([v["pos"] + offset, v["quat"]])


# stream → (topic, expected (E, K) values of message k, time of message k)
EXPECTED = {
    "mocap_torso": ("/mocap/torso", lambda v: [_pose(v)], "header"),
    "tf_torso": ("/tf", lambda v: [_pose(v)], "header"),
    "tf_shin": ("/tf", lambda v: [_pose(v, 1.0)], "header"),
    "rigid": ("/mocap/rigid_bodies", lambda v: [_pose(v), _pose(v, 1.0)], "header"),
    "markers": ("/mocap/markers", lambda v: [v["pos"], v["pos"] + 2.0], "header"),
    "imu": ("/imu", lambda v: [np.concatenate([v["quat"], v["gyro"], v["accel"]])], "header"),
    "joints": (
        "/joint_states",
        lambda v: np.stack([v["q"], v["qd"], v["tau"]], axis=1)[::-1],  # config: knee, hip
        "header",
    ),
    "command": ("/joint_commands", lambda v: v["tau"][:, None], "log"),
    "trajectory": ("/joint_trajectory", lambda v: v["tau"][::-1, None], "header+1ms"),
    "foot_ft": ("/ft/foot", lambda v: [np.concatenate([v["force"], v["torque"]])], "header"),
}


def _expected(stream: str, skip: set[int] = frozenset()):
    topic, values, clock = EXPECTED[stream]
    ks = [k for k in range(COUNTS[topic]) if k not in skip]
    if clock == "log":
        times = [rl.sample_log_time(topic, k) for k in ks]
    else:
        extra = 1_000_000 if clock == "header+1ms" else 0
        times = [rl.sample_stamp(topic, k) + extra for k in ks]
    return np.array(times), np.array([np.asarray(values(rl.value(topic, k))) for k in ks])


@pytest.mark.parametrize("stream", list(EXPECTED))
def test_every_message_type_round_trips_exactly(sample_log, stream):
    m = sample_log.measurements[stream]
    t_ns, values = _expected(stream)
    assert m.t_ns.dtype == np.int64
    np.testing.assert_array_equal(m.t_ns, t_ns)
    np.testing.assert_array_equal(m.values, values)
    assert m.bad.total == 0
    assert sample_log.warnings == () and not sample_log.truncated


def test_measurement_layout_names_elements_and_components(sample_log):
    joints = sample_log.measurements["joints"]
    assert (joints.element_type, joints.elements) == ("joint", ("knee", "hip"))
    assert joints.components == ("position", "velocity", "effort")
    np.testing.assert_array_equal(joints.component("position")[0], [-0.2, 0.1])
    np.testing.assert_array_equal(joints.element("hip")[0], [0.1, 1.0, 0.0])
    imu = sample_log.measurements["imu"]
    assert imu.components[:4] == ("qw", "qx", "qy", "qz") and imu.mask.all()
    command = sample_log.measurements["command"]
    np.testing.assert_array_equal(command.log_time_ns, command.t_ns)


def test_topic_statistics(sample_log):
    imu = sample_log.topics["/imu"]
    assert (imu.msg_type, imu.count) == (t.IMU, COUNTS["/imu"])
    assert imu.clock_offset_ns == -500_000  # stamps lead log times by the latency
    stamps = np.array([rl.sample_stamp("/imu", k) for k in range(COUNTS["/imu"])])
    assert imu.rate_hz == pytest.approx(1e9 / np.median(np.diff(stamps)))
    gap, _ = imu.largest_gap
    assert gap == np.diff([rl.sample_log_time("/imu", k) for k in range(COUNTS["/imu"])]).max()
    assert sample_log.topics["/joint_commands"].clock_offset_ns is None  # no header


def test_joint_state_in_any_order_with_any_subset(tmp_path):
    config = load_config(rl.write_robot(tmp_path))
    s = rl.T0
    msgs = [
        rl.Msg("/joint_states", t.JOINT_STATE, s, rl.joint_state(s, ["hip_joint"], [0.5])),
        rl.Msg(
            "/joint_states",
            t.JOINT_STATE,
            s + 1,
            rl.joint_state(s + 1, ["x", "knee_joint", "hip_joint"], [9, 1.5, 2.5], [], [7, 8, 9]),
        ),
    ]
    rl.write_mcap(tmp_path / "j.mcap", msgs)
    joints = read_log(tmp_path / "j.mcap", config, require=False).measurements["joints"]
    nan = np.nan
    expected = [
        [[nan, nan, nan], [0.5, nan, nan]],  # knee missing; no velocity/effort
        [[1.5, nan, 8.0], [2.5, nan, 9.0]],  # no velocity
    ]
    np.testing.assert_array_equal(joints.values, expected)
    np.testing.assert_array_equal(joints.mask, ~np.isnan(expected))
    assert joints.bad.total == 0


def test_occluded_markers_are_missing_not_bad(tmp_path):
    """A frame without one marker keeps the visible markers; NaN marks the occluded one."""
    config = load_config(rl.write_robot(tmp_path))
    s = rl.T0
    both = [(rl.USE_INDEX, 7, "", (1, 2, 3)), (rl.USE_NAME, 0, "knee", (4, 5, 6))]
    knee_only = [(rl.USE_NAME, 0, "knee", (7, 8, 9))]
    msgs = [
        rl.Msg("/mocap/markers", t.MARKERS, s, rl.markers(s, both)),
        rl.Msg("/mocap/markers", t.MARKERS, s + 1, rl.markers(s + 1, knee_only)),
    ]
    rl.write_mcap(tmp_path / "m.mcap", msgs)
    markers = read_log(tmp_path / "m.mcap", config, require=False).measurements["markers"]
    nan = np.nan
    np.testing.assert_array_equal(
        markers.values, [[[1, 2, 3], [4, 5, 6]], [[nan, nan, nan], [7, 8, 9]]]
    )
    assert markers.bad.total == 0


def test_log_time_stamps_and_per_topic_time_offsets(sample, tmp_path):
    _, path, _ = sample
    text = rl.SAMPLE_CONFIG.replace(
        'topic = "/imu"\n', 'topic = "/imu"\nstamp = "log"\ntime_offset_ns = -2_000_000\n'
    ).replace('topic = "/mocap/torso"\n', 'topic = "/mocap/torso"\ntime_offset_ns = 7\n')
    config = load_config(rl.write_robot(tmp_path, text))
    log = read_log(path, config)
    imu, mocap = log.measurements["imu"], log.measurements["mocap_torso"]
    log_times = [rl.sample_log_time("/imu", k) - 2_000_000 for k in range(COUNTS["/imu"])]
    np.testing.assert_array_equal(imu.t_ns, log_times)
    np.testing.assert_array_equal(mocap.t_ns, _expected("mocap_torso")[0] + 7)


def _line(t0: int, t_ns: np.ndarray) -> np.ndarray:
    return 0.25 + 3.0 * (t_ns - t0) / 1e9


def test_multi_rate_streams_align_on_one_grid(tmp_path):
    """200 Hz mocap, 500 Hz IMU and 100 Hz commands with jitter, onto a 100 Hz grid."""
    config = load_config(rl.write_robot(tmp_path))
    msgs = []
    for k in range(100):  # mocap 200 Hz; x = line(t); one dropout at k = 50..53
        s = rl.T0 + k * 5_000_000 + rl.jitter_ns(k)
        if not 50 <= k <= 53:
            pos = [_line(rl.T0, np.array(s)), 0, 1]
            msgs.append(
                rl.Msg("/mocap/torso", t.POSE_STAMPED, s, rl.pose_stamped(s, pos, [1, 0, 0, 0]))
            )
    for k in range(250):  # imu 500 Hz, header stamps 1 ms late: corrected by time_offset_ns
        s = rl.T0 + k * 2_000_000 + rl.jitter_ns(k + 3) + 1_000_000
        gyro = [_line(rl.T0, np.array(s - 1_000_000)), 0, 0]
        msgs.append(rl.Msg("/imu", t.IMU, s, rl.imu(s, gyro, [0, 0, 9.81])))
    for k in range(50):  # commands 100 Hz, held until the next
        s = rl.T0 + k * 10_000_000 + 400_000
        msgs.append(
            rl.Msg("/joint_commands", t.FLOAT64_MULTI_ARRAY, s, rl.float64_multi_array([k, -k]))
        )
    msgs.sort(key=lambda m: m.log_time_ns)
    rl.write_mcap(tmp_path / "multi.mcap", msgs)
    text = rl.SAMPLE_CONFIG.replace(
        'topic = "/imu"\n', 'topic = "/imu"\ntime_offset_ns = -1_000_000\n'
    )
    config = load_config(rl.write_robot(tmp_path, text))
    log = read_log(tmp_path / "multi.mcap", config, require=False)
    streams = {k: log.measurements[k] for k in ("mocap_torso", "imu", "command")}
    grid = time_grid(streams.values(), rate_hz=100.0)
    assert grid[0] == max(m.t_ns[0] for m in streams.values())
    assert np.all(np.diff(grid) == 10_000_000)

    mocap = resample(streams["mocap_torso"], grid, max_gap_ns=8_000_000)
    imu = resample(streams["imu"], grid, max_gap_ns=8_000_000)
    command = resample(streams["command"], grid, max_gap_ns=15_000_000)
    in_dropout = (grid > rl.T0 + 49 * 5_000_000 + 50_000) & (grid < rl.T0 + 54 * 5_000_000 - 50_000)
    assert in_dropout.sum() == 2
    np.testing.assert_allclose(
        mocap[~in_dropout, 0, 0], _line(rl.T0, grid[~in_dropout]), atol=1e-12
    )
    assert np.isnan(mocap[in_dropout]).all()
    np.testing.assert_allclose(mocap[~in_dropout, 0, 3:], [[1, 0, 0, 0]] * (~in_dropout).sum())
    np.testing.assert_allclose(imu[:, 0, 4], _line(rl.T0, grid), atol=1e-12)
    assert np.isnan(imu[:, 0, :4]).all()  # the IMU reports no orientation
    k_held = (grid - rl.T0 - 400_000) // 10_000_000
    np.testing.assert_array_equal(command[:, :, 0], np.stack([k_held, -k_held], axis=1))


def test_quaternions_interpolate_on_the_short_arc(tmp_path):
    config = load_config(rl.write_robot(tmp_path))
    q0 = np.array([np.cos(0.1), 0, 0, np.sin(0.1)])
    q1 = -np.array([np.cos(0.2), 0, 0, np.sin(0.2)])  # the same rotation sign-flipped
    msgs = [
        rl.Msg(
            "/mocap/torso",
            t.POSE_STAMPED,
            rl.T0 + i * 10,
            rl.pose_stamped(rl.T0 + i * 10, [0, 0, 0], q),
        )
        for i, q in enumerate([q0, q1])
    ]
    rl.write_mcap(tmp_path / "q.mcap", msgs)
    m = read_log(tmp_path / "q.mcap", config, require=False).measurements["mocap_torso"]
    mid = resample(m, np.array([rl.T0 + 5]), max_gap_ns=100)[0, 0, 3:]
    np.testing.assert_allclose(mid, [np.cos(0.15), 0, 0, np.sin(0.15)], atol=1e-3)
    assert np.linalg.norm(mid) == pytest.approx(1.0)


def test_imu_and_wrench_axes_are_rotated_into_the_site_frame(tmp_path):
    # sensor axes turned 90° about z in the site frame: sensor x = site y
    q_site_sensor = [float(np.cos(np.pi / 4)), 0.0, 0.0, float(np.sin(np.pi / 4))]
    text = rl.SAMPLE_CONFIG.replace(
        'site = "imu"\n', f'site = "imu"\nquat_site_sensor = {q_site_sensor}\n'
    ).replace('site = "foot_ft"\n', f'site = "foot_ft"\nquat_site_sensor = {q_site_sensor}\n')
    config = load_config(rl.write_robot(tmp_path, text))
    s = rl.T0
    msgs = [
        rl.Msg("/imu", t.IMU, s, rl.imu(s, [1, 0, 0], [0, 2, 0], q_site_sensor)),
        rl.Msg("/imu", t.IMU, s + 1, rl.imu(s + 1, [0, 0, 3], [0, 0, 9.81], None)),
        rl.Msg("/ft/foot", t.WRENCH_STAMPED, s, rl.wrench_stamped(s, [1, 0, 0], [0, 1, 0])),
    ]
    rl.write_mcap(tmp_path / "rot.mcap", msgs)
    log = read_log(tmp_path / "rot.mcap", config, require=False)
    imu, ft = log.measurements["imu"].values[:, 0], log.measurements["foot_ft"].values[0, 0]
    # the sensor's orientation is the site's rotation: the site frame is level
    np.testing.assert_allclose(imu[0, :4], [1, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(imu[0, 4:], [0, 1, 0, -2, 0, 0], atol=1e-15)
    assert np.isnan(imu[1, :4]).all()  # no orientation (covariance[0] = -1)
    np.testing.assert_allclose(imu[1, 4:], [0, 0, 3, 0, 0, 9.81], atol=1e-15)
    np.testing.assert_allclose(ft, [0, 1, 0, -1, 0, 0], atol=1e-15)


def test_bad_samples_are_counted_per_stream_and_topic_and_skipped(tmp_path):
    config = load_config(rl.write_robot(tmp_path))
    rl.write_mcap(tmp_path / "bad.mcap", rl.bad_sample_recording(DURATION))
    log = read_log(tmp_path / "bad.mcap", config)
    for name, m in log.measurements.items():
        assert m.bad.as_dict() == {
            reason: rl.BAD_STREAM_COUNTS.get(name, {}).get(reason, 0) for reason in m.bad.as_dict()
        }, name
        t_ns, values = _expected(name, rl.BAD_SKIPPED.get(name, set()))
        np.testing.assert_array_equal(m.t_ns, t_ns)
        if name != "joints":  # message 6 of /joint_states has a NaN in an unmapped joint
            np.testing.assert_array_equal(m.values, values)
    for topic, stats in log.topics.items():
        expected = rl.BAD_TOPIC_COUNTS.get(topic, {})
        assert {k: v for k, v in stats.bad.as_dict().items() if v} == expected, topic


def test_undecodable_and_unknown_types_are_counted(tmp_path):
    text = (
        rl.SAMPLE_CONFIG
        + '[streams.imu2]\ntype = "imu"\ntopic = "/mocap/torso"\nsite = "imu"\nrequired = false\n'
    )
    config = load_config(rl.write_robot(tmp_path, text))
    msgs = rl.sample_recording(DURATION)
    k = next(i for i, m in enumerate(msgs) if m.topic == "/joint_states")
    fields = dict(msgs[k].fields, name=["knee_joint", "CORRUPT", "hip_joint"])
    msgs[k] = rl.Msg(msgs[k].topic, msgs[k].msg_type, msgs[k].log_time_ns, fields)
    data = rl.corrupt_string_length(rl.mcap_bytes(msgs, compression="none"), "CORRUPT")
    (tmp_path / "c.mcap").write_bytes(data)
    log = read_log(tmp_path / "c.mcap", config)
    assert log.measurements["joints"].bad.undecodable == 1
    assert len(log.measurements["joints"]) == COUNTS["/joint_states"] - 1
    assert log.topics["/joint_states"].bad.undecodable == 1
    assert log.measurements["imu2"].bad.unknown_type == COUNTS["/mocap/torso"]
    assert len(log.measurements["imu2"]) == 0


def test_messages_without_a_ros2_schema_are_unknown_types(tmp_path):
    """A JSON channel (a non-ROS tool's MCAP) is counted, per topic and per stream, not read."""
    text = rl.SAMPLE_CONFIG + '[streams.j]\ntype = "imu"\ntopic = "/json"\nsite = "imu"\n'
    config = load_config(rl.write_robot(tmp_path, text))
    with (tmp_path / "json.mcap").open("wb") as f:
        writer = McapWriter(f)
        writer.start(profile="", library="test")
        schema = writer.register_schema("Imu", "jsonschema", b"{}")
        channel = writer.register_channel("/json", "json", schema)
        for k in range(3):
            writer.add_message(channel, log_time=rl.T0 + k, publish_time=rl.T0 + k, data=b"{}")
        writer.finish()
    log = read_log(tmp_path / "json.mcap", config, require=False, decode_all=True)
    assert log.topics["/json"].msg_type == "Imu"
    assert log.topics["/json"].bad.unknown_type == 3
    assert log.measurements["j"].bad.unknown_type == 3 and len(log.measurements["j"]) == 0


def test_missing_required_topic_is_one_clear_error(sample, tmp_path):
    _, path, _ = sample
    text = rl.SAMPLE_CONFIG.replace('topic = "/imu"', 'topic = "/imu_raw"')
    config = load_config(rl.write_robot(tmp_path, text))
    with pytest.raises(MissingTopicError) as err:
        read_log(path, config)
    message = str(err.value)
    assert "required stream 'imu': topic '/imu_raw' is not in the log" in message
    assert "/ft/foot, /imu, /joint_commands" in message
    optional = text.replace('site = "imu"\n', 'site = "imu"\nrequired = false\n')
    log = read_log(path, load_config(rl.write_robot(tmp_path, optional)))
    assert len(log.measurements["imu"]) == 0 and log.measurements["imu"].values.shape == (0, 1, 10)


def test_required_stream_without_usable_samples_says_why(sample, tmp_path):
    _, path, _ = sample
    text = rl.SAMPLE_CONFIG.replace('topic = "/imu"', 'topic = "/mocap/torso"')
    config = load_config(rl.write_robot(tmp_path, text))
    with pytest.raises(
        MissingTopicError,
        match=r"'imu': topic '/mocap/torso' has 100 messages "
        r"\(geometry_msgs/msg/PoseStamped\) but no usable sample \(unknown_type=100\)",
    ):
        read_log(path, config)


def _chunk_ends(data: bytes) -> list[int]:
    import io

    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    return sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_truncated_file_returns_everything_before_the_cut(tmp_path, compression):
    config = load_config(rl.write_robot(tmp_path))
    msgs = rl.sample_recording(DURATION)
    data = rl.mcap_bytes(msgs, chunk_size=1, compression=compression)  # a chunk per message
    ends = _chunk_ends(data)
    assert len(ends) == len(msgs)
    for cut in [
        40,
        ends[0] - 1,
        ends[0],
        ends[100] + 5,
        ends[len(ends) // 2] + 17,
        ends[-1],
        len(data) - 1,
    ]:
        path = tmp_path / f"cut_{cut}.mcap"
        path.write_bytes(data[:cut])
        log = read_log(path, config, require=False)
        assert log.truncated and len(log.warnings) == 1
        assert "truncated or damaged after byte" in log.warnings[0]
        n = sum(1 for e in ends if e <= cut)  # messages whose chunk is complete
        rl.write_mcap(tmp_path / "prefix.mcap", msgs[:n])
        prefix = read_log(tmp_path / "prefix.mcap", config, require=False)
        for name, m in log.measurements.items():
            np.testing.assert_array_equal(m.t_ns, prefix.measurements[name].t_ns)
            np.testing.assert_array_equal(m.values, prefix.measurements[name].values)
        assert sum(len(m) for m in log.measurements.values()) == sum(
            len(m) for m in prefix.measurements.values()
        )


def test_truncated_default_chunked_file_keeps_complete_chunks(sample, tmp_path):
    _, path, config = sample
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    log = read_log(cut, config, require=False)
    assert log.truncated and f"of {len(data) // 2} (" in log.warnings[0]
    assert all(len(m) == 0 for m in log.measurements.values())  # one 1 MiB chunk, cut in half


@pytest.mark.parametrize("split", [True, False])
def test_rosbag2_folder_written_by_rosbags_reads_into_the_same_arrays(
    sample, sample_log, tmp_path, split
):
    _, _, config = sample
    msgs = rl.sample_recording(DURATION)
    folder = rl.write_rosbag2(tmp_path / "bag", msgs, split_at=len(msgs) // 2 if split else None)
    files = sorted(p.name for p in folder.glob("*.mcap"))
    assert files == (["bag_0.mcap", "bag_1.mcap"] if split else ["bag_0.mcap"])
    log = read_log(folder, config)
    for name, m in log.measurements.items():
        np.testing.assert_array_equal(m.t_ns, sample_log.measurements[name].t_ns)
        np.testing.assert_array_equal(m.values, sample_log.measurements[name].values)
        np.testing.assert_array_equal(m.log_time_ns, sample_log.measurements[name].log_time_ns)
    assert log.warnings == ()
    (folder / "metadata.yaml").unlink()  # a recorder that crashed never wrote it
    again = read_log(folder, config)
    np.testing.assert_array_equal(
        again.measurements["imu"].values, sample_log.measurements["imu"].values
    )


def test_rosbag2_folder_with_a_missing_split_file_warns(sample, tmp_path):
    _, _, config = sample
    msgs = rl.sample_recording(DURATION)
    folder = rl.write_rosbag2(tmp_path / "bag", msgs, split_at=len(msgs) // 2)
    (folder / "bag_1.mcap").unlink()
    log = read_log(folder, config)
    assert log.truncated and "bag_1.mcap: listed in metadata.yaml but missing" in log.warnings[0]
    n_imu = sum(1 for m in msgs[: len(msgs) // 2] if m.topic == "/imu")
    assert len(log.measurements["imu"]) == n_imu


def test_paths_that_are_not_logs(tmp_path):
    with pytest.raises(LogError, match="no such file or folder"):
        read_log(tmp_path / "absent.mcap")
    (tmp_path / "notes.txt").write_text("hello world")
    with pytest.raises(LogError, match=r"notes.txt: not an MCAP file"):
        read_log(tmp_path / "notes.txt")
    bag = tmp_path / "sqlite_bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n"
        "  storage_identifier: sqlite3\n"
        "  relative_file_paths: [a.db3]\n"
    )
    with pytest.raises(LogError, match="rosbag2 storage 'sqlite3' is not supported"):
        read_log(bag)
    shutil.rmtree(bag)
    bag.mkdir()
    with pytest.raises(LogError, match="not a rosbag2 folder"):
        read_log(bag)


def test_reading_without_config_gives_topic_statistics(sample):
    _, path, _ = sample
    log = read_log(path)
    assert log.measurements == {}
    assert sorted(log.topics) == sorted(rl.SAMPLE_TOPICS)
    assert {k: s.count for k, s in log.topics.items()} == COUNTS
    assert all(s.decoded for s in log.topics.values())


def test_reading_with_a_config_decodes_only_its_topics(sample, tmp_path):
    _, path, _ = sample
    text = rl.SAMPLE_CONFIG.split("[streams.tf_torso]")[0]
    log = read_log(path, load_config(rl.write_robot(tmp_path, text)))
    assert list(log.topics) == ["/mocap/torso"]
    assert Path(log.source) == path


@pytest.mark.parametrize("cut", [False, True])
def test_a_time_slice_reads_the_messages_received_within_it(tmp_path, cut):
    """log_time=(a, b): exactly the samples received in [a, b), the same arrays as the whole
    read's there — from the chunk index where the file has one (small chunks: most are not
    read), by reading it through where it has none (cut: no summary)."""
    config = load_config(rl.write_robot(tmp_path))
    data = rl.mcap_bytes(rl.sample_recording(DURATION), chunk_size=2000)
    path = tmp_path / "log.mcap"
    path.write_bytes(data[: len(data) - 100] if cut else data)
    whole = read_log(path, config, require=False)
    first, last = log_time_span(path)
    received = np.concatenate([m.log_time_ns for m in whole.measurements.values()])
    assert first <= received.min() and received.max() <= last
    a, b = first + (last - first) // 3, first + (last - first) // 2
    part = read_log(path, config, log_time=(a, b), require=False)
    for name, m in whole.measurements.items():
        inside = (m.log_time_ns >= a) & (m.log_time_ns < b)
        got = part.measurements[name]
        assert inside.any() and len(got) == inside.sum(), name
        np.testing.assert_array_equal(got.t_ns, m.t_ns[inside])
        np.testing.assert_array_equal(got.values, m.values[inside])


def test_a_stream_cannot_be_sliced(tmp_path):
    """A FIFO is read once: a time slice of it is one clear error."""
    fifo = tmp_path / "live.mcap"
    os.mkfifo(fifo)
    with pytest.raises(LogError, match="a time slice needs a file or folder"):
        read_log(fifo, log_time=(0, 1))
