"""Raw MCAP messages, in file order, from a file, a rosbag2 folder, a FIFO or a byte stream.

The only module that walks MCAP records. What is validated before anything is used: every
chunk's CRC (of its uncompressed records), the summary's CRC (footer) before its chunk index is
trusted, and the data section's CRC (DataEnd) where a writer stored one and chunks without a
CRC of their own were read. What a CRC does not cover is checked too: a chunk record must be
exactly its fields and data, its sizes must agree, and a zero CRC among chunks that carry one
is damage; a chunk without a CRC must hold as many messages as its message index lists. A
damaged record is never yielded as changed values; what is salvaged instead:

- A complete file is read through its chunk index, chunk by chunk (chunks of unwanted topics
  are never decompressed); a damaged chunk (CRC mismatch, decompression error, unparsable
  records) is skipped with its time range and message count, and every other chunk is read.
- A file without a usable summary (a crashed recorder, a cut copy, a damaged summary) and a
  byte stream are read record by record. A damaged chunk whose length agrees with its own
  layout is skipped (counted by the message index records that follow it); after any other
  damage (a garbage length or opcode, an unreadable record) a file is searched forward for
  the next chunk whose CRC validates, while a stream, which cannot seek, stops there. A
  record whose content is a CRC-valid chunk is read as one even if its opcode is damaged.
  A cut file or stream keeps every message before the cut.
- A rosbag2 folder reads each split file so; a damaged split loses only its own damage.

Each loss is a `LostData` in `LogSource.lost` and a line in `LogSource.warnings`. Only a path
that is not a log at all, an I/O error, or a stream that does not start as MCAP raises, and
then always `LogError`. Every source yields messages in the order they were written (for a
recorder, the order they arrived), so a file and the same bytes through a pipe give the same
sequence. Absurd lengths never allocate: reads are capped at what the file holds, a stream's
records at `RECORD_SIZE_LIMIT`, and a chunk's declared sizes are checked before decompressing.
"""

from __future__ import annotations

import io
import os
import re
import stat
import struct
import sys
import zlib
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NamedTuple

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    McapRecord,
    Message,
    MessageIndex,
    Schema,
)
from mcap.stream_reader import CRCValidationError, breakup_chunk
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from estimator.errors import LogError
from estimator.io.logs.ros2_types import normalize_type

RECORD_SIZE_LIMIT = 1 << 30  # the longest record a stream may send, the largest chunk inflated

_MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")  # opcode, content length: the head of every record
_FOOTER = struct.Struct("<BQQQI")  # the footer record: head, summary start, offset start, CRC
_CHUNK_FIELDS = struct.Struct("<QQQII")  # start, end time, uncompressed size, CRC, codec length
_CHUNK_PREFIX = _RECORD.size + _CHUNK_FIELDS.size + 4 + 8  # up to the data length ('zstd')
_CODECS = (b"", b"lz4", b"zstd")
_CHUNK_OPCODE = bytes([Opcode.CHUNK])
_SCAN_BLOCK = 1 << 20  # bytes searched at a time for the next chunk


@dataclass(frozen=True)
class LostData:
    """Messages a damaged log lost.

    file: the MCAP file (or stream) they were in. start_ns, end_ns: the log times they lie
    between (None: unknown). messages: how many (None: unknown). reason: what was damaged.
    at_byte: where the damage starts in the file (None: not at one place).
    """

    file: str
    start_ns: int | None
    end_ns: int | None
    messages: int | None
    reason: str
    at_byte: int | None = None

    def describe(self, t0_ns: int | None = None) -> str:
        """One line; times in seconds after `t0_ns` (the log's start), absolute ns without."""
        count = "an unknown number of" if self.messages is None else str(self.messages)
        at = f" at byte {self.at_byte}" if self.at_byte is not None else ""
        return f"{self.file}: {self.reason}{at}; lost {count} messages logged {self._span(t0_ns)}"

    def _span(self, t0_ns: int | None) -> str:
        def when(t_ns: int) -> str:
            return f"{(t_ns - t0_ns) / 1e9:.3f} s" if t0_ns is not None else f"at {t_ns} ns"

        start, end = self.start_ns, self.end_ns
        if start is not None and end is not None:
            if t0_ns is None:
                return f"between {start} and {end} ns (log time)"
            return f"between {when(start)} and {when(end)} into the log"
        if start is not None:
            return f"after {when(start)}" + (" into the log" if t0_ns is not None else "")
        if end is not None:
            return f"before {when(end)}" + (" into the log" if t0_ns is not None else "")
        return "at unknown times"


class RawMessage(NamedTuple):
    """One undecoded message. `msg_type` is the schema name (`pkg/msg/Type`), '' if none."""

    topic: str
    msg_type: str
    schema: Schema | None
    message_encoding: str
    log_time_ns: int
    data: bytes


