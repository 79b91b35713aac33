"""What a reading gives per grating, and its conversion to curvature [1/m] with the checks of its entries.

A reading gives exactly one of :data:`QUANTITIES`' keys: ``curvature``, per grating ``[ux, uy]`` [1/m] or null;
``strain``: per grating the C core strains ``[eps_1, ..., eps_C]`` of the rod file's multicore ``fibre``
(``|eps| <= MAX_STRAIN``), or null; ``curvature_polar``: per grating ``[kappa, phi]``, the curvature magnitude
(>= 0) and the bend angle [rad] from d1 towards d2, or null; ``wavelength``: per grating the C peak wavelengths,
the rod's ``fibre.wavelength.reference`` subtracted here, or null; ``wavelength_shift``: the C shifts from the
reference, or null. All are turned into (ux, uy) [1/m] here, so everything downstream sees curvature. The sensor
physics (core strains to curvature, a shift through the calibration) is :mod:`torchrod.sensors`'; this module reads
a reading's entries, checks them and names the bad one.

Units
    Values are read in the units the rod's fibre says (:class:`torchrod.sensors.Fibre`: ``curvature_unit``,
    ``strain_unit``, ``wavelength_unit``; the commands' options set them), SI (and nm) without one, and converted
    to SI here; the bounds hold in SI (:data:`MAX_CURVATURE`, :data:`torchrod.sensors.MAX_STRAIN`, a peak within
    :data:`torchrod.sensors.WAVELENGTH_RANGE_NM`, a shift within :data:`torchrod.sensors.MAX_WAVELENGTH_SHIFT`).
    Tensors handed to the estimator (:func:`torchrod.estimate.checks.check_readings`) are always curvature in 1/m.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from ..errors import ReadingError
from ..estimate.checks import MAX_CURVATURE
from ..sensors import DEFAULT_UNITS, UNIT_TABLES
from .numbers import as_number
from .values import describe, quote

__all__ = [
    "MAX_CURVATURE",
    "QUANTITIES",
    "curvature_tensor",
    "polar_curvature",
    "reading_curvature",
    "strain_curvature",
    "wavelength_curvature",
    "wavelength_shifts",
    "wavelength_values",
]


def _missing_hint(what: str) -> str:
    return f"(for a grating without a reading give null in place of the pair {what})"


def _units(fibre: Any, key: str) -> tuple[float, str]:
    """The readings' unit ``key`` (``"curvature_unit"``, ...) as (factor to SI, name): the fibre's, else SI."""
    name = DEFAULT_UNITS[key] if fibre is None else getattr(fibre, key)
    return UNIT_TABLES[key][name], name


def curvature_tensor(
    value: Any, num_gratings: int, what: str = "curvature", *, scale: float = 1.0, unit: str = "1/m"
) -> torch.Tensor:
    """A reading's curvature as a (G, 2) float64 CPU tensor [1/m], a row of NaN per missing grating.

    Args:
        value: a list or tuple of G entries, each ``[ux, uy]`` or None; or a (G, 2) real tensor or array (a row
            of NaN marks a missing grating; a half-NaN row and infinities are refused).
        num_gratings: G.
        scale, unit: the values' unit (``unit``, named in messages) and its factor to 1/m; the bound
            :data:`MAX_CURVATURE` applies to the value in 1/m.
    Raises:
        ValueError: naming the entry and quoting its value (the rules: :mod:`torchrod.io.reading`,
            :mod:`torchrod.io.numbers`).
    """
    G = num_gratings
    if isinstance(value, torch.Tensor) or (
        hasattr(value, "__array__") and hasattr(value, "shape") and not isinstance(value, (list, tuple))
    ):
        return _tensor_rows(value, G, what, scale, unit)
    if not isinstance(value, (list, tuple)):
        raise ReadingError(  # noqa: TRY004 (bad data, one kind of error)
            f"{what} must be an array of {G} [ux, uy] pairs [{unit}] (null for a missing grating), got "
            f"{describe(value)}"
        )
    if len(value) != G:
        raise ReadingError(
            f"{what} holds {len(value)} gratings, the rod has {G}: give one [ux, uy] pair or null per grating, "
            "in the rod file's order"
        )
    limit = MAX_CURVATURE / scale
    nan = math.nan
    flat: list[float] = []  # ux, uy of each grating in turn
    missing = 0
    for k, row in enumerate(value):
        if row is None:
            flat += (nan, nan)
            missing += 1
            continue
        if type(row) is list and len(row) == 2:  # the usual case, checked fast
            a, b = row
            if type(a) is float and type(b) is float and abs(a) <= limit and abs(b) <= limit:
                flat += row
                continue
        where = f"{what}[{k}]"
        if not isinstance(row, (list, tuple)) or len(row) != 2:
            raise ReadingError(f"{where} must be a pair [ux, uy] of numbers [{unit}] or null, got {describe(row)}")
        for j, x in enumerate(row):
            try:
                flat.append(as_number(x, f"{where}[{j}]", bound=limit, unit=unit))
            except ValueError as exc:
                if isinstance(x, float) and math.isnan(x):
                    raise ReadingError(f"{exc} {_missing_hint(where)}") from None
                raise
    if missing == G:  # (a value given is a number: as_number refuses NaN)
        raise ReadingError(f"all gratings are missing: {what} needs at least one [ux, uy] pair")
    # Through NumPy: a quarter of the cost of torch.tensor on a list, for a line's few values.
    out = torch.from_numpy(np.array(flat).reshape(G, 2))
    return out if scale == 1.0 else out * scale


def _tensor_rows(value: Any, G: int, what: str, scale: float = 1.0, unit: str = "1/m") -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        try:
            value = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ReadingError(f"{what} must be a real (G, 2) array, got {quote(value)} ({exc})") from None
    if value.dtype == torch.bool or value.is_complex():
        raise ReadingError(f"{what} must be a real tensor, got {value.dtype}")
    if tuple(value.shape) != (G, 2):
        raise ReadingError(f"{what} must have shape ({G}, 2) for this rod, got {tuple(value.shape)}")
    t = value.detach().to("cpu", torch.float64)
    limit = MAX_CURVATURE / scale
    present = 0
    for k, (a, b) in enumerate(t.tolist()):  # (G, 2) values: a Python loop is cheaper than tensor checks
        if abs(a) <= limit and abs(b) <= limit:
            present += 1
        elif math.isnan(a) and math.isnan(b):
            continue
        elif math.isnan(a) or math.isnan(b):
            raise ReadingError(f"{what}[{k}] has one NaN component: a missing grating is a row of NaN")
        else:
            for j, x in enumerate((a, b)):
                as_number(x, f"{what}[{k}][{j}]", bound=limit, unit=unit)
    if not present:
        raise ReadingError(f"all gratings are missing: {what} needs at least one finite row")
    return t if scale == 1.0 else t * scale


QUANTITIES = {
    "curvature": "curvature",
    "strain": "strain",
    "polar": "curvature_polar",
    "wavelength": "wavelength",
    "wavelength-shift": "wavelength_shift",
}
"""What a reading may give, by its name in options (``--csv-quantity``) and its JSON key."""


def _entries(value: Any, G: int, what: str, shape: str) -> list[Any]:
    if not isinstance(value, (list, tuple)):
        raise ReadingError(
            f"{what} must be an array of {G} {shape} (null for a missing grating), got {describe(value)}"
        )  # noqa: TRY004
    if len(value) != G:
        raise ReadingError(f"{what} holds {len(value)} gratings, the rod has {G}: give one {shape} or null per grating")
    return list(value)


def _converted(pair: tuple[float, float], where: str, source: str) -> list[float]:
    if not (abs(pair[0]) <= MAX_CURVATURE and abs(pair[1]) <= MAX_CURVATURE):
        raise ReadingError(
            f"{where} gives a curvature of {quote(list(pair))} 1/m, beyond the bound of {MAX_CURVATURE:g} 1/m; "
            f"check the units of the {source}"
        )
    return [pair[0], pair[1]]


def strain_curvature(value: Any, num_gratings: int, fibre: Any, what: str = "strain") -> list[Any]:
    """A reading's core strains (one list of C per grating, or None; in the fibre's ``strain_unit``) -> its G
    (ux, uy) pairs [1/m] or None, by the fibre's least squares (:class:`torchrod.sensors.Fibre`). ``ValueError``
    naming the entry."""
    from ..sensors import MAX_STRAIN

    if fibre is None or not fibre.cores:
        raise ReadingError(
            f'{what} needs the rod\'s multicore fibre: add "fibre": {{"cores": [[x, y], ...]}} (core positions [m]) '
            "to the rod file"
        )
    scale, unit = _units(fibre, "strain_unit")
    hint = "strain is dimensionless: 1e-6 is one microstrain" if scale == 1.0 else f"strains are read in {unit}"
    C = fibre.num_cores
    rows: list[Any] = []
    for k, entry in enumerate(_entries(value, num_gratings, what, f"list of {C} core strains")):
        if entry is None:
            rows.append(None)
            continue
        where = f"{what}[{k}]"
        if not isinstance(entry, (list, tuple)) or len(entry) != C:
            raise ReadingError(
                f"{where} must be a list of {C} core strains (the fibre has {C} cores), got {describe(entry)}"
            )
        eps = []
        for c, x in enumerate(entry):
            try:
                eps.append(as_number(x, f"{where}[{c}]", bound=MAX_STRAIN / scale) * scale)
            except ValueError as exc:
                if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x)):
                    raise ReadingError(f"{exc} ({hint})") from None
                raise
        rows.append(_converted(fibre.strain_to_curvature(eps), where, "strains"))
    return rows


def polar_curvature(value: Any, num_gratings: int, what: str = "curvature_polar", fibre: Any = None) -> list[Any]:
    """A reading's (kappa, phi [rad]) per grating, or None -> its G (ux, uy) pairs [1/m] or None; kappa in the
    fibre's ``curvature_unit`` (1/m without a fibre)."""
    from ..sensors import polar_to_curvature

    scale, unit = _units(fibre, "curvature_unit")
    rows: list[Any] = []
    for k, entry in enumerate(_entries(value, num_gratings, what, "[kappa, phi] pair")):
        if entry is None:
            rows.append(None)
            continue
        where = f"{what}[{k}]"
        if not isinstance(entry, (list, tuple)) or len(entry) != 2:
            raise ReadingError(f"{where} must be a pair [kappa, phi] ([{unit}], [rad]) or null, got {describe(entry)}")
        kappa = as_number(entry[0], f"{where}[0]", bound=MAX_CURVATURE / scale, unit=unit)
        if kappa < 0.0:
            raise ReadingError(f"{where}[0] is a curvature magnitude and must be >= 0 [{unit}], got {quote(entry[0])}")
        phi = as_number(entry[1], f"{where}[1]", bound=1e6, unit="rad")
        rows.append(_converted(polar_to_curvature(kappa * scale, phi), where, "curvature"))
    return rows


