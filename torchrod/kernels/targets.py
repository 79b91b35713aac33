"""The one kernel source compiled for each target: ``"python"`` (as written, for debugging), ``"cpu"`` (Numba) and
``"cuda"`` (numba-cuda, one GPU thread per reading).

The kernel modules (:data:`MODULES`) are plain numeric Python: scalars, loops, and arrays passed in. For a compiled
target every function of theirs is rebuilt in one namespace of the target's own (the same code objects, their
global names bound to the target's compiled functions) and decorated for it: ``numba.njit`` for the CPU,
``numba.cuda.jit(device=True)`` for CUDA, each function compiled once, for the types of its arguments (not again
for each constant a caller passes: :func:`.patches.general`). What differs between targets is this thin layer
alone: how a reading's scratch is found (one per CPU thread, reused reading after reading; one per GPU thread, sliced
from batch arrays) and how readings are walked.

Compilation is done once per machine and kept on disk, under a directory named after a digest of the kernel
source and the compiler's version (so a changed kernel or Numba never loads stale code): ``$TORCHROD_CACHE_DIR``,
else ``$XDG_CACHE_HOME/torchrod`` or ``~/.cache/torchrod``. It is announced once on stderr (what compiles, about how
long, where it is kept), and processes that start together take turns through a file lock, so one compiles and
the others load. A cache folder that cannot be written is loaded from when it holds the kernels; a write that fails
(a full disk) leaves no entry behind, is said once, and the kernels are kept in memory for the run (both through
Numba's private interfaces, :mod:`.patches`: with a Numba release outside :data:`.patches.TESTED` such a folder is
not used, the kernels compiled in memory, and a failed write raises Numba's error). A caller
compiles before it starts any clock (:meth:`Compiled.ready`): the time never counts against a reading's budget, and
a cold run answers as a warm one does.

A first compile for the CPU need not hold the first answers back (:meth:`Compiled.start`): it runs in a child
process (announced as above), and meanwhile readings are solved one at a time by the same source run as Python
(``"python"``: far slower, the same arithmetic in the same order), with no deadline, so their answers are the
compiled kernels'. When the child is done the kernels are loaded from the cache and used from the next reading on.
``TORCHROD_COMPILE=foreground`` waits for the compile instead, before the first reading (as :meth:`Compiled.ready`).
Every CPU compile with a writable cache runs in a child process, and the process that waits for it loads the kernels
from the cache, as every later run does: kernels compiled in the process that runs them ran at about half the speed.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import importlib
import os
import signal
import subprocess
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any

from . import patches

MODULES = ("views", "linalg", "march", "precurved", "fit", "scan", "counts", "covariance", "search", "network")
"""The kernel source, in the order its functions are rebuilt (callees before callers)."""

TARGETS = ("python", "cpu", "cuda")

_lock = threading.Lock()

COMPILE_CHILD = (
    "import sys; sys.path.insert(0, sys.argv[2]); from torchrod.kernels import targets; "
    "targets.die_with_parent(int(sys.argv[1])); c = getattr(targets, sys.argv[3])(); c.ready(); "
    "raise SystemExit(targets.UNKEPT if c._unkept else 0)"
)
"""The program of the child process that compiles CPU kernels (arguments: the parent's pid, the folder holding the
parent's ``torchrod`` package, so that the child compiles the same source whatever its import path, and the name of
the function of this module that makes them: ``cpu``, ``cpu_network``, ``cpu_schedule``)."""

UNKEPT = 3
"""The exit status of a compiling child that could not write the kernels into the cache (a full disk, say): it said
so, and its parent compiles them for itself, kept in memory, without trying the cache again."""

_CHILD = "TORCHROD_COMPILING_CHILD"
"""Set in the environment of the child process that compiles CPU kernels (:meth:`Compiled.start`,
:meth:`Compiled.ready`)."""


def _modules() -> list[types.ModuleType]:
    return [importlib.import_module(f"{__package__}.{name}") for name in MODULES]


def namespace(decorate: Any, accessor: Any, inlined: Any, name: str = "", view: Any = None) -> dict[str, Any]:
    """One namespace holding every kernel function rebuilt and decorated (the accessors of :mod:`.views` with
    ``accessor``, the small functions each module lists in its ``INLINE`` with ``inlined``, the rest with ``decorate``),
    and the kernel modules' other globals (constants, named tuples, ``math``). With a ``name``, the namespace is a
    module's of that name (``torchrod.kernels.<name>``, registered in ``sys.modules``, so that Numba's on-disk cache
    finds the functions' globals again in a new process). ``view``: the target's own :func:`.views.view`. Two kernel
    functions of one name, or two different globals of one name, are a mistake of the source: ValueError."""
    modules = _modules()
    functions: dict[str, types.FunctionType] = {}
    for mod in modules:
        for key, value in vars(mod).items():
            if isinstance(value, types.FunctionType) and value.__module__ == mod.__name__ and not key.startswith("__"):
                if key in functions:
                    raise ValueError(f"kernel function {key!r} is defined twice ({mod.__name__})")
                functions[key] = value
    ns: dict[str, Any] = {}
    if name:
        module = types.ModuleType(
            f"{__package__}.{name}", "The kernels rebuilt for one target (torchrod.kernels.targets)."
        )
        sys.modules[module.__name__] = module
        ns = module.__dict__
    for mod in modules:
        for key, value in vars(mod).items():
            if key.startswith("__") or key in functions or key == "INLINE":
                continue
            if key in ns and ns[key] is not value:
                raise ValueError(f"kernel global {key!r} means two things ({mod.__name__})")
            ns[key] = value
    inline = {fn for mod in modules for fn in getattr(mod, "INLINE", ())}
    for key, fn in functions.items():
        rebuilt = types.FunctionType(fn.__code__, ns, fn.__name__, fn.__defaults__, fn.__closure__)
        if key == "view" and view is not None:
            ns[key] = view
        elif fn.__module__.endswith(".views"):
            ns[key] = accessor(rebuilt)
        elif key in inline:
            ns[key] = inlined(rebuilt)
        else:
            ns[key] = decorate(rebuilt)
    return ns


def source_digest(extra: str = "") -> str:
    """A digest of the kernel source and of the compiler, naming the on-disk cache of compiled kernels."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for name in (*MODULES, "status", "layout", "targets", "patches"):
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


