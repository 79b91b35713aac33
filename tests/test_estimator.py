"""The Estimator end to end: recovery, zero contacts, verdicts, guarded numerics, targets, options."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch

import torchrod as tr
from torchrod.estimate.estimator import EstimateResult, Estimator, EstimatorOptions
from torchrod.estimate.status import STATUSES

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
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    sampler = LoadSampler(
        min_forces=k, max_forces=k, force_range=force, min_separation=separation, s_range=(s_min, rod.length)
    )
    return generate(rod, count, sampler=sampler, sensor=SensorModel(noise=noise), seed=seed)


def options(est: Estimator, **changes) -> EstimatorOptions:
    """The estimator's options with ``changes``: a call's own options."""
    return dataclasses.replace(est.options, **changes)


def force_errors(result: EstimateResult, loads: tr.PointForces, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Relative force errors and location errors [m] of the first k forces (both sorted by s)."""
    tf, ef = loads.f[:, :k], result.forces.f[:, :k]
    rel = torch.linalg.vector_norm(ef - tf, dim=-1) / torch.linalg.vector_norm(tf, dim=-1)
    return rel, (result.forces.s[:, :k] - loads.s[:, :k]).abs()


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


@pytest.mark.parametrize("target", ["cpu", "python"])
def test_batched_equals_one_at_a_time(rod, target):
    """A reading's result does not depend on the readings batched with it, nor on the threads a batch is spread
    over (each reading's search is its own)."""
    _loads, u = readings(rod, CLEAN_CASES[:6], noise=0.1, seed=5)
    est = Estimator(rod, EstimatorOptions(noise=0.1, target=target, threads=2))
    together = est.estimate(u)
    for b in range(u.shape[0]):
        alone = est.estimate(u[b : b + 1])
        assert alone.num_forces.item() == together.num_forces[b].item()
        assert torch.allclose(alone.forces.s, together.forces.s[b : b + 1], rtol=0, atol=1e-9)
        assert torch.allclose(alone.forces.f, together.forces.f[b : b + 1], rtol=0, atol=1e-9)
        assert torch.allclose(alone.loss, together.loss[b : b + 1], rtol=1e-9)
        assert alone.status.item() == together.status[b].item()


def test_the_torch_glue_of_other_devices_answers_as_the_numpy_glue_of_the_cpu(rod, monkeypatch):
    """Around the kernels, a CPU batch is laid out and checked on NumPy views, a GPU batch with torch operations on
    the device. Run on the CPU with the views turned off (every array a tensor, as on a GPU), the same readings,
    some gratings missing and a block of starts, give the same answers bit for bit."""
    from torchrod.estimate import checks
    from torchrod.estimate import estimator as module

    _loads, u = readings(rod, CLEAN_CASES[:5], noise=0.1, seed=3)
    mask = torch.ones(u.shape[:2], dtype=torch.bool)
    mask[1, 4] = mask[3, 0] = False
    starts = {2: tr.PointForces(torch.full((5, 2), 0.15, dtype=F64).cumsum(1), torch.zeros(5, 2, 2, dtype=F64))}
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    want = est.estimate(u, mask, extra_starts=starts)
    monkeypatch.setattr(module, "host_view", lambda x: x)
    monkeypatch.setattr(checks, "host_view", lambda x: x)
    monkeypatch.setattr(module, "_zeros", lambda device, *shapes: [torch.zeros(s, dtype=d) for s, d in shapes])
    got = est.estimate(u, mask, extra_starts=starts)
    for name in ("num_forces", "status", "p_value", "loss", "std", "losses_by_count", "evaluations"):
        assert torch.equal(getattr(got, name).nan_to_num(7.0), getattr(want, name).nan_to_num(7.0)), name
    assert torch.equal(got.forces.s, want.forces.s) and torch.equal(got.forces.f, want.forces.f)


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
    assert torch.allclose(result.noise, torch.full_like(result.noise, math.hypot(0.1, 1e-3)))


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
    paper = est.estimate(u, options=options(est, selection="threshold", threshold=3.0))
    assert paper.num_forces.item() == 2
    assert paper.losses_by_count[0, 1] > 3.0 > paper.losses_by_count[0, 2]  # column h: the loss of h forces
    fixed = est.estimate(u, options=options(est, num_forces=3))
    assert fixed.num_forces.item() == 3 and fixed.forces.s.shape == (1, 3)
    assert torch.isnan(fixed.losses_by_count[0, :3]).all() and torch.isfinite(fixed.losses_by_count[0, 3])
    assert fixed.loss.item() <= paper.losses_by_count[0, 2].item() + 1e-6  # three forces fit at least as well


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
        est.estimate(u, extra_starts={2: tr.PointForces(torch.zeros(1, 3, dtype=F64), torch.zeros(1, 3, 2, dtype=F64))})


