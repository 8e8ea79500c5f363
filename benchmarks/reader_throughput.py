"""Reader throughput (messages/s) on a 1-minute humanoid log.

    .venv/bin/python benchmarks/reader_throughput.py --out out/bench
    .venv/bin/python benchmarks/reader_throughput.py --log run.mcap --config cfg.toml

Without `--log` it writes a humanoid-like ROS 2 log for the bundled humanoid model: mocap
PoseStamped 200 Hz × 2 bodies, IMU 500 Hz, JointState 500 Hz × 21 joints, Float64MultiArray
commands 100 Hz × 21 actuators (90 000 messages per minute). It then times, best of
`--repeat`: mcap_ros2's own decoding of every message (the floor), `read_log` (file reader),
`ByteStreamReader` fed through an OS pipe, and `read_log(decode_all=True)` (what `physfuse
inspect` does). Prints a table and writes `OUT/reader_throughput.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the ROS 2 log writer the tests use

import ros2_logs as rl  # noqa: E402

from estimator.config import Config, load_config  # noqa: E402
from estimator.io.logs import ByteStreamReader, read_log  # noqa: E402
from estimator.io.logs import ros2_types as t  # noqa: E402
from physics.model import load_model  # noqa: E402

RATES_HZ = {"mocap": 200, "imu": 500, "joint_states": 500, "commands": 100}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", type=Path, help="an existing log (needs --config)")
    parser.add_argument("--config", type=Path, help="config for --log")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of generated log")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per reader (best)")
    parser.add_argument("--out", type=Path, help="write OUT/reader_throughput.json")
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        if args.log:
            if not args.config:
                parser.error("--log needs --config")
            log_path, config = args.log, load_config(args.config)
        else:
            log_path, config = _write_humanoid_log(Path(tmp), args.duration)
        n_messages = _count_messages(log_path)
        results = {
            "mcap_ros2 decode (floor)": _best(args.repeat, lambda: _decode_all(log_path)),
            "read_log (file)": _best(args.repeat, lambda: read_log(log_path, config)),
            "ByteStreamReader (pipe)": _best(args.repeat, lambda: _read_pipe(log_path, config)),
            "read_log decode_all (inspect)": _best(
                args.repeat, lambda: read_log(log_path, config, decode_all=True)
            ),
        }
        size = log_path.stat().st_size

    rows = {name: {"seconds": s, "messages_per_s": n_messages / s} for name, s in results.items()}
    print(
        f"log: {args.log or 'generated humanoid log'}, {n_messages} messages, {size / 1e6:.1f} MB"
    )
    print(f"{'reader':<32} {'seconds':>8} {'messages/s':>12}")
    for name, row in rows.items():
        print(f"{name:<32} {row['seconds']:>8.3f} {row['messages_per_s']:>12.0f}")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        report = {
            "benchmark": "reader_throughput",
            "log": str(args.log) if args.log else f"generated humanoid, {args.duration} s",
            "messages": n_messages,
            "bytes": size,
            "repeat": args.repeat,
            "results": rows,
            "machine": {
                "python": platform.python_version(),
                "platform": platform.platform(),
                "cpus": os.cpu_count(),
            },
        }
        path = args.out / "reader_throughput.json"
        path.write_text(json.dumps(report, indent=2))
        print(f"wrote {path}")
    return 0


def _write_humanoid_log(folder: Path, duration_s: float) -> tuple[Path, Config]:
    model = load_model("humanoid")
    joints = [model.joint(i).name for i in range(model.njnt) if model.jnt_type[i] == 3]
    actuators = [model.actuator(i).name for i in range(model.nu)]
    config_path = folder / "humanoid.toml"
    config_path.write_text(
        'model = "humanoid"\n'
        '[streams.mocap_torso]\ntype = "pose"\ntopic = "/mocap/torso"\nbody = "torso"\n'
        '[streams.mocap_pelvis]\ntype = "pose"\ntopic = "/mocap/pelvis"\nbody = "pelvis"\n'
        '[streams.imu]\ntype = "imu"\ntopic = "/imu"\nsite = "imu"\n'
        '[streams.joints]\ntype = "joint_state"\ntopic = "/joint_states"\njoints = "model"\n'
        '[streams.command]\ntype = "command"\ntopic = "/joint_commands"\n'
        f"actuators = {json.dumps(actuators)}\n"
    )
    rng = np.random.default_rng(0)
    msgs: list[rl.Msg] = []

    def times(rate: int) -> np.ndarray:
        n = int(duration_s * rate)
        return rl.T0 + np.arange(n) * (1_000_000_000 // rate) + rng.integers(-20_000, 20_000, n)

    for topic in ("/mocap/torso", "/mocap/pelvis"):
        for s in times(RATES_HZ["mocap"]):
            fields = rl.pose_stamped(int(s), rng.normal(size=3), rl.unit_quat(float(s) * 1e-9))
            msgs.append(rl.Msg(topic, t.POSE_STAMPED, int(s) + 3_000_000, fields))
    for s in times(RATES_HZ["imu"]):
        fields = rl.imu(int(s), rng.normal(size=3), rng.normal(size=3), rl.unit_quat(1.0))
        msgs.append(rl.Msg("/imu", t.IMU, int(s) + 500_000, fields))
    for s in times(RATES_HZ["joint_states"]):
        q, qd, tau = rng.normal(size=(3, len(joints)))
        fields = rl.joint_state(int(s), joints, q, qd, tau)
        msgs.append(rl.Msg("/joint_states", t.JOINT_STATE, int(s) + 250_000, fields))
    for s in times(RATES_HZ["commands"]):
        fields = rl.float64_multi_array(rng.normal(size=len(actuators)))
        msgs.append(rl.Msg("/joint_commands", t.FLOAT64_MULTI_ARRAY, int(s), fields))
    msgs.sort(key=lambda m: m.log_time_ns)
    path = folder / "humanoid.mcap"
    rl.write_mcap(path, msgs)
    return path, load_config(config_path)


def _count_messages(path: Path) -> int:
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    return summary.statistics.message_count


def _decode_all(path: Path) -> None:
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _ in reader.iter_decoded_messages(log_time_order=False):
            pass


def _read_pipe(path: Path, config: Config) -> None:
    read_fd, write_fd = os.pipe()
    data = path.read_bytes()

    def feed() -> None:
        with os.fdopen(write_fd, "wb") as pipe:
            for at in range(0, len(data), 65536):
                pipe.write(data[at : at + 65536])

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    with os.fdopen(read_fd, "rb") as pipe:
        for _ in ByteStreamReader(pipe, config).samples():
            pass
    writer.join()


def _best(repeat: int, fn: Callable[[], object]) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


if __name__ == "__main__":
    sys.exit(main())
