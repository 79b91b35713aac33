"""``torchrod calibrate``: fit the location bias and the bending stiffness from readings with known forces.

``torchrod calibrate --rod ROD READINGS.jsonl [--out NEW_ROD.json] [--directions known|free]``

ROD is a rod JSON file or a preset name. READINGS.jsonl holds one reading per line,
``{"id": ..., "curvature": [[u_x, u_y] or null, ...], "forces": [{"s": ..., "fx": ..., "fy": ...}, ...]}``, with the
known forces located in the true (fibre's) coordinate [m] and their body-frame components [N]. The calibrated rod
(``location_bias``, and the stiffness: a rod given by its geometry keeps it and gets a new ``youngs_modulus``; a rod
given by ``bending_stiffness`` gets a new one) goes to ``--out`` (default: standard output); the fitted values with
their standard errors go to standard error. See :mod:`torchrod.calibration` for the method.
"""

from __future__ import annotations

import argparse
import json
import sys

HELP = "fit the location bias and bending stiffness from readings with known forces"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("readings", help="JSON-lines file of readings with known forces")
    parser.add_argument("--rod", required=True, help="rod JSON file or preset name (e.g. nitinol290)")
    parser.add_argument("--out", default="-", help="calibrated rod JSON file (default: standard output)")
    parser.add_argument(
        "--directions",
        choices=("known", "free"),
        default="known",
        help="stiffness step: use the known force components, or only their magnitudes (default: %(default)s)",
    )
    parser.add_argument(
        "--initial-bias", type=float, default=0.0, help="start of the bias fit [m] (default: 0)"
    )



def run(args: argparse.Namespace) -> int:
    from ...estimate.calibration import calibrate, read_readings, summary
    from ...presets import load as load_rod

    rod = load_rod(args.rod)
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
        new_rod.to_json(args.out)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0
