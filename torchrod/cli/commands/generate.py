"""``torchrod generate``: synthetic training sets (.npz) and synthetic reading streams (JSON lines).

Sets: ``torchrod generate --rod ROD --count N --out PATH.npz [--seed S] [sampler and sensor options]``.
Streams: ``torchrod generate --trajectory --rod ROD --count N --out PATH.jsonl [--rate HZ] [--truth PATH]``.
ROD is a rod JSON file or a preset name. A one-line summary goes to stderr. A ``--count`` whose set or stream
would need more memory than the machine has free is refused up front, with how many fit (make the rest in parts,
each with its own ``--seed``). ``--out`` and ``--truth`` never name the rod file or each other.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

from ...errors import OptionsError
from ...io.jsonl import check_output, same_path
from . import add_device_option, check_device, rod_help

HELP = "synthetic training sets (.npz) and synthetic reading streams (.jsonl)"


def configure(parser: argparse.ArgumentParser) -> None:
    from ...synthetic import ContactModel, LoadSampler, SensorModel

    ls, sm, cm = LoadSampler(), SensorModel(), ContactModel()
    parser.add_argument("--rod", required=True, help=rod_help())
    parser.add_argument("--count", type=int, required=True, help="number of load cases (or readings with --trajectory)")
    parser.add_argument("--out", required=True, help="output file: .npz set, or .jsonl stream with --trajectory")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    g = parser.add_argument_group("loads")
    g.add_argument("--min-forces", type=int, default=ls.min_forces, help="default: %(default)s")
    g.add_argument("--max-forces", type=int, default=ls.max_forces, help="default: %(default)s")
    g.add_argument("--force-min", type=float, default=ls.force_range[0], help="[N] (default: %(default)s)")
    g.add_argument("--force-max", type=float, default=ls.force_range[1], help="[N] (default: %(default)s)")
    g.add_argument("--min-separation", type=float, default=ls.min_separation, help="[m] (default: %(default)s)")
    g.add_argument("--s-min", type=float, default=None, help="[m] lowest location (default: 0.02 L)")
    g.add_argument("--s-max", type=float, default=None, help="[m] highest location (default: L)")
    g.add_argument(
        "--max-bending-deg",
        type=float,
        default=math.degrees(ls.max_bending),
        help="limit on the total turning angle [deg] (default: %(default)s; 0 or inf: no limit)",
    )
    g = parser.add_argument_group("sensor")
    g.add_argument("--noise", type=float, default=sm.noise, help="Gaussian sigma [1/m] (default: %(default)s)")
    g.add_argument("--offset-std", type=float, default=sm.offset_std, help="[1/m] (default: %(default)s)")
    g.add_argument("--missing-prob", type=float, default=sm.missing_prob, help="default: %(default)s")
    g.add_argument(
        "--location-bias",
        type=float,
        default=sm.location_bias,
        help="[m], as in the rod file: the readings see the forces at s - bias (default: %(default)s)",
    )
    g = parser.add_argument_group("sets")
    g.add_argument("--batch-size", type=int, default=4096, help="cases per forward pass (default: %(default)s)")
    add_device_option(g, "torch device the forward model runs on: cpu (default), cuda, cuda:1, ...")
    g.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="progress bar (default: if a terminal)",
    )
    g = parser.add_argument_group("streams")
    g.add_argument("--trajectory", action="store_true", help="write a stream of readings instead of a set")
    g.add_argument("--rate", type=float, default=100.0, help="readings per second [Hz] (default: %(default)s)")
    g.add_argument("--truth", default=None, help="ground-truth file (default: OUT with _truth before the suffix)")
    g.add_argument("--drift-speed", type=float, default=cm.drift_speed, help="[m/s] (default: %(default)s)")
    g.add_argument("--decimals", type=int, default=6, help="decimals of the curvature written [1/m] (default: 6)")


def memory_per_case(num_gratings: int, max_forces: int, trajectory: bool) -> int:
    """About how many bytes of memory one case of a set (or one reading of a ``--trajectory``) holds while it is
    made: a set keeps float64 tensors of its loads and readings (``25 H + 33 G`` bytes a case), three times over at
    its peak (the parts, their concatenation, the arrays saved); a trajectory keeps every reading and its truth as
    Python lists and dicts (hundreds of bytes per grating and per force) until it is written."""
    G, H = num_gratings, max(1, max_forces)
    if trajectory:
        return 600 * G + 1000 * H + 1000
    return 3 * (25 * H + 33 * G)


def available_memory() -> int | None:
    """The memory this machine can still give [bytes] (``MemAvailable``, else the free pages), None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def check_memory(count: int, rod, max_forces: int, trajectory: bool) -> None:
    """:class:`~torchrod.errors.OptionsError` up front when ``--count`` cases would need more memory than the
    machine has free (:func:`memory_per_case`), instead of a ``MemoryError`` hours later; the message says how
    many cases fit."""
    per_case = memory_per_case(rod.num_gratings, max_forces, trajectory)
    free = available_memory()
    if free is None or count * per_case <= free:
        return
    what = "readings" if trajectory else "cases"
    raise OptionsError(
        f"--count {count} would need about {_bytes(count * per_case)} of memory (about {_bytes(per_case)} per "
        f"{what[:-1]}), more than the {_bytes(free)} this machine has free: make at most {free // per_case} {what} "
        "at a time (a different --seed for each part)"
    )


