"""Rods with few gratings and imperfect calibrations: a count the reading cannot test is never chosen, a rod's
calibration error weighs the fit, its rod-file form, its refusals, and the noise learned with it."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from torchrod.errors import RodError
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.estimate.noise import RunningNoise, calibration_terms
from torchrod.estimate.options import default_max_forces
from torchrod.eval.few_gratings import needle, needle_readings
from torchrod.loads import PointForces
from torchrod.model.body_frame import simulate
from torchrod.rod import Rod

F64 = torch.float64
SIGMA = 0.05
FIVE = (0.030, 0.060, 0.090, 0.104, 0.119)
"""[m] A needle's gratings where two forces leave 10 - 6 = 4 degrees of freedom: they can be chosen."""


def test_two_forces_are_never_chosen_on_three_gratings():
    """6 values: one force leaves 3 degrees of freedom, two leave none. Asked for up to 3, two true forces, a badly
    calibrated grating, the noise known or not: never more than one force, and the counts above one not fitted."""
    rod = needle()
    u1, _ = needle_readings(rod, 24, 0.5, SIGMA, seed=4)
    loads = PointForces(
        torch.tensor([[0.08, 0.126]], dtype=F64).expand(8, -1),
        torch.tensor([[[0.3, -0.1], [-0.2, 0.25]]], dtype=F64).expand(8, -1, -1),
    )
    u2 = simulate(rod, loads).grating_curvature + SIGMA * torch.randn(
        8, 3, 2, generator=torch.Generator().manual_seed(1), dtype=F64
    )
    for noise in (SIGMA, None):
        for u in (u1, u2):
            result = Estimator(rod, EstimatorOptions(max_forces=3, noise=noise)).estimate(u)
            assert int(result.num_forces.max()) <= 1
            assert bool(result.losses_by_count[:, 2:].isnan().all())
    # the two forces' readings are explained by no single force: with the noise known the status says so (of the
    # misfit test's power at 3 degrees of freedom: 7 of these 8)
    result = Estimator(rod, EstimatorOptions(max_forces=3, noise=SIGMA)).estimate(u2)
    assert result.statuses.count("misfit") >= 6


def test_the_present_gratings_count():
    """Five gratings test two forces; with two of them missing a reading holds 6 values, and tests one."""
    rod = needle().with_(gratings=FIVE)
    loads = PointForces(torch.tensor([[0.07, 0.125]], dtype=F64), torch.tensor([[[0.4, 0.0], [0.0, -0.3]]], dtype=F64))
    u = simulate(rod, loads).grating_curvature
    estimator = Estimator(rod, EstimatorOptions(max_forces=3, noise=0.01))
    assert estimator.estimate(u).num_forces.tolist() == [2]
    mask = torch.tensor([[True, False, True, False, True]])
    assert estimator.estimate(u, mask).num_forces.tolist() == [1]


def test_the_default_count_follows_the_gratings():
    assert default_max_forces(3) == 1 and default_max_forces(5) == 2 and default_max_forces(14) == 3
    assert default_max_forces(1) == 0
    assert Estimator(needle()).options.max_forces == 1
    assert Estimator(needle().with_(gratings=FIVE)).options.max_forces == 2
    import torchrod as tr

    assert Estimator(tr.presets.nitinol290()).options == EstimatorOptions()


def test_the_weights_of_a_calibration_error():
    """sigma_k^2 = sigma^2 + (rel_k |u_k|)^2 with the measured u_k; the weight sigma / sigma_k; none with the noise
    unknown, and none at a missing grating."""
    rod = needle([0.1, 0.0, 0.5])
    u = torch.tensor([[[1.0, -2.0], [0.5, 0.5], [0.2, float("nan")]]], dtype=F64)
    mask = torch.tensor([[True, True, False]])
    opts = EstimatorOptions(noise=SIGMA)
    _, w, noise2 = Estimator(rod, opts)._kernel_readings(u, mask, opts)
    s2 = SIGMA**2 + opts.noise_floor**2
    assert float(noise2[0]) == pytest.approx(s2)
    expect = [math.sqrt(s2 / (s2 + (0.1 * x) ** 2)) for x in (1.0, -2.0)] + [1.0, 1.0, 0.0, 0.0]
    assert w[0].tolist() == pytest.approx(expect)
    unknown = EstimatorOptions()
    _, w, _ = Estimator(rod, unknown)._kernel_readings(u, mask, unknown)
    assert w[0].tolist() == [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]


