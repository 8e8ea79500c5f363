"""`physfuse stream`: estimate a live robot as its messages arrive (fixed-lag smoothing).

    physfuse replay recordings/humanoid_push.mcap --to tcp://127.0.0.1:9000 &
    physfuse stream --config configs/humanoid_push.toml --source tcp://127.0.0.1:9000 \\
        --out out/live.mcap

A reader process takes messages off the source and decodes them as they arrive
(`DecodingReader`: the decoding's Python does not take the GIL from the solver); the main
process buffers the samples in the `Stream` and solves whatever knots are ready whenever it
is free, so that a slow solve takes more knots next time instead of falling behind message
by message. Every
update writes the newest knots under `/estimate/...` and the knots that left the lag under
`/estimate_smoothed/...`, and flushes: the file reads back up to the last update even if
the process is killed. SIGINT and SIGTERM end the run with the window smoothed and the
file closed.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import sys
import threading
import time
import uuid
from collections import deque
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from estimator.cli.estimate import add_start_pose_argument
from estimator.config import load_config
from estimator.diagnose.detect import DetectorSettings
from estimator.diagnose.report import event_dict, message, write_event
from estimator.errors import ConfigError, LogError
from estimator.io.live import DecodingReader, McapStreamServer, RawReader, check_source
from estimator.io.logs.measurements import BadSampleCounts
from estimator.io.mcap_writer import EstimateWriter
from estimator.model_checks import check_for_estimate
from estimator.settings import Settings
from estimator.solver.incremental import RELINEARIZE_S
from estimator.stream import FILTER_CORES, NEWEST, Stream, Update, newest_from

STATUS_EVERY_S = 1.0
SMOOTHED_PREFIX = "/estimate_smoothed"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, required=True, help="TOML config (configs/)")
    parser.add_argument(
        "--source",
        required=True,
        help="- (an MCAP byte stream on stdin), tcp://HOST:PORT (a replay or a robot's MCAP "
        "stream; reconnected when it breaks off), ws://HOST:PORT (a robot's foxglove_bridge) "
        "or an MCAP file still being written",
    )
    parser.add_argument(
        "--lag", type=float, default=0.5, metavar="S", help="fixed lag, s (default 0.5)"
    )
    parser.add_argument("--out", type=Path, help="MCAP file of the estimate (newest and smoothed)")
    parser.add_argument(
        "--publish",
        metavar="SINK",
        help="the estimate as a live MCAP byte stream: - (standard output) or tcp://HOST:PORT "
        "(served to every client that connects; port 0: any free one)",
    )
    parser.add_argument(
        "--rerun",
        metavar="spawn|serve|FILE.rrd",
        help="the estimate live in Rerun: a native viewer (spawn), a web viewer on localhost "
        "(serve), or a recording file that grows with the run",
    )
    parser.add_argument(
        "--bridge-publish",
        metavar="ws://HOST:PORT",
        help="publish the estimate into the robot's ROS 2 graph through its foxglove_bridge "
        "(which must offer clientPublish): Odometry, JointState, WrenchStamped, AccelStamped",
    )
    parser.add_argument(
        "--foxglove",
        type=int,
        metavar="PORT",
        help="serve the estimate live on a Foxglove WebSocket server on PORT (0: any free one)",
    )
    parser.add_argument(
        "--newest",
        choices=("auto", *NEWEST),
        default="auto",
        help="where the newest estimate of each knot comes from: filter (an EKF step as soon as "
        "the knot is ready, the smoother in a process of its own), smoother (each update of the "
        f"fixed-lag smoother publishes its newest knots) or auto (default: filter on a machine "
        f"with {FILTER_CORES} cores or more, else smoother)",
    )
    parser.add_argument(
        "--iterations",
        type=int,
        default=2,
        help="iterations per update: Gauss–Newton steps on the newest knots (Levenberg–"
        "Marquardt on the whole window with --relinearize 0) (default 2)",
    )
    parser.add_argument(
        "--relinearize",
        type=float,
        default=RELINEARIZE_S,
        metavar="S",
        help="relinearize the rows of the newest S seconds of knots at each update and keep "
        "the older ones linear (incremental, iSAM2-like); 0: re-solve the whole window at "
        f"each update (default {RELINEARIZE_S:g})",
    )
    parser.add_argument(
        "--fit-softness",
        choices=("first_window", "none"),
        help="first_window: fit the contact softness on the stream's first fit_softness_s "
        "(2 s) as `physfuse estimate` fits it on a log's, in a process of its own, publishing "
        "with the model's own meanwhile, then re-solve the window with it; none: the model's "
        "own throughout (default: the config's fit_softness, first_window unless it gives the "
        "softness)",
    )
    parser.add_argument(
        "--stale",
        type=float,
        default=0.25,
        metavar="S",
        help="a stream this far behind the others stops holding knots back, s (default 0.25)",
    )
    parser.add_argument(
        "--reconnect",
        type=float,
        default=10.0,
        metavar="S",
        help="give up on a TCP source after S s without a connection (default 10)",
    )
    parser.add_argument(
        "--diagnose",
        action="store_true",
        help="detect unmodeled contacts and slips online on the newest knots "
        "(docs/diagnostics.md): each "
        "event reported when confirmed and again, final, when it ends, on /diagnostics and "
        "/diagnostics/events and in the terminal",
    )
    parser.add_argument(
        "--false-alarms-per-min",
        type=float,
        default=1.0,
        metavar="RATE",
        help="--diagnose: the target false-alarm rate that sets the threshold (default 1)",
    )
    parser.add_argument(
        "--stats",
        type=Path,
        help="JSON of the run: latencies, backlog, solve times, keys relinearized, counts",
    )
    add_start_pose_argument(parser)
    parser.add_argument("--quiet", action="store_true", help="no status line")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.start_pose is not None:
        config = config.starting_at(*args.start_pose)
    if args.lag <= 0 or args.stale <= 0 or args.iterations < 1 or args.relinearize < 0:
        raise ConfigError(
            "--lag and --stale must be > 0 s, --relinearize ≥ 0 s and --iterations ≥ 1"
        )
    if args.false_alarms_per_min <= 0:
        raise ConfigError(f"--false-alarms-per-min {args.false_alarms_per_min}: must be > 0")
    settings = replace(Settings.from_config(config), max_iterations=args.iterations)
    if args.fit_softness is not None:
        settings = replace(settings, fit_softness=args.fit_softness)
    check_for_estimate(config, settings)
    check_source(args.source)
    if args.out is not None and not args.out.parent.is_dir():
        raise LogError(f"--out {args.out}: no such folder {args.out.parent}")
    detector = DetectorSettings(false_alarms_per_min=args.false_alarms_per_min)
    stream = Stream(
        config,
        settings,
        lag_s=args.lag,
        stale_s=args.stale,
        diagnose=detector if args.diagnose else None,
        relinearize_s=args.relinearize,
        newest=newest_from(args.newest),
    )
    model = config.load_model()
    imu_sites = {s.name: s.elements[0] for s in config.streams.values() if s.kind == "imu"}
    run_id = str(uuid.uuid4())
    # (a viewer that cannot open: before the rest)
    rerun = _Rerun(args.rerun, model, run_id, args.diagnose)
    sinks = []  # (live ones first: one that cannot start leaves no file behind)
    if args.publish == "-":
        sinks.append(
            EstimateWriter(
                sys.stdout.buffer, model, config.model_ref, stream.h, run_id, chunked=False
            )
        )
    elif args.publish is not None:
        server = McapStreamServer(args.publish)
        sinks.append(EstimateWriter(server, model, config.model_ref, stream.h, run_id))
        host = args.publish.rsplit(":", 1)[0]
        print(f"physfuse stream: publishing the estimate on {host}:{server.port}", file=sys.stderr)
    if args.bridge_publish is not None:
        from estimator.io.foxglove import BridgePublisher

        bridge = BridgePublisher(args.bridge_publish)
        sinks.append(EstimateWriter(bridge, model, config.model_ref, stream.h, run_id))
    if args.foxglove is not None:
        from estimator.io.foxglove import FoxgloveSink  # (foxglove-sdk only when asked for)

        live = FoxgloveSink(args.foxglove)
        sinks.append(EstimateWriter(live, model, config.model_ref, stream.h, run_id))
        print(f"physfuse stream: serving the estimate on ws://0.0.0.0:{live.port}", file=sys.stderr)
    if args.out is not None:
        sinks.append(
            EstimateWriter(args.out, model, config.model_ref, stream.h, run_id, chunked=False)
        )
    status = Status(args.quiet)
    stream.wait_ready()  # (the smoother's process up before the source is read)
    # (the filter's process decodes for itself; the smoother's node in a process of its own)
    reader: RawReader | DecodingReader = (
        RawReader({s.topic for s in config.streams.values()}, args.source, args.reconnect)
        if stream.job is not None
        else DecodingReader(args.config, args.source, args.reconnect)
    )
    previous = signal.signal(signal.SIGTERM, _interrupt)
    interrupted = False
    later: deque[Update] = deque()  # smoothed knots to write between the newest ones
    try:
        done = False
        while not done:
            try:
                done = _drain(reader.queue, stream, status, wait=not later)
                status.queued.append(reader.queue.qsize())
                for update in stream.update():
                    status.add(update, stream)
                    if update.source == "filter" or stream.job is None:
                        _write(sinks, update, imu_sites, stream)
                        rerun.log(update, stream)
                    else:
                        later.extend(_pieces(update))
                if later:  # (a piece at a time: the next newest knots wait for no more)
                    _write(sinks, later[0], imu_sites, stream)
                    rerun.log(later.popleft(), stream)
                status.show(stream)
            except KeyboardInterrupt:
                interrupted = True
                break
    finally:
        reader.close()
        signal.signal(signal.SIGTERM, previous)
        try:
            for update in later:  # (added to the status when it came)
                _write(sinks, update, imu_sites, stream)
                rerun.log(update, stream)
            for update in stream.close():
                status.add(update, stream)
                _write(sinks, update, imu_sites, stream)
                rerun.log(update, stream)
        finally:
            for sink in sinks:
                sink.close()
            rerun.close()
    status.show(stream, final=True)
    if args.stats is not None:
        args.stats.write_text(json.dumps(status.report(stream), indent=2) + "\n")
    if not status.error and stream.counts.samples == 0 and not interrupted:
        topics = ", ".join(sorted({s.topic for s in config.streams.values()}))
        status.error = (
            f"no message on the config's topics ({topics}) came from {args.source} "
            f"({status.messages} messages on other topics)"
        )
    if status.error:
        print(f"physfuse stream: error: {status.error}", file=sys.stderr)
        return 2
    return 130 if interrupted else 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _drain(inbox: Any, stream: Stream, status: Status, wait: bool = True) -> bool:
    """Buffer every message waiting (waiting up to 50 ms for the first, unless not `wait`);
    True at the end."""
    try:
        item = inbox.get(timeout=0.05) if wait else inbox.get_nowait()
    except queue.Empty:
        return False
    while True:
        kind = item[0]
        if kind == "end":
            return True
        if kind == "raw":  # (RawReader: decoded here)
            samples = stream.decode(item[1])
            for sample in samples:
                stream.push_sample(sample, item[2])
            status.received += bool(samples)
            status.messages = stream.counts.messages
            status.decoded_here = True
        elif kind == "samples":
            for sample in item[1]:
                stream.push_sample(sample, item[2])
            status.received += 1
        elif kind == "counts":  # (decoded in the reader process)
            status.messages, status.bad = item[1], item[2]
            stream.counts.messages = item[1]
        elif kind == "log":
            status.log(item[1])
        elif kind == "error":
            status.error = item[1]
        try:
            item = inbox.get_nowait()
        except queue.Empty:
            return False


# smoothed knots written between two newest ones (a smoother's update brings up to half a lag
# of them: ~2 ms each on the humanoid)
PIECE_KNOTS = 4


def _pieces(update: Update) -> list[Update]:
    """A smoother's update as pieces of PIECE_KNOTS smoothed knots (its events with the first)."""
    n = len(update.smoothed)
    out = []
    for i in range(0, max(n, 1), PIECE_KNOTS):
        j = min(i + PIECE_KNOTS, n)
        out.append(
            replace(
                update,
                estimate=update.estimate.at(
                    slice(update.smoothed.start + i, update.smoothed.start + j)
                ),
                smoothed=range(j - i),
                newest=range(0),
                events=update.events if i == 0 else [],
            )
        )
    return out


