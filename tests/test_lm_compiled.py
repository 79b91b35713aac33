"""The compiled Levenberg-Marquardt step (:mod:`torchrod.estimate._lm_compiled`) against the array code of
:mod:`torchrod.estimate.lm` it restates: the same states step for step (crossings, held locations, the geodesic
acceleration and the active set included), the same solves, and the estimator's same answers."""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_lm import F64, clean, fits_at, problem_for

import torchrod as tr
from torchrod.backend import NUMPY, torch_backend
from torchrod.estimate import _lm_compiled, lm, search
from torchrod.estimate.problem import SNAP, Fits
from torchrod.model import compiled

pytestmark = pytest.mark.skipif(not compiled.available(), reason="the compiled step needs Numba")


@pytest.fixture(autouse=True)
def _loaded():
    """Small solves take the compiled step once the kernels are loaded (:func:`.compiled.takes`)."""
    assert compiled.load()


FLOAT_FIELDS = ("r", "J", "loss", "damping", "ratio", "noise2", "A", "g")
EXACT_FIELDS = ("steps", "held", "converged", "done")


def assert_same_state(a, b, rtol=1e-7):
    """The same discrete state (intervals, steps, held locations, stopping flags) and numbers that agree to
    rounding: some of these systems have condition numbers near 1e20 (a force at the base barely bends the rod),
    where two orders of the same sums part at about 1e-11 per step; ``rtol`` for the rest, and looser for whole
    solves, whose steps compound it."""
    assert np.array_equal(a.fits.reading, b.fits.reading)
    assert np.array_equal(a.fits.interval, b.fits.interval)
    np.testing.assert_allclose(b.fits.s, a.fits.s, rtol=0, atol=1e-3 * rtol)  # [m]
    np.testing.assert_allclose(b.fits.f, a.fits.f, rtol=rtol, atol=1e-3 * rtol)  # [N]
    for name in EXACT_FIELDS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for name in FLOAT_FIELDS:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        scale = np.nanmax(np.abs(x[np.isfinite(x)])) if np.isfinite(x).any() else 1.0
        np.testing.assert_allclose(y, x, rtol=rtol, atol=1e-2 * rtol * scale, err_msg=name)
    assert_same_solutions(a, b, rtol)


def assert_same_solutions(a, b, rtol):
    """The next step's proposal and the decrement, solutions of the damped normal systems (:func:`lm._damped`):
    equal to ``rtol`` where a's systems are well conditioned; elsewhere (condition numbers of 1e12 and more, where
    two correct solves of systems equal to rounding differ in the leading digits) b's proposal must solve b's own
    system to rounding (a backward error of 1e-12), and the decrements must pass the same convergence test
    (checked above)."""
    for i in range(a.fits.rows):
        M = lm._damped(NUMPY, b.A[i : i + 1], lm._free(b.held[i : i + 1], NUMPY), b.damping[i : i + 1])[0]
        if not np.isfinite(M).all():
            continue
        if condition(a)[i] < 1e6:
            np.testing.assert_allclose(b.proposal[i], a.proposal[i], rtol=rtol, atol=1e-9, err_msg="proposal")
            np.testing.assert_allclose(b.decrement[i], a.decrement[i], rtol=rtol, atol=1e-12, err_msg="decrement")
        else:
            scale = np.linalg.norm(M) * np.linalg.norm(b.proposal[i]) + np.linalg.norm(b.g[i])
            assert np.linalg.norm(M @ b.proposal[i] + b.g[i]) <= 1e-12 * scale, "proposal"


def condition(state):
    """(R,) the condition number of each row's damped normal system at its damping."""
    M = lm._damped(NUMPY, state.A, lm._free(state.held, NUMPY), state.damping)
    return np.array([np.linalg.cond(m) if np.isfinite(m).all() else np.inf for m in M])


def noisy_problem(rod, gen, B, h, noise=0.1):
    s = 0.02 + 0.27 * torch.rand(B, h, dtype=F64, generator=gen)
    f = 0.8 * torch.randn(B, h, 2, dtype=F64, generator=gen)
    u = clean(rod, s.tolist(), f.tolist()) + noise * torch.randn(B, rod.num_gratings, 2, dtype=F64, generator=gen)
    present = torch.rand(B, rod.num_gratings, generator=gen) > 0.15  # some gratings missing
    return problem_for(NUMPY, rod, u, present, noise=noise)


