"""Read a ROS 2 MCAP file or rosbag2 folder into per-stream measurement arrays.

    log = read_log("run.mcap", load_config("configs/humanoid.toml"))
    imu = log.measurements["imu"]          # Measurement: t_ns (N,), values (N, 1, 10)

A truncated or damaged file yields everything before the damage and a warning in
`Log.warnings`; bad samples are skipped and counted per stream (`Measurement.bad`) and per
topic (`Log.topics[...].bad`); a required stream whose topic is absent, or that has no usable
sample, raises `MissingTopicError`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from estimator.config import Config
from estimator.errors import MissingTopicError
from estimator.logs.measurements import (
    BadSampleCounts,
    Measurement,
    Sample,
    TopicStats,
    collect,
)
from estimator.logs.samples import SampleExtractor
from estimator.logs.source import LogSource, open_log


@dataclass(frozen=True)
class Log:
    """Everything read from one log.

    measurements: per config stream, in config order (empty without a config).
    topics: statistics of every topic read (all topics when read without a config or with
        `decode_all`), sorted by name.
    names_seen: per config stream, which of its source names (JointState joints, rigid
        bodies, markers, TF child frames) occur in the log.
    warnings: one line per problem with the file itself (truncation, damage).
    """

    source: str
    measurements: Mapping[str, Measurement]
    topics: Mapping[str, TopicStats]
    names_seen: Mapping[str, frozenset[str]]
    warnings: tuple[str, ...]
    truncated: bool


def read_log(
    path: str | Path,
    config: Config | None = None,
    *,
    decode_all: bool = False,
    require: bool = True,
) -> Log:
    """Read a log file or rosbag2 folder.

    config: the streams to extract; None reads topic statistics only.
    decode_all: decode every topic (header stamps and bad counts for all of them), not only
        the config's; without a config every topic is decoded anyway.
    require: raise `MissingTopicError` for a required stream without usable samples.
    """
    only = None if config is None or decode_all else set(config.topics)
    source = open_log(path, topics=only)
    extractor = SampleExtractor(config, decode_all=decode_all or config is None)
    samples = list(extract(source, extractor))
    return finish(source, extractor, samples, config, require=require)


def extract(source: LogSource, extractor: SampleExtractor) -> Iterator[Sample]:
    """The accepted samples of `source`, in log order, as its messages are read."""
    for raw in source:
        yield from extractor.feed(raw)


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
        check_required(source.name, config, topics, accepted, bad, available=source.topics)
    return Log(
        source=source.name,
        measurements=measurements,
        topics=topics,
        names_seen=extractor.names_seen(),
        warnings=tuple(source.warnings),
        truncated=source.truncated,
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
) -> None:
    """Raise `MissingTopicError` naming every required stream without usable samples."""
    problems = missing_required(config, topics, accepted, bad, available)
    if problems:
        raise MissingTopicError(f"{source}: " + "; ".join(problems))