def test_poorly_determined_flags(rod):
    """What the data cannot decide is flagged: a force seen by the first grating only (between 10 and 30 mm: its
    magnitude trades against its lever), a force whose gratings leave no residual to test one more force with
    (at 45 mm: 2 gratings, 4 residuals, 3 unknowns), two parallel forces 2 mm apart between two gratings (their
    split is not determined). A force beyond the last grating is seen by every grating: determined."""
    cases = [
        [(0.02, 0.5, 0.5)],
        [(0.045, 0.5, 0.5)],
        [(0.154, 0.4, 0.0), (0.156, 0.4, 0.0)],
        [(0.28, 0.2, 0.1)],
        [(0.15, 0.5, 0.5)],
    ]
    _loads, u = readings(rod, cases)
    est = Estimator(rod, EstimatorOptions(noise=0.01))
    result = est.estimate(u[:2], options=options(est, num_forces=1))
    assert result.statuses == ["poorly_determined", "poorly_determined"]
    pair = est.estimate(u[2:3], options=options(est, num_forces=2))
    assert pair.statuses == ["poorly_determined"]
    fine = est.estimate(u[3:], options=options(est, num_forces=1))
    assert fine.statuses == ["ok", "ok"] and not bool(fine.poorly_determined.any())


def test_a_rod_with_fewer_gratings_than_starts(rod):
    """A rod with one or two gratings (fewer intervals than the scan's three starts) is estimated, not crashed on.
    One force leaves 4 - 3 = 1 (two gratings) or no degree of freedom: fewer than a count needs to be tested, so the
    count chosen is none, and with the noise known the status says that it does not explain the reading
    (``misfit``). Asked for one force (``num_forces``), two gratings recover a clean force beyond them, flagged
    ``poorly_determined``."""
    s, f = torch.tensor([[0.28]], dtype=F64), torch.tensor([[[0.5, 0.2]]], dtype=F64)
    for G in (1, 2):
        few = dataclasses.replace(rod, gratings=rod.gratings[-G:])
        u = tr.simulate(few, tr.PointForces(s, f)).grating_curvature
        for noise in (0.1, None):
            for B in (1, 20):  # one reading per call and a batch spread over threads
                result = Estimator(few, EstimatorOptions(noise=noise)).estimate(u.expand(B, -1, -1).clone())
                assert result.num_forces.tolist() == [0] * B
                if noise is not None:
                    assert result.statuses == ["misfit"] * B
                fixed = Estimator(few, EstimatorOptions(noise=noise, num_forces=1)).estimate(
                    u.expand(B, -1, -1).clone()
                )
                assert fixed.statuses == ["poorly_determined"] * B
                assert fixed.num_forces.tolist() == [1] * B
                if G == 2:
                    assert (fixed.forces.s[:, 0] - 0.28).abs().max() < 1e-5
                    assert (fixed.forces.f[:, 0] - f[0, 0]).abs().max() < 1e-4


