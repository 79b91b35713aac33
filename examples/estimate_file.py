"""Estimate the forces of a file of readings from Python, and summarise the answers by status.

    python examples/estimate_file.py [READINGS.jsonl] [--rod ROD] [--noise SIGMA] [--count N] [--out FILE]

READINGS defaults to the shipped example stream (``python -m torchrod.data example_stream.jsonl``); JSON lines or
CSV, as ``torchrod estimate`` reads them. Lines that cannot be used are reported and skipped; the rest are
estimated in one batched call. ``--out`` writes one JSON answer per reading, as ``torchrod estimate`` does.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json

import torchrod as tr
from torchrod.data import path as shipped_file
from torchrod.io.readings import ReadingSource, stack_readings
from torchrod.learn.warm_start import shipped_network


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("readings", nargs="?", default=str(shipped_file("example_stream.jsonl")))
    parser.add_argument("--rod", default="nitinol290", help="rod JSON file or preset name (default nitinol290)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor noise sigma [1/m] (default 0.1)")
    parser.add_argument("--count", type=int, default=None, help="estimate only the first N readings")
    parser.add_argument("--out", help="write one JSON answer per reading to this file")
    args = parser.parse_args(argv)

    rod = tr.presets.load(args.rod)
    source = ReadingSource(args.readings, rod.num_gratings, rod.gratings, "auto", fibre=rod.fibre)
    readings = list(itertools.islice(source, args.count))
    good = [r for r in readings if r.ok]
    for bad in (r for r in readings if not r.ok):
        print(f"skipped: {bad.error}")
    if not good:
        print("no usable reading")
        return 1

    network, which = shipped_network(rod)  # the network shipped for this rod's layout, as the CLI picks it
    print(f"{len(good)} readings from {args.readings}; {which}")
    options = tr.EstimatorOptions(noise=args.noise)
    estimator = tr.Estimator(rod, options, warm_start=network)
    curvature, mask = stack_readings(good)  # (B, G, 2) [1/m], (B, G) False where a grating gave no value
    result = estimator.estimate(curvature, mask)
    records = result.to_records([r.id for r in good])

    print("statuses:", dict(collections.Counter(record["status"] for record in records)))
    print("forces per reading:", dict(sorted(collections.Counter(record["num_forces"] for record in records).items())))
    first = records[0]
    print(f"first answer: {json.dumps(first)[:300]}")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            for record in records:
                fh.write(json.dumps(record) + "\n")
        print(f"wrote {len(records)} answers to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
