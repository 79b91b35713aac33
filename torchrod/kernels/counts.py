"""Choosing the number of forces (0 included) from the best loss of each count, for one reading.

The loss of a fit of h forces to n residuals is ``loss_h`` [1/m^2]; ``loss_0`` is the reading's own energy. Two
rules (``Options.rule``):

``RULE_THRESHOLD`` (the paper's): the first h with ``loss_h < threshold``, else the largest h fitted. The
    threshold has units and ignores the number of gratings and the noise; kept to reproduce the paper.

``RULE_NOISE`` (the default): nested likelihood-ratio tests, smallest h first. Adding k forces to a model that
    already holds the true ones lowers the loss by sigma^2 times a chi-square variable with 3k degrees of freedom,
    except that the added locations are free: the drop is a maximum over locations, whose tail is heavier, so the
    test takes the Bonferroni bound over the G grating intervals. h is accepted when, for every larger fitted h',
    ``loss_h - loss_h' <= sigma^2 chi2_{1 - alpha/G}(3 (h' - h))``, and (a guard against gross misfit) ``loss_h <=
    sigma^2 chi2_{1 - alpha/50}(n - 3h)``. The smallest accepted h wins; if none is, the fewest forces that no
    larger count improves on beyond noise; failing that, the largest fitted count. With sigma unknown it is
    estimated from the largest fit, ``sigma^2 = loss_H / (n - 3 H)``, and the drops are tested with the F law (no
    misfit guard: the misfit is what estimates sigma). sigma^2 includes the floor^2 in both cases.

Either rule chooses only among the counts the reading can test (:func:`testable`): a fit of h forces has 3h unknowns
against the reading's n values (2 per present grating), and a count leaving fewer than ``Options.min_dof`` degrees
of freedom is never chosen, however well it fits (with none left it always fits exactly). Those counts are left out
of the tests altogether (the noise's estimate and the drops included), as if not fitted; a fixed count
(``Options.fixed``) is the caller's choice and is not judged. Where the chosen count cannot explain the reading at
the noise, the verdict says so (:func:`unexplained`: ``misfit``).

A patch of load shorter than the gratings' spacing is one contact that a point force does not quite fit: a grating
under the patch reads more than one force at its centre would give. To the gratings such a patch is a force and a
light force beside it pushing the same way (:func:`unresolved_pair`), and the count tests may answer it so. Where
the chosen fit holds such a pair and the data do not pin the pair down (the fit is poorly determined), the
reading's count is capped at one force fewer (its ``cap`` in :data:`.layout.INFO`, set by
:func:`torchrod.kernels.search.merge_patches` with ``Options.merge_patches``; the noise rule only), and the tests
choose again among the counts below. The pair may lie ``PATCH_SPAN`` spacings apart where the fit of one force
fewer explains the reading at the given noise, ``PATCH_SPAN_MISFIT`` where it does not (the answer is then a
``misfit``: one contact, not a point) or the noise is not given; otherwise it is poorly determined. The cap acts as
:func:`testable` does: counts above it are left out of the tests.

The quantiles come from tables the caller makes once (:func:`torchrod.kernels.host.count_tables`, held in the
``tables`` group of :data:`COUNTS_PARTS`, indexed by the count difference and by the degrees of
freedom). The one special function computed here is the chi-square
survival of the reported p-value (:func:`chi2_survival`), once per reading.
"""

import math

from .status import MISFIT, OK, POORLY_DETERMINED, TIMEOUT, UNCONVERGED
from .views import reading_of, tables_of

