"""``torchrod bench backlog``: a backlog of readings through ``torchrod stream``, this version beside others.

Readings: ``--count`` (default 20,000) readings of 1 to 3 forces drawn as the accuracy tables draw them (the
envelope of ``torchrod bench estimate``: forces at least 25 mm apart, 0.05 to 2 N, bending <= 90 degrees), noise
``--noise``, written once as JSON lines to a temporary file. Each way is a ``torchrod stream --rod ROD --input
FILE --summary`` process with default options (every core, the shipped network where it fits, the noise learned):
this version (the package the bench runs, wherever it is run from), and each ``--against DIR``, a checkout
of another version run as ``python -m torchrod`` from that folder (so its own package is imported). Each way runs
once untimed on the first lines (its kernels compiled or loaded), then the ways take turns ``--runs`` times, so a
machine whose speed drifts slows each alike. The figure is the command's own ``readings/s`` (the readings over
the time from the first reading to the last answer: start-up and warm-up left out); the statuses of the last run
show whether the ways answer alike.
"""

from __future__ import annotations

import argparse
import itertools
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from ...presets import load as load_rod
from ..commands import rod_help
from . import SUITES
from .estimate import readings
from .pacer import child_command, reading_line

HELP = SUITES["backlog"]

__all__ = ["HELP", "configure", "run"]

_RATE = re.compile(r"(\d+) readings, (\d+) errors, (\d+) readings/s")
_STATUSES = re.compile(r"statuses: (.*)")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument("--count", type=int, default=20_000, help="readings in the backlog (default 20000)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--seed", type=int, default=4242, help="seed of the readings (default 4242)")
    parser.add_argument("--runs", type=int, default=3, help="timed runs of each way, taking turns (default 3)")
    parser.add_argument(
        "--against",
        action="append",
        default=[],
        metavar="DIR",
        help="a checkout of another torchrod version to run beside this one (repeatable)",
    )


def _write(rod, args: argparse.Namespace, path: Path) -> None:
    data = readings(rod, None, args.count, args.noise, args.seed)
    with open(path, "w") as fh:
        for i, reading in enumerate(data.curvature.tolist()):
            fh.write(reading_line(i, None, [[round(a, 6), round(b, 6)] for a, b in reading]) + "\n")


def _stream(folder: str | None, rod: str, path: Path) -> tuple[int, str]:
    """One ``torchrod stream`` run on ``path``: its readings/s and its statuses line."""
    arguments = ["stream", "--rod", rod, "--input", os.fspath(path), "--summary"]
    cmd = child_command(*arguments) if folder is None else [sys.executable, "-m", "torchrod", *arguments]
    done = subprocess.run(cmd, cwd=folder, capture_output=True, text=True, check=False)
    rate = _RATE.search(done.stderr)
    if done.returncode != 0 or rate is None:
        tail = "\n".join(done.stderr.strip().splitlines()[-5:])
        raise RuntimeError(f"`{' '.join(cmd)}` in {folder or os.getcwd()} failed (exit {done.returncode}):\n{tail}")
    statuses = _STATUSES.search(done.stderr)
    return int(rate.group(3)), statuses.group(1) if statuses else "?"


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    ways: list[tuple[str, str | None]] = [("this version", None)]
    for folder in args.against:
        if not (Path(folder) / "torchrod" / "__init__.py").is_file():
            print(f"torchrod bench backlog: {folder!r} is not a torchrod checkout (no torchrod/__init__.py)")
            return 2
        ways.append((folder, os.path.abspath(folder)))
    print(
        f"torchrod bench backlog: {args.count} readings of 1-3 forces (seed {args.seed}, noise {args.noise} 1/m) "
        f"through `torchrod stream --rod {args.rod}` with default options, {os.cpu_count()} cores, {args.runs} runs "
        "of each way taking turns"
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "backlog.jsonl"
        _write(rod, args, path)
        first = Path(tmp) / "first.jsonl"
        with open(path) as src, open(first, "w") as dst:
            dst.writelines(itertools.islice(src, 200))
        for _, folder in ways:
            _stream(folder, args.rod, first)  # warm-up: kernels compiled or loaded, untimed
        rates: dict[str, list[int]] = {name: [] for name, _ in ways}
        statuses: dict[str, str] = {}
        for _ in range(args.runs):
            for name, folder in ways:
                rate, statuses[name] = _stream(folder, args.rod, path)
                rates[name].append(rate)
    width = max(len(name) for name, _ in ways)
    print(f"{'way':<{width}}  {'readings/s, each run':<28} {'median':>8}  statuses (last run)")
    for name, _ in ways:
        runs = ", ".join(f"{r:,}" for r in rates[name])
        print(f"{name:<{width}}  {runs:<28} {statistics.median(rates[name]):>8,.0f}  {statuses[name]}")
    base = statistics.median(rates[ways[0][0]])
    for name, _ in ways[1:]:
        print(f"this version / {name}: {base / statistics.median(rates[name]):.2f}")
    return 0
