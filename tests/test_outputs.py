"""Outputs whole or not at all, and every way a run stops is one line (estimator/io/outputs.py).

Real `physfuse` processes on the smallest recording (single_joint, 3 s, `--method raw`: about
2 s a run, most of it start-up), killed with SIGKILL and SIGINT while they read, estimate and
write; after each, --out holds the previous complete set or the new one, never a part or a mix.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import rerun as rr
from mcap.reader import make_reader
from mcap.writer import Writer

from estimator.cli import main
from estimator.io import outputs
from estimator.io.outputs import OutputFile, OutputFolder

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "recordings" / "single_joint.mcap"
CONFIG = ROOT / "configs" / "single_joint.toml"
FAST = ["--method", "raw", "--quiet"]
SET = ("estimate.mcap", "estimate.rrd", "summary.json")


def estimate_argv(out: Path, log: Path = LOG, *extra: str) -> list[str]:
    return ["estimate", str(log), "--config", str(CONFIG), "--out", str(out), *FAST, *extra]


def start(argv: list[str], **kwargs) -> subprocess.Popen:
    """A physfuse run in a child process, with Ctrl-C's default disposition: started from a
    shell's background job (`make test &`) it would inherit SIGINT ignored."""
    return subprocess.Popen(
        [sys.executable, "-m", "estimator.cli", *argv],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        **kwargs,
    )


def temporary(out: Path, pid: int | str = "*") -> list[Path]:
    """The temporary folders of runs on `out` (beside it), or of the run of process `pid`."""
    return sorted(out.parent.glob(f".{out.name}.tmp-{pid}-*"))


Phase = Callable[[Path, int], bool]


def writing(name: str | None) -> Phase:
    """A phase of the run of process `pid` on `out`: its temporary folder made (name None:
    the log is being read), or `name` begun in it."""

    def reached(out: Path, pid: int) -> bool:
        return any(name is None or (t / name).exists() for t in temporary(out, pid))

    return reached


def run_until(
    argv: list[str], out: Path, phase: Phase, sig: int, snapshot: Callable[[], Any] = lambda: None
) -> tuple[int, str, int, Any]:
    """Start a run, send `sig` once it reaches `phase` (sent while the run is stopped, so
    that it lands there): (exit status, stderr, process id, `snapshot()` taken just before
    that run started). A run that ends before this process sees it reach the phase (a busy
    machine: it polls every 2 ms) is started again, up to 5 times."""
    for _ in range(5):
        before = snapshot()
        proc = start(argv)
        deadline = time.monotonic() + 60
        while proc.poll() is None and not phase(out, proc.pid) and time.monotonic() < deadline:
            time.sleep(0.002)
        sent = proc.poll() is None
        if sent:
            proc.send_signal(signal.SIGSTOP)
            proc.send_signal(sig)
            proc.send_signal(signal.SIGCONT)
        _, err = proc.communicate(timeout=60)
        if sent:
            break
    return proc.returncode, err, proc.pid, before


def read_set(out: Path) -> str | None:
    """The run id of the complete set in `out` (None: no set), after checking every file
    reads back whole and all three come from that one run."""
    if not out.exists() or not any((out / n).exists() for n in SET):
        return None
    summary = json.loads((out / "summary.json").read_text())
    with (out / "estimate.mcap").open("rb") as f:
        reader = make_reader(f)
        stated = reader.get_summary().statistics.message_count
        read = sum(1 for _ in reader.iter_messages())
        (meta,) = [m for m in reader.iter_metadata() if m.name == "physfuse.estimate"]
    assert read == stated > 0, (read, stated)
    rrd = rr.chunk.RrdReader(out / "estimate.rrd")
    (recording,) = rrd.recordings()
    assert rrd.stream().to_chunks(), "estimate.rrd holds no data"
    assert meta.metadata["run_id"] == recording.recording_id == summary["run_id"]
    return summary["run_id"]


