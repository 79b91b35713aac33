"""Amortised estimation on streams of readings.

An FBG interrogator sends curvature readings at 100 Hz or more while the robot moves. :func:`stream` takes any
iterable of readings and yields one result per reading, in input order, as soon as its batch is solved:

- a reader thread pulls the input into a bounded queue, so a slow source never holds a batch back; a source that
  never waits (a list or tuple of readings, or a source whose ``never_waits`` is true: a
  :class:`~torchrod.io.sources.ReadingSource` of a regular file, a ROS bag) is read instead by the stream's own
  thread, a batch at a time while the solver threads work: two threads running Python at once cost the
  interpreter more than the reading does (docs/core.md, "Two cores through a backlog");
- readings are gathered into batches, closed when ``batch_size`` readings (times ``workers``) are pending or when
  the oldest pending reading has waited ``max_latency`` seconds (by default 0: a reading that finds the estimator
  idle is solved at once); readings that queued up while a batch was being solved all join the next one (up to a
  full batch), so under load batches form by themselves and grow instead of falling behind; with ``workers`` > 1
  each batch goes to an idle solver thread while the next readings are taken, so consecutive batches are solved
  at once on different cores (the kernels run without the interpreter lock) and their answers still come in order;
  once a file is read to its end, what is left goes out in ``workers`` parts, their readings shared among every
  core;
- a stream that learns its noise (``learn_noise``) sends its first batches in rounds that grow with the fits
  learned from, each round shared among the solver threads and solved with the noise from every round before;
  after that a batch takes the noise learned once all but the last ``2 * workers - 1`` batches handed out were
  answered, so a file's answers are the same whatever the threads' timing;
- each reading is estimated as :meth:`~torchrod.Estimator.estimate` would alone (the warm-start network's
  guesses when the estimator has one, the scan's starts, the count chosen per reading), so the stream's answers
  are the static estimator's; with ``track``, readings in batches of at most ``track_limit`` also start from the
  forces of the last solved reading (the count it chose, and that count less its weakest force, for a contact
  that vanishes);
- every reading is checked by the rules of :mod:`torchrod.io.reading` (the same as ``torchrod estimate``'s): a
  reading that cannot be used (an error upstream, NaN in a list, a value beyond the curvature bound, a wrong
  grating count, no grating present, an id JSON cannot echo) yields an error result in its place and the stream
  goes on; missing gratings are masked; should the estimator fail on a reading, that reading alone gets an error
  result;
- memory stays bounded: at most a batch of pending readings plus ``read_ahead`` queued ones (and one held by the
  reader thread);
- a ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM as :class:`torchrod.io.jsonl.Terminated` in the CLI) raised while
  the stream waits or solves, or thrown into the generator at a ``yield``, first flushes: the reader thread stops
  taking from the source (a :class:`~torchrod.io.sources.ReadingSource`, the CLI's, first gives the readings of
  the lines it has already read), every reading already taken from it (queued, or in the reader's hands) is
  solved and yielded, then the same exception is raised again. A source read by the stream's own thread is
  read with SIGINT and SIGTERM held (in the main thread), so the signal is raised between readings, never
  inside the source. The end of the input flushes the same way. Interrupted while a first compile of the kernels
  runs (readings are then solved as Python, far slower), the flush solves nothing more: the readings taken and not
  yet solved are answered in order as error results (:data:`UNSOLVED`), said once on stderr, and the compile is
  stopped, not waited for.

Readings are :class:`~torchrod.io.reading.Reading` objects or dicts with the same keys; results are
:class:`StreamResult`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import math
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from types import GeneratorType
from typing import Any, cast

import torch

from ..errors import OptionsError, TorchrodTypeError
from ..estimate.estimator import Estimator
from ..estimate.noise import NoiseLearning, RunningNoise, calibration_terms
from ..estimate.status import STATUSES
from ..kernels.targets import note_interrupt, note_unsolved
from ..loads import PointForces
from .reading import Reading, stack_readings, to_reading

__all__ = ["Reading", "StreamOptions", "StreamResult", "StreamStats", "answer_each", "stream", "warm_up"]


@dataclass(frozen=True)
class StreamResult:
    """The result for one reading.

    Attributes:
        id: the reading's id.
        t: the reading's timestamp [s] (None when it has none).
        record: JSON-ready dict: the :meth:`torchrod.estimate.estimator.EstimateResult.to_records` form plus ``t`` (when
            given) and ``latency_ms``; for an unusable reading ``{"id", "error"}`` (plus ``t``).
        latency: [s] from the moment the reader thread took the reading from the source to the end of its
            batch's solve.
        error: why the reading could not be used; None for a solved reading.
        batch: readings solved together with this one (itself included); solve_time: [s] that batch's estimate.
        line: the reading's input line, when it came with one (:attr:`Reading.line`).
        batch_end: whether it is the last result of its batch: the next comes from another solve (a writer that
            holds a batch's lines flushes here).
    """

    id: Any
    t: float | None
    record: dict[str, Any]
    latency: float = 0.0
    error: str | None = None
    batch: int = 1
    solve_time: float = 0.0
    _result: Any = field(default=None, repr=False, compare=False)
    _index: int = field(default=0, repr=False, compare=False)
    line: int | None = None
    batch_end: bool = True

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def estimate(self) -> Any:
        """The reading's :class:`torchrod.estimate.estimator.EstimateResult` (a batch of one), None for an error."""
        return None if self._result is None else self._result[self._index]


@dataclass(frozen=True)
class StreamOptions:
    """Batching of a stream.

    Attributes:
        batch_size: the most readings solved together. It bounds only a backlog: a source the solver keeps up with
            leaves fewer readings pending. Large, so that a backlog is cleared in few calls; the price is that the
            first answers of a large backlog wait for its whole batch.
        max_latency: [s] the longest the oldest pending reading waits for more readings before its batch is
            solved (0, the default: solve whatever is available at once; a wait lets a fast source fill larger
            batches at the cost of latency).
        read_ahead: bound on readings taken from the source and queued beyond the pending batch; None: twice
            the batch (with less, a backlog cannot fill whole batches: a batch takes what is queued). A source
            that never waits (module docstring) is read a batch at a time, with nothing queued.
        track: start the readings of a batch from the last solved reading's forces too, when the batch holds
            at most ``track_limit`` readings (loads change slowly between frames). Off by default: the search
            finds what these starts find, and they cost time. A larger batch (a backlog) spans too many frames for
            one previous solution to be near most of its readings.
        device: torch device the readings are estimated on.
        learn_noise: with no noise given (neither the estimator's ``noise`` nor an override), learn the sensor's
            sigma from the stream's own fits (:mod:`torchrod.estimate.noise`) and, once learned, solve every
            reading with it as a known noise: faster (counts settle early) and as accurate as with the true sigma.
            Until then a batch holds ``after`` readings, and until the sigma comes from enough fits, no more
            readings than ``growth`` times the fits learned from (:class:`~torchrod.estimate.noise.NoiseLearning`).
            None: every reading estimates its own noise.
        workers: solver threads (None: one per CPU core). Each batch is solved whole by an idle thread while the
            next readings are taken: a backlog keeps every core busy with batches of ``batch_size``, and a live
            source's consecutive readings are solved at once, so one slow reading does not hold the next ones back
            (their answers still come in input order). With ``track`` the batches are solved one after another
            (each starts from the last one's answer), each spread over the threads.
    """

    batch_size: int = 1024
    max_latency: float = 0.0
    read_ahead: int | None = None
    track: bool = False
    track_limit: int = 16
    device: str | torch.device = "cpu"
    learn_noise: NoiseLearning | None = NoiseLearning()
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.learn_noise is not None and not isinstance(self.learn_noise, NoiseLearning):
            raise TorchrodTypeError(f"learn_noise must be NoiseLearning or None, got {type(self.learn_noise).__name__}")
        for name in ("batch_size", "read_ahead", "track_limit", "workers"):
            v = getattr(self, name)
            if v is None and name in ("read_ahead", "workers"):
                continue
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise OptionsError(f"{name} must be an integer >= 1, got {v!r}")
        lat = self.max_latency
        if isinstance(lat, bool) or not isinstance(lat, (int, float)) or not (0.0 <= lat < math.inf):
            raise OptionsError(f"max_latency must be a finite number of seconds >= 0, got {lat!r}")


# ---------------------------------------------------------------------------------------------------- the stream
_END = object()
_HALTED = object()  # the reader stopped taking from the source, as asked (a flush)
_POLL = 0.1  # [s] longest uninterrupted wait (keeps the reader thread responsive to stop)
_LEARNING_PART = 64  # fewest readings of a part when a batch of the noise's learning is shared among threads
UNSOLVED = "not solved: the run was interrupted while the kernels were compiling"
"""The error of a reading taken from the source and not solved when the run was interrupted during a first compile
(module docstring)."""


def _reader(state: _Stream, source: Iterable[Any]) -> None:
    """Pull ``source`` into ``state.q`` as checked :class:`_Pending` readings (checked here, in parallel with the
    solver); then _END, or the exception the source raised. Once ``state.halt`` is set, put the reading in hand and
    then _HALTED, and take nothing more; ``state.in_source`` is set while waiting on the source."""
    q, stop, halt, in_source = state.q, state.stop, state.halt, state.in_source

    def put(entry: Any) -> bool:
        while not stop.is_set():
            try:
                q.put(entry, timeout=_POLL)
                return True
            except queue.Full:
                continue
        return False

    try:
        items = iter(source)
        while not halt.is_set():
            in_source.set()
            try:
                item = next(items)
            except StopIteration:
                break
            finally:
                in_source.clear()
            arrived = time.perf_counter()
            reading = to_reading(item, state.G, fibre=state.fibre)
            if not put(_Pending(reading, arrived)):
                return
            if state.hungry:  # (the stream waits for batches alone while every solver thread has its own)
                state.wake.set()
        else:
            put(_HALTED)
            return
    except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
        put(exc)
        return
    put(_END)


@dataclass
class _Pending:
    reading: Reading  # checked: a curvature tensor, or an error
    arrived: float

    @property
    def ok(self) -> bool:
        return self.reading.error is None


@dataclass
class _Slot:
    """A batch taken from the pending readings: its results, or the future of its solve in a solver thread, or
    (``here``, while the kernels compile) the noise it was handed out with and how many of its readings were solved
    so far on the stream's thread, one at a time (:meth:`_Stream.step`)."""

    batch: list[_Pending]
    results: list[StreamResult] | None = None
    future: Any = None
    here: bool = False
    noise: float | None = None
    solved: int = 0
    starts: dict[int, PointForces] | None = None  # its tracking starts, taken when it was handed out
    last: PointForces | None = None  # the last solution among its readings solved so far (tracking)

    def done(self) -> bool:
        return self.results is not None or self.future is None or self.future.done()


class _Stream:
    """The state of one :func:`stream`: queue, pending batch, last solution."""

    def __init__(self, estimator: Any, readings: Iterable[Any], options: StreamOptions, estimate: Any) -> None:
        from ..kernels.host import cpu_threads

        self.estimator, self.options = estimator, options
        self._checked_call = isinstance(estimator, Estimator)  # (its readings need no second check: _call)
        self.estimate_options = estimate  # the EstimatorOptions of every batch
        # those options per learned noise (None: none learned) and CPU threads
        self._options: dict[tuple[float | None, int], Any] = {}
        self.workers = cpu_threads(options.workers)
        # Solver threads: each batch whole in one (the kernels release the interpreter lock), unless tracking.
        self.pool = None
        if self.workers > 1 and not options.track:
            self.pool = concurrent.futures.ThreadPoolExecutor(self.workers, thread_name_prefix="torchrod-stream")
        self.threads = 1 if self.pool is not None else self.workers  # CPU threads of one batch's solve
        self.G = estimator.rod.num_gratings
        self.fibre = estimator.rod.fibre
        self.device = torch.device(options.device)
        self.batch_size = options.batch_size
        read_ahead = options.read_ahead if options.read_ahead is not None else 2 * self.batch_size * self.workers
        self.q: queue.Queue = queue.Queue(maxsize=read_ahead)
        self.stop = threading.Event()
        self.halt = threading.Event()
        self.wake = threading.Event()  # set by the reader after a reading (while hungry) and by a finished batch
        self.hungry = True  # False while the stream waits for a batch alone: a new reading could not be sent yet
        self.in_source = threading.Event()
        self.pending: list[_Pending] = []
        # The last solved reading's forces, in reported coordinates, (1, h).
        self.previous: PointForces | None = None
        self.finished = False
        self.error: BaseException | None = None
        learn = options.learn_noise is not None and estimate.noise is None and estimate.selection == "noise"
        self.noise = RunningNoise(cast(NoiseLearning, options.learn_noise)) if learn else None  # learn: it is set
        # Batches handed out and answered, in order; the learned noise after each count of answered batches (those
        # a batch may take its noise from); the count answered when the learning's last round was (None: before).
        self.sent = self.received = 0
        self._noise_after: dict[int, float | None] = {0: None}
        self._learned_at: int | None = None
        self._tail: int | None = None  # the readings of each part of what was left when the input ended (step)
        # At most this many batches are in flight when one is handed out (and none when one is solved here).
        self._lag = 2 * self.workers - 1 if self.pool is not None else 0
        self.max_noise = float(estimate.max_noise)
        # Started by the first ``next``: a stream that is never iterated takes nothing from its source.
        self.thread = threading.Thread(target=_reader, args=(self, readings), daemon=True, name="torchrod-reader")
        self.source: Any = readings  # any iterable; a ReadingSource also has halt() and waiting (drain)
        # A source that never waits is read here, between batches (module docstring), not by the reader thread.
        self.direct: Iterator[Any] | None = iter(readings) if _never_waits(readings) else None

    def _take(self, entry: Any) -> None:
        if entry is _END or entry is _HALTED:
            self.finished = True
        elif isinstance(entry, BaseException):
            self.finished = True
            self.error = entry  # raised once the readings before it are answered
        else:
            self.pending.append(entry)

    def fill(self, wait: bool = True) -> None:
        """Take readings until a batch is due: a full batch pending, the oldest pending waited ``max_latency``
        (everything already queued still joins, up to a full batch), or the source ended. ``wait`` False: take
        only what is queued now."""
        opts = self.options
        if self.direct is not None:
            self._read(self.batch_size)
            return
        while not wait and len(self.pending) < self.batch_size and not self.finished:
            try:
                self._take(self.q.get_nowait())
            except queue.Empty:
                return
        while len(self.pending) < self.batch_size and not self.finished:
            if self.pending:
                left = opts.max_latency - (time.perf_counter() - self.pending[0].arrived)
                try:
                    entry = self.q.get(timeout=min(left, _POLL)) if left > 0 else self.q.get_nowait()
                except queue.Empty:
                    if left <= _POLL:
                        return
                    continue
            else:
                try:
                    entry = self.q.get(timeout=_POLL)
                except queue.Empty:
                    continue
            self._take(entry)

    def _read(self, size: float) -> None:
        """Read the source here (one that never waits) until ``size`` readings are pending or it ends, with SIGINT
        and SIGTERM held: a signal arrives between two readings, not inside the source, which the flush reads on."""
        assert self.direct is not None
        G, fibre, pending = self.G, self.fibre, self.pending
        with _HeldSignals() as held:
            while len(pending) < size and not held.caught:
                try:
                    item = next(self.direct)
                except StopIteration:
                    self.finished = True
                    break
                except Exception as exc:  # noqa: BLE001 - raised once the readings before it are answered
                    self.finished = True
                    self.error = exc
                    break
                pending.append(_Pending(to_reading(item, G, fibre=fibre), time.perf_counter()))

    def step(self, flight: collections.deque[_Slot]) -> list[StreamResult] | None:
        """The results of the next batch in input order, or None at the end of the input. Batches are taken from
        the pending readings as they come and handed to an idle solver thread (or solved here without a pool, or
        when one reading comes to an idle stream, or a reading at a time while the kernels compile: :meth:`advance`),
        while this thread goes on taking readings; at most two batches per thread are in flight. A batch leaves
        ``pending`` only once it is handed out or solved, and ``flight`` only once its results are returned, so an
        interrupt loses none."""
        while True:
            if flight and flight[0].here:
                return self.advance(flight)
            self.wake.clear()  # (before the checks: what happens after them sets it again)
            self.hungry = True  # (before the queue is looked at: a reading put after that sets wake)
            if flight and flight[0].done() and not self._may_send(flight):
                # (readings waiting for a free solver thread go out first: at the end of a backlog the threads
                # would otherwise stand idle while this one writes a batch's answers)
                return self.take(flight)
            if not self.finished:
                self.fill(wait=not flight)
            if not self.pending:
                if not flight:
                    return None  # fill waits for a reading unless something is in flight: the input ended
                self.wake.wait(_POLL)  # for a reading, or the first batch in flight
                continue
            if self.pool is not None and not self._may_send(flight):
                # every thread has its batches, or the next batch's size and noise wait on the fits in flight: wait
                # for a batch, not woken by each reading that arrives meanwhile (a backlog's thousands)
                self.hungry = False
                self.wake.wait(_POLL)
                continue
            limit = self.batch_limit()
            if self.noise is not None and self._learned_at is None and limit >= self.batch_size:
                self._learned_at = self.received  # (every batch before is answered: learning waits for them)
            parts = min(self.workers, min(limit, len(self.pending)) // _LEARNING_PART)
            if self.pool is not None and self.learning and parts > 1:
                # Learning the noise: this round's readings go out at once, shared among the solver threads (each
                # part with the same noise, so the answers are those of one batch), and the next round waits for
                # them all.
                batch = self.pending[:limit]
                size = -(-len(batch) // parts)
                for k in range(0, len(batch), size):
                    part = batch[k : k + size]
                    flight.append(self.defer(part) if self.compiling else self.send(part))
                del self.pending[: len(batch)]
                continue
            last = self.direct is not None and self.finished and self.pool is not None
            if last:
                # The input is all read: what is left is shared among the solver threads (a short file is not one
                # batch on one thread while the others wait), in parts fixed when the input ended, so that the
                # batches, and the noise each takes, do not depend on the threads' timing.
                if self._tail is None:
                    self._tail = -(-len(self.pending) // self.workers)
                limit = min(limit, self._tail)
            batch = self.pending[:limit]
            # A lone reading that finds every solver thread idle is solved here: handing it to a thread and back
            # would cost two thread wake-ups, a large share of a paced reading's latency. Readings that come
            # meanwhile wait in the queue and go out together once it is answered (after it, in any case).
            alone = not flight and len(batch) == 1 and self.q.empty()
            if self.compiling:
                slot = self.defer(batch)
            elif self.pool is not None and not alone:
                # The input's last batches spread their readings over every core: a thread that finishes first
                # takes readings of the batch still running, rather than waiting idle at the end.
                slot = self.send(batch, self.workers if last else 1)
            else:
                slot = _Slot(batch, results=self.solve(batch))
            del self.pending[: len(batch)]
            flight.append(slot)

    def _may_send(self, flight: collections.deque[_Slot]) -> bool:
        """Whether pending readings can go to a solver thread now: one is pending, fewer than two batches per thread
        are in flight, the next batch's size and noise do not wait on the fits in flight, and the kernels are not
        compiling (batches are then solved here, :meth:`advance`)."""
        return (
            self.pool is not None
            and bool(self.pending)
            and len(flight) < 2 * self.workers
            and not (flight and (self.learning or self.compiling))
        )

    def batch_limit(self) -> int:
        """The most pending readings the next batch takes: ``batch_size``, but while the stream learns its noise no
        more than ``learn_noise.growth`` times the fits learned from so far, and before it has a sigma,
        ``learn_noise.after``. So a backlog's first large batch does not solve every reading with a noise of its own
        (slower, less accurate) before the stream has the fits it learns from, nor a thousand readings with a sigma
        learned from 32 fits: the batches grow until the sigma comes from enough fits."""
        size = self.batch_size
        if self.noise is None:
            return size
        learning = self.noise.learning
        if self.noise.count < learning.after:  # no sigma yet (without sorting the fits to find out)
            return min(size, learning.after)
        return min(size, max(learning.after, learning.growth * self.noise.used))

    @property
    def compiling(self) -> bool:
        """Whether the estimator's kernels are still compiling (readings are then solved as Python, far slower)."""
        return getattr(self.estimator, "compiling", bool)()

    @property
    def learning(self) -> bool:
        """Whether the stream is still learning its noise: its batches go out in rounds, each held to fewer than
        ``batch_size`` readings by the fits learned from so far (:meth:`batch_limit`), and a round waits for the
        batches of the one before."""
        return self.noise is not None and self._learned_at is None

    def hand_out(self) -> float | None:
        """Count a batch handed out now (to a solver thread or solved here); the learned noise it is solved with
        (None: none), the same whatever the solver threads' timing, so that a file's answers are the same in every
        run: while learning, the noise after every batch before (a round waits for them); then the noise once all
        but the last ``2 * workers - 1`` batches handed out were answered (at most that many are in flight when one
        is handed out), but never older than the learning's end. Read from what :meth:`take` kept: no sort of the
        fits again."""
        answered = self.received if self._learned_at is None else max(self.sent - self._lag, self._learned_at)
        self.sent += 1
        return self._noise_after[answered]

    def advance(self, flight: collections.deque[_Slot]) -> list[StreamResult]:
        """The results of the next reading of the oldest batch in flight, one solved here (:meth:`defer`, while the
        kernels compile): one reading at a time, as Python, each answered as soon as it is solved; once the kernels
        are ready, the rest of the batch at once. The batch leaves ``flight`` with its last reading (:meth:`take`).
        The batches and the noise each is solved with are those the stream forms with the kernels ready, and a
        reading's answer does not depend on the readings solved with it: a cold run answers as a warm one."""
        slot = flight[0]
        if not self.compiling or slot.solved + 1 >= len(slot.batch):
            return self.take(flight)
        results = self._solve(slot.batch[slot.solved : slot.solved + 1], slot.noise, slot)
        slot.solved += 1
        return results

    def take(self, flight: collections.deque[_Slot]) -> list[StreamResult]:
        """The results of the oldest batch in flight (waiting for them; of a batch solved here, its readings not yet
        answered), which leaves ``flight``; the learned noise after it is kept for :meth:`hand_out`."""
        results = self.receive(flight[0])
        flight.popleft()
        self.received += 1
        self._noise_after[self.received] = self.learned_noise
        if self.received - self._lag - 1 != self._learned_at:  # (no longer needed; the learning's end is kept)
            self._noise_after.pop(self.received - self._lag - 1, None)
        return results

    def drain(self) -> None:
        """The flush after an interrupt: take everything the reader already took (the queue, and the reading in
        its hands) and no more. A source with ``halt()`` and ``waiting``
        (:class:`~torchrod.io.sources.ReadingSource`) is asked to end after the lines it already read, and the
        reader runs until it ends or waits on its input; any other source is left at once: the reader stops after
        the reading in its hands and is left alone once it waits on the source (it then holds nothing). A source
        read on this thread is read here to the end of the lines it already read (a ReadingSource), or left at
        once."""
        halt: Any = getattr(self.source, "halt", None)
        cooperative = callable(halt) and hasattr(self.source, "waiting")
        if self.direct is not None:
            if cooperative and not self.finished:
                halt()
                self._read(math.inf)  # (ends with the lines already read)
            self.finished = True
            return
        if cooperative:
            halt()
        else:
            self.halt.set()
        while not self.finished:
            try:
                entry = self.q.get(timeout=_POLL / 4)
            except queue.Empty:
                if not self.thread.is_alive():
                    return
                if self.source.waiting if cooperative else self.in_source.is_set():
                    return
                continue
            self._take(entry)

    def unsolved(self, flight: collections.deque[_Slot]) -> Iterator[StreamResult]:
        """The flush after an interrupt while the kernels compile: the answers already solved, then every other
        reading taken from the source as an error result, in order (said on stderr); nothing is solved."""
        left = [p for slot in flight if slot.here and slot.results is None for p in slot.batch[slot.solved :]]
        note_unsolved(sum(p.ok for p in [*left, *self.pending]))
        while flight:
            slot = flight[0]
            if slot.here and slot.results is None:
                slot.results = self._unsolved(slot.batch[slot.solved :])
            yield from self.take(flight)
        while self.pending:
            batch = self.pending[: self.batch_size]
            del self.pending[: len(batch)]
            yield from self._unsolved(batch)

    def _unsolved(self, batch: Sequence[_Pending]) -> list[StreamResult]:
        """Each reading of ``batch`` as an error result: not solved (:meth:`unsolved`); an unusable one with its
        own error."""
        return self._results(batch, [(None, 0, None, UNSOLVED)] * sum(p.ok for p in batch), 0.0)

    def _call(self, curvature: torch.Tensor, mask: torch.Tensor, options: Any, starts: Any) -> Any:
        """The estimator's call on stacked readings, each checked when it was taken (:func:`to_reading`), so an
        :class:`~torchrod.estimate.estimator.Estimator` does not check them again; any other estimator gets the
        plain call."""
        if self._checked_call:
            return self.estimator.estimate(curvature, mask, options=options, extra_starts=starts, _checked=True)
        return self.estimator.estimate(curvature, mask, options=options, extra_starts=starts)

    def solve(self, batch: Sequence[_Pending]) -> list[StreamResult]:
        """Estimate the usable readings of ``batch`` together, here; one result per reading, in order."""
        return self._solve(batch, self.hand_out())

    def _solve(self, batch: Sequence[_Pending], noise: float | None, slot: _Slot | None = None) -> list[StreamResult]:
        """``batch`` estimated here with ``noise``; as a part of ``slot`` (one solved here), with its tracking starts,
        and leaving as the last solution the last one among its readings solved so far, as the whole batch would."""
        good = [p for p in batch if p.ok]
        start = time.perf_counter()
        starts = self._tracking_starts(len(good)) if slot is None else _first(slot.starts, len(good))
        answers = self._answers(good, *self._estimate(good, noise, starts=starts)) if good else []
        if slot is not None and self.options.track:
            if self.previous is None:
                self.previous = slot.last
            slot.last = self.previous
        return self._results(batch, answers, time.perf_counter() - start)

    def send(self, batch: list[_Pending], threads: int = 1) -> _Slot:
        """Hand ``batch`` to a solver thread, its kernels on ``threads`` CPU threads; :meth:`receive` gives its
        results."""
        good = [p for p in batch if p.ok]
        noise = self.hand_out()
        if not good:
            return _Slot(batch, results=self._results(batch, [], 0.0))
        assert self.pool is not None  # step() sends only with a pool
        future = self.pool.submit(self._timed_estimate, good, noise, threads)
        future.add_done_callback(lambda _: self.wake.set())
        return _Slot(batch, future=future)

    def defer(self, batch: list[_Pending]) -> _Slot:
        """Hand ``batch`` out to be solved on this thread by :meth:`advance` (while the kernels compile)."""
        starts = self._tracking_starts(sum(p.ok for p in batch))
        return _Slot(batch, here=True, noise=self.hand_out(), starts=starts)

    def _timed_estimate(self, good: Sequence[_Pending], learned: float | None, threads: int) -> tuple[float, Any]:
        """:meth:`_estimate` in a solver thread, with its own duration [s]: a batch's solve time, not counting its
        wait for the thread (behind the batch before it) nor for this thread to take its results."""
        began = time.perf_counter()
        out = self._estimate(good, learned, threads, self._tracking_starts(len(good)))
        return time.perf_counter() - began, out

    def receive(self, slot: _Slot) -> list[StreamResult]:
        """The results of a batch :meth:`send` handed out (waiting for them), as :meth:`solve` gives them."""
        if slot.results is not None:
            return slot.results
        if slot.here:
            slot.results = self._solve(slot.batch[slot.solved :], slot.noise, slot)
            return slot.results
        good = [p for p in slot.batch if p.ok]
        took, out = slot.future.result()
        slot.results = self._results(slot.batch, self._answers(good, *out), took)
        return slot.results

    def _results(self, batch: Sequence[_Pending], answers: list, elapsed: float) -> list[StreamResult]:
        """The :class:`StreamResult` of each reading of ``batch``: its answer, or its error; ``elapsed`` [s] the
        batch's solve time."""
        good = [p for p in batch if p.ok]
        done = time.perf_counter()
        out, answers_it = [], iter(answers)
        end = len(batch) - 1
        for k, p in enumerate(batch):
            r = p.reading
            latency = done - p.arrived
            result, index, rec, error = (None, 0, None, r.error) if not p.ok else next(answers_it)
            if error is not None:
                if r.line is not None and not error.startswith("line "):
                    error = f"line {r.line}: {error}"
                rec = {"id": r.id, "error": error}
                if r.t is not None:
                    rec["t"] = r.t
                out.append(
                    StreamResult(r.id, r.t, rec, latency, error, len(batch), elapsed, line=r.line, batch_end=k == end)
                )
                continue
            assert rec is not None  # an answer without an error holds its record
            if r.t is not None:
                rec["t"] = r.t
            rec["latency_ms"] = round(1e3 * latency, 3)
            out.append(StreamResult(r.id, r.t, rec, latency, None, len(good), elapsed, result, index, r.line, k == end))
        return out

    def _estimate(
        self,
        good: Sequence[_Pending],
        learned: float | None,
        threads: int | None = None,
        starts: dict[int, PointForces] | None = None,
    ) -> tuple[Any, torch.Tensor, float | None, Any]:
        """The batched call on ``good`` with the ``learned`` noise (None: none), its kernels on ``threads`` CPU
        threads (None: the stream's own), the tracking ``starts`` (:meth:`_tracking_starts`) beside its own: (its
        result, the mask, that noise, None), or, should it fail, (None, the mask, the noise, what came instead: the
        error message of a single reading, else each reading's own call, as this returns it)."""
        curvature, mask = stack_readings([p.reading for p in good])
        if self.device.type != "cpu":
            curvature, mask = curvature.to(self.device), mask.to(self.device)
        threads = self.threads if threads is None else threads
        options = self._options.get((learned, threads))
        if options is None:  # (made once per noise: a replace checks every option again, a cost at one reading)
            options = dataclasses.replace(self.estimate_options, threads=threads)
            if learned is not None:
                options = dataclasses.replace(options, noise=learned)
            if len(self._options) > 64:
                self._options.clear()
            self._options[learned, threads] = options
        try:
            result = self._call(curvature, mask, options, starts)
        except Exception as exc:  # noqa: BLE001 - a reading that breaks the solver must not stop the stream
            if len(good) == 1:
                return None, mask, learned, f"estimation failed: {_exception_text(exc)}"
            one = _first(starts, 1)
            each = [self._estimate(good[k : k + 1], learned, threads, one) for k in range(len(good))]
            return None, mask, learned, each
        return result, mask, learned, None

    def _answers(
        self, good: Sequence[_Pending], result: Any, mask: torch.Tensor, learned: float | None, alone: Any
    ) -> list[tuple[Any, int, dict | None, str | None]]:
        """(batch result, index in it, record, None) per reading of a batched call's ``result`` (or of each
        reading's own call, or its error); the fits teach the noise, the last one is the tracking start."""
        if result is None:
            if isinstance(alone, str):  # one reading, and its call failed
                return [(None, 0, None, alone)]
            return [a for p, each in zip(good, alone, strict=True) for a in self._answers([p], *each)]
        records = result.to_records([p.reading.id for p in good])
        if learned is not None:
            for rec in records:
                rec["noise"] = learned
        if self.noise is not None:
            # fits that stopped early (unconverged, or cut by the time budget) overstate the noise
            use = (result.status != STATUSES.index("unconverged")) & (result.status != STATUSES.index("timeout"))
            values = 2 * mask.sum(1)
            dof = values - 3 * result.num_forces.to(mask.device)
            rod = getattr(self.estimator, "rod", None)
            terms = None
            if rod is not None and rod.calibration_error and learned is not None:  # the calibration's share
                curvature = stack_readings([p.reading for p in good])[0].to(mask.device)
                variance = rod.calibration_variance(torch.where(mask[..., None], curvature, 0.0))
                s2 = None if learned is None else learned**2 + float(self.estimate_options.noise_floor) ** 2
                terms = calibration_terms(variance[use], mask[use], s2)
            self.noise.add(result.loss[use].tolist(), dof[use].tolist(), terms)
        if self.options.track:
            self.previous = _last_solution(result)
        return [(result, k, rec, None) for k, rec in enumerate(records)]

    @property
    def learned_noise(self) -> float | None:
        """The sigma learned from the stream [1/m] once there is one the verdict believes (at most the estimator's
        ``max_noise``), else None."""
        sigma = self.noise.sigma if self.noise is not None else None
        return sigma if sigma is not None and sigma <= self.max_noise else None

    def _tracking_starts(self, B: int) -> dict[int, PointForces] | None:
        """The last solution as starts for every reading of the batch: its count h, and h - 1 without its weakest
        force (a contact that fades away)."""
        prev = self.previous
        if prev is None or not self.options.track or B > self.options.track_limit:
            return None
        h = prev.s.shape[1]
        starts = {h: PointForces(prev.s.expand(B, h), prev.f.expand(B, h, 2))}
        if h > 1:
            keep = torch.linalg.vector_norm(prev.f[0], dim=-1).argsort(descending=True)[: h - 1].sort().values
            starts[h - 1] = PointForces(prev.s[:, keep].expand(B, h - 1), prev.f[:, keep].expand(B, h - 1, 2))
        return starts

    def close(self) -> None:
        self.stop.set()
        # Unblock a reader waiting on a full queue; a reader blocked inside the source (e.g. a terminal read)
        # cannot be woken: it is a daemon thread and ends with the source or the process.
        try:
            while True:
                self.q.get_nowait()
        except queue.Empty:
            pass
        if self.thread.is_alive():
            self.thread.join(timeout=2 * _POLL)
        if self.pool is not None:
            self.pool.shutdown(wait=True)
        close = getattr(self.direct, "close", None)
        if callable(close):  # (a file read here is closed with the stream, not when its reader is collected)
            close()


def _never_waits(source: Any) -> bool:
    """Whether taking a reading from ``source`` never waits: a list or tuple, or a source that says so by a true
    ``never_waits`` (a :class:`~torchrod.io.sources.ReadingSource` of a regular file, a ROS bag)."""
    return isinstance(source, (list, tuple)) or getattr(source, "never_waits", False) is True


class _HeldSignals:
    """SIGINT and SIGTERM, where Python handles them, held while the block runs (in the main thread; elsewhere no
    signal is delivered): the first one that came is handled, as it would have been, when the block ends."""

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.caught: tuple[int, Any] | None = None
        self._saved: dict[int, Any] = {}

    def _hold(self, signum: int, frame: Any) -> None:
        if self.caught is None:
            self.caught = (signum, frame)

    def __enter__(self) -> _HeldSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in self._SIGNALS:
                handler = signal.getsignal(sig)
                if callable(handler):
                    self._saved[sig] = handler
                    signal.signal(sig, self._hold)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        if self.caught is not None:
            self._saved[self.caught[0]](*self.caught)


def _exception_text(exc: BaseException) -> str:
    """A short message for a failed estimate (the exception's type too when it is not a ValueError/RuntimeError)."""
    text = str(exc)
    text = text if len(text) <= 300 else text[:300] + "..."
    return text if isinstance(exc, (ValueError, RuntimeError)) else f"{type(exc).__name__}: {text}"


def _first(starts: dict[int, PointForces] | None, n: int) -> dict[int, PointForces] | None:
    """The first ``n`` rows of tracking starts (every row holds the same start; None: none)."""
    return None if starts is None else {h: PointForces(pf.s[:n], pf.f[:n]) for h, pf in starts.items()}


def _last_solution(result: Any) -> PointForces | None:
    """The forces of the batch's last converged reading (reported coordinates, as ``extra_starts`` takes them) as a
    (1, h) start; None if no reading converged."""
    ok = result.converged & (result.num_forces >= 1)
    if not bool(ok.any()):
        return None
    b = int(ok.nonzero()[-1])
    h = int(result.num_forces[b])
    s = result.forces.s[b : b + 1, :h].detach().to(torch.float64)  # sorted by s, padding last
    f = result.forces.f[b : b + 1, :h].detach().to(torch.float64)
    if not (bool(torch.isfinite(s).all()) and bool(torch.isfinite(f).all())):
        return None
    return PointForces(s, f)


def stream(
    estimator: Any,
    readings: Iterable[Reading | dict[str, Any]],
    options: StreamOptions = StreamOptions(),
    estimate_options: Any = None,
) -> Iterator[StreamResult]:
    """Estimate the forces of every reading of ``readings``, in order, in latency-bounded batches.

    Args:
        estimator: a :class:`torchrod.Estimator` (with its ``warm_start`` network, if any).
        readings: any iterable (possibly endless, possibly slow) of :class:`Reading` or dicts with the keys
            ``id``, ``curvature`` ((G, 2) [1/m]), optional ``t`` [s] and ``error``.
        options: batching (:class:`StreamOptions`).
        estimate_options: the :class:`torchrod.EstimatorOptions` of every batch (default: the estimator's).
    Yields:
        one :class:`StreamResult` per reading, in input order; an unusable reading gives an error result.
    Raises:
        whatever iterating ``readings`` raised (after the results of the readings before it);
        the ``KeyboardInterrupt`` (or subclass) after flushing, when interrupted (module docstring).
    """
    from ..estimate.options import EstimatorOptions

    if not isinstance(options, StreamOptions):
        raise TorchrodTypeError(f"options must be StreamOptions, got {type(options).__name__}")
    estimate = estimator.options if estimate_options is None else estimate_options
    if not isinstance(estimate, EstimatorOptions):
        raise TorchrodTypeError(f"estimate_options must be EstimatorOptions, got {type(estimate).__name__}")
    return _run(_Stream(estimator, readings, options, estimate), options)


def _run(state: _Stream, options: StreamOptions) -> Iterator[StreamResult]:
    if state.direct is None:
        state.thread.start()
    flight: collections.deque[_Slot] = collections.deque()  # batches taken from pending, not yet yielded
    try:
        interrupted: KeyboardInterrupt | None = None
        while True:
            try:
                results = state.step(flight)
            except KeyboardInterrupt as exc:
                interrupted = exc
                break
            if results is None:  # the end of the input
                break
            for k, r in enumerate(results):
                try:
                    yield r
                except KeyboardInterrupt as exc:
                    # Thrown in at a yield: hand out this batch's other results, then flush.
                    interrupted = exc
                    yield from results[k + 1 :]
                    break
            if interrupted is not None:
                break
        if interrupted is not None:
            # Flush: everything already taken from the source (a second interrupt is not caught), waiting neither
            # for the kernel cache's lock nor, at exit, for a compile.
            note_interrupt()
            state.drain()
            if state.compiling:
                # Solved as Python one at a time, a read-ahead of readings would take minutes: each is answered
                # unsolved, in order, at once, and said.
                yield from state.unsolved(flight)
                raise interrupted
            while flight:
                yield from state.take(flight)
            while state.pending:
                batch = state.pending[: state.batch_limit()]
                flight.append(_Slot(batch, results=state.solve(batch)))
                del state.pending[: len(batch)]
                yield from state.take(flight)
            raise interrupted
        if state.error is not None:
            raise state.error
    finally:
        state.close()


def warm_up(estimator: Any, device: str | torch.device = "cpu") -> None:
    """Estimate two simulated readings (one and two forces), and make the warm-start network's forward pass on
    ``device``, so that first-call costs (the kernels' compilation or loading, per-rod setup, the network's compiled
    pass or its trace on a GPU, lazy initialisation in torch) do not land on the first real readings' latency."""
    from ..model.body_frame import simulate

    rod = estimator.rod
    L = rod.length
    loads = PointForces.from_lists([[(0.6 * L, 0.3, 0.2)], [(0.4 * L, -0.2, 0.3), (0.8 * L, 0.2, 0.1)]])
    u = simulate(rod, loads).grating_curvature.to(device)
    estimator.estimate(u)
    ready = getattr(getattr(estimator, "warm_start", None), "ready", None)
    if callable(ready):
        ready(u.device, u.dtype)


# ---------------------------------------------------------------------------------------------------- statistics
class _Quantiles:
    """Quantiles of positive numbers in bounded memory: a log-spaced histogram (bins 1% wide from ``low`` to
    ``high``; values outside are clamped into the end bins), so a quantile is known to within 1%."""

    _RATIO = 1.01

    def __init__(self, low: float, high: float) -> None:
        self.low = low
        self.bins = [0] * (math.ceil(math.log(high / low) / math.log(self._RATIO)) + 1)
        self.count = 0

    def add(self, x: float) -> None:
        k = 0 if x <= self.low else int(math.log(x / self.low) / math.log(self._RATIO))
        self.bins[min(k, len(self.bins) - 1)] += 1
        self.count += 1

    def quantile(self, q: float) -> float:
        """The q-quantile (nearest rank), NaN without data."""
        if not self.count:
            return math.nan
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for k, n in enumerate(self.bins):
            seen += n
            if seen >= rank:
                return self.low * self._RATIO ** (k + 0.5)
        raise AssertionError("unreachable")  # pragma: no cover


class StreamStats:
    """Running statistics of a stream, in bounded memory (a fixed histogram per quantity).

    :meth:`add` each result (with the reading's true forces when known); then ``readings``, ``errors``,
    :meth:`latency` quantiles [s] (from the moment a reading was taken from the source to the end of its batch's
    solve), :meth:`solve_time` quantiles [s] (its batch's estimation alone), and against the truth
    ``count_accuracy``, :meth:`force_error` [N] and :meth:`location_error` [m] quantiles (forces paired in order of
    location, over readings whose count is right).

    Latency is what a live source sees: the batching wait, the queue in front of the reading, and the solve. When
    the input comes faster than it is solved (a file read all at once, a backlog) the queue dominates: every
    reading waits for all those before it, and the latency grows with the input's length; the solve time per
    reading is then the measure of the estimation's cost. :meth:`summary` says so when it happens.
    """

    def __init__(self) -> None:
        self.readings = 0
        self.errors = 0
        self.batches: float = 0
        self.busy = 0.0  # [s] total estimation time
        self._latency = _Quantiles(1e-6, 1e4)
        self._solve = _Quantiles(1e-7, 1e4)
        self.judged = 0  # readings with a truth
        self.right = 0  # ... whose count is right
        self._force = _Quantiles(1e-7, 1e3)
        self._location = _Quantiles(1e-9, 1e2)
        self.learned_noise: float | None = None  # the last sigma learned from the stream [1/m]
        self.learned_from: int | None = None  # the first reading (1-based) solved with a learned sigma
        self.statuses: dict[str, int] = {}  # readings per status (ok, misfit, ..., timeout)

    def add(self, result: StreamResult, truth: Sequence[tuple[float, float, float]] | None = None) -> None:
        """Count ``result``; ``truth``: the reading's true forces as (s [m], fx [N], fy [N]), any order."""
        self.readings += 1
        if not result.ok:
            self.errors += 1
            return
        status = result.record.get("status")
        if status is not None:
            self.statuses[status] = self.statuses.get(status, 0) + 1
        if "noise" in result.record:
            self.learned_noise = result.record["noise"]
            if self.learned_from is None:
                self.learned_from = self.readings
        self._latency.add(result.latency)
        self._solve.add(max(result.solve_time, 1e-7))
        self.busy += result.solve_time / max(1, result.batch)
        self.batches += 1.0 / max(1, result.batch)
        if truth is None:
            return
        self.judged += 1
        forces = result.record["forces"]
        if len(forces) != len(truth):
            return
        self.right += 1
        for est, (s, fx, fy) in zip(forces, sorted(truth), strict=False):
            self._force.add(math.hypot(est["fx"] - fx, est["fy"] - fy))
            self._location.add(abs(est["s"] - s))

    def latency(self, q: float) -> float:
        """The q-quantile of the latency [s] (class docstring)."""
        return self._latency.quantile(q)

    def solve_time(self, q: float) -> float:
        """The q-quantile of the solve time of the readings' batches [s]."""
        return self._solve.quantile(q)

    @property
    def count_accuracy(self) -> float:
        return self.right / self.judged if self.judged else math.nan

    def force_error(self, q: float = 0.5) -> float:
        return self._force.quantile(q)

    def location_error(self, q: float = 0.5) -> float:
        return self._location.quantile(q)

    def summary(self, elapsed: float | None = None) -> list[str]:
        """Short human-readable lines: readings, errors, readings/s (over ``elapsed`` [s]), latency, accuracy."""
        solved = self.readings - self.errors
        rate = f", {self.readings / elapsed:.0f} readings/s over {elapsed:.2f} s" if elapsed else ""
        lines = [f"{self.readings} readings, {self.errors} errors{rate}"]
        if solved:
            latency, solve = self.latency(0.5), self.solve_time(0.5)
            lines.append(
                f"latency median {1e3 * latency:.1f} ms, p99 {1e3 * self.latency(0.99):.1f} ms "
                "(reading taken to answer made); "
                f"solve time {1e3 * self.busy / max(self.batches, 1e-9):.1f} ms per batch of "
                f"{solved / max(self.batches, 1e-9):.0f} readings, {1e3 * self.busy / solved:.2f} ms per reading "
                f"(means over {max(1, round(self.batches))} batches)"
            )
            if latency > 2.0 * solve + 0.05:
                lines.append(
                    "latency includes queueing: the input came faster than it was solved (as when a file is read "
                    "at once), so readings waited behind earlier ones; the solve time per reading is the cost of "
                    "estimation, and a source no faster than the solver sees about a small batch's solve time plus "
                    "the batching wait"
                )
        if self.statuses:
            lines.append(
                "statuses: " + ", ".join(f"{name} {self.statuses[name]}" for name in STATUSES if name in self.statuses)
            )
        if self.learned_noise is not None:
            lines.append(
                f"noise learned from the stream: sigma {self.learned_noise:.4g} 1/m (last value), used from reading "
                f"{self.learned_from} on"
            )
        if self.judged:
            lines.append(
                f"against the truth ({self.judged} readings): count accuracy {100 * self.count_accuracy:.1f}%"
                + (
                    f"; right count: median force error {self.force_error():.4f} N, median location error "
                    f"{1e3 * self.location_error():.2f} mm"
                    if self.right
                    else ""
                )
            )
        return lines


def answer_each(
    estimator: Any,
    source: Iterable[Any],
    options: StreamOptions,
    emit: Callable[[StreamResult], None],
    written: Callable[[], int] = lambda: 0,
) -> KeyboardInterrupt | None:
    """:func:`stream` with every result handed to ``emit``, in order: the one loop that ``torchrod stream`` and
    ``torchrod estimate`` answer readings by. An interrupt (``KeyboardInterrupt``, or the CLI's ``Terminated``)
    that comes while ``emit`` runs is thrown into the stream, which flushes: every reading already read is still
    emitted. ``written`` counts what ``emit`` has written (a writer's lines): a result whose emit was interrupted
    is emitted again only if it wrote nothing. Returns the interrupt, or None."""
    results = cast("GeneratorType[StreamResult, None, None]", stream(estimator, source, options))  # (a generator)
    interrupted: KeyboardInterrupt | None = None
    current: StreamResult | None = None
    before = written()
    try:
        for current in results:
            emit(current)
            current = None
            before = written()
    except KeyboardInterrupt as exc:
        interrupted = exc
        try:
            if current is not None and written() == before:  # interrupted before it was written
                emit(current)
            if results.gi_frame is not None:  # interrupted here, not inside the stream: let it flush
                emit(results.throw(exc))
                for result in results:
                    emit(result)
        except (KeyboardInterrupt, StopIteration):
            pass
    finally:
        results.close()
    return interrupted
