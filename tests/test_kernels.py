"""The kernels' pieces, each held to an independent reference: the torch simulator and its autograd gradients,
finite differences, NumPy's linear algebra, SciPy's quantiles and hand-made losses. They run as Python (the same
source the compiled targets run), one reading at a time through :meth:`torchrod.Estimator.kit`."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

import torchrod as tr
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.kernels import counts, covariance, linalg, march, precurved, search
from torchrod.kernels.fit import evaluate
from torchrod.kernels.host import chi2_quantile, f_quantile
from torchrod.kernels.views import march_of, model_of, rows_of

F64 = torch.float64
ROD = tr.presets.nitinol290()


def _kit(rod=ROD, noise=0.1, **options):
    est = Estimator(rod, EstimatorOptions(noise=noise, **options))
    return est.kit(torch.zeros(rod.num_gratings, 2, dtype=F64))


def _forces(*triples):
    s = np.array([[t[0] for t in triples]])
    f = np.array([[[t[1], t[2]] for t in triples]])
    return s, f


def _simulate(rod, s, f, at=None):
    loads = tr.PointForces(torch.tensor(s, dtype=F64), torch.tensor(f, dtype=F64))
    if at is None:
        return tr.grating_curvature(rod, loads)[0].numpy()
    return tr.simulate(rod, loads, at=torch.tensor(at, dtype=F64)).curvature[0].numpy()


# ------------------------------------------------------------------------------------------------ straight marches
def test_the_fitting_model_is_the_simulator_to_its_accuracy_and_its_jacobian_the_autograd_gradient():
    k = _kit()
    q = model_of(k).query
    s, f = _forces((0.12, -0.9, 1.1), (0.25, 0.6, -0.4))
    assert march.march_fit(k, q, 14, s[0], f[0], 2, 6, False)
    curv, jac = march_of(k).curv[:14].copy(), march_of(k).jac[:14, :, :6].copy()
    ref = _simulate(ROD, s, f)
    assert np.abs(curv - ref).max() < 2e-3 * np.abs(ref).max()  # the fitting model's accuracy (RKN4, 0.3 rad)
    # the Jacobian against the simulator's autograd gradient (an independent code, the exact model)
    st = torch.tensor(s, dtype=F64, requires_grad=True)
    ft = torch.tensor(f, dtype=F64, requires_grad=True)
    u = tr.grating_curvature(ROD, tr.PointForces(st, ft))[0]
    for g in range(14):
        for c in range(2):
            gs, gf = torch.autograd.grad(u[g, c], (st, ft), retain_graph=True)
            want = np.stack([gs[0].numpy(), gf[0, :, 0].numpy(), gf[0, :, 1].numpy()], 1).reshape(-1)
            assert np.allclose(jac[g, c], want, rtol=2e-3, atol=2e-3 * np.abs(want).max() + 1e-9), (g, c)


def test_the_fitting_models_force_columns_are_its_own_finite_differences():
    """The force columns are the tangent of the discrete scheme: they match central differences of the march itself
    to the differences' own error; the location columns are the continuous derivative (to the scheme's order)."""
    k = _kit()
    q = model_of(k).query
    s, f = _forces((0.14, 0.7, -0.5), (0.26, -0.3, 0.8))
    march.march_fit(k, q, 14, s[0], f[0], 2, 6, False)
    jac = march_of(k).jac[:14, :, :6].copy()
    eps = 1e-6
    for j in range(2):
        for c in range(2):
            fp, fm = f.copy(), f.copy()
            fp[0, j, c] += eps
            fm[0, j, c] -= eps
            march.march_fit(k, q, 14, s[0], fp[0], 2, 0, False)
            up = march_of(k).curv[:14].copy()
            march.march_fit(k, q, 14, s[0], fm[0], 2, 0, False)
            um = march_of(k).curv[:14].copy()
            fd = (up - um) / (2 * eps)
            assert np.allclose(jac[:, :, 3 * j + 1 + c], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
        sp, sm = s.copy(), s.copy()
        sp[0, j] += 1e-5
        sm[0, j] -= 1e-5
        march.march_fit(k, q, 14, sp[0], f[0], 2, 0, False)
        up = march_of(k).curv[:14].copy()
        march.march_fit(k, q, 14, sm[0], f[0], 2, 0, False)
        um = march_of(k).curv[:14].copy()
        fd = (up - um) / 2e-5
        assert np.allclose(jac[:, :, 3 * j], fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


def test_the_exact_model_is_the_simulator():
    k = _kit()
    q = model_of(k).query
    for triples in (((0.2, 0.5, 0.5),), ((0.05, 1.5, -0.3), (0.13, -0.8, 0.9), (0.29, 0.4, 0.4))):
        s, f = _forces(*triples)
        assert march.march_exact(k, q, 14, s[0], f[0], len(triples))
        ref = _simulate(ROD, s, f)
        assert np.abs(march_of(k).curv[:14] - ref).max() <= 1e-10 * np.abs(ref).max()


def test_a_grating_at_a_force_sees_it_move_from_the_distal_side():
    """At a tie the force comes first: the grating at the force's location reads the state after the jump, so its
    location derivative is the slope jump i (f_x + i f_y) / EI (the distal one-sided derivative)."""
    k = _kit()
    q = model_of(k).query
    s, f = _forces((q[6], 0.4, -0.7))
    march.march_fit(k, q, 14, s[0], f[0], 1, 3, False)
    jac = march_of(k).jac
    ei = ROD.bending_stiffness
    assert math.isclose(jac[6, 0, 0], 0.7 / ei, rel_tol=1e-12)  # Re(i (f_x + i f_y)) / EI = -f_y / EI
    assert math.isclose(jac[6, 1, 0], 0.4 / ei, rel_tol=1e-12)
    assert np.all(march_of(k).curv[7:14] == 0.0)  # distal to the force: no load, no steps


def test_the_propagator_gives_the_response_to_a_force_added_anywhere():
    """Phi(p) Phi(c)^-1 applied to the slope jump of a unit force at c is the linear response of grating p: the
    finite difference of the march with a small force added at c."""
    k = _kit()
    q = model_of(k).query
    s, f = _forces((0.22, 0.8, 0.3))
    c = 0.173
    at = np.concatenate([q, [c]])
    march.march_fit(k, at, 15, s[0], f[0], 1, 0, True)
    phi = march_of(k).phi[:15, :4, :4].copy()
    inv = 1.0 / ROD.bending_stiffness
    for comp, jump in ((0, np.array([0.0, 0.0, 0.0, inv])), (1, np.array([0.0, 0.0, -inv, 0.0]))):
        resp = phi[:14, :2] @ np.linalg.solve(phi[14], jump)  # (14, 2)
        resp[q > c] = 0.0  # a force bends only the gratings proximal to it
        eps = 1e-5  # (the base with a zero force at c: the same events, so the same discrete scheme)
        s2, f2 = _forces((0.22, 0.8, 0.3), (c, eps if comp == 0 else 0.0, eps if comp == 1 else 0.0))
        march.march_fit(k, q, 14, s2[0], f2[0], 2, 0, False)
        up = march_of(k).curv[:14].copy()
        s0, f0 = _forces((0.22, 0.8, 0.3), (c, 0.0, 0.0))
        march.march_fit(k, q, 14, s0[0], f0[0], 2, 0, False)
        fd = (up - march_of(k).curv[:14]) / eps
        assert np.allclose(resp, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


def test_the_schedule_orders_ties_and_counts_steps_by_its_rules():
    q = np.array([0.05, 0.15, 0.25])
    s = np.array([0.15, 0.2])
    f = np.array([[0.5, 0.0], [0.0, -0.4]])
    ei, L = 7.4e-3, 0.29
    jump = np.array([complex(-f[j, 1] / ei, f[j, 0] / ei) for j in range(2)])
    mag = np.abs(jump)
    order, seg, steps = np.empty(5, np.int64), np.empty(5), np.empty(5, np.int64)
    march.schedule(q, 3, s, jump, mag, 2, L, 0.3, 64, True, order, seg, steps)
    assert order.tolist() == [4, 1, 0, 3, 2]  # tip to base; the force at 0.15 before the grating there
    assert np.allclose(seg, [0.04, 0.05, 0.05, 0.0, 0.1])
    assert steps[0] == 0  # the grating at 0.25, distal to every force: the state is zero there
    # the rigorous rule at the grating at 0.05: |m| <= sum |f| / EI, |U| <= min(sum |f| lever / EI, sqrt(2 M))
    M = mag.sum()
    u = min(mag[0] * 0.10 + mag[1] * 0.15, math.sqrt(2 * M))
    assert steps[4] == math.ceil(max(u, math.sqrt(M)) * 0.1 / 0.3)
    # the estimator's rule sums the jumps as vectors: never more steps than the rigorous rule
    est = np.empty(5, np.int64)
    march.schedule(q, 3, s, jump, mag, 2, L, 0.3, 64, False, order, seg, est)
    assert np.all(est <= steps)
    march.schedule(q, 3, s, jump, mag, 2, L, 1e-9, 7, True, order, seg, steps)
    assert steps.max() == 7  # capped


def test_the_events_are_sorted_tip_to_base_by_position_then_index():
    """The event order is Python's sort by (position descending, index) whatever the queries and the extra events
    hold: one or two increasing runs of queries and increasing extra events (merged), more runs or ties
    (insertion-sorted); forces, queries and extra events at equal positions."""
    rng = np.random.default_rng(3)
    for trial in range(800):
        h, Q, X = int(rng.integers(0, 5)), int(rng.integers(0, 30)), int(rng.integers(0, 4)) * (trial % 2)
        grid = np.round(rng.uniform(0.0, 0.3, 60), 2 if trial % 3 else 6)  # coarse grids make ties
        runs = 1 + trial % 4  # 1-2: the merge; 3-4: the insertion sort, as are repeated positions in a run
        query = np.concatenate([np.sort(part) for part in np.array_split(grid[:Q], runs)]) if Q else grid[:0]
        extra = np.sort(grid[40 : 40 + X]) if trial % 5 else grid[40 : 40 + X]
        s = rng.choice(np.concatenate([grid[30:35], query, extra]), size=h)
        order = np.empty(h + Q + X, np.int64)
        march.event_order(query, Q, extra, X, s, h, order)
        at = np.concatenate([s, query, extra])
        assert order.tolist() == sorted(range(h + Q + X), key=lambda i: (-at[i], i)), (query, extra, s)


def test_the_gram_matrix_stops_at_each_columns_zero_tail_and_equals_the_full_sums():
    """J^T J with each column's trailing zero rows left out equals the full sums in order, bit for bit; a J that is
    not finite gets the full sums (inf times a zero is NaN there), and gram says whether J is finite."""
    from torchrod.kernels.fit import gram

    rng = np.random.default_rng(5)
    n, P = 28, 9
    for trial in range(40):
        J = rng.normal(size=(n, P))
        for p in range(P):
            J[2 * int(rng.integers(0, 15)) :, p] = 0.0 if trial % 2 else -0.0  # a force's distal gratings
        if trial % 5 == 0:
            J[n - 1, int(rng.integers(0, P))] = math.inf if trial % 10 else math.nan
        A, tail = np.empty((P, P)), np.empty(P, np.int64)
        with np.errstate(invalid="ignore"):
            finite = gram(J, n, P, A, tail)
            full = [[sum((J[m, p] * J[m, q] for m in range(n)), 0.0) for q in range(P)] for p in range(P)]
        assert np.array_equal(A, np.array(full), equal_nan=True)
        assert finite == bool(np.isfinite(J).all())


def test_the_scans_model_of_one_more_force_is_the_full_damped_normal_system():
    """Each candidate's decrement and force from the Schur complement (its sums cut at the last grating its
    response reaches) are those of the whole damped normal system solved by NumPy; a grating missing."""
    from torchrod.kernels.fit import FLOOR, TINY
    from torchrod.kernels.scan import scan_model
    from torchrod.kernels.views import scan_of

    s, f = _forces((0.115, 0.6, 0.0), (0.237, 0.0, 0.7))
    u = torch.tensor(_simulate(ROD, s, f))
    u[6] = math.nan
    k = Estimator(ROD, EstimatorOptions(noise=0.1)).kit(u)
    for h0, s0, f0 in ((1, [0.2], [[0.3, 0.3]]), (2, [0.1, 0.25], [[0.5, 0.1], [0.1, 0.5]])):
        rows = _fit(k, h0, h0, s0, np.array(f0))
        scan_model(k, rows.s[h0], rows.f[h0], rows.interval[h0], h0, h0)
        sw = scan_of(k)
        P, n = 3 * h0, 2 * ROD.num_gratings
        J, r = sw.J[:n, :P], sw.r[:n]
        Jc = sw.Jc[: sw.dec.shape[0]]
        C = Jc.shape[0]
        assert (Jc[:, 2 * 6 : 2 * 6 + 2] == 0).all() and (Jc[-1, : 2 * ROD.num_gratings - 2] != 0).any()
        scale = max(np.diag(J.T @ J).max(), max(np.diag(Jc[c].T @ Jc[c]).max() for c in range(C)))
        checked = 0
        for c in range(C):
            Jf = np.concatenate([J, Jc[c]], axis=1)
            A = Jf.T @ Jf
            M = A + np.diag(TINY * np.diag(A) + FLOOR * scale)
            g = Jf.T @ r
            x = np.linalg.solve(M, g)
            if not (sw.xc[c] == 0).all():
                bound = 1e-14 * np.linalg.cond(M) * np.abs(x).max()  # rounding, amplified by the system's condition
                assert np.abs(sw.xc[c] - x[P:]).max() <= bound
                assert sw.dec[c] == pytest.approx(g @ x, rel=1e-9)
                checked += 1
        assert checked > C // 2


# ------------------------------------------------------------------------------------------------ precurved
def test_the_precurved_march_is_the_simulator_and_its_jacobian_the_autograd_gradient():
    rod = tr.presets.load("ctr250")
    k = _kit(rod)
    q = model_of(k).query
    G = rod.num_gratings
    s, f = _forces((0.195, 0.3, -0.4), (0.24, -0.2, 0.5))  # (not at a grating: autograd takes a side there)
    assert precurved.march_precurved(k, q, G, s[0], f[0], 2, 6, False, precurved.EXACT_MAX_STEP)
    curv, jac = march_of(k).curv[:G].copy(), march_of(k).jac[:G, :, :6].copy()
    st = torch.tensor(s, dtype=F64, requires_grad=True)
    ft = torch.tensor(f, dtype=F64, requires_grad=True)
    u = tr.grating_curvature(rod, tr.PointForces(st, ft))[0]
    assert np.abs(curv - u.detach().numpy()).max() < 1e-7 * np.abs(u.detach().numpy()).max()
    for g in range(G):
        for c in range(2):
            gs, gf = torch.autograd.grad(u[g, c], (st, ft), retain_graph=True)
            want = np.stack([gs[0].numpy(), gf[0, :, 0].numpy(), gf[0, :, 1].numpy()], 1).reshape(-1)
            assert np.allclose(jac[g, c], want, rtol=1e-5, atol=1e-6 * np.abs(want).max() + 1e-9), (g, c)


def test_the_precurved_propagator_gives_the_response_to_a_force_added_anywhere():
    rod = tr.presets.load("ctr250")
    k = _kit(rod)
    q = model_of(k).query
    G = rod.num_gratings
    s, f = _forces((0.2, 0.3, 0.1))
    c = 0.137
    at = np.concatenate([q, [c]])
    precurved.march_precurved(k, at, G + 1, s[0], f[0], 1, 0, True, precurved.FIT_MAX_STEP)
    phi = march_of(k).phi[: G + 1].copy()
    for comp in (0, 1):
        unit = np.zeros(6)
        unit[comp] = 1.0  # the internal force n jumps by the unit force
        resp = phi[:G, :2] @ np.linalg.solve(phi[G, 2:8], unit)
        resp[q > c] = 0.0
        eps = 1e-5
        s2, f2 = _forces((0.2, 0.3, 0.1), (c, eps if comp == 0 else 0.0, eps if comp == 1 else 0.0))
        precurved.march_precurved(k, q, G, s2[0], f2[0], 2, 0, False, precurved.FIT_MAX_STEP)
        up = march_of(k).curv[:G].copy()
        s0, f0 = _forces((0.2, 0.3, 0.1), (c, 0.0, 0.0))
        precurved.march_precurved(k, q, G, s0[0], f0[0], 2, 0, False, precurved.FIT_MAX_STEP)
        fd = (up - march_of(k).curv[:G]) / eps
        assert np.allclose(resp, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


# ------------------------------------------------------------------------------------------------ linear algebra
def test_small_solves_are_numpys_and_fail_as_data():
    rng = np.random.default_rng(0)
    for P in (1, 3, 6, 9):
        A = rng.normal(size=(P + 4, P))
        M = A.T @ A + 1e-3 * np.eye(P)
        b = rng.normal(size=P)
        x, L = np.empty(P), np.empty((P, P))
        assert linalg.spd_solve(M, b, x, P, L)
        assert np.allclose(x, np.linalg.solve(M, b), rtol=1e-10)
        G = rng.normal(size=(P, P))
        LU, piv, y = np.empty((P, P)), np.empty(P, np.int64), np.empty(P)
        assert linalg.lu_factor(G, LU, piv, P) and linalg.lu_apply(LU, piv, b, y, P)
        assert np.allclose(y, np.linalg.solve(G, b), rtol=1e-9)
    x, L = np.ones(2), np.empty((2, 2))
    assert not linalg.spd_solve(np.array([[1.0, 2.0], [2.0, 1.0]]), np.ones(2), x, 2, L)  # not positive definite
    assert np.all(x == 0.0)
    assert not linalg.spd_solve(np.array([[math.nan, 0.0], [0.0, 1.0]]), np.ones(2), x, 2, L)
    assert not linalg.lu_factor(np.zeros((2, 2)), np.empty((2, 2)), np.empty(2, np.int64), 2)  # singular


def test_the_eigenvalues_are_numpys():
    rng = np.random.default_rng(1)
    for P in (1, 2, 5, 9):
        A = rng.normal(size=(P, P))
        A = A + A.T
        w, V, a = np.empty(P), np.empty((P, P)), np.empty((P, P))
        assert linalg.symmetric_eigen(A, w, V, a, P)
        assert np.allclose(w, np.linalg.eigvalsh(A), rtol=1e-12, atol=1e-12 * np.abs(w).max())
        assert np.allclose(A @ V, V * w, atol=1e-11 * np.abs(w).max())
        assert np.allclose(V.T @ V, np.eye(P), atol=1e-12)
    A = np.diag([1e-20, 1.0, 1e20])  # far apart scales: each eigenvalue to its own relative accuracy
    w, V, a = np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    assert linalg.symmetric_eigen(A, w, V, a, 3) and np.allclose(w, [1e-20, 1.0, 1e20], rtol=1e-14)
    assert not linalg.symmetric_eigen(np.full((2, 2), math.inf), w, V, a, 2)
    assert np.isnan(w[:2]).all()


def test_jacobi_settles_clustered_and_spread_eigenvalues_to_rounding():
    # Entries too small to move a diagonal are zeroed after a few sweeps: clustered eigenvalues (the slow case for
    # the off-diagonal decay) and eigenvalues twelve decades apart keep their relative accuracy and orthogonality.
    rng = np.random.default_rng(11)
    for spectrum in ([1.0, 1.0 + 1e-9, 1.0 + 2e-9, 2.0, 2.0 + 1e-12, 3.0, 5.0, 5.0, 7.0],
                     np.logspace(-6, 6, 9), [0.0, 0.0, 1e-14, 1.0, 1.0, 1.0, 4.0, 4.0, 9.0]):  # fmt: skip
        Q, _ = np.linalg.qr(rng.normal(size=(9, 9)))
        A = Q @ np.diag(spectrum) @ Q.T
        A = 0.5 * (A + A.T)
        w, V, a = np.empty(9), np.empty((9, 9)), np.empty((9, 9))
        assert linalg.symmetric_eigen(A, w, V, a, 9)
        reference = np.linalg.eigvalsh(A)
        assert np.allclose(w, reference, rtol=0, atol=1e-13 * np.abs(reference).max())
        assert np.allclose(A @ V, V * w, atol=1e-12 * np.abs(w).max())
        assert np.allclose(V.T @ V, np.eye(9), atol=1e-12)


def test_the_covariance_of_a_linear_model_is_its_inverse_normal_matrix():
    k = _kit()
    rng = np.random.default_rng(3)
    J = rng.normal(size=(28, 6))
    cov = np.empty((6, 6))
    cond = covariance.covariance(k, J, 6, np.ones(6, bool), 0.5, cov)
    assert np.allclose(cov, 0.25 * np.linalg.inv(J.T @ J), rtol=1e-10)
    d = 1 / np.sqrt(np.diag(J.T @ J))
    w = np.linalg.eigvalsh(J.T @ J * np.outer(d, d))
    assert math.isclose(cond, w[-1] / w[0], rel_tol=1e-10)
    active = np.array([True, True, True, False, False, False])
    covariance.covariance(k, J, 6, active, 1.0, cov)
    assert np.allclose(cov[:3, :3], np.linalg.inv(J[:, :3].T @ J[:, :3]), rtol=1e-10)
    assert np.isnan(cov[3:]).all() and np.isnan(cov[:, 3:]).all()
    # Inactive columns (trailing, or between active ones) leave the condition number that of the active columns.
    for active in (np.array([True, True, True, False, False, False]), np.array([True, False, True, True, False, True])):
        cond = covariance.covariance(k, J, 6, active, 1.0, cov)
        Ja = J[:, active]
        d = 1 / np.sqrt(np.diag(Ja.T @ Ja))
        w = np.linalg.eigvalsh(Ja.T @ Ja * np.outer(d, d))
        assert math.isclose(cond, w[-1] / w[0], rel_tol=1e-10)
        assert np.allclose(cov[np.ix_(active, active)], np.linalg.inv(Ja.T @ Ja), rtol=1e-10)
        assert np.isnan(cov[~active]).all() and np.isnan(cov[:, ~active]).all()
    J[4, 2] = math.nan  # a diverged fit: NaN and an infinite condition number, not an exception
    assert covariance.covariance(k, J, 6, np.ones(6, bool), 1.0, cov) == math.inf
    assert np.isnan(cov).all()
    # The eigensolver's last results serve again only for the same matrix (the second pass), never after another.
    J[4, 2] = 0.5
    d = 1 / np.sqrt(np.diag(J.T @ J))
    w = np.linalg.eigvalsh(J.T @ J * np.outer(d, d))
    for _ in range(2):
        assert math.isclose(covariance.covariance(k, J, 6, np.ones(6, bool), 0.5, cov), w[-1] / w[0], rel_tol=1e-10)
        assert np.allclose(cov, 0.25 * np.linalg.inv(J.T @ J), rtol=1e-10)


# ------------------------------------------------------------------------------------------------ count tests
def test_the_tables_are_scipys_quantiles():
    for p, d in ((0.95, 3), (0.999, 25), (0.5, 1)):
        assert math.isclose(chi2_quantile(p, d), stats.chi2.ppf(p, d), rel_tol=1e-12)
        assert math.isclose(f_quantile(p, d, 20), stats.f.ppf(p, d, 20), rel_tol=1e-12)
    assert chi2_quantile(0.9, 0) == math.inf


def _counts_kit(n: int, noise: float | None, **options):
    k = _kit(noise=noise, noise_floor=0.0, **options)
    k.info[0].residuals = n
    k.info[0].known = noise is not None
    k.info[0].noise2 = 0.0 if noise is None else noise * noise
    return k


def test_the_count_rules_on_given_losses():
    sigma = 0.1
    c1 = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2  # the largest loss drop one more force may make by noise
    base, big = 0.25, 50.0  # about sigma^2 (28 - 3); no force
    rows = [
        ([big, base, base - 0.5 * c1, base - 0.6 * c1], 1, 1),  # a second force explains noise only
        ([big, base + 2 * c1, base, base - 0.1 * c1], 2, 1),  # the second force is needed
        ([big, 50.0, 49.0, base], 3, 3),  # two forces do not help but three do: 3, not 1
        ([0.28, 0.27, 0.26, 0.25], 0, 0),  # pure noise: no force helps
        ([big, base, math.nan, math.nan], 1, 1),  # only counts 0 and 1 fitted
    ]
    k = _counts_kit(28, sigma)
    t = _counts_kit(28, sigma, selection="threshold", threshold=1.0)
    u = _counts_kit(28, None)
    for losses, want, paper in rows:
        chosen, used = counts.select_count(k, np.array(losses + [math.nan]), 4)
        assert (chosen, used) == (want, sigma)
        assert counts.select_count(t, np.array(losses + [math.nan]), 4)[0] == paper  # the first below the threshold
        if not math.isnan(losses[3]):  # sigma from the largest fit: the F test decides alike here
            chosen, used = counts.select_count(u, np.array(losses + [math.nan]), 4)
            assert chosen == want
            assert math.isclose(used, math.sqrt(losses[3] / 19), rel_tol=1e-12)


def test_with_no_count_accepted_the_fewest_forces_no_larger_count_improves_on_win():
    sigma = 0.1
    c1 = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2
    k = _counts_kit(28, sigma)
    assert counts.select_count(k, np.array([50.0, 30.0, 20.0, 20.0 - 0.5 * c1, math.nan]), 4)[0] == 2
    assert counts.select_count(k, np.array([50.0, 30.0, 20.0, 10.0, math.nan]), 4)[0] == 3
    for noise in (sigma, None):  # two residuals: one force fits exactly and no count has a degree of freedom
        k = _counts_kit(2, noise)
        k.opt.floor2 = 1e-6
        k.opt.min_dof = -1000  # no count left out of the choice
        assert counts.select_count(k, np.array([5.0, 1e-12, 1e-13, 1e-14, math.nan]), 4)[0] == 1


def test_a_count_the_reading_cannot_test_is_never_chosen():
    """A count whose fit leaves fewer than ``min_dof`` degrees of freedom is left out of the choice altogether (as if
    not fitted), however well it fits: 6 residuals test one force (3 left), not two (none)."""
    sigma = 0.1
    for noise in (sigma, None):
        k = _counts_kit(6, noise)
        k.opt.floor2 = 1e-6
        assert k.opt.min_dof == 3 and counts.testable(k, 4) == 2
        assert counts.select_count(k, np.array([5000.0, 3.0, 1e-12, 1e-13, math.nan]), 4)[0] == 1
        k = _counts_kit(2, noise)
        assert counts.testable(k, 4) == 1
        assert counts.select_count(k, np.array([5.0, 1e-12, 1e-13, 1e-14, math.nan]), 4)[0] == 0
    k = _counts_kit(6, sigma)
    assert counts.settled(k, np.array([50.0, 0.01, math.nan, math.nan, math.nan]), 2, 0.0)  # count 2: not fitted


def test_a_count_is_chosen_just_below_its_ceiling_and_not_just_above():
    rng = np.random.default_rng(7)
    checked = 0
    for noise in (0.1, None):
        for _ in range(40):
            n, top = int(rng.choice([12, 28])), int(rng.choice([2, 3]))
            k = _counts_kit(n, noise)
            k.opt.floor2 = 1e-6
            if noise is not None:
                k.info[0].noise2 = noise * noise + 1e-6
            losses = np.full(5, math.nan)
            losses[: top + 1] = rng.uniform(0.0, 3.0, top + 1)
            losses[top] = rng.uniform(0.0, 0.01 * (n - 3 * top))
            for h in range(top):
                trial = losses.copy()
                trial[:h] = 1e6  # beyond every misfit and drop limit: never accepted
                c = counts.ceiling(k, trial, 4, h)
                if c <= 1e-6:
                    continue
                for delta, chosen in ((-1e-9, True), (1e-9, False)):
                    trial[h] = c + delta
                    assert (counts.select_count(k, trial, 4)[0] == h) == chosen, (noise, n, trial.tolist(), h, c)
                checked += 1
    assert checked > 100


def test_a_count_is_settled_only_when_one_more_force_cannot_change_it():
    sigma = 0.1
    drop = chi2_quantile(1.0 - 0.05 / 14, 3) * sigma**2
    k = _counts_kit(28, sigma)
    for losses, gain, want in (([50.0, 0.25], 0.1 * drop, True), ([50.0, 0.25], 0.9 * drop, False),
                               ([50.0, 30.0], 29.0, False)):  # fmt: skip
        scratch = np.array(losses + [math.nan])
        assert counts.settled(k, scratch, 2, gain) == want
        assert math.isnan(scratch[2])  # its scratch slot given back
    assert not counts.settled(_counts_kit(28, None), np.array([50.0, 0.25, math.nan]), 2, 0.0)


def test_the_misfit_test_is_the_chi_square_p_value_below_its_level():
    k = _counts_kit(28, 0.1)
    q = stats.chi2.ppf(1 - 1e-3, 28 - 3)
    assert not counts.unexplained(k, 1, 0.01 * q * 0.999)
    assert counts.unexplained(k, 1, 0.01 * q * 1.001)
    assert counts.unexplained(k, 1, math.inf) and counts.unexplained(k, 1, math.nan)
    assert not counts.unexplained(k, 10, 1e9)  # no degree of freedom left: nothing to test


def test_the_chi_square_survival_matches_scipy_over_its_range():
    """The reported p-value's special function (run as the kernel source), against scipy's chi2.sf: from p near 1
    to 1e-250, for small and large degrees of freedom, both parities, and either side of the switch to logarithms
    (x / 2 = 700)."""
    worst = 0.0
    for dof in [*range(1, 40), 57, 100, 255, 1001, 4001]:
        for p in (1 - 1e-12, 0.999, 0.5, 1e-3, 1e-9, 1e-40, 1e-120, 1e-250):
            x = stats.chi2.isf(p, dof)
            want = stats.chi2.sf(x, dof)
            worst = max(worst, abs(counts.chi2_survival(x, dof) - want) / want)
    assert worst < 1e-11
    for x in (1399.0, 1401.0):
        for dof in (1, 2, 1300, 1301, 1500, 1501):
            want, got = stats.chi2.sf(x, dof), counts.chi2_survival(x, dof)
            assert abs(got - want) <= 1e-11 * want if want > 1e-290 else got <= 1e-290
    assert counts.chi2_survival(0.0, 3) == 1.0 and counts.chi2_survival(-1.0, 4) == 1.0
    assert counts.chi2_survival(math.inf, 3) == 0.0 and math.isnan(counts.chi2_survival(math.nan, 3))


def test_the_status_codes_the_kernels_write_are_the_statuses_in_order():
    from torchrod.estimate.status import STATUSES

    assert [tr.Status(name).code for name in STATUSES] == [
        counts.OK,
        counts.MISFIT,
        counts.UNCONVERGED,
        counts.POORLY_DETERMINED,
        counts.TIMEOUT,
    ]


def test_a_readings_status_and_p_value_follow_its_chosen_fit():
    """The verdict's order (timeout, misfit, unconverged, poorly determined, ok) and the p-value at the noise given
    or, unknown, at the largest believed; checked against scipy's chi-square law."""
    k = _counts_kit(28, 0.1)
    q = stats.chi2.ppf(1 - 1e-3, 28 - 3)
    loss = 0.01 * q * 0.5
    assert counts.p_value(k, 1, loss) == pytest.approx(stats.chi2.sf(loss / 0.01, 25), rel=1e-12)
    assert counts.verdict(k, 1, loss, True, False) == counts.OK
    assert counts.verdict(k, 1, loss, True, True) == counts.POORLY_DETERMINED
    assert counts.verdict(k, 1, loss, False, True) == counts.UNCONVERGED
    assert counts.verdict(k, 1, 0.01 * q * 1.01, False, True) == counts.MISFIT
    assert counts.p_value(k, 1, math.inf) == 0.0 and counts.verdict(k, 1, math.nan, True, False) == counts.MISFIT
    assert math.isnan(counts.p_value(k, 10, 1.0))  # no degree of freedom left: no p-value, no misfit
    assert counts.verdict(k, 10, 1e9, True, False) == counts.OK
    k.info[0].cut = True
    assert counts.verdict(k, 1, 0.01 * q * 1.01, False, True) == counts.TIMEOUT
    unknown = _counts_kit(28, None)
    s2 = unknown.opt.max_noise2
    assert counts.p_value(unknown, 2, 3.0) == pytest.approx(stats.chi2.sf(3.0 / s2, 22), rel=1e-12)


