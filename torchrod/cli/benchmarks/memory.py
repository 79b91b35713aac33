"""``torchrod bench memory``: whether a long stream keeps its memory flat.

A ``torchrod stream --rod ROD --workers W`` process (the torchrod this benchmark runs) is fed ``--count`` readings
as JSON lines through a pipe, as fast as it takes them: ``--distinct`` simulated readings of a synthetic trajectory
(torchrod.synthetic.generate_trajectory, noise ``--noise`` [1/m]), cycled, each line with its own id, so that
no two lines are the same. Its answers are counted as they come, by a reader that keeps nothing of them. Every
``--interval`` seconds the resident memory (RSS, ``VmRSS`` of Linux's /proc) of the process and of any process it
started is sampled, with the count of answers so far.

Printed: a row per tenth of the run (the first sample at which that share of the readings was answered): the share
answered in whole per cent, rounded down (so that only all the readings read 100 %), the readings answered, the
seconds since the start, the RSS [MiB] and the number of processes; then the peak RSS, the
growth from the first tenth to the end and to the highest sample in between, in % (the first tenth leaves out the
start-up: imports, the kernels, the first batches), and the verdict against ``--limit`` (default 10 %) on the
larger of the two: a stream that holds on to something per reading (finished futures, records, a list of
latencies) grows with the count, one that does not stays flat. The exit status is 0 whatever the verdict (1 if the
stream failed: it answered fewer lines than it was sent, or exited with a status other than 0). Linux only (/proc).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..commands import rod_help
from . import SUITES
from .pacer import child_command, family

if TYPE_CHECKING:
    from ...rod import Rod

HELP = SUITES["memory"]

__all__ = ["HELP", "Sample", "configure", "growth", "reading_lines", "rss_bytes", "run", "tenths"]

LIMIT = 10.0
"""[%] Default largest growth of the RSS from the first tenth of the run to its end that counts as flat."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (__doc__ or "").split("\n\n", 1)[1].replace("``", "")
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument(
        "--count", type=int, default=1_000_000, help="readings sent through the stream (default 1000000)"
    )
    parser.add_argument(
        "--workers", type=int, default=2, metavar="W", help="the stream's --workers (default 2; 0: one per core)"
    )
    parser.add_argument("--distinct", type=int, default=256, help="simulated readings cycled through (default 256)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor noise of the readings [1/m] (default 0.1)")
    parser.add_argument(
        "--interval", type=float, default=0.5, metavar="S", help="seconds between memory samples (default 0.5)"
    )
    parser.add_argument(
        "--limit",
        type=float,
        default=LIMIT,
        metavar="PCT",
        help=f"largest growth that is flat [%%] (default {LIMIT:g})",
    )
    parser.add_argument(
        "--stream-option",
        action="append",
        default=[],
        metavar="OPT",
        help="one more option of the stream, e.g. --stream-option=--noise=0.1 (repeatable)",
    )
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2000 readings, 64 distinct")


@dataclass(frozen=True)
class Sample:
    """One sample: seconds since the start, answers so far, RSS of the stream's processes [bytes], their number."""

    t: float
    answered: int
    rss: int
    processes: int


