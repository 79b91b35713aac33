"""The estimator with a warm-start network: a network can only help; a weak one says so and adds starts only."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import warnings

import pytest
import torch

import torchrod as tr
from torchrod.data import path as shipped_file
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.learn.checkpoint import load_checkpoint
from torchrod.learn.warm_start import QUALITY_KEYS, TRUST_TOLERANCE, WarmStart, load_estimator, quality_verdict

CHECKPOINT = shipped_file("nitinol290.pt")


def _readings(rod, cases):
    loads = tr.PointForces.from_lists(cases)
    return tr.grating_curvature(rod, loads), loads


def test_the_shipped_checkpoint_records_its_quality_and_is_used_beside_the_scan():
    """The shipped network records its held-back quality, with the estimator's answers from its guesses alone and
    beside the scan; the verdict follows from those two. The estimator says once if it is weak and then uses its
    guesses beside the scan's starts; clean readings are recovered."""
    _, meta = load_checkpoint(CHECKPOINT)
    quality = meta["quality"]
    assert set(quality) >= set(QUALITY_KEYS)
    assert 0.5 < quality["count_accuracy"] < 1.0 and quality["readings"] >= 1000
    assert 0.5 < quality["search_count_accuracy"] < 1.0 and 0.5 < quality["trusted_count_accuracy"] < 1.0
    weak = quality_verdict(meta)
    falls = quality["trusted_count_accuracy"] < quality["search_count_accuracy"] - TRUST_TOLERANCE["count_accuracy"]
    rises = any(
        quality[f"trusted_{k}"] > quality[f"search_{k}"] * (1 + TRUST_TOLERANCE[k])
        for k in ("force_error_median", "location_error_median")
    )
    dearer = quality["trusted_evaluations"] >= quality["plain_evaluations"]
    worse = quality["trusted_worse_fits"] > TRUST_TOLERANCE["worse_fits"]
    assert bool(weak) == (falls or rises or dearer or worse)
    rod = tr.presets.nitinol290()
    messages = []
    est = load_estimator(CHECKPOINT, rod, warn=messages.append)
    assert isinstance(est.warm_start, WarmStart)
    assert est.options.starts > 0 and est.options.trust_guesses == (not weak)
    assert len(messages) == (1 if weak else 0)
    assert not weak or ("not trusted" in messages[0] and "--checkpoint none" in messages[0])
    kappa, loads = _readings(rod, [[(0.2, 0.3, -0.2)], [(0.1, -0.5, 0.4), (0.22, 0.2, 0.3)]])
    r = est.estimate(kappa, options=dataclasses.replace(est.options, noise=0.0))
    assert r.num_forces.tolist() == [1, 2]
    true = loads.sorted()
    for b, h in enumerate([1, 2]):
        assert torch.allclose(r.forces.s[b, :h], true.s[b, :h], atol=1e-4)
        assert torch.allclose(r.forces.f[b, :h], true.f[b, :h], rtol=1e-3, atol=1e-3)


def test_a_checkpoint_without_recorded_quality_is_weak(tmp_path):
    """An older checkpoint without a recorded quality is called weak, and says how to record one."""
    from torchrod.learn.checkpoint import save_checkpoint

    net, meta = load_checkpoint(CHECKPOINT)
    path = tmp_path / "old.pt"
    save_checkpoint(path, net, step=meta["step"], epoch=meta["epoch"])
    messages = []
    est = load_estimator(path, tr.presets.nitinol290(), warn=messages.append)
    assert not est.options.trust_guesses and est.warm_start is not None
    assert len(messages) == 1 and "torchrod train --evaluate" in messages[0]


TRUSTED_QUALITY = {  # a recorded quality that trusts the network: as accurate trusted, and cheaper than no network
    "search_count_accuracy": 0.80,
    "search_force_error_median": 0.04,
    "search_location_error_median": 0.001,
    "trusted_count_accuracy": 0.80,
    "trusted_force_error_median": 0.04,
    "trusted_location_error_median": 0.001,
    "search_evaluations": 30.0,
    "trusted_evaluations": 20.0,
    "plain_evaluations": 25.0,
    "trusted_worse_fits": 0.0,
}


