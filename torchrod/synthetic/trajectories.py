"""Synthetic reading streams: readings at a fixed rate whose contacts appear, drift, grow, shrink and vanish
smoothly (:func:`generate_trajectory`, with :class:`ContactModel`), and their JSON-lines files
(:func:`write_trajectory`).

The loads keep the limits of a :class:`~torchrod.synthetic.loadsets.LoadSampler` (count, separation, location
range, bending limit) at every reading, and the readings carry the sensor effects of a
:class:`~torchrod.synthetic.loadsets.SensorModel`, as in the load sets of :mod:`torchrod.synthetic.loadsets`.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..errors import OptionsError
from ..loads import PointForces
from ..rod import Rod
from .loadsets import (
    LoadSampler,
    SensorModel,
    _apply_sensor,
    _check_resolved,
    _derive_seed,
    _finite,
    _int,
    _pair,
    _profiles,
    _sensor_draws,
    _shifted,
)

__all__ = ["ContactModel", "Trajectory", "generate_trajectory", "truth_path", "write_trajectory"]


@dataclass(frozen=True)
class ContactModel:
    """How the contacts of a synthetic stream live (times in s, lengths in m).

    A contact appears at a random free location (at least ``min_separation + margin`` from the others) with the
    sampler's smallest magnitude, ramps up (smoothstep over ``ramp`` seconds) to a peak magnitude, wobbles by up to
    ``wobble`` of its peak, ramps down and vanishes after ``duration`` seconds. Its location drifts at a constant
    speed up to ``drift_speed`` and bounces off the ends of the location range and off its neighbours; its
    direction turns at up to ``rotation_speed`` rad/s. New contacts arrive at ``arrival_rate`` per second while
    fewer than ``max_forces`` are present, and at once when fewer than ``min_forces`` are. The peak magnitude is
    drawn in ``force_range`` capped by the single-force small-deflection bound ``2 EI max_bending / s^2``; a
    per-frame factor c <= 1, smoothed over ``smoothing`` seconds (an erosion then a moving average, which never
    exceeds the needed factor), then scales all forces of a frame so that the bending limit holds at every frame.
    """

    drift_speed: float = 0.005
    rotation_speed: float = 0.3
    duration: tuple[float, float] = (1.5, 5.0)
    ramp: tuple[float, float] = (0.5, 1.2)
    wobble: float = 0.15
    arrival_rate: float = 0.8
    margin: float = 0.002
    smoothing: float = 0.5

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name in ("drift_speed", "rotation_speed", "wobble", "arrival_rate", "margin", "smoothing"):
            v = _finite(name, getattr(self, name))
            if v < 0.0:
                raise OptionsError(f"{name} must be >= 0, got {getattr(self, name)!r}")
            set_(self, name, v)
        if self.wobble >= 1.0:
            raise OptionsError(f"wobble must be < 1, got {self.wobble!r}")
        for name in ("duration", "ramp"):
            lo, hi = _pair(name, getattr(self, name))
            if lo <= 0.0:
                raise OptionsError(f"{name} must be positive, got {getattr(self, name)!r}")
            set_(self, name, (lo, hi))


@dataclass
class Trajectory:
    """A synthetic stream: T readings at ``rate`` Hz and their ground truth.

    Attributes:
        readings: T dicts ``{"id": "f000123", "t": seconds, "curvature": [[ux, uy], ...]}`` ([1/m]; ``None`` for
            a missing grating).
        truth: T dicts ``{"id", "t", "forces": [{"s", "fx", "fy"}, ...]}`` (m, N; sorted by s).
        t: (T,) times [s].
        loads: the forces, (T, max_forces) padded, sorted by s.
        clean, curvature: (T, G, 2) [1/m]; mask (T, G) bool; offsets (G, 2) [1/m] (as in
            :class:`~torchrod.synthetic.loadsets.SyntheticSet`).
        events: frames where a contact appears or vanishes (the only frames where forces may jump).
        scale: (T,) the bending-limit factor c applied to each frame's forces.
    """

    readings: list[dict[str, Any]]
    truth: list[dict[str, Any]]
    t: torch.Tensor
    loads: PointForces
    clean: torch.Tensor
    curvature: torch.Tensor
    mask: torch.Tensor
    offsets: torch.Tensor
    events: list[int] = field(default_factory=list)
    scale: torch.Tensor | None = None


class _Contact:
    __slots__ = (
        "angle",
        "down",
        "end",
        "ident",
        "omega",
        "peak",
        "period",
        "phase",
        "s",
        "start",
        "up",
        "v",
        "wob",
    )
    ident: int
    s: float
    v: float
    angle: float
    omega: float
    peak: float
    start: int
    end: int
    up: float
    down: float
    wob: float
    period: float
    phase: float


def _smoothstep(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def _plan(
    rod: Rod, count: int, rate: float, sampler: LoadSampler, model: ContactModel, g: torch.Generator
) -> tuple[list[list[tuple[int, float, float, float]]], list[int]]:
    """Frame by frame, the contacts as (id, s, fx, fy) before the bending scale, and the event frames."""
    lo, hi = sampler.location_range(rod)
    f_lo, f_hi = sampler.force_range
    gap = sampler.min_separation + model.margin
    dt = 1.0 / rate
    ei = rod.bending_stiffness

    def rand() -> float:
        return float(torch.rand((), generator=g, dtype=torch.float64))

    def uniform(a: float, b: float) -> float:
        return a + (b - a) * rand()

    active: list[_Contact] = []
    next_id = 0

    def spawn(k: int) -> bool:
        nonlocal next_id
        for _ in range(64):
            s = uniform(lo, hi)
            if all(abs(s - c.s) >= gap for c in active):
                break
        else:
            return False
        c = _Contact()
        c.ident, next_id = next_id, next_id + 1
        c.s = s
        c.v = uniform(-model.drift_speed, model.drift_speed)
        c.angle = uniform(0.0, 2.0 * math.pi)
        c.omega = uniform(-model.rotation_speed, model.rotation_speed)
        cap = 2.0 * ei * sampler.max_bending / max(s, 1e-9) ** 2
        c.peak = uniform(f_lo, max(f_lo, min(f_hi, cap)))
        duration = uniform(*model.duration)
        c.start = k
        c.end = k + max(1, round(duration * rate))  # last frame where it is present
        up, down = uniform(*model.ramp), uniform(*model.ramp)
        if up + down > duration:
            up, down = up * duration / (up + down), down * duration / (up + down)
        c.up, c.down = up, down
        c.wob = uniform(0.0, model.wobble)
        c.period = uniform(1.0, 3.0)
        c.phase = uniform(0.0, 2.0 * math.pi)
        active.append(c)
        return True

    frames: list[list[tuple[int, float, float, float]]] = []
    events: list[int] = []
    for k in range(count):
        before = {c.ident for c in active}
        active[:] = [c for c in active if c.end >= k]
        if k == 0:
            n0 = sampler.min_forces + int(rand() * (sampler.max_forces - sampler.min_forces + 1))
            for _ in range(min(n0, sampler.max_forces)):
                spawn(k)
        else:
            # Move: constant drift, bounce off the range ends; moves that would bring two contacts closer than
            # min_separation are undone and those contacts turn back (a valid previous state always exists).
            old = {c.ident: c.s for c in active}
            for c in active:
                s_new = c.s + c.v * dt
                if s_new < lo or s_new > hi:
                    c.v = -c.v
                    s_new = c.s
                c.s = s_new
            while True:
                order = sorted(active, key=lambda c: c.s)
                clash = {
                    c.ident
                    for a, b in itertools.pairwise(order)
                    if b.s - a.s < sampler.min_separation
                    for c in (a, b)
                    if c.s != old[c.ident]
                }
                if not clash:
                    break
                for c in active:
                    if c.ident in clash:
                        c.s, c.v = old[c.ident], -c.v
            while len(active) < sampler.min_forces and spawn(k):
                pass
            if len(active) < sampler.max_forces and rand() < model.arrival_rate * dt:
                spawn(k)
        if {c.ident for c in active} != before and k > 0:
            events.append(k)
        row = []
        for c in active:
            age, left = (k - c.start) * dt, (c.end - k) * dt
            env = _smoothstep(age / c.up) * _smoothstep(left / c.down)
            wob = 1.0 + c.wob * math.sin(2.0 * math.pi * age / c.period + c.phase)
            mag = min(f_hi, f_lo + (c.peak * wob - f_lo) * env)
            ang = c.angle + c.omega * age
            row.append((c.ident, c.s, mag * math.cos(ang), mag * math.sin(ang)))
        frames.append(sorted(row, key=lambda x: x[1]))
    return frames, events


def _bending_scale(rod: Rod, loads: PointForces, limit: float, window: int) -> torch.Tensor:
    """A smooth per-frame factor c (T,) in (0, 1] with total turning of (c f) <= limit at every frame."""
    T = loads.batch_size
    mask = loads.mask
    assert mask is not None  # the loads come from PointForces.from_lists, which always sets a mask

    def turning(c: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        sub = PointForces(loads.s[rows], loads.f[rows] * c.unsqueeze(-1).unsqueeze(-1), mask[rows])
        return _profiles(rod, sub)[1]

    c = torch.ones(T, dtype=torch.float64)
    for _ in range(6):
        beta = turning(c, torch.arange(T))
        bad = (beta > limit).nonzero().flatten()
        if bad.numel() == 0:
            return c
        # Bisection on the frames beyond the limit: the largest factor (within 1e-3) that satisfies it.
        lo, hi = torch.zeros(bad.numel(), dtype=torch.float64), c[bad].clone()
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            ok = turning(mid, bad) <= 0.995 * limit
            lo, hi = torch.where(ok, mid, lo), torch.where(ok, hi, mid)
        need = c.clone()
        need[bad] = lo
        c = _opening(need, window)
    raise AssertionError("bending-limit scaling did not converge")  # pragma: no cover


def _opening(c: torch.Tensor, w: int) -> torch.Tensor:
    """Erosion (min over +-w) then moving average (over +-w): smooth, and <= c at every frame."""
    if w <= 0:
        return c
    pad = torch.nn.functional.pad(c.view(1, 1, -1), (2 * w, 2 * w), value=1.0).view(-1)
    eroded = pad.unfold(0, 2 * w + 1, 1).amin(dim=1)  # frames -w .. T+w-1
    return eroded.unfold(0, 2 * w + 1, 1).mean(dim=1)


def generate_trajectory(
    rod: Rod,
    count: int,
    *,
    rate: float = 100.0,
    sensor: SensorModel = SensorModel(),
    sampler: LoadSampler = LoadSampler(),
    contacts: ContactModel = ContactModel(),
    seed: int = 0,
    decimals: int | None = None,
) -> Trajectory:
    """A synthetic stream of ``count`` readings at ``rate`` Hz with moving, growing, appearing contacts.

    At most ``sampler.max_forces`` contacts at a time, at least ``min_separation`` apart, within the sampler's
    location range and bending limit at every frame (see :class:`ContactModel`). Readings carry the sensor effects
    of ``sensor`` (offsets drawn once for the stream).

    Args:
        rod: the rod.
        count: number of readings T.
        rate: readings per second [Hz].
        sensor, sampler, contacts: sensor effects, force limits, and how contacts live.
        seed: the only source of randomness.
        decimals: round the readings' curvature to this many decimals [1/m] in ``readings`` (the tensors and
            the truth keep full precision).
    Returns:
        :class:`Trajectory`.
    """
    count, seed = _int("count", count), _int("seed", seed)
    if count < 1:
        raise OptionsError(f"count must be >= 1, got {count}")
    rate = _finite("rate", rate)
    if rate <= 0.0:
        raise OptionsError(f"rate must be positive (Hz), got {rate}")
    if decimals is not None:
        decimals = _int("decimals", decimals)
    frames, events = _plan(
        rod, count, rate, sampler, contacts, torch.Generator().manual_seed(_derive_seed(seed, "trajectory"))
    )
    h = sampler.max_forces
    loads = PointForces.from_lists([[(s, fx, fy) for _, s, fx, fy in row] for row in frames], max_forces=h)
    window = round(contacts.smoothing * rate)
    scale = _bending_scale(rod, loads, sampler.max_bending, window) if math.isfinite(sampler.max_bending) else None
    if scale is not None:
        loads = PointForces(loads.s, loads.f * scale.view(-1, 1, 1), loads.mask)
    G = rod.num_gratings
    shifted = _shifted(rod, loads, -sensor.location_bias)
    clean, _, resolved = _profiles(rod, shifted)
    _check_resolved(resolved, shifted, "frame")
    sg = torch.Generator().manual_seed(_derive_seed(seed, "trajectory-sensor"))
    offsets = sensor.offset_std * torch.randn(G, 2, generator=sg, dtype=torch.float64)
    noise, missing = _sensor_draws(count, G, sg)
    curvature, mask = _apply_sensor(clean, offsets, noise, missing, sensor)
    t = torch.arange(count, dtype=torch.float64) / rate
    readings, truth = [], []
    values = curvature.tolist()
    present = mask.tolist()
    times = t.tolist()
    for k, forces in enumerate(loads.to_lists()):
        ident = f"f{k:06d}"
        row = [
            ([round(u, decimals) for u in uv] if decimals is not None else uv) if ok else None
            for uv, ok in zip(values[k], present[k], strict=False)
        ]
        readings.append({"id": ident, "t": times[k], "curvature": row})
        truth.append({"id": ident, "t": times[k], "forces": [{"s": s, "fx": fx, "fy": fy} for s, fx, fy in forces]})
    return Trajectory(
        readings=readings,
        truth=truth,
        t=t,
        loads=loads,
        clean=clean,
        curvature=curvature,
        mask=mask,
        offsets=offsets,
        events=events,
        scale=scale,
    )


def truth_path(path: str | os.PathLike) -> str:
    """The default ground-truth file beside a stream: ``PATH.jsonl`` -> ``PATH_truth.jsonl``."""
    root, ext = os.path.splitext(os.fspath(path))
    return f"{root}_truth{ext or '.jsonl'}"


def write_trajectory(
    trajectory: Trajectory, path: str | os.PathLike, truth: str | os.PathLike | None = None
) -> tuple[str, str]:
    """Write the readings to ``path`` and the ground truth to ``truth`` (default :func:`truth_path`), one JSON
    object per line. Returns both paths."""
    path = os.fspath(path)
    truth = truth_path(path) if truth is None else os.fspath(truth)
    _write_lines(path, trajectory.readings)
    _write_lines(truth, trajectory.truth)
    return path, truth


def _write_lines(path: str, rows: Iterable[dict[str, Any]]) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        for row in rows:
            fh.write(json.dumps(row, separators=(",", ":")))
            fh.write("\n")
