"""``torchrod bench network``: what the warm-start network buys, on a held-back simulated set.

Readings: the envelope of ``torchrod evaluate`` (k = 1, 2, 3 forces at least 25 mm apart, 0.05 to 2 N in any
body-frame direction, locations from the second grating to the tip, bending <= 90 degrees), Gaussian noise
``--noise``, drawn from a seed the shipped checkpoint was not trained on. Three rows per k:

* ``network``: the network alone (its most probable count and that count's forces);
* ``estimator``: the estimator without a network (the scan's starts);
* ``estimator+network``: :func:`torchrod.load_estimator`: the network's guesses beside the scan's
  starts, or alone where the checkpoint's recorded quality says it can be trusted;
* ``trusted``: the estimator trusting the network whatever its recorded verdict (``trust_guesses``: its most
  probable count and the one below fitted from its guesses alone, the counts below not fitted);
* ``torch target``: the same estimator with ``target="torch"``: the network's guesses refined in torch, judged
  by the kernels, the readings not answered ``ok`` searched again (:mod:`torchrod.estimate.refine`).

Columns: count accuracy, median force error (|f_est - f_true| / |f_true|, %) and location error (mm) over readings
whose count is right, median solver steps of the chosen fit, mean forward-model evaluations per reading, readings
per second batched (``--batch-size``), time of one reading alone (``--single`` readings, median), and agreement
with the estimator alone: the share of readings given its count, and among those the share whose every force and
location is within one of its standard deviations of the estimator alone's (``within 1 sd``). All rows run side by
side in one process; the checkpoint's trust verdict comes first.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from types import SimpleNamespace
from typing import Any

import torch

from ...estimate.estimator import Estimator, EstimatorOptions
from ...learn.warm_start import SHIPPED_CHECKPOINT, load_estimator, quality_verdict
from ...presets import load as load_rod
from ..commands import rod_help
from ..commands.evaluate import cell_metrics
from . import SUITES
from .estimate import readings

HELP = SUITES["network"]

__all__ = ["HELP", "configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument("--checkpoint", default=SHIPPED_CHECKPOINT, help="warm-start checkpoint")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--count", type=int, default=300, help="held-back readings per k (default 300)")
    parser.add_argument("--single", type=int, default=20, help="readings timed one at a time per k (default 20)")
    parser.add_argument("--batch-size", type=int, default=500, help="readings per batched call (default 500)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=777, help="seed of the held-back readings (default 777)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 12 readings per k, 2 timed singly")


def _network_alone(warm_start, data, k: int) -> dict:
    guess = warm_start.guess(data.curvature, data.mask)
    count = guess.count
    H = max(guess.forces)
    s = torch.zeros(count.shape[0], H, dtype=data.curvature.dtype)
    f = torch.zeros(count.shape[0], H, 2, dtype=data.curvature.dtype)
    for h, pf in guess.forces.items():
        rows = count == h
        s[rows, :h] = pf.s[rows].to(s.dtype)
        f[rows, :h] = pf.f[rows].to(f.dtype)
    fake: Any = SimpleNamespace(  # stands in for an EstimateResult
        num_forces=count,
        forces=SimpleNamespace(s=s, f=f),
        statuses=["ok"] * count.shape[0],  # the network gives no verdict
    )
    return cell_metrics([fake], data.loads.s, data.loads.f, k)


def _within_sd(answers: list, reference: list) -> torch.Tensor:
    """(N,) whether each answer's forces and locations lie within one of the reference answer's standard deviations
    of the reference's (answers of the same count; padding ignored)."""
    got = [torch.cat([getattr(r.forces, x) for r in answers]) for x in ("s", "f")]
    ref = [torch.cat([getattr(r.forces, x) for r in reference]) for x in ("s", "f")]
    std = torch.cat([r.std for r in reference])
    active = torch.cat([r.forces.mask for r in reference])
    width = min(got[0].shape[1], ref[0].shape[1])
    ok_s = (got[0][:, :width] - ref[0][:, :width]).abs() <= std[:, :width, 0]
    ok_f = ((got[1][:, :width] - ref[1][:, :width]).abs() <= std[:, :width, 1:]).all(-1)
    return ((ok_s & ok_f) | ~active[:, :width]).all(1)