# -- a run stopped at any moment ------------------------------------------------------------------
def test_a_killed_run_leaves_the_previous_set_or_the_new_one(tmp_path, capsys):
    out = tmp_path / "o"
    first = start(estimate_argv(out))
    assert first.wait(60) == 0, first.communicate()
    previous = read_set(out)
    assert previous is not None and not temporary(out)
    (out / "notes.txt").write_text("mine")  # not the set's: kept through every run
    # killed while reading the log and while writing each file; the later the kill, the
    # nearer the swap (right after the summary, the last file): there the new set may be in
    reading, mcap = writing(None), writing("estimate.mcap")
    for phase in (reading, mcap, writing("estimate.rrd"), writing("summary.json")):
        code, err, _, previous = run_until(
            estimate_argv(out), out, phase, signal.SIGKILL, lambda: read_set(out)
        )
        assert code == -signal.SIGKILL, (code, err)
        now = read_set(out)  # complete, and from one run: raises otherwise
        assert now == previous or (phase not in (reading, mcap) and now is not None)
        assert (out / "notes.txt").read_text() == "mine"
        previous = now
    assert temporary(out), "a killed run leaves its temporary folder (removed by the next)"

    # Ctrl-C while writing: exit 130, one line, its temporary folder removed
    code, err, pid, previous = run_until(
        estimate_argv(out), out, writing("estimate.mcap"), signal.SIGINT, lambda: read_set(out)
    )
    assert code == 130 and err == "physfuse estimate: interrupted\n", (code, err)
    assert read_set(out) == previous and not temporary(out, pid)

    # a second run on the same --out is refused while the first holds it (stopped there),
    # before its log is read (the log named here does not exist)
    proc = start(estimate_argv(out))
    deadline = time.monotonic() + 60
    while not writing(None)(out, proc.pid) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    proc.send_signal(signal.SIGSTOP)
    try:
        assert main(estimate_argv(out, tmp_path / "none.mcap")) == 2
    finally:
        proc.send_signal(signal.SIGCONT)
        assert proc.wait(60) == 0, proc.communicate()
    err = capsys.readouterr().err
    assert err == f"physfuse estimate: error: --out {out}: {outputs.BUSY}\n"
    new = read_set(out)
    assert new is not None and new != previous
    assert not temporary(out), "the leftovers of killed runs are removed"
    assert sorted(p.name for p in out.iterdir()) == sorted([*SET, "notes.txt"])


def test_a_closed_stdout_ends_quietly_with_the_outputs_written(tmp_path):
    """`physfuse estimate ... | head -3`: the reader gone before the summary is printed."""
    proc = start(estimate_argv(tmp_path / "o"))
    assert proc.stdout is not None
    proc.stdout.close()
    err = proc.stderr.read() if proc.stderr else ""
    assert proc.wait(60) == 141
    assert "Traceback" not in err and "Exception ignored" not in err and err == "", err
    assert read_set(tmp_path / "o") is not None


# -- --out checked before any work ----------------------------------------------------------------
def one_line_error(capsys, argv: list[str]) -> str:
    start_s = time.perf_counter()
    assert main(argv) == 2
    assert time.perf_counter() - start_s < 5
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("physfuse estimate: error: "), err
    return err


def test_an_unusable_out_is_one_line_before_the_log_is_read(tmp_path, capsys):
    """Each case names --out, not the log (which does not exist): --out comes first."""
    none = tmp_path / "none.mcap"
    blocked = tmp_path / "blocked"
    (blocked / "estimate.mcap").mkdir(parents=True)
    err = one_line_error(capsys, estimate_argv(blocked, none))
    assert f"--out {blocked}: {blocked}/estimate.mcap is a folder" in err
    (tmp_path / "file").write_text("")
    err = one_line_error(capsys, estimate_argv(tmp_path / "file", none))
    assert "is a file, expected a folder" in err
    err = one_line_error(capsys, estimate_argv(Path("/proc/physfuse/o"), none))
    assert "--out /proc/physfuse/o: cannot create the folder" in err
    busy = tmp_path / "shared"
    (busy / "runs").mkdir(parents=True)
    err = one_line_error(capsys, estimate_argv(busy, none))
    assert "holds the folder 'runs'" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocked", "file", "shared"]


