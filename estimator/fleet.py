"""Many logs at once: `physfuse estimate LOG... --workers N | --ray-address ADDR`.

Each log is one Ray task that runs the single-log command (`physfuse estimate LOG --config
CONFIG --out DIR/<name>`) in a Ray worker, its terminal output kept in DIR/<name>.txt. A log
that fails is reported with its one-line error and the others go on; a task whose worker
dies (killed, out of memory, a lost node) is retried by Ray (RETRIES); DIR/fleet.csv and
DIR/fleet.json sum the fleet up, one row per log.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import io
import json
import logging
import os
import socket
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from estimator.errors import ConfigError

RETRIES = 2  # a task whose worker process dies is run again, up to this many times
LIST_SUFFIXES = (".txt", ".list")  # a file of log paths, one per line
COLUMNS = (
    "log",
    "status",
    "error",
    "duration_s",
    "wall_s",
    "position_mm",
    "joint_deg",
    "node",
    "node_id",
    "out",
)


@dataclass
class LogResult:
    """One log of a fleet: `status` ok | failed (with `error`, its one line)."""

    log: str
    status: str
    error: str = ""
    duration_s: float | None = None
    wall_s: float | None = None
    position_mm: float | None = None  # against ground truth where the log has it: bodies' mean
    joint_deg: float | None = None
    node: str = ""  # the host that ran it
    node_id: str = ""  # and its Ray node
    out: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def expand_logs(items: Sequence[Path]) -> list[Path]:
    """The logs named by `items`: files, globs, folders (their MCAP files and rosbag2
    folders; a folder with metadata.yaml is one rosbag2 log) and list files (.txt / .list:
    one path per line, relative to the list; # comments). Raises ConfigError naming an item
    that names no log."""
    logs: list[Path] = []
    for item in items:
        text = str(item)
        if any(c in text for c in "*?["):
            matched = sorted(Path(p) for p in glob.glob(text, recursive=True))
            found = [p for p in matched if _is_log(p)]
        elif item.is_dir():
            found = [item] if (item / "metadata.yaml").exists() else _logs_in(item)
        elif item.suffix in LIST_SUFFIXES and item.is_file():
            lines = [ln.split("#", 1)[0].strip() for ln in item.read_text().splitlines()]
            found = expand_logs([item.parent / ln for ln in lines if ln])
        else:
            found = [item]  # a file (or a FIFO, or "-"): the single-log command checks it
        if not found:
            raise ConfigError(
                f"{item}: no log there (expected .mcap files or rosbag2 folders with metadata.yaml)"
            )
        logs += found
    return list(dict.fromkeys(logs))


def _is_log(path: Path) -> bool:
    return path.suffix == ".mcap" or (path / "metadata.yaml").exists()


def _logs_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if _is_log(p))


def output_names(logs: Sequence[Path]) -> list[str]:
    """A folder name per log: its stem, with its parent folders' names where stems repeat."""
    stems = [log.stem if log.suffix == ".mcap" else log.name for log in logs]
    names, depth = stems, 0
    while len(set(names)) < len(names) and depth < 8:
        depth += 1
        names = [
            "_".join([*log.parts[-depth - 1 : -1], stem])
            for log, stem in zip(logs, stems, strict=True)
        ]
    return names


def config_for(log: Path, config: Path) -> Path:
    """The config of one log: `config` itself, or FOLDER/<log name>.toml for a folder."""
    if not config.is_dir():
        return config
    name = log.stem if log.suffix == ".mcap" else log.name
    path = config / f"{name}.toml"
    if not path.exists():
        raise ConfigError(f"{log}: no config for it: expected {path} (--config is a folder)")
    return path


def estimate_one(argv: list[str], transcript: str) -> dict[str, Any]:
    """Run `physfuse estimate` with argv in this process (a Ray worker, one CPU: MuJoCo on one
    thread), its output into `transcript`; its exit code, its error line and where it ran."""
    import ray

    from estimator.cli import main

    buffer = io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
        try:
            code = main(["estimate", *argv])
        except Exception as err:  # a bug: reported for this log, and the fleet goes on
            print(f"physfuse estimate: internal error: {type(err).__name__}: {err}")
            code = 70
    text = buffer.getvalue()
    Path(transcript).write_text(f"$ physfuse estimate {' '.join(argv)}\n{text}")
    errors = [
        ln for ln in text.splitlines() if ln.startswith("physfuse estimate:") and " error" in ln
    ]
    return {
        "code": code,
        "error": errors[-1].removeprefix("physfuse estimate: ").removeprefix("error: ")
        if errors
        else "",
        "wall_s": time.perf_counter() - start,
        "node": socket.gethostname(),
        "node_id": ray.get_runtime_context().get_node_id() if ray.is_initialized() else "",
        "pid": os.getpid(),
    }


def run_fleet(
    logs: Sequence[Path],
    config: Path,
    out: Path,
    options: list[str],
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[LogResult, int, int], None] | None = None,
) -> list[LogResult]:
    """Estimate every log as a Ray task, DIR/<name> per log; the fleet's rows (also written
    to out/fleet.csv and out/fleet.json)."""
    import ray

    names = output_names(logs)
    out.mkdir(parents=True, exist_ok=True)
    jobs: list[tuple[Path, str, list[str] | None, str]] = []
    for log, name in zip(logs, names, strict=True):
        try:
            where = ["--config", str(config_for(log, config)), "--out", str(out / name)]
            jobs.append((log, name, [str(log), *where, "--quiet", *options], ""))
        except ConfigError as err:
            jobs.append((log, name, None, str(err)))
    with ray_session(workers, address):
        task = as_task(estimate_one)
        pending: dict[Any, tuple[Path, str]] = {}
        results: dict[str, LogResult] = {}
        # the largest logs first: the fleet ends sooner than when a long one starts last
        for log, name, argv, error in sorted(jobs, key=lambda job: -_size(job[0])):
            if argv is None:
                results[name] = LogResult(str(log), "failed", error=error)
                continue
            ref = task.remote(argv, str(out / f"{name}.txt"))
            pending[ref] = (log, name)
        done = len(results)
        for name in results:
            if progress:
                progress(results[name], done, len(jobs))
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            log, name = pending.pop(ready[0])
            try:
                outcome = ray.get(ready[0])
                result = _row(log, out / name, outcome)
            except ray.exceptions.RayError as err:  # retries spent: a worker kept dying
                line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                result = LogResult(str(log), "failed", error=f"{type(err).__name__}: {line}")
            results[name] = result
            done += 1
            if progress:
                progress(result, done, len(jobs))
    rows = [results[name] for _, name, _, _ in jobs]
    write_summary(out, rows)
    return rows


