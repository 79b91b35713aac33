"""One reading at a time on Python floats: the estimator's path for a few readings per call on the CPU.

At one reading per call the batched estimator (:mod:`torchrod.estimator`) spends most of its time in torch's
per-operation dispatch: every row of its Levenberg-Marquardt polish is a handful of (1, 2G, P) tensors pushed
through a few hundred small operations per step (measured at B = 1, one force: ~8 ms, of which ~0.5 ms is the
forward model itself). Here each (count, start) of a reading is fitted with the SAME iteration on Python floats and
numpy arrays of at most 28 x 9: the same unknowns (z, phi_x, phi_y) with ``s = L (1 + sin z) / 2`` and ``f = phi EI /
L^2``, the same residuals and Jacobian (:func:`torchrod.sensitivity.march_row`, the batched march's scheme and step
counts), the same damped Gauss-Newton step, trust region and damping schedule, and the same stopping rule (the
Gauss-Newton decrement at most ``decrement_tolerance`` x sigma^2).

What this path does not do, it hands back: :class:`ReadingFit.fit` reports a fit that has not converged within the
polish budget, or that ends with a force on a grating (on the loss's kink, whose one-sided handling and probes live
in the batched path), and the estimator then solves that reading with the batched path (polish with kink handling,
then L-BFGS); so does a chosen fit whose loss is worse than the noise explains (a likely local minimum). Where a
reading's fits agree, the two paths reach the same optimum to within the stopping tolerance (tests/test_estimator.py
compares them). How starts are tried and when a reading's count is decided is the estimator's part
(:meth:`torchrod.estimator.Estimator.estimate`, module docstring).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..model.sensitivity import march_row

__all__ = ["Fit", "ReadingFit"]


@dataclass(frozen=True)
class Fit:
    """One fitted (count, start) of a reading.

    Attributes:
        s: h locations [m] (model coordinates); f: h pairs (f_x, f_y) [N].
        loss: sum over present gratings of squared residuals [1/m^2].
        decrement: the Gauss-Newton decrement at the final point [1/m^2] (inf where its solve failed).
        sigma2: the sigma^2 the stopping test used [1/m^2].
        converged: decrement <= tolerance x sigma2.
        steps: Levenberg-Marquardt steps taken (one forward evaluation each).
        on_kink: a force ended within ``kink`` of a present grating (the batched path must decide).
    """

    s: tuple[float, ...]
    f: tuple[tuple[float, float], ...]
    loss: float
    decrement: float
    sigma2: float
    converged: bool
    steps: int
    on_kink: bool


class ReadingFit:
    """The least-squares problem of one reading, fitted on Python floats (module docstring).

    Args:
        query: G grating positions [m]; length: L [m]; bending_stiffness: EI [N m^2].
        curvature: G pairs (u_x, u_y) [1/m] (anything finite at missing gratings); present: G bools.
        sigma2: the given sigma^2 with the floor [1/m^2], or None (then per fit: loss / dof, at least ``floor2``).
        floor2: the noise floor squared [1/m^2].
        tolerance: ``decrement_tolerance``; max_step_angle, max_steps: the forward model's accuracy.
        edge, max_dphi, max_dz, kink: the estimator's start margin (fraction of L), trust region (force units
            EI / L^2 and radians of z per step) and kink radius [m].
    """

    def __init__(
        self,
        query: Sequence[float],
        length: float,
        bending_stiffness: float,
        curvature: Sequence[Sequence[float]],
        present: Sequence[bool],
        *,
        sigma2: float | None,
        floor2: float,
        tolerance: float,
        max_step_angle: float,
        max_steps: int,
        edge: float,
        max_dphi: float,
        max_dz: float,
        kink: float,
    ) -> None:
        self.query = [float(x) for x in query]
        self.L, self.EI = float(length), float(bending_stiffness)
        self.f_unit = self.EI / (self.L * self.L)
        self.present = np.repeat(np.asarray(present, dtype=np.float64), 2)  # (2G,) per residual
        self.u_meas = np.asarray(curvature, dtype=np.float64).reshape(-1) * self.present
        self.present_q = [q for q, p in zip(self.query, present) if p]
        self.n_residuals = int(self.present.sum())
        self.sigma2_given, self.floor2, self.tolerance = sigma2, floor2, tolerance
        self.max_step_angle, self.max_steps = max_step_angle, max_steps
        self.edge, self.max_dphi, self.max_dz, self.kink = edge, max_dphi, max_dz, kink

    # ------------------------------------------------------------------ unknowns
    def to_unknowns(self, s: Sequence[float], f: Sequence[Sequence[float]]) -> np.ndarray:
        """Locations [m] and forces [N] -> unknowns (3h,) (z, phi_x, phi_y) per force; s kept ``edge`` inside."""
        L, lo, hi = self.L, self.edge * self.L, (1.0 - self.edge) * self.L
        v = []
        for si, (fx, fy) in zip(s, f):
            si = min(max(float(si), lo), hi)
            v += [math.asin(min(max(2.0 * si / L - 1.0, -1.0), 1.0)), fx / self.f_unit, fy / self.f_unit]
        return np.asarray(v, dtype=np.float64)

    def forces(self, v: np.ndarray) -> tuple[list[float], list[tuple[float, float]]]:
        vv = v.tolist()
        s = [0.5 * self.L * (1.0 + math.sin(z)) for z in vv[0::3]]
        f = [(px * self.f_unit, py * self.f_unit) for px, py in zip(vv[1::3], vv[2::3])]
        return s, f

    def residual(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r (2G,) [1/m] (zero at missing gratings) and dr/dv (2G, 3h)."""
        s, f = self.forces(v)
        u, du = march_row(
            self.query,
            s,
            f,
            self.L,
            self.EI,
            max_step_angle=self.max_step_angle,
            max_steps=self.max_steps,
        )
        r = np.array(u).view(np.float64) * self.present - self.u_meas
        jac = np.array(du)  # (G, 3h) complex
        h = len(s)
        J = np.stack((jac.real, jac.imag), axis=1).reshape(2 * len(u), 3 * h)
        chain = np.empty(3 * h)
        chain[0::3] = 0.5 * self.L * np.cos(v[0::3])
        chain[1::3] = self.f_unit
        chain[2::3] = self.f_unit
        return r, J * chain * self.present[:, None]

    def sigma2(self, loss: float, h: int) -> float:
        if self.sigma2_given is not None:
            return self.sigma2_given
        return max(loss / max(self.n_residuals - 3 * h, 1), self.floor2)

    @staticmethod
    def _step(A: list[list[float]], g: list[float], damping: float) -> tuple[list[float], float]:
        """The damped Gauss-Newton step for the normal matrix A = J^T J and gradient g = J^T r, and its decrement
        (the estimator's ``_gn_step`` without held locations): Cholesky in Python floats (P <= 9), inf on
        failure."""
        P = len(g)
        d = [A[i][i] for i in range(P)]
        extra = 1e-12 * max(max(d), 2.2250738585072014e-308)
        c = [[0.0] * P for _ in range(P)]
        for i in range(P):
            ci = c[i]
            for j in range(i + 1):
                cj = c[j]
                x = A[i][j] - sum(ci[k] * cj[k] for k in range(j))
                if i == j:
                    x += damping * d[i] + extra
                    if not x > 0.0:  # not positive definite (or NaN)
                        return [0.0] * P, math.inf
                    ci[i] = math.sqrt(x)
                else:
                    ci[j] = x / cj[j]
        y = [0.0] * P
        for i in range(P):
            y[i] = (-g[i] - sum(c[i][k] * y[k] for k in range(i))) / c[i][i]
        step = [0.0] * P
        for i in reversed(range(P)):
            step[i] = (y[i] - sum(c[k][i] * step[k] for k in range(i + 1, P))) / c[i][i]
        if not all(map(math.isfinite, step)):
            return [0.0] * P, math.inf
        return step, -sum(a * b for a, b in zip(g, step))

    def fit(self, s0: Sequence[float], f0: Sequence[Sequence[float]], iterations: int) -> Fit:
        """Up to ``iterations`` Levenberg-Marquardt steps from (s0 [m], f0 [N]), as the batched polish takes them."""
        v = self.to_unknowns(s0, f0)
        h = v.shape[0] // 3
        r, J = self.residual(v)
        loss = float(r @ r)
        lam, steps = 1e-3, 0
        half = 0.5 * math.pi
        while True:
            A, g = (J.T @ J).tolist(), (J.T @ r).tolist()
            _, dec = self._step(A, g, 1e-9)
            s2 = self.sigma2(loss, h)
            done = dec <= self.tolerance * s2
            if done or steps >= iterations or lam >= 1e9:
                break
            step, _ = self._step(A, g, lam)
            # Trust region (force units EI / L^2, radians of z), then z kept in [-pi/2, pi/2].
            big = max(
                max(abs(x) for i, x in enumerate(step) if i % 3) / self.max_dphi,
                max(abs(x) for x in step[0::3]) / self.max_dz,
                1.0,
            )
            step = [x / big for x in step]
            t = 1.0
            for z, dz in zip(v[0::3].tolist(), step[0::3]):
                if dz != 0.0:
                    t = min(t, min(max(((half if dz > 0 else -half) - z) / dz, 0.0), 1.0))
            v_try = v + t * np.asarray(step)
            r_try, J_try = self.residual(v_try)
            loss_try = float(r_try @ r_try)
            steps += 1
            if math.isfinite(loss_try) and loss_try < loss:
                v, r, J, loss = v_try, r_try, J_try, loss_try
                lam = max(lam / 3.0, 1e-9)
            else:
                lam = min(lam * 4.0, 1e9)
        s, f = self.forces(v)
        on_kink = any(abs(si - q) < self.kink for si in s for q in self.present_q)
        return Fit(tuple(s), tuple(f), loss, dec, s2, bool(done), steps, on_kink)