def rss_bytes(pid: int) -> int:
    """Resident memory of process ``pid`` [bytes] (``VmRSS`` in /proc/PID/status); 0 when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return 0
    return 0


def reading_lines(rod: Rod, distinct: int, noise: float) -> list[tuple[str, str]]:
    """``distinct`` readings of a synthetic trajectory as the text around their id: (``'{"id": '``,
    ``', "t": T, "curvature": [...]}'``) with the curvature [1/m] to 1e-6 1/m, null for a missing grating."""
    import torch

    from ...synthetic import SensorModel, generate_trajectory

    sensor = SensorModel(noise=noise, location_bias=rod.location_bias)
    trajectory = generate_trajectory(rod, distinct, sensor=sensor, seed=0)
    u = torch.where(trajectory.mask.unsqueeze(-1), trajectory.curvature, math.nan).tolist()
    out = []
    for k in range(distinct):
        cells = [None if math.isnan(a) else [round(a, 6), round(b, 6)] for a, b in u[k]]
        out.append(('{"id": ', f', "t": {float(trajectory.t[k]):.4f}, "curvature": {json.dumps(cells)}}}\n'))
    return out


def tenths(samples: Sequence[Sample], count: int) -> list[Sample]:
    """The first sample at which each tenth of ``count`` readings was answered (10 %, 20 %, ..., 100 %), leaving out
    the tenths no sample reached; the last sample of the live stream stands for 100 % when none reached it."""
    live = [s for s in samples if s.rss > 0]
    out: list[Sample] = []
    for k in range(1, 11):
        due = math.ceil(k * count / 10)
        hit = next((s for s in live if s.answered >= due), None)
        if hit is None and k == 10 and live:
            hit = live[-1]
        if hit is not None and (not out or hit is not out[-1]):
            out.append(hit)
    return out


def growth(first: Sample, later: int) -> float:
    """The growth of the RSS from the sample ``first`` to ``later`` [bytes], in %."""
    return 100.0 * (later - first.rss) / first.rss if first.rss > 0 else math.nan


def run(args: argparse.Namespace) -> int:
    from ...presets import load as load_rod

    count, distinct = (2000, 64) if args.quick else (args.count, args.distinct)
    if count < 10 or distinct < 1:
        raise ValueError("--count must be >= 10 and --distinct >= 1")
    if args.workers < 0 or not args.interval > 0 or not args.limit >= 0:
        raise ValueError("--workers must be >= 0, --interval > 0 and --limit >= 0")
    if not os.path.exists("/proc/self/status"):
        raise ValueError("bench memory reads the processes' memory from /proc: Linux only")
    rod = load_rod(args.rod)
    texts = reading_lines(rod, min(distinct, count), args.noise)
    stream_args = ["--rod", args.rod, "--workers", str(args.workers), *args.stream_option]
    print(
        f"# torchrod bench memory: torchrod stream {' '.join(stream_args)}, {count} readings through a pipe "
        f"({len(texts)} distinct, cycled, each with its own id), RSS of its processes every {args.interval:g} s"
    )
    proc = subprocess.Popen(
        child_command("stream", *stream_args),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdin is not None and proc.stdout is not None and proc.stderr is not None  # all pipes
    answered = [0, 0]  # lines, error lines
    failed: list[BaseException] = []
    stderr_tail = bytearray()

    def write() -> None:
        stdin = proc.stdin
        assert stdin is not None
        try:
            for k0 in range(0, count, 256):
                chunk = []
                for k in range(k0, min(k0 + 256, count)):
                    head, tail = texts[k % len(texts)]
                    chunk.append(f"{head}{k}{tail}")
                stdin.write("".join(chunk).encode())
            stdin.close()
        except BaseException as exc:  # noqa: BLE001 - reported below
            failed.append(exc)

    def read() -> None:
        fd = proc.stdout.fileno()  # type: ignore[union-attr]
        rest = b""
        while data := os.read(fd, 2**16):
            lines = (rest + data).split(b"\n")
            rest = lines.pop()
            answered[1] += sum(1 for line in lines if b'"error": ' in line)
            answered[0] += len(lines)

    def drain_stderr() -> None:
        fd = proc.stderr.fileno()  # type: ignore[union-attr]
        while data := os.read(fd, 2**12):
            stderr_tail.extend(data)
            del stderr_tail[: max(0, len(stderr_tail) - 4000)]

    threads = [threading.Thread(target=f, daemon=True) for f in (write, read, drain_stderr)]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    samples: list[Sample] = []
    while proc.poll() is None:
        pids = family(proc.pid)
        rss = sum(rss_bytes(pid) for pid in pids)
        samples.append(Sample(time.perf_counter() - start, answered[0], rss, len(pids)))
        time.sleep(args.interval)
    elapsed = time.perf_counter() - start
    for thread in threads[1:]:
        thread.join(timeout=10)
    status = proc.wait()

    rows = tenths(samples, count)
    mib = 2**20
    print(f"{'share':>6} | {'answered':>9} {'s':>8} | {'RSS MiB':>8} {'procs':>5}")
    for row in rows:
        print(
            f"{100 * row.answered // count:>5d}% | {row.answered:>9} {row.t:>8.1f} | {row.rss / mib:>8.1f} "
            f"{row.processes:>5}"
        )
    peak = max((s.rss for s in samples), default=0)
    rate = answered[0] / elapsed if elapsed > 0 else math.nan
    print(
        f"# {answered[0]} answers ({answered[1]} error lines) in {elapsed:.1f} s ({rate:.0f} readings/s), "
        f"exit status {status}; {len(samples)} samples; peak RSS {peak / mib:.1f} MiB"
    )
    if len(rows) >= 2:
        # The end, and the highest sample in between (the last sample may fall in the exit's clean-up).
        first, end = rows[0], rows[-1]
        high = max(s.rss for s in samples if first.t <= s.t <= end.t)
        grew, worst = growth(first, end.rss), growth(first, high)
        verdict = "flat" if max(grew, worst) <= args.limit else "GROWS"
        print(
            f"# growth from the first tenth ({first.rss / mib:.1f} MiB) to the end ({end.rss / mib:.1f} MiB): "
            f"{grew:+.1f} %, to the highest sample in between ({high / mib:.1f} MiB): {worst:+.1f} %; {verdict} "
            f"(limit {args.limit:g} %)"
        )
    if failed or answered[0] != count or status != 0:
        why = f"; writing failed: {failed[0]}" if failed else ""
        text = stderr_tail.decode(errors="replace").strip()
        print(f"# the stream failed: {answered[0]} of {count} answered, exit status {status}{why}")
        if text:
            print("# its standard error ends: " + text[-1000:].replace("\n", "\n# "))
        return 1
    return 0