class LogSource:
    """Iterate a log's messages once; the attributes below fill in as it goes.

    topics: every topic seen (a declared channel, even one without messages) → message type.
    warnings: one line per problem with the log itself (damage, truncation).
    lost: one `LostData` per damaged or missing part (each also has a line in `warnings`).
    truncated: the log ends early (a cut file or stream, damage that reaches the end of the
        data, a missing split file); a damaged chunk in the middle is lost, not truncation.
    start_ns: the first log time met, which lost time ranges are given relative to.
    window: (start, end) ns: only the messages received in [start, end) (`open_log`).
    """

    def __init__(self, name: str, iterate: Callable[[LogSource], Iterator[RawMessage]]):
        self.name = name
        self.window: tuple[int, int] | None = None
        self.topics: dict[str, str] = {}
        self.warnings: list[str] = []
        self.lost: list[LostData] = []
        self.truncated = False
        self.start_ns: int | None = None
        self._iterate = iterate

    def __iter__(self) -> Iterator[RawMessage]:
        try:
            for raw in self._iterate(self):
                if self.window is None or self.window[0] <= raw.log_time_ns < self.window[1]:
                    yield raw
        except LogError:
            raise
        except OSError as err:
            raise LogError(f"{self.name}: read error: {err}") from err
        except Exception as err:  # a last guard: damaged bytes only ever raise LogError
            raise LogError(f"{self.name}: unreadable MCAP data ({_describe(err)})") from err

    def warn(self, text: str, *, truncated: bool = False) -> None:
        self.warnings.append(text)
        self.truncated = self.truncated or truncated

    def lose(self, lost: LostData, text: str | None = None, *, truncated: bool = False) -> None:
        """Record a loss; its warning is `text`, or the loss described."""
        self.lost.append(lost)
        self.warn(text or lost.describe(self.start_ns), truncated=truncated)

    def saw_time(self, t_ns: int) -> None:
        if self.start_ns is None:
            self.start_ns = t_ns


def open_log(
    path: str | Path,
    topics: Collection[str] | None = None,
    log_time: tuple[int, int] | None = None,
) -> LogSource:
    """A source over an MCAP file, a rosbag2 folder (metadata.yaml + split .mcap files), a
    FIFO, or standard input (`-`); the last two are read as byte streams.

    topics: read only these (None: all). log_time: (start, end) ns, only the messages the
    recorder received in [start, end) (a file's chunks outside are not read: a slice of a long
    log costs its own size; a FIFO or standard input cannot be sliced). Raises `LogError` if
    the path is not a log.
    """
    if log_time is not None:
        if str(path) == "-" or Path(path).is_fifo():
            raise LogError(f"{path}: a stream is read once; a time slice needs a file or folder")
        source = open_log(path, topics)
        source.window = log_time
        return source
    if str(path) == "-":
        stdin = getattr(sys.stdin, "buffer", None)
        if stdin is None:
            raise LogError("-: standard input is not open for reading bytes")
        return open_stream(stdin, "<stdin>", topics)
    path = Path(path)
    if path.is_dir():
        files = _rosbag2_files(path)
        return LogSource(str(path), lambda src: _iter_folder(src, files, topics))
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise LogError(f"{path}: no such file or folder") from None
    except OSError as err:
        raise LogError(f"{path}: {err.strerror}") from err
    if stat.S_ISFIFO(mode):
        return LogSource(str(path), lambda src: _iter_fifo(src, path, topics))
    if not stat.S_ISREG(mode):
        raise LogError(f"{path}: not a file, folder or FIFO")
    if (problem := _not_mcap(path)) is not None:
        raise LogError(problem)
    return LogSource(str(path), lambda src: _iter_file(src, path, topics))


def log_time_span(path: str | Path) -> tuple[int, int]:
    """(first, last) receive time of a log file's or rosbag2 folder's messages: from each
    file's chunk index, or, in a file without one (cut, damaged), by reading it through."""
    path = Path(path)
    first, last = [], []
    for file in _rosbag2_files(path) if path.is_dir() else [path]:
        if not file.is_file() or _not_mcap(file) is not None:
            continue
        with file.open("rb") as f:
            index, _ = _read_index(f, os.fstat(f.fileno()).st_size)
        if index is not None:
            first.append(min(c.message_start_time for c in index.chunks))
            last.append(max(c.message_end_time for c in index.chunks))
            continue
        times = [raw.log_time_ns for raw in open_log(file)]
        if times:
            first.append(min(times))
            last.append(max(times))
    if not first:
        raise LogError(f"{path}: no messages")
    return min(first), max(last)


def open_stream(
    stream: IO[bytes], name: str = "<stream>", topics: Collection[str] | None = None
) -> LogSource:
    """A source over a non-seekable MCAP byte stream (pipe, socket), read as bytes arrive."""
    return LogSource(name, lambda src: _Scan(src, name, _Input(stream), topics).messages())