def starts_on_and_near_bounds(problem, gen, h):
    """Starts of h forces: one in four on its interval's lower bound, one in four on its upper one, one in four
    within SNAP of a bound, the rest inside; random loads."""
    xp = NUMPY
    B = problem.batch_size
    m = np.asarray(problem.intervals)
    j = (torch.rand(B, h, generator=gen).numpy() * m[:, None]).astype(np.int64)
    reading = np.arange(B)
    lo, hi = problem.lo[reading[:, None], j], problem.hi[reading[:, None], j]
    kind = torch.randint(0, 4, (B, h), generator=gen).numpy()
    frac = torch.rand(B, h, dtype=F64, generator=gen).numpy()
    s = np.where(kind == 0, lo, np.where(kind == 1, hi, lo + (hi - lo) * np.where(kind == 2, 0.5 * SNAP, frac)))
    f = 0.6 * torch.randn(B, h, 2, dtype=F64, generator=gen).numpy()
    return Fits(xp.asarray(reading, "int"), s, f, j)


def started(problem, gen, h, known):
    """The problem (its noise given, or estimated per fit), the default policy, and the array code's start from
    starts on, near and off their bounds, checked against the compiled start."""
    if not known:
        problem = dataclasses.replace(problem, noise2=None)
    policy = lm.LMPolicy()
    fits = starts_on_and_near_bounds(problem, gen, h)
    state = lm.start(problem, policy, fits)
    assert_same_state(state, _lm_compiled.start(problem, policy, fits))
    return problem, policy, state


@pytest.mark.parametrize("known", [True, False], ids=["noise-given", "noise-per-fit"])
@pytest.mark.parametrize("h", [1, 2, 3])
def test_the_compiled_step_takes_the_array_codes_steps(rod, gen, h, known):
    """From the same state, one compiled step gives the array code's next state, for eight steps of 48 fits
    started on, near and off their bounds, some with the geodesic acceleration; the run passes through
    crossings, held locations and accelerated steps (checked, so that the comparison covers them). The noise
    given, or estimated from each fit's loss."""
    problem, policy, state = started(noisy_problem(rod, gen, 48, h), gen, h, known)
    crossed = held = accelerated = 0
    for k in range(8):
        if k % 2:  # every other step: half the rows as if their last step had curved
            state = state.replace(ratio=np.where(np.arange(48) % 2 == 0, 0.1, state.ratio))
        ours = _lm_compiled.step(problem, policy, state)
        theirs = lm._step(problem, policy, state)
        assert_same_state(theirs, ours)
        crossed += int((theirs.fits.interval != state.fits.interval).any(1).sum())
        held += int(theirs.held.any(1).sum())
        accelerated += int((state.ratio < policy.acceleration).sum())
        state = theirs
    assert crossed and held and accelerated


def test_a_compiled_solve_is_the_array_codes_solve(rod, gen, monkeypatch):
    """Whole solves, with a ``stop`` and from a state part-way: the same fits, losses and steps."""
    problem = noisy_problem(rod, gen, 32, 2)
    policy = lm.LMPolicy(iterations=12)
    fits = starts_on_and_near_bounds(problem, gen, 2)

    def stop(state):  # every other row stops after four steps
        return (state.steps >= 4) & (np.arange(state.fits.rows) % 2 == 0)

    ours = [lm.solve(problem, policy, fits, stop=stop), lm.solve(problem, policy, lm.start(problem, policy, fits))]
    monkeypatch.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
    theirs = [lm.solve(problem, policy, fits, stop=stop), lm.solve(problem, policy, lm.start(problem, policy, fits))]
    for a, b in zip(theirs, ours, strict=True):
        assert_same_state(a, b, rtol=1e-5)
    assert int(ours[0].steps.sum()) < int(ours[1].steps.sum())  # the stop stopped some rows


def test_a_compiled_solve_keeps_the_deadline_and_leaves_the_callers_state(rod, gen):
    problem = noisy_problem(rod, gen, 8, 2)
    policy = lm.LMPolicy()
    state = lm.start(problem, policy, starts_on_and_near_bounds(problem, gen, 2))
    before = {k: np.copy(getattr(state, k)) for k in FLOAT_FIELDS + EXACT_FIELDS}
    late = lm.solve(problem, policy, state, deadline=time.perf_counter() - 1.0)
    assert np.array_equal(late.steps, state.steps) and np.array_equal(late.done, state.done)
    done = lm.solve(problem, policy, state)
    assert done.steps.sum() > 0
    for k, v in before.items():
        assert np.array_equal(getattr(state, k), v, equal_nan=True), k


