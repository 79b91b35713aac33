"""Force estimation: the sensitivity model, starts, count selection, uncertainty and the Estimator end to end."""

from __future__ import annotations

import math

import pytest
import torch

import torchrod as tr
from torchrod.estimate.estimator import EstimateResult, Estimator, EstimatorOptions
from torchrod.estimate.selection import count_limits, select_count
from torchrod.estimate.starts import GridStarts
from torchrod.estimate.uncertainty import gauss_newton_covariance
from torchrod.model.body_frame import integrate_curvature
from torchrod.model.sensitivity import curvature_and_jacobian

F64 = torch.float64


def readings(rod: tr.Rod, cases, noise: float = 0.0, seed: int = 0) -> tuple[tr.PointForces, torch.Tensor]:
    """Loads from per-case (s, fx, fy) lists (padded to 3) and their simulated readings with Gaussian noise."""
    loads = tr.PointForces.from_lists(cases, max_forces=3)
    clean = tr.simulate(rod, loads).grating_curvature
    gen = torch.Generator().manual_seed(seed)
    return loads, clean + noise * torch.randn(clean.shape, generator=gen, dtype=F64)


def sampled(
    rod: tr.Rod,
    k: int,
    count: int,
    noise: float,
    seed: int,
    s_min: float = 0.05,
    separation=0.025,
    force=(0.05, 2.0),
):
    from torchrod.learn.synthetic import LoadSampler, SensorModel, generate

    sampler = LoadSampler(
        min_forces=k, max_forces=k, force_range=force, min_separation=separation, s_range=(s_min, rod.length)
    )
    return generate(rod, count, sampler=sampler, sensor=SensorModel(noise=noise), seed=seed)


