"""``torchrod bench stream``: amortised estimation on a stream of readings against one reading at a time.

Readings: a synthetic trajectory (:func:`torchrod.synthetic.generate_trajectory`) of ``--count`` readings at
``--rate`` Hz: 1 to 3 contacts that appear, move, grow and vanish, Gaussian noise ``--noise`` per component. The
estimator (default options, count chosen among 0..3, told the noise; the warm-start network of ``--checkpoint``
when it fits the rod, loaded as :func:`torchrod.load_estimator` does: its guesses are starts beside the scan's
unless its recorded quality says it can be trusted; ``--set`` changes any option) runs
the same readings several ways, in one run:

* ``static, batched``: :meth:`Estimator.estimate` on consecutive batches of ``--batch-size`` (no tracking);
* ``static, one at a time``: :meth:`Estimator.estimate` on ``--single`` consecutive readings from the middle of
  the trajectory, one call each (latency: the call's wall time);
* ``stream, backlog, 1 thread``: :func:`torchrod.io.stream.stream` over all readings available at once on one solver
  thread (throughput; latency is then mostly the wait in the read-ahead queue);
* ``stream, backlog, P threads``: the same backlog on ``--workers`` P solver threads (``StreamOptions(workers=P)``,
  each batch whole in one thread): how throughput scales from one core to P;
* ``stream, backlog, no network`` (when a network is used): the same backlog without it;
* ``stream, backlog, noise learned`` and ``noise per reading``: the same backlog with an estimator told no noise,
  which the stream learns from its fits (:mod:`torchrod.estimate.noise`, the default) or, as before that existed,
  each reading estimates alone;
* ``stream, paced``: the first ``--paced`` readings, the source releasing reading k at k / ``--pace`` seconds (as an
  interrogator would; default: the trajectory's own rate, real time); latency from release to answer (a reading
  the stream is too busy to take waits, and that counts), batches closed by ``--max-latency-ms``;
* ``stream, one at a time``: batches of one on the same readings as ``static, one at a time``, each released when
  the previous answer is out (latency: release to answer).
* ``CLI, R Hz from outside`` (``--external``, default 100 and 1000 Hz): a ``torchrod stream`` process (the
  command's own options, with this run's ``--noise``, network, ``--batch-size`` and ``--threads``; ``--set`` does
  not reach it) fed the first ``--paced`` readings as JSON lines through a pipe at R Hz by a writer thread
  (:mod:`.pacer`), the latency measured by the writing process from the line's due time to reading its answer; at the
  first rate once per ``--external-budgets`` entry (default: the command's own time budget, and 10 ms), all with
  ``--external-workers`` threads (the command's ``--workers``, default 0: one per core). The timing starts after a
  warm-up of five lines, once the process is idle. A note per
  row gives the median latency over each tenth of the run (:func:`tenth_medians`; a stream that cannot keep up
  falls behind: its latency grows from tenth to tenth, where one that keeps up stays level after the first tenths,
  which start from an empty queue; the readings' difficulty varies along the trajectory, so a run needs enough
  seconds to tell the two apart), the answers' statuses (``timeout``: cut by the time budget) and how long the warm-up
  waited for an idle process. cpu ms is the child's; readings per batch and evaluations are not reported (the answers
  do not carry them).
* ``CLI, backlog from a file`` (with the ``--external`` rows): a ``torchrod stream`` process with the same options
  given every reading of the trajectory in a file (``--input FILE --summary``, answers to a file), as a recorded
  experiment is answered; readings/s by the command's own clock, from its first reading taken to its last answer
  written (its start-up and warm-up left out). Beside ``static, batched``, the estimate alone on every core over the
  same readings, it shows what reading the lines and writing the answers cost.

``--device`` (default cpu) runs every row on that device (e.g. ``cuda``: one GPU thread per reading): the readings
are moved to it, the CLI rows get the same ``--device``, and the row of P threads is left out.

The stream rows (and the CLI's) start each reading as the static estimator does; with ``--track`` they also start
small batches from the last answer's forces (``StreamOptions(track=True)``; in ``one at a time`` always one frame
old).

Per way: readings per second (wall), process CPU time per reading, latency median and 99th percentile, readings
per batch, the accuracy against the truth (count accuracy, and over the readings whose count is right the median
force error |f_est - f_true| [N] and location error [mm], forces paired in order of location), and the mean number
of forward-model evaluations per reading (every residual, with or without its Jacobian, of every fit and scan).
``--profile`` adds where the time goes in a backlog stream of (at most) the first 2000 readings on one thread, a
separate pass under cProfile (cumulative times): the network's guesses, the kernels (the whole search, compiled),
the rest of ``estimate`` (its set-up and report), and the stream's own work (batching, checking readings, result
records). Every timing follows a warm-up and, as in ``torchrod stream``, the set-up frozen out of the garbage
collector's full collections (:func:`torchrod.cli.commands.settle`); torch runs on ``--threads`` threads.
"""

