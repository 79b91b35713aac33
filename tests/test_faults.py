"""Faults at the edges of the command line: named pipes as inputs, closed standard streams, degenerate rods, absurd
sizes, and outputs that would overwrite an input. Each must end in answers or in one clear error line, never in a
hang or a traceback."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cases import interruptible

import torchrod as tr
from torchrod.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
STREAM = ["stream", "--rod", "nitinol290", "--checkpoint", "none", "--noise", "0.05", "--max-forces", "1"]


def _lines(count: int) -> list[str]:
    """``count`` JSON reading lines of one force each on the paper's rod."""
    rod = tr.presets.nitinol290()
    loads = tr.PointForces.from_lists([[(0.15 + 0.004 * k, 0.3, -0.2)] for k in range(count)])
    u = tr.simulate(rod, loads).grating_curvature.tolist()
    return [json.dumps({"id": f"r{k}", "curvature": u[k]}) + "\n" for k in range(count)]


def _torchrod(*args: str) -> list[str]:
    return [sys.executable, "-X", "faulthandler", "-m", "torchrod", *args, "--threads", "1"]


def _shell(command: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``command`` through sh (for ``<&-`` and ``>&-``), in the repository root."""
    return subprocess.run(
        command, shell=True, cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=timeout, check=False
    )


def _waiting_for_a_writer(pid: int) -> bool:
    """Whether a thread of process ``pid`` waits in the kernel for the writer of a named pipe (Linux)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            if (task / "wchan").read_text().strip() == "wait_for_partner":
                return True
        except OSError:
            continue
    return False


# ---------------------------------------------------------------------------------------------------- named pipes
@pytest.mark.skipif(not hasattr(os, "mkfifo") or not Path("/proc/self/task").exists(), reason="Linux named pipes")
@pytest.mark.parametrize("command", ["stream", "estimate"])
def test_a_named_pipe_is_opened_once_and_every_line_is_answered(tmp_path, command):
    """The input is never opened to probe it: a probe took the writer's data (it wrote into the probe and died of
    SIGPIPE when the probe closed), and the real open then waited for a writer for good."""
    fifo = tmp_path / "readings"
    os.mkfifo(fifo)
    lines = _lines(6)
    written: list[BaseException | None] = [None]

    def writer() -> None:
        try:
            with open(fifo, "w", encoding="utf-8") as fh:  # blocks until the command opens the pipe
                fh.writelines(lines)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            written[0] = exc

    thread = threading.Thread(target=writer, daemon=True)
    thread.start()
    args = [*STREAM, "--input", str(fifo)] if command == "stream" else ["estimate", "--rod", "nitinol290", str(fifo)]
    proc = subprocess.Popen(_torchrod(*args), cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        out, err = proc.communicate(timeout=10)
        pytest.fail(f"the command hung on the named pipe; its stderr:\n{err.decode()[-4000:]}")
    finally:
        if thread.is_alive():  # free the writer, should the command never have opened the pipe
            with open(fifo, "rb"):
                pass
        thread.join(10)
    assert written[0] is None, f"the writer failed: {written[0]!r}"
    answers = [json.loads(x) for x in out.decode().splitlines()]
    assert proc.returncode == 0, err.decode()[-2000:]
    assert [a["id"] for a in answers] == [f"r{k}" for k in range(6)]
    assert all(a["num_forces"] == 1 for a in answers)


@pytest.mark.skipif(not hasattr(os, "mkfifo") or not Path("/proc/self/task").exists(), reason="Linux named pipes")
@pytest.mark.parametrize("command", ["stream", "estimate"])
def test_sigterm_ends_a_command_still_waiting_for_the_writer_of_its_named_pipe(tmp_path, command):
    fifo = tmp_path / "readings"
    os.mkfifo(fifo)
    args = [*STREAM, "--input", str(fifo)] if command == "stream" else ["estimate", "--rod", "nitinol290", str(fifo)]
    proc = subprocess.Popen(_torchrod(*args), cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 90
        while not _waiting_for_a_writer(proc.pid):
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "the command never came to open its input"
            time.sleep(0.1)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            status = proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            pytest.fail("SIGTERM did not end a command waiting for the writer of its named pipe")
        assert time.monotonic() - t0 < 10
        err = proc.stderr.read().decode()
        assert status == 143, err[-2000:]
        assert proc.stdout.read() == b"" and "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_an_interrupted_stream_does_not_wait_for_a_writer_that_never_comes(tmp_path):
    """The stream's flush after an interrupt takes what its reader already read; a reader still opening a named
    pipe (no writer yet) holds nothing, and the flush used to wait for it for good. In a child process, so that a
    hang is a failure, not a stuck test run."""
    fifo = tmp_path / "readings"
    os.mkfifo(fifo)
    script = f"""
import os, signal, threading, time
import torchrod as tr
from torchrod.io.readings import ReadingSource
from torchrod.io.stream import StreamOptions, stream
rod = tr.presets.nitinol290()
source = ReadingSource({str(fifo)!r}, rod.num_gratings, rod.gratings)
results = stream(tr.Estimator(rod, tr.EstimatorOptions(max_forces=1, noise=0.1)), source, StreamOptions())
threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
t0 = time.monotonic()
try:
    next(results)
except KeyboardInterrupt:
    print("flushed", round(time.monotonic() - t0, 1))
"""
    try:
        done = subprocess.run(
            [sys.executable, "-c", script],
            cwd=ROOT,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=90,
            check=False,
            preexec_fn=interruptible,  # (a test run started in the background ignores SIGINT, and its children)
        )
    except subprocess.TimeoutExpired:
        pytest.fail("the interrupted stream waited for a writer of its named pipe")
    assert done.stdout.startswith("flushed"), done.stderr[-2000:]


def test_check_input_never_opens_what_it_checks(tmp_path, monkeypatch):
    """check_input looks at the file (stat) and does not open it; a socket is refused by name."""
    import builtins
    import socket

    from torchrod.io.jsonl import check_input

    path = tmp_path / "in.jsonl"
    path.write_text("{}\n")
    opened = []
    real_open, real_os_open = builtins.open, os.open
    monkeypatch.setattr(builtins, "open", lambda *a, **k: opened.append(a) or real_open(*a, **k))
    monkeypatch.setattr(os, "open", lambda *a, **k: opened.append(a) or real_os_open(*a, **k))
    check_input(str(path), "--input")
    assert opened == []
    monkeypatch.undo()
    sock = socket.socket(socket.AF_UNIX)
    try:
        sock.bind(str(tmp_path / "s"))
        with pytest.raises(ValueError, match="is a socket"):
            check_input(str(tmp_path / "s"), "--input")
    finally:
        sock.close()


# ---------------------------------------------------------------------------------------------------- closed streams
@pytest.mark.parametrize(
    "args",
    [
        " ".join(STREAM),
        "estimate --rod nitinol290 -",
        "simulate --rod nitinol290 -",
        "calibrate --rod nitinol290 -",
    ],
)
def test_closed_standard_input_or_output_is_one_clear_error(args):
    exe = f"{sys.executable} -m torchrod {args}"
    closed_in = _shell(f"{exe} <&-")
    assert closed_in.returncode == 2, closed_in.stderr[-2000:]
    assert "standard input is closed" in closed_in.stderr and "Traceback" not in closed_in.stderr
    closed_out = _shell(f"{exe} >&- </dev/null")
    assert closed_out.returncode == 2, closed_out.stderr[-2000:]
    assert "standard output is closed" in closed_out.stderr and "Traceback" not in closed_out.stderr


def test_with_standard_output_closed_the_answers_go_to_out(tmp_path):
    """--out is the way to run with standard output closed: the answers land in the file (and the descriptor
    Python left free for standard output is not given to that file)."""
    readings, out = tmp_path / "r.jsonl", tmp_path / "a.jsonl"
    readings.write_text("".join(_lines(2)))
    done = _shell(f"{sys.executable} -m torchrod {' '.join(STREAM)} --input {readings} --out {out} >&-")
    assert done.returncode == 0, done.stderr[-2000:]
    assert [json.loads(x)["id"] for x in out.read_text().splitlines()] == ["r0", "r1"]


def test_a_command_that_prints_its_result_says_when_standard_output_is_closed():
    """Commands without --out (evaluate) used to print into nothing, silently, with status 0."""
    done = _shell(f"{sys.executable} -m torchrod evaluate --count-per-cell 1 --noise 0 --max-forces 1 >&-")
    assert done.returncode == 2 and "standard output is closed" in done.stderr and "Traceback" not in done.stderr


# ---------------------------------------------------------------------------------------------------- degenerate input
def test_a_fibre_with_cores_at_1e_150_m_is_refused_at_load(tmp_path, capsys):
    rod = tmp_path / "rod.json"
    r = 1e-150
    data = {**tr.presets.nitinol290().to_dict(), "fibre": {"cores": [[r, 0.0], [-r / 2, r], [-r / 2, -r]]}}
    rod.write_text(json.dumps(data))
    readings = tmp_path / "r.jsonl"
    readings.write_text("".join(_lines(1)))
    assert main(["estimate", "--rod", str(rod), str(readings)]) == 2
    err = capsys.readouterr().err
    assert "fibre.cores" in err and "1e-150" in err and "metres" in err
    with pytest.raises(tr.errors.RodError, match="fibre.cores"):
        tr.Rod.from_dict(data)


def test_a_rod_of_length_1e_300_is_refused_at_load_naming_the_value(tmp_path, capsys):
    rod = tmp_path / "rod.json"
    rod.write_text(json.dumps({"length": 1e-300, "bending_stiffness": 7e-3, "gratings": [0.0]}))
    forces = tmp_path / "f.jsonl"
    forces.write_text('{"forces": []}\n')
    assert main(["simulate", "--rod", str(rod), str(forces)]) == 2
    err = capsys.readouterr().err
    assert "length = 1e-300 m" in err and "1 mm to 20 m" in err and "Traceback" not in err


def test_generate_refuses_a_count_beyond_memory_up_front(tmp_path, capsys):
    t0 = time.monotonic()
    for extra in ([], ["--trajectory"]):
        out = tmp_path / ("x.jsonl" if extra else "x.npz")
        assert main(["generate", "--rod", "nitinol290", "--count", "100000000000", "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert "--count 100000000000 would need about" in err and "at a time" in err
        assert not out.exists()
    assert time.monotonic() - t0 < 30


def test_memory_per_case_follows_the_set_it_makes():
    """The estimate behind the refusal grows with the gratings and forces, and is far larger per trajectory
    reading (Python lists and dicts) than per set case (float64 tensors)."""
    from torchrod.cli.commands.generate import memory_per_case

    assert memory_per_case(14, 3, False) == 3 * (25 * 3 + 33 * 14)
    assert memory_per_case(28, 3, False) > memory_per_case(14, 3, False)
    assert memory_per_case(14, 3, True) > 5 * memory_per_case(14, 3, False)


# ---------------------------------------------------------------------------------------------------- outputs
def _files(tmp_path: Path) -> dict[str, Path]:
    rod = tmp_path / "rod.json"
    tr.presets.nitinol290().to_json(rod)
    readings = tmp_path / "readings.jsonl"
    readings.write_text("".join(_lines(2)))
    truth = tmp_path / "truth.jsonl"
    truth.write_text('{"id": "r0", "forces": []}\n{"id": "r1", "forces": []}\n')
    checkpoint = tmp_path / "net.pt"
    checkpoint.write_bytes(b"not read before the check")
    forces = tmp_path / "forces.jsonl"
    forces.write_text('{"forces": []}\n')
    calibration = tmp_path / "cal.jsonl"
    calibration.write_text(json.dumps({**json.loads(_lines(1)[0]), "forces": [{"s": 0.2, "fx": 0.3, "fy": 0}]}) + "\n")
    estimates = tmp_path / "estimates.jsonl"
    estimates.write_text('{"id": "r0", "forces": []}\n{"id": "r1", "forces": []}\n')
    data = tmp_path / "set.npz"
    data.write_bytes(b"not read before the check")
    return {
        "rod": rod,
        "readings": readings,
        "truth": truth,
        "checkpoint": checkpoint,
        "forces": forces,
        "calibration": calibration,
        "estimates": estimates,
        "data": data,
    }


CASES = {
    "estimate readings": (["estimate", "--rod", "{rod}", "{readings}", "--out", "{readings}"], "readings"),
    "estimate rod": (["estimate", "--rod", "{rod}", "{readings}", "--out", "{rod}"], "rod"),
    "estimate checkpoint": (
        ["estimate", "--rod", "{rod}", "{readings}", "--checkpoint", "{checkpoint}", "--out", "{checkpoint}"],
        "checkpoint",
    ),
    "stream input": ([*STREAM[:2], "{rod}", *STREAM[3:], "--input", "{readings}", "--out", "{readings}"], "readings"),
    "stream rod": ([*STREAM[:2], "{rod}", *STREAM[3:], "--input", "{readings}", "--out", "{rod}"], "rod"),
    "stream truth": (
        [*STREAM, "--input", "{readings}", "--summary", "--truth", "{truth}", "--out", "{truth}"],
        "truth",
    ),
    "stream checkpoint": (
        [*STREAM[:4], "{checkpoint}", *STREAM[5:], "--input", "{readings}", "--out", "{checkpoint}"],
        "checkpoint",
    ),
    "stream bag": ([*STREAM, "--input", "{readings}", "--output-bag", "{readings}"], "readings"),
    "simulate forces": (["simulate", "--rod", "{rod}", "{forces}", "--out", "{forces}"], "forces"),
    "simulate rod": (["simulate", "--rod", "{rod}", "{forces}", "--out", "{rod}"], "rod"),
    "calibrate readings": (["calibrate", "--rod", "{rod}", "{calibration}", "--out", "{calibration}"], "calibration"),
    "calibrate rod": (["calibrate", "--rod", "{rod}", "{calibration}", "--out", "{rod}"], "rod"),
    "generate rod": (["generate", "--rod", "{rod}", "--count", "4", "--out", "{rod}"], "rod"),
    "generate truth": (
        ["generate", "--trajectory", "--rod", "{rod}", "--count", "4", "--out", "{tmp}/s.jsonl", "--truth", "{rod}"],
        "rod",
    ),
    "plot readings": (
        ["plot", "{readings}", "{estimates}", "--rod", "{rod}", "--id", "r0", "--out", "{readings}"],
        None,
    ),
    "plot rod": (["plot", "{readings}", "{estimates}", "--rod", "{rod}", "--id", "r0", "--out", "{rod}"], None),
    "train rod": (["train", "--rod", "{rod}", "--checkpoint", "{rod}", "--epochs", "1"], "rod"),
    "train data": (["train", "--data", "{data}", "--checkpoint", "{data}", "--epochs", "1"], "data"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_an_output_that_names_an_input_is_refused_and_the_input_kept(tmp_path, capsys, case):
    files = _files(tmp_path)
    argv, victim = CASES[case]
    names = {**{k: str(v) for k, v in files.items()}, "tmp": str(tmp_path)}
    if case.startswith("plot"):  # a .png name for one figure: make the input such a name
        for key in ("readings", "rod"):
            png = tmp_path / f"{key}.png"
            files[key].rename(png)
            files[key] = png
            names[key] = str(png)
        victim = "readings" if case == "plot readings" else "rod"
    before = {k: p.read_bytes() for k, p in files.items()}
    status = main([a.format(**names) for a in argv])
    err = capsys.readouterr().err
    assert status == 2, err
    assert "would erase the input" in err and str(files[victim]) in err
    assert {k: p.read_bytes() for k, p in files.items()} == before


def test_generate_refuses_out_and_truth_on_one_file(tmp_path, capsys):
    path = tmp_path / "s.jsonl"
    assert main(["generate", "--trajectory", "--rod", "nitinol290", "--count", "4", "--out", str(path), "--truth",
                 str(path)]) == 2  # fmt: skip
    assert "same file" in capsys.readouterr().err and not path.exists()


def test_a_count_the_rod_cannot_determine_is_warned(tmp_path, capsys):
    """Three gratings give 6 values per reading: one force (3 unknowns) leaves 3 degrees of freedom to test its fit,
    two leave none. The default count follows the rod (no warning); a larger --max-forces is warned about."""
    rod = tmp_path / "rod.json"
    rod.write_text(json.dumps({"length": 0.29, "bending_stiffness": 7.39e-3, "gratings": [0.05, 0.15, 0.25]}))
    readings = tmp_path / "r.jsonl"
    readings.write_text('{"id": 0, "curvature": [[0.5, 0.1], [0.2, 0.0], [0.05, 0.0]]}\n')
    assert main(["estimate", "--rod", str(rod), "--noise", "0.1", str(readings)]) == 0
    assert not any("warning" in line for line in capsys.readouterr().err.splitlines())
    assert main(["estimate", "--rod", str(rod), "--noise", "0.1", "--max-forces", "3", str(readings)]) == 0
    err = capsys.readouterr().err
    assert (
        "torchrod estimate: warning: --max-forces 3 asks for more forces than a reading of this rod's 3 grating(s) "
        "can test (1: a fit of h forces has 3h unknowns"
    ) in err
    assert "more than 1 are never chosen" in err
    assert main(["estimate", "--rod", str(rod), "--noise", "0.1", "--max-forces", "1", str(readings)]) == 0
    assert not any("warning" in line for line in capsys.readouterr().err.splitlines())


NETWORK_GUESS = """
import torch, torchrod as tr
from torchrod.learn.warm_start import shipped_network
ws, _ = shipped_network(tr.presets.nitinol290())
u = torch.zeros(1, 14, 2, dtype=torch.float64)
u[0, :5, 0] = 3.0
print(ws.compiled_arrays(u, torch.ones(1, 14, dtype=torch.bool))[0].tolist())
"""


@pytest.mark.parametrize("part", ["nbi", "nbc"])
def test_a_damaged_kernel_cache_entry_is_compiled_again(tmp_path, part):
    """A cache file cut short (the index or the compiled code) is a missing entry: the run says so, compiles the
    kernels again and answers as before; the run after it loads them quietly."""
    env = {**ENV, "TORCHROD_CACHE_DIR": str(tmp_path)}

    def run() -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", NETWORK_GUESS], capture_output=True, text=True, env=env,
                              timeout=300, cwd=ROOT)  # fmt: skip

    first = run()
    assert first.returncode == 0, first.stderr[-2000:]
    files = list(tmp_path.rglob(f"*network_rows*.{part}"))
    assert files
    for path in files:
        path.write_bytes(path.read_bytes()[:20])
    second = run()
    assert second.returncode == 0, second.stderr[-2000:]
    assert "damaged copy of the network kernels" in second.stderr and "compiling them again" in second.stderr
    assert second.stdout == first.stdout
    third = run()
    assert third.returncode == 0 and third.stdout == first.stdout and "damaged" not in third.stderr


@contextlib.contextmanager
def _held_cache_lock(cache_root):
    """The CPU kernel cache's lock under ``cache_root``, held by this process (as a compiling process stopped by
    Ctrl-Z holds it)."""
    import fcntl

    from torchrod.kernels import targets

    old = os.environ.get("TORCHROD_CACHE_DIR")
    os.environ["TORCHROD_CACHE_DIR"] = str(cache_root)
    try:
        directory = targets._cache_directory("cpu")
    finally:
        if old is None:
            del os.environ["TORCHROD_CACHE_DIR"]
        else:
            os.environ["TORCHROD_CACHE_DIR"] = old
    with open(directory / ".lock", "a+") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def test_a_locked_kernel_cache_is_waited_for_with_a_word_and_a_bound(tmp_path):
    """Another process holding the cache's lock (stopped while compiling, say): the run says what it waits for,
    gives up after the bound, compiles the kernels itself and answers as a run with the cache free does."""
    env = {**ENV, "TORCHROD_CACHE_DIR": str(tmp_path), "TORCHROD_LOCK_WAIT": "2"}
    with _held_cache_lock(tmp_path):
        began = time.monotonic()
        waited = subprocess.run([sys.executable, "-c", NETWORK_GUESS], capture_output=True, text=True, env=env,
                                timeout=300, cwd=ROOT)  # fmt: skip
        took = time.monotonic() - began
    assert waited.returncode == 0, waited.stderr[-2000:]
    assert "waiting for another torchrod process that is compiling the kernels" in waited.stderr
    assert "still locked after 2 s: compiling the kernels here" in waited.stderr
    assert took < 120
    free = subprocess.run([sys.executable, "-c", NETWORK_GUESS], capture_output=True, text=True, env=env,
                          timeout=300, cwd=ROOT)  # fmt: skip
    assert free.returncode == 0 and free.stdout == waited.stdout and "waiting" not in free.stderr


def test_a_run_waiting_for_the_cache_lock_stops_on_sigterm(tmp_path):
    """Waiting for a locked cache, ``torchrod estimate`` ends promptly on SIGTERM (143), without a traceback."""
    readings = tmp_path / "r.jsonl"
    readings.write_text("".join(_lines(1)))
    env = {**ENV, "TORCHROD_CACHE_DIR": str(tmp_path / "cache"), "TORCHROD_LOCK_WAIT": "120"}
    (tmp_path / "cache").mkdir()
    with _held_cache_lock(tmp_path / "cache"):
        command = _torchrod("estimate", "--rod", "nitinol290", "--noise", "0.05", str(readings))
        pipe = subprocess.PIPE
        proc = subprocess.Popen(command, stdout=pipe, stderr=pipe, text=True, env=env, cwd=ROOT)
        deadline = time.monotonic() + 120
        seen = ""
        while "waiting for another torchrod process" not in seen and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            seen += line
        assert "waiting for another torchrod process" in seen, seen
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert time.monotonic() - sent < 10, "SIGTERM was not answered promptly"
    assert proc.returncode in (143, -signal.SIGTERM), (proc.returncode, err[-2000:])
    assert "Traceback" not in err


FULL_DISK = """
import errno
from numba.core import caching


def _no_space(self, name, data):
    raise OSError(errno.ENOSPC, "No space left on device")


caching.IndexDataCacheFile._save_data = _no_space  # (after the index is written: what a full disk leaves)
"""


def test_a_kernel_cache_on_a_full_disk_keeps_the_kernels_in_memory_and_leaves_no_entry(tmp_path):
    """Writing the compiled kernels into the cache fails (no space left, once the index is written): the run says so
    once, answers as a run with a cache does, and leaves no entry behind, so the next run announces its compile."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(FULL_DISK)
    cache = tmp_path / "cache"
    free = {**ENV, "TORCHROD_CACHE_DIR": str(cache)}
    full = {**free, "PYTHONPATH": str(site) + os.pathsep + ENV["PYTHONPATH"]}

    def run(env: dict[str, str]) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", NETWORK_GUESS], capture_output=True, text=True, env=env,
                              timeout=300, cwd=ROOT)  # fmt: skip

    first = run(full)
    assert first.returncode == 0, first.stderr[-2000:]
    assert first.stderr.count("could not write the network kernels into the kernel cache") == 1, first.stderr
    assert "No space left on device" in first.stderr and "Traceback" not in first.stderr
    assert "kept in memory" in first.stderr
    assert not list(cache.rglob("*network_rows*.nb[ic]")), "a partial entry was left in the cache"
    second = run(free)
    assert second.returncode == 0, second.stderr[-2000:]
    assert second.stdout == first.stdout
    assert "compiling the network kernels for the CPU" in second.stderr and "could not write" not in second.stderr
    assert list(cache.rglob("*network_rows*.nbc"))


CACHE_HITS = (
    "from torchrod.kernels import targets; c = targets.cpu_network(); c.ready(); "
    "print(sum(c.entry.stats.cache_hits.values()), sum(c.entry.stats.cache_misses.values()))"
)


def _read_only_run(cache: Path, program: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``program`` run with the folder ``cache`` read-only: its permissions taken away, or, for root (whom they do
    not stop), mounted read-only in a mount namespace of its own (skipped where that cannot be done)."""
    command = [sys.executable, "-c", program]
    if os.geteuid() == 0:
        mount = 'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" && exec "$@"'
        probe = subprocess.run(["unshare", "-m", "sh", "-c", mount, str(cache), "true"], capture_output=True,
                               check=False) if shutil.which("unshare") else None  # fmt: skip
        if probe is None or probe.returncode != 0:
            pytest.skip("root ignores permissions, and no read-only mount can be made here")
        command = ["unshare", "-m", "sh", "-c", mount, str(cache), *command]
    modes = {path: path.stat().st_mode for path in [cache, *cache.rglob("*")]}
    for path, mode in modes.items():
        path.chmod(mode & ~0o222)
    try:
        return subprocess.run(command, capture_output=True, text=True, env=env, timeout=300, cwd=ROOT, check=False)
    finally:
        for path, mode in modes.items():
            path.chmod(mode)


def test_a_read_only_cache_that_holds_the_kernels_is_loaded_from(tmp_path):
    """Kernels compiled into a cache that is read-only afterwards (a shared or packaged cache) are loaded from it,
    without a compile, a lock or a write."""
    env = {**ENV, "TORCHROD_CACHE_DIR": str(tmp_path)}
    first = subprocess.run([sys.executable, "-c", CACHE_HITS], capture_output=True, text=True, env=env, timeout=300,
                           cwd=ROOT)  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    again = _read_only_run(tmp_path, CACHE_HITS, env)
    assert again.returncode == 0, again.stderr[-2000:]
    assert again.stdout.split() == ["1", "0"], again.stdout  # a cache hit, no compile
    assert "compiling" not in again.stderr and "could not write" not in again.stderr, again.stderr


@pytest.mark.parametrize("command", ["stream", "estimate"])
def test_ctrl_c_during_a_first_compile_answers_the_readings_read_unsolved_at_once(tmp_path, command):
    """Interrupted while a first compile runs in the background (its readings solved as Python meanwhile), a stream
    solves nothing more: every reading it read is answered, in order, those not yet solved as such, it says so,
    and it ends at once, stopping the compile instead of waiting for it. ``torchrod estimate`` is the same stream."""
    count = 600
    readings = tmp_path / "r.jsonl"
    curvature = [json.loads(line)["curvature"] for line in _lines(30)]
    lines = (json.dumps({"id": f"r{k}", "curvature": curvature[k % 30]}) + "\n" for k in range(count))
    readings.write_text("".join(lines))
    args = [*STREAM, "--threads", "1", "--input", str(readings)]
    if command == "estimate":
        args = ["estimate", *STREAM[1:], str(readings)]
    script = f"""
import os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # (a shell's background job starts with it ignored)
from torchrod.cli import main
from torchrod.io import stream
from torchrod.kernels import targets
targets.COMPILE_CHILD = "import time; time.sleep(300)"  # (a first compile that outlasts the run)
advance, solved = stream._Stream.advance, []
def counted(self, flight):  # (Ctrl-C once 20 readings were solved as Python)
    solved.append(1)
    if len(solved) == 20:
        os.kill(os.getpid(), signal.SIGINT)
    return advance(self, flight)
stream._Stream.advance = counted
sys.exit(main([*{args!r}]))
"""
    env = {**ENV, "TORCHROD_CACHE_DIR": str(tmp_path / "cache")}  # (empty: the estimation kernels compile)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120, check=False, preexec_fn=interruptible)  # fmt: skip
    assert done.returncode == 130, done.stderr[-2000:]
    answers = [json.loads(line) for line in done.stdout.splitlines()]
    assert [a["id"] for a in answers] == [f"r{k}" for k in range(count)]
    unsolved = [k for k, a in enumerate(answers) if "not solved" in a.get("error", "")]
    assert unsolved and unsolved == list(range(unsolved[0], count)), "the readings after the interrupt were solved"
    assert 19 <= unsolved[0] <= 20 and all("forces" in a for a in answers[: unsolved[0]])
    assert f"answering the {len(unsolved)} readings read and not yet solved as not solved" in done.stderr
    assert "compile stopped with the run" in done.stderr and "Traceback" not in done.stderr
