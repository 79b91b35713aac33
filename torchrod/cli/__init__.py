"""The ``torchrod`` command: one subcommand per task, each implemented in ``torchrod/cli/commands/<name>.py``.

Every command module defines ``HELP`` (one line), ``configure(parser)`` and ``run(args) -> int``; they are imported
only when their subcommand runs, and ``import torchrod`` loads nothing heavy, so ``torchrod --version`` and
``torchrod --help`` answer without importing torch. :data:`COMMANDS` holds what ``--help`` tells a user about each.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import textwrap
import warnings
from collections.abc import Callable, Sequence
from types import ModuleType

from ..errors import TorchrodError

__all__ = ["COMMANDS", "DESCRIPTION", "command_parser", "help_pages", "main"]

DESCRIPTION = (
    "Where a thin elastic rod (catheter, needle, concentric tube) is touched, and how hard,\n"
    "from the curvature that fibre Bragg gratings (FBG) along it read."
)

COMMANDS: dict[str, str] = {
    "estimate": "contact forces (where and how hard, with uncertainties) from FBG curvature readings, "
    "JSON lines in and out",
    "stream": "contact forces from a live stream of readings (JSON lines or CSV), batched under a latency bound",
    "simulate": "the curvature the gratings would read under given point forces (to test or to make data)",
    "plot": "figures of readings and their estimates: the bent rod with its forces, the fit, forces over time",
    "calibrate": "fit a rod's location bias and bending stiffness from readings with known forces",
    "rod": "write a rod file from its numbers, or check one: EI, the grating layout, how many forces it can tell "
    "apart, the warm-start network, the curvature of a 1 N tip load",
    "generate": "synthetic training sets and synthetic reading streams with their true forces",
    "train": "train the warm-start network that gives the estimator its first guess",
    "evaluate": "how accurate the estimator is on simulated readings, by number of forces and noise level",
    "bench": "speed and accuracy benchmarks, measured side by side (startup, forward, estimate, stream, ...)",
}

EPILOG = (
    "ROD (the --rod option) is a rod JSON file or a preset name ({presets}).\n"
    "Units are SI: m, N, 1/m. 'torchrod COMMAND --help' lists a command's options."
)
"""The end of ``torchrod --help``; ``{presets}`` becomes every preset's name (:data:`torchrod.presets.PRESETS`)."""


def _command_list(width: int = 88) -> str:
    """The commands and what each is for, as ``torchrod --help`` lists them."""
    indent = 2 + max(map(len, COMMANDS)) + 2
    lines = ["commands:"]
    for name, text in COMMANDS.items():
        lines += textwrap.wrap(text, width, initial_indent=f"  {name:<{indent - 2}}", subsequent_indent=" " * indent)
    return "\n".join(lines)


