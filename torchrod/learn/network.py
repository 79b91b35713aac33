"""The warm-start network itself: the torch module that guesses the contact forces from one FBG reading, for the
refinement to start from (:mod:`.warm_start` binds it to a rod for inference, :mod:`.checkpoint` stores it).

The network works in dimensionless form. With s~ = s / L, u~ = u L and f~ = f L^2 / EI the body-frame equations
(:mod:`torchrod.model.body_frame`) read U~'' = -|U~|^2 U~ / 2 with jumps f~ / 1 at the forces: the length and the
stiffness leave the problem. So one network serves every rod whose gratings sit at the same relative positions s_k / L,
whatever its length and stiffness; the checkpoint records that layout and :meth:`WarmStart.load` refuses a rod
whose layout differs (by more than ``LAYOUT_TOLERANCE``).

Input: the reading u~ (B, G, 2) and the grating mask (B, G) (False = missing grating; its values are ignored).
Output, for each possible count h = 1..H: the h forces, sorted by location by construction (the locations are the
cumulative sums of a softmax over h + 1 gaps, each at least ``MIN_GAP``, so 0 < s~_1 < ... < s~_h < 1), and logits for
the count.

The problem is symmetric under a rotation of the cross-section plane (an isotropic rod: rotating every force by an
angle rotates every curvature by it) and under a reflection (u_y -> -u_y is f_x -> -f_x). The network uses both:
it turns each reading to a canonical frame (its largest curvature along +x, the sum of u_y non-negative), predicts
there, and turns the forces back. That leaves the MLP one fundamental domain to learn.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, cast

import torch
from torch import nn

from ..errors import CheckpointError
from ..kernels import network as network_kernel
from ..loads import PointForces
from ..rod import Rod
from ..values import brief

__all__ = ["MIN_GAP", "NetConfig", "NetOutput", "WarmStartNet", "to_dimensionless", "unit_rod"]

# The network's rules, shared with its forward pass for inference (torchrod.kernels.network).
MIN_GAP = network_kernel.MIN_GAP
"""Least gap between guessed locations, and between them and the rod's ends, as a fraction of the length."""


