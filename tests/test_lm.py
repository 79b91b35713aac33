"""The least-squares problem and its solvers: intervals, one-sided derivatives at gratings, the Levenberg-Marquardt
policy on two backends, the exact-model finish, L-BFGS for what the LM leaves open, the scan."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.backend import NUMPY, torch_backend
from torchrod.estimate import lm, search
from torchrod.estimate.finish import refine_open
from torchrod.estimate.problem import (
    Fits,
    evaluate,
    exact_residual,
    interval_of,
    make_problem,
    near_kink,
    sided,
)
from torchrod.estimate.refine import LBFGSOptions

F64 = torch.float64
BACKENDS = [NUMPY, torch_backend()]


def problem_for(xp, rod, curvature, present=None, noise=0.0):
    B, G = curvature.shape[:2]
    present = torch.ones(B, G, dtype=torch.bool) if present is None else present
    u = torch.where(present.unsqueeze(-1), curvature, 0.0)
    return make_problem(
        xp,
        rod.length,
        rod.bending_stiffness,
        rod.gratings,
        xp.asarray(u),
        xp.asarray(present, "bool"),
        noise2=xp.full((B,), noise**2 + 1e-6),
        floor2=1e-6,
        step_angle=0.3,
        max_steps=12,
    )


def fits_at(xp, problem, s, f):
    reading = xp.arange(len(s))
    j, s = interval_of(problem, reading, xp.asarray(s))
    return Fits(reading, s, xp.asarray(f), j)


def clean(rod, s, f):
    return tr.simulate(rod, tr.PointForces(torch.tensor(s, dtype=F64), torch.tensor(f, dtype=F64))).grating_curvature


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_intervals_of_a_reading_with_missing_gratings(rod, xp):
    present = torch.ones(1, rod.num_gratings, dtype=torch.bool)
    present[0, [0, 5]] = False  # 10 mm and 110 mm missing
    problem = problem_for(xp, rod, torch.zeros(1, rod.num_gratings, 2, dtype=F64), present)
    m = int(xp.tolist(problem.intervals)[0])
    assert m == 12
    lo, hi = np.asarray(xp.tolist(problem.lo))[0, :m], np.asarray(xp.tolist(problem.hi))[0, :m]
    assert lo[0] == pytest.approx(0.03) and hi[-1] == pytest.approx(rod.length)
    assert hi[3] == pytest.approx(0.13) and lo[3] == pytest.approx(0.09)  # [90, 130] mm across the missing 110
    # a location proximal to the first present grating moves onto it; one on a grating takes the interval above
    j, s = interval_of(problem, xp.asarray([0], "int"), xp.asarray([[0.02, 0.13]]))
    assert xp.tolist(j) == [[0, 4]] and np.allclose(xp.tolist(s), [[0.03, 0.13]])


def test_sided_jacobian_at_a_grating(rod):
    """A force on its interval's upper bound (proximal to that grating) does not bend the grating; on its lower
    bound it does, with the slope jump as derivative."""
    xp = NUMPY
    q = rod.gratings[6]
    u = clean(rod, [[q]], [[[0.5, 0.2]]])
    problem = problem_for(xp, rod, u)
    upper = Fits(xp.asarray([0], "int"), xp.asarray([[q]]), xp.asarray([[[0.5, 0.2]]]), xp.asarray([[5]], "int"))
    lower = dataclasses.replace(upper, interval=xp.asarray([[6]], "int"))
    _, J = evaluate(problem, upper)
    Ju, Jl = sided(problem, upper, J), sided(problem, lower, J)
    row = 2 * 6  # grating 6's two residuals
    assert np.all(Ju[0, row : row + 2, 0] == 0.0)
    jump = np.array([-0.2, 0.5]) / rod.bending_stiffness * rod.length  # scaled unknown s / L
    assert np.allclose(Jl[0, row : row + 2, 0], jump, rtol=1e-12)


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_lm_crosses_gratings_to_the_optimum(rod, xp):
    """From starts two intervals off, the policy's crossings carry each force across the gratings to the truth,
    and the exact-model finish lands on it to 1e-9."""
    s_true, f_true = [[0.123, 0.217]], [[[0.8, -0.3], [-0.5, 0.9]]]
    problem = problem_for(xp, rod, clean(rod, s_true, f_true))
    start = fits_at(xp, problem, [[0.085, 0.255]], [[[0.2, 0.1], [0.1, 0.3]]])
    state = lm.finish(problem, lm.LMPolicy(), lm.solve(problem, lm.LMPolicy(), start))
    assert bool(xp.all(state.converged))
    assert np.allclose(xp.tolist(state.fits.s), s_true, atol=1e-9)
    assert np.allclose(xp.tolist(state.fits.f), f_true, atol=1e-8)
    assert xp.tolist(state.fits.interval) == [[5, 10]]


def test_the_two_backends_take_the_same_steps(rod, gen):
    s = 0.05 + 0.24 * torch.rand(6, 2, dtype=F64, generator=gen)
    f = 0.8 * torch.randn(6, 2, 2, dtype=F64, generator=gen)
    u = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature + 0.1 * torch.randn(
        6, rod.num_gratings, 2, dtype=F64, generator=gen
    )
    start_s = (s + 0.02).clamp(max=rod.length).tolist()
    start_f = (0.5 * f).tolist()
    out = []
    for xp in BACKENDS:
        problem = problem_for(xp, rod, u, noise=0.1)
        st = lm.solve(problem, lm.LMPolicy(), fits_at(xp, problem, start_s, start_f))
        out.append([np.asarray(xp.tolist(x)) for x in (st.fits.s, st.fits.f, st.loss, st.steps, st.converged)])
    for a, b in zip(*out, strict=False):
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12)


def test_a_kink_minimum_holds_the_force_on_the_grating(rod):
    """A clean reading of a force exactly on a grating: the optimum is on the loss's kink, where no gradient
    vanishes; the fit converges onto it (within the kink radius, 1 um) and is known to sit there."""
    xp = NUMPY
    q = rod.gratings[8]
    problem = problem_for(xp, rod, clean(rod, [[q]], [[[0.4, -0.6]]]))
    st = lm.solve(problem, lm.LMPolicy(), fits_at(xp, problem, [[q + 0.006]], [[[0.3, -0.5]]]))
    assert bool(st.converged[0]) and abs(st.fits.s[0, 0] - q) < 1e-6
    assert bool(near_kink(problem, st.fits)[0])


def test_failed_linear_algebra_is_data_not_an_exception(rod):
    """A reading holding 1e300: the fit's residuals overflow; the solver reports a non-finite loss, stops, and
    raises nothing."""
    xp = NUMPY
    u = clean(rod, [[0.2]], [[[0.5, 0.2]]])
    u[0, 3, 0] = 1e300
    problem = problem_for(xp, rod, u)
    with np.errstate(all="ignore"):
        st = lm.solve(problem, lm.LMPolicy(), fits_at(xp, problem, [[0.2]], [[[0.5, 0.2]]]))
    assert bool(st.done[0]) and not bool(st.converged[0])


def test_lbfgs_finishes_what_the_lm_budget_leaves_open(rod):
    """Three Levenberg-Marquardt steps are not enough from a far start; the L-BFGS refinement of the open rows
    lowers their loss and the policy's stopping test then judges them again."""
    xp = NUMPY
    s_true, f_true = [[0.14, 0.24]], [[[0.9, 0.2], [-0.4, 0.6]]]
    problem = problem_for(xp, rod, clean(rod, s_true, f_true))
    policy = lm.LMPolicy(iterations=3)
    st = lm.solve(problem, policy, fits_at(xp, problem, [[0.13, 0.25]], [[[0.1, 0.1], [0.1, 0.1]]]))
    assert not bool(st.converged[0])
    done = refine_open(problem, policy, LBFGSOptions(max_iter=60, tolerance_grad=1e-12), st)
    assert float(done.loss[0]) < 1e-3 * float(st.loss[0])
    assert int(done.steps[0]) > int(st.steps[0])