def _build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from ..presets import PRESETS

    parser = argparse.ArgumentParser(
        prog="torchrod",
        description=DESCRIPTION,
        epilog=f"{_command_list()}\n\n{EPILOG.format(presets=', '.join(PRESETS))}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"torchrod {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", help="one of the commands below")
    for name in COMMANDS:
        sub.add_parser(name, add_help=False)
    return parser


def command_parser(name: str, module: ModuleType | None = None) -> argparse.ArgumentParser:
    """The argument parser of ``torchrod NAME`` (``module``: the command's module, imported when not given)."""
    if module is None:
        module = importlib.import_module(f".commands.{name}", __package__)
    parser = argparse.ArgumentParser(prog=f"torchrod {name}", description=COMMANDS[name])
    module.configure(parser)
    return parser


def help_pages(width: int = 100) -> dict[str, str]:
    """What ``--help`` prints for ``torchrod``, each command and each benchmark suite, keyed by the command line
    (``"torchrod"``, ``"torchrod estimate"``, ``"torchrod bench stream"``, ...), wrapped at ``width`` columns: the
    source of the documentation's CLI reference, so that it is never copied by hand. Imports every command."""
    import os

    from .benchmarks import SUITES
    from .commands.bench import load_suite, suite_parser

    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(width)  # argparse wraps at the terminal's width
    try:
        pages = {"torchrod": _build_parser().format_help()}
        for name in COMMANDS:
            pages[f"torchrod {name}"] = command_parser(name).format_help()
        for suite in SUITES:
            module = load_suite(suite)
            if module is not None:
                pages[f"torchrod bench {suite}"] = suite_parser(suite, module).format_help()
    finally:
        if saved is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = saved
    return pages


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``torchrod`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or argv[0] not in COMMANDS:
        if argv and not argv[0].startswith("-"):
            parser.print_usage(sys.stderr)
            print(f"torchrod: unknown command {argv[0]!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
            return 2
        parser.parse_args(argv)  # --help / --version exit here
        parser.print_help()
        return 2
    name = argv[0]
    try:
        module = importlib.import_module(f".commands.{name}", __package__)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.endswith(f"commands.{name}"):
            print(f"torchrod {name}: not available in this version", file=sys.stderr)
            return 2
        raise
    sub = command_parser(name, module)
    args = sub.parse_args(argv[1:])
    restore = _standard_streams()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_printer(name)
            return int(module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader of our output went away (as with `| head`): stop quietly, as for SIGPIPE.
        from ..io.jsonl import quiet_closed_pipe

        quiet_closed_pipe(sys.stdout)
        return 141
    except (TorchrodError, ValueError, OSError) as exc:
        # A bad input, option, rod file or checkpoint (the library's own errors, TorchrodTypeError too; OSError: a
        # directory, a missing or unreadable file, a full disk, a closed standard stream): one line, no traceback.
        print(f"torchrod {name}: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        # Name only the options this command has that size its work (plot has neither --count nor --batch-size).
        flags = {option for action in sub._actions for option in action.option_strings}
        sizes = [f for f in ("--count", "--count-per-cell", "--batch-size", "--samples", "--dpi") if f in flags]
        smaller = f" (a smaller {' or '.join(sizes)})" if sizes else ""
        print(f"torchrod {name}: error: out of memory; ask for less at a time{smaller}", file=sys.stderr)
        return 2
    finally:
        restore()
        from .commands import unsettle

        unsettle()  # what the command froze (commands.settle) is the collector's again, and the interpreter as it
        # was: main() may be called in a process that goes on (a test, a script)


def _standard_streams() -> Callable[[], None]:
    """Make a command safe to run with a standard stream closed (``<&-``, ``>&-``, ``2>&-``); returns what undoes
    the change to ``sys`` (the file descriptors stay taken).

    A closed descriptor 0, 1 or 2 is taken by the null device, so that a file the command opens never lands on it
    (and output meant for the terminal never goes into an output file). Python starts with ``sys.stdin`` /
    ``sys.stdout`` / ``sys.stderr`` None then: standard input stays None (reading ``-`` is refused with a clear
    error, :func:`torchrod.io.jsonl.check_input`), standard output becomes a
    :class:`~torchrod.io.jsonl.ClosedOutput` (writing an answer there is one clear error, never a silent loss), and
    standard error goes to the null device."""
    from ..io.jsonl import ClosedOutput

    for fd, flags in ((0, os.O_RDONLY), (1, os.O_WRONLY), (2, os.O_WRONLY)):
        try:
            os.fstat(fd)
        except OSError:
            taken = os.open(os.devnull, flags)
            if taken != fd:  # (a lower descriptor was free too: it is taken in its own turn)
                os.dup2(taken, fd)
                os.close(taken)
    stdout, stderr = sys.stdout, sys.stderr
    if stdout is None:
        sys.stdout = ClosedOutput()
    if stderr is None:
        sys.stderr = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 - closed by the returned function

    def restore() -> None:
        if stdout is None:
            sys.stdout = stdout
        if stderr is None:
            sys.stderr.close()
            sys.stderr = stderr

    return restore


def _warning_printer(name: str) -> Callable[..., None]:
    """``warnings.showwarning`` for a command: torchrod's own warnings (:class:`torchrod.errors.TorchrodWarning`,
    such as a rod that cannot determine what is asked) as one line ``torchrod NAME: warning: ...`` on stderr, each
    text once; others as Python prints them."""
    from ..errors import TorchrodWarning

    default = warnings.showwarning
    shown: set[str] = set()  # (a rod copied inside the command warns again: each text is printed once)

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001 - warnings' API
        if isinstance(category, type) and issubclass(category, TorchrodWarning):
            if str(message) not in shown:
                shown.add(str(message))
                print(f"torchrod {name}: warning: {message}", file=sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)

    return show


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
