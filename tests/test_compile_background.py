"""A first compile of the CPU kernels in a background process: readings are solved meanwhile by the same source run
as Python, with the compiled kernels' answers, one at a time, with no deadline; the kernels are used as soon as the
child is done; the child ends with its parent. And a kernel function is compiled once, not once per constant its
callers pass."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

import torchrod as tr
from torchrod.estimate.noise import NoiseLearning
from torchrod.kernels import host, patches, targets

ROD = tr.presets.nitinol290()


def _readings(count: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    s = 0.08 + 0.2 * torch.rand((count, 2), generator=g, dtype=torch.float64)
    f = torch.rand((count, 2, 2), generator=g, dtype=torch.float64) - 0.5
    u = tr.simulate(ROD, tr.PointForces(s, f)).grating_curvature
    return u + 0.05 * torch.randn(u.shape, generator=g, dtype=torch.float64)


class _Compiling:
    """A stand-in for the compiling child: running until :meth:`end` (it waits on its standard input)."""

    def __init__(self, compiled: targets.Compiled) -> None:
        self.compiled = compiled
        self.proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
        compiled._child = self.proc

    def end(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            self.proc.wait(10)

    def __enter__(self) -> _Compiling:
        return self

    def __exit__(self, *exc: object) -> None:
        self.end()
        self.compiled.compiling()  # (collects the child)


def _counting_python(monkeypatch, after=None):
    """The Python kernels as the plan finds them while compiling, counting the readings they solve, and calling
    ``after(n)`` after each."""
    solved = []
    python = targets.python()

    class Counting:
        def entry(self, first, last, *args):
            python.entry(first, last, *args)
            solved.append(first)
            if after is not None:
                after(len(solved))

    monkeypatch.setattr(host, "targets_python", lambda: Counting())
    return solved


def test_readings_are_solved_as_python_while_compiling_and_compiled_after(monkeypatch):
    u = _readings(5)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05))
    warm = est.estimate(u)  # the compiled kernels' answers (the suite compiled them before the first test)
    compiled = est.plan().compiled
    with _Compiling(compiled) as child:
        solved = _counting_python(monkeypatch, after=lambda n: child.end() if n == 3 else None)
        assert est.compiling()
        cold = est.estimate(u)
    assert solved == [0, 1, 2]  # the first three as Python, then the child was done: the rest compiled
    assert not est.compiling()
    for name in ("num_forces", "status", "evaluations", "iterations"):
        assert torch.equal(getattr(cold, name), getattr(warm, name)), name
    torch.testing.assert_close(cold.forces.s, warm.forces.s, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(cold.forces.f, warm.forces.f, rtol=1e-12, atol=1e-15)


def test_batches_solved_as_python_while_compiling_take_turns(monkeypatch):
    """Two threads estimating while the kernels compile solve their batches as Python one after the other, not side
    by side: such a solve holds the interpreter lock, so side by side each would take as long as both."""
    import threading

    u = _readings(4)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05, threads=1))
    est.plan()
    order = []

    def solved(n):
        order.append(threading.current_thread().name)
        time.sleep(0.02)  # (hands the interpreter to the other thread, which would start its own batch)

    start = threading.Barrier(2)
    results = {}

    def work(k):
        start.wait()
        results[k] = est.estimate(u[2 * k : 2 * k + 2])

    with _Compiling(est.plan().compiled):
        _counting_python(monkeypatch, after=solved)
        threads = [threading.Thread(target=work, args=(k,), name=f"t{k}") for k in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
    assert sorted(order) == ["t0", "t0", "t1", "t1"]
    assert order[0] == order[1] and order[2] == order[3]  # one batch, then the other
    assert all(results[k].batch_size == 2 for k in range(2))


def test_no_deadline_cuts_a_reading_solved_while_compiling(monkeypatch):
    u = _readings(2)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05, time_budget=1e-9))
    cut = est.estimate(u)
    assert set(cut.statuses) == {"timeout"}  # the budget binds on the compiled kernels
    with _Compiling(est.plan().compiled):
        solved = _counting_python(monkeypatch)
        cold = est.estimate(u)
    assert solved == [0, 1] and "timeout" not in cold.statuses
    assert cold.statuses == tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05)).estimate(u).statuses


def test_a_stream_takes_one_reading_at_a_time_while_compiling(monkeypatch):
    u = _readings(4)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05))
    est.plan()
    readings = [{"id": i, "curvature": u[i].tolist()} for i in range(4)]
    with _Compiling(est.plan().compiled):
        _counting_python(monkeypatch)
        results = list(tr.stream(est, readings, tr.StreamOptions(workers=1)))
    assert [r.id for r in results] == [0, 1, 2, 3] and [r.batch for r in results] == [1, 1, 1, 1]
    assert all(r.error is None for r in results)


def test_a_stream_with_solver_threads_solves_one_reading_at_a_time_on_its_own_while_compiling(monkeypatch):
    """With solver threads, each reading is solved on the stream's own thread once the one before is answered: none
    waits in a solver thread behind another (its solve time would count that wait), and the solves never overlap."""
    from torchrod.io import stream as stream_module

    u = _readings(4)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05))
    est.plan()
    readings = [{"id": i, "curvature": u[i].tolist()} for i in range(4)]
    events = []
    send = stream_module._Stream.send

    def recorded(self, batch, threads=1):
        events.append("send")
        return send(self, batch, threads)

    monkeypatch.setattr(stream_module._Stream, "send", recorded)
    with _Compiling(est.plan().compiled):
        _counting_python(monkeypatch, after=lambda n: events.append("solved"))
        results = list(tr.stream(est, readings, tr.StreamOptions(workers=2)))
    assert [r.id for r in results] == [0, 1, 2, 3] and all(r.error is None for r in results)
    assert events == ["solved"] * 4  # (none handed to a solver thread)


def test_a_stream_that_learns_its_noise_answers_alike_cold_and_warm(monkeypatch):
    """A stream that learns its noise forms the same batches, each solved with the same learned noise, whether the
    kernels compile meanwhile (its readings then solved as Python, one at a time, until the compile ends in the
    middle of a batch) or not: the same answers bit for bit."""
    u = _readings(40)
    est = tr.Estimator(ROD)  # (no noise given: the stream learns it)
    est.plan()
    readings = [{"id": i, "curvature": u[i].tolist()} for i in range(40)]
    options = tr.StreamOptions(batch_size=16, workers=2, learn_noise=NoiseLearning(after=4, growth=2))

    def answers(results):
        return [{k: v for k, v in r.record.items() if k != "latency_ms"} for r in results]

    warm = list(tr.stream(est, readings, options))
    assert len({r.batch for r in warm}) >= 3  # (batches of several sizes: the learning's rounds, then full ones)
    assert sum("noise" in r.record for r in warm) >= 30
    with _Compiling(est.plan().compiled) as child:
        solved = _counting_python(monkeypatch, after=lambda n: child.end() if n == 7 else None)
        cold = list(tr.stream(est, readings, options))
    assert len(solved) == 7 and [r.batch for r in cold[:6]] == [1] * 6
    assert answers(cold) == answers(warm)


def test_a_tracking_stream_answers_alike_cold_and_warm(monkeypatch):
    """With tracking, each batch's readings also start from the last solution of the batch before: solved a reading
    at a time while compiling, a batch's readings still take the starts it was handed out with."""
    u = _readings(20)
    est = tr.Estimator(ROD, tr.EstimatorOptions(noise=0.05))
    est.plan()
    readings = [{"id": i, "curvature": u[i].tolist()} for i in range(20)]
    options = tr.StreamOptions(batch_size=6, track=True, learn_noise=None)

    def answers(results):
        return [{k: v for k, v in r.record.items() if k != "latency_ms"} for r in results]

    warm = list(tr.stream(est, readings, options))
    with _Compiling(est.plan().compiled) as child:
        solved = _counting_python(monkeypatch, after=lambda n: child.end() if n == 8 else None)
        cold = list(tr.stream(est, readings, options))
    assert len(solved) == 8
    assert answers(cold) == answers(warm)