def _late_after(looks, n):
    looks.append(None)
    return len(looks) > n


def _record_steps(rounds, state):
    rounds.append(int(state.steps.max()))
    return np.zeros(state.fits.rows, bool)


def test_the_compiled_solve_looks_at_the_deadline_every_few_row_steps(rod, gen):
    """Between two looks at the deadline the compiled solve takes rounds of steps (every open row once each) while
    their row steps stay within ``STEPS_PER_CHECK``, at least one round: one row takes that many steps per look,
    sixteen rows one step each; a deadline that passes after the first look ends the solve there, and a ``stop``
    is looked at after every round."""
    policy = lm.LMPolicy(tolerance=1e-300)  # no row converges: each goes on for its whole iteration budget
    K = _lm_compiled.STEPS_PER_CHECK
    for rows, per_look in ((1, K), (2, K // 2), (16, 1)):
        problem = noisy_problem(rod, gen, rows, 2)
        fits = starts_on_and_near_bounds(problem, gen, 2)
        looks: list[None] = []
        late = functools.partial(_late_after, looks, 1)  # late at the second look
        state = _lm_compiled.solve(problem, policy, fits, late, None)
        assert len(looks) == 2 and (state.steps == per_look).all() and not state.done.any()
        rounds: list[int] = []
        stop = functools.partial(_record_steps, rounds)
        state = _lm_compiled.solve(problem, policy, fits, lambda r=rounds: len(r) > 3, stop)
        assert rounds == [0, 1, 2, 3] and (state.steps == 3).all()


def test_rows_the_compiled_march_cannot_take_are_solved_in_python(rod, monkeypatch):
    """A start with a non-finite load: the compiled solve declines (None) and lm.solve answers as the array code
    does; a precurved rod, the torch backend and TORCHROD_NUMBA=0 never take the compiled step."""
    problem = problem_for(NUMPY, rod, clean(rod, [[0.1]], [[[0.5, 0.2]]]))
    fits = fits_at(NUMPY, problem, [[0.12]], [[[np.nan, 0.2]]])
    assert _lm_compiled.solve(problem, lm.LMPolicy(), fits, lambda: False, None) is None
    ours = lm.solve(problem, lm.LMPolicy(), fits)
    monkeypatch.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
    theirs = lm.solve(problem, lm.LMPolicy(), fits)
    assert np.array_equal(ours.loss, theirs.loss, equal_nan=True) and np.array_equal(ours.steps, theirs.steps)
    monkeypatch.undo()
    assert _lm_compiled.usable(problem, 1, 1)
    assert not _lm_compiled.usable(problem_for(torch_backend(), rod, clean(rod, [[0.1]], [[[0.5, 0.2]]])), 1, 1)
    monkeypatch.setenv("TORCHROD_NUMBA", "0")
    assert not _lm_compiled.usable(problem, 1, 1)


def stratified_readings(rod, gen, n):
    """n noisy readings of 1-3 forces: a force near a grating, near the base, at the tip or anywhere, in turn;
    every third reading with gratings missing."""
    q = torch.tensor(rod.gratings, dtype=F64)
    s, f, h = [], [], []
    for i in range(n):
        k = 1 + i % 3
        where = 0.02 + 0.27 * torch.rand(k, dtype=F64, generator=gen)
        kind = i % 4
        if kind == 0:
            where[0] = q[int(torch.randint(0, len(q), (1,), generator=gen))] + 4e-4 * (
                torch.rand(1, generator=gen) - 0.5
            )
        elif kind == 1:
            where[0] = 0.004 + 0.01 * torch.rand(1, dtype=F64, generator=gen)
        elif kind == 2:
            where[0] = rod.length - 1e-3
        s.append(torch.cat([where, torch.zeros(3 - k, dtype=F64)]))
        f.append(torch.cat([0.9 * torch.randn(k, 2, dtype=F64, generator=gen), torch.zeros(3 - k, 2, dtype=F64)]))
        h.append(k)
    s, f = torch.stack(s), torch.stack(f)
    active = torch.arange(3)[None, :] < torch.tensor(h)[:, None]
    u = tr.simulate(rod, tr.PointForces(s, f, active)).grating_curvature
    u = u + 0.1 * torch.randn(u.shape, dtype=F64, generator=gen)
    mask = torch.ones(n, rod.num_gratings, dtype=torch.bool)
    mask[::3, 3] = False
    mask[::3, 9] = False
    return u, mask


def test_the_estimator_answers_the_same_with_the_compiled_step(rod, gen, monkeypatch):
    """48 stratified readings, one per call and as one batch: the same counts, statuses and evaluations, and
    forces within 1e-7 N and 1 nm (the exact model's last steps, at a damping of 1e-9, round the most), with the
    compiled steps and without."""
    u, mask = stratified_readings(rod, gen, 48)
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1))

    def answers():
        single = [est.estimate(u[i : i + 1], mask[i : i + 1]) for i in range(u.shape[0])]
        return single + [est.estimate(u, mask)]

    ours = answers()
    monkeypatch.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
    theirs = answers()
    for a, b in zip(theirs, ours, strict=True):
        assert a.statuses == b.statuses
        assert torch.equal(a.num_forces, b.num_forces) and torch.equal(a.evaluations, b.evaluations)
        torch.testing.assert_close(b.forces.f.nan_to_num(), a.forces.f.nan_to_num(), rtol=0, atol=1e-7)
        torch.testing.assert_close(b.forces.s.nan_to_num(), a.forces.s.nan_to_num(), rtol=0, atol=1e-9)


