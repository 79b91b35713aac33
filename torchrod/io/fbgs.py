"""Shape-sensing streams: length-prefixed records of curvature and bend angle per grating (FBGS-style software).

``torchrod stream --input tcp://HOST:PORT --protocol fbgs`` connects to the shape-sensing program's TCP server; the
same parser reads such a stream recorded to a file (``--input RECORDING --protocol fbgs``) or piped to standard
input. The record, as the public drivers of these systems read it (what is assumed is said here):

Framing
    Each record is a 4-byte big-endian unsigned length L, then L bytes of ASCII text. A length of 0 or above
    :data:`MAX_RECORD_BYTES` means the stream is not in this framing (or out of step): it is reported once and the
    stream ends, since no later record boundary can be found.

Fields (tab-separated; a trailing CR/LF is dropped)
    1. date, 2. time (``HH:MM:SS.fff`` or ``HH-MM-SS.fff``: the reading's ``t``, seconds since midnight, a day
       added when it steps back by more than 12 h; another form leaves ``t`` out),
    3. the sample number (an integer: the reading's ``id``),
    4. the number of channels M, then per channel: its number, its grating count n, four status values, n peak
       wavelengths and n peak powers (skipped: the curvature below is what is read),
    5. per sensor a block opened by a label that starts with ``Curvature`` (for example ``Curvature [1/cm]``),
       then one curvature magnitude per grating, then a label (the bend angle's), then one bend angle [rad] per
       grating, then further labelled blocks (the reconstructed shape), which are skipped.

    The curvature's unit is taken from the label's brackets (``[1/cm]``, ``[1/m]``, ``[1/mm]``); without one it is
    the ``--curvature-unit`` given, else 1/cm (what these systems send). The count of values of a block is read up to
    the next label, so a record says itself how many gratings it holds; it must be the rod's G. The first sensor's
    block is read; a record holding several sensors reads the first. The bend angle is taken as measured from the
    body frame's d1 towards d2 (align the sensor's angle reference with d1 in the rod file's frame).

Each record becomes the reading ``{"id": sample, "t": time, "curvature_polar": [[kappa, phi], ...]}`` (kappa in
1/m), checked by the one reading parser (:mod:`torchrod.io.reading`). A record that cannot be used (another grating
count, a field that is not a number, no curvature block) is an error answer in its place and the stream goes on; a
record cut short by the end of the stream (the connection closed mid-record) is one error answer, after every
complete record before it. An error answer's ``id`` is the record's sample number when it could be read. A time
that is not a time of day (``25:00:00``, ``99:99:99``) and a curvature or bend angle that is not finite (``NaN``)
make the record an error, naming the field.
"""

from __future__ import annotations

import os
import re
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

from ..errors import ReadingError
from ..sensors import CURVATURE_UNITS
from .quantities import curvature_tensor, polar_curvature
from .reading import Reading, _checked
from .tcp import TcpReader, is_tcp
from .values import quote

__all__ = ["DEFAULT_UNIT", "MAX_RECORD_BYTES", "FbgsSource", "parse_record", "read_records"]

MAX_RECORD_BYTES = 16 * 2**20
"""The longest record accepted [bytes]: a longer announced length means the stream is not in this framing."""

DEFAULT_UNIT = "1/cm"
"""The curvature unit of a record whose label names none."""

_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)  # a value of a block, refused as not finite
_TIME = re.compile(r"([0-9]{1,2})[:-]([0-9]{2})[:-]([0-9]{2}(?:\.[0-9]*)?)")
_UNIT = re.compile(r"\[\s*(1/[a-z]+)\s*\]", re.IGNORECASE)


class RecordError(ReadingError):
    """A record that cannot be used; the stream goes on after it. ``sample``: its sample number when it was read
    (the error answer's ``id``), else None."""

    sample: Any = None


def _int_field(fields: list[str], k: int, what: str) -> int:
    if k >= len(fields):
        raise RecordError(f"the record ends before its {what} (field {k + 1})")
    text = fields[k].strip()
    if not re.fullmatch(r"[+-]?[0-9]{1,9}", text):
        raise RecordError(f"field {k + 1} ({what}) must be an integer, got {quote(text)}")
    return int(text)