def _write(
    sinks: list[EstimateWriter], update: Update, imu_sites: dict[str, str], stream: Stream
) -> None:
    for sink in sinks:
        sink.write(update.estimate, update.newest, imu_sites)
        sink.write(update.estimate, update.smoothed, imu_sites, prefix=SMOOTHED_PREFIX)
        for e in update.events:  # at the smoother's newest knot: when it was reported
            assert stream.t0_ns is not None
            write_event(sink.writer, e, stream.t0_ns, update.at_ns)
        sink.flush()


class _Rerun:
    """`--rerun`: the Rerun recording (its time origin the stream's first knot): each
    update's newest knots, then its smoothed ones over them."""

    def __init__(self, to: str | None, model: Any, run_id: str, diagnose: bool) -> None:
        self.live: Any = None
        if to is not None:
            from estimator.io.rerun import LiveRecording  # (Rerun only when asked for)

            self.live = LiveRecording(model, to, run_id, diagnose=diagnose)

    def log(self, update: Update, stream: Stream) -> None:
        if self.live is not None and stream.t0_ns is not None:
            self.live.log(update.estimate, update.newest, stream.t0_ns)
            self.live.log(update.estimate, update.smoothed, stream.t0_ns)
            self.live.log_events(update.events)

    def close(self) -> None:
        if self.live is not None:
            self.live.close()


