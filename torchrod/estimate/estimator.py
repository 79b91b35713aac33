"""Estimating the contact forces from FBG curvature readings: starts, batched refinement, count selection.

For every reading and every candidate count h (1..max_forces, or the fixed ``num_forces``) the estimator

1. proposes starting points: the grid scan of :mod:`torchrod.starts` (small-deflection linear least squares over
   location sets, ``starts`` per count), plus caller-supplied guesses (``extra_starts``: a network's guess, the
   previous frame's solution) and, when a ``warm_start`` is attached, its guesses;
2. refines ALL (reading, count, start) rows together with ONE call of the batched L-BFGS of
   :mod:`torchrod.refine` (strong-Wolfe line search, per-row history, step and stopping), each row minimising its
   own loss ``sum over present gratings of |u_model - u_measured|^2`` [1/m^2] (float64; missing gratings are left
   out of the sum, never zeroed). Rows with fewer forces than the widest count carry padded, masked forces whose
   unknowns never move. Before it, ``polish`` (default 12) batched Levenberg-Marquardt steps move every start
   towards its optimum (see below): L-BFGS finishes the rows they leave open;
3. keeps the best start of each count and chooses the count (:mod:`torchrod.selection`);
4. attaches the Gauss-Newton uncertainty (:mod:`torchrod.uncertainty`) and reports locations as
   ``s_model + rod.location_bias``, sorted by s.

Parameterisation. Each force is (z, phi_x, phi_y) with ``s = L (1 + sin z) / 2`` and ``f = phi EI / L^2``: s in
units of L, f in units of EI / L^2, the scales at which the rod's curvature is of order 1/L. The sine keeps s in
[0, L] without bounds or projection, which matters for L-BFGS: a projected step breaks the curvature pairs (the
step taken is not the one the pair records), whereas under the sine map every iterate is feasible and the pairs
are exact. A contact at the tip s = L (common: the tip touches first) is reached at a finite z = pi/2, where
ds/dz = 0 and d^2 s/dz^2 = -L/2: when the unconstrained optimum lies beyond the tip, the loss in z has a regular,
strictly convex minimum at pi/2 instead of a kink at a bound, so L-BFGS converges to it at its usual rate. (A
logistic map would push z to infinity instead.) Starts are kept a little inside (0, L) so ds/dz != 0 there.

The Levenberg-Marquardt polish (``polish`` steps, default 12). The loss is a sum of squares whose Jacobian the sensitivity pass gives for
free, so Gauss-Newton steps converge in a few evaluations where L-BFGS must first learn the curvature; and the
loss has kinks: grating k sees a force only while it lies distal to k, so the residual's derivative in s_i jumps
where s_i crosses s_k, and a least-squares optimum often sits exactly on such a kink (no gradient vanishes there;
smooth optimisers zig-zag across it). The polish handles kinks explicitly (:meth:`_Problem.kinks`): a step that
would carry a force across a grating is also tried cut where the force lands on it (the better of the two
trials is kept); a force on a grating stays there while the others converge, and leaves it only if the loss falls
off the kink on one side. Measured on 60 readings per count at sigma = 0.1 1/m, ``polish=12`` reaches the same
counts and losses as plain L-BFGS (``polish=0``; count right 100 / 96.7 / 90.0 % for 1 / 2 / 3 forces either way) in
0.65-0.95 of the time and flags more rows converged (kinks stop L-BFGS's gradient test, not the polish's decrement
test); on the 10,000-reading stream benchmark it is 2-3x faster (300 -> 930 readings/s batched, 43 -> 19 ms one at a
time).

L-BFGS. The rows still open are whitened with the Gauss-Newton matrix at their start (or polished) point:
``v = v0 + alpha C^-T y`` with ``C C^T = J0^T J0`` (Cholesky, lightly damped: 1e-3 of its diagonal). L-BFGS then
sees a problem whose Hessian is about the identity near the start, and its first step, ``min(1, 1/|g|_1)`` times
the gradient, is exactly the Gauss-Newton step when ``alpha = max(|g~|_1, 1)`` and the loss is scaled by
``1 / alpha^2`` (g~ the whitened gradient). Forces pinned on a kink keep their location. The loss and its gradient
come from one sensitivity pass (gradient ``J^T r``), fed to autograd as a linear term, so that
:func:`torchrod.refine.lbfgs` (which differentiates ``loss.sum()``) needs no backward pass through the integrator.

A few readings per call (at most ``scalar_readings``, default 4, on the CPU). Batched, the polish costs torch's
per-operation dispatch: at one reading per call that is ~8 ms for a ~1 ms problem. Such calls fit each reading on
Python floats instead (:mod:`torchrod.scalar_fit`: the same unknowns, forward model, Levenberg-Marquardt step,
trust region and stopping rule), trying its starts in turn (guesses first; for one force it stops at a final fit
the count accepts, for more forces it fits every start, as the batched path does); larger counts are left at their first start once the count
is decided whatever they would reach (:func:`torchrod.selection.choose_count` on the current losses and on the
Gauss-Newton predictions). A reading whose chosen fit is not final (unconverged, or on a kink) or worse than noise
explains (above the chi-square 95 % quantile) is handed to the batched path. Measured at B = 1 (one force, count
given, network start): 2.1 ms against 14 ms batched; the two paths reach the same optimum on nearly every reading
(tests/test_estimator.py).

Stopping. A row has converged when the Gauss-Newton decrement (the loss decrease a Gauss-Newton step promises) is
at most ``decrement_tolerance`` x sigma^2: what is left to gain is far below the noise. With known sigma (or the
threshold rule) a reading is also *settled* as soon as its count is decided whatever its still-running fits do
(:meth:`_Problem.settled`), and its rows stop: fits of larger counts than the chosen one need not converge. In
L-BFGS both stops are reported as a zero gradient, which ends the row through the gradient test. A row's result
depends only on its own data: the integrator's steps are chosen per row.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from ..io.readings import check_readings
from ..loads import PointForces
from ..model.sensitivity import ESTIMATION_STEP_ANGLE, curvature_and_jacobian
from ..rod import Rod
from .refine import LBFGSOptions, RefineResult, lbfgs
from .selection import RULES, choose_count, count_limits, misfit_limit, noise_quantile, select_count
from .starts import GridStarts
from .uncertainty import CONDITION_LIMIT, force_uncertainty

__all__ = ["DEFAULT_LBFGS", "EstimateResult", "Estimator", "EstimatorOptions"]

DEFAULT_LBFGS = LBFGSOptions(
    max_iter=30, history_size=10, lr=1.0, tolerance_grad=1e-9, tolerance_change=1e-12
)
"""Refinement settings. Losses are whitened and scaled (module docstring): the gradient tolerance is on the
whitened gradient divided by alpha (at most its starting 1-norm), i.e. the distance to the optimum in 1/m of
curvature residual, relative to the start's when that exceeds 1."""

_EDGE = 0.005  # starts are kept in [_EDGE L, (1 - _EDGE) L]
_DAMPING = 1e-3  # relative damping of the whitening matrix
_MAX_DPHI = 10.0  # largest force change per polish step, in units of EI / L^2
_MAX_DZ = 0.5  # largest change of z per polish step [rad]
_MAX_STEPS = 12  # cap on integrator steps per segment while fitting (far-off trial points need no accuracy)
_GROUP_ROWS = 256  # rows from which a residual evaluation marches each force count separately
_SUSPECT = 0.95
_KINK = 1e-5  # [m] a location this close to a grating sits on the loss's kink (see _Problem.decrement)


