"""The one kernel source compiled for each target: ``"python"`` (as written, for debugging), ``"cpu"`` (Numba) and
``"cuda"`` (numba-cuda, one GPU thread per reading).

The kernel modules (:data:`MODULES`) are plain numeric Python: scalars, loops, and arrays passed in. For a compiled
target every function of theirs is rebuilt in one namespace of the target's own (the same code objects, their
global names bound to the target's compiled functions) and decorated for it: ``numba.njit`` for the CPU,
``numba.cuda.jit(device=True)`` for CUDA. What differs between targets is this thin layer alone: how a reading's
scratch is found (one per CPU thread, reused reading after reading; one per GPU thread, sliced from batch arrays)
and how readings are walked.

Compilation is done once per machine and kept on disk, under a directory named after a digest of the kernel
source and the compiler's version (so a changed kernel or Numba never loads stale code): ``$TORCHROD_CACHE_DIR``,
else ``$XDG_CACHE_HOME/torchrod`` or ``~/.cache/torchrod``. It is announced once on stderr (what compiles, about how
long, where it is kept), and processes that start together take turns through a file lock, so one compiles and
the others load. A caller compiles before it starts any clock (:func:`ready`): the time never counts against a
reading's budget, and a cold run answers as a warm one does.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib
import os
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any

MODULES = ("views", "linalg", "march", "precurved", "fit", "scan", "counts", "covariance", "search")
"""The kernel source, in the order its functions are rebuilt (callees before callers)."""

TARGETS = ("python", "cpu", "cuda")

_lock = threading.Lock()


def _modules() -> list[types.ModuleType]:
    return [importlib.import_module(f"{__package__}.{name}") for name in MODULES]


def namespace(decorate: Any, accessor: Any) -> dict[str, Any]:
    """One namespace holding every kernel function rebuilt and decorated (the accessors of :mod:`.views` with
    ``accessor``, to be inlined where called; the rest with ``decorate``), and the kernel modules' other globals
    (constants, named tuples, ``math``). Two kernel functions of one name, or two different globals of one name,
    are a mistake of the source: ValueError."""
    modules = _modules()
    functions: dict[str, types.FunctionType] = {}
    for mod in modules:
        for name, value in vars(mod).items():
            if isinstance(value, types.FunctionType) and value.__module__ == mod.__name__:
                if name in functions:
                    raise ValueError(f"kernel function {name!r} is defined twice ({mod.__name__})")
                functions[name] = value
    ns: dict[str, Any] = {}
    for mod in modules:
        for name, value in vars(mod).items():
            if name.startswith("__") or name in functions:
                continue
            if name in ns and ns[name] is not value:
                raise ValueError(f"kernel global {name!r} means two things ({mod.__name__})")
            ns[name] = value
    for name, fn in functions.items():
        rebuilt = types.FunctionType(fn.__code__, ns, fn.__name__, fn.__defaults__, fn.__closure__)
        ns[name] = (accessor if fn.__module__.endswith(".views") else decorate)(rebuilt)
    return ns


def source_digest(extra: str = "") -> str:
    """A digest of the kernel source and of the compiler, naming the on-disk cache of compiled kernels."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for name in (*MODULES, "layout", "targets"):
        h.update((here / f"{name}.py").read_bytes())
    import numba

    h.update(f"numba {numba.__version__} python {sys.version_info[:2]} {extra}".encode())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """Where compiled kernels are kept (module docstring)."""
    given = os.environ.get("TORCHROD_CACHE_DIR")
    if given:
        return Path(given)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchrod"


@contextlib.contextmanager
def _file_lock(path: Path):
    """An exclusive lock on ``path`` between processes (POSIX; elsewhere no lock: the cache's own writes are
    atomic, a second process only compiles too)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with open(path, "a+") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _say(message: str) -> None:
    print(f"torchrod: {message}", file=sys.stderr, flush=True)


def _expected_seconds(root: Path, target: str) -> str:
    """How long a compile took here last time (a guess before the first)."""
    try:
        seconds = float((root / f"compile-seconds-{target}").read_text())
        return f"about {seconds:.0f} s, as last time here"
    except (OSError, ValueError):
        return "about a minute"


class Compiled:
    """A target's compiled entry with its on-disk cache (:func:`cpu`, :func:`cuda`)."""

    def __init__(self, target: str, entry: Any, directory: Path | None, warm: Any) -> None:
        self.target = target
        self.entry = entry
        self.directory = directory
        self._warm = warm
        self._ready = False

    def ready(self) -> None:
        """Compile (announced) or load the kernels now, once; processes take turns through the cache's lock."""
        if self._ready:
            return
        with _lock:
            if self._ready:
                return
            root = cache_root()
            fresh = self.directory is None or not any(self.directory.glob("**/*.nbi"))
            lock = contextlib.nullcontext()
            if self.directory is not None:
                lock = _file_lock(self.directory / ".lock")
            with lock:
                if self.directory is not None:
                    fresh = not any(self.directory.glob("**/*.nbi"))
                where = f"kept in {self.directory}" if self.directory is not None else "not kept (no writable cache)"
                if fresh:
                    _say(
                        f"compiling the estimation kernels for the {self.target.upper()} "
                        f"({_expected_seconds(root, self.target)}; once per machine and version, {where})"
                    )
                began = time.perf_counter()
                self._warm(self.entry)
                took = time.perf_counter() - began
                if fresh:
                    _say(f"kernels compiled in {took:.0f} s")
                    with contextlib.suppress(OSError):
                        (root / f"compile-seconds-{self.target}").write_text(f"{took:.1f}")
            self._ready = True


