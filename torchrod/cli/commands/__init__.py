"""One module per ``torchrod`` subcommand (see :mod:`torchrod.cli`), and the option checks they share."""

from __future__ import annotations

import argparse
import gc
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (torch is imported where a command needs it: `torchrod --help` starts without it)
    import torch

__all__ = [
    "add_device_option",
    "add_sensor_options",
    "add_time_budget_option",
    "check_device",
    "check_estimation_options",
    "rod_help",
    "sensor_noise",
    "settle",
    "time_budget",
]


def rod_help(default: str | None = None, what: str = "") -> str:
    """The help of a ``--rod`` option: a rod file, or one of the presets, every one named (:data:`torchrod.presets.
    PRESETS`); ``what`` says more about the rod, ``default`` its default."""
    from ...presets import PRESETS

    text = f"rod JSON file or preset name{what} (presets: {', '.join(PRESETS)})"
    return text if default is None else f"{text[:-1]}; default {default})"


def settle() -> None:
    """Move everything the command has made so far (torch, the rod, the estimator and its network) out of reach
    of the garbage collector (:func:`gc.freeze`), once it is set up and before the readings come. Each reading's
    records and results are many small objects, which set off collections; a full one walked every object torch
    made at its import, and in a stream that cost as much per reading as making the records.
    :func:`torchrod.cli.main` gives them back (:func:`gc.unfreeze`) when the command returns, so a program or test
    that calls it goes on as before; the library's own functions never freeze: they do not change the interpreter of
    the program that calls them."""
    gc.freeze()


def check_estimation_options(args: argparse.Namespace) -> None:
    """Check ``--batch-size``, ``--noise`` and ``--threads`` of an estimating command and apply ``--threads``.

    Raises ``ValueError`` naming the option and its bad value (the CLI turns it into exit status 2).
    """
    import torch

    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.noise is not None and not args.noise >= 0.0:
        raise ValueError(f"--noise must be >= 0, got {args.noise}")
    budget = getattr(args, "time_budget_ms", None)
    if budget is not None and not 0.0 <= budget < float("inf"):
        raise ValueError(f"--time-budget-ms must be >= 0, got {budget}")
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)


def add_time_budget_option(parser: argparse.ArgumentParser, default_ms: float | None) -> None:
    """``--time-budget-ms``: the per-reading time budget (``EstimatorOptions.time_budget``, in ms at this edge)."""
    shown = "none" if default_ms is None else f"{default_ms:g}"
    parser.add_argument(
        "--time-budget-ms",
        type=float,
        default=default_ms,
        metavar="MS",
        help="time budget per reading: a batch of B readings stops searching after B x MS, and the readings it "
        f"cut are answered with the best fit so far and status timeout (default {shown})",
    )


def time_budget(args: argparse.Namespace) -> float | None:
    """``--time-budget-ms`` in seconds (SI inside), None for no budget."""
    budget = getattr(args, "time_budget_ms", None)
    return None if budget is None else budget / 1e3


ESTIMATION_DEVICE_HELP = (
    "torch device the readings are estimated on: cpu (default), cuda, cuda:1, ... (a GPU runs the torch backend, at "
    "present far slower than the CPU: docs/results.md, 'On a GPU')"
)


def add_device_option(parser: argparse.ArgumentParser, text: str = ESTIMATION_DEVICE_HELP) -> None:
    """``--device`` (default cpu), checked by :func:`check_device`; ``text``, its help, says what runs there."""
    parser.add_argument("--device", default="cpu", help=text)


def check_device(args: argparse.Namespace, processes: int = 1) -> torch.device:
    """``--device`` as a :class:`torch.device`; ``ValueError`` for a name torch does not know, a device this
    machine does not have (found now, not at the first reading), or worker ``processes`` (which solve on CPU cores)
    asked for beside a device other than the CPU (where one process solves whole batches)."""
    import torch

    try:
        dev = torch.device(args.device)
    except (RuntimeError, ValueError):
        raise ValueError(f"--device {args.device!r} is not a torch device (cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {args.device!r}: torch sees no CUDA device on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"--device {args.device!r}: this machine has {torch.cuda.device_count()} CUDA devices")
    elif dev.type != "cpu":
        try:
            torch.zeros(1, device=dev)
        except (RuntimeError, AssertionError) as exc:
            raise ValueError(f"--device {args.device!r} cannot be used here: {exc}") from None
    if dev.type != "cpu" and processes > 1:
        raise ValueError(
            f"--workers {args.workers} asks for {processes} processes, which solve on CPU cores; with --device "
            f"{args.device} one process solves whole batches on the device: leave --workers at 1"
        )
    return dev


def add_sensor_options(parser: argparse.ArgumentParser) -> None:
    """``--csv-quantity`` and ``--strain-noise``: readings from other sensors (:mod:`torchrod.sensors`)."""
    parser.add_argument(
        "--csv-quantity",
        choices=("curvature", "polar", "strain"),
        default="curvature",
        help="what a CSV row gives per grating: ux, uy [1/m] (default); kappa [1/m], phi [rad]; or the fibre's "
        "core strains (JSON lines say it by their key: curvature, curvature_polar, strain)",
    )
    parser.add_argument(
        "--strain-noise",
        type=float,
        metavar="SIGMA",
        help="strain noise sigma per core (dimensionless) of the rod's multicore fibre, instead of --noise: the "
        "curvature noise it implies weighs the fit",
    )
    parser.add_argument(
        "--relative",
        action="store_true",
        help="readings of a precurved rod are the change from its unloaded shape, u - u* (default: the total "
        "curvature u, which a fibre straight when unstrained reads)",
    )


def sensor_noise(args: argparse.Namespace, rod) -> None:
    """Turn ``--strain-noise`` into ``args.noise`` (the curvature sigma it implies through the rod's fibre);
    ``ValueError`` when it cannot be used."""
    strain = getattr(args, "strain_noise", None)
    if strain is None:
        return
    if args.noise is not None:
        raise ValueError("give --noise (curvature sigma) or --strain-noise (core strain sigma), not both")
    if rod.fibre is None:
        raise ValueError('--strain-noise needs the rod file\'s multicore fibre ("fibre": {"cores": [[x, y], ...]})')
    if not strain >= 0.0 or strain == float("inf"):
        raise ValueError(f"--strain-noise must be >= 0 and finite, got {strain}")
    args.noise = rod.fibre.curvature_sigma(strain)
