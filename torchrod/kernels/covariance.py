"""The uncertainty of a fit and whether the data decide it: the Gauss-Newton covariance at the optimum.

Near the optimum the residuals are r ~ r* + J (theta - theta*), so with independent sensor noise sigma per component
the estimate's covariance is ``sigma^2 (J^T J)^-1``. It is taken in scaled form, ``D (D J^T J D)^-1 D`` with
D = diag(J^T J)^(-1/2), whose eigenvalues measure identifiability whatever the units. A fit is *poorly determined*
when that matrix's condition number exceeds ``condition_limit``; when it has fewer residuals than unknowns, or the
gratings proximal to its most distal force leave fewer than three residuals beyond its unknowns; when a force lies
in the first interval (one grating sees it: magnitude and lever cannot be told apart); when a location's standard
deviation exceeds its interval's length; or when a standard deviation is not finite. A force on a grating (a kink
of the loss) is judged from both one-sided Jacobians, and the worse counts.
"""

import math

from .fit import KINK, gram
from .linalg import symmetric_eigen
from .views import cov_of, model_of, reading_of

COVARIANCE_PARTS: dict[str, dict[str, tuple[tuple[int | str, ...], str]]] = {
    "cov": {  # the covariance's work
        "Jm": (("n", "P"), "f"), "ok": (("P",), "b"), "d": (("P",), "f"), "C": (("P", "P"), "f"),
        "w": (("P",), "f"), "V": (("P", "P"), "f"), "a": (("P", "P"), "f"), "inv": (("P",), "f"),
        "cov": (("P", "P"), "f"), "active": (("P",), "b"), "Js": (("n", "P"), "f"), "std2": (("W", 3), "f"),
        "tail": (("P",), "i"), "last": (("P", "P"), "f"),
    },
}  # fmt: skip
"""The parts of a reading's arenas that this module's functions own, by group: {name: (shape, kind)}, in the terms of
:data:`.layout.SPEC`, which places every kernel module's groups in the arenas and generates their views."""

DIAG_MIN = 1e-300
"""An unknown whose J^T J diagonal is not above this has no scale: not determined."""

EPS = 2.220446049250313e-16
"""float64's machine epsilon: eigenvalues below EPS x the largest count as zero."""

INLINE = ("near_kink",)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def covariance(k, J, P, active, sigma, cov):
    """``sigma^2 (J^T J)^-1`` (P x P, in the columns' units) over the active columns (``active[p]``; the others, and
    everything where J or the matrix is not finite, NaN) into cov; returns the condition number of the
    unit-diagonal matrix (inf where singular or not finite)."""
    cw = cov_of(k)
    n = 2 * k.rod.num_gratings
    finite_rows = True
    for m in range(n):
        for p in range(P):
            v = J[m, p]
            if not math.isfinite(v):
                finite_rows = False
                v = 0.0
            cw.Jm[m, p] = v if active[p] else 0.0
    gram(cw.Jm, n, P, cw.C, cw.tail)  # J^T J, scaled to unit diagonal in place
    unscaled = False
    for p in range(P):
        acc = cw.C[p, p]
        cw.ok[p] = active[p] and acc > DIAG_MIN and math.isfinite(acc)
        cw.d[p] = 1.0 / math.sqrt(acc) if cw.ok[p] else 0.0
        unscaled = unscaled or (active[p] and not cw.ok[p])
    for p in range(P):
        for q in range(p + 1):
            v = 1.0 if p == q else 0.0
            if cw.ok[p] and cw.ok[q]:
                v = cw.C[p, q] * cw.d[p] * cw.d[q]
            cw.C[p, q] = v
            cw.C[q, p] = v
    # Beyond the last active column the matrix is the identity: its eigenvalues are 1 and its eigenvectors the unit
    # vectors there, so only the leading block needs the eigensolver (a unit-diagonal matrix has an eigenvalue at
    # most and one at least 1, so the identity's leave the extremes as they are).
    m = 0
    for p in range(P):
        if active[p]:
            m = p + 1
    ok = eigen_again(k, cw.C, cw.w, cw.V, cw.a, m)
    lo = 1.0
    hi = 1.0
    if m > 0:
        lo = cw.w[0] if m == P or cw.w[0] < 1.0 else 1.0
        hi = cw.w[m - 1] if m == P or cw.w[m - 1] > 1.0 else 1.0
    condition = math.inf
    if ok and lo > EPS * abs(hi) and not unscaled and finite_rows:
        condition = hi / lo
    s2 = sigma * sigma
    for p in range(m):
        cw.inv[p] = 1.0 / cw.w[p] if cw.w[p] > EPS * abs(hi) else 0.0
    for p in range(P):
        for q in range(P):
            v = math.nan
            if ok and finite_rows and cw.ok[p] and cw.ok[q]:
                acc = 0.0
                for e in range(m):
                    acc += cw.V[p, e] * cw.inv[e] * cw.V[q, e]
                v = acc * cw.d[p] * cw.d[q] * s2
            cov[p, q] = v
    return condition


