"""The precurved rod: body-frame Cosserat equations in three dimensions with intrinsic curvature and torsion.

A concentric-tube robot's tube or a preshaped catheter has an unloaded body-frame curvature u*(s) (the rod file's
``intrinsic_curvature``). Under load the moment is m = K (u - u*), K = diag(EI, EI, GJ), so the rod twists (u_z is
no longer zero) and the straight rod's complex reduction (:mod:`.body_frame`) no longer holds. With follower point
forces f_i (body-frame components (f_x, f_y, 0) at s_i) and no distributed load, the body-frame internal force n and
moment m obey, between forces (docs/physics.md, "Precurved rods"),

    n' = -u x n,      m' = -u x m - e3 x n,      u = u* + K^-1 m,

with n = m = 0 at the free tip (so u(L) = u*(L)), and n steps by f_i across s_i: n(s_i-) = n(s_i+) + f_i. The
moment is continuous everywhere, so where u* jumps, u jumps by the same amount. It is still an initial-value
problem from the tip: the march starts at s = L and integrates towards the base.

Discretisation: classical Runge-Kutta (RK4) on segments split at every event (each force, each query position,
each breakpoint of u*), so that u* is constant on every step and point forces act exactly where they are; each
segment takes ``ceil(longest such segment in the batch / max_step)`` equal steps, so the error falls as
``max_step^4``. A reading at s is ``u*(s+) + K^-1 m(s)``: a grating exactly at a breakpoint reads the value just
distal to it, as on the unloaded rod. At a tie a force is applied before a query at the same place is read (the
query sees the force's location derivative from the distal side, as in :mod:`.sensitivity`).

One march, on either backend (:mod:`torchrod.backend`): on torch tensors it is differentiable by autograd
(``gradcheck`` holds it to that; :func:`torchrod.simulate` uses it for precurved rods), and with ``jacobian`` or
``seeds`` it also carries tangents through the same RK4 steps, for the estimator:

* the derivatives of the readings with respect to every force's (s_i, f_x, f_y): a force's f-columns start at its
  event as the unit jumps of n, its s-column as ``(u x f_i, e3 x f_i)``, the difference of the rates on the two
  sides of the jump (moving the force distally by ds lets the loaded rates act over ds more);
* with ``seeds``, the propagator Phi(s) of the linearised equations from the tip (six seed tangents, the identity
  at s = L), which the estimator's scan uses to find the response to a force added anywhere
  (:mod:`torchrod.estimate.search`).

A rod without intrinsic curvature keeps the fast straight-rod path of :mod:`.body_frame`; this march agrees with it
(tests: to ~2e-10 at the default step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..backend import Backend, TorchBackend
from ..loads import PointForces
from ..rod import Rod

__all__ = ["DEFAULT_MAX_STEP", "EXACT_MAX_STEP", "FIT_MAX_STEP", "Precurved", "grating_curvature", "intrinsic", "march"]

DEFAULT_MAX_STEP = 5e-4
"""Longest RK4 step [m] of the simulator and of the estimator's exact model (relative error ~2e-10 on the presets:
at the 12 1/m of a concentric tube's curved section the turning per step stays below 0.01 rad)."""

FIT_MAX_STEP = 1e-2
"""Longest RK4 step [m] while fitting (relative error ~4e-5, below the straight rod's fitting model's ~1e-4; the fits'
final steps and reported losses use :data:`EXACT_MAX_STEP`)."""

EXACT_MAX_STEP = 1e-3
"""Longest RK4 step [m] of the estimator's exact model: its final steps and the losses the count tests and the verdict
judge (relative error ~3e-9: the curvature to ~1e-7 1/m, far below the noise floor of 1e-3 1/m)."""


@dataclass(frozen=True)
class Precurved:
    """What the march needs of a precurved rod (SI units).

    Attributes:
        length: L [m]; bending, torsion: EI and GJ [N m^2].
        segments: the intrinsic curvature, ``(from, to, ux, uy)`` per segment (:class:`torchrod.Rod`).
        breakpoints: where u* may jump inside (0, L) [m] (:meth:`torchrod.Rod.breakpoints`).
    """

    length: float
    bending: float
    torsion: float
    segments: tuple[tuple[float, float, float, float], ...]
    breakpoints: tuple[float, ...]

    @classmethod
    def of(cls, rod: Rod) -> Precurved:
        return cls(
            rod.length, rod.bending_stiffness, rod.torsion_stiffness, rod.intrinsic_curvature, tuple(rod.breakpoints())
        )


