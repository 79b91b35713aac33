"""Small dense linear algebra for one reading: the normal systems of a fit (up to 3 unknowns per force), the
propagator's systems of the scan, and the eigenvalues of the covariance.

Plain numeric Python on arrays passed in (no allocation), so that :mod:`torchrod.kernels.targets` compiles it for
the CPU and for CUDA and it also runs as Python. Every function works on the leading ``P x P`` block of its
arrays, so the callers can pass scratch sized for the largest system. A function that cannot do its job (a
matrix that is not finite, not positive definite, singular) says so by returning False and leaves zeros; it never
raises.
"""

import math

import numpy as np
from numpy.typing import NDArray

EIGEN_SWEEPS = 60
"""Most sweeps of the cyclic Jacobi eigenvalue method: it converges quadratically, in under ten sweeps for the
9 x 9 matrices it is given, so reaching this bound means the input was not a number."""

EIGEN_SETTLED = 3
"""Sweeps after which an off-diagonal entry too small to change either diagonal entry it couples (100 |a_pq| lost
in the rounding of |a_pp| and of |a_qq|) is set to zero instead of rotated: the eigenvalues are then settled to
rounding, and the sweeps that would only drive such entries down to underflow are skipped."""

INLINE = (
    "sumsq",
    "dot",
    "spd_solve",
)
"""Small functions the CUDA target inlines where they are called (:func:`.targets.cuda_namespace`)."""


def sumsq(x: NDArray[np.float64], n: int) -> float:
    """sum_{k < n} x[k]^2."""
    t = 0.0
    for k in range(n):
        t += x[k] * x[k]
    return t


def dot(a: NDArray[np.float64], b: NDArray[np.float64], n: int) -> float:
    """sum_{k < n} a[k] b[k]."""
    t = 0.0
    for k in range(n):
        t += a[k] * b[k]
    return t


