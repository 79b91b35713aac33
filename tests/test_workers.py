"""Batches spread over worker processes (:mod:`torchrod.estimate.workers`): the same answers as one process, extra
starts split with their rows, no reading lost when a worker dies, estimator errors raised as themselves, the stream
and the CLI with ``--workers``, and the flush after Ctrl-C with workers running."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
import warnings

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.estimate.workers import ParallelEstimator, concat_results, resolve_processes
from torchrod.io.stream import Reading, StreamOptions, stream
from torchrod.learn.synthetic import SensorModel, generate_trajectory

NOISE = 0.1


def _trajectory(count: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor, list[list[tuple[float, ...]]]]:
    """(T, G, 2) curvature [1/m], (T, G) mask (5% of gratings missing) and the true forces of a synthetic stream."""
    rod = tr.presets.nitinol290()
    sensor = SensorModel(noise=NOISE, missing_prob=0.05)
    traj = generate_trajectory(rod, count, rate=100.0, sensor=sensor, seed=seed)
    truth = [[(f["s"], f["fx"], f["fy"]) for f in t["forces"]] for t in traj.truth]
    return traj.curvature, traj.mask, truth


def _items(u: torch.Tensor, m: torch.Tensor) -> list[Reading]:
    """The readings of a trajectory as stream items: id k, a row of NaN at each missing grating."""
    return [Reading(k, torch.where(m[k].unsqueeze(-1), u[k], math.nan)) for k in range(u.shape[0])]


def _json_rows(u: torch.Tensor, m: torch.Tensor) -> list[list]:
    """Readings as JSON lists: [ux, uy] per grating, None for a missing one."""
    return [
        [pair if ok else None for pair, ok in zip(r, k, strict=True)]
        for r, k in zip(u.tolist(), m.tolist(), strict=True)
    ]


def _assert_identical(a: tr.EstimateResult, b: tr.EstimateResult) -> None:
    """Every field equal bit for bit (NaN where the other has NaN)."""
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        pairs = [(x.s, y.s), (x.f, y.f), (x.active, y.active)] if field.name == "forces" else [(x, y)]
        for p, q in pairs:
            assert p.dtype == q.dtype and p.shape == q.shape, field.name
            assert (
                torch.equal(p, q) or torch.equal(p.isnan(), q.isnan()) and torch.equal(p.nan_to_num(), q.nan_to_num())
            )


def _assert_close(a: tr.EstimateResult, b: tr.EstimateResult) -> None:
    """The same counts and verdicts; a converged fit's numbers equal to rounding, an unconverged one's loss to 1e-6
    (a reading's answer depends on its batch: module docstring of torchrod.estimate.workers)."""
    assert torch.equal(a.num_forces, b.num_forces) and torch.equal(a.status, b.status)
    assert torch.equal(a.forces.active, b.forces.active) and torch.equal(a.converged, b.converged)
    c = a.converged
    torch.testing.assert_close(a.forces.s[c], b.forces.s[c], rtol=0, atol=1e-9)
    torch.testing.assert_close(a.forces.f[c], b.forces.f[c], rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(a.loss[c], b.loss[c], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(a.loss, b.loss, rtol=1e-6, atol=1e-12)


@pytest.fixture(scope="module")
def estimator() -> tr.Estimator:
    return tr.Estimator(tr.presets.nitinol290(), tr.EstimatorOptions(noise=NOISE))


@pytest.fixture(scope="module")
def parallel(estimator):
    """Two processes, started once for the module's tests that leave the pool whole."""
    with ParallelEstimator(estimator, 2) as par:
        par.warm(wait=True)
        yield par


# ---------------------------------------------------------------------------------------------------- the API
def test_two_processes_give_the_in_process_answers(estimator, parallel):
    u, m, _ = _trajectory(24)
    got = parallel.estimate(u, m)
    assert parallel.worker_pids() and parallel.restarts == 0
    # The same chunks (rows 0-11 and 12-23) in this process: bit for bit.
    _assert_identical(got, concat_results([estimator.estimate(u[:12], m[:12]), estimator.estimate(u[12:], m[12:])]))
    # The whole batch in one call: the same to rounding.
    _assert_close(got, estimator.estimate(u, m))
    # Overrides reach the workers; float32 readings come back as float32.
    got = parallel.estimate(u.float(), m, max_forces=1)
    assert got.loss.dtype == torch.float32 and int(got.num_forces.max()) <= 1
    _assert_identical(
        got, concat_results([estimator.estimate(u[a:b].float(), m[a:b], max_forces=1) for a, b in ((0, 12), (12, 24))])
    )


def test_chunks_are_solved_here_while_the_workers_start_if_asked(estimator):
    """``wait_for_workers=False`` (``torchrod estimate``): a batch that comes while the workers are still starting
    (seconds) is solved in this process in the same chunks, so with the same answers bit for bit; it starts the pool
    and hands nothing to it. By default the call waits for the workers, which then solve their chunks."""
    u, m, _ = _trajectory(16)
    expected = concat_results([estimator.estimate(u[:8], m[:8]), estimator.estimate(u[8:], m[8:])])
    with ParallelEstimator(estimator, 2) as par:
        _assert_identical(par.estimate(u, m, wait_for_workers=False), expected)
        assert par._pool is not None and par._chunks_out == [] and par.starting()
        _assert_identical(par.estimate(u, m), expected)  # waits for the worker
        assert len(par._chunks_out) == 1 and not par.starting()


def test_small_batches_stay_in_process(estimator):
    u, m, _ = _trajectory(15)
    par = ParallelEstimator(estimator, 2)
    _assert_identical(par.estimate(u, m), estimator.estimate(u, m))
    assert par._pool is None  # 15 readings: no chunk of 8 for a second process, so no pool was started
    assert not ParallelEstimator(estimator, 1).starting()  # one process: nothing ever starts
    assert par._plan(16) == [(0, 8), (8, 16)] and par._plan(101) == [(0, 50), (50, 101)]
    assert ParallelEstimator(estimator, 3)._plan(24) == [(0, 8), (8, 16), (16, 24)]


def test_extra_starts_are_split_with_their_rows(estimator, parallel):
    """One force fitted with no scan (starts=0): the fit starts only from the extra start, each reading's own
    strongest true force, distinct per row. A chunk given another chunk's starts would fit other answers."""
    u, m, truth = _trajectory(24, seed=2)
    strongest = [max(t, key=lambda x: math.hypot(x[1], x[2])) if t else (0.1, 0.0, 0.0) for t in truth]
    s = torch.tensor([[x[0]] for x in strongest], dtype=u.dtype)
    f = torch.tensor([[[x[1], x[2]]] for x in strongest], dtype=u.dtype)
    fixed = dict(num_forces=1, starts=0)
    got = parallel.estimate(u, m, extra_starts={1: tr.PointForces(s, f)}, **fixed)
    chunks = [
        estimator.estimate(u[a:b], m[a:b], extra_starts={1: tr.PointForces(s[a:b], f[a:b])}, **fixed)
        for a, b in ((0, 12), (12, 24))
    ]
    _assert_identical(got, concat_results(chunks))
    _assert_close(got, estimator.estimate(u, m, extra_starts={1: tr.PointForces(s, f)}, **fixed))
    # Starts of the wrong batch size are the estimator's to refuse, with its own message.
    with pytest.raises(ValueError, match="shape"):
        parallel.estimate(u, m, extra_starts={1: tr.PointForces(s[:5], f[:5])})


def test_an_estimator_with_the_shipped_network_pickles_and_splits():
    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT, WarmStart

    if not os.path.exists(SHIPPED_CHECKPOINT):
        pytest.skip("no shipped checkpoint")
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE), warm_start=WarmStart.load(SHIPPED_CHECKPOINT, rod))
    again = pickle.loads(pickle.dumps(est))
    u, m, _ = _trajectory(16, seed=3)
    assert torch.equal(again.warm_start.guess(u, m).forces[2].s, est.warm_start.guess(u, m).forces[2].s)
    with ParallelEstimator(est, 2) as par:
        got = par.estimate(u, m)
        assert par.restarts == 0
    _assert_identical(got, concat_results([est.estimate(u[:8], m[:8]), est.estimate(u[8:], m[8:])]))


def test_workers_read_the_estimator_from_a_private_file_removed_with_its_owner():
    """A worker's start-up arguments stay small: a pickled network (about a megabyte) in them overfills the pipe that
    starts the process, and the caller then waits about a second for the child to import torch and read it. The
    estimator goes through a temporary file instead, readable by its owner only, which the workers read, and which
    goes when the :class:`ParallelEstimator` does."""
    import gc

    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT, WarmStart

    if not os.path.exists(SHIPPED_CHECKPOINT):
        pytest.skip("no shipped checkpoint")
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE), warm_start=WarmStart.load(SHIPPED_CHECKPOINT, rod))
    u, m, _ = _trajectory(16, seed=4)
    par = ParallelEstimator(est, 2)
    assert par.starting() and par._pool is not None  # asked with no pool: it starts one
    par.warm(wait=True)
    assert not par.starting()
    path = par._payload_argument()
    assert len(par._payload) > 2**16  # more than a pipe holds
    assert os.stat(path).st_mode & 0o077 == 0
    assert len(pickle.dumps(par._pool._initargs)) < 2**12  # the pool's own record of what each worker gets
    with open(path, "rb") as file:
        again = pickle.load(file)
    assert torch.equal(again.warm_start.guess(u, m).forces[2].s, est.warm_start.guess(u, m).forces[2].s)
    got = par.estimate(u, m)
    _assert_identical(got, concat_results([est.estimate(u[:8], m[:8]), est.estimate(u[8:], m[8:])]))
    par.close()
    assert os.path.exists(path)  # a closed ParallelEstimator still estimates, starting workers again
    del par
    gc.collect()
    assert not os.path.exists(path)