def _with_quality(tmp_path, **quality):
    from torchrod.learn.checkpoint import save_checkpoint

    net, meta = load_checkpoint(CHECKPOINT)
    path = tmp_path / "net.pt"
    save_checkpoint(path, net, step=meta["step"], epoch=meta["epoch"], quality={**meta["quality"], **quality})
    return path


@pytest.mark.parametrize(
    ("change", "trusted"),
    [
        ({}, True),
        ({"trusted_count_accuracy": 0.80 - 0.004}, True),  # within half a point
        ({"trusted_count_accuracy": 0.80 - 0.006}, False),
        ({"trusted_force_error_median": 0.04 * 1.049}, True),
        ({"trusted_force_error_median": 0.04 * 1.051}, False),
        ({"trusted_location_error_median": 0.001 * 1.06}, False),
        ({"trusted_count_accuracy": float("nan")}, False),  # not recorded
        ({"trusted_evaluations": 25.0}, False),  # saves nothing against no network
        ({"trusted_evaluations": 24.9, "search_evaluations": 20.0}, True),
        ({"trusted_worse_fits": 0.004}, True),
        ({"trusted_worse_fits": 0.006}, False),  # wrong local minima the medians do not show
    ],
)
def test_a_network_is_trusted_when_its_guesses_alone_answer_as_well_as_the_search(tmp_path, change, trusted):
    """The verdict compares the estimator from the guesses alone with the estimator that also scans, on the same
    held-back readings (within :data:`TRUST_TOLERANCE`), not the network alone against a fixed bar; a trusted
    network's guesses start the fits alone."""
    alone = {"count_accuracy": 0.5}  # the network alone: not the test
    path = _with_quality(tmp_path, **{**TRUSTED_QUALITY, **alone, **change})
    messages = []
    est = load_estimator(path, tr.presets.nitinol290(), warn=messages.append)
    assert est.options.trust_guesses == trusted and est.warm_start is not None
    assert len(messages) == (0 if trusted else 1)
    if not trusted:
        assert "not trusted" in messages[0] and "torchrod train --evaluate" in messages[0]  # the next step
        assert ("records no" in messages[0]) == ("nan" in repr(change))


def test_a_checkpoint_that_records_only_the_network_alone_is_weak(tmp_path):
    """A checkpoint recorded before the estimator's comparison was part of the quality is weak, and says how to
    record it."""
    net, meta = load_checkpoint(CHECKPOINT)
    from torchrod.learn.checkpoint import save_checkpoint

    path = tmp_path / "older.pt"
    alone = {k: meta["quality"][k] for k in QUALITY_KEYS[:5]}
    save_checkpoint(path, net, step=meta["step"], epoch=meta["epoch"], quality=alone)
    messages = []
    est = load_estimator(path, tr.presets.nitinol290(), warn=messages.append)
    assert not est.options.trust_guesses
    assert len(messages) == 1 and "torchrod train --evaluate" in messages[0] and "trusted_count_accuracy" in messages[0]


def test_recording_the_quality_of_a_checkpoint(tmp_path):
    """``torchrod train --evaluate CHECKPOINT`` measures the held-back quality and writes it into the file, the
    weights unchanged."""
    from torchrod.cli import main

    path = tmp_path / "net.pt"
    shutil.copy(CHECKPOINT, path)
    before, _ = load_checkpoint(path)
    assert main(["train", "--evaluate", str(path), "--rod", "nitinol290", "--validation", "200"]) == 0
    after, meta = load_checkpoint(path)
    assert meta["quality"]["readings"] == 200.0 and set(meta["quality"]) >= set(QUALITY_KEYS)
    for a, b in zip(before.state_dict().values(), after.state_dict().values(), strict=False):
        assert torch.equal(a, b)


def test_a_longer_rod_with_the_same_relative_layout_uses_the_network_too():
    base = tr.presets.nitinol290()
    scale = 1.5
    rod = base.with_(length=base.length * scale, gratings=[g * scale for g in base.gratings], bending_stiffness=0.02)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the quality note
        est = load_estimator(CHECKPOINT, rod)
    assert est.warm_start is not None
    kappa, _ = _readings(rod, [[(0.3, 0.4, 0.1)]])
    r = est.estimate(kappa, options=dataclasses.replace(est.options, noise=0.0))
    assert int(r.num_forces[0]) == 1
    assert abs(float(r.forces.s[0, 0]) - 0.3) < 1e-4


