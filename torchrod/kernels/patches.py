"""The two places where torchrod steps into Numba's private interfaces to compile its kernels faster, kept here and
applied only to the Numba versions they were checked on (:data:`TESTED`).

Neither changes the compiled arithmetic, so the answers are the same, bit for bit, with or without them: outside
the tested versions the kernels compile as Numba compiles them, only more slowly. :func:`optimised_at_entry`
optimises a compile's whole module once, at its entry, not once per function above each kernel;
:func:`general` compiles a kernel function once for its argument types, not once per constant a caller passes.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any

__all__ = ["TESTED", "general", "optimised_at_entry", "supported"]

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
