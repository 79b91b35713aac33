"""Named views of a reading's arenas: one accessor per group of :data:`.layout.SPEC` (``rows_of(k)``,
``lm_of(k)``, ...), returning a named tuple of views into the arenas of the :class:`.layout.Kit` ``k``.

The accessors are made from the description in :mod:`.layout` when this module is imported (each a few slices and
reshapes, inlined where they are called on a compiled target), so the description is the only place the arenas'
parts are listed.
"""

from collections import namedtuple

from .layout import SPEC

ARENA = {"f": "k.f", "i": "k.i", "c": "k.c", "b": "k.b", "k": "k.const"}

GROUP_TYPES = {group: namedtuple(group.capitalize() + "View", list(parts)) for group, parts in SPEC.items()}
"""The named tuple of each group's views."""


def _accessor_source(group: str, parts: dict) -> str:
    items = []
    for name, (shape, kind) in parts.items():
        dims = [f"L.{x}" if isinstance(x, str) else str(x) for x in shape]
        start = f"L.{group}_{name}"
        size = " * ".join(dims)
        view = f"{ARENA[kind]}[{start}:{start} + {size}]"
        if len(dims) > 1:
            view += f".reshape(({', '.join(dims)}))"
        items.append(view)
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
