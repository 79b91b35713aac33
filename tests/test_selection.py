"""Count selection (0 included), settlement, the verdict, and the uncertainty's linear algebra."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchrod.backend import NUMPY, torch_backend
from torchrod.estimate.selection import ceilings, chi2_quantile, chi2_survival, f_quantile, select_count, settled
from torchrod.estimate.status import STATUSES, verdict
from torchrod.estimate.uncertainty import gauss_newton_covariance

BACKENDS = [NUMPY, torch_backend()]


def test_quantiles_are_scipy_stats():
    for p, k in ((0.95, 3), (0.999, 25), (0.5, 1)):
        assert math.isclose(chi2_quantile(p, k), stats.chi2.ppf(p, k), rel_tol=1e-12)
        assert math.isclose(f_quantile(p, k, 20), stats.f.ppf(p, k, 20), rel_tol=1e-12)
    assert chi2_quantile(0.9, 0) == math.inf
    x = np.array([1.0, 10.0, 40.0])
    assert np.allclose(chi2_survival(x, np.array([3, 3, 25])), stats.chi2.sf(x, [3, 3, 25]), rtol=1e-12)
    assert np.isnan(chi2_survival([1.0], [0])[0])


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_selection_rules_on_given_losses(xp):
    counts, n = [0, 1, 2, 3], xp.asarray([28] * 5, "int")
    sigma = 0.1
    c1 = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2  # largest allowed loss drop for one more force
    base = 0.25  # about sigma^2 (28 - 3)
    big = 50.0
    losses = xp.asarray(
        [
            [big, base, base - 0.5 * c1, base - 0.6 * c1],  # a second force explains noise only: 1
            [big, base + 2 * c1, base, base - 0.1 * c1],  # the second force is needed: 2
            [big, 50.0, 49.0, base],  # two forces do not help but three do: 3 (not 1)
            [0.28, 0.27, 0.26, 0.25],  # pure noise: no force helps: 0
            [big, base, math.nan, math.nan],  # only counts 0 and 1 fitted
        ]
    )
    chosen, used = select_count(xp, losses, counts, n, noise=sigma, significance=0.05, num_gratings=14)
    assert xp.tolist(chosen) == [1, 2, 3, 0, 1]
    assert np.allclose(xp.tolist(used), sigma)
    chosen, _ = select_count(xp, losses, counts, n, rule="threshold", threshold=1.0)
    assert xp.tolist(chosen) == [1, 1, 3, 0, 1]  # the paper's rule: the first loss below the threshold
    # sigma estimated from the largest fit: the F test gives the same answers on these
    chosen, used = select_count(xp, losses[:4], counts, n[:4], noise=None, significance=0.05, num_gratings=14)
    assert xp.tolist(chosen) == [1, 2, 3, 0]
    assert math.isclose(xp.tolist(used)[0], math.sqrt((base - 0.6 * c1) / 19), rel_tol=1e-12)
    with pytest.raises(ValueError, match="counts"):
        select_count(xp, losses, [1, 0, 2, 3], n)


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_when_no_count_is_accepted_the_fewest_forces_no_larger_count_improves_on(xp):
    """A reading no count explains (every loss far above the misfit guard) reports the fewest forces that no larger
    count improves on beyond noise, not the largest count; the same where no count has degrees of freedom left (one
    present grating: 2 residuals, so a single force already fits exactly). Nothing passes: the largest count."""
    counts, sigma = [0, 1, 2, 3], 0.1
    c1 = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2
    losses = xp.asarray(
        [
            [50.0, 30.0, 20.0, 20.0 - 0.5 * c1],  # misfit at every count; the third force adds nothing: 2
            [50.0, 30.0, 20.0, 10.0],  # misfit, every force helps: 3
            [5.0, 1e-12, 1e-13, 1e-14],  # 2 residuals: one force fits exactly: 1
        ]
    )
    n = xp.asarray([28, 28, 2], "int")
    for noise in (sigma, None):
        chosen, _ = select_count(
            xp, losses, counts, n, noise=noise, significance=0.05, num_gratings=14, floor=1e-3
        )  # the estimator's floor: with the noise unknown and no degrees of freedom, sigma is the floor
        assert xp.tolist(chosen)[2] == 1
        if noise is not None:
            assert xp.tolist(chosen)[:2] == [2, 3]


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_a_count_is_chosen_just_below_its_ceiling_and_not_just_above(xp):
    """ceilings() is the largest loss at which select_count accepts a count: on random losses (counts 0..3 or
    0..2 fitted, 12 or 28 residuals, noise given and unknown, the largest count's fit acceptable), a count whose
    loss is set 1e-9 below its ceiling is chosen (the smaller counts made hopeless), and 1e-9 above it is not."""
    rng = np.random.default_rng(7)
    counts = [0, 1, 2, 3]
    kw = dict(rule="noise", significance=0.05, num_gratings=14, floor=1e-3)
    checked = 0
    for noise in (0.1, None):
        for _ in range(40):
            n, top = int(rng.choice([12, 28])), int(rng.choice([2, 3]))
            losses = np.full(4, np.nan)
            losses[: top + 1] = rng.uniform(0.0, 3.0, top + 1)
            losses[top] = rng.uniform(0.0, 0.01 * (n - 3 * top))  # about what noise of 0.1 leaves
            res = xp.asarray([n], "int")
            for h in range(top):
                trial = losses.copy()
                trial[:h] = 1e6  # beyond every misfit and drop limit: never accepted
                c = xp.tolist(ceilings(xp, xp.asarray(trial[None]), counts, res, noise=noise, **kw))[0][h]
                if c <= 1e-6:  # a ceiling below the loss scale the test can resolve
                    continue
                for delta, chosen in ((-1e-9, True), (1e-9, False)):
                    trial[h] = c + delta
                    got, _ = select_count(xp, xp.asarray(trial[None]), counts, res, noise=noise, **kw)
                    assert (xp.tolist(got)[0] == h) == chosen, (noise, n, trial.tolist(), h, c)
                checked += 1
    assert checked > 100
    with_threshold = ceilings(
        xp, xp.asarray([[1.0, 0.5]]), [0, 1], xp.asarray([28], "int"), rule="threshold", threshold=2.0
    )
    assert xp.tolist(with_threshold) == [[2.0, 2.0]]
    with pytest.raises(ValueError, match="rule"):
        ceilings(xp, xp.asarray([[1.0, 0.5]]), [0, 1], xp.asarray([28], "int"), rule="paper")


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_a_count_is_settled_only_when_one_more_force_cannot_change_it(xp):
    n = xp.asarray([28, 28, 28], "int")
    sigma = 0.1
    drop = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2
    losses = xp.asarray([[50.0, 0.25], [50.0, 0.25], [50.0, 30.0]])
    gain = xp.asarray([0.1 * drop, 0.9 * drop, 29.0])
    kw = dict(rule="noise", noise=sigma, threshold=3.0, significance=0.05, floor=0.0, num_gratings=14)
    # 1: the promised gain is far below the drop test; 2: within the safety factor; 3: count 1 is no fit at all
    assert xp.tolist(settled(xp, losses, [0, 1], n, gain, **kw)) == [True, False, False]
    # with the noise unknown nothing is settled (sigma comes from the largest fit)
    assert not bool(xp.any(settled(xp, losses, [0, 1], n, gain, **{**kw, "noise": None})))


def test_verdict_order():
    p = np.array([1e-5, 1e-5, 0.5, 0.5, 0.5])
    conv = np.array([False, True, False, True, True])
    poor = np.array([True, True, True, True, False])
    codes = verdict(NUMPY, p, conv, poor, 1e-3)
    assert [STATUSES[c] for c in codes.tolist()] == [
        "misfit",
        "misfit",
        "unconverged",
        "poorly_determined",
        "ok",
    ]
    # a search cut by the time budget says so before anything else
    codes = verdict(NUMPY, p, conv, poor, 1e-3, np.array([True, False, False, False, True]))
    assert [STATUSES[c] for c in codes.tolist()] == ["timeout", "misfit", "unconverged", "poorly_determined", "timeout"]


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_gauss_newton_covariance_of_a_linear_model(xp):
    gen = torch.Generator().manual_seed(3)
    J = torch.randn(2, 10, 3, dtype=torch.float64, generator=gen)
    sigma = torch.tensor([0.1, 2.0], dtype=torch.float64)
    cov, cond = gauss_newton_covariance(xp, xp.asarray(J), xp.asarray(sigma), xp.asarray(torch.ones(2, 3), "bool"))
    ref = torch.linalg.inv(J.transpose(1, 2) @ J) * (sigma**2).view(2, 1, 1)
    assert np.allclose(xp.tolist(cov), ref.numpy(), rtol=1e-10)
    assert all(c >= 1 for c in xp.tolist(cond))
    active = xp.asarray([[True, True, False], [True, True, True]], "bool")
    cov, _ = gauss_newton_covariance(xp, xp.asarray(J), xp.asarray(torch.ones(2, dtype=torch.float64)), active)
    cov = np.asarray(xp.tolist(cov))
    assert np.isnan(cov[0, 2]).all() and np.isnan(cov[0, :, 2]).all()
    assert np.allclose(cov[0, :2, :2], torch.linalg.inv(J[0, :, :2].T @ J[0, :, :2]).numpy(), rtol=1e-10)


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_the_covariance_of_a_broken_matrix_is_nan_not_an_exception(xp):
    """A row with NaN or infinite entries (a reading of 1e300, a diverged fit) gets NaN and an infinite condition
    number; the other rows of the batch are unaffected."""
    J = torch.randn(3, 10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    J[1, 2, 1] = math.nan
    J[2, 0, 0] = math.inf
    cov, cond = gauss_newton_covariance(
        xp,
        xp.asarray(J),
        xp.asarray(torch.ones(3, dtype=torch.float64)),
        xp.asarray(torch.ones(3, 3), "bool"),
    )
    cov, cond = np.asarray(xp.tolist(cov)), np.asarray(xp.tolist(cond))
    assert np.isfinite(cov[0]).all() and np.isfinite(cond[0])
    assert np.isnan(cov[1:]).all() and np.isinf(cond[1:]).all()
