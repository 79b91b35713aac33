"""How the library checks a plain value and quotes an offending one in an error message.

The lowest layer of the package (it imports nothing of torchrod): the rod, its fibre and every other description
read from a file or an argument check their numbers with :func:`real` and :func:`positive`, and name a bad value as
:func:`show` spells it.
"""

from __future__ import annotations

import json
import math
import numbers
import sys
from typing import Any

from .errors import RodError

__all__ = ["MAX_CURVATURE", "QUOTE_CHARS", "brief", "clip", "is_number", "positive", "real", "show"]

QUOTE_CHARS = 100
"""Characters of an offending value quoted in an error message."""

MAX_CURVATURE = 1e6
"""[1/m] The largest curvature component accepted from any input: a bend radius of 1 um. A nitinol tube or an
optical fibre breaks at radii of millimetres (curvature ~ 1e3 1/m), so a larger value is a unit or scaling error
(microstrain, 1/km, a raw interrogator count), refused at the edge instead of being handed to the estimator."""


def clip(text: str, limit: int = QUOTE_CHARS) -> str:
    """``text`` on one line, at most about ``limit`` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def brief(value: Any) -> str:
    """``repr(value)`` on one line, at most about :data:`QUOTE_CHARS` characters (a value whose repr fails is named
    by its type)."""
    try:
        return clip(repr(value))
    except Exception:  # noqa: BLE001 -- a value whose repr fails is still named by its type
        return f"a {type(value).__name__}"


def show(value: Any) -> str:
    """An offending value as an error message quotes it: JSON spelling where there is one (null, true, "0.29"),
    at most about 100 characters, and never the whole of a huge integer."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        try:
            digits = str(abs(value))
        except ValueError:  # beyond Python's int-to-text limit
            return f"an integer of more than {sys.get_int_max_str_digits()} digits"
        if len(digits) > 30:
            return f"{'-' if value < 0 else ''}{digits[:12]}... (an integer of {len(digits)} digits)"
        return str(value)
    if isinstance(value, (str, list, tuple, dict)):
        try:
            return clip(json.dumps(value if not isinstance(value, tuple) else list(value), default=repr))
        except (TypeError, ValueError, RecursionError):
            pass
    try:
        return clip(repr(value))
    except Exception:  # noqa: BLE001 -- a value whose repr fails is still named by its type
        return f"a {type(value).__name__}"


def is_number(value: Any) -> bool:
    """A real number: int, float, numpy's real scalars, a 0-d tensor or array of a numeric dtype. Not a bool,
    a string, null or a container, which ``float()`` would turn into a number or a confusing error."""
    if isinstance(value, bool):
        return False
    if isinstance(value, numbers.Real):
        return True
    dtype = getattr(value, "dtype", None)
    return getattr(value, "ndim", None) == 0 and dtype is not None and "bool" not in str(dtype)


def real(name: str, value: Any, unit: str = "") -> float:
    """``value`` as a finite float, or ``ValueError`` naming ``name`` and the value."""
    if not is_number(value):
        raise RodError(f"{name} must be a number{unit}, got {show(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise RodError(f"{name} is too large{unit}, got {show(value)}") from None
    except (TypeError, ValueError):
        raise RodError(f"{name} must be a number{unit}, got {show(value)}") from None
    if not math.isfinite(x):
        raise RodError(f"{name} must be finite{unit}, got {show(value)}")
    return x


def positive(name: str, value: Any, unit: str = "") -> float:
    x = real(name, value, unit)
    if x <= 0.0:
        raise RodError(f"{name} must be positive{unit}, got {show(value)}")
    return x
