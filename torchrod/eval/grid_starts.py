"""The paper tools' common start: a grid scan of location sets with linear least squares.

The baselines of :mod:`torchrod.eval.paper` (the paper's node method, BVP + Levenberg-Marquardt, BVP + derivative
propagation) all start from these guesses, so that their timings compare the inner models and not the starts. (The
estimator itself starts from the sequential scan of :mod:`torchrod.kernels.scan`, whose cost grows linearly
with the number of gratings; this one enumerates location sets, which is affordable for the paper's 14 gratings and
at most three forces.)

With the locations fixed, the small-deflection curvature is linear in the forces (docs/physics.md, the sign check):

    U(s_k) = u_x + i u_y = sum_i (s_i - s_k)^+ c_i / EI,    c_i = i (f_x,i + i f_y,i) = -f_y,i + i f_x,i,

one real design matrix A (G, h), A_ki = (s_i - s_k)^+ / EI, shared by the two components. For every candidate set
of locations on a grid the best forces are a linear least-squares solve and the misfit is
``|u|^2 - |Q^T u|^2`` with Q an orthonormal basis of A's columns, so scanning all candidates for all readings is one
matrix product (readings x components, G) @ (G, candidates x h). The best few candidates that are not near copies
of each other (all locations within ``separation`` of a better one's) become the starts, with their linear forces.
The scan never forms the projections themselves: ``|Q^T u|^2 = u^T (Q Q^T) u`` is linear in the reading's second
moments ``sum_c u_c u_c^T``, so the misfits of all candidates are one product (B, G(G+1)/2) @ (G(G+1)/2, K).

Grid: ``step`` apart from half a step above the first grating to the tip, L included (a force proximal to the first
grating leaves no trace on any grating, so none is proposed there); for h >= 2 the candidates are the sets of
increasing grid locations at least ``separation`` apart. Missing gratings are rows of A removed: readings are grouped
by their mask, and the bases are computed per mask (cached: a broken grating is usually broken for a whole file).
Rank-deficient candidates (e.g. two forces both beyond the last present grating) use the basis of the columns'
span (SVD, relative singular values below 1e-9 dropped) and the minimum-norm forces.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch

from ..errors import OptionsError
from ..rod import Rod

__all__ = ["GridStarts", "Starts"]

_RANK_TOL = 1e-9
_CACHE_SIZE = 64


@dataclass(frozen=True)
class Starts:
    """Starting guesses for one count h.

    Attributes:
        s: (B, S, h) locations [m] (increasing along h).
        f: (B, S, h, 2) body-frame (f_x, f_y) [N] of the linear fit.
        loss: (B, S) misfit of the linear model, sum over present gratings of squared residuals [1/m^2].
    """

    s: torch.Tensor
    f: torch.Tensor
    loss: torch.Tensor


class GridStarts:
    """Grid-scan starts for a rod (see the module docstring). Cheap to call repeatedly: per-mask bases are cached.

    Args:
        rod: the rod.
        step: grid spacing [m]; None: half the mean grating spacing (or L / 20 with one grating).
        separation: least distance [m] between the locations of a candidate, and the radius within which a
            worse candidate counts as a copy of a better one; None: the mean grating spacing (or L / 10).
        dtype, device: of the cached tensors (the readings passed in must match).
    """

    def __init__(
        self,
        rod: Rod,
        *,
        step: float | None = None,
        separation: float | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        g = rod.gratings
        spacing = (g[-1] - g[0]) / (len(g) - 1) if len(g) > 1 else rod.length / 10.0
        self.step = float(step) if step is not None else spacing / 2.0
        self.separation = float(separation) if separation is not None else spacing
        if not (self.step > 0.0 and math.isfinite(self.step)):
            raise OptionsError(f"grid step must be positive, got {step!r}")
        if not (self.separation >= 0.0 and math.isfinite(self.separation)):
            raise OptionsError(f"separation must be >= 0, got {separation!r}")
        self.rod = rod
        self.dtype, self.device = dtype, torch.device(device) if device is not None else torch.device("cpu")
        lo = min(g[0] + self.step / 2.0, rod.length)
        n = max(1, math.ceil((rod.length - lo) / self.step - 1e-9) + 1)
        self.grid = (
            torch.linspace(lo, rod.length, n, dtype=dtype, device=self.device)
            if n > 1
            else torch.tensor([rod.length], dtype=dtype, device=self.device)
        )
        self._candidates: dict[int, torch.Tensor] = {}
        self._bases: dict[tuple[int, bytes], tuple[torch.Tensor, torch.Tensor]] = {}
        self._copies: dict[int, torch.Tensor] = {}

    # ------------------------------------------------------------------ candidates
    def candidates(self, h: int) -> torch.Tensor:
        """(K, h) candidate location sets [m], increasing, neighbours at least ``separation`` apart."""
        if h not in self._candidates:
            pts = self.grid.tolist()
            sep = self.separation - 1e-12
            combos = [
                c
                for c in itertools.combinations(range(len(pts)), h)
                if all(pts[b] - pts[a] >= sep for a, b in itertools.pairwise(c))
            ]
            if not combos:  # the grid is too short for h separated forces: drop the separation
                combos = list(itertools.combinations_with_replacement(range(len(pts)), h))
            idx = torch.tensor(combos, dtype=torch.long, device=self.device).reshape(-1, h)
            self._candidates[h] = self.grid[idx]
        return self._candidates[h]

    def _copy_matrix(self, h: int) -> torch.Tensor:
        """(K, K) bool: candidate j lies within ``separation`` (every location) of candidate i."""
        if h not in self._copies:
            c = self.candidates(h)
            self._copies[h] = (c.unsqueeze(1) - c.unsqueeze(0)).abs().amax(-1) < self.separation
        return self._copies[h]

    def _basis(self, h: int, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For a grating mask (G,): the projectors onto the candidates' column spaces as (T, K) coefficients of
        the reading's second moments (T = G (G + 1) / 2, upper triangle, off-diagonal terms doubled), and the
        pseudo-inverses (K, h, G) of the masked design matrices (zero columns at missing gratings)."""
        key = (h, bytes(present.to(torch.uint8).cpu().numpy()))
        hit = self._bases.get(key)
        if hit is not None:
            return hit
        cand = self.candidates(h)  # (K, h)
        gr = self.rod.grating_positions(self.dtype, self.device)
        A = (cand.unsqueeze(1) - gr.view(1, -1, 1)).clamp(min=0.0) / self.rod.bending_stiffness  # (K, G, h)
        A = A * present.to(self.dtype).view(1, -1, 1)
        U, S, Vh = torch.linalg.svd(A, full_matrices=False)  # (K, G, h), (K, h), (K, h, h)
        keep = S > _RANK_TOL * S[:, :1].clamp(min=torch.finfo(self.dtype).tiny)
        Q = U * keep.unsqueeze(1).to(self.dtype)
        inv_s = torch.where(keep, 1.0 / S.clamp(min=torch.finfo(self.dtype).tiny), torch.zeros_like(S))
        pinv = Vh.transpose(1, 2) @ (inv_s.unsqueeze(-1) * U.transpose(1, 2))  # (K, h, G)
        G = A.shape[1]
        iu = torch.triu_indices(G, G, device=self.device)
        proj = (Q @ Q.transpose(1, 2))[:, iu[0], iu[1]]  # (K, T)
        proj = proj * torch.where(iu[0] == iu[1], 1.0, 2.0).to(self.dtype)
        value = (proj.T.contiguous(), pinv)
        if len(self._bases) >= _CACHE_SIZE:
            self._bases.pop(next(iter(self._bases)))
        self._bases[key] = value
        return value

    # ------------------------------------------------------------------ scan
    def __call__(self, curvature: torch.Tensor, mask: torch.Tensor, h: int, count: int) -> Starts:
        """The ``count`` best distinct candidates for ``h`` forces, per reading.

        Args:
            curvature: (B, G, 2) readings [1/m], zero (or anything finite) at missing gratings.
            mask: (B, G) bool, True where the grating was read.
            h: number of forces (>= 1); count: starts per reading (>= 1; fewer candidates: repeated).
        Returns:
            :class:`Starts` with S = ``count``.
        """
        B, G, _ = curvature.shape
        cand = self.candidates(h)
        K = cand.shape[0]
        u = torch.where(mask.unsqueeze(-1), curvature, torch.zeros((), dtype=curvature.dtype, device=curvature.device))
        loss = torch.empty(B, K, dtype=self.dtype, device=self.device)
        iu = torch.triu_indices(G, G, device=self.device)
        moments = torch.einsum("bgc,bkc->bgk", u, u)[:, iu[0], iu[1]]  # (B, T)
        energy = u.square().sum((1, 2)).unsqueeze(1)  # (B, 1)
        patterns, which = torch.unique(mask, dim=0, return_inverse=True)
        for p in range(patterns.shape[0]):
            rows = (which == p).nonzero().squeeze(1)
            proj, _ = self._basis(h, patterns[p])
            loss[rows] = energy[rows] - moments[rows] @ proj
        loss = loss.clamp(min=0.0)
        # Best distinct candidates: pick the best, suppress its near copies, repeat.
        copies = self._copy_matrix(h)
        chosen: list[torch.Tensor] = []
        work = loss.clone()
        inf = torch.tensor(float("inf"), dtype=self.dtype, device=self.device)
        for _ in range(count):
            best = work.argmin(dim=1)  # (B,)
            exhausted = torch.isinf(work.gather(1, best.unsqueeze(1))).squeeze(1)
            if chosen:
                best = torch.where(exhausted, chosen[0], best)
            chosen.append(best)
            work = torch.where(copies[best], inf, work)
        idx = torch.stack(chosen, dim=1)  # (B, S)
        s = cand[idx]  # (B, S, h)
        # Linear forces of the chosen candidates, per mask pattern.
        c = torch.empty(B, count, h, 2, dtype=self.dtype, device=self.device)
        for p in range(patterns.shape[0]):
            rows = (which == p).nonzero().squeeze(1)
            _, pinv = self._basis(h, patterns[p])
            c[rows] = torch.einsum("bshg,bgc->bshc", pinv[idx[rows]], u[rows])
        # c = -f_y + i f_x per component pair (Re from u_x, Im from u_y).
        f = torch.stack((c[..., 1], -c[..., 0]), dim=-1)
        return Starts(s=s, f=f, loss=loss.gather(1, idx))