def test_kernels_that_cannot_run_cost_one_warning_and_the_array_code_solves(rod, monkeypatch):
    """As with the marches: a kernel that raises (an incompatible Numba) is reported once, with the reason, and
    every solve from then on runs the array code, to its answers."""
    from torchrod.estimate import _lm_kernels

    problem = problem_for(NUMPY, rod, clean(rod, [[0.1]], [[[0.5, 0.2]]]))
    fits = fits_at(NUMPY, problem, [[0.12]], [[[0.3, 0.2]]])
    monkeypatch.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
    want = lm.solve(problem, lm.LMPolicy(), fits)
    monkeypatch.undo()

    def broken(*args):
        raise TypeError("no such signature")

    monkeypatch.setattr(_lm_kernels, "start_rows", broken)
    monkeypatch.setattr(_lm_compiled, "_broken", None)
    with pytest.warns(RuntimeWarning, match="no such signature"):
        got = lm.solve(problem, lm.LMPolicy(), fits)
    assert not _lm_compiled.usable(problem, 1, 1)
    assert_same_state(want, got, rtol=0)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    gratings=st.lists(st.floats(0.02, 1.0), min_size=3, max_size=10, unique=True),
    tip=st.booleans(),
    length=st.floats(0.05, 1.5),
    stiffness=st.floats(1e-3, 1.0),
    h=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
    missing=st.floats(0.0, 0.5),
    known=st.booleans(),
)
def test_the_compiled_step_on_random_rods_and_readings(gratings, tip, length, stiffness, h, seed, missing, known):
    """Fuzzed: rods of 3 to 10 gratings (one at the tip, or not), lengths, stiffnesses, readings of any shape
    (random curvatures, some gratings missing) and fits started on, near and off their bounds, with and without
    the acceleration: three steps, each from the array code's state, give its next state."""
    q = sorted({min(round(g * length, 6), length) for g in gratings})
    assume(len(q) >= 3 and min(np.diff(q)) > 1e-4)
    if tip:
        q[-1] = length
    rod = tr.Rod(length=length, bending_stiffness=stiffness, gratings=tuple(q))
    gen = torch.Generator().manual_seed(seed)
    B, G = 12, len(q)
    u = (3.0 / length) * torch.randn(B, G, 2, dtype=F64, generator=gen)
    present = torch.rand(B, G, generator=gen) >= missing
    present[:, 0] = True  # at least one interval
    problem, policy, state = started(problem_for(NUMPY, rod, u, present, noise=0.1 / length), gen, h, known)
    for k in range(3):
        if k == 1:
            state = state.replace(ratio=np.where(np.arange(B) % 2 == 0, 0.1, state.ratio))
        theirs, ours = lm._step(problem, policy, state), _lm_compiled.step(problem, policy, state)
        # A step solves the state's damped system again where a force leaves its bounds or the acceleration is
        # taken: rows whose system is too ill conditioned for two correct solves to agree are left out.
        rows = np.flatnonzero(condition(state) < 1e8)
        assert_same_state(theirs.take(NUMPY, rows), ours.take(NUMPY, rows), rtol=1e-6)
        state = theirs


