"""Synthetic sets and streams: distribution limits, forward-model consistency, sensor statistics, the file format,
the Dataset, the CLI, and smooth, physical streams."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod import synthetic as sy
from torchrod.cli import main
from torchrod.data import path as shipped_file
from torchrod.synthetic.loadsets import _digest, _profile


@pytest.fixture(scope="module")
def small_set() -> sy.SyntheticSet:
    rod = tr.presets.nitinol290()
    return sy.generate(rod, 600, sensor=sy.SensorModel(noise=0.2), seed=11)


def _grating_curvature(rod: tr.Rod, loads: tr.PointForces) -> torch.Tensor:
    """The library's checked forward model, with a tight step bound (reference accuracy ~1e-9)."""
    return tr.simulate(rod, loads, max_step_angle=0.02).grating_curvature


# ------------------------------------------------------------------------------------------------ options
@pytest.mark.parametrize(
    "kwargs",
    [
        {"min_forces": 0},
        {"min_forces": 3, "max_forces": 2},
        {"force_range": (2.0, 1.0)},
        {"force_range": (-1.0, 1.0)},
        {"min_separation": -0.01},
        {"s_range": (0.1, 0.12)},  # too short for 3 forces 25 mm apart
        {"max_bending": 0.0},
    ],
)
def test_sampler_rejects_bad_options(kwargs):
    with pytest.raises(ValueError):
        sy.LoadSampler(**kwargs)


@pytest.mark.parametrize("kwargs", [{"noise": -0.1}, {"missing_prob": 1.0}, {"offset_std": math.nan}])
def test_sensor_rejects_bad_options(kwargs):
    with pytest.raises(ValueError):
        sy.SensorModel(**kwargs)


def test_s_range_beyond_the_rod_is_an_error(rod):
    with pytest.raises(ValueError, match="beyond"):
        sy.sample_loads(rod, 4, sy.LoadSampler(s_range=(0.1, 0.5)), torch.Generator().manual_seed(0))


# ------------------------------------------------------------------------------------------------ sampling
def test_sample_loads_respects_the_sampler(rod, gen):
    sampler = sy.LoadSampler(min_forces=1, max_forces=3, force_range=(0.2, 1.5), min_separation=0.03)
    loads = sy.sample_loads(rod, 900, sampler, gen)
    assert loads.s.shape == (900, 3) and loads.f.shape == (900, 3, 2) and loads.s.dtype == torch.float64
    active, count = loads.active, loads.count
    # padding last, zeroed; counts uniform in [1, 3] (kept uniform: a rejected case is redrawn with its count)
    assert torch.equal(active, torch.arange(3) < count.unsqueeze(1))
    assert (loads.s[~active] == 0).all() and (loads.f[~active] == 0).all()
    freq = torch.bincount(count, minlength=4)[1:].double() / 900
    assert torch.allclose(freq, torch.full((3,), 1 / 3, dtype=torch.float64), atol=0.05)
    lo, hi = sampler.location_range(rod)
    assert lo == pytest.approx(0.02 * rod.length) and hi == rod.length
    assert (loads.s[active] >= lo).all() and (loads.s[active] <= hi).all()
    mag = loads.magnitude()[active]
    assert (mag >= 0.2 - 1e-12).all() and (mag <= 1.5 + 1e-12).all()
    gaps = (loads.s[:, 1:] - loads.s[:, :-1])[active[:, 1:]]
    assert (gaps >= 0.03 - 1e-12).all()
    # the bending limit, checked with an independent, finer quadrature of the checked forward model
    turning = sy.total_turning(rod, loads, samples=1025)
    assert turning.max() <= sampler.max_bending + 1e-3
    # and the limit binds: the admitted cases reach it
    assert turning.max() > 0.95 * sampler.max_bending


def test_directions_are_uniform(rod, gen):
    loads = sy.sample_loads(rod, 1000, sy.LoadSampler(), gen)
    angle = torch.atan2(loads.f[..., 1], loads.f[..., 0])[loads.active]
    # the mean resultant length of uniform angles is ~ 1/sqrt(n)
    assert torch.stack((angle.cos().mean(), angle.sin().mean())).norm() < 4 / math.sqrt(angle.numel())


