"""The CUDA target. Without a GPU: numba-cuda's simulator runs the CUDA entry (one thread per reading, scratch sliced
from batch arrays, several launches per batch) on the CPU, and must answer as the compiled CPU kernels do; the
kernel compiles to PTX where the CUDA compiler is installed. With a GPU (tests marked ``cuda``, skipped elsewhere;
``torchrod bench gpu`` runs them): the estimator, its network, the stream and the commands answer on the device as
on the CPU."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from cases import stratified_readings

import torchrod as tr
from torchrod.io.stream import Reading, StreamOptions, stream

HERE = Path(__file__).resolve().parent

# The same decisions everywhere; the numbers to rounding: the devices (and the simulator's Python arithmetic) round
# differently, and a fit's last steps amplify that by the conditioning of its problem.
FORCE_ATOL, LOCATION_ATOL = 1e-7, 1e-9

SIMULATED = """
import json, sys
sys.path.insert(0, {tests!r})
import torch
import torchrod as tr
from cases import stratified_readings

rod = tr.presets.nitinol290()
u, mask = stratified_readings(rod, torch.Generator().manual_seed(5), {count})
out = {{}}
for noise in (0.1, None):
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=noise, target="cuda"))
    est.plan(device="cpu").launch_limit = 7  # several launches per batch, the last one short
    r = est.estimate(u, mask)
    out[str(noise)] = dict(statuses=[str(s) for s in r.statuses], counts=r.num_forces.tolist(),
                           evaluations=r.evaluations.tolist(), s=r.forces.s.nan_to_num().tolist(),
                           f=r.forces.f.nan_to_num().tolist())
print(json.dumps(out))
"""


def test_the_cuda_kernel_under_the_simulator_answers_as_the_cpu_kernels():
    """24 stratified readings (near gratings, the base, the tip, gratings missing), the noise given and not: the
    CUDA entry under numba-cuda's simulator, in launches of 7 readings, gives every reading the count, status and
    number of evaluations of the compiled CPU kernels, and their forces to rounding."""
    pytest.importorskip("numba.cuda")
    count = 24
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    done = subprocess.run(
        [sys.executable, "-c", SIMULATED.format(tests=str(HERE), count=count)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    simulated = json.loads(done.stdout.splitlines()[-1])
    rod = tr.presets.nitinol290()
    u, mask = stratified_readings(rod, torch.Generator().manual_seed(5), count)
    for noise in (0.1, None):
        cpu = tr.Estimator(rod, tr.EstimatorOptions(noise=noise, target="cpu")).estimate(u, mask)
        sim = simulated[str(noise)]
        assert sim["statuses"] == [str(s) for s in cpu.statuses]
        assert sim["counts"] == cpu.num_forces.tolist()
        assert sim["evaluations"] == cpu.evaluations.tolist()
        torch.testing.assert_close(torch.tensor(sim["s"], dtype=torch.float64), cpu.forces.s.nan_to_num(),
                                   rtol=0, atol=LOCATION_ATOL)  # fmt: skip
        torch.testing.assert_close(torch.tensor(sim["f"], dtype=torch.float64), cpu.forces.f.nan_to_num(),
                                   rtol=0, atol=FORCE_ATOL)  # fmt: skip


ON_THE_SIMULATOR = """
import json, sys
import torch
import torchrod as tr

u = torch.tensor(json.load(open({path!r})), dtype=torch.float64)
est = tr.Estimator(tr.presets.nitinol290(), tr.EstimatorOptions({options}, target="cuda"))
r = est.estimate(u)
print(json.dumps(dict(statuses=[str(s) for s in r.statuses], evaluations=r.evaluations.tolist(),
                      counts=r.num_forces.tolist(), s=r.forces.s.tolist(), f=r.forces.f.tolist())))
