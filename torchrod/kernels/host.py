"""The host's side of the kernels: the records, the model and the count tests' tables of an estimator, and the walk
of a batch over CPU threads or GPU threads.

Nothing here is numerical beyond setting up: the answers come from the kernels (:mod:`.search`). The count tests'
quantiles are made once here (SciPy), so that the kernels compute no special functions.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from .counts import MISFIT_FACTOR
from .layout import KINDS, OPTIONS, ROD, Arenas, Batch, Outputs, Setup, Sizes, allocate, constants, layout, record

__all__ = ["Plan", "chi2_quantile", "count_tables", "f_quantile", "options_record", "rod_setup", "setup_of"]


@functools.lru_cache(maxsize=8192)
def chi2_quantile(p: float, dof: int) -> float:
    """The p-quantile of the chi-square law with ``dof`` degrees of freedom (inf for dof <= 0)."""
    if dof <= 0:
        return math.inf
    from scipy import special

    return float(special.chdtri(dof, 1.0 - p))


@functools.lru_cache(maxsize=8192)
def f_quantile(p: float, d1: int, d2: int) -> float:
    """The p-quantile of Fisher's F law with (d1, d2) degrees of freedom."""
    from scipy import special

    return float(special.fdtri(d1, max(d2, 1), p))


@functools.lru_cache(maxsize=64)
def _count_tables(
    num_gratings: int, max_forces: int, significance: float, suspect: float, kink_suspect: float, misfit_level: float
) -> tuple[tuple[str, np.ndarray], ...]:
    a = significance / max(1, num_gratings)
    K = max_forces + 2
    D = 2 * num_gratings + 1
    guard_p = 1.0 - significance / MISFIT_FACTOR
    drop_chi2 = np.array([math.inf] + [chi2_quantile(1.0 - a, 3 * k) for k in range(1, K)])
    drop_f = np.full((K, D), math.inf)
    for k in range(1, K):
        for d in range(D):
            drop_f[k, d] = 3 * k * f_quantile(1.0 - a, 3 * k, max(d, 1))

    def by_dof(p: float, at_zero: float) -> np.ndarray:
        return np.array([at_zero] + [chi2_quantile(p, d) for d in range(1, D)])

    return (
        ("tables_drop_chi2", drop_chi2),
        ("tables_drop_f", drop_f),
        ("tables_misfit", by_dof(guard_p, -1.0)),
        ("tables_guard", by_dof(guard_p, math.inf)),
        ("tables_suspect", by_dof(suspect, math.inf)),
        ("tables_kink", by_dof(kink_suspect, math.inf)),
        ("tables_verdict", by_dof(1.0 - misfit_level, math.inf)),
    )


def count_tables(
    num_gratings: int, max_forces: int, significance: float, suspect: float, kink_suspect: float, misfit_level: float
) -> dict[str, np.ndarray]:
    """The quantiles of the count tests and the search (the ``tables`` group of :data:`.counts.COUNTS_PARTS`) for a
    rod of ``num_gratings`` gratings and counts up to ``max_forces``: the drop limits at ``significance /
    num_gratings`` (Bonferroni over the intervals), the misfit guard at ``significance / MISFIT_FACTOR``, the
    ``suspect`` and ``kink_suspect`` quantiles, and the verdict's at ``1 - misfit_level``; by degrees of freedom
    0..2G."""
    return dict(_count_tables(num_gratings, max_forces, significance, suspect, kink_suspect, misfit_level))


def rod_setup(
    *,
    length: float,
    ei: float,
    gj: float,
    bias: float,
    gratings: Sequence[float],
    segments: Sequence[tuple[float, float, float, float]],
    breakpoints: Sequence[float],
    step_angle: float,
    max_steps: int,
    exact_angle: float,
    exact_max_steps: int,
    method: Any,
) -> tuple[np.recarray, dict[str, np.ndarray]]:
    """The :data:`.layout.ROD` record and the parts of the ``model`` group of :data:`.march.MARCH_PARTS` of a rod (SI
    units): ``segments`` its intrinsic curvature (from, to, u*_x, u*_y), ``breakpoints`` where u* may jump,
    ``method`` the exact model's tableau (c, a, bp, bv, as :class:`torchrod.model.nystrom.Tableau` holds them)."""
    extra = np.array([0.0, *breakpoints], np.float64)
    rod = record(
        ROD,
        length=length,
        ei=ei,
        gj=gj,
        force_unit=ei / (length * length),
        bias=bias,
        num_gratings=len(gratings),
        precurved=len(segments) > 0,
        nseg=len(segments),
        nextra=extra.shape[0],
        step_angle=step_angle,
        max_steps=max_steps,
        exact_angle=exact_angle,
        exact_max_steps=exact_max_steps,
    )
    seg = np.zeros((max(len(segments), 1), 4))
    for i, row in enumerate(segments):
        seg[i] = row
    return rod, {
        "model_query": np.asarray(gratings, np.float64),
        "model_tab_c": np.asarray(method.c, np.float64),
        "model_tab_a": np.asarray(method.matrix(), np.float64),
        "model_tab_bp": np.asarray(method.bp, np.float64),
        "model_tab_bv": np.asarray(method.bv, np.float64),
        "model_segments": seg,
        "model_extra": extra,
    }


