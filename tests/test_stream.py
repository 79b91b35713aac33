"""Streams of readings: order and count, bad and partial readings, tracking a force that comes and goes, latency-
bounded flushing through a pipe, Ctrl-C and end of input, bounded read-ahead; the CLI and ``torchrod bench stream``."""

from __future__ import annotations

import array
import fcntl
import json
import math
import os
import re
import select
import signal
import subprocess
import sys
import termios
import threading
import time

import pytest
import torch
from cases import interruptible

import torchrod as tr
from torchrod.cli import main
from torchrod.data import path as shipped_file
from torchrod.io.jsonl import LineWriter
from torchrod.io.stream import Reading, StreamOptions, StreamResult, StreamStats, stream

NOISE = 0.05


def _readings(rod: tr.Rod, cases: list[list[tuple[float, float, float]]], seed: int = 0) -> torch.Tensor:
    """(T, G, 2) noisy readings [1/m] of the load cases (location, fx, fy), sigma NOISE."""
    loads = tr.PointForces.from_lists(cases, max_forces=max(1, max(len(c) for c in cases)))
    u = tr.simulate(rod, loads).grating_curvature
    g = torch.Generator().manual_seed(seed)
    return u + NOISE * torch.randn(u.shape, generator=g, dtype=u.dtype)


def _one_force_lines(rod: tr.Rod, count: int) -> list[dict]:
    cases = [[(0.15 + 0.002 * k, 0.3, -0.2)] for k in range(count)]
    u = _readings(rod, cases).tolist()
    return [{"id": f"r{k}", "t": 0.01 * k, "curvature": u[k]} for k in range(count)]


class _Slow:
    """An estimator that takes ``delay`` [s] longer over each batch."""

    def __init__(self, inner: tr.Estimator, delay: float) -> None:
        self.inner, self.rod, self.options, self.delay = inner, inner.rod, inner.options, delay

    def estimate(self, *args, **kwargs):
        time.sleep(self.delay)
        return self.inner.estimate(*args, **kwargs)


@pytest.fixture(scope="module")
def estimator() -> tr.Estimator:
    return tr.Estimator(tr.presets.nitinol290(), tr.EstimatorOptions(max_forces=2, noise=NOISE))


# ---------------------------------------------------------------------------------------------------- the API
def test_a_batchs_solve_time_is_its_own_not_its_wait_for_a_solver_thread(rod, estimator):
    """Two solver threads, two batches each in flight: the second batch on a thread waits for the first, and its
    solve time is still its own estimate's (it once counted the wait from when the batch was handed out)."""
    delay = 0.2
    lines = _one_force_lines(rod, 8)
    results = list(tr.stream(_Slow(estimator, delay), lines, tr.StreamOptions(workers=2, batch_size=2)))
    assert [r.id for r in results] == [line["id"] for line in lines] and all(r.error is None for r in results)
    assert [r.batch for r in results] == [2] * 8
    times = [r.solve_time for r in results]
    assert min(times) >= delay and max(times) < 1.75 * delay, times
    assert max(r.latency for r in results) > 1.9 * delay  # (a batch did wait behind another)


def test_order_count_and_bad_readings(rod, estimator):
    good = _one_force_lines(rod, 6)
    G = rod.num_gratings
    holed = dict(
        good[3],
        id="holed",
        curvature=[None if k in (2, 7) else r for k, r in enumerate(good[3]["curvature"])],
    )
    nan_list = dict(good[0], id="nan", curvature=[[math.nan, 0.0]] + good[0]["curvature"][1:])
    items = [
        good[0],
        Reading(id="upstream", error="line 2: not valid JSON"),
        {"id": "short", "curvature": good[1]["curvature"][:5]},
        nan_list,
        good[1],
        {"id": "empty", "curvature": [None] * G},
        holed,
        {"id": "bad-t", "t": "soon", "curvature": good[2]["curvature"]},
        Reading(id="tensor", curvature=torch.tensor(good[2]["curvature"]), t=5.0),
        Reading(
            id="tensor-holed",
            curvature=torch.tensor(good[4]["curvature"]).index_fill(0, torch.tensor([5]), math.nan),
        ),
        "not a reading",
        good[5],
    ]
    out = list(stream(estimator, items, StreamOptions(batch_size=3, max_latency=0.0)))
    assert [r.id for r in out] == [getattr(x, "id", x.get("id") if isinstance(x, dict) else None) for x in items]
    errors = {r.id: r.error for r in out if not r.ok}
    assert set(errors) == {"upstream", "short", "nan", "empty", "bad-t", None}
    assert errors["upstream"] == "line 2: not valid JSON"
    assert "5 gratings" in errors["short"] and "finite" in errors["nan"] and "all gratings" in errors["empty"]
    assert "t must be" in errors["bad-t"] and "Reading or a dict" in errors[None]
    for r in out:
        if r.ok:
            assert r.record["num_forces"] == 1 and r.estimate.num_forces.tolist() == [1]
            (f,) = r.record["forces"]
            assert f["s"] == pytest.approx(0.15, abs=0.03) and f["fx"] == pytest.approx(0.3, abs=0.05)
            assert r.record["latency_ms"] >= 0 and r.latency > 0
        else:
            assert set(r.record) <= {"id", "error", "t"}
    by_id = {r.id: r.record for r in out}
    assert by_id["r0"]["t"] == 0.0 and by_id["tensor"]["t"] == 5.0
    assert "t" not in by_id["tensor-holed"]
    # a reading with missing gratings is the same fit as its full reading, less the missing residuals
    full = estimator.estimate(torch.tensor([good[3]["curvature"]], dtype=torch.float64))
    mask = torch.ones(1, G, dtype=torch.bool)
    mask[0, [2, 7]] = False
    masked = estimator.estimate(torch.tensor([good[3]["curvature"]], dtype=torch.float64), mask)
    assert by_id["holed"]["loss"] == pytest.approx(float(masked.loss[0]), rel=1e-3)
    assert by_id["holed"]["loss"] < float(full.loss[0])


def test_source_error_comes_after_the_readings_before_it(rod, estimator):
    lines = _one_force_lines(rod, 3)

    def source():
        yield from lines
        raise OSError("interrogator gone")

    got = []
    with pytest.raises(OSError, match="interrogator gone"):
        for r in stream(estimator, source(), StreamOptions(batch_size=8, max_latency=10.0)):
            got.append(r.id)
    assert got == ["r0", "r1", "r2"]


def _answers(results) -> list[dict]:
    return [{k: v for k, v in r.record.items() if k != "latency_ms"} for r in results]