def test_a_read_only_out_is_one_line_before_the_log_is_read(tmp_path, capsys):
    none = tmp_path / "none.mcap"
    if os.geteuid() != 0:  # permissions: root passes them
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        try:
            err = one_line_error(capsys, estimate_argv(locked / "o", none))
            assert f"--out {locked}/o: cannot create the folder (Permission denied)" in err
            err = one_line_error(capsys, estimate_argv(locked, none))
            assert f"--out {locked}: is not writable" in err
        finally:
            locked.chmod(0o700)
    # immutable (chattr +i): read-only for root too
    frozen = tmp_path / "frozen"
    (frozen / "o").mkdir(parents=True)
    made = subprocess.run(["chattr", "+i", str(frozen)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"chattr +i: {made.stderr.decode().strip()}")
    try:
        err = one_line_error(capsys, estimate_argv(frozen / "o", none))
        assert f"--out {frozen}/o: cannot write in {frozen}" in err
    finally:
        subprocess.run(["chattr", "-i", str(frozen)], check=True)


# -- viewers and skipped samples -----------------------------------------------------------------
def test_a_viewer_that_cannot_open_leaves_the_recording_and_says_how_to_open_it(
    tmp_path, capsys, monkeypatch
):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = tmp_path / "o"
    assert main(estimate_argv(out, LOG, "--spawn")) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--spawn needs a display" in err
    assert err.startswith("physfuse estimate: warning: ")
    assert err.rstrip().endswith(f"rerun {out}/estimate.rrd)")
    assert read_set(out) is not None


def with_bad_samples(source: Path, target: Path, topic: str, copies: int) -> None:
    """A copy of a log with `copies` extra copies of one message of `topic` (the same time:
    skipped as duplicate_time)."""
    with source.open("rb") as f, target.open("wb") as o:
        reader = make_reader(f)
        writer = Writer(o)
        writer.start(profile="ros2", library="test")
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, dict(meta.metadata))
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        done = False
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            repeat = 1 + copies if channel.topic == topic and not done else 1
            done = done or channel.topic == topic
            for _ in range(repeat):
                writer.add_message(
                    channels[channel.id], message.log_time, message.data, message.publish_time
                )
        writer.finish()


def test_skipped_samples_are_printed_and_in_the_summary(tmp_path, capsys):
    log = tmp_path / "dup.mcap"
    with_bad_samples(LOG, log, "/joint_states", 2)
    out = tmp_path / "o"
    assert main(estimate_argv(out, log)) == 0
    err = capsys.readouterr().err
    assert "physfuse estimate: joints: skipped 2 of 1502 samples (duplicate_time=2)\n" in err
    skipped = json.loads((out / "summary.json").read_text())["skipped_samples"]
    assert skipped["joints"] == {"kept": 1500, "skipped": 2, "by_reason": {"duplicate_time": 2}}
    assert skipped["command"] == {"kept": 1500, "skipped": 0, "by_reason": {}}


# -- the helpers themselves ----------------------------------------------------------------------
def test_an_error_inside_keeps_the_previous_set_and_a_swap_keeps_other_files(tmp_path):
    out = tmp_path / "o"
    with OutputFolder(out, ("a", "b")) as tmp:
        (tmp / "a").write_text("1")
        (tmp / "b").write_text("1")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(KeyError), OutputFolder(out, ("a", "b")) as tmp:
        (tmp / "a").write_text("2")
        raise KeyError("stopped")
    assert [(out / n).read_text() for n in ("a", "b", "notes.txt")] == ["1", "1", "mine"]
    with OutputFolder(out, ("a", "b")) as tmp:
        (tmp / "a").write_text("2")
        (tmp / "b").write_text("2")
    assert [(out / n).read_text() for n in ("a", "b", "notes.txt")] == ["2", "2", "mine"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]
    with OutputFolder(out, ("a", "b")) as tmp:
        with pytest.raises(outputs.OutputError, match="writing it"), OutputFolder(out, ("a",)):
            pass  # a second holder of the lock (in this process too)
        (tmp / "a").write_text("3")
        (tmp / "b").write_text("3")
    with pytest.raises(RuntimeError, match="did not write a"), OutputFolder(out, ("a",)):
        pass
    assert (out / "a").read_text() == "3"


