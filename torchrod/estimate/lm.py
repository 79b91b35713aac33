"""The Levenberg-Marquardt policy, once: damping, trust region, bounds, grating crossings and the stopping rule.

Every fit of the estimator, on either backend (:mod:`torchrod.backend`), is solved by :func:`solve` with one
:class:`LMPolicy`; the state of a solve is explicit data (:class:`LMState`), passed in and returned.

One iteration, per row (a fit of h forces to one reading, :mod:`.problem`):

1. Analyse the current point (:func:`analyse`). A force on a bound of its interval whose loss would fall by
   leaving the interval is *held* there (its location is left out of the step), unless the loss also falls on the
   far side of the grating: then it *crosses*, taking the neighbouring interval (same location, the other
   one-sided derivative). A force held where the loss rises on both sides sits on a kink of the loss (a local
   minimum that smooth descent cannot leave; the search decides whether a better one exists elsewhere).
2. Stop when the Gauss-Newton decrement (the loss decrease a Gauss-Newton step promises, held locations fixed) is
   at most ``tolerance`` x sigma^2: what is left to gain is far below the noise (converged). Also stop after
   ``iterations`` steps or when the damping reaches its ceiling (a step that lowers the loss cannot be found).
3. Step: the damped Gauss-Newton step ``(A + lambda diag A) dx = -g`` (Marquardt's scaling, A = J^T J, g = J^T r,
   in the scaled unknowns of :mod:`.problem`), shortened so that no force changes by more than
   ``max_force_step`` (units EI / L^2), and each location clipped to its interval.
4. One evaluation at the trial point; accepted if the loss falls (damping / ``decrease``), else rejected (damping x
   ``increase``).

The fitting model is the fast 4th-order march (relative accuracy ~1e-4 of the curvature). :func:`finish` then takes
``exact_steps`` Gauss-Newton steps on the residual of the simulator's model (accurate to ~1e-9) with the fitting
model's Jacobian (a simplified Newton iteration: the two models' Jacobians differ by ~1e-4, so each step gains four
digits), and reports that residual and its loss: what the count tests and the verdict judge is the physics.

On the NumPy backend, for a straight rod, where the compiled marches run (:func:`torchrod.model.compiled.takes`),
:func:`solve` runs :func:`start` and each :func:`_step` compiled (:mod:`._lm_compiled`): the same operations row by
row, with this policy's numbers, and so does :func:`finish_counted`. The loop, the deadline and ``stop`` stay here.
Tests hold the compiled forms to these (tests/test_lm_compiled.py); they agree to rounding, since sums and solves
round in another order.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import _lm_compiled
from .problem import Fits, Problem, bounds, evaluate, exact_residual, kink_slopes, near_bounds, sided, sigma2

__all__ = ["LMPolicy", "LMState", "analyse", "finish", "finish_counted", "gauss_newton", "solve", "start"]


@dataclass(frozen=True)
class LMPolicy:
    """The Levenberg-Marquardt policy (module docstring).

    Attributes:
        damping: lambda at the start of a fit.
        increase, decrease: lambda is multiplied by ``increase`` after a rejected step, divided by ``decrease``
            after an accepted one, and kept in [``min_damping``, ``max_damping``]; at ``max_damping`` the fit
            stops (stalled).
        max_force_step: the largest change of a force component per step [EI / L^2].
        tolerance: converged when the Gauss-Newton decrement is at most ``tolerance`` x sigma^2.
        iterations: at most this many steps (evaluations after the first) per fit.
        refine_iterations: for the fits an answer is made of that ``iterations`` left open (not converged, not
            stalled), at most this many more steps, from where they stand (:class:`.search.Solver`; 0: none). Such
            fits creep along a direction the data barely determine; spent on every fit, the same steps cost more.
        exact_steps: Gauss-Newton steps on the exact model's residual after convergence (:func:`finish`), each
            taken only where it promises more than ``exact_tolerance`` x sigma^2.
        acceleration: add the geodesic acceleration to a step when the previous one lowered the loss by less than
            this fraction of what its Gauss-Newton model promised (the residual curves: the linear model misled;
            None: never); probe: its finite-difference step, a fraction of the step; acceleration_limit: the
            largest ratio 2 |a| / |v| at which it is taken.
    """

    damping: float = 1e-3
    increase: float = 4.0
    decrease: float = 3.0
    min_damping: float = 1e-9
    max_damping: float = 1e9
    max_force_step: float = 10.0
    tolerance: float = 1e-3
    iterations: int = 30
    refine_iterations: int = 70
    exact_steps: int = 3
    exact_tolerance: float = 1e-4
    acceleration: float | None = 0.5
    probe: float = 0.1
    acceleration_limit: float = 0.75

    def __post_init__(self) -> None:
        for name in ("damping", "increase", "decrease", "min_damping", "max_damping", "max_force_step"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0.0:
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if not (self.increase > 1.0 and self.decrease > 1.0):
            raise ValueError(f"increase and decrease must exceed 1, got {self.increase!r}, {self.decrease!r}")
        if not (self.tolerance > 0.0):
            raise ValueError(f"tolerance must be positive, got {self.tolerance!r}")
        for name in ("iterations", "refine_iterations", "exact_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {v!r}")


@dataclass(frozen=True)
class LMState:
    """The state of R fits (backend arrays, row first).

    Attributes:
        fits: the current point (:class:`.problem.Fits`).
        r: (R, 2G) residuals [1/m]; J: (R, 2G, 3h) their Jacobian in the march's convention at ties (the solvers
            use :func:`.problem.sided`); loss: (R,) [1/m^2].
        damping: (R,) lambda; steps: (R,) steps taken (each one evaluation).
        held: (R, h) bool, locations held on a bound of their interval.
        decrement: (R,) the Gauss-Newton decrement at the current point [1/m^2] (inf where its solve failed).
        noise2: (R,) sigma^2 of the stopping rule [1/m^2]; converged: (R,) bool; done: (R,) bool (converged,
            stalled or out of steps).
        A: (R, 3h, 3h) J^T J over the unknowns that move (held locations' rows and columns zero); g: (R, 3h) the
            gradient J^T r over them; proposal: (R, 3h) the damped Gauss-Newton step at the current damping.
        ratio: (R,) the last step's loss decrease over the one its Gauss-Newton model promised (1 before any).
    """

    fits: Fits
    r: Any
    J: Any
    loss: Any
    damping: Any
    steps: Any
    held: Any
    decrement: Any
    noise2: Any
    converged: Any
    done: Any
    A: Any = None
    g: Any = None
    proposal: Any = None
    ratio: Any = None

    def replace(self, **changes: Any) -> LMState:
        """A copy with ``changes``: :func:`dataclasses.replace` without its per-call introspection (the solver
        makes a few per step)."""
        if not changes.keys() <= _STATE_FIELDS:
            raise TypeError(f"LMState has no fields {sorted(changes.keys() - _STATE_FIELDS)}")
        new = object.__new__(LMState)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def take(self, xp: Any, idx: Any) -> LMState:
        if _every_row(xp, idx, self.fits.rows):  # the state itself (states are never changed in place)
            return self

        def pick(name: str) -> Any:
            if name == "fits":
                return self.fits.take(idx)
            x = getattr(self, name)
            return None if x is None else x[idx]

        return self.replace(**{name: pick(name) for name in _STATE_FIELDS})

    def put(self, xp: Any, idx: Any, part: LMState) -> LMState:
        if _every_row(xp, idx, self.fits.rows):  # every row replaced, in order: ``part``, and None where self has
            return part.replace(**{name: None for name in _STATE_FIELDS if getattr(self, name) is None})

        def merge(name: str) -> Any:
            a, b = getattr(self, name), getattr(part, name)
            return None if a is None or b is None else xp.put(a, idx, b)

        fits = Fits(
            *(xp.put(getattr(self.fits, k), idx, getattr(part.fits, k)) for k in ("reading", "s", "f", "interval"))
        )
        return self.replace(**{name: (fits if name == "fits" else merge(name)) for name in _STATE_FIELDS})


_STATE_FIELDS = frozenset(f.name for f in dataclasses.fields(LMState))

FLOOR = 1e-12
"""Every damped system adds this fraction of its largest diagonal entry to its diagonal (:func:`_damped`)."""
SCALE_MIN = 1e-300
"""The least scale (largest diagonal entry) :data:`FLOOR` is taken of, so that a system of zeros (unknowns no
residual depends on) still gets a positive diagonal."""
TINY = 1e-9
"""The damping of the system whose solution gives the Gauss-Newton decrement (:func:`analyse`) and of the exact
model's steps (:func:`finish`): next to none, so that a nearly singular system still solves."""


def _every_row(xp: Any, idx: Any, rows: int) -> bool:
    """Whether the row indices ``idx`` are 0, 1, ..., rows - 1: every row, in order."""
    return idx.shape[0] == rows and (rows == 0 or bool(xp.all(idx == xp.arange(rows))))


def _damped(xp: Any, A: Any, free: Any, damping: Any, repeat: int = 1) -> Any:
    """``A + damping diag A + 1e-12 max diag A`` (R, P, P) with an identity-like row (the largest diagonal) for each
    unknown that does not move (``free`` (R, P) 0.0); A (R, P, P) is J^T J over the free unknowns, damping (R,)
    or, with ``repeat`` k, (k R,): the k systems of each damping, stacked (k R, P, P)."""
    R, P = free.shape
    if P == 0:
        return xp.concat([A] * repeat) if repeat > 1 else A
    d = xp.diagonal(A)
    scale = xp.clip(xp.amax(d, 1), lo=SCALE_MIN)[:, None]
    base = FLOOR * scale + (1.0 - free) * scale
    out = xp.concat([A] * repeat) if repeat > 1 else xp.copy(A)
    idx = xp.arange(P)
    # (k, R, P) -> (k R, P): the k dampings of each system against its one diagonal, broadcast
    out[:, idx, idx] = (d + damping.reshape(repeat, R, 1) * d + base).reshape(repeat * R, P)
    return out


def _system(xp: Any, J: Any, r: Any, free: Any, damping: Any) -> tuple[Any, Any, Any]:
    """The damped normal matrix (:func:`_damped`) over the ``free`` (R, P) unknowns, the gradient g = J^T r (R, P)
    and the masked Jacobian (R, n, P); damping a number or (R,)."""
    free = xp.astype(free, "float")
    Jf = J * free[:, None, :]
    g = xp.einsum("rkp,rk->rp", Jf, r)
    A = xp.mT(Jf) @ Jf
    if isinstance(damping, float):
        damping = xp.full((J.shape[0],), damping)
    return _damped(xp, A, free, damping), g, Jf


def gauss_newton(xp: Any, J: Any, r: Any, free: Any, damping: Any) -> tuple[Any, Any]:
    """The damped Gauss-Newton step (R, P) and its decrement (R,) = -g . step with only the ``free`` (R, P)
    unknowns moving: ``(A + damping diag A + 1e-12 max diag A) step = -g`` over them. A failed solve (not
    positive definite, not finite) gives a zero step and an infinite decrement."""
    A, g, _ = _system(xp, J, r, free, damping)
    x, ok = xp.spd_solve(A, g)
    step = -x
    dec = xp.where(ok, -(g * step).sum(1), math.inf)
    return step, dec


def _free(held: Any, xp: Any) -> Any:
    """(R, 3h) float: 1.0 for every unknown except the held locations (0.0)."""
    R, h = held.shape
    keep = xp.ones((R, h, 3))
    keep[:, :, 0] = xp.astype(~held, "float")
    return keep.reshape(R, 3 * h)


def analyse(problem: Problem, policy: LMPolicy, state: LMState) -> LMState:
    """Crossings, held locations, the decrement, the stopping tests and the next step's proposal at the current
    point (module docstring, steps 1 and 2): one normal system, solved with the tiny damping of the decrement and
    the current damping of the step in one batched solve."""
    xp = problem.xp
    fits, r = state.fits, state.r
    R, h = fits.s.shape
    lo, hi = bounds(problem, fits)
    J = sided(problem, fits, state.J, hi)
    g = xp.einsum("rkp,rk->rp", J, r)
    near_lo, near_hi = near_bounds(problem, fits, (lo, hi))
    if bool(xp.any(near_lo | near_hi)):
        at_lo, at_hi = fits.s == lo, fits.s == hi
        g_s = g[:, 0::3]
        c_lo, c_hi = kink_slopes(problem, fits, r, (lo, hi))
        m = problem.intervals[fits.reading][:, None]
        # Leave the interval where the loss falls on both sides of the bound's grating (from on or near it: the
        # interval's own optimum may sit micrometres inside, the better one beyond the grating).
        down = near_lo & ((g_s >= 0.0) | ~at_lo) & (fits.interval > 0) & (g_s - c_lo > 0.0)
        up = near_hi & ((g_s <= 0.0) | ~at_hi) & (fits.interval < m - 1) & (g_s + c_hi < 0.0)
        if bool(xp.any(down | up)):
            interval = fits.interval - xp.astype(down, "int") + xp.astype(up, "int")
            s = xp.where(down, lo, xp.where(up, hi, fits.s))  # onto the grating
            moved = xp.nonzero(xp.any((s != fits.s).reshape(R, h), 1))
            fits = Fits(fits.reading, s, fits.f, interval)
            if moved.shape[0]:  # snapped onto the grating (a few micrometres): the residuals there, exactly
                r_m, J_m = evaluate(problem, fits.take(moved))
                r, J_raw = xp.put(r, moved, r_m), xp.put(state.J, moved, J_m)
                loss = xp.put(state.loss, moved, (r_m * r_m).sum(1))
                state = state.replace(fits=fits, r=r, J=J_raw, loss=loss)
            lo, hi = bounds(problem, fits)
            at_lo, at_hi = fits.s == lo, fits.s == hi
            J = sided(problem, fits, state.J, hi)
            g = xp.einsum("rkp,rk->rp", J, r)
        g_s = g[:, 0::3]
        held = (at_lo & (g_s >= 0.0)) | (at_hi & (g_s <= 0.0))
        free = _free(held, xp)
        J = J * free[:, None, :]
        g = g * free
    else:  # no force near a bound: none held (what the masking above would give, without its operations)
        held = xp.zeros((R, h), "bool")
        free = xp.ones((R, 3 * h))
    A = xp.mT(J) @ J
    both = _damped(xp, A, free, xp.concat([TINY + 0.0 * state.damping, state.damping]), repeat=2)
    x, ok = xp.spd_solve(both, xp.concat([g, g]))
    dec = xp.where(ok[:R], (g * x[:R]).sum(1), math.inf)
    proposal = -x[R:]
    noise2 = sigma2(problem, fits, state.loss)
    converged = dec <= policy.tolerance * noise2
    done = converged | (state.steps >= policy.iterations) | (state.damping >= policy.max_damping)
    return state.replace(
        fits=fits,
        held=held,
        decrement=dec,
        noise2=noise2,
        converged=converged,
        done=done,
        A=A,
        g=g,
        proposal=proposal,
    )


def start(problem: Problem, policy: LMPolicy, fits: Fits) -> LMState:
    """The state at ``fits`` (one evaluation), analysed."""
    xp = problem.xp
    R, h = fits.s.shape
    r, J = evaluate(problem, fits)
    loss = (r * r).sum(1)
    loss = xp.where(xp.isfinite(loss), loss, math.inf)
    zeros = xp.zeros((R,))
    state = LMState(
        fits=fits,
        r=r,
        J=J,
        loss=loss,
        damping=zeros + policy.damping,
        steps=xp.zeros((R,), "int"),
        held=xp.zeros((R, h), "bool"),
        decrement=zeros,
        noise2=zeros,
        converged=xp.zeros((R,), "bool"),
        done=xp.zeros((R,), "bool"),
        ratio=zeros + 1.0,
    )
    return analyse(problem, policy, state)


def _step(problem: Problem, policy: LMPolicy, state: LMState) -> LMState:
    """One Levenberg-Marquardt step of every row of ``state`` (module docstring, steps 3 and 4), analysed."""
    xp = problem.xp
    fits = state.fits
    R, h = fits.s.shape
    lo, hi = bounds(problem, fits)

    def moved(dx: Any, rows: Any = None) -> Fits:  # the fits moved by dx (of every row, or of ``rows``)
        at, low, high = (fits, lo, hi) if rows is None else (fits.take(rows), lo[rows], hi[rows])
        d = dx.reshape(dx.shape[0], h, 3)
        s = xp.clip(at.s + d[..., 0] * problem.length, low, high)
        return Fits(at.reading, s, at.f + d[..., 1:] * problem.force_unit, at.interval)

    def shortened(dx: Any) -> Any:  # the trust region on the force components
        f_part = dx.reshape(R, h, 3)[..., 1:].reshape(R, 2 * h)
        return dx / xp.clip(xp.amax(abs(f_part), 1) / policy.max_force_step, lo=1.0)[:, None]

    held, A, g, proposal = state.held, state.A, state.g, state.proposal
    # Active set: a force on a bound whose proposed step points out of its interval is held there too (the clipped
    # step would not be the Gauss-Newton step of the other unknowns), and the step recomputed without it.
    ds = proposal.reshape(R, h, 3)[..., 0]
    out = ((fits.s == lo) & (ds < 0.0)) | ((fits.s == hi) & (ds > 0.0))
    if bool(xp.any(out)):
        held = held | out
        keep = _free(held, xp)
        A = A * keep[:, :, None] * keep[:, None, :]
        g = g * keep
        proposal = -xp.spd_solve(_damped(xp, A, keep, state.damping), g)[0]
    v = shortened(proposal)
    dx = v
    curved = state.ratio < policy.acceleration if policy.acceleration is not None else None
    if curved is not None and h and bool(xp.any(curved)):
        # Geodesic acceleration, for the rows whose last step curved: the residual's second derivative along v by
        # a finite difference, and the correction it asks for, taken when small against v.
        rows = xp.nonzero(curved)
        n, v_c, here = rows.shape[0], v[rows], fits.take(rows)
        probe = moved(policy.probe * v_c, rows)
        r_p, _ = evaluate(problem, probe, jacobian=False)
        actual = (
            xp.concat(
                [((probe.s - here.s) / problem.length)[..., None], (probe.f - here.f) / problem.force_unit], 2
            ).reshape(n, 3 * h)
            / policy.probe
        )
        free = _free(held[rows], xp)
        Jf = sided(problem, here, state.J[rows]) * free[:, None, :]
        r_vv = (2.0 / policy.probe) * ((r_p - state.r[rows]) / policy.probe - xp.einsum("rkp,rp->rk", Jf, actual))
        x_a, ok_a = xp.spd_solve(_damped(xp, A[rows], free, state.damping[rows]), xp.einsum("rkp,rk->rp", Jf, r_vv))
        a = -x_a

        def norm(x):
            return xp.lib.sqrt((x * x).sum(1))

        use = ok_a & xp.all(xp.isfinite(r_vv), 1) & (2.0 * norm(a) <= policy.acceleration_limit * norm(v_c))
        dx = shortened(v + xp.put(xp.zeros((R, 3 * h)), rows, xp.where(use[:, None], 0.5 * a, 0.0)))
    trial = moved(dx)
    r_t, J_t = evaluate(problem, trial)
    loss_t = (r_t * r_t).sum(1)
    better = xp.isfinite(loss_t) & (loss_t < state.loss)
    # The decrease the Gauss-Newton model promised for the step taken: -(2 g.dx + dx^T A dx).
    taken = xp.concat(
        [((trial.s - fits.s) / problem.length)[..., None], (trial.f - fits.f) / problem.force_unit], 2
    ).reshape(R, 3 * h)
    promised = -(2.0 * (g * taken).sum(1) + (taken * (A @ taken[:, :, None])[..., 0]).sum(1))
    ratio = xp.where(better & (promised > 0), (state.loss - loss_t) / xp.where(promised > 0, promised, 1.0), 0.0)
    b1, b2 = better[:, None], better[:, None, None]
    new = state.replace(
        fits=Fits(fits.reading, xp.where(b1, trial.s, fits.s), xp.where(b2, trial.f, fits.f), fits.interval),
        r=xp.where(b1, r_t, state.r),
        J=xp.where(b2, J_t, state.J),
        loss=xp.where(better, loss_t, state.loss),
        damping=xp.where(
            better,
            xp.clip(state.damping / policy.decrease, lo=policy.min_damping),
            xp.clip(state.damping * policy.increase, hi=policy.max_damping),
        ),
        steps=state.steps + 1,
        ratio=ratio,
    )
    return analyse(problem, policy, new)


def solve(
    problem: Problem,
    policy: LMPolicy,
    fits: Fits | LMState,
    deadline: float | None = None,
    stop: Callable[[LMState], Any] | None = None,
) -> LMState:
    """Fit every row of ``fits`` (or continue the solves of a state) until each is done (module docstring), or
    until ``time.perf_counter()`` passes ``deadline``: the rows still going are then returned as they are, with
    ``done`` False (a later call may continue them). ``stop(state) -> (R,) bool``, checked on all rows at the
    start and after each step: the rows where it holds are done (the caller knows where they lead)."""
    xp = problem.xp

    def late() -> bool:
        return deadline is not None and time.perf_counter() > deadline

    rows, h = fits.s.shape if isinstance(fits, Fits) else fits.fits.s.shape
    if _lm_compiled.usable(problem, rows, h):
        compiled_state = _lm_compiled.solve(problem, policy, fits, late, stop)
        if compiled_state is not None:
            return compiled_state
    state = start(problem, policy, fits) if isinstance(fits, Fits) else fits
    if stop is not None:
        state = state.replace(done=state.done | stop(state))
    while True:
        idx = xp.nonzero(~state.done)
        if idx.shape[0] == 0 or late():
            return state
        if idx.shape[0] == state.done.shape[0]:  # every row still going: no need to gather and scatter
            state = _step(problem, policy, state)
        else:
            state = state.put(xp, idx, _step(problem, policy, state.take(xp, idx)))
        if stop is not None:
            state = state.replace(done=state.done | stop(state))


def finish(problem: Problem, policy: LMPolicy, state: LMState) -> LMState:
    """The fits of ``state`` moved to the exact model's optimum (module docstring); r and loss from the exact
    model, J the fitting model's (at the fitting model's optimum, within ~1e-4)."""
    return finish_counted(problem, policy, state)[0]


def finish_counted(problem: Problem, policy: LMPolicy, state: LMState) -> tuple[LMState, Any]:
    """:func:`finish`, and (R,) the exact-model evaluations each row needs: the residual, then one per step it
    tries, up to its first step that is not worth taking or does not lower the loss. That is what the row costs
    alone; in a batch the loop runs while any row moves, and a row that has stopped is evaluated again at the same
    point, to the same end (its state is the one it reaches alone)."""
    xp = problem.xp
    fits = state.fits
    R, h = fits.s.shape
    if _lm_compiled.usable(problem, R, h):
        compiled = _lm_compiled.finish_counted(problem, policy, state)
        if compiled is not None:
            return compiled
    r = exact_residual(problem, fits)
    loss = (r * r).sum(1)
    used = xp.ones((R,), "int")
    if h == 0:
        return state.replace(r=r, loss=loss), used
    J = sided(problem, fits, state.J)
    free = _free(state.held, xp)
    going = xp.ones((R,), "bool")  # rows still moving as they would alone
    for _ in range(policy.exact_steps):
        dx, dec = gauss_newton(xp, J, r, free, TINY)
        # A step whose promise is far below the noise moves the fit by a sliver of its standard deviation: skip.
        worth = ~(dec <= policy.exact_tolerance * sigma2(problem, fits, loss))
        going = going & worth
        if not bool(xp.any(worth)):
            break
        dx = xp.where(worth[:, None], dx, 0.0).reshape(R, h, 3)
        lo, hi = bounds(problem, fits)
        trial = Fits(
            fits.reading,
            xp.clip(fits.s + dx[..., 0] * problem.length, lo, hi),
            fits.f + dx[..., 1:] * problem.force_unit,
            fits.interval,
        )
        r_t = exact_residual(problem, trial)
        loss_t = (r_t * r_t).sum(1)
        used = used + xp.astype(going, "int")
        better = worth & xp.isfinite(loss_t) & (loss_t < loss)
        going = going & better
        if not bool(xp.any(better)):
            break
        fits = Fits(
            fits.reading,
            xp.where(better[:, None], trial.s, fits.s),
            xp.where(better[:, None, None], trial.f, fits.f),
            fits.interval,
        )
        r = xp.where(better[:, None], r_t, r)
        loss = xp.where(better, loss_t, loss)
    loss = xp.where(xp.isfinite(loss), loss, math.inf)
    return state.replace(fits=fits, r=r, loss=loss), used
