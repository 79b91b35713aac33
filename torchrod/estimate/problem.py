"""The least-squares problem of force estimation, defined once: readings, unknowns, intervals, residuals, kinks.

For B readings of a rod with G gratings, a *fit* of h forces to reading b minimises

    loss = sum over present gratings k of |u_model(s_k) - u_measured,k|^2        [1/m^2]

over the forces' locations s_i [m] and body-frame components f_i = (f_x, f_y) [N]. Everything here is a pure
function of frozen data, on either backend (:mod:`torchrod.backend`); the solvers (:mod:`.lm`, :mod:`.lbfgs`) and
the search (:mod:`.search`) build on it.

Intervals. Grating k sees a force only while the force lies distal to it, so the residual is smooth in s_i between
two neighbouring *present* gratings and has a kink where s_i crosses one: dU_k/ds_i is 0 on the proximal side and
the slope jump J_i = i (f_x + i f_y) / EI on the distal side. Each force therefore carries the index of its
interval, [p_j, p_j+1] between the reading's present gratings p_1 < ... < p_m (the last one [p_m, L]), and stays in
it while a solver moves it: inside an interval every derivative exists, and a force on a bound has the one-sided
derivative of its own interval (the distal one at its lower bound, the proximal one at its upper bound). Moving
across a grating is a decision of the solver (:func:`.lm.analyse`), taken from the one-sided slopes
(:func:`kink_slopes`). No interval is proximal to p_1: a force there bends no present grating.

Units. Solvers work in scaled unknowns x = (s / L, f / F) with F = EI / L^2, the scales at which the curvature is of
order 1/L; :func:`evaluate` returns the Jacobian in those units. Locations stay in metres in :class:`Fits`, so a
force on a bound sits exactly on the grating's position.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from ..backend import Backend
from ..model.sensitivity import march, march_propagator

__all__ = [
    "Fits",
    "Problem",
    "evaluate",
    "exact_residual",
    "interval_of",
    "kink_sides",
    "kink_slopes",
    "near_bounds",
    "near_kink",
    "make_problem",
    "sided",
    "sigma2",
]


@dataclass(frozen=True)
class Problem:
    """B readings of one rod, ready to fit (backend arrays).

    Attributes:
        xp: the backend.
        length: L [m]; stiffness: EI [N m^2].
        query: (G,) grating positions [m].
        u: (B, 2G) measured (u_x, u_y) per grating, flattened, zero at missing gratings [1/m].
        weight: (B, 2G) 1.0 at present gratings' residuals, 0.0 at missing ones.
        residuals: (B,) n = 2 x present gratings.
        lo, hi: (B, G) interval bounds [m] (intervals j < ``intervals``; the rest padded with L).
        lo_k, hi_k: (B, G) grating index at each bound (hi_k = -1 at the tip, lo_k = -1 for padding).
        intervals: (B,) number m of intervals (present gratings below L).
        noise2: (B,) the noise variance the stopping rule and the tests use (the given sigma^2 plus the floor^2)
            [1/m^2], or None: estimated per fit from its loss (:func:`sigma2`).
        floor2: the noise floor^2 [1/m^2] (the forward model's accuracy).
        step_angle, max_steps: the fitting model's accuracy (:mod:`torchrod.model.sensitivity`).
        precurved: None for a straight rod; for a precurved one, its :class:`torchrod.model.precurved.Precurved`,
            whose march (:mod:`torchrod.model.precurved`) is then the forward model of every fit.
    """

    xp: Backend
    length: float
    stiffness: float
    query: Any
    u: Any
    weight: Any
    residuals: Any
    lo: Any
    hi: Any
    lo_k: Any
    hi_k: Any
    intervals: Any
    noise2: Any
    floor2: float
    step_angle: float
    max_steps: int
    precurved: Any = None

    @property
    def force_unit(self) -> float:
        """F = EI / L^2 [N]."""
        return self.stiffness / (self.length * self.length)

    @property
    def batch_size(self) -> int:
        return self.u.shape[0]


def per_problem(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn(problem, *args)`` kept for the last problem it was called with (by identity: a :class:`Problem` is
    frozen and its arrays are never written), one result per ``args``: a search calls such functions of one
    problem many times per reading. The problem and its results are held until another problem comes."""
    last: list[tuple[Any, dict]] = [(None, {})]

    @functools.wraps(fn)
    def cached(problem: Problem, *args: Any) -> Any:
        held, memo = last[0]  # one read: the memo is always this problem's, whatever other threads do
        if held is not problem:
            memo = {}
            last[0] = (problem, memo)
        if args not in memo:
            memo[args] = fn(problem, *args)
        return memo[args]

    return cached


def make_problem(
    xp: Backend,
    length: float,
    stiffness: float,
    gratings: Any,
    curvature: Any,
    present: Any,
    *,
    noise2: Any,
    floor2: float,
    step_angle: float,
    max_steps: int,
    precurved: Any = None,
) -> Problem:
    """:class:`Problem` from (B, G, 2) curvature (anything finite at missing gratings) and (B, G) ``present``."""
    B, G = present.shape
    q = xp.asarray(gratings)
    w = xp.astype(present, "float")
    u = (curvature * w[:, :, None]).reshape(B, 2 * G)
    weight = xp.expand(w[:, :, None], (B, G, 2)).reshape(B, 2 * G)
    # Present gratings first, in order: the lower bounds of the intervals.
    ar = xp.arange(G)
    key = xp.where(present, xp.astype(ar, "float"), xp.astype(ar, "float") + G)
    k_sorted = xp.argsort_desc(-key)  # ascending key
    m = xp.astype(present, "int").sum(1)  # (B,)
    slot = xp.arange(G)[None, :] < m[:, None]
    lo = xp.where(slot, q[k_sorted], float(length))
    lo_k = xp.where(slot, k_sorted, -1)
    hi = xp.concat([lo[:, 1:], lo[:, :1] * 0.0 + float(length)], 1)
    hi_k = xp.concat([lo_k[:, 1:], lo_k[:, :1] * 0 - 1], 1)
    # A grating at the tip (p_m = L) closes no interval: drop the empty last interval.
    m = xp.astype(slot & (hi > lo), "int").sum(1)
    return Problem(
        xp=xp,
        length=float(length),
        stiffness=float(stiffness),
        query=q,
        u=u,
        weight=weight,
        residuals=2 * xp.astype(present, "int").sum(1),
        lo=lo,
        hi=hi,
        lo_k=lo_k,
        hi_k=hi_k,
        intervals=m,
        noise2=noise2,
        floor2=float(floor2),
        step_angle=float(step_angle),
        max_steps=int(max_steps),
        precurved=precurved,
    )


@dataclass(frozen=True)
class Fits:
    """R fits of h forces each (backend arrays): row r fits reading ``reading[r]``.

    Attributes:
        reading: (R,) reading index.
        s: (R, h) locations [m] (model coordinates), each inside its interval.
        f: (R, h, 2) body-frame (f_x, f_y) [N].
        interval: (R, h) interval index of each force (:class:`Problem`).
    """

    reading: Any
    s: Any
    f: Any
    interval: Any

    @property
    def rows(self) -> int:
        return self.s.shape[0]

    @property
    def h(self) -> int:
        return self.s.shape[1]

    def take(self, idx: Any) -> Fits:
        return Fits(self.reading[idx], self.s[idx], self.f[idx], self.interval[idx])


def bounds(problem: Problem, fits: Fits) -> tuple[Any, Any]:
    """(R, h) lower and upper bound [m] of each force's interval."""
    rows = fits.reading[:, None]
    return problem.lo[rows, fits.interval], problem.hi[rows, fits.interval]


def interval_of(problem: Problem, reading: Any, s: Any) -> tuple[Any, Any]:
    """The interval of each location s (R, h) [m] of readings ``reading`` (R,), and s moved into it: a location
    proximal to the first present grating goes to that grating (the first interval's lower bound)."""
    xp = problem.xp
    lo = problem.lo[reading]  # (R, G)
    m = problem.intervals[reading]
    valid = xp.arange(lo.shape[1])[None, :] < m[:, None]
    j = xp.astype((valid[:, None, :] & (lo[:, None, :] <= s[:, :, None])), "int").sum(2) - 1
    j = xp.clip(j, lo=0)
    j = xp.where(j < m[:, None], j, m[:, None] - 1)
    fits_lo = problem.lo[reading[:, None], j]
    fits_hi = problem.hi[reading[:, None], j]
    return j, xp.clip(s, fits_lo, fits_hi)


def march_fits(
    problem: Problem, query: Any, s: Any, f: Any, *, jacobian: bool, seeds: bool = False
) -> tuple[Any, Any, Any]:
    """The fitting model's march of R force sets (s (R, h) [m], f (R, h, 2) [N]) at ``query`` (Q,) or (R, Q), on the
    problem's rod (straight: :mod:`torchrod.model.sensitivity`; precurved: :mod:`torchrod.model.precurved` at
    ``FIT_MAX_STEP``): curvature (R, Q, 2) [1/m], its Jacobian (R, Q, 2, h, 3) or None, and with ``seeds`` the
    propagator of the linearised equations from the tip (straight (R, Q, 4, 4), precurved (R, Q, 6, 6)), else None."""
    xp = problem.xp
    if problem.precurved is not None:
        from ..model.precurved import FIT_MAX_STEP
        from ..model.precurved import march as march_precurved

        u3, _, jac, phi = march_precurved(
            xp, query, s, f, problem.precurved, max_step=FIT_MAX_STEP, jacobian=jacobian, seeds=seeds
        )
        return u3[..., :2], jac, phi
    options = dict(jacobian=jacobian, step_angle=problem.step_angle, max_steps=problem.max_steps)
    if seeds:
        return march_propagator(xp, query, s, f, problem.length, problem.stiffness, **options)
    u, jac = march(xp, query, s, f, problem.length, problem.stiffness, **options)
    return u, jac, None


def evaluate(problem: Problem, fits: Fits, jacobian: bool = True) -> tuple[Any, Any]:
    """Residuals r (R, 2G) [1/m] (zero at missing gratings) and their Jacobian (R, 2G, 3h) w.r.t. the scaled
    unknowns (s / L, f / F) of each force, in the march's convention at ties (distal one-sided; see
    :func:`sided`); None for the Jacobian with ``jacobian=False``."""
    R, h = fits.s.shape
    G = problem.query.shape[0]
    u, jac, _ = march_fits(problem, problem.query, fits.s, fits.f, jacobian=jacobian)
    w = problem.weight[fits.reading]
    r = (u.reshape(R, 2 * G) - problem.u[fits.reading]) * w
    if not jacobian:
        return r, None
    L, F = problem.length, problem.force_unit
    jac[..., 0] *= L
    jac[..., 1:] *= F
    J = jac.reshape(R, 2 * G, 3 * h) * w[:, :, None]
    return r, J


def exact_residual(problem: Problem, fits: Fits) -> Any:
    """Residuals (R, 2G) [1/m] from the simulator's model (:func:`torchrod.model.body_frame.integrate_curvature`:
    8th-order, rigorous step bound, ~1e-9 accurate; for a precurved rod :mod:`torchrod.model.precurved` at
    ``EXACT_MAX_STEP``, ~3e-9) instead of the fitting model (relative accuracy ~1e-4 of the curvature, ~4e-5
    precurved): the final Gauss-Newton steps of a fit and its reported loss use it, so that the count tests and the
    verdict see the physics, not the fitting model's discretisation."""
    from ..model.body_frame import march_curvature

    xp = problem.xp
    R, h = fits.s.shape
    G = problem.query.shape[0]
    if problem.precurved is not None:
        from ..model.precurved import EXACT_MAX_STEP
        from ..model.precurved import march as march_precurved

        u = march_precurved(xp, problem.query, fits.s, fits.f, problem.precurved, max_step=EXACT_MAX_STEP)[0][..., :2]
    elif h == 0:  # no force: the rod is straight
        return -problem.u[fits.reading] * problem.weight[fits.reading]
    else:
        u = march_curvature(xp, problem.query, fits.s, fits.f, problem.length, problem.stiffness)
    w = problem.weight[fits.reading]
    return (u.reshape(R, 2 * G) - problem.u[fits.reading]) * w


def _jump_column(problem: Problem, fits: Fits) -> Any:
    """(R, h, 2) the distal one-sided dU_k/d(s/L) of a grating at a force's location: the slope jump times L."""
    xp = problem.xp
    scale = problem.length / problem.stiffness
    return xp.stack([-fits.f[..., 1] * scale, fits.f[..., 0] * scale], 2)


def sided(problem: Problem, fits: Fits, J: Any, hi: Any = None) -> Any:
    """The Jacobian with each force's own one-sided derivative at a bound of its interval. A force on its upper
    bound (the grating that closes its interval distally) lies proximal to that grating, which does not see it
    move: the s-entries of that grating's residuals are zero (the march gives the distal value there). ``hi``:
    the upper bounds of :func:`bounds`, if the caller has them."""
    xp = problem.xp
    R, h = fits.s.shape
    G = problem.query.shape[0]
    if hi is None:
        _, hi = bounds(problem, fits)
    hi_k = problem.hi_k[fits.reading[:, None], fits.interval]  # (R, h)
    on_hi = (fits.s == hi) & (hi_k >= 0)  # (R, h)
    if not bool(xp.any(on_hi)):
        return J
    hit = on_hi[:, None, :] & (xp.arange(G)[None, :, None] == hi_k[:, None, :])  # (R, G, h)
    Jv = J.reshape(R, G, 2, h, 3)
    s_col = xp.where(hit[:, :, None, :], 0.0, Jv[..., 0])
    return xp.concat([s_col[..., None], Jv[..., 1:]], 4).reshape(R, 2 * G, 3 * h)


KINK = 1e-6
"""[m] a force this close to a present grating sits on the loss's kink there (:func:`kink_sides`)."""


def near_kink(problem: Problem, fits: Fits) -> Any:
    """(R,) bool: a force of the fit lies within :data:`KINK` of a present grating (on the loss's kink there)."""
    xp = problem.xp
    R = fits.rows
    G = problem.query.shape[0]
    present = problem.weight[fits.reading].reshape(R, G, 2)[..., 0] > 0
    near = abs(fits.s[:, None, :] - problem.query[None, :, None]) <= KINK
    return xp.any((near & present[:, :, None]).reshape(R, -1), 1)


def kink_sides(problem: Problem, fits: Fits, J: Any) -> tuple[Any, Any]:
    """The Jacobian of a fit with, for every force within :data:`KINK` of a present grating, that grating's
    s-entries from the proximal side (zero) and from the distal side (the slope jump): (J_proximal, J_distal),
    each (R, 2G, 3h). A force on a kink is described equally well from either side; its uncertainty is the worse
    of the two."""
    xp = problem.xp
    R, h = fits.s.shape
    G = problem.query.shape[0]
    present = problem.weight[fits.reading].reshape(R, G, 2)[..., 0] > 0  # (R, G)
    near = (abs(fits.s[:, None, :] - problem.query[None, :, None]) <= KINK) & present[:, :, None]  # (R, G, h)
    Jv = J.reshape(R, G, 2, h, 3)
    jc = _jump_column(problem, fits)  # (R, h, 2)
    sel = near[:, :, None, :]
    col = Jv[..., 0]  # (R, G, 2, h)
    prox = xp.where(sel, 0.0, col)
    dist = xp.where(sel, xp.expand(xp.mT(jc)[:, None], (R, G, 2, h)), col)
    out = []
    for c in (prox, dist):
        out.append(xp.concat([c[..., None], Jv[..., 1:]], 4).reshape(R, 2 * G, 3 * h))
    return out[0], out[1]


SNAP = 1e-3
"""A force within this fraction of its interval's length from a bound counts as on that bound for the decision to
cross the grating there (:func:`near_bounds`): an interval's own optimum a few micrometres from the grating, with
the loss falling on the far side, must not hide the better interval next to it."""


def near_bounds(problem: Problem, fits: Fits, lo_hi: tuple[Any, Any] | None = None) -> tuple[Any, Any]:
    """(R, h) bool each: a force within :data:`SNAP` of its interval's lower / upper bound (or on it). ``lo_hi``:
    :func:`bounds`, if the caller has them."""
    lo, hi = bounds(problem, fits) if lo_hi is None else lo_hi
    tol = SNAP * (hi - lo)
    return fits.s - lo <= tol, hi - fits.s <= tol


def kink_slopes(problem: Problem, fits: Fits, r: Any, lo_hi: tuple[Any, Any] | None = None) -> tuple[Any, Any]:
    """(R, h) each: the contribution to d(loss/2)/d(s/L) of the grating at a force's lower bound (its distal
    one-sided term, zero unless the force is near that bound, :func:`near_bounds`) and of the grating at its upper
    bound (the term it would gain by crossing it, zero unless near it). With g the sided gradient, the slope just
    proximal to a force on its lower bound is g - the first, just distal to a force on its upper bound g + the
    second. ``lo_hi``: :func:`bounds`, if the caller has them."""
    xp = problem.xp
    R, h = fits.s.shape
    G = problem.query.shape[0]
    near_lo, near_hi = near_bounds(problem, fits, lo_hi)
    rows = fits.reading[:, None]
    lo_k = problem.lo_k[rows, fits.interval]
    hi_k = problem.hi_k[rows, fits.interval]
    jc = _jump_column(problem, fits)  # (R, h, 2)
    rr = r.reshape(R, G, 2)

    row = xp.arange(R)[:, None]

    def at(k):
        return rr[row, xp.clip(k, lo=0)]  # (R, h, 2)

    c_lo = xp.where(near_lo & (lo_k >= 0), (at(lo_k) * jc).sum(2), 0.0)
    c_hi = xp.where(near_hi & (hi_k >= 0), (at(hi_k) * jc).sum(2), 0.0)
    return c_lo, c_hi


def sigma2(problem: Problem, fits: Fits, loss: Any) -> Any:
    """(R,) the noise variance a fit is measured against [1/m^2]: the given one, or (noise unknown) the fit's own
    loss per degree of freedom, at least the floor^2."""
    xp = problem.xp
    if problem.noise2 is not None:
        return problem.noise2[fits.reading]
    dof = xp.clip(xp.astype(problem.residuals[fits.reading] - 3 * fits.h, "float"), lo=1.0)
    return xp.clip(loss / dof, lo=problem.floor2)


def with_forces(fits: Fits, s: Any, f: Any, interval: Any | None = None) -> Fits:
    """``fits`` with new locations and forces (and intervals)."""
    return replace(fits, s=s, f=f, interval=fits.interval if interval is None else interval)