def options_record(**values: Any) -> np.recarray:
    """The :data:`.layout.OPTIONS` record from its fields, every one given (:func:`.layout.record`)."""
    return record(OPTIONS, **values)


def setup_of(
    rod: np.recarray, model: dict, opt: np.recarray, tables: dict, guess_counts: Sequence[int]
) -> tuple[Setup, Sizes]:
    """The batch's :class:`.layout.Setup` and its arenas' :class:`.layout.Sizes`: the records, the constants' arena
    holding ``model`` and ``tables``, and the counts of the guess blocks."""
    counts = [int(h) for h in guess_counts]
    o, r = opt[0], rod[0]
    z = Sizes(
        G=int(r.num_gratings),
        H=int(o.max_forces),
        starts=int(o.starts),
        per_interval=int(o.per_interval),
        exchange_top=int(o.exchange_top),
        guess_rows=max([counts.count(h) for h in set(counts)] + [0]),
        stages=int(np.asarray(model["model_tab_c"]).shape[0]),
        nseg=int(r.nseg),
        nextra=int(r.nextra),
    )
    lay, _ = layout(z)
    const = constants(lay, {**model, **tables})
    return Setup(rod, opt, lay, const, np.asarray(counts, np.int64).reshape(-1)), z


def outputs(B: int, W: int, empty: Any = np.empty) -> Outputs:
    """The outputs of B readings of result width W, made by ``empty(shape, dtype)``."""
    return Outputs(
        count=empty((B,), np.int64),
        s=empty((B, W), np.float64),
        f=empty((B, W, 2), np.float64),
        std=empty((B, W, 3), np.float64),
        loss=empty((B,), np.float64),
        converged=empty((B,), np.bool_),
        iterations=empty((B,), np.int64),
        poorly=empty((B,), np.bool_),
        losses=empty((B, W + 1), np.float64),
        sigma=empty((B,), np.float64),
        evaluations=empty((B,), np.int64),
        cut=empty((B,), np.bool_),
        p_value=empty((B,), np.float64),
        status=empty((B,), np.int64),
    )


SCHEDULE_PYTHON_ROWS = 64
"""A simulator batch of at most this many rows takes its schedule from the kernel source run as Python (no compiled
code to load); a larger one from the compiled schedule. Both give the same step counts."""


