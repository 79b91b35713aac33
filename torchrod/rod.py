"""The rod: length, bending stiffness, FBG grating positions and location bias (SI units throughout).

A :class:`Rod` is a frozen description of a straight, isotropic, inextensible and unshearable elastic rod clamped
at its base (arc length ``s = 0``) and free at its tip (``s = length``). Its bending stiffness ``EI`` [N m^2] is
either given directly or computed from a tube's geometry and Young's modulus. The FBG gratings that read the
curvature sit at ``gratings`` [m] along it. The location bias [m] is the paper's ``s_bias``: an estimated location is
``s_model + location_bias``.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from .errors import RodError, RodWarning
from .values import clip as _clip
from .values import is_number
from .values import positive as _positive
from .values import real as _real
from .values import show as _show

if TYPE_CHECKING:  # torch is imported where a tensor is made: a rod file can be checked without it
    import torch

    from .sensors import Fibre

__all__ = [
    "AGREEMENT",
    "COINCIDENT",
    "DEFAULT_POISSON_RATIO",
    "LENGTH_RANGE",
    "MAX_DIAMETER",
    "YOUNGS_MODULUS_RANGE",
    "FORCE_RULE",
    "MAX_CALIBRATION_ERROR",
    "MIN_TEST_DOF",
    "Rod",
    "max_testable_forces",
    "tube_bending_stiffness",
]

DEFAULT_POISSON_RATIO = 0.33
"""nu for the torsional stiffness GJ = EI / (1 + nu) of a tube when the rod gives neither ``poisson_ratio`` nor
``torsional_stiffness`` (a straight rod never twists under follower forces, so there it changes nothing)."""

AGREEMENT = 1e-9
"""Relative tolerance within which a given ``bending_stiffness`` and the one the geometry gives must agree."""

MAX_FILE_BYTES = 16 * 2**20
"""A rod file larger than this (16 MiB) is refused unread: it cannot be a rod description."""

LENGTH_RANGE = (1e-3, 20.0)
"""[m] The plausible rod lengths (1 mm to 20 m): a length outside is taken for a unit error (a rod file written in
millimetres) and refused, with the conversion to SI in the message."""

YOUNGS_MODULUS_RANGE = (1e6, 1.2e12)
"""[Pa] The plausible Young's moduli: from soft elastomers (about 1 MPa) to diamond (about 1.2 TPa). A modulus
outside (``193`` for a steel in GPa) is refused as a unit error; :mod:`torchrod.estimate.calibration` holds a
fitted modulus to the same range."""

MAX_DIAMETER = 0.1
"""[m] The largest plausible tube diameter: a larger one is taken for a unit error (millimetres) and refused."""

COINCIDENT = 1e-6
"""Gratings closer than this fraction of the length read the same curvature (a warning); a force must be able to
act on at least this fraction of the length distal to the first grating, else no reading can see any force."""

_GEOMETRY = ("outer_diameter", "inner_diameter", "youngs_modulus")


def tube_bending_stiffness(outer_diameter: float, inner_diameter: float, youngs_modulus: float) -> float:
    """Bending stiffness EI [N m^2] of a round tube: ``E * pi * (d_out^4 - d_in^4) / 64`` (diameters in m, E in Pa)."""
    return youngs_modulus * math.pi * (outer_diameter**4 - inner_diameter**4) / 64.0


def _geometry_stiffness(
    outer_diameter: Any, inner_diameter: Any, youngs_modulus: Any
) -> tuple[float, float, float, float]:
    """Checked (d_out [m], d_in [m], E [Pa], EI [N m^2]) of a tube; ``ValueError`` naming the bad one."""
    d_out = _positive("outer_diameter", outer_diameter, " [m]")
    d_in = _real("inner_diameter", inner_diameter, " [m]")
    if d_in < 0.0:
        raise RodError(f"inner_diameter must be >= 0 [m] (0 for a solid rod), got {_show(inner_diameter)}")
    if d_in >= d_out:
        raise RodError(f"inner_diameter ({_show(inner_diameter)} m) must be smaller than outer_diameter ({d_out} m)")
    e = _positive("youngs_modulus", youngs_modulus, " [Pa]")
    ei = tube_bending_stiffness(d_out, d_in, e)
    if not (math.isfinite(ei) and ei > 0.0):
        raise RodError(
            f"outer_diameter {d_out} m, inner_diameter {d_in} m and youngs_modulus {e} Pa give a bending "
            f"stiffness of {ei} N m^2, not a positive finite number"
        )
    return d_out, d_in, e, ei


def _as_si(value: float, unit: str, scales: Sequence[tuple[str, float]], plausible: tuple[float, float]) -> str:
    """The first reading of ``value`` in another unit that is plausible, as advice (``"; in millimetres? give
    0.4"``), or nothing."""
    for name, factor in scales:
        converted = value * factor
        if plausible[0] <= converted <= plausible[1]:
            return f" (if it is in {name}, give {converted:.6g} {unit})"
    return ""


def _unit_problems(length: float, geometry: tuple[float, float, float] | None) -> list[str]:
    """What in a rod's length and tube geometry is implausible in SI units (each with its likely conversion)."""
    out = []
    lo, hi = LENGTH_RANGE
    if not lo <= length <= hi:
        fix = _as_si(length, "m", (("millimetres", 1e-3), ("centimetres", 1e-2)), LENGTH_RANGE)
        out.append(f"length = {length:g} m lies outside the plausible {lo * 1e3:g} mm to {hi:g} m{fix}")
    if geometry is not None:
        d_out, d_in, e = geometry
        for name, d in (("outer_diameter", d_out), ("inner_diameter", d_in)):
            if d > MAX_DIAMETER:
                fix = _as_si(d, "m", (("millimetres", 1e-3),), (0.0, MAX_DIAMETER))
                out.append(f"{name} = {d:g} m is larger than {MAX_DIAMETER:g} m{fix}")
        lo, hi = YOUNGS_MODULUS_RANGE
        if not lo <= e <= hi:
            fix = _as_si(e, "Pa", (("GPa", 1e9), ("MPa", 1e6)), YOUNGS_MODULUS_RANGE)
            out.append(f"youngs_modulus = {e:g} Pa lies outside the plausible {lo:g} to {hi:g} Pa{fix}")
    return out


@dataclass(frozen=True)
class Rod:
    """A straight elastic rod clamped at ``s = 0`` with FBG gratings along it.

    Attributes:
        length: rod length L [m].
        bending_stiffness: EI [N m^2] (isotropic: K_11 = K_22 = EI).
        gratings: grating positions [m], strictly increasing inside [0, L].
        location_bias: the paper's s_bias [m]; reported locations are ``s_model + location_bias``.
        outer_diameter: the tube's outer diameter [m], if the stiffness came from geometry.
        inner_diameter: the tube's inner diameter [m] (0 for a solid rod), if the stiffness came from geometry.
        youngs_modulus: E [Pa], if the stiffness came from geometry.
        poisson_ratio: nu, optional: the torsional stiffness is GJ = EI / (1 + nu) (nu = ``DEFAULT_POISSON_RATIO``
            when neither it nor ``torsional_stiffness`` is given). Torsion enters only a precurved rod: a straight
            one never twists under follower forces (``docs/physics.md``, erratum 2).
        torsional_stiffness: GJ [N m^2] given directly, instead of ``poisson_ratio``.
        intrinsic_curvature: the unloaded rod's body-frame curvature u* [1/m], piecewise constant: segments
            ``(from, to, ux, uy)`` ([m], [m], [1/m], [1/m]), sorted and not overlapping, zero elsewhere; JSON
            ``[{"from": s0, "to": s1, "u": [ux, uy]}, ...]``. A rod without any is straight.
        fibre: the sensor (:class:`torchrod.sensors.Fibre`, or its JSON form ``{"cores": [[x, y], ...],
            "wavelength": {...}, "curvature_unit": ..., ...}``), optional: needed only for readings given as core
            strains or peak wavelengths, or in units other than SI (docs/sensors.md).
        calibration_error: the relative error of each grating's calibration (a fraction of the signal: 0.1 for a
            gain known to 10 %), one per grating, or () for none (a single number is every grating's; all zeros is
            none). The estimator then weighs each value of a reading by ``sigma_k^2 = sigma^2 + (rel_k |u_k|)^2``
            (:meth:`calibration_variance`, docs/guides/calibrate.md); ``torchrod calibrate --fibre`` writes it.

    Build one with :meth:`from_geometry`, the constructor (stiffness given directly), :meth:`from_dict` or
    :meth:`from_json`. The constructor validates everything strictly (a bool, a string or null is not a number;
    every value finite and in its physical range) and raises ``ValueError`` naming the offending key and value.
    Given both the stiffness and the geometry, they must agree to ``AGREEMENT`` (relative); the geometry's value
    is then kept, so that a rod and its JSON form compare equal.
    """

    length: float
    bending_stiffness: float
    gratings: tuple[float, ...]
    location_bias: float = 0.0
    outer_diameter: float | None = None
    inner_diameter: float | None = None
    youngs_modulus: float | None = None
    poisson_ratio: float | None = None
    fibre: Fibre | None = None
    torsional_stiffness: float | None = None
    intrinsic_curvature: tuple[tuple[float, float, float, float], ...] = ()
    calibration_error: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        length = _positive("length", self.length, " [m]")
        set_(self, "length", length)
        ei = _positive("bending_stiffness", self.bending_stiffness, " [N m^2]")
        geometry = {k: getattr(self, k) for k in _GEOMETRY}
        given = [k for k, v in geometry.items() if v is not None]
        if given and len(given) < 3:
            missing = [k for k in _GEOMETRY if k not in given]
            raise RodError(
                f"outer_diameter, inner_diameter and youngs_modulus go together: {given} given, {missing} missing"
            )
        checked = _geometry_stiffness(*geometry.values()) if given else None
        problems = _unit_problems(length, checked[:3] if checked else None)
        if problems:
            raise RodError(
                "implausible rod values, as if not in SI units (metres, pascals): "
                + "; ".join(problems)
                + ". Give the rod in SI units"
            )
        set_(self, "gratings", _check_gratings(self.gratings, length))
        bias = _real("location_bias", self.location_bias, " [m]")
        if abs(bias) >= length:
            raise RodError(
                f"location_bias must be smaller in size than the length ({length} m), got {_show(self.location_bias)}"
            )
        set_(self, "location_bias", bias)
        if checked is not None:
            d_out, d_in, e, ei_geometry = checked
            if not math.isclose(ei, ei_geometry, rel_tol=AGREEMENT, abs_tol=0.0):
                raise RodError(
                    f"bending_stiffness {_show(self.bending_stiffness)} N m^2 contradicts the geometry "
                    f"(outer_diameter {d_out} m, inner_diameter {d_in} m, youngs_modulus {e} Pa give "
                    f"{ei_geometry:.9g} N m^2): give one or the other, or values that agree to {AGREEMENT:g}"
                )
            ei = ei_geometry
            set_(self, "outer_diameter", d_out)
            set_(self, "inner_diameter", d_in)
            set_(self, "youngs_modulus", e)
        set_(self, "bending_stiffness", ei)
        if self.poisson_ratio is not None:
            nu = _real("poisson_ratio", self.poisson_ratio)
            if not (-1.0 < nu < 0.5):
                raise RodError(f"poisson_ratio must lie in (-1, 0.5), got {_show(self.poisson_ratio)}")
            set_(self, "poisson_ratio", nu)
        if self.fibre is not None:
            from .sensors import Fibre

            if not isinstance(self.fibre, Fibre):
                set_(self, "fibre", Fibre.from_dict(self.fibre))
            self.fibre.check_gratings(len(self.gratings))
        if self.torsional_stiffness is not None:
            if self.poisson_ratio is not None:
                raise RodError(
                    f"give poisson_ratio ({_show(self.poisson_ratio)}) or torsional_stiffness "
                    f"({_show(self.torsional_stiffness)} N m^2), not both"
                )
            set_(self, "torsional_stiffness", _positive("torsional_stiffness", self.torsional_stiffness, " [N m^2]"))
        set_(self, "intrinsic_curvature", _check_intrinsic(self.intrinsic_curvature, length))
        set_(self, "calibration_error", _check_calibration_error(self.calibration_error, len(self.gratings)))
        for text in self.limitations:
            warnings.warn(text, RodWarning, stacklevel=3)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_geometry(
        cls,
        length: float,
        outer_diameter: float,
        inner_diameter: float,
        youngs_modulus: float,
        gratings: Sequence[float],
        location_bias: float = 0.0,
        poisson_ratio: float | None = None,
        fibre: Fibre | Mapping[str, Any] | None = None,
        torsional_stiffness: float | None = None,
        intrinsic_curvature: Any = (),
        calibration_error: Any = (),
    ) -> Rod:
        """A tube of the given diameters [m] and Young's modulus [Pa]; EI follows from them."""
        d_out, d_in, e, ei = _geometry_stiffness(outer_diameter, inner_diameter, youngs_modulus)
        return cls(
            length=length,
            bending_stiffness=ei,
            gratings=cast("tuple[float, ...]", gratings),  # __post_init__ makes the tuple
            location_bias=location_bias,
            outer_diameter=d_out,
            inner_diameter=d_in,
            youngs_modulus=e,
            poisson_ratio=poisson_ratio,
            fibre=cast("Fibre | None", fibre),  # __post_init__ reads a mapping as a Fibre
            torsional_stiffness=torsional_stiffness,
            intrinsic_curvature=intrinsic_curvature,
            calibration_error=calibration_error,
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Rod:
        """From the JSON form (SI units): ``length``, ``gratings``, ``location_bias`` (optional), and
        ``bending_stiffness`` or ``outer_diameter`` + ``inner_diameter`` + ``youngs_modulus`` (or both, if they
        agree to ``AGREEMENT``), ``poisson_ratio`` or ``torsional_stiffness`` (optional), ``fibre`` (optional:
        :meth:`torchrod.sensors.Fibre.from_dict`), ``intrinsic_curvature`` (optional:
        ``[{"from", "to", "u": [ux, uy]}, ...]``), ``calibration_error`` (optional: one fraction per grating, or one
        for all). Unknown keys are refused (a misspelt key would otherwise be
        ignored)."""
        if not isinstance(data, Mapping):
            raise RodError(f"a rod description must be a JSON object, got {type(data).__name__}")  # noqa: TRY004 (a bad file)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(_show(k) if not isinstance(k, str) else k for k in data if k not in known)
        if unknown:
            raise RodError(_clip(f"unknown rod keys {unknown}; known keys are {sorted(known)}"))
        for key in ("length", "gratings"):
            if key not in data:
                raise RodError(f"rod description is missing {key!r}")
        geometry = [k for k in _GEOMETRY if k in data]
        if geometry and len(geometry) < 3:
            raise RodError(
                f"rod description gives {geometry}: outer_diameter, inner_diameter and youngs_modulus go together"
            )
        if "bending_stiffness" not in data and not geometry:
            raise RodError(
                "rod description needs bending_stiffness, or outer_diameter, inner_diameter and youngs_modulus"
            )
        if "bending_stiffness" not in data:
            return cls.from_geometry(**data)
        return cls(**data)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> Rod:
        """Read a rod file (the JSON form of :meth:`from_dict`, UTF-8).

        Every problem is one :class:`~torchrod.errors.RodError` (a ``ValueError``) naming the file: a directory, an
        unreadable or missing file, a file over ``MAX_FILE_BYTES``, text that is not JSON (or repeats a key), and
        what :meth:`from_dict` refuses.
        """
        name = os.fspath(path)
        if os.path.isdir(name):
            raise RodError(f"{name}: is a directory, not a rod file")
        try:
            with open(name, "rb") as fh:
                raw = fh.read(MAX_FILE_BYTES + 1)
        except OSError as exc:
            raise RodError(f"{name}: cannot read the rod file ({exc.strerror or type(exc).__name__})") from None
        if len(raw) > MAX_FILE_BYTES:
            raise RodError(f"{name}: larger than {MAX_FILE_BYTES // 2**20} MiB, not a rod file")
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError:
            raise RodError(f"{name}: not a rod file (not UTF-8 text)") from None
        try:
            data = json.loads(text, object_pairs_hook=_no_repeated_keys)
        except json.JSONDecodeError as exc:
            raise RodError(f"{name}: not valid JSON ({exc})") from None
        except RecursionError:
            raise RodError(f"{name}: not a rod file (nested too deeply)") from None
        except ValueError as exc:  # a repeated key, or an integer beyond Python's int-to-text limit
            raise RodError(f"{name}: {_clip(str(exc))}") from None
        try:
            return cls.from_dict(data)
        except ValueError as exc:
            raise RodError(f"{name}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form; geometry is written when known, else ``bending_stiffness``."""
        out: dict[str, Any] = {"length": self.length}
        if self.outer_diameter is not None:
            out["outer_diameter"] = self.outer_diameter
            out["inner_diameter"] = self.inner_diameter
            out["youngs_modulus"] = self.youngs_modulus
        else:
            out["bending_stiffness"] = self.bending_stiffness
        if self.poisson_ratio is not None:
            out["poisson_ratio"] = self.poisson_ratio
        out["gratings"] = list(self.gratings)
        out["location_bias"] = self.location_bias
        if self.fibre is not None:
            out["fibre"] = self.fibre.to_dict()
        if self.torsional_stiffness is not None:
            out["torsional_stiffness"] = self.torsional_stiffness
        if self.intrinsic_curvature:
            out["intrinsic_curvature"] = [
                {"from": a, "to": b, "u": [ux, uy]} for a, b, ux, uy in self.intrinsic_curvature
            ]
        if self.calibration_error:
            out["calibration_error"] = list(self.calibration_error)
        return out

    def to_json(self, path: str | os.PathLike) -> None:
        """Write the JSON form to ``path``."""
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=2)
            fh.write("\n")

    # ------------------------------------------------------------------ helpers
    @property
    def num_gratings(self) -> int:
        return len(self.gratings)

    @property
    def precurved(self) -> bool:
        """Whether the unloaded rod is curved somewhere (a nonzero ``intrinsic_curvature``)."""
        return any(ux != 0.0 or uy != 0.0 for _, _, ux, uy in self.intrinsic_curvature)

    @property
    def torsion_stiffness(self) -> float:
        """GJ [N m^2]: ``torsional_stiffness``, else EI / (1 + nu) with nu = ``poisson_ratio`` or
        ``DEFAULT_POISSON_RATIO``."""
        if self.torsional_stiffness is not None:
            return self.torsional_stiffness
        nu = DEFAULT_POISSON_RATIO if self.poisson_ratio is None else self.poisson_ratio
        return self.bending_stiffness / (1.0 + nu)

    def intrinsic_at(self, s: Sequence[float], side: str = "distal") -> list[tuple[float, float]]:
        """u* = (ux*, uy*) [1/m] at each position s [m]; at a breakpoint, the value just distal to it (towards the
        tip), which is what a grating there reads on the unloaded rod, or with ``side="proximal"`` the value just
        before it."""
        if side not in ("distal", "proximal"):
            raise RodError(f"side must be 'distal' or 'proximal', got {side!r}")
        out = []
        for x in s:
            value = (0.0, 0.0)
            for a, b, ux, uy in self.intrinsic_curvature:
                inside = (a <= x < b or x == b == self.length) if side == "distal" else (a < x <= b or x == a == 0.0)
                if inside:
                    value = (ux, uy)
            out.append(value)
        return out

    def unloaded_curvature(
        self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """(G, 2) what the gratings read on the unloaded rod [1/m]: u* at each (the distal value at a breakpoint),
        zero for a straight rod (``dtype`` default float64)."""
        import torch

        return torch.tensor(
            self.intrinsic_at(self.gratings), dtype=torch.float64 if dtype is None else dtype, device=device
        ).reshape(self.num_gratings, 2)

    def calibration_variance(self, curvature: torch.Tensor) -> torch.Tensor:
        """(..., G, 2) the variance [1/m^2] the calibration error adds to each value of readings ``curvature``
        (..., G, 2) [1/m]: ``(rel_g |u|)^2`` with the measured value u (so a reading's weights are fixed before any
        fit); zeros for a rod without a calibration error, and at a value that is not finite (a missing grating)."""
        import torch

        if not self.calibration_error:
            return torch.zeros_like(curvature)
        rel = torch.tensor(self.calibration_error, dtype=curvature.dtype, device=curvature.device)
        u = torch.nan_to_num(curvature, nan=0.0, posinf=0.0, neginf=0.0)
        return (rel[:, None] * u).square()

    def breakpoints(self) -> list[float]:
        """The positions [m] inside (0, L) where u* may jump: every segment's ends."""
        return sorted({x for a, b, _, _ in self.intrinsic_curvature for x in (a, b) if 0.0 < x < self.length})

    def grating_positions(
        self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """Grating positions as a tensor (G,) [m] (``dtype`` default float64)."""
        import torch

        return torch.tensor(self.gratings, dtype=torch.float64 if dtype is None else dtype, device=device)

    def with_(self, **changes: Any) -> Rod:
        """A copy with some fields changed. Changing ``bending_stiffness`` alone drops the geometry that no longer
        produces it; changing the geometry alone recomputes the stiffness from it."""
        touched = set(_GEOMETRY) & set(changes)
        if "bending_stiffness" in changes and not touched:
            changes.update(outer_diameter=None, inner_diameter=None, youngs_modulus=None)
        elif touched and "bending_stiffness" not in changes:
            geometry = [changes.get(k, getattr(self, k)) for k in _GEOMETRY]
            if all(v is not None for v in geometry):
                changes["bending_stiffness"] = _geometry_stiffness(*geometry)[3]
        return dataclasses.replace(self, **changes)

    def differences(self, other: Rod, rel_tol: float = AGREEMENT) -> list[str]:
        """What a reading depends on that differs between ``self`` and ``other``: the length, the bending stiffness
        and the grating positions (relative tolerance ``rel_tol``; the location bias and how the stiffness was
        given do not count). Empty when they agree; else one phrase each, ``self``'s value first."""
        out = []
        if not math.isclose(self.length, other.length, rel_tol=rel_tol):
            out.append(f"length {self.length} m vs {other.length} m")
        if not math.isclose(self.bending_stiffness, other.bending_stiffness, rel_tol=rel_tol):
            out.append(f"bending_stiffness {self.bending_stiffness:.9g} vs {other.bending_stiffness:.9g} N m^2")
        if not math.isclose(self.torsion_stiffness, other.torsion_stiffness, rel_tol=rel_tol) and (
            self.precurved or other.precurved
        ):
            out.append(f"torsional stiffness {self.torsion_stiffness:.9g} vs {other.torsion_stiffness:.9g} N m^2")
        if self.intrinsic_curvature != other.intrinsic_curvature and (self.precurved or other.precurved):
            out.append(
                _clip(f"intrinsic curvature {list(self.intrinsic_curvature)}")
                + " vs "
                + _clip(f"{list(other.intrinsic_curvature)}")
            )
        tol = rel_tol * max(self.length, other.length)
        if self.num_gratings != other.num_gratings or any(
            abs(a - b) > tol for a, b in zip(self.gratings, other.gratings, strict=False)
        ):
            out.append(
                _clip(f"{self.num_gratings} gratings at {list(self.gratings)}")
                + " vs "
                + _clip(f"{other.num_gratings} at {list(other.gratings)}")
            )
        return out

    @property
    def limitations(self) -> tuple[str, ...]:
        """What this rod cannot determine, one sentence each (empty for a rod without such limits). Each is also
        given as a :class:`~torchrod.errors.RodWarning` when the rod is made (the CLI prints it):

        - a single grating: two values per reading, fewer than a force's three unknowns (s, f_x, f_y);
        - a first grating beyond half the length: a force proximal to it bends no grating, so no reading sees it;
        - two gratings closer than :data:`COINCIDENT` times the length: they read the same curvature, which then
          counts twice in the fit (a count test too sure of itself, when they carry one sensor's value twice).

        A rod on which no force can be seen at all (its only grating at the tip) is refused when it is made.
        """
        out = []
        L, g = self.length, self.gratings
        if len(g) == 1:
            out.append(
                f"a single grating (at {g[0]:g} m) reads 2 values per reading, fewer than the 3 unknowns (s, fx, fy) "
                "of one force: it cannot locate a force; give the rod's other gratings"
            )
        if g[0] > 0.5 * L:
            out.append(
                f"the first grating lies at {g[0]:g} m, {100 * g[0] / L:.0f} % of the length: a force proximal to "
                "it bends no grating, so no reading can see a force there (answers say 0 forces)"
            )
        for k, (a, b) in enumerate(itertools.pairwise(g), start=1):
            if b - a < COINCIDENT * L:
                out.append(
                    f"gratings[{k - 1}] and gratings[{k}] lie {b - a:.3g} m apart: they read the same curvature, which "
                    "counts twice in the fit (a count test too sure of itself if they carry one sensor's value "
                    "twice); give one of them"
                )
                break
        return tuple(out)

    @property
    def relative_gratings(self) -> tuple[float, ...]:
        """Grating positions divided by the length (the layout a trained network is tied to)."""
        return tuple(g / self.length for g in self.gratings)


def _check_gratings(gratings: Any, length: float) -> tuple[float, ...]:
    """Grating positions [m] as a tuple of floats: a list of finite numbers, strictly increasing inside [0, L]."""
    if (
        isinstance(gratings, (str, bytes, Mapping, set, frozenset))
        or not isinstance(gratings, Iterable)
        or getattr(gratings, "ndim", 1) != 1
    ):
        raise RodError(f"gratings must be a list of positions [m], got {_show(gratings)}")
    g = tuple(_real(f"gratings[{k}]", x, " [m]") for k, x in enumerate(gratings))
    if not g:
        raise RodError("gratings must hold at least one position, got none")
    for k, x in enumerate(g):
        if not 0.0 <= x <= length:
            fix = _as_si(x, "m", (("millimetres", 1e-3), ("centimetres", 1e-2)), (0.0, length))
            raise RodError(
                f"gratings[{k}] = {x:g} m must lie inside the rod, [0, {length:g}] m: positions are in metres from "
                f"the base, as the length{fix}"
            )
    if length - g[0] < COINCIDENT * length:
        raise RodError(
            f"no grating lies proximal to the tip (the first is at {g[0]:g} m of {length:g} m): a force anywhere on "
            "the rod bends the rod only proximal to it, so no grating could ever read one; give the gratings "
            "between the base and the loads"
        )
    for k, (a, b) in enumerate(itertools.pairwise(g), start=1):
        if b <= a:
            raise RodError(f"gratings must be strictly increasing: gratings[{k}] = {b} m follows {a} m")
    return g


MAX_CALIBRATION_ERROR = 10.0
"""The largest relative calibration error a rod may give (1000 % of the signal): a larger one is no calibration."""


def _check_calibration_error(errors: Any, count: int) -> tuple[float, ...]:
    """Relative calibration errors as a tuple of ``count`` floats in [0, MAX_CALIBRATION_ERROR] (one number: every
    grating's), or () for none (all zeros)."""
    if is_number(errors) or isinstance(errors, bool):
        errors = [errors] * count
    if (
        isinstance(errors, (str, bytes, Mapping, set, frozenset))
        or not isinstance(errors, Iterable)
        or getattr(errors, "ndim", 1) != 1
    ):
        raise RodError(f"calibration_error must be a fraction, or a list of one per grating, got {_show(errors)}")
    out = tuple(_real(f"calibration_error[{k}]", x, " (a fraction of the signal)") for k, x in enumerate(errors))
    if len(out) not in (0, count):
        raise RodError(f"calibration_error must hold one fraction per grating ({count}), got {len(out)}")
    for k, x in enumerate(out):
        if not 0.0 <= x <= MAX_CALIBRATION_ERROR:
            raise RodError(
                f"calibration_error[{k}] must lie in [0, {MAX_CALIBRATION_ERROR:g}] (a fraction of the signal: 0.1 "
                f"for 10 %), got {x:g}"
            )
    return out if any(x > 0.0 for x in out) else ()


def _check_intrinsic(segments: Any, length: float) -> tuple[tuple[float, float, float, float], ...]:
    """Intrinsic-curvature segments as sorted ``(from, to, ux, uy)`` tuples: from the JSON form (dicts with
    ``from``, ``to``, ``u``) or tuples; each inside [0, L] with from < to, none overlapping."""
    if segments is None:
        return ()
    if isinstance(segments, (str, bytes, Mapping)) or not isinstance(segments, Iterable):
        raise RodError(f"intrinsic_curvature must be a list of segments, got {_show(segments)}")
    out = []
    for k, seg in enumerate(segments):
        where = f"intrinsic_curvature[{k}]"
        if isinstance(seg, Mapping):
            extra = sorted(str(key) for key in seg if key not in ("from", "to", "u"))
            missing = [key for key in ("from", "to", "u") if key not in seg]
            if extra or missing:
                raise RodError(
                    f'{where} must be {{"from": s0, "to": s1, "u": [ux, uy]}}'
                    + (f": unknown {extra}" if extra else "")
                    + (f": missing {missing}" if missing else "")
                )
            u = seg["u"]
            if isinstance(u, (str, bytes, Mapping)) or not isinstance(u, Sequence) or len(u) != 2:
                raise RodError(f"{where}.u must be [ux, uy] [1/m], got {_show(u)}")
            a, b, ux, uy = seg["from"], seg["to"], u[0], u[1]
        elif isinstance(seg, Sequence) and not isinstance(seg, (str, bytes)) and len(seg) == 4:
            a, b, ux, uy = seg
        else:
            raise RodError(f'{where} must be {{"from": s0, "to": s1, "u": [ux, uy]}}, got {_show(seg)}')
        a = _real(f"{where}.from", a, " [m]")
        b = _real(f"{where}.to", b, " [m]")
        ux = _real(f"{where}.u[0]", ux, " [1/m]")
        uy = _real(f"{where}.u[1]", uy, " [1/m]")
        if not 0.0 <= a < b <= length:
            raise RodError(f"{where} must satisfy 0 <= from < to <= length ({length} m), got from {a}, to {b}")
        out.append((a, b, ux, uy))
    out.sort()
    for (a0, b0, *_), (a1, b1, *_) in itertools.pairwise(out):
        if a1 < b0:
            raise RodError(f"intrinsic_curvature segments [{a0}, {b0}] and [{a1}, {b1}] m overlap")
    return tuple(out)


def _no_repeated_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object as a dict, refusing a key given twice (``json`` would silently keep the last)."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise RodError(_clip(f"the key {key!r} appears twice in one object"))
        out[key] = value
    return out


# ------------------------------------------------------------------------------------------------ what a rod can tell
MIN_TEST_DOF = 3
"""The fewest degrees of freedom a fit must leave for its count to be tested against the noise (a chi-square test of
fewer says little): :func:`max_testable_forces`."""

FORCE_RULE = (
    "a fit of h forces has 3h unknowns (s, fx, fy each) against the 2G values of a reading (ux, uy at each of G "
    f"gratings); h forces can be told apart when 2G - 3h >= {MIN_TEST_DOF} degrees of freedom are left to test the "
    "fit against the noise"
)
"""The rule of :func:`max_testable_forces`, in words."""


def max_testable_forces(num_gratings: int) -> int:
    """The most forces that readings of ``num_gratings`` gratings can tell apart (:data:`FORCE_RULE`): the largest h
    with ``2 G - 3 h >= MIN_TEST_DOF`` (0 when not even one force leaves that many; a reading that misses gratings
    has fewer)."""
    return max(0, (2 * num_gratings - MIN_TEST_DOF) // 3)
