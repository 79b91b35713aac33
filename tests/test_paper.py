"""The paper's experiments (torchrod.paper) and ``torchrod bench paper``."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.eval import paper as P
from torchrod.eval.grid_starts import GridStarts


@pytest.fixture
def calibrated() -> tr.Rod:
    """The paper's tube with its calibrated location bias (-3.12 mm)."""
    return tr.presets.nitinol290(calibrated=True)


def _one_reading(rod: tr.Rod, noise: float = 0.1, seed: int = 3) -> P.Readings:
    return P.paper_readings(rod, 1, 1, noise=noise, seed=seed)


def test_baselines_solve_the_same_problem_and_torchrod_agrees(calibrated):
    rd = _one_reading(calibrated)
    u, truth = rd.curvature[0], rd.truth(0)
    grid = GridStarts(calibrated)
    q = 40
    fits = {
        name: P.paper_estimate(P.make_model(name, calibrated, q), u, num_forces=1, grid=grid).fit
        for name in P.BASELINES
    }
    ref = fits["nodes"].forces
    for name in ("bvp_lm", "bvp_dp"):
        # The same node-spread load through a different 4th-order integrator (global frame, base to tip): the same
        # estimate to 2e-4 relative (this force near the base is seen by two gratings only: the worst conditioned;
        # along its flat direction where the fit stops depends on the inner shooting's path, which GJ changes
        # although the solution does not depend on it).
        gap = np.abs(fits[name].forces - ref)
        assert gap[0, 0] < 1e-5 and gap[0, 1:].max() < 2e-4 * np.abs(ref[0, 1:]).max(), (
            name,
            fits[name],
            ref,
        )
        assert fits[name].loss == pytest.approx(fits["nodes"].loss, rel=1e-5)
    # LM and DP differ only in the inner Jacobian: the same shots, the same answer (to the shooting tolerance).
    np.testing.assert_allclose(fits["bvp_lm"].forces, fits["bvp_dp"].forces, atol=1e-5)
    # torchrod's estimator (exact point loads) differs from the node scheme by its discretisation error only, which
    # falls as q grows.
    est = Estimator(calibrated, EstimatorOptions(noise=0.1, num_forces=1))
    result = est.estimate(u[None])
    mine = np.array(result.forces.to_lists()[0])
    fine = P.paper_estimate(P.NodeModel(calibrated, 160), u, num_forces=1, grid=grid).fit.forces
    coarse_gap, fine_gap = np.abs(mine - ref), np.abs(mine - fine)
    assert fine_gap.max() < coarse_gap.max() / 4, (coarse_gap, fine_gap)
    # What is left is far inside the estimate's own uncertainty (its stopping rule is set by the noise).
    std = result.std[0, 0].numpy()
    assert (fine_gap[0] < 0.05 * std).all(), (fine_gap, std)
    # And all of them found the force behind the reading (to the noise: 0.1 1/m).
    assert abs(mine[0, 0] - truth[0, 0]) < 5e-3
    assert math.hypot(*(mine[0, 1:] - truth[0, 1:])) < 0.1


def test_fit_recovers_noise_free_forces_in_reported_coordinates(calibrated):
    # Two forces, curvature from the node model itself: the fit must return them exactly, shifted by the bias.
    model = P.NodeModel(calibrated, 60)
    true_model = np.array([[0.11, 0.4, -0.3], [0.23, -0.2, 0.25]])
    u = model(true_model[None])[0]
    start = P.grid_start(GridStarts(calibrated), u, 2)
    fit = P.fit_forces(model, u, start)
    assert fit.success and fit.loss < 1e-16
    expected = true_model.copy()
    expected[:, 0] += calibrated.location_bias  # reported = model + bias
    np.testing.assert_allclose(fit.forces, expected, atol=1e-7)
    assert fit.evaluations >= fit.nfev  # Jacobian columns counted too


