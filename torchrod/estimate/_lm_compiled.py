"""The Levenberg-Marquardt solve of :mod:`.lm` with its step compiled (Numba), for straight rods on the NumPy backend:
the loop, the deadline and ``stop`` stay in Python; each step of every open row, and the start, run in
:mod:`._lm_kernels`, which write :func:`.lm._step` and :func:`.lm.analyse` row by row. So do the scan's models of one
more force (:func:`scan`), the exact model's finish (:func:`finish_counted`) and the fits' Gauss-Newton covariance
(:func:`covariance`, for :mod:`.uncertainty`).

The kernels restate the array code's operations row by row; its numbers (the :class:`.lm.LMPolicy` passed in,
``lm.FLOOR``, ``lm.TINY``, ``lm.SCALE_MIN``, ``problem.SNAP``, the covariance's cut-offs) are passed to them. Tests hold
the two to the same states step for step, and the estimator to the same answers (tests/test_lm_compiled.py). They agree
to rounding, not bit for bit: the array code's sums and solves run in NumPy's and LAPACK's order. Where the kernels
cannot run here (an incompatible Numba), one warning says so and every solve runs the array code, as
:mod:`torchrod.model.compiled` does for the marches."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from ..model import compiled
from ..model.sensitivity import SCALAR_WORK, march_work
from . import problem as _problem
from .problem import Fits, Problem

__all__ = ["covariance", "finish_counted", "scan", "solve", "start", "step", "usable"]


class _Failed(Exception):
    """A row whose march input was not finite: the caller solves in Python instead."""


_broken: str | None = None  # why the kernels could not run here, once they could not

STEPS_PER_CHECK = 8
"""The compiled solve runs its rounds of steps (one step of every open row each, as :func:`.lm.solve`) without
returning to Python while their row steps stay within this many (at least one round): a solve of a few rows pays
the loop's Python costs once per several steps, and looks at its deadline after this many row steps at most, or
after one round where more rows are open. A ``stop``, when given, is looked at after every round."""


def usable(problem: Problem, rows: int, h: int) -> bool:
    """Whether :func:`solve` runs for a solve of ``rows`` fits of ``h`` forces of ``problem``: a straight rod on
    the NumPy backend, where the compiled marches run (:func:`torchrod.model.compiled.takes`, with the loading
    policy of the marches: the kernels once loaded, or for a solve whose marches would load them)."""
    if problem.xp.name != "numpy" or problem.precurved is not None or _broken is not None:
        return False
    return compiled.takes(march_work(rows, 3 * h) > SCALAR_WORK)


@_problem.per_problem
def _problem_args(problem: Problem) -> tuple:
    """The kernels' view of ``problem`` (kept: the search calls the kernels a dozen times per reading)."""
    noise2 = np.zeros(0) if problem.noise2 is None else np.ascontiguousarray(problem.noise2, np.float64)
    return (
        np.ascontiguousarray(problem.query, np.float64),
        np.ascontiguousarray(problem.u, np.float64),
        np.ascontiguousarray(problem.weight, np.float64),
        np.ascontiguousarray(problem.lo, np.float64),
        np.ascontiguousarray(problem.hi, np.float64),
        np.ascontiguousarray(problem.lo_k, np.int64),
        np.ascontiguousarray(problem.hi_k, np.int64),
        np.ascontiguousarray(problem.intervals, np.int64),
        noise2,
        np.ascontiguousarray(problem.residuals, np.int64),
        float(problem.floor2),
        float(problem.length),
        float(problem.stiffness),
        float(problem.force_unit),
        float(problem.step_angle),
        int(problem.max_steps),
        float(_problem.SNAP),
    )


@functools.cache
def _policy_args(policy: Any) -> tuple:
    from .lm import FLOOR, SCALE_MIN, TINY

    acceleration = -math.inf if policy.acceleration is None else float(policy.acceleration)
    return (
        float(policy.tolerance),
        int(policy.iterations),
        float(policy.max_damping),
        float(policy.increase),
        float(policy.decrease),
        float(policy.min_damping),
        float(policy.max_force_step),
        acceleration,
        float(policy.probe),
        float(policy.acceleration_limit),
        FLOOR,
        TINY,
        SCALE_MIN,
    )


