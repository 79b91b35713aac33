"""Uncertainty of estimated forces: the Gauss-Newton covariance at the optimum.

Near the least-squares optimum the residuals are r(theta) ~ r* + J (theta - theta*), with J (n, 3h) the Jacobian of
the present gratings' residuals w.r.t. every force's (s, f_x, f_y). With independent sensor noise of standard
deviation sigma per component, the estimate's covariance is ``sigma^2 (J^T J)^-1``; its diagonal gives the
per-force standard deviations of (s [m], f_x [N], f_y [N]). J comes from :func:`torchrod.sensitivity.
curvature_and_jacobian` (forward sensitivities, batched).

The inverse is taken in scaled form: with D = diag(J^T J)^(-1/2), ``(J^T J)^-1 = D (D J^T J D)^-1 D``, and the
eigenvalues of the unit-diagonal matrix D J^T J D measure identifiability independently of units. A reading is
flagged ``poorly_determined`` when that matrix's condition number exceeds ``condition_limit`` (two forces that
the gratings cannot tell apart, a force of near-zero magnitude whose location is free, fewer residuals than
unknowns), or when a force lies distal to the last present grating (its location is then inferred only from the
slope of the curvature proximal to it, and a force at the tip trades location against magnitude).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..model.sensitivity import ESTIMATION_STEP_ANGLE, curvature_and_jacobian
from ..rod import Rod

__all__ = ["CONDITION_LIMIT", "Uncertainty", "force_uncertainty", "gauss_newton_covariance"]

CONDITION_LIMIT = 1e8
"""Default limit on the condition number of the unit-diagonal Gauss-Newton matrix."""


@dataclass(frozen=True)
class Uncertainty:
    """Gauss-Newton uncertainty of B estimates with up to h forces each.

    Attributes:
        std: (B, h, 3) standard deviations of (s [m], f_x [N], f_y [N]); NaN for padded forces.
        covariance: (B, 3h, 3h) covariance of (s_1, fx_1, fy_1, s_2, ...) [SI]; NaN rows/columns for padding.
        condition: (B,) condition number of the unit-diagonal J^T J (inf when singular).
        poorly_determined: (B,) bool (see the module docstring).
    """

    std: torch.Tensor
    covariance: torch.Tensor
    condition: torch.Tensor
    poorly_determined: torch.Tensor


def gauss_newton_covariance(
    jacobian: torch.Tensor, sigma: torch.Tensor, active: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``sigma^2 (J^T J)^-1`` per sample, over the active parameters.

    Args:
        jacobian: (B, n, P) residual Jacobian (rows of missing residuals zero).
        sigma: (B,) noise standard deviation per residual.
        active: (B, P) bool, parameters to include (others get NaN); None: all.
    Returns:
        covariance (B, P, P) and the condition number (B,) of the unit-diagonal normal matrix.
    """
    B, _, P = jacobian.shape
    dtype = jacobian.dtype
    if active is None:
        active = torch.ones(B, P, dtype=torch.bool, device=jacobian.device)
    J = jacobian * active.unsqueeze(1).to(dtype)
    A = J.transpose(1, 2) @ J  # (B, P, P)
    diag = A.diagonal(dim1=1, dim2=2)
    scale_ok = active & (diag > torch.finfo(dtype).tiny)
    d = torch.where(scale_ok, diag.clamp(min=torch.finfo(dtype).tiny).rsqrt(), torch.zeros_like(diag))
    C = A * d.unsqueeze(1) * d.unsqueeze(2)
    # Inactive parameters: identity rows so the matrix stays invertible; they are NaN-ed below.
    eye = torch.eye(P, dtype=dtype, device=jacobian.device)
    C = torch.where((~active).unsqueeze(1) | (~active).unsqueeze(2), eye, C)
    evals, evecs = torch.linalg.eigh(C)
    lo, hi = evals[:, 0], evals[:, -1]
    eps = torch.finfo(dtype).eps
    condition = torch.where(lo > eps * hi.abs(), hi / lo, torch.full_like(lo, float("inf")))
    condition = torch.where((active & ~scale_ok).any(1), torch.full_like(condition, float("inf")), condition)
    inv_evals = torch.where(evals > eps * hi.abs().unsqueeze(1), 1.0 / evals, torch.zeros_like(evals))
    C_inv = (evecs * inv_evals.unsqueeze(1)) @ evecs.transpose(1, 2)
    cov = C_inv * d.unsqueeze(1) * d.unsqueeze(2) * (sigma**2).view(-1, 1, 1)
    bad = ~(active & scale_ok)
    cov = cov.masked_fill(bad.unsqueeze(1) | bad.unsqueeze(2), float("nan"))
    return cov, condition


def force_uncertainty(
    rod: Rod,
    s: torch.Tensor,
    f: torch.Tensor,
    force_mask: torch.Tensor,
    grating_mask: torch.Tensor,
    sigma: torch.Tensor,
    *,
    condition_limit: float = CONDITION_LIMIT,
    max_step_angle: float = ESTIMATION_STEP_ANGLE,
) -> Uncertainty:
    """Gauss-Newton uncertainty of the forces (s, f) given as model locations (no location bias).

    Args:
        rod: the rod.
        s: (B, h) [m], f: (B, h, 2) [N], force_mask: (B, h) bool (False: padding).
        grating_mask: (B, G) bool, True where the grating was read.
        sigma: (B,) noise standard deviation per curvature component [1/m].
        condition_limit: flag readings whose unit-diagonal normal matrix is worse conditioned than this.
        max_step_angle: accuracy of the forward model (:mod:`torchrod.sensitivity`).
    Returns:
        :class:`Uncertainty`.
    """
    B, h = s.shape
    q = rod.grating_positions(s.dtype, s.device)
    _, jac = curvature_and_jacobian(
        q, s, f, rod.length, rod.bending_stiffness, mask=force_mask, max_step_angle=max_step_angle
    )
    jac = jac * grating_mask.to(s.dtype).view(B, -1, 1, 1, 1)
    J = jac.reshape(B, -1, 3 * h)
    active = force_mask.repeat_interleave(3, dim=1)
    cov, condition = gauss_newton_covariance(J, sigma, active)
    std = cov.diagonal(dim1=1, dim2=2).clamp(min=0.0).sqrt().reshape(B, h, 3)
    last = torch.where(grating_mask, q, torch.full_like(q, -float("inf"))).amax(dim=1)  # (B,)
    distal = (force_mask & (s > last.unsqueeze(1) + 1e-12)).any(dim=1)
    residuals = 2 * grating_mask.sum(dim=1)
    underdetermined = residuals < 3 * force_mask.sum(dim=1)
    nonfinite = (~torch.isfinite(std) & force_mask.unsqueeze(-1)).any(dim=(1, 2))
    poorly = ~(condition <= condition_limit) | distal | underdetermined | nonfinite
    return Uncertainty(std=std, covariance=cov, condition=condition, poorly_determined=poorly)
