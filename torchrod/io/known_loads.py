"""Files of readings with known forces, as ``torchrod calibrate`` reads them (:func:`read_readings`).

One reading a line, JSON or CSV: ``{"id": ..., "curvature": [[u_x, u_y] or null, ...], "forces": [{"s": ...,
"fx": ..., "fy": ...}, ...]}``, one curvature pair per grating [1/m] (or the rod's fibre's quantity: strain,
wavelengths), the known forces with ``s`` [m] in the true (fibre's) coordinate and components [N] in the body
frame. The reading follows the rules of every reading (:mod:`torchrod.io.reading`); the fit itself is
:func:`torchrod.calibrate`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import torch

from ..errors import ReadingError
from ..estimate.calibration import CalibrationData
from ..loads import PointForces
from ..rod import Rod
from .numbers import as_number
from .reading import parse_reading as parse_one
from .sources import iter_records, unusable_lines
from .values import describe

__all__ = ["parse_reading", "read_readings"]


def parse_reading(
    obj: Any, num_gratings: int, gratings: Sequence[float] | None = None, fibre: Any = None
) -> tuple[list[list[float] | None], list[tuple[float, float, float]]]:
    """One calibration record: the curvature pairs (None where missing) and the known forces (s, f_x, f_y).

    The reading itself (``curvature`` or ``strain`` or ``curvature_polar``, ``id``, ``t``, ``gratings``; other keys
    ignored) follows the rules of every
    reading (:mod:`torchrod.io.reading`); ``forces`` is required, a list of ``{"s", "fx", "fy"}`` objects (finite,
    nonzero). Raises ``ValueError`` naming the first bad field.
    """
    reading = parse_one(obj, num_gratings, gratings, fibre=fibre)
    if "forces" not in obj:
        raise ReadingError('missing \'forces\' (the known forces, [{"s": ..., "fx": ..., "fy": ...}, ...])')
    forces = obj["forces"]
    if not isinstance(forces, list):
        raise ReadingError(f"forces must be an array of {{'s', 'fx', 'fy'}} objects, got {describe(forces)}")  # noqa: TRY004
    known = []
    for j, force in enumerate(forces):
        if not isinstance(force, dict) or set(force) != {"s", "fx", "fy"}:
            raise ReadingError(f"forces[{j}] must be an object with keys 's', 'fx', 'fy', got {describe(force)}")
        s, fx, fy = (as_number(force[k], f"forces[{j}].{k}") for k in ("s", "fx", "fy"))
        if fx == 0.0 and fy == 0.0:
            raise ReadingError(f"forces[{j}] has zero magnitude: a known force must be nonzero")
        known.append((s, fx, fy))
    pairs = [None if math.isnan(ux) else [ux, uy] for ux, uy in reading.curvature.tolist()]
    return pairs, known


def read_readings(
    path: str | os.PathLike,
    rod: Rod,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    fmt: str = "auto",
    quantity: str = "curvature",
    max_line: int | None = None,
) -> CalibrationData:
    """Read a file of readings with known forces (format in the module docstring; ``"-"`` reads standard input):
    JSON lines, or CSV (:data:`torchrod.io.sources.FORMATS`; the known forces in the columns ``s_J, fx_J, fy_J``,
    J = 1, 2, ..., all three empty for a force a row does not have), in the units the rod's fibre says.

    Every line is checked; raises ``ValueError`` naming the bad lines (the first five, and how many there are)
    when any line cannot be used, or when no reading is found. ``max_line``: the longest line read [bytes] (None:
    the rod's, :func:`torchrod.io.sources.line_limit`).
    """
    name = "standard input" if os.fspath(path) == "-" else os.fspath(path)
    rows, forces, ids, bad = [], [], [], []

    def parse(obj: Any) -> Any:
        return parse_reading(obj, rod.num_gratings, rod.gratings, rod.fibre)

    records = iter_records(path, rod.num_gratings, parse, fmt, quantity=quantity, fibre=rod.fibre, max_line=max_line)
    for record in records:
        if not record.ok or record.value is None:
            bad.append(record.error)
            continue
        pairs, known = record.value
        rows.append(pairs)
        forces.append(known)
        ids.append(record.id)
    if bad:
        raise unusable_lines(name, bad)
    if not rows:
        raise ReadingError(f"{name}: no readings")
    present = torch.tensor([[p is not None for p in r] for r in rows], dtype=torch.bool, device=device)
    curvature = torch.tensor(
        [[p if p is not None else [0.0, 0.0] for p in r] for r in rows], dtype=dtype, device=device
    )
    loads = PointForces.from_lists(forces, dtype=dtype, device=device)
    return CalibrationData(curvature, present, loads, tuple(ids))
