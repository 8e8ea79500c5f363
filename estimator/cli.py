"""The `physfuse` command. Each subcommand lives in its own module and registers here."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from estimator.errors import PhysfuseError
from physics.errors import PhysicsError

# name -> (module path, help); modules expose `add_arguments(parser)` and `run(args) -> int`.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "reproduce": ("physics.reproduce.cli", "reproduce the paper's figures (benchmarks)"),
    "inspect": ("estimator.inspect_cmd", "topics, rates, gaps and bad samples of a robot log"),
    "simulate": ("estimator.simulate_cmd", "simulate a robot log with ground truth (MCAP)"),
    "estimate": ("estimator.estimate_cmd", "smooth a robot log into motion and contact forces"),
    "calibrate": (
        "estimator.calibrate_cmd",
        "fit the model's contact softness to a log (by the mocap cost of the estimate)",
    ),
    "evaluate": (
        "estimator.evaluate_cmd",
        "errors of an estimate against ground truth, or of a held-out sensor's prediction",
    ),
}


def _load(module_path: str) -> tuple[Callable[[argparse.ArgumentParser], None], Callable]:
    import importlib

    module = importlib.import_module(module_path)
    return module.add_arguments, module.run


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="physfuse",
        description="State estimation for articulated robots with invertible contact dynamics.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_path, help_text) in SUBCOMMANDS.items():
        add_arguments, run = _load(module_path)
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_arguments(p)
        p.set_defaults(_run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (PhysfuseError, PhysicsError) as err:
        print(f"physfuse {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
