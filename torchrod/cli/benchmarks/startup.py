"""``torchrod bench startup``: how long torchrod takes before it answers, against importing torch.

Measured side by side in one run, each as a fresh subprocess of this Python (``python -m torchrod``, with this
torchrod first on the path, in a temporary folder so that no checkout in the working folder shadows it):

* ``python -c "import torch"`` (the floor every torch program pays),
* ``torchrod --version`` and ``torchrod --help`` (which should not import torch at all),
* ``torchrod estimate --rod ROD one.jsonl`` on a one-reading file written to the temporary folder (the reading is
  the small-deflection curvature of one 0.05 N force at 0.6 L, computed here without torch).

The runs are interleaved (round after round, each command once per round, after an untimed warm-up round), so that
a change in the machine's load hits every command alike; each line gives the median and the fastest of ``--runs``
wall times [s] and the median's ratio to the torch import. The aim is an estimate within 1.3x the torch import.
Unless ``--quick``, a last run with ``-X importtime`` lists the heavy imports (cumulative time >= ``--min-ms``) that
torchrod makes during that estimate, with the module that made each (or "run time" for an import inside a
function): what to make lazy, or avoid, next.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence

from ..commands import rod_help
from . import SUITES

HELP = SUITES["startup"]

__all__ = ["HELP", "configure", "heavy_imports", "run"]

AIM = 1.3
"""Largest ratio of a one-reading ``torchrod estimate`` to ``python -c "import torch"`` that meets the aim."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (__doc__ or "").split("\n\n", 1)[1].replace("``", "")
    parser.add_argument("--runs", type=int, default=5, help="timed runs of each command (default 5)")
    parser.add_argument(
        "--rod",
        default="nitinol290",
        help=rod_help("nitinol290", " of the one-reading estimate"),
    )
    parser.add_argument(
        "--min-ms",
        type=float,
        default=50.0,
        help="list imports made by torchrod that take at least this [ms] (50)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="a smoke run: one timed run each, no warm-up, no import list"
    )


def _one_reading(rod) -> dict:
    """The small-deflection reading of one force f = (0.03, 0.04) N at s_i = 0.6 L: u_x = -f_y (s_i - s) / EI and
    u_y = f_x (s_i - s) / EI proximal to it, 0 distal (docs/physics.md, the sign check) [1/m]."""
    s_i, fx, fy = 0.6 * rod.length, 0.03, 0.04
    lever = [max(0.0, s_i - s) / rod.bending_stiffness for s in rod.gratings]
    return {"id": "startup", "curvature": [[-fy * a, fx * a] for a in lever]}


def _environment() -> dict[str, str]:
    """This process's environment with the running torchrod first on the path."""
    import torchrod

    root = os.path.dirname(os.path.dirname(os.path.abspath(torchrod.__file__)))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    return env