def _cache_directory(target: str, extra: str = "") -> Path | None:
    path = cache_root() / f"kernels-{target}-{source_digest(extra)}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".probe"
        probe.write_text("")
        probe.unlink()
    except OSError:
        return None
    return path


@contextlib.contextmanager
def _numba_cache_dir(path: Path | None):
    """Dispatchers made inside this context keep their cache in ``path`` (Numba reads its CACHE_DIR setting when a
    cached function is made)."""
    import numba

    old = numba.config.CACHE_DIR
    if path is not None:
        numba.config.CACHE_DIR = str(path)
    try:
        yield
    finally:
        numba.config.CACHE_DIR = old


@functools.cache
def python() -> Compiled:
    """The kernels as written, run by the interpreter (slow; for debugging and for tests of the source)."""
    from . import search

    c = Compiled("python", search.estimate_rows, None, lambda entry: None)
    c._ready = True
    return c


@functools.cache
def cpu() -> Compiled:
    """The kernels compiled by Numba for this CPU: ``entry(first, last, setup, batch, work, flag)`` estimates
    readings first..last-1 on one scratch, without the interpreter lock (threads run it side by side)."""
    import numba

    from .warmup import warm_up

    directory = _cache_directory("cpu")
    inner = {"nogil": True, "no_cpython_wrapper": True, "no_cfunc_wrapper": True}
    ns = namespace(numba.njit(**inner), numba.njit(**inner))
    with _numba_cache_dir(directory):
        entry = numba.njit(nogil=True, cache=directory is not None)(ns["estimate_rows"].py_func)
    return Compiled("cpu", entry, directory, lambda e: warm_up("cpu", e))


_CUDA_ENTRY = """
def estimate_kernel(setup, batch, arenas, flag, offset, count):
    t = cuda.grid(1)
    if t < count:
        mine = Arenas(arenas.f[t], arenas.i[t], arenas.c[t], arenas.b[t], arenas.info[t])
        estimate_one(offset + t, setup, batch, mine, flag)
"""


def cuda_namespace() -> dict[str, Any]:
    """The kernels as CUDA device functions, and the entry ``estimate_kernel(setup, batch, arenas, flag, offset,
    count)``: GPU thread t estimates reading offset + t on row t of the arenas (not yet compiled: the caller jits it,
    or compiles it to PTX)."""
    from numba import cuda

    from .layout import Arenas

    ns = namespace(cuda.jit(device=True), cuda.jit(device=True, inline="always"))
    ns.update({"cuda": cuda, "Arenas": Arenas})
    exec(compile(_CUDA_ENTRY, "<torchrod.kernels.targets cuda entry>", "exec"), ns)  # noqa: S102
    return ns


@functools.cache
def cuda() -> Compiled:
    """The kernels compiled by numba-cuda: ``entry[blocks, threads](setup, batch, W, flag, offset, count)``."""
    import numba_cuda  # noqa: F401 - the extra that provides the CUDA target
    from numba import cuda as nb_cuda

    from .warmup import warm_up

    directory = _cache_directory("cuda", getattr(numba_cuda, "__version__", ""))
    ns = cuda_namespace()
    with _numba_cache_dir(directory):
        entry = nb_cuda.jit(cache=directory is not None)(ns["estimate_kernel"])
    return Compiled("cuda", entry, directory, lambda e: warm_up("cuda", e))


def get(target: str) -> Compiled:
    """The compiled kernels of ``target`` (:data:`TARGETS`)."""
    if target == "python":
        return python()
    if target == "cpu":
        return cpu()
    if target == "cuda":
        return cuda()
    raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
