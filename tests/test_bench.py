"""Smoke tests of ``torchrod bench``: each suite runs end to end and prints what it promises (no timing checks)."""

from __future__ import annotations

import os
import re
import time

import pytest
import torch

from torchrod.cli import main
from torchrod.cli.commands import bench


def test_bench_forward_quick_prints_both_tables(capsys):
    threads = torch.get_num_threads()
    assert main(["bench", "forward", "--quick", "--threads", "1"]) == 0
    assert torch.get_num_threads() == threads  # the suite restores the thread count
    out = capsys.readouterr().out
    assert "torch threads 1" in out
    # The speed table: every scheme at every batch size, with positive times and rates.
    for scheme in ("exact", "nodes q=90", "nodes q=250"):
        for B in (1, 16):
            row = re.search(rf"^{re.escape(scheme)}\s+{B}\s+(.*)$", out, re.MULTILINE)
            assert row, (scheme, B, out)
            numbers = [float(x) for x in row.group(1).split()]
            assert len(numbers) == 6 and all(x > 0 for x in numbers), row.group(0)
    # The accuracy table: the exact scheme meets its 1e-6 requirement on these large deflections, and the node
    # scheme's error falls from q = 90 to q = 250.
    acc = {
        m.group(1): float(m.group(2)) for m in re.finditer(r"^(exact|nodes q=\d+)\s+(\S+)\s+\S+$", out, re.MULTILINE)
    }
    assert set(acc) == {"exact", "nodes q=90", "nodes q=250"}, out
    assert acc["exact"] < 1e-6
    assert acc["nodes q=250"] < acc["nodes q=90"]


