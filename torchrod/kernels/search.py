"""The whole estimate of one reading: the fit of every count, the search for the global minimum of each, the count
chosen, the uncertainty and the record.

For counts h = 1, ..., H in turn, each from the one below (:func:`fit_counts`):

* **Scan** (:mod:`.scan`): where one more force helps most, from the best fit of h - 1 forces; its best interval
  starts a fit, the next ones are kept for later. With a known noise, a reading whose count is already decided
  (:func:`.counts.settled`) is not fitted further.
* **First fits**: the guesses (a warm-start network's, the caller's) and the scan's best start, fitted side by
  side (:func:`solve_rows`); a row that another row of the reading has joined in the same intervals with a lower
  loss stops (its *twin*: one force has one minimum per interval, and more forces are taken to behave alike);
  the best is finished on the exact model. Trusted guesses start alone, with no scan, and a count below the largest
  they give that has none of its own is not fitted (the network's count probabilities stand for those fits).

Then the fits that matter are searched further where they look suspicious (unconverged, a loss above a quantile
of a correct fit's, or a force on a grating with a loss above a lower one): the chosen count's, those of smaller
counts that could still be accepted, the count below a chosen fit the data cannot determine and the count above
a chosen fit that misfits. Their further starts are the scan's other intervals (:func:`explore`: each start takes
a few steps and goes on only while it promises to beat the fit; a start that reaches the fit's own intervals
stops there), then the exchange (:func:`exchange`): each force in turn removed and re-placed by the scan among all
intervals. A chosen fit holding a force that is zero within its uncertainty starts the count below without that
force (:func:`drop_negligible`). The chosen fit, where its step budget left it open, takes more steps from where it
stands (:func:`refine`); where it then holds a pair of forces the gratings cannot tell from one patch of load, the
reading is answered with one force fewer (:func:`merge_patches`), that fit refined alike.

With the count fixed to h, a fit that misfits a reading bending the rod far is searched once more through h + 1
forces (:func:`escape`).

The count is chosen (:mod:`.counts`), its uncertainty judged (:mod:`.covariance`), and the forces reported by
location with the rod's location bias, with the fit's p-value and the reading's status (:func:`.counts.verdict`).
The caller's stop flag (a deadline) or an evaluation budget cut the search where it stands; the reading is then
marked ``cut`` and answered with the best fit so far.
"""

import math

from .counts import (
    PATCH_SPAN,
    PATCH_SPAN_MISFIT,
    RULE_NOISE,
    p_value,
    plausible_limit,
    select_count,
    settled,
    spacing,
    suspect_limits,
    unexplained,
    unresolved_pair,
    verdict,
)
from .covariance import near_kink, uncertainty
from .fit import bounds, finish, late, sided, start, step
from .scan import interval_of, scan_model, scan_starts
from .views import Kit, lm_of, model_of, reading_of, rows_of, search_of

