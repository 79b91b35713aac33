"""One module per ``torchrod`` subcommand (see :mod:`torchrod.cli`), and the option checks they share."""

from __future__ import annotations

import argparse
import gc
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (torch is imported where a command needs it: `torchrod --help` starts without it)
    import torch

__all__ = [
    "add_device_option",
    "add_input_options",
    "add_sensor_options",
    "add_time_budget_option",
    "check_device",
    "check_estimation_options",
    "rod_help",
    "reading_source",
    "sensor_noise",
    "sensor_rod",
    "settle",
    "time_budget",
]


def rod_help(default: str | None = None, what: str = "") -> str:
    """The help of a ``--rod`` option: a rod file, or one of the presets, every one named
    (:data:`torchrod.presets.PRESETS`); ``what`` says more about the rod, ``default`` its default."""
    from ...presets import PRESETS

    text = f"rod JSON file or preset name{what} (presets: {', '.join(PRESETS)})"
    return text if default is None else f"{text[:-1]}; default {default})"


SWITCH_INTERVAL = 0.0005
"""[s] How long a thread running Python keeps the interpreter lock while another asks for it, during a command's
readings (Python's default is 5 ms). A stream's solver threads need the lock for a moment before and after each
batch's kernels, and the thread reading and writing lines holds it nearly all the time: at the default, a solver
thread waited milliseconds for each short step while its core stood idle."""

_saved: list[float] = []  # the switch interval settle() replaced


def settle() -> None:
    """Move everything the command has made so far (torch, the rod, the estimator and its network) out of reach
    of the garbage collector (:func:`gc.freeze`), once it is set up and before the readings come, and hand the
    interpreter lock between threads sooner (:data:`SWITCH_INTERVAL`). Each reading's records and results are many
    small objects, which set off collections; a full one walked every object torch made at its import, and in a
    stream that cost as much per reading as making the records. :func:`unsettle` undoes both when the command
    returns (:func:`torchrod.cli.main`), so a program or test that calls it goes on as before; the library's own
    functions do neither: they do not change the interpreter of the program that calls them."""
    gc.freeze()
    if not _saved:
        _saved.append(sys.getswitchinterval())
    sys.setswitchinterval(SWITCH_INTERVAL)


def unsettle() -> None:
    """Undo :func:`settle` (nothing when it was not called): the objects frozen are the collector's again, and the
    interpreter's switch interval is what it was."""
    gc.unfreeze()
    if _saved:
        sys.setswitchinterval(_saved.pop())


def check_estimation_options(args: argparse.Namespace) -> None:
    """Check ``--batch-size``, ``--noise`` and ``--threads`` of an estimating command and apply ``--threads``.

    Raises ``ValueError`` naming the option and its bad value (the CLI turns it into exit status 2).
    """
    import torch

    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    from ...errors import OptionsError
    from ...io.quantities import MAX_CURVATURE

    if args.noise is not None and not args.noise >= 0.0:
        raise ValueError(f"--noise must be >= 0, got {args.noise}")
    if args.noise is not None and not args.noise <= MAX_CURVATURE:
        raise OptionsError(
            f"--noise must be at most {MAX_CURVATURE:g} 1/m, the largest curvature a reading may carry, got "
            f"{args.noise:g}"
        )
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
    "torch device the readings are estimated on: cpu (default), cuda, cuda:1, ... (on a GPU one thread estimates "
    "each reading: for large batches; needs numba-cuda, pip install torchrod[cuda])"
)


def add_device_option(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, text: str = ESTIMATION_DEVICE_HELP
) -> None:
    """``--device`` (default cpu), checked by :func:`check_device`; ``text``, its help, says what runs there."""
    parser.add_argument("--device", default="cpu", help=text)


def check_device(args: argparse.Namespace) -> torch.device:
    """``--device`` as a :class:`torch.device`; ``ValueError`` for a name torch does not know, or a device this
    machine does not have (found now, not at the first reading)."""
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
    return dev