def test_without_a_temporary_file_the_workers_get_the_pickle_itself(estimator, monkeypatch):
    """Where no temporary file can be written, the estimator goes in the workers' start-up arguments, as before."""
    import tempfile

    def refuse(*args, **kwargs):
        raise OSError("read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    u, m, _ = _trajectory(16, seed=5)
    with ParallelEstimator(estimator, 2) as par:
        assert isinstance(par._payload_argument(), bytes)
        got = par.estimate(u, m)
        assert par.restarts == 0
    _assert_identical(got, concat_results([estimator.estimate(u[:8], m[:8]), estimator.estimate(u[8:], m[8:])]))


class _InWorker:
    """A picklable warm start that, in a worker process and on a batch of ``at_least`` readings or more (8), exits
    the process (``"exit"``) or raises (``"raise"``); elsewhere, and on a worker's first ``spare`` calls (its
    warm-up), it guesses nothing."""

    def __init__(self, how: str, at_least: int = 8, spare: int = 0) -> None:
        self.how, self.at_least, self.spare = how, at_least, spare

    def __call__(self, curvature: torch.Tensor, mask: torch.Tensor) -> dict:
        if multiprocessing.parent_process() is not None and self.spare > 0:
            self.spare -= 1
            return {}
        if multiprocessing.parent_process() is not None and curvature.shape[0] >= self.at_least:
            if self.how == "exit":
                os._exit(7)
            raise FloatingPointError("boom in a worker")
        return {}


def test_a_killed_worker_loses_no_reading(estimator):
    u, m, _ = _trajectory(24)
    expected = concat_results([estimator.estimate(u[:12], m[:12]), estimator.estimate(u[12:], m[12:])])
    with ParallelEstimator(estimator, 2) as par:
        par.warm(wait=True)
        (pid,) = par.worker_pids()
        os.kill(pid, signal.SIGKILL)  # the idle worker dies: found when the batch is handed out, or when it is due
        _assert_identical(par.estimate(u, m), expected)
        assert par.restarts == 1
        _assert_identical(par.estimate(u, m), expected)  # a new pool
        assert par.restarts == 1 and par.worker_pids() and par.worker_pids() != [pid]


def test_a_worker_that_dies_mid_batch_loses_no_reading():
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=2), warm_start=_InWorker("exit"))
    u, m, _ = _trajectory(16)
    expected = concat_results([est.estimate(u[:8], m[:8]), est.estimate(u[8:], m[8:])])
    with ParallelEstimator(est, 2, max_restarts=1) as par:
        for restarts in (1, 2):  # every pool dies on its first chunk; its chunk is solved here
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                _assert_identical(par.estimate(u, m), expected)
            assert par.restarts == restarts
            assert [str(w.message) for w in caught] == (
                [] if restarts == 1 else ["the worker processes failed 2 times; solving in one process from now on"]
            )
        assert not par.parallel  # restarts used up: from now on the whole batch in this process, with no pool
        _assert_identical(par.estimate(u, m), est.estimate(u, m))
        assert par._pool is None