def test_without_a_network_for_the_rod_it_says_so_once_and_what_to_do():
    rod = tr.presets.nitinol290().with_(gratings=[0.02 + 0.025 * k for k in range(11)])
    messages = []
    est = load_estimator(CHECKPOINT, rod, warn=messages.append)
    assert est.warm_start is None and est.options.starts > 0
    assert len(messages) == 1 and "no warm-start network for this rod" in messages[0]
    assert "torchrod train" in messages[0]  # how to get one
    kappa, _ = _readings(rod, [[(0.2, 0.3, 0.0)]])
    r = est.estimate(kappa, options=dataclasses.replace(est.options, noise=0.0))
    assert int(r.num_forces[0]) == 1 and abs(float(r.forces.s[0, 0]) - 0.2) < 1e-4
    with pytest.warns(UserWarning, match="no warm-start network"):
        load_estimator(CHECKPOINT, rod)


def test_an_under_trained_network_changes_the_count_accuracy_by_less_than_a_point(tmp_path):
    """A network trained for a handful of steps guesses badly; beside the scan's starts it cannot make the
    estimator worse: the count accuracy on 400 noisy readings moves by less than one point (4 readings). Its extra
    starts can only lower each count's best loss, so where it moves the count at all it is towards the truth."""
    from torchrod.learn.training import TrainConfig, train
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    rod = tr.presets.nitinol290()
    path = tmp_path / "weak.pt"
    config = TrainConfig(
        generate=512,
        validation=128,
        epochs=1,
        batch_size=256,
        hidden=16,
        depth=1,
        checkpoint=str(path),
        logdir=None,
        progress=False,
        physics_batch=0,
    )
    result = train(config)
    assert quality_verdict({"quality": result.quality})  # it is weak, and it knows it
    messages = []
    with_net = load_estimator(path, rod, EstimatorOptions(noise=0.1), warn=messages.append)
    assert len(messages) == 1 and "not trusted" in messages[0] and not with_net.options.trust_guesses
    lo = rod.gratings[1]
    sampler = LoadSampler(min_forces=1, max_forces=3, s_range=(lo, rod.length))
    data = generate(rod, 400, sampler=sampler, sensor=SensorModel(noise=0.1), seed=77)
    plain = Estimator(rod, EstimatorOptions(noise=0.1)).estimate(data.curvature)
    helped = with_net.estimate(data.curvature)
    truth = data.loads.count

    def acc(r):
        return float((r.num_forces == truth).double().mean())

    assert abs(acc(helped) - acc(plain)) < 0.01, (acc(helped), acc(plain))


def test_starts_zero_needs_another_start():
    rod = tr.presets.nitinol290()
    kappa, _ = _readings(rod, [[(0.2, 0.3, 0.0)]])
    with pytest.raises(ValueError, match="starts=0"):
        Estimator(rod, EstimatorOptions(starts=0)).estimate(kappa)
    # With an extra start for every count it runs without the scan.
    extra = {h: tr.PointForces.from_lists([[(0.05 + 0.08 * i, 0.1, 0.0) for i in range(h)]]) for h in (1, 2, 3)}
    r = Estimator(rod, EstimatorOptions(starts=0, noise=0.0)).estimate(kappa, extra_starts=extra)
    assert int(r.num_forces[0]) == 1 and abs(float(r.forces.s[0, 0]) - 0.2) < 1e-4


