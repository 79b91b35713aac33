"""The Runge-Kutta-Nystrom march behind the forward model: orders, the discrete adjoint, torch.func, step counts.

Orders are fitted on a two-dimensional motion of U'' = -|U|^2 U / 2: from U = 0 a kick W = (3, 0), a crossing of
0.5, a kick (0, 4), a crossing of 0.7; the reference is scipy's DOP853 at rtol 1e-13. (On one-dimensional motions
some of the order conditions drop out and the 8th-order method shows a slope near 10.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

import torchrod as tr
from torchrod.model import nystrom
from torchrod.model.body_frame import step_counts

F64 = torch.float64
SEGMENTS = ((0.5, (3.0, 0.0)), (0.7, (0.0, 4.0)))  # (length, kick before it)


def _reference_end() -> np.ndarray:
    def rhs(_t, y):
        u = y[:2]
        return np.concatenate((y[2:], -0.5 * (u @ u) * u))

    y = np.zeros(4)
    for length, kick in SEGMENTS:
        y[2:] += kick
        y = solve_ivp(rhs, (0.0, length), y, method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    return y


def _march_end(tab, steps: int) -> np.ndarray:
    h, kick = [0.0], [(0.0, 0.0)]
    for length, k in SEGMENTS:
        kick[-1] = k  # applied after the previous step: before this segment
        h += [length / steps] * steps
        kick += [(0.0, 0.0)] * steps
    z = nystrom.march(torch.tensor([h], dtype=F64), tab, kick=torch.tensor([kick], dtype=F64))
    return z[0, -1].numpy()


@pytest.mark.parametrize("name", ["rkn4", "rkn6", "rkn8"])
def test_each_method_converges_at_its_order(name):
    tab = nystrom.METHODS[name]
    ref = _reference_end()
    assert np.abs(ref[:2]).min() > 0.5  # the motion left the first kick's line
    steps, errors = [], []
    for n in (2, 3, 4, 6, 8, 12, 16, 24, 32):
        err = float(np.abs(_march_end(tab, n) - ref).max() / np.abs(ref).max())
        if 1e-12 < err < 1e-3:  # asymptotic range, clear of round-off
            steps.append(n)
            errors.append(err)
    assert len(steps) >= 3, (name, steps, errors)
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - tab.order) < 0.5, (name, slope, errors)


def _random_inputs(B: int, K: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    h = (0.01 + 0.03 * torch.rand(B, K, generator=g, dtype=F64)).requires_grad_()
    kick = (10 * torch.randn(B, K, 2, generator=g, dtype=F64)).requires_grad_()
    forcing = (100 * torch.randn(B, K + 1, 2, generator=g, dtype=F64)).requires_grad_()
    return h, kick, forcing


@pytest.mark.parametrize("name", ["rkn4", "rkn6", "rkn8"])
def test_discrete_adjoint_passes_gradcheck(name):
    tab = nystrom.METHODS[name]
    h, kick, forcing = _random_inputs(3, 5)
    assert torch.autograd.gradcheck(lambda h, k: nystrom.march(h, tab, kick=k), (h, kick))
    assert torch.autograd.gradcheck(lambda h, k, p: nystrom.march(h, tab, kick=k, forcing=p), (h, kick, forcing))


def test_the_adjoint_and_plain_autograd_agree_in_values_and_gradients():
    h, kick, forcing = _random_inputs(5, 9, seed=1)
    weights = torch.randn(5, 9, 4, generator=torch.Generator().manual_seed(2), dtype=F64)
    results = {}
    for adjoint in (True, False):
        z = nystrom.march(h, nystrom.RKN8, kick=kick, forcing=forcing, adjoint=adjoint)
        grads = torch.autograd.grad((z * weights).sum(), (h, kick, forcing))
        results[adjoint] = (z.detach(), grads)
    (z, g), (z0, g0) = results[True], results[False]
    assert z0.abs().max() > 1.0  # a nonlinear regime, not a trivially small state
    torch.testing.assert_close(z, z0, rtol=1e-12, atol=1e-12)
    for a, b in zip(g, g0, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("adjoint", [True, False])
def test_torch_func_transforms_compose_with_the_march(adjoint):
    """jacrev and vmap over the march (the adjoint's backward run under vmap by jacrev) give the Jacobian that
    autograd gives row by row."""
    h, kick, forcing = (t.detach() for t in _random_inputs(2, 4))

    def f(k: torch.Tensor) -> torch.Tensor:
        return nystrom.march(h, nystrom.RKN8, kick=k, forcing=forcing, adjoint=adjoint)

    jac = torch.func.jacrev(f)(kick)
    ref = torch.autograd.functional.jacobian(lambda k: nystrom.march(h, nystrom.RKN8, kick=k, forcing=forcing,
                                                                     adjoint=False), kick)  # fmt: skip
    torch.testing.assert_close(jac, ref, rtol=1e-12, atol=1e-12)
    per_row = torch.func.vmap(lambda hr, kr: nystrom.march(hr[None], nystrom.RKN8, kick=kr[None], adjoint=adjoint))
    torch.testing.assert_close(per_row(h, kick)[:, 0], nystrom.march(h, nystrom.RKN8, kick=kick), rtol=1e-13, atol=0)


def test_a_second_derivative_through_the_adjoint_is_refused_and_works_without_it():
    h, kick, _ = _random_inputs(2, 4)
    z = nystrom.march(h, nystrom.RKN8, kick=kick)
    with pytest.raises(tr.TorchrodError, match="adjoint=False"):
        torch.autograd.grad(z.sum(), kick, create_graph=True)
    # without the adjoint: the Hessian-vector product matches finite differences of the gradient
    v = torch.randn(kick.shape, generator=torch.Generator().manual_seed(4), dtype=F64)

    def grad_at(k: torch.Tensor, create: bool) -> torch.Tensor:
        out = nystrom.march(h.detach(), nystrom.RKN8, kick=k, adjoint=False)
        return torch.autograd.grad((out**2).sum(), k, create_graph=create)[0]

    k = kick.detach().requires_grad_()
    (hv,) = torch.autograd.grad((grad_at(k, True) * v).sum(), k)
    eps = 1e-6
    fd = (grad_at((kick.detach() + eps * v).requires_grad_(), False) - grad_at(
        (kick.detach() - eps * v).requires_grad_(), False)) / (2 * eps)  # fmt: skip
    torch.testing.assert_close(hv, fd, rtol=1e-6, atol=1e-6)


def test_float32_stays_float32():
    h, kick, _ = _random_inputs(4, 6)
    for adjoint in (True, False):
        z = nystrom.march(h.float(), nystrom.RKN8, kick=kick.float(), adjoint=adjoint)
        assert z.dtype == torch.float32
        assert torch.autograd.grad(z.sum(), h)[0].dtype == F64  # the gradient follows its input


def test_empty_inputs():
    assert nystrom.march(torch.zeros(0, 3, dtype=F64), nystrom.RKN8).shape == (0, 3, 4)
    assert nystrom.march(torch.zeros(2, 0, dtype=F64), nystrom.RKN8).shape == (2, 0, 4)


# ---------------------------------------------------------------------------------------------- step counts
def test_rate_bound_behind_the_step_counts_holds(rod):
    # |U(s)| <= min(sum_i |f_i| (s_i - s)^+ / EI, sqrt(2 M)) and |m(s)| <= M = sum_{s_i > s} |f_i| / EI.
    g = torch.Generator().manual_seed(5)
    B, h = 64, 3
    s = 0.02 + 0.27 * torch.rand(B, h, generator=g, dtype=F64)
    f = 2.0 * (2 * torch.rand(B, h, 2, generator=g, dtype=F64) - 1)
    sim = tr.simulate(rod, tr.PointForces(s, f), samples=300)
    ei = rod.bending_stiffness
    lever = (s.unsqueeze(1) - sim.s.view(1, -1, 1)).clamp(min=0)  # (B, S, h)
    fmag = f.norm(dim=-1).unsqueeze(1) / ei
    bound_m = (fmag * (lever > 0)).sum(-1)
    bound_u = torch.minimum((fmag * lever).sum(-1), (2 * bound_m).sqrt())
    u = sim.curvature.norm(dim=-1)
    m = sim.internal_force.norm(dim=-1) / ei
    assert (u <= bound_u * (1 + 1e-9) + 1e-12).all()
    assert (m <= bound_m * (1 + 1e-9) + 1e-12).all()
    assert (u / bound_u.clamp(min=1e-9)).max() > 0.5  # the energy bound is not loose at large deflection


def test_every_sample_keeps_its_own_schedule(rod):
    # One hard sample (2 N near the tip) and easy ones: the easy samples' results do not change when batched
    # (their steps are their own, the batch pads them with zero-length steps).
    cases = [[(0.28, 1.4, -1.4)], [(0.1, 1e-3, 0.0)], [(0.15, 0.0, 0.05), (0.05, 0.02, 0.0)]]
    loads = tr.PointForces.from_lists(cases)
    counts = step_counts(rod, loads, max_step_angle=0.1)
    assert counts.sum(1)[0] > counts.sum(1)[1:].max()  # the hard one needs more steps
    batched = tr.simulate(rod, loads, max_step_angle=0.1).grating_curvature
    for b, case in enumerate(cases):
        alone = tr.simulate(rod, tr.PointForces.from_lists([case]), max_step_angle=0.1).grating_curvature[0]
        torch.testing.assert_close(batched[b], alone, rtol=1e-13, atol=1e-13)