def test_bending_limit_has_an_effect(rod):
    loose = sy.LoadSampler(max_bending=math.inf)
    tight = sy.LoadSampler(max_bending=0.3)
    a = sy.sample_loads(rod, 100, loose, torch.Generator().manual_seed(1))
    b = sy.sample_loads(rod, 100, tight, torch.Generator().manual_seed(1))
    assert sy.total_turning(rod, a).max() > 2.0
    assert sy.total_turning(rod, b, samples=1025).max() <= 0.3 + 1e-3


def test_cases_the_forward_model_does_not_resolve_are_redrawn(rod, monkeypatch):
    # Without a bending limit, forces of hundreds of newtons make the fixed steps (one per L/128) longer than the
    # step rule allows (the readings drift off, and far beyond they are NaN): such cases are redrawn, and the
    # simulator's flagged cases (here: 1e6 N with 256 steps allowed) are refused by total_turning.
    import functools

    from torchrod.model import body_frame

    sampler = sy.LoadSampler(max_forces=1, force_range=(1.0, 1000.0), max_bending=math.inf)
    loads = sy.sample_loads(rod, 64, sampler, torch.Generator().manual_seed(3))
    clean = _profile(rod, loads)[0]
    sim = tr.simulate(rod, loads)
    assert bool(getattr(sim, "accurate", torch.ones(1, dtype=torch.bool)).all())
    err = (clean - sim.grating_curvature).abs().amax(dim=(1, 2)) / sim.grating_curvature.abs().amax(dim=(1, 2))
    assert err.max() < 1e-5, float(err.max())
    assert loads.f.norm(dim=-1).max() > 100.0  # large forces stay where the model resolves them
    monkeypatch.setattr(body_frame, "simulate", functools.partial(body_frame.simulate, max_steps=256))
    with pytest.raises(ValueError, match="the first case 0 with a force of 1e\\+06 N"):
        sy.total_turning(rod, tr.PointForces.from_lists([[(0.29, 0.0, 1e6)]]))


def test_turning_angle_small_deflection(rod):
    # one small force: |u(s)| = f (s1 - s) / EI, so the turning is f s1^2 / (2 EI)
    f, s1 = 1e-3, 0.2
    loads = tr.PointForces.from_lists([[(s1, 0.0, f)]])
    expected = f * s1**2 / (2 * rod.bending_stiffness)
    assert float(sy.total_turning(rod, loads, samples=1001)) == pytest.approx(expected, rel=1e-4)


def test_sample_loads_reproducible(rod):
    a = sy.sample_loads(rod, 200, sy.LoadSampler(), torch.Generator().manual_seed(5))
    b = sy.sample_loads(rod, 200, sy.LoadSampler(), torch.Generator().manual_seed(5))
    c = sy.sample_loads(rod, 200, sy.LoadSampler(), torch.Generator().manual_seed(6))
    assert torch.equal(a.s, b.s) and torch.equal(a.f, b.f) and torch.equal(a.active, b.active)
    assert not torch.equal(a.s, c.s)


# ------------------------------------------------------------------------------------------------ generate
def test_clean_readings_are_the_forward_model(small_set):
    d = small_set
    assert d.clean.shape == (600, 14, 2) and d.curvature.shape == (600, 14, 2) and d.mask.shape == (600, 14)
    ref = _grating_curvature(d.rod, d.loads)
    assert torch.allclose(d.clean, ref, rtol=0, atol=1e-7)
    assert d.clean.abs().max() > 5.0  # not a trivially small set


def test_noise_statistics(small_set):
    d = small_set
    residual = d.curvature - d.clean
    n = residual.numel()
    # std of a Gaussian estimated from n samples has relative standard error 1/sqrt(2n)
    assert float(residual.std()) == pytest.approx(0.2, rel=4 / math.sqrt(2 * n))
    assert abs(float(residual.mean())) < 4 * 0.2 / math.sqrt(n)
    # independent across gratings and components
    flat = residual.reshape(600, -1)
    corr = torch.corrcoef(flat.T) - torch.eye(flat.shape[1], dtype=flat.dtype)
    assert corr.abs().max() < 0.2
    assert d.mask.all() and torch.equal(d.offsets, torch.zeros(14, 2, dtype=torch.float64))


