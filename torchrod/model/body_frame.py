"""The body-frame rod model: curvature as an initial-value problem integrated from the free tip to the base.

Equations (docs/physics.md, "The body-frame equations"): for a straight, isotropic, inextensible, unshearable rod with
no external moment, u_z = 0 and

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
the jump happens exactly at s_i (no node count in the default scheme). Each segment between events is crossed with
explicit Runge-Kutta-Nystrom steps (default: the 8th-order method of Dormand, El-Mikkawy & Prince). The events,
their order at ties and the step counts are the schedule of :mod:`torchrod.model.schedule` (one definition for
every march), here with its rigorous ``"bound"`` rule on the local rate: rate x step <= ``max_step_angle``.
Every sample gets its own step counts; a batch runs max over samples of (total steps) steps, shorter schedules
padded with steps of length zero.

The march (:mod:`torchrod.model.nystrom`) runs inside one autograd node with a hand-written discrete adjoint (the exact
gradient of the discrete scheme, in O(steps) memory): on the CPU in NumPy (or plain Python numbers for a batch of a
few), elsewhere in torch. ``adjoint=False`` instead records every torch operation for autograd: slower, but it
supports ``torch.func`` transforms and higher derivatives.

The paper's scheme (``scheme="nodes"``) spreads each force onto the two nearest of q uniform nodes (docs/physics.md,
erratum 3) and integrates the distributed load, interpolated linearly between nodes, one step per node interval
(classical 4th-order Runge-Kutta-Nystrom by default).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch

from ..backend import torch_backend
from ..loads import PointForces, spread_to_nodes
from ..rod import Rod
from . import compiled, schedule
from .nystrom import METHODS, Tableau, _forward_array, _forward_generic, _sq_complex, march

__all__ = [
    "DEFAULT_STEP_ANGLE",
    "METHODS",
    "Simulation",
    "grating_curvature",
    "integrate_curvature",
    "integrate_curvature_nodes",
    "simulate",
    "step_counts",
]

DEFAULT_STEP_ANGLE = 0.8
"""Default bound on (local rate) x (step) per step of the default method ("rkn8"), dimensionless. Measured on
large deflections (bending >= 90 degrees, 1-3 forces up to 2 N on the paper's tube, adversarial sets included):
gratings within 5e-8 of a converged reference relative to max |u|, and within 1e-7 with only two query points (no
help from the gratings' event spacing). On that tube the gratings (20 mm apart) already make every segment short
enough for one step, so the cost is one 8-stage step per event."""

DEFAULT_MAX_STEPS = 64
"""Default cap on the steps of one segment between events (forces, gratings)."""

Scheme = Literal["exact", "nodes"]


@dataclass(frozen=True)
class Simulation:
    """The result of :func:`simulate`.

    Attributes:
        grating_curvature: (B, G, 2) curvature (u_x, u_y) at the rod's gratings [1/m].
        s: (S,) positions along the rod where the profiles below are sampled [m], increasing.
        curvature: (B, S, 2) curvature at ``s`` [1/m].
        internal_force: (B, S, 3) body-frame internal force n = R^T N at ``s`` [N] (proximal side of a force).
        twist: (B, S) the twist u_z at ``s`` [1/m] of a precurved rod (None for a straight rod, which never twists).
    """

    grating_curvature: torch.Tensor
    s: torch.Tensor
    curvature: torch.Tensor
    internal_force: torch.Tensor
    twist: torch.Tensor | None = None

    @property
    def full_curvature(self) -> torch.Tensor:
        """(B, S, 3) (u_x, u_y, u_z) at ``s`` [1/m] (u_z zero for a straight rod)."""
        uz = self.twist if self.twist is not None else torch.zeros_like(self.curvature[..., 0])
        return torch.cat([self.curvature, uz.unsqueeze(-1)], -1)

    def curvature_magnitude(self) -> torch.Tensor:
        """(B, S) |u| along the rod [1/m]."""
        return torch.linalg.vector_norm(self.curvature, dim=-1)


# ================================================================================================= the schemes
def _as_stiffness(ei: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """EI as a (B, 1) or (1, 1) tensor on ``like``'s dtype and device."""
    ei = torch.as_tensor(ei, dtype=like.dtype, device=like.device)
    if ei.dim() == 0:
        return ei.reshape(1, 1)
    if ei.dim() == 1 and ei.shape[0] in (1, like.shape[0]):
        return ei.unsqueeze(1)
    raise ValueError(
        f"bending_stiffness must be a scalar or have shape (B,) = ({like.shape[0]},), got {tuple(ei.shape)}"
    )


_DEFAULT_METHOD = {"exact": "rkn8", "nodes": "rkn4"}


def _method(name: str | None, scheme: str) -> Tableau:
    name = _DEFAULT_METHOD[scheme] if name is None else name
    if name not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {name!r}")
    return METHODS[name]


def _valid_loads(loads: PointForces) -> tuple[torch.Tensor, torch.Tensor]:
    """(s, f) with padded forces at s = 0 carrying no load, whatever (even NaN) they hold. Autograd-safe."""
    if loads.mask is None:
        return loads.s, loads.f
    s = torch.where(loads.mask, loads.s, torch.zeros_like(loads.s))
    f = torch.where(loads.mask.unsqueeze(-1), loads.f, torch.zeros_like(loads.f))
    return s, f


def _events(
    query: torch.Tensor, s: torch.Tensor, f: torch.Tensor, ei: torch.Tensor, length: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The schedule's events (:func:`torchrod.model.schedule.events`): positions (B, E) [m], the sort order (B, E)
    (indices < h are forces), segment lengths (B, E) [m], and the jump of W at each event (B, E, 2) [1/m^2]."""
    B, Q = s.shape[0], query.shape[0]
    # Jump of W = dU/dt (t = L - s) at a force: W(s_i-) = W(s_i+) - (f_y - i f_x)/EI, as real pairs (-f_y, f_x)/EI.
    jump_f = torch.stack((-f[..., 1], f[..., 0]), dim=-1) / ei.unsqueeze(-1)  # (B, h, 2)
    pos_sorted, order, seg = schedule.events(torch_backend(s.device), query, s, length)
    jump = torch.cat((jump_f, jump_f.new_zeros(B, Q, 2)), dim=1).gather(1, order.unsqueeze(-1).expand(-1, -1, 2))
    return pos_sorted, order, seg, jump


def _step_counts(
    s: torch.Tensor,
    f: torch.Tensor,
    ei: torch.Tensor,
    pos: torch.Tensor,
    seg: torch.Tensor,
    angle: float,
    cap: int,
) -> torch.Tensor:
    """(B, E) steps per segment: the schedule's rigorous ``"bound"`` rule (:mod:`torchrod.model.schedule`)."""
    fmag = torch.linalg.vector_norm(f, dim=-1) / ei  # (B, h) [1/m^2]
    xp = torch_backend(s.device)
    return schedule.step_counts(xp, s, fmag, pos, seg, step_angle=angle, max_steps=cap, rule="bound")


def step_counts(
    rod: Rod,
    loads: PointForces,
    *,
    bending_stiffness: float | torch.Tensor | None = None,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> torch.Tensor:
    """(B, E) steps per segment that :func:`grating_curvature` takes with the exact scheme (a diagnostic).

    Segments run between events (the rod's gratings and the forces, padding included), tip to base, E = G + h.
    A batch runs max over samples of the row sums: every sample's own steps, then zero-length steps.
    """
    s, f = _valid_loads(loads)
    ei = _as_stiffness(rod.bending_stiffness if bending_stiffness is None else bending_stiffness, s)
    with torch.no_grad():
        pos_sorted, _, seg, _ = _events(rod.grating_positions(s.dtype, s.device), s, f, ei, rod.length)
        return _step_counts(s, f, ei, pos_sorted, seg, max_step_angle, max_steps)


def integrate_curvature(
    query: torch.Tensor,
    loads: PointForces,
    length: float,
    bending_stiffness: float | torch.Tensor,
    *,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    steps: int | None = None,
    max_steps: int = DEFAULT_MAX_STEPS,
    return_force: bool = False,
    method: str | None = None,
    adjoint: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Exact point loads: U and (optionally) the internal force at ``query``, tip-to-base, batched.

    No input checks (the hot path of estimation); :func:`simulate` is the checked entry point.

    Args:
        query: (Q,) positions [m] in [0, length] where the state is wanted.
        loads: B point-force sets, locations in [0, length].
        length: rod length L [m].
        bending_stiffness: EI [N m^2]: a float, or a tensor () or (B,) (differentiable).
        max_step_angle: bound on (local rate) x (step) per step; ``steps`` fixes the steps per segment instead.
        max_steps: most steps in one segment.
        method: "rkn8" (default), "rkn6" or "rkn4" (:data:`METHODS`).
        adjoint: hand-written discrete adjoint (fast); False records every operation for autograd.
    Returns:
        curvature (B, Q, 2) [1/m] and, with ``return_force``, the internal force (B, Q, 3) [N] (proximal side of a
        force at the query), else None.
    """
    tab = _method(method, "exact")
    s, f = _valid_loads(loads)
    B, h = s.shape
    ei = _as_stiffness(bending_stiffness, s)
    pos_sorted, order, seg, jump = _events(query, s, f, ei, length)
    E = seg.shape[1]
    with torch.no_grad():
        if steps is None:
            counts = _step_counts(s, f, ei, pos_sorted, seg, max_step_angle, max_steps)
        else:
            counts = torch.full((B, E), int(steps), dtype=torch.int64, device=s.device)
    # Every sample runs K steps: its own step lengths, then zero-length steps once its events are done
    # (schedule.sequence). ends: the step that ends each event (forces, then queries, in input order).
    hstep, slot = schedule.sequence(torch_backend(s.device), order, seg, counts)  # (B, K) [m], (B, E)
    K, ends = hstep.shape[1], slot - 1
    kick_at = ends.gather(1, order).unsqueeze(-1).expand(-1, -1, 2)  # in event order, as ``jump``
    kick = jump.new_zeros(B, K, 2).scatter(1, kick_at, jump)  # (B, K, 2)
    Z = march(hstep, tab, kick=kick, adjoint=adjoint)  # (B, K, 4)
    at_query = Z.gather(1, ends[:, h:].unsqueeze(-1).expand(-1, -1, 4))  # (B, Q, 4)
    curvature = at_query[..., :2]
    force = _internal_force(at_query, ei) if return_force else None
    return curvature, force


ROWS_MAX_BATCH = 12
""":func:`march_curvature` runs batches up to this size one row at a time on Python numbers. Measured against the
arrays on 1-3 forces of ``bench estimate``'s envelope (docs/results.md, "The two forward-sensitivity marches"): the
rows win up to 16 rows for one or two forces and up to 12 for three."""


def march_curvature(
    xp: Any,
    query: Any,
    s: Any,
    f: Any,
    length: float,
    bending_stiffness: float,
    *,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    method: str | None = None,
) -> Any:
    """:func:`integrate_curvature` without autograd on a backend's arrays (:mod:`torchrod.backend`): curvature
    (B, Q, 2) [1/m] at ``query`` (Q,) for forces s (B, h) [m], f (B, h, 2) [N]. The same schedule and method; a few
    rows on NumPy (at most :data:`ROWS_MAX_BATCH`) run one at a time on Python numbers (no per-operation overhead),
    the rest as arrays; where the compiled march runs (:mod:`torchrod.model.compiled`), every NumPy batch runs one
    row at a time on it."""
    tab = _method(method, "exact")
    B, h = s.shape
    Q = query.shape[0]
    ei = float(bending_stiffness)
    fmag = xp.lib.sqrt((f * f).sum(-1)) / ei
    jump = xp.complex(-f[..., 1], f[..., 0]) / ei  # (B, h) slope jumps
    if xp.name == "numpy" and (B <= ROWS_MAX_BATCH or compiled.available()):
        import numpy as np

        out = np.zeros((B, Q, 2))
        python = range(B)
        if compiled.takes(B > ROWS_MAX_BATCH):
            # The same march compiled (the small batches give the same numbers on either), every batch size; rows
            # with a non-finite input stay on Python numbers.
            marched = compiled.exact_rows(query, s, fmag, jump, length, max_step_angle, DEFAULT_MAX_STEPS, tab, out)
            python = np.flatnonzero(~marched).tolist()
        if not len(python):
            return out
        queries, positions, magnitudes, slopes = query.tolist(), s.tolist(), fmag.tolist(), jump.tolist()
        for b in python:
            jumps = slopes[b]
            order, seg, counts = schedule.row(
                queries,
                positions[b],
                magnitudes[b],
                length,
                step_angle=max_step_angle,
                max_steps=DEFAULT_MAX_STEPS,
                rule="bound",
                skip=True,
            )
            hs, kicks, ends = [], [], []
            for e, idx in enumerate(order):
                n = counts[e]  # 0 only for queries distal to every force
                if n:
                    hs += [seg[e] / n] * n
                    kicks += [None] * (n - 1) + [jumps[idx] if idx < h and jumps[idx] != 0 else None]
                ends.append(len(hs) - 1)
            Us, _, _ = _forward_generic(tab, 0j, hs, [x * x for x in hs], kicks, None, _sq_complex, False)
            at = [0j] * Q
            for e, idx in enumerate(order):
                if idx >= h and ends[e] >= 0:
                    at[idx - h] = Us[ends[e]]
            z = np.asarray(at)
            out[b, :, 0], out[b, :, 1] = z.real, z.imag
        return out
    pos, order, seg = schedule.events(xp, query, s, length)
    steps = schedule.step_counts(
        xp, s, fmag, pos, seg, step_angle=max_step_angle, max_steps=DEFAULT_MAX_STEPS, rule="bound"
    )
    steps = schedule.skip_unloaded(xp, order, steps, h)  # the zero state distal to every force: no steps
    # Arrays: every row runs K steps, its own step lengths then zero-length steps (as integrate_curvature). Slot j:
    # the state after j steps (0: the zero state before any).
    hstep, slot = schedule.sequence(xp, order, seg, steps)  # (B, K), (B, E)
    K = hstep.shape[1]
    at = xp.astype(slot[:, :h, None] - 1 == xp.arange(K)[None, None, :], "complex")  # (B, h, K): forces' steps
    kick = (at * jump[:, :, None]).sum(1)  # (B, K), the slope jumps after each step
    kick2 = xp.stack([kick.real, kick.imag], 1)  # (B, 2, K)
    hs = xp.mT(hstep)
    kicks = kick2.transpose(2, 1, 0) if xp.name == "numpy" else kick2.permute(2, 1, 0)
    Z, _ = _forward_array(tab, hs + 0.0, kicks + 0.0, None, False)  # (K, 4, B)
    Zb = Z.transpose(2, 0, 1) if xp.name == "numpy" else Z.permute(2, 0, 1)  # (B, K, 4)
    Zb = xp.concat([xp.zeros((B, 1, 4)), Zb], 1)
    return Zb[xp.expand(xp.arange(B)[:, None], (B, Q)), slot[:, h:]][..., :2]


def _internal_force(state: torch.Tensor, ei: torch.Tensor) -> torch.Tensor:
    """n = EI m with m_x + i m_y = i U' = -i W and m_z = -|U|^2/2; state (B, Q, 4) = (U, W)."""
    ux, uy, wx, wy = state.unbind(-1)
    m = torch.stack((wy, -wx, -0.5 * (ux * ux + uy * uy)), dim=-1)
    return m * ei.unsqueeze(-1)


def integrate_curvature_nodes(
    query: torch.Tensor,
    loads: PointForces,
    length: float,
    bending_stiffness: float | torch.Tensor,
    nodes: int,
    *,
    return_force: bool = False,
    method: str | None = None,
    adjoint: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The paper's scheme: forces spread onto ``nodes`` uniform nodes (hat weights), one step per interval.

    Same arguments and returns as :func:`integrate_curvature`; ``nodes`` is the paper's q (>= 2); ``method``
    defaults to "rkn4".
    """
    tab = _method(method, "nodes")
    s, f = _valid_loads(loads)
    loads = PointForces(s, f)
    B = s.shape[0]
    dtype, device = s.dtype, s.device
    ei = _as_stiffness(bending_stiffness, s)
    grid = torch.linspace(0.0, float(length), nodes, dtype=dtype, device=device)
    w_nodes = spread_to_nodes(loads, grid)  # (B, q, 2) [N/m]
    # Events: the nodes and the queries, shared by the whole batch; the load is linear between events.
    pos = torch.cat((query, grid))
    pos_sorted, order = pos.sort(descending=True, stable=True)
    # Linear interpolation of the nodal load at the events (between nodes j and j + 1).
    d = float(length) / (nodes - 1)
    j = (pos_sorted / d).floor().clamp(0, nodes - 2).to(torch.int64)
    frac = ((pos_sorted - grid[j]) / d).clamp(0.0, 1.0).unsqueeze(-1)  # (E, 1)
    w_events = torch.lerp(w_nodes[:, j], w_nodes[:, j + 1], frac)  # (B, E, 2) [N/m]
    # U_tt = U'' = g(U) + phi, phi = (-w_y, w_x) / EI as a real pair; in stage units (|U|^2 U) P = -2 phi.
    P = torch.stack((2.0 * w_events[..., 1], -2.0 * w_events[..., 0]), dim=-1) / ei.unsqueeze(-1)
    # Step e runs from event e-1 to event e; the first event is the node at s = L (a zero-length step), so the
    # boundary values are P at the tip, then P at each event.
    start = torch.cat((pos_sorted.new_tensor([float(length)]), pos_sorted[:-1]))
    hstep = (start - pos_sorted).clamp(min=0.0).expand(B, -1)
    Z = march(hstep, tab, forcing=torch.cat((P[:, :1], P), dim=1), adjoint=adjoint)
    inverse = order.argsort()[: query.shape[0]]
    at_query = Z[:, inverse]
    curvature = at_query[..., :2]
    force = _internal_force(at_query, ei) if return_force else None
    return curvature, force


# ================================================================================================= public API
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


def _check_options(bending_stiffness, steps, max_step_angle, method, scheme) -> None:
    if bending_stiffness is not None:
        ei = torch.as_tensor(bending_stiffness).detach()
        if not bool(torch.isfinite(ei).all()) or bool((ei <= 0).any()):
            raise ValueError(f"bending_stiffness must be finite and > 0 N m^2, got {ei.tolist()}")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    if not max_step_angle > 0 or max_step_angle == float("inf"):
        raise ValueError(f"max_step_angle must be finite and > 0, got {max_step_angle!r}")
    _method(method, scheme)


def grating_curvature(
    rod: Rod,
    loads: PointForces,
    *,
    scheme: Scheme = "exact",
    nodes: int = 250,
    bending_stiffness: float | torch.Tensor | None = None,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    method: str | None = None,
    adjoint: bool = True,
) -> torch.Tensor:
    """(B, G, 2) curvature at the rod's gratings [1/m] (the measurement model). Unchecked, for hot loops.

    Arguments as :func:`simulate`.
    """
    query = rod.grating_positions(loads.dtype, loads.device)
    ei = rod.bending_stiffness if bending_stiffness is None else bending_stiffness
    if rod.precurved:
        if method is not None:
            raise ValueError("a precurved rod is simulated by torchrod.model.precurved's RK4: no method")
        return _precurved(rod, loads, query, scheme, nodes, ei)[0][..., :2]
    if scheme == "exact":
        return integrate_curvature(
            query, loads, rod.length, ei, max_step_angle=max_step_angle, method=method, adjoint=adjoint
        )[0]
    return integrate_curvature_nodes(query, loads, rod.length, ei, nodes, method=method, adjoint=adjoint)[0]


def _precurved(
    rod: Rod, loads: PointForces, query: torch.Tensor, scheme: Scheme, nodes: int, ei: Any
) -> tuple[torch.Tensor, torch.Tensor]:
    """u (B, Q, 3) and n (B, Q, 3) of a precurved rod at ``query`` by :mod:`.precurved`'s RK4 march; with the
    paper's node scheme the forces are first spread onto ``nodes`` uniform nodes, a distributed load linear between
    them."""
    from .precurved import simulate_torch

    if scheme == "exact":
        return simulate_torch(rod, loads, query, bending_stiffness=ei)
    grid = torch.linspace(0.0, rod.length, nodes, dtype=loads.dtype, device=loads.device)
    none = PointForces(loads.s[:, :0], loads.f[:, :0])
    return simulate_torch(rod, none, query, bending_stiffness=ei, load=spread_to_nodes(loads, grid))


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
    method: str | None = None,
    adjoint: bool = True,
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
        max_step_angle: accuracy knob of the exact scheme (bound on (local rate) x (step) per step).
        steps: fixed steps per segment for the exact scheme (overrides ``max_step_angle``), for convergence studies.
        method: Runge-Kutta-Nystrom method, "rkn8", "rkn6" or "rkn4" (default "rkn8" for the exact scheme, "rkn4"
            for the node scheme).
        adjoint: gradients from the hand-written discrete adjoint (default, fast); ``False`` records every torch
            operation instead (for ``torch.func`` transforms and higher derivatives).
    Returns:
        :class:`Simulation`; dtype and device follow ``loads``.

    A precurved rod (``rod.intrinsic_curvature``) is simulated by :func:`torchrod.model.precurved.march` (RK4,
    autograd; ``scheme`` and ``nodes`` apply, ``steps``, ``method``, ``max_step_angle`` and ``adjoint`` are the
    straight rod's); its curvature is the total body-frame curvature u, which a fibre that is straight when
    unstrained reads.
    """
    _check_loads(rod, loads)
    if scheme not in ("exact", "nodes"):
        raise ValueError(f"scheme must be 'exact' or 'nodes', got {scheme!r}")
    if scheme == "nodes" and (not isinstance(nodes, int) or nodes < 2):
        raise ValueError(f"nodes must be an integer >= 2, got {nodes!r}")
    if samples < 0:
        raise ValueError(f"samples must be >= 0, got {samples}")
    _check_options(bending_stiffness, steps, max_step_angle, method, scheme)
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
    if rod.precurved:
        # Intrinsic curvature: the general march (:mod:`.precurved`); the straight rod keeps the fast path below.
        if steps is not None or method is not None:
            raise ValueError(
                "a precurved rod (intrinsic_curvature) is simulated by the RK4 march of torchrod.model.precurved: "
                f"steps and method must be unset, got steps={steps!r}, method={method!r}"
            )
        curv, force = _precurved(rod, loads, query, scheme, nodes, ei)
    elif scheme == "exact":
        curv, force = integrate_curvature(
            query,
            loads,
            rod.length,
            ei,
            max_step_angle=max_step_angle,
            steps=steps,
            return_force=True,
            method=method,
            adjoint=adjoint,
        )
    else:
        curv, force = integrate_curvature_nodes(
            query, loads, rod.length, ei, nodes, return_force=True, method=method, adjoint=adjoint
        )
    G = grat.shape[0]
    extra = query[G:]
    if extra.numel():
        srt, idx = extra.sort()
        profile_s, profile_u, profile_n = srt, curv[:, G:][:, idx], force[:, G:][:, idx]
    else:
        profile_s, profile_u, profile_n = grat, curv[:, :G], force[:, :G]
    twist = profile_u[..., 2] if profile_u.shape[-1] == 3 else None
    return Simulation(
        grating_curvature=curv[:, :G, :2],
        s=profile_s,
        curvature=profile_u[..., :2],
        internal_force=profile_n,
        twist=twist,
    )
