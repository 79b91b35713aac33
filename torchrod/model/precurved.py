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
query sees the force's location derivative from the distal side, as in the estimator's kernels).

The march runs on torch tensors and is differentiable by autograd (``gradcheck`` holds it to that;
:func:`torchrod.simulate` uses it for precurved rods). The estimator integrates the same equations in its kernels
(:mod:`torchrod.kernels.precurved`), with the tangents and the propagator it needs, per reading.

A rod without intrinsic curvature keeps the fast straight-rod path of :mod:`.body_frame`; this march agrees with it
(tests: to ~2e-10 at the default step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..errors import OptionsError
from ..kernels.precurved import EXACT_MAX_STEP, FIT_MAX_STEP
from ..loads import PointForces
from ..rod import Rod

__all__ = ["DEFAULT_MAX_STEP", "EXACT_MAX_STEP", "FIT_MAX_STEP", "Precurved", "grating_curvature", "intrinsic", "march"]

DEFAULT_MAX_STEP = 5e-4
"""Longest RK4 step [m] of the simulator (relative error ~2e-10 on the presets: at the 12 1/m of a concentric tube's
curved section the turning per step stays below 0.01 rad); :func:`torchrod.simulate` takes shorter ones, checked,
where large loads turn the rod faster (:data:`torchrod.model.body_frame.PRECURVED_TRUSTED_ANGLE`). The estimator's
models take :data:`FIT_MAX_STEP` and :data:`EXACT_MAX_STEP`."""


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


def intrinsic(model: Precurved, s: torch.Tensor) -> torch.Tensor:
    """u* = (ux*, uy*, 0) [1/m] at positions ``s`` (any shape) as a (..., 3) tensor; at a breakpoint the distal
    value (:meth:`torchrod.Rod.intrinsic_at`)."""
    zero = s * 0.0
    ux, uy = zero, zero
    for a, b, vx, vy in model.segments:
        inside = (s >= a) & ((s < b) | ((s == b) & (b == model.length)))
        ux = torch.where(inside, vx, ux)
        uy = torch.where(inside, vy, uy)
    return torch.stack([ux, uy, zero], -1)


_HAT = ((0, 0, 0, 0, 0, -1, 0, 1, 0), (0, 0, 1, 0, 0, 0, -1, 0, 0), (0, -1, 0, 1, 0, 0, 0, 0, 0))
"""v @ _HAT, reshaped (3, 3), is the matrix of v x (row-major)."""


def _hat(v: torch.Tensor, hat: torch.Tensor) -> torch.Tensor:
    """(R, 3, 3): the matrices of v x for v (R, 3); ``hat`` is :data:`_HAT` as a tensor."""
    return (v @ hat).reshape(v.shape[0], 3, 3)


def march(
    query: torch.Tensor,
    s: torch.Tensor,
    f: torch.Tensor,
    model: Precurved,
    *,
    active: torch.Tensor | None = None,
    max_step: float = DEFAULT_MAX_STEP,
    bending: Any = None,
    steps: int | None = None,
    load: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The precurved rod under R sets of forces (module docstring), read at ``query``, differentiable.

    Args:
        query: (Q,) positions [m] in [0, L], any order, or (R, Q): each row its own.
        s: (R, h) force locations [m]; f: (R, h, 2) body-frame (f_x, f_y) [N]; active: (R, h) bool (None: all).
        max_step: the longest RK4 step [m].
        bending: EI [N m^2] overriding the model's (a number or an (R,) / (1,) tensor; GJ scales with it).
        steps: a fixed number of RK4 steps per segment instead of ``max_step``'s count (which follows the batch's
            longest segment): each row's result is then independent of the rest of the batch.
        load: (R, q, 2) a distributed body-frame load (w_x, w_y) [N/m] at q uniform nodes over [0, L], linear
            between them (the paper's node scheme: point forces spread onto the nodes), added to n' = -u x n - w.
    Returns:
        u (R, Q, 3) body-frame curvature [1/m]; n (R, Q, 3) body-frame internal force [N] (proximal side).
    """
    if not (isinstance(max_step, (int, float)) and math.isfinite(max_step) and max_step > 0.0):
        raise OptionsError(f"max_step must be a positive length [m], got {max_step!r}")
    R, h = s.shape
    Q = query.shape[-1]
    dtype, device = s.dtype, s.device
    rows_q = query if query.dim() == 2 else query[None, :].expand(R, Q)
    L = model.length
    ei = model.bending if bending is None else bending
    ratio = model.torsion / model.bending
    if isinstance(ei, (int, float)):
        kinv = torch.tensor([[1.0 / ei, 1.0 / ei, 1.0 / (ei * ratio)]], dtype=dtype, device=device)  # (1, 3)
    else:
        ei = ei.reshape(-1, 1)
        kinv = torch.cat([1.0 / ei, 1.0 / ei, 1.0 / (ei * ratio)], 1)  # (R or 1, 3)
    on = torch.ones((R, h), dtype=torch.bool, device=device) if active is None else active
    f3 = torch.cat([f * on.to(dtype)[:, :, None], f[:, :, :1] * 0.0], 2)  # (R, h, 3), zero if inactive
    s_ev = torch.where(on, s, torch.full_like(s, L))  # an inactive slot: an event at the tip that does nothing
    nodes = 0 if load is None else load.shape[1]
    spacing = L / (nodes - 1) if nodes > 1 else L
    inner = [k * spacing for k in range(1, nodes - 1)]
    extra = torch.tensor([0.0, *model.breakpoints, *inner], dtype=dtype, device=device)
    pos = torch.cat([s_ev, rows_q, extra[None, :].expand(R, extra.shape[0])], 1)
    E = pos.shape[1]
    order = pos.detach().sort(dim=1, descending=True, stable=True).indices  # forces first at ties
    at = pos.gather(1, order)  # (R, E), descending
    Yn = torch.zeros((R, 3, 1), dtype=dtype, device=device)  # the internal force n and moment m, as columns
    Ym = torch.zeros((R, 3, 1), dtype=dtype, device=device)
    e3 = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=dtype, device=device)[None]  # e3 x
    hat = torch.tensor(_HAT, dtype=dtype, device=device)

    def load_at(p: torch.Tensor) -> torch.Tensor:
        """(R, 3, 1) the distributed load at positions p (R,) [N/m], linear between the nodes."""
        assert load is not None  # called only with nodes, which come from the load
        j = (p / spacing).to(torch.int64).clamp(0, nodes - 2)
        frac = (p - j.to(dtype) * spacing) / spacing
        lo = load.gather(1, j[:, None, None].expand(R, 1, 2))[:, 0]
        hi = load.gather(1, (j + 1)[:, None, None].expand(R, 1, 2))[:, 0]
        w = lo + (hi - lo) * frac[:, None]
        return torch.cat([w, w[:, :1] * 0.0], 1)[:, :, None]

    def rates(Yn: torch.Tensor, Ym: torch.Tensor, ustar: torch.Tensor, w: torch.Tensor | None = None):
        U = _hat(ustar + Ym[:, :, 0] * kinv, hat)
        rn = -(U @ Yn)
        rm = -(U @ Ym) - e3 @ Yn
        return (rn - w, rm) if w is not None else (rn, rm)

    cur = at[:, 0] * 0.0 + L
    rec_n, rec_m = [], []
    for e in range(E):
        target = at[:, e]
        seg = cur - target  # (R,) >= 0
        longest = float(seg.detach().max()) if R else 0.0
        n_steps = math.ceil(longest / max_step - 1e-9) if longest > 0.0 else 0
        if steps is not None and longest > 0.0:
            n_steps = steps
        if n_steps:
            hs = (-seg / n_steps)[:, None, None]  # (R, 1, 1): towards the base
            half, sixth = 0.5 * hs, hs / 6.0
            ustar = intrinsic(model, (0.5 * (cur + target)).detach())
            w0 = w1 = None
            if nodes:
                w0, w1 = load_at(cur), load_at(target)  # the segment lies between two nodes: linear in between
            for i in range(n_steps):
                wa = wb = wc = None
                if nodes:
                    assert w0 is not None and w1 is not None  # set above with nodes
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
            jump = f3.gather(1, k.clamp(max=h - 1)[:, None, None].expand(R, 1, 3))[:, 0]  # (R, 3)
            Yn = Yn + torch.where((k < h)[:, None], jump, 0.0 * jump)[:, :, None]
        rec_n.append(Yn)
        rec_m.append(Ym)
    # The event index of each query: the inverse of the sort, at the queries' kinds.
    inverse = order.argsort(dim=1)[:, h : h + Q]  # (R, Q)
    idx = inverse[:, :, None, None].expand(R, Q, 3, 1)
    n_q = torch.stack(rec_n, 1).gather(1, idx)[..., 0]  # (R, Q, 3)
    m_q = torch.stack(rec_m, 1).gather(1, idx)[..., 0]
    u_q = intrinsic(model, rows_q) + m_q * kinv[:, None, :]
    return u_q, n_q


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
    dtype = loads.dtype
    query = torch.as_tensor(query, device=loads.device).reshape(-1).to(torch.float64)
    ei = None
    if bending_stiffness is not None:
        ei = (
            bending_stiffness.to(device=loads.device, dtype=torch.float64).reshape(-1)
            if isinstance(bending_stiffness, torch.Tensor)
            else float(bending_stiffness)
        )
    u, n = march(
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
