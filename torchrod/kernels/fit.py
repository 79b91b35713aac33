"""One reading's least-squares fits: the residuals, the Levenberg-Marquardt policy and the exact-model finish.

A fit of h forces to a reading minimises ``loss = sum over present gratings of |u_model - u_measured|^2`` [1/m^2]
over each force's location s_i [m] and body-frame (f_x, f_y) [N]. The solver works in scaled unknowns (s / L,
f / F), F = EI / L^2, the scales at which the curvature is of order 1/L.

Intervals. A grating sees a force only while the force lies distal to it, so the residual is smooth in s_i
between two neighbouring present gratings and has a kink where s_i crosses one (dU_k/ds_i is 0 on the proximal
side, the slope jump i (f_x + i f_y) / EI on the distal side). Each force carries the index of its interval between
the reading's present gratings and stays in it while a step moves it; a force on a bound has its own interval's
one-sided derivative (:func:`sided`). Crossing a grating is a decision of :func:`analyse`.

One Levenberg-Marquardt iteration of a row (a fit held in the ``rows`` group of :data:`.search.SEARCH_PARTS`,
seen through :func:`torchrod.kernels.views.rows_of`):

1. :func:`analyse`: a force on (or within :data:`SNAP` of) a bound whose loss falls by leaving the interval is
   held there, unless the loss also falls beyond the grating: then it crosses into the neighbouring interval.
   The Gauss-Newton decrement (what a step promises, held locations fixed) decides convergence: at most
   ``tolerance`` x sigma^2. A fit is also done after its step limit, or when the damping reaches its ceiling.
2. :func:`step`: the damped Gauss-Newton step ``(A + lambda diag A) dx = -g`` (A = J^T J), shortened so that no
   force changes by more than ``max_force_step`` (units F), locations clipped to their intervals; a force whose
   step points out of its interval from a bound is held too; the geodesic acceleration corrects the step when the
   last one was curved. One evaluation at the trial point: accepted if the loss falls (damping / ``decrease``),
   else rejected (damping x ``increase``).

The fitting model is the fast fourth-order march (~1e-4 of the curvature); :func:`finish` then takes Gauss-Newton
steps on the exact model's residual (~1e-9) with the fitting model's Jacobian and reports that residual and loss,
so the count tests and the verdict judge the physics.
"""

import math

from .linalg import spd_solve, sumsq
from .march import march_exact, march_fit, slope_jump
from .precurved import EXACT_MAX_STEP, FIT_MAX_STEP, march_precurved
from .views import lm_of, march_of, model_of, reading_of, rows_of

