"""Point forces on the rod: batched locations and body-frame components, with padding for ragged counts.

A batch of B load cases holds up to h forces each. Locations ``s`` are (B, h) [m] measured from the clamped base;
components ``f`` are (B, h, 2) [N], the body-frame (f_x, f_y) at s_i, perpendicular to the rod (a frictionless
contact: no axial component, no moment). Load cases with fewer than h forces are padded: ``mask`` (B, h) is True for
real forces and False for padding; padded forces carry no load whatever their ``s`` and ``f`` hold.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch

from .errors import OptionsError, TorchrodTypeError

__all__ = ["PointForces", "spread_to_nodes"]


@dataclass(frozen=True)
class PointForces:
    """A batch of point-force sets.

    Attributes:
        s: (B, h) locations [m] from the base.
        f: (B, h, 2) body-frame components (f_x, f_y) [N].
        mask: (B, h) bool, True for a real force; ``None`` means all are real.
    """

    s: torch.Tensor
    f: torch.Tensor
    mask: torch.Tensor | None = None

    def __post_init__(self) -> None:
        s, f, mask = self.s, self.f, self.mask
        if not isinstance(s, torch.Tensor) or not isinstance(f, torch.Tensor):
            raise TorchrodTypeError(f"s and f must be tensors, got {type(s).__name__} and {type(f).__name__}")
        if s.dim() != 2:
            raise OptionsError(f"s must have shape (B, h), got {tuple(s.shape)}")
        if f.dim() != 3 or f.shape[:2] != s.shape or f.shape[2] != 2:
            raise OptionsError(f"f must have shape (B, h, 2) = {(*s.shape, 2)}, got {tuple(f.shape)}")
        if not s.is_floating_point() or not f.is_floating_point():
            raise TorchrodTypeError(f"s and f must be floating point, got {s.dtype} and {f.dtype}")
        if s.dtype != f.dtype:
            raise TorchrodTypeError(f"s and f must share a dtype, got {s.dtype} and {f.dtype}")
        if s.device != f.device:
            raise OptionsError(f"s and f must be on one device, got {s.device} and {f.device}")
        if mask is not None:
            if not isinstance(mask, torch.Tensor) or mask.shape != s.shape:
                shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
                raise OptionsError(f"mask must have shape (B, h) = {tuple(s.shape)}, got {shape}")
            if mask.device != s.device:
                raise OptionsError(f"mask must be on the device of s ({s.device}), got {mask.device}")
            object.__setattr__(self, "mask", mask.to(torch.bool))

    # ------------------------------------------------------------------ views
    @property
    def batch_size(self) -> int:
        return self.s.shape[0]

    @property
    def max_forces(self) -> int:
        return self.s.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.s.dtype

    @property
    def device(self) -> torch.device:
        return self.s.device

    @property
    def active(self) -> torch.Tensor:
        """(B, h) bool: True for real forces."""
        if self.mask is None:
            return torch.ones(self.s.shape, dtype=torch.bool, device=self.s.device)
        return self.mask

    @property
    def count(self) -> torch.Tensor:
        """(B,) number of real forces per load case."""
        return self.active.sum(dim=1)

    def masked_f(self) -> torch.Tensor:
        """(B, h, 2) [N] with padded forces zeroed (autograd-safe: no in-place writes)."""
        if self.mask is None:
            return self.f
        return self.f * self.mask.unsqueeze(-1).to(self.f.dtype)

    def magnitude(self) -> torch.Tensor:
        """(B, h) [N] force magnitudes (zero for padding)."""
        return torch.linalg.vector_norm(self.masked_f(), dim=-1)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> PointForces:
        mask = None if self.mask is None else self.mask.to(device=device)
        return PointForces(self.s.to(dtype=dtype, device=device), self.f.to(dtype=dtype, device=device), mask)

    def __getitem__(self, index) -> PointForces:
        """Select load cases along the batch dimension (an int keeps a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        mask = None if self.mask is None else self.mask[index]
        return PointForces(self.s[index], self.f[index], mask)

    def sorted(self) -> PointForces:
        """The same forces ordered by location, padding last."""
        key = self.s.masked_fill(~self.active, float("inf"))
        order = key.argsort(dim=1)
        s = self.s.gather(1, order)
        f = self.f.gather(1, order.unsqueeze(-1).expand(-1, -1, 2))
        mask = None if self.mask is None else self.mask.gather(1, order)
        return PointForces(s, f, mask)

    def to_lists(self) -> list[list[tuple[float, float, float]]]:
        """Per load case, the real forces as (s [m], f_x [N], f_y [N]) tuples, in stored order."""
        s = self.s.detach().cpu().tolist()
        f = self.f.detach().cpu().tolist()
        m = self.active.cpu().tolist()
        return [
            [(si, fi[0], fi[1]) for si, fi, mi in zip(sr, fr, mr, strict=False) if mi]
            for sr, fr, mr in zip(s, f, m, strict=False)
        ]

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_lists(
        cls,
        cases: Sequence[Iterable[Sequence[float]]],
        *,
        max_forces: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> PointForces:
        """From per-case lists of (s [m], f_x [N], f_y [N]); pads to the largest count (or ``max_forces``)."""
        rows = [[tuple(float(v) for v in force) for force in case] for case in cases]
        for i, row in enumerate(rows):
            for force in row:
                if len(force) != 3:
                    raise OptionsError(f"case {i}: a force is (s, fx, fy), got {force}")
        h = max((len(r) for r in rows), default=0)
        if max_forces is not None:
            if h > max_forces:
                raise OptionsError(f"a case holds {h} forces, more than max_forces={max_forces}")
            h = max_forces
        h = max(h, 1)
        B = len(rows)
        s = torch.zeros(B, h, dtype=dtype)
        f = torch.zeros(B, h, 2, dtype=dtype)
        mask = torch.zeros(B, h, dtype=torch.bool)
        for i, row in enumerate(rows):
            for j, (si, fx, fy) in enumerate(row):
                s[i, j], f[i, j, 0], f[i, j, 1], mask[i, j] = si, fx, fy, True
        return cls(s.to(device), f.to(device), mask.to(device))


def spread_to_nodes(loads: PointForces, nodes: torch.Tensor) -> torch.Tensor:
    """The paper's point-to-node spreading, with its erratum fixed (docs/physics.md, erratum 3).

    A force f at s between nodes loc_{j-1} and loc_j (spacing d) becomes distributed loads f (loc_j - s) / d^2 at
    node j-1 and f (s - loc_{j-1}) / d^2 at node j: a hat function, the nearer node gets more. Interpolated
    linearly between nodes, the distributed load carries exactly the force f and the moment f s.

    Args:
        loads: B point-force sets.
        nodes: (q,) uniformly spaced node positions [m].
    Returns:
        (B, q, 2) distributed load at the nodes [N/m].
    """
    if nodes.dim() != 1 or nodes.numel() < 2:
        raise OptionsError(f"nodes must have shape (q,) with q >= 2, got {tuple(nodes.shape)}")
    d = nodes[1] - nodes[0]
    hat = torch.clamp(1.0 - (loads.s.unsqueeze(-1) - nodes).abs() / d, min=0.0)  # (B, h, q)
    return torch.einsum("bhq,bhc->bqc", hat, loads.masked_f()) / d
