"""``torchrod evaluate``: accuracy and speed of the estimator on simulated readings over a realistic envelope.

Usage: ``torchrod evaluate [--rod ROD] [--count-per-cell N] [--noise 0,0.1,0.3] [--seed S]``.

For every number of forces k = 1..``--max-forces`` and every noise level sigma, N load cases are drawn
(:mod:`torchrod.synthetic.loadsets`): k forces at least ``--min-separation`` apart (25 mm), magnitudes uniform in
``--force-range`` (0.05 to 2 N) in any body-frame direction, locations uniform over [``--s-min``, L], cases whose
rod turns by more than ``--max-bending-deg`` (90 degrees) redrawn; their readings carry Gaussian noise sigma per
component (and the rod's location bias). The estimator (``torchrod.Estimator``, default options, up to
``--max-forces`` forces, the count chosen automatically) is told sigma (``--estimator-noise known``, the default: a
sensor's noise is a datasheet figure) or estimates it (``estimate``).

Default ``--s-min``: the rod's second grating. A force proximal to the first grating bends no grating (it leaves no
trace in the readings), and a force between the first two gratings is seen by one grating only, whose two
components cannot separate the force's magnitude from its lever: location and magnitude are not identifiable there.
``--s-min 0.0058`` evaluates the synthetic default range (0.02 L) instead, unobservable forces included.

Rows, for every sigma:

* ``0``: no force, the reading pure noise: "count ok" is how often the count is 0;
* ``k`` = 1..H: as above;
* ``k nb`` (near base): k forces, the most proximal within 20 mm of the second grating (between the first grating
  and 20 mm distal to the second), where a force is seen by few gratings;
* ``unexpl.``: readings no few point forces produce (:func:`unexplainable`: alternating signs at successive
  gratings, a sine wave of three grating spacings, random values; 1 to 10 1/m), plus the noise: the "misfit"
  column is how often the verdict says so.

Printed, per row: readings, count accuracy (chosen count = k), the same over the readings whose weakest force is
at least 0.2 N (a 0.05 N force near the base bends the rod less than the noise), then over the forces of the
readings whose count is right (estimated and true forces paired in order of location): median, 90th percentile
and root mean square of the force error |f_est - f_true| / |f_true| [%] and of the location error [mm] (outliers
are what the root mean square shows); the share of readings whose status is not ``ok`` and the share ``misfit``;
estimation wall time per reading (all readings of a row estimated in batches of ``--batch-size``). ``--json``
prints the same numbers as JSON lines instead.

``--input strain`` passes every reading through a multicore fibre (the rod's ``fibre``, else
:data:`EVALUATION_FIBRE`): the clean curvature becomes core strains, plus a random common strain per grating
(temperature, uniform within +-1e-3) and Gaussian strain noise per core at the level that implies the row's sigma
for the curvature, and is turned back by the fibre's least squares (:mod:`torchrod.sensors`), as strain readings
are read; the estimator is given that sigma, as ``--strain-noise`` gives it.

``--input wavelength`` passes every reading through the peak wavelengths of the rod's fibre (its calibration
matrices or its physics route; without a wavelength section, the physics route of :data:`EVALUATION_FIBRE` with
reference wavelengths 1530 + 2.5 k nm): the shifts the bend gives, a random temperature per grating (the common
strain above, as shifts the conversion removes) and Gaussian wavelength noise per core at the level that implies
the row's sigma for the curvature (the largest over the gratings, as ``--wavelength-noise`` gives it), turned back
by the conversion the reading parser applies (:mod:`torchrod.sensors`).

``--recovery N`` runs the clean-recovery study instead (:mod:`torchrod.eval.recovery`): N stratified noise-free
cases, the verdicts per stratum, and every case missed or answered wrong. With ``--large-bends`` its envelope is the
rod's elastic range (bending strain up to ``--max-strain``, 4 % by default) instead of 90 degrees of turning, with a
fourth stratum of cases turning the rod beyond 135 degrees.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any, NamedTuple

import torch

from ...estimate.estimator import EstimateResult, Estimator, EstimatorOptions
from ...presets import load as load_rod
from ...rod import Rod
from ...sensors import WAVELENGTH_UNITS
from . import rod_help

HELP = "accuracy of the estimator on simulated readings over a realistic envelope"

EVALUATION_FIBRE = ((3.5e-5, 0.0), (-1.75e-5, 3.0311e-5), (-1.75e-5, -3.0311e-5))
"""[m] The cores of ``--input strain`` when the rod has no fibre: three at 120 degrees, 35 um off the axis (a
common multicore shape-sensing fibre)."""

EVALUATION_REFERENCE_NM = (1530.0, 2.5)
"""[nm] ``--input wavelength`` without a rod wavelength section: grating k (0-based) reflects at 1530 + 2.5 k nm on
every core (gratings along a fibre are written at distinct wavelengths)."""

COMMON_STRAIN = 1e-3
"""``--input strain``: the common strain per grating is uniform in +-this (about 100 K of temperature change)."""

STRONG = 0.2
"""[N] the column ``ok >=0.2N`` counts only readings whose weakest force is at least this strong."""

__all__ = [
    "HELP",
    "cell_metrics",
    "configure",
    "evaluate_cell",
    "misfit_cell",
    "run",
    "through_sensor",
    "through_wavelengths",
    "unexplainable",
    "zero_cell",
]


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
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument("--count-per-cell", type=int, default=200, metavar="N", help="readings per cell (default 200)")
    parser.add_argument("--noise", type=_floats, default=[0.0, 0.1, 0.3], help="sigmas [1/m] (default 0,0.1,0.3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the load cases and noise (default 0)")
    parser.add_argument("--max-forces", type=int, default=3, help="forces per reading 1..H (default 3)")
    parser.add_argument("--force-range", type=_floats, default=[0.05, 2.0], help="[N] (default 0.05,2)")
    parser.add_argument("--min-separation", type=float, default=0.025, help="[m] (default 0.025)")
    parser.add_argument("--s-min", type=float, default=None, help="[m] lowest location (default: the 2nd grating)")
    parser.add_argument("--max-bending-deg", type=float, default=90.0, help="turning limit [deg] (default 90)")
    parser.add_argument(
        "--estimator-noise",
        choices=("known", "estimate"),
        default="known",
        help="give sigma to the estimator?",
    )
    parser.add_argument("--batch-size", type=int, default=500, help="readings per estimate call (default 500)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as the timings assume)")
    parser.add_argument(
        "--rows",
        type=_rows,
        default=ROWS,
        help="comma-separated rows to run, of " + ",".join(ROWS) + " (default: all)",
    )
    parser.add_argument(
        "--recovery",
        type=int,
        default=0,
        metavar="N",
        help="instead of the table: N stratified clean cases (torchrod.eval.recovery), verdicts per stratum and every "
        "failure (the tests run 1000 at seed 0)",
    )
    parser.add_argument(
        "--large-bends",
        action="store_true",
        help="with --recovery: cases up to the rod's elastic limit (bending strain up to --max-strain) instead of 90 "
        "degrees of turning, a quarter of them turning it beyond 135 degrees",
    )
    parser.add_argument(
        "--max-strain",
        type=float,
        default=None,
        help="with --large-bends: the largest bending strain |u| d_out / 2 (default 0.04)",
    )
    parser.add_argument(
        "--input",
        choices=("curvature", "strain", "wavelength"),
        default="curvature",
        help="readings as curvature (default), as a multicore fibre's core strains, or as its peak wavelengths "
        "(see below)",
    )
    parser.add_argument("--json", action="store_true", help="JSON lines instead of a table")


ROWS = ("zero", "forces", "near-base", "unexplainable")


def _rows(text: str) -> tuple[str, ...]:
    rows = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows:
        raise argparse.ArgumentTypeError(f"rows must be among {','.join(ROWS)}, got {text!r}")
    return rows


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
    near_base: bool = False,
    fibre: Any = None,
) -> dict[str, Any]:
    """Simulate ``count`` readings with ``k`` forces and noise ``sigma``, estimate them, return the cell's metrics
    (:func:`cell_metrics` plus ``time_ms`` per reading, wall clock of the estimation alone). ``near_base``: only
    cases whose most proximal force lies between the first grating and 20 mm distal to the second (drawn over
    [first grating, L] and kept when they do). ``fibre``: readings pass through its core strains, or its peak
    wavelengths when it is a :class:`WavelengthInput` (:func:`through_sensor`)."""
    from ...synthetic import LoadSampler, SensorModel, generate

    lo = s_min if s_min is not None else (rod.gratings[1] if rod.num_gratings > 1 else 0.02 * rod.length)
    if near_base:
        lo = rod.gratings[0]
    sampler = LoadSampler(
        min_forces=k,
        max_forces=k,
        force_range=force_range,
        min_separation=min_separation,
        s_range=(lo, rod.length),
        max_bending=max_bending,
    )
    sensor = SensorModel(noise=0.0 if fibre is not None else sigma, location_bias=rod.location_bias)
    cell_seed = seed * 1000 + 10 * k + round(100 * sigma) + (500 if near_base else 0)
    if near_base:
        edge = (rod.gratings[1] if rod.num_gratings > 1 else rod.gratings[0]) + 0.02 + rod.location_bias
        curvature_parts: list[torch.Tensor] = []
        mask_parts: list[torch.Tensor] = []
        s_parts: list[torch.Tensor] = []
        f_parts: list[torch.Tensor] = []
        kept, draw = 0, 0
        while kept < count:
            data = generate(rod, 4 * count, sampler=sampler, sensor=sensor, seed=cell_seed + 7919 * draw)
            near = data.loads.s[:, 0] < edge
            curvature_parts.append(data.curvature[near])
            mask_parts.append(data.mask[near])
            s_parts.append(data.loads.s[near])
            f_parts.append(data.loads.f[near])
            kept += int(near.sum())
            draw += 1
        curvature, mask = torch.cat(curvature_parts)[:count], torch.cat(mask_parts)[:count]
        s_true, f_true = torch.cat(s_parts)[:count], torch.cat(f_parts)[:count]
    else:
        data = generate(rod, count, sampler=sampler, sensor=sensor, seed=cell_seed)
        curvature, mask, s_true, f_true = data.curvature, data.mask, data.loads.s, data.loads.f
    if fibre is not None:
        curvature = through_sensor(curvature, sigma, fibre, cell_seed)
    results, elapsed = _estimate(rod, curvature, mask, sigma, max_forces, noise_known, batch_size)
    out = cell_metrics(results, s_true, f_true, k)
    out.update(forces=k, noise=sigma, time_ms=1e3 * elapsed / max(1, count), row=f"{k} nb" if near_base else str(k))
    return out


def through_fibre(clean: torch.Tensor, sigma: float, fibre: Any, seed: int) -> torch.Tensor:
    """(N, G, 2) clean curvature [1/m] -> the curvature read from a multicore fibre: core strains plus a common
    strain per grating (uniform in +-:data:`COMMON_STRAIN`) and Gaussian strain noise per core at the sigma that
    implies ``sigma`` [1/m] for the curvature (:meth:`torchrod.sensors.Fibre.curvature_sigma`), turned back by the
    fibre's least squares."""
    g = torch.Generator().manual_seed(seed + 7)
    N, G, _ = clean.shape
    common = COMMON_STRAIN * (2.0 * torch.rand(N, G, generator=g, dtype=clean.dtype) - 1.0)
    strain_sigma = sigma / fibre.curvature_sigma(1.0)
    noise = strain_sigma * torch.randn(N, G, fibre.num_cores, generator=g, dtype=clean.dtype)
    return fibre.curvature(fibre.strain(clean, common) + noise)


