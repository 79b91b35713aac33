"""Estimate a live sensor's readings as they arrive, in latency-bounded batches.

    python examples/stream_sensor.py [--count N] [--rate HZ] [--noise SIGMA]

A stand-in for an interrogator: a generator that yields the shipped example stream's readings at ``--rate`` readings
per second, as a driver would. :func:`torchrod.stream` answers them in order; a reading that arrives while
a batch is solved joins the next batch. Each answer carries ``latency_ms``, from taking the reading to its answer.
Replace ``sensor()`` with your driver: any iterable of dicts with ``id``, ``t`` [s] and ``curvature`` (one
[u_x, u_y] pair [1/m] per grating, None for a grating without a value).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from collections.abc import Iterator

import torchrod as tr
from torchrod.data import path as shipped_file
from torchrod.io.stream import StreamOptions, warm_up
from torchrod.learn.warm_start import shipped_network


def sensor(count: int, rate: float) -> Iterator[dict]:
    """``count`` readings of the shipped example stream, one every 1 / ``rate`` seconds."""
    with open(shipped_file("example_stream.jsonl"), encoding="utf-8") as fh:
        start = time.perf_counter()
        for k, line in enumerate(itertools.islice(fh, count)):
            delay = start + k / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            reading = json.loads(line)
            yield {"id": reading["id"], "t": reading["t"], "curvature": reading["curvature"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=100, help="readings (default 100, at most 500)")
    parser.add_argument("--rate", type=float, default=50.0, help="readings per second (default 50)")
    parser.add_argument("--noise", type=float, default=0.1, help="sensor noise sigma [1/m] (default 0.1)")
    args = parser.parse_args(argv)

    rod = tr.presets.nitinol290()
    network, which = shipped_network(rod)
    estimator = tr.Estimator(rod, tr.EstimatorOptions(noise=args.noise), warm_start=network)
    warm_up(estimator)  # first-call costs now, not on the first reading's latency
    print(f"streaming {args.count} readings at {args.rate:g} Hz; {which}")
    latencies = []
    for answer in tr.stream(estimator, sensor(args.count, args.rate), StreamOptions(batch_size=64)):
        if answer.error is not None:
            print(f"{answer.id}: {answer.error}")
            continue
        latencies.append(answer.record["latency_ms"])
        forces = " ".join(f"{1e3 * f['s']:.0f}mm/{f['magnitude']:.2f}N" for f in answer.record["forces"])
        print(f"{answer.id} t={answer.t:.2f}s {answer.record['status']:<17} {forces}")
    if latencies:
        print(f"latency median {statistics.median(latencies):.1f} ms, max {max(latencies):.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
