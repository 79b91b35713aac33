"""``torchrod stream``: forces from a live stream of FBG readings, answered as they arrive.

Usage: ``torchrod stream --rod ROD [--checkpoint C] [--input FILE | tcp://HOST:PORT]`` (default: standard input). ROD is
a rod JSON file or a preset name (the presets are listed under --rod). ``--input tcp://HOST:PORT`` connects to a server
that sends the readings and reads until it closes the connection.

Input, one reading a line, read as it arrives (a pipe from an interrogator is fine):

* JSON lines, the format of ``torchrod estimate`` plus an optional timestamp ``t`` [s]::

      {"id": "f000123", "t": 1.23, "curvature": [[ux, uy], null, ...]}

* or CSV, one reading a row. A first row of names (no numbers) is a header naming the columns: ``id`` and ``t``
  (optional), ``ux_1 .. ux_G`` and ``uy_1 .. uy_G`` (1-based, any order), or ``kappa_K, phi_K``, ``eps_K_C``,
  ``lambda_K_C``, ``dlambda_K_C`` for the other quantities; other columns are ignored. Without a header a row is
  ``id, t, ux_1, uy_1, ..., ux_G, uy_G`` [1/m] (or ``t`` and the values, or the values alone). All the cells of a
  missing grating are empty (``t`` may be empty too); an integer id stays an integer. A CSV number is
  ``[+-]digits[.digits][e[+-]digits]`` in ASCII (``12``, ``-1.5``, ``.5``, ``2.5E-3``; spaces around the cell are
  fine); ``1_000``, ``0x1f``, ``1 000`` are not numbers, and ``nan``/``inf`` are refused as not finite (leave a
  missing value's cell empty).

* or a ROS bag (``--input RUN --topic TOPIC``; ``pip install "torchrod[ros]"``): ``std_msgs/Float64MultiArray``
  messages of 2G values (ux, uy per grating, NaN for a missing one), ``t`` the bag's time stamp, ``id`` the
  message's index (torchrod.io.rosbag). ``--output-bag OUT`` also writes the answers into a new bag:
  ``/torchrod/estimate`` (String, the JSON answer), ``/torchrod/contact_<k>/wrench`` (WrenchStamped, body frame) and
  ``/torchrod/contact_<k>/arc_length`` (Float64, s [m]), NaN for an empty slot.

* or an interrogator's peak log (``TIME: l_1, ..., l_N`` [nm], ``--peaks`` says which peak is which grating and
  core; torchrod.io.peaklog), converted through the rod file's ``fibre.wavelength`` section;

* or, with ``--protocol fbgs``, the length-prefixed records of shape-sensing software: a 4-byte big-endian length,
  then tab-separated ASCII fields (date, time, sample number, the channels' peaks, then ``Curvature [1/cm]`` and
  one curvature magnitude per grating, a label and one bend angle [rad] per grating, then the shape, skipped);
  ``id`` is the sample number, ``t`` the time of day [s]. From ``tcp://HOST:PORT``, a recorded file or stdin; a
  record cut short or with another grating count is an error line (torchrod.io.fbgs has what is assumed).

A JSON line may give ``strain``, ``curvature_polar``, ``wavelength`` or ``wavelength_shift`` instead of
``curvature``; ``--strain-noise`` or ``--wavelength-noise`` [pm] gives the sensor's noise instead of ``--noise``,
and ``--curvature-unit``, ``--strain-unit``, ``--wavelength-unit`` the units the readings are in (default: the rod
file's fibre says, else 1/m, strain and nm; see ``torchrod estimate --help`` and docs/sensors.md).

``--format auto`` (the default) reads CSV for a .csv file and JSON lines for .jsonl, else JSON lines when the first
non-blank line starts with ``{``, a peak log when it is ``TIME: number, ...``, else CSV. The rules for a reading
are those of ``torchrod estimate`` (one parser for both): finite numbers, each curvature component at most 1e6 1/m
in magnitude, ids that JSON can echo.

Output: one JSON line per input line, in input order, each written and flushed as soon as its batch is solved::

    {"id", "status", "num_forces", "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"}, ...],
     "p_value", "loss", "converged", "iterations", "evaluations", "poorly_determined", "t", "latency_ms"}

(the fields of ``torchrod estimate``; ``t`` echoed when given; ``latency_ms`` from the moment the line was read to
its answer). Readings are solved in batches of up to ``--batch-size``: a line that finds the estimator idle is
solved at once, and lines that arrive while a batch is solved form the next batch (``--max-latency-ms`` MS makes a
batch wait up to MS for more lines; ``--workers N``, default 0: one per CPU core, solves each batch in one of N
threads while the next lines are read, so that a backlog or a file uses every core and a live source's consecutive
readings are solved on different cores).
Each reading starts from the scan of the estimator and the warm-start network's guess (as in
``load_estimator``, a network adds starts, never replaces the scan; ``--track`` adds the previous
reading's solution); the number of forces is chosen among 0..``--max-forces`` (``--noise``: the sensor's sigma
[1/m]). Without ``--noise`` the stream learns the sigma from its own fits (the median of each fit's loss over its
chi-square median, torchrod.estimate.noise): the first 32 fits estimate the noise per reading, every later batch
uses the learned sigma as a known noise and its answers carry it as ``"noise"`` [1/m]; ``--per-reading-noise`` keeps
estimating it per reading instead. Each reading has a time budget, ``--time-budget-ms`` (default 50; 0 answers
at once with no fit): a batch of B readings stops searching B times it after it began, and the readings it cut
short are answered with the best fit found so far and ``"status": "timeout"``. ``--checkpoint`` defaults to the
network shipped for the rod's grating layout (``nitinol290``'s, as in ``torchrod estimate``), else the stream runs
without a network (said once on stderr); ``--checkpoint none`` turns the network off. ``--out FILE`` writes the
answers to FILE.
``--device cuda`` estimates on a GPU (the same kernels compiled by numba-cuda; needs ``torchrod[cuda]``).

Every non-blank input line gets exactly one output line (a CSV header excepted; a CSV row whose quoted cell holds a
line break is one row over several lines, answered once). A line that cannot be used (bad
JSON or CSV, a wrong number of gratings, NaN, a value out of bounds, all gratings missing) gives
``{"id": ... or null, "error": "line N: ..."}`` naming the field and quoting at most about 100 characters of the
value, and the stream goes on; missing gratings are left out of the fit. The end of the input, Ctrl-C and SIGTERM
answer every line read so far before stopping. Memory stays bounded (a batch and a bounded read-ahead; a line
longer than ``--max-line-bytes``, by default 1 MiB, more for a rod of thousands of gratings, is an error line, read
past without being held). ``--input`` may be a named pipe or a
device: it is opened once, and SIGTERM ends a stream still waiting for the pipe's writer. ``--out`` and
``--output-bag`` never name an input. Exit status: 0, or 1 if any line failed or the output bag could not be written
(a full disk: said once on stderr, the answers go on), 130 after Ctrl-C, 143 after SIGTERM, 141 when the reader of
the output goes away, 2 for a bad rod, checkpoint or option, a damaged input bag (after the answers of the messages
before the damage) or a closed standard input or output.

With ``--output-bag``, a reading whose ``t`` the bag cannot hold as a time stamp (ROS 1: 0 <= t < 2^32 s; ROS 2:
0 <= t < 2^31 s; so not milliseconds since the epoch) is answered with an error line saying so and left out of
the bag; the others are written, and the bag stays readable.

``--summary`` prints to stderr at the end: readings, errors, readings/s, the latency (from reading a line to
answering it) median and 99th percentile beside the solve time per batch and per reading, and with ``--truth FILE``
(``{"id", "forces": [{"s", "fx", "fy"}, ...]}`` per line, as ``torchrod generate --trajectory`` writes) the count
accuracy and the median force and location errors of the readings whose count is right. Latency is what a live
source at its real rate sees; for input that comes faster than it is solved (a file read at once) it includes the
time readings wait behind earlier ones, which grows with the file, and the summary says so: the solve time per
reading is then the cost of estimation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from typing import Any, cast

from ...errors import ReadingError
from ...estimate.estimator import Estimator, EstimatorOptions
from ...estimate.noise import NoiseLearning
from ...estimate.options import LMPolicy
from ...io.formats import INPUT_FORMATS, topic_help
from ...io.jsonl import (
    LineWriter,
    check_input,
    check_keys,
    check_output,
    get_list,
    get_number,
    interrupt_status,
    open_output,
    parse_records,
    read_lines,
    same_path,
    until_interrupted,
)
from ...io.sources import ReadingSource
from ...io.stream import StreamOptions, StreamResult, StreamStats, answer_each, warm_up
from ...presets import load as load_rod
from ...rod import Rod
from . import (
    add_device_option,
    add_input_options,
    add_sensor_options,
    add_time_budget_option,
    check_device,
    check_estimation_options,
    reading_source,
    rod_help,
    sensor_noise,
    sensor_rod,
    settle,
    time_budget,
)
from .estimate import (
    add_merge_patches_option,
    add_workers_option,
    check_counts,
    check_workers,
    choose_network,
    trusting,
)

HELP = "amortised estimation on a stream of readings"

DEFAULT_TIME_BUDGET_MS = 50.0
"""The stream's default time budget per reading [ms] (``--time-budget-ms``): long enough that few readings are cut
short on a 2-core CPU, short enough to bound the slow tail of one reading's search."""

