"""``torchrod rod``: write a rod file from its numbers, or check an existing one, and show what it can do.

From numbers (SI units: m, Pa, N m^2), the options named as the rod file's keys:

  torchrod rod --length 0.6 --outer-diameter 0.0012 --inner-diameter 0.0009 --youngs-modulus 193e9 \\
      --gratings 0.05,0.15,0.25,0.35,0.45,0.55 --out my_rod.json

An existing rod file, or a preset:

  torchrod rod my_rod.json

Either way the rod is checked as every command checks it (a value in millimetres or GPa is refused, with the
conversion), and the report says: EI; where the gratings sit; how many forces a reading can tell apart (a fit of h
forces has 3h unknowns against the 2G values of a reading, and needs 3 degrees of freedom left to be tested);
whether the shipped warm-start network serves the grating layout; and the curvature a 1 N tip load gives at the
grating nearest the clamp, against a typical sensor noise of 0.1 1/m (--noise for another). The fibre and
intrinsic_curvature sections are not options: add them to the written file by hand (docs/sensors.md,
docs/guides/precurved.md), then check the file again.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from typing import Any

from . import rod_help

HELP = "write a rod file from its numbers, or check one, and show what the rod can do"

NUMBER_OPTIONS: dict[str, str] = {
    "length": "from the clamp to the free tip [m]",
    "outer_diameter": "the tube's outer diameter [m]",
    "inner_diameter": "the tube's inner diameter [m] (0 for a solid rod)",
    "youngs_modulus": "Young's modulus [Pa] (67e9 for Nitinol, 193e9 for steel)",
    "bending_stiffness": "EI [N m^2], instead of the three above",
    "location_bias": "added to every reported location [m] (default 0; torchrod calibrate fits it)",
    "poisson_ratio": "nu of a precurved rod's torsion, GJ = EI / (1 + nu) (default 0.33)",
    "torsional_stiffness": "GJ [N m^2], instead of --poisson-ratio",
    "calibration_error": "every grating's relative calibration error, a fraction of the signal (0.1: 10 %%; default "
    "none; per grating in the file; torchrod calibrate --fibre writes it)",
}
"""The rod file's number keys that are options of their own (``--length`` for ``length``, ...), with their help;
``gratings`` is ``--gratings``, and ``fibre`` and ``intrinsic_curvature`` are added to the file by hand."""

NOT_OPTIONS = ("fibre", "intrinsic_curvature")
"""The rod file's keys that are no option: sections too rich for a command line."""


def _option(key: str) -> str:
    return "--" + key.replace("_", "-")


def _gratings(text: str) -> list[float]:
    """``--gratings`` for argparse: comma-separated positions [m]; a usage error names an entry that is no number."""
    out = []
    for k, cell in enumerate(text.split(","), start=1):
        try:
            out.append(float(cell.strip()))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"entry {k}, {cell.strip()!r}, is not a number: give positions [m] separated by commas, as "
                "0.05,0.15,0.25"
            ) from None
    return out


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "rod",
        nargs="?",
        metavar="ROD",
        help=rod_help(what=" to check") + "; or leave it out and give the rod's numbers",
    )
    numbers = parser.add_argument_group("the rod's numbers (instead of ROD; SI units)")
    metavars = {"length": "M", "outer_diameter": "M", "inner_diameter": "M", "youngs_modulus": "PA"}
    for key in ("length", "outer_diameter", "inner_diameter", "youngs_modulus", "bending_stiffness"):
        numbers.add_argument(_option(key), type=float, metavar=metavars.get(key, "X"), help=NUMBER_OPTIONS[key])
    numbers.add_argument(
        "--gratings",
        type=_gratings,
        metavar="S1,S2,...",
        help="each grating's arc length from the clamp [m], increasing, comma-separated",
    )
    for key in ("location_bias", "poisson_ratio", "torsional_stiffness", "calibration_error"):
        numbers.add_argument(_option(key), type=float, metavar="X", help=NUMBER_OPTIONS[key])
    parser.add_argument(
        "--out",
        metavar="FILE",
        help="write the rod file there ('-': standard output, the report then goes to standard error)",
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="SIGMA",
        help="the sensor's curvature noise [1/m] the tip load's curvature is set against (default 0.1)",
    )


def _from_numbers(args: argparse.Namespace):
    """The rod the number options describe (:meth:`torchrod.Rod.from_dict`, which names a bad value)."""
    from ...rod import Rod

    data: dict[str, Any] = {key: getattr(args, key) for key in NUMBER_OPTIONS if getattr(args, key) is not None}
    if args.gratings is not None:
        data["gratings"] = args.gratings
    missing = [_option(key) for key in ("length", "gratings") if key not in data]
    if missing:
        raise ValueError(f"give {' and '.join(missing)} (or a rod file, ROD)")
    if not any(key in data for key in ("outer_diameter", "inner_diameter", "youngs_modulus", "bending_stiffness")):
        raise ValueError("give --outer-diameter, --inner-diameter and --youngs-modulus, or --bending-stiffness")
    return Rod.from_dict(data)


