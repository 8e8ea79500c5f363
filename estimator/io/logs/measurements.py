"""What reading a log produces: per-stream samples and arrays, bad-sample counts, topic stats.

Conventions: times are int64 nanoseconds; a stream's values have shape (N, E, K) — N samples,
E model elements (`elements`, the config's order), K components (`components`); quaternions
are (w, x, y, z); NaN marks a field the message did not carry (a joint missing from a
JointState, an IMU without orientation), and `mask` is its complement.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields, replace

import numpy as np

from estimator.config import Config, StreamConfig
from estimator.io.logs.decode import IMU, JOINT, POINT, POSE, SCALAR, WRENCH

# Components (the K axis) of each stream kind's values.
STREAM_COMPONENTS: Mapping[str, tuple[str, ...]] = {
    "pose": POSE,
    "tf": POSE,
    "rigid_bodies": POSE,
    "markers": POINT,
    "imu": IMU,
    "joint_state": JOINT,
    "command": SCALAR,
    "wrench": WRENCH,
    "contact_flags": SCALAR,
}


@dataclass(frozen=True)
class BadSampleCounts:
    """Messages skipped on one stream (or topic), by reason."""

    nan: int = 0  # a used field is NaN or ±Inf
    out_of_bounds: int = 0  # a value beyond the physical bound of its component (`BOUNDS`)
    bad_time: int = 0  # a stamp or log time outside any plausible clock (|t| ≥ 2^62 ns)
    time_jump: int = 0  # one stamp far from both neighbours (a corrupt stamp, not a new origin)
    duplicate_time: int = 0  # same time as the previous kept sample
    backwards_time: int = 0  # earlier than the previous kept sample
    wrong_length: int = 0  # arrays of inconsistent length (JointState, commands)
    unknown_name: int = 0  # none of the mapped names (joints, bodies, markers) is present
    unknown_type: int = 0  # a message type the stream cannot read, or no usable schema
    undecodable: int = 0  # the CDR bytes do not decode with the schema

    @property
    def total(self) -> int:
        return sum(self.as_dict().values())

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def reasons() -> tuple[str, ...]:
        return tuple(f.name for f in fields(BadSampleCounts))


@dataclass(frozen=True, slots=True)
class Sample:
    """One accepted message on one stream. values: (E, K), the stream's elements × components."""

    stream: str
    t_ns: int
    log_time_ns: int
    values: np.ndarray


@dataclass(frozen=True)
class Measurement:
    """Every accepted sample of one stream, in time order (t_ns strictly increasing).

    t_ns: (N,) int64, the stream's time (header stamp or log time, plus the config offset).
    log_time_ns: (N,) int64, when the recorder received each message.
    values: (N, E, K) float64; `elements` are model names of `element_type`.
    """

    stream: str
    kind: str
    topic: str
    element_type: str
    elements: tuple[str, ...]
    components: tuple[str, ...]
    t_ns: np.ndarray
    log_time_ns: np.ndarray
    values: np.ndarray
    bad: BadSampleCounts

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def mask(self) -> np.ndarray:
        """(N, E, K) bool: the field was in the message (values finite)."""
        return np.isfinite(self.values)

    def between(self, t0_ns: int, t1_ns: int) -> Measurement:
        """The samples with t0 ≤ t < t1 (ns, int: float would round a log's clock)."""
        i0, i1 = np.searchsorted(self.t_ns, np.array([t0_ns, t1_ns], dtype=np.int64))
        return replace(
            self,
            t_ns=self.t_ns[i0:i1],
            log_time_ns=self.log_time_ns[i0:i1],
            values=self.values[i0:i1],
        )

    def element(self, name: str) -> np.ndarray:
        """(N, K) values of one model element."""
        return self.values[:, self.elements.index(name), :]

    def component(self, name: str) -> np.ndarray:
        """(N, E) values of one component (e.g. "position" of a JointState)."""
        return self.values[:, :, self.components.index(name)]


def collect(
    samples: Iterable[Sample],
    config: Config,
    bad: Mapping[str, BadSampleCounts],
) -> dict[str, Measurement]:
    """Stack samples into one `Measurement` per config stream (empty ones included)."""
    rows: dict[str, list[Sample]] = {name: [] for name in config.streams}
    for sample in samples:
        rows[sample.stream].append(sample)
    return {
        name: _stack(stream, rows[name], bad.get(name, BadSampleCounts()))
        for name, stream in config.streams.items()
    }


def _stack(stream: StreamConfig, samples: list[Sample], bad: BadSampleCounts) -> Measurement:
    components = STREAM_COMPONENTS[stream.kind]
    shape = (len(samples), len(stream.elements), len(components))
    values = np.stack([s.values for s in samples]) if samples else np.zeros(shape)
    return Measurement(
        stream=stream.name,
        kind=stream.kind,
        topic=stream.topic,
        element_type=stream.element_type,
        elements=stream.elements,
        components=components,
        t_ns=np.array([s.t_ns for s in samples], dtype=np.int64),
        log_time_ns=np.array([s.log_time_ns for s in samples], dtype=np.int64),
        values=values,
        bad=bad,
    )


@dataclass(frozen=True)
class TopicStats:
    """Timing and health of one topic, over every message in the log.

    count: messages on the topic.
    log_time_ns: (n,) int64, receive time of each message, in log order (n = count, or 0
        when times were not kept).
    stamp_ns, stamp_log_time_ns: (m,) int64, header stamps of the m decoded messages that
        carry one, and those messages' log times (m = 0 if the topic was not decoded).
    bad: counts from the message alone (no config): undecodable, NaN, wrong lengths,
        duplicate and backwards header stamps.
    """

    topic: str
    msg_type: str
    count: int
    log_time_ns: np.ndarray
    stamp_ns: np.ndarray
    stamp_log_time_ns: np.ndarray
    bad: BadSampleCounts
    decoded: bool

    @property
    def times_ns(self) -> np.ndarray:
        """The topic's own clock: header stamps if it has them, else log times (sorted)."""
        times = self.stamp_ns if len(self.stamp_ns) >= 2 else self.log_time_ns
        return np.sort(times)

    @property
    def span_ns(self) -> tuple[int, int] | None:
        """(first, last) log time, None for a topic without (kept) messages."""
        if not len(self.log_time_ns):
            return None
        return int(self.log_time_ns.min()), int(self.log_time_ns.max())

    @property
    def rate_hz(self) -> float:
        """1 / median interval between messages (0 with fewer than two)."""
        dt = np.diff(self.times_ns)
        dt = dt[dt > 0]
        return float(1e9 / np.median(dt)) if len(dt) else 0.0

    @property
    def largest_gap(self) -> tuple[int, int] | None:
        """(gap_ns, log time at its start) of the longest wait between two messages' arrival.

        On the recorder's clock, so gaps of different topics line up; None with < 2 messages.
        """
        times = np.sort(self.log_time_ns)
        if len(times) < 2:
            return None
        dt = np.diff(times)
        i = int(np.argmax(dt))
        return int(dt[i]), int(times[i])

    @property
    def jitter_ns(self) -> float:
        """Standard deviation of the interval between messages (0 with fewer than three)."""
        dt = np.diff(self.times_ns)
        return float(np.std(dt)) if len(dt) >= 2 else 0.0

    @property
    def clock_offset_ns(self) -> float | None:
        """Median of header.stamp − log_time: the sender's clock (and latency) vs the recorder's."""
        if not len(self.stamp_ns):
            return None
        return float(np.median(self.stamp_ns - self.stamp_log_time_ns))
