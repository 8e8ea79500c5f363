"""From raw MCAP messages to per-stream samples: decode, map onto the model, check, count.

The one pipeline shared by the file reader and the byte-stream reader. For each message:
decode the CDR bytes with mcap_ros2 (schema from the log), turn it into `Record`s
(`decode.py`), then for every stream on its topic select the configured entries in the
config's element order, rotate sensor axes into the site frame, time it
(`t = header.stamp or log_time, + time_offset_ns`), and accept it or count why not:

- `unknown_type`: the topic's message type is not one the stream reads, or has no schema;
- `undecodable`: the bytes do not decode;
- `wrong_length`: array lengths disagree (JointState, JointTrajectory, a Float64MultiArray
  whose length is not the number of actuators);
- `unknown_name`: none of the stream's names (joints, bodies, markers) is in the message;
- `nan`: a used field is NaN or ±Inf;
- `out_of_bounds`: a used value beyond its component's physical bound (`BOUNDS`, e.g.
  10 km for a position, 1000 rad/s for a gyro; a stream's `max_abs` overrides them), or a
  quaternion whose norm is not within [0.5, 2];
- `bad_time`: a stamp or log time outside any plausible clock (|t| ≥ 2^62 ns, ~146 years);
- `time_jump`: one stamp far from both neighbours — later than the next sample while the
  previous and the next are in order, or, at the stream's start or end, cut off from the
  rest by a gap of over `MAX_TIME_JUMP_NS` and 100 of the stream's intervals. One corrupt
  stamp is an outlier of that sample, never a new origin for the stream; to judge it a
  sample is released one sample late (two at the stream's start);
- `duplicate_time` / `backwards_time`: not later than the stream's previous accepted sample.

A skipped message is only counted; the stream continues. A TF stream silently ignores
transforms of other frames (a /tf topic carries many). Per topic, the same checks run on the
message alone (no config) and feed `TopicStats`.
"""

from __future__ import annotations

import contextlib
import io
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import mujoco
import numpy as np
from mcap_ros2._dynamic import serialize_dynamic  # as estimator.io.mcap_writer
from mcap_ros2.decoder import DecoderFactory

from estimator.config import ARRAY_KINDS, Config, StreamConfig
from estimator.io.logs import ros2_types
from estimator.io.logs.decode import (
    DECODERS,
    TRAJECTORY,
    BadSampleError,
    Record,
    non_finite,
    stamp_ns,
)
from estimator.io.logs.measurements import STREAM_COMPONENTS, BadSampleCounts, Sample, TopicStats
from estimator.io.logs.source import RawMessage

_IDENTITY = (1.0, 0.0, 0.0, 0.0)
# Largest plausible |value| per component: beyond these a value is damage, not physics.
BOUNDS: dict[str, float] = {
    **dict.fromkeys(("qw", "qx", "qy", "qz"), 2.0),  # and a norm within [0.5, 2]
    **dict.fromkeys(("px", "py", "pz"), 1e4),  # m
    **dict.fromkeys(("wx", "wy", "wz"), 1e3),  # rad/s
    **dict.fromkeys(("ax", "ay", "az"), 1e4),  # m/s²
    **dict.fromkeys(("position", "positions", "velocity", "velocities"), 1e4),  # rad, m, /s
    **dict.fromkeys(("accelerations",), 1e6),
    **dict.fromkeys(("effort", "value", "fx", "fy", "fz", "tx", "ty", "tz"), 1e6),  # N, N·m
}
QUAT = ("qw", "qx", "qy", "qz")
MAX_TIME_NS = 1 << 62  # |t| beyond this is no clock (int64 headroom for differences)
MAX_TIME_JUMP_NS = 1_000_000_000  # a gap that can isolate a stream's first or last sample
_FIRST = (np.zeros(1, dtype=np.intp), np.ones(1, dtype=bool), True)


