"""The kernels' data: named records for the settings, and one reading's scratch in a few arenas whose named parts
each kernel module declares beside the functions that own them (its ``*_PARTS``) and that are placed in the arenas
here (:data:`SPEC`), so that every target allocates them alike and every kernel function reads them by name.

Records (NumPy structured arrays, read as ``k.rod.length``):

* :data:`ROD`: the rod and its models' accuracy settings;
* :data:`OPTIONS`: the estimator's options, flattened (:class:`torchrod.EstimatorOptions` fills it);
* :data:`INFO`: one reading's own numbers while it is estimated (its intervals, noise, evaluations, whether its
  search was cut);
* :data:`LAYOUT`: the sizes of the problem and where each named part of the arenas starts.

A reading's scratch is four arenas (float64, int64, complex128, bool), and the constants it reads (the grating
positions, the exact model's tableau, the count tests' quantiles) one float64 arena. A kernel function takes a small
:class:`Kit` (the records, the arenas) and makes the views it needs with the accessors of :mod:`.views` (``rows =
rows_of(k)``, then ``rows.loss[i]``): passed between functions, a few arenas cost the compiler far less than a
tuple of a hundred arrays would. The accessors and their type stub are generated from :data:`SPEC` by ``python -m
torchrod.kernels.layout`` (:func:`render_views`, :func:`render_stub`).
"""

from collections import namedtuple

import numpy as np

from .counts import COUNTS_PARTS
from .covariance import COVARIANCE_PARTS
from .fit import FIT_PARTS
from .march import MARCH_PARTS
from .precurved import PRECURVED_PARTS
from .scan import SCAN_PARTS
from .search import SEARCH_PARTS
from .views import Kit  # noqa: F401 - generated beside the accessors that read it; the host makes it from here

ROD = np.dtype(
    [
        ("length", np.float64),  # L [m]
        ("ei", np.float64),  # EI [N m^2]
        ("gj", np.float64),  # GJ [N m^2] (precurved rods)
        ("force_unit", np.float64),  # F = EI / L^2 [N]
        ("bias", np.float64),  # the location bias added to reported locations [m]
        ("num_gratings", np.int64),
        ("precurved", np.bool_),
        ("nseg", np.int64),  # intrinsic-curvature segments
        ("nextra", np.int64),  # events besides forces and queries (the base and the segment ends)
        ("step_angle", np.float64),  # the fitting model's bound on (rate) x (step)
        ("max_steps", np.int64),  # the fitting model's most steps per segment
        ("exact_angle", np.float64),  # the exact model's
        ("exact_max_steps", np.int64),
    ],
    align=True,  # CUDA reads only aligned fields
)

OPTIONS = np.dtype(
    [
        ("max_forces", np.int64),  # H: the rows hold counts 0..H (a fixed count's H is one more, for its escape)
        ("fixed", np.int64),  # the fixed count, or -1: chosen
        ("min_dof", np.int64),  # a count leaving fewer degrees of freedom is never chosen (counts.testable)
        ("starts", np.int64),
        ("settle", np.bool_),
        ("trusted", np.bool_),
        ("twins", np.bool_),
        ("rule", np.int64),  # counts.RULE_NOISE or RULE_THRESHOLD
        ("merge_patches", np.bool_),  # search.merge_patches
        ("threshold", np.float64),  # [1/m^2]
        ("floor2", np.float64),  # [1/m^2]
        ("max_noise2", np.float64),  # (max_noise^2 + floor^2) [1/m^2]: the misfit test's sigma^2, noise unknown
        ("hopeless", np.float64),
        ("explained", np.float64),
        ("escape_turning", np.float64),  # [rad] (search.escape)
        ("per_interval", np.int64),
        ("exchange_top", np.int64),
        ("rounds", np.int64),
        ("explore", np.int64),
        ("condition_limit", np.float64),
        ("max_evaluations", np.int64),  # 0: no budget
        ("damping", np.float64),
        ("increase", np.float64),
        ("decrease", np.float64),
        ("min_damping", np.float64),
        ("max_damping", np.float64),
        ("max_force_step", np.float64),
        ("tolerance", np.float64),
        ("iterations", np.int64),
        ("refine_iterations", np.int64),
        ("exact_steps", np.int64),
        ("exact_tolerance", np.float64),
        ("acceleration", np.float64),  # -inf: never
        ("probe", np.float64),
        ("acceleration_limit", np.float64),
    ],
    align=True,
)

