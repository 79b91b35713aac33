"""A needle with few gratings and an imperfect calibration: what the count rule and a calibration error buy.

The rod (:func:`needle`): a 130 mm nitinol needle (the shipped rods' tube) with 3 gratings at 60, 104 and 119 mm, so
6 values per reading: one force (3 unknowns) leaves 3 degrees of freedom to test its fit, two forces leave none and
are never chosen (:mod:`torchrod.kernels.counts`). The readings (:func:`needle_readings`): one force near the tip
(122 to 130 mm, 0.05 to 0.5 N in any direction), Gaussian noise ``sigma``, and one grating, drawn per reading,
reading ``1 + gain_error`` times its curvature (a gain off by ``gain_error``).

:func:`study` estimates each set of readings twice, with the noise known: by a rod without a calibration error and
by one whose every grating carries the relative error ``gain_error`` (``Rod.calibration_error``; which grating is off
is not said), the count chosen among 0 to ``max_forces`` (3 by default: more than the needle can test). Per row: the
fraction of readings answered with no force, one and more; over the readings answered with one force, the spread (root
mean square) of the force direction's error [deg], of the magnitude's relative error [%] and of the location's error
[mm]; the fraction answered ``ok``; the count accuracy (one force answered, the truth). A gain error scales both
components of one grating's reading alike, so it leaves that grating's bending direction as it is: it moves the
magnitude and the location more than the direction. ``torchrod bench gratings`` prints the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..estimate.estimator import Estimator, EstimatorOptions
from ..loads import PointForces
from ..rod import Rod

__all__ = ["NEEDLE_GRATINGS", "StudyRow", "needle", "needle_readings", "study"]

NEEDLE_GRATINGS = (0.060, 0.104, 0.119)
"""[m] The needle's grating positions."""

TIP_ZONE = (0.122, 0.130)
"""[m] Where the needle's force acts: distal to the last grating, up to the tip."""

MAGNITUDES = (0.05, 0.5)
"""[N] The range of the force's magnitude."""


def needle(calibration_error: float = 0.0) -> Rod:
    """The 130 mm needle (module docstring), with ``calibration_error`` at every grating (0: none)."""
    return Rod.from_geometry(
        length=0.130,
        outer_diameter=0.001397,
        inner_diameter=0.001118,
        youngs_modulus=67e9,
        gratings=NEEDLE_GRATINGS,
        calibration_error=calibration_error,
    )


def needle_readings(
    rod: Rod, count: int, gain_error: float, sigma: float, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` readings (count, G, 2) [1/m] of one force near the tip, with one grating's gain off by ``gain_error``
    and noise ``sigma`` [1/m], and the true forces (count, 3): (s [m], f_x, f_y [N])."""
    from ..model.body_frame import simulate

    gen = torch.Generator().manual_seed(seed)
    uniform = lambda lo, hi: lo + (hi - lo) * torch.rand(count, generator=gen, dtype=torch.float64)  # noqa: E731
    s = uniform(*TIP_ZONE)
    size = uniform(*MAGNITUDES)
    angle = uniform(-math.pi, math.pi)
    f = torch.stack([size * torch.cos(angle), size * torch.sin(angle)], dim=-1)
    loads = PointForces(s[:, None], f[:, None, :], torch.ones(count, 1, dtype=torch.bool))
    u = simulate(rod, loads).grating_curvature.to(torch.float64)
    off = torch.randint(rod.num_gratings, (count,), generator=gen)
    gain = torch.ones(count, rod.num_gratings, dtype=torch.float64)
    gain[torch.arange(count), off] += gain_error
    u = u * gain[..., None] + sigma * torch.randn(u.shape, generator=gen, dtype=torch.float64)
    return u, torch.cat([s[:, None], f], dim=-1)


@dataclass(frozen=True)
class StudyRow:
    """One row of :func:`study`'s table (module docstring)."""

    gain_error: float
    calibration_error: float
    none: float
    one: float
    more: float
    direction_spread: float
    magnitude_error: float
    location_error: float
    ok: float
    count_accuracy: float


def _row(gain_error: float, calibration_error: float, result, truth: torch.Tensor) -> StudyRow:
    n = result.num_forces
    one = n == 1
    est = result.forces.f[:, 0, :]
    err = torch.atan2(est[:, 1], est[:, 0]) - torch.atan2(truth[:, 2], truth[:, 1])
    err = torch.remainder(err + math.pi, 2 * math.pi) - math.pi
    rms = lambda x: float(x[one].square().mean().sqrt()) if bool(one.any()) else math.nan  # noqa: E731
    size = est.norm(dim=-1) / truth[:, 1:].norm(dim=-1) - 1.0
    where = result.forces.s[:, 0] - truth[:, 0]
    frac = lambda x: float(x.double().mean())  # noqa: E731
    return StudyRow(
        gain_error=gain_error,
        calibration_error=calibration_error,
        none=frac(n == 0),
        one=frac(one),
        more=frac(n >= 2),
        direction_spread=math.degrees(rms(err)),
        magnitude_error=100 * rms(size),
        location_error=1e3 * rms(where),
        ok=frac(result.ok),
        count_accuracy=frac(one),
    )


def study(
    gain_errors: tuple[float, ...] = (0.0, 0.1, 0.25, 0.5, 1.0),
    count: int = 200,
    sigma: float = 0.05,
    max_forces: int = 3,
    seed: int = 0,
    threads: int | None = None,
    noise_known: bool = True,
) -> list[StudyRow]:
    """The table (module docstring): for each gain error, a row without a calibration error and one with it; with
    ``noise_known`` False the estimator is not told ``sigma`` (each reading's noise is its own, and the calibration
    error, which needs a known noise, changes nothing)."""
    rows = []
    plain = needle()
    for k, e in enumerate(gain_errors):
        u, truth = needle_readings(plain, count, e, sigma, seed + k)
        for rel in (0.0, e) if e > 0.0 else (0.0,):
            rod = needle(rel)
            options = EstimatorOptions(max_forces=max_forces, noise=sigma if noise_known else None, threads=threads)
            result = Estimator(rod, options).estimate(u)
            rows.append(_row(e, rel, result, truth))
    return rows


def table(rows: list[StudyRow]) -> list[str]:
    """The rows as the lines of a Markdown table."""
    out = [
        "| gain error | calibration error | 0 forces | 1 force | 2+ forces | direction spread (deg) | magnitude error "
        "(%) | location error (mm) | ok | count accuracy |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def spread(x: float) -> str:  # (no reading answered with one force: no spread, an empty cell)
        return f"{x:.1f}" if math.isfinite(x) else ""

    for r in rows:
        out.append(
            f"| {100 * r.gain_error:.0f} % | {'none' if r.calibration_error == 0 else f'{r.calibration_error:g}'} | "
            f"{r.none:.2f} | {r.one:.2f} | {r.more:.2f} | {spread(r.direction_spread)} | "
            f"{spread(r.magnitude_error)} | {spread(r.location_error)} | {r.ok:.2f} | {r.count_accuracy:.2f} |"
        )
    return out
