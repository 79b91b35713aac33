"""Refinement in torch: batched Levenberg-Marquardt fits of given starts, on the readings' own device.

``EstimatorOptions(target="torch")`` fits each count's starts (the warm-start network's guesses, or the caller's)
with the torch simulator, every reading of the batch at once, with no compile step; then the kernels take the
refined fits as their only starts (``starts=0``), so that the count rule, the covariance and the verdict are the
compiled search's own, and a reading whose verdict is not ``ok`` is searched again by the full compiled search
(:meth:`torchrod.Estimator.estimate`).

The fit of one count h for B readings: parameters theta (B, h, 3) = (s [m], f_x, f_y [N]) in model coordinates,
residuals ``c(theta) - u`` at the present gratings, a damping lambda per reading. Each step builds the Jacobian
(B, 2G, 3h) from 3h one-sided differences of the simulator (one batched forward pass each: forward-mode autograd
through the march costs several times more), solves the damped normal equations per reading, and keeps the step
where it lowers the loss (lambda divided by ``decrease``), else raises lambda by ``increase``. A reading is
converged when its Gauss-Newton decrement is at most ``tolerance`` x sigma^2, as the kernels' fits are
(:class:`~torchrod.estimate.options.LMPolicy`). Locations stay in [0, L].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..loads import PointForces
from ..model.body_frame import grating_curvature
from ..rod import Rod
from .options import LMPolicy

__all__ = ["DIFFERENCE_STEP", "TorchFit", "refine"]

DIFFERENCE_STEP = 1e-7
"""The one-sided difference step of the Jacobian, relative to the rod's length (locations) and to the force scale
EI / L^2 (components): about the square root of float64's epsilon, so the columns hold about half its digits,
plenty for a Levenberg-Marquardt step (the kernels polish the fit afterwards)."""


@dataclass(frozen=True)
class TorchFit:
    """Refined fits of one count h for B readings (model coordinates).

    Attributes:
        s: (B, h) locations [m].
        f: (B, h, 2) body-frame components [N].
        loss: (B,) the fit's loss [1/m^2].
        converged: (B,) bool, the Gauss-Newton decrement fell to the tolerance.
        evaluations: (B,) long, simulator passes spent on each reading.
    """

    s: torch.Tensor
    f: torch.Tensor
    loss: torch.Tensor
    converged: torch.Tensor
    evaluations: torch.Tensor


def _residuals(
    rod: Rod, theta: torch.Tensor, u: torch.Tensor, present: torch.Tensor, step_angle: float
) -> torch.Tensor:
    """(B, 2G) the residuals [1/m] of fits ``theta`` (B, h, 3) against readings ``u`` (B, G, 2), zero at missing
    gratings."""
    model = grating_curvature(rod, PointForces(theta[..., 0], theta[..., 1:]), max_step_angle=step_angle)
    r = torch.where(present[..., None], model - u, torch.zeros((), dtype=u.dtype, device=u.device))
    return r.reshape(r.shape[0], -1)


@torch.no_grad()
def refine(
    rod: Rod,
    u: torch.Tensor,
    present: torch.Tensor,
    s: torch.Tensor,
    f: torch.Tensor,
    *,
    sigma2: float,
    lm: LMPolicy,
    step_angle: float,
) -> TorchFit:
    """Fit h forces to B readings from the starts ``s`` (B, h) [m] and ``f`` (B, h, 2) [N] (model coordinates,
    finite), as the module docstring says.

    Args:
        rod: the rod (its own stiffness; locations in model coordinates).
        u: (B, G, 2) float64 readings [1/m], zero at missing gratings (a precurved rod's unloaded shape included).
        present: (B, G) bool.
        sigma2: the sigma^2 [1/m^2] the convergence test is scaled by (the given noise's, or the floor's).
        lm: the damping policy and the iteration limit (``iterations`` steps at most: the kernels finish the fit).
        step_angle: the simulator's step rule (the estimator's ``max_step_angle``).
    """
    B, h = s.shape
    dtype, device = u.dtype, u.device
    L = rod.length
    theta = torch.cat([s[..., None], f], dim=-1).to(dtype)
    theta[..., 0] = theta[..., 0].clamp(0.0, L)
    P = 3 * h
    scale = torch.tensor([L] + [rod.bending_stiffness / L**2] * 2, dtype=dtype, device=device).repeat(h)
    lam = torch.full((B,), lm.damping, dtype=dtype, device=device)
    r = _residuals(rod, theta, u, present, step_angle)
    loss = r.square().sum(-1)
    evaluations = torch.ones(B, dtype=torch.long, device=device)
    converged = torch.zeros(B, dtype=torch.bool, device=device)
    stopped = torch.zeros(B, dtype=torch.bool, device=device)
    limit = lm.tolerance * sigma2
    eye = torch.eye(P, dtype=dtype, device=device)
    for _ in range(lm.iterations):
        open_ = ~stopped
        if not bool(open_.any()):
            break
        idx = open_.nonzero().squeeze(1)
        th, rr, up, pr = theta[idx], r[idx], u[idx], present[idx]
        n = idx.shape[0]
        J = torch.empty(n, rr.shape[1], P, dtype=dtype, device=device)
        flat = th.reshape(n, P)
        for p in range(P):
            step = DIFFERENCE_STEP * scale[p] * torch.clamp(flat[:, p].abs() / scale[p], min=1.0)
            if p % 3 == 0:  # a location at the tip steps back into the rod
                step = torch.where(flat[:, p] + step > L, -step, step)
            moved = flat.clone()
            moved[:, p] += step
            J[:, :, p] = (_residuals(rod, moved.reshape(n, h, 3), up, pr, step_angle) - rr) / step[:, None]
        evaluations[idx] += P
        A = J.transpose(1, 2) @ J
        g = (J.transpose(1, 2) @ rr[..., None])[..., 0]
        damped = A + lam[idx, None, None] * (torch.diagonal(A, dim1=1, dim2=2)[..., None] * eye + 1e-300 * eye)
        delta = -torch.linalg.lstsq(damped, g[..., None]).solution[..., 0]
        decrement = -(g * delta).sum(-1)  # the Gauss-Newton model's promised fall of the loss (>= 0)
        trial = (flat + delta).reshape(n, h, 3)
        trial[..., 0] = trial[..., 0].clamp(0.0, L)
        r_new = _residuals(rod, trial, up, pr, step_angle)
        evaluations[idx] += 1
        loss_new = r_new.square().sum(-1)
        better = torch.isfinite(loss_new) & (loss_new < loss[idx])
        theta[idx] = torch.where(better[:, None, None], trial, th)
        r[idx] = torch.where(better[:, None], r_new, rr)
        loss[idx] = torch.where(better, loss_new, loss[idx])
        lam[idx] = torch.where(better, lam[idx] / lm.decrease, lam[idx] * lm.increase).clamp(
            lm.min_damping, lm.max_damping
        )
        small = decrement <= limit
        converged[idx] = small
        stopped[idx] = small | ~torch.isfinite(decrement) | (lam[idx] >= lm.max_damping)  # (stalled: stops too)
    return TorchFit(theta[..., 0], theta[..., 1:], loss, converged, evaluations)
