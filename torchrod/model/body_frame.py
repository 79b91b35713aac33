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
their order at ties and the step counts come from the estimator's own schedule
(:func:`torchrod.kernels.march.schedule`, one definition for every march), with its rigorous rule on the local
rate: rate x step <= ``max_step_angle``. Every sample gets its own step counts; a batch runs max over samples of
(total steps) steps, shorter schedules padded with steps of length zero. The step counts are integers (no gradient
flows through them); the step lengths are differentiable in the locations.

:func:`simulate` also controls the error of the default scheme at any load. The rule bounds the error of one step,
but the errors of many steps add up: at loads far beyond a rod's working range (kilonewtons on the paper's tube, the
rod looping many times) the same step angle gives errors of 1e-5 relative and more. So each sample's rate bound is
integrated over the rod (its "turning", [rad]); up to :data:`TRUSTED_TURNING` the rule alone keeps the curvature
within :data:`ACCURACY` of its largest value (measured), and beyond, the sample is marched with smaller steps and
again with half those steps, their difference (Richardson) estimating the error of the finer one, which is returned.
A sample that cannot be shown within :data:`ACCURACY` in ``max_steps`` steps, or whose result is not finite, is
flagged: :attr:`Simulation.accurate` is False there. A precurved rod's march is checked the same way beyond
:data:`PRECURVED_TRUSTED_ANGLE`.

The march (:mod:`torchrod.model.nystrom`) runs inside one autograd node with a hand-written discrete adjoint (the exact
gradient of the discrete scheme, in O(steps) memory). ``adjoint=False`` instead records every torch operation for
autograd: slower, but it supports ``torch.func`` transforms and higher derivatives.

The paper's scheme (``scheme="nodes"``) spreads each force onto the two nearest of q uniform nodes (docs/physics.md,
erratum 3) and integrates the distributed load, interpolated linearly between nodes, one step per node interval
(classical 4th-order Runge-Kutta-Nystrom by default).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from ..errors import OptionsError, TorchrodError, TorchrodTypeError
from ..kernels.march import EXACT_MAX_STEPS, EXACT_STEP_ANGLE
from ..loads import PointForces, spread_to_nodes
from ..rod import Rod
from .nystrom import METHODS, Tableau, march

__all__ = [
    "ACCURACY",
    "DEFAULT_STEP_ANGLE",
    "MAX_STEPS",
    "METHODS",
    "PRECURVED_TRUSTED_ANGLE",
    "Simulation",
    "grating_curvature",
    "integrate_curvature",
    "integrate_curvature_nodes",
    "simulate",
    "step_counts",
    "TRUSTED_TURNING",
]

DEFAULT_STEP_ANGLE = EXACT_STEP_ANGLE
"""Default bound on (local rate) x (step) per step of the default method ("rkn8"), dimensionless: the estimator's
exact model's. Measured on large deflections (bending >= 90 degrees, 1-3 forces up to 2 N on the paper's tube):
gratings within 5e-8 of a converged reference relative to max |u|. On that tube the gratings (20 mm apart) already
make every segment short enough for one step, so the cost is one 8-stage step per event."""

DEFAULT_MAX_STEPS = EXACT_MAX_STEPS
"""Default cap on the steps of one segment between events (forces, gratings) of :func:`integrate_curvature` and
:func:`step_counts` (:func:`simulate` caps the steps of a whole sample instead: :data:`MAX_STEPS`)."""

ACCURACY = 1e-6
"""Error bound of :func:`simulate`'s default scheme on a straight rod, relative: the curvature [1/m] at every position
a sample returns is within ACCURACY times the largest |u| among them (float64; float32 adds its own rounding).
Samples that cannot be shown within it are flagged (:attr:`Simulation.accurate`)."""

TRUSTED_TURNING = 20.0
"""Turning [rad] (the schedule's rate bound integrated over the rod) up to which a sample marched by the step rule
(the default method, ``max_step_angle`` <= :data:`DEFAULT_STEP_ANGLE`) is taken to be within :data:`ACCURACY` without
a check. Measured on the paper's tube, 1-3 forces of 0.003-160 N anywhere (8000 cases against a march with steps
eight times shorter): at most 5.6e-7 relative up to 20 rad (7000 cases), 8e-7 between 30 and 60 rad."""

