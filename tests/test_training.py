"""Training the warm-start network: the losses, a tiny run, checkpoints and resume, two-process DDP, the CLI."""

from __future__ import annotations

import json
import os
import socket
import time

import pytest
import torch

import torchrod as tr
from torchrod.cli import main as cli_main
from torchrod.learn.checkpoint import load_checkpoint
from torchrod.learn.network import NetConfig, NetOutput
from torchrod.learn.training import (
    TrainConfig,
    TrainingData,
    compute_losses,
    evaluate_guess,
    train,
)
from torchrod.learn.warm_start import WarmStart, WarmStartGuess
from torchrod.synthetic import LoadSampler, SensorModel, SyntheticSet, generate

TINY = {
    "batch_size": 64,
    "validation": 64,
    "hidden": 32,
    "depth": 2,
    "physics_batch": 16,
    "logdir": None,
    "progress": False,
}


@pytest.fixture(scope="module")
def tiny_set() -> SyntheticSet:
    """512 simulated cases of 1 to 3 forces on the paper's rod, noiseless (training adds the noise)."""
    return generate(tr.presets.nitinol290(), 512, sampler=LoadSampler(), sensor=SensorModel(noise=0.0), seed=5)


@pytest.fixture(scope="module")
def tiny(tiny_set) -> TrainingData:
    return TrainingData.from_set(tiny_set)


def test_training_data_are_dimensionless(tiny_set, tiny):
    rod = tiny_set.rod
    L, EI = rod.length, rod.bending_stiffness
    loads = tiny_set.loads
    assert tiny.count.tolist() == loads.count.tolist()
    active = loads.active
    torch.testing.assert_close(tiny.s[active], (loads.s[active] / L).float())
    torch.testing.assert_close(tiny.f[active], (loads.f[active] * L * L / EI).float())
    torch.testing.assert_close(tiny.clean, (tiny_set.clean * L).float())
    # The unit rod (L = EI = 1, relative gratings) reproduces the dimensionless readings.
    unit = tr.Rod(length=1.0, bending_stiffness=1.0, gratings=rod.relative_gratings)
    u = tr.grating_curvature(unit, tr.PointForces(tiny.s[:8].double(), tiny.f[:8].double(), active[:8]))
    torch.testing.assert_close(u.float(), tiny.clean[:8], rtol=1e-5, atol=1e-5)


class _Oracle(torch.nn.Module):
    """Outputs the given forces for the true count and something else for the other heads."""

    def __init__(self, s: torch.Tensor, f: torch.Tensor, count: torch.Tensor, H: int) -> None:
        super().__init__()
        self.s, self.f, self.count, self.H = s, f, count, H

    def forward(self, reading, mask):
        B = reading.shape[0]
        logits = torch.nn.functional.one_hot(self.count - 1, self.H).float() * 20.0
        s_heads, f_heads = [], []
        for h in range(1, self.H + 1):
            base = torch.linspace(0.1, 0.9, h).expand(B, h).clone()
            fb = torch.ones(B, h, 2)
            sel = self.count == h
            base[sel] = self.s[sel, :h]
            fb[sel] = self.f[sel, :h]
            s_heads.append(base)
            f_heads.append(fb)
        return NetOutput(logits, tuple(s_heads), tuple(f_heads))


def test_losses_vanish_for_the_true_forces_and_not_otherwise(tiny):
    idx = torch.arange(32)
    s, f, count = tiny.s[idx], tiny.f[idx], tiny.count[idx]
    reading = tiny.clean[idx].clone()
    present = torch.ones(32, tiny.clean.shape[1], dtype=torch.bool)
    present[::3, 5] = False
    reading[~present] = 1e3  # garbage at missing gratings must not enter the physics loss
    config = NetConfig.for_rod(tiny.rod, **tiny.normalisation())
    terms = compute_losses(
        _Oracle(s, f, count, 3), config, reading, present, s, f, count, physics_weight=1.0, physics_batch=32
    )
    assert float(terms["location"]) == 0.0 and float(terms["force"]) == 0.0
    assert float(terms["count"]) < 1e-6
    assert float(terms["physics"]) < 1e-6  # the rod model of the true forces reproduces the reading
    f_wrong = f * 1.2
    terms = compute_losses(
        _Oracle(s, f_wrong, count, 3),
        config,
        reading,
        present,
        s,
        f,
        count,
        physics_weight=1.0,
        physics_batch=32,
    )
    assert float(terms["force"]) > 0.1 and float(terms["physics"]) > 1e-3


