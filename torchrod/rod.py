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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["Rod", "tube_bending_stiffness"]


def tube_bending_stiffness(outer_diameter: float, inner_diameter: float, youngs_modulus: float) -> float:
    """Bending stiffness EI [N m^2] of a round tube: ``E * pi * (d_out^4 - d_in^4) / 64`` (diameters in m, E in Pa)."""
    return youngs_modulus * math.pi * (outer_diameter**4 - inner_diameter**4) / 64.0


def _positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return v


@dataclass(frozen=True)
class Rod:
    """A straight elastic rod clamped at ``s = 0`` with FBG gratings along it.

    Attributes:
        length: rod length L [m].
        bending_stiffness: EI [N m^2] (isotropic: K_11 = K_22 = EI).
        gratings: grating positions [m], strictly increasing inside [0, L].
        location_bias: the paper's s_bias [m]; reported locations are ``s_model + location_bias``.
        outer_diameter, inner_diameter: tube diameters [m], if the stiffness came from geometry.
        youngs_modulus: E [Pa], if the stiffness came from geometry.
        poisson_ratio: nu, optional (torsion never enters the model: see NOTES.md, erratum 2).

    Build one with :meth:`from_geometry`, the constructor (stiffness given directly), :meth:`from_dict` or
    :meth:`from_json`. The constructor validates everything and raises ``ValueError`` naming the offending value.
    """

    length: float
    bending_stiffness: float
    gratings: tuple[float, ...]
    location_bias: float = 0.0
    outer_diameter: float | None = None
    inner_diameter: float | None = None
    youngs_modulus: float | None = None
    poisson_ratio: float | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "length", _positive("length", self.length))
        set_(self, "bending_stiffness", _positive("bending_stiffness", self.bending_stiffness))
        try:
            g = tuple(float(x) for x in self.gratings)
        except (TypeError, ValueError):
            raise ValueError(f"gratings must be a sequence of numbers, got {self.gratings!r}") from None
        if len(g) == 0:
            raise ValueError("gratings must hold at least one position, got none")
        if not all(math.isfinite(x) for x in g):
            raise ValueError(f"gratings must be finite, got {list(g)}")
        if g[0] < 0.0 or g[-1] > self.length:
            raise ValueError(f"gratings must lie inside [0, {self.length}] m, got {list(g)}")
        if any(b <= a for a, b in itertools.pairwise(g)):
            raise ValueError(f"gratings must be strictly increasing, got {list(g)}")
        set_(self, "gratings", g)
        try:
            bias = float(self.location_bias)
        except (TypeError, ValueError):
            raise ValueError(f"location_bias must be a number, got {self.location_bias!r}") from None
        if not math.isfinite(bias) or abs(bias) >= self.length:
            raise ValueError(f"location_bias must be finite and smaller than the length, got {self.location_bias!r}")
        set_(self, "location_bias", bias)
        geometry = (self.outer_diameter, self.inner_diameter, self.youngs_modulus)
        if any(x is not None for x in geometry):
            if any(x is None for x in geometry):
                raise ValueError(
                    "outer_diameter, inner_diameter and youngs_modulus go together, got "
                    f"{geometry}"
                )
            d_out = _positive("outer_diameter", self.outer_diameter)
            d_in = float(self.inner_diameter)
            if not math.isfinite(d_in) or d_in < 0.0:
                raise ValueError(f"inner_diameter must be >= 0, got {self.inner_diameter!r}")
            if d_in >= d_out:
                raise ValueError(f"inner_diameter ({d_in}) must be smaller than outer_diameter ({d_out})")
            set_(self, "outer_diameter", d_out)
            set_(self, "inner_diameter", d_in)
            set_(self, "youngs_modulus", _positive("youngs_modulus", self.youngs_modulus))
        if self.poisson_ratio is not None:
            nu = float(self.poisson_ratio)
            if not (-1.0 < nu < 0.5):
                raise ValueError(f"poisson_ratio must lie in (-1, 0.5), got {self.poisson_ratio!r}")
            set_(self, "poisson_ratio", nu)

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
    ) -> Rod:
        """A tube of the given diameters [m] and Young's modulus [Pa]; EI follows from them."""
        d_out = _positive("outer_diameter", outer_diameter)
        d_in = float(inner_diameter)
        if d_in < 0.0 or d_in >= d_out:
            raise ValueError(f"inner_diameter ({inner_diameter}) must lie in [0, outer_diameter={d_out})")
        ei = tube_bending_stiffness(d_out, d_in, _positive("youngs_modulus", youngs_modulus))
        return cls(
            length=length,
            bending_stiffness=ei,
            gratings=tuple(gratings),
            location_bias=location_bias,
            outer_diameter=d_out,
            inner_diameter=d_in,
            youngs_modulus=youngs_modulus,
            poisson_ratio=poisson_ratio,
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Rod:
        """From the JSON form (SI units): ``length``, ``gratings``, ``location_bias`` (optional), and either
        ``outer_diameter`` + ``inner_diameter`` + ``youngs_modulus`` or ``bending_stiffness``."""
        if not isinstance(data, Mapping):
            raise ValueError(f"a rod description must be a JSON object, got {type(data).__name__}")  # noqa: TRY004 (a bad file)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown rod keys {unknown}; known keys are {sorted(known)}")
        for key in ("length", "gratings"):
            if key not in data:
                raise ValueError(f"rod description is missing {key!r}")
        geometry = [k for k in ("outer_diameter", "inner_diameter", "youngs_modulus") if k in data]
        if geometry and len(geometry) < 3:
            raise ValueError(
                f"rod description gives {geometry}: outer_diameter, inner_diameter and youngs_modulus go together"
            )
        if "bending_stiffness" not in data and not geometry:
            raise ValueError("rod description needs bending_stiffness, or outer_diameter, inner_diameter and youngs_modulus")
        kwargs = dict(data)
        if "bending_stiffness" not in kwargs:
            return cls.from_geometry(
                length=kwargs["length"],
                outer_diameter=kwargs["outer_diameter"],
                inner_diameter=kwargs["inner_diameter"],
                youngs_modulus=kwargs["youngs_modulus"],
                gratings=_as_sequence(kwargs["gratings"]),
                location_bias=kwargs.get("location_bias", 0.0),
                poisson_ratio=kwargs.get("poisson_ratio"),
            )
        kwargs["gratings"] = tuple(_as_sequence(kwargs["gratings"]))
        return cls(**kwargs)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> Rod:
        """Read a rod file (the JSON form of :meth:`from_dict`)."""
        try:
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
        return cls.from_dict(data)

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

    def grating_positions(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> torch.Tensor:
        """Grating positions as a tensor (G,) [m]."""
        return torch.tensor(self.gratings, dtype=dtype, device=device)

    def with_(self, **changes: Any) -> Rod:
        """A copy with some fields changed. Changing ``bending_stiffness`` drops the geometry that no longer
        produces it."""
        if "bending_stiffness" in changes and not {"outer_diameter", "inner_diameter", "youngs_modulus"} & set(changes):
            changes.update(outer_diameter=None, inner_diameter=None, youngs_modulus=None)
        return dataclasses.replace(self, **changes)

    @property
    def relative_gratings(self) -> tuple[float, ...]:
        """Grating positions divided by the length (the layout a trained network is tied to)."""
        return tuple(g / self.length for g in self.gratings)


def _as_sequence(x: Any) -> Sequence[float]:
    if isinstance(x, (str, bytes)) or not hasattr(x, "__iter__"):
        raise ValueError(f"gratings must be a list of positions in m, got {x!r}")
    return list(x)
