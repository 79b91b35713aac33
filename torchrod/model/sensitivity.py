"""Curvature at the gratings and its Jacobian w.r.t. the forces, in one tip-to-base pass (forward sensitivities).

Estimation evaluates the forward model many times per reading and always wants the derivative with respect to
every unknown (s_i, f_x,i, f_y,i). With at most a few forces there are few unknowns, so carrying their tangents
along the march (forward mode) gives the whole residual Jacobian in one pass, which the estimator needs anyway
for its Gauss-Newton steps, stopping test, scans and covariance.

The march is the body-frame model of :mod:`torchrod.model.body_frame` in complex form: with U = u_x + i u_y and
t = L - s, U_tt = -|U|^2 U / 2 between forces, U = U_t = 0 at the free tip, and at a force (f_x, f_y) at s_i the
slope jumps, W = U_t -> W + i (f_x + i f_y) / EI. A fourth-order Runge-Kutta-Nystrom scheme integrates it, on the
schedule of :mod:`torchrod.model.schedule` (events, tie-breaks and step counts; rule ``"estimate"``).

Tangents. For a parameter p, (dU/dp, dW/dp) obey the linearised equation, with
D(|U|^2 U)[dU] = 2 |U|^2 dU + U^2 conj(dU); the RKN stages are applied to the tangents with that linearisation
(the tangent of the discrete scheme). Every stage is linear in (U, dU) except g = |U|^2 U, and g is homogeneous of
degree 3 (D g[U] = 3 g), so primal and tangents share one (B, 1 + P) complex state and one set of operations.
At a force event:

* d/df_x and d/df_y: the slope jump adds i / EI and -1 / EI to dW.
* d/ds_i: moving the force distally by ds moves the jump earlier in t by ds; to first order the state just
  proximal to the force changes by (F(Y+) - F(Y-)) ds with F(U, W) = (W, -|U|^2 U / 2) the vector field, which is
  (jump, 0) since U is continuous. So dU/ds_i gains the jump i (f_x + i f_y) / EI and dW/ds_i is unchanged. This
  is the exact derivative of the continuous problem; it matches the discrete scheme's to its O(h^4) accuracy. At a
  grating exactly at s_i the schedule's tie-break (forces first) gives the distal one-sided derivative there.

A force of zero magnitude changes nothing, but its f-columns are the linearised response to a new force at its
location: the estimator's scan for where to add a force uses exactly that.

Implementations of the one scheme: :func:`march` on arrays (NumPy or torch, :mod:`torchrod.backend`, batched),
and :func:`_march_rows` one row at a time on the CPU (no per-operation overhead), on Python complex numbers or,
where Numba is installed, compiled (:mod:`torchrod.model.compiled`: the same operations, so the same numbers
exactly). Arrays and rows give the same numbers to rounding (tests/test_sensitivity.py).
"""

from __future__ import annotations

from typing import Any

import torch

from ..backend import NUMPY, Backend, TorchBackend
from . import compiled
from .schedule import events, sequence, skip_unloaded, step_counts
from .schedule import row as row_schedule

__all__ = [
    "CHUNK",
    "ESTIMATION_STEP_ANGLE",
    "SCALAR_WORK",
    "curvature_and_jacobian",
    "march",
    "march_propagator",
    "march_work",
]

SCALAR_WORK = 80
"""Batches on the NumPy backend whose work (:func:`march_work`) is at most this are marched one row at a time on
Python complex numbers (no per-operation overhead), larger ones on arrays. The first path's cost grows with that
work, the second's is mostly fixed per operation at small batch: this puts the switch at the crossover
``torchrod bench forward --paths`` measures (docs/results.md). Where the compiled rows run
(:func:`torchrod.model.compiled.available`), every batch on the NumPy backend takes them: they cost less than the
arrays at every batch size that command measures."""


def march_work(rows: int, columns: int) -> int:
    """The work of a march of ``rows`` rows carrying ``columns`` tangent columns (3 per force with the Jacobian, 4
    with the propagator's seeds): rows x (4 + columns), the measure :data:`SCALAR_WORK` is set against."""
    return rows * (4 + columns)


CHUNK = 384
"""Rows marched together (larger batches are split: the working set stays in cache, and each part gets step
counts for its own rows; measured on 2 cores: 2700 rows of 3 forces take 92 ms in one march, 56 ms in chunks)."""

