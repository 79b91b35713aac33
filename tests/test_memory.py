"""Memory and leftovers of the readings commands: a line of tens of MB costs no more than a short one, and a killed
stream leaves no process and no file behind. (A long stream's memory: ``torchrod bench memory``, too slow for a
test at a length that tells.)"""

from __future__ import annotations

import io
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

import torchrod as tr
from torchrod.io.jsonl import Overlong, read_lines
from torchrod.io.readings import MIN_LINE_BYTES, iter_readings, line_limit

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
QUICK = ["--rod", "nitinol290", "--checkpoint", "none", "--noise", "0.05", "--max-forces", "1", "--threads", "1"]
LINUX = pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")


def _lines(count: int) -> list[str]:
    """``count`` JSON reading lines of one force each on the paper's rod (ids r0, r1, ...)."""
    rod = tr.presets.nitinol290()
    loads = tr.PointForces.from_lists([[(0.15 + 0.1 * (k % 11) / 11, 0.3, -0.2)] for k in range(count)])
    u = tr.simulate(rod, loads).grating_curvature.tolist()
    return [json.dumps({"id": f"r{k}", "curvature": u[k]}) + "\n" for k in range(count)]


def _torchrod(*args: str) -> list[str]:
    return [sys.executable, "-m", "torchrod", *args]


def _peak_rss(args: list[str], out: Path, timeout: float = 120.0) -> tuple[int, int]:
    """Run ``torchrod ARGS`` with standard output to ``out``: (its exit status, its peak RSS [bytes], from
    ``wait4``: this child's alone)."""
    with open(out, "wb") as fh:
        proc = subprocess.Popen(_torchrod(*args), cwd=ROOT, env=ENV, stdout=fh, stderr=subprocess.DEVNULL)
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        timer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)  # (reaped here: Popen must not wait for it again)
    return proc.returncode, usage.ru_maxrss * 1024  # (kB on Linux)


# ---------------------------------------------------------------------------------------------------- long lines
def test_the_line_limit_follows_the_rod():
    """1 MiB for any rod of up to thousands of gratings (a reading of the paper's rod is a few hundred bytes),
    64 bytes per value of the largest reading above that."""
    assert line_limit(14) == MIN_LINE_BYTES == 2**20
    assert line_limit(100_000) == 64 * 100_000 * 3
    rod = tr.presets.nitinol290()
    assert len(_lines(1)[0]) < 1000 < line_limit(rod.num_gratings, rod.fibre)


def test_a_reading_line_over_the_rods_limit_is_an_error_line_unless_the_limit_is_raised(tmp_path):
    (good,) = _lines(1)
    path = tmp_path / "in.jsonl"
    path.write_text('{"id": "pad", "curvature": ' + json.dumps([[0.0, 0.0]] * 200_000) + "}\n" + good)
    assert path.stat().st_size > MIN_LINE_BYTES
    readings = list(iter_readings(path, 14))
    assert [r.error for r in readings] == [f"line 1: longer than {MIN_LINE_BYTES} bytes; not read", None]
    assert readings[1].id == "r0"
    raised = list(iter_readings(path, 14, max_line=4 * MIN_LINE_BYTES))
    assert raised[0].id == "pad" and "curvature holds 200000 gratings" in raised[0].error and raised[1].ok


def test_a_text_stream_takes_at_most_the_limit_of_a_line_at_once():
    """An open text stream (a replaced stdin) is bounded as a file is: the long line comes as an Overlong, the next
    line after it, numbered as in the input."""
    lines = list(read_lines(io.StringIO('{"a": 1}\n' + "x" * 50_000 + "\n\n" + '{"b": 2}\n' + "y" * 3000), None, 1000))
    assert [n for n, _ in lines] == [1, 2, 4, 5]
    assert lines[0][1] == '{"a": 1}\n' and lines[2][1] == '{"b": 2}\n'
    assert isinstance(lines[1][1], Overlong) and lines[1][1].limit == 1000
    assert isinstance(lines[3][1], Overlong)