def force_errors(result: EstimateResult, loads: tr.PointForces, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Relative force errors and location errors [m] of the first k forces (both sorted by s)."""
    tf, ef = loads.f[:, :k], result.forces.f[:, :k]
    rel = torch.linalg.vector_norm(ef - tf, dim=-1) / torch.linalg.vector_norm(tf, dim=-1)
    return rel, (result.forces.s[:, :k] - loads.s[:, :k]).abs()


# ---------------------------------------------------------------------------------------------- sensitivity
def test_sensitivity_matches_forward_model_and_autograd(rod, gen):
    s = 0.03 + 0.26 * torch.rand(4, 3, dtype=F64, generator=gen)
    f = 0.6 * torch.randn(4, 3, 2, dtype=F64, generator=gen)
    q = rod.grating_positions()
    u, J = curvature_and_jacobian(
        q, s, f, rod.length, rod.bending_stiffness, max_step_angle=0.02, max_steps=400
    )
    ref = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    assert (u - ref).abs().max() < 1e-7 * ref.abs().max()

    def fwd(s_, f_):
        return integrate_curvature(q, tr.PointForces(s_, f_), rod.length, rod.bending_stiffness)[0]

    Js, Jf = torch.autograd.functional.jacobian(fwd, (s, f))
    Js = torch.stack([Js[b, :, :, b] for b in range(4)])  # (B, G, 2, h)
    Jf = torch.stack([Jf[b, :, :, b] for b in range(4)])  # (B, G, 2, h, 2)
    assert (J[..., 0] - Js).abs().max() < 1e-6 * Js.abs().max()
    assert (J[..., 1:] - Jf).abs().max() < 1e-6 * Jf.abs().max()


def test_sensitivity_padding_and_batch_independence(rod, gen):
    s = 0.03 + 0.26 * torch.rand(6, 3, dtype=F64, generator=gen)
    f = 0.6 * torch.randn(6, 3, 2, dtype=F64, generator=gen)
    q = rod.grating_positions()
    mask = torch.tensor([[True, True, False]] * 6)
    u, J = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, mask=mask)
    u2, _J2 = curvature_and_jacobian(q, s[:, :2], f[:, :2], rod.length, rod.bending_stiffness)
    assert (u - u2).abs().max() < 1e-4  # padded force: no load (its event only splits a segment)
    assert J[..., 2, :].abs().max() == 0.0  # and zero Jacobian columns
    for b in range(6):  # each row's steps are its own: batching does not change a result
        ub, Jb = curvature_and_jacobian(
            q, s[b : b + 1], f[b : b + 1], rod.length, rod.bending_stiffness, mask=mask[b : b + 1]
        )
        assert torch.equal(ub, u[b : b + 1]) and torch.equal(Jb, J[b : b + 1])


@pytest.mark.parametrize("h", [1, 2, 3])
def test_sensitivity_scalar_rows_equal_the_batched_march(rod, gen, monkeypatch, h):
    """Small CPU batches march row by row on Python complex numbers: the same numbers as the torch march, also
    with padded forces, a force exactly on a grating (event order), one at the tip and the step cap binding."""
    import torchrod.model.sensitivity as sens

    B = 6
    q = rod.grating_positions()
    s = 0.03 + 0.26 * torch.rand(B, h, dtype=F64, generator=gen)
    s[0, 0] = q[4]  # on a grating: the grating does not see it
    s[1, -1] = rod.length
    f = 1.5 * torch.randn(B, h, 2, dtype=F64, generator=gen)
    mask = torch.rand(B, h, generator=gen) > 0.3
    mask[:, 0] = True
    for kwargs in ({}, {"mask": mask}, {"max_steps": 2}, {"jacobian": False}):
        u1, J1 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, **kwargs)
        monkeypatch.setattr(sens, "SCALAR_ROWS", 0)
        u2, J2 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, **kwargs)
        monkeypatch.setattr(sens, "SCALAR_ROWS", 8)
        assert u1.dtype == u2.dtype and u1.shape == u2.shape
        assert (u1 - u2).abs().max() <= 1e-12 * u2.abs().max()
        if J2 is None:
            assert J1 is None
        else:
            assert J1.shape == J2.shape and (J1 - J2).abs().max() <= 1e-12 * J2.abs().max()


# ---------------------------------------------------------------------------------------------- starts
def test_grid_starts_are_exact_for_small_forces_on_the_grid(rod):
    grid = GridStarts(rod)
    cand = grid.candidates(2)
    s_true = cand[(cand[:, 0] > 0.08).nonzero()[5, 0]]  # a pair of the scan, both seen by several gratings
    loads = tr.PointForces(s_true.view(1, 2), torch.tensor([[[1e-4, -2e-4], [3e-4, 1e-4]]], dtype=F64))
    u = tr.simulate(rod, loads).grating_curvature
    st = grid(u, torch.ones(1, rod.num_gratings, dtype=torch.bool), 2, 2)
    assert torch.allclose(st.s[0, 0], s_true)  # linear regime: the true pair is the best candidate
    assert torch.allclose(st.f[0, 0], loads.f[0], rtol=1e-3, atol=1e-9)
    assert (st.s[0, 1] - st.s[0, 0]).abs().max() >= grid.separation  # the second start is not a near copy


# ---------------------------------------------------------------------------------------------- selection
def test_selection_rules_on_given_losses():
    counts, n = [1, 2, 3], torch.tensor([28, 28, 28, 28])
    sigma = 0.1
    drop, _misfit = count_limits(counts, n, significance=0.05, num_gratings=14)
    c1 = float(drop[0, 0, 1]) * sigma**2  # largest allowed loss drop for one more force
    base = 0.25  # about sigma^2 (28 - 3)
    losses = torch.tensor(
        [
            [base, base - 0.5 * c1, base - 0.6 * c1],  # a second force explains noise only: 1
            [base + 2 * c1, base, base - 0.1 * c1],  # the second force is needed: 2
            [50.0, 49.0, base],  # two forces do not help but three do: 3 (not 1)
            [base, float("nan"), float("nan")],  # only one count fitted
        ],
        dtype=F64,
    )
    chosen, used = select_count(losses, counts, n, noise=sigma, significance=0.05, num_gratings=14)
    assert chosen.tolist() == [1, 2, 3, 1]
    assert torch.allclose(used, torch.full((4,), sigma, dtype=F64))
    # the paper's rule: first loss below the threshold
    chosen, _ = select_count(losses, counts, n, rule="threshold", threshold=1.0)
    assert chosen.tolist() == [1, 1, 3, 1]
    # sigma estimated from the largest fit: the F test gives the same answers on these
    chosen, used = select_count(losses[:3], counts, n[:3], noise=None, significance=0.05, num_gratings=14)
    assert chosen.tolist() == [1, 2, 3]
    assert torch.allclose(used[0], torch.tensor(math.sqrt((base - 0.6 * c1) / 19), dtype=F64))


# ---------------------------------------------------------------------------------------------- uncertainty
def test_gauss_newton_covariance_of_a_linear_model():
    gen = torch.Generator().manual_seed(3)
    J = torch.randn(2, 10, 3, dtype=F64, generator=gen)
    cov, cond = gauss_newton_covariance(J, torch.tensor([0.1, 2.0], dtype=F64))
    ref = torch.linalg.inv(J.transpose(1, 2) @ J) * torch.tensor([0.01, 4.0], dtype=F64).view(2, 1, 1)
    assert torch.allclose(cov, ref, rtol=1e-10)
    assert bool((cond >= 1).all())
    active = torch.tensor([[True, True, False], [True, True, True]])
    cov, _ = gauss_newton_covariance(J, torch.ones(2, dtype=F64), active)
    assert torch.isnan(cov[0, 2]).all() and torch.isnan(cov[0, :, 2]).all()
    assert torch.allclose(cov[0, :2, :2], torch.linalg.inv(J[0, :, :2].T @ J[0, :, :2]), rtol=1e-10)


# ---------------------------------------------------------------------------------------------- recovery
CLEAN_CASES = [
    [(0.2, 0.3, 0.0)],
    [(0.07, -1.2, 0.5)],
    [(0.29, 0.05, -0.2)],  # a tip contact: s = L exactly
    [(0.13, 0.4, 0.4)],  # exactly on a grating (a kink of the loss)
    [(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)],
    [(0.06, 0.8, 0.1), (0.16, -0.3, -0.6)],
    [(0.08, 0.5, 0.2), (0.16, -0.4, 0.3), (0.24, 0.1, -0.25)],
    [(0.06, -0.7, 0.9), (0.14, 0.6, 0.2), (0.27, 0.1, 0.15)],
]


def test_clean_readings_are_recovered(rod):
    """Noise-free readings: every count right, forces within 0.1 %, locations within 0.1 mm."""
    loads, u = readings(rod, CLEAN_CASES)
    result = Estimator(rod, EstimatorOptions(noise=0.0)).estimate(u)
    assert result.num_forces.tolist() == [len(c) for c in CLEAN_CASES]
    for b, case in enumerate(CLEAN_CASES):
        k = len(case)
        rel, ds = force_errors(result[b], loads[b], k)
        assert rel.max() < 1e-3, (case, result.forces[b].to_lists())
        assert ds.max() < 1e-4, (case, result.forces[b].to_lists())
    assert bool(result.converged.all())
    assert bool((result.loss < 1e-4).all())


@pytest.mark.parametrize("k", [1, 2, 3])
def test_clean_random_readings_are_recovered(rod, k):
    """Random well-conditioned cases (forces >= 0.2 N, >= 40 mm apart, from the third grating on)."""
    data = sampled(rod, k, 12, 0.0, seed=20 + k, separation=0.04, force=(0.2, 2.0))
    result = Estimator(rod, EstimatorOptions(noise=0.0)).estimate(data.curvature)
    assert bool((result.num_forces == k).all())
    rel, ds = force_errors(result, data.loads, k)
    assert rel.max() < 1e-3
    assert ds.max() < 1e-4


def test_batched_equals_one_at_a_time(rod):
    """The batched path: a reading's result does not depend on the readings batched with it."""
    _loads, u = readings(rod, CLEAN_CASES[:6], noise=0.1, seed=5)
    est = Estimator(rod, EstimatorOptions(noise=0.1, scalar_readings=0))
    together = est.estimate(u)
    for b in range(u.shape[0]):
        alone = est.estimate(u[b : b + 1])
        assert alone.num_forces.item() == together.num_forces[b].item()
        assert torch.allclose(alone.forces.s, together.forces.s[b : b + 1], rtol=0, atol=1e-9)
        assert torch.allclose(alone.forces.f, together.forces.f[b : b + 1], rtol=0, atol=1e-9)
        assert torch.allclose(alone.loss, together.loss[b : b + 1], rtol=1e-9)


@pytest.mark.parametrize("num_forces", [None, 1])
def test_small_batch_path_reaches_the_batched_optimum(rod, num_forces):
    """One reading per call on Python floats (scalar_fit) against the batched path on the same readings: the
    same count, and the same optimum to within the stopping tolerance in nearly every reading (the two take
    slightly different routes, so a reading may end in another local minimum: 1 in 60 two-force readings when
    measured; none of 150 one-force readings)."""
    data = sampled(rod, 1, 12, 0.1, seed=41)
    two = sampled(rod, 2, 12, 0.1, seed=42)
    u = torch.cat((data.curvature, two.curvature))
    est = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=num_forces))
    batched = est.estimate(u, scalar_readings=0)
    small = [est.estimate(u[b : b + 1]) for b in range(u.shape[0])]
    assert all(r.num_forces.item() == batched.num_forces[b].item() for b, r in enumerate(small))
    same = 0
    for b, r in enumerate(small):
        h = r.num_forces.item()
        ds = (r.forces.s[0, :h] - batched.forces.s[b, :h]).abs().max().item()
        df = (r.forces.f[0, :h] - batched.forces.f[b, :h]).abs().max().item()
        same += ds < 1e-5 and df < 1e-4
        assert r.converged.item() == batched.converged[b].item()  # (one 2-force reading fits no single force)
        assert r.std.shape == (1, est.options.width, 3) and torch.isfinite(r.std[0, :h]).all()
    assert same >= u.shape[0] - 2, same
    # several readings in one call take the same path, reading by reading
    four = est.estimate(u[:4])
    for b in range(4):
        assert torch.equal(four.forces.s[b], small[b].forces.s[0])
        torch.testing.assert_close(
            four.losses_by_count[b], small[b].losses_by_count[0], rtol=0, atol=0, equal_nan=True
        )