# ------------------------------------------------------------------------------------------------ fits
def test_one_force_has_one_minimum_per_interval():
    """What the search's one-force shortcut rests on: within one interval the loss of one force has one local
    minimum, so every fit that ends converged in an interval ends at the same loss. Checked where it is least
    obvious: one-force fits of noisy two-force readings (misfits), from five starts in every interval (three
    locations, two of them also with the force reversed)."""
    from torchrod.kernels.fit import start

    gen = torch.Generator().manual_seed(11)
    est = Estimator(ROD, EstimatorOptions(noise=0.1))
    compared = converged = total = 0
    for _ in range(6):
        s = np.sort(0.05 + 0.24 * torch.rand(1, 2, dtype=F64, generator=gen).numpy(), 1)
        f = 0.8 * torch.randn(1, 2, 2, dtype=F64, generator=gen).numpy()
        u = _simulate(ROD, s, f) + 0.1 * torch.randn(14, 2, dtype=F64, generator=gen).numpy()
        k = est.kit(torch.tensor(u))
        rows = rows_of(k)
        q = model_of(k).query
        ends: dict[int, list[float]] = {}
        for j in range(13):
            for frac, sign in ((0.15, 1.0), (0.15, -1.0), (0.5, 1.0), (0.85, 1.0), (0.85, -1.0)):
                i = 5
                loc = q[j] + frac * (q[j + 1] - q[j])
                search.load_row(k, i, 1, np.array([loc]), sign * np.array([[0.4, -0.3]]), np.array([j]))
                start(k, i, 30)
                search.solve_rows(k, np.array([i]), 1, 30, search.STOP_NONE, 0.0, False)
                total += 1
                if rows.converged[i]:
                    converged += 1
                    ends.setdefault(int(rows.interval[i, 0]), []).append(float(rows.loss[i]))
        for found in ends.values():
            if len(found) > 1:
                compared += 1
                assert max(found) - min(found) <= 10.0 * 1e-3 * 0.1**2, found
    assert converged > 0.8 * total and compared >= 6


