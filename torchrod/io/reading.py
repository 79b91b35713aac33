"""One FBG reading: the record (:class:`Reading`), and the one set of rules every entry point checks it by.

``torchrod estimate``, ``torchrod stream``, ``torchrod calibrate``, ``torchrod plot`` and the Python stream API
(:func:`torchrod.io.stream.stream`: dicts, lists, tensors) all check readings here, and the estimator checks the
tensors handed to it by the same bounds (:func:`torchrod.estimate.checks.check_readings`), so a reading means the
same thing, and fails with the same message, wherever it enters. How a line becomes the reading's object is its
format's business (:mod:`torchrod.io.csv_rows`, :mod:`torchrod.io.peaklog`, JSON lines as they are; chosen by
:mod:`torchrod.io.sources`); what a reading's values may be and how they become curvature is
:mod:`torchrod.io.quantities`'; numbers follow :mod:`torchrod.io.numbers`.

A reading
    ``curvature``: one entry per grating of the rod, in the rod file's order: a pair ``[ux, uy]`` [1/m], or
    ``null``/``None`` for a grating that gave no reading (it is left out of the fit, never read as zero). As a
    tensor or array it is (G, 2) with a row of NaN for a missing grating. At least one grating must be present.
    ``id`` (optional): any JSON value, echoed in the answer (rules below). ``t`` (optional): a timestamp [s],
    echoed. ``gratings`` (optional, JSON): the grating positions [m]; when given they must be the rod's (within
    1e-9 m), which catches readings meant for another rod. Other keys are ignored. Instead of ``curvature`` a
    reading may give one of the other quantities of :data:`torchrod.io.quantities.QUANTITIES`.

Ids
    An id is echoed as given when JSON can write it: a string, a finite number, true, false, null, or an array or
    object of these, nested at most ``MAX_ID_DEPTH`` levels and at most ``MAX_ID_CHARS`` characters as JSON. An id
    JSON cannot write (``NaN``, ``Infinity``, an overflowing number, an integer of more than 4300 digits, an id too
    deep or too long) makes its line an error whose answer has ``"id": null`` and names the line: the answer is
    still in the line's position, and the message says which line it was.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..errors import ReadingError
from .numbers import as_number
from .quantities import reading_curvature
from .values import HugeInteger, describe, int_digit_limit, kind, quote

__all__ = [
    "GRATING_TOLERANCE",
    "MAX_ID_CHARS",
    "MAX_ID_DEPTH",
    "Reading",
    "check_gratings",
    "check_id",
    "check_time",
    "id_problem",
    "parse_reading",
    "stack_readings",
    "to_reading",
]

MAX_ID_DEPTH = 32
"""Deepest nesting of an id (arrays and objects) that is echoed."""

MAX_ID_CHARS = 1000
"""Longest id, as JSON text, that is echoed."""


GRATING_TOLERANCE = 1e-9
"""[m] How far a reading's ``gratings`` may lie from the rod's."""


@dataclass(frozen=True)
class Reading:
    """One FBG reading.

    Attributes:
        id: the reading's identifier (echoed in its result; any JSON value).
        curvature: (G, 2) [1/m], either a tensor (a row of NaN marks a missing grating) or a list of G
            ``[ux, uy]`` pairs with ``None`` for a missing grating (NaN in a list is an error, as in JSON input).
            Checked readings (from :func:`parse_reading`, :func:`to_reading`) hold a float64 CPU tensor.
        t: timestamp [s], optional, echoed.
        error: set when the reading could not be used; it then passes through as an error result.
        line: the input line it came from (1-based), when read from a file or stream; for messages.
    """

    id: Any = None
    curvature: Any = None
    t: float | None = None
    error: str | None = None
    line: int | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def id_problem(value: Any) -> str | None:
    """Why JSON cannot echo ``value`` as an id (module docstring), or None when it can. Never recurses."""
    if value is None or (type(value) is str and len(value) + 2 <= MAX_ID_CHARS):  # (the usual ids, at once)
        return None
    size = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if item is None or isinstance(item, bool):
            size += 5
        elif isinstance(item, str):
            size += len(item) + 2
        elif isinstance(item, HugeInteger):
            return f"id holds an integer of {item.digits} digits ({item.head}...), which JSON output cannot carry"
        elif isinstance(item, int):
            digits = int(item.bit_length() * 0.30103) + 1
            limit = int_digit_limit()
            if limit and digits > limit:
                return f"id holds an integer of about {digits} digits, which JSON output cannot carry"
            size += digits
        elif isinstance(item, float):
            if not math.isfinite(item):
                held = "" if item is value else f" (it holds {quote(item)})"
                return f"id {quote(value)} cannot be written as JSON{held}"
            size += 24
        elif isinstance(item, (list, tuple, dict)):
            if depth >= MAX_ID_DEPTH:
                return f"id is nested more than {MAX_ID_DEPTH} levels deep ({quote(value)})"
            if isinstance(item, dict):
                if not all(isinstance(k, str) for k in item):
                    return f"id {quote(value)} has an object key that is not a string"
                size += sum(len(k) + 4 for k in item)
                stack.extend((v, depth + 1) for v in item.values())
            else:
                stack.extend((v, depth + 1) for v in item)
            size += 2 + len(item)
        else:
            return f"id must be a JSON value, got {kind(item)}"
        if size > MAX_ID_CHARS:
            return f"id is longer than {MAX_ID_CHARS} characters as JSON ({quote(value)})"
    return None


_ID_HINT = (
    "; an id must be a string, a finite number, true, false, null, or an array or object of these, at most "
    f"{MAX_ID_DEPTH} levels deep and {MAX_ID_CHARS} characters as JSON"
)


def check_id(value: Any) -> Any:
    """``value`` if JSON can echo it as an id, else ``ValueError`` saying why (module docstring)."""
    problem = id_problem(value)
    if problem is not None:
        raise ReadingError(problem + _ID_HINT)
    return value


def check_time(value: Any, what: str = "t") -> float | None:
    """A timestamp [s]: None when absent (None), else a finite number of seconds."""
    if value is None:
        return None
    try:
        return as_number(value, what)
    except ValueError as exc:
        raise ReadingError(f"{exc} ({what} is a timestamp in seconds, or null)") from None


def check_gratings(value: Any, gratings: Sequence[float], what: str = "gratings") -> None:
    """The grating positions [m] a reading declares must be the rod's (within :data:`GRATING_TOLERANCE`)."""
    if not isinstance(value, (list, tuple)):
        raise ReadingError(f"{what} must be an array of the grating positions [m], got {describe(value)}")  # noqa: TRY004
    positions = [as_number(x, f"{what}[{k}]") for k, x in enumerate(value)]
    if len(positions) != len(gratings) or any(
        abs(a - b) > GRATING_TOLERANCE for a, b in zip(positions, gratings, strict=False)
    ):
        raise ReadingError(
            f"{what} {quote(positions)} do not match the rod's {quote(list(gratings))}: "
            "these readings are for another rod (give the matching --rod)"
        )


