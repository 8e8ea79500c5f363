"""Fuzzing the log readers: mutated recordings through `read_log`, the byte-stream reader and
`physfuse inspect`, counting every exception that is not physfuse's own and every value read
changed without a flag.

    .venv/bin/python benchmarks/fuzz.py --inputs 100000 --jobs 2 --out out/fuzz

The originals are the first `--seconds` of the bundled recordings (humanoid_push: poses, IMU,
joint states, commands; arm_box: markers and a force/torque sensor), rewritten with small
chunks and each of zstd, lz4 and no compression, so that an input has many chunks. Each
input is one original with one mutation (`MUTATIONS`):

- byte level: flipped bits, overwritten / zeroed / deleted / duplicated byte runs,
  truncation — anywhere in the file (header, chunks, summary, footer);
- message level (the file rewritten whole, valid MCAP): one message's header stamp jumped
  by ±1000 s or set to 0 / the int32 limit, its log time set to 0 or ≥ 2^63, one float64
  field of it set to ±1e300, NaN or Inf.

Outcomes per input and reader: `error` (a `PhysfuseError`: one clear line), `flagged` (read,
with a warning or more skipped samples than the original), `exact` (every stream's times and
values equal the original's), `silent` (values changed with no flag — a failure) and
`crash` (any other exception — a failure). Prints a table and writes OUT/fuzz.json.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import struct
import sys
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.cli import main as physfuse  # noqa: E402
from estimator.config import Config, load_config  # noqa: E402
from estimator.errors import PhysfuseError  # noqa: E402
from estimator.io.logs import ByteStreamReader, Log, read_log  # noqa: E402

ORIGINALS = {"humanoid_push": "humanoid_push", "arm_box": "arm_box"}  # recording → config
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": None}
READERS = ("read_log", "byte_stream", "inspect")
FAILURES = ("crash", "silent")


@dataclass(frozen=True)
class Original:
    name: str
    config_path: Path
    data: bytes
    messages: (
        list  # (channel topic, schema name, schema encoding, schema data, enc, log_time, data)
    )


# -- the originals ----------------------------------------------------------------------------
def originals(seconds: float, chunk_size: int = 2048) -> list[Original]:
    """The first `seconds` of each bundled recording, rewritten per compression."""
    out = []
    for recording, config in ORIGINALS.items():
        with (ROOT / "recordings" / f"{recording}.mcap").open("rb") as f:
            reader = make_reader(f)
            t0 = reader.get_summary().statistics.message_start_time  # type: ignore[union-attr]
            messages = [
                (
                    channel.topic,
                    schema.name if schema else "",
                    schema.encoding if schema else "",
                    schema.data if schema else b"",
                    channel.message_encoding,
                    message.log_time,
                    message.data,
                )
                for schema, channel, message in reader.iter_messages(log_time_order=False)
                if message.log_time < t0 + seconds * 1e9
            ]
        for label, compression in COMPRESSIONS.items():
            data = write(messages, compression, chunk_size)
            path = ROOT / "configs" / f"{config}.toml"
            out.append(Original(f"{recording}/{label}", path, data, messages))
    return out


def write(messages: list, compression: CompressionType | None, chunk_size: int) -> bytes:
    """An MCAP file of `messages` (with their schemas and channels), chunked."""
    buf = io.BytesIO()
    writer = Writer(
        buf,
        chunk_size=chunk_size,
        compression=compression or CompressionType.NONE,
        use_chunking=True,
    )
    writer.start(profile="ros2", library="physfuse-fuzz")
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    for topic, name, encoding, schema_data, msg_encoding, log_time, data in messages:
        if name not in schemas:
            schemas[name] = writer.register_schema(name, encoding, schema_data)
        if topic not in channels:
            channels[topic] = writer.register_channel(topic, msg_encoding, schemas[name])
        writer.add_message(channels[topic], log_time, data, log_time)
    writer.finish()
    return buf.getvalue()


# -- mutations --------------------------------------------------------------------------------
def _flip_bits(rng: np.random.Generator, o: Original) -> bytes:
    data = bytearray(o.data)
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(len(data)))
        data[i] ^= 1 << int(rng.integers(8))
    return bytes(data)


def _span(rng: np.random.Generator, n: int) -> tuple[int, int]:
    start = int(rng.integers(n))
    return start, min(n, start + int(rng.integers(1, 65)))


def _overwrite(rng: np.random.Generator, o: Original) -> bytes:
    a, b = _span(rng, len(o.data))
    return o.data[:a] + rng.bytes(b - a) + o.data[b:]


def _zero(rng: np.random.Generator, o: Original) -> bytes:
    a, b = _span(rng, len(o.data))
    return o.data[:a] + bytes(b - a) + o.data[b:]


def _delete(rng: np.random.Generator, o: Original) -> bytes:
    a, b = _span(rng, len(o.data))
    return o.data[:a] + o.data[b:]


def _duplicate(rng: np.random.Generator, o: Original) -> bytes:
    a, b = _span(rng, len(o.data))
    return o.data[:b] + o.data[a:b] + o.data[b:]


def _truncate(rng: np.random.Generator, o: Original) -> bytes:
    return o.data[: int(rng.integers(len(o.data)))]


def _one_message(
    rng: np.random.Generator, o: Original, change: Callable[[np.random.Generator, tuple], tuple]
) -> bytes:
    """The original rewritten with one random message changed by `change`."""
    messages = list(o.messages)
    i = int(rng.integers(len(messages)))
    messages[i] = change(rng, messages[i])
    return write(messages, CompressionType.ZSTD, 2048)


def _stamp(rng: np.random.Generator, m: tuple) -> tuple:
    """Header stamp (CDR bytes 4–8: int32 sec, after the encapsulation header) jumped."""
    data = bytearray(m[6])
    if len(data) < 12 or m[1] in ("std_msgs/msg/Float64MultiArray", "tf2_msgs/msg/TFMessage"):
        return m  # no leading header: left as it is (read exactly)
    (sec,) = struct.unpack_from("<i", data, 4)
    choice = int(rng.integers(4))
    new = [sec + 1000, max(sec - 1000, 0), 0, 2**31 - 1][choice]
    struct.pack_into("<i", data, 4, new)
    return (*m[:6], bytes(data))


def _log_time(rng: np.random.Generator, m: tuple) -> tuple:
    new = [0, 1 << 63, (1 << 64) - 1, m[5] + 1000 * 10**9][int(rng.integers(4))]
    return (*m[:5], new, m[6])


def _float(rng: np.random.Generator, m: tuple) -> tuple:
    """One aligned float64 of the message (past its header) set to a value beyond physics."""
    data = bytearray(m[6])
    offsets = list(range(20, len(data) - 7, 8))  # CDR aligns to 8 after the 4-byte header
    if not offsets:
        return m
    i = offsets[int(rng.integers(len(offsets)))]
    value = [1e300, -1e300, float("nan"), float("inf")][int(rng.integers(4))]
    struct.pack_into("<d", data, i, value)
    return (*m[:6], bytes(data))


MUTATIONS: dict[str, Callable[[np.random.Generator, Original], bytes]] = {
    "flip_bits": _flip_bits,
    "overwrite": _overwrite,
    "zero": _zero,
    "delete": _delete,
    "duplicate": _duplicate,
    "truncate": _truncate,
    "stamp": lambda rng, o: _one_message(rng, o, _stamp),
    "log_time": lambda rng, o: _one_message(rng, o, _log_time),
    "float": lambda rng, o: _one_message(rng, o, _float),
}


# -- outcomes ---------------------------------------------------------------------------------
def _same(a: Log, b: Log) -> bool:
    """Every stream's times and values equal (NaN equal to NaN)."""
    for name, m in a.measurements.items():
        n = b.measurements[name]
        if not np.array_equal(m.t_ns, n.t_ns) or not np.array_equal(
            m.values, n.values, equal_nan=True
        ):
            return False
    return True


