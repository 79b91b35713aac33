"""Where to start the fits of h forces, and how to leave a wrong local minimum: the scan, the starts, the exchange.

The loss of a fit is smooth inside each force's grating interval and has kinks between them (:mod:`.problem`), and
for h >= 2 it has local minima that differ in which intervals the forces occupy. The search finds the global
minimum of each count from the one below it, with work linear in the number of gratings:

* **Scan** (:func:`scan`). Given a fit of h - 1 forces (for h = 1, no force), the Gauss-Newton model of adding one
  more force at a candidate location c, with every unknown of the fit free to adjust, promises a loss decrease
  (its decrement: the score statistic for a force at c). Candidates sit at ``per_interval`` points inside each
  interval of the reading; their responses come from ONE march of the fit with the propagator of the linearised
  rod equation (:func:`torchrod.model.sensitivity.march_propagator`), and the fit's own normal system is
  factored once for all of them (:func:`_added_force`), so the scan costs one march and a 2 x 2 solve per
  candidate: O(G) candidates, each O(G). The best candidate of each interval is ranked by its
  decrement, and the ``top`` best intervals become starts: the fit moved by the Gauss-Newton step with the new
  force at c.
* **Other starts** (:func:`_explore`). A suspicious fit (below) is also fitted from the scan's other intervals
  for its last force, each start kept only while it promises to beat the fit. One force has one local minimum per
  interval, so a one-force start that enters the interval of the fit it is to beat, without a lower loss, stops.
* **Twins** (``twins``, :func:`_twins`). Two rows of one reading whose forces occupy the same intervals (as a set,
  each force in its own interval, none held on a bound) are taken to descend to the same fit: the one with the
  higher loss stops, among the first fits of a count and among the other starts of two or more forces, and a
  start of any count that enters the intervals of the converged fit it is to beat without a lower loss stops. For
  one force this is the one minimum per interval; for more it is an assumption that tests check (two-force fits
  from several starts in one pair of intervals end at one loss; estimates with and without twins agree).
* **Exchange** (:func:`exchange`). A fit whose loss is worse than a correct fit's typically is (noise known:
  above the ``suspect`` quantile of the chi-square law; noise unknown: always), or that holds a force on a grating
  (a kink of the loss, where the loss rises on both sides: true forces seldom sit exactly on a grating, wrong local
  minima often do), may hold one force in a wrong interval. For each of its forces in turn, the force is removed and the
  scan re-places it among all intervals; the best re-placement that lowers the loss replaces the fit. Repeated on the
  fits it changed, while it helps (at most ``rounds``).
* **Trusted guesses** (``trusted``). A warm-start network's guesses, when trusted, replace the scan's best start
  among a count's first fits. The suspicious fits are then searched as above; and the count just above the chosen
  one, whose fit the count test rejected and which nothing else would search again, is also fitted from the scan's
  best start, as without trust: a guess that ends in a wrong local minimum there would keep the count too small.

Rows are laid out in blocks of B (one row per reading), so the best row of each reading is a minimum over the
block axis (:func:`best_of`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

from . import _lm_compiled, lm
from .finish import refine_open
from .problem import Fits, Problem, interval_of, march_fits, near_kink, per_problem, sided
from .refine import LBFGSOptions

__all__ = ["SearchOptions", "best_of", "exchange", "scan"]


@dataclass(frozen=True)
class Solver:
    """How a set of starts is fitted: the Levenberg-Marquardt policy (:mod:`.lm`) on every start, then, for the
    best fit of each reading, L-BFGS (:mod:`.finish`) where the LM left it open (None: not) and the exact-model
    steps. ``deadline`` (a ``time.perf_counter()`` value, None: none) cuts the work short: LM solves stop where
    they are, and :func:`fit_counts` skips what is left and says which readings it cut."""

    policy: lm.LMPolicy
    lbfgs: LBFGSOptions | None = None
    deadline: float | None = None

    def late(self) -> bool:
        """Whether ``time.perf_counter()`` has passed the deadline (never without one)."""
        return self.deadline is not None and time.perf_counter() > self.deadline

    def solve(self, problem: Problem, fits: Fits | lm.LMState, stop: Any = None) -> lm.LMState:
        """Levenberg-Marquardt on every row; past the deadline the rows still going stop, ``done`` False.
        ``stop``: as :func:`.lm.solve`'s."""
        return lm.solve(problem, self.policy, fits, self.deadline, stop)

    def finish(self, problem: Problem, best: lm.LMState) -> tuple[lm.LMState, bool, Any]:
        """The fits kept (the best of each reading): the exact-model steps (:func:`.lm.finish`); past the deadline
        only the exact model's residual (the fits stay at the fitting model's optimum, ~1e-4 off) and True: the
        rows were cut short. Also (R,) the exact-model evaluations each row needed
        (:func:`.lm.finish_counted`)."""
        if self.late():
            done, used = lm.finish_counted(problem, dataclasses.replace(self.policy, exact_steps=0), best)
            return done, True, used
        done, used = lm.finish_counted(problem, self.policy, best)
        return done, False, used

    def refine(self, problem: Problem, chosen: lm.LMState) -> tuple[lm.LMState, Any]:
        """The fits the answer is made of, where the LM budget left them open: more LM steps from where they stand
        (``policy.refine_iterations``), then L-BFGS where still open (:mod:`.finish`), then the exact-model steps
        again; the others unchanged. Also (R,) the evaluations that took (0 where unchanged)."""
        xp = problem.xp
        spent = xp.zeros((chosen.fits.rows,), "int")
        if self.lbfgs is None and self.policy.refine_iterations == 0:
            return chosen, spent
        open_ = xp.nonzero(
            ~chosen.converged & (chosen.steps >= self.policy.iterations) & (chosen.damping < self.policy.max_damping)
        )
        if open_.shape[0] == 0:
            return chosen, spent
        part, used = chosen.take(xp, open_), xp.zeros((open_.shape[0],), "int")
        policy = self.policy
        if policy.refine_iterations > 0:
            policy = dataclasses.replace(policy, iterations=policy.refine_iterations)
            part = lm.solve(problem, policy, part.fits, self.deadline)  # the fitting model's residual again
            used = 1 + part.steps
        if self.lbfgs is not None:
            before = part.steps
            part = refine_open(problem, policy, self.lbfgs, part)
            used = used + part.steps - before
        done, exact = lm.finish_counted(problem, self.policy, part)
        return chosen.put(xp, open_, done), xp.put(spent, open_, used + exact)


