"""``torchrod calibrate``: fit a rod from readings with known loads: its location bias and bending stiffness, or
(``--fibre``) its fibre's wavelength-to-curvature matrices from jig readings.

Usage: ``torchrod calibrate --rod ROD READINGS [--out NEW_ROD.json] [--directions known|free]`` ('-' reads the readings
from standard input), or ``torchrod calibrate --fibre --rod ROD JIG_READINGS --out NEW_ROD.json``. ROD is a rod JSON
file or a preset name (the presets are listed under --rod). READINGS are JSON lines or CSV (``--format``; the unit
options as for ``torchrod estimate``).

Location bias and stiffness: READINGS holds one reading with its known forces per line::

    {"id": "c1", "curvature": [[ux, uy], null, ...], "forces": [{"s": 0.12, "fx": 0.3, "fy": -0.1}, ...]}

``curvature``: one [ux, uy] pair [1/m] per grating in the rod file's order, ``null`` for a grating without a
reading (the rules of ``torchrod estimate``: finite numbers, at most 1e6 1/m; optional ``id``, ``t`` [s] and
``gratings``, which must be the rod's; other keys are ignored; ``strain``, ``curvature_polar``, ``wavelength`` or
``wavelength_shift`` may stand for ``curvature``). ``forces``: the known forces, ``s`` [m] in the true (fibre's)
coordinate, ``fx``, ``fy`` [N] in the body frame, nonzero; ``[]`` for a reading without load. In CSV the forces are
the columns ``s_J, fx_J, fy_J`` (J = 1, 2, ...). ``torchrod simulate`` output with a ``forces`` key added is such a
line. Every line must be usable: the command stops with status 2 naming the bad lines (a calibration from a
silently thinned set would mislead). The calibrated rod (``location_bias``, and the stiffness: a rod given by its
geometry keeps it and gets a new ``youngs_modulus``; a rod given by ``bending_stiffness`` gets a new one) goes to
``--out`` (default: standard output); the fitted values with their standard errors go to standard error. See
torchrod.estimate.calibration for the method.

A calibration the command cannot stand behind is refused: exit status 1, the reasons on standard error, and no rod
written. It is refused when the readings are inconsistent with the known forces (all but zero, as from a dead
sensor; fitted forces pointing against the known ones, as with a flipped sign), when a residual lies far beyond
the noise (``--noise SIGMA``, the sensor's sigma [1/m]; without it, what forces fitted freely leave), when the
stiffness lies outside physical bounds (0.1 to 10 times the rod file's; a Young's modulus of 1e6 to 1.2e12 Pa) or
is not determined by the data (a standard error above 10 %), or when a solve did not converge. ``--force`` writes
the rod anyway (the reasons are still printed, as warnings).

Fibre (``--fibre``): JIG_READINGS holds readings of the fibre on jigs of known constant curvature, each tagged with
the jig::

    {"id": 1, "wavelength": [[l_1, ..., l_C] or null, ...], "jig": {"curvature": 10.0, "angle": 1.5708, "name": "J10"}}

(``wavelength`` [nm] with the rod file's ``fibre.wavelength.reference`` subtracted, or ``wavelength_shift``; the
jig's curvature magnitude in the curvature unit, 1/m by default, and its bend direction [rad] from d1 towards d2;
``name`` optional, else the jig is known by its curvature). CSV: the columns ``lambda_K_C`` or ``dlambda_K_C``,
``jig_curvature``, ``jig_angle``, ``jig``. Each grating's 2 x C matrix (u = A (d - mean d), 1/m per nm) is fitted by
least squares. Standard error shows, per grating, the residual [1/m], the leave-one-jig-out prediction error
[1/m] and the gain [1/m per nm] against the gratings' median and the physics route (with the rod file's cores),
and a warning for each gain off by more than ``--gain-tolerance`` (default 0.25). The rod file with
``fibre.wavelength.calibration`` (and, when it had no reference, the straight jig's mean as the reference) goes to
``--out``. See torchrod.jig for the method. The calibration is refused as above (exit status 1, no rod written,
``--force`` writes it anyway) when a grating's residual or leave-one-jig-out error exceeds 10 % of the jig
curvatures' RMS, when no jig can be left out, or, with the rod file's cores and a reference, when a grating's gain
is more than 3 times off the physics route's or its matrix turns a bend by more than 45 degrees from it or mirrors
it (jig angles off by pi, curvatures in another unit). Readings that bend in one direction only are refused (exit
status 2).

``--out`` never overwrites the rod file or the readings it was made from.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from . import add_input_options, add_sensor_options, rod_help, sensor_rod

HELP = "fit a rod's location bias and stiffness from known forces, or its fibre's calibration from jig readings"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "readings",
        metavar="READINGS",
        help="readings with known forces (or, with --fibre, jig readings), JSON lines or CSV; '-' for stdin",
    )
    parser.add_argument("--rod", required=True, help=rod_help())
    parser.add_argument("--out", default="-", help="calibrated rod JSON file (default: standard output)")
    parser.add_argument(
        "--fibre",
        action="store_true",
        help="fit the fibre's wavelength-to-curvature matrices from jig readings instead (see below)",
    )
    parser.add_argument(
        "--gain-tolerance",
        type=float,
        default=None,
        metavar="F",
        help="--fibre: warn about a grating whose gain differs from the median's or the physics route's by more than "
        "this fraction (default 0.25)",
    )
    parser.add_argument(
        "--directions",
        choices=("known", "free"),
        default="known",
        help="stiffness step: use the known force components, or only their magnitudes (default: %(default)s)",
    )
    parser.add_argument("--initial-bias", type=float, default=0.0, help="start of the bias fit [m] (default: 0)")
    add_input_options(parser, protocol=False)
    add_sensor_options(parser, estimating=False)
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


def _write(rod, out: str) -> None:
    if out == "-":
        json.dump(rod.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return
    try:
        rod.to_json(out)
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot write there ({exc.strerror or exc})") from None
    print(f"wrote {out}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from ...io.jsonl import STDOUT_CLOSED, ClosedOutput, check_input, check_output
    from ...presets import load as load_rod

    # The output is checked before the fit (a wrong --out costs no time), and written only once the fit is accepted.
    check_output(args.out, {"READINGS": args.readings, "--rod": args.rod})
    if args.out == "-" and (sys.stdout is None or isinstance(sys.stdout, ClosedOutput)):
        raise ValueError(STDOUT_CLOSED)
    base = load_rod(args.rod)
    rod = sensor_rod(args, base)  # the options' units read the readings; the rod written keeps its own
    check_input(args.readings, "READINGS")
    if args.noise is not None and not 0.0 < args.noise < float("inf"):
        raise ValueError(f"--noise must be a positive sigma [1/m], got {args.noise}")
    from ...errors import OptionsError
    from ...io.quantities import MAX_CURVATURE

    if args.noise is not None and args.noise > MAX_CURVATURE:
        raise OptionsError(
            f"--noise must be at most {MAX_CURVATURE:g} 1/m, the largest curvature a reading may carry, got "
            f"{args.noise:g}"
        )
    if args.fibre:
        return _fibre(args, rod, base)
    if args.gain_tolerance is not None:
        raise ValueError("--gain-tolerance is an option of --fibre")
    from ...estimate.calibration import calibrate, summary
    from ...io.known_loads import read_readings

    data = read_readings(args.readings, rod, fmt=args.format, quantity=args.csv_quantity, max_line=args.max_line_bytes)
    result = calibrate(rod, data, directions=args.directions, initial_bias=args.initial_bias, noise=args.noise)
    print(
        f"torchrod calibrate: {data.num_readings} readings, {int(data.forces.count.sum())} known forces",
        file=sys.stderr,
    )
    for line in summary(result, rod):
        if not line.startswith("problem: "):
            print(line, file=sys.stderr)
    return _refuse_or_write("torchrod calibrate", result.problems, args, lambda: result.apply(base, force=args.force))


def _fibre(args: argparse.Namespace, rod, base) -> int:
    from ...jig import GAIN_TOLERANCE, calibrate_fibre, read_jig_readings, report

    quantity = args.csv_quantity if args.csv_quantity in ("wavelength", "wavelength-shift") else "wavelength"
    data = read_jig_readings(args.readings, rod, args.format, quantity=quantity, max_line=args.max_line_bytes)
    tolerance = GAIN_TOLERANCE if args.gain_tolerance is None else args.gain_tolerance
    result = calibrate_fibre(rod, data, tolerance)
    for line in report(result, data):
        print(f"torchrod calibrate --fibre: {line}", file=sys.stderr)
    return _refuse_or_write("torchrod calibrate --fibre", result.problems, args, lambda: result.apply(base))


def _refuse_or_write(who: str, problems: Any, args: argparse.Namespace, calibrated: Any) -> int:
    """Exit status 1 and no rod written while the calibration has ``problems`` (each said), unless ``--force``
    (then each is a warning); else the rod ``calibrated()`` makes is written to ``--out`` and 0."""
    if problems and not args.force:
        for text in problems:
            print(f"{who}: refused: {text}", file=sys.stderr)
        print(f"{who}: no rod written (--force writes it anyway)", file=sys.stderr)
        return 1
    for text in problems:
        print(f"{who}: warning (forced): {text}", file=sys.stderr)
    _write(calibrated(), args.out)
    return 0
