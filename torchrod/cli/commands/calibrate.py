"""``torchrod calibrate``: fit the location bias and the bending stiffness from readings with known forces.

Usage: ``torchrod calibrate --rod ROD READINGS.jsonl [--out NEW_ROD.json] [--directions known|free]`` ('-' reads
the readings from standard input). ROD is a rod JSON file or a preset name such as ``nitinol290``.

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
output, never one of the inputs); the fitted values with their standard errors go to standard error. See
torchrod.estimate.calibration for the method.

A calibration the command cannot stand behind is refused: exit status 1, the reasons on standard error, and no rod
written. It is refused when the readings are inconsistent with the known forces (all but zero, as from a dead
sensor; fitted forces pointing against the known ones, as with a flipped sign), when a residual lies far beyond
the noise (``--noise SIGMA``, the sensor's sigma [1/m]; without it, what forces fitted freely leave), when the
stiffness lies outside physical bounds (0.1 to 10 times the rod file's; a Young's modulus of 1e6 to 1.2e12 Pa) or
is not determined by the data (a standard error above 10 %), or when a solve did not converge. ``--force`` writes
the rod anyway (the reasons are still printed, as warnings).
"""

from __future__ import annotations

import argparse
import json
import sys

HELP = "fit the location bias and bending stiffness from readings with known forces"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "readings",
        metavar="READINGS.jsonl",
        help="readings with known forces, one JSON object a line (format below); '-' for stdin",
    )
    parser.add_argument("--rod", required=True, help="rod JSON file or preset name (e.g. nitinol290)")
    parser.add_argument("--out", default="-", help="calibrated rod JSON file (default: standard output)")
    parser.add_argument(
        "--directions",
        choices=("known", "free"),
        default="known",
        help="stiffness step: use the known force components, or only their magnitudes (default: %(default)s)",
    )
    parser.add_argument("--initial-bias", type=float, default=0.0, help="start of the bias fit [m] (default: 0)")
    parser.add_argument(
        "--noise",
        type=float,
        metavar="SIGMA",
        help="the sensor's noise sigma [1/m], to judge the residuals by (default: what freely fitted forces leave)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="write the rod even when the calibration is refused (its reasons are printed as warnings)",
    )


def run(args: argparse.Namespace) -> int:
    from ...estimate.calibration import calibrate, read_readings, summary
    from ...io.jsonl import STDOUT_CLOSED, ClosedOutput, check_input, check_output
    from ...presets import load as load_rod

    rod = load_rod(args.rod)
    check_input(args.readings, "READINGS")
    if args.noise is not None and not 0.0 < args.noise < float("inf"):
        raise ValueError(f"--noise must be a positive sigma [1/m], got {args.noise}")
    # The output is checked before the fit (a wrong --out costs no time), and written only once the fit is accepted.
    check_output(args.out, {"READINGS": args.readings, "--rod": args.rod})
    if args.out == "-" and (sys.stdout is None or isinstance(sys.stdout, ClosedOutput)):
        raise ValueError(STDOUT_CLOSED)
    data = read_readings(args.readings, rod)
    result = calibrate(rod, data, directions=args.directions, initial_bias=args.initial_bias, noise=args.noise)
    print(
        f"torchrod calibrate: {data.num_readings} readings, {int(data.forces.count.sum())} known forces",
        file=sys.stderr,
    )
    for line in summary(result, rod):
        if not line.startswith("problem: "):
            print(line, file=sys.stderr)
    if result.problems and not args.force:
        for text in result.problems:
            print(f"torchrod calibrate: refused: {text}", file=sys.stderr)
        print("torchrod calibrate: no rod written (--force writes it anyway)", file=sys.stderr)
        return 1
    for text in result.problems:
        print(f"torchrod calibrate: warning (forced): {text}", file=sys.stderr)
    new_rod = result.apply(rod, force=args.force)
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