def _gather(array: np.ndarray, index: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Rows `index` of array (n, K); rows not found are NaN (values) or False (presence)."""
    fill = np.nan if array.dtype.kind == "f" else False
    out = np.full((len(index), array.shape[1]), fill, dtype=array.dtype)
    out[found] = array[index[found]]
    return out


class SampleExtractor:
    """Feed raw messages in log order; get accepted samples back, and counts at the end.

    config: the streams to extract (None: topic statistics only).
    decode_all: decode every topic, not only the config's, so that `topic_stats` has header
        stamps and message-level bad counts everywhere (what `physfuse inspect` shows).
    keep_times: keep every message's times for `topic_stats` (memory grows with the log);
        without, topics keep only counts (a long-running live stream).
    """

    def __init__(self, config: Config | None, *, decode_all: bool = False, keep_times: bool = True):
        self.config = config
        self.decode_all = decode_all
        self.keep_times = keep_times
        self._streams: dict[str, list[_StreamState]] = {}
        if config is not None:
            for stream in config.streams.values():
                self._streams.setdefault(stream.topic, []).append(_StreamState(stream))
        self._topics: dict[str, _TopicState] = {}
        self._decoders: dict[tuple[Any, ...], _Codec | None] = {}

    def feed(self, raw: RawMessage) -> list[Sample]:
        """The samples `raw` contributes (usually 0 or 1 per stream on its topic)."""
        topic = self._topics.get(raw.topic)
        if topic is None:
            topic = self._topics[raw.topic] = _TopicState(raw.msg_type, self.keep_times)
        topic.n_messages += 1
        if not 0 <= raw.log_time_ns < MAX_TIME_NS:
            topic.count("bad_time")
            for state in self._streams.get(raw.topic, ()):
                state.count("bad_time")
            return []
        if self.keep_times:
            topic.log_times.append(raw.log_time_ns)
        streams = self._streams.get(raw.topic, ())
        if not streams and not self.decode_all:
            return []
        try:
            records = self._decode(raw, topic)
        except BadSampleError as bad:
            topic.count(bad.reason)
            for state in streams:
                state.count(bad.reason)
            return []
        if records is None:  # decodable but of a type without a record decoder
            for state in streams:
                state.count("unknown_type")
            return []
        topic.check(records, raw.log_time_ns)
        samples: list[Sample] = []
        for state in streams:
            samples.extend(state.samples(raw, records))
        return samples

    def flush(self) -> list[Sample]:
        """The samples still held back for the time check, once the log has ended."""
        return [
            sample
            for states in self._streams.values()
            for state in states
            for sample in state.flush()
        ]

    def bad_counts(self) -> dict[str, BadSampleCounts]:
        """Per config stream: the messages it skipped, by reason."""
        return {s.cfg.name: s.frozen_counts() for states in self._streams.values() for s in states}

    def names_seen(self) -> dict[str, frozenset[str]]:
        """Per config stream: which of its source names (joints, frames, ...) the log has."""
        return {s.cfg.name: frozenset(s.seen) for states in self._streams.values() for s in states}

    def topic_stats(self, declared: Mapping[str, str] | None = None) -> dict[str, TopicStats]:
        """Per topic (plus `declared` topics without messages), sorted by name."""
        declared = declared or {}
        names = sorted(set(self._topics) | set(declared))
        return {
            name: (
                self._topics[name].stats(name)
                if name in self._topics
                else _TopicState(declared[name], keep_times=False).stats(name)
            )
            for name in names
        }

    def _decode(self, raw: RawMessage, topic: _TopicState) -> tuple[Record, ...] | None:
        """Records of a message; None if its type has no record decoder (stamp still taken)."""
        codec = self._codec(raw)
        if codec is None:
            raise BadSampleError("unknown_type", f"no ROS 2 schema for {raw.msg_type or 'it'}")
        try:
            msg = codec.decode(raw.data)
        except Exception as err:  # any failure inside the CDR parser means bad bytes
            raise BadSampleError("undecodable", str(err)) from err
        topic.decoded = True
        to_records = DECODERS.get(raw.msg_type)
        if to_records is None:
            header = getattr(msg, "header", None)
            if header is not None and hasattr(header, "stamp") and topic.keep_times:
                topic.stamps.append((stamp_ns(header), raw.log_time_ns))
            return None
        codec.check_length(msg, raw.data)
        try:
            records = to_records(msg)
        except (AttributeError, TypeError, ValueError) as err:  # fields not as the type says
            raise BadSampleError("undecodable", str(err)) from err
        if not all(_is_name(n) for r in records for n in r.names):  # damaged bytes in a name
            raise BadSampleError("undecodable", "a name with control or invalid bytes")
        return records

    def _codec(self, raw: RawMessage) -> _Codec | None:
        schema = raw.schema
        if schema is None:
            return None
        key = (schema.name, schema.encoding, schema.data, raw.message_encoding)
        if key not in self._decoders:
            decode = encode = None
            # its vendored parser prints to stderr on a bad schema: keep that quiet
            with contextlib.redirect_stderr(io.StringIO()):
                with contextlib.suppress(Exception):  # a schema text mcap_ros2 cannot parse
                    decode = DecoderFactory().decoder_for(raw.message_encoding, schema)
                with contextlib.suppress(Exception):  # (then the length goes unchecked)
                    encode = serialize_dynamic(schema.name, schema.data.decode())[schema.name]
            codec = None if decode is None else _Codec(decode, encode)
            self._decoders[key] = codec
        return self._decoders[key]


class _Codec:
    """A schema's CDR decoder, and its encoder to check the message used all of its bytes."""

    def __init__(self, decode: Callable[[bytes], Any], encode: Callable[[Any], bytes] | None):
        self.decode = decode
        self.encode = encode

    def check_length(self, msg: Any, data: bytes) -> None:
        """Bytes left over after the message (beyond the ≤ 3 bytes of alignment a writer may
        pad with) mean a damaged length decoded a shorter array: the values read are not the
        logged ones."""
        if self.encode is None:
            return
        try:
            left = len(data) - len(self.encode(msg))
        except Exception as err:  # fields the type's own encoder refuses
            raise BadSampleError("undecodable", str(err)) from err
        if left > 3:
            raise BadSampleError("undecodable", f"{left} bytes left after the message")


def _is_name(name: str) -> bool:
    """A joint, frame or marker name as a ROS node writes it: printable, no bytes the decoder
    had to replace (a name with them is damage, not an entry of another joint)."""
    return name.isprintable() and "\ufffd" not in name


class _TopicState:
    """Message-level statistics of one topic (no config involved)."""

    def __init__(self, msg_type: str, keep_times: bool):
        self.msg_type = msg_type
        self.keep_times = keep_times
        self.n_messages = 0
        self.log_times: list[int] = []
        self.stamps: list[tuple[int, int]] = []  # (header stamp, log time)
        self.counts = dict.fromkeys(BadSampleCounts.reasons(), 0)
        self.last: dict[str, int] = {}  # per TF child frame ('' for other types)
        self.decoded = False

    def count(self, reason: str) -> None:
        self.counts[reason] += 1

    def check(self, records: tuple[Record, ...], log_time_ns: int) -> None:
        stamped = [r for r in records if r.stamp_ns is not None]
        if any(abs(r.stamp_ns or 0) >= MAX_TIME_NS for r in stamped):
            self.count("bad_time")
            return
        if stamped and self.keep_times:
            self.stamps.append((stamped[0].stamp_ns or 0, log_time_ns))
        if any(non_finite(r) for r in records):
            self.count("nan")
            return
        keyed = len(records) != 1 or self.msg_type in (
            ros2_types.TF_MESSAGE,
            ros2_types.TRANSFORM_STAMPED,
        )
        for r in stamped:
            key = r.names[0] if keyed and r.names else ""
            t = (r.stamp_ns or 0) + r.delay_ns
            last = self.last.get(key)
            if last is not None and t == last:
                self.count("duplicate_time")
            elif last is not None and t < last:
                self.count("backwards_time")
            else:
                self.last[key] = t

    def stats(self, topic: str) -> TopicStats:
        stamps = np.array(self.stamps, dtype=np.int64).reshape(-1, 2)
        return TopicStats(
            topic=topic,
            msg_type=self.msg_type,
            count=self.n_messages,
            log_time_ns=np.array(self.log_times, dtype=np.int64),
            stamp_ns=stamps[:, 0].copy(),
            stamp_log_time_ns=stamps[:, 1].copy(),
            bad=BadSampleCounts(**self.counts),
            decoded=self.decoded,
        )


class _StreamState:
    """One config stream: maps records onto its elements and keeps its time order."""

    def __init__(self, cfg: StreamConfig):
        self.cfg = cfg
        accepted = ros2_types.ACCEPTED_TYPES[cfg.kind]
        if cfg.kind == "command":  # a list of actuators reads arrays, a table trajectories
            accepted = (
                (ros2_types.FLOAT64_MULTI_ARRAY,)
                if cfg.field is None
                else (ros2_types.JOINT_TRAJECTORY,)
            )
        self.accepted = accepted
        # the record columns the stream uses (None: all of them)
        self.columns = [TRAJECTORY.index(cfg.field)] if cfg.field is not None else None
        self.single = cfg.sources is None or cfg.kind == "tf"
        self.plans: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray, bool]] = {}
        self.rotation: np.ndarray | None = None
        self.quat_sensor_site = np.zeros(4)
        if cfg.quat_site_sensor != _IDENTITY:
            q = np.array(cfg.quat_site_sensor)
            self.rotation = np.zeros(9)
            mujoco.mju_quat2Mat(self.rotation, q)
            self.rotation = self.rotation.reshape(3, 3)  # R_site_sensor
            mujoco.mju_negQuat(self.quat_sensor_site, q)
        self.counts = dict.fromkeys(BadSampleCounts.reasons(), 0)
        self.last_t: int | None = None
        self.pending: list[Sample] = []  # held until the next sample judges their time
        self.intervals: deque[int] = deque(maxlen=16)  # between the last kept samples
        self.seen: set[str] = set()
        components = STREAM_COMPONENTS[cfg.kind]
        if self.columns is not None:
            components = tuple(TRAJECTORY[c] for c in self.columns)
        bounds = {**BOUNDS, **cfg.max_abs}
        self.bound = np.array([bounds.get(c, np.inf) for c in components])
        self.quat = [components.index(q) for q in QUAT] if QUAT[0] in components else None

    def count(self, reason: str) -> None:
        self.counts[reason] += 1

    def frozen_counts(self) -> BadSampleCounts:
        return BadSampleCounts(**self.counts)

    def samples(self, raw: RawMessage, records: tuple[Record, ...]) -> list[Sample]:
        if raw.msg_type not in self.accepted:
            self.count("unknown_type")
            return []
        if self.cfg.kind == "tf":
            child, parent = (
                self.cfg.sources[0] if self.cfg.sources else "",
                self.cfg.parent_frame_id,
            )
            records = tuple(
                r
                for r in records
                if r.names[0] == child and (parent is None or r.frame_id == parent)
            )
        out = []
        for record in records:
            try:
                values = self.row(record)
            except BadSampleError as bad:
                self.count(bad.reason)
                continue
            base = record.stamp_ns if self.cfg.stamp == "header" else raw.log_time_ns
            t = (base or 0) + record.delay_ns + self.cfg.time_offset_ns
            if abs(t) >= MAX_TIME_NS:
                self.count("bad_time")
                continue
            out.extend(self.order(Sample(self.cfg.name, t, raw.log_time_ns, values)))
        return out

    def order(self, sample: Sample) -> list[Sample]:
        """The samples released by this one's arrival: each is judged with the next in view.

        A held sample is a `time_jump` if it is later than the next while the previous kept
        and the next are in order (its stamp jumped ahead); the stream's first, if a gap
        over `MAX_TIME_JUMP_NS` and 100 intervals of the samples after it follows it.
        """
        self.pending.append(sample)
        released = []
        while len(self.pending) >= (3 if self.last_t is None else 2):
            cur, nxt = self.pending[0].t_ns, self.pending[1].t_ns
            if self.last_t is None:
                after = self.pending[2].t_ns - nxt
                jumped = cur > nxt < self.pending[2].t_ns or (
                    after > 0 and nxt - cur > max(MAX_TIME_JUMP_NS, 100 * after)
                )
            else:
                jumped = cur > nxt > self.last_t
            held = self.pending.pop(0)
            if jumped:
                self.count("time_jump")
            else:
                released.extend(self.keep(held))
        return released

    def flush(self) -> list[Sample]:
        """Release the held samples at the end of the log; the last is judged by its gap."""
        released = []
        while self.pending:
            held = self.pending.pop(0)
            gap = held.t_ns - (self.last_t if self.last_t is not None else held.t_ns)
            if (
                not self.pending
                and self.intervals
                and gap > max(MAX_TIME_JUMP_NS, 100 * float(np.median(self.intervals)))
            ):
                self.count("time_jump")
            else:
                released.extend(self.keep(held))
        return released

    def keep(self, sample: Sample) -> list[Sample]:
        """[sample] if it is later than the last kept one, else [] and counted."""
        if self.last_t is not None and sample.t_ns <= self.last_t:
            self.count("duplicate_time" if sample.t_ns == self.last_t else "backwards_time")
            return []
        if self.last_t is not None:
            self.intervals.append(sample.t_ns - self.last_t)
        self.last_t = sample.t_ns
        return [sample]

    def row(self, record: Record) -> np.ndarray:
        """(E, K) values of the stream's elements from one record."""
        if self.single:  # the record's only entry (a TF record is already the right frame)
            if not record.names:
                raise BadSampleError("wrong_length", "empty message")
            self.seen.add(record.names[0])
            index, found, complete = _FIRST
        else:
            index, found, complete = self.plan(record.names)
        values = record.values[index] if complete else _gather(record.values, index, found)
        if self.columns is not None:
            values = values[:, self.columns]
        if record.present is None:
            # an entry absent from the message (an occluded marker) is missing, not bad
            carried = values if complete else values[found]
            if not np.isfinite(carried).all():
                raise BadSampleError("nan", "NaN or Inf in a used field")
        else:
            present = record.present[index] if complete else _gather(record.present, index, found)
            if self.columns is not None:
                present = present[:, self.columns]
            if not present.any():
                raise BadSampleError("wrong_length", "the message carries none of the used fields")
            if (present & ~np.isfinite(values)).any():
                raise BadSampleError("nan", "NaN or Inf in a used field")
        self.check_bounds(values)
        if self.rotation is not None:
            self.rotate(values[0])
        return values

    def check_bounds(self, values: np.ndarray) -> None:
        """Raise `out_of_bounds` for a value beyond its bound or a quaternion far from unit."""
        with np.errstate(invalid="ignore"):
            if (np.abs(values) > self.bound).any():
                raise BadSampleError("out_of_bounds", "a value beyond its physical bound")
            if self.quat is not None:
                norm = np.linalg.norm(values[:, self.quat], axis=1)
                if ((norm < 0.5) | (norm > 2.0)).any():
                    raise BadSampleError("out_of_bounds", "a quaternion far from unit norm")

    def plan(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, bool]:
        """(index (E,), found (E,), all found) of the stream's sources in `names`, cached.

        Messages on a topic almost always repeat the same names, so the lookup is built once
        per distinct name list.
        """
        plan = self.plans.get(names)
        if plan is not None:
            return plan
        cfg = self.cfg
        assert cfg.sources is not None
        if cfg.kind in ARRAY_KINDS and cfg.field is None and len(names) != len(cfg.elements):
            what = "actuators" if cfg.kind == "command" else "feet"
            raise BadSampleError(
                "wrong_length", f"{len(names)} values for {len(cfg.elements)} {what}"
            )
        lookup = {name: i for i, name in enumerate(names)}
        index = np.array([lookup.get(src, -1) for src in cfg.sources], dtype=np.intp)
        found = index >= 0
        if not found.any():
            raise BadSampleError("unknown_name", "none of the mapped names is in the message")
        self.seen.update(src for src, ok in zip(cfg.sources, found, strict=True) if ok)
        if len(self.plans) >= 256:  # names that change every message: do not grow forever
            self.plans.clear()
        plan = self.plans[names] = (index, found, bool(found.all()))
        return plan

    def rotate(self, v: np.ndarray) -> None:
        """Sensor axes → site axes, in place: v_site = R_site_sensor v_sensor.

        IMU orientation: q_ref_site = q_ref_sensor ⊗ conj(q_site_sensor).
        """
        rot = self.rotation
        assert rot is not None
        if self.cfg.kind == "imu":
            if np.isfinite(v[0:4]).all():
                q = np.empty(4)
                mujoco.mju_mulQuat(q, v[0:4], self.quat_sensor_site)
                v[0:4] = q
            v[4:7] = rot @ v[4:7]
            v[7:10] = rot @ v[7:10]
        else:  # wrench: force, torque
            v[0:3] = rot @ v[0:3]
            v[3:6] = rot @ v[3:6]