FIT_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "lm": {  # one Levenberg-Marquardt step's work
        "lo": (("W",), "f"), "hi": (("W",), "f"), "Js": (("n", "P"), "f"), "free": (("P",), "f"),
        "gi": (("P",), "f"), "near_lo": (("W",), "b"), "near_hi": (("W",), "b"), "new_int": (("W",), "i"),
        "new_s": (("W",), "f"), "M": (("P", "P"), "f"), "L": (("P", "P"), "f"), "x": (("P",), "f"),
        "A": (("P", "P"), "f"), "prop": (("P",), "f"), "v": (("P",), "f"), "dx": (("P",), "f"), "pv": (("P",), "f"),
        "st": (("W",), "f"), "ft": (("W", 2), "f"), "rt": (("n",), "f"), "Jt": (("n", "P"), "f"),
        "taken": (("P",), "f"), "rv": (("n",), "f"), "rhs": (("P",), "f"), "tail": (("P",), "i"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

FLOOR = 1e-12
"""Every damped system adds this fraction of its largest diagonal entry to its diagonal."""

SCALE_MIN = 1e-300
"""The least scale (largest diagonal entry) :data:`FLOOR` is taken of: a system of zeros still gets a diagonal."""

TINY = 1e-9
"""The damping of the system that gives the Gauss-Newton decrement and of the exact model's steps: next to none,
so that a nearly singular system still solves."""

SNAP = 1e-3
"""A force within this fraction of its interval's length from a bound counts as on that bound for the decision to
cross the grating there: an interval's own optimum micrometres from the grating, with the loss falling on the far
side, must not hide the better interval next to it."""

KINK = 1e-6
"""[m] a force this close to a present grating sits on the loss's kink there."""

INLINE = (
    "late",
    "march_model",
    "bounds",
    "gradient",
    "gram",
    "noise2_of",
    "start",
    "shortened",
    "moved",
    "sided",
    "damped",
)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def late(k):
    """Whether the reading's search must stop: the caller's stop flag (a deadline passed) or its evaluation
    budget spent."""
    if k.flag[0] != 0:
        return True
    budget = k.opt.max_evaluations
    return budget > 0 and k.info[0].evaluations >= budget


def march_model(k, query, Q, s, f, h, F, seeds, exact):
    """The rod's forward model at ``Q`` queries into the march views' curv (and jac with F = 3h, phi with seeds):
    the fitting model, or with ``exact`` the exact one (no tangents); counted as one evaluation."""
    k.info[0].evaluations += 1
    if k.rod.precurved:
        return march_precurved(k, query, Q, s, f, h, F, seeds, EXACT_MAX_STEP if exact else FIT_MAX_STEP)
    if exact:
        return march_exact(k, query, Q, s, f, h)
    return march_fit(k, query, Q, s, f, h, F, seeds)


def evaluate(k, s, f, h, jacobian, exact, r, J):
    """Residuals r (n,) [1/m] of forces (s, f) (zero at missing gratings) and, with ``jacobian``, their Jacobian
    J (n, 3h) in the scaled unknowns, in the march's convention at ties (distal one-sided). Returns the loss
    (inf where not finite)."""
    G = k.rod.num_gratings
    F = 3 * h if jacobian else 0
    march_model(k, model_of(k).query, G, s, f, h, F, False, exact)
    u = k.u
    w = k.w
    mw = march_of(k)
    curv = mw.curv
    jac = mw.jac
    L = k.rod.length
    FU = k.rod.force_unit
    for g in range(G):
        for c in range(2):
            m = 2 * g + c
            r[m] = (curv[g, c] - u[m]) * w[m]
            for p in range(F):
                J[m, p] = jac[g, c, p] * (L if p % 3 == 0 else FU) * w[m]
    loss = sumsq(r, 2 * G)
    return loss if math.isfinite(loss) else math.inf


def bounds(k, interval, h, lo, hi):
    """lo, hi (h,) [m]: the bounds of each force's interval."""
    rd = reading_of(k)
    for j in range(h):
        lo[j] = rd.lo[interval[j]]
        hi[j] = rd.hi[interval[j]]


def sided(k, J, s, hi, interval, h, n, out):
    """out = J with each force's own one-sided derivative at the upper bound of its interval: a force on it lies
    proximal to the grating that closes the interval, which does not see it move (zero s-entries there)."""
    rd = reading_of(k)
    for m in range(n):
        for p in range(3 * h):
            out[m, p] = J[m, p]
    for j in range(h):
        g = rd.hi_k[interval[j]]
        if s[j] == hi[j] and g >= 0:
            out[2 * g, 3 * j] = 0.0
            out[2 * g + 1, 3 * j] = 0.0


def gradient(J, r, n, P, g):
    """g = J^T r over P columns."""
    for p in range(P):
        t = 0.0
        for m in range(n):
            t += J[m, p] * r[m]
        g[p] = t


def gram(J, n, P, A, tail):
    """A = J^T J over P columns. A force moves only the gratings proximal to it, so each column ends in zero rows:
    the sums stop where either column's last nonzero row is (``tail`` (P,), scratch). That is exactly the full sums
    when J is finite (the terms left out are zeros); where it is not, the sums are full. Returns whether J is
    finite."""
    finite = True
    for p in range(P):
        last = n
        while last > 0 and J[last - 1, p] == 0.0:
            last -= 1
        tail[p] = last
        for m in range(last):
            finite = finite and math.isfinite(J[m, p])
    for p in range(P):
        for q in range(p, P):
            rows = n
            if finite:
                rows = tail[p] if tail[p] < tail[q] else tail[q]
            t = 0.0
            for m in range(rows):
                t += J[m, p] * J[m, q]
            A[p, q] = t
            A[q, p] = t
    return finite


def damped(A, free, P, damping, out):
    """out = A + damping diag A + FLOOR max diag A, with the largest diagonal entry for each unknown that does
    not move (``free`` 0.0)."""
    scale = SCALE_MIN
    for p in range(P):
        d = A[p, p]
        if d != d or d > scale:
            scale = d
    for p in range(P):
        for q in range(P):
            out[p, q] = A[p, q]
        d = A[p, p]
        out[p, p] = d + damping * d + (FLOOR * scale + (1.0 - free[p]) * scale)


def noise2_of(k, loss, h):
    """sigma^2 [1/m^2] a fit of h forces is measured against: the reading's given one, or (noise unknown) the
    fit's own loss per degree of freedom, at least the floor^2."""
    info = k.info[0]
    if info.known:
        return info.noise2
    dof = info.residuals - 3 * h
    v = loss / (dof if dof > 1 else 1.0)
    return v if (v != v or v >= k.opt.floor2) else k.opt.floor2


def analyse(k, i, limit):
    """Crossings, held locations, the decrement, the stopping tests and the next step's proposal of row i at its
    current point (module docstring, step 1); ``limit``: the row's step limit."""
    rows = rows_of(k)
    lw = lm_of(k)
    rd = reading_of(k)
    opt = k.opt
    G = k.rod.num_gratings
    n = 2 * G
    h = rows.count[i]
    P = 3 * h
    s = rows.s[i]
    f = rows.f[i]
    interval = rows.interval[i]
    r = rows.r[i]
    lo = lw.lo
    hi = lw.hi
    Js = lw.Js
    free = lw.free
    gi = lw.gi
    bounds(k, interval, h, lo, hi)
    sided(k, rows.J[i], s, hi, interval, h, n, Js)
    for p in range(P):
        free[p] = 1.0
    gradient(Js, r, n, P, gi)
    near = False
    for j in range(h):
        tol = SNAP * (hi[j] - lo[j])
        lw.near_lo[j] = s[j] - lo[j] <= tol
        lw.near_hi[j] = hi[j] - s[j] <= tol
        near = near or lw.near_lo[j] or lw.near_hi[j]
        rows.held[i, j] = False
    if near:
        scale = k.rod.length / k.rod.ei
        m_int = k.info[0].intervals
        cross = False
        for j in range(h):
            jc = slope_jump(f[j, 0], f[j, 1], scale)  # the slope jump's grating entries, per unit s / L
            jc0 = jc.real
            jc1 = jc.imag
            g_lo = rd.lo_k[interval[j]]
            g_hi = rd.hi_k[interval[j]]
            c_lo = 0.0
            c_hi = 0.0
            if lw.near_lo[j] and g_lo >= 0:
                c_lo = r[2 * g_lo] * jc0 + r[2 * g_lo + 1] * jc1
            if lw.near_hi[j] and g_hi >= 0:
                c_hi = r[2 * g_hi] * jc0 + r[2 * g_hi + 1] * jc1
            g_s = gi[3 * j]
            at_lo = s[j] == lo[j]
            at_hi = s[j] == hi[j]
            # Leave the interval where the loss falls on both sides of the bound's grating.
            down = lw.near_lo[j] and (g_s >= 0.0 or not at_lo) and interval[j] > 0 and g_s - c_lo > 0.0
            up = lw.near_hi[j] and (g_s <= 0.0 or not at_hi) and interval[j] < m_int - 1 and g_s + c_hi < 0.0
            lw.new_int[j] = interval[j]
            lw.new_s[j] = s[j]
            if down or up:
                lw.new_int[j] = interval[j] - (1 if down else 0) + (1 if up else 0)
                lw.new_s[j] = lo[j] if down else hi[j]
                cross = True
        if cross:
            moved = False
            for j in range(h):
                moved = moved or lw.new_s[j] != s[j]
                s[j] = lw.new_s[j]
                interval[j] = lw.new_int[j]
            if moved:  # snapped onto the grating: the residuals there, exactly
                rows.loss[i] = evaluate(k, s, f, h, True, False, r, rows.J[i])
            bounds(k, interval, h, lo, hi)
            sided(k, rows.J[i], s, hi, interval, h, n, Js)
            gradient(Js, r, n, P, gi)
        for j in range(h):
            g_s = gi[3 * j]
            held = (s[j] == lo[j] and g_s >= 0.0) or (s[j] == hi[j] and g_s <= 0.0)
            rows.held[i, j] = held
            if held:
                free[3 * j] = 0.0
        for m in range(n):
            for p in range(P):
                Js[m, p] = Js[m, p] * free[p]
        for p in range(P):
            gi[p] = gi[p] * free[p]
    A = rows.A[i]
    gram(Js, n, P, A, lw.tail)
    for p in range(P):
        rows.g[i, p] = gi[p]
    damped(A, free, P, TINY, lw.M)
    if spd_solve(lw.M, gi, lw.x, P, lw.L):
        t = 0.0
        for p in range(P):
            t += gi[p] * lw.x[p]
        rows.decrement[i] = t
    else:
        rows.decrement[i] = math.inf
    damped(A, free, P, rows.damping[i], lw.M)
    spd_solve(lw.M, gi, lw.x, P, lw.L)
    for p in range(P):
        rows.proposal[i, p] = -lw.x[p]
    rows.noise2[i] = noise2_of(k, rows.loss[i], h)
    rows.converged[i] = rows.decrement[i] <= opt.tolerance * rows.noise2[i]
    rows.done[i] = rows.converged[i] or rows.steps[i] >= limit or rows.damping[i] >= opt.max_damping


def start(k, i, limit):
    """Row i at its forces: one evaluation, the damping reset, analysed."""
    rows = rows_of(k)
    h = rows.count[i]
    rows.loss[i] = evaluate(k, rows.s[i], rows.f[i], h, True, False, rows.r[i], rows.J[i])
    rows.damping[i] = k.opt.damping
    rows.steps[i] = 0
    rows.ratio[i] = 1.0
    rows.converged[i] = False
    rows.done[i] = False
    analyse(k, i, limit)


def shortened(dx, P, max_force_step, out):
    """out = dx shortened so that no force component moves by more than ``max_force_step`` (units F)."""
    big = -math.inf
    for p in range(P):
        if p % 3 != 0:
            a = abs(dx[p])
            if a != a or a > big:
                big = a
    d = big / max_force_step
    if not (d != d) and d < 1.0:
        d = 1.0
    for p in range(P):
        out[p] = dx[p] / d


def moved(k, s, f, lo, hi, dx, h, s_out, f_out):
    """(s_out, f_out): the forces moved by dx (scaled units), each location clipped to its interval."""
    L = k.rod.length
    FU = k.rod.force_unit
    for j in range(h):
        v = s[j] + dx[3 * j] * L
        if v < lo[j]:
            v = lo[j]
        if v > hi[j]:
            v = hi[j]
        s_out[j] = v
        f_out[j, 0] = f[j, 0] + dx[3 * j + 1] * FU
        f_out[j, 1] = f[j, 1] + dx[3 * j + 2] * FU


def step(k, i, limit):
    """One Levenberg-Marquardt step of row i (module docstring, step 2), then :func:`analyse`."""
    rows = rows_of(k)
    lw = lm_of(k)
    opt = k.opt
    G = k.rod.num_gratings
    n = 2 * G
    h = rows.count[i]
    P = 3 * h
    s = rows.s[i]
    f = rows.f[i]
    interval = rows.interval[i]
    L = k.rod.length
    FU = k.rod.force_unit
    lo = lw.lo
    hi = lw.hi
    bounds(k, interval, h, lo, hi)
    A = lw.A
    gi = lw.gi
    prop = lw.prop
    free = lw.free
    for p in range(P):
        gi[p] = rows.g[i, p]
        prop[p] = rows.proposal[i, p]
        for q in range(P):
            A[p, q] = rows.A[i, p, q]
    out = False
    for j in range(h):
        held = rows.held[i, j]
        ds = prop[3 * j]
        if (s[j] == lo[j] and ds < 0.0) or (s[j] == hi[j] and ds > 0.0):
            held = True
            out = True
        free[3 * j] = 0.0 if held else 1.0
        free[3 * j + 1] = 1.0
        free[3 * j + 2] = 1.0
    if out:
        # A force on a bound whose step points out of its interval is held there too, and the step recomputed.
        for p in range(P):
            for q in range(P):
                A[p, q] = A[p, q] * free[p] * free[q]
            gi[p] = gi[p] * free[p]
        damped(A, free, P, rows.damping[i], lw.M)
        spd_solve(lw.M, gi, lw.x, P, lw.L)
        for p in range(P):
            prop[p] = -lw.x[p]
    v = lw.v
    dx = lw.dx
    shortened(prop, P, opt.max_force_step, v)
    for p in range(P):
        dx[p] = v[p]
    if rows.ratio[i] < opt.acceleration:
        # Geodesic acceleration: the residual's second derivative along v by a finite difference, and the
        # correction it asks for, taken when small against v.
        for p in range(P):
            lw.pv[p] = opt.probe * v[p]
        moved(k, s, f, lo, hi, lw.pv, h, lw.st, lw.ft)
        evaluate(k, lw.st, lw.ft, h, False, False, lw.rt, lw.Jt)
        for j in range(h):
            lw.taken[3 * j] = ((lw.st[j] - s[j]) / L) / opt.probe
            lw.taken[3 * j + 1] = ((lw.ft[j, 0] - f[j, 0]) / FU) / opt.probe
            lw.taken[3 * j + 2] = ((lw.ft[j, 1] - f[j, 1]) / FU) / opt.probe
        Js = lw.Js
        sided(k, rows.J[i], s, hi, interval, h, n, Js)
        finite = True
        r_vv = lw.rv
        for m in range(n):
            t = 0.0
            for p in range(P):
                Js[m, p] = Js[m, p] * free[p]
                t += Js[m, p] * lw.taken[p]
            r_vv[m] = (2.0 / opt.probe) * ((lw.rt[m] - rows.r[i, m]) / opt.probe - t)
            finite = finite and math.isfinite(r_vv[m])
        gradient(Js, r_vv, n, P, lw.rhs)
        damped(A, free, P, rows.damping[i], lw.M)
        ok_a = spd_solve(lw.M, lw.rhs, lw.x, P, lw.L)
        if ok_a and finite and 2.0 * math.sqrt(sumsq(lw.x, P)) <= opt.acceleration_limit * math.sqrt(sumsq(v, P)):
            for p in range(P):
                lw.pv[p] = v[p] - 0.5 * lw.x[p]
            shortened(lw.pv, P, opt.max_force_step, dx)
    moved(k, s, f, lo, hi, dx, h, lw.st, lw.ft)
    loss_t = evaluate(k, lw.st, lw.ft, h, True, False, lw.rt, lw.Jt)
    better = loss_t < rows.loss[i]
    for j in range(h):
        lw.taken[3 * j] = (lw.st[j] - s[j]) / L
        lw.taken[3 * j + 1] = (lw.ft[j, 0] - f[j, 0]) / FU
        lw.taken[3 * j + 2] = (lw.ft[j, 1] - f[j, 1]) / FU
    promised = 0.0  # -(2 g.dx + dx^T A dx): the decrease the Gauss-Newton model promised for the step taken
    for p in range(P):
        a = 0.0
        for q in range(P):
            a += A[p, q] * lw.taken[q]
        promised -= 2.0 * gi[p] * lw.taken[p] + lw.taken[p] * a
    if better and promised > 0.0:
        rows.ratio[i] = (rows.loss[i] - loss_t) / promised
    else:
        rows.ratio[i] = 0.0
    if better:
        for j in range(h):
            s[j] = lw.st[j]
            f[j, 0] = lw.ft[j, 0]
            f[j, 1] = lw.ft[j, 1]
        for m in range(n):
            rows.r[i, m] = lw.rt[m]
            for p in range(P):
                rows.J[i, m, p] = lw.Jt[m, p]
        rows.loss[i] = loss_t
        d = rows.damping[i] / opt.decrease
        rows.damping[i] = d if d >= opt.min_damping else opt.min_damping
    else:
        d = rows.damping[i] * opt.increase
        rows.damping[i] = d if d <= opt.max_damping else opt.max_damping
    rows.steps[i] += 1
    analyse(k, i, limit)


def finish(k, i, exact_steps):
    """Row i moved to the exact model's optimum: its residual and loss from the exact model, then up to
    ``exact_steps`` Gauss-Newton steps on it with the fitting model's Jacobian, each taken only where it promises
    more than ``exact_tolerance`` x sigma^2 and lowers the loss (module docstring)."""
    rows = rows_of(k)
    lw = lm_of(k)
    opt = k.opt
    G = k.rod.num_gratings
    n = 2 * G
    h = rows.count[i]
    P = 3 * h
    s = rows.s[i]
    f = rows.f[i]
    r = rows.r[i]
    if h == 0 and not k.rod.precurved:  # no force: the straight rod stays straight
        for m in range(n):
            r[m] = -k.u[m] * k.w[m]
        rows.loss[i] = sumsq(r, n)
        return
    rows.loss[i] = evaluate(k, s, f, h, False, True, r, lw.Jt)
    if h == 0:
        return
    lo = lw.lo
    hi = lw.hi
    bounds(k, rows.interval[i], h, lo, hi)
    Js = lw.Js
    sided(k, rows.J[i], s, hi, rows.interval[i], h, n, Js)
    for j in range(h):
        lw.free[3 * j] = 0.0 if rows.held[i, j] else 1.0
        lw.free[3 * j + 1] = 1.0
        lw.free[3 * j + 2] = 1.0
    for m in range(n):
        for p in range(P):
            Js[m, p] = Js[m, p] * lw.free[p]
    gram(Js, n, P, lw.A, lw.tail)
    damped(lw.A, lw.free, P, TINY, lw.M)
    for _ in range(exact_steps):
        gradient(Js, r, n, P, lw.gi)
        dec = math.inf
        if spd_solve(lw.M, lw.gi, lw.x, P, lw.L):
            dec = 0.0
            for p in range(P):
                dec += lw.gi[p] * lw.x[p]
        if dec <= opt.exact_tolerance * noise2_of(k, rows.loss[i], h):
            break  # what is left is a sliver of the standard deviation
        for p in range(P):
            lw.dx[p] = -lw.x[p]
        moved(k, s, f, lo, hi, lw.dx, h, lw.st, lw.ft)
        loss_t = evaluate(k, lw.st, lw.ft, h, False, True, lw.rt, lw.Jt)
        if not loss_t < rows.loss[i]:
            break
        for j in range(h):
            s[j] = lw.st[j]
            f[j, 0] = lw.ft[j, 0]
            f[j, 1] = lw.ft[j, 1]
        for m in range(n):
            r[m] = lw.rt[m]
        rows.loss[i] = loss_t