def _block(fields: list[str], start: int, what: str) -> tuple[list[float], int]:
    """The numbers from field ``start`` up to the next field that is not one: (values, index of that field).
    ``NaN`` and infinities count as values of the block (so the count stays right) and are refused naming the
    grating (``what``: the block's name)."""
    values = []
    k = start
    while k < len(fields) and (_NUMBER.fullmatch(fields[k].strip()) or _NONFINITE.fullmatch(fields[k].strip())):
        if _NONFINITE.fullmatch(fields[k].strip()):
            raise RecordError(
                f"grating {k - start + 1}'s {what} (field {k + 1}) is {quote(fields[k].strip())}, not a finite number"
            )
        values.append(float(fields[k]))
        k += 1
    return values, k


def parse_record(
    payload: bytes, num_gratings: int, unit: str | None = None
) -> tuple[Any, float | None, list[list[float]]]:
    """One record's text -> (sample number, t [s] or None, per grating [kappa [1/m], phi [rad]]).

    ``unit``: the curvature unit when the label names none (default :data:`DEFAULT_UNIT`); a label that names
    another unit than a given ``unit`` is an error. Raises :class:`RecordError` naming what is wrong.
    """
    try:
        text = payload.decode("ascii")
    except UnicodeDecodeError as exc:
        raise RecordError(f"not ASCII text (byte {exc.start} is {payload[exc.start]:#04x})") from None
    fields = text.rstrip("\r\n").split("\t")
    if len(fields) < 4:
        raise RecordError(f"{len(fields)} tab-separated fields, expected date, time, sample number, channels, ...")
    sample = _int_field(fields, 2, "sample number")
    try:
        return sample, *_record_values(fields, num_gratings, unit)
    except RecordError as exc:
        exc.sample = sample
        raise


def _record_values(fields: list[str], num_gratings: int, unit: str | None) -> tuple[float | None, list[list[float]]]:
    """(t, pairs) of :func:`parse_record` from the fields after the sample number."""
    channels = _int_field(fields, 3, "channel count")
    if channels < 0:
        raise RecordError(f"field 4 (channel count) is {channels}")
    k = 4
    for m in range(channels):
        _int_field(fields, k, f"channel {m + 1}'s number")
        n = _int_field(fields, k + 1, f"channel {m + 1}'s grating count")
        if n < 0:
            raise RecordError(f"channel {m + 1}'s grating count is {n}")
        k += 6 + 2 * n
    if k > len(fields):
        raise RecordError("the record ends inside its channel data (the channels' counts announce more fields)")
    label_at = next((j for j in range(k, len(fields)) if fields[j].strip().lower().startswith("curvature")), None)
    if label_at is None:
        raise RecordError(
            "no curvature block (a field 'Curvature [1/cm]' followed by the values): is the shape-sensing "
            "program sending curvature?"
        )
    label = fields[label_at].strip()
    found = _UNIT.search(label)
    named = found.group(1).lower() if found else None
    if named is not None and named not in CURVATURE_UNITS:
        raise RecordError(
            f"the label {quote(label)} names a unit torchrod does not know ({', '.join(CURVATURE_UNITS)})"
        )
    if named is not None and unit is not None and named != unit:
        raise RecordError(f"the label {quote(label)} says {named}, but the curvature unit was given as {unit}")
    scale = CURVATURE_UNITS[named or unit or DEFAULT_UNIT]
    kappa, end = _block(fields, label_at + 1, "curvature")
    if end >= len(fields):
        raise RecordError("the record ends after the curvature values, before the bend angles")
    phi, _ = _block(fields, end + 1, "bend angle")
    if len(kappa) != len(phi):
        raise RecordError(f"{len(kappa)} curvature values but {len(phi)} bend angles")
    if len(kappa) != num_gratings:
        raise RecordError(f"{len(kappa)} gratings, the rod has {num_gratings}: is this the rod's sensor?")
    t = None
    time = _TIME.fullmatch(fields[1].strip())
    if time is not None:
        h, mi, s = int(time[1]), int(time[2]), float(time[3])
        if h > 23 or mi > 59 or s >= 61.0:  # (61: a leap second)
            raise RecordError(f"field 2 (time) {quote(fields[1].strip())} is not a time of day (HH:MM:SS.fff)")
        t = 3600.0 * h + 60.0 * mi + s
    return t, [[x * scale, p] for x, p in zip(kappa, phi, strict=True)]