def test_an_estimator_exception_in_a_worker_is_raised_as_itself():
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=2), warm_start=_InWorker("raise"))
    u, m, _ = _trajectory(16)
    with ParallelEstimator(est, 2) as par:
        with pytest.raises(FloatingPointError, match="boom in a worker"):
            par.estimate(u, m)
        assert par.restarts == 0  # an estimator error does not break the pool
        # The stream answers such a batch reading by reading (in this process, where the warm start does not fail).
        items = _items(u, m)
        out = list(stream(par, items, StreamOptions(batch_size=16, max_latency=60.0)))
    assert [r.id for r in out] == list(range(16)) and all(r.ok for r in out)
    assert [r.record["num_forces"] for r in out] == est.estimate(u, m).num_forces.tolist()


def test_submit_hands_a_batch_whole_to_an_idle_worker(estimator):
    """submit(): with the worker ready and idle, a batch goes whole to it and the call returns without waiting; while
    it is busy, the next batch is solved here before submit returns; each answer is the in-process answer of the
    same batch, bit for bit."""
    u, m, _ = _trajectory(9)
    with ParallelEstimator(estimator, 3) as par:
        assert not par.idle()  # no pool yet: idle() starts one
        par.warm(wait=True)
        assert par.idle() and len(par.worker_pids()) == 2
        first = par.submit(u[:3], m[:3])
        second = par.submit(u[3:6], m[3:6], max_forces=1)
        assert first._future is not None and second._future is not None  # both handed out
        busy = not par.idle()
        third = par.submit(u[6:], m[6:])
        assert third.done() if busy else True
        _assert_identical(first.result(), estimator.estimate(u[:3], m[:3]))
        _assert_identical(second.result(), estimator.estimate(u[3:6], m[3:6], max_forces=1))
        _assert_identical(third.result(), estimator.estimate(u[6:], m[6:]))
        assert first.done() and second.done() and par.idle()
    # One process: solved before submit returns.
    alone = ParallelEstimator(estimator, 1).submit(u[:2], m[:2])
    assert alone.done() and alone._future is None
    _assert_identical(alone.result(), estimator.estimate(u[:2], m[:2]))