ESTIMATION_STEP_ANGLE = 0.3
"""Default bound on (local rate) x (step) for estimation. Over the synthetic envelope (1-3 forces, 0.05-2 N, bending
up to 90 degrees; 400 cases) the curvature at the gratings is within 5.0e-4 1/m of the converged solution (99th
percentile 2.9e-4; 0.2: 1.5e-4, 0.4: 9.6e-4), a twentieth of the estimator's noise floor."""


def march(
    xp: Backend,
    query: Any,
    s: Any,
    f: Any,
    length: float,
    bending_stiffness: float,
    *,
    active: Any = None,
    jacobian: bool = True,
    step_angle: float = ESTIMATION_STEP_ANGLE,
    max_steps: int = 64,
) -> tuple[Any, Any]:
    """Curvature at ``query`` and, optionally, its derivative w.r.t. each force's (s, f_x, f_y). Unchecked.

    Args:
        xp: the backend of the arrays.
        query: (Q,) or per row (B, Q) positions [m] in [0, L] (the gratings).
        s: (B, h) force locations [m] in [0, L].
        f: (B, h, 2) body-frame components (f_x, f_y) [N].
        length: L [m]; bending_stiffness: EI [N m^2].
        active: (B, h) bool, False for padded forces (no load, zero Jacobian columns); None: all real.
        jacobian: also return the Jacobian.
        step_angle: bound on (rate) x (step) per RKN step; max_steps: cap on the steps per segment.
    Returns:
        curvature (B, Q, 2) [1/m], and the Jacobian (B, Q, 2, h, 3) of (u_x, u_y) w.r.t. (s [m], f_x [N], f_y [N])
        of each force ([1/m^2], [1/(m N)], [1/(m N)]), or None.
    """
    u, jac, _ = _march(xp, query, s, f, length, bending_stiffness, active, jacobian, False, step_angle, max_steps)
    return u, jac


def march_propagator(
    xp: Backend,
    query: Any,
    s: Any,
    f: Any,
    length: float,
    bending_stiffness: float,
    *,
    jacobian: bool = True,
    step_angle: float = ESTIMATION_STEP_ANGLE,
    max_steps: int = 64,
) -> tuple[Any, Any, Any]:
    """:func:`march` (with the Jacobian unless ``jacobian=False``), plus the propagator of the linearised equation
    at each query.

    The propagator Phi(p) (4 x 4, real) maps a perturbation (dU, dW) of the state at the free tip, as the real
    vector (Re dU, Im dU, Re dW, Im dW), to the perturbation it causes at p. The response at a query p of a slope
    jump dW at a point c distal to it is then Phi(p) Phi(c)^-1 (0, 0, Re dW, Im dW): the effect of a new force at
    c, for every pair (p, c), from one march (the linearised flow is volume-preserving, det Phi = 1).

    Returns:
        curvature (B, Q, 2), Jacobian (B, Q, 2, h, 3) as :func:`march` (or None), and Phi (B, Q, 4, 4).
    """
    return _march(xp, query, s, f, length, bending_stiffness, None, jacobian, True, step_angle, max_steps)


def _march(xp, query, s, f, length, ei, active, jacobian, seeds, step_angle, max_steps):
    B = s.shape[0]
    columns = (3 * s.shape[1] if jacobian else 0) + (4 if seeds else 0)
    if xp.name == "numpy" and (march_work(B, columns) <= SCALAR_WORK or compiled.available()):
        return _march_rows(query, s, f, length, ei, active, jacobian, seeds, step_angle, max_steps)
    if B > CHUNK:
        parts = [
            _march_arrays(
                xp,
                query if query.ndim == 1 else query[i : i + CHUNK],
                s[i : i + CHUNK],
                f[i : i + CHUNK],
                length,
                ei,
                None if active is None else active[i : i + CHUNK],
                jacobian,
                seeds,
                step_angle,
                max_steps,
            )
            for i in range(0, B, CHUNK)
        ]

        def cat(k):
            return None if parts[0][k] is None else xp.concat([p[k] for p in parts])

        return cat(0), cat(1), cat(2)
    return _march_arrays(xp, query, s, f, length, ei, active, jacobian, seeds, step_angle, max_steps)


