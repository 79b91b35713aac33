"""The global-frame BVP: reference solver, the body-frame IVP against it, and the paper's shooting baselines."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.model.global_bvp import (
    BVPSolution,
    ShootingSolver,
    reference_grating_curvature,
    solve_reference,
)

ROD = tr.presets.nitinol290()
L, EI = ROD.length, ROD.bending_stiffness

# Large deflections (base-to-tip bending of 128, 141 and 168 degrees), non-planar: forces in different directions.
LARGE = {
    "two": [(0.15, 1.5, 0.0), (0.25, 0.0, -1.0)],
    "three": [(0.1, 0.8, 0.6), (0.2, -0.5, 1.2), (0.29, 0.6, 0.4)],
    "three_hairpin": [(0.07, 1.5, -0.4), (0.17, -0.3, 1.1), (0.26, 0.7, 0.5)],
}


@functools.cache
def reference(name: str) -> BVPSolution:
    """Reference solution at 0, the gratings, L and the force locations (cached across tests)."""
    forces = LARGE[name]
    at = np.unique(np.concatenate(([0.0, L], ROD.gratings, [f[0] for f in forces])))
    return solve_reference(ROD, forces, at=at)


def at_gratings(sol: BVPSolution) -> np.ndarray:
    idx = np.searchsorted(sol.s, ROD.gratings)
    assert np.allclose(sol.s[idx], ROD.gratings)
    return sol.u[idx, :2]


def bending_deg(sol: BVPSolution) -> float:
    return float(np.degrees(np.arccos(np.clip(sol.R[-1][2, 2], -1.0, 1.0))))


# ------------------------------------------------------------------------------------------------ the reference
def test_reference_small_deflection_sign_and_beam_theory():
    # One small f_y > 0 at s_i: u_x(s) = -f_y (s_i - s)/EI before s_i, 0 beyond; the rod deflects towards +y.
    si, fy = 0.17, 1e-4
    s = np.linspace(0.0, L, 30)
    sol = solve_reference(ROD, [(si, 0.0, fy)], at=s)
    assert sol.converged
    expected = -fy * np.clip(si - s, 0.0, None) / EI
    scale = np.abs(expected).max()
    assert np.abs(sol.u[:, 0] - expected).max() <= 1e-5 * scale  # nonlinear terms ~ (f L^2/EI)^2 ~ 1e-6
    assert np.abs(sol.u[:, 1:]).max() <= 1e-9 * scale
    assert sol.P[-1, 1] == pytest.approx(fy * si**2 * (3 * L - si) / (6 * EI), rel=1e-5)


def test_reference_satisfies_the_boundary_and_balance_laws():
    forces = LARGE["three"]
    sol = reference("three")
    assert sol.converged and sol.residual <= 1e-11
    assert sol.s[0] == 0.0 and np.abs(sol.P[0]).max() == 0.0 and np.abs(sol.R[0] - np.eye(3)).max() == 0.0
    RtR = np.einsum("sji,sjk->sik", sol.R, sol.R)
    assert np.abs(RtR - np.eye(3)).max() <= 1e-12
    assert np.abs(sol.u[:, 2]).max() <= 1e-9 * np.abs(sol.u).max()  # no twist
    # Global equilibrium of the whole rod: N(0) = sum F_i, M(0) = sum P(s_i) x F_i, F_i = R(s_i) (f_x, f_y, 0).
    idx = np.searchsorted(sol.s, [f[0] for f in forces])
    F = np.stack([sol.R[k] @ np.array([fx, fy, 0.0]) for k, (_, fx, fy) in zip(idx, forces, strict=False)])
    fscale = np.abs(F).sum()
    assert np.abs(sol.N[0] - F.sum(0)).max() <= 1e-10 * fscale
    assert np.abs(sol.M[0] - np.cross(sol.P[idx], F).sum(0)).max() <= 1e-10 * fscale * L
    # The internal force proximal to the last force is that force alone.
    assert np.abs(sol.N[idx[-1]] - F[-1]).max() <= 1e-10 * fscale


def test_torsional_stiffness_does_not_matter():
    # docs/physics.md, erratum 2: u_z stays 0, so GJ (here through Poisson's ratio) does not change the solution.
    forces = [(0.12, 0.9, 0.4), (0.24, -0.3, 0.8)]
    a = reference_grating_curvature(ROD.with_(poisson_ratio=0.0), forces)
    b = reference_grating_curvature(ROD.with_(poisson_ratio=0.45), forces)
    assert np.abs(a - b).max() <= 1e-9 * np.abs(a).max()


def test_reference_accepts_point_forces_and_checks_inputs():
    forces = [(0.2, 0.1, -0.2), (0.05, 0.3, 0.0)]
    a = reference_grating_curvature(ROD, forces)
    b = reference_grating_curvature(ROD, tr.PointForces.from_lists([forces], max_forces=3))
    assert a.shape == (ROD.num_gratings, 2)
    assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max()
    zero = solve_reference(ROD, [])
    assert zero.converged and zero.iterations == 0 and np.abs(zero.u).max() == 0.0
    with pytest.raises(ValueError, match="force locations"):
        solve_reference(ROD, [(0.3, 1.0, 0.0)])
    with pytest.raises(ValueError, match="shape"):
        solve_reference(ROD, [(0.1, 1.0)])
    with pytest.raises(ValueError, match="batch size 1"):
        solve_reference(ROD, tr.PointForces.from_lists([forces, forces]))


# ------------------------------------------------------------------------------------------------ IVP vs BVP
@pytest.mark.parametrize("name", sorted(LARGE))
def test_body_frame_ivp_matches_global_bvp_at_large_deflection(name):
    ref = reference(name)
    assert ref.converged
    assert bending_deg(ref) >= 90.0
    sim = tr.simulate(ROD, tr.PointForces.from_lists([LARGE[name]]), at=torch.tensor(ref.s))
    u_ref = at_gratings(ref)
    rel = np.abs(sim.grating_curvature[0].numpy() - u_ref).max() / np.abs(u_ref).max()
    assert rel <= 1e-6, f"{name}: IVP vs BVP relative difference {rel:.3g}"
    # The body-frame internal force n = R^T N along the rod, on the proximal side at the force locations.
    n_ref = np.einsum("sji,sj->si", ref.R, ref.N)
    assert torch.equal(sim.s, torch.tensor(ref.s))
    rel_n = np.abs(sim.internal_force[0].numpy() - n_ref).max() / np.abs(n_ref).max()
    assert rel_n <= 1e-6, f"{name}: internal force relative difference {rel_n:.3g}"


# ------------------------------------------------------------------------------------------------ baselines
@pytest.mark.parametrize("jacobian", ["fd", "dp"])
def test_baselines_converge_to_the_reference_as_q_grows(jacobian):
    ref = at_gratings(reference("two"))
    qs = np.array([25, 50, 100])
    errors = []
    for q in qs:
        solver = ShootingSolver(ROD, nodes=int(q), jacobian=jacobian, warm_start=False)
        u = solver.grating_curvature(LARGE["two"])
        assert solver.last.converged and solver.last.residual <= solver.tol
        errors.append(np.abs(u - ref).max() / np.abs(ref).max())
    errors = np.array(errors)
    # Point forces act exactly at their location, so the error is RK4's: slope -4 in q.
    slope = np.polyfit(np.log(qs), np.log(errors), 1)[0]
    assert np.all(np.diff(errors) < 0), errors
    assert slope <= -3.5, (slope, errors)
    assert errors[-1] <= 1e-6, errors


def test_fd_and_dp_find_the_same_discrete_solution():
    forces = LARGE["three"]
    fd = ShootingSolver(ROD, nodes=60, jacobian="fd", warm_start=False).solve(forces)
    dp = ShootingSolver(ROD, nodes=60, jacobian="dp", warm_start=False).solve(forces)
    assert fd.converged and dp.converged
    assert np.abs(fd.u - dp.u).max() <= 1e-8 * np.abs(dp.u).max()
    # Derivative propagation pays one (tangent) integration per iteration; fd pays 1 + 6 shots.
    assert dp.evaluations <= dp.iterations + 2 < fd.evaluations


def test_derivative_propagation_gives_the_finite_difference_jacobian():
    forces = LARGE["two"]
    solver = ShootingSolver(ROD, nodes=40, jacobian="dp")
    fd_solver = ShootingSolver(ROD, nodes=40, jacobian="fd")
    z = np.array([0.3, -0.8, 0.2, 0.12, 0.05, -0.01])  # away from the solution: a generic point
    r, J = solver.tip_residual(forces, z)
    r_fd, J_fd = fd_solver.tip_residual(forces, z)
    assert np.array_equal(r, r_fd)
    # Central differences of the discrete residual, step relative to each unknown.
    J_c = np.empty((6, 6))
    for j in range(6):
        dz = np.zeros(6)
        dz[j] = 1e-6 * max(abs(z[j]), 1e-2)
        plus, _ = solver.tip_residual(forces, z + dz, jacobian=False)
        minus, _ = solver.tip_residual(forces, z - dz, jacobian=False)
        J_c[:, j] = (plus - minus) / (2 * dz[j])
    # Compare column by column in consistent units (columns scale with the unknown's unit).
    for j in range(6):
        scale = np.abs(J_c[:, j]).max()
        assert np.abs(J[:, j] - J_c[:, j]).max() <= 1e-7 * scale
        assert np.abs(J_fd[:, j] - J_c[:, j]).max() <= 1e-5 * scale


def test_warm_start_from_a_previous_solution():
    forces = LARGE["two"]
    nearby = [(s + 0.002, fx * 1.02, fy * 0.98) for s, fx, fy in forces]
    solver = ShootingSolver(ROD, nodes=50, jacobian="dp")
    cold = solver.solve(nearby)  # the first solve starts from the small-deflection guess
    solver.solve(forces)
    warm = solver.solve(nearby)  # starts from the solution for `forces`
    explicit = ShootingSolver(ROD, nodes=50, jacobian="dp", warm_start=False).solve(nearby, initial=solver.last)
    assert cold.converged and warm.converged
    assert warm.iterations <= 4 < cold.iterations
    assert np.abs(warm.u - cold.u).max() <= 1e-8 * np.abs(cold.u).max()
    assert explicit.iterations <= 1  # already at the root: `initial=` took the previous (nearby) solution


def test_node_scheme_matches_the_body_frame_node_scheme():
    # Two independent implementations of the paper's spreading (global-frame RK4, body-frame RKN) converge to
    # each other as q grows: their difference is integration error only.
    forces = [(0.137, 0.9, 0.3), (0.221, -0.2, 0.7)]
    loads = tr.PointForces.from_lists([forces])
    diffs = []
    for q in (50, 100, 200):
        u = ShootingSolver(ROD, nodes=q, jacobian="dp", scheme="nodes").grating_curvature(forces)
        v = tr.simulate(ROD, loads, scheme="nodes", nodes=q).grating_curvature[0].numpy()
        diffs.append(np.abs(u - v).max() / np.abs(v).max())
    assert diffs[0] > diffs[1] > diffs[2]
    assert diffs[2] <= 1e-4, diffs


def test_shooting_solver_checks_inputs():
    with pytest.raises(ValueError, match="nodes"):
        ShootingSolver(ROD, nodes=1)
    with pytest.raises(ValueError, match="jacobian"):
        ShootingSolver(ROD, jacobian="newton")
    with pytest.raises(ValueError, match="scheme"):
        ShootingSolver(ROD, scheme="spline")
    with pytest.raises(ValueError, match="force locations"):
        ShootingSolver(ROD).solve([(-0.01, 1.0, 0.0)])


@pytest.mark.slow
def test_very_large_load_with_continuation():
    # 4.1 N at 0.2 m: 151 degrees of bending; plain LM from the small-deflection guess struggles, the load
    # continuation fallback gets there. Both baselines then agree with the reference.
    forces = [(0.2, 4.0, 1.0)]
    ref = solve_reference(ROD, forces)
    assert ref.converged and bending_deg(ref) > 150.0
    for jac in ("fd", "dp"):
        sol = ShootingSolver(ROD, nodes=100, jacobian=jac, warm_start=False).solve(forces)
        assert sol.converged
        assert np.abs(sol.u - ref.u).max() <= 1e-5 * np.abs(ref.u).max()
