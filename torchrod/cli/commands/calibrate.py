"""``torchrod calibrate``: fit the location bias and the bending stiffness from readings with known forces.

Usage: ``torchrod calibrate --rod ROD READINGS.jsonl [--out NEW_ROD.json] [--directions known|free]`` ('-' reads
the readings from standard input). ROD is a rod JSON file or a preset name (the presets are listed under --rod).

Input: READINGS.jsonl holds one reading with its known forces per line::

    {"id": "c1", "curvature": [[ux, uy], null, ...], "forces": [{"s": 0.12, "fx": 0.3, "fy": -0.1}, ...]}

``curvature``: one [ux, uy] pair [1/m] per grating in the rod file's order, ``null`` for a grating without a
reading (the rules of ``torchrod estimate``: finite numbers, at most 1e6 1/m; optional ``id``, ``t`` [s] and
``gratings``, which must be the rod's; other keys are ignored). ``forces``: the known forces, ``s`` [m] in the true
(fibre's) coordinate, ``fx``, ``fy`` [N] in the body frame, nonzero; ``[]`` for a reading without load.
``torchrod simulate`` output with a ``forces`` key added is such a line. Every line must be usable: the command
stops with status 2 naming the bad lines (a calibration from a silently thinned set would mislead).

Output: the calibrated rod (``location_bias``, and the stiffness: a rod given by its geometry keeps it and gets a
new ``youngs_modulus``; a rod given by ``bending_stiffness`` gets a new one) goes to ``--out`` (default: standard
output); the fitted values with their standard errors go to standard error. See torchrod.estimate.calibration for
the method.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import rod_help

HELP = "fit the location bias and bending stiffness from readings with known forces"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "readings",
        metavar="READINGS.jsonl",
        help="readings with known forces, one JSON object a line (format below); '-' for stdin",
    )
    parser.add_argument("--rod", required=True, help=rod_help())
    parser.add_argument("--out", default="-", help="calibrated rod JSON file (default: standard output)")
    parser.add_argument(
        "--directions",
        choices=("known", "free"),
        default="known",
        help="stiffness step: use the known force components, or only their magnitudes (default: %(default)s)",
    )
    parser.add_argument("--initial-bias", type=float, default=0.0, help="start of the bias fit [m] (default: 0)")


def run(args: argparse.Namespace) -> int:
    from ...estimate.calibration import calibrate, read_readings, summary
    from ...io.jsonl import check_input
    from ...presets import load as load_rod

    rod = load_rod(args.rod)
    check_input(args.readings, "READINGS")
    data = read_readings(args.readings, rod)
    result = calibrate(rod, data, directions=args.directions, initial_bias=args.initial_bias)
    new_rod = result.apply(rod)
    print(
        f"torchrod calibrate: {data.num_readings} readings, {int(data.forces.count.sum())} known forces",
        file=sys.stderr,
    )
    for line in summary(result, rod):
        print(line, file=sys.stderr)
    if args.out == "-":
        json.dump(new_rod.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        try:
            new_rod.to_json(args.out)
        except OSError as exc:
            raise ValueError(f"--out {args.out}: cannot write there ({exc.strerror or exc})") from None
        print(f"wrote {args.out}", file=sys.stderr)
    return 0