def test_exact_loss_maps_reported_locations_to_the_model(calibrated):
    rd = P.paper_readings(calibrated, 2, 2, noise=0.0, seed=2)
    for i in range(2):
        assert P.exact_loss(calibrated, rd.curvature[i], rd.truth(i)) < 1e-12
        moved = rd.truth(i) + np.array([0.002, 0.0, 0.0])
        assert P.exact_loss(calibrated, rd.curvature[i], moved) > 1e-4
    assert P.exact_loss(calibrated, rd.curvature[0], np.zeros((0, 3))) == pytest.approx(
        float(rd.curvature[0].square().sum())
    )


def test_fit_ignores_missing_gratings(calibrated):
    model = P.NodeModel(calibrated, 60)
    true_model = np.array([[0.2, 0.5, 0.1]])
    u = model(true_model[None])[0]
    mask = np.ones(calibrated.num_gratings, dtype=bool)
    mask[[2, 5]] = False
    u[~mask] = 1e3  # garbage where the gratings are missing
    fit = P.fit_forces(model, u, np.array([[0.15, 0.3, 0.0]]), mask=mask)
    np.testing.assert_allclose(fit.forces[0, 1:], true_model[0, 1:], atol=1e-7)


def test_threshold_rule_raises_the_count_until_the_loss_is_small(calibrated):
    rod = calibrated.with_(location_bias=0.0)
    true = tr.PointForces(
        torch.tensor([[0.09, 0.22]], dtype=torch.float64),
        torch.tensor([[[0.6, 0.0], [0.0, -0.5]]], dtype=torch.float64),
    )
    u = tr.grating_curvature(rod, true)[0]
    est = P.paper_estimate(P.NodeModel(rod, 120), u, max_forces=3)
    assert sorted(est.fits) == [1, 2]  # stopped at two: the first count under the paper's threshold
    assert est.fits[1].loss > P.PAPER_THRESHOLD > est.fits[2].loss
    assert est.num_forces == 2
    np.testing.assert_allclose(est.fit.forces[:, 0], [0.09, 0.22], atol=2e-4)
    given = P.paper_estimate(P.NodeModel(rod, 120), u, num_forces=3)
    assert list(given.fits) == [3] and given.num_forces == 3


def test_paper_readings_spread_range_and_bias(calibrated):
    rd = P.paper_readings(calibrated, 1, 13, noise=0.0, seed=5)
    assert len(rd) == 13 and rd.curvature.shape == (13, calibrated.num_gratings, 2)
    mags = rd.loads.magnitude()[:, 0]
    assert bool(((mags >= P.FORCE_RANGE[0]) & (mags <= P.FORCE_RANGE[1])).all())
    s = rd.loads.s[:, 0]
    # One case per 13th of the location range, in order along the rod.
    assert bool((s[1:] > s[:-1]).all())
    lo, hi = calibrated.gratings[1], calibrated.length - 0.01
    edges = torch.linspace(lo, hi, 14, dtype=torch.float64)
    assert bool(((s >= edges[:-1]) & (s <= edges[1:])).all())
    # Noise-free readings are the forward model with the forces at s - bias (reported = model + bias).
    shifted = tr.PointForces(rd.loads.s - calibrated.location_bias, rd.loads.f, rd.loads.mask)
    expected = tr.grating_curvature(calibrated, shifted)
    torch.testing.assert_close(rd.curvature, expected, atol=1e-6, rtol=1e-6)
    three = P.paper_readings(calibrated, 3, 4, noise=0.15, seed=1)
    assert three.loads.count.tolist() == [3, 3, 3, 3] and three.truth(0).shape == (3, 3)


def test_match_forces_and_accuracy_by_hand():
    truth = [np.array([[0.10, 1.0, 0.0], [0.20, 0.0, 1.0]]), np.array([[0.15, 0.6, 0.8]])]
    est = [np.array([[0.205, 0.0, 1.2], [0.098, 0.9, 0.0]]), np.array([[0.14, 0.0, 1.0], [0.25, 0.1, 0.0]])]
    assert P.match_forces(truth[0], est[0]) == [(0, 1), (1, 0)]  # in order of location
    assert P.match_forces(truth[1], est[1]) == [(0, 0)]  # the nearer of two estimates
    acc = P.accuracy(truth, est)
    assert acc.readings == 2 and acc.count_correct == 1
    df = np.array([-0.1, 0.2, 0.0])  # |f| errors of the three pairs
    ds = np.array([-0.002, 0.005, -0.01])
    assert acc.force_rmse == pytest.approx(math.sqrt(np.mean(df**2)))
    assert acc.location_rmse == pytest.approx(math.sqrt(np.mean(ds**2)))
    with pytest.raises(ValueError, match="truths"):
        P.accuracy(truth, est[:1])