def cholesky_factor(M: NDArray[np.float64], L: NDArray[np.float64], P: int) -> bool:
    """The lower Cholesky factor L of the symmetric positive definite M (its lower triangle is read). False where
    M is not finite or not positive definite (L is then left unusable)."""
    for j in range(P):
        d = M[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not (d > 0.0 and math.isfinite(d)):
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, P):
            v = M[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            if not math.isfinite(v):
                return False
            L[i, j] = v / d
    return True


def cholesky_apply(L: NDArray[np.float64], b: NDArray[np.float64], x: NDArray[np.float64], P: int) -> bool:
    """x = (L L^T)^-1 b for the factor of :func:`cholesky_factor` (x may be b). False where x is not finite."""
    for i in range(P):
        v = b[i]
        for k in range(i):
            v -= L[i, k] * x[k]
        x[i] = v / L[i, i]
    ok = True
    for i in range(P - 1, -1, -1):
        v = x[i]
        for k in range(i + 1, P):
            v -= L[k, i] * x[k]
        x[i] = v / L[i, i]
        ok = ok and math.isfinite(x[i])
    return ok


def spd_solve(
    M: NDArray[np.float64], b: NDArray[np.float64], x: NDArray[np.float64], P: int, L: NDArray[np.float64]
) -> bool:
    """Solve M x = b for symmetric positive definite M (P x P), by Cholesky; L (P, P) scratch. True where it
    succeeded (M and b finite, M positive definite, x finite); elsewhere x = 0."""
    ok = cholesky_factor(M, L, P)
    if ok:
        for i in range(P):
            ok = ok and math.isfinite(b[i])
    if ok:
        ok = cholesky_apply(L, b, x, P)
    if not ok:
        for i in range(P):
            x[i] = 0.0
    return ok


def lu_factor(M: NDArray[np.float64], LU: NDArray[np.float64], piv: NDArray[np.int64], P: int) -> bool:
    """LU decomposition with partial pivoting of the general M (P x P) into LU (unit lower and upper triangles)
    and the row order piv. False where M is not finite or singular."""
    for i in range(P):
        piv[i] = i
        for j in range(P):
            v = M[i, j]
            if not math.isfinite(v):
                return False
            LU[i, j] = v
    for k in range(P):
        p = k
        big = abs(LU[k, k])
        for i in range(k + 1, P):
            if abs(LU[i, k]) > big:
                big = abs(LU[i, k])
                p = i
        if big == 0.0:
            return False
        if p != k:
            for j in range(P):
                t = LU[k, j]
                LU[k, j] = LU[p, j]
                LU[p, j] = t
            t_i = piv[k]
            piv[k] = piv[p]
            piv[p] = t_i
        for i in range(k + 1, P):
            m = LU[i, k] / LU[k, k]
            LU[i, k] = m
            for j in range(k + 1, P):
                LU[i, j] -= m * LU[k, j]
    return True


def lu_apply(
    LU: NDArray[np.float64], piv: NDArray[np.int64], b: NDArray[np.float64], x: NDArray[np.float64], P: int
) -> bool:
    """x = M^-1 b from :func:`lu_factor`'s LU and piv (x must not be b). False where x is not finite."""
    for i in range(P):
        v = b[piv[i]]
        for k in range(i):
            v -= LU[i, k] * x[k]
        x[i] = v
    ok = True
    for i in range(P - 1, -1, -1):
        v = x[i]
        for k in range(i + 1, P):
            v -= LU[i, k] * x[k]
        x[i] = v / LU[i, i]
        ok = ok and math.isfinite(x[i])
    return ok


def symmetric_eigen(
    A: NDArray[np.float64], w: NDArray[np.float64], V: NDArray[np.float64], a: NDArray[np.float64], P: int
) -> bool:
    """Eigenvalues w (ascending) and orthonormal eigenvectors (the columns of V) of the symmetric A (P x P, read
    whole), by the cyclic Jacobi method on the copy ``a`` (P, P scratch). False where A is not finite (w and V are
    then NaN)."""
    ok = True
    for i in range(P):
        for j in range(P):
            a[i, j] = A[i, j]
            V[i, j] = 1.0 if i == j else 0.0
            ok = ok and math.isfinite(A[i, j])
    if ok:
        for sweep in range(EIGEN_SWEEPS):
            off = 0.0
            for p in range(P):
                for q in range(p + 1, P):
                    off += a[p, q] * a[p, q]
            if off == 0.0:
                break
            for p in range(P - 1):
                for q in range(p + 1, P):
                    apq = a[p, q]
                    if apq == 0.0:
                        continue
                    g = 100.0 * abs(apq)
                    if sweep >= EIGEN_SETTLED and abs(a[p, p]) + g == abs(a[p, p]) and abs(a[q, q]) + g == abs(a[q, q]):
                        a[p, q] = 0.0
                        a[q, p] = 0.0
                        continue
                    diff = a[q, q] - a[p, p]
                    if abs(diff) > 1e150 * abs(apq):  # theta^2 would overflow: t ~ 1 / (2 theta)
                        t = apq / diff
                    else:
                        theta = diff / (apq + apq)
                        t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                        if theta < 0.0:
                            t = -t
                    c = 1.0 / math.sqrt(t * t + 1.0)
                    s = t * c
                    for k in range(P):
                        akp = a[k, p]
                        akq = a[k, q]
                        a[k, p] = c * akp - s * akq
                        a[k, q] = s * akp + c * akq
                    for k in range(P):
                        apk = a[p, k]
                        aqk = a[q, k]
                        a[p, k] = c * apk - s * aqk
                        a[q, k] = s * apk + c * aqk
                    a[p, q] = 0.0
                    a[q, p] = 0.0
                    for k in range(P):
                        vkp = V[k, p]
                        vkq = V[k, q]
                        V[k, p] = c * vkp - s * vkq
                        V[k, q] = s * vkp + c * vkq
        for i in range(P):
            w[i] = a[i, i]
        for i in range(1, P):  # ascending, the vectors along
            j = i
            while j > 0 and w[j - 1] > w[j]:
                t = w[j - 1]
                w[j - 1] = w[j]
                w[j] = t
                for k in range(P):
                    t = V[k, j - 1]
                    V[k, j - 1] = V[k, j]
                    V[k, j] = t
                j -= 1
    else:
        for i in range(P):
            w[i] = math.nan
            for j in range(P):
                V[i, j] = math.nan
    return ok