@dataclass(frozen=True)
class EstimatorOptions:
    """Settings of :class:`Estimator` (all can be overridden per call of :meth:`Estimator.estimate`).

    Attributes:
        max_forces: the largest count considered; counts 1..max_forces are fitted and one is chosen.
        num_forces: a fixed count instead (only that count is fitted); the result then holds num_forces slots.
        noise: sensor sigma per curvature component [1/m]; None: estimated per reading (selection F test).
        selection: ``"noise"`` (significance test, default) or ``"threshold"`` (the paper's rule).
        threshold: the paper's loss threshold [1/m^2] for ``selection="threshold"``.
        significance: alpha of the count tests, before the Bonferroni factor G (:mod:`torchrod.selection`).
        noise_floor: [1/m] added in quadrature to sigma: the forward model's accuracy (so a noise-free reading
            is not held to a loss of exactly zero).
        lbfgs: refinement settings (:class:`torchrod.refine.LBFGSOptions`).
        starts: grid starts per count (the best distinct candidates of the scan); 0 skips the scan, which needs
            other starts for every count (a warm-start network, ``extra_starts``).
        grid_step, start_separation: grid spacing and least separation of the scan [m] (None: from the gratings,
            see :class:`torchrod.starts.GridStarts`).
        max_step_angle: accuracy of the forward model used for fitting (:mod:`torchrod.sensitivity`).
        condition_limit: ``poorly_determined`` above this condition number (:mod:`torchrod.uncertainty`).
        decrement_tolerance: a fit stops when a Gauss-Newton step would lower its loss by less than this times
            sigma^2 (sigma: the given noise with the floor, else the fit's own loss / degrees of freedom, floored).
        polish: Levenberg-Marquardt steps applied to every start before the L-BFGS refinement (0: plain L-BFGS,
            same accuracy, 2-3x slower; see the module docstring).
        scalar_readings: calls with at most this many readings on the CPU fit each reading on Python floats
            (:mod:`torchrod.scalar_fit`: the same iteration without torch's per-operation cost; a reading it
            cannot finish goes to the batched path); 0: always the batched path. Needs ``polish`` > 0. Measured
            per reading (1-3 forces, count automatic, network starts): 13.4 against 17.5 ms at 1 reading per
            call, 12.3 against 16.0 at 2, 11.1 against 10.8 at 4, 9.8 against 8.7 at 8.
    """

    max_forces: int = 3
    num_forces: int | None = None
    noise: float | None = None
    selection: str = "noise"
    threshold: float = 3.0
    significance: float = 0.05
    noise_floor: float = 0.01
    lbfgs: LBFGSOptions = DEFAULT_LBFGS
    starts: int = 2
    grid_step: float | None = None
    start_separation: float | None = None
    max_step_angle: float = ESTIMATION_STEP_ANGLE
    condition_limit: float = CONDITION_LIMIT
    decrement_tolerance: float = 1e-4
    polish: int = 12
    scalar_readings: int = 4

    def __post_init__(self) -> None:
        def integer(name: str, low: int) -> None:
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")

        integer("max_forces", 1)
        integer("starts", 0)
        integer("polish", 0)
        integer("scalar_readings", 0)
        if self.num_forces is not None:
            integer("num_forces", 1)
        if self.noise is not None and not (math.isfinite(float(self.noise)) and float(self.noise) >= 0.0):
            raise ValueError(f"noise must be None or a finite sigma >= 0 [1/m], got {self.noise!r}")
        if self.selection not in RULES:
            raise ValueError(f"selection must be one of {RULES}, got {self.selection!r}")
        if not (math.isfinite(float(self.threshold)) and float(self.threshold) > 0.0):
            raise ValueError(f"threshold must be positive [1/m^2], got {self.threshold!r}")
        if not 0.0 < float(self.significance) < 1.0:
            raise ValueError(f"significance must lie in (0, 1), got {self.significance!r}")
        if not (math.isfinite(float(self.noise_floor)) and float(self.noise_floor) >= 0.0):
            raise ValueError(f"noise_floor must be >= 0 [1/m], got {self.noise_floor!r}")
        if not isinstance(self.lbfgs, LBFGSOptions):
            raise TypeError(f"lbfgs must be LBFGSOptions, got {type(self.lbfgs).__name__}")
        if not (float(self.max_step_angle) > 0.0):
            raise ValueError(f"max_step_angle must be positive, got {self.max_step_angle!r}")
        if not (float(self.condition_limit) > 1.0):
            raise ValueError(f"condition_limit must exceed 1, got {self.condition_limit!r}")

    @property
    def counts(self) -> list[int]:
        """The counts fitted: [num_forces], or 1..max_forces."""
        return [self.num_forces] if self.num_forces is not None else list(range(1, self.max_forces + 1))

    @property
    def width(self) -> int:
        """Force slots in a result: num_forces if fixed, else max_forces."""
        return self.num_forces if self.num_forces is not None else self.max_forces