def test_the_physics_loss_pulls_the_forces_toward_the_reading(tiny):
    # Gradient of the physics loss alone with respect to the predicted forces: a descent step on forces that are
    # 20 % too large must shrink them toward the truth and lower the loss (the rod model is differentiable).
    idx = torch.arange(16)
    s, f, count = tiny.s[idx], tiny.f[idx], tiny.count[idx]
    present = torch.ones(16, tiny.clean.shape[1], dtype=torch.bool)
    config = NetConfig.for_rod(tiny.rod, **tiny.normalisation())
    scale = torch.tensor(1.2, requires_grad=True)

    def physics(k):
        terms = compute_losses(
            _Oracle(s, f * k, count, 3),
            config,
            tiny.clean[idx],
            present,
            s,
            f,
            count,
            physics_weight=1.0,
            physics_batch=16,
        )
        return terms["physics"]

    loss = physics(scale)
    (grad,) = torch.autograd.grad(loss, scale)
    assert float(grad) > 0
    assert float(physics(scale.detach() - 0.05)) < float(loss.detach())


def test_a_tiny_run_lowers_the_loss(tiny, tmp_path):
    config = TrainConfig(epochs=8, lr=1e-2, checkpoint=str(tmp_path / "c.pt"), **TINY)
    result = train(config, data=tiny)
    first, last = result.history[0], result.history[-1]
    assert last["total"] < 0.75 * first["total"]
    assert last["location"] < first["location"] and last["force"] < first["force"]
    assert result.step == 8 * (512 // 64) and result.epoch == 8
    assert 0.0 <= result.metrics["count_accuracy"] <= 1.0


def test_checkpoint_holds_what_resuming_needs_and_resume_matches_an_uninterrupted_run(tiny, tmp_path, monkeypatch):
    import shutil

    from torchrod.learn import training

    # Keep the checkpoint written after epoch 1 of a 2-epoch run: the state an interrupted run leaves behind.
    save = training.save_checkpoint

    def save_and_keep(path, net, **kwargs):
        save(path, net, **kwargs)
        if kwargs["epoch"] == 1:
            shutil.copy(path, tmp_path / "epoch1.pt")

    monkeypatch.setattr(training, "save_checkpoint", save_and_keep)
    straight = train(TrainConfig(epochs=2, checkpoint=str(tmp_path / "a.pt"), **TINY), data=tiny)
    net, meta = load_checkpoint(tmp_path / "epoch1.pt")
    assert meta["step"] == 8 and meta["epoch"] == 1
    assert meta["torchrod_version"] == tr.__version__
    assert meta["config"]["curvature_scale"] == pytest.approx(tiny.normalisation()["curvature_scale"])
    assert meta["config"]["force_scale"] == pytest.approx(tiny.normalisation()["force_scale"])
    assert meta["train_config"]["epochs"] == 2 and "optimizer" in meta and "count_accuracy" in meta["metrics"]
    assert WarmStart.load(tmp_path / "epoch1.pt", tiny.rod).matches(tiny.rod)
    resumed = train(
        TrainConfig(epochs=2, checkpoint=str(tmp_path / "b.pt"), resume=str(tmp_path / "epoch1.pt"), **TINY),
        data=tiny,
    )
    assert resumed.step == straight.step == 16 and len(resumed.history) == 1
    for (name, a), b in zip(straight.net.state_dict().items(), resumed.net.state_dict().values(), strict=False):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    # The resumed run really moved on from the checkpoint.
    assert not torch.allclose(net.state_dict()["out.weight"], resumed.net.state_dict()["out.weight"])


def test_evaluate_guess_measures_what_it_says():
    truth = tr.PointForces.from_lists(
        [[(0.10, 1.0, 0.0)], [(0.05, 0.0, 1.0), (0.20, 0.5, 0.5)], [(0.15, -1.0, 0.0)]], max_forces=3
    )
    probs = torch.tensor([[0.9, 0.1, 0.0], [0.2, 0.8, 0.0], [0.1, 0.3, 0.6]], dtype=torch.float64)
    forces = {
        1: tr.PointForces(
            torch.tensor([[0.102], [0.0], [0.15]], dtype=torch.float64),
            torch.tensor([[[1.0, 0.3]], [[0.0, 0.0]], [[-1.0, 0.0]]], dtype=torch.float64),
        ),
        2: tr.PointForces(
            torch.tensor([[0.0, 0.1], [0.051, 0.196], [0.1, 0.2]], dtype=torch.float64),
            torch.tensor([[[0.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [0.5, 0.4]], [[0.0, 0.0]] * 2], dtype=torch.float64),
        ),
        3: tr.PointForces(torch.zeros(3, 3).double(), torch.zeros(3, 3, 2).double()),
    }
    m = evaluate_guess(WarmStartGuess(probs, forces), truth)
    assert m["count_accuracy"] == pytest.approx(2 / 3)
    # Cases 0 and 2 hold one force (guessed 1 and 3), case 1 holds two (guessed 2); no case holds three.
    assert m["count_accuracy_1"] == 0.5 and m["count_accuracy_2"] == 1.0 and "count_accuracy_3" not in m
    assert m["cases_1"] == 2 and m["cases_2"] == 1
    assert m["location_error_median_1"] == pytest.approx(0.001)  # median of 0.002 and 0.0 (case 2: guess for 1)
    assert m["force_error_median_1"] == pytest.approx(0.15)
    assert m["location_error_median_2"] == pytest.approx(0.0025)  # median of 0.001 and 0.004
    assert m["force_error_median_2"] == pytest.approx(0.05)  # median of 0.0 and 0.1


def test_train_config_checks_its_values():
    with pytest.raises(ValueError, match="epochs"):
        TrainConfig(epochs=0)
    with pytest.raises(ValueError, match="missing_prob"):
        TrainConfig(missing_prob=1.0)
    with pytest.raises(ValueError, match="device"):
        TrainConfig(device="tpu")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, folder: str, data_path: str) -> None:
    import faulthandler

    # A crash in native code (gloo) leaves a trace the test prints.
    faulthandler.enable(file=open(os.path.join(folder, f"fault{rank}.txt"), "w"), all_threads=True)
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world),
        LOCAL_RANK=str(rank),
        LOCAL_WORLD_SIZE=str(world),
    )
    data = TrainingData.from_set(SyntheticSet.load(data_path))
    config = TrainConfig(epochs=2, checkpoint=os.path.join(folder, "ddp.pt"), threads=1, device="cpu", **TINY)
    result = train(config, data=data)
    torch.save({"state": result.net.state_dict(), "step": result.step}, os.path.join(folder, f"rank{rank}.pt"))


