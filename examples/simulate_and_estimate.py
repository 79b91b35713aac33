"""Simulate known contact forces on the paper's tube, add sensor noise, and estimate them back.

    python examples/simulate_and_estimate.py [--count N] [--noise SIGMA] [--seed S]

Prints, per reading, the true forces and the estimate: its status, the number of forces, and each force's location
[mm] and components [N] with their standard deviations. SI units inside; millimetres only in what is printed.
"""

from __future__ import annotations

import argparse
import random

import torch

import torchrod as tr
from torchrod.learn.warm_start import SHIPPED_CHECKPOINT


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=5, help="readings to simulate (default 5)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor noise sigma [1/m] (default 0.1)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rod = tr.presets.nitinol290()  # 290 mm Nitinol tube, 14 gratings at 10, 30, ..., 270 mm
    rng = random.Random(args.seed)
    cases = []  # per reading: one or two forces (s [m], f_x [N], f_y [N]), 60-280 mm from the base, 40 mm apart
    for _ in range(args.count):
        s = sorted(rng.sample(range(60, 281, 40), rng.randint(1, 2)))
        cases.append([(1e-3 * x, rng.uniform(-1, 1), rng.uniform(-1, 1)) for x in s])
    loads = tr.PointForces.from_lists(cases)

    kappa = tr.grating_curvature(rod, loads)  # (B, 14, 2) body-frame curvature at the gratings [1/m]
    noisy = kappa + args.noise * torch.randn(
        kappa.shape, generator=torch.Generator().manual_seed(args.seed), dtype=kappa.dtype
    )

    estimator = tr.load_estimator(SHIPPED_CHECKPOINT, rod, tr.EstimatorOptions(noise=args.noise))
    result = estimator.estimate(noisy)
    for b, record in enumerate(result.to_records()):
        truth = ", ".join(f"{1e3 * s:.1f} mm ({fx:+.3f}, {fy:+.3f}) N" for s, fx, fy in cases[b])
        print(f"reading {b}: true {truth}")
        print(f"  estimate: {record['status']}, {record['num_forces']} force(s), p-value {record['p_value']:.2f}")
        for force in record["forces"]:
            print(
                f"    s = {1e3 * force['s']:.1f} +- {1e3 * force['std_s']:.1f} mm, "
                f"f = ({force['fx']:+.3f} +- {force['std_fx']:.3f}, {force['fy']:+.3f} +- {force['std_fy']:.3f}) N"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