__all__ = ["HELP", "configure", "load_truth", "read_stream", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--rod", required=True, help=rod_help())
    parser.add_argument(
        "--checkpoint",
        default=None,
        metavar="C",
        help="warm-start network checkpoint, or 'none' (default: the network shipped for the rod's grating layout, if "
        "any, as in torchrod estimate)",
    )
    parser.add_argument(
        "--input", default="-", metavar="FILE", help="readings file, or tcp://HOST:PORT (default '-': stdin)"
    )
    add_input_options(parser)
    parser.add_argument(
        "--topic",
        help="read --input as a ROS bag (ROS 1 .bag, ROS 2 directory) and take the readings from TOPIC "
        f"({topic_help()}; needs pip install 'torchrod[ros]')",
    )
    parser.add_argument(
        "--output-bag",
        metavar="OUT",
        help="also write the estimates into a new ROS bag OUT (a ROS 1 bag if it ends in .bag, else a ROS 2 "
        "directory): /torchrod/estimate (String, the JSON answer), /torchrod/contact_<k>/wrench (WrenchStamped) "
        "and /torchrod/contact_<k>/arc_length (Float64)",
    )
    add_sensor_options(parser)
    add_merge_patches_option(parser)
    parser.add_argument("--out", metavar="FILE", help="write the answers to FILE (default: standard output)")
    parser.add_argument(
        "--batch-size",
        type=int,
        default=StreamOptions.batch_size,
        metavar="B",
        help="most readings per batch (%(default)s)",
    )
    parser.add_argument(
        "--max-latency-ms",
        type=float,
        default=0.0,
        metavar="MS",
        help="longest wait for more lines before a batch is solved (default 0)",
    )
    add_time_budget_option(parser, DEFAULT_TIME_BUDGET_MS)
    parser.add_argument(
        "--track",
        action="store_true",
        help="also start small batches from the last answer's forces (StreamOptions.track; off: it costs time)",
    )
    parser.add_argument(
        "--max-forces",
        type=int,
        metavar="H",
        help="choose the count in 0..H (default: as many as the rod's gratings can test, at most 3)",
    )
    parser.add_argument(
        "--noise", type=float, metavar="SIGMA", help="sensor noise sigma [1/m]; default: learned from the stream"
    )
    parser.add_argument(
        "--per-reading-noise",
        action="store_true",
        help="without --noise, estimate each reading's noise alone instead of learning one sigma from the stream",
    )
    parser.add_argument(
        "--iterations",
        type=int,
        default=LMPolicy.iterations,
        metavar="STEPS",
        help="most Levenberg-Marquardt steps per fit while the search compares counts (default %(default)s)",
    )
    add_device_option(parser)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads, for the warm-start network (default 1: the solver threads, --workers, use the cores)",
    )
    add_workers_option(parser)
    parser.add_argument("--summary", action="store_true", help="a short summary on stderr at the end")
    parser.add_argument("--truth", metavar="FILE", help="true forces per id, for --summary's accuracy")