from __future__ import annotations

import argparse
import ast
import cProfile
import dataclasses
import json
import math
import os
import pstats
import re
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import torch

from ...estimate.estimator import Estimator, EstimatorOptions
from ...io.stream import Reading, StreamOptions, StreamResult, StreamStats, stream, warm_up
from ...kernels.host import cpu_threads
from ...presets import load as load_rod
from ..commands import add_device_option, check_device, rod_help, settle
from . import SUITES
from .pacer import ExternalStream, child_command, cpu_time, reading_line, sleep_until

HELP = SUITES["stream"]

__all__ = ["HELP", "configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rod", default="nitinol290", help=rod_help("nitinol290"))
    parser.add_argument("--count", type=int, default=10_000, help="readings in the trajectory (default 10000)")
    parser.add_argument("--rate", type=float, default=100.0, help="trajectory frame rate [Hz] (default 100)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor sigma [1/m] (default 0.1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the trajectory (default 0)")
    parser.add_argument(
        "--batch-size", type=int, default=StreamOptions.batch_size, help="readings per batch (default %(default)s)"
    )
    parser.add_argument("--max-latency-ms", type=float, default=0.0, help="stream batching wait (default 0)")
    parser.add_argument(
        "--pace", type=float, default=None, help="paced stream release rate [Hz] (default: --rate, real time)"
    )
    parser.add_argument("--paced", type=int, default=2000, help="readings of the paced stream (default 2000)")
    parser.add_argument("--single", type=int, default=500, help="readings run one at a time (default 500)")
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="warm-start network, or 'none' (default: the shipped one if it fits)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an EstimatorOptions field for every way (repeatable; e.g. starts=1, lm.iterations=20)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    add_device_option(parser)
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        metavar="P",
        help="solver threads of the parallel backlog row (default 0: one per CPU core; 1: no such row)",
    )
    parser.add_argument(
        "--external",
        default="100,1000",
        metavar="HZ,...",
        help="rates of the externally paced `torchrod stream` rows (default 100,1000; 'none': no such rows)",
    )
    parser.add_argument(
        "--external-budgets",
        default="default,10",
        metavar="MS,...",
        help="--time-budget-ms of the externally paced rows at the first rate ('default': the command's own; "
        "default 'default,10'); the other rates run with the default",
    )
    parser.add_argument(
        "--external-workers",
        type=int,
        default=0,
        metavar="N",
        help="--workers of the externally paced rows (default 0: the command's default, one thread per core)",
    )
    parser.add_argument(
        "--track", action="store_true", help="the stream rows also start from the last answer (StreamOptions.track)"
    )
    parser.add_argument("--profile", action="store_true", help="where the time goes (a separate profiled pass)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 300 readings, 100 paced, 20 one at a time")


