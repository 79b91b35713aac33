"""Choosing the number of forces (0 included) from the best loss of each count, and when that choice is settled.

The loss of a fit with h forces is ``loss_h = sum over present gratings of |u_model - u_measured|^2`` [1/m^2], with
``n = 2 G_present`` residuals and ``3 h`` unknowns; ``loss_0`` is the reading's own energy (no force). Two rules:

``"threshold"`` (the paper's): the first h with ``loss_h < threshold``, else the largest h fitted. The threshold has
    units of 1/m^2 and ignores the number of gratings and the noise (docs/physics.md, erratum 4); kept to
    reproduce it.

``"noise"`` (the default): nested likelihood-ratio tests, smallest h first. With Gaussian noise of known sigma,
    adding k forces to a model that already holds the true ones lowers the loss by ``sigma^2`` times a chi-square
    variable with 3k degrees of freedom, except that the added forces' locations are free: the drop is the maximum
    over locations of such variables (the nuisance parameter is not identified under the smaller model), whose tail
    is heavier. The test therefore uses the Bonferroni bound over the G grating intervals where a force can hide:
    h is accepted when, for every larger fitted count h',

        loss_h - loss_h' <= sigma^2 chi2_{1 - alpha / G}(3 (h' - h)),

    and (a guard against gross misfit, when every fit is poor) ``loss_h <= sigma^2 chi2_{1 - alpha_fit}(n - 3h)``
    with ``alpha_fit = alpha / MISFIT_FACTOR``. The smallest accepted h wins. If none is (a reading no count
    explains, or too few residuals for any test), the smallest h that passes the drop tests alone wins: the fewest
    forces that no larger count improves on beyond noise; failing that, the largest fitted count.
    h = 0 is tested like any other count: a reading of pure noise is "no contact". With sigma unknown it is
    estimated from the largest fit, ``sigma^2 = loss_H / (n - 3 H)``, and the drop is tested with the F law:
    ``((loss_h - loss_h') / (3 (h' - h))) / sigma^2 <= F_{1 - alpha / G}(3 (h' - h), n - 3H)`` (no misfit guard:
    the misfit is what estimates sigma).

A one-force reading is therefore not split in two (a second force lowers the loss only by fitting noise), and two
forces are kept apart whenever merging them raises the loss beyond what noise explains. sigma^2 is floored by
``floor^2`` (added in quadrature): the forward model is exact only to the integrator's accuracy, so a noise-free
reading must not demand a loss of exactly zero. Counts without degrees of freedom left (``3 h >= n``) are never
accepted by a test and only chosen when no count is.

:func:`settled` tells, with the noise known, whether a count is decided before the next count is fitted, from the
scan's promise of what one more force could gain (:mod:`.search`).

Runs on either backend (:mod:`torchrod.backend`); the quantiles come from ``scipy.special`` (imported on first use)
and are cached.
"""

from __future__ import annotations

import functools
import math
from typing import Any

__all__ = [
    "MISFIT_FACTOR",
    "RULES",
    "ceilings",
    "chi2_quantile",
    "chi2_survival",
    "f_quantile",
    "misfit_limit",
    "select_count",
    "settled",
]

RULES = ("noise", "threshold")

MISFIT_FACTOR = 50.0
"""The count tests' misfit guard runs at ``alpha / MISFIT_FACTOR``: it only rejects fits far worse than noise."""


@functools.lru_cache(maxsize=8192)
def chi2_quantile(p: float, dof: int) -> float:
    """The p-quantile of the chi-square law with ``dof`` degrees of freedom (inf for dof <= 0)."""
    if dof <= 0:
        return math.inf
    from scipy import special

    return float(special.chdtri(dof, 1.0 - p))


@functools.lru_cache(maxsize=8192)
def f_quantile(p: float, d1: int, d2: int) -> float:
    """The p-quantile of Fisher's F law with (d1, d2) degrees of freedom."""
    from scipy import special

    return float(special.fdtri(d1, max(d2, 1), p))


