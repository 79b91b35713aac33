"""The one-row marches compiled with Numba, when Numba is installed: the estimator's tangent march
(:mod:`torchrod.model.sensitivity`) and its exact model's march (:func:`torchrod.model.body_frame.march_curvature`).

The estimator marches a few rows at a time most of the time (one reading's fits, the last rows of a batch still
stepping), where arrays cost a fixed overhead per operation and the Python-number marches
(:func:`torchrod.model.sensitivity._row`, :func:`torchrod.model.nystrom._forward_generic`) cost the interpreter's
time per number. This module runs those marches, on the same schedule (:func:`torchrod.model.schedule.row`, rules
``"estimate"`` and ``"bound"``, unloaded events skipped), in the same order of floating-point operations,
compiled: tests hold them to the Python-number marches bit for bit (tests/test_sensitivity.py). They are a backend
of those schemes, not second schemes: the RKN coefficients (the exact model's from its tableau), the step rules and
the tie-breaks are the ones those modules define.

Numba is optional (``pip install torchrod[fast]``): without it, or with the environment variable
``TORCHROD_NUMBA=0``, :func:`available` is False and the marches run as before. Loading the kernels costs a
process about half a second (Numba's import and its on-disk cache, next to this file where that is writable;
the first load after an install compiles them, a few seconds), more than a one-shot command on a few readings
spends marching. So they load (:func:`load`) when a march too large for the Python numbers comes (on the NumPy
backend such marches always take them), or when a long-running process asks: a stream's warm-up and the worker
processes do. Until then the small marches run on the Python numbers, which give the same numbers bit for bit,
so an answer does not depend on whether they had loaded.

Where they run, the estimator's Levenberg-Marquardt steps run compiled too (:mod:`torchrod.estimate._lm_compiled`,
kernels in ``torchrod/estimate/_lm_kernels.py``, on this module's loading policy). Those agree with the array code
to rounding rather than bit for bit, so a small one-shot estimate (kernels not loaded) and the same reading in a
stream can differ in the last digits of the fit.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
import warnings
from typing import Any

import numpy as np

__all__ = ["available", "call", "exact_rows", "load", "loaded", "march_rows", "takes"]


def load() -> bool:
    """Load the kernels now (compiled, or from Numba's cache) and run them once, where :func:`available`; returns
    whether they are loaded. For processes that will march many small batches: a stream, a worker, a loop over
    single readings."""
    if not available():
        return False
    from .nystrom import RKN4

    one, jump = np.full((1, 1), 0.5), np.ones((1, 1), np.complex128)
    march_rows(np.zeros(1), one, jump, None, 1.0, 1.0, np.zeros((1, 1, 2)), np.zeros((1, 1, 2, 3)), None, 0.3, 4)
    exact_rows(np.zeros(1), one, one, jump, 1.0, 0.3, 4, RKN4, np.zeros((1, 1, 2)))
    return available()  # False where the kernels failed to load


def loaded() -> bool:
    """Whether the kernels are loaded in this process (by :func:`load` or a large march)."""
    return _kernels_module() is not None


def available() -> bool:
    """Whether the compiled march runs here: Numba is installed, ``TORCHROD_NUMBA`` is not ``0``, and the kernels
    have not failed to load (an incompatible Numba: then a warning says why, once, and the marches run as without
    Numba)."""
    return os.environ.get("TORCHROD_NUMBA", "1") != "0" and _failure is None and _installed()


_failure: str | None = None  # why the kernels could not load, once they could not


def takes(large: bool) -> bool:
    """Whether a NumPy march runs compiled: where :func:`available`, once the kernels are loaded, or for a march
    too ``large`` for the Python numbers (which loads them). The one loading policy of both marches."""
    return available() and (large or loaded())


def _run(name: str, rows: int, *args: Any) -> np.ndarray:
    """Call kernel ``name`` of :mod:`._kernels` on a batch of ``rows`` rows, with ``args`` and then the (rows,)
    bool array it marks the rows it marched in; returned. None marched (with a warning, and :func:`available`
    False from then on) where the kernels cannot be imported or compiled here."""
    global _failure
    marched = np.zeros(rows, np.bool_)
    if _failure is None:
        _failure = call(__name__.rpartition(".")[0] + "._kernels", name, (*args, marched), "marches", "marching")
    return marched


def call(module: str, name: str, args: tuple, what: str, doing: str) -> str | None:
    """Call kernel ``name`` of ``module`` with ``args``; where it cannot be imported or compiled here (whatever an
    incompatible Numba raises), warn (``what``: the kernels, ``doing``: what goes on without them) and return why
    (None: it ran). The callers stop using their kernels from then on."""
    try:
        getattr(importlib.import_module(module), name)(*args)
    except Exception as exc:  # noqa: BLE001 - whatever an incompatible Numba raises, the work goes on without it
        why = f"{type(exc).__name__}: {exc}"
        warnings.warn(
            f"torchrod: the compiled {what} could not run ({why}); {doing} without them "
            "(set TORCHROD_NUMBA=0 to skip them)",
            RuntimeWarning,
            stacklevel=4,
        )
        return why
    return None


@functools.cache
def _installed() -> bool:
    return importlib.util.find_spec("numba") is not None


def march_rows(
    query: np.ndarray,
    s: np.ndarray,
    jump: np.ndarray,
    active: np.ndarray | None,
    length: float,
    ei: float,
    curvature: np.ndarray,
    jacobian: np.ndarray | None,
    propagator: np.ndarray | None,
    step_angle: float,
    max_steps: int,
) -> np.ndarray:
    """The one-row march of every row of a batch whose inputs are finite, compiled, into the given outputs.

    Args:
        query: (Q,) or per row (B, Q) positions [m]; s: (B, h) force locations [m]; jump: (B, h) complex slope
            jumps i (f_x + i f_y) / EI [1/m^2], zero for padding; active: (B, h) bool, False for padded forces
            (None: all real). length: L [m]; ei: EI [N m^2].
        curvature: (B, Q, 2) out [1/m]; jacobian: (B, Q, 2, F) out, F = 3 h (None: no Jacobian); propagator:
            (B, Q, 4, 4) out (None: no seeds); their layouts are :func:`torchrod.model.sensitivity._march_rows`'s.
    Returns:
        (B,) bool: the rows marched. The others (a non-finite input, whose schedule NaN orders; every row where the
        kernels cannot run) are left to the caller, their outputs untouched.
    """
    B, h = s.shape
    queries = query[None, :] if query.ndim == 1 else query
    F = 0 if jacobian is None else jacobian.shape[-1]
    return _run(
        "batch",
        B,
        np.ascontiguousarray(queries, np.float64),
        np.ascontiguousarray(s, np.float64),
        np.ascontiguousarray(jump, np.complex128),
        np.ones((B, h), np.bool_) if active is None else np.ascontiguousarray(active, np.bool_),
        float(length),
        float(ei),
        curvature,
        np.empty((B, queries.shape[1], 2, 0)) if jacobian is None else jacobian,
        np.empty((1, 1, 4, 4)) if propagator is None else propagator,
        F,
        propagator is not None,
        float(step_angle),
        int(max_steps),
    )


def exact_rows(
    query: np.ndarray,
    s: np.ndarray,
    magnitude: np.ndarray,
    jump: np.ndarray,
    length: float,
    step_angle: float,
    max_steps: int,
    tableau: Any,
    curvature: np.ndarray,
) -> np.ndarray:
    """The exact model's one-row march (:func:`torchrod.model.body_frame.march_curvature`) of every row whose
    inputs are finite, compiled, into ``curvature``.

    Args:
        query: (Q,) positions [m]; s: (B, h) force locations [m]; magnitude: (B, h) |f| / EI [1/m^2] (the
            ``"bound"`` step rule's); jump: (B, h) complex slope jumps [1/m^2]; length: L [m];
            tableau: the :class:`torchrod.model.nystrom.Tableau`; curvature: (B, Q, 2) out [1/m].
    Returns:
        (B,) bool: the rows marched (the others are left to the caller).
    """
    return _run(
        "exact_rows",
        s.shape[0],
        np.ascontiguousarray(query, np.float64),
        np.ascontiguousarray(s, np.float64),
        np.ascontiguousarray(magnitude, np.float64),
        np.ascontiguousarray(jump, np.complex128),
        float(length),
        float(step_angle),
        int(max_steps),
        *_tableau_arrays(tableau),
        curvature,
    )


@functools.cache
def _tableau_arrays(tableau: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """(c, a, bp, bv, fsal) of a tableau as the kernel takes them (a few tableaus exist: made once each)."""
    c, bp, bv = (np.asarray(x, np.float64) for x in (tableau.c, tableau.bp, tableau.bv))
    return c, tableau.matrix(), bp, bv, bool(tableau.fsal)


def _kernels_module() -> Any:
    return sys.modules.get(__name__.rpartition(".")[0] + "._kernels")
