"""The estimator, its warm-start network, the stream and the commands on a CUDA device, against their CPU twins
(the torch backend on the CPU, which runs the same operations): the same counts, verdicts and evaluations, forces
to rounding. Skipped without a GPU; CI has none, so these run where a GPU is lent (README, Development)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import torch
from test_lm_compiled import stratified_readings

import torchrod as tr
from torchrod.io.stream import Reading, StreamOptions, stream
from torchrod.learn.warm_start import SHIPPED_CHECKPOINT

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]


def assert_same_answers(gpu: tr.EstimateResult, cpu: tr.EstimateResult) -> None:
    """The same counts, verdicts and evaluations; forces within 1e-7 N and 1 nm, as the compiled steps are held
    to the array code (tests/test_lm_compiled.py): the devices round differently, the decisions do not move."""
    assert gpu.status.is_cuda and gpu.forces.s.is_cuda and gpu.std.is_cuda
    assert gpu.statuses == cpu.statuses
    assert torch.equal(gpu.num_forces.cpu(), cpu.num_forces)
    assert torch.equal(gpu.evaluations.cpu(), cpu.evaluations)
    torch.testing.assert_close(gpu.forces.f.cpu().nan_to_num(), cpu.forces.f.nan_to_num(), rtol=0, atol=1e-7)
    torch.testing.assert_close(gpu.forces.s.cpu().nan_to_num(), cpu.forces.s.nan_to_num(), rtol=0, atol=1e-9)
    torch.testing.assert_close(gpu.p_value.cpu().nan_to_num(), cpu.p_value.nan_to_num(), rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("noise", [0.1, None], ids=["noise-given", "noise-per-reading"])
def test_the_estimator_on_cuda_answers_as_its_cpu_twin(rod, gen, noise):
    """48 stratified readings (near gratings, the base, the tip, gratings missing), as one batch and a few one per
    call; the default backend on a GPU is torch, which the CPU twin is told to use."""
    u, mask = stratified_readings(rod, gen, 48)
    cpu = tr.Estimator(rod, tr.EstimatorOptions(noise=noise, backend="torch"))
    gpu = tr.Estimator(rod, tr.EstimatorOptions(noise=noise))
    assert_same_answers(gpu.estimate(u.cuda(), mask.cuda()), cpu.estimate(u, mask))
    for i in range(0, 48, 7):
        one, present = u[i : i + 1], mask[i : i + 1]
        assert_same_answers(gpu.estimate(one.cuda(), present.cuda()), cpu.estimate(one, present))


def test_float32_readings_on_cuda_are_answered_in_float32(rod, gen):
    u, mask = stratified_readings(rod, gen, 6)
    res = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1)).estimate(u.float().cuda(), mask.cuda())
    assert res.forces.f.dtype == torch.float32 and res.forces.f.is_cuda
    cpu = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1, backend="torch")).estimate(u.float(), mask)
    assert res.statuses == cpu.statuses


@pytest.mark.filterwarnings("ignore:torchrod. the warm-start network")
def test_the_network_guesses_on_cuda_as_on_the_cpu(rod, gen):
    """The shipped warm-start network on the GPU (its copy made there once), in an estimator from the checkpoint."""
    u, mask = stratified_readings(rod, gen, 24)
    gpu = tr.Estimator.from_checkpoint(SHIPPED_CHECKPOINT, rod, tr.EstimatorOptions(noise=0.1))
    cpu = tr.Estimator.from_checkpoint(SHIPPED_CHECKPOINT, rod, tr.EstimatorOptions(noise=0.1, backend="torch"))
    g, c = gpu.warm_start.guess(u.cuda(), mask.cuda()), cpu.warm_start.guess(u, mask)
    for h in c.forces:
        assert g.forces[h].f.is_cuda
        torch.testing.assert_close(g.forces[h].f.cpu(), c.forces[h].f, rtol=1e-5, atol=1e-6)
    assert_same_answers(gpu.estimate(u.cuda(), mask.cuda()), cpu.estimate(u, mask))


def test_a_stream_on_cuda_answers_as_on_the_cpu(rod, gen):
    """A backlog and a stream learning its noise, on the device and on the CPU twin: the same answers in order."""
    u, mask = stratified_readings(rod, gen, 40)
    items = [Reading(k, torch.where(mask[k, :, None], u[k], math.nan)) for k in range(40)]
    est = {
        "cuda": tr.Estimator(rod, tr.EstimatorOptions(backend="auto")),
        "cpu": tr.Estimator(rod, tr.EstimatorOptions(backend="torch")),
    }
    for batch in (1, 16):
        answers = {}
        for device, e in est.items():
            opts = StreamOptions(batch_size=batch, device=device)
            answers[device] = [r.record for r in stream(e, iter(items), opts)]
        for g, c in zip(answers["cuda"], answers["cpu"], strict=True):
            assert (g["id"], g["status"], g["num_forces"]) == (c["id"], c["status"], c["num_forces"])
            for fg, fc in zip(g["forces"], c["forces"], strict=True):
                assert math.isclose(fg["fx"], fc["fx"], abs_tol=1e-7) and math.isclose(fg["s"], fc["s"], abs_tol=1e-9)


def run_cli(*args: str, stdin: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "torchrod", *args], input=stdin, capture_output=True, text=True, timeout=300
    )


def test_the_commands_estimate_on_cuda(rod, gen):
    """``torchrod estimate`` and ``torchrod stream`` with ``--device cuda`` answer as on the CPU with the torch
    backend's twin (the same statuses and counts; the commands' CPU runs use NumPy, which rounds differently)."""
    u, mask = stratified_readings(rod, gen, 12)
    lines = "".join(
        json.dumps(
            {"id": k, "curvature": [row if m else None for row, m in zip(u[k].tolist(), mask[k].tolist(), strict=True)]}
        )
        + "\n"
        for k in range(12)
    )
    # (no time budget: the stream's default would cut readings by the machine's speed; tests/test_budget.py)
    common = ["--rod", "nitinol290", "--noise", "0.1", "--checkpoint", "none", "--time-budget-ms", "1e9"]
    for command in (["estimate", "-"], ["stream"]):
        out = {}
        for device in ("cuda", "cpu"):
            done = run_cli(*command, *common, "--device", device, stdin=lines)
            assert done.returncode == 0, done.stderr
            out[device] = [json.loads(line) for line in done.stdout.splitlines()]
        assert [(a["id"], a["status"], a["num_forces"]) for a in out["cuda"]] == [
            (a["id"], a["status"], a["num_forces"]) for a in out["cpu"]
        ]


def test_a_device_that_cannot_be_used_is_refused(rod):
    done = run_cli("stream", "--rod", "nitinol290", "--device", "cuda:99", stdin="")
    assert done.returncode == 2 and "cuda:99" in done.stderr
    done = run_cli("stream", "--rod", "nitinol290", "--device", "cuda", "--workers", "2", stdin="")
    assert done.returncode == 2 and "--workers" in done.stderr
