"""Named views of a reading's arenas: one accessor per group of :data:`.layout.SPEC` (``rows_of(k)``,
``lm_of(k)``, ...), returning a named tuple of views into the arenas of the :class:`.layout.Kit` ``k``.

The accessors are made from the description in :mod:`.layout` when this module is imported (each a few
:func:`view` calls, inlined where they are called on a compiled target), so the description is the only place the
arenas' parts are listed.
"""

from collections import namedtuple
from typing import Any

from .layout import SPEC

ARENA = {"f": "k.f", "i": "k.i", "c": "k.c", "b": "k.b", "k": "k.const"}

GROUP_TYPES: dict[str, Any] = {
    group: namedtuple(group.capitalize() + "View", list(parts)) for group, parts in SPEC.items()
}
"""The named tuple of each group's views."""


def view(arena, start, shape):
    """The part of the 1-D ``arena`` from ``start`` as a C-contiguous array of ``shape`` (a tuple). Compiled targets
    replace this with an intrinsic of their own (:mod:`.targets`) that builds the view directly: no size checks
    (the layout is known good), so little code to compile at each of its many uses."""
    size = 1
    for d in shape:
        size *= d
    return arena[start : start + size].reshape(shape)


def _accessor_source(group: str, parts: dict) -> str:
    items = []
    for name, (shape, kind) in parts.items():
        dims = [f"L.{x}" if isinstance(x, str) else str(x) for x in shape]
        items.append(f"view({ARENA[kind]}, L.{group}_{name}, ({', '.join(dims)},))")
    return (
        f"def {group}_of(k):\n"
        f'    """The {group} part of the arenas, as named views."""\n'
        "    L = k.lay\n"
        f"    return {group.capitalize()}View({', '.join(items)})\n"
    )


for _group in SPEC:
    globals()[f"{_group.capitalize()}View"] = GROUP_TYPES[_group]
    exec(compile(_accessor_source(_group, SPEC[_group]), f"<torchrod.kernels.views {_group}_of>", "exec"), globals())
del _group


def __getattr__(name: str) -> Any:
    # The accessors above exist once this module has run; this tells static checkers that names they cannot see
    # (made by ``exec``) are there, and is only reached for a name that really is missing.
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
