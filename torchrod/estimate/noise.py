"""The sensor's noise learned from the fits themselves: a running robust estimate for streams.

A reading whose noise is not given is tested with the F law against a sigma estimated from that reading alone
(:mod:`torchrod.kernels.counts`). This costs accuracy (the F law's quantiles are wider than the chi-square law's) and
time (a count is never settled early, so every count is fitted). A stream comes from one sensor, so its sigma can be
learned once from the stream and then used as a known noise.

The estimate: a correct fit of h forces to n residuals leaves ``loss ~ sigma^2 chi2(n - 3h)``
(:mod:`torchrod.kernels.counts`), so each fit gives ``loss / median(chi2(n - 3h))``, whose median over fits is sigma^2
(exactly when every fit has the same degrees of freedom, and to within a few percent when gratings are missing now and
then). The median ignores the fits that are not correct (a misfit, a force missed) as long as they are fewer than half.
Fits without degrees of freedom left, and unconverged ones, are not used. Only the most recent ``window`` fits count, so
a sensor whose noise drifts slowly is followed.

A rod with a calibration error (``Rod.calibration_error``) adds ``m_k^2 = (rel_k u_k)^2`` to each value's variance,
and a fit with the noise known weighs each residual by ``w_k = sigma_ref / sqrt(sigma_ref^2 + m_k^2)`` at the sigma
it was told. Such a fit's loss holds on average ``(n - 3h) / n`` of ``sum_k w_k^2 (sigma^2 + m_k^2)`` over its n
values, so ``loss / median(chi2(n - 3h))`` estimates ``sigma^2 mean(w^2) + mean(w^2 m^2)``, and each fit gives
``(loss / median(chi2) - mean(w^2 m^2)) / mean(w^2)`` (not below zero) as its sigma^2 (:func:`calibration_terms`,
:meth:`RunningNoise.add`). The equal share assumes each value takes an equal part of the fit's degrees of freedom;
a value the fit leans on more leaves less of its error in the loss, but at ``sigma_ref = sigma`` every weighed
residual has the same variance and the estimate is sigma^2 whatever the shares: the learned sigma is the sensor's
own at its fixed point. The fits made before a sigma is learned (the noise unknown, no weights) teach sigma^2 plus
the calibration's share, an overestimate, so the stream starts above the sensor's sigma and comes down to it (from
below, taking the share off fits that do not weigh it out, it would start near zero and flag every reading).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import OptionsError
from ..kernels.host import chi2_quantile

if TYPE_CHECKING:
    import torch

__all__ = ["NoiseLearning", "RunningNoise", "calibration_terms"]


def calibration_terms(
    variance: torch.Tensor, present: torch.Tensor, noise2: float | None
) -> tuple[list[float], list[float]]:
    """Per fit, ``mean(w^2)`` and ``mean(w^2 m^2)`` [1/m^2] over its present values (module docstring): the
    calibration's ``variance`` m^2 (B, G, 2) [1/m^2] of each value, the ``present`` (B, G) gratings, and the
    ``noise2`` (sigma_ref^2 [1/m^2]) the weights were made at, None for fits with the noise unknown (no weights)."""
    import torch

    w2 = torch.ones_like(variance) if noise2 is None else noise2 / (noise2 + variance)
    keep = present[..., None].to(variance.dtype)
    n = 2.0 * present.sum(1).to(variance.dtype).clamp(min=1)
    weight = (w2 * keep).sum((1, 2)) / n
    share = (w2 * variance * keep).sum((1, 2)) / n
    return weight.tolist(), share.tolist()


@dataclass(frozen=True)
class NoiseLearning:
    """How a stream learns its noise (module docstring).

    Attributes:
        after: fits used before the estimate is (until then every reading estimates its own noise).
        window: the most recent fits the estimate is made from.
        growth: while the estimate comes from fewer fits than a stream's batch holds, a batch holds at most
            ``growth`` times the fits it comes from (at least ``after``): a sigma from few fits answers few
            readings, and a backlog's batches grow to full size in a few steps (32, 128, 640, ... with the
            defaults).
    """

    after: int = 32
    window: int = 1000
    growth: int = 4

    def __post_init__(self) -> None:
        for name in ("after", "window", "growth"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise OptionsError(f"{name} must be an integer >= 1, got {v!r}")
        if self.window < self.after:
            raise OptionsError(f"window ({self.window}) must be at least after ({self.after})")


class RunningNoise:
    """The running estimate (module docstring): :meth:`add` the chosen fits, read :attr:`sigma`."""

    def __init__(self, learning: NoiseLearning = NoiseLearning()) -> None:
        self.learning = learning
        self._ratios: collections.deque[float] = collections.deque(maxlen=learning.window)
        self.used = 0  # fits added in all

    def add(
        self, loss: Iterable[float], dof: Iterable[int], calibration: tuple[list[float], list[float]] | None = None
    ) -> None:
        """Add fits: their losses [1/m^2] and degrees of freedom (residuals less 3 per force); fits with no
        degree of freedom or a non-finite loss are skipped. ``calibration``: with a rod's calibration error, per fit
        ``mean(w^2)`` and ``mean(w^2 m^2)`` (:func:`calibration_terms`; module docstring); None: none."""
        losses = [float(x) for x in loss]
        weight, share = calibration if calibration is not None else ([1.0] * len(losses), [0.0] * len(losses))
        for x, d, a, c in zip(losses, dof, weight, share, strict=True):
            d = int(d)
            if d <= 0 or not math.isfinite(x) or x < 0.0:
                continue
            self._ratios.append(max(x / chi2_quantile(0.5, d) - c, 0.0) / a)
            self.used += 1

    @property
    def count(self) -> int:
        """Fits the current estimate is made from."""
        return len(self._ratios)

    @property
    def sigma(self) -> float | None:
        """The estimate [1/m], or None before ``learning.after`` fits."""
        if len(self._ratios) < self.learning.after:
            return None
        ordered = sorted(self._ratios)
        n = len(ordered)
        mid = ordered[n // 2] if n % 2 else 0.5 * (ordered[n // 2 - 1] + ordered[n // 2])
        return math.sqrt(mid)
