"""The Numba kernels of :mod:`torchrod.model.compiled` (imported only where they run: this imports Numba).

Module-level functions, so that Numba's on-disk cache finds them again in a new process."""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def schedule(query, s, jump, length, step_angle, max_steps, bound, order, seg, steps):
    # schedule.row(rule="bound" if bound else "estimate", skip=True), line for line (for "bound", jump holds the
    # magnitudes as complex numbers with zero imaginary parts: their sums are the real sums exactly).
    h = s.shape[0]
    E = h + query.shape[0]
    pos = np.empty(E)
    pos[:h] = s
    pos[h:] = query
    ranked = np.argsort(-pos, kind="mergesort")  # stable: forces first at ties, as sorted(reverse=True)
    passed = np.zeros(h, np.bool_)
    reached = False
    start = length
    cap = float(max_steps)
    top = max(max_steps, 1)
    for e in range(E):
        idx = ranked[e]
        p = pos[idx]
        d = start - p
        if not (d != d or d >= 0.0):
            d = 0.0
        order[e] = idx
        seg[e] = d
        start = p
        if not reached:
            if idx < h:
                reached = True
                passed[idx] = True
            steps[e] = 1 if reached else 0
            continue
        a = 0j
        m = 0j
        for i in range(h):
            if passed[i]:
                x = s[i] - p
                if x > 0.0:
                    a += jump[i] * x
                    m += jump[i]
        if bound:
            rm = math.sqrt(m.real)
            r2 = math.sqrt(2.0 * m.real)
            lo = a.real if a.real <= r2 else r2
            rate = lo if lo >= rm else rm
        else:
            ra = abs(a)
            rm = math.sqrt(abs(m))
            rate = ra if ra != ra or ra >= rm else rm
        need = rate * d / step_angle
        if need != need:
            steps[e] = 1
        elif need >= cap:
            steps[e] = top
        else:
            steps[e] = max(int(math.ceil(need)), 1)
        if idx < h:
            passed[idx] = True


@_jit
def row(order, seg, steps, jump, active, h, F, seeds, ei, curvature, jacobian, propagator):
    # sensitivity._row on one schedule: the same operations in the same order, every column in a fixed slot.
    C = F + 4
    du = np.zeros(C, np.complex128)
    dw = np.zeros(C, np.complex128)
    carried = np.zeros(C, np.bool_)
    if seeds:
        du[F] = 1.0
        du[F + 1] = 1j
        dw[F + 2] = 1.0
        dw[F + 3] = 1j
        carried[F:] = True
    anything = seeds
    u0 = 0j
    w0 = 0j
    d_fx = 1j / ei
    d_fy = -1.0 / ei
    for e in range(order.shape[0]):
        idx = order[e]
        n = steps[e]
        if n == 0 and anything:
            for c in range(C):
                if carried[c]:
                    du[c] = du[c] + seg[e] * dw[c]
        hs = ch = k16 = k4 = k12 = kw = 0.0
        if n:
            hs = seg[e] / n
            ch, k16, k4, k12, kw = 0.5 * hs, -hs * hs / 16.0, -hs * hs / 4.0, -hs * hs / 12.0, -hs / 12.0
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
            t1a, t1b = 2.0 * a1, q1
            s2a, s2b = 1.0 + k16 * t1a, k16 * t1b
            c2 = 2.0 * a2
            t2a, t2b = c2 * s2a + q2 * s2b.conjugate(), c2 * s2b + q2 * s2a.conjugate()
            t2c, t2d = c2 * ch, q2 * ch
            s3a, s3b, s3c, s3d = 1.0 + k4 * t2a, k4 * t2b, hs + k4 * t2c, k4 * t2d
            c3 = 2.0 * a3
            t3a, t3b = c3 * s3a + q3 * s3b.conjugate(), c3 * s3b + q3 * s3a.conjugate()
            t3c, t3d = c3 * s3c + q3 * s3d.conjugate(), c3 * s3d + q3 * s3c.conjugate()
            ya, yb = 1.0 + k12 * (t1a + 2.0 * t2a), k12 * (t1b + 2.0 * t2b)
            yc, yd = hs + k12 * 2.0 * t2c, k12 * 2.0 * t2d
            wa, wb = kw * (t1a + 4.0 * t2a + t3a), kw * (t1b + 4.0 * t2b + t3b)
            wc, wd = 1.0 + kw * (4.0 * t2c + t3c), kw * (4.0 * t2d + t3d)
            for c in range(C):
                if carried[c]:
                    y = du[c]
                    w = dw[c]
                    yy = y.conjugate()
                    ww = w.conjugate()
                    du[c] = ya * y + yb * yy + yc * w + yd * ww
                    dw[c] = wa * y + wb * yy + wc * w + wd * ww
        if idx < h:
            w0 += jump[idx]
            if F and active[idx]:
                anything = True
                k = 3 * idx
                carried[k] = carried[k + 1] = carried[k + 2] = True
                du[k] = jump[idx]
                dw[k + 1] = d_fx
                dw[k + 2] = d_fy
        else:
            q = idx - h
            curvature[q, 0] = u0.real
            curvature[q, 1] = u0.imag
            for c in range(F):
                jacobian[q, 0, c] = du[c].real
                jacobian[q, 1, c] = du[c].imag
            if seeds:
                for c in range(4):
                    propagator[q, 0, c] = du[F + c].real
                    propagator[q, 1, c] = du[F + c].imag
                    propagator[q, 2, c] = dw[F + c].real
                    propagator[q, 3, c] = dw[F + c].imag


