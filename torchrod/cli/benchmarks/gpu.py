"""``torchrod bench gpu``: the CUDA kernels in one run: their compilation, the CUDA tests, and readings per second.

1. **Lowering** (no GPU needed: ``pip install "torchrod[cuda]"``): the whole estimation kernel typed for CUDA and
   lowered to NVVM IR for ``--arch`` (default sm_90, the H100 and H200), timed. With ``--ptx``, also compiled to
   PTX by NVIDIA's optimiser (tens of minutes or more over the whole search) and, where ``ptxas`` is found (the pip
   CUDA compiler ships it), the registers and the stack each thread uses: what limits how many readings an SM
   holds at once.
2. **Tests** (a GPU): ``pytest -m cuda tests/test_cuda.py``, where the tests are (a source checkout): the estimator,
   its network, the stream and the commands on the GPU against their CPU twins.
3. **Throughput** (a GPU): readings per second at batches of 2^14 to 2^20 (``--sizes``) in float64 by both GPU
   paths: the torch target (the GPU default: the shipped network's guesses refined in torch, judged by the CPU
   kernels) and then the CUDA kernel target (one GPU thread per reading; its compile timed, ``--skip-kernels``
   leaves it out), each against the CPU kernels on every core on a slice of the same readings: readings of 1 to 3
   forces of ``torchrod bench estimate``'s envelope, noise 0.1 1/m (given), tiled from a few thousand simulated
   ones.

Each part is skipped, with a line saying why, where it cannot run; the run prints as it goes, so a run cut short
still reports what it did.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from . import SUITES

HELP = SUITES["gpu"]

__all__ = ["HELP", "configure", "lowering_seconds", "ptx_report", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--arch", default="sm_90", help="the GPU architecture of the PTX (default sm_90)")
    parser.add_argument(
        "--sizes", default="14,16,18,20", metavar="K,...", help="batches of 2^K readings (default 14,16,18,20)"
    )
    parser.add_argument("--skip-kernels", action="store_true", help="the torch target only: no CUDA kernel compile")
    parser.add_argument("--skip-tests", action="store_true", help="no CUDA tests")
    parser.add_argument("--ptx", action="store_true", help="also compile PTX and count registers (tens of minutes)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: the lowering and a batch of 2^10")


@contextlib.contextmanager
def _no_device(cc: tuple[int, int]):
    """numba-cuda asks the current device for its compute capability when it compiles a device function; without a
    GPU (or to compile for another one) it is told ``cc`` instead."""
    import numba.cuda.dispatcher as dispatcher

    class _Device:
        compute_capability = cc

    saved = dispatcher.get_current_device
    dispatcher.get_current_device = lambda: _Device()
    try:
        yield
    finally:
        dispatcher.get_current_device = saved


def _kernel_signature(arch: str) -> tuple[tuple[int, int], tuple[Any, ...]]:
    """The compute capability of ``arch`` (sm_90: (9, 0)) and the estimation kernel's argument types."""
    import numba

    from ...kernels import layout, warmup

    match = re.fullmatch(r"sm_(\d)(\d+)", arch)
    if match is None:
        raise ValueError(f"--arch must look like sm_90, got {arch!r}")
    setup, sizes = warmup.tiny_setup()
    batch = warmup.tiny_batch()
    arenas = layout.allocate(sizes, (1,))
    types = tuple(numba.typeof(x) for x in (setup, batch, arenas))
    signature = (*types, numba.typeof(batch.noise2[:1].astype("int64")), numba.int64, numba.int64)
    return (int(match.group(1)), int(match.group(2))), signature


def lowering_seconds(arch: str = "sm_90") -> float:
    """Type the whole estimation kernel for CUDA and lower it to NVVM IR for ``arch`` (everything numba-cuda does
    before NVIDIA's optimiser), in seconds: every line of the kernel source is then proven valid CUDA device code,
    without a GPU and in far less time than the optimiser takes. Numba's typing or lowering errors propagate."""
    import numba
    from numba.cuda.compiler import compile_cuda

    from ...kernels import targets

    cc, signature = _kernel_signature(arch)
    began = time.perf_counter()
    with _no_device(cc):
        compile_cuda(targets.cuda_namespace()["estimate_kernel"], numba.types.void, signature, cc=cc)
    return time.perf_counter() - began