def _mm(x: float) -> str:
    return f"{x * 1e3:.6g}"


def _newtons(x: float) -> str:
    return f"{x:.3g} N" if x >= 1.0 else f"{x * 1e3:.3g} mN"


def report_lines(report, where: str) -> list[str]:
    """The report of :func:`torchrod.eval.rod_report.describe_rod` as ``torchrod rod`` prints it."""
    from ...rod import MIN_TEST_DOF

    wrap = textwrap.TextWrapper(width=100, subsequent_indent=" " * 20)
    lines = [f"rod                 {where}", f"length              {_mm(report.length)} mm"]
    source = "from the geometry, E pi (d_out^4 - d_in^4) / 64" if report.stiffness_from == "geometry" else "as given"
    lines.append(f"EI                  {report.bending_stiffness:.6g} N m^2 ({source})")
    lines += wrap.wrap(
        f"gratings            {report.num_gratings}, at {', '.join(_mm(g) for g in report.gratings)} mm from the clamp"
    )
    lines += ["", *report.layout.splitlines(), ""]
    h, n = report.max_forces, report.values_per_reading
    if h:
        forces = (
            f"up to {h} told apart by a full reading: {n} values (ux, uy per grating) against 3 unknowns a force "
            f"(s, fx, fy) leave {n - 3 * h} >= {MIN_TEST_DOF} degrees of freedom to test the fit of {h}, and "
            f"{n - 3 * (h + 1)} for {h + 1}"
        )
    else:
        forces = (
            f"none told apart: a reading's {n} values leave fewer than {MIN_TEST_DOF} degrees of freedom to test "
            "the fit of one force (3 unknowns: s, fx, fy)"
        )
    lines += wrap.wrap(f"forces              {forces}")
    if h < 3:
        lines += wrap.wrap(
            f"                    estimate and stream choose among 0 to {h} forces (their default here), and "
            "never more whatever the largest count they are given"
        )
    network = report.network_reason
    if report.network_weak:
        network += f"; weak, so its guesses only add starts beside the search's: {report.network_weak}"
    lines += wrap.wrap(f"warm-start network  {network}")
    tip = (
        f"{report.tip_curvature:.3g} 1/m at the grating nearest the clamp ({_mm(report.base_grating)} mm), "
        f"{report.tip_signal_to_noise:.3g} times a noise of {report.noise:g} 1/m"
    )
    if not report.tip_curvature_accurate:
        tip += " (the load bends the rod too far for the simulation's accuracy bound)"
    if abs(report.tip_curvature - report.tip_curvature_linear) > 0.1 * report.tip_curvature_linear:
        tip += (
            f"; the load bends the rod far: small loads give {report.tip_curvature_linear:.3g} 1/m per N there (a "
            "linear response)"
        )
    tip += f"; a tip force of {_newtons(report.smallest_tip_force)} gives that grating a curvature equal to the noise"
    lines += wrap.wrap(f"{report.tip_load:g} N at the tip      {tip}")
    for text in report.limitations:
        lines += wrap.wrap(f"limitation          {text}")
    if not report.limitations:
        lines.append("limitations         none")
    return lines


def run(args: argparse.Namespace) -> int:
    from ...eval.rod_report import TYPICAL_NOISE, describe_rod
    from ...io.jsonl import STDOUT_CLOSED, ClosedOutput, check_output
    from ...presets import load as load_rod

    given = [_option(key) for key in (*NUMBER_OPTIONS, "gratings") if getattr(args, key) is not None]
    if args.rod is not None and given:
        raise ValueError(
            f"give a rod file (ROD) or the rod's numbers, not both (ROD {args.rod} and {', '.join(given)})"
        )
    if args.rod is None and not given:
        raise ValueError("give a rod file or preset (ROD) to check, or the rod's numbers (--length, --gratings, ...)")
    if args.noise is not None and not 0.0 < args.noise < float("inf"):
        raise ValueError(f"--noise must be a positive sigma [1/m], got {args.noise}")
    check_output(args.out, {"ROD": args.rod})
    if args.out == "-" and (sys.stdout is None or isinstance(sys.stdout, ClosedOutput)):
        raise ValueError(STDOUT_CLOSED)
    rod = load_rod(args.rod) if args.rod is not None else _from_numbers(args)
    report = describe_rod(rod, TYPICAL_NOISE if args.noise is None else args.noise)
    if args.out == "-":
        json.dump(rod.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    elif args.out is not None:
        try:
            rod.to_json(args.out)
        except OSError as exc:
            raise ValueError(f"--out {args.out}: cannot write there ({exc.strerror or exc})") from None
    where = args.rod if args.rod is not None else (args.out if args.out not in (None, "-") else "the numbers given")
    text = "\n".join(report_lines(report, where))
    print(text, file=sys.stderr if args.out == "-" else sys.stdout)
    if args.out not in (None, "-"):
        print(f"wrote {args.out}", file=sys.stderr)
    return 0
