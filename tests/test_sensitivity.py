"""The forward-sensitivity march and the event schedule every march shares."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchrod as tr
import torchrod.model.sensitivity as sens
from torchrod.backend import NUMPY, torch_backend
from torchrod.model import compiled, schedule
from torchrod.model.body_frame import integrate_curvature, march_curvature, step_counts
from torchrod.model.nystrom import METHODS
from torchrod.model.sensitivity import curvature_and_jacobian, march, march_propagator

F64 = torch.float64


def _path(monkeypatch, path: str) -> None:
    """Send the NumPy backend's marches down one path: ``"rows"`` (Python numbers), ``"arrays"`` or
    ``"compiled"`` (the Numba rows; the caller checks that they are available)."""
    monkeypatch.setenv("TORCHROD_NUMBA", "1" if path == "compiled" else "0")
    monkeypatch.setattr(sens, "SCALAR_WORK", 0 if path == "arrays" else 10**6)
    if path == "compiled":
        assert compiled.load()


def test_sensitivity_matches_forward_model_and_autograd(rod, gen):
    s = 0.03 + 0.26 * torch.rand(4, 3, dtype=F64, generator=gen)
    f = 0.6 * torch.randn(4, 3, 2, dtype=F64, generator=gen)
    q = rod.grating_positions()
    u, J = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, max_step_angle=0.02, max_steps=400)
    ref = tr.simulate(rod, tr.PointForces(s, f)).grating_curvature
    assert (u - ref).abs().max() < 1e-7 * ref.abs().max()

    def fwd(s_, f_):
        return integrate_curvature(q, tr.PointForces(s_, f_), rod.length, rod.bending_stiffness)[0]

    Js, Jf = torch.autograd.functional.jacobian(fwd, (s, f))
    Js = torch.stack([Js[b, :, :, b] for b in range(4)])  # (B, G, 2, h)
    Jf = torch.stack([Jf[b, :, :, b] for b in range(4)])  # (B, G, 2, h, 2)
    assert (J[..., 0] - Js).abs().max() < 1e-6 * Js.abs().max()
    assert (J[..., 1:] - Jf).abs().max() < 1e-6 * Jf.abs().max()


def test_sensitivity_padding_and_batch_independence(rod, gen):
    s = 0.03 + 0.26 * torch.rand(12, 3, dtype=F64, generator=gen)
    f = 0.6 * torch.randn(12, 3, 2, dtype=F64, generator=gen)
    q = rod.grating_positions()
    mask = torch.tensor([[True, True, False]] * 12)
    u, J = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, mask=mask)
    u2, _J2 = curvature_and_jacobian(q, s[:, :2], f[:, :2], rod.length, rod.bending_stiffness)
    # a padded force carries no load: its event only splits a segment (a discretisation change far below 1e-4)
    assert (u - u2).abs().max() < 1e-4 * u.abs().max()
    assert J[..., 2, :].abs().max() == 0.0  # and zero Jacobian columns
    for b in range(12):  # each row's steps are its own: batching does not change a result
        ub, Jb = curvature_and_jacobian(
            q, s[b : b + 1], f[b : b + 1], rod.length, rod.bending_stiffness, mask=mask[b : b + 1]
        )
        assert torch.allclose(ub, u[b : b + 1], rtol=0, atol=1e-12)
        assert torch.allclose(Jb, J[b : b + 1], rtol=0, atol=1e-10)


@pytest.mark.parametrize("h", [1, 2, 3])
def test_three_implementations_of_the_march_agree(rod, gen, monkeypatch, h):
    """Python rows (small NumPy batches), NumPy arrays and torch tensors: one scheme, the same numbers, also with
    padded forces, a force exactly on a grating, one at the tip and the step cap binding."""
    B = 6
    q = rod.grating_positions()
    s = 0.03 + 0.26 * torch.rand(B, h, dtype=F64, generator=gen)
    s[0, 0] = q[4]
    s[1, -1] = rod.length
    f = 1.5 * torch.randn(B, h, 2, dtype=F64, generator=gen)
    mask = torch.rand(B, h, generator=gen) > 0.3
    mask[:, 0] = True
    for kwargs in ({}, {"mask": mask}, {"max_steps": 2}, {"jacobian": False}):
        _path(monkeypatch, "rows")
        u1, J1 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, **kwargs)  # Python rows
        _path(monkeypatch, "arrays")
        u2, J2 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, **kwargs)  # NumPy arrays
        u3, J3 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, backend="torch", **kwargs)
        if compiled.available():  # the compiled rows: the Python rows' operations, so the same numbers exactly
            _path(monkeypatch, "compiled")
            u4, J4 = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness, **kwargs)
            assert torch.equal(u4, u1) and (J1 is None if J4 is None else torch.equal(J4, J1))
        for u, Jx in ((u2, J2), (u3, J3)):
            assert u1.shape == u.shape and (u1 - u).abs().max() <= 1e-12 * u.abs().max()
            if Jx is None:
                assert J1 is None
            else:
                assert J1.shape == Jx.shape and (J1 - Jx).abs().max() <= 1e-12 * Jx.abs().max()


@pytest.mark.parametrize("h", [0, 1, 3])
def test_three_implementations_of_the_propagator_march_agree(rod, gen, monkeypatch, h):
    """The propagator's march (seeds carried from the tip: across the zero state distal to the most distal force
    the rows advance them by the exact linear map, the arrays step them) on Python rows, NumPy arrays and torch
    tensors, with two forces tied at one location and forces distal to every grating."""
    B = 5
    q = rod.grating_positions().numpy()
    s = 0.03 + 0.26 * torch.rand(B, h, dtype=F64, generator=gen).numpy()
    f = 1.2 * torch.randn(B, h, 2, dtype=F64, generator=gen).numpy()
    if h >= 2:
        s[0, 1] = s[0, 0]
    if h:
        s[1, :] = rod.length - 1e-3 * np.arange(h)  # every force distal to the last grating
    args = (q, s, f, rod.length, rod.bending_stiffness)
    _path(monkeypatch, "rows")
    rows = march_propagator(NUMPY, *args)
    _path(monkeypatch, "arrays")
    arrays = march_propagator(NUMPY, *args)
    if compiled.available():
        _path(monkeypatch, "compiled")
        for a, c in zip(rows, march_propagator(NUMPY, *args), strict=True):
            assert (a is None and c is None) or np.array_equal(a, c)
    xp = torch_backend()
    tensors = march_propagator(xp, *(torch.as_tensor(a) for a in args[:3]), *args[3:])
    for a, b, c in zip(rows, arrays, tensors, strict=True):
        if a is None:
            assert b is None and c is None
            continue
        assert a.shape == b.shape == tuple(c.shape)
        if a.size:
            scale = max(1.0, float(np.abs(a).max()))
            assert np.abs(a - b).max() <= 1e-12 * scale and np.abs(a - c.numpy()).max() <= 1e-12 * scale


def test_a_grating_at_a_force_gives_the_distal_one_sided_derivative(rod):
    """The schedule's tie-break (forces first): a grating exactly at a force sees it with zero lever, so its
    derivative in s is the slope jump i (f_x + i f_y) / EI; the curvature itself does not depend on the order."""
    q = rod.grating_positions()
    fx, fy = 0.4, -0.7
    s = torch.tensor([[q[6].item()]], dtype=F64)
    f = torch.tensor([[[fx, fy]]], dtype=F64)
    u, J = curvature_and_jacobian(q, s, f, rod.length, rod.bending_stiffness)
    jump = torch.tensor([-fy, fx], dtype=F64) / rod.bending_stiffness
    assert torch.allclose(J[0, 6, :, 0, 0], jump, rtol=1e-12)
    assert u[0, 6].abs().max() == 0.0  # zero lever
    assert J[0, 7:].abs().max() == 0.0  # distal gratings see nothing


def test_the_propagator_gives_the_response_to_a_new_force(rod, gen):
    """Phi(k) Phi(c)^-1 applied to a unit slope jump at c is the f-column of a zero force added at c."""
    B, h = 3, 2
    q = rod.grating_positions().numpy()
    s = np.sort(0.05 + 0.24 * torch.rand(B, h, dtype=F64, generator=gen).numpy(), 1)
    f = 0.6 * torch.randn(B, h, 2, dtype=F64, generator=gen).numpy()
    cand = np.sort(0.02 + 0.27 * torch.rand(B, 5, dtype=F64, generator=gen).numpy(), 1)
    G = q.shape[0]
    query = np.concatenate([np.broadcast_to(q, (B, G)), cand], 1)
    fine = {"step_angle": 0.02, "max_steps": 400}  # both marches converged: only the method is compared
    _u, _J, phi = march_propagator(NUMPY, query, s, f, rod.length, rod.bending_stiffness, **fine)
    ei = rod.bending_stiffness
    for b in range(B):
        for c in range(5):
            s2 = np.concatenate([s[b : b + 1], [[cand[b, c]]]], 1)
            f2 = np.concatenate([f[b : b + 1], [[[0.0, 0.0]]]], 1)
            _, J = march(NUMPY, q, s2, f2, rod.length, ei, **fine)
            col = J[0, :, :, h, 1]  # d/df_x of the zero force
            M = np.linalg.solve(phi[b, G + c], np.array([0.0, 0.0, 0.0, 1.0 / ei]))
            resp = np.array([phi[b, k, :2] @ M if q[k] < cand[b, c] else [0.0, 0.0] for k in range(G)])
            assert np.abs(col - resp).max() <= 1e-6 * np.abs(col).max()


def test_one_schedule_for_every_march(rod, gen):
    """The simulator's step counts are the schedule's ``"bound"`` rule, the estimator's the ``"estimate"`` rule
    on the same events; the array and Python-row simulators agree."""
    s = 0.03 + 0.26 * torch.rand(8, 3, dtype=F64, generator=gen)
    f = 1.2 * torch.randn(8, 3, 2, dtype=F64, generator=gen)
    loads = tr.PointForces(s, f)
    q = rod.grating_positions()
    xp = torch_backend()
    pos, order, seg = schedule.events(xp, q, s, rod.length)
    fmag = torch.linalg.vector_norm(f, dim=-1) / rod.bending_stiffness
    bound = schedule.step_counts(xp, s, fmag, pos, seg, step_angle=0.8, max_steps=64, rule="bound")
    assert torch.equal(bound, step_counts(rod, loads))
    jump = torch.complex(-f[..., 1], f[..., 0]) / rod.bending_stiffness
    est = schedule.step_counts(xp, s, jump, pos, seg, step_angle=0.8, max_steps=64, rule="estimate")
    assert not torch.equal(est, bound)  # two rules on one set of events
    with pytest.raises(ValueError, match="rule"):
        schedule.rates(xp, s, jump, pos, "guess")
    # The marches that start from the zero state skip the events distal to every force, and only those.
    skipped = schedule.skip_unloaded(xp, order, bound, 3)
    first = (order < 3).int().argmax(1)  # each row's most distal force, as an event index
    distal = torch.arange(order.shape[1])[None, :] < first[:, None]
    assert torch.equal(skipped, torch.where(distal, 0, bound)) and bool(distal.any())
    # Each row's steps end to end: the lengths cover its stepped segments, zero past its end; an event's slot is
    # the steps taken up to and including it.
    for backend, args in ((xp, (order, seg, skipped)), (NUMPY, (order.numpy(), seg.numpy(), skipped.numpy()))):
        hstep, slot = schedule.sequence(backend, *args)
        hstep, slot = torch.as_tensor(hstep), torch.as_tensor(slot)
        assert hstep.shape == (8, int(skipped.sum(1).max())) and slot.shape == order.shape
        for b in range(8):
            n = skipped[b].tolist()
            want = [seg[b, e].item() / n[e] for e in range(len(n)) for _ in range(n[e])]
            assert (
                torch.equal(hstep[b, : len(want)], torch.tensor(want, dtype=F64))
                and hstep[b, len(want) :].abs().sum() == 0
            )
            for e, idx in enumerate(order[b].tolist()):
                assert slot[b, idx] == sum(n[: e + 1])
    ref = tr.simulate(rod, loads).grating_curvature.numpy()  # steps every event
    rows = march_curvature(NUMPY, q.numpy(), s.numpy(), f.numpy(), rod.length, rod.bending_stiffness)
    arrays = march_curvature(xp, q, s, f, rod.length, rod.bending_stiffness).numpy()
    assert np.abs(rows - ref).max() < 1e-12 and np.abs(arrays - ref).max() < 1e-12


def test_the_one_row_schedule_is_the_array_schedule(rod):
    """``schedule.row`` (Python numbers, for the marches that run a row at a time) gives the same order, segments and
    step counts as ``events``, ``step_counts`` and ``skip_unloaded`` on arrays, for both rules, with and without the
    skip: random forces of 0 to 3, ties between forces, forces on gratings and at the tip, loads from 0.1 to 100 N
    (up to the step cap), and queries beside the gratings."""
    rng = np.random.default_rng(7)
    q = rod.grating_positions().numpy()
    xp = NUMPY
    checked = capped = 0
    for _ in range(400):
        h = int(rng.integers(0, 4))
        s = rng.uniform(0.0, rod.length, (1, h))
        if h >= 2 and rng.random() < 0.3:
            s[0, 1] = s[0, 0]
        if h and rng.random() < 0.3:
            s[0, 0] = q[rng.integers(q.shape[0])]
        if h and rng.random() < 0.1:
            s[0, -1] = rod.length
        f = rng.normal(0.0, rng.choice([0.1, 1.0, 10.0, 100.0]), (1, h, 2))
        query = q if rng.random() < 0.5 else np.concatenate([q, rng.uniform(0.0, rod.length, 10)])
        jumps = {
            "estimate": xp.complex(-f[..., 1], f[..., 0]) / rod.bending_stiffness,
            "bound": np.sqrt((f * f).sum(-1)) / rod.bending_stiffness,
        }
        pos, order, seg = schedule.events(xp, query, s, rod.length)
        for rule, jump in jumps.items():
            steps = schedule.step_counts(xp, s, jump, pos, seg, step_angle=0.3, max_steps=64, rule=rule)
            for skip in (False, True):
                want = schedule.skip_unloaded(xp, order, steps, h) if skip else steps
                got = schedule.row(
                    query.tolist(), s[0].tolist(), jump[0].tolist(), rod.length,
                    step_angle=0.3, max_steps=64, rule=rule, skip=skip,
                )  # fmt: skip
                assert got == (order[0].tolist(), seg[0].tolist(), want[0].tolist())
                checked += 1
                capped += int(want.max(initial=0) == 64)
    assert checked == 1600 and capped > 0
    with pytest.raises(ValueError, match="rule"):
        schedule.row([0.1], [0.2], [1j], rod.length, step_angle=0.3, max_steps=64, rule="guess", skip=False)


def _random_forces(rng, rod, q, zero: float = 0.0) -> tuple[np.ndarray, np.ndarray, bool]:
    """A batch of 1-5 rows of 0-3 forces from 0.1 to 10 N (past the step cap): ties between forces, forces on
    gratings and at the tip, with probability ``zero`` a zero force, and with probability 0.1 a NaN in one row.
    Returns s (B, h) [m], f (B, h, 2) [N] and whether a NaN was put in."""
    h, B = int(rng.integers(0, 4)), int(rng.integers(1, 6))
    s = rng.uniform(0.0, rod.length, (B, h))
    if h >= 2 and rng.random() < 0.3:
        s[:, 1] = s[:, 0]
    if h and rng.random() < 0.3:
        s[:, 0] = q[rng.integers(q.shape[0])]
    if h and rng.random() < 0.1:
        s[:, -1] = rod.length
    f = rng.normal(0.0, rng.choice([0.1, 1.0, 10.0]), (B, h, 2))
    if h and rng.random() < zero:
        f[0, 0] = 0.0
    nan = bool(h and rng.random() < 0.1)
    if nan:
        f[rng.integers(B), 0, 0] = np.nan
    return s, f, nan


@pytest.mark.skipif(not compiled.available(), reason="Numba is not installed (pip install torchrod[fast])")
def test_the_compiled_rows_are_the_python_rows_bit_for_bit(rod, monkeypatch):
    """The Numba march (schedule and steps) against the Python-number march, exactly: 300 random batches of 0 to 3
    forces from 0.1 to 10 N (past the step cap), ties between forces, forces on gratings and at the tip, padded
    forces, per-row queries, with and without the Jacobian and the propagator's seeds, and rows with a NaN input
    among finite ones (those stay on the Python path, the finite rows around them do not)."""
    assert compiled.load()
    rng = np.random.default_rng(11)
    q = rod.grating_positions().numpy()
    compared = nan_rows = 0
    for _ in range(300):
        s, f, nan = _random_forces(rng, rod, q)
        h, B, nan_rows = s.shape[1], s.shape[0], nan_rows + nan
        active = None if rng.random() < 0.5 else rng.random((B, h)) > 0.3
        query = q if rng.random() < 0.5 else rng.uniform(0.0, rod.length, (B, 20))
        jacobian, seeds = bool(h and rng.random() < 0.8), bool(rng.random() < 0.4)
        args = (query, s, f, rod.length, rod.bending_stiffness, active, jacobian, seeds, 0.3, int(rng.choice([2, 64])))
        monkeypatch.setenv("TORCHROD_NUMBA", "0")
        want = sens._march_rows(*args)
        monkeypatch.setenv("TORCHROD_NUMBA", "1")
        got = sens._march_rows(*args)
        for a, b in zip(want, got, strict=True):
            assert (a is None and b is None) or np.array_equal(a, b, equal_nan=True)
            compared += a is not None
    assert compared > 500 and nan_rows > 10
    monkeypatch.setenv("TORCHROD_NUMBA", "0")
    assert not compiled.available()


_LOADING = """
import sys, torch
import torchrod as tr
from torchrod.estimate.estimator import Estimator, EstimatorOptions
from torchrod.io.stream import warm_up
from torchrod.model import compiled
rod = tr.presets.load("nitinol290")
u = tr.simulate(rod, tr.PointForces.from_lists([[(0.2, 0.3, -0.2)], [(0.1, 0.2, 0.1), (0.25, -0.3, 0.2)]]))
u = u.grating_curvature + 0.1 * torch.randn(2, rod.num_gratings, 2, generator=torch.Generator().manual_seed(0))
est = Estimator(rod, EstimatorOptions(noise=0.1))
before = est.estimate(u[1:])
print("one reading", compiled.loaded())
{load}
print("loaded", compiled.loaded())
after = est.estimate(u[1:])
same = before.statuses == after.statuses and torch.equal(before.evaluations, after.evaluations)
same = same and torch.allclose(before.forces.s, after.forces.s, rtol=0, atol=1e-11)
print("same", same and torch.allclose(before.forces.f, after.forces.f, rtol=0, atol=1e-9))
"""


@pytest.mark.skipif(not compiled.available(), reason="Numba is not installed (pip install torchrod[fast])")
@pytest.mark.parametrize("load", ["warm_up(est)", "est.estimate(u.repeat(32, 1, 1))"])
def test_the_compiled_march_loads_for_large_marches_and_warm_ups_only(load):
    """In a new process: one reading marches only small batches, which do not load Numba (half a second, more than
    the reading costs); a stream's warm-up, or a batch with a march too large for the Python numbers, loads it; and
    the reading's answer is the same before and after: the same statuses and work, the fits to rounding (once
    loaded, its Levenberg-Marquardt steps run compiled too, tests/test_lm_compiled.py, whose sums and solves
    round differently from the array code's)."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _LOADING.format(load=load)], capture_output=True, text=True, timeout=300, check=True
    ).stdout.split("\n")
    assert out[:3] == ["one reading False", "loaded True", "same True"], out