def _device_name(device: torch.device) -> str:
    """``cpu``, or a GPU's name beside its device (``cuda:0 (NVIDIA H100 80GB HBM3)``)."""
    if device.type != "cuda":
        return str(device)
    index = device.index if device.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


def _network(spec: str | None, rod: Any) -> tuple[Any, str]:
    from ...learn.warm_start import SHIPPED_CHECKPOINT, WarmStart

    if spec is not None and spec.lower() == "none":
        return None, "none"
    path = spec or SHIPPED_CHECKPOINT
    if spec is None and not os.path.exists(path):
        return None, "none (no shipped checkpoint)"
    try:
        return WarmStart.load(path, rod), os.path.relpath(path)
    except ValueError as exc:
        if spec is not None:
            raise
        return None, f"none ({exc})"


class _Row:
    def __init__(self, name: str) -> None:
        self.name = name
        self.stats = StreamStats()
        self.wall = self.cpu = 0.0
        self.evaluations = 0  # forward-model evaluations (residuals, with or without Jacobian) of solved readings
        self.external = False  # answers read from a `torchrod stream` process: no batch sizes or evaluations

    def line(self, width: int = 34) -> str:
        s = self.stats
        n = s.readings
        solved = n - s.errors
        per_batch = solved / s.batches if s.batches and not self.external else math.nan
        evals = self.evaluations / max(solved, 1) if not self.external else math.nan
        ferr, serr = (s.force_error(), 1e3 * s.location_error()) if s.right else (math.nan, math.nan)
        return (
            f"{self.name:<{width}} | {n:>6} {n / self.wall:>7.0f} {1e3 * self.cpu / n:>7.2f} | "
            f"{1e3 * s.latency(0.5):>7.1f} {1e3 * s.latency(0.99):>7.1f} | {per_batch:>6.1f} | "
            f"{100 * s.count_accuracy:>6.1f}% {ferr:>8.4f} {serr:>7.2f} | {evals:>6.1f}"
        )


def _timed(
    row: _Row, results: Iterable[StreamResult], truth: list[list[tuple[float, float, float]]], pids: Iterable[int] = ()
) -> None:
    """Drain ``results`` into ``row``; ids are trajectory frame indices; ``pids``: worker processes whose CPU time
    counts too."""
    w0, c0 = time.perf_counter(), time.process_time() + cpu_time(pids)
    batch, evaluations = None, []  # the last batch's result and its evaluations, read off the device once
    for r in results:
        row.stats.add(r, truth[r.id])
        if r._result is not None:  # (the batch's result: slicing it per reading would cost inside the timing)
            if r._result is not batch:
                batch, evaluations = r._result, r._result.evaluations.tolist()
            row.evaluations += evaluations[r._index]
    row.wall, row.cpu = time.perf_counter() - w0, time.process_time() + cpu_time(pids) - c0