LOCK_WAIT = 300.0
"""[s] How long a process waits for another that holds the kernel cache's lock (compiling the kernels into it)
before it compiles them itself without waiting (the cache's own writes are atomic). ``$TORCHROD_LOCK_WAIT``
overrides it; the answers are the same either way."""

LOCK_POLL = 0.2
"""[s] How often a waiting process tries the lock again (and so how soon it answers a signal)."""


def _lock_wait() -> float:
    try:
        return max(0.0, float(os.environ.get("TORCHROD_LOCK_WAIT", LOCK_WAIT)))
    except ValueError:
        return LOCK_WAIT


@contextlib.contextmanager
def _file_lock(path: Path):
    """An exclusive lock on ``path`` between processes (POSIX; elsewhere no lock: the cache's own writes are
    atomic, a second process only compiles too). A lock held by another process is said once on stderr and tried
    again every :data:`LOCK_POLL` seconds (so Ctrl-C and SIGTERM stop the wait), for at most :data:`LOCK_WAIT`
    seconds (a process holding it stopped, by Ctrl-Z say, would hold it for ever): then the work goes on without
    it, and says so."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    try:
        opened = open(path, "a+")
    except OSError:  # (no lock file can be made: a full disk; the work goes on as without POSIX)
        yield
        return
    with opened as handle:
        held = _try_lock(fcntl, handle)
        if not held and _INTERRUPTED:
            _say(f"the kernel cache {path.parent} is locked: after the interrupt, compiling the kernels here")
        elif not held:
            wait = _lock_wait()
            _say(
                f"waiting for another torchrod process that is compiling the kernels into {path.parent} (up to "
                f"{wait:.0f} s; Ctrl-C stops)"
            )
            deadline = time.monotonic() + wait
            try:
                while not held and time.monotonic() < deadline:
                    time.sleep(LOCK_POLL)
                    held = _try_lock(fcntl, handle)
            except BaseException:  # an interrupt: what the run still answers on its way out waits no more
                _interrupted()
                raise
            if not held:
                _say(f"the kernel cache {path.parent} is still locked after {wait:.0f} s: compiling the kernels here")
        try:
            yield
        finally:
            if held:
                fcntl.flock(handle, fcntl.LOCK_UN)


_INTERRUPTED = False
"""Set once the run was interrupted (in a wait for the lock, or :func:`note_interrupt`): no lock is waited for
after that, so the readings a run answers on its way out do not wait either."""


def _interrupted() -> None:
    global _INTERRUPTED
    _INTERRUPTED = True


def _try_lock(fcntl: Any, handle: Any) -> bool:
    """Whether the exclusive lock on ``handle`` was taken now (without waiting)."""
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _say(message: str) -> None:
    """One line on stderr; nothing when there is no stderr (a process started with it closed), never stdout."""
    if sys.stderr is None:
        return
    with contextlib.suppress(OSError, ValueError):
        print(f"torchrod: {message}", file=sys.stderr, flush=True)


_FIRST_GUESS = {
    "cpu-estimation": "one to four minutes",
    "cpu-schedule": "a few seconds",
    "cpu-network": "a few seconds",
    "cuda-estimation": "tens of minutes: NVIDIA's optimiser takes long over the whole search",
}
"""How long a first compile takes (a 2-core machine at the top of each range), before one was timed here."""


def _expected_seconds(root: Path, target: str, what: str) -> str:
    """How long a compile took here last time (a guess before the first)."""
    try:
        seconds = float((root / f"compile-seconds-{target}-{what}").read_text())
        return f"about {seconds:.0f} s, as last time here"
    except (OSError, ValueError):
        return _FIRST_GUESS.get(f"{target}-{what}", "a few minutes")


class Compiled:
    """A target's compiled entry with its on-disk cache (:func:`cpu`, :func:`cuda`); ``what`` it is, for the
    announcement."""

    def __init__(
        self,
        target: str,
        entry: Any,
        directory: Path | None,
        warm: Any,
        what: str = "estimation",
        quiet: bool = False,
        maker: str = "cpu",
        writable: bool = True,
    ) -> None:
        self.target = target
        self.entry = entry
        self.directory = directory
        self.what = what
        self.quiet = quiet  # nothing to announce (the simulator's "compilation" is none)
        self.maker = maker  # the function of this module that makes it (what a compiling child calls)
        self._warm = warm
        self._ready = False
        self._child: subprocess.Popen[bytes] | None = None
        self._tried_child = False  # a compiling child ran to its end: no second one
        self._repaired = False  # a damaged cache entry was removed and compiled again (once)
        self.writable = writable  # False: a read-only cache that holds the kernels, loaded from, never written
        self._unkept = False  # the cache could not be written (or read): the kernels are compiled and kept in memory
        if directory is not None:
            patches.guard_saves(entry, self._unwritten)

    def _unwritten(self, exc: OSError) -> None:
        """Numba's write of the compiled entry into the cache failed (a full disk, a read-only cache), softly
        (:func:`.patches.guard_saves`): what it left is removed (so that a later run finds no entry and announces its
        compile), it is said once, and the kernels compiled are used from memory (:meth:`_in_memory`)."""
        self._in_memory()
        if self.writable:
            self._drop_entry()
        _say(
            f"could not write the {self.what} kernels into the kernel cache {self.directory} "
            f"({exc.strerror or exc}): they are kept in memory for this run; a later run compiles them again"
        )

    def _in_memory(self) -> None:
        """From now on the kernels are compiled here and kept in memory: the cache is neither read nor written
        (:func:`.patches.stop_caching`)."""
        self._unkept = True
        patches.stop_caching(self.entry)

    def _cached(self) -> bool:
        """Whether the entry's compiled code is in the on-disk cache (looked at without the lock)."""
        pattern = f"**/*{self.entry.__name__}*.nbi" if self.target != "cuda" else "**/*.nbi"
        return self.directory is not None and not self._unkept and any(self.directory.glob(pattern))

    def start(self) -> None:
        """Make the kernels usable: loaded now where they are cached; a first CPU compile started in a child process
        (module docstring; :meth:`compiling` says while it runs); otherwise compiled now (:meth:`ready`)."""
        if self._ready or self._child is not None:
            return
        background = os.environ.get("TORCHROD_COMPILE", "background") != "foreground"
        # (Without a writable cache a child's compile would be lost: compiled here.)
        if (
            self.target != "cpu"
            or self.what != "estimation"
            or not background
            or self.directory is None
            or not self.writable
            or self._cached()
        ):
            self.ready()
            return
        with _lock:
            if self._ready or self._child is not None:
                return
            try:
                self._child = self._compiling_child()
            except OSError:
                self._child = None
        if self._child is None:
            self.ready()
        else:
            atexit.register(_finish, self._child)
            _say(
                f"compiling the {self.what} kernels for the CPU in a background process "
                f"({_expected_seconds(cache_root(), self.target, self.what)}; once per machine and version, kept in "
                f"{self.directory}); meanwhile readings are solved one at a time by the kernels run as Python: slower, "
                "the same answers"
            )

    def compiling(self) -> bool:
        """Whether the kernels are still being compiled by the child process :meth:`start` began; once it is done,
        they are loaded (or, should the child have failed, compiled here) before this returns False."""
        child = self._child
        if child is None:
            return False
        if child.poll() is None:
            return True
        if _INTERRUPTED and not self._cached():  # (it ended with the run, without the kernels: none compiled here)
            return True
        with _lock:
            self._child = None
            self._tried_child = True  # (what it left in the cache is loaded; if nothing, compiled here)
            if child.returncode == UNKEPT:
                self._in_memory()
        self.ready()
        return False

    def _compiling_child(self) -> subprocess.Popen[bytes]:
        """A child process that compiles these CPU kernels into the cache (its stderr is this process's)."""
        return subprocess.Popen(
            [sys.executable, "-c", COMPILE_CHILD, str(os.getpid()), str(Path(__file__).parents[2]), self.maker],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            env={**os.environ, _CHILD: "1"},
        )

    def _compile_in_child(self) -> None:
        """A first CPU compile with a writable cache, done by a child process while this one waits (announced
        here), so that this process loads the kernels from the cache as every later run does: the same kernels
        compiled in the process that runs them ran at about half that speed, for the life of the process
        (docs/core.md, Compilation). Should the child fail, or a child have run already (in the background) and
        left nothing, :meth:`ready` compiles here."""
        if (
            self.target != "cpu"
            or self.directory is None
            or not self.writable
            or os.environ.get(_CHILD)
            or self._tried_child
        ):
            return
        if self._cached():  # (looked at last: it reads the cache's directory)
            return
        self._announce()
        self._tried_child = True
        try:
            if self._compiling_child().wait() == UNKEPT:
                self._in_memory()
        except OSError:
            return

    def _announce(self) -> None:
        """Say on stderr that these kernels compile now: about how long, and where they are kept."""
        where = f"kept in {self.directory}" if self.directory is not None else "not kept (no writable cache)"
        if self._unkept:
            where = f"kept in memory: the kernel cache {self.directory} cannot be written"
        _say(
            f"compiling the {self.what} kernels for {'the CPU' if self.target == 'cpu' else 'CUDA'} "
            f"({_expected_seconds(cache_root(), self.target, self.what)}; once per machine and version, {where})"
        )

    def ready(self) -> None:
        """Compile (announced) or load the kernels now, once; processes take turns through the cache's lock. A
        first CPU compile with a writable cache runs in a child process (:meth:`_compile_in_child`), and the
        kernels are then loaded from the cache."""
        if self._ready:
            return
        with _lock:
            if self._ready:
                return
            self._compile_in_child()  # (before the cache's lock is taken here: the child takes it)
            root = cache_root()
            lock: contextlib.AbstractContextManager[Any] = contextlib.nullcontext()
            # The lock is for compiling: kernels already in the cache are loaded without it (the cache's index is
            # written last, and atomically), so a run never waits for another's compile of other kernels.
            if (
                self.directory is not None
                and self.writable
                and not self._unkept
                and not (self._cached() and not self._repaired)
            ):
                lock = _file_lock(self.directory / ".lock")
            damaged = False
            with lock:  # (the cache looked at once the lock is held: another process may just have filled it)
                fresh = not self.quiet and not self._cached()
                if fresh and not os.environ.get(_CHILD):  # (a compiling child's parent announced it)
                    self._announce()
                began = time.perf_counter()
                source = getattr(self.entry, "py_func", self.entry)  # (a Numba dispatcher's Python function)
                at_entry = patches.optimised_at_entry(source.__qualname__) if self.target == "cpu" else None
                try:
                    with at_entry or contextlib.nullcontext():
                        self._warm(self.entry)
                except Exception as exc:
                    # Loading what the cache holds failed: a damaged entry (cut short, overwritten). It is a missing
                    # one: removed, said, and compiled again below, once the cache's lock is free for a child.
                    if fresh or self._repaired or self.directory is None:
                        raise
                    damaged = True
                    if self.writable:
                        self._drop_entry()
                    else:  # (a read-only cache: compiled here, kept in memory)
                        self._in_memory()
                    _say(
                        f"the kernel cache {self.directory} held a damaged copy of the {self.what} kernels "
                        f"({type(exc).__name__}): {'removed' if self.writable else 'not used'}; compiling them again"
                    )
                took = time.perf_counter() - began
                if fresh:
                    _say(f"{self.what} kernels compiled in {took:.0f} s")
                    with contextlib.suppress(OSError):
                        (root / f"compile-seconds-{self.target}-{self.what}").write_text(f"{took:.1f}")
            if damaged:
                self._repaired = True
                self._tried_child = False
            else:
                self._ready = True
        if damaged:
            self.ready()

    def _drop_entry(self) -> None:
        """Remove this entry's files from the on-disk cache (its index and compiled code), whatever they hold."""
        pattern = f"*{self.entry.__name__}*.nb[ic]" if self.target != "cuda" else "*.nb[ic]"
        for path in self.directory.rglob(pattern) if self.directory is not None else ():
            with contextlib.suppress(OSError):
                path.unlink()