def test_a_source_that_never_waits_is_read_without_a_reader_thread_and_answered_alike(
    rod, estimator, tmp_path, monkeypatch
):
    """A list, or a file through a ReadingSource, is read by the stream's own thread between batches; a generator
    (it may wait) by the reader thread. The answers are the same."""
    import torchrod.io.stream as stream_module
    from torchrod.io.readings import ReadingSource

    readers: set[str] = set()
    original = stream_module.to_reading

    def to_reading(*args, **kwargs):
        readers.add(threading.current_thread().name)
        return original(*args, **kwargs)

    monkeypatch.setattr(stream_module, "to_reading", to_reading)

    lines = _one_force_lines(rod, 12)
    lines[5] = {"id": "bad", "curvature": [[1.0, 2.0]]}
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    options = StreamOptions(batch_size=4, max_latency=0.0, workers=2)
    got, threads = {}, {}
    sources = {
        "generator": lambda: (line for line in lines),
        "list": lambda: lines,
        "file": lambda: ReadingSource(str(path), rod.num_gratings, rod.gratings),
    }
    for name, make in sources.items():
        readers.clear()
        got[name] = _answers(stream(estimator, make(), options))
        threads[name] = sorted(readers)
    main = threading.current_thread().name
    assert threads == {"generator": ["torchrod-reader"], "list": [main], "file": [main]}
    assert [a["id"] for a in got["list"]] == [line["id"] for line in lines] and "error" in got["list"][5]
    assert got["list"] == got["generator"]
    assert [{k: v for k, v in a.items() if k != "error"} for a in got["file"]] == [
        {k: v for k, v in a.items() if k != "error"} for a in got["list"]
    ]
    assert got["file"][5]["error"].startswith("line 6: ")


def test_what_is_left_when_a_source_that_never_waits_ends_is_shared_among_the_solver_threads(rod, estimator):
    lines = _one_force_lines(rod, 13)
    slow = _Slow(estimator, 0.3)  # (the first batch is still in flight when the second is formed)
    batches = [r.batch for r in stream(slow, lines, StreamOptions(batch_size=64, workers=2))]
    assert batches == [7] * 7 + [6] * 6
    batches = [r.batch for r in stream(estimator, lines, StreamOptions(batch_size=4, workers=2))]
    assert batches == [4] * 12 + [1]  # (full batches while the input lasts)


def test_only_a_regular_file_is_a_reading_source_that_never_waits(rod, tmp_path):
    from torchrod.io.readings import ReadingSource

    path, fifo = tmp_path / "in.jsonl", tmp_path / "fifo"
    path.write_text("")
    os.mkfifo(fifo)
    never = {
        name: ReadingSource(source, rod.num_gratings).never_waits
        for name, source in {"file": str(path), "fifo": str(fifo), "stdin": "-", "tcp": "tcp://127.0.0.1:9"}.items()
    }
    assert never == {"file": True, "fifo": False, "stdin": False, "tcp": False}


def test_a_file_read_by_the_stream_is_closed_with_it(rod, estimator, tmp_path):
    from torchrod.io.readings import ReadingSource

    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in _one_force_lines(rod, 40)))

    def open_here() -> int:
        real = os.path.realpath(path)
        return sum(os.path.realpath(f"/proc/self/fd/{fd}") == real for fd in os.listdir("/proc/self/fd"))

    results = stream(estimator, ReadingSource(str(path), rod.num_gratings), StreamOptions(batch_size=4))
    next(results)
    assert open_here() == 1
    results.close()
    assert open_here() == 0


def test_a_source_read_by_the_stream_raises_after_the_readings_before_it(rod, estimator):
    lines = _one_force_lines(rod, 3)

    class Source:  # the stream reads it itself
        never_waits = True

        def __iter__(self):
            yield from lines
            raise OSError("disk gone")

    got = []
    with pytest.raises(OSError, match="disk gone"):
        for r in stream(estimator, Source(), StreamOptions(batch_size=8)):
            got.append(r.id)
            assert not any(t.name == "torchrod-reader" for t in threading.enumerate())
    assert got == ["r0", "r1", "r2"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_a_signal_while_the_stream_reads_a_file_comes_between_readings_and_loses_none(
    rod, estimator, tmp_path, monkeypatch, sig
):
    """A signal that arrives while the stream's own thread reads a file is held until the reading in hand is taken,
    then raised as it would have been (KeyboardInterrupt; the CLI's Terminated for SIGTERM), and the flush answers
    every line already read: a prefix of the file longer than the readings taken, shorter than the file."""
    import torchrod.io.stream as stream_module
    from torchrod.io.jsonl import Terminated, sigterm_as_interrupt
    from torchrod.io.readings import ReadingSource

    # Python's own SIGINT handler, as an interactive run has it: a test run started in the background (`cmd &`)
    # inherits SIGINT ignored.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _signal_while_reading(rod, estimator, tmp_path, monkeypatch, sig, stream_module, Terminated, ReadingSource,
                              sigterm_as_interrupt)  # fmt: skip
    finally:
        signal.signal(signal.SIGINT, previous)


def _signal_while_reading(rod, estimator, tmp_path, monkeypatch, sig, stream_module, Terminated, ReadingSource,
                          sigterm_as_interrupt):  # fmt: skip
    lines = [{**line, "id": f"r{k}"} for k, line in enumerate(_one_force_lines(rod, 60) * 5)]
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    assert path.stat().st_size > 2 * 2**16  # more than the first read of the file
    calls = [0]
    original = stream_module.to_reading

    def to_reading(*args, **kwargs):
        calls[0] += 1
        if calls[0] == 20:
            os.kill(os.getpid(), sig)
        return original(*args, **kwargs)

    monkeypatch.setattr(stream_module, "to_reading", to_reading)
    source = ReadingSource(str(path), rod.num_gratings, rod.gratings)
    got = []
    expected = KeyboardInterrupt if sig == signal.SIGINT else Terminated

    def run() -> None:
        for r in stream(estimator, source, StreamOptions(batch_size=8, workers=1)):
            assert r.ok
            got.append(r.id)

    with pytest.raises(expected):
        if sig == signal.SIGTERM:
            with sigterm_as_interrupt():
                run()
        else:
            run()
    assert got == [f"r{k}" for k in range(len(got))]
    assert calls[0] >= 20 and 20 <= len(got) < len(lines)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


class _Flaky:
    """An estimator that fails on any batch holding a reading whose first value is 123 (as a batch can fail on one
    reading that breaks a solver)."""

    def __init__(self, inner: tr.Estimator) -> None:
        self.inner, self.rod, self.options = inner, inner.rod, inner.options

    def estimate(self, curvature, mask=None, **kwargs):
        if bool((curvature[:, 0, 0] == 123.0).any()):
            raise RuntimeError("solver broke")
        return self.inner.estimate(curvature, mask, **kwargs)


