"""The ``torchrod`` command: one subcommand per task, each implemented in ``torchrod/cli/commands/<name>.py``.

Every command module defines ``HELP`` (one line), ``configure(parser)`` and ``run(args) -> int``; they are imported
only when their subcommand runs, so ``torchrod --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

__all__ = ["COMMANDS", "main"]

COMMANDS: dict[str, str] = {
    "simulate": "curvature at the gratings for given point forces (JSON lines in, JSON lines out)",
    "estimate": "forces from FBG curvature readings (JSON lines in, JSON lines out)",
    "calibrate": "fit the location bias and bending stiffness from readings with known forces",
    "evaluate": "accuracy of the estimator on simulated readings over a realistic envelope",
    "generate": "synthetic training sets and synthetic reading streams",
    "train": "train the warm-start network",
    "stream": "amortised estimation on a stream of readings",
    "bench": "benchmarks: forward model, estimation, streams, the paper's comparison",
    "plot": "figures of readings and their estimates",
}


def _build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(prog="torchrod", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"torchrod {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``torchrod`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or argv[0] not in COMMANDS:
        if argv and not argv[0].startswith("-"):
            parser.print_usage(sys.stderr)
            print(f"torchrod: unknown command {argv[0]!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
            return 2
        parser.parse_args(argv)  # --help / --version exit here
        parser.print_help()
        return 2
    name = argv[0]
    try:
        module = importlib.import_module(f".commands.{name}", __package__)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.endswith(f"commands.{name}"):
            print(f"torchrod {name}: not available in this version", file=sys.stderr)
            return 2
        raise
    sub = argparse.ArgumentParser(prog=f"torchrod {name}", description=COMMANDS[name])
    module.configure(sub)
    args = sub.parse_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader of our output went away (as with `| head`): stop quietly, as for SIGPIPE.
        from ..io.jsonl import quiet_closed_pipe

        quiet_closed_pipe(sys.stdout)
        return 141
    except (ValueError, FileNotFoundError) as exc:
        print(f"torchrod {name}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