def die_with_parent(parent: int) -> None:
    """In a compiling child: end as soon as the process that started it is gone (killed: a parent that exits
    normally waits for the compile first, :meth:`Compiled.start`). A watchdog thread looks every half second. Ctrl-C,
    which a terminal sends to the child too, is the parent's to answer: it stops the child, or waits for it."""
    with contextlib.suppress(ValueError):  # (not the main thread: nothing to ignore it for)
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="torchrod-parent-watch").start()


def _finish(child: subprocess.Popen[bytes]) -> None:
    """At the parent's exit: a compile still running is waited for, so the cache is filled for the next run; after
    an interrupt (:func:`note_interrupt`) it is stopped instead, and said, so that the run ends at once."""
    if child.poll() is not None:
        return
    if _INTERRUPTED:
        with contextlib.suppress(OSError):
            child.terminate()
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                child.kill()
        _say("the kernels' compile stopped with the run; a later run compiles them again")
        return
    _say("finishing the compile of the kernels before exiting (once: later runs load them)")
    with contextlib.suppress(KeyboardInterrupt):
        child.wait()


def note_interrupt() -> None:
    """The run was interrupted (Ctrl-C, SIGTERM) and is answering what it read on its way out: from now on no lock
    of the kernel cache is waited for, and a background compile is stopped at exit instead of waited for."""
    _interrupted()