@dataclass(frozen=True)
class NetConfig:
    """Shape and normalisation of a :class:`WarmStartNet`.

    Attributes:
        relative_gratings: the layout, s_k / L for the G gratings, increasing in (0, 1].
        max_forces: H, the largest number of forces the network proposes.
        hidden: width of the hidden layers.
        depth: number of hidden layers.
        curvature_scale: typical |u L| of the training readings (dimensionless); inputs are divided by it.
        force_scale: typical |f| L^2 / EI of the training forces (dimensionless); force outputs are multiples of it.
        intrinsic_curvature: a precurved rod's u*, dimensionless: segments ``(from / L, to / L, ux* L, uy* L)``
            (empty for a straight rod); torsion_ratio: its GJ / EI. Both are part of the layout a network serves.
    """

    relative_gratings: tuple[float, ...]
    max_forces: int = 3
    hidden: int = 192
    depth: int = 3
    curvature_scale: float = 5.0
    force_scale: float = 5.0
    intrinsic_curvature: tuple[tuple[float, float, float, float], ...] = ()
    torsion_ratio: float | None = None

    def __post_init__(self) -> None:
        raw = self.relative_gratings
        if isinstance(raw, (str, bytes, Mapping)) or not isinstance(raw, Iterable):
            raise CheckpointError(f"relative_gratings must be a list of numbers, got {brief(raw)}")  # noqa: TRY004
        raw = tuple(raw)
        if any(isinstance(x, bool) or not isinstance(x, numbers.Real) for x in raw):
            raise CheckpointError(f"relative_gratings must be a list of numbers, got {brief(list(raw))}")
        g = tuple(float(x) for x in raw)
        if not g or any(not (0.0 <= x <= 1.0) for x in g) or any(b <= a for a, b in itertools.pairwise(g)):
            raise CheckpointError(f"relative_gratings must increase inside [0, 1], got {brief(list(g))}")
        object.__setattr__(self, "relative_gratings", g)
        for name in ("max_forces", "hidden", "depth"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise CheckpointError(f"{name} must be a positive integer, got {brief(v)}")
        for name in ("curvature_scale", "force_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v <= 0.0:
                raise CheckpointError(f"{name} must be positive and finite, got {brief(v)}")
            object.__setattr__(self, name, float(v))
        # Checked by the rod they describe (the unit rod: lengths in units of L).
        unit = unit_rod(self)
        object.__setattr__(self, "intrinsic_curvature", unit.intrinsic_curvature)
        if self.torsion_ratio is not None:
            object.__setattr__(self, "torsion_ratio", unit.torsion_stiffness)

    @property
    def num_gratings(self) -> int:
        return len(self.relative_gratings)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["relative_gratings"] = list(self.relative_gratings)
        d["intrinsic_curvature"] = [list(x) for x in self.intrinsic_curvature]
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> NetConfig:
        """From :meth:`to_dict`'s form; ``ValueError`` naming an unknown or missing key or a bad value."""
        if not isinstance(data, Mapping):
            raise CheckpointError(f"a network config must be a mapping, got {type(data).__name__}")  # noqa: TRY004
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            raise CheckpointError(f"unknown network config keys {unknown}; known keys are {sorted(known)}")
        if "relative_gratings" not in data:
            raise CheckpointError("the network config lacks 'relative_gratings' (the grating layout)")
        return cls(**data)

    @classmethod
    def for_rod(cls, rod: Rod, **kwargs: Any) -> NetConfig:
        """A config with ``rod``'s layout (and, for a precurved rod, its dimensionless precurvature and GJ / EI)."""
        if rod.precurved:
            L = rod.length
            kwargs.setdefault(
                "intrinsic_curvature", tuple((a / L, b / L, ux * L, uy * L) for a, b, ux, uy in rod.intrinsic_curvature)
            )
            kwargs.setdefault("torsion_ratio", rod.torsion_stiffness / rod.bending_stiffness)
        return cls(relative_gratings=rod.relative_gratings, **kwargs)


class NetOutput(NamedTuple):
    """Raw, dimensionless network output (a tuple, so that DistributedDataParallel can see through it).

    Attributes:
        count_logits: (B, H) logits for 1..H forces.
        s: H tensors, ``s[h-1]`` (B, h): locations s / L, increasing along the last dimension.
        f: H tensors, ``f[h-1]`` (B, h, 2): body-frame components f L^2 / EI.
    """

    count_logits: torch.Tensor
    s: tuple[torch.Tensor, ...]
    f: tuple[torch.Tensor, ...]


def _head_sizes(max_forces: int) -> list[int]:
    # per count h: h + 1 gap logits and 2 h force components
    return [(h + 1) + 2 * h for h in range(1, max_forces + 1)]


class WarmStartNet(nn.Module):
    """Dimensionless reading -> count logits and, for each count, sorted dimensionless forces.

    ``forward(reading, mask)``: reading (B, G, 2) u L (dimensionless; values at missing gratings are ignored),
    mask (B, G) bool (True = grating read). Returns :class:`NetOutput`. Computes in float32 whatever the input
    dtype (the caller casts back; see :class:`WarmStart`).
    """

    stencil: torch.Tensor  # a buffer (register_buffer in __init__)

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        G, H, W = config.num_gratings, config.max_forces, config.hidden
        layers: list[nn.Module] = []
        width = 3 * G + 1 + (3 * (G - 2) if G >= 3 else 0)
        # Three-point second-derivative weights at the interior gratings (non-uniform spacing), dimensionless.
        g = torch.tensor(config.relative_gratings, dtype=torch.float64)
        if G >= 3:
            h1, h2 = g[1:-1] - g[:-2], g[2:] - g[1:-1]
            weights = torch.stack((2 / (h1 * (h1 + h2)), -2 / (h1 * h2), 2 / (h2 * (h1 + h2))), dim=1)
            spacing = float((g[-1] - g[0]) / (G - 1))
        else:
            weights, spacing = torch.zeros(0, 3, dtype=torch.float64), 1.0
        self.register_buffer("stencil", weights.float(), persistent=False)
        self._spacing2 = spacing * spacing
        for _ in range(config.depth):
            layers += [nn.Linear(width, W), nn.LayerNorm(W), nn.SiLU()]
            width = W
        self.body = nn.Sequential(*layers)
        # One output layer for every head: every parameter takes part in every loss (DDP needs no unused ones).
        self.out = nn.Linear(W, H + sum(_head_sizes(H)))

    def forward(self, reading: torch.Tensor, mask: torch.Tensor) -> NetOutput:
        cfg = self.config
        dtype = self.out.weight.dtype
        present = mask.to(torch.bool)
        x = torch.where(present.unsqueeze(-1), reading.to(dtype), torch.zeros((), dtype=dtype, device=reading.device))
        x = x.contiguous()  # viewed as complex below (any layout of the reading: a transposed one keeps its strides)
        turn, sign, zc = _canonical_frame(x, present)
        xc = torch.stack((zc.real, zc.imag * sign.unsqueeze(1)), dim=-1)
        # Shape and size apart: the reading divided by its RMS over the read gratings, and the log of that RMS.
        # In the small-deflection regime forces are linear in the reading, so forces are predicted relative to it.
        pf = present.to(dtype)
        rms = (
            ((xc.square().sum(-1) * pf).sum(1) / pf.sum(1).clamp(min=1.0))
            .sqrt()
            .clamp(min=network_kernel.RMS_FLOOR * cfg.curvature_scale)
        )
        parts = [(xc / rms.view(-1, 1, 1)).flatten(1), pf, torch.log(rms / cfg.curvature_scale).unsqueeze(1)]
        if cfg.num_gratings >= 3:
            parts += list(self._load_density(xc, pf, rms))
        features = torch.cat(parts, dim=1)  # (B, 3G + 1 + 3(G - 2))
        force_unit = (rms * (cfg.force_scale / cfg.curvature_scale)).view(-1, 1, 1)
        raw = self.out(self.body(features))
        H = cfg.max_forces
        count_logits, rest = raw[:, :H], raw[:, H:]
        s_out: list[torch.Tensor] = []
        f_out: list[torch.Tensor] = []
        start = 0
        back = turn.conj().resolve_conj().unsqueeze(1)  # the rotation back to the reading's frame
        for h, size in zip(range(1, H + 1), _head_sizes(H), strict=False):
            chunk = rest[:, start : start + size]
            start += size
            # Every gap at least MIN_GAP: locations strictly inside (0, 1) and strictly increasing, even in float32.
            gaps = MIN_GAP + (1.0 - (h + 1) * MIN_GAP) * torch.softmax(chunk[:, : h + 1], dim=1)
            s_out.append(torch.cumsum(gaps, dim=1)[:, :h])
            fc = chunk[:, h + 1 :].reshape(-1, h, 2) * force_unit
            # Undo the reflection (u_y -> -u_y is f_x -> -f_x), then the rotation (forces turn with the curvature).
            fc = torch.stack((fc[..., 0] * sign.unsqueeze(1), fc[..., 1]), dim=-1)
            f_out.append(torch.view_as_real(torch.view_as_complex(fc) * back))
        return NetOutput(count_logits, tuple(s_out), tuple(f_out))

    def _load_density(self, xc: torch.Tensor, pf: torch.Tensor, rms: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The distributed load the reading implies at the interior gratings, and where it is defined.

        Between forces U'' = -|U|^2 U / 2 (dimensionless form), so r = U'' + |U|^2 U / 2 vanishes away from the
        forces and peaks near each of them: counting forces becomes counting peaks. U'' is the three-point
        difference; r is defined where a grating and both neighbours are read. Returns r h^2 / rms (B, 2(G-2)),
        with h the mean grating spacing, and the validity (B, G-2).
        """
        w = self.stencil.to(xc.dtype)
        second = w[:, 0, None] * xc[:, :-2] + w[:, 1, None] * xc[:, 1:-1] + w[:, 2, None] * xc[:, 2:]
        mid = xc[:, 1:-1]
        r = second + 0.5 * mid.square().sum(-1, keepdim=True) * mid
        valid = pf[:, :-2] * pf[:, 1:-1] * pf[:, 2:]
        r = r * valid.unsqueeze(-1) * (self._spacing2 / rms.view(-1, 1, 1))
        return r.flatten(1), valid


def _canonical_frame(x: torch.Tensor, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The unit complex number turn (B,) whose product with the reading (as u_x + i u_y) takes its largest read
    curvature to +x, the reflection sign (B,) that then makes the sum of u_y over the read gratings non-negative,
    and that product (B, G) complex. No gradient flows through the frame."""
    z = torch.view_as_complex(x)  # (B, G)
    with torch.no_grad():
        mag = z.abs().masked_fill(~present, -1.0)
        ref = z.gather(1, mag.argmax(dim=1, keepdim=True)).squeeze(1)  # (B,)
        norm = ref.abs()
        turn = torch.where(norm > 0, ref.conj() / norm.clamp(min=torch.finfo(norm.dtype).tiny), torch.ones_like(ref))
    turned = z * turn.unsqueeze(1)
    with torch.no_grad():
        sign = torch.where(turned.imag.sum(dim=1) >= 0, 1.0, -1.0).to(x.dtype)
    return turn, sign, turned


# ---------------------------------------------------------------------------------------------------- dimensionless


def unit_rod(layout: NetConfig | Sequence[float]) -> Rod:
    """The dimensionless rod of a network's layout (a :class:`NetConfig`, or the relative grating positions of a
    straight rod): length 1, EI = 1, its gratings, precurvature and GJ / EI (for the physics loss)."""
    if not isinstance(layout, NetConfig):
        return Rod(length=1.0, bending_stiffness=1.0, gratings=tuple(layout))
    segments = cast(
        "tuple[tuple[float, float, float, float], ...]", tuple(tuple(x) for x in layout.intrinsic_curvature)
    )
    return Rod(
        length=1.0,
        bending_stiffness=1.0,
        gratings=layout.relative_gratings,
        intrinsic_curvature=segments,
        torsional_stiffness=layout.torsion_ratio,
    )


def to_dimensionless(rod: Rod, curvature: torch.Tensor | None = None, loads: PointForces | None = None):
    """(u L, PointForces(s / L, f L^2 / EI)) for whichever of ``curvature`` [1/m] and ``loads`` are given."""
    L, EI = rod.length, rod.bending_stiffness
    u = None if curvature is None else curvature * L
    p = None if loads is None else PointForces(loads.s / L, loads.f * (L * L / EI), loads.mask)
    return u, p
