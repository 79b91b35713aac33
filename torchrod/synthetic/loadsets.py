"""Synthetic load sets: load cases, their FBG readings, and the training sets' file format.

Load cases (:class:`LoadSampler`, :func:`sample_loads`)
    The number of forces k is drawn first, uniformly in ``[min_forces, max_forces]``. Given k, the locations are
    uniform over all configurations in ``s_range`` whose neighbours lie at least ``min_separation`` apart (drawn
    exactly, without rejection: k sorted uniforms in a range shortened by ``(k - 1) * min_separation``, the j-th
    shifted by ``j * min_separation``). Magnitudes are uniform in ``force_range`` [N], directions uniform in the
    body-frame (f_x, f_y) plane.

    Bending limit: a case is rejected when its total turning angle ``int_0^L |u(s)| ds`` exceeds ``max_bending``.
    The total turning bounds the angle between the base and tip tangents from above, and equals it for planar
    loads. It is computed from the forward model (the body-frame IVP of :mod:`torchrod.model.body_frame`) sampled at
    129 uniform positions and integrated by the trapezoid rule; |u| has kinks at the forces, so the quadrature error
    is of order (L/128)^2 |f|/EI / 8, about 2e-4 rad at the paper's rod and 2 N (a test checks it against a fine
    grid). A rejected case is redrawn with the same k (only the rejected rows are redrawn, vectorised), so the
    counts keep their uniform distribution and, given k, the cases are uniform over the admissible set. So is a
    case the forward model's fixed steps do not resolve (values not finite, or on a straight rod a step longer than
    the simulator's step rule allows: forces far beyond the rod's range, possible without a bending limit); a
    trajectory frame, or a case moved by a location bias, that it does not resolve is refused (ValueError).

Patches of load (:func:`sample_patches`)
    A contact spread over a length rather than at a point: many equal point forces side by side, to hold the
    estimator's point-force model against.

Sensor effects (:class:`SensorModel`)
    ``clean`` is the noise-free reading: the forward model's curvature at the gratings, for the forces moved to
    ``s - location_bias`` (clamped to [0, L]) when a location bias is simulated (the meaning of
    :attr:`torchrod.rod.Rod.location_bias`: reported = model + bias). The reading is
    ``curvature = clean + offsets + noise * N(0, 1)``; ``offsets`` (G, 2) are drawn once per set
    (``offset_std * N(0, 1)``) and stored; each grating is missing independently with ``missing_prob`` (mask
    False, curvature 0.0). The loads are independent of the sensor model: one seed gives the same loads and clean
    readings whatever the noise.

Reproducibility (:func:`generate`)
    All randomness comes from ``torch.Generator`` objects seeded from ``seed``: the cases are split into chunks of
    :data:`CHUNK` rows, and chunk c draws its loads and its sensor noise from generators seeded with a hash of
    ``(seed, c)``. The per-case forward model uses a fixed number of steps per segment, so a case's result does not
    depend on the other cases in its batch. One seed gives the same arrays whatever ``batch_size`` and device
    (bitwise for the draws, the loads and the masks; curvature equal to rounding in the last bits).

File format (``.npz``, ``format_version`` 1)
    Written with numpy (:meth:`SyntheticSet.save`, ``numpy.savez_compressed``), read with ``allow_pickle=False``.
    Arrays, with N cases, h = ``max_forces``, G gratings:

    ============== ============ ======= =============================================================
    name           shape        dtype   meaning
    ============== ============ ======= =============================================================
    ``s``          (N, h)       float64 force locations [m], sorted, padding last (0.0)
    ``f``          (N, h, 2)    float64 body-frame (f_x, f_y) [N], 0.0 for padding
    ``force_mask`` (N, h)       bool    True for a real force
    ``count``      (N,)         int64   number of real forces
    ``clean``      (N, G, 2)    float64 noise-free curvature at the gratings [1/m]
    ``curvature``  (N, G, 2)    float64 noisy curvature [1/m], 0.0 where missing
    ``mask``       (N, G)       bool    True where the grating has a reading
    ``offsets``    (G, 2)       float64 the set's constant per-grating offsets [1/m]
    ``meta``       ()           unicode JSON: see below
    ============== ============ ======= =============================================================

    ``meta`` holds ``{"format": "torchrod-dataset", "format_version": 1, "torchrod_version", "rod":
    Rod.to_dict(), "sampler", "sensor" (the dataclasses' fields), "seed", "count", "candidates" (cases examined,
    for the rejection rate), "sha256"}``. The hash runs over the arrays in name order, each as its name, its dtype
    string, its shape and its C-order bytes. :meth:`SyntheticSet.load` raises ``ValueError`` for a file that is not
    a torchrod set, a newer format version, unreadable, missing or altered arrays (hash), inconsistent shapes or
    dtypes, and a rod whose length, stiffness or gratings differ from the one given.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from ..errors import OptionsError, TorchrodTypeError
from ..loads import PointForces
from ..model.body_frame import DEFAULT_STEP_ANGLE, integrate_curvature
from ..rod import Rod

__all__ = [
    "CHUNK",
    "FORMAT",
    "FORMAT_VERSION",
    "LoadSampler",
    "SensorModel",
    "SyntheticDataset",
    "SyntheticSet",
    "PATCH_PARTS",
    "generate",
    "sample_loads",
    "sample_patches",
    "total_turning",
    "turning_and_peak",
]

FORMAT = "torchrod-dataset"
FORMAT_VERSION = 1
CHUNK = 256
"""Rows per seed chunk: generation batches hold whole chunks, so ``batch_size`` is rounded up to a multiple."""

PROFILE_SAMPLES = 129
"""Uniform positions on [0, L] where |u| is sampled for the total turning angle (trapezoid rule)."""
_STEPS = 1  # fixed Runge-Kutta-Nystrom steps per segment (segments <= L/128): grating curvature within ~4e-7 1/m
_COARSE_SAMPLES = 17  # first pass: prune candidates far beyond the bending limit
_COARSE_MARGIN = 0.1  # [rad], five times the coarse pass's largest error seen near the limit
_MAX_ROUNDS = 24  # redraw rounds before giving up on a case
_REPEATS = (1, 1, 2, 2, 4, 4, 8, 8, 16, 16, 32, 32, 64)  # candidates per pending case, by round

_ARRAYS = ("s", "f", "force_mask", "count", "clean", "curvature", "mask", "offsets")


# ---------------------------------------------------------------------------------------------------- options
def _finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise OptionsError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise OptionsError(f"{name} must be finite, got {value!r}")
    return v


def _pair(name: str, value: Any) -> tuple[float, float]:
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise OptionsError(f"{name} must be a pair (low, high), got {value!r}") from None
    lo, hi = _finite(f"{name}[0]", lo), _finite(f"{name}[1]", hi)
    if hi < lo:
        raise OptionsError(f"{name} must have low <= high, got {value!r}")
    return lo, hi


def _int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TorchrodTypeError(f"{name} must be an integer, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class LoadSampler:
    """How random load cases are drawn (see the module docstring).

    Attributes:
        min_forces, max_forces: the number of forces per case, uniform in [min_forces, max_forces] (>= 1).
        force_range: (low, high) magnitude [N], uniform; the direction is uniform in the (f_x, f_y) plane.
        min_separation: least distance between two forces of a case [m].
        s_range: (low, high) locations [m]; ``None`` means (0.02 L, L).
        max_bending: limit on the total turning angle int_0^L |u| ds [rad]; cases beyond are redrawn
            (``math.inf``: no limit).
    """

    min_forces: int = 1
    max_forces: int = 3
    force_range: tuple[float, float] = (0.05, 2.0)
    min_separation: float = 0.025
    s_range: tuple[float, float] | None = None
    max_bending: float = math.pi / 2

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        lo, hi = _int("min_forces", self.min_forces), _int("max_forces", self.max_forces)
        if lo < 1 or hi < lo:
            raise OptionsError(f"need 1 <= min_forces <= max_forces, got min_forces={lo}, max_forces={hi}")
        set_(self, "min_forces", lo)
        set_(self, "max_forces", hi)
        f_lo, f_hi = _pair("force_range", self.force_range)
        if f_lo < 0.0:
            raise OptionsError(f"force_range must be non-negative, got {self.force_range!r}")
        set_(self, "force_range", (f_lo, f_hi))
        sep = _finite("min_separation", self.min_separation)
        if sep < 0.0:
            raise OptionsError(f"min_separation must be >= 0, got {self.min_separation!r}")
        set_(self, "min_separation", sep)
        if self.s_range is not None:
            s_lo, s_hi = _pair("s_range", self.s_range)
            if s_lo < 0.0:
                raise OptionsError(f"s_range must be non-negative, got {self.s_range!r}")
            if s_hi - s_lo < (hi - 1) * sep:
                raise OptionsError(
                    f"s_range {self.s_range!r} is too short for {hi} forces {sep} m apart (needs {(hi - 1) * sep} m)"
                )
            set_(self, "s_range", (s_lo, s_hi))
        mb = float(self.max_bending)
        if not mb > 0.0:
            raise OptionsError(f"max_bending must be positive (rad), got {self.max_bending!r}")
        set_(self, "max_bending", mb)

    def location_range(self, rod: Rod) -> tuple[float, float]:
        """The (low, high) location range [m] on ``rod``, checked against its length and the separation."""
        lo, hi = (0.02 * rod.length, rod.length) if self.s_range is None else self.s_range
        if hi > rod.length:
            raise OptionsError(f"s_range {self.s_range!r} reaches beyond the rod's length {rod.length} m")
        if hi - lo < (self.max_forces - 1) * self.min_separation:
            raise OptionsError(
                f"location range ({lo}, {hi}) m is too short for {self.max_forces} forces {self.min_separation} m apart"
            )
        return lo, hi

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["force_range"] = list(self.force_range)
        d["s_range"] = None if self.s_range is None else list(self.s_range)
        d["max_bending"] = self.max_bending if math.isfinite(self.max_bending) else None
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LoadSampler:
        data = dict(data)
        if data.get("max_bending", 0.0) is None:
            data["max_bending"] = math.inf
        for key in ("force_range", "s_range"):
            if data.get(key) is not None:
                data[key] = tuple(data[key])
        return cls(**data)


@dataclass(frozen=True)
class SensorModel:
    """Sensor effects applied to the clean curvature (see the module docstring).

    Attributes:
        noise: Gaussian sigma of each component [1/m], independent per grating and reading.
        offset_std: sigma of constant per-grating offsets [1/m], drawn once per set and stored.
        missing_prob: probability that a grating has no reading, independently per grating and reading.
        location_bias: [m], with the meaning of :attr:`torchrod.rod.Rod.location_bias` (reported location =
            model location + bias): readings are simulated with the forces at ``s - location_bias`` (clamped to
            [0, L]), what a fibre registered at the wrong place sees, so an estimator whose rod carries the same
            bias reports the true ``s``. The stored loads stay at ``s``.
    """

    noise: float = 0.1
    offset_std: float = 0.0
    missing_prob: float = 0.0
    location_bias: float = 0.0

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name in ("noise", "offset_std"):
            v = _finite(name, getattr(self, name))
            if v < 0.0:
                raise OptionsError(f"{name} must be >= 0, got {getattr(self, name)!r}")
            set_(self, name, v)
        p = _finite("missing_prob", self.missing_prob)
        if not 0.0 <= p < 1.0:
            raise OptionsError(f"missing_prob must lie in [0, 1), got {self.missing_prob!r}")
        set_(self, "missing_prob", p)
        set_(self, "location_bias", _finite("location_bias", self.location_bias))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SensorModel:
        return cls(**data)


# ---------------------------------------------------------------------------------------------------- physics
def _profile(rod: Rod, loads: PointForces) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Grating curvature (B, G, 2) [1/m], total turning angle (B,) [rad] with a fixed step count, and (B,) bool
    whether these are resolved: finite, and (a straight rod) the fixed steps within the simulator's step rule
    (:func:`_within_step_rule`; far beyond it the march diverges).

    The fixed step count (``_STEPS`` per segment, segments no longer than L/128) makes each case's result
    independent of the rest of the batch; the adaptive default would take its steps from the batch's worst case.
    """
    dtype, device = loads.dtype, loads.device
    grat = rod.grating_positions(dtype, device)
    grid = torch.linspace(0.0, rod.length, PROFILE_SAMPLES, dtype=dtype, device=device)
    G = grat.shape[0]
    if rod.precurved:
        # The turning the load causes, int |u - u*| ds (a precurved rod's own shape is not deflection); RK4 steps
        # of at most L/128 (relative error ~1e-7).
        from ..model.precurved import Precurved, intrinsic, simulate_torch

        with torch.no_grad():
            u3, _ = simulate_torch(rod, loads, torch.cat((grat, grid)), steps=_STEPS)
        shape = intrinsic(Precurved.of(rod), grid.to(torch.float64)).to(dtype)
        curv = u3[..., :2]
        bend = torch.linalg.vector_norm(u3[:, G:] - shape[None], dim=-1)
    else:
        curv, _ = integrate_curvature(torch.cat((grat, grid)), loads, rod.length, rod.bending_stiffness, steps=_STEPS)
        bend = torch.linalg.vector_norm(curv[:, G:], dim=-1)
    turning = torch.trapezoid(bend, dx=rod.length / (PROFILE_SAMPLES - 1))
    resolved = curv.flatten(1).isfinite().all(dim=1) & turning.isfinite()
    if not rod.precurved:
        resolved &= _within_step_rule(rod, loads)
    return curv[:, :G], turning, resolved