@dataclass(frozen=True)
class SearchOptions:
    """How starts are found (module docstring).

    Attributes:
        per_interval: scan candidates per grating interval.
        top: intervals tried per count (starts from the scan).
        exchange_top: re-placements tried per exchange round: those the scan promises the lowest loss from, over
            every removed force.
        rounds: at most this many exchange rounds per count.
        explore: steps a start of the wider search takes before it is dropped, unless its loss has fallen below
            the fit it tries to beat (then it is fitted to the end).
        suspect: a fit with known noise is searched further (its other starts, the exchange) when its loss
            exceeds this quantile of the chi-square law of a correct fit's loss; kink_suspect: the same for a fit
            with a force on a grating.
        hopeless, explained: a count below the chosen one is searched further only when its loss is within
            ``hopeless`` times the loss it needs to pass the count tests (its ceiling, given the fits of the larger
            counts: :func:`.selection.ceilings`), or below ``explained`` times the loss of the count
            under it (it explains nearly all of that one's misfit: on a clean reading a wrong local minimum of the
            true count does).
        twins: stop a row that another row of the same reading has joined in the same intervals with a lower loss,
            and a start of the wider search that reaches the intervals of the fit it is to beat without a lower
            loss (module docstring; False: only the one-force case, which always holds).
    """

    per_interval: int = 2
    top: int = 3
    exchange_top: int = 2
    rounds: int = 2
    explore: int = 8
    suspect: float = 0.95
    kink_suspect: float = 0.5
    hopeless: float = 3.0
    explained: float = 0.01
    twins: bool = True

    def __post_init__(self) -> None:
        for name in ("per_interval", "top", "exchange_top", "explore"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if isinstance(self.rounds, bool) or not isinstance(self.rounds, int) or self.rounds < 0:
            raise ValueError(f"rounds must be an integer >= 0, got {self.rounds!r}")
        for name in ("suspect", "kink_suspect"):
            if not 0.0 < float(getattr(self, name)) < 1.0:
                raise ValueError(f"{name} must lie in (0, 1), got {getattr(self, name)!r}")
        if not float(self.hopeless) >= 1.0:
            raise ValueError(f"hopeless must be >= 1, got {self.hopeless!r}")
        if not isinstance(self.twins, bool):
            raise ValueError(f"twins must be True or False, got {self.twins!r}")


@dataclass(frozen=True)
class Scan:
    """The result of :func:`scan` for R0 base fits.

    Attributes:
        starts: Fits of h forces, ``top`` blocks of R0 rows (block t holds each base row's t-th best interval).
        gain: (R0,) the largest decrement over all candidates [1/m^2]: the loss decrease the best added force
            promises (0 where no candidate could be scored).
        predicted: (top, R0) the loss each start's Gauss-Newton model promises [1/m^2] (inf: no such start).
    """

    starts: Fits
    gain: Any
    predicted: Any = None


def _candidates(problem: Problem, reading: Any, per_interval: int) -> tuple[Any, Any, Any]:
    """Candidate locations (R0, C) [m], their intervals (R0, C) and validity (R0, C), C = per_interval x G, of the
    readings ``reading`` (R0,)."""
    s, j, valid = _all_candidates(problem, per_interval)
    return s[reading], j[reading], valid[reading]


@per_problem
def _all_candidates(problem: Problem, per_interval: int) -> tuple[Any, Any, Any]:
    """:func:`_candidates` of every reading (the scan of each count asks for them again)."""
    xp = problem.xp
    lo, hi = problem.lo, problem.hi  # (B, G)
    B, G = lo.shape
    frac = xp.asarray([(k + 0.5) / per_interval for k in range(per_interval)])  # (K,)
    s = (lo[:, :, None] + (hi - lo)[:, :, None] * frac).reshape(B, G * per_interval)
    j = xp.expand(xp.arange(G)[:, None], (G, per_interval)).reshape(G * per_interval)
    j = xp.expand(j[None, :], (B, G * per_interval))
    valid = j < problem.intervals[:, None]
    return s, j, valid


def _responses(problem: Problem, base: Fits, cand: Any, known: tuple[Any, Any] | None) -> tuple[Any, Any, Any]:
    """For R0 base fits: residuals r (R0, 2G), the sided Jacobian J (R0, 2G, 3h0) (``known``: given, else from the
    march), and the responses of the gratings to a unit force (f_x, f_y) added at each candidate, Jc (R0, C, 2G,
    2), in scaled units."""
    xp = problem.xp
    R0, h0 = base.s.shape
    G = problem.query.shape[0]
    q = problem.query
    w = problem.weight[base.reading]
    if h0 == 0 and problem.precurved is None:
        # No force yet: the rod is straight and the response is the small-deflection lever, (c - q_k)^+ / EI.
        r, J = -problem.u[base.reading] * w, xp.zeros((R0, 2 * G, 0))
        lever = xp.clip(cand[:, :, None] - q[None, None, :], lo=0.0) * (1.0 / problem.stiffness)  # (R0, C, G)
        zero = 0.0 * lever
        resp = xp.stack([xp.stack([zero, lever], 3), xp.stack([-lever, zero], 3)], 4)  # (R0, C, G, 2 uxy, 2 f)
    else:
        query = xp.concat([xp.expand(q[None, :], (R0, G)), cand], 1)  # each row: the gratings and its candidates
        u, jac, rows, phi, rhs = _propagator(problem, base, query, jacobian=known is None)
        if known is None:
            r = (u[:, :G].reshape(R0, 2 * G) - problem.u[base.reading]) * w
            scale = xp.asarray([problem.length, problem.force_unit, problem.force_unit])
            J = sided(problem, base, (jac[:, :G] * scale).reshape(R0, 2 * G, 3 * h0) * w[:, :, None])
        else:
            r, J = known
        # Phi(k) Phi(c)^-1 applied to the state's jump under a unit f_x and f_y at c.
        C, S = cand.shape[1], rhs.shape[0]
        M, _ = xp.solve(phi[:, G:], xp.expand(rhs, (R0, C, S, 2)))  # (R0, C, S, 2); a failed solve: no response
        # One (2G, S) @ (S, 2) product per candidate, not G small ones: the same numbers at a fifth of the time.
        resp = (rows[:, :G].reshape(R0, 1, 2 * G, S) @ M).reshape(R0, C, G, 2, 2)
        prox = xp.astype(q[None, None, :] < cand[:, :, None], "float")  # gratings proximal to c
        resp = resp * prox[:, :, :, None, None]
    Jc = (resp * w.reshape(R0, 1, G, 2, 1) * problem.force_unit).reshape(R0, cand.shape[1], 2 * G, 2)
    return r, J, Jc


def _propagator(problem: Problem, base: Fits, query: Any, *, jacobian: bool) -> tuple[Any, ...]:
    """The base fits' march with the propagator Phi of its linearised equations from the tip, at ``query``
    (R0, Q): curvature (R0, Q, 2), its Jacobian (or None), the (u_x, u_y) rows of Phi (R0, Q, 2, S), Phi itself
    (R0, Q, S, S), and the jump of the state under a unit f_x and f_y (S, 2). The straight rod's state is (U, W)
    as real pairs (S = 4; :func:`torchrod.model.sensitivity.march_propagator`), a precurved rod's (n, m) (S = 6;
    :mod:`torchrod.model.precurved`)."""
    xp = problem.xp
    u, jac, phi = march_fits(problem, query, base.s, base.f, jacobian=jacobian, seeds=True)
    if problem.precurved is not None:
        rhs = xp.zeros((6, 2))
        rhs[0, 0] = 1.0  # a unit f_x: n jumps by e_x
        rhs[1, 1] = 1.0
        return u, jac, phi[:, :, :2], phi[:, :, 2:], rhs
    inv_ei = 1.0 / problem.stiffness
    jumps = xp.asarray([[0.0, -inv_ei], [inv_ei, 0.0]])  # slope jumps (Re dW, Im dW) x (f_x, f_y)
    return u, jac, phi[:, :, :2], phi, xp.concat([xp.zeros((2, 2)), jumps], 0)


def scan(problem: Problem, base: Fits | lm.LMState, *, per_interval: int, top: int, trust: float) -> Scan:
    """Starts for h = base.h + 1 forces from R0 base fits (module docstring).

    Args:
        base: R0 fits of h0 >= 0 forces, or the solver's state of them (whose residuals and Jacobian are then
            reused: the scan's march computes only the propagator).
        per_interval: candidates per interval; top: starts per base fit.
        trust: the largest force component of a start's Gauss-Newton step [EI / L^2] (the step is shortened).
    """
    xp = problem.xp
    known = None
    if isinstance(base, lm.LMState):
        known = (base.r, sided(problem, base.fits, base.J))
        base = base.fits
    R0, h0 = base.s.shape
    G = problem.query.shape[0]
    cand, cint, valid = _candidates(problem, base.reading, per_interval)
    compiled = _lm_compiled.scan(problem, base, cand, known) if _lm_compiled.usable(problem, R0, h0) else None
    if compiled is not None:  # the same, compiled (._lm_compiled)
        r, J, dec, xc, yb, Y = compiled
        steps = _steps(xp, xc, yb, Y)
    else:
        r, J, Jc = _responses(problem, base, cand, known)
        dec, steps = _added_force(xp, J, r, Jc)
    dec = xp.where(valid & xp.isfinite(dec), dec, -math.inf)
    # The best candidate of each interval, then the `top` best intervals.
    K = per_interval
    dec_i = dec.reshape(R0, G, K)
    best_k = xp.argmin(-dec_i, 2)  # (R0, G)
    dec_g = xp.amax(dec_i, 2)  # (R0, G), the best candidate's: dec holds no NaN
    order = xp.argsort_desc(dec_g)[:, :top]  # (R0, top) intervals
    if order.shape[1] < top:  # fewer gratings than starts: the best interval fills the rest (repeated below too)
        order = xp.concat([order] + [order[:, :1]] * (top - order.shape[1]), 1)
    gain = xp.amax(dec_g, 1)
    gain = xp.where(xp.isfinite(gain), xp.clip(gain, lo=0.0), 0.0)
    base_loss = (r * r).sum(1)
    # The `top` starts of every base row at once, in blocks (row t R0 + i: base row i's t-th best interval).
    c = order * K + xp.take(best_k, order, 1)  # (R0, top) candidate indices
    dec_c = xp.take(dec, c, 1)
    ok = xp.isfinite(dec_c)
    # A base row with fewer intervals than `top` repeats its best start.
    c = xp.where(ok, c, c[:, :1])
    predicted = xp.mT(xp.where(ok, base_loss[:, None] - xp.take(dec, c, 1), math.inf))  # (top, R0)
    c = xp.mT(c).reshape(-1)  # (top R0,) block order
    i = xp.concat([xp.arange(R0)] * top)
    st = steps(i, c)  # (top R0, Pb + 2)
    big = xp.clip(xp.amax(abs(st), 1) / trust, lo=1.0)[:, None]
    st = st / big
    Pb = 3 * h0
    d = st[:, :Pb].reshape(top * R0, h0, 3)
    reading = base.reading[i]
    s_old = base.s[i] + d[..., 0] * problem.length
    f_old = base.f[i] + d[..., 1:] * problem.force_unit
    # A base force the step moves past a grating starts in the interval it moves into.
    int_old, s_old = interval_of(problem, reading, s_old)
    starts = Fits(
        reading,
        xp.concat([s_old, cand[i, c][:, None]], 1),
        xp.concat([f_old, st[:, None, Pb:] * problem.force_unit], 1),
        xp.concat([int_old, cint[i, c][:, None]], 1),
    )
    return Scan(starts=starts, gain=gain, predicted=predicted)


def _added_force(xp: Any, J: Any, r: Any, Jc: Any) -> tuple[Any, Any]:
    """The Gauss-Newton model of each base fit with one more force at each candidate, every unknown free.

    For base row i and candidate c the normal system of the columns [J_i, Jc_ic] is
    ``[[Abb, Abc], [Acb, Acc]] x = [gb; gc]``, lightly damped (``lm.TINY`` of each diagonal entry plus ``lm.FLOOR``
    of the row's largest one, base and candidates alike). It is solved through the base block K, shared by a row's C
    candidates and inverted once, so that each candidate costs a 2 x 2 system, its Schur complement:
    ``S = Acc - Y Abc`` with ``Y = Acb K^-1``, ``S x_c = z = gc - Y gb``; then ``x_b = K^-1 gb - Y^T x_c`` and the
    decrement g.x is ``gb.K^-1 gb + z.x_c``. Where the base columns span a candidate's response to rounding (S is
    then rounding error, and the decrement of the new force zero to the same accuracy) the candidate adds nothing:
    ``x_c = 0``.

    Args:
        J: (R0, n, Pb) the base fits' Jacobians; r: (R0, n) residuals; Jc: (R0, C, n, 2) the responses to a unit
            force at each candidate (scaled units).

    Returns:
        (R0, C) decrements (-inf where the base system failed), and ``steps(i, c)``: the Gauss-Newton steps
        (len(i), Pb + 2) of base rows ``i`` with candidates ``c`` (the base unknowns, then the new force's).
    """
    R0, C = Jc.shape[:2]
    Pb = J.shape[-1]
    tiny, floor = lm.TINY, lm.FLOOR
    Abb = xp.mT(J) @ J  # (R0, Pb, Pb)
    Acc = xp.mT(Jc) @ Jc  # (R0, C, 2, 2)
    gc = (r[:, None, None, :] @ Jc)[:, :, 0, :]  # (R0, C, 2)
    d_b, d_c = xp.diagonal(Abb), xp.diagonal(Acc)  # (R0, Pb), (R0, C, 2)
    scale = xp.clip(xp.amax(xp.concat([d_b, d_c.reshape(R0, 2 * C)], 1), 1), lo=lm.SCALE_MIN)[:, None]
    S, z = Acc, gc
    if Pb:
        K = Abb + xp.eye(Pb) * (tiny * d_b + floor * scale)[:, :, None]
        K_inv, ok = xp.spd_solve(K, xp.expand(xp.eye(Pb), (R0, Pb, Pb)))  # (R0, Pb, Pb)
        gb = xp.einsum("rkp,rk->rp", J, r)
        yb = (K_inv @ gb[:, :, None])[..., 0]  # K^-1 gb
        Acb = xp.mT(Jc) @ J[:, None]  # (R0, C, 2, Pb)
        Y = (Acb.reshape(R0, 2 * C, Pb) @ K_inv).reshape(R0, C, 2, Pb)  # Acb K^-1 (K symmetric)
        S = S - (Y[:, :, :, None, :] * Acb[:, :, None, :, :]).sum(4)
        z = z - (Y @ gb[:, None, :, None])[..., 0]
        base_dec = (gb * yb).sum(1)[:, None]
    else:
        base_dec, ok = 0.0, xp.ones((R0,), "bool")
        yb, Y = xp.zeros((R0, 0)), xp.zeros((R0, C, 2, 0))
    a = S[..., 0, 0] + (tiny * d_c[..., 0] + floor * scale)
    d = S[..., 1, 1] + (tiny * d_c[..., 1] + floor * scale)
    b = 0.5 * (S[..., 0, 1] + S[..., 1, 0])
    det = a * d - b * b
    adds = (a > 0.0) & (det > 0.0)
    det = xp.where(adds, det, 1.0)
    xc = xp.stack([(d * z[..., 0] - b * z[..., 1]) / det, (a * z[..., 1] - b * z[..., 0]) / det], 2)  # (R0, C, 2)
    xc = xp.where(adds[:, :, None], xc, 0.0)
    dec = xp.where(ok[:, None], base_dec + (z * xc).sum(2), -math.inf)
    return dec, _steps(xp, xc, yb, Y)


def _steps(xp: Any, xc: Any, yb: Any, Y: Any) -> Any:
    """``steps(i, c)`` of :func:`_added_force` from the pieces of its solution: the new force's xc (R0, C, 2),
    K^-1 gb yb (R0, Pb) and Y (R0, C, 2, Pb)."""

    def steps(i: Any, c: Any) -> Any:
        x_c = xc[i, c]  # (n, 2)
        if not yb.shape[1]:
            return -x_c
        x_b = yb[i] - (x_c[:, None, :] @ Y[i, c])[:, 0, :]
        return -xp.concat([x_b, x_c], 1)

    return steps


def best_of(xp: Any, state: lm.LMState, B: int, slack: Any = None, layout: tuple[Any, int] | None = None) -> Any:
    """(B,) the row index of each reading's best fit in ``state`` (rows in blocks of B): the lowest loss, where
    fits within ``slack`` (B,) [1/m^2] of it count as equal and a converged one is preferred.

    ``layout`` ``(slot, blocks)``: blocks that hold only some of the B readings; row r is reading ``slot[r] % B``
    of block ``slot[r] // B``, out of ``blocks`` (every reading in at least one block)."""
    if layout is None:
        key = state.loss.reshape(-1, B)
        if slack is not None:
            key = key - slack[None, :] * xp.astype(state.converged.reshape(-1, B), "float")
    else:
        slot, blocks = layout
        key = state.loss
        if slack is not None:
            key = key - slack[slot % B] * xp.astype(state.converged, "float")
        key = xp.put(xp.full((blocks * B,), math.inf), slot, key).reshape(-1, B)  # a missing row: last
    key = xp.where(key == key, key, math.inf)  # NaN last
    best = xp.argmin(key, 0) * B + xp.arange(B)
    if layout is None:
        return best
    return xp.put(xp.zeros((blocks * B,), "int"), slot, xp.arange(slot.shape[0]))[best]


def exchange(
    problem: Problem,
    solver: Solver,
    best: lm.LMState,
    suspect: Any,
    options: SearchOptions,
) -> lm.LMState:
    """Re-place the forces of suspicious fits one at a time (module docstring).

    Args:
        best: one fit of h >= 1 forces per row (rows of distinct readings, any order).
        suspect: the limits of :func:`suspicious` ((R,), (R,)) [1/m^2].
    Returns:
        ``best`` with every improved row replaced, (R,) the forward evaluations spent on each row, and (R,) whether
        the solver's deadline cut the row's exchange short.
    """
    xp = problem.xp
    R, h = best.fits.s.shape
    spent = xp.zeros((R,), "int")
    cut = xp.zeros((R,), "bool")
    # A fit a round left unchanged would meet the same scan and starts again: later rounds take only the fits the
    # last one changed.
    fresh = xp.ones((R,), "bool")
    for _ in range(options.rounds):
        rows = xp.nonzero(suspicious(problem, best, suspect) & fresh)
        n = rows.shape[0]
        if n == 0:
            break
        if solver.late():
            cut = xp.put(cut, rows, xp.ones((n,), "bool"))
            break
        cur = best.take(xp, rows)
        # Base fits: each row without force i, i = 0..h-1 (blocks of n).
        keep = [[k for k in range(h) if k != i] for i in range(h)]
        base = Fits(
            *(
                xp.concat([getattr(cur.fits, name)[:, k] if name != "reading" else cur.fits.reading for k in keep])
                for name in ("reading", "s", "f", "interval")
            )
        )
        T = options.exchange_top + 1
        sc = scan(problem, base, per_interval=options.per_interval, top=T, trust=solver.policy.max_force_step)
        # The re-placements the scan promises most from, over every removed force, not into its own interval.
        pred = sc.predicted.reshape(T, h, n)
        own = xp.mT(cur.fits.interval)[None]  # (1, h, n)
        pred = xp.where(sc.starts.interval[:, -1].reshape(T, h, n) == own, math.inf, pred)
        E = min(options.exchange_top, T * h)
        pick_rows = xp.argsort_desc(-pred.reshape(T * h, n).T)[:, :E].T * n + xp.arange(n)[None, :]  # (E, n)
        starts = [sc.starts.take(pick_rows[e]) for e in range(E)]
        found, work, short = _explore(problem, solver, options, starts, cur.loss, _home(xp, cur, options.twins))
        spent = xp.add_at(spent, rows, work + h)
        cut = xp.put(cut, rows, cut[rows] | short)
        margin = 10.0 * solver.policy.tolerance * cur.noise2
        better = found.loss < cur.loss - margin
        fresh = xp.put(fresh, rows, better)
        if not bool(xp.any(better)):
            break
        at = xp.nonzero(better)
        best = best.put(xp, rows[at], found.take(xp, at))
    return best, spent, cut


@dataclass(frozen=True)
class CountFits:
    """The best fit of each count h = 0..H for B readings (:func:`fit_counts`).

    Attributes:
        states: index h: an :class:`.lm.LMState` of B rows (row b: reading b); rows not fitted hold zeros and a
            NaN loss.
        fitted: index h: (B,) bool, the readings whose count h was fitted.
        evaluations: (B,) forward-model evaluations spent on each reading (one row marched once each).
        cut: (B,) bool, the solver's deadline cut the reading's search short: its fits are the best found so far.
    """

    states: list[lm.LMState]
    fitted: list[Any]
    evaluations: Any
    cut: Any


def _blank(xp: Any, B: int, h: int, G: int) -> lm.LMState:
    """B rows of h forces holding nothing (a NaN loss): the rows of readings a count was not fitted for."""
    zeros = xp.zeros((B,))
    return lm.LMState(
        fits=Fits(xp.arange(B), xp.zeros((B, h)), xp.zeros((B, h, 2)), xp.zeros((B, h), "int")),
        r=xp.zeros((B, 2 * G)),
        J=xp.zeros((B, 2 * G, 3 * h)),
        loss=zeros + math.nan,
        damping=zeros,
        steps=xp.zeros((B,), "int"),
        held=xp.zeros((B, h), "bool"),
        decrement=zeros,
        noise2=zeros,
        converged=xp.zeros((B,), "bool"),
        done=xp.ones((B,), "bool"),
    )


def no_force(problem: Problem) -> lm.LMState:
    """The fit of no force to every reading: residual -u, loss = the reading's energy (converged by definition)."""
    xp = problem.xp
    B = problem.batch_size
    G = problem.query.shape[0]
    state = _blank(xp, B, 0, G)
    r = -problem.u
    return state.replace(r=r, loss=(r * r).sum(1), converged=xp.ones((B,), "bool"))


def _among(xp: Any, guess: Fits, readings: Any, B: int) -> Fits:
    """The rows of ``guess`` (a block of starts, one row per reading it holds, reading order) of the readings
    ``readings`` (increasing): all of them when ``guess`` holds every reading."""
    if guess.rows == B:
        return guess.take(readings)
    wanted = xp.put(xp.zeros((B,), "bool"), readings, xp.ones((readings.shape[0],), "bool"))
    return guess.take(xp.nonzero(wanted[guess.reading]))


def _rows(blocks: list[Fits]) -> Fits:
    return Fits(*(_cat(blocks, k) for k in ("reading", "s", "f", "interval")))


def _cat(blocks: list[Fits], name: str) -> Any:
    parts = [getattr(b, name) for b in blocks]
    if len(parts) == 1:
        return parts[0]
    lib = type(parts[0]).__module__
    if lib.startswith("numpy"):
        import numpy as np

        return np.concatenate(parts)
    import torch

    return torch.cat(parts)


def suspicious(problem: Problem, state: lm.LMState, limits: tuple[Any, Any]) -> Any:
    """(R,) bool: fits worth a wider search: unconverged, a loss above ``limits[0]`` (R,), or a force on a grating
    with a loss above ``limits[1]`` (R,)."""
    loss_limit, kink_limit = limits
    on = near_kink(problem, state.fits) & (state.loss > kink_limit)
    return ~state.converged | (state.loss > loss_limit) | on


@dataclass(frozen=True)
class Rules:
    """The statistical decisions the search takes, as functions (:class:`torchrod.Estimator` makes them from its
    options with :mod:`.selection`). Arrays are the backend's; ``readings`` (n,) are reading indices.

    Attributes:
        choose: ``choose(losses) -> (B,)`` the count chosen from the losses (B, top + 1) of counts 0..top (NaN:
            not fitted).
        settled: ``settled(losses, readings, gain) -> (n,) bool``: with the losses (n, h + 1) of counts 0..h and
            the scan's promised gain (n,) of one more force, whether the count is decided already; None: never.
        suspect: ``suspect(h, readings) -> ((n,), (n,))``: the losses above which a fit of h forces is searched
            further, in general and with a force on a grating (:func:`suspicious`); None: never searched further.
        plausible: ``plausible(readings, losses) -> (n, top + 1)``: with the losses (n, top + 1) of counts
            0..top (NaN: not fitted), the loss of each count above which, if it is below the chosen one, it is
            hopeless (no better local minimum would make it acceptable), so not searched further.
        doubtful: ``doubtful(state) -> (n,) bool``: the fits of ``state`` (n rows of one count, row i reading i of
            ``state.fits.reading``) are poorly determined (:mod:`.uncertainty`); the count below such a chosen fit
            is searched further (a poorly determined fit often holds one force too many for a local minimum of
            the count below).
        unexplained: ``unexplained(readings, chosen, loss) -> (n,) bool``: the chosen fits (``chosen`` forces,
            ``loss``) would be answered as a misfit; the count above such a fit is searched further (a local
            minimum of that count, no better than the chosen one, is all that keeps the answer a misfit).
    """

    choose: Any
    settled: Any = None
    suspect: Any = None
    plausible: Any = None
    doubtful: Any = None
    unexplained: Any = None


def fit_counts(
    problem: Problem,
    solver: Solver,
    options: SearchOptions,
    rules: Rules,
    *,
    top_count: int,
    starts: int,
    guesses: dict[int, list[Fits]],
    needed: set[int] | None = None,
    trusted: bool = False,
) -> CountFits:
    """The best fit of each count 0..``top_count``, each count's starts from the one below (module docstring).

    First every count is fitted from its first starts (the guesses and the scan's best interval), counts in turn,
    readings whose count is settled dropping out. Then the fits that matter are searched further where they look
    :func:`suspicious`: the chosen count's, and those of smaller counts that could still be accepted (their other
    scan starts, then the exchange); with trusted guesses, first the count just above the chosen one from the
    scan's best start (module docstring).

    Args:
        rules: the decisions (:class:`Rules`).
        starts: scan starts per count (0: only ``guesses``).
        guesses: {h: [Fits]} further starts (a network's guess, a previous solution), each force already in its
            interval: a block of B rows (one per reading, in reading order) or of the rows of some readings
            (increasing ``Fits.reading``; those it leaves out are started from the scan, whether trusted or not).
        needed: the counts that must be fitted (None: all); with ``starts=0`` a count without guesses is left
            unfitted unless needed (then it is an error).
        trusted: the guesses are good enough to start alone (a network whose recorded quality says so): the first
            fits of a count with guesses skip the scan's start, which then serves only a fit found suspicious.
    """
    xp = problem.xp
    B = problem.batch_size
    G = problem.query.shape[0]
    states = [lm.finish(problem, solver.policy, no_force(problem))]
    fitted = [xp.ones((B,), "bool")]
    scans: list[Any] = [None]
    evaluations = xp.zeros((B,), "int")
    cut = xp.zeros((B,), "bool")
    open_ = xp.arange(B)
    unscanned = [False] * (top_count + 1)  # trusted guesses took the place of the scan's best start for count h
    for h in range(1, top_count + 1):
        n = open_.shape[0]
        sc = None
        if n and solver.late():  # out of time: the open readings keep the counts fitted so far
            cut = xp.put(cut, open_, xp.ones((n,), "bool"))
            open_ = open_[:0]
            n = 0
        if n and (starts > 0 or rules.settled is not None):
            base = states[h - 1].take(xp, open_)
            sc = scan(
                problem,
                base,
                per_interval=options.per_interval,
                top=max(starts, 1),
                trust=solver.policy.max_force_step,
            )
            evaluations = xp.add_at(evaluations, open_, xp.ones((n,), "int"))
            if rules.settled is not None:
                done = rules.settled(xp.stack([states[k].loss[open_] for k in range(h)], 1), open_, sc.gain)
                if bool(xp.any(done)):
                    keep = xp.nonzero(~done)
                    rows = (keep[None, :] + n * xp.arange(max(starts, 1))[:, None]).reshape(-1)
                    open_ = open_[keep]
                    sc = Scan(starts=sc.starts.take(rows), gain=sc.gain[keep], predicted=sc.predicted[:, keep])
                    n = open_.shape[0]
        state = _blank(xp, B, h, G)
        first = [_among(xp, g, open_, B) for g in guesses.get(h, [])] if n else []
        first = [g for g in first if g.rows]
        if n and starts > 0:
            if not (first and trusted):
                first.append(sc.starts.take(xp.arange(n)))
            else:
                unscanned[h] = True
                if any(g.rows < n for g in first):  # trusted guesses that skip some readings: the scan starts those
                    covered = xp.zeros((B,), "bool")
                    for g in first:
                        covered = xp.put(covered, g.reading, xp.ones((g.rows,), "bool"))
                    alone = xp.nonzero(~covered[open_])
                    if alone.shape[0]:
                        first.append(sc.starts.take(alone))
        if n and not first and (needed is None or h in needed):
            raise ValueError(f"no start for h = {h}: starts=0 needs a warm start or extra_starts for every count")
        done_here = xp.zeros((B,), "bool")
        if first:
            best, spent, short = _first_fits(problem, solver, first, open_, options.twins)
            evaluations = xp.add_at(evaluations, open_, spent)
            cut = xp.put(cut, open_, cut[open_] | short)
            state = state.put(xp, open_, best)
            done_here = xp.put(done_here, open_, xp.ones((n,), "bool"))
        states.append(state)
        fitted.append(done_here)
        scans.append((open_, sc))
    if rules.suspect is not None:
        # Search further where it matters.
        for h in range(2, top_count + 1):
            # Just above the chosen count, a fit from trusted guesses alone (the scan's best start skipped) is the
            # one the count test rejected; a wrong local minimum of it would keep the count too small, so it is
            # fitted from the scan's best start too, as the full search fits it.
            if not unscanned[h] or scans[h][1] is None:
                continue
            readings = xp.nonzero(fitted[h] & (rules.choose(xp.stack([s.loss for s in states], 1)) == h - 1))
            if readings.shape[0] == 0:
                continue
            if solver.late():
                cut = xp.put(cut, readings, xp.ones((readings.shape[0],), "bool"))
                continue
            best_start = _scan_starts(xp, scans[h], readings, B, range(1))
            cur, spent, short = _try_starts(problem, solver, options, states[h].take(xp, readings), best_start)
            evaluations = xp.add_at(evaluations, readings, spent)
            cut = xp.put(cut, readings, cut[readings] | short)
            states[h] = states[h].put(xp, readings, cur)
        losses = xp.stack([s.loss for s in states], 1)
        chosen = rules.choose(losses)
        near_limit = None if rules.plausible is None else rules.plausible(xp.arange(B), losses)  # (B, top + 1)
        every = xp.arange(B)
        misfit = xp.zeros((B,), "bool")
        if rules.unexplained is not None:
            misfit = rules.unexplained(every, chosen, xp.take(losses, chosen[:, None], 1)[:, 0])
        doubt = xp.zeros((B,), "bool")
        if rules.doubtful is not None:
            for h in range(2, top_count + 1):
                mine = xp.nonzero(fitted[h] & (chosen == h))
                if mine.shape[0]:
                    doubt = xp.put(doubt, mine, rules.doubtful(states[h].take(xp, mine)))
        for h in range(1, top_count + 1):
            cand = fitted[h] & suspicious(problem, states[h], rules.suspect(h, every))
            if rules.plausible is not None:
                # A smaller count is worth more search where a better local minimum could make it acceptable: its
                # loss within a few misfit limits, or far below the count under it (it explains most of what that
                # one leaves: a wrong local minimum of the true count looks like this on a clean reading).
                near = states[h].loss <= near_limit[:, h]
                most = states[h].loss <= options.explained * states[h - 1].loss
                # Under a poorly determined chosen fit, the count below is searched further even if its fit looks
                # acceptable: a wrong local minimum of it can pass the noise test yet lose the count test to a fit
                # with one force too many.
                below = (chosen == h + 1) & doubt
                # Above a chosen fit the verdict would call a misfit, likewise: a wrong local minimum of the count
                # above (a near tie between the scan's intervals can lead to one) leaves the reading unexplained.
                above = (chosen == h - 1) & misfit
                forced = below | above
                cand = (cand & ((chosen == h) | ((chosen > h) & (near | most)))) | (fitted[h] & forced)
                # The exchange (costlier) only for the chosen count and next to a chosen fit found doubtful or
                # unexplained.
                wide = (chosen == h) | forced
            else:
                cand = cand & (chosen >= h)
                wide = chosen >= h
            readings = xp.nonzero(cand)
            if readings.shape[0] == 0:
                continue
            if solver.late():
                cut = xp.put(cut, readings, xp.ones((readings.shape[0],), "bool"))
                continue
            cur = states[h].take(xp, readings)
            limit = rules.suspect(h, readings)
            if rules.plausible is not None:  # rows next to a doubtful or unexplained answer: every fit is suspicious
                here = forced[readings]
                limit = (xp.where(here, 0.0, limit[0]), xp.where(here, 0.0, limit[1]))
            # The scan's other intervals for the count's last force.
            if scans[h][1] is not None and starts > 1:
                more = _scan_starts(xp, scans[h], readings, B, range(1, starts))
                cur, spent, short = _try_starts(problem, solver, options, cur, more)
                evaluations = xp.add_at(evaluations, readings, spent)
                cut = xp.put(cut, readings, cut[readings] | short)
            # If still suspicious: the exchange re-places every force.
            mine = xp.nonzero(wide[readings] & suspicious(problem, cur, limit))
            if h >= 2 and mine.shape[0]:
                best, spent, short = exchange(
                    problem, solver, cur.take(xp, mine), (limit[0][mine], limit[1][mine]), options
                )
                evaluations = xp.add_at(evaluations, readings[mine], spent)
                cut = xp.put(cut, readings[mine], cut[readings[mine]] | short)
                cur = cur.put(xp, mine, best)
            states[h] = states[h].put(xp, readings, cur)
    # L-BFGS for the chosen fits the Levenberg-Marquardt budget left open.
    chosen = rules.choose(xp.stack([s.loss for s in states], 1))
    for h in range(1, top_count + 1):
        mine = xp.nonzero(fitted[h] & (chosen == h))
        if mine.shape[0] and solver.late():  # no time to refine: the fits the LM left open stay open
            cut = xp.put(cut, mine, cut[mine] | ~states[h].converged[mine])
        elif mine.shape[0]:
            after, spent = solver.refine(problem, states[h].take(xp, mine))
            evaluations = xp.add_at(evaluations, mine, spent)
            states[h] = states[h].put(xp, mine, after)
    return CountFits(states=states, fitted=fitted, evaluations=evaluations, cut=cut)


def _scan_starts(xp: Any, scanned: tuple[Any, Scan], readings: Any, B: int, ranks: range) -> list[Fits]:
    """The starts of ``readings`` that a count's scan ranked ``ranks`` (0: its best interval), one block each;
    ``scanned``: the readings the scan ran on and the :class:`Scan`."""
    on, sc = scanned
    pos = xp.put(xp.zeros((B,), "int") - 1, on, xp.arange(on.shape[0]))[readings]
    return [sc.starts.take(t * on.shape[0] + pos) for t in ranks]


def _try_starts(
    problem: Problem, solver: Solver, options: SearchOptions, cur: lm.LMState, starts: list[Fits]
) -> tuple[lm.LMState, Any, Any]:
    """``cur`` (n fits, one per reading) with each fit replaced by the best of its ``starts`` (blocks of n rows,
    :func:`_explore`; a start that reaches the fit's intervals stops there) where that is lower by more than the
    solver's slack; also the evaluations spent and whether the deadline cut it short, per reading."""
    xp = problem.xp
    found, spent, short = _explore(problem, solver, options, starts, cur.loss, _home(xp, cur, options.twins))
    better = xp.nonzero(found.loss < cur.loss - 10.0 * solver.policy.tolerance * cur.noise2)
    if better.shape[0]:
        cur = cur.put(xp, better, found.take(xp, better))
    return cur, spent, short


def _explore(
    problem: Problem,
    solver: Solver,
    options: SearchOptions,
    starts: list[Fits],
    current: Any,
    home: Any = None,
) -> tuple[lm.LMState, Any, Any]:
    """The best of ``starts`` (blocks of n rows) per reading, fitted only while promising: each row takes at most
    ``options.explore`` steps, and only the rows whose loss, or the loss a Gauss-Newton step promises from it,
    has fallen below ``current`` (n,), the reading's loss to beat, are fitted to the end. Returns the best rows (n),
    finished on the exact model, the evaluations spent per reading and (n,) whether the deadline cut it short.

    ``home`` (n, h): the intervals of the reading's current fit (None: no such stop). The loss of one force has one
    local minimum within an interval (for small deflections the best force at a location is linear least squares,
    and the loss left is a ratio of two quadratic forms of a plane direction set by the location: one minimum per
    half-turn; ``test_one_force_has_one_minimum_per_interval`` checks it on misfits), so a row that enters the
    current fit's interval without a lower loss descends to that fit: it is dropped there. For more forces the same
    is assumed of a set of intervals (``SearchOptions.twins``, which also drops the twins among the rows of two or
    more forces, :func:`_twins`). A reading whose rows are all dropped has nothing better: its row gets an infinite
    loss and skips the exact-model steps (so the deadline cannot cut it there)."""
    xp = problem.xp
    n = starts[0].rows
    rows = _rows(starts)
    short = dataclasses.replace(
        solver,
        policy=dataclasses.replace(solver.policy, iterations=min(options.explore, solver.policy.iterations)),
        lbfgs=None,
    )
    goal = xp.concat([current] * len(starts))
    stop = None
    if home is not None:
        homes = _as_set(xp, xp.concat([home] * len(starts)))
        known = homes[:, 0] >= 0  # rows with a fit to go back to
        twins = _twins(xp, n, len(starts)) if home.shape[1] > 1 and len(starts) > 1 else None

        def stop(state: lm.LMState) -> Any:
            key = _as_set(xp, state.fits.interval)
            back = xp.all(key == homes, 1) & known & (state.loss >= goal)
            return back if twins is None else back | twins(state, key)

    st = short.solve(problem, rows, stop)
    cut = _cut(xp, st, n)
    dropped = xp.zeros((rows.rows,), "bool") if stop is None else stop(st) & ~st.converged
    # Promising: the loss, or what a Gauss-Newton step promises from it, is below the loss to beat.
    finite = xp.isfinite(st.decrement)
    promise = xp.where(finite, st.loss - xp.where(finite, st.decrement, 0.0), st.loss)
    going = xp.nonzero(~st.converged & ~dropped & (promise < goal) & (st.damping < solver.policy.max_damping))
    if going.shape[0]:
        part = st.take(xp, going)
        part = part.replace(done=part.steps >= solver.policy.iterations)
        st = st.put(xp, going, solver.solve(problem, part))
        cut = cut | _cut(xp, st, n)
    spent = (1 + st.steps).reshape(-1, n).sum(0)
    slack = 10.0 * solver.policy.tolerance * st.noise2[:n]
    pick = st.take(xp, best_of(xp, st, n, slack))
    live = ~xp.all(dropped.reshape(-1, n), 0)  # (n,) a reading with a row not dropped
    best = pick.replace(loss=xp.where(live, pick.loss, math.inf))
    at = xp.nonzero(live)
    late = False
    if at.shape[0]:
        done, late, used = solver.finish(problem, pick.take(xp, at))
        best = best.put(xp, at, done)
        spent = xp.add_at(spent, at, used)
    return best, spent, cut | (live & late)


def _first_fits(
    problem: Problem, solver: Solver, first: list[Fits], readings: Any, twins: bool = False
) -> tuple[lm.LMState, Any, Any]:
    """The best of the ``first`` starts per reading of ``readings`` (n,), finished on the exact model; the
    evaluations spent and (n,) whether the deadline cut a start short, per reading. A block holds a row for every
    one of the n readings, in their order, or (a network guess kept only where the network finds its count
    likely, :meth:`torchrod.Estimator.estimate`) rows for some of them, named by ``Fits.reading``; every reading
    has a row in some block. ``twins``: a row that another row of its reading joins with a lower loss stops
    (:func:`_twins`)."""
    xp = problem.xp
    n = readings.shape[0]
    dense = all(b.rows == n for b in first)
    slot = None
    if not dense:  # row r is reading slot[r] % n of block slot[r] // n
        at = xp.put(xp.zeros((problem.batch_size,), "int"), readings, xp.arange(n))
        slot = xp.concat([at[b.reading] + k * n for k, b in enumerate(first)])
    stop = _twins(xp, n, len(first), slot) if twins and len(first) > 1 else None
    st = solver.solve(problem, _rows(first), stop=stop)
    if dense:
        spent = (1 + st.steps).reshape(-1, n).sum(0)
        pick = best_of(xp, st, n, 10.0 * solver.policy.tolerance * st.noise2[:n])
        cut = _cut(xp, st, n)
    else:
        pos = slot % n
        spent = xp.add_at(xp.zeros((n,), "int"), pos, 1 + st.steps)
        # The slack from each reading's row in the first block that holds it, as the dense layout takes block 0's
        # (with the noise unknown a row's sigma^2 is its own): the same choice as without the skipped rows.
        blocks = len(first)
        held = xp.put(xp.zeros((blocks * n,), "bool"), slot, xp.ones((slot.shape[0],), "bool")).reshape(blocks, n)
        noise2 = xp.put(xp.zeros((blocks * n,)), slot, st.noise2).reshape(blocks, n)
        lowest = xp.argmin(xp.where(held, xp.astype(xp.arange(blocks), "float")[:, None], math.inf), 0)
        noise2 = xp.take(noise2, lowest[None, :], 0)[0]
        pick = best_of(xp, st, n, 10.0 * solver.policy.tolerance * noise2, (slot, blocks))
        cut = xp.add_at(xp.zeros((n,), "int"), pos, xp.astype(~st.done, "int")) > 0
    best, late, used = solver.finish(problem, st.take(xp, pick))
    return best, spent + used, cut | late


def _as_set(xp: Any, interval: Any) -> Any:
    """(R, h) each row's intervals in decreasing order: equal rows hold the same set of intervals; a row with two
    forces in one interval (where a set of intervals holds several minima) becomes -1s, equal to no row's."""
    key = xp.take(interval, xp.argsort_desc(interval), 1)
    if key.shape[1] < 2:
        return key
    repeated = xp.any(key[:, 1:] == key[:, :-1], 1)
    return xp.where(repeated[:, None], -1, key)


def _home(xp: Any, current: lm.LMState, twins: bool) -> Any:
    """The intervals (R, h) of the fits the wider search is to beat, for :func:`_explore`'s stop: with ``twins``
    those of the fits that converged in the open (-1 elsewhere: a start in the intervals of a fit still creeping
    towards its minimum may get there first, and a fit held on a bound is a minimum of its own beside the one
    inside); without, one force's of every fit (the one-force shortcut as it was), None for more forces."""
    if not twins:
        return current.fits.interval if current.fits.s.shape[1] == 1 else None
    inside = current.converged & ~xp.any(current.held, 1)
    return xp.where(inside[:, None], current.fits.interval, -1)


def _twins(xp: Any, n: int, blocks: int, slot: Any = None) -> Any:
    """A ``stop`` for :func:`.lm.solve` (module docstring, "Twins") on rows laid out in ``blocks`` blocks of n
    readings (``slot`` (R,): the layout of :func:`best_of` for blocks that hold some readings only): ``stop(state)``
    is (R,) True for each row that a row of the same reading in another block matches, the same set of intervals,
    with a lower loss (equal losses: the earlier block's row goes on). Rows with two forces in one interval or a
    location held on a bound of its interval match none: those have minima of their own beside the one inside."""

    def stop(state: lm.LMState, as_set: Any = None) -> Any:  # as_set: _as_set of the state's intervals, if known
        h = state.fits.s.shape[1]
        as_set = _as_set(xp, state.fits.interval) if as_set is None else as_set
        key = xp.where(xp.any(state.held, 1)[:, None], -1, as_set)
        loss = xp.where(state.loss == state.loss, state.loss, math.inf)
        if slot is None:
            key, loss = key.reshape(blocks, n, h), loss.reshape(blocks, n)
        else:  # absent rows: interval -1, matching none
            key = xp.put(xp.full((blocks * n, h), -1, "int"), slot, key).reshape(blocks, n, h)
            loss = xp.put(xp.full((blocks * n,), math.inf), slot, loss).reshape(blocks, n)
        present = key[:, :, 0] >= 0  # in distinct intervals, none held on a bound
        drop = [xp.zeros((n,), "bool") for _ in range(blocks)]
        for a in range(blocks):
            for b in range(a + 1, blocks):
                same = xp.all(key[a] == key[b], 1) & present[a] & present[b]
                drop[b] = drop[b] | (same & (loss[b] >= loss[a]))
                drop[a] = drop[a] | (same & (loss[a] > loss[b]))
        out = xp.concat(drop)
        return out if slot is None else out[slot]

    return stop


def _cut(xp: Any, state: lm.LMState, n: int) -> Any:
    """(n,) bool: a row of the reading (rows in blocks of n) that its solve left going (the deadline cut it)."""
    return xp.any(~state.done.reshape(-1, n), 0)
