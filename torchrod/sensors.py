"""What sensors other than a (u_x, u_y) reading give, turned into curvature at the edge (SI units).

Everything past the reading parser (:mod:`torchrod.io.reading`) sees body-frame curvature [1/m]; this module holds
the one definition of each conversion that gets it there, and the rod file's ``fibre`` section that describes the
sensor (:class:`Fibre`). docs/sensors.md is the user's reference of every key.

Multicore fibre strains
    A shape-sensing fibre carries C cores at positions (x_c, y_c) [m] in the rod's cross-section (x along the body
    frame's d1, y along d2). Bending with body-frame curvature (u_x, u_y) stretches core c by

        eps_c = u_x y_c - u_y x_c + eps_0                                                  [strain, 1 = 100 %]

    where eps_0, common to the cores of one grating, is the strain that does not bend the fibre (temperature, axial
    load) and is unknown. Per grating, (u_x, u_y, eps_0) follow from the C strains by least squares with the design
    matrix A (C x 3, rows (y_c, -x_c, 1)); A has full rank, and the fit is possible, exactly when at least three
    cores do not lie on one line. With independent strain noise sigma_eps per core, the curvature it implies has
    covariance sigma_eps^2 [(A^T A)^-1] restricted to (u_x, u_y): :meth:`Fibre.curvature_sigma` gives the sigma the
    estimator weighs the fit with. For cores spread evenly round a circle (three at 120 degrees, four at 90, ...)
    that covariance is isotropic and the sigma is exact; for other layouts it is the larger principal sigma, so the
    noise tests stay conservative (:attr:`Fibre.anisotropy` says by how much).

Peak wavelengths (:class:`Wavelength`)
    An interrogator reports each grating's Bragg wavelength per core. With d_c the shift of core c from the
    reference (unloaded) state, a grating's curvature is linear in its C shifts, u = M_g d, by one of two routes:

    * with a calibration matrix A_g (2 x C, fitted on a jig, :mod:`torchrod.jig`): M_g = A_g (I - 1 1^T / C), i.e.
      u = A_g (d - mean(d)): the shift common to the grating's cores (temperature) is taken out first;
    * without one, through the physics: each core's strain is eps_c = d_c / (lambda_ref,c (1 - p_e)) (p_e the
      effective photoelastic coefficient), then the multicore least squares above, which takes out the common
      strain: M_g = P (diag lambda_ref (1 - p_e))^-1 with P the (u_x, u_y) rows of the least-squares map.

    The calibration route removes a shift equal on the grating's cores exactly; the physics route removes an equal
    strain, i.e. shifts proportional to each core's reference wavelength (as temperature gives). Independent
    wavelength noise sigma per core gives the curvature covariance sigma^2 M_g M_g^T: :meth:`Fibre.wavelength_sigmas`.

Curvature magnitude and bend angle
    Commercial shape-sensing systems report kappa >= 0 [1/m] and the bend angle phi [rad] per station:
    u_x = kappa cos phi, u_y = kappa sin phi (:func:`polar_to_curvature`).

Units
    Readings may come in other units than SI; :data:`CURVATURE_UNITS`, :data:`STRAIN_UNITS` and
    :data:`WAVELENGTH_UNITS` are the one table of each, as factors to SI (1/m, dimensionless strain, m). A rod
    file's ``fibre`` may say which its sensor writes (``curvature_unit``, ``strain_unit``, ``wavelength_unit``); the
    commands' options of the same names override it. Values in the rod file itself are in fixed units (core
    positions in m, reference wavelengths in nm, calibrations in 1/m per nm).

The parser of readings applies these per reading, so everything past it sees curvature only. This module imports no
torch at import: a rod file with a fibre is checked without it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from .errors import RodError
from .values import real as _real
from .values import show as _show

__all__ = [
    "CALIBRATION_GAIN",
    "CURVATURE_UNITS",
    "DEFAULT_UNITS",
    "MAX_CORE_RADIUS",
    "MAX_STRAIN",
    "MIN_CORE_SPREAD",
    "MAX_WAVELENGTH_SHIFT",
    "NOMINAL_WAVELENGTH",
    "PEAK_ORDERS",
    "PHOTOELASTIC",
    "STRAIN_UNITS",
    "UNIT_TABLES",
    "WAVELENGTH_RANGE_NM",
    "WAVELENGTH_UNITS",
    "Fibre",
    "Wavelength",
    "polar_to_curvature",
    "unit_scale",
]

MAX_STRAIN = 0.1
"""A core strain beyond 10 % is refused: glass fibres break at a few percent, so such a value is a unit error (a
strain of 1e-6 is one microstrain)."""

MAX_CORE_RADIUS = 0.05
"""[m] a core farther than this from the rod's axis is refused (a unit error: core positions are in metres)."""

