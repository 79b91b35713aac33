"""An estimate differentiated through its optimum (torchrod.estimate.implicit).

The references are independent of the backward pass: central differences of re-estimation by the compiled search
(converged tightly, so that each re-estimate is the minimiser to rounding), torch's gradcheck of the same, an
estimator built for another rod (the stiffness), and the rod equations' scaling law.
"""

from __future__ import annotations

import pytest
import torch

import torchrod as tr
from torchrod.errors import OptionsError
from torchrod.estimate.options import LMPolicy

F64 = torch.float64
TIGHT = LMPolicy(tolerance=1e-14, iterations=200, exact_steps=20, exact_tolerance=1e-14)
"""Fits converged to rounding: a re-estimate is then the minimiser, which finite differences can be taken of."""


@pytest.fixture(scope="module")
def rod():
    return tr.presets.nitinol290()


@pytest.fixture(scope="module")
def estimator(rod):
    return tr.Estimator(rod, tr.EstimatorOptions(noise=0.05, lm=TIGHT))


def _readings(rod, cases, noise, seed):
    """(B, G, 2) readings of 1-force or 2-force cases [(s list [m], f list [N])], with Gaussian noise [1/m]."""
    width = max(len(s) for s, _ in cases)
    s = torch.zeros(len(cases), width, dtype=F64)
    f = torch.zeros(len(cases), width, 2, dtype=F64)
    mask = torch.zeros(len(cases), width, dtype=torch.bool)
    for b, (sb, fb) in enumerate(cases):
        s[b, : len(sb)] = torch.tensor(sb, dtype=F64)
        f[b, : len(sb)] = torch.tensor(fb, dtype=F64)
        mask[b, : len(sb)] = True
    u = tr.grating_curvature(rod, tr.PointForces(s, f, mask))
    generator = torch.Generator().manual_seed(seed)
    return u + noise * torch.randn(u.shape, dtype=F64, generator=generator)


# Stratified where failures hide: a tip load (on the last bound), next to a grating, mid-rod, two forces, near the
# base with two gratings proximal to it.
CASES = [
    ([0.29], [[0.3, 0.2]]),
    ([0.1101], [[0.4, 0.1]]),
    ([0.2], [[-0.5, 0.35]]),
    ([0.1, 0.22], [[0.5, 0.0], [-0.2, 0.6]]),
    ([0.06], [[1.2, -0.8]]),
]


def _objective(result, weights):
    """A scalar that every force, location and the loss enter, with fixed random weights."""
    ws, wf, wl = weights
    return (result.forces.s * ws).sum() + (result.forces.f * wf).sum() + (result.loss * wl).sum()


@pytest.mark.parametrize("case", range(len(CASES)))
def test_the_gradient_in_the_readings_is_the_derivative_of_re_estimation(rod, estimator, case):
    """Central differences of the compiled search's re-estimates, along a random direction, agree with the backward
    pass's gradient (readings answered ``ok``; noise 0.05 1/m, so the residuals are not zero)."""
    u = _readings(rod, [CASES[case]], noise=0.05, seed=case)
    x = u.clone().requires_grad_(True)
    result = estimator.estimate(x)
    assert result.statuses == ["ok"] and int(result.num_forces) == len(CASES[case][0])
    g = torch.Generator().manual_seed(100 + case)
    weights = (
        torch.randn(result.forces.s.shape, dtype=F64, generator=g),
        torch.randn(result.forces.f.shape, dtype=F64, generator=g),
        torch.randn(result.loss.shape, dtype=F64, generator=g),
    )
    (grad,) = torch.autograd.grad(_objective(result, weights), x)
    direction = torch.randn(u.shape, dtype=F64, generator=g)
    eps = 1e-5
    plus = _objective(estimator.estimate(u + eps * direction), weights)
    minus = _objective(estimator.estimate(u - eps * direction), weights)
    numeric = float(plus - minus) / (2 * eps)
    analytic = float((grad * direction).sum())
    assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-6)