def test_a_calibration_error_keeps_a_gain_error_from_making_a_phantom_force():
    """Five gratings, one force near the tip, one grating's gain off by 50 %: without a calibration error most
    readings are answered with a phantom second force (the misfit the gain makes looks like one); with the error
    the calibration reports (0.5), one force each."""
    plain = needle().with_(gratings=FIVE)
    u, _ = needle_readings(plain, 40, 0.5, SIGMA, seed=1)
    options = EstimatorOptions(max_forces=3, noise=SIGMA)
    without = Estimator(plain, options).estimate(u)
    assert float((without.num_forces >= 2).double().mean()) > 0.5
    within = Estimator(plain.with_(calibration_error=0.5), options).estimate(u)
    assert within.num_forces.tolist() == [1] * 40
    assert float(within.ok.double().mean()) > 0.9


def test_the_rod_file_keeps_the_calibration_error(tmp_path):
    rod = needle([0.1, 0.02, 0.3])
    path = tmp_path / "rod.json"
    rod.to_json(path)
    assert json.loads(path.read_text())["calibration_error"] == [0.1, 0.02, 0.3]
    assert Rod.from_json(path) == rod
    assert needle(0.1).calibration_error == (0.1, 0.1, 0.1)
    assert needle(0.0).calibration_error == () and "calibration_error" not in needle().to_dict()
    assert needle([0, 0, 0]) == needle()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-0.1, "calibration_error[0] must lie in [0, 10] (a fraction of the signal: 0.1 for 10 %), got -0.1"),
        ([0.1, float("nan"), 0.1], "calibration_error[1] must be finite (a fraction of the signal), got nan"),
        ([0.1, 0.1, 11.0], "calibration_error[2] must lie in [0, 10] (a fraction of the signal: 0.1 for 10 %), got 11"),
        ([0.1, 0.2], "calibration_error must hold one fraction per grating (3), got 2"),
        ("0.1", 'calibration_error must be a fraction, or a list of one per grating, got "0.1"'),
        ([0.1, True, 0.1], "calibration_error[1] must be a number (a fraction of the signal), got true"),
    ],
)
def test_nonsense_calibration_errors_are_refused(value, message):
    with pytest.raises(RodError) as err:
        needle(value)
    assert str(err.value) == message
    with pytest.raises(RodError, match=r"calibration_error"):
        Rod.from_dict({**needle().to_dict(), "calibration_error": value})


def test_the_learned_noise_takes_the_calibrations_share_off():
    """Losses of fits that hold the calibration's variance besides the noise (equal weights, or weights made at a
    sigma far too small): with the calibration's terms taken off, the median of the fits' estimates is the sensor's
    sigma^2 again."""
    n, d, sigma = 6, 3, 0.05
    variance = torch.tensor([0.001, 0.004, 0.0001, 0.002, 0.0, 0.003], dtype=F64).view(1, 3, 2)  # m_k^2 [1/m^2]
    present = torch.ones(1, 3, dtype=torch.bool)
    torch.manual_seed(0)
    chi = torch.distributions.Chi2(d).sample((4000,)).double() / d  # the loss's spread about its mean
    for noise2 in (None, 1e-6):
        w2 = torch.ones(6, dtype=F64) if noise2 is None else noise2 / (noise2 + variance.flatten())
        mean = d / n * float((w2 * (sigma**2 + variance.flatten())).sum())
        losses = (mean * chi).tolist()
        terms = calibration_terms(variance.expand(len(losses), -1, -1), present.expand(len(losses), -1), noise2)
        plain, corrected = RunningNoise(), RunningNoise()
        plain.add(losses, [d] * len(losses))
        corrected.add(losses, [d] * len(losses), terms)
        assert corrected.sigma == pytest.approx(sigma, rel=0.1)
        assert abs(plain.sigma / sigma - 1.0) > 0.2


