"""The places where torchrod steps into Numba's private interfaces, kept here and applied only to the Numba versions
they were checked on (:data:`TESTED`); outside them each does nothing, or gives nothing, as its docstring says.

None changes the compiled arithmetic, so the answers are the same, bit for bit, with or without them.
Two make the first compile faster (outside the tested versions the kernels compile as Numba compiles them, only more
slowly): :func:`optimised_at_entry` optimises a compile's whole module once, at its entry, not once per function
above each kernel; :func:`general` compiles a kernel function once for its argument types, not once per constant a
caller passes. :func:`without_reference_counts` gives the CPU option that leaves reference counting out of the
kernels (outside: counted, slower). Three concern the on-disk cache of compiled kernels (outside: Numba's own cache,
or none): :func:`guard_saves` makes a write that fails (a full disk) fail softly, :func:`stop_caching` turns a
dispatcher's cache off, and :func:`read_only_cache` loads kernels from a folder that cannot be written.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import Any

__all__ = [
    "TESTED",
    "general",
    "guard_saves",
    "optimised_at_entry",
    "read_only_cache",
    "stop_caching",
    "supported",
    "without_reference_counts",
]

TESTED = ((0, 59), (0, 68))
"""The oldest and newest Numba releases (major, minor) the patches were checked on, both included."""


@functools.cache
def supported() -> bool:
    """Whether the installed Numba's release lies within :data:`TESTED`."""
    import numba

    try:
        release = tuple(int(x) for x in numba.__version__.split(".")[:2])
    except ValueError:  # a development build's version: not checked
        return False
    return TESTED[0] <= release <= TESTED[1]


@contextlib.contextmanager
def optimised_at_entry(entry: str):
    """Numba's CPU compiles made inside this context optimise their whole module only for the entry ``entry`` (a
    function's qualified name), once, not for every kernel function it calls.

    Numba compiles each function called by another into a library of its own, links into it the libraries of the
    functions it calls, and optimises the result (inlining across the functions, the loop passes) before the caller
    links it in again and optimises its own module anew: the code of a kernel deep in the search is optimised once
    per function above it, most of a first compile's time in LLVM. Here each function's own code is still optimised
    when it is made (Numba's function passes), and the whole search once, in the entry's module, which inlines and
    optimises across every function as before: the machine code runs at least as fast, and its arithmetic is the same
    (no fast-math: LLVM keeps every IEEE operation), so the answers are the same, bit for bit. The functions compiled
    here are the kernels' callees, called only from compiled code, which links them into a caller's module.

    Holds Numba's compiler lock, so that no other thread's compile runs with the change. With a Numba outside
    :data:`TESTED`, or without the internal it relies on, compiles as Numba does."""
    if not supported():
        yield
        return
    try:
        from numba.core import codegen
        from numba.core.compiler_lock import global_compiler_lock

        library: Any = codegen.CPUCodeLibrary  # (a method replaced for the while: typed loosely)
        optimise = library._optimize_final_module
    except (ImportError, AttributeError):  # pragma: no cover - another Numba: its own way
        yield
        return

    def at_entry_only(lib: Any) -> None:
        if lib.name == entry:
            optimise(lib)

    with global_compiler_lock:
        library._optimize_final_module = at_entry_only
        try:
            yield
        finally:
            library._optimize_final_module = optimise


def general(dispatcher: Any, unliteral: Any) -> Any:
    """``dispatcher`` (a compiled kernel function) made to be compiled for the types of its arguments, not for the
    constants a caller passes (``unliteral``: the target's map from a constant's type to its plain type), and
    returned. Numba would otherwise compile a function, and everything it calls, once more for each constant (a flag
    given as ``True`` in one place and ``False`` in another, a count given as ``0``): a large share of the first
    compile, for no faster code. The compiled arithmetic is the same, and so are the answers, bit for bit. (Set on
    the one dispatcher, which the compiler asks for the signature of a call: its class and all else stay Numba's.)
    With a Numba outside :data:`TESTED`, the dispatcher as it is."""
    if not supported():
        return dispatcher
    by_constants = dispatcher.get_call_template

    def get_call_template(args: Any, kws: Any) -> Any:
        return by_constants([unliteral(a) for a in args], {k: unliteral(v) for k, v in kws.items()})

    dispatcher.get_call_template = get_call_template
    return dispatcher


