"""``torchrod bench gratings``: a needle with 3 gratings and one grating's gain off, with and without a calibration
error.

The study of :mod:`torchrod.eval.few_gratings`: a 130 mm needle with gratings at 60, 104 and 119 mm, one force near the
tip, Gaussian noise ``--noise`` (known to the estimator, or not with ``--noise-unknown``), one grating per reading
reading ``1 + e`` times its curvature for each gain error e of ``--gain-errors``; each set estimated by the needle
without a calibration error and by the needle whose every grating carries the relative error e, the count chosen among 0
to ``--max-forces`` (3 by default: more than the needle can test, so the count rule is what keeps two forces out).
Prints a Markdown table: the fraction answered with 0, 1 and 2 or more forces, the spread of the direction, magnitude
and location errors over the readings answered with one force, the fraction answered ``ok`` and the count accuracy.
``--quick``: a smoke run.
"""

from __future__ import annotations

import argparse
import time

from . import SUITES

HELP = SUITES["gratings"]

__all__ = ["HELP", "configure", "run"]


def _fractions(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated fractions, got {text!r}") from None
    if not values or any(not 0.0 <= v <= 10.0 for v in values):
        raise argparse.ArgumentTypeError(f"expected fractions in [0, 10], got {text!r}")
    return values


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a smoke run: 8 readings per row, two gain errors")
    parser.add_argument("--count", type=int, default=200, help="readings per gain error (default 200)")
    parser.add_argument(
        "--gain-errors", type=_fractions, default=(0.0, 0.1, 0.25, 0.5, 1.0), metavar="E1,E2,...",
        help="the bad grating's gain errors, fractions (default 0,0.1,0.25,0.5,1)",
    )  # fmt: skip
    parser.add_argument("--noise", type=float, default=0.05, help="sensor sigma [1/m], known (default 0.05)")
    parser.add_argument(
        "--noise-unknown", action="store_true", help="the estimator is not told the noise (each reading's own)"
    )
    parser.add_argument("--max-forces", type=int, default=3, help="the largest count asked for (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the readings (default 0)")
    parser.add_argument("--threads", type=int, help="CPU threads of the kernels (default: every core)")


def run(args: argparse.Namespace) -> int:
    from ...eval.few_gratings import study, table

    if args.count < 1 or args.noise <= 0.0 or args.max_forces < 1:
        raise ValueError("--count and --max-forces must be >= 1, --noise positive")
    count, errors = (8, (0.0, 0.5)) if args.quick else (args.count, args.gain_errors)
    began = time.perf_counter()
    rows = study(errors, count, args.noise, args.max_forces, args.seed, args.threads, not args.noise_unknown)
    known = "not told the estimator" if args.noise_unknown else "known"
    print(
        f"needle 130 mm, gratings at 60, 104, 119 mm; one force near the tip; noise {args.noise:g} 1/m ({known}); "
        f"{count} readings per gain error; --max-forces {args.max_forces}"
    )
    print("\n".join(table(rows)))
    print(f"({time.perf_counter() - began:.0f} s)")
    return 0
