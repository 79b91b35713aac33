"""FBG readings: the checks every consumer of curvature readings shares.

A batch of readings is ``curvature`` (B, G, 2) [1/m], the (u_x, u_y) measured at each of the rod's G gratings, and
``mask`` (B, G) bool, True where the grating has a reading. A missing grating is False in the mask (or NaN in the
curvature when no mask is given); its values are ignored, never read as zero.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["check_readings"]


def check_readings(curvature: Any, mask: Any, num_gratings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a batch of readings and return ``(curvature, mask)``.

    Args:
        curvature: (B, G, 2) floating-point tensor [1/m].
        mask: (B, G) bool tensor on curvature's device, or None: the gratings whose two components are finite.
        num_gratings: G, the rod's grating count.
    Raises:
        TypeError: curvature is not a floating-point tensor, or mask is not bool.
        ValueError: a wrong shape (naming it), a mask on another device, or a grating marked present whose value is
            not finite.
    """
    if not isinstance(curvature, torch.Tensor) or not curvature.is_floating_point():
        raise TypeError(
            f"curvature must be a floating-point tensor, got {getattr(curvature, 'dtype', type(curvature))!r}"
        )
    G = num_gratings
    if curvature.dim() != 3 or curvature.shape[1:] != (G, 2):
        raise ValueError(f"curvature must have shape (B, {G}, 2) for this rod, got {tuple(curvature.shape)}")
    B = curvature.shape[0]
    finite = torch.isfinite(curvature).all(-1)
    if mask is None:
        return curvature, finite
    if not isinstance(mask, torch.Tensor) or mask.shape != (B, G):
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"mask must have shape (B, G) = {(B, G)}, got {shape}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.device != curvature.device:
        raise ValueError(f"mask is on {mask.device} but curvature is on {curvature.device}")
    bad = mask & ~finite
    if bool(bad.any()):
        b, g = (int(x) for x in bad.nonzero()[0])
        raise ValueError(f"curvature[{b}, {g}] is not finite but the mask marks it present")
    return curvature, mask