def _iter_fifo(src: LogSource, path: Path, topics: Collection[str] | None) -> Iterator[RawMessage]:
    with path.open("rb") as f:  # waits for a writer to open the FIFO
        yield from _Scan(src, str(path), _Input(f), topics).messages()


# -- rosbag2 folders ---------------------------------------------------------------------------
def _rosbag2_files(folder: Path) -> list[Path]:
    """The folder's storage files in recording order, from metadata.yaml when it exists.

    rosbag2 writes metadata.yaml when a recording closes; without it (a crash) the .mcap
    files are taken in their split order (`name_0.mcap`, `name_1.mcap`, ...).
    """
    meta_path = folder / "metadata.yaml"
    if not meta_path.is_file():
        files = sorted(folder.glob("*.mcap"), key=split_index)
        if not files:
            raise LogError(f"{folder}: not a rosbag2 folder (no metadata.yaml, no .mcap files)")
        return files
    try:
        meta = YAML(typ="safe").load(meta_path.read_text(encoding="utf-8"))
        info = meta["rosbag2_bagfile_information"]
        storage = info.get("storage_identifier", "mcap")
        relative = [str(p) for p in info["relative_file_paths"]]
        compression = info.get("compression_mode", "") or ""
    except (YAMLError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as err:
        raise LogError(f"{meta_path}: not a valid rosbag2 metadata file: {err!r}") from err
    if storage != "mcap":
        raise LogError(
            f"{folder}: rosbag2 storage {storage!r} is not supported; physfuse reads 'mcap' "
            f"(convert with `ros2 bag convert` or `rosbags-convert`)"
        )
    if compression.lower() not in ("", "none"):
        raise LogError(
            f"{folder}: rosbag2 compression mode {compression!r} is not supported; "
            "re-record or convert without file/message compression (MCAP chunk compression "
            "is fine)"
        )
    return [folder / Path(p).name for p in relative]


def split_index(path: Path) -> tuple[int, str]:
    match = re.search(r"_(\d+)\.mcap$", path.name)
    return (int(match.group(1)) if match else -1, path.name)


def _iter_folder(
    src: LogSource, files: list[Path], topics: Collection[str] | None
) -> Iterator[RawMessage]:
    """Each split file in turn; one that is missing or unreadable loses only itself."""
    for path in files:
        if not path.is_file():
            problem: str | None = f"{path}: listed in metadata.yaml but missing; skipped"
        elif (problem := _not_mcap(path)) is not None:
            problem += "; skipped"
        if problem is not None:
            src.lose(LostData(str(path), None, None, None, "split file"), problem, truncated=True)
            continue
        yield from _iter_file(src, path, topics)


# -- one file ----------------------------------------------------------------------------------
def _not_mcap(path: Path) -> str | None:
    """Why the file is not MCAP (one line), None if it starts as MCAP."""
    with path.open("rb") as f:
        head = f.read(len(_MAGIC))
    return None if head == _MAGIC else f"{path}: not an MCAP file (starts with {head[:8]!r})"


class _Index(NamedTuple):
    """What a complete file's CRC-checked summary says."""

    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    chunks: list[ChunkIndex]  # in file order
    data_end: int  # offset of the DataEnd record
    data_crc: int  # its data section CRC (0: none stored)


def _iter_file(src: LogSource, path: Path, topics: Collection[str] | None) -> Iterator[RawMessage]:
    name = str(path)
    with path.open("rb") as f:
        size = os.fstat(f.fileno()).st_size
        index, problem = _read_index(f, size)
        if index is not None:
            yield from _iter_indexed(src, f, name, size, index, topics)
            return
        if problem:
            src.warn(f"{name}: MCAP summary unusable ({problem}); read record by record")
        f.seek(0)
        scan = _Scan(src, name, _Input(f, size), topics, summary_reported=bool(problem))
        yield from scan.messages()


def _read_index(f: IO[bytes], size: int) -> tuple[_Index | None, str]:
    """The file's summary, or (None, why it is unusable).

    `why` is '' when the file simply has none to use: it was cut or its recorder crashed
    (the record-by-record scan reports that), or its writer wrote no chunk index.
    """
    tail_at = size - _FOOTER.size - len(_MAGIC)
    if tail_at < len(_MAGIC):
        return None, ""
    f.seek(tail_at)
    tail = f.read(_FOOTER.size + len(_MAGIC))
    if tail[-len(_MAGIC) :] != _MAGIC:
        return None, ""
    opcode, length, summary_start, _, summary_crc = _FOOTER.unpack_from(tail)
    if opcode != Opcode.FOOTER or length != _FOOTER.size - _RECORD.size:
        return None, "damaged footer"
    if summary_start == 0:
        return None, ""
    if not len(_MAGIC) <= summary_start <= tail_at:
        return None, f"footer points at byte {summary_start}, outside the file"
    f.seek(summary_start)
    summary = f.read(tail_at - summary_start)
    # the CRC covers the summary and the footer up to the CRC field itself
    if summary_crc and zlib.crc32(tail[: _FOOTER.size - 4], zlib.crc32(summary)) != summary_crc:
        return None, "summary CRC mismatch"
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    chunks: list[ChunkIndex] = []
    try:
        for opcode, body in _records_in(summary):
            record = _parse(opcode, body)
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, ChunkIndex):
                chunks.append(record)
    except Exception as err:
        return None, f"damaged summary: {_reason(err)}"
    if not chunks:
        return None, ""
    chunks.sort(key=lambda c: c.chunk_start_offset)
    if not all(
        len(_MAGIC) <= c.chunk_start_offset
        and c.chunk_start_offset + max(c.chunk_length, _RECORD.size) <= summary_start
        for c in chunks
    ):
        return None, "chunk index points outside the data section"
    if not summary_crc and not all(_chunk_head_matches(f, c) for c in chunks):
        return None, "chunk index does not match the chunks (the summary has no CRC)"
    data_end = summary_start - _RECORD.size - 4  # DataEnd closes the data section
    data_crc = 0
    if data_end >= len(_MAGIC):
        f.seek(data_end)
        data_end_record = f.read(_RECORD.size + 4)
        if _RECORD.unpack_from(data_end_record) == (Opcode.DATA_END, 4):
            data_crc = struct.unpack_from("<I", data_end_record, _RECORD.size)[0]
    return _Index(schemas, channels, chunks, data_end, data_crc), ""


