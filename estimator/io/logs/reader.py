"""Read a ROS 2 MCAP file, rosbag2 folder, FIFO or stdin into per-stream measurement arrays.

    log = read_log("run.mcap", load_config("configs/humanoid.toml"))
    imu = log.measurements["imu"]          # Measurement: t_ns (N,), values (N, 1, 10)

A damaged file yields every message that its CRCs vouch for: a damaged chunk is skipped, a cut
file keeps everything before the cut, and each loss is a `LostData` in `Log.lost` (file, time
range, message count) and a line in `Log.warnings` (see `source`). Bad samples are skipped
and counted per stream (`Measurement.bad`) and per topic (`Log.topics[...].bad`); a required
stream whose topic is absent, or that has no usable sample, raises `MissingTopicError`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from estimator.config import Config
from estimator.errors import MissingTopicError
from estimator.io.logs.measurements import (
    BadSampleCounts,
    Measurement,
    Sample,
    TopicStats,
    collect,
)
from estimator.io.logs.samples import SampleExtractor
from estimator.io.logs.source import LogSource, LostData, open_log


@dataclass(frozen=True)
class Log:
    """Everything read from one log.

    measurements: per config stream, in config order (empty without a config).
    topics: statistics of every topic read (all topics when read without a config or with
        `decode_all`), sorted by name.
    names_seen: per config stream, which of its source names (JointState joints, rigid
        bodies, markers, TF child frames) occur in the log.
    warnings: one line per problem with the file itself (truncation, damage).
    truncated: the log ends early (cut, or unreadable to its end, or a split file missing).
    lost: what damage cost, one `LostData` per damaged region (each also has a warning).
    """

    source: str
    measurements: Mapping[str, Measurement]
    topics: Mapping[str, TopicStats]
    names_seen: Mapping[str, frozenset[str]]
    warnings: tuple[str, ...]
    truncated: bool
    lost: tuple[LostData, ...] = ()


def read_log(
    path: str | Path,
    config: Config | None = None,
    *,
    decode_all: bool = False,
    require: bool = True,
    log_time: tuple[int, int] | None = None,
) -> Log:
    """Read a log file, rosbag2 folder, FIFO, or standard input (`-`).

    config: the streams to extract; None reads topic statistics only.
    decode_all: decode every topic (header stamps and bad counts for all of them), not only
        the config's; without a config every topic is decoded anyway.
    require: raise `MissingTopicError` for a required stream without usable samples.
    log_time: (start, end) ns: only the messages received in [start, end) (a slice of a long
        log file or folder, read without the rest: `source.open_log`).
    """
    only = None if config is None or decode_all else set(config.topics)
    source = open_log(path, topics=only, log_time=log_time)
    extractor = SampleExtractor(config, decode_all=decode_all or config is None)
    samples = list(extract(source, extractor))
    return finish(source, extractor, samples, config, require=require)


def extract(source: LogSource, extractor: SampleExtractor) -> Iterator[Sample]:
    """The accepted samples of `source`, in log order, as its messages are read."""
    for raw in source:
        yield from extractor.feed(raw)
    yield from extractor.flush()  # the samples held back to judge their stamps


def finish(
    source: LogSource,
    extractor: SampleExtractor,
    samples: list[Sample],
    config: Config | None,
    *,
    require: bool,
) -> Log:
    """Assemble a `Log` once a source is exhausted (shared with the byte-stream reader)."""
    bad = extractor.bad_counts()
    measurements = collect(samples, config, bad) if config is not None else {}
    topics = extractor.topic_stats(source.topics if extractor.decode_all else None)
    if require and config is not None:
        accepted = {name: len(m) for name, m in measurements.items()}
        check_required(
            source.name,
            config,
            topics,
            accepted,
            bad,
            available=source.topics,
            damage=source.warnings,
        )
    return Log(
        source=source.name,
        measurements=measurements,
        topics=topics,
        names_seen=extractor.names_seen(),
        warnings=tuple(source.warnings),
        truncated=source.truncated,
        lost=tuple(source.lost),
    )


def missing_required(
    config: Config,
    topics: Mapping[str, TopicStats],
    accepted: Mapping[str, int],
    bad: Mapping[str, BadSampleCounts],
    available: Iterable[str] = (),
) -> list[str]:
    """One line per required stream whose topic is absent or that has no usable sample.

    accepted: samples kept per stream; bad: skipped messages per stream; available: every
    topic the log declares (also those not read), listed when a topic is missing.
    """
    problems = []
    for name, stream in config.streams.items():
        if not stream.required or accepted.get(name, 0) > 0:
            continue
        topic = topics.get(stream.topic)
        if topic is None or topic.count == 0:
            listed = sorted({*available, *(t for t, s in topics.items() if s.count)})
            problems.append(
                f"required stream {name!r}: topic {stream.topic!r} is not in the log "
                f"(its topics: {', '.join(listed) or 'none'})"
            )
        else:
            counts = bad.get(name, BadSampleCounts()).as_dict()
            why = ", ".join(f"{k}={v}" for k, v in counts.items() if v) or "no matching entry"
            problems.append(
                f"required stream {name!r}: topic {stream.topic!r} has {topic.count} "
                f"messages ({topic.msg_type or 'no schema'}) but no usable sample ({why})"
            )
    return problems


def check_required(
    source: str,
    config: Config,
    topics: Mapping[str, TopicStats],
    accepted: Mapping[str, int],
    bad: Mapping[str, BadSampleCounts],
    available: Iterable[str] = (),
    damage: Sequence[str] = (),
) -> None:
    """Raise `MissingTopicError` naming every required stream without usable samples.

    damage: the log's warnings; the first is quoted, since damage may be why.
    """
    problems = missing_required(config, topics, accepted, bad, available)
    if problems:
        if damage:
            problems.append(f"the log is damaged ({len(damage)} warnings, first: {damage[0]})")
        raise MissingTopicError(f"{source}: " + "; ".join(problems))
