"""The `physfuse` command. Each subcommand lives in its own module and registers here."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Callable, Sequence

from estimator.errors import PhysfuseError
from physics.errors import PhysicsError

# name -> (module path, help); modules expose `add_arguments(parser)` and `run(args) -> int`.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "reproduce": ("physics.reproduce.cli", "reproduce the paper's figures (benchmarks)"),
    "inspect": ("estimator.cli.inspect", "topics, rates, gaps and bad samples of a robot log"),
    "simulate": ("estimator.cli.simulate", "simulate a robot log with ground truth (MCAP)"),
    "estimate": ("estimator.cli.estimate", "smooth a robot log into motion and contact forces"),
    "calibrate": (
        "estimator.cli.calibrate",
        "fit the model's contact softness to a log (by the mocap cost of the estimate)",
    ),
    "evaluate": (
        "estimator.cli.evaluate",
        "errors of an estimate against ground truth, or of a held-out sensor's prediction",
    ),
    "diagnose": (
        "estimator.cli.diagnose",
        "unmodeled contacts (pushes, collisions) and sensor faults in a robot log",
    ),
    "stream": (
        "estimator.cli.stream",
        "estimate a live robot as its messages arrive (fixed-lag smoothing)",
    ),
    "replay": ("estimator.cli.replay", "serve a recording as a live MCAP stream at its pace"),
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
    """Run a subcommand; whatever stops it ends in one line on stderr, never a traceback."""
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:  # Ctrl-C while the subcommands load
        print("physfuse: interrupted", file=sys.stderr)
        return 130
    name = f"physfuse {args.command}"
    try:
        code = int(args._run(args) or 0)
        sys.stdout.flush()  # a closed stdout shows here, not as a message at exit
        return code
    except BrokenPipeError:  # stdout closed early (`physfuse ... | head -3`): end quietly
        return _stdout_closed()
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130  # 128 + SIGINT, as a shell reports a command stopped by Ctrl-C
    except (PhysfuseError, PhysicsError) as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a file that cannot be read or written: name it
        where = f"{err.filename}: " if err.filename is not None else ""
        print(f"{name}: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2


def _stdout_closed() -> int:
    """The Python docs' recipe (signal module, "Note on SIGPIPE"): point stdout at devnull so
    that the flush at exit does not fail again; 141 = 128 + SIGPIPE, the status a shell
    reports for a writer stopped by a closed pipe."""
    with contextlib.suppress(OSError, ValueError):  # no real descriptor (captured in tests)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    return 141


if __name__ == "__main__":
    sys.exit(main())
