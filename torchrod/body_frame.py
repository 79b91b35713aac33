"""The body-frame rod model: curvature as an initial-value problem integrated from the free tip to the base.

Equations (NOTES.md, "The body-frame equations"): for a straight, isotropic, inextensible, unshearable rod with no
external moment, u_z = 0 and

    u_x' = n_y / EI,    u_y' = -n_x / EI,    n' = -f - u x n.

Two exact reductions make this cheap and parameter-free:

1. With m = n / EI [1/m^2] the stiffness leaves the differential equation and only scales the loads.
2. m_z + |u|^2 / 2 is constant along the rod (differentiate: m_z' = -(u x m)_z = -(u_x u_x' + u_y u_y')), also
   across perpendicular point forces (they do not change m_z or u), and it is 0 at the free tip. So m_z = -|u|^2/2
   everywhere, and in complex form U = u_x + i u_y, (m_x + i m_y) = i U':

       U'' = -|U|^2 U / 2 + (i w_x - w_y) / EI          (w: distributed perpendicular load [N/m])

   A point force (f_x, f_y) at s_i makes U' jump going from tip to base: U'(s_i-) = U'(s_i+) + (f_y - i f_x)/EI.

The rod is integrated from s = L (U = U' = 0) to s = 0 as a sequence of events: the query positions (gratings, sample
points) and the force locations, sorted per sample, so every sample in a batch keeps its own load locations and
the jump happens exactly at s_i (no node count in the default scheme). Each segment between events is crossed
with fourth-order Runge-Kutta-Nystrom steps; the number of steps in a segment is chosen from a rigorous bound on
|U| (|U(s)| <= sum_i |f_i| (s_i - s)^+ / EI) so that max(|U|, sqrt|m|) h stays below ``max_step_angle``
(|m| <= sum over distal forces of |f_i| / EI).

The paper's scheme (``scheme="nodes"``) spreads each force onto the two nearest of q uniform nodes (NOTES.md,
erratum 3) and integrates the distributed load, interpolated linearly between nodes, one step per node interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from .loads import PointForces, spread_to_nodes
from .rod import Rod

__all__ = ["Simulation", "simulate", "grating_curvature", "integrate_curvature", "DEFAULT_STEP_ANGLE"]

DEFAULT_STEP_ANGLE = 0.08
"""Default bound on (local rate) x (step) per Runge-Kutta-Nystrom step, dimensionless: gratings within 1e-6 relative."""

Scheme = Literal["exact", "nodes"]


@dataclass(frozen=True)
class Simulation:
    """The result of :func:`simulate`.

    Attributes:
        grating_curvature: (B, G, 2) curvature (u_x, u_y) at the rod's gratings [1/m].
        s: (S,) positions along the rod where the profiles below are sampled [m], increasing.
        curvature: (B, S, 2) curvature at ``s`` [1/m].
        internal_force: (B, S, 3) body-frame internal force n = R^T N at ``s`` [N] (proximal side of a force).
    """

    grating_curvature: torch.Tensor
    s: torch.Tensor
    curvature: torch.Tensor
    internal_force: torch.Tensor

    def curvature_magnitude(self) -> torch.Tensor:
        """(B, S) |u| along the rod [1/m]."""
        return torch.linalg.vector_norm(self.curvature, dim=-1)


def _as_stiffness(ei: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """EI as a (B, 1) or (1, 1) tensor on ``like``'s dtype and device."""
    ei = torch.as_tensor(ei, dtype=like.dtype, device=like.device)
    if ei.dim() == 0:
        return ei.reshape(1, 1)
    if ei.dim() == 1 and ei.shape[0] in (1, like.shape[0]):
        return ei.unsqueeze(1)
    raise ValueError(f"bending_stiffness must be a scalar or have shape (B,) = ({like.shape[0]},), got {tuple(ei.shape)}")


def _steps_for(rate: torch.Tensor, lengths: torch.Tensor, max_step_angle: float, max_steps: int) -> list[int]:
    """Steps per segment so that rate * (segment length / steps) <= max_step_angle in every sample."""
    need = (rate * lengths).amax(dim=0) / max_step_angle  # (E,)
    need = torch.nan_to_num(need, nan=1.0, posinf=float(max_steps))
    return [min(max_steps, max(1, math.ceil(x))) for x in need.tolist()]


