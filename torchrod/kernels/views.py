"""Named views of a reading's arenas: one accessor per group of :data:`.layout.SPEC` (``rows_of(k)``,
``lm_of(k)``, ...), returning a named tuple of views into the arenas of the :class:`.layout.Kit` ``k``.

GENERATED from :data:`.layout.SPEC` by ``python -m torchrod.kernels.layout``: do not edit by hand (a test holds
this file equal to what the description gives). Each accessor is a few :func:`view` calls, inlined where it is
called on a compiled target, so the description stays the only place the arenas' parts are listed, and grep, the
type checker and a reader all see the code.
"""

from collections import namedtuple


def view(arena, start, shape):
    """The part of the 1-D ``arena`` from ``start`` as a C-contiguous array of ``shape`` (a tuple). Compiled targets
    replace this with an intrinsic of their own (:mod:`.targets`) that builds the view directly: no size checks
    (the layout is known good), so little code to compile at each of its many uses."""
    size = 1
    for d in shape:
        size *= d
    return arena[start : start + size].reshape(shape)


ModelView = namedtuple(
    "ModelView",
    [
        "query",
        "tab_c",
        "tab_a",
        "tab_bp",
        "tab_bv",
        "segments",
        "extra",
    ],
)

TablesView = namedtuple(
    "TablesView",
    [
        "drop_chi2",
        "drop_f",
        "misfit",
        "guard",
        "suspect",
        "kink",
        "verdict",
    ],
)

ReadingView = namedtuple(
    "ReadingView",
    [
        "lo",
        "hi",
        "lo_k",
        "hi_k",
    ],
)

RowsView = namedtuple(
    "RowsView",
    [
        "s",
        "f",
        "interval",
        "held",
        "r",
        "J",
        "A",
        "g",
        "proposal",
        "loss",
        "damping",
        "steps",
        "ratio",
        "decrement",
        "noise2",
        "converged",
        "done",
        "count",
    ],
)

MarchView = namedtuple(
    "MarchView",
    [
        "curv",
        "jac",
        "phi",
        "order",
        "seg",
        "steps",
        "jump",
        "mag",
        "du",
        "dw",
        "carried",
        "ys",
        "gs",
    ],
)

PrecurvedView = namedtuple(
    "PrecurvedView",
    [
        "yn",
        "ym",
        "tn",
        "tm",
        "kn",
        "km",
        "an",
        "am",
    ],
)

LmView = namedtuple(
    "LmView",
    [
        "lo",
        "hi",
        "Js",
        "free",
        "gi",
        "near_lo",
        "near_hi",
        "new_int",
        "new_s",
        "M",
        "L",
        "x",
        "A",
        "prop",
        "v",
        "dx",
        "pv",
        "st",
        "ft",
        "rt",
        "Jt",
        "taken",
        "rv",
        "rhs",
        "tail",
    ],
)

ScanView = namedtuple(
    "ScanView",
    [
        "cand",
        "cint",
        "valid",
        "at",
        "r",
        "J",
        "Jraw",
        "Jc",
        "Mphi",
        "LU",
        "piv",
        "col",
        "xcol",
        "Msol",
        "Abb",
        "Acc",
        "gc",
        "Kb",
        "Lb",
        "e",
        "xk",
        "Kinv",
        "gb",
        "yb",
        "Acb",
        "Y",
        "xc",
        "dec",
        "best_c",
        "order",
        "st",
    ],
)

CovView = namedtuple(
    "CovView",
    [
        "Jm",
        "ok",
        "d",
        "C",
        "w",
        "V",
        "a",
        "inv",
        "cov",
        "active",
        "Js",
        "std2",
        "tail",
        "last",
    ],
)

SearchView = namedtuple(
    "SearchView",
    [
        "fitted",
        "have_scan",
        "unscanned",
        "losses",
        "gain",
        "near_limit",
        "sc_s",
        "sc_f",
        "sc_int",
        "sc_pred",
        "ex_s",
        "ex_f",
        "ex_int",
        "ex_pred",
        "taken",
        "keys",
        "flags",
        "ids",
        "going",
        "home",
        "bs",
        "bf",
        "bint",
        "Jrep",
        "std",
        "slot_s",
        "slot_f",
        "slot_int",
        "order",
    ],
)


def model_of(k):
    """The model part of the arenas, as named views."""
    L = k.lay
    return ModelView(
        view(k.const, L.model_query, (L.G,)),
        view(k.const, L.model_tab_c, (L.S,)),
        view(k.const, L.model_tab_a, (L.S, L.S)),
        view(k.const, L.model_tab_bp, (L.S,)),
        view(k.const, L.model_tab_bv, (L.S,)),
        view(k.const, L.model_segments, (L.NSEG, 4)),
        view(k.const, L.model_extra, (L.NX,)),
    )


