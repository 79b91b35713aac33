"""FBG readings: what one reading is, and the one set of rules every entry point checks it by.

``torchrod estimate``, ``torchrod stream``, ``torchrod calibrate``, ``torchrod plot``, the Python stream API
(:func:`torchrod.io.stream.stream`: dicts, lists, tensors) and the estimator itself (:func:`check_readings`, on
tensors) all check readings here, so a reading means the same thing, and fails with the same message, wherever it
enters.

A reading
    ``curvature``: one entry per grating of the rod, in the rod file's order: a pair ``[ux, uy]`` [1/m], or
    ``null``/``None`` for a grating that gave no reading (it is left out of the fit, never read as zero). As a
    tensor or array it is (G, 2) with a row of NaN for a missing grating. At least one grating must be present.
    ``id`` (optional): any JSON value, echoed in the answer (rules below). ``t`` (optional): a timestamp [s],
    echoed. ``gratings`` (optional, JSON): the grating positions [m]; when given they must be the rod's (within
    1e-9 m), which catches readings meant for another rod. Other keys are ignored.

    Instead of ``curvature`` a reading may give one of (:mod:`torchrod.sensors`; exactly one of the three):
    ``strain``: per grating the C core strains ``[eps_1, ..., eps_C]`` of the rod file's multicore ``fibre``
    (dimensionless: 1e-6 is one microstrain; ``|eps| <= MAX_STRAIN``), or null; ``curvature_polar``: per grating
    ``[kappa, phi]``, the curvature magnitude (>= 0) [1/m] and the bend angle [rad] from d1 towards d2, or null.
    Both are turned into (ux, uy) here, so everything downstream sees curvature.

Numbers
    A number is a JSON number (Python: ``int``, ``float`` or another real number; never a boolean or a string). It
    must be finite: ``NaN``, ``Infinity`` and literals that overflow a double (``1e999``, an integer of 400 digits)
    are refused. A curvature component must also satisfy ``|u| <= MAX_CURVATURE`` (1e6 1/m, a bend radius of 1 um:
    no rod or fibre bends that much, so such a value is a unit or scaling error). Finite values within the bound
    are passed on as they are, however implausible (1e4 1/m reaches the estimator, which flags a bad fit).

CSV rows (``--format csv``)
    ``id, t`` and then, per grating in order, ``ux, uy`` (``quantity="curvature"``), ``kappa, phi``
    (``"polar"``) or the C core strains (``"strain"``); all the cells of a missing grating are empty. A first row
    of names is a header and skipped.

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

Messages
    Every message names the field (``curvature[3][0]``, ``t``, ``id``) and quotes at most ``QUOTE_CHARS``
    characters of the offending value (with its full length when cut), so a 10 MB value gives a short message;
    quoting never recurses, so deeply nested values are quoted safely too.
"""

from __future__ import annotations

import math
import numbers
import re
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch

__all__ = [
    "MAX_CURVATURE",
    "MAX_ID_CHARS",
    "MAX_ID_DEPTH",
    "MAX_INT_DIGITS",
    "QUANTITIES",
    "QUOTE_CHARS",
    "HugeInteger",
    "Reading",
    "ReadingSource",
    "as_number",
    "check_gratings",
    "check_id",
    "check_readings",
    "check_time",
    "csv_number",
    "curvature_tensor",
    "describe",
    "id_problem",
    "iter_readings",
    "parse_csv_row",
    "parse_reading",
    "polar_curvature",
    "quote",
    "reading_curvature",
    "stack_readings",
    "strain_curvature",
    "to_reading",
]

MAX_CURVATURE = 1e6
"""[1/m] The largest curvature component accepted from any input: a bend radius of 1 um. A nitinol tube or an
optical fibre breaks at radii of millimetres (curvature ~ 1e3 1/m), so a larger value is a unit or scaling error
(microstrain, 1/km, a raw interrogator count), refused at the edge instead of being handed to the estimator."""

