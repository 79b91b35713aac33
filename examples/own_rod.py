"""Describe a rod of your own, check it, save it as a rod file, and estimate on it.

    python examples/own_rod.py [--out my_rod.json] [--count N]

The rod: a 400 mm stainless-steel tube, 1.2 mm outside and 0.9 mm inside diameter, E = 193 GPa, with 8 gratings
every 50 mm from 25 mm. Every value in SI units (m, Pa): a rod file in mm or GPa is refused, as the units are not
checked elsewhere. The rod file this writes is what ``--rod`` takes on the command line. No shipped network fits
its grating layout, so the estimator finds its starts by its scan alone (as accurate, a little slower).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import torch

import torchrod as tr


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", help="where to write the rod file (default: a temporary folder)")
    parser.add_argument("--count", type=int, default=3, help="readings to simulate and estimate (default 3)")
    args = parser.parse_args(argv)

    rod = tr.Rod.from_geometry(
        length=0.400,  # [m]
        outer_diameter=1.2e-3,  # [m]
        inner_diameter=0.9e-3,  # [m]
        youngs_modulus=193e9,  # [Pa]
        gratings=[round(0.025 + 0.050 * k, 6) for k in range(8)],  # [m] from the clamped base
    )
    print(f"bending stiffness EI = {rod.bending_stiffness:.4g} N m^2, {rod.num_gratings} gratings")

    out = args.out or os.path.join(tempfile.mkdtemp(), "my_rod.json")
    rod.to_json(out)
    again = tr.Rod.from_json(out)  # what `--rod my_rod.json` reads
    assert again.bending_stiffness == rod.bending_stiffness and again.gratings == rod.gratings
    print(f"rod file: {out}")
    print(json.dumps(json.loads(open(out, encoding="utf-8").read())))

    # One force per reading, somewhere past the second grating, simulated and estimated back.
    cases = [[(0.10 + 0.25 * k / max(args.count - 1, 1), 0.3, -0.2 + 0.1 * k)] for k in range(args.count)]
    kappa = tr.grating_curvature(rod, tr.PointForces.from_lists(cases))
    noisy = kappa + 0.05 * torch.randn(kappa.shape, generator=torch.Generator().manual_seed(1), dtype=kappa.dtype)
    result = tr.Estimator(rod, tr.EstimatorOptions(noise=0.05)).estimate(noisy)
    for case, record in zip(cases, result.to_records(), strict=True):
        (s, fx, fy) = case[0]
        got = "; ".join(f"{1e3 * f['s']:.1f} mm ({f['fx']:+.3f}, {f['fy']:+.3f}) N" for f in record["forces"])
        print(f"true {1e3 * s:.1f} mm ({fx:+.3f}, {fy:+.3f}) N -> {record['status']}: {got}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
