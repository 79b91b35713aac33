"""The paper's experiments (Xiao & Chen, "Efficient Force Estimation for Continuum Robot"), as reusable functions.

Three pieces, used by ``torchrod bench paper`` and by the figures of :mod:`torchrod.eval.plots`:

Baseline estimators (:func:`fit_forces`, :func:`paper_estimate`)
    The paper compares three ways of computing the curvature inside one outer optimiser (MATLAB's fmincon): the
    global-frame BVP solved by shooting with Levenberg-Marquardt (a finite-difference Jacobian), the same with
    derivative propagation, and its body-frame IVP with point forces spread onto q nodes. Here the three share one
    outer optimiser too: scipy's ``least_squares`` (trust-region reflective, the location bounded to [0, L]) on the
    curvature residuals, with a forward-difference Jacobian over each force's (s, f_x, f_y) (:class:`FitOptions`:
    same steps, same tolerances, same start for every inner model). The inner models (:class:`CurvatureModel`):

    * :class:`BVPModel`: :class:`torchrod.model.global_bvp.ShootingSolver` (classical RK4 on the q nodes, the paper's
      node spreading of the forces) with ``jacobian="fd"`` (Levenberg-Marquardt, its 6 perturbed shots integrated as one
      vectorised batch) or ``"dp"`` (derivative propagation). Every inner solve is warm-started from the solution at
      the outer iterate last evaluated (the perturbed solves of the outer Jacobian from the one at their base point).
    * :class:`NodeModel`: the body-frame IVP with the node scheme (:func:`torchrod.model.body_frame.grating_curvature`,
      ``scheme="nodes"``); the outer Jacobian's perturbed force sets are one batched call.

    All three discretise the same problem (RK4-class integration of the same node-spread load), so their estimates
    agree to the inner solver's tolerance; torchrod's own estimator integrates exact point loads and agrees with
    them to the node scheme's discretisation error, which falls as q^-2.

    The count: :func:`paper_estimate` fits h = 1, 2, ... until the loss drops below the paper's threshold 3.0
    (its rule, erratum 4 in docs/physics.md), or fits a given count. Starts: the best candidate of torchrod's grid scan
    (:class:`torchrod.eval.grid_starts.GridStarts`, small-deflection linear least squares), the same for every inner
    model.

Readings and accuracy (:func:`paper_readings`, :func:`accuracy`)
    Shaped like the paper's experiments: for k = 1, 2, 3 forces, 13 cases whose (mean) locations are spread along
    the rod (one per 13th of the location range), magnitudes 0.27 to 1.96 N in any body-frame direction, the rod
    turning by at most 90 degrees; readings simulated with the paper's calibrated location bias and Gaussian noise.
    RMSE of the force magnitude and of the location over the estimated forces paired with the true ones.

Loss maps (:func:`loss_maps`)
    The paper's figure: the curvature loss and the shape loss over a grid of (location, magnitude) of one force,
    around a true force at 200 mm, 0.3 N; the whole grid in one batched forward call.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, cast

import numpy as np
import torch

from ..errors import OptionsError, TorchrodTypeError
from ..kernels import counts
from ..loads import PointForces
from ..model.body_frame import grating_curvature, simulate
from ..model.global_bvp import BVPSolution, ShootingSolver
from ..model.shape import rod_shape
from ..rod import Rod
from .grid_starts import GridStarts

__all__ = [
    "BASELINES",
    "FORCE_RANGE",
    "PAPER_FORCE_RMSE",
    "PAPER_LOCATION_RMSE",
    "PAPER_NODES",
    "PAPER_SPEEDUP",
    "PAPER_TABLE_II",
    "PAPER_THRESHOLD",
    "PAPER_TIMES",
    "Accuracy",
    "AccuracyStudy",
    "BVPModel",
    "CurvatureModel",
    "Fit",
    "FitOptions",
    "LossMaps",
    "MethodRun",
    "NodeModel",
    "PaperEstimate",
    "Readings",
    "SpeedTable",
    "Timed",
    "accuracy",
    "accuracy_study",
    "exact_loss",
    "fit_forces",
    "grid_start",
    "loss_maps",
    "make_model",
    "match_forces",
    "paper_estimate",
    "paper_readings",
    "speed_table",
]

# ------------------------------------------------------------------------------------------------ the paper's numbers
PAPER_TABLE_II: dict[int, dict[str, float]] = {
    50: {"bvp_lm": 4.68, "bvp_dp": 2.23, "nodes": 0.07},
    100: {"bvp_lm": 14.22, "bvp_dp": 4.06, "nodes": 0.14},
    150: {"bvp_lm": 21.28, "bvp_dp": 4.91, "nodes": 0.19},
    200: {"bvp_lm": 27.61, "bvp_dp": 7.63, "nodes": 0.26},
}
"""Its Table II: single-force estimation time [s] per node count q (MATLAB, fmincon, 6-core i7)."""

PAPER_SPEEDUP: dict[str, float] = {"bvp_lm": 101.6, "bvp_dp": 29.0}
"""Its speed-ups of the body-frame method at q = 100 (time of the baseline / time of its method)."""

PAPER_FORCE_RMSE: dict[int, float] = {1: 0.084, 2: 0.115, 3: 0.109}
"""Force-magnitude RMSE [N] for 1, 2, 3 forces at q = 250 (13 experiments each, the real bench)."""

PAPER_LOCATION_RMSE: dict[int, float] = {1: 2.95e-3, 2: 3.15e-3, 3: 5.19e-3}
"""Location RMSE [m] for 1, 2, 3 forces at q = 250."""

PAPER_TIMES: dict[int, dict[int, float]] = {
    90: {1: 0.134, 2: 0.344, 3: 0.730},
    250: {1: 0.315, 2: 0.857, 3: 1.890},
}
"""Estimation time [s] of its method for 1, 2, 3 forces at q = 90 and 250."""

PAPER_THRESHOLD = counts.PAPER_THRESHOLD
"""Its count rule: raise h until the curvature loss [1/m^2] drops below this (the estimator's ``threshold``)."""

PAPER_NODES = 250
"""The node count of its accuracy results."""

FORCE_RANGE = (0.27, 1.96)
"""[N] the range of the forces of its experiments."""


# ================================================================================================ inner models
class CurvatureModel:
    """An inner curvature model: force sets in model coordinates -> curvature at the rod's gratings.

    Subclasses implement :meth:`__call__`; ``evaluations`` counts the force sets evaluated (one per row).
    """

    name = "model"

    def __init__(self, rod: Rod, nodes: int) -> None:
        if not isinstance(rod, Rod):
            raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
        if not isinstance(nodes, int) or isinstance(nodes, bool) or nodes < 2:
            raise OptionsError(f"nodes must be an integer >= 2, got {nodes!r}")
        self.rod = rod
        self.nodes = nodes
        self.evaluations = 0

    def __call__(self, x: np.ndarray, *, base: bool = True) -> np.ndarray:
        """Curvature (K, G, 2) [1/m] for K force sets ``x`` (K, h, 3) of rows (s [m] model, f_x [N], f_y [N]).

        ``base``: row 0 is an outer iterate (a warm-startable model keeps its solution); False: the rows are
        perturbations of the last iterate (the outer Jacobian), which start from it and leave it as it is.
        """
        raise NotImplementedError

    def reset(self) -> None:
        """Forget any warm-start state (before a new reading)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(nodes={self.nodes})"


class NodeModel(CurvatureModel):
    """The paper's method: the body-frame IVP with forces spread onto q nodes (batched torch, float64, no grad)."""

    name = "nodes"

    def __call__(self, x: np.ndarray, *, base: bool = True) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        self.evaluations += x.shape[0]
        t = torch.from_numpy(np.ascontiguousarray(x))
        with torch.no_grad():
            u = grating_curvature(self.rod, PointForces(t[..., 0], t[..., 1:]), scheme="nodes", nodes=self.nodes)
        return u.numpy()


class BVPModel(CurvatureModel):
    """The global-frame BVP by shooting (RK4 on q nodes, node-spread forces), warm-started (module docstring).

    Args:
        rod, nodes: the rod and q.
        jacobian: ``"fd"`` (Levenberg-Marquardt with a finite-difference Jacobian: the paper's "BVP + LM") or
            ``"dp"`` (derivative propagation: "BVP + DP").
        tol: the shooting tolerance on the scaled tip residual (:class:`torchrod.model.global_bvp.ShootingSolver`).
    Attributes ``solves``, ``iterations`` and ``failures`` count the inner solves, their Levenberg-Marquardt
    iterations and the solves that did not converge.
    """

    def __init__(self, rod: Rod, nodes: int, jacobian: Literal["fd", "dp"] = "dp", *, tol: float = 1e-10) -> None:
        super().__init__(rod, nodes)
        self.solver = ShootingSolver(rod, nodes=nodes, jacobian=jacobian, scheme="nodes", tol=tol, warm_start=False)
        self.name = f"bvp_{'lm' if jacobian == 'fd' else 'dp'}"
        self._anchor: BVPSolution | None = None
        self.solves = self.iterations = self.failures = 0

    def reset(self) -> None:
        self._anchor = None

    def __call__(self, x: np.ndarray, *, base: bool = True) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        out = np.empty((x.shape[0], self.rod.num_gratings, 2))
        anchor = self._anchor
        for k in range(x.shape[0]):
            sol = self.solver.solve(x[k], at=self.rod.gratings, initial=anchor)
            self.evaluations += 1
            self.solves += 1
            self.iterations += sol.iterations
            if not sol.converged:
                self.failures += 1
                out[k] = np.nan
                continue
            out[k] = sol.curvature
            if base and k == 0:
                self._anchor = sol
        return out


# ================================================================================================ the outer fit
@dataclass(frozen=True)
class FitOptions:
    """Settings of the shared outer optimiser (scipy ``least_squares``, method "trf").

    Attributes:
        ftol, xtol, gtol: scipy's tolerances (relative loss change, relative step, scaled gradient).
        max_nfev: most residual evaluations.
        diff_step: forward-difference step, relative to the variable scales (L for s, EI / L^2 for forces).
    """

    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-8
    max_nfev: int = 200
    diff_step: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("ftol", "xtol", "gtol", "diff_step"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise OptionsError(f"{name} must be a positive number, got {v!r}")
        if not isinstance(self.max_nfev, int) or self.max_nfev < 1:
            raise OptionsError(f"max_nfev must be an integer >= 1, got {self.max_nfev!r}")


@dataclass(frozen=True)
class Fit:
    """One outer fit of h forces.

    Attributes:
        forces: (h, 3) rows (s [m], f_x [N], f_y [N]), sorted by s; s REPORTED (model + rod.location_bias).
        loss: sum over present gratings of squared curvature residuals [1/m^2].
        nfev, njev: residual and Jacobian evaluations of the outer optimiser.
        evaluations: force sets the inner model evaluated (Jacobian columns included).
        success: scipy's success flag (a tolerance was met).
        seconds: wall time of the fit [s].
    """

    forces: np.ndarray
    loss: float
    nfev: int
    njev: int
    evaluations: int
    success: bool
    seconds: float

    @property
    def num_forces(self) -> int:
        return int(self.forces.shape[0])


def _reading(curvature, mask, G: int) -> tuple[np.ndarray, np.ndarray]:
    u = np.asarray(curvature.detach().cpu().numpy() if isinstance(curvature, torch.Tensor) else curvature, float)
    if u.shape != (G, 2):
        raise OptionsError(f"a reading must have shape (G, 2) = ({G}, 2), got {u.shape}")
    if mask is None:
        m = np.isfinite(u).all(-1)
    else:
        m = np.asarray(mask.cpu().numpy() if isinstance(mask, torch.Tensor) else mask, dtype=bool)
        if m.shape != (G,):
            raise OptionsError(f"mask must have shape (G,) = ({G},), got {m.shape}")
    if not m.any():
        raise OptionsError("the reading has no present grating")
    return np.where(m[:, None], u, 0.0), m


def fit_forces(
    model: CurvatureModel,
    curvature,
    start: np.ndarray,
    *,
    mask=None,
    options: FitOptions = FitOptions(),
) -> Fit:
    """Fit h forces to one reading with the shared outer optimiser and ``model`` inside.

    Args:
        model: the inner curvature model (its rod gives L, EI, gratings and the location bias).
        curvature: (G, 2) measured (u_x, u_y) [1/m] (array or tensor).
        start: (h, 3) starting rows (s [m] MODEL coordinates, f_x [N], f_y [N]).
        mask: (G,) bool, True where the grating was read; None: the finite entries.
        options: :class:`FitOptions`.
    Returns:
        :class:`Fit` (locations reported: model + ``rod.location_bias``).
    """
    from scipy.optimize import least_squares

    rod = model.rod
    u, m = _reading(curvature, mask, rod.num_gratings)
    start = np.asarray(start, dtype=np.float64)
    if start.ndim != 2 or start.shape[1] != 3 or start.shape[0] < 1:
        raise OptionsError(f"start must have shape (h, 3) with h >= 1, got {start.shape}")
    h = start.shape[0]
    L = rod.length
    F = rod.bending_stiffness / L**2
    scale = np.tile([L, F, F], h)
    lower = np.tile([0.0, -np.inf, -np.inf], h)
    upper = np.tile([L, np.inf, np.inf], h)
    x0 = start.reshape(-1).copy()
    x0[0::3] = np.clip(x0[0::3], 1e-3 * L, (1.0 - 1e-3) * L)
    target = u[m].reshape(-1)
    cache: dict[bytes, np.ndarray] = {}
    model.reset()
    evals0 = model.evaluations

    def fun(x: np.ndarray) -> np.ndarray:
        r = model(x.reshape(1, h, 3))[0][m].reshape(-1) - target
        cache.clear()
        cache[x.tobytes()] = r
        return np.nan_to_num(r, nan=1e6)

    def jac(x: np.ndarray) -> np.ndarray:
        r0 = cache.get(x.tobytes())
        if r0 is None:
            r0 = fun(x)
        step = options.diff_step * scale
        step = np.where(x + step > upper, -step, step)  # backward at the upper bound
        X = x + np.diag(step)
        R = model(X.reshape(-1, h, 3), base=False)[:, m].reshape(X.shape[0], -1) - target
        return np.nan_to_num((R - r0) / step[:, None], nan=0.0).T

    t0 = time.perf_counter()
    res = least_squares(
        fun,
        x0,
        jac=jac,
        bounds=(lower, upper),
        method="trf",
        x_scale=scale,
        ftol=options.ftol,
        xtol=options.xtol,
        gtol=options.gtol,
        max_nfev=options.max_nfev,
    )
    seconds = time.perf_counter() - t0
    rows = res.x.reshape(h, 3).copy()
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    rows[:, 0] += rod.location_bias
    return Fit(
        forces=rows,
        loss=float(2.0 * res.cost),
        nfev=int(res.nfev),
        njev=int(res.njev or 0),
        evaluations=model.evaluations - evals0,
        success=bool(res.success),
        seconds=seconds,
    )


def exact_loss(rod: Rod, curvature, forces, mask=None) -> float:
    """The curvature loss [1/m^2] of reported rows ``forces`` (h, 3) (s reported, f_x, f_y) for one reading (G, 2),
    under torchrod's exact point-load model (locations mapped to the model's: s - ``rod.location_bias``): a common
    yardstick for estimates made with different models."""
    u, m = _reading(curvature, mask, rod.num_gratings)
    rows = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
    if not len(rows):
        return float((u[m] ** 2).sum())
    s = np.clip(rows[:, 0] - rod.location_bias, 0.0, rod.length)
    loads = PointForces(torch.from_numpy(s[None].copy()), torch.from_numpy(rows[None, :, 1:].copy()))
    with torch.no_grad():
        model = grating_curvature(rod, loads)[0].numpy()
    return float(((model - u)[m] ** 2).sum())


def grid_start(grid: GridStarts, curvature, h: int, mask=None) -> np.ndarray:
    """(h, 3) the best candidate of the grid scan for h forces (model coordinates): the baselines' shared start."""
    rod = grid.rod
    u, m = _reading(curvature, mask, rod.num_gratings)
    st = grid(torch.as_tensor(u, dtype=grid.dtype).unsqueeze(0), torch.as_tensor(m).unsqueeze(0), h, 1)
    s = st.s[0, 0].cpu().numpy()
    f = st.f[0, 0].cpu().numpy()
    return np.concatenate((s[:, None], f), axis=1)


@dataclass(frozen=True)
class PaperEstimate:
    """The paper's procedure on one reading.

    Attributes:
        fit: the chosen fit (its ``forces`` are the estimate, reported coordinates).
        fits: every count fitted, h -> :class:`Fit`.
        seconds: total wall time [s] (all counts fitted, starts included).
    """

    fit: Fit
    fits: dict[int, Fit]
    seconds: float

    @property
    def num_forces(self) -> int:
        return self.fit.num_forces


def paper_estimate(
    model: CurvatureModel,
    curvature,
    *,
    mask=None,
    num_forces: int | None = None,
    max_forces: int = 3,
    threshold: float = PAPER_THRESHOLD,
    grid: GridStarts | None = None,
    options: FitOptions = FitOptions(),
) -> PaperEstimate:
    """The paper's estimation: fit h = 1, 2, ... until the loss drops below ``threshold`` [1/m^2] (at most
    ``max_forces``; the last one fitted is kept), or fit ``num_forces`` when given. Starts: :func:`grid_start`."""
    grid = GridStarts(model.rod) if grid is None else grid
    counts = [num_forces] if num_forces is not None else list(range(1, max_forces + 1))
    t0 = time.perf_counter()
    fits: dict[int, Fit] = {}
    chosen = None
    for h in counts:
        fits[h] = fit_forces(model, curvature, grid_start(grid, curvature, h, mask), mask=mask, options=options)
        chosen = fits[h]
        if num_forces is None and chosen.loss < threshold:
            break
    assert chosen is not None
    return PaperEstimate(fit=chosen, fits=fits, seconds=time.perf_counter() - t0)


# ================================================================================================ readings, accuracy
@dataclass(frozen=True)
class Readings:
    """Simulated readings with their true loads.

    Attributes:
        curvature: (N, G, 2) noisy readings [1/m]; mask: (N, G) bool.
        loads: the true forces (N, H), REPORTED coordinates (the locations the estimators must return).
        noise: the sensor sigma [1/m]; location_bias: the bias simulated [m].
    """

    curvature: torch.Tensor
    mask: torch.Tensor
    loads: PointForces
    noise: float
    location_bias: float

    def __len__(self) -> int:
        return self.curvature.shape[0]

    def truth(self, i: int) -> np.ndarray:
        """(k, 3) rows (s [m], f_x [N], f_y [N]) of reading i, sorted by s."""
        rows = np.array(self.loads[i].to_lists()[0], dtype=np.float64).reshape(-1, 3)
        return rows[np.argsort(rows[:, 0], kind="stable")]


def paper_readings(
    rod: Rod,
    forces: int,
    count: int = 13,
    *,
    noise: float = 0.15,
    seed: int = 0,
    force_range: tuple[float, float] = FORCE_RANGE,
    s_range: tuple[float, float] | None = None,
    min_separation: float = 0.025,
    max_bending: float = math.pi / 2,
) -> Readings:
    """``count`` readings with ``forces`` forces each, shaped like the paper's experiments (module docstring).

    Loads come from :func:`torchrod.synthetic.loadsets.generate` (``LoadSampler`` with ``force_range``, ``s_range``
    (default: the second grating to 10 mm short of the tip), ``min_separation`` and ``max_bending``;
    ``SensorModel(noise=noise, location_bias=rod.location_bias)``): from a pool of 12 x ``count`` cases, case j is
    the first whose mean location lies in the j-th of ``count`` equal parts of the location range (the nearest
    unused case when a part is empty), so the cases spread along the rod.
    """
    from ..synthetic import LoadSampler, SensorModel, generate

    if count < 1:
        raise OptionsError(f"count must be >= 1, got {count}")
    lo, hi = s_range if s_range is not None else (rod.gratings[min(1, rod.num_gratings - 1)], rod.length - 0.01)
    sampler = LoadSampler(
        min_forces=forces,
        max_forces=forces,
        force_range=force_range,
        min_separation=min_separation,
        s_range=(lo, hi),
        max_bending=max_bending,
    )
    sensor = SensorModel(noise=noise, location_bias=rod.location_bias)
    pool = generate(rod, 12 * count, sampler=sampler, sensor=sensor, seed=seed)
    s = pool.loads.s
    key = ((s * pool.loads.active).sum(1) / pool.loads.count).numpy()
    edges = np.linspace(lo, hi, count + 1)
    used = np.zeros(len(key), dtype=bool)
    chosen: list[int] = []
    for j in range(count):
        inside = np.nonzero((key >= edges[j]) & (key <= edges[j + 1]) & ~used)[0]
        if inside.size:
            pick = int(inside[0])
        else:
            distance = np.where(used, np.inf, np.abs(key - 0.5 * (edges[j] + edges[j + 1])))
            pick = int(np.argmin(distance))
        used[pick] = True
        chosen.append(pick)
    idx = torch.tensor(chosen)
    return Readings(
        curvature=pool.curvature[idx],
        mask=pool.mask[idx],
        loads=pool.loads[idx].sorted(),
        noise=noise,
        location_bias=rod.location_bias,
    )


def match_forces(true: np.ndarray, estimate: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (i_true, j_estimate) of forces: in order of location when the counts agree, else the assignment of
    min(k, m) pairs with the least total location distance. Rows are (s, f_x, f_y)."""
    true = np.asarray(true, dtype=np.float64).reshape(-1, 3)
    estimate = np.asarray(estimate, dtype=np.float64).reshape(-1, 3)
    if len(true) == len(estimate):
        return list(zip(np.argsort(true[:, 0]).tolist(), np.argsort(estimate[:, 0]).tolist(), strict=False))
    from scipy.optimize import linear_sum_assignment

    cost = np.abs(true[:, None, 0] - estimate[None, :, 0])
    i, j = linear_sum_assignment(cost)
    return list(zip(i.tolist(), j.tolist(), strict=False))


@dataclass(frozen=True)
class Accuracy:
    """Accuracy of estimates against the truth (the paper's RMSE), over readings of one force count.

    Attributes:
        readings: how many; count_correct: how many with the right count.
        force_rmse: RMSE of | |f_est| - |f_true| | over paired forces [N].
        location_rmse: RMSE of s_est - s_true over paired forces [m].
        force_errors, location_errors: the paired errors [N], [m].
    """

    readings: int
    count_correct: int
    force_rmse: float
    location_rmse: float
    force_errors: np.ndarray = field(repr=False)
    location_errors: np.ndarray = field(repr=False)


def accuracy(truth: Sequence[np.ndarray], estimates: Sequence[np.ndarray]) -> Accuracy:
    """:class:`Accuracy` of ``estimates`` (per reading (m, 3) rows, reported coordinates) against ``truth`` (per
    reading (k, 3)); forces paired by :func:`match_forces` (unpaired ones enter only the count accuracy)."""
    if len(truth) != len(estimates):
        raise OptionsError(f"{len(truth)} truths but {len(estimates)} estimates")
    df, ds = [], []
    right = 0
    for t, e in zip(truth, estimates, strict=False):
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        e = np.asarray(e, dtype=np.float64).reshape(-1, 3)
        right += int(len(t) == len(e))
        for i, j in match_forces(t, e):
            df.append(math.hypot(e[j, 1], e[j, 2]) - math.hypot(t[i, 1], t[i, 2]))
            ds.append(e[j, 0] - t[i, 0])
    df_a, ds_a = np.array(df), np.array(ds)

    def rmse(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a**2))) if a.size else math.nan

    return Accuracy(len(truth), right, rmse(df_a), rmse(ds_a), df_a, ds_a)


# ================================================================================================ loss maps
@dataclass(frozen=True)
class LossMaps:
    """The loss maps of the paper's figure.

    Attributes:
        s: (S,) model locations of the grid [m]; magnitude: (F,) force magnitudes of the grid [N].
        curvature_loss: (F, S) sum over gratings of |u - u_true|^2 [1/m^2].
        shape_loss: (F, S) sum over the centreline samples of |P - P_true|^2 [m^2].
        true: (3,) the true force (s [m], f_x [N], f_y [N]); direction: (2,) the unit direction of the grid's forces.
        samples: (P,) the centreline sample positions of the shape loss [m].
    """

    s: np.ndarray
    magnitude: np.ndarray
    curvature_loss: np.ndarray
    shape_loss: np.ndarray
    true: np.ndarray
    direction: np.ndarray
    samples: np.ndarray

    def minimum(self, which: str) -> tuple[float, float]:
        """(s [m], magnitude [N]) of the grid's smallest ``"curvature"`` or ``"shape"`` loss."""
        grid = {"curvature": self.curvature_loss, "shape": self.shape_loss}[which]
        i, j = np.unravel_index(np.nanargmin(grid), grid.shape)
        return float(self.s[j]), float(self.magnitude[i])


def loss_maps(
    rod: Rod,
    *,
    true: tuple[float, float, float] = (0.2, 0.3, 0.0),
    s_range: tuple[float, float] = (0.1, 0.29),
    magnitude_range: tuple[float, float] = (0.0, 0.5),
    size: tuple[int, int] = (96, 101),
    samples: int = 59,
) -> LossMaps:
    """The curvature and shape losses of one force over a (location, magnitude) grid (module docstring).

    Args:
        rod: the rod (exact point loads, model coordinates).
        true: the true force (s [m], f_x [N], f_y [N]); the grid's forces share its direction.
        s_range: (low, high) locations [m]; magnitude_range: (low, high) magnitudes [N].
        size: (S, F) grid points in location and in magnitude.
        samples: uniform centreline samples on [0, L] for the shape loss (P = samples).
    Returns:
        :class:`LossMaps`; the truth and the S x F grid are evaluated in one batched :func:`torchrod.simulate`
        call (curvature at the gratings and along the rod), the shapes by :func:`torchrod.model.shape.rod_shape`.
    """
    S, F = size
    if S < 2 or F < 2:
        raise OptionsError(f"size must be at least (2, 2), got {size}")
    s0, fx0, fy0 = (float(v) for v in true)
    norm = math.hypot(fx0, fy0)
    direction = np.array([fx0, fy0]) / norm if norm > 0 else np.array([1.0, 0.0])
    s_grid = np.linspace(*s_range, S)
    f_grid = np.linspace(*magnitude_range, F)
    ss, ff = np.meshgrid(s_grid, f_grid)  # (F, S)
    s_all = np.concatenate(([s0], ss.ravel()))
    f_all = np.concatenate(([[fx0, fy0]], ff.ravel()[:, None] * direction[None, :]))
    loads = PointForces(torch.from_numpy(s_all).view(-1, 1), torch.from_numpy(f_all).view(-1, 1, 2))
    with torch.no_grad():
        sim = simulate(rod, loads, samples=samples)
        shp = rod_shape(sim.s, sim.full_curvature)
    u = sim.grating_curvature.numpy()
    p = shp.position.numpy()
    curvature_loss = ((u[1:] - u[:1]) ** 2).sum((1, 2)).reshape(F, S)
    shape_loss = ((p[1:] - p[:1]) ** 2).sum((1, 2)).reshape(F, S)
    return LossMaps(
        s=s_grid,
        magnitude=f_grid,
        curvature_loss=curvature_loss,
        shape_loss=shape_loss,
        true=np.array([s0, fx0, fy0]),
        direction=direction,
        samples=sim.s.numpy(),
    )


# ================================================================================================ the experiments
@dataclass(frozen=True)
class Timed:
    """One estimate and its cost.

    Attributes:
        forces: (h, 3) rows (s [m] reported, f_x [N], f_y [N]) sorted by s.
        wall: wall-clock seconds; cpu: process CPU seconds.
    """

    forces: np.ndarray
    wall: float
    cpu: float


def _timed(call, *args, **kwargs) -> tuple[Any, float, float]:
    """``call(*args, **kwargs)``, its wall-clock and process CPU seconds."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = call(*args, **kwargs)
    return out, time.perf_counter() - w0, time.process_time() - c0


def _torchrod_rows(result) -> np.ndarray:
    rows = np.array(result.forces.to_lists()[0], dtype=np.float64).reshape(-1, 3)
    return rows[np.argsort(rows[:, 0], kind="stable")]


def _median(values: Sequence[float]) -> float:
    return float(np.median(values)) if len(values) else math.nan


BASELINES = ("bvp_lm", "bvp_dp", "nodes")
"""The paper's three methods, as names of :func:`make_model`."""


def make_model(name: str, rod: Rod, nodes: int) -> CurvatureModel:
    """The inner model ``"bvp_lm"``, ``"bvp_dp"`` or ``"nodes"`` (:data:`BASELINES`) at q = ``nodes``."""
    if name == "nodes":
        return NodeModel(rod, nodes)
    if name in ("bvp_lm", "bvp_dp"):
        return BVPModel(rod, nodes, "fd" if name == "bvp_lm" else "dp")
    raise OptionsError(f"unknown baseline {name!r}; known: {BASELINES}")


@dataclass(frozen=True)
class SpeedTable:
    """The paper's Table II measured here: single-force estimation per method and node count.

    Attributes:
        nodes: the node counts q.
        baselines: method -> q -> one :class:`Timed` per reading (the same readings for all).
        torchrod: one :class:`Timed` per reading, one reading per call (B = 1).
        torchrod_batched: wall seconds per reading when ``batch_size`` readings are estimated in one call.
        failures: method -> q -> inner solves that did not converge (BVP only).
        batch_size: the readings of the batched call.
        rod, readings: what was estimated (for :meth:`exact_losses`).
    """

    nodes: tuple[int, ...]
    baselines: dict[str, dict[int, list[Timed]]]
    torchrod: list[Timed]
    torchrod_batched: float
    failures: dict[str, dict[int, int]]
    batch_size: int = 1
    rod: Rod | None = None
    readings: Readings | None = None

    def median(self, method: str, q: int | None = None, what: str = "wall") -> float:
        """Median seconds per estimate of ``method`` (a baseline at ``q``, or ``"torchrod"``)."""
        runs = self.torchrod if method == "torchrod" else self.baselines[method][cast(int, q)]  # a baseline has a q
        return _median([getattr(r, what) for r in runs])

    def speedup(self, method: str, q: int, what: str = "wall", batched: bool = False) -> float:
        """Median time of ``method`` at ``q`` over torchrod's (B = 1, or per reading batched)."""
        mine = self.torchrod_batched if batched else self.median("torchrod", what=what)
        return self.median(method, q, what) / mine

    def estimates(self, method: str, q: int | None = None) -> list[np.ndarray]:
        runs = self.torchrod if method == "torchrod" else self.baselines[method][cast(int, q)]  # a baseline has a q
        return [r.forces for r in runs]

    def gaps(self, a: str, b: str, q: int) -> tuple[np.ndarray, np.ndarray]:
        """Per reading, the largest |s_a - s_b| [m] and |f_a - f_b| [N] (vector difference) over paired forces of
        methods ``a`` and ``b`` (baselines at ``q``, or ``"torchrod"``)."""
        ds, df = [], []
        for x, y in zip(self.estimates(a, q), self.estimates(b, q), strict=False):
            pairs = match_forces(x, y)
            ds.append(max((abs(x[i, 0] - y[j, 0]) for i, j in pairs), default=0.0))
            df.append(max((math.hypot(x[i, 1] - y[j, 1], x[i, 2] - y[j, 2]) for i, j in pairs), default=0.0))
        return np.array(ds), np.array(df)

    def agreement(self, a: str, b: str, q: int) -> tuple[float, float]:
        """Largest |s_a - s_b| [m] and |f_a - f_b| [N] over the readings (:meth:`gaps`)."""
        ds, df = self.gaps(a, b, q)
        return float(ds.max(initial=0.0)), float(df.max(initial=0.0))

    def exact_losses(self, method: str, q: int | None = None) -> np.ndarray:
        """(N,) each estimate's curvature loss [1/m^2] under the exact point-load model (:func:`exact_loss`)."""
        if self.rod is None or self.readings is None:
            raise OptionsError("this table does not hold its rod and readings")
        rd = self.readings
        return np.array(
            [exact_loss(self.rod, rd.curvature[i], x, rd.mask[i]) for i, x in enumerate(self.estimates(method, q))]
        )


def speed_table(
    rod: Rod,
    readings: Readings,
    estimator,
    *,
    nodes: Sequence[int] = (50, 100, 150, 200),
    methods: Sequence[str] = BASELINES,
    options: FitOptions = FitOptions(),
    batch: Readings | None = None,
    progress=None,
) -> SpeedTable:
    """Single-force estimation time of the paper's three methods (shared outer optimiser, :func:`paper_estimate`
    with one force) at each q, and of ``estimator`` (a :class:`torchrod.estimate.estimator.Estimator`, which should fit
    one force: ``num_forces=1``), on the same ``readings``, one reading per call; and torchrod's time per reading when
    ``batch`` (default: ``readings``) is estimated in one call.

    Every method gets an untimed warm-up on reading 0 except the BVP ones (no caches to fill, and slow).
    ``progress(text)`` is called before each (method, q) block.
    """
    grid = GridStarts(rod)
    N = len(readings)
    curv, mask = readings.curvature, readings.mask
    baselines: dict[str, dict[int, list[Timed]]] = {m: {} for m in methods}
    failures: dict[str, dict[int, int]] = {m: {} for m in methods}
    for q in nodes:
        for name in methods:
            if progress:
                progress(f"{name} q={q}")
            model = make_model(name, rod, q)
            if name == "nodes":
                paper_estimate(model, curv[0], mask=mask[0], num_forces=1, grid=grid, options=options)
            runs = []
            for i in range(N):
                est, wall, cpu = _timed(
                    paper_estimate, model, curv[i], mask=mask[i], num_forces=1, grid=grid, options=options
                )
                runs.append(Timed(est.fit.forces, wall, cpu))
            baselines[name][q] = runs
            failures[name][q] = getattr(model, "failures", 0)
    if progress:
        progress("torchrod")
    estimator.estimate(curv[:1], mask[:1])  # warm-up
    mine = []
    for i in range(N):
        res, wall, cpu = _timed(estimator.estimate, curv[i : i + 1], mask[i : i + 1])
        mine.append(Timed(_torchrod_rows(res), wall, cpu))
    batch = readings if batch is None else batch
    _, wall, _ = _timed(estimator.estimate, batch.curvature, batch.mask)
    return SpeedTable(tuple(nodes), baselines, mine, wall / len(batch), failures, len(batch), rod, readings)


@dataclass(frozen=True)
class MethodRun:
    """One method on one set of readings: estimates (per reading (m, 3), reported) and times [s]."""

    estimates: list[np.ndarray]
    wall: list[float]
    cpu: list[float]

    @property
    def median_wall(self) -> float:
        return _median(self.wall)


@dataclass(frozen=True)
class AccuracyStudy:
    """The accuracy study (module docstring) for several force counts.

    Attributes:
        readings: k -> :class:`Readings` with k forces each.
        runs: label -> k -> :class:`MethodRun`. Labels: ``"torchrod"`` (count chosen automatically),
            ``"torchrod known"`` (count given), ``"nodes q=Q"`` (the paper's method at q = Q, count given) and
            ``"nodes q=Q threshold"`` (its count rule, at the paper's q).
        nodes: the node counts of the paper's method.
    """

    readings: dict[int, Readings]
    runs: dict[str, dict[int, MethodRun]]
    nodes: tuple[int, ...]

    def accuracy(self, label: str, k: int) -> Accuracy:
        rd = self.readings[k]
        return accuracy([rd.truth(i) for i in range(len(rd))], self.runs[label][k].estimates)


def accuracy_study(
    rod: Rod,
    readings: dict[int, Readings],
    estimator,
    *,
    nodes: Sequence[int] = (50, 90, 150, PAPER_NODES),
    threshold_nodes: int | None = PAPER_NODES,
    threshold: float = PAPER_THRESHOLD,
    options: FitOptions = FitOptions(),
    progress=None,
) -> AccuracyStudy:
    """Run torchrod's ``estimator`` (count automatic, and given) and the paper's method (node scheme with the shared
    outer optimiser, count given, at every q of ``nodes``; with its threshold rule at ``threshold_nodes``) on the
    same readings, one reading per call, timing each estimate."""
    grid = GridStarts(rod)
    runs: dict[str, dict[int, MethodRun]] = {}

    def record(label: str, k: int, call, **kwargs) -> None:
        """Run ``call(curvature (G, 2), mask (G,), **kwargs) -> rows`` on every reading with k forces."""
        est, wall, cpu = [], [], []
        rd = readings[k]
        for i in range(len(rd)):
            rows, w, c = _timed(call, rd.curvature[i], rd.mask[i], **kwargs)
            est.append(rows)
            wall.append(w)
            cpu.append(c)
        runs.setdefault(label, {})[k] = MethodRun(est, wall, cpu)

    def mine(u: torch.Tensor, m: torch.Tensor, **overrides) -> np.ndarray:
        opts = dataclasses.replace(estimator.options, **overrides) if overrides else None
        return _torchrod_rows(estimator.estimate(u[None], m[None], options=opts))

    def theirs(u: torch.Tensor, m: torch.Tensor, model: CurvatureModel, **kwargs) -> np.ndarray:
        return paper_estimate(model, u, mask=m, grid=grid, options=options, **kwargs).fit.forces

    first = next(iter(readings.values()))
    estimator.estimate(first.curvature[:1], first.mask[:1])  # warm-up
    for k in readings:
        if progress:
            progress(f"torchrod, {k} force(s)")
        record("torchrod", k, mine)
        record("torchrod known", k, mine, num_forces=k)
        for q in nodes:
            if progress:
                progress(f"nodes q={q}, {k} force(s)")
            model = NodeModel(rod, q)
            paper_estimate(model, first.curvature[0], mask=first.mask[0], num_forces=1, grid=grid)  # warm-up
            record(f"nodes q={q}", k, theirs, model=model, num_forces=k)
            if q == threshold_nodes:
                record(
                    f"nodes q={q} threshold",
                    k,
                    theirs,
                    model=model,
                    max_forces=max(readings),
                    threshold=threshold,
                )
    return AccuracyStudy(dict(readings), runs, tuple(nodes))