QUOTE_CHARS = 100
"""Characters of an offending value quoted in a message, at most (its length is added when it is cut)."""

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
                text = _scalar_text(item, limit)
                if text is None:
                    stack.append(_pieces(item))
                    continue
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
        raise ValueError(  # noqa: TRY004 (bad data, one kind of error)
            f"{what} must be a finite number, got an integer of {value.digits} digits ({value!r})"
        )
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{what} must be a number, got {describe(value)}")  # noqa: TRY004 (bad data, one kind of error)
    try:
        x = float(value)
    except OverflowError:
        raise ValueError(f"{what} must be a finite number, got {quote(value)}, which overflows a float") from None
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {quote(x)}")
    if bound is not None and not abs(x) <= bound:
        unit = f" {unit}" if unit else ""
        raise ValueError(
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
        raise ValueError(f"{what} must be finite, got {quote(cell)} (leave a missing value's cell empty)")
    if not _CSV_NUMBER.fullmatch(cell):
        raise ValueError(
            f"{what} must be a number, got {quote(cell)}: a CSV number is decimal digits with an optional sign, "
            "point and exponent (no underscores, hexadecimal or separators)"
        )
    x = float(cell)
    if math.isinf(x):
        raise ValueError(f"{what} must be a finite number, got {quote(cell)}, which overflows a float")
    return as_number(x, what, bound=bound, unit=unit)


# ---------------------------------------------------------------------------------------------------- fields
def id_problem(value: Any) -> str | None:
    """Why JSON cannot echo ``value`` as an id (module docstring), or None when it can. Never recurses."""
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
        raise ValueError(problem + _ID_HINT)
    return value


def check_time(value: Any, what: str = "t") -> float | None:
    """A timestamp [s]: None when absent (None), else a finite number of seconds."""
    if value is None:
        return None
    try:
        return as_number(value, what)
    except ValueError as exc:
        raise ValueError(f"{exc} ({what} is a timestamp in seconds, or null)") from None


def check_gratings(value: Any, gratings: Sequence[float], what: str = "gratings") -> None:
    """The grating positions [m] a reading declares must be the rod's (within :data:`GRATING_TOLERANCE`)."""
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{what} must be an array of the grating positions [m], got {describe(value)}")  # noqa: TRY004
    positions = [as_number(x, f"{what}[{k}]") for k, x in enumerate(value)]
    if len(positions) != len(gratings) or any(
        abs(a - b) > GRATING_TOLERANCE for a, b in zip(positions, gratings, strict=False)
    ):
        raise ValueError(
            f"{what} {quote(positions)} do not match the rod's {quote(list(gratings))}: "
            "these readings are for another rod (give the matching --rod)"
        )


def _missing_hint(what: str) -> str:
    return f"(for a grating without a reading give null in place of the pair {what})"


def curvature_tensor(value: Any, num_gratings: int, what: str = "curvature") -> torch.Tensor:
    """A reading's curvature as a (G, 2) float64 CPU tensor [1/m], a row of NaN per missing grating.

    Args:
        value: a list or tuple of G entries, each ``[ux, uy]`` or None; or a (G, 2) real tensor or array (a row
            of NaN marks a missing grating; a half-NaN row and infinities are refused).
        num_gratings: G.
    Raises:
        ValueError: naming the entry and quoting its value (module docstring: the rules).
    """
    G = num_gratings
    if isinstance(value, torch.Tensor) or (
        hasattr(value, "__array__") and hasattr(value, "shape") and not isinstance(value, (list, tuple))
    ):
        return _tensor_rows(value, G, what)
    if not isinstance(value, (list, tuple)):
        raise ValueError(  # noqa: TRY004 (bad data, one kind of error)
            f"{what} must be an array of {G} [ux, uy] pairs [1/m] (null for a missing grating), got {describe(value)}"
        )
    if len(value) != G:
        raise ValueError(
            f"{what} holds {len(value)} gratings, the rod has {G}: give one [ux, uy] pair or null per grating, "
            "in the rod file's order"
        )
    nan = math.nan
    rows: list[tuple[float, float]] = []
    for k, row in enumerate(value):
        if row is None:
            rows.append((nan, nan))
            continue
        if type(row) is list and len(row) == 2:  # the usual case, checked fast
            a, b = row
            if type(a) is float and type(b) is float and abs(a) <= MAX_CURVATURE and abs(b) <= MAX_CURVATURE:
                rows.append((a, b))
                continue
        where = f"{what}[{k}]"
        if not isinstance(row, (list, tuple)) or len(row) != 2:
            raise ValueError(f"{where} must be a pair [ux, uy] of numbers [1/m] or null, got {describe(row)}")
        pair = []
        for j, x in enumerate(row):
            try:
                pair.append(as_number(x, f"{where}[{j}]", bound=MAX_CURVATURE, unit="1/m"))
            except ValueError as exc:
                if isinstance(x, float) and math.isnan(x):
                    raise ValueError(f"{exc} {_missing_hint(where)}") from None
                raise
        rows.append((pair[0], pair[1]))
    if len(rows) == 0 or all(math.isnan(r[0]) for r in rows):
        raise ValueError(f"all gratings are missing: {what} needs at least one [ux, uy] pair")
    return torch.tensor(rows, dtype=torch.float64).reshape(G, 2)


def _tensor_rows(value: Any, G: int, what: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        try:
            value = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ValueError(f"{what} must be a real (G, 2) array, got {quote(value)} ({exc})") from None
    if value.dtype == torch.bool or value.is_complex():
        raise ValueError(f"{what} must be a real tensor, got {value.dtype}")
    if tuple(value.shape) != (G, 2):
        raise ValueError(f"{what} must have shape ({G}, 2) for this rod, got {tuple(value.shape)}")
    t = value.detach().to("cpu", torch.float64)
    present = 0
    for k, (a, b) in enumerate(t.tolist()):  # (G, 2) values: a Python loop is cheaper than tensor checks
        if abs(a) <= MAX_CURVATURE and abs(b) <= MAX_CURVATURE:
            present += 1
        elif math.isnan(a) and math.isnan(b):
            continue
        elif math.isnan(a) or math.isnan(b):
            raise ValueError(f"{what}[{k}] has one NaN component: a missing grating is a row of NaN")
        else:
            for j, x in enumerate((a, b)):
                as_number(x, f"{what}[{k}][{j}]", bound=MAX_CURVATURE, unit="1/m")
    if not present:
        raise ValueError(f"all gratings are missing: {what} needs at least one finite row")
    return t


QUANTITIES = {"curvature": "curvature", "strain": "strain", "polar": "curvature_polar"}
"""What a reading may give, by its name in options (``--csv-quantity``) and its JSON key."""


def _entries(value: Any, G: int, what: str, shape: str) -> list[Any]:
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{what} must be an array of {G} {shape} (null for a missing grating), got {describe(value)}")  # noqa: TRY004
    if len(value) != G:
        raise ValueError(f"{what} holds {len(value)} gratings, the rod has {G}: give one {shape} or null per grating")
    return list(value)


def _converted(pair: tuple[float, float], where: str, source: str) -> list[float]:
    if not (abs(pair[0]) <= MAX_CURVATURE and abs(pair[1]) <= MAX_CURVATURE):
        raise ValueError(
            f"{where} gives a curvature of {quote(list(pair))} 1/m, beyond the bound of {MAX_CURVATURE:g} 1/m; "
            f"check the units of the {source}"
        )
    return [pair[0], pair[1]]


def strain_curvature(value: Any, num_gratings: int, fibre: Any, what: str = "strain") -> list[Any]:
    """A reading's core strains (one list of C per grating, or None) -> its G (ux, uy) pairs [1/m] or None, by
    the fibre's least squares (:class:`torchrod.sensors.Fibre`). ``ValueError`` naming the entry."""
    from ..sensors import MAX_STRAIN

    if fibre is None:
        raise ValueError(
            f'{what} needs the rod\'s multicore fibre: add "fibre": {{"cores": [[x, y], ...]}} (core positions [m]) '
            "to the rod file"
        )
    C = fibre.num_cores
    rows: list[Any] = []
    for k, entry in enumerate(_entries(value, num_gratings, what, f"list of {C} core strains")):
        if entry is None:
            rows.append(None)
            continue
        where = f"{what}[{k}]"
        if not isinstance(entry, (list, tuple)) or len(entry) != C:
            raise ValueError(
                f"{where} must be a list of {C} core strains (the fibre has {C} cores), got {describe(entry)}"
            )
        eps = []
        for c, x in enumerate(entry):
            try:
                eps.append(as_number(x, f"{where}[{c}]", bound=MAX_STRAIN))
            except ValueError as exc:
                if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x)):
                    raise ValueError(f"{exc} (strain is dimensionless: 1e-6 is one microstrain)") from None
                raise
        rows.append(_converted(fibre.strain_to_curvature(eps), where, "strains"))
    return rows