class WavelengthInput(NamedTuple):
    """``--input wavelength``: readings pass through this fibre's peak wavelengths (:func:`through_wavelengths`)."""

    fibre: Any


def through_sensor(clean: torch.Tensor, sigma: float, sensor: Any, seed: int) -> torch.Tensor:
    """:func:`through_wavelengths` for a :class:`WavelengthInput`, else :func:`through_fibre` (core strains)."""
    if isinstance(sensor, WavelengthInput):
        return through_wavelengths(clean, sigma, sensor.fibre, seed)
    return through_fibre(clean, sigma, sensor, seed)


def evaluation_wavelength_fibre(rod: Rod) -> Any:
    """The fibre of ``--input wavelength``: the rod's when its fibre has a wavelength section, else the cores of
    the rod's fibre (or :data:`EVALUATION_FIBRE`) read through the physics route with the reference wavelengths
    :data:`EVALUATION_REFERENCE_NM`, the same on every core."""
    from ...sensors import Fibre

    if rod.fibre is not None and rod.fibre.wavelength is not None:
        return rod.fibre
    cores = rod.fibre.cores if rod.fibre is not None and rod.fibre.cores else EVALUATION_FIBRE
    first, step = EVALUATION_REFERENCE_NM
    reference = [[first + step * g] * len(cores) for g in range(rod.num_gratings)]
    return Fibre(cores=cores, wavelength={"reference": reference})