def tables_of(k):
    """The tables part of the arenas, as named views."""
    L = k.lay
    return TablesView(
        view(k.const, L.tables_drop_chi2, (L.KT,)),
        view(k.const, L.tables_drop_f, (L.KT, L.D)),
        view(k.const, L.tables_misfit, (L.D,)),
        view(k.const, L.tables_guard, (L.D,)),
        view(k.const, L.tables_suspect, (L.D,)),
        view(k.const, L.tables_kink, (L.D,)),
        view(k.const, L.tables_verdict, (L.D,)),
    )


def reading_of(k):
    """The reading part of the arenas, as named views."""
    L = k.lay
    return ReadingView(
        view(k.f, L.reading_lo, (L.G,)),
        view(k.f, L.reading_hi, (L.G,)),
        view(k.i, L.reading_lo_k, (L.G,)),
        view(k.i, L.reading_hi_k, (L.G,)),
    )


def rows_of(k):
    """The rows part of the arenas, as named views."""
    L = k.lay
    return RowsView(
        view(k.f, L.rows_s, (L.R, L.W)),
        view(k.f, L.rows_f, (L.R, L.W, 2)),
        view(k.i, L.rows_interval, (L.R, L.W)),
        view(k.b, L.rows_held, (L.R, L.W)),
        view(k.f, L.rows_r, (L.R, L.n)),
        view(k.f, L.rows_J, (L.R, L.n, L.P)),
        view(k.f, L.rows_A, (L.R, L.P, L.P)),
        view(k.f, L.rows_g, (L.R, L.P)),
        view(k.f, L.rows_proposal, (L.R, L.P)),
        view(k.f, L.rows_loss, (L.R,)),
        view(k.f, L.rows_damping, (L.R,)),
        view(k.i, L.rows_steps, (L.R,)),
        view(k.f, L.rows_ratio, (L.R,)),
        view(k.f, L.rows_decrement, (L.R,)),
        view(k.f, L.rows_noise2, (L.R,)),
        view(k.b, L.rows_converged, (L.R,)),
        view(k.b, L.rows_done, (L.R,)),
        view(k.i, L.rows_count, (L.R,)),
    )


def march_of(k):
    """The march part of the arenas, as named views."""
    L = k.lay
    return MarchView(
        view(k.f, L.march_curv, (L.Q, 2)),
        view(k.f, L.march_jac, (L.Q, 2, L.P)),
        view(k.f, L.march_phi, (L.Q, 8, 6)),
        view(k.i, L.march_order, (L.E,)),
        view(k.f, L.march_seg, (L.E,)),
        view(k.i, L.march_steps, (L.E,)),
        view(k.c, L.march_jump, (L.W,)),
        view(k.f, L.march_mag, (L.W,)),
        view(k.c, L.march_du, (L.NC,)),
        view(k.c, L.march_dw, (L.NC,)),
        view(k.b, L.march_carried, (L.NC,)),
        view(k.c, L.march_ys, (L.S,)),
        view(k.c, L.march_gs, (L.S,)),
    )


def precurved_of(k):
    """The precurved part of the arenas, as named views."""
    L = k.lay
    return PrecurvedView(
        view(k.f, L.precurved_yn, (3, L.NC)),
        view(k.f, L.precurved_ym, (3, L.NC)),
        view(k.f, L.precurved_tn, (3, L.NC)),
        view(k.f, L.precurved_tm, (3, L.NC)),
        view(k.f, L.precurved_kn, (3, L.NC)),
        view(k.f, L.precurved_km, (3, L.NC)),
        view(k.f, L.precurved_an, (3, L.NC)),
        view(k.f, L.precurved_am, (3, L.NC)),
    )


def lm_of(k):
    """The lm part of the arenas, as named views."""
    L = k.lay
    return LmView(
        view(k.f, L.lm_lo, (L.W,)),
        view(k.f, L.lm_hi, (L.W,)),
        view(k.f, L.lm_Js, (L.n, L.P)),
        view(k.f, L.lm_free, (L.P,)),
        view(k.f, L.lm_gi, (L.P,)),
        view(k.b, L.lm_near_lo, (L.W,)),
        view(k.b, L.lm_near_hi, (L.W,)),
        view(k.i, L.lm_new_int, (L.W,)),
        view(k.f, L.lm_new_s, (L.W,)),
        view(k.f, L.lm_M, (L.P, L.P)),
        view(k.f, L.lm_L, (L.P, L.P)),
        view(k.f, L.lm_x, (L.P,)),
        view(k.f, L.lm_A, (L.P, L.P)),
        view(k.f, L.lm_prop, (L.P,)),
        view(k.f, L.lm_v, (L.P,)),
        view(k.f, L.lm_dx, (L.P,)),
        view(k.f, L.lm_pv, (L.P,)),
        view(k.f, L.lm_st, (L.W,)),
        view(k.f, L.lm_ft, (L.W, 2)),
        view(k.f, L.lm_rt, (L.n,)),
        view(k.f, L.lm_Jt, (L.n, L.P)),
        view(k.f, L.lm_taken, (L.P,)),
        view(k.f, L.lm_rv, (L.n,)),
        view(k.f, L.lm_rhs, (L.P,)),
        view(k.i, L.lm_tail, (L.P,)),
    )