def test_the_estimate_command_answers_each_reading_as_it_is_solved_while_compiling(tmp_path, monkeypatch, capsys):
    from torchrod.cli import main

    u = _readings(3)
    path = tmp_path / "r.jsonl"
    path.write_text("".join(json.dumps({"id": i, "curvature": u[i].tolist()}) + "\n" for i in range(3)))
    sizes = []
    estimate = tr.Estimator.estimate

    def counted(self, curvature, *args, **kwargs):
        sizes.append(curvature.shape[0])
        return estimate(self, curvature, *args, **kwargs)

    monkeypatch.setattr(tr.Estimator, "estimate", counted)
    with _Compiling(targets.cpu()):
        _counting_python(monkeypatch)
        assert main(["estimate", "--rod", "nitinol290", "--noise", "0.05", str(path)]) == 0
    assert sizes == [1, 1, 1]
    answers = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [a["id"] for a in answers] == [0, 1, 2] and all("forces" in a for a in answers)
    # Compiled: one batch (on one solver thread: on more, a thread that is free takes part of a batch still running)
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.05", "--workers", "1", str(path)]) == 0
    assert sizes == [1, 1, 1, 3]


def test_start_announces_the_background_compile_and_loads_when_it_is_done(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(targets, "COMPILE_CHILD", "import time; time.sleep(0.5)")
    monkeypatch.delenv("TORCHROD_COMPILE", raising=False)
    # (the stand-in compiles below take no time: their record of it must not be the real cache's "last time")
    monkeypatch.setenv("TORCHROD_CACHE_DIR", str(tmp_path / "root"))
    loaded = []

    def estimate_rows():  # (the entry's name: what the cache is looked for by)
        pass

    compiled = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: loaded.append(entry))
    compiled.start()
    err = capsys.readouterr().err
    assert "compiling the estimation kernels for the CPU in a background process" in err
    assert "meanwhile readings are solved one at a time by the kernels run as Python" in err
    assert compiled.compiling() and not loaded
    deadline = time.monotonic() + 30
    while compiled.compiling():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert loaded == [estimate_rows] and compiled._ready
    # Cached (an index file of the entry), or asked to compile in the foreground: loaded or compiled at once.
    (tmp_path / "x.estimate_rows-1.py311.nbi").write_text("")
    again = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: loaded.append(entry))
    again.start()
    assert not again.compiling() and again._ready and len(loaded) == 2
    # In the foreground: compiled by a child while this process waits (announced once, here), then loaded; should
    # the child fail, compiled here (announced again).
    monkeypatch.setenv("TORCHROD_COMPILE", "foreground")
    index = tmp_path / "x.estimate_rows-1.py311.nbi"
    index.unlink()
    child = f"import pathlib, sys; assert sys.argv[3] == 'cpu'; pathlib.Path({str(index)!r}).write_text('')"
    monkeypatch.setattr(targets, "COMPILE_CHILD", child)
    capsys.readouterr()
    third = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: loaded.append(entry))
    third.start()
    assert not third.compiling() and len(loaded) == 3 and index.exists()
    err = capsys.readouterr().err
    assert err.count("compiling the estimation kernels for the CPU (") == 1
    assert "background" not in err
    index.unlink()
    monkeypatch.setattr(targets, "COMPILE_CHILD", "raise SystemExit(1)")
    failed = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: loaded.append(entry))
    failed.start()
    assert not failed.compiling() and len(loaded) == 4
    assert capsys.readouterr().err.count("compiling the estimation kernels for the CPU (") == 2
    # A background child that ended without the kernels: compiled here, not by a second child.
    monkeypatch.delenv("TORCHROD_COMPILE")
    broken = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: loaded.append(entry))
    broken.start()
    monkeypatch.setattr(targets, "COMPILE_CHILD", child)  # (a second child would fill the cache: it must not run)
    deadline = time.monotonic() + 30
    while broken.compiling():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert len(loaded) == 5 and not index.exists()
    err = capsys.readouterr().err
    assert "in a background process" in err and err.count("compiling the estimation kernels for the CPU (") == 1
    monkeypatch.setenv("TORCHROD_COMPILE", "foreground")
    # No writable cache: a child's compile would be lost, so it is done here.
    monkeypatch.delenv("TORCHROD_COMPILE")
    fourth = targets.Compiled("cpu", estimate_rows, None, lambda entry: loaded.append(entry))
    fourth.start()
    assert not fourth.compiling() and len(loaded) == 6


