"""No silent local minima: stratified clean readings are recovered, or the status says the answer is doubtful.

1,000 random noise-free cases (:mod:`torchrod.eval.recovery`): a third with a force within 20 mm of the first two
gratings, a third with 1 to 3 gratings missing, a third anywhere, pairs straddling a grating throughout. Every
case the data decide must be recovered exactly or within the answer's own error bars; the search may fail only
where it says so; a confident wrong answer fails the test. Every failure is printed.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchrod as tr
from torchrod.eval import recovery as R


def _show(rows):
    return "\n".join(
        f"{r['verdict']} {r['stratum']} status={r['status']} missing={r['missing']} truth="
        + str([(round(s, 5), round(math.hypot(*f), 4)) for s, f in r["truth"]])
        + " estimate="
        + str([(round(s, 5), round(math.hypot(*f), 4)) for s, f in r["estimate"]])
        for r in rows
    )


@pytest.mark.slow
def test_stratified_clean_recovery():
    rod = tr.presets.nitinol290()
    rows = R.run(rod, 1000, seed=0)
    summary = R.summarise(rows)
    total = summary["all"]
    print(summary)
    assert total["cases"] == 1000
    assert {s: summary[s]["cases"] for s in R.STRATA} == {"near base": 334, "missing": 333, "anywhere": 333}
    assert sum(r["straddle"] for r in rows) >= 100
    assert sum(r["decidable"] for r in rows) >= 300  # the claim is about many identifiable cases
    bad = [r for r in rows if r["verdict"] == "wrong"]
    assert not bad, "confident wrong answers:\n" + _show(bad)
    silent = [r for r in rows if r["verdict"] == "missed" and r["status"] == "ok"]
    assert not silent, "identifiable cases missed silently:\n" + _show(silent)
    missed = [r for r in rows if r["verdict"] == "missed"]
    assert len(missed) <= 2, "identifiable cases missed (flagged):\n" + _show(missed)
    # Most identifiable cases are recovered to 0.1 mm / 0.1 % outright.
    decided = [r for r in rows if r["decidable"]]
    assert sum(r["verdict"] == "exact" for r in decided) >= 0.97 * len(decided)


@pytest.mark.slow
def test_clean_recovery_up_to_the_elastic_limit():
    """The envelope of the elastic range (bending strain up to 4 %), a quarter of the cases turning the rod beyond
    135 degrees: no confident wrong answer, no identifiable case missed, every identifiable single force exact.
    (``torchrod evaluate --recovery 600 --large-bends`` runs more; docs/results.md has its table.)"""
    rod = tr.presets.nitinol290()
    rows = R.run(rod, 80, seed=1, elastic=True)
    summary = R.summarise(rows)
    print(summary)
    assert {s: summary[s]["cases"] for s in R.ELASTIC_STRATA} == {s: 20 for s in R.ELASTIC_STRATA}
    bad = [r for r in rows if r["verdict"] in ("wrong", "missed")]
    assert not bad, "confident wrong answers or missed identifiable cases:\n" + _show(bad)
    singles = [r for r in rows if r["decidable"] and len(r["truth"]) == 1]
    assert len(singles) >= 10
    assert all(r["verdict"] == "exact" for r in singles), _show([r for r in singles if r["verdict"] != "exact"])
    large = [r for r in rows if r["stratum"] == "large bend"]
    assert sum(r["verdict"] == "exact" for r in large) >= 0.7 * len(large)


def test_the_elastic_envelope_is_what_it_says():
    """Every "large bend" case turns the rod beyond 135 degrees, and no case bends it beyond the strain limit."""
    from torchrod.model.body_frame import simulate

    rod = tr.presets.nitinol290()
    cases = R.recovery_cases(rod, 16, seed=4, elastic=True, max_strain=0.03)
    assert [c.stratum for c in cases] == list(R.ELASTIC_STRATA) * 4
    loads = tr.PointForces.from_lists(
        [[(s, fx, fy) for s, (fx, fy) in zip(c.s, c.f, strict=True)] for c in cases], max_forces=3
    )
    sim = simulate(rod, loads, samples=513)
    size = sim.curvature_magnitude()
    turning = torch.trapezoid(size, sim.s, dim=-1)
    assert float(size.amax()) * rod.outer_diameter / 2 <= 0.03 * 1.01
    large = torch.tensor([c.stratum == "large bend" for c in cases])
    assert bool((turning[large] > math.radians(135.0)).all())
    assert float(turning[large].max()) > math.radians(180.0)  # the envelope reaches past a half turn
    with pytest.raises(ValueError, match="max_strain"):
        R.recovery_cases(rod, 1, elastic=True, max_strain=2.0)


def test_identifiable_classifier():
    """The classifier's rules, on hand-made cases."""
    rod = tr.presets.nitinol290()
    G = len(rod.gratings)

    def case(s, f, present=None, stratum="anywhere"):
        return R.RecoveryCase(s, f, present or [True] * G, stratum, False)

    # One force mid-interval: decided.
    assert R.identifiable(rod, case([0.15], [(0.5, -0.3)]))
    # In the first interval (only the first grating sees it): not decided.
    assert not R.identifiable(rod, case([0.02], [(0.5, -0.3)]))
    # Two forces in one interval: not decided.
    assert not R.identifiable(rod, case([0.151, 0.165], [(0.5, -0.3), (0.2, 0.4)]))
    # A force 3 micrometres past the second grating bends only the first measurably: not decided.
    assert not R.identifiable(rod, case([0.030003], [(1.0, 0.5)]))
    # The same force with the first grating missing falls into the first interval.
    present = [False] + [True] * (G - 1)
    assert not R.identifiable(rod, case([0.04], [(1.0, 0.5)], present))