def test_the_residual_is_the_reading_less_the_model_at_present_gratings_only():
    s, f = _forces((0.2, 0.5, 0.2))
    u = _simulate(ROD, s, f)
    mask = torch.ones(14, dtype=torch.bool)
    mask[4] = False
    est = Estimator(ROD, EstimatorOptions(noise=0.1))
    k = est.kit(torch.tensor(u) + 0.5, mask)
    r, J = np.empty(28), np.empty((28, 3))
    loss = evaluate(k, s[0], f[0], 1, True, True, r, J)
    assert np.all(r[8:10] == 0.0)  # the missing grating
    want = -0.5 * np.ones(28)
    want[8:10] = 0.0
    assert np.allclose(r, want, atol=1e-8)
    assert math.isclose(loss, 0.25 * 26, rel_tol=1e-6)


def _fit(k, i, h, s, f, limit=30):
    """Row i fitted from (s, f) of h forces in their intervals, then finished on the exact model."""
    from torchrod.kernels.fit import finish, start
    from torchrod.kernels.scan import interval_of

    rows = rows_of(k)
    rows.count[i] = h
    for j in range(h):
        interval_of(k, s[j], rows.interval[i], rows.s[i], j)
        rows.f[i, j] = f[j]
        rows.held[i, j] = False
    start(k, i, limit)
    search.solve_rows(k, np.array([i]), 1, limit, search.STOP_NONE, 0.0, False)
    finish(k, i, 3)
    return rows