def through_wavelengths(clean: torch.Tensor, sigma: float, fibre: Any, seed: int) -> torch.Tensor:
    """(N, G, 2) clean curvature [1/m] -> the curvature read from the fibre's peak wavelengths: the shifts the bend
    gives (:meth:`torchrod.sensors.Fibre.bending_shift`) plus a temperature per grating (an apparent common strain
    uniform in +-:data:`COMMON_STRAIN`, :meth:`~torchrod.sensors.Fibre.temperature_shift`) and Gaussian wavelength
    noise per core at the sigma whose implied curvature sigma, the largest over the gratings, is ``sigma`` [1/m]
    (as ``--wavelength-noise`` weighs the fit), added to the reference when there is one and turned back by the
    fibre's conversion (:meth:`~torchrod.sensors.Fibre.wavelength_curvature`)."""
    g = torch.Generator().manual_seed(seed + 11)
    N, G, _ = clean.shape
    common = COMMON_STRAIN * (2.0 * torch.rand(N, G, generator=g, dtype=clean.dtype) - 1.0)
    wavelength_sigma = sigma / max(fibre.wavelength_sigmas(1.0))
    noise = wavelength_sigma * torch.randn(N, G, fibre.num_cores, generator=g, dtype=clean.dtype)
    shift = fibre.bending_shift(clean) + fibre.temperature_shift(common) + noise
    reference = fibre.reference_m()
    if reference is not None:  # as read: absolute wavelengths, the reference subtracted
        ref = torch.tensor(reference, dtype=clean.dtype)
        shift = (ref + shift) - ref
    return fibre.wavelength_curvature(shift)


