"""Runge-Kutta-Nystrom marching of the reduced rod equation, batched, with a hand-written discrete adjoint.

The body-frame model (:mod:`torchrod.body_frame`) reduces to U'' = g(U) + phi with g(U) = -|U|^2 U / 2 for the
complex curvature U = u_x + i u_y, integrated over t = L - s from the tip. :func:`march` runs K explicit steps per
sample, each sample with its own step lengths, and adds a "kick" to W = dU/dt after each step (the jump at a point
force). Its gradient is the exact gradient of the discrete scheme, computed by a backward sweep over the steps
(the discrete adjoint) rather than by recording every operation, which at small batches costs far more than the
arithmetic.

Three interchangeable implementations of one scheme:

* ``"scalar"``: one sample at a time on Python complex numbers; the fastest for a batch of a few on the CPU.
* ``"numpy"`` / ``"torch"``: the batch at once, a value as a (2, B) real array (x and y rows), the stages of a step
  in an (s, 2, B) buffer combined by matrix products; NumPy on the CPU, torch elsewhere (CUDA).
* ``adjoint=False``: the scalar kernel's code run on (2, B) torch tensors under autograd: slower, but every
  operation is a torch operation, so ``torch.func`` transforms and higher derivatives work.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np
import torch

__all__ = ["METHODS", "Tableau", "march"]

# A batch at most this large runs on Python numbers: NumPy costs ~1-3 us per operation on small arrays, which a
# per-sample loop of Python arithmetic beats up to about 10 samples (measured on the forward model, B = 1..12).
SCALAR_MAX_BATCH = 8


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


# ================================================================================================= generic kernel
# Works on any values supporting + and * (by a float or by a per-sample h): Python complex numbers, or (2, B) real
# tensors. ``sq(Y)`` is |Y|^2 and ``dot(a, b)`` the real inner product of a and b, per sample.


def _sq_complex(y: complex) -> float:
    return y.real * y.real + y.imag * y.imag


def _dot_complex(a: complex, b: complex) -> float:
    return a.real * b.real + a.imag * b.imag


def _sq_rows(y: Any) -> Any:
    return (y * y).sum(0)


def _forward_generic(tab: Tableau, zero, hs, h2s, kicks, forcing, sq: Callable, save: bool):
    """Steps k = 0..K-1 from U = W = ``zero``; after step k, W += kicks[k] (``kicks`` or an entry None: no kick).

    ``forcing`` (or None): K + 1 values at the step boundaries, in stage units, linear within a step: stage i of
    step k is |Y|^2 Y + P_k + c_i (P_k+1 - P_k).
    Returns the lists of U and W after each step (post-kick) and, with ``save``, what the adjoint needs.
    """
    s = tab.stages
    c, rows, bp, bv = tab.c, tab.a_rows, tab.bp, tab.bv
    U = W = zero
    Us, Ws, saved = [], [], []
    carried = None
    for k in range(len(hs)):
        h, h2 = hs[k], h2s[k]
        hW = h * W
        if carried is None:
            r = sq(U)
            G0, r0 = r * U, r
        else:
            G0, r0 = carried
        if forcing is not None:
            p0 = forcing[k]
            pd = forcing[k + 1] - p0
            G0 = G0 + p0
        Ys, rs, accs, Gs = [U], [r0], [None], [G0]
        for i in range(1, s):
            acc = None
            for j, a in rows[i]:
                acc = a * Gs[j] if acc is None else acc + a * Gs[j]
            Y = U + c[i] * hW + h2 * acc
            r = sq(Y)
            G = r * Y
            if tab.fsal and i == s - 1:
                carried = (G, r)  # the next step's first stage: Y_s is the new U
            if forcing is not None:
                G = G + (p0 + c[i] * pd)
            Ys.append(Y)
            rs.append(r)
            accs.append(acc)
            Gs.append(G)
        accv = None
        for j in range(s):
            if bv[j] != 0.0:
                accv = bv[j] * Gs[j] if accv is None else accv + bv[j] * Gs[j]
        W_new = W + h * accv
        if tab.fsal:
            U_new, accp = Ys[-1], accs[-1]
        else:
            accp = None
            for j in range(s):
                if bp[j] != 0.0:
                    accp = bp[j] * Gs[j] if accp is None else accp + bp[j] * Gs[j]
            U_new = U + hW + h2 * accp
        if save:
            saved.append((W, Ys, rs, accs, accp, accv))
        if kicks is not None and kicks[k] is not None:
            W_new = W_new + kicks[k]
        U, W = U_new, W_new
        Us.append(U)
        Ws.append(W)
    return Us, Ws, saved


def _backward_generic(tab: Tableau, saved, hs, h2s, gUs, gWs, forcing: bool, dot: Callable):
    """The discrete adjoint of :func:`_forward_generic`: gradients of a loss with respect to each step's h, kick
    and forcing, given its gradients with respect to each (post-kick) U and W. A value's gradient is stored like
    the value: the partial derivatives with respect to its x and y parts as x and y parts. Returns the lists
    of gradients for h, the kicks and (with ``forcing``, K + 1 entries) the forcing values.

    Per step (the forward recurrences read backwards): with Ub, Wb the adjoints of U+, W+ and Gb_i those of G_i,
        Gb_i = h^2 bp_i Ub + h bv_i Wb + h^2 sum_{j > i} a_ji Yb_j,   Yb_i = J(Y_i) Gb_i,
        J(Y) v = |Y|^2 v + 2 (Y . v) Y   (the symmetric Jacobian of |Y|^2 Y),
        Ub <- Ub + sum_i Yb_i,   Wb <- Wb + h (Ub + sum_i c_i Yb_i),
        hb = (Ub + sum_i c_i Yb_i) . W + Wb . accv + 2 h (Ub . accp + sum_i Yb_i . acc_i).
    """
    s = tab.stages
    c, cols, bp, bv = tab.c, tab.a_cols, tab.bp, tab.bv
    K = len(saved)
    hb, kb = [None] * K, [None] * K
    Pb = [None] * (K + 1) if forcing else None
    Ub = Wb = None
    for k in range(K - 1, -1, -1):
        Ub = gUs[k] if Ub is None else Ub + gUs[k]
        Wb = gWs[k] if Wb is None else Wb + gWs[k]
        kb[k] = Wb
        W, Ys, rs, accs, accp, accv = saved[k]
        h, h2 = hs[k], h2s[k]
        h2Ub, hWb = h2 * Ub, h * Wb
        Yb: list[Any] = [None] * s
        sum0 = sumd = None
        for i in range(s - 1, -1, -1):
            gb = None
            if bp[i] != 0.0:
                gb = bp[i] * h2Ub
            if bv[i] != 0.0:
                gb = bv[i] * hWb if gb is None else gb + bv[i] * hWb
            t = None
            for j, a in cols[i]:
                t = a * Yb[j] if t is None else t + a * Yb[j]
            if t is not None:
                gb = h2 * t if gb is None else gb + h2 * t
            if gb is None:
                continue
            if forcing:
                sum0 = gb if sum0 is None else sum0 + gb
                if c[i] != 0.0:
                    sumd = c[i] * gb if sumd is None else sumd + c[i] * gb
            Y = Ys[i]
            d = dot(Y, gb)
            Yb[i] = rs[i] * gb + (d + d) * Y
        S = Ub
        Ub_new = Ub
        inner = dot(Ub, accp)
        for i in range(s):
            if Yb[i] is not None:
                Ub_new = Ub_new + Yb[i]
                if i:
                    S = S + c[i] * Yb[i]
                    inner = inner + dot(Yb[i], accs[i])
        hb[k] = dot(S, W) + dot(Wb, accv) + (h + h) * inner
        if forcing:  # stage forcing P_k (1 - c_i) + P_k+1 c_i
            if sumd is not None:
                sum0 = sum0 - sumd
                Pb[k + 1] = sumd if Pb[k + 1] is None else Pb[k + 1] + sumd
            Pb[k] = sum0
        Ub, Wb = Ub_new, Wb + h * S
    return hb, kb, Pb


# ================================================================================================= array kernel
class _Lib:
    """The few array functions the batched kernel needs, for NumPy or torch."""

    def __init__(self, like: Any):
        self.torch = isinstance(like, torch.Tensor)
        self.dtype = like.dtype
        self.device = like.device if self.torch else None

    def empty(self, *shape: int) -> Any:
        if self.torch:
            return torch.empty(shape, dtype=self.dtype, device=self.device)
        return np.empty(shape, dtype=self.dtype)

    def zeros(self, *shape: int) -> Any:
        if self.torch:
            return torch.zeros(shape, dtype=self.dtype, device=self.device)
        return np.zeros(shape, dtype=self.dtype)

    def array(self, x: Any) -> Any:
        if self.torch:
            return torch.as_tensor(np.asarray(x), dtype=self.dtype, device=self.device)
        return np.asarray(x, dtype=self.dtype)

    def mul(self, a: Any, b: Any, out: Any) -> Any:
        return torch.mul(a, b, out=out) if self.torch else np.multiply(a, b, out=out)

    def matmul(self, a: Any, b: Any, out: Any) -> Any:
        if self.torch:  # torch.matmul(vector, matrix, out=) wants a (1, n) out
            return out.copy_(torch.matmul(a, b))
        return np.matmul(a, b, out=out)

    def sum0(self, a: Any, out: Any) -> Any:
        return torch.sum(a, 0, out=out) if self.torch else np.sum(a, 0, out=out)


def _forward_array(tab: Tableau, hs, kicks, forcing, save: bool):
    """Batched forward: hs (K, B), kicks (K, 2, B) or None, forcing (K + 1, 2, B) or None (as in
    :func:`_forward_generic`), NumPy or torch (no autograd).

    Returns Z (K, 4, B) = (U, W) after each step (post-kick) and what :func:`_backward_array` needs.
    """
    K, B = hs.shape
    s = tab.stages
    lib = _Lib(hs)
    A = lib.array(tab.matrix())
    c3 = lib.array(tab.c).reshape(s, 1, 1)
    bp, bv = lib.array(tab.bp), lib.array(tab.bv)
    h2s = hs * hs
    Z = lib.empty(K, 4, B)
    U = W = lib.zeros(2, B)
    carried = None
    saved = []
    for k in range(K):
        h, h2 = hs[k], h2s[k]
        hW = h * W
        # (s, 2, B); row 0 is U, rows i get h^2 acc_i below. In place: NumPy checks the call stack (slow) before
        # reusing a large temporary in an expression like U + c3 * hW.
        Y = c3 * hW
        Y += U
        G, r, acc = lib.empty(s, 2, B), lib.empty(s, B), lib.empty(s, 2, B)
        G2, acc2 = G.reshape(s, 2 * B), acc.reshape(s, 2 * B)
        if carried is None:
            lib.sum0(U * U, out=r[0])
            lib.mul(r[0], U, out=G[0])
        else:
            G[0], r[0] = carried
        if forcing is not None:
            p0 = forcing[k]
            pd = forcing[k + 1] - p0
            G[0] += p0
        acc[0] = 0.0
        for i in range(1, s):
            lib.matmul(A[i, :i], G2[:i], out=acc2[i])
            Y[i] += h2 * acc[i]
            lib.sum0(Y[i] * Y[i], out=r[i])
            lib.mul(r[i], Y[i], out=G[i])
            if tab.fsal and i == s - 1:
                carried = (G[i].clone() if lib.torch else G[i].copy(), r[i])
            if forcing is not None:
                G[i] += p0 + c3[i] * pd
        accv = (bv @ G2).reshape(2, B)
        W_new = W + h * accv
        if tab.fsal:
            U_new, accp = Y[s - 1], acc[s - 1]
        else:
            accp = (bp @ G2).reshape(2, B)
            U_new = U + hW + h2 * accp
        if save:
            saved.append((W, Y, r, acc, accp, accv))
        if kicks is not None:
            W_new += kicks[k]
        Z[k, :2], Z[k, 2:] = U_new, W_new
        U, W = U_new, W_new
    return Z, (hs, h2s, saved)


def _backward_array(tab: Tableau, state, gZ, forcing: bool):
    """Batched discrete adjoint (the recurrences of :func:`_backward_generic`); gZ (K, 4, B).

    Returns hb (K, B), kick grads (K, 2, B) and, with ``forcing``, forcing grads (K + 1, 2, B), else None.
    """
    hs, h2s, saved = state
    K, B = hs.shape
    s = tab.stages
    lib = _Lib(hs)
    AT = lib.array(tab.matrix().T)
    c = lib.array(tab.c)
    bp3, bv3 = lib.array(tab.bp).reshape(s, 1, 1), lib.array(tab.bv).reshape(s, 1, 1)
    last_used = max(i for i in range(s) if tab.bp[i] != 0.0 or tab.bv[i] != 0.0 or tab.a_cols[i])
    hb, kb = lib.empty(K, B), lib.empty(K, 2, B)
    Pb = lib.zeros(K + 1, 2, B) if forcing else None
    Ub, Wb = lib.zeros(2, B), lib.zeros(2, B)
    for k in range(K - 1, -1, -1):
        Ub = Ub + gZ[k, :2]
        Wb = Wb + gZ[k, 2:]
        kb[k] = Wb
        W, Y, r, acc, accp, accv = saved[k]
        h, h2 = hs[k], h2s[k]
        Gb = bp3 * (h2 * Ub)  # (s, 2, B), the stage adjoints once complete
        Gb += bv3 * (h * Wb)
        Yb = lib.zeros(s, 2, B)
        Yb2 = Yb.reshape(s, 2 * B)
        for i in range(last_used, -1, -1):
            if i < s - 1:
                Gb[i] += h2 * (AT[i, i + 1 :] @ Yb2[i + 1 :]).reshape(2, B)
            d = (Y[i] * Gb[i]).sum(0)
            lib.mul(r[i], Gb[i], out=Yb[i])
            Yb[i] += (d + d) * Y[i]
        if forcing:  # stage forcing P_k (1 - c_i) + P_k+1 c_i
            towards_end = (c @ Gb.reshape(s, 2 * B)).reshape(2, B)
            Pb[k + 1] += towards_end
            Pb[k] += Gb.sum(0) - towards_end
        S = Ub + (c @ Yb2).reshape(2, B)
        inner = (Ub * accp).sum(0) + (Yb * acc).sum((0, 1))
        hb[k] = (S * W).sum(0) + (Wb * accv).sum(0) + (h + h) * inner
        Ub = Ub + Yb.sum(0)
        Wb = Wb + h * S
    return hb, kb, Pb


# ================================================================================================= autograd
def _complex_rows(t: torch.Tensor | None) -> list[list[complex]] | None:
    """(B, n, 2) -> per sample, n Python complex numbers."""
    return None if t is None else [[complex(x, y) for x, y in row] for row in t.tolist()]


def _run_forward(backend: str, tab: Tableau, h, kick, forcing, save: bool):
    """Z (B, K, 4) and the state for :func:`_run_backward`."""
    B, K = h.shape
    if backend == "scalar":
        hl = h.tolist()
        kl = _complex_rows(kick)
        fl = _complex_rows(forcing)
        rows, state = [], []
        for b in range(B):
            h2 = [x * x for x in hl[b]]
            kicks = None if kl is None else [None if z == 0 else z for z in kl[b]]
            Us, Ws, saved = _forward_generic(
                tab, 0j, hl[b], h2, kicks, None if fl is None else fl[b], _sq_complex, save
            )
            rows.append([(u.real, u.imag, w.real, w.imag) for u, w in zip(Us, Ws, strict=False)])
            state.append((hl[b], h2, saved))
        return torch.tensor(rows, dtype=h.dtype, device=h.device).reshape(B, K, 4), state
    if backend == "torch":
        hs = h.detach().t().contiguous()

        def rows(t):
            return None if t is None else t.detach().permute(1, 2, 0).contiguous()
    else:
        hs = np.ascontiguousarray(h.detach().cpu().numpy().T)

        def rows(t):
            return None if t is None else np.ascontiguousarray(t.detach().cpu().numpy().transpose(1, 2, 0))

    Z, state = _forward_array(tab, hs, rows(kick), rows(forcing), save)  # (B, n, 2) -> (n, 2, B)
    return torch.as_tensor(Z, device=h.device).permute(2, 0, 1), state


def _run_backward(backend: str, tab: Tableau, state, gZ: torch.Tensor, forcing: bool):
    """Gradients for (h, kick, forcing) (None for no forcing) from gZ (B, K, 4)."""
    B = gZ.shape[0]
    dt, dev = gZ.dtype, gZ.device
    if backend == "scalar":
        g = gZ.tolist()
        hb, kb, Pb = [], [], []

        def pair(z):
            return (0.0, 0.0) if z is None else (z.real, z.imag)

        for b in range(B):
            hl, h2, saved = state[b]
            gU = [complex(x[0], x[1]) for x in g[b]]
            gW = [complex(x[2], x[3]) for x in g[b]]
            res = _backward_generic(tab, saved, hl, h2, gU, gW, forcing, _dot_complex)
            hb.append(res[0])
            kb.append([pair(z) for z in res[1]])
            if forcing:
                Pb.append([pair(z) for z in res[2]])
        out = [torch.tensor(hb, dtype=dt, device=dev), torch.tensor(kb, dtype=dt, device=dev)]
        return (*out, torch.tensor(Pb, dtype=dt, device=dev) if forcing else None)
    if backend == "numpy":
        gZ_k = np.ascontiguousarray(gZ.detach().cpu().numpy().transpose(1, 2, 0))
    else:
        gZ_k = gZ.detach().permute(1, 2, 0).contiguous()
    hb, kb, Pb = _backward_array(tab, state, gZ_k, forcing)

    def back(x):
        return torch.as_tensor(x, device=dev).permute(2, 0, 1)  # (n, 2, B) -> (B, n, 2)

    return torch.as_tensor(hb, device=dev).t(), back(kb), back(Pb) if forcing else None


class _March(torch.autograd.Function):
    """Z = march(h, kick, forcing) with the discrete adjoint as its backward."""

    @staticmethod
    def forward(ctx, h, kick, forcing, tab, backend):  # type: ignore[override]
        save = any(ctx.needs_input_grad[:3])
        Z, state = _run_forward(backend, tab, h, kick, forcing, save)
        ctx.state, ctx.tab, ctx.backend, ctx.forcing = state, tab, backend, forcing is not None
        ctx.kick = kick is not None
        return Z

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gZ):  # type: ignore[override]
        hb, kb, Pb = _run_backward(ctx.backend, ctx.tab, ctx.state, gZ, ctx.forcing)
        return hb, kb if ctx.kick else None, Pb, None, None


def default_backend(batch: int, device: torch.device) -> str:
    """The fastest implementation for a batch on a device (see the module docstring)."""
    if device.type != "cpu":
        return "torch"
    return "scalar" if batch <= SCALAR_MAX_BATCH else "numpy"


def march(
    h: torch.Tensor,
    tab: Tableau,
    *,
    kick: torch.Tensor | None = None,
    forcing: torch.Tensor | None = None,
    adjoint: bool = True,
    backend: str | None = None,
) -> torch.Tensor:
    """Integrate U'' = -|U|^2 U / 2 (+ forcing) from U = W = 0 over K steps per sample, differentiably.

    Args:
        h: (B, K) step lengths [m] (zero: the step does nothing).
        tab: the method (:data:`METHODS`).
        kick: (B, K, 2) added to W = dU/dt after each step [1/m^2], or None.
        forcing: (B, K + 1, 2) values P of a forcing at the step boundaries, linear within each step, in units
            of the stage value |U|^2 U [1/m^3], so that U'' = -(|U|^2 U + P) / 2; or None.
        adjoint: gradients from the discrete adjoint (default) or from autograd through every operation.
        backend: "scalar", "numpy" (CPU only) or "torch"; default :func:`default_backend`.
    Returns:
        (B, K, 4): (U_x, U_y, W_x, W_y) after each step and its kick.
    """
    B, K = h.shape
    if B == 0 or K == 0:
        keep = sum(0.0 * t.sum() for t in (h, kick, forcing) if t is not None)  # an empty result in the graph
        return h.new_zeros(B, K, 4) + keep
    if adjoint:
        return _March.apply(h, kick, forcing, tab, backend or default_backend(B, h.device))

    def rows(t):
        return None if t is None else t.permute(1, 2, 0).unbind(0)  # (B, n, 2) -> n x (2, B)

    hs = h.unbind(1)
    Us, Ws, _ = _forward_generic(
        tab, h.new_zeros(2, B), hs, [x * x for x in hs], rows(kick), rows(forcing), _sq_rows, False
    )
    return torch.cat((torch.stack(Us), torch.stack(Ws)), dim=1).permute(2, 0, 1)