def wavelength_values(
    value: Any, num_gratings: int, num_cores: int, fibre: Any, what: str = "wavelength", *, shift: bool = False
) -> list[Any]:
    """A reading's peak wavelengths (``shift`` False) or wavelength shifts (True), one list of C per grating or
    None, in the fibre's ``wavelength_unit`` -> per grating the C values [m], or None. ``ValueError`` naming the
    entry for a value that is not a finite number, a wavelength outside
    :data:`torchrod.sensors.WAVELENGTH_RANGE_NM` or a shift beyond :data:`torchrod.sensors.MAX_WAVELENGTH_SHIFT`
    (both unit errors)."""
    from ..sensors import MAX_WAVELENGTH_SHIFT, WAVELENGTH_RANGE_NM, WAVELENGTH_UNITS

    scale, unit = _units(fibre, "wavelength_unit")
    nm = WAVELENGTH_UNITS["nm"]
    low, high = (x * nm for x in WAVELENGTH_RANGE_NM)
    C = num_cores
    rows: list[Any] = []
    for k, entry in enumerate(_entries(value, num_gratings, what, f"list of {C} values [{unit}]")):
        if entry is None:
            rows.append(None)
            continue
        where = f"{what}[{k}]"
        if not isinstance(entry, (list, tuple)) or len(entry) != C:
            raise ReadingError(
                f"{where} must be a list of {C} values [{unit}] (one per core, in the calibration's column order), "
                f"got {describe(entry)}"
            )
        values = []
        for c, x in enumerate(entry):
            v = as_number(x, f"{where}[{c}]") * scale
            if shift and not abs(v) <= MAX_WAVELENGTH_SHIFT:
                raise ReadingError(
                    f"{where}[{c}] = {quote(x)} {unit} is a shift beyond {MAX_WAVELENGTH_SHIFT / scale:g} {unit}, "
                    "which no fibre survives: check the wavelength unit (--wavelength-unit nm or pm)"
                )
            if not shift and not low <= v <= high:
                raise ReadingError(
                    f"{where}[{c}] = {quote(x)} {unit} is not a peak wavelength (FBGs reflect between "
                    f"{low / scale:g} and {high / scale:g} {unit}): check the wavelength unit (--wavelength-unit nm "
                    "or pm), or give shifts as wavelength_shift"
                )
            values.append(v)
        rows.append(values)
    return rows


