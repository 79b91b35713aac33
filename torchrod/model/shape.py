"""The rod's shape: centreline and frames from a sampled curvature profile (torch, batched, differentiable).

The kinematics of an inextensible, unshearable rod (docs/physics.md): R' = R u^, P' = R e3, clamped base P(0) = 0,
R(0) = I (tangent +z). Given the body-frame curvature u at samples s_0 = 0 < s_1 < ... < s_{S-1}, each interval
[s_k, s_{k+1}] (length h_k) is crossed with the exponential midpoint rule (second-order Magnus): the curvature is
taken constant at its mean a_k = (u_k + u_{k+1}) / 2 over the interval, and the arc it describes is followed
exactly,

    R_{k+1} = R_k exp(h_k a_k^)                              (Rodrigues' formula)
    P_{k+1} = P_k + h_k R_k V(h_k a_k) e3,   V(phi) = I + (1 - cos t)/t^2 phi^ + (t - sin t)/t^3 phi^2, t = |phi|

(V integrates exp(s a^) over the interval). The scheme is exact for piecewise-constant curvature (circular arcs),
second order in the sample spacing for smooth profiles (also with the kinks point forces put in u: one interval
holds the kink), keeps the frames orthonormal to rounding, and has even series for small angles (smooth, safe
gradients at zero curvature). The frames are accumulated by a parallel prefix product (log2 S batched matmuls).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import OptionsError, TorchrodTypeError
from ..loads import PointForces
from ..rod import Rod
from .body_frame import simulate

__all__ = ["Shape", "bending_angle", "rod_shape", "shape"]


@dataclass(frozen=True)
class Shape:
    """A batch of rod shapes.

    Attributes:
        s: (S,) arc-length positions [m], from the base (s = 0), non-decreasing.
        position: (B, S, 3) centreline P(s) in the base frame [m] (base at the origin, initial tangent +z).
        frames: (B, S, 3, 3) rotation R(s); its columns are the body axes, column 2 the tangent.
    """

    s: torch.Tensor
    position: torch.Tensor
    frames: torch.Tensor

    @property
    def tangent(self) -> torch.Tensor:
        """(B, S, 3) unit tangent R e3."""
        return self.frames[..., :, 2]

    @property
    def tip(self) -> torch.Tensor:
        """(B, 3) position of the last sample [m] (the tip when ``s`` ends at L)."""
        return self.position[:, -1]


def _hat(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) with hat(v) w = v x w."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), dim=-2)


def _arc_coefficients(t2: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """sin t / t, (1 - cos t)/t^2, (t - sin t)/t^3 as functions of t^2 (Taylor series below t = 1e-2)."""
    small = t2 < 1e-4
    safe = torch.where(small, torch.ones_like(t2), t2)
    t = safe.sqrt()
    sin, cos = torch.sin(t), torch.cos(t)
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, sin / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - cos) / safe)
    c = torch.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - sin) / (safe * t))
    return a, b, c


def _prefix_product(m: torch.Tensor) -> torch.Tensor:
    """Inclusive prefix products m_0, m_0 m_1, m_0 m_1 m_2, ... along dim 1 of (B, K, 3, 3) (Hillis-Steele scan)."""
    k = m.shape[1]
    shift = 1
    while shift < k:
        m = torch.cat((m[:, :shift], m[:, :-shift] @ m[:, shift:]), dim=1)
        shift *= 2
    return m


def rod_shape(s: torch.Tensor, curvature: torch.Tensor) -> Shape:
    """Centreline and frames from a sampled curvature profile (exponential midpoint rule, second order).

    Args:
        s: (S,) positions [m], non-decreasing, starting at the clamped base s_0 = 0; S >= 1.
        curvature: (B, S, 2) body-frame curvature (u_x, u_y) at ``s`` [1/m] (or (B, S, 3) with the twist u_z).
    Returns:
        :class:`Shape` with positions (B, S, 3) [m] and frames (B, S, 3, 3); dtype and device follow
        ``curvature``; differentiable in ``curvature`` and ``s``.
    """
    if not isinstance(s, torch.Tensor) or not isinstance(curvature, torch.Tensor):
        raise TorchrodTypeError(
            f"s and curvature must be tensors, got {type(s).__name__} and {type(curvature).__name__}"
        )
    if s.dim() != 1 or s.numel() < 1:
        raise OptionsError(f"s must have shape (S,) with S >= 1, got {tuple(s.shape)}")
    S = s.shape[0]
    if curvature.dim() != 3 or curvature.shape[1] != S or curvature.shape[2] not in (2, 3):
        raise OptionsError(
            f"curvature must have shape (B, S, 2) = (B, {S}, 2) (or (B, S, 3)), got {tuple(curvature.shape)}"
        )
    if not curvature.is_floating_point():
        raise TorchrodTypeError(f"curvature must be floating point, got {curvature.dtype}")
    if s.device != curvature.device:
        raise OptionsError(f"s and curvature must be on one device, got {s.device} and {curvature.device}")
    s = s.to(curvature.dtype)
    sd = s.detach()
    if float(sd[0]) != 0.0:
        raise OptionsError(f"s must start at the clamped base s = 0, got s[0] = {float(sd[0])}")
    if S > 1 and bool((sd[1:] < sd[:-1]).any()):
        raise OptionsError("s must be non-decreasing")
    B = curvature.shape[0]
    u = curvature
    if u.shape[2] == 2:
        u = torch.cat((u, u.new_zeros(B, S, 1)), dim=-1)
    eye = torch.eye(3, dtype=u.dtype, device=u.device)
    if S == 1:
        return Shape(s=s, position=u.new_zeros(B, 1, 3), frames=eye.expand(B, 1, 3, 3).clone())
    h = (s[1:] - s[:-1]).unsqueeze(-1)  # (S-1, 1) [m]
    phi = 0.5 * (u[:, 1:] + u[:, :-1]) * h  # (B, S-1, 3) rotation vector of each interval [rad]
    t2 = (phi * phi).sum(-1)
    a, b, c = (x[..., None, None] for x in _arc_coefficients(t2))
    K = _hat(phi)
    K2 = K @ K
    step_rot = eye + a * K + b * K2  # exp(phi^), Rodrigues
    V = eye + b * K + c * K2  # (1/h) int_0^h exp(sigma a^) d sigma
    frames = torch.cat((eye.expand(B, 1, 3, 3), _prefix_product(step_rot)), dim=1)  # (B, S, 3, 3)
    chord = (frames[:, :-1] @ V[..., :, 2:3]).squeeze(-1) * h  # R_k V e3 h_k, (B, S-1, 3)
    position = torch.cat((u.new_zeros(B, 1, 3), chord.cumsum(dim=1)), dim=1)
    return Shape(s=s, position=position, frames=frames)


def shape(rod: Rod, loads: PointForces, samples: int = 200, **simulate_options) -> Shape:
    """The shape of a loaded rod: :func:`torchrod.simulate` sampled at ``samples`` uniform positions on [0, L],
    then :func:`rod_shape`.

    Args:
        rod: the rod.
        loads: B point-force sets (body-frame components).
        samples: number of uniform samples (>= 2); the error of the shape falls as samples^-2.
        simulate_options: passed to :func:`torchrod.simulate` (e.g. ``scheme``, ``bending_stiffness``).
    Returns:
        :class:`Shape` with S = ``samples`` (more if ``at=`` adds positions).
    """
    if not isinstance(samples, int) or samples < 2:
        raise OptionsError(f"samples must be an integer >= 2, got {samples!r}")
    if not rod.precurved:
        sim = simulate(rod, loads, samples=samples, **simulate_options)
        return rod_shape(sim.s, sim.curvature)
    # A precurved rod: with its twist, and u* jumps sampled on both sides (each breakpoint twice: proximal value,
    # then distal), so that the midpoint rule never averages across a jump.
    breaks = rod.breakpoints()
    extra = simulate_options.pop("at", None)
    at = torch.tensor(breaks, dtype=loads.dtype, device=loads.device)
    if extra is not None:
        at = torch.cat([at, torch.as_tensor(extra, dtype=loads.dtype, device=loads.device).reshape(-1)])
    sim = simulate(rod, loads, samples=samples, at=at, **simulate_options)
    s, u = sim.s, sim.full_curvature
    parts_s, parts_u, start = [], [], 0
    for b in breaks:
        (dx, dy), (px, py) = rod.intrinsic_at([b])[0], rod.intrinsic_at([b], side="proximal")[0]
        jump = torch.tensor([dx - px, dy - py, 0.0], dtype=u.dtype, device=u.device)
        k = int(torch.searchsorted(s.detach(), torch.tensor(b, dtype=s.dtype, device=s.device)))
        parts_s += [s[start:k], s[k : k + 1]]
        parts_u += [u[:, start:k], u[:, k : k + 1] - jump]
        start = k
    parts_s.append(s[start:])
    parts_u.append(u[:, start:])
    return rod_shape(torch.cat(parts_s), torch.cat(parts_u, 1))


def bending_angle(shape: Shape) -> torch.Tensor:
    """(B,) angle between the base and tip tangents [rad], in [0, pi] (atan2 of |t0 x t1| and t0 . t1)."""
    if not isinstance(shape, Shape):
        raise TorchrodTypeError(f"shape must be a Shape (torchrod.rod_shape), got {type(shape).__name__}")
    t0 = shape.frames[:, 0, :, 2]
    t1 = shape.frames[:, -1, :, 2]
    sin = torch.linalg.vector_norm(torch.linalg.cross(t0, t1, dim=-1), dim=-1)
    cos = (t0 * t1).sum(-1)
    return torch.atan2(sin, cos)
