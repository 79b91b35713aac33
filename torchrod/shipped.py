"""The files that ship inside the package, found through :mod:`importlib.resources` wherever torchrod is installed.

- ``nitinol290.json``, ``ctr250.json``: the rod files of the presets (:mod:`torchrod.presets`), to copy as the
  start of a rod file of your own; ``tube1000.json``: a 1.0 m tube with 40 gratings.
- ``nitinol290.pt``: the warm-start network trained for the ``nitinol290`` grating layout (it serves every rod whose
  gratings sit at the same positions relative to its length).
- ``example_forces.jsonl``: point forces in the input format of ``torchrod simulate``.
- ``example_stream.jsonl`` and ``example_stream_truth.jsonl``: 500 simulated readings at 50 Hz on ``nitinol290``
  (1 to 3 contacts that slide, grow, appear and vanish; noise 0.1 1/m) and the forces that made them.

``python -m torchrod.data`` lists them with their paths; ``python -m torchrod.data NAME`` prints one path (for a
shell: ``torchrod stream --rod nitinol290 --input "$(python -m torchrod.data example_stream.jsonl)"``).

In the repository the rod files and the example data are the top-level folder ``data/``, which installs as the
package ``torchrod.data``, and the network is in ``checkpoints/``, which installs as ``torchrod.checkpoints``
(``pyproject.toml``'s ``package-dir``: one copy of each file). This module is the code of :mod:`torchrod.data`.
"""

from __future__ import annotations

import atexit
import contextlib
import os
from importlib import resources
from pathlib import Path

from .errors import MissingFileError

__all__ = ["FILES", "PACKAGES", "main", "path"]

FILES: dict[str, str] = {
    "nitinol290.json": "the paper's 290 mm Nitinol tube, 14 gratings (preset nitinol290)",
    "ctr250.json": "a precurved 250 mm tube, 12 gratings (preset ctr250)",
    "tube1000.json": "a 1.0 m tube with 40 gratings",
    "nitinol290.pt": "the warm-start network for the nitinol290 grating layout",
    "example_forces.jsonl": "point forces, the input of torchrod simulate",
    "example_stream.jsonl": "500 simulated readings at 50 Hz on nitinol290, noise 0.1 1/m",
    "example_stream_truth.jsonl": "the true forces of example_stream.jsonl",
}
"""The shipped files, by name, with what each holds."""

PACKAGES: dict[str, str] = {name: "torchrod.checkpoints" if name.endswith(".pt") else "torchrod.data" for name in FILES}
"""The package each shipped file installs in: the networks in ``torchrod.checkpoints`` (the repository's
``checkpoints/``), the rest in ``torchrod.data`` (its ``data/``)."""

_extracted = contextlib.ExitStack()  # files copied out of a zipped install live until the interpreter exits
atexit.register(_extracted.close)


def path(name: str) -> Path:
    """The file system path of the shipped file ``name`` (one of :data:`FILES`).

    Raises :class:`torchrod.errors.MissingFileError` naming the known files for any other name, and when the
    installation lacks the file (a broken install: reinstall torchrod).
    """
    if name not in FILES:
        raise MissingFileError(f"torchrod ships no file {name!r}; shipped files: {', '.join(FILES)}")
    try:
        resource = resources.files(PACKAGES[name]).joinpath(name)
    except ModuleNotFoundError:  # an install made before the package held it: its files are not found
        resource = None
    if resource is None or not resource.is_file():
        where = f" ({resource})" if resource is not None else f" (no package {PACKAGES[name]})"
        raise MissingFileError(
            f"torchrod's shipped file {name!r} is missing from this installation{where}: reinstall torchrod"
        )
    if isinstance(resource, Path):
        return resource
    return Path(_extracted.enter_context(resources.as_file(resource)))  # a zipped install: a temporary copy


def main(argv: list[str] | None = None) -> int:
    """``python -m torchrod.data [NAME]``: the shipped files with their paths, or the path of one."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if args and args[0] in ("-h", "--help"):
        print("usage: python -m torchrod.data [NAME]\n\nthe files torchrod ships, or the path of the one named")
        return 0
    if args:
        try:
            print(os.fspath(path(args[0])))
        except MissingFileError as exc:
            print(f"torchrod.data: error: {exc}", file=sys.stderr)
            return 2
        return 0
    width = max(map(len, FILES))
    for name, what in FILES.items():
        print(f"{name:<{width}}  {what}\n{'':<{width}}  {path(name)}")
    return 0