def _estimate(rod, curvature, mask, sigma, max_forces, noise_known, batch_size):
    """Estimate the readings in batches; the results and the wall time of the estimation alone [s]."""
    estimator = Estimator(rod, EstimatorOptions(max_forces=max_forces, noise=sigma if noise_known else None))
    estimator.estimate(curvature[:1], mask[:1])  # warm-up: first-call costs
    results = []
    start = time.perf_counter()
    for b0 in range(0, curvature.shape[0], batch_size):
        results.append(estimator.estimate(curvature[b0 : b0 + batch_size], mask[b0 : b0 + batch_size]))
    return results, time.perf_counter() - start


def zero_cell(
    rod: Rod,
    sigma: float,
    count: int,
    *,
    seed: int = 0,
    max_forces: int = 3,
    noise_known: bool = True,
    batch_size: int = 500,
    fibre: Any = None,
) -> dict[str, Any]:
    """``count`` readings of an untouched rod (its unloaded shape, zero unless precurved, and Gaussian noise
    ``sigma``): how often the count is 0."""
    g = torch.Generator().manual_seed(seed * 1000 + round(100 * sigma) + 1)
    zero = _unloaded(rod).expand(count, rod.num_gratings, 2)
    if fibre is not None:
        curvature = through_sensor(zero, sigma, fibre, seed * 1000 + round(100 * sigma) + 1)
    else:
        curvature = zero + sigma * torch.randn(count, rod.num_gratings, 2, generator=g, dtype=torch.float64)
    return _forceless_cell(rod, curvature, sigma, 0, "0", max_forces, noise_known, batch_size)