SEARCH_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "reading": {  # the reading's intervals between present gratings: bounds [m] and their gratings (-1: none)
        "lo": (("G",), "f"), "hi": (("G",), "f"), "lo_k": (("G",), "i"), "hi_k": (("G",), "i"),
    },
    "rows": {  # fit states: rows 0..H the best fit of each count, the rest the search's work rows
        "s": (("R", "W"), "f"), "f": (("R", "W", 2), "f"), "interval": (("R", "W"), "i"), "held": (("R", "W"), "b"),
        "r": (("R", "n"), "f"), "J": (("R", "n", "P"), "f"), "A": (("R", "P", "P"), "f"), "g": (("R", "P"), "f"),
        "proposal": (("R", "P"), "f"), "loss": (("R",), "f"), "damping": (("R",), "f"), "steps": (("R",), "i"),
        "ratio": (("R",), "f"), "decrement": (("R",), "f"), "noise2": (("R",), "f"), "converged": (("R",), "b"),
        "done": (("R",), "b"), "count": (("R",), "i"),
    },
    "search": {  # the search's bookkeeping: counts fitted, scans kept, exchange starts, stop rules, the report
        "fitted": (("R",), "b"), "have_scan": (("R",), "b"), "unscanned": (("R",), "b"), "losses": (("R",), "f"),
        "gain": (("R",), "f"),
        "near_limit": (("R",), "f"), "sc_s": (("R", "NT", "W"), "f"), "sc_f": (("R", "NT", "W", 2), "f"),
        "sc_int": (("R", "NT", "W"), "i"), "sc_pred": (("R", "NT"), "f"), "ex_s": (("TE", "W"), "f"),
        "ex_f": (("TE", "W", 2), "f"), "ex_int": (("TE", "W"), "i"), "ex_pred": (("TE",), "f"),
        "taken": (("TE",), "b"), "keys": (("R", "W"), "i"), "flags": (("R",), "b"), "ids": (("R",), "i"),
        "going": (("R",), "i"), "home": (("W",), "i"), "bs": (("W",), "f"), "bf": (("W", 2), "f"),
        "bint": (("W",), "i"), "Jrep": (("n", "P"), "f"), "std": (("W", 3), "f"), "slot_s": (("W",), "f"),
        "slot_f": (("W", 2), "f"), "slot_int": (("W",), "i"), "order": (("W",), "i"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

STOP_NONE = 0
STOP_TWINS = 1
STOP_HOME = 2

SLACK = 10.0
"""Fits within SLACK x tolerance x sigma^2 of the lowest loss count as equal when the best is picked (a converged one
is preferred), and a new fit must beat the current one by as much to replace it."""


# ------------------------------------------------------------------------------------------------ rows
def copy_row(k, src, dst):
    """Row ``dst`` of the rows becomes a copy of row ``src``."""
    rows = rows_of(k)
    H = rows.s.shape[1]
    n = rows.r.shape[1]
    P = rows.g.shape[1]
    for j in range(H):
        rows.s[dst, j] = rows.s[src, j]
        rows.f[dst, j, 0] = rows.f[src, j, 0]
        rows.f[dst, j, 1] = rows.f[src, j, 1]
        rows.interval[dst, j] = rows.interval[src, j]
        rows.held[dst, j] = rows.held[src, j]
    for m in range(n):
        rows.r[dst, m] = rows.r[src, m]
        for p in range(P):
            rows.J[dst, m, p] = rows.J[src, m, p]
    for p in range(P):
        rows.g[dst, p] = rows.g[src, p]
        rows.proposal[dst, p] = rows.proposal[src, p]
        for q in range(P):
            rows.A[dst, p, q] = rows.A[src, p, q]
    rows.loss[dst] = rows.loss[src]
    rows.damping[dst] = rows.damping[src]
    rows.steps[dst] = rows.steps[src]
    rows.ratio[dst] = rows.ratio[src]
    rows.decrement[dst] = rows.decrement[src]
    rows.noise2[dst] = rows.noise2[src]
    rows.converged[dst] = rows.converged[src]
    rows.done[dst] = rows.done[src]
    rows.count[dst] = rows.count[src]


INLINE = (
    "finish_best",
    "note_cut",
    "work_ids",
    "try_starts",
    "suspicious",
    "choose",
    "location_key",
    "estimate_one",
    "blank_row",
    "load_row",
    "searched",
)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def load_row(k, i, h, s, f, interval):
    """Row i holds h forces at (s, f) in their intervals (a start, not yet evaluated)."""
    rows = rows_of(k)
    rows.count[i] = h
    for j in range(h):
        rows.s[i, j] = s[j]
        rows.f[i, j, 0] = f[j, 0]
        rows.f[i, j, 1] = f[j, 1]
        rows.interval[i, j] = interval[j]
        rows.held[i, j] = False


def blank_row(k, i, h):
    """Row i: a count not fitted (a NaN loss)."""
    rows = rows_of(k)
    rows.count[i] = h
    for j in range(rows.s.shape[1]):
        rows.s[i, j] = 0.0
        rows.f[i, j, 0] = 0.0
        rows.f[i, j, 1] = 0.0
        rows.interval[i, j] = 0
        rows.held[i, j] = False
    rows.loss[i] = math.nan
    rows.steps[i] = 0
    rows.converged[i] = False
    rows.done[i] = True


def intervals_key(k, i, key):
    """key (h,): row i's intervals in decreasing order; all -1 where two forces share one (such a set holds minima
    of its own) or, with ``held`` rows excluded by the caller, never equal to another row's."""
    rows = rows_of(k)
    h = rows.count[i]
    for j in range(h):
        key[j] = rows.interval[i, j]
    for a in range(1, h):
        v = key[a]
        b = a
        while b > 0 and key[b - 1] < v:
            key[b] = key[b - 1]
            b -= 1
        key[b] = v
    repeated = False
    for a in range(1, h):
        repeated = repeated or key[a] == key[a - 1]
    if repeated:
        for j in range(h):
            key[j] = -1


# ------------------------------------------------------------------------------------------------ solving
def stop_flags(k, ids, nr, kind, goal, twins):
    """The rows among ids[:nr] that a stop rule ends (into the search work's ``flags``):

    * ``STOP_HOME``: a row in the intervals (the ``home`` key) of the fit it is to beat, without a lower loss than
      ``goal``, descends to that fit; with ``twins`` also the rule below;
    * ``STOP_TWINS``: a row that another row joins in the same set of intervals (none held on a bound) with a lower
      loss (at equal losses the earlier row goes on)."""
    rows = rows_of(k)
    sw = search_of(k)
    for a in range(nr):
        i = ids[a]
        sw.flags[a] = False
        intervals_key(k, i, sw.keys[a])
        if kind == STOP_HOME and k.info[0].home_known:
            same = True
            for j in range(rows.count[i]):
                same = same and sw.keys[a, j] == sw.home[j]
            if same and rows.loss[i] >= goal:
                sw.flags[a] = True
    if kind == STOP_TWINS or twins:
        for a in range(nr):
            i = ids[a]
            for j in range(rows.count[i]):
                if rows.held[i, j]:
                    sw.keys[a, 0] = -1
        for a in range(nr):
            ia = ids[a]
            la = rows.loss[ia] if rows.loss[ia] == rows.loss[ia] else math.inf
            for b in range(a + 1, nr):
                ib = ids[b]
                if sw.keys[a, 0] < 0 or sw.keys[b, 0] < 0:
                    continue
                same = True
                for j in range(rows.count[ia]):
                    same = same and sw.keys[a, j] == sw.keys[b, j]
                if not same:
                    continue
                lb = rows.loss[ib] if rows.loss[ib] == rows.loss[ib] else math.inf
                if lb >= la:
                    sw.flags[b] = True
                else:
                    sw.flags[a] = True


def solve_rows(k, ids, nr, limit, kind, goal, twins):
    """Levenberg-Marquardt on the rows ids[:nr] side by side (each already started or continuing), one step of
    every open row per round, until each is done, a stop rule ends it (:func:`stop_flags`), or the search must
    stop (:func:`.fit.late`: the rows still going are left as they are, not done)."""
    rows = rows_of(k)
    sw = search_of(k)
    if kind != STOP_NONE:
        stop_flags(k, ids, nr, kind, goal, twins)
        for a in range(nr):
            if sw.flags[a]:
                rows.done[ids[a]] = True
    while True:
        going = False
        for a in range(nr):
            going = going or not rows.done[ids[a]]
        if not going or late(k):
            return
        for a in range(nr):
            if not rows.done[ids[a]]:
                step(k, ids[a], limit)
        if kind != STOP_NONE:
            stop_flags(k, ids, nr, kind, goal, twins)
            for a in range(nr):
                if sw.flags[a]:
                    rows.done[ids[a]] = True


def best_of(k, ids, nr):
    """The row among ids[:nr] with the lowest loss, where fits within the slack of it count as equal and a
    converged one is preferred (the first at a tie; NaN last)."""
    rows = rows_of(k)
    slack = SLACK * k.opt.tolerance * rows.noise2[ids[0]]
    best = ids[0]
    key_best = math.inf
    for a in range(nr):
        i = ids[a]
        key = rows.loss[i] - (slack if rows.converged[i] else 0.0)
        if not key == key:
            key = math.inf
        if key < key_best:
            key_best = key
            best = i
    return best


def finish_best(k, i):
    """The fit kept finished on the exact model (only its exact residual once the search must stop: then the
    reading is cut)."""
    if late(k):
        finish(k, i, 0)
        k.info[0].cut = True
    else:
        finish(k, i, k.opt.exact_steps)


def note_cut(k, ids, nr):
    """A row the search left going (its deadline passed) cuts the reading."""
    for a in range(nr):
        if not rows_of(k).done[ids[a]]:
            k.info[0].cut = True


def work_ids(k, nr):
    """ids[:nr] = the first nr work rows (the rows after the H + 1 best fits). (Nothing returned: a CUDA device
    function returns no array it was not given.)"""
    sw = search_of(k)
    first = k.opt.max_forces + 1
    for a in range(nr):
        sw.ids[a] = first + a


def first_fits(k, h, nr):
    """The best of the starts in the first nr work rows (fitted side by side, twins stopped), finished, as the best
    fit of h forces."""
    work_ids(k, nr)
    ids = search_of(k).ids
    for a in range(nr):
        start(k, ids[a], k.opt.iterations)
    kind = STOP_TWINS if (k.opt.twins and nr > 1) else STOP_NONE
    solve_rows(k, ids, nr, k.opt.iterations, kind, 0.0, False)
    note_cut(k, ids, nr)
    best = best_of(k, ids, nr)
    finish_best(k, best)
    copy_row(k, best, h)


def set_home(k, h):
    """The intervals of the best fit of h forces as the key its wider search must not return to: with twins, only
    for a fit that converged in the open (one still creeping may be reached first; one held on a bound is a
    minimum of its own beside the one inside); without, one force's fit only."""
    rows = rows_of(k)
    sw = search_of(k)
    inside = rows.converged[h]
    for j in range(h):
        inside = inside and not rows.held[h, j]
    use = inside if k.opt.twins else h == 1
    k.info[0].home_known = False
    if use:
        intervals_key(k, h, sw.home)
        k.info[0].home_known = sw.home[0] >= 0


def explore(k, h, nr):
    """The best of the starts in the first nr work rows against the best fit of h forces (row h), fitted only
    while promising: each takes at most ``explore`` steps, and only the rows whose loss, or what a Gauss-Newton step
    promises from it, has fallen below the fit's are fitted to the end. A row that enters the fit's own intervals
    without a lower loss stops (:func:`set_home`). Returns the best row, finished, or -1 where every row stopped
    so."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    work_ids(k, nr)
    ids = search_of(k).ids
    goal = rows.loss[h]
    set_home(k, h)
    use_home = opt.twins or h == 1
    short = opt.explore if opt.explore < opt.iterations else opt.iterations
    for a in range(nr):
        start(k, ids[a], short)
    kind = STOP_HOME if use_home else STOP_NONE
    twins = use_home and opt.twins and h > 1 and nr > 1
    solve_rows(k, ids, nr, short, kind, goal, twins)
    note_cut(k, ids, nr)
    live = False
    if kind != STOP_NONE:
        stop_flags(k, ids, nr, kind, goal, twins)
    going = 0
    for a in range(nr):
        i = ids[a]
        dropped = kind != STOP_NONE and sw.flags[a] and not rows.converged[i]
        live = live or not dropped
        dec = rows.decrement[i]
        promise = rows.loss[i] - dec if math.isfinite(dec) else rows.loss[i]
        if not rows.converged[i] and not dropped and promise < goal and rows.damping[i] < opt.max_damping:
            rows.done[i] = rows.steps[i] >= opt.iterations
            sw.going[going] = i
            going += 1
    if going:
        solve_rows(k, sw.going, going, opt.iterations, STOP_NONE, 0.0, False)
        note_cut(k, sw.going, going)
    if not live:
        return -1
    work_ids(k, nr)
    ids = search_of(k).ids
    best = best_of(k, ids, nr)
    finish_best(k, best)
    return best


def try_starts(k, h, nr):
    """The best fit of h forces replaced by the best of the starts in the first nr work rows (:func:`explore`)
    where that is lower by more than the slack."""
    rows = rows_of(k)
    found = explore(k, h, nr)
    if found >= 0 and rows.loss[found] < rows.loss[h] - SLACK * k.opt.tolerance * rows.noise2[h]:
        copy_row(k, found, h)


def suspicious(k, i, loss_limit, kink_limit):
    """Whether row i's fit is worth a wider search: unconverged, a loss above ``loss_limit``, or a force on a
    grating with a loss above ``kink_limit``."""
    rows = rows_of(k)
    if not rows.converged[i] or rows.loss[i] > loss_limit:
        return True
    return rows.loss[i] > kink_limit and near_kink(k, rows.s[i], rows.count[i])


def without_force(k, h, i):
    """The best fit of h forces less its force i, into the search's base (``bs``, ``bf``, ``bint``: h - 1 forces)."""
    rows = rows_of(k)
    sw = search_of(k)
    b = 0
    for j in range(h):
        if j != i:
            sw.bs[b] = rows.s[h, j]
            sw.bf[b, 0] = rows.f[h, j, 0]
            sw.bf[b, 1] = rows.f[h, j, 1]
            sw.bint[b] = rows.interval[h, j]
            b += 1


def exchange(k, h, loss_limit, kink_limit):
    """Re-place the forces of the best fit of h >= 2 forces one at a time, while it is suspicious (at most
    ``rounds`` times): each force removed, the scan re-places it among all intervals (not its own), and the
    re-placements it promises most from are explored; the best that lowers the loss replaces the fit."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    T = opt.exchange_top + 1
    E = opt.exchange_top if opt.exchange_top < T * h else T * h
    for _ in range(opt.rounds):
        if not suspicious(k, h, loss_limit, kink_limit):
            return
        if late(k):
            k.info[0].cut = True
            return
        for i in range(h):  # the fit without force i, scanned
            without_force(k, h, i)
            base_loss = scan_model(k, sw.bs, sw.bf, sw.bint, h - 1, -1)
            scan_starts(k, sw.bs, sw.bf, h - 1, base_loss, T, opt.max_force_step, sw.ex_s, sw.ex_f, sw.ex_int,
                        sw.ex_pred, i, h)  # fmt: skip
            for t in range(T):
                if sw.ex_int[t * h + i, h - 1] == rows.interval[h, i]:
                    sw.ex_pred[t * h + i] = math.inf  # back into its own interval: nothing new
        for c in range(T * h):
            sw.taken[c] = False
        for e in range(E):  # the E re-placements with the lowest promised loss (the first at a tie)
            pick = -1
            for c in range(T * h):
                if not sw.taken[c] and (pick < 0 or sw.ex_pred[c] < sw.ex_pred[pick]):
                    pick = c
            sw.taken[pick] = True
            load_row(k, opt.max_forces + 1 + e, h, sw.ex_s[pick], sw.ex_f[pick], sw.ex_int[pick])
        found = explore(k, h, E)
        if not (found >= 0 and rows.loss[found] < rows.loss[h] - SLACK * opt.tolerance * rows.noise2[h]):
            return
        copy_row(k, found, h)


def refine(k, h):
    """The chosen fit of h forces, where its step budget left it open (not converged, not stalled): up to
    ``refine_iterations`` more steps from where it stands, then finished on the exact model."""
    rows = rows_of(k)
    opt = k.opt
    if rows.converged[h] or rows.steps[h] < opt.iterations or rows.damping[h] >= opt.max_damping:
        return
    if opt.refine_iterations == 0:
        return
    work_ids(k, 1)
    ids = search_of(k).ids
    i = ids[0]
    load_row(k, i, h, rows.s[h], rows.f[h], rows.interval[h])
    start(k, i, opt.refine_iterations)
    solve_rows(k, ids, 1, opt.refine_iterations, STOP_NONE, 0.0, False)
    finish(k, i, opt.exact_steps)
    copy_row(k, i, h)


NEGLIGIBLE = 9.21
"""A force whose (f_x, f_y) lies within this squared distance of zero, in its own standard deviations, is not told
apart from no force (the Wald test of f = 0 at 1 %: the chi-square law of 2 degrees of freedom)."""


def drop_negligible(k):
    """Where the chosen fit of h >= 2 forces holds a force that is zero within its uncertainty, the fit without it
    starts the count below, and the count is chosen again. Such a force stands in for nothing: it appears where the
    search of h - 1 forces ended in a wrong minimum (large bends make the loss far from the small-deflection lever
    the scan assumes), and without it the fit of h forces is the better fit of h - 1. Repeated while the count
    falls."""
    rows = rows_of(k)
    sw = search_of(k)
    H = k.opt.max_forces
    if k.opt.fixed >= 0:
        return
    for _ in range(H):
        chosen = choose(k)
        if chosen < 2 or not sw.fitted[chosen] or not sw.fitted[chosen - 1]:
            return
        if late(k):
            k.info[0].cut = True
            return
        doubtful(k, chosen)
        drop = -1
        for j in range(chosen):
            zx = rows.f[chosen, j, 0] / sw.std[j, 1]
            zy = rows.f[chosen, j, 1] / sw.std[j, 2]
            if drop < 0 and not (zx * zx + zy * zy > NEGLIGIBLE):  # (NaN: undetermined, so negligible too)
                drop = j
        if drop < 0:
            return
        without_force(k, chosen, drop)
        load_row(k, H + 1, chosen - 1, sw.bs, sw.bf, sw.bint)
        try_starts(k, chosen - 1, 1)
        if choose(k) >= chosen:
            return


def merge_patches(k):
    """Where the chosen fit of h >= 2 forces holds a pair the gratings cannot tell from one patch of load
    (:func:`.counts.unresolved_pair`: within ``PATCH_SPAN`` spacings where the fit of h - 1 forces explains the
    reading at the given noise, within ``PATCH_SPAN_MISFIT`` where it misfits or the noise is not given) and the
    data do not pin the pair down (the fit is poorly determined, :func:`doubtful`), the reading's count is capped at
    h - 1 and chosen again, the answer poorly determined (:func:`report`) or a misfit (``Options.merge_patches``, the
    noise rule only). Repeated while the count falls. Whether the count fell."""
    rows = rows_of(k)
    sw = search_of(k)
    if k.opt.fixed >= 0 or not k.opt.merge_patches or k.opt.rule != RULE_NOISE:
        return False
    fell = False
    for _ in range(k.opt.max_forces):
        chosen = choose(k)
        if chosen < 2 or not sw.fitted[chosen] or not sw.fitted[chosen - 1]:
            return fell
        explains = k.info[0].known and not unexplained(k, chosen - 1, rows.loss[chosen - 1])
        span = PATCH_SPAN if explains else PATCH_SPAN_MISFIT
        if not unresolved_pair(rows.s[chosen], rows.f[chosen], chosen, span, spacing(k)):
            return fell
        if not doubtful(k, chosen):  # the data pin the pair down: two forces, resolved
            return fell
        k.info[0].cap = chosen - 1
        fell = True
    return fell


# ------------------------------------------------------------------------------------------------ counts
def choose(k):
    """The count chosen from the best loss of each count so far."""
    sw = search_of(k)
    H = k.opt.max_forces
    for h in range(H + 1):
        sw.losses[h] = rows_of(k).loss[h]
    if k.opt.fixed >= 0:
        return k.opt.fixed
    chosen, _ = select_count(k, sw.losses, H + 1)
    return chosen


def doubtful(k, h):
    """Whether the best fit of h forces is poorly determined (:mod:`.covariance`)."""
    rows = rows_of(k)
    sw = search_of(k)
    n = 2 * k.rod.num_gratings
    lw = lm_of(k)
    bounds(k, rows.interval[h], h, lw.lo, lw.hi)
    sided(k, rows.J[h], rows.s[h], lw.hi, rows.interval[h], h, n, sw.Jrep)
    info = k.info[0]
    if info.known:
        sigma = math.sqrt(info.noise2)
    else:
        dof = info.residuals - 3 * h
        sigma = math.sqrt(rows.loss[h] / (dof if dof > 1 else 1) + k.opt.floor2)
    return uncertainty(k, sw.Jrep, h, h, rows.s[h], rows.f[h], rows.interval[h], sigma, sw.std)


def load_guess(k, i, h, gs, gf):
    """Row i starts from a guess of h forces (gs (h,) [m], model coordinates; gf (h, 2) [N]): a guess that is not
    finite becomes a force with no load in the middle of the first interval; each force in its interval."""
    rows = rows_of(k)
    rd = reading_of(k)
    ok = True
    for j in range(h):
        ok = ok and math.isfinite(gs[j]) and math.isfinite(gf[j, 0]) and math.isfinite(gf[j, 1])
    rows.count[i] = h
    for j in range(h):
        s = gs[j] if ok else 0.5 * (rd.lo[0] + rd.hi[0])
        if s < 0.0:
            s = 0.0
        if s > k.rod.length:
            s = k.rod.length
        interval_of(k, s, rows.interval[i], rows.s[i], j)
        rows.f[i, j, 0] = gf[j, 0] if ok else 0.0
        rows.f[i, j, 1] = gf[j, 1] if ok else 0.0
        rows.held[i, j] = False


def scan_from(k, h):
    """The scan for a force added to the best fit of h - 1 forces: its starts for h forces, and the loss it
    promises to take away (``gain[h]``)."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    T = opt.starts if opt.starts > 1 else 1
    base_loss = scan_model(k, rows.s[h - 1], rows.f[h - 1], rows.interval[h - 1], h - 1, h - 1)
    sw.gain[h] = scan_starts(k, rows.s[h - 1], rows.f[h - 1], h - 1, base_loss, T, opt.max_force_step, sw.sc_s[h],
                             sw.sc_f[h], sw.sc_int[h], sw.sc_pred[h], 0, 1)  # fmt: skip
    sw.have_scan[h] = True


def fit_counts(k, gs, gf, guse, gcount):
    """The best fit of each count 0..H (module docstring). Guesses: block g holds gcount[g] forces (gs (K, H) [m],
    gf (K, H, 2) [N]) and is used where guse[g]."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    H = opt.max_forces
    rule_settle = opt.settle and opt.fixed < 0 and opt.starts > 0
    rows.count[0] = 0
    finish(k, 0, 0)
    rows.converged[0] = True
    rows.done[0] = True
    rows.steps[0] = 0
    sw.fitted[0] = True
    sw.losses[0] = rows.loss[0]
    # Trusted guesses amortise the search: a count they give is fitted from them alone with no scan, and a count
    # below the largest they give, without a guess of its own, is not fitted at all.
    top_guess = 0
    if opt.trusted:
        for g in range(gcount.shape[0]):
            if guse[g] and gcount[g] > top_guess:
                top_guess = gcount[g]
    is_open = True
    for h in range(1, H + 1):
        sw.fitted[h] = False
        sw.have_scan[h] = False
        sw.unscanned[h] = False
        blank_row(k, h, h)
        sw.losses[h] = math.nan
        if h > searched(k):  # (the fixed count's escape fits the count above it: :func:`escape`)
            continue
        if is_open and late(k):
            k.info[0].cut = True
            is_open = False
        nr = 0
        if is_open:
            for g in range(gcount.shape[0]):
                if gcount[g] == h and guse[g]:
                    load_guess(k, H + 1 + nr, h, gs[g], gf[g])
                    nr += 1
        guessed = opt.trusted and nr > 0
        if is_open and opt.starts > 0 and h < top_guess and not guessed:
            continue
        if is_open and opt.starts > 0 and not guessed:
            scan_from(k, h)
            if rule_settle and settled(k, sw.losses, h, sw.gain[h]):
                is_open = False
        if not is_open:
            continue
        if opt.starts > 0:
            if guessed:
                sw.unscanned[h] = True  # trusted guesses start alone
            else:
                load_row(k, H + 1 + nr, h, sw.sc_s[h, 0], sw.sc_f[h, 0], sw.sc_int[h, 0])
                nr += 1
        if nr > 0:
            first_fits(k, h, nr)
            sw.fitted[h] = True
            sw.losses[h] = rows.loss[h]


def search_further(k):
    """The suspicious fits that matter searched further, then the chosen fit refined (module docstring)."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    H = opt.max_forces
    top = searched(k)
    for h in range(2, top + 1):
        # Above a chosen count whose fit came from trusted guesses alone: the scan's best start too, as the full
        # search fits it (a guess in a wrong local minimum there would keep the count too small).
        if not sw.unscanned[h] or not sw.fitted[h - 1]:
            continue
        if sw.fitted[h] and choose(k) == h - 1:
            if late(k):
                k.info[0].cut = True
                continue
            if not sw.have_scan[h]:
                scan_from(k, h)
            load_row(k, H + 1, h, sw.sc_s[h, 0], sw.sc_f[h, 0], sw.sc_int[h, 0])
            try_starts(k, h, 1)
    chosen = choose(k)
    for h in range(top + 1):
        sw.near_limit[h] = plausible_limit(k, sw.losses, top + 1, h)
    misfit = unexplained(k, chosen, rows.loss[chosen])
    doubt = chosen >= 2 and sw.fitted[chosen] and doubtful(k, chosen)
    for h in range(1, top + 1):
        loss_limit, kink_limit = suspect_limits(k, h)
        cand = sw.fitted[h] and suspicious(k, h, loss_limit, kink_limit)
        near = rows.loss[h] <= sw.near_limit[h]
        # (a count fitted from trusted guesses alone is not searched further for explaining most of the one below)
        most = rows.loss[h] <= opt.explained * rows.loss[h - 1] and not sw.unscanned[h]
        forced = (chosen == h + 1 and doubt) or (chosen == h - 1 and misfit)
        cand = (cand and (chosen == h or (chosen > h and (near or most)))) or (sw.fitted[h] and forced)
        wide = chosen == h or forced
        if not cand:
            continue
        if late(k):
            k.info[0].cut = True
            continue
        if forced:  # next to a doubtful or unexplained answer every fit is suspicious
            loss_limit = 0.0
            kink_limit = 0.0
        if not sw.have_scan[h] and sw.fitted[h - 1] and opt.starts > 1:
            scan_from(k, h)  # a count fitted from trusted guesses alone, scanned once it looks suspicious
        if sw.have_scan[h] and opt.starts > 1:
            for t in range(1, opt.starts):
                load_row(k, H + t, h, sw.sc_s[h, t], sw.sc_f[h, t], sw.sc_int[h, t])
            try_starts(k, h, opt.starts - 1)
        if wide and h >= 2 and suspicious(k, h, loss_limit, kink_limit):
            exchange(k, h, loss_limit, kink_limit)
    drop_negligible(k)
    finish_chosen(k)
    if merge_patches(k):
        finish_chosen(k)


def finish_chosen(k):
    """The chosen fit refined where its step budget left it open (:func:`refine`), unless the reading is late (then
    an open fit marks it cut)."""
    rows = rows_of(k)
    chosen = choose(k)
    if chosen >= 1 and search_of(k).fitted[chosen]:
        if late(k):
            if not rows.converged[chosen]:
                k.info[0].cut = True
        else:
            refine(k, chosen)


def searched(k):
    """The largest count the search fits and chooses among: the fixed count, else ``max_forces`` (with a fixed
    count the rows hold one count more, for :func:`escape`)."""
    return k.opt.fixed if k.opt.fixed >= 0 else k.opt.max_forces


def turning(k):
    """How far the reading turns the rod [rad]: the integral of |u - u0| along it (u0 the unloaded curvature), from
    the gratings' values by the trapezoid rule, the base's segment at the first grating's value and a missing
    grating's value zero. Read from the residual of no force (row 0), which holds ``(u0 - u) w``."""
    G = k.rod.num_gratings
    q = model_of(k).query
    r = rows_of(k).r[0]
    total = 0.0
    before = 0.0
    for g in range(G):
        size = 0.0
        if k.w[2 * g] > 0.0 and k.w[2 * g + 1] > 0.0:
            x = r[2 * g] / k.w[2 * g]
            y = r[2 * g + 1] / k.w[2 * g + 1]
            size = math.sqrt(x * x + y * y)
        if g == 0:
            total += size * q[0]
        else:
            total += 0.5 * (size + before) * (q[g] - q[g - 1])
        before = size
    return total


def escape(k):
    """A fixed count h >= 1 whose fit misfits a reading that turns the rod far (more than ``escape_turning``),
    searched once more through h + 1 forces.

    The scan's starts assume small deflections; at a large bend the search of h forces alone can end in a wrong
    minimum that misfits, while the fit of h + 1 forces reaches the right one with one force to spare. So the count
    h + 1 is fitted from the scan of the best h and, while it looks suspicious, searched further as a chosen count
    is (the scan's other starts, the exchange); that fit without its weakest force starts h once more, and the
    better fit of h is kept. The count above stays out of the answer; its evaluations are counted."""
    opt = k.opt
    h = opt.fixed
    if h < 1 or opt.max_forces <= h or k.info[0].cut:
        return
    rows = rows_of(k)
    sw = search_of(k)
    if not unexplained(k, h, rows.loss[h]) or not turning(k) > opt.escape_turning:
        return
    if late(k):
        k.info[0].cut = True
        return
    H = opt.max_forces
    up = h + 1
    scan_from(k, up)
    load_row(k, H + 1, up, sw.sc_s[up, 0], sw.sc_f[up, 0], sw.sc_int[up, 0])
    first_fits(k, up, 1)
    sw.fitted[up] = True
    loss_limit, kink_limit = suspect_limits(k, up)
    if opt.starts > 1 and suspicious(k, up, loss_limit, kink_limit):
        for t in range(1, opt.starts):
            load_row(k, H + t, up, sw.sc_s[up, t], sw.sc_f[up, t], sw.sc_int[up, t])
        try_starts(k, up, opt.starts - 1)
    if suspicious(k, up, loss_limit, kink_limit):
        exchange(k, up, loss_limit, kink_limit)
    weakest = 0
    least = math.inf
    for j in range(up):
        size = rows.f[up, j, 0] * rows.f[up, j, 0] + rows.f[up, j, 1] * rows.f[up, j, 1]
        if size < least:
            least = size
            weakest = j
    without_force(k, up, weakest)
    load_row(k, H + 1, h, sw.bs, sw.bf, sw.bint)
    try_starts(k, h, 1)
    if not late(k):
        refine(k, h)


# ------------------------------------------------------------------------------------------------ the reading
def prepare(k, noise2):
    """The reading's intervals between its present gratings (the last closed by the tip; a grating at the tip
    closes none), its residual count and its noise (``noise2`` < 0: unknown)."""
    G = k.rod.num_gratings
    L = k.rod.length
    info = k.info[0]
    rd = reading_of(k)
    query = model_of(k).query
    m = 0
    for g in range(G):
        if k.w[2 * g] > 0.0:
            rd.lo[m] = query[g]
            rd.lo_k[m] = g
            m += 1
    for j in range(m, G):
        rd.lo[j] = L
        rd.lo_k[j] = -1
    intervals = 0
    for j in range(G):
        if j + 1 < m:
            rd.hi[j] = rd.lo[j + 1]
            rd.hi_k[j] = rd.lo_k[j + 1]
        else:
            rd.hi[j] = L
            rd.hi_k[j] = -1
        if j < m and rd.hi[j] > rd.lo[j]:
            intervals += 1
    info.intervals = intervals
    info.residuals = 2 * m
    info.eigen_m = -1
    info.known = noise2 >= 0.0
    info.noise2 = noise2 if noise2 >= 0.0 else 0.0
    info.evaluations = 0
    info.cut = False
    info.cap = k.opt.max_forces


def location_key(s):
    """A location as a sort key: a location that is not a number after every number."""
    return s if s == s else math.inf


def report(k, b, out):
    """The reading's answer into the outputs at b: the chosen count, its forces by location with the location
    bias, their standard deviations, the loss of every count and the diagnostics."""
    rows = rows_of(k)
    sw = search_of(k)
    opt = k.opt
    info = k.info[0]
    H = opt.max_forces
    W = out.s.shape[1]
    if opt.fixed < 0:
        for h in range(H + 1):
            sw.losses[h] = rows.loss[h]
        chosen, sigma = select_count(k, sw.losses, H + 1)
    else:
        chosen = 0
        for h in range(opt.fixed + 1):
            if sw.fitted[h]:
                chosen = h
        if info.known:
            sigma = math.sqrt(info.noise2)
        else:
            dof = info.residuals - 3 * chosen
            v = rows.loss[chosen] / (dof if dof > 1 else 1)
            sigma = math.sqrt((v if v > 0.0 else 0.0) + opt.floor2)
    n = 2 * k.rod.num_gratings
    for m in range(n):
        for p in range(3 * W):
            sw.Jrep[m, p] = 0.0
    lw = lm_of(k)
    if chosen:
        bounds(k, rows.interval[chosen], chosen, lw.lo, lw.hi)
        sided(k, rows.J[chosen], rows.s[chosen], lw.hi, rows.interval[chosen], chosen, n, sw.Jrep)
    for j in range(W):
        sw.slot_s[j] = rows.s[chosen, j] if j < chosen else 0.0
        sw.slot_f[j, 0] = rows.f[chosen, j, 0] if j < chosen else 0.0
        sw.slot_f[j, 1] = rows.f[chosen, j, 1] if j < chosen else 0.0
        sw.slot_int[j] = rows.interval[chosen, j] if j < chosen else 0
    poorly = uncertainty(k, sw.Jrep, W, chosen, sw.slot_s, sw.slot_f, sw.slot_int, sigma, sw.std)
    poorly = poorly or info.cap < H  # (a count merged down from a pair it could not pin down: merge_patches)
    for j in range(W):  # by location (stable; a location that is not a number last among the forces)
        sw.order[j] = j
    for a in range(1, chosen):
        v = sw.order[a]
        key = location_key(sw.slot_s[v])
        c = a
        while c > 0 and location_key(sw.slot_s[sw.order[c - 1]]) > key:
            sw.order[c] = sw.order[c - 1]
            c -= 1
        sw.order[c] = v
    for j in range(W):
        o = sw.order[j]
        if j < chosen:
            out.s[b, j] = sw.slot_s[o] + k.rod.bias
            out.f[b, j, 0] = sw.slot_f[o, 0]
            out.f[b, j, 1] = sw.slot_f[o, 1]
            for c in range(3):
                out.std[b, j, c] = sw.std[o, c]
        else:
            out.s[b, j] = 0.0
            out.f[b, j, 0] = 0.0
            out.f[b, j, 1] = 0.0
            for c in range(3):
                out.std[b, j, c] = math.nan
    loss = rows.loss[chosen]
    converged = rows.converged[chosen] and math.isfinite(loss)
    out.count[b] = chosen
    out.loss[b] = loss
    out.converged[b] = converged
    out.iterations[b] = rows.steps[chosen]
    out.poorly[b] = poorly
    out.sigma[b] = sigma
    out.evaluations[b] = info.evaluations
    out.cut[b] = info.cut
    out.p_value[b] = p_value(k, chosen, loss)
    out.status[b] = verdict(k, chosen, loss, converged, poorly)
    for h in range(W + 1):
        out.losses[b, h] = math.nan
        if (opt.fixed < 0 or h == opt.fixed) and h <= H and sw.fitted[h]:
            out.losses[b, h] = rows.loss[h]


def estimate_one(b, setup, batch, arenas, flag):
    """The estimate of reading b of the batch (module docstring) on the scratch ``arenas``, written to
    ``batch.out``."""
    k = Kit(setup.rod[0], setup.opt[0], setup.lay[0], arenas.info, setup.const, arenas.f, arenas.i, arenas.c,
            arenas.b, batch.u[b], batch.w[b], flag)  # fmt: skip
    prepare(k, batch.noise2[b])
    fit_counts(k, batch.gs[b], batch.gf[b], batch.guse[b], setup.gcount)
    search_further(k)
    escape(k)
    report(k, b, batch.out)


def estimate_rows(first, last, setup, batch, arenas, flag):
    """Readings first..last-1 of the batch one after the other on one scratch (the CPU's entry, and the plain
    Python one for debugging)."""
    for b in range(first, last):
        estimate_one(b, setup, batch, arenas, flag)