def _chunk_head_matches(f: IO[bytes], index: ChunkIndex) -> bool:
    f.seek(index.chunk_start_offset)
    head = f.read(_RECORD.size)
    return _RECORD.unpack(head) == (Opcode.CHUNK, index.chunk_length - _RECORD.size)


def _iter_indexed(
    src: LogSource,
    f: IO[bytes],
    name: str,
    size: int,
    index: _Index,
    topics: Collection[str] | None,
) -> Iterator[RawMessage]:
    """Chunk by chunk through the chunk index, in file order; damaged chunks are skipped."""
    declared = _Declared(src, name, topics)
    for record in (*index.schemas.values(), *index.channels.values()):
        declared.declare(record)
    src.saw_time(min(c.message_start_time for c in index.chunks))
    wanted = None
    if topics is not None:
        wanted = {i for i, channel in index.channels.items() if channel.topic in topics}
    # a writer gives all chunks a CRC or none: a zero one among CRCs is damage
    need_crc = any(_chunk_crc(f, entry) for entry in index.chunks)
    unchecked = False  # a chunk without a CRC of its own was read
    for entry in index.chunks:
        if src.window is not None and not (
            entry.message_start_time < src.window[1] and entry.message_end_time >= src.window[0]
        ):
            continue  # outside the slice asked for: not read
        if (
            wanted is not None
            and entry.message_index_offsets
            and not (wanted & entry.message_index_offsets.keys())
        ):
            continue
        f.seek(entry.chunk_start_offset)
        # the index's (CRC-checked) length bounds the chunk, not the chunk's own length field
        content = f.read(entry.chunk_length)[_RECORD.size :]
        try:
            chunk = _parse(Opcode.CHUNK, content)
            assert isinstance(chunk, Chunk)
            records = _chunk_records(chunk, len(content), need_crc=need_crc)
        except Exception as err:
            count = _indexed_count(f, entry, size)
            reason = f"damaged chunk ({_reason(err)})"
            start, end = entry.message_start_time, entry.message_end_time
            src.lose(LostData(name, start, end, count, reason, entry.chunk_start_offset))
            continue
        messages = [r for r in records if isinstance(r, Message)]
        if chunk.uncompressed_crc == 0:  # unchecked: its message index is the only witness
            unchecked = True
            count = _indexed_count(f, entry, size)
            if count is not None and count != len(messages):
                src.lose(_miscounted(name, entry.chunk_start_offset, chunk, len(messages), count))
        for record in records:
            if isinstance(record, Message):
                if (raw := declared.message(record)) is not None:
                    yield raw
            else:
                declared.declare(record)
    declared.report()
    if unchecked and index.data_crc and _crc_of(f, index.data_end) != index.data_crc:
        src.warn(
            f"{name}: data section CRC mismatch where chunks carry no CRC of their own; "
            "values read from those chunks may be damaged"
        )


def _chunk_crc(f: IO[bytes], entry: ChunkIndex) -> int:
    f.seek(entry.chunk_start_offset + _RECORD.size + 24)  # after the times and the size
    return int.from_bytes(f.read(4), "little")