def note_unsolved(count: int) -> None:
    """Say that a run interrupted while its kernels compile answers the ``count`` readings it read and had not
    solved as unsolved (solving them as Python would take minutes), and stops the compile at exit."""
    _say(
        f"interrupted while the kernels compile: answering the {count} readings read and not yet solved as not "
        "solved, and stopping the compile"
    )


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


def _read_only_directory(target: str, name: str, extra: str = "") -> Path | None:
    """The cache's directory of ``target`` when it cannot be written (:func:`_cache_directory` gave none) but holds
    the compiled entry ``name`` (its index): loaded from as it is, never written
    (:func:`.patches.read_only_cache`)."""
    path = cache_root() / f"kernels-{target}-{source_digest(extra)}"
    try:
        return path if any(path.glob(f"**/*{name}*.nbi")) else None
    except OSError:
        return None


@contextlib.contextmanager
def _numba_cache_dir(path: Path | None):
    """Dispatchers made inside this context keep their cache in ``path`` (Numba reads its CACHE_DIR setting when a
    cached function is made)."""
    import numba

    config: Any = numba.config  # (its settings are made at import: no static attributes)
    old = config.CACHE_DIR
    if path is not None:
        config.CACHE_DIR = str(path)
    try:
        yield
    finally:
        config.CACHE_DIR = old