def polar_curvature(value: Any, num_gratings: int, what: str = "curvature_polar") -> list[Any]:
    """A reading's (kappa [1/m], phi [rad]) per grating, or None -> its G (ux, uy) pairs [1/m] or None."""
    from ..sensors import polar_to_curvature

    rows: list[Any] = []
    for k, entry in enumerate(_entries(value, num_gratings, what, "[kappa, phi] pair")):
        if entry is None:
            rows.append(None)
            continue
        where = f"{what}[{k}]"
        if not isinstance(entry, (list, tuple)) or len(entry) != 2:
            raise ValueError(f"{where} must be a pair [kappa, phi] ([1/m], [rad]) or null, got {describe(entry)}")
        kappa = as_number(entry[0], f"{where}[0]", bound=MAX_CURVATURE, unit="1/m")
        if kappa < 0.0:
            raise ValueError(f"{where}[0] is a curvature magnitude and must be >= 0 [1/m], got {quote(entry[0])}")
        phi = as_number(entry[1], f"{where}[1]", bound=1e6, unit="rad")
        rows.append(_converted(polar_to_curvature(kappa, phi), where, "curvature"))
    return rows


def reading_curvature(obj: Mapping[str, Any], num_gratings: int, fibre: Any = None) -> torch.Tensor:
    """The (G, 2) curvature [1/m] of a reading object that gives ``curvature``, ``strain`` or
    ``curvature_polar`` (exactly one)."""
    given = [key for key in QUANTITIES.values() if key in obj]
    if len(given) > 1:
        raise ValueError(f"a reading gives {' and '.join(given)}: give exactly one of {', '.join(QUANTITIES.values())}")
    if not given:
        raise ValueError(
            f"missing 'curvature' (an array of {num_gratings} [ux, uy] pairs [1/m], one per grating; or 'strain' "
            "or 'curvature_polar')"
        )
    key = given[0]
    if key == "strain":
        rows = strain_curvature(obj[key], num_gratings, fibre)
    elif key == "curvature_polar":
        rows = polar_curvature(obj[key], num_gratings)
    else:
        return curvature_tensor(obj[key], num_gratings)
    if all(r is None for r in rows):
        raise ValueError(f"all gratings are missing: {key} needs at least one grating's values")
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
    if not isinstance(obj, Mapping):
        raise ValueError(  # noqa: TRY004 (bad data, one kind of error)
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
    curvature = torch.stack([r.curvature for r in readings])
    mask = ~torch.isnan(curvature).any(-1)
    return torch.where(mask.unsqueeze(-1), curvature, torch.zeros((), dtype=curvature.dtype)), mask


# ---------------------------------------------------------------------------------------------------- CSV
def parse_csv_row(
    cells: Sequence[str],
    num_gratings: int,
    *,
    line: int | None = None,
    quantity: str = "curvature",
    fibre: Any = None,
) -> Reading:
    """One CSV row ``id, t``, then per grating ``ux, uy`` (``quantity="curvature"``), ``kappa, phi``
    (``"polar"``) or the fibre's C core strains (``"strain"``) -> a checked :class:`Reading` (``ValueError``
    naming the cell as the JSON field, ``curvature[k][j]``, so messages match the JSON ones). All the cells of a
    missing grating are empty."""
    if quantity not in QUANTITIES:
        raise ValueError(f"quantity must be one of {', '.join(QUANTITIES)}, got {quantity!r}")
    G = num_gratings
    key = QUANTITIES[quantity]
    if quantity == "strain" and fibre is None:
        strain_curvature([], G, None)  # raises: the rod has no fibre
    per = fibre.num_cores if quantity == "strain" else 2
    names = {"curvature": "ux, uy", "polar": "kappa, phi", "strain": f"{per} core strains"}[quantity]
    width = 2 + per * G
    if len(cells) != width:
        raise ValueError(f"expected {width} cells (id, t, then {names} for {G} gratings), got {len(cells)}")
    ident = check_id(cells[0].strip() or None)
    t = csv_number(cells[1], "t")
    rows: list[Any] = []
    for k in range(G):
        group = cells[2 + per * k : 2 + per * (k + 1)]
        if not any(c.strip() for c in group):
            rows.append(None)
            continue
        where = f"{key}[{k}]"
        values = [csv_number(c, f"{where}[{j}]") for j, c in enumerate(group)]
        for j, x in enumerate(values):
            if x is None:
                raise ValueError(
                    f"{where}[{j}] must be a number, got null (an empty cell): leave all the cells of a missing "
                    "grating empty"
                )
        rows.append(values)
    return _checked(Reading(ident, reading_curvature({key: rows}, G, fibre), t, None, line))


def _csv_cells(text: str) -> list[str]:
    import csv

    return next(csv.reader([text.rstrip("\r\n")]), [])


def _is_csv_header(cells: Sequence[str]) -> bool:
    """A first row whose non-empty cells after the id are all non-numbers (at least one)."""
    rest = [c.strip() for c in cells[1:] if c.strip()]
    if not rest:
        return False
    return not any(_CSV_NUMBER.fullmatch(c) or _CSV_NONFINITE.fullmatch(c) for c in rest)


def _csv_readings(
    lines: Iterable[tuple[int, str]], num_gratings: int, quantity: str = "curvature", fibre: Any = None
) -> Iterator[Reading]:
    import csv

    from .jsonl import Overlong, overlong_error

    first = True
    for number, text in lines:
        if isinstance(text, Overlong):
            yield Reading(error=overlong_error(number), line=number)
            continue
        try:
            cells = _csv_cells(text)
        except csv.Error as exc:
            yield Reading(error=f"line {number}: not valid CSV ({quote(str(exc))})", line=number)
            continue
        if first:
            first = False
            if _is_csv_header(cells):
                continue
        ident = (cells[0].strip() or None) if cells else None
        ident = ident if id_problem(ident) is None else None
        try:
            yield parse_csv_row(cells, num_gratings, line=number, quantity=quantity, fibre=fibre)
        except ValueError as exc:
            yield Reading(ident, error=f"line {number}: {exc}", line=number)


# ---------------------------------------------------------------------------------------------------- files
FORMATS = ("auto", "jsonl", "csv")


def iter_readings(
    source: Any,
    num_gratings: int,
    gratings: Sequence[float] | None = None,
    fmt: str = "jsonl",
    control: Any = None,
    *,
    quantity: str = "curvature",
    fibre: Any = None,
) -> Iterator[Reading]:
    """Readings from ``source`` (a path, ``"-"`` for standard input, or an open text stream), lazily, one
    :class:`Reading` per non-blank line in order (a CSV header row excepted): checked, or with ``error`` set
    (``"line N: ..."``) for a line that cannot be used.

    Args:
        fmt: ``"jsonl"``, ``"csv"`` (module docstring), or ``"auto"``: JSON lines when the first non-blank line
            starts with ``{``, else CSV.
        control: a :class:`torchrod.io.jsonl.ReadControl` to end the reading at the lines already read.
        quantity: what a CSV row gives per grating (:data:`QUANTITIES`); a JSON line says it by its key.
        fibre: the rod's multicore fibre, for strains.
    """
    from .jsonl import parse_records, read_lines

    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if quantity not in QUANTITIES:
        raise ValueError(f"quantity must be one of {', '.join(QUANTITIES)}, got {quantity!r}")
    lines: Iterator[tuple[int, str]] = iter(read_lines(source, control))
    if fmt == "auto":
        from .jsonl import Overlong

        # The first line that was read decides (an overlong line, not kept, cannot: it is an error in either format).
        held = []
        head = next(lines, None)
        while head is not None and isinstance(head[1], Overlong):
            held.append(head)
            head = next(lines, None)
        fmt = "jsonl" if head is None or head[1].lstrip().startswith("{") else "csv"
        lines = _chain(held + ([head] if head is not None else []), lines)
    if fmt == "csv":
        yield from _csv_readings(lines, num_gratings, quantity, fibre)
        return
    for record in parse_records(lines, lambda obj: parse_reading(obj, num_gratings, gratings, fibre=fibre)):
        if record.ok and record.value is not None:
            yield _checked(replace(record.value, line=record.line))
        else:
            yield Reading(record.id, error=record.error, line=record.line)


class ReadingSource:
    """The readings of a file or standard input (:func:`iter_readings`), as an iterable that the flush after an
    interrupt can end at the lines already read: :meth:`halt` makes it yield the readings of the complete lines it
    holds in memory and then end instead of reading more; :attr:`waiting` is true while it waits on the input
    (holding no complete line). :func:`torchrod.io.stream.stream` uses both when its source has them."""

    def __init__(
        self,
        source: Any,
        num_gratings: int,
        gratings: Sequence[float] | None = None,
        fmt: str = "jsonl",
        *,
        quantity: str = "curvature",
        fibre: Any = None,
    ) -> None:
        from .jsonl import ReadControl

        if fmt not in FORMATS:
            raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
        self.control = ReadControl()
        self._readings = iter_readings(
            source, num_gratings, gratings, fmt, self.control, quantity=quantity, fibre=fibre
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
def check_readings(curvature: Any, mask: Any, num_gratings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a batch of readings and return ``(curvature, mask)`` (the estimator's and the network's check).

    Args:
        curvature: (B, G, 2) floating-point tensor [1/m].
        mask: (B, G) bool tensor on curvature's device, True where the grating was read; or None: a grating is
            missing where both its components are NaN.
        num_gratings: G, the rod's grating count.
    Returns:
        ``curvature`` unchanged and the mask.
    Raises:
        TypeError: curvature is not a floating-point tensor, or mask is not bool.
        ValueError: a wrong shape (naming it), a mask on another device, or a present grating whose value is not
            finite or exceeds :data:`MAX_CURVATURE` (without a mask: also a row with one NaN component, or an
            infinity), naming the first such entry.
    """
    if not isinstance(curvature, torch.Tensor) or not curvature.is_floating_point():
        raise TypeError(
            f"curvature must be a floating-point tensor, got {getattr(curvature, 'dtype', type(curvature))!r}"
        )
    G = num_gratings
    if curvature.dim() != 3 or curvature.shape[1:] != (G, 2):
        raise ValueError(f"curvature must have shape (B, {G}, 2) for this rod, got {tuple(curvature.shape)}")
    B = curvature.shape[0]
    if mask is None:
        nan = torch.isnan(curvature)
        mask = ~nan.all(-1)
        # One device sync: half-NaN rows, and present values that are infinite or beyond the bound.
        bad = (nan.any(-1) & mask) | (mask & ~(curvature.abs() <= MAX_CURVATURE).all(-1))
        if bool(bad.any()):
            b, g = (int(x) for x in bad.nonzero()[0])
            pair = [float(x) for x in curvature[b, g]]
            if any(math.isnan(x) for x in pair):
                raise ValueError(
                    f"curvature[{b}, {g}] = {pair} has one NaN component: a missing grating is a row of NaN "
                    "(or give a mask)"
                )
            raise ValueError(_present_problem(b, g, pair))
        return curvature, mask
    if not isinstance(mask, torch.Tensor) or mask.shape != (B, G):
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"mask must have shape (B, G) = {(B, G)}, got {shape}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.device != curvature.device:
        raise ValueError(f"mask is on {mask.device} but curvature is on {curvature.device}")
    bad = mask & ~(curvature.abs() <= MAX_CURVATURE).all(-1)
    if bool(bad.any()):
        b, g = (int(x) for x in bad.nonzero()[0])
        raise ValueError(_present_problem(b, g, [float(x) for x in curvature[b, g]], " but the mask marks it present"))
    return curvature, mask


def _present_problem(b: int, g: int, pair: list[float], masked: str = "") -> str:
    if not all(math.isfinite(x) for x in pair):
        return f"curvature[{b}, {g}] is not finite ({quote(pair)}){masked}"
    return (
        f"curvature[{b}, {g}] = {quote(pair)} 1/m exceeds the bound of {MAX_CURVATURE:g} 1/m that any reading must "
        "respect (check the units and scaling)"
    )