def _bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000
    raise AssertionError("unreachable")  # pragma: no cover


def run(args: argparse.Namespace) -> int:
    from ...presets import load as load_rod
    from ...synthetic import (
        ContactModel,
        LoadSampler,
        SensorModel,
        generate,
        generate_trajectory,
        truth_path,
        write_trajectory,
    )

    rod = load_rod(args.rod)
    if args.count < 0:
        raise ValueError(f"--count must be >= 0, got {args.count}")
    from ...io.quantities import MAX_CURVATURE

    if args.noise > MAX_CURVATURE:  # (NaN and negative sigmas are refused by the sensor model)
        raise OptionsError(
            f"--noise must be at most {MAX_CURVATURE:g} 1/m, the largest curvature a reading may carry, got "
            f"{args.noise:g}"
        )
    check_output(args.out, {"--rod": args.rod})
    if args.trajectory:
        truth = args.truth if args.truth is not None else truth_path(args.out)
        check_output(truth, {"--rod": args.rod}, "--truth")
        if same_path(truth, args.out):
            raise OptionsError(f"--out and --truth name the same file, {args.out}: give two")
    check_memory(args.count, rod, args.max_forces, args.trajectory)
    device = check_device(args)
    s_range = None
    if args.s_min is not None or args.s_max is not None:
        s_range = (
            0.02 * rod.length if args.s_min is None else args.s_min,
            rod.length if args.s_max is None else args.s_max,
        )
    bending = args.max_bending_deg
    sampler = LoadSampler(
        min_forces=args.min_forces,
        max_forces=args.max_forces,
        force_range=(args.force_min, args.force_max),
        min_separation=args.min_separation,
        s_range=s_range,
        max_bending=math.inf if bending == 0 or not math.isfinite(bending) else math.radians(bending),
    )
    sensor = SensorModel(
        noise=args.noise,
        offset_std=args.offset_std,
        missing_prob=args.missing_prob,
        location_bias=args.location_bias,
    )
    start = time.perf_counter()
    if args.trajectory:
        contacts = ContactModel(drift_speed=args.drift_speed)
        traj = generate_trajectory(
            rod,
            args.count,
            rate=args.rate,
            sensor=sensor,
            sampler=sampler,
            contacts=contacts,
            seed=args.seed,
            decimals=args.decimals,
        )
        out, truth = write_trajectory(traj, args.out, args.truth)
        seconds = time.perf_counter() - start
        print(
            f"torchrod generate: {args.count} readings ({args.count / args.rate:.2f} s at {args.rate:g} Hz, "
            f"{len(traj.events)} appear/vanish events, up to {int(traj.loads.count.max())} contacts) in "
            f"{seconds:.2f} s -> {out}, truth -> {truth}",
            file=sys.stderr,
        )
        return 0
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    data = generate(
        rod,
        args.count,
        sampler=sampler,
        sensor=sensor,
        seed=args.seed,
        batch_size=args.batch_size,
        progress=progress,
        device=device,
    )
    data.save(args.out)
    seconds = time.perf_counter() - start
    rate = args.count / seconds if seconds > 0 else float("inf")
    rejection = data.rejection_rate
    rejected = "n/a" if rejection is None else f"{100.0 * rejection:.1f}% of {data.candidates} candidates"
    print(
        f"torchrod generate: {args.count} cases in {seconds:.2f} s ({rate:.0f} samples/s), "
        f"rejection rate {rejected} -> {args.out}",
        file=sys.stderr,
    )
    return 0
