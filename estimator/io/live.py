"""Live sources and the replay server: MCAP byte streams from stdin, a TCP socket or a file
still being written, and a recording served at its own pace.

    for raw, arrival in messages("tcp://127.0.0.1:9000", stop):    # reconnects with backoff
        stream.push(raw, arrival)

    replay("recordings/humanoid_push.mcap", "tcp://127.0.0.1:9000", rate=1.0)

A source yields `RawMessage`s as their bytes arrive (`estimator.io.logs.source.open_stream`);
a TCP stream that breaks off mid-record or before its footer is reconnected with backoff
(0.1 s doubling to 2 s, for up to `reconnect_s` without a connection), one that ends with
its footer ends the source. The replay server writes each message as its own record and
flushes it (an unchunked MCAP), at its log time divided by `rate` after the first (rate 0:
as fast as the reader takes them).
"""

from __future__ import annotations

import contextlib
import io
import multiprocessing
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator
from pathlib import Path
from typing import IO, Any, NamedTuple, cast
from urllib.parse import urlsplit

from mcap.writer import Writer

from estimator.errors import LogError
from estimator.io.logs.source import RawMessage, open_log, open_stream, split_index
from estimator.io.mcap_writer import Positioned, Ros2Writer

BACKOFF_S = (0.1, 2.0)  # first and longest wait between connection attempts


def parse_address(spec: str, what: str) -> tuple[str, int]:
    """(host, port) of "tcp://HOST:PORT" (LogError naming `what` otherwise)."""
    url = urlsplit(spec)
    try:
        port = url.port
    except ValueError:
        port = None
    if url.scheme != "tcp" or port is None:
        raise LogError(f"{what} {spec!r}: expected tcp://HOST:PORT, ws://HOST:PORT, '-' or a file")
    return url.hostname or "127.0.0.1", port


def check_source(spec: str) -> None:
    """A source spec that cannot be one: LogError naming it (before anything starts)."""
    if spec == "-":
        return
    if spec.startswith(("ws://", "wss://")):
        return  # (a Foxglove WebSocket server: checked when it connects)
    if "://" in spec:
        parse_address(spec, "--source")
    elif not Path(spec).exists():
        raise LogError(
            f"--source {spec!r}: no such file (expected '-', tcp://HOST:PORT, ws://HOST:PORT "
            "or a file)"
        )


def messages(
    spec: str,
    stop: threading.Event,
    reconnect_s: float = 10.0,
    follow_s: float = 2.0,
    log: Callable[[str], None] = lambda line: print(line, file=sys.stderr),
    topics: Collection[str] = (),
    stdin: IO[bytes] | None = None,
) -> Iterator[tuple[RawMessage, float]]:
    """(message, arrival time on `time.perf_counter`) from a live source: "-" (stdin),
    "tcp://HOST:PORT" (a replay server, a robot's MCAP stream), "ws://HOST:PORT" (a
    `foxglove_bridge`: its channels on `topics`), or a file being written (followed until it
    has not grown for `follow_s`). `log` gets one line per connection event and per problem
    with the bytes."""
    if spec.startswith(("ws://", "wss://")):
        from estimator.io.foxglove import bridge_messages  # (it builds on this module)

        yield from bridge_messages(spec, topics, stop, reconnect_s, log)
        return
    if spec == "-":
        yield from _read(open_stream(stdin or sys.stdin.buffer, "<stdin>"), stop)
        return
    if spec.startswith("tcp://"):
        yield from _tcp(spec, stop, reconnect_s, log)
        return
    path = Path(spec)
    if not path.exists():
        raise LogError(
            f"source {spec!r}: no such file (expected '-', tcp://HOST:PORT, ws://HOST:PORT or "
            "a file)"
        )
    if path.is_dir():
        yield from _follow_folder(path, stop, follow_s, log)
        return
    yield from _follow_file(path, stop, follow_s, log)


