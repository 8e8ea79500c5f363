"""`physfuse reproduce fig2|fig3 --out DIR`: the paper's two results, as benchmarks."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("figure", choices=["fig2", "fig3"], help="which figure to reproduce")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output directory")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        help="simulated seconds (default: fig2 4 s, fig3 20 s)",
    )


def run(args: argparse.Namespace) -> int:
    if args.figure == "fig2":
        from physics.reproduce import fig2

        fig2.run(args.out, duration=args.duration or 4.0, seed=args.seed)
    else:
        from physics.reproduce import fig3

        fig3.run(args.out, duration=args.duration or 20.0, seed=args.seed)
    return 0