def test_the_fits_cross_gratings_to_the_optimum():
    """From starts two intervals off, the crossings carry each force across the gratings to the truth, and the
    exact-model finish lands on it to 1e-9."""
    s, f = _forces((0.123, 0.8, -0.3), (0.217, -0.5, 0.9))
    k = Estimator(ROD, EstimatorOptions()).kit(torch.tensor(_simulate(ROD, s, f)))  # noise unknown: the floor
    rows = _fit(k, 5, 2, [0.085, 0.255], np.array([[0.2, 0.1], [0.1, 0.3]]))
    assert rows.converged[5]
    assert np.allclose(rows.s[5, :2], s[0], atol=1e-9) and np.allclose(rows.f[5, :2], f[0], atol=1e-8)
    assert rows.interval[5, :2].tolist() == [5, 10]


def test_a_kink_minimum_holds_the_force_on_the_grating():
    """A clean reading of a force exactly on a grating: the optimum is on the loss's kink, where no gradient
    vanishes; the fit converges onto it and is known to sit there."""
    q = ROD.gratings[8]
    s, f = _forces((q, 0.4, -0.6))
    k = Estimator(ROD, EstimatorOptions(noise=0.1)).kit(torch.tensor(_simulate(ROD, s, f)))
    rows = _fit(k, 5, 1, [q + 0.006], np.array([[0.3, -0.5]]))
    assert rows.converged[5] and abs(rows.s[5, 0] - q) < 1e-6
    assert covariance.near_kink(k, rows.s[5], 1)


