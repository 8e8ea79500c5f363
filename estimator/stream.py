"""A live robot's messages in, its estimate out: the fixed-lag smoother fed as samples arrive.

    stream = Stream(config, Settings.from_config(config), lag_s=0.5)
    for raw in source:                       # RawMessage (estimator.io.logs), in arrival order
        stream.push(raw)                     # decoded, checked, buffered
        for update in stream.update():       # the knots that became ready, solved (or
                                             # update(min_knots=25): fewer, larger solves)
            update.estimate, update.newest, update.smoothed
    stream.close()                           # the end: the rest of the window, smoothed

Knots lie on a grid of step h from the first sample (commands excluded), as for a whole
log; solving starts once every mapped stream has spoken (a stream still silent `stale_s`
after the first is left out). Key k is ready once
every live stream has a sample at or after t_k: a stream whose newest sample is more than
`stale_s` behind the newest of all stops holding the knots back (a sensor that stopped), and
its samples older than the window are counted late and dropped. Latency is measured from the
arrival of the sample that made a knot ready to the update that publishes its newest estimate.

With `fit_softness = "first_window"` (the default) the contact softness is fitted on the
stream's first `fit_softness_s` as a batch estimate fits it on the log's (`run.
softness_fitted`), in a process of its own (`SoftnessFitJob`): the node publishes with the
model's own softness meanwhile, then re-solves its window with the fitted one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import ThreadpoolController

from estimator.config import Config, load_config
from estimator.diagnose.detect import DetectorSettings, Event
from estimator.diagnose.online import OnlineDetector
from estimator.diagnose.slip import OnlineSlips
from estimator.errors import ConfigError, LogError
from estimator.estimate import Estimate
from estimator.io.logs.measurements import (
    STREAM_COMPONENTS,
    BadSampleCounts,
    Measurement,
    Sample,
)
from estimator.io.logs.samples import SampleExtractor
from estimator.io.logs.source import RawMessage
from estimator.knots import MAX_KNOTS
from estimator.newest import NewestFilter
from estimator.problem import model_with_sensors
from estimator.run import WINDOW_MARGIN_NS, softness_fitted
from estimator.settings import Settings
from estimator.solver.fixed_lag import FixedLag, LagStep
from estimator.solver.incremental import RELINEARIZE_S, IncrementalLag
from physics.model import weight

# the most new keys one solve takes, as a fraction of the lag. Measured with whole-window
# updates (`--relinearize 0`), where a solve costs about as much for 10 new keys as for 50: at
# a quarter lag a live node fell behind for good (real rate on this 2-core machine, replayed
# as `benchmarks/stream_latency.py` does, two runs each: latency p50 2.1–3.5 s, p99 3.5–5.3
# s), at half a lag or a whole one it kept within 0.6–1.0 s (p99 1.1–2.0 s); Go2 replayed at
# --rate 0 through its 1.28 s mocap dropout, base 0.67 mm at half a lag, 0.40 at a quarter,
# 7.95 at a whole lag. An incremental update costs ~26 ms plus 5–6 ms per new key
# (humanoid_push): only a backlog reaches the bound
BACKLOG_STEP = 0.5


NEWEST = ("smoother", "filter")  # where a stream's newest estimate comes from (`Stream`)

# the filter runs beside the smoother's process and the source's reader: on this project's
# 2-core machines the two together did not keep up with quadruped_trot's 200 knots/s at its
# real rate (docs/streaming.md); where the node has cores to spare it publishes each knot in
# a few ms. The bound is a judgment, not measured (no machine here has 3 or 4 cores)
FILTER_CORES = 4


def newest_from(choice: str) -> str:
    """`stream --newest auto`: the filter where the machine has FILTER_CORES cores or more."""
    if choice != "auto":
        return choice
    return "filter" if (os.cpu_count() or 1) >= FILTER_CORES else "smoother"


# the samples the filter keeps before the key it steps from (each stream's last one before it
# is kept too: a held command, a pose to interpolate from)
FILTER_MARGIN_NS = 100_000_000
FILTER_STALE_PERIODS = 3.0  # (`Stream._stale_ns`)


# the process's BLAS, held to one thread while the solver runs beside MuJoCo's threads: on a
# busy machine a multithreaded OpenBLAS spin-waits (humanoid_push's incremental update with a
# second process busy: 44 ms on one BLAS thread, 167 ms on two, 109 of them in the Cholesky)
BLAS = ThreadpoolController()


@dataclass(frozen=True)
class Update:
    """What one solve publishes. estimate: the window's knots; newest / smoothed: indices
    into it (`LagStep`); latency_s: per newest knot, from the arrival of the sample that made
    it ready to now; backlog: knots ready and not yet solved when the solve started;
    relinearized: the keys whose rows the solve relinearized (a whole-window solve: all).
    With `Stream(newest="filter")` an update is either the filter's (`source` "filter": the
    newest knots, as soon as they are ready) or the smoother's (only smoothed knots; backlog
    and solve_s are its own)."""

    estimate: Estimate
    newest: range
    smoothed: range
    latency_s: list[float]
    backlog: int
    solve_s: float
    event: str = ""  # a divergence detected, and what was done
    events: list[Event] = field(default_factory=list)  # diagnostics (`Stream(diagnose=…)`)
    relinearized: int = 0
    at_ns: int = 0  # the smoother's newest knot when it was made (its events' time)
    source: str = "smoother"  # "filter": the newest knots of `Stream(newest="filter")`


@dataclass
class Counts:
    """The node's running counts, for the status line and the end of the run."""

    messages: int = 0  # messages pushed
    samples: int = 0  # accepted samples
    late: int = 0  # samples older than the window when they arrived (dropped)
    knots_newest: int = 0
    knots_smoothed: int = 0
    updates: int = 0
    divergences: int = 0
    events: list[str] = field(default_factory=list)