_FIELDS = ("r", "J", "loss", "damping", "steps", "held", "A", "g", "proposal", "ratio", "decrement", "noise2",
           "converged", "done")  # fmt: skip
_DTYPES = {"steps": np.int64, "held": np.bool_, "converged": np.bool_, "done": np.bool_}


def _arrays(state: Any) -> tuple:
    """The kernels' state tuple: fresh C-contiguous copies (the caller's state is never changed). A state not
    analysed (no proposal) is left to the array code."""
    if state.A is None or state.g is None or state.proposal is None:
        raise _Failed
    fits = state.fits
    out = [
        np.array(fits.reading, np.int64),
        np.array(fits.s, np.float64),
        np.array(fits.f, np.float64),
        np.array(fits.interval, np.int64),
    ]
    out += [np.array(getattr(state, k), _DTYPES.get(k, np.float64)) for k in _FIELDS]
    out.append(np.zeros(fits.rows, np.bool_))  # failed
    return tuple(out)


def _state(S: tuple) -> Any:
    from .lm import LMState

    return LMState(Fits(S[0], S[1], S[2], S[3]), **dict(zip(_FIELDS, S[4:18], strict=True)))


def _start(problem: Problem, policy: Any, fits: Fits, P_: tuple, O_: tuple) -> tuple:
    R, h = fits.s.shape
    n = problem.u.shape[1]
    S = (
        np.array(fits.reading, np.int64),
        np.array(fits.s, np.float64),
        np.array(fits.f, np.float64),
        np.array(fits.interval, np.int64),
        np.zeros((R, n)),
        np.zeros((R, n, 3 * h)),
        np.zeros(R),
        np.full(R, float(policy.damping)),
        np.zeros(R, np.int64),
        np.zeros((R, h), np.bool_),
        np.zeros((R, 3 * h, 3 * h)),
        np.zeros((R, 3 * h)),
        np.zeros((R, 3 * h)),
        np.ones(R),
        np.zeros(R),
        np.zeros(R),
        np.zeros(R, np.bool_),
        np.zeros(R, np.bool_),
        np.zeros(R, np.bool_),
    )
    _kernel("start_rows", P_, S, O_)
    if S[18].any():
        raise _Failed
    return S


def solve(problem: Problem, policy: Any, fits: Any, late: Any, stop: Any) -> Any:
    """:func:`.lm.solve` with compiled steps (``late()``: whether its deadline has passed); None where it cannot
    run (no force, a march input not finite, or the kernels failed to load): the caller then solves in Python."""
    if (fits.h if isinstance(fits, Fits) else fits.fits.h) == 0:
        return None
    P_, O_ = _problem_args(problem), _policy_args(policy)
    try:
        S = _start(problem, policy, fits, P_, O_) if isinstance(fits, Fits) else _arrays(fits)
        done = S[17]
        if stop is not None:
            done |= np.asarray(stop(_state(S)), np.bool_)
        while True:
            if done.all() or late():
                return _state(S)
            _kernel("steps_rows", P_, S, O_, 0 if stop is not None else STEPS_PER_CHECK)
            if S[18].any():
                raise _Failed
            if stop is not None:
                done |= np.asarray(stop(_state(S)), np.bool_)
    except _Failed:
        return None


def _kernel(name: str, *args: Any) -> None:
    """Run kernel ``name`` of :mod:`._lm_kernels`; where it cannot be imported or compiled here, warn once, stop
    using the kernels (:func:`usable` False from then on) and raise :class:`_Failed`."""
    global _broken
    _broken = compiled.call(__name__.rpartition(".")[0] + "._lm_kernels", name, args, "search steps", "solving")
    if _broken is not None:
        raise _Failed


def start(problem: Problem, policy: Any, fits: Fits) -> Any:
    """:func:`.lm.start` compiled (None where it cannot run)."""
    try:
        return _state(_start(problem, policy, fits, _problem_args(problem), _policy_args(policy)))
    except _Failed:
        return None


