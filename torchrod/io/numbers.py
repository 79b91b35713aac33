"""Number parsing: a number of a decoded reading (:func:`as_number`) and a CSV cell (:func:`csv_number`).

Numbers
    A number is a JSON number (Python: ``int``, ``float`` or another real number; never a boolean or a string). It
    must be finite: ``NaN``, ``Infinity`` and literals that overflow a double (``1e999``, an integer of 400 digits)
    are refused. A curvature component must also satisfy ``|u| <= MAX_CURVATURE`` (1e6 1/m, a bend radius of 1 um:
    no rod or fibre bends that much, so such a value is a unit or scaling error). Finite values within the bound
    are passed on as they are, however implausible (1e4 1/m reaches the estimator, which flags a bad fit).

CSV numbers
    ``[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?`` with ASCII digits, spaces around the cell
    allowed: ``12``, ``-1.5``, ``.5``, ``5.``, ``2.5E-3``. Not numbers: ``1_000`` (Python's ``float`` takes it, a
    CSV number must not), ``0x1f``, ``1,000`` (two cells), ``1 000``, ``½``, non-ASCII digits. ``nan``, ``inf`` and
    ``infinity`` (any case, any sign) are read as numbers and refused as not finite. An empty cell is a missing
    value: both cells of a grating empty mark it missing, an empty ``t`` is no timestamp.
"""

from __future__ import annotations

import math
import numbers
import re
from typing import Any

from ..errors import ReadingError
from .values import HugeInteger, describe, quote

__all__ = ["CSV_NONFINITE", "CSV_NUMBER", "as_number", "csv_number"]


def as_number(value: Any, what: str, *, bound: float | None = None, unit: str = "") -> float:
    """``value`` as a finite float under the number rules (module docstring); ``ValueError`` naming ``what``.

    Args:
        value: a decoded JSON value or a Python number (booleans, strings and containers are refused).
        what: the field's name in messages, e.g. ``"curvature[3][0]"``.
        bound: refuse ``|value| > bound`` too (e.g. :data:`torchrod.estimate.checks.MAX_CURVATURE`); ``unit`` names
            its unit.
    """
    if type(value) is float and math.isfinite(value) and (bound is None or abs(value) <= bound):
        return value  # the usual case, checked fast
    if isinstance(value, HugeInteger):
        raise ReadingError(  # noqa: TRY004 (bad data, one kind of error)
            f"{what} must be a finite number, got an integer of {value.digits} digits ({value!r})"
        )
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ReadingError(f"{what} must be a number, got {describe(value)}")  # noqa: TRY004 (bad data, one kind of error)
    try:
        x = float(value)
    except OverflowError:
        raise ReadingError(f"{what} must be a finite number, got {quote(value)}, which overflows a float") from None
    if not math.isfinite(x):
        raise ReadingError(f"{what} must be finite, got {quote(x)}")
    if bound is not None and not abs(x) <= bound:
        unit = f" {unit}" if unit else ""
        raise ReadingError(
            f"{what} = {x!r}{unit} is beyond the bound of {bound:g}{unit} that any input must respect; "
            "check the units and scaling of the input"
        )
    return x


CSV_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
"""A CSV number (module docstring: CSV numbers), matched whole."""

CSV_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
"""The spellings of a CSV cell read as a number and refused as not finite."""


def csv_number(text: str, what: str, *, bound: float | None = None, unit: str = "") -> float | None:
    """A CSV cell as a number under the CSV number grammar (module docstring); None for an empty cell.

    ``ValueError`` names ``what`` for a cell that is not a number, not finite, or beyond ``bound``.
    """
    cell = text.strip()
    if not cell:
        return None
    if CSV_NONFINITE.fullmatch(cell):
        raise ReadingError(f"{what} must be finite, got {quote(cell)} (leave a missing value's cell empty)")
    if not CSV_NUMBER.fullmatch(cell):
        raise ReadingError(
            f"{what} must be a number, got {quote(cell)}: a CSV number is decimal digits with an optional sign, "
            "point and exponent (no underscores, hexadecimal or separators)"
        )
    x = float(cell)
    if math.isinf(x):
        raise ReadingError(f"{what} must be a finite number, got {quote(cell)}, which overflows a float")
    return as_number(x, what, bound=bound, unit=unit)
