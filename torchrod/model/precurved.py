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
distal to it, as on the unloaded rod. Every operation is a torch operation on (B, 3) tensors, so the march is
batched and differentiable by autograd (``gradcheck`` holds it to that), on any device and dtype.

This is the general model; a rod without intrinsic curvature keeps the fast straight-rod path of
:mod:`.body_frame`, to which this march agrees (tests: to ~1e-12 with fine steps).
"""

from __future__ import annotations

import math

import torch

from ..loads import PointForces
from ..rod import Rod

__all__ = ["DEFAULT_MAX_STEP", "grating_curvature", "intrinsic", "march"]

DEFAULT_MAX_STEP = 5e-4
"""Longest RK4 step [m] by default (a fraction of a millimetre: at the 12 1/m of a concentric tube's curved section
the turning per step stays below 0.01 rad)."""


def intrinsic(rod: Rod, s: torch.Tensor) -> torch.Tensor:
    """u* = (ux*, uy*, 0) [1/m] at positions ``s`` (any shape) as a (..., 3) tensor of s's dtype and device; at a
    breakpoint the distal value (:meth:`torchrod.Rod.intrinsic_at`)."""
    out = torch.zeros((*s.shape, 3), dtype=s.dtype, device=s.device)
    for a, b, ux, uy in rod.intrinsic_curvature:
        inside = (s >= a) & ((s < b) | ((s == b) & (b == rod.length)))
        value = torch.tensor([ux, uy, 0.0], dtype=s.dtype, device=s.device)
        out = torch.where(inside.unsqueeze(-1), value, out)
    return out


def _rates(n: torch.Tensor, m: torch.Tensor, ustar: torch.Tensor, kinv: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """d/ds of (n, m) (B, 3) each."""
    u = ustar + m * kinv
    e3n = torch.stack([-n[:, 1], n[:, 0], torch.zeros_like(n[:, 0])], 1)  # e3 x n
    return -torch.linalg.cross(u, n), -torch.linalg.cross(u, m) - e3n


def march(
    rod: Rod,
    loads: PointForces,
    query: torch.Tensor,
    *,
    max_step: float = DEFAULT_MAX_STEP,
    bending_stiffness: float | torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Curvature and internal force of the precurved ``rod`` under ``loads`` at ``query`` (module docstring).

    Args:
        rod: the rod (length, EI, GJ, intrinsic curvature).
        loads: B sets of follower point forces (body frame, [m] and [N]); inactive slots carry no force.
        query: (Q,) positions in [0, L] [m], any order.
        max_step: the longest RK4 step [m].
        bending_stiffness: overrides the rod's EI [N m^2] (a float, or a () or (B,) tensor; GJ scales with it).
    Returns:
        u (B, Q, 3) body-frame curvature [1/m] and n (B, Q, 3) body-frame internal force [N] (the proximal side of a
        force at the query); dtype and device follow ``loads``.
    """
    if not (isinstance(max_step, (int, float)) and math.isfinite(max_step) and max_step > 0.0):
        raise ValueError(f"max_step must be a positive length [m], got {max_step!r}")
    dtype, device = loads.dtype, loads.device
    B, h = loads.s.shape
    query = torch.as_tensor(query, dtype=dtype, device=device).reshape(-1)
    Q = query.shape[0]
    ei = torch.as_tensor(rod.bending_stiffness if bending_stiffness is None else bending_stiffness, dtype=dtype)
    ei = ei.to(device).reshape(-1, 1)  # (1, 1) or (B, 1)
    gj = ei * (rod.torsion_stiffness / rod.bending_stiffness)
    kinv = torch.cat([1.0 / ei, 1.0 / ei, 1.0 / gj], 1)  # (1 or B, 3)
    f = loads.masked_f()  # (B, h, 2), zero where inactive
    force3 = torch.cat([f, torch.zeros_like(f[..., :1])], -1)  # (B, h, 3)
    extra = torch.tensor([0.0, *rod.breakpoints()], dtype=dtype, device=device)
    # Events per sample: forces (kinds 0..h-1), queries (h..h+Q-1), breakpoints and the base (the rest).
    s_forces = torch.where(loads.active, loads.s, torch.full_like(loads.s, rod.length))  # padding: a no-op at L
    pos = torch.cat([s_forces, query.expand(B, Q), extra.expand(B, extra.shape[0])], 1)  # (B, E)
    E = pos.shape[1]
    order = torch.argsort(-pos.detach(), dim=1, stable=True)
    at = torch.gather(pos, 1, order)  # (B, E) descending
    kind = order
    n = torch.zeros((B, 3), dtype=dtype, device=device)
    m = torch.zeros((B, 3), dtype=dtype, device=device)
    cur = torch.full((B,), rod.length, dtype=dtype, device=device)
    recorded_m, recorded_n = [], []
    rows = torch.arange(B, device=device)
    for e in range(E):
        target = at[:, e]
        seg = cur - target  # (B,) >= 0
        longest = float(seg.detach().max()) if B else 0.0
        steps = math.ceil(longest / max_step - 1e-9) if longest > 0.0 else 0
        if steps:
            ds = (-seg / steps).unsqueeze(1)  # (B, 1): towards the base
            ustar = intrinsic(rod, (0.5 * (cur + target)).detach())  # constant on the segment
            for _ in range(steps):
                a_n, a_m = _rates(n, m, ustar, kinv)
                b_n, b_m = _rates(n + 0.5 * ds * a_n, m + 0.5 * ds * a_m, ustar, kinv)
                c_n, c_m = _rates(n + 0.5 * ds * b_n, m + 0.5 * ds * b_m, ustar, kinv)
                d_n, d_m = _rates(n + ds * c_n, m + ds * c_m, ustar, kinv)
                n = n + ds / 6.0 * (a_n + 2.0 * b_n + 2.0 * c_n + d_n)
                m = m + ds / 6.0 * (a_m + 2.0 * b_m + 2.0 * c_m + d_m)
        cur = target
        k = kind[:, e]
        if h:
            is_force = (k < h).unsqueeze(1)
            jump = force3[rows, k.clamp(max=h - 1)]  # (B, 3)
            n = n + torch.where(is_force, jump, torch.zeros_like(jump))
        recorded_m.append(m)
        recorded_n.append(n)
    m_events = torch.stack(recorded_m, 1)  # (B, E, 3)
    n_events = torch.stack(recorded_n, 1)
    # The event index of each query: the inverse of the sort, at the queries' kinds.
    inverse = torch.argsort(order, dim=1)[:, h : h + Q]  # (B, Q)
    idx = inverse.unsqueeze(-1).expand(B, Q, 3)
    m_q, n_q = torch.gather(m_events, 1, idx), torch.gather(n_events, 1, idx)
    u = intrinsic(rod, query).unsqueeze(0) + m_q * kinv.unsqueeze(1)
    return u, n_q


def grating_curvature(
    rod: Rod, loads: PointForces, *, relative: bool = False, max_step: float = DEFAULT_MAX_STEP
) -> torch.Tensor:
    """(B, G, 2) what the gratings read [1/m]: the total body-frame curvature (ux, uy), or with ``relative`` the
    change from the unloaded shape, u - u*."""
    query = rod.grating_positions(loads.dtype, loads.device)
    u, _ = march(rod, loads, query, max_step=max_step)
    if relative:
        u = u - intrinsic(rod, query).unsqueeze(0)
    return u[..., :2]