def test_a_failing_batch_is_retried_reading_by_reading(rod, estimator):
    lines = _one_force_lines(rod, 4)
    poison = dict(lines[1], id="poison", curvature=[[123.0, 0.0]] + lines[1]["curvature"][1:])
    items = [lines[0], poison, lines[2], lines[3]]
    out = list(stream(_Flaky(estimator), items, StreamOptions(batch_size=4, max_latency=1.0)))
    assert [r.id for r in out] == ["r0", "poison", "r2", "r3"]
    assert [r.ok for r in out] == [True, False, True, True]
    assert out[1].error == "estimation failed: solver broke"
    assert all(r.record["num_forces"] == 1 for r in out if r.ok)


def test_bad_options_raise_at_once_and_an_unused_stream_reads_nothing(estimator):
    taken = []

    def source():
        taken.append(1)
        yield {}

    with pytest.raises(TypeError, match="estimate_options must be EstimatorOptions"):
        stream(estimator, source(), StreamOptions(), {"max_forces": 2})
    with pytest.raises(TypeError, match="options must be StreamOptions"):
        stream(estimator, source(), {"batch_size": 2})
    results = stream(estimator, source())
    time.sleep(0.2)
    assert taken == []
    del results


def test_tracking_starts_are_the_last_solution_in_reported_coordinates():
    """The calibrated rod reports s = s_model + bias: the previous solution goes back as a start unchanged (the
    estimator takes extra starts in reported coordinates), for batches up to track_limit, not beyond."""
    rod = tr.presets.nitinol290(calibrated=True)
    inner = tr.Estimator(rod, tr.EstimatorOptions(max_forces=2, noise=NOISE))
    seen = []

    class Spy:
        def __init__(self) -> None:
            self.rod, self.options = rod, inner.options

        def estimate(self, curvature, mask=None, *, extra_starts=None, **kw):
            seen.append(extra_starts)
            result = inner.estimate(curvature, mask, extra_starts=extra_starts, **kw)
            seen.append(result)
            return result

    cases = [[(0.12, -0.4, 0.3), (0.22, 0.5, 0.2)]] * 6
    u = _readings(rod, cases, seed=5)
    items = [Reading(k, u[k]) for k in range(6)]
    list(stream(Spy(), items, StreamOptions(batch_size=2, max_latency=10.0, track=True, track_limit=2)))
    starts, results = seen[0::2], seen[1::2]
    assert starts[0] is None and len(starts) == 3
    for before, given in zip(results, starts[1:], strict=False):
        h = int(before.num_forces[-1])
        assert h == 2 and set(given) == {2, 1}
        torch.testing.assert_close(given[2].s, before.forces.s[-1:, :2].expand(2, 2))
        torch.testing.assert_close(given[2].f, before.forces.f[-1:, :2].expand(2, 2, 2))
        weakest = int(torch.linalg.vector_norm(before.forces.f[-1, :2], dim=-1).argmin())
        torch.testing.assert_close(given[1].s[0], before.forces.s[-1, [1 - weakest]])
    seen.clear()
    list(stream(Spy(), items, StreamOptions(batch_size=3, max_latency=10.0, track=True, track_limit=2)))
    assert seen[0::2] == [None, None]


def test_latency_bound_flushes_a_slow_source(rod, estimator):
    """A source slower than the latency bound: each answer comes before the source produces the next reading but
    one, although the batch (64) never fills."""
    lines = _one_force_lines(rod, 5)
    produced: list[float] = []

    def slow():
        for line in lines:
            produced.append(time.perf_counter())
            yield line
            time.sleep(0.4)

    answered = []
    for r in stream(estimator, slow(), StreamOptions(batch_size=64, max_latency=0.01)):
        answered.append((time.perf_counter(), len(produced)))
        assert r.ok and r.batch == 1
    assert len(answered) == 5
    assert all(seen <= k + 2 for k, (_, seen) in enumerate(answered))


@pytest.mark.parametrize("workers", [1, 2])
def test_read_ahead_is_bounded(rod, estimator, workers):
    """A fast source (100 000 readings ready at once): the stream never takes more than the batches in flight (two
    per solver thread, with more than one), the rest of the current batch, the read-ahead and the one the reader
    holds beyond what it answered."""
    (line,) = _one_force_lines(rod, 1)
    flight = 4 * (2 * workers if workers > 1 else 0)
    taken = [0]

    def source():
        for k in range(100_000):
            taken[0] += 1
            yield dict(line, id=k)

    options = StreamOptions(batch_size=4, max_latency=0.0, read_ahead=8, workers=workers)
    results = stream(estimator, source(), options)
    try:
        first = next(results)
        time.sleep(0.3)
        assert first.id == 0
        assert taken[0] <= flight + 4 + 8 + 1
        for _ in range(10):
            next(results)
        time.sleep(0.3)
        # answered 11; the batches in flight, the rest of their batch (<= 3), the queue (8), the reader's hand (1)
        assert taken[0] <= 11 + flight + 3 + 8 + 1
    finally:
        results.close()
    before = taken[0]
    time.sleep(0.3)
    assert taken[0] == before  # the reader thread stopped with the stream


def test_interrupt_at_a_yield_flushes_everything_taken(rod, estimator):
    lines = _one_force_lines(rod, 10)
    results = stream(estimator, iter(lines), StreamOptions(batch_size=4, max_latency=0.0, read_ahead=16))
    got = [next(results).id]
    time.sleep(0.2)  # the reader has queued every line by now
    got.append(results.throw(KeyboardInterrupt()).id)
    with pytest.raises(KeyboardInterrupt):
        for r in results:
            got.append(r.id)
    assert got == [f"r{k}" for k in range(10)]


def test_interrupt_at_a_yield_of_a_list_flushes_the_readings_read_and_no_more(rod, estimator):
    """A list is read by the stream's own thread a batch at a time: the flush answers the batches read so far (at
    least the one answered before the interrupt), in order, and takes nothing more from the list."""
    lines = _one_force_lines(rod, 40)
    results = stream(estimator, lines, StreamOptions(batch_size=4, max_latency=0.0, workers=1))
    got = [next(results).id]
    got.append(results.throw(KeyboardInterrupt()).id)
    with pytest.raises(KeyboardInterrupt):
        got.extend(r.id for r in results)
    assert got == [f"r{k}" for k in range(len(got))]
    assert 4 <= len(got) < 40 and len(got) % 4 == 0