def test_the_scan_finds_where_a_force_is_missing():
    """From the right one-force fit of a two-force reading, the scan's best interval for the second force is the
    true one, and its promised gain is most of the one-force fit's loss."""
    from torchrod.kernels.scan import scan_model, scan_starts

    s, f = _forces((0.115, 0.6, 0.0), (0.237, 0.0, 0.7))
    k = Estimator(ROD, EstimatorOptions(noise=0.1)).kit(torch.tensor(_simulate(ROD, s, f)))
    rows = _fit(k, 1, 1, [0.2], np.array([[0.3, 0.3]]))
    base = scan_model(k, rows.s[1], rows.f[1], rows.interval[1], 1, 1)
    out_s, out_f, out_i, pred = np.empty((3, 3)), np.empty((3, 3, 2)), np.empty((3, 3), np.int64), np.empty(3)
    gain = scan_starts(k, rows.s[1], rows.f[1], 1, base, 3, 10.0, out_s, out_f, out_i, pred, 0, 1)
    assert 0.23 <= out_s[0, 1] <= 0.25 or 0.11 <= out_s[0, 1] <= 0.13
    assert gain > 0.5 * rows.loss[1]
    assert pred[0] <= pred[1] <= pred[2]  # the starts by the loss their models promise


def test_a_reading_that_overflows_is_data_not_an_exception():
    """A reading holding 1e300: the residuals overflow; the fit reports a non-finite loss, stops, and raises
    nothing."""
    from torchrod.kernels.host import kit

    plan = Estimator(ROD, EstimatorOptions(noise=0.1, target="python")).plan()
    k = kit(plan.setup, plan.sizes, np.full(28, 1e300), np.ones(28), 0.01)  # (the estimator's input check refuses it)
    with np.errstate(all="ignore"):
        rows = _fit(k, 5, 1, [0.2], np.array([[0.3, 0.3]]))
    assert not rows.converged[5] and not math.isfinite(rows.loss[5])