def _timed(estimator: Estimator, data, batch_size: int, single: int) -> tuple[list, float, float]:
    estimator.estimate(data.curvature[:2], data.mask[:2])  # warm-up (per-rod caches)
    results = []
    start = time.perf_counter()
    for b0 in range(0, data.curvature.shape[0], batch_size):
        results.append(estimator.estimate(data.curvature[b0 : b0 + batch_size], data.mask[b0 : b0 + batch_size]))
    batched = (time.perf_counter() - start) / data.curvature.shape[0]
    times = []
    for i in range(min(single, data.curvature.shape[0])):
        t0 = time.perf_counter()
        estimator.estimate(data.curvature[i : i + 1], data.mask[i : i + 1])
        times.append(time.perf_counter() - t0)
    return results, batched, statistics.median(times) if times else float("nan")


def run(args: argparse.Namespace) -> int:
    from ...learn.warm_start import WarmStart

    torch.set_num_threads(args.threads)
    rod = load_rod(args.rod)
    count, single = (12, 2) if args.quick else (args.count, args.single)
    warm_start = WarmStart.load(args.checkpoint, rod)
    plain = Estimator(rod, EstimatorOptions(noise=args.noise))
    with_net = load_estimator(args.checkpoint, rod, EstimatorOptions(noise=args.noise), warn=lambda _: None)
    on_torch = Estimator(rod, dataclasses.replace(with_net.options, target="torch"), warm_start=with_net.warm_start)
    trusting = Estimator(rod, EstimatorOptions(noise=args.noise, trust_guesses=True), warm_start=warm_start)
    weak = quality_verdict(warm_start.meta)
    print(
        f"torchrod bench network: {rod.num_gratings} gratings, noise {args.noise} 1/m, {count} held-back readings "
        f"per k (seed {args.seed}), torch threads {torch.get_num_threads()}, checkpoint {args.checkpoint}"
    )
    print(f"trust verdict: {'trusted' if not weak else f'not trusted ({weak})'}")
    header = (
        f"{'k':>2} {'method':<18} {'count ok':>9} {'force err':>10} {'loc err':>8} {'iters':>6} {'evals':>7} "
        f"{'readings/s':>11} {'ms at B=1':>10} {'agree':>7} {'within 1 sd':>12}"
    )
    print(header)
    print("-" * len(header))
    for k in (1, 2, 3):
        data = readings(rod, k, count, args.noise, args.seed + k)
        rows: list[tuple[str, dict[str, Any], list | None, float | None, float | None]] = [
            ("network", _network_alone(warm_start, data, k), None, None, None)
        ]
        ways = [("estimator", plain), ("estimator+network", with_net), ("trusted", trusting)]
        for name, est in [*ways, ("torch target", on_torch)]:
            results, t_batched, t_one = _timed(est, data, args.batch_size, single)
            rows.append((name, cell_metrics(results, data.loads.s, data.loads.f, k), results, t_batched, t_one))
        reference = rows[1][2] or []
        alone = torch.cat([r.num_forces for r in reference])
        for name, m, answers, batched, one in rows:
            if answers is not None:
                iters = f"{torch.cat([r.iterations for r in answers]).double().median().item():.0f}"
                evals = f"{torch.cat([r.evaluations for r in answers]).double().mean().item():.1f}"
                same = torch.cat([r.num_forces for r in answers]) == alone
                agree = f"{100 * same.double().mean().item():.1f}%"
                near = _within_sd(answers, reference)[same]
                within = f"{100 * near.double().mean().item():.1f}%" if near.numel() else "-"
            else:
                iters = evals = agree = within = "-"
            print(
                f"{k:>2} {name:<18} {100 * m['count_accuracy']:>8.1f}% {m['force_error_median']:>9.2f}% "
                f"{m['location_error_median']:>6.2f}mm {iters:>6} {evals:>7} "
                f"{'-' if batched is None else f'{1 / batched:.0f}':>11} "
                f"{'-' if one is None else f'{1e3 * one:.1f}':>10} {agree:>7} {within:>12}",
                flush=True,
            )
    return 0
