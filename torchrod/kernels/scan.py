"""Where one more force helps most: the scan of candidate locations from a fit of h forces.

Given a fit (base) of h forces, the Gauss-Newton model of adding one more force at a candidate location c, with
every unknown of the fit free to adjust, promises a loss decrease (its decrement: the score statistic for a force
at c). Candidates sit at ``per_interval`` points inside each interval between the reading's present gratings.
Their responses come from ONE march of the base with the propagator of the linearised rod equations: the response
at grating p to a slope jump at c is Phi(p) Phi(c)^-1 applied to the jump (the straight rod's (U, W) state, or the
precurved rod's (n, m)); with no force yet on a straight rod, the small-deflection lever (c - p)^+ / EI. The base's
normal system is factored once for all candidates, so each candidate costs a 2 x 2 Schur complement
(:func:`added_force`). The best candidate of each interval is ranked by its decrement; the ``T`` best intervals
become starts: the base moved by the Gauss-Newton step with the new force at c (:func:`scan_starts`).
"""

import math

from .fit import FLOOR, SCALE_MIN, TINY, bounds, gradient, gram, march_model, sided
from .linalg import cholesky_apply, cholesky_factor, lu_apply, lu_factor, sumsq
from .march import slope_jump
from .views import lm_of, march_of, model_of, reading_of, rows_of, scan_of

