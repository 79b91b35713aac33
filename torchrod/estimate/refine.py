"""Batched L-BFGS with per-sample history, line search and stopping.

``torch.optim.LBFGS`` treats all parameters as one vector: a batch of readings fitted together shares one curvature
history, one step length and one stopping test, so one hard reading stalls (or distorts) all the others. :func:`lbfgs`
runs B independent L-BFGS solves in lockstep instead:

* per-sample history: the curvature pairs (s, y) live in (B, m, P) tensors with a (B, m) validity mask, shifted per
  sample when that sample accepts a pair (a pair is skipped when y.s <= 1e-10, as torch does);
* per-sample two-loop recursion and initial Hessian scale H_diag = y.s / y.y;
* per-sample strong-Wolfe line search (bracketing, then zoom with safeguarded cubic interpolation), each sample in its
  own phase of it;
* per-sample stopping: gradient tolerance, change tolerances, ``max_iter`` and ``max_eval``.

Every round evaluates the objective ONCE, batched, at the trial points of all samples still running; finished samples
are frozen and neither evaluated nor counted. The decisions mirror ``torch.optim.LBFGS(line_search_fn="strong_wolfe")``
one for one (its defaults, its first step ``min(1, 1/|g|_1) * lr``, its ``max_ls = max_eval - evaluations so far``,
its quirks in the line search), so a batch of one follows torch's iterates to rounding (see tests/test_refine.py).

Differences from torch, all outside its well-defined behaviour: a trial point whose loss or gradient is not finite is
treated as a loss of +inf (the line search backs off instead of propagating NaN); a cubic interpolation that is not
finite falls back to bisection; a sample whose starting loss or gradient is not finite stops at once, unconverged.
Losses stay in the dtype of ``x0`` (torch converts them to Python floats).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LBFGSOptions", "Objective", "RefineResult", "lbfgs"]

Objective = Callable[[Tensor, Tensor], Tensor]
"""``fun(x, rows) -> loss``: x (b, P) the rows being evaluated, rows (b,) long their indices in the original batch,
loss (b,) one loss per row. Rows must be independent (loss[i] depends on x[i] only)."""

_C1 = 1e-4  # sufficient decrease (Armijo), torch's default
_C2 = 0.9  # curvature condition, torch's default
_CURVATURE_EPS = 1e-10  # a pair with y.s <= this is skipped, as in torch


@dataclass(frozen=True)
class LBFGSOptions:
    """Settings of :func:`lbfgs`, with ``torch.optim.LBFGS``'s meanings (per sample).

    Attributes:
        max_iter: at most this many iterations (line searches) per sample.
        history_size: number m of curvature pairs kept per sample.
        lr: initial trial step of each line search (the first iteration uses ``min(1, 1/|g|_1) * lr``).
        tolerance_grad: stop when max |g| <= this (converged).
        tolerance_change: stop when the step's max |t d| <= this, when the loss changes by less than this, or when
            the directional derivative g.d > -this (converged).
        max_eval: at most this many evaluations per sample (default ``max_iter * 5 // 4``, like torch).
    """

    max_iter: int = 100
    history_size: int = 10
    lr: float = 1.0
    tolerance_grad: float = 1e-7
    tolerance_change: float = 1e-9
    max_eval: int | None = None

    def __post_init__(self) -> None:
        for name in ("max_iter", "history_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if self.max_eval is not None and (not isinstance(self.max_eval, int) or self.max_eval < 1):
            raise ValueError(f"max_eval must be an integer >= 1 or None, got {self.max_eval!r}")
        if not float(self.lr) > 0.0:
            raise ValueError(f"lr must be positive, got {self.lr!r}")
        for name in ("tolerance_grad", "tolerance_change"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    @property
    def evaluations_limit(self) -> int:
        """``max_eval``, or its default ``max_iter * 5 // 4``."""
        return self.max_eval if self.max_eval is not None else self.max_iter * 5 // 4


@dataclass(frozen=True)
class RefineResult:
    """The result of :func:`lbfgs`, per sample.

    Attributes:
        x: (B, P) the solution (the last accepted iterate).
        loss: (B,) the loss at ``x``.
        grad: (B, P) the gradient at ``x``.
        converged: (B,) bool: stopped by a tolerance (gradient, or a change tolerance before the iteration and
            evaluation limits ran out), not by ``max_iter`` / ``max_eval`` or a non-finite start.
        iterations: (B,) long, iterations counted as torch does (the last, aborted one included).
        evaluations: (B,) long, objective evaluations of that sample (the start included).
    """

    x: Tensor
    loss: Tensor
    grad: Tensor
    converged: Tensor
    iterations: Tensor
    evaluations: Tensor


def _evaluate(fun: Objective, x: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
    """Loss (b,) and gradient (b, P) of ``fun`` at the rows ``x`` (b, P), by autograd of the summed loss."""
    with torch.enable_grad():
        xr = x.detach().requires_grad_(True)
        loss = fun(xr, rows)
        if not isinstance(loss, Tensor) or loss.shape != (x.shape[0],):
            shape = tuple(loss.shape) if isinstance(loss, Tensor) else type(loss).__name__
            raise ValueError(f"fun(x, rows) must return per-row losses of shape ({x.shape[0]},), got {shape}")
        if loss.requires_grad:
            (grad,) = torch.autograd.grad(loss.sum(), xr, allow_unused=True)
        else:
            grad = None
    if grad is None:
        grad = torch.zeros_like(x)
    return loss.detach().to(x.dtype), grad.detach()


def _cubic_min(
    x1: Tensor, f1: Tensor, g1: Tensor, x2: Tensor, f2: Tensor, g2: Tensor, lo: Tensor, hi: Tensor
) -> Tensor:
    """Minimiser of the cubic through (x1, f1, g1) and (x2, f2, g2), kept in [lo, hi]; midpoint if it has none.

    The same formula and safeguards as torch's ``_cubic_interpolate``, elementwise; a non-finite result (an infinite
    loss at one end) falls back to the midpoint as well.
    """
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1**2 - g1 * g2
    d2 = d2_square.clamp(min=0).sqrt()
    min_pos = torch.where(
        x1 <= x2,
        x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2)),
        x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2)),
    )
    clipped = torch.minimum(torch.maximum(min_pos, lo), hi)
    ok = (d2_square >= 0) & torch.isfinite(clipped)
    return torch.where(ok, clipped, (lo + hi) / 2.0)


