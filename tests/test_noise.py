"""The noise a stream learns from its own fits (torchrod.estimate.noise) and how the stream uses it."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.estimate.noise import NoiseLearning, RunningNoise
from torchrod.io.stream import StreamOptions, stream


def _fits(rng: np.random.Generator, sigma: float, n: int) -> tuple[list[float], list[int]]:
    """Losses of n correct fits: sigma^2 chi2(dof), dof as for 14 gratings (some missing) and 0 to 3 forces."""
    dof = rng.choice([28, 26, 25, 22, 19, 16], size=n).tolist()
    return (sigma**2 * rng.chisquare(dof)).tolist(), dof


def test_running_noise_is_right_and_robust():
    rng = np.random.default_rng(0)
    est = RunningNoise(NoiseLearning(after=50, window=2000))
    loss, dof = _fits(rng, 0.2, 49)
    est.add(loss, dof)
    assert est.sigma is None  # not before `after` fits
    loss, dof = _fits(rng, 0.2, 1451)
    # A quarter of the fits are gross misfits (a force missed, a reading no force explains): the median ignores them.
    bad = [100.0 * x for x in rng.uniform(1.0, 50.0, size=500).tolist()]
    est.add(loss + bad, dof + [20] * len(bad))
    assert est.count == 2000  # the window keeps the latest 2000 (here all)
    assert est.sigma == pytest.approx(0.2, rel=0.12)
    clean = RunningNoise(NoiseLearning(after=50, window=2000))
    clean.add(*_fits(rng, 0.2, 1500))
    assert clean.sigma == pytest.approx(0.2, rel=0.03)


def test_running_noise_skips_unusable_fits_and_follows_a_drift():
    est = RunningNoise(NoiseLearning(after=2, window=100))
    est.add([1.0, math.nan, math.inf, 1.0, -1.0], [0, 10, 10, -3, 10])
    assert est.count == 0 and est.used == 0
    rng = np.random.default_rng(1)
    est.add(*_fits(rng, 0.1, 300))
    assert est.sigma == pytest.approx(0.1, rel=0.1)
    est.add(*_fits(rng, 0.3, 100))  # the window (100) now holds only the new sensor's fits
    assert est.sigma == pytest.approx(0.3, rel=0.1)
    assert est.used == 400
    with pytest.raises(ValueError, match="mismatch|zip|length|argument"):
        est.add([1.0, 2.0], [10])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"after": 0}, "after"),
        ({"window": 0}, "window"),
        ({"after": 10, "window": 5}, "window"),
        ({"growth": 0}, "growth"),
        ({"after": 2.5}, "after"),
    ],
)
def test_learning_options_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NoiseLearning(**kwargs)
    with pytest.raises(TypeError, match="learn_noise"):
        StreamOptions(learn_noise=32)


@pytest.mark.parametrize(("growth", "batches"), [(1, [20] * 20 + [30] * 30 + [10] * 20), (4, [30] * 60 + [5] * 10)])
def test_a_stream_without_noise_learns_it_and_answers_like_the_true_noise(growth, batches):
    """Readings of one and two forces at sigma 0.2, the estimator told no noise, all queued at once: the first batch
    holds only the ``after`` readings the noise is learned from (not a full batch) and estimates the noise per
    reading, every later batch uses the sigma learned from the fits before it, close to the true one, holds no more
    readings than ``growth`` times those fits, and counts as the estimator told the true sigma does."""
    rod = tr.presets.nitinol290()
    sigma, n = 0.2, 90
    g = torch.Generator().manual_seed(3)
    s = 0.08 + 0.2 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    f = 0.4 + 0.6 * torch.rand(n, 2, 2, generator=g, dtype=torch.float64)
    mask = torch.ones(n, 2, dtype=torch.bool)
    mask[::2, 1] = False  # every other reading has one force
    s[:, 1] = torch.where(mask[:, 1], s[:, 1], s[:, 0])
    loads = tr.PointForces(s, f, mask)
    u = tr.simulate(rod, loads).grating_curvature
    u = u + sigma * torch.randn(u.shape, generator=g, dtype=u.dtype)
    lines = [{"id": k, "curvature": u[k].tolist()} for k in range(n)]
    learning = NoiseLearning(after=20, growth=growth)
    options = StreamOptions(batch_size=30, max_latency=10.0, track=False, learn_noise=learning, workers=2)

    learned = list(stream(tr.Estimator(rod, tr.EstimatorOptions(max_forces=2)), lines, options))
    assert all("noise" not in r.record and r.batch == 20 for r in learned[:20])
    used = [r.record["noise"] for r in learned[20:]]
    assert len(used) == 70 and all(v == pytest.approx(sigma, rel=0.15) for v in used)
    # then batches no larger than growth x the fits learned from (20, then 40; or 80), up to the full 30, and what
    # is left at the end of the input in one part per solver thread
    assert [r.batch for r in learned[20:]] == batches
    known = list(stream(tr.Estimator(rod, tr.EstimatorOptions(max_forces=2, noise=sigma)), lines, options))
    assert all("noise" not in r.record for r in known)  # a noise given is never replaced
    same = sum(a.record["num_forces"] == b.record["num_forces"] for a, b in zip(learned[20:], known[20:], strict=True))
    assert same >= 68
    off = StreamOptions(batch_size=30, track=False, learn_noise=None)
    unknown = list(stream(tr.Estimator(rod, tr.EstimatorOptions(max_forces=2)), lines[:40], off))
    assert all("noise" not in r.record for r in unknown)


def test_cli_stream_learns_the_noise_unless_told(tmp_path, capsys):
    """``torchrod stream`` without ``--noise``: answers after the first 32 fits (the default ``after``: the first
    batch holds only those, though 40 could go) carry the learned sigma and the summary says from which reading it
    was used; ``--per-reading-noise`` and ``--noise`` learn nothing."""
    from torchrod.cli import main

    rod = tr.presets.nitinol290()
    n = 50
    g = torch.Generator().manual_seed(5)
    loads = tr.PointForces(
        0.1 + 0.15 * torch.rand(n, 1, generator=g, dtype=torch.float64),
        0.5 + 0.5 * torch.rand(n, 1, 2, generator=g, dtype=torch.float64),
    )
    u = tr.simulate(rod, loads).grating_curvature
    u = u + 0.1 * torch.randn(u.shape, generator=g, dtype=u.dtype)
    path = tmp_path / "in.jsonl"
    path.write_text("".join(json.dumps({"id": k, "curvature": u[k].tolist()}) + "\n" for k in range(n)))
    base = [
        "stream",
        "--rod",
        "nitinol290",
        "--checkpoint",
        "none",
        "--input",
        str(path),
        "--batch-size",
        "40",
        "--max-latency-ms",
        "10000",
    ]
    assert main([*base, "--summary"]) == 0
    cap = capsys.readouterr()
    records = [json.loads(line) for line in cap.out.splitlines()]
    assert len(records) == n and all("noise" not in r for r in records[:32])
    assert all(r["noise"] == pytest.approx(0.1, rel=0.2) for r in records[32:])
    assert "noise learned from the stream: sigma" in cap.err and "used from reading 33 on" in cap.err
    for extra in (["--per-reading-noise"], ["--noise", "0.1"]):
        assert main([*base, *extra, "--summary"]) == 0
        cap = capsys.readouterr()
        assert not any("noise" in json.loads(line) for line in cap.out.splitlines())
        assert "noise learned" not in cap.err


def test_fits_cut_by_the_time_budget_teach_nothing():
    """A fit the time budget cut is not a converged fit: its loss says nothing about the noise. With a budget of 0
    every reading of pure noise (0.1 1/m) times out with no force fitted; those losses would teach sigma ~0.1, so
    a stream that learned from them would answer with a ``"noise"`` field."""
    rod = tr.presets.nitinol290()
    gen = torch.Generator().manual_seed(3)
    u = 0.1 * torch.randn(60, rod.num_gratings, 2, dtype=torch.float64, generator=gen)
    est = tr.Estimator(rod, tr.EstimatorOptions(max_forces=1))
    readings = [{"id": k, "curvature": u[k]} for k in range(60)]
    out = list(stream(est, readings, StreamOptions(batch_size=8), dataclasses.replace(est.options, time_budget=0.0)))
    assert [r.record["status"] for r in out] == ["timeout"] * 60
    assert not any("noise" in r.record for r in out)


class _Jittery:
    """An estimator that waits a random time (0 to 20 ms, seeded) before each batch: the solver threads finish in
    another order than in a plain run."""

    def __init__(self, inner: tr.Estimator, seed: int) -> None:
        self.inner, self.rod, self.options = inner, inner.rod, inner.options
        self.rng = np.random.default_rng(seed)

    def estimate(self, *args, **kwargs):
        import time

        time.sleep(0.02 * float(self.rng.random()))
        return self.inner.estimate(*args, **kwargs)


def _learning_lines(n: int) -> list[dict]:
    """n readings of one force (sigma 0.1), ids 0..n-1."""
    rod = tr.presets.nitinol290()
    g = torch.Generator().manual_seed(5)
    s = 0.08 + 0.2 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    f = 0.3 + 0.5 * torch.rand(n, 1, 2, generator=g, dtype=torch.float64)
    u = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    u = u + 0.1 * torch.randn(u.shape, generator=g, dtype=u.dtype)
    return [{"id": k, "curvature": u[k].tolist()} for k in range(n)]


def test_a_backlogs_learned_noise_and_answers_do_not_depend_on_the_solver_threads_timing(monkeypatch):
    """A backlog read at once, the noise learned, two solver threads: the learning's rounds are shared among the
    threads (each round's parts with one noise, the next round after all of them), and every later batch takes the
    noise learned once all but the last three batches handed out were answered; what is left when the input ends
    goes out in parts fixed then. So the batches, the noise of each reading and its answer are the same however
    long each batch takes."""
    import torchrod.io.stream as streaming

    monkeypatch.setattr(streaming, "_LEARNING_PART", 4)  # (rounds of 8 readings or more split in two)
    rod = tr.presets.nitinol290()
    lines = _learning_lines(461)
    options = StreamOptions(batch_size=64, track=False, workers=2, learn_noise=NoiseLearning(after=8, growth=4))
    estimator = tr.Estimator(rod, tr.EstimatorOptions(max_forces=2))
    plain = list(stream(estimator, lines, options))
    # rounds of 8 (two parts of 4), then 32 (growth x 8 fits; two parts of 16), then full batches, then the 37
    # readings left at the end of the input in two parts
    assert [r.batch for r in plain] == [4] * 8 + [16] * 32 + [64] * 384 + [19] * 19 + [18] * 18
    noise = [r.record.get("noise") for r in plain]
    assert noise[:8] == [None] * 8 and len(set(noise[8:40])) == 1
    # batches 4-7 take the noise after the learning (4 batches answered); batches 8 and 9 that after 5 and 6
    assert len(set(noise[40:296])) == 1 and len({noise[40], noise[296], noise[360]}) == 3
    assert len(set(noise[296:360])) == 1 and len(set(noise[360:424])) == 1

    def answers(results):
        return [{k: v for k, v in r.record.items() if k != "latency_ms"} for r in results]

    for seed in (1, 2):
        jittery = list(stream(_Jittery(estimator, seed), lines, options))
        assert answers(jittery) == answers(plain)