def _jumps(xp: Backend, f: Any, active: Any, ei: float) -> Any:
    """(B, h) complex slope jumps J_i = i (f_x + i f_y) / EI [1/m^2], zero for padding."""
    jump = xp.complex(-f[..., 1], f[..., 0]) / ei
    return jump if active is None else xp.where(active, jump, 0.0 * jump)


def _schedule(xp, query, s, jump, length, step_angle, max_steps, skip):
    """The events and step counts of :mod:`.schedule`; ``skip``: the unloaded events get no steps."""
    pos, order, seg = events(xp, query, s, length)
    steps = step_counts(xp, s, jump, pos, seg, step_angle=step_angle, max_steps=max_steps, rule="estimate")
    if skip:
        steps = skip_unloaded(xp, order, steps, s.shape[1])
    return pos, order, seg, steps


def _g(xp: Backend, y: Any) -> Any:
    """Column 0: g = |y0|^2 y0; columns 1..P: its tangent 2 |y0|^2 y_p + y0^2 conj(y_p). y: (B, 1 + P) complex."""
    cy = xp.conj(y)
    y0 = y[:, :1]
    a = y0 * cy[:, :1]  # |y0|^2, complex-typed so that no operation below converts dtypes
    g = (y0 * y0) * cy + (a + a) * y  # column 0: 3 g (D g[y0] = 3 g)
    g[:, :1] *= 1.0 / 3.0
    return g