def test_exact_residual_is_the_simulator(rod, gen):
    xp = NUMPY
    s = 0.05 + 0.24 * torch.rand(3, 2, dtype=F64, generator=gen)
    f = torch.randn(3, 2, 2, dtype=F64, generator=gen)
    u = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    problem = problem_for(xp, rod, u)
    r = exact_residual(problem, fits_at(xp, problem, s.tolist(), f.tolist()))
    assert np.abs(r).max() < 1e-12
    r_fast, _ = evaluate(problem, fits_at(xp, problem, s.tolist(), f.tolist()))
    assert 1e-9 < np.abs(r_fast).max() < 1e-3 * np.abs(u.numpy()).max()  # the fitting model: 4th order


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_the_scan_finds_where_a_force_is_missing(rod, xp):
    """From the right one-force fit of a two-force reading, the scan's best interval for the second force is the
    true one, and its promised gain is most of the one-force fit's loss."""
    s_true, f_true = [[0.115, 0.237]], [[[0.6, 0.0], [0.0, 0.7]]]
    problem = problem_for(xp, rod, clean(rod, s_true, f_true))
    # the best one-force fit
    one = lm.finish(
        problem,
        lm.LMPolicy(),
        lm.solve(problem, lm.LMPolicy(), fits_at(xp, problem, [[0.2]], [[[0.3, 0.3]]])),
    )
    sc = search.scan(problem, one.fits, per_interval=2, top=3, trust=10.0)
    new_s = float(xp.tolist(sc.starts.s[0, -1]))
    assert 0.23 <= new_s <= 0.25 or 0.11 <= new_s <= 0.13
    assert float(xp.tolist(sc.gain)[0]) > 0.5 * float(xp.tolist(one.loss)[0])


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
@pytest.mark.parametrize("h0", [0, 1, 2])
def test_the_scans_response_to_a_new_force_is_the_models_jacobian(rod, xp, h0):
    """The scan's responses of the gratings to a unit force at each candidate (from the base fit's propagator, or
    the straight rod's lever for no base force) equal the forward model's Jacobian columns of a force added there
    with zero load; and its residual and base Jacobian are the model's."""
    s_base, f_base = [[0.08, 0.21][:h0]], [[[0.5, -0.2], [0.1, 0.6]][:h0]]
    u = clean(rod, [[0.05, 0.17, 0.26]], [[[0.3, 0.2], [-0.4, 0.1], [0.2, 0.5]]])
    problem = problem_for(xp, rod, u)
    base = fits_at(xp, problem, s_base, xp.asarray(f_base) if h0 else xp.zeros((1, 0, 2)))
    cand, cint, valid = search._candidates(problem, base.reading, 2)
    r, J, Jc = search._responses(problem, base, cand, None)
    C = cand.shape[1]
    assert tuple(Jc.shape) == (1, C, 2 * problem.query.shape[0], 2) and bool(xp.all(valid))
    s_all = xp.concat([xp.expand(base.s, (C, h0)), xp.mT(cand)], 1)
    f_all = xp.concat([xp.expand(base.f, (C, h0, 2)), xp.zeros((C, 1, 2))], 1)
    interval = xp.concat([xp.expand(base.interval, (C, h0)), xp.mT(cint)], 1)
    r_m, J_m = evaluate(problem, Fits(xp.zeros((C,), "int"), s_all, f_all, interval))
    col = np.asarray(xp.tolist(J_m)).reshape(C, -1, h0 + 1, 3)[:, :, h0, 1:]  # (C, 2G, 2): d r / d(f_x, f_y) new
    resp = np.asarray(xp.tolist(Jc))[0]
    scale = np.abs(col).max()
    assert scale > 0 and np.abs(resp - col).max() < 1e-3 * scale
    assert np.allclose(np.asarray(xp.tolist(r))[0], np.asarray(xp.tolist(r_m))[0], rtol=0, atol=1e-3 * scale)
    if h0:
        J_base = np.asarray(xp.tolist(J_m)).reshape(C, -1, h0 + 1, 3)[0, :, :h0].reshape(-1, 3 * h0)
        assert np.abs(np.asarray(xp.tolist(J))[0] - J_base).max() < 1e-3 * np.abs(J_base).max()


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
@pytest.mark.parametrize("Pb", [0, 3, 6])
def test_the_scans_block_solve_is_the_damped_normal_system_of_each_candidate(xp, Pb):
    """The scan's per-candidate solve through the shared base block (its Schur complement) gives the decrement and
    the step of each candidate's whole damped normal system, solved densely: for random columns, for a candidate
    that responds as a base force does (the damping alone then decides the split) and for one with no response
    (it adds nothing: the base fit's decrement, a zero force step)."""
    rng = np.random.default_rng(Pb)
    R0, C, n = 3, 6, 16
    J = rng.normal(size=(R0, n, Pb))
    r = rng.normal(size=(R0, n))
    Jc = rng.normal(size=(R0, C, n, 2))
    Jc[:, -1] = 0.0
    if Pb:
        Jc[:, -2] = J[:, :, 1:3]
    dec, steps = search._added_force(xp, xp.asarray(J), xp.asarray(r), xp.asarray(Jc))
    dec = np.asarray(xp.tolist(dec))
    i, c = np.repeat(np.arange(R0), C), np.tile(np.arange(C), R0)
    st = np.asarray(xp.tolist(steps(xp.asarray(i, "int"), xp.asarray(c, "int")))).reshape(R0, C, Pb + 2)
    for k in range(R0):
        scale = max(np.einsum("np,np->p", J[k], J[k]).max(initial=0.0), np.einsum("cni,cni->ci", Jc[k], Jc[k]).max())
        for j in range(C):
            M = np.concatenate([J[k], Jc[k, j]], 1)
            A, g = M.T @ M, M.T @ r[k]
            x = np.linalg.solve(A + np.diag(1e-9 * np.diag(A) + 1e-12 * scale), g)
            tol = 1e-5 if j == C - 2 and Pb else 1e-9  # duplicate columns: a condition number of about 1e9
            assert dec[k, j] == pytest.approx(g @ x, rel=tol)
            assert np.allclose(st[k, j], -x, rtol=tol, atol=tol * np.abs(x).max())
        A_b, g_b = J[k].T @ J[k], J[k].T @ r[k]
        base_dec = g_b @ np.linalg.solve(A_b + np.diag(1e-9 * np.diag(A_b) + 1e-12 * scale), g_b) if Pb else 0.0
        assert dec[k, -1] == pytest.approx(base_dec, rel=1e-9, abs=1e-300) and not st[k, -1, Pb:].any()
        assert np.all(dec[k] >= base_dec * (1 - 1e-9))


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_the_scans_block_solve_lets_a_candidate_the_base_spans_add_nothing(xp):
    """Two base forces nearly in one place (their columns equal to 1e-6) and a candidate responding as one of them:
    the Schur complement of the candidate is rounding error, not positive definite. The candidate then adds nothing
    (the base fit's decrement, a zero force step) rather than a step of that error's size; the rows whose
    complement stays definite are unaffected."""
    rng = np.random.default_rng(0)
    n, Pb = 16, 6
    J = rng.normal(size=(n, Pb)) * np.array([10.0, 1.0, 1.0, 10.0, 1.0, 1.0])
    J[:, 3:] = J[:, :3] + 3.6e-6 * rng.normal(size=(n, 3))
    r = rng.normal(size=n)
    Jc = np.stack([J[:, 1:3], rng.normal(size=(n, 2))])[None]  # (1, 2, n, 2)
    dec, steps = search._added_force(xp, xp.asarray(J[None]), xp.asarray(r[None]), xp.asarray(Jc))
    dec = np.asarray(xp.tolist(dec))[0]
    st = np.asarray(xp.tolist(steps(xp.asarray([0, 0], "int"), xp.asarray([0, 1], "int"))))
    Acc = Jc[0, 0].T @ Jc[0, 0]
    K = J.T @ J
    K_inv = np.linalg.inv(K + np.diag(1e-9 * np.diag(K) + 1e-12 * np.diag(K).max()))
    S = Acc - Jc[0, 0].T @ J @ K_inv @ J.T @ Jc[0, 0] + np.diag(1e-9 * np.diag(Acc) + 1e-12 * np.diag(K).max())
    assert np.linalg.eigvalsh(S).min() <= 0.0  # the case this test is for
    g = J.T @ r
    base_dec = g @ K_inv @ g
    assert dec[0] == pytest.approx(base_dec, rel=1e-6) and not st[0, Pb:].any()
    assert np.isfinite(dec[1]) and dec[1] > base_dec and np.abs(st[1, Pb:]).max() > 0.0