def intrinsic(xp: Backend, model: Precurved, s: Any) -> Any:
    """u* = (ux*, uy*, 0) [1/m] at positions ``s`` (any shape) as a (..., 3) array; at a breakpoint the distal
    value (:meth:`torchrod.Rod.intrinsic_at`)."""
    zero = s * 0.0
    ux, uy = zero, zero
    for a, b, vx, vy in model.segments:
        inside = (s >= a) & ((s < b) | ((s == b) & (b == model.length)))
        ux = xp.where(inside, vx, ux)
        uy = xp.where(inside, vy, uy)
    return xp.stack([ux, uy, zero], -1)


_HAT = ((0, 0, 0, 0, 0, -1, 0, 1, 0), (0, 0, 1, 0, 0, 0, -1, 0, 0), (0, -1, 0, 1, 0, 0, 0, 0, 0))
"""v @ _HAT, reshaped (3, 3), is the matrix of v x (row-major)."""


def _hat(v: Any, hat: Any) -> Any:
    """(R, 3, 3): the matrices of v x for v (R, 3); ``hat`` is :data:`_HAT` as an array of v's backend."""
    return (v @ hat).reshape(v.shape[0], 3, 3)


def _plain(x: Any) -> Any:
    """``x`` without autograd history (positions pick u*, the order and the step counts: no gradient flows there)."""
    return x.detach() if isinstance(x, torch.Tensor) else x