def _unloaded(rod: Rod) -> torch.Tensor:
    """(1, G, 2) what the gratings read on the unloaded rod [1/m]: its intrinsic curvature (zero when straight)."""
    return rod.unloaded_curvature().unsqueeze(0)


def _forceless_cell(rod, curvature, sigma, k, row, max_forces, noise_known, batch_size) -> dict[str, Any]:
    """The metrics of readings that carry no true forces (k = 0: none; -1: not made of forces at all)."""
    count = curvature.shape[0]
    mask = torch.ones(count, rod.num_gratings, dtype=torch.bool)
    results, elapsed = _estimate(rod, curvature, mask, sigma, max_forces, noise_known, batch_size)
    empty = torch.zeros(count, 0, dtype=torch.float64)
    out = cell_metrics(results, empty, empty.unsqueeze(-1).expand(count, 0, 2), k)
    out.update(forces=k if k >= 0 else None, noise=sigma, time_ms=1e3 * elapsed / count, row=row)
    return out


def unexplainable(rod: Rod, count: int, sigma: float, seed: int = 0, fibre: Any = None) -> torch.Tensor:
    """(count, G, 2) readings [1/m] no few point forces produce, plus noise ``sigma``.

    Between point forces the bending moment is linear in s (small deflection), so h forces give a curvature along
    the gratings made of h + 1 straight pieces; these readings change slope at nearly every grating: in turn
    alternating signs at successive gratings, a sine wave of period three grating spacings, and independent random
    values per grating; amplitude 1 to 10 1/m in a random direction. (A constant curvature or one growing toward
    the tip is not among them: a force couple beyond the last grating, or two opposed forces, makes those.) On a
    precurved rod they are changes from its unloaded shape."""
    g = torch.Generator().manual_seed(seed * 1000 + round(100 * sigma) + 2)
    G = rod.num_gratings
    k = torch.arange(G, dtype=torch.float64)
    kind = torch.arange(count) % 3
    phase = 2.0 * math.pi * torch.rand(count, 1, generator=g, dtype=torch.float64)
    shapes = torch.where(
        (kind == 0)[:, None],
        (-1.0) ** k,
        torch.where(
            (kind == 1)[:, None],
            torch.sin(2.0 * math.pi * k / 3.0 + phase),
            2.0 * torch.rand(count, G, generator=g, dtype=torch.float64) - 1.0,
        ),
    )
    amp = 1.0 + 9.0 * torch.rand(count, generator=g, dtype=torch.float64)
    ang = 2.0 * math.pi * torch.rand(count, generator=g, dtype=torch.float64)
    direction = torch.stack([torch.cos(ang), torch.sin(ang)], -1)  # (count, 2)
    clean = (amp[:, None] * shapes)[:, :, None] * direction[:, None, :] + _unloaded(rod)
    if fibre is not None:
        return through_sensor(clean, sigma, fibre, seed * 1000 + round(100 * sigma) + 2)
    return clean + sigma * torch.randn(count, G, 2, generator=g, dtype=torch.float64)