def test_small_batch_path_hands_kinks_to_the_batched_path(rod, monkeypatch):
    """A clean reading whose force sits exactly on a grating: its optimum is on the loss's kink, which only the
    batched path handles; the one-reading path hands that reading over, and keeps the others."""
    on = rod.gratings[6]
    cases = [[(0.2, 0.3, -0.2)], [(on, 0.4, 0.25)], [(0.12, -0.5, 0.1)]]
    loads, u = readings(rod, cases)
    est = Estimator(rod, EstimatorOptions(noise=0.0, num_forces=1))
    handed = []
    batched_path = est._estimate_batched

    def spy(curvature, *args):
        handed.append(curvature.shape[0])
        return batched_path(curvature, *args)

    monkeypatch.setattr(est, "_estimate_batched", spy)
    result = est.estimate(u)
    assert handed == [1]  # only the reading on the kink
    reference = Estimator(rod, EstimatorOptions(noise=0.0, num_forces=1, scalar_readings=0)).estimate(u[1:2])
    assert torch.equal(result.forces.s[1], reference.forces.s[0])
    assert torch.equal(result.std[1], reference.std[0])
    assert abs(result.forces.s[1, 0].item() - on) < 1e-6 and bool(result.converged.all())
    rel, ds = force_errors(result, loads, 1)
    assert rel.max() < 1e-3 and ds.max() < 1e-4