def scan_of(k):
    """The scan part of the arenas, as named views."""
    L = k.lay
    return ScanView(
        view(k.f, L.scan_cand, (L.C,)),
        view(k.i, L.scan_cint, (L.C,)),
        view(k.b, L.scan_valid, (L.C,)),
        view(k.f, L.scan_at, (L.Q,)),
        view(k.f, L.scan_r, (L.n,)),
        view(k.f, L.scan_J, (L.n, L.P)),
        view(k.f, L.scan_Jraw, (L.n, L.P)),
        view(k.f, L.scan_Jc, (L.C, L.n, 2)),
        view(k.f, L.scan_Mphi, (6, 6)),
        view(k.f, L.scan_LU, (6, 6)),
        view(k.i, L.scan_piv, (6,)),
        view(k.f, L.scan_col, (6,)),
        view(k.f, L.scan_xcol, (6,)),
        view(k.f, L.scan_Msol, (6, 2)),
        view(k.f, L.scan_Abb, (L.P, L.P)),
        view(k.f, L.scan_Acc, (L.C, 2, 2)),
        view(k.f, L.scan_gc, (L.C, 2)),
        view(k.f, L.scan_Kb, (L.P, L.P)),
        view(k.f, L.scan_Lb, (L.P, L.P)),
        view(k.f, L.scan_e, (L.P,)),
        view(k.f, L.scan_xk, (L.P,)),
        view(k.f, L.scan_Kinv, (L.P, L.P)),
        view(k.f, L.scan_gb, (L.P,)),
        view(k.f, L.scan_yb, (L.P,)),
        view(k.f, L.scan_Acb, (2, L.P)),
        view(k.f, L.scan_Y, (L.C, 2, L.P)),
        view(k.f, L.scan_xc, (L.C, 2)),
        view(k.f, L.scan_dec, (L.C,)),
        view(k.i, L.scan_best_c, (L.G,)),
        view(k.i, L.scan_order, (L.G,)),
        view(k.f, L.scan_st, (L.P2,)),
    )


def cov_of(k):
    """The cov part of the arenas, as named views."""
    L = k.lay
    return CovView(
        view(k.f, L.cov_Jm, (L.n, L.P)),
        view(k.b, L.cov_ok, (L.P,)),
        view(k.f, L.cov_d, (L.P,)),
        view(k.f, L.cov_C, (L.P, L.P)),
        view(k.f, L.cov_w, (L.P,)),
        view(k.f, L.cov_V, (L.P, L.P)),
        view(k.f, L.cov_a, (L.P, L.P)),
        view(k.f, L.cov_inv, (L.P,)),
        view(k.f, L.cov_cov, (L.P, L.P)),
        view(k.b, L.cov_active, (L.P,)),
        view(k.f, L.cov_Js, (L.n, L.P)),
        view(k.f, L.cov_std2, (L.W, 3)),
        view(k.i, L.cov_tail, (L.P,)),
        view(k.f, L.cov_last, (L.P, L.P)),
    )


def search_of(k):
    """The search part of the arenas, as named views."""
    L = k.lay
    return SearchView(
        view(k.b, L.search_fitted, (L.R,)),
        view(k.b, L.search_have_scan, (L.R,)),
        view(k.b, L.search_unscanned, (L.R,)),
        view(k.f, L.search_losses, (L.R,)),
        view(k.f, L.search_gain, (L.R,)),
        view(k.f, L.search_near_limit, (L.R,)),
        view(k.f, L.search_sc_s, (L.R, L.NT, L.W)),
        view(k.f, L.search_sc_f, (L.R, L.NT, L.W, 2)),
        view(k.i, L.search_sc_int, (L.R, L.NT, L.W)),
        view(k.f, L.search_sc_pred, (L.R, L.NT)),
        view(k.f, L.search_ex_s, (L.TE, L.W)),
        view(k.f, L.search_ex_f, (L.TE, L.W, 2)),
        view(k.i, L.search_ex_int, (L.TE, L.W)),
        view(k.f, L.search_ex_pred, (L.TE,)),
        view(k.b, L.search_taken, (L.TE,)),
        view(k.i, L.search_keys, (L.R, L.W)),
        view(k.b, L.search_flags, (L.R,)),
        view(k.i, L.search_ids, (L.R,)),
        view(k.i, L.search_going, (L.R,)),
        view(k.i, L.search_home, (L.W,)),
        view(k.f, L.search_bs, (L.W,)),
        view(k.f, L.search_bf, (L.W, 2)),
        view(k.i, L.search_bint, (L.W,)),
        view(k.f, L.search_Jrep, (L.n, L.P)),
        view(k.f, L.search_std, (L.W, 3)),
        view(k.f, L.search_slot_s, (L.W,)),
        view(k.f, L.search_slot_f, (L.W, 2)),
        view(k.i, L.search_slot_int, (L.W,)),
        view(k.i, L.search_order, (L.W,)),
    )