@pytest.mark.parametrize("known", [True, False], ids=["noise-given", "noise-per-fit"])
def test_the_compiled_finish_is_the_array_codes_finish(rod, gen, known, monkeypatch):
    """The exact model's steps after a solve (``lm.finish_counted``): the same fits, residuals and losses to
    rounding, and the same evaluations per row, for fits converged and not (solves cut at 2 and at 30 steps), with
    no step worth taking (``exact_tolerance`` huge) and with none allowed (``exact_steps=0``)."""
    problem = noisy_problem(rod, gen, 40, 2)
    if not known:
        problem = dataclasses.replace(problem, noise2=None)
    fits = starts_on_and_near_bounds(problem, gen, 2)
    policies = [lm.LMPolicy(), lm.LMPolicy(iterations=2), lm.LMPolicy(exact_tolerance=1e9), lm.LMPolicy(exact_steps=0)]
    used = []
    for policy in policies:
        state = lm.solve(problem, policy, fits)
        ours = _lm_compiled.finish_counted(problem, policy, state)
        with monkeypatch.context() as m:
            m.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
            theirs = lm.finish_counted(problem, policy, state)
        assert np.array_equal(ours[1], theirs[1])
        assert_same_state(theirs[0], ours[0], rtol=1e-6)  # steps at a damping of 1e-9: less well conditioned
        used.append(int(ours[1].max()))
    assert used[0] >= 2 and used[1] >= 3 and used[2] == 1 and used[3] == 1