def _within_step_rule(rod: Rod, loads: PointForces) -> torch.Tensor:
    """(B,) bool: whether one step per L/128 keeps the simulator's step rule, rate x step <= its default
    :data:`~torchrod.model.body_frame.DEFAULT_STEP_ANGLE`, with the rule's rigorous rate bound
    (:mod:`torchrod.kernels.march`) where it is largest, at the base: max(min(sum |f_i| s_i, sqrt(2 M)), sqrt(M)),
    M = sum |f_i| / EI (every segment of :func:`_profile` is at most L/128 long)."""
    magnitude = torch.linalg.vector_norm(loads.f, dim=-1)
    magnitude = torch.where(loads.active, magnitude, torch.zeros_like(magnitude)) / rod.bending_stiffness
    total = magnitude.sum(dim=1)
    lever = (magnitude * torch.where(loads.active, loads.s, torch.zeros_like(loads.s))).sum(dim=1)
    rate = torch.maximum(torch.minimum(lever, (2.0 * total).sqrt()), total.sqrt())
    return rate * (rod.length / (PROFILE_SAMPLES - 1)) <= DEFAULT_STEP_ANGLE


PROFILE_CHUNK = 4096
"""Cases :func:`_profiles` hands :func:`_profile` at a time: its working memory (the curvature at every sample of
every case) grows with the batch, so a long trajectory is profiled in chunks (the results do not depend on it)."""


