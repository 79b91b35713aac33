"""Jig calibration of a fibre's wavelength-to-curvature matrices (``torchrod calibrate --fibre``).

A jig holds the fibre at a known constant curvature kappa [1/m] with a known bend direction theta [rad] (measured
in the body frame from d1 towards d2), so every grating reads u = kappa (cos theta, sin theta). From readings taken
on several jigs (and at several bend directions), each grating's 2 x C matrix A_g of the calibration route,
u = A_g (d - mean(d)) (:mod:`torchrod.sensors`), is fitted by least squares:

* per grating, the centred shifts D (one row d - mean(d) per reading, [m]) and the jig curvatures U (one row per
  reading) give A_g^T = D^+ U, with D^+ the pseudo-inverse of D truncated to its two largest singular values: a
  bend moves the C shifts within a plane (u_x and u_y), so a third direction holds only noise and is given no
  weight. The fitted rows are orthogonal to (1, ..., 1): the common shift (temperature) takes no part;
* the residual per grating is the RMS of U - D A_g^T [1/m];
* leave-one-jig-out: each jig (by its ``name``, else its curvature) is left out in turn, the matrices fitted on
  the others, and the left-out readings predicted: the RMS of that prediction, per jig and per grating [1/m], is
  what the calibration is worth on a curvature it was not fitted to; divided by the RMS of the jig curvatures'
  components over the readings it was taken on, it is the grating's relative error (a fraction of the signal,
  noise included, so on the safe side), which the rod written takes as its ``calibration_error`` (the estimator
  weighs each grating's values by it: docs/guides/calibrate.md);
* each grating's gain, sqrt(s_1 s_2) of A_g's singular values [1/m per nm], is compared with the median of the
  gratings' gains and, where the rod file gives the cores, with the physics route's gain
  (1 / (lambda_ref (1 - p_e)) over the cores' geometry); a grating off by more than ``tolerance`` (a fraction,
  default :data:`GAIN_TOLERANCE`) is warned about: a swapped core, a wrong jig tag, a broken grating.

The readings need two bend directions at least (90 degrees apart is best) at a nonzero curvature. Readings of
absolute wavelengths use the rod file's reference; a rod without one takes the mean of the straight jig's readings
(curvature 0) as its reference and writes it with the calibration.

Readings (JSON lines): ``{"id": ..., "wavelength": [[l_1, ..., l_C] or null, ...], "jig": {"curvature": kappa,
"angle": theta, "name": "J1"}}`` (or ``"wavelength_shift"``); ``curvature`` in the readings' curvature unit
(``--curvature-unit``, default 1/m), ``angle`` [rad] (may be left out at curvature 0), ``name`` optional. CSV: the
columns ``lambda_K_C`` (or ``dlambda_K_C``), ``jig_curvature``, ``jig_angle`` and ``jig``.
"""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from .errors import ReadingError
from .rod import MAX_CALIBRATION_ERROR, Rod

__all__ = [
    "FIT_TOLERANCE",
    "GAIN_TOLERANCE",
    "MAX_ROTATION",
    "PHYSICS_FACTOR",
    "JigCalibration",
    "JigData",
    "calibrate_fibre",
    "fit_matrices",
    "read_jig_readings",
    "report",
]

GAIN_TOLERANCE = 0.25
"""A grating whose gain differs from the median of the gratings', or from the physics route's, by more than this
fraction is warned about."""

FIT_TOLERANCE = 0.1
"""A grating whose fit leaves a residual, or whose leave-one-jig-out prediction an error, above this fraction of the
jig curvatures' RMS (per component) refuses the calibration: the shifts do not follow the jigs (random data,
readings of another fibre, jigs tagged with wrong angles). Good jig readings leave well under 1 % (2 pm of noise
per core is about 0.04 1/m against curvatures of 5 to 20 1/m)."""

PHYSICS_FACTOR = 3.0
"""Where the rod file gives the cores and a reference: a grating whose gain differs from the physics route's by more
than this factor either way refuses the calibration (a unit error: jig curvatures in 1/cm read as 1/m are 100x
off); a smaller difference up to it is only warned about (:data:`GAIN_TOLERANCE`)."""

MAX_ROTATION = math.pi / 4
"""[rad] Where the rod file gives the cores and a reference: a grating whose fitted matrix turns a bend by more than
this from the physics route's direction, or mirrors it, refuses the calibration (jig angles off by pi, measured
from d2 instead of d1, or turning the other way; cores in another order)."""