def test_interrupt_answers_the_reading_the_reader_holds(rod, estimator):
    """With a full read-ahead queue the reader thread holds one more reading; the flush after an interrupt takes it
    too: every reading taken from the source is answered, and the source is not read further."""
    lines = _one_force_lines(rod, 40)
    taken = [0]

    def source():
        for line in lines:
            taken[0] += 1
            yield line

    results = stream(estimator, source(), StreamOptions(batch_size=2, max_latency=0.0, read_ahead=2))
    got = [next(results).id]
    time.sleep(0.3)  # the queue is full and the reader waits with a reading in hand
    got.append(results.throw(KeyboardInterrupt()).id)
    with pytest.raises(KeyboardInterrupt):
        got.extend(r.id for r in results)
    assert got == [f"r{k}" for k in range(taken[0])] and taken[0] < len(lines)


def test_interrupt_answers_every_line_a_file_source_already_read(rod, estimator, tmp_path):
    """A ReadingSource (the CLI's) is ended at the lines it already read: all 40 lines of a small file, read at
    once, are answered after an interrupt, although the queue held only a few of them."""
    from torchrod.io.readings import ReadingSource

    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in _one_force_lines(rod, 40)))
    source = ReadingSource(str(path), rod.num_gratings, rod.gratings)
    results = stream(estimator, source, StreamOptions(batch_size=2, max_latency=0.0, read_ahead=2))
    got = [next(results).id]
    got.append(results.throw(KeyboardInterrupt()).id)
    with pytest.raises(KeyboardInterrupt):
        got.extend(r.id for r in results)
    assert got == [f"r{k}" for k in range(40)]


def test_an_interrupt_is_raised_again_as_it_came(rod, estimator):
    """A subclass of KeyboardInterrupt (the CLI's SIGTERM) comes out of the flush as itself."""
    from torchrod.io.jsonl import Terminated

    results = stream(estimator, iter(_one_force_lines(rod, 4)), StreamOptions(batch_size=2, max_latency=0.0))
    got = [next(results).id]
    time.sleep(0.2)  # the reader thread has queued every line by now (else the flush answers only those it read)
    got.append(results.throw(Terminated()).id)
    with pytest.raises(Terminated):
        got.extend(r.id for r in results)
    assert got == ["r0", "r1", "r2", "r3"]


def test_api_readings_that_used_to_crash_the_stream_are_error_results(rod, estimator):
    """Huge integers, values beyond the bound and ids JSON cannot echo, in dicts, lists and tensors: one error
    result each, in order, and the stream goes on."""
    (good,) = _one_force_lines(rod, 1)
    u = good["curvature"]
    items = [
        dict(good, id="t400", t=10**400),
        dict(good, id="u400", curvature=[[10**400, 0]] + u[1:]),
        dict(good, id="e308", curvature=[[1e308, 0.0]] + u[1:]),
        Reading("tensor-e308", torch.tensor([[1e308, 0.0]] + u[1:], dtype=torch.float64)),
        dict(good, id=math.nan),
        dict(good, id="str", curvature=[["1.5", 0.0]] + u[1:]),
        good,
    ]
    out = list(stream(estimator, items, StreamOptions(batch_size=8, max_latency=0.0)))
    assert [r.id for r in out] == ["t400", "u400", "e308", "tensor-e308", None, "str", "r0"]
    assert [r.ok for r in out] == [False] * 6 + [True]
    assert "t must be a finite number" in out[0].error and "overflows a float" in out[1].error
    assert all("beyond the bound" in r.error for r in out[2:4]) and "id NaN" in out[4].error
    assert 'curvature[0][0] must be a number, got a string "1.5"' in out[5].error


def test_stats_say_when_latency_includes_queueing():
    """A file read at once: latencies far above the solve time are queueing, and the summary says so."""
    queued, live = StreamStats(), StreamStats()
    for k in range(50):
        rec = {"id": k, "forces": []}
        queued.add(StreamResult(k, None, rec, latency=0.1 * k, batch=1, solve_time=0.01))
        live.add(StreamResult(k, None, rec, latency=0.012, batch=1, solve_time=0.01))
    assert queued.solve_time(0.5) == pytest.approx(0.01, rel=0.011)
    text, plain = "\n".join(queued.summary(5.0)), "\n".join(live.summary(5.0))
    assert "latency median" in text and "solve time 10.0 ms per batch of 1 readings, 10.00 ms per reading" in text
    assert "latency includes queueing" in text and "queueing" not in plain


def test_tracking_a_force_that_appears_and_vanishes(rod):
    """A steady force at 0.22 m and a second one at 0.11 m that ramps up, stays and fades away: the stream (previous
    solutions as starts) gets the count right on the frames where the second force is clearly present or absent,
    with errors like the static estimator's on the same readings."""
    T = 36
    cases, truth = [], []
    for k in range(T):
        a = (0.22 - 0.0003 * k, 0.6 * math.cos(0.02 * k), 0.6 * math.sin(0.02 * k))
        w = min(1.0, max(0.0, (k - 8) / 3)) * min(1.0, max(0.0, (28 - k) / 3))  # 0 before 8, 1 on 11..25
        forces = [a] if w == 0 else sorted([a, (0.11 + 0.0002 * k, -0.5 * w, 0.3 * w)])
        cases.append(forces)
        truth.append(forces)
    u = _readings(rod, cases, seed=3)
    estimator = tr.Estimator(rod, tr.EstimatorOptions(max_forces=3, noise=NOISE))
    items = [Reading(id=k, curvature=u[k], t=0.01 * k) for k in range(T)]
    out = list(stream(estimator, items, StreamOptions(batch_size=4, max_latency=0.0, track=True)))
    static = estimator.estimate(u).to_records()
    clear = [k for k in range(T) if k < 8 or 11 <= k <= 25 or k >= 28]
    right = [k for k in clear if out[k].record["num_forces"] == len(truth[k])]
    assert len(right) >= len(clear) - 2

    def errors(records):
        stats = StreamStats()
        for k in clear:
            stats.add(StreamResult(records[k]["id"], None, records[k], latency=0.001), truth[k])
        return stats

    mine, ref = errors([r.record for r in out]), errors(static)
    assert mine.count_accuracy >= ref.count_accuracy - 0.05
    assert mine.force_error() <= 1.3 * ref.force_error() + 0.005
    assert mine.location_error() <= 1.3 * ref.location_error() + 0.5e-3
    assert mine.force_error() < 0.05 and mine.location_error() < 3e-3