def ptx_report(arch: str = "sm_90") -> dict[str, Any]:
    """The estimation kernel as PTX for ``arch``: {"ptx_bytes", "seconds", and where ptxas runs, "registers",
    "stack_bytes", "spill_bytes"}; ``RuntimeError`` saying why where the CUDA compiler is missing. NVIDIA's
    optimiser (NVVM) takes long over the whole search: tens of minutes or more on a small machine."""
    from numba import cuda

    from ...kernels import targets

    cc, signature = _kernel_signature(arch)
    began = time.perf_counter()
    with _no_device(cc):
        try:
            ptx, _ = cuda.compile_ptx(targets.cuda_namespace()["estimate_kernel"], signature, cc=cc)
        except Exception as exc:  # noqa: BLE001 - a missing libNVVM shows up in several exception types
            raise RuntimeError(f"no CUDA compiler here ({type(exc).__name__}: {str(exc)[:200]})") from None
    out: dict[str, Any] = {"ptx_bytes": len(ptx), "seconds": time.perf_counter() - began}
    ptxas = _ptxas()
    if ptxas is not None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "estimate.ptx"
            path.write_text(ptx)
            done = subprocess.run(
                [ptxas, f"-arch={arch}", "-v", str(path), "-o", str(Path(tmp) / "estimate.cubin")],
                capture_output=True,
                text=True,
                check=False,
            )
        text = done.stdout + done.stderr
        for key, pattern in (
            ("registers", r"Used (\d+) registers"),
            ("stack_bytes", r"(\d+) bytes stack frame"),
            ("spill_bytes", r"(\d+) bytes spill stores"),
        ):
            found = re.findall(pattern, text)
            if found:
                out[key] = max(int(x) for x in found)
        if done.returncode != 0:
            out["ptxas_error"] = text.strip()[-300:]
    return out


def _ptxas() -> str | None:
    """ptxas on the PATH, or the one the pip CUDA compiler installs."""
    found = shutil.which("ptxas")
    if found:
        return found
    with contextlib.suppress(ImportError):
        import nvidia.cuda_nvcc  # type: ignore[import-not-found]

        for base in nvidia.cuda_nvcc.__path__:
            candidate = Path(base) / "bin" / "ptxas"
            if candidate.exists():
                return str(candidate)
    return None


def _readings(count: int) -> tuple[Any, Any]:
    """The nitinol290 preset and ``count`` readings of 1 to 3 forces of ``torchrod bench estimate``'s envelope."""
    from ...presets import nitinol290
    from .estimate import readings

    rod = nitinol290()
    return rod, readings(rod, None, count, 0.1, 0)


def run(args: argparse.Namespace) -> int:
    import torch

    print(f"# torchrod bench gpu: torch {torch.__version__}, CUDA available: {torch.cuda.is_available()}", flush=True)
    _ptx(args)
    if not torch.cuda.is_available():
        print("tests and throughput: skipped: torch sees no CUDA device", flush=True)
        return 0
    tests = Path(__file__).resolve().parents[3] / "tests" / "test_cuda.py"
    if args.skip_tests:
        print("tests: skipped (--skip-tests)", flush=True)
    elif not tests.exists():
        print(f"tests: skipped: {tests} not found (run from a source checkout)", flush=True)
    else:
        began = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-m", "cuda", str(tests)], cwd=tests.parents[1], check=False
        )
        print(f"tests: exit status {done.returncode} in {time.perf_counter() - began:.0f} s", flush=True)
    _throughput(args)
    return 0


def _ptx(args: argparse.Namespace) -> None:
    """The lowering, and with ``--ptx`` the PTX: its size, and the registers, stack and spills per thread where
    ptxas runs."""
    try:
        print(f"lowering: the estimation kernel typed and lowered for {args.arch} in "
              f"{lowering_seconds(args.arch):.0f} s", flush=True)  # fmt: skip
    except ImportError as exc:
        print(f"lowering: skipped: {exc}", flush=True)
        return
    if not args.ptx:
        print("PTX: skipped (without --ptx)", flush=True)
        return
    try:
        report = ptx_report(args.arch)
    except (RuntimeError, ImportError) as exc:
        print(f"PTX: skipped: {exc}", flush=True)
        return
    parts = [f"{report['ptx_bytes']} bytes of PTX for {args.arch} in {report['seconds']:.0f} s"]
    if "registers" in report:
        parts.append(
            f"{report['registers']} registers, {report.get('stack_bytes', 0)} bytes of stack and "
            f"{report.get('spill_bytes', 0)} bytes of spill stores per thread (ptxas)"
        )
    else:
        parts.append("ptxas not found: no register count")
    print("PTX: " + "; ".join(parts), flush=True)