def _time(argv: Sequence[str], cwd: str, env: dict[str, str]) -> float:
    """Wall time [s] of one run of ``argv``; ``ValueError`` with its stderr if it fails."""
    t0 = time.perf_counter()
    done = subprocess.run(list(argv), cwd=cwd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise ValueError(f"{' '.join(argv[1:])} exited with status {done.returncode}: {tail}")
    return wall


RUN_TIME = "run time (an import inside a function)"
"""The importer :func:`heavy_imports` names for a package first imported while torchrod code runs."""


def heavy_imports(importtime: str, min_seconds: float) -> list[tuple[str, float, str]]:
    """From ``python -X importtime`` output: (package, cumulative seconds, importer) for the imports of packages
    other than torchrod and torch made by torchrod, taking at least ``min_seconds`` each, slowest first.

    The output lists each module after the modules it imported, one nesting level deeper; a module's importer is
    the next line at a shallower level. A top-level line after torchrod's first is an import made at run time
    (inside a function), named ``RUN_TIME``. Lines are grouped by the first two parts of the name
    (``scipy.stats``), since a lazily loaded package may show only its submodules.
    """
    rows: list[tuple[int, float, str]] = []
    for line in importtime.splitlines():
        if not line.startswith("import time:") or line.count("|") != 2:
            continue
        _, cumulative, name = line.split("|")
        if not cumulative.strip().isdigit():  # the header line
            continue
        depth = len(name) - len(name.lstrip(" "))
        rows.append((depth, int(cumulative) * 1e-6, name.strip()))
    top = min((d for d, _, _ in rows), default=0)
    first = next((k for k, (_, _, n) in enumerate(rows) if n.split(".")[0] == "torchrod"), len(rows))
    groups: dict[tuple[str, str], float] = {}
    for k, (depth, seconds, name) in enumerate(rows):
        if name.split(".")[0] in ("torchrod", "torch"):  # torchrod itself; torch is the floor measured above
            continue
        importer = next((n for d, _, n in rows[k + 1 :] if d < depth), "")
        if importer.split(".")[0] == "torchrod" or (depth == top and k > first and not importer):
            key = (".".join(name.split(".")[:2]), importer or RUN_TIME)
            groups[key] = groups.get(key, 0.0) + seconds
    out = [(name, seconds, importer) for (name, importer), seconds in groups.items() if seconds >= min_seconds]
    return sorted(out, key=lambda row: -row[1])


def run(args: argparse.Namespace) -> int:
    from ...presets import load as load_rod

    runs = 1 if args.quick else args.runs
    if runs < 1:
        raise ValueError(f"--runs must be >= 1, got {args.runs}")
    rod = load_rod(args.rod)
    env = _environment()
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="torchrod-startup-") as tmp:
        reading = os.path.join(tmp, "one.jsonl")
        with open(reading, "w", encoding="utf-8") as fh:
            fh.write(json.dumps(_one_reading(rod)) + "\n")
        rod_arg = args.rod if not os.path.exists(args.rod) else os.path.abspath(args.rod)
        commands = {
            'python -c "import torch"': [py, "-c", "import torch"],
            "torchrod --version": [py, "-m", "torchrod", "--version"],
            "torchrod --help": [py, "-m", "torchrod", "--help"],
            f"torchrod estimate --rod {args.rod} (one reading)": [
                py,
                "-m",
                "torchrod",
                "estimate",
                "--rod",
                rod_arg,
                reading,
            ],
        }
        times: dict[str, list[float]] = {name: [] for name in commands}
        for round_ in range(runs + (0 if args.quick else 1)):
            for name, argv in commands.items():
                wall = _time(argv, tmp, env)
                if args.quick or round_ > 0:  # round 0 warms the file cache
                    times[name].append(wall)
        imports = None
        if not args.quick:
            estimate = list(commands.values())[-1]
            done = subprocess.run(
                [py, "-X", "importtime", *estimate[1:]],
                cwd=tmp,
                env=env,
                capture_output=True,
                text=True,
                check=False,
            )
            imports = heavy_imports(done.stderr, 1e-3 * args.min_ms)

    floor = statistics.median(times['python -c "import torch"'])
    print(
        f"# torchrod bench startup: median and fastest of {runs} run(s) per command, interleaved"
        f"{'' if args.quick else ' after a warm-up round'}; python {sys.version.split()[0]}, "
        f"{os.cpu_count()} CPU(s)"
    )
    width = max(map(len, commands))
    print(f"{'command':<{width}} | {'median s':>8} {'min s':>7} | {'/ import torch':>14}")
    for name, walls in times.items():
        median = statistics.median(walls)
        print(f"{name:<{width}} | {median:>8.3f} {min(walls):>7.3f} | {median / floor:>14.2f}")
    ratio = statistics.median(times[list(commands)[-1]]) / floor
    print(
        f"aim: the one-reading estimate within {AIM}x the torch import: {'met' if ratio <= AIM else 'missed'} "
        f"({ratio:.2f}x)"
    )
    if imports is not None:
        if imports:
            print(f"imports of {args.min_ms:g} ms or more made by torchrod during that estimate:")
            for name, seconds, importer in imports:
                print(f"  {name:<24} {seconds:6.2f} s  imported by {importer}")
        else:
            print(f"no import of {args.min_ms:g} ms or more made by torchrod besides torch")
    return 0