COUNTS_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "tables": {  # the count tests' quantiles (:func:`torchrod.kernels.host.count_tables`)
        "drop_chi2": (("KT",), "k"), "drop_f": (("KT", "D"), "k"), "misfit": (("D",), "k"), "guard": (("D",), "k"),
        "suspect": (("D",), "k"), "kink": (("D",), "k"), "verdict": (("D",), "k"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

RULE_NOISE = 0
RULE_THRESHOLD = 1

PAPER_THRESHOLD = 3.0
"""[1/m^2] The paper's count threshold: the first h whose loss drops below it (``RULE_THRESHOLD``'s default, and
the paper reproduction's rule)."""

MISFIT_FACTOR = 50.0
"""The count tests' misfit guard runs at ``alpha / MISFIT_FACTOR``: it only rejects fits far worse than noise."""

PATCH_SPAN = 2.5
"""A pair of forces is taken for one patch only when they lie less than this many grating spacings apart, where one
force fewer explains the reading at the given noise (:func:`unresolved_pair`)."""

PATCH_SPAN_MISFIT = 1.5
"""A pair of forces is taken for one patch only when they lie less than this many grating spacings apart, where one
force fewer misfits the reading or the noise is not given. At a low noise one force misfits a patch over a grating
(the gratings see that it is no point), and the pair that stands in for it lies within about one spacing; a real
pair whose light force the count tests find lies further apart, mostly."""

PATCH_COSINE = 0.8660254037844387
"""A pair of forces is taken for one patch only when they push the same way: the cosine of the angle between them at
least this (30 degrees). A patch's load is one-signed; a real pair's directions are independent."""

PATCH_LEVER = 0.125
"""A pair of forces is taken for one patch only when the lighter force's moment about the heavier one's location,
``|f_light| d``, is below this fraction of the pair's load times the grating spacing, ``(|f_a| + |f_b|) spacing``.
A patch of width w centred on a grating makes that grating read its load times w / 8 more moment than one force
at its centre would, so this bounds what a patch no longer than the spacing can stand in for."""

SETTLE_SAFETY = 2.0
"""A count is settled when even ``loss_last - SETTLE_SAFETY x gain`` (the scan's promise for one more force, a
local estimate) would not make the next count chosen."""

INLINE = (
    "testable",
    "dof_index",
    "largest_fitted",
    "test_sigma2",
    "drop_limit",
    "misfit_limit",
    "passes_drops",
    "quantile_scale",
    "suspect_limits",
    "unexplained",
    "plausible_limit",
    "ceiling",
    "spacing",
)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def testable(k, C):
    """How many of the counts 0..C-1 the reading can test: those whose fit leaves at least ``min_dof`` degrees of
    freedom in its residuals (module docstring), no force always among them; none above the reading's cap."""
    d = k.info[0].residuals - k.opt.min_dof
    top = d // 3 + 1 if d >= 0 else 1
    cap = k.info[0].cap + 1  # (the count a patch's pair has been merged down to, :func:`unresolved_pair`)
    if cap < top:
        top = cap
    return top if top < C else C


def dof_index(k, d):
    """A degrees-of-freedom count as an index into the tables (row 0 holds the values for d <= 0)."""
    return d if d > 0 else 0


def largest_fitted(losses, C):
    """The largest count with a loss (0 where none has)."""
    last = 0
    for h in range(C):
        if losses[h] == losses[h]:
            last = h
    return last


def test_sigma2(k, losses, C):
    """sigma^2 [1/m^2] of the count tests, and the degrees of freedom the F law takes (0 with the noise known)."""
    info = k.info[0]
    if info.known:
        return info.noise2, 0
    last = largest_fitted(losses, C)
    dof = info.residuals - 3 * last
    s2 = k.opt.floor2
    if dof > 0:
        s2 += losses[last] / dof
    return s2, dof if dof > 1 else 1


def drop_limit(k, dh, dof_ref):
    """The largest drop of the loss [units of sigma^2] that adding dh > 0 forces may make by fitting noise."""
    if k.info[0].known:
        return tables_of(k).drop_chi2[dh]
    return tables_of(k).drop_f[dh, dof_ref]


def misfit_limit(k, h):
    """The largest loss_h / sigma^2 the tests accept (-1 where no degree of freedom is left; inf with the noise
    unknown)."""
    d = k.info[0].residuals - 3 * h
    if d <= 0:
        return -1.0
    if not k.info[0].known:
        return math.inf
    return tables_of(k).misfit[d]


def passes_drops(k, losses, C, h, s2, dof_ref):
    """Whether no larger fitted count improves on h beyond noise."""
    for h2 in range(h + 1, C):
        if losses[h] - losses[h2] > drop_limit(k, h2 - h, dof_ref) * s2:  # NaN (not fitted) passes
            return False
    return True


def select_count(k, losses, C):
    """The chosen count among the testable ones of 0..C-1 (losses NaN where not fitted), and sigma [1/m] (module
    docstring)."""
    info = k.info[0]
    C = testable(k, C)
    last = largest_fitted(losses, C)
    if k.opt.rule == RULE_THRESHOLD:
        chosen = last
        for h in range(C):
            if losses[h] == losses[h] and losses[h] < k.opt.threshold:
                chosen = h
                break
        if info.known:
            return chosen, math.sqrt(info.noise2)
        d = info.residuals - 3 * chosen
        s2 = k.opt.floor2
        if d > 0:
            s2 += losses[chosen] / d
        return chosen, math.sqrt(s2)
    s2, dof_ref = test_sigma2(k, losses, C)
    fewest = -1
    for h in range(C):
        if not losses[h] == losses[h]:
            continue
        if not passes_drops(k, losses, C, h, s2, dof_ref):
            continue
        if fewest < 0:
            fewest = h
        if losses[h] <= misfit_limit(k, h) * s2 and info.residuals - 3 * h > 0:
            return h, math.sqrt(s2)
    return (fewest if fewest >= 0 else last), math.sqrt(s2)


def spacing(k):
    """The mean spacing [m] of the reading's present gratings (0 with fewer than two)."""
    m = k.info[0].residuals // 2
    if m < 2:
        return 0.0
    lo = reading_of(k).lo
    return (lo[m - 1] - lo[0]) / (m - 1)


def unresolved_pair(s, f, h, span, delta):
    """Whether two of the h forces (s (h,) [m], f (h, 2) [N]) look to gratings ``delta`` [m] apart like one patch of
    load (module docstring): less than ``span`` spacings apart, pushing the same way within ``PATCH_COSINE``, the
    lighter one's moment about the heavier below ``PATCH_LEVER`` of the pair's load times the spacing."""
    if not delta > 0.0:
        return False
    for a in range(h):
        na = math.sqrt(f[a, 0] * f[a, 0] + f[a, 1] * f[a, 1])
        for b in range(a + 1, h):
            nb = math.sqrt(f[b, 0] * f[b, 0] + f[b, 1] * f[b, 1])
            d = abs(s[a] - s[b])
            if not (na > 0.0 and nb > 0.0 and d < span * delta):
                continue
            if f[a, 0] * f[b, 0] + f[a, 1] * f[b, 1] < PATCH_COSINE * na * nb:
                continue
            light = na if na < nb else nb
            if light * d < PATCH_LEVER * (na + nb) * delta:
                return True
    return False


def ceiling(k, losses, C, h):
    """The largest loss [1/m^2] at which count h passes the tests, the other counts' losses as they are: a fit of h
    forces that no better local minimum could bring below it cannot be chosen."""
    if k.opt.rule == RULE_THRESHOLD:
        return k.opt.threshold
    C = testable(k, C)
    s2, dof_ref = test_sigma2(k, losses, C)
    best = math.inf
    for h2 in range(h + 1, C):
        v = losses[h2] + drop_limit(k, h2 - h, dof_ref) * s2
        if v == v and v < best:
            best = v
    guard = misfit_limit(k, h) * s2
    return guard if guard < best else best


def settled(k, losses, C, gain):
    """Whether the count among 0..C-1 is decided whatever count C would reach, given the scan's promised ``gain``
    [1/m^2] of one more force: with a known noise, or the threshold rule; never with the noise unknown (every
    count is needed to estimate it); always where count C is one the reading cannot test (:func:`testable`).
    Uses losses[C] as scratch."""
    if testable(k, C + 1) <= C:
        return True
    if k.opt.rule == RULE_THRESHOLD:
        for h in range(C):
            if losses[h] == losses[h] and losses[h] < k.opt.threshold:
                return True
        return False
    if not k.info[0].known:
        return False
    nxt = losses[C - 1] - SETTLE_SAFETY * gain
    losses[C] = nxt if nxt > 0.0 else 0.0
    chosen, _ = select_count(k, losses, C + 1)
    losses[C] = math.nan
    return chosen <= C - 1


def quantile_scale(k):
    """The sigma^2 [1/m^2] the search's quantiles are taken at: the given noise, or (unknown) the floor."""
    info = k.info[0]
    return info.noise2 if info.known else k.opt.floor2


def suspect_limits(k, h):
    """The losses [1/m^2] above which a fit of h forces is searched further, in general and with a force on a
    grating: the ``suspect`` and ``kink_suspect`` quantiles of a correct fit's loss."""
    d = dof_index(k, k.info[0].residuals - 3 * h)
    scale = quantile_scale(k)
    return tables_of(k).suspect[d] * scale, tables_of(k).kink[d] * scale


def plausible_limit(k, losses, C, h):
    """A count below the chosen one is searched further only under this loss [1/m^2]: ``hopeless`` times the
    smaller of its ceiling and the misfit guard's quantile at the noise."""
    d = dof_index(k, k.info[0].residuals - 3 * h)
    guard = tables_of(k).guard[d] * quantile_scale(k)
    c = ceiling(k, losses, C, h)
    return k.opt.hopeless * (guard if guard < c else c)


def chi2_survival(x, dof):
    """P(X > x) for X ~ chi-square with an integer ``dof`` >= 1 degrees of freedom.

    With y = x / 2, the closed forms of an integer dof: for an even dof 2n, the chance of fewer than n events of a
    Poisson law of mean y, ``sum_{j<n} e^-y y^j / j!``; for an odd dof 2n + 1, ``erfc(sqrt(y))`` plus ``sum_{j<n}
    e^-y y^(j+1/2) / Gamma(j + 3/2)``. Every term is positive, so the sums lose no digits to cancellation; each term
    follows from the previous one by a factor y / (j + d + 1), or, where e^-y would underflow (y > 700), by its
    logarithm.
    """
    if not x > 0.0:
        return 1.0 if x == x else x
    if x == math.inf:
        return 0.0
    y = 0.5 * x
    d = 0.5 * (dof % 2)  # the terms' half-integer offset for an odd dof
    n = dof // 2
    total = math.erfc(math.sqrt(y)) if d > 0.0 else 0.0
    if y <= 700.0:
        term = math.exp(-y) if d == 0.0 else math.exp(-y) * math.sqrt(y) / math.gamma(1.5)
        for j in range(n):
            total += term
            term *= y / (j + d + 1.0)
    else:
        log_y = math.log(y)
        log_term = -y + d * log_y - math.lgamma(d + 1.0)
        for j in range(n):
            total += math.exp(log_term)
            log_term += log_y - math.log(j + d + 1.0)
    return total if total < 1.0 else 1.0


def unexplained(k, h, loss):
    """Whether a fit of h forces with this loss is a misfit (its chi-square p-value at the given noise, or at the
    largest believed, below ``misfit_level``): the loss over that sigma^2 above the level's quantile, or a loss
    that is not a number."""
    if not math.isfinite(loss):
        return True
    d = k.info[0].residuals - 3 * h
    if d <= 0:
        return False
    return loss / misfit_sigma2(k) > tables_of(k).verdict[d]


def misfit_sigma2(k):
    """The misfit test's sigma^2 [1/m^2]: the given noise's, else the largest believed (``max_noise``), with the
    floor."""
    info = k.info[0]
    return info.noise2 if info.known else k.opt.max_noise2


def verdict(k, h, loss, converged, poorly):
    """The reading's status code (:mod:`torchrod.estimate.status`: the first that applies of timeout, misfit,
    unconverged, poorly determined, ok) for its chosen fit of h forces."""
    if k.info[0].cut:
        return TIMEOUT
    if unexplained(k, h, loss):
        return MISFIT
    if not converged:
        return UNCONVERGED
    if poorly:
        return POORLY_DETERMINED
    return OK


def p_value(k, h, loss):
    """The chi-square p-value of a fit of h forces with this loss at the given noise, or at the largest believed
    (the misfit test's: :func:`unexplained`): 0 for a loss that is not a number, NaN with no degree of freedom
    left."""
    if not math.isfinite(loss):
        return 0.0
    d = k.info[0].residuals - 3 * h
    if d <= 0:
        return math.nan
    return chi2_survival(loss / misfit_sigma2(k), d)