def test_the_generated_accessors_are_the_ones_the_layout_gives():
    """torchrod/kernels/views.py and its type stub views.pyi are generated from layout.SPEC (``python -m
    torchrod.kernels.layout``), which places the parts the kernel modules declare: a part added to a declaration
    without regenerating the files fails here. The groups lie in the arenas in the order of layout.GROUPS, each
    declared by one kernel module."""
    from pathlib import Path

    from torchrod.kernels import counts, covariance, fit, layout, march, precurved, scan, search, views

    here = Path(views.__file__)
    assert here.read_text(encoding="utf-8") == layout.render_views()
    assert here.with_suffix(".pyi").read_text(encoding="utf-8") == layout.render_stub()
    assert tuple(layout.SPEC) == layout.GROUPS
    declared = {}
    for module in (march, counts, search, precurved, fit, scan, covariance):
        (name,) = [key for key in vars(module) if key.endswith("_PARTS")]
        for group, parts in getattr(module, name).items():
            assert group not in declared, group
            declared[group] = parts
    assert declared == layout.SPEC
    assert views.Kit is layout.Kit and views.Kit._fields == tuple(name for name, _ in layout.KIT)
    for group, parts in layout.SPEC.items():
        assert getattr(views, f"{group.capitalize()}View")._fields == tuple(parts)
        assert callable(getattr(views, f"{group}_of"))
    with pytest.raises(ValueError, match="declared twice"):
        layout._assemble(scan.SCAN_PARTS, scan.SCAN_PARTS)
    with pytest.raises(ValueError, match="not those of GROUPS"):
        layout._assemble(scan.SCAN_PARTS)