def _follow_file(
    path: Path, stop: threading.Event, follow_s: float, log: Callable[[str], None]
) -> Iterator[tuple[RawMessage, float]]:
    """A file being written, to its footer or until it has not grown for `follow_s`."""
    with path.open("rb") as f:
        source = open_stream(cast(IO[bytes], _Growing(f, follow_s, stop)), str(path))
        yield from _read(source, stop)
        for line in source.warnings:
            if source.truncated and "no footer" in line:
                continue  # (a recording still open, or stopped: its end is here)
            log(line)


def _follow_folder(
    folder: Path, stop: threading.Event, follow_s: float, log: Callable[[str], None]
) -> Iterator[tuple[RawMessage, float]]:
    """A rosbag2 folder being recorded: its split files (`name_0.mcap`, `name_1.mcap`, ...)
    in order, each followed to its footer (the recorder closes a split before it opens the
    next) or until it has not grown for `follow_s` and no later split has appeared."""
    done: set[Path] = set()
    waited = time.monotonic()
    while not stop.is_set():
        splits = [p for p in sorted(folder.glob("*.mcap"), key=split_index) if p not in done]
        if not splits:
            if time.monotonic() - waited > follow_s:
                return
            time.sleep(0.02)
            continue
        done.add(splits[0])
        yield from _follow_file(splits[0], stop, follow_s, log)
        waited = time.monotonic()


def _read(
    source: Iterable[RawMessage], stop: threading.Event
) -> Iterator[tuple[RawMessage, float]]:
    for raw in source:
        yield raw, time.perf_counter()
        if stop.is_set():
            return


def _tcp(
    spec: str, stop: threading.Event, reconnect_s: float, log: Callable[[str], None]
) -> Iterator[tuple[RawMessage, float]]:
    host, port = parse_address(spec, "source")
    retry = Reconnect(spec, reconnect_s, log)
    while not stop.is_set():
        try:
            sock = socket.create_connection((host, port), timeout=1.0)
        except OSError as err:
            if retry.failed(err):
                continue
            return
        sock.settimeout(None)
        log(f"source {spec}: connected")
        retry.succeeded()
        with sock, sock.makefile("rb") as f:
            source = open_stream(f, spec)
            try:
                yield from _read(source, stop)
            except (OSError, LogError) as err:  # reset by the peer, or not an MCAP stream
                source.warn(f"{spec}: {err}", truncated=True)
        for line in source.warnings:
            log(f"source {line}")
        if not source.truncated:  # the stream ended with its footer: the end of the run
            return
        log(f"source {spec}: disconnected mid-stream; reconnecting")
        retry.lost()


def source_error(err: LogError | OSError) -> str:
    """The one line a reader reports for a source it cannot read."""
    if isinstance(err, LogError):
        return str(err)
    where = f"{err.filename}: " if err.filename else ""
    return f"{where}{err.strerror or err}"


class RawReader:
    """A live source read on a thread of the node's process, its messages left for the node
    to decode (`Stream.push`): where the node's process runs only the filter
    (`stream --newest filter`), decoding there costs less than the process of
    `DecodingReader` and its queue. Items on `queue`, in order:

        ("raw", RawMessage, arrival)   one message as it arrived
        ("log", line)                  a source event (connected, cut off, ...)
        ("error", line)                the source cannot be read (then "end")
        ("end",)
    """

    def __init__(self, topics: Collection[str], source: str, reconnect_s: float) -> None:
        self.queue: queue.Queue[tuple] = queue.Queue()
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=self._read, args=(list(topics), source, reconnect_s), daemon=True
        )
        self.thread.start()

    def _read(self, topics: list[str], source: str, reconnect_s: float) -> None:
        out = self.queue
        try:
            for raw, arrival in messages(
                source,
                self.stop,
                reconnect_s,
                log=lambda line: out.put(("log", line)),
                topics=topics,
            ):
                out.put(("raw", raw, arrival))
        except (LogError, OSError) as err:
            out.put(("error", source_error(err)))
        finally:
            out.put(("end",))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=1.0)  # (a thread blocked on a quiet source: it is a daemon)


