"""The exceptions torchrod raises for input it cannot use.

Every error torchrod raises on purpose derives from :class:`TorchrodError`, so a program can catch the library's
own complaints apart from bugs. The subclasses also derive from the built-in exception a Python user expects for
the same mistake (a bad value is a :class:`ValueError`, a missing file a :class:`FileNotFoundError`), so code
written against the built-in types keeps working. Messages name the offending value and say what to do.

A reading the estimator cannot fit is not an exception: it is answered with a status (:class:`torchrod.Status`).
"""

from __future__ import annotations

__all__ = [
    "CheckpointError",
    "MissingFileError",
    "OptionsError",
    "ReadingError",
    "ReadingWarning",
    "RodError",
    "RodWarning",
    "TorchrodError",
    "TorchrodTypeError",
    "TorchrodWarning",
]


class TorchrodError(Exception):
    """Base class of the errors torchrod raises for input it cannot use."""


class ReadingError(TorchrodError, ValueError):
    """A reading (curvature, strain, wavelengths, a line of a file) cannot be used: wrong shape, not a number,
    beyond a physical bound, an unknown column."""


class RodError(TorchrodError, ValueError):
    """A rod description cannot be used: a missing or implausible value (units other than SI, say), gratings
    outside the rod, a fibre that cannot give curvature."""


class CheckpointError(TorchrodError, ValueError):
    """A warm-start checkpoint cannot be used: damaged, not a checkpoint, an invalid network config, or a network
    trained for another grating layout."""


class OptionsError(TorchrodError, ValueError):
    """An option is out of its range or does not fit the other options."""


class TorchrodTypeError(TorchrodError, TypeError):
    """An argument of the wrong kind: a NumPy array where a tensor is needed, a dict where options are, an integer
    tensor of readings."""


class MissingFileError(TorchrodError, FileNotFoundError):
    """A file the caller named does not exist (a checkpoint, a rod file, an input)."""


class TorchrodWarning(UserWarning):
    """Base class of the warnings torchrod gives about input it can use, but not fully (the CLI prints them as one
    line each on stderr)."""


class RodWarning(TorchrodWarning):
    """A rod that works, but cannot determine everything a user may ask of it: forces where no grating can see
    them, gratings so close that they read the same curvature, a single grating (:attr:`torchrod.Rod.limitations`)."""


class ReadingWarning(TorchrodWarning):
    """Readings that can be used, but not as their file may mean: a CSV header without ``id`` or ``t`` whose other
    columns are ignored (a ``sample`` or ``time`` column that was meant as one of them)."""