@pytest.mark.parametrize("how", ["exit", "raise"])
def test_a_submitted_batch_whose_worker_fails(how):
    """A worker that dies on a submitted batch: the batch is solved here when its result is asked for, and the pool
    is started afresh; an estimator error in the worker is raised by result() as itself."""
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=2), warm_start=_InWorker(how))
    u, m, _ = _trajectory(8)
    with ParallelEstimator(est, 2) as par:
        par.warm(wait=True)
        solving = par.submit(u, m)
        assert solving._future is not None
        if how == "exit":
            _assert_identical(solving.result(), est.estimate(u, m))
            assert par.restarts == 1
        else:
            with pytest.raises(FloatingPointError, match="boom in a worker"):
                solving.result()
            assert par.restarts == 0


def test_a_broken_pool_is_dropped_once_whoever_finds_it_first():
    """A worker dies on a submitted batch; a later batch finds the pool broken first and drops it: the submitted
    batch's result is then solved here without dropping (and counting) the pool a second time."""
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=2), warm_start=_InWorker("exit", 1, spare=1))
    u, m, _ = _trajectory(18)
    with ParallelEstimator(est, 2) as par:
        par.warm(wait=True)
        solving = par.submit(u[:2], m[:2])
        assert solving._future is not None
        deadline = time.monotonic() + 60
        while not solving.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        halves = concat_results([est.estimate(u[2:10], m[2:10]), est.estimate(u[10:], m[10:])])
        _assert_identical(par.estimate(u[2:], m[2:]), halves)  # (16 rows: split, the pool found broken)
        assert par.restarts == 1
        _assert_identical(solving.result(), est.estimate(u[:2], m[:2]))
        assert par.restarts == 1


class _SlowInWorker:
    """A picklable warm start that sleeps ``delay`` seconds in a worker process and guesses nothing."""

    def __init__(self, delay: float) -> None:
        self.delay = delay

    def __call__(self, curvature: torch.Tensor, mask: torch.Tensor) -> dict:
        if multiprocessing.parent_process() is not None:
            time.sleep(self.delay)
        return {}


def test_the_first_batch_handed_out_starts_a_spare_worker():
    """Two processes: the pool has one worker, and a batch split by estimate() leaves it so; the first batch submit()
    hands out starts a spare worker in a pool of its own; once it is ready, two batches go out at once, one to each
    worker, and with both busy the estimator is full(); the answers are the in-process ones, bit for bit."""
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=1), warm_start=_SlowInWorker(0.5))
    u, m, _ = _trajectory(19)
    with ParallelEstimator(est, 2) as par:
        par.warm(wait=True)
        halves = concat_results([est.estimate(u[:8], m[:8]), est.estimate(u[8:16], m[8:16])])
        _assert_identical(par.estimate(u[:16], m[:16]), halves)
        assert par._spare is None and len(par.worker_pids()) == 1
        first = par.submit(u[16:17], m[16:17])
        assert first._pool is par._pool and par._spare is not None
        par._spare_ready.result(timeout=120)
        _assert_identical(first.result(), est.estimate(u[16:17], m[16:17]))
        second, third = par.submit(u[17:18], m[17:18]), par.submit(u[18:], m[18:])
        assert {second._pool, third._pool} == {par._pool, par._spare} and par.full() and not par.idle()
        assert len(par.worker_pids()) == 2
        _assert_identical(second.result(), est.estimate(u[17:18], m[17:18]))
        _assert_identical(third.result(), est.estimate(u[18:], m[18:]))
        assert par.idle() and not par.full()
    assert par.worker_pids() == []