def misfit_cell(
    rod: Rod,
    sigma: float,
    count: int,
    *,
    seed: int = 0,
    max_forces: int = 3,
    noise_known: bool = True,
    batch_size: int = 500,
    fibre: Any = None,
) -> dict[str, Any]:
    """``count`` :func:`unexplainable` readings: how often the verdict is ``misfit``."""
    curvature = unexplainable(rod, count, sigma, seed, fibre)
    return _forceless_cell(rod, curvature, sigma, -1, "unexpl.", max_forces, noise_known, batch_size)


def cell_metrics(results: list[EstimateResult], s_true: torch.Tensor, f_true: torch.Tensor, k: int) -> dict[str, Any]:
    """Count accuracy, statuses, and force / location errors of estimates against the truth.

    Args:
        results: estimates of the readings, in order (concatenated).
        s_true: (N, >= k) true locations [m] (reported coordinates), sorted; f_true: (N, >= k, 2) [N].
        k: the true count (0: none; -1: no count is right, the readings are not made of forces).
    """
    num = torch.cat([r.num_forces for r in results])
    s_est = torch.cat([r.forces.s for r in results])
    f_est = torch.cat([r.forces.f for r in results])
    statuses = [s for r in results for s in r.statuses]
    ok = num == k
    n = num.shape[0]

    def frac(x):
        return float(x.double().mean()) if x.numel() else math.nan

    strong = (
        torch.linalg.vector_norm(f_true[:, :k], dim=-1).amin(dim=1) >= STRONG
        if k > 0
        else torch.ones(n, dtype=torch.bool)
    )
    out: dict[str, Any] = {
        "readings": n,
        "count_accuracy": frac(ok) if k >= 0 else math.nan,
        "count_accuracy_strong": frac(ok[strong]) if k >= 0 and bool(strong.any()) else math.nan,
        "not_ok": sum(s != "ok" for s in statuses) / n if n else math.nan,
        "misfit": sum(s == "misfit" for s in statuses) / n if n else math.nan,
        "poorly_determined": sum(s == "poorly_determined" for s in statuses) / n if n else math.nan,
    }
    names = ("median", "p90", "rms")
    if k > 0 and bool(ok.any()):
        ts, tf = s_true[ok][:, :k], f_true[ok][:, :k]
        es, ef = s_est[ok][:, :k], f_est[ok][:, :k]
        f_err = (torch.linalg.vector_norm(ef - tf, dim=-1) / torch.linalg.vector_norm(tf, dim=-1)).flatten() * 100
        s_err = (es - ts).abs().flatten() * 1e3
        for label, err in (("force_error", f_err), ("location_error", s_err)):
            out.update(
                {
                    f"{label}_median": float(err.median()),
                    f"{label}_p90": float(err.quantile(0.9)),
                    f"{label}_rms": float(err.pow(2).mean().sqrt()),
                }
            )
    else:
        out.update({f"{label}_{m}": math.nan for label in ("force_error", "location_error") for m in names})
    return out


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    if args.count_per_cell < 1:
        raise ValueError(f"--count-per-cell must be >= 1, got {args.count_per_cell}")
    if args.max_forces < 1:
        raise ValueError(f"--max-forces must be >= 1, got {args.max_forces}")
    if len(args.force_range) != 2 or not 0 < args.force_range[0] <= args.force_range[1]:
        raise ValueError(f"--force-range must be two magnitudes low,high [N], got {args.force_range}")
    from ...errors import OptionsError
    from ...io.quantities import MAX_CURVATURE

    if max(args.noise) > MAX_CURVATURE:
        raise OptionsError(
            f"--noise sigmas must be at most {MAX_CURVATURE:g} 1/m, the largest curvature a reading may carry, got "
            f"{max(args.noise):g}"
        )
    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    if (args.large_bends or args.max_strain is not None) and not args.recovery:
        raise ValueError("--large-bends and --max-strain go with --recovery N")
    if args.max_strain is not None and not (args.large_bends and 0.0 < args.max_strain < 1.0):
        raise ValueError(f"--max-strain goes with --large-bends and must lie in (0, 1), got {args.max_strain}")
    if args.recovery:
        return _recovery(rod, args.recovery, args.seed, args.json, args.large_bends, args.max_strain)
    fibre: Any = None  # a Fibre (strain) or a WavelengthInput (wavelength)
    if args.input == "strain":
        from ...sensors import Fibre

        fibre = rod.fibre if rod.fibre is not None and rod.fibre.cores else Fibre(cores=EVALUATION_FIBRE)
        if not args.json:
            cores = ", ".join(f"({1e6 * x:.1f}, {1e6 * y:.1f})" for x, y in fibre.cores)
            print(
                f"# readings as core strains of a fibre with cores at {cores} um, common strain within "
                f"+-{COMMON_STRAIN:g}, strain sigma = sigma x {1.0 / fibre.curvature_sigma(1.0):.3g} m"
            )
    if args.input == "wavelength":
        wavelength_fibre = evaluation_wavelength_fibre(rod)
        fibre = WavelengthInput(wavelength_fibre)
        if not args.json:
            per_pm = max(wavelength_fibre.wavelength_sigmas(WAVELENGTH_UNITS["pm"]))
            route = (
                "calibration matrices of the rod file"
                if wavelength_fibre.route == "calibration"
                else "physics (cores at "
                + ", ".join(f"({1e6 * x:.1f}, {1e6 * y:.1f})" for x, y in wavelength_fibre.cores)
                + f" um, p_e {wavelength_fibre.wavelength.photoelastic:g})"
            )
            print(
                f"# readings as peak wavelengths through the {route}, a temperature per grating (common strain "
                f"within +-{COMMON_STRAIN:g}), wavelength sigma = sigma x {1.0 / per_pm:.4g} pm per 1/m"
            )
    bending = math.radians(args.max_bending_deg) if args.max_bending_deg > 0 else math.inf
    lo = args.s_min if args.s_min is not None else rod.gratings[1] if rod.num_gratings > 1 else None
    if not args.json:
        where = f"s in [{lo * 1e3:.1f}, {rod.length * 1e3:.1f}] mm" if lo is not None else "s default range"
        print(
            f"# {args.count_per_cell} readings per row; forces {args.force_range[0]:g}-{args.force_range[1]:g} N, "
            f">= {args.min_separation * 1e3:g} mm apart, {where} (nb: the most proximal within 20 mm of the 2nd "
            f"grating), bending <= {args.max_bending_deg:g} deg; "
            f"sigma {'given to' if args.estimator_noise == 'known' else 'estimated by'} the estimator; seed {args.seed}"
        )
        head = (
            "forces",
            "noise",
            "n",
            "count ok",
            "ok >=0.2N",
            "F med",
            "F p90",
            "F rms",
            "s med",
            "s p90",
            "s rms",
            "not ok",
            "misfit",
            "ms/read",
        )
        units = ("", "[1/m]", "", "[%]", "[%]", "[%]", "[%]", "[%]", "[mm]", "[mm]", "[mm]", "[%]", "[%]", "")
        widths = (7, 6, 5, 9, 10, 7, 7, 7, 7, 7, 7, 7, 7, 8)
        print(" ".join(f"{h:>{w}}" for h, w in zip(head, widths, strict=False)))
        print(" ".join(f"{u:>{w}}" for u, w in zip(units, widths, strict=False)))
    common = dict(
        seed=args.seed,
        max_forces=args.max_forces,
        noise_known=args.estimator_noise == "known",
        batch_size=args.batch_size,
        fibre=fibre,
    )
    cells: list[tuple[str, int | None]] = [("zero", 0)] if "zero" in args.rows else []
    if "forces" in args.rows:
        cells += [("k", k) for k in range(1, args.max_forces + 1)]
    if "near-base" in args.rows:
        cells += [("near base", k) for k in range(1, args.max_forces + 1)]
    if "unexplainable" in args.rows:
        cells += [("unexplainable", None)]
    for kind, k in cells:
        for sigma in args.noise:
            if kind == "zero":
                m = zero_cell(rod, sigma, args.count_per_cell, **common)
            elif kind == "unexplainable":
                m = misfit_cell(rod, sigma, args.count_per_cell, **common)
            else:
                assert k is not None  # only the unexplainable row has no count
                m = evaluate_cell(
                    rod,
                    k,
                    sigma,
                    args.count_per_cell,
                    force_range=(args.force_range[0], args.force_range[1]),
                    min_separation=args.min_separation,
                    s_min=lo,
                    max_bending=bending,
                    near_base=kind == "near base",
                    **common,
                )
            if args.json:
                print(
                    json.dumps(
                        {key: (v if not isinstance(v, float) or math.isfinite(v) else None) for key, v in m.items()}
                    )
                )
            else:

                def pct(v):
                    return "-" if not math.isfinite(v) else f"{100 * v:.1f}"

                def num(v):
                    return "-" if not math.isfinite(v) else f"{v:.2f}"

                cols = (
                    m["row"],
                    f"{sigma:g}",
                    str(m["readings"]),
                    pct(m["count_accuracy"]),
                    pct(m["count_accuracy_strong"]),
                    num(m["force_error_median"]),
                    num(m["force_error_p90"]),
                    num(m["force_error_rms"]),
                    num(m["location_error_median"]),
                    num(m["location_error_p90"]),
                    num(m["location_error_rms"]),
                    pct(m["not_ok"]),
                    pct(m["misfit"]),
                    num(m["time_ms"]),
                )
                print(" ".join(f"{c:>{w}}" for c, w in zip(cols, widths, strict=False)))
            sys.stdout.flush()
    return 0