@pytest.mark.parametrize(("h0", "from_state"), [(0, False), (1, False), (1, True), (2, False), (2, True), (3, True)])
def test_the_compiled_scan_is_the_array_codes_scan(rod, gen, h0, from_state, monkeypatch):
    """The scan's responses and Gauss-Newton models of one more force (``search._responses`` and
    ``search._added_force``) compiled, from no force (the lever), from fits (the march's Jacobian) and from solver
    states (their own, sided), readings with gratings missing: the same residuals and Jacobians, and at every
    candidate whose system is well conditioned the same decrement and step; and the same starts from
    ``search.scan`` where those candidates decide them. (At a candidate the base nearly spans, the Schur
    complement is cancellation and its decrement and step mean nothing on either side.)"""
    problem = noisy_problem(rod, gen, 24, max(h0, 1))
    B = problem.batch_size
    if h0 == 0:
        base = Fits(np.arange(B), np.zeros((B, 0)), np.zeros((B, 0, 2)), np.zeros((B, 0), np.int64))
    else:
        base = starts_on_and_near_bounds(problem, gen, h0)
        if from_state:
            base = lm.solve(problem, lm.LMPolicy(iterations=3), base)
    fits = base.fits if from_state else base
    known = (base.r, lm.sided(problem, base.fits, base.J)) if from_state else None
    cand, _, _ = search._candidates(problem, fits.reading, 2)
    C = cand.shape[1]
    r, J, dec, xc, yb, Y = _lm_compiled.scan(problem, fits, cand, known)
    r0, J0, Jc0 = search._responses(problem, fits, cand, known)
    dec0, steps0 = search._added_force(NUMPY, J0, r0, Jc0)
    np.testing.assert_allclose(r, r0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J, J0, rtol=1e-12, atol=1e-12 * np.abs(J0).max(initial=1.0))
    assert np.array_equal(np.isfinite(dec), np.isfinite(dec0))
    # The condition of each candidate's system [J, Jc], its columns scaled to unit norm (its normal equations, which
    # both solve, have the square of it).
    cols = np.concatenate([np.broadcast_to(J0[:, None], (B, C) + J0.shape[1:]), Jc0], 3)
    cols = cols / np.maximum(np.linalg.norm(cols, axis=2, keepdims=True), 1e-300)
    well = np.isfinite(dec0) & (np.linalg.cond(cols) < 1e4)
    assert well.mean() > 0.2
    np.testing.assert_allclose(dec[well], dec0[well], rtol=1e-7, atol=1e-9 * np.abs(dec0[well]).max())
    i, c = np.nonzero(well)
    ours, theirs = search._steps(NUMPY, xc, yb, Y)(i, c), steps0(i, c)
    np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-9 * np.abs(theirs).max())
    # The whole scan, on the readings whose four best intervals (the three starts and the next) come from
    # well-conditioned candidates apart by more than 1e-6 of their decrements: the same intervals, starts, gains
    # and predicted losses.
    got = search.scan(problem, base, per_interval=2, top=3, trust=10.0)
    with monkeypatch.context() as m:
        m.setattr(_lm_compiled, "usable", lambda problem, rows, h: False)
        want = search.scan(problem, base, per_interval=2, top=3, trust=10.0)
    per = np.where(np.isfinite(dec0), dec0, -np.inf).reshape(B, -1, 2)  # (B, intervals, 2 candidates)
    order = np.argsort(-per.max(2), axis=1, kind="stable")[:, :4]
    top = np.take_along_axis(per.max(2), order, 1)
    clear = np.take_along_axis(well.reshape(B, -1, 2).all(2), order, 1).all(1)
    gaps = np.abs(np.diff(top, axis=1))
    clear &= np.all((gaps > 1e-6 * np.abs(top[:, :1])) | ~np.isfinite(gaps), axis=1)
    apart = np.flatnonzero(clear)
    assert apart.shape[0] >= B // 4
    rows = (apart[None, :] + B * np.arange(3)[:, None]).reshape(-1)  # their three starts (blocks of B)
    assert np.array_equal(got.starts.interval[rows], want.starts.interval[rows])
    np.testing.assert_allclose(got.starts.s[rows], want.starts.s[rows], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.starts.f[rows], want.starts.f[rows], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(got.gain[apart], want.gain[apart], rtol=1e-7, atol=1e-12)
    big = np.abs(want.predicted[np.isfinite(want.predicted)]).max()  # a loss less a decrement: cancellation
    np.testing.assert_allclose(got.predicted[:, apart], want.predicted[:, apart], rtol=1e-7, atol=1e-9 * big)


def test_the_compiled_covariance_is_the_array_codes():
    """``uncertainty.gauss_newton_covariance`` row by row (the kernel that fit_uncertainty runs where the steps run
    compiled), against its array code: Jacobians with columns scaled over six orders, unknowns left out, a column of
    zeros, two equal columns, two nearly equal ones, entries not finite, entries whose squares overflow, and no
    unknown at all. The same conditions (infinite where infinite; to rounding where the matrix is well conditioned)
    and the same covariances, NaN where NaN."""
    from torchrod.estimate.uncertainty import gauss_newton_covariance

    rng = np.random.default_rng(7)
    B, n, P = 24, 28, 9
    J = rng.standard_normal((B, n, P)) * 10.0 ** rng.uniform(-3, 3, (B, 1, P))
    active = np.ones((B, P), bool)
    active[10:15] = rng.random((5, P)) < 0.6
    J[15, :, 4] = 0.0  # a column of zeros
    J[16, :, 5] = J[16, :, 2]  # two equal columns: singular
    J[17, :, 5] = J[17, :, 2] * (1 + 1e-6 * rng.standard_normal(n))  # nearly equal: ill conditioned
    J[18, 3, 1] = np.nan
    J[19, 7, 8] = -np.inf
    J[20, :, 6] = 1e200  # its square overflows
    active[21] = False
    J[22, :, 3] = np.nan  # an inactive column not finite: the row still counts as not finite
    active[22, 3] = False
    sigma = rng.uniform(0.05, 0.3, B)
    with np.errstate(all="ignore"):  # the array code's overflow, as in the estimator
        want_cov, want_cond = gauss_newton_covariance(NUMPY, J, sigma, active)
    got_cov, got_cond = gauss_newton_covariance(NUMPY, J, sigma, active, compiled=True)
    # Two equal columns: the least eigenvalue is rounding, on either side of the cut that makes the condition
    # infinite (checked below: beyond any limit on both sides).
    other = np.arange(B) != 16
    assert np.array_equal(np.isinf(got_cond[other]), np.isinf(want_cond[other]))
    assert np.array_equal(np.isnan(got_cov), np.isnan(want_cov))
    assert np.isinf(want_cond[[15, 18, 19, 20, 22]]).all() and np.isnan(want_cov[18]).all()
    well = np.isfinite(want_cond) & (want_cond < 1e8)
    assert well.sum() >= 15
    np.testing.assert_allclose(got_cond[well], want_cond[well], rtol=1e-9)
    for b in np.nonzero(well)[0]:
        scale = np.abs(want_cov[b][np.isfinite(want_cov[b])]).max(initial=1.0)
        np.testing.assert_allclose(got_cov[b], want_cov[b], rtol=1e-9, atol=1e-12 * scale, equal_nan=True)
    # Singular and ill conditioned: both see a condition beyond any limit.
    assert got_cond[16] > 1e12 and want_cond[16] > 1e12 and got_cond[17] > 1e8 and want_cond[17] > 1e8
    none = gauss_newton_covariance(NUMPY, J[:, :, :0], sigma, active[:, :0], compiled=True)
    assert none[0].shape == (B, 0, 0) and (none[1] == 1.0).all()