def test_choose_count_is_select_count_for_one_reading(gen):
    """The one-reading twin of the count selection gives select_count's choice (random losses, NaN = unfitted)."""
    from torchrod.estimate.selection import choose_count

    counts = [1, 2, 3]
    for trial in range(300):
        losses = torch.rand(3, generator=gen, dtype=F64) * torch.tensor([2.0, 1.0, 0.6], dtype=F64)
        losses = losses.sort(descending=True).values
        if trial % 7 == 0:
            losses[2] = float("nan")
        n = int(torch.randint(8, 29, (1,), generator=gen))
        noise = float(torch.rand(1, generator=gen)) * 0.2 + 0.01
        for rule in ("noise", "threshold"):
            chosen, _ = select_count(
                losses.view(1, 3),
                counts,
                torch.tensor([n]),
                rule=rule,
                noise=noise,
                threshold=0.5,
                floor=0.01,
                num_gratings=14,
            )
            mine = choose_count(
                losses.tolist(),
                counts,
                n,
                rule=rule,
                sigma2=noise**2 + 0.01**2,
                threshold=0.5,
                significance=0.05,
                num_gratings=14,
            )
            assert counts[mine] == chosen.item(), (losses, n, noise, rule)


def test_scalar_gauss_newton_step_is_the_cholesky_solution(gen):
    from torchrod.estimate.scalar_fit import ReadingFit

    for P in (3, 6, 9):
        J = torch.randn(28, P, generator=gen, dtype=F64)
        r = torch.randn(28, generator=gen, dtype=F64)
        A, g = J.T @ J, J.T @ r
        step, dec = ReadingFit._step(A.tolist(), g.tolist(), 0.1)
        damped = A + torch.diag(0.1 * A.diagonal() + 1e-12 * A.diagonal().max())
        expected = -torch.linalg.solve(damped, g)
        assert torch.allclose(torch.tensor(step, dtype=F64), expected, rtol=1e-10, atol=1e-12)
        assert math.isclose(dec, -(g @ expected).item(), rel_tol=1e-10)
    bad, dec = ReadingFit._step([[1.0, 2.0], [2.0, 1.0]], [1.0, 0.0], 0.0)  # indefinite
    assert dec == math.inf and bad == [0.0, 0.0]


