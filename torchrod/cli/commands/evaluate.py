"""``torchrod evaluate``: accuracy and speed of the estimator on simulated readings over a realistic envelope.

Usage: ``torchrod evaluate [--rod ROD] [--count-per-cell N] [--noise 0,0.1,0.3] [--seed S]``.

For every number of forces k = 1..``--max-forces`` and every noise level sigma, N load cases are drawn
(:mod:`torchrod.synthetic`): k forces at least ``--min-separation`` apart (25 mm), magnitudes uniform in
``--force-range`` (0.05 to 2 N) in any body-frame direction, locations uniform over [``--s-min``, L], cases whose
rod turns by more than ``--max-bending-deg`` (90 degrees) redrawn; their readings carry Gaussian noise sigma per
component (and the rod's location bias). The estimator (``torchrod.Estimator``, default options, up to
``--max-forces`` forces, the count chosen automatically) is told sigma (``--estimator-noise known``, the default: a
sensor's noise is a datasheet figure) or estimates it (``estimate``).

Default ``--s-min``: the rod's second grating. A force proximal to the first grating bends no grating (it leaves no
trace in the readings), and a force between the first two gratings is seen by one grating only, whose two
components cannot separate the force's magnitude from its lever: location and magnitude are not identifiable there.
``--s-min 0.0058`` evaluates the synthetic default range (0.02 L) instead, unobservable forces included.

Printed, per (k, sigma) cell: readings, count accuracy (chosen count = k), the same over the readings whose weakest
force is at least 0.2 N (a 0.05 N force near the base bends the rod less than the noise), then over the forces of
the readings whose count is right (estimated and true forces paired in order of location): median and 90th
percentile force error |f_est - f_true| / |f_true| [%], median and 90th percentile location error [mm]; the share
of readings flagged poorly determined; estimation wall time per reading (all readings of a cell estimated in
batches of ``--batch-size``). ``--json`` prints the same numbers as JSON lines instead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

import torch

from ...estimate.estimator import EstimateResult, Estimator, EstimatorOptions
from ...presets import load as load_rod
from ...rod import Rod

HELP = "accuracy of the estimator on simulated readings over a realistic envelope"

STRONG = 0.2
"""[N] the column ``ok >=0.2N`` counts only readings whose weakest force is at least this strong."""

__all__ = ["HELP", "cell_metrics", "configure", "evaluate_cell", "run"]


def _floats(text: str) -> list[float]:
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not values or any(not math.isfinite(v) or v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected non-negative numbers, got {text!r}")
    return values


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "--rod", default="nitinol290", help="rod JSON file or preset name (default nitinol290)"
    )
    parser.add_argument(
        "--count-per-cell", type=int, default=200, metavar="N", help="readings per cell (default 200)"
    )
    parser.add_argument(
        "--noise", type=_floats, default=[0.0, 0.1, 0.3], help="sigmas [1/m] (default 0,0.1,0.3)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the load cases and noise (default 0)")
    parser.add_argument("--max-forces", type=int, default=3, help="forces per reading 1..H (default 3)")
    parser.add_argument("--force-range", type=_floats, default=[0.05, 2.0], help="[N] (default 0.05,2)")
    parser.add_argument("--min-separation", type=float, default=0.025, help="[m] (default 0.025)")
    parser.add_argument(
        "--s-min", type=float, default=None, help="[m] lowest location (default: the 2nd grating)"
    )
    parser.add_argument(
        "--max-bending-deg", type=float, default=90.0, help="turning limit [deg] (default 90)"
    )
    parser.add_argument(
        "--estimator-noise",
        choices=("known", "estimate"),
        default="known",
        help="give sigma to the estimator?",
    )
    parser.add_argument(
        "--batch-size", type=int, default=500, help="readings per estimate call (default 500)"
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1, as the timings assume)"
    )
    parser.add_argument("--json", action="store_true", help="JSON lines instead of a table")


def evaluate_cell(
    rod: Rod,
    k: int,
    sigma: float,
    count: int,
    *,
    seed: int = 0,
    max_forces: int = 3,
    force_range: tuple[float, float] = (0.05, 2.0),
    min_separation: float = 0.025,
    s_min: float | None = None,
    max_bending: float = math.pi / 2,
    noise_known: bool = True,
    batch_size: int = 500,
) -> dict[str, Any]:
    """Simulate ``count`` readings with ``k`` forces and noise ``sigma``, estimate them, return the cell's metrics
    (:func:`cell_metrics` plus ``time_ms`` per reading, wall clock of the estimation alone)."""
    from ...learn.synthetic import LoadSampler, SensorModel, generate

    lo = s_min if s_min is not None else (rod.gratings[1] if rod.num_gratings > 1 else 0.02 * rod.length)
    sampler = LoadSampler(
        min_forces=k,
        max_forces=k,
        force_range=force_range,
        min_separation=min_separation,
        s_range=(lo, rod.length),
        max_bending=max_bending,
    )
    sensor = SensorModel(noise=sigma, location_bias=rod.location_bias)
    data = generate(
        rod, count, sampler=sampler, sensor=sensor, seed=seed * 1000 + 10 * k + round(100 * sigma)
    )
    estimator = Estimator(rod, EstimatorOptions(max_forces=max_forces, noise=sigma if noise_known else None))
    estimator.estimate(data.curvature[:1], data.mask[:1])  # warm-up: per-rod caches, first-call costs
    results = []
    start = time.perf_counter()
    for b0 in range(0, count, batch_size):
        results.append(
            estimator.estimate(data.curvature[b0 : b0 + batch_size], data.mask[b0 : b0 + batch_size])
        )
    elapsed = time.perf_counter() - start
    out = cell_metrics(results, data.loads.s, data.loads.f, k)
    out.update(forces=k, noise=sigma, time_ms=1e3 * elapsed / max(1, count))
    return out


def cell_metrics(
    results: list[EstimateResult], s_true: torch.Tensor, f_true: torch.Tensor, k: int
) -> dict[str, Any]:
    """Count accuracy and force / location errors of estimates against the truth.

    Args:
        results: estimates of the readings, in order (concatenated).
        s_true: (N, >= k) true locations [m] (reported coordinates), sorted; f_true: (N, >= k, 2) [N].
        k: the true count.
    """
    num = torch.cat([r.num_forces for r in results])
    s_est = torch.cat([r.forces.s for r in results])
    f_est = torch.cat([r.forces.f for r in results])
    poorly = torch.cat([r.poorly_determined for r in results])
    ok = num == k
    n = num.shape[0]
    strong = torch.linalg.vector_norm(f_true[:, :k], dim=-1).amin(dim=1) >= STRONG
    out: dict[str, Any] = {
        "readings": n,
        "count_accuracy": float(ok.double().mean()) if n else math.nan,
        "count_accuracy_strong": float(ok[strong].double().mean()) if bool(strong.any()) else math.nan,
        "poorly_determined": float(poorly.double().mean()) if n else math.nan,
    }
    if bool(ok.any()):
        ts, tf = s_true[ok][:, :k], f_true[ok][:, :k]
        es, ef = s_est[ok][:, :k], f_est[ok][:, :k]
        f_err = (
            torch.linalg.vector_norm(ef - tf, dim=-1) / torch.linalg.vector_norm(tf, dim=-1)
        ).flatten() * 100
        s_err = (es - ts).abs().flatten() * 1e3
        out.update(
            force_error_median=float(f_err.median()),
            force_error_p90=float(f_err.quantile(0.9)),
            location_error_median=float(s_err.median()),
            location_error_p90=float(s_err.quantile(0.9)),
        )
    else:
        out.update(
            force_error_median=math.nan,
            force_error_p90=math.nan,
            location_error_median=math.nan,
            location_error_p90=math.nan,
        )
    return out


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    if args.count_per_cell < 1:
        raise ValueError(f"--count-per-cell must be >= 1, got {args.count_per_cell}")
    if args.max_forces < 1:
        raise ValueError(f"--max-forces must be >= 1, got {args.max_forces}")
    if len(args.force_range) != 2 or not 0 < args.force_range[0] <= args.force_range[1]:
        raise ValueError(f"--force-range must be two magnitudes low,high [N], got {args.force_range}")
    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    bending = math.radians(args.max_bending_deg) if args.max_bending_deg > 0 else math.inf
    lo = args.s_min if args.s_min is not None else rod.gratings[1] if rod.num_gratings > 1 else None
    if not args.json:
        where = f"s in [{lo * 1e3:.1f}, {rod.length * 1e3:.1f}] mm" if lo is not None else "s default range"
        print(
            f"# {args.count_per_cell} readings per cell; forces {args.force_range[0]:g}-{args.force_range[1]:g} N, "
            f">= {args.min_separation * 1e3:g} mm apart, {where}, bending <= {args.max_bending_deg:g} deg; "
            f"sigma {'given to' if args.estimator_noise == 'known' else 'estimated by'} the estimator; seed {args.seed}"
        )
        print(
            f"{'forces':>6} {'noise':>6} {'n':>5} {'count ok':>9} {'ok >=0.2N':>10} {'F err med':>10} {'F err p90':>10} "
            f"{'s err med':>10} {'s err p90':>10} {'poorly':>7} {'ms/read':>8}"
        )
        print(
            f"{'':>6} {'[1/m]':>6} {'':>5} {'[%]':>9} {'[%]':>10} {'[%]':>10} {'[%]':>10} {'[mm]':>10} {'[mm]':>10} {'[%]':>7} {'':>8}"
        )
    for k in range(1, args.max_forces + 1):
        for sigma in args.noise:
            m = evaluate_cell(
                rod,
                k,
                sigma,
                args.count_per_cell,
                seed=args.seed,
                max_forces=args.max_forces,
                force_range=(args.force_range[0], args.force_range[1]),
                min_separation=args.min_separation,
                s_min=lo,
                max_bending=bending,
                noise_known=args.estimator_noise == "known",
                batch_size=args.batch_size,
            )
            if args.json:
                print(
                    json.dumps(
                        {
                            key: (v if not isinstance(v, float) or math.isfinite(v) else None)
                            for key, v in m.items()
                        }
                    )
                )
            else:
                print(
                    f"{k:>6} {sigma:>6g} {m['readings']:>5} {100 * m['count_accuracy']:>9.1f} "
                    f"{100 * m['count_accuracy_strong']:>10.1f} "
                    f"{m['force_error_median']:>10.2f} {m['force_error_p90']:>10.2f} "
                    f"{m['location_error_median']:>10.2f} {m['location_error_p90']:>10.2f} "
                    f"{100 * m['poorly_determined']:>7.1f} {m['time_ms']:>8.2f}"
                )
            sys.stdout.flush()
    return 0