@pytest.mark.slow
def test_two_processes_with_ddp_end_with_identical_weights(tiny_set, tmp_path):
    import torch.multiprocessing as mp

    data_path = str(tmp_path / "tiny.npz")
    tiny_set.save(data_path)
    ctx = mp.start_processes(
        _ddp_worker,
        args=(2, _free_port(), str(tmp_path), data_path),
        nprocs=2,
        join=False,
        start_method="spawn",
    )
    deadline = time.monotonic() + 120.0
    try:
        while not ctx.join(timeout=1.0):
            assert time.monotonic() < deadline, "two-process training did not finish within 120 s"
    except Exception:
        for r in (0, 1):
            trace = tmp_path / f"fault{r}.txt"
            print(f"==== rank {r}:", trace.read_text()[-6000:] if trace.exists() else "(no trace)")
        raise
    finally:
        for p in ctx.processes:
            if p.is_alive():
                p.kill()
    a, b = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    # 512 cases over 2 processes in batches of 64: 4 steps per epoch on each.
    assert a["step"] == b["step"] == 8
    for name, value in a["state"].items():
        assert torch.equal(value, b["state"][name]), name
    net, meta = load_checkpoint(tmp_path / "ddp.pt")  # rank 0 saved the checkpoint
    assert meta["step"] == 8
    for name, value in net.state_dict().items():
        assert torch.equal(value, a["state"][name]), name