def test_a_calibration_error_survives_dataclass_copies():
    rod = needle(0.2)
    assert dataclasses.replace(rod, location_bias=0.001).calibration_error == (0.2, 0.2, 0.2)
    assert rod.with_(bending_stiffness=0.01).calibration_error == (0.2, 0.2, 0.2)


def test_bench_gratings_quick_prints_the_table(capsys):
    from torchrod.cli import main

    assert main(["bench", "gratings", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "| gain error | calibration error | 0 forces | 1 force | 2+ forces |" in out
    assert "| 50 % | 0.5 |" in out and "| 0 % | none |" in out


def test_the_gratings_table_leaves_the_spreads_empty_where_no_reading_has_one_force():
    from torchrod.eval.few_gratings import StudyRow, table

    values = {f.name: 0.5 for f in dataclasses.fields(StudyRow)}
    unmeasured = dict.fromkeys(("direction_spread", "magnitude_error", "location_error"), math.nan)
    lines = table([StudyRow(**values), StudyRow(**{**values, **unmeasured})])
    assert lines[-2] == "| 50 % | 0.5 | 0.50 | 0.50 | 0.50 | 0.5 | 0.5 | 0.5 | 0.50 | 0.50 |"
    assert lines[-1] == "| 50 % | 0.5 | 0.50 | 0.50 | 0.50 |  |  |  | 0.50 | 0.50 |"


def test_the_gradients_hold_the_calibration_weights():
    """The differentiable path fits what the kernels fit: the loss's gradient in the readings is that of the
    weighed loss at the optimum, -2 w^2 (c(theta*) - u), with the weights held fixed."""
    rod = needle(0.2)
    u, _ = needle_readings(rod, 2, 0.0, SIGMA, seed=3)
    options = EstimatorOptions(noise=SIGMA)
    estimator = Estimator(rod, options)
    x = u.clone().requires_grad_(True)
    result = estimator.estimate(x)
    assert result.num_forces.tolist() == [1, 1]
    (grad,) = torch.autograd.grad(result.loss.sum(), x)
    _, w, _ = estimator._kernel_readings(u, torch.ones(2, 3, dtype=torch.bool), options)
    w = torch.as_tensor(w).view(2, 3, 2)
    assert bool((w < 0.99).any())
    loads = PointForces(result.forces.s.detach() - rod.location_bias, result.forces.f.detach(), result.forces.active)
    c = simulate(rod, loads).grating_curvature
    assert torch.allclose(grad, -2 * w.square() * (c - u), rtol=1e-6, atol=1e-9)


def test_a_stream_learns_the_sensors_own_noise_beside_a_calibration_error():
    """Readings whose every value carries a gain error of 10 % (drawn per reading) besides the sensor's noise: a
    stream on the rod that says so comes down to the sensor's sigma (from above: 0.125 from its first fits, 0.059
    after 300 readings); on a rod that does not, it learns a sigma that takes in the calibration's share too."""
    import torchrod as tr
    from torchrod.estimate.noise import NoiseLearning

    rod = needle().with_(gratings=FIVE)
    clean, _ = needle_readings(rod, 300, 0.0, 0.0, seed=5)
    gen = torch.Generator().manual_seed(6)
    u = clean * (1.0 + 0.1 * torch.randn(clean.shape, generator=gen, dtype=F64))
    u = u + SIGMA * torch.randn(clean.shape, generator=gen, dtype=F64)
    readings = [{"id": k, "curvature": u[k]} for k in range(len(u))]
    options = tr.StreamOptions(learn_noise=NoiseLearning(after=32), workers=1)
    learned = {}
    for rel in (0.0, 0.1):
        est = Estimator(rod.with_(calibration_error=rel), EstimatorOptions(max_forces=2))
        out = [r.record for r in tr.stream(est, readings, options)]
        learned[rel] = out[-1]["noise"]
    assert learned[0.1] == pytest.approx(SIGMA, rel=0.25)
    assert learned[0.0] > 1.5 * SIGMA