def test_offsets_and_missing_gratings(rod):
    sensor = sy.SensorModel(noise=0.0, offset_std=0.5, missing_prob=0.3)
    d = sy.generate(rod, 400, sensor=sensor, seed=2)
    present = d.mask
    assert float((~present).double().mean()) == pytest.approx(0.3, abs=0.03)
    assert (d.curvature[~present] == 0).all()
    # one constant offset per grating and component, the same in every reading
    diff = torch.where(present.unsqueeze(-1), d.curvature - d.clean, torch.nan)
    assert torch.allclose(diff.nanmean(dim=0), d.offsets, atol=1e-12)
    assert float(d.offsets.std()) == pytest.approx(0.5, rel=0.5)


def test_same_seed_same_set_whatever_the_batch_size(rod):
    sensor = sy.SensorModel(noise=0.1, missing_prob=0.1, offset_std=0.05)
    a = sy.generate(rod, 600, sensor=sensor, seed=4, batch_size=256)
    b = sy.generate(rod, 600, sensor=sensor, seed=4, batch_size=100_000)
    c = sy.generate(rod, 20, sensor=sensor, seed=5)
    for x, y in ((a.loads.s, b.loads.s), (a.loads.f, b.loads.f), (a.mask, b.mask), (a.offsets, b.offsets)):
        assert torch.equal(x, y)
    assert torch.allclose(a.clean, b.clean, rtol=1e-12, atol=1e-12)
    assert torch.allclose(a.curvature, b.curvature, rtol=1e-12, atol=1e-12)
    assert a.candidates == b.candidates
    assert not torch.equal(a.loads.s[:20], c.loads.s)


def test_loads_do_not_depend_on_the_sensor_model(rod):
    a = sy.generate(rod, 300, sensor=sy.SensorModel(noise=0.0), seed=9)
    b = sy.generate(rod, 300, sensor=sy.SensorModel(noise=0.3, missing_prob=0.2), seed=9)
    assert torch.equal(a.loads.s, b.loads.s) and torch.equal(a.loads.f, b.loads.f)
    assert torch.equal(a.clean, b.clean) and torch.equal(a.curvature, a.clean)


def test_location_bias_moves_the_forces_seen(rod):
    bias = -0.004
    d = sy.generate(rod, 200, sensor=sy.SensorModel(noise=0.0, location_bias=bias), seed=3)
    # Same meaning as Rod.location_bias: reported = model + bias, so the model sees the forces at s - bias.
    moved = tr.PointForces(
        torch.where(d.loads.active, d.loads.s - bias, d.loads.s).clamp(0, rod.length), d.loads.f, d.loads.mask
    )
    assert torch.allclose(d.clean, _grating_curvature(rod, moved), atol=1e-7)
    assert not torch.allclose(d.clean, _grating_curvature(rod, d.loads), atol=1e-3)


def test_rejection_rate_is_reported(small_set):
    rate = small_set.rejection_rate
    assert rate is not None and 0.3 < rate < 0.95  # the default envelope bends the rod far beyond 90 degrees


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_generate_on_cuda_matches_cpu(rod):
    a = sy.generate(rod, 300, seed=6)
    b = sy.generate(rod, 300, seed=6, device="cuda")
    assert b.clean.device.type == "cpu"
    assert torch.equal(a.loads.s, b.loads.s) and torch.equal(a.mask, b.mask)
    assert torch.allclose(a.clean, b.clean, atol=1e-10)


def test_zero_cases(rod):
    d = sy.generate(rod, 0)
    assert len(d) == 0 and d.clean.shape == (0, 14, 2)


