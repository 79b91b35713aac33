"""Batched L-BFGS: a batch of one follows torch.optim.LBFGS, batched equals looped, samples stop on their own."""

from __future__ import annotations

import pytest
import torch

from torchrod import PointForces, grating_curvature, presets
from torchrod.estimate.refine import LBFGSOptions, RefineResult, lbfgs
from torchrod.model.body_frame import integrate_curvature

F64 = torch.float64


def rosenbrock(x: torch.Tensor) -> torch.Tensor:
    return (100.0 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1.0 - x[:, :-1]) ** 2).sum(1)


def torch_lbfgs(loss_of_vector, x0: torch.Tensor, options: LBFGSOptions) -> tuple[torch.Tensor, dict]:
    """torch.optim.LBFGS with the same settings on one parameter vector; returns x and its state."""
    p = x0.detach().clone().requires_grad_(True)
    opt = torch.optim.LBFGS(
        [p],
        lr=options.lr,
        max_iter=options.max_iter,
        max_eval=options.max_eval,
        tolerance_grad=options.tolerance_grad,
        tolerance_change=options.tolerance_change,
        history_size=options.history_size,
        line_search_fn="strong_wolfe",
    )

    def closure():
        opt.zero_grad()
        loss = loss_of_vector(p)
        loss.backward()
        return loss

    opt.step(closure)
    return p.detach(), opt.state[p]


def assert_same_as_torch(fun, x0: torch.Tensor, options: LBFGSOptions, tol: float = 1e-10) -> RefineResult:
    res = lbfgs(fun, x0.unsqueeze(0), options)
    ref, state = torch_lbfgs(lambda p: fun(p.unsqueeze(0), torch.zeros(1, dtype=torch.long))[0], x0, options)
    assert (res.x[0] - ref).abs().max().item() <= tol * max(1.0, ref.abs().max().item())
    assert int(res.iterations[0]) == state["n_iter"]
    assert int(res.evaluations[0]) == state["func_evals"]
    return res


# ---------------------------------------------------------------------------------------------- torch agreement
@pytest.mark.parametrize(
    "start, options",
    [
        ([-1.2, 1.0], LBFGSOptions()),
        ([-1.2, 1.0], LBFGSOptions(max_iter=20, history_size=5, lr=0.5)),
        ([-1.5, 2.0, 0.5, -0.3], LBFGSOptions(history_size=100, max_iter=200)),
        ([3.0, -2.0], LBFGSOptions(max_iter=60, max_eval=40)),  # stops on max_eval
        # the line search runs out of evaluations
        ([-1.2, 1.0, 0.8], LBFGSOptions(max_iter=40, max_eval=9, history_size=3)),
    ],
)
def test_one_sample_matches_torch_on_rosenbrock(start, options):
    assert_same_as_torch(lambda x, rows: rosenbrock(x), torch.tensor(start, dtype=F64), options)


@pytest.mark.parametrize("lr, tol", [(3.0, 1e-10), (10.0, 1e-8)])
def test_every_iterate_matches_torch_with_long_steps(lr, tol):
    """Long first trials make the line search extrapolate, bracket and zoom; compare the k-th iterate for every k.

    The decisions (iterations, evaluations) agree exactly; the iterates differ only by rounding (torch's BLAS dot
    products sum in another order), which the Rosenbrock valley amplifies to ~1e-9 midway with lr = 10 before it
    shrinks again near the minimum.
    """
    x0 = torch.tensor([-1.2, 1.0], dtype=F64)
    counts = []
    for k in range(1, 31):
        options = LBFGSOptions(max_iter=k, lr=lr, max_eval=400, history_size=4)
        res = assert_same_as_torch(lambda x, rows: rosenbrock(x), x0, options, tol)
        counts.append(int(res.evaluations[0]))
    assert counts[-1] > 31  # the line searches did more than accept their first trial
    assert res.converged[0] and res.loss[0] < 1e-9


ROD = presets.nitinol290()
S_UNIT = 0.1  # the location is fitted in units of 10 cm so that s and f have similar sensitivities


def one_force_curvature(x: torch.Tensor, *, steps: int | None = None) -> torch.Tensor:
    """(B, G, 2) curvature of one force with x = (s / 10 cm, fx [N], fy [N])."""
    loads = PointForces(S_UNIT * x[:, :1], x[:, None, 1:])
    if steps is None:
        return grating_curvature(ROD, loads)
    query = ROD.grating_positions(x.dtype, x.device)
    return integrate_curvature(query, loads, ROD.length, ROD.bending_stiffness, steps=steps)[0]


def test_one_sample_matches_torch_on_a_torchrod_fit():
    truth = torch.tensor([[1.7, 0.3, -0.5]], dtype=F64)
    reading = one_force_curvature(truth)
    start = torch.tensor([1.5, 0.2, -0.3], dtype=F64)

    def fun(x, rows):
        return ((one_force_curvature(x) - reading[rows]) ** 2).sum((1, 2))

    res = assert_same_as_torch(fun, start, LBFGSOptions())
    assert bool(res.converged[0])
    assert (res.x - truth).abs().max().item() < 1e-4  # the fit recovers the force it was simulated with