def test_by_default_a_reading_is_answered_as_the_static_estimator_answers_it(rod):
    """Without tracking (the default) a stream adds no starts: each reading's answer is the estimator's on that
    reading alone, whatever batch it fell in (two-force readings whose second force comes and goes)."""
    cases = [[(0.21, 0.5, 0.2)] + ([(0.09, -0.4, 0.3)] if 3 <= k <= 8 else []) for k in range(12)]
    u = _readings(rod, [sorted(c) for c in cases], seed=4)
    estimator = tr.Estimator(rod, tr.EstimatorOptions(max_forces=3, noise=NOISE))
    items = [Reading(id=k, curvature=u[k]) for k in range(len(cases))]
    out = list(stream(estimator, items, StreamOptions(batch_size=5)))
    for k, r in enumerate(out):
        alone = estimator.estimate(u[k : k + 1])
        assert r.record["status"] == alone.statuses[0] and r.record["num_forces"] == int(alone.num_forces[0]), k
        h = int(alone.num_forces[0])
        got = torch.tensor([f["s"] for f in r.record["forces"]], dtype=u.dtype)
        torch.testing.assert_close(got, alone.forces.s[0, :h], atol=1e-7, rtol=0)


def test_stream_stats_quantiles():
    stats = StreamStats()
    for k in range(1, 101):
        rec = {"id": k, "forces": [{"s": 0.1 + 1e-4 * k, "fx": 0.5, "fy": 0.0}]}
        stats.add(StreamResult(k, None, rec, latency=k * 1e-3), [(0.1, 0.5 + 1e-3 * k, 0.0)])
    stats.add(StreamResult(None, None, {"id": None, "error": "x"}, error="x"))
    assert stats.readings == 101 and stats.errors == 1 and stats.count_accuracy == 1.0
    assert stats.latency(0.5) == pytest.approx(0.050, rel=0.011)
    assert stats.latency(0.99) == pytest.approx(0.099, rel=0.011)
    assert stats.force_error() == pytest.approx(0.050, rel=0.011)
    assert stats.location_error() == pytest.approx(0.005, rel=0.011)


def test_options_are_checked():
    for bad in ({"batch_size": 0}, {"read_ahead": 0}, {"max_latency": -1.0}, {"max_latency": math.inf}):
        with pytest.raises(ValueError):
            StreamOptions(**bad)


# ---------------------------------------------------------------------------------------------------- the CLI
def _line_ids(text: str) -> list:
    return [json.loads(x).get("id") for x in text.splitlines()]


def test_cli_jsonl_with_bad_lines(rod, tmp_path, capsys):
    good = _one_force_lines(rod, 4)
    lines = [
        json.dumps(good[0]),
        "this is not json",
        '{"id": "nan", "curvature": ' + json.dumps(good[1]["curvature"][:13])[:-1] + ", [NaN, 0.0]]}",
        json.dumps({"id": "short", "curvature": good[1]["curvature"][:3]}),
        "",
        json.dumps(dict(good[1], curvature=[None] + good[1]["curvature"][1:])),
        json.dumps(dict(good[2], t="noon")),
        json.dumps(good[3]),
    ]
    path = tmp_path / "in.jsonl"
    path.write_text("\n".join(lines) + "\n")
    args = [
        "stream",
        "--rod",
        "nitinol290",
        "--checkpoint",
        "none",
        "--noise",
        str(NOISE),
        "--max-forces",
        "2",
    ]
    status = main([*args, "--input", str(path), "--batch-size", "2", "--summary"])
    cap = capsys.readouterr()
    out = [json.loads(x) for x in cap.out.splitlines()]
    assert status == 1
    assert [o["id"] for o in out] == ["r0", None, "nan", "short", "r1", "r2", "r3"]
    assert [("error" in o) for o in out] == [False, True, True, True, False, True, False]
    assert out[1]["error"].startswith("line 2: not valid JSON") and "finite" in out[2]["error"]
    assert "3 gratings" in out[3]["error"] and "line 7: t must be a number" in out[5]["error"]
    assert out[4]["num_forces"] == 1 and out[4]["t"] == pytest.approx(0.01)
    assert "7 readings, 4 errors" in cap.err and "latency median" in cap.err and "solve time" in cap.err


def test_cli_freezes_what_it_set_up_and_gives_it_back(rod, tmp_path, capsys, monkeypatch):
    """``torchrod stream`` moves what it set up out of the garbage collector's full collections and shortens the
    interpreter's switch interval before the readings come (``commands.settle``), and :func:`main` undoes both when
    the command returns, so a process that calls it, as this test does, goes on as before."""
    import gc

    from torchrod.cli import commands

    frozen, interval = [], []
    freeze = gc.freeze
    monkeypatch.setattr(gc, "freeze", lambda: (freeze(), frozen.append(gc.get_freeze_count())))
    estimate = tr.Estimator.estimate
    monkeypatch.setattr(
        tr.Estimator, "estimate", lambda *a, **k: (interval.append(sys.getswitchinterval()), estimate(*a, **k))[1]
    )
    before = sys.getswitchinterval()
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(x) + "\n" for x in _one_force_lines(rod, 2)))
    args = ["stream", "--rod", "nitinol290", "--checkpoint", "none", "--noise", str(NOISE), "--input", str(path)]
    assert main(args) == 0
    assert len(capsys.readouterr().out.splitlines()) == 2
    assert len(frozen) == 1 and frozen[0] > 0 and gc.get_freeze_count() == 0
    assert interval[-1] == commands.SWITCH_INTERVAL != before and sys.getswitchinterval() == before


class _CountingOut:
    """Standard output that counts its flushes and keeps its text."""

    def __init__(self) -> None:
        self.text, self.flushes = [], 0

    def write(self, text: str) -> int:
        self.text.append(text)
        return len(text)

    def flush(self) -> None:
        self.flushes += 1


@pytest.mark.parametrize("command", ["stream", "estimate"])
def test_cli_flushes_once_per_batch_not_once_per_line(rod, tmp_path, monkeypatch, command):
    """A batch's answers are written together and flushed once, after the last of them: a flush per line cost a
    system call per reading. Every line is written, in order."""
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps(x) + "\n" for x in _one_force_lines(rod, 10)))
    out = _CountingOut()
    monkeypatch.setattr(sys, "stdout", out)
    given = ["--input", str(path)] if command == "stream" else [str(path)]
    args = [command, "--rod", "nitinol290", "--checkpoint", "none", "--noise", str(NOISE), *given]
    assert main([*args, "--batch-size", "4"]) == 0
    lines = "".join(out.text).splitlines()
    assert [json.loads(x)["id"] for x in lines] == [f"r{k}" for k in range(10)]
    assert 1 <= out.flushes <= 4  # (batches of at most 4 readings: 10 lines)
    held = _CountingOut()  # (the writer's own: lines held, then one flush)
    writer = LineWriter(held)
    assert all(writer.answer({"id": k}, flush=False) for k in range(3))
    assert held.flushes == 0 and writer.lines == 3
    writer.flush()
    assert held.flushes == 1 and "".join(held.text) == '{"id": 0}\n{"id": 1}\n{"id": 2}\n'