def _pick(pair: Tensor, index: Tensor) -> Tensor:
    """pair (B, 2) or (B, 2, P) at index (B,) in {0, 1}."""
    if pair.dim() == 2:
        return pair.gather(1, index.unsqueeze(1)).squeeze(1)
    return pair.gather(1, index.view(-1, 1, 1).expand(-1, 1, pair.shape[2])).squeeze(1)


def _put(pair: Tensor, index: Tensor, mask: Tensor, value: Tensor) -> Tensor:
    """pair with pair[b, index[b]] = value[b] where mask[b]."""
    slot = (torch.arange(2, device=pair.device) == index.unsqueeze(1)) & mask.unsqueeze(1)  # (B, 2)
    if pair.dim() == 2:
        return torch.where(slot, value.unsqueeze(1), pair)
    return torch.where(slot.unsqueeze(2), value.unsqueeze(1), pair)


def _shift(history: Tensor, new: Tensor, mask: Tensor) -> Tensor:
    """history (B, m, ...) with, where mask (B,), the oldest entry dropped and ``new`` (B, ...) appended."""
    shifted = torch.cat((history[:, 1:], new.unsqueeze(1)), 1)
    return torch.where(mask.view(-1, *([1] * (history.dim() - 1))), shifted, history)


def _direction(g: Tensor, hs: Tensor, hy: Tensor, rho: Tensor, valid: Tensor, h_diag: Tensor) -> Tensor:
    """Two-loop recursion per sample: -H g with the valid pairs of each sample (oldest first along dim 1)."""
    m = hs.shape[1]
    q = -g
    alpha = []
    for i in range(m - 1, -1, -1):
        a = torch.where(valid[:, i], (hs[:, i] * q).sum(1) * rho[:, i], torch.zeros_like(rho[:, i]))
        q = q - a.unsqueeze(1) * hy[:, i]
        alpha.append(a)
    alpha.reverse()
    r = q * h_diag.unsqueeze(1)
    for i in range(m):
        be = (hy[:, i] * r).sum(1) * rho[:, i]
        coef = torch.where(valid[:, i], alpha[i] - be, torch.zeros_like(be))
        r = r + coef.unsqueeze(1) * hs[:, i]
    return r


