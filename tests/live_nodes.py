"""The streaming node's processes for the tests: `physfuse replay` on a free loopback port and
`physfuse stream` against it, on the smallest bundled recording."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
NAME = "single_joint"  # the smallest bundled recording: 3 s, 1 500 knots
LOG = ROOT / "recordings" / f"{NAME}.mcap"
CONFIG = ROOT / "configs" / f"{NAME}.toml"
PHYSFUSE = [sys.executable, "-m", "estimator.cli"]


def replay(rate: float) -> tuple[subprocess.Popen, int]:
    """`physfuse replay` of the recording on a free loopback port: (process, port)."""
    proc = subprocess.Popen(
        [*PHYSFUSE, "replay", str(LOG), "--to", "tcp://127.0.0.1:0", "--rate", str(rate)],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    line = proc.stderr.readline()  # "physfuse replay: serving ... on port N"
    assert "on port" in line, line
    return proc, int(line.rsplit(" ", 1)[1])


def stream(source: str, out: Path | None, *more: str) -> subprocess.Popen:
    """`physfuse stream` of the recording's config from `source` (`--out out` if given)."""
    return subprocess.Popen(
        [*PHYSFUSE, "stream", "--config", str(CONFIG), "--source", source]
        + ([] if out is None else ["--out", str(out)])
        + list(more),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for_size(path: Path, size: int, timeout_s: float = 120.0) -> None:
    """Until the file holds `size` bytes (a node's first updates are out)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (not path.exists() or path.stat().st_size < size):
        time.sleep(0.05)


def stop(*processes: subprocess.Popen) -> None:
    for proc in processes:
        proc.kill()
        proc.wait(timeout=30)
