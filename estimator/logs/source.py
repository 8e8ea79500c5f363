"""Raw MCAP messages, in file order, from a file, a rosbag2 folder or a live byte stream.

The only module that walks MCAP records. A complete, indexed file is read through its chunk
index (chunks of unwanted topics are never decompressed); a file without a valid summary
(the recorder crashed, the copy was cut) and a byte stream are read record by record, and
whatever follows the last readable record is reported as a warning, never an exception.
Every source yields messages in the order they were written, which for a recorder is the
order they arrived, so a file and the same bytes through a pipe give the same sequence.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import IO, Any, NamedTuple

from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from estimator.errors import LogError
from estimator.logs.ros2_types import normalize_type


class RawMessage(NamedTuple):
    """One undecoded message. `msg_type` is the schema name (`pkg/msg/Type`), '' if none."""

    topic: str
    msg_type: str
    schema: Schema | None
    message_encoding: str
    log_time_ns: int
    data: bytes


class LogSource:
    """Iterate a log's messages once; `topics`, `warnings` and `truncated` fill in as it goes.

    `topics` maps every topic seen (a declared channel, even one without messages) to its
    message type.
    """

    def __init__(self, name: str, iterate: Callable[[LogSource], Iterator[RawMessage]]):
        self.name = name
        self.topics: dict[str, str] = {}
        self.warnings: list[str] = []
        self.truncated = False
        self._iterate = iterate

    def __iter__(self) -> Iterator[RawMessage]:
        return self._iterate(self)

    def warn(self, text: str, *, truncated: bool = False) -> None:
        self.warnings.append(text)
        self.truncated = self.truncated or truncated


def open_log(path: str | Path, topics: Collection[str] | None = None) -> LogSource:
    """A source over an MCAP file or a rosbag2 folder (metadata.yaml + split .mcap files).

    `topics`: read only these (None: all). Raises `LogError` if the path is not a log.
    """
    path = Path(path)
    if path.is_dir():
        files = _rosbag2_files(path)
        return LogSource(str(path), lambda src: _iter_folder(src, files, topics))
    if not path.is_file():
        raise LogError(f"{path}: no such file or folder")
    _check_magic(path)
    return LogSource(str(path), lambda src: _iter_file(src, path, topics))


def open_stream(stream: IO[bytes], name: str = "<stream>") -> LogSource:
    """A source over a non-seekable MCAP byte stream (pipe, socket), read as bytes arrive."""
    return LogSource(name, lambda src: _iter_linear(src, _ExactReader(stream), None, name))


# -- rosbag2 folders ---------------------------------------------------------------------------
def _rosbag2_files(folder: Path) -> list[Path]:
    """The folder's storage files in recording order, from metadata.yaml when it exists.

    rosbag2 writes metadata.yaml when a recording closes; without it (a crash) the .mcap
    files are taken in their split order (`name_0.mcap`, `name_1.mcap`, ...).
    """
    meta_path = folder / "metadata.yaml"
    if not meta_path.is_file():
        files = sorted(folder.glob("*.mcap"), key=_split_index)
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


def _split_index(path: Path) -> tuple[int, str]:
    match = re.search(r"_(\d+)\.mcap$", path.name)
    return (int(match.group(1)) if match else -1, path.name)


def _iter_folder(
    src: LogSource, files: list[Path], topics: Collection[str] | None
) -> Iterator[RawMessage]:
    for path in files:
        if not path.is_file():
            src.warn(f"{path}: listed in metadata.yaml but missing; skipped", truncated=True)
            continue
        _check_magic(path)
        yield from _iter_file(src, path, topics)


# -- one file ----------------------------------------------------------------------------------
_MAGIC = b"\x89MCAP0\r\n"


def _check_magic(path: Path) -> None:
    with path.open("rb") as f:
        head = f.read(len(_MAGIC))
    if head != _MAGIC:
        raise LogError(f"{path}: not an MCAP file (starts with {head[:8]!r})")


def _iter_file(src: LogSource, path: Path, topics: Collection[str] | None) -> Iterator[RawMessage]:
    with path.open("rb") as f:
        summary = None
        summary_error = None
        try:
            summary = SeekingReader(f).get_summary()
        except Exception as err:  # any unreadable footer/summary: salvage record by record
            summary_error = err
        if summary is None or not summary.chunk_indexes:
            f.seek(0)
            size = path.stat().st_size
            warnings_before = len(src.warnings)
            yield from _iter_linear(src, _ExactReader(f), topics, str(path), size)
            if summary_error is not None and len(src.warnings) == warnings_before:
                src.warn(f"{path}: damaged MCAP summary ({_describe(summary_error)})")
            return
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            src.topics.setdefault(channel.topic, _type_name(schema))
        reader = SeekingReader(f)
        it = reader.iter_messages(topics=topics, log_time_order=False)
        while True:
            try:
                schema, channel, message = next(it)
            except StopIteration:
                return
            except Exception as err:  # damaged chunk in an indexed file
                src.warn(f"{path}: stopped at a damaged chunk: {_describe(err)}", truncated=True)
                return
            yield _raw(channel, schema, message)


def _iter_linear(
    src: LogSource,
    stream: _ExactReader,
    topics: Collection[str] | None,
    name: str,
    size: int | None = None,
) -> Iterator[RawMessage]:
    """Record by record; schemas and channels are remembered as they appear.

    size: the file's length, for the warning; None for a stream.
    """
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    records = StreamReader(stream, record_size_limit=1 << 30).records  # type: ignore[arg-type]
    while True:
        try:
            record = next(records)
        except StopIteration:  # the footer and the closing magic were read
            return
        except OSError as err:
            raise LogError(f"{name}: read error: {err}") from err
        except Exception as err:  # truncated or damaged from here on
            if stream.count <= len(_MAGIC):
                raise LogError(f"{name}: not an MCAP stream ({_describe(err)})") from err
            of_size = f" of {size}" if size is not None else ""
            src.warn(
                f"{name}: truncated or damaged after byte {stream.count}{of_size} "
                f"({_describe(err)}); kept every complete message before it",
                truncated=True,
            )
            return
        if isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                src.warn(f"{name}: message on undeclared channel {record.channel_id}; skipped")
                continue
            if topics is None or channel.topic in topics:
                yield _raw(channel, schemas.get(channel.schema_id), record)
        elif isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            src.topics.setdefault(record.topic, _type_name(schemas.get(record.schema_id)))


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


def _describe(err: BaseException) -> str:
    text = str(err)
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


class _ExactReader:
    """`read(n)` that waits for all n bytes (or EOF) from any file-like, and counts them.

    MCAP's record parser expects full reads; a raw socket or pipe returns what has arrived.
    """

    def __init__(self, raw: Any):
        self._raw = raw
        self.count = 0

    def read(self, n: int = -1) -> bytes:
        if n < 0:
            data = self._raw.read()
            self.count += len(data)
            return bytes(data)
        parts = []
        remaining = n
        while remaining > 0:
            part = self._raw.read(remaining)
            if not part:
                break
            parts.append(part)
            remaining -= len(part)
        data = b"".join(parts)
        self.count += len(data)
        return data