def test_the_numba_patches_step_aside_outside_the_releases_they_were_checked_on(monkeypatch):
    """Outside patches.TESTED neither patch touches Numba: the dispatcher comes back as it is, and the compile's
    optimisation is Numba's own."""
    import numba
    from numba.core import codegen

    from torchrod.kernels import patches

    assert patches.supported() == (
        patches.TESTED[0] <= tuple(int(x) for x in numba.__version__.split(".")[:2]) <= patches.TESTED[1]
    )
    monkeypatch.setattr(patches, "supported", lambda: False)
    sentinel = object()
    assert patches.general(sentinel, lambda t: t) is sentinel
    before = codegen.CPUCodeLibrary._optimize_final_module
    with patches.optimised_at_entry("anything"):
        assert codegen.CPUCodeLibrary._optimize_final_module is before


class _Cache:
    """A stand-in for a dispatcher's on-disk cache: its writes fail as on a full disk; it can be turned off."""

    def __init__(self):
        self.on = True

    def save_overload(self, sig, data):
        raise OSError(28, "No space left on device")

    def disable(self):
        self.on = False


def test_the_cache_patches_fail_writes_softly_turn_the_cache_off_and_read_a_read_only_folder(monkeypatch, tmp_path):
    """Within patches.TESTED: a failed write reaches the given function instead of the compile, the cache turns off,
    and a dispatcher made without a cache is given one that reads the folder Numba's CACHE_DIR names; a dispatcher
    without an on-disk cache is left as it is."""
    import types

    import numba

    from torchrod.kernels import patches

    if not patches.supported():
        pytest.skip("this Numba lies outside patches.TESTED")
    dispatcher = types.SimpleNamespace(_cache=_Cache())
    failed = []
    assert patches.guard_saves(dispatcher, failed.append)
    dispatcher._cache.save_overload("sig", "data")
    assert [exc.errno for exc in failed] == [28]
    assert patches.stop_caching(dispatcher) and not dispatcher._cache.on
    plain = types.SimpleNamespace()
    assert not patches.guard_saves(plain, failed.append) and not patches.stop_caching(plain)
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    jitted = numba.njit(lambda x: x + 1.0)
    assert patches.read_only_cache(jitted)
    assert type(jitted._cache).__name__ == "ReadOnlyCache" and str(tmp_path) in jitted._cache.cache_path
    assert patches.without_reference_counts() == {"_nrt": False}