class _Buffer:
    """One stream's samples since the window's margin, appended in time order."""

    def __init__(self, name: str, kind: str) -> None:
        self.name, self.kind = name, kind
        self.t: list[int] = []
        self.log_t: list[int] = []
        self.values: list[np.ndarray] = []

    def add(self, s: Sample) -> None:
        self.t.append(s.t_ns)
        self.log_t.append(s.log_time_ns)
        self.values.append(s.values)

    def trim(self, before_ns: int) -> None:
        """Drop the samples before `before_ns`, keeping the last one before it (a held
        command)."""
        i = int(np.searchsorted(self.t, before_ns)) - 1
        if i > 0:
            del self.t[:i], self.log_t[:i], self.values[:i]


def _as_measurements(
    config: Config, buffers: Mapping[str, _Buffer], bad: Mapping[str, BadSampleCounts]
) -> dict[str, Measurement]:
    """Buffered samples as the batch reader's arrays."""
    out = {}
    for name, stream in config.streams.items():
        b = buffers[name]
        components = STREAM_COMPONENTS[stream.kind]
        values = (
            np.stack(b.values) if b.values else np.zeros((0, len(stream.elements), len(components)))
        )
        out[name] = Measurement(
            stream=name,
            kind=stream.kind,
            topic=stream.topic,
            element_type=stream.element_type,
            elements=stream.elements,
            components=components,
            t_ns=np.array(b.t, dtype=np.int64),
            log_time_ns=np.array(b.log_t, dtype=np.int64),
            values=values,
            bad=bad.get(name, BadSampleCounts()),
        )
    return out


class SoftnessFitJob:
    """The contact-softness fit of a stream's start (`run.softness_fitted` on the knots t_ns,
    as a batch estimate fits the log's start) in a Python process of its own, at a lower
    priority, so that the node keeps publishing meanwhile. `result()`: (the fitted settings,
    the fit) once it is done, a line saying why it failed, or None while it runs."""

    def __init__(
        self,
        config: Config,
        measurements: dict[str, Measurement],
        settings: Settings,
        t_ns: np.ndarray,
    ) -> None:
        self.folder = tempfile.TemporaryDirectory(prefix="physfuse_fit_")
        job = Path(self.folder.name)
        # (the config by its file: its streams are read-only mappings, which do not pickle)
        with (job / "in.pickle").open("wb") as f:
            pickle.dump((config.path, config.start_pose, measurements, settings, t_ns), f)
        # a fresh interpreter (not multiprocessing's spawn: that re-runs a user's script) on
        # one thread, MuJoCo's and BLAS's (`fit_job`: at the lowest priority)
        one = {"PHYSFUSE_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "from estimator.stream import fit_job; fit_job()",
                str(job),
                str(os.getpid()),  # (the node: `_end_with`)
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, **one},
        )
        self.started = time.perf_counter()
        self.took_s = 0.0
        self.out: tuple[Settings, dict[str, float]] | str | None = None

    def result(self, timeout: float | None = 0.0) -> tuple[Settings, dict[str, float]] | str | None:
        """Wait up to `timeout` s (None: until it is done)."""
        if self.out is not None:
            return self.out
        try:
            status = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            return None
        self.took_s = time.perf_counter() - self.started
        out = Path(self.folder.name) / "out.pickle"
        if out.exists():
            with out.open("rb") as f:
                self.out = pickle.load(f)
        else:  # (killed: out of memory, a signal)
            self.out = f"its process ended with status {status}"
        self.folder.cleanup()
        return self.out

    def cancel(self) -> None:
        self.process.kill()
        self.process.wait()
        self.folder.cleanup()


