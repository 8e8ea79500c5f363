"""The byte-stream reader: a pipe fed in small pieces gives what the file reader gives."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest
import ros2_logs as rl

from estimator.config import load_config
from estimator.errors import LogError, MissingTopicError
from estimator.io.logs import ByteStreamReader, read_log

DURATION = 0.3


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(config, MCAP bytes written a chunk per message, the file reader's Log of them)."""
    folder = tmp_path_factory.mktemp("stream")
    config = load_config(rl.write_robot(folder))
    data = rl.mcap_bytes(rl.sample_recording(DURATION), chunk_size=1)
    (folder / "log.mcap").write_bytes(data)
    return config, data, read_log(folder / "log.mcap", config, require=False)


class _PipeWriter(threading.Thread):
    """Writes bytes into a pipe `piece` bytes at a time; optionally pauses at `pause_at`."""

    def __init__(self, data: bytes, piece: int, pause_at: int | None = None):
        super().__init__(daemon=True)
        self.read_fd, self.write_fd = os.pipe()
        self.data, self.piece, self.pause_at = data, piece, pause_at
        self.resume = threading.Event()
        self.paused = threading.Event()
        self.written = 0

    def run(self) -> None:
        try:
            for at in range(0, len(self.data), self.piece):
                if self.pause_at is not None and at >= self.pause_at and not self.paused.is_set():
                    self.paused.set()
                    self.resume.wait(timeout=20)
                os.write(self.write_fd, self.data[at : at + self.piece])
                self.written = at + self.piece
        except BrokenPipeError:  # the reader stopped reading (a stream it rejected)
            pass
        finally:
            os.close(self.write_fd)


def _assert_same(measurements, expected):
    assert list(measurements) == list(expected)
    for name, m in measurements.items():
        np.testing.assert_array_equal(m.t_ns, expected[name].t_ns)
        np.testing.assert_array_equal(m.log_time_ns, expected[name].log_time_ns)
        np.testing.assert_array_equal(m.values, expected[name].values)
        assert m.bad == expected[name].bad


@pytest.mark.parametrize("buffering", [-1, 0])  # a buffered reader, and raw short reads
def test_pipe_fed_7_bytes_at_a_time_gives_the_file_readers_measurements(recording, buffering):
    config, data, expected = recording
    writer = _PipeWriter(data, piece=7)
    writer.start()
    with os.fdopen(writer.read_fd, "rb", buffering=buffering) as pipe:
        log = ByteStreamReader(pipe, config, require=False).read_all()
    writer.join(timeout=10)
    _assert_same(log.measurements, expected.measurements)
    assert log.warnings == () and not log.truncated
    assert sum(len(m) for m in log.measurements.values()) > 300


def test_samples_arrive_before_the_stream_ends(recording):
    config, data, expected = recording
    writer = _PipeWriter(data, piece=7, pause_at=len(data) // 3)
    writer.start()
    got = []
    with os.fdopen(writer.read_fd, "rb") as pipe:
        reader = ByteStreamReader(pipe, config, require=False)
        for sample in reader.samples():
            if not got:  # the writer is still holding back two thirds of the log
                assert writer.written <= writer.pause_at + 7 < len(data)
                writer.resume.set()
            got.append(sample)
    writer.join(timeout=10)
    assert writer.paused.is_set()
    imu = [s for s in got if s.stream == "imu"]
    np.testing.assert_array_equal([s.t_ns for s in imu], expected.measurements["imu"].t_ns)
    np.testing.assert_array_equal(
        np.stack([s.values for s in imu]), expected.measurements["imu"].values
    )
    assert reader.bad_counts["imu"].total == 0


@pytest.mark.parametrize("fraction", [0.37, 0.81])
def test_a_stream_that_stops_mid_record_ends_cleanly_with_a_warning(recording, tmp_path, fraction):
    config, data, _ = recording
    cut = int(len(data) * fraction)
    writer = _PipeWriter(data[:cut], piece=7)
    writer.start()
    with os.fdopen(writer.read_fd, "rb") as pipe:
        reader = ByteStreamReader(pipe, config, name="robot", require=False)
        samples = list(reader.samples())
    writer.join(timeout=10)
    assert reader.truncated and len(reader.warnings) == 1
    assert reader.warnings[0].startswith("robot: truncated or damaged after byte")
    (tmp_path / "cut.mcap").write_bytes(data[:cut])  # the file reader salvages the same
    from_file = read_log(tmp_path / "cut.mcap", config, require=False)
    assert len(samples) == sum(len(m) for m in from_file.measurements.values()) > 0
    imu = [s.t_ns for s in samples if s.stream == "imu"]
    np.testing.assert_array_equal(imu, from_file.measurements["imu"].t_ns)


def test_required_topic_missing_from_a_stream_raises_when_it_ends(recording):
    config, _, _ = recording
    data = rl.mcap_bytes([m for m in rl.sample_recording(0.1) if m.topic != "/imu"])
    writer = _PipeWriter(data, piece=4096)
    writer.start()
    with os.fdopen(writer.read_fd, "rb") as pipe:
        reader = ByteStreamReader(pipe, config)
        with pytest.raises(MissingTopicError, match="required stream 'imu': topic '/imu'"):
            for _ in reader.samples():
                pass
    writer.join(timeout=10)


def test_a_stream_that_is_not_mcap_is_an_error(recording):
    config, _, _ = recording
    writer = _PipeWriter(b"GET / HTTP/1.1\r\n\r\n", piece=7)
    writer.start()
    with os.fdopen(writer.read_fd, "rb") as pipe, pytest.raises(LogError, match="not an MCAP"):
        ByteStreamReader(pipe, config, name="sock").read_all()
    writer.join(timeout=10)


def test_a_stream_is_read_once(recording):
    config, data, _ = recording
    writer = _PipeWriter(data, piece=65536)
    writer.start()
    with os.fdopen(writer.read_fd, "rb") as pipe:
        reader = ByteStreamReader(pipe, config, require=False)
        reader.read_all()
        with pytest.raises(RuntimeError, match="reads its stream once"):
            next(reader.samples())
    writer.join(timeout=10)
