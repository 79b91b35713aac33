"""What sensors other than a (u_x, u_y) reading give, turned into curvature at the edge (SI units).

Multicore fibre (:class:`Fibre`)
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

Curvature magnitude and bend angle
    Commercial shape-sensing systems report kappa >= 0 [1/m] and the bend angle phi [rad] per station:
    u_x = kappa cos phi, u_y = kappa sin phi (:func:`polar_to_curvature`).

The parser of readings (:mod:`torchrod.io.readings`) applies these per reading, so everything past it sees
curvature only. This module imports no torch: a rod file with a fibre is checked without it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .errors import RodError

__all__ = ["MAX_CORE_RADIUS", "MAX_STRAIN", "MIN_CORE_SPREAD", "Fibre", "polar_to_curvature"]

MAX_STRAIN = 0.1
"""A core strain beyond 10 % is refused: glass fibres break at a few percent, so such a value is a unit error (a
strain of 1e-6 is one microstrain)."""

MAX_CORE_RADIUS = 0.05
"""[m] a core farther than this from the rod's axis is refused (a unit error: core positions are in metres)."""

MIN_CORE_SPREAD = 1e-6
"""[m] the smallest RMS distance of the cores from their centre: closer cores (1 um; fibres space them tens of
micrometres apart) read almost no strain from any bend, and their least squares would divide by nearly nothing."""

_COLLINEAR = 1e-8  # smallest / largest eigenvalue of the cores' scatter below which they count as on one line


def _symmetric2_eigen(a: float, b: float, d: float) -> tuple[float, float]:
    """The eigenvalues (small, large) of [[a, b], [b, d]]."""
    mean, diff = 0.5 * (a + d), math.hypot(0.5 * (a - d), b)
    return mean - diff, mean + diff


@dataclass(frozen=True)
class Fibre:
    """A multicore shape-sensing fibre: its cores' positions in the body-frame cross-section.

    Attributes:
        cores: C >= 3 pairs (x_c, y_c) [m], x along d1 and y along d2, not all on one line.

    Raises ``ValueError`` naming the bad core (a bool, a string or null is not a number).
    """

    cores: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        from .rod import _real, _show

        cores = self.cores
        if not isinstance(cores, (list, tuple)):
            raise ValueError(f"fibre.cores must be an array of [x, y] core positions [m], got {_show(cores)}")  # noqa: TRY004
        if len(cores) < 3:
            raise ValueError(f"fibre.cores needs at least 3 cores (not on one line), got {len(cores)}")
        checked = []
        for c, core in enumerate(cores):
            if not isinstance(core, (list, tuple)) or len(core) != 2:
                raise ValueError(f"fibre.cores[{c}] must be a pair [x, y] [m], got {_show(core)}")
            x, y = (_real(f"fibre.cores[{c}][{j}]", v, " [m]") for j, v in enumerate(core))
            if math.hypot(x, y) > MAX_CORE_RADIUS:
                raise ValueError(
                    f"fibre.cores[{c}] = [{x:g}, {y:g}] lies {math.hypot(x, y):g} m from the axis, more than "
                    f"{MAX_CORE_RADIUS:g} m: core positions are in metres (35 um = 3.5e-5)"
                )
            checked.append((x, y))
        object.__setattr__(self, "cores", tuple(checked))
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
            raise ValueError(
                f"fibre.cores {_show([list(c) for c in checked])} lie on one line: the curvature across that line "
                "cannot be told from the common strain; a fibre needs at least 3 cores not on one line"
            )
        # The least-squares map strain -> (u_x, u_y, eps_0): rows of (A^T A)^-1 A^T, kept as Python floats.
        rows = [(y, -x, 1.0) for x, y in checked]
        ata = [[sum(r[i] * r[j] for r in rows) for j in range(3)] for i in range(3)]
        inv = _inverse3(ata)
        pinv = tuple(tuple(sum(inv[i][k] * r[k] for k in range(3)) for r in rows) for i in range(3))
        object.__setattr__(self, "_pinv", pinv)
        object.__setattr__(self, "_cov", (inv[0][0], inv[0][1], inv[1][1]))

    @classmethod
    def from_dict(cls, data: Any) -> Fibre:
        """From the rod file's ``"fibre": {"cores": [[x1, y1], ...]}`` (unknown keys refused)."""
        from .rod import _show

        if not isinstance(data, Mapping):
            raise ValueError(f'fibre must be an object {{"cores": [[x, y], ...]}}, got {_show(data)}')  # noqa: TRY004
        unknown = sorted(str(k) for k in data if k != "cores")
        if unknown:
            raise ValueError(f"unknown fibre keys {unknown}; the known key is 'cores'")
        if "cores" not in data:
            raise ValueError("fibre is missing 'cores' (the [x, y] core positions [m])")
        return cls(cores=data["cores"])

    def to_dict(self) -> dict[str, Any]:
        return {"cores": [list(c) for c in self.cores]}

    @property
    def num_cores(self) -> int:
        return len(self.cores)

    def strain_to_curvature(self, strain: Sequence[float]) -> tuple[float, float]:
        """One grating's C core strains -> its (u_x, u_y) [1/m] by least squares (eps_0 eliminated)."""
        p = self._pinv  # type: ignore[attr-defined]
        return (
            sum(a * e for a, e in zip(p[0], strain, strict=True)),
            sum(a * e for a, e in zip(p[1], strain, strict=True)),
        )

    def curvature_to_strain(self, ux: float, uy: float, common: float = 0.0) -> list[float]:
        """The C core strains that (u_x, u_y) [1/m] and the common strain eps_0 give (the inverse of
        :meth:`strain_to_curvature`)."""
        return [ux * y - uy * x + common for x, y in self.cores]

    def curvature(self, strain: Any) -> Any:
        """Tensor form of :meth:`strain_to_curvature`: strains (..., C) -> curvature (..., 2) [1/m] (a NaN strain
        gives NaN), in the input's dtype and device."""
        import torch

        p = torch.tensor(self._pinv[:2], dtype=strain.dtype, device=strain.device)  # type: ignore[attr-defined]
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
        p = self._pinv  # type: ignore[attr-defined]
        return [[y, -x, 1.0] for x, y in self.cores], [list(p[0]), list(p[1])]

    def curvature_sigma(self, strain_sigma: float) -> float:
        """The curvature sigma [1/m] per component that independent core strain noise ``strain_sigma`` implies
        (the larger principal one where the layout is not isotropic; module docstring)."""
        from .rod import _real

        s = _real("strain noise", strain_sigma)
        if s < 0.0:
            raise ValueError(f"strain noise must be >= 0, got {strain_sigma!r}")
        a, b, d = self._cov  # type: ignore[attr-defined]
        return s * math.sqrt(_symmetric2_eigen(a, b, d)[1])

    @property
    def anisotropy(self) -> float:
        """The ratio of the larger to the smaller principal curvature sigma (1 for an isotropic layout)."""
        small, large = _symmetric2_eigen(*self._cov)  # type: ignore[attr-defined]
        return math.sqrt(large / small)


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
