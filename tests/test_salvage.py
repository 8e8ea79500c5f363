"""Damaged logs: every chunk whose CRC holds is read, the rest is reported, nothing raises.

The recording is the sample recording in 4 zstd chunks with CRCs (mcap_ros2's writer). Every
check compares against the original: a message read from a damaged file is identical to the
original's or absent, and what is absent is what `lost` reports.
"""

from __future__ import annotations

import io
import os
import random
import struct
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import ros2_logs as rl
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer as McapWriter

from estimator.config import Config, load_config
from estimator.errors import LogError
from estimator.io.logs import ByteStreamReader, Log, LostData, read_log
from estimator.io.logs.source import LogSource, open_log, open_stream

DURATION = 0.5
CHUNK_SIZE = 64_000  # the sample recording in 4 chunks

Key = tuple[str, int, bytes]  # topic, log time, data: a message's identity


@dataclass(frozen=True)
class Recording:
    folder: Path
    config: Config
    msgs: list[rl.Msg]
    data: bytes
    chunks: list[ChunkIndex]  # in file order
    in_chunk: list[list[Key]]  # the messages of each chunk, in file order
    summary_start: int

    def write(self, name: str, data: bytes) -> Path:
        path = self.folder / name
        path.write_bytes(data)
        return path

    def data_of(self, k: int) -> tuple[int, int]:
        """[start, end) of chunk k's compressed data in the file."""
        c = self.chunks[k]
        start = c.chunk_start_offset + 9 + 40 + len(c.compression)
        return start, c.chunk_start_offset + c.chunk_length

    def without(self, *ks: int) -> list[Key]:
        return [m for k, keys in enumerate(self.in_chunk) if k not in ks for m in keys]


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Recording:
    folder = tmp_path_factory.mktemp("salvage")
    config = load_config(rl.write_robot(folder))
    msgs = rl.sample_recording(DURATION)
    data = rl.mcap_bytes(msgs, chunk_size=CHUNK_SIZE)
    chunks = _chunks(data)
    assert len(chunks) == 4
    in_chunk = [_chunk_keys(data, c) for c in chunks]
    assert sum(map(len, in_chunk)) == len(msgs) and all(in_chunk)
    summary_start = struct.unpack_from("<Q", data, len(data) - 28)[0]  # in the footer
    return Recording(folder, config, msgs, data, chunks, in_chunk, summary_start)


def _chunks(data: bytes) -> list[ChunkIndex]:
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def _chunk_keys(data: bytes, c: ChunkIndex) -> list[Key]:
    """The messages of one chunk, as the mcap package itself reads them."""
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    at = c.chunk_start_offset + 9
    chunk = Chunk.read(ReadDataStream(io.BytesIO(data[at : at + c.chunk_length - 9])))
    return [
        (summary.channels[r.channel_id].topic, r.log_time, r.data)
        for r in breakup_chunk(chunk, validate_crc=True)
        if isinstance(r, Message)
    ]


def _flip(data: bytes, *at: int) -> bytes:
    out = bytearray(data)
    for i in at:
        out[i] ^= 0xFF
    return bytes(out)


def _read(path: Path | str) -> tuple[list[Key], LogSource]:
    source = open_log(path)
    return [(m.topic, m.log_time_ns, m.data) for m in source], source


def _assert_measurements_equal(log: Log, expected: Log) -> None:
    for name, m in log.measurements.items():
        np.testing.assert_array_equal(m.t_ns, expected.measurements[name].t_ns)
        np.testing.assert_array_equal(m.values, expected.measurements[name].values)


def _log_of(rec: Recording, keys: list[Key], name: str) -> Log:
    """read_log of a clean file holding just these messages (what a salvage must equal)."""
    kept = {(topic, t) for topic, t, _ in keys}
    msgs = [m for m in rec.msgs if (m.topic, m.log_time_ns) in kept]
    rl.write_mcap(rec.folder / name, msgs, chunk_size=CHUNK_SIZE)
    return read_log(rec.folder / name, rec.config, require=False)


def _s(rec: Recording, t_ns: int) -> str:
    return f"{(t_ns - rec.chunks[0].message_start_time) / 1e9:.3f} s"


