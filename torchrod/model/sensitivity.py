"""Curvature at the gratings and its Jacobian w.r.t. the forces, in one tip-to-base pass (forward sensitivities).

Estimation evaluates the forward model hundreds of times per reading, and always wants the derivative with respect
to every unknown (s_i, f_x,i, f_y,i). Reverse-mode autograd through the forward model adds a backward pass per
evaluation and gives only the gradient of one scalar; with at most 3 forces there are at most 9 unknowns, so
carrying their tangents along the march (forward mode) gives the whole residual Jacobian in one pass, which the
estimator needs anyway for its Gauss-Newton steps, stopping test and covariance.

The march is the body-frame model of :mod:`torchrod.body_frame` in complex form: with U = u_x + i u_y and
t = L - s, U_tt = -|U|^2 U / 2 between forces, U = U_t = 0 at the free tip, and at a force (f_x, f_y) at s_i the
slope jumps, W = U_t -> W + i (f_x + i f_y) / EI. A fourth-order Runge-Kutta-Nystrom scheme integrates it, with
per-row step counts from an estimate of the solution's rate (see the comment in :func:`curvature_and_jacobian`).

Tangents. For a parameter p, (dU/dp, dW/dp) obey the linearised equation, with
D(|U|^2 U)[dU] = 2 |U|^2 dU + U^2 conj(dU); the RKN stages are applied to the tangents with that linearisation
(the tangent of the discrete scheme). Every stage is linear in (U, dU) except g = |U|^2 U, and g is homogeneous of
degree 3 (D g[U] = 3 g), so primal and tangents share one (B, 1 + P) complex state and one set of operations.
At a force event:

* d/df_x and d/df_y: the slope jump adds i / EI and -1 / EI to dW.
* d/ds_i: moving the force distally by ds moves the jump earlier in t by ds; to first order the state just
  proximal to the force changes by (F(Y+) - F(Y-)) ds with F(U, W) = (W, -|U|^2 U / 2) the vector field, which is
  (jump, 0) since U is continuous. So dU/ds_i gains the jump i (f_x + i f_y) / EI and dW/ds_i is unchanged. This
  is the exact derivative of the continuous problem; it matches the discrete scheme's to its O(h^4) accuracy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

__all__ = ["CHUNK", "ESTIMATION_STEP_ANGLE", "SCALAR_ROWS", "curvature_and_jacobian", "march_row"]

SCALAR_ROWS = 8
"""Batches of at most this many rows on the CPU are marched one row at a time on Python complex numbers
(:func:`march_row`): at B = 1 a pass for one force takes ~0.09 ms there against ~1.2 ms in torch, whose cost at
small batch is per-operation dispatch (measured on this project's 2-core CPU). The two give the same numbers to
rounding (the same scheme, steps and event order)."""

CHUNK = 384
"""Rows marched together by :func:`curvature_and_jacobian` (measured on 2 cores: 2700 rows of 3 forces take 92 ms in
one march, 56 ms in chunks of 338; much smaller chunks pay the per-operation overhead)."""

ESTIMATION_STEP_ANGLE = 0.3
"""Default bound on (local rate) x (step) for estimation. Over the synthetic envelope (1-3 forces, 0.05-2 N, bending
up to 90 degrees; 400 cases) the curvature at the gratings is within 5.0e-4 1/m of the converged solution (99th
percentile 2.9e-4; 0.2: 1.5e-4, 0.4: 9.6e-4; against torchrod.synthetic's readings), a twentieth of the
estimator's noise floor and a few thousandths of the sensor noise."""


def _g(y: torch.Tensor) -> torch.Tensor:
    """Column 0: 3 |y0|^2 y0 (three times g); columns 1..P: the tangent 2 |y0|^2 y_p + y0^2 conj(y_p).

    y: (B, 1 + P) complex. The factor 1/3 of column 0 is folded into the RKN coefficients by the caller.
    """
    cy = torch.conj_physical(y)
    y0 = y[:, :1]
    a = y0 * cy[:, :1]  # |y0|^2, complex-typed so that no operation below converts dtypes
    return torch.addcmul((y0 * y0) * cy, a, y, value=2.0)


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
    chunk: int = CHUNK,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Curvature at ``query`` and, optionally, its derivative w.r.t. each force's (s, f_x, f_y). Unchecked, no autograd.

    Args:
        query: (Q,) positions [m] in [0, L] (the gratings).
        s: (B, h) force locations [m] in [0, L].
        f: (B, h, 2) body-frame components (f_x, f_y) [N].
        length: L [m]; bending_stiffness: EI [N m^2].
        mask: (B, h) bool, False for padded forces (no load, zero Jacobian columns); None: all real.
        jacobian: also return the Jacobian.
        max_step_angle: bound on (rate) x (step) per RKN step; max_steps: cap on the steps per segment.
        chunk: rows marched together (larger batches are split: the march's working set then stays in cache,
            and each part gets step counts for its own rows).
    Returns:
        curvature (B, Q, 2) [1/m], and the Jacobian (B, Q, 2, h, 3) of (u_x, u_y) w.r.t. (s [m], f_x [N], f_y [N])
        of each force ([1/m^2], [1/(m N)], [1/(m N)]), or None.
    """
    B, h = s.shape
    if B <= SCALAR_ROWS and s.device.type == "cpu":
        return _scalar_rows(query, s, f, length, bending_stiffness, mask, jacobian, max_step_angle, max_steps)
    if B > chunk:
        parts = [
            curvature_and_jacobian(
                query,
                s[i : i + chunk],
                f[i : i + chunk],
                length,
                bending_stiffness,
                mask=None if mask is None else mask[i : i + chunk],
                jacobian=jacobian,
                max_step_angle=max_step_angle,
                max_steps=max_steps,
                chunk=chunk,
            )
            for i in range(0, B, chunk)
        ]
        curv = torch.cat([c for c, _ in parts])
        return curv, (torch.cat([j for _, j in parts]) if jacobian else None)
    Q = query.shape[0]
    E = Q + h
    real, device = s.dtype, s.device
    cplx = torch.complex128 if real == torch.float64 else torch.complex64
    s = s.detach()
    f = f.detach()
    if mask is not None:
        f = f * mask.unsqueeze(-1).to(real)
    ei = float(bending_stiffness)
    jump_f = torch.complex(-f[..., 1], f[..., 0]) / ei  # (B, h): i (f_x + i f_y) / EI
    pos = torch.cat((query.to(real).expand(B, Q), s), dim=1)  # (B, E)
    pos_sorted, order = pos.sort(dim=1, descending=True, stable=True)
    start = torch.cat((pos_sorted.new_full((B, 1), float(length)), pos_sorted[:, :-1]), dim=1)
    seg = (start - pos_sorted).clamp(min=0.0)  # (B, E), tip to base

    # Step counts per row and segment. The local rate is estimated as max(|U|, sqrt|m|) of the small-deflection
    # solution at the segment's proximal end, U = sum_i J_i (s_i - s)^+ and m = sum_{s_i > s} J_i (vector sums of
    # the jumps J_i = i (f_x + i f_y) / EI): unlike the rigorous bound of body_frame (sums of magnitudes) it lets
    # opposed forces cancel; measured over the synthetic envelope it costs no accuracy at the default step angle
    # (ESTIMATION_STEP_ANGLE) and saves a quarter of the work. Every row takes its own count (the batch loops to the
    # largest; a row past its count takes steps of length zero, which leave its state unchanged), so a row's
    # result does not depend on the rows batched with it.
    lever = (s.unsqueeze(1) - pos_sorted.unsqueeze(2)).clamp(min=0.0)  # (B, E, h)
    jc = jump_f.unsqueeze(1)  # (B, 1, h)
    rate = torch.maximum((jc * lever).sum(-1).abs(), (jc * (lever > 0)).sum(-1).abs().sqrt())
    need = (rate * seg / max_step_angle).nan_to_num(nan=1.0, posinf=float(max_steps))
    steps_be = need.ceil().clamp(min=1.0, max=float(max_steps))  # (B, E)
    counts = steps_be.amax(dim=0).to(torch.long).tolist()
    least = steps_be.amin(dim=0).to(torch.long).tolist()

    # Jumps per event: column 0 the primal slope jump, columns 1.. the tangent jumps (dW for f, dU for s).
    P = 3 * h if jacobian else 0
    zeros_q = jump_f.new_zeros(B, Q)
    jump_w0 = torch.cat((zeros_q, jump_f), dim=1).gather(1, order)  # (B, E)
    if jacobian:
        onehot = (order.unsqueeze(-1) - Q == torch.arange(h, device=device)).to(real)  # (B, E, h)
        active = onehot if mask is None else onehot * mask.unsqueeze(1).to(real)
        dw = torch.zeros(3, dtype=cplx, device=device)
        dw[1], dw[2] = 1j / ei, -1.0 / ei
        jump_w = torch.cat(
            (jump_w0.unsqueeze(-1), (active.unsqueeze(-1) * dw).reshape(B, E, P)), dim=-1
        )  # (B, E, 1 + P)
        du = torch.zeros(B, E, h, 3, dtype=cplx, device=device)
        du[..., 0] = onehot * jump_f.unsqueeze(1)
        jump_u = torch.cat((du.new_zeros(B, E, 1), du.reshape(B, E, P)), dim=-1)
    else:
        jump_w = jump_w0.unsqueeze(-1)
        jump_u = None
    weight = torch.ones(1 + P, dtype=cplx, device=device)
    weight[0] = 1.0 / 3.0  # _g returns 3 g in column 0

    hstep = (seg / steps_be).unsqueeze(-1).to(cplx)  # (B, E, 1), complex-typed (no per-operation conversions)
    # RKN coefficients per event (B, E, 1 + P), the g-weights folded in: see _march in body_frame.
    c_half = 0.5 * hstep
    c16 = (-1.0 / 16.0) * hstep * hstep * weight
    c4 = -0.25 * hstep * hstep * weight
    c12 = (-1.0 / 12.0) * hstep * hstep * weight
    cw = (-1.0 / 12.0) * hstep * weight
    Z = torch.zeros(B, 1 + P, dtype=cplx, device=device)  # U and its tangents
    Zw = torch.zeros_like(Z)  # W = U_t and its tangents
    recorded = []
    for e in range(E):
        coefficients = hstep[:, e], c_half[:, e], c16[:, e], c4[:, e], c12[:, e], cw[:, e]
        hs, ch, k16, k4, k12, kw = coefficients
        for k in range(counts[e]):
            if k >= least[e]:  # rows past their own count step by zero
                on = (steps_be[:, e : e + 1] > k).to(cplx)
                hs, ch, k16, k4, k12, kw = (c * on for c in coefficients)
            g1 = _g(Z)
            g2 = _g(torch.addcmul(torch.addcmul(Z, ch, Zw), k16, g1))
            p = torch.addcmul(Z, hs, Zw)
            g3 = _g(torch.addcmul(p, k4, g2))
            Z = torch.addcmul(p, k12, torch.add(g1, g2, alpha=2.0))
            Zw = torch.addcmul(Zw, kw, torch.add(torch.add(g1, g2, alpha=4.0), g3))
        Zw = Zw + jump_w[:, e]
        if jump_u is not None:
            Z = Z + jump_u[:, e]
        recorded.append(Z)
    states = torch.stack(recorded, dim=1)  # (B, E, 1 + P)
    inverse = order.argsort(dim=1)[:, :Q]
    at_query = states.gather(1, inverse.unsqueeze(-1).expand(-1, -1, 1 + P))  # (B, Q, 1 + P)
    curvature = torch.view_as_real(at_query[..., 0].contiguous())
    if not jacobian:
        return curvature, None
    jac = torch.view_as_real(at_query[..., 1:].contiguous())  # (B, Q, P, 2)
    return curvature, jac.transpose(-1, -2).reshape(B, Q, 2, h, 3)


def _scalar_rows(
    query: torch.Tensor,
    s: torch.Tensor,
    f: torch.Tensor,
    length: float,
    bending_stiffness: float,
    mask: torch.Tensor | None,
    jacobian: bool,
    max_step_angle: float,
    max_steps: int,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`curvature_and_jacobian` for a few rows on the CPU, one :func:`march_row` per row."""
    B, h = s.shape
    Q = query.shape[0]
    q = query.tolist()
    s_rows, f_rows = s.detach().tolist(), f.detach().tolist()
    active = [[True] * h] * B if mask is None else mask.tolist()
    curv, jac = [], []
    for b in range(B):
        u, du = march_row(
            q,
            s_rows[b],
            f_rows[b],
            length,
            bending_stiffness,
            active=active[b],
            jacobian=jacobian,
            max_step_angle=max_step_angle,
            max_steps=max_steps,
        )
        curv.append([(z.real, z.imag) for z in u])
        if jacobian:
            jac.append([[[c.real for c in row], [c.imag for c in row]] for row in du])
    curvature = torch.tensor(curv, dtype=s.dtype).view(B, Q, 2)
    if not jacobian:
        return curvature, None
    return curvature, torch.tensor(jac, dtype=s.dtype).view(B, Q, 2, h, 3)


def march_row(
    query: Sequence[float],
    s: Sequence[float],
    f: Sequence[Sequence[float]],
    length: float,
    bending_stiffness: float,
    *,
    active: Sequence[bool] | None = None,
    jacobian: bool = True,
    max_step_angle: float = ESTIMATION_STEP_ANGLE,
    max_steps: int = 64,
) -> tuple[list[complex], list[list[complex]]]:
    """One row of :func:`curvature_and_jacobian` on Python floats: the same scheme, step counts and event order.

    Args:
        query: Q positions [m]; s: h locations [m]; f: h pairs (f_x, f_y) [N]; length: L [m];
            bending_stiffness: EI [N m^2].
        active: h flags, False for a padded force (no load, zero Jacobian columns); None: all real.
        jacobian, max_step_angle, max_steps: as in :func:`curvature_and_jacobian`.
    Returns:
        U = u_x + i u_y at each query point (Q complex) [1/m] and, with ``jacobian``, for each query point the 3h
        complex derivatives dU/d(s_i [m], f_x,i [N], f_y,i [N]) (an empty list per point otherwise).
    """
    Q, h = len(query), len(s)
    ei = float(bending_stiffness)
    if active is None:
        active = [True] * h
    jumps = [complex(-fy, fx) / ei if on else 0j for (fx, fy), on in zip(f, active)]
    # Events tip to base; at equal positions the grating first (it does not see a force sitting on it), as the
    # stable descending sort of the batched march orders them.
    events = sorted(
        [(float(query[k]), 0, k) for k in range(Q)] + [(float(s[i]), 1, i) for i in range(h)],
        key=lambda e: (-e[0], e[1]),
    )
    P = 3 * h if jacobian else 0
    u0, w0 = 0j, 0j  # U and W = U_t
    du = [0j] * P  # tangents
    dw = [0j] * P
    out_u = [0j] * Q
    out_j: list[list[complex]] = [[] for _ in range(Q)]
    prev, started = float(length), False
    d_fx, d_fy = 1j / ei, -1.0 / ei
    for pos, kind, idx in events:
        seg = max(prev - pos, 0.0)
        prev = pos
        n = 0
        if started:  # before the most distal force the state is zero and stays zero: nothing to step
            lever, total = 0j, 0j
            for i in range(h):
                d = s[i] - pos
                if d > 0.0:
                    lever += jumps[i] * d
                    total += jumps[i]
            need = max(abs(lever), math.sqrt(abs(total))) * seg / max_step_angle
            if math.isnan(need):
                n = 1
            else:  # as the batched march: nan -> 1 step, at most max_steps (inf included)
                n = max_steps if need >= max_steps else max(math.ceil(need), 1)
        hs = seg / n if n else 0.0
        ch, k16, k4, k12, kw = 0.5 * hs, -hs * hs / 16.0, -hs * hs / 4.0, -hs * hs / 12.0, -hs / 12.0
        for _ in range(n):
            # g(U) = |U|^2 U and its tangent 2 |U|^2 dU + U^2 conj(dU), at the three stages
            a = u0.real * u0.real + u0.imag * u0.imag
            q1 = u0 * u0
            g1 = a * u0
            t1 = [2.0 * a * y + q1 * y.conjugate() for y in du]
            y0 = u0 + ch * w0 + k16 * g1
            a = y0.real * y0.real + y0.imag * y0.imag
            q2 = y0 * y0
            g2 = a * y0
            ys = [z + ch * w + k16 * g for z, w, g in zip(du, dw, t1)]
            t2 = [2.0 * a * y + q2 * y.conjugate() for y in ys]
            p0 = u0 + hs * w0
            y0 = p0 + k4 * g2
            a = y0.real * y0.real + y0.imag * y0.imag
            q3 = y0 * y0
            g3 = a * y0
            ps = [z + hs * w for z, w in zip(du, dw)]
            ys = [p + k4 * g for p, g in zip(ps, t2)]
            t3 = [2.0 * a * y + q3 * y.conjugate() for y in ys]
            u0 = p0 + k12 * (g1 + 2.0 * g2)
            w0 = w0 + kw * (g1 + 4.0 * g2 + g3)
            du = [p + k12 * (x1 + 2.0 * x2) for p, x1, x2 in zip(ps, t1, t2)]
            dw = [w + kw * (x1 + 4.0 * x2 + x3) for w, x1, x2, x3 in zip(dw, t1, t2, t3)]
        if kind == 1:
            started = True
            w0 += jumps[idx]
            if P and active[idx]:
                dw[3 * idx + 1] += d_fx
                dw[3 * idx + 2] += d_fy
                du[3 * idx] += jumps[idx]
        else:
            out_u[idx] = u0
            out_j[idx] = list(du)
    return out_u, out_j
