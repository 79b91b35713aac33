"""``torchrod stream``: forces from a live stream of FBG readings, answered as they arrive.

Usage: ``torchrod stream --rod ROD [--checkpoint C] [--input FILE]`` (default: standard input). ROD is a rod JSON
file or a preset name such as ``nitinol290``.

Input, one reading a line, read as it arrives (a pipe from an interrogator is fine):

* JSON lines, the format of ``torchrod estimate`` plus an optional timestamp ``t`` [s]::

      {"id": "f000123", "t": 1.23, "curvature": [[ux, uy], null, ...]}

* or CSV, one reading a row: ``id, t, ux_1, uy_1, ..., ux_G, uy_G`` [1/m] with both cells of a missing grating
  empty (``t`` may be empty too); a first row whose cells after the id are not numbers is a header and skipped.

``--format auto`` (the default) reads JSON lines when the first non-blank line starts with ``{``, else CSV.

Output: one JSON line per input line, in input order, each written and flushed as soon as its batch is solved::

    {"id", "num_forces", "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"}, ...], "loss",
     "converged", "iterations", "poorly_determined", "t", "latency_ms"}

(the fields of ``torchrod estimate``; ``t`` echoed when given; ``latency_ms`` from the moment the line was read to
its answer). Readings are solved in batches of up to ``--batch-size``, a batch closing when the oldest reading in it
has waited ``--max-latency-ms``. Each reading starts from the warm-start network's guess, the grid scan, and the
previous reading's solution (with the network, the grid scan is skipped, as in ``Estimator.from_checkpoint``);
the number of forces is chosen among 1..``--max-forces`` (``--noise``: the sensor's
sigma [1/m]; without it the noise is estimated per reading). ``--checkpoint`` defaults to the shipped
``checkpoints/nitinol290.pt`` when the rod's grating layout matches it, else the stream runs without a network (said
once on stderr); ``--checkpoint none`` turns the network off.

A line that cannot be used (bad JSON or CSV, a wrong number of gratings, NaN, all gratings missing) gives
``{"id": ... or null, "error": "line N: ..."}`` and the stream goes on; missing gratings are left out of the fit.
The end of the input and Ctrl-C answer every line read so far before stopping. Memory stays bounded (a batch and a
bounded read-ahead). Exit status: 0, or 1 if any line failed, 130 after Ctrl-C, 141 when the reader of the output
goes away, 2 for a bad rod, checkpoint or option.

``--summary`` prints to stderr at the end: readings, errors, readings/s, latency median and 99th percentile, and with
``--truth FILE`` (``{"id", "forces": [{"s", "fx", "fy"}, ...]}`` per line, as ``torchrod generate --trajectory``
writes) the count accuracy and the median force and location errors of the readings whose count is right.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

from ...estimate.estimator import Estimator, EstimatorOptions
from ...io.jsonl import (
    LineWriter,
    Record,
    as_number,
    check_keys,
    get_list,
    get_number,
    parse_records,
    read_lines,
)
from ...io.stream import Reading, StreamOptions, StreamResult, StreamStats, stream, warm_up
from ...presets import load as load_rod
from ...rod import Rod
from . import check_estimation_options
from .estimate import parse_reading

HELP = "amortised estimation on a stream of readings"

__all__ = ["HELP", "configure", "load_truth", "read_stream", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--rod", required=True, help="rod JSON file or preset name (e.g. nitinol290)")
    parser.add_argument(
        "--checkpoint",
        default=None,
        metavar="C",
        help="warm-start network checkpoint, or 'none' (default: the shipped one if the layout matches)",
    )
    parser.add_argument("--input", default="-", metavar="FILE", help="readings file (default '-': stdin)")
    parser.add_argument("--format", choices=("auto", "jsonl", "csv"), default="auto", help="input format")
    parser.add_argument(
        "--batch-size", type=int, default=64, metavar="B", help="most readings per batch (64)"
    )
    parser.add_argument(
        "--max-latency-ms", type=float, default=20.0, metavar="MS", help="longest wait for a batch (20 ms)"
    )
    parser.add_argument("--max-forces", type=int, default=3, metavar="H", help="choose the count in 1..H (3)")
    parser.add_argument(
        "--noise", type=float, metavar="SIGMA", help="sensor noise sigma [1/m]; default: estimated"
    )
    parser.add_argument(
        "--polish",
        type=int,
        default=EstimatorOptions.polish,
        metavar="STEPS",
        help="Levenberg-Marquardt steps before L-BFGS (default %(default)s; 12 about halves the time per reading)",
    )
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    parser.add_argument("--summary", action="store_true", help="a short summary on stderr at the end")
    parser.add_argument("--truth", metavar="FILE", help="true forces per id, for --summary's accuracy")


# ---------------------------------------------------------------------------------------------------- input
def _parse_json(obj: dict[str, Any], rod: Rod) -> tuple[Any, float | None]:
    """One reading object -> (per grating (ux, uy) or None, t or None); ``ValueError`` names the bad field."""
    t = obj.get("t")
    return parse_reading(obj, rod), (None if t is None else as_number(t, "t"))


def _cell(text: str) -> Any:
    """A CSV cell as JSON would carry it: None when empty, a float when it reads as one, else the text."""
    text = text.strip()
    if not text:
        return None
    try:
        return float(text)
    except ValueError:
        return text


def _csv_lines(lines: Iterable[tuple[int, str]], rod: Rod) -> Iterator[Record[Any]]:
    """CSV rows -> records, through the JSON path: each row becomes the object ``{"id", "t", "curvature"}`` and is
    parsed like a JSON line (same checks, same messages); only a wrong cell count is reported here."""
    G = rod.num_gratings
    width = 2 + 2 * G
    first = True
    for number, text in lines:
        try:
            cells = next(csv.reader([text]))
        except csv.Error as exc:
            yield Record(number, None, None, f"line {number}: not valid CSV ({exc})")
            continue
        values = [_cell(c) for c in cells]
        if first:
            first = False
            rest = values[1:]
            if any(isinstance(v, str) for v in rest) and not any(isinstance(v, float) for v in rest):
                continue  # a header
        ident = (cells[0].strip() or None) if cells else None
        if len(values) != width:
            yield Record(
                number,
                ident,
                None,
                f"line {number}: expected {width} cells (id, t, then ux, uy for {G} gratings), got {len(values)}",
            )
            continue
        pairs = [values[2 + 2 * k : 4 + 2 * k] for k in range(G)]
        obj = {
            "id": ident,
            "t": values[1],
            "curvature": [None if pair == [None, None] else pair for pair in pairs],
        }
        # NaN and infinity survive as JSON extensions, so the JSON path refuses them with its own message.
        yield from parse_records([(number, json.dumps(obj))], lambda o: _parse_json(o, rod))


def read_stream(source: str, rod: Rod, fmt: str = "auto") -> Iterator[Reading]:
    """Readings from ``source`` (a path or ``"-"``) in format ``"jsonl"``, ``"csv"`` or ``"auto"`` (JSON lines if
    the first non-blank line starts with ``{``), lazily: unusable lines become readings with an ``error``."""
    lines = read_lines(source)
    if fmt == "auto":
        head = next(lines, None)
        if head is None:
            return
        fmt = "jsonl" if head[1].lstrip().startswith("{") else "csv"
        lines = itertools.chain([head], lines)
    if fmt == "jsonl":
        records = parse_records(lines, lambda obj: _parse_json(obj, rod))
    elif fmt == "csv":
        records = _csv_lines(lines, rod)
    else:
        raise ValueError(f"format must be auto, jsonl or csv, got {fmt!r}")
    for record in records:
        if record.ok:
            curvature, t = record.value
            yield Reading(record.id, curvature, t)
        else:
            yield Reading(record.id, error=record.error)


def load_truth(path: str) -> dict[str, list[tuple[float, float, float]]]:
    """True forces per reading id (key: the id as JSON text) from ``{"id", "forces": [{"s", "fx", "fy"}, ...]}``
    lines; ``ValueError`` for a line that cannot be used."""

    def parse(obj: dict[str, Any]) -> list[tuple[float, float, float]]:
        out = []
        for k, force in enumerate(get_list(obj, "forces")):
            where = f"forces[{k}]"
            check_keys(force, ("s", "fx", "fy"), where=where)
            out.append(tuple(get_number(force, key, where) for key in ("s", "fx", "fy")))
        return out

    truth = {}
    for record in parse_records(read_lines(path), parse):
        if not record.ok:
            raise ValueError(f"--truth {path}: {record.error}")
        truth[json.dumps(record.id)] = record.value
    return truth


# ---------------------------------------------------------------------------------------------------- the command
def _warm_start(args: argparse.Namespace, rod: Rod) -> Any:
    """The network the options ask for, or None (the default checkpoint only when it fits the rod)."""
    from ...learn.warm_start import SHIPPED_CHECKPOINT, WarmStart

    if args.checkpoint is not None:
        if args.checkpoint.lower() == "none":
            return None
        return WarmStart.load(args.checkpoint, rod)
    if not os.path.exists(SHIPPED_CHECKPOINT):
        print(f"torchrod stream: no warm-start network ({SHIPPED_CHECKPOINT} not found)", file=sys.stderr)
        return None
    try:
        return WarmStart.load(SHIPPED_CHECKPOINT, rod)
    except ValueError as exc:
        print(f"torchrod stream: no warm-start network: {exc}", file=sys.stderr)
        return None


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    check_estimation_options(args)
    if not 0.0 <= args.max_latency_ms < float("inf"):
        raise ValueError(f"--max-latency-ms must be >= 0, got {args.max_latency_ms}")
    if args.truth is not None and not args.summary:
        raise ValueError("--truth is used by --summary; give both")
    truth = load_truth(args.truth) if args.truth is not None else None
    if args.input != "-" and not os.path.exists(args.input):
        raise FileNotFoundError(f"--input {args.input} not found")
    network = _warm_start(args, rod)
    options = EstimatorOptions(max_forces=args.max_forces, noise=args.noise, polish=args.polish)
    if network is not None and network.max_forces >= args.max_forces:
        # As Estimator.from_checkpoint: the network's guesses replace the grid scan.
        options = dataclasses.replace(options, starts=0)
    estimator = Estimator(rod, options, warm_start=network)
    options = StreamOptions(batch_size=args.batch_size, max_latency=args.max_latency_ms / 1e3)
    # Warm-up before the first reading: per-rod caches and first-call costs would otherwise land on its latency.
    warm_up(estimator)
    writer = LineWriter()
    stats = StreamStats()
    start = time.perf_counter()

    def emit(result: StreamResult) -> None:
        writer.write(result.record)
        if result.error is not None:
            writer.errors += 1
        if args.summary:
            known = truth.get(json.dumps(result.id)) if truth is not None and result.ok else None
            stats.add(result, known)

    results = stream(estimator, read_stream(args.input, rod, args.format), options)
    interrupted = False
    try:
        for result in results:
            emit(result)
    except KeyboardInterrupt:
        interrupted = True
        if results.gi_frame is not None:  # interrupted here, not inside the stream: let it flush
            try:
                emit(results.throw(KeyboardInterrupt()))
                for result in results:
                    emit(result)
            except (KeyboardInterrupt, StopIteration):
                pass
    finally:
        results.close()
        if args.summary:
            for line in stats.summary(time.perf_counter() - start):
                print(f"torchrod stream: {line}", file=sys.stderr)
    if interrupted:
        return 130
    return 1 if writer.errors else 0