@LINUX
@pytest.mark.parametrize("command", ["stream", "estimate"])
def test_lines_of_tens_of_megabytes_cost_no_memory_and_the_next_line_is_answered(tmp_path, command):
    """A 60 MB line and a 15 MB line of small numbers (decoded, about 20 bytes of Python objects per byte: the 15 MB
    one took 270 MB more when lines up to 16 MiB were decoded) are one error line each, read past in chunks; the
    command's peak RSS stays within 32 MiB of the same command reading the good line alone, and the good line after
    them is answered."""
    (good,) = _lines(1)
    path = tmp_path / "long.jsonl"
    with open(path, "w") as fh:
        for size in (60_000_000, 15_000_000):
            fh.write('{"id": "long", "curvature": [')
            for _ in range(size // 600_000):
                fh.write("[0,0]," * 100_000)
            fh.write("[0,0]]}\n")
        fh.write(good)
    alone = tmp_path / "good.jsonl"
    alone.write_text(good)

    def run(source: Path) -> tuple[int, int, list[dict]]:
        where = ["--input", str(source)] if command == "stream" else [str(source)]
        extra = ["--workers", "2"] if command == "stream" else []
        status, rss = _peak_rss([command, *QUICK, *extra, *where], tmp_path / "out.jsonl")
        return status, rss, [json.loads(x) for x in (tmp_path / "out.jsonl").read_text().splitlines()]

    status, base, out = run(alone)
    assert status == 0 and [o["id"] for o in out] == ["r0"]
    status, peak, out = run(path)
    assert peak - base < 32 * 2**20, f"peak RSS {peak / 2**20:.0f} MiB against {base / 2**20:.0f} MiB"
    assert status == 1
    assert [o.get("error") for o in out[:2]] == [
        f"line {k}: longer than {MIN_LINE_BYTES} bytes; not read" for k in (1, 2)
    ]
    assert out[2]["id"] == "r0" and out[2]["num_forces"] == 1


# ---------------------------------------------------------------------------------------------------- SIGKILL
def _session(sid: int) -> list[int]:
    """The live processes of session ``sid`` (Linux's /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if fields[0] != "Z" and int(fields[3]) == sid:  # (state, ppid, pgrp, session)
            out.append(int(entry))
    return out


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@LINUX
def test_a_stream_killed_while_it_solves_leaves_no_process_and_no_file(tmp_path):
    """SIGKILL on ``torchrod stream --workers 2`` in the middle of a backlog (its solver threads busy, in its one
    process): within a few seconds no process of its session is left, and it left nothing in its temporary folder,
    in /tmp or in the kernels' cache (a copy of the warm one, so that only this process writes there)."""
    from torchrod.kernels.targets import cache_root

    path = tmp_path / "backlog.jsonl"
    path.write_text("".join(_lines(64)) * 100)  # 6400 readings: seconds of solving
    cache, temp = tmp_path / "cache", tmp_path / "tmp"
    shutil.copytree(cache_root(), cache)
    temp.mkdir()
    before_cache, before_tmp = _files(cache), set(os.listdir("/tmp"))
    env = {**ENV, "TORCHROD_CACHE_DIR": str(cache), "TMPDIR": str(temp)}
    out = tmp_path / "out.jsonl"
    with open(out, "wb") as fh:
        proc = subprocess.Popen(
            _torchrod("stream", *QUICK, "--workers", "2", "--input", str(path)),
            cwd=ROOT,
            env=env,
            stdout=fh,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + 120
        while out.stat().st_size == 0 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the stream ended before it was killed"
        assert out.stat().st_size > 0, "no answer within 120 s"
        assert len(os.listdir(f"/proc/{proc.pid}/task")) >= 3  # the main thread and the solver threads
        assert _session(proc.pid) == [proc.pid]  # threads of one process: no worker process
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
    deadline = time.monotonic() + 5
    while _session(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _session(proc.pid) == []
    answered = out.read_text().splitlines()
    assert 0 < len(answered) < 6400 and all("status" in json.loads(x) for x in answered[:-1])  # (the last may be cut)
    assert os.listdir(temp) == []
    assert _files(cache) == before_cache
    # (torchrod-startup-*: `torchrod bench startup`'s own folder, made by a test that may run beside this one)
    made = {name for name in set(os.listdir("/tmp")) - before_tmp if name.startswith("torchrod")}
    assert {name for name in made if not name.startswith("torchrod-startup-")} == set()
