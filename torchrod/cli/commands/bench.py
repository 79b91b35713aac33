"""``torchrod bench SUITE [options]``: run one benchmark suite (``torchrod/cli/benchmarks/SUITE.py``).

Suites: see :data:`torchrod.cli.benchmarks.SUITES`. ``torchrod bench SUITE --help`` lists a suite's own options. A suite
whose module is not part of this version is reported as not available (exit status 2).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from types import ModuleType

from ..benchmarks import SUITES

HELP = "speed and accuracy benchmarks, measured side by side (startup, forward, estimate, stream, ...)"

__all__ = ["HELP", "configure", "load_suite", "run", "suite_parser"]


def configure(parser: argparse.ArgumentParser) -> None:
    lines = [f"  {name:10s} {text}" for name, text in SUITES.items()]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "suites:\n" + "\n".join(lines)
    parser.add_argument("suite", metavar="SUITE", nargs="?", help=f"one of: {', '.join(SUITES)}")
    parser.add_argument("options", nargs=argparse.REMAINDER, help="the suite's options (SUITE --help lists them)")


def load_suite(name: str) -> ModuleType | None:
    """The suite's module, or None when this version does not have it."""
    try:
        return importlib.import_module(f"torchrod.cli.benchmarks.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"torchrod.cli.benchmarks.{name}":
            return None
        raise


def run(args: argparse.Namespace) -> int:
    name = args.suite
    if name is None:
        print("torchrod bench: name a suite; suites:", file=sys.stderr)
        for suite, text in SUITES.items():
            print(f"  {suite:10s} {text}", file=sys.stderr)
        return 2
    if name not in SUITES:
        print(f"torchrod bench: unknown suite {name!r}; suites: {', '.join(SUITES)}", file=sys.stderr)
        return 2
    module = load_suite(name)
    if module is None:
        print(f"torchrod bench {name}: not available in this version", file=sys.stderr)
        return 2
    parser = suite_parser(name, module)
    # A first compile waited for (here and in the commands a suite starts), before any clock: not in the background
    # while the kernels run as Python (torchrod.kernels.targets), which would be timed instead.
    os.environ.setdefault("TORCHROD_COMPILE", "foreground")
    return int(module.run(parser.parse_args(args.options)) or 0)


def suite_parser(name: str, module: ModuleType) -> argparse.ArgumentParser:
    """The argument parser of ``torchrod bench NAME`` (``module``: the suite's, from :func:`load_suite`)."""
    parser = argparse.ArgumentParser(prog=f"torchrod bench {name}", description=module.HELP)
    module.configure(parser)
    return parser