def test_without_an_atomic_exchange_the_fallback_swap_recovers(tmp_path, monkeypatch):
    """Where renameat2(RENAME_EXCHANGE) is missing: --out renamed aside, the new one in. A
    run killed between the two renames leaves the previous set aside; the next run puts it
    back before anything else."""
    monkeypatch.setattr(outputs, "_renameat2", lambda: None)
    out = tmp_path / "o"
    for value in ("1", "2"):
        with OutputFolder(out, ("a",)) as tmp:
            (tmp / "a").write_text(value)
    assert (out / "a").read_text() == "2" and sorted(os.listdir(tmp_path)) == ["o"]
    out.rename(tmp_path / ".o.old-1-x")  # killed between the renames
    with pytest.raises(KeyError), OutputFolder(out, ("a",)):
        assert (out / "a").read_text() == "2"  # back in place first
        raise KeyError("stopped")
    assert (out / "a").read_text() == "2" and sorted(os.listdir(tmp_path)) == ["o"]


def test_a_single_file_is_replaced_whole(tmp_path):
    path = tmp_path / "x.json"
    outputs.write_file(path, "1")
    with pytest.raises(KeyError), OutputFile(path) as tmp:
        tmp.write_text("2")
        raise KeyError("stopped")
    assert path.read_text() == "1" and sorted(os.listdir(tmp_path)) == ["x.json"]
    with OutputFile(path, keep_unchanged=True) as tmp:
        tmp.write_text("1")
    outputs.write_file(path, "3")
    assert path.read_text() == "3" and sorted(os.listdir(tmp_path)) == ["x.json"]
    (tmp_path / "d").mkdir()
    with pytest.raises(outputs.OutputError, match="is a directory"), OutputFile(tmp_path / "d"):
        pass


def test_a_killed_simulate_leaves_the_previous_log(tmp_path):
    log = tmp_path / "x.mcap"
    argv = ["simulate", "single_joint", "--duration", "0.2", "--quiet", "--out", str(log)]
    assert main(argv) == 0
    code, _, _, before = run_until(
        [*argv[:3], "1.0", *argv[4:], "--seed", "1"],
        log,
        lambda p, pid: bool(list(p.parent.glob(f".x.mcap.tmp-{pid}-*"))),
        signal.SIGKILL,
        log.read_bytes,
    )
    assert code == -signal.SIGKILL
    assert log.read_bytes() == before


def test_a_reader_of_out_sees_one_whole_set_at_every_instant(tmp_path):
    """While runs swap sets in, --out always names a folder, and a reader that opens it reads
    one complete set (renameat2 RENAME_EXCHANGE: the name never points at nothing or a mix)."""
    if outputs._renameat2() is None:
        pytest.skip("no renameat2 here: the fallback swap leaves a moment without --out")
    out = tmp_path / "o"
    with OutputFolder(out, ("a", "b")) as tmp:
        (tmp / "a").write_text("0")
        (tmp / "b").write_text("0")
    seen: list[tuple[str, str]] = []
    errors: list[BaseException] = []
    done = threading.Event()

    def read() -> None:
        while not done.is_set():
            try:
                folder = os.open(out, os.O_RDONLY | os.O_DIRECTORY)  # never missing
            except BaseException as err:
                errors.append(err)
                return
            try:
                pair = []
                for name in ("a", "b"):
                    fd = os.open(name, os.O_RDONLY, dir_fd=folder)
                    pair.append(os.read(fd, 16).decode())
                    os.close(fd)
                seen.append((pair[0], pair[1]))
            except FileNotFoundError:
                pass  # a set swapped out meanwhile is deleted: gone, never mixed
            finally:
                os.close(folder)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for k in range(1, 101):
            with OutputFolder(out, ("a", "b")) as tmp:
                (tmp / "a").write_text(str(k))
                (tmp / "b").write_text(str(k))
    finally:
        done.set()
        reader.join()
    assert not errors, errors
    assert len(seen) > 100 and all(a == b for a, b in seen), [p for p in seen if p[0] != p[1]]
    assert (out / "a").read_text() == "100"