@pytest.mark.skipif(not compiled.available(), reason="Numba is not installed (pip install torchrod[fast])")
def test_the_compiled_exact_model_rows_are_the_python_rows_bit_for_bit(rod, monkeypatch):
    """The exact model's march (``march_curvature``: the "bound" step rule and a tableau's generic RKN steps)
    compiled against its Python-number rows, exactly, for every tableau: 300 random batches as above, zero forces
    (no kick), and NaN rows among finite ones; and against the arrays at a large batch, to rounding."""
    assert compiled.load()
    rng = np.random.default_rng(5)
    q = rod.grating_positions().numpy()
    methods, nan_rows = set(), 0
    for _ in range(300):
        s, f, nan = _random_forces(rng, rod, q, zero=0.2)
        nan_rows += nan
        method = str(rng.choice(sorted(METHODS)))
        methods.add(method)
        args = (NUMPY, q, s, f, rod.length, rod.bending_stiffness)
        monkeypatch.setenv("TORCHROD_NUMBA", "0")
        want = march_curvature(*args, method=method)
        monkeypatch.setenv("TORCHROD_NUMBA", "1")
        assert np.array_equal(march_curvature(*args, method=method), want, equal_nan=True)
    assert methods == set(METHODS) and nan_rows > 10
    s = rng.uniform(0.02, rod.length, (200, 3))
    f = rng.normal(0.0, 0.5, (200, 3, 2))
    args = (NUMPY, q, s, f, rod.length, rod.bending_stiffness)
    got = march_curvature(*args)
    monkeypatch.setenv("TORCHROD_NUMBA", "0")
    arrays = march_curvature(*args)
    assert np.abs(got - arrays).max() <= 1e-12 * np.abs(arrays).max()


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_compiled_marches_that_cannot_run_warn_once_and_march_without(rod, gen, monkeypatch):
    """An incompatible Numba (here: kernels missing from their module) costs a warning, once: that march's rows go
    to the Python numbers, the next marches to the arrays, each with its path's own numbers."""
    import sys
    import types

    import torchrod.model

    broken = types.ModuleType("torchrod.model._kernels")
    monkeypatch.setitem(sys.modules, "torchrod.model._kernels", broken)
    monkeypatch.setattr(torchrod.model, "_kernels", broken, raising=False)
    monkeypatch.setattr(compiled, "_installed", lambda: True)
    monkeypatch.setattr(compiled, "_failure", None)
    monkeypatch.setenv("TORCHROD_NUMBA", "1")
    q = rod.grating_positions().numpy()
    s = 0.03 + 0.26 * torch.rand(40, 3, dtype=F64, generator=gen).numpy()
    f = 0.8 * torch.randn(40, 3, 2, dtype=F64, generator=gen).numpy()
    args = (NUMPY, q, s, f, rod.length, rod.bending_stiffness)
    with pytest.warns(RuntimeWarning, match="compiled marches could not run"):
        first = march(*args)
    assert not compiled.available() and "AttributeError" in compiled._failure
    second = march(*args)  # no warning: pytest's filter below turns one into an error
    monkeypatch.setenv("TORCHROD_NUMBA", "0")
    monkeypatch.setattr(sens, "SCALAR_WORK", 10**6)
    rows = march(*args)
    monkeypatch.setattr(sens, "SCALAR_WORK", 0)
    arrays = march(*args)
    assert all(np.array_equal(a, b) for a, b in zip(first, rows, strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(second, arrays, strict=True))
