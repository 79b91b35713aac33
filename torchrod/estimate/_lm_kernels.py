"""The Numba kernels of :mod:`torchrod.estimate._lm_compiled` (imported only where they run: this imports Numba).

One Levenberg-Marquardt step and one analysis of :mod:`.lm` per row, for the straight rod on the NumPy backend:
:func:`.lm._step` and :func:`.lm.analyse` written row by row, each array operation of theirs a loop here, in their
order; likewise the scan's models, the exact model's finish and the Gauss-Newton covariance of :mod:`.uncertainty`.
Module-level functions, so that Numba's on-disk cache finds them again in a new process."""

from __future__ import annotations

import math

import numba
import numpy as np

from ..model._kernels import exact_rows as _exact_rows
from ..model._kernels import row as _march_row
from ..model._kernels import schedule as _schedule

_jit = numba.njit(cache=True, nogil=True)
_SAFE_MIN = np.finfo(np.float64).tiny  # LAPACK's dlamch("S")


@_jit
def _sum(x, n):
    # numpy's pairwise sum of x[:n] (n <= 128): 8 running sums, combined in pairs, then the rest.
    if n < 8:
        res = 0.0
        for i in range(n):
            res += x[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
    i = 8
    while i < n - (n % 8):
        r0 += x[i]
        r1 += x[i + 1]
        r2 += x[i + 2]
        r3 += x[i + 3]
        r4 += x[i + 4]
        r5 += x[i + 5]
        r6 += x[i + 6]
        r7 += x[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += x[i]
        i += 1
    return res


@_jit
def _sumsq(r, tmp):
    n = r.shape[0]
    for k in range(n):
        tmp[k] = r[k] * r[k]
    return _sum(tmp, n)


@_jit
def _evaluate(query, s, f, u_b, w_b, length, ei, force_unit, step_angle, max_steps, jacobian, r, J, work):
    # problem.evaluate of one row: residuals r (n,) and, with ``jacobian``, J (n, 3h) in the march's convention.
    # False where an input is not finite (the caller then steps these rows in Python).
    order, seg, steps, jump, active, curv, jac, prop = work
    h = s.shape[0]
    Q = query.shape[0]
    inv = 1.0 / ei
    for j in range(h):
        jump[j] = complex(-f[j, 1] * inv, f[j, 0] * inv)
        if not (math.isfinite(s[j]) and math.isfinite(jump[j].real) and math.isfinite(jump[j].imag)):
            return False
    F = 3 * h if jacobian else 0
    _schedule(query, s, jump, length, step_angle, max_steps, False, order, seg, steps)
    _march_row(order, seg, steps, jump, active, h, F, False, ei, curv, jac, prop)
    for q in range(Q):
        for c in range(2):
            k = 2 * q + c
            r[k] = (curv[q, c] - u_b[k]) * w_b[k]
            if jacobian:
                for p in range(F):
                    v = jac[q, c, p]
                    v = v * length if p % 3 == 0 else v * force_unit
                    J[k, p] = v * w_b[k]
    return True


@_jit
def _solve(M, b, x):
    # backend.spd_solve of one system (LU with partial pivoting, as LAPACK's): x, and whether it succeeded (M and b
    # finite, no zero pivot, x finite); x is zero where it did not.
    P = M.shape[0]
    ok = True
    for i in range(P):
        if not math.isfinite(b[i]):
            ok = False
        for j in range(P):
            if not math.isfinite(M[i, j]):
                ok = False
    if ok:
        a = M.copy()
        y = b.copy()
        for k in range(P):
            p = k
            big = abs(a[k, k])
            for i in range(k + 1, P):
                if abs(a[i, k]) > big:
                    big = abs(a[i, k])
                    p = i
            if big == 0.0:
                ok = False
                break
            if p != k:
                for j in range(P):
                    a[k, j], a[p, j] = a[p, j], a[k, j]
                y[k], y[p] = y[p], y[k]
            inv = 1.0 / a[k, k]
            tiny = abs(a[k, k]) < _SAFE_MIN  # LAPACK divides by such a pivot instead (its reciprocal overflows)
            for i in range(k + 1, P):
                m = a[i, k] / a[k, k] if tiny else a[i, k] * inv
                a[i, k] = m
                for j in range(k + 1, P):
                    a[i, j] -= m * a[k, j]
                y[i] -= m * y[k]
        if ok:  # back substitution column by column (BLAS's trsm)
            for k in range(P - 1, -1, -1):
                if y[k] != 0.0:
                    y[k] = y[k] / a[k, k]
                    for i in range(k):
                        y[i] -= y[k] * a[i, k]
            for k in range(P):
                x[k] = y[k]
                if not math.isfinite(x[k]):
                    ok = False
    if not ok:
        x[:] = 0.0
    return ok


@_jit
def _damped(A, free, damping, floor, scale_min, out):
    # lm._damped of one system: A + damping diag A + floor max diag A, and the largest diagonal for fixed unknowns.
    P = A.shape[0]
    scale = A[0, 0] if P else 0.0
    for p in range(1, P):
        d = A[p, p]
        if d != d or d > scale:
            scale = d
    if not (scale != scale) and scale < scale_min:
        scale = scale_min
    out[:, :] = A
    for p in range(P):
        d = A[p, p]
        out[p, p] = d + damping * d + (floor * scale + (1.0 - free[p]) * scale)


@_jit
def _bounds(lo_b, hi_b, interval, lo, hi):
    for j in range(interval.shape[0]):
        lo[j] = lo_b[interval[j]]
        hi[j] = hi_b[interval[j]]


@_jit
def _sided(J, s, hi, hik_b, interval, out):
    # problem.sided: a force on the upper bound of its interval gets zero s-entries at that bound's grating.
    out[:, :] = J
    for j in range(s.shape[0]):
        k = hik_b[interval[j]]
        if s[j] == hi[j] and k >= 0:
            out[2 * k, 3 * j] = 0.0
            out[2 * k + 1, 3 * j] = 0.0


@_jit
def _gradient(J, r, g):
    n, P = J.shape
    for p in range(P):
        t = 0.0
        for k in range(n):
            t += J[k, p] * r[k]
        g[p] = t


@_jit
def _gram(J, A):
    n, P = J.shape
    for p in range(P):
        for q in range(p, P):
            t = 0.0
            for k in range(n):
                t += J[k, p] * J[k, q]
            A[p, q] = t
            A[q, p] = t


@_jit
def _noise2(loss, reading, h, noise2, residuals, floor2):
    if noise2.shape[0]:
        return noise2[reading]
    dof = max(float(residuals[reading] - 3 * h), 1.0)
    v = loss / dof
    return v if (v != v or v >= floor2) else floor2


@_jit
def _analyse(i, P_, S_, O_, work):
    # lm.analyse of row i of the state (S_), in place; P_: the problem's arrays and numbers, O_: the policy's.
    (query, u, weight, lo_all, hi_all, lok_all, hik_all, intervals, noise2, residuals, floor2, length, ei,
     force_unit, step_angle, max_steps, snap) = P_  # fmt: skip
    (reading, s, f, interval, r, J, loss, damping, steps, held, A, g, proposal, ratio, decrement, noise2_out,
     converged, done, failed) = S_  # fmt: skip
    tolerance, iterations, max_damping, floor, tiny, scale_min = O_[0], O_[1], O_[2], O_[10], O_[11], O_[12]
    b = reading[i]
    h = s.shape[1]
    P = 3 * h
    n = r.shape[1]
    lo = np.empty(h)
    hi = np.empty(h)
    _bounds(lo_all[b], hi_all[b], interval[i], lo, hi)
    Js = np.empty((n, P))
    _sided(J[i], s[i], hi, hik_all[b], interval[i], Js)
    free = np.ones(P)
    gi = np.empty(P)
    _gradient(Js, r[i], gi)
    near_lo = np.empty(h, np.bool_)
    near_hi = np.empty(h, np.bool_)
    near = False
    for j in range(h):
        tol = snap * (hi[j] - lo[j])
        near_lo[j] = s[i, j] - lo[j] <= tol
        near_hi[j] = hi[j] - s[i, j] <= tol
        near = near or near_lo[j] or near_hi[j]
    for j in range(h):
        held[i, j] = False
    if near:
        at_lo = np.empty(h, np.bool_)
        at_hi = np.empty(h, np.bool_)
        scale = length / ei
        m = intervals[b]
        cross = False
        new_int = interval[i].copy()
        new_s = s[i].copy()
        for j in range(h):
            at_lo[j] = s[i, j] == lo[j]
            at_hi[j] = s[i, j] == hi[j]
            jc0 = -f[i, j, 1] * scale
            jc1 = f[i, j, 0] * scale
            k_lo = lok_all[b, interval[i, j]]
            k_hi = hik_all[b, interval[i, j]]
            c_lo = 0.0
            c_hi = 0.0
            if near_lo[j] and k_lo >= 0:
                c_lo = r[i, 2 * k_lo] * jc0 + r[i, 2 * k_lo + 1] * jc1
            if near_hi[j] and k_hi >= 0:
                c_hi = r[i, 2 * k_hi] * jc0 + r[i, 2 * k_hi + 1] * jc1
            g_s = gi[3 * j]
            down = near_lo[j] and (g_s >= 0.0 or not at_lo[j]) and interval[i, j] > 0 and g_s - c_lo > 0.0
            up = near_hi[j] and (g_s <= 0.0 or not at_hi[j]) and interval[i, j] < m - 1 and g_s + c_hi < 0.0
            if down or up:
                new_int[j] = interval[i, j] - (1 if down else 0) + (1 if up else 0)
                new_s[j] = lo[j] if down else hi[j]
                cross = True
        if cross:
            moved = False
            for j in range(h):
                moved = moved or new_s[j] != s[i, j]
                s[i, j] = new_s[j]
                interval[i, j] = new_int[j]
            if moved:  # snapped onto the grating: the residuals there, exactly
                if not _evaluate(query, s[i], f[i], u[b], weight[b], length, ei, force_unit, step_angle, max_steps,
                                 True, r[i], J[i], work):  # fmt: skip
                    failed[i] = True
                    return
                loss[i] = _sumsq(r[i], np.empty(n))
            _bounds(lo_all[b], hi_all[b], interval[i], lo, hi)
            for j in range(h):
                at_lo[j] = s[i, j] == lo[j]
                at_hi[j] = s[i, j] == hi[j]
            _sided(J[i], s[i], hi, hik_all[b], interval[i], Js)
            _gradient(Js, r[i], gi)
        for j in range(h):
            g_s = gi[3 * j]
            held[i, j] = (at_lo[j] and g_s >= 0.0) or (at_hi[j] and g_s <= 0.0)
            if held[i, j]:
                free[3 * j] = 0.0
        for k in range(n):
            for p in range(P):
                Js[k, p] = Js[k, p] * free[p]
        for p in range(P):
            gi[p] = gi[p] * free[p]
    Ai = A[i]
    _gram(Js, Ai)
    g[i, :] = gi
    M = np.empty((P, P))
    x = np.empty(P)
    _damped(Ai, free, tiny + 0.0 * damping[i], floor, scale_min, M)
    ok = _solve(M, gi, x)
    if ok:
        t = np.empty(P)
        for p in range(P):
            t[p] = gi[p] * x[p]
        decrement[i] = _sum(t, P)
    else:
        decrement[i] = math.inf
    _damped(Ai, free, damping[i], floor, scale_min, M)
    _solve(M, gi, x)
    for p in range(P):
        proposal[i, p] = -x[p]
    noise2_out[i] = _noise2(loss[i], b, h, noise2, residuals, floor2)
    converged[i] = decrement[i] <= tolerance * noise2_out[i]
    done[i] = converged[i] or steps[i] >= iterations or damping[i] >= max_damping


@_jit
def _free(held_row, free):
    for j in range(held_row.shape[0]):
        free[3 * j] = 0.0 if held_row[j] else 1.0
        free[3 * j + 1] = 1.0
        free[3 * j + 2] = 1.0


@_jit
def _shortened(dx, max_force_step, out):
    # the trust region on the force components
    h = dx.shape[0] // 3
    big = -math.inf
    for j in range(h):
        for c in (1, 2):
            a = abs(dx[3 * j + c])
            if a != a or a > big:
                big = a
    d = big / max_force_step
    if not (d != d) and d < 1.0:
        d = 1.0
    for p in range(dx.shape[0]):
        out[p] = dx[p] / d


@_jit
def _moved(s, f, lo, hi, dx, length, force_unit, s_out, f_out):
    for j in range(s.shape[0]):
        v = s[j] + dx[3 * j] * length
        v = max(v, lo[j]) if not (v != v) else v
        v = min(v, hi[j]) if not (v != v) else v
        s_out[j] = v
        f_out[j, 0] = f[j, 0] + dx[3 * j + 1] * force_unit
        f_out[j, 1] = f[j, 1] + dx[3 * j + 2] * force_unit


@_jit
def _step(i, any_curved, P_, S_, O_, work):
    # lm._step of row i (then lm.analyse), in place; ``any_curved``: some row of this step takes the geodesic
    # acceleration (every row's step is then shortened once more, as the array code does).
    (query, u, weight, lo_all, hi_all, lok_all, hik_all, intervals, noise2, residuals, floor2, length, ei,
     force_unit, step_angle, max_steps, snap) = P_  # fmt: skip
    (reading, s, f, interval, r, J, loss, damping, steps, held, A, g, proposal, ratio, decrement, noise2_out,
     converged, done, failed) = S_  # fmt: skip
    (tolerance, iterations, max_damping, increase, decrease, min_damping, max_force_step, acceleration, probe,
     acceleration_limit, floor, tiny, scale_min) = O_  # fmt: skip
    b = reading[i]
    h = s.shape[1]
    P = 3 * h
    n = r.shape[1]
    lo = np.empty(h)
    hi = np.empty(h)
    _bounds(lo_all[b], hi_all[b], interval[i], lo, hi)
    Ai = A[i].copy()
    gi = g[i].copy()
    prop = proposal[i].copy()
    held_i = held[i].copy()
    out = False
    for j in range(h):
        ds = prop[3 * j]
        o = (s[i, j] == lo[j] and ds < 0.0) or (s[i, j] == hi[j] and ds > 0.0)
        if o:
            held_i[j] = True
            out = True
    free = np.empty(P)
    _free(held_i, free)
    M = np.empty((P, P))
    x = np.empty(P)
    if out:
        for p in range(P):
            for q in range(P):
                Ai[p, q] = Ai[p, q] * free[p] * free[q]
            gi[p] = gi[p] * free[p]
        _damped(Ai, free, damping[i], floor, scale_min, M)
        _solve(M, gi, x)
        for p in range(P):
            prop[p] = -x[p]
    v = np.empty(P)
    _shortened(prop, max_force_step, v)
    dx = v.copy()
    if any_curved:
        add = np.zeros(P)
        if ratio[i] < acceleration:
            sp = np.empty(h)
            fp = np.empty((h, 2))
            pv = np.empty(P)
            for p in range(P):
                pv[p] = probe * v[p]
            _moved(s[i], f[i], lo, hi, pv, length, force_unit, sp, fp)
            r_p = np.empty(n)
            if not _evaluate(query, sp, fp, u[b], weight[b], length, ei, force_unit, step_angle, max_steps, False,
                             r_p, J[i], work):  # fmt: skip
                failed[i] = True
                return
            actual = np.empty(P)
            for j in range(h):
                actual[3 * j] = ((sp[j] - s[i, j]) / length) / probe
                actual[3 * j + 1] = ((fp[j, 0] - f[i, j, 0]) / force_unit) / probe
                actual[3 * j + 2] = ((fp[j, 1] - f[i, j, 1]) / force_unit) / probe
            Jf = np.empty((n, P))
            _sided(J[i], s[i], hi, hik_all[b], interval[i], Jf)
            finite = True
            r_vv = np.empty(n)
            for k in range(n):
                t = 0.0
                for p in range(P):
                    Jf[k, p] = Jf[k, p] * free[p]
                    t += Jf[k, p] * actual[p]
                r_vv[k] = (2.0 / probe) * ((r_p[k] - r[i, k]) / probe - t)
                finite = finite and math.isfinite(r_vv[k])
            rhs = np.empty(P)
            _gradient(Jf, r_vv, rhs)
            _damped(Ai, free, damping[i], floor, scale_min, M)
            ok_a = _solve(M, rhs, x)
            na = _sumsq(x, np.empty(P))
            nv = _sumsq(v, np.empty(P))
            if ok_a and finite and 2.0 * math.sqrt(na) <= acceleration_limit * math.sqrt(nv):
                for p in range(P):
                    add[p] = 0.5 * -x[p]
        w = np.empty(P)
        for p in range(P):
            w[p] = v[p] + add[p]
        _shortened(w, max_force_step, dx)
    st = np.empty(h)
    ft = np.empty((h, 2))
    _moved(s[i], f[i], lo, hi, dx, length, force_unit, st, ft)
    r_t = np.empty(n)
    J_t = np.empty((n, P))
    if not _evaluate(query, st, ft, u[b], weight[b], length, ei, force_unit, step_angle, max_steps, True, r_t, J_t,
                     work):  # fmt: skip
        failed[i] = True
        return
    loss_t = _sumsq(r_t, np.empty(n))
    better = math.isfinite(loss_t) and loss_t < loss[i]
    taken = np.empty(P)
    for j in range(h):
        taken[3 * j] = (st[j] - s[i, j]) / length
        taken[3 * j + 1] = (ft[j, 0] - f[i, j, 0]) / force_unit
        taken[3 * j + 2] = (ft[j, 1] - f[i, j, 1]) / force_unit
    t1 = np.empty(P)
    t2 = np.empty(P)
    for p in range(P):
        t1[p] = gi[p] * taken[p]
        a = 0.0
        for q in range(P):
            a += Ai[p, q] * taken[q]
        t2[p] = taken[p] * a
    promised = -(2.0 * _sum(t1, P) + _sum(t2, P))
    if better and promised > 0:
        ratio[i] = (loss[i] - loss_t) / promised
    else:
        ratio[i] = 0.0
    if better:
        for j in range(h):
            s[i, j] = st[j]
            f[i, j, 0] = ft[j, 0]
            f[i, j, 1] = ft[j, 1]
        r[i, :] = r_t
        J[i, :, :] = J_t
        loss[i] = loss_t
        d = damping[i] / decrease
        damping[i] = d if (d != d or d >= min_damping) else min_damping
    else:
        d = damping[i] * increase
        damping[i] = d if (d != d or d <= max_damping) else max_damping
    steps[i] += 1
    _analyse(i, P_, S_, O_, work)


@_jit
def _buffers(h, Q):
    E = h + Q
    return (np.empty(E, np.int64), np.empty(E), np.empty(E, np.int64), np.empty(h, np.complex128),
            np.ones(h, np.bool_), np.empty((Q, 2)), np.empty((Q, 2, 3 * h)), np.empty((1, 4, 4)))  # fmt: skip


@_jit
def _round(rows, P_, S_, O_, work):
    # One lm._step of the rows ``rows`` as one batch, in place: ``any_curved`` (some row's last step curved, its ratio
    # below the policy's acceleration) is the batch's, as lm._step sees it.
    acceleration = O_[7]
    any_curved = False
    for i in rows:
        any_curved = any_curved or S_[13][i] < acceleration
    for i in rows:
        _step(i, any_curved, P_, S_, O_, work)


@_jit
def step_rows(rows, P_, S_, O_):
    # lm._step of the state's ``rows``, in place.
    _round(rows, P_, S_, O_, _buffers(S_[1].shape[1], P_[0].shape[0]))


@_jit
def start_rows(P_, S_, O_):
    # lm.start of every row: the state at its fits (one evaluation), analysed; in place.
    (query, u, weight, lo_all, hi_all, lok_all, hik_all, intervals, noise2, residuals, floor2, length, ei,
     force_unit, step_angle, max_steps, snap) = P_  # fmt: skip
    reading, s, f, r, J, loss, failed = S_[0], S_[1], S_[2], S_[4], S_[5], S_[6], S_[18]
    h = s.shape[1]
    work = _buffers(h, query.shape[0])
    tmp = np.empty(r.shape[1])
    for i in range(s.shape[0]):
        b = reading[i]
        if not _evaluate(query, s[i], f[i], u[b], weight[b], length, ei, force_unit, step_angle, max_steps, True,
                         r[i], J[i], work):  # fmt: skip
            failed[i] = True
            continue
        v = _sumsq(r[i], tmp)
        loss[i] = v if math.isfinite(v) else math.inf
        _analyse(i, P_, S_, O_, work)


@_jit
def _exact(query, s, f, u_b, w_b, length, ei, step_angle, max_steps, tableau, r, curv):
    # problem.exact_residual of one row (straight rod, h >= 1): body_frame.march_curvature's compiled row. False
    # where an input is not finite.
    c, a, bp, bv, fsal = tableau
    h = s.shape[0]
    inv = 1.0 / ei
    mag = np.empty((1, h))
    jump = np.empty((1, h), np.complex128)
    for j in range(h):
        mag[0, j] = math.sqrt(f[j, 0] * f[j, 0] + f[j, 1] * f[j, 1]) / ei
        jump[0, j] = complex(-f[j, 1] * inv, f[j, 0] * inv)
    marched = np.zeros(1, np.bool_)
    _exact_rows(query, s.reshape(1, h), mag, jump, length, step_angle, max_steps, c, a, bp, bv, fsal, curv, marched)
    if not marched[0]:
        return False
    for q in range(query.shape[0]):
        for k in range(2):
            r[2 * q + k] = (curv[0, q, k] - u_b[2 * q + k]) * w_b[2 * q + k]
    return True


@_jit
def finish_rows(P_, S_, O_, E_, used):
    # lm.finish_counted of every row, in place: the exact model's residual, then its Gauss-Newton steps with the
    # fitting model's Jacobian while they are worth taking and lower the loss; ``used`` (R,) out: the evaluations.
    (query, u, weight, lo_all, hi_all, lok_all, hik_all, intervals, noise2, residuals, floor2, length, ei,
     force_unit, step_angle, max_steps, snap) = P_  # fmt: skip
    reading, s, f, interval, r, J, loss, held, failed = S_[0], S_[1], S_[2], S_[3], S_[4], S_[5], S_[6], S_[9], S_[18]
    floor, tiny, scale_min = O_[10], O_[11], O_[12]
    exact_steps, exact_tolerance, exact_angle, exact_max_steps, tableau = E_
    R, h = s.shape
    P = 3 * h
    n = r.shape[1]
    curv = np.empty((1, query.shape[0], 2))
    tmp = np.empty(n)
    lo = np.empty(h)
    hi = np.empty(h)
    Js = np.empty((n, P))
    free = np.empty(P)
    g = np.empty(P)
    A = np.empty((P, P))
    M = np.empty((P, P))
    x = np.empty(P)
    t = np.empty(P)
    st = np.empty(h)
    ft = np.empty((h, 2))
    r_t = np.empty(n)
    for i in range(R):
        b = reading[i]
        if not _exact(query, s[i], f[i], u[b], weight[b], length, ei, exact_angle, exact_max_steps, tableau, r[i],
                      curv):  # fmt: skip
            failed[i] = True
            continue
        loss[i] = _sumsq(r[i], tmp)
        used[i] = 1
        _bounds(lo_all[b], hi_all[b], interval[i], lo, hi)
        _sided(J[i], s[i], hi, hik_all[b], interval[i], Js)
        _free(held[i], free)
        for k in range(n):
            for p in range(P):
                Js[k, p] = Js[k, p] * free[p]
        _gram(Js, A)
        for _ in range(exact_steps):
            # lm.gauss_newton at damping TINY: the step and its decrement
            _gradient(Js, r[i], g)
            _damped(A, free, tiny, floor, scale_min, M)
            ok = _solve(M, g, x)
            for p in range(P):
                t[p] = g[p] * -x[p]
            dec = -_sum(t, P) if ok else math.inf
            worth = not (dec <= exact_tolerance * _noise2(loss[i], b, h, noise2, residuals, floor2))
            if not worth:
                break
            for p in range(P):
                x[p] = -x[p]
            _moved(s[i], f[i], lo, hi, x, length, force_unit, st, ft)
            if not _exact(query, st, ft, u[b], weight[b], length, ei, exact_angle, exact_max_steps, tableau, r_t,
                          curv):  # fmt: skip
                failed[i] = True
                break
            loss_t = _sumsq(r_t, tmp)
            used[i] += 1
            if not (math.isfinite(loss_t) and loss_t < loss[i]):
                break
            s[i, :] = st
            f[i, :, :] = ft
            r[i, :] = r_t
            loss[i] = loss_t
        if not math.isfinite(loss[i]):
            loss[i] = math.inf


@_jit
def scan_rows(P_, base, known, cand, tiny, floor, scale_min, r, J, dec, xc, yb, Y, ok, failed):
    # search._responses and search._added_force of every base row (straight rod), in place: the residuals r
    # (R0, n) and sided Jacobian J (R0, n, Pb) (given: ``known``), and the Gauss-Newton model of one more force
    # at each candidate: decrements dec (R0, C), its solution's pieces xc (R0, C, 2), yb (R0, Pb), Y (R0, C, 2, Pb),
    # ok (R0,) where the base block solved. ``failed``: a row this cannot take (the array code then scans).
    (query, u, weight, lo_all, hi_all, lok_all, hik_all, intervals, noise2, residuals, floor2, length, ei,
     force_unit, step_angle, max_steps, snap) = P_  # fmt: skip
    reading, s, f, interval = base
    R0, h = s.shape
    G = query.shape[0]
    C = cand.shape[1]
    n = 2 * G
    Pb = 3 * h
    Q = G + C
    inv = 1.0 / ei
    order = np.empty(h + Q, np.int64)
    seg = np.empty(h + Q)
    steps = np.empty(h + Q, np.int64)
    jump = np.empty(h, np.complex128)
    active = np.ones(h, np.bool_)
    at = np.empty(Q)
    curv = np.empty((Q, 2))
    jac = np.empty((Q, 2, Pb))
    phi = np.empty((Q, 4, 4))
    Jraw = np.empty((n, Pb))
    lo = np.empty(h)
    hi = np.empty(h)
    Jc = np.empty((C, n, 2))
    Mphi = np.empty((4, 4))
    col = np.empty(4)
    x = np.empty(4)
    Msol = np.empty((4, 2))
    Abb = np.empty((Pb, Pb))
    K = np.empty((Pb, Pb))
    Kinv = np.empty((Pb, Pb))
    e = np.empty(Pb)
    xk = np.empty(Pb)
    gb = np.empty(Pb)
    t = np.empty(max(Pb, 1))
    Acc = np.empty((C, 2, 2))
    gc = np.empty((C, 2))
    Acb = np.empty((2, Pb))
    for i in range(R0):
        b = reading[i]
        w = weight[b]
        if h == 0:  # no force yet: the rod is straight, the response is the small-deflection lever
            for k in range(n):
                r[i, k] = -u[b, k] * w[k]
            for c in range(C):
                for g in range(G):
                    lever = max(cand[i, c] - query[g], 0.0) * inv
                    Jc[c, 2 * g, 0] = 0.0 * w[2 * g] * force_unit
                    Jc[c, 2 * g, 1] = -lever * w[2 * g] * force_unit
                    Jc[c, 2 * g + 1, 0] = lever * w[2 * g + 1] * force_unit
                    Jc[c, 2 * g + 1, 1] = 0.0 * w[2 * g + 1] * force_unit
        else:
            for g in range(G):
                at[g] = query[g]
            for c in range(C):
                at[G + c] = cand[i, c]
            for j in range(h):
                jump[j] = complex(-f[i, j, 1] * inv, f[i, j, 0] * inv)
            if not (np.isfinite(at).all() and np.isfinite(s[i]).all() and np.isfinite(jump).all()):
                failed[0] = True
                return
            F = 0 if known else Pb
            _schedule(at, s[i], jump, length, step_angle, max_steps, False, order, seg, steps)
            _march_row(order, seg, steps, jump, active, h, F, True, ei, curv, jac, phi)
            if not known:
                for g in range(G):
                    for k in range(2):
                        m = 2 * g + k
                        r[i, m] = (curv[g, k] - u[b, m]) * w[m]
                        for p in range(Pb):
                            v = jac[g, k, p] * (length if p % 3 == 0 else force_unit)
                            Jraw[m, p] = v * w[m]
                _bounds(lo_all[b], hi_all[b], interval[i], lo, hi)
                _sided(Jraw, s[i], hi, hik_all[b], interval[i], J[i])
            for c in range(C):
                # Phi(c)^-1 applied to the state's jump under a unit f_x and f_y at c: the rhs [0, 0; jumps]
                for a_ in range(4):
                    for b_ in range(4):
                        Mphi[a_, b_] = phi[G + c, a_, b_]
                for j in range(2):
                    col[0] = 0.0
                    col[1] = 0.0
                    col[2] = 0.0 if j == 0 else -inv
                    col[3] = inv if j == 0 else 0.0
                    if not _solve(Mphi, col, x):
                        failed[0] = True  # a singular propagator: the array code's least squares
                        return
                    for a_ in range(4):
                        Msol[a_, j] = x[a_]
                for g in range(G):
                    prox = 1.0 if query[g] < cand[i, c] else 0.0
                    for k in range(2):
                        for j in range(2):
                            v = 0.0
                            for a_ in range(4):
                                v += phi[g, k, a_] * Msol[a_, j]
                            Jc[c, 2 * g + k, j] = (v * prox) * w[2 * g + k] * force_unit
        # _added_force: the base block K inverted once, a 2 x 2 Schur complement per candidate
        d_max = -math.inf
        _gram(J[i], Abb)
        for p in range(Pb):
            d = Abb[p, p]
            if d != d or d > d_max:
                d_max = d
        for c in range(C):
            for a_ in range(2):
                for b_ in range(2):
                    v = 0.0
                    for k in range(n):
                        v += Jc[c, k, a_] * Jc[c, k, b_]
                    Acc[c, a_, b_] = v
                v = 0.0
                for k in range(n):
                    v += r[i, k] * Jc[c, k, a_]
                gc[c, a_] = v
                d = Acc[c, a_, a_]
                if d != d or d > d_max:
                    d_max = d
        scale = d_max if (d_max != d_max or d_max >= scale_min) else scale_min
        base_dec = 0.0
        ok[i] = True
        if Pb:
            for p in range(Pb):
                for q in range(Pb):
                    K[p, q] = Abb[p, q] + (1.0 if p == q else 0.0) * (tiny * Abb[p, p] + floor * scale)
            for q in range(Pb):
                for p in range(Pb):
                    e[p] = 1.0 if p == q else 0.0
                if not _solve(K, e, xk):
                    ok[i] = False
                for p in range(Pb):
                    Kinv[p, q] = xk[p]
            if not ok[i]:
                Kinv[:, :] = 0.0
            _gradient(J[i], r[i], gb)
            for p in range(Pb):
                v = 0.0
                for q in range(Pb):
                    v += Kinv[p, q] * gb[q]
                yb[i, p] = v
                t[p] = gb[p] * v
            base_dec = _sum(t, Pb)
        for c in range(C):
            S00, S01, S10, S11 = Acc[c, 0, 0], Acc[c, 0, 1], Acc[c, 1, 0], Acc[c, 1, 1]
            z0, z1 = gc[c, 0], gc[c, 1]
            if Pb:
                for a_ in range(2):
                    for p in range(Pb):
                        v = 0.0
                        for k in range(n):
                            v += Jc[c, k, a_] * J[i, k, p]
                        Acb[a_, p] = v
                for a_ in range(2):
                    for p in range(Pb):
                        v = 0.0
                        for q in range(Pb):
                            v += Acb[a_, q] * Kinv[q, p]
                        Y[i, c, a_, p] = v
                s00 = s01 = s10 = s11 = 0.0
                y0 = y1 = 0.0
                for p in range(Pb):
                    s00 += Y[i, c, 0, p] * Acb[0, p]
                    s01 += Y[i, c, 0, p] * Acb[1, p]
                    s10 += Y[i, c, 1, p] * Acb[0, p]
                    s11 += Y[i, c, 1, p] * Acb[1, p]
                    y0 += Y[i, c, 0, p] * gb[p]
                    y1 += Y[i, c, 1, p] * gb[p]
                S00, S01, S10, S11 = S00 - s00, S01 - s01, S10 - s10, S11 - s11
                z0, z1 = z0 - y0, z1 - y1
            a = S00 + (tiny * Acc[c, 0, 0] + floor * scale)
            d = S11 + (tiny * Acc[c, 1, 1] + floor * scale)
            bb = 0.5 * (S01 + S10)
            det = a * d - bb * bb
            adds = a > 0.0 and det > 0.0
            if not adds:
                det = 1.0
            x0 = (d * z0 - bb * z1) / det if adds else 0.0
            x1 = (a * z1 - bb * z0) / det if adds else 0.0
            xc[i, c, 0] = x0
            xc[i, c, 1] = x1
            dec[i, c] = base_dec + (z0 * x0 + z1 * x1) if ok[i] else -math.inf


@_jit
def covariance_rows(J, sigma, active, diag_min, eps, cov, condition):
    # uncertainty.gauss_newton_covariance row by row, into cov (B, P, P) and condition (B,).
    B, n, P = J.shape
    Jm = np.empty((n, P))
    Cm = np.empty((P, P))
    d = np.empty(P)
    scale_ok = np.empty(P, np.bool_)
    inv = np.empty(P)
    for b in range(B):
        finite_row = True
        for k in range(n):
            for p in range(P):
                v = J[b, k, p]
                if not math.isfinite(v):
                    finite_row = False
                    v = 0.0
                Jm[k, p] = v
        finite = True  # the scaled matrix (the eigensolver's input)
        any_unscaled = False
        for p in range(P):  # the diagonal and the scales (the array code zeroes inactive columns: they have none)
            acc = 0.0
            if active[b, p]:
                for k in range(n):
                    acc += Jm[k, p] * Jm[k, p]
            scale_ok[p] = active[b, p] and acc > diag_min and math.isfinite(acc)
            d[p] = 1.0 / math.sqrt(max(acc, diag_min)) if scale_ok[p] else 0.0
            any_unscaled = any_unscaled or (active[b, p] and not scale_ok[p])
        for p in range(P):
            for q in range(p + 1):
                if not (scale_ok[p] and scale_ok[q]):
                    v = 1.0 if p == q else 0.0
                else:
                    acc = 0.0
                    for k in range(n):
                        acc += Jm[k, p] * Jm[k, q]
                    v = acc * d[p] * d[q]
                finite = finite and math.isfinite(v)
                Cm[p, q] = v
                Cm[q, p] = v
        ok = finite
        w, V = np.zeros(P), np.zeros((P, P))
        if ok:
            try:
                w, V = np.linalg.eigh(Cm)
            except Exception:  # the eigensolver failed on this row: as the array code, not determined
                ok = False
        lo, hi = w[0], w[P - 1]
        if ok and lo > eps * abs(hi) and not any_unscaled and finite_row:
            condition[b] = hi / (lo if lo > 0 else 1.0)
        else:
            condition[b] = math.inf
        for p in range(P):
            inv[p] = 1.0 / (w[p] if w[p] != 0 else 1.0) if w[p] > eps * abs(hi) else 0.0
        s2 = sigma[b] * sigma[b]
        for p in range(P):
            for q in range(P):
                if ok and finite_row and scale_ok[p] and scale_ok[q]:
                    acc = 0.0
                    for k in range(P):
                        acc += V[p, k] * inv[k] * V[q, k]
                    cov[b, p, q] = acc * d[p] * d[q] * s2
                else:
                    cov[b, p, q] = math.nan


@_jit
def steps_rows(P_, S_, O_, most):
    # Rounds of lm._step, each on the rows not done at its start (in place), as lm.solve's loop takes them: at least
    # one round, then more while their row steps together stay within ``most``; stops early once every row is done
    # or a row failed.
    work = _buffers(S_[1].shape[1], P_[0].shape[0])
    done, failed = S_[17], S_[18]
    R = done.shape[0]
    rows = np.empty(R, np.int64)
    spent = 0
    while True:
        n = 0
        for i in range(R):
            if not done[i]:
                rows[n] = i
                n += 1
        if n == 0 or (spent > 0 and spent + n > most):
            return
        _round(rows[:n], P_, S_, O_, work)
        spent += n
        for k in range(n):
            if failed[rows[k]]:
                return
