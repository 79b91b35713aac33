"""Ready-made rods.

``nitinol290`` is the paper's Nitinol tube (Xiao & Chen): L = 290 mm, d_out = 1.397 mm, d_in = 1.118 mm,
E = 67 GPa (EI about 7.39e-3 N m^2), FBG gratings every 20 mm at 10, 30, ..., 270 mm (14 gratings).
Its calibrated location bias is -3.12 mm; the preset ships with ``location_bias=0`` (an uncalibrated rod) and
``nitinol290(calibrated=True)`` carries the paper's value.

Each preset also ships as a rod file (:func:`rod_file`, in :mod:`torchrod.data`): the start of a rod file of your
own.

``ctr250`` is a precurved tube of a concentric-tube robot: the same Nitinol cross-section, L = 250 mm, straight
for the first 150 mm and then curved at 12 1/m about its d1 axis (u* = (12, 0) 1/m) to the tip, nu = 0.33 (GJ =
EI / 1.33), gratings every 20 mm at 10, 30, ..., 230 mm (12 gratings).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .errors import MissingFileError, RodError
from .rod import Rod

__all__ = ["PAPER_LOCATION_BIAS", "PRESETS", "ctr250", "get", "load", "nitinol290", "rod_file"]

PAPER_LOCATION_BIAS = -3.12e-3  # [m], the paper's calibrated s_bias

_PAPER_TUBE: dict[str, Any] = {"outer_diameter": 1.397e-3, "inner_diameter": 1.118e-3, "youngs_modulus": 67e9}
"""The paper's Nitinol cross-section and modulus ([m], [m], [Pa]), shared by the presets."""


def nitinol290(calibrated: bool = False) -> Rod:
    """The paper's 290 mm Nitinol tube with 14 gratings at 10, 30, ..., 270 mm."""
    return Rod.from_geometry(
        length=0.29,
        **_PAPER_TUBE,
        gratings=[(10 + 20 * k) * 1e-3 for k in range(14)],
        location_bias=PAPER_LOCATION_BIAS if calibrated else 0.0,
    )


def ctr250() -> Rod:
    """A precurved 250 mm Nitinol tube: straight to 150 mm, then 12 1/m to the tip; 12 gratings at 10..230 mm."""
    return Rod.from_geometry(
        length=0.25,
        **_PAPER_TUBE,
        gratings=[(10 + 20 * k) * 1e-3 for k in range(12)],
        poisson_ratio=0.33,
        intrinsic_curvature=[{"from": 0.15, "to": 0.25, "u": [12.0, 0.0]}],
    )


PRESETS = {"nitinol290": nitinol290, "ctr250": ctr250}


ROD_FILES = {"nitinol290": "nitinol290.json", "ctr250": "ctr250.json"}
"""The rod file each preset ships as (in :mod:`torchrod.data`)."""


def rod_file(name: str) -> Path:
    """The path of the shipped rod file of preset ``name``: the same rod as :func:`get`, as JSON, a template to
    copy for a rod of your own. Raises :class:`~torchrod.errors.RodError` naming the presets for another name."""
    from .shipped import path

    if name not in ROD_FILES:
        raise RodError(f"unknown rod preset {name!r}; known presets: {', '.join(PRESETS)}")
    return path(ROD_FILES[name])


def get(name: str) -> Rod:
    """A preset by name; raises ``ValueError`` listing the known names."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise RodError(f"unknown rod preset {name!r}; known presets: {sorted(PRESETS)}") from None


def load(spec: str | os.PathLike) -> Rod:
    """A rod from a JSON file path or a preset name (the ``--rod`` argument of every command).

    A path that exists is read as a rod file (:meth:`Rod.from_json`: a directory, an unreadable file or a bad
    description is a ``ValueError`` naming the file and the problem). Otherwise ``spec`` must name a preset; if it
    does not, a ``spec`` that reads as a path (a folder separator, or ending in ``.json``) raises
    :class:`~torchrod.errors.MissingFileError`, and any other a :class:`~torchrod.errors.RodError` naming the presets.
    """
    if not isinstance(spec, (str, os.PathLike)):
        raise RodError(f"a rod must be given as a rod file or a preset name, got {type(spec).__name__}")  # noqa: TRY004
    name = os.fspath(spec)
    if os.path.lexists(name):
        return Rod.from_json(name)
    if name in PRESETS:
        return PRESETS[name]()
    shown = name if len(name) <= 100 else name[:97] + "..."
    if os.sep in name or "/" in name or name.lower().endswith(".json"):  # meant as a file: the file is missing
        raise MissingFileError(f"--rod {shown!r}: no such rod file (check the path; presets: {', '.join(PRESETS)})")
    raise RodError(f"--rod {shown!r} is neither a rod file nor a preset (presets: {', '.join(PRESETS)})")
