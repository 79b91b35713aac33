"""The estimator with the shipped warm-start network: used when the layout matches, a fallback when not."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.learn.warm_start import WarmStart

CHECKPOINT = Path(__file__).resolve().parents[1] / "checkpoints" / "nitinol290.pt"


def _readings(rod, cases):
    loads = tr.PointForces.from_lists(cases)
    return tr.grating_curvature(rod, loads), loads


def test_from_checkpoint_uses_the_network_when_the_layout_matches():
    rod = tr.presets.nitinol290()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback notice
        est = Estimator.from_checkpoint(CHECKPOINT, rod)
    assert isinstance(est.warm_start, WarmStart)
    assert est.options.starts == 0  # the network replaces the grid scan
    kappa, loads = _readings(rod, [[(0.2, 0.3, -0.2)], [(0.1, -0.5, 0.4), (0.22, 0.2, 0.3)]])
    r = est.estimate(kappa, noise=0.0)
    assert r.num_forces.tolist() == [1, 2]
    true = loads.sorted()
    for b, h in enumerate([1, 2]):
        assert torch.allclose(r.forces.s[b, :h], true.s[b, :h], atol=1e-4)
        assert torch.allclose(r.forces.f[b, :h], true.f[b, :h], rtol=1e-3, atol=1e-3)


def test_a_longer_rod_with_the_same_relative_layout_uses_the_network_too():
    base = tr.presets.nitinol290()
    scale = 1.5
    rod = base.with_(length=base.length * scale, gratings=[g * scale for g in base.gratings], bending_stiffness=0.02)
    est = Estimator.from_checkpoint(CHECKPOINT, rod)
    assert est.warm_start is not None
    kappa, _ = _readings(rod, [[(0.3, 0.4, 0.1)]])
    r = est.estimate(kappa, noise=0.0)
    assert int(r.num_forces[0]) == 1
    assert abs(float(r.forces.s[0, 0]) - 0.3) < 1e-4


def test_falls_back_to_the_grid_scan_when_the_layout_differs_and_says_so_once():
    rod = tr.presets.nitinol290().with_(gratings=[0.02 + 0.025 * k for k in range(11)])
    messages = []
    est = Estimator.from_checkpoint(CHECKPOINT, rod, warn=messages.append)
    assert est.warm_start is None and est.options.starts > 0
    assert len(messages) == 1 and "grid scan" in messages[0]
    kappa, _ = _readings(rod, [[(0.2, 0.3, 0.0)]])
    r = est.estimate(kappa, noise=0.0)
    assert int(r.num_forces[0]) == 1 and abs(float(r.forces.s[0, 0]) - 0.2) < 1e-4
    with pytest.warns(UserWarning, match="grid scan"):
        Estimator.from_checkpoint(CHECKPOINT, rod)


def test_starts_zero_needs_another_start():
    rod = tr.presets.nitinol290()
    kappa, _ = _readings(rod, [[(0.2, 0.3, 0.0)]])
    with pytest.raises(ValueError, match="starts=0"):
        Estimator(rod, EstimatorOptions(starts=0)).estimate(kappa)
    # With an extra start for every count it runs without the scan.
    extra = {h: tr.PointForces.from_lists([[(0.05 + 0.08 * i, 0.1, 0.0) for i in range(h)]]) for h in (1, 2, 3)}
    r = Estimator(rod, EstimatorOptions(starts=0)).estimate(kappa, extra_starts=extra, noise=0.0)
    assert int(r.num_forces[0]) == 1 and abs(float(r.forces.s[0, 0]) - 0.2) < 1e-4


def test_bench_network_runs_and_prints_its_table(capsys):
    from torchrod.cli import main

    assert main(["bench", "network", "--quick", "--count", "6"]) == 0
    out = capsys.readouterr().out
    for k in (1, 2, 3):
        for name in ("network", "estimator", "estimator+network"):
            assert any(line.split()[:2] == [str(k), name] for line in out.splitlines()), (k, name)