# ------------------------------------------------------------------------------------------------ file format
def test_save_load_round_trip(tmp_path, rod):
    d = sy.generate(rod, 50, sensor=sy.SensorModel(noise=0.1, offset_std=0.2, missing_prob=0.1), seed=8)
    path = tmp_path / "set.data"  # any name: kept as given
    d.save(path)
    assert path.exists() and not (tmp_path / "set.data.npz").exists()
    e = sy.SyntheticSet.load(path, rod=rod)
    assert e.rod == rod and e.sampler == d.sampler and e.sensor == d.sensor and e.seed == 8
    assert e.candidates == d.candidates
    for name in ("clean", "curvature", "mask", "offsets"):
        assert torch.equal(getattr(d, name), getattr(e, name))
    assert torch.equal(d.loads.s, e.loads.s) and torch.equal(d.loads.f, e.loads.f)
    assert torch.equal(d.loads.active, e.loads.active)
    # a rod that differs only in its calibration (location bias) reads the same physics: accepted
    sy.SyntheticSet.load(path, rod=tr.presets.nitinol290(calibrated=True))
    with np.load(path, allow_pickle=False) as npz:
        meta = json.loads(str(npz["meta"]))
        assert npz["count"].dtype == np.int64 and npz["mask"].dtype == np.bool_ and npz["s"].dtype == np.float64
    assert meta["format"] == "torchrod-dataset" and meta["format_version"] == 1 and meta["count"] == 50
    assert meta["torchrod_version"] == tr.__version__ and len(meta["sha256"]) == 64


@pytest.fixture
def saved(tmp_path, rod):
    path = tmp_path / "set.npz"
    sy.generate(rod, 40, seed=1).save(path)
    return path


def _rewrite(src, dst, change):
    """Copy a set with its arrays and meta changed by ``change(arrays, meta)``, as a valid zip."""
    with np.load(src, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "meta"}
        meta = json.loads(str(npz["meta"]))
    change(arrays, meta)
    with open(dst, "wb") as fh:
        np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)


def test_load_rejects_another_rod(saved, rod):
    with pytest.raises(ValueError, match="different rod.*bending_stiffness"):
        sy.SyntheticSet.load(saved, rod=rod.with_(bending_stiffness=2 * rod.bending_stiffness))
    with pytest.raises(ValueError, match="different rod.*gratings"):
        sy.SyntheticSet.load(saved, rod=rod.with_(gratings=rod.gratings[:-1]))


def test_load_rejects_truncated_and_flipped_files(saved, tmp_path):
    raw = saved.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match="corrupt or unreadable"):
        sy.SyntheticSet.load(cut)
    for where in (0.3, 0.5, 0.7):
        flipped = bytearray(raw)
        i = int(where * len(raw))
        flipped[i : i + 8] = bytes(b ^ 0xFF for b in flipped[i : i + 8])
        bad = tmp_path / "flipped.npz"
        bad.write_bytes(bytes(flipped))
        with pytest.raises(ValueError, match="corrupt"):
            sy.SyntheticSet.load(bad)
    text = tmp_path / "text.npz"
    text.write_text("not a data set\n")
    with pytest.raises(ValueError, match="corrupt or unreadable"):
        sy.SyntheticSet.load(text)


def test_load_rejects_altered_arrays(saved, tmp_path):
    bad = tmp_path / "bad.npz"

    def nudge(arrays, meta):
        arrays["curvature"] = arrays["curvature"].copy()
        arrays["curvature"][3, 4, 1] += 1e-9

    _rewrite(saved, bad, nudge)
    with pytest.raises(ValueError, match="sha256"):
        sy.SyntheticSet.load(bad)

    def drop(arrays, meta):
        del arrays["clean"]

    _rewrite(saved, bad, drop)
    with pytest.raises(ValueError, match="missing arrays \\['clean'\\]"):
        sy.SyntheticSet.load(bad)


