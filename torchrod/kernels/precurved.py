"""The precurved rod's march for one force set, with the tangents and the propagator the estimator needs.

A rod with intrinsic curvature u* twists under load, so the straight rod's complex reduction does not hold; the
body-frame internal force n and moment m obey, between forces (docs/physics.md, "Precurved rods"),

    n' = -u x n,      m' = -u x m - e3 x n,      u = u* + K^-1 m,      K = diag(EI, EI, GJ),

from n = m = 0 at the free tip, with n jumping by the force (f_x, f_y, 0) across each force, going towards the
base. u* is piecewise constant; the events (forces, queries, the base and the ends of the u* segments) split the
rod so that u* is constant on every step. Each segment takes ``ceil(segment / max_step)`` classical Runge-Kutta
steps, so the error falls as ``max_step^4``. A query reads ``u*(s) + K^-1 m(s)``, with u* just distal to a segment
end; at a tie a force is applied before a query at the same place is read.

The same steps carry tangent columns: for each force, d/ds (the difference of the rates on the two sides of its
jump, ``(u x f, e3 x f)``), d/df_x and d/df_y (unit jumps of n); with ``seeds``, six unit perturbations of (n, m)
at the tip, whose responses make the propagator of the linearised equations (the scan's responses to a force added
anywhere). :mod:`torchrod.model.precurved` integrates the same equations in torch for the simulator.
"""

import math

from .march import event_order, event_position
from .views import march_of, model_of, precurved_of