def _miscounted(name: str, at: int, chunk: Chunk, held: int, indexed: int) -> LostData:
    """A chunk without a CRC that holds other than its message index lists."""
    return LostData(
        name,
        chunk.message_start_time,
        chunk.message_end_time,
        abs(indexed - held),
        f"chunk without a CRC holds {held} messages, its message index lists {indexed} "
        "(values read from it may be damaged)",
        at,
    )


def _indexed_count(f: IO[bytes], entry: ChunkIndex, size: int) -> int | None:
    """Messages in an indexed chunk by its message index records (None: unknown)."""
    at = entry.chunk_start_offset + entry.chunk_length
    f.seek(at)
    data = f.read(max(0, min(entry.message_index_length, size - at)))
    try:
        indexes = [_parse(op, body) for op, body in _records_in(data)]
    except Exception:
        return None
    counts = [len(i.records) for i in indexes if isinstance(i, MessageIndex)]
    return sum(counts) if counts else None


def _crc_of(f: IO[bytes], end: int) -> int:
    """CRC32 of the file's first `end` bytes."""
    f.seek(0)
    crc, at = 0, 0
    while at < end and (block := f.read(min(_SCAN_BLOCK, end - at))):
        crc = zlib.crc32(block, crc)
        at += len(block)
    return crc