class DecodingReader:
    """A live source read and decoded in a process of its own: decoding and checking a
    message takes about 0.4 ms of Python, which in a thread would take the GIL from the
    solver (measured: its updates 1.7× slower). Items on `queue`, in order:

        ("samples", [Sample, ...], arrival)   one message's accepted samples
        ("counts", messages, {stream: BadSampleCounts})   about every 0.5 s, and at the end
        ("log", line)                          a source event (connected, cut off, ...)
        ("error", line)                        the source cannot be read (then "end")
        ("end",)
    """

    def __init__(self, config_path: str | Path, source: str, reconnect_s: float) -> None:
        context = multiprocessing.get_context("fork")  # (stdin and the config, as they are)
        self.queue: Any = context.Queue()
        self.stop = context.Event()
        stdin = os.dup(0) if source == "-" else None
        self.process = context.Process(
            target=_decode,
            args=(str(config_path), source, reconnect_s, self.queue, self.stop, stdin),
            daemon=True,
        )
        self.process.start()
        if stdin is not None:
            os.close(stdin)

    def close(self) -> None:
        self.stop.set()
        self.process.join(timeout=1.0)
        if self.process.is_alive():  # (blocked on a quiet source)
            self.process.terminate()
            self.process.join(timeout=5.0)


def _decode(
    config_path: str,
    source: str,
    reconnect_s: float,
    out: Any,
    stop: Any,
    stdin_fd: int | None,
) -> None:
    """The decoding process (`DecodingReader`)."""
    from estimator.config import load_config
    from estimator.io.logs.samples import SampleExtractor

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (the node ends it)
    parent = os.getppid()
    config = load_config(config_path)
    extractor = SampleExtractor(config, keep_times=False)
    topics = [s.topic for s in config.streams.values()]
    stdin = os.fdopen(stdin_fd, "rb") if stdin_fd is not None else None
    count, reported = 0, time.monotonic()
    try:
        for raw, arrival in messages(
            source,
            stop,
            reconnect_s,
            log=lambda line: out.put(("log", line)),
            topics=topics,
            stdin=stdin,
        ):
            count += 1
            samples = extractor.feed(raw)
            if samples:
                out.put(("samples", samples, arrival))
            if time.monotonic() - reported > 0.5:
                reported = time.monotonic()
                out.put(("counts", count, extractor.bad_counts()))
                if os.getppid() != parent:  # the node is gone
                    return
        out.put(("samples", extractor.flush(), time.perf_counter()))
    except (LogError, OSError) as err:
        out.put(("error", source_error(err)))
    finally:
        out.put(("counts", count, extractor.bad_counts()))
        out.put(("end",))


class Reconnect:
    """When to try a source again: after 0.1 s, doubling to 2 s (`BACKOFF_S`), until
    `reconnect_s` have passed since the last connection; a source that never connected is
    then an error (LogError), one that did has ended."""

    def __init__(self, spec: str, reconnect_s: float, log: Callable[[str], None]) -> None:
        self.spec, self.reconnect_s, self.log = spec, reconnect_s, log
        self.wait, self.since, self.connected = BACKOFF_S[0], time.monotonic(), False

    def failed(self, err: Exception) -> bool:
        """A connection attempt failed: True (after the wait) to try again, False to stop."""
        if time.monotonic() - self.since > self.reconnect_s:
            line = f"source {self.spec}: no connection for {self.reconnect_s:g} s ({err})"
            if not self.connected:  # nothing ever came: the source is wrong
                raise LogError(line) from None
            self.log(f"{line}; giving up")
            return False
        time.sleep(self.wait)
        self.wait = min(2 * self.wait, BACKOFF_S[1])
        return True

    def succeeded(self) -> None:
        self.connected, self.wait = True, BACKOFF_S[0]

    def lost(self) -> None:
        """The connection dropped: the time to give up counts from now."""
        self.since = time.monotonic()


class _Growing(io.RawIOBase):
    """A file still being written, read as a stream: at its end, wait for more bytes until
    it has not grown for `idle_s` (or `stop` is set)."""

    def __init__(self, f: IO[bytes], idle_s: float, stop: threading.Event) -> None:
        self.f, self.idle_s, self.stop = f, idle_s, stop

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        last = time.monotonic()
        while True:
            data = self.f.read(n)
            if data or self.stop.is_set() or time.monotonic() - last > self.idle_s:
                return data
            time.sleep(0.01)