MAX_STEPS = 8192
"""Default most steps of one sample's march in :func:`simulate` (all its segments together), which bounds the time
and memory one sample can take. On the paper's tube it keeps a force of 1e5 N at the tip within :data:`ACCURACY`
(the rod loops some 230 times); a sample that would need more is flagged."""

_COARSE_ANGLE = 1.47
"""Step angle of a checked sample's coarser march at turning :data:`TRUSTED_TURNING`, scaled by (TRUSTED_TURNING /
turning)^(1/4) above it: the global error grows as turning^2 angle^8 (measured), so this aims the coarser march at
64 ACCURACY and the finer one, with half the steps, at a quarter of ACCURACY."""

PRECURVED_TRUSTED_ANGLE = 0.3
"""Bound on (rate) x (step) up to which a precurved rod's RK4 march (:mod:`.precurved`, steps of at most
:data:`torchrod.model.precurved.DEFAULT_MAX_STEP`) is taken to be within :data:`ACCURACY` without a check, the rate
bounding |u| over the rod: max |u*| + sum_i |f_i| s_i / min(EI, GJ), or sqrt(sum_i |f_i| / min(EI, GJ)) if larger.
Measured on the ``ctr250`` preset, 1-3 forces of 0.003-500 N anywhere (400 cases against steps four times shorter):
at most 1.2e-7 relative up to 0.3, 1.6e-6 up to 1. Beyond, :func:`simulate` checks the sample as it does a straight
rod's, halving the step."""

_PRECURVED_COARSE_ANGLE = 0.8  # (rate) x (step) of a checked precurved sample's coarser march, at first

_UNCAPPED = 1 << 40  # a per-segment cap the schedule never reaches in practice (the sample's total is capped instead)
_TURNING_ANGLE = 1e-4  # [rad] the step angle of the schedule that measures the turning (its rounding: this per force)

Scheme = Literal["exact", "nodes"]


@dataclass(frozen=True)
class Simulation:
    """The result of :func:`simulate`.

    Attributes:
        grating_curvature: (B, G, 2) curvature (u_x, u_y) at the rod's gratings [1/m].
        s: (S,) positions along the rod where the profiles below are sampled [m], increasing.
        curvature: (B, S, 2) curvature at ``s`` [1/m].
        internal_force: (B, S, 3) body-frame internal force n = R^T N at ``s`` [N] (proximal side of a force).
        accurate: (B,) bool, True where the sample's values are finite and within :data:`ACCURACY` of the rod
            model's solution (the exact scheme, straight or precurved). False where the steps could not keep that
            bound within ``max_steps``, where the values are not finite (NaN or infinite: loads far too large), or
            where it cannot be shown (fixed ``steps`` shorter than the rule's, or the turning beyond
            :data:`TRUSTED_TURNING`). The node scheme approximates the loads themselves: there it says only that the
            values are finite. The values are returned either way (a flagged sample's may be far off).
        twist: (B, S) the twist u_z at ``s`` [1/m] of a precurved rod (None for a straight rod, which never twists).
    """

    grating_curvature: torch.Tensor
    s: torch.Tensor
    curvature: torch.Tensor
    internal_force: torch.Tensor
    accurate: torch.Tensor
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
    raise OptionsError(
        f"bending_stiffness must be a scalar or have shape (B,) = ({like.shape[0]},), got {tuple(ei.shape)}"
    )


_DEFAULT_METHOD = {"exact": "rkn8", "nodes": "rkn4"}


def _method(name: str | None, scheme: str) -> Tableau:
    name = _DEFAULT_METHOD[scheme] if name is None else name
    if name not in METHODS:
        raise OptionsError(f"method must be one of {sorted(METHODS)}, got {name!r}")
    return METHODS[name]