@_jit
def batch(query, s, jump, active, length, ei, curvature, jacobian, propagator, F, seeds, step_angle, max_steps,
          marched):  # fmt: skip
    B, h = s.shape
    E = h + query.shape[1]
    order = np.empty(E, np.int64)
    seg = np.empty(E)
    steps = np.empty(E, np.int64)
    for b in range(B):
        at = query[0] if query.shape[0] == 1 else query[b]
        if not (np.isfinite(at).all() and np.isfinite(s[b]).all() and np.isfinite(jump[b]).all()):
            continue
        schedule(at, s[b], jump[b], length, step_angle, max_steps, False, order, seg, steps)
        row(order, seg, steps, jump[b], active[b], h, F, seeds, ei, curvature[b], jacobian[b],
            propagator[b] if seeds else propagator[0])  # fmt: skip
        marched[b] = True


@_jit
def _weighted(w, G, n):
    # sum_{j < n} w_j G_j over the nonzero w_j, from the first term on: nystrom._forward_generic's sums exactly.
    acc = 0j
    first = True
    for j in range(n):
        if w[j] != 0.0:
            acc = w[j] * G[j] if first else acc + w[j] * G[j]
            first = False
    return acc


@_jit
def exact_rows(query, s, magnitude, jump, length, step_angle, max_steps, c, a, bp, bv, fsal, curvature, marched):
    # body_frame.march_curvature's rows: schedule.row(rule="bound", skip=True), then nystrom._forward_generic on
    # the tableau (c, a, bp, bv, fsal) with the slope jump after a force's last step: the same operations in the
    # same order (each sum over a tableau row starts from its first nonzero term, as the Python one does).
    B, h = s.shape
    Q = query.shape[0]
    S = c.shape[0]
    E = h + Q
    order = np.empty(E, np.int64)
    seg = np.empty(E)
    steps = np.empty(E, np.int64)
    Ys = np.empty(S, np.complex128)
    Gs = np.empty(S, np.complex128)
    for b in range(B):
        if not (np.isfinite(s[b]).all() and np.isfinite(jump[b]).all() and np.isfinite(magnitude[b]).all()):
            continue
        schedule(query, s[b], magnitude[b] + 0j, length, step_angle, max_steps, True, order, seg, steps)
        U = 0j
        W = 0j
        stepped = False
        carried = False
        Gc = 0j
        for e in range(E):
            idx = order[e]
            n = steps[e]
            hstep = seg[e] / n if n else 0.0
            h2 = hstep * hstep
            for _ in range(n):
                hW = hstep * W
                Ys[0] = U
                Gs[0] = Gc if carried else (U.real * U.real + U.imag * U.imag) * U
                for i in range(1, S):
                    Y = U + c[i] * hW + h2 * _weighted(a[i], Gs, i)
                    G = (Y.real * Y.real + Y.imag * Y.imag) * Y
                    if fsal and i == S - 1:
                        Gc = G
                        carried = True
                    Ys[i] = Y
                    Gs[i] = G
                W_new = W + hstep * _weighted(bv, Gs, S)
                if fsal:
                    U_new = Ys[S - 1]
                else:
                    U_new = U + hW + h2 * _weighted(bp, Gs, S)
                U = U_new
                W = W_new
                stepped = True
            if idx < h:
                if n and jump[b, idx] != 0:
                    W = W + jump[b, idx]
            elif stepped:
                curvature[b, idx - h, 0] = U.real
                curvature[b, idx - h, 1] = U.imag
            else:
                curvature[b, idx - h, 0] = 0.0
                curvature[b, idx - h, 1] = 0.0
        marched[b] = True
