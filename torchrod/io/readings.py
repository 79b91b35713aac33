"""FBG readings: what one reading is, and the one set of rules every entry point checks it by.

``torchrod estimate``, ``torchrod stream``, ``torchrod calibrate``, ``torchrod plot`` and the Python stream API
(:func:`torchrod.io.stream.stream`: dicts, lists, tensors) all check readings here, and the estimator checks the
tensors handed to it by the same bounds (:func:`torchrod.estimate.checks.check_readings`), so a reading means the
same thing, and fails with the same message, wherever it enters.

A reading
    ``curvature``: one entry per grating of the rod, in the rod file's order: a pair ``[ux, uy]`` [1/m], or
    ``null``/``None`` for a grating that gave no reading (it is left out of the fit, never read as zero). As a
    tensor or array it is (G, 2) with a row of NaN for a missing grating. At least one grating must be present.
    ``id`` (optional): any JSON value, echoed in the answer (rules below). ``t`` (optional): a timestamp [s],
    echoed. ``gratings`` (optional, JSON): the grating positions [m]; when given they must be the rod's (within
    1e-9 m), which catches readings meant for another rod. Other keys are ignored.

    Instead of ``curvature`` a reading may give one of (:mod:`torchrod.sensors`; exactly one of
    :data:`QUANTITIES`' keys): ``strain``: per grating the C core strains ``[eps_1, ..., eps_C]`` of the rod file's
    multicore ``fibre`` (``|eps| <= MAX_STRAIN``), or null; ``curvature_polar``: per grating ``[kappa, phi]``, the
    curvature magnitude (>= 0) and the bend angle [rad] from d1 towards d2, or null; ``wavelength``: per grating the
    C peak wavelengths, the rod's ``fibre.wavelength.reference`` subtracted here, or null; ``wavelength_shift``: the
    C shifts from the reference, or null. All are turned into (ux, uy) [1/m] here, so everything downstream sees
    curvature.

Units
    Values are read in the units the rod's fibre says (:class:`torchrod.sensors.Fibre`: ``curvature_unit``,
    ``strain_unit``, ``wavelength_unit``; the commands' options set them), SI (and nm) without one, and converted
    to SI here; the bounds hold in SI (:data:`MAX_CURVATURE`, :data:`torchrod.sensors.MAX_STRAIN`, a peak within
    :data:`torchrod.sensors.WAVELENGTH_RANGE_NM`, a shift within :data:`torchrod.sensors.MAX_WAVELENGTH_SHIFT`).
    Tensors handed to the estimator (:func:`torchrod.estimate.checks.check_readings`) are always curvature in 1/m.

Numbers
    A number is a JSON number (Python: ``int``, ``float`` or another real number; never a boolean or a string). It
    must be finite: ``NaN``, ``Infinity`` and literals that overflow a double (``1e999``, an integer of 400 digits)
    are refused. A curvature component must also satisfy ``|u| <= MAX_CURVATURE`` (1e6 1/m, a bend radius of 1 um:
    no rod or fibre bends that much, so such a value is a unit or scaling error). Finite values within the bound
    are passed on as they are, however implausible (1e4 1/m reaches the estimator, which flags a bad fit).

CSV rows (``--format csv``, :class:`CsvLayout`)
    A first row of at least two cells, none of them a number, is a header naming the columns (case ignored):
    ``id`` and ``t`` (optional), ``ux_K``/``uy_K`` (grating K, 1-based), ``kappa_K``/``phi_K``, ``eps_K_C`` (core C,
    1-based), ``lambda_K_C`` or ``dlambda_K_C`` for every grating of exactly one quantity, in any order; ``s_J``,
    ``fx_J``, ``fy_J`` and ``jig_curvature``, ``jig_angle``, ``jig`` for the calibrations; other columns are ignored.
    A header that cannot be used raises :class:`~torchrod.errors.ReadingError` listing what was expected (and the
    columns it ignored); one without ``id`` or ``t`` that ignores columns is read with a
    :class:`~torchrod.errors.ReadingWarning` naming them. A first line of one cell that holds semicolons, tabs,
    vertical bars or spaces between names or numbers raises a ``ReadingError`` naming the separator. Without a
    header a row is, by its width, ``id, t`` then the values, ``t`` then the values, or the values alone, per
    grating in order ``ux, uy`` (``quantity="curvature"``), ``kappa, phi`` (``"polar"``) or the C core values
    (``"strain"``, ``"wavelength"``, ``"wavelength-shift"``). All the cells of a missing grating are empty. An id
    cell is read as JSON reads the same text (:func:`csv_id`: ``7`` is an integer). A row becomes the reading's JSON
    object and passes the same checks as a JSON line.

CSV numbers
    ``[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?`` with ASCII digits, spaces around the cell
    allowed: ``12``, ``-1.5``, ``.5``, ``5.``, ``2.5E-3``. Not numbers: ``1_000`` (Python's ``float`` takes it, a
    CSV number must not), ``0x1f``, ``1,000`` (two cells), ``1 000``, ``½``, non-ASCII digits. ``nan``, ``inf`` and
    ``infinity`` (any case, any sign) are read as numbers and refused as not finite. An empty cell is a missing
    value: both cells of a grating empty mark it missing, an empty ``t`` is no timestamp.

Ids
    An id is echoed as given when JSON can write it: a string, a finite number, true, false, null, or an array or
    object of these, nested at most ``MAX_ID_DEPTH`` levels and at most ``MAX_ID_CHARS`` characters as JSON. An id
    JSON cannot write (``NaN``, ``Infinity``, an overflowing number, an integer of more than 4300 digits, an id too
    deep or too long) makes its line an error whose answer has ``"id": null`` and names the line: the answer is
    still in the line's position, and the message says which line it was.

Lines
    A line of JSON, CSV or a peak log longer than :func:`line_limit` of the rod (1 MiB, more for a rod whose
    readings hold more than 16 384 values) is an error line (``longer than N bytes; not read``) and is read past in
    chunks without being held: no reading of the rod needs such a line, and decoding one would cost up to about 20
    times its size in memory. ``max_line`` (``--max-line-bytes``) sets another limit.

Messages
    Every message names the field (``curvature[3][0]``, ``t``, ``id``) and quotes at most ``QUOTE_CHARS``
    characters of the offending value (with its full length when cut), so a 10 MB value gives a short message;
    quoting never recurses, so deeply nested values are quoted safely too.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import sys
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
import torch

from ..errors import OptionsError, ReadingError, ReadingWarning
from ..estimate.checks import MAX_CURVATURE
from ..sensors import DEFAULT_UNITS, UNIT_TABLES

__all__ = [
    "MAX_CURVATURE",
    "MAX_ID_CHARS",
    "MAX_ID_DEPTH",
    "MAX_INT_DIGITS",
    "FORMATS",
    "QUANTITIES",
    "QUOTE_CHARS",
    "CsvLayout",
    "HugeInteger",
    "LINE_BYTES_PER_VALUE",
    "MIN_LINE_BYTES",
    "Reading",
    "ReadingSource",
    "as_number",
    "check_gratings",
    "check_id",
    "check_time",
    "csv_id",
    "csv_number",
    "curvature_tensor",
    "describe",
    "detect_format",
    "id_problem",
    "iter_readings",
    "iter_records",
    "line_limit",
    "parse_csv_row",
    "parse_reading",
    "polar_curvature",
    "quote",
    "reading_curvature",
    "stack_readings",
    "strain_curvature",
    "to_reading",
    "wavelength_curvature",
    "wavelength_shifts",
    "unusable_lines",
    "wavelength_values",
]

QUOTE_CHARS = 100
"""Characters of an offending value quoted in a message, at most (its length is added when it is cut)."""

MAX_ID_DEPTH = 32
"""Deepest nesting of an id (arrays and objects) that is echoed."""

MAX_ID_CHARS = 1000
"""Longest id, as JSON text, that is echoed."""

MIN_LINE_BYTES = 2**20
"""[bytes] The least :func:`line_limit` gives: a reading line of a rod of a few dozen gratings is a few kB, an id at
most :data:`MAX_ID_CHARS`; the rest is room for keys a reading may carry besides (they are ignored)."""

LINE_BYTES_PER_VALUE = 64
"""[bytes] What :func:`line_limit` allows per value of a reading: a double written in full is at most 24
characters, with its separator and brackets about 30."""

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


class HugeInteger:
    """A JSON integer literal of more than :func:`int_digit_limit` digits (4300, Python's default limit). The JSON
    decoder of :mod:`torchrod.io.jsonl` yields it in place of the integer, so such a line fails with a message naming
    the field instead of aborting the run. Keeps only the head of the digits."""

    __slots__ = ("digits", "head", "negative")

    def __init__(self, text: str) -> None:
        self.negative = text.startswith("-")
        body = text.lstrip("+-")
        self.digits = len(body)
        self.head = body[:20]

    def __repr__(self) -> str:
        return f"{'-' if self.negative else ''}{self.head}... ({self.digits} digits)"


MAX_INT_DIGITS = 4300
"""The most digits of an integer read from JSON (Python's default int <-> str limit): converting longer ones costs
time quadratic in their length, and Python refuses to write them back."""


def int_digit_limit() -> int:
    """The most digits of an integer read or written: Python's int <-> str limit when it is set lower than
    :data:`MAX_INT_DIGITS`, else that."""
    get = getattr(sys, "get_int_max_str_digits", None)
    limit = int(get()) if get is not None else 0
    return min(limit, MAX_INT_DIGITS) if limit > 0 else MAX_INT_DIGITS


# ---------------------------------------------------------------------------------------------------- quoting
_END = object()


class _Piece(str):
    """Literal text in :func:`quote`'s work list (a plain ``str`` there is a value to render)."""


def _int_text(x: int) -> str:
    limit = int_digit_limit()
    approx = int(x.bit_length() * 0.30103) + 1
    if limit and approx > limit:
        return f"an integer of about {approx} digits"
    text = str(x)
    digits = len(text.lstrip("-"))
    return text if digits <= 24 else f"{text[:21]}... ({digits} digits)"


def _scalar_text(value: Any, limit: int) -> str | None:
    """JSON-like text of a scalar; None for a container."""
    if value is None:
        return "null"
    if value is True or value is False:
        return "true" if value else "false"
    if isinstance(value, HugeInteger):
        return repr(value)
    if isinstance(value, int):
        return _int_text(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return repr(value)
    if isinstance(value, str):
        import json

        if len(value) > limit:
            cut = max(8, limit - 40)
            return json.dumps(value[:cut], ensure_ascii=False)[:-1] + f'..." ({len(value)} characters)'
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple, dict)):
        return None
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)} and dtype {value.dtype}"
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"an array of shape {tuple(value.shape)} and dtype {value.dtype}"
    if isinstance(value, numbers.Number):
        return _scalar_text(float(value), limit) if isinstance(value, numbers.Real) else type(value).__name__
    return f"a {type(value).__name__}"