def test_cli_csv_with_header_and_missing_gratings(rod, tmp_path, capsys):
    good = _one_force_lines(rod, 3)
    G = rod.num_gratings
    header = ",".join(["id", "t"] + [f"{c}{k + 1}" for k in range(G) for c in ("ux", "uy")])

    def row(line, missing=()):
        cells = [line["id"], str(line["t"])]
        for k, (ux, uy) in enumerate(line["curvature"]):
            cells += ["", ""] if k in missing else [repr(ux), repr(uy)]
        return ",".join(cells)

    bad_cell = row(good[1]).split(",")
    bad_cell[5] = "abc"
    half = row(good[1]).split(",")
    half[4] = ""
    rows = [
        header,
        row(good[0]),
        ",".join(bad_cell),
        row(good[1], missing=(3, 9)),
        "x,1.0,2.0",
        ",".join(half),
    ]
    rows.append(row(good[2]).replace(repr(good[2]["curvature"][6][0]), "nan", 1))
    rows.append(row(good[2]))
    path = tmp_path / "in.csv"
    path.write_text("\n".join(rows) + "\n")
    status = main(
        [
            "stream",
            "--rod",
            "nitinol290",
            "--checkpoint",
            "none",
            "--noise",
            str(NOISE),
            "--max-forces",
            "1",
            "--input",
            str(path),
        ]
    )
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert status == 1
    assert [o["id"] for o in out] == ["r0", "r1", "r1", "x", "r1", "r2", "r2"]
    assert [("error" in o) for o in out] == [False, True, False, True, True, True, False]
    assert "curvature[1][1] must be a number" in out[1]["error"] and out[1]["error"].startswith("line 3:")
    assert "the row has 3 cells, the header (line 1) names 30 columns" in out[3]["error"]
    assert "curvature[1][0] must be a number, got null" in out[4]["error"]
    assert "curvature[6][0] must be finite" in out[5]["error"]
    assert out[2]["forces"][0]["s"] == pytest.approx(0.152, abs=0.03) and out[2]["t"] == pytest.approx(0.01)
    # --format jsonl refuses the CSV lines one by one
    assert (
        main(
            [
                "stream",
                "--rod",
                "nitinol290",
                "--checkpoint",
                "none",
                "--format",
                "jsonl",
                "--max-forces",
                "1",
                "--input",
                str(path),
            ]
        )
        == 1
    )
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(out) == len(rows) and all("not valid JSON" in o["error"] for o in out)


def test_cli_hostile_lines_and_out(rod, tmp_path, capsys):
    """JSON lines and CSV rows that used to crash the stream or give an all-null "estimate": one error line each,
    in order, naming the line and field; --out takes the answers; an unwritable --out is status 2."""
    (good,) = _one_force_lines(rod, 1)
    u = good["curvature"]
    rest = json.dumps(u[1:])[1:]
    lines = [
        json.dumps(good),
        '{"id": "t400", "t": ' + "1" * 400 + ', "curvature": ' + json.dumps(u) + "}",
        '{"id": "u400", "curvature": [[' + "2" * 400 + ", 0], " + rest + "}",
        '{"id": "e308", "curvature": [[1e308, 0], ' + rest + "}",
        '{"id": Infinity, "curvature": ' + json.dumps(u) + "}",
        '{"id": "big", "curvature": [["' + "z" * 1_000_000 + '", 0], ' + rest + "}",  # (under the 1 MiB limit)
        json.dumps(dict(good, id="last")),
    ]
    path = tmp_path / "in.jsonl"
    path.write_text("\n".join(lines) + "\n")
    target = tmp_path / "out.jsonl"
    base = [
        "stream",
        "--rod",
        "nitinol290",
        "--checkpoint",
        "none",
        "--noise",
        str(NOISE),
        "--max-forces",
        "1",
    ]
    assert main([*base, "--input", str(path), "--out", str(target)]) == 1
    assert capsys.readouterr().out == ""
    out = [json.loads(x) for x in target.read_text().splitlines()]
    assert [o["id"] for o in out] == ["r0", "t400", "u400", "e308", None, "big", "last"]
    assert [("error" in o) for o in out] == [False, True, True, True, True, True, False]
    for k, message in [
        (1, "t must be a finite number"),
        (2, "curvature[0][0] must be a finite number"),
        (3, "curvature[0][0] = 1e+308 1/m is beyond the bound"),
        (4, "id Infinity"),
        (5, "curvature[0][0] must be a number, got a string"),
    ]:
        assert out[k]["error"].startswith(f"line {k + 1}: ") and message in out[k]["error"], out[k]["error"]
        assert len(out[k]["error"]) < 400
    assert main([*base, "--input", str(path), "--out", str(tmp_path / "no" / "x.jsonl")]) == 2
    assert "cannot write there" in capsys.readouterr().err
    # CSV: no underscores, no hexadecimal, no 400-digit timestamp that crashes the reader
    cells = [repr(x) for pair in u for x in pair]
    rows = [
        ",".join(["a", "0.1", *cells]),
        ",".join(["us", "0.2", "1_000", *cells[1:]]),
        ",".join(["hex", "0x10", *cells]),
        ",".join(["t400", "9" * 400, *cells]),
        ",".join(["b", "0.3", *cells]),
    ]
    path = tmp_path / "in.csv"
    path.write_text("\n".join(rows) + "\n")
    assert main([*base, "--input", str(path)]) == 1
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [o["id"] for o in out] == ["a", "us", "hex", "t400", "b"]
    assert [("error" in o) for o in out] == [False, True, True, True, False]
    assert 'line 2: curvature[0][0] must be a number, got "1_000"' in out[1]["error"]
    assert "line 3: t must be a number" in out[2]["error"]
    assert "line 4: t must be a finite number" in out[3]["error"] and "overflows a float" in out[3]["error"]


def test_cli_truth_summary(tmp_path, capsys):
    root = shipped_file("example_stream.jsonl").parent
    stream_path = os.path.join(root, "example_stream.jsonl")
    if not os.path.exists(stream_path):
        pytest.skip("no shipped example stream")
    with open(stream_path) as fh:
        lines = fh.read().splitlines()[200:230]
    path = tmp_path / "part.jsonl"
    path.write_text("\n".join(lines) + "\n")
    status = main(
        [
            "stream",
            "--rod",
            "nitinol290",
            "--checkpoint",
            "none",
            "--noise",
            "0.1",
            "--input",
            str(path),
            "--summary",
            "--truth",
            os.path.join(root, "example_stream_truth.jsonl"),
        ]
    )
    cap = capsys.readouterr()
    assert status == 0 and len(cap.out.splitlines()) == 30
    assert "against the truth (30 readings): count accuracy" in cap.err
    assert "median force error" in cap.err
    # every answer's status, tallied
    tally = next(line for line in cap.err.splitlines() if "statuses: " in line)
    counts = [int(part.split()[-1]) for part in tally.split("statuses: ")[1].split(", ")]
    assert sum(counts) == 30


