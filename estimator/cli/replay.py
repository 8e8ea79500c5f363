"""`physfuse replay`: serve a recording as a live MCAP byte stream at its own pace.

physfuse replay recordings/humanoid_push.mcap --to tcp://127.0.0.1:9000 [--rate 1]
physfuse replay recordings/humanoid_push.mcap --to - | physfuse stream --source - ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from estimator.errors import ConfigError
from estimator.io.live import replay


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, help="ROS 2 MCAP file or rosbag2 folder")
    parser.add_argument(
        "--to",
        required=True,
        help="- (standard output) or tcp://HOST:PORT (listens; serves the first client)",
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="pace: 1 real time (default), 2 twice as fast, 0 as fast as the reader takes it",
    )
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all)")


def run(args: argparse.Namespace) -> int:
    if args.rate < 0:
        raise ConfigError(f"--rate {args.rate:g}: expected ≥ 0 (0: as fast as possible)")

    def ready(port: int) -> None:
        print(f"physfuse replay: serving {args.log} on port {port}", file=sys.stderr, flush=True)

    sent = replay(args.log, args.to, args.rate, ready, args.topics)
    print(f"physfuse replay: {sent} messages sent", file=sys.stderr)
    return 0
