"""An independent reference for the body-frame rod model: scipy's DOP853 on the FULL body-frame system.

docs/physics.md, "The body-frame equations": for a straight, isotropic, inextensible, unshearable rod with no external
moment (u_z = 0),

    u_x' = n_y / EI,    u_y' = -n_x / EI,    n' = -f - u x n,    u = (u_x, u_y, 0),

integrated from the free tip (u = 0, n = 0 at s = L) to the clamped base; crossing a point force f_i = (f_x, f_y, 0)
(body frame) at s_i going from tip to base, n jumps: n(s_i^-) = n(s_i^+) + f_i. Unlike torchrod's integrator this
keeps all five states (n_z included: no use of m_z = -|u|^2/2) and uses a general-purpose adaptive solver.

The frame rides along: Q(s) = R(L)^T R(s) obeys Q' = Q u^ with Q(L) = I, so R(L) = Q(0)^T and R(s) = Q(0)^T Q(s).
This gives the global frame at every query without a second (base-to-tip) pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

__all__ = ["Reference", "reduced_reference", "reference_solution"]


@dataclass(frozen=True)
class Reference:
    """Reference state at the queries (in the order given).

    u: (Q, 2) curvature [1/m]; n: (Q, 3) body-frame internal force [N] (proximal side of a force at the query);
    R: (Q, 3, 3) rotation from body to global frame; tip_angle: angle between base and tip tangents [rad].
    """

    u: np.ndarray
    n: np.ndarray
    R: np.ndarray
    tip_angle: float


def _rhs(ei: float):
    def rhs(_s: float, y: np.ndarray) -> np.ndarray:
        ux, uy, nx, ny, nz = y[:5]
        q = y[5:].reshape(3, 3)
        u_hat = np.array([[0.0, 0.0, uy], [0.0, 0.0, -ux], [-uy, ux, 0.0]])
        u_cross_n = (uy * nz, -ux * nz, ux * ny - uy * nx)  # u x n with u_z = 0
        dn = [-c for c in u_cross_n]  # n' = -u x n between point forces (f = 0 there)
        return np.concatenate(([ny / ei, -nx / ei], dn, (q @ u_hat).ravel()))

    return rhs


def reference_solution(
    length: float,
    bending_stiffness: float,
    forces: Sequence[tuple[float, float, float]],
    query: Sequence[float],
    *,
    rtol: float = 1e-12,
    atol: float = 1e-14,
) -> Reference:
    """Integrate tip to base with DOP853 between events (forces and queries), exact jumps at the forces.

    Args:
        length: L [m]; bending_stiffness: EI [N m^2].
        forces: (s [m], f_x [N], f_y [N]) body-frame point forces, s in [0, L].
        query: positions [m] in [0, L].
    """
    by_location: dict[float, list[tuple[float, float]]] = {}
    for s, fx, fy in forces:
        by_location.setdefault(float(s), []).append((float(fx), float(fy)))
    events = sorted({float(length), 0.0, *by_location, *(float(q) for q in query)}, reverse=True)
    rhs = _rhs(float(bending_stiffness))
    y = np.concatenate((np.zeros(5), np.eye(3).ravel()))
    state: dict[float, np.ndarray] = {}
    for k, a in enumerate(events):
        for fx, fy in by_location.get(a, []):
            y[2] += fx  # n(s_i^-) = n(s_i^+) + f_i
            y[3] += fy
        state[a] = y.copy()
        if k + 1 < len(events):
            sol = solve_ivp(rhs, (a, events[k + 1]), y, method="DOP853", rtol=rtol, atol=atol)
            if not sol.success:
                raise RuntimeError(sol.message)
            y = sol.y[:, -1].copy()
    r_tip = state[0.0][5:].reshape(3, 3).T  # R(L) = Q(0)^T
    rows = [state[float(q)] for q in query]
    u = np.array([r[:2] for r in rows])
    n = np.array([r[2:5] for r in rows])
    R = np.array([r_tip @ r[5:].reshape(3, 3) for r in rows])
    tangent = r_tip[:, 2]
    tip_angle = float(np.arctan2(np.hypot(tangent[0], tangent[1]), tangent[2]))
    return Reference(u=u, n=n, R=R, tip_angle=tip_angle)


def reduced_reference(
    length: float, bending_stiffness: float, query: Sequence[float], s_force: float, fx: float, fy: float
) -> np.ndarray:
    """(Q, 2) curvature [1/m] at ``query`` under one force (fx, fy) [N] at s_force [m], by DOP853 (rtol 1e-13) on
    the reduced equation U'' = -|U|^2 U / 2, U = u_x + i u_y, in t = L - s from the force to the base, starting from
    U = 0, U_t = (-f_y + i f_x) / EI (U = 0 distal to the force). Four states instead of fourteen: cheap enough for
    loads that loop the rod hundreds of times."""
    ei = float(bending_stiffness)

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        g = -0.5 * (y[0] * y[0] + y[1] * y[1])
        return [y[2], y[3], g * y[0], g * y[1]]

    s = np.asarray(query, dtype=np.float64)
    proximal = s < s_force
    t_query = length - s[proximal]
    t_eval = np.sort(t_query)
    start = [0.0, 0.0, -fy / ei, fx / ei]
    atol = 1e-13 * float(np.hypot(fx, fy)) / ei
    sol = solve_ivp(rhs, (length - s_force, length), start, method="DOP853", t_eval=t_eval, rtol=1e-13, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    u = np.zeros((s.size, 2))
    u[proximal] = sol.y[:2].T[np.searchsorted(t_eval, t_query)]
    return u