def test_a_background_compile_that_could_not_write_the_cache_is_done_again_here_in_memory(
    tmp_path, monkeypatch, capsys
):
    """The compiling child could not write the kernels into the cache (a full disk: it said so, and ends with
    :data:`targets.UNKEPT`): the kernels are compiled here, announced as kept in memory, the cache neither read nor
    tried again."""
    monkeypatch.setattr(targets, "COMPILE_CHILD", f"raise SystemExit({targets.UNKEPT})")
    monkeypatch.delenv("TORCHROD_COMPILE", raising=False)
    monkeypatch.setenv("TORCHROD_CACHE_DIR", str(tmp_path / "root"))
    compiled_here = []

    def estimate_rows():  # (the entry's name: what the cache is looked for by)
        pass

    compiled = targets.Compiled("cpu", estimate_rows, tmp_path, lambda entry: compiled_here.append(entry))
    compiled.start()
    deadline = time.monotonic() + 30
    while compiled.compiling():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert compiled_here == [estimate_rows] and compiled._ready and compiled._unkept
    err = capsys.readouterr().err
    assert f"kept in memory: the kernel cache {tmp_path} cannot be written" in err
    assert not (tmp_path / ".lock").exists()  # (no lock taken for a compile the cache will not keep)


def test_a_process_that_waits_for_a_first_compile_runs_the_kernels_loaded_from_the_cache(tmp_path):
    """The network's kernels (the quickest to compile) compiled into an empty cache in the foreground: the process
    that asked for them runs them as loaded from the cache (a hit, no compile of its own), as a later run does."""
    program = (
        "from torchrod.kernels import targets; c = targets.cpu_network(); c.ready(); "
        "print(sum(c.entry.stats.cache_hits.values()), sum(c.entry.stats.cache_misses.values()))"
    )
    env = {**os.environ, "TORCHROD_CACHE_DIR": str(tmp_path), "TORCHROD_COMPILE": "foreground"}
    done = subprocess.run([sys.executable, "-c", program], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["1", "0"]
    assert "compiling the network kernels for the CPU" in done.stderr and "network kernels compiled in" in done.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_compiling_child_ends_with_its_parent(tmp_path):
    """The parent killed (SIGKILL: no exit handler runs): the child's watchdog ends it within a second or so."""
    pidfile = tmp_path / "child.pid"
    parent = textwrap.dedent(
        f"""
        import subprocess, sys, time
        child = subprocess.Popen([sys.executable, "-c",
            "import os, sys, time; from torchrod.kernels import targets; targets.die_with_parent(int(sys.argv[1])); "
            "open(sys.argv[2], 'w').write(str(os.getpid())); time.sleep(60)", str(__import__('os').getpid()),
            {str(pidfile)!r}])
        time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", parent])
    try:
        deadline = time.monotonic() + 60
        while not (pidfile.exists() and pidfile.read_text()):
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        child = int(pidfile.read_text())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        deadline = time.monotonic() + 10
        while _alive(child):
            assert time.monotonic() < deadline, "the compiling child outlived its killed parent"
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_kernel_function_is_compiled_once_whatever_constants_its_callers_pass():
    """Numba compiles a function called with the constant True and with False twice (each a literal type), and
    everything it calls with it; the kernels' dispatcher compiles it once, for a bool, with the same results."""
    import numba
    from numba.core import types as nb_types

    def scaled(x, double):
        return 2.0 * x if double else x

    general = patches.general(numba.njit(scaled), nb_types.unliteral)
    plain = numba.njit(scaled)

    @numba.njit
    def through_general(x):
        return general(x, True) + general(x, False)

    @numba.njit
    def through_plain(x):
        return plain(x, True) + plain(x, False)

    assert through_general(1.5) == through_plain(1.5) == 4.5
    assert len(plain.signatures) == 2  # the behaviour worked around: were it gone, so would be the need
    assert [tuple(map(str, sig)) for sig in general.signatures] == [("float64", "bool")]


def test_a_compile_optimises_the_whole_module_at_the_entry_alone():
    """Inside ``patches.optimised_at_entry``, Numba optimises the linked module of the entry only (a callee's library is
    linked into its caller and optimised there), with the same results; afterwards Numba is as it was."""
    import numba
    from numba.core import codegen

    original = codegen.CPUCodeLibrary._optimize_final_module
    optimised: list[str] = []

    def spy(lib):
        optimised.append(lib.name)
        original(lib)

    codegen.CPUCodeLibrary._optimize_final_module = spy
    try:

        @numba.njit(no_cpython_wrapper=True)
        def half_square(x):
            return 0.5 * x * x

        def whole_entry(x, n):
            t = 0.0
            for k in range(n):
                t += half_square(x + k)
            return t

        entry = numba.njit(whole_entry)
        with patches.optimised_at_entry(whole_entry.__qualname__):
            got = entry(0.25, 7)
        assert codegen.CPUCodeLibrary._optimize_final_module is spy  # restored
    finally:
        codegen.CPUCodeLibrary._optimize_final_module = original
    assert got == sum(0.5 * (0.25 + k) ** 2 for k in range(7))
    assert optimised == [whole_entry.__qualname__]  # half_square's library was compiled, and not optimised as a whole