def test_load_rejects_inconsistent_shapes(saved, tmp_path):
    bad = tmp_path / "bad.npz"

    def shorten(arrays, meta):  # a consistent hash over inconsistent arrays
        arrays["clean"] = arrays["clean"][:-1]
        meta["sha256"] = _digest(arrays)

    _rewrite(saved, bad, shorten)
    with pytest.raises(ValueError, match="inconsistent.*'clean'"):
        sy.SyntheticSet.load(bad)

    def miscount(arrays, meta):
        arrays["count"] = arrays["count"] + 1
        meta["sha256"] = _digest(arrays)

    _rewrite(saved, bad, miscount)
    with pytest.raises(ValueError, match="'count' disagrees"):
        sy.SyntheticSet.load(bad)


def test_load_rejects_wrong_format_and_newer_versions(saved, tmp_path):
    bad = tmp_path / "bad.npz"
    _rewrite(saved, bad, lambda a, m: m.update(format="something-else"))
    with pytest.raises(ValueError, match="not a torchrod data set"):
        sy.SyntheticSet.load(bad)
    _rewrite(saved, bad, lambda a, m: m.update(format_version=2))
    with pytest.raises(ValueError, match="newer torchrod"):
        sy.SyntheticSet.load(bad)
    plain = tmp_path / "plain.npz"
    np.savez(plain, x=np.zeros(3))
    with pytest.raises(ValueError, match="not a torchrod data set"):
        sy.SyntheticSet.load(plain)
    with pytest.raises(FileNotFoundError):
        sy.SyntheticSet.load(tmp_path / "nowhere.npz")


# ------------------------------------------------------------------------------------------------ dataset
def test_dataset_items(small_set):
    ds = small_set.to_dataset()
    assert len(ds) == 600
    item = ds[7]
    shapes = {k: (tuple(v.shape), v.dtype) for k, v in item.items()}
    assert shapes == {
        "curvature": ((14, 2), torch.float64),
        "mask": ((14,), torch.bool),
        "s": ((3,), torch.float64),
        "f": ((3, 2), torch.float64),
        "force_mask": ((3,), torch.bool),
        "count": ((), torch.int64),
    }
    assert int(item["count"]) == int(item["force_mask"].sum())
    assert torch.equal(item["curvature"], small_set.curvature[7])
    batch = next(iter(torch.utils.data.DataLoader(small_set.to_dataset(torch.float32), batch_size=16)))
    assert batch["curvature"].shape == (16, 14, 2) and batch["curvature"].dtype == torch.float32
    assert batch["count"].shape == (16,)


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_generates_the_set_of_the_api(tmp_path, rod, capsys):
    out = tmp_path / "cli.npz"
    argv = [
        "generate",
        "--rod",
        "nitinol290",
        "--count",
        "60",
        "--out",
        str(out),
        "--seed",
        "7",
        "--noise",
        "0.3",
        "--max-forces",
        "2",
        "--force-max",
        "1.0",
        "--missing-prob",
        "0.05",
        "--max-bending-deg",
        "60",
    ]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "60 cases" in err and "samples/s" in err and "rejection rate" in err
    d = sy.SyntheticSet.load(out, rod=rod)
    sampler = sy.LoadSampler(max_forces=2, force_range=(0.05, 1.0), max_bending=math.radians(60))
    ref = sy.generate(rod, 60, sampler=sampler, sensor=sy.SensorModel(noise=0.3, missing_prob=0.05), seed=7)
    assert d.sampler == sampler
    assert torch.equal(d.loads.s, ref.loads.s) and torch.equal(d.curvature, ref.curvature)


def test_cli_reads_rod_files_and_reports_errors(tmp_path, capsys):
    out = tmp_path / "cli.npz"
    rod_file = str(shipped_file("nitinol290.json"))
    assert main(["generate", "--rod", rod_file, "--count", "5", "--out", str(out)]) == 0
    assert main(["generate", "--rod", "no-such-rod", "--count", "5", "--out", str(out)]) == 2
    assert "neither a rod file nor a preset" in capsys.readouterr().err
    assert main(["generate", "--rod", "nitinol290", "--count", "5", "--out", str(out), "--noise", "-1"]) == 2


# ------------------------------------------------------------------------------------------------ streams
@pytest.fixture(scope="module")
def stream():
    rod = tr.presets.nitinol290()
    return rod, sy.generate_trajectory(rod, 1200, rate=100.0, sensor=sy.SensorModel(noise=0.0), seed=21)


