"""Runge-Kutta-Nystrom marching of the reduced rod equation, batched, with a hand-written discrete adjoint.

The body-frame model (:mod:`torchrod.model.body_frame`) reduces to U'' = g(U) + phi with g(U) = -|U|^2 U / 2 for the
complex curvature U = u_x + i u_y, integrated over t = L - s from the tip. :func:`march` runs K explicit steps per
sample, each sample with its own step lengths, and adds a "kick" to W = dU/dt after each step (the jump at a point
force). Its gradient is the exact gradient of the discrete scheme, computed by a backward sweep over the steps
(the discrete adjoint) rather than by recording every operation, which at small batches costs far more than the
arithmetic. Values are (2, B) real tensors (x and y rows). The adjoint composes with ``torch.func`` (``jacrev``,
``vmap``, ``grad``); it gives first derivatives only, and says so when asked for a second.

``adjoint=False`` records the same scheme under autograd instead: slower, but higher derivatives work.

The methods' tableaus live here, once: the estimator's exact model (:mod:`torchrod.kernels.march`) takes its
coefficients from :data:`RKN8`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
import torch

from ..errors import TorchrodError

__all__ = ["METHODS", "Tableau", "march"]


# ================================================================================================= tableaus
@dataclass(frozen=True)
class Tableau:
    """An explicit Runge-Kutta-Nystrom method for U'' = g(U) (g without U'), s stages, order ``order``:

        Y_i = U + c_i h W + h^2 sum_j a_ij G_j,   U+ = U + h W + h^2 sum_j bp_j G_j,   W+ = W + h sum_j bv_j G_j

    with G_j = g(Y_j). The stored coefficients multiply |Y|^2 Y (the -1/2 of g is folded into a, bp and bv).
    ``fsal``: the last stage is the new position (a_s = bp, c_s = 1), so its G is the next step's first.
    """

    name: str
    order: int
    c: tuple[float, ...]
    a: tuple[tuple[float, ...], ...]  # row i holds a_i0 .. a_i(i-1)
    bp: tuple[float, ...]
    bv: tuple[float, ...]
    fsal: bool
    # Nonzero coefficients as (index, value): a_rows[i] over j < i, a_cols[j] over i > j (for the adjoint).
    a_rows: tuple[tuple[tuple[int, float], ...], ...] = field(init=False, repr=False)
    a_cols: tuple[tuple[tuple[int, float], ...], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        s = len(self.c)
        rows = tuple(tuple((j, x) for j, x in enumerate(row) if x != 0.0) for row in self.a)
        cols = tuple(tuple((i, self.a[i][j]) for i in range(j + 1, s) if self.a[i][j] != 0.0) for j in range(s))
        object.__setattr__(self, "a_rows", rows)
        object.__setattr__(self, "a_cols", cols)

    @property
    def stages(self) -> int:
        return len(self.c)

    @property
    def evaluations(self) -> int:
        """Evaluations of g per step."""
        return self.stages - 1 if self.fsal else self.stages

    def matrix(self) -> np.ndarray:
        """(s, s) strictly lower-triangular a."""
        out = np.zeros((self.stages, self.stages))
        for i, row in enumerate(self.a):
            out[i, : len(row)] = row
        return out


def _tableau(name: str, order: int, c, a, bp, bv, fsal: bool) -> Tableau:
    half = Fraction(-1, 2)  # g(Y) = -|Y|^2 Y / 2

    def scaled(xs):
        return tuple(float(half * Fraction(x)) for x in xs)

    return Tableau(name, order, tuple(float(x) for x in c), tuple(scaled(r) for r in a), scaled(bp), scaled(bv), fsal)


F = Fraction
# The classical three-stage 4th-order method (nodes 0, 1/2, 1).
RKN4 = _tableau(
    "rkn4",
    4,
    (0, F(1, 2), 1),
    ((), (F(1, 8),), (0, F(1, 2))),
    (F(1, 6), F(1, 3), 0),
    (F(1, 6), F(2, 3), F(1, 6)),
    False,
)
# RKN6(4)6FM of Dormand, El-Mikkawy & Prince, "Families of Runge-Kutta-Nystrom formulae", IMA J. Numer. Anal. 7
# (1987) 235-250: six stages, the last one reused by the next step (5 evaluations per step).
RKN6 = _tableau(
    "rkn6",
    6,
    (0, F(1, 10), F(3, 10), F(7, 10), F(17, 25), 1),
    (
        (),
        (F(1, 200),),
        (F(-1, 2200), F(1, 22)),
        (F(637, 6600), F(-7, 110), F(7, 33)),
        (F(225437, 1968750), F(-30073, 281250), F(65569, 281250), F(-9367, 984375)),
        (F(151, 2142), F(5, 116), F(385, 1368), F(55, 168), F(-6250, 28101)),
    ),
    (F(151, 2142), F(5, 116), F(385, 1368), F(55, 168), F(-6250, 28101), 0),
    (F(151, 2142), F(25, 522), F(275, 684), F(275, 252), F(-78125, 112404), F(1, 12)),
    True,
)
# RKN8(6)9FM of the same paper without its ninth stage (that one only serves the embedded error estimate):
# eight evaluations per step.
RKN8 = _tableau(
    "rkn8",
    8,
    (0, F(1, 20), F(1, 10), F(3, 10), F(1, 2), F(7, 10), F(9, 10), 1),
    (
        (),
        (F(1, 800),),
        (F(1, 600), F(1, 300)),
        (F(9, 200), F(-9, 100), F(9, 100)),
        (F(-66701, 197352), F(28325, 32892), F(-2665, 5482), F(2170, 24669)),
        (
            F(227015747, 304251000),
            F(-54897451, 30425100),
            F(12942349, 10141700),
            F(-9499, 304251),
            F(539, 9250),
        ),
        (
            F(-1131891597, 901789000),
            F(41964921, 12882700),
            F(-6663147, 3220675),
            F(270954, 644135),
            F(-108, 5875),
            F(114, 1645),
        ),
        (
            F(13836959, 3667458),
            F(-17731450, 1833729),
            F(1063919505, 156478208),
            F(-33213845, 39119552),
            F(13335, 28544),
            F(-705, 14272),
            F(1645, 57088),
        ),
    ),
    (F(223, 7938), 0, F(1175, 8064), F(925, 6048), F(41, 448), F(925, 14112), F(1175, 72576), 0),
    (
        F(223, 7938),
        0,
        F(5875, 36288),
        F(4625, 21168),
        F(41, 224),
        F(4625, 21168),
        F(5875, 36288),
        F(223, 7938),
    ),
    False,
)
del F

METHODS: dict[str, Tableau] = {t.name: t for t in (RKN4, RKN6, RKN8)}
"""The methods by name: "rkn4", "rkn6", "rkn8" (orders 4, 6, 8)."""


# ================================================================================================= the scheme
# On (2, B) real tensors (x and y rows), every operation a plain torch operation, nothing written in place: the same
# code runs recorded by autograd (``adjoint=False``), inside the adjoint's forward, and under torch.func.vmap.


def _sq_rows(y: torch.Tensor) -> torch.Tensor:
    return (y * y).sum(0)


def _combine(pairs, values: list, like: torch.Tensor) -> torch.Tensor:
    """sum of coefficient * values[index] over (index, coefficient) ``pairs`` (zeros like ``like`` if none)."""
    terms = [a * values[j] for j, a in pairs if a != 0.0]
    return sum(terms[1:], terms[0]) if terms else torch.zeros_like(like)


def _forward(tab: Tableau, zero, hs, kicks, forcing, record: list | None = None):
    """Steps k = 0..K-1 from U = W = ``zero``; after step k, W += kicks[k] (``kicks`` None: no kick).

    ``forcing`` (or None): K + 1 values at the step boundaries, in stage units, linear within a step: stage i of
    step k is |Y|^2 Y + P_k + c_i (P_k+1 - P_k). ``record`` (a list, or None): per step, what the discrete adjoint
    needs, (W, Y (s, 2, B), |Y|^2 (s, B), acc (s, 2, B), accp, accv), appended.
    Returns the lists of U and W after each step (post-kick).
    """
    s = tab.stages
    c, rows, bp, bv = tab.c, tab.a_rows, tab.bp, tab.bv
    U = W = zero
    Us, Ws = [], []
    carried = None
    for k in range(len(hs)):
        h = hs[k]
        h2 = h * h
        hW = h * W
        r0 = _sq_rows(U) if carried is None else carried[1]
        G0 = r0 * U if carried is None else carried[0]
        if forcing is not None:
            p0 = forcing[k]
            pd = forcing[k + 1] - p0
            G0 = G0 + p0
        Ys, rs, accs, Gs = [U], [r0], [torch.zeros_like(U)], [G0]
        for i in range(1, s):
            acc = _combine(rows[i], Gs, U)
            Y = U + c[i] * hW + h2 * acc
            r = _sq_rows(Y)
            G = r * Y
            if tab.fsal and i == s - 1:
                carried = (G, r)  # the next step's first stage: Y_s is the new U
            if forcing is not None:
                G = G + (p0 + c[i] * pd)
            Ys.append(Y)
            rs.append(r)
            accs.append(acc)
            Gs.append(G)
        accv = _combine(enumerate(bv), Gs, U)
        W_new = W + h * accv
        if tab.fsal:
            U_new, accp = Ys[-1], accs[-1]
        else:
            accp = _combine(enumerate(bp), Gs, U)
            U_new = U + hW + h2 * accp
        if record is not None:
            record.append((W, torch.stack(Ys), torch.stack(rs), torch.stack(accs), accp, accv))
        if kicks is not None:
            W_new = W_new + kicks[k]
        U, W = U_new, W_new
        Us.append(U)
        Ws.append(W)
    return Us, Ws


def _backward(tab: Tableau, hs, saved, gZ, forcing: bool):
    """The discrete adjoint of :func:`_forward`: ``saved`` its record stacked over the steps, gZ (K, 4, B) the
    gradients w.r.t. each step's (post-kick) U and W. Per step (the forward recurrences read backwards): with Ub, Wb
    the adjoints of U+, W+ and Gb_i those of G_i,

        Gb_i = h^2 bp_i Ub + h bv_i Wb + h^2 sum_{j > i} a_ji Yb_j,   Yb_i = J(Y_i) Gb_i,
        J(Y) v = |Y|^2 v + 2 (Y . v) Y   (the symmetric Jacobian of |Y|^2 Y),
        Ub <- Ub + sum_i Yb_i,   Wb <- Wb + h (Ub + sum_i c_i Yb_i),
        hb = (Ub + sum_i c_i Yb_i) . W + Wb . accv + 2 h (Ub . accp + sum_i Yb_i . acc_i).

    Returns hb (K, B), the kick gradients (K, 2, B) and, with ``forcing``, the forcing gradients (K + 1, 2, B), else
    None.
    """
    W_all, Y_all, r_all, acc_all, accp_all, accv_all = saved
    K = hs.shape[0]
    s = tab.stages
    c = tab.c
    last_used = max(i for i in range(s) if tab.bp[i] != 0.0 or tab.bv[i] != 0.0 or tab.a_cols[i])
    zero = torch.zeros_like(gZ[0, :2])
    hb, kb = [zero[0]] * K, [zero] * K
    Pb = [zero] * (K + 1)
    Ub = Wb = zero
    for k in range(K - 1, -1, -1):
        Ub = Ub + gZ[k, :2]
        Wb = Wb + gZ[k, 2:]
        kb[k] = Wb
        W, Y, r, acc, accp, accv = W_all[k], Y_all[k], r_all[k], acc_all[k], accp_all[k], accv_all[k]
        h = hs[k]
        h2 = h * h
        Yb = [zero] * s
        Gb = [zero] * s
        for i in range(last_used, -1, -1):
            g = tab.bp[i] * (h2 * Ub) + tab.bv[i] * (h * Wb)
            if tab.a_cols[i]:
                g = g + h2 * _combine(tab.a_cols[i], Yb, zero)
            Gb[i] = g
            d = (Y[i] * g).sum(0)
            Yb[i] = r[i] * g + (d + d) * Y[i]
        if forcing:  # stage forcing P_k (1 - c_i) + P_k+1 c_i
            towards_end = _combine(enumerate(c), Gb, zero)
            Pb[k + 1] = Pb[k + 1] + towards_end
            Pb[k] = Pb[k] + (sum(Gb[1:], Gb[0]) - towards_end)
        S = Ub + _combine(enumerate(c), Yb, zero)
        inner = (Ub * accp).sum(0) + sum(((Yb[i] * acc[i]).sum(0) for i in range(s)), zero[0])
        hb[k] = (S * W).sum(0) + (Wb * accv).sum(0) + (h + h) * inner
        Ub = Ub + sum(Yb[1:], Yb[0])
        Wb = Wb + h * S
    return torch.stack(hb), torch.stack(kb), torch.stack(Pb) if forcing else None


def _rows(t: torch.Tensor | None) -> torch.Tensor | None:
    """(B, n, 2) -> (n, 2, B): the scheme's layout."""
    return None if t is None else t.permute(1, 2, 0)


# ================================================================================================= autograd
class _March(torch.autograd.Function):
    """Z = march(h, kick, forcing) with the discrete adjoint as its backward. Written for torch.func: a forward
    without ``ctx`` that returns what the backward needs as extra (non-differentiable) outputs, and a vmap rule
    generated from its plain torch operations, so ``jacrev``, ``vmap`` and ``grad`` compose with it."""

    generate_vmap_rule = True

    @staticmethod
    def forward(h, kick, forcing, tab):  # type: ignore[override]
        record: list = []
        Us, Ws = _forward(tab, h.new_zeros(2, h.shape[0]), h.t(), _rows(kick), _rows(forcing), record)
        Z = torch.cat((torch.stack(Us), torch.stack(Ws)), dim=1).permute(2, 0, 1)  # (B, K, 4)
        saved = tuple(torch.stack(part) for part in zip(*record, strict=True))
        return (Z, *saved)

    @staticmethod
    def setup_context(ctx, inputs, output):  # type: ignore[override]
        h, kick, forcing, tab = inputs
        _, *saved = output
        ctx.mark_non_differentiable(*saved)
        ctx.save_for_backward(h, *saved)
        ctx.tab, ctx.kick, ctx.forcing = tab, kick is not None, forcing is not None

    @staticmethod
    def backward(ctx, gZ, *_):  # type: ignore[override]
        if torch.is_grad_enabled() and not _inside_torch_func():
            raise TorchrodError(
                "the forward model's discrete adjoint gives first derivatives only: for second derivatives "
                "(create_graph=True, a Hessian) simulate with adjoint=False"
            )
        h, *saved = ctx.saved_tensors
        hb, kb, Pb = _backward(ctx.tab, h.t(), saved, gZ.permute(1, 2, 0), ctx.forcing)

        def back(x: torch.Tensor) -> torch.Tensor:
            return x.permute(2, 0, 1)  # (n, 2, B) -> (B, n, 2)

        return hb.t(), back(kb) if ctx.kick else None, back(Pb) if ctx.forcing and Pb is not None else None, None


def _inside_torch_func() -> bool:
    """Whether a torch.func transform is running (its backward passes run with grad mode on, as a second
    derivative would)."""
    try:
        return torch._C._functorch.peek_interpreter_stack() is not None
    except AttributeError:  # an older torch without the interpreter stack
        return False


def march(
    h: torch.Tensor,
    tab: Tableau,
    *,
    kick: torch.Tensor | None = None,
    forcing: torch.Tensor | None = None,
    adjoint: bool = True,
) -> torch.Tensor:
    """Integrate U'' = -|U|^2 U / 2 (+ forcing) from U = W = 0 over K steps per sample, differentiably.

    Args:
        h: (B, K) step lengths [m] (zero: the step does nothing).
        tab: the method (:data:`METHODS`).
        kick: (B, K, 2) added to W = dU/dt after each step [1/m^2], or None.
        forcing: (B, K + 1, 2) values P of a forcing at the step boundaries, linear within each step, in units
            of the stage value |U|^2 U [1/m^3], so that U'' = -(|U|^2 U + P) / 2; or None.
        adjoint: gradients from the discrete adjoint (default: first derivatives, and torch.func transforms) or
            from autograd through every operation (higher derivatives too).
    Returns:
        (B, K, 4): (U_x, U_y, W_x, W_y) after each step and its kick.
    """
    B, K = h.shape
    if B == 0 or K == 0:
        keep = sum(0.0 * t.sum() for t in (h, kick, forcing) if t is not None)  # an empty result in the graph
        return h.new_zeros(B, K, 4) + keep
    inputs = (h, kick, forcing)
    if adjoint and torch.is_grad_enabled() and (_inside_torch_func() or any(
            t is not None and t.requires_grad for t in inputs)):  # fmt: skip
        return _March.apply(h, kick, forcing, tab)[0]
    Us, Ws = _forward(tab, h.new_zeros(2, B), h.t(), _rows(kick), _rows(forcing))
    return torch.cat((torch.stack(Us), torch.stack(Ws)), dim=1).permute(2, 0, 1)