def chi2_survival(x: Any, dof: Any) -> Any:
    """P(chi2_dof > x), elementwise on NumPy arrays or floats (NaN where dof <= 0)."""
    import numpy as np
    from scipy import special

    x, dof = np.asarray(x, dtype=np.float64), np.asarray(dof, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(dof > 0, special.chdtrc(np.maximum(dof, 1.0), np.maximum(x, 0.0)), np.nan)


def misfit_limit(residuals: int, h: int, significance: float) -> float:
    """The largest ``loss_h / sigma^2`` the count tests accept for h forces and ``residuals`` residuals (-1 where
    3h >= residuals: never accepted)."""
    q = chi2_quantile(1.0 - significance / MISFIT_FACTOR, residuals - 3 * h)
    return q if math.isfinite(q) else -1.0


@functools.lru_cache(maxsize=4096)
def _limit_row(
    counts: tuple[int, ...], residuals: int, significance: float, num_gratings: int, dof_ref: int | None
) -> tuple[tuple[tuple[float, ...], ...], tuple[float, ...]]:
    """One reading's drop (C x C) and misfit (C) limits in units of sigma^2 (module docstring): chi-square with
    the noise given (``dof_ref`` None), else F with ``dof_ref`` degrees of freedom in the largest fit."""
    a = significance / max(1, num_gratings)
    if dof_ref is None:
        drop = tuple(
            tuple(chi2_quantile(1.0 - a, 3 * (h2 - h)) if h2 > h else math.inf for h2 in counts) for h in counts
        )
        return drop, tuple(misfit_limit(residuals, h, significance) for h in counts)
    drop = tuple(
        tuple(3 * (h2 - h) * f_quantile(1.0 - a, 3 * (h2 - h), dof_ref) if h2 > h else math.inf for h2 in counts)
        for h in counts
    )
    return drop, tuple(math.inf if residuals - 3 * h > 0 else -1.0 for h in counts)


def _limits(xp: Any, counts: list[int], residuals: Any, significance: float, num_gratings: int, dof_ref: Any):
    """drop (B, C, C) in units of sigma^2 (inf where h' <= h) and misfit (B, C) limits (module docstring), per
    reading (:func:`_limit_row`, cached: a stream's readings share a few rows)."""
    B, C = residuals.shape[0], len(counts)
    if B == 0:
        return xp.zeros((0, C, C)), xp.zeros((0, C))
    refs = [None] * B if dof_ref is None else [int(r) for r in xp.tolist(dof_ref)]
    keys = list(zip((int(n) for n in xp.tolist(residuals)), refs, strict=True))
    if len(set(keys)) == 1:
        drop, misfit = _limit_row(tuple(counts), keys[0][0], significance, num_gratings, keys[0][1])
        return xp.expand(xp.asarray(drop)[None], (B, C, C)), xp.expand(xp.asarray(misfit)[None], (B, C))
    rows = [_limit_row(tuple(counts), n, significance, num_gratings, ref) for n, ref in keys]
    return xp.asarray([d for d, _ in rows]), xp.asarray([m for _, m in rows])


def _dof_last(xp: Any, losses: Any, counts: list[int], residuals: Any) -> tuple[Any, Any]:
    """The degrees of freedom n - 3h (B, C) and (B,) the column of the largest fitted count."""
    h = xp.asarray([float(c) for c in counts])
    dof = xp.astype(residuals, "float")[:, None] - 3.0 * h
    fitted = xp.astype(losses == losses, "int")
    return dof, xp.argmin(-(fitted * (xp.arange(len(counts)) + 1)), 1)


def _noise_tests(
    xp: Any,
    losses: Any,
    counts: list[int],
    residuals: Any,
    noise: float | None,
    significance: float,
    floor: float,
    num_gratings: int,
) -> tuple[Any, ...]:
    """The ``"noise"`` rule's sigma^2 (B,) [1/m^2] (given, or from the largest fit), its drop (B, C, C) and
    misfit (B, C) limits in units of sigma^2 (module docstring), the degrees of freedom (B, C) and the largest
    fitted count's column (B,)."""
    dof, last = _dof_last(xp, losses, counts, residuals)
    floor2 = float(floor) ** 2
    if noise is not None:
        sigma2 = xp.full((losses.shape[0],), float(noise) ** 2 + floor2)
        drop, misfit = _limits(xp, counts, residuals, significance, num_gratings, None)
    else:
        loss_H = xp.take(losses, last[:, None], 1)[:, 0]
        dof_H = xp.take(dof, last[:, None], 1)[:, 0]
        sigma2 = xp.where(dof_H > 0, loss_H / xp.clip(dof_H, lo=1.0), 0.0) + floor2
        drop, misfit = _limits(xp, counts, residuals, significance, num_gratings, xp.clip(dof_H, lo=1.0))
    return sigma2, drop, misfit, dof, last


def ceilings(
    xp: Any,
    losses: Any,
    counts: list[int],
    residuals: Any,
    *,
    rule: str = "noise",
    noise: float | None = None,
    threshold: float = 3.0,
    significance: float = 0.05,
    floor: float = 0.0,
    num_gratings: int = 1,
) -> Any:
    """(B, C) the largest loss [1/m^2] at which each count passes the tests of :func:`select_count`, the other
    counts' losses as they are: for ``"noise"``, the misfit limit and, for every larger fitted count h', its loss
    plus the drop limit (a negative value where the count has no degrees of freedom left); for ``"threshold"``, the
    threshold. A fit of h forces that no better local minimum could bring below its ceiling cannot be chosen, so
    the search need not look for one (:mod:`.search`). Arguments as :func:`select_count`."""
    if rule not in RULES:
        raise ValueError(f"selection rule must be one of {RULES}, got {rule!r}")
    B, C = losses.shape
    if rule == "threshold":
        return xp.full((B, C), float(threshold))
    sigma2, drop, misfit, _, _ = _noise_tests(xp, losses, counts, residuals, noise, significance, floor, num_gratings)
    s2 = sigma2[:, None, None]
    beaten = losses[:, None, :] + drop * s2  # (B, C, C): h' fitted, larger: loss_h' + drop; else inf or NaN
    beaten = xp.where(beaten == beaten, beaten, math.inf)
    return xp.lib.minimum(xp.amin(beaten, 2), misfit * sigma2[:, None])


def select_count(
    xp: Any,
    losses: Any,
    counts: list[int],
    residuals: Any,
    *,
    rule: str = "noise",
    noise: float | None = None,
    threshold: float = 3.0,
    significance: float = 0.05,
    floor: float = 0.0,
    num_gratings: int = 1,
) -> tuple[Any, Any]:
    """The chosen count per reading, and the noise level used.

    Args:
        xp: the backend of the arrays (:mod:`torchrod.backend`).
        losses: (B, C) best loss [1/m^2] for each of ``counts`` (increasing, 0 allowed); NaN where not fitted.
        counts: the C counts, increasing (e.g. [0, 1, 2, 3]).
        residuals: (B,) number of residuals n = 2 x (present gratings) of each reading.
        rule: ``"noise"`` or ``"threshold"``.
        noise: sensor sigma [1/m] per component; None: estimated per reading from the largest fit.
        threshold: the paper's loss threshold [1/m^2] (``rule="threshold"``).
        significance: alpha of the tests (``rule="noise"``), before the Bonferroni factor.
        floor: [1/m] added in quadrature to sigma (model accuracy).
        num_gratings: G, the Bonferroni factor of the tests.
    Returns:
        chosen (B,) int (a value of ``counts``), and sigma (B,) [1/m]: the noise used (given or estimated from
        the largest fit, with the floor); for ``"threshold"`` without a given noise, the residual estimate of the
        chosen fit, ``sqrt(loss_h / (n - 3 h))``, floored.
    """
    if rule not in RULES:
        raise ValueError(f"selection rule must be one of {RULES}, got {rule!r}")
    if not 0.0 < significance < 1.0:
        raise ValueError(f"significance must lie in (0, 1), got {significance!r}")
    B, C = losses.shape
    if C != len(counts) or list(counts) != sorted(set(counts)) or min(counts) < 0:
        raise ValueError(f"counts must be increasing, >= 0 and match losses' {C} columns, got {counts}")
    lib = xp.lib
    h = xp.asarray([float(c) for c in counts])  # (C,)
    fitted = losses == losses
    floor2 = float(floor) ** 2
    if rule == "threshold":
        ok = fitted & (losses < threshold)
        sigma2 = None if noise is None else xp.full((B,), float(noise) ** 2 + floor2)
        dof, last = _dof_last(xp, losses, counts, residuals)
    else:
        sigma2, drop, misfit, dof, last = _noise_tests(
            xp, losses, counts, residuals, noise, significance, floor, num_gratings
        )
        s2 = sigma2[:, None, None]
        diff = losses[:, :, None] - losses[:, None, :]  # (B, C, C): loss_h - loss_h'
        pair_ok = ~(diff > drop * s2)  # NaN (unfitted h') passes
        ok = fitted & xp.all(pair_ok, 2) & (losses <= misfit * sigma2[:, None]) & (dof > 0)
    fallback = last
    if rule != "threshold":
        # No count accepted (every fit worse than the noise explains, or none with degrees of freedom left): the
        # fewest forces that no larger count improves on beyond noise, else the largest fitted.
        fewest = fitted & xp.all(pair_ok, 2)
        fallback = xp.where(xp.any(fewest, 1), xp.argmin(-xp.astype(fewest, "int"), 1), last)
    first = xp.where(xp.any(ok, 1), xp.argmin(-xp.astype(ok, "int"), 1), fallback)
    chosen = xp.astype(h[first], "int")
    if sigma2 is None:
        lc = xp.take(losses, first[:, None], 1)[:, 0]
        dc = xp.take(dof, first[:, None], 1)[:, 0]
        sigma2 = xp.where(dc > 0, lc / xp.clip(dc, lo=1.0), 0.0) + floor2
    return chosen, lib.sqrt(sigma2)


def settled(
    xp: Any,
    losses: Any,
    counts: list[int],
    residuals: Any,
    gain: Any,
    *,
    rule: str,
    noise: float | None,
    threshold: float,
    significance: float,
    floor: float,
    num_gratings: int,
    safety: float = 2.0,
) -> Any:
    """(B,) bool: readings whose count is decided among ``counts`` (all fitted, the last one the largest so far)
    whatever the next count would reach, given ``gain`` (B,) [1/m^2], the loss decrease the scan promises for one
    more force. The next count's loss is taken as ``loss_last - safety x gain`` (the Gauss-Newton promise is a
    local estimate; ``safety`` covers its error). Only with a known noise or the threshold rule (with sigma
    estimated from the largest fit, every count must be fitted): otherwise nothing is settled."""
    B = losses.shape[0]
    if rule == "noise" and noise is None:
        return xp.zeros((B,), "bool")
    if rule == "threshold":
        return xp.any((losses == losses) & (losses < threshold), 1)
    nxt = xp.clip(losses[:, -1] - safety * gain, lo=0.0)
    extended = xp.concat([losses, nxt[:, None]], 1)
    chosen, _ = select_count(
        xp,
        extended,
        counts + [counts[-1] + 1],
        residuals,
        rule=rule,
        noise=noise,
        threshold=threshold,
        significance=significance,
        floor=floor,
        num_gratings=num_gratings,
    )
    return chosen <= counts[-1]