SCAN_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "scan": {  # the scan's candidates, responses and Gauss-Newton models
        "cand": (("C",), "f"), "cint": (("C",), "i"), "valid": (("C",), "b"), "at": (("Q",), "f"),
        "r": (("n",), "f"), "J": (("n", "P"), "f"), "Jraw": (("n", "P"), "f"), "Jc": (("C", "n", 2), "f"),
        "Mphi": ((6, 6), "f"), "LU": ((6, 6), "f"), "piv": ((6,), "i"), "col": ((6,), "f"), "xcol": ((6,), "f"),
        "Msol": ((6, 2), "f"), "Abb": (("P", "P"), "f"), "Acc": (("C", 2, 2), "f"), "gc": (("C", 2), "f"),
        "Kb": (("P", "P"), "f"), "Lb": (("P", "P"), "f"), "e": (("P",), "f"), "xk": (("P",), "f"),
        "Kinv": (("P", "P"), "f"), "gb": (("P",), "f"), "yb": (("P",), "f"), "Acb": ((2, "P"), "f"),
        "Y": (("C", 2, "P"), "f"), "xc": (("C", 2), "f"), "dec": (("C",), "f"), "best_c": (("G",), "i"),
        "order": (("G",), "i"), "st": (("P2",), "f"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

INLINE = ("interval_of", "response_rows")
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def interval_of(k, s, j_out, s_out, idx):
    """The interval of location s [m] (the last present grating at or proximal to it; the first interval for a
    location proximal to every present grating) into j_out[idx], and s moved into it into s_out[idx]."""
    rd = reading_of(k)
    m = k.info[0].intervals
    j = -1
    for g in range(m):
        if rd.lo[g] <= s:
            j += 1
    if j < 0:
        j = 0
    if j > m - 1:
        j = m - 1
    lo = rd.lo[j]
    hi = rd.hi[j]
    v = s
    if v < lo:
        v = lo
    if v > hi:
        v = hi
    j_out[idx] = j
    s_out[idx] = v


def scan_model(k, bs, bf, bint, h0, known_row):
    """The scan's model for the base (bs (h0,) [m], bf (h0, 2) [N], intervals bint): the base residuals and sided
    Jacobian (from row ``known_row`` of the rows, or from a march where it is -1), every candidate's response and
    its Gauss-Newton model of one more force (:func:`added_force`). Writes the scan work; returns the base loss."""
    sw = scan_of(k)
    rows = rows_of(k)
    rd = reading_of(k)
    query = model_of(k).query
    G = k.rod.num_gratings
    n = 2 * G
    Pb = 3 * h0
    K = k.opt.per_interval
    C = K * G
    FU = k.rod.force_unit
    inv = 1.0 / k.rod.ei
    m_int = k.info[0].intervals
    for j in range(G):
        lo = rd.lo[j]
        hi = rd.hi[j]
        for kk in range(K):
            c = j * K + kk
            sw.cand[c] = lo + (hi - lo) * ((kk + 0.5) / K)
            sw.cint[c] = j
            sw.valid[c] = j < m_int
    r = sw.r
    J = sw.J
    Jc = sw.Jc
    w = k.w
    if h0 == 0 and not k.rod.precurved:
        # No force yet: the rod is straight, and the response is the small-deflection lever (c - q)^+ / EI.
        k.info[0].evaluations += 1
        for m in range(n):
            r[m] = -k.u[m] * w[m]
        for c in range(C):
            for g in range(G):
                lever = sw.cand[c] - query[g]
                lever = (lever if lever > 0.0 else 0.0) * inv
                Jc[c, 2 * g, 0] = 0.0
                Jc[c, 2 * g, 1] = -lever * w[2 * g] * FU
                Jc[c, 2 * g + 1, 0] = lever * w[2 * g + 1] * FU
                Jc[c, 2 * g + 1, 1] = 0.0
    else:
        at = sw.at
        for g in range(G):
            at[g] = query[g]
        for c in range(C):
            at[G + c] = sw.cand[c]
        known = known_row >= 0
        F = 0 if known else Pb
        march_model(k, at, G + C, bs, bf, h0, F, True, False)
        mw = march_of(k)
        curv = mw.curv
        jac = mw.jac
        phi = mw.phi
        if known:
            for m in range(n):
                r[m] = rows.r[known_row, m]
            lw = lm_of(k)
            bounds(k, bint, h0, lw.lo, lw.hi)
            sided(k, rows.J[known_row], bs, lw.hi, bint, h0, n, J)
        else:
            L = k.rod.length
            Jraw = sw.Jraw
            for g in range(G):
                for cc in range(2):
                    m = 2 * g + cc
                    r[m] = (curv[g, cc] - k.u[m]) * w[m]
                    for p in range(Pb):
                        Jraw[m, p] = jac[g, cc, p] * (L if p % 3 == 0 else FU) * w[m]
            lw = lm_of(k)
            bounds(k, bint, h0, lw.lo, lw.hi)
            sided(k, Jraw, bs, lw.hi, bint, h0, n, J)
        # The response at each grating to a unit f_x and f_y at each candidate: Phi(p) Phi(c)^-1 (the state's jump).
        S = 6 if k.rod.precurved else 4
        top = 2 if k.rod.precurved else 0  # phi's rows of the state (below the rows of d(u_x, u_y))
        for c in range(C):
            for a in range(S):
                for b in range(S):
                    sw.Mphi[a, b] = phi[G + c, top + a, b] if k.rod.precurved else phi[G + c, a, b]
            ok = lu_factor(sw.Mphi, sw.LU, sw.piv, S)
            for j in range(2):
                for a in range(S):
                    sw.col[a] = 0.0
                if k.rod.precurved:
                    sw.col[j] = 1.0  # a unit force: n jumps by e_x or e_y
                else:
                    unit = slope_jump(1.0 - j, float(j), inv)  # a unit f_x or f_y: the slope W jumps
                    sw.col[2] = unit.real
                    sw.col[3] = unit.imag
                ok = ok and lu_apply(sw.LU, sw.piv, sw.col, sw.xcol, S)
                for a in range(S):
                    sw.Msol[a, j] = sw.xcol[a] if ok else 0.0
            for g in range(G):
                prox = 1.0 if query[g] < sw.cand[c] else 0.0
                for cc in range(2):
                    for j in range(2):
                        v = 0.0
                        for a in range(S):
                            v += phi[g, cc, a] * sw.Msol[a, j]
                        Jc[c, 2 * g + cc, j] = (v * prox) * w[2 * g + cc] * FU
    added_force(k, h0)
    return sumsq(r, n)


def response_rows(Jc, c, n, finite):
    """The rows of candidate c's response Jc[c] (n, 2) up to its last one that is not zero (n unless ``finite``)."""
    rows = n
    if finite:
        while rows > 0 and Jc[c, rows - 1, 0] == 0.0 and Jc[c, rows - 1, 1] == 0.0:
            rows -= 1
    return rows


def added_force(k, h0):
    """The Gauss-Newton model of the base with one more force at each candidate, every unknown free.

    For candidate c the normal system of the columns [J, Jc_c] is ``[[Abb, Abc], [Acb, Acc]] x = [gb; gc]``,
    lightly damped (:data:`TINY` of each diagonal entry plus :data:`FLOOR` of the largest). It is solved through
    the base block K, shared by the candidates and inverted once, so that each candidate costs its 2 x 2 Schur
    complement ``S = Acc - Y Abc`` with ``Y = Acb K^-1``: ``S x_c = z = gc - Y gb``, ``x_b = K^-1 gb - Y^T x_c``, and
    the decrement g.x is ``gb.K^-1 gb + z.x_c``. Where the base columns span a candidate's response to rounding (S
    is then rounding error) the candidate adds nothing: x_c = 0. Writes dec (C,) (-inf where the base block failed),
    xc (C, 2), yb (Pb,), Y (C, 2, Pb)."""
    sw = scan_of(k)
    G = k.rod.num_gratings
    n = 2 * G
    Pb = 3 * h0
    C = k.opt.per_interval * G
    J = sw.J
    Jc = sw.Jc
    r = sw.r
    d_max = -math.inf
    finite = gram(J, n, Pb, sw.Abb, lm_of(k).tail)
    for p in range(Pb):
        d = sw.Abb[p, p]
        if d != d or d > d_max:
            d_max = d
    # A candidate's response is zero at the gratings distal to it: its sums stop at its last nonzero row. (Exactly
    # the full sums: the terms left out are zeros, unless r or J is not finite there, when nothing is left out.)
    for m in range(n):
        finite = finite and math.isfinite(r[m])
    for c in range(C):
        rows = response_rows(Jc, c, n, finite)
        # (every sum taken in one pass over the rows: each still adds its terms in row order, so its value is the
        # same, but the sums no longer wait on each other)
        a00 = 0.0
        a01 = 0.0
        a11 = 0.0
        g0 = 0.0
        g1 = 0.0
        for m in range(rows):
            x0 = Jc[c, m, 0]
            x1 = Jc[c, m, 1]
            a00 += x0 * x0
            a01 += x0 * x1
            a11 += x1 * x1
            g0 += r[m] * x0
            g1 += r[m] * x1
        sw.Acc[c, 0, 0] = a00
        sw.Acc[c, 0, 1] = a01
        sw.Acc[c, 1, 0] = a01
        sw.Acc[c, 1, 1] = a11
        sw.gc[c, 0] = g0
        sw.gc[c, 1] = g1
        if a00 != a00 or a00 > d_max:
            d_max = a00
        if a11 != a11 or a11 > d_max:
            d_max = a11
    scale = d_max if (d_max != d_max or d_max >= SCALE_MIN) else SCALE_MIN
    base_dec = 0.0
    ok = True
    if Pb:
        for p in range(Pb):
            for q in range(Pb):
                sw.Kb[p, q] = sw.Abb[p, q]
            sw.Kb[p, p] = sw.Abb[p, p] + (TINY * sw.Abb[p, p] + FLOOR * scale)
        ok = cholesky_factor(sw.Kb, sw.Lb, Pb)
        for q in range(Pb):
            for p in range(Pb):
                sw.e[p] = 1.0 if p == q else 0.0
            ok = ok and cholesky_apply(sw.Lb, sw.e, sw.xk, Pb)
            for p in range(Pb):
                sw.Kinv[p, q] = sw.xk[p] if ok else 0.0
        if not ok:
            for p in range(Pb):
                for q in range(Pb):
                    sw.Kinv[p, q] = 0.0
        gradient(J, r, n, Pb, sw.gb)
        for p in range(Pb):
            v = 0.0
            for q in range(Pb):
                v += sw.Kinv[p, q] * sw.gb[q]
            sw.yb[p] = v
            base_dec += sw.gb[p] * v
    for c in range(C):
        S00 = sw.Acc[c, 0, 0]
        S01 = sw.Acc[c, 0, 1]
        S10 = sw.Acc[c, 1, 0]
        S11 = sw.Acc[c, 1, 1]
        z0 = sw.gc[c, 0]
        z1 = sw.gc[c, 1]
        if Pb:
            rows = response_rows(Jc, c, n, finite)
            for p in range(0, Pb, 3):  # (a force's three columns at once; each sum in row order, as above)
                t00 = 0.0
                t01 = 0.0
                t02 = 0.0
                t10 = 0.0
                t11 = 0.0
                t12 = 0.0
                for m in range(rows):
                    x0 = Jc[c, m, 0]
                    x1 = Jc[c, m, 1]
                    j0 = J[m, p]
                    j1 = J[m, p + 1]
                    j2 = J[m, p + 2]
                    t00 += x0 * j0
                    t01 += x0 * j1
                    t02 += x0 * j2
                    t10 += x1 * j0
                    t11 += x1 * j1
                    t12 += x1 * j2
                sw.Acb[0, p] = t00
                sw.Acb[0, p + 1] = t01
                sw.Acb[0, p + 2] = t02
                sw.Acb[1, p] = t10
                sw.Acb[1, p + 1] = t11
                sw.Acb[1, p + 2] = t12
            for a in range(2):
                for p in range(Pb):
                    v = 0.0
                    for q in range(Pb):
                        v += sw.Acb[a, q] * sw.Kinv[q, p]
                    sw.Y[c, a, p] = v
            s00 = 0.0
            s01 = 0.0
            s10 = 0.0
            s11 = 0.0
            y0 = 0.0
            y1 = 0.0
            for p in range(Pb):
                s00 += sw.Y[c, 0, p] * sw.Acb[0, p]
                s01 += sw.Y[c, 0, p] * sw.Acb[1, p]
                s10 += sw.Y[c, 1, p] * sw.Acb[0, p]
                s11 += sw.Y[c, 1, p] * sw.Acb[1, p]
                y0 += sw.Y[c, 0, p] * sw.gb[p]
                y1 += sw.Y[c, 1, p] * sw.gb[p]
            S00 -= s00
            S01 -= s01
            S10 -= s10
            S11 -= s11
            z0 -= y0
            z1 -= y1
        a = S00 + (TINY * sw.Acc[c, 0, 0] + FLOOR * scale)
        d = S11 + (TINY * sw.Acc[c, 1, 1] + FLOOR * scale)
        bb = 0.5 * (S01 + S10)
        det = a * d - bb * bb
        x0 = 0.0
        x1 = 0.0
        if a > 0.0 and det > 0.0:
            x0 = (d * z0 - bb * z1) / det
            x1 = (a * z1 - bb * z0) / det
        sw.xc[c, 0] = x0
        sw.xc[c, 1] = x1
        sw.dec[c] = base_dec + (z0 * x0 + z1 * x1) if ok else -math.inf


def scan_starts(k, bs, bf, h0, base_loss, T, trust, out_s, out_f, out_int, out_pred, off, stride):
    """The T best intervals of the scan (:func:`scan_model` just run on the base bs, bf of h0 forces) as starts of
    h0 + 1 forces, written to row ``off + t * stride`` of out_s (., H), out_f (., H, 2), out_int (., H) and
    out_pred (.,): the loss each start's Gauss-Newton model promises (inf: no such start; a base with fewer
    intervals than T repeats its best). Returns the gain: the largest decrement over all candidates [1/m^2] (0
    where none could be scored)."""
    sw = scan_of(k)
    G = k.rod.num_gratings
    K = k.opt.per_interval
    C = K * G
    L = k.rod.length
    FU = k.rod.force_unit
    Pb = 3 * h0
    for c in range(C):
        if not (sw.valid[c] and math.isfinite(sw.dec[c])):
            sw.dec[c] = -math.inf
    gain = -math.inf
    for j in range(G):  # the best candidate of each interval (the first at a tie)
        best = j * K
        for kk in range(1, K):
            if sw.dec[j * K + kk] > sw.dec[best]:
                best = j * K + kk
        sw.best_c[j] = best
        sw.order[j] = j
        if sw.dec[best] > gain:
            gain = sw.dec[best]
    for i in range(1, G):  # the intervals by decreasing decrement, stable
        key = sw.order[i]
        v = sw.dec[sw.best_c[key]]
        j = i
        while j > 0 and sw.dec[sw.best_c[sw.order[j - 1]]] < v:
            sw.order[j] = sw.order[j - 1]
            j -= 1
        sw.order[j] = key
    first = sw.best_c[sw.order[0]]
    for t in range(T):
        c = sw.best_c[sw.order[t]] if t < G else first
        pred = base_loss - sw.dec[c]
        if not math.isfinite(sw.dec[c]):
            c = first
            pred = math.inf
        row = off + t * stride
        out_pred[row] = pred
        # The Gauss-Newton step with the new force at c: x_c, then the base's x_b = K^-1 gb - Y^T x_c (negated).
        big = 1.0
        x0 = sw.xc[c, 0]
        x1 = sw.xc[c, 1]
        for p in range(Pb):
            sw.st[p] = -(sw.yb[p] - (x0 * sw.Y[c, 0, p] + x1 * sw.Y[c, 1, p]))
        sw.st[Pb] = -x0
        sw.st[Pb + 1] = -x1
        for p in range(Pb + 2):
            a = abs(sw.st[p]) / trust
            if a > big:
                big = a
        for j in range(h0):
            interval_of(k, bs[j] + (sw.st[3 * j] / big) * L, out_int[row], out_s[row], j)
            out_f[row, j, 0] = bf[j, 0] + (sw.st[3 * j + 1] / big) * FU
            out_f[row, j, 1] = bf[j, 1] + (sw.st[3 * j + 2] / big) * FU
        out_s[row, h0] = sw.cand[c]
        out_int[row, h0] = sw.cint[c]
        out_f[row, h0, 0] = (sw.st[Pb] / big) * FU
        out_f[row, h0, 1] = (sw.st[Pb + 1] / big) * FU
    if not math.isfinite(gain):
        return 0.0
    return gain if gain > 0.0 else 0.0