def _flagged(log: Log, original: Log) -> bool:
    skipped = sum(m.bad.total for m in log.measurements.values())
    return bool(log.warnings) or skipped > sum(m.bad.total for m in original.measurements.values())


def _outcome(read: Callable[[], Log], original: Log) -> tuple[str, str]:
    try:
        log = read()
    except PhysfuseError:
        return "error", ""
    except Exception as err:  # what the fuzzer hunts: anything not physfuse's own
        where = traceback.extract_tb(err.__traceback__)[-1]
        return "crash", f"{type(err).__name__} at {Path(where.filename).name}:{where.lineno}"
    if _same(log, original):
        return "exact", ""
    return ("flagged", "") if _flagged(log, original) else ("silent", "")


def _inspect(path: Path, config_path: Path) -> tuple[str, str]:
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            code = physfuse(["inspect", str(path), "--config", str(config_path)])
    except Exception as err:
        where = traceback.extract_tb(err.__traceback__)[-1]
        return "crash", f"{type(err).__name__} at {Path(where.filename).name}:{where.lineno}"
    return ("exact" if code == 0 else "error"), ""


def run_inputs(
    seed: int,
    n: int,
    seconds: float,
    readers: tuple[str, ...] = READERS,
    only: frozenset[str] | None = None,
) -> dict:
    """`n` mutated inputs from `seed`: outcome counts per (mutation, reader), crash sites.
    only: read just the inputs of these mutations (the same inputs as a whole run makes)."""
    rng = np.random.default_rng(seed)
    base = originals(seconds)
    configs: dict[Path, Config] = {o.config_path: load_config(o.config_path) for o in base}
    clean = {o.name: _read_bytes(o.data, configs[o.config_path]) for o in base}
    counts: Counter[tuple[str, str, str]] = Counter()
    crashes: Counter[str] = Counter()
    examples: dict[str, str] = {}
    names = list(MUTATIONS)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "input.mcap"
        for i in range(n):
            o = base[int(rng.integers(len(base)))]
            mutation = names[int(rng.integers(len(names)))]
            data = MUTATIONS[mutation](rng, o)
            if only is not None and mutation not in only:
                continue
            path.write_bytes(data)
            config = configs[o.config_path]
            results = _run_readers(readers, path, data, config, o.config_path, clean[o.name])
            for reader, (outcome, where) in results.items():
                counts[(mutation, reader, outcome)] += 1
                if outcome in FAILURES:
                    key = f"{reader} {outcome} {where}".strip()
                    crashes[key] += 1
                    examples.setdefault(key, f"seed {seed} input {i}: {o.name} {mutation}")
    return {
        "counts": [[*k, v] for k, v in sorted(counts.items())],
        "failures": dict(crashes),
        "examples": examples,
    }