def as_task(function: Callable[..., Any], env_vars: Mapping[str, str] | None = None) -> Any:
    """`function` as a Ray task of one CPU, MuJoCo on one thread there (PHYSFUSE_THREADS, read
    when the estimator is imported), run again when its worker dies; env_vars: more of its
    workers' environment."""
    import ray

    env = {"env_vars": {"PHYSFUSE_THREADS": "1", **(env_vars or {})}}
    return ray.remote(num_cpus=1, max_retries=RETRIES, runtime_env=env)(function)


@contextlib.contextmanager
def ray_session(workers: int | None = None, address: str | None = None) -> Iterator[None]:
    """Ray for the block: connected to the cluster at `address`, or a local Ray of `workers`
    CPUs (default: the cores) started and stopped here; one already initialized is used."""
    import ray

    if ray.is_initialized():
        yield
        return
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": logging.ERROR,  # Ray's start-up lines: physfuse prints its own
    }
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray.init(num_cpus=workers or os.cpu_count() or 1, **kwargs)
    try:
        yield
    finally:
        ray.shutdown()


def _size(log: Path) -> int:
    """Bytes of a log file or rosbag2 folder (0 for what is neither)."""
    if log.is_file():
        return log.stat().st_size
    if log.is_dir():
        return sum(p.stat().st_size for p in log.rglob("*") if p.is_file())
    return 0


