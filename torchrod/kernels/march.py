"""The straight rod's marches for one force set: the schedule of events, the fitting model with its tangents and
propagator, and the exact model.

Equations (docs/physics.md): with U = u_x + i u_y and t = L - s, U_tt = -|U|^2 U / 2 between forces, U = U_t = 0
at the free tip, and at a force (f_x, f_y) at s_i the slope W = U_t jumps by J_i = i (f_x + i f_y) / EI.

The schedule (:func:`schedule`) fixes, for every march of the estimator:

* the events and their order: sorted by position from the tip to the base; at equal positions a force comes
  before a query (the query reads the state after the jump: a grating at a force sees it move, the distal
  one-sided derivative in s);
* the segments between consecutive events, and the steps on each: ``ceil(rate x segment / step_angle)``, at
  least 1, at most ``max_steps``, where the rate bounds the solution's local rate max(|U|, sqrt|m|) [1/m] at the
  segment's proximal end. Rule ``bound`` (the exact model's, rigorous): |m| is at most the sum of the distal
  |f_i| / EI, and |U| at most min(sum |f_i| (s_i - s)^+ / EI, sqrt(2 M)). Rule ``estimate`` (the fitting
  model's): the same terms with vector sums of the complex jumps, so that opposed forces cancel;
* the events distal to every force need no steps: the state there is zero.

The fitting model (:func:`march_fit`) is the classical three-stage fourth-order Runge-Kutta-Nystrom method, which
also carries the tangents of the discrete scheme: for each force the derivatives with respect to (s_i, f_x, f_y)
(the jump itself starts the s-column, i / EI and -1 / EI the f-columns' slopes), and with ``seeds`` the propagator
of the linearised equation from the tip (four unit perturbations of (U, W)). Every stage is linear in the tangents
with the same coefficients, so each step computes its real-linear map once and applies it to every column.

The exact model (:func:`march_exact`) is the eighth-order method whose tableau :mod:`torchrod.model.nystrom`
defines (passed in as arrays), on the rigorous rule: accurate to about 1e-9 of the curvature.
"""

import math

from .views import march_of, model_of