def test_the_cache_patches_step_aside_outside_the_releases_they_were_checked_on(monkeypatch, tmp_path):
    """Outside patches.TESTED the cache is Numba's own: a failed write is not guarded (it raises, as Numba's does),
    the cache is not turned off, a read-only folder gets no cache (the entry is compiled in memory: no directory),
    and the kernels are reference counted (no options)."""
    import types

    import numba

    from torchrod.kernels import patches, targets

    targets._cpu_namespace()  # (built, and kept, with the patches as this Numba takes them)
    monkeypatch.setattr(patches, "supported", lambda: False)
    dispatcher = types.SimpleNamespace(_cache=_Cache())
    save = dispatcher._cache.save_overload
    assert not patches.guard_saves(dispatcher, lambda exc: None)
    assert dispatcher._cache.save_overload == save and "save_overload" not in vars(dispatcher._cache)
    assert not patches.stop_caching(dispatcher) and dispatcher._cache.on
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    jitted = numba.njit(lambda x: x + 1.0)
    cache = jitted._cache
    assert not patches.read_only_cache(jitted) and jitted._cache is cache
    assert patches.without_reference_counts() == {}
    monkeypatch.setattr(targets, "_cache_directory", lambda target, extra="": None)
    monkeypatch.setattr(targets, "_read_only_directory", lambda target, name, extra="": tmp_path)
    compiled = targets._cpu_entry("network_rows", lambda entry: None, "network", "cpu_network")
    assert compiled.directory is None and not compiled.writable
    assert type(compiled.entry._cache).__name__ == "NullCache"
    compiled._in_memory()
    assert compiled._unkept


def test_only_the_patches_module_steps_into_numbas_private_interfaces():
    """Numba's private names (a dispatcher's cache, the caching module, the CPU library's final optimisation, the
    reference-counting option, the dispatcher's call template) appear in torchrod/kernels/patches.py and nowhere else
    in the package (torchrod's own ``self._cache`` aside)."""
    import re
    from pathlib import Path

    private = re.compile(
        r"(?<!self)\._cache\b|numba\.core\.caching|import[^\n]*\bcaching\b|save_overload|_optimize_final_module"
        r"|CPUCodeLibrary|\b_nrt\b|get_call_template|_locator_classes|_impl_class"
    )
    package = Path(__file__).resolve().parents[1] / "torchrod"
    found = {
        str(path.relative_to(package)): sorted(set(private.findall(path.read_text(encoding="utf-8"))))
        for path in package.rglob("*.py")
    }
    patches = found.pop(str(Path("kernels", "patches.py")))
    assert {"._cache", "save_overload", "_optimize_final_module", "_nrt", "get_call_template"} <= set(patches)
    assert {path: names for path, names in found.items() if names} == {}


def test_the_warm_up_runs_the_search_on_its_tiny_reading_as_python():
    """The warm-up's options are the dtype's zeros but for the few its tiny problem needs: with them the kernel
    source, run as Python, scans from two starts, fits both counts (settling and twins on, the acceleration finite)
    and answers one converged force, every number finite."""
    from torchrod.kernels import warmup
    from torchrod.kernels.layout import OPTIONS, allocate

    setup, sizes = warmup.tiny_setup()
    o = setup.opt[0]
    assert setup.opt.dtype == OPTIONS and set(warmup.WARM_OPTIONS) <= set(OPTIONS.names)
    assert o.max_forces == 1 and o.fixed == -1 and o.starts >= 2 and o.settle and o.twins
    assert math.isfinite(o.acceleration) and o.probe > 0.0 and o.iterations > 0 and o.exact_steps > 0
    batch = warmup.tiny_batch()
    search.estimate_rows(0, 1, setup, batch, allocate(sizes), np.zeros(1, np.int64))
    out = batch.out
    assert out.count[0] == 1 and out.converged[0] and out.evaluations[0] > 0 and not out.cut[0]
    assert np.isfinite(out.s).all() and np.isfinite(out.f).all() and np.isfinite(out.losses).all()
    assert out.status[0] in (counts.OK, counts.POORLY_DETERMINED)  # (two gratings hold one force loosely)