def _external_rows(
    args: argparse.Namespace, rows: list[_Row], trajectory: Any, paced: int, truth: list, network: str
) -> list[str]:
    """The rows of ``torchrod stream`` processes fed from outside (:mod:`.pacer`), and a note per row: how the
    latency moved over the run (growing: the stream fell behind) and the answers' statuses."""
    spec = args.external.strip().lower()
    if spec == "none":
        return []
    try:
        rates = [float(x) for x in spec.split(",")]
        budgets = [None if x.strip() == "default" else float(x) for x in args.external_budgets.split(",")]
    except ValueError:
        raise ValueError(
            f"--external takes rates in Hz and --external-budgets ms or 'default', got {args.external!r} and "
            f"{args.external_budgets!r}"
        ) from None
    if not all(r > 0 and math.isfinite(r) for r in rates) or not all(b is None or b >= 0 for b in budgets):
        raise ValueError(f"--external rates must be positive and budgets >= 0, got {args.external!r}")
    if args.external_workers < 0:
        raise ValueError(f"--external-workers must be >= 0, got {args.external_workers}")
    checkpoint = "none" if network.startswith("none") else network
    base = ["--rod", args.rod, "--noise", f"{args.noise:g}", "--checkpoint", checkpoint]
    base += ["--batch-size", str(args.batch_size), "--threads", str(args.threads), "--device", args.device]
    if args.external_workers != 0:
        base += ["--workers", str(args.external_workers)]
    if args.track:
        base += ["--track"]
    u = torch.where(trajectory.mask.unsqueeze(-1), trajectory.curvature, math.nan).tolist()
    lines = [reading_line(k, float(trajectory.t[k]), u[k]) for k in range(len(u))]
    warm = [reading_line(f"warm-up {k}", None, u[k]) for k in range(min(5, paced))]
    runs = [(rates[0], b) for b in budgets] + [(r, None) for r in rates[1:]]
    notes = []
    for rate, budget in runs:
        extra = [] if budget is None else ["--time-budget-ms", f"{budget:g}"]
        name = f"CLI, {rate:g} Hz from outside" + ("" if budget is None else f", budget {budget:g} ms")
        if args.external_workers != 0:
            name += f", {args.external_workers} thr."
        row = _Row(name)
        row.external = True
        pacer = ExternalStream(base + extra, warm).start()
        latencies = []
        w0 = last = time.perf_counter()
        for r in pacer.run(lines[:paced], list(range(paced)), rate):
            last = time.perf_counter()
            row.stats.add(r, truth[r.id])
            latencies.append(r.latency)
        # (readings/s up to the last answer: the child's exit after it is not the stream's time)
        row.wall, row.cpu = last - w0, pacer.cpu
        rows.append(row)
        statuses = ", ".join(f"{k} {v}" for k, v in row.stats.statuses.items())
        tenths = " ".join(f"{1e3 * m:.0f}" for m in tenth_medians(latencies))
        notes.append(
            f"# {name}: latency median over each tenth of the run {tenths} ms; statuses: {statuses}; "
            f"{pacer.settled:.1f} s waited after the warm-up for idle processes"
        )
    notes.append(_backlog_row(base, lines, rows, truth))
    return notes


def _backlog_row(base: list[str], lines: list[str], rows: list[_Row], truth: list) -> str:
    """The row of a ``torchrod stream`` process given every line at once in a file (``--input FILE --summary``, its
    output to a file, as a recorded experiment is answered): its own readings/s over its stream (from the first
    reading taken to the last answer written, its start-up and warm-up left out), its answers' accuracy and their
    latency (the wait in its queue, mostly); cpu ms is not reported (the child's CPU time holds its start-up)."""
    row = _Row("CLI, backlog from a file")
    row.external = True
    with tempfile.TemporaryDirectory(prefix="torchrod-bench-") as folder:
        source, answers = os.path.join(folder, "readings.jsonl"), os.path.join(folder, "answers.jsonl")
        with open(source, "w") as fh:
            fh.writelines(line + "\n" for line in lines)
        with open(answers, "w") as out:
            done = subprocess.run(
                child_command("stream", *base, "--input", source, "--summary"),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.PIPE,
                text=True,
                check=False,
            )
        rate = re.search(r"(\d+) readings, \d+ errors, \d+ readings/s over ([0-9.]+) s", done.stderr)
        if done.returncode != 0 or rate is None:
            raise RuntimeError(
                f"torchrod stream {' '.join(base)} --input FILE --summary failed (exit status {done.returncode}): "
                f"{done.stderr.strip()[-500:]}"
            )
        with open(answers) as fh:
            for text in fh:
                record = json.loads(text)
                latency = 1e-3 * record.get("latency_ms", math.nan)
                row.stats.add(
                    StreamResult(record.get("id"), record.get("t"), record, latency, record.get("error")),
                    truth[record["id"]],
                )
    row.wall, row.cpu = float(rate.group(2)), math.nan
    rows.append(row)
    statuses = ", ".join(f"{k} {v}" for k, v in row.stats.statuses.items())
    # Beside the estimate alone in the same run: on a machine whose speed changes from minute to minute, the share
    # says more than either rate.
    alone = next((r for r in rows if r.name.startswith("static, batched")), None)
    share = ""
    if alone is not None and alone.stats.readings and alone.wall > 0 and row.wall > 0:
        ratio = (row.stats.readings / row.wall) / (alone.stats.readings / alone.wall)
        share = f" ({100 * ratio:.0f} % of the readings/s of '{alone.name}' in this run)"
    return f"# {row.name}: {rate.group(1)} readings in {row.wall:.2f} s by its own clock{share}; statuses: {statuses}"