def test_missing_gratings_are_masked_out(rod):
    loads, u = readings(rod, CLEAN_CASES[4:6], noise=0.0)
    est = Estimator(rod, EstimatorOptions(noise=0.0))
    missing = torch.zeros(2, rod.num_gratings, dtype=torch.bool)
    missing[0, [2, 7]] = True
    missing[1, [0, 5, 11]] = True
    holed = u.masked_fill(missing.unsqueeze(-1), float("nan"))
    result = est.estimate(holed)  # NaN marks the missing gratings
    assert result.num_forces.tolist() == [2, 2]
    rel, ds = force_errors(result, loads, 2)
    assert rel.max() < 1e-3 and ds.max() < 1e-4
    # an explicit mask ignores whatever the missing entries hold (garbage, not zeros)
    garbage = u.masked_fill(missing.unsqueeze(-1), 1e3)
    again = est.estimate(garbage, ~missing)
    assert torch.allclose(again.forces.f, result.forces.f, atol=1e-12)
    # zeroed gratings, by contrast, would be data: the fit must differ
    zeroed = est.estimate(u.masked_fill(missing.unsqueeze(-1), 0.0))
    assert not torch.allclose(zeroed.forces.f, result.forces.f, atol=1e-3)


def test_uncertainty_is_calibrated(rod):
    """Noisy one-force readings: about 68 % of the true values lie within one reported std.

    300 readings: the fraction inside has a binomial standard deviation of sqrt(0.683 * 0.317 / 300) = 0.027; the
    tolerance 0.1 is 3.7 of them (a chance failure below 3e-4 per parameter), while a std wrong by a factor 1.5
    would move the fraction to 0.49 or 0.87.
    """
    data = sampled(rod, 1, 300, 0.1, seed=11, s_min=0.05)
    result = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=1)).estimate(data.curvature)
    z_s = (result.forces.s[:, 0] - data.loads.s[:, 0]) / result.std[:, 0, 0]
    z_f = (result.forces.f[:, 0] - data.loads.f[:, 0]) / result.std[:, 0, 1:]
    inside = torch.stack((z_s.abs() < 1, z_f[:, 0].abs() < 1, z_f[:, 1].abs() < 1), dim=1).double()
    frac = inside.mean(dim=0)
    assert bool(((frac - 0.683).abs() < 0.1).all()), frac
    assert torch.allclose(result.noise, torch.full_like(result.noise, math.hypot(0.1, 0.01)))


def test_one_force_is_not_split(rod):
    """100 noisy one-force readings: the count is 1 in at least 95 (the false-split rate is about 1 %)."""
    data = sampled(rod, 1, 100, 0.1, seed=12, s_min=0.03)
    result = Estimator(rod, EstimatorOptions(noise=0.1)).estimate(data.curvature)
    assert int((result.num_forces == 1).sum()) >= 95


def test_close_forces_are_kept_apart_when_the_data_tell(rod):
    """Noise 0.1 1/m. Two perpendicular 0.5 N forces 25 mm apart: two forces (one force misses them by far more
    than noise). Two parallel 0.35 N forces 4 mm apart with no grating between them: proximal to both, their
    curvature is that of one 0.7 N force at their midpoint (to first order), so the data cannot tell them apart and
    they are merged into it."""
    apart = [[(0.150, 0.5, 0.0), (0.175, 0.0, 0.5)]] * 20
    close = [[(0.155, 0.35, 0.0), (0.159, 0.35, 0.0)]] * 20
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    _, u = readings(rod, apart, noise=0.1, seed=31)
    result = est.estimate(u)
    assert int((result.num_forces == 2).sum()) >= 19, result.num_forces.tolist()
    _, u = readings(rod, close, noise=0.1, seed=32)
    merged = est.estimate(u)
    assert int((merged.num_forces == 1).sum()) >= 19, merged.num_forces.tolist()
    one = merged.num_forces == 1
    assert torch.allclose(merged.forces.magnitude()[one, 0], torch.tensor(0.7, dtype=F64), rtol=0.05)
    assert bool(((merged.forces.s[one, 0] - 0.157).abs() < 3e-3).all())