def parse_reading(
    obj: Mapping[str, Any],
    num_gratings: int,
    gratings: Sequence[float] | None = None,
    *,
    line: int | None = None,
    fibre: Any = None,
) -> Reading:
    """One reading object (a decoded JSON line or a dict) -> a checked :class:`Reading`.

    Keys (module docstring): ``curvature`` (or ``strain`` with the rod's ``fibre``, or ``curvature_polar``),
    ``id``, ``t``, ``gratings`` (checked against ``gratings``, the rod's positions [m], when both are given);
    others are ignored.
    Raises:
        ValueError: naming the first bad field.
    """
    if type(obj) is not dict and not isinstance(obj, Mapping):  # (a decoded line is a dict: no ABC check)
        raise ReadingError(  # noqa: TRY004 (bad data, one kind of error)
            f'a reading must be an object {{"id": ..., "curvature": [[ux, uy], ...]}}, got {describe(obj)}'
        )
    ident = check_id(obj.get("id"))
    if "gratings" in obj and gratings is not None:
        check_gratings(obj["gratings"], gratings)
    curvature = reading_curvature(obj, num_gratings, fibre)
    t = check_time(obj.get("t"))
    return _checked(Reading(ident, curvature, t, None, line))


def _checked(reading: Reading) -> Reading:
    """``reading``, marked as made here from input that passed every check (a flag outside the dataclass's fields:
    equality, ``repr`` and :func:`dataclasses.replace` ignore it), so that :func:`to_reading` need not check it
    again: a stream reads each line through a :class:`~torchrod.io.sources.ReadingSource`, then takes what it
    yields through :func:`to_reading`, and the second check cost as much again."""
    object.__setattr__(reading, "_checked", True)
    return reading


def _given_error(error: Any) -> str:
    """An error passed in with a reading, as a message of bounded length (a string kept as it is up to 1000
    characters; anything else quoted)."""
    if isinstance(error, str):
        return error if len(error) <= 1000 else error[:997] + "..."
    return quote(error)


def to_reading(item: Any, num_gratings: int, gratings: Sequence[float] | None = None, *, fibre: Any = None) -> Reading:
    """Anything given as a reading (a :class:`Reading` or a mapping with its keys) -> a checked :class:`Reading`
    (float64 CPU curvature), or one with ``error`` set. Never raises (the Python stream API's entry point).
    ``fibre``: the rod's (:class:`torchrod.sensors.Fibre`), for readings that give core strains."""
    if isinstance(item, Reading):
        if item.__dict__.get("_checked") and item.curvature.shape[0] == num_gratings:
            return item  # made by the checks below, for a rod with as many gratings
        if item.error is not None:
            ident = item.id if id_problem(item.id) is None else None
            return replace(item, id=ident, curvature=None, error=_given_error(item.error))
        fields: Mapping[str, Any] = {"id": item.id, "curvature": item.curvature, "t": item.t}
        line = item.line
    elif isinstance(item, Mapping):
        if item.get("error") is not None:
            ident = item.get("id") if id_problem(item.get("id")) is None else None
            return Reading(ident, error=_given_error(item["error"]), line=item.get("line"))
        fields, line = item, None
    else:
        return Reading(error=f"a reading must be a Reading or a dict, got {kind(item)} {quote(item)}")
    ident = fields.get("id")
    ident = ident if id_problem(ident) is None else None
    try:
        return parse_reading(fields, num_gratings, gratings, line=line, fibre=fibre)
    except ValueError as exc:
        return Reading(ident, error=_at(line, str(exc)), line=line)
    except Exception as exc:  # noqa: BLE001 - a reading never stops the stream
        return Reading(ident, error=_at(line, f"unreadable reading ({type(exc).__name__}: {quote(str(exc))})"))


def _at(line: int | None, message: str) -> str:
    return message if line is None or message.startswith("line ") else f"line {line}: {message}"


def stack_readings(readings: Sequence[Reading]) -> tuple[torch.Tensor, torch.Tensor]:
    """Checked readings -> (curvature (B, G, 2) float64 [1/m] with 0 at missing gratings, mask (B, G) bool)."""
    curvature = torch.stack([r.curvature for r in readings]).detach()  # (a new tensor: zeroed in place below)
    values = curvature.numpy()
    missing = np.isnan(values).any(-1)
    values[missing] = 0.0
    return curvature, torch.from_numpy(~missing)