def _march_arrays(xp, query, s, f, length, ei, active, jacobian, seeds, step_angle, max_steps):
    """:func:`march` on arrays: all rows at once, each on its own schedule. Iteration k takes every row's k-th
    step (its events' steps one after the other; a row whose schedule is done steps by zero, which leaves its
    state unchanged), so a batch costs the largest row's step count, not the sum over events of the largest
    counts. The rows are taken in decreasing order of their step counts, so the rows that still step at
    iteration k are a leading slice (a view) and the finished ones cost nothing (a batch's rows differ in their
    counts by a third on average). With ``seeds``, four more tangent columns start at the tip from the unit
    perturbations of (U, W) (:func:`march_propagator`)."""
    B, h = s.shape
    Q = query.shape[-1]
    ei = float(ei)
    jump_f = _jumps(xp, f, active, ei)  # (B, h)
    # The seeds move from the tip on, so with them every event steps (a step of the zero state advances them by
    # the linear map exactly).
    pos, order, seg, steps_be = _schedule(xp, query, s, jump_f, length, step_angle, max_steps, not seeds)

    F = 3 * h if jacobian else 0
    S = 4 if seeds else 0
    P = F + S
    C = 1 + P

    # Slots: slot j holds the state after j steps and the jumps of the events that end there (schedule.sequence:
    # each row takes its events' steps one after the other; slot 0 is before any step).
    hstep, slot = sequence(xp, order, seg, steps_be)  # (B, K), (B, E) in force-then-query order
    K = hstep.shape[1]
    # Rows by decreasing step count (perm), and live[k]: how many of them take a k-th step (k = 0..K-1).
    total = xp.amax(slot, 1)
    perm = xp.argsort_desc(total)
    rank = xp.put(xp.zeros((B,), "int"), perm, xp.arange(B))  # row b's place in that order
    live = xp.tolist(B - xp.lib.cumsum(xp.lib.bincount(total, minlength=K + 1), 0)[:K])
    at_step = slot[:, h:]  # (B, Q) each query's record: the slot that ends its event, in input order
    hstep, slot, jump_f = hstep[perm], slot[perm], jump_f[perm]
    active = None if active is None else active[perm]
    hstep = xp.astype(hstep, "complex")
    # The RKN coefficients of every step (K, B, 1): hs, hs/2, -hs^2/16, -hs^2/4, -hs^2/12, -hs/12.
    hs_k = xp.mT(hstep)[:, :, None]
    h2_k = hs_k * hs_k
    ch_k, k16_k, k4_k, k12_k, kw_k = (
        0.5 * hs_k,
        (-1.0 / 16.0) * h2_k,
        -0.25 * h2_k,
        (-1.0 / 12.0) * h2_k,
        (-1.0 / 12.0) * hs_k,
    )

    # The jumps of each force (B, h, C): column 0 the primal slope jump, then its own tangents' (dW for f_x, f_y,
    # dU for s), placed in the slot that ends its event.
    jump_w = xp.zeros((B, h, C), "complex")
    jump_u = xp.zeros((B, h, C), "complex")
    jump_w[:, :, 0] = jump_f
    if jacobian:
        real = xp.ones((B, h), "complex") if active is None else xp.astype(active, "complex")
        for i in range(h):
            jump_u[:, i, 1 + 3 * i] = jump_f[:, i]
            jump_w[:, i, 2 + 3 * i] = real[:, i] * (1j / ei)
            jump_w[:, i, 3 + 3 * i] = real[:, i] * (-1.0 / ei)
    # The kicks of each slot: the (row, force) pairs whose event ends there, grouped by slot. A force's event
    # always takes a step of its own (step_counts gives every segment one), so a row has at most one pair per slot.
    pair_slot = slot[:, :h].reshape(B * h)
    by_slot = xp.argsort_desc(-xp.astype(pair_slot, "float")[None, :])[0]  # pairs in increasing slot order
    ends = [0] + xp.tolist(xp.lib.cumsum(xp.lib.bincount(pair_slot, minlength=K + 1), 0))  # slot j: ends[j:j + 2]
    kick_rows = by_slot // h if h > 1 else by_slot
    kick_u, kick_w = jump_u.reshape(B * h, C)[by_slot], jump_w.reshape(B * h, C)[by_slot]

    def kick(Z, Zw, j):
        a, b = ends[j], ends[j + 1]
        if a == b:
            return Z, Zw
        rows = kick_rows[a:b]
        if xp.name == "numpy":  # in place: Z and Zw are this step's own arrays
            Z[rows] += kick_u[a:b]
            Zw[rows] += kick_w[a:b]
            return Z, Zw
        return Z.index_add(0, rows, kick_u[a:b]), Zw.index_add(0, rows, kick_w[a:b])

    Z = xp.zeros((B, 1 + P), "complex")  # U and its tangents
    Zw = xp.zeros((B, 1 + P), "complex")  # W = U_t and its tangents
    if seeds:
        Z = Z + xp.asarray([0.0] * (1 + F) + [1.0, 1j, 0.0, 0.0], "complex")
        Zw = Zw + xp.asarray([0.0] * (1 + F) + [0.0, 0.0, 1.0, 1j], "complex")
    Z, Zw = kick(Z, Zw, 0)
    # The state after each step (slot k + 1) for the rows that take that step (the others' later slots are never
    # read), one after the other: slot j's rows start at offset[j].
    recorded, recorded_w = [Z], [Zw]
    offset = [0, B]
    for k in range(K):
        m = live[k]
        Z, Zw = Z[:m], Zw[:m]
        # RKN4 (the classical three-stage method).
        hs = hs_k[k, :m]
        g1 = _g(xp, Z)
        g2 = _g(xp, Z + ch_k[k, :m] * Zw + k16_k[k, :m] * g1)
        p = Z + hs * Zw
        g3 = _g(xp, p + k4_k[k, :m] * g2)
        two = g2 + g2
        t = g1 + two
        Z = p + k12_k[k, :m] * t
        Zw = Zw + kw_k[k, :m] * (t + two + g3)
        Z, Zw = kick(Z, Zw, k + 1)
        recorded.append(Z)
        if seeds:
            recorded_w.append(Zw)
        offset.append(offset[-1] + m)
    at = xp.asarray(offset, "int")[at_step] + rank[:, None]  # (B, Q) each query's record, rows in input order
    at_query = xp.concat(recorded)[at]  # (B, Q, 1 + P)
    curvature = xp.real_pairs(at_query[..., 0])
    jac = phi = None
    if jacobian:
        jac = xp.mT(xp.real_pairs(at_query[..., 1 : 1 + F])).reshape(B, Q, 2, h, 3)  # (B, Q, F, 2) -> ...
    if seeds:
        w_query = xp.concat(recorded_w)[at]
        du, dw = xp.real_pairs(at_query[..., 1 + F :]), xp.real_pairs(w_query[..., 1 + F :])  # (B, Q, 4, 2)
        phi = xp.mT(xp.concat([du, dw], 3))  # (B, Q, 4 rows, 4 seeds)
    return curvature, jac, phi