def test_cli_default_checkpoint_is_refused_for_another_layout(tmp_path, capsys):
    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT

    if not os.path.exists(SHIPPED_CHECKPOINT):
        pytest.skip("no shipped checkpoint")
    rod = tr.Rod(length=0.3, bending_stiffness=7e-3, gratings=(0.05, 0.1, 0.15, 0.2, 0.25))
    rod_path = tmp_path / "rod.json"
    rod.to_json(str(rod_path))
    loads = tr.PointForces.from_lists([[(0.2, 0.3, 0.1)]])
    u = tr.simulate(rod, loads).grating_curvature[0].tolist()
    path = tmp_path / "in.jsonl"
    path.write_text(json.dumps({"id": 1, "curvature": u}) + "\n" + json.dumps({"id": 2, "curvature": u}) + "\n")
    # stream and estimate pick the shipped network the same way: none fits this layout, said once on stderr.
    for argv in (["stream", "--input", str(path)], ["estimate", str(path)]):
        assert main([*argv, "--rod", str(rod_path), "--max-forces", "1"]) == 0
        cap = capsys.readouterr()
        assert cap.err.count("no shipped warm-start network fits this rod's grating layout") == 1, argv
        assert [json.loads(x)["num_forces"] for x in cap.out.splitlines()] == [1, 1]


def test_cli_estimate_and_stream_use_the_shipped_network_alike(tmp_path, capsys, monkeypatch):
    """Without --checkpoint, estimate and stream both take the network shipped for the rod's layout; with
    --checkpoint none, neither does."""
    from torchrod.cli.commands import estimate as estimate_command

    chosen = []
    original = estimate_command.choose_network

    def spy(checkpoint, rod, command):
        network = original(checkpoint, rod, command)
        chosen.append((command, checkpoint, network is not None))
        return network

    monkeypatch.setattr(estimate_command, "choose_network", spy)
    from torchrod.cli.commands import stream as stream_command

    monkeypatch.setattr(stream_command, "choose_network", spy)
    u = tr.grating_curvature(tr.presets.nitinol290(), tr.PointForces.from_lists([[(0.2, 0.3, 0.1)]]))[0].tolist()
    path = tmp_path / "in.jsonl"
    path.write_text(json.dumps({"id": 1, "curvature": u}) + "\n")
    for extra in ([], ["--checkpoint", "none"]):
        assert main(["estimate", "--rod", "nitinol290", "--noise", "0.01", str(path), *extra]) == 0
        assert main(["stream", "--rod", "nitinol290", "--noise", "0.01", "--input", str(path), *extra]) == 0
    capsys.readouterr()
    assert chosen == [
        ("estimate", None, True),
        ("stream", None, True),
        ("estimate", "none", False),
        ("stream", "none", False),
    ]


def _unread(pipe) -> int:
    buf = array.array("i", [0])
    fcntl.ioctl(pipe.fileno(), termios.FIONREAD, buf)
    return buf[0]


def _start(*options: str) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-X",
        "faulthandler",  # a hung child dumps every thread's stack on SIGABRT (see _wait)
        "-m",
        "torchrod",
        "stream",
        "--rod",
        "nitinol290",
        "--noise",
        str(NOISE),
        "--max-forces",
        "1",
        "--checkpoint",
        "none",
        "--threads",
        "1",
        *options,
    ]
    return subprocess.Popen(
        cmd,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        bufsize=1,
        preexec_fn=interruptible,
    )


