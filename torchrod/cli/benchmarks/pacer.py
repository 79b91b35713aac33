"""An external pacer for ``torchrod bench stream``: a ``torchrod stream`` process fed JSON lines at a fixed rate
through a pipe, as an interrogator would feed it, with every latency measured by the process that writes the lines
(from the time a line is due to reading its answer), so the numbers include what a user's process sees: the pipe,
parsing, the stream's batching and the answer's JSON.

The child is started and warmed up first, the ``warm`` readings sent one at a time, each after the previous
answer, in two rounds: the first reading, and the rest; after each round the pacer waits until the child and its
worker processes (``--workers``) are idle. A worker starts in the background (it imports torch and warms up:
seconds of CPU), the pool when the stream starts and any worker started by the stream's first batches in the
second round, and timing while one does would measure its start-up, not the stream. Then the paced lines go out
on a writer thread at ``rate`` Hz, line k due at k / ``rate`` s and sent then (:func:`sleep_until`; one the writer
could not send on time, because the pipe was full or the writer was slow, goes out at once), while the calling
thread reads the answers. Latency counts from the line's due time, as a sensor's reading is taken on schedule
whether or not its reader keeps up: a stream that falls behind and stops reading its input cannot hide the wait.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from ...io.stream import StreamResult

__all__ = ["ExternalStream", "child_command", "cpu_time", "reading_line", "sleep_until"]

_CHILD = "import sys; sys.path.insert(0, sys.argv.pop(1)); from torchrod.cli import main; sys.exit(main(sys.argv[1:]))"


def child_command(*arguments: str) -> list[str]:
    """The command that runs ``torchrod ARGUMENTS`` in a child process with the torchrod package this process runs.
    ``python -m torchrod`` would import the one in the child's working directory first, whatever ``PYTHONPATH``
    says, so a benchmark of one version run from another version's checkout would time the wrong code."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    return [sys.executable, "-c", _CHILD, root, *arguments]


def reading_line(ident: Any, t: float | None, curvature: Sequence[Sequence[float]]) -> str:
    """One input line of ``torchrod stream``: ``{"id", "t", "curvature"}``, a missing (NaN) grating as null."""
    cells = [None if any(math.isnan(v) for v in pair) else [float(pair[0]), float(pair[1])] for pair in curvature]
    record: dict[str, Any] = {"id": ident, "curvature": cells}
    if t is not None:
        record["t"] = t
    return json.dumps(record)