# -- (a) one damaged chunk, summary intact ------------------------------------------------------
def test_a_damaged_chunk_loses_only_its_own_messages(rec):
    start, end = rec.data_of(1)
    path = rec.write("a.mcap", _flip(rec.data, (start + end) // 2))
    got, source = _read(path)
    assert got == rec.without(1)
    c = rec.chunks[1]
    assert source.lost == [
        LostData(
            str(path),
            c.message_start_time,
            c.message_end_time,
            len(rec.in_chunk[1]),
            "damaged chunk (CRC mismatch)",
            c.chunk_start_offset,
        )
    ]
    (warning,) = source.warnings
    assert f"lost {len(rec.in_chunk[1])} messages" in warning
    assert f"between {_s(rec, c.message_start_time)} and {_s(rec, c.message_end_time)}" in warning
    assert not source.truncated

    log = read_log(path, rec.config, require=False)
    assert log.lost == tuple(source.lost) and log.warnings == (warning,)
    _assert_measurements_equal(log, _log_of(rec, rec.without(1), "a_expected.mcap"))


# -- (b) a damaged chunk and a damaged summary: the record-by-record scan -----------------------
@pytest.mark.parametrize("where", ["summary", "footer", "cut footer"])
def test_b_damaged_chunk_with_damaged_summary(rec, where):
    start, end = rec.data_of(1)
    data = _flip(rec.data, (start + end) // 2)
    if where == "summary":
        data = _flip(data, rec.summary_start + 40)
    elif where == "footer":
        data = _flip(data, len(data) - 28)  # the footer's summary start (low byte)
    else:
        data = data[: len(data) - 10]
    path = rec.write("b.mcap", data)
    got, source = _read(path)
    assert got == rec.without(1)
    c = rec.chunks[1]
    lost = [x for x in source.lost if x.reason.startswith("damaged chunk")]
    assert [(x.start_ns, x.end_ns, x.messages, x.at_byte) for x in lost] == [
        (c.message_start_time, c.message_end_time, len(rec.in_chunk[1]), c.chunk_start_offset)
    ]
    assert any(f"lost {len(rec.in_chunk[1])} messages" in w for w in source.warnings)
    if where == "cut footer":
        assert source.truncated and "truncated or damaged after byte" in source.warnings[-1]
    else:
        assert not source.truncated
        assert "MCAP summary unusable" in source.warnings[0]


# -- (c) a chunk's length field destroyed ------------------------------------------------------
@pytest.mark.parametrize("length", [2**63 + 12345, 100, "short by 7"])
def test_c_destroyed_chunk_length(rec, length):
    c = rec.chunks[1]
    out = bytearray(rec.data)
    value = c.chunk_length - 9 - 7 if length == "short by 7" else length
    struct.pack_into("<Q", out, c.chunk_start_offset + 1, value)
    # the summary knows the chunk's length: nothing is lost
    got, source = _read(rec.write("c_indexed.mcap", bytes(out)))
    assert got == rec.without() and source.lost == [] and source.warnings == []
    # without the summary, the scan searches on for the next chunk whose CRC validates
    path = rec.write("c.mcap", _flip(bytes(out), rec.summary_start + 40))
    got, source = _read(path)
    assert got == rec.without(1)
    (lost,) = source.lost
    assert lost.at_byte == c.chunk_start_offset and lost.messages is None
    assert lost.start_ns == rec.in_chunk[0][-1][1]  # after the last message read ...
    assert lost.end_ns == rec.chunks[2].message_start_time  # ... before the next chunk's first
    assert f"unreadable bytes {c.chunk_start_offset}..{rec.chunks[2].chunk_start_offset}" in (
        lost.reason
    )
    assert not source.truncated


@pytest.mark.parametrize("opcode", [0x02, 0x04, 0x07, 0x0E, 0x46, 0x86])
def test_c_chunk_with_a_damaged_opcode_is_read_by_its_crc(rec, opcode):
    """0x06 with one bit flipped: a footer, channel, message index, summary offset, garbage
    or private record; its content is still the chunk its CRC vouches for."""
    out = bytearray(_flip(rec.data, rec.summary_start + 40))  # the record-by-record scan
    out[rec.chunks[1].chunk_start_offset] = opcode
    got, source = _read(rec.write("c_opcode.mcap", bytes(out)))
    assert got == rec.without() and source.lost == []


@pytest.mark.parametrize("summary", ["intact", "damaged"])
def test_c_a_zeroed_crc_among_crcs_is_damage(rec, summary):
    """A writer gives all chunks a CRC or none: a zero CRC field is damage (to the field, or
    with the data after it, as a zeroed run of bytes does)."""
    c = rec.chunks[1]
    out = bytearray(rec.data)
    out[c.chunk_start_offset + 33 : c.chunk_start_offset + 37] = bytes(4)
    if summary == "damaged":
        out = bytearray(_flip(bytes(out), rec.summary_start + 40))
    got, source = _read(rec.write("c_zero_crc.mcap", bytes(out)))
    assert got == rec.without(1)
    lost = [x for x in source.lost if x.reason.startswith("damaged chunk")]
    assert [(x.at_byte, x.messages) for x in lost] == [(c.chunk_start_offset, len(rec.in_chunk[1]))]
    assert "no CRC, while the file's other chunks carry one" in lost[0].reason


# -- (d) a file cut inside a chunk -------------------------------------------------------------
def test_d_file_cut_mid_chunk_keeps_every_chunk_before(rec):
    c = rec.chunks[2]
    cut = c.chunk_start_offset + c.chunk_length // 2
    path = rec.write("d.mcap", rec.data[:cut])
    got, source = _read(path)
    assert got == rec.without(2, 3)
    assert source.truncated
    (warning,) = source.warnings
    assert f"truncated or damaged after byte {c.chunk_start_offset} of {cut}" in warning
    (lost,) = source.lost
    assert (lost.start_ns, lost.end_ns, lost.at_byte) == (
        rec.in_chunk[1][-1][1],
        None,
        c.chunk_start_offset,
    )
    log = read_log(path, rec.config, require=False)
    _assert_measurements_equal(log, _log_of(rec, rec.without(2, 3), "d_expected.mcap"))


def test_d_a_required_topic_lost_to_damage_says_the_log_is_damaged(rec):
    path = rec.write("d_early.mcap", rec.data[: rec.chunks[0].chunk_start_offset + 100])
    with pytest.raises(LogError, match=r"is not in the log .*; the log is damaged \(1 warnings"):
        read_log(path, rec.config)


# -- (e) no damage is ever read as changed values -----------------------------------------------
def _damaged_variants(data: bytes, n: int):
    rng = random.Random(1234)
    for _ in range(n):  # one flipped byte anywhere past the magic
        yield _flip(data, rng.randrange(8, len(data)))
    for _ in range(n // 2):  # a burst of garbage
        at = rng.randrange(8, len(data) - 64)
        yield data[:at] + rng.randbytes(rng.choice([3, 9, 64])) + data[at + 9 :]
    for _ in range(n // 4):  # a garbage length (which reaches gigabytes)
        out = bytearray(data)
        struct.pack_into("<Q", out, rng.randrange(8, len(data) - 8), rng.getrandbits(64))
        yield bytes(out)
    for _ in range(n // 4):  # bytes missing from the middle
        at = rng.randrange(8, len(data) - 100)
        yield data[:at] + data[at + rng.randrange(1, 100) :]


def _is_subsequence(got: list[Key], original: list[Key]) -> bool:
    it = iter(original)
    return all(any(m == o for o in it) for m in got)


def test_e_damage_is_never_read_as_changed_values(rec, tmp_path):
    original = rec.without()
    lost_somewhere = 0
    for i, data in enumerate(_damaged_variants(rec.data, 120)):
        path = tmp_path / f"e{i}.mcap"
        path.write_bytes(data)
        got, source = _read(path)  # never raises: the magic is intact
        assert _is_subsequence(got, original), i
        if len(got) < len(original):
            lost_somewhere += 1
            assert source.lost, i  # what is missing is reported
    assert lost_somewhere > 20
    for k in range(4):  # a flipped byte inside a chunk loses that chunk only
        start, end = rec.data_of(k)
        for at in (start, (start + end) // 2, end - 1):
            path = tmp_path / f"e_chunk{k}_{at}.mcap"
            path.write_bytes(_flip(rec.data, at))
            assert _read(path)[0] == rec.without(k)


def test_e_decoded_values_of_a_damaged_file_are_the_originals(rec, tmp_path):
    original = read_log(rec.write("e_original.mcap", rec.data), rec.config, require=False)
    rows = {
        name: {int(t): v for t, v in zip(m.t_ns, m.values, strict=True)}
        for name, m in original.measurements.items()
    }
    rng = random.Random(99)
    for i in range(12):
        path = tmp_path / f"e_decoded{i}.mcap"
        path.write_bytes(_flip(rec.data, rng.randrange(8, len(rec.data))))
        log = read_log(path, rec.config, require=False)
        for name, m in log.measurements.items():
            for t, v in zip(m.t_ns, m.values, strict=True):
                np.testing.assert_array_equal(v, rows[name][int(t)])


def test_e_damaged_streams_raise_only_log_error(rec):
    original = rec.without()
    variants = [b"", b"\x89MCAP", rec.data[:8], _flip(rec.data, 0)]
    for data in [*variants, *_damaged_variants(rec.data, 40)]:
        for piece in (7, 4096):
            pipe = _Feeder(data, piece)
            with os.fdopen(pipe.read_fd, "rb") as f:
                source = open_stream(f, "pipe")
                try:
                    got = [(m.topic, m.log_time_ns, m.data) for m in source]
                except LogError as err:
                    assert "\n" not in str(err) and data[:8] != rec.data[:8]
                else:
                    assert _is_subsequence(got, original)
            pipe.join(timeout=10)


def test_absurd_sizes_allocate_nothing(rec, tmp_path):
    c = rec.chunks[1]
    out = bytearray(rec.data)
    struct.pack_into("<Q", out, c.chunk_start_offset + 9 + 16, 2**62)  # uncompressed size
    got, source = _read(rec.write("sizes.mcap", bytes(out)))
    assert got == rec.without(1) and "implausible" in source.lost[0].reason
    stream = rec.data[:8] + struct.pack("<BQ", 0x06, 2**40)  # a stream's record of 1 TiB
    pipe = _Feeder(stream, 4096)
    with os.fdopen(pipe.read_fd, "rb") as f:
        reader = ByteStreamReader(f, rec.config, require=False)
        reader.read_all()
    assert reader.truncated and "exceeds the limit" in reader.warnings[0]


# -- (f) a rosbag2 folder with a damaged split ---------------------------------------------------
def test_f_rosbag2_damaged_split_loses_only_its_damaged_chunk(rec, tmp_path):
    half = len(rec.msgs) // 2
    folder = rl.write_rosbag2(tmp_path / "bag", rec.msgs, split_at=half)
    parts = [rec.msgs[:half], rec.msgs[half:]]
    for i, part in enumerate(parts):  # mcap_ros2's writer: zstd chunks with CRCs
        rl.write_mcap(folder / f"bag_{i}.mcap", part, chunk_size=CHUNK_SIZE // 2)
    first, second = ((folder / f"bag_{i}.mcap").read_bytes() for i in range(2))
    chunks = _chunks(first)
    assert len(chunks) >= 3
    c = chunks[1]
    (folder / "bag_0.mcap").write_bytes(_flip(first, c.chunk_start_offset + c.chunk_length - 5))
    got, source = _read(folder)
    kept = [m for k in chunks if k is not c for m in _chunk_keys(first, k)]
    kept += [m for k in _chunks(second) for m in _chunk_keys(second, k)]
    assert got == kept
    (lost,) = source.lost
    assert lost.file == str(folder / "bag_0.mcap") and lost.messages == len(_chunk_keys(first, c))
    log = read_log(folder, rec.config, require=False)
    assert log.lost == (lost,) and not log.truncated
    _assert_measurements_equal(log, _log_of(rec, kept, "f_expected.mcap"))
    # a split that is not MCAP at all loses only itself
    (folder / "bag_0.mcap").write_bytes(b"\x00" * 1000)
    log = read_log(folder, rec.config, require=False)
    assert log.truncated and "bag_0.mcap: not an MCAP file" in log.warnings[0]
    assert sum(log.topics[t].count for t in log.topics) == len(parts[1])


# -- (g) standard input and FIFOs ----------------------------------------------------------------
class _Feeder(threading.Thread):
    """Writes bytes into a pipe (or opens and writes a FIFO) from a thread."""

    def __init__(self, data: bytes, piece: int = 4096, fifo: Path | None = None):
        super().__init__(daemon=True)
        self.data, self.piece, self.fifo = data, piece, fifo
        if fifo is None:
            self.read_fd, self.write_fd = os.pipe()
        self.start()

    def run(self) -> None:
        fd = os.open(self.fifo, os.O_WRONLY) if self.fifo is not None else self.write_fd
        try:
            for at in range(0, len(self.data), self.piece):
                os.write(fd, self.data[at : at + self.piece])
        except BrokenPipeError:  # the reader gave up on a stream it rejected
            pass
        finally:
            os.close(fd)


def test_g_fifo_is_read_as_a_stream(rec, tmp_path):
    expected = read_log(rec.write("g.mcap", rec.data), rec.config, require=False)
    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    feeder = _Feeder(rec.data, 1000, fifo=fifo)
    log = read_log(fifo, rec.config, require=False)
    feeder.join(timeout=10)
    assert log.source == str(fifo) and log.warnings == () and not log.truncated
    _assert_measurements_equal(log, expected)
    # a damaged chunk through a FIFO: skipped, counted by the message indexes that follow it
    start, end = rec.data_of(1)
    feeder = _Feeder(_flip(rec.data, (start + end) // 2), 1000, fifo=fifo)
    got, source = _read(fifo)
    feeder.join(timeout=10)
    assert got == rec.without(1)
    (lost,) = source.lost
    assert (
        lost.messages == len(rec.in_chunk[1]) and lost.start_ns == rec.chunks[1].message_start_time
    )


def test_g_stdin_dash_is_read_as_a_stream(rec, monkeypatch):
    expected = read_log(rec.write("g_stdin.mcap", rec.data), rec.config, require=False)
    feeder = _Feeder(rec.data, 777)
    stdin = SimpleNamespace(buffer=os.fdopen(feeder.read_fd, "rb"))
    monkeypatch.setattr(sys, "stdin", stdin)
    log = read_log("-", rec.config, require=False)
    feeder.join(timeout=10)
    stdin.buffer.close()
    assert log.source == "<stdin>" and log.warnings == ()
    _assert_measurements_equal(log, expected)


def test_g_real_stdin_in_a_subprocess(rec):
    code = (
        "from estimator.io.logs import read_log; log = read_log('-'); "
        "print(sum(t.count for t in log.topics.values()), len(log.warnings))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], input=rec.data, capture_output=True, check=True, timeout=120
    )
    assert out.stdout.split() == [str(len(rec.msgs)).encode(), b"0"]


# -- files without CRCs, and the data section CRC ------------------------------------------------
def test_a_file_without_crcs_reads(rec):
    data = rl.mcap_bytes(rec.msgs, chunk_size=CHUNK_SIZE, enable_crcs=False)
    assert struct.unpack_from("<I", data, len(data) - 12)[0] == 0  # no summary CRC either
    got, source = _read(rec.write("nocrc.mcap", data))
    assert got == rec.without() and source.warnings == []
    cut = data[: _chunks(data)[-1].chunk_start_offset]  # read record by record
    got, source = _read(rec.write("nocrc_cut.mcap", cut))
    assert got == rec.without(3) and source.truncated


@pytest.mark.parametrize("summary", ["intact", "cut"])
def test_a_chunk_without_crc_is_checked_against_its_message_index(rec, summary):
    data = rl.mcap_bytes(rec.msgs, chunk_size=CHUNK_SIZE, compression="none", enable_crcs=False)
    c = _chunks(data)[1]
    out = bytearray(data)
    first_record = c.chunk_start_offset + 9 + 40
    out[first_record : first_record + 9] = bytes(9)  # its first record's opcode and length
    if summary == "cut":
        out = out[: len(out) - 20]
    got, source = _read(rec.write("nocrc_damaged.mcap", bytes(out)))
    assert _is_subsequence(got, rec.without()) and len(got) < len(rec.msgs)
    lost = [x for x in source.lost if x.at_byte == c.chunk_start_offset]
    assert [x.messages for x in lost] == [len(rec.msgs) - len(got)]
    assert "chunk without a CRC holds 0 messages" in lost[0].reason


def test_data_section_crc_flags_damage_outside_chunks(tmp_path):
    path = tmp_path / "unchunked.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f, use_chunking=False, enable_data_crcs=True)
        writer.start(profile="", library="test")
        schema = writer.register_schema("Imu", "jsonschema", b"{}")
        channel = writer.register_channel("/json", "json", schema)
        for k in range(5):
            writer.add_message(channel, log_time=k, publish_time=k, data=b"value %d" % k)
        writer.finish()
    assert len(_read(path)[0]) == 5 and _read(path)[1].warnings == []
    data = path.read_bytes()
    path.write_bytes(data.replace(b"value 3", b"value 8"))
    got, source = _read(path)
    assert [m[2] for m in got] == [b"value 0", b"value 1", b"value 2", b"value 8", b"value 4"]
    (warning,) = source.warnings
    assert "data section CRC mismatch" in warning


def test_not_mcap_is_one_line_log_error(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"PK\x03\x04 a zip file")
    with pytest.raises(LogError, match=r"x.mcap: not an MCAP file") as err:
        read_log(tmp_path / "x.mcap")
    assert "\n" not in str(err.value)