def wavelength_shifts(
    value: Any, num_gratings: int, fibre: Any, what: str = "wavelength", absolute: bool | None = None
) -> list[Any]:
    """A reading's peak wavelengths (``what`` ``"wavelength"``: absolute, the rod's reference subtracted here) or
    shifts (``"wavelength_shift"``; ``absolute`` says which when ``what`` is another name), one list of C per
    grating or None, in the fibre's ``wavelength_unit`` -> per grating the C shifts [m], or None
    (:func:`wavelength_values` checks the values; a wavelength further than
    :data:`torchrod.sensors.MAX_WAVELENGTH_SHIFT` from its reference is refused too)."""
    from ..sensors import MAX_WAVELENGTH_SHIFT

    if fibre is None or fibre.wavelength is None:
        raise ReadingError(
            f'{what} needs the rod file\'s "fibre": {{"wavelength": {{...}}}} section (a reference with the cores, or '
            "a calibration): docs/sensors.md"
        )
    absolute = what == "wavelength" if absolute is None else absolute
    reference = fibre.reference_m() if absolute else None
    if absolute and reference is None:
        raise ReadingError(
            f"{what} gives peak wavelengths, and the rod file's fibre.wavelength has no reference to subtract: add "
            "fibre.wavelength.reference [nm], or give the shifts as wavelength_shift"
        )
    rows = wavelength_values(value, num_gratings, fibre.num_cores, fibre, what, shift=not absolute)
    if reference is None:
        return rows
    scale, unit = _units(fibre, "wavelength_unit")
    for k, row in enumerate(rows):
        if row is None:
            continue
        for c, v in enumerate(row):
            d = v - reference[k][c]
            if not abs(d) <= MAX_WAVELENGTH_SHIFT:
                raise ReadingError(
                    f"{what}[{k}][{c}] lies {d / scale:g} {unit} from its reference {reference[k][c] / scale:g} "
                    f"{unit}, a shift beyond {MAX_WAVELENGTH_SHIFT / scale:g} {unit} that no fibre survives: check the "
                    "reference, the peak layout and the wavelength unit"
                )
            row[c] = d
    return rows


