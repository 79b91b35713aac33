"""``torchrod plot``: figures of readings and their estimates (PNG).

Usage: ``torchrod plot READINGS.jsonl ESTIMATES.jsonl --rod ROD [--truth TRUTH.jsonl] [--id ID | --all]
[--out DIR|FILE]``.

READINGS: the input of ``torchrod estimate``/``torchrod stream`` (``{"id", "curvature": [[ux, uy] or null, ...]}``,
``"t"`` [s] for a stream), in any of their formats and units (JSON lines, CSV, a peak log; ``--format``,
``--csv-quantity``, ``--peaks`` and the unit options as for ``torchrod estimate``). ESTIMATES: their output, one
JSON line per reading (``{"id", "forces": [{"s", "fx", "fy"}, ...]}``; error lines are skipped). Estimates are
matched to readings by id when every reading has a distinct id, else by line order. TRUTH (optional): the true
forces, ``{"id", "t", "forces": [{"s", "fx", "fy"}, ...]}`` per line (the format of
the shipped ``example_stream_truth.jsonl``: torchrod.data), matched by id.

Figures:

* for a stream (readings with ``"t"``): each estimated force at its location against time, a dot whose area
  grows with its magnitude, the forces of consecutive readings linked into contact tracks (one colour each), and
  below, the magnitudes against time in the same colours; a strip on top marks the readings whose status is not
  ``ok`` (or that have no estimate), one colour per status. With TRUTH, the true contacts are drawn as grey lines,
  and those missed (no estimated force within 20 mm) as red crosses, counted in the title. Written as
  ``stream.png``;
* per reading: the rod's 3-D shape from the estimated forces with the forces drawn as arrows at their locations
  (and the true ones, dashed, when TRUTH is given), the measured and the fitted curvature at each grating, and the
  residuals; written as ``reading-ID.png``.

One file is written unless more are asked for: readings without ``"t"`` give the figure of the first reading (and
say on stderr how many more there are); ``--id ID`` draws the reading with that id instead (of a stream too), and
``--all`` one figure per reading.

``--out`` is a folder (default: the current one) or, for a single figure, a file name ending in ``.png``. The paths
written are printed, one a line. The rod (``--rod``, a rod file or preset name) must be the one the estimates were
made with: its location bias maps reported locations back to the model's. There is no default: without ``--rod``
the inputs must say which rod, by a ``"rod"`` field (a preset name, a rod file relative to the input's folder, or
a rod object) in their lines, all naming the same rod.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from typing import Any, cast

from ...io.jsonl import as_number, check_input, check_output, get_list, read_lines, read_records
from ...presets import load as load_rod
from ...rod import Rod
from . import add_input_options, add_sensor_options, rod_help, sensor_rod

HELP = "figures of readings and their estimates"

__all__ = ["HELP", "configure", "parse_forces", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("readings", metavar="READINGS", help="readings (JSON lines, CSV or a peak log)")
    parser.add_argument("estimates", metavar="ESTIMATES.jsonl", help="their estimates (torchrod estimate/stream)")
    parser.add_argument(
        "--rod",
        help=rod_help(what=" the estimates were made with, required unless the inputs say"),
    )
    parser.add_argument("--truth", metavar="TRUTH.jsonl", help="true forces per reading (optional)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--id", dest="ident", metavar="ID", help="the figure of the reading with this id")
    which.add_argument("--all", action="store_true", help="one figure per reading (default: one file in all)")
    parser.add_argument("--out", default=".", help="output folder, or a .png file for one figure (default .)")
    parser.add_argument("--dpi", type=int, default=90, help="resolution of the PNGs (default 90)")
    add_input_options(parser, protocol=False)
    add_sensor_options(parser, estimating=False)


def parse_forces(obj: dict[str, Any]) -> list[tuple[float, float, float]]:
    """The ``"forces"`` of a JSON object as rows (s [m], f_x [N], f_y [N]); ``ValueError``/``TypeError`` name a bad
    entry."""
    rows = []
    for k, f in enumerate(get_list(obj, "forces")):
        if not isinstance(f, dict):
            raise TypeError(f"forces[{k}] must be an object with s, fx, fy, got {f!r}")
        try:
            rows.append(tuple(as_number(f[key], f"forces[{k}].{key}") for key in ("s", "fx", "fy")))
        except KeyError as exc:
            raise ValueError(f"forces[{k}] lacks {exc.args[0]!r}") from None
    return cast("list[tuple[float, float, float]]", rows)  # three numbers per row


def _time(obj: dict[str, Any]) -> float | None:
    return as_number(obj["t"], "t") if obj.get("t") is not None else None


def _readings(args: argparse.Namespace, rod: Rod) -> list[Any]:
    """The records of READINGS (:func:`torchrod.io.sources.iter_records`), each value (curvature [1/m], t)."""
    from ...io.reading import parse_reading
    from ...io.sources import iter_records

    def parse(obj: dict[str, Any]):
        reading = parse_reading(obj, rod.num_gratings, rod.gratings, fibre=rod.fibre)
        return reading.curvature.tolist(), reading.t

    records = iter_records(
        args.readings,
        rod.num_gratings,
        parse,
        args.format,
        quantity=args.csv_quantity,
        fibre=rod.fibre,
        peaks=args.peaks,
        max_line=args.max_line_bytes,
    )
    return list(records)


def _forces_and_time(obj: dict[str, Any]):
    """(forces, t [s] or None, status or None) of an estimate or truth line; an error line raises."""
    if "error" in obj and "forces" not in obj:
        raise ValueError(str(obj["error"]))
    status = obj.get("status")
    return parse_forces(obj), _time(obj), None if status is None else str(status)


def _rod_named_in(*paths: str) -> Rod:
    """The rod the ``"rod"`` fields of the input lines name (all the same), else ``ValueError``: which rod?"""
    import json

    named: dict[str, tuple[str, Any]] = {}
    for path in paths:
        for _, line in read_lines(path):  # (lines of bounded length: an endless one is not held)
            if '"rod"' not in line:
                continue
            try:
                obj = json.loads(line)
            except (ValueError, RecursionError):
                continue
            if isinstance(obj, dict) and obj.get("rod") is not None:
                named.setdefault(json.dumps(obj["rod"], sort_keys=True), (path, obj["rod"]))
    if not named:
        raise ValueError(
            "which rod? pass --rod ROD (the rod file or preset name the estimates were made with); "
            f"neither {paths[0]} nor {paths[1]} says"
        )
    if len(named) > 1:
        raise ValueError(f"the inputs name {len(named)} different rods; pass --rod ROD")
    path, spec = next(iter(named.values()))
    if isinstance(spec, dict):
        return Rod.from_dict(spec)
    if not isinstance(spec, str):
        raise ValueError(f'{path}: "rod" must be a preset name, a rod file or a rod object, got {spec!r:.60}')  # noqa: TRY004
    beside = os.path.join(os.path.dirname(path), spec)
    return load_rod(beside if not os.path.isabs(spec) and os.path.exists(beside) else spec)


def _file_name(ident: Any, line: int) -> str:
    text = f"line{line}" if ident is None else str(ident)
    return "reading-" + (re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or f"line{line}") + ".png"


def run(args: argparse.Namespace) -> int:
    from ...eval import plots

    for path, what in ((args.readings, "READINGS"), (args.estimates, "ESTIMATES"), (args.truth, "--truth")):
        if path is not None:
            check_input(path, what)
    rod = load_rod(args.rod) if args.rod is not None else _rod_named_in(args.readings, args.estimates)
    rod = sensor_rod(args, rod)
    if args.dpi < 10:
        raise ValueError(f"--dpi must be >= 10, got {args.dpi}")
    readings = _readings(args, rod)
    bad = [r.error for r in readings if not r.ok]
    readings = [r for r in readings if r.ok]
    if not readings:
        raise ValueError(f"{args.readings}: no usable reading" + (f" ({bad[0]})" if bad else ""))
    estimates = list(read_records(args.estimates, _forces_and_time))
    ids = [r.id for r in readings]
    by_id = all(i is not None for i in ids) and len(set(map(repr, ids))) == len(ids)
    if by_id:
        table = {repr(e.id): e for e in estimates if e.ok}
        matched: list[Any] = [table.get(repr(i)) for i in ids]  # usable records (value set) or None
    else:
        ok = [e for e in estimates]
        matched = [ok[k] if k < len(ok) and ok[k].ok else None for k in range(len(readings))]
    truth: dict[str, Any] | None = None  # usable records (value set) by repr(id)
    if args.truth:
        truth = {repr(t.id): t for t in read_records(args.truth, _forces_and_time) if t.ok}

    stream = any(r.value[1] is not None for r in readings)
    if args.ident is not None:
        chosen = [k for k, r in enumerate(readings) if r.id is not None and str(r.id) == args.ident]
        if not chosen:
            raise ValueError(f"no reading with id {args.ident!r} in {args.readings}")
        jobs: list[tuple[str, int | None]] = [("reading", k) for k in chosen[:1]]
    elif args.all:
        jobs = [("reading", k) for k in range(len(readings))]
    elif stream:
        jobs = [("stream", None)]
    else:
        jobs = [("reading", 0)]
        if len(readings) > 1:
            print(
                f"torchrod plot: the figure of the first of {len(readings)} readings; --all draws one per reading, "
                "--id ID the one with that id",
                file=sys.stderr,
            )
    single_file = args.out.lower().endswith(".png")
    if single_file and len(jobs) > 1:
        raise ValueError(f"--out {args.out} names one file but --all asks for {len(jobs)} figures: give a folder")
    inputs = {"READINGS": args.readings, "ESTIMATES": args.estimates, "--truth": args.truth, "--rod": args.rod}

    def target(name: str) -> str:
        path = args.out if single_file else os.path.join(args.out, name)
        check_output(path, inputs)
        return path

    for kind, k in jobs:
        if kind == "stream":
            timed = [k for k, r in enumerate(readings) if r.value[1] is not None]
            t = [readings[k].value[1] for k in timed]
            est = [matched[k].value[0] if matched[k] is not None else None for k in timed]
            if all(e is None for e in est):
                raise ValueError(f"{args.estimates}: no estimate matches the readings")
            # (an estimate line without a status is taken as ok; a reading without an estimate has none)
            statuses = [(matched[k].value[2] or "ok") if matched[k] is not None else None for k in timed]
            tt = tv = None
            if truth is not None:
                # The truth of the readings plotted at their times, else (no id matches) all of it at its own.
                keys = [(k, repr(readings[k].id)) for k in timed]
                pairs = [(readings[k].value[1], truth[key].value[0]) for k, key in keys if key in truth]
                if not pairs:
                    pairs = sorted(
                        ((v.value[1] if v.value[1] is not None else math.nan, v.value[0]) for v in truth.values()),
                        key=lambda p: p[0],
                    )
                tt, tv = [p[0] for p in pairs], [p[1] for p in pairs]
            fig = plots.stream_figure(
                t,
                est,
                statuses=statuses,
                truth_t=tt,
                truth=tv,
                title=f"{os.path.basename(args.readings)}: {len(est)} readings",
            )
            path = target("stream.png")
        else:
            assert k is not None  # a reading's job holds its index
            r, e = readings[k], matched[k]
            if e is None:
                raise ValueError(f"no estimate for reading {r.id!r} (line {r.line}) in {args.estimates}")
            curvature, t = r.value
            true_rows = None
            if truth is not None and repr(r.id) in truth:
                true_rows = truth[repr(r.id)].value[0]
            title = f"reading {r.id!r}" + (f", t = {t:g} s" if t is not None else "") + f": {len(e.value[0])} force(s)"
            fig = plots.reading_figure(rod, curvature, e.value[0], truth=true_rows, title=title)
            path = target(_file_name(r.id, r.line))
        print(plots.save(fig, path, dpi=args.dpi))
    return 0