# -- record by record: files without a usable summary, and streams ------------------------------
class _Scan:
    """One pass over a file's or stream's records, from the magic to the footer.

    A damaged chunk whose length agrees with its layout is skipped; any other damage in a
    file starts a search for the next chunk whose CRC validates, and ends a stream.
    """

    def __init__(
        self,
        src: LogSource,
        name: str,
        inp: _Input,
        topics: Collection[str] | None,
        *,
        summary_reported: bool = False,
    ):
        self.src, self.name, self.inp = src, name, inp
        self.declared = _Declared(src, name, topics)
        self.summary_reported = summary_reported  # the summary's damage was already warned of
        self.pending: _Pending | None = None  # the last chunk, until its message indexes pass
        self.indexed: int | None = None  # the messages those index records list
        self.crc_chunks = 0  # chunks with a CRC so far (then a zero CRC is damage)
        self.unchecked: list[int] = []  # chunks read without a CRC: their messages
        self.damaged = False  # something was skipped: the data section CRC cannot match
        self.chunked = False  # a chunk was met: a message outside chunks is then damage
        self.in_summary = False  # past DataEnd: no messages follow
        self.last_ns: int | None = None  # the last message's log time, bounds a lost region

    def messages(self) -> Iterator[RawMessage]:
        head = self.inp.read(len(_MAGIC))
        if head != _MAGIC:
            raise LogError(f"{self.name}: not an MCAP stream (starts with {head[:8]!r})")
        yield from self._records()
        self._flush()
        self.declared.report()
        if self.unchecked and self.crc_chunks:  # written before the first chunk with a CRC
            self.src.warn(
                f"{self.name}: {len(self.unchecked)} chunks carry no CRC while later ones do "
                f"(a damaged CRC field?); their {sum(self.unchecked)} messages were read "
                "unchecked"
            )

    def _records(self) -> Iterator[RawMessage]:
        inp = self.inp
        while True:
            start, crc_before = inp.pos, inp.crc
            head = inp.read(_RECORD.size)
            if len(head) < _RECORD.size:
                self._cut(start, "cut inside a record" if head else "no footer")
                return
            opcode, length = _RECORD.unpack(head)
            if opcode != Opcode.MESSAGE_INDEX:
                self._flush()
            if (problem := self._length_problem(length, start)) is not None:
                if self.in_summary or not self._resync(start, problem):
                    self._cut(start, problem)
                    return
                continue
            body = inp.read(length)
            if len(body) < length:
                self._cut(start, f"cut inside a record, {len(body)} of its {length} bytes")
                return
            if opcode != Opcode.CHUNK and _looks_like_chunk(body):
                opcode = Opcode.CHUNK  # a chunk whose opcode is damaged: its CRC decides
            if opcode == Opcode.CHUNK:
                messages = self._chunk(start, body)
                if messages is None:
                    return
                yield from messages
                continue
            record, problem = self._record(opcode, body)
            if problem is not None:
                if self.in_summary:  # every message was read; the summary is only an index
                    if not self.summary_reported:
                        self.src.warn(f"{self.name}: damaged summary at byte {start} ({problem})")
                    return
                if not self._resync(start, problem):
                    self._cut(start, problem)
                    return
                continue
            if isinstance(record, Message):
                self.src.saw_time(record.log_time)
                self.last_ns = record.log_time
                if (raw := self.declared.message(record)) is not None:
                    yield raw
            elif isinstance(record, Schema | Channel):
                self.declared.declare(record)
            elif isinstance(record, MessageIndex):
                if self.pending is not None:
                    self.indexed = (self.indexed or 0) + len(record.records)
            elif isinstance(record, DataEnd):
                self.in_summary = True
                self._check_data_crc(record.data_section_crc, crc_before)
            elif isinstance(record, Footer):
                end = inp.pos
                if inp.read(len(_MAGIC)) != _MAGIC:
                    self._cut(end, "no closing magic")
                return

    def _record(self, opcode: int, body: bytes) -> tuple[McapRecord | None, str | None]:
        """The record (None: one this reader passes over), or why it cannot be trusted."""
        if opcode == 0 or 0x10 <= opcode < 0x80:  # 0x80-0xff are private records
            return None, f"unknown record opcode {opcode:#04x}"
        try:
            record = _parse(opcode, body)
        except Exception as err:
            return None, f"unreadable record ({_reason(err)})"
        if isinstance(record, Message) and self.chunked:  # no writer mixes the two
            return None, "message record outside the chunks"
        return record, None

    def _chunk(self, start: int, body: bytes) -> list[RawMessage] | None:
        """The wanted messages of a chunk record ([] if it is damaged and skipped); None if
        the scan must stop there."""
        self.chunked = True
        chunk: Chunk | None = None
        try:
            parsed = _parse(Opcode.CHUNK, body)
            chunk = parsed if isinstance(parsed, Chunk) else None
            if chunk is None:
                raise _DamageError("its fields overrun the record")
            records = _chunk_records(chunk, len(body), need_crc=self.crc_chunks > 0)
        except Exception as err:
            reason = f"damaged chunk ({_reason(err)})"
            codec = len(chunk.compression.encode()) if chunk is not None else 0
            if chunk is None or len(body) != _CHUNK_FIELDS.size + codec + 8 + len(chunk.data):
                # the length field disagrees with the chunk's own layout: skipping by it
                # would land anywhere, so search for the next valid chunk instead
                if self._resync(start, reason):
                    return []
                self._cut(start, reason)
                return None
            if chunk.message_start_time <= chunk.message_end_time:
                self.src.saw_time(chunk.message_start_time)
            self.pending, self.indexed = _Pending(start, chunk, None, reason), None
            self.damaged = True
            return []
        self.src.saw_time(chunk.message_start_time)
        messages, held = [], 0
        for record in records:
            if isinstance(record, Message):
                held += 1
                self.last_ns = record.log_time
                if (raw := self.declared.message(record)) is not None:
                    messages.append(raw)
            else:
                self.declared.declare(record)
        if chunk.uncompressed_crc:
            self.crc_chunks += 1
        else:  # unchecked: its message index records, next, are the only witness
            self.unchecked.append(held)
            self.pending, self.indexed = _Pending(start, chunk, held, ""), None
        return messages

    def _check_data_crc(self, expected: int, actual: int | None) -> None:
        """Warn if the data section's CRC (where stored) fails with no damage found before."""
        if expected and actual is not None and not self.damaged and actual != expected:
            self.src.warn(
                f"{self.name}: data section CRC mismatch: bytes that no chunk CRC covers are "
                "damaged; values read outside CRC-checked chunks may be wrong"
            )

    def _length_problem(self, length: int, start: int) -> str | None:
        if self.inp.size is not None:
            if length > self.inp.size - start - _RECORD.size:
                return f"record length {length} runs past the end of the file"
        elif length > RECORD_SIZE_LIMIT:
            return f"record length {length} exceeds the limit of {RECORD_SIZE_LIMIT}"
        return None

    def _resync(self, start: int, problem: str) -> bool:
        """Search a file from just after `start` for the next valid chunk and go on there;
        False if there is none (or this is a stream, which cannot seek)."""
        self.damaged = True
        if self.inp.size is None:
            return False
        found = _find_chunk(self.inp, start + 1)
        if found is None:
            return False
        at, next_ns = found
        reason = f"unreadable bytes {start}..{at} ({problem})"
        self.src.lose(LostData(self.name, self.last_ns, next_ns, None, reason, start))
        self.inp.seek(at)
        return True

    def _cut(self, at: int, problem: str) -> None:
        """The data ends (or is unreadable to the end) at byte `at`."""
        self._flush()
        of_size = f" of {self.inp.size}" if self.inp.size is not None else ""
        text = (
            f"{self.name}: truncated or damaged after byte {at}{of_size} ({problem}); "
            "kept every complete message before it"
        )
        if self.in_summary:  # nothing but the index was lost
            self.src.warn(text, truncated=True)
            return
        lost = LostData(self.name, self.last_ns, None, None, f"truncated ({problem})", at)
        self.src.lose(lost, text, truncated=True)

    def _flush(self) -> None:
        """Once a chunk's message index records have passed: report it if it was skipped (with
        their count), or if it had no CRC and holds other than they list."""
        pending, self.pending = self.pending, None
        if pending is None:
            return
        chunk, indexed = pending.chunk, self.indexed
        if pending.held is None:
            times: tuple[int | None, int | None] = (None, None)
            if chunk.message_start_time <= chunk.message_end_time:
                times = (chunk.message_start_time, chunk.message_end_time)
            self.src.lose(LostData(self.name, *times, indexed, pending.reason, pending.start))
        elif indexed is not None and indexed != pending.held:
            self.src.lose(_miscounted(self.name, pending.start, chunk, pending.held, indexed))


