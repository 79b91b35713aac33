"""``torchrod bench forward``: speed and accuracy of the forward model (the measurement model of estimation).

Speed: :func:`torchrod.grating_curvature` on the paper's tube, per reading, for the exact scheme (default settings)
and the paper's node scheme at q = 90 and 250, at batch sizes 1, 64 and 4096; forward alone (no autograd) and
forward + backward (the gradient of a squared-curvature loss with respect to every force's location and
components, what an estimator's line search needs). Each time is the best over a few repeats of the mean over
enough calls to last a while, wall clock (the column ``cpu`` is the process CPU time of forward + backward, which a
busy machine inflates less); all configurations run side by side in one process.

Accuracy: the same schemes on the first cases of the same set, against an independent converged reference
(scipy's DOP853 at rtol 1e-12 on the full body-frame system u' = (n_y, -n_x)/EI, n' = -u x n, with exact jumps at
the forces: no m_z reduction, no Runge-Kutta-Nystrom), as max |error| / max |u| over a case's gratings.

Cases: 1 to 3 forces (padded to 3) of 0.3 to 2 N in any body-frame direction, anywhere on [0.02 m, L], drawn with a
seeded generator and kept when the rod's tangent turns by at least 90 degrees from the base somewhere along it.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ... import presets
from ...loads import PointForces
from ...model.body_frame import grating_curvature, step_counts
from ...rod import Rod
from . import SUITES

HELP = SUITES["forward"]

__all__ = [
    "HELP",
    "SCHEMES",
    "configure",
    "large_deflection_cases",
    "reference_curvature",
    "run",
    "time_call",
]

SCHEMES: tuple[tuple[str, dict], ...] = (
    ("exact", {}),
    ("nodes q=90", {"scheme": "nodes", "nodes": 90}),
    ("nodes q=250", {"scheme": "nodes", "nodes": 250}),
)
"""The schemes compared: name and :func:`torchrod.grating_curvature` options."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a smoke run: B = 1 and 16, 3 accuracy cases, 1 repeat")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", metavar="B", help="default: 1 64 4096")
    parser.add_argument("--cases", type=int, help="accuracy cases (default 24)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the load cases (default 0)")


# ------------------------------------------------------------------------------------------------- cases
def large_deflection_cases(
    rod: Rod,
    count: int,
    *,
    generator: torch.Generator,
    max_forces: int = 3,
    force_range: tuple[float, float] = (0.3, 2.0),
    min_turn_degrees: float = 90.0,
    dtype: torch.dtype = torch.float64,
) -> PointForces:
    """``count`` load cases (module docstring), padded to ``max_forces`` (padding: s = 0, f = 0, mask False).

    The turn is the largest angle between the base tangent and the tangent anywhere on the rod, from
    :func:`torchrod.model.shape.shape` on 65 samples (a filter: its error of a fraction of a degree does not matter).
    """
    from ...model.shape import shape

    lo, hi = force_range
    kept_s, kept_f, kept_m = [], [], []
    total = 0
    while total < count:
        n = 2 * (count - total) + 8
        h = torch.randint(1, max_forces + 1, (n, 1), generator=generator)
        mask = torch.arange(max_forces) < h
        s = 0.02 + (rod.length - 0.02) * torch.rand(n, max_forces, generator=generator, dtype=dtype)
        mag = lo + (hi - lo) * torch.rand(n, max_forces, generator=generator, dtype=dtype)
        ang = 2 * math.pi * torch.rand(n, max_forces, generator=generator, dtype=dtype)
        f = torch.stack((mag * ang.cos(), mag * ang.sin()), dim=-1)
        s, f = s * mask, f * mask.unsqueeze(-1)
        with torch.no_grad():
            frames = shape(rod, PointForces(s, f, mask), samples=65).frames
        t = frames[..., :, 2]  # (n, S, 3) tangents
        cos = (t[:, :1] * t).sum(-1).clamp(-1.0, 1.0)
        keep = torch.acos(cos).amax(dim=1) >= math.radians(min_turn_degrees)
        kept_s.append(s[keep])
        kept_f.append(f[keep])
        kept_m.append(mask[keep])
        total += int(keep.sum())
    return PointForces(torch.cat(kept_s)[:count], torch.cat(kept_f)[:count], torch.cat(kept_m)[:count])


def reference_curvature(rod: Rod, forces: Sequence[tuple[float, float, float]], rtol: float = 1e-12) -> np.ndarray:
    """(G, 2) curvature at the gratings [1/m] of one load case ((s [m], f_x [N], f_y [N]) forces), by scipy's
    DOP853 on the full body-frame system (module docstring), tip to base, event by event."""
    from scipy.integrate import solve_ivp

    ei = rod.bending_stiffness

    def rhs(_s: float, y: np.ndarray) -> np.ndarray:
        ux, uy, nx, ny, nz = y
        return np.array([ny / ei, -nx / ei, -uy * nz, ux * nz, -(ux * ny - uy * nx)])  # n' = -u x n

    at_force: dict[float, np.ndarray] = {}
    for s, fx, fy in forces:
        at_force[float(s)] = at_force.get(float(s), np.zeros(2)) + (fx, fy)
    events = sorted({rod.length, *rod.gratings, *at_force}, reverse=True)
    y, here = np.zeros(5), rod.length
    curvature: dict[float, np.ndarray] = {}
    for p in events:
        if p < here:
            sol = solve_ivp(rhs, (here, p), y, method="DOP853", rtol=rtol, atol=1e-14)
            if not sol.success:
                raise RuntimeError(sol.message)
            y, here = sol.y[:, -1].copy(), p
        if p in at_force:
            y[2:4] += at_force[p]  # n(s_i^-) = n(s_i^+) + f_i
        curvature[p] = y[:2].copy()
    return np.array([curvature[g] for g in rod.gratings])


