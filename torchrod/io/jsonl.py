"""JSON lines in and out, shared by the line-oriented commands (``simulate``, ``estimate``, ``stream``).

Every such command reads one JSON object per line and writes one JSON object per line, in the same order, whatever
a line holds. A line that cannot be used never stops the run: it becomes an error line ``{"id": ..., "error": "line
N: ..."}`` (the id when the line had one JSON can echo, else null) and the command exits with status 1 at the end.
Blank lines (only whitespace) are skipped; they still count in the line numbers.

Reading::

    for record in read_records(path_or_dash, parse):   # lazy: fine for an endless stdin
        ...  # record.line, record.id, record.value (what parse returned) or record.error (a message)

A line is what ends with ``\\n``; it is decoded as UTF-8 (undecodable bytes become U+FFFD and fail as bad JSON on
their own line; a byte-order mark on the first line is dropped); a line longer than the reader's limit
(``max_line``, by default :data:`MAX_LINE_BYTES`; readings are read with their rod's,
:func:`torchrod.io.sources.line_limit`) is an error line and is skipped without being held in memory (only its first
:data:`OVERLONG_HEAD` characters are kept, to name the line by its id when it starts with one: :func:`overlong_id`).
JSON is decoded by :func:`decode`: Python's decoder, except that an integer of more than 4300 digits becomes a
:class:`~torchrod.io.values.HugeInteger` (refused by the number rules, naming its field) instead of aborting the
decoding, and nesting too deep for the decoder is an error of its line. ``NaN``, ``Infinity`` and overflowing
literals (``1e999``) decode as non-finite floats and are refused by the number rules of :mod:`torchrod.io.numbers`,
so the line's id is still reported. An id that JSON cannot echo (:func:`torchrod.io.reading.id_problem`) makes the
line an error with id null.

``parse(obj)`` turns one decoded JSON object into what the command needs and raises ``ValueError`` (or
``TypeError``/``KeyError``) for a line it cannot use; the helpers :func:`get_number`, :func:`get_list`,
:func:`check_keys` and :func:`as_number` raise ``ValueError`` with messages that name the field and quote at most
about 100 characters of the bad value.

Batching: :func:`batched` groups any iterable into lists of at most ``size`` items, in order, so a command can run
one batched tensor call per chunk and still answer line by line.

Writing: :class:`LineWriter` writes JSON, one object per line, flushed after each line so a pipe sees every answer
as soon as it is made. :meth:`LineWriter.write` refuses ``NaN``/``inf`` (``ValueError``: not JSON);
:meth:`LineWriter.answer` writes an error line in place of an answer JSON cannot hold, so one line always comes out.

Ending: :func:`open_output` opens ``--out``; :func:`sigterm_as_interrupt` makes SIGTERM raise :class:`Terminated`
(a ``KeyboardInterrupt``) so that a command flushes on it as on Ctrl-C; :func:`interrupt_status` gives 130 or 143;
a :class:`ReadControl` ends :func:`read_lines` at the lines it already read, for that flush.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import signal
import stat
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import IO, Any, Generic, TypeVar

from ..errors import MissingFileError, OptionsError, ReadingError
from .numbers import as_number
from .reading import check_id, id_problem
from .tcp import TcpReader, is_tcp
from .values import HugeInteger, describe, int_digit_limit, quote

__all__ = [
    "MAX_LINE_BYTES",
    "OVERLONG_HEAD",
    "ClosedOutput",
    "LineWriter",
    "ReadControl",
    "Record",
    "Terminated",
    "as_number",
    "batched",
    "check_input",
    "check_keys",
    "check_output",
    "decode",
    "get_list",
    "get_number",
    "interrupt_status",
    "open_output",
    "overlong_id",
    "parse_records",
    "parsed_record",
    "quiet_closed_pipe",
    "read_lines",
    "read_records",
    "same_path",
    "sigterm_as_interrupt",
]

T = TypeVar("T")

Inputs = Sequence[str] | Mapping[str, str | None]
"""The inputs an output must not overwrite: paths, or what each is mapped to its path."""

STDIN_CLOSED = "standard input is closed: give the input as a file path instead of '-', or pipe it in"
STDOUT_CLOSED = (
    "standard output is closed (started with >&-): give --out FILE where the command takes one, or run it with "
    "standard output open"
)

MAX_LINE_BYTES = 16 * 2**20
"""The longest input line a reader takes by default [bytes]; a longer one is an error line, read past in chunks
without being held. Decoding a line into Python objects costs up to about 20 times its size in memory (an array of
small numbers), so this bound also bounds what one line can cost. Readings are read with a much lower bound, their
rod's (:func:`torchrod.io.sources.line_limit`)."""

