"""Types of :mod:`.views` for the type checker: the named views typed by kind, the accessors by the
views they return.

GENERATED with :mod:`.views` by ``python -m torchrod.kernels.layout``: do not edit by hand.
"""

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

class Kit(NamedTuple):
    rod: Any
    opt: Any
    lay: Any
    info: Any
    const: NDArray[np.float64]
    f: NDArray[np.float64]
    i: NDArray[np.int64]
    c: NDArray[np.complex128]
    b: NDArray[np.bool_]
    u: NDArray[np.float64]
    w: NDArray[np.float64]
    flag: NDArray[np.int64]

def view(arena: NDArray[Any], start: int, shape: tuple[int, ...]) -> NDArray[Any]: ...

class ModelView(NamedTuple):
    query: NDArray[np.float64]
    tab_c: NDArray[np.float64]
    tab_a: NDArray[np.float64]
    tab_bp: NDArray[np.float64]
    tab_bv: NDArray[np.float64]
    segments: NDArray[np.float64]
    extra: NDArray[np.float64]

class TablesView(NamedTuple):
    drop_chi2: NDArray[np.float64]
    drop_f: NDArray[np.float64]
    misfit: NDArray[np.float64]
    guard: NDArray[np.float64]
    suspect: NDArray[np.float64]
    kink: NDArray[np.float64]
    verdict: NDArray[np.float64]

class ReadingView(NamedTuple):
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    lo_k: NDArray[np.int64]
    hi_k: NDArray[np.int64]

class RowsView(NamedTuple):
    s: NDArray[np.float64]
    f: NDArray[np.float64]
    interval: NDArray[np.int64]
    held: NDArray[np.bool_]
    r: NDArray[np.float64]
    J: NDArray[np.float64]
    A: NDArray[np.float64]
    g: NDArray[np.float64]
    proposal: NDArray[np.float64]
    loss: NDArray[np.float64]
    damping: NDArray[np.float64]
    steps: NDArray[np.int64]
    ratio: NDArray[np.float64]
    decrement: NDArray[np.float64]
    noise2: NDArray[np.float64]
    converged: NDArray[np.bool_]
    done: NDArray[np.bool_]
    count: NDArray[np.int64]  # type: ignore[assignment]  # (a part named like a method of tuple: the field hides it)

class MarchView(NamedTuple):
    curv: NDArray[np.float64]
    jac: NDArray[np.float64]
    phi: NDArray[np.float64]
    order: NDArray[np.int64]
    seg: NDArray[np.float64]
    steps: NDArray[np.int64]
    jump: NDArray[np.complex128]
    mag: NDArray[np.float64]
    du: NDArray[np.complex128]
    dw: NDArray[np.complex128]
    carried: NDArray[np.bool_]
    ys: NDArray[np.complex128]
    gs: NDArray[np.complex128]

class PrecurvedView(NamedTuple):
    yn: NDArray[np.float64]
    ym: NDArray[np.float64]
    tn: NDArray[np.float64]
    tm: NDArray[np.float64]
    kn: NDArray[np.float64]
    km: NDArray[np.float64]
    an: NDArray[np.float64]
    am: NDArray[np.float64]

class LmView(NamedTuple):
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    Js: NDArray[np.float64]
    free: NDArray[np.float64]
    gi: NDArray[np.float64]
    near_lo: NDArray[np.bool_]
    near_hi: NDArray[np.bool_]
    new_int: NDArray[np.int64]
    new_s: NDArray[np.float64]
    M: NDArray[np.float64]
    L: NDArray[np.float64]
    x: NDArray[np.float64]
    A: NDArray[np.float64]
    prop: NDArray[np.float64]
    v: NDArray[np.float64]
    dx: NDArray[np.float64]
    pv: NDArray[np.float64]
    st: NDArray[np.float64]
    ft: NDArray[np.float64]
    rt: NDArray[np.float64]
    Jt: NDArray[np.float64]
    taken: NDArray[np.float64]
    rv: NDArray[np.float64]
    rhs: NDArray[np.float64]
    tail: NDArray[np.int64]

class ScanView(NamedTuple):
    cand: NDArray[np.float64]
    cint: NDArray[np.int64]
    valid: NDArray[np.bool_]
    at: NDArray[np.float64]
    r: NDArray[np.float64]
    J: NDArray[np.float64]
    Jraw: NDArray[np.float64]
    Jc: NDArray[np.float64]
    Mphi: NDArray[np.float64]
    LU: NDArray[np.float64]
    piv: NDArray[np.int64]
    col: NDArray[np.float64]
    xcol: NDArray[np.float64]
    Msol: NDArray[np.float64]
    Abb: NDArray[np.float64]
    Acc: NDArray[np.float64]
    gc: NDArray[np.float64]
    Kb: NDArray[np.float64]
    Lb: NDArray[np.float64]
    e: NDArray[np.float64]
    xk: NDArray[np.float64]
    Kinv: NDArray[np.float64]
    gb: NDArray[np.float64]
    yb: NDArray[np.float64]
    Acb: NDArray[np.float64]
    Y: NDArray[np.float64]
    xc: NDArray[np.float64]
    dec: NDArray[np.float64]
    best_c: NDArray[np.int64]
    order: NDArray[np.int64]
    st: NDArray[np.float64]

class CovView(NamedTuple):
    Jm: NDArray[np.float64]
    ok: NDArray[np.bool_]
    d: NDArray[np.float64]
    C: NDArray[np.float64]
    w: NDArray[np.float64]
    V: NDArray[np.float64]
    a: NDArray[np.float64]
    inv: NDArray[np.float64]
    cov: NDArray[np.float64]
    active: NDArray[np.bool_]
    Js: NDArray[np.float64]
    std2: NDArray[np.float64]
    tail: NDArray[np.int64]
    last: NDArray[np.float64]

class SearchView(NamedTuple):
    fitted: NDArray[np.bool_]
    have_scan: NDArray[np.bool_]
    unscanned: NDArray[np.bool_]
    losses: NDArray[np.float64]
    gain: NDArray[np.float64]
    near_limit: NDArray[np.float64]
    sc_s: NDArray[np.float64]
    sc_f: NDArray[np.float64]
    sc_int: NDArray[np.int64]
    sc_pred: NDArray[np.float64]
    ex_s: NDArray[np.float64]
    ex_f: NDArray[np.float64]
    ex_int: NDArray[np.int64]
    ex_pred: NDArray[np.float64]
    taken: NDArray[np.bool_]
    keys: NDArray[np.int64]
    flags: NDArray[np.bool_]
    ids: NDArray[np.int64]
    going: NDArray[np.int64]
    home: NDArray[np.int64]
    bs: NDArray[np.float64]
    bf: NDArray[np.float64]
    bint: NDArray[np.int64]
    Jrep: NDArray[np.float64]
    std: NDArray[np.float64]
    slot_s: NDArray[np.float64]
    slot_f: NDArray[np.float64]
    slot_int: NDArray[np.int64]
    order: NDArray[np.int64]

def model_of(k: Kit) -> ModelView: ...
def tables_of(k: Kit) -> TablesView: ...
def reading_of(k: Kit) -> ReadingView: ...
def rows_of(k: Kit) -> RowsView: ...
def march_of(k: Kit) -> MarchView: ...
def precurved_of(k: Kit) -> PrecurvedView: ...
def lm_of(k: Kit) -> LmView: ...
def scan_of(k: Kit) -> ScanView: ...
def cov_of(k: Kit) -> CovView: ...
def search_of(k: Kit) -> SearchView: ...