class Status:
    """The terminal's status line and the run's statistics (`--stats`)."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.start = time.perf_counter()
        self.last_shown = self.start
        self.received = 0  # messages with samples
        self.messages = 0  # every message read
        self.bad: dict[str, BadSampleCounts] = {}  # skipped, per stream (the decoder's)
        self.decoded_here = False  # (RawReader: the stream's own counts)
        self.latency: list[float] = []
        self.backlog: list[int] = []
        self.solve: list[float] = []
        # newest = "filter": the smoother's updates (in its own process)
        self.smoother_backlog: list[int] = []
        self.smoother_solve: list[float] = []
        self.relinearized: list[int] = []  # keys whose rows each smoother update relinearized
        self.queued: list[int] = []  # messages waiting when the solver took the ready knots
        self.recent: deque[float] = deque(maxlen=500)
        self.lines: deque[str] = deque(maxlen=3)  # the latest source events and warnings
        self.events: list[dict[str, Any]] = []  # --diagnose: every report (event_dict)
        self.error = ""
        self.lock = threading.Lock()

    def log(self, line: str) -> None:
        with self.lock:
            self.lines.append(line)
        if not self.quiet:
            print(f"physfuse stream: {line}", file=sys.stderr)

    def add(self, update: Update, stream: Stream) -> None:
        self.latency += update.latency_s
        self.recent.extend(update.latency_s)
        if update.source == "filter" or stream.job is None:  # (the newest knots')
            self.backlog.append(update.backlog)
            self.solve.append(update.solve_s)
        else:
            self.smoother_backlog.append(update.backlog)
            self.smoother_solve.append(update.solve_s)
        if update.source == "smoother":
            self.relinearized.append(update.relinearized)
        if update.event:
            self.log(update.event)
        for e in update.events:
            assert stream.t0_ns is not None
            self.events.append(event_dict(e, stream.t0_ns))
            at = (e.start_ns - stream.t0_ns) / 1e9
            self.log(f"{'event' if e.ongoing else 'event ended'} at {at:.3f} s: {message(e)}")

    def show(self, stream: Stream, final: bool = False) -> None:
        now = time.perf_counter()
        if self.quiet or (not final and now - self.last_shown < STATUS_EVERY_S):
            return
        self.last_shown = now
        c = stream.counts
        wall = max(now - self.start, 1e-9)
        if self.decoded_here:
            self.bad = dict(stream.bad_counts)
        bad = sum(b.total for b in self.bad.values())
        p50, p99 = (np.percentile(self.recent, (50, 99)) * 1e3) if self.recent else (np.nan,) * 2
        line = (
            f"in {self.messages / wall:.0f} msg/s, out {c.knots_newest / wall:.0f} knots/s | "
            f"latency p50 {p50:.0f} ms p99 {p99:.0f} ms | backlog "
            f"{self.backlog[-1] if self.backlog else 0} knots, "
            f"{self.queued[-1] if self.queued else 0} messages | late {c.late} bad {bad} | "
            f"divergences {c.divergences}"
        )
        print(("done: " if final else "") + line, file=sys.stderr)

    def report(self, stream: Stream) -> dict[str, Any]:
        lat = np.array(self.latency)
        return {
            "wall_s": time.perf_counter() - self.start,
            "messages": self.messages,
            "messages_with_samples": self.received,
            "latency_s": self.latency,
            "latency_p50_s": float(np.percentile(lat, 50)) if len(lat) else None,
            "latency_p99_s": float(np.percentile(lat, 99)) if len(lat) else None,
            "backlog": self.backlog,
            "queued": self.queued,
            "solve_s": self.solve,
            "smoother_backlog": self.smoother_backlog,
            "smoother_solve_s": self.smoother_solve,
            "relinearized": self.relinearized,
            "counts": asdict(stream.counts),
            "bad": {
                name: b.as_dict()
                for name, b in (stream.bad_counts if self.decoded_here else self.bad).items()
            },
            "knot_s": stream.h,
            "events": self.events,
            "softness_fit": stream.softness_fit,  # (empty: none applied)
        }