def test_bench_network_runs_and_prints_its_table(capsys):
    from torchrod.cli import main

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["bench", "network", "--quick", "--count", "6"]) == 0
    out = capsys.readouterr().out
    assert "within 1 sd" in out and "trust verdict: " in out
    for k in (1, 2, 3):
        for name in ("network", "estimator", "estimator+network", "trusted"):
            assert any(line.split()[:2] == [str(k), name] for line in out.splitlines()), (k, name)
        # The estimator alone agrees with itself: its count and every force within 1 sd, on every reading.
        (alone,) = [line.split() for line in out.splitlines() if line.split()[:2] == [str(k), "estimator"]]
        assert alone[-2:] == ["100.0%", "100.0%"], alone
        (torch_row,) = [line for line in out.splitlines() if line.startswith(f" {k} torch target")]
        assert re.search(r"\d+\.\d%\s+(\d+\.\d%|-)$", torch_row), torch_row


class _FixedGuess:
    """A warm start that returns the same guesses and count probabilities whatever the readings."""

    def __init__(self, probs, forces):
        self.probs, self.forces = probs, forces

    def guess(self, curvature, mask):
        from torchrod.learn.warm_start import WarmStartGuess

        return WarmStartGuess(self.probs, self.forces)


@pytest.mark.parametrize(
    ("trust", "noise"),
    [(False, 0.05), (True, 0.05), (False, None)],
)
def test_a_network_guess_starts_only_the_readings_that_find_its_count_likely(trust, noise):
    """With ``guess_probability`` p, a network guess of h forces is a start only for the readings whose count
    probabilities give h at least p: a batch answers as if each reading had been estimated alone with a network
    that gives no guess for its unlikely counts (same counts, statuses, fits and evaluations), trusted or not (a
    trusted network's skipped readings start from the scan), the noise given or not (then the best start's tie
    margin comes from each fit's own sigma, the same either way)."""
    rod = tr.presets.nitinol290()
    cases = [
        [(0.1, -0.5, 0.4), (0.22, 0.2, 0.3)],
        [(0.08, 0.3, 0.2), (0.2, -0.4, 0.1)],
        [(0.15, 0.6, -0.2)],
        [(0.06, 0.2, 0.5), (0.16, -0.3, 0.1), (0.26, 0.3, 0.2)],
    ]
    kappa, _ = _readings(rod, cases)
    kappa = kappa + 0.05 * torch.randn(kappa.shape, generator=torch.Generator().manual_seed(5), dtype=kappa.dtype)
    probs = torch.tensor(
        [[0.0, 1.0, 0.0], [0.5, 0.5, 0.0], [1 / 3, 1 / 3, 1 / 3], [0.005, 0.99, 0.005]], dtype=torch.float64
    )
    # Guesses off the truth (a network is not exact), the same for every reading.
    forces = {
        h: tr.PointForces.from_lists([[(0.04 + 0.09 * i, 0.1, -0.1) for i in range(h)]] * len(cases)) for h in (1, 2, 3)
    }
    opts = EstimatorOptions(noise=noise, trust_guesses=trust)
    batch = Estimator(rod, opts, warm_start=_FixedGuess(probs, forces)).estimate(kappa)
    for b in range(len(cases)):
        if trust:  # trusted: the most probable count (the first at a tie) and the one below, whatever p is
            top = int(probs[b].argmax()) + 1
            likely = [h for h in forces if h in (top, top - 1)]
        else:
            likely = [h for h in forces if probs[b, h - 1] >= 0.01]
        kept = {h: tr.PointForces(forces[h].s[b : b + 1], forces[h].f[b : b + 1]) for h in likely}
        one = torch.zeros(1, 3, dtype=torch.float64)
        one[0, max(likely) - 1] = 1.0  # the same counts chosen again for the reading alone
        alone = Estimator(rod, opts, warm_start=_FixedGuess(one if trust else torch.ones(1, 3), kept))
        answer = alone.estimate(kappa[b : b + 1])
        assert batch.statuses[b] == answer.statuses[0], b
        assert int(batch.num_forces[b]) == int(answer.num_forces[0]), b
        assert torch.allclose(batch.forces.s[b], answer.forces.s[0], atol=1e-7, equal_nan=True), b
        assert int(batch.evaluations[b]) == int(answer.evaluations[0]), b
    if not trust:  # every guess used (p = 0) is another search, with more evaluations
        every = Estimator(rod, dataclasses.replace(opts, guess_probability=0.0), warm_start=_FixedGuess(probs, forces))
        assert int(every.estimate(kappa).evaluations.sum()) > int(batch.evaluations.sum())