def test_judge_verdicts():
    c = R.RecoveryCase([0.1, 0.2], [(1.0, 0.0), (0.0, 0.5)], [True] * 14, "anywhere", False)
    tight = [(1e-6, 1e-4, 1e-4)] * 2
    exact = ([0.10005, 0.2], [(1.0005, 0.0), (0.0, 0.5)])
    assert R.judge(c, 2, *exact, tight, "ok", True, False) == "exact"
    off = ([0.1003, 0.2], [(1.0, 0.0), (0.0, 0.5)])
    assert R.judge(c, 2, *off, tight, "ok", True, False) == "missed"
    assert R.judge(c, 2, *off, [(1e-3, 1e-2, 1e-2)] * 2, "ok", True, False) == "within_error"
    assert R.judge(c, 2, *off, tight, "poorly_determined", False, False) == "flagged"
    assert R.judge(c, 2, *off, tight, "ok", False, False) == "wrong"
    one = ([0.15], [(1.0, 0.5)])
    assert R.judge(c, 1, *one, tight[:1], "ok", False, True) == "parsimonious"
    assert R.judge(c, 1, *one, tight[:1], "ok", False, False) == "wrong"


def test_explains_is_an_independent_check():
    rod = tr.presets.nitinol290()
    c = R.RecoveryCase([0.12], [(0.8, -0.2)], [True] * 14, "anywhere", False)
    u, _ = R.readings(rod, [c])
    assert R.explains(rod, c, u[0], [0.12], [(0.8, -0.2)], 1e-3)
    assert not R.explains(rod, c, u[0], [0.121], [(0.8, -0.2)], 1e-3)
    assert torch.isfinite(u).all()


def test_the_gauss_newton_condition_is_that_of_the_autograd_jacobian():
    """The condition from one reverse pass over copies of the case against the Jacobian torch's autograd builds one
    value at a time (``torch.autograd.functional.jacobian``), on cases with missing gratings and 1-3 forces."""
    import numpy as np

    from torchrod.model.body_frame import simulate

    rod = tr.presets.nitinol290()
    for case in R.recovery_cases(rod, 6, seed=2):

        def curvature(s: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
            return simulate(rod, tr.PointForces(s, f)).grating_curvature[0]  # noqa: B023 (used at once)

        s0, f0 = torch.tensor([case.s], dtype=torch.float64), torch.tensor([case.f], dtype=torch.float64)
        js, jf = torch.autograd.functional.jacobian(curvature, (s0, f0))  # (G, 2, 1, h), (G, 2, 1, h, 2)
        J = torch.cat((js[:, :, 0, :, None], jf[:, :, 0]), dim=-1)[torch.tensor(case.present)]
        J = J.reshape(-1, 3 * len(case.s)).numpy()
        N = J.T @ J
        d = np.sqrt(np.diag(N))
        expected = float(np.linalg.cond(N / np.outer(d, d)))
        assert R.gauss_newton_condition(rod, case) == pytest.approx(expected, rel=1e-9), case


def test_the_gauss_newton_condition_tells_a_determined_force_from_one_the_gratings_cannot_place():
    """A force between the 5th and 6th gratings of the paper's tube is seen by five gratings: its (s, f_x, f_y) are
    determined, the scaled normal matrix well conditioned. The same force with only the nearest grating proximal
    to it present: magnitude and lever cannot be told apart, the matrix is singular to rounding. Two forces in one
    place: singular too."""
    rod = tr.presets.nitinol290()
    G = rod.num_gratings
    one = R.RecoveryCase([0.10], [(0.4, -0.3)], [True] * G, "anywhere", False)
    alone = R.RecoveryCase([0.10], [(0.4, -0.3)], [k == 4 for k in range(G)], "missing", False)  # 90 mm only
    pair = R.RecoveryCase([0.10, 0.10], [(0.4, -0.3), (0.4, -0.3)], [True] * G, "anywhere", False)
    good = R.gauss_newton_condition(rod, one)
    assert 1.0 <= good < 1e4
    assert R.gauss_newton_condition(rod, alone) > 1e8
    assert R.gauss_newton_condition(rod, pair) > 1e8
    assert R.identifiable(rod, one) and not R.identifiable(rod, pair)