def _march_rows(query, s, f, length, ei, active, jacobian, seeds, step_angle, max_steps):
    """:func:`march` on NumPy arrays one row at a time: its schedule (:func:`.schedule.row`), then its march on
    complex numbers (:func:`_row`), each compiled where :func:`.compiled.available` (rows with a non-finite input
    excepted), else on Python numbers."""
    import numpy as np

    B, h = s.shape
    Q = query.shape[-1]
    ei = float(ei)
    F = 3 * h if jacobian else 0
    curv = np.zeros((B, Q, 2))
    jac = np.zeros((B, Q, 2, F)) if jacobian else None
    phi = np.zeros((B, Q, 4, 4)) if seeds else None
    jump = _jumps(NUMPY, f, active, ei)
    python = range(B)
    if compiled.takes(march_work(B, F + 4 * seeds) > SCALAR_WORK):
        # The same march compiled (the smaller marches give the same numbers on either); rows with a non-finite
        # input stay on Python numbers.
        marched = compiled.march_rows(query, s, jump, active, length, ei, curv, jac, phi, step_angle, max_steps)
        python = np.flatnonzero(~marched).tolist()
    if not len(python):
        return curv, (jac.reshape(B, Q, 2, h, 3) if jacobian else None), phi
    on = [[True] * h] * B if active is None else active.tolist()
    positions, jumps, queries = s.tolist(), jump.tolist(), query.tolist()
    for b in python:
        order, seg, steps = row_schedule(
            queries if query.ndim == 1 else queries[b],
            positions[b],
            jumps[b],
            length,
            step_angle=step_angle,
            max_steps=max_steps,
            rule="estimate",
            skip=True,
        )
        u, du, dw = _row(order, seg, steps, jumps[b], on[b], Q, h, F, seeds, ei)
        z = np.asarray(u)
        curv[b, :, 0], curv[b, :, 1] = z.real, z.imag
        d = np.asarray(du).reshape(Q, F + 4 * seeds)
        if jacobian:
            jac[b, :, 0], jac[b, :, 1] = d[:, :F].real, d[:, :F].imag
        if seeds:
            w = np.asarray(dw).reshape(Q, 4)
            phi[b] = np.stack((d[:, F:].real, d[:, F:].imag, w.real, w.imag), axis=1)
    return curv, (jac.reshape(B, Q, 2, h, 3) if jacobian else None), phi


