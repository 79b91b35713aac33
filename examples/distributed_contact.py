"""A patch of load, not a point: how the estimator answers a contact spread over a few millimetres.

    python examples/distributed_contact.py [--count N] [--width MM] [--noise SIGMA] [--seed S]

Each reading is a patch of load ``--width`` mm long (25 equal point forces side by side, 0.2 to 2 N in all, in one
direction drawn at random), its centre drawn between the second grating and the tip of the ``nitinol290`` rod
(gratings 20 mm apart), with noise ``--noise`` (0.1 1/m). The estimator answers each, with the noise given and with each
reading's own; the script counts the answers of two forces or more, says whether their patch straddles a grating
and how many the count tests alone give (``merge_patches=False``: no pair merged into one patch), and for each such
answer prints where its forces are and how well one force alone fits the reading.
"""

from __future__ import annotations

import argparse

import torch

import torchrod as tr


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=300, help="patches (default 300)")
    parser.add_argument("--width", type=float, default=12.0, help="patch length [mm] (default 12)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    rod = tr.presets.nitinol290()
    generator = torch.Generator().manual_seed(args.seed)
    width = args.width / 1e3
    loads, centre = tr.synthetic.sample_patches(rod, args.count, width, generator)
    u = tr.grating_curvature(rod, loads)
    u = u + args.noise * torch.randn(u.shape, generator=generator, dtype=u.dtype)
    q = torch.tensor(rod.gratings, dtype=torch.float64)
    straddles = ((q[None, :] > centre[:, None] - width / 2) & (q[None, :] < centre[:, None] + width / 2)).any(1)
    print(
        f"{args.count} patches {args.width:g} mm long on {rod.num_gratings} gratings {1e3 * (q[1] - q[0]):.0f} mm "
        f"apart, noise {args.noise:g} 1/m; {int(straddles.sum())} straddle a grating"
    )
    for noise in (args.noise, None):
        result = tr.Estimator(rod, tr.EstimatorOptions(noise=noise)).estimate(u)
        tests_alone = tr.Estimator(rod, tr.EstimatorOptions(noise=noise, merge_patches=False)).estimate(u)
        two = result.num_forces >= 2
        said = "given" if noise is not None else "each reading's own"
        print(
            f"noise {said}: {int(two.sum())} of {args.count} answered with two forces or more "
            f"({int((two & straddles).sum())} of them straddling a grating; "
            f"{int((tests_alone.num_forces >= 2).sum())} with the count tests alone, merge_patches=False)"
        )
        idx = two.nonzero().flatten()
        if not len(idx):
            continue
        alone = tr.Estimator(rod, tr.EstimatorOptions(noise=noise, num_forces=1)).estimate(u[idx])
        for j, i in enumerate(idx.tolist()):
            n = int(result.num_forces[i])
            where = ", ".join(f"{1e3 * s:.1f}" for s in result.forces.s[i, :n].tolist())
            sizes = ", ".join(f"{f:.2f}" for f in result.forces.f[i, :n].norm(dim=-1).tolist())
            print(
                f"  patch at {1e3 * float(centre[i]):.1f} mm, {float(loads.f[i].sum(0).norm()):.2f} N: forces at "
                f"{where} mm of {sizes} N; one force alone: p-value {float(alone.p_value[j]):.2g}, "
                f"{alone.statuses[j]}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