def test_trusted_guesses_fit_only_the_most_probable_count_and_the_one_below():
    """A trusted network amortises the search: its most probable count and the one below are fitted from its
    guesses alone, a count below those is not fitted at all (NaN loss), the count above is scanned for as the full
    search does; clean readings get the full search's count and forces, for fewer evaluations."""
    rod = tr.presets.nitinol290()
    cases = [
        [(0.1, -0.5, 0.4), (0.22, 0.2, 0.3), (0.27, 0.3, -0.2)],
        [(0.08, 0.3, 0.2), (0.16, -0.4, 0.1), (0.25, 0.4, 0.3)],
    ]
    kappa, loads = _readings(rod, cases)
    kappa = kappa + 0.02 * torch.randn(kappa.shape, generator=torch.Generator().manual_seed(3), dtype=kappa.dtype)
    probs = torch.tensor([[0.0, 0.0, 1.0]] * len(cases), dtype=torch.float64)
    # Guesses near the truth for 3 forces, and the 2 forces nearest the tip for 2.
    forces = {
        3: tr.PointForces(loads.s + 0.003, loads.f * 1.05),
        2: tr.PointForces(loads.s[:, 1:], loads.f[:, 1:]),
        1: tr.PointForces(loads.s[:, 2:], loads.f[:, 2:]),
    }
    opts = EstimatorOptions(noise=0.02)
    trusted = Estimator(rod, dataclasses.replace(opts, trust_guesses=True), warm_start=_FixedGuess(probs, forces))
    full = Estimator(rod, opts).estimate(kappa)
    got = trusted.estimate(kappa)
    assert got.losses_by_count[:, 1].isnan().all()  # count 1: below the one below the network's count
    assert not got.losses_by_count[:, 2:].isnan().any()
    assert torch.equal(got.num_forces, full.num_forces) and (got.num_forces == 3).all()
    # The same minimum within one standard deviation (a force on a grating sits in a flat valley of the loss).
    assert torch.allclose(got.loss, full.loss, rtol=1e-3)
    assert ((got.forces.s - full.forces.s).abs() <= full.std[..., 0]).all()
    assert ((got.forces.f - full.forces.f).abs() <= full.std[..., 1:]).all()
    assert (got.evaluations < full.evaluations).all()


def test_guess_probability_is_a_probability():
    for bad in (-0.1, 1.0, float("nan"), True):
        with pytest.raises(ValueError, match="guess_probability"):
            EstimatorOptions(guess_probability=bad)


def test_twins_answer_as_the_search_without_them_for_fewer_evaluations():
    """``SearchOptions.twins`` stops rows that another row of the same reading joins in the same intervals (the
    network's guess and the scan's start, the wider search's starts). On noisy readings of one to three forces
    with the shipped network, the estimates equal those of the search without twins: the same counts and
    statuses, the chosen losses within a hundredth of sigma^2 on all but a few readings and never worse by more
    than 2 sigma^2. It spends fewer evaluations."""
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    rod = tr.presets.nitinol290()
    sampler = LoadSampler(min_forces=1, max_forces=3, force_range=(0.05, 2.0), min_separation=0.025)
    data = generate(rod, 160, sampler=sampler, sensor=SensorModel(noise=0.1), seed=17)
    opts = EstimatorOptions(noise=0.1)
    est = load_estimator(CHECKPOINT, rod, opts, warn=lambda _: None)
    assert est.options.search.twins
    on = est.estimate(data.curvature, data.mask)
    untwinned = dataclasses.replace(est.options, search=dataclasses.replace(opts.search, twins=False))
    off = est.estimate(data.curvature, data.mask, options=untwinned)
    assert on.num_forces.tolist() == off.num_forces.tolist()
    assert on.statuses == off.statuses
    worse = (on.loss - off.loss) / 0.1**2
    assert int((worse.abs() > 0.01).sum()) <= 4 and float(worse.max()) < 2.0
    assert int(on.evaluations.sum()) < 0.95 * int(off.evaluations.sum())