def _ready_workers(monkeypatch) -> tuple[list[bool], threading.Event]:
    """(sent, ready): ``sent`` gets, per submit(), whether the batch went to a worker; ``ready`` is set once a
    stream's workers are ready (its warm() waits for them)."""
    sent: list[bool] = []
    ready = threading.Event()
    submit, warm = ParallelEstimator.submit, ParallelEstimator.warm

    def counting(self, *args, **kwargs):
        solving = submit(self, *args, **kwargs)
        sent.append(solving._future is not None)
        return solving

    def waiting(self, wait=False):
        warm(self, wait=True)
        ready.set()

    monkeypatch.setattr(ParallelEstimator, "submit", counting)
    monkeypatch.setattr(ParallelEstimator, "warm", waiting)
    return sent, ready


def _paced_items(u: torch.Tensor, m: torch.Tensor, period: float, ready: threading.Event):
    """The readings, one every ``period`` s once ``ready`` is set (a live source, started when the workers are)."""
    assert ready.wait(120)
    for k in range(u.shape[0]):
        time.sleep(period)
        yield Reading(k, torch.where(m[k].unsqueeze(-1), u[k], math.nan))


def test_a_live_stream_hands_small_batches_to_idle_workers(estimator, monkeypatch):
    """workers=2 fed slower than it solves: readings go whole to an idle worker while this process takes the next
    (the workers' answers come back in input order); every reading is answered as the estimator answers it alone."""
    sent, ready = _ready_workers(monkeypatch)
    u, m, _ = _trajectory(30, seed=5)
    out = list(stream(estimator, _paced_items(u, m, 0.03, ready), StreamOptions(workers=2)))
    assert [r.id for r in out] == list(range(30)) and all(r.ok for r in out)
    assert sum(sent) >= 10  # (a reading that found both workers busy waited for one)
    alone = [estimator.estimate(u[k : k + 1], m[k : k + 1]) for k in range(30)]
    assert [r.record["num_forces"] for r in out] == [int(a.num_forces[0]) for a in alone]
    assert [r.record["status"] for r in out] == [a.to_records([0])[0]["status"] for a in alone]
    for r, a in zip(out, alone, strict=True):
        assert r.record["loss"] == pytest.approx(float(a.loss[0]), rel=1e-6)


@pytest.mark.parametrize("how", ["raise", "exit"])
def test_a_live_stream_answers_what_its_workers_fail_on(how, monkeypatch):
    """Every batch handed to a worker fails there (the estimator raises, or the worker dies): each of its readings
    is estimated in the stream's own process instead, and every reading is answered as the estimator answers it
    alone; after a worker died the stream starts workers again and hands them batches."""
    sent, ready = _ready_workers(monkeypatch)
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=2), warm_start=_InWorker(how, 1, spare=1))
    u, m, _ = _trajectory(12, seed=7)
    period = 0.03 if how == "raise" else 0.1
    out = list(stream(est, _paced_items(u, m, period, ready), StreamOptions(workers=2)))
    assert [r.id for r in out] == list(range(12)) and all(r.ok for r in out)
    assert sum(sent) >= (6 if how == "raise" else 2)
    alone = [est.estimate(u[k : k + 1], m[k : k + 1]) for k in range(12)]
    assert [r.record["num_forces"] for r in out] == [int(a.num_forces[0]) for a in alone]
    for r, a in zip(out, alone, strict=True):
        assert r.record["loss"] == pytest.approx(float(a.loss[0]), rel=1e-6)


def test_a_live_stream_flushes_the_batches_its_workers_hold(monkeypatch):
    """An interrupt while the stream holds batches (each takes 0.3 s in the worker, readings come every 20 ms, and
    those that find the worker busy are solved in the stream's own process meanwhile): the batches taken are
    waited for and yielded in order before the readings still pending, then the interrupt is raised again."""
    sent, ready = _ready_workers(monkeypatch)
    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=NOISE, max_forces=1), warm_start=_SlowInWorker(0.3))
    u, m, _ = _trajectory(40, seed=6)
    results = stream(est, _paced_items(u, m, 0.02, ready), StreamOptions(workers=2))
    got = [next(results), next(results)]
    assert sent[:1] == [True]
    got.append(results.throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        got.extend(results)
    assert [r.id for r in got] == list(range(len(got))) and all(r.ok for r in got)
    assert len(got) >= 4


def test_options_are_checked(estimator):
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="workers"):
            StreamOptions(workers=bad)
    for bad in (-1, 2.0, None):
        with pytest.raises(ValueError, match="processes"):
            ParallelEstimator(estimator, bad)
    with pytest.raises(ValueError, match="min_chunk"):
        ParallelEstimator(estimator, 2, min_chunk=0)
    assert resolve_processes(0) == (os.cpu_count() or 1) and resolve_processes(3) == 3
    unpicklable = tr.Estimator(estimator.rod, estimator.options, warm_start=lambda u, m: {})
    with pytest.raises(TypeError, match="pickle"):
        ParallelEstimator(unpicklable, 2)
    one = ParallelEstimator(unpicklable, 1)  # one process needs no pickling and no pool
    u, m, _ = _trajectory(20)
    _assert_identical(one.estimate(u, m), estimator.estimate(u, m))
    assert one.worker_pids() == [] and one._pool is None


