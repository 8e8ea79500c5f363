"""Measurements from a live MCAP byte stream (a pipe or socket), yielded as bytes arrive.

    reader = ByteStreamReader(sock.makefile("rb"), config)
    for sample in reader.samples():   # Sample(stream, t_ns, log_time_ns, values (E, K))
        handle(sample)                # e.g. append to a buffer, in arrival order
    reader.warnings                   # e.g. the stream ended mid-record

The stream is read record by record without seeking, so a sample is yielded as soon as the
message that carries it has arrived (a writer must send unchunked records, or flush chunks,
for that to be immediate). It gives the same samples, counts and warnings as `read_log` on a
file with the same bytes: both run `SampleExtractor` over the messages in written order. A
stream that stops mid-record (the robot crashed) ends the iteration cleanly with a warning; a
chunk whose CRC fails is skipped and reported in `lost` (a stream cannot search forward past a
garbage record length, so that ends it like a cut).
Memory stays bounded: samples are not kept, and topics keep counts only unless asked for
`statistics`.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import IO

from estimator.config import Config
from estimator.io.logs.measurements import BadSampleCounts, Sample
from estimator.io.logs.reader import Log, check_required, extract, finish
from estimator.io.logs.samples import SampleExtractor
from estimator.io.logs.source import LostData, open_stream


class ByteStreamReader:
    """Reads one MCAP byte stream, once.

    stream: any object with `read(n)` (a pipe from `os.fdopen(fd, "rb")`, a socket's
        `makefile("rb")`, a raw `FileIO`); short reads are waited out.
    require: when the stream ends, raise `MissingTopicError` for a required stream that
        never produced a usable sample.
    statistics: keep every message's times, so that `read_all().topics` has rates, gaps and
        clock offsets (memory grows with the stream).
    """

    def __init__(
        self,
        stream: IO[bytes],
        config: Config,
        *,
        name: str = "<stream>",
        require: bool = True,
        statistics: bool = False,
    ):
        self.config = config
        self.name = name
        self.require = require
        self._source = open_stream(stream, name)
        self._extractor = SampleExtractor(config, keep_times=statistics)
        self._accepted = dict.fromkeys(config.streams, 0)
        self._started = False

    def samples(self) -> Iterator[Sample]:
        """Each accepted sample, in stream order, as soon as its message has been read."""
        self._start()
        for sample in extract(self._source, self._extractor):
            self._accepted[sample.stream] += 1
            yield sample
        if self.require:
            check_required(
                self.name,
                self.config,
                self._extractor.topic_stats(),
                self._accepted,
                self._extractor.bad_counts(),
                available=self._source.topics,
                damage=self._source.warnings,
            )

    def read_all(self) -> Log:
        """Read the whole stream into the same `Log` that `read_log` gives for a file."""
        self._start()
        samples = list(extract(self._source, self._extractor))
        return finish(self._source, self._extractor, samples, self.config, require=self.require)

    @property
    def bad_counts(self) -> Mapping[str, BadSampleCounts]:
        """Skipped messages per stream so far."""
        return self._extractor.bad_counts()

    @property
    def warnings(self) -> tuple[str, ...]:
        """Problems with the stream itself so far (e.g. it ended mid-record)."""
        return tuple(self._source.warnings)

    @property
    def truncated(self) -> bool:
        return self._source.truncated

    @property
    def lost(self) -> tuple[LostData, ...]:
        """What damage has cost so far, one `LostData` per damaged region."""
        return tuple(self._source.lost)

    def _start(self) -> None:
        if self._started:
            raise RuntimeError("a ByteStreamReader reads its stream once")
        self._started = True