# ---------------------------------------------------------------------------------------------------- input
def read_stream(
    source: str, rod: Rod, fmt: str = "auto", *, quantity: str = "curvature", topic: str | None = None
) -> Any:
    """Readings from ``source`` (a path, ``"-"`` or ``tcp://HOST:PORT``) in a format of
    :data:`torchrod.io.sources.FORMATS`, lazily, checked by :mod:`torchrod.io.reading`: unusable lines become
    readings with an ``error``. The flush after an interrupt ends it at the lines already read. With ``topic``,
    ``source`` is a ROS bag (:class:`torchrod.io.rosbag.BagSource`)."""
    if topic is not None:
        from ...io.rosbag import BagSource

        return BagSource(source, topic, rod.num_gratings)
    return ReadingSource(source, rod.num_gratings, rod.gratings, fmt, quantity=quantity, fibre=rod.fibre)


def load_truth(path: str) -> dict[str, list[tuple[float, float, float]]]:
    """True forces per reading id (key: the id as JSON text) from ``{"id", "forces": [{"s", "fx", "fy"}, ...]}``
    lines; ``ValueError`` for a line that cannot be used."""
    check_input(path, "--truth")

    def parse(obj: dict[str, Any]) -> list[tuple[float, float, float]]:
        out = []
        for k, force in enumerate(get_list(obj, "forces")):
            where = f"forces[{k}]"
            check_keys(force, ("s", "fx", "fy"), where=where)
            out.append(tuple(get_number(force, key, where) for key in ("s", "fx", "fy")))
        return cast("list[tuple[float, float, float]]", out)  # three numbers per force

    truth = {}
    for record in parse_records(read_lines(path), parse):
        if not record.ok:
            raise ValueError(f"--truth {path}: {record.error}")
        assert record.value is not None  # a usable line's value: parse() returns a list
        truth[_key(record.id)] = record.value
    return truth


