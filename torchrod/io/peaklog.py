"""Peak logs: the text files an FBG interrogator's logging program writes, one sample a line.

A line is ``TIME: l_1, l_2, ..., l_N``: a time stamp, a colon, then N peak wavelengths separated by commas (or by
spaces when the line holds no comma), in the readings' wavelength unit (nm unless ``--wavelength-unit pm`` or the
rod file's ``fibre.wavelength_unit`` says otherwise). Such logs come from Hyperion/si155-class interrogators, whose
peaks are listed channel after channel, each channel's peaks in order of wavelength.

Time stamps (they become the reading's ``t`` [s]; the reading has no ``id``):

* ``HH-MM-SS.ffffff`` or ``HH:MM:SS.ffffff``: seconds since midnight; a step back of more than 12 h from the
  previous line is taken as midnight passing (a day is added);
* either of these after a date ``YYYY-MM-DD`` (and a space, ``T`` or ``_``): seconds since midnight of the first
  line's date;
* a plain number: seconds, as given.

Which peak is which: the N values map onto (grating, core) by the rod file's ``fibre.wavelength.peaks`` or the
option ``--peaks``: ``by-core`` (the default: core 1's G gratings in the rod's order, then core 2's, ...: one
interrogator channel per core), ``by-grating`` (grating 1's C cores, then grating 2's, ...), or an explicit list of
N entries ``[grating, core]`` (1-based) or null for a peak that belongs to no grating (a temperature reference,
say). N must match the layout: a line with another count is an error line (a peak that was not detected shifts
all those after it, so its neighbours cannot be placed either), and the next lines go on. An empty value (two
commas in a row, or nothing after the last comma of N values) is a peak that was not detected: its grating is
missing from that reading. One comma after all N values ends the line (some loggers write it) and is read past.

Each line becomes the reading ``{"t": ..., "wavelength": [[l_1, ..., l_C] or null, ...]}``, checked by the one
reading parser (:mod:`torchrod.io.reading`): the rod's reference is subtracted and the conversion of
:mod:`torchrod.sensors` applied.
"""

from __future__ import annotations

import datetime
import re
from collections.abc import Callable, Iterable, Iterator
from typing import Any, cast

from ..errors import OptionsError, ReadingError
from .numbers import csv_number
from .values import quote

__all__ = ["PeakLog", "is_peak_line", "parse_peaks_option", "peak_time"]

_TIME = re.compile(
    r"(?:(?P<y>[0-9]{4})-(?P<mo>[0-9]{2})-(?P<d>[0-9]{2})[ T_])?"
    r"(?P<h>[0-9]{1,2})[-:](?P<mi>[0-9]{2})[-:](?P<s>[0-9]{2}(?:\.[0-9]*)?)"
)
_SECONDS = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_FIRST_VALUE = re.compile(r"\s*[+-]?(?:[0-9]|\.[0-9])")
_DAY = 86400.0


def _split(text: str) -> tuple[str, str] | None:
    """(time, values) of a peak log line: split at its last colon; None when it has none or a comma before it."""
    head, colon, tail = text.rpartition(":")
    if not colon or "," in head or not head.strip():
        return None
    return head.strip(), tail


def is_peak_line(text: str) -> bool:
    """Whether ``text`` looks like a peak log line (a time stamp, a colon, a number): the test of ``--format
    auto``."""
    parts = _split(text.strip())
    if parts is None:
        return False
    head, tail = parts
    return bool((_TIME.fullmatch(head) or _SECONDS.fullmatch(head)) and _FIRST_VALUE.match(tail))


def peak_time(text: str) -> tuple[float, datetime.date | None, bool]:
    """A time stamp as (seconds, its date or None, whether it is a time of day); ``ValueError`` naming it."""
    match = _TIME.fullmatch(text)
    if match is not None:
        h, mi, s = int(match["h"]), int(match["mi"]), float(match["s"])
        if h > 23 or mi > 59 or s >= 61.0:
            raise ReadingError(f"time stamp {quote(text)} is not a time of day (HH-MM-SS.ffffff)")
        date = None
        if match["y"] is not None:
            try:
                date = datetime.date(int(match["y"]), int(match["mo"]), int(match["d"]))
            except ValueError:
                raise ReadingError(f"time stamp {quote(text)} holds no valid date (YYYY-MM-DD)") from None
        return 3600.0 * h + 60.0 * mi + s, date, True
    if _SECONDS.fullmatch(text):
        return cast(float, csv_number(text, "the time stamp")), None, False  # a number: not an empty cell
    raise ReadingError(
        f"time stamp {quote(text)} is not HH-MM-SS.ffffff, HH:MM:SS.ffffff (optionally after YYYY-MM-DD) or a number "
        "of seconds"
    )