def view_intrinsic(intrinsic: Any, types: Any, cgutils: Any, arrayobj: Any, imputils: Any) -> Any:
    """:func:`.views.view` as an intrinsic of a Numba target, from that target's own ``intrinsic`` decorator,
    ``types``, ``cgutils``, array and implementation utilities (numba's for the CPU, numba-cuda's for CUDA): the view
    is built from the arena's data pointer, the shape and C-order strides, with no checks and no call."""

    @intrinsic
    def view(typingctx, arena, start, shape):
        if not (isinstance(arena, types.Array) and arena.ndim == 1 and isinstance(shape, types.BaseTuple)):
            return None
        result = arena.copy(ndim=len(shape), layout="C")

        def codegen(context, builder, sig, args):
            arena_type, start_type, shape_type = sig.args
            source = arrayobj.make_array(arena_type)(context, builder, args[0])
            out = arrayobj.make_array(sig.return_type)(context, builder)
            dims = [context.cast(builder, d, t, types.intp)
                    for d, t in zip(cgutils.unpack_tuple(builder, args[2]), shape_type, strict=True)]  # fmt: skip
            strides: list[Any] = []
            step = source.itemsize
            for d in reversed(dims):
                strides.insert(0, step)
                step = builder.mul(step, d)
            first = context.cast(builder, args[1], start_type, types.intp)
            arrayobj.populate_array(out, data=builder.gep(source.data, [first]), shape=dims, strides=strides,
                                    itemsize=source.itemsize, meminfo=source.meminfo, parent=source.parent)  # fmt: skip
            return imputils.impl_ret_borrowed(context, builder, sig.return_type, out._getvalue())

        return result(arena, start, shape), codegen

    return view