def add_sensor_options(parser: argparse.ArgumentParser, *, estimating: bool = True) -> None:
    """The options of readings from other sensors and in other units (:mod:`torchrod.sensors`): ``--csv-quantity``,
    ``--peaks``, the unit options, and for an estimating command ``--strain-noise``, ``--wavelength-noise`` and
    ``--relative``. :func:`sensor_rod` and :func:`sensor_noise` apply them."""
    from ...io.peaklog import parse_peaks_option
    from ...io.quantities import QUANTITIES
    from ...sensors import CURVATURE_UNITS, STRAIN_UNITS, WAVELENGTH_UNITS

    parser.add_argument(
        "--csv-quantity",
        choices=tuple(QUANTITIES),
        default="curvature",
        help="what a CSV row without a header gives per grating: ux, uy (default); kappa, phi [rad]; the fibre's "
        "core strains; its peak wavelengths; or its wavelength shifts (a header row names its columns instead; JSON "
        "lines say it by their key: curvature, curvature_polar, strain, wavelength, wavelength_shift)",
    )
    parser.add_argument(
        "--peaks",
        type=_peaks_option(parse_peaks_option),
        metavar="LAYOUT",
        help="which (grating, core) each value of a peak log line is: by-core (core 1's gratings, then core 2's, "
        "...), by-grating, or per peak GRATING:CORE (1-based) or - for a peak not read, comma-separated "
        "(default: the rod file's fibre.wavelength.peaks, else by-core)",
    )
    units = (
        ("--curvature-unit", CURVATURE_UNITS, "curvature and curvature magnitude", "1/m"),
        ("--strain-unit", STRAIN_UNITS, "core strains", "strain (dimensionless)"),
        ("--wavelength-unit", WAVELENGTH_UNITS, "peak wavelengths and shifts", "nm"),
    )
    for option, table, what, default in units:
        parser.add_argument(
            option,
            choices=tuple(table),
            default=None,
            help=f"unit of the readings' {what} (default: the rod file's fibre.{option[2:].replace('-', '_')}, "
            f"else {default}); converted to SI as they are read",
        )
    if not estimating:
        return
    parser.add_argument(
        "--strain-noise",
        type=float,
        metavar="SIGMA",
        help="strain noise sigma per core (dimensionless) of the rod's multicore fibre, instead of --noise: the "
        "curvature noise it implies weighs the fit",
    )
    parser.add_argument(
        "--wavelength-noise",
        type=float,
        metavar="SIGMA",
        help="peak wavelength noise sigma per core [pm], instead of --noise: the curvature noise it implies through "
        "each grating's conversion (calibration matrix or physics) weighs the fit (the largest over the gratings)",
    )
    parser.add_argument(
        "--relative",
        action="store_true",
        help="readings of a precurved rod are the change from its unloaded shape, u - u* (default: the total "
        "curvature u, which a fibre straight when unstrained reads)",
    )


def _peaks_option(parse):
    """``--peaks`` for argparse: a bad layout is a usage error naming it."""

    def parse_option(text: str):
        try:
            return parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return parse_option


def sensor_rod(args: argparse.Namespace, rod):
    """``rod`` with its fibre's units as the unit options say (a fibre of units alone for a rod without one), and
    ``--peaks`` checked against its wavelength section; ``ValueError`` when they do not fit."""
    from ...sensors import UNIT_TABLES, Fibre

    units = {key: getattr(args, key) for key in UNIT_TABLES if getattr(args, key, None) is not None}
    if units:
        rod = rod.with_(fibre=rod.fibre.with_(**units) if rod.fibre is not None else Fibre(**units))
    peaks = getattr(args, "peaks", None)
    if peaks is not None:
        if rod.fibre is None or rod.fibre.wavelength is None:
            raise ValueError(
                '--peaks maps a peak log onto the rod file\'s "fibre": {"wavelength": ...}, which it lacks'
            )
        try:
            rod.fibre.peak_layout(peaks)
        except ValueError as exc:
            raise ValueError(str(exc)) from None
    return rod


