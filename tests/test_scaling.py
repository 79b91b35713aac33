"""The estimator scales with the rod: a 1.0 m rod with 40 gratings (``data/tube1000.json``) estimates 1 to 3
forces in bounded memory, with work per grating comparable to the 290 mm rod's.

Work is counted, not timed (the machine is shared): forward-model evaluations per reading, each a march whose cost
grows linearly with the gratings. Wall times per grating are in docs/results.md (``torchrod bench estimate``).
"""

from __future__ import annotations

import math
import tracemalloc
from pathlib import Path

import torch

import torchrod as tr
from torchrod.data import path as shipped_file
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.eval import recovery as R

ROOT = Path(__file__).resolve().parents[1]


def _noisy(rod, count, seed, noise=0.1):
    """1 to 3 forces over [second grating, L], magnitudes scaled with 1 / L^2 from the 290 mm envelope (0.05-2 N)
    so that the rods bend alike (at most 90 degrees)."""
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    k = (0.29 / rod.length) ** 2
    sampler = LoadSampler(
        min_forces=1,
        max_forces=3,
        force_range=(0.05 * k, 2.0 * k),
        min_separation=0.025 * rod.length / 0.29,
        s_range=(rod.gratings[1], rod.length),
        max_bending=math.pi / 2,
    )
    return generate(rod, count, sampler=sampler, sensor=SensorModel(noise=noise), seed=seed)


def test_long_rod_bounded_memory_and_work():
    short = tr.presets.nitinol290()
    long = tr.Rod.from_json(shipped_file("tube1000.json"))
    assert long.length == 1.0 and long.num_gratings == 40
    work, accuracy = {}, {}
    for name, rod in (("short", short), ("long", long)):
        data = _noisy(rod, 48, seed=3)
        est = Estimator(rod, EstimatorOptions(noise=0.1))
        est.estimate(data.curvature[:1], data.mask[:1])  # any one-time set-up outside the measurement
        tracemalloc.start()
        try:
            res = est.estimate(data.curvature, data.mask)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        print(f"{name}: peak {peak / 2**20:.1f} MiB")
        assert peak < 2**30, f"{name}: peak {peak / 2**20:.0f} MiB"
        if name == "long":
            assert peak < 256 * 2**20, f"long rod, 48 readings: peak {peak / 2**20:.0f} MiB"
        assert all(s in ("ok", "poorly_determined") for s in res.statuses), res.statuses
        work[name] = res.evaluations.double().mean().item()
        accuracy[name] = (res.num_forces == data.loads.count).double().mean().item()
    print("evaluations per reading", work, "count accuracy", accuracy)
    # Evaluations per reading do not grow with the rod (each costs O(G)): time per grating stays comparable.
    assert work["long"] <= 1.5 * work["short"], work
    assert accuracy["long"] >= 0.6, accuracy


def test_long_rod_clean_recovery():
    """Clean readings on the long rod: the same recovery verdicts as on the short one (no silent local minima)."""
    rod = tr.Rod.from_json(shipped_file("tube1000.json"))
    rows = R.run(rod, 60, seed=5)
    verdicts = [r["verdict"] for r in rows]
    assert "wrong" not in verdicts and "missed" not in verdicts, [
        r for r in rows if r["verdict"] in ("wrong", "missed")
    ]
    assert verdicts.count("exact") >= 0.4 * len(rows)


def test_work_does_not_depend_on_length():
    """The same gratings on a 0.29 m and a 2.9 m rod, forces scaled to the same turning: the same answers, with
    about the same work (the old grid starts grew with the length)."""
    base = tr.presets.nitinol290()
    scaled = base.with_(length=2.9, gratings=tuple(10 * q for q in base.gratings))
    cases = [[(0.15, 0.5, -0.2)], [(0.12, -0.4, 0.3), (0.24, 0.2, 0.1)]]
    evaluations = []
    for rod, k in ((base, 1.0), (scaled, 10.0)):
        loads = tr.PointForces.from_lists(
            [[(k * s, fx / k**2, fy / k**2) for s, fx, fy in c] for c in cases], max_forces=2
        )
        u = tr.simulate(rod, loads).grating_curvature
        res = Estimator(rod, EstimatorOptions(noise=0.0)).estimate(u)
        assert res.num_forces.tolist() == [1, 2]
        assert res.statuses == ["ok", "ok"]
        assert torch.allclose(res.forces.s[1, :2], torch.tensor([0.12 * k, 0.24 * k], dtype=torch.float64), rtol=1e-5)
        evaluations.append(res.evaluations.double())
    assert torch.all(evaluations[1] <= 1.5 * evaluations[0] + 2), evaluations
