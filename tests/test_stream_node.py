"""The streaming node end to end on loopback: `physfuse replay` serving a recording over a real
TCP socket, `physfuse stream` estimating it as it arrives, and what a killed, disconnected or
diverging node leaves behind."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from live_nodes import CONFIG, LOG, PHYSFUSE, ROOT, replay, stream, wait_for_size
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from estimator.batch import estimate
from estimator.config import load_config
from estimator.io.live import send
from estimator.io.logs import read_log
from estimator.io.logs.source import RawMessage, open_log
from estimator.io.logs.source import open_stream as open_log_stream
from estimator.io.state_topics import at_times, read_state_topics, trajectory_errors
from estimator.settings import Settings
from estimator.stream import Stream


def _joint_error(path: Path, prefix: str) -> tuple[float, int]:
    """(RMS joint error in degrees against the recording's truth, knots) of one prefix."""
    model = load_config(CONFIG).load_model()
    t, q = read_state_topics(path, prefix).qpos(model)
    tg, qg = read_state_topics(LOG).qpos(model)
    return trajectory_errors(model, q, at_times(tg, qg, t))["joint_deg"], len(t)


@pytest.fixture(scope="module")
def batch_joint_error() -> float:
    config = load_config(CONFIG)
    settings = replace(Settings.from_config(config), fit_softness="none")
    est, _ = estimate(config, read_log(LOG, config).measurements, settings)
    model = config.load_model()
    tg, qg = read_state_topics(LOG).qpos(model)
    return trajectory_errors(model, est.qpos, at_times(tg, qg, est.t_ns))["joint_deg"]


def test_a_recording_replayed_over_tcp_is_estimated_as_it_arrives(tmp_path, batch_joint_error):
    replayer, port = replay(rate=0)
    out, stats = tmp_path / "live.mcap", tmp_path / "stats.json"
    # (the model's softness throughout, as the batch's: a softness fit back before the end
    # would re-solve the whole window there; tests/test_softness_fit.py has the fit)
    node = stream(
        f"tcp://127.0.0.1:{port}",
        out,
        "--stats",
        str(stats),
        "--quiet",
        "--diagnose",
        "--fit-softness",
        "none",
        "--newest",
        "filter",
    )
    _, err = node.communicate(timeout=300)
    replayer.wait(timeout=30)
    assert node.returncode == 0, err
    report = json.loads(stats.read_text())
    # --diagnose: the tip pressing the floor (`diagnose` calls it the contact's model error),
    # each event reported while on and again final, into the file as into the stats
    reported = report["events"]
    assert reported and all(e["target"] == "arm" for e in reported)
    assert [e.get("ongoing", False) for e in reported] == [True, False] * (len(reported) // 2)
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        typed = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/diagnostics/events"])]
    assert [(m.target, m.ongoing) for m in typed] == [
        (e["target"], e.get("ongoing", False)) for e in reported
    ]
    knots = round(3.0 / report["knot_s"])
    # every knot but the two ends published once newest and once smoothed
    assert report["counts"]["knots_newest"] >= knots - 3
    assert report["counts"]["knots_smoothed"] >= knots - 3
    assert len(report["latency_s"]) == report["counts"]["knots_newest"]
    # once the window is incremental an update relinearizes the keys it took in (at most
    # half the lag's, replayed at --rate 0) and the newest 0.04 s, not the whole window (at
    # its first whole solve 320 keys; then 125 each, measured)
    # (the newest knots are the filter's: the smoother's updates run in a process of their own)
    assert len(report["relinearized"]) == len(report["smoother_solve_s"])
    keys = (0.5 * 0.5 + 0.04) / report["knot_s"]
    assert max(report["relinearized"][-5:]) <= keys < max(report["relinearized"])
    newest, n_newest = _joint_error(out, "/estimate")
    smoothed, n_smoothed = _joint_error(out, "/estimate_smoothed")
    # (the filter publishes each key once it is ready, the smoother's first from key 0 on)
    assert n_newest == report["counts"]["knots_newest"] and abs(n_smoothed - n_newest) <= 2
    # the smoothed estimate at 0.5 s lag is as good as the whole log's (1.0× measured)
    assert smoothed <= 1.2 * batch_joint_error, (smoothed, batch_joint_error)
    assert newest <= 2.0 * batch_joint_error, (newest, batch_joint_error)


def test_a_killed_node_leaves_an_mcap_that_reads_back(tmp_path):
    replayer, port = replay(rate=1)
    out = tmp_path / "live.mcap"
    node = stream(f"tcp://127.0.0.1:{port}", out, "--quiet")
    wait_for_size(out, 50_000)
    node.send_signal(signal.SIGKILL)
    node.wait(timeout=30)
    replayer.kill()
    replayer.wait(timeout=30)
    assert node.returncode == -signal.SIGKILL
    model = load_config(CONFIG).load_model()
    t, q = read_state_topics(out, "/estimate").qpos(model)  # (a truncated file: salvaged)
    assert len(t) > 20 and np.all(np.diff(t) > 0) and np.all(np.isfinite(q))


def test_sigterm_smooths_the_window_and_closes_the_file(tmp_path):
    replayer, port = replay(rate=1)
    out = tmp_path / "live.mcap"
    node = stream(f"tcp://127.0.0.1:{port}", out, "--quiet")
    wait_for_size(out, 50_000)
    node.send_signal(signal.SIGTERM)
    node.wait(timeout=60)
    replayer.kill()
    replayer.wait(timeout=30)
    assert node.returncode == 130
    with out.open("rb") as f:  # a whole MCAP: its summary and footer are there
        reader = make_reader(f)
        assert reader.get_summary() is not None
        topics = {channel.topic for _, channel, _ in reader.iter_messages()}
    assert "/estimate/joint_states" in topics and "/estimate_smoothed/joint_states" in topics


def _halves() -> tuple[list[RawMessage], list[RawMessage]]:
    messages = list(open_log(LOG))
    t_mid = (messages[0].log_time_ns + messages[-1].log_time_ns) // 2
    return [m for m in messages if m.log_time_ns < t_mid], [
        m for m in messages if m.log_time_ns >= t_mid
    ]


def test_malformed_bytes_and_a_disconnect_do_not_stop_the_node(tmp_path):
    """Connection 1: the first half of the log with 20 joint messages whose CDR is garbage,
    then garbage bytes and a hang-up; connection 2 (the node reconnects): the second half."""
    first, second = _halves()
    rng = np.random.default_rng(0)
    damaged = [i for i, m in enumerate(first) if m.topic == "/joint_states"][100:120]
    for i in damaged:
        first[i] = first[i]._replace(data=rng.bytes(len(first[i].data)))
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve() -> None:
        with server:
            for part, garbage in ((first, True), (second, False)):
                conn, _ = server.accept()
                with conn, conn.makefile("wb") as out:
                    if garbage:  # records cut off by bytes that are no record
                        writer_bytes = _unfinished(part)
                        out.write(writer_bytes + rng.bytes(300))
                    else:
                        send(part, out)

    threading.Thread(target=serve, daemon=True).start()
    out, stats = tmp_path / "live.mcap", tmp_path / "stats.json"
    node = stream(f"tcp://127.0.0.1:{port}", out, "--stats", str(stats))
    _, err = node.communicate(timeout=300)
    assert node.returncode == 0, err
    assert "reconnecting" in err and err.count(": connected") == 2
    report = json.loads(stats.read_text())
    assert report["bad"]["joints"]["undecodable"] == len(damaged)
    # the estimate runs through both connections, to the end of the log
    model = load_config(CONFIG).load_model()
    t, _ = read_state_topics(out, "/estimate_smoothed").qpos(model)
    assert t[0] - first[0].log_time_ns < 0.1e9
    assert second[-1].log_time_ns - t[-1] < 0.1e9


def _unfinished(messages: list[RawMessage]) -> bytes:
    """The messages as an MCAP stream without its end (a sender that died mid-stream)."""
    import io

    buffer = io.BytesIO()
    send(messages, buffer)
    data = buffer.getvalue()
    return data[: data.rfind(b"\x0f")]  # cut before the DataEnd record (opcode 0x0f)


def test_a_divergence_is_detected_reset_and_reported():
    """The Python API: a window whose solution went NaN is found on the next update, solved
    again from the measurements, and the estimate goes on."""
    config = load_config(CONFIG)
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5)
    messages = list(open_log(LOG))
    updates = []
    for i, raw in enumerate(messages):
        stream.push(raw)
        if i % 200 == 0:
            updates += stream.update()
        if i == len(messages) // 2:
            assert stream.lag is not None and len(stream.lag.qpos)
            stream.lag.qpos[:] = np.nan  # the injected divergence
    updates += stream.close()
    events = [u.event for u in updates if u.event]
    assert len(events) == 1 and "divergence 1." in events[0] and "reset" in events[0]
    assert stream.counts.divergences == 1
    after = updates[[u.event for u in updates].index(events[0]) :]
    assert all(np.all(np.isfinite(u.estimate.qpos[u.smoothed])) for u in after)
    model = config.load_model()
    tg, qg = read_state_topics(LOG).qpos(model)
    t = np.concatenate([u.estimate.t_ns[u.smoothed] for u in updates])
    q = np.concatenate([u.estimate.qpos[u.smoothed] for u in updates])
    assert trajectory_errors(model, q, at_times(tg, qg, t))["joint_deg"] < 0.01


def test_newest_from_the_filter_smoothed_from_the_smoothers_process():
    """`Stream(newest="filter")`: each ready knot published by the EKF step at once, the
    smoother's knots back from its process; a filter state gone NaN restarts the filter from
    the measurements and is reported; the newest knots stay near the truth, the smoothed ones
    as near as the smoother's alone."""
    config = load_config(CONFIG)
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, newest="filter")
    stream.wait_ready()
    messages = list(open_log(LOG))
    updates = []
    for i, raw in enumerate(messages):
        stream.push(raw)
        updates += stream.update()
        if i == len(messages) // 2:
            assert stream.filter is not None and stream.filter.filter is not None
            stream.filter.filter.ekf.x[:] = np.nan  # the injected divergence
    updates += stream.close()
    assert stream.job is not None and stream.job.process.poll() == 0
    newest = [u for u in updates if u.source == "filter"]
    smoothed = [u for u in updates if u.source == "smoother"]
    events = [u.event for u in newest if u.event]
    assert len(events) == 1 and "not finite" in events[0] and "restarted" in events[0]
    assert stream.counts.divergences == 1
    # every key but the few around the restart published newest, each as soon as it was ready
    # (one key per update here: the messages pushed one at a time)
    knots = round(3.0 / stream.h)
    assert knots - 6 <= stream.counts.knots_newest <= knots
    assert all(len(u.newest) == len(u.latency_s) and not u.smoothed for u in newest)
    assert stream.counts.knots_smoothed >= knots - 3
    assert all(not u.newest and not u.latency_s for u in smoothed)
    model = config.load_model()
    tg, qg = read_state_topics(LOG).qpos(model)

    def joint_error(us: list, part: str) -> float:
        t = np.concatenate([u.estimate.t_ns[getattr(u, part)] for u in us])
        q = np.concatenate([u.estimate.qpos[getattr(u, part)] for u in us])
        assert np.all(np.isfinite(q))
        return trajectory_errors(model, q, at_times(tg, qg, t))["joint_deg"]

    assert joint_error(smoothed, "smoothed") < 0.01  # (as the smoother's alone: above)
    assert joint_error(newest, "newest") < 0.02