def _run_readers(
    readers: tuple[str, ...],
    path: Path,
    data: bytes,
    config: Config,
    config_path: Path,
    original: Log,
) -> dict[str, tuple[str, str]]:
    """Outcome per reader of one mutated input (`data`, written at `path`)."""
    results = {}
    if "read_log" in readers:
        results["read_log"] = _outcome(lambda: read_log(path, config), original)
    if "byte_stream" in readers:
        results["byte_stream"] = _outcome(lambda: _read_bytes(data, config), original)
    if "inspect" in readers:
        results["inspect"] = _inspect(path, config_path)
    return results


def _read_bytes(data: bytes, config: Config) -> Log:
    return ByteStreamReader(io.BytesIO(data), config, require=False).read_all()


# -- the benchmark ----------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", type=int, default=100_000, help="mutated inputs in all")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes")
    parser.add_argument("--seed", type=int, default=0, help="first seed (one per batch)")
    parser.add_argument("--batch", type=int, default=500, help="inputs per batch")
    parser.add_argument("--seconds", type=float, default=0.1, help="of each recording")
    parser.add_argument(
        "--only",
        nargs="+",
        choices=list(MUTATIONS),
        help="read only these mutations' inputs (the same inputs a whole run makes)",
    )
    parser.add_argument("--out", type=Path, default=Path("out/fuzz"), help="output dir")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    batches = [
        (
            args.seed + b,
            min(args.batch, args.inputs - b * args.batch),
            args.seconds,
            frozenset(args.only) if args.only else None,
        )
        for b in range((args.inputs + args.batch - 1) // args.batch)
    ]
    total: Counter[tuple[str, str, str]] = Counter()
    failures: Counter[str] = Counter()
    examples: dict[str, str] = {}
    with ProcessPoolExecutor(args.jobs) as pool:
        for done, result in enumerate(pool.map(_batch, batches), 1):
            for mutation, reader, outcome, n in result["counts"]:
                total[(mutation, reader, outcome)] += n
            failures.update(result["failures"])
            for k, v in result["examples"].items():
                examples.setdefault(k, v)
            print(f"\rbatch {done}/{len(batches)}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    wall = time.perf_counter() - started
    report = _report(total, failures, examples, args, wall)
    _print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fuzz.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out / 'fuzz.json'}")
    return 0 if not failures else 1


def _batch(batch: tuple[int, int, float, frozenset[str] | None]) -> dict:
    seed, n, seconds, only = batch
    return run_inputs(seed, n, seconds, only=only)


def _report(total, failures, examples, args, wall) -> dict:
    outcomes = ("exact", "flagged", "error", *FAILURES)
    table = {}
    for mutation in MUTATIONS:
        for reader in READERS:
            row = {o: total[(mutation, reader, o)] for o in outcomes}
            if sum(row.values()):
                table[f"{mutation} / {reader}"] = row
    return {
        "inputs": args.inputs,
        "only": sorted(args.only) if args.only else None,
        "seed": args.seed,
        "seconds_of_each_recording": args.seconds,
        "outcomes": outcomes,
        "table": table,
        "failures": dict(failures),
        "failure_examples": examples,
        "totals": {o: sum(total[(m, r, o)] for m in MUTATIONS for r in READERS) for o in outcomes},
        "wall_time_s": wall,
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} cores, "
        f"Python {platform.python_version()}",
    }


def _print(report: dict) -> None:
    outcomes = report["outcomes"]
    print(f"{report['inputs']} mutated inputs, {report['wall_time_s']:.0f} s")
    print(f"{'mutation / reader':28s}" + "".join(f"{o:>9s}" for o in outcomes))
    for key, row in report["table"].items():
        print(f"{key:28s}" + "".join(f"{row[o]:9d}" for o in outcomes))
    print(f"{'total':28s}" + "".join(f"{report['totals'][o]:9d}" for o in outcomes))
    for where, n in sorted(report["failures"].items(), key=lambda kv: -kv[1]):
        print(f"  {n:6d}× {where}  (e.g. {report['failure_examples'][where]})")


if __name__ == "__main__":
    sys.exit(main())