def test_threshold_rule_and_fixed_count(rod):
    _loads, u = readings(rod, CLEAN_CASES[4:5])
    est = Estimator(rod)
    paper = est.estimate(u, selection="threshold", threshold=3.0)
    assert paper.num_forces.item() == 2
    assert paper.losses_by_count[0, 0] > 3.0 > paper.losses_by_count[0, 1]
    fixed = est.estimate(u, num_forces=3)
    assert fixed.num_forces.item() == 3 and fixed.forces.s.shape == (1, 3)
    assert torch.isnan(fixed.losses_by_count[0, :2]).all()
    assert fixed.loss.item() <= paper.losses_by_count[0, 1].item() + 1e-6  # three forces fit at least as well


def test_extra_starts_and_location_bias(gen):
    rod = tr.presets.nitinol290(calibrated=True)
    cases = [[(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)]]
    model = tr.PointForces.from_lists(cases, max_forces=3)
    u = tr.simulate(rod, model).grating_curvature
    est = Estimator(rod, EstimatorOptions(noise=0.0))
    result = est.estimate(u)
    # reported locations carry the bias
    assert torch.allclose(result.forces.s[0, :2], model.s[0, :2] + rod.location_bias, atol=1e-6)
    # a previous solution, passed back as a start in reported coordinates, gives the same answer
    again = est.estimate(u, extra_starts={2: tr.PointForces(result.forces.s[:, :2], result.forces.f[:, :2])})
    assert torch.allclose(again.forces.s, result.forces.s, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        est.estimate(
            u, extra_starts={2: tr.PointForces(torch.zeros(1, 3, dtype=F64), torch.zeros(1, 3, 2, dtype=F64))}
        )


def test_poorly_determined_flags(rod):
    # a force beyond the last grating (270 mm), and one seen by the first grating only (between 10 and 30 mm)
    _loads, u = readings(rod, [[(0.28, 0.2, 0.1)], [(0.02, 0.5, 0.5)], [(0.15, 0.5, 0.5)]])
    result = Estimator(rod, EstimatorOptions(noise=0.01, num_forces=1)).estimate(u)
    assert result.poorly_determined.tolist() == [True, True, False]


def test_input_checks_and_dtype(rod):
    est = Estimator(rod)
    with pytest.raises(ValueError, match="shape"):
        est.estimate(torch.zeros(2, 5, 2, dtype=F64))
    with pytest.raises(ValueError, match="no present grating"):
        est.estimate(torch.full((1, rod.num_gratings, 2), float("nan"), dtype=F64))
    with pytest.raises(TypeError):
        est.estimate(torch.zeros(1, rod.num_gratings, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="max_forces"):
        EstimatorOptions(max_forces=0)
    with pytest.raises(ValueError, match="scalar_readings"):
        EstimatorOptions(scalar_readings=-1)
    _, u = readings(rod, CLEAN_CASES[:1])
    res32 = est.estimate(u.float(), noise=0.01)
    assert res32.forces.s.dtype == torch.float32 and res32.std.dtype == torch.float32
    # both paths report in the input's dtype
    batched32 = est.estimate(u.float(), noise=0.01, scalar_readings=0)
    assert batched32.forces.s.dtype == torch.float32 and batched32.std.dtype == torch.float32
    assert torch.allclose(res32.forces.s, batched32.forces.s, atol=1e-6)
    records = res32.to_records(["a"])
    assert records[0]["id"] == "a" and records[0]["num_forces"] == 1
    assert set(records[0]["forces"][0]) == {"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"}


def test_warm_start_hook_supplies_starts(rod):
    """A warm start (model coordinates) is asked once per call, for every count, and its guesses are used."""
    cases = [[(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)]]
    truth = tr.PointForces.from_lists(cases)
    u = tr.simulate(rod, truth).grating_curvature
    calls = []

    def guess(curvature, mask):
        calls.append((tuple(curvature.shape), bool(mask.all())))
        return {2: truth, 7: truth}  # a count that is not fitted is ignored

    result = Estimator(rod, EstimatorOptions(noise=0.0, starts=1), warm_start=guess).estimate(u)
    assert calls == [((1, rod.num_gratings, 2), True)]
    assert result.num_forces.item() == 2
    assert torch.allclose(result.forces.s[0, :2], truth.s[0], atol=1e-6)
    with pytest.raises(TypeError, match="warm_start"):
        Estimator(rod, warm_start=42)