class _Pending(NamedTuple):
    """A chunk whose message index records are still to come."""

    start: int  # its offset
    chunk: Chunk
    held: int | None  # the messages read from it; None: it was skipped as damaged
    reason: str  # why it was skipped


class _Input:
    """Exact reads from a file or stream: the position, the file's size (None: a stream) and
    the CRC of all bytes read (None once a seek has skipped some).

    A long read is made in pieces, so that memory grows only as bytes actually arrive.
    """

    _PIECE = 1 << 20

    def __init__(self, raw: Any, size: int | None = None):
        self.raw = raw
        self.size = size
        self.pos = 0
        self.crc: int | None = 0

    def read(self, n: int) -> bytes:
        parts = []
        remaining = n
        while remaining > 0:
            part = self.raw.read(min(remaining, self._PIECE))
            if not part:
                break
            parts.append(part)
            remaining -= len(part)
        data = b"".join(parts)
        self.pos += len(data)
        if self.crc is not None:
            self.crc = zlib.crc32(data, self.crc)
        return data

    def seek(self, pos: int) -> None:
        self.raw.seek(pos)
        self.pos = pos
        self.crc = None


def _find_chunk(inp: _Input, start: int) -> tuple[int, int] | None:
    """(offset, start time) of the first chunk record at or after `start` whose fields are
    plausible and whose CRC validates; None if there is none before the end of the file."""
    assert inp.size is not None
    f, size = inp.raw, inp.size
    block_at = start
    while block_at < size:
        f.seek(block_at)
        block = f.read(_SCAN_BLOCK + _CHUNK_PREFIX)  # overlaps the next block by one header
        i = block.find(_CHUNK_OPCODE)
        while 0 <= i < _SCAN_BLOCK:
            head = block[i : i + _CHUNK_PREFIX]
            extent = _chunk_extent(head, size - block_at - i)
            if extent is not None and _chunk_validates(f, block_at + i, extent):
                return block_at + i, _CHUNK_FIELDS.unpack_from(head, _RECORD.size)[0]
            i = block.find(_CHUNK_OPCODE, i + 1)
        block_at += _SCAN_BLOCK
    return None


def _chunk_extent(head: bytes, room: int) -> int | None:
    """The record size of a chunk starting `head` if its fields are plausible, else None.

    Plausible: it fits in the `room` left in the file, has a CRC, a known compression, times
    in order, a sane uncompressed size, and a record length that agrees with its data length.
    The opcode is not looked at: it may be the damaged part.
    """
    if len(head) < _CHUNK_PREFIX - 4:
        return None
    _, length = _RECORD.unpack_from(head)
    start_ns, end_ns, uncompressed, crc, codec_length = _CHUNK_FIELDS.unpack_from(head, 9)
    codec_at = _RECORD.size + _CHUNK_FIELDS.size
    if codec_length > 4 or len(head) < codec_at + codec_length + 8:
        return None
    if head[codec_at : codec_at + codec_length] not in _CODECS:
        return None
    (data_length,) = struct.unpack_from("<Q", head, codec_at + codec_length)
    plausible = (
        crc != 0
        and start_ns <= end_ns
        and uncompressed <= RECORD_SIZE_LIMIT
        and length == _CHUNK_FIELDS.size + codec_length + 8 + data_length
        and _RECORD.size + length <= room
    )
    return _RECORD.size + length if plausible else None


def _looks_like_chunk(body: bytes) -> bool:
    """Whether a record's content is a plausible chunk (with a CRC) that fills it exactly."""
    head = _RECORD.pack(Opcode.CHUNK, len(body)) + body[: _CHUNK_PREFIX - _RECORD.size]
    return _chunk_extent(head, _RECORD.size + len(body)) is not None


def _chunk_validates(f: IO[bytes], at: int, extent: int) -> bool:
    f.seek(at)
    try:
        chunk = _parse(Opcode.CHUNK, f.read(extent)[_RECORD.size :])
        assert isinstance(chunk, Chunk)
        _chunk_records(chunk, extent - _RECORD.size, need_crc=True)
    except Exception:
        return False
    return True


# -- records (parsed by the mcap package) -------------------------------------------------------
class _DamageError(Exception):
    """Damage found by a check of ours (the mcap package raises its own errors)."""


class _ExactBytes(io.BytesIO):
    """A record's content whose short read raises: its fields must lie inside it."""

    def read(self, size: int | None = -1, /) -> bytes:
        data = super().read(size)
        if size is not None and 0 <= size != len(data):
            raise EndOfFile()
        return data