INFO = np.dtype(
    [
        ("intervals", np.int64),
        ("residuals", np.int64),
        ("noise2", np.float64),  # (sigma^2 + floor^2) [1/m^2] where known
        ("known", np.bool_),
        ("evaluations", np.int64),
        ("cut", np.bool_),
        ("cap", np.int64),  # the largest count the reading may be answered with; below max_forces: a patch merged
        ("home_known", np.bool_),
        ("eigen_m", np.int64),  # the size of the last matrix the covariance's eigensolver took (-1: none yet)
        ("eigen_ok", np.bool_),  # and whether it was finite
    ],
    align=True,
)

DIMS = ("G", "H", "n", "P", "P2", "W", "C", "Q", "R", "NT", "TE", "E", "NC", "S", "NSEG", "NX", "KT", "D")
"""The sizes the arenas' parts follow from (:func:`dims`)."""

GROUPS = ("model", "tables", "reading", "rows", "march", "precurved", "lm", "scan", "cov", "search")
"""The groups of the arenas' parts, in the order they lie in the arenas (each group's parts in the order declared)."""


def _assemble(*declared: dict) -> dict:
    """The groups of the kernel modules' declarations, in the order of :data:`GROUPS` (each declared once)."""
    found: dict = {}
    for parts in declared:
        for group, fields in parts.items():
            if group in found:
                raise ValueError(f"the arenas' group {group!r} is declared twice")
            found[group] = fields
    if set(found) != set(GROUPS):
        raise ValueError(f"the arenas' groups {sorted(found)} are not those of GROUPS {sorted(GROUPS)}")
    return {group: found[group] for group in GROUPS}


SPEC: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = _assemble(
    MARCH_PARTS, COUNTS_PARTS, SEARCH_PARTS, PRECURVED_PARTS, FIT_PARTS, SCAN_PARTS, COVARIANCE_PARTS
)
"""The arenas' parts: group -> {name: (shape in :data:`DIMS` or numbers, kind)}; kinds: f float64, i int64, c
complex128, b bool, k the constants' float64 arena. Each group is declared beside the kernel functions that own it
(``MARCH_PARTS`` in :mod:`.march`: the rod's model and the marches' work; ``COUNTS_PARTS`` in :mod:`.counts`: the
count tests' tables; ``SEARCH_PARTS`` in :mod:`.search`: the reading, the fit rows and the search's bookkeeping;
``PRECURVED_PARTS`` in :mod:`.precurved`; ``FIT_PARTS`` in :mod:`.fit`: the Levenberg-Marquardt step's ``lm``;
``SCAN_PARTS`` in :mod:`.scan`; ``COVARIANCE_PARTS`` in :mod:`.covariance`: ``cov``) and placed here in the order
of :data:`GROUPS`. Each group becomes a named tuple of views (:mod:`.views`)."""

KINDS = {"f": np.float64, "i": np.int64, "c": np.complex128, "b": np.bool_, "k": np.float64}

LAYOUT = np.dtype(
    [(d, np.int64) for d in DIMS] + [(f"{g}_{name}", np.int64) for g, parts in SPEC.items() for name in parts]
)

Sizes = namedtuple("Sizes", "G H starts per_interval exchange_top guess_rows stages nseg nextra")
"""What the arenas' sizes follow from: G gratings, H the largest count, the search's settings, the most guess
blocks for one count, the exact model's stages, the intrinsic-curvature segments and the precurved rod's extra
events."""

Setup = namedtuple("Setup", "rod opt lay const gcount")
"""What the batch shares: the :data:`ROD`, :data:`OPTIONS` and :data:`LAYOUT` records (one element each), the
constants' arena and gcount (K,), the count of each guess block."""

Outputs = namedtuple(
    "Outputs", "count s f std loss converged iterations poorly losses sigma evaluations cut p_value status"
)
"""Per reading (batch first, W = the result width): count (B,), s (B, W) [m] by location with the bias, f (B, W, 2)
[N], std (B, W, 3), loss (B,) [1/m^2], converged (B,), iterations (B,), poorly (B,), losses (B, W + 1) by count,
sigma (B,) [1/m], evaluations (B,), cut (B,), p_value (B,), status (B,) (a code of
:data:`torchrod.estimate.status.STATUSES`)."""

Batch = namedtuple("Batch", "u w noise2 gs gf guse out")
"""Per reading: u (B, 2G) the readings [1/m] (zero at missing gratings), w (B, 2G) 1.0 where present, noise2 (B,)
sigma^2 + floor^2 [1/m^2] or -1 (unknown), the guesses gs (B, K, H) [m], gf (B, K, H, 2) [N], guse (B, K), and the
:class:`Outputs`."""

Arenas = namedtuple("Arenas", "f i c b info")
"""Scratch arenas (one reading's, or one per thread along a leading axis) and the :data:`INFO` records."""