def _pieces(container: Any) -> Iterator[Any]:
    if isinstance(container, dict):
        yield _Piece("{")
        for k, (key, v) in enumerate(container.items()):
            if k:
                yield _Piece(", ")
            yield key if isinstance(key, str) else _Piece(repr(key))
            yield _Piece(": ")
            yield v
        yield _Piece("}")
    else:
        yield _Piece("[")
        for k, v in enumerate(container):
            if k:
                yield _Piece(", ")
            yield v
        yield _Piece("]")


def quote(value: Any, limit: int = QUOTE_CHARS) -> str:
    """``value`` as JSON-like text of at most about ``limit`` characters (cut with ``...``).

    Never raises and never recurses: nested arrays and objects are walked with an explicit stack that stops once
    ``limit`` characters are out, so a value nested 100 000 levels deep or 10 MB long costs ``limit`` steps.
    """
    out: list[str] = []
    size = 0
    stack: list[Iterator[Any]] = [iter((value,))]
    try:
        while stack and size <= limit:
            item = next(stack[-1], _END)
            if item is _END:
                stack.pop()
                continue
            if isinstance(item, _Piece):
                text = str(item)
            else:
                scalar = _scalar_text(item, limit)
                if scalar is None:
                    stack.append(_pieces(item))
                    continue
                text = scalar
            out.append(text)
            size += len(text)
    except Exception:  # noqa: BLE001 - a message must come out whatever the value holds
        out.append(" ?")
    text = "".join(out)
    # A lone scalar formats itself within about the limit (keeping its length note); only more is cut here.
    return text if len(text) <= limit + 40 and not stack else text[:limit] + "..."