def test_cli_trains_logs_and_saves(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ckpt, logs = tmp_path / "ws.pt", tmp_path / "logs"
    status = cli_main(
        [
            "train",
            "--generate",
            "256",
            "--validation",
            "32",
            "--epochs",
            "1",
            "--batch-size",
            "64",
            "--hidden",
            "16",
            "--depth",
            "1",
            "--log-every",
            "1",
            "--physics-batch",
            "8",
            "--logdir",
            str(logs),
            "--checkpoint",
            str(ckpt),
            "--quiet",
        ]
    )
    assert status == 0
    ws = WarmStart.load(ckpt, tr.presets.nitinol290())
    assert ws.meta["step"] == 4
    events = EventAccumulator(str(logs))
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    assert {"train/loss_total", "train/loss_physics", "train/lr", "val/count_accuracy"} <= scalars
    assert any(t.startswith("val/location_error_median_mm") for t in scalars)
    assert any(t.startswith("val/force_error_median") for t in scalars)
    assert "val/fits" in events.Tags()["images"]


def test_cli_train_reports_the_held_back_quality_once_with_and_without_the_network(tmp_path, capsys):
    """The network report: one quality block (on stdout, not again in the progress on stderr), the estimator's
    accuracy without the network, with its guesses beside the scan and with its guesses alone side by side, and
    what to do when the network is not trusted."""
    from torchrod.learn.training import QUALITY_ROWS, format_quality

    ckpt = tmp_path / "ws.pt"
    small = ["--generate", "256", "--validation", "32", "--epochs", "1", "--batch-size", "64", "--hidden", "16"]
    small += ["--depth", "1", "--physics-batch", "8", "--logdir", "none", "--checkpoint", str(ckpt)]
    assert cli_main(["train", *small]) == 0  # with progress lines on stderr
    captured = capsys.readouterr()
    assert (captured.out + captured.err).count("held-back quality") == 1
    block = captured.out[captured.out.index("held-back quality") :]
    rows = {who: line for line in block.splitlines() for _, who in QUALITY_ROWS if line.strip().startswith(who)}
    assert set(rows) == {who for _, who in QUALITY_ROWS}
    # Every estimator row has its count accuracy and errors: with and without the network, side by side.
    for who in ("estimator without the network", "estimator, guesses beside the scan"):
        assert rows[who].count("%") == 2 and " mm" in rows[who], rows[who]
    quality = WarmStart.load(ckpt, tr.presets.nitinol290()).meta["quality"]
    assert 0.0 <= quality["plain_count_accuracy"] <= 1.0 and quality["readings"] == 32.0
    assert block.rstrip("\n") == format_quality(quality)
    # A one-epoch, 16-unit network is not trusted, and the report says what to do about it.
    assert "trusted: no" in block and "What to do" in block and "--checkpoint none" in block
    # A record the verdict trusts ends with that, and no advice.
    trusted = dict(quality, trusted_worse_fits=0.0, trusted_evaluations=1.0, plain_evaluations=2.0)
    for key in ("count_accuracy", "force_error_median", "location_error_median"):
        trusted[f"trusted_{key}"] = trusted[f"search_{key}"]
    text = format_quality(trusted)
    assert text.endswith("trusted: yes: the estimator starts its fits from the network's guesses alone")
    assert "What to do" not in text


def test_cli_train_refuses_a_rod_that_contradicts_the_data_set_and_accepts_one_that_agrees(tiny_set, tmp_path, capsys):
    data = tmp_path / "set.npz"
    tiny_set.save(data)
    softer = tmp_path / "softer.json"
    tr.presets.nitinol290().with_(youngs_modulus=60e9).to_json(softer)
    small = [
        "--validation",
        "32",
        "--epochs",
        "1",
        "--batch-size",
        "64",
        "--hidden",
        "16",
        "--depth",
        "1",
        "--physics-batch",
        "8",
        "--logdir",
        "none",
        "--quiet",
    ]
    ckpt = tmp_path / "ws.pt"
    status = cli_main(["train", "--data", str(data), "--rod", str(softer), "--checkpoint", str(ckpt), *small])
    err = capsys.readouterr().err
    assert status == 2 and not ckpt.exists()
    assert err.startswith(
        f"torchrod train: error: --rod {softer} contradicts the data set {data}, made for another rod: "
        "bending_stiffness 0.00738830604 vs 0.00661639347 N m^2"
    ), err
    assert err.count("\n") == 1
    # A rod that agrees (the preset by name, or the same rod written as a file with its stiffness) is accepted.
    same = tmp_path / "same.json"
    rod = tr.presets.nitinol290()
    same.write_text(
        json.dumps({"length": rod.length, "bending_stiffness": rod.bending_stiffness, "gratings": list(rod.gratings)})
    )
    for given in ("nitinol290", str(same)):
        assert cli_main(["train", "--data", str(data), "--rod", given, "--checkpoint", str(ckpt), *small]) == 0
        assert WarmStart.load(ckpt, rod).meta["epoch"] == 1
        ckpt.unlink()
    # Without --rod, the set's rod (a network for a 16-grating set, say) is used without a check.
    assert TrainConfig().rod is None


def test_search_labels_are_the_searchs_own_fit_of_every_count_and_its_count():
    """Each count's label is the search's best fit of that many forces (in model coordinates: the location bias
    taken away), sorted by location; the count label is the count the search chooses. On clean one-force readings
    that is the truth, and the fit of one more force keeps the loss no higher."""
    from torchrod.estimate.estimator import Estimator, EstimatorOptions
    from torchrod.learn.labels import search_labels

    rod = tr.presets.nitinol290()
    rod = tr.Rod(length=rod.length, bending_stiffness=rod.bending_stiffness, gratings=rod.gratings, location_bias=0.004)
    truth = tr.PointForces.from_lists([[(0.12, 0.5, -0.3)], [(0.21, -0.2, 0.6)], [(0.26, 0.4, 0.4)]])
    u = tr.grating_curvature(rod, tr.PointForces(truth.s - rod.location_bias, truth.f))
    mask = torch.ones(u.shape[:2], dtype=torch.bool)
    labels = search_labels(rod, u, mask, noise=0.01, batch_size=2)
    assert labels.count.tolist() == [1, 1, 1]
    assert labels.fitted.all()
    torch.testing.assert_close(labels.s[:, 0, :1], truth.s - rod.location_bias, atol=1e-5, rtol=0)
    torch.testing.assert_close(labels.f[:, 0, :1], truth.f, atol=1e-4, rtol=0)
    for h in (2, 3):
        assert (labels.s[:, h - 1, :h].diff(dim=1) >= 0).all() and labels.s[:, h - 1, h:].isnan().all()
    fixed = Estimator(rod, EstimatorOptions(noise=0.01, num_forces=2)).estimate(u, mask)
    torch.testing.assert_close(labels.s[:, 1, :2], fixed.forces.s - rod.location_bias)


def test_a_network_trained_on_the_searchs_fits_learns_every_head(tiny, tmp_path):
    """``labels="search"``: one fixed noisy reading per case, labelled by the search (a count of 0 allowed, left
    out of the cross-entropy), and every head learns its count's fit: the losses fall over a tiny run."""
    small = TrainingData(
        rod=tiny.rod, s=tiny.s[:128], f=tiny.f[:128], count=tiny.count[:128], clean=tiny.clean[:128],
        mask=tiny.mask[:128],
    )  # fmt: skip
    labelled = small.with_search_labels(noise=0.1, missing_prob=0.05, seed=3)
    assert labelled.reading is not None and labelled.fits is not None
    assert labelled.fits[0].shape == (128, 3, 3) and labelled.fits[1].shape == (128, 3, 3, 2)
    assert not torch.equal(labelled.reading, small.clean) and (labelled.count <= 3).all()
    assert not labelled.mask.all()  # gratings missing as drawn, the same every epoch
    config = TrainConfig(epochs=6, lr=1e-2, checkpoint=str(tmp_path / "s.pt"), labels="search", **TINY)
    result = train(config, data=labelled)
    first, last = result.history[0], result.history[-1]
    assert last["location"] < first["location"] and last["force"] < first["force"]
    # A batch whose count labels are all 0 has no cross-entropy term to learn from, and nothing breaks.
    net = result.net
    zero = torch.zeros(4, dtype=torch.long)
    fits = tuple(x[:4] for x in labelled.fits)
    terms = compute_losses(
        net, net.config, labelled.reading[:4], labelled.mask[:4], labelled.s[:4], labelled.f[:4], zero,
        physics_weight=0.1, physics_batch=4, fits=fits,
    )  # fmt: skip
    assert terms["total"].isfinite() and float(terms["count"].detach()) == 0.0