_RANK = 1e-6  # second singular value / first below which the readings span one bend direction only


@dataclass(frozen=True)
class JigData:
    """R jig readings.

    Attributes:
        shifts: (R, G, C) wavelength shifts [m] from the reference, NaN at a missing grating.
        curvature: (R, 2) the jig's (u_x, u_y) [1/m].
        jigs: per reading the jig it was taken on (its name, else its curvature [1/m]).
        ids: the readings' ids.
        reference: (G, C) [m] the reference the shifts are taken from, when it came from the straight jig (else
            None: the rod file's, or shifts given as such).
    """

    shifts: torch.Tensor
    curvature: torch.Tensor
    jigs: tuple[Any, ...]
    ids: tuple[Any, ...] = ()
    reference: torch.Tensor | None = None


@dataclass(frozen=True)
class JigCalibration:
    """The fitted matrices and their checks (module docstring).

    Attributes:
        matrices: (G, 2, C) A_g [1/m per m] (SI; :meth:`apply` writes them per nm).
        residual: (G,) RMS curvature residual of each grating's fit [1/m].
        readings: (G,) readings each grating was fitted on.
        leave_one_out: {jig: RMS [1/m] of its readings predicted from the others' fit, None when the others do not
            determine the matrices}.
        leave_one_out_grating: (G,) per grating, the RMS of its left-out predictions over all jigs [1/m] (NaN when
            no jig could be left out).
        relative_error: (G,) ``leave_one_out_grating`` over the RMS of the jig curvatures' components on the same
            readings: each grating's relative calibration error (NaN where not known).
        gains: (G,) sqrt(s_1 s_2) of each A_g [1/m per nm].
        physics_gains: (G,) the physics route's gains [1/m per nm], or None without the cores or a reference.
        tolerance: the fraction the warnings use.
        warnings: one sentence per grating whose gain is off.
        reference: (G, C) [m] from the straight jig, to be written with the calibration; None to keep the rod's.
        problems: why the calibration cannot be stood behind (:data:`FIT_TOLERANCE`, :data:`PHYSICS_FACTOR`,
            :data:`MAX_ROTATION`; no jig that can be left out); ``torchrod calibrate --fibre`` then writes no rod
            without ``--force``. Empty when it can.
    """

    matrices: torch.Tensor
    residual: torch.Tensor
    readings: torch.Tensor
    leave_one_out: dict[Any, float | None]
    leave_one_out_grating: torch.Tensor
    gains: torch.Tensor
    physics_gains: torch.Tensor | None
    tolerance: float
    warnings: tuple[str, ...]
    reference: torch.Tensor | None = None
    problems: tuple[str, ...] = ()
    relative_error: torch.Tensor | None = None

    def apply(self, rod: Rod) -> Rod:
        """``rod`` with ``fibre.wavelength.calibration`` set to the fitted matrices (1/m per nm), its reference from
        the straight jig when it had none, and its ``calibration_error`` the gratings' relative errors where every
        grating has one (else the rod's own)."""
        from .sensors import WAVELENGTH_UNITS, Fibre, Wavelength

        nm = WAVELENGTH_UNITS["nm"]
        calibration = (self.matrices * nm).tolist()
        fibre = rod.fibre if rod.fibre is not None else Fibre()
        old = fibre.wavelength
        reference = old.reference if old is not None else None
        if self.reference is not None:
            reference = (self.reference / nm).tolist()
        wavelength = Wavelength(
            reference=reference,
            calibration=calibration,
            photoelastic=old.photoelastic if old is not None else Wavelength.photoelastic,
            peaks=old.peaks if old is not None else "by-core",
        )
        changes: dict[str, Any] = {"fibre": fibre.with_(wavelength=wavelength)}
        rel = self.relative_error
        if rel is not None and bool(torch.isfinite(rel).all()):
            changes["calibration_error"] = [min(float(x), MAX_CALIBRATION_ERROR) for x in rel]
        return rod.with_(**changes)