OVERLONG_HEAD = 4096
"""[characters] The start of a line over the limit that is kept (:attr:`Overlong.head`): room for ``{"id": `` and
an id of :data:`torchrod.io.reading.MAX_ID_CHARS` characters, escapes included, or a CSV row's first cell."""

MAX_MESSAGE_CHARS = 600
"""The longest error message written (messages quote at most ~100 characters of a value; this is a safety net)."""


@dataclass(frozen=True)
class Record(Generic[T]):
    """One input line, read.

    Attributes:
        line: 1-based line number in the source (blank lines count but yield no record).
        id: the object's ``"id"`` (any JSON value JSON can echo) or None when absent or unusable.
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


class Overlong(str):
    """Stands for an input line longer than ``limit`` [bytes], the reader's: its text is not kept, only its first
    :data:`OVERLONG_HEAD` characters, :attr:`head`."""

    limit: int
    head: str

    def __new__(cls, limit: int, head: str = "") -> Overlong:
        self = super().__new__(cls, "")
        self.limit = limit
        self.head = head
        return self


def overlong_error(number: int, text: Overlong) -> str:
    """The error of input line ``number`` when it is the :class:`Overlong` ``text`` (in every format)."""
    return f"line {number}: longer than {text.limit} bytes; not read"


_ID_KEY = re.compile(r'\s*\{\s*"id"\s*:\s*')
_AFTER_VALUE = re.compile(r"\s*[,}]")


def overlong_id(text: Overlong) -> Any:
    """The id of a JSON line too long to read, when the line opens with it (``{"id": ...,``) and the id ends within
    its :attr:`~Overlong.head`, and JSON can echo it (:func:`torchrod.io.reading.id_problem`); else None."""
    match = _ID_KEY.match(text.head)
    if match is None:
        return None
    try:
        ident, end = _DECODER.raw_decode(text.head, match.end())
    except (ValueError, RecursionError):
        return None
    if _AFTER_VALUE.match(text.head, end) is None:  # (a number cut short by the head's end is not the id)
        return None
    return ident if id_problem(ident) is None else None


def line_bytes(max_line: int | None) -> int:
    """The limit of a reader given ``max_line`` [bytes] (None: :data:`MAX_LINE_BYTES`); ``ValueError`` unless it is
    an integer >= 1."""
    if max_line is None:
        return MAX_LINE_BYTES
    if not isinstance(max_line, int) or isinstance(max_line, bool) or max_line < 1:
        raise OptionsError(f"the line limit must be an integer >= 1 [bytes], got {max_line!r}")
    return max_line


# ---------------------------------------------------------------------------------------------------- reading
class ReadControl:
    """Lets another thread end a line reader at the lines it already holds (the flush after an interrupt).

    After :meth:`halt`, :func:`read_lines` yields the complete lines already read from the file descriptor, then ends
    as at the end of the input instead of reading more. ``waiting`` is set while the reader waits on the input (it
    then holds no complete line).
    """

    def __init__(self) -> None:
        self.halted = threading.Event()
        self.waiting = threading.Event()

    def halt(self) -> None:
        self.halted.set()


def read_lines(
    source: str | os.PathLike | IO[str], control: ReadControl | None = None, max_line: int | None = None
) -> Iterator[tuple[int, str]]:
    """Non-blank lines of ``source`` with their 1-based numbers, lazily.

    ``source`` is a path, ``"-"`` for standard input (looked up when reading starts, so tests may replace it),
    ``tcp://HOST:PORT`` (a server that sends the lines, :mod:`torchrod.io.tcp`), or an open text stream (not closed
    here). Paths and standard input are read as bytes from the file descriptor (no
    buffer lock is held while waiting, so a reader thread blocked on a pipe never hangs the interpreter's exit) and
    decoded line by line as UTF-8 (module docstring); a path is closed when the iterator is exhausted or closed.
    Raises FileNotFoundError for a missing path when iteration starts. A line over ``max_line`` bytes (None:
    :data:`MAX_LINE_BYTES`; characters for a text stream) comes as an :class:`Overlong`, read past in chunks: the
    reader never holds more than about ``max_line`` + 64 KiB of input. ``control`` (:class:`ReadControl`) lets
    another thread end the reading early.
    """
    limit = line_bytes(max_line)
    control = control if control is not None else ReadControl()
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) == "-":
        stdin = sys.stdin
        if stdin is None:  # the process was started with its standard input closed (`<&-`)
            raise OptionsError(STDIN_CLOSED)
        try:
            fd = stdin.fileno()
        except (AttributeError, OSError, ValueError):  # a replaced stdin (tests): a text stream
            yield from _numbered(stdin, control, limit)
        else:
            yield from _numbered_bytes(lambda n: os.read(fd, n), control, limit)
    elif is_tcp(source):
        with TcpReader(str(source), control.halted) as conn:
            yield from _numbered_bytes(conn.read, control, limit)
    elif isinstance(source, (str, os.PathLike)):
        if control.halted.is_set():
            return
        # Opening a named pipe waits for its writer: that wait counts as waiting on the input, so that a flush after
        # an interrupt (ReadControl.halt) need not wait for a writer that may never come.
        control.waiting.set()
        try:
            fh = open(source, "rb", buffering=0)  # noqa: SIM115 - closed below
        finally:
            control.waiting.clear()
        with fh:
            yield from _numbered_bytes(fh.read, control, limit)
    else:
        yield from _numbered(source, control, limit)


def _numbered(stream: IO[str], control: ReadControl, limit: int, chunk: int = 2**16) -> Iterator[tuple[int, str]]:
    # readline() rather than iteration: a pipe's lines come through as soon as they arrive. At most limit + 1
    # characters are taken at once: a longer line is an Overlong, the rest of it read past in chunks.
    number = 0
    while not control.halted.is_set():
        control.waiting.set()
        try:
            text = stream.readline(limit + 1)
            overlong = len(text) > limit
            head = text[:OVERLONG_HEAD] if overlong else ""
            while overlong and text and not text.endswith("\n"):
                text = stream.readline(chunk)
        finally:
            control.waiting.clear()
        if overlong:
            number += 1
            yield number, Overlong(limit, head)
            continue
        if not text:
            return
        number += 1
        if text.strip():
            yield number, text


class _Cut(bytes):
    """The first bytes of a line over the limit (:func:`_raw_lines`), the rest of it dropped."""


def _raw_lines(
    read: Callable[[int], bytes | None], control: ReadControl, limit: int, chunk: int = 2**16
) -> Iterator[bytes]:
    """Lines (with their newline) from an unbuffered ``read``, as soon as each is complete; for a line over
    ``limit`` bytes a :class:`_Cut` of its first :data:`OVERLONG_HEAD` bytes (the rest dropped as it is read, so
    memory stays bounded). Once ``control`` is halted, ends when the complete lines in memory are out (a partial
    line is dropped); a ``read`` that returns None (it saw the halt while waiting) ends it the same way."""
    buf = bytearray()
    pos = 0  # start of the current line in buf
    scanned = 0  # buf[pos:scanned] holds no newline
    overlong = False
    head = b""  # the start of an overlong line
    while True:
        nl = buf.find(b"\n", scanned)
        if nl >= 0:
            if overlong:
                yield _Cut(head)
            elif nl + 1 - pos > limit:
                yield _Cut(buf[pos : min(nl + 1, pos + OVERLONG_HEAD)])
            else:
                yield bytes(memoryview(buf)[pos : nl + 1])  # (a memoryview slice: one copy of the line, not two)
            overlong = False
            pos = scanned = nl + 1
            continue
        del buf[:pos]
        pos, scanned = 0, len(buf)
        if len(buf) > limit:
            if not overlong:
                head = bytes(buf[:OVERLONG_HEAD])
            overlong = True
            buf.clear()
            scanned = 0
        if control.halted.is_set():
            return
        control.waiting.set()
        try:
            data = read(chunk)
        finally:
            control.waiting.clear()
        if data is None:
            return
        if not data:
            if overlong:
                yield _Cut(head)
            elif buf:
                yield bytes(buf)
            return
        buf += data


def _numbered_bytes(read: Callable[[int], bytes | None], control: ReadControl, limit: int) -> Iterator[tuple[int, str]]:
    for number, raw in enumerate(_raw_lines(read, control, limit), start=1):
        if isinstance(raw, _Cut):
            head = raw.decode("utf-8", errors="replace")
            yield number, Overlong(limit, head[1:] if number == 1 and head.startswith("\ufeff") else head)
            continue
        text = raw.decode("utf-8", errors="replace")
        if number == 1 and text.startswith("\ufeff"):
            text = text[1:]
        if text.strip():
            yield number, text


def _parse_int(text: str) -> int | HugeInteger:
    limit = int_digit_limit()
    if limit and len(text) - text.startswith("-") > limit:
        return HugeInteger(text)
    return int(text)


_DECODER = json.JSONDecoder(parse_int=_parse_int)  # one for every line: json.loads with an option makes one per call


def decode(text: str) -> Any:
    """One JSON value from ``text`` (module docstring); ``ValueError`` with a short message when it is not JSON."""
    try:
        if text.startswith("\ufeff"):  # refused as json.loads refuses it, with its message
            return json.loads(text, parse_int=_parse_int)
        return _DECODER.decode(text)
    except json.JSONDecodeError as exc:
        raise ReadingError(f"not valid JSON ({exc.msg} at column {exc.colno})") from None
    except RecursionError:
        raise ReadingError("not usable JSON: nested too deeply") from None
    except ValueError as exc:  # pragma: no cover - the decoder's other refusals
        raise ReadingError(f"not valid JSON ({_clip(str(exc))})") from None


def _key(key: Any) -> str:
    """A key for a message: its repr when short, else its quote."""
    return repr(key) if isinstance(key, str) and len(key) <= 40 else quote(key, 40)


def _clip(message: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    return message if len(message) <= limit else message[:limit] + f"... ({len(message)} characters)"


def parse_records(lines: Iterable[tuple[int, str]], parse: Callable[[dict[str, Any]], T]) -> Iterator[Record[T]]:
    """Decode each (number, text) line as a JSON object and apply ``parse``; failures become error records.

    One record per line, in order. ``ValueError``, ``TypeError``, ``KeyError``, ``OverflowError`` and
    ``RecursionError`` raised by ``parse`` are caught and turned into the record's error; any other exception is a
    bug and propagates.
    """
    for number, text in lines:
        yield _record(number, text, parse)


def _record(number: int, text: str, parse: Callable[[dict[str, Any]], T]) -> Record[T]:
    at = f"line {number}: "
    if isinstance(text, Overlong):
        return Record(number, overlong_id(text), None, overlong_error(number, text))
    try:
        obj = decode(text)
    except ValueError as exc:
        return Record(number, None, None, at + str(exc))
    if not isinstance(obj, dict):
        return Record(number, None, None, f"{at}expected a JSON object, got {describe(obj)}")
    return parsed_record(number, obj, parse)


def parsed_record(number: int, obj: Mapping[str, Any], parse: Callable[[Any], T]) -> Record[T]:
    """The :class:`Record` of line ``number`` whose reading object (a decoded JSON object, or one a CSV row or peak
    log line was made into) is ``obj``: ``parse(obj)``, or the error it raised (the exceptions
    :func:`parse_records` catches), with ``obj``'s id when JSON can echo it."""
    at = f"line {number}: "
    ident = obj.get("id")
    try:
        check_id(ident)
    except ValueError as exc:
        return Record(number, None, None, at + str(exc))
    try:
        value = parse(obj)
    except KeyError as exc:
        key = exc.args[0] if exc.args else "?"
        return Record(number, ident, None, f"{at}missing key {_key(key)}")
    except RecursionError:
        return Record(number, ident, None, f"{at}a value is nested too deeply")
    except (ValueError, TypeError, OverflowError) as exc:
        return Record(number, ident, None, at + _clip(str(exc)))
    return Record(number, ident, value)


def read_records(source: str | os.PathLike | IO[str], parse: Callable[[dict[str, Any]], T]) -> Iterator[Record[T]]:
    """:func:`read_lines` then :func:`parse_records`: one :class:`Record` per non-blank line, in order, lazily."""
    return parse_records(read_lines(source), parse)


def check_input(path: str, what: str) -> None:
    """An error naming ``what`` when ``path`` cannot be read (``"-"``: standard input closed), before any output is
    made: :class:`~torchrod.errors.MissingFileError` when it does not exist, :class:`~torchrod.errors.OptionsError`
    (a ``ValueError``) for a folder, a socket or no permission. A TCP address (``tcp://HOST:PORT``) is checked for
    its form only: the connection opens when reading starts.

    The check looks at the file (``os.stat``) and never opens it: opening a named pipe to probe it and closing it
    again would take the writer's data, or end the writer with SIGPIPE. A named pipe or a character device (a
    serial port, ``/dev/stdin``) is read once, by the command."""
    if path == "-":
        if sys.stdin is None:
            raise OptionsError(STDIN_CLOSED)
        return
    if is_tcp(path):
        from .tcp import tcp_address

        tcp_address(path)
        return
    if not os.path.lexists(path):
        raise MissingFileError(f"{what} {path}: no such file (check the path)")
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise OptionsError(f"{what} {path}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(mode):
        raise OptionsError(f"{what} {path}: Is a directory (give a file)")
    if stat.S_ISSOCK(mode):
        raise OptionsError(
            f"{what} {path}: is a socket, which cannot be read as a file; connect to it and pipe the lines in "
            f"(e.g. socat UNIX-CONNECT:{path} - | torchrod ...)"
        )
    if not os.access(path, os.R_OK):
        raise OptionsError(f"{what} {path}: Permission denied")


def batched(items: Iterable[T], size: int) -> Iterator[list[T]]:
    """Consecutive lists of at most ``size`` items, in order (the last may be shorter); lazy."""
    if not isinstance(size, int) or size < 1:
        raise OptionsError(f"batch size must be an integer >= 1, got {size!r}")
    chunk: list[T] = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


# ---------------------------------------------------------------------------------------------------- writing
_ENCODER = json.JSONEncoder(allow_nan=False)
"""``json.dumps(obj, allow_nan=False)``'s encoder, made once (``dumps`` with an option makes one per call)."""


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
        self._emit(json.dumps(obj, allow_nan=False))

    def _emit(self, text: str, flush: bool = True) -> None:
        out = self.stream
        try:
            out.write(text + "\n")
        except BrokenPipeError:
            quiet_closed_pipe(out)
            raise
        if flush:
            self.flush()
        self.lines += 1

    def flush(self) -> None:
        """Flush the lines written so far (see :meth:`answer`)."""
        try:
            self.stream.flush()
        except BrokenPipeError:
            quiet_closed_pipe(self.stream)
            raise

    def answer(self, obj: Mapping[str, Any], line: int | None = None, *, flush: bool = True) -> bool:
        """Write ``obj``; if JSON cannot hold it (NaN, an unwritable value), write an error line naming ``line`` in
        its place and count it as an error. Returns whether ``obj`` itself was written. ``flush`` False leaves the
        line in the stream's buffer, for answers that come together (a batch's): one flush after the last of them
        costs less than one per line, and none is held back longer than the batch takes to write."""
        try:
            text = _ENCODER.encode(obj)
        except (ValueError, TypeError, OverflowError, RecursionError) as exc:
            at = f"line {line}: " if line is not None else ""
            self.error(obj.get("id"), f"{at}the answer cannot be written as JSON ({_clip(str(exc), 200)})")
            return False
        self._emit(text, flush)
        return True

    def error(self, ident: Any, message: str, **extra: Any) -> None:
        """The error line ``{"id": ident, "error": message, **extra}``; an id JSON cannot echo becomes null, and the
        message is cut to :data:`MAX_MESSAGE_CHARS`. Never fails on its content."""
        obj = {"id": ident if id_problem(ident) is None else None, "error": _clip(str(message))}
        try:
            text = json.dumps({**obj, **extra}, allow_nan=False)
        except (ValueError, TypeError, OverflowError, RecursionError):
            text = json.dumps(obj)
        self._emit(text)
        self.errors += 1

    def record_error(self, record: Record[Any]) -> None:
        """The error line of a record that could not be read."""
        self.error(record.id, record.error or "unknown error")


class ClosedOutput(io.TextIOBase):
    """Stands in for ``sys.stdout`` when the process was started with standard output closed (``>&-``, where
    Python leaves ``sys.stdout`` None and ``print`` would drop every line without a word): writing to it raises
    ``OSError`` (EBADF) saying so, which the CLI reports as one error line (:func:`torchrod.cli.main`)."""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        raise OSError(errno.EBADF, STDOUT_CLOSED)


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


def same_path(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name the same file: the same file on disk when both exist (links followed), else the
    same absolute path once links are resolved."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_output(path: str | None, inputs: Inputs = (), option: str = "--out") -> None:
    """:class:`~torchrod.errors.OptionsError` when the output ``path`` of ``option`` is one of ``inputs`` (writing
    it would erase that input): a sequence of paths, or a mapping from what each is (``"--rod"``, ``"READINGS"``)
    to its path. ``None``, ``"-"`` and inputs that are no file (a preset name, ``"-"``) are left alone."""
    if path is None or path == "-":
        return
    named = inputs.items() if isinstance(inputs, Mapping) else ((None, source) for source in inputs)
    for label, source in named:
        if source is None or os.fspath(source) == "-" or not os.path.lexists(source):
            continue
        if same_path(source, path):
            which = f" ({label})" if label else ""
            raise OptionsError(
                f"{option} {path} is the input {os.fspath(source)}{which}: writing it would erase the input; "
                "give another path"
            )


@contextlib.contextmanager
def open_output(path: str | None, inputs: Inputs = ()) -> Iterator[IO[str] | None]:
    """``--out PATH`` opened for writing (UTF-8, closed at the end), or None for standard output (``None``/``"-"``).

    Raises ``ValueError`` (exit status 2) naming the path when it cannot be written (a missing folder, a folder,
    no permission), when it is one of ``inputs`` (:func:`check_output`: it would be emptied before being read), or,
    for standard output, when the process was started with standard output closed (``>&-``).
    """
    if path is None or path == "-":
        if sys.stdout is None or isinstance(sys.stdout, ClosedOutput):
            raise OptionsError(STDOUT_CLOSED)
        yield None
        return
    check_output(path, inputs)
    try:
        fh = open(path, "w", encoding="utf-8")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise OptionsError(f"--out {path}: cannot write there ({exc.strerror or exc})") from None
    try:
        yield fh
    finally:
        fh.close()


# ---------------------------------------------------------------------------------------------------- signals
class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread while :func:`sigterm_as_interrupt` is active. A ``KeyboardInterrupt``,
    so everything that flushes on Ctrl-C flushes on it too; the command then exits with status 143."""


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread (as SIGINT raises
    ``KeyboardInterrupt``); the previous handler is restored after. Does nothing outside the main thread."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGTERM"):
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interrupt_status(exc: BaseException) -> int:
    """Exit status after an interrupt: 143 for SIGTERM (:class:`Terminated`), 130 for Ctrl-C."""
    return 143 if isinstance(exc, Terminated) else 130


def until_interrupted(command: Callable[[], int]) -> int:
    """Run a command with SIGTERM as an interrupt; its status, or :func:`interrupt_status` if interrupted (the
    command flushes what it answered on the way out)."""
    with sigterm_as_interrupt():
        try:
            return command()
        except KeyboardInterrupt as exc:
            from ..kernels.targets import note_interrupt

            note_interrupt()  # (an interrupted run ends now, not when a first compile would)
            return interrupt_status(exc)


# ---------------------------------------------------------------------------------------------- field helpers
def get_number(obj: Mapping[str, Any], key: str, where: str = "") -> float:
    """``obj[key]`` as a finite float. ``where`` prefixes the field name in errors, e.g. ``"forces[2]"``."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        raise ReadingError(f"missing {name!r}")
    return as_number(obj[key], name)


def get_list(obj: Mapping[str, Any], key: str, where: str = "") -> list[Any]:
    """``obj[key]``, which must be a JSON array."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        raise ReadingError(f"missing {name!r}")
    value = obj[key]
    if not isinstance(value, list):
        raise ReadingError(f"{name} must be an array, got {describe(value)}")  # noqa: TRY004 (bad data, one kind of error)
    return value


def check_keys(
    obj: Any, required: Sequence[str], optional: Sequence[str] = (), where: str = "object"
) -> Mapping[str, Any]:
    """Check that ``obj`` is a JSON object holding every ``required`` key and no key outside required + optional.

    Returns ``obj``; raises ``ValueError`` naming ``where`` and the missing or unknown keys.
    """
    if not isinstance(obj, dict):
        raise ReadingError(f"{where} must be an object, got {describe(obj)}")  # noqa: TRY004 (bad data, one kind of error)
    missing = [k for k in required if k not in obj]
    if missing:
        raise ReadingError(f"{where} is missing {', '.join(repr(k) for k in missing)}")
    allowed = set(required) | set(optional)
    unknown = sorted(k for k in obj if k not in allowed)
    if unknown:
        shown = ", ".join(_key(k) for k in unknown[:10])
        raise ReadingError(
            f"{where} has unknown key(s) {shown}{' ...' if len(unknown) > 10 else ''}; "
            f"expected {', '.join(repr(k) for k in (*required, *optional))}"
        )
    return obj