def test_stream_is_smooth_between_events(stream):
    _rod, traj = stream
    model, rate = sy.ContactModel(), 100.0
    f_hi = sy.LoadSampler().force_range[1]
    # Rates of change allowed by the contact model [N/s]: the smoothstep ramp (slope 1.5 / ramp time) of a peak
    # with wobble, the wobble itself, the rotation, and the moving average of the bending factor (window 2w+1).
    w = round(model.smoothing * rate)
    df_bound = (
        1.5 / model.ramp[0] * f_hi * (1 + model.wobble)
        + f_hi * model.wobble * 2 * math.pi / 1.0
        + f_hi * model.rotation_speed
    ) / rate + f_hi / (2 * w + 1)
    loads, events = traj.loads, set(traj.events)
    assert 3 <= len(events) < 60  # contacts do come and go
    steps_s, steps_f = [], []
    for k in range(1, loads.batch_size):
        if k in events:
            continue
        assert int(loads.count[k]) == int(loads.count[k - 1]), k
        on = loads.active[k]
        steps_s.append((loads.s[k] - loads.s[k - 1]).abs()[on])
        steps_f.append((loads.f[k] - loads.f[k - 1]).norm(dim=-1)[on])
    ds, df = torch.cat(steps_s), torch.cat(steps_f)
    assert ds.max() <= model.drift_speed / rate * (1 + 1e-9)
    assert ds.max() > 0.2 * model.drift_speed / rate  # they do drift
    assert df.max() <= df_bound
    assert df.median() < 0.01  # typical frame-to-frame change of a force, in N at 100 Hz


def test_stream_respects_the_limits(stream):
    rod, traj = stream
    sampler = sy.LoadSampler()
    loads = traj.loads
    assert loads.count.max() <= 3 and loads.count.min() >= 1
    assert int(loads.count.max()) == 3
    gaps = (loads.s[:, 1:] - loads.s[:, :-1])[loads.active[:, 1:]]
    assert gaps.min() >= sampler.min_separation
    lo, hi = sampler.location_range(rod)
    assert loads.s[loads.active].min() >= lo and loads.s[loads.active].max() <= hi
    turning = sy.total_turning(rod, loads, samples=1025)
    assert turning.max() <= sampler.max_bending + 1e-3
    assert traj.scale is not None and float(traj.scale.min()) > 0


def test_stream_truth_matches_readings(stream):
    rod, traj = stream
    assert len(traj.readings) == len(traj.truth) == 1200
    frames = [0, 150, 600, 1199]
    cases = [[(f["s"], f["fx"], f["fy"]) for f in traj.truth[k]["forces"]] for k in frames]
    ref = _grating_curvature(rod, tr.PointForces.from_lists(cases, max_forces=3))
    got = torch.tensor([traj.readings[k]["curvature"] for k in frames], dtype=torch.float64)
    assert torch.allclose(got, ref, atol=1e-7)
    for k in frames:
        r, t = traj.readings[k], traj.truth[k]
        assert r["id"] == t["id"] == f"f{k:06d}" and r["t"] == t["t"] == pytest.approx(k / 100.0)
        assert [f["s"] for f in t["forces"]] == sorted(f["s"] for f in t["forces"])


def test_noisy_stream_with_missing_gratings(rod):
    sensor = sy.SensorModel(noise=0.15, missing_prob=0.2)
    traj = sy.generate_trajectory(rod, 300, rate=50.0, sensor=sensor, seed=2, decimals=6)
    again = sy.generate_trajectory(rod, 300, rate=50.0, sensor=sensor, seed=2, decimals=6)
    assert traj.readings == again.readings and traj.truth == again.truth
    nulls = [u is None for r in traj.readings for u in r["curvature"]]
    assert sum(nulls) / len(nulls) == pytest.approx(0.2, abs=0.03)
    values = torch.tensor([[u if u is not None else [math.nan] * 2 for u in r["curvature"]] for r in traj.readings])
    residual = (values.double() - traj.clean)[traj.mask]
    assert float(residual.std()) == pytest.approx(0.15, rel=0.05)
    assert all(len(str(x).split(".")[-1]) <= 6 for r in traj.readings[:20] for u in r["curvature"] if u for x in u)