# ---------------------------------------------------------------------------------------------------- reading
def _jig(obj: Any, scale: float) -> tuple[float, float, Any]:
    """(kappa [1/m], theta [rad], name or None) of a reading's ``jig`` object; ``ValueError`` naming the field."""
    from .io.numbers import as_number
    from .io.reading import check_id
    from .io.values import describe

    if "jig" not in obj:
        raise ReadingError('missing \'jig\' (the jig it was read on: {"curvature": kappa, "angle": theta})')
    jig = obj["jig"]
    if not isinstance(jig, dict):
        raise ReadingError(f'jig must be an object {{"curvature": kappa, "angle": theta}}, got {describe(jig)}')  # noqa: TRY004
    unknown = sorted(str(k) for k in jig if k not in ("curvature", "angle", "name"))
    if unknown:
        raise ReadingError(f"jig has unknown key(s) {unknown}; the known keys are curvature, angle, name")
    if "curvature" not in jig:
        raise ReadingError("jig is missing 'curvature' (the jig's constant curvature, >= 0)")
    kappa = as_number(jig["curvature"], "jig.curvature")
    if kappa < 0.0:
        raise ReadingError(
            f"jig.curvature is a magnitude and must be >= 0, got {kappa!r} (the angle gives the direction)"
        )
    if "angle" not in jig and kappa != 0.0:
        raise ReadingError("jig is missing 'angle' (the bend direction [rad] from d1 towards d2)")
    theta = as_number(jig.get("angle", 0.0), "jig.angle", bound=1e6, unit="rad")
    name = check_id(jig.get("name"))
    return kappa * scale, theta, name


def read_jig_readings(
    path: str | os.PathLike, rod: Rod, fmt: str = "auto", *, quantity: str = "wavelength", max_line: int | None = None
) -> JigData:
    """Read jig readings (module docstring) from ``path`` (``"-"``: standard input) in a format of
    :data:`torchrod.io.sources.FORMATS`; every line must be usable (a calibration from a silently thinned set
    would mislead): ``ReadingError`` naming the bad lines otherwise. ``max_line``: the longest line read [bytes]
    (None: the rod's, :func:`torchrod.io.sources.line_limit`)."""
    from .io.quantities import wavelength_shifts, wavelength_values
    from .io.sources import iter_records, unusable_lines

    fibre = rod.fibre
    if fibre is None or (fibre.wavelength is None and fibre.num_cores == 0):
        raise ReadingError(
            'jig calibration needs the rod file\'s "fibre" with the cores\' count: a "wavelength" section (reference) '
            'or "cores"'
        )
    G, C = rod.num_gratings, fibre.num_cores
    scale = fibre.scale("curvature_unit")
    has_reference = fibre.wavelength is not None and fibre.wavelength.reference is not None

    def parse(obj: Any) -> tuple[list[Any], bool, tuple[float, float, Any]]:
        keys = [k for k in ("wavelength", "wavelength_shift") if k in obj]
        others = [k for k in ("curvature", "strain", "curvature_polar") if k in obj]
        if others or len(keys) != 1:
            raise ReadingError("a jig reading gives exactly one of wavelength, wavelength_shift")
        key = keys[0]
        absolute = key == "wavelength"
        jig = _jig(obj, scale)
        if absolute and not has_reference:
            values = wavelength_values(obj[key], G, C, fibre, key)
        elif fibre.wavelength is not None:
            values = wavelength_shifts(obj[key], G, fibre, key)
        else:
            values = wavelength_values(obj[key], G, C, fibre, key, shift=True)
        return values, absolute and not has_reference, jig

    name = "standard input" if os.fspath(path) == "-" else os.fspath(path)
    rows, bad, ids = [], [], []
    records = iter_records(path, G, parse, fmt, quantity=quantity, fibre=fibre, max_line=max_line)
    for record in records:
        if not record.ok:
            bad.append(record.error)
            continue
        rows.append(record.value)
        ids.append(record.id)
    if bad:
        raise unusable_lines(name, bad)
    if not rows:
        raise ReadingError(f"{name}: no jig readings")
    kinds = {raw for _, raw, _ in rows}
    if len(kinds) > 1:
        raise ReadingError(f"{name}: give every reading as wavelength, or every one as wavelength_shift, not both")
    nan = math.nan
    shifts = torch.tensor(
        [[[nan] * C if g is None else g for g in values] for values, _, _ in rows], dtype=torch.float64
    )
    curvature = torch.tensor([[k * math.cos(a), k * math.sin(a)] for _, _, (k, a, _) in rows], dtype=torch.float64)
    jigs = tuple(n if n is not None else k for _, _, (k, _, n) in rows)
    reference = None
    if kinds == {True}:
        straight = torch.tensor([k == 0.0 for _, _, (k, _, _) in rows])
        if not bool(straight.any()):
            raise ReadingError(
                f"{name}: the readings give absolute wavelengths and the rod file's fibre has no reference: add "
                "readings on a straight jig (curvature 0), whose mean becomes the reference, or give the reference"
            )
        reference = torch.nanmean(shifts[straight], dim=0)
        if bool(torch.isnan(reference).any()):
            g = int(torch.isnan(reference).any(-1).nonzero()[0])
            raise ReadingError(f"{name}: grating {g + 1} has no reading on the straight jig to take its reference from")
        shifts = shifts - reference
    return JigData(shifts, curvature, jigs, tuple(ids), reference)


