"""The rod's shape from its curvature: beam theory, exact arcs, the global-frame BVP, convergence order."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.model.global_bvp import solve_reference
from torchrod.model.shape import Shape, bending_angle, rod_shape, shape

ROD = tr.presets.nitinol290()
L, EI = ROD.length, ROD.bending_stiffness


def orthonormality_error(frames: torch.Tensor) -> float:
    eye = torch.eye(3, dtype=frames.dtype)
    return float((frames.transpose(-1, -2) @ frames - eye).abs().max())


def test_small_deflection_matches_the_cantilever_formulas():
    # Tip deflection F L^3 / (3 EI) towards the force, and F a^2 (3L - a) / (6 EI) for a force at s = a.
    F, a = 1e-4, 0.15
    loads = tr.PointForces.from_lists([[(L, 0.0, F)], [(L, F, 0.0)], [(L, -F, 0.0)], [(a, 0.0, F)]])
    tip = shape(ROD, loads, samples=200).tip
    d_tip, d_mid = F * L**3 / (3 * EI), F * a**2 * (3 * L - a) / (6 * EI)
    expected = torch.tensor([[0.0, d_tip, L], [d_tip, 0.0, L], [-d_tip, 0.0, L], [0.0, d_mid, L]], dtype=torch.float64)
    # Nonlinear terms are of relative size (F L^2 / EI)^2 ~ 1e-6; the shortening along z is ~ d^2 / L.
    assert torch.allclose(tip[:, :2], expected[:, :2], rtol=1e-4, atol=1e-12)
    assert torch.allclose(tip[:, 2], expected[:, 2], atol=1e-6)


def test_constant_curvature_gives_an_exact_circular_arc():
    # u = (k, 0): R = Rot_x(k s), tangent (0, -sin ks, cos ks), P = (0, (cos ks - 1)/k, sin(ks)/k), for any S.
    k = 7.0  # k L = 2.03 rad: beyond 90 degrees
    s = torch.linspace(0.0, L, 13, dtype=torch.float64)
    u = torch.zeros(2, 13, 2, dtype=torch.float64)
    u[0, :, 0] = k
    u[1, :, 1] = k  # about y: tangent (sin ks, 0, cos ks), P = ((1 - cos ks)/k, 0, sin(ks)/k)
    sh = rod_shape(s, u)
    ks = k * s
    assert torch.allclose(sh.position[0, :, 1], (torch.cos(ks) - 1) / k, atol=1e-15, rtol=0)
    assert torch.allclose(sh.position[0, :, 2], torch.sin(ks) / k, atol=1e-15, rtol=0)
    assert torch.allclose(sh.position[1, :, 0], (1 - torch.cos(ks)) / k, atol=1e-15, rtol=0)
    assert torch.allclose(sh.tangent[0, :, 1], -torch.sin(ks), atol=1e-14, rtol=0)
    assert torch.allclose(bending_angle(sh), torch.full((2,), k * L, dtype=torch.float64), atol=1e-13, rtol=0)
    assert sh.position[:, :, 0][0].abs().max() == 0.0


def test_tip_matches_the_global_bvp_at_large_deflection():
    forces = [(0.1, 0.8, 0.6), (0.2, -0.5, 1.2), (0.29, 0.6, 0.4)]  # non-planar, 141 degrees of bending
    ref = solve_reference(ROD, forces, at=[0.0, L])
    sh = shape(ROD, tr.PointForces.from_lists([forces]), samples=401)
    assert math.degrees(float(bending_angle(sh))) == pytest.approx(math.degrees(math.acos(ref.R[-1][2, 2])), abs=1e-3)
    assert math.degrees(float(bending_angle(sh))) > 90.0
    error = np.abs(sh.tip[0].numpy() - ref.P[-1]).max()
    assert error <= 1e-5, error  # second order: 3.7e-6 m with 400 intervals here (0.0013 % of L)
    assert np.abs(sh.frames[0, -1].numpy() - ref.R[-1]).max() <= 2e-5
    assert orthonormality_error(sh.frames) <= 1e-13


def test_second_order_convergence_with_the_sample_spacing():
    # Curvature profile from the reference BVP (accurate to ~1e-10) with forces on every grid's nodes, so the kinks
    # of u sit on samples; the tip position and frame error must fall as h^2.
    forces = [(L * 8 / 25, 1.2, 0.5), (L * 16 / 25, -0.6, 1.0), (L, 0.3, -0.7)]
    fine = 400
    ref = solve_reference(ROD, forces, at=np.linspace(0.0, L, fine + 1))
    intervals = np.array([25, 50, 100, 200])
    err_p, err_r = [], []
    for n in intervals:
        idx = np.arange(0, fine + 1, fine // n)
        sh = rod_shape(torch.tensor(ref.s[idx]), torch.tensor(ref.u[None, idx, :2]))
        err_p.append(np.abs(sh.tip[0].numpy() - ref.P[-1]).max())
        err_r.append(np.abs(sh.frames[0, -1].numpy() - ref.R[-1]).max())
        assert orthonormality_error(sh.frames) <= 1e-14
    h = L / intervals
    slope_p = np.polyfit(np.log(h), np.log(err_p), 1)[0]
    slope_r = np.polyfit(np.log(h), np.log(err_r), 1)[0]
    assert 1.9 <= slope_p <= 2.1, (slope_p, err_p)
    assert 1.9 <= slope_r <= 2.1, (slope_r, err_r)


def test_frames_stay_orthonormal_and_the_tangent_is_the_centreline_derivative():
    g = torch.Generator().manual_seed(3)
    s = torch.linspace(0.0, L, 300, dtype=torch.float64)
    u = 30.0 * torch.randn(4, 300, 2, generator=g, dtype=torch.float64)  # rough, large curvature
    sh = rod_shape(s, u)
    assert orthonormality_error(sh.frames) <= 1e-13
    assert torch.allclose(torch.linalg.det(sh.frames), torch.ones(4, 300, dtype=torch.float64), atol=1e-13)
    # Inextensible: consecutive points are at most one spacing apart (chord <= arc), and nearly that.
    chord = torch.linalg.vector_norm(sh.position.diff(dim=1), dim=-1)
    ds = s.diff()
    assert bool((chord <= ds * (1 + 1e-12)).all()) and bool((chord >= ds * 0.99).all())


def test_batched_equals_looped_and_dtype_follows():
    g = torch.Generator().manual_seed(0)
    s = torch.linspace(0.0, L, 50, dtype=torch.float64)
    u = 10.0 * torch.randn(3, 50, 2, generator=g, dtype=torch.float64)
    batched = rod_shape(s, u)
    for b in range(3):
        single = rod_shape(s, u[b : b + 1])
        assert torch.allclose(batched.position[b], single.position[0], atol=1e-15, rtol=0)
        assert torch.allclose(batched.frames[b], single.frames[0], atol=1e-15, rtol=0)
    low = rod_shape(s.float(), u.float())
    assert low.position.dtype == torch.float32 and low.frames.dtype == torch.float32
    assert torch.allclose(low.position.double(), batched.position, atol=1e-5)


def test_gradcheck_in_curvature_and_positions():
    g = torch.Generator().manual_seed(1)
    rest = torch.tensor([0.04, 0.1, 0.13, 0.2], dtype=torch.float64, requires_grad=True)  # s_0 = 0 stays fixed
    u = (5.0 * torch.randn(2, 5, 2, generator=g, dtype=torch.float64)).requires_grad_()

    def f(rest, u):
        sh = rod_shape(torch.cat((rest.new_zeros(1), rest)), u)
        return sh.position, sh.frames

    assert torch.autograd.gradcheck(f, (rest, u))
    s = torch.cat((rest.new_zeros(1), rest))
    # Zero curvature takes the series branch: gradients there are finite and exact (dP_y/du_x(0) = -s_tip^2/2).
    zero = torch.zeros(1, 5, 2, dtype=torch.float64, requires_grad=True)
    tip_y = rod_shape(s.detach(), zero).tip[0, 1]
    (grad,) = torch.autograd.grad(tip_y, zero)
    assert torch.isfinite(grad).all()
    # Trapezoid weights of int_0^L (s - L) u_x ds, the linearised deflection.
    sd = s.detach()
    w = torch.zeros(5, dtype=torch.float64)
    h = sd.diff()
    w[:-1] += h / 2 * (sd[:-1] + h / 2 - sd[-1])  # midpoint lever of each interval
    w[1:] += h / 2 * (sd[:-1] + h / 2 - sd[-1])
    assert torch.allclose(grad[0, :, 0], w, atol=1e-15)
    assert torch.equal(grad[0, :, 1], torch.zeros(5, dtype=torch.float64))


def test_rod_shape_checks_inputs():
    s = torch.linspace(0.0, L, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"\(B, S, 2\)"):
        rod_shape(s, torch.zeros(1, 4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="start at the clamped base"):
        rod_shape(s + 0.01, torch.zeros(1, 5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="non-decreasing"):
        rod_shape(s.flip(0).roll(1), torch.zeros(1, 5, 2, dtype=torch.float64))
    with pytest.raises(TypeError):
        rod_shape(s.tolist(), torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match="samples"):
        shape(ROD, tr.PointForces.from_lists([[(0.1, 0.0, 0.1)]]), samples=1)
    single = rod_shape(s[:1], torch.zeros(2, 1, 2, dtype=torch.float64))
    assert isinstance(single, Shape) and single.position.shape == (2, 1, 3)
    assert torch.equal(bending_angle(single), torch.zeros(2, dtype=torch.float64))