def tenth_medians(values: Sequence[float]) -> list[float]:
    """The median of each tenth of ``values`` in order (fewer parts when there are fewer than ten values): a stream
    that keeps up has a level latency, one that falls behind a latency that grows from tenth to tenth."""
    n = len(values)
    parts = min(10, n)
    out = []
    for k in range(parts):
        part = sorted(values[k * n // parts : (k + 1) * n // parts])
        out.append(part[len(part) // 2])
    return out


def _static_batched(
    estimator: Estimator, curvature: torch.Tensor, mask: torch.Tensor, B: int
) -> Iterator[StreamResult]:
    for b0 in range(0, curvature.shape[0], B):
        t0 = time.perf_counter()
        res = estimator.estimate(curvature[b0 : b0 + B], mask[b0 : b0 + B])
        records = res.to_records(list(range(b0, b0 + res.batch_size)))
        dt = time.perf_counter() - t0
        for k, rec in enumerate(records):
            yield StreamResult(
                rec["id"], None, rec, latency=dt, batch=len(records), solve_time=dt, _result=res, _index=k
            )


def _static_single(
    estimator: Estimator, curvature: torch.Tensor, mask: torch.Tensor, frames: list[int]
) -> Iterator[StreamResult]:
    for k in frames:
        t0 = time.perf_counter()
        res = estimator.estimate(curvature[k : k + 1], mask[k : k + 1])
        (rec,) = res.to_records([k])
        dt = time.perf_counter() - t0
        yield StreamResult(k, None, rec, latency=dt, solve_time=dt, _result=res)


def _paced(items: list[Reading], rate: float, due: dict[Any, float]) -> Iterator[Reading]:
    """Release reading k at k / ``rate`` s (at once when late); ``due`` gets each reading's release time by id."""
    t0 = time.perf_counter()
    for k, item in enumerate(items):
        due[item.id] = t0 + k / rate
        sleep_until(due[item.id])
        yield item


def _since_due(results: Iterable[StreamResult], due: dict[Any, float]) -> Iterator[StreamResult]:
    """The results with their latency counted from the reading's release time, not from when the stream took it: a
    stream that falls behind stops taking readings once its read-ahead is full, and the wait before that is latency
    too."""
    for r in results:
        yield dataclasses.replace(r, latency=time.perf_counter() - due[r.id])


class _LockStep:
    """A source that releases the next reading only once the previous answer is out (``answered()``)."""

    def __init__(self, items: list[Reading]) -> None:
        self.items = items
        self.ready = threading.Semaphore(1)

    def __iter__(self) -> Iterator[Reading]:
        for item in self.items:
            self.ready.acquire()
            yield item

    def answered(self, results: Iterable[StreamResult]) -> Iterator[StreamResult]:
        for r in results:
            self.ready.release()
            yield r


_PHASES: list[tuple[str, Callable[[str, str], bool]]] = [
    ("network guesses", lambda f, n: f.endswith("warm_start.py") and n == "guess"),
    ("kernels", lambda f, n: f.endswith("host.py") and n == "run"),
]
"""Phases of an estimate, each a function's cumulative time (the kernels: the whole search of every reading)."""


def _profile_lines(profile: cProfile.Profile, wall: float, readings: int) -> list[str]:
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]

    def cumulative(match: Callable[[str, str], bool]) -> float:
        return sum(ct for (f, _, n), (_, _, _, ct, _) in stats.items() if match(f, n))

    total = cumulative(lambda f, n: f.endswith("estimator.py") and n == "estimate")
    head = f"# where the time goes: backlog stream of the first {readings} readings under cProfile, {wall:.2f} s"
    lines = [head + " wall (profiler overhead included):"]
    inside = 0.0  # the phases within estimate
    for name, match in _PHASES:
        t = cumulative(match)
        inside += t
        lines.append(f"#   {name:<20} {t:>7.2f} s  {100 * t / wall:>5.1f}%")
    rest, other = total - inside, wall - total
    lines.append(f"#   {'rest of estimate':<20} {rest:>7.2f} s  {100 * rest / wall:>5.1f}%")
    # The reader thread's work shows up wherever the main thread waits for the GIL, mostly outside estimate.
    lines.append(f"#   {'stream, records':<20} {other:>7.2f} s  {100 * other / wall:>5.1f}%")
    return lines


def _options(noise: float | None, settings: list[str], network: Any) -> EstimatorOptions:
    """EstimatorOptions(noise=noise) (with a trusted network, ``trust_guesses``, as ``load_estimator``
    sets it), then the ``FIELD=VALUE`` settings (values as Python literals; ``lm.FIELD`` and ``search.FIELD`` set a
    field of the Levenberg-Marquardt policy or of the search options)."""
    from ...learn.warm_start import is_trusted

    options = EstimatorOptions(noise=noise, trust_guesses=is_trusted(network))
    for setting in settings:
        name, sep, text = setting.partition("=")
        if not sep:
            raise ValueError(f"--set takes FIELD=VALUE, got {setting!r}")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            raise ValueError(f"--set {setting!r}: the value must be a Python literal") from None
        name = name.strip()
        part, dot, field = name.partition(".")
        if dot and part in ("lm", "search"):
            inner = dataclasses.replace(getattr(options, part), **{field: value})
            options = dataclasses.replace(options, **{part: inner})
        else:
            options = dataclasses.replace(options, **{name: value})
    return options


def run(args: argparse.Namespace) -> int:
    from ...synthetic import SensorModel, generate_trajectory

    rod = load_rod(args.rod)
    count, single, paced = (300, 20, 100) if args.quick else (args.count, args.single, args.paced)
    if min(count, single, paced, args.batch_size, args.threads) < 1:
        raise ValueError("--count, --single, --paced, --batch-size and --threads must be >= 1")
    if args.workers < 0:
        raise ValueError(f"--workers must be >= 0 (0: one per CPU core), got {args.workers}")
    device = check_device(args)
    workers = cpu_threads(args.workers or None)
    pace = args.rate if args.pace is None else args.pace
    if not (pace > 0 and args.rate > 0 and args.max_latency_ms >= 0):
        raise ValueError("--pace and --rate must be positive, --max-latency-ms >= 0")
    single, paced = min(single, count), min(paced, count)
    window = list(range((count - single) // 2, (count - single) // 2 + single))
    torch.set_num_threads(args.threads)
    network, network_name = _network(args.checkpoint, rod)
    estimator = Estimator(rod, _options(args.noise, args.set, network), warm_start=network)
    trajectory = generate_trajectory(
        rod,
        count,
        rate=args.rate,
        sensor=SensorModel(noise=args.noise, location_bias=rod.location_bias),
        seed=args.seed,
    )
    truth = [[(f["s"], f["fx"], f["fy"]) for f in t["forces"]] for t in trajectory.truth]
    curvature, mask = trajectory.curvature, trajectory.mask
    items = [
        Reading(k, torch.where(mask[k].unsqueeze(-1), curvature[k], math.nan), float(trajectory.t[k]))
        for k in range(count)
    ]
    B = args.batch_size
    options = StreamOptions(
        batch_size=B, max_latency=args.max_latency_ms / 1e3, track=args.track, device=device, workers=1
    )
    counts = [len(t) for t in truth]
    print(
        f"# torchrod bench stream: {count} readings of a {args.rate:g} Hz trajectory "
        f"({', '.join(f'{sum(c == h for c in counts)} with {h}' for h in sorted(set(counts)))} forces), "
        f"noise {args.noise:g} 1/m (known but where a row says otherwise), "
        f"count chosen in 0..{estimator.options.max_forces}, "
        f"network {network_name}, torch threads {torch.get_num_threads()}, device {_device_name(device)}"
    )
    print("# estimator options: " + ", ".join(f"{k}={v!r}" for k, v in dataclasses.asdict(estimator.options).items()))
    warm_up(estimator, device)
    settle()  # as `torchrod stream` does once it is set up (commands.settle)
    rows = []

    row = _Row(f"static, batched (B={B})")
    on_device = curvature.to(device), mask.to(device)
    _timed(row, _static_batched(estimator, *on_device, B), truth)
    rows.append(row)

    row = _Row("static, one at a time")
    _timed(row, _static_single(estimator, *on_device, window), truth)
    rows.append(row)

    row = _Row(f"stream, backlog, 1 thread (B<={B})")
    _timed(row, stream(estimator, items, options), truth)
    rows.append(row)

    if workers > 1 and device.type == "cpu":
        row = _Row(f"stream, backlog, {workers} threads")
        _timed(row, stream(estimator, items, dataclasses.replace(options, workers=workers)), truth)
        rows.append(row)

    if network is not None:
        # The same backlog without the network: what its guesses save (or cost).
        bare = Estimator(rod, _options(args.noise, args.set, None))
        row = _Row("stream, backlog, no network")
        _timed(row, stream(bare, items, options), truth)
        rows.append(row)

    # The same backlog from an estimator told no noise: learned from the stream's fits, and estimated per reading.
    blind = Estimator(rod, _options(None, args.set, network), warm_start=network)
    for name, learn in (("learned", options.learn_noise), ("per reading", None)):
        row = _Row(f"stream, backlog, noise {name}")
        _timed(row, stream(blind, items, dataclasses.replace(options, learn_noise=learn)), truth)
        rows.append(row)

    row = _Row(f"stream, paced {pace:g} Hz")
    due: dict[Any, float] = {}
    _timed(row, _since_due(stream(estimator, _paced(items[:paced], pace, due), options), due), truth)
    rows.append(row)

    notes = _external_rows(args, rows, trajectory, paced, truth, network_name)

    lock = _LockStep([items[k] for k in window])
    row = _Row("stream, one at a time")
    single_options = StreamOptions(batch_size=1, max_latency=0.0, track=args.track, device=device)
    _timed(row, lock.answered(stream(estimator, lock, single_options)), truth)
    rows.append(row)

    width = max(len(row.name) for row in rows)
    print(
        f"{'way':<{width}} | {'rd':>6} {'rd/s':>7} {'cpu ms':>7} | {'lat ms':>7} {'p99':>7} | {'rd/bt':>6} | "
        f"{'count':>7} {'f err N':>8} {'s err mm':>7} | {'evals':>6}"
    )
    for row in rows:
        print(row.line(width))
    for note in notes:
        print(note)
    if args.profile:
        # A separate pass, so that the profiler's overhead stays out of the table.
        profiled = _Row("profiled")
        profile = cProfile.Profile()
        profile.enable()
        _timed(profiled, stream(estimator, items[: min(count, 2000)], options), truth)
        profile.disable()
        for line in _profile_lines(profile, profiled.wall, profiled.stats.readings):
            print(line)
    return 0