def _row(log: Path, folder: Path, outcome: dict[str, Any]) -> LogResult:
    """A finished task's row: from its summary.json when it wrote one."""
    result = LogResult(
        str(log),
        "ok" if outcome["code"] == 0 else "failed",
        error=outcome["error"] if outcome["code"] != 0 else "",
        wall_s=outcome["wall_s"],
        node=outcome["node"],
        node_id=outcome.get("node_id", ""),
        out=str(folder) if outcome["code"] == 0 else "",
    )
    if outcome["code"] != 0 and not result.error:
        result.error = f"exit status {outcome['code']} (see {folder}.txt)"
    summary = folder / "summary.json"
    if outcome["code"] == 0 and summary.exists():
        report = json.loads(summary.read_text())
        result.duration_s = report.get("duration_s")
        accuracy = (report.get("accuracy_vs_ground_truth") or {}).get("estimate") or {}
        positions = [v for k, v in accuracy.items() if k.endswith("_pos_mm")]
        result.position_mm = sum(positions) / len(positions) if positions else None
        result.joint_deg = accuracy.get("joint_deg")
    return result


def write_summary(out: Path, rows: Sequence[LogResult]) -> None:
    """out/fleet.csv and out/fleet.json, one row per log, each file written whole."""
    records = [{k: v for k, v in asdict(r).items() if k in COLUMNS} for r in rows]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(COLUMNS))
    writer.writeheader()
    writer.writerows(records)
    for name, content in (
        ("fleet.csv", text.getvalue()),
        ("fleet.json", json.dumps(records, indent=2) + "\n"),
    ):
        partial = out / f".{name}.partial"
        partial.write_text(content)
        partial.replace(out / name)


def table(rows: Sequence[LogResult]) -> str:
    """The fleet as a terminal table."""
    lines = [f"{'log':40s} {'status':7s} {'log s':>7s} {'wall s':>7s} {'pos mm':>8s}  error"]
    for r in rows:
        lines.append(
            f"{Path(r.log).name[:40]:40s} {r.status:7s} {_num(r.duration_s, 7, 2)} "
            f"{_num(r.wall_s, 7, 1)} {_num(r.position_mm, 8, 3)}  {r.error}"
        )
    ok = sum(r.status == "ok" for r in rows)
    lines.append(f"{ok} of {len(rows)} logs estimated")
    return "\n".join(lines)


def _num(value: float | None, width: int, digits: int) -> str:
    return f"{value:{width}.{digits}f}" if value is not None else f"{'—':>{width}s}"


def task_processes() -> list[int]:
    """PIDs of this machine's Ray workers inside a fleet task (Ray titles a worker by the task
    it runs: ray::estimate_one), read from /proc; [] where there is no /proc."""
    pids = []
    proc = Path("/proc")
    for entry in proc.iterdir() if proc.is_dir() else []:
        if entry.name.isdigit():
            try:
                if (entry / "cmdline").read_bytes().startswith(b"ray::estimate_one"):
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


class Progress:
    """The fleet's progress on stderr: one bar on a terminal, a line per finished log
    otherwise; a failed log's line either way."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=0, unit="log", disable=not sys.stderr.isatty())

    def __call__(self, result: LogResult, done: int, total: int) -> None:
        failed = f"{result.log}: failed: {result.error}"
        if self.bar.disable:
            what = "ok" if result.status == "ok" else failed
            print(f"[{done}/{total}] {result.log}: {what}", file=sys.stderr, flush=True)
            return
        self.bar.total = total
        if result.status != "ok":
            self.bar.write(failed, file=sys.stderr)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        self.bar.close()