# -- the estimate as a live MCAP byte stream ---------------------------------------------------


class McapStreamServer:
    """A `MessageSink` serving the estimate as an unchunked MCAP byte stream to every client
    that connects to "tcp://HOST:PORT" (port 0: any free one, `port`): each client gets its
    own stream from the moment it connects (header, then each topic's channel on first use);
    a client that goes away is dropped."""

    def __init__(self, address: str) -> None:
        host, port = parse_address(address, "--publish")
        self.server = socket.create_server((host, port))
        self.port = self.server.getsockname()[1]
        self.clients: list[_Client] = []
        self.lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:  # closed
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            out = conn.makefile("wb")
            with self.lock:
                self.clients.append(_Client(conn, out, Ros2Writer(out, chunked=False)))

    def write(self, topic: str, msg_type: str, fields: Any, log_time_ns: int, **qos: Any) -> None:
        self._each(lambda c: c.writer.write(topic, msg_type, fields, log_time_ns, **qos))

    def add_metadata(self, name: str, data: Any) -> None:
        """(A client that connects later would not get it: the file keeps it.)"""

    def flush(self) -> None:
        self._each(lambda c: c.writer.flush())

    def finish(self) -> None:
        self.server.close()
        self._each(lambda c: c.writer.finish())
        with self.lock:
            for client in self.clients:
                client.close()
            self.clients.clear()

    def _each(self, do: Callable[[_Client], None]) -> None:
        with self.lock:
            for client in list(self.clients):
                try:
                    do(client)
                except OSError:  # the client went away
                    self.clients.remove(client)
                    client.close()


class _Client(NamedTuple):
    conn: socket.socket
    out: IO[bytes]
    writer: Ros2Writer

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.out.close()
        self.conn.close()


# -- the replay server ------------------------------------------------------------------------


def replay(
    log_path: str | Path,
    to: str,
    rate: float = 1.0,
    ready: Callable[[int], None] | None = None,
    topics: list[str] | None = None,
) -> int:
    """Serve a recording as a live MCAP byte stream at `rate` × its pace: to "-" (stdout) or
    "tcp://HOST:PORT" (listens; serves the first client that connects; port 0: any free
    one, passed to `ready`). Returns the messages sent."""
    if to == "-":
        return _send(log_path, sys.stdout.buffer, rate, topics)
    host, port = parse_address(to, "--to")
    with socket.create_server((host, port)) as server:
        if ready is not None:
            ready(server.getsockname()[1])
        conn, _ = server.accept()
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with conn.makefile("wb") as out:
                try:
                    return _send(log_path, out, rate, topics)
                except (BrokenPipeError, ConnectionResetError):
                    return 0


def _send(log_path: str | Path, out: IO[bytes], rate: float, topics: list[str] | None) -> int:
    return send(open_log(log_path, topics=topics), out, rate)


def send(messages: Iterable[RawMessage], out: IO[bytes], rate: float = 0.0) -> int:
    """Write messages to `out` as an unchunked MCAP stream, each flushed as it is written, at
    their log times divided by `rate` after the first (0: at once); returns the count."""
    writer = Writer(cast(IO[bytes], Positioned(out)), use_chunking=False)
    writer.start(profile="ros2", library="physfuse replay")
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    start_wall: float | None = None
    start_log = 0
    sent = 0
    for raw in messages:
        if start_wall is None:
            start_wall, start_log = time.perf_counter(), raw.log_time_ns
        if rate > 0:
            due = start_wall + (raw.log_time_ns - start_log) / 1e9 / rate
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        channel = channels.get(raw.topic)
        if channel is None:
            schema = 0
            if raw.schema is not None:
                schema = schemas.get(raw.msg_type) or writer.register_schema(
                    raw.schema.name, raw.schema.encoding, raw.schema.data
                )
                schemas[raw.msg_type] = schema
            channel = channels[raw.topic] = writer.register_channel(
                raw.topic, raw.message_encoding, schema
            )
        writer.add_message(channel, raw.log_time_ns, raw.data, raw.log_time_ns)
        out.flush()
        sent += 1
    writer.finish()
    out.flush()
    return sent