def march(
    xp: Backend,
    query: Any,
    s: Any,
    f: Any,
    model: Precurved,
    *,
    active: Any = None,
    max_step: float = DEFAULT_MAX_STEP,
    jacobian: bool = False,
    seeds: bool = False,
    bending: Any = None,
    steps: int | None = None,
    load: Any = None,
) -> tuple[Any, Any, Any, Any]:
    """The precurved rod under R sets of forces (module docstring), read at ``query``.

    Args:
        query: (Q,) positions [m] in [0, L], any order, or (R, Q): each row its own.
        s: (R, h) force locations [m]; f: (R, h, 2) body-frame (f_x, f_y) [N]; active: (R, h) bool (None: all).
        max_step: the longest RK4 step [m].
        jacobian: also the derivatives of the readings w.r.t. each force's (s [m], f_x [N], f_y [N]).
        seeds: also the propagator of the linearised equations at the queries.
        bending: EI [N m^2] overriding the model's (a number or an (R,) / (1,) array; GJ scales with it).
        steps: a fixed number of RK4 steps per segment instead of ``max_step``'s count (which follows the batch's
            longest segment): each row's result is then independent of the rest of the batch.
        load: (R, q, 2) a distributed body-frame load (w_x, w_y) [N/m] at q uniform nodes over [0, L], linear
            between them (the paper's node scheme: point forces spread onto the nodes), added to n' = -u x n - w;
            not with ``jacobian`` or ``seeds``.
    Returns:
        u (R, Q, 3) body-frame curvature [1/m]; n (R, Q, 3) body-frame internal force [N] (proximal side);
        jac (R, Q, 2, h, 3) d(u_x, u_y)/d(s, f_x, f_y) or None; phi (R, Q, 8, 6) or None: per query the
        propagator's rows d(u_x, u_y) (2) and d(n, m) (6) w.r.t. the state (n, m) at the tip.
    """
    if not (isinstance(max_step, (int, float)) and math.isfinite(max_step) and max_step > 0.0):
        raise ValueError(f"max_step must be a positive length [m], got {max_step!r}")
    R, h = s.shape
    Q = query.shape[-1]
    rows_q = query if len(query.shape) == 2 else xp.expand(query[None, :], (R, Q))
    L = model.length
    ei = model.bending if bending is None else bending
    ratio = model.torsion / model.bending
    if isinstance(ei, (int, float)):
        kinv = xp.asarray([[1.0 / ei, 1.0 / ei, 1.0 / (ei * ratio)]])  # (1, 3)
    else:
        ei = ei.reshape(-1, 1)
        kinv = xp.concat([1.0 / ei, 1.0 / ei, 1.0 / (ei * ratio)], 1)  # (R or 1, 3)
    on = xp.ones((R, h), "bool") if active is None else active
    f3 = xp.concat([f * xp.astype(on, "float")[:, :, None], f[:, :, :1] * 0.0], 2)  # (R, h, 3), zero if inactive
    s_ev = xp.where(on, s, L)  # an inactive slot: an event at the tip that does nothing
    nodes = 0 if load is None else load.shape[1]
    if nodes and (jacobian or seeds):
        raise ValueError("a distributed load is for the forward march only (no jacobian, no seeds)")
    spacing = L / (nodes - 1) if nodes > 1 else L
    inner = [k * spacing for k in range(1, nodes - 1)]
    extra = xp.asarray([0.0, *model.breakpoints, *inner])
    pos = xp.concat([s_ev, rows_q, xp.expand(extra[None, :], (R, extra.shape[0]))], 1)
    E = pos.shape[1]
    order = xp.argsort_desc(_plain(pos))  # forces first at ties
    at = xp.take(pos, order, 1)  # (R, E), descending
    P = (3 * h if jacobian else 0) + (6 if seeds else 0)
    # The state and its tangents side by side: column 0 of Yn, Ym (R, 3, 1 + P) is (n, m), the rest d(n, m).
    Yn = xp.zeros((R, 3, 1 + P))
    Ym = xp.zeros((R, 3, 1 + P))
    if seeds:
        eye = xp.eye(3)[None]
        Yn[:, :, P - 5 : P - 2] = eye
        Ym[:, :, P - 2 :] = eye
    cols = xp.arange(1 + P)[None, :]  # (1, 1 + P)
    kinv3 = kinv[:, :, None]
    e3 = xp.asarray([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])[None]  # e3 x
    hat = xp.asarray(_HAT)

    def load_at(p):
        """(R, 3, 1) the distributed load at positions p (R,) [N/m], linear between the nodes."""
        j = xp.clip(xp.astype(p / spacing, "int"), lo=0, hi=nodes - 2)
        frac = (p - xp.astype(j, "float") * spacing) / spacing
        lo = xp.take(load, xp.expand(j[:, None, None], (R, 1, 2)), 1)[:, 0]
        hi = xp.take(load, xp.expand((j + 1)[:, None, None], (R, 1, 2)), 1)[:, 0]
        w = lo + (hi - lo) * frac[:, None]
        return xp.concat([w, w[:, :1] * 0.0], 1)[:, :, None]

    def rates(Yn, Ym, ustar, w=None):
        """d/ds of (Yn, Ym): the equations on column 0, their linearisation on the tangents."""
        n, m = Yn[:, :, :1], Ym[:, :, :1]
        U = _hat(ustar + m[:, :, 0] * kinv, hat)
        rn = -(U @ Yn)
        rm = -(U @ Ym) - e3 @ Yn
        if w is not None:
            rn = rn - w
        if not P:
            return rn, rm
        du = Ym[:, :, 1:] * kinv3  # -du x n = n x du, and the same for m
        rn = xp.concat([rn[:, :, :1], rn[:, :, 1:] + _hat(n[:, :, 0], hat) @ du], 2)
        rm = xp.concat([rm[:, :, :1], rm[:, :, 1:] + _hat(m[:, :, 0], hat) @ du], 2)
        return rn, rm

    cur = at[:, 0] * 0.0 + L
    rec_n, rec_m = [], []
    for e in range(E):
        target = at[:, e]
        seg = cur - target  # (R,) >= 0
        longest = float(xp.amax(_plain(seg), 0)) if R else 0.0
        n_steps = math.ceil(longest / max_step - 1e-9) if longest > 0.0 else 0
        if steps is not None and longest > 0.0:
            n_steps = steps
        if n_steps:
            hs = (-seg / n_steps)[:, None, None]  # (R, 1, 1): towards the base
            half, sixth = 0.5 * hs, hs / 6.0
            mid = 0.5 * (cur + target)
            ustar = intrinsic(xp, model, _plain(mid))
            w0 = w1 = None
            if nodes:
                w0, w1 = load_at(cur), load_at(target)  # the segment lies between two nodes: linear in between
            for i in range(n_steps):
                wa = wb = wc = None
                if nodes:
                    wa, wb, wc = (w0 + (w1 - w0) * ((i + c) / n_steps) for c in (0.0, 0.5, 1.0))
                a_n, a_m = rates(Yn, Ym, ustar, wa)
                b_n, b_m = rates(Yn + half * a_n, Ym + half * a_m, ustar, wb)
                c_n, c_m = rates(Yn + half * b_n, Ym + half * b_m, ustar, wb)
                d_n, d_m = rates(Yn + hs * c_n, Ym + hs * c_m, ustar, wc)
                Yn = Yn + sixth * (a_n + 2.0 * (b_n + c_n) + d_n)
                Ym = Ym + sixth * (a_m + 2.0 * (b_m + c_m) + d_m)
        cur = target
        if h:
            k = order[:, e]
            is_force = k < h
            j = xp.clip(k, hi=h - 1)
            jump = xp.take(f3, xp.expand(j[:, None, None], (R, 1, 3)), 1)[:, 0]  # (R, 3)
            jump = xp.where(is_force[:, None], jump, 0.0 * jump)
            add_n = xp.where(cols == 0, jump[:, :, None], 0.0)  # (R, 3, 1 + P)
            add_m = None
            if jacobian:
                # The force's columns start here: d/ds (the difference of the rates across the jump, with the
                # distal segment's u*), d/df_x and d/df_y (unit jumps of n).
                u_here = intrinsic(xp, model, _plain(target))
                U = _hat(u_here + Ym[:, :, 0] * kinv, hat)
                ds_n, ds_m = (U @ jump[:, :, None])[:, :, 0], (e3 @ jump[:, :, None])[:, :, 0]
                live = (is_force & xp.take(on, j[:, None], 1)[:, 0])[:, None]
                base = 1 + 3 * j[:, None]
                c_s, c_x, c_y = (cols == base) & live, (cols == base + 1) & live, (cols == base + 2) & live
                unit_x = xp.asarray([1.0, 0.0, 0.0])[None, :, None]
                unit_y = xp.asarray([0.0, 1.0, 0.0])[None, :, None]
                add_n = add_n + xp.where(c_s[:, None, :], ds_n[:, :, None], 0.0)
                add_n = add_n + xp.where(c_x[:, None, :], unit_x, 0.0) + xp.where(c_y[:, None, :], unit_y, 0.0)
                add_m = xp.where(c_s[:, None, :], ds_m[:, :, None], 0.0)
            Yn = Yn + add_n
            if add_m is not None:
                Ym = Ym + add_m
        rec_n.append(Yn)
        rec_m.append(Ym)
    # The event index of each query: the inverse of the sort, at the queries' kinds.
    inverse = xp.argsort_desc(-order)[:, h : h + Q]  # (R, Q)
    idx = xp.expand(inverse[:, :, None, None], (R, Q, 3, 1 + P))
    Yn_q = xp.take(xp.stack(rec_n, 1), idx, 1)  # (R, Q, 3, 1 + P)
    Ym_q = xp.take(xp.stack(rec_m, 1), idx, 1)
    n_q = Yn_q[..., 0]
    u_q = intrinsic(xp, model, rows_q) + Ym_q[..., 0] * kinv[:, None, :]
    jac = phi = None
    if P:
        du_q = Ym_q[:, :, :2, 1:] * kinv[:, None, :2, None]  # (R, Q, 2, P)
        if jacobian:
            jac = du_q[..., : 3 * h].reshape(R, Q, 2, h, 3)
        if seeds:
            phi = xp.concat([du_q[..., P - 6 :], Yn_q[..., P - 5 :], Ym_q[..., P - 5 :]], 2)  # (R, Q, 8, 6)
    return u_q, n_q, jac, phi