def test_a_smoother_process_that_dies_leaves_the_newest_estimate_going():
    config = load_config(CONFIG)
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, newest="filter")
    stream.wait_ready()
    messages = list(open_log(LOG))
    for i, raw in enumerate(messages):
        stream.push(raw)
        list(stream.update())
        if i == len(messages) // 3:
            assert stream.job is not None
            stream.job.process.kill()
    list(stream.close())
    lines = [e for e in stream.counts.events if "the smoother stopped" in e]
    assert len(lines) == 1 and "the newest estimate goes on" in lines[0], stream.counts.events
    assert stream.counts.knots_newest >= round(3.0 / stream.h) - 3
    assert 0 < stream.counts.knots_smoothed < stream.counts.knots_newest / 2


def test_a_source_that_is_not_there_is_one_line(tmp_path):
    node = stream("tcp://127.0.0.1:1", tmp_path / "x.mcap", "--reconnect", "0.3", "--quiet")
    _, err = node.communicate(timeout=120)
    assert "no connection for 0.3 s" in err and "Traceback" not in err
    bad = stream("udp://robot:9", tmp_path / "y.mcap")
    _, err = bad.communicate(timeout=120)
    assert bad.returncode == 2 and err.strip().count("\n") == 0
    assert "expected tcp://HOST:PORT" in err


