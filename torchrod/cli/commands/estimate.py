"""``torchrod estimate``: contact forces from FBG curvature readings (JSON lines in, JSON lines out).

Usage: ``torchrod estimate ROD READINGS [--out FILE]`` or ``torchrod estimate --rod ROD READINGS`` ('-' reads standard
input). ROD is a rod JSON file (see torchrod.Rod.from_json) or a preset name (the presets are listed under --rod).
READINGS is JSON lines, CSV or an interrogator's peak log, told apart by the extension or the first line (``--format``
forces one; docs/sensors.md has every format).

Each input line is one reading, as ``torchrod simulate`` writes them::

    {"id": "r1", "curvature": [[ux, uy], [ux, uy], null, ...]}

with one [ux, uy] pair [1/m] per grating in the rod file's order and ``null`` for a grating that gave no reading
(it is left out of the fit). ``id`` is optional (any JSON value, echoed back); ``t`` [s] is optional; a
``gratings`` list, if present, must match the rod's; other keys are ignored. Numbers must be finite, and a
curvature component at most 1e6 1/m in magnitude (a bend radius of 1 um: a larger value is a unit or scaling
error); finite values within that bound reach the estimator, however implausible. CSV: a header row names the
columns (``id`` and ``t`` optional; ``ux_1 .. ux_G`` and ``uy_1 .. uy_G`` in any order, or the other quantities'
columns below); without one the cells are ``id, t, ux_1, uy_1, ...`` (or ``t`` and the values, or the values
alone); an integer id stays an integer, as in JSON.

Other sensors: a line may give ``"strain": [[eps_1, ..., eps_C] or null, ...]`` (the core strains of the rod
file's multicore ``"fibre": {"cores": [[x, y], ...]}``), ``"curvature_polar": [[kappa, phi] or null, ...]``
(magnitude and bend angle [rad]), ``"wavelength"`` (peak wavelengths per grating and core, the rod file's
``fibre.wavelength.reference`` subtracted) or ``"wavelength_shift"`` instead of ``curvature``; all are turned into
curvature as they are read (torchrod.sensors). CSV columns ``kappa_K, phi_K``, ``eps_K_C``, ``lambda_K_C`` or
``dlambda_K_C`` give the same (or ``--csv-quantity`` without a header). ``--strain-noise SIGMA`` or
``--wavelength-noise SIGMA`` [pm] gives the sensor's noise instead of ``--noise``. Units: ``--curvature-unit
1/m|1/cm|1/mm``, ``--strain-unit strain|microstrain``, ``--wavelength-unit nm|pm`` (default: the rod file's fibre
says, else SI and nm). ``--protocol fbgs`` reads length-prefixed shape-sensing records instead of lines (see
``torchrod stream --help``).

Each output line answers the input line in the same position::

    {"id": "r1", "status": "ok", "num_forces": 2, "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx",
     "std_fy"}, ...], "p_value", "loss", "converged", "iterations", "evaluations", "poorly_determined", "time_ms"}

``status`` is the verdict on the answer: ``ok``; ``misfit`` (no set of forces of the counts considered explains the
reading at the noise: check the sensor and the rod file, do not act on the forces); ``unconverged``;
``poorly_determined`` (the data cannot tell this answer from others; use the standard deviations); or ``timeout``
(``--time-budget-ms`` MS, none by default: a batch of B lines stops searching after B x MS and the lines it cut
short get the best fit found so far). ``p_value`` is
the chi-square p-value of the fit. ``num_forces`` 0 with ``forces`` [] means no contact. ``forces`` sorted by s [m]
(reported location: model location + the rod's location_bias), body-frame components [N], their Gauss-Newton
standard deviations; ``loss`` the sum of squared curvature residuals [1/m^2]; ``time_ms`` the estimation time of the
line's batch divided by its readings. The count is chosen among 0 to ``--max-forces`` (or fixed by ``--num-forces``) by
the rule of ``--selection``; with ``--noise`` (the sensor's sigma per component [1/m]) the tests know the noise, without
it they estimate it from each reading (slower and weaker).
The starts of a trained warm-start network join the scan's: by default the network shipped for the rod's grating
layout (``nitinol290`` and every rod with its gratings at the same positions relative to the length; for another
layout the command says once on stderr that it runs without one), ``--checkpoint PATH`` names another, and
``--checkpoint none`` turns it off. As in ``load_estimator``, a network that its checkpoint does not
show to be trustworthy only adds starts beside the scan's, so it cannot make results worse. ``torchrod stream``
chooses its network the same way.

Every non-blank input line gets exactly one output line, in order, whatever it holds (a CSV row whose quoted cell
holds a line break is one row over several lines, answered once). A line that cannot be used
(bad JSON, a wrong number of gratings, a non-numeric, non-finite or out-of-bound value, all gratings missing, an id
JSON cannot echo such as NaN) gives ``{"id": ... or null, "error": "line N: ..."}`` naming the field and quoting
at most about 100 characters of the value, and the other lines go on. The exit status is 1 if any line failed,
else 0; 2 for a bad rod file, checkpoint or option (such as an ``--out`` that cannot be written or that names an
input) or a closed standard input or output; 141 when the reader of the output goes away; 130 after Ctrl-C and 143
after SIGTERM, both once every line already read is answered. READINGS may be a named pipe or a device: it is
opened once.

Lines are estimated in batches of ``--batch-size`` (one batched call per batch; should it fail, each reading
alone), answers in input order; a progress bar on stderr counts readings when stderr is a terminal (not with
``--quiet``). ``--out FILE`` writes the answers to FILE instead of standard output. Each batch is spread over every
CPU core (``--workers N``: N threads). The first run after an install compiles the estimation kernels once (it says
so on stderr, and where it keeps them); the answers are the same either way.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from typing import Any

from ...errors import MissingFileError
from ...estimate.estimator import Estimator, EstimatorOptions
from ...estimate.options import RULES
from ...io.jsonl import LineWriter, check_input, check_output, open_output, until_interrupted
from ...io.stream import StreamOptions, StreamResult, answer_each
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

HELP = "forces from FBG curvature readings (JSON lines in, JSON lines out)"

__all__ = [
    "HELP",
    "choose_network",
    "configure",
    "load_network",
    "options_from_args",
    "rod_and_readings",
    "run",
    "trusting",
]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "\n\n".join((__doc__ or "").split("\n\n")[1:]).replace("``", "").replace("::", ":")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "paths",
        nargs="+",
        metavar="[ROD] READINGS",
        help="the rod (a rod JSON file or preset name, unless --rod gives it) and the readings (JSON lines, CSV or a "
        "peak log; '-' for stdin)",
    )
    parser.add_argument("--rod", help=rod_help(what=", instead of the first argument"))
    count = parser.add_mutually_exclusive_group()
    count.add_argument(
        "--max-forces",
        type=int,
        metavar="H",
        help="choose the count in 0..H (default: as many as the rod's gratings can test, at most 3)",
    )
    count.add_argument("--num-forces", type=int, metavar="N", help="fit exactly N forces")
    parser.add_argument("--noise", type=float, metavar="SIGMA", help="sensor noise sigma [1/m]; default: estimated")
    parser.add_argument("--selection", choices=RULES, default="noise", help="count rule (default noise)")
    add_merge_patches_option(parser)
    parser.add_argument(
        "--threshold",
        type=float,
        default=3.0,
        help="loss threshold [1/m^2] of --selection threshold (default 3.0)",
    )
    parser.add_argument(
        "--starts",
        type=int,
        default=None,
        help=f"scan starts per count (default {EstimatorOptions.starts}; 0: only the network's, with --checkpoint)",
    )
    parser.add_argument(
        "--checkpoint",
        default=None,
        metavar="PATH",
        help="warm-start network checkpoint whose guesses start the fits (default: the network shipped for the rod's "
        "grating layout, if any; 'none': no network)",
    )
    add_input_options(parser)
    add_sensor_options(parser)
    parser.add_argument("--out", metavar="FILE", help="write the answers to FILE (default: standard output)")
    parser.add_argument("--batch-size", type=int, default=1024, metavar="B", help="readings per batch (default 1024)")
    add_time_budget_option(parser, None)
    add_device_option(parser)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads, for the warm-start network (default 1: the solver threads, --workers, use the cores)",
    )
    add_workers_option(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def check_counts(args: argparse.Namespace, rod: Rod | None = None) -> None:
    """``--max-forces`` and ``--num-forces`` (where the command has them) must be >= 0 (``ValueError``, status 2);
    the estimator judges the rest. ``--max-forces`` not given becomes the ``rod``'s default
    (:func:`~torchrod.estimate.options.default_max_forces`: as many as its gratings can test, at most 3). With the
    ``rod``, a count asked for that a full reading cannot test (its 3 unknowns per force, s, fx, fy, leave fewer
    than :data:`~torchrod.rod.MIN_TEST_DOF` degrees of freedom in the 2 values per grating) is warned about
    (:class:`~torchrod.errors.RodWarning`): the estimator never chooses such a count, and a fixed one is not
    tested."""
    from ...estimate.options import default_max_forces
    from ...rod import FORCE_RULE, max_testable_forces

    for option in ("max_forces", "num_forces"):
        value = getattr(args, option, None)
        if value is not None and value < 0:
            raise ValueError(f"--{option.replace('_', '-')} must be >= 0, got {value}")
    if hasattr(args, "max_forces") and args.max_forces is None:
        args.max_forces = default_max_forces(rod.num_gratings) if rod is not None else EstimatorOptions.max_forces
        return
    if rod is None:
        return
    option = "num_forces" if getattr(args, "num_forces", None) is not None else "max_forces"
    count = getattr(args, option, None)
    most = max_testable_forces(rod.num_gratings)
    if count is not None and count > most:
        import warnings

        from ...errors import RodWarning

        effect = f"a fit of {count} is not tested" if option == "num_forces" else f"more than {most} are never chosen"
        warnings.warn(
            f"--{option.replace('_', '-')} {count} asks for more forces than a reading of this rod's "
            f"{rod.num_gratings} grating(s) can test ({most}: {FORCE_RULE}): {effect}",
            RodWarning,
            stacklevel=2,
        )


def add_merge_patches_option(parser: argparse.ArgumentParser) -> None:
    """``--no-merge-patches``: the count tests alone (``EstimatorOptions.merge_patches`` False)."""
    parser.add_argument(
        "--no-merge-patches",
        dest="merge_patches",
        action="store_false",
        help="answer a poorly determined pair of forces that the gratings cannot tell from one patch of load as two, "
        "as the count tests alone give it (default: one force)",
    )


def add_workers_option(parser: argparse.ArgumentParser) -> None:
    """``--workers N``: the CPU threads the readings are solved on."""
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        metavar="N",
        help="solve on N CPU threads (default 0: one per CPU core)",
    )


def check_workers(args: argparse.Namespace) -> int:
    """The CPU threads ``--workers`` asks for (0: one per CPU core); ``ValueError`` below 0."""
    from ...kernels.host import cpu_threads

    if args.workers < 0:
        raise ValueError(f"--workers must be >= 1, or 0 for one per CPU core, got {args.workers}")
    return cpu_threads(args.workers or None)


def options_from_args(args: argparse.Namespace) -> EstimatorOptions:
    """The :class:`EstimatorOptions` the command-line arguments ask for (``ValueError`` for bad values). A network
    (``--checkpoint``) adds its guesses, trusted or not as :func:`trusting` says."""
    workers = getattr(args, "workers", 0)
    return EstimatorOptions(
        max_forces=args.max_forces,
        num_forces=args.num_forces,
        noise=args.noise,
        selection=args.selection,
        threshold=args.threshold,
        merge_patches=args.merge_patches,
        starts=EstimatorOptions.starts if args.starts is None else args.starts,
        relative=getattr(args, "relative", False),
        time_budget=time_budget(args),
        threads=workers or None,
    )


def trusting(options: EstimatorOptions, network: Any) -> EstimatorOptions:
    """``options`` with ``trust_guesses`` as ``load_estimator`` sets it: a trusted network's guesses
    start the fits alone (:func:`torchrod.learn.warm_start.is_trusted`), a weak one's are starts beside the scan's."""
    from ...learn.warm_start import is_trusted

    return dataclasses.replace(options, trust_guesses=is_trusted(network))


def choose_network(checkpoint: str | None, rod: Rod, command: str) -> Any:
    """The warm-start network ``--checkpoint`` asks for, the same way in ``estimate`` and ``stream``: by default
    (None) the network shipped for ``rod``'s grating layout (:func:`torchrod.learn.warm_start.shipped_network`; when
    none fits, said once on stderr and None), ``none`` for no network, else the file (:func:`load_network`)."""
    if checkpoint is not None:
        return load_network(checkpoint, rod)
    from ...learn.warm_start import shipped_network

    network, line = shipped_network(rod)
    if network is None:
        print(f"torchrod {command}: {line}", file=sys.stderr)
    return network


def load_network(checkpoint: str | None, rod: Rod) -> Any:
    """The warm-start network of ``--checkpoint`` (None for None or ``none``); :class:`MissingFileError` when the
    file does not exist, ``ValueError`` naming the file when it cannot be used (not a checkpoint, another grating
    layout)."""
    if checkpoint is None or checkpoint.lower() == "none":
        return None
    from ...learn.warm_start import UNTRUSTED_ADVICE, WarmStart, quality_verdict

    if not os.path.exists(checkpoint):
        raise MissingFileError(f"--checkpoint {checkpoint}: no such file (give a checkpoint file, or 'none')")
    try:
        network = WarmStart.load(checkpoint, rod)  # its errors name the file and what is wrong
    except Exception as exc:  # noqa: BLE001 - an unreadable file is a bad option, not a crash
        if isinstance(exc, ValueError):
            raise
        raise ValueError(
            f"{checkpoint}: cannot load it as a warm-start checkpoint ({type(exc).__name__}: {str(exc)[:200]})"
        ) from None
    weak = quality_verdict(network.meta)
    if weak:
        print(
            f"torchrod: the warm-start network {checkpoint} is not trusted ({weak}): {UNTRUSTED_ADVICE}",
            file=sys.stderr,
        )
    return network


def rod_and_readings(args: argparse.Namespace) -> None:
    """Set ``args.rod`` and ``args.readings`` from ``[ROD] READINGS`` and ``--rod`` (``ValueError`` for another
    count)."""
    paths = list(args.paths)
    if args.rod is None and len(paths) == 2:
        args.rod, args.readings = paths
    elif args.rod is not None and len(paths) == 1:
        args.readings = paths[0]
    else:
        given = "--rod and " if args.rod is not None else ""
        raise ValueError(
            f"give the rod and the readings (torchrod estimate ROD READINGS, or --rod ROD READINGS); got {given}"
            f"{len(paths)} argument(s): {' '.join(paths)}"
        )


def run(args: argparse.Namespace) -> int:
    return until_interrupted(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    rod_and_readings(args)
    rod = sensor_rod(args, load_rod(args.rod))
    check_estimation_options(args)
    sensor_noise(args, rod)
    check_counts(args, rod)
    workers = check_workers(args)
    device = check_device(args)
    if args.starts is not None and args.starts < 0:
        raise ValueError(f"--starts must be >= 0, got {args.starts}")
    check_input(args.readings, "READINGS")
    inputs = {"READINGS": args.readings, "--rod": args.rod, "--checkpoint": args.checkpoint}
    check_output(args.out, inputs)
    network = choose_network(args.checkpoint, rod, "estimate")
    estimator = Estimator(rod, trusting(options_from_args(args), network), warm_start=network)
    estimator.plan(device=device)  # the kernels compiled or loaded before the first reading
    settle()
    readings = reading_source(args, rod, args.readings)
    from tqdm import tqdm

    # A stream with no latency bound: the batches, the fall-back to single readings, the flush on an interrupt and
    # the first run's compile are the stream's (torchrod.io.stream); each reading's noise is its own.
    options = StreamOptions(batch_size=args.batch_size, learn_noise=None, device=device, workers=workers)
    with open_output(args.out, inputs) as out:
        writer = LineWriter(out)
        bar = tqdm(
            disable=args.quiet or not sys.stderr.isatty(),
            file=sys.stderr,
            unit="reading",
            dynamic_ncols=True,
            leave=False,
        )

        def emit(result: StreamResult) -> None:
            if result.error is not None:
                writer.error(result.id, result.error)
            else:
                record = {k: v for k, v in result.record.items() if k not in _STREAM_ONLY}
                record["time_ms"] = 1e3 * result.solve_time / max(result.batch, 1)
                writer.answer(record, result.line, flush=result.batch_end)
            bar.update(1)

        try:
            interrupted = answer_each(estimator, readings, options, emit, lambda: writer.lines)
        except BrokenPipeError:  # the reader went away (| head): stop quietly
            return 141
        finally:
            bar.close()
    if interrupted is not None:
        raise interrupted
    return 1 if writer.errors else 0


_STREAM_ONLY = ("t", "latency_ms")
"""What a stream's record holds that an estimate's does not: an estimate answers a file, so it echoes no time and
has no latency; its ``time_ms`` is the solve time per reading of its batch."""