PRECURVED_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "precurved": {  # the precurved march's state and Runge-Kutta stages
        "yn": ((3, "NC"), "f"), "ym": ((3, "NC"), "f"), "tn": ((3, "NC"), "f"), "tm": ((3, "NC"), "f"),
        "kn": ((3, "NC"), "f"), "km": ((3, "NC"), "f"), "an": ((3, "NC"), "f"), "am": ((3, "NC"), "f"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

FIT_MAX_STEP = 1e-2
"""Longest step [m] of the fitting model (relative error ~4e-5)."""

EXACT_MAX_STEP = 1e-3
"""Longest step [m] of the exact model, which the final steps of every fit and the losses the tests judge use
(relative error ~3e-9: far below the noise floor)."""

INLINE = (
    "intrinsic_x",
    "intrinsic_y",
)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def intrinsic_x(segments, nseg, length, s):
    """u*_x at s [1/m]: the value of the last segment holding s (just distal to a segment end)."""
    v = 0.0
    for k in range(nseg):
        a = segments[k, 0]
        b = segments[k, 1]
        if s >= a and (s < b or (s == b and b == length)):
            v = segments[k, 2]
    return v


def intrinsic_y(segments, nseg, length, s):
    """u*_y at s [1/m] (as :func:`intrinsic_x`)."""
    v = 0.0
    for k in range(nseg):
        a = segments[k, 0]
        b = segments[k, 1]
        if s >= a and (s < b or (s == b and b == length)):
            v = segments[k, 3]
    return v


def precurved_rates(Yn, Ym, Rn, Rm, ux0, uy0, k1, k3, NC):
    """(Rn, Rm) (3, NC) = d/ds of (Yn, Ym): the equations on column 0, their linearisation on the others."""
    ux = ux0 + Ym[0, 0] * k1
    uy = uy0 + Ym[1, 0] * k1
    uz = Ym[2, 0] * k3
    n0 = Yn[0, 0]
    n1 = Yn[1, 0]
    n2 = Yn[2, 0]
    m0 = Ym[0, 0]
    m1 = Ym[1, 0]
    m2 = Ym[2, 0]
    for c in range(NC):
        a0 = Yn[0, c]
        a1 = Yn[1, c]
        a2 = Yn[2, c]
        b0 = Ym[0, c]
        b1 = Ym[1, c]
        b2 = Ym[2, c]
        # -u x n and -u x m - e3 x n
        r0 = -(uy * a2 - uz * a1)
        r1 = -(uz * a0 - ux * a2)
        r2 = -(ux * a1 - uy * a0)
        q0 = -(uy * b2 - uz * b1) + a1
        q1 = -(uz * b0 - ux * b2) - a0
        q2 = -(ux * b1 - uy * b0)
        if c > 0:  # the tangents: + n x du and + m x du, du = K^-1 dm
            d0 = b0 * k1
            d1 = b1 * k1
            d2 = b2 * k3
            r0 += n1 * d2 - n2 * d1
            r1 += n2 * d0 - n0 * d2
            r2 += n0 * d1 - n1 * d0
            q0 += m1 * d2 - m2 * d1
            q1 += m2 * d0 - m0 * d2
            q2 += m0 * d1 - m1 * d0
        Rn[0, c] = r0
        Rn[1, c] = r1
        Rn[2, c] = r2
        Rm[0, c] = q0
        Rm[1, c] = q1
        Rm[2, c] = q2


def march_precurved(k, query, Q, s, f, h, F, seeds, max_step):
    """The precurved rod at ``Q`` queries (module docstring), into the march views: curvature ``curv`` (Q, 2)
    [1/m] (u_x, u_y, the total curvature); with ``F`` = 3h the Jacobian ``jac`` (Q, 2, F) w.r.t. each force's
    (s [m], f_x [N], f_y [N]); with ``seeds`` the propagator ``phi`` (Q, 8, 6): rows d(u_x, u_y) then d(n, m) at
    the query, columns d(n, m) at the tip. False where an input is not finite (outputs NaN)."""
    rod = k.rod
    model = model_of(k)
    segments = model.segments
    extra = model.extra  # the base and the ends of the u* segments
    mw = march_of(k)
    pw = precurved_of(k)
    curv = mw.curv
    jac = mw.jac
    phi = mw.phi
    nseg = rod.nseg
    L = rod.length
    k1 = 1.0 / rod.ei
    k3 = 1.0 / rod.gj
    ok = True
    for j in range(h):
        ok = ok and math.isfinite(s[j]) and math.isfinite(f[j, 0]) and math.isfinite(f[j, 1])
    if not ok:
        for q in range(Q):
            curv[q, 0] = math.nan
            curv[q, 1] = math.nan
            for c in range(F):
                jac[q, 0, c] = math.nan
                jac[q, 1, c] = math.nan
        return False
    NX = rod.nextra
    E = h + Q + NX
    order = mw.order
    event_order(query, Q, extra, NX, s, h, order)
    NC = 1 + F + (6 if seeds else 0)
    Yn = pw.yn
    Ym = pw.ym
    Tn = pw.tn
    Tm = pw.tm
    Kn = pw.kn
    Km = pw.km
    An = pw.an
    Am = pw.am
    for i in range(3):
        for c in range(NC):
            Yn[i, c] = 0.0
            Ym[i, c] = 0.0
    if seeds:
        for i in range(3):
            Yn[i, F + 1 + i] = 1.0
            Ym[i, F + 4 + i] = 1.0
    cur = L
    for e in range(E):
        k = order[e]
        target = event_position(s, query, extra, h, Q, k)
        seg = cur - target
        n_steps = 0
        if seg > 0.0:
            n_steps = int(math.ceil(seg / max_step - 1e-9))
            if n_steps < 1:
                n_steps = 1
        if n_steps:
            hs = -seg / n_steps
            half = 0.5 * hs
            sixth = hs / 6.0
            mid = 0.5 * (cur + target)
            ux0 = intrinsic_x(segments, nseg, L, mid)
            uy0 = intrinsic_y(segments, nseg, L, mid)
            for _ in range(n_steps):
                precurved_rates(Yn, Ym, Kn, Km, ux0, uy0, k1, k3, NC)
                for i in range(3):
                    for c in range(NC):
                        An[i, c] = Kn[i, c]
                        Am[i, c] = Km[i, c]
                        Tn[i, c] = Yn[i, c] + half * Kn[i, c]
                        Tm[i, c] = Ym[i, c] + half * Km[i, c]
                precurved_rates(Tn, Tm, Kn, Km, ux0, uy0, k1, k3, NC)
                for i in range(3):
                    for c in range(NC):
                        An[i, c] += 2.0 * Kn[i, c]
                        Am[i, c] += 2.0 * Km[i, c]
                        Tn[i, c] = Yn[i, c] + half * Kn[i, c]
                        Tm[i, c] = Ym[i, c] + half * Km[i, c]
                precurved_rates(Tn, Tm, Kn, Km, ux0, uy0, k1, k3, NC)
                for i in range(3):
                    for c in range(NC):
                        An[i, c] += 2.0 * Kn[i, c]
                        Am[i, c] += 2.0 * Km[i, c]
                        Tn[i, c] = Yn[i, c] + hs * Kn[i, c]
                        Tm[i, c] = Ym[i, c] + hs * Km[i, c]
                precurved_rates(Tn, Tm, Kn, Km, ux0, uy0, k1, k3, NC)
                for i in range(3):
                    for c in range(NC):
                        Yn[i, c] += sixth * (An[i, c] + Kn[i, c])
                        Ym[i, c] += sixth * (Am[i, c] + Km[i, c])
        cur = target
        if k < h:
            fx = f[k, 0]
            fy = f[k, 1]
            if F:
                # The force's columns start here: d/ds = the rates' difference across the jump, with u* just
                # distal to the force; d/df_x, d/df_y the unit jumps of n.
                ux = intrinsic_x(segments, nseg, L, target) + Ym[0, 0] * k1
                uy = intrinsic_y(segments, nseg, L, target) + Ym[1, 0] * k1
                uz = Ym[2, 0] * k3
                b = 1 + 3 * k
                Yn[0, b] += -uz * fy
                Yn[1, b] += uz * fx
                Yn[2, b] += ux * fy - uy * fx
                Ym[0, b] += -fy
                Ym[1, b] += fx
                Yn[0, b + 1] += 1.0
                Yn[1, b + 2] += 1.0
            Yn[0, 0] += fx
            Yn[1, 0] += fy
        elif k < h + Q:
            q = k - h
            curv[q, 0] = intrinsic_x(segments, nseg, L, target) + Ym[0, 0] * k1
            curv[q, 1] = intrinsic_y(segments, nseg, L, target) + Ym[1, 0] * k1
            for c in range(F):
                jac[q, 0, c] = Ym[0, 1 + c] * k1
                jac[q, 1, c] = Ym[1, 1 + c] * k1
            if seeds:
                for c in range(6):
                    col = F + 1 + c
                    phi[q, 0, c] = Ym[0, col] * k1
                    phi[q, 1, c] = Ym[1, col] * k1
                    for i in range(3):
                        phi[q, 2 + i, c] = Yn[i, col]
                        phi[q, 5 + i, c] = Ym[i, col]
    return True