def _profiles(rod: Rod, loads: PointForces) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_profile` of any number of cases, :data:`PROFILE_CHUNK` at a time (the same results, in bounded
    working memory)."""
    if loads.batch_size <= PROFILE_CHUNK:
        return _profile(rod, loads)
    parts = [_profile(rod, loads[i : i + PROFILE_CHUNK]) for i in range(0, loads.batch_size, PROFILE_CHUNK)]
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts])


def _check_resolved(resolved: torch.Tensor, loads: PointForces, what: str) -> None:
    """Refuse loads whose readings the fixed-step forward model does not resolve (:func:`_profile`), naming the
    first such ``what`` (a case, a frame) and its largest force."""
    bad = (~resolved).nonzero().flatten()
    if bad.numel():
        k = int(bad[0])
        largest = float(torch.linalg.vector_norm(loads.f[k], dim=-1).masked_fill(~loads.active[k], 0.0).max())
        raise OptionsError(
            f"{bad.numel()} {what}(s), the first {what} {k} with a force of {largest:.3g} N, lie beyond what the "
            "forward model resolves (values not finite, or beyond its step rule or error bound): lower the forces "
            "(force_range), or set max_bending"
        )


def _admissible(rod: Rod, loads: PointForces, limit: float) -> torch.Tensor:
    """(B,) bool: False where a coarse estimate of the total turning (17 samples, one step per segment, error
    below 0.02 rad for cases near the limit) exceeds the limit by more than ``_COARSE_MARGIN``. A cheap first pass:
    the decision on the remaining cases is taken by :func:`_profile`."""
    if not math.isfinite(limit) or rod.precurved:  # (no cheap coarse model of a precurved rod: all go on)
        return torch.ones(loads.batch_size, dtype=torch.bool, device=loads.device)
    grid = torch.linspace(0.0, rod.length, _COARSE_SAMPLES, dtype=loads.dtype, device=loads.device)
    curv, _ = integrate_curvature(grid, loads, rod.length, rod.bending_stiffness, steps=1)
    coarse = torch.trapezoid(torch.linalg.vector_norm(curv, dim=-1), dx=rod.length / (_COARSE_SAMPLES - 1))
    return coarse <= limit + _COARSE_MARGIN


def total_turning(rod: Rod, loads: PointForces, *, samples: int = PROFILE_SAMPLES) -> torch.Tensor:
    """Total turning angle ``int_0^L |u(s)| ds`` [rad], (B,), from :func:`torchrod.simulate` on ``samples``
    uniform positions (trapezoid rule). An upper bound of the base-to-tip tangent angle, exact for planar loads.
    Raises ``ValueError`` for loads the simulation flags (``accurate`` False: far beyond the rod's range)."""
    return turning_and_peak(rod, loads, samples=samples)[0]


def turning_and_peak(
    rod: Rod, loads: PointForces, *, samples: int = PROFILE_SAMPLES
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) the total turning [rad] (:func:`total_turning`) and (B,) the largest |u| [1/m] among the same samples
    (the bending strain's peak over d_out / 2), from one simulation; ``ValueError`` as :func:`total_turning`."""
    from ..model.body_frame import simulate

    if samples < 2:
        raise OptionsError(f"samples must be >= 2, got {samples}")
    sim = simulate(rod, loads, samples=samples)
    _check_resolved(sim.accurate, loads, "case")
    size = sim.curvature_magnitude()
    return torch.trapezoid(size, sim.s, dim=-1), size.amax(dim=-1)


def _shifted(rod: Rod, loads: PointForces, bias: float) -> PointForces:
    """The loads moved to s + bias, clamped to [0, L] (padding stays put)."""
    if bias == 0.0:
        return loads
    s = torch.where(loads.active, (loads.s + bias).clamp(0.0, rod.length), loads.s)
    return PointForces(s, loads.f, loads.mask)


# ---------------------------------------------------------------------------------------------------- sampling
def _derive_seed(seed: int, *parts: Any) -> int:
    """A 63-bit seed for one purpose (and chunk), from the user's seed: a hash, so streams do not overlap."""
    digest = hashlib.sha256(repr((int(seed), *parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def _draw(
    counts: torch.Tensor, sampler: LoadSampler, s_range: tuple[float, float], generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Candidate cases with the given force counts (n,): s (n, h), f (n, h, 2), mask (n, h), float64 on the
    generator's device. Draws a fixed amount per row (whatever its count), so the streams stay aligned."""
    n, h = counts.shape[0], sampler.max_forces
    opts: dict[str, Any] = {"generator": generator, "dtype": torch.float64, "device": generator.device}
    u = torch.rand(n, h, **opts)
    mag = torch.rand(n, h, **opts)
    ang = torch.rand(n, h, **opts)
    counts = counts.to(generator.device)
    col = torch.arange(h, device=generator.device)
    mask = col < counts.unsqueeze(1)
    lo, hi = s_range
    sep = sampler.min_separation
    u = torch.where(mask, u, torch.inf).sort(dim=1).values
    span = (hi - lo) - (counts - 1).to(torch.float64) * sep  # (n,)
    s = torch.where(mask, lo + u * span.unsqueeze(1) + col.to(torch.float64) * sep, 0.0)
    s = s.clamp(max=hi)  # rounding only
    f_lo, f_hi = sampler.force_range
    m = f_lo + (f_hi - f_lo) * mag
    a = 2.0 * math.pi * ang
    f = torch.stack((m * torch.cos(a), m * torch.sin(a)), dim=-1) * mask.unsqueeze(-1)
    return s, f, mask


def _sample_rows(
    rod: Rod,
    sampler: LoadSampler,
    chunks: Sequence[tuple[torch.Generator, int]],
    device: torch.device,
) -> tuple[PointForces, torch.Tensor, int]:
    """Accepted cases for a list of (generator, rows) chunks, evaluated together; each chunk's draws depend only
    on its own generator and its own cases' outcomes.

    Returns the loads (n, h) and their grating curvature (n, G, 2) on ``device``, and the number of candidates
    examined (for each case, its draws up to and including the accepted one).
    """
    s_range = sampler.location_range(rod)
    h = sampler.max_forces
    G = rod.num_gratings
    counts = [
        torch.randint(sampler.min_forces, sampler.max_forces + 1, (n,), generator=g, device=g.device).cpu()
        for g, n in chunks
    ]
    total = sum(n for _, n in chunks)
    out_s = torch.zeros(total, h, dtype=torch.float64, device=device)
    out_f = torch.zeros(total, h, 2, dtype=torch.float64, device=device)
    out_m = torch.zeros(total, h, dtype=torch.bool, device=device)
    out_c = torch.zeros(total, G, 2, dtype=torch.float64, device=device)
    offsets = [0]
    for _, n in chunks:
        offsets.append(offsets[-1] + n)
    pending = [torch.arange(n) for _, n in chunks]  # per chunk, local rows still to fill
    examined = 0
    for round_ in range(_MAX_ROUNDS):
        r = _REPEATS[min(round_, len(_REPEATS) - 1)]
        parts, rows = [], []
        for (g, _), cnt, pend, off in zip(chunks, counts, pending, offsets, strict=False):
            if pend.numel() == 0:
                continue
            parts.append(_draw(cnt[pend].repeat_interleave(r), sampler, s_range, g))
            rows.append(pend + off)
        if not parts:
            break
        s = torch.cat([p[0] for p in parts]).to(device)
        f = torch.cat([p[1] for p in parts]).to(device)
        m = torch.cat([p[2] for p in parts]).to(device)
        ok = _admissible(rod, PointForces(s, f, m), sampler.max_bending)
        keep = ok.nonzero().flatten()
        grating = torch.zeros(s.shape[0], G, 2, dtype=torch.float64, device=device)
        if keep.numel():
            grating_kept, turning, resolved = _profile(rod, PointForces(s[keep], f[keep], m[keep]))
            grating[keep] = grating_kept
            ok[keep] = (turning <= sampler.max_bending) & resolved
        ok = ok.reshape(-1, r)  # (P, r)
        has = ok.any(dim=1)
        first = ok.to(torch.int8).argmax(dim=1)  # first accepted candidate of each pending case
        examined += int(torch.where(has, first + 1, r).sum())
        rows_all = torch.cat(rows).to(device)
        pick = torch.arange(ok.shape[0], device=device) * r + first
        pick, dest = pick[has], rows_all[has]
        out_s[dest], out_f[dest], out_m[dest], out_c[dest] = s[pick], f[pick], m[pick], grating[pick]
        filled = has.cpu()
        start = 0
        for i, pend in enumerate(pending):
            k = pend.numel()
            pending[i] = pend[~filled[start : start + k]]
            start += k
    else:
        left = sum(p.numel() for p in pending)
        raise OptionsError(
            f"{left} load cases still exceed max_bending={sampler.max_bending} rad (or what the forward model "
            f"resolves) after {_MAX_ROUNDS} rounds of redraws: the sampler almost never meets the bending limit "
            "(lower force_range or max_forces, or raise max_bending)"
        )
    return PointForces(out_s, out_f, out_m), out_c, examined


def sample_loads(
    rod: Rod, count: int, sampler: LoadSampler = LoadSampler(), generator: torch.Generator | None = None
) -> PointForces:
    """``count`` random load cases within the sampler's limits (module docstring), drawn from ``generator``.

    Args:
        rod: the rod (length, stiffness: the bending limit depends on them).
        count: number of cases.
        sampler: the distribution.
        generator: the source of randomness (required for reproducibility; a fresh unseeded one if ``None``).
    Returns:
        :class:`PointForces` with s (count, max_forces) [m], f (count, max_forces, 2) [N] and a mask, float64 on
        CPU, sorted by s with padding last (padded s and f are 0.0).
    """
    count = _int("count", count)
    if count < 0:
        raise OptionsError(f"count must be >= 0, got {count}")
    if not isinstance(sampler, LoadSampler):
        raise TorchrodTypeError(f"sampler must be a LoadSampler, got {type(sampler).__name__}")
    g = torch.Generator() if generator is None else generator
    if not isinstance(g, torch.Generator):
        raise TorchrodTypeError(f"generator must be a torch.Generator, got {type(g).__name__}")
    parts = []
    for start in range(0, count, 4096):
        loads, _, _ = _sample_rows(rod, sampler, [(g, min(4096, count - start))], torch.device("cpu"))
        parts.append(loads)
    if not parts:
        h = sampler.max_forces
        z = torch.zeros(0, h, dtype=torch.float64)
        return PointForces(z, torch.zeros(0, h, 2, dtype=torch.float64), torch.zeros(0, h, dtype=torch.bool))
    return PointForces(
        torch.cat([p.s for p in parts]), torch.cat([p.f for p in parts]), torch.cat([p.active for p in parts])
    )


PATCH_PARTS = 25
"""Point forces side by side that stand for one patch of load (:func:`sample_patches`)."""


def sample_patches(
    rod: Rod,
    count: int,
    width: float,
    generator: torch.Generator | None = None,
    *,
    force_range: tuple[float, float] = (0.2, 2.0),
) -> tuple[PointForces, torch.Tensor]:
    """``count`` patches of load, each ``width`` [m] long: :data:`PATCH_PARTS` equal point forces side by side, all
    one way, uniform in direction in the (f_x, f_y) plane, their total uniform in ``force_range`` [N], the patch's
    centre uniform between the second grating and the tip (the whole patch on the rod). A contact spread over a few
    millimetres, to hold the estimator's point forces against.

    Returns:
        the loads (:class:`PointForces`, s (count, PATCH_PARTS) [m], f (count, PATCH_PARTS, 2) [N], float64 on
        CPU) and each patch's centre (count,) [m].
    """
    count = _int("count", count)
    if count < 0:
        raise OptionsError(f"count must be >= 0, got {count}")
    width = _finite("width", width)
    lo, hi = rod.gratings[1 if rod.num_gratings > 1 else 0] + width / 2, rod.length - width / 2
    if not (width > 0.0 and hi > lo):
        raise OptionsError(
            f"width must be positive and leave room between the second grating and the tip, got {width!r} m"
        )
    f_lo, f_hi = _pair("force_range", force_range)
    g = torch.Generator() if generator is None else generator
    if not isinstance(g, torch.Generator):
        raise TorchrodTypeError(f"generator must be a torch.Generator, got {type(g).__name__}")
    f64 = torch.float64
    centre = lo + (hi - lo) * torch.rand(count, generator=g, dtype=f64)
    total = f_lo + (f_hi - f_lo) * torch.rand(count, generator=g, dtype=f64)
    angle = 2 * math.pi * torch.rand(count, generator=g, dtype=f64)
    offsets = width * ((torch.arange(PATCH_PARTS, dtype=f64) + 0.5) / PATCH_PARTS - 0.5)
    direction = torch.stack([angle.cos(), angle.sin()], dim=-1)
    f = (total[:, None] * direction / PATCH_PARTS)[:, None, :].expand(count, PATCH_PARTS, 2)
    return PointForces(centre[:, None] + offsets[None, :], f.contiguous()), centre


def _sensor_draws(n: int, G: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard normal noise (n, G, 2) and uniforms (n, G) for the missing gratings, on CPU."""
    noise = torch.randn(n, G, 2, generator=generator, dtype=torch.float64)
    missing = torch.rand(n, G, generator=generator, dtype=torch.float64)
    return noise, missing


def _apply_sensor(
    clean: torch.Tensor,
    offsets: torch.Tensor,
    noise: torch.Tensor,
    missing_u: torch.Tensor,
    sensor: SensorModel,
) -> tuple[torch.Tensor, torch.Tensor]:
    mask = ~(missing_u < sensor.missing_prob)
    curvature = clean + offsets + sensor.noise * noise
    curvature = torch.where(mask.unsqueeze(-1), curvature, 0.0)
    return curvature, mask


# ---------------------------------------------------------------------------------------------------- the set
class SyntheticDataset(torch.utils.data.Dataset):
    """A :class:`SyntheticSet` as a map-style dataset.

    Item i is a dict: ``curvature`` (G, 2) [1/m] (0.0 where missing), ``mask`` (G,) bool, ``s`` (h,) [m],
    ``f`` (h, 2) [N], ``force_mask`` (h,) bool, ``count`` () int64. The whole columns are attributes of the same
    names (first dimension N) for batched indexing.
    """

    def __init__(self, synthetic: SyntheticSet, dtype: torch.dtype = torch.float64) -> None:
        self.curvature = synthetic.curvature.to(dtype)
        self.mask = synthetic.mask
        self.s = synthetic.loads.s.to(dtype)
        self.f = synthetic.loads.f.to(dtype)
        self.force_mask = synthetic.loads.active
        self.count = synthetic.loads.count.to(torch.int64)

    def __len__(self) -> int:
        return self.curvature.shape[0]

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {
            "curvature": self.curvature[index],
            "mask": self.mask[index],
            "s": self.s[index],
            "f": self.f[index],
            "force_mask": self.force_mask[index],
            "count": self.count[index],
        }


@dataclass
class SyntheticSet:
    """N synthetic load cases and their readings (shapes: N cases, h = ``sampler.max_forces``, G gratings).

    Attributes:
        rod, sampler, sensor, seed: how the set was made.
        loads: the forces, s (N, h) [m] and f (N, h, 2) [N] with mask, sorted by s, padding last.
        clean: (N, G, 2) noise-free curvature at the gratings [1/m].
        curvature: (N, G, 2) the readings [1/m]: clean + offsets + noise, 0.0 where missing.
        mask: (N, G) bool, True where the grating has a reading.
        offsets: (G, 2) constant per-grating offsets of this set [1/m] (zeros if ``None`` is given).
        candidates: cases examined while sampling (``1 - N / candidates`` is the rejection rate), if known.
    """

    rod: Rod
    sampler: LoadSampler
    sensor: SensorModel
    seed: int
    loads: PointForces
    clean: torch.Tensor
    curvature: torch.Tensor
    mask: torch.Tensor
    offsets: torch.Tensor | None = None
    candidates: int | None = None

    def __post_init__(self) -> None:
        N, h = self.loads.s.shape
        G = self.rod.num_gratings
        if self.offsets is None:
            self.offsets = torch.zeros(G, 2, dtype=self.clean.dtype, device=self.clean.device)
        if h != self.sampler.max_forces:
            raise OptionsError(f"loads hold {h} forces per case, the sampler's max_forces is {self.sampler.max_forces}")
        for name, want in (
            ("clean", (N, G, 2)),
            ("curvature", (N, G, 2)),
            ("mask", (N, G)),
            ("offsets", (G, 2)),
        ):
            got = tuple(getattr(self, name).shape)
            if got != want:
                raise OptionsError(f"{name} must have shape {want} (N cases, G = {G} gratings), got {got}")
        if self.mask.dtype != torch.bool:
            raise OptionsError(f"mask must be bool, got {self.mask.dtype}")

    def __len__(self) -> int:
        return self.loads.s.shape[0]

    @property
    def rejection_rate(self) -> float | None:
        """Fraction of examined cases rejected by the bending limit (``None`` if unknown)."""
        if not self.candidates:
            return None
        return 1.0 - len(self) / self.candidates

    def to_dataset(self, dtype: torch.dtype = torch.float64) -> SyntheticDataset:
        """A :class:`SyntheticDataset` over this set (float tensors in ``dtype``)."""
        return SyntheticDataset(self, dtype)

    # ------------------------------------------------------------------ file format
    def _arrays(self) -> dict[str, np.ndarray]:
        def a(x: torch.Tensor, dtype: Any) -> np.ndarray:
            return np.ascontiguousarray(x.detach().cpu().numpy().astype(dtype, copy=False))

        assert self.offsets is not None  # __post_init__ replaces None with zeros
        return {
            "s": a(self.loads.s, np.float64),
            "f": a(self.loads.f, np.float64),
            "force_mask": a(self.loads.active, np.bool_),
            "count": a(self.loads.count, np.int64),
            "clean": a(self.clean, np.float64),
            "curvature": a(self.curvature, np.float64),
            "mask": a(self.mask, np.bool_),
            "offsets": a(self.offsets, np.float64),
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the set to ``path`` (``.npz``, format in the module docstring; written atomically, the name is
        kept as given)."""
        from .. import __version__

        arrays = self._arrays()
        meta = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "torchrod_version": __version__,
            "rod": self.rod.to_dict(),
            "sampler": self.sampler.to_dict(),
            "sensor": self.sensor.to_dict(),
            "seed": int(self.seed),
            "count": len(self),
            "candidates": None if self.candidates is None else int(self.candidates),
            "sha256": _digest(arrays),
        }
        path = os.fspath(path)
        folder = os.path.dirname(os.path.abspath(path))
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=folder)
        try:
            with os.fdopen(fd, "wb") as fh:
                # cast: the stub's allow_pickle: bool keyword would reject a dict of arrays
                np.savez_compressed(fh, meta=np.array(json.dumps(meta)), **cast("dict[str, Any]", arrays))
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path: str | os.PathLike, rod: Rod | None = None) -> SyntheticSet:
        """Read a set written by :meth:`save`, checking it (``ValueError`` naming the problem).

        Args:
            path: the ``.npz`` file.
            rod: if given, the set's rod must have the same length, bending stiffness and gratings (the
                quantities the readings depend on; the location bias and the description may differ).
        """
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FileNotFoundError(f"no such data set: {path}")
        try:
            with np.load(path, allow_pickle=False) as npz:
                names = set(npz.files)
                if "meta" not in names:
                    raise OptionsError(f"{path}: not a torchrod data set (no 'meta' entry)")
                meta_raw = npz["meta"]
                if meta_raw.shape != () or meta_raw.dtype.kind != "U":
                    raise OptionsError(f"{path}: not a torchrod data set ('meta' is not a JSON string)")
                meta = json.loads(str(meta_raw))
                if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                    raise OptionsError(f"{path}: not a torchrod data set (format tag {meta.get('format')!r})")
                version = meta.get("format_version")
                if not isinstance(version, int):
                    raise OptionsError(f"{path}: format_version is missing or not an integer ({version!r})")  # noqa: TRY004
                if version > FORMAT_VERSION:
                    raise OptionsError(
                        f"{path}: format_version {version} was written by a newer torchrod "
                        f"({meta.get('torchrod_version')}); this one reads up to {FORMAT_VERSION}"
                    )
                missing = [n for n in _ARRAYS if n not in names]
                extra = sorted(names - set(_ARRAYS) - {"meta"})
                if missing or extra:
                    raise OptionsError(f"{path}: corrupt data set: missing arrays {missing}, unexpected arrays {extra}")
                arrays = {n: npz[n] for n in _ARRAYS}
        except ValueError as exc:
            if str(exc).startswith(path):
                raise
            raise OptionsError(f"{path}: corrupt or unreadable data set ({exc})") from None
        except Exception as exc:  # noqa: BLE001 -- zipfile.BadZipFile, zlib.error, EOFError, OSError, ...: a damaged file
            raise OptionsError(f"{path}: corrupt or unreadable data set ({type(exc).__name__}: {exc})") from None
        if meta.get("sha256") != _digest(arrays):
            raise OptionsError(f"{path}: corrupt data set: the arrays do not match the stored sha256")
        try:
            stored_rod = Rod.from_dict(meta["rod"])
            sampler = LoadSampler.from_dict(meta["sampler"])
            sensor = SensorModel.from_dict(meta["sensor"])
            seed, count = int(meta["seed"]), int(meta["count"])
        except (KeyError, TypeError, ValueError) as exc:
            raise OptionsError(f"{path}: corrupt data set metadata ({exc})") from None
        _check_arrays(path, arrays, count, sampler.max_forces, stored_rod.num_gratings)
        if rod is not None:
            diff = _rod_differences(stored_rod, rod)
            if diff:
                raise OptionsError(f"{path}: the set was made for a different rod ({'; '.join(diff)})")
        loads = PointForces(
            torch.from_numpy(arrays["s"]),
            torch.from_numpy(arrays["f"]),
            torch.from_numpy(arrays["force_mask"]),
        )
        return cls(
            rod=stored_rod,
            sampler=sampler,
            sensor=sensor,
            seed=seed,
            loads=loads,
            clean=torch.from_numpy(arrays["clean"]),
            curvature=torch.from_numpy(arrays["curvature"]),
            mask=torch.from_numpy(arrays["mask"]),
            offsets=torch.from_numpy(arrays["offsets"]),
            candidates=meta.get("candidates"),
        )


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(a.dtype.str.encode())
        h.update(repr(tuple(a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _check_arrays(path: str, arrays: dict[str, np.ndarray], N: int, h: int, G: int) -> None:
    want = {
        "s": ((N, h), np.float64),
        "f": ((N, h, 2), np.float64),
        "force_mask": ((N, h), np.bool_),
        "count": ((N,), np.int64),
        "clean": ((N, G, 2), np.float64),
        "curvature": ((N, G, 2), np.float64),
        "mask": ((N, G), np.bool_),
        "offsets": ((G, 2), np.float64),
    }
    for name, (shape, dtype) in want.items():
        a = arrays[name]
        if a.shape != shape or a.dtype != dtype:
            raise OptionsError(
                f"{path}: inconsistent data set: {name!r} is {a.dtype}{list(a.shape)}, expected "
                f"{np.dtype(dtype)}{list(shape)} (N = {N} cases, h = {h} forces, G = {G} gratings)"
            )
        if a.dtype == np.float64 and not np.isfinite(a).all():
            raise OptionsError(f"{path}: inconsistent data set: {name!r} holds non-finite values")
    if not np.array_equal(arrays["force_mask"].sum(axis=1), arrays["count"]):
        raise OptionsError(f"{path}: inconsistent data set: 'count' disagrees with 'force_mask'")


def _rod_differences(a: Rod, b: Rod) -> list[str]:
    out = []
    if not math.isclose(a.length, b.length, rel_tol=1e-12):
        out.append(f"length {a.length} m vs {b.length} m")
    if not math.isclose(a.bending_stiffness, b.bending_stiffness, rel_tol=1e-9):
        out.append(f"bending_stiffness {a.bending_stiffness} vs {b.bending_stiffness} N m^2")
    if len(a.gratings) != len(b.gratings) or any(
        abs(x - y) > 1e-12 for x, y in zip(a.gratings, b.gratings, strict=False)
    ):
        out.append(f"gratings {list(a.gratings)} vs {list(b.gratings)}")
    return out


# ---------------------------------------------------------------------------------------------------- generate
def generate(
    rod: Rod,
    count: int,
    *,
    sampler: LoadSampler = LoadSampler(),
    sensor: SensorModel = SensorModel(),
    seed: int = 0,
    batch_size: int = 4096,
    progress: bool = False,
    device: torch.device | str | None = None,
) -> SyntheticSet:
    """A synthetic set of ``count`` load cases and their readings (module docstring: distribution, sensor model,
    reproducibility).

    Args:
        rod: the rod.
        count: number of cases N.
        sampler, sensor: the load distribution and the sensor effects.
        seed: the only source of randomness; the same seed gives the same set whatever ``batch_size``.
        batch_size: cases evaluated together (memory ~ 5 kB per case), rounded up to a multiple of :data:`CHUNK`.
        progress: a tqdm progress bar on stderr.
        device: where the forward model runs (random draws stay on CPU); the set is returned on CPU.
    Returns:
        :class:`SyntheticSet` (float64, CPU).
    """
    count = _int("count", count)
    seed = _int("seed", seed)
    batch_size = _int("batch_size", batch_size)
    if count < 0:
        raise OptionsError(f"count must be >= 0, got {count}")
    if batch_size < 1:
        raise OptionsError(f"batch_size must be >= 1, got {batch_size}")
    if not isinstance(rod, Rod):
        raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
    if not isinstance(sampler, LoadSampler) or not isinstance(sensor, SensorModel):
        raise TorchrodTypeError("sampler must be a LoadSampler and sensor a SensorModel")
    sampler.location_range(rod)
    dev = torch.device("cpu") if device is None else torch.device(device)
    G, h = rod.num_gratings, sampler.max_forces
    per_batch = max(1, math.ceil(batch_size / CHUNK))
    sizes = [min(CHUNK, count - start) for start in range(0, count, CHUNK)]
    offsets = sensor.offset_std * torch.randn(
        G, 2, generator=torch.Generator().manual_seed(_derive_seed(seed, "offsets")), dtype=torch.float64
    )
    s_parts, f_parts, m_parts, clean_parts, curv_parts, mask_parts = [], [], [], [], [], []
    examined = 0
    bar = _progress(count, progress, "cases")
    try:
        for b0 in range(0, len(sizes), per_batch):
            idx = range(b0, min(b0 + per_batch, len(sizes)))
            chunks = [(torch.Generator().manual_seed(_derive_seed(seed, "loads", c)), sizes[c]) for c in idx]
            loads, clean, n_examined = _sample_rows(rod, sampler, chunks, dev)
            examined += n_examined
            if sensor.location_bias != 0.0:
                shifted = _shifted(rod, loads, -sensor.location_bias)
                clean, _, resolved = _profile(rod, shifted)
                _check_resolved(resolved, shifted, "case")
            draws = [
                _sensor_draws(sizes[c], G, torch.Generator().manual_seed(_derive_seed(seed, "sensor", c))) for c in idx
            ]
            noise = torch.cat([d[0] for d in draws])
            missing = torch.cat([d[1] for d in draws])
            clean = clean.cpu()
            curvature, mask = _apply_sensor(clean, offsets, noise, missing, sensor)
            s_parts.append(loads.s.cpu())
            f_parts.append(loads.f.cpu())
            m_parts.append(loads.active.cpu())
            clean_parts.append(clean)
            curv_parts.append(curvature)
            mask_parts.append(mask)
            bar.update(loads.batch_size)
    finally:
        bar.close()

    def cat(parts: list[torch.Tensor], shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        return torch.cat(parts) if parts else torch.zeros(shape, dtype=dtype)

    loads = PointForces(
        cat(s_parts, (0, h), torch.float64),
        cat(f_parts, (0, h, 2), torch.float64),
        cat(m_parts, (0, h), torch.bool),
    )
    return SyntheticSet(
        rod=rod,
        sampler=sampler,
        sensor=sensor,
        seed=seed,
        loads=loads,
        clean=cat(clean_parts, (0, G, 2), torch.float64),
        curvature=cat(curv_parts, (0, G, 2), torch.float64),
        mask=cat(mask_parts, (0, G), torch.bool),
        offsets=offsets,
        candidates=examined,
    )


def _progress(total: int, enabled: bool, unit: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, file=sys.stderr, unit=unit, dynamic_ncols=True, leave=False)