MAX_WAVELENGTH_SHIFT = 1e-7
"""[m] A wavelength shift beyond 100 nm is refused: at 1550 nm it would be a strain of about 8 %, beyond what a glass
fibre survives, so such a value is a unit error (pm read as nm, or a reading against another reference)."""

WAVELENGTH_RANGE_NM = (200.0, 5000.0)
"""[nm] A reference wavelength outside this range is refused (FBGs reflect in the visible and near infrared): the
rod file gives wavelengths in nm, so 1.55e-6 (metres) or 1550000 (pm) is a unit error."""

PHOTOELASTIC = 0.22
"""The effective photoelastic coefficient p_e of silica fibre, used by the physics route when the rod file gives
none."""

NOMINAL_WAVELENGTH = 1550e-9
"""[m] The wavelength :meth:`Fibre.temperature_shift` assumes for a calibrated fibre without a reference."""

CURVATURE_UNITS = {"1/m": 1.0, "1/cm": 100.0, "1/mm": 1000.0}
"""Curvature units of readings and their factor to 1/m."""

STRAIN_UNITS = {"strain": 1.0, "microstrain": 1e-6}
"""Strain units of readings and their factor to strain (dimensionless)."""

WAVELENGTH_UNITS = {"nm": 1e-9, "pm": 1e-12}
"""Wavelength units of readings and their factor to m."""

UNIT_TABLES = {"curvature_unit": CURVATURE_UNITS, "strain_unit": STRAIN_UNITS, "wavelength_unit": WAVELENGTH_UNITS}
"""Each unit key (rod file ``fibre`` section, command option) and its table."""

DEFAULT_UNITS = {"curvature_unit": "1/m", "strain_unit": "strain", "wavelength_unit": "nm"}
"""What readings are in when neither the rod file nor an option says: SI, and nm for wavelengths (interrogators
write nm; nobody writes metres)."""

PEAK_ORDERS = ("by-core", "by-grating")
"""The regular orders of a peak log's N = G x C peaks: ``by-core`` (core 1's G gratings, then core 2's, ...: an
interrogator with one channel per core, each channel's peaks in order along the fibre) or ``by-grating`` (grating
1's C cores, then grating 2's, ...)."""

MIN_CORE_SPREAD = 1e-6
"""[m] the smallest RMS distance of the cores from their centre: closer cores (1 um; fibres space them tens of
micrometres apart) read almost no strain from any bend, and their least squares would divide by nearly nothing."""

_COLLINEAR = 1e-8  # smallest / largest eigenvalue of the cores' scatter below which they count as on one line

CALIBRATION_GAIN = (1e-4, 1e5)
"""[1/m per nm] The range a calibration matrix's gains must lie in: both singular values of each grating's centred
matrix A_g (I - 1 1^T / C), the curvature one nm of differential shift reads. A bend u shifts a core at radius r by
lambda (1 - p_e) r u, so C cores spread evenly round radius r read gains of sqrt(2 / C) / (lambda (1 - p_e) r)
(three cores 35 um off the axis at 1530 nm: about 16). The largest any fibre can read, at r =
:data:`MIN_CORE_SPREAD` (1 um), lambda = 200 nm, 1 - p_e = 0.5 (silica: 0.78) and C = 3, is about 8e3; the
smallest, at r = :data:`MAX_CORE_RADIUS` (5 cm), lambda = 5000 nm, p_e = 0 and C = 32, about 1e-3. The bounds lie
an order of magnitude beyond each. A smaller gain turns every reading within :data:`MAX_WAVELENGTH_SHIFT` into
almost no curvature (all zeros, or a calibration written in 1/m per m, reads every reading as "no force"); a
larger one is a unit error the other way. A matrix whose smaller gain is below :data:`_COLLINEAR` ** 0.5 of its
larger (rank one once centred: equal columns, proportional rows, two cores) reads every bend on one line, and is
refused too."""


def unit_scale(key: str, name: Any, what: str | None = None, error: type[ValueError] = RodError) -> float:
    """The factor from unit ``name`` to SI for unit key ``key`` (:data:`UNIT_TABLES`); ``error`` naming ``what``
    (default: the key) and the known units when ``name`` is not one."""
    table = UNIT_TABLES[key]
    if not isinstance(name, str) or name not in table:
        raise error(f"{what or key} must be one of {', '.join(table)}, got {_show(name)}")
    return table[name]


def _symmetric2_eigen(a: float, b: float, d: float) -> tuple[float, float]:
    """The eigenvalues (small, large) of [[a, b], [b, d]]."""
    mean, diff = 0.5 * (a + d), math.hypot(0.5 * (a - d), b)
    return mean - diff, mean + diff


def _number(name: str, value: Any, unit: str = "") -> float:
    """A finite number from a rod file, or :class:`RodError` naming ``name``."""

    try:
        return _real(name, value, unit)
    except ValueError as exc:
        raise RodError(str(exc)) from None


def _rows(name: str, value: Any, what: str) -> list[Any]:

    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
        raise RodError(f"{name} must be an array of {what}, got {_show(value)}")
    return list(value)


