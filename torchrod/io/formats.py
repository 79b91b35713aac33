"""The input formats in one table, :data:`INPUT_FORMATS`: what ``--format``, ``--protocol`` and ROS bags read.

Each entry is an :class:`InputFormat` of one of three kinds, and adding an interrogator's format is adding its entry
(with its reader, in its own module):

* a line format (:attr:`InputFormat.lines`): one reading a line of a file, standard input or a ``tcp://HOST:PORT``
  connection (:mod:`torchrod.io.sources` reads the lines); ``--format NAME`` chooses it, and ``--format auto`` finds
  it by the file's extension (:attr:`InputFormat.extensions`) or its first non-blank line
  (:attr:`InputFormat.detect`);
* a protocol (:attr:`InputFormat.protocol`): a framing of its own over a byte stream (a recording, standard input or
  a ``tcp://HOST:PORT`` server), which ``--protocol NAME`` chooses;
* a bag message type (:attr:`InputFormat.bag_type`): the messages of a ROS bag topic of that type are the readings
  (``--topic``, :class:`torchrod.io.rosbag.BagSource`).

The readers are imported when an entry is used, so that the table costs nothing to load.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

__all__ = [
    "AUTO_DEFAULT",
    "AUTO_OTHERWISE",
    "CURVATURE_ARRAY",
    "INPUT_FORMATS",
    "InputFormat",
    "ReadOptions",
    "bag_formats",
    "format_help",
    "line_formats",
    "protocol_help",
    "protocols",
    "topic_help",
]


@dataclass(frozen=True)
class ReadOptions:
    """What a reader needs to know of the rod and the options.

    Attributes:
        num_gratings: G, the rod's gratings.
        quantity: what a CSV row without a header gives per grating
            (:data:`torchrod.io.quantities.QUANTITIES`).
        fibre: the rod's :class:`torchrod.sensors.Fibre` (cores, wavelength section, units), or None.
        peaks: a peak log's layout, overriding the rod file's (:meth:`torchrod.sensors.Fibre.peak_layout`).
        unit: the curvature unit an option gave (``--curvature-unit``), for a protocol whose records say their own
            unit; None when no option gave one.
        max_line: the longest line (or CSV record) read [bytes]; None: the reader's default.
    """

    num_gratings: int
    quantity: str = "curvature"
    fibre: Any = None
    peaks: Any = None
    unit: str | None = None
    max_line: int | None = None


LineReader = Callable[[Iterable[tuple[int, str]], Callable[[Any], Any], ReadOptions], Iterator[Any]]
"""A line format's reader: the numbered lines (:func:`torchrod.io.jsonl.read_lines`), the parser of a reading
object and the options -> one :class:`torchrod.io.jsonl.Record` per line, lazily."""

ProtocolReader = Callable[[Any, ReadOptions], Any]
"""A protocol's reader: the source (a path, ``"-"`` or ``tcp://HOST:PORT``) and the options -> an iterable of
:class:`torchrod.io.reading.Reading` that a stream can halt (:class:`torchrod.io.sources.ReadingSource`'s
interface)."""

MessageReader = Callable[[Any, int, str], dict[str, Any]]
"""A bag message type's reader: the decoded message, G and the message's name in messages -> the reading's object
(its values; the bag gives ``id`` and ``t``); :class:`~torchrod.errors.ReadingError` with the whole message for a
message that cannot be used, any other exception for one that cannot be decoded."""


@dataclass(frozen=True)
class InputFormat:
    """One way readings come in (module docstring): exactly one of ``lines``, ``protocol`` and ``bag_type`` is set.

    Attributes:
        what: what it reads, in messages and help (``"shape-sensing records"``).
        detail: more about it for ``--help`` ('' for none).
        lines: a line format's reader.
        extensions: the file extensions ``--format auto`` reads as this line format (lower case, with the dot).
        detect: whether a first non-blank line (BOM and leading spaces dropped) is this line format's, for
            ``--format auto``; None: never by the first line.
        detect_help: how ``--format auto`` knows it by its first line, for ``--help``.
        protocol: a protocol's reader (``--protocol NAME``).
        bag_type: the ROS message type whose messages it reads (``std_msgs/msg/Float64MultiArray``).
        message: a bag message type's reader.
    """

    what: str
    detail: str = ""
    lines: LineReader | None = None
    extensions: tuple[str, ...] = ()
    detect: Callable[[str], bool] | None = None
    detect_help: str = ""
    protocol: ProtocolReader | None = None
    bag_type: str | None = None
    message: MessageReader | None = None

    def __post_init__(self) -> None:
        kinds = [self.lines is not None, self.protocol is not None, self.bag_type is not None]
        if sum(kinds) != 1 or (self.bag_type is not None) != (self.message is not None):
            raise TypeError(f"an input format is exactly one of a line format, a protocol or a bag type: {self.what}")


# ---------------------------------------------------------------------------------------------------- readers
def _jsonl_lines(lines: Iterable[tuple[int, str]], parse: Callable[[Any], Any], options: ReadOptions) -> Iterator[Any]:
    from .jsonl import parse_records

    return parse_records(lines, parse)


def _csv_lines(lines: Iterable[tuple[int, str]], parse: Callable[[Any], Any], options: ReadOptions) -> Iterator[Any]:
    from .csv_rows import csv_records

    return csv_records(lines, options.num_gratings, options.quantity, options.fibre, parse, options.max_line)


def _peak_lines(lines: Iterable[tuple[int, str]], parse: Callable[[Any], Any], options: ReadOptions) -> Iterator[Any]:
    from .peaklog import PeakLog

    return PeakLog(options.fibre, options.num_gratings, options.peaks).records(lines, parse)


def _json_head(text: str) -> bool:
    return text.startswith(("{", "["))


def _peak_head(text: str) -> bool:
    from .peaklog import is_peak_line

    return is_peak_line(text)


def _fbgs_source(source: Any, options: ReadOptions) -> Any:
    from .fbgs import FbgsSource

    return FbgsSource(source, options.num_gratings, unit=options.unit)


def _curvature_array(message: Any, num_gratings: int, where: str) -> dict[str, Any]:
    from .rosbag import curvature_array

    return curvature_array(message, num_gratings, where)


# ---------------------------------------------------------------------------------------------------- the table
CURVATURE_ARRAY = "std_msgs/msg/Float64MultiArray"
"""The ROS message type of a topic of curvature readings: 2G values ``ux_1, uy_1, ..., ux_G, uy_G`` [1/m]."""

INPUT_FORMATS: dict[str, InputFormat] = {
    "jsonl": InputFormat(
        "JSON lines",
        lines=_jsonl_lines,
        extensions=(".jsonl", ".json", ".ndjson"),
        detect=_json_head,
        detect_help="{ for JSON lines",
    ),
    "csv": InputFormat("CSV rows", lines=_csv_lines, extensions=(".csv",)),
    "peaks": InputFormat(
        "an interrogator's peak log", lines=_peak_lines, detect=_peak_head, detect_help="TIME: numbers for a peak log"
    ),
    "fbgs": InputFormat(
        "shape-sensing records",
        "length-prefixed records of curvature [1/cm] and bend angle per grating from shape-sensing software (a "
        "tcp://HOST:PORT server, a recording, or stdin)",
        protocol=_fbgs_source,
    ),
    "curvature-array": InputFormat(
        "curvature arrays",
        "2G values ux_1, uy_1, ..., ux_G, uy_G [1/m], NaN for both values of a missing grating",
        bag_type=CURVATURE_ARRAY,
        message=_curvature_array,
    ),
}
"""Every input format by its name (module docstring); the order is the one ``--help`` lists them in, and the one
``--format auto`` tries their first-line tests in."""

AUTO_DEFAULT = "jsonl"
"""What ``--format auto`` reads an input as when no line was read to decide by (nothing, or only overlong lines)."""

AUTO_OTHERWISE = "csv"
"""What ``--format auto`` reads an input as when neither its extension nor its first line names a format."""


def line_formats() -> dict[str, InputFormat]:
    """The line formats of :data:`INPUT_FORMATS` (``--format``), in its order."""
    return {name: f for name, f in INPUT_FORMATS.items() if f.lines is not None}


def protocols() -> dict[str, InputFormat]:
    """The protocols of :data:`INPUT_FORMATS` (``--protocol``), in its order."""
    return {name: f for name, f in INPUT_FORMATS.items() if f.protocol is not None}


def bag_formats() -> dict[str, InputFormat]:
    """The bag message types of :data:`INPUT_FORMATS`, by their ROS message type."""
    return {f.bag_type: f for f in INPUT_FORMATS.values() if f.bag_type is not None}


def format_help() -> str:
    """``--format``'s help, from the table."""
    names = ", ".join(f"{name} ({f.what})" for name, f in line_formats().items())
    extensions = "; ".join(", ".join(f.extensions) for f in line_formats().values() if f.extensions)
    heads = ", ".join(f.detect_help for f in line_formats().values() if f.detect is not None)
    return (
        f"input format: {names}, or auto (default): by the extension ({extensions}), else by the first line "
        f"({heads}, else {INPUT_FORMATS[AUTO_OTHERWISE].what})"
    )


def protocol_help() -> str:
    """``--protocol``'s help, from the table."""
    named = " or ".join(f"{name}: {f.detail}" for name, f in protocols().items())
    return f"lines (default: one reading a line, in --format) or {named}"


def topic_help() -> str:
    """What ``--topic`` reads, for its help: each bag message type of the table and its values."""
    return "; ".join(f"{kind}: {f.detail}" for kind, f in bag_formats().items())
