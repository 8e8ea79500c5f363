"""`physfuse inspect` on a sample recording, a truncated copy and a log with bad samples."""

from __future__ import annotations

import json

import pytest
import ros2_logs as rl

from estimator.cli import main
from estimator.io.logs import BadSampleCounts

DURATION = 0.5
COUNTS = rl.sample_counts(DURATION)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("inspect")
    config = rl.write_robot(folder)
    log = folder / "sample.mcap"
    rl.write_mcap(log, rl.sample_recording(DURATION), chunk_size=4096)
    bad = folder / "bad.mcap"
    rl.write_mcap(bad, rl.bad_sample_recording(DURATION))
    return folder, config, log, bad


def _run(capsys, *argv):
    code = main(["inspect", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def _row(out: str, topic: str) -> list[str]:
    (line,) = [line for line in out.splitlines() if line.startswith(topic + " ")]
    return line.split()


def test_sample_recording_is_reported_topic_by_topic(files, capsys, tmp_path):
    _, config, log, _ = files
    report = tmp_path / "report.json"
    code, out, err = _run(capsys, log, "--config", config, "--json", report)
    assert (code, err) == (0, "")
    assert f"9 topics, {sum(COUNTS.values())} messages" in out
    for topic, (msg_type, _, latency) in rl.SAMPLE_TOPICS.items():
        row = _row(out, topic)
        assert row[1:3] == [msg_type, str(COUNTS[topic])]
        offset = "-" if topic == "/joint_commands" else f"{-latency / 1e6:.2f}"
        assert row[-2:] == [offset, "-"]  # stamp − log time, no bad samples
    assert "from -3.00 ms (/mocap/markers) to -0.10 ms (/joint_trajectory), 2.90 ms apart" in out
    assert "WARNING" not in out and "MISSING" not in out
    assert "found              joint 'knee_joint' in /joint_states" in out
    assert "found              model actuator 'knee_motor'" in out
    data = json.loads(report.read_text())
    assert {t["topic"]: t["count"] for t in data["topics"]} == COUNTS
    assert data["streams"]["imu"] == {
        "samples": COUNTS["/imu"],
        "bad": dict.fromkeys(BadSampleCounts.reasons(), 0),
    }
    assert all(c["found"] for c in data["checklist"]) and not data["truncated"]
    imu = next(t for t in data["topics"] if t["topic"] == "/imu")
    assert imu["clock_offset_ns"] == -500_000 and imu["rate_hz"] == pytest.approx(500, rel=0.01)


def test_truncated_copy_warns_and_still_reports(files, capsys, tmp_path):
    _, config, log, _ = files
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    code, out, err = _run(capsys, cut, "--config", config, "--json", tmp_path / "r.json")
    assert (code, err) == (0, "")
    (warning,) = [line for line in out.splitlines() if line.startswith("WARNING")]
    assert "cut.mcap: truncated or damaged after byte" in warning
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["truncated"]
    counts = {t["topic"]: t["count"] for t in report["topics"]}
    assert set(counts) == set(COUNTS)
    assert all(0 < counts[k] < COUNTS[k] for k in COUNTS)
    assert int(_row(out, "/imu")[2]) == counts["/imu"]


def test_injected_bad_samples_are_counted_per_topic_and_stream(files, capsys, tmp_path):
    _, config, _, bad = files
    code, out, err = _run(capsys, bad, "--config", config, "--json", tmp_path / "r.json")
    assert (code, err) == (0, "")
    assert _row(out, "/mocap/torso")[-3:] == ["nan=1", "duplicate_time=1", "backwards_time=1"]
    assert _row(out, "/imu")[-1] == "nan=1"
    assert _row(out, "/joint_states")[-2:] == ["nan=1", "wrong_length=1"]
    assert _row(out, "/joint_commands")[-1] == "-"
    (joints,) = [line for line in out.splitlines() if line.startswith("joints ")]
    columns = joints.split()  # stream, type, topic, samples, rate, gap, at, skipped…
    assert columns[3] == str(COUNTS["/joint_states"] - 2)
    assert columns[-2:] == ["wrong_length=1", "unknown_name=1"]
    report = json.loads((tmp_path / "r.json").read_text())
    for stream, expected in rl.BAD_STREAM_COUNTS.items():
        got = {k: v for k, v in report["streams"][stream]["bad"].items() if v}
        assert got == expected, stream
    for topic in report["topics"]:
        got = {k: v for k, v in topic["bad"].items() if v}
        assert got == rl.BAD_TOPIC_COUNTS.get(topic["topic"], {}), topic["topic"]


def test_missing_required_topic_and_names_exit_2_with_one_line(files, capsys):
    folder, _, log, _ = files
    text = (
        rl.SAMPLE_CONFIG.replace('topic = "/imu"', 'topic = "/imu_raw"')
        .replace("knee_joint = ", "knee_jnt = ")
        .replace('child_frame_id = "shin_link"', 'child_frame_id = "foot_link"')
    )
    (folder / "broken.toml").write_text(text)
    code, out, err = _run(capsys, log, "--config", folder / "broken.toml")
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("physfuse inspect: error: ")
    assert "topic /imu_raw (streams.imu.topic) not in the log" in err
    assert (
        "joint 'knee_jnt' in /joint_states (streams.joints.joints.knee_jnt) never in the log" in err
    )
    assert "MISSING            topic /imu_raw  [streams.imu.topic]: not in the log" in out
    # an optional stream's missing frame is listed, not fatal
    assert "missing (optional) TF frame 'foot_link' in /tf  [streams.tf_shin.child_frame_id]" in out
    assert "foot_link" not in err
    assert _row(out, "/imu")[2] == str(COUNTS["/imu"])  # the report still lists every topic


def test_unknown_model_names_are_listed_and_exit_2(files, capsys):
    folder, _, log, _ = files
    (folder / "names.toml").write_text(rl.SAMPLE_CONFIG.replace('body = "shin"', 'body = "calf"'))
    code, out, err = _run(capsys, log, "--config", folder / "names.toml")
    assert code == 2
    assert (
        "model body 'calf'" in err and "not in the model; valid: world, torso, thigh, shin" in err
    )
    assert "MISSING            model body 'calf'  [streams.tf_shin.body]" in out


def test_without_a_config_every_topic_is_reported(files, capsys):
    _, _, log, _ = files
    code, out, err = _run(capsys, log)
    assert (code, err) == (0, "")
    assert all(_row(out, topic)[2] == str(n) for topic, n in COUNTS.items())
    assert "checklist" not in out


def test_bad_arguments_are_one_line_errors(files, capsys, tmp_path):
    _, _, log, _ = files
    (tmp_path / "x.txt").write_text("not a log")
    code, _, err = _run(capsys, tmp_path / "x.txt")
    assert code == 2 and err.startswith("physfuse inspect: error: ") and err.count("\n") == 1
    assert "not an MCAP file" in err
    code, _, err = _run(capsys, log, "--config", tmp_path / "none.toml")
    assert code == 2 and "config file not found" in err


def test_a_dropout_of_one_tf_child_frame_is_reported_per_frame(tmp_path, capsys):
    """/tf goes on at 100 Hz while shin_link is missing from it for 0.2 s: the topic's gap is
    10 ms, the tf_shin stream's 210 ms, at 0.3 s."""
    config = rl.write_robot(tmp_path)
    messages = rl.sample_recording(1.0)
    tf = [msg for msg in messages if msg.topic == "/tf"]
    t0 = tf[0].fields["transforms"][0]["header"]["stamp"]
    for msg in tf:
        stamp = msg.fields["transforms"][0]["header"]["stamp"]
        t = stamp["sec"] - t0["sec"] + (stamp["nanosec"] - t0["nanosec"]) / 1e9
        if 0.305 < t < 0.505:
            msg.fields["transforms"] = [
                tf for tf in msg.fields["transforms"] if tf["child_frame_id"] != "shin_link"
            ]
    log = tmp_path / "dropout.mcap"
    rl.write_mcap(log, messages)
    code, out, _ = _run(capsys, log, "--config", config)
    assert code == 0
    topic = _row(out, "/tf")
    assert float(topic[5]) < 1.0 and float(topic[6]) < 15.0  # span, largest gap in ms
    shin = _row(out, "tf_shin")
    torso = _row(out, "tf_torso")
    assert 205.0 < float(shin[5]) < 215.0 and float(shin[6]) == pytest.approx(0.3, abs=0.011)
    assert float(torso[5]) < 15.0