def _valid_loads(loads: PointForces) -> tuple[torch.Tensor, torch.Tensor]:
    """(s, f) with padded forces at s = 0 carrying no load, whatever (even NaN) they hold. Autograd-safe."""
    if loads.mask is None:
        return loads.s, loads.f
    s = torch.where(loads.mask, loads.s, torch.zeros_like(loads.s))
    f = torch.where(loads.mask.unsqueeze(-1), loads.f, torch.zeros_like(loads.f))
    return s, f


def _schedule(
    query: torch.Tensor, s: torch.Tensor, f: torch.Tensor, ei: torch.Tensor, length: float, angle: float, cap: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The events of each sample, tip to base: the order (B, E) (indices < h forces, then the queries), their
    positions (B, E) [m] and segment lengths (B, E) [m] (differentiable in s), and the steps per segment (B, E)
    of the schedule's rigorous rule (:func:`torchrod.kernels.host.schedule_rows`; 0 distal to every force, where the
    state is zero)."""
    from ..kernels.host import schedule_rows

    B, h = s.shape
    Q = query.shape[0]
    with torch.no_grad():
        order_np, steps_np = schedule_rows(
            _values(query), _values(s), _values(f), _values(ei.expand(B, 1)[:, 0]), length, angle, cap
        )
    order = torch.from_numpy(order_np).to(s.device)
    pos = torch.cat((s, query.expand(B, Q)), dim=1).gather(1, order)
    start = torch.cat((pos.new_full((B, 1), float(length)), pos[:, :-1]), dim=1)
    seg = (start - pos).clamp(min=0.0)
    return order, pos, seg, torch.from_numpy(steps_np).to(s.device)


def _values(t: torch.Tensor) -> np.ndarray:
    """The numbers a tensor holds, as a NumPy array, also under torch.func's gradient transforms (which wrap it):
    the step schedule is chosen from the values, not differentiated."""
    t = t.detach()
    try:
        from torch._C import _DisableFuncTorch
        from torch._C._functorch import get_unwrapped, is_batchedtensor, is_functorch_wrapped_tensor
    except ImportError:  # an older torch: nothing wraps
        return t.cpu().numpy()
    if not is_functorch_wrapped_tensor(t):
        return t.cpu().numpy()
    with _DisableFuncTorch():
        while is_functorch_wrapped_tensor(t):
            if is_batchedtensor(t):
                raise TorchrodError(
                    "the forward model cannot run under torch.func.vmap: its step schedule depends on each "
                    "sample's loads; pass the samples as one batch instead (every function here is batched)"
                )
            t = get_unwrapped(t)
        return t.cpu().numpy()


def _sequence(order: torch.Tensor, seg: torch.Tensor, steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sample's steps one after the other: hstep (B, K) the step lengths [m] (zero past a sample's last step,
    K the largest sample's count), and slot (B, E), the steps taken when each force's and each query's event is
    reached, forces first, then the queries, in their input order."""
    B, E = steps.shape
    last = steps.cumsum(1)  # (B, E)
    K = int(last[:, -1].max()) if B else 0
    event = torch.searchsorted(last, torch.arange(K, device=steps.device).expand(B, K).contiguous(), right=True)
    length = torch.where(steps > 0, seg / steps.clamp(min=1), torch.zeros_like(seg))
    hstep = torch.cat((length, length.new_zeros(B, 1)), dim=1).gather(1, event)
    inverse = torch.empty_like(order).scatter_(1, order, torch.arange(E, device=order.device).expand(B, E))
    return hstep, last.gather(1, inverse)


def _jumps(f: torch.Tensor, ei: torch.Tensor) -> torch.Tensor:
    """(B, h, 2) the jump of W = dU/dt (t = L - s) at each force: W(s_i-) = W(s_i+) - (f_y - i f_x)/EI, as real
    pairs (-f_y, f_x)/EI."""
    return torch.stack((-f[..., 1], f[..., 0]), dim=-1) / ei.unsqueeze(-1)