def test_the_docs_python_example_runs(monkeypatch):
    """docs/streaming.md's Python API example, as a user pastes it."""
    page = (ROOT / "docs" / "streaming.md").read_text()
    code = page.split("```python\n")[1].split("```")[0]
    assert "from estimator.stream import Stream" in code
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(code, scope)
    assert scope["stream"].counts.knots_smoothed >= 1490  # 3 s at 2 ms, both ends aside
    assert scope["final"] and len(scope["final"][-1].smoothed) > 0


def test_derivatives_are_reused_only_near_where_they_were_taken():
    from estimator.solver.linearize import Derivatives

    kept = Derivatives(h=0.01, tol_q=1e-4)
    q, v, a = np.zeros(7), np.zeros(6), np.zeros(6)
    F, S = np.ones((3, 6, 6)), np.ones((3, 6, 4))
    kept.put(5, q, v, a, F, S)
    assert (
        kept.get(
            5,
            q + 0.5e-4,
            v + 0.5e-2,
            a + 0.5,
        )
        is not None
    )  # within tol, h, h²
    assert kept.get(5, q + 2e-4, v, a) is None
    assert kept.get(5, q, v + 2e-2, a) is None
    assert kept.get(5, q, v, a + 2.0) is None
    assert kept.get(6, q, v, a) is None
    assert kept.get(5, q * np.nan, v, a) is None
    kept.forget_before(6)
    assert kept.get(5, q, v, a) is None and (kept.reused, kept.computed) == (1, 1)


