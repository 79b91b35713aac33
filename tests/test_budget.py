"""The budgets: a cut search says ``timeout``, and a reading it did not cut keeps its answer. The evaluation budget
cuts at the same place on every machine; the wall-clock budget is the caller's deadline."""

from __future__ import annotations

import dataclasses
import json
import time

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.synthetic import LoadSampler, SensorModel, generate


@pytest.fixture(scope="module")
def cases():
    rod = tr.presets.nitinol290()
    data = [
        generate(rod, 6, sampler=LoadSampler(min_forces=k, max_forces=k), sensor=SensorModel(noise=0.1), seed=40 + k)
        for k in (1, 2, 3)
    ]
    return rod, torch.cat([d.curvature for d in data])


def _same(a, b) -> bool:
    """The same answer from the same work."""
    return (
        torch.equal(a.evaluations, b.evaluations)
        and torch.equal(a.num_forces, b.num_forces)
        and torch.equal(a.status, b.status)
        and torch.equal(a.forces.s, b.forces.s)
        and torch.equal(a.forces.f, b.forces.f)
    )


def _with(est, **changes):
    return dataclasses.replace(est.options, **changes)


def test_a_budget_of_nothing_times_every_reading_out(cases):
    rod, u = cases
    result = Estimator(rod, EstimatorOptions(noise=0.1, time_budget=0.0)).estimate(u)
    assert result.statuses == ["timeout"] * u.shape[0]
    # the best answer so far: no force fitted yet, reported as such, with finite numbers
    assert result.num_forces.eq(0).all() and torch.isfinite(result.loss).all()
    assert [r["status"] for r in result.to_records()] == ["timeout"] * u.shape[0]
    # a fixed count the budget left unfitted is not reported as a fit: the answer is the largest count fitted
    cut = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=2, time_budget=0.0)).estimate(u)
    assert cut.statuses == ["timeout"] * u.shape[0] and cut.num_forces.eq(0).all()
    assert all(r["forces"] == [] for r in cut.to_records())


def test_an_ample_budget_changes_nothing(cases):
    rod, u = cases
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    free = est.estimate(u)
    assert _same(free, est.estimate(u, options=_with(est, time_budget=60.0)))
    assert _same(free, est.estimate(u, options=_with(est, max_evaluations=100_000)))


@pytest.mark.parametrize("fixed", [None, 3])
def test_only_the_readings_the_evaluation_budget_cut_change(cases, fixed):
    """Budgets from tight to ample cut some readings and not others; every reading not called ``timeout`` has
    exactly its unbounded answer, every ``timeout`` is a reading whose search was really cut (it spent at least
    the budget, and no more work than unbounded), and the same budget gives the same answers again."""
    rod, u = cases
    est = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=fixed))
    free = est.estimate(u)
    seen = set()
    for budget in (5, 15, 30, 60):
        got = est.estimate(u, options=_with(est, max_evaluations=budget))
        assert _same(got, est.estimate(u, options=_with(est, max_evaluations=budget, threads=1)))
        for k in range(got.batch_size):
            out = got.statuses[k] == "timeout"
            seen.add(out)
            if not out:
                assert _same(got[k], free[k]), (budget, k)
            else:
                assert budget <= int(got.evaluations[k]) <= int(free.evaluations[k]), (budget, k)
                assert fixed is None or int(got.num_forces[k]) <= fixed
    assert seen == {True, False}, "the budgets should cut some readings and not others"


def test_a_deadline_stops_the_searches_where_they_stand(cases):
    """A wall-clock budget far below what the batch needs cuts most readings (the deadline reached from another
    thread while the kernels run); the answers are still well-formed."""
    rod, u = cases
    est = Estimator(rod, EstimatorOptions(noise=0.1, threads=1))
    est.estimate(u[:1])  # compiled before: the budget never counts compilation
    many = u.repeat(20, 1, 1)
    got = est.estimate(many, options=_with(est, time_budget=1e-6))
    assert got.statuses.count("timeout") > many.shape[0] // 2
    assert torch.isfinite(got.loss).all()


def test_the_time_budgets_alarms_fire_at_their_deadlines_and_not_once_cancelled():
    """The deadlines of calls are kept by one thread: each flag is set at or after its own deadline (whatever the
    order they were armed in), none before; a cancelled alarm never sets its flag."""
    from torchrod.estimate.estimator import _ALARMS

    class Flag:  # stands in for the kernels' stop flag, noting when it was set
        def __init__(self) -> None:
            self.at: float | None = None

        def fill(self, value: int) -> None:
            assert value == 1
            self.at = time.perf_counter()

    now = time.perf_counter()
    delays = (0.3, 0.1, 0.2, 0.15)
    flags = [Flag() for _ in delays]
    alarms = [_ALARMS.arm(now + delay, flag) for delay, flag in zip(delays, flags, strict=True)]
    _ALARMS.cancel(alarms[3])
    give_up = now + 10.0
    while not all(f.at is not None for f in flags[:3]) and time.perf_counter() < give_up:
        time.sleep(0.01)
    time.sleep(0.05)
    for delay, flag in zip(delays[:3], flags[:3], strict=True):
        assert flag.at is not None and flag.at >= now + delay
    assert flags[3].at is None
    passed = Flag()
    _ALARMS.arm(time.perf_counter() - 1.0, passed)
    assert passed.at is not None  # a deadline already past: set before arm returns


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