def _wait(proc: subprocess.Popen, timeout: float) -> int:
    """The child's exit status; if it hangs, its threads' stacks (faulthandler, on SIGABRT) in the failure."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        _, err = proc.communicate(timeout=10)
        pytest.fail(f"the child did not exit within {timeout} s; its stderr and stacks:\n{err[-6000:]}")


def _read_line(proc: subprocess.Popen, timeout: float) -> str | None:
    """The next output line, or None if none starts within ``timeout`` (lines are written whole and flushed)."""
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    return proc.stdout.readline() if ready else None


def test_cli_pipe_answers_before_the_input_ends(rod):
    """A slow writer on stdin: every answer arrives while the input is still open (the batch of 64 never fills;
    the latency bound closes it)."""
    lines = _one_force_lines(rod, 4)
    proc = _start("--max-latency-ms", "10")
    try:
        for line in lines:
            proc.stdin.write(json.dumps(line) + "\n")
            proc.stdin.flush()
            answer = _read_line(proc, timeout=60)
            assert answer is not None, proc.stderr.read() if proc.poll() is not None else "no answer"
            out = json.loads(answer)
            assert out["id"] == line["id"] and out["num_forces"] == 1
            time.sleep(0.2)
        assert proc.poll() is None  # still running: the input is open
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
    finally:
        proc.kill() if proc.poll() is None else None


@pytest.mark.parametrize("how", ["end of input", "ctrl-c", "sigterm"])
def test_cli_flushes_pending_readings(rod, how):
    """Readings pending in a batch that is far from full and a latency bound of a minute are answered at the end of
    the input, on Ctrl-C (exit status 130) or on SIGTERM (143), at once."""
    lines = _one_force_lines(rod, 3)
    proc = _start("--max-latency-ms", "60000", "--batch-size", "100")
    try:
        proc.stdin.write("".join(json.dumps(line) + "\n" for line in lines))
        proc.stdin.flush()
        deadline = time.monotonic() + 60
        while _unread(proc.stdin) and time.monotonic() < deadline:  # until the command has read them
            time.sleep(0.05)
        time.sleep(0.5)
        assert _read_line(proc, timeout=0.5) is None  # pending: nothing answered yet
        t0 = time.monotonic()
        if how == "end of input":
            proc.stdin.close()
        else:
            proc.send_signal(signal.SIGINT if how == "ctrl-c" else signal.SIGTERM)
        status = _wait(proc, 30)
        assert time.monotonic() - t0 < 20
        out = proc.stdout.read().splitlines()
        assert status == {"end of input": 0, "ctrl-c": 130, "sigterm": 143}[how], proc.stderr.read()
        assert [json.loads(x)["id"] for x in out] == ["r0", "r1", "r2"]
        assert "Fatal" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_bench_stream_runs_and_reports_every_way(capsys):
    args = ["bench", "stream", "--count", "40", "--single", "3", "--paced", "20", "--pace", "400"]
    external = ["--external", "400", "--external-budgets", "default,0"]
    assert main([*args, "--checkpoint", "none", "--set", "max_forces=2", "--profile", *external]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if "|" in line and not line.startswith("way")]
    threads = os.cpu_count() or 1
    assert [r.split("|")[0].strip() for r in rows] == [
        "static, batched (B=1024)",
        "static, one at a time",
        "stream, backlog, 1 thread (B<=1024)",
        *([f"stream, backlog, {threads} threads"] if threads > 1 else []),
        "stream, backlog, noise learned",
        "stream, backlog, noise per reading",
        "stream, paced 400 Hz",
        "CLI, 400 Hz from outside",
        "CLI, 400 Hz from outside, budget 0 ms",
        "CLI, backlog from a file",
        "stream, one at a time",
    ]
    readings = [int(r.split("|")[1].split()[0]) for r in rows]
    assert readings == [40, 3, 40, *([40] if threads > 1 else []), 40, 40, 20, 20, 20, 40, 3]
    # the process paced from outside answers every line; with no time at all, every answer says so
    assert "# CLI, 400 Hz from outside, budget 0 ms: latency median" in out and "statuses: timeout 20" in out
    # the process given the whole trajectory in a file answers every reading, as the stream in process does
    note = next(line for line in out.splitlines() if line.startswith("# CLI, backlog from a file: 40 readings in"))
    assert sum(int(n) for n in re.findall(r"[a-z_]+ (\d+)", note.split("statuses: ")[1])) == 40
    assert re.search(r"\(\d+ % of the readings/s of 'static, batched \(B=\d+\)' in this run\)", note), note
    # the stream over the same readings as the static batches agrees with them on the count
    static, backlog = (float(rows[k].split("|")[4].split()[0].rstrip("%")) for k in (0, 2))
    assert abs(static - backlog) <= 10.0
    assert "max_forces=2" in out and "kernels" in out  # the options, and where the time goes


def test_a_stream_whose_solver_threads_are_busy_waits_for_a_batch_not_for_each_reading(rod, estimator, monkeypatch):
    """A source faster than two busy solver threads: while both hold their batches, a reading that arrives cannot be
    sent, so the stream sleeps until a batch is done instead of waking for each reading (a backlog's thousands of
    wake-ups): fewer passes of its loop than half the readings, where waking for each made more than one each."""
    import torchrod.io.stream as streaming

    passes = [0]
    fill = streaming._Stream.fill

    def counted(self, wait=True):
        passes[0] += 1
        return fill(self, wait)

    monkeypatch.setattr(streaming._Stream, "fill", counted)
    u = torch.tensor(_one_force_lines(rod, 1)[0]["curvature"])

    def source():
        for k in range(300):
            time.sleep(0.0005)
            yield Reading(k, u)

    got = list(stream(_Slow(estimator, 0.05), source(), StreamOptions(batch_size=8, read_ahead=1000, workers=2)))
    assert [r.id for r in got] == list(range(300)) and all(r.ok for r in got)
    assert passes[0] < 150


def test_bench_paced_latency_counts_the_wait_of_a_stream_that_falls_behind(rod, estimator):
    """The paced rows count latency from each reading's release time. A stream solving 25 ms per reading fed at
    1 kHz, with room for one queued reading, takes each reading late: the wait between release and the stream taking
    the reading grows with every reading, and the latency counts it."""
    from torchrod.cli.benchmarks.stream import _paced, _since_due

    items = [Reading(k, torch.tensor(line["curvature"])) for k, line in enumerate(_one_force_lines(rod, 12))]
    due: dict = {}
    options = StreamOptions(batch_size=1, read_ahead=1, workers=1)  # one solver thread: it falls behind
    got = list(_since_due(stream(_Slow(estimator, 0.025), _paced(items, 1000.0, due), options), due))
    assert [r.id for r in got] == list(range(12)) and sorted(due) == list(range(12))
    waited = [r.latency - 1e-3 * r.record["latency_ms"] for r in got]  # from release until the stream took it
    assert waited[-1] > 0.2 and waited[-1] > waited[0] + 0.15
    assert got[-1].latency > 2 * 1e-3 * got[-1].record["latency_ms"]


class _Where(_Slow):
    """An estimator that records the thread and batch size of each call."""

    def __init__(self, inner: tr.Estimator, delay: float = 0.0) -> None:
        super().__init__(inner, delay)
        self.calls: list[tuple[str, int]] = []

    def estimate(self, curvature, *args, **kwargs):
        self.calls.append((threading.current_thread().name, curvature.shape[0]))
        return super().estimate(curvature, *args, **kwargs)


def test_a_lone_reading_is_solved_on_the_streams_thread_and_a_burst_by_the_solver_threads(rod, estimator):
    """A paced source (each reading arrives after the last is answered) has its readings solved on the thread that
    iterates the stream, with no hand-off to a solver thread and back; readings that arrive together still go to the
    solver threads, and every answer comes in input order."""
    u = torch.tensor(_one_force_lines(rod, 1)[0]["curvature"])
    where = _Where(estimator)

    def paced():
        for k in range(5):
            time.sleep(0.05)
            yield Reading(k, u)

    got = list(stream(where, paced(), StreamOptions(workers=2)))
    assert [r.id for r in got] == list(range(5)) and all(r.ok for r in got)
    here = threading.current_thread().name
    assert where.calls == [(here, 1)] * 5

    burst = _Where(estimator, delay=0.05)
    got = list(stream(burst, (Reading(k, u) for k in range(40)), StreamOptions(batch_size=8, workers=2)))
    assert [r.id for r in got] == list(range(40)) and all(r.ok for r in got)
    assert any(name.startswith("torchrod-stream") for name, _ in burst.calls)


def test_a_reading_is_checked_once_as_it_is_read_not_again_per_batch(rod, estimator, monkeypatch):
    """Each reading is checked when the stream takes it; the estimator does not check the stacked batch again,
    and the answers are those of the estimator's own checked call."""
    import torchrod.estimate.estimator as estimator_module

    lines = _one_force_lines(rod, 12)
    lines[4] = {"id": "bad", "curvature": [[1e9, 0.0]] * rod.num_gratings}  # beyond the curvature bound
    expected = list(stream(estimator, lines, StreamOptions(batch_size=4, workers=1)))
    calls = []
    checks = estimator_module.check_readings

    def counted(*args, **kwargs):
        calls.append(1)
        return checks(*args, **kwargs)

    monkeypatch.setattr(estimator_module, "check_readings", counted)
    got = list(stream(estimator, lines, StreamOptions(batch_size=4, workers=1)))
    assert calls == []

    def answers(results):
        return [{k: v for k, v in r.record.items() if k != "latency_ms"} for r in results]

    assert answers(got) == answers(expected)
    assert got[4].error is not None and "bad" == got[4].id
    u = torch.tensor([line["curvature"] for line in lines[:2]], dtype=torch.float64)
    estimator.estimate(u)  # a caller's own tensors are checked
    assert calls == [1]
