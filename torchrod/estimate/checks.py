"""The checks of a batch of readings handed to the estimator or the network as tensors.

Readings parsed from text are checked where they are read (:mod:`torchrod.io.reading`); a tensor given to
:meth:`torchrod.Estimator.estimate` is checked here, with the same bounds, so the estimator never imports the
parsers.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..errors import ReadingError, TorchrodTypeError
from ..values import MAX_CURVATURE

__all__ = ["MAX_CURVATURE", "check_readings", "host_view"]


def host_view(x: torch.Tensor) -> Any:
    """A CPU tensor as a NumPy array sharing its memory (without its gradient), for a few cheap operations that are
    written for both types: at a batch of one reading, NumPy's operations cost a fraction of torch's dispatch; a
    tensor elsewhere (a GPU's) or of a type NumPy lacks is returned as it is."""
    if x.device.type == "cpu" and x.dtype in _NUMPY_TYPES:
        return x.detach().numpy()
    return x


_NUMPY_TYPES = (torch.float64, torch.float32, torch.bool)


def check_readings(curvature: Any, mask: Any, num_gratings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a batch of readings and return ``(curvature, mask)`` (the estimator's and the network's check).

    Args:
        curvature: (B, G, 2) floating-point tensor [1/m].
        mask: (B, G) bool tensor on curvature's device, True where the grating was read; or None: a grating is
            missing where both its components are NaN.
        num_gratings: G, the rod's grating count.
    Returns:
        ``curvature`` unchanged and the mask.
    Raises:
        TorchrodTypeError: curvature is not a floating-point tensor, or mask is not bool.
        ReadingError: a wrong shape (naming it), a mask on another device, or a present grating whose value is not
            finite or exceeds :data:`MAX_CURVATURE` (without a mask: also a row with one NaN component, or an
            infinity), naming the first such entry.
    """
    if not isinstance(curvature, torch.Tensor):
        kind = f"{type(curvature).__module__}.{type(curvature).__qualname__}".removeprefix("builtins.")
        raise TorchrodTypeError(f"curvature is not a torch tensor (got a {kind}): use torch.as_tensor(curvature)")
    if not curvature.is_floating_point():
        raise TorchrodTypeError(f"curvature must be a floating-point tensor, got dtype {curvature.dtype}")
    G = num_gratings
    if curvature.dim() != 3 or curvature.shape[1:] != (G, 2):
        raise ReadingError(f"curvature must have shape (B, {G}, 2) for this rod, got {tuple(curvature.shape)}")
    B = curvature.shape[0]
    if mask is None:
        values = host_view(curvature)  # (NumPy's operations where it can: cheaper than torch's on a few readings)
        nan = values != values
        present = ~nan.all(-1)
        # One device sync: half-NaN rows, and present values that are infinite or beyond the bound.
        bad = (nan.any(-1) & present) | (present & ~(abs(values) <= MAX_CURVATURE).all(-1))
        mask = torch.from_numpy(present) if isinstance(present, np.ndarray) else present
        if bool(bad.any()):
            b, g = (int(x) for x in torch.as_tensor(bad).nonzero()[0])
            pair = [float(x) for x in curvature[b, g]]
            if any(math.isnan(x) for x in pair):
                raise ReadingError(
                    f"curvature[{b}, {g}] = {pair} has one NaN component: a missing grating is a row of NaN "
                    "(or give a mask)"
                )
            raise ReadingError(_present_problem(b, g, pair))
        return curvature, mask
    if not isinstance(mask, torch.Tensor) or mask.shape != (B, G):
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ReadingError(f"mask must have shape (B, G) = {(B, G)}, got {shape}")
    if mask.dtype != torch.bool:
        raise TorchrodTypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.device != curvature.device:
        raise ReadingError(f"mask is on {mask.device} but curvature is on {curvature.device}")
    values, present = host_view(curvature), host_view(mask)
    if bool((present & ~(abs(values) <= MAX_CURVATURE).all(-1)).any()):
        bad = mask & ~(curvature.abs() <= MAX_CURVATURE).all(-1)
        b, g = (int(x) for x in bad.nonzero()[0])
        raise ReadingError(
            _present_problem(b, g, [float(x) for x in curvature[b, g]], " but the mask marks it present")
        )
    return curvature, mask


def _present_problem(b: int, g: int, pair: list[float], masked: str = "") -> str:
    if not all(math.isfinite(x) for x in pair):
        return f"curvature[{b}, {g}] is not finite ({_pair(pair)}){masked}"
    return (
        f"curvature[{b}, {g}] = {_pair(pair)} 1/m exceeds the bound of {MAX_CURVATURE:g} 1/m that any reading must "
        "respect (check the units and scaling)"
    )


def _pair(pair: list[float]) -> str:
    """A curvature pair as JSON spells it (NaN, Infinity)."""
    words = {math.inf: "Infinity", -math.inf: "-Infinity"}
    return "[" + ", ".join("NaN" if math.isnan(x) else words.get(x, repr(x)) for x in pair) + "]"