_READERS: dict[int, Callable[[ReadDataStream], McapRecord]] = {
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


def _parse(opcode: int, body: bytes) -> McapRecord | None:
    """The record with this opcode and content, read by the mcap package; None for a kind
    this reader does not use. Raises if the content is shorter than its fields say."""
    stream = ReadDataStream(_ExactBytes(body))
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(body))
    read = _READERS.get(opcode)
    return read(stream) if read is not None else None


def _records_in(data: bytes) -> Iterator[tuple[int, bytes]]:
    """(opcode, content) of each record in a buffer of whole records; raises at a bad length."""
    at = 0
    while at < len(data):
        if len(data) - at < _RECORD.size:
            raise _DamageError("a record header is cut short")
        opcode, length = _RECORD.unpack_from(data, at)
        end = at + _RECORD.size + length
        if end > len(data):
            raise _DamageError(f"record length {length} runs past its section")
        yield opcode, data[at + _RECORD.size : end]
        at = end


def _chunk_records(chunk: Chunk, length: int, *, need_crc: bool = False) -> list[McapRecord]:
    """The schema, channel and message records of a chunk record (content `length` bytes)
    whose CRC matches; raises on damage.

    What a CRC cannot vouch for is checked too: the record is exactly the chunk's fields and
    data (as every writer lays it out), and its declared sizes agree with the data; these
    checks come first, so that a damaged size cannot make the decompressor allocate
    gigabytes. need_crc: the file's other chunks carry a CRC, so a zero one is damage.
    """
    if length != _CHUNK_FIELDS.size + len(chunk.compression.encode()) + 8 + len(chunk.data):
        raise _DamageError("record length disagrees with the chunk's data length")
    if chunk.uncompressed_size > RECORD_SIZE_LIMIT:
        raise _DamageError(f"uncompressed size {chunk.uncompressed_size} is implausible")
    declared = len(chunk.data)
    if chunk.compression == "zstd":
        declared = zstandard.frame_content_size(chunk.data)
    elif chunk.compression == "lz4":
        declared = lz4.frame.get_frame_info(chunk.data)["content_size"] or -1
    if declared not in (-1, chunk.uncompressed_size):
        raise _DamageError("data size disagrees with the chunk's uncompressed size")
    if need_crc and chunk.uncompressed_crc == 0:
        raise _DamageError("no CRC, while the file's other chunks carry one")
    return breakup_chunk(chunk, validate_crc=True)


class _Declared:
    """Schemas and channels declared so far, and the messages of undeclared channels."""

    def __init__(self, src: LogSource, name: str, topics: Collection[str] | None):
        self.src, self.name, self.topics = src, name, topics
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.orphans: dict[int, int] = {}  # undeclared channel id → messages skipped
        self.orphan_span: tuple[int, int] | None = None  # their first and last log time

    def declare(self, record: McapRecord) -> None:
        """Remember a schema or channel; the first declaration of an id stands (a later,
        different one can only be damage outside the CRC-checked chunks)."""
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel) and record.id not in self.channels:
            self.channels[record.id] = record
            schema = self.schemas.get(record.schema_id)
            self.src.topics.setdefault(record.topic, _type_name(schema))

    def message(self, message: Message) -> RawMessage | None:
        """The message if its topic is wanted, else None (counted if its channel is unknown)."""
        channel = self.channels.get(message.channel_id)
        if channel is None:
            self.orphans[message.channel_id] = self.orphans.get(message.channel_id, 0) + 1
            first = self.orphan_span[0] if self.orphan_span else message.log_time
            self.orphan_span = (first, message.log_time)
            return None
        if self.topics is not None and channel.topic not in self.topics:
            return None
        return _raw(channel, self.schemas.get(channel.schema_id), message)

    def report(self) -> None:
        """One loss for all messages skipped for an undeclared channel."""
        if self.orphans and self.orphan_span is not None:
            ids = ", ".join(str(i) for i in sorted(self.orphans))
            first, last = self.orphan_span
            reason = f"messages on undeclared channel(s) {ids} (their declaration was lost)"
            self.src.lose(LostData(self.name, first, last, sum(self.orphans.values()), reason))


def _raw(channel: Channel, schema: Schema | None, message: Message) -> RawMessage:
    return RawMessage(
        topic=channel.topic,
        msg_type=_type_name(schema),
        schema=schema,
        message_encoding=channel.message_encoding,
        log_time_ns=message.log_time,
        data=message.data,
    )


def _type_name(schema: Schema | None) -> str:
    return normalize_type(schema.name) if schema is not None else ""


def _reason(err: BaseException) -> str:
    if isinstance(err, CRCValidationError):
        return "CRC mismatch"
    if isinstance(err, _DamageError | EndOfFile):
        return str(err) or "its fields overrun the record"
    return _describe(err)


def _describe(err: BaseException) -> str:
    text = str(err)
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