def test_the_estimate_is_published_as_a_live_mcapstream():
    """--publish tcp://: another program connects and reads the estimate as it is made, with
    physfuse's own byte-stream reader."""
    replayer, port = replay(rate=1)
    node = subprocess.Popen(
        [
            *PHYSFUSE,
            "stream",
            "--config",
            str(CONFIG),
            "--source",
            f"tcp://127.0.0.1:{port}",
            "--publish",
            "tcp://127.0.0.1:0",
            "--quiet",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert node.stderr is not None
    line = node.stderr.readline()  # "physfuse stream: publishing the estimate on tcp://...:N"
    assert "publishing the estimate on tcp://127.0.0.1:" in line, line
    topics = []
    try:
        with socket.create_connection(("127.0.0.1", int(line.rsplit(":", 1)[1]))) as sock:
            for raw in open_log_stream(sock.makefile("rb")):
                topics.append(raw.topic)
                if topics.count("/estimate_smoothed/joint_states") == 5:
                    break
    finally:
        node.terminate()
        node.wait(timeout=60)
        replayer.kill()
        replayer.wait(timeout=30)
    assert topics.count("/estimate/joint_states") >= 5


def test_a_sensor_that_stops_does_not_stop_the_knots():
    """The arm's mocap stops halfway: once it is --stale behind, the encoders alone ready
    the knots, and every knot to the end is estimated."""
    config = load_config(CONFIG)
    settings = replace(Settings.from_config(config), max_iterations=2, fit_softness="none")
    stream = Stream(config, settings, lag_s=0.5, stale_s=0.25)
    messages = list(open_log(LOG, topics=[s.topic for s in config.streams.values()]))
    t_mid = (messages[0].log_time_ns + messages[-1].log_time_ns) // 2
    updates = []
    for i, raw in enumerate(messages):
        if raw.topic == "/mocap/arm/pose" and raw.log_time_ns > t_mid:
            continue
        stream.push(raw)
        if i % 200 == 0:
            updates += stream.update()
    newest_before_close = stream.counts.knots_newest
    updates += stream.close()
    knots = round((messages[-1].log_time_ns - messages[0].log_time_ns) / 1e9 / stream.h)
    # the newest estimate kept up with the encoders, not stuck where the mocap stopped
    assert newest_before_close > 0.9 * knots
    assert stream.counts.knots_smoothed >= knots - 5  # (the two ends, stamps vs log times)


def test_the_live_rerun_recording_reads_back(tmp_path):
    """--rerun FILE.rrd: the recording read back with Rerun's own reader has every body's
    pose at (nearly) every knot, the uncertainty plots, on seconds since the first knot, and
    the --diagnose events."""
    from test_visualize import read_recording

    replayer, port = replay(rate=0)
    rrd = tmp_path / "live.rrd"
    out, stats = tmp_path / "x.mcap", tmp_path / "stats.json"
    node = stream(
        f"tcp://127.0.0.1:{port}",
        out,
        "--rerun",
        str(rrd),
        "--quiet",
        "--diagnose",
        "--stats",
        str(stats),
    )
    _, err = node.communicate(timeout=300)
    replayer.wait(timeout=30)
    assert node.returncode == 0, err
    entities = read_recording(rrd)
    # --diagnose: every report on the timeline, as in --stats
    reports = json.loads(stats.read_text())["events"]
    assert reports and len(entities["/diagnostics/events"].time_ns) == len(reports)
    arm = [e for path, e in entities.items() if path.startswith("/world/model/")]
    assert arm, list(entities)
    times = sorted(set(arm[0].time_ns))
    assert len(times) >= 1490 and times[0] >= 0 and times[-1] < 3.1e9
    assert any(path.startswith("/plots/uncertainty/") for path in entities)


def test_a_rosbag2_folder_being_recorded_is_followed_split_by_split(tmp_path):
    """A recorder writes split 0 piece by piece, closes it, then split 1: the node follows
    the folder and estimates through both."""
    import io

    first, second = _halves()
    folder = tmp_path / "bag"
    folder.mkdir()
    splits = []
    for part in (first, second):
        buffer = io.BytesIO()
        send(part, buffer)
        splits.append(buffer.getvalue())

    def record() -> None:
        for i, data in enumerate(splits):
            with (folder / f"bag_{i}.mcap").open("wb") as f:
                for at in range(0, len(data), 20_000):
                    f.write(data[at : at + 20_000])
                    f.flush()
                    time.sleep(0.01)

    recorder = threading.Thread(target=record, daemon=True)
    recorder.start()
    out, stats = tmp_path / "live.mcap", tmp_path / "stats.json"
    node = stream(str(folder), out, "--stats", str(stats), "--quiet")
    _, err = node.communicate(timeout=300)
    recorder.join(timeout=60)
    assert node.returncode == 0, err
    assert json.loads(stats.read_text())["messages"] == len(first) + len(second)
    model = load_config(CONFIG).load_model()
    t, _ = read_state_topics(out, "/estimate_smoothed").qpos(model)
    assert second[-1].log_time_ns - t[-1] < 0.1e9


def test_a_source_without_the_configs_topics_is_one_line(tmp_path):
    replayer = subprocess.Popen(
        [*PHYSFUSE, "replay", str(LOG), "--to", "-", "--rate", "0", "--topics", "/tf"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
    )
    node = subprocess.run(
        [*PHYSFUSE, "stream", "--config", str(CONFIG), "--source", "-", "--quiet"],
        cwd=ROOT,
        stdin=replayer.stdout,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    replayer.wait(timeout=30)
    assert node.returncode == 2 and node.stderr.count("\n") == 1, node.stderr
    assert "no message on the config's topics (/joint_commands, /joint_states" in node.stderr


def test_streams_on_different_clocks_are_one_error_not_a_hang():
    from estimator.errors import LogError
    from estimator.io.logs.measurements import Sample

    config = load_config(CONFIG)
    stream = Stream(config, Settings.from_config(config), lag_s=0.5)
    stream.push_sample(Sample("joints", 1_000_000_000, 0, np.zeros((1, 3))))
    stream.push_sample(Sample("mocap_arm", 1_000_001_000, 0, np.zeros((1, 7))))
    stream.push_sample(Sample("joints", 1_002_000_000, 0, np.zeros((1, 3))))
    with pytest.raises(LogError, match="different clocks"):  # boot time, then epoch time
        stream.push_sample(Sample("mocap_arm", 1_700_000_000_000_000_000, 0, np.zeros((1, 7))))
