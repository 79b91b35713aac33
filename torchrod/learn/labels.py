"""The search's own fits as the warm-start network's training targets, so that the network amortises the search.

A network trained on the truths of simulated readings learns forces the data cannot show (one below the noise, two
closer than the gratings resolve): the search's fits leave those out, so the guesses start the fits away from the
minima the search finds, and a fit from them takes as many steps as one from the scan's start. Labelled instead, on
fixed noisy readings, with the compiled search's best fit of every count (each count's search run on its own) and
the count it chooses, the network learns the map from a reading to the minima the estimator would reach: its
guesses start the fits at their ends, and its count probabilities say which counts need fitting
(``trust_guesses``).

Locations are in model coordinates (the rod's location bias taken away), as the network guesses them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..estimate.estimator import Estimator
from ..estimate.options import EstimatorOptions
from ..rod import Rod

__all__ = ["SearchLabels", "search_labels"]


@dataclass(frozen=True)
class SearchLabels:
    """The search's answers for N readings, up to H forces.

    Attributes:
        s: (N, H, H) [m] row h - 1: the locations of the best fit of h forces, increasing (NaN beyond h).
        f: (N, H, H, 2) [N] their forces (zero beyond h).
        fitted: (N, H) bool: the fit of h forces converged to finite values (a target worth learning).
        count: (N,) the count the search chooses, 0..H.
    """

    s: torch.Tensor
    f: torch.Tensor
    fitted: torch.Tensor
    count: torch.Tensor


def search_labels(
    rod: Rod,
    curvature: torch.Tensor,
    mask: torch.Tensor,
    noise: float,
    *,
    max_forces: int = 3,
    batch_size: int = 4096,
    progress: Callable[[int, int], None] | None = None,
) -> SearchLabels:
    """The search's fit of each count 1..``max_forces`` and its chosen count for readings (N, G, 2) [1/m] with
    their mask (N, G), at the known sensor noise ``noise`` [1/m]. ``progress(done, total)`` is called after each
    batch of ``batch_size`` readings."""
    N = curvature.shape[0]
    H = max_forces
    options = EstimatorOptions(noise=noise, max_forces=H)
    chooser = Estimator(rod, options)
    fixed = {h: Estimator(rod, EstimatorOptions(noise=noise, num_forces=h)) for h in range(1, H + 1)}
    s = torch.full((N, H, H), float("nan"), dtype=torch.float64)
    f = torch.zeros((N, H, H, 2), dtype=torch.float64)
    fitted = torch.zeros((N, H), dtype=torch.bool)
    count = torch.zeros(N, dtype=torch.long)
    for b0 in range(0, N, batch_size):
        u, m = curvature[b0 : b0 + batch_size], mask[b0 : b0 + batch_size]
        count[b0 : b0 + u.shape[0]] = chooser.estimate(u, m).num_forces.cpu()
        for h, estimator in fixed.items():
            answer = estimator.estimate(u, m)
            fs = answer.forces.s.detach().cpu().to(torch.float64)[:, :h] - rod.location_bias
            ff = answer.forces.f.detach().cpu().to(torch.float64)[:, :h]
            ok = answer.converged.cpu() & fs.isfinite().all(1) & ff.isfinite().flatten(1).all(1)
            s[b0 : b0 + u.shape[0], h - 1, :h] = fs
            f[b0 : b0 + u.shape[0], h - 1, :h] = torch.where(ok[:, None, None], ff, 0.0)
            fitted[b0 : b0 + u.shape[0], h - 1] = ok
        if progress is not None:
            progress(min(b0 + batch_size, N), N)
    return SearchLabels(s=s, f=f, fitted=fitted, count=count)