def _row(order, seg, steps, jumps, active, Q, h, F, seeds, ei):
    """One row of the march on Python complex numbers, on a precomputed schedule (same scheme as the arrays).

    Returns U at each query (Q complex), for each query its F + 4 seeds tangents dU, and (with ``seeds``) the
    seeds' dW (the force tangents' dW are not kept). A force's three tangent columns are zero until the march
    reaches the force, so they are carried only from there on (``cols``: the columns carried, in ``du``/``dw``
    order).
    """
    u0, w0 = 0j, 0j  # U and W = U_t
    cols = list(range(F, F + 4)) if seeds else []
    du = [1.0 + 0j, 1j, 0j, 0j] if seeds else []
    dw = [0j, 0j, 1.0 + 0j, 1j] if seeds else []
    zeros = [0j] * (F + (4 if seeds else 0))
    out_u = [0j] * Q
    out_j: list[list[complex]] = [[]] * Q
    out_w: list[list[complex]] = [[]] * Q
    d_fx, d_fy = 1j / ei, -1.0 / ei
    for e, idx in enumerate(order):
        n = steps[e]  # 0 distal to every force (schedule.skip_unloaded): the state is zero there
        if not n and du:
            # The zero state's tangent map over the segment is exactly linear (g's derivative vanishes at U = 0):
            # the seeds advance in one move, dU += seg dW, where a step of the scheme would give the same.
            du = [y + seg[e] * w for y, w in zip(du, dw, strict=True)]
        if n:
            hs = seg[e] / n
            ch, k16, k4, k12, kw = 0.5 * hs, -hs * hs / 16.0, -hs * hs / 4.0, -hs * hs / 12.0, -hs / 12.0
        for _ in range(n):
            # The primal stages, g(U) = |U|^2 U at each.
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
            if not du:
                continue
            # The step's tangent map is real-linear, the same for every column: dU' = A dU + B conj(dU) + C dW +
            # D conj(dW), dW' likewise. Its coefficients, from the same three stages (each stage's tangent is
            # 2 |y|^2 x + y^2 conj(x)), cost a fixed few operations; every column then costs two of those forms.
            t1a, t1b = 2.0 * a1, q1  # stage 1's tangent of dU (no dW)
            s2a, s2b = 1.0 + k16 * t1a, k16 * t1b  # the stage-2 point: dU + ch dW + k16 t1
            c2 = 2.0 * a2
            t2a, t2b = c2 * s2a + q2 * s2b.conjugate(), c2 * s2b + q2 * s2a.conjugate()
            t2c, t2d = c2 * ch, q2 * ch
            s3a, s3b, s3c, s3d = 1.0 + k4 * t2a, k4 * t2b, hs + k4 * t2c, k4 * t2d  # dU + hs dW + k4 t2
            c3 = 2.0 * a3
            t3a, t3b = c3 * s3a + q3 * s3b.conjugate(), c3 * s3b + q3 * s3a.conjugate()
            t3c, t3d = c3 * s3c + q3 * s3d.conjugate(), c3 * s3d + q3 * s3c.conjugate()
            ya, yb = 1.0 + k12 * (t1a + 2.0 * t2a), k12 * (t1b + 2.0 * t2b)
            yc, yd = hs + k12 * 2.0 * t2c, k12 * 2.0 * t2d
            wa, wb = kw * (t1a + 4.0 * t2a + t3a), kw * (t1b + 4.0 * t2b + t3b)
            wc, wd = 1.0 + kw * (4.0 * t2c + t3c), kw * (4.0 * t2d + t3d)
            du_next, dw_next = [], []
            add_u, add_w = du_next.append, dw_next.append
            for y, w in zip(du, dw, strict=True):
                yy, ww = y.conjugate(), w.conjugate()
                add_u(ya * y + yb * yy + yc * w + yd * ww)
                add_w(wa * y + wb * yy + wc * w + wd * ww)
            du, dw = du_next, dw_next
        if idx < h:
            w0 += jumps[idx]
            if F and active[idx]:
                # From here on the force's columns: d/ds (dU gains the jump), d/df_x, d/df_y (dW gains i/EI, -1/EI).
                cols += [3 * idx, 3 * idx + 1, 3 * idx + 2]
                du += [jumps[idx], 0j, 0j]
                dw += [0j, d_fx, d_fy]
        else:
            if F:
                full = list(zeros)
                for c, v in zip(cols, du, strict=False):
                    full[c] = v
            else:  # only the seeds, in their order (du is never changed in place without force columns)
                full = du
            out_u[idx - h] = u0
            out_j[idx - h] = full
            if seeds:
                out_w[idx - h] = dw[:4]
    return out_u, out_j, out_w


def curvature_and_jacobian(
    query: torch.Tensor,
    s: torch.Tensor,
    f: torch.Tensor,
    length: float,
    bending_stiffness: float,
    *,
    mask: torch.Tensor | None = None,
    jacobian: bool = True,
    max_step_angle: float = ESTIMATION_STEP_ANGLE,
    max_steps: int = 64,
    backend: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`march` for torch tensors: float64 results on the inputs' device, no autograd.

    ``backend``: ``"numpy"`` (CPU only) or ``"torch"``; default NumPy on the CPU, torch elsewhere. ``mask`` is
    :func:`march`'s ``active``. Shapes and units as :func:`march`.
    """
    device = s.device
    name = backend or ("numpy" if device.type == "cpu" else "torch")
    xp: Backend = NUMPY if name == "numpy" else TorchBackend(device)

    def conv(t, kind="float"):
        return None if t is None else xp.asarray(t.detach(), kind)

    u, jac = march(
        xp,
        conv(query),
        conv(s),
        conv(f),
        length,
        bending_stiffness,
        active=conv(mask, "bool"),
        jacobian=jacobian,
        step_angle=max_step_angle,
        max_steps=max_steps,
    )

    def back(x):
        return None if x is None else xp.to_torch(x, device).to(torch.float64)

    return back(u), back(jac)