def lbfgs(fun: Objective, x0: Tensor, options: LBFGSOptions = LBFGSOptions()) -> RefineResult:
    """Minimise B independent objectives with L-BFGS and a strong-Wolfe line search, each sample on its own.

    Args:
        fun: ``fun(x, rows) -> loss``: x (b, P) the rows being evaluated (a subset of the batch: finished samples
            are not evaluated), rows (b,) long their indices in ``x0``'s batch (so ``fun`` can pick the data of
            those rows, e.g. ``readings[rows]``), loss (b,) per-row losses. Rows must be independent; gradients
            come from autograd of ``loss.sum()``. Called once per round, for all running samples together.
        x0: (B, P) starting points (floating point); the result has its dtype and device.
        options: :class:`LBFGSOptions` (per-sample limits and tolerances, torch's meanings).
    Returns:
        :class:`RefineResult` with per-sample solution, loss, gradient, convergence flag and counts.
    """
    if not isinstance(x0, Tensor):
        raise TypeError(f"x0 must be a tensor, got {type(x0).__name__}")
    if x0.dim() != 2 or x0.shape[0] == 0 or x0.shape[1] == 0:
        raise ValueError(f"x0 must have shape (B, P) with B, P >= 1, got {tuple(x0.shape)}")
    if not x0.is_floating_point():
        raise TypeError(f"x0 must be floating point, got {x0.dtype}")
    if not isinstance(options, LBFGSOptions):
        raise TypeError(f"options must be LBFGSOptions, got {type(options).__name__}")

    B, P = x0.shape
    m = options.history_size
    dtype, device = x0.dtype, x0.device
    tol_grad, tol_change, lr = options.tolerance_grad, options.tolerance_change, float(options.lr)
    max_iter, max_eval = options.max_iter, options.evaluations_limit

    def zeros(*shape: int, kind: torch.dtype = dtype) -> Tensor:
        return torch.zeros(*shape, dtype=kind, device=device)

    def w(mask: Tensor, new: Tensor, old: Tensor) -> Tensor:
        """where(mask) broadcast over trailing dimensions."""
        return torch.where(mask.view(-1, *([1] * (new.dim() - 1))), new, old)

    everyone = torch.arange(B, device=device)
    x = x0.detach().clone()
    f, g = _evaluate(fun, x, everyone)
    evals = torch.ones(B, dtype=torch.long, device=device)
    n_iter = zeros(B, kind=torch.long)
    finite = torch.isfinite(f) & torch.isfinite(g).all(1)
    converged = finite & (g.abs().amax(1) <= tol_grad)
    stopped = converged | ~finite

    # Per-sample L-BFGS memory: pairs oldest first along dim 1, invalid slots at the front.
    hist_s, hist_y, rho = zeros(B, m, P), zeros(B, m, P), zeros(B, m)
    valid = zeros(B, m, kind=torch.bool)
    h_diag = torch.ones(B, dtype=dtype, device=device)
    d, last_step = zeros(B, P), zeros(B, P)
    prev_g, prev_f = g.clone(), f.clone()
    # Line-search state: trial step t; bracketing (phase 0) keeps the previous trial, zoom (phase 1) a bracket.
    t = zeros(B)
    gtd0, d_norm = zeros(B), zeros(B)
    ls_iter, max_ls = zeros(B, kind=torch.long), zeros(B, kind=torch.long)
    zoom = zeros(B, kind=torch.bool)
    ls_done = zeros(B, kind=torch.bool)
    insuf = zeros(B, kind=torch.bool)
    t_prev, f_prev, gtd_prev, g_prev = zeros(B), zeros(B), zeros(B), zeros(B, P)
    bt, bf, bgtd, bg = zeros(B, 2), zeros(B, 2), zeros(B, 2), zeros(B, 2, P)
    low = zeros(B, kind=torch.long)
    need_direction = ~stopped

    while True:
        # ---- new iterations: memory update, two-loop direction, first trial step (torch's step(), loop top)
        if bool(need_direction.any()):
            M = need_direction
            first = n_iter == 0
            n_iter = n_iter + M.long()
            y = g - prev_g
            ys = (y * last_step).sum(1)
            accept = M & ~first & (ys > _CURVATURE_EPS)
            hist_s, hist_y = _shift(hist_s, last_step, accept), _shift(hist_y, y, accept)
            rho = _shift(rho, 1.0 / ys, accept)
            valid = _shift(valid, torch.ones_like(accept), accept)
            h_diag = torch.where(accept, ys / (y * y).sum(1), h_diag)
            d = w(M, _direction(g, hist_s, hist_y, rho, valid, h_diag), d)
            prev_g, prev_f = w(M, g, prev_g), torch.where(M, f, prev_f)
            t_first = torch.clamp(1.0 / g.abs().sum(1), max=1.0) * lr
            t = torch.where(M, torch.where(first, t_first, torch.full_like(t, lr)), t)
            gtd = (g * d).sum(1)
            flat = M & (gtd > -tol_change)  # no descent left: a change tolerance
            stopped, converged = stopped | flat, converged | flat
            S = M & ~flat  # start a line search
            gtd0 = torch.where(S, gtd, gtd0)
            d_norm = torch.where(S, d.abs().amax(1), d_norm)
            max_ls = torch.where(S, max_eval - evals, max_ls)
            ls_iter = torch.where(S, torch.zeros_like(ls_iter), ls_iter)
            zoom, ls_done, insuf = zoom & ~S, ls_done & ~S, insuf & ~S
            t_prev = torch.where(S, torch.zeros_like(t_prev), t_prev)
            f_prev, gtd_prev, g_prev = (
                torch.where(S, f, f_prev),
                torch.where(S, gtd, gtd_prev),
                w(S, g, g_prev),
            )
            need_direction = torch.zeros_like(need_direction)

        active = ~stopped
        if not bool(active.any()):
            break

        # ---- one batched evaluation at x + t d of every running sample
        rows = active.nonzero().squeeze(1)
        f_rows, g_rows = _evaluate(fun, x[rows] + t[rows].unsqueeze(1) * d[rows], rows)
        f_new = zeros(B).index_copy(0, rows, f_rows)
        g_new = zeros(B, P).index_copy(0, rows, g_rows)
        evals = evals + active.long()
        bad = ~(torch.isfinite(f_new) & torch.isfinite(g_new).all(1))
        f_new = torch.where(bad, torch.full_like(f_new, float("inf")), f_new)
        gtd_new = (g_new * d).sum(1)
        armijo = f + _C1 * t * gtd0
        curvature_ok = gtd_new.abs() <= -_C2 * gtd0

        # ---- zoom phase: the new point replaces an end of the bracket (torch's _strong_wolfe, zoom loop body)
        Z = active & zoom
        f_low = _pick(bf, low)
        high = 1 - low
        to_high = Z & ((f_new > armijo) | (f_new >= f_low))
        to_low = Z & ~to_high
        bt, bf = _put(bt, high, to_high, t), _put(bf, high, to_high, f_new)
        bgtd, bg = _put(bgtd, high, to_high, gtd_new), _put(bg, high, to_high, g_new)
        wolfe = to_low & curvature_ok
        swap = to_low & ~curvature_ok & (gtd_new * (_pick(bt, high) - _pick(bt, low)) >= 0)
        bt, bf = _put(bt, high, swap, _pick(bt, low)), _put(bf, high, swap, _pick(bf, low))
        bgtd, bg = _put(bgtd, high, swap, _pick(bgtd, low)), _put(bg, high, swap, _pick(bg, low))
        bt, bf = _put(bt, low, to_low, t), _put(bf, low, to_low, f_new)
        bgtd, bg = _put(bgtd, low, to_low, gtd_new), _put(bg, low, to_low, g_new)
        low = torch.where(to_high, (bf[:, 0] > bf[:, 1]).long(), low)
        ls_done = ls_done | wolfe

        # ---- bracketing phase (torch's _strong_wolfe, first loop)
        Br = active & ~zoom
        within = ls_iter < max_ls
        fail = (f_new > armijo) | ((ls_iter > 1) & (f_new >= f_prev))
        cond_a = Br & within & fail
        cond_b = Br & within & ~fail & curvature_ok
        cond_c = Br & within & ~fail & ~curvature_ok & (gtd_new >= 0)
        extend = Br & within & ~(cond_a | cond_b | cond_c)
        out_of_evals = Br & ~within
        bracket = cond_a | cond_c  # [t_prev, t]
        start = torch.stack((torch.where(out_of_evals, torch.zeros_like(t), t_prev), t), 1)
        start_f = torch.stack((torch.where(out_of_evals, f, f_prev), f_new), 1)
        start_gtd = torch.stack((torch.where(out_of_evals, gtd0, gtd_prev), gtd_new), 1)
        start_g = torch.stack((w(out_of_evals, g, g_prev), g_new), 1)
        opened = bracket | out_of_evals
        bt, bf, bgtd, bg = (
            w(opened, start, bt),
            w(opened, start_f, bf),
            w(opened, start_gtd, bgtd),
            w(opened, start_g, bg),
        )
        low = torch.where(opened, (bf[:, 0] > bf[:, 1]).long(), low)
        insuf = insuf & ~opened
        # the strong Wolfe conditions hold at t: a one-point bracket
        bt, bf = _put(bt, torch.zeros_like(low), cond_b, t), _put(bf, torch.zeros_like(low), cond_b, f_new)
        bg = _put(bg, torch.zeros_like(low), cond_b, g_new)
        low = torch.where(cond_b, torch.zeros_like(low), low)
        zoom = zoom | opened | cond_b
        ls_done = ls_done | cond_b
        # extrapolate: cubic step in [t + 0.01 (t - t_prev), 10 t]
        t_ext = _cubic_min(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, t + 0.01 * (t - t_prev), t * 10)
        t_prev, f_prev = torch.where(extend, t, t_prev), torch.where(extend, f_new, f_prev)
        gtd_prev, g_prev = torch.where(extend, gtd_new, gtd_prev), w(extend, g_new, g_prev)
        t = torch.where(extend, t_ext, t)
        ls_iter = ls_iter + extend.long()

        # ---- zoom: next trial inside the bracket, or the line search ends
        Zp = active & zoom & ~ls_done
        lo_b, hi_b = bt.amin(1), bt.amax(1)
        ends = Zp & (((bt[:, 1] - bt[:, 0]).abs() * d_norm < tol_change) | (ls_iter >= max_ls))
        ls_done = ls_done | ends
        Zp = Zp & ~ends
        t_zoom = _cubic_min(bt[:, 0], bf[:, 0], bgtd[:, 0], bt[:, 1], bf[:, 1], bgtd[:, 1], lo_b, hi_b)
        eps = 0.1 * (hi_b - lo_b)
        near = torch.minimum(hi_b - t_zoom, t_zoom - lo_b) < eps
        move = near & (insuf | (t_zoom >= hi_b) | (t_zoom <= lo_b))
        moved = torch.where((t_zoom - hi_b).abs() < (t_zoom - lo_b).abs(), hi_b - eps, lo_b + eps)
        t = torch.where(Zp, torch.where(move, moved, t_zoom), t)
        insuf = torch.where(Zp, near & ~move, insuf)
        ls_iter = ls_iter + Zp.long()

        # ---- finished line searches: take the step, test for stopping (torch's step(), loop bottom)
        F = active & ls_done
        if bool(F.any()):
            t_res = _pick(bt, low)
            step = t_res.unsqueeze(1) * d
            x = w(F, x + step, x)
            last_step = w(F, step, last_step)
            f, g = torch.where(F, _pick(bf, low), f), w(F, _pick(bg, low), g)
            optimal = g.abs().amax(1) <= tol_grad
            small = (step.abs().amax(1) <= tol_change) | ((f - prev_f).abs() < tol_change)
            limit = (n_iter >= max_iter) | (evals >= max_eval)
            stop = F & (limit | optimal | small)
            converged = converged | (F & (optimal | (small & ~limit)))
            stopped = stopped | stop
            need_direction = F & ~stop
            zoom, ls_done = zoom & ~F, ls_done & ~F

    return RefineResult(x=x, loss=f, grad=g, converged=converged, iterations=n_iter, evaluations=evals)