class ExternalStream:
    """A ``torchrod stream`` child process and the pipe that paces it.

    Args:
        arguments: the options after ``torchrod stream`` (``--rod`` and the rest; input and output are the pipes).
        warm: lines (``reading_line`` text) sent one at a time before any timing, answers discarded.
        settle: [s] at most this long after each round of the warm-up, wait until the child and its own child
            processes use less than ``IDLE`` of a core over two windows of ``WINDOW`` (:func:`wait_idle`); 0: no
            wait.
    """

    def __init__(self, arguments: Sequence[str], warm: Sequence[str] = (), settle: float = 60.0) -> None:
        self.arguments = list(arguments)
        self.warm = list(warm)
        self.settle = settle
        self.cpu = math.nan  # [s] CPU time (user + system) of the child and its workers during the run (Linux /proc)
        self.settled = math.nan  # [s] the wait for the child's processes to be idle after the warm-up
        self.process: subprocess.Popen | None = None

    def start(self) -> ExternalStream:
        """Start the child and warm it up (its start-up and first calls stay out of the timed run)."""
        self.process = subprocess.Popen(
            child_command("stream", *self.arguments),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            bufsize=1,
        )
        assert self.process.stdout is not None  # stdout=PIPE
        self.settled = 0.0
        for round_ in (self.warm[:1], self.warm[1:]):
            for line in round_:
                self._send(line)
                if not self.process.stdout.readline():
                    raise RuntimeError(f"torchrod stream {' '.join(self.arguments)} ended during its warm-up")
            if self.settle > 0 and round_:
                t0 = time.perf_counter()
                wait_idle(self.process.pid, self.settle)
                self.settled += time.perf_counter() - t0
        return self

    def _send(self, line: str) -> None:
        assert self.process is not None and self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

    def run(self, lines: Sequence[str], ids: Sequence[Any], rate: float) -> Iterator[StreamResult]:
        """Send ``lines`` (ids ``ids``, in order) at ``rate`` Hz and yield each answer as a
        :class:`StreamResult` whose latency runs from the line's due time (the child's own ``latency_ms`` stays in
        the record);
        the child ends with its input, and :attr:`cpu` then holds its CPU time."""
        if self.process is None:
            self.start()
        proc = self.process
        assert proc is not None  # start() set it
        stdin, stdout = proc.stdin, proc.stdout
        assert stdin is not None and stdout is not None  # both are pipes
        cpu0 = cpu_time(family(proc.pid))
        sent: dict[str, float] = {}
        failed: list[BaseException] = []

        def write() -> None:
            try:
                t0 = time.perf_counter()
                for k, (ident, line) in enumerate(zip(ids, lines, strict=True)):
                    due = t0 + k / rate
                    sent[json.dumps(ident)] = due
                    sleep_until(due)
                    self._send(line)
                stdin.close()
            except BaseException as exc:  # noqa: BLE001 - reported by the reading thread
                failed.append(exc)

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        got = 0
        cpu1 = math.nan
        for text in stdout:
            now = time.perf_counter()
            record = json.loads(text)
            key = json.dumps(record.get("id"))
            latency = now - sent.get(key, now)
            got += 1
            if got == len(lines):
                cpu1 = cpu_time(family(proc.pid))
            yield StreamResult(record.get("id"), record.get("t"), record, latency=latency, error=record.get("error"))
        writer.join()
        proc.wait()
        self.cpu = cpu1 - cpu0
        if failed:
            raise RuntimeError(f"the pacer could not write to torchrod stream: {failed[0]}")
        if got != len(lines):
            raise RuntimeError(f"torchrod stream answered {got} of {len(lines)} lines (exit status {proc.returncode})")


SPIN = 5e-4
"""[s] :func:`sleep_until` sleeps until this long before the time it waits for, then waits actively."""


def sleep_until(due: float) -> None:
    """Return at ``due`` (``time.perf_counter`` seconds), not later than the clock allows: a sleep alone ends late by
    the system's timer slack and wake-up (about 0.1 ms at the median on a small shared machine), and a pacer that
    sends a line late would count its own delay as the stream's latency. So sleep until :data:`SPIN` before it, then
    wait actively (holding the interpreter lock for at most that long: another thread of the process waits no
    longer)."""
    wait = due - time.perf_counter() - SPIN
    if wait > 0:
        time.sleep(wait)
    while time.perf_counter() < due:
        pass


IDLE = 0.1
"""The share of one core below which :func:`wait_idle` calls a process family idle."""

WINDOW = 0.25
"""[s] the window over which :func:`wait_idle` measures CPU use."""


def family(pid: int) -> list[int]:
    """``pid`` and the live processes whose parent it is (a stream's workers; Linux's /proc, else ``[pid]``)."""
    out = [pid]
    try:
        entries = os.listdir("/proc")
    except OSError:
        return out
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid:
            out.append(int(entry))
    return out


def wait_idle(pid: int, timeout: float) -> bool:
    """Wait until process ``pid`` and its child processes used less than :data:`IDLE` of a core in each of two
    consecutive :data:`WINDOW` windows (a worker that has not appeared yet shows in the second), at most
    ``timeout`` seconds; whether they did."""
    end = time.perf_counter() + timeout
    quiet = 0
    before = cpu_time(family(pid))
    while time.perf_counter() < end:
        time.sleep(WINDOW)
        now = cpu_time(family(pid))
        quiet = quiet + 1 if now - before < IDLE * WINDOW else 0
        if quiet >= 2:
            return True
        before = now
    return False


def cpu_time(pids: Iterable[int]) -> float:
    """CPU time [s] (user + system) the live processes ``pids`` have used so far (Linux's /proc; 0 for one that
    cannot be read)."""
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime, in ticks
        except (OSError, ValueError, IndexError):
            continue
    return total
