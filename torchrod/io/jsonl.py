"""JSON lines in and out, shared by the line-oriented commands (``simulate``, ``estimate``, ``stream``).

Every such command reads one JSON object per line and writes one JSON object per line, in the same order. A line
that cannot be used never stops the run: it becomes an error line ``{"id": ..., "error": "line N: ..."}`` (the id
when the line had a readable one, else null) and the command exits with status 1 at the end.

Reading::

    for record in read_records(path_or_dash, parse):   # lazy: fine for an endless stdin
        ...  # record.line, record.id, record.value (what parse returned) or record.error (a message)

``parse(obj)`` turns one decoded JSON object into what the command needs and raises ``ValueError`` (or
``TypeError``/``KeyError``) for a line it cannot use; the helpers :func:`get_number`, :func:`get_list`,
:func:`check_keys` and :func:`as_number` raise ``ValueError`` with messages that name the field and the bad value.
Non-finite numbers (``NaN``, ``Infinity`` and overflowing literals such as ``1e999``, which Python's json accepts)
are refused by the number helpers, so the id of such a line is still reported.

Batching: :func:`batched` groups any iterable into lists of at most ``size`` items, in order, so a command can run
one batched tensor call per chunk and still answer line by line.

Writing: :class:`LineWriter` writes compact-enough JSON, one object per line, flushed after each line so a pipe
sees every answer as soon as it is made; ``NaN``/``inf`` are refused (``ValueError``), since they are not JSON.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import IO, Any, Generic, TypeVar

__all__ = [
    "LineWriter",
    "Record",
    "as_number",
    "batched",
    "check_keys",
    "get_list",
    "get_number",
    "parse_records",
    "quiet_closed_pipe",
    "read_lines",
    "read_records",
]

T = TypeVar("T")


@dataclass(frozen=True)
class Record(Generic[T]):
    """One input line, read.

    Attributes:
        line: 1-based line number in the source (blank lines count but yield no record).
        id: the object's ``"id"`` (any JSON value) or None when absent or unreadable.
        value: what ``parse`` returned; None when the line could not be used.
        error: why the line could not be used (starts with ``"line N: "``); None when it could.
    """

    line: int
    id: Any
    value: T | None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def read_lines(source: str | os.PathLike | IO[str]) -> Iterator[tuple[int, str]]:
    """Non-blank lines of ``source`` with their 1-based numbers, lazily.

    ``source`` is a path, ``"-"`` for standard input (looked up when reading starts, so tests may replace it), or an
    open text stream (not closed here). A path is opened as UTF-8 (undecodable bytes become U+FFFD, so they fail as
    bad JSON on their own line instead of ending the run) and closed when the iterator is exhausted or closed.
    Raises FileNotFoundError for a missing path when iteration starts.
    """
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) == "-":
        yield from _numbered(sys.stdin)
    elif isinstance(source, (str, os.PathLike)):
        with open(source, encoding="utf-8", errors="replace") as fh:
            yield from _numbered(fh)
    else:
        yield from _numbered(source)


def _numbered(stream: IO[str]) -> Iterator[tuple[int, str]]:
    # readline() rather than iteration: a pipe's lines come through as soon as they arrive.
    for number, text in enumerate(iter(stream.readline, ""), start=1):
        if text.strip():
            yield number, text


def parse_records(
    lines: Iterable[tuple[int, str]], parse: Callable[[dict[str, Any]], T]
) -> Iterator[Record[T]]:
    """Decode each (number, text) line as a JSON object and apply ``parse``; failures become error records.

    ``ValueError``, ``TypeError`` and ``KeyError`` raised by ``parse`` are caught and turned into the record's
    error; any other exception is a bug and propagates.
    """
    for number, text in lines:
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as exc:
            yield Record(
                number, None, None, f"line {number}: not valid JSON ({exc.msg} at column {exc.colno})"
            )
            continue
        except RecursionError:
            yield Record(number, None, None, f"line {number}: JSON nested too deeply")
            continue
        if not isinstance(obj, dict):
            yield Record(number, None, None, f"line {number}: expected a JSON object, got {_json_type(obj)}")
            continue
        ident = obj.get("id")
        try:
            value = parse(obj)
        except KeyError as exc:
            key = exc.args[0] if exc.args else "?"
            yield Record(number, ident, None, f"line {number}: missing key {key!r}")
        except (ValueError, TypeError) as exc:
            yield Record(number, ident, None, f"line {number}: {exc}")
        else:
            yield Record(number, ident, value)


def read_records(
    source: str | os.PathLike | IO[str], parse: Callable[[dict[str, Any]], T]
) -> Iterator[Record[T]]:
    """:func:`read_lines` then :func:`parse_records`: one :class:`Record` per non-blank line, in order, lazily."""
    return parse_records(read_lines(source), parse)


def batched(items: Iterable[T], size: int) -> Iterator[list[T]]:
    """Consecutive lists of at most ``size`` items, in order (the last may be shorter); lazy."""
    if not isinstance(size, int) or size < 1:
        raise ValueError(f"batch size must be an integer >= 1, got {size!r}")
    chunk: list[T] = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class LineWriter:
    """Writes one JSON object per line and flushes; counts the lines and the error lines.

    Args:
        stream: a text stream; None means ``sys.stdout`` as it is at each write (so redirections and pytest's
            capsys are honoured).
    """

    def __init__(self, stream: IO[str] | None = None) -> None:
        self._stream = stream
        self.lines = 0
        self.errors = 0

    @property
    def stream(self) -> IO[str]:
        return self._stream if self._stream is not None else sys.stdout

    def write(self, obj: Mapping[str, Any]) -> None:
        """One line; raises ``ValueError`` if ``obj`` holds NaN or infinity (not JSON) and writes nothing then.

        ``BrokenPipeError`` (the reader went away, as with ``| head``) propagates after :func:`quiet_closed_pipe`;
        a command stops on it (exit status 141, as for SIGPIPE).
        """
        text = json.dumps(obj, allow_nan=False)
        out = self.stream
        try:
            out.write(text + "\n")
            out.flush()
        except BrokenPipeError:
            quiet_closed_pipe(out)
            raise
        self.lines += 1

    def error(self, ident: Any, message: str) -> None:
        """The error line ``{"id": ident, "error": message}``."""
        self.write({"id": ident, "error": message})
        self.errors += 1

    def record_error(self, record: Record[Any]) -> None:
        """The error line of a record that could not be read."""
        self.error(record.id, record.error or "unknown error")


def quiet_closed_pipe(stream: IO[str]) -> None:
    """Point ``stream``'s file descriptor at the null device, so that nothing written after its reader went away
    (the interpreter's final flush included) raises ``BrokenPipeError`` again. Streams without one are left alone."""
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


# ---------------------------------------------------------------------------------------------- field helpers
def _json_type(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _brief(value: Any, limit: int = 60) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_number(value: Any, what: str) -> float:
    """``value`` as a finite float; ``what`` names it in the error (booleans and strings are refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what} must be a number, got {_json_type(value)} {_brief(value)}")  # noqa: TRY004 (bad data, one kind of error)
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {x}")
    return x


def get_number(obj: Mapping[str, Any], key: str, where: str = "") -> float:
    """``obj[key]`` as a finite float. ``where`` prefixes the field name in errors, e.g. ``"forces[2]"``."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        raise ValueError(f"missing {name!r}")
    return as_number(obj[key], name)


def get_list(obj: Mapping[str, Any], key: str, where: str = "") -> list[Any]:
    """``obj[key]``, which must be a JSON array."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        raise ValueError(f"missing {name!r}")
    value = obj[key]
    if not isinstance(value, list):
        raise ValueError(f"{name} must be an array, got {_json_type(value)} {_brief(value)}")  # noqa: TRY004 (bad data, one kind of error)
    return value


def check_keys(
    obj: Any, required: Sequence[str], optional: Sequence[str] = (), where: str = "object"
) -> Mapping[str, Any]:
    """Check that ``obj`` is a JSON object holding every ``required`` key and no key outside required + optional.

    Returns ``obj``; raises ``ValueError`` naming ``where`` and the missing or unknown keys.
    """
    if not isinstance(obj, dict):
        raise ValueError(f"{where} must be an object, got {_json_type(obj)} {_brief(obj)}")  # noqa: TRY004 (bad data, one kind of error)
    missing = [k for k in required if k not in obj]
    if missing:
        raise ValueError(f"{where} is missing {', '.join(repr(k) for k in missing)}")
    allowed = set(required) | set(optional)
    unknown = sorted(k for k in obj if k not in allowed)
    if unknown:
        raise ValueError(
            f"{where} has unknown key(s) {', '.join(repr(k) for k in unknown)}; "
            f"expected {', '.join(repr(k) for k in (*required, *optional))}"
        )
    return obj