def dims(z: Sizes) -> dict:
    """The values of :data:`DIMS` for these sizes."""
    H = z.H
    W = max(H, 1)
    G = z.G
    C = z.per_interval * G
    return {
        "G": G,
        "H": H,
        "n": 2 * G,
        "P": max(3 * H, 1),
        "P2": 3 * H + 2,
        "W": W,
        "C": C,
        "Q": G + C,
        "R": (H + 2) + max(z.guess_rows + 1, z.starts - 1, z.exchange_top, 1),
        "NT": max(z.starts, 1),
        "TE": (z.exchange_top + 1) * W,
        "E": H + G + C + z.nextra,
        "NC": 1 + 3 * H + 6,
        "S": max(z.stages, 1),
        "NSEG": max(z.nseg, 1),
        "NX": max(z.nextra, 1),
        "KT": H + 2,
        "D": 2 * G + 1,
    }


def _size(shape: tuple, d: dict) -> int:
    out = 1
    for x in shape:
        out *= d[x] if isinstance(x, str) else x
    return out


def layout(z: Sizes) -> tuple[np.recarray, dict]:
    """The :data:`LAYOUT` record of these sizes and the length of each arena ({kind: length})."""
    d = dims(z)
    lay = np.zeros(1, LAYOUT).view(np.recarray)
    for name, value in d.items():
        lay[name] = value
    ends = dict.fromkeys(KINDS, 0)
    for group, parts in SPEC.items():
        for name, (shape, kind) in parts.items():
            lay[f"{group}_{name}"] = ends[kind]
            ends[kind] += _size(shape, d)
    return lay, {kind: max(n, 1) for kind, n in ends.items()}


def allocate(z: Sizes, lead: tuple = (), empty=np.empty) -> Arenas:
    """One reading's scratch arenas (``lead`` (): one; (N,): N of them), made by ``empty(shape, dtype)``."""
    _, lengths = layout(z)
    info = empty(lead + (1,), INFO)
    if isinstance(info, np.ndarray):
        info = info.view(np.recarray)
    f, i, c, b = (empty(lead + (lengths[kind],), KINDS[kind]) for kind in "ficb")
    return Arenas(f, i, c, b, info)


def record(dtype: np.dtype, **values) -> np.recarray:
    """A one-element record array of ``dtype`` with ``values`` (every field must be given)."""
    names = set(dtype.names or ())
    missing = names - set(values)
    if missing or set(values) - names:
        raise KeyError(f"record fields missing {sorted(missing)} or unknown {sorted(set(values) - names)}")
    out = np.zeros(1, dtype).view(np.recarray)
    for name, value in values.items():
        out[name] = value
    return out


def constants(lay: np.recarray, parts: dict) -> np.ndarray:
    """The constants' arena of :data:`LAYOUT` ``lay`` holding ``parts`` ({"model_query": array, ...}: every part
    of the groups of kind k)."""
    d = {name: int(lay[0][name]) for name in DIMS}
    length = sum(_size(shape, d) for g in SPEC.values() for shape, kind in g.values() if kind == "k")
    out = np.zeros(max(length, 1))
    for group, fields in SPEC.items():
        for name, (shape, kind) in fields.items():
            if kind != "k":
                continue
            key = f"{group}_{name}"
            value = np.asarray(parts[key], np.float64)
            want = tuple(d[x] if isinstance(x, str) else x for x in shape)
            start = int(lay[0][key])
            block = np.zeros(want)
            block[tuple(slice(0, s) for s in value.shape)] = value
            out[start : start + block.size] = block.ravel()
    return out


for _dtype in (ROD, OPTIONS, INFO, LAYOUT):  # a field must not hide an attribute of NumPy's records (as T does)
    _clash = [name for name in _dtype.names or () if name in dir(np.record)]
    if _clash:
        raise ValueError(f"record fields {_clash} hide attributes of numpy.record")
del _dtype


# ------------------------------------------------------------------------------------------------ generated accessors
ARENA = {"f": "k.f", "i": "k.i", "c": "k.c", "b": "k.b", "k": "k.const"}
"""The Kit's arena of each kind, as the accessors name it."""

KIT = (
    ("rod", "Any"), ("opt", "Any"), ("lay", "Any"), ("info", "Any"), ("const", "NDArray[np.float64]"),
    ("f", "NDArray[np.float64]"), ("i", "NDArray[np.int64]"), ("c", "NDArray[np.complex128]"),
    ("b", "NDArray[np.bool_]"), ("u", "NDArray[np.float64]"), ("w", "NDArray[np.float64]"),
    ("flag", "NDArray[np.int64]"),
)  # fmt: skip
"""The fields of :class:`Kit` and their types for the type checker (the records are NumPy records: Any)."""