# ------------------------------------------------------------------------------------------------- timing
def time_call(fn: Callable[[], object], *, min_time: float, repeats: int) -> tuple[float, float]:
    """(wall, cpu) seconds per call of ``fn``: the best over ``repeats`` of the mean over enough calls to last
    ``min_time`` (after one warm-up call)."""
    start = time.perf_counter()
    fn()
    calls = max(1, math.ceil(min_time / max(time.perf_counter() - start, 1e-9)))
    wall = cpu = math.inf
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        for _ in range(calls):
            fn()
        wall = min(wall, (time.perf_counter() - w) / calls)
        cpu = min(cpu, (time.process_time() - c) / calls)
    return wall, cpu


def _speed(rod: Rod, loads: PointForces, options: dict, min_time: float, repeats: int) -> dict[str, float]:
    B = loads.batch_size

    def forward() -> None:
        with torch.no_grad():
            grating_curvature(rod, loads, **options)

    s = loads.s.detach().clone().requires_grad_(True)
    f = loads.f.detach().clone().requires_grad_(True)
    leaf = PointForces(s, f, loads.mask)

    def forward_backward() -> None:
        grating_curvature(rod, leaf, **options).square().sum().backward()

    fwd, _ = time_call(forward, min_time=min_time, repeats=repeats)
    both, both_cpu = time_call(forward_backward, min_time=min_time, repeats=repeats)
    if options.get("scheme", "exact") == "exact":
        steps = int(step_counts(rod, loads).sum(1).max())
    else:
        steps = options["nodes"] + rod.num_gratings  # one step per node interval and per grating split
    return {"fwd": fwd / B, "fwd_bwd": both / B, "fwd_bwd_cpu": both_cpu / B, "steps": steps}


def _microseconds(x: float) -> str:
    return f"{x * 1e6:10.1f}"


# ------------------------------------------------------------------------------------------------- the suite
def run(args: argparse.Namespace) -> int:
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    sizes = args.batch_sizes or ([1, 16] if args.quick else [1, 64, 4096])
    if min(sizes) < 1:
        raise ValueError(f"batch sizes must be >= 1, got {sizes}")
    cases = args.cases if args.cases is not None else (3 if args.quick else 24)
    if cases < 1:
        raise ValueError(f"--cases must be >= 1, got {cases}")
    min_time, repeats = (0.02, 1) if args.quick else (0.25, 3)
    rod = presets.nitinol290()
    previous = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        loads = large_deflection_cases(rod, max(max(sizes), cases), generator=torch.Generator().manual_seed(args.seed))
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        print(
            f"torchrod bench forward: nitinol290 (L = {rod.length} m, {rod.num_gratings} gratings), float64, CPU, "
            f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, load average {load:.1f}"
        )
        print(
            f"cases: {loads.batch_size} load cases, 1-3 forces (padded to 3) of 0.3-2 N anywhere on [0.02, L], "
            f"tangent turning >= 90 deg (seed {args.seed})"
        )
        print()
        header = (
            f"{'scheme':12s} {'B':>5s} {'fwd':>10s} {'fwd+bwd':>10s} {'cpu':>10s} "
            f"{'fwd':>10s} {'fwd+bwd':>10s} {'steps':>6s}"
        )
        print(f"{'':18s} {'time per reading [us]':^32s} {'readings/s':^21s}")
        print(header)
        for name, options in SCHEMES:
            for B in sizes:
                r = _speed(rod, loads[:B], options, min_time, repeats)
                print(
                    f"{name:12s} {B:5d} {_microseconds(r['fwd'])} {_microseconds(r['fwd_bwd'])} "
                    f"{_microseconds(r['fwd_bwd_cpu'])} {1 / r['fwd']:10.0f} {1 / r['fwd_bwd']:10.0f} {r['steps']:6d}"
                )
        print(
            "steps: Runge-Kutta-Nystrom steps each sample runs (exact: the batch's largest need, 8 stages per step; "
            "nodes: one per node interval and grating, 3 stages per step)"
        )
        print()
        acc = loads[:cases]
        refs = [reference_curvature(rod, forces) for forces in acc.to_lists()]
        print(f"accuracy at the gratings vs a converged reference (DOP853, rtol 1e-12), {cases} of the cases:")
        print(f"{'scheme':12s} {'max rel. error':>15s} {'median':>10s}   (max |u - u_ref| / max |u_ref| per case)")
        for name, options in SCHEMES:
            with torch.no_grad():
                got = grating_curvature(rod, acc, **options).numpy()
            errors = [float(np.abs(g - r).max() / np.abs(r).max()) for g, r in zip(got, refs, strict=False)]
            print(f"{name:12s} {max(errors):15.2e} {float(np.median(errors)):10.2e}")
    finally:
        torch.set_num_threads(previous)
    return 0