"""


def _simulated(u: torch.Tensor, options: str, tmp_path: Path) -> dict:
    """The CUDA entry's answers under numba-cuda's simulator to readings u (B, G, 2) on ``nitinol290``, with
    ``EstimatorOptions({options})``."""
    path = tmp_path / "u.json"
    path.write_text(json.dumps(u.tolist()))
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    done = subprocess.run([sys.executable, "-c", ON_THE_SIMULATOR.format(path=str(path), options=options)],
                          capture_output=True, text=True, timeout=600, env=env, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.slow
def test_the_fixed_count_escape_under_the_simulator_answers_as_the_cpu_kernels(tmp_path):
    """Three large-bend readings whose fixed count of one misfits without the escape (tests/test_large_bends.py):
    the CUDA entry under the simulator searches them again through two forces as the CPU kernels do, with the same
    statuses and evaluations, and the forces to rounding."""
    pytest.importorskip("numba.cuda")
    from test_large_bends import _cases, _reading

    cases = [c for c in _cases(30, seed=5) if c[0] > 0.28][:3]
    u = torch.tensor([_reading(c)[0].tolist() for c in cases], dtype=torch.float64)
    simulated = _simulated(u, "noise=0.1, num_forces=1", tmp_path)
    options = tr.EstimatorOptions(noise=0.1, num_forces=1, target="cpu")
    cpu = tr.Estimator(tr.presets.nitinol290(), options).estimate(u)
    alone = tr.Estimator(tr.presets.nitinol290(), dataclasses.replace(
        options, search=dataclasses.replace(options.search, escape_turning=math.inf))).estimate(u)  # fmt: skip
    assert alone.statuses == [tr.Status.MISFIT] * 3  # the readings this test is for
    assert simulated["statuses"] == [str(s) for s in cpu.statuses] and tr.Status.MISFIT not in cpu.statuses
    assert simulated["evaluations"] == cpu.evaluations.tolist()
    torch.testing.assert_close(torch.tensor(simulated["s"], dtype=torch.float64), cpu.forces.s, rtol=0,
                               atol=LOCATION_ATOL)  # fmt: skip
    torch.testing.assert_close(torch.tensor(simulated["f"], dtype=torch.float64), cpu.forces.f, rtol=0,
                               atol=FORCE_ATOL)  # fmt: skip


@pytest.mark.slow
def test_patches_merged_into_one_force_under_the_simulator_as_on_the_cpu(tmp_path):
    """Three patch readings that the count tests alone answer as a pair (tests/test_patches.py): the CUDA entry under
    the simulator merges them into one force as the CPU kernels do, with the same statuses and evaluations, and the
    forces to rounding."""
    pytest.importorskip("numba.cuda")
    from test_patches import _both, _readings

    rod = tr.presets.nitinol290()
    loads, _ = tr.synthetic.sample_patches(rod, 600, 0.012, torch.Generator().manual_seed(21))
    u = _readings(rod, loads, 22)
    merged, alone = _both(rod, u, noise=0.1)
    u = u[(merged.num_forces < alone.num_forces).nonzero().flatten()[:3]]
    assert len(u) == 3  # the readings this test is for
    simulated = _simulated(u, "noise=0.1", tmp_path)
    cpu = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1, target="cpu")).estimate(u)
    assert simulated["counts"] == cpu.num_forces.tolist() == [1, 1, 1]
    assert simulated["statuses"] == [str(s) for s in cpu.statuses]
    assert simulated["evaluations"] == cpu.evaluations.tolist()
    torch.testing.assert_close(torch.tensor(simulated["s"], dtype=torch.float64), cpu.forces.s, rtol=0,
                               atol=LOCATION_ATOL)  # fmt: skip
    torch.testing.assert_close(torch.tensor(simulated["f"], dtype=torch.float64), cpu.forces.f, rtol=0,
                               atol=FORCE_ATOL)  # fmt: skip


def test_the_estimation_kernel_types_and_lowers_for_cuda():
    """The whole estimate per reading as one CUDA kernel, typed by numba-cuda and lowered to NVVM IR for sm_90 (the
    H100 and H200) without a GPU: every line of the kernel source is valid CUDA device code (the simulator above
    runs it as Python and would not notice, say, a device function returning an array). NVIDIA's optimiser, which
    takes far longer, runs in ``torchrod bench gpu --ptx``."""
    pytest.importorskip("numba.cuda")
    from torchrod.cli.benchmarks.gpu import lowering_seconds

    assert lowering_seconds("sm_90") > 0.0
    # Every device function typed once, for its arguments' types (not again for each constant a caller passes).
    kernels = vars(sys.modules["torchrod.kernels.cuda_kernels"])
    typed = {key: len(value.overloads) for key, value in kernels.items() if hasattr(value, "overloads")}
    assert typed["estimate_one"] == typed["march_model"] == 1
    assert max(typed.values()) == 1, typed


# ---------------------------------------------------------------------------------------------- on a GPU
def assert_same_answers(gpu: tr.EstimateResult, cpu: tr.EstimateResult) -> None:
    """The same counts, verdicts and evaluations; forces and locations to rounding."""
    assert gpu.status.is_cuda and gpu.forces.s.is_cuda and gpu.std.is_cuda
    assert gpu.statuses == cpu.statuses
    assert torch.equal(gpu.num_forces.cpu(), cpu.num_forces)
    assert torch.equal(gpu.evaluations.cpu(), cpu.evaluations)
    torch.testing.assert_close(gpu.forces.f.cpu().nan_to_num(), cpu.forces.f.nan_to_num(), rtol=0, atol=FORCE_ATOL)
    torch.testing.assert_close(gpu.forces.s.cpu().nan_to_num(), cpu.forces.s.nan_to_num(), rtol=0, atol=LOCATION_ATOL)
    torch.testing.assert_close(gpu.p_value.cpu().nan_to_num(), cpu.p_value.nan_to_num(), rtol=1e-6, atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("noise", [0.1, None], ids=["noise-given", "noise-per-reading"])
def test_the_estimator_on_cuda_answers_as_on_the_cpu(rod, gen, noise):
    """48 stratified readings as one batch (and in launches of 5), and a few one per call."""
    u, mask = stratified_readings(rod, gen, 48)
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=noise))
    cpu = est.estimate(u, mask)
    assert_same_answers(est.estimate(u.cuda(), mask.cuda()), cpu)
    est.plan(device="cuda").launch_limit = 5
    assert_same_answers(est.estimate(u.cuda(), mask.cuda()), cpu)
    for i in range(0, 48, 7):
        one, present = u[i : i + 1], mask[i : i + 1]
        assert_same_answers(est.estimate(one.cuda(), present.cuda()), cpu[i])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_float32_readings_on_cuda_are_answered_in_float32(rod, gen):
    u, mask = stratified_readings(rod, gen, 6)
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1))
    res = est.estimate(u.float().cuda(), mask.cuda())
    assert res.forces.f.dtype == torch.float32 and res.forces.f.is_cuda
    assert res.statuses == est.estimate(u.float(), mask).statuses


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.filterwarnings("ignore:torchrod. the warm-start network")
def test_the_network_guesses_on_cuda_as_on_the_cpu(rod, gen):
    """The shipped warm-start network on the GPU (its copy made there once), in an estimator from the checkpoint."""
    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT

    u, mask = stratified_readings(rod, gen, 24)
    est = tr.load_estimator(SHIPPED_CHECKPOINT, rod, tr.EstimatorOptions(noise=0.1))
    g, c = est.warm_start.guess(u.cuda(), mask.cuda()), est.warm_start.guess(u, mask)
    for h in c.forces:
        assert g.forces[h].f.is_cuda
        torch.testing.assert_close(g.forces[h].f.cpu(), c.forces[h].f, rtol=1e-5, atol=1e-6)
    assert_same_answers(est.estimate(u.cuda(), mask.cuda()), est.estimate(u, mask))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_stream_on_cuda_answers_as_on_the_cpu(rod, gen):
    """A backlog and a stream learning its noise, on the device and on the CPU: the same answers in order."""
    u, mask = stratified_readings(rod, gen, 40)
    items = [Reading(k, torch.where(mask[k, :, None], u[k], math.nan)) for k in range(40)]
    est = tr.Estimator(rod, tr.EstimatorOptions())
    for batch in (1, 16):
        answers = {}
        for device in ("cuda", "cpu"):
            opts = StreamOptions(batch_size=batch, device=device, workers=1)
            answers[device] = [r.record for r in stream(est, iter(items), opts)]
        for g, c in zip(answers["cuda"], answers["cpu"], strict=True):
            assert (g["id"], g["status"], g["num_forces"]) == (c["id"], c["status"], c["num_forces"])
            for fg, fc in zip(g["forces"], c["forces"], strict=True):
                assert math.isclose(fg["fx"], fc["fx"], abs_tol=FORCE_ATOL)
                assert math.isclose(fg["s"], fc["s"], abs_tol=LOCATION_ATOL)


def run_cli(*args: str, stdin: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "torchrod", *args], input=stdin, capture_output=True, text=True, timeout=600
    )


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_commands_estimate_on_cuda(rod, gen):
    """``torchrod estimate`` and ``torchrod stream`` with ``--device cuda`` answer as on the CPU."""
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


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_device_that_cannot_be_used_is_refused(rod):
    done = run_cli("stream", "--rod", "nitinol290", "--device", "cuda:99", stdin="")
    assert done.returncode == 2 and "cuda:99" in done.stderr