# ---------------------------------------------------------------------------------------------------- fitting
def _fit_one(d: torch.Tensor, u: torch.Tensor, what: str) -> torch.Tensor:
    """One grating's A (2 x C) [1/m per m] from its shifts ``d`` (n, C) [m] and curvatures ``u`` (n, 2): the
    rank-2 least squares of the module docstring; ``ReadingError`` when the readings span less than a plane."""
    centred = d - d.mean(-1, keepdim=True)
    if centred.shape[0] < 2:
        raise ReadingError(f"{what}: {centred.shape[0]} reading(s); a 2 x C matrix needs two bend directions at least")
    w, s, vh = torch.linalg.svd(centred, full_matrices=False)
    bends = torch.linalg.svdvals(u)  # the jig curvatures must span a plane too, or a row of A is left zero
    if s.numel() < 2 or not s[1] > _RANK * s[0] or not bends[1] > _RANK * bends[0]:
        raise ReadingError(
            f"{what}: the readings span one bend direction only; add readings at another angle (90 degrees apart is "
            "best) at a nonzero curvature"
        )
    a_t = vh[:2].T @ ((w[:, :2].T @ u) / s[:2, None])  # (C, 2)
    return a_t.T


def fit_matrices(
    shifts: torch.Tensor, curvature: torch.Tensor, keep: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per grating, A_g (G, 2, C) [1/m per m] fitted on the readings ``keep`` (R,) (all by default) where the
    grating was read, with each grating's RMS residual (G,) [1/m] and reading count (G,)."""
    R, G, C = shifts.shape
    keep = torch.ones(R, dtype=torch.bool) if keep is None else keep
    mats, rms, counts = [], [], []
    for g in range(G):
        rows = keep & ~torch.isnan(shifts[:, g]).any(-1)
        d, u = shifts[rows, g], curvature[rows]
        a = _fit_one(d, u, f"grating {g + 1}")
        resid = u - (d - d.mean(-1, keepdim=True)) @ a.T
        mats.append(a)
        rms.append(resid.pow(2).mean().sqrt())
        counts.append(int(rows.sum()))
    return torch.stack(mats), torch.stack(rms), torch.tensor(counts)


def _gain(a: torch.Tensor) -> torch.Tensor:
    """sqrt(s_1 s_2) of each (..., 2, C) matrix."""
    s = torch.linalg.svdvals(a)
    return (s[..., 0] * s[..., 1]).sqrt()


def calibrate_fibre(rod: Rod, data: JigData, tolerance: float = GAIN_TOLERANCE) -> JigCalibration:
    """Fit the matrices from jig readings and check them (module docstring)."""
    from .errors import OptionsError
    from .sensors import PHOTOELASTIC, WAVELENGTH_UNITS, Fibre

    if not 0.0 < tolerance < float("inf"):
        raise OptionsError(f"the gain tolerance must be a positive fraction, got {tolerance!r}")
    nm = WAVELENGTH_UNITS["nm"]
    matrices, residual, counts = fit_matrices(data.shifts, data.curvature)
    G = matrices.shape[0]
    jigs = list(dict.fromkeys(data.jigs))
    lojo: dict[Any, float | None] = {}
    sq = torch.zeros(G, dtype=torch.float64)
    n = torch.zeros(G, dtype=torch.float64)
    signal = torch.zeros(G, dtype=torch.float64)  # the jig curvatures' squares on the readings left out
    for jig in jigs:
        out = torch.tensor([j == jig for j in data.jigs])
        try:
            mats, _, _ = fit_matrices(data.shifts, data.curvature, ~out)
        except ReadingError:
            lojo[jig] = None
            continue
        d = data.shifts[out]  # (r, G, C)
        pred = torch.einsum("gjc,rgc->rgj", mats, d - d.mean(-1, keepdim=True))
        err = (pred - data.curvature[out][:, None, :]).pow(2).sum(-1)  # (r, G)
        read = ~torch.isnan(err)
        lojo[jig] = float(err[read].sum().div(2 * read.sum()).sqrt()) if bool(read.any()) else None
        sq += torch.where(read, err, 0.0).sum(0)
        n += 2 * read.sum(0)
        signal += (read * data.curvature[out].pow(2).sum(-1)[:, None]).sum(0)
    lojo_grating = (sq / n).sqrt()
    relative = lojo_grating / (signal / n).sqrt()
    gains = _gain(matrices) * nm
    physics = phys_maps = None
    reference = data.reference
    old = rod.fibre.wavelength if rod.fibre is not None else None
    if reference is None and old is not None and old.reference is not None:
        assert rod.fibre is not None  # old is its wavelength section
        reference = torch.tensor(rod.fibre.reference_m(), dtype=torch.float64)
    if rod.fibre is not None and rod.fibre.cores and reference is not None:
        pe = old.photoelastic if old is not None else PHOTOELASTIC
        phys = Fibre(cores=rod.fibre.cores, wavelength={"reference": (reference / nm).tolist(), "photoelastic": pe})
        phys_maps = torch.tensor(phys.shift_maps(), dtype=torch.float64)
        physics = _gain(phys_maps) * nm
    median = statistics.median(gains.tolist())
    warnings = []
    for g in range(G):
        off = float(gains[g]) / median - 1.0
        if abs(off) > tolerance:
            warnings.append(
                f"grating {g + 1}'s gain {float(gains[g]):.4g} 1/m per nm is {100 * off:+.0f} % from the gratings' "
                f"median {median:.4g} (tolerance {100 * tolerance:g} %): check its cores' order, its jig readings and "
                "the grating itself"
            )
        if physics is not None:
            off = float(gains[g] / physics[g]) - 1.0
            if abs(off) > tolerance:
                warnings.append(
                    f"grating {g + 1}'s gain {float(gains[g]):.4g} 1/m per nm is {100 * off:+.0f} % from the physics "
                    f"route's {float(physics[g]):.4g} (tolerance {100 * tolerance:g} %): check the cores' positions "
                    "and order, the photoelastic coefficient and the jig curvatures' unit"
                )
    problems = _problems(matrices, residual, lojo, lojo_grating, data.curvature, gains, physics, phys_maps)
    return JigCalibration(
        matrices=matrices,
        residual=residual,
        readings=counts,
        leave_one_out=lojo,
        leave_one_out_grating=lojo_grating,
        gains=gains,
        physics_gains=physics,
        tolerance=tolerance,
        warnings=tuple(warnings),
        reference=data.reference,
        problems=problems,
        relative_error=relative,
    )


def _gratings(which: list[int]) -> str:
    shown = ", ".join(str(g + 1) for g in which[:8]) + (f" and {len(which) - 8} more" if len(which) > 8 else "")
    return f"grating{'s' if len(which) > 1 else ''} {shown}"


def _problems(
    matrices: torch.Tensor,
    residual: torch.Tensor,
    lojo: dict[Any, float | None],
    lojo_grating: torch.Tensor,
    curvature: torch.Tensor,
    gains: torch.Tensor,
    physics: torch.Tensor | None,
    phys_maps: torch.Tensor | None,
) -> tuple[str, ...]:
    """Why the fitted matrices cannot be stood behind (:attr:`JigCalibration.problems`)."""
    problems = []
    scale = float(curvature.pow(2).mean().sqrt())  # the jig curvatures' RMS per component [1/m]
    for name, values, what in (
        (
            "residual",
            residual,
            "the shifts do not follow the jig curvatures (random or shuffled readings, another fibre's, jigs tagged "
            "with wrong angles)",
        ),
        (
            "leave-one-jig-out error",
            lojo_grating,
            "a jig left out is not predicted by the others (a jig with a wrong curvature or angle tag, readings "
            "that do not follow the jigs)",
        ),
    ):
        off = [g for g in range(len(values)) if float(values[g]) > FIT_TOLERANCE * scale]
        if off:
            worst = max(float(values[g]) for g in off)
            problems.append(
                f"{_gratings(off)}: {name} up to {worst:.4g} 1/m, {100 * worst / scale:.0f} % of the jig curvatures' "
                f"RMS {scale:.4g} 1/m (bound {100 * FIT_TOLERANCE:g} %): {what}"
            )
    if lojo and all(v is None for v in lojo.values()):
        problems.append(
            f"no jig of {len(lojo)} can be left out and predicted from the others (every one is needed to determine "
            "the matrices), so nothing checks the fit: add readings on more jigs, at two bend directions or more"
        )
    if physics is not None and phys_maps is not None:
        ratio = gains / physics
        off = [g for g in range(len(ratio)) if not 1 / PHYSICS_FACTOR <= float(ratio[g]) <= PHYSICS_FACTOR]
        if off:
            worst = max((float(ratio[g]) for g in off), key=lambda r: abs(math.log(r)) if r > 0 else math.inf)
            problems.append(
                f"{_gratings(off)}: gain up to {worst:.4g} times the physics route's (bound a factor "
                f"{PHYSICS_FACTOR:g}): check the jig curvatures' unit (--curvature-unit), the readings' wavelength "
                "unit and the cores' positions"
            )
        turned, mirrored = [], []
        worst_angle = 0.0
        for g in range(matrices.shape[0]):
            t = matrices[g] @ torch.linalg.pinv(phys_maps[g])  # (2, 2): the identity for a matrix that agrees
            if float(torch.linalg.det(t)) <= 0.0:
                mirrored.append(g)
                continue
            angle = math.atan2(float(t[1, 0] - t[0, 1]), float(t[0, 0] + t[1, 1]))
            if abs(angle) > MAX_ROTATION:
                turned.append(g)
                worst_angle = max(worst_angle, abs(angle))
        if turned:
            problems.append(
                f"{_gratings(turned)}: the fit turns a bend by up to {math.degrees(worst_angle):.0f} degrees from the "
                f"physics route's direction (bound {math.degrees(MAX_ROTATION):g}): check the jig angles (radians, "
                "from d1 towards d2) and the cores' positions"
            )
        if mirrored:
            problems.append(
                f"{_gratings(mirrored)}: the fit mirrors a bend against the physics route's (one component's sign, "
                "or the cores' order, differs): check the jig angles' sense (from d1 towards d2) and the cores' order"
            )
    return tuple(problems)


def _percent(values: torch.Tensor | None, g: int) -> str:
    """Entry g of ``values`` (fractions) as a percentage, or ``-`` where not known."""
    if values is None or not math.isfinite(float(values[g])):
        return "-"
    return f"{100 * float(values[g]):.2f}%"


def report(result: JigCalibration, data: JigData) -> Sequence[str]:
    """The lines ``torchrod calibrate --fibre`` prints: per grating, the per-jig check, the warnings."""
    G = result.matrices.shape[0]
    jigs = list(dict.fromkeys(data.jigs))
    out = [
        f"{data.curvature.shape[0]} jig readings on {len(jigs)} jigs, {G} gratings x {result.matrices.shape[2]} cores",
        f"{'grating':>7} {'readings':>8} {'residual':>10} {'left out':>10} {'relative':>9} {'gain':>12} "
        f"{'vs median':>10} " + (f"{'vs physics':>10}" if result.physics_gains is not None else ""),
        f"{'':>7} {'':>8} {'[1/m]':>10} {'[1/m]':>10} {'':>9} {'[1/m per nm]':>12} {'':>10}",
    ]
    median = statistics.median(result.gains.tolist())
    for g in range(G):
        line = (
            f"{g + 1:>7} {int(result.readings[g]):>8} {float(result.residual[g]):>10.4g} "
            f"{float(result.leave_one_out_grating[g]):>10.4g} {_percent(result.relative_error, g):>9} "
            f"{float(result.gains[g]):>12.4g} "
            f"{100 * (float(result.gains[g]) / median - 1):>+9.1f}%"
        )
        if result.physics_gains is not None:
            line += f" {100 * (float(result.gains[g] / result.physics_gains[g]) - 1):>+9.1f}%"
        out.append(line)
    for jig, rms in result.leave_one_out.items():
        count = sum(j == jig for j in data.jigs)
        shown = "not determined by the other jigs" if rms is None else f"RMS {rms:.4g} 1/m"
        out.append(f"leave-one-jig-out: jig {jig!r} ({count} readings) predicted from the others: {shown}")
    out.extend(f"warning: {w}" for w in result.warnings)
    return out
