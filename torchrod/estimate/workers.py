"""Every core for a batch: an :class:`~torchrod.estimate.estimator.Estimator` spread over worker processes.

The estimator runs on NumPy and spends most of its time in Python (a few hundred small array operations per
reading), so torch's intra-op threads do not speed it up and Python threads would share one interpreter lock;
processes do. :class:`ParallelEstimator` splits a batch of B readings into up to N contiguous chunks, solves N - 1
of them in worker processes and one in the calling process at the same time, and joins the answers in order.

- Small batches are not split (a chunk holds at least ``min_chunk`` readings): a single reading, or the small
  batches of a live stream, would pay the transfer and gain nothing.
- Workers are started with ``spawn`` (the callers run threads, with which ``fork`` is unsafe), lazily on the first
  batch big enough to split (:meth:`ParallelEstimator.warm` starts them early). Each receives the pickled estimator
  once (its warm-start network included), runs torch on one thread, ignores SIGINT (the caller handles Ctrl-C and
  flushes; a worker must keep solving for it) and estimates two readings to fill its first-call caches.
- A stream fed no faster than it is solved makes batches too small to split; :meth:`ParallelEstimator.submit`
  hands such a batch whole to an idle worker and returns at once (:func:`torchrod.io.stream.stream` does this with
  ``workers`` > 1). The first batch handed out starts one spare worker in a pool of its own, so that N processes
  give N workers to hand batches to while the calling process only reads and collects; a file, whose batches are
  split, never starts it (a pool of N workers would: it starts a worker for any chunk while none is idle).
- Nothing is lost: a chunk whose worker dies (or whose pool breaks) is solved in the calling process, and the pool
  is started afresh for the next batch (at most ``max_restarts`` times; then every batch runs in the calling
  process). An exception the estimator raises in a worker reaches the caller as the same exception type.
- A reading's answer depends on the batch it is solved in. A converged fit differs at the level of rounding (the
  batched search's shared steps: about 1e-12 relative in the loss and 1e-12 m in a location over 192 readings, with
  and without missing gratings); a fit that did not converge (status ``unconverged``) stops where its budget ran out,
  and rounding differences grow along its flat direction (1.2 um and 4e-8 relative in the loss, in one reading of
  24); ``evaluations`` counts batched steps and may differ too. A split batch therefore
  equals the in-process estimate of the same chunks bit for bit, and the whole batch's estimate to that level (the
  counts and verdicts agreed in every test; a reading at a near tie of two counts could differ).

Use it as the estimator it wraps (``estimate``; ``rod``, ``options`` and ``warm_start`` pass through, so
:func:`torchrod.io.stream.stream` takes it too), and close it (``close()`` or ``with``). A script that uses it must
guard its top level with ``if __name__ == "__main__":`` (``spawn`` imports the main module in each worker).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import gc
import multiprocessing
import os
import pickle
import signal
import tempfile
import time
import warnings
import weakref
from collections.abc import Mapping, Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np
import torch

from ..loads import PointForces
from .estimator import EstimateResult

__all__ = ["MIN_CHUNK", "ParallelEstimator", "Solving", "concat_results", "resolve_processes"]

MIN_CHUNK = 8
"""The fewest readings a chunk holds: a batch of fewer than 2 * MIN_CHUNK readings is solved in one process."""


def resolve_processes(processes: int) -> int:
    """The number of processes that ``processes`` asks for: itself if >= 1, one per CPU core (``os.cpu_count()``)
    for 0; ``ValueError`` for anything else."""
    if not isinstance(processes, int) or isinstance(processes, bool) or processes < 0:
        raise ValueError(f"processes must be an integer >= 1, or 0 for one per CPU core, got {processes!r}")
    return processes if processes else max(1, os.cpu_count() or 1)


def concat_results(results: Sequence[EstimateResult]) -> EstimateResult:
    """The results of consecutive batches as one, along the batch dimension (all with the same width W)."""
    if not results:
        raise ValueError("concat_results needs at least one result, got none")
    if len(results) == 1:
        return results[0]
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(EstimateResult):
        if f.name == "forces":
            parts = [r.forces for r in results]
            masks = None if all(p.mask is None for p in parts) else torch.cat([p.active for p in parts])
            fields["forces"] = PointForces(torch.cat([p.s for p in parts]), torch.cat([p.f for p in parts]), masks)
        else:
            fields[f.name] = torch.cat([getattr(r, f.name) for r in results])
    return EstimateResult(**fields)


# ---------------------------------------------------------------------------------------------------- transfer
# Tensors cross the process boundary as NumPy arrays: pickled by value (torch's own reduction would put every
# small tensor in a shared-memory file of its own), and converted back bit for bit.
def _array(x: torch.Tensor | None) -> np.ndarray | None:
    return None if x is None else x.detach().cpu().numpy()


def _tensor(x: np.ndarray | None) -> torch.Tensor | None:
    return None if x is None else torch.from_numpy(x)


def _pack_forces(pf: PointForces) -> tuple[Any, Any, Any]:
    return _array(pf.s), _array(pf.f), _array(pf.mask)


def _unpack_forces(packed: tuple[Any, Any, Any]) -> PointForces:
    s, f, mask = packed
    return PointForces(_tensor(s), _tensor(f), _tensor(mask))


def _pack_result(result: EstimateResult) -> dict[str, Any]:
    return {
        f.name: _pack_forces(result.forces) if f.name == "forces" else _array(getattr(result, f.name))
        for f in dataclasses.fields(EstimateResult)
    }


def _unpack_result(packed: Mapping[str, Any]) -> EstimateResult:
    return EstimateResult(
        **{k: _unpack_forces(v) if k == "forces" else _tensor(v) for k, v in packed.items()},
    )


# ---------------------------------------------------------------------------------------------------- the worker
_ESTIMATOR: Any = None  # in a worker: the estimator it was given

_IDLE_EXIT = 0.2
"""[s] how long :meth:`ParallelEstimator.close` waits for workers with nothing to do to exit by themselves before
it terminates them (an idle one exits in milliseconds; one still starting would take a second or more)."""


def _init_worker(payload: str | bytes, warm: bool) -> None:
    """A worker's start: one torch thread, SIGINT ignored (the caller handles Ctrl-C), the estimator (pickled in the
    file named ``payload``, or the pickle itself), a warm-up."""
    global _ESTIMATOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    if isinstance(payload, bytes):
        _ESTIMATOR = pickle.loads(payload)
    else:
        with open(payload, "rb") as file:
            _ESTIMATOR = pickle.load(file)
    if warm:
        from ..io.stream import warm_up

        warm_up(_ESTIMATOR)
    gc.freeze()  # what the worker is made of, out of the collector's full collections (cli.commands.settle)


def _ready() -> int:
    return os.getpid()


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except OSError:
        pass


def _solve_chunk(
    curvature: np.ndarray, mask: np.ndarray | None, starts: dict[int, Any] | None, overrides: dict[str, Any]
) -> dict[str, Any]:
    extra = None if starts is None else {h: _unpack_forces(p) for h, p in starts.items()}
    result = _ESTIMATOR.estimate(_tensor(curvature), _tensor(mask), extra_starts=extra, **overrides)
    return _pack_result(result)


def _running(processes: Sequence[Any], timeout: float | None) -> list[Any]:
    """The processes of ``processes`` still running after waiting up to ``timeout`` seconds (None: until all have
    exited) for them to exit. It waits on their sentinels, which does not reap them (see :func:`_end`)."""
    from multiprocessing.connection import wait

    pending = {p.sentinel: p for p in processes}
    deadline = None if timeout is None else time.monotonic() + timeout
    while pending:
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0.0:
            break
        for sentinel in wait(list(pending), left):
            del pending[sentinel]
    return list(pending.values())


def _end(processes: Sequence[Any], timeout: float = 1.0, grace: float = 0.0) -> None:
    """End worker processes: those still running ``grace`` seconds from now get SIGTERM, and SIGKILL ``timeout``
    seconds later; returns once every one has exited.

    Their exits are awaited on the processes' sentinels, never by joining them: the pool's manager thread joins
    (reaps) its workers itself, and two threads reaping one child race, the loser's ``multiprocessing`` then seeing
    the dead worker as running until the winner records its exit code. :meth:`ParallelEstimator.close` then waits
    for the manager threads."""
    left = _running(processes, grace)
    for p in left:
        p.terminate()
    left = _running(left, timeout)
    for p in left:
        p.kill()
    _running(left, None)


# ---------------------------------------------------------------------------------------------------- the wrapper
class ParallelEstimator:
    """An estimator whose batches are solved in ``processes`` processes at once (module docstring).

    Args:
        estimator: the :class:`~torchrod.estimate.estimator.Estimator` (picklable: its rod, options and warm-start
            network are; a warm start that is a local function or lambda is not).
        processes: N >= 1, the processes a batch is spread over, the calling one included (N - 1 workers); 1 runs
            every batch in the calling process, with no pool; 0: one per CPU core.
        min_chunk: the fewest readings per chunk.
        max_restarts: how often a broken pool is started afresh before every batch stays in the calling process.
        warm_workers: each worker estimates two simulated readings when it starts.
    Raises:
        ValueError: for a bad ``processes``, ``min_chunk`` or ``max_restarts``.
        TypeError: if ``processes`` > 1 and the estimator cannot be pickled.
    """

    def __init__(
        self,
        estimator: Any,
        processes: int = 2,
        *,
        min_chunk: int = MIN_CHUNK,
        max_restarts: int = 3,
        warm_workers: bool = True,
    ) -> None:
        self.processes = resolve_processes(processes)
        for name, value, low in (("min_chunk", min_chunk, 1), ("max_restarts", max_restarts, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if not callable(getattr(estimator, "estimate", None)):
            raise TypeError(f"estimator must have an estimate() method, got {type(estimator).__name__}")
        self.estimator = estimator
        self.min_chunk = min_chunk
        self.max_restarts = max_restarts
        self.restarts = 0  # pools found broken so far
        self._warm_workers = warm_workers
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._starting: list[concurrent.futures.Future] = []
        self._submitted: list[tuple[concurrent.futures.Future, Any]] = []  # (batch handed out by submit, its pool)
        self._spare: concurrent.futures.ProcessPoolExecutor | None = None  # one more worker, for submit() alone
        self._spare_ready: concurrent.futures.Future | None = None
        self._spawned: dict[int, Any] = {}  # every worker process a pool of this object started, by pid
        self._managers: list[Any] = []  # the manager threads of the pools stopped so far (they reap the workers)
        self._payload = b""
        self._payload_path: str | None = None
        self._chunks_out: list[concurrent.futures.Future] = []  # chunks handed to workers by estimate(), not done
        if self.processes > 1:
            try:
                self._payload = pickle.dumps(estimator)
            except Exception as exc:  # noqa: BLE001 - whatever pickling raises, the cause is the same
                raise TypeError(
                    f"the estimator cannot be sent to worker processes ({type(exc).__name__}: {exc}); use "
                    "processes=1, or a warm start that can be pickled (not a local function or lambda)"
                ) from exc

    # The wrapped estimator's attributes, so that the stream and warm_up take this object as an estimator.
    @property
    def rod(self) -> Any:
        return self.estimator.rod

    @property
    def options(self) -> Any:
        return self.estimator.options

    @property
    def warm_start(self) -> Any:
        return getattr(self.estimator, "warm_start", None)

    # ------------------------------------------------------------------ the pool
    @property
    def parallel(self) -> bool:
        """True while batches may go to workers (processes > 1 and the restarts not used up)."""
        return self.processes > 1 and self.restarts <= self.max_restarts

    def _new_pool(self, workers: int) -> tuple[concurrent.futures.ProcessPoolExecutor, list[concurrent.futures.Future]]:
        """A pool of ``workers`` workers, started now: one task per worker makes it start them all (it starts one
        per task while none is idle); the tasks' futures say when they are ready."""
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_worker,
            initargs=(self._payload_argument(), self._warm_workers),
        )
        starting = [pool.submit(_ready) for _ in range(workers)]
        self._spawned.update(getattr(pool, "_processes", None) or {})
        return pool, starting

    def _payload_argument(self) -> str | bytes:
        """The pickled estimator, in a private temporary file that each worker reads as it starts (removed when this
        object is collected, or at exit). Passed in the worker's start-up arguments instead, a payload of about a
        megabyte (a network's weights) overfilled the pipe that starts the process, and the caller's start of a
        worker waited until the new process had imported torch and read it: about a second, which the first
        batch a stream handed out waited too (docs/results.md, "Starting a worker without waiting for it"). Where
        no temporary file can be written, the pickle itself, as before."""
        if self._payload_path is None:
            try:
                fd, path = tempfile.mkstemp(prefix="torchrod-estimator-", suffix=".pickle")
            except OSError:
                return self._payload
            try:
                with os.fdopen(fd, "wb") as file:
                    file.write(self._payload)
            except OSError:
                _remove(path)
                return self._payload
            self._payload_path = path
            weakref.finalize(self, _remove, path)
        return self._payload_path

    def _ensure_pool(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool, self._starting = self._new_pool(self.processes - 1)
        return self._pool

    def warm(self, wait: bool = False, spare: bool = False) -> None:
        """Start the workers now instead of on the first batch big enough to split; ``spare``: the spare worker
        too, which :meth:`submit` otherwise starts with the first batch it hands out; ``wait``: until they are
        ready (each has imported torch, unpickled the estimator and warmed up: seconds). No effect with one
        process."""
        if not self.parallel:
            return
        try:
            self._ensure_pool()
            if spare and self._spare is None:
                self._spare, (self._spare_ready,) = self._new_pool(1)
            if wait:
                for future in [*self._starting, *([self._spare_ready] if spare else [])]:
                    future.result()
        except BrokenProcessPool:
            self._broken()

    def worker_pids(self) -> list[int]:
        """The process ids of the running workers, the spare's included ([] before the pool starts)."""
        pools = (self._pool, self._spare)
        processes = [p for pool in pools for p in list((getattr(pool, "_processes", None) or {}).values())]
        return [p.pid for p in processes if p.is_alive()]

    def _broken(self, pool: concurrent.futures.ProcessPoolExecutor | None = None) -> None:
        """Drop a broken pool, the main one or (``pool``) the spare (its chunks are solved here); the next batch
        starts a new one."""
        self.restarts += 1
        if pool is not None and pool is self._spare:
            self._spare, self._spare_ready = None, None
        else:
            pool, self._pool, self._starting = self._pool, None, []
        if pool is not None:
            self._stop(pool)
        if self.restarts > self.max_restarts:
            warnings.warn(
                f"the worker processes failed {self.restarts} times; solving in one process from now on",
                RuntimeWarning,
                stacklevel=3,
            )

    def _stop(self, pool: concurrent.futures.ProcessPoolExecutor, timeout: float = 1.0, grace: float = 1.0) -> None:
        """Shut ``pool`` down: idle workers exit at once, a worker still busy (on an abandoned chunk, after an
        interrupt, or starting) is given ``grace`` seconds, then terminated (SIGTERM), and killed (SIGKILL) if it is
        still there ``timeout`` seconds later: when this returns, no worker of ``pool`` is left running, and the
        pool's manager thread, which reaps them, is given ``timeout`` seconds to finish."""
        processes = list((getattr(pool, "_processes", None) or {}).values())
        manager = getattr(pool, "_executor_manager_thread", None)
        if manager is not None:
            self._managers.append(manager)
        pool.shutdown(wait=False, cancel_futures=True)
        _end(processes, timeout, grace=grace)
        if manager is not None:
            manager.join(timeout)

    def close(self) -> None:
        """Stop the workers (the object still estimates afterwards, starting a new pool if needed): the current
        pool's, and any worker of an earlier pool still running; then wait (a second at most) for the pools'
        manager threads, which reap them. A worker busy on a batch (abandoned after an interrupt) is given a second
        to finish; with none busy, a worker still starting (importing torch) is not waited for."""
        busy = any(not f.done() for f in [*self._chunks_out, *(f for f, _ in self._submitted)])
        pools = [self._pool, self._spare]
        self._pool, self._starting, self._spare, self._spare_ready, self._submitted = None, [], None, None, []
        self._chunks_out = []
        for pool in pools:
            if pool is not None:
                self._stop(pool, grace=1.0 if busy else _IDLE_EXIT)
        spawned, self._spawned = list(self._spawned.values()), {}
        _end(spawned)
        managers, self._managers = self._managers, []
        for manager in managers:
            manager.join(1.0)

    def __enter__(self) -> ParallelEstimator:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ estimation
    def _plan(self, B: int) -> list[tuple[int, int]]:
        """Contiguous [start, end) row ranges, as even as can be, each at least ``min_chunk`` rows."""
        n = max(1, min(self.processes, B // self.min_chunk))
        bounds = [k * B // n for k in range(n + 1)]
        return list(zip(bounds[:-1], bounds[1:], strict=True))

    def estimate(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor | None = None,
        *,
        extra_starts: Mapping[int, PointForces] | None = None,
        wait_for_workers: bool = True,
        **overrides: Any,
    ) -> EstimateResult:
        """:meth:`Estimator.estimate <torchrod.estimate.estimator.Estimator.estimate>` (same arguments: curvature
        (B, G, 2) [1/m], mask (B, G) bool or None, extra_starts {h: PointForces (B, h)} in reported coordinates,
        EstimatorOptions overrides), the B rows spread over the processes in contiguous chunks.

        ``wait_for_workers`` False: while the workers are still starting (:meth:`starting`: seconds), solve every
        chunk in this process instead of waiting for them; the same chunks, so the same answers. For a caller
        that sends batch after batch (``torchrod estimate`` on a file): its first batches do not wait, and the
        workers join once ready. One large batch is faster waited for.

        Returns:
            the :class:`EstimateResult` of the B readings, in order (the chunks' results joined).
        Raises:
            what the estimator raises, the same type whether it was raised here or in a worker (the first chunk's
            in row order, after every chunk is done). A batch the estimator would refuse as a whole (a bad shape,
            a reading with no grating) is passed to it whole, so it raises as it would in one process.
        """
        chunks = self._chunks(curvature, mask, extra_starts)
        if chunks is None:
            return self.estimator.estimate(curvature, mask, extra_starts=extra_starts, **overrides)
        futures: list[concurrent.futures.Future | None] = []
        try:
            self._hand_out(chunks[1:], overrides, futures, wait_for_workers)
            results: list[EstimateResult | None] = [None] * len(chunks)
            errors: list[BaseException | None] = [None] * len(chunks)
            results[0], errors[0] = self._here(chunks[0], overrides)
            broken = False
            for k, future in enumerate(futures, start=1):
                if future is not None:
                    try:
                        results[k] = _unpack_result(future.result())
                        continue
                    except BrokenProcessPool:
                        broken = True
                    except Exception as exc:  # noqa: BLE001 - raised below, in row order
                        errors[k] = exc
                        continue
                results[k], errors[k] = self._here(chunks[k], overrides)
            if broken:
                self._broken()
        except BaseException:  # an interrupt: what the workers still have to do is not wanted any more
            for future in futures:
                if future is not None:
                    future.cancel()
            raise
        for error in errors:
            if error is not None:
                raise error
        return concat_results(results)  # type: ignore[arg-type]

    def _hand_out(self, chunks: list[Any], overrides: dict[str, Any], futures: list[Any], wait: bool) -> None:
        """Hand ``chunks`` to the workers, appending to ``futures`` (as they go: an interrupt cancels those handed
        out) each chunk's future, or None for a chunk to solve here: every chunk while the workers are still
        starting, unless ``wait`` (:meth:`estimate`), or the rest when the pool is found broken."""
        if not wait and self.starting():
            futures += [None] * len(chunks)
            return
        try:
            pool = self._ensure_pool()
            for chunk in chunks:
                futures.append(pool.submit(_solve_chunk, *self._packed(chunk), overrides))
            self._chunks_out = [f for f in self._chunks_out if not f.done()] + [f for f in futures if f]
            self._spawned.update(getattr(pool, "_processes", None) or {})  # (a pool may start more on demand)
        except BrokenProcessPool:  # a worker died while idle: this batch's chunks are solved here
            self._broken()
            futures += [None] * (len(chunks) - len(futures))

    def starting(self) -> bool:
        """True while the workers are being started (each imports torch and warms up: seconds), when
        :meth:`estimate` would wait for them; with no pool running this starts one and says True. False with one
        process. A caller with work of its own, such as a stream, solves alone meanwhile rather than wait."""
        if not self.parallel:
            return False
        if self._pool is None:
            self.warm()
            return self._pool is not None
        return not all(f.done() for f in self._starting)

    def idle(self) -> bool:
        """True when a worker (the spare's included) is started, ready and solving no batch handed to it by
        :meth:`submit` (chunks of :meth:`estimate` are not counted: it waits for them before it returns). With no
        pool running (not started yet, or dropped when a worker died) this starts one, ready seconds later, and says
        False."""
        return self._idle_pool() is not None

    def _idle_pool(self) -> concurrent.futures.ProcessPoolExecutor | None:
        """:meth:`idle`'s answer as the pool whose worker is idle (:meth:`_free`), or None; starts the pool if
        none is running."""
        if not self.parallel:
            return None
        if self._pool is None:
            self.warm()
            return None
        return self._free()

    def full(self) -> bool:
        """True when every worker, the spare's included, is solving a batch handed to it by :meth:`submit`: a
        caller that only hands batches out should wait for one rather than solve beside them on their cores."""
        ready = self._spare_ready is not None and self._spare_ready.done()
        return self.parallel and self._pool is not None and ready and self._free() is None

    def _free(self) -> concurrent.futures.ProcessPoolExecutor | None:
        """A pool with a ready worker that :meth:`submit` has not handed a batch: the main pool first, or None."""
        self._submitted = [(f, pool) for f, pool in self._submitted if not f.done()]
        busy = [pool for _, pool in self._submitted]
        if all(f.done() for f in self._starting) and busy.count(self._pool) < self.processes - 1:
            return self._pool
        if self._spare is not None and self._spare_ready.done() and self._spare not in busy:
            return self._spare
        return None

    def submit(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor | None = None,
        *,
        extra_starts: Mapping[int, PointForces] | None = None,
        queue: bool = False,
        **overrides: Any,
    ) -> Solving:
        """Start :meth:`estimate` of a batch and return without waiting where a worker is :meth:`idle`: the batch
        goes to it whole. Otherwise (no idle worker, one process, a batch the workers should not take) the batch is
        estimated before this returns, split as :meth:`estimate` splits it.

        ``queue``: the batch goes whole to the workers (the main pool, not the spare, which this then does not
        start) even while they are busy, and waits there for one: for a caller that keeps them fed with a backlog.

        Returns:
            a :class:`Solving`: ``done()`` says whether the result is there, ``result()`` waits for it.
        """
        pool = self._pool if queue and self.parallel else self._idle_pool()
        chunks = self._chunks(curvature, mask, extra_starts, whole=True) if pool is not None else None
        if chunks:
            try:
                future = pool.submit(_solve_chunk, *self._packed(chunks[0]), overrides)
                self._submitted.append((future, pool))
                if self._spare is None and not queue:  # the first batch handed out: the spare worker starts
                    self._spare, (self._spare_ready,) = self._new_pool(1)
                return Solving(self, chunks[0], overrides, future, pool)
            except BrokenProcessPool:
                self._broken(pool)
        solving = Solving(self, (curvature, mask, extra_starts), overrides)
        try:
            solving._value = self.estimate(curvature, mask, extra_starts=extra_starts, **overrides)
        except Exception as exc:  # noqa: BLE001 - raised by result(), as from a worker
            solving._error = exc
        return solving

    def _chunks(
        self, curvature: Any, mask: Any, extra_starts: Any, whole: bool = False
    ) -> list[tuple[Any, Any, Any]] | None:
        """The batch's chunks as (curvature, mask, extra_starts) each (``whole``: one chunk of every row), or None
        to solve it whole here: one process, too few readings to split, a device other than the CPU, or anything
        the estimator should judge whole."""
        if not self.parallel or not isinstance(curvature, torch.Tensor) or curvature.dim() != 3:
            return None
        B = curvature.shape[0]
        plan = [(0, B)] if whole else self._plan(B)
        if (len(plan) < 2 and not whole) or curvature.device.type != "cpu":
            return None
        if mask is not None:
            if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != curvature.shape[:2]:
                return None
            if not bool(mask.any(dim=1).all()):  # a reading with no grating: the estimator's error names its row
                return None
        elif bool(torch.isnan(curvature).all(-1).all(-1).any()):
            return None
        starts = dict(extra_starts) if extra_starts else {}
        for pf in starts.values():
            if not isinstance(pf, PointForces) or pf.s.shape[0] != B or pf.device.type != "cpu":
                return None
        return [
            (
                curvature[a:b],
                None if mask is None else mask[a:b],
                {
                    h: PointForces(pf.s[a:b], pf.f[a:b], None if pf.mask is None else pf.mask[a:b])
                    for h, pf in starts.items()
                }
                or None,
            )
            for a, b in plan
        ]

    @staticmethod
    def _packed(chunk: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
        curvature, mask, starts = chunk
        packed = None if starts is None else {h: _pack_forces(pf) for h, pf in starts.items()}
        return _array(curvature), _array(mask), packed

    def _here(
        self, chunk: tuple[Any, Any, Any], overrides: dict[str, Any]
    ) -> tuple[EstimateResult | None, Exception | None]:
        """Solve a chunk in the calling process: (result, None), or (None, the exception)."""
        curvature, mask, starts = chunk
        try:
            return self.estimator.estimate(curvature, mask, extra_starts=starts, **overrides), None
        except Exception as exc:  # noqa: BLE001 - raised by estimate(), in row order
            return None, exc


class Solving:
    """A batch handed to :meth:`ParallelEstimator.submit`: being estimated in a worker, or already estimated.

    ``done()`` says, without waiting, whether :meth:`result` would return at once. Should the worker die, the batch
    is estimated in the calling process when :meth:`result` is asked for (nothing is lost), and the pool is started
    afresh for later batches, as :meth:`ParallelEstimator.estimate` does.
    """

    def __init__(
        self,
        owner: ParallelEstimator,
        chunk: tuple[Any, Any, Any],
        overrides: dict[str, Any],
        future: concurrent.futures.Future | None = None,
        pool: concurrent.futures.ProcessPoolExecutor | None = None,
    ) -> None:
        self._owner, self._chunk, self._overrides = owner, chunk, overrides
        self._future, self._pool = future, pool
        self._value: EstimateResult | None = None
        self._error: Exception | None = None

    def done(self) -> bool:
        return self._future is None or self._future.done()

    def add_done_callback(self, callback: Any) -> None:
        """Call ``callback()`` (from another thread, or at once if done) when the result is there."""
        if self._future is None:
            callback()
        else:
            self._future.add_done_callback(lambda _future: callback())

    def result(self) -> EstimateResult:
        """The batch's :class:`EstimateResult` (waiting for the worker); raises what the estimator raised."""
        if self._future is not None:
            try:
                self._value = _unpack_result(self._future.result())
            except BrokenProcessPool:
                if self._pool in (self._owner._pool, self._owner._spare):  # (not dropped yet for another batch)
                    self._owner._broken(self._pool)
                self._value, self._error = self._owner._here(self._chunk, self._overrides)
            except Exception as exc:  # noqa: BLE001 - raised below, as estimate() would
                self._error = exc
            self._future = None  # (only once the outcome is known: an interrupt while waiting keeps it)
        if self._error is not None:
            raise self._error
        assert self._value is not None
        return self._value