MARCH_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "model": {  # the rod: grating positions [m], the exact model's tableau, the intrinsic curvature
        "query": (("G",), "k"), "tab_c": (("S",), "k"), "tab_a": (("S", "S"), "k"), "tab_bp": (("S",), "k"),
        "tab_bv": (("S",), "k"), "segments": (("NSEG", 4), "k"), "extra": (("NX",), "k"),
    },
    "march": {  # the marches' outputs and their straight-rod work
        "curv": (("Q", 2), "f"), "jac": (("Q", 2, "P"), "f"), "phi": (("Q", 8, 6), "f"),
        "order": (("E",), "i"), "seg": (("E",), "f"), "steps": (("E",), "i"), "jump": (("W",), "c"),
        "mag": (("W",), "f"), "du": (("NC",), "c"), "dw": (("NC",), "c"), "carried": (("NC",), "b"),
        "ys": (("S",), "c"), "gs": (("S",), "c"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

INLINE = ("slope_jump", "event_position")

FIT_STEP_ANGLE = 0.3
"""Default bound on (local rate) x (step) of the fitting model. Over the synthetic envelope (1-3 forces, 0.05-2 N,
bending up to 90 degrees) the curvature at the gratings is within about 5e-4 1/m of the converged solution, a
twentieth of the estimator's noise floor."""

FIT_MAX_STEPS = 12
"""Most steps of the fitting model on one segment (a trial point far off needs no accuracy)."""

EXACT_STEP_ANGLE = 0.8
"""Bound on (local rate) x (step) of the exact model (and the simulator's default): the curvature within about 5e-8
of a converged reference relative to its largest value, at deflections of 90 degrees and more."""

EXACT_MAX_STEPS = 64
"""Most steps of the exact model on one segment."""


def slope_jump(fx, fy, inv):
    """The jump of the slope W = U_t across a force (fx, fy) [N], going towards the base: i (fx + i fy) / EI, with
    ``inv`` = 1 / EI [1/(N m^2)] (or any scale in its place)."""
    return complex(-fy * inv, fx * inv)


def event_position(s, query, extra, h, Q, e):
    """The position [m] of event e: force e (e < h), query e - h, or ``extra[e - h - Q]``."""
    if e < h:
        return s[e]
    if e < h + Q:
        return query[e - h]
    return extra[e - h - Q]


def event_order(query, Q, extra, X, s, h, order):
    """The ``h`` forces at ``s``, the ``Q`` queries and ``X`` extra events (the precurved rod's base and segment
    ends) sorted tip to base into ``order`` (h + Q + X,): an index < h for a force, ``h + q`` for query q,
    ``h + Q + x`` for extra event x; by position, descending, and at equal positions by that index (a force before
    a query). Queries in at most two strictly increasing runs (a rod's gratings; the scan's gratings, then its
    candidates) and increasing extra events are merged with the sorted forces in one pass; others, or a NaN
    anywhere, are insertion-sorted. Both give the one order the rule defines."""
    E = h + Q + X
    split = Q  # the second run's first query (Q: one run)
    merge = True
    for q in range(Q):
        if query[q] != query[q]:
            merge = False
        elif q > 0 and not query[q] > query[q - 1]:
            if split < Q:
                merge = False
            split = q
    for x in range(X):
        if not (extra[x] == extra[x] and (x == 0 or extra[x] > extra[x - 1])):
            merge = False
    for j in range(h):
        if s[j] != s[j]:
            merge = False
    if not merge:
        for e in range(E):
            order[e] = e
        for i in range(1, E):  # stable insertion sort, descending: the lower index first at a tie
            k = order[i]
            p = event_position(s, query, extra, h, Q, k)
            j = i
            while j > 0:
                o = order[j - 1]
                if event_position(s, query, extra, h, Q, o) >= p:
                    break
                order[j] = o
                j -= 1
            order[j] = k
        return
    # The forces sorted into the last h places (stable, descending); then each place from the first takes the
    # largest of the next force and of the runs read backwards (at a tie the lower index: a force, then the first
    # run, the second, the extra events). The place written is never after the next force's, so no force is
    # overwritten before it is taken.
    first = E - h
    for j in range(h):
        i = first + j
        while i > first and s[order[i - 1]] < s[j]:
            order[i] = order[i - 1]
            i -= 1
        order[i] = j
    fi = first
    a = split - 1
    b = Q - 1
    x = X - 1
    for e in range(E):
        pick = -1
        best = 0.0
        if fi < E:
            pick = 0
            best = s[order[fi]]
        if a >= 0 and (pick < 0 or query[a] > best):
            pick = 1
            best = query[a]
        if b >= split and (pick < 0 or query[b] > best):
            pick = 2
            best = query[b]
        if x >= 0 and (pick < 0 or extra[x] > best):
            pick = 3
        if pick == 0:
            order[e] = order[fi]
            fi += 1
        elif pick == 1:
            order[e] = h + a
            a -= 1
        elif pick == 2:
            order[e] = h + b
            b -= 1
        else:
            order[e] = h + Q + x
            x -= 1


def schedule(query, Q, s, jump, mag, h, length, step_angle, max_steps, bound, order, seg, steps):
    """The events of ``h`` forces at ``s`` and ``Q`` queries, tip to base (module docstring): ``order`` (E,) an
    index < h for a force, ``h + q`` for query q; ``seg`` (E,) [m] the segment ending at each event; ``steps`` (E,)
    its steps (0 distal to every force). ``jump`` (h,) complex slope jumps [1/m^2] (rule ``estimate``), ``mag`` (h,)
    their magnitudes |f| / EI (rule ``bound``)."""
    E = h + Q
    event_order(query, Q, query, 0, s, h, order)
    start = length
    reached = False
    cap = float(max_steps)
    for e in range(E):
        idx = order[e]
        p = s[idx] if idx < h else query[idx - h]
        d = start - p
        if not d >= 0.0:
            d = 0.0
        seg[e] = d
        start = p
        if not reached:  # nothing loads the rod distal to here: the state is zero and needs no step
            if idx < h:
                reached = True
                steps[e] = 1
            else:
                steps[e] = 0
            continue
        ar = 0.0
        ai = 0.0
        mr = 0.0
        mi = 0.0
        for i in range(h):
            lever = s[i] - p
            if lever > 0.0:  # distal forces only (the ones the march has passed)
                if bound:
                    ar += mag[i] * lever
                    mr += mag[i]
                else:
                    ar += jump[i].real * lever
                    ai += jump[i].imag * lever
                    mr += jump[i].real
                    mi += jump[i].imag
        if bound:
            r2 = math.sqrt(2.0 * mr)
            u = ar if ar <= r2 else r2
            rm = math.sqrt(mr)
            rate = u if u >= rm else rm
        else:
            ra = math.sqrt(ar * ar + ai * ai)  # (not hypot: the same number on every target)
            rm = math.sqrt(math.sqrt(mr * mr + mi * mi))
            rate = ra if ra >= rm else rm
        need = rate * d / step_angle
        if need != need:
            steps[e] = 1
        elif need >= cap:
            steps[e] = max_steps if max_steps > 1 else 1
        else:
            n = int(math.ceil(need))
            steps[e] = n if n > 1 else 1


def schedule_rows(query, s, f, ei, length, step_angle, max_steps, order, seg, steps, jump, mag):
    """:func:`schedule` of every row b of forces s (B, h) [m], f (B, h, 2) [N] at the queries (Q,) [m] with the
    rigorous ``bound`` rule (the simulator's), into order, seg and steps (B, E); ``ei`` (B,) [N m^2] each row's
    stiffness; jump (h,) and mag (h,) scratch."""
    B = s.shape[0]
    h = s.shape[1]
    Q = query.shape[0]
    for b in range(B):
        inv = 1.0 / ei[b]
        for j in range(h):
            jump[j] = slope_jump(f[b, j, 0], f[b, j, 1], inv)
            mag[j] = math.sqrt(f[b, j, 0] * f[b, j, 0] + f[b, j, 1] * f[b, j, 1]) * inv
        schedule(query, Q, s[b], jump, mag, h, length, step_angle, max_steps, True, order[b], seg[b], steps[b])


def march_fit(k, query, Q, s, f, h, F, seeds):
    """The fitting model of the straight rod at ``Q`` queries, into the march views: curvature ``curv`` (Q, 2)
    [1/m]; with ``F`` = 3h the Jacobian ``jac`` (Q, 2, F) w.r.t. each force's (s [m], f_x [N], f_y [N]); with
    ``seeds`` the propagator ``phi`` (Q, 4, 4): rows (Re dU, Im dU, Re dW, Im dW) at the query, columns the same at
    the tip. False where an input is not finite (the outputs are then NaN)."""
    rod = k.rod
    mw = march_of(k)
    curv = mw.curv
    jac = mw.jac
    phi = mw.phi
    ei = rod.ei
    inv = 1.0 / ei
    ok = True
    for j in range(h):
        mw.jump[j] = slope_jump(f[j, 0], f[j, 1], inv)
        ok = ok and math.isfinite(s[j]) and math.isfinite(f[j, 0]) and math.isfinite(f[j, 1])
    for q in range(Q):
        ok = ok and math.isfinite(query[q])
    if not ok:
        for q in range(Q):
            curv[q, 0] = math.nan
            curv[q, 1] = math.nan
            for c in range(F):
                jac[q, 0, c] = math.nan
                jac[q, 1, c] = math.nan
        return False
    schedule(query, Q, s, mw.jump, mw.mag, h, rod.length, rod.step_angle, rod.max_steps, False, mw.order, mw.seg,
             mw.steps)  # fmt: skip
    du = mw.du
    dw = mw.dw
    carried = mw.carried
    C = F + 4
    for c in range(C):
        du[c] = 0j
        dw[c] = 0j
        carried[c] = False
    if seeds:
        du[F] = 1.0
        du[F + 1] = 1j
        dw[F + 2] = 1.0
        dw[F + 3] = 1j
        for c in range(F, C):
            carried[c] = True
    anything = seeds
    u0 = 0j
    w0 = 0j
    d_fx = slope_jump(1.0, 0.0, inv)  # the jump's derivatives in f_x and f_y
    d_fy = slope_jump(0.0, 1.0, inv)
    for e in range(h + Q):
        idx = mw.order[e]
        n = mw.steps[e]
        if n == 0 and anything:
            # The zero state's tangent map over the segment is exactly linear: the seeds move as dU += seg dW.
            for c in range(C):
                if carried[c]:
                    du[c] = du[c] + mw.seg[e] * dw[c]
        hs = 0.0
        if n:
            hs = mw.seg[e] / n
        ch = 0.5 * hs
        k16 = -hs * hs / 16.0
        k4 = -hs * hs / 4.0
        k12 = -hs * hs / 12.0
        kw = -hs / 12.0
        for _ in range(n):
            a1 = u0.real * u0.real + u0.imag * u0.imag
            q1 = u0 * u0
            g1 = a1 * u0
            y0 = u0 + ch * w0 + k16 * g1
            a2 = y0.real * y0.real + y0.imag * y0.imag
            q2 = y0 * y0
            g2 = a2 * y0
            p0 = u0 + hs * w0
            y0 = p0 + k4 * g2
            a3 = y0.real * y0.real + y0.imag * y0.imag
            q3 = y0 * y0
            g3 = a3 * y0
            u0 = p0 + k12 * (g1 + 2.0 * g2)
            w0 = w0 + kw * (g1 + 4.0 * g2 + g3)
            if not anything:
                continue
            # The step's tangent map: dU' = ya dU + yb conj(dU) + yc dW + yd conj(dW), dW' likewise (each stage's
            # tangent is 2 |y|^2 x + y^2 conj(x)).
            t1a = 2.0 * a1
            t1b = q1
            s2a = 1.0 + k16 * t1a
            s2b = k16 * t1b
            c2 = 2.0 * a2
            t2a = c2 * s2a + q2 * s2b.conjugate()
            t2b = c2 * s2b + q2 * s2a.conjugate()
            t2c = c2 * ch
            t2d = q2 * ch
            s3a = 1.0 + k4 * t2a
            s3b = k4 * t2b
            s3c = hs + k4 * t2c
            s3d = k4 * t2d
            c3 = 2.0 * a3
            t3a = c3 * s3a + q3 * s3b.conjugate()
            t3b = c3 * s3b + q3 * s3a.conjugate()
            t3c = c3 * s3c + q3 * s3d.conjugate()
            t3d = c3 * s3d + q3 * s3c.conjugate()
            ya = 1.0 + k12 * (t1a + 2.0 * t2a)
            yb = k12 * (t1b + 2.0 * t2b)
            yc = hs + k12 * 2.0 * t2c
            yd = k12 * 2.0 * t2d
            wa = kw * (t1a + 4.0 * t2a + t3a)
            wb = kw * (t1b + 4.0 * t2b + t3b)
            wc = 1.0 + kw * (4.0 * t2c + t3c)
            wd = kw * (4.0 * t2d + t3d)
            for c in range(C):
                if carried[c]:
                    y = du[c]
                    w = dw[c]
                    yy = y.conjugate()
                    ww = w.conjugate()
                    du[c] = ya * y + yb * yy + yc * w + yd * ww
                    dw[c] = wa * y + wb * yy + wc * w + wd * ww
        if idx < h:
            w0 += mw.jump[idx]
            if F:
                # From here on the force's columns: d/ds (dU gains the jump), d/df_x, d/df_y (dW gains i/EI, -1/EI).
                anything = True
                k = 3 * idx
                carried[k] = True
                carried[k + 1] = True
                carried[k + 2] = True
                du[k] = mw.jump[idx]
                dw[k + 1] = d_fx
                dw[k + 2] = d_fy
        else:
            q = idx - h
            curv[q, 0] = u0.real
            curv[q, 1] = u0.imag
            for c in range(F):
                jac[q, 0, c] = du[c].real
                jac[q, 1, c] = du[c].imag
            if seeds:
                for c in range(4):
                    phi[q, 0, c] = du[F + c].real
                    phi[q, 1, c] = du[F + c].imag
                    phi[q, 2, c] = dw[F + c].real
                    phi[q, 3, c] = dw[F + c].imag
    return True


def march_exact(k, query, Q, s, f, h):
    """The exact model of the straight rod: curvature ``curv`` (Q, 2) [1/m] at ``Q`` queries, into the march
    views, by the model's tableau (c, a, bp, bv of an explicit Runge-Kutta-Nystrom method for U'' = g(U), g folded
    into the coefficients as :class:`torchrod.model.nystrom.Tableau` stores them) on the rigorous step rule. False
    where an input is not finite (``curv`` is then NaN)."""
    rod = k.rod
    mw = march_of(k)
    tab = model_of(k)
    curv = mw.curv
    ei = rod.ei
    inv = 1.0 / ei
    ok = True
    for j in range(h):
        mw.jump[j] = slope_jump(f[j, 0], f[j, 1], inv)
        mw.mag[j] = math.sqrt(f[j, 0] * f[j, 0] + f[j, 1] * f[j, 1]) * inv
        ok = ok and math.isfinite(s[j]) and math.isfinite(mw.mag[j])
    if not ok:
        for q in range(Q):
            curv[q, 0] = math.nan
            curv[q, 1] = math.nan
        return False
    schedule(query, Q, s, mw.jump, mw.mag, h, rod.length, rod.exact_angle, rod.exact_max_steps, True, mw.order,
             mw.seg, mw.steps)  # fmt: skip
    S = tab.tab_c.shape[0]
    ys = mw.ys
    gs = mw.gs
    U = 0j
    W = 0j
    for e in range(h + Q):
        idx = mw.order[e]
        n = mw.steps[e]
        hstep = 0.0
        if n:
            hstep = mw.seg[e] / n
        h2 = hstep * hstep
        for _ in range(n):
            hW = hstep * W
            ys[0] = U
            gs[0] = (U.real * U.real + U.imag * U.imag) * U
            for i in range(1, S):
                acc = 0j
                for j in range(i):
                    acc += tab.tab_a[i, j] * gs[j]
                Y = U + tab.tab_c[i] * hW + h2 * acc
                ys[i] = Y
                gs[i] = (Y.real * Y.real + Y.imag * Y.imag) * Y
            accv = 0j
            accp = 0j
            for j in range(S):
                accv += tab.tab_bv[j] * gs[j]
                accp += tab.tab_bp[j] * gs[j]
            W = W + hstep * accv
            U = U + hW + h2 * accp
        if idx < h:
            W = W + mw.jump[idx]
        else:
            curv[idx - h, 0] = U.real
            curv[idx - h, 1] = U.imag
    return True