def wavelength_curvature(value: Any, num_gratings: int, fibre: Any, what: str = "wavelength") -> list[Any]:
    """:func:`wavelength_shifts`, then each grating's curvature [1/m] through the fibre's map
    (:meth:`torchrod.sensors.Fibre.shift_to_curvature`): G pairs or None."""
    shifts = wavelength_shifts(value, num_gratings, fibre, what)
    return [
        None if d is None else _converted(fibre.shift_to_curvature(k, d), f"{what}[{k}]", "wavelengths")
        for k, d in enumerate(shifts)
    ]


def reading_curvature(obj: Mapping[str, Any], num_gratings: int, fibre: Any = None) -> torch.Tensor:
    """The (G, 2) curvature [1/m] of a reading object that gives exactly one of :data:`QUANTITIES`' keys, in the
    units the fibre says (SI without one)."""
    given = [key for key in QUANTITIES.values() if key in obj]
    if len(given) > 1:
        raise ReadingError(
            f"a reading gives {' and '.join(given)}: give exactly one of {', '.join(QUANTITIES.values())}"
        )
    if not given:
        raise ReadingError(
            f"missing 'curvature' (an array of {num_gratings} [ux, uy] pairs [1/m], one per grating; or one of "
            f"{', '.join(list(QUANTITIES.values())[1:])})"
        )
    key = given[0]
    if key == "strain":
        rows = strain_curvature(obj[key], num_gratings, fibre)
    elif key == "curvature_polar":
        rows = polar_curvature(obj[key], num_gratings, fibre=fibre)
    elif key in ("wavelength", "wavelength_shift"):
        rows = wavelength_curvature(obj[key], num_gratings, fibre, key)
    else:
        scale, unit = _units(fibre, "curvature_unit")
        return curvature_tensor(obj[key], num_gratings, scale=scale, unit=unit)
    if all(r is None for r in rows):
        raise ReadingError(f"all gratings are missing: {key} needs at least one grating's values")
    return curvature_tensor(rows, num_gratings)
