"""``torchrod bench paper``: the paper's evaluation (Xiao & Chen) measured here, in one run, beside its numbers.

1. Table II: single-force estimation time at q = 50, 100, 150, 200 for the paper's three methods, BVP + Levenberg-
   Marquardt, BVP + derivative propagation and its body-frame method with the node scheme, all inside ONE shared
   outer optimiser (scipy ``least_squares``, forward-difference Jacobian over (s, f_x, f_y), the same start and
   tolerances: :mod:`torchrod.eval.paper`), and torchrod's default estimator (exact point loads, warm-start network when
   its checkpoint is there, Levenberg-Marquardt; the count fixed to 1 so the comparison is like for like). The same
   ``--table-readings`` readings for every method (few: the BVP baselines take seconds each); the median wall time
   per estimate, one reading per call (torchrod also batched: all readings in one call, per reading), the ratios
   beside the paper's (29.0x and 101.6x at q = 100) and the largest difference between the estimates (the
   baselines solve the same discrete problem; torchrod differs from them by the node scheme's discretisation
   error, which falls with q).
2. Accuracy, shaped like the paper's experiments: ``--per-count`` readings (13) for 1, 2 and 3 forces of 0.27 to
   1.96 N spread along the rod, Gaussian noise ``--noise`` (0.15 1/m, the middle of a real FBG's 0.1 to 0.2) and the
   paper's calibrated location bias (-3.12 mm: readings simulated with it, estimates made with a rod that carries
   it). RMSE of the force magnitude and of the location beside the paper's, for torchrod's default (count chosen
   automatically; and given) and for the paper's method (node scheme, q = 250, the shared outer optimiser; count
   given, and by its own threshold rule).
3. Accuracy and time against q for the paper's method (count given), and the time for 1, 2 and 3 forces beside
   the paper's (q = 90 and 250) and torchrod's (count automatic).
4. The loss maps of the paper's figure (curvature and shape loss around 200 mm, 0.3 N; one batched forward call).

Figures (PNG) go to ``--out`` (``paper_table2.png``, ``paper_vs_q.png``, ``paper_loss_maps.png``). All
estimators run one reading at a time on ``--threads`` torch threads (default 1); scipy/numpy run single-threaded
on arrays this small. ``--quick``: a tiny configuration (seconds) for smoke tests.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
import torch

from ... import presets
from ...errors import MissingFileError
from ...estimate.estimator import Estimator, EstimatorOptions
from ...eval import paper as P
from ...learn.warm_start import SHIPPED_CHECKPOINT
from ..commands import rod_help
from . import SUITES

HELP = SUITES["paper"]

__all__ = ["HELP", "configure", "default_estimator", "run"]


def _ints(text: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 2 for v in values):
        raise argparse.ArgumentTypeError(f"expected node counts >= 2, got {text!r}")
    return values


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--rod", default=None, help=rod_help("nitinol290, calibrated"))
    parser.add_argument(
        "--location-bias",
        type=float,
        default=presets.PAPER_LOCATION_BIAS,
        help="[m] simulated and estimated location bias (default: the paper's -3.12e-3)",
    )
    parser.add_argument("--noise", type=float, default=0.15, help="sensor sigma [1/m] (default 0.15)")
    parser.add_argument("--table-nodes", type=_ints, default=[50, 100, 150, 200], help="q of Table II")
    parser.add_argument(
        "--table-readings", type=int, default=7, help="readings timed per method in Table II (default 7)"
    )
    parser.add_argument(
        "--batch",
        type=int,
        default=256,
        help="single-force readings of torchrod's batched timing (one call; default 256)",
    )
    parser.add_argument("--per-count", type=int, default=13, help="readings per force count (default 13)")
    parser.add_argument(
        "--accuracy-nodes",
        type=_ints,
        default=[30, 50, 90, 150, 250],
        help="q of the paper's method in the accuracy study (the last: its threshold rule too)",
    )
    parser.add_argument(
        "--checkpoint", default=SHIPPED_CHECKPOINT, help="warm-start network for torchrod ('none': without one)"
    )
    parser.add_argument("--no-network", action="store_true", help="torchrod without the warm-start network")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the readings (default 0)")
    parser.add_argument("--out", default="bench-paper", help="folder for the PNG figures (default bench-paper)")
    parser.add_argument("--no-figures", action="store_true", help="tables only")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    parser.add_argument("--quick", action="store_true", help="a tiny configuration (seconds): a smoke test")


def _checkpoint_path(path: str) -> str:
    """``--checkpoint``'s file; :class:`~torchrod.errors.MissingFileError` when it does not exist (a path named
    is an error, never silently skipped: ``--checkpoint none`` runs without a network)."""
    if not os.path.exists(path):
        raise MissingFileError(f"--checkpoint {path}: no such file (give a checkpoint file, or 'none')")
    return path


def default_estimator(rod, noise: float, checkpoint: str | None, **options) -> tuple[Estimator, str]:
    """torchrod's default estimator for ``rod`` told the sensor ``noise``, with the warm-start network of
    ``checkpoint`` when it exists and fits the rod; returns it and a line saying which."""
    opts = EstimatorOptions(noise=noise, **options)
    if not checkpoint or checkpoint.lower() == "none":
        return Estimator(rod, opts), "without a warm-start network (none given)"
    path = _checkpoint_path(checkpoint)
    from ...learn.warm_start import WarmStart

    try:
        net = WarmStart.load(path, rod)
    except (ValueError, RuntimeError, KeyError) as exc:
        return Estimator(rod, opts), f"without a warm-start network ({path} unusable: {exc})"
    return Estimator(rod, opts, warm_start=net), f"with the warm-start network {path}"


def _fmt(x: float, width: int = 8) -> str:
    if not math.isfinite(x):
        return f"{'-':>{width}}"
    if x >= 100:
        return f"{x:>{width}.0f}"
    if x >= 1:
        return f"{x:>{width}.2f}"
    return f"{x:>{width}.4f}"


def run(args: argparse.Namespace) -> int:
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    if not (args.noise >= 0.0 and math.isfinite(args.noise)):
        raise ValueError(f"--noise must be a finite sigma >= 0, got {args.noise}")
    if min(args.table_readings, args.per_count, args.batch) < 1:
        raise ValueError("--table-readings, --per-count and --batch must be >= 1")
    table_nodes, acc_nodes = args.table_nodes, args.accuracy_nodes
    table_readings, per_count, map_size, batch_size = (
        args.table_readings,
        args.per_count,
        (96, 101),
        args.batch,
    )
    if args.quick:
        table_nodes, acc_nodes, table_readings, per_count, map_size, batch_size = (
            [20, 40],
            [30, 60],
            1,
            2,
            (24, 21),
            4,
        )
    rod = presets.nitinol290() if args.rod is None else presets.load(args.rod)
    rod = rod.with_(location_bias=args.location_bias)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()

    def progress(text: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - t_start:6.1f} s] {text}", file=sys.stderr, flush=True)

    try:
        return _run(
            args,
            rod,
            table_nodes,
            acc_nodes,
            table_readings,
            per_count,
            map_size,
            batch_size,
            progress,
            t_start,
        )
    finally:
        torch.set_num_threads(threads)


def _run(args, rod, table_nodes, acc_nodes, table_readings, per_count, map_size, batch_size, progress, t_start) -> int:
    checkpoint = None if args.no_network else args.checkpoint
    single, which = default_estimator(rod, args.noise, checkpoint, num_forces=1)
    auto, _ = default_estimator(rod, args.noise, checkpoint)
    print(
        f"# torchrod bench paper: L = {1e3 * rod.length:.0f} mm, EI = {rod.bending_stiffness:.4g} N m^2, "
        f"{rod.num_gratings} gratings, location bias {1e3 * rod.location_bias:+.2f} mm, noise {args.noise:g} 1/m, "
        f"torch threads {torch.get_num_threads()}"
    )
    print(f"# torchrod default: Estimator (exact point loads, Levenberg-Marquardt, noise known) {which}")
    print(
        "# baselines: scipy least_squares (trf, s in [0, L]), forward-difference Jacobian over (s, fx, fy), "
        "grid-scan start, the same tolerances; inner: RK4 shooting (LM: fd Jacobian, vectorised; DP: derivative "
        "propagation), warm-started; or the body-frame node scheme (batched)"
    )

    # ------------------------------------------------------------------ 1. Table II
    table_rd = P.paper_readings(rod, 1, table_readings, noise=args.noise, seed=args.seed + 100)
    batch_rd = P.paper_readings(rod, 1, batch_size, noise=args.noise, seed=args.seed + 200)
    table = P.speed_table(rod, table_rd, single, nodes=table_nodes, batch=batch_rd, progress=progress)
    print()
    print(
        f"## Table II: single-force estimation time [s], median over {table_readings} reading(s), one per call "
        f"(paper: MATLAB fmincon, 6-core i7); torchrod batched: {table.batch_size} readings in one call, per "
        "reading"
    )
    print(
        f"{'q':>5} | {'BVP+LM':>8} {'paper':>7} | {'BVP+DP':>8} {'paper':>7} | {'nodes':>8} {'paper':>7} | "
        f"{'torchrod':>8} {'batched':>8}"
    )
    t_mine = table.median("torchrod")
    for q in table_nodes:
        pq = P.PAPER_TABLE_II.get(q, {})
        cells = []
        for name in P.BASELINES:
            cells.append(f"{_fmt(table.median(name, q))} {_fmt(pq.get(name, math.nan), 7)}")
        print(f"{q:>5} | " + " | ".join(cells) + f" | {_fmt(t_mine)} {_fmt(table.torchrod_batched)}")
    print("speed-ups (baseline time / torchrod time; paper: its node method as the reference):")
    for q in table_nodes:
        paper_row = P.PAPER_TABLE_II.get(q)
        parts = []
        for name in ("bvp_lm", "bvp_dp", "nodes"):
            mine = table.speedup(name, q)
            cpu = table.speedup(name, q, what="cpu")
            batched = table.speedup(name, q, batched=True)
            paper = paper_row[name] / paper_row["nodes"] if paper_row and name != "nodes" else math.nan
            ptxt = f", paper {paper:.1f}x" if math.isfinite(paper) else ""
            if name == "nodes":
                parts.append(f"{name} {mine:.2f}x (cpu {cpu:.2f}x, batched {batched:.1f}x)")
            else:
                parts.append(f"{name} {mine:.1f}x (cpu {cpu:.1f}x, batched {batched:.0f}x{ptxt})")
        print(f"  q = {q}: " + "; ".join(parts))
    print(
        "agreement: largest |ds| [mm] / |df| [N] over the readings (median |ds| in brackets); 'exact loss': the "
        "largest excess of torchrod's loss over the node scheme's, both estimates under the exact model [1/m^2]"
    )
    mine_loss = table.exact_losses("torchrod")
    for q in table_nodes:
        parts = []
        for method, ref in (("bvp_lm", "nodes"), ("bvp_dp", "nodes"), ("torchrod", "nodes")):
            ds, df = table.gaps(method, ref, q)
            parts.append(f"{method} vs {ref} {1e3 * ds.max():.2g} / {df.max():.2g} ({1e3 * np.median(ds):.2g})")
        excess = float((mine_loss - table.exact_losses("nodes", q)).max())
        fails = sum(table.failures[m][q] for m in table.failures)
        print(
            f"  q = {q}: "
            + "; ".join(parts)
            + f"; exact loss {excess:+.2g}"
            + (f"; {fails} inner BVP solve(s) failed" if fails else "")
        )

    # ------------------------------------------------------------------ 2. accuracy
    readings = {k: P.paper_readings(rod, k, per_count, noise=args.noise, seed=args.seed + k) for k in (1, 2, 3)}
    study = P.accuracy_study(rod, readings, auto, nodes=acc_nodes, threshold_nodes=acc_nodes[-1], progress=progress)
    qp = acc_nodes[-1]
    print()
    print(
        f"## Accuracy: {per_count} readings per count, forces {P.FORCE_RANGE[0]}-{P.FORCE_RANGE[1]} N spread "
        f"along the rod, noise {args.noise:g} 1/m, location bias {1e3 * rod.location_bias:+.2f} mm "
        "(simulated readings; the paper's: its bench)"
    )
    print(
        f"{'method':<24} {'forces':>6} {'count ok':>8} | {'F RMSE [N]':>10} {'paper':>6} | "
        f"{'s RMSE [mm]':>11} {'paper':>6} | {'median [s]':>10}"
    )
    labels = ["torchrod", "torchrod known", f"nodes q={qp}", f"nodes q={qp} threshold"]
    for label in labels:
        for k in readings:
            a = study.accuracy(label, k)
            name = {
                "torchrod": "torchrod (auto count)",
                "torchrod known": "torchrod (count given)",
                f"nodes q={qp}": f"paper q={qp} (count given)",
                f"nodes q={qp} threshold": f"paper q={qp} (threshold)",
            }[label]
            print(
                f"{name:<24} {k:>6} {a.count_correct:>5}/{a.readings:<2} | {a.force_rmse:>10.4f} "
                f"{P.PAPER_FORCE_RMSE[k]:>6.3f} | {1e3 * a.location_rmse:>11.2f} "
                f"{1e3 * P.PAPER_LOCATION_RMSE[k]:>6.2f} | {study.runs[label][k].median_wall:>10.4f}"
            )

    # ------------------------------------------------------------------ 3. against q, and 1/2/3 forces
    print()
    print("## Against q: the paper's method (count given); force RMSE [N] / location RMSE [mm] / median time [s]")
    print(f"{'q':>5} | " + " | ".join(f"{k} force(s)".center(26) for k in readings))
    for q in acc_nodes:
        cells = []
        for k in readings:
            a = study.accuracy(f"nodes q={q}", k)
            cells.append(
                f"{a.force_rmse:>8.4f} {1e3 * a.location_rmse:>7.2f} {study.runs[f'nodes q={q}'][k].median_wall:>9.4f}"
            )
        print(f"{q:>5} | " + " | ".join(cells))
    cells = []
    for k in readings:
        a = study.accuracy("torchrod", k)
        cells.append(
            f"{a.force_rmse:>8.4f} {1e3 * a.location_rmse:>7.2f} {study.runs['torchrod'][k].median_wall:>9.4f}"
        )
    print(f"{'exact':>5} | " + " | ".join(cells) + "   (torchrod default, count automatic)")
    print()
    print("## Time per estimate [s] for 1, 2, 3 forces (median, one reading per call)")
    print(f"{'method':<30} " + " ".join(f"{k} force(s)".rjust(11) for k in readings))
    for q in (90, 250):
        if q in P.PAPER_TIMES:
            print(f"{f'paper, q={q} (MATLAB)':<30} " + " ".join(f"{P.PAPER_TIMES[q][k]:>11.3f}" for k in readings))
        if f"nodes q={q}" in study.runs:
            print(
                f"{f'paper method here, q={q}':<30} "
                + " ".join(f"{study.runs[f'nodes q={q}'][k].median_wall:>11.4f}" for k in readings)
            )
    print(
        f"{'torchrod (auto count)':<30} "
        + " ".join(f"{study.runs['torchrod'][k].median_wall:>11.4f}" for k in readings)
    )
    print(
        f"{'torchrod (count given)':<30} "
        + " ".join(f"{study.runs['torchrod known'][k].median_wall:>11.4f}" for k in readings)
    )

    # ------------------------------------------------------------------ 4. loss maps
    print()
    progress("loss maps")
    L = rod.length
    maps = P.loss_maps(
        rod.with_(location_bias=0.0), size=map_size, true=(0.2 * L / 0.29, 0.3, 0.0), s_range=(0.1 * L / 0.29, L)
    )
    print(
        f"## Loss maps: one force at {1e3 * maps.true[0]:.0f} mm, {maps.true[1]:.2f} N; grid "
        f"{len(maps.s)} locations x {len(maps.magnitude)} magnitudes (one batched forward call)"
    )
    for which in ("curvature", "shape"):
        s_min, f_min = maps.minimum(which)
        print(f"  {which} loss: minimum at {1e3 * s_min:.1f} mm, {f_min:.3f} N")

    # ------------------------------------------------------------------ figures
    if not args.no_figures:
        from ...eval import plots

        written = [
            plots.save(plots.speed_figure(table, P.PAPER_TABLE_II), os.path.join(args.out, "paper_table2.png")),
            plots.save(
                plots.versus_q_figure(study, P.PAPER_FORCE_RMSE, P.PAPER_LOCATION_RMSE, P.PAPER_TIMES),
                os.path.join(args.out, "paper_vs_q.png"),
            ),
            plots.save(plots.loss_maps_figure(maps), os.path.join(args.out, "paper_loss_maps.png")),
        ]
        print()
        print("figures: " + ", ".join(written))
    print(f"# total {time.perf_counter() - t_start:.0f} s")
    return 0
