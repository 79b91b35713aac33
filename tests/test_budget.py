"""The per-reading time budget: a cut search says ``timeout``, and a reading it did not cut keeps its answer."""

from __future__ import annotations

import json
import types

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.estimate import estimator as estimator_module
from torchrod.estimate import lm, search
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.learn.synthetic import LoadSampler, SensorModel, generate


class _Clock:
    """A stand-in for the ``time`` module whose ``perf_counter`` advances ``tick`` seconds per call: the budget's
    checks then cut the search at the same place on every machine."""

    def __init__(self, tick: float) -> None:
        self.now, self.tick = 0.0, tick

    def perf_counter(self) -> float:
        self.now += self.tick
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = _Clock(1e-3)
    module = types.SimpleNamespace(perf_counter=fake.perf_counter)
    for mod in (estimator_module, search, lm):
        monkeypatch.setattr(mod, "time", module)
    return fake


@pytest.fixture(scope="module")
def cases():
    rod = tr.presets.nitinol290()
    data = [
        generate(rod, 6, sampler=LoadSampler(min_forces=k, max_forces=k), sensor=SensorModel(noise=0.1), seed=40 + k)
        for k in (1, 2, 3)
    ]
    return rod, torch.cat([d.curvature for d in data])


def _same(a, b) -> bool:
    """The same answer (to the 1e-9 that batching the rows differently leaves, tests/test_estimator.py) from the
    same work."""
    return (
        torch.equal(a.evaluations, b.evaluations)
        and torch.equal(a.num_forces, b.num_forces)
        and torch.equal(a.status, b.status)
        and torch.allclose(a.forces.s, b.forces.s, rtol=0, atol=1e-9)
        and torch.allclose(a.forces.f, b.forces.f, rtol=0, atol=1e-9)
    )


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_a_budget_of_nothing_times_every_reading_out(cases, backend):
    rod, u = cases
    result = Estimator(rod, EstimatorOptions(noise=0.1, time_budget=0.0, backend=backend)).estimate(u)
    assert result.statuses == ["timeout"] * u.shape[0]
    # the best answer so far: no force fitted yet, reported as such, with finite numbers
    assert result.num_forces.eq(0).all() and torch.isfinite(result.loss).all()
    assert [r["status"] for r in result.to_records()] == ["timeout"] * u.shape[0]
    # a fixed count the budget left unfitted is not reported as a fit: the answer is the largest count fitted
    fixed = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=2, backend=backend))
    cut = fixed.estimate(u, time_budget=0.0)
    assert cut.statuses == ["timeout"] * u.shape[0] and cut.num_forces.eq(0).all()
    assert all(r["forces"] == [] for r in cut.to_records())


def test_an_ample_budget_changes_nothing(cases):
    rod, u = cases
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    assert _same(est.estimate(u), est.estimate(u, time_budget=60.0))


@pytest.mark.parametrize(
    ("batch", "backend", "fixed"), [(1, "numpy", None), (18, "numpy", None), (18, "torch", None), (18, "numpy", 3)]
)
def test_only_the_readings_the_budget_cut_change(cases, clock, batch, backend, fixed):
    """With a clock that ticks per check, budgets from tight to ample cut some readings and not others; every
    reading not called ``timeout`` has exactly its unbounded answer, and every ``timeout`` is a reading whose
    search was really cut (a shorter budget never yields more work)."""
    rod, u = cases
    est = Estimator(rod, EstimatorOptions(noise=0.1, backend=backend, num_forces=fixed))
    free = [est.estimate(u[i : i + batch]) for i in range(0, u.shape[0], batch)]
    seen = set()
    for budget in (0.002, 0.01, 0.03, 0.1):
        for i in range(0, u.shape[0], batch):
            got = est.estimate(u[i : i + batch], time_budget=budget)
            ref = free[i // batch]
            for k in range(got.batch_size):
                out = got.statuses[k] == "timeout"
                seen.add(out)
                if not out:
                    assert _same(got[k], ref[k]), (budget, i + k)
                else:
                    assert int(got.evaluations[k]) <= int(ref.evaluations[k]), (budget, i + k)
                    assert int(got.num_forces[k]) <= int(ref.num_forces[k]) or fixed is None
    assert seen == {True, False}, "the budgets should cut some readings and not others"


def test_the_budget_is_checked(cases):
    rod, _ = cases
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="time_budget"):
            EstimatorOptions(time_budget=bad)


def _lines(rod, tmp_path):
    cases = [[(0.2, 0.3, 0.0)], [(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)]]
    u = tr.simulate(rod, tr.PointForces.from_lists(cases, max_forces=2)).grating_curvature.tolist()
    path = tmp_path / "readings.jsonl"
    path.write_text("".join(json.dumps({"id": f"r{b}", "curvature": u[b]}) + "\n" for b in range(2)))
    return path


@pytest.mark.parametrize("command", ["estimate", "stream"])
def test_the_commands_take_a_budget(command, tmp_path, capsys):
    rod = tr.presets.nitinol290()
    path = _lines(rod, tmp_path)
    where = [str(path)] if command == "estimate" else ["--input", str(path), "--checkpoint", "none"]
    base = [command, "--rod", "nitinol290", "--noise", "0.01", *where]
    assert main([*base, "--time-budget-ms", "0"]) == 0
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [(o["id"], o["status"], o["num_forces"]) for o in out] == [("r0", "timeout", 0), ("r1", "timeout", 0)]
    assert main([*base, "--time-budget-ms", "60000"]) == 0
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [(o["status"], o["num_forces"]) for o in out] == [("ok", 1), ("ok", 2)]
    assert main([*base, "--time-budget-ms", "-1"]) == 2
    assert "--time-budget-ms must be >= 0, got -1" in capsys.readouterr().err