def test_state_replace_copies_with_changes_and_refuses_unknown_fields(rod):
    xp = NUMPY
    problem = problem_for(xp, rod, clean(rod, [[0.2]], [[[0.3, 0.1]]]))
    state = lm.start(problem, lm.LMPolicy(), fits_at(xp, problem, [[0.18]], [[[0.2, 0.0]]]))
    copy = state.replace(loss=state.loss + 1.0, steps=state.steps + 2)
    assert xp.tolist(copy.loss)[0] == xp.tolist(state.loss)[0] + 1.0 and xp.tolist(copy.steps) == [2]
    assert xp.tolist(state.steps) == [0] and copy.fits is state.fits and copy.J is state.J
    assert dataclasses.replace(state, loss=copy.loss, steps=copy.steps).__dict__.keys() == copy.__dict__.keys()
    with pytest.raises(TypeError, match="nope"):
        state.replace(nope=1)


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_state_take_and_put_of_every_row_in_order_are_the_general_ones(rod, xp):
    """take and put of rows 0..R-1 (a shortcut: the state itself, the part itself) give what a permutation and its
    inverse give through the general gather and scatter, None fields included."""
    u = clean(rod, [[0.2], [0.12], [0.25]], [[[0.3, 0.1]], [[-0.2, 0.4]], [[0.1, -0.1]]])
    problem = problem_for(xp, rod, u)
    state = lm.start(problem, lm.LMPolicy(), fits_at(xp, problem, [[0.18], [0.1], [0.27]], [[[0.2, 0.0]]] * 3))
    part = lm.solve(problem, lm.LMPolicy(), state).replace(proposal=None)
    every, perm = xp.arange(3), xp.asarray([2, 0, 1], "int")
    inverse = xp.asarray([1, 2, 0], "int")

    def same(a, b):
        for name in lm._STATE_FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            if name == "fits":
                x, y = (x.reading, x.s, x.f, x.interval), (y.reading, y.s, y.f, y.interval)
            else:
                x, y = (x,), (y,)
            for p, q in zip(x, y, strict=True):
                assert (p is None) == (q is None), name
                if p is not None:
                    assert xp.tolist(p) == xp.tolist(q), name

    same(state.take(xp, every), state.take(xp, perm).take(xp, inverse))
    same(state.put(xp, every, part), state.put(xp, perm, part.take(xp, perm)))
    same(part.put(xp, every, state), part.put(xp, perm, state.take(xp, perm)))  # None where the target has None


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_best_of_blocks_that_hold_some_readings(xp):
    """``best_of`` with a layout (blocks that hold only some readings) picks, for each reading, its lowest-loss row
    among the rows it has (a converged row within the slack preferred, NaN last); with every row present it is
    the dense choice."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    B, blocks = 5, 3
    loss = rng.uniform(0.0, 1.0, blocks * B)
    loss[[2, 9]] = np.nan
    converged = rng.uniform(size=blocks * B) < 0.5
    slack = np.array([0.2, 0.05, 0.3, 0.1, 0.25])  # per reading

    def state(rows):
        return SimpleNamespace(loss=xp.asarray(loss[rows]), converged=xp.asarray(converged[rows], "bool"))

    every = np.arange(blocks * B)
    dense = xp.tolist(search.best_of(xp, state(every), B, xp.asarray(slack)))
    laid = xp.tolist(search.best_of(xp, state(every), B, xp.asarray(slack), (xp.asarray(every, "int"), blocks)))
    assert laid == dense
    present = np.array([k for k in every if k not in (0, 5, 6, 13)])  # reading 0 only in block 2
    layout = (xp.asarray(present, "int"), blocks)
    got = xp.tolist(search.best_of(xp, state(present), B, xp.asarray(slack), layout))
    for b in range(B):
        rows = [i for i, k in enumerate(present) if k % B == b]
        key = [loss[present[i]] - slack[b] * converged[present[i]] for i in rows]
        key = [np.inf if np.isnan(v) else v for v in key]
        assert got[b] == rows[int(np.argmin(key))], b


def noisy_two_force_problem(rod, n, seed):
    """The NumPy problem of n readings of two random forces (0.05-0.29 m, components ~ N(0, 0.8^2) N) with noise
    0.1 1/m: their one-force fits are misfits, where local minima hide."""
    gen = torch.Generator().manual_seed(seed)
    s = 0.05 + 0.24 * torch.rand(n, 2, dtype=F64, generator=gen)
    f = torch.randn(n, 2, 2, dtype=F64, generator=gen) * 0.8
    u = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    return problem_for(NUMPY, rod, u + 0.1 * torch.randn(u.shape, dtype=F64, generator=gen), noise=0.1)


def test_one_force_has_one_minimum_per_interval(rod):
    """What the search's one-force shortcut rests on (:func:`torchrod.estimate.search._explore`): within one interval
    the loss of one force has one local minimum, so every start that ends in an interval ends at the same fit. Checked
    where it is least obvious: one-force fits of noisy two-force readings (misfits), from five starts in every
    interval (three locations, two of them also with the force reversed)."""
    n = 16
    problem = noisy_two_force_problem(rod, n, seed=11)
    m = int(problem.intervals[0])
    lo, hi = problem.lo[0, :m], problem.hi[0, :m]
    starts = [(a, sign) for a in (0.15, 0.5, 0.85) for sign in ((1.0,) if a == 0.5 else (1.0, -1.0))]
    reading = np.repeat(np.arange(n), m * len(starts))
    interval = np.tile(np.repeat(np.arange(m), len(starts)), n)
    frac = np.tile(np.array([a for a, _ in starts]), n * m)
    sign = np.tile(np.array([g for _, g in starts]), n * m)
    guess = sign[:, None] * np.array([0.4, -0.3])
    fits = Fits(
        reading, (lo[interval] + frac * (hi[interval] - lo[interval]))[:, None], guess[:, None, :], interval[:, None]
    )
    policy = lm.LMPolicy()
    out = lm.solve(problem, policy, fits)
    assert bool(out.converged.mean() > 0.8)
    margin = 10.0 * policy.tolerance * 0.1**2
    compared = 0
    for b in range(n):
        for j in range(m):
            rows = np.nonzero((reading == b) & (out.fits.interval[:, 0] == j) & out.converged)[0]
            if len(rows) > 1:
                compared += 1
                spread = out.loss[rows].max() - out.loss[rows].min()
                assert spread <= margin, (b, j, out.loss[rows], out.fits.s[rows, 0])
    assert compared >= n


def test_the_one_force_shortcut_finds_what_the_full_search_finds(rod):
    """The wider search of a one-force fit drops a start that enters the fit's interval without a lower loss
    (:func:`torchrod.estimate.search._explore`). Against the same search without the shortcut, on noisy two-force
    readings, from each reading's worst converged one-force fit (a local minimum where there are several): the same
    readings improve, to the same fits, for fewer evaluations."""
    n, xp = 48, NUMPY
    problem = noisy_two_force_problem(rod, n, seed=5)
    policy = lm.LMPolicy()
    solver = search.Solver(policy)
    options = search.SearchOptions()
    # One fit from the middle of every interval; the current fit is each reading's worst converged one.
    m = int(problem.intervals[0])
    mid = 0.5 * (problem.lo[0, :m] + problem.hi[0, :m])
    reading, interval = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
    guess = np.tile([[[0.4, -0.3]]], (n * m, 1, 1))
    every = lm.finish(
        problem, policy, lm.solve(problem, policy, Fits(reading, mid[interval][:, None], guess, interval[:, None]))
    )
    worst = np.argmax(np.where(every.converged, every.loss, -np.inf).reshape(n, m), 1) + m * np.arange(n)
    cur = every.take(xp, worst)
    base = lm.finish(problem, policy, search.no_force(problem))
    sc = search.scan(problem, base, per_interval=options.per_interval, top=2, trust=policy.max_force_step)
    more = [sc.starts.take(t * n + np.arange(n)) for t in (0, 1)]
    full, spent_full, _ = search._explore(problem, solver, options, more, cur.loss)
    fast, spent_fast, _ = search._explore(problem, solver, options, more, cur.loss, cur.fits.interval)
    margin = 10.0 * policy.tolerance * cur.noise2
    better_full, better_fast = full.loss < cur.loss - margin, fast.loss < cur.loss - margin
    assert better_fast.tolist() == better_full.tolist()
    assert np.allclose(fast.loss[better_fast], full.loss[better_full], rtol=1e-9, atol=0.0)
    assert np.all(spent_fast <= spent_full) and spent_fast.sum() < 0.8 * spent_full.sum()
    assert 4 <= better_full.sum() <= n - 4  # both outcomes are tested
    assert np.isinf(fast.loss).any()  # some readings had every start dropped: nothing finished for them


def test_the_exact_finish_counts_what_each_row_costs_alone(rod, monkeypatch):
    """``finish_counted`` gives each row the exact-model evaluations it makes alone (its residual, then each step
    it tries until one is not worth taking or does not lower the loss): in a batch, the rows reach what they reach
    alone and are counted as alone, although the batch loop evaluates every row while any moves."""
    n, xp = 24, NUMPY
    problem = noisy_two_force_problem(rod, n, seed=8)
    policy = lm.LMPolicy()
    s = problem.lo[:, 2:3] + 0.3 * (problem.hi[:, 2:3] - problem.lo[:, 2:3])
    fitted = lm.solve(problem, policy, Fits(np.arange(n), s, np.tile([[[0.4, -0.3]]], (n, 1, 1)), np.full((n, 1), 2)))
    calls = []
    real = lm.exact_residual
    monkeypatch.setattr(lm, "exact_residual", lambda p, f: calls.append(f.rows) or real(p, f))
    # The array code, whose calls are counted here (the compiled finish is held to its counts in test_lm_compiled).
    monkeypatch.setattr(lm._lm_compiled, "usable", lambda problem, rows, h: False)
    batch, used = lm.finish_counted(problem, policy, fitted)
    assert sum(calls) == n * (1 + len(calls[1:])) and len(set(xp.tolist(used))) > 1  # rows differ
    for b in range(n):
        calls.clear()
        alone, one = lm.finish_counted(problem, policy, fitted.take(xp, np.array([b])))
        assert xp.tolist(one) == [len(calls)] == [int(used[b])], b
        assert np.allclose(alone.loss, batch.loss[b : b + 1], rtol=1e-12, atol=0)
        assert np.allclose(alone.fits.s, batch.fits.s[b : b + 1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("xp", BACKENDS, ids=lambda b: b.name)
def test_twins_stop_the_row_with_the_higher_loss(xp):
    """``search._twins``: of two rows of one reading whose forces hold the same intervals, in any order, the one
    with the higher loss stops (equal losses: the later block's; a NaN loss counts as the highest); rows in other
    intervals, rows of other readings, rows with a location held on a bound and rows with two forces in one
    interval go on. With a layout of blocks that hold some readings only, an absent row matches nothing."""
    from types import SimpleNamespace

    n, blocks = 3, 3
    # rows in blocks of n: row k n + b is reading b's row in block k
    interval = [
        [1, 3], [0, 2], [4, 5],  # block 0
        [3, 1], [0, 2], [5, 6],  # block 1
        [2, 3], [2, 0], [6, 7],  # block 2
    ]  # fmt: skip
    loss = [5.0, 2.0, 1.0, 4.0, 2.0, 1.0, 1.0, np.nan, 1.0]

    def state(rows, held=()):
        iv = np.array(interval)[rows]
        on_bound = np.zeros(iv.shape, dtype=bool)
        on_bound[list(held), 0] = True
        return SimpleNamespace(
            fits=SimpleNamespace(s=xp.zeros(iv.shape), interval=xp.asarray(iv, "int")),
            loss=xp.asarray(np.array(loss)[rows]),
            held=xp.asarray(on_bound, "bool"),
        )

    every = np.arange(blocks * n)
    got = xp.tolist(search._twins(xp, n, blocks)(state(every)))
    # reading 0: block 0 = block 1 as a set, higher loss; reading 1: a tie (block 1 stops) and a NaN (block 2)
    assert got == [True, False, False, False, True, False, False, True, False]
    # a location held on a bound (reading 0, block 1) or two forces in one interval (reading 2): no twins
    interval[2], interval[5] = [4, 4], [4, 4]
    got = xp.tolist(search._twins(xp, n, blocks)(state(every, held=[3])))
    assert got == [False, False, False, False, True, False, False, True, False]
    present = np.array([0, 1, 2, 5, 6, 7, 8])  # reading 0 and 1 absent from block 1
    got = xp.tolist(search._twins(xp, n, blocks, xp.asarray(present, "int"))(state(present)))
    assert got == [False, False, False, False, False, True, False]


def test_two_forces_have_one_minimum_per_pair_of_intervals(rod):
    """What the twins rest on for more than one force (:func:`torchrod.estimate.search._twins`): two-force fits that
    end in the same pair of intervals end at the same fit. Checked where local minima hide: two-force fits of noisy
    three-force readings (misfits), from four starts in each of several pairs of intervals (two locations, the
    forces as guessed and reversed)."""
    n = 12
    gen = torch.Generator().manual_seed(21)
    s = 0.04 + 0.25 * torch.rand(n, 3, dtype=F64, generator=gen)
    f = torch.randn(n, 3, 2, dtype=F64, generator=gen) * 0.6
    u = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    problem = problem_for(NUMPY, rod, u + 0.1 * torch.randn(u.shape, dtype=F64, generator=gen), noise=0.1)
    m = int(problem.intervals[0])
    lo, hi = problem.lo[0, :m], problem.hi[0, :m]
    pairs = [(i, j) for i in range(0, m, 2) for j in range(i + 1, m, 3)]
    starts = [(a, sign) for a in (0.25, 0.75) for sign in (1.0, -1.0)]
    rows = [(b, p, a, g) for b in range(n) for p in pairs for a, g in starts]
    reading = np.array([b for b, _, _, _ in rows])
    interval = np.array([p for _, p, _, _ in rows])
    frac = np.array([a for _, _, a, _ in rows])[:, None]
    sign = np.array([g for _, _, _, g in rows])[:, None, None]
    loc = lo[interval] + frac * (hi[interval] - lo[interval])
    guess = sign * np.array([[0.3, -0.2], [-0.2, 0.4]])[None]
    policy = lm.LMPolicy()
    out = lm.solve(problem, policy, Fits(reading, loc, guess, interval))
    assert bool(out.converged.mean() > 0.8)
    margin = 10.0 * policy.tolerance * 0.1**2
    ends = np.sort(out.fits.interval, 1)
    # Twins never pair fits with two forces in one interval or a location held on a bound: those have minima of
    # their own (a force held on the first grating beside one inside the interval: the bulk of what this excludes).
    apart = out.converged & (ends[:, 0] != ends[:, 1]) & ~out.held.any(1)
    compared = 0
    for b in range(n):
        for pair in {tuple(e) for e in ends[(reading == b) & apart]}:
            same = np.nonzero((reading == b) & apart & np.all(ends == pair, 1))[0]
            if len(same) > 1:
                compared += 1
                spread = out.loss[same].max() - out.loss[same].min()
                assert spread <= margin, (b, pair, out.loss[same])
    assert compared >= 2 * n


def test_a_solve_checks_its_stop_at_the_start(rod):
    """``lm.solve``'s ``stop`` is checked on the starting point too: the rows it names take no step at all (twins
    that begin in the same intervals cost one evaluation, not two); the others are fitted as without it."""
    n = 8
    problem = noisy_two_force_problem(rod, n, seed=4)
    s = problem.lo[:, 2:3] + 0.3 * (problem.hi[:, 2:3] - problem.lo[:, 2:3])
    fits = Fits(np.arange(n), s, np.tile([[[0.4, -0.3]]], (n, 1, 1)), np.full((n, 1), 2))
    policy = lm.LMPolicy()
    even = np.arange(n) % 2 == 0
    out = lm.solve(problem, policy, fits, stop=lambda state: even)
    alone = lm.solve(problem, policy, fits)
    assert out.done.all() and (out.steps[even] == 0).all() and not out.converged[even].any()
    assert (alone.steps[even] > 0).all()
    assert np.array_equal(out.steps[~even], alone.steps[~even]) and np.allclose(out.loss[~even], alone.loss[~even])


def test_per_problem_keeps_the_last_problems_results_and_only_its(rod):
    """``problem.per_problem``: one call per problem and arguments while that problem lasts; another problem (even
    an equal copy) is computed afresh, and the first one's results are not kept beside it."""
    from torchrod.estimate.problem import per_problem

    calls = []

    @per_problem
    def width(problem, k):
        calls.append(k)
        return problem.batch_size * k

    a = problem_for(NUMPY, rod, clean(rod, [[0.1]], [[[0.5, 0.2]]]))
    b = dataclasses.replace(a)
    assert [width(a, 2), width(a, 2), width(a, 3), width(b, 2), width(a, 2)] == [2, 2, 3, 2, 2]
    assert calls == [2, 3, 2, 2]