# ---------------------------------------------------------------------------------------------- batching
def test_batched_equals_one_at_a_time_on_torchrod_fits():
    g = torch.Generator().manual_seed(3)
    B = 6
    truth = torch.cat(
        (
            0.5 + 2.0 * torch.rand(B, 1, generator=g, dtype=F64),
            2 * torch.rand(B, 2, generator=g, dtype=F64) - 1,
        ),
        1,
    )
    # fixed steps: every row's model is independent of the batch
    readings = one_force_curvature(truth, steps=3)
    x0 = truth + 0.15 * torch.randn(B, 3, generator=g, dtype=F64)

    def fun(x, rows):
        return ((one_force_curvature(x, steps=3) - readings[rows]) ** 2).sum((1, 2))

    options = LBFGSOptions()
    batched = lbfgs(fun, x0, options)
    for i in range(B):
        alone = lbfgs(lambda x, rows, i=i: fun(x, rows + i), x0[i : i + 1], options)
        assert (batched.x[i] - alone.x[0]).abs().max().item() < 1e-12
        assert int(batched.iterations[i]) == int(alone.iterations[0])
        assert int(batched.evaluations[i]) == int(alone.evaluations[0])
        assert bool(batched.converged[i]) == bool(alone.converged[0])
    assert bool(batched.converged.all())
    assert len(set(batched.iterations.tolist())) > 1  # the rows stopped at different iterations


def test_a_hard_row_does_not_hold_back_the_others():
    """Rows: two quadratics, Rosenbrock (slow), an unbounded linear loss (diverges), a NaN loss."""
    scales = torch.tensor([1.0, 30.0], dtype=F64)

    def fun(x, rows):
        quad = ((x - 0.5) ** 2 * scales).sum(1)
        out = torch.where(rows <= 1, quad, rosenbrock(x))
        out = torch.where(rows == 3, -(x.sum(1)), out)
        # NaN only in row 4, its gradient included
        nan_row = torch.where(rows == 4, float("nan"), 1.0).to(x.dtype)
        return torch.where(rows == 4, x.sum(1) * nan_row, out)

    calls: list[list[int]] = []

    def counting(x, rows):
        calls.append(rows.tolist())
        return fun(x, rows)

    x0 = torch.tensor([[3.0, -1.0], [-2.0, 4.0], [-1.2, 1.0], [0.0, 0.0], [1.0, 1.0]], dtype=F64)
    options = LBFGSOptions(max_iter=60)
    res = lbfgs(counting, x0, options)
    assert res.converged.tolist() == [True, True, True, False, False]
    assert (res.x[:3] - torch.tensor([[0.5, 0.5], [0.5, 0.5], [1.0, 1.0]], dtype=F64)).abs().max() < 1e-5
    # each row evolves as if it were alone
    for i in range(4):
        alone = lbfgs(lambda x, rows, i=i: fun(x, rows + i), x0[i : i + 1], options)
        assert torch.equal(res.x[i], alone.x[0]) or (res.x[i] - alone.x[0]).abs().max() < 1e-12
        assert int(res.iterations[i]) == int(alone.iterations[0])
        assert int(res.evaluations[i]) == int(alone.evaluations[0])
    # the diverging row ran out of its budget; the NaN row stopped after its first evaluation
    assert int(res.iterations[3]) == options.max_iter or int(res.evaluations[3]) >= options.evaluations_limit
    assert res.loss[3] < -1e3
    assert int(res.evaluations[4]) == 1 and int(res.iterations[4]) == 0
    # finished rows are not evaluated again: calls shrink to the rows still running, and each row's count of
    # appearances is its evaluation count
    assert calls[0] == [0, 1, 2, 3, 4]
    assert calls[-1] == [3]
    for i in range(5):
        assert sum(i in c for c in calls) == int(res.evaluations[i])
    assert len(set(res.iterations[:3].tolist())) == 3


def test_a_start_at_the_minimum_stops_at_once():
    res = lbfgs(lambda x, rows: rosenbrock(x), torch.ones(2, 3, dtype=F64))
    assert res.converged.all() and (res.iterations == 0).all() and (res.evaluations == 1).all()
    assert torch.equal(res.x, torch.ones(2, 3, dtype=F64))


# ---------------------------------------------------------------------------------------------- dtype, device, errors
def test_dtype_follows_x0():
    x0 = torch.tensor([[-1.2, 1.0], [0.5, 2.0]], dtype=torch.float32)
    res = lbfgs(lambda x, rows: rosenbrock(x), x0, LBFGSOptions(tolerance_change=1e-12, tolerance_grad=1e-5))
    for t in (res.x, res.loss, res.grad):
        assert t.dtype == torch.float32 and t.device == x0.device
    assert res.converged.dtype == torch.bool and res.iterations.dtype == torch.long
    assert (res.x - 1.0).abs().max() < 1e-2


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    x0 = torch.tensor([[-1.2, 1.0], [3.0, -2.0], [0.0, 0.0]], dtype=F64)
    cpu = lbfgs(lambda x, rows: rosenbrock(x), x0)
    gpu = lbfgs(lambda x, rows: rosenbrock(x), x0.cuda())
    assert gpu.x.device.type == "cuda" and gpu.iterations.device.type == "cuda"
    assert (gpu.x.cpu() - cpu.x).abs().max() < 1e-6
    assert torch.equal(gpu.converged.cpu(), cpu.converged)


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match=r"\(B, P\)"):
        lbfgs(lambda x, rows: x.sum(1), torch.zeros(3, dtype=F64))
    with pytest.raises(TypeError, match="floating"):
        lbfgs(lambda x, rows: x.sum(1), torch.zeros(2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        lbfgs(lambda x, rows: x.sum(), torch.zeros(2, 2, dtype=F64))
    with pytest.raises(ValueError, match="history_size"):
        LBFGSOptions(history_size=0)
    with pytest.raises(ValueError, match="lr"):
        LBFGSOptions(lr=0.0)
    assert LBFGSOptions(max_iter=20).evaluations_limit == 25