def step(problem: Problem, policy: Any, state: Any) -> Any:
    """:func:`.lm._step` of every row of ``state`` compiled (None where it cannot run)."""
    try:
        S = _arrays(state)
        _kernel("step_rows", np.arange(state.fits.rows), _problem_args(problem), S, _policy_args(policy))
    except _Failed:
        return None
    return None if S[18].any() else _state(S)


def finish_counted(problem: Problem, policy: Any, state: Any) -> Any:
    """:func:`.lm.finish_counted` compiled: (the finished state, (R,) evaluations), or None where it cannot run
    (no force, a state not analysed, a march input not finite)."""
    if state.fits.h == 0:
        return None
    exact = _exact_args(policy)
    used = np.zeros(state.fits.rows, np.int64)
    try:
        S = _arrays(state)
        _kernel("finish_rows", _problem_args(problem), S, _policy_args(policy), exact, used)
    except _Failed:
        return None
    if S[18].any():
        return None
    fits = Fits(state.fits.reading, S[1], S[2], state.fits.interval)
    return state.replace(fits=fits, r=S[4], loss=S[6]), used


@functools.cache
def _exact_args(policy: Any) -> tuple:
    """The exact march's settings as :func:`finish_counted`'s kernel takes them."""
    from ..model import body_frame
    from ..model.compiled import _tableau_arrays

    return (
        int(policy.exact_steps),
        float(policy.exact_tolerance),
        float(body_frame.DEFAULT_STEP_ANGLE),
        int(body_frame.DEFAULT_MAX_STEPS),
        _tableau_arrays(body_frame._method(None, "exact")),
    )


def scan(problem: Problem, base: Fits, cand: Any, known: tuple[Any, Any] | None) -> Any:
    """:func:`.search._responses` and :func:`.search._added_force` compiled for ``base`` (R0 fits) and candidates
    ``cand`` (R0, C) [m] (``known``: the base's residuals and sided Jacobian): r (R0, n), J (R0, n, 3h), the
    decrements (R0, C) and the pieces of the steps (:func:`.search._steps`); None where it cannot run (a march input
    not finite, a singular propagator)."""
    from .lm import FLOOR, SCALE_MIN, TINY

    R0, h = base.s.shape
    C = cand.shape[1]
    n, Pb = problem.u.shape[1], 3 * h
    r, J = np.zeros((R0, n)), np.zeros((R0, n, Pb))
    if known is not None:
        r[:], J[:] = known
    dec, xc, ok = np.empty((R0, C)), np.empty((R0, C, 2)), np.empty(R0, np.bool_)
    yb, Y = np.zeros((R0, Pb)), np.zeros((R0, C, 2, Pb))
    failed = np.zeros(1, np.bool_)
    fits = (
        np.ascontiguousarray(base.reading, np.int64),
        np.ascontiguousarray(base.s, np.float64),
        np.ascontiguousarray(base.f, np.float64),
        np.ascontiguousarray(base.interval, np.int64),
    )
    cand = np.ascontiguousarray(cand, np.float64)
    try:
        _kernel("scan_rows", _problem_args(problem), fits, known is not None, cand, TINY, FLOOR, SCALE_MIN, r, J,
                dec, xc, yb, Y, ok, failed)  # fmt: skip
    except _Failed:
        return None
    if failed[0]:
        return None
    return r, J, dec, xc, yb, Y  # dec: -inf where the base block failed (ok False)


def covariance(J: np.ndarray, sigma: np.ndarray, active: np.ndarray, diag_min: float, eps: float) -> Any:
    """:func:`.uncertainty.gauss_newton_covariance` compiled: (covariance (B, P, P), condition (B,)); None where it
    cannot run (the kernels failed to load)."""
    if _broken is not None:
        return None
    B, _, P = J.shape
    cov, condition = np.empty((B, P, P)), np.empty(B)
    try:
        _kernel("covariance_rows", np.ascontiguousarray(J, np.float64), np.ascontiguousarray(sigma, np.float64),
                np.ascontiguousarray(active, np.bool_), diag_min, eps, cov, condition)  # fmt: skip
    except _Failed:
        return None
    return cov, condition