def test_stream_with_workers_flushes_on_an_interrupt_and_stops_its_workers(estimator, tmp_path):
    """Ctrl-C at the first answer: every line the file source already read is answered (batches of 16 over two
    processes), the interrupt is raised again, and the stream's workers are gone."""
    from torchrod.io.readings import ReadingSource

    u, m, _ = _trajectory(40)
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps({"id": k, "curvature": r}) + "\n" for k, r in enumerate(_json_rows(u, m))))
    before = set(multiprocessing.active_children())
    source = ReadingSource(str(path), 14, tr.presets.nitinol290().gratings)
    results = stream(estimator, source, StreamOptions(batch_size=16, read_ahead=2, workers=2))
    got = [next(results)]
    got.append(results.throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        got.extend(results)
    assert [r.id for r in got] == list(range(40)) and all(r.ok for r in got)
    assert max(r.batch for r in got) >= 16  # a batch (of up to 2 x 16) was split
    assert set(multiprocessing.active_children()) <= before


# ---------------------------------------------------------------------------------------------------- the CLI
def _lines(path, count: int = 32) -> None:
    u, m, _ = _trajectory(count, seed=4)
    text = "".join(
        json.dumps({"id": f"r{k}", "t": 0.01 * k, "curvature": r}) + "\n" for k, r in enumerate(_json_rows(u, m))
    )
    path.write_text(text)


def _answers(capsys, drop: str) -> list[dict]:
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    for o in out:
        o.pop(drop, None)
    return out


def test_cli_estimate_with_two_workers_answers_as_one(tmp_path, capsys):
    path = tmp_path / "in.jsonl"
    _lines(path, 24)
    base = ["estimate", "--rod", "nitinol290", "--noise", str(NOISE), "--quiet", str(path)]
    assert main([*base, "--workers", "2", "--batch-size", "24"]) == 0
    two = _answers(capsys, "time_ms")
    # One process on the same chunks (batches of 12): the same lines.
    assert main([*base, "--workers", "1", "--batch-size", "12"]) == 0
    assert two == _answers(capsys, "time_ms") and len(two) == 24
    assert main([*base, "--workers", "-1"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err


def _has_option(command: str, option: str) -> bool:
    import importlib

    parser = argparse.ArgumentParser()
    importlib.import_module(f"torchrod.cli.commands.{command}").configure(parser)
    return option in parser._option_string_actions


def test_a_stream_runs_on_a_given_parallel_estimator_and_leaves_it_running(estimator):
    """A ParallelEstimator given to stream() is the stream's workers (batches of its processes x batch_size, split
    over them) and stays running when the stream ends, ready for the next one; its spare worker can be started
    ahead too (``warm(spare=True)``). A ``workers`` option other than 1 or its own count is refused."""
    u, m, _ = _trajectory(40)
    items = _items(u, m)
    with ParallelEstimator(estimator, 2) as par:
        par.warm(wait=True, spare=True)
        pids = par.worker_pids()
        assert len(pids) == 2 and not par.starting()
        out = list(stream(par, items, StreamOptions(batch_size=8, max_latency=60.0)))
        assert [r.id for r in out] == list(range(40)) and [r.batch for r in out[:32]] == [16] * 32
        assert [r.record["num_forces"] for r in out] == estimator.estimate(u, m).num_forces.tolist()
        assert par.worker_pids() == pids  # left running
        again = list(stream(par, items[:5], StreamOptions(workers=2)))
        assert [r.id for r in again] == list(range(5)) and par.worker_pids() == pids
        with pytest.raises(ValueError, match="workers is 3 but the ParallelEstimator has 2"):
            stream(par, items, StreamOptions(workers=3))


def test_a_backlog_keeps_the_workers_fed_without_barriers(estimator, monkeypatch):
    """A backlog (a whole batch of every process pending) goes in batches of ``batch_size``, each solved whole:
    queued at the worker, two at a time, and solved in the stream's own process while the worker is fed, with no
    barrier between batches; the answers are those of one process on batches of that size (to rounding: where the
    batches begin depends on when the reader has read how much), in input order."""
    from torchrod.io import stream as stream_module

    ways = {"queued": 0, "here": 0}
    send, solve = stream_module._Stream.send, stream_module._Stream.solve

    def counted_send(self, batch, queue=False):
        ways["queued"] += queue
        return send(self, batch, queue)

    def counted_solve(self, batch, here=False):
        ways["here"] += here
        return solve(self, batch, here)

    monkeypatch.setattr(stream_module._Stream, "send", counted_send)
    monkeypatch.setattr(stream_module._Stream, "solve", counted_solve)
    u, m, _ = _trajectory(96)
    items = _items(u, m)
    with ParallelEstimator(estimator, 2) as par:
        par.warm(wait=True)
        out = list(stream(par, items, StreamOptions(batch_size=8, read_ahead=96)))
    assert ways["queued"] >= 2 and ways["here"] >= 1, ways
    assert [r.id for r in out] == list(range(96))
    alone = list(stream(estimator, items, StreamOptions(batch_size=8, max_latency=60.0)))
    for a, b in zip(alone, out, strict=True):
        assert a.record["num_forces"] == b.record["num_forces"] and a.record["status"] == b.record["status"]
        assert a.record["loss"] == pytest.approx(b.record["loss"], rel=1e-6)


class _Starting:
    """A stand-in for the stream's :class:`ParallelEstimator` whose workers are starting until ``ready`` is set: its
    own estimate records each batch it is given (solved by the wrapped estimator, in this process)."""

    ready = False
    given: list[int] = []

    def __init__(self, estimator, processes):
        self.estimator, self.processes, self.min_chunk = estimator, processes, 8

    def starting(self):
        return not _Starting.ready

    def estimate(self, curvature, mask=None, **kwargs):
        _Starting.given.append(curvature.shape[0])
        return self.estimator.estimate(curvature, mask, **kwargs)

    def warm(self):
        pass

    def idle(self):
        return False

    def full(self):
        return False

    def close(self):
        pass


@pytest.mark.parametrize("track", [False, True])
def test_a_stream_solves_alone_while_its_workers_start(estimator, monkeypatch, track):
    """Until the workers are ready a stream solves its batches in its own process, and a batch holds what one
    process solves (``batch_size``): split over workers still starting, it waited seconds for them, this process
    idle. Once they are ready, the batches hold ``workers`` x ``batch_size`` and go to them. With ``track`` the
    batches keep their size throughout (their ends decide the tracking starts)."""
    import torchrod.estimate.workers as workers_module

    monkeypatch.setattr(workers_module, "ParallelEstimator", _Starting)
    monkeypatch.setattr(_Starting, "ready", False)
    monkeypatch.setattr(_Starting, "given", [])
    u, m, _ = _trajectory(64)
    items = _items(u, m)
    options = StreamOptions(batch_size=8, workers=2, read_ahead=64, track=track, max_latency=60.0)
    results = stream(estimator, items, options)
    first = [next(results) for _ in range(24)]
    assert _Starting.given == []  # nothing handed to the workers while they start
    assert max(r.batch for r in first) == (16 if track else 8)
    _Starting.ready = True
    rest = list(results)
    assert [r.id for r in first + rest] == list(range(64))
    # Ready: twice the batch (the last one what is left), to the workers.
    # (With track the first 24 answers took two batches of 16: the last 8 of them come with the rest.)
    assert _Starting.given == ([16, 16] if track else [16, 16, 8])
    one = StreamOptions(batch_size=8 * (2 if track else 1), track=track, max_latency=60.0)  # (full batches)
    alone = list(stream(estimator, items, one))
    for a, b in zip(alone[:24], first, strict=True):
        assert a.record["num_forces"] == b.record["num_forces"] and a.record["status"] == b.record["status"]
        assert a.record["loss"] == pytest.approx(b.record["loss"], rel=1e-6)


def test_cli_stream_with_two_workers_answers_as_one(tmp_path, capsys):
    """Batches of 16 (closed by size: the latency bound is a minute), tracking starts included: --batch-size 16
    with one process, 8 per process with two (each batch solved as two chunks of 8, so the numbers agree to
    rounding)."""
    path = tmp_path / "in.jsonl"
    _lines(path, 32)
    base = ["stream", "--rod", "nitinol290", "--checkpoint", "none", "--noise", str(NOISE), "--input", str(path)]
    base += ["--max-latency-ms", "60000"]
    if _has_option("stream", "--time-budget-ms"):
        base += ["--time-budget-ms", "1e9"]  # no timeouts: the answers must not depend on the machine's load
    if _has_option("stream", "--track"):
        base += ["--track"]
    assert main([*base, "--workers", "1", "--batch-size", "16"]) == 0
    one = _answers(capsys, "latency_ms")
    assert main([*base, "--workers", "2", "--batch-size", "8"]) == 0
    two = _answers(capsys, "latency_ms")
    assert [o["id"] for o in two] == [f"r{k}" for k in range(32)]
    numbers = ("forces", "loss", "p_value", "iterations")  # an unconverged fit's can differ (module docstring)
    for a, b in zip(one, two, strict=True):
        assert {k: v for k, v in a.items() if k not in numbers} == {k: v for k, v in b.items() if k not in numbers}
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-6)
        if a["converged"]:
            assert a["loss"] == pytest.approx(b["loss"], rel=1e-9)
            for fa, fb in zip(a["forces"], b["forces"], strict=True):
                assert fa == pytest.approx(fb, rel=1e-6, abs=1e-8)


def _unread(pipe) -> int:
    """Bytes written to ``pipe`` that its reader has not read yet."""
    import array
    import fcntl
    import termios

    buf = array.array("i", [0])
    fcntl.ioctl(pipe.fileno(), termios.FIONREAD, buf)
    return buf[0]


def _ctrl_c_after_reading(path, options: list[str], period: float | None) -> None:
    """``torchrod stream --workers 2`` (plus ``options``) fed the lines of ``path`` (at once, or one every ``period``
    s, the input left open), then Ctrl-C once it has read them all: every line answered in order, exit status 130,
    no traceback, and no process of the command left."""
    lines = path.read_text().splitlines(keepends=True)
    cmd = [sys.executable, "-m", "torchrod", "stream", "--rod", "nitinol290", "--noise", str(NOISE)]
    cmd += ["--max-forces", "2", "--checkpoint", "none", "--threads", "1", "--workers", "2", *options]

    def interruptible() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    proc = subprocess.Popen(
        cmd,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: the workers' too, so that leftovers can be found
        preexec_fn=interruptible,
    )
    try:
        for chunk in [lines] if period is None else [[line] for line in lines]:
            proc.stdin.write("".join(chunk))
            proc.stdin.flush()
            if period is not None:
                time.sleep(period)
        deadline = time.monotonic() + 60
        while _unread(proc.stdin) and time.monotonic() < deadline:  # until the command has read them
            time.sleep(0.01)
        time.sleep(0.5 if period is None else 0.05)
        proc.send_signal(signal.SIGINT)  # to the command alone, as the existing stream tests do
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert [json.loads(x)["id"] for x in out.splitlines()] == [f"r{k}" for k in range(len(lines))]
    assert "Traceback" not in err
    deadline = time.monotonic() + 10
    while _group(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _group(proc.pid) == []  # no process of the command's group is left (its workers stopped)


def test_cli_stream_with_workers_flushes_on_ctrl_c(tmp_path):
    """40 readings pending (a batch of 100 and a minute's latency bound), then Ctrl-C: all answered (over two
    processes), exit status 130, and no process of the command is left."""
    path = tmp_path / "in.jsonl"
    _lines(path, 40)
    _ctrl_c_after_reading(path, ["--batch-size", "100", "--max-latency-ms", "60000"], None)


def test_cli_live_stream_with_workers_flushes_on_ctrl_c(tmp_path):
    """A live source (a line every 50 ms for 3 s, the input left open) into ``--workers 2`` with no batching wait:
    once the workers are up, lines go whole to idle workers; Ctrl-C right after the last line is read answers every
    line, in order, exit status 130, and no process of the command is left."""
    path = tmp_path / "in.jsonl"
    _lines(path, 60)
    _ctrl_c_after_reading(path, [], 0.05)


def _group(pgid: int) -> list[str]:
    """The processes of group ``pgid`` that still run (not zombies: an orphan's exit status may wait for a reaper
    that a container's init does not provide), as "pid state command" (Linux /proc)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        name, rest = stat[stat.index("(") + 1 : stat.rindex(")")], stat[stat.rindex(")") + 2 :].split()
        if int(rest[2]) == pgid and rest[0] != "Z":
            found.append(f"{pid} {rest[0]} {name}")
    return found


def test_close_waits_for_busy_workers_only(estimator, monkeypatch):
    """``close()`` gives a worker busy on a batch (abandoned after an interrupt) a second to finish before it
    terminates it, but does not wait for workers that have nothing to do, some perhaps still importing torch: a
    short input with ``--workers 2`` no longer ends a second after its last answer."""
    import concurrent.futures

    import torchrod.estimate.workers as workers

    graces = []
    real = workers._end

    def spy(processes, timeout=1.0, grace=0.0):
        graces.append(grace)
        real(processes, timeout, grace)

    monkeypatch.setattr(workers, "_end", spy)
    par = ParallelEstimator(estimator, 2)
    par.warm()  # started, perhaps not ready
    par.close()
    assert graces[0] == workers._IDLE_EXIT < 1.0
    par.warm()
    pending = concurrent.futures.Future()  # a chunk a worker is still solving
    par._chunks_out = [pending]
    graces.clear()
    par.close()
    assert graces[0] == 1.0 and par._chunks_out == []