def test_input_checks_and_dtype(rod):
    est = Estimator(rod)
    with pytest.raises(ValueError, match="shape"):
        est.estimate(torch.zeros(2, 5, 2, dtype=F64))
    with pytest.raises(ValueError, match="no present grating"):
        est.estimate(torch.full((1, rod.num_gratings, 2), float("nan"), dtype=F64))
    with pytest.raises(TypeError):
        est.estimate(torch.zeros(1, rod.num_gratings, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="max_forces"):
        EstimatorOptions(max_forces=-1)
    with pytest.raises(ValueError, match="num_forces"):
        EstimatorOptions(num_forces=-1)
    with pytest.raises(ValueError, match="target"):
        EstimatorOptions(target="jax")
    with pytest.raises(TypeError, match="EstimatorOptions"):
        est.estimate(torch.zeros(1, rod.num_gratings, 2, dtype=F64), options={"noise": 0.1})
    with pytest.raises(ValueError, match="max_noise"):
        EstimatorOptions(max_noise=0.0)
    with pytest.raises(ValueError, match=r"noise = 0.0 with noise_floor = 0.0 leaves no noise"):
        EstimatorOptions(noise=0.0, noise_floor=0.0)  # (the kernels would divide by sigma^2 = 0)
    with pytest.raises(ValueError, match=r"max_noise = 1e-200 with noise_floor = 0.0"):
        EstimatorOptions(max_noise=1e-200, noise_floor=0.0)  # squares to zero
    assert EstimatorOptions(noise=0.0).noise2 > 0.0  # the default floor keeps sigma^2 positive
    _, u = readings(rod, CLEAN_CASES[:1])
    res32 = est.estimate(u.float(), options=options(est, noise=0.01))
    res64 = est.estimate(u, options=options(est, noise=0.01))
    # reported in the input's dtype (computed in float64)
    assert res32.forces.s.dtype == torch.float32 and res32.std.dtype == torch.float32
    assert res32.p_value.dtype == torch.float32 and res64.forces.s.dtype == F64
    assert torch.allclose(res32.forces.s.double(), res64.forces.s, atol=1e-6)
    records = res32.to_records(["a"])
    assert records[0]["id"] == "a" and records[0]["num_forces"] == 1 and records[0]["status"] == "ok"
    assert 0.0 <= records[0]["p_value"] <= 1.0
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

    # with starts=0 the warm start's guess is the only start: two forces fitted from it alone
    result = Estimator(rod, EstimatorOptions(noise=0.0, starts=0, num_forces=2), warm_start=guess).estimate(u)
    assert calls == [((1, rod.num_gratings, 2), True)]
    assert result.num_forces.item() == 2
    assert torch.allclose(result.forces.s[0, :2], truth.s[0], atol=1e-6)
    with pytest.raises(TypeError, match="warm_start"):
        Estimator(rod, warm_start=42)


# ---------------------------------------------------------------------------------------------- verdicts
@pytest.mark.parametrize("sigma", [0.1, 0.3])
def test_pure_noise_is_no_contact(rod, sigma):
    """Readings of sensor noise alone: count 0 with no forces in at least 95 % of them (measured: 99.5 %), status
    ok; the count is chosen among 0..3 by the same tests as any other count."""
    gen = torch.Generator().manual_seed(int(100 * sigma))
    u = sigma * torch.randn(100, rod.num_gratings, 2, dtype=F64, generator=gen)
    result = Estimator(rod, EstimatorOptions(noise=sigma)).estimate(u)
    assert int((result.num_forces == 0).sum()) >= 95
    none = result.num_forces == 0
    assert not bool(result.forces.active[none].any())
    assert all(r["forces"] == [] for r, n in zip(result.to_records(), none.tolist(), strict=False) if n)
    assert int((result.status[none] == STATUSES.index("ok")).sum()) >= 90


def test_zero_forces_can_be_asked_for(rod):
    _, u = readings(rod, CLEAN_CASES[:2], noise=0.1, seed=3)
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    zero = est.estimate(u, options=options(est, num_forces=0))
    assert zero.num_forces.tolist() == [0, 0] and zero.forces.s.shape == (2, 0)
    assert zero.statuses == ["misfit", "misfit"]  # a loaded rod is not explained by no force
    only = est.estimate(u, options=options(est, max_forces=0))
    assert only.num_forces.tolist() == [0, 0]


def test_readings_no_forces_explain_are_misfits(rod):
    """Alternating signs at successive gratings, and +-1e4 1/m, are produced by no set of 1 to 3 forces: never
    ok, with a p-value near zero, given the noise or not (then tested at ``max_noise``)."""
    G = rod.num_gratings
    alternating = torch.tensor([[(-1) ** k * 3.0, (-1) ** k] for k in range(G)], dtype=F64)
    huge = torch.tensor([[(-1) ** k * 1e4, 0.0] for k in range(G)], dtype=F64)
    u = torch.stack((alternating, huge))
    for noise in (0.1, None):
        result = Estimator(rod, EstimatorOptions(noise=noise)).estimate(u)
        assert result.statuses == ["misfit", "misfit"], noise
        assert bool((result.p_value < 1e-6).all())


@pytest.mark.parametrize("target", ["cpu", "python"])
def test_a_lone_spike_from_close_forces_is_not_a_misfit(rod, target):
    """A strange-looking reading that three close forces do produce exactly (a lone bump at one grating) is
    explained, not called a misfit: the verdict judges the fit, not the look of the reading. The reading is
    nearly symmetric, so the scan's best intervals for the third force tie to rounding, and one of them leads to a
    local minimum that leaves the two-force fit chosen, a misfit: the reading scaled by 1 + 1e-15 went there.
    Above an unexplained answer the count above is searched further, so every such rounding finds the forces."""
    q = rod.gratings[7]
    cases = [[(q - 0.008, 0.0, 1.0), (q + 0.002, 0.0, -2.0), (q + 0.011, 0.0, 1.0)]]
    _, u = readings(rod, cases)
    est = Estimator(rod, EstimatorOptions(noise=0.01, target=target))
    for scale in (1.0, 1.0 + 1e-15, 1.0 - 1e-15, 1.0 + 1e-13, 1.0 + 1e-12):
        result = est.estimate(u * scale)
        assert result.statuses[0] != "misfit" and result.num_forces.item() == 3, scale
        assert result.p_value.item() > 1e-3


def test_one_absurd_reading_does_not_take_the_batch_down(rod):
    """A value of 1e6 1/m (and NaN entries elsewhere) makes the linear algebra of that reading fail; it gets a
    verdict, the others are answered as if alone."""
    _, u = readings(rod, CLEAN_CASES[:3], noise=0.1, seed=7)
    bad = u.clone()
    bad[1, 4, 0] = 1e6
    est = Estimator(rod, EstimatorOptions(noise=0.1))
    result = est.estimate(bad)
    assert result.statuses[1] == "misfit"
    alone = est.estimate(u[[0, 2]])
    assert torch.allclose(result.forces.s[[0, 2]], alone.forces.s, atol=1e-9)
    assert result.statuses[0] == alone.statuses[0] and result.statuses[2] == alone.statuses[1]


def test_a_large_clean_force_is_one_force(rod):
    """A clean 7 N force at 150 mm bends the rod far beyond the envelope: one force, exact, status ok (no phantom
    second force from the fitting model's error: the reported fits use the exact model)."""
    _, u = readings(rod, [[(0.15, 7.0, 0.0)]])
    result = Estimator(rod, EstimatorOptions(noise=0.0)).estimate(u)
    assert result.num_forces.item() == 1 and result.statuses == ["ok"]
    assert abs(result.forces.s[0, 0].item() - 0.15) < 1e-6
    assert abs(result.forces.f[0, 0, 0].item() - 7.0) < 1e-5


def test_the_compiled_kernels_answer_as_their_source_run_as_python(rod):
    """One source, two ways of running it: compiled for the CPU (Numba) and interpreted as Python. On noisy 1-3
    force readings (near gratings, the base, the tip, gratings missing) both give every reading the same count,
    status and number of model evaluations, and the same forces to rounding: a compiled kernel, or a stale cache of
    one, cannot change an answer unseen."""
    from cases import stratified_readings

    u, mask = stratified_readings(rod, torch.Generator().manual_seed(9), 24)
    for noise in (0.1, None):
        a = Estimator(rod, EstimatorOptions(noise=noise, target="cpu")).estimate(u, mask)
        b = Estimator(rod, EstimatorOptions(noise=noise, target="python")).estimate(u, mask)
        assert a.num_forces.tolist() == b.num_forces.tolist() and a.statuses == b.statuses
        assert torch.equal(a.evaluations, b.evaluations)
        assert torch.allclose(a.forces.s.nan_to_num(), b.forces.s.nan_to_num(), atol=1e-9)
        assert torch.allclose(a.forces.f.nan_to_num(), b.forces.f.nan_to_num(), atol=1e-8)
        assert torch.allclose(a.loss, b.loss, rtol=1e-8)


def test_a_clean_reading_whose_right_fit_creeps_is_recovered(rod):
    """Three clean forces (from ``torchrod evaluate``'s clean three-force row) whose right fit converges slowly, far
    above the noise floor for many steps: a stopping rule that judges such a fit on its own residual scale stops it
    early and reports two forces merged near 90 mm as a `misfit`. It must be recovered exactly."""
    case = [
        (0.04989156076035581, 1.1159746633225904, 0.12941004123111263),
        (0.09522365899478971, -0.8320217180198041, 1.4559732391858717),
        (0.1342348624099265, -0.26115456682113114, -0.4788247448637113),
    ]
    loads, u = readings(rod, [case])
    res = Estimator(rod, EstimatorOptions(noise=0.0)).estimate(u)
    assert res.num_forces.tolist() == [3] and res.statuses[0] != "misfit"
    rel, ds = force_errors(res, loads, 3)
    assert float(rel.max()) < 1e-3 and float(ds.max()) < 1e-4


def test_trusted_guesses_in_a_wrong_place_do_not_keep_the_count_too_small(rod):
    """Trusted guesses replace the scan's best start; a guess that ends in a wrong local minimum of the count above
    the chosen one would make that count look unneeded. That fit is also started from the scan's best interval, as
    the full search starts it, so trusted guesses all bunched at the tip (a network gone wrong) leave the counts of
    80 noisy three-force readings within 3 of the full search's (without that, 61 of them came out with fewer
    forces)."""
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    B = 80
    sampler = LoadSampler(min_forces=3, max_forces=3, s_range=(rod.gratings[1], rod.length))
    data = generate(rod, B, sampler=sampler, sensor=SensorModel(noise=0.1), seed=5)
    bad = {
        h: tr.PointForces(
            torch.full((B, h), 0.28, dtype=torch.float64) - 0.004 * torch.arange(h),
            torch.zeros(B, h, 2, dtype=torch.float64),
        )
        for h in (1, 2, 3)
    }
    opts = EstimatorOptions(noise=0.1)
    full = Estimator(rod, opts).estimate(data.curvature)
    trusted = Estimator(rod, dataclasses.replace(opts, trust_guesses=True)).estimate(data.curvature, extra_starts=bad)
    truth = data.loads.count
    assert int((full.num_forces == truth).sum()) >= 0.8 * B  # the readings can be counted
    assert int((trusted.num_forces < full.num_forces).sum()) <= 3
    assert int((trusted.num_forces == truth).sum()) >= int((full.num_forces == truth).sum()) - 3


# A reading of the `bench stream` trajectory (seed 0, reading 621: one force of 0.21 N at 148 mm, noise 0.1 1/m),
# whose chosen fit, of two forces, creeps along a direction the data barely determine.
CREEPING = [
    [0.5789085643066753, -3.9758345823179506],
    [0.4491097914292039, -3.416327348326002],
    [0.29730370450632637, -2.9008576262301187],
    [0.45283684356506637, -2.0818725464230092],
    [0.12161792300759336, -1.6770057631413313],
    [-0.03866756867291596, -1.0956229554916632],
    [0.011315234590758491, -0.4009896956967772],
    [-0.017912546538729018, 0.124531965970848],
    [-0.02873398125255032, 0.3647610161911581],
    [0.08491167465927972, -0.09121709312567518],
    [0.058785059737430846, 0.03635447448565405],
    [-0.014051081486528255, -0.09390009005861777],
    [0.03931594056936082, -0.1344240939030433],
    [0.060815722976914836, 0.05001370865098801],
]


def test_a_chosen_fit_still_improving_after_its_steps_gets_more_of_them(rod):
    """After ``LMPolicy.iterations`` steps the chosen fit of this reading is still improving: it gets up to
    ``refine_iterations`` more from where it stands (it needs 72 of them), converges, and is answered for what it is
    (poorly determined). Without them it stays ``unconverged``, with the same count and a loss no lower."""
    from torchrod.estimate.options import LMPolicy

    u = torch.tensor([CREEPING], dtype=torch.float64)
    answers = {}
    for more in (LMPolicy().refine_iterations, 0):
        opts = EstimatorOptions(noise=0.1, lm=LMPolicy(refine_iterations=more))
        answers[more] = Estimator(rod, opts).estimate(u)
    refined, raw = answers[LMPolicy().refine_iterations], answers[0]
    assert refined.statuses == ["poorly_determined"] and bool(refined.converged[0])
    assert raw.statuses == ["unconverged"] and not bool(raw.converged[0])
    assert int(refined.num_forces[0]) == int(raw.num_forces[0]) == 2
    assert float(refined.loss[0]) <= float(raw.loss[0])
    with pytest.raises(ValueError, match="refine_iterations"):
        LMPolicy(refine_iterations=-1)


def test_a_record_writes_a_value_that_is_not_finite_as_null_and_keeps_the_others(rod):
    """JSON holds no NaN or infinity: a force's value that is not finite (here a standard deviation NaN, another
    infinite) becomes null in the record, alone; the other values of that force and of every other force stay."""
    result = Estimator(rod, EstimatorOptions(noise=0.1, num_forces=2)).estimate(
        tr.grating_curvature(rod, tr.PointForces.from_lists([[(0.1, 0.3, 0.2), (0.2, -0.2, 0.1)]]))
    )
    clean = result.to_records()[0]["forces"]
    result.std[0, 0, 1] = math.nan
    result.std[0, 1, 2] = math.inf
    forces = result.to_records()[0]["forces"]
    assert forces[0]["std_fx"] is None and forces[1]["std_fy"] is None
    assert {k: v for k, v in forces[0].items() if k != "std_fx"} == {k: v for k, v in clean[0].items() if k != "std_fx"}
    assert {k: v for k, v in forces[1].items() if k != "std_fy"} == {k: v for k, v in clean[1].items() if k != "std_fy"}
    assert all(v is not None for f in clean for v in f.values())


def test_a_status_is_a_string_enum_member_and_a_plain_string_in_records(rod):
    """``EstimateResult.statuses`` are :class:`torchrod.Status` members, equal to their strings; the records carry
    the plain strings, so that they serialise as JSON."""
    import json

    result = Estimator(rod, EstimatorOptions(noise=0.1)).estimate(torch.zeros(2, rod.num_gratings, 2))
    assert result.statuses == [tr.Status.OK, tr.Status.OK] and result.statuses[0] == "ok"
    assert isinstance(result.statuses[0], tr.Status) and str(result.statuses[0]) == "ok"
    record = result.to_records()[0]
    assert type(record["status"]) is str and json.loads(json.dumps(record))["status"] == "ok"
    assert [s.value for s in tr.Status] == list(STATUSES)


def _options_record_written_out(o: EstimatorOptions):
    """The kernels' options record of ``o``, every field written out by hand: the reference the record is held to."""
    import numpy as np

    from torchrod.kernels.layout import OPTIONS, record

    lm, sr = o.lm, o.search
    floor2 = float(o.noise_floor) ** 2
    return record(
        OPTIONS,
        max_forces=o.width + (1 if o.num_forces and sr.escape_turning < float("inf") else 0),
        fixed=-1 if o.num_forces is None else o.num_forces,
        min_dof=tr.rod.MIN_TEST_DOF,
        starts=o.starts,
        settle=o.settle,
        trusted=o.trust_guesses,
        twins=sr.twins,
        rule={"noise": 0, "threshold": 1}[o.selection],
        merge_patches=o.merge_patches,
        threshold=o.threshold,
        floor2=floor2,
        max_noise2=float(o.max_noise) ** 2 + floor2,
        hopeless=sr.hopeless,
        explained=sr.explained,
        escape_turning=sr.escape_turning,
        per_interval=sr.per_interval,
        exchange_top=sr.exchange_top,
        rounds=sr.rounds,
        explore=sr.explore,
        condition_limit=o.condition_limit,
        max_evaluations=o.max_evaluations,
        damping=lm.damping,
        increase=lm.increase,
        decrease=lm.decrease,
        min_damping=lm.min_damping,
        max_damping=lm.max_damping,
        max_force_step=lm.max_force_step,
        tolerance=lm.tolerance,
        iterations=lm.iterations,
        refine_iterations=lm.refine_iterations,
        exact_steps=lm.exact_steps,
        exact_tolerance=lm.exact_tolerance,
        acceleration=-np.inf if lm.acceleration is None else lm.acceleration,
        probe=lm.probe,
        acceleration_limit=lm.acceleration_limit,
    )


@pytest.mark.parametrize(
    "opts",
    [
        EstimatorOptions(),
        EstimatorOptions(noise=0.02, max_forces=2, noise_floor=0.0, max_evaluations=500, condition_limit=1e6),
        EstimatorOptions(
            num_forces=2,
            max_forces=4,
            selection="threshold",
            threshold=2.5,
            max_noise=0.3,
            noise_floor=2e-3,
            starts=5,
            settle=False,
            trust_guesses=True,
            merge_patches=False,
            lm=tr.LMPolicy(
                damping=1e-2,
                increase=5.0,
                decrease=2.5,
                min_damping=1e-8,
                max_damping=1e8,
                max_force_step=4.0,
                tolerance=1e-4,
                iterations=17,
                refine_iterations=0,
                exact_steps=2,
                exact_tolerance=1e-5,
                acceleration=None,
                probe=0.2,
                acceleration_limit=0.5,
            ),
            search=tr.SearchOptions(
                per_interval=3,
                exchange_top=4,
                rounds=1,
                explore=5,
                suspect=0.9,
                kink_suspect=0.4,
                hopeless=2.0,
                explained=0.02,
                twins=False,
                escape_turning=1.0,
            ),
        ),
        EstimatorOptions(max_forces=0, lm=tr.LMPolicy(acceleration=0.25)),
        EstimatorOptions(num_forces=1, search=tr.SearchOptions(escape_turning=float("inf"))),
    ],
    ids=["default", "known-noise", "fixed-threshold-policies", "no-forces", "fixed-no-escape"],
)
def test_the_options_record_holds_each_option_as_written_out_by_hand(opts):
    """The kernels' options record, made from the options by name, is byte for byte the one every field of it written
    out by hand gives."""
    assert opts.record().tobytes() == _options_record_written_out(opts).tobytes()


def test_every_options_record_field_is_filled_once_and_every_option_of_its_name_is_passed():
    """Each field of the kernels' options record is made by one conversion or is one option of its name (none twice,
    none by nobody, no conversion for a field that is not there), and each option of an OPTIONS field's name that no
    conversion makes reaches the record as it is."""
    from torchrod.estimate.options import KERNEL_CONVERSIONS
    from torchrod.kernels.layout import OPTIONS

    names = set(OPTIONS.names)
    parts = {"": EstimatorOptions, "lm": tr.LMPolicy, "search": tr.SearchOptions}
    by_name = [
        (part, f.name)
        for part, cls in parts.items()
        for f in dataclasses.fields(cls)
        if f.name in names and f.name not in KERNEL_CONVERSIONS
    ]
    filled = list(KERNEL_CONVERSIONS) + [name for _, name in by_name]
    assert sorted(filled) == sorted(names)
    base = EstimatorOptions()
    for part, name in by_name:
        old = getattr(getattr(base, part) if part else base, name)
        new = (not old) if isinstance(old, bool) else old + 1 if isinstance(old, int) else old * 1.5
        if part:
            changed = dataclasses.replace(base, **{part: dataclasses.replace(getattr(base, part), **{name: new})})
        else:
            changed = dataclasses.replace(base, **{name: new})
        assert changed.record()[0][name] == new, name
    # two dataclasses of the options that name one field of the record are an error, not a silent choice
    clash = dataclasses.make_dataclass("Clash", [("damping", float, 1.0)], bases=(tr.SearchOptions,), frozen=True)
    with pytest.raises(tr.OptionsError, match="'damping' is named by both LMPolicy and Clash"):
        EstimatorOptions(search=clash()).record()


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), True, "1.5"])
def test_an_escape_bound_that_is_not_a_positive_angle_is_refused(value):
    with pytest.raises(
        tr.OptionsError, match=f"escape_turning must be a positive angle .* got {re.escape(repr(value))}"
    ):
        tr.SearchOptions(escape_turning=value)
    assert tr.SearchOptions(escape_turning=float("inf")).escape_turning == float("inf")