# ---------------------------------------------------------------------------------------------------- wavelength
def _check_gains(where: str, rows: tuple[tuple[float, ...], ...]) -> None:
    """:class:`RodError` naming ``where`` when the centred 2 x C matrix ``rows`` has rank below 2 or a gain outside
    :data:`CALIBRATION_GAIN` (its docstring)."""
    centred = [[a - sum(r) / len(r) for a in r] for r in rows]
    scale = max((abs(a) for r in centred for a in r), default=0.0)
    lo, hi = CALIBRATION_GAIN
    if scale == 0.0:
        raise RodError(
            f"{where} reads no curvature from any shift: it is zero once the shift common to the cores is taken "
            "out (all zeros, or equal columns); fit it on a jig (torchrod calibrate --fibre)"
        )
    x, y = ([a / scale for a in r] for r in centred)  # scaled, so that 1e-300 does not underflow when squared
    xx, xy, yy = (sum(a * b for a, b in zip(u, v, strict=True)) for u, v in ((x, x), (x, y), (y, y)))
    small, large = (scale * math.sqrt(max(e, 0.0)) for e in _symmetric2_eigen(xx, xy, yy))
    if small <= large * math.sqrt(_COLLINEAR):
        raise RodError(
            f"{where} is of rank one once the shift common to the cores is taken out (gains {large:.3g} and "
            f"{small:.3g} 1/m per nm): it reads every bend along one line; a calibration needs at least 3 cores "
            "and two independent rows"
        )
    if small < lo or large > hi:
        raise RodError(
            f"{where} has gains {small:.3g} to {large:.3g} 1/m per nm, outside the {lo:g} to {hi:g} any fibre "
            "reads (three cores 35 um off the axis read about 16): the rod file gives calibrations in 1/m per nm"
        )


