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
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
from typing import Any

import numpy as np

__all__ = ["available", "exact_rows", "load", "loaded", "march_rows"]


def load() -> bool:
    """Load the kernels now (compiled, or from Numba's cache) and run them once, where :func:`available`; returns
    whether they are loaded. For processes that will march many small batches: a stream, a worker, a loop over
    single readings."""
    if not available():
        return False
    march_rows(np.zeros(1), np.full((1, 1), 0.5), np.ones((1, 1), np.complex128), None, 1.0, 1.0,
               np.zeros((1, 1, 2)), np.zeros((1, 1, 2, 3)), None, 0.3, 4)  # fmt: skip
    return True


def loaded() -> bool:
    """Whether the kernels are loaded in this process (by :func:`load` or a large march)."""
    return _kernels_module() is not None


def available() -> bool:
    """Whether the compiled march runs here: Numba is installed and ``TORCHROD_NUMBA`` is not ``0``."""
    return os.environ.get("TORCHROD_NUMBA", "1") != "0" and _installed()


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
        (B,) bool: the rows marched. The others (a non-finite input, whose schedule NaN orders) are left to the
        caller, their outputs untouched.
    """
    kernel = _kernel()
    B, h = s.shape
    queries = query[None, :] if query.ndim == 1 else query
    F = 0 if jacobian is None else jacobian.shape[-1]
    marched = np.zeros(B, np.bool_)
    kernel(
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
        marched,
    )
    return marched


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
    from . import _kernels

    B, h = s.shape
    marched = np.zeros(B, np.bool_)
    _kernels.exact_rows(
        np.ascontiguousarray(query, np.float64),
        np.ascontiguousarray(s, np.float64),
        np.ascontiguousarray(magnitude, np.float64),
        np.ascontiguousarray(jump, np.complex128),
        float(length),
        float(step_angle),
        int(max_steps),
        *_tableau_arrays(tableau),
        curvature,
        marched,
    )
    return marched


@functools.cache
def _tableau_arrays(tableau: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """(c, a, bp, bv, fsal) of a tableau as the kernel takes them (a few tableaus exist: made once each)."""
    c, bp, bv = (np.asarray(x, np.float64) for x in (tableau.c, tableau.bp, tableau.bv))
    return c, tableau.matrix(), bp, bv, bool(tableau.fsal)


def _kernel() -> Any:
    from . import _kernels  # imports Numba: only where the compiled march runs

    return _kernels.batch


def _kernels_module() -> Any:
    return sys.modules.get(__name__.rpartition(".")[0] + "._kernels")
