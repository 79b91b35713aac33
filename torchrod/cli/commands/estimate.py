"""``torchrod estimate``: contact forces from FBG curvature readings (JSON lines in, JSON lines out).

Usage: ``torchrod estimate --rod ROD READINGS.jsonl`` (``-`` reads standard input). ROD is a rod JSON file (see
torchrod.Rod.from_json) or a preset name such as ``nitinol290``.

Each input line is one reading, as ``torchrod simulate`` writes them::

    {"id": "r1", "curvature": [[ux, uy], [ux, uy], null, ...]}

with one [ux, uy] pair [1/m] per grating in the rod file's order and ``null`` for a grating that gave no reading
(it is left out of the fit). ``id`` is optional (any JSON value, echoed back); a ``gratings`` list, if present, must
match the rod's; other keys are ignored.

Each output line answers the input line in the same position::

    {"id": "r1", "num_forces": 2, "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"}, ...],
     "loss", "converged", "iterations", "poorly_determined", "time_ms"}

``forces`` sorted by s [m] (reported location: model location + the rod's location_bias), body-frame components
[N], their Gauss-Newton standard deviations; ``loss`` the sum of squared curvature residuals [1/m^2];
``time_ms`` the estimation time of the line's batch divided by its readings. The count is chosen among 1 to
``--max-forces`` (or fixed by ``--num-forces``) by the rule of ``--selection``; with ``--noise`` (the sensor's sigma
per component [1/m]) the tests know the noise, without it they estimate it from each reading (slower and weaker).

A line that cannot be used (bad JSON, a wrong number of gratings, a non-numeric or NaN value, all gratings missing)
gives ``{"id": ... or null, "error": "line N: ..."}`` and the other lines go on; the exit status is 1 if any line
failed, else 0 (2 for a bad rod file or option, 141 when the reader of the output goes away).

Lines are estimated in batches of ``--batch-size`` (one batched call per batch), answers in input order; a progress
bar on stderr counts readings when stderr is a terminal (not with ``--quiet``).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import torch

from ...estimate.estimator import Estimator, EstimatorOptions
from ...estimate.selection import RULES
from ...io.jsonl import LineWriter, Record, as_number, batched, get_list, read_records
from ...presets import load as load_rod
from ...rod import Rod
from . import check_estimation_options

HELP = "forces from FBG curvature readings (JSON lines in, JSON lines out)"

__all__ = ["HELP", "configure", "options_from_args", "parse_reading", "run"]

Reading = list[tuple[float, float] | None]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "readings", metavar="READINGS.jsonl", help="readings, one JSON object a line; '-' for stdin"
    )
    parser.add_argument("--rod", required=True, help="rod JSON file or preset name (e.g. nitinol290)")
    count = parser.add_mutually_exclusive_group()
    count.add_argument(
        "--max-forces", type=int, default=3, metavar="H", help="choose the count in 1..H (default 3)"
    )
    count.add_argument("--num-forces", type=int, metavar="N", help="fit exactly N forces")
    parser.add_argument(
        "--noise", type=float, metavar="SIGMA", help="sensor noise sigma [1/m]; default: estimated"
    )
    parser.add_argument("--selection", choices=RULES, default="noise", help="count rule (default noise)")
    parser.add_argument(
        "--threshold",
        type=float,
        default=3.0,
        help="loss threshold [1/m^2] of --selection threshold (default 3.0)",
    )
    parser.add_argument("--starts", type=int, default=EstimatorOptions.starts, help="grid starts per count")
    parser.add_argument(
        "--batch-size", type=int, default=256, metavar="B", help="readings per batch (default 256)"
    )
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def options_from_args(args: argparse.Namespace) -> EstimatorOptions:
    """The :class:`EstimatorOptions` the command-line arguments ask for (``ValueError`` for bad values)."""
    return EstimatorOptions(
        max_forces=args.max_forces if args.num_forces is None else max(args.max_forces, args.num_forces),
        num_forces=args.num_forces,
        noise=args.noise,
        selection=args.selection,
        threshold=args.threshold,
        starts=args.starts,
    )


def parse_reading(obj: dict[str, Any], rod: Rod) -> Reading:
    """One input object -> per grating (ux, uy) or None (missing); ``ValueError`` names the bad field."""
    rows = get_list(obj, "curvature")
    G = rod.num_gratings
    if len(rows) != G:
        raise ValueError(f"curvature holds {len(rows)} gratings, the rod has {G}")
    if "gratings" in obj:
        given = get_list(obj, "gratings")
        positions = [as_number(x, f"gratings[{k}]") for k, x in enumerate(given)]
        if len(positions) != G or any(abs(a - b) > 1e-9 for a, b in zip(positions, rod.gratings)):
            raise ValueError(f"gratings {positions} do not match the rod's {list(rod.gratings)}")
    out: Reading = []
    for k, row in enumerate(rows):
        if row is None:
            out.append(None)
            continue
        if not isinstance(row, list) or len(row) != 2:
            raise ValueError(f"curvature[{k}] must be [ux, uy] or null, got {row!r}")
        out.append((as_number(row[0], f"curvature[{k}][0]"), as_number(row[1], f"curvature[{k}][1]")))
    if all(x is None for x in out):
        raise ValueError("all gratings are missing")
    return out


def run(args: argparse.Namespace) -> int:
    rod = load_rod(args.rod)
    check_estimation_options(args)
    estimator = Estimator(rod, options_from_args(args))
    device = torch.device(args.device)
    writer = LineWriter()
    records = read_records(args.readings, lambda obj: parse_reading(obj, rod))
    from tqdm import tqdm

    bar = tqdm(
        disable=args.quiet or not sys.stderr.isatty(),
        file=sys.stderr,
        unit="reading",
        dynamic_ncols=True,
        leave=False,
    )
    try:
        for chunk in batched(records, args.batch_size):
            _answer(estimator, chunk, writer, device)
            bar.update(len(chunk))
    except BrokenPipeError:  # the reader went away (| head): stop quietly
        return 141
    finally:
        bar.close()
    return 1 if writer.errors else 0


def _answer(
    estimator: Estimator, chunk: list[Record[Reading]], writer: LineWriter, device: torch.device
) -> None:
    good = [r for r in chunk if r.ok]
    results: list[dict[str, Any]] = []
    elapsed = 0.0
    if good:
        nan = float("nan")
        values = [[(nan, nan) if x is None else x for x in (r.value or [])] for r in good]
        curvature = torch.tensor(values, dtype=torch.float64, device=device)
        start = time.perf_counter()
        result = estimator.estimate(curvature)
        elapsed = time.perf_counter() - start
        results = result.to_records([r.id for r in good])
    per_reading = 1e3 * elapsed / max(1, len(good))
    answers = iter(results)
    for record in chunk:
        if not record.ok:
            writer.record_error(record)
            continue
        out = next(answers)
        out["time_ms"] = per_reading
        writer.write(out)