def _reading(sample: Any, t: float | None, pairs: list[list[float]], G: int) -> Reading:
    """A record's values as a checked reading (the polar rules of :mod:`torchrod.io.quantities`: kappa >= 0, bounds)."""
    return _checked(Reading(sample, curvature_tensor(polar_curvature(pairs, G), G), t))


def read_records(read: Callable[[int], bytes | None], num_gratings: int, unit: str | None = None) -> Iterator[Reading]:
    """The readings of a byte stream of records (module docstring): ``read(n)`` gives up to ``n`` bytes, ``b""`` at
    the end, None when the reading is to stop (a flush: a partial record is then dropped). One :class:`Reading` per
    record, in order; an error reading, ``"record N: ..."`` (N 1-based), for a record that cannot be used."""
    buf = bytearray()
    number = 0
    days, last = 0, None
    while True:
        number += 1
        if _fill(read, buf, 4) is None:
            return
        if len(buf) < 4:
            if buf:
                yield Reading(error=f"record {number}: truncated: the stream ended inside its 4-byte length")
            return
        size = int.from_bytes(buf[:4], "big")
        if not 0 < size <= MAX_RECORD_BYTES:
            yield Reading(
                error=f"record {number}: announces {size} bytes (the limit is {MAX_RECORD_BYTES}): the stream is not "
                "4-byte big-endian length-prefixed records, or is out of step; reading stops here",
            )
            return
        if _fill(read, buf, 4 + size) is None:
            return
        if len(buf) < 4 + size:
            yield Reading(
                error=f"record {number}: truncated: {size} bytes announced, {len(buf) - 4} received before the stream "
                "ended",
            )
            return
        payload = bytes(buf[4 : 4 + size])
        del buf[: 4 + size]
        sample = None
        try:
            sample, t, pairs = parse_record(payload, num_gratings, unit)
            if t is not None:
                if last is not None and t < last - 43200.0:
                    days += 1
                last = t
                t += 86400.0 * days
            yield _reading(sample, t, pairs, num_gratings)
        except ValueError as exc:
            # the sample number names the record's error answer when it was read (the record's id)
            yield Reading(getattr(exc, "sample", None) if sample is None else sample, error=f"record {number}: {exc}")


def _fill(read: Callable[[int], bytes | None], buf: bytearray, size: int) -> bool | None:
    """Read into ``buf`` until it holds ``size`` bytes or the stream ends (True), or None when ``read`` says stop."""
    while len(buf) < size:
        data = read(min(2**16, size - len(buf)))
        if data is None:
            return None
        if not data:
            return True
        buf += data
    return True


class FbgsSource:
    """The readings of an FBGS-style record stream from ``source``: ``tcp://HOST:PORT``, a recorded file, or ``"-"``
    (standard input), as an iterable the stream can halt (:class:`torchrod.io.sources.ReadingSource`'s interface:
    :meth:`halt`, :attr:`waiting`). ``unit``: the curvature unit of records whose label names none.
    Opening a TCP source that cannot be reached raises :class:`~torchrod.errors.OptionsError`."""

    def __init__(self, source: Any, num_gratings: int, unit: str | None = None) -> None:
        self.source, self.G, self.unit = source, num_gratings, unit
        self._halted = threading.Event()
        self._waiting = threading.Event()

    def __iter__(self) -> Iterator[Reading]:
        source = self.source
        if is_tcp(source):
            with TcpReader(str(source), self._halted) as conn:
                yield from read_records(self._watched(conn.read), self.G, self.unit)
        elif source == "-":
            fd = sys.stdin.fileno()
            yield from read_records(self._watched(lambda n: os.read(fd, n)), self.G, self.unit)
        else:
            with open(source, "rb", buffering=0) as fh:
                yield from read_records(self._watched(fh.read), self.G, self.unit)

    def _watched(self, read: Callable[[int], bytes | None]) -> Callable[[int], bytes | None]:
        def watched(n: int) -> bytes | None:
            if self._halted.is_set():
                return None
            self._waiting.set()
            try:
                return read(n)
            finally:
                self._waiting.clear()

        return watched

    def halt(self) -> None:
        self._halted.set()

    @property
    def waiting(self) -> bool:
        return self._waiting.is_set()