@dataclass(frozen=True)
class Wavelength:
    """How a fibre's peak wavelengths become curvature: the rod file's ``fibre.wavelength`` section.

    Attributes:
        reference: (G, C) the unloaded state's wavelengths [nm], one row per grating in the rod's order, the C
            values in the order of the calibration's columns (or of ``fibre.cores``); None if not given (then
            readings must give shifts, and a calibration is needed).
        calibration: (G, 2, C) per grating the matrix A_g [1/m per nm] with u = A_g (d - mean(d)); None: the
            physics route (module docstring), which needs ``reference`` and ``fibre.cores``.
        photoelastic: p_e of the physics route (default :data:`PHOTOELASTIC`); unused with a calibration.
        peaks: how a peak log's N values map onto (grating, core): ``"by-core"`` or ``"by-grating"``
            (:data:`PEAK_ORDERS`), or N entries (grating, core), 0-based here (1-based in the rod file), None for a
            peak that is not read.

    Values are in the rod file's units (nm, 1/m per nm); :class:`Fibre` converts them to SI once.
    Raises :class:`~torchrod.errors.RodError` naming the field.
    """

    reference: Any = None
    calibration: Any = None
    photoelastic: float = PHOTOELASTIC
    peaks: Any = "by-core"

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        if self.reference is None and self.calibration is None:
            raise RodError(
                "fibre.wavelength needs a reference (the unloaded wavelengths [nm], one row per grating), a "
                "calibration (per grating a 2 x C matrix [1/m per nm]), or both"
            )
        widths = set()
        if self.reference is not None:
            rows = []
            for g, row in enumerate(_rows("fibre.wavelength.reference", self.reference, "rows [nm], one per grating")):
                where = f"fibre.wavelength.reference[{g}]"
                values = tuple(_number(f"{where}[{c}]", x, " [nm]") for c, x in enumerate(_rows(where, row, "[nm]")))
                lo, hi = WAVELENGTH_RANGE_NM
                for c, x in enumerate(values):
                    if not lo <= x <= hi:
                        raise RodError(
                            f"{where}[{c}] = {x:g} is not a wavelength in nm (FBGs reflect between {lo:g} and {hi:g} "
                            "nm): the rod file gives wavelengths in nm"
                        )
                rows.append(values)
                widths.add(len(values))
            if not rows:
                raise RodError("fibre.wavelength.reference holds no grating")
            set_(self, "reference", tuple(rows))
        if self.calibration is not None:
            mats = []
            for g, mat in enumerate(_rows("fibre.wavelength.calibration", self.calibration, "2 x C matrices")):
                where = f"fibre.wavelength.calibration[{g}]"
                pair = _rows(where, mat, "two rows [[a11, ..., a1C], [a21, ..., a2C]] [1/m per nm]")
                if len(pair) != 2:
                    raise RodError(f"{where} must hold two rows (u_x, u_y), got {len(pair)}")
                rows2 = tuple(
                    tuple(
                        _number(f"{where}[{j}][{c}]", x, " [1/m per nm]")
                        for c, x in enumerate(_rows(f"{where}[{j}]", r, "[1/m per nm]"))
                    )
                    for j, r in enumerate(pair)
                )
                if len(rows2[0]) != len(rows2[1]):
                    raise RodError(f"{where}: its two rows have {len(rows2[0])} and {len(rows2[1])} columns")
                _check_gains(f"{where} (grating {g + 1})", rows2)
                mats.append(rows2)
                widths.add(len(rows2[0]))
            if not mats:
                raise RodError("fibre.wavelength.calibration holds no grating")
            set_(self, "calibration", tuple(mats))
        if len(widths) != 1:
            raise RodError(
                f"fibre.wavelength: every grating needs the same number of cores, got {sorted(widths)} "
                "(reference rows and calibration columns)"
            )
        (C,) = widths
        if C < 3:
            raise RodError(
                f"fibre.wavelength gives {C} value(s) per grating: it needs at least 3 cores (with 2, once their "
                "common shift is taken out, every bend reads along one line)"
            )
        if self.reference is not None and self.calibration is not None and len(self.reference) != len(self.calibration):
            raise RodError(
                f"fibre.wavelength.reference has {len(self.reference)} rows but the calibration "
                f"{len(self.calibration)} matrices: one of each per grating"
            )
        pe = _number("fibre.wavelength.photoelastic", self.photoelastic)
        if not 0.0 <= pe < 1.0:
            raise RodError(f"fibre.wavelength.photoelastic must lie in [0, 1) (silica: about 0.22), got {pe:g}")
        set_(self, "photoelastic", pe)
        set_(self, "peaks", _check_peaks(self.peaks, self.num_gratings, C))

    @property
    def num_gratings(self) -> int:
        return len(self.reference if self.reference is not None else self.calibration)

    @property
    def num_cores(self) -> int:
        return len(self.reference[0]) if self.reference is not None else len(self.calibration[0][0])

    @classmethod
    def from_dict(cls, data: Any) -> Wavelength:
        """From the rod file's ``"wavelength": {"reference", "calibration", "photoelastic", "peaks"}`` (unknown keys
        refused; ``peaks`` 1-based)."""

        if not isinstance(data, Mapping):
            raise RodError(
                f'fibre.wavelength must be an object {{"reference": ..., "calibration": ...}}, got {_show(data)}'
            )
        known = ("reference", "calibration", "photoelastic", "peaks")
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            raise RodError(f"unknown fibre.wavelength keys {unknown}; the known keys are {list(known)}")
        peaks = data.get("peaks", "by-core")
        if not isinstance(peaks, str):
            peaks = _one_based_peaks(peaks)
        return cls(
            reference=data.get("reference"),
            calibration=data.get("calibration"),
            photoelastic=data.get("photoelastic", PHOTOELASTIC),
            peaks=peaks,
        )

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.reference is not None:
            out["reference"] = [list(r) for r in self.reference]
        if self.calibration is not None:
            out["calibration"] = [[list(r) for r in m] for m in self.calibration]
        if self.photoelastic != PHOTOELASTIC:
            out["photoelastic"] = self.photoelastic
        if self.peaks != "by-core":
            out["peaks"] = (
                self.peaks
                if isinstance(self.peaks, str)
                else [None if p is None else [p[0] + 1, p[1] + 1] for p in self.peaks]
            )
        return out


def _one_based_peaks(peaks: Any) -> Any:
    """The rod file's 1-based ``[[grating, core] or null, ...]`` as 0-based pairs (checked by :func:`_check_peaks`)."""

    entries = _rows("fibre.wavelength.peaks", peaks, '[grating, core] pairs (1-based) or null, or "by-core"')
    out: list[Any] = []
    for k, p in enumerate(entries):
        if p is None:
            out.append(None)
            continue
        if isinstance(p, (str, bytes, Mapping)) or not isinstance(p, Sequence) or len(p) != 2:
            raise RodError(f"fibre.wavelength.peaks[{k}] must be [grating, core] (1-based) or null, got {_show(p)}")
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in p):
            raise RodError(f"fibre.wavelength.peaks[{k}] must hold two integers (1-based), got {_show(p)}")
        out.append((p[0] - 1, p[1] - 1))
    return tuple(out)