def sensor_noise(args: argparse.Namespace, rod) -> None:
    """Turn ``--strain-noise`` or ``--wavelength-noise`` into ``args.noise`` (the curvature sigma it implies through
    the rod's fibre; for wavelengths the largest over the gratings, said on stderr when they differ);
    ``ValueError`` when it cannot be used."""
    import sys

    from ...errors import OptionsError
    from ...io.quantities import MAX_CURVATURE
    from ...sensors import MAX_STRAIN, MAX_WAVELENGTH_SHIFT, WAVELENGTH_UNITS

    strain = getattr(args, "strain_noise", None)
    wavelength = getattr(args, "wavelength_noise", None)
    given = [
        name
        for name, v in (("--noise", args.noise), ("--strain-noise", strain), ("--wavelength-noise", wavelength))
        if v is not None
    ]
    if len(given) > 1:
        raise ValueError(
            f"give one of --noise (curvature sigma), --strain-noise and --wavelength-noise, not both "
            f"({' and '.join(given)})"
        )
    if strain is not None:
        if rod.fibre is None or not rod.fibre.cores:
            raise ValueError('--strain-noise needs the rod file\'s multicore fibre ("fibre": {"cores": [[x, y], ...]})')
        if not strain >= 0.0 or strain == float("inf"):
            raise ValueError(f"--strain-noise must be >= 0 and finite, got {strain}")
        if strain > MAX_STRAIN:
            raise OptionsError(
                f"--strain-noise must be at most {MAX_STRAIN:g}, the largest strain a reading may carry (it is "
                f"dimensionless: 1e-6 is one microstrain), got {strain:g}"
            )
        args.noise = rod.fibre.curvature_sigma(strain)
    if wavelength is not None:
        if rod.fibre is None or rod.fibre.wavelength is None:
            raise ValueError('--wavelength-noise needs the rod file\'s "fibre": {"wavelength": {...}} section')
        if not wavelength >= 0.0 or wavelength == float("inf"):
            raise ValueError(f"--wavelength-noise must be >= 0 and finite [pm], got {wavelength}")
        pm = WAVELENGTH_UNITS["pm"]
        if wavelength * pm > MAX_WAVELENGTH_SHIFT:
            raise OptionsError(
                f"--wavelength-noise must be at most {MAX_WAVELENGTH_SHIFT / pm:g} pm, the largest shift a reading "
                f"may carry, got {wavelength:g}"
            )
        sigmas = rod.fibre.wavelength_sigmas(wavelength * pm)
        args.noise = max(sigmas)
        low = min(sigmas)
        if low < 0.9 * args.noise:
            print(
                f"torchrod: --wavelength-noise {wavelength:g} pm implies a curvature sigma of {low:.3g} to "
                f"{args.noise:.3g} 1/m over the gratings; the fit is weighed with the largest",
                file=sys.stderr,
            )
    if (strain is not None or wavelength is not None) and not args.noise <= MAX_CURVATURE:
        option, value = ("--strain-noise", strain) if strain is not None else ("--wavelength-noise", wavelength)
        raise OptionsError(
            f"{option} {value:g} implies a curvature sigma of {args.noise:.3g} 1/m, beyond the largest curvature a "
            f"reading may carry ({MAX_CURVATURE:g} 1/m): check its unit"
        )


def reading_source(args: argparse.Namespace, rod, path: str):
    """The readings of ``path`` as the options ask: a protocol's records (``--protocol NAME``, an entry of
    :data:`torchrod.io.formats.INPUT_FORMATS`, e.g. :mod:`torchrod.io.fbgs`), or lines in ``--format``
    (:class:`torchrod.io.sources.ReadingSource`)."""
    protocol = getattr(args, "protocol", "lines")
    if protocol != "lines":
        from ...io.formats import ReadOptions, protocols

        reader = protocols()[protocol].protocol
        assert reader is not None  # (a protocol's entry has its reader)
        options = ReadOptions(
            rod.num_gratings,
            quantity=getattr(args, "csv_quantity", "curvature"),
            fibre=rod.fibre,
            peaks=getattr(args, "peaks", None),
            unit=getattr(args, "curvature_unit", None),
        )
        return reader(path, options)
    from ...io.sources import ReadingSource

    return ReadingSource(
        path,
        rod.num_gratings,
        rod.gratings,
        args.format,
        quantity=args.csv_quantity,
        fibre=rod.fibre,
        peaks=getattr(args, "peaks", None),
        max_line=getattr(args, "max_line_bytes", None),
    )


def _line_bytes(text: str) -> int:
    """``--max-line-bytes`` for argparse: an integer >= 1, else a usage error naming it."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer number of bytes >= 1, got {text!r}")
    return value


def add_input_options(parser: argparse.ArgumentParser, *, protocol: bool = True) -> None:
    """``--format``, ``--max-line-bytes`` (and ``--protocol``): how a readings input is read."""
    from ...io.formats import format_help, protocol_help, protocols
    from ...io.sources import MIN_LINE_BYTES, format_names

    parser.add_argument("--format", choices=format_names(), default="auto", help=format_help())
    parser.add_argument(
        "--max-line-bytes",
        type=_line_bytes,
        default=None,
        metavar="N",
        help=f"longest input line read; a longer one is an error line, read past without being held (default: "
        f"{MIN_LINE_BYTES} bytes, or 64 per value of the rod's largest reading when more; decoding a line can take "
        "20 times its size in memory)",
    )
    if protocol:
        parser.add_argument(
            "--protocol",
            choices=("lines", *protocols()),
            default="lines",
            help=protocol_help(),
        )
