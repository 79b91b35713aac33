"""Gradients of an estimate through its optimum, by the implicit function theorem.

The compiled search (:mod:`torchrod.kernels`) finds each reading's fit; it is the forward pass and is never
unrolled. At the chosen fit theta* (each active force's location s [m] and components f_x, f_y [N], in model
coordinates) the loss ``L(theta, u) = sum over present gratings of |w (c(theta) - u)|^2`` (w the values' weights:
1, or a rod's calibration error's, held fixed as the kernels hold them) is stationary in theta:
``g(theta*, u) = dL/dtheta = 0``. Differentiating that condition gives the fit's response to the readings u,

    d theta* / d u = -H^-1 d g / d u,        H = d g / d theta   (the Newton matrix of the fit at theta*),

which the backward pass applies to the incoming gradient v: it solves ``H lambda = v`` per reading, then returns
``-d (g . lambda) / d u``. ``c`` is the torch simulator (:func:`torchrod.model.body_frame.grating_curvature`,
recorded by autograd so that it has second derivatives), so H holds both the Gauss-Newton part ``2 J^T J`` and
the residuals' own curvature: the gradient is that of the exact minimiser, on noisy readings too.

What carries no gradient, and why:

- the count, the status, ``converged``, ``iterations``, ``evaluations``: piecewise constant in the data;
- padding (the forces beyond a reading's count) and the standard deviations, p-values and per-count losses;
- a force whose location sits on a bound of its interval (a grating, the base or the tip, where the loss has a
  kink): the search holds it there, and so does a small change of the data, so d s / d u = 0 for it and its
  components respond with s fixed;
- a fit whose Newton matrix is singular (forces the gratings cannot separate: ``poorly_determined``) takes the
  pseudo-inverse's least-norm response; such gradients are as undetermined as the answer.

The stiffness and the location bias enter outside the search, exactly: the body-frame equations are unchanged when
every force and EI scale together (``n / EI`` and ``u`` stay the same), so an estimate at stiffness EI is the one at
the rod's EI0 with every force times ``EI / EI0``; the reported location is ``s_model + bias``. Both are
differentiable operations on the fit at the rod's own values.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from ..loads import PointForces
from ..model.body_frame import grating_curvature
from ..rod import Rod

__all__ = ["BOUND_TOLERANCE", "fit_loss", "on_bound", "through_optimum"]

BOUND_TOLERANCE = 1e-9
"""A force within this fraction of the rod's length of a grating, the base or the tip is taken to sit on that
bound of its interval (the search leaves forces exactly on a bound it holds them to)."""


def fit_loss(
    rod: Rod, theta: torch.Tensor, active: torch.Tensor, u: torch.Tensor, present: torch.Tensor, step_angle: float
) -> torch.Tensor:
    """(B,) the fit's loss [1/m^2] at parameters ``theta`` (B, W, 3) = (s [m], f_x, f_y [N]) of the ``active``
    (B, W) forces, against readings ``u`` (B, G, 2) [1/m] at the ``present`` (B, G) gratings, or weighed by
    ``present`` (B, G, 2) float weights (0 at a missing grating); twice differentiable in ``theta`` and ``u`` (the
    simulator's autograd record, not its adjoint)."""
    loads = PointForces(theta[..., 0], theta[..., 1:], active)
    model = grating_curvature(rod, loads, max_step_angle=step_angle, adjoint=False)
    if present.dtype != torch.bool:
        return ((model - u) * present).square().sum((1, 2))
    residual = torch.where(present[..., None], model - u, torch.zeros((), dtype=u.dtype, device=u.device))
    return residual.square().sum((1, 2))


def on_bound(rod: Rod, s: torch.Tensor) -> torch.Tensor:
    """(B, W) bool: locations ``s`` [m] (model coordinates) on a grating, the base or the tip
    (:data:`BOUND_TOLERANCE`)."""
    bounds = torch.tensor((0.0, *rod.gratings, rod.length), dtype=s.dtype, device=s.device)
    return ((s[..., None] - bounds).abs() <= BOUND_TOLERANCE * rod.length).any(-1)


@dataclasses.dataclass(frozen=True)
class _Fit:
    """What the backward pass needs besides the saved tensors."""

    rod: Rod
    step_angle: float


class _Optimum(torch.autograd.Function):
    """theta* as a function of the readings: the identity forward, the implicit function theorem backward."""

    @staticmethod
    def forward(ctx: Any, u: torch.Tensor, theta: torch.Tensor, free: torch.Tensor, present: torch.Tensor, fit: _Fit):
        ctx.save_for_backward(u, theta, free, present)
        ctx.fit = fit
        return theta.clone()

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor):  # type: ignore[override]
        u, theta, free, present = ctx.saved_tensors
        fit: _Fit = ctx.fit
        B, W, _ = theta.shape
        P = 3 * W
        with torch.enable_grad():
            th = theta.detach().requires_grad_(True)
            uu = u.detach().requires_grad_(True)
            active = free.any(-1)
            loss = fit_loss(fit.rod, th, active, uu, present, fit.step_angle)
            (g,) = torch.autograd.grad(loss.sum(), th, create_graph=True)
            g = g.reshape(B, P)
            rows = [torch.autograd.grad(g[:, j].sum(), th, retain_graph=True)[0].reshape(B, P) for j in range(P)]
            H = torch.stack(rows, dim=1)  # (B, P, P): readings are independent, so each is its own block
            keep = free.reshape(B, P)
            both = keep[:, :, None] & keep[:, None, :]
            eye = torch.eye(P, dtype=H.dtype, device=H.device).expand(B, P, P)
            H = torch.where(both, 0.5 * (H + H.transpose(1, 2)), eye).detach()
            v = torch.where(keep, grad.reshape(B, P).to(H.dtype), 0.0)
            lam = (torch.linalg.pinv(H, hermitian=True) @ v[..., None])[..., 0]
            lam = torch.where(keep, lam, 0.0)
            (gu,) = torch.autograd.grad((g * lam).sum(), uu)
        return -gu, None, None, None, None


def through_optimum(
    rod: Rod,
    u: torch.Tensor,
    present: torch.Tensor,
    s: torch.Tensor,
    f: torch.Tensor,
    active: torch.Tensor,
    step_angle: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The fit (s (B, W) [m] in model coordinates, f (B, W, 2) [N]) at the rod's own stiffness, as differentiable
    functions of the readings ``u`` (B, G, 2) [1/m] (float64, zero at missing gratings, a precurved rod's unloaded
    shape included), with the values the search found (module docstring); ``present``: the (B, G) mask, or the
    (B, G, 2) weights of :func:`fit_loss`."""
    theta = torch.cat([s[..., None], f], dim=-1).detach()
    free = active[..., None] & torch.stack(
        [~on_bound(rod, s.detach()), torch.ones_like(active), torch.ones_like(active)], dim=-1
    )
    out = _Optimum.apply(u, theta, free, present, _Fit(rod, step_angle))
    return out[..., 0], out[..., 1:]