def without_reference_counts() -> dict[str, Any]:
    """Numba's options that compile a CPU function without reference counting (``_nrt``, an option Numba keeps for
    itself), for kernels that allocate nothing and see only arrays their caller owns for the whole call: counted, each
    view made and each array passed between kernel functions costs an atomic increment and decrement, about half of a
    reading's time, and threads sharing one array contend for its count. With a Numba outside :data:`TESTED`, no
    options: the kernels are counted, as Numba compiles them, and slower, to the same answers."""
    return {"_nrt": False} if supported() else {}


def guard_saves(dispatcher: Any, failed: Callable[[OSError], None]) -> bool:
    """Numba's write of ``dispatcher``'s compiled code into its on-disk cache made to fail softly: an OSError it
    raises (a full disk, a read-only folder) is handed to ``failed``, and the compile's code is used from memory where
    Numba would raise the error from the compile. Returns whether the write is guarded. With a Numba outside
    :data:`TESTED`, or a dispatcher without such a cache, False and the dispatcher as it is: a write that fails raises
    from the compile, as Numba's does (a folder that cannot be written is then no cache at all, and the kernels
    compile in memory: :func:`read_only_cache`)."""
    if not supported():
        return False
    cache: Any = getattr(dispatcher, "_cache", None)
    save = getattr(cache, "save_overload", None)
    if save is None:
        return False

    def guarded(sig: Any, data: Any) -> None:
        try:
            save(sig, data)
        except OSError as exc:
            failed(exc)

    cache.save_overload = guarded
    return True


def stop_caching(dispatcher: Any) -> bool:
    """``dispatcher``'s on-disk cache turned off: its later compiles neither load from it nor write into it (Numba
    offers no public way back from ``cache=True``), for kernels kept in memory once the cache failed them (a write
    that failed, a damaged entry in a read-only cache). Returns whether it was turned off. With a Numba outside
    :data:`TESTED`, or a dispatcher without such a cache, False and the cache as it is; with such a Numba neither
    :func:`guard_saves` nor :func:`read_only_cache` acts, so no failure they report asks for this."""
    if not supported():
        return False
    disable = getattr(getattr(dispatcher, "_cache", None), "disable", None)
    if disable is None:
        return False
    disable()
    return True


def read_only_cache(dispatcher: Any) -> bool:
    """``dispatcher`` (made without a cache) given Numba's on-disk cache in the folder ``numba.config.CACHE_DIR``
    names now, the same files a writable cache holds, for a folder that cannot be written: what it holds is loaded,
    and a write fails (:func:`guard_saves`). Numba's own cache finds no place for a function in such a folder (it
    cannot write a probe file there), and compiles it again in every run. Returns whether it was given. With a Numba
    outside :data:`TESTED`, or without the internals it relies on, False and the dispatcher as it is: the folder is
    not used, and the kernels compile in memory."""
    if not supported():
        return False
    try:
        from numba.core import caching

        class Locator(caching.UserProvidedCacheLocator):
            def ensure_cache_path(self) -> None:  # (read from: nothing to make, nothing to probe)
                pass

        class Impl(caching.CompileResultCacheImpl):
            _locator_classes = [Locator]

        class ReadOnlyCache(caching.FunctionCache):
            _impl_class = Impl

        dispatcher._cache = ReadOnlyCache(dispatcher.py_func)
    except (ImportError, AttributeError):  # pragma: no cover - another Numba: its own way
        return False
    return True
