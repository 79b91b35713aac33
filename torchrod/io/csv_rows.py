"""CSV readings: the header's layout (:class:`CsvLayout`), a row's cells, and the rows of a file as records.

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
    object and passes the same checks as a JSON line (:func:`torchrod.io.reading.parse_reading`); its numbers follow
    :mod:`torchrod.io.numbers`. A quoted cell may hold a line break: its row then spans the lines up to the closing
    quote and is one record, numbered by its first line, at most as long as a line may be (a longer one, as a quote
    never closed makes, is one error record). A line too long to read keeps the id its first cell holds.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, cast

from ..errors import OptionsError, ReadingError, ReadingWarning
from .numbers import CSV_NONFINITE, CSV_NUMBER, csv_number
from .quantities import QUANTITIES
from .reading import Reading, id_problem, parse_reading
from .values import HugeInteger, int_digit_limit, quote

__all__ = ["CsvLayout", "csv_id", "csv_records", "parse_csv_row"]


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
    numbers = [p for p in parts if CSV_NUMBER.fullmatch(p) or CSV_NONFINITE.fullmatch(p)]
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
    return not any(CSV_NUMBER.fullmatch(c) or CSV_NONFINITE.fullmatch(c) for c in rest)


def _ends_quoted(text: str, inside: bool = False) -> bool:
    """Whether CSV ``text`` ends inside a quoted cell (``inside``: it starts inside one), as :mod:`csv` reads it: a
    quote opens a cell only at the cell's start, ``""`` within quotes is one quote, and after a closing quote the
    cell's quotes are literal. Scans with ``str.find``, so a long line costs little."""
    i = 0
    if not inside and text.startswith('"'):
        inside, i = True, 1
    while True:
        if inside:
            j = text.find('"', i)
            if j < 0:
                return True
            if text.startswith('"', j + 1):
                i = j + 2
                continue
            inside, i = False, j + 1
        j = text.find(",", i)
        if j < 0:
            return False
        i = j + 1
        if text.startswith('"', i):
            inside, i = True, i + 1


MAX_RECORD_LINES = 16
"""The most lines one CSV record may span through quoted line breaks. A quote left open by mistake then costs its
own line only: the lines after it are read again as rows of their own, and a live stream's answers wait for at most
this many lines."""


def _whole_record(
    number: int, text: str, rows: Iterator[tuple[int, str]], limit: int
) -> tuple[str, str | None, list[tuple[int, str]]]:
    """The record that starts on line ``number`` with ``text``, which ends inside a quoted cell: ``text`` and the
    lines after it up to the one that closes the cell, joined (the line breaks stay in the cell, as CSV means), with
    no problem and nothing to read again. A cell not closed within :data:`MAX_RECORD_LINES` lines or ``limit``
    bytes is a quote left open: '', the error of line ``number``, and the lines taken after it, to be read again
    as rows. At the end of the input the record is what was read, as :mod:`csv` reads an unclosed quote."""
    from .jsonl import Overlong

    parts, size = [text], len(text)
    taken: list[tuple[int, str]] = []
    while True:
        more = next(rows, None)
        if more is None:
            return "".join(parts), None, []
        taken.append(more)
        last, line = more
        if isinstance(line, Overlong) or size + len(line) > limit or len(taken) >= MAX_RECORD_LINES:
            return (
                "",
                (
                    f"line {number}: a quoted cell opens here and is not closed within {MAX_RECORD_LINES} lines or "
                    f"{limit} bytes (a stray quote?); the line is not read, the lines after it are"
                ),
                taken,
            )
        parts.append(line)
        size += len(line)
        if not _ends_quoted(line, inside=True):
            return "".join(parts), None, []


class _Again:
    """Numbered lines, with lines taken ahead handed back to be read again first."""

    def __init__(self, lines: Iterable[tuple[int, str]]) -> None:
        self._lines = iter(lines)
        self._back: list[tuple[int, str]] = []

    def __iter__(self) -> _Again:
        return self

    def __next__(self) -> tuple[int, str]:
        return self._back.pop() if self._back else next(self._lines)

    def again(self, taken: list[tuple[int, str]]) -> None:
        self._back.extend(reversed(taken))


def _overlong_id(head: str, layout: CsvLayout | None) -> Any:
    """The id of a CSV line too long to read, from its first cell when that is the id and ends within ``head``
    (the line's start): the header's first column is ``id``; or, without a header, the cell is text (a number
    there could be ``t`` or a value). None otherwise, or when JSON cannot echo it."""
    import csv

    if layout is not None and layout.id_column != 0:
        return None
    try:
        cells = _csv_cells(head)
    except csv.Error:
        return None
    if len(cells) < 2:  # (the first cell may go on past the head)
        return None
    ident = csv_id(cells[0])
    if layout is None and not isinstance(ident, str):
        return None
    return ident if id_problem(ident) is None else None


def csv_records(
    lines: Iterable[tuple[int, str]],
    num_gratings: int,
    quantity: str,
    fibre: Any,
    parse: Callable[[Any], Any],
    max_line: int | None = None,
) -> Iterator[Any]:
    """The records of CSV ``lines`` (numbered, as :func:`torchrod.io.jsonl.read_lines` gives them), lazily: a
    header row first when there is one (:class:`CsvLayout`), then one :class:`torchrod.io.jsonl.Record` per row,
    its reading object handed to ``parse``; a row that cannot be used is an error record (``"line N: ..."``). A
    row whose quoted cell holds a line break spans lines and is one record, numbered by its first line; it may be
    at most ``max_line`` characters long (None: :data:`torchrod.io.jsonl.MAX_LINE_BYTES`), as a line is. A line
    too long to read keeps its id when its first cell holds it (:func:`_overlong_id`)."""
    import csv

    from .jsonl import MAX_LINE_BYTES, Overlong, Record, overlong_error, parsed_record

    limit = MAX_LINE_BYTES if max_line is None else max_line
    layout: CsvLayout | None = None
    first = True
    rows = _Again(lines)
    for number, text in rows:
        if isinstance(text, Overlong):
            yield Record(number, _overlong_id(text.head, layout), None, overlong_error(number, text))
            continue
        if '"' in text and _ends_quoted(text):
            text, problem, again = _whole_record(number, text, rows, limit)
            if problem is not None:
                yield Record(number, None, None, problem)
                rows.again(again)
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