# ---------------------------------------------------------------------------------------------------- the command
def run(args: argparse.Namespace) -> int:
    return until_interrupted(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    rod = sensor_rod(args, load_rod(args.rod))
    check_estimation_options(args)
    sensor_noise(args, rod)
    check_counts(args, rod)
    workers = check_workers(args)
    device = check_device(args)
    if args.topic is not None and args.input == "-":
        raise ValueError("--topic reads a ROS bag: give its path with --input")
    if args.topic is not None and args.protocol != "lines":
        what = INPUT_FORMATS[args.protocol].what
        raise ValueError(f"--topic reads a ROS bag; --protocol {args.protocol} reads {what}: give one")
    inputs = _inputs(args)
    check_output(args.out, inputs)
    if args.output_bag is not None:
        from ...io.rosbag import require_rosbags

        require_rosbags()
        check_output(args.output_bag, {**inputs, "--out": args.out}, "--output-bag")
        if os.path.lexists(args.output_bag):
            raise ValueError(f"--output-bag {args.output_bag} exists already: a bag is never overwritten")
        if args.out is not None and same_path(args.out, args.output_bag):
            raise ValueError(f"--out and --output-bag name the same path, {args.out}: give two")
    if not 0.0 <= args.max_latency_ms < float("inf"):
        raise ValueError(f"--max-latency-ms must be >= 0, got {args.max_latency_ms}")
    if args.truth is not None and not args.summary:
        raise ValueError("--truth is used by --summary; give both")
    truth = load_truth(args.truth) if args.truth is not None else None
    if args.topic is None:
        check_input(args.input, "--input")
    network = choose_network(args.checkpoint, rod, "stream")
    if args.iterations < 0:
        raise ValueError(f"--iterations must be >= 0, got {args.iterations}")
    # As load_estimator: a trusted network's guesses start the fits alone, a weak one's are beside.
    estimator_options = EstimatorOptions(
        max_forces=args.max_forces,
        noise=args.noise,
        lm=LMPolicy(iterations=args.iterations),
        relative=args.relative,
        time_budget=time_budget(args),
        merge_patches=args.merge_patches,
    )
    estimator = Estimator(rod, trusting(estimator_options, network), warm_start=network)
    options = StreamOptions(
        batch_size=args.batch_size,
        max_latency=args.max_latency_ms / 1e3,
        learn_noise=None if args.per_reading_noise else NoiseLearning(),
        track=args.track,
        device=device,
        workers=workers,
    )
    warm_up(estimator, device)  # the kernels and first-call costs before the first reading, not on its latency
    settle()
    if args.topic is not None:
        source = read_stream(args.input, rod, topic=args.topic)
    else:
        source = reading_source(args, rod, args.input)
    with open_output(args.out, inputs) as out:
        bag = _open_bag(args.output_bag, args.max_forces)
        status = 2
        try:
            status = _answer(args, estimator, options, source, LineWriter(out), truth, bag)
        finally:
            if bag is not None:
                status = _close_bag(bag, status)
        return status


def _inputs(args: argparse.Namespace) -> dict[str, str | None]:
    """The files the command reads, by option, which no output may overwrite."""
    from ...learn.warm_start import SHIPPED_CHECKPOINT

    checkpoint = SHIPPED_CHECKPOINT if args.checkpoint is None else args.checkpoint
    return {"--input": args.input, "--rod": args.rod, "--checkpoint": checkpoint, "--truth": args.truth}


def _open_bag(path: str | None, slots: int) -> Any:
    """The open :class:`torchrod.io.rosbag.BagWriter` of ``--output-bag``, or None."""
    if path is None:
        return None
    from ...io.rosbag import BagWriter

    return BagWriter(path, slots).__enter__()


def _close_bag(bag: Any, status: int) -> int:
    """Close the bag; a storage that refuses then (a full disk) is one error line and makes ``status`` 0 a 1."""
    try:
        bag.close()
    except OSError as exc:
        print(f"torchrod stream: error: {exc}", file=sys.stderr)
        return 1 if status == 0 else status
    return status


def _answer(
    args: argparse.Namespace,
    estimator: Any,
    options: StreamOptions,
    source: Any,
    writer: LineWriter,
    truth: dict[str, Any] | None,
    bag: Any = None,
) -> int:
    stats = StreamStats()
    start = time.perf_counter()

    def emit(result: StreamResult) -> None:
        extra = {"t": result.t} if result.t is not None else {}
        record = {"id": result.id, "error": result.error, **extra} if result.error is not None else result.record
        if bag is not None and bag.failed is None:
            try:
                bag.write(record, result.t)
            except ReadingError as exc:  # a time stamp the bag cannot hold: an error line for this reading alone
                at = f"line {result.line}: " if result.line is not None else ""
                writer.error(result.id, at + str(exc), **extra)
                if args.summary:
                    stats.add(dataclasses.replace(result, error=str(exc)))
                return
            except OSError as exc:  # the storage refused (a full disk): the answers go on, the bag stops here
                print(
                    f"torchrod stream: error: {exc}; the answers go on on the output, the bag stops here (exit "
                    "status 1)",
                    file=sys.stderr,
                )
        if result.error is not None:
            writer.error(result.id, result.error, **extra)
        else:
            writer.answer(result.record, result.line, flush=result.batch_end)
        if args.summary:
            known = truth.get(_key(result.id)) if truth is not None and result.ok else None
            stats.add(result, known)

    try:
        interrupted = answer_each(estimator, source, options, emit, lambda: writer.lines)
    finally:
        if args.summary:
            for line in stats.summary(time.perf_counter() - start):
                print(f"torchrod stream: {line}", file=sys.stderr)
    if interrupted is not None:
        return interrupt_status(interrupted)
    return 1 if writer.errors or (bag is not None and bag.failed is not None) else 0


def _key(ident: Any) -> str:
    """An id as a key of the truth table (its JSON text)."""
    return json.dumps(ident)