def describe(value: Any) -> str:
    """``value``'s JSON kind and its quote, as ``a string "abc"``, for messages."""
    if value is None:
        return "null"
    if value is True or value is False:
        return f"a boolean {quote(value)}"
    if isinstance(value, str):
        return f"a string {quote(value)}"
    if isinstance(value, (list, tuple)):
        return f"an array {quote(value)}"
    if isinstance(value, dict):
        return f"an object {quote(value)}"
    if isinstance(value, (int, float, HugeInteger)):
        return f"a number {quote(value)}"
    return quote(value)


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if value is True or value is False:
        return "a boolean"
    if isinstance(value, (int, float, HugeInteger)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return f"a {type(value).__name__}"


# ---------------------------------------------------------------------------------------------------- numbers
def as_number(value: Any, what: str, *, bound: float | None = None, unit: str = "") -> float:
    """``value`` as a finite float under the number rules (module docstring); ``ValueError`` naming ``what``.

    Args:
        value: a decoded JSON value or a Python number (booleans, strings and containers are refused).
        what: the field's name in messages, e.g. ``"curvature[3][0]"``.
        bound: refuse ``|value| > bound`` too (e.g. :data:`MAX_CURVATURE`); ``unit`` names its unit.
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


_CSV_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_CSV_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def csv_number(text: str, what: str, *, bound: float | None = None, unit: str = "") -> float | None:
    """A CSV cell as a number under the CSV number grammar (module docstring); None for an empty cell.

    ``ValueError`` names ``what`` for a cell that is not a number, not finite, or beyond ``bound``.
    """
    cell = text.strip()
    if not cell:
        return None
    if _CSV_NONFINITE.fullmatch(cell):
        raise ReadingError(f"{what} must be finite, got {quote(cell)} (leave a missing value's cell empty)")
    if not _CSV_NUMBER.fullmatch(cell):
        raise ReadingError(
            f"{what} must be a number, got {quote(cell)}: a CSV number is decimal digits with an optional sign, "
            "point and exponent (no underscores, hexadecimal or separators)"
        )
    x = float(cell)
    if math.isinf(x):
        raise ReadingError(f"{what} must be a finite number, got {quote(cell)}, which overflows a float")
    return as_number(x, what, bound=bound, unit=unit)


# ---------------------------------------------------------------------------------------------------- fields
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
            return f"id must be a JSON value, got {_kind(item)}"
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
        ValueError: naming the entry and quoting its value (module docstring: the rules).
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
    again: a stream reads each line through a :class:`ReadingSource`, then takes what it yields through
    :func:`to_reading`, and the second check cost as much again."""
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
        return Reading(error=f"a reading must be a Reading or a dict, got {_kind(item)} {quote(item)}")
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


# ---------------------------------------------------------------------------------------------------- CSV
_JSON_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(\.[0-9]+)?([eE][+-]?[0-9]+)?")


def csv_id(text: str) -> Any:
    """A CSV id cell as JSON reads the same text: empty -> None; a JSON number -> an int when it has neither point
    nor exponent (``"7"`` -> 7), else a float (``"1.5"``); anything else -> the text with the spaces around it
    dropped (``"007"``, ``"+5"`` and ``"r1"`` are not JSON numbers and stay strings)."""
    cell = text.strip()
    if not cell:
        return None
    match = _JSON_NUMBER.fullmatch(cell)
    if match is None:
        return cell
    if match.group(1) is None and match.group(2) is None:
        if len(cell.lstrip("-")) > int_digit_limit():
            return HugeInteger(cell)
        return int(cell)
    return float(cell)


_COLUMN = re.compile(r"(ux|uy|kappa|phi|eps|lambda|dlambda|s|fx|fy)_?([0-9]+)(?:_([0-9]+))?")
_PAIRS = {
    "ux": ("curvature", 0),
    "uy": ("curvature", 1),
    "kappa": ("curvature_polar", 0),
    "phi": ("curvature_polar", 1),
}
_PER_CORE = {"eps": "strain", "lambda": "wavelength", "dlambda": "wavelength_shift"}
_FORCE_FIELDS = ("s", "fx", "fy")
_JIG_COLUMNS = {"jig": "name", "jig_curvature": "curvature", "jig_angle": "angle"}
_COLUMN_NAMES = {  # the JSON key of each quantity and how its columns are named, for messages
    "curvature": "ux_K, uy_K",
    "curvature_polar": "kappa_K, phi_K",
    "strain": "eps_K_C",
    "wavelength": "lambda_K_C",
    "wavelength_shift": "dlambda_K_C",
}


def _expected_columns(G: int) -> str:
    return (
        f"id and t (both optional), then the columns of one quantity for gratings K = 1..{G} (cores C = 1..C): "
        "ux_K and uy_K (curvature), kappa_K and phi_K (curvature magnitude and bend angle), eps_K_C (core strains), "
        "lambda_K_C (peak wavelengths) or dlambda_K_C (wavelength shifts)"
    )


_ID_LIKE = frozenset({"sample", "samples", "index", "idx", "frame", "seq", "sequence", "n", "no", "number", "count"})
_TIME_LIKE = frozenset({"time", "timestamp", "time_s", "times", "seconds", "sec", "secs", "stamp", "clock"})


def _shown_columns(columns: Sequence[str], most: int = 8) -> str:
    shown = ", ".join(repr(c) for c in columns[:most])
    return shown + (f" and {len(columns) - most} more" if len(columns) > most else "")


def _ignored_note(ignored: Sequence[str]) -> str:
    """What a header error adds about the columns the header does not read ('' when none)."""
    return f" (it ignores the columns {_shown_columns(ignored)})" if ignored else ""


def _unread_columns(at: str, ignored: Sequence[str]) -> str:
    """The warning about a header without ``id`` or ``t`` whose ``ignored`` columns are read by no one."""
    hints = []
    for column in ignored:
        name = column.strip().lower()
        if name in _ID_LIKE:
            hints.append(f"rename {column!r} to id to echo it as each answer's id")
        elif name in _TIME_LIKE or name.startswith("time"):
            hints.append(f"rename {column!r} to t to read it as the time stamp [s]")
    advice = "; ".join(hints) if hints else "name a column id or t to have it read as the reading's id or time stamp"
    return f"{at} has no id or t column and ignores the columns {_shown_columns(ignored)}: {advice}"


_SEPARATORS = {";": "semicolons (;)", "\t": "tabs", "|": "vertical bars (|)", " ": "spaces"}
"""What a CSV line in one cell may be separated by instead of commas, and its name in a message."""


def _one_cell_problem(cells: Sequence[str], line: int) -> str | None:
    """Why a first CSV line read as one cell cannot be read: the separator it holds instead of commas. None when it
    holds none of :data:`_SEPARATORS`, or when its parts are neither column names nor numbers (a title line, which
    stays an error line of its own)."""
    if len(cells) != 1:
        return None
    text = cells[0].strip()
    counts = {sep: text.count(sep) for sep in _SEPARATORS}
    found = [sep for sep in _SEPARATORS if counts[sep] and sep != " "]
    if not found and not counts[" "]:
        return None
    sep = max(found, key=lambda x: counts[x]) if found else " "
    parts = [part.strip() for part in text.split(sep) if part.strip()]
    names = [p.lower() for p in parts if p.lower() in ("id", "t") or _COLUMN.fullmatch(p.lower())]
    numbers = [p for p in parts if _CSV_NUMBER.fullmatch(p) or _CSV_NONFINITE.fullmatch(p)]
    if len(parts) < 2 or not (names or len(numbers) == len(parts)):
        return None
    return (
        f"line {line}: the CSV {'header' if names else 'first row'} is one cell ({quote(text, 60)}): its columns are "
        f"separated by {_SEPARATORS[sep]}, not commas; write the file with commas between the columns (a "
        "spreadsheet's CSV export may use its list separator instead)"
    )


def _per_grating(key: str, fibre: Any, where: str) -> int:
    """Values per grating of quantity ``key``: 2, or the fibre's C (``ValueError`` when the rod has no such fibre)."""
    if key in ("curvature", "curvature_polar"):
        return 2
    if key == "strain":
        if fibre is None or not fibre.cores:
            raise ReadingError(f'{where} give core strains: add "fibre": {{"cores": [[x, y], ...]}} to the rod file')
    elif fibre is None or fibre.num_cores == 0:
        raise ReadingError(f'{where} give wavelengths: add "fibre": {{"wavelength": {{...}}}} to the rod file')
    return fibre.num_cores


@dataclass(frozen=True)
class CsvLayout:
    """Where each cell of a CSV row goes: from a header row (:meth:`from_header`) or by position
    (:meth:`positional`). :meth:`reading_object` turns a row into the JSON object of the same reading, which the
    one reading parser then checks.

    Attributes:
        key: the quantity's JSON key (:data:`QUANTITIES`).
        per: values per grating.
        width: cells a row holds.
        id_column, t_column: their column (0-based), or None.
        data: (column, grating, index) of every value cell, 0-based.
        forces: per known force (0-based), its ``s``, ``fx``, ``fy`` columns (``torchrod calibrate``).
        jig: the jig's ``name``, ``curvature``, ``angle`` columns (``torchrod calibrate --fibre``).
        header: the header row's line, None for a positional layout.
    """

    key: str
    per: int
    width: int
    id_column: int | None
    t_column: int | None
    data: tuple[tuple[int, int, int], ...]
    forces: tuple[tuple[int, int, int], ...] = ()
    jig: tuple[tuple[str, int], ...] = ()
    header: int | None = None

    @classmethod
    def from_header(cls, cells: Sequence[str], num_gratings: int, fibre: Any = None, line: int = 1) -> CsvLayout:
        """The layout a header row names (module docstring); :class:`~torchrod.errors.ReadingError` naming the
        line when it names no reading column, two quantities, a value twice (one name twice, or two spellings of
        one value: ``ux_1`` and ``ux01``), or not every grating's columns."""
        G = num_gratings
        at = f"line {line}: the CSV header"
        names = [c.strip().lower() for c in cells]
        seen: dict[str, int] = {}
        twice = sorted({n for n in names if n and names.count(n) > 1})
        if twice:
            raise ReadingError(f"{at} names {', '.join(repr(n) for n in twice)} more than once")
        id_col = t_col = None
        values: dict[str, dict[tuple[int, int], int]] = {}
        forces: dict[int, dict[str, int]] = {}
        jig: dict[str, int] = {}
        ignored: list[str] = []  # the header's other columns, as written
        slots: dict[tuple[Any, ...], int] = {}  # what each column gives, so two spellings of one are caught

        def claim(slot: tuple[Any, ...], col: int) -> None:
            if slot in slots:
                first = cells[slots[slot]].strip()
                raise ReadingError(
                    f"{at} names {first!r} and {cells[col].strip()!r}, two columns for the same value: keep one"
                )
            slots[slot] = col

        for col, name in enumerate(names):
            seen[name] = col
            match = _COLUMN.fullmatch(name)
            if match is None and name not in ("id", "t", *_JIG_COLUMNS):
                if name:
                    ignored.append(cells[col].strip())
            elif name == "id":
                id_col = col
            elif name == "t":
                t_col = col
            elif name in _JIG_COLUMNS:
                jig[_JIG_COLUMNS[name]] = col
            elif match is not None:
                stem, k, c = match.group(1), int(match.group(2)), match.group(3)
                if stem in _PER_CORE:
                    if c is None:
                        raise ReadingError(f"{at}: column {name!r} needs a core number too ({stem}_K_C, 1-based)")
                    claim((_PER_CORE[stem], k, int(c)), col)
                    values.setdefault(_PER_CORE[stem], {})[(k, int(c))] = col
                elif c is not None:
                    raise ReadingError(f"{at}: column {name!r} has a core number, which {stem}_K does not take")
                elif stem in _FORCE_FIELDS:
                    claim(("force", k, stem), col)
                    forces.setdefault(k, {})[stem] = col
                else:
                    key, j = _PAIRS[stem]
                    claim((key, k, j + 1), col)
                    values.setdefault(key, {})[(k, j + 1)] = col
        if not values:
            shown = ", ".join(repr(c.strip()) for c in cells[:12]) + (" ..." if len(cells) > 12 else "")
            raise ReadingError(f"{at} names no reading column ({shown}); expected {_expected_columns(G)}")
        if len(values) > 1:
            raise ReadingError(
                f"{at} names columns of {' and '.join(sorted(values))}: a file gives exactly one quantity"
            )
        ((key, cols),) = values.items()
        per = _per_grating(key, fibre, f"{at}'s {_COLUMN_NAMES[key]} columns")
        stems = {"curvature": ("ux", "uy"), "curvature_polar": ("kappa", "phi")}.get(key)

        def column_name(k: int, j: int) -> str:
            return f"{stems[j - 1]}_{k}" if stems else f"{_COLUMN_NAMES[key].split('_')[0]}_{k}_{j}"

        beyond = sorted((k, j) for k, j in cols if not (1 <= k <= G and 1 <= j <= per))
        if beyond:
            k, j = beyond[0]
            raise ReadingError(
                f"{at} names column {column_name(k, j)!r}, outside the rod's gratings 1..{G}"
                + (f" and the fibre's cores 1..{per}" if not stems else "")
                + " (numbers are 1-based)"
            )
        missing = [column_name(k, j) for k in range(1, G + 1) for j in range(1, per + 1) if (k, j) not in cols]
        if missing:
            more = f" and {len(missing) - 6} more" if len(missing) > 6 else ""
            raise ReadingError(
                f"{at} lacks the columns {', '.join(missing[:6])}{more}: give every grating's columns (leave a "
                "missing grating's cells empty in its rows)" + _ignored_note(ignored)
            )
        force_cols: list[tuple[int, int, int]] = []
        for j in sorted(forces):
            lack = [f for f in _FORCE_FIELDS if f not in forces[j]]
            if lack:
                raise ReadingError(f"{at}: force {j} lacks the column(s) {', '.join(f'{f}_{j}' for f in lack)}")
            force_cols.append(cast("tuple[int, int, int]", tuple(forces[j][f] for f in _FORCE_FIELDS)))  # s, fx, fy
        if id_col is None and t_col is None and ignored:
            warnings.warn(_unread_columns(at, ignored), ReadingWarning, stacklevel=2)
        data = tuple((col, k - 1, j - 1) for (k, j), col in sorted(cols.items()))
        return cls(key, per, len(cells), id_col, t_col, data, tuple(force_cols), tuple(sorted(jig.items())), line)

    @classmethod
    def positional(cls, width: int, num_gratings: int, quantity: str = "curvature", fibre: Any = None) -> CsvLayout:
        """The layout of a row without a header, by its width: ``id, t`` then the values; ``t`` then the values; or
        the values alone (per grating in order ``ux, uy`` / ``kappa, phi`` / the C core values);
        ``ValueError`` for any other width."""
        if quantity not in QUANTITIES:
            raise OptionsError(f"quantity must be one of {', '.join(QUANTITIES)}, got {quantity!r}")
        key = QUANTITIES[quantity]
        per = _per_grating(key, fibre, f"rows of --csv-quantity {quantity}")
        G = num_gratings
        values = per * G
        names = {"curvature": "ux, uy", "curvature_polar": "kappa, phi"}.get(key, f"{per} {key.replace('_', ' ')}s")
        if width not in (values, values + 1, values + 2):
            raise ReadingError(
                f"expected {values + 2} cells (id, t, then {names} for {G} gratings), {values + 1} (t, then the "
                f"values) or {values} (the values alone), got {width}; or give a header row naming the columns"
            )
        lead = width - values
        data = tuple((lead + per * k + j, k, j) for k in range(G) for j in range(per))
        return cls(key, per, width, 0 if lead == 2 else None, lead - 1 if lead else None, data)

    def ident(self, cells: Sequence[str]) -> Any:
        """The row's id (:func:`csv_id`), or None when it has none or one JSON cannot echo."""
        if self.id_column is None or self.id_column >= len(cells):
            return None
        ident = csv_id(cells[self.id_column])
        return ident if id_problem(ident) is None else None

    def reading_object(self, cells: Sequence[str]) -> dict[str, Any]:
        """One row as the reading's JSON object (``id``, ``t``, the quantity's key; ``forces`` and ``jig`` where
        the header names them). ``ValueError`` naming the cell as the JSON field (``curvature[3][0]``)."""
        n = len(cells)
        if n < self.width or any(c.strip() for c in cells[self.width :]):
            where = f"the header (line {self.header}) names {self.width} columns" if self.header else f"{self.width}"
            raise ReadingError(f"the row has {n} cells, {where}")
        obj: dict[str, Any] = {}
        if self.id_column is not None:
            obj["id"] = csv_id(cells[self.id_column])
        if self.t_column is not None:
            obj["t"] = csv_number(cells[self.t_column], "t")
        key = self.key
        rows: list[Any] = [[None] * self.per for _ in range(max((k for _, k, _ in self.data), default=-1) + 1)]
        for col, k, j in self.data:
            rows[k][j] = csv_number(cells[col], f"{key}[{k}][{j}]")
        for k, row in enumerate(rows):
            if all(x is None for x in row):
                rows[k] = None
                continue
            for j, x in enumerate(row):
                if x is None:
                    raise ReadingError(
                        f"{key}[{k}][{j}] must be a number, got null (an empty cell): leave all the cells of a "
                        "missing grating empty"
                    )
        obj[key] = rows
        if self.forces:
            forces = []
            for j, cols in enumerate(self.forces, start=1):
                got = [csv_number(cells[c], f"{name}_{j}") for c, name in zip(cols, _FORCE_FIELDS, strict=True)]
                if all(x is None for x in got):
                    continue
                if any(x is None for x in got):
                    raise ReadingError(f"force {j} has an empty cell: give s_{j}, fx_{j} and fy_{j}, or none of them")
                forces.append(dict(zip(_FORCE_FIELDS, got, strict=True)))
            obj["forces"] = forces
        if self.jig:
            jig: dict[str, Any] = {}
            for name, col in self.jig:
                if name == "name":
                    value = csv_id(cells[col])
                else:
                    value = csv_number(cells[col], f"jig_{name}")
                if value is not None:
                    jig[name] = value
            obj["jig"] = jig
        return obj


def parse_csv_row(
    cells: Sequence[str],
    num_gratings: int,
    *,
    line: int | None = None,
    quantity: str = "curvature",
    fibre: Any = None,
    layout: CsvLayout | None = None,
) -> Reading:
    """One CSV row -> a checked :class:`Reading`: by ``layout`` (a header's), else by position
    (:meth:`CsvLayout.positional`: ``id, t``, or ``t``, or nothing, then per grating ``ux, uy``
    (``quantity="curvature"``), ``kappa, phi`` (``"polar"``) or the fibre's C core values (``"strain"``,
    ``"wavelength"``, ``"wavelength-shift"``)). ``ValueError`` naming the cell as the JSON field
    (``curvature[k][j]``), so messages match the JSON ones. All the cells of a missing grating are empty."""
    if layout is None:
        layout = CsvLayout.positional(len(cells), num_gratings, quantity, fibre)
    return parse_reading(layout.reading_object(cells), num_gratings, line=line, fibre=fibre)


def _csv_cells(text: str) -> list[str]:
    import csv

    return next(csv.reader([text.rstrip("\r\n")]), [])


def _is_csv_header(cells: Sequence[str]) -> bool:
    """A first row of at least two non-empty cells, none of them a number."""
    rest = [c.strip() for c in cells if c.strip()]
    if len(rest) < 2:
        return False
    return not any(_CSV_NUMBER.fullmatch(c) or _CSV_NONFINITE.fullmatch(c) for c in rest)


def _csv_records(
    lines: Iterable[tuple[int, str]], num_gratings: int, quantity: str, fibre: Any, parse: Callable[[Any], Any]
) -> Iterator[Any]:
    import csv

    from .jsonl import Overlong, Record, overlong_error, parsed_record

    layout: CsvLayout | None = None
    first = True
    for number, text in lines:
        if isinstance(text, Overlong):
            yield Record(number, None, None, overlong_error(number, text))
            continue
        try:
            cells = _csv_cells(text)
        except csv.Error as exc:
            yield Record(number, None, None, f"line {number}: not valid CSV ({quote(str(exc))})")
            continue
        if first:
            first = False
            problem = _one_cell_problem(cells, number)
            if problem is not None:
                raise ReadingError(problem)
            if _is_csv_header(cells):
                layout = CsvLayout.from_header(cells, num_gratings, fibre, number)
                continue
        ident = None
        try:
            if layout is None:
                # a row without a header whose width fits no layout is named by its first cell when that is text
                # (it can only be an id)
                lead = csv_id(cells[0]) if cells else None
                ident = lead if isinstance(lead, str) and id_problem(lead) is None else None
            row_layout = layout or CsvLayout.positional(len(cells), num_gratings, quantity, fibre)
            ident = row_layout.ident(cells)
            obj = row_layout.reading_object(cells)
        except ValueError as exc:
            yield Record(number, ident, None, f"line {number}: {exc}")
            continue
        yield parsed_record(number, obj, parse)


# ---------------------------------------------------------------------------------------------------- files
FORMATS = ("auto", "jsonl", "csv", "peaks")
"""Input formats of a readings file: JSON lines, CSV, an interrogator's peak log (:mod:`torchrod.io.peaklog`), or
``auto``: by the file's extension (``.csv``; ``.jsonl``, ``.json``, ``.ndjson``), else by its first non-blank line
(``{`` opens JSON lines, ``TIME: number, ...`` a peak log, anything else is CSV)."""


def detect_format(source: Any, head: str | None) -> str:
    """The format ``auto`` reads ``source`` as, given its first non-blank line ``head`` (:data:`FORMATS`)."""
    from .peaklog import is_peak_line

    name = os.fspath(source) if isinstance(source, (str, os.PathLike)) else str(getattr(source, "name", ""))
    ext = os.path.splitext(name)[1].lower()
    if ext == ".csv":
        return "csv"
    if ext in (".jsonl", ".json", ".ndjson"):
        return "jsonl"
    if head is None:
        return "jsonl"
    text = head.lstrip("\ufeff").lstrip()
    if text.startswith(("{", "[")):
        return "jsonl"
    if is_peak_line(text):
        return "peaks"
    return "csv"


def iter_records(
    source: Any,
    num_gratings: int,
    parse: Callable[[Any], Any],
    fmt: str = "jsonl",
    control: Any = None,
    *,
    quantity: str = "curvature",
    fibre: Any = None,
    peaks: Any = None,
    max_line: int | None = None,
) -> Iterator[Any]:
    """Each non-blank line of ``source`` (a path, ``"-"``, ``tcp://HOST:PORT`` or an open text stream) as the
    reading's JSON object (a JSON line decoded, a CSV row or a peak log line made into one), handed to ``parse``:
    one :class:`torchrod.io.jsonl.Record` per line (a CSV header excepted), in order, lazily; a line that cannot be
    used is an error record (``"line N: ..."``). A CSV header that cannot be used raises
    :class:`~torchrod.errors.ReadingError` (no row can be read without it).

    Args:
        fmt: one of :data:`FORMATS`.
        control: a :class:`torchrod.io.jsonl.ReadControl` to end the reading at the lines already read.
        quantity: what a CSV row without a header gives per grating (:data:`QUANTITIES`).
        fibre: the rod's :class:`torchrod.sensors.Fibre` (cores, wavelength section, units).
        peaks: a peak log's layout, overriding the rod file's (:meth:`torchrod.sensors.Fibre.peak_layout`).
        max_line: the longest line read [bytes] (None: the rod's, :func:`line_limit`); a longer one is an error
            record, read past without being held.
    """
    from .jsonl import line_bytes, parse_records, read_lines

    if fmt not in FORMATS:
        raise OptionsError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if quantity not in QUANTITIES:
        raise OptionsError(f"quantity must be one of {', '.join(QUANTITIES)}, got {quantity!r}")
    limit = line_limit(num_gratings, fibre) if max_line is None else line_bytes(max_line)
    lines: Iterator[tuple[int, str]] = iter(read_lines(source, control, limit))
    if fmt == "auto":
        from .jsonl import Overlong

        # The first line that was read decides (an overlong line, not kept, cannot: it is an error in either format).
        held = []
        head = next(lines, None)
        while head is not None and isinstance(head[1], Overlong):
            held.append(head)
            head = next(lines, None)
        if head is None and not held:
            return
        fmt = detect_format(source, None if head is None else head[1])
        lines = _chain(held + ([head] if head is not None else []), lines)
    if fmt == "csv":
        yield from _csv_records(lines, num_gratings, quantity, fibre, parse)
    elif fmt == "peaks":
        from .peaklog import PeakLog

        yield from PeakLog(fibre, num_gratings, peaks).records(lines, parse)
    else:
        yield from parse_records(lines, parse)


def iter_readings(
    source: Any,
    num_gratings: int,
    gratings: Sequence[float] | None = None,
    fmt: str = "jsonl",
    control: Any = None,
    *,
    quantity: str = "curvature",
    fibre: Any = None,
    peaks: Any = None,
    max_line: int | None = None,
) -> Iterator[Reading]:
    """Readings from ``source`` (:func:`iter_records`, whose ``max_line`` bounds a line), lazily, one
    :class:`Reading` per non-blank line in order (a CSV header row excepted): checked, or with ``error`` set
    (``"line N: ..."``) for a line that cannot be used."""

    def parse(obj: Any) -> Reading:
        return parse_reading(obj, num_gratings, gratings, fibre=fibre)

    records = iter_records(
        source, num_gratings, parse, fmt, control, quantity=quantity, fibre=fibre, peaks=peaks, max_line=max_line
    )
    for record in records:
        if record.ok and record.value is not None:
            # The reading parse just made, not yet seen by anyone: its line set in place (cheaper than a copy).
            object.__setattr__(record.value, "line", record.line)
            yield record.value
        else:
            yield Reading(record.id, error=record.error, line=record.line)


class ReadingSource:
    """The readings of a file, standard input or a TCP connection (:func:`iter_readings`), as an iterable that the
    flush after an interrupt can end at the lines already read: :meth:`halt` makes it yield the readings of the
    complete lines it holds in memory and then end instead of reading more; :attr:`waiting` is true while it waits
    on the input (holding no complete line). :func:`torchrod.io.stream.stream` uses both when its source has them.
    ``max_line`` bounds a line as in :func:`iter_records` (None: the rod's, :func:`line_limit`). ``never_waits``
    is true for a regular file, not a pipe, a device, standard input or a TCP connection (the stream then reads it
    without a reader thread)."""

    def __init__(
        self,
        source: Any,
        num_gratings: int,
        gratings: Sequence[float] | None = None,
        fmt: str = "jsonl",
        *,
        quantity: str = "curvature",
        fibre: Any = None,
        peaks: Any = None,
        max_line: int | None = None,
    ) -> None:
        from .jsonl import ReadControl

        if fmt not in FORMATS:
            raise OptionsError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
        self.control = ReadControl()
        self.never_waits = (
            isinstance(source, (str, os.PathLike)) and os.fspath(source) != "-" and os.path.isfile(source)
        )
        self._readings = iter_readings(
            source,
            num_gratings,
            gratings,
            fmt,
            self.control,
            quantity=quantity,
            fibre=fibre,
            peaks=peaks,
            max_line=max_line,
        )

    def __iter__(self) -> Iterator[Reading]:
        return self._readings

    def halt(self) -> None:
        self.control.halt()

    @property
    def waiting(self) -> bool:
        return self.control.waiting.is_set()


def _chain(head: list[tuple[int, str]], rest: Iterator[tuple[int, str]]) -> Iterator[tuple[int, str]]:
    yield from head
    yield from rest


# ---------------------------------------------------------------------------------------------------- tensors
def line_limit(num_gratings: int, fibre: Any = None) -> int:
    """The longest line read as a reading of a rod of ``num_gratings`` gratings [bytes]: :data:`MIN_LINE_BYTES`, or
    :data:`LINE_BYTES_PER_VALUE` per value its largest reading holds when that is more (per grating, one value per
    core of the fibre's, at least two, and its position in ``gratings``). A longer line is an error line read past
    without being held (module docstring), so a line costs at most a few tens of MB whatever it holds."""
    cores = len(getattr(fibre, "cores", None) or ())
    values = num_gratings * (max(2, cores) + 1)
    return max(MIN_LINE_BYTES, LINE_BYTES_PER_VALUE * values)


def unusable_lines(name: str, bad: list[str]) -> ReadingError:
    """The error of a file whose every line must be usable (a calibration's): how many lines were not, and the
    first five of their error lines."""
    more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
    return ReadingError(f"{name}: {len(bad)} unusable line(s): " + "; ".join(bad[:5]) + more)