def _check_peaks(peaks: Any, G: int, C: int, what: str = "fibre.wavelength.peaks") -> Any:
    """``peaks`` (an order of :data:`PEAK_ORDERS`, or 0-based (grating, core) pairs and None) checked against G
    gratings and C cores: every (grating, core) at most once, and each grating either complete or absent."""

    if isinstance(peaks, str):
        if peaks not in PEAK_ORDERS:
            raise RodError(
                f"{what} must be {' or '.join(PEAK_ORDERS)}, or a list of [grating, core], got {_show(peaks)}"
            )
        return peaks
    entries = _rows(what, peaks, "[grating, core] pairs or null")
    seen: dict[tuple[int, int], int] = {}
    out: list[tuple[int, int] | None] = []
    for k, p in enumerate(entries):
        if p is None:
            out.append(None)
            continue
        g, c = p
        if not (0 <= g < G and 0 <= c < C):
            raise RodError(
                f"{what}[{k}] = [{g + 1}, {c + 1}] is outside the fibre's {G} gratings and {C} cores (1-based)"
            )
        if (g, c) in seen:
            raise RodError(f"{what}[{k}] and {what}[{seen[(g, c)]}] both map to grating {g + 1}, core {c + 1}")
        seen[(g, c)] = k
        out.append((g, c))
    for g in {g for g, _ in seen}:
        cores = sorted(c for gg, c in seen if gg == g)
        if len(cores) != C:
            raise RodError(f"{what} maps {len(cores)} of grating {g + 1}'s {C} cores: a grating needs all or none")
    if not seen:
        raise RodError(f"{what} maps no peak to a grating")
    return tuple(out)


