"""Where readings come from: a file, standard input or a TCP connection, read line by line in a format chosen by
name or by the input itself, each line made a checked :class:`~torchrod.io.reading.Reading`.

Lines
    A line of JSON, CSV or a peak log longer than :func:`line_limit` of the rod (1 MiB, more for a rod whose
    readings hold more than 16 384 values) is an error line (``longer than N bytes; not read``) and is read past in
    chunks without being held: no reading of the rod needs such a line, and decoding one would cost up to about 20
    times its size in memory. ``max_line`` (``--max-line-bytes``) sets another limit. The error keeps the line's id
    when the line starts with it (:func:`torchrod.io.jsonl.overlong_id`; a CSV row's first cell).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from ..errors import OptionsError, ReadingError
from .formats import AUTO_DEFAULT, AUTO_OTHERWISE, INPUT_FORMATS, ReadOptions, line_formats
from .quantities import QUANTITIES
from .reading import Reading, parse_reading

__all__ = [
    "FORMATS",
    "LINE_BYTES_PER_VALUE",
    "MIN_LINE_BYTES",
    "ReadingSource",
    "detect_format",
    "format_names",
    "iter_readings",
    "iter_records",
    "line_limit",
    "unusable_lines",
]

MIN_LINE_BYTES = 2**20
"""[bytes] The least :func:`line_limit` gives: a reading line of a rod of a few dozen gratings is a few kB, an
id at most :data:`torchrod.io.reading.MAX_ID_CHARS`; the rest is room for keys a reading may carry besides (they are
ignored)."""

LINE_BYTES_PER_VALUE = 64
"""[bytes] What :func:`line_limit` allows per value of a reading: a double written in full is at most 24
characters, with its separator and brackets about 30."""


FORMATS = ("auto", *line_formats())
"""Input formats of a readings file: the line formats of :data:`torchrod.io.formats.INPUT_FORMATS` (JSON lines, CSV,
an interrogator's peak log, :mod:`torchrod.io.peaklog`), or ``auto``: by the file's extension (``.jsonl``, ``.json``,
``.ndjson``; ``.csv``), else by its first non-blank line (``{`` opens JSON lines, ``TIME: number, ...`` a peak log,
anything else is CSV)."""


def format_names() -> tuple[str, ...]:
    """``auto`` and the line formats of :data:`torchrod.io.formats.INPUT_FORMATS` as the table holds them now
    (:data:`FORMATS` is their names when the package was loaded)."""
    return ("auto", *line_formats())


def _check_format(fmt: str) -> None:
    names = format_names()
    if fmt not in names:
        raise OptionsError(f"format must be one of {', '.join(names)}, got {fmt!r}")


def detect_format(source: Any, head: str | None) -> str:
    """The format ``auto`` reads ``source`` as, given its first non-blank line ``head`` (:data:`FORMATS`): the line
    format whose extension the name has, else the first whose test the line passes
    (:attr:`torchrod.io.formats.InputFormat.detect`), else :data:`torchrod.io.formats.AUTO_OTHERWISE`; without a
    line, :data:`torchrod.io.formats.AUTO_DEFAULT`."""
    formats = line_formats()
    name = os.fspath(source) if isinstance(source, (str, os.PathLike)) else str(getattr(source, "name", ""))
    ext = os.path.splitext(name)[1].lower()
    for fmt, entry in formats.items():
        if ext in entry.extensions:
            return fmt
    if head is None:
        return AUTO_DEFAULT
    text = head.lstrip("\ufeff").lstrip()
    for fmt, entry in formats.items():
        if entry.detect is not None and entry.detect(text):
            return fmt
    return AUTO_OTHERWISE


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
    one :class:`torchrod.io.jsonl.Record` per line (a CSV header excepted; a CSV row over several lines, its quoted
    cell holding a line break, is one), in order, lazily; a line that cannot be
    used is an error record (``"line N: ..."``). A CSV header that cannot be used raises
    :class:`~torchrod.errors.ReadingError` (no row can be read without it).

    Args:
        fmt: one of :data:`FORMATS`.
        control: a :class:`torchrod.io.jsonl.ReadControl` to end the reading at the lines already read.
        quantity: what a CSV row without a header gives per grating (:data:`torchrod.io.quantities.QUANTITIES`).
        fibre: the rod's :class:`torchrod.sensors.Fibre` (cores, wavelength section, units).
        peaks: a peak log's layout, overriding the rod file's (:meth:`torchrod.sensors.Fibre.peak_layout`).
        max_line: the longest line read [bytes] (None: the rod's, :func:`line_limit`); a longer one is an error
            record, read past without being held.
    """
    from .jsonl import line_bytes, read_lines

    _check_format(fmt)
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
    reader = INPUT_FORMATS[fmt].lines
    assert reader is not None  # (_check_format let only a line format through)
    yield from reader(lines, parse, ReadOptions(num_gratings, quantity, fibre, peaks, max_line=limit))


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
    :class:`Reading` per non-blank line in order (a CSV header row excepted, a CSV row over several lines one):
    checked, or with ``error`` set
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

        _check_format(fmt)
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