def test_bench_gpu_without_a_gpu_says_what_it_skips(capsys, monkeypatch):
    """``torchrod bench gpu`` on a machine without a GPU: every part it cannot run is named with the reason, and the
    run succeeds. (The lowering itself is tests/test_cuda.py's; here it is stood in for, to report its time.)"""
    from torchrod.cli.benchmarks import gpu

    pytest.importorskip("numba.cuda")
    monkeypatch.setattr(gpu, "lowering_seconds", lambda arch: 12.0)
    assert main(["bench", "gpu"]) == 0
    out = capsys.readouterr().out
    assert "lowering: the estimation kernel typed and lowered for sm_90 in 12 s" in out
    assert "PTX: skipped (without --ptx)" in out
    if not torch.cuda.is_available():
        assert "tests and throughput: skipped: torch sees no CUDA device" in out


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads /proc (Linux)")
def test_bench_memory_quick_prints_a_row_per_sample_tenth_and_the_verdict(capsys):
    """``torchrod bench memory --quick``: a stream process fed 2000 readings; rows of share, answers, seconds, RSS
    [MiB] and processes, the last at 100 %; the growth and a verdict. Whether the memory stays flat is the
    benchmark's to measure: here, that the growth line is made of the rows' numbers and the verdict follows from
    them and the limit."""
    assert main(["bench", "memory", "--quick", "--workers", "1", "--interval", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "torchrod stream --rod nitinol290 --workers 1, 2000 readings" in out
    rows = re.findall(r"^\s*(\d+)% \|\s+(\d+)\s+([\d.]+) \|\s+([\d.]+)\s+(\d+)$", out, re.MULTILINE)
    assert rows and rows[-1][:2] == ("100", "2000"), out
    assert all(float(rss) > 0 and int(procs) >= 1 for *_, rss, procs in rows)
    # rows in order: each a later tenth, with more answers, no earlier in time; each share is its answers'
    shares, answered, seconds = ([float(row[k]) for row in rows] for k in range(3))
    assert shares == sorted(set(shares)) and answered == sorted(set(answered)) and seconds == sorted(seconds)
    assert all(share == 100 * n // 2000 for share, n in zip(shares, answered, strict=True))  # (rounded down)
    assert "2000 answers (0 error lines)" in out
    growth = re.search(
        r"^# growth from the first tenth \(([\d.]+) MiB\) to the end \(([\d.]+) MiB\): ([+-][\d.]+) %, "
        r"to the highest sample in between \(([\d.]+) MiB\): ([+-][\d.]+) %; (flat|GROWS) \(limit 10 %\)$",
        out,
        re.MULTILINE,
    )
    assert growth, out
    first, end, grew, high, worst = (float(growth.group(k)) for k in range(1, 6))
    verdict = growth.group(6)
    assert len(rows) >= 2 and (first, end) == (float(rows[0][3]), float(rows[-1][3]))
    # each percentage from its MiB, within what the printing allows (percentages to 0.1 %, sizes to 0.1 MiB)
    for percent, later in ((grew, end), (worst, high)):
        slack = 0.05 + 100 * 0.05 * (1 + later / first) / first
        assert percent == pytest.approx(100 * (later - first) / first, abs=slack)
    # the highest sample between the first tenth and the end is no lower than either
    assert high >= max(first, end) - 0.05 and worst >= grew - 0.05
    if abs(worst - 10) > 0.05:  # a growth that rounds onto the limit may fall either side of it
        assert verdict == ("flat" if max(grew, worst) <= 10 else "GROWS")


def test_bench_rejects_unknown_and_reports_missing_suites(capsys, monkeypatch):
    assert main(["bench", "nosuch"]) == 2
    assert "unknown suite" in capsys.readouterr().err
    # A suite torchrod knows by name but whose module this version lacks.
    monkeypatch.setitem(bench.SUITES, "absent_suite_for_test", "a suite without a module")
    assert main(["bench", "absent_suite_for_test"]) == 2
    assert "not available" in capsys.readouterr().err


def test_bench_forward_rejects_bad_options(capsys):
    assert main(["bench", "forward", "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err


def test_the_pacer_sends_a_line_no_sooner_than_it_is_due():
    """``pacer.sleep_until`` (the pacer's wait for a line's due time, asleep and then active): it never returns before
    the time asked for, whether that is further away than its active wait, within it, or past."""
    from torchrod.cli.benchmarks import pacer

    for ahead in (0.0, -0.01, 0.1 * pacer.SPIN, 0.5 * pacer.SPIN, 2 * pacer.SPIN, 0.01):
        due = time.perf_counter() + ahead
        pacer.sleep_until(due)
        assert time.perf_counter() >= due


def test_the_pacer_waits_until_the_stream_and_its_workers_are_idle():
    """``pacer.wait_idle`` (the external pacer's wait before timing): a process whose child burns CPU for a
    second (as a stream's worker starting up does) is not idle until the burn ends; then it is, and ``family``
    finds the child. With a timeout within the burn it gives up and says so."""
    import subprocess
    import sys
    import time

    from torchrod.cli.benchmarks import pacer

    child = "import time\nt = time.time()\nwhile time.time() - t < 1.0: pass\ntime.sleep(60)"
    parent = f"import subprocess, sys, time\nsubprocess.Popen([sys.executable, '-c', {child!r}])\ntime.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", parent])
    try:
        t0 = time.perf_counter()
        while len(pacer.family(proc.pid)) < 2 and time.perf_counter() - t0 < 20:
            time.sleep(0.02)
        assert len(pacer.family(proc.pid)) == 2
        assert not pacer.wait_idle(proc.pid, 0.6)  # two windows, both within the burn
        assert pacer.wait_idle(proc.pid, 30.0)
        assert time.perf_counter() - t0 >= 1.0
    finally:
        for pid in pacer.family(proc.pid)[1:]:
            subprocess.run(["kill", str(pid)], check=False)
        proc.kill()
        proc.wait()


def test_tenth_medians_show_a_latency_that_grows_and_one_that_stays_level():
    from torchrod.cli.benchmarks.stream import tenth_medians

    growing = [0.001 * k for k in range(100)]  # a backlog that grows by a reading's wait every reading
    assert tenth_medians(growing) == [0.001 * (10 * k + 5) for k in range(10)]
    level = [0.5 + 0.1 * ((7 * k) % 3) for k in range(100)]
    assert max(tenth_medians(level)) - min(tenth_medians(level)) <= 0.1
    assert tenth_medians([3.0, 1.0, 2.0]) == [3.0, 1.0, 2.0] and tenth_medians([]) == []


def test_the_pacers_child_runs_this_torchrod_not_the_one_in_its_working_directory(tmp_path):
    """``python -m torchrod`` imports the package in the working directory first, whatever ``PYTHONPATH`` says, so
    a benchmark of one version run from another's checkout timed the other's CLI. The pacer's child runs the
    package its parent runs, even from a directory holding another ``torchrod``."""
    import subprocess
    import sys

    from torchrod.cli.benchmarks.pacer import child_command

    shadow = tmp_path / "torchrod"
    shadow.mkdir()
    (shadow / "__init__.py").write_text("raise ImportError('the torchrod of the working directory')\n")
    (shadow / "__main__.py").write_text("")
    assert subprocess.run([sys.executable, "-m", "torchrod", "--version"], cwd=tmp_path).returncode != 0
    out = subprocess.run(child_command("--version"), cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.startswith("torchrod "), out.stderr


def test_bench_backlog_runs_this_version_beside_another_checkout(capsys, tmp_path):
    """The backlog bench streams the same readings through this version and through a checkout given with
    ``--against`` (here a folder that imports this package), and reports both rates, their ratio and statuses."""
    import torchrod

    other = tmp_path / "other"
    (other / "torchrod").mkdir(parents=True)
    here = os.path.dirname(os.path.dirname(torchrod.__file__))
    # A checkout whose `python -m torchrod` runs this package's CLI: the bench cannot tell it from another version.
    (other / "torchrod" / "__init__.py").write_text(
        f"import sys\nsys.path.insert(0, {here!r})\ndel sys.modules['torchrod']\nimport torchrod\n"
    )
    (other / "torchrod" / "__main__.py").write_text("from torchrod.cli import main\nraise SystemExit(main())\n")
    assert main(["bench", "backlog", "--count", "60", "--runs", "1", "--against", str(other)]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("this version  ", str(other)))]
    assert len(rows) == 2 and all(re.search(r"\d+\s+ok \d+", row) for row in rows), out
    assert re.search(r"this version / .*: \d+\.\d\d", out), out
    assert main(["bench", "backlog", "--against", str(tmp_path)]) == 2  # not a checkout