def eigen_again(k, C, w, V, a, m):
    """:func:`.linalg.symmetric_eigen` of C's leading m x m block into w and V, unless that block is the one the
    last call of this reading took, bit for bit: then w and V hold its results already (a chosen fit is judged when
    the search doubts it and again when it is reported)."""
    info = k.info[0]
    last = cov_of(k).last
    same = info.eigen_m == m
    for p in range(m if same else 0):
        for q in range(m):
            x = C[p, q]
            y = last[p, q]
            if not (x == y and math.copysign(1.0, x) == math.copysign(1.0, y)):  # (NaN: never the same)
                same = False
    if same:
        return info.eigen_ok
    ok = symmetric_eigen(C, w, V, a, m)
    for p in range(m):
        for q in range(m):
            last[p, q] = C[p, q]
    info.eigen_m = m
    info.eigen_ok = ok
    return ok


def judge(k, J, W, count, s, interval, sigma, std):
    """The standard deviations std (W, 3) of (s [m], f_x [N], f_y [N]) of a fit of ``count`` forces held in W
    slots (J (n, 3W) its scaled Jacobian, the slots beyond count padding, NaN), and whether it is poorly
    determined (module docstring)."""
    cw = cov_of(k)
    P = 3 * W
    for p in range(P):
        cw.active[p] = p // 3 < count
    condition = covariance(k, J, P, cw.active, sigma, cw.cov)
    L = k.rod.length
    FU = k.rod.force_unit
    for j in range(W):
        for c in range(3):
            unit = L if c == 0 else FU
            var = cw.cov[3 * j + c, 3 * j + c] * unit * unit
            if var != var:
                std[j, c] = math.nan
            else:
                std[j, c] = math.sqrt(var if var > 0.0 else 0.0)
    poorly = not (condition <= k.opt.condition_limit)
    info = k.info[0]
    rd = reading_of(k)
    query = model_of(k).query
    distal = -1.0
    for j in range(count):
        if s[j] > distal:
            distal = s[j]
        if interval[j] == 0:
            poorly = True  # one grating sees it
        for c in range(3):
            if not math.isfinite(std[j, c]):
                poorly = True
        if std[j, 0] > rd.hi[interval[j]] - rd.lo[interval[j]]:
            poorly = True  # located no better than its interval
    informative = 0
    for g in range(k.rod.num_gratings):
        if k.w[2 * g] > 0.0 and query[g] < distal:
            informative += 2
    if info.residuals < 3 * count or (count > 0 and informative - 3 * count < 3):
        poorly = True
    return poorly


def near_kink(k, s, h):
    """Whether a force lies within :data:`KINK` of a present grating (on the loss's kink there)."""
    query = model_of(k).query
    for j in range(h):
        for g in range(k.rod.num_gratings):
            if k.w[2 * g] > 0.0 and abs(s[j] - query[g]) <= KINK:
                return True
    return False


def uncertainty(k, J, W, count, s, f, interval, sigma, std):
    """:func:`judge` of a fit, from both one-sided Jacobians where a force sits on a grating (the larger standard
    deviations, and poorly determined if either side is). J (n, 3W) is the fit's sided Jacobian; std (W, 3) out."""
    if not near_kink(k, s, count):
        return judge(k, J, W, count, s, interval, sigma, std)
    cw = cov_of(k)
    n = 2 * k.rod.num_gratings
    P = 3 * W
    scale = k.rod.length / k.rod.ei
    query = model_of(k).query
    poorly = False
    for side in range(2):
        for m in range(n):
            for p in range(P):
                cw.Js[m, p] = J[m, p]
        for j in range(count):
            for g in range(k.rod.num_gratings):
                if k.w[2 * g] > 0.0 and abs(s[j] - query[g]) <= KINK:
                    # proximal: the grating does not see the force move; distal: it sees the slope jump
                    cw.Js[2 * g, 3 * j] = 0.0 if side == 0 else -f[j, 1] * scale
                    cw.Js[2 * g + 1, 3 * j] = 0.0 if side == 0 else f[j, 0] * scale
        worse = judge(k, cw.Js, W, count, s, interval, sigma, cw.std2 if side else std)
        poorly = poorly or worse
    for j in range(W):
        for c in range(3):
            if std[j, c] == std[j, c] and not cw.std2[j, c] <= std[j, c]:  # the larger; NaN wins
                std[j, c] = cw.std2[j, c]
    return poorly
