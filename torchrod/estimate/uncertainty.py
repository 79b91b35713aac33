"""Uncertainty of estimated forces: the Gauss-Newton covariance at the optimum, and when the data cannot decide.

Near the least-squares optimum the residuals are r(theta) ~ r* + J (theta - theta*), with J (n, 3h) the Jacobian of
the present gratings' residuals w.r.t. every force's (s, f_x, f_y). With independent sensor noise of standard
deviation sigma per component, the estimate's covariance is ``sigma^2 (J^T J)^-1``; its diagonal gives the
per-force standard deviations of (s [m], f_x [N], f_y [N]). J is the fit's own (:mod:`.problem`, one-sided at a
grating the force sits on).

The inverse is taken in scaled form: with D = diag(J^T J)^(-1/2), ``(J^T J)^-1 = D (D J^T J D)^-1 D``, and the
eigenvalues of the unit-diagonal matrix D J^T J D measure identifiability independently of units. A fit is
*poorly determined* (the data cannot tell its answer from others) when:

* that matrix's condition number exceeds ``condition_limit`` (two forces the gratings cannot tell apart, a force
  of near-zero magnitude whose location is free);
* it has fewer residuals than unknowns, or the gratings that see its forces (those proximal to the most distal
  force) leave fewer than three residuals beyond its unknowns: one more force there would fit as well, so the
  count itself cannot be tested;
* a force lies in the reading's first interval, between its first two present gratings: one grating sees it,
  and its two components cannot separate the force's magnitude from its lever;
* a force's location is uncertain by more than the interval it lies in (standard deviation above the interval's
  length: the data cannot say between which gratings it acts);
* a standard deviation is not finite (the linear algebra failed: guarded, never raised).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from . import _lm_compiled
from .problem import bounds, kink_sides, near_kink

__all__ = ["CONDITION_LIMIT", "Uncertainty", "fit_uncertainty", "gauss_newton_covariance", "uncertainty"]

CONDITION_LIMIT = 1e8
"""Default limit on the condition number of the unit-diagonal Gauss-Newton matrix."""

_DIAG_MIN = 1e-300  # an unknown whose J^T J diagonal is not above this has no scale: not determined
_EPS = 2.220446049250313e-16  # float64's machine epsilon: eigenvalues below eps x the largest count as zero


@dataclass(frozen=True)
class Uncertainty:
    """Gauss-Newton uncertainty of B fits with up to h forces each (backend arrays).

    Attributes:
        std: (B, h, 3) standard deviations of (s [m], f_x [N], f_y [N]); NaN for padded forces.
        covariance: (B, 3h, 3h) covariance of (s_1, fx_1, fy_1, s_2, ...) [SI]; NaN rows/columns for padding.
        condition: (B,) condition number of the unit-diagonal J^T J (inf when singular).
        poorly_determined: (B,) bool (see the module docstring).
    """

    std: Any
    covariance: Any
    condition: Any
    poorly_determined: Any


def gauss_newton_covariance(xp: Any, J: Any, sigma: Any, active: Any, *, compiled: bool = False) -> tuple[Any, Any]:
    """``sigma^2 (J^T J)^-1`` per sample over the active unknowns, guarded: a sample whose matrix is not finite or
    whose eigensolver fails gets NaN and an infinite condition number (never an exception).

    Args:
        J: (B, n, P) residual Jacobian (rows of missing residuals zero), any units per column.
        sigma: (B,) noise standard deviation per residual.
        active: (B, P) bool, unknowns to include (others get NaN).
        compiled: run the same, row by row, in the kernel of :mod:`._lm_compiled` (NumPy arrays only; where it
            cannot run, the array code does).
    Returns:
        covariance (B, P, P) in the columns' units and the condition number (B,).
    """
    lib = xp.lib
    B, _, P = J.shape
    if P == 0:  # no unknowns: nothing to be uncertain about
        return xp.zeros((B, 0, 0)), xp.ones((B,))
    if compiled and xp.name == "numpy":
        out = _lm_compiled.covariance(J, sigma, active, _DIAG_MIN, _EPS)
        if out is not None:
            return out
    act = xp.astype(active, "float")
    # A row whose Jacobian is not finite (a diverged fit, an absurd reading) gets NaN: sanitised here, flagged below.
    finite_rows = xp.all(xp.isfinite(J.reshape(B, -1)), 1)
    J = xp.where(xp.isfinite(J), J, 0.0)
    Jm = J * act[:, None, :]
    A = xp.mT(Jm) @ Jm  # (B, P, P)
    diag = xp.diagonal(A)
    scale_ok = active & (diag > _DIAG_MIN) & xp.isfinite(diag)
    d = xp.where(scale_ok, 1.0 / lib.sqrt(xp.clip(diag, lo=_DIAG_MIN)), 0.0)
    Cm = A * d[:, :, None] * d[:, None, :]
    # Inactive unknowns: identity rows, so the matrix stays invertible; they are NaN-ed below.
    inactive = ~scale_ok
    eye = xp.eye(P)
    Cm = xp.where(inactive[:, :, None] | inactive[:, None, :], xp.expand(eye, (B, P, P)), Cm)
    evals, evecs, ok = xp.eigh(Cm)
    lo, hi = evals[:, 0], evals[:, -1]
    eps = _EPS
    condition = xp.where(ok & (lo > eps * abs(hi)), hi / xp.where(lo > 0, lo, 1.0), math.inf)
    condition = xp.where(xp.any(active & ~scale_ok, 1), math.inf, condition)
    inv = xp.where(evals > eps * abs(hi)[:, None], 1.0 / xp.where(evals != 0, evals, 1.0), 0.0)
    C_inv = (evecs * inv[:, None, :]) @ xp.mT(evecs)
    cov = C_inv * d[:, :, None] * d[:, None, :] * (sigma * sigma)[:, None, None]
    ok = ok & finite_rows
    condition = xp.where(finite_rows, condition, math.inf)
    bad = ~(active & scale_ok) | ~ok[:, None]
    cov = xp.where(bad[:, :, None] | bad[:, None, :], math.nan, cov)
    return cov, condition


def uncertainty(
    xp: Any,
    J: Any,
    sigma: Any,
    active: Any,
    s: Any,
    interval: Any,
    interval_length: Any,
    residuals: Any,
    informative: Any,
    *,
    length: float,
    force_unit: float,
    condition_limit: float = CONDITION_LIMIT,
    compiled: bool = False,
) -> Uncertainty:
    """Uncertainty and the poorly-determined verdict of B fits (module docstring).

    Args:
        J: (B, n, 3h) Jacobian in the scaled unknowns (s / L, f / F) of :mod:`.problem`; padded forces' columns
            anything (they are inactive).
        sigma: (B,) noise per curvature component [1/m].
        active: (B, h) bool, real forces.
        s: (B, h) locations [m]; interval: (B, h) their interval index; interval_length: (B, h) [m].
        residuals: (B,) present residuals n; informative: (B,) those of the gratings proximal to the most
            distal force.
        length: L [m]; force_unit: F = EI / L^2 [N] (the scales of J's columns).
        compiled: as :func:`gauss_newton_covariance`.
    """
    B, h = active.shape
    lib = xp.lib
    act = xp.expand(active[:, :, None], (B, h, 3)).reshape(B, 3 * h)
    cov, condition = gauss_newton_covariance(xp, J, sigma, act, compiled=compiled)
    unit = xp.asarray([length, force_unit, force_unit] * h)
    cov = cov * unit[None, :, None] * unit[None, None, :]
    var = xp.diagonal(cov).reshape(B, h, 3)
    std = lib.sqrt(xp.clip(var, lo=0.0))
    std = xp.where(var == var, std, var)  # NaN stays NaN
    count = xp.astype(active, "int").sum(1)
    underdetermined = (residuals < 3 * count) | ((count > 0) & (informative - 3 * count < 3))
    nonfinite = xp.any(active & ~xp.all(xp.isfinite(std), 2), 1)
    one_grating = xp.any(active & (interval == 0), 1)
    unplaced = xp.any(active & (std[..., 0] > interval_length), 1)
    poorly = ~(condition <= condition_limit) | underdetermined | nonfinite | one_grating | unplaced
    return Uncertainty(std=std, covariance=cov, condition=condition, poorly_determined=poorly)


def fit_uncertainty(
    problem: Any,
    fits: Any,
    active: Any,
    J: Any,
    sigma: Any,
    *,
    condition_limit: float = CONDITION_LIMIT,
) -> Uncertainty:
    """:func:`uncertainty` of B fits of a :class:`.problem.Problem` (row b: reading b): ``fits`` (B, W) with
    ``active`` (B, W) their real forces, J (B, 2G, 3W) their sided Jacobians, sigma (B,) [1/m]. A force on a
    grating (a kink of the loss) is judged from both one-sided Jacobians; the worse one counts. The covariance runs
    compiled where the solver's steps do (:func:`._lm_compiled.usable`)."""
    xp = problem.xp
    B, W = active.shape
    compiled = _lm_compiled.usable(problem, B, W)
    G = problem.query.shape[0]
    lo, hi = bounds(problem, fits)
    distal = xp.amax(xp.where(active, fits.s, -1.0), 1) if W else xp.zeros((B,)) - 1.0
    present = problem.weight[fits.reading].reshape(B, G, 2)[..., 0] > 0
    informative = 2 * xp.astype(present & (problem.query[None, :] < distal[:, None]), "int").sum(1)
    sides = kink_sides(problem, fits, J) if bool(xp.any(near_kink(problem, fits))) else (J,)
    both = [
        uncertainty(
            xp,
            Jk,
            sigma,
            active,
            fits.s,
            fits.interval,
            hi - lo,
            problem.residuals[fits.reading],
            informative,
            length=problem.length,
            force_unit=problem.force_unit,
            condition_limit=condition_limit,
            compiled=compiled,
        )
        for Jk in sides
    ]
    unc = both[0]
    if len(both) == 2:
        worse = xp.where(unc.std != unc.std, unc.std, xp.lib.maximum(unc.std, both[1].std))
        unc = dataclasses.replace(unc, std=worse, poorly_determined=unc.poorly_determined | both[1].poorly_determined)
    return unc
