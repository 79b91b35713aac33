"""``EstimatorOptions(target="torch")``: the warm start's guesses refined in torch, judged by the kernels.

Held to the default target on held-out noisy readings it never saw (the shipped network's), not to itself.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchrod as tr
from torchrod.errors import OptionsError
from torchrod.estimate import refine
from torchrod.learn.warm_start import SHIPPED_CHECKPOINT
from torchrod.synthetic import SensorModel, generate

F64 = torch.float64


@pytest.fixture(scope="module")
def rod():
    return tr.presets.nitinol290()


@pytest.fixture(scope="module")
def estimator(rod):
    return tr.load_estimator(SHIPPED_CHECKPOINT, rod, tr.EstimatorOptions(noise=0.1), warn=lambda _: None)


@pytest.fixture(scope="module")
def held_out(rod):
    data = generate(rod, 36, sensor=SensorModel(noise=0.1), seed=424242)  # 0-3 forces, gratings missing at times
    return data.curvature, data.mask


def test_the_torch_target_answers_as_the_default_target(estimator, held_out):
    """The same count on at least 97 % of held-out noisy readings, and on those, every force within two of the
    default answer's standard deviations on at least 95 %."""
    u, mask = held_out
    want = estimator.estimate(u, mask)
    got = estimator.estimate(u, mask, options=tr.EstimatorOptions(noise=0.1, target="torch"))
    same = got.num_forces == want.num_forces
    n = u.shape[0]
    assert int(same.sum()) >= math.floor(0.97 * n), (got.num_forces.tolist(), want.num_forces.tolist())
    close = []
    for b in same.nonzero().flatten().tolist():
        active = want.forces.active[b]
        sd = want.std[b][active]
        ds = (got.forces.s[b][active] - want.forces.s[b][active]).abs() <= 2 * sd[:, 0] + 1e-9
        df = ((got.forces.f[b][active] - want.forces.f[b][active]).abs() <= 2 * sd[:, 1:] + 1e-9).all(-1)
        close.append(bool((ds & df).all()))
    assert sum(close) >= math.floor(0.95 * len(close))
    # Its evaluations hold the torch refinement's passes too: more than the kernels' polish alone would need.
    assert bool((got.evaluations > 0).all())


def test_the_refinement_reaches_the_minimum_from_a_nearby_start(rod):
    """One force, a start 5 mm and 30 % off: the torch fit ends where the compiled search's does, its loss no
    higher, and converged."""
    loads = tr.PointForces(torch.tensor([[0.16]], dtype=F64), torch.tensor([[[0.5, -0.4]]], dtype=F64))
    u = tr.grating_curvature(rod, loads) + 0.05 * torch.randn(1, rod.num_gratings, 2, dtype=F64,
                                                               generator=torch.Generator().manual_seed(2))  # fmt: skip
    present = torch.ones(1, rod.num_gratings, dtype=torch.bool)
    fit = refine.refine(
        rod, u, present, torch.tensor([[0.165]], dtype=F64), torch.tensor([[[0.35, -0.28]]], dtype=F64),
        sigma2=0.05**2, lm=tr.LMPolicy(), step_angle=tr.EstimatorOptions().max_step_angle,
    )  # fmt: skip
    want = tr.Estimator(rod, tr.EstimatorOptions(num_forces=1, noise=0.05)).estimate(u)
    assert bool(fit.converged.all())
    assert float(fit.loss) <= float(want.loss) * (1 + 1e-6) + 1e-12
    assert float((fit.s - want.forces.s[:, :1]).abs().max()) < 0.1 * float(want.std[0, 0, 0])
    assert float((fit.f - want.forces.f[:, :1]).abs().max()) < 0.1 * float(want.std[0, 0, 1:].min())


def test_without_starts_the_torch_target_says_what_to_give(rod):
    u = tr.grating_curvature(rod, tr.PointForces(torch.tensor([[0.2]], dtype=F64), torch.ones(1, 1, 2, dtype=F64)))
    plain = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1, target="torch"))
    with pytest.raises(OptionsError, match="warm start"):
        plain.estimate(u)


def test_the_torch_target_keeps_the_readings_dtype(estimator, held_out):
    u, mask = held_out
    got = estimator.estimate(u[:3].float(), mask[:3], options=tr.EstimatorOptions(noise=0.1, target="torch"))
    assert got.forces.f.dtype == torch.float32 and got.forces.f.device == u.device


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_the_gpu_the_default_is_the_torch_target_and_answers_as_the_cpu(estimator, held_out):
    """CUDA readings, default options: refined on the GPU with no CUDA compile, answered on the GPU, the CPU's
    count on at least 97 % of the held-out readings; and the estimate is differentiable there too."""
    u, mask = held_out
    want = estimator.estimate(u, mask)
    x = u.cuda().requires_grad_(True)
    got = estimator.estimate(x, mask.cuda())
    assert got.forces.f.device.type == "cuda"
    same = got.num_forces.cpu() == want.num_forces
    assert int(same.sum()) >= math.floor(0.97 * u.shape[0])
    ok = got.ok
    (grad,) = torch.autograd.grad(got.forces.f[ok][got.forces.active[ok]].sum(), x)
    assert grad.device.type == "cuda" and bool(torch.isfinite(grad).all())