def test_gradcheck_through_the_search(rod, estimator):
    """torch's gradcheck: the Jacobian of the forces and locations of two readings (one and two forces, answered
    ``ok``) in every reading component, against its numerical Jacobian of re-estimates."""
    u = _readings(rod, [CASES[2], CASES[3]], noise=0.02, seed=7)
    before = estimator.estimate(u)
    assert before.statuses == ["ok", "ok"]
    active = before.forces.active

    def forces(x):
        r = estimator.estimate(x)
        assert torch.equal(r.forces.active, active)  # the count holds under the perturbations
        return r.forces.s[active], r.forces.f[active]

    assert torch.autograd.gradcheck(forces, (u.clone().requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_the_stiffness_obeys_the_scaling_law(rod, estimator):
    """On any reading, f is proportional to EI and s does not depend on it: d f / d EI = f / EI, d s / d EI = 0;
    and the answer at a given EI is the one of an estimator built for a rod of that stiffness."""
    u = _readings(rod, [CASES[1], CASES[3]], noise=0.05, seed=3)
    ei = torch.tensor(rod.bending_stiffness * 1.3, dtype=F64, requires_grad=True)
    result = estimator.estimate(u, bending_stiffness=ei)
    active = result.forces.active
    (df,) = torch.autograd.grad(result.forces.f[active].sum(), ei)
    assert float(df) == pytest.approx(float(result.forces.f[active].sum().detach() / ei.detach()), rel=1e-12)
    assert not result.forces.s.requires_grad  # d s / d EI = 0: the locations do not depend on EI at all
    stiffer = tr.Estimator(rod.with_(bending_stiffness=float(ei.detach())), estimator.options)
    other = stiffer.estimate(u)
    assert torch.equal(other.num_forces, result.num_forces) and other.statuses == result.statuses
    assert torch.allclose(other.forces.f[active], result.forces.f[active].detach(), rtol=1e-6, atol=1e-9)
    assert torch.allclose(other.forces.s[active], result.forces.s[active].detach(), rtol=0, atol=1e-8)
    assert torch.allclose(other.std[active], result.std[active], rtol=1e-4, atol=1e-12)


def test_the_location_bias_moves_the_locations_alone(rod, estimator):
    u = _readings(rod, [CASES[2]], noise=0.05, seed=4)
    bias = torch.tensor([-0.003], dtype=F64, requires_grad=True)
    result = estimator.estimate(u, location_bias=bias)
    plain = estimator.estimate(u)
    active = result.forces.active
    assert torch.allclose(result.forces.s[active], plain.forces.s[active] - 0.003, rtol=0, atol=1e-15)
    (ds,) = torch.autograd.grad(result.forces.s[active].sum(), bias, retain_graph=True)
    assert float(ds) == int(active.sum())
    assert not result.forces.f.requires_grad  # the forces do not depend on the bias at all


def test_missing_gratings_padding_and_counts_carry_no_gradient(rod, estimator):
    """A missing grating's value gets no gradient (it is not read), nor does anything through the padding; the
    count and status are integers, with no gradient."""
    u = _readings(rod, [CASES[1]], noise=0.05, seed=5)
    u[0, 3] = float("nan")  # a missing grating
    x = u.clone().requires_grad_(True)
    result = estimator.estimate(x)
    assert result.statuses == ["ok"]
    assert not result.num_forces.is_floating_point() and not result.status.is_floating_point()
    (grad,) = torch.autograd.grad(result.forces.f.sum() + result.forces.s.sum(), x, retain_graph=True)
    assert torch.equal(grad[0, 3], torch.zeros(2, dtype=F64))
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0.0
    padding = ~result.forces.active
    (pad,) = torch.autograd.grad(result.forces.f[padding].sum(), x, allow_unused=True, materialize_grads=True)
    assert float(pad.abs().sum()) == 0.0


def test_an_estimate_without_gradients_is_the_plain_one(rod, estimator):
    """Asking for gradients changes no value: the forces, locations, loss and std are those of a plain estimate,
    in the readings' dtype (float32 here), and the float32 gradient comes back in float32."""
    u = _readings(rod, [CASES[0], CASES[3]], noise=0.05, seed=6).to(torch.float32)
    plain = estimator.estimate(u)
    x = u.clone().requires_grad_(True)
    tracked = estimator.estimate(x)
    for name in ("num_forces", "status", "loss", "std", "p_value"):
        torch.testing.assert_close(
            getattr(tracked, name).detach(), getattr(plain, name), rtol=0, atol=0, equal_nan=True
        )
    assert torch.equal(tracked.forces.s.detach(), plain.forces.s)
    assert torch.equal(tracked.forces.f.detach(), plain.forces.f)
    assert tracked.forces.f.dtype == torch.float32 and tracked.forces.f.grad_fn is not None
    (grad,) = torch.autograd.grad(tracked.forces.f.sum(), x)
    assert grad.dtype == torch.float32
    with torch.no_grad():
        assert estimator.estimate(x).forces.f.grad_fn is None


@pytest.mark.parametrize(
    ("value", "match"),
    [(-1.0, "positive"), (float("nan"), "finite"), (torch.ones(3), r"shape \(B,\)"), ("7e-3", "a number")],
)
def test_a_bad_stiffness_is_refused(rod, estimator, value, match):
    u = _readings(rod, [CASES[0]], noise=0.0, seed=0)
    with pytest.raises(OptionsError, match=match):
        estimator.estimate(u, bending_stiffness=value)


def test_the_guides_example_runs():
    """docs/guides/differentiate.md's first code block runs as written and gives forces with a gradient."""
    import re
    from pathlib import Path

    guide = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "differentiate.md").read_text(encoding="utf-8")
    code = re.findall(r"```python\n(.*?)```", guide, re.S)[0]
    scope: dict = {}
    exec(compile(code, "differentiate.md", "exec"), scope)
    assert scope["result"].forces.f.grad_fn is not None and scope["result"].forces.s.grad_fn is not None
    assert scope["dF_du"].shape == scope["u"].shape and bool(scope["dF_du"].abs().sum() > 0)