def schedule_rows(
    query: np.ndarray, s: np.ndarray, f: np.ndarray, ei: np.ndarray, length: float, step_angle: float, max_steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's events (B, E) (:func:`torchrod.kernels.march.schedule` with the rigorous rule: an index < h
    a force, ``h + q`` query q; tip to base) and the steps on each segment (B, E), for forces s (B, h) [m],
    f (B, h, 2) [N] at the queries (Q,) [m] of rods of stiffness ei (B,) [N m^2]."""
    from . import march, targets

    s = np.ascontiguousarray(s, np.float64)
    B, h = s.shape
    E = h + query.shape[0]
    order, seg, steps = np.empty((B, E), np.int64), np.empty((B, E)), np.empty((B, E), np.int64)
    args = (np.ascontiguousarray(query, np.float64), s, np.ascontiguousarray(f, np.float64),
            np.ascontiguousarray(ei, np.float64), float(length), float(step_angle), int(max_steps), order, seg, steps,
            np.empty(max(h, 1), np.complex128), np.empty(max(h, 1)))  # fmt: skip
    if B <= SCHEDULE_PYTHON_ROWS:
        march.schedule_rows(*args)
    else:
        compiled = targets.cpu_schedule()
        compiled.ready()
        compiled.entry(*args)
    return order, steps


NETWORK_BLOCK = 16
"""Readings that go through the network's layers together (each layer's weights read once for all of them)."""


def network_rows(
    u: np.ndarray,
    present: np.ndarray,
    length: float,
    force_si: float,
    net: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int],
    max_forces: int,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The warm-start network's guesses (:func:`.network.network_rows`) for readings u (B, G, 2) [1/m] with
    ``present`` (B, G) on a rod of ``length`` [m] with EI / L^2 = ``force_si`` [N]: the count probabilities (B, H),
    the locations (B, H, H) [m] and forces (B, H, H, 2) [N] of each count h in ``[:, h - 1, :h]``. ``net``: the
    packed network (params, layers, scales, stencil as the module's docstring says, and the widest layer).
    ``compiled`` False: the kernel source run as Python (debugging, tests)."""
    from . import network, targets

    params, layers, scales, stencil, widest = net
    B, G = present.shape
    H = int(max_forces)
    probs, s, f = np.empty((B, H)), np.empty((B, H, H)), np.empty((B, H, H, 2))
    R = max(1, min(B, NETWORK_BLOCK))
    args = (np.ascontiguousarray(u, np.float64), np.ascontiguousarray(present, np.bool_), float(length),
            float(force_si), params, layers, H, scales, stencil, probs, s, f, np.empty((G, 2)), np.empty((R, 4)),
            np.empty((R, widest), np.float32), np.empty((R, widest), np.float32))  # fmt: skip
    if compiled:
        entry = targets.cpu_network()
        entry.ready()
        entry.entry(*args)
    else:
        network.network_rows(*args)
    return probs, s, f


def kit(setup: Setup, sizes: Sizes, u: np.ndarray, w: np.ndarray, noise2: float = -1.0) -> Any:
    """A :class:`.layout.Kit` of one reading (u (2G,) [1/m], w (2G,) 1.0 where present, noise2 sigma^2 + floor^2
    [1/m^2] or -1: unknown) on fresh scratch, its intervals prepared: for calling kernel functions one by one, as
    Python (debugging, tests)."""
    from .layout import Kit
    from .search import prepare

    a = allocate(sizes)
    u, w = np.ascontiguousarray(u, np.float64), np.ascontiguousarray(w, np.float64)
    flag = np.zeros(1, np.int64)
    k = Kit(setup.rod[0], setup.opt[0], setup.lay[0], a.info, setup.const, a.f, a.i, a.c, a.b, u, w, flag)
    prepare(k, float(noise2))
    return k


_local = threading.local()

_AS_PYTHON = threading.Lock()
"""Held by the thread solving a batch by the kernels run as Python while the CPU kernels compile
(:meth:`Plan.run`): such a solve holds the interpreter lock throughout, so two threads solving side by side gain
nothing, and each reading's solve would take several times its own cost (a stream's solve times would say so)."""


def targets_python() -> Any:
    """The kernels as written (:func:`.targets.python`)."""
    from . import targets

    return targets.python()


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="torchrod-kernel")


def cpu_threads(threads: int | None) -> int:
    """The CPU threads a batch runs on: ``threads``, or every core for None."""
    return max(1, threads if threads is not None else _cores())


@functools.cache
def _cores() -> int:
    """The machine's cores (asked once: the system call costs as much as a small batch's bookkeeping)."""
    return os.cpu_count() or 1