def _recovery(rod: Rod, count: int, seed: int, as_json: bool, elastic: bool, max_strain: float | None) -> int:
    """``--recovery N``: the clean-recovery study (:mod:`torchrod.eval.recovery`), its verdicts per stratum and
    every case that is missed or wrong (``elastic``: up to the elastic limit, ``--large-bends``)."""
    from ...eval import recovery

    if count < 1:
        raise ValueError(f"--recovery must be >= 1, got {count}")
    strain = recovery.ELASTIC_STRAIN if max_strain is None else max_strain
    start = time.perf_counter()
    rows = recovery.run(rod, count, seed=seed, elastic=elastic, max_strain=strain)
    elapsed = time.perf_counter() - start
    summary = recovery.summarise(rows)
    failures = [r for r in rows if r["verdict"] in ("missed", "wrong")]
    if as_json:
        print(json.dumps({"summary": summary, "failures": failures, "seconds": elapsed}))
        return 0
    decided = sum(r["decidable"] for r in rows)
    envelope = f"up to a bending strain of {strain:g}" if elastic else "up to 90 degrees of turning"
    print(
        f"# {count} clean cases (seed {seed}) {envelope}: {decided} the data decide, "
        f"{sum(r['straddle'] for r in rows)} with a pair straddling a grating; {elapsed:.1f} s"
    )
    print(f"{'stratum':<10} {'cases':>6} " + " ".join(f"{v:>13}" for v in recovery.VERDICTS))
    for key in (*(recovery.ELASTIC_STRATA if elastic else recovery.STRATA), "all"):
        cell = summary.get(key, {"cases": 0})
        print(f"{key:<10} {cell['cases']:>6} " + " ".join(f"{cell.get(v, 0):>13}" for v in recovery.VERDICTS))
    for r in failures:
        truth = ", ".join(f"{1e3 * s:.3f} mm {math.hypot(*f):.3f} N" for s, f in r["truth"])
        est = ", ".join(f"{1e3 * s:.3f} mm {math.hypot(*f):.3f} N" for s, f in r["estimate"])
        print(
            f"{r['verdict']}: {r['stratum']}, status {r['status']}, missing gratings {r['missing']}; "
            f"truth [{truth}]; estimate [{est}]"
        )
    return 0