def test_loss_maps_minimum_at_the_truth_and_batched_equals_alone(rod):
    maps = P.loss_maps(rod, s_range=(0.1, 0.29), magnitude_range=(0.0, 0.5), size=(20, 11), samples=30)
    assert maps.curvature_loss.shape == (11, 20) == maps.shape_loss.shape
    for which in ("curvature", "shape"):
        s_min, f_min = maps.minimum(which)
        assert s_min == pytest.approx(0.2) and f_min == pytest.approx(0.3)
    assert maps.curvature_loss.min() < 1e-20 and maps.shape_loss.min() < 1e-20
    # One grid point computed alone gives the batched value.
    j, i = 15, 8  # s = 0.25 m, |f| = 0.4 N along x
    alone = tr.simulate(
        rod,
        tr.PointForces(torch.tensor([[0.25]], dtype=torch.float64), torch.tensor([[[0.4, 0.0]]], dtype=torch.float64)),
    )
    truth = tr.simulate(
        rod,
        tr.PointForces(torch.tensor([[0.2]], dtype=torch.float64), torch.tensor([[[0.3, 0.0]]], dtype=torch.float64)),
    )
    direct = float((alone.grating_curvature - truth.grating_curvature).square().sum())
    assert maps.curvature_loss[i, j] == pytest.approx(direct, rel=1e-8)
    # Both losses vanish at the truth only.
    for grid in (maps.curvature_loss, maps.shape_loss):
        assert (grid > 1e-20).sum() == grid.size - 1


def test_bench_paper_quick_prints_tables_and_writes_figures(tmp_path, capsys):
    threads = torch.get_num_threads()
    out = tmp_path / "figs"
    assert main(["bench", "paper", "--quick", "--no-network", "--quiet", "--out", str(out)]) == 0
    assert torch.get_num_threads() == threads
    text = capsys.readouterr().out
    assert "without a warm-start network" in text
    # Table II rows: q, then BVP+LM, paper, BVP+DP, paper, nodes, paper, torchrod, batched.
    for q in (20, 40):
        row = re.search(rf"^\s+{q} \|(.*)$", text, re.MULTILINE)
        assert row, text
        cells = row.group(1).replace("|", " ").split()
        times = [float(c) for c in cells if c != "-"]
        assert len(times) == 5 and all(t > 0 for t in times), row.group(0)
        assert re.search(rf"q = {q}: bvp_lm [\d.]+x .*bvp_dp [\d.]+x", text)
        agree = re.search(
            rf"q = {q}: bvp_lm vs nodes (\S+) / (\S+) \((\S+)\); bvp_dp vs nodes (\S+) / (\S+) \((\S+)\);.*"
            r"exact loss (\S+)$",
            text,
            re.MULTILINE,
        )
        assert agree, text
        # The baselines agree to far below a micrometre and a millinewton; torchrod's estimate is never worse than
        # the node scheme's under the exact model.
        assert max(float(x) for x in agree.groups()[:6]) < 1e-2, agree.group(0)
        assert float(agree.group(7)) < 1e-4, agree.group(0)
    for label in (
        "torchrod (auto count)",
        "torchrod (count given)",
        "paper q=60 (count given)",
        "paper q=60 (threshold)",
    ):
        for k in (1, 2, 3):
            assert re.search(rf"^{re.escape(label)}\s+{k}\s+\d/2", text, re.MULTILINE), (label, k)
    assert "paper, q=90 (MATLAB)" in text and "0.134" in text
    assert re.search(r"curvature loss: minimum at \S+ mm", text)
    for name in ("paper_table2.png", "paper_vs_q.png", "paper_loss_maps.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_bench_paper_rejects_bad_options(capsys):
    assert main(["bench", "paper", "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err
