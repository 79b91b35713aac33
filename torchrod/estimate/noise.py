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

A rod with a calibration error (``Rod.calibration_error``) adds ``(rel_k u_k)^2`` to each value's variance. A fit
made with the noise known weighs it out (its loss is in the units of the sensor's sigma^2, as the estimator's
weights make it); a fit made with the noise unknown does not, and its loss holds on average ``(n - 3h) / n`` of the
calibration's summed variance besides the noise: the caller gives that share (:meth:`RunningNoise.add`'s
``calibration``, :func:`calibration_share`) and it is taken off before the ratio, so what is learned is the
sensor's own sigma.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable
from dataclasses import dataclass

from ..errors import OptionsError
from ..kernels.host import chi2_quantile

__all__ = ["NoiseLearning", "RunningNoise", "calibration_share"]


def calibration_share(variance: Iterable[float], values: Iterable[int], dof: Iterable[int]) -> list[float]:
    """Per fit, the share of its loss [1/m^2] that a calibration error makes on average where the fit does not weigh
    it out: ``(dof / n) x`` the summed calibration ``variance`` of its n present ``values`` (module docstring)."""
    return [
        float(v) * int(d) / int(n) if int(n) > 0 and int(d) > 0 else 0.0
        for v, n, d in zip(variance, values, dof, strict=True)
    ]


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

    def add(self, loss: Iterable[float], dof: Iterable[int], calibration: Iterable[float] | None = None) -> None:
        """Add fits: their losses [1/m^2] and degrees of freedom (residuals less 3 per force); fits with no
        degree of freedom or a non-finite loss are skipped. ``calibration``: per fit, the share of its loss a
        calibration error makes [1/m^2] (module docstring; None: none), taken off first (not below zero)."""
        losses = [float(x) for x in loss]
        shares = [0.0] * len(losses) if calibration is None else [float(c) for c in calibration]
        for x, d, c in zip(losses, dof, shares, strict=True):
            d = int(d)
            if d <= 0 or not math.isfinite(x) or x < 0.0:
                continue
            self._ratios.append(max(x - c, 0.0) / chi2_quantile(0.5, d))
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