class SmootherJob:
    """The fixed-lag smoother of a `Stream(newest="filter")` in a Python process of its own
    (`smoother_job`, at a lower priority than the node's filter), fed the node's samples and
    sending back its updates with the smoothed knots only (and its diagnostics).

    Samples go out and updates come in through the process's stdin and stdout, pickled, each
    way on a thread of its own, so that the filter never waits for the pipe."""

    def __init__(
        self,
        config: Config,
        settings: Settings,
        lag_s: float,
        stale_s: float,
        diagnose: DetectorSettings | None,
        relinearize_s: float,
    ) -> None:
        one = {"PHYSFUSE_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "from estimator.stream import smoother_job; smoother_job()",
                str(os.getpid()),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env={**os.environ, **one},
        )
        self.outbox: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self.inbox: queue.Queue[tuple[str, Any]] = queue.Queue()
        # (the config by its file: its streams are read-only mappings, which do not pickle)
        start = (config.path, config.start_pose, settings, lag_s, stale_s, diagnose, relinearize_s)
        self.send(("start", start))
        threading.Thread(target=self._write, daemon=True).start()
        threading.Thread(target=self._read, daemon=True).start()
        self.done = False
        self.failure = ""  # why the process ended before it was closed

    def send(self, item: tuple[str, Any]) -> None:
        self.outbox.put(item)

    def wait_ready(self, timeout_s: float) -> None:
        """Wait until the process has started its smoother (its interpreter's imports take a
        second or two of a core: a node that took samples meanwhile would start behind)."""
        try:
            kind, payload = self.inbox.get(timeout=timeout_s)
        except queue.Empty:
            return
        if kind != "ready":
            self.inbox.put((kind, payload))  # (an error: `results` raises it)

    def _write(self) -> None:
        pipe = self.process.stdin
        assert pipe is not None
        with contextlib.suppress(BrokenPipeError, OSError):  # (the job ended: `_read` says why)
            while (item := self.outbox.get()) is not None:
                pickle.dump(item, pipe, protocol=pickle.HIGHEST_PROTOCOL)
                pipe.flush()

    def _read(self) -> None:
        pipe = self.process.stdout
        assert pipe is not None
        try:
            while True:
                self.inbox.put(pickle.load(pipe))
        except (EOFError, OSError, pickle.UnpicklingError):
            status = self.process.wait()
            self.inbox.put(("ended", f"the smoother's process ended with status {status}"))

    def results(self, timeout: float | None = 0.0) -> list[tuple[Update, dict]]:
        """The updates back so far (waiting up to `timeout` s for the first)."""
        out: list[tuple[Update, dict]] = []
        while not self.done:
            try:
                kind, payload = (
                    self.inbox.get(timeout=timeout) if not out else self.inbox.get_nowait()
                )
            except queue.Empty:
                break
            if kind == "update":
                out.append(payload)
            elif kind == "ready":
                continue
            elif kind in ("done", "ended", "error"):
                self.done = True
                if kind != "done":
                    self.failure = str(payload)
        return out

    def finish(self, timeout_s: float = 600.0) -> list[tuple[Update, dict]]:
        """Close the smoother's window and wait for its last updates."""
        self.send(("close", None))
        out: list[tuple[Update, dict]] = []
        deadline = time.perf_counter() + timeout_s
        while not self.done and time.perf_counter() < deadline:
            out += self.results(timeout=1.0)
        self.close()
        return out

    def close(self) -> None:
        self.outbox.put(None)
        if self.process.poll() is None:
            try:
                self.process.wait(5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def smoother_job() -> None:
    """The process of a `SmootherJob`: a `Stream(newest="smoother")` fed from stdin."""
    os.nice(5)  # (the node's filter first)
    parent = int(sys.argv[1])
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # (the pipe is the updates')
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()
    inbox: queue.Queue[tuple[str, Any]] = queue.Queue()

    def read() -> None:
        with contextlib.suppress(EOFError, OSError):
            while True:
                inbox.put(pickle.load(inp))
        inbox.put(("close", None))  # (the node is gone: end)

    def send(kind: str, payload: Any) -> None:
        pickle.dump((kind, payload), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        _, (path, start_pose, settings, lag_s, stale_s, diagnose, relinearize_s) = pickle.load(inp)
        config = dataclasses.replace(load_config(path), start_pose=start_pose)
        stream = Stream(
            config, settings, lag_s, stale_s, diagnose=diagnose, relinearize_s=relinearize_s
        )
        send("ready", None)
        threading.Thread(target=read, daemon=True).start()
        closing = False
        while not closing:
            items = [inbox.get()]
            while not inbox.empty():  # (all that came while it solved: one update for them)
                items.append(inbox.get_nowait())
            for kind, payload in items:
                if kind == "samples":
                    for sample, arrival in payload:
                        stream.push_sample(sample, arrival)
                closing = closing or kind == "close"
            updates = stream.close() if closing else stream.update()
            for update in updates:
                if len(update.smoothed) or update.events or update.event:
                    send("update", (_smoothed_only(update), _job_counts(stream)))
        send("done", _job_counts(stream))
    except (ConfigError, LogError) as err:
        send("error", str(err))
    except Exception as err:  # (one line back to the node)
        send("error", f"{type(err).__name__}: {err}")
    out.flush()
    os._exit(0)  # (the reader thread may be blocked on stdin: no interpreter shutdown)


def _smoothed_only(update: Update) -> Update:
    """The part of a smoother's update a filtered stream publishes: its smoothed knots."""
    sm = update.smoothed
    estimate = update.estimate.at(slice(sm.start, sm.stop))
    return replace(
        update, estimate=estimate, newest=range(0), smoothed=range(len(sm)), latency_s=[]
    )


def _job_counts(stream: Stream) -> dict[str, Any]:
    c = stream.counts
    return {"late": c.late, "divergences": c.divergences, "softness_fit": stream.softness_fit}


def _exit_with(parent: int) -> None:
    """A job's watchdog: end the process once the node that started it is gone."""
    while os.getppid() == parent:
        time.sleep(ORPHAN_POLL_S)
    os._exit(1)


ORPHAN_POLL_S = 0.5  # how often a fit's process checks that its node is still there


def _end_with(parent: int, job: Path) -> None:
    """A fit's watchdog: once the node that started it is gone (killed: nobody waits for the
    fit any more), remove the job's folder and end the process, not hold a core for nothing."""
    while os.getppid() == parent:
        time.sleep(ORPHAN_POLL_S)
    shutil.rmtree(job, ignore_errors=True)
    os._exit(1)


def fit_job() -> None:
    """The process of a `SoftnessFitJob`: its folder's in.pickle fitted into out.pickle."""
    os.nice(19)  # (the node's updates first)
    job = Path(sys.argv[1])
    threading.Thread(target=_end_with, args=(int(sys.argv[2]), job), daemon=True).start()
    with (job / "in.pickle").open("rb") as f:
        path, start_pose, measurements, settings, t_ns = pickle.load(f)
    out: tuple[Settings, dict[str, float]] | str
    try:
        config = dataclasses.replace(load_config(path), start_pose=start_pose)
        out = softness_fitted(config, measurements, settings, t_ns)
    except Exception as err:  # (one line back to the node, which keeps the model's softness)
        out = f"{type(err).__name__}: {err}"
    with (job / "out.partial").open("wb") as f:
        pickle.dump(out, f)
    (job / "out.partial").replace(job / "out.pickle")


class Stream:
    """The streaming estimator: samples in, fixed-lag estimates out (`estimator.solver.
    fixed_lag`).

    lag_s: how long a knot stays in the window before its estimate is final (smoothed).
    stale_s: a stream this far behind the newest sample stops holding knots back.
    relinearize_s: the newest knots whose rows each update relinearizes, the older ones kept
        linear (`estimator.solver.incremental`); 0: each update re-solves the whole window
        (`estimator.solver.fixed_lag`).
    clock: the time of arrival of a pushed message (seconds; `time.perf_counter`).
    diagnose: run the unmodeled-contact and slip detectors on the newest knots
        (`Update.events`; `estimator.diagnose.online`, `estimator.diagnose.slip`).
    newest: "smoother" — each update solves the ready knots and publishes the smoother's
        newest estimate of them; "filter" — the newest estimate of each ready knot comes from
        an EKF step (`estimator.newest`, a few ms), and the fixed-lag smoother runs in a
        process of its own (`SmootherJob`), whose smoothed knots (and diagnostics) come back
        in later updates.
    settings.fit_softness = "first_window" (and a config that does not give the softness):
        the softness fitted on the first fit_softness_s of knots (`SoftnessFitJob`; its
        result in `softness_fit`), the window re-solved with it once it is done.
    """

    def __init__(
        self,
        config: Config,
        settings: Settings,
        lag_s: float = 0.5,
        stale_s: float = 0.25,
        clock: Callable[[], float] = time.perf_counter,
        diagnose: DetectorSettings | None = None,
        relinearize_s: float = RELINEARIZE_S,
        newest: str = "smoother",
    ) -> None:
        if newest not in NEWEST:
            raise ConfigError(f"newest {newest!r}: expected one of {', '.join(NEWEST)}")
        self.config, self.settings, self.clock = config, settings, clock
        self.compiled = model_with_sensors(config)
        self.model = self.compiled[0]
        self.h = settings.h or float(self.model.opt.timestep)
        self.detector, self.slips = None, None
        # newest = "filter": the filter here, the smoother (and the detectors) in its process
        self.job = (
            SmootherJob(config, settings, lag_s, stale_s, diagnose, relinearize_s)
            if newest == "filter"
            else None
        )
        self.filter: NewestFilter | None = None
        self.filtered_until = -1  # the newest key the filter published
        self.filter_divergences = 0
        self.smoother_failed = False
        self.pending: list[tuple[Sample, float]] = []  # samples not yet sent to the job
        self.job_counts: dict[str, int] = {}
        if diagnose is not None and self.job is None:
            sigma_f = settings.contact_force_std * weight(self.model)
            self.detector = OnlineDetector(self.model, sigma_f, self.h, diagnose)
            self.slips = OnlineSlips(self.model, weight(self.model), self.h, diagnose)
        self.step_ns = round(self.h * 1e9)
        self.relinearize = round(relinearize_s / self.h)  # keys (0: whole solves)
        self.lag_knots = max(1, round(lag_s / self.h))
        self.backlog_step = max(1, round(BACKLOG_STEP * self.lag_knots))
        self.stale_ns = round(stale_s * 1e9)
        self.extractor = SampleExtractor(config, keep_times=False)
        self.buffers = {name: _Buffer(name, s.kind) for name, s in config.streams.items()}
        self.first_t: dict[str, int] = {}
        self.last_t: dict[str, int] = {}
        self.lag: FixedLag | None = None
        self.t0_ns: int | None = None  # the knots' grid: t0_ns + k h, once it has started
        self.ready_until = -1  # the newest ready key (global)
        self.solved_until = -1  # the newest key solved
        # (newest key readied, arrival of the sample that readied it), oldest first
        self.ready_marks: deque[tuple[int, float]] = deque()
        self.counts = Counts()
        # the contact-softness fit: every sample kept until the fit's knots are ready
        fits = (
            settings.fit_softness == "first_window"
            and settings.method == "physics"
            and not settings.sets_softness
            and self.job is None  # (the job's smoother fits it)
        )
        self.fit_keys = round(settings.fit_softness_s / self.h) if fits else 0
        self.fit_buffers = (
            {name: _Buffer(name, s.kind) for name, s in config.streams.items()} if fits else None
        )
        self.fit_job: SoftnessFitJob | None = None
        self.batch_iterations = Settings.from_config(config).max_iterations
        self.softness_fit: dict[str, float] = {}  # the fit, once applied
        self.pending_event = ""  # (reported with the next update)

    # -- in --------------------------------------------------------------------------------

    def push(self, raw: RawMessage, arrival: float | None = None) -> None:
        """One message as it arrived (decoded, checked and buffered; malformed ones counted
        in `bad_counts`)."""
        arrival = self.clock() if arrival is None else arrival
        for sample in self.decode(raw):
            self.push_sample(sample, arrival)

    def decode(self, raw: RawMessage) -> list[Sample]:
        """The samples of one message (`push` without buffering them: a reader thread can
        decode while the solver runs, and hand the samples to `push_sample`)."""
        self.counts.messages += 1
        return self.extractor.feed(raw)

    def push_sample(self, sample: Sample, arrival: float | None = None) -> None:
        """One decoded sample (a user's node that decodes its own messages)."""
        arrival = self.clock() if arrival is None else arrival
        if sample.stream not in self.buffers:
            raise ConfigError(
                f"a sample of stream {sample.stream!r}: not a stream of {self.config.path} "
                f"(its streams: {', '.join(self.buffers)})"
            )
        lag = self.lag
        if lag is not None and sample.t_ns < lag.t_ns(lag.first, lag.first + 1)[0]:
            self.counts.late += 1  # its knots have left the window
            return
        if self.job is not None:
            self.pending.append((sample, arrival))  # (the smoother's own checks there)
        self.counts.samples += 1
        self.buffers[sample.stream].add(sample)
        if self.fit_buffers is not None:
            self.fit_buffers[sample.stream].add(sample)
        self.first_t.setdefault(sample.stream, sample.t_ns)
        self.last_t[sample.stream] = sample.t_ns
        self._advance_ready(arrival)

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """newest = "filter": wait until the smoother's process is up (before taking samples)."""
        if self.job is not None:
            self.job.wait_ready(timeout_s)

    @property
    def bad_counts(self) -> Mapping[str, BadSampleCounts]:
        """Messages skipped per stream so far (malformed, out of order, ...)."""
        return self.extractor.bad_counts()

    # -- out -------------------------------------------------------------------------------

    def update(self, min_knots: int = 1) -> Iterator[Update]:
        """Solve the keys that became ready since the last update: one solve for all of
        them, or (a backlog) one per half lag of new keys (`BACKLOG_STEP`).
        min_knots: wait until at least this many keys are ready (fewer, larger solves:
        throughput for latency)."""
        if self.job is not None:
            yield from self._filtered(min_knots)
            yield from self._smoothed()
            return
        self._fit_softness()
        if self.ready_until - self.solved_until < min_knots:
            return
        while self.lag is not None and self.ready_until > self.solved_until:
            start = self.clock()
            backlog = self.ready_until - self.solved_until
            last = min(self.ready_until, self.solved_until + self.backlog_step)
            with BLAS.limit(limits=1, user_api="blas"):  # (as `batch.estimate`)
                step = self.lag.advance(self._measurements(), last)
            self.solved_until = last
            if step is not None:
                yield self._published(step, backlog, start)

    def close(self) -> Iterator[Update]:
        """The end of the stream: the samples held for their time check, a last update, and
        the window's remaining knots smoothed."""
        arrival = self.clock()
        for sample in self.extractor.flush():
            self.push_sample(sample, arrival)
        yield from self.update()
        if self.job is not None:
            self.job.send(("samples", self.pending))
            self.pending = []
            yield from self._smoothed(self.job.finish())
            return
        if self.fit_job is not None and self.fit_job.result() is None:
            self.fit_job.cancel()  # (the stream ended before its fit)
            event = (
                "the contact-softness fit was still running at the end of the stream: the "
                "model's own softness was used throughout"
            )
            self._report(event)
        if self.lag is None:
            return
        start = self.clock()
        with BLAS.limit(limits=1, user_api="blas"):
            step = self.lag.finish(self._measurements())
        self.lag.close()
        if step is not None:
            update = self._published(step, 0, start)
            if self.detector is not None and self.slips is not None:
                update.events.extend(self.detector.close() + self.slips.close())
            yield update

    # -- the contact softness ----------------------------------------------------------------

    def _fit_softness(self) -> None:
        """Start the fit once its knots are ready; apply it once it is done."""
        lag = self.lag
        if lag is None:
            return
        if self.fit_buffers is not None and self.ready_until >= self.fit_keys:
            measurements = _as_measurements(self.config, self.fit_buffers, self.bad_counts)
            # (solved as the batch solves, not with an update's few iterations)
            batch = replace(self.settings, max_iterations=self.batch_iterations)
            self.fit_job = SoftnessFitJob(
                self.config, measurements, batch, lag.t_ns(0, self.fit_keys)
            )
            self.fit_buffers = None
            self._report(
                f"fitting the contact softness on the stream's first {batch.fit_softness_s:g} s "
                "in a process of its own; the model's own until then"
            )
        job = self.fit_job
        out = None if job is None else job.result()
        if job is None or out is None:
            return
        self.fit_job = None
        if isinstance(out, str):
            event = f"the contact-softness fit failed ({out}): the model's own softness kept"
        else:
            fitted, fit = out
            self.settings = replace(
                self.settings,
                softness_eps_scale=fitted.softness_eps_scale,
                softness_kappa_scale=fitted.softness_kappa_scale,
                model_softness_std=fitted.model_softness_std,
            )
            self.softness_fit = fit
            lag.retune(self.settings, self.batch_iterations)
            event = (
                f"contact softness fitted on the stream's first {self.settings.fit_softness_s:g} "
                f"s in {job.took_s:.0f} s: ε × {fit['eps_scale']:.3f} ×/÷ "
                f"{1 + fit['eps_scale_sigma']:.3f}, κ × {fit['kappa_scale']:.3f} ×/÷ "
                f"{1 + fit['kappa_scale_sigma']:.3f}"
                f"{'' if fit.get('settled', 1.0) else ' (still moving when its rounds ran out)'}"
                "; the window re-solved with it"
            )
        self._report(event)

    def _report(self, event: str) -> None:
        """An event for the run's counts and the terminal (the next update's `event`)."""
        self.counts.events.append(event)
        self.pending_event = f"{self.pending_event}; {event}" if self.pending_event else event

    # -- the knot grid ---------------------------------------------------------------------

    def _advance_ready(self, arrival: float) -> None:
        tracked = {
            name: t for name, t in self.last_t.items() if self.buffers[name].kind != "command"
        }
        if not tracked:
            return
        newest = max(tracked.values())
        if self.t0_ns is None:
            self._start(newest)
            if self.t0_ns is None:
                return
        live = [t for name, t in tracked.items() if t >= newest - self._stale_ns(name)]
        ready = int((min(live) - self.t0_ns) // self.step_ns)
        if ready <= self.ready_until:
            return
        if ready - self.ready_until >= MAX_KNOTS:  # streams on different clocks, or a jump
            each = ", ".join(f"{name} {t / 1e9:.6g} s" for name, t in tracked.items())
            raise LogError(
                f"the streams' times jumped over {MAX_KNOTS:.0e} knots ({each}); are they on "
                "different clocks? Align them with a stream's time_offset_ns, or read the "
                'recorder\'s times with stamp = "log"'
            )
        self.ready_marks.append((ready, arrival))
        self.ready_until = ready

    def _stale_ns(self, name: str) -> int:
        """How far a stream may be behind the newest sample before it stops holding knots
        back: `stale_s`; for the filter, at most FILTER_STALE_PERIODS of the stream's own sample
        period (its mocap dropping out delays the newest estimate by that, not by stale_s; its
        samples that come after their key was filtered are the smoother's only)."""
        if self.job is None:
            return self.stale_ns
        t = self.buffers[name].t
        if len(t) < 2:
            return self.stale_ns
        period = (t[-1] - t[0]) / (len(t) - 1)
        return min(self.stale_ns, int(FILTER_STALE_PERIODS * period))

    def _start(self, newest: int) -> None:
        """The grid starts once every mapped stream (commands aside) has a sample, or
        `stale_s` after the first did: at the first sample, as `knot_grid` starts a log."""
        waiting = [
            name
            for name, b in self.buffers.items()
            if b.kind != "command" and name not in self.first_t
        ]
        earliest = min(t for n, t in self.first_t.items() if self.buffers[n].kind != "command")
        if waiting and newest - earliest < self.stale_ns:
            return
        if waiting:
            self.counts.events.append(
                f"started without {', '.join(waiting)} (silent {self.stale_ns / 1e9:g} s after "
                "the first stream)"
            )
        self.t0_ns = earliest
        if self.job is not None:
            self.filter = NewestFilter(self.config, self.settings, self.compiled, earliest, self.h)
        elif self.relinearize:
            self.lag = IncrementalLag(
                self.config,
                self.settings,
                self.compiled,
                earliest,
                self.lag_knots,
                self.relinearize,
            )
        else:
            self.lag = FixedLag(self.config, self.settings, self.compiled, earliest, self.lag_knots)

    def _arrival(self, key: int, default: float) -> float:
        """When the sample that readied `key` arrived (marks of keys before it are dropped:
        knots are published in order)."""
        marks = self.ready_marks
        while marks and marks[0][0] < key:
            marks.popleft()
        return marks[0][1] if marks else default

    # -- newest = "filter" ---------------------------------------------------------------------

    def _filtered(self, min_knots: int) -> Iterator[Update]:
        """The filter's step over the keys that became ready (samples on to the job first)."""
        job, nf = self.job, self.filter
        assert job is not None
        if self.pending:
            job.send(("samples", self.pending))
            self.pending = []
        if nf is None or self.ready_until - self.filtered_until < min_knots:
            return
        keep_from = int(nf.t_ns(self.filtered_until, self.filtered_until + 1)[0]) - FILTER_MARGIN_NS
        for b in self.buffers.values():
            b.trim(keep_from)
        measurements = _as_measurements(self.config, self.buffers, self.bad_counts)
        # one key at a time, each published as soon as it is done (the caller writes it
        # before the next is filtered)
        start = self.clock()
        with BLAS.limit(limits=1, user_api="blas"):
            for est in nf.steps(measurements, self.ready_until):
                key = int((est.t_ns[0] - nf.t0_ns) // nf.step_ns)
                now = self.clock()
                self.counts.knots_newest += 1
                self.counts.updates += 1
                event, self.pending_event = self.pending_event, ""
                yield Update(
                    est,
                    range(1),
                    range(0),
                    [now - self._arrival(key, now)],
                    self.ready_until - key,
                    now - start,
                    event,
                    at_ns=int(est.t_ns[0]),
                    source="filter",
                )
                start = self.clock()
        self.filtered_until = self.ready_until
        if nf.diverged:
            self.filter_divergences += 1
            self.counts.divergences += 1
            self._report(f"{nf.diverged}: the filter restarted from the measurements")

    def _smoothed(self, updates: list[tuple[Update, dict]] | None = None) -> Iterator[Update]:
        """The smoother's updates that came back from its process (one that failed: a line,
        and the newest estimate goes on)."""
        job = self.job
        assert job is not None
        back = job.results() if updates is None else updates
        if job.failure and not self.smoother_failed:
            self.smoother_failed = True
            self._report(
                f"the smoother stopped ({job.failure}): the newest estimate goes on, nothing "
                "more is smoothed"
            )
        for update, counts in back:
            c = self.counts
            c.knots_smoothed += len(update.smoothed)
            c.updates += 1
            c.late, c.divergences = counts["late"], counts["divergences"] + self.filter_divergences
            if update.event:
                c.events.append(update.event)
            self.softness_fit = counts.get("softness_fit", self.softness_fit)
            yield update

    def _measurements(self) -> dict[str, Measurement]:
        """The buffered samples around the window, as the batch reader's arrays."""
        assert self.lag is not None
        keep_from = int(self.lag.t_ns(self.lag.first, self.lag.first + 1)[0]) - WINDOW_MARGIN_NS
        for b in self.buffers.values():
            b.trim(keep_from)
        return _as_measurements(self.config, self.buffers, self.bad_counts)

    def _published(self, step: LagStep, backlog: int, start: float) -> Update:
        events = []
        if self.detector is not None and step.known_sigma is not None:
            events = self.detector.add(step.estimate, step.newest, step.known_sigma)
        if self.slips is not None:
            events += self.slips.add(step.estimate, step.newest)
        now = self.clock()
        latency = [now - self._arrival(step.first + i, now) for i in step.newest]
        c = self.counts
        c.updates += 1
        c.knots_newest += len(step.newest)
        c.knots_smoothed += len(step.smoothed)
        if step.diverged:
            c.divergences += 1
            assert self.lag is not None
            t = (step.estimate.t_ns[-1] - self.lag.t0_ns) / 1e9
            self._report(
                f"divergence {t:.3f} s into the stream: {step.diverged}; window reset from the "
                "measurements"
            )
        event, self.pending_event = self.pending_event, ""
        t = step.estimate.t_ns
        return Update(
            step.estimate,
            step.newest,
            step.smoothed,
            latency,
            backlog,
            now - start,
            event,
            events,
            step.relinearized,
            int(t[step.newest[-1]] if step.newest else t[-1]),
        )