@dataclass(frozen=True)
class EstimateResult:
    """Estimates for B readings, batch first (W = the options' ``width``: max_forces, or num_forces if fixed).

    Attributes:
        forces: (B, W) forces sorted by location, padding (mask False) last; s REPORTED = s_model +
            rod.location_bias [m], f body-frame (f_x, f_y) [N].
        num_forces: (B,) long, the chosen count.
        loss: (B,) loss of the chosen fit: sum over present gratings of squared residuals [1/m^2].
        converged: (B,) bool, the chosen fit's refinement stopped on a tolerance.
        iterations: (B,) long, Levenberg-Marquardt polish steps plus L-BFGS iterations of the chosen fit;
            evaluations: (B,) long, its forward-model evaluations (polish steps plus L-BFGS evaluations).
        std: (B, W, 3) standard deviations of (s [m], f_x [N], f_y [N]); NaN for padding.
        poorly_determined: (B,) bool (:mod:`torchrod.uncertainty`).
        losses_by_count: (B, W) best loss of each count h = 1..W [1/m^2]; NaN where h was not fitted.
        noise: (B,) sigma used for the selection and the covariance [1/m].
    """

    forces: PointForces
    num_forces: torch.Tensor
    loss: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    std: torch.Tensor
    poorly_determined: torch.Tensor
    losses_by_count: torch.Tensor
    noise: torch.Tensor
    evaluations: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.num_forces.shape[0]

    def __len__(self) -> int:
        return self.batch_size

    def __getitem__(self, index: int | slice | torch.Tensor) -> EstimateResult:
        """Select readings along the batch dimension (an int keeps a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        fields = {
            f.name: getattr(self, f.name)[index]
            for f in dataclasses.fields(self)
            if getattr(self, f.name) is not None
        }
        return EstimateResult(**fields)

    def to_records(self, ids: Sequence[Any] | None = None) -> list[dict[str, Any]]:
        """One JSON-ready dict per reading (the ``torchrod estimate`` output, without ``time_ms``).

        ``{"id", "num_forces", "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"}, ...] sorted
        by s, "loss", "converged", "iterations", "poorly_determined"}``; SI units; a non-finite number is null.
        ``ids`` default to the batch index.
        """
        B = self.batch_size
        if ids is None:
            ids = list(range(B))
        elif len(ids) != B:
            raise ValueError(f"ids must hold {B} entries, got {len(ids)}")

        def num(x: float) -> float | None:
            return x if math.isfinite(x) else None

        s = self.forces.s.detach().cpu().tolist()
        f = self.forces.f.detach().cpu().tolist()
        active = self.forces.active.cpu().tolist()
        std = self.std.detach().cpu().tolist()
        n = self.num_forces.cpu().tolist()
        loss = self.loss.detach().cpu().tolist()
        conv = self.converged.cpu().tolist()
        it = self.iterations.cpu().tolist()
        poor = self.poorly_determined.cpu().tolist()
        out = []
        for b in range(B):
            forces = []
            for j in range(len(s[b])):
                if not active[b][j]:
                    continue
                fx, fy = f[b][j]
                forces.append(
                    {
                        "s": num(s[b][j]),
                        "fx": num(fx),
                        "fy": num(fy),
                        "magnitude": num(math.hypot(fx, fy)),
                        "std_s": num(std[b][j][0]),
                        "std_fx": num(std[b][j][1]),
                        "std_fy": num(std[b][j][2]),
                    }
                )
            out.append(
                {
                    "id": ids[b],
                    "num_forces": int(n[b]),
                    "forces": forces,
                    "loss": num(loss[b]),
                    "converged": bool(conv[b]),
                    "iterations": int(it[b]),
                    "poorly_determined": bool(poor[b]),
                }
            )
        return out


WarmStartLike = Callable[[torch.Tensor, torch.Tensor], Mapping[int, PointForces]]


class Estimator:
    """Force estimation for one rod (module docstring: the method).

    Args:
        rod: the rod (length, EI, gratings, location bias).
        options: :class:`EstimatorOptions`.
        warm_start: optional source of extra starts, in MODEL coordinates (no location bias): an object with a
            ``guess(curvature, mask)`` method returning something with a ``forces`` dict {h: PointForces (B, h)}
            (e.g. :class:`torchrod.warm_start.WarmStart`), or a callable ``(curvature, mask) -> {h: PointForces}``.
    """

    def __init__(
        self, rod: Rod, options: EstimatorOptions = EstimatorOptions(), warm_start: Any = None
    ) -> None:
        if not isinstance(rod, Rod):
            raise TypeError(f"rod must be a Rod, got {type(rod).__name__}")
        if not isinstance(options, EstimatorOptions):
            raise TypeError(f"options must be EstimatorOptions, got {type(options).__name__}")
        if warm_start is not None and not (hasattr(warm_start, "guess") or callable(warm_start)):
            raise TypeError(
                f"warm_start must have a guess() method or be callable, got {type(warm_start).__name__}"
            )
        self.rod = rod
        self.options = options
        self.warm_start = warm_start
        self._grids: dict[tuple, GridStarts] = {}

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        rod: Rod,
        options: EstimatorOptions | None = None,
        *,
        warn: Callable[[str], None] | None = None,
    ) -> Estimator:
        """An estimator whose starts come from a trained warm-start network.

        The network is used when its grating layout (positions relative to the length) matches ``rod``'s; then
        the grid scan is skipped (``starts=0``) unless ``options`` say otherwise. When the layout does not match
        (or the file is missing), the estimator falls back to the start that needs no network and says so once
        through ``warn`` (default: a :class:`UserWarning`).

        Args:
            path: a checkpoint written by :mod:`torchrod.training` (loaded with ``weights_only=True``).
            rod: the rod to estimate on.
            options: estimator settings; default ``EstimatorOptions(starts=0)`` with the network, else the defaults.
        """
        from ..learn.warm_start import WarmStart

        try:
            ws = WarmStart.load(path, rod)
        except (ValueError, FileNotFoundError) as exc:
            message = (
                f"torchrod: not using the warm-start network ({exc}); starting from the grid scan instead"
            )
            if warn is None:
                warnings.warn(message, UserWarning, stacklevel=2)
            else:
                warn(message)
            return cls(rod, options if options is not None else EstimatorOptions())
        return cls(rod, options if options is not None else EstimatorOptions(starts=0), warm_start=ws)

    def stream(self, readings: Any, options: Any = None, **overrides: Any) -> Any:
        """Estimate a stream of readings in order, in latency-bounded batches (:func:`torchrod.stream.stream`).

        Args:
            readings: any iterable of :class:`torchrod.stream.Reading` (or dicts with ``id``, ``curvature``,
                optional ``t``).
            options: :class:`torchrod.stream.StreamOptions` (batch size, latency bound).
            **overrides: :class:`EstimatorOptions` fields for every batch.
        Yields:
            one :class:`torchrod.stream.StreamResult` per reading, in input order.
        """
        from ..io.stream import StreamOptions, stream

        return stream(self, readings, options if options is not None else StreamOptions(), **overrides)

    def _grid(self, options: EstimatorOptions, dtype: torch.dtype, device: torch.device) -> GridStarts:
        key = (options.grid_step, options.start_separation, dtype, device)
        grid = self._grids.get(key)
        if grid is None:
            grid = GridStarts(
                self.rod,
                step=options.grid_step,
                separation=options.start_separation,
                dtype=dtype,
                device=device,
            )
            self._grids[key] = grid
        return grid

    # ------------------------------------------------------------------ input checks
    def _check(self, curvature: Any, mask: Any) -> tuple[torch.Tensor, torch.Tensor]:
        curvature, mask = check_readings(curvature, mask, self.rod.num_gratings)
        if curvature.shape[0] == 0:
            raise ValueError(f"curvature must hold at least one reading, got shape {tuple(curvature.shape)}")
        empty = ~mask.any(dim=1)
        if bool(empty.any()):
            rows = empty.nonzero().squeeze(1).tolist()
            raise ValueError(f"readings {rows[:10]} have no present grating (mask all False)")
        return curvature, mask

    # ------------------------------------------------------------------ the method
    def estimate(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor | None = None,
        *,
        extra_starts: Mapping[int, PointForces] | None = None,
        **overrides: Any,
    ) -> EstimateResult:
        """Estimate the forces behind B readings.

        Args:
            curvature: (B, G, 2) measured (u_x, u_y) at the rod's gratings [1/m]; values at missing gratings are
                ignored (may be NaN).
            mask: (B, G) bool, True where the grating was read; None: the finite entries.
            extra_starts: {h: PointForces (B, h)} additional starting guesses in REPORTED coordinates (as in
                :attr:`EstimateResult.forces`, so a previous solution can be passed as is); rows whose mask is
                False are ignored; counts that are not fitted are ignored.
            **overrides: any :class:`EstimatorOptions` field for this call.
        Returns:
            :class:`EstimateResult` in ``curvature``'s dtype and device (computed in float64).
        """
        opts = dataclasses.replace(self.options, **overrides) if overrides else self.options
        curvature, mask = self._check(curvature, mask)
        device, dtype = curvature.device, torch.float64
        B = curvature.shape[0]
        u_meas = torch.where(
            mask.unsqueeze(-1), curvature.to(dtype), torch.zeros((), dtype=dtype, device=device)
        )
        guesses = self._guesses(curvature, mask, opts, extra_starts)
        if opts.polish > 0 and device.type == "cpu" and B <= opts.scalar_readings:
            return self._estimate_small(curvature, mask, u_meas, opts, guesses)
        return self._estimate_batched(curvature, mask, u_meas, opts, guesses)

    def _guesses(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        extra_starts: Mapping[int, PointForces] | None,
    ) -> dict[int, list[PointForces]]:
        """The starts other than the grid scan, per fitted count, in model coordinates: the caller's
        ``extra_starts`` (location bias removed), then the warm start's guesses."""
        B = curvature.shape[0]
        guesses: dict[int, list[PointForces]] = {h: [] for h in opts.counts}
        if extra_starts:
            for h, pf in extra_starts.items():
                if h in guesses:
                    guesses[h].append(self._check_guess(pf, B, h, shift=-self.rod.location_bias))
        if self.warm_start is not None:
            if hasattr(self.warm_start, "guess"):
                net = self.warm_start.guess(curvature, mask)
            else:
                net = self.warm_start(curvature, mask)
            for h, pf in (net.forces if hasattr(net, "forces") else net).items():
                if h in guesses:
                    guesses[h].append(self._check_guess(pf, B, h, shift=0.0))
        for h in opts.counts:
            if opts.starts == 0 and not guesses[h]:
                raise ValueError(
                    f"starts=0 skips the grid scan, but no other start was given for h = {h} "
                    "(attach a warm start or pass extra_starts for every count)"
                )
        return guesses

    def _estimate_batched(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        u_meas: torch.Tensor,
        opts: EstimatorOptions,
        guesses: dict[int, list[PointForces]],
    ) -> EstimateResult:
        """All readings' (count, start) rows at once: polish, L-BFGS, best start, count, report."""
        out_dtype, device = curvature.dtype, curvature.device
        dtype = torch.float64
        rod = self.rod
        B = curvature.shape[0]
        counts, H = opts.counts, opts.width

        # ---- starts: (s, f) per count, in model coordinates, (B, S_h, h)
        grid = self._grid(opts, dtype, device)
        row_s, row_f, row_h = [], [], []
        for h in counts:
            if opts.starts > 0:
                st = grid(u_meas, mask, h, opts.starts)
                s_h, f_h = st.s, st.f  # (B, S, h), (B, S, h, 2)
            else:
                s_h = u_meas.new_empty(B, 0, h)
                f_h = u_meas.new_empty(B, 0, h, 2)
            for pf in guesses[h]:
                ok = (pf.active & torch.isfinite(pf.s) & torch.isfinite(pf.f).all(-1)).all(dim=1).view(B, 1)
                # A guess that is unusable for a row falls back to that row's first start (or, with no scan,
                # to the first guess: the network's, which is always finite).
                base_s = s_h[:, 0] if s_h.shape[1] else pf.s.to(dtype).nan_to_num(0.5 * rod.length)
                base_f = f_h[:, 0] if f_h.shape[1] else pf.f.to(dtype).nan_to_num(0.0)
                s_h = torch.cat((s_h, torch.where(ok, pf.s.to(dtype), base_s).unsqueeze(1)), dim=1)
                f_h = torch.cat(
                    (f_h, torch.where(ok.unsqueeze(-1), pf.f.to(dtype), base_f).unsqueeze(1)), dim=1
                )
            S = s_h.shape[1]
            s_rows = s_h.transpose(0, 1).reshape(S * B, h)
            f_rows = f_h.transpose(0, 1).reshape(S * B, h, 2)
            row_s.append(torch.cat((s_rows, s_rows.new_zeros(S * B, H - h)), dim=1))
            row_f.append(torch.cat((f_rows, f_rows.new_zeros(S * B, H - h, 2)), dim=1))
            row_h.append(torch.full((S * B,), h, dtype=torch.long, device=device))
        row_count = torch.cat(row_h)
        reading = torch.arange(B, device=device).repeat(row_count.shape[0] // B)
        problem = _Problem(rod, opts, u_meas, mask, reading, row_count, counts, H)
        v0 = problem.to_unknowns(torch.cat(row_s), torch.cat(row_f))

        # ---- Levenberg-Marquardt polish of the starts, then one batched L-BFGS over every row
        v1, polish_iterations = problem.polish(v0, opts.polish)
        res = problem.refine(v1)
        v_star = res.x
        row_loss = res.loss

        # ---- best start per (reading, count), then the count. Among starts whose losses differ by less than
        # what the stopping rule ignores, a converged one is preferred (others may have been stopped early).
        C_ = len(counts)
        best_loss = torch.full((B, C_), float("inf"), dtype=dtype, device=device)
        best_row = torch.zeros(B, C_, dtype=torch.long, device=device)
        slack = (
            10.0
            * opts.decrement_tolerance
            * problem.sigma2(
                torch.nan_to_num(row_loss, posinf=0.0).sqrt().unsqueeze(1),
                torch.arange(row_loss.shape[0], device=device),
            )
        )
        key = row_loss - slack * problem.cur_done.to(dtype)
        for ci, h in enumerate(counts):
            rows_h = (row_count == h).nonzero().squeeze(1).view(-1, B)  # (S, B)
            lh = row_loss[rows_h]
            j = key[rows_h].argmin(dim=0)
            best_loss[:, ci] = lh.gather(0, j.unsqueeze(0)).squeeze(0)
            best_row[:, ci] = rows_h.gather(0, j.unsqueeze(0)).squeeze(0)
        fit_losses = torch.where(torch.isinf(best_loss), torch.full_like(best_loss, float("nan")), best_loss)
        chosen, sigma = self._select(fit_losses, problem.residual_count, opts)
        ci = torch.searchsorted(torch.tensor(counts, device=device), chosen)
        rows = best_row.gather(1, ci.unsqueeze(1)).squeeze(1)  # (B,)

        # ---- the chosen fits: convergence at the final point, uncertainty, reported form
        r, J = problem.residual(v_star[rows], rows)
        decrement, sigma2_rows = problem.decrement(r, J, rows, v_star[rows])
        s, f, fm = problem.forces(v_star[rows], rows)
        return self._report(
            s,
            f,
            fm,
            mask,
            opts,
            chosen=chosen,
            sigma=sigma,
            loss=r.square().sum(-1),
            converged=decrement <= opts.decrement_tolerance * sigma2_rows,
            iterations=res.iterations[rows] + polish_iterations[rows],
            evaluations=res.evaluations[rows] + polish_iterations[rows],
            fit_losses=fit_losses,
            out_dtype=out_dtype,
        )

    def _estimate_small(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        u_meas: torch.Tensor,
        opts: EstimatorOptions,
        guesses: dict[int, list[PointForces]],
    ) -> EstimateResult:
        """A few readings on the CPU, each fitted on Python floats (:mod:`torchrod.scalar_fit`; the module
        docstring). The readings it hands back (the chosen fit unconverged, on a kink or worse than the noise
        explains, or a count that unfinished fits could still change) take the batched path."""
        from .scalar_fit import Fit, ReadingFit

        rod, B, device = self.rod, curvature.shape[0], curvature.device
        counts, H, C = opts.counts, opts.width, len(opts.counts)
        query = rod.gratings
        sigma2 = None if opts.noise is None else float(opts.noise) ** 2 + float(opts.noise_floor) ** 2
        present = mask.tolist()
        n_res = [2 * sum(p) for p in present]
        rows = u_meas.tolist()
        # Early stop among a count's starts, for one force only (its loss has no competing minima in s): a final fit
        # below the count's misfit limit. With more forces every start is fitted: nearby minima of almost equal loss
        # are common, and stopping at the first acceptable one lost accuracy on the paper's readings (the batched
        # path, which runs all starts, found lower losses on 1-3 of 13). And a reading whose chosen fit is worse
        # than noise explains (above the chi-square quantile _SUSPECT) goes to the batched path (its kink handling
        # finds better minima). Both need the noise.
        if sigma2 is not None:
            limit = [
                [misfit_limit(n, h, opts.significance) * sigma2 if h == 1 else -math.inf for h in counts]
                for n in n_res
            ]
            suspect = [[noise_quantile(n, h, _SUSPECT) * sigma2 for h in counts] for n in n_res]
        else:
            limit = suspect = None
        guess_rows = {
            h: [(pf.s.tolist(), pf.f.tolist(), pf.active.tolist()) for pf in guesses[h]] for h in counts
        }
        grid_rows: dict[int, tuple[list, list]] = {}

        def grid_starts(h: int) -> tuple[list, list]:
            if h not in grid_rows:
                st = self._grid(opts, torch.float64, device)(u_meas, mask, h, opts.starts)
                grid_rows[h] = (st.s.tolist(), st.f.tolist())
            return grid_rows[h]

        def starts_of(b: int, h: int) -> Iterator[tuple[list, list]]:
            """Reading b's starts for h forces: the guesses first (a network's is usually the best), then the
            grid scan's (computed on first need, for all readings at once)."""
            for s_g, f_g, on in guess_rows[h]:
                s_b, f_b = s_g[b], f_g[b]
                if all(on[b]) and all(math.isfinite(x) for x in s_b + [c for p in f_b for c in p]):
                    yield s_b, f_b
                elif opts.starts == 0:  # as the batched path: the unusable guess with NaNs replaced
                    yield (
                        [x if math.isfinite(x) else 0.5 * rod.length for x in s_b],
                        [[x if math.isfinite(x) else 0.0 for x in p] for p in f_b],
                    )
            if opts.starts > 0:
                gs, gf = grid_starts(h)
                yield from zip(gs[b], gf[b])

        def final(fit: Fit) -> bool:
            return fit.converged and not fit.on_kink

        def optimistic(fit: Fit) -> float:
            """The loss, or for an unfinished fit the Gauss-Newton prediction of where it would end."""
            return fit.loss if final(fit) else max(fit.loss - fit.decrement, 0.0)

        decidable = C > 1 and (opts.selection == "threshold" or sigma2 is not None)
        rule = {
            "rule": opts.selection,
            "sigma2": sigma2,
            "threshold": opts.threshold,
            "significance": opts.significance,
            "num_gratings": rod.num_gratings,
        }
        fits = []  # per reading: per count, the kept Fit
        for b in range(B):
            problem = ReadingFit(
                query,
                rod.length,
                rod.bending_stiffness,
                rows[b],
                present[b],
                sigma2=sigma2,
                floor2=float(opts.noise_floor) ** 2,
                tolerance=opts.decrement_tolerance,
                max_step_angle=opts.max_step_angle,
                max_steps=_MAX_STEPS,
                edge=_EDGE,
                max_dphi=_MAX_DPHI,
                max_dz=_MAX_DZ,
                kink=_KINK,
            )
            kept: list[Fit] = []
            at_start: dict[int, Fit] = {}  # larger counts evaluated at their first start only
            for ci, h in enumerate(counts):
                best, best_key = None, math.inf
                for s0, f0 in starts_of(b, h):
                    fit = problem.fit(s0, f0, opts.polish)
                    key = fit.loss - 10.0 * opts.decrement_tolerance * fit.sigma2 * final(fit)
                    if best is None or key < best_key:
                        best, best_key = fit, key
                    if final(fit) and limit is not None and fit.loss <= limit[b][ci]:
                        break
                assert best is not None
                kept.append(best)
                if decidable and ci < C - 1:
                    # Settled already? The larger counts at their first start: if the choice is the same with
                    # their current losses and with the losses they might reach, they need no fitting.
                    for cj in range(ci + 1, C):
                        if cj not in at_start:
                            at_start[cj] = problem.fit(*next(starts_of(b, counts[cj])), 0)
                    trial = kept + [at_start[cj] for cj in range(ci + 1, C)]
                    high = choose_count([x.loss for x in trial], counts, n_res[b], **rule)
                    low = choose_count([optimistic(x) for x in trial], counts, n_res[b], **rule)
                    if high == low and high <= ci and final(trial[high]):
                        kept = trial
                        break
            fits.append(kept)

        # The count, from the kept fits' losses; it must not depend on how far the unfinished fits would still
        # fall (their losses minus decrements as the optimistic bound), and the chosen fit must be final.
        dtype = torch.float64
        upper = torch.tensor([[fit.loss for fit in kept] for kept in fits], dtype=dtype, device=device)
        residual_count = torch.tensor(n_res, device=device)
        chosen, sigma = self._select(upper, residual_count, opts)
        handled = [True] * B
        if C > 1 and not all(final(fit) for kept in fits for fit in kept):
            lower = torch.tensor(
                [[optimistic(fit) for fit in kept] for kept in fits], dtype=dtype, device=device
            )
            handled = (chosen == self._select(lower, residual_count, opts)[0]).tolist()
        chosen_fits = [kept[counts.index(h)] for kept, h in zip(fits, chosen.tolist())]
        handled = [ok and final(fit) for ok, fit in zip(handled, chosen_fits)]
        if suspect is not None:
            handled = [
                ok and fit.loss <= suspect[b][counts.index(h)]
                for b, (ok, fit, h) in enumerate(zip(handled, chosen_fits, chosen.tolist()))
            ]
        if not any(handled):
            return self._estimate_batched(curvature, mask, u_meas, opts, guesses)

        pad = [H - len(fit.s) for fit in chosen_fits]
        steps = torch.tensor([fit.steps for fit in chosen_fits], device=device)
        out = self._report(
            torch.tensor(
                [list(fit.s) + [0.0] * p for fit, p in zip(chosen_fits, pad)], dtype=dtype, device=device
            ),
            torch.tensor(
                [[list(x) for x in fit.f] + [[0.0, 0.0]] * p for fit, p in zip(chosen_fits, pad)],
                dtype=dtype,
                device=device,
            ),
            torch.tensor([[True] * (H - p) + [False] * p for p in pad], device=device),
            mask,
            opts,
            chosen=chosen,
            sigma=sigma,
            loss=torch.tensor([fit.loss for fit in chosen_fits], dtype=dtype, device=device),
            converged=torch.tensor([fit.converged for fit in chosen_fits], device=device),
            iterations=steps,
            evaluations=steps,
            fit_losses=upper,
            out_dtype=curvature.dtype,
        )
        if all(handled):
            return out
        back = [b for b in range(B) if not handled[b]]
        idx = torch.tensor(back, device=device)
        part = self._estimate_batched(
            curvature[idx],
            mask[idx],
            u_meas[idx],
            opts,
            {h: [pf[idx] for pf in g] for h, g in guesses.items()},
        )
        return _merge(out, part, idx)

    def _select(
        self, fit_losses: torch.Tensor, residual_count: torch.Tensor, opts: EstimatorOptions
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return select_count(
            fit_losses,
            opts.counts,
            residual_count,
            rule=opts.selection,
            noise=opts.noise,
            threshold=opts.threshold,
            significance=opts.significance,
            floor=opts.noise_floor,
            num_gratings=self.rod.num_gratings,
        )

    def _report(
        self,
        s: torch.Tensor,
        f: torch.Tensor,
        fm: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        *,
        chosen: torch.Tensor,
        sigma: torch.Tensor,
        loss: torch.Tensor,
        converged: torch.Tensor,
        iterations: torch.Tensor,
        evaluations: torch.Tensor,
        fit_losses: torch.Tensor,
        out_dtype: torch.dtype,
    ) -> EstimateResult:
        """The chosen fits (model locations s (B, H) [m], f (B, H, 2) [N], force mask fm) in reported form: the
        Gauss-Newton uncertainty, forces sorted by s, locations shifted by the rod's location bias."""
        rod = self.rod
        B, H = fm.shape
        unc = force_uncertainty(
            rod,
            s,
            f,
            fm,
            mask,
            sigma,
            condition_limit=opts.condition_limit,
            max_step_angle=opts.max_step_angle,
        )
        order = s.masked_fill(~fm, float("inf")).argsort(dim=1)
        s = s.gather(1, order)
        f = f.gather(1, order.unsqueeze(-1).expand(-1, -1, 2))
        fm = fm.gather(1, order)
        std = unc.std.gather(1, order.unsqueeze(-1).expand(-1, -1, 3))
        s_rep = torch.where(fm, s + rod.location_bias, torch.zeros_like(s))
        by_count = torch.full((B, H), float("nan"), dtype=s.dtype, device=s.device)
        for k, h in enumerate(opts.counts):
            by_count[:, h - 1] = fit_losses[:, k]
        cast = lambda x: x.to(out_dtype)
        return EstimateResult(
            forces=PointForces(cast(s_rep), cast(f), fm),
            num_forces=chosen,
            loss=cast(loss),
            converged=converged,
            iterations=iterations,
            std=cast(std),
            poorly_determined=unc.poorly_determined,
            losses_by_count=cast(by_count),
            noise=cast(sigma),
            evaluations=evaluations,
        )

    def _check_guess(self, pf: Any, B: int, h: int, shift: float) -> PointForces:
        if not isinstance(pf, PointForces):
            raise TypeError(f"a start for h = {h} must be PointForces, got {type(pf).__name__}")
        if pf.s.shape != (B, h):
            raise ValueError(
                f"the starts for h = {h} must have shape (B, h) = {(B, h)}, got {tuple(pf.s.shape)}"
            )
        s = (pf.s.detach() + shift).clamp(0.0, self.rod.length)
        return PointForces(s, pf.f.detach(), pf.mask)


class _Problem:
    """All (reading, count, start) rows of one :meth:`Estimator.estimate` call: residuals, Jacobians, the stopping
    rule, the Levenberg-Marquardt polish and the L-BFGS refinement. Rows are ordered count-major, then start, then
    reading (row = (count block, start) * B + reading)."""

    def __init__(
        self,
        rod: Rod,
        opts: EstimatorOptions,
        u_meas: torch.Tensor,
        mask: torch.Tensor,
        reading: torch.Tensor,
        row_count: torch.Tensor,
        counts: list[int],
        H: int,
    ) -> None:
        self.rod, self.opts = rod, opts
        self.L, self.EI = rod.length, rod.bending_stiffness
        self.f_unit = self.EI / (self.L * self.L)
        self.u_meas, self.mask = u_meas, mask
        self.gmask = mask.to(u_meas.dtype).unsqueeze(-1)  # (B, G, 1)
        self.reading, self.row_count, self.counts, self.H = reading, row_count, counts, H
        self.P = 3 * H
        self.R = reading.shape[0]
        self.B, self.G = mask.shape
        dtype, device = u_meas.dtype, u_meas.device
        self.dtype, self.device = dtype, device
        self.fmask = torch.arange(H, device=device).unsqueeze(0) < row_count.unsqueeze(1)  # (R, H)
        self.active_p = self.fmask.repeat_interleave(3, dim=1)  # (R, P)
        self.pad_eye = (~self.active_p).to(dtype)
        self.query = rod.grating_positions(dtype, device)
        self.residual_count = 2 * mask.sum(dim=1)  # (B,)
        self.dof = (self.residual_count[reading] - 3 * row_count).to(dtype).clamp(min=1.0)  # (R,)
        self.floor2 = float(opts.noise_floor) ** 2
        self.sigma2_given = None if opts.noise is None else float(opts.noise) ** 2 + self.floor2
        # Critical values per (reading, count) for early settlement (known sigma or the threshold rule only):
        # misfit (B, C) the largest acceptable loss, drop (B, C, C) the largest acceptable loss_h - loss_h'.
        C = len(counts)
        self.C = C
        self.count_index = torch.searchsorted(torch.tensor(counts, device=device), row_count)  # (R,)
        self.cell = reading * C + self.count_index  # (R,) index of (reading, count)
        self.drop = None
        if opts.selection == "threshold":
            self.misfit = torch.full((self.B, C), float(opts.threshold), dtype=dtype, device=device)
        elif self.sigma2_given is not None:
            drop, misfit = count_limits(
                counts, self.residual_count, significance=opts.significance, num_gratings=self.G
            )
            self.drop = drop.to(dtype) * self.sigma2_given
            self.misfit = misfit.to(dtype) * self.sigma2_given
        else:
            self.misfit = None

    # ------------------------------------------------------------------ unknowns <-> forces
    def to_unknowns(self, s: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        """(R, H) locations [m] and (R, H, 2) forces [N] -> (R, P) unknowns (z, phi_x, phi_y); padding at z = -pi/2."""
        L, fm = self.L, self.fmask
        s = torch.where(fm, s.clamp(_EDGE * L, (1.0 - _EDGE) * L), torch.zeros_like(s))
        z = torch.asin((2.0 * s / L - 1.0).clamp(-1.0, 1.0))
        phi = torch.where(fm.unsqueeze(-1), f / self.f_unit, torch.zeros_like(f))
        return torch.cat((z.unsqueeze(-1), phi), dim=-1).reshape(self.R, self.P)

    def forces(self, v: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Unknowns (b, P) -> s (b, H) [m], f (b, H, 2) [N] (zero for padding), force mask (b, H)."""
        vv = v.view(-1, self.H, 3)
        fm = self.fmask[rows]
        s = torch.where(fm, 0.5 * self.L * (1.0 + torch.sin(vv[..., 0])), torch.zeros_like(vv[..., 0]))
        f = torch.where(fm.unsqueeze(-1), vv[..., 1:] * self.f_unit, torch.zeros_like(vv[..., 1:]))
        return s, f, fm

    # ------------------------------------------------------------------ residuals and the stopping rule
    def residual(self, v: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """r (b, 2G) [1/m] (zero at missing gratings) and dr/dv (b, 2G, P) for the rows ``rows``."""
        b, H, G = v.shape[0], self.H, self.G
        vv = v.view(b, H, 3)
        z = vv[..., 0]
        s = 0.5 * self.L * (1.0 + torch.sin(z))
        f = vv[..., 1:] * self.f_unit
        counts = self.row_count[rows]
        if b < _GROUP_ROWS or H == 1:
            u, jac = self._march(s, f, self.fmask[rows])  # (b, G, 2), (b, G, 2, H, 3)
        else:
            # Large batches: march each count with its own forces only (no padded events or tangents).
            u = s.new_empty(b, G, 2)
            jac = s.new_zeros(b, G, 2, H, 3)
            for h in counts.unique().tolist():
                at = (counts == h).nonzero().squeeze(1)
                u_h, jac_h = self._march(s[at, :h], f[at, :h], None)
                u[at] = u_h
                jac[at, :, :, :h] = jac_h
        gm = self.gmask[self.reading[rows]]
        r = (u - self.u_meas[self.reading[rows]]) * gm
        dsdz = 0.5 * self.L * torch.cos(z)
        unit = torch.full_like(dsdz, self.f_unit)
        chain = torch.stack((dsdz, unit, unit), dim=-1)  # (b, H, 3)
        J = jac * chain.view(b, 1, 1, H, 3) * gm.unsqueeze(-1).unsqueeze(-1)
        return r.reshape(b, 2 * G), J.reshape(b, 2 * G, self.P)

    def _march(
        self, s: torch.Tensor, f: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        u, jac = curvature_and_jacobian(
            self.query,
            s,
            f,
            self.L,
            self.EI,
            mask=mask,
            max_step_angle=self.opts.max_step_angle,
            max_steps=_MAX_STEPS,
        )
        assert jac is not None
        return u, jac

    def _normal(self, J: torch.Tensor, rows: torch.Tensor, damping: torch.Tensor | float) -> torch.Tensor:
        A = J.transpose(1, 2) @ J
        d = A.diagonal(dim1=1, dim2=2)
        scale = d.amax(dim=1, keepdim=True).clamp(min=torch.finfo(self.dtype).tiny)
        if isinstance(damping, torch.Tensor):
            damping = damping.unsqueeze(1)
        return A + torch.diag_embed(damping * d + 1e-12 * scale + self.pad_eye[rows] * scale)

    def kinks(
        self, r: torch.Tensor, J: torch.Tensor, rows: torch.Tensor, v: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One-sided Jacobians at the loss's kinks, and the forces pinned on one.

        Grating k sees a force only while the force lies distal to it, so the residual has a kink in s_i at
        s_i = s_k: dU_k/ds_i is 0 on the proximal side and the slope jump i (f_x + i f_y) / EI on the distal side
        (the force's lever at k grows from zero). A least-squares optimum can sit exactly on such a kink, where
        no gradient vanishes. For a force within ``_KINK`` of a present grating both one-sided derivatives of the
        loss are formed: if the loss rises on both sides, the force is pinned there (its s is left out of the
        Gauss-Newton step and of the convergence test; the other unknowns keep being optimised); otherwise the
        Jacobian of the side the loss falls towards is used.

        Returns:
            J (b, 2G, P) with the chosen sides (pinned s columns zeroed), and pinned (b, H) bool.
        """
        b, H, G = v.shape[0], self.H, self.G
        vv = v.view(b, H, 3)
        z = vv[..., 0]
        s = 0.5 * self.L * (1.0 + torch.sin(z))
        present = self.mask[self.reading[rows]].unsqueeze(1)  # (b, 1, G)
        near = (
            ((s.unsqueeze(-1) - self.query).abs() < _KINK) & present & self.fmask[rows].unsqueeze(-1)
        )  # (b, H, G)
        if not bool(near.any()):
            self._last_slopes = None
            return J, torch.zeros(b, H, dtype=torch.bool, device=v.device)
        f = vv[..., 1:] * self.f_unit
        dsdz = 0.5 * self.L * torch.cos(z)
        jump = (
            torch.stack((-f[..., 1], f[..., 0]), dim=-1) / self.EI * dsdz.unsqueeze(-1)
        )  # (b, H, 2) dU_k/dz
        Jv = J.view(b, G, 2, H, 3)
        sel = near.permute(0, 2, 1).unsqueeze(2)  # (b, G, 1, H)
        col = Jv[..., 0]  # (b, G, 2, H): the s columns
        prox = torch.where(sel, torch.zeros_like(col), col)
        dist = torch.where(sel, jump.permute(0, 2, 1).unsqueeze(1).expand(b, G, 2, H), col)
        rr = r.view(b, G, 2, 1)
        g_prox = (prox * rr).sum((1, 2))  # (b, H): d(loss/2)/dz from the proximal side
        g_dist = (dist * rr).sum((1, 2))
        on = near.any(-1)
        self._last_slopes = (g_prox, g_dist, near)
        pinned = on & (g_prox <= 0) & (g_dist >= 0)
        use_dist = on & ~pinned & ((g_dist < 0) & ((g_prox <= 0) | (-g_dist > g_prox)))
        new_col = torch.where(use_dist.unsqueeze(1).unsqueeze(1), dist, prox)
        new_col = torch.where(on.unsqueeze(1).unsqueeze(1), new_col, col)
        new_col = torch.where(pinned.unsqueeze(1).unsqueeze(1), torch.zeros_like(new_col), new_col)
        Jv = torch.cat((new_col.unsqueeze(-1), Jv[..., 1:]), dim=-1)
        return Jv.reshape(b, 2 * G, self.P), pinned

    def _near_kink(self, v: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(b, H) bool: the force lies within ``_KINK`` of a present grating."""
        s = 0.5 * self.L * (1.0 + torch.sin(v.view(-1, self.H, 3)[..., 0]))
        present = self.mask[self.reading[rows]].unsqueeze(1)
        return ((s.unsqueeze(-1) - self.query).abs() < _KINK).logical_and(present).any(-1) & self.fmask[rows]

    def _gn_step(
        self,
        J: torch.Tensor,
        r: torch.Tensor,
        rows: torch.Tensor,
        damping: torch.Tensor | float,
        fixed: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Damped Gauss-Newton step (b, P) with the locations ``fixed`` (b, H) held, and its decrement (b,)
        ``g^T (A)^-1 g`` (the loss decrease the step promises; inf where the solve failed)."""
        hold = torch.zeros(J.shape[0], self.H, 3, dtype=torch.bool, device=J.device)
        hold[..., 0] = fixed
        hold = hold.view(-1, self.P)
        J = torch.where(hold.unsqueeze(1), torch.zeros_like(J), J)
        g = (J.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1)
        A = self._normal(J, rows, damping)
        A = A + torch.diag_embed(hold.to(A.dtype) * A.diagonal(dim1=1, dim2=2).amax(1, keepdim=True))
        chol, info = torch.linalg.cholesky_ex(A)
        step = -torch.cholesky_solve(g.unsqueeze(-1), chol).squeeze(-1)
        ok = (info == 0).unsqueeze(1) & torch.isfinite(step)
        step = torch.where(ok, step, torch.zeros_like(step))
        dec = torch.where(ok.all(1), -(g * step).sum(-1), torch.full_like(g[:, 0], float("inf")))
        return step, dec

    def sigma2(self, r: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(b,) the sigma^2 the stopping test measures against: the given noise with the floor, else the fit's own
        loss per degree of freedom, floored."""
        if self.sigma2_given is None:
            return (r.square().sum(-1) / self.dof[rows]).clamp(min=self.floor2)
        return torch.full_like(r[:, 0], self.sigma2_given)

    def decrement(
        self, r: torch.Tensor, J: torch.Tensor, rows: torch.Tensor, v: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gauss-Newton decrement (the loss decrease of a GN step; at kinks with the one-sided Jacobians of
        :meth:`kinks`, pinned locations held) and sigma^2 (:meth:`sigma2`). A fit has converged when the decrement
        is at most ``decrement_tolerance`` x sigma^2: what is left to gain is far below the noise."""
        Jk, pinned = self.kinks(r, J, rows, v)
        _, dec = self._gn_step(Jk, r, rows, 1e-9, pinned)
        return dec, self.sigma2(r, rows)

    # ------------------------------------------------------------------ early settlement
    def _reset_state(self, r: torch.Tensor, dec: torch.Tensor, done: torch.Tensor) -> None:
        """Per-row state for :meth:`settled`: latest loss, decrement, convergence and hopelessness."""
        self.cur_loss = r.square().sum(-1)
        self.cur_dec = dec
        self.cur_done = done
        self.cur_hopeless = self._hopeless(self.cur_loss, dec, torch.arange(self.R, device=self.device))

    def _update_state(
        self, rows: torch.Tensor, loss: torch.Tensor, dec: torch.Tensor, done: torch.Tensor
    ) -> None:
        self.cur_loss = self.cur_loss.index_copy(0, rows, loss)
        self.cur_dec = self.cur_dec.index_copy(0, rows, dec)
        self.cur_done = self.cur_done.index_copy(0, rows, done)
        self.cur_hopeless = self.cur_hopeless.index_copy(0, rows, self._hopeless(loss, dec, rows))

    def _hopeless(self, loss: torch.Tensor, dec: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Rows stagnating far from acceptable: the Gauss-Newton prediction ``dec`` (no location held) would not
        even halve their loss, and the loss it leaves stays above twice the misfit limit of their count (only with
        known critical values). Such a fit sits near a poor local minimum; it counts as final for settlement."""
        if self.misfit is None:
            return torch.zeros_like(loss, dtype=torch.bool)
        limit = self.misfit.reshape(-1)[self.cell[rows]]
        left = loss - dec
        return (left > 2.0 * limit.clamp(min=0.0)) & (left > 0.5 * loss)

    def settled(self, running: torch.Tensor) -> torch.Tensor:
        """(B,) bool: readings whose count is decided whatever their still-running fits do (known sigma or the
        threshold rule; never with sigma estimated). ``running`` (R,) marks the rows still being optimised.

        A count is accepted once one of its fits has converged with a loss that passes the count's tests against
        lower estimates (current loss minus decrement) of the larger counts' final losses; it is rejected once all
        its fits are final and fail a test against the larger counts' current losses (which can only fall). The
        reading is settled when a count is accepted and every smaller count rejected.
        """
        if self.misfit is None:
            return torch.zeros(self.B, dtype=torch.bool, device=self.device)
        dtype, device, cells, inf = self.dtype, self.device, self.B * self.C, float("inf")

        def reduce(values: torch.Tensor, how: str, fill: float) -> torch.Tensor:
            out = torch.full((cells,), fill, dtype=dtype, device=device)
            return out.scatter_reduce(0, self.cell, values, how).view(self.B, self.C)

        final = ~running | self.cur_done | self.cur_hopeless
        upper = reduce(self.cur_loss, "amin", inf)
        all_final = reduce((~final).to(dtype), "amax", 0.0) == 0
        best_done = reduce(
            torch.where(self.cur_done, self.cur_loss, torch.full_like(self.cur_loss, inf)), "amin", inf
        )
        if self.drop is None:  # the threshold rule
            accepted = best_done < self.misfit
            rejected = all_final & (upper >= self.misfit)
        else:
            lower = reduce((self.cur_loss - self.cur_dec).clamp(min=0.0), "amin", inf)
            later = torch.ones(self.C, self.C, dtype=torch.bool, device=device).triu(1)  # h' > h
            beats = (best_done.unsqueeze(2) - lower.unsqueeze(1) <= self.drop) | ~later
            accepted = (best_done <= self.misfit) & beats.all(dim=2)
            gain = (upper.unsqueeze(2) - upper.unsqueeze(1) > self.drop) & later
            rejected = all_final & ((upper > self.misfit) | gain.any(dim=2))
        before = torch.cumprod(torch.cat((torch.ones_like(rejected[:, :1]), rejected[:, :-1]), 1), 1).bool()
        return (accepted & before).any(dim=1)

    # ------------------------------------------------------------------ Levenberg-Marquardt polish
    def polish(self, v: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Up to ``iterations`` Levenberg-Marquardt steps on every row still open (one batched evaluation per
        step), with the kink handling of :meth:`kinks`: a step stops where a force reaches a grating
        (:meth:`_step_fraction`); the force then stays there while the other unknowns converge, and leaves only
        if the loss falls off the kink on one side. Rows stop when converged or when their reading is settled.
        Returns the improved unknowns and the steps taken per row; leaves the per-row state for :meth:`refine`."""
        R, device = self.R, self.device
        taken = torch.zeros(R, dtype=torch.long, device=device)
        rows = torch.arange(R, device=device)
        r, J = self.residual(v, rows)
        loss = r.square().sum(-1)
        lam = torch.full((R,), 1e-3, dtype=self.dtype, device=device)
        stuck = torch.zeros(R, self.H, dtype=torch.bool, device=device)
        running = torch.ones(R, dtype=torch.bool, device=device)
        tol = self.opts.decrement_tolerance
        self._reset_state(r, torch.full_like(loss, float("inf")), torch.zeros_like(running))
        # Kink probes: a fit that converges onto a kink that is a local minimum (the loss rises on both sides) is
        # restarted once from the middle of the grating interval on the gentler side, its solution kept aside; the
        # better of the two is kept. A kink is a trap smooth descent cannot leave, the true minimum may be beyond.
        probed = torch.zeros(R, dtype=torch.bool, device=device)
        best_v, best_r, best_J, best_loss = v, r, J, torch.full_like(loss, float("inf"))
        for it in range(iterations + 1):
            idx = running.nonzero().squeeze(1)
            if idx.numel() == 0:
                break
            Ji, ri, vi = J[idx], r[idx], v[idx]
            Jk, vmin = self.kinks(ri, Ji, idx, vi)
            slopes = self._last_slopes
            st = stuck[idx] & self._near_kink(vi, idx)
            _, dec = self._gn_step(Jk, ri, idx, 1e-9, st | vmin)
            small = dec <= tol * self.sigma2(ri, idx)
            done = small & ~(st & ~vmin).any(1)
            probe = done & vmin.any(1) & ~probed[idx] & (it < iterations)
            if bool(probe.any()):
                at = probe.nonzero().squeeze(1)
                rows_p = idx[at]
                best_v = best_v.index_copy(0, rows_p, vi[at])
                best_r = best_r.index_copy(0, rows_p, ri[at])
                best_J = best_J.index_copy(0, rows_p, Ji[at])
                best_loss = best_loss.index_copy(0, rows_p, loss[rows_p])
                v_probe = self._probe_point(vi[at], vmin[at], slopes, at, rows_p)
                r_p, J_p = self.residual(v_probe, rows_p)
                v = v.index_copy(0, rows_p, v_probe)
                r = r.index_copy(0, rows_p, r_p)
                J = J.index_copy(0, rows_p, J_p)
                loss = loss.index_copy(0, rows_p, r_p.square().sum(-1))
                probed = probed.index_fill(0, rows_p, True)
                stuck = stuck.index_fill(0, rows_p, False)
                lam = lam.index_fill(0, rows_p, 1e-3)
                done = done & ~probe
                taken = taken.index_add(0, rows_p, torch.ones_like(rows_p))
            _, dec_free = self._gn_step(Jk, ri, idx, 1e-9, vmin)
            self._update_state(idx, torch.minimum(loss[idx], best_loss[idx]), dec_free, done)
            running = running.index_copy(0, idx, ~done & (lam[idx] < 1e9))
            running = running & ~self.settled(running)[self.reading]
            if it == iterations:
                break
            keep = running[idx] & ~probe  # probed rows start afresh next iteration
            idx, Jk, vmin, st, ri, vi, Ji, small = (x[keep] for x in (idx, Jk, vmin, st, ri, vi, Ji, small))
            if idx.numel() == 0:
                break
            st = st & ~(
                ~vmin & small.unsqueeze(1)
            )  # release: the others have converged, the loss falls off the kink
            step, _ = self._gn_step(Jk, ri, idx, lam[idx], st | vmin)
            # Trust region: at most _MAX_DPHI (force units EI/L^2) and _MAX_DZ per step, then no grating crossed.
            vv = step.view(-1, self.H, 3)
            big = torch.maximum(
                vv[..., 1:].abs().amax((1, 2)) / _MAX_DPHI, vv[..., 0].abs().amax(1) / _MAX_DZ
            )
            step = step / big.clamp(min=1.0).unsqueeze(1)
            # Two trials in one evaluation: the step as it is, and, where it crosses a grating, the step cut where
            # the first force lands on it. The better one is taken: crossing may jump over a kink that is a local
            # minimum, landing reaches a kink that is the minimum.
            t, landed, t_bound = self._step_fraction(vi, step, idx)
            full = vi + step * t_bound.unsqueeze(1)
            cut = (t < t_bound).nonzero().squeeze(1)
            v_cut = vi[cut] + step[cut] * t[cut].unsqueeze(1)
            r_both, J_both = self.residual(torch.cat((full, v_cut)), torch.cat((idx, idx[cut])))
            n = idx.shape[0]
            r_try, J_try, v_try = r_both[:n], J_both[:n], full
            loss_try = r_try.square().sum(-1)
            loss_cut = r_both[n:].square().sum(-1)
            take_cut = torch.zeros(n, dtype=torch.bool, device=device)
            take_cut[cut] = torch.isfinite(loss_cut) & ~(loss_try[cut] <= loss_cut)
            if bool(take_cut.any()):
                which = take_cut[cut]
                pos = cut[which]
                r_try = r_try.index_copy(0, pos, r_both[n:][which])
                J_try = J_try.index_copy(0, pos, J_both[n:][which])
                v_try = v_try.index_copy(0, pos, v_cut[which])
                loss_try = loss_try.index_copy(0, pos, loss_cut[which])
            landed = landed & take_cut.unsqueeze(1)
            better = torch.isfinite(loss_try) & (loss_try < loss[idx])
            v = v.index_copy(0, idx, torch.where(better.unsqueeze(1), v_try, vi))
            r = r.index_copy(0, idx, torch.where(better.unsqueeze(1), r_try, ri))
            J = J.index_copy(0, idx, torch.where(better.view(-1, 1, 1), J_try, Ji))
            loss = loss.index_copy(0, idx, torch.where(better, loss_try, loss[idx]))
            stuck = stuck.index_copy(0, idx, torch.where(better.unsqueeze(1), st | landed, stuck[idx]))
            lam = lam.index_copy(0, idx, torch.where(better, lam[idx] / 3.0, lam[idx] * 4.0).clamp(1e-9, 1e9))
            taken = taken.index_add(0, idx, torch.ones_like(idx))
        # Probed rows whose restart did no better return to their kink solution (converged there).
        back = probed & (best_loss <= loss)
        if bool(back.any()):
            at = back.nonzero().squeeze(1)
            v = v.index_copy(0, at, best_v[at])
            r = r.index_copy(0, at, best_r[at])
            J = J.index_copy(0, at, best_J[at])
            running = running.index_fill(0, at, False)
            self.cur_done = self.cur_done.index_fill(0, at, True)
            self.cur_loss = self.cur_loss.index_copy(0, at, best_loss[at])
            self.cur_dec = self.cur_dec.index_fill(0, at, 0.0)
        self._polished = (v, r, J, running)
        return v, taken

    def _probe_point(
        self, v: torch.Tensor, pinned: torch.Tensor, slopes: tuple, at: torch.Tensor, rows: torch.Tensor
    ) -> torch.Tensor:
        """v (b, P) with its first pinned force moved off its grating to the middle of the neighbouring interval on
        the side where the loss rises more gently (``slopes``: the one-sided slopes of :meth:`kinks`)."""
        b = v.shape[0]
        g_prox, g_dist, _ = (x[at] for x in slopes)
        first = pinned & (pinned.cumsum(1) == 1)  # (b, H)
        vv = v.view(b, self.H, 3).clone()
        s = 0.5 * self.L * (1.0 + torch.sin(vv[..., 0]))
        q = self.query
        present = self.mask[self.reading[rows]]  # (b, G)
        inf = torch.full_like(s.unsqueeze(-1).expand(-1, -1, q.shape[0]), float("inf"))
        above = torch.where(present.unsqueeze(1) & (q > s.unsqueeze(-1) + _KINK), q.expand_as(inf), inf).amin(
            -1
        )
        below = torch.where(
            present.unsqueeze(1) & (q < s.unsqueeze(-1) - _KINK), q.expand_as(inf), -inf
        ).amax(-1)
        above = torch.where(torch.isfinite(above), above, torch.full_like(s, self.L))
        below = torch.where(torch.isfinite(below), below, torch.zeros_like(s))
        distal = g_dist.abs() <= g_prox.abs()
        target = torch.where(distal, 0.5 * (s + above), 0.5 * (s + below))
        z_new = torch.asin((2.0 * target / self.L - 1.0).clamp(-1.0, 1.0))
        vv[..., 0] = torch.where(first, z_new, vv[..., 0])
        return vv.view(b, self.P)

    def _step_fraction(
        self, v: torch.Tensor, step: torch.Tensor, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(b,) largest t in (0, 1] such that v + t step moves no force across a present grating (it may land on
        one) and keeps every z in [-pi/2, pi/2] (where s(z) is monotone); (b, H) the forces that land; and (b,) the
        largest t that only keeps z in range.

        The loss has a kink where a force crosses a grating (:meth:`kinks`); a Gauss-Newton model built on one
        side of it mispredicts the other, and an optimum on the kink is reached by landing on it, not by stepping
        over it back and forth.
        """
        b, H = v.shape[0], self.H
        half = math.pi / 2
        z = v.view(b, H, 3)[..., 0]
        dz = step.view(b, H, 3)[..., 0]
        moving = self.fmask[rows] & (dz != 0)
        safe = torch.where(moving, dz, torch.ones_like(dz))
        target = torch.where(dz > 0, torch.full_like(z, half), torch.full_like(z, -half))
        t = torch.where(moving, ((target - z) / safe).clamp(min=0.0, max=1.0), torch.ones_like(z))  # (b, H)
        z_new = z + t * dz
        s_old = 0.5 * self.L * (1.0 + torch.sin(z))
        s_new = 0.5 * self.L * (1.0 + torch.sin(z_new))
        q = self.query.view(1, 1, -1)
        zq = torch.asin((2.0 * self.query / self.L - 1.0).clamp(-1.0, 1.0)).view(1, 1, -1)
        present = self.mask[self.reading[rows]].unsqueeze(1)  # (b, 1, G)
        crossed = (
            present
            & moving.unsqueeze(-1)
            & ((s_old.unsqueeze(-1) - q) * (s_new.unsqueeze(-1) - q) < 0)
            & ((s_old.unsqueeze(-1) - q).abs() > 1e-9 * self.L)
        )
        t_cross = torch.where(
            crossed, (zq - z.unsqueeze(-1)) / safe.unsqueeze(-1), torch.ones_like(crossed, dtype=z.dtype)
        )
        t_cross = t_cross.clamp(min=0.0, max=1.0).amin(dim=-1)  # (b, H)
        t_row = torch.minimum(t, t_cross).amin(dim=1)  # (b,)
        landed = crossed.any(-1) & (t_cross <= t_row.unsqueeze(1))
        return t_row, landed, t.amin(dim=1)

    # ------------------------------------------------------------------ L-BFGS
    def refine(self, v0: torch.Tensor) -> RefineResult:
        """One batched L-BFGS call over the rows still open (not converged, reading not settled), whitened at ``v0``
        (module docstring); closed rows keep ``v0`` with zero iterations. Returns the result for all R rows in
        terms of the unknowns v: ``x`` (R, P) and ``loss`` (R,) the sum of squared residuals [1/m^2]."""
        R, P, dtype, device = self.R, self.P, self.dtype, self.device
        all_rows = torch.arange(R, device=device)
        polished = getattr(self, "_polished", None)
        if polished is not None and polished[0] is v0:
            _, r_all, J_all, open_all = polished
        else:
            r_all, J_all = self.residual(v0, all_rows)
            dec0, s20 = self.decrement(r_all, J_all, all_rows, v0)
            self._reset_state(r_all, dec0, dec0 <= self.opts.decrement_tolerance * s20)
            open_all = ~self.cur_done
        open_all = open_all & ~self.settled(open_all)[self.reading]
        zeros = torch.zeros(R, dtype=torch.long, device=device)
        result = RefineResult(
            x=v0,
            loss=r_all.square().sum(-1),
            grad=torch.zeros_like(v0),
            converged=self.cur_done.clone(),
            iterations=zeros,
            evaluations=zeros,
        )
        idx = open_all.nonzero().squeeze(1)  # the open rows, in the L-BFGS batch's order
        n = idx.shape[0]
        if n == 0:
            return result
        r0, J0, w0 = r_all[idx], J_all[idx], v0[idx]
        # Forces pinned on a kink at the start stay there (L-BFGS knows no kinks): their s is held fixed.
        _, pinned = self.kinks(r0, J0, idx, w0)
        free = torch.ones(n, self.H, 3, dtype=dtype, device=device)
        free[..., 0] = (~pinned).to(dtype)
        free = free.view(n, P)
        J0 = J0 * free.unsqueeze(1)
        A = self._normal(J0, idx, _DAMPING)
        C, info = torch.linalg.cholesky_ex(A)
        if bool((info != 0).any()):  # numerically indefinite rows: fall back to the diagonal
            C = torch.where(
                (info != 0).view(-1, 1, 1), torch.diag_embed(A.diagonal(dim1=1, dim2=2).sqrt()), C
            )
        eye = torch.eye(P, dtype=dtype, device=device)
        T = torch.linalg.solve_triangular(C.transpose(1, 2), eye.expand(n, P, P), upper=True)  # T^T A T = I
        g_white = (T.transpose(1, 2) @ (J0.transpose(1, 2) @ r0.unsqueeze(-1))).squeeze(-1)
        alpha = g_white.abs().sum(dim=1).clamp(min=1.0)
        T = T * alpha.view(n, 1, 1)
        weight = 1.0 / (alpha * alpha)
        first = {"pending": True}

        def objective(y: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
            yd = y.detach()
            rows = idx[local]
            v = w0[local] + free[local] * (T[local] @ yd.unsqueeze(-1)).squeeze(-1)
            c = weight[local]
            if first["pending"] and local.shape[0] == n and not bool(yd.any()):
                first["pending"] = False  # the start: already evaluated
                r, J = r0, J0
            else:
                first["pending"] = False
                r, J = self.residual(v, rows)
            sq = r.square().sum(-1)
            grad_v = (J.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1) * free[local]
            grad_y = c.unsqueeze(1) * (T[local].transpose(1, 2) @ grad_v.unsqueeze(-1)).squeeze(-1)
            # Stopping: the row's own test (GN decrement), or its reading settled. A zero gradient ends the row
            # through L-BFGS's gradient test.
            dec, sigma2 = self.decrement(r, J, rows, v)
            now = dec <= self.opts.decrement_tolerance * sigma2
            self._update_state(rows, sq, dec, now)
            running = torch.zeros(R, dtype=torch.bool, device=device).index_fill(0, rows, True)
            stop = now | self.settled(running)[self.reading[rows]]
            grad_y = torch.where(stop.unsqueeze(1), torch.zeros_like(grad_y), grad_y)
            return 0.5 * c * sq + ((y - yd) * grad_y).sum(-1)

        res = lbfgs(objective, torch.zeros(n, P, dtype=dtype, device=device), self.opts.lbfgs)
        x = w0 + free * (T @ res.x.unsqueeze(-1)).squeeze(-1)
        loss = 2.0 * res.loss / weight
        loss = torch.where(torch.isfinite(loss), loss, torch.full_like(loss, float("inf")))
        return RefineResult(
            x=result.x.index_copy(0, idx, x),
            loss=result.loss.index_copy(0, idx, loss),
            grad=result.grad,
            converged=result.converged.index_copy(0, idx, res.converged),
            iterations=zeros.index_copy(0, idx, res.iterations),
            evaluations=zeros.index_copy(0, idx, res.evaluations),
        )


def _merge(base: EstimateResult, part: EstimateResult, idx: torch.Tensor) -> EstimateResult:
    """``base`` with its readings ``idx`` (k,) replaced by the k readings of ``part``."""

    def put(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        a = a.clone()
        a[idx] = b.to(a.dtype)
        return a

    fields: dict[str, Any] = {}
    for field in dataclasses.fields(base):
        a, b = getattr(base, field.name), getattr(part, field.name)
        if field.name == "forces":
            fields["forces"] = PointForces(put(a.s, b.s), put(a.f, b.f), put(a.active, b.active))
        else:
            fields[field.name] = None if a is None or b is None else put(a, b)
    return EstimateResult(**fields)