TYPES = {
    "f": "NDArray[np.float64]",
    "i": "NDArray[np.int64]",
    "c": "NDArray[np.complex128]",
    "b": "NDArray[np.bool_]",
    "k": "NDArray[np.float64]",
}
"""The type of a view of each kind, for the type checker."""

_VIEWS_HEAD = f'''"""Named views of a reading's arenas: one accessor per group of :data:`.layout.SPEC` (``rows_of(k)``,
``lm_of(k)``, ...), returning a named tuple of views into the arenas of the :class:`Kit` ``k``.

GENERATED by ``python -m torchrod.kernels.layout`` from the parts each kernel module declares (its ``*_PARTS``,
placed in the arenas by :data:`.layout.SPEC`): do not edit by hand (a test holds this file, and its type stub
``views.pyi``, equal to what the declarations give). Each accessor is a few :func:`view` calls, inlined where it
is called on a compiled target, so the declarations stay the only place the arenas' parts are listed, and grep, the
type checker and a reader all see the code.
"""

from collections import namedtuple

Kit = namedtuple("Kit", "{" ".join(name for name, _ in KIT)}")
"""Everything a kernel function of one reading reads: the :data:`.layout.ROD`, :data:`.layout.OPTIONS` and
:data:`.layout.LAYOUT` records, the reading's :data:`.layout.INFO`, the constants' arena, the four scratch arenas,
the reading's u (2G,) [1/m] and w (2G,) (1.0 where present), and the caller's stop flag (1,)."""


def view(arena, start, shape):
    """The part of the 1-D ``arena`` from ``start`` as a C-contiguous array of ``shape`` (a tuple). Compiled targets
    replace this with an intrinsic of their own (:mod:`.targets`) that builds the view directly: no size checks
    (the layout is known good), so little code to compile at each of its many uses."""
    size = 1
    for d in shape:
        size *= d
    return arena[start : start + size].reshape(shape)
'''

_KIT_FIELDS = "".join(f"    {name}: {type_}\n" for name, type_ in KIT)
_STUB_HEAD = f'''"""Types of :mod:`.views` for the type checker: the named views typed by kind, the accessors by the
views they return.

GENERATED with :mod:`.views` by ``python -m torchrod.kernels.layout``: do not edit by hand.
"""

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

class Kit(NamedTuple):
{_KIT_FIELDS}
def view(arena: NDArray[Any], start: int, shape: tuple[int, ...]) -> NDArray[Any]: ...
'''


def render_views() -> str:
    """The source of :mod:`.views`: for each group of :data:`SPEC`, its named tuple and its accessor."""
    out = [_VIEWS_HEAD, "\n"]
    for group, parts in SPEC.items():
        kind = group.capitalize() + "View"
        fields = "".join(f'        "{name}",\n' for name in parts)
        out.append(f'\n{kind} = namedtuple(\n    "{kind}",\n    [\n{fields}    ],\n)\n')
    for group, parts in SPEC.items():
        items = []
        for name, (shape, kind) in parts.items():
            dims_ = [f"L.{x}" if isinstance(x, str) else str(x) for x in shape]
            tup = f"({dims_[0]},)" if len(dims_) == 1 else f"({', '.join(dims_)})"
            items.append(f"        view({ARENA[kind]}, L.{group}_{name}, {tup}),\n")
        out.append(
            f"\n\ndef {group}_of(k):\n"
            f'    """The {group} part of the arenas, as named views."""\n'
            "    L = k.lay\n"
            f"    return {group.capitalize()}View(\n{''.join(items)}    )\n"
        )
    return "".join(out)


_SHADOW = "  # type: ignore[assignment]  # (a part named like a method of tuple: the field hides it)"


def render_stub() -> str:
    """The source of the type stub ``views.pyi``: :class:`Kit`, and for each group of :data:`SPEC` its named tuple
    (each view typed by its kind) and its accessor."""
    out = [_STUB_HEAD]
    for group, parts in SPEC.items():
        fields = "".join(
            f"    {name}: {TYPES[kind]}{_SHADOW if name in dir(tuple) else ''}\n" for name, (_, kind) in parts.items()
        )
        out.append(f"\nclass {group.capitalize()}View(NamedTuple):\n{fields}")
    out.append("\n")
    for group in SPEC:
        out.append(f"def {group}_of(k: Kit) -> {group.capitalize()}View: ...\n")
    return "".join(out)


if __name__ == "__main__":  # python -m torchrod.kernels.layout: write the generated accessors and their types
    from pathlib import Path

    here = Path(__file__).parent
    (here / "views.py").write_text(render_views(), encoding="utf-8")
    (here / "views.pyi").write_text(render_stub(), encoding="utf-8")
