"""L-BFGS for the fits the Levenberg-Marquardt budget leaves open.

A fit still unconverged after ``LMPolicy.iterations`` steps (a long curved valley, a nearly singular Jacobian) is
handed to the batched L-BFGS of :mod:`.refine` (per-row history, line search and stopping), then analysed again by
the Levenberg-Marquardt policy's own stopping test. Each force stays in its interval through
``s = lo + (hi - lo) (1 + sin z) / 2``: every iterate is feasible, and the curvature pairs L-BFGS records are
exact (a projected step would break them). Forces are ``phi = f / F`` (F = EI / L^2). Losses are scaled by the
start's, so the gradient tolerance is relative. The objective is one evaluation of the fitting model per row
(loss and, as a linear term, its gradient ``J^T r``: no backward pass through the march), and rows are
independent, as :data:`.refine.Objective` requires.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from . import lm
from .problem import Fits, Problem, bounds, evaluate, sided
from .refine import LBFGSOptions, lbfgs

__all__ = ["refine_open"]


def refine_open(problem: Problem, policy: lm.LMPolicy, options: LBFGSOptions, state: lm.LMState) -> lm.LMState:
    """``state`` with its rows that ran out of Levenberg-Marquardt steps (not converged, not stalled) refined by
    L-BFGS and analysed again (their step counts grow by the L-BFGS evaluations)."""
    xp = problem.xp
    open_ = xp.nonzero(~state.converged & (state.steps >= policy.iterations) & (state.damping < policy.max_damping))
    n = open_.shape[0]
    if n == 0 or state.fits.h == 0:
        return state
    part = state.take(xp, open_)
    fits = part.fits
    R, h = fits.s.shape
    lo, hi = bounds(problem, fits)
    width = hi - lo
    device = torch.device("cpu") if xp.name == "numpy" else xp.device

    def to_t(x):
        return xp.to_torch(x, device).to(torch.float64)

    lo_t, width_t = to_t(lo), to_t(width)
    edge = 1e-3  # keep z off +-pi/2, where ds/dz = 0
    frac = ((to_t(fits.s) - lo_t) / torch.where(width_t > 0, width_t, torch.ones_like(width_t))) * 2.0 - 1.0
    z0 = torch.asin(frac.clamp(-1.0, 1.0)).clamp(-math.pi / 2 + edge, math.pi / 2 - edge)
    phi0 = to_t(fits.f) / problem.force_unit
    y0 = torch.cat((z0.unsqueeze(-1), phi0), -1).reshape(R, 3 * h)
    scale = to_t(part.loss).clamp(min=1e-300)

    def unpack(y: torch.Tensor, rows: torch.Tensor) -> tuple[Fits, torch.Tensor]:
        v = y.detach().reshape(-1, h, 3)
        z = v[..., 0]
        s = lo_t[rows] + width_t[rows] * (1.0 + torch.sin(z)) / 2.0
        f = v[..., 1:] * problem.force_unit
        idx = xp.asarray(rows.cpu(), "int")
        sub = fits.take(idx)
        return Fits(sub.reading, xp.asarray(s), xp.asarray(f), sub.interval), torch.cos(z)

    def objective(y: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        sub, cos_z = unpack(y, rows)
        r, J = evaluate(problem, sub)
        J = sided(problem, sub, J)
        loss = to_t((r * r).sum(1))
        g = to_t(xp.einsum("rkp,rk->rp", J, r)).reshape(-1, h, 3)  # d(loss/2)/d(s/L, phi)
        dsdz = width_t[rows] * cos_z / 2.0 / problem.length  # d(s/L)/dz
        g = torch.cat(((g[..., 0] * dsdz).unsqueeze(-1), g[..., 1:]), -1).reshape(-1, 3 * h)
        c = 1.0 / scale[rows]
        loss = torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf))
        return 0.5 * c * loss + ((y - y.detach()) * (c.unsqueeze(1) * g)).sum(-1)

    res = lbfgs(objective, y0, options)
    out, _ = unpack(res.x, torch.arange(R, device=device))
    r, J = evaluate(problem, out)
    loss = (r * r).sum(1)
    better = xp.isfinite(loss) & (loss < part.loss)
    b1, b2 = better[:, None], better[:, None, None]
    moved = dataclasses.replace(
        part,
        fits=Fits(fits.reading, xp.where(b1, out.s, fits.s), xp.where(b2, out.f, fits.f), fits.interval),
        r=xp.where(b1, r, part.r),
        J=xp.where(b2, J, part.J),
        loss=xp.where(better, loss, part.loss),
        steps=part.steps + xp.asarray(res.evaluations.cpu(), "int"),
    )
    return state.put(xp, open_, lm.analyse(problem, policy, moved))