def test_cli_writes_a_stream(tmp_path, capsys):
    out = tmp_path / "s.jsonl"
    assert (
        main(
            [
                "generate",
                "--trajectory",
                "--rod",
                "nitinol290",
                "--count",
                "120",
                "--rate",
                "40",
                "--out",
                str(out),
                "--seed",
                "3",
                "--noise",
                "0.1",
            ]
        )
        == 0
    )
    assert "120 readings" in capsys.readouterr().err
    readings = [json.loads(line) for line in out.read_text().splitlines()]
    truth = [json.loads(line) for line in (tmp_path / "s_truth.jsonl").read_text().splitlines()]
    assert len(readings) == len(truth) == 120
    assert set(readings[0]) == {"id", "t", "curvature"} and set(truth[0]) == {"id", "t", "forces"}
    assert readings[1]["t"] == pytest.approx(1 / 40) and len(readings[0]["curvature"]) == 14
    assert set(truth[5]["forces"][0]) == {"s", "fx", "fy"}
    other = tmp_path / "elsewhere.jsonl"
    assert (
        main(
            [
                "generate",
                "--trajectory",
                "--rod",
                "nitinol290",
                "--count",
                "10",
                "--out",
                str(out),
                "--truth",
                str(other),
            ]
        )
        == 0
    )
    assert len(other.read_text().splitlines()) == 10


def test_shipped_example_stream():
    root = shipped_file("example_stream.jsonl").parent
    readings_path = os.path.join(root, "example_stream.jsonl")
    truth_path = os.path.join(root, "example_stream_truth.jsonl")
    if not os.path.exists(readings_path):
        pytest.skip("no shipped example stream")
    assert os.path.getsize(readings_path) + os.path.getsize(truth_path) < 300_000
    with open(readings_path) as fh:
        readings = [json.loads(line) for line in fh]
    with open(truth_path) as fh:
        truth = [json.loads(line) for line in fh]
    assert [r["id"] for r in readings] == [t["id"] for t in truth]
    rod = tr.presets.nitinol290()
    frames = [0, len(truth) // 2, len(truth) - 1]
    cases = [[(f["s"], f["fx"], f["fy"]) for f in truth[k]["forces"]] for k in frames]
    ref = _grating_curvature(rod, tr.PointForces.from_lists(cases, max_forces=3))
    got = torch.tensor([readings[k]["curvature"] for k in frames], dtype=torch.float64)
    # the readings are the truth's forces seen through noise of sigma 0.1 1/m (84 residuals)
    assert float((got - ref).std()) == pytest.approx(0.1, rel=0.3)


def test_turning_and_peak_of_a_small_tip_force_are_the_lever_arm_s():
    """Small deflection, a force F at the tip: |u(s)| = F (L - s) / EI, so the peak is F L / EI at the base and the
    turning F L^2 / (2 EI)."""
    from torchrod.synthetic import total_turning, turning_and_peak

    rod = tr.presets.nitinol290()
    L, EI, F = rod.length, rod.bending_stiffness, 1e-5
    loads = tr.PointForces(torch.tensor([[L]], dtype=torch.float64), torch.tensor([[[0.0, F]]], dtype=torch.float64))
    turning, peak = turning_and_peak(rod, loads)
    assert peak.shape == turning.shape == (1,)
    assert float(peak[0]) == pytest.approx(F * L / EI, rel=1e-6)
    assert float(turning[0]) == pytest.approx(F * L**2 / (2 * EI), rel=1e-3)
    assert torch.equal(total_turning(rod, loads), turning)


def test_the_learn_package_gives_the_same_names():
    """``torchrod.learn.synthetic`` is another name for the same objects (code that imports them from there)."""
    from torchrod.learn import synthetic as learn_synthetic

    assert learn_synthetic.__all__ == sy.__all__
    for name in sy.__all__:
        assert getattr(learn_synthetic, name) is getattr(sy, name), name