def parse_peaks_option(text: str) -> Any:
    """``--peaks``: ``by-core``, ``by-grating``, or a comma-separated list of ``GRATING:CORE`` (1-based) and ``-``
    for a peak that is not read -> the form :meth:`torchrod.sensors.Fibre.peak_layout` takes (0-based pairs);
    :class:`~torchrod.errors.OptionsError` naming the bad entry."""
    from ..sensors import PEAK_ORDERS

    spec = text.strip()
    if spec in PEAK_ORDERS:
        return spec
    out: list[Any] = []
    for k, item in enumerate(spec.split(",")):
        item = item.strip()
        if item in ("-", "null"):
            out.append(None)
            continue
        match = re.fullmatch(r"([0-9]+):([0-9]+)", item)
        if match is None or int(match[1]) < 1 or int(match[2]) < 1:
            raise OptionsError(
                f"--peaks entry {k + 1} is {item!r}: give {' or '.join(PEAK_ORDERS)}, or per peak GRATING:CORE "
                "(1-based) or - for a peak that is not read, separated by commas"
            )
        out.append((int(match[1]) - 1, int(match[2]) - 1))
    return tuple(out)


class PeakLog:
    """Reads the lines of one peak log (module docstring) into reading objects, keeping the day count across
    lines.

    Args:
        fibre: the rod's :class:`torchrod.sensors.Fibre` with its wavelength section.
        num_gratings: G.
        peaks: the layout, overriding the rod file's (:func:`parse_peaks_option`'s form).
    Raises:
        ReadingError: the rod has no wavelength section, or the layout does not fit it.
    """

    def __init__(self, fibre: Any, num_gratings: int, peaks: Any = None) -> None:
        if fibre is None or fibre.wavelength is None:
            raise ReadingError(
                'a peak log needs the rod file\'s "fibre": {"wavelength": {"reference": ..., ...}} section: the '
                "reference to subtract and the conversion to curvature (docs/sensors.md)"
            )
        try:
            self.layout = fibre.peak_layout(peaks)
        except ValueError as exc:
            raise OptionsError(str(exc)) from None
        self.G, self.C = num_gratings, fibre.num_cores
        order = peaks if isinstance(peaks, str) else fibre.wavelength.peaks if peaks is None else None
        self.described = f"{self.G} gratings x {self.C} cores, {order}" if isinstance(order, str) else "--peaks"
        self._first_date: datetime.date | None = None
        self._last: float | None = None  # the last time of day [s]
        self._days = 0

    def reading_object(self, text: str) -> dict[str, Any]:
        """One line as ``{"t", "wavelength"}``; ``ValueError`` naming what is wrong."""
        parts = _split(text.strip())
        if parts is None:
            raise ReadingError(f"not a peak log line (TIME: l1, l2, ...): {quote(text.strip())}")
        head, tail = parts
        t = self._time(head)
        tail = tail.strip()
        cells = tail.split(",") if "," in tail else tail.split()
        N = len(self.layout)
        if len(cells) == N + 1 and not cells[-1].strip():
            # one comma after the N values ends the line; an empty last of N values is an undetected last peak
            cells.pop()
        if len(cells) != N:
            raise ReadingError(
                f"{len(cells)} peaks, the layout ({self.described}) has {N}: a peak that was not detected shifts the "
                "others, so the line is left out (mark an undetected peak by an empty value to keep the others)"
            )
        rows: list[Any] = [[None] * self.C for _ in range(self.G)]
        for k, (cell, place) in enumerate(zip(cells, self.layout, strict=True)):
            value = csv_number(cell, f"peak {k + 1}")
            if place is not None:
                rows[place[0]][place[1]] = value
        wavelength = [None if any(v is None for v in row) else row for row in rows]
        return {"t": t, "wavelength": wavelength}

    def _time(self, head: str) -> float:
        seconds, date, of_day = peak_time(head)
        if not of_day:
            return seconds
        if date is not None:
            if self._first_date is None:
                self._first_date = date
            return (date - self._first_date).days * _DAY + seconds
        if self._last is not None and seconds < self._last - _DAY / 2:
            self._days += 1
        self._last = seconds
        return self._days * _DAY + seconds

    def records(self, lines: Iterable[tuple[int, str]], parse: Callable[[Any], Any]) -> Iterator[Any]:
        """One :class:`torchrod.io.jsonl.Record` per line: ``parse`` of its reading object, or its error."""
        from .jsonl import Overlong, Record, overlong_error, parsed_record

        for number, text in lines:
            if isinstance(text, Overlong):
                yield Record(number, None, None, overlong_error(number, text))
                continue
            try:
                obj = self.reading_object(text)
            except ValueError as exc:
                yield Record(number, None, None, f"line {number}: {exc}")
                continue
            yield parsed_record(number, obj, parse)
