"""``torchrod bench estimate``: speed of force estimation, one reading at a time and batched.

Readings: the envelope of ``torchrod evaluate`` (k forces at least 25 mm apart, 0.05 to 2 N in any body-frame
direction (on a rod of length L other than 0.29 m, scaled by (0.29 m / L)^2, which bends it alike), locations uniform
from the rod's second grating to the tip, bending <= 90 degrees), Gaussian noise ``--noise`` per component, for k =
1, 2, 3 and for a mix of the three. The estimator runs with its default options, the count chosen automatically among
0..3, and is told the noise (as a calibrated sensor would).

Per k: B = 1 (``--single`` readings estimated one after the other: mean, median, 90th and 99th percentiles of the
wall time per call, and the mean process CPU time, which a busy machine inflates less) and batched (``--batched``
readings in calls of ``--batch-size``: readings per second, wall and CPU). Count accuracy is printed as a sanity
check. Every timing follows a warm-up call (the kernels compiled or loaded, per-rod set-up). ``--threads`` is the
CPU threads of a batched call (a single reading is never split); the one-at-a-time rows run on one.
``--device`` estimates on that device (e.g. ``cuda``, the readings made on the CPU and moved there; the batched
time includes reading the counts back); ``--forces`` picks the rows. ``--checkpoint`` adds a warm-start network's
guesses (``shipped``: the one shipped for the rod's layout; by default none). ``--gap-ms`` waits that long before
each one-at-a-time call, as a live source paced at 1000 / MS Hz leaves the estimator idle between its readings:
the processor's caches then start cold, which costs more than the arithmetic at a batch of one.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time

import torch

from ...estimate.estimator import Estimator
from ...io.stream import warm_up
from ...presets import load as load_rod
from ..commands import add_device_option, check_device, rod_help
from . import SUITES
from .stream import _network, _options

HELP = SUITES["estimate"]

__all__ = ["HELP", "configure", "readings", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--single", type=int, default=40, help="readings timed one at a time per k (default 40)")
    parser.add_argument("--batched", type=int, default=1000, help="readings timed batched per k (default 1000)")
    parser.add_argument("--batch-size", type=int, default=500, help="readings per batched call (default 500)")
    parser.add_argument("--threads", type=int, default=1, help="CPU threads of the batched calls (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the readings (default 0)")
    parser.add_argument(
        "--forces", default="1,2,3,1-3", metavar="K,...", help="the rows: counts 1, 2, 3 and the mix 1-3 (default all)"
    )
    parser.add_argument(
        "--checkpoint", default="none", help="warm-start network: a checkpoint, 'shipped' or 'none' (default none)"
    )
    parser.add_argument(
        "--gap-ms", type=float, default=0.0, help="idle time before each one-at-a-time call [ms] (default 0)"
    )
    add_device_option(parser)
    parser.add_argument("--quick", action="store_true", help="a smoke run: 3 single and 20 batched readings")


def readings(rod, k: int | None, count: int, noise: float, seed: int):
    """A :class:`torchrod.synthetic.loadsets.SyntheticSet` of ``count`` readings with k forces (None: 1 to 3)."""
    from ...synthetic import LoadSampler, SensorModel, generate

    lo = rod.gratings[1] if rod.num_gratings > 1 else 0.02 * rod.length
    scale = (0.29 / rod.length) ** 2  # the same turning as on the 290 mm tube (moment ~ force x length)
    sampler = LoadSampler(
        min_forces=k or 1,
        max_forces=k or 3,
        force_range=(0.05 * scale, 2.0 * scale),
        s_range=(lo, rod.length),
        max_bending=math.pi / 2,
    )
    sensor = SensorModel(noise=noise, location_bias=rod.location_bias)
    return generate(rod, count, sampler=sampler, sensor=sensor, seed=seed)


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    single, batched, batch_size = args.single, args.batched, args.batch_size
    if args.quick:
        single, batched = 3, 20
    if min(single, batched, batch_size) < 1:
        raise ValueError("--single, --batched and --batch-size must be >= 1")
    if not (0.0 <= args.gap_ms < math.inf):
        raise ValueError(f"--gap-ms must be a finite number >= 0, got {args.gap_ms}")
    rows = {"1": 1, "2": 2, "3": 3, "1-3": None}
    wanted = [x.strip() for x in args.forces.split(",")]
    if not wanted or any(x not in rows for x in wanted):
        raise ValueError(f"--forces takes some of 1, 2, 3 and 1-3, comma-separated, got {args.forces!r}")
    device = check_device(args)
    torch.set_num_threads(1)
    network, network_name = _network(None if args.checkpoint == "shipped" else args.checkpoint, rod)
    if args.checkpoint == "shipped" and network is None:
        raise ValueError(f"no shipped network fits this rod: {network_name}")
    options = dataclasses.replace(_options(args.noise, [], network), threads=args.threads)
    estimator = Estimator(rod, options, warm_start=network)
    one = dataclasses.replace(estimator.options, threads=1)
    gap = args.gap_ms / 1e3
    print(
        f"# torchrod bench estimate: {rod.num_gratings} gratings, noise {args.noise:g} 1/m (known), "
        f"count chosen in 0..3, CPU threads of a batch {args.threads}, device {device}, network {network_name}"
        + (f", {args.gap_ms:g} ms idle before each one-at-a-time call" if gap else "")
    )
    print(
        f"{'forces':>6} | {'B=1 ms mean':>11} {'median':>7} {'p90':>7} {'p99':>7} {'cpu':>7} | {'batched rd/s':>12} "
        f"{'ms/rd':>7} {'cpu ms/rd':>9} | {'count ok':>8}"
    )
    estimator.plan(device=device, wait=True)
    warm_up(estimator, device)  # (the network's passes for small and large batches too)
    for k in (rows[x] for x in wanted):
        data = readings(rod, k, max(single, batched), args.noise, args.seed + (k or 0))
        curvature, mask = data.curvature.to(device), data.mask.to(device)
        truth = data.loads.count
        estimator.estimate(curvature[:1], mask[:1])  # warm-up
        walls, cpus, right = [], [], 0
        for b in range(single):
            if gap:
                time.sleep(gap)
            w0, c0 = time.perf_counter(), time.process_time()
            res = estimator.estimate(curvature[b : b + 1], mask[b : b + 1], options=one)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
            right += int(res.num_forces[0].cpu() == truth[b])
        w0, c0 = time.perf_counter(), time.process_time()
        for b0 in range(0, batched, batch_size):
            res = estimator.estimate(
                curvature[b0 : min(batched, b0 + batch_size)], mask[b0 : min(batched, b0 + batch_size)]
            )
            right += int((res.num_forces.cpu() == truth[b0 : b0 + res.num_forces.shape[0]]).sum())
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        walls_ms = sorted(1e3 * w for w in walls)
        p90, p99 = (walls_ms[min(len(walls_ms) - 1, math.ceil(q * len(walls_ms)) - 1)] for q in (0.9, 0.99))
        label = str(k) if k else "1-3"
        print(
            f"{label:>6} | {statistics.mean(walls_ms):>11.1f} {statistics.median(walls_ms):>7.1f} {p90:>7.1f} "
            f"{p99:>7.1f} "
            f"{1e3 * statistics.mean(cpus):>7.1f} | {batched / wall:>12.0f} {1e3 * wall / batched:>7.2f} "
            f"{1e3 * cpu / batched:>9.2f} | {100 * right / (single + batched):>7.1f}%"
        )
    return 0
