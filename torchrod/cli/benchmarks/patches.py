"""``torchrod bench patches``: patches of load against point forces and real pairs, with the patch rule and the count
tests alone.

The study of :mod:`torchrod.eval.patches` on ``nitinol290``: ``--count`` patches ``--width`` mm long (0.2 to 2 N, any
direction, centred between the second grating and the tip), the same loads as one force at each patch's centre, and
readings of 2 and 3 real forces at least 25 mm apart; noise ``--noise``, given to the estimator and not. Each set is
estimated with ``merge_patches`` on and off. Prints a Markdown table: the fraction answered with two forces or more
and with the right count, both ways, and the answers the rule changed. ``--quick``: a smoke run.
"""

from __future__ import annotations

import argparse
import time

from . import SUITES

HELP = SUITES["patches"]

__all__ = ["HELP", "configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a smoke run: 40 readings per set")
    parser.add_argument("--count", type=int, default=3000, help="readings per set of loads (default 3000)")
    parser.add_argument("--width", type=float, default=12.0, help="patch length [mm] (default 12)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--seed", type=int, default=1000, help="seed of the loads and the noise (default 1000)")
    parser.add_argument("--threads", type=int, help="CPU threads of the kernels (default: every core)")


def run(args: argparse.Namespace) -> int:
    from ...eval.patches import study, table

    if args.count < 1 or args.noise <= 0.0 or args.width <= 0.0:
        raise ValueError("--count must be >= 1, --noise and --width positive")
    count = 40 if args.quick else args.count
    began = time.perf_counter()
    rows = study(count, args.width / 1e3, args.noise, args.seed, args.threads)
    print(
        f"nitinol290 (gratings 20 mm apart): {count} readings per set; patches {args.width:g} mm long; "
        f"noise {args.noise:g} 1/m; seed {args.seed}"
    )
    print("\n".join(table(rows)))
    print(f"({time.perf_counter() - began:.0f} s)")
    return 0
