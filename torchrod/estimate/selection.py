"""Choosing the number of forces from the best loss of each count.

The loss of a fit with h forces is ``loss_h = sum over present gratings of |u_model - u_measured|^2`` [1/m^2], with
``n = 2 G_present`` residuals and ``3 h`` unknowns. Two rules:

``"threshold"`` (the paper's): the first h with ``loss_h < threshold``, else the largest h fitted. The threshold has
    units of 1/m^2 and ignores the number of gratings and the noise (NOTES.md, erratum 4); kept to reproduce it.

``"noise"`` (the default): nested likelihood-ratio tests, smallest h first. With Gaussian noise of known sigma,
    adding k forces to a model that already holds the true ones lowers the loss by ``sigma^2`` times a chi-square
    variable with 3k degrees of freedom, except that the added forces' locations are free: the drop is the maximum
    over locations of such variables (the nuisance parameter is not identified under the smaller model), whose tail
    is heavier. The test therefore uses the Bonferroni bound over the G grating intervals where a force can hide:
    h is accepted when, for every larger fitted count h',

        loss_h - loss_h' <= sigma^2 chi2_{1 - alpha / G}(3 (h' - h)),

    and (a guard against gross misfit, when every fit is poor) ``loss_h <= sigma^2 chi2_{1 - alpha_fit}(n - 3h)``
    with ``alpha_fit = alpha / 50``. The smallest accepted h wins; if none is, the largest fitted count.
    With sigma unknown it is estimated from the largest fit, ``sigma^2 = loss_H / (n - 3 H)``, and the drop is
    tested with the F law: ``((loss_h - loss_h') / (3 (h' - h))) / sigma^2 <= F_{1 - alpha / G}(3 (h' - h), n - 3H)``
    (no misfit guard: the misfit is what estimates sigma).

A one-force reading is therefore not split in two (a second force lowers the loss only by fitting noise), and two
forces are kept apart whenever merging them raises the loss beyond what noise explains (the data decide: two
forces closer than a grating interval, or a weak one, may be indistinguishable from one). sigma^2 is floored by
``floor^2`` (added in quadrature): the forward model is exact only to the integrator's accuracy, so a noise-free
reading must not demand a loss of exactly zero. Counts without degrees of freedom left (``3 h >= n``) are never
accepted by a test and only chosen as the last resort.

:func:`count_limits` exposes the same critical values, which the estimator also uses to stop fits early once a
reading's count is decided.
"""

from __future__ import annotations

import functools
import math

import torch
from scipy import stats

__all__ = [
    "MISFIT_FACTOR",
    "RULES",
    "choose_count",
    "count_limits",
    "misfit_limit",
    "noise_quantile",
    "select_count",
]

RULES = ("noise", "threshold")

MISFIT_FACTOR = 50.0
"""The misfit guard runs at ``alpha / MISFIT_FACTOR``: it only rejects fits far worse than noise."""


