"""The global-frame Cosserat rod as a boundary-value problem, solved by shooting from the base.

This module is the independent check of :mod:`torchrod.model.body_frame` and the home of the paper's two baselines. It
works in numpy/scipy, one load case at a time, with rotation matrices in the global frame (no body-frame reduction).

Equations (the paper's eqs. 1-4, standard Cosserat sign, docs/physics.md) for an inextensible, unshearable rod
(v = e3) with no external moment::

    P' = R e3,    R' = R u^,    N' = -F_e,    M' = -P' x N,    M = R K (u - u*),   K = diag(EI, EI, GJ)

with GJ = ``rod.torsion_stiffness`` and u* the rod's intrinsic curvature (zero for a straight rod, whose torsion
stays zero at the solution; a precurved rod twists). u* is piecewise constant, so the integration is split at its
breakpoints too, and a position at a breakpoint reads the distal value.
Boundary conditions: clamped base P(0) = 0, R(0) = I; free tip N(L+) = 0, M(L) = 0. The loads are follower point
forces: at s_i the global force is F_i = R(s_i) (f_x, f_y, 0), so going from base to tip N drops by F_i at s_i
(a force exactly at s = L acts before the tip condition). Body-frame curvature: u = u* + K^{-1} R^T M.

Shooting: the unknowns are z = (N(0), M(0)) (6 numbers); the residual is r(z) = (N(L+), M(L)). Internally both are
scaled, N by a force scale F_s = max(sum |f_i|, EI/L^2) and M by F_s L, so the 6 x 6 problem is well balanced.
The small-deflection solution (R = I along the rod) is the initial guess:

    N(0) = sum_i F_i,    M(0) = sum_i s_i e3 x F_i

(from M(0) = M(L) + int_0^L P' x N ds with P' = e3): one f_y > 0 at s_i gives M_x(0) = -s_i f_y, so
u_x(0) = -f_y s_i / EI, the standard sign of docs/physics.md.

Two solvers:

* :func:`solve_reference`: scipy's DOP853 (rtol 1e-12) segment by segment between force locations, Newton-type
  iterations (Levenberg-Marquardt with a forward-difference Jacobian) to a scaled tip residual of 1e-12, started
  from a coarse RK4 shooting solution (q = 64; the small-deflection guess and load continuation as fallbacks).
  Slow and accurate: the reference for tests.
* :class:`ShootingSolver`: the paper's baselines, fixed-step classical Runge-Kutta (RK4) on q uniform nodes, with
  Levenberg-Marquardt on the tip residual and the Jacobian either by forward differences (``jacobian="fd"``, the
  six perturbed shots integrated together as one vectorised batch) or by derivative propagation
  (``jacobian="dp"``, Rucker & Webster 2011: the tangent system d(state)/dz is integrated with the state by the same
  RK4 steps, so the Jacobian of the discrete residual comes out of one pass). Warm-startable from a previous
  solution, as an outer force-estimation loop needs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..errors import OptionsError, TorchrodTypeError
from ..loads import PointForces
from ..rod import DEFAULT_POISSON_RATIO, Rod

__all__ = [
    "DEFAULT_POISSON_RATIO",
    "BVPSolution",
    "ShootingSolver",
    "reference_grating_curvature",
    "solve_reference",
]


_STATE = 18  # P (3), R (9, row-major), N (3), M (3)
_P, _R, _N, _M = slice(0, 3), slice(3, 12), slice(12, 15), slice(15, 18)


@dataclass(frozen=True)
class BVPSolution:
    """A solved rod, sampled at positions ``s`` (numpy, SI units).

    Attributes:
        s: (S,) positions along the rod [m], increasing.
        P: (S, 3) centreline positions, global frame [m].
        R: (S, 3, 3) frames (columns: body axes in the global frame).
        N: (S, 3) internal force, global frame [N] (proximal side of a force at that position).
        M: (S, 3) internal moment, global frame [N m].
        u: (S, 3) body-frame curvature K^{-1} R^T M [1/m] (u_z is the twist, zero at the solution).
        base: (6,) the shooting unknowns (N(0) [N], M(0) [N m]).
        residual: scaled tip residual max |(N(L+), M(L)/L)| / F_s at the solution (dimensionless).
        iterations: Levenberg-Marquardt iterations (accepted and rejected steps).
        evaluations: integrations of the rod (a batched integration of the fd Jacobian counts 6).
        converged: whether the residual met the tolerance.
    """

    s: np.ndarray
    P: np.ndarray
    R: np.ndarray
    N: np.ndarray
    M: np.ndarray
    u: np.ndarray
    base: np.ndarray
    residual: float
    iterations: int
    evaluations: int
    converged: bool

    @property
    def curvature(self) -> np.ndarray:
        """(S, 2) the (u_x, u_y) a grating would read [1/m]."""
        return self.u[:, :2]

    @property
    def tip(self) -> np.ndarray:
        """(3,) the last sampled position [m] (the tip when ``s`` ends at L)."""
        return self.P[-1]


# ---------------------------------------------------------------------------------------------------- helpers
def _stiffness(rod: Rod) -> np.ndarray:
    """(3,) inverse stiffnesses K^{-1} = (1/EI, 1/EI, 1/GJ) [1/(N m^2)]."""
    ei = rod.bending_stiffness
    return np.array([1.0 / ei, 1.0 / ei, 1.0 / rod.torsion_stiffness])


def _intrinsic(rod: Rod, s: np.ndarray | Sequence[float]) -> np.ndarray:
    """(len(s), 3) u* [1/m] at positions s (the distal value at a breakpoint)."""
    return np.array([[ux, uy, 0.0] for ux, uy in rod.intrinsic_at(np.asarray(s, dtype=np.float64).tolist())])


def _force_array(rod: Rod, forces) -> np.ndarray:
    """(h, 3) rows (s [m], f_x [N], f_y [N]) sorted by s, validated against the rod."""
    if isinstance(forces, PointForces):
        if forces.batch_size != 1:
            raise OptionsError(f"one load case at a time: PointForces must have batch size 1, got {forces.batch_size}")
        forces = forces.to_lists()[0]
    arr = np.asarray(list(forces) if not isinstance(forces, np.ndarray) else forces, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise OptionsError(f"forces must be a list of (s, fx, fy) rows, shape (h, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise OptionsError(f"forces must be finite, got {arr.tolist()}")
    bad = (arr[:, 0] < 0.0) | (arr[:, 0] > rod.length)
    if bad.any():
        raise OptionsError(f"force locations must lie in [0, L = {rod.length}] m, got {arr[bad, 0].tolist()}")
    return arr[np.argsort(arr[:, 0], kind="stable")]


def _scales(rod: Rod, forces: np.ndarray) -> tuple[float, float]:
    """Force scale F_s [N] and moment scale F_s L [N m] for the unknowns and the residual."""
    fs = max(
        float(np.hypot(forces[:, 1], forces[:, 2]).sum()) if len(forces) else 0.0,
        rod.bending_stiffness / rod.length**2,
    )
    return fs, fs * rod.length


def _small_deflection_guess(forces: np.ndarray) -> np.ndarray:
    """(6,) N(0) = sum F_i, M(0) = sum s_i e3 x F_i with R = I (the linear cantilever) [N, N m]."""
    z = np.zeros(6)
    for s, fx, fy in forces:
        z[0] += fx
        z[1] += fy
        # e3 x (fx, fy, 0) = (-fy, fx, 0)
        z[3] += -s * fy
        z[4] += s * fx
    return z


def _hat(u: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) with hat(u) v = u x v."""
    h = np.zeros(u.shape + (3,))
    h[..., 0, 1], h[..., 0, 2] = -u[..., 2], u[..., 1]
    h[..., 1, 0], h[..., 1, 2] = u[..., 2], -u[..., 0]
    h[..., 2, 0], h[..., 2, 1] = -u[..., 1], u[..., 0]
    return h


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b along the last axis (broadcasting; cheaper than np.cross for tiny arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def _initial_state(z: np.ndarray) -> np.ndarray:
    """(K, 18) base states for K sets of unknowns z (K, 6) [SI]."""
    y = np.zeros((z.shape[0], _STATE))
    y[:, _R] = np.eye(3).ravel()
    y[:, _N] = z[:, :3]
    y[:, _M] = z[:, 3:]
    return y


def _levenberg_marquardt(
    residual: Callable[[np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray],
    z0: np.ndarray,
    *,
    tol: float,
    max_iter: int,
    tau: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Levenberg-Marquardt (Madsen, Nielsen & Tingleff's damping update) on a square, scaled system.

    ``residual(z) -> r (6,)``, ``jacobian(z, r) -> J (6, 6)`` (``r`` = residual(z), reused by finite differences).
    Stops when max |r| <= tol. Returns (z, r, iterations, converged).
    """
    z = z0.copy()
    r = residual(z)
    if not np.isfinite(r).all():
        return z, r, 0, False
    if np.abs(r).max() <= tol:
        return z, r, 0, True
    J = jacobian(z, r)
    A, g = J.T @ J, J.T @ r
    mu, nu = tau * float(np.diag(A).max()), 2.0
    cost = float(r @ r)
    for it in range(1, max_iter + 1):
        try:
            step = np.linalg.solve(A + mu * np.eye(6), -g)
        except np.linalg.LinAlgError:
            mu, nu = mu * nu, nu * 2.0
            continue
        z_new = z + step
        r_new = residual(z_new)
        cost_new = float(r_new @ r_new) if np.isfinite(r_new).all() else math.inf
        predicted = float(step @ (mu * step - g))  # = cost - (linear model cost), > 0
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if rho > 0.0:
            z, r, cost = z_new, r_new, cost_new
            if np.abs(r).max() <= tol:
                return z, r, it, True
            J = jacobian(z, r)
            A, g = J.T @ J, J.T @ r
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
        else:
            mu, nu = mu * nu, nu * 2.0
        if np.abs(step).max() <= 1e-15 * (1.0 + np.abs(z).max()):
            break
    return z, r, it, False


def _with_continuation(
    solve: Callable[[float, np.ndarray], tuple[np.ndarray, np.ndarray, int, bool]],
    z0: np.ndarray,
    guess_at: Callable[[float], np.ndarray],
    max_levels: int = 6,
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Solve at full load from z0; if that fails, march the load scale 0 -> 1 in steps, halving on failure."""
    z, r, iters, ok = solve(1.0, z0)
    if ok:
        return z, r, iters, ok
    total = iters
    scale, step, z_prev = 0.0, 0.25, guess_at(0.0)
    halvings = 0
    while scale < 1.0:
        target = min(1.0, scale + step)
        guess = z_prev if scale > 0.0 else guess_at(target)
        z, r, iters, ok = solve(target, guess)
        total += iters
        if ok:
            scale, z_prev = target, z
        else:
            halvings += 1
            if halvings > max_levels:
                return z, r, total, False
            step *= 0.5
    return z_prev, r, total, True


# ---------------------------------------------------------------------------------------------------- reference
def _reference_rhs(kinv: np.ndarray, ustar: np.ndarray) -> Callable[[float, np.ndarray], np.ndarray]:
    def rhs(_s: float, y: np.ndarray) -> np.ndarray:
        R = y[_R].reshape(3, 3)
        N, M = y[_N], y[_M]
        u = ustar + kinv * (R.T @ M)  # M = R K (u - u*)
        t = R[:, 2]  # P' = R e3
        out = np.empty(_STATE)
        out[_P] = t
        out[_R] = (R @ _hat(u)).ravel()  # R' = R u^
        out[_N] = 0.0  # N' = -F_e = 0 between point forces
        out[_M] = -_cross(t, N)  # M' = -P' x N
        return out

    return rhs


def _reference_shoot(
    rod: Rod,
    forces: np.ndarray,
    z: np.ndarray,
    query: np.ndarray,
    rtol: float,
    atol: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate base -> tip with DOP853 from unknowns z (6,) [SI]; returns (tip state after the last force (18,),
    states at ``query`` (Q, 18), proximal side of forces)."""
    from scipy.integrate import solve_ivp

    kinv = _stiffness(rod)
    events = np.unique(np.concatenate((forces[:, 0], query, rod.breakpoints(), [0.0, rod.length])))
    y = _initial_state(z[None])[0]
    recorded = np.empty((len(query), _STATE))
    fi = 0
    for k, s in enumerate(events):
        if k > 0 and s > events[k - 1]:
            rhs = _reference_rhs(kinv, _intrinsic(rod, [0.5 * (events[k - 1] + s)])[0])  # u* constant here
            with np.errstate(over="ignore", invalid="ignore"):
                sol = solve_ivp(rhs, (events[k - 1], s), y, method="DOP853", rtol=rtol, atol=atol)
            if not sol.success or not np.isfinite(sol.y[:, -1]).all():
                # A wild trial step of the outer iteration: report no solution (Levenberg-Marquardt rejects it).
                recorded[:] = np.nan
                return np.full(_STATE, np.nan), recorded
            y = sol.y[:, -1].copy()
        recorded[query == s] = y
        while fi < len(forces) and forces[fi, 0] == s:
            R = y[_R].reshape(3, 3)
            y[_N] -= R @ np.array([forces[fi, 1], forces[fi, 2], 0.0])  # N drops by R f_i going base -> tip
            fi += 1
    return y, recorded


def _solution(
    rod: Rod,
    query: np.ndarray,
    states: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    iters: int,
    evals: int,
    ok: bool,
) -> BVPSolution:
    R = states[:, _R].reshape(-1, 3, 3)
    M = states[:, _M]
    u = _intrinsic(rod, query).reshape(-1, 3) + _stiffness(rod) * np.einsum("kji,kj->ki", R, M)
    return BVPSolution(
        s=query.copy(),
        P=states[:, _P].copy(),
        R=R.copy(),
        N=states[:, _N].copy(),
        M=M.copy(),
        u=u,
        base=z.copy(),
        residual=float(np.abs(r).max()),
        iterations=iters,
        evaluations=evals,
        converged=ok,
    )


def _default_query(rod: Rod, at) -> np.ndarray:
    if at is None:
        return np.unique(np.concatenate(([0.0], rod.gratings, [rod.length])))
    q = np.asarray(at, dtype=np.float64).reshape(-1)
    if not np.isfinite(q).all() or (q < 0.0).any() or (q > rod.length).any():
        raise OptionsError(f"sample positions must lie in [0, L = {rod.length}] m, got {q.tolist()}")
    if (np.diff(q) < 0).any():
        raise OptionsError("sample positions must be non-decreasing")
    return q


def solve_reference(
    rod: Rod,
    forces: Sequence[Sequence[float]] | np.ndarray | PointForces,
    at: Sequence[float] | np.ndarray | None = None,
    *,
    rtol: float = 1e-12,
    atol: float = 1e-15,
    tol: float = 1e-12,
    max_iter: int = 50,
    initial: np.ndarray | BVPSolution | None = None,
) -> BVPSolution:
    """The reference solution of the global-frame BVP (DOP853 + Levenberg-Marquardt shooting).

    Args:
        rod: the rod (length, EI, poisson_ratio for GJ).
        forces: one load case: rows (s [m], f_x [N], f_y [N]) with body-frame components, or a
            :class:`PointForces` of batch size 1.
        at: (S,) non-decreasing positions [m] to sample; default: 0, the gratings and L.
        rtol, atol: DOP853 tolerances (atol in the state's SI units: m, N, N m).
        tol: bound on the scaled tip residual max |(N(L+), M(L)/L)| / F_s.
        max_iter: Levenberg-Marquardt iterations per attempt (load continuation follows a failure).
        initial: base unknowns (6,) (N(0) [N], M(0) [N m]) or a previous solution to start from.
    Returns:
        :class:`BVPSolution` at ``at``; ``converged`` is False if the residual never met ``tol``.
    """
    f = _force_array(rod, forces)
    query = _default_query(rod, at)
    fs, ms = _scales(rod, f)
    scale = np.array([fs] * 3 + [ms] * 3)
    none = np.zeros(0)
    evals = 0

    def shoot_scaled(load: float):
        fl = f.copy()
        fl[:, 1:] *= load

        def residual(zs: np.ndarray) -> np.ndarray:
            nonlocal evals
            evals += 1
            y, _ = _reference_shoot(rod, fl, zs * scale, none, rtol, atol)
            return np.concatenate((y[_N], y[_M])) / scale

        def jacobian(zs: np.ndarray, r: np.ndarray) -> np.ndarray:
            J = np.empty((6, 6))
            for j in range(6):
                dz = np.zeros(6)
                dz[j] = 1e-6
                J[:, j] = (residual(zs + dz) - r) / 1e-6
            return J

        return residual, jacobian

    tau = 1e-3  # Levenberg-Marquardt's initial damping, relative to max diag(J^T J)

    def solve_at(load: float, zs0: np.ndarray):
        residual, jacobian = shoot_scaled(load)
        return _levenberg_marquardt(residual, jacobian, zs0, tol=tol, max_iter=max_iter, tau=tau)

    def guess_at(load: float) -> np.ndarray:
        return load * _small_deflection_guess(f) / scale

    if initial is None:
        # A coarse RK4 shooting solve is a good start (the answer depends only on the DOP853 shots below).
        coarse = ShootingSolver(rod, nodes=64, jacobian="dp", warm_start=False).solve(f, at=[rod.length])
        z0 = coarse.base / scale if coarse.converged else guess_at(1.0)
        tau = 1e-9 if coarse.converged else tau  # near the root: Newton steps
    else:
        z0 = (initial.base if isinstance(initial, BVPSolution) else np.asarray(initial, dtype=np.float64)) / scale
    zs, r, iters, ok = _with_continuation(solve_at, z0, guess_at)
    z = zs * scale
    y_tip, states = _reference_shoot(rod, f, z, query, rtol, atol)
    r = np.concatenate((y_tip[_N], y_tip[_M])) / scale
    return _solution(rod, query, states, z, r, iters, evals + 1, ok)


def reference_grating_curvature(
    rod: Rod, forces: Sequence[Sequence[float]] | np.ndarray | PointForces, **options
) -> np.ndarray:
    """(G, 2) reference curvature (u_x, u_y) at the rod's gratings [1/m] for one load case of (s, f_x, f_y) rows.

    Options go to :func:`solve_reference`; raises ``RuntimeError`` if the shooting did not converge.
    """
    sol = solve_reference(rod, forces, at=rod.gratings, **options)
    if not sol.converged:
        raise RuntimeError(f"reference shooting did not converge (scaled residual {sol.residual:.3g})")
    return sol.curvature


# ---------------------------------------------------------------------------------------------------- baselines
@dataclass(frozen=True)
class _Grid:
    """The discretisation of one load case: RK4 steps between consecutive grid points."""

    s: np.ndarray  # (n,) grid points [m]: nodes, queries (and force locations in the exact scheme)
    h: np.ndarray  # (n-1,) step lengths [m]
    w: np.ndarray | None  # (n, 3) distributed body-frame load at grid points [N/m] (node scheme), else None
    jumps: dict[int, np.ndarray]  # grid index -> (3,) summed body-frame point force there [N] (exact scheme)
    record: np.ndarray  # (Q,) grid index of each query
    ustar: np.ndarray | None = None  # (n-1, 3) intrinsic curvature on each step [1/m] (precurved), else None


class ShootingSolver:
    """The paper's BVP baselines: fixed-step RK4 on q uniform nodes, shooting with Levenberg-Marquardt.

    Args:
        rod: the rod.
        nodes: q, the number of uniform nodes on [0, L] (q - 1 RK4 intervals, >= 2).
        jacobian: ``"fd"``: forward differences of the tip residual (six perturbed shots, integrated together as
            one vectorised batch); ``"dp"``: derivative propagation (Rucker & Webster 2011), the 18 x 6 tangent
            system integrated alongside the state by the same RK4 steps: the exact Jacobian of the discrete
            residual from one pass.
        scheme: ``"exact"`` (default): a point force acts exactly at its location (the RK4 interval holding it is
            split there, the internal force jumps); ``"nodes"``: the paper's spreading of each force onto the two
            nearest nodes (hat weights, docs/physics.md erratum 3), a distributed load linear between nodes, as
            ``simulate(..., scheme="nodes")``. The exact scheme converges as q^-4, the node scheme as q^-2.
        tol: bound on the scaled tip residual max |(N(L+), M(L)/L)| / F_s.
        max_iter: Levenberg-Marquardt iterations per attempt.
        warm_start: start each solve from the previous converged solution (when no ``initial`` is given), as an
            outer estimation loop wants; otherwise from the small-deflection solution. Levenberg-Marquardt's
            initial damping is 1e-3 max diag(J^T J) from the small-deflection guess, 1e-6 from a previous solution.
        continuation: if a solve fails from its start, march the load from zero (robust at large deflection).

    Grid points are the q nodes, the gratings (and the queries of :meth:`solve`) and, in the exact scheme, the force
    locations: each interval between consecutive grid points is one RK4 step.
    The last solve's counters are in ``last`` (a :class:`BVPSolution`).
    """

    def __init__(
        self,
        rod: Rod,
        nodes: int = 250,
        jacobian: Literal["fd", "dp"] = "dp",
        *,
        scheme: Literal["exact", "nodes"] = "exact",
        tol: float = 1e-10,
        max_iter: int = 100,
        warm_start: bool = True,
        continuation: bool = True,
    ) -> None:
        if not isinstance(rod, Rod):
            raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
        if not isinstance(nodes, (int, np.integer)) or nodes < 2:
            raise OptionsError(f"nodes must be an integer >= 2, got {nodes!r}")
        if jacobian not in ("fd", "dp"):
            raise OptionsError(f"jacobian must be 'fd' or 'dp', got {jacobian!r}")
        if scheme not in ("exact", "nodes"):
            raise OptionsError(f"scheme must be 'exact' or 'nodes', got {scheme!r}")
        self.rod = rod
        self.nodes = int(nodes)
        self.jacobian = jacobian
        self.scheme = scheme
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.warm_start = bool(warm_start)
        self.continuation = bool(continuation)
        self.last: BVPSolution | None = None
        self._evals = 0
        self._kinv = _stiffness(rod)
        self._node_s = np.linspace(0.0, rod.length, self.nodes)

    def __repr__(self) -> str:
        return f"ShootingSolver(nodes={self.nodes}, jacobian={self.jacobian!r}, scheme={self.scheme!r})"

    # ------------------------------------------------------------------ discretisation
    def _grid(self, forces: np.ndarray, query: np.ndarray) -> _Grid:
        L = self.rod.length
        parts = [self._node_s, query, np.asarray(self.rod.breakpoints(), dtype=np.float64)]
        if self.scheme == "exact":
            parts.append(forces[:, 0])
        s = np.unique(np.concatenate(parts))
        record = np.searchsorted(s, query)
        jumps: dict[int, np.ndarray] = {}
        w = None
        if self.scheme == "exact":
            for si, fx, fy in forces:
                k = int(np.searchsorted(s, si))
                jumps[k] = jumps.get(k, np.zeros(3)) + np.array([fx, fy, 0.0])
        else:
            d = L / (self.nodes - 1)
            w_nodes = np.zeros((self.nodes, 3))
            if len(forces):
                hat = np.clip(1.0 - np.abs(forces[:, :1] - self._node_s) / d, 0.0, None)  # (h, q)
                w_nodes[:, :2] = hat.T @ forces[:, 1:] / d  # [N/m]
            w = np.stack([np.interp(s, self._node_s, w_nodes[:, c]) for c in range(3)], axis=1)
        ustar = _intrinsic(self.rod, 0.5 * (s[:-1] + s[1:])) if self.rod.precurved else None
        return _Grid(s=s, h=np.diff(s), w=w, jumps=jumps, record=record, ustar=ustar)

    # ------------------------------------------------------------------ right-hand sides
    def _rhs(self, y: np.ndarray, w: np.ndarray | None, ustar: np.ndarray | None = None) -> np.ndarray:
        """d/ds of K states y (K, 18); w (3,) body-frame distributed load [N/m] or None; ustar (3,) the intrinsic
        curvature on this step [1/m] or None (straight)."""
        K = y.shape[0]
        R = y[:, _R].reshape(K, 3, 3)
        N, M = y[:, _N], y[:, _M]
        u = self._kinv * np.einsum("kji,kj->ki", R, M)
        if ustar is not None:
            u = u + ustar
        t = R[:, :, 2]
        out = np.empty_like(y)
        out[:, _P] = t
        out[:, _R] = (R @ _hat(u)).reshape(K, 9)
        out[:, _N] = 0.0 if w is None else -(R @ w)  # N' = -R w
        out[:, _M] = -_cross(t, N)
        return out

    def _rhs_tangent(self, y: np.ndarray, w: np.ndarray | None, ustar: np.ndarray | None = None) -> np.ndarray:
        """d/ds of [state; 6 tangents] (7, 18): the state's equations and their linearisation (derivative
        propagation): dP' = dR e3, dR' = dR u^ + R du^, du = K^{-1}(dR^T M + R^T dM), dN' = -dR w,
        dM' = -(dR e3) x N - (R e3) x dN."""
        Rs = y[:, _R].reshape(7, 3, 3)  # R and its six derivatives dR
        R = Rs[0]
        N, M = y[0, _N], y[0, _M]
        dN, dM = y[1:, _N], y[1:, _M]
        m = np.einsum("kji,j->ki", Rs, M)  # R^T M and dR^T M
        m[1:] += dM @ R  # + R^T dM
        H = _hat(self._kinv * m)  # u^ and du^
        if ustar is not None:
            H[0] += _hat(ustar)  # u = u* + K^-1 R^T M (u* constant on the step: du has no share of it)
        ts = Rs[:, :, 2]  # t = R e3 and dt = dR e3
        out = np.empty_like(y)
        out[:, _P] = ts
        dRs = Rs @ H[0]  # R u^ and dR u^
        dRs[1:] += R @ H[1:]  # + R du^
        out[:, _R] = dRs.reshape(7, 9)
        out[:, _M] = -_cross(ts, N)  # -(t x N) and -(dt x N)
        out[1:, _M] -= _cross(ts[0], dN)  # - t x dN
        if w is None:
            out[:, _N] = 0.0
        else:
            out[:, _N] = -(Rs @ w)  # -R w and -dR w
        return out

    # ------------------------------------------------------------------ integration
    def _march(self, grid: _Grid, y: np.ndarray, tangent: bool, record: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Classical RK4 base -> tip over the grid. y (K, 18): K shots (``tangent``: row 0 the state, rows 1..6 its
        derivatives). Returns (states at L+ (K, 18), states at the queries (Q, K, 18) or None)."""
        with np.errstate(over="ignore", invalid="ignore"):  # a wild trial step gives inf/nan: LM rejects it
            return self._march_steps(grid, y, tangent, record)

    def _march_steps(self, grid: _Grid, y: np.ndarray, tangent: bool, record: bool):
        rhs = self._rhs_tangent if tangent else self._rhs
        n = len(grid.s)
        rec: Any = np.empty((n, *y.shape)) if record else None  # an array when record
        w = grid.w
        for k in range(n):
            if record:
                rec[k] = y
            if k in grid.jumps:
                y = y.copy()
                f = grid.jumps[k]
                if tangent:
                    y[0, _N] -= y[0, _R].reshape(3, 3) @ f
                    y[1:, _N] -= y[1:, _R].reshape(6, 3, 3) @ f
                else:
                    y[:, _N] -= y[:, _R].reshape(-1, 3, 3) @ f
            if k == n - 1:
                break
            h = grid.h[k]
            if h == 0.0:
                continue
            if w is None:
                w0 = wm = w1 = None
            else:
                w0, w1 = w[k], w[k + 1]
                wm = 0.5 * (w0 + w1)
            us = None if grid.ustar is None else grid.ustar[k]
            k1 = rhs(y, w0, us)
            k2 = rhs(y + (0.5 * h) * k1, wm, us)
            k3 = rhs(y + (0.5 * h) * k2, wm, us)
            k4 = rhs(y + h * k3, w1, us)
            y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return y, (rec[grid.record] if record else None)

    # ------------------------------------------------------------------ shooting
    def tip_residual(
        self, forces, unknowns: np.ndarray, *, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The discrete tip residual r = (N(L+) [N], M(L) [N m]) for base unknowns (N(0) [N], M(0) [N m]) (6,),
        and with ``jacobian`` its Jacobian dr/d(unknowns) (6, 6) by this solver's method (SI, unscaled)."""
        f = _force_array(self.rod, forces)
        grid = self._grid(f, np.zeros(0))
        fs, ms = _scales(self.rod, f)
        scale = np.array([fs] * 3 + [ms] * 3)
        residual, jac = self._problem(grid, scale)
        zs = np.asarray(unknowns, dtype=np.float64) / scale
        r = residual(zs)
        if not jacobian:
            return r * scale, None
        J = jac(zs, r)
        return r * scale, J * scale[:, None] / scale[None, :]

    def _problem(self, grid: _Grid, scale: np.ndarray, keep: dict | None = None):
        """Scaled residual and Jacobian callables for one grid; counts integrations in ``self._evals``.

        With ``keep`` (a dict), each residual evaluation leaves its unknowns and its states at the grid's queries
        there (``keep["z"]``, ``keep["states"]`` (Q, 18)), so the converged solution needs no extra integration.
        """
        record = keep is not None

        def kept(zs: np.ndarray, rec: np.ndarray | None) -> None:
            if record:
                assert keep is not None and rec is not None  # record: a keep dict, and the march recorded
                keep["z"], keep["states"] = zs.copy(), rec[:, 0]

        if self.jacobian == "dp":
            cache: dict[bytes, np.ndarray] = {}

            def integrate_dp(zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                self._evals += 1
                y = np.zeros((7, _STATE))
                y[0] = _initial_state((zs * scale)[None])[0]
                y[1:, _N] = np.eye(6)[:, :3] * scale[:3]  # d N(0) / d zs_j
                y[1:, _M] = np.eye(6)[:, 3:] * scale[3:]  # d M(0) / d zs_j
                tip, rec = self._march(grid, y, tangent=True, record=record)
                kept(zs, rec)
                r = np.concatenate((tip[0, _N], tip[0, _M])) / scale
                J = np.concatenate((tip[1:, _N], tip[1:, _M]), axis=1).T / scale[:, None]
                return r, J

            def residual_dp(zs: np.ndarray) -> np.ndarray:
                r, J = integrate_dp(zs)
                cache.clear()
                cache[zs.tobytes()] = J
                return r

            def jac_dp(zs: np.ndarray, r: np.ndarray) -> np.ndarray:
                J = cache.get(zs.tobytes())
                if J is None:
                    _, J = integrate_dp(zs)
                return J

            return residual_dp, jac_dp

        def shots(zs: np.ndarray, rec: bool = False) -> np.ndarray:
            self._evals += zs.shape[0]
            tip, states = self._march(grid, _initial_state(zs * scale), tangent=False, record=rec)
            if rec:
                kept(zs[0], states)
            return np.concatenate((tip[:, _N], tip[:, _M]), axis=1) / scale

        def residual(zs: np.ndarray) -> np.ndarray:
            return shots(zs[None], rec=record)[0]

        def jac(zs: np.ndarray, r: np.ndarray) -> np.ndarray:
            # Forward differences, the six perturbed shots in one vectorised integration.
            steps = 1.5e-8 * np.maximum(1.0, np.abs(zs))
            perturbed = zs + np.diag(steps)
            return ((shots(perturbed) - r) / steps[:, None]).T

        return residual, jac

    def solve(
        self,
        forces: Sequence[Sequence[float]] | np.ndarray | PointForces,
        *,
        at: Sequence[float] | np.ndarray | None = None,
        initial: np.ndarray | BVPSolution | None = None,
    ) -> BVPSolution:
        """Solve one load case.

        Args:
            forces: rows (s [m], f_x [N], f_y [N]) (body frame), or a :class:`PointForces` of batch size 1.
            at: (S,) non-decreasing positions [m] to report (added to the grid); default: 0, the gratings and L.
            initial: base unknowns (6,) (N(0) [N], M(0) [N m]) or a previous solution; default: the previous
                converged solution when ``warm_start``, else the small-deflection solution.
        Returns:
            :class:`BVPSolution` with iterations, evaluations (integrations) and the converged flag.
        """
        f = _force_array(self.rod, forces)
        query = _default_query(self.rod, at)
        grid = self._grid(f, query)
        fs, ms = _scales(self.rod, f)
        scale = np.array([fs] * 3 + [ms] * 3)
        self._evals = 0

        tau = 1e-3  # Levenberg-Marquardt's initial damping (relative to max diag J^T J) from a cold start
        keep: dict = {}  # the last full-load shot: its unknowns and states at the queries

        def solve_at(load: float, zs0: np.ndarray):
            fl = f.copy()
            fl[:, 1:] *= load
            if load == 1.0:
                residual, jac = self._problem(grid, scale, keep)
            else:
                residual, jac = self._problem(self._grid(fl, query), scale)
            return _levenberg_marquardt(residual, jac, zs0, tol=self.tol, max_iter=self.max_iter, tau=tau)

        def guess_at(load: float) -> np.ndarray:
            return load * _small_deflection_guess(f) / scale

        if initial is not None:
            z0 = (initial.base if isinstance(initial, BVPSolution) else np.asarray(initial, dtype=np.float64)) / scale
            tau = 1e-6  # near a previous solution: close to Newton steps
        elif self.warm_start and self.last is not None and self.last.converged:
            z0 = self.last.base / scale
            tau = 1e-6
        else:
            z0 = guess_at(1.0)
        if self.continuation:
            zs, r, iters, ok = _with_continuation(solve_at, z0, guess_at)
        else:
            zs, r, iters, ok = solve_at(1.0, z0)
        z = zs * scale
        if "z" in keep and np.array_equal(keep["z"], zs):
            states = keep["states"]
        else:
            tip, rec = self._march(grid, _initial_state(z[None]), tangent=False, record=True)
            self._evals += 1
            assert rec is not None  # record=True
            states = rec[:, 0]
            r = np.concatenate((tip[0, _N], tip[0, _M])) / scale
        sol = _solution(self.rod, query, states, z, r, iters, self._evals, ok)
        self.last = sol
        return sol

    def grating_curvature(
        self,
        forces: Sequence[Sequence[float]] | np.ndarray | PointForces,
        *,
        initial: np.ndarray | BVPSolution | None = None,
    ) -> np.ndarray:
        """(G, 2) curvature (u_x, u_y) at the rod's gratings [1/m]; see :meth:`solve` (``self.last`` holds the
        counters and the converged flag)."""
        return self.solve(forces, at=self.rod.gratings, initial=initial).curvature
