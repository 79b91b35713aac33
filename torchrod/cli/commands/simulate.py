"""``torchrod simulate``: FBG curvature readings for given point forces (JSON lines in, JSON lines out).

Usage: ``torchrod simulate --rod ROD FORCES.jsonl`` (``-`` reads standard input). ROD is a rod JSON file
(see torchrod.Rod.from_json) or a preset name (the presets are listed under --rod).

Each input line is a load case::

    {"id": "c1", "forces": [{"s": 0.12, "fx": 0.3, "fy": -0.1}, ...]}

with ``s`` the force location [m] from the clamped base and ``fx``, ``fy`` its body-frame components [N] (standard
Cosserat sign, docs/physics.md: a small ``fy > 0`` at s_i gives u_x = -fy (s_i - s)/EI proximal to it). ``forces`` may
be empty (a straight rod); ``id`` is optional (any JSON value, echoed back); other top-level keys are ignored. A rod
with a location bias (a calibrated rod, paper: s_est = s_model + s_bias) takes ``s`` in the same coordinate its
estimates are reported in, and simulates at s_model = s - location_bias, which must lie in [0, L].

Each output line answers the input line in the same position::

    {"id": "c1", "curvature": [[ux, uy], ...], "gratings": [s_1, ...]}

``curvature`` [1/m] holds one pair per grating in the rod file's order, ``gratings`` their positions [m].
``--samples N`` adds ``"profile": {"s": [...], "curvature": [[ux, uy], ...]}`` at N uniform positions over [0, L].
``--tip-angle`` adds ``"tip_angle"``, the angle between the base and tip tangents [rad], from the frames (4th-order
Magnus over 128 intervals: within 1e-5 rad); it samples the curvature at 256 more points, which costs several times
the gratings alone. For a precurved rod, which twists, the angle comes from its shape (2001 samples, twist included).

A line that cannot be used (bad JSON, a missing or unknown key, a non-numeric, NaN or infinite value, a location off
the rod) gives ``{"id": ... or null, "error": "line N: ..."}`` and the other lines go on; so does a case whose forces
are so large that the simulation cannot keep its error bound (1e-6 of the largest curvature; torchrod.simulate's
``accurate``) or gives values that are not finite. The exit status is 1 if any line failed, else 0 (2 for a bad rod
file or option, 141 when the reader of the output goes away).

``--noise SIGMA`` adds Gaussian noise of standard deviation SIGMA [1/m] to every component of ``curvature`` (the
readings an interrogator would give; ``profile`` and ``tip_angle`` stay exact), drawn line by line in input order
from a generator seeded with ``--seed N`` (the same seed gives the same noise whatever ``--batch-size``; without
``--seed`` every run draws afresh).

Lines are simulated in batches of ``--batch-size`` (one batched, padded call per batch), answers in input order.
``--out FILE`` writes the answers to FILE instead of standard output.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from typing import Any, Literal

import torch

from ...io.jsonl import (
    LineWriter,
    Record,
    batched,
    check_input,
    check_keys,
    check_output,
    get_list,
    get_number,
    open_output,
    read_records,
)
from ...loads import PointForces
from ...model.body_frame import ACCURACY, MAX_STEPS, simulate
from ...model.shape import bending_angle, shape
from ...presets import load as load_rod
from ...rod import Rod
from . import add_device_option, check_device, rod_help

HELP = "curvature at the gratings for given point forces (JSON lines in, JSON lines out)"

__all__ = ["HELP", "configure", "parse_case", "run", "simulate_cases", "tip_angle"]

TIP_INTERVALS = 128
"""Intervals of the Magnus integration of the frames behind ``tip_angle`` (measured error <= 1e-5 rad at
bending up to 180 degrees on the paper's tube)."""

PRECURVED_TIP_SAMPLES = 2001
"""Samples of the shape (:func:`torchrod.model.shape.shape`, second order, twist included) behind a precurved
rod's ``tip_angle`` (tests/test_precurved.py holds it to the global-frame shooting's frames)."""

Force = tuple[float, float, float]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join(__doc__.split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("forces", metavar="FORCES.jsonl", help="load cases, one JSON object a line; '-' for stdin")
    parser.add_argument("--rod", required=True, help=rod_help())
    parser.add_argument(
        "--samples", type=int, default=0, metavar="N", help="also output the curvature profile at N positions"
    )
    parser.add_argument(
        "--scheme",
        choices=("exact", "nodes"),
        default="exact",
        help="'exact' point loads (default) or the paper's node spreading",
    )
    parser.add_argument("--tip-angle", action="store_true", help="also output the tip's bending angle [rad] (slower)")
    parser.add_argument("--nodes", type=int, default=250, metavar="Q", help="node count q for --scheme nodes")
    parser.add_argument(
        "--batch-size",
        type=int,
        default=256,
        metavar="B",
        help="lines simulated per batched call (default 256)",
    )
    add_device_option(parser, "torch device the forward model runs on: cpu (default), cuda, cuda:1, ...")
    parser.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="Gaussian noise sigma [1/m] added to each curvature component (default 0: exact)",
    )
    parser.add_argument("--seed", type=int, metavar="N", help="seed of --noise (default: a fresh draw each run)")
    parser.add_argument("--out", metavar="FILE", help="write the answers to FILE (default: standard output)")


def parse_case(obj: dict[str, Any], rod: Rod) -> list[Force]:
    """One input object -> its forces as (s_model [m], fx [N], fy [N]); ``ValueError`` names the bad field."""
    forces = get_list(obj, "forces")
    lo, hi = rod.location_bias, rod.length + rod.location_bias
    out = []
    for k, force in enumerate(forces):
        where = f"forces[{k}]"
        check_keys(force, required=("s", "fx", "fy"), where=where)
        s = get_number(force, "s", where)
        if not lo <= s <= hi:
            raise ValueError(f"{where}.s = {s} m lies off the rod: it must lie in [{lo:g}, {hi:g}] m")
        # Clamp the rounding of s - bias at the ends back onto the rod.
        s_model = min(max(s - rod.location_bias, 0.0), rod.length)
        out.append((s_model, get_number(force, "fx", where), get_number(force, "fy", where)))
    return out


def simulate_cases(
    rod: Rod,
    cases: Sequence[Sequence[Force]],
    *,
    samples: int = 0,
    with_tip_angle: bool = False,
    scheme: Literal["exact", "nodes"] = "exact",
    nodes: int = 250,
    device: torch.device | str | None = None,
) -> list[dict[str, Any]]:
    """Simulate load cases in one batched call; one output dict per case (without its id).

    Args:
        cases: per case, its forces (s [m] in [0, L], fx [N], fy [N]).
        samples: profile points over [0, L] (0: no profile).
        with_tip_angle: also the angle between base and tip tangents.
        scheme, nodes, device: as :func:`torchrod.simulate` (the loads are float64 on ``device``).
    Returns:
        dicts with ``curvature`` (G x [ux, uy]) [1/m] and ``gratings`` [m], plus ``tip_angle`` [rad] and ``profile``
        when asked for. A case whose result is not finite gets ``{"error": ...}`` instead.
    """
    dtype = torch.float64
    loads = PointForces.from_lists(cases, dtype=dtype, device=device)
    L = rod.length
    # A precurved rod twists (u_z), which the Magnus step below leaves out: its angle comes from the shape instead.
    magnus = with_tip_angle and not rod.precurved
    gauss = _gauss_points(L, TIP_INTERVALS if magnus else 0, dtype, loads.device)
    profile_s = torch.linspace(0.0, L, samples, dtype=dtype, device=loads.device)
    import warnings

    import numpy as np

    # Loads far beyond the rod's range overflow on the way (NumPy would print a RuntimeWarning with its source line
    # for each): the outcome is judged below, case by case (not finite, or beyond the error bound), and said in
    # torchrod's words (_beyond).
    with torch.no_grad(), np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sim = simulate(rod, loads, at=torch.cat((profile_s, gauss)), scheme=scheme, nodes=nodes, max_steps=MAX_STEPS)
        u_profile = sim.curvature[:, torch.searchsorted(sim.s, profile_s)]
        checks = [sim.grating_curvature.flatten(1), u_profile.flatten(1)]
        if magnus:
            angle = tip_angle(sim.curvature[:, torch.searchsorted(sim.s, gauss)], L / TIP_INTERVALS)
        elif with_tip_angle:
            angle = bending_angle(shape(rod, loads, samples=PRECURVED_TIP_SAMPLES, scheme=scheme, nodes=nodes))
        if with_tip_angle:
            checks.append(angle.unsqueeze(1))
    finite = torch.cat(checks, dim=1).isfinite().all(dim=1).tolist()
    accurate = sim.accurate.tolist()
    gratings = list(rod.gratings)
    curvature = sim.grating_curvature.cpu().tolist()
    angle_list = angle.cpu().tolist() if with_tip_angle else []
    profile = u_profile.cpu().tolist()
    s_list = profile_s.cpu().tolist()
    results: list[dict[str, Any]] = []
    for b, case in enumerate(cases):
        if not (finite[b] and accurate[b]):
            bound = finite[b] and scheme == "exact"  # not accurate, yet finite
            results.append({"error": _beyond(case, bound)})
            continue
        out: dict[str, Any] = {"curvature": curvature[b], "gratings": gratings}
        if with_tip_angle:
            out["tip_angle"] = angle_list[b]
        if samples:
            out["profile"] = {"s": s_list, "curvature": profile[b]}
        results.append(out)
    return results


def _beyond(case: Sequence[Force], bound: bool) -> str:
    """The error of a case the simulation cannot answer: its values are not finite, or (``bound``: the exact
    scheme) not within the simulator's error bound (:data:`torchrod.model.body_frame.ACCURACY`)."""
    largest = max((math.hypot(fx, fy) for _, fx, fy in case), default=0.0)
    if bound:
        return (
            f"the simulation cannot keep its error within {ACCURACY:g} of the largest curvature for these forces "
            f"(largest {largest:.3g} N) in {MAX_STEPS} steps: they lie far beyond the rod's range"
        )
    return f"the simulation gave non-finite values: the forces (largest {largest:.3g} N) are too large"


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    if args.samples < 0:
        raise ValueError(f"--samples must be >= 0, got {args.samples}")
    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.scheme == "nodes" and args.nodes < 2:
        raise ValueError(f"--nodes must be >= 2, got {args.nodes}")
    if not (math.isfinite(args.noise) and args.noise >= 0.0):
        raise ValueError(f"--noise must be a finite sigma >= 0 [1/m], got {args.noise}")
    from ...errors import OptionsError
    from ...io.quantities import MAX_CURVATURE

    if args.noise > MAX_CURVATURE:
        raise OptionsError(
            f"--noise must be at most {MAX_CURVATURE:g} 1/m, the largest curvature a reading may carry (no reader "
            f"takes the readings it would write), got {args.noise:g}"
        )
    if args.seed is not None and args.noise == 0.0:
        raise ValueError("--seed sets the noise of --noise SIGMA; give both")
    check_input(args.forces, "FORCES")
    inputs = {"FORCES": args.forces, "--rod": args.rod}
    check_output(args.out, inputs)
    device = check_device(args)
    options = {
        "samples": args.samples,
        "with_tip_angle": args.tip_angle,
        "scheme": args.scheme,
        "nodes": args.nodes,
        "device": device,
    }
    noise = _Noise(args.noise, args.seed) if args.noise > 0.0 else None
    records = read_records(args.forces, lambda obj: parse_case(obj, rod))
    with open_output(args.out, inputs) as out:
        writer = LineWriter(out)
        try:
            _run(rod, records, writer, args.batch_size, options, noise)
        except BrokenPipeError:  # the reader went away (| head): stop quietly
            return 141
    return 1 if writer.errors else 0


class _Noise:
    """Gaussian noise [1/m] on the written curvature, drawn reading by reading in input order from one seeded
    generator (so the draws do not depend on the batch size)."""

    def __init__(self, sigma: float, seed: int | None) -> None:
        self.sigma = sigma
        self.generator = torch.Generator()
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    def add(self, curvature: list[list[float]]) -> list[list[float]]:
        u = torch.tensor(curvature, dtype=torch.float64)
        return (u + self.sigma * torch.randn(u.shape, generator=self.generator, dtype=u.dtype)).tolist()


def _run(
    rod: Rod,
    records,
    writer: LineWriter,
    batch_size: int,
    options: dict[str, Any],
    noise: _Noise | None = None,
) -> None:
    for chunk in batched(records, batch_size):
        good = [r for r in chunk if r.ok]
        answers = iter(_answer(rod, good, options))
        for record in chunk:
            if not record.ok:
                writer.record_error(record)
                continue
            out = next(answers)
            if "error" in out:
                writer.error(record.id, f"line {record.line}: {out['error']}")
            else:
                if noise is not None:
                    out["curvature"] = noise.add(out["curvature"])
                writer.answer({"id": record.id, **out}, record.line)


def _answer(rod: Rod, good: list[Record[list[Force]]], options: dict[str, Any]) -> list[dict[str, Any]]:
    """Batched results for readable records; if the batch fails as a whole, each case alone (isolates the bad one)."""
    if not good:
        return []
    cases = [r.value or [] for r in good]
    try:
        return simulate_cases(rod, cases, **options)
    except ValueError:
        out = []
        for case in cases:
            try:
                out.extend(simulate_cases(rod, [case], **options))
            except ValueError as exc:
                out.append({"error": str(exc)})
        return out


# ---------------------------------------------------------------------------------------------- frames
def _gauss_points(length: float, intervals: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(2 K,) the two Gauss-Legendre points of each of K equal intervals over [0, L], increasing."""
    if intervals == 0:
        return torch.zeros(0, dtype=dtype, device=device)
    h = length / intervals
    mid = (torch.arange(intervals, dtype=dtype, device=device) + 0.5) * h
    d = h * math.sqrt(3.0) / 6.0
    return torch.stack((mid - d, mid + d), dim=1).reshape(-1).clamp(0.0, length)


def _quaternion_product(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product of (..., 4) quaternions (w, x, y, z): the rotation p then q in the body frame, R_p R_q."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        (
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ),
        dim=-1,
    )


def tip_angle(u_gauss: torch.Tensor, h: float) -> torch.Tensor:
    """Angle between the base and tip tangents [rad], (B,), from the curvature at Gauss points.

    R' = R u^ (body-frame curvature, u_z = 0) is crossed interval by interval with the 4th-order Magnus step
    R_{k+1} = R_k exp(Omega_k^), Omega_k = h/2 (u_1 + u_2) + sqrt(3) h^2 / 12 (u_1 x u_2) (the commutator term is the
    twist non-planar bending brings), u_1, u_2 at the interval's Gauss points. Rotations are unit quaternions,
    exp(Omega^) = (cos(t/2), sin(t/2) Omega / t) with t = |Omega|, multiplied as a balanced tree (log2 K products);
    R(0) = I, so the tip tangent R(L) e3 comes from the product alone.

    Args:
        u_gauss: (B, 2 K, 2) curvature [1/m] at the Gauss points of K equal intervals of length ``h`` [m].
    """
    B = u_gauss.shape[0]
    u = torch.cat((u_gauss, torch.zeros_like(u_gauss[..., :1])), dim=-1).reshape(B, -1, 2, 3)
    u1, u2 = u[:, :, 0], u[:, :, 1]
    omega = 0.5 * h * (u1 + u2) + (math.sqrt(3.0) / 12.0) * h * h * torch.linalg.cross(u1, u2, dim=-1)
    half = 0.5 * torch.linalg.vector_norm(omega, dim=-1, keepdim=True)
    # sin(t/2) / t = sinc(t / (2 pi)) / 2: exact at t = 0.
    q = torch.cat((torch.cos(half), 0.5 * torch.sinc(half / math.pi) * omega), dim=-1)  # (B, K, 4)
    identity = q.new_tensor([1.0, 0.0, 0.0, 0.0])
    while q.shape[1] > 1:
        if q.shape[1] % 2:
            q = torch.cat((q, identity.expand(B, 1, 4)), dim=1)
        q = _quaternion_product(q[:, 0::2], q[:, 1::2])
    w, x, y, z = q[:, 0].unbind(-1)
    tx, ty, tz = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)
    return torch.atan2(torch.hypot(tx, ty), tz)