def count_limits(
    counts: list[int],
    residuals: torch.Tensor,
    *,
    significance: float,
    num_gratings: int,
    dof_reference: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Critical values of the ``"noise"`` rule, in units of sigma^2.

    Args:
        counts: the C fitted counts, increasing.
        residuals: (B,) residual count n of each reading.
        significance: alpha.
        num_gratings: G, the Bonferroni factor.
        dof_reference: (B,) denominator degrees of freedom for the F law (sigma estimated); None: chi-square.
    Returns:
        drop (B, C, C): the largest allowed ``(loss_h - loss_h') / sigma^2`` for h = counts[i] against
        h' = counts[j] > h (inf elsewhere); misfit (B, C): the largest allowed ``loss_h / sigma^2`` (inf when sigma
        is estimated; -1 where 3h >= n).
    """
    B, C = residuals.shape[0], len(counts)
    dtype, device = torch.float64, residuals.device
    a = significance / max(1, num_gratings)
    drop = torch.full((B, C, C), float("inf"), dtype=dtype)
    for i, h in enumerate(counts):
        for j, h2 in enumerate(counts):
            if h2 <= h:
                continue
            d1 = 3 * (h2 - h)
            if dof_reference is None:
                drop[:, i, j] = _chi2_quantile(1.0 - a, d1)
            else:
                d2 = dof_reference.clamp(min=1).cpu().double().numpy()
                drop[:, i, j] = torch.as_tensor(d1 * stats.f.ppf(1.0 - a, d1, d2), dtype=dtype)
    n = residuals.cpu().to(dtype).unsqueeze(1) - 3.0 * torch.tensor(counts, dtype=dtype)
    if dof_reference is None:
        values = {int(r): [misfit_limit(int(r), h, significance) for h in counts] for r in residuals.tolist()}
        misfit = torch.tensor([values[int(r)] for r in residuals.tolist()], dtype=dtype).view(B, C)
    else:
        misfit = torch.where(n > 0, torch.full_like(n, float("inf")), torch.full_like(n, -1.0))
    return drop.to(device), misfit.to(device)


@functools.lru_cache(maxsize=4096)
def _chi2_quantile(p: float, dof: int) -> float:
    return float(stats.chi2.ppf(p, dof))


def misfit_limit(residuals: int, h: int, significance: float) -> float:
    """The misfit guard of the ``"noise"`` rule with known sigma: the largest allowed ``loss_h / sigma^2`` for h
    forces fitted to ``residuals`` residuals (-1 where 3h >= residuals). Cached: the quantile is the same for
    every reading with the same gratings present."""
    q = noise_quantile(residuals, h, 1.0 - significance / MISFIT_FACTOR)
    return q if math.isfinite(q) else -1.0


def noise_quantile(residuals: int, h: int, p: float) -> float:
    """The p-quantile of ``loss_h / sigma^2`` for a correct fit of h forces to ``residuals`` residuals: chi-square
    with residuals - 3h degrees of freedom (inf where there are none). Cached."""
    dof = residuals - 3 * h
    return _chi2_quantile(p, dof) if dof > 0 else math.inf


def select_count(
    losses: torch.Tensor,
    counts: list[int],
    residuals: torch.Tensor,
    *,
    rule: str = "noise",
    noise: float | None = None,
    threshold: float = 3.0,
    significance: float = 0.05,
    floor: float = 0.0,
    num_gratings: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The chosen count per reading, and the noise level used.

    Args:
        losses: (B, C) best loss [1/m^2] for each of ``counts`` (increasing); NaN where a count was not fitted.
        counts: the C counts, increasing (e.g. [1, 2, 3]).
        residuals: (B,) number of residuals n = 2 x (present gratings) of each reading.
        rule: ``"noise"`` or ``"threshold"``.
        noise: sensor sigma [1/m] per component; None: estimated per reading from the largest fit.
        threshold: the paper's loss threshold [1/m^2] (``rule="threshold"``).
        significance: alpha of the tests (``rule="noise"``), before the Bonferroni factor.
        floor: [1/m] added in quadrature to sigma (model accuracy).
        num_gratings: G, the Bonferroni factor of the tests.
    Returns:
        chosen (B,) long (a value of ``counts``), and sigma (B,) [1/m]: the noise used (given or estimated from
        the largest fit, with the floor); for ``"threshold"`` without a given noise, the residual estimate of the
        chosen fit, ``sqrt(loss_h / (n - 3 h))``, floored.
    """
    if rule not in RULES:
        raise ValueError(f"selection rule must be one of {RULES}, got {rule!r}")
    if not 0.0 < significance < 1.0:
        raise ValueError(f"significance must lie in (0, 1), got {significance!r}")
    B, C = losses.shape
    if C != len(counts) or list(counts) != sorted(set(counts)):
        raise ValueError(f"counts must be increasing and match losses' {C} columns, got {counts}")
    dtype, device = losses.dtype, losses.device
    h = torch.tensor(counts, dtype=dtype, device=device)  # (C,)
    n = residuals.to(dtype).unsqueeze(1)  # (B, 1)
    dof = n - 3.0 * h  # (B, C)
    fitted = torch.isfinite(losses)
    floor2 = float(floor) ** 2
    col = torch.arange(C, device=device)
    last = (fitted.to(torch.long) * (col + 1)).argmax(dim=1)  # (B,) the largest fitted count's column

    if rule == "threshold":
        ok = fitted & (losses < threshold)
        sigma2 = (
            None
            if noise is None
            else torch.full((B,), float(noise) ** 2 + floor2, dtype=dtype, device=device)
        )
    else:
        if noise is not None:
            sigma2 = torch.full((B,), float(noise) ** 2 + floor2, dtype=dtype, device=device)
            drop, misfit = count_limits(
                counts, residuals, significance=significance, num_gratings=num_gratings
            )
        else:
            loss_H = losses.gather(1, last.unsqueeze(1)).squeeze(1)
            dof_H = dof.gather(1, last.unsqueeze(1)).squeeze(1)
            sigma2 = torch.where(dof_H > 0, loss_H / dof_H.clamp(min=1.0), torch.zeros_like(loss_H)) + floor2
            drop, misfit = count_limits(
                counts, residuals, significance=significance, num_gratings=num_gratings, dof_reference=dof_H
            )
        s2 = sigma2.view(B, 1, 1)
        diff = losses.unsqueeze(2) - losses.unsqueeze(1)  # (B, C, C): loss_h - loss_h'
        pair_ok = ~(diff > drop.to(dtype) * s2)  # NaN (unfitted h') passes
        ok = fitted & pair_ok.all(dim=2) & (losses <= misfit.to(dtype) * sigma2.unsqueeze(1)) & (dof > 0)
    first_ok = torch.where(ok.any(dim=1), ok.to(torch.long).argmax(dim=1), last)
    chosen = h[first_ok].to(torch.long)
    if sigma2 is None:
        lc = losses.gather(1, first_ok.unsqueeze(1)).squeeze(1)
        dc = dof.gather(1, first_ok.unsqueeze(1)).squeeze(1)
        sigma2 = torch.where(dc > 0, lc / dc.clamp(min=1.0), torch.zeros_like(lc)) + floor2
    return chosen, sigma2.sqrt()


def choose_count(
    losses: list[float],
    counts: list[int],
    residuals: int,
    *,
    rule: str,
    sigma2: float | None,
    threshold: float,
    significance: float,
    num_gratings: int,
) -> int:
    """:func:`select_count` for ONE reading on Python floats, where its critical values are known (a given sigma, or
    the threshold rule): the index into ``counts`` of the chosen count. For the estimator's one-reading path, which
    asks many times per reading whether its count is already decided.

    Args:
        losses: C best losses [1/m^2] for ``counts`` (NaN: not fitted); residuals: n = 2 x present gratings.
        sigma2: the given sigma^2 with the floor [1/m^2] (required by the ``"noise"`` rule).
        rule, threshold, significance, num_gratings: as in :func:`select_count`.
    """
    fitted = [not math.isnan(x) for x in losses]
    last = max((i for i, ok in enumerate(fitted) if ok), default=0)
    if rule == "threshold":
        ok = [fit and x < threshold for fit, x in zip(fitted, losses)]
    else:
        if sigma2 is None:
            raise ValueError("choose_count needs the noise (sigma2) with the 'noise' rule")
        a = significance / max(1, num_gratings)
        ok = []
        for i, h in enumerate(counts):
            good = fitted[i] and residuals - 3 * h > 0
            good = good and losses[i] <= misfit_limit(residuals, h, significance) * sigma2
            for j in range(i + 1, len(counts)):
                if good and losses[i] - losses[j] > _chi2_quantile(1.0 - a, 3 * (counts[j] - h)) * sigma2:
                    good = False  # a NaN (unfitted) larger count never rejects
            ok.append(good)
    return next((i for i, good in enumerate(ok) if good), last)