def _throughput(args: argparse.Namespace) -> None:
    """Readings per second on the GPU by both paths: the torch target (the shipped network's guesses refined in
    torch, judged by the CPU kernels; the GPU default) first, then the CUDA kernel target, whose compile is timed;
    each beside the CPU kernels on the same readings."""
    import torch

    from ...estimate.estimator import Estimator, EstimatorOptions
    from ...kernels.host import cpu_threads
    from ...learn.warm_start import SHIPPED_CHECKPOINT, load_estimator

    sizes = [10] if args.quick else [int(k) for k in args.sizes.split(",")]
    rod, data = _readings(4096)
    device = torch.device("cuda")
    print(f"# {torch.cuda.get_device_name(device)}; float64; noise 0.1 1/m given; counts 0..3", flush=True)
    gpu_u, gpu_m = data.curvature.to(device), data.mask.to(device)
    cpu_est = Estimator(rod, EstimatorOptions(noise=0.1, target="cpu"))
    cpu_n = 4096
    cpu_est.estimate(data.curvature[:2], data.mask[:2])
    t0 = time.perf_counter()
    want = cpu_est.estimate(data.curvature[:cpu_n], data.mask[:cpu_n])
    cpu = cpu_n / (time.perf_counter() - t0)
    print(f"CPU kernels, {cpu_threads(None)} threads: {cpu:,.0f} readings/s over {cpu_n} readings", flush=True)
    on_torch = load_estimator(SHIPPED_CHECKPOINT, rod, EstimatorOptions(noise=0.1, target="torch"), warn=print)
    on_torch.estimate(gpu_u[:64], gpu_m[:64])  # the network's trace and the CPU kernels, before the clock
    _sizes(on_torch, "torch target", sizes, gpu_u, gpu_m, want, cpu)
    if args.skip_kernels:
        print("CUDA kernel target: skipped (--skip-kernels)", flush=True)
        return
    est = Estimator(rod, EstimatorOptions(noise=0.1, target="cuda"))
    t0 = time.perf_counter()
    est.estimate(gpu_u[:64], gpu_m[:64])  # compiled (announced) or loaded, before the clock
    print(f"CUDA kernel target: compiled or loaded in {time.perf_counter() - t0:.0f} s", flush=True)
    _sizes(est, "CUDA kernels", sizes, gpu_u, gpu_m, want, cpu)
    with contextlib.suppress(Exception):
        free, total = torch.cuda.mem_get_info(device)
        print(f"GPU memory in use at the end: {(total - free) / 2**30:.1f} of {total / 2**30:.1f} GiB", flush=True)


def _sizes(est: Any, name: str, sizes: list[int], gpu_u: Any, gpu_m: Any, want: Any, cpu: float) -> None:
    """One line per batch of 2^k readings (the readings tiled): readings per second, against the CPU kernels', and
    the share of the first readings given the CPU kernels' count."""
    import torch

    n = want.num_forces.shape[0]
    for k in sizes:
        B = 1 << k
        reps = (B + gpu_u.shape[0] - 1) // gpu_u.shape[0]
        u = gpu_u.repeat(reps, 1, 1)[:B].contiguous()
        m = gpu_m.repeat(reps, 1)[:B].contiguous()
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        res = est.estimate(u, m)
        torch.cuda.synchronize()
        wall = time.perf_counter() - t0
        first = min(B, n)
        same = float((res.num_forces[:first].cpu() == want.num_forces[:first]).float().mean())
        print(
            f"{name}, B = 2^{k} = {B}: {B / wall:,.0f} readings/s ({wall:.2f} s; {B / wall / cpu:.1f}x the CPU "
            f"kernels); the CPU kernels' count on {100 * same:.1f}% of the first {first} readings",
            flush=True,
        )
