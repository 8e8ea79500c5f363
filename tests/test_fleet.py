"""Many logs as Ray tasks (estimator/fleet.py): which logs a command line names, one folder
per log, a bad log reported in one line while the others go on, and a task whose worker is
killed run again — on a real local Ray."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tomlkit

from estimator.errors import ConfigError
from estimator.fleet import expand_logs, output_names, task_processes
from estimator.io.state_topics import read_state_topics

ROOT = Path(__file__).resolve().parent.parent
PHYSFUSE = [sys.executable, "-m", "estimator.cli"]


def test_logs_are_named_by_files_globs_folders_and_lists(tmp_path):
    for name in ("a.mcap", "b.mcap", "notes.md"):
        (tmp_path / name).write_bytes(b"")
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    listed = tmp_path / "logs.txt"
    listed.write_text("b.mcap  # the second\n\n# a comment line\nbag\n")
    assert expand_logs([tmp_path]) == [tmp_path / "a.mcap", tmp_path / "b.mcap", bag]
    assert expand_logs([Path(f"{tmp_path}/*.mcap")]) == [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    assert expand_logs([listed, tmp_path / "b.mcap"]) == [tmp_path / "b.mcap", bag]
    assert expand_logs([bag]) == [bag]  # a rosbag2 folder is one log
    with pytest.raises(ConfigError, match=r"\*\.db3: no log there"):
        expand_logs([Path(f"{tmp_path}/*.db3")])


def test_logs_of_the_same_name_take_their_folders_names():
    logs = [Path("day1/robot/run.mcap"), Path("day2/robot/run.mcap"), Path("day2/other.mcap")]
    assert output_names(logs) == ["day1_robot_run", "day2_robot_run", "day2_other"]
    assert output_names([Path("x/a.mcap"), Path("y/b.mcap")]) == ["a", "b"]


def _run(args, **kwargs):
    return subprocess.run(
        [*PHYSFUSE, *args], capture_output=True, text=True, cwd=ROOT, timeout=600, **kwargs
    )


def test_a_fleet_estimates_each_log_and_reports_a_bad_one_in_one_line(tmp_path):
    """Two logs on a local Ray of 2 workers, the configs from a folder: the good one gets
    its whole output folder; the one that is not an MCAP file is one line in the table and
    in fleet.json, and the status is 1."""
    configs = tmp_path / "configs"
    configs.mkdir()
    shutil.copy(ROOT / "configs" / "single_joint.toml", configs / "single_joint.toml")
    shutil.copy(ROOT / "configs" / "single_joint.toml", configs / "broken.toml")
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap file")
    out = tmp_path / "out"
    done = _run(
        [
            "estimate",
            "recordings/single_joint.mcap",
            str(broken),
            "--config",
            str(configs),
            "--out",
            str(out),
            "--workers",
            "2",
            "--method",
            "raw",
        ]
    )
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    rows = {Path(r["log"]).name: r for r in json.loads((out / "fleet.json").read_text())}
    assert rows["single_joint.mcap"]["status"] == "ok"
    assert rows["single_joint.mcap"]["duration_s"] == pytest.approx(3.0, abs=0.05)
    assert rows["broken.mcap"]["status"] == "failed"
    assert rows["broken.mcap"]["error"] == f"{broken}: not an MCAP file (starts with b'not an m')"
    assert sorted(p.name for p in (out / "single_joint").iterdir()) == [
        "estimate.mcap",
        "estimate.rrd",
        "summary.json",
    ]
    assert not (out / "broken").exists()  # an output folder is whole or absent
    assert (out / "fleet.csv").read_text().count("\n") == 3  # header and one row per log
    assert "1 of 2 logs estimated" in done.stdout


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the Ray worker through /proc")
def test_a_task_whose_worker_is_killed_runs_again_with_the_same_result(tmp_path):
    """The log is a FIFO, so the task waits on it; its worker is SIGKILLed there; Ray runs
    the task again on a new worker, which then reads the log: the estimate is the one a
    single process makes of the same log."""
    fifo = tmp_path / "single_joint.mcap"
    os.mkfifo(fifo)
    config = str(ROOT / "configs" / "single_joint.toml")
    out = tmp_path / "fleet"
    fleet = subprocess.Popen(
        [
            *PHYSFUSE,
            "estimate",
            str(fifo),
            "--config",
            config,
            "--out",
            str(out),
            "--workers",
            "1",
            "--method",
            "raw",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        killed = _wait_for(task_processes)
        os.kill(killed[0], signal.SIGKILL)
        retried = _wait_for(lambda: [p for p in task_processes() if p not in killed])
        assert retried
        writer = threading.Thread(
            target=lambda: fifo.write_bytes(
                (ROOT / "recordings" / "single_joint.mcap").read_bytes()
            )
        )
        writer.start()
        _, stderr = fleet.communicate(timeout=300)
        writer.join(timeout=60)
    finally:
        fleet.kill()
    assert fleet.returncode == 0, stderr
    single = tmp_path / "single"
    done = _run(
        [
            "estimate",
            "recordings/single_joint.mcap",
            "--config",
            config,
            "--out",
            str(single),
            "--method",
            "raw",
            "--quiet",
        ]
    )
    assert done.returncode == 0, done.stderr
    by_fleet = read_state_topics(out / "single_joint" / "estimate.mcap", prefix="/estimate")
    alone = read_state_topics(single / "estimate.mcap", prefix="/estimate")
    assert by_fleet.joint_names == alone.joint_names
    np.testing.assert_array_equal(by_fleet.joints.t_ns, alone.joints.t_ns)
    np.testing.assert_array_equal(by_fleet.joints.values, alone.joints.values)


def _wait_for(find, timeout_s: float = 120.0):
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        found = find()
        if found:
            return found
        time.sleep(0.2)
    raise AssertionError(f"nothing found in {timeout_s} s")


def test_a_log_in_chunks_on_two_workers_is_the_one_process_estimate_within_its_sigma(tmp_path):
    """humanoid_push in chunks of 2 s seen 1 s past each end, on 2 workers: the same knots
    as one process, and a torso position within its reported σ of one process's at every
    knot (the joins included)."""
    base = ["estimate", "recordings/humanoid_push.mcap", "--config", "configs/humanoid_push.toml"]
    one, chunked = tmp_path / "one", tmp_path / "chunked"
    for out, extra in (
        (one, []),
        (chunked, ["--chunk", "2", "--chunk-overlap", "1", "--workers", "2"]),
    ):
        done = _run([*base, "--out", str(out), "--method", "kinematic", "--quiet", *extra])
        assert done.returncode == 0, done.stderr
    a = read_state_topics(one / "estimate.mcap", prefix="/estimate").odometry["torso"]
    b = read_state_topics(chunked / "estimate.mcap", prefix="/estimate").odometry["torso"]
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    sigma = np.sqrt(a.values[:, [13, 17, 21]])
    assert np.all(np.abs(a.values[:, :3] - b.values[:, :3]) < sigma)
    summary = json.loads((chunked / "summary.json").read_text())
    assert summary["knots"] == len(a.t_ns) and summary["windows"] == 2
    # each chunk read its own slice of the file: every sample counted once, as one read does
    whole = json.loads((one / "summary.json").read_text())
    assert summary["skipped_samples"] == whole["skipped_samples"]
    raw, chunked_raw = (s["accuracy_vs_ground_truth"]["raw"] for s in (whole, summary))
    assert chunked_raw.keys() == raw.keys()
    for metric, value in raw.items():  # the same measurements on the same knots
        assert chunked_raw[metric] == pytest.approx(value, rel=1e-9), metric


def test_chunks_need_a_log_they_can_slice(tmp_path):
    """--chunk on a FIFO: one line saying why, nothing written."""
    fifo = tmp_path / "live.mcap"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    config = "configs/single_joint.toml"
    done = _run(["estimate", str(fifo), "--config", config, "--chunk", "1", "--out", str(out)])
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "record it to a file" in done.stderr, done.stderr
    assert not (tmp_path / "out").exists()


def test_chunks_refuse_what_they_cannot_cut_before_the_log_is_read(tmp_path):
    """--chunk with a filter or the raw method, or a chunk of 0 s: one line, nothing written."""
    base = ["estimate", "recordings/single_joint.mcap", "--config", "configs/single_joint.toml"]
    for extra, said in (
        (["--chunk", "1", "--method", "raw"], "--method raw estimates a log in one pass"),
        (["--chunk", "0"], "--chunk 0, --chunk-overlap 2: expected s > 0 and s ≥ 0"),
    ):
        done = _run([*base, "--out", str(tmp_path / "out"), *extra])
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1 and said in done.stderr, done.stderr
        assert not (tmp_path / "out").exists()


def test_chunks_flag_commands_that_disagree_with_the_efforts(tmp_path):
    """A chunked run still checks the commands against the logged efforts (over its first
    chunk): two actuators swapped in the command stream are named."""
    document = tomlkit.parse((ROOT / "configs" / "quadruped_trot.toml").read_text())
    names = document["streams"]["command"]["actuators"]
    names[1], names[2] = names[2], names[1]
    document["model"] = str(ROOT / "physics" / "models" / "quadruped.xml")
    config = tmp_path / "swapped.toml"
    config.write_text(tomlkit.dumps(document))
    argv = ["estimate", "recordings/quadruped_trot.mcap", "--config", str(config), "--quiet"]
    argv += ["--out", str(tmp_path / "out"), "--method", "kinematic", "--chunk", "1"]
    done = _run([*argv, "--workers", "2"])
    assert done.returncode == 0, done.stderr
    assert "warning: commands to actuator 'front_left_knee'" in done.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert any("'front_left_knee'" in w for w in summary["warnings"])


def test_a_join_inside_a_mocap_gap_longer_than_the_overlap_is_named():
    from estimator.chunks import _joins_in_gaps
    from estimator.io.logs.measurements import BadSampleCounts, Measurement

    knots = np.arange(0, 4_000_000_000, 10_000_000)  # 4 s of 10 ms knots
    # mocap at 100 Hz with a gap from 1.6 s to 2.9 s; the chunk's own knots 1–2 s
    t = knots[(knots < 1_600_000_000) | (knots >= 2_900_000_000)]
    mocap = Measurement(
        "mocap_base", "pose", "/base", "body", ("base",), ("px",), t, t,
        np.zeros((len(t), 1, 1)), BadSampleCounts(),
    )  # fmt: skip
    seen_to = {2.5: 250, 3.0: 301}  # the last knot the chunk sees: 0.5 s and 1 s past 2 s
    first, end = 100, 200
    short = _joins_in_gaps({"mocap_base": mocap}, knots[: seen_to[2.5]], first, end)
    assert len(short) == 1
    assert "'mocap_base'" in short[0] and "0.50 s" in short[0] and "after its join" in short[0]
    assert _joins_in_gaps({"mocap_base": mocap}, knots[: seen_to[3.0]], first, end) == []