@pytest.mark.parametrize("command", ["estimate", "stream"])
def test_the_commands_trust_a_network_as_from_checkpoint_does(tmp_path, monkeypatch, capsys, command):
    """``torchrod estimate`` and ``torchrod stream`` with ``--checkpoint`` trust the network exactly when
    ``load_estimator`` does (:func:`torchrod.learn.warm_start.is_trusted`)."""
    from torchrod.cli import main
    from torchrod.learn.warm_start import is_trusted

    trusted = _with_quality(tmp_path, **TRUSTED_QUALITY)
    rod = tr.presets.nitinol290()
    kappa, _ = _readings(rod, [[(0.2, 0.3, -0.2)]])
    readings = tmp_path / "in.jsonl"
    readings.write_text(json.dumps({"id": 0, "curvature": kappa[0].tolist()}) + "\n")
    seen = []
    real = Estimator.__init__

    def spy(self, rod, options=None, **kwargs):
        seen.append(options.trust_guesses)
        real(self, rod, options, **kwargs)

    monkeypatch.setattr(Estimator, "__init__", spy)
    for path in (trusted, CHECKPOINT):
        net = WarmStart.load(path, rod)
        seen.clear()
        args = ["--rod", "nitinol290", "--checkpoint", str(path), "--noise", "0.1"]
        if command == "estimate":
            assert main(["estimate", *args, str(readings)]) == 0
        else:
            assert main(["stream", *args, "--input", str(readings)]) == 0
        assert seen and set(seen) == {is_trusted(net)}
        assert '"num_forces": 1' in capsys.readouterr().out
        messages = []
        assert load_estimator(path, rod, warn=messages.append).options.trust_guesses == is_trusted(net)
    assert is_trusted(WarmStart.load(trusted, rod)) and not is_trusted(WarmStart.load(CHECKPOINT, rod))
    assert not is_trusted(None)


def test_from_checkpoint_on_a_missing_path_raises_naming_it(tmp_path):
    """A checkpoint the caller names that does not exist is an error, not a warning and a run without the network
    asked for."""
    missing = tmp_path / "checkpoints" / "nitinol290.pt"
    with pytest.raises(tr.MissingFileError, match="nitinol290.pt"):
        load_estimator(missing, tr.presets.nitinol290())
    with pytest.raises(FileNotFoundError):  # the standard type too
        load_estimator(str(missing), tr.presets.nitinol290())


def test_with_the_network_a_reading_answers_alike_alone_and_in_a_large_batch(rod):
    """With the shipped warm-start network, a reading's answer is the same bit for bit alone and in a batch of 36
    (larger than the network's blocks of readings): its guesses, made in float32, do not depend on the batch, so a
    file's answers do not depend on how it is split (one reading at a time while the kernels compile, then in
    batches)."""
    from torchrod.synthetic import LoadSampler, SensorModel, generate

    def drawn(k: int) -> torch.Tensor:
        sampler = LoadSampler(min_forces=k, max_forces=k, min_separation=0.025, s_range=(0.05, rod.length))
        return generate(rod, 12, sampler=sampler, sensor=SensorModel(noise=0.1), seed=40 + k).curvature

    u = torch.cat([drawn(k) for k in (1, 2, 3)])
    mask = torch.ones(u.shape[:2], dtype=torch.bool)
    mask[::5, 6] = False
    est = load_estimator(CHECKPOINT, rod, EstimatorOptions(noise=0.1), warn=lambda _: None)
    together = est.estimate(u, mask)
    assert int((together.num_forces >= 2).sum()) >= 12  # (the batch holds several counts)
    for b in range(u.shape[0]):
        alone = est.estimate(u[b : b + 1], mask[b : b + 1])
        for name in ("num_forces", "status", "p_value", "loss", "std", "iterations"):
            assert torch.equal(getattr(alone, name).nan_to_num(7.0), getattr(together, name)[b : b + 1].nan_to_num(7.0))
        assert torch.equal(alone.forces.s.nan_to_num(7.0), together.forces.s[b : b + 1].nan_to_num(7.0))
        assert torch.equal(alone.forces.f.nan_to_num(7.0), together.forces.f[b : b + 1].nan_to_num(7.0))