def integrate_curvature(
    query: torch.Tensor,
    loads: PointForces,
    length: float,
    bending_stiffness: float | torch.Tensor,
    *,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    steps: int | None = None,
    max_steps: int = 64,
    return_force: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Exact point loads: U and (optionally) the internal force at ``query``, tip-to-base, batched.

    No input checks (the hot path of estimation); :func:`simulate` is the checked entry point.

    Args:
        query: (Q,) positions [m] in [0, length] where the state is wanted.
        loads: B point-force sets, locations in [0, length].
        length: rod length L [m].
        bending_stiffness: EI [N m^2]: a float, or a tensor () or (B,) (differentiable).
        max_step_angle: bound on |U| h per step; ``steps`` fixes the steps per segment instead.
    Returns:
        curvature (B, Q, 2) [1/m] and, with ``return_force``, the internal force (B, Q, 3) [N], else None.
    """
    s, f = loads.s, loads.masked_f()
    B, h = s.shape
    Q = query.shape[0]
    ei = _as_stiffness(bending_stiffness, s)
    # Jump of W = dU/dt (t = L - s) at a force: W(s_i-) = W(s_i+) - (f_y - i f_x)/EI, as real pairs (-f_y, f_x)/EI.
    jump_f = torch.stack((-f[..., 1], f[..., 0]), dim=-1) / ei.unsqueeze(-1)  # (B, h, 2)
    pos = torch.cat((query.expand(B, Q), s), dim=1)  # (B, E)
    jump = torch.cat((jump_f.new_zeros(B, Q, 2), jump_f), dim=1)  # (B, E, 2)
    pos_sorted, order = pos.sort(dim=1, descending=True, stable=True)
    jump_sorted = jump.gather(1, order.unsqueeze(-1).expand(-1, -1, 2))
    start = torch.cat((pos_sorted.new_full((B, 1), float(length)), pos_sorted[:, :-1]), dim=1)
    seg = (start - pos_sorted).clamp(min=0.0)  # (B, E) segment lengths, tip to base
    E = seg.shape[1]

    if steps is None:
        with torch.no_grad():
            fmag = (torch.linalg.vector_norm(f, dim=-1) / ei).unsqueeze(1)  # (B, 1, h) [1/m^2]
            lever = (s.unsqueeze(1) - pos_sorted.unsqueeze(2)).clamp(min=0.0)  # (B, E, h) [m]
            # Rigorous bounds at each segment's proximal end: |U| <= sum_i |f_i| (s_i - s)^+ / EI and
            # |m| <= sum_{s_i > s} |f_i| / EI. The local rate of the solution is max(|U|, sqrt|m|) [1/m].
            bound_u = (fmag * lever).sum(-1)
            bound_m = (fmag * (lever > 0)).sum(-1)
            rate = torch.maximum(bound_u, bound_m.sqrt())
            counts = _steps_for(rate, seg, max_step_angle, max_steps)
    else:
        counts = [int(steps)] * E
    U, W, recorded = _march(seg, counts, jump_sorted.unbind(1), None)
    states = torch.stack(recorded, dim=1)  # (B, E, 4) state at each event, proximal side
    inverse = order.argsort(dim=1)[:, :Q]  # sorted index of each query
    at_query = states.gather(1, inverse.unsqueeze(-1).expand(-1, -1, 4))
    curvature = at_query[..., :2]
    force = _internal_force(at_query, ei) if return_force else None
    return curvature, force


def _internal_force(state: torch.Tensor, ei: torch.Tensor) -> torch.Tensor:
    """n = EI m with m_x + i m_y = i U' = -i W and m_z = -|U|^2/2; state (B, Q, 4) = (U, W)."""
    ux, uy, wx, wy = state.unbind(-1)
    m = torch.stack((wy, -wx, -0.5 * (ux * ux + uy * uy)), dim=-1)
    return m * ei.unsqueeze(-1)


def _march(
    seg: torch.Tensor,
    counts: list[int],
    jumps: tuple[torch.Tensor, ...] | list[torch.Tensor],
    forcing: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """March U_tt = -|U|^2 U / 2 + phi(t) over segments (t = L - s increasing), recording (U, W) after each event.

    Fourth-order Runge-Kutta-Nystrom (three stages, nodes 0, 1/2, 1). With g~ = |U|^2 U (so g = -g~/2):
        Y2 = U + h/2 W - h^2/16 g~1,  Y3 = U + h W - h^2/4 g~2,
        U+ = U + h W - h^2/12 (g~1 + 2 g~2),  W+ = W - h/12 (g~1 + 4 g~2 + g~3)
    ``forcing`` = (phi at segment starts, phi at segment ends), each (B, E, 2) [1/m^3], linear in between, for the
    paper's node scheme.
    """
    B, E = seg.shape
    dtype, device = seg.dtype, seg.device
    U = torch.zeros(B, 2, dtype=dtype, device=device)
    W = torch.zeros(B, 2, dtype=dtype, device=device)
    recorded: list[torch.Tensor] = []
    n = torch.tensor(counts, dtype=dtype, device=device)
    hstep = (seg / n).unsqueeze(-1)  # (B, E, 1)
    scales = torch.tensor([0.5, -1.0 / 16.0, 1.0, -0.25, -1.0 / 12.0, -1.0 / 12.0], dtype=dtype, device=device)
    powers = torch.tensor([1.0, 2.0, 1.0, 2.0, 2.0, 1.0], dtype=dtype, device=device)
    coef = (hstep.pow(powers) * scales).unsqueeze(-1).unbind(1)  # E x (B, 6, 1)
    if forcing is not None:
        # With a forcing phi the stage accelerations are g + phi; fold phi into the same coefficients.
        f0, f1 = (x.unbind(1) for x in forcing)
    for e in range(E):
        c_half, c_16, c_h, c_4, c_12, c_w = coef[e].unbind(1)
        for k in range(counts[e]):
            g1 = U * (U * U).sum(-1, keepdim=True)
            Y = torch.addcmul(torch.addcmul(U, c_half, W), c_16, g1)
            g2 = Y * (Y * Y).sum(-1, keepdim=True)
            P = torch.addcmul(U, c_h, W)
            Y = torch.addcmul(P, c_4, g2)
            g3 = Y * (Y * Y).sum(-1, keepdim=True)
            if forcing is not None:
                # phi varies linearly inside a segment; stage times are t, t + h/2, t + h within the segment.
                p1 = torch.lerp(f0[e], f1[e], k / counts[e])
                p2 = torch.lerp(f0[e], f1[e], (k + 0.5) / counts[e])
                p3 = torch.lerp(f0[e], f1[e], (k + 1.0) / counts[e])
                # g~ terms carry the factor -1/2 through the coefficients; phi enters as -2 phi in g~ units.
                g1 = g1 - 2.0 * p1
                g2 = g2 - 2.0 * p2
                g3 = g3 - 2.0 * p3
            U = torch.addcmul(P, c_12, torch.add(g1, g2, alpha=2.0))
            W = torch.addcmul(W, c_w, torch.add(torch.add(g1, g2, alpha=4.0), g3))
        W = W + jumps[e]
        recorded.append(torch.cat((U, W), dim=-1))
    return U, W, recorded


def integrate_curvature_nodes(
    query: torch.Tensor,
    loads: PointForces,
    length: float,
    bending_stiffness: float | torch.Tensor,
    nodes: int,
    *,
    return_force: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The paper's scheme: forces spread onto ``nodes`` uniform nodes (hat weights), one RKN step per interval.

    Same arguments and returns as :func:`integrate_curvature`; ``nodes`` is the paper's q (>= 2).
    """
    s = loads.s
    B = s.shape[0]
    dtype, device = s.dtype, s.device
    ei = _as_stiffness(bending_stiffness, s)
    grid = torch.linspace(0.0, float(length), nodes, dtype=dtype, device=device)
    w_nodes = spread_to_nodes(loads, grid)  # (B, q, 2) [N/m]
    # Events: the nodes and the queries, shared by the whole batch; the load is linear between events.
    pos = torch.cat((query, grid))
    pos_sorted, order = pos.sort(descending=True, stable=True)
    d = grid[1] - grid[0]
    hat = torch.clamp(1.0 - (pos_sorted.unsqueeze(-1) - grid).abs() / d, min=0.0)  # (E, q)
    w_events = torch.einsum("eq,bqc->bec", hat, w_nodes)  # (B, E, 2)
    # phi = (-w_y, w_x) / EI in the (U_x, U_y) pair; U_tt = U'' (t = L - s).
    phi = torch.stack((-w_events[..., 1], w_events[..., 0]), dim=-1) / ei.unsqueeze(-1)
    # Segment e runs from event e-1 to event e; the first event is the node at s = L (a zero-length segment).
    phi_start = torch.cat((phi[:, :1], phi[:, :-1]), dim=1)
    start = torch.cat((pos_sorted.new_tensor([float(length)]), pos_sorted[:-1]))
    seg = (start - pos_sorted).clamp(min=0.0).expand(B, -1)
    E = seg.shape[1]
    zero_jumps = [phi.new_zeros(B, 2)] * E
    _, _, recorded = _march(seg, [1] * E, zero_jumps, (phi_start, phi))
    states = torch.stack(recorded, dim=1)
    inverse = order.argsort()[: query.shape[0]]
    at_query = states[:, inverse]
    curvature = at_query[..., :2]
    force = _internal_force(at_query, ei) if return_force else None
    return curvature, force


def _check_loads(rod: Rod, loads: PointForces) -> None:
    if not isinstance(loads, PointForces):
        raise TypeError(f"loads must be PointForces, got {type(loads).__name__}")
    active = loads.active
    s = loads.s.detach()
    if not bool(torch.isfinite(s[active]).all()) or not bool(torch.isfinite(loads.f.detach()[active]).all()):
        raise ValueError("load locations and components must be finite")
    bad = active & ((s < 0.0) | (s > rod.length))
    if bool(bad.any()):
        b, i = (int(x) for x in bad.nonzero()[0])
        raise ValueError(f"force location s[{b}, {i}] = {float(s[b, i])} m lies outside [0, L = {rod.length}] m")


def grating_curvature(
    rod: Rod,
    loads: PointForces,
    *,
    scheme: Scheme = "exact",
    nodes: int = 250,
    bending_stiffness: float | torch.Tensor | None = None,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
) -> torch.Tensor:
    """(B, G, 2) curvature at the rod's gratings [1/m] (the measurement model). Unchecked, for hot loops."""
    query = rod.grating_positions(loads.dtype, loads.device)
    ei = rod.bending_stiffness if bending_stiffness is None else bending_stiffness
    if scheme == "exact":
        return integrate_curvature(query, loads, rod.length, ei, max_step_angle=max_step_angle)[0]
    return integrate_curvature_nodes(query, loads, rod.length, ei, nodes)[0]


def simulate(
    rod: Rod,
    loads: PointForces,
    *,
    samples: int = 0,
    at: torch.Tensor | None = None,
    scheme: Scheme = "exact",
    nodes: int = 250,
    bending_stiffness: float | torch.Tensor | None = None,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    steps: int | None = None,
) -> Simulation:
    """Curvature and internal force of a clamped rod under point forces, batched and differentiable.

    Args:
        rod: the rod (length, EI, gratings).
        loads: B point-force sets; locations must lie in [0, L].
        samples: also sample the profiles at this many uniform positions over [0, L].
        at: (S,) extra positions [m] to sample at (besides the gratings and ``samples``).
        scheme: ``"exact"`` (point loads exact, the default) or ``"nodes"`` (the paper's node spreading).
        nodes: the paper's q for ``scheme="nodes"``.
        bending_stiffness: overrides ``rod.bending_stiffness``: a float or a tensor () / (B,) [N m^2]
            (a tensor that requires grad makes the result differentiable in EI).
        max_step_angle: accuracy knob of the exact scheme (bound on |U| h per step).
        steps: fixed steps per segment for the exact scheme (overrides ``max_step_angle``), for convergence studies.
    Returns:
        :class:`Simulation`; dtype and device follow ``loads``.
    """
    _check_loads(rod, loads)
    if scheme not in ("exact", "nodes"):
        raise ValueError(f"scheme must be 'exact' or 'nodes', got {scheme!r}")
    if scheme == "nodes" and (not isinstance(nodes, int) or nodes < 2):
        raise ValueError(f"nodes must be an integer >= 2, got {nodes!r}")
    if samples < 0:
        raise ValueError(f"samples must be >= 0, got {samples}")
    dtype, device = loads.dtype, loads.device
    grat = rod.grating_positions(dtype, device)
    parts = [grat]
    if samples:
        parts.append(torch.linspace(0.0, rod.length, samples, dtype=dtype, device=device))
    if at is not None:
        at = torch.as_tensor(at, dtype=dtype, device=device).reshape(-1)
        if bool(((at < 0) | (at > rod.length) | ~torch.isfinite(at)).any()):
            raise ValueError(f"sample positions must lie in [0, {rod.length}] m, got {at.tolist()}")
        parts.append(at)
    query = torch.cat(parts)
    ei = rod.bending_stiffness if bending_stiffness is None else bending_stiffness
    if scheme == "exact":
        curv, force = integrate_curvature(
            query, loads, rod.length, ei, max_step_angle=max_step_angle, steps=steps, return_force=True
        )
    else:
        curv, force = integrate_curvature_nodes(query, loads, rod.length, ei, nodes, return_force=True)
    G = grat.shape[0]
    extra = query[G:]
    if extra.numel():
        srt, idx = extra.sort()
        profile_s, profile_u, profile_n = srt, curv[:, G:][:, idx], force[:, G:][:, idx]
    else:
        profile_s, profile_u, profile_n = grat, curv[:, :G], force[:, :G]
    return Simulation(grating_curvature=curv[:, :G], s=profile_s, curvature=profile_u, internal_force=profile_n)