@functools.cache
def _cpu_view() -> Any:
    from numba.core import cgutils, imputils, types
    from numba.extending import intrinsic
    from numba.np import arrayobj

    return view_intrinsic(intrinsic, types, cgutils, arrayobj, imputils)


@functools.cache
def _cuda_view() -> Any:
    import importlib

    from numba.cuda import types
    from numba.cuda.core import imputils

    cgutils = importlib.import_module("numba.cuda.cgutils")  # (numba-cuda's own; numba's stubs do not list it)
    from numba.cuda.extending import intrinsic
    from numba.cuda.np import arrayobj

    return view_intrinsic(intrinsic, types, cgutils, arrayobj, imputils)


@functools.cache
def python() -> Compiled:
    """The kernels as written, run by the interpreter (slow; for debugging and for tests of the source)."""
    from . import search

    c = Compiled("python", search.estimate_rows, None, lambda entry: None)
    c._ready = True
    return c


CPU_FLAGS: dict[str, Any] = {"nogil": True}
"""Numba's options for every CPU kernel function and entry, with :func:`.patches.without_reference_counts`. Without the
interpreter lock, so that threads run batches side by side."""


@functools.cache
def _cpu_namespace() -> dict[str, Any]:
    import numba
    from numba.core import types as nb_types

    inner: dict[str, Any] = {
        **CPU_FLAGS,
        **patches.without_reference_counts(),
        "no_cpython_wrapper": True,
        "no_cfunc_wrapper": True,
    }

    def decorate(fn: Any) -> Any:
        return patches.general(numba.njit(**inner)(fn), nb_types.unliteral)

    # The functions a module lists in its INLINE are compiled as the others are: LLVM inlines what it sees fit when it
    # optimises the entry's module (patches.optimised_at_entry). Numba's own inliner would type such a function again
    # at each call site: a longer compile, for code no faster (the same answers either way).
    return namespace(decorate, numba.njit(**inner), decorate, "cpu_kernels", _cpu_view())