def step_counts(
    rod: Rod,
    loads: PointForces,
    *,
    bending_stiffness: float | torch.Tensor | None = None,
    max_step_angle: float = DEFAULT_STEP_ANGLE,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> torch.Tensor:
    """(B, E) steps per segment that :func:`grating_curvature` takes with the exact scheme (a diagnostic), events in
    order from the tip (the rod's gratings and the forces, padding included), E = G + h; 0 for the events distal to
    every force. A batch runs max over samples of the row sums: every sample's own steps, then zero-length steps."""
    s, f = _valid_loads(loads)
    ei = _as_stiffness(rod.bending_stiffness if bending_stiffness is None else bending_stiffness, s)
    query = rod.grating_positions(s.dtype, s.device)
    return _schedule(query, s, f, ei, rod.length, max_step_angle, max_steps)[3]


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
    ei = _as_stiffness(bending_stiffness, s)
    order, _, seg, counts = _schedule(query, s, f, ei, length, max_step_angle, max_steps)
    if steps is not None:
        counts = torch.full_like(counts, int(steps))
    at_query = _march_events(tab, order, seg, counts, _jumps(f, ei), adjoint)
    curvature = at_query[..., :2]
    force = _internal_force(at_query, ei) if return_force else None
    return curvature, force


def _march_events(
    tab: Tableau, order: torch.Tensor, seg: torch.Tensor, counts: torch.Tensor, jumps: torch.Tensor, adjoint: bool
) -> torch.Tensor:
    """(b, Q, 4) the state (U, W) at the queries of b samples, from their events (:func:`_schedule`: order, seg
    (b, E)), the steps on each segment (b, E) and the slope jumps (b, h, 2) at their forces."""
    b, h = jumps.shape[:2]
    # Every sample runs K steps: its own step lengths, then zero-length steps once its events are done. slot: the
    # steps taken when each event is reached (forces, then queries, in input order).
    hstep, slot = _sequence(order, seg, counts)  # (b, K) [m], (b, E)
    K = hstep.shape[1]
    kick = jumps.new_zeros(b, K + 1, 2).scatter_add(1, slot[:, :h].unsqueeze(-1).expand(b, h, 2), jumps)[:, 1:]
    Z = march(hstep, tab, kick=kick, adjoint=adjoint)  # (b, K, 4)
    Z = torch.cat((Z.new_zeros(b, 1, 4), Z), dim=1)  # slot 0: the zero state before any step
    return Z.gather(1, slot[:, h:].unsqueeze(-1).expand(-1, -1, 4))  # (b, Q, 4)


def _controlled(
    query: torch.Tensor,
    loads: PointForces,
    length: float,
    bending_stiffness: float | torch.Tensor,
    *,
    max_step_angle: float,
    steps: int | None,
    max_steps: int,
    method: str | None,
    adjoint: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`integrate_curvature` with the error control of :func:`simulate` (module docstring): curvature
    (B, Q, 2) [1/m], internal force (B, Q, 3) [N] and ``accurate`` (B,) bool.

    A sample whose turning is at most :data:`TRUSTED_TURNING` (method "rkn8", ``max_step_angle`` at most the default)
    takes the rule's steps once. Any other takes ``c`` steps per segment, from the rule at the smaller of
    ``max_step_angle`` and the coarse angle for its turning, and ``2 c``; the finer result is returned, with the
    error estimate |fine - coarse| / (2^order - 1). While that exceeds :data:`ACCURACY` and the steps fit in
    ``max_steps``, the steps double again. Where even the first pair does not fit, ``c`` is scaled down to fit (the
    rule's bound then no longer holds, and the estimate decides). With ``steps`` every sample takes that many steps
    per segment, and it counts as accurate only where those are at least the default rule's and the turning is
    trusted. Each sample's steps are its own, so its result does not depend on the rest of the batch.
    """
    tab = _method(method, "exact")
    s, f = _valid_loads(loads)
    B = s.shape[0]
    ei = _as_stiffness(bending_stiffness, s)
    jumps = _jumps(f, ei)
    order, _, seg, counts = _schedule(query, s, f, ei, length, max_step_angle, _UNCAPPED)
    turning = _turning(s, f, ei, length)
    rule = _values(counts)
    device = counts.device

    def run(rows: np.ndarray, n: np.ndarray, grad: bool = True) -> torch.Tensor:
        idx = torch.from_numpy(rows).to(device)
        with contextlib.nullcontext() if grad else torch.no_grad():
            return _march_events(tab, order[idx], seg[idx], torch.from_numpy(n).to(device), jumps[idx], adjoint)

    def finite(Z: torch.Tensor) -> np.ndarray:
        return np.isfinite(_values(Z)).all(axis=(1, 2))

    if steps is not None:
        Z = run(np.arange(B), np.full_like(rule, int(steps)))
        if method in (None, "rkn8"):
            default = _values(_schedule(query, s, f, ei, length, DEFAULT_STEP_ANGLE, _UNCAPPED)[3])
            covered = (turning <= TRUSTED_TURNING) & (int(steps) >= default).all(axis=1)
        else:
            covered = np.zeros(B, dtype=bool)
        return Z[..., :2], _internal_force(Z, ei), torch.from_numpy(covered & finite(Z)).to(device)

    total = rule.sum(axis=1)
    trusted = (turning <= TRUSTED_TURNING) & (total <= max_steps)
    if tab is not METHODS["rkn8"] or max_step_angle > DEFAULT_STEP_ANGLE:
        trusted[:] = False
    parts: list[tuple[np.ndarray, torch.Tensor]] = []
    accurate = np.zeros(B, dtype=bool)
    easy = np.flatnonzero(trusted)
    if easy.size:
        Z = run(easy, rule[easy])
        accurate[easy] = finite(Z)
        parts.append((easy, Z))
    hard = np.flatnonzero(~trusted)
    if hard.size:
        Z, accurate[hard] = _checked(run, rule[hard], turning[hard], hard, max_step_angle, max_steps, tab.order)
        parts.append((hard, Z))
    if not parts:  # an empty batch
        Z = _march_events(tab, order, seg, counts, jumps, adjoint)
        return Z[..., :2], _internal_force(Z, ei), torch.from_numpy(accurate).to(device)
    rows = np.concatenate([r for r, _ in parts])
    inverse = torch.from_numpy(np.argsort(rows, kind="stable")).to(device)
    Z = torch.cat([z for _, z in parts])[inverse]
    return Z[..., :2], _internal_force(Z, ei), torch.from_numpy(accurate).to(device)


def _turning(s: torch.Tensor, f: torch.Tensor, ei: torch.Tensor, length: float) -> np.ndarray:
    """(B,) each sample's turning [rad]: the schedule's rate bound integrated over the rod between its forces (the
    bound at each segment's proximal end, where it is largest), so that it does not depend on the queries."""
    from ..kernels.host import schedule_rows

    base = np.zeros(1)
    stiffness = _values(ei.expand(s.shape[0], 1)[:, 0])
    steps = schedule_rows(base, _values(s), _values(f), stiffness, length, _TURNING_ANGLE, _UNCAPPED)[1]
    return _TURNING_ANGLE * steps.sum(axis=1)


def _checked(run, rule: np.ndarray, turning: np.ndarray, rows: np.ndarray, angle: float, max_steps: int, order: int):
    """The checked samples of :func:`_controlled`: (b, Q, 4) the finer march's state at the queries and (b,) bool,
    whether its error estimate is within :data:`ACCURACY` (False where a value is not finite). ``rule`` (b, E) the
    rule's steps at ``angle``, ``turning`` (b,) [rad], ``rows`` the samples' indices for ``run``."""
    relative = TRUSTED_TURNING / np.maximum(turning, TRUSTED_TURNING)  # (0, 1]: turning is finite
    coarse_angle = np.minimum(angle, _COARSE_ANGLE * relative**0.25)
    n = _scaled(rule, angle / coarse_angle, max_steps // 2)
    coarse = run(rows, n, grad=False)
    fine = run(rows, 2 * n)
    divisor = float(2**order - 1)
    ok = np.zeros(rows.size, dtype=bool)
    todo = np.arange(rows.size)
    while True:
        pick = torch.from_numpy(todo).to(fine.device)
        u_fine = _values(fine[pick, :, :2])
        estimate = np.abs(u_fine - _values(coarse[pick, :, :2])).max(axis=(1, 2), initial=0.0) / divisor
        scale = np.abs(u_fine).max(axis=(1, 2), initial=0.0)
        ok[todo] = (estimate <= ACCURACY * scale) & np.isfinite(u_fine).all(axis=(1, 2)) & np.isfinite(estimate)
        todo = todo[~ok[todo] & (4 * n[todo].sum(axis=1) <= max_steps)]
        if not todo.size:
            return fine, ok
        n[todo] *= 2
        pick = torch.from_numpy(todo).to(fine.device)
        coarse = coarse.index_copy(0, pick, fine[pick].detach())
        fine = fine.index_copy(0, pick, run(rows[todo], 2 * n[todo]))


def _scaled(rule: np.ndarray, factor: np.ndarray, limit: int) -> np.ndarray:
    """(b, E) ceil(rule x factor) steps, at least one where the rule takes any, with each row's factor lowered where
    needed so that the row's total stays within ``limit`` (or at one step per segment)."""
    active = rule > 0
    total = rule.sum(axis=1).astype(np.float64)
    room = np.maximum(limit - active.sum(axis=1), 0) / np.maximum(total, 1.0)
    factor = np.minimum(factor, room)[:, None]
    n = np.ceil(rule * factor)
    return np.where(active, np.maximum(n, 1.0), 0.0).astype(np.int64)


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
        raise TorchrodTypeError(f"loads must be PointForces, got {type(loads).__name__}")
    active = loads.active
    s = loads.s.detach()
    if not bool(torch.isfinite(s[active]).all()) or not bool(torch.isfinite(loads.f.detach()[active]).all()):
        raise OptionsError("load locations and components must be finite")
    bad = active & ((s < 0.0) | (s > rod.length))
    if bool(bad.any()):
        b, i = (int(x) for x in bad.nonzero()[0])
        raise OptionsError(f"force location s[{b}, {i}] = {float(s[b, i])} m lies outside [0, L = {rod.length}] m")


def _check_options(bending_stiffness, steps, max_step_angle, method, scheme) -> None:
    if bending_stiffness is not None:
        ei = torch.as_tensor(bending_stiffness).detach()
        if not bool(torch.isfinite(ei).all()) or bool((ei <= 0).any()):
            raise OptionsError(f"bending_stiffness must be finite and > 0 N m^2, got {ei.tolist()}")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise OptionsError(f"steps must be an integer >= 1, got {steps!r}")
    if not max_step_angle > 0 or max_step_angle == float("inf"):
        raise OptionsError(f"max_step_angle must be finite and > 0, got {max_step_angle!r}")
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
    """(B, G, 2) curvature at the rod's gratings [1/m] (the measurement model). Unchecked, for hot loops: the step
    rule alone, at most :data:`DEFAULT_MAX_STEPS` steps a segment, without :func:`simulate`'s error control and flag
    (which matter only for loads far beyond a rod's working range).

    Arguments as :func:`simulate`.
    """
    query = rod.grating_positions(loads.dtype, loads.device)
    ei = rod.bending_stiffness if bending_stiffness is None else bending_stiffness
    if rod.precurved:
        if method is not None:
            raise OptionsError("a precurved rod is simulated by torchrod.model.precurved's RK4: no method")
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


def _precurved_controlled(
    rod: Rod, loads: PointForces, query: torch.Tensor, ei: Any, max_steps: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """u (B, Q, 3), n (B, Q, 3) and ``accurate`` (B,) of a precurved rod (the exact scheme): :func:`_precurved` for
    the samples within :data:`PRECURVED_TRUSTED_ANGLE`; each other one marched with steps DEFAULT_MAX_STEP / 2^j and
    half those (RK4: error estimate |fine - coarse| / 15), j from its rate bound, j + 1 while the estimate exceeds
    :data:`ACCURACY` and the finer march fits in ``max_steps`` steps over the rod."""
    from .precurved import DEFAULT_MAX_STEP, Precurved, simulate_torch

    model = Precurved.of(rod)
    s, f = _valid_loads(loads)
    B = s.shape[0]
    device = s.device
    stiffness = _values(_as_stiffness(ei, s).expand(B, 1)[:, 0]) * min(1.0, model.torsion / model.bending)
    fv = _values(f)
    magnitude = np.hypot(fv[..., 0], fv[..., 1])  # (B, h) [N], zero where padded
    own = max((math.hypot(ux, uy) for _, _, ux, uy in model.segments), default=0.0)
    lever = own + (magnitude * _values(s)).sum(axis=1) / stiffness
    rate = np.maximum(lever, np.sqrt(magnitude.sum(axis=1) / stiffness))  # (B,) [1/m]
    per_row = isinstance(ei, torch.Tensor) and ei.numel() == B and B > 1

    def run(rows: np.ndarray, step: float, grad: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        idx = torch.from_numpy(rows).to(device)
        sub = PointForces(loads.s[idx], loads.f[idx], None if loads.mask is None else loads.mask[idx])
        stiff = ei.reshape(-1)[idx] if per_row else ei
        with contextlib.nullcontext() if grad else torch.no_grad():
            return simulate_torch(rod, sub, query, max_step=step, bending_stiffness=stiff)

    def finite(u: torch.Tensor, n: torch.Tensor) -> np.ndarray:
        return np.isfinite(_values(torch.cat((u, n), dim=-1))).all(axis=(1, 2))

    accurate = np.zeros(B, dtype=bool)
    parts: list[tuple[np.ndarray, torch.Tensor, torch.Tensor]] = []
    easy = np.flatnonzero(rate * DEFAULT_MAX_STEP <= PRECURVED_TRUSTED_ANGLE)
    if easy.size:
        u, n = run(easy, DEFAULT_MAX_STEP)
        accurate[easy] = finite(u, n)
        parts.append((easy, u, n))
    hard = np.flatnonzero(~(rate * DEFAULT_MAX_STEP <= PRECURVED_TRUSTED_ANGLE))
    if hard.size:
        top = max(0, math.floor(math.log2(DEFAULT_MAX_STEP * max_steps / (2.0 * rod.length))))
        with np.errstate(divide="ignore", invalid="ignore"):
            wanted = np.ceil(np.log2(rate[hard] * DEFAULT_MAX_STEP / _PRECURVED_COARSE_ANGLE))
        level = np.clip(np.nan_to_num(wanted, nan=top, posinf=top), 0, top).astype(np.int64)
        done: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        pending = np.arange(hard.size)
        while pending.size:
            again = []
            for j in np.unique(level[pending]):
                group = pending[level[pending] == j]
                step = DEFAULT_MAX_STEP / 2.0**j
                coarse = _values(run(hard[group], step, grad=False)[0])
                u, n = run(hard[group], step / 2.0)
                fine = _values(u)
                estimate = np.abs(fine - coarse).max(axis=(1, 2), initial=0.0) / 15.0
                scale = np.abs(fine).max(axis=(1, 2), initial=0.0)
                ok = (estimate <= ACCURACY * scale) & finite(u, n)
                for k, row in enumerate(group):
                    done[int(row)] = (u[k], n[k])
                    accurate[hard[row]] = ok[k]
                again.append(group[~ok & (level[group] < top)])
            pending = np.concatenate(again)
            level[pending] += 1
        parts.append(
            (
                hard,
                torch.stack([done[k][0] for k in range(hard.size)]),
                torch.stack([done[k][1] for k in range(hard.size)]),
            )
        )
    if not parts:  # an empty batch
        u, n = simulate_torch(rod, loads, query, bending_stiffness=ei)
        return u, n, torch.from_numpy(accurate).to(device)
    rows = np.concatenate([r for r, _, _ in parts])
    inverse = torch.from_numpy(np.argsort(rows, kind="stable")).to(device)
    u = torch.cat([p[1] for p in parts])[inverse]
    n = torch.cat([p[2] for p in parts])[inverse]
    return u, n, torch.from_numpy(accurate).to(device)


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
    max_steps: int = MAX_STEPS,
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
        max_step_angle: accuracy knob of the exact scheme (bound on (local rate) x (step) per step); a sample beyond
            :data:`TRUSTED_TURNING` takes smaller steps still, to keep its error within :data:`ACCURACY`.
        steps: fixed steps per segment for the exact scheme (overrides ``max_step_angle``), for convergence studies.
        max_steps: most steps of one sample's march in the exact scheme (all segments together; for a precurved rod,
            the step is at least L / max_steps); a sample that would need more to keep its error bound is marched
            with about this many and flagged.
        method: Runge-Kutta-Nystrom method, "rkn8", "rkn6" or "rkn4" (default "rkn8" for the exact scheme, "rkn4"
            for the node scheme).
        adjoint: gradients from the hand-written discrete adjoint (default, fast); ``False`` records every torch
            operation instead (for ``torch.func`` transforms and higher derivatives).
    Returns:
        :class:`Simulation`; dtype and device follow ``loads``. Its ``accurate`` (B,) flags the samples whose values
        are not finite or not shown within :data:`ACCURACY` (extreme loads): check it where loads may be large.

    A precurved rod (``rod.intrinsic_curvature``) is simulated by :func:`torchrod.model.precurved.march` (RK4,
    autograd; ``scheme``, ``nodes`` and ``max_steps`` apply, ``steps``, ``method``, ``max_step_angle`` and ``adjoint``
    are the straight rod's; large loads get shorter steps, checked, :data:`PRECURVED_TRUSTED_ANGLE`); its curvature
    is the total body-frame curvature u, which a fibre that is straight when unstrained reads.
    """
    _check_loads(rod, loads)
    if scheme not in ("exact", "nodes"):
        raise OptionsError(f"scheme must be 'exact' or 'nodes', got {scheme!r}")
    if scheme == "nodes" and (not isinstance(nodes, int) or nodes < 2):
        raise OptionsError(f"nodes must be an integer >= 2, got {nodes!r}")
    if samples < 0:
        raise OptionsError(f"samples must be >= 0, got {samples}")
    _check_options(bending_stiffness, steps, max_step_angle, method, scheme)
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise OptionsError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    dtype, device = loads.dtype, loads.device
    grat = rod.grating_positions(dtype, device)
    parts = [grat]
    if samples:
        parts.append(torch.linspace(0.0, rod.length, samples, dtype=dtype, device=device))
    if at is not None:
        at = torch.as_tensor(at, dtype=dtype, device=device).reshape(-1)
        if bool(((at < 0) | (at > rod.length) | ~torch.isfinite(at)).any()):
            raise OptionsError(f"sample positions must lie in [0, {rod.length}] m, got {at.tolist()}")
        parts.append(at)
    query = torch.cat(parts)
    ei = rod.bending_stiffness if bending_stiffness is None else bending_stiffness
    force: torch.Tensor | None  # (the integrators' second result: None only without return_force)
    if rod.precurved:
        # Intrinsic curvature: the general march (:mod:`.precurved`); the straight rod keeps the fast path below.
        if steps is not None or method is not None:
            raise OptionsError(
                "a precurved rod (intrinsic_curvature) is simulated by the RK4 march of torchrod.model.precurved: "
                f"steps and method must be unset, got steps={steps!r}, method={method!r}"
            )
        if scheme == "exact":
            curv, force, accurate = _precurved_controlled(rod, loads, query, ei, max_steps)
        else:
            curv, force = _precurved(rod, loads, query, scheme, nodes, ei)
    elif scheme == "exact":
        curv, force, accurate = _controlled(
            query,
            loads,
            rod.length,
            ei,
            max_step_angle=max_step_angle,
            steps=steps,
            max_steps=max_steps,
            method=method,
            adjoint=adjoint,
        )
    else:
        curv, force = integrate_curvature_nodes(
            query, loads, rod.length, ei, nodes, return_force=True, method=method, adjoint=adjoint
        )
    assert force is not None  # return_force=True
    if scheme != "exact":  # the node scheme: only whether the values are finite
        values = torch.cat((curv.flatten(1), force.flatten(1)), dim=1).detach()
        accurate = values.isfinite().all(dim=1)
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
        accurate=accurate,
        twist=twist,
    )