def simulate_torch(
    rod: Rod,
    loads: PointForces,
    query: torch.Tensor,
    *,
    max_step: float = DEFAULT_MAX_STEP,
    bending_stiffness: float | torch.Tensor | None = None,
    steps: int | None = None,
    load: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`march` on torch tensors with autograd, as :func:`torchrod.simulate` uses it: u (B, Q, 3) [1/m] and n
    (B, Q, 3) [N] at ``query`` (Q,) [m]; dtype and device follow ``loads`` (computed in float64); ``steps`` as
    :func:`march`'s; ``load`` (B, q, 2) [N/m] a distributed load at q uniform nodes (:func:`march`)."""
    xp = TorchBackend(loads.device)
    dtype = loads.dtype
    query = torch.as_tensor(query, device=loads.device).reshape(-1).to(torch.float64)
    ei = None
    if bending_stiffness is not None:
        ei = (
            bending_stiffness.to(device=loads.device, dtype=torch.float64).reshape(-1)
            if isinstance(bending_stiffness, torch.Tensor)
            else float(bending_stiffness)
        )
    u, n, _, _ = march(
        xp,
        query,
        loads.s.to(torch.float64),
        loads.f.to(torch.float64),
        Precurved.of(rod),
        active=loads.active,
        max_step=max_step,
        bending=ei,
        steps=steps,
        load=None if load is None else load.to(torch.float64),
    )
    return u.to(dtype), n.to(dtype)


def grating_curvature(
    rod: Rod, loads: PointForces, *, relative: bool = False, max_step: float = DEFAULT_MAX_STEP
) -> torch.Tensor:
    """(B, G, 2) what the gratings read [1/m]: the total body-frame curvature (ux, uy), or with ``relative`` the
    change from the unloaded shape, u - u*."""
    query = rod.grating_positions(torch.float64, loads.device)
    u, _ = simulate_torch(rod, loads, query, max_step=max_step)
    u = u[..., :2]
    return u - rod.unloaded_curvature(u.dtype, u.device) if relative else u