def _cpu_entry(name: str, warm: Any, what: str, maker: str) -> Compiled:
    import numba

    directory = _cache_directory("cpu")
    writable = directory is not None
    if directory is None:
        directory = _read_only_directory("cpu", name)
    flags: dict[str, Any] = {**CPU_FLAGS, **patches.without_reference_counts(), "cache": writable}
    with _numba_cache_dir(directory):
        entry = numba.njit(**flags)(_cpu_namespace()[name].py_func)
        if directory is not None and not writable and not patches.read_only_cache(entry):
            directory = None  # (a read-only cache this Numba cannot load from: compiled here, kept in memory)
    return Compiled("cpu", entry, directory, warm, what, maker=maker, writable=writable)


@functools.cache
def cpu() -> Compiled:
    """The kernels compiled by Numba for this CPU: ``entry(first, last, setup, batch, arenas, flag)`` estimates
    readings first..last-1 on one scratch, without the interpreter lock (threads run it side by side)."""
    from .warmup import warm_up

    return _cpu_entry("estimate_rows", lambda e: warm_up("cpu", e), "estimation", "cpu")


@functools.cache
def cpu_schedule() -> Compiled:
    """The simulator's schedule (:func:`.march.schedule_rows`) compiled by Numba for this CPU."""
    from .warmup import warm_up_schedule

    return _cpu_entry("schedule_rows", warm_up_schedule, "schedule", "cpu_schedule")


@functools.cache
def cpu_network() -> Compiled:
    """The warm-start network's forward pass (:func:`.network.network_rows`) compiled by Numba for this CPU."""
    from .warmup import warm_up_network

    return _cpu_entry("network_rows", warm_up_network, "network", "cpu_network")


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

    from .host import simulated
    from .layout import Arenas

    # Inlined by NVVM (forceinline), not by Numba's IR inliner: that one types an inlined function again at every
    # call site, which over this source takes far longer than the compile itself.
    jit: Any = cuda.jit  # (numba's stubs type the simulator's jit, which takes fewer options)
    if simulated():
        inline = decorate = jit(device=True)
    else:
        unliteral = importlib.import_module("numba.cuda.types").unliteral  # (numba-cuda's own type system)

        def general(options: dict[str, Any]) -> Any:
            return lambda fn: patches.general(jit(**options)(fn), unliteral)

        decorate = general({"device": True})
        inline = general({"device": True, "forceinline": True})

    ns = namespace(decorate, inline, inline, "cuda_kernels", None if simulated() else _cuda_view())
    ns.update({"cuda": cuda, "Arenas": Arenas})
    exec(compile(_CUDA_ENTRY, "<torchrod.kernels.targets cuda entry>", "exec"), ns)  # noqa: S102
    return ns


@functools.cache
def cuda() -> Compiled:
    """The kernels compiled by numba-cuda: ``entry[blocks, threads](setup, batch, W, flag, offset, count)``."""
    import numba_cuda  # noqa: F401 - the extra that provides the CUDA target
    from numba import cuda as nb_cuda

    from .host import simulated
    from .warmup import warm_up

    directory = None if simulated() else _cache_directory("cuda", getattr(numba_cuda, "__version__", ""))
    ns = cuda_namespace()
    with _numba_cache_dir(directory):
        entry = nb_cuda.jit(cache=directory is not None)(ns["estimate_kernel"])
    return Compiled("cuda", entry, directory, lambda e: warm_up("cuda", e), quiet=simulated())


def get(target: str) -> Compiled:
    """The compiled kernels of ``target`` (:data:`TARGETS`)."""
    if target == "python":
        return python()
    if target == "cpu":
        return cpu()
    if target == "cuda":
        return cuda()
    raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