# ---------------------------------------------------------------------------------------------------- the fibre
@dataclass(frozen=True)
class Fibre:
    """The rod file's ``fibre`` section: what the rod's sensor writes and how it becomes curvature.

    Attributes:
        cores: C >= 3 pairs (x_c, y_c) [m], x along d1 and y along d2, not all on one line; empty when not given
            (readings of core strains, and wavelengths without a calibration, need them).
        wavelength: the peak-wavelength conversion (:class:`Wavelength`, or its JSON form), or None.
        curvature_unit: the unit curvature readings come in (:data:`UNIT_TABLES`; default :data:`DEFAULT_UNITS`).
            A command's option of the same name overrides it, as for the two below.
        strain_unit: the unit core-strain readings come in (the same tables and defaults).
        wavelength_unit: the unit peak-wavelength readings come in (the same tables and defaults).

    Raises :class:`~torchrod.errors.RodError` (a ``ValueError``) naming the bad field (a bool, a string or null is
    not a number).
    """

    cores: Any = ()
    wavelength: Any = None
    curvature_unit: str = DEFAULT_UNITS["curvature_unit"]
    strain_unit: str = DEFAULT_UNITS["strain_unit"]
    wavelength_unit: str = DEFAULT_UNITS["wavelength_unit"]
    _derived: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:

        set_ = object.__setattr__
        for key in UNIT_TABLES:
            unit_scale(key, getattr(self, key), f"fibre.{key}")
        if self.wavelength is not None and not isinstance(self.wavelength, Wavelength):
            set_(self, "wavelength", Wavelength.from_dict(self.wavelength))
        cores = self.cores
        if cores is None:
            cores = ()
        if not isinstance(cores, (list, tuple)):
            raise RodError(f"fibre.cores must be an array of [x, y] core positions [m], got {_show(cores)}")
        if cores:
            set_(self, "cores", self._checked_cores(cores))
        else:
            set_(self, "cores", ())
        wl = self.wavelength
        if wl is not None:
            if wl.calibration is None and not self.cores:
                raise RodError(
                    "fibre.wavelength without a calibration converts through the physics and needs fibre.cores (the "
                    "[x, y] core positions [m]); or give fibre.wavelength.calibration"
                )
            if self.cores and len(self.cores) != wl.num_cores:
                raise RodError(
                    f"fibre.wavelength gives {wl.num_cores} values per grating but fibre.cores holds {len(self.cores)} "
                    "cores: the columns follow the cores, one each"
                )
            self._derive_wavelength(wl)

    def _checked_cores(self, cores: Sequence[Any]) -> tuple[tuple[float, float], ...]:

        if len(cores) < 3:
            raise RodError(f"fibre.cores needs at least 3 cores (not on one line), got {len(cores)}")
        checked = []
        for c, core in enumerate(cores):
            if not isinstance(core, (list, tuple)) or len(core) != 2:
                raise RodError(f"fibre.cores[{c}] must be a pair [x, y] [m], got {_show(core)}")
            x, y = (_number(f"fibre.cores[{c}][{j}]", v, " [m]") for j, v in enumerate(core))
            if math.hypot(x, y) > MAX_CORE_RADIUS:
                raise RodError(
                    f"fibre.cores[{c}] = [{x:g}, {y:g}] lies {math.hypot(x, y):g} m from the axis, more than "
                    f"{MAX_CORE_RADIUS:g} m: core positions are in metres (35 um = 3.5e-5)"
                )
            checked.append((x, y))
        mx = sum(x for x, _ in checked) / len(checked)
        my = sum(y for _, y in checked) / len(checked)
        sxx = sum((x - mx) ** 2 for x, _ in checked)
        syy = sum((y - my) ** 2 for _, y in checked)
        sxy = sum((x - mx) * (y - my) for x, y in checked)
        spread = math.sqrt((sxx + syy) / len(checked))
        if spread < MIN_CORE_SPREAD:
            raise RodError(
                f"fibre.cores {_show([list(c) for c in checked])} lie within {spread:.3g} m of their centre, less "
                f"than {MIN_CORE_SPREAD:g} m: such cores read almost no strain from any bend; core positions are in "
                "metres (35 um = 3.5e-5)"
            )
        small, large = _symmetric2_eigen(sxx, sxy, syy)
        if not large > 0.0 or small <= _COLLINEAR * large:
            raise RodError(
                f"fibre.cores {_show([list(c) for c in checked])} lie on one line: the curvature across that line "
                "cannot be told from the common strain; a fibre needs at least 3 cores not on one line"
            )
        # The least-squares map strain -> (u_x, u_y, eps_0): rows of (A^T A)^-1 A^T, kept as Python floats.
        rows = [(y, -x, 1.0) for x, y in checked]
        ata = [[sum(r[i] * r[j] for r in rows) for j in range(3)] for i in range(3)]
        inv = _inverse3(ata)
        pinv = tuple(tuple(sum(inv[i][k] * r[k] for k in range(3)) for r in rows) for i in range(3))
        self._derived["pinv"] = pinv
        self._derived["cov"] = (inv[0][0], inv[0][1], inv[1][1])
        return tuple(checked)

    def _derive_wavelength(self, wl: Wavelength) -> None:
        """The SI forms, once: reference [m], and each grating's map M_g (2 x C) [1/m per m] (module docstring)."""
        nm = WAVELENGTH_UNITS["nm"]
        C = wl.num_cores
        reference = None if wl.reference is None else [[x * nm for x in row] for row in wl.reference]
        # The shift [m] per unit of strain on each core, lambda_ref,c (1 - p_e): the one definition of the physics
        # route's strain <-> shift relation, used both ways (maps, bending_shift, temperature_shift).
        per_strain = None if reference is None else [[x * (1.0 - wl.photoelastic) for x in row] for row in reference]
        maps = []
        if wl.calibration is not None:
            for mat in wl.calibration:
                # A (d - mean d) = A P d with P = I - 1 1^T / C; A is per nm, d in m.
                rows = []
                for r in mat:
                    mean = sum(r) / C
                    rows.append([(a - mean) / nm for a in r])
                maps.append(rows)
        else:
            p = self._derived["pinv"]
            assert per_strain is not None  # no calibration: Wavelength requires the reference then
            for row in per_strain:
                maps.append([[p[j][c] / row[c] for c in range(C)] for j in range(2)])
        self._derived["reference"] = reference
        self._derived["per_strain"] = per_strain
        self._derived["maps"] = maps

    # ------------------------------------------------------------------ the rod file
    @classmethod
    def from_dict(cls, data: Any) -> Fibre:
        """From the rod file's ``"fibre": {"cores", "wavelength", "curvature_unit", "strain_unit",
        "wavelength_unit"}`` (all optional, at least one given; unknown keys refused)."""

        if not isinstance(data, Mapping):
            raise RodError(f'fibre must be an object {{"cores": [[x, y], ...], ...}}, got {_show(data)}')
        known = ("cores", "wavelength", *UNIT_TABLES)
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            raise RodError(f"unknown fibre keys {unknown}; the known keys are {list(known)}")
        if not data:
            raise RodError(f"fibre is empty: give at least one of {', '.join(known)}")
        if "cores" in data and not isinstance(data["cores"], (list, tuple)):
            raise RodError(f"fibre.cores must be an array of [x, y] core positions [m], got {_show(data['cores'])}")
        units = {k: data[k] for k in UNIT_TABLES if k in data}
        return cls(cores=data.get("cores", ()), wavelength=data.get("wavelength"), **units)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.cores:
            out["cores"] = [list(c) for c in self.cores]
        if self.wavelength is not None:
            out["wavelength"] = self.wavelength.to_dict()
        for key, default in DEFAULT_UNITS.items():
            if getattr(self, key) != default:
                out[key] = getattr(self, key)
        return out

    def with_(self, **changes: Any) -> Fibre:
        """A copy with some fields changed (units from a command's options, a new wavelength section)."""
        return replace(self, **changes)

    def check_gratings(self, num_gratings: int) -> None:
        """:class:`RodError` when the wavelength section's rows are not one per grating of the rod."""
        wl = self.wavelength
        if wl is not None and wl.num_gratings != num_gratings:
            part = "reference" if wl.reference is not None else "calibration"
            raise RodError(
                f"fibre.wavelength.{part} has {wl.num_gratings} rows but the rod has {num_gratings} gratings: "
                "one row per grating, in the rod file's order"
            )
        if wl is not None and not isinstance(wl.peaks, str) and len(wl.peaks) == 0:
            raise RodError("fibre.wavelength.peaks is empty")

    # ------------------------------------------------------------------ units
    def scale(self, key: str) -> float:
        """The factor from the readings' unit ``key`` (``"curvature_unit"``, ...) to SI."""
        return UNIT_TABLES[key][getattr(self, key)]

    # ------------------------------------------------------------------ strains
    @property
    def num_cores(self) -> int:
        """C: the cores' count, or the wavelength section's values per grating; 0 for a fibre that gives neither."""
        if self.cores:
            return len(self.cores)
        return self.wavelength.num_cores if self.wavelength is not None else 0

    def _pinv(self) -> Any:
        p = self._derived.get("pinv")
        if p is None:
            raise RodError(
                "core strains need the fibre's core positions: add \"cores\": [[x, y], ...] [m] to the rod file's fibre"
            )
        return p

    def strain_to_curvature(self, strain: Sequence[float]) -> tuple[float, float]:
        """One grating's C core strains -> its (u_x, u_y) [1/m] by least squares (eps_0 eliminated)."""
        p = self._pinv()
        return (
            sum(a * e for a, e in zip(p[0], strain, strict=True)),
            sum(a * e for a, e in zip(p[1], strain, strict=True)),
        )

    def curvature_to_strain(self, ux: float, uy: float, common: float = 0.0) -> list[float]:
        """The C core strains that (u_x, u_y) [1/m] and the common strain eps_0 give (the inverse of
        :meth:`strain_to_curvature`)."""
        self._pinv()
        return [ux * y - uy * x + common for x, y in self.cores]

    def curvature(self, strain: Any) -> Any:
        """Tensor form of :meth:`strain_to_curvature`: strains (..., C) -> curvature (..., 2) [1/m] (a NaN strain
        gives NaN), in the input's dtype and device."""
        import torch

        p = torch.tensor(self._pinv()[:2], dtype=strain.dtype, device=strain.device)
        return strain @ p.T

    def strain(self, curvature: Any, common: Any = 0.0) -> Any:
        """Tensor form of :meth:`curvature_to_strain`: curvature (..., 2) [1/m] and common strain (broadcast to
        (...)) -> core strains (..., C)."""
        import torch

        a = torch.tensor(self.matrices()[0], dtype=curvature.dtype, device=curvature.device)  # (C, 3)
        common = torch.as_tensor(common, dtype=curvature.dtype, device=curvature.device)
        return curvature @ a[:, :2].T + common[..., None] * a[:, 2]

    def matrices(self) -> tuple[list[list[float]], list[list[float]]]:
        """(A, P): A (C x 3) maps (u_x, u_y, eps_0) to the core strains, P (2 x C) the strains to (u_x, u_y), as
        nested lists, for array code (``torch.tensor(P) @ strain``)."""
        p = self._pinv()
        return [[y, -x, 1.0] for x, y in self.cores], [list(p[0]), list(p[1])]

    def curvature_sigma(self, strain_sigma: float) -> float:
        """The curvature sigma [1/m] per component that independent core strain noise ``strain_sigma`` implies
        (the larger principal one where the layout is not isotropic; module docstring)."""

        self._pinv()
        s = _real("strain noise", strain_sigma)
        if s < 0.0:
            raise RodError(f"strain noise must be >= 0, got {strain_sigma!r}")
        a, b, d = self._derived["cov"]
        return s * math.sqrt(_symmetric2_eigen(a, b, d)[1])

    @property
    def anisotropy(self) -> float:
        """The ratio of the larger to the smaller principal curvature sigma (1 for an isotropic layout)."""
        self._pinv()
        small, large = _symmetric2_eigen(*self._derived["cov"])
        return math.sqrt(large / small)

    # ------------------------------------------------------------------ wavelengths
    def _maps(self) -> list[list[list[float]]]:
        maps = self._derived.get("maps")
        if maps is None:
            raise RodError(
                'wavelength readings need the rod file\'s "fibre": {"wavelength": {...}} section (a reference and '
                "the cores, or a calibration)"
            )
        return maps

    @property
    def route(self) -> str | None:
        """``"calibration"``, ``"physics"`` or None (no wavelength section): how wavelengths become curvature."""
        if self.wavelength is None:
            return None
        return "calibration" if self.wavelength.calibration is not None else "physics"

    def reference_m(self) -> list[list[float]] | None:
        """The reference wavelengths (G, C) [m], or None when the rod file gives none."""
        self._maps()
        ref = self._derived["reference"]
        return None if ref is None else [list(r) for r in ref]

    def shift_maps(self) -> list[list[list[float]]]:
        """Each grating's M_g (2 x C) [1/m per m], u = M_g d with d the core shifts [m] (module docstring), as nested
        lists (G, 2, C)."""
        return [[list(r) for r in m] for m in self._maps()]

    def shift_to_curvature(self, grating: int, shift: Sequence[float]) -> tuple[float, float]:
        """One grating's C wavelength shifts [m] -> its (u_x, u_y) [1/m] (the float path the reading parser uses)."""
        m = self._maps()[grating]
        return (
            sum(a * d for a, d in zip(m[0], shift, strict=True)),
            sum(a * d for a, d in zip(m[1], shift, strict=True)),
        )

    def wavelength_curvature(self, shift: Any) -> Any:
        """Tensor form of :meth:`shift_to_curvature`: shifts (..., G, C) [m] -> curvature (..., G, 2) [1/m], in the
        input's dtype and device (a NaN shift gives NaN)."""
        import torch

        m = torch.tensor(self._maps(), dtype=shift.dtype, device=shift.device)  # (G, 2, C)
        return torch.einsum("gjc,...gc->...gj", m, shift)

    def bending_shift(self, curvature: Any) -> Any:
        """The shifts (..., G, C) [m] the bend (..., G, 2) [1/m] alone gives, so that
        ``wavelength_curvature(bending_shift(u)) == u``: through the physics lambda_ref,c (1 - p_e)
        (u_x y_c - u_y x_c), with a calibration its pseudo-inverse (the least-norm shifts, equal-sum over cores)."""
        import torch

        dtype, device = curvature.dtype, curvature.device
        if self.route == "physics":
            per_strain = torch.tensor(self._derived["per_strain"], dtype=dtype, device=device)  # (G, C)
            return self.strain(curvature) * per_strain
        m = torch.tensor(self._maps(), dtype=dtype, device=device)
        inverse = torch.linalg.pinv(m)  # (G, C, 2)
        return torch.einsum("gcj,...gj->...gc", inverse, curvature)

    def temperature_shift(self, common: Any) -> Any:
        """The shifts (..., G, C) [m] of an apparent common strain ``common`` (..., G) (temperature), as the
        conversion removes it exactly (module docstring): common x lambda_ref,c (1 - p_e) per core through the
        physics; common x mean lambda_ref (1 - p_e), equal on the grating's cores, with a calibration
        (:data:`NOMINAL_WAVELENGTH` without a reference)."""
        import torch

        common = torch.as_tensor(common)
        G, C = len(self._maps()), self.num_cores
        per_strain = self._derived["per_strain"]
        if per_strain is None:
            nominal = NOMINAL_WAVELENGTH * (1.0 - self.wavelength.photoelastic)
            per = torch.full((G, C), nominal, dtype=common.dtype, device=common.device)
        else:
            per = torch.tensor(per_strain, dtype=common.dtype, device=common.device)
        if self.route == "calibration":
            per = per.mean(-1, keepdim=True).expand(G, C)
        return common[..., None] * per

    def wavelength_sigmas(self, sigma: float) -> list[float]:
        """Per grating, the curvature sigma [1/m] that independent wavelength noise ``sigma`` [m] per core implies:
        the larger principal sigma of sigma^2 M_g M_g^T."""

        s = _real("wavelength noise", sigma)
        if s < 0.0:
            raise RodError(f"wavelength noise must be >= 0, got {sigma!r}")
        out = []
        for m in self._maps():
            a = sum(x * x for x in m[0])
            b = sum(x * y for x, y in zip(m[0], m[1], strict=True))
            d = sum(y * y for y in m[1])
            out.append(s * math.sqrt(max(0.0, _symmetric2_eigen(a, b, d)[1])))
        return out

    def peak_layout(self, peaks: Any = None) -> list[tuple[int, int] | None]:
        """Where each value of a peak log line goes: per peak (grating, core) 0-based, or None for a peak that is
        not read. ``peaks`` (an order of :data:`PEAK_ORDERS` or 0-based pairs) overrides the rod file's."""
        self._maps()
        wl = self.wavelength
        G, C = wl.num_gratings, wl.num_cores
        spec = wl.peaks if peaks is None else _check_peaks(peaks, G, C, "--peaks")
        if spec == "by-core":
            return [(k % G, k // G) for k in range(G * C)]
        if spec == "by-grating":
            return [(k // C, k % C) for k in range(G * C)]
        return list(spec)


def _inverse3(m: list[list[float]]) -> list[list[float]]:
    """The inverse of a 3 x 3 matrix (adjugate over determinant)."""
    (a, b, c), (d, e, f), (g, h, i) = m
    co = [
        [e * i - f * h, -(d * i - f * g), d * h - e * g],
        [-(b * i - c * h), a * i - c * g, -(a * h - b * g)],
        [b * f - c * e, -(a * f - c * d), a * e - b * d],
    ]
    det = a * co[0][0] + b * co[0][1] + c * co[0][2]
    return [[co[j][i] / det for j in range(3)] for i in range(3)]


def polar_to_curvature(kappa: Any, phi: Any) -> Any:
    """Curvature magnitude kappa >= 0 [1/m] and bend angle phi [rad] -> (u_x, u_y) = kappa (cos phi, sin phi):
    a pair of floats for floats, a (..., 2) tensor for tensors."""
    if isinstance(kappa, (int, float)) and isinstance(phi, (int, float)):
        return kappa * math.cos(phi), kappa * math.sin(phi)
    import torch

    return torch.stack([kappa * torch.cos(phi), kappa * torch.sin(phi)], -1)