class Plan:
    """A batch's walk through the kernels of one target (:mod:`.targets`): per reading, ``estimate_one``."""

    def __init__(self, target: str, setup: Setup, sizes: Sizes) -> None:
        from . import targets

        self.target = target
        self.compiled = targets.get(target)
        self.setup = setup
        self.sizes = sizes
        self._cuda_lock = threading.Lock()
        self._cuda: dict[int, tuple[Setup, Arenas, int]] = {}

    def _work(self) -> Arenas:
        """This thread's scratch for these sizes (made once per thread, reused)."""
        cache = getattr(_local, "work", None)
        if cache is None:
            cache = _local.work = {}
        if self.sizes not in cache:
            cache[self.sizes] = allocate(self.sizes)
        return cache[self.sizes]

    def run(self, batch: Batch, flag: np.ndarray, threads: int | None = None, device: int = 0) -> None:
        """Estimate every reading of ``batch`` into its outputs (CPU and Python: NumPy arrays; CUDA: arrays on GPU
        ``device``). ``flag`` (1,) int64: set it non-zero (from another thread) to stop every search where it
        stands; ``threads``: CPU threads (None: every core)."""
        B = batch.u.shape[0]
        first = 0
        if self.compiled.compiling():  # (a first CPU compile in the background: targets.Compiled.start)
            python = targets_python()
            never = np.zeros(1, np.int64)  # no deadline: the answer is the compiled kernels'
            with _AS_PYTHON:  # (one batch at a time: the batches are solved in turn, each at full speed)
                while first < B and self.compiled.compiling():
                    python.entry(first, first + 1, self.setup, batch, self._work(), never)
                    first += 1
            if first == B:
                return
        self.compiled.ready()
        if self.target == "cuda":
            self._run_cuda(batch, flag, device)
            return
        entry = self.compiled.entry
        workers = 1 if self.target == "python" else min(cpu_threads(threads), B - first)
        if workers <= 1:
            entry(first, B, self.setup, batch, self._work(), flag)
            return
        # Readings differ in cost (a hard one can take many times an easy one's time): small chunks taken in turn.
        chunk = max(1, (B - first) // (4 * workers))
        lock = threading.Lock()
        state = [first]

        def worker() -> None:
            work = self._work()
            while True:
                with lock:
                    first = state[0]
                    state[0] = min(B, first + chunk)
                if first >= B:
                    return
                entry(first, min(B, first + chunk), self.setup, batch, work, flag)

        futures = [_pool(_cores()).submit(worker) for _ in range(workers - 1)]
        try:
            worker()
        finally:
            for f in futures:
                f.result()

    launch_limit: int | None = None
    """The most readings one CUDA launch takes (None: as many as a quarter of the free GPU memory holds scratch
    for); a batch beyond it runs in several launches."""

    CUDA_THREADS = 64
    """GPU threads per block: one reading each."""

    def _run_cuda(self, batch: Batch, flag: Any, device: int) -> None:
        from numba import cuda

        B = batch.u.shape[0]
        _, lengths = layout(self.sizes)
        per_reading = sum(lengths[kind] * np.dtype(KINDS[kind]).itemsize for kind in "ficb")
        context = contextlib.nullcontext() if simulated() else cuda.gpus[device]
        with self._cuda_lock, context:  # (one batch at a time on the kept scratch)
            try:
                free, _ = cuda.current_context().get_memory_info()
            except (AttributeError, NotImplementedError):  # numba-cuda's simulator: no device memory to measure
                free = 4 * B * per_reading
            chunk = int(max(1, min(B, (free // 4) // max(per_reading, 1))))
            if self.launch_limit is not None:
                chunk = min(chunk, self.launch_limit)
            setup, arenas = self._cuda_scratch(device, chunk)
            threads = self.CUDA_THREADS
            for offset in range(0, B, chunk):
                count = min(chunk, B - offset)
                blocks = (count + threads - 1) // threads
                self.compiled.entry[blocks, threads](setup, batch, arenas, flag, offset, count)
            cuda.synchronize()

    def _cuda_scratch(self, device: int, chunk: int) -> tuple[Setup, Arenas]:
        """The setup copied to GPU ``device`` and scratch for at least ``chunk`` readings there, made once and kept
        (grown when a launch needs more)."""
        kept = self._cuda.get(device)
        if kept is None or kept[2] < chunk:
            self._cuda.pop(device, None)  # (the old scratch freed before the new is made)
            kept = (_device_setup(self.setup), allocate(self.sizes, (chunk,), empty=_device_empty), chunk)
            self._cuda[device] = kept
        return kept[0], kept[1]


def simulated() -> bool:
    """Whether numba-cuda's simulator stands in for a GPU (``NUMBA_ENABLE_CUDASIM=1``): the CUDA kernels then run on
    the CPU, on host arrays (tests of the CUDA target without a GPU)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") == "1"


def _device_empty(shape: tuple, dtype: Any) -> Any:
    """A GPU array (host arrays under the simulator, records readable by name there as on the GPU)."""
    if simulated():
        out = np.empty(shape, dtype)
        return out.view(np.recarray) if out.dtype.names else out
    from numba import cuda

    return cuda.device_array(shape, dtype)


def _device_setup(setup: Setup) -> Setup:
    """The setup's arrays copied to the GPU (small; as they are under the simulator)."""
    if simulated():
        return setup
    from numba import cuda

    return Setup(*(cuda.to_device(np.ascontiguousarray(v)) for v in setup))
