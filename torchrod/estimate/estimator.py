"""Estimating the contact forces behind FBG curvature readings.

For B readings, :meth:`Estimator.estimate`

1. checks the readings (:func:`torchrod.estimate.checks.check_readings`): missing gratings are masked, never read as
   zero;
2. asks the warm-start network, when the estimator has one, for a first guess of each count;
3. runs the kernels (:mod:`torchrod.kernels`) on every reading, on the CPU's cores or one GPU thread per reading:
   the fit of every count 0..max_forces, each from the one below, the search for each count's global minimum, the
   count chosen by the significance tests, the Gauss-Newton uncertainty, the chi-square p-value of the chosen fit
   and the reading's status (:mod:`.status`: ``ok``, ``misfit``, ``unconverged``, ``poorly_determined``,
   ``timeout``);
4. returns them as tensors in the input's dtype and on its device.

Locations are reported as ``s_model + rod.location_bias``, forces sorted by location. A reading the numerics fail on
is answered with a status, never an exception.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from ..errors import OptionsError, ReadingError, TorchrodTypeError
from ..kernels import host as _kernels
from ..kernels.layout import Batch
from ..loads import PointForces
from ..rod import Rod
from . import implicit, refine
from .checks import check_readings, host_view
from .options import EstimatorOptions, LMPolicy, SearchOptions, default_max_forces
from .status import Status

__all__ = ["EstimateResult", "Estimator", "EstimatorOptions", "GuessSource", "LMPolicy", "SearchOptions"]


@dataclass(frozen=True)
class EstimateResult:
    """Estimates for B readings, batch first (W = the options' ``width``: max_forces, or num_forces if fixed).

    Attributes:
        forces: (B, W) forces sorted by location, padding (mask False) last; s REPORTED = s_model +
            rod.location_bias [m], f body-frame (f_x, f_y) [N].
        num_forces: (B,) long, the chosen count (0: no contact).
        status: (B,) long, the verdict's code: its position in :class:`~torchrod.Status` (``ok``, ``misfit``,
            ``unconverged``, ``poorly_determined``, ``timeout``; :mod:`torchrod.estimate.status` says what each
            means and what to do). :attr:`statuses` gives them as :class:`~torchrod.Status` members.
        p_value: (B,) the chi-square p-value of the chosen fit's loss (the chance that a correct fit is this bad or
            worse; NaN with no degree of freedom left).
        loss: (B,) loss of the chosen fit: sum over present gratings of squared residuals [1/m^2].
        converged: (B,) bool, the chosen fit stopped on its tolerance.
        iterations: (B,) long, the chosen fit's solver steps.
        std: (B, W, 3) standard deviations of (s [m], f_x [N], f_y [N]); NaN for padding.
        poorly_determined: (B,) bool (:class:`~torchrod.estimate.status.Status`, ``poorly_determined``).
        losses_by_count: (B, W + 1) best loss of each count h = 0..W [1/m^2]; NaN where h was not fitted.
        noise: (B,) sigma used for the selection and the covariance [1/m].
        evaluations: (B,) long, forward-model evaluations spent on the reading (all its fits and scans).
    """

    forces: PointForces
    num_forces: torch.Tensor
    status: torch.Tensor
    p_value: torch.Tensor
    loss: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    std: torch.Tensor
    poorly_determined: torch.Tensor
    losses_by_count: torch.Tensor
    noise: torch.Tensor
    evaluations: torch.Tensor

    @property
    def batch_size(self) -> int:
        return self.num_forces.shape[0]

    def __len__(self) -> int:
        return self.batch_size

    @property
    def statuses(self) -> list[Status]:
        """The verdicts, one per reading (each a string: ``result.statuses[0] == "ok"``)."""
        return [_MEMBERS[c] for c in self.status.tolist()]

    @property
    def ok(self) -> torch.Tensor:
        """(B,) bool: status ``ok``."""
        return self.status == Status.OK.code

    def __getitem__(self, index: int | slice | torch.Tensor) -> EstimateResult:
        """Select readings along the batch dimension (an int keeps a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        fields = {f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)}
        return EstimateResult(**fields)

    def to_records(self, ids: Sequence[Any] | None = None) -> list[dict[str, Any]]:
        """One JSON-ready dict per reading (the ``torchrod estimate`` output, without ``time_ms``).

        ``{"id", "status", "num_forces", "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"},
        ...] sorted by s, "p_value", "loss", "converged", "iterations", "evaluations", "poorly_determined"}``; SI
        units; a non-finite number is null. ``ids`` default to the batch index.
        """
        B = self.batch_size
        if ids is None:
            ids = list(range(B))
        elif len(ids) != B:
            raise OptionsError(f"ids must hold {B} entries, got {len(ids)}")

        def num(x: float) -> float | None:
            return x if math.isfinite(x) else None

        # (tolist reads any tensor, on any device, with or without a gradient: one call each)
        s = self.forces.s.tolist()
        f = self.forces.f.tolist()
        active = self.forces.active.tolist()
        std = self.std.tolist()
        n = self.num_forces.tolist()
        status = self.statuses
        p = self.p_value.tolist()
        loss = self.loss.tolist()
        conv = self.converged.tolist()
        it = self.iterations.tolist()
        spent = self.evaluations.tolist()
        poor = self.poorly_determined.tolist()
        out = []
        isfinite, hypot = math.isfinite, math.hypot
        for b in range(B):
            forces = []
            for j in range(len(s[b])):
                if not active[b][j]:
                    continue
                fx, fy = f[b][j]
                sj, (s0, s1, s2), size = s[b][j], std[b][j], hypot(fx, fy)
                # (a sum is finite only where every term is: one test for the usual force, each value's otherwise)
                values = (sj, fx, fy, size, s0, s1, s2)
                v: tuple[float | None, ...] = values if isfinite(sum(values)) else tuple(map(num, values))
                forces.append({"s": v[0], "fx": v[1], "fy": v[2], "magnitude": v[3], "std_s": v[4], "std_fx": v[5],
                               "std_fy": v[6]})  # fmt: skip
            out.append(
                {
                    "id": ids[b],
                    "status": status[b].value,
                    "num_forces": int(n[b]),
                    "forces": forces,
                    "p_value": num(p[b]),
                    "loss": num(loss[b]),
                    "converged": bool(conv[b]),
                    "iterations": int(it[b]),
                    "evaluations": int(spent[b]),
                    "poorly_determined": bool(poor[b]),
                }
            )
        return out


@runtime_checkable
class GuessSource(Protocol):
    """What the estimator takes as a ``warm_start``: a source of first guesses, such as the trained network
    (:class:`torchrod.WarmStart`), in MODEL coordinates (no location bias).

    ``guess(curvature (B, G, 2) [1/m], mask (B, G) bool)`` returns an object with ``forces``, a dict {h:
    :class:`~torchrod.PointForces` (B, h)}, and optionally ``count_probs`` (B, H), the probability of 1..H forces
    (a count's guess then starts a fit only where it is at least ``guess_probability``). A source may also offer
    ``compiled_arrays(curvature, mask)``: the same guesses as NumPy arrays (probabilities (B, H), locations (B, H,
    H) [m], forces (B, H, H, 2) [N], count h in ``[:, h - 1, :h]``), which the estimator uses for CPU readings.
    """

    def guess(self, curvature: torch.Tensor, mask: torch.Tensor) -> Any: ...


class Estimator:
    """Force estimation for one rod (module docstring: the method).

    Args:
        rod: the rod (length, EI, gratings, location bias).
        options: :class:`EstimatorOptions` (None: the defaults, with ``max_forces`` as many as the rod's gratings
            can test, at most 3: :func:`~torchrod.estimate.options.default_max_forces`).
        warm_start: optional source of extra starts (:class:`GuessSource`, e.g. :class:`torchrod.WarmStart`), or a
            callable ``(curvature, mask) -> {h: PointForces}``. Its guesses are starts beside the scan's (``starts``
            > 0): a network can add starts, never take the search's away, unless the options trust them
            (``trust_guesses``, as :func:`torchrod.load_estimator` sets for a trusted network).
    """

    def __init__(self, rod: Rod, options: EstimatorOptions | None = None, warm_start: Any = None) -> None:
        if not isinstance(rod, Rod):
            raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
        options = EstimatorOptions(max_forces=default_max_forces(rod.num_gratings)) if options is None else options
        if not isinstance(options, EstimatorOptions):
            raise TorchrodTypeError(f"options must be EstimatorOptions, got {type(options).__name__}")
        if warm_start is not None and not (hasattr(warm_start, "guess") or callable(warm_start)):
            raise TorchrodTypeError(
                f"warm_start must have a guess() method or be callable, got {type(warm_start).__name__}"
            )
        self.rod = rod
        self.options = options
        self.warm_start = warm_start
        self._plans: dict[Any, Any] = {}
        self._compiled: list[Any] = []  # the plans' compiled kernels, each once (few: one per target)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ input checks
    def _check(self, curvature: Any, mask: Any) -> tuple[torch.Tensor, torch.Tensor]:
        curvature, mask = check_readings(curvature, mask, self.rod.num_gratings)
        if curvature.shape[0] == 0:
            raise ReadingError(f"curvature must hold at least one reading, got shape {tuple(curvature.shape)}")
        if not bool(host_view(mask).any(1).all()):
            rows = (~mask.any(dim=1)).nonzero().squeeze(1).tolist()
            raise ReadingError(f"readings {rows[:10]} have no present grating (mask all False)")
        return curvature, mask

    @staticmethod
    def _target(opts: EstimatorOptions, device: torch.device) -> str:
        if opts.target == "auto":
            return "cuda" if device.type == "cuda" else "cpu"
        if (opts.target == "cuda") != (device.type == "cuda") and not _kernels.simulated():
            raise OptionsError(f"target {opts.target!r} does not run readings on {device}: move them, or target 'auto'")
        return opts.target

    def plan(
        self,
        options: EstimatorOptions | None = None,
        guess_counts: Sequence[int] = (),
        device: Any = "cpu",
        wait: bool = False,
    ):
        """The kernels' plan for these options and guess blocks (their counts), made once and kept: its setup, and
        the compiled kernels of the target, loaded now, or compiled (announced the first time; never inside a
        reading's time budget): a first CPU compile runs in the background while readings are solved by the
        kernels run as Python (:meth:`torchrod.kernels.targets.Compiled.start`), unless ``wait`` (then this waits
        for it, as a benchmark needs)."""
        opts = self.options if options is None else options
        target = self._target(opts, torch.device(device))
        key = (opts, tuple(guess_counts), target)
        with self._lock:
            plan = self._plans.get(key)
            if plan is None:
                from ..kernels.host import Plan, count_tables, rod_setup, setup_of
                from ..kernels.march import EXACT_MAX_STEPS, EXACT_STEP_ANGLE, FIT_MAX_STEPS
                from ..model.nystrom import RKN8

                rod = self.rod
                rec, model = rod_setup(
                    length=rod.length,
                    ei=rod.bending_stiffness,
                    gj=rod.torsion_stiffness,
                    bias=rod.location_bias,
                    gratings=rod.gratings,
                    segments=rod.intrinsic_curvature if rod.precurved else (),
                    breakpoints=rod.breakpoints() if rod.precurved else (),
                    step_angle=opts.max_step_angle,
                    max_steps=FIT_MAX_STEPS,
                    exact_angle=EXACT_STEP_ANGLE,
                    exact_max_steps=EXACT_MAX_STEPS,
                    method=RKN8,
                )
                record = opts.record()
                tables = count_tables(
                    rod.num_gratings,
                    int(record[0].max_forces),
                    opts.significance,
                    opts.search.suspect,
                    opts.search.kink_suspect,
                    opts.misfit_level,
                )
                setup, sizes = setup_of(rec, model, record, tables, guess_counts)
                plan = Plan(target, setup, sizes)
                if len(self._plans) > 32:
                    self._plans.clear()
                self._plans[key] = plan
                if plan.compiled not in self._compiled:
                    self._compiled.append(plan.compiled)
        if wait:
            plan.compiled.ready()
        else:
            plan.compiled.start()
        return plan

    def compiling(self) -> bool:
        """Whether a first compile of the CPU kernels is still running in the background (:meth:`plan`): readings
        are then solved one at a time, much more slowly, with the same answers."""
        return any(compiled.compiling() for compiled in self._compiled)

    def kit(self, curvature: torch.Tensor, mask: torch.Tensor | None = None, options: EstimatorOptions | None = None):
        """The kernels' :class:`~torchrod.kernels.layout.Kit` of one reading (curvature (G, 2) [1/m], mask (G,)), for
        calling kernel functions one by one as Python (debugging, tests); noise as ``options`` say."""
        from ..kernels.host import kit

        opts = self.options if options is None else options
        curvature, mask = self._check(curvature[None], None if mask is None else mask[None])
        plan = self.plan(dataclasses.replace(opts, target="python"))
        u, w, _ = self._kernel_readings(curvature.cpu(), mask.cpu(), opts)
        return kit(plan.setup, plan.sizes, u[0], w[0], opts.noise2)

    # ------------------------------------------------------------------ the method
    def estimate(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor | None = None,
        *,
        options: EstimatorOptions | None = None,
        extra_starts: Mapping[int, PointForces] | None = None,
        bending_stiffness: float | torch.Tensor | None = None,
        location_bias: float | torch.Tensor | None = None,
        _checked: bool = False,
    ) -> EstimateResult:
        """Estimate the forces behind B readings.

        The forces and locations are differentiable (:mod:`torchrod.estimate.implicit`, through the optimum, with
        no unrolling): in the readings when ``curvature`` requires grad, in the stiffness and the location bias
        when they are given as tensors that do. The count, the status and the other fields carry no gradient;
        ``loss`` has its gradient in the readings too.

        Args:
            curvature: (B, G, 2) measured (u_x, u_y) at the rod's gratings [1/m]; values at missing gratings are
                ignored (may be NaN).
            mask: (B, G) bool, True where the grating was read; None: the finite entries.
            options: :class:`EstimatorOptions` for this call (default: the estimator's).
            extra_starts: {h: PointForces (B, h)} additional starting guesses in REPORTED coordinates (as in
                :attr:`EstimateResult.forces`, so a previous solution can be passed as is); a row whose forces are
                not all finite starts from no load instead; counts that are not fitted are ignored.
            bending_stiffness: EI [N m^2] for these readings instead of the rod's: a number, or a tensor () or (B,)
                (the rod's torsional stiffness scales with it). Exact by the scaling law of the rod's equations:
                the estimate at EI0 with every force (and its standard deviation) times EI / EI0.
            location_bias: the location bias [m] for these readings instead of the rod's: a number, or a tensor
                () or (B,); reported locations are ``s_model + location_bias``.
        Returns:
            :class:`EstimateResult` in ``curvature``'s dtype and device (computed in float64).
        """
        opts = self.options if options is None else options
        if not isinstance(opts, EstimatorOptions):
            raise TorchrodTypeError(f"options must be EstimatorOptions, got {type(opts).__name__}")
        if not _checked or mask is None:  # (a stream's readings, each checked as it was read, are not again)
            curvature, mask = self._check(curvature, mask)
        B = curvature.shape[0]
        ei = _per_reading("bending_stiffness", bending_stiffness, B, curvature, positive=True)
        bias = _per_reading("location_bias", location_bias, B, curvature, positive=False)
        tracked = torch.is_grad_enabled() and any(
            isinstance(x, torch.Tensor) and x.requires_grad for x in (curvature, bending_stiffness, location_bias)
        )
        if ei is None and bias is None and not tracked:
            return self._estimate(curvature, mask, opts, extra_starts, curvature.dtype)
        if extra_starts and (ei is not None or bias is not None):  # the caller's starts at the rod's own values
            extra_starts = {
                h: self._own_values(pf, ei, bias) for h, pf in extra_starts.items() if isinstance(pf, PointForces)
            }
        base = self._estimate(curvature.detach(), mask, opts, extra_starts, torch.float64)
        return self._differentiable(base, curvature, mask, opts, ei, bias)

    def _own_values(self, pf: PointForces, ei: torch.Tensor | None, bias: torch.Tensor | None) -> PointForces:
        """Starts given at the stiffness ``ei`` (B,) and bias ``bias`` (B,), moved to the rod's own values."""
        s, f = pf.s.detach(), pf.f.detach()
        if bias is not None:
            s = s - bias.detach().to(s.dtype)[:, None] + self.rod.location_bias
        if ei is not None:
            f = f * (self.rod.bending_stiffness / ei.detach().to(f.dtype))[:, None, None]
        return PointForces(s, f, pf.mask)

    def _differentiable(
        self,
        base: EstimateResult,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        ei: torch.Tensor | None,
        bias: torch.Tensor | None,
    ) -> EstimateResult:
        """``base`` (float64, at the rod's stiffness and bias) at the given stiffness and bias, its forces and
        loss differentiable as :meth:`estimate` says, in ``curvature``'s dtype."""
        rod = self.rod
        active = base.forces.active
        s, f, loss = base.forces.s - rod.location_bias, base.forces.f, base.loss
        if torch.is_grad_enabled() and curvature.requires_grad:
            u = self._filled(curvature, mask, opts)
            weights = self._weights(curvature.detach(), mask, opts)  # held fixed, as the kernels hold them
            present = mask if weights is None else torch.where(mask[..., None], weights.to(u.device), 0.0)
            s, f = implicit.through_optimum(rod, u, present, s, f, active, opts.max_step_angle)
            theta = torch.cat([s.detach()[..., None], f.detach()], dim=-1)
            again = implicit.fit_loss(rod, theta, active, u, present, opts.max_step_angle)
            loss = loss + (again - again.detach())  # the loss's value, its gradient (the envelope theorem)
        std = base.std
        if ei is not None:
            scale = ei / rod.bending_stiffness
            f = f * scale[:, None, None]
            std = torch.cat([std[..., :1], std[..., 1:] * scale.detach()[:, None, None]], dim=-1)
        s = s + (bias[:, None] if bias is not None else rod.location_bias)
        s = torch.where(active, s, base.forces.s)
        f = torch.where(active[..., None], f, base.forces.f)
        result = dataclasses.replace(base, forces=PointForces(s, f, active), loss=loss, std=std)
        return _in_dtype(result, curvature.dtype)

    def _filled(self, curvature: torch.Tensor, mask: torch.Tensor, opts: EstimatorOptions) -> torch.Tensor:
        """(B, G, 2) float64 readings [1/m] as the torch model is fitted to them: zero at missing gratings, a
        precurved rod's unloaded shape added back to ``relative`` readings; differentiable in ``curvature``."""
        u = torch.where(mask[..., None], curvature.to(torch.float64), 0.0)
        if opts.relative and self.rod.precurved:
            u = u + self.rod.unloaded_curvature(torch.float64, u.device)
        return u

    def _estimate(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        extra_starts: Mapping[int, PointForces] | None,
        out_dtype: torch.dtype,
        network: bool = True,
    ) -> EstimateResult:
        """:meth:`estimate` of checked readings at the rod's own stiffness and bias, without gradients (with
        ``network`` False, the warm start's guesses are left out: only ``extra_starts``)."""
        gpu_default = opts.target == "auto" and curvature.device.type == "cuda"
        if opts.target == "torch" or (gpu_default and (self.warm_start is not None or bool(extra_starts))):
            return self._estimate_torch(curvature, mask, opts, extra_starts, out_dtype)
        device = curvature.device
        B, G = mask.shape
        W = opts.width
        u, w, noise2 = self._kernel_readings(curvature, mask, opts)
        blocks = self._guesses(curvature, mask, opts, extra_starts, network)
        counts = [h for h, _, _, _ in blocks]
        if opts.starts == 0:
            needed = set(opts.counts) - {0}
            missing = sorted(needed - set(counts))
            if missing:
                raise OptionsError(
                    f"no start for h = {missing[0]}: starts=0 needs a warm start or extra_starts for every count"
                )
        plan = self.plan(opts, counts, device)  # compiled before the clock starts
        began = time.perf_counter()
        H = max(W, 1)
        K = max(len(blocks), 1)
        gs, gf, guse = _zeros(device, ((B, K, H), torch.float64), ((B, K, H, 2), torch.float64), ((B, K), torch.bool))
        for k, (h, s, f, use) in enumerate(blocks):
            gs[:, k, :h] = _host(s)
            gf[:, k, :h] = _host(f)
            guse[:, k] = _host(use)
        out = _outputs(B, W, device)
        flag = np.zeros(1, np.int64)
        alarm = None
        if opts.time_budget is not None and plan.target != "cuda" and not plan.compiled.compiling():
            alarm = _ALARMS.arm(began + B * opts.time_budget, flag)
        try:
            batch = _batch(u, w, noise2, gs, gf, guse, out, plan.target)
            gpu = (
                device.index
                if device.index is not None
                else (torch.cuda.current_device() if device.type == "cuda" else 0)
            )
            plan.run(batch, flag, opts.threads, gpu)
        finally:
            if alarm is not None:
                _ALARMS.cancel(alarm)
        return self._report(out, mask, opts, out_dtype)

    def _kernel_readings(self, curvature: torch.Tensor, mask: torch.Tensor, opts: EstimatorOptions) -> tuple[Any, ...]:
        """The kernels' readings of checked ``curvature`` (B, G, 2) [1/m] and ``mask`` (B, G): u (B, 2G) float64
        [1/m] (zero at a missing grating; a precurved rod's unloaded shape added back to ``relative`` readings), w
        (B, 2G) the weights of the values (:meth:`_weights`; 0 where missing), noise2 (B,) (``opts.noise2``); NumPy
        arrays for a CPU batch (cheaper than torch's operations on a few readings), tensors on curvature's device
        otherwise."""
        B, G = mask.shape
        values, present = host_view(curvature.to(torch.float64)), host_view(mask)
        weights = self._weights(curvature, mask, opts)
        if opts.relative and self.rod.precurved:  # readings of the change from the unloaded shape: add it back
            values = values + host_view(self.rod.unloaded_curvature(torch.float64, curvature.device))
        if isinstance(values, np.ndarray):
            w = np.repeat(present, 2, axis=1).astype(np.float64)
            if weights is not None:
                w = w * host_view(weights).reshape(B, 2 * G)
            return (
                np.where(present[:, :, None], values, 0.0).reshape(B, 2 * G),
                w,
                np.full(B, opts.noise2),
            )
        w = present.repeat_interleave(2, dim=1).to(torch.float64)
        if weights is not None:
            w = w * weights.reshape(B, 2 * G)
        return (
            torch.where(present[:, :, None], values, 0.0).reshape(B, 2 * G),
            w,
            torch.full((B,), opts.noise2, device=curvature.device, dtype=torch.float64),
        )

    def _weights(self, curvature: torch.Tensor, mask: torch.Tensor, opts: EstimatorOptions) -> torch.Tensor | None:
        """(B, G, 2) float64 the weights of a rod's calibration error (``Rod.calibration_error``), None without one
        or with the noise unknown.

        A value u_k of relative calibration error rel_k carries ``sigma_k^2 = sigma^2 + (rel_k |u_k|)^2`` (the
        measured value: the weights are fixed per reading), and its residual is weighed by ``sigma / sigma_k``: the
        loss stays in the units of the sensor's sigma^2 (``opts.noise2``, the floor included), so every test of the
        kernels reads it as it reads an unweighted one. With the noise unknown there is no sigma to weigh against
        (one sigma per reading cannot be split into the sensor's and the calibration's parts): the values keep
        equal weights and the per-reading sigma takes in the calibration error too."""
        if not self.rod.calibration_error or opts.noise is None:
            return None
        model = self.rod.calibration_variance(torch.where(mask[..., None], curvature.to(torch.float64), 0.0))
        return (opts.noise2 / (opts.noise2 + model)).sqrt()

    def _estimate_torch(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        extra_starts: Mapping[int, PointForces] | None,
        out_dtype: torch.dtype,
    ) -> EstimateResult:
        """``target="torch"`` (:mod:`torchrod.estimate.refine`): each count's starts refined in torch on the readings'
        device; the kernels then fit from the refined fits alone and judge them; a reading not answered ``ok``
        is searched again by the full compiled search. Every evaluation is counted."""
        rod = self.rod
        device = curvature.device
        B = mask.shape[0]
        # Every count's guesses, however improbable the network finds the count: each count is fitted from them.
        blocks = self._guesses(
            curvature, mask, dataclasses.replace(opts, guess_probability=0.0, trust_guesses=False), extra_starts
        )
        needed = [h for h in opts.counts if h > 0]
        missing = sorted(set(needed) - {h for h, _, _, _ in blocks})
        if missing:
            raise OptionsError(
                f"target 'torch' refines starts, and none is given for h = {missing[0]}: give the estimator a "
                "warm start (torchrod.load_estimator) or extra_starts for every count"
            )
        u = self._filled(curvature, mask, opts)
        sigma2 = opts.noise2 if opts.noise is not None else float(opts.noise_floor) ** 2
        spent = torch.zeros(B, dtype=torch.long, device=device)
        starts: dict[int, PointForces] = {}
        for h in needed:
            best_s = torch.full((B, h), math.nan, dtype=torch.float64, device=device)
            best_f = torch.zeros((B, h, 2), dtype=torch.float64, device=device)
            best_loss = torch.full((B,), math.inf, dtype=torch.float64, device=device)
            for hh, s, f, use in blocks:
                if hh != h:
                    continue
                s, f, use = (torch.as_tensor(x, device=device) for x in (s, f, use))
                rows = use & torch.isfinite(s).all(1) & torch.isfinite(f).all(1).all(1)
                idx = rows.nonzero().squeeze(1)
                if idx.numel() == 0:
                    continue
                fit = refine.refine(
                    rod, u[idx], mask[idx], s[idx].to(torch.float64), f[idx].to(torch.float64),
                    sigma2=sigma2, lm=opts.lm, step_angle=opts.max_step_angle,
                )  # fmt: skip
                spent[idx] += fit.evaluations
                better = fit.loss < best_loss[idx]
                best_s[idx] = torch.where(better[:, None], fit.s, best_s[idx])
                best_f[idx] = torch.where(better[:, None, None], fit.f, best_f[idx])
                best_loss[idx] = torch.where(better, fit.loss, best_loss[idx])
            starts[h] = PointForces(best_s + rod.location_bias, best_f)
        # The kernels, on the CPU: the refined fits as their only (trusted) starts, then the full search where the
        # verdict is not clean.
        host = torch.device("cpu")
        c, m = curvature.to(host), mask.to(host)
        kernel_opts = dataclasses.replace(opts, target="auto", starts=0, trust_guesses=True)
        on_host = {h: pf.to(device=host) for h, pf in starts.items()}
        result = self._estimate(c, m, kernel_opts, on_host, out_dtype, network=False)
        result = dataclasses.replace(result, evaluations=result.evaluations + spent.to(host))
        again = (result.status != Status.OK.code).nonzero().squeeze(1)
        if again.numel():
            sub = None if not extra_starts else {h: pf[again] for h, pf in extra_starts.items()}
            full = self._estimate(c[again], m[again], dataclasses.replace(opts, target="auto"), sub, out_dtype)
            full = dataclasses.replace(full, evaluations=full.evaluations + result.evaluations[again])
            result = _spliced(result, again, full)
        return _to_device(result, device)

    # ------------------------------------------------------------------ stages
    def _guesses(
        self,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        extra_starts: Mapping[int, PointForces] | None,
        network: bool = True,
    ) -> list[tuple[int, Any, Any, Any]]:
        """The starts other than the scan's, per count 1..top, as blocks (h, s (B, h) [m] in model coordinates, f
        (B, h, 2) [N], use (B,) bool; tensors, or NumPy arrays from the network's compiled pass): the caller's
        ``extra_starts`` (location bias removed), then the warm start's guesses (used where the network gives the
        count at least ``guess_probability``)."""
        B = curvature.shape[0]
        top = opts.width
        device = curvature.device
        out: list[tuple[int, Any, Any, Any]] = []
        per_count: dict[int, list[tuple[Any, Any, Any]]] = {h: [] for h in range(1, top + 1)}

        def everyone() -> torch.Tensor:
            return torch.ones((B,), dtype=torch.bool, device=device)

        def add(h: int, pf: Any, shift: float, use: torch.Tensor) -> None:
            # A block of h forces as the kernels take it: locations shifted to model coordinates, inactive forces
            # NaN (the row then starts from no load). (Operations that would change nothing are left out: at a
            # batch of one reading, each costs more than its arithmetic.)
            pf = self._check_guess(pf, B, h)
            s = pf.s.detach().to(device, torch.float64)
            if shift != 0.0:
                s = s + shift
            f = pf.f.detach().to(device, torch.float64)
            if pf.mask is not None:
                f = torch.where(pf.mask.to(device)[:, :, None], f, torch.full_like(f, math.nan))
            per_count[h].append((s, f, use))

        def gate(probs: Any) -> tuple[Any, list[bool]]:
            # Where each count's guess starts a fit, (B, H) (None: everywhere), and whether it does anywhere, per
            # count: where the network gives the count at least guess_probability (a tensor or a NumPy array).
            # Trusted, only the network's most probable count and the one below it: the kernels fit those alone,
            # and the count tests need the one below.
            if probs is None or opts.starts <= 0 or (opts.guess_probability <= 0 and not opts.trust_guesses):
                return None, []
            if opts.trust_guesses:
                top = probs.argmax(1)[:, None]
                h = (np.arange if isinstance(probs, np.ndarray) else partial(torch.arange, device=device))(
                    probs.shape[1]
                )[None, :]
                likely = (h == top) | (h == top - 1)
            else:
                likely = probs >= opts.guess_probability
            return likely, likely.any(0).tolist()  # (one transfer for every count)

        if extra_starts:
            use = everyone()
            for h, pf in extra_starts.items():
                if h in per_count:
                    add(h, pf, -self.rod.location_bias, use)
        source = self.warm_start if network else None
        if source is not None:
            if device.type == "cpu" and hasattr(source, "compiled_arrays"):
                # The compiled pass's arrays as they are: at a batch of one reading, each torch operation on them
                # would cost more than the network itself.
                probs_np, s_np, f_np = source.compiled_arrays(curvature, mask)
                likely, anyone = gate(probs_np)
                for h in range(1, probs_np.shape[1] + 1):
                    if h in per_count and (h > len(anyone) or anyone[h - 1]):
                        use_np = likely[:, h - 1] if likely is not None else np.ones(B, np.bool_)
                        per_count[h].append((s_np[:, h - 1, :h], f_np[:, h - 1, :h], use_np))
            else:
                net = source.guess(curvature, mask) if hasattr(source, "guess") else source(curvature, mask)
                probs = getattr(net, "count_probs", None)
                likely, anyone = gate(None if probs is None else probs.detach().to(device))
                for h, pf in (net.forces if hasattr(net, "forces") else net).items():
                    if h in per_count and (h > len(anyone) or anyone[h - 1]):
                        use = likely[:, h - 1] if likely is not None and h <= likely.shape[1] else everyone()
                        add(h, pf, 0.0, use)
        for h, found in per_count.items():  # (every block added is used by some reading)
            for s, f, use in found:
                clamp = np.clip if isinstance(s, np.ndarray) else torch.clamp
                out.append((h, clamp(s, 0.0, self.rod.length), f, use))
        return out

    def _report(self, out: Any, mask: torch.Tensor, opts: EstimatorOptions, dtype: torch.dtype) -> EstimateResult:
        """The kernels' outputs (p-values and statuses included) as an :class:`EstimateResult`."""
        t = _tensors(out)
        count = t["count"]
        W = t["s"].shape[1]
        if isinstance(out.count, np.ndarray):  # (NumPy's comparison: cheaper than torch's at a batch of one)
            active = torch.from_numpy(np.arange(W)[None, :] < out.count[:, None])
        else:
            active = torch.arange(W, device=count.device)[None, :] < count[:, None]
        if dtype != torch.float64:  # the kernels' real outputs (float64) in the readings' dtype
            for name, x in t.items():
                if x.dtype == torch.float64:
                    t[name] = x.to(dtype)
        return EstimateResult(
            forces=PointForces(t["s"], t["f"], active),
            num_forces=count,
            status=t["status"],
            p_value=t["p_value"],
            loss=t["loss"],
            converged=t["converged"],
            iterations=t["iterations"],
            std=t["std"],
            poorly_determined=t["poorly"],
            losses_by_count=t["losses"],
            noise=t["sigma"],
            evaluations=t["evaluations"],
        )

    def _check_guess(self, pf: Any, B: int, h: int) -> PointForces:
        if not isinstance(pf, PointForces):
            raise TorchrodTypeError(f"a start for h = {h} must be PointForces, got {type(pf).__name__}")
        if pf.s.shape != (B, h):
            raise OptionsError(f"the starts for h = {h} must have shape (B, h) = {(B, h)}, got {tuple(pf.s.shape)}")
        return pf


class _Alarms:
    """One daemon thread that sets the kernels' stop flags when their batches' time budgets run out.

    A thread per call (:class:`threading.Timer`) costs more than solving one reading: starting one waits until the
    new thread runs. Here a call only adds its deadline to a heap. The thread sleeps until the earliest deadline in
    it; a cancelled alarm stays in the heap until it comes first and is then dropped, so the thread wakes about
    once per budget, not once per call.
    """

    def __init__(self) -> None:
        self._wake = threading.Condition()
        self._heap: list[list[Any]] = []  # [deadline (perf_counter s), order, flag or None once cancelled]
        self._order = 0
        self._until = math.inf  # the deadline the thread sleeps until
        self._thread: threading.Thread | None = None

    def arm(self, deadline: float, flag: np.ndarray) -> list[Any]:
        """Set ``flag`` to 1 at ``deadline`` (``time.perf_counter`` seconds), at once if it has passed (before the
        kernels start); the alarm, for :meth:`cancel`."""
        if deadline <= time.perf_counter():
            flag.fill(1)
            return [deadline, 0, None]
        with self._wake:
            self._order += 1
            alarm = [deadline, self._order, flag]
            heapq.heappush(self._heap, alarm)
            if self._thread is None or not self._thread.is_alive():  # (none yet, or a forked child's copy)
                self._thread = threading.Thread(target=self._run, daemon=True, name="torchrod-time-budget")
                self._until = math.inf
                self._thread.start()
            elif deadline < self._until:
                self._wake.notify()
        return alarm

    def cancel(self, alarm: list[Any]) -> None:
        """The alarm will not fire (its flag is left as it is)."""
        with self._wake:
            alarm[2] = None

    def _run(self) -> None:
        with self._wake:
            while True:
                heap = self._heap
                now = time.perf_counter()
                while heap and (heap[0][2] is None or heap[0][0] <= now):
                    _, _, flag = heapq.heappop(heap)
                    if flag is not None:
                        flag.fill(1)
                self._until = heap[0][0] if heap else math.inf
                self._wake.wait(None if not heap else self._until - now)


_ALARMS = _Alarms()


def _outputs(B: int, W: int, device: torch.device) -> Any:
    """The kernels' outputs for B readings of width W: NumPy arrays for the CPU (the kernels' own type there, made
    without torch's dispatch; :func:`_tensors` shares their memory), torch tensors on any other device."""
    if device.type == "cpu":
        return _kernels.outputs(B, W)
    return _kernels.outputs(B, W, lambda shape, dtype: torch.empty(shape, dtype=_TORCH[np.dtype(dtype)], device=device))


_TORCH = {np.dtype(np.float64): torch.float64, np.dtype(np.int64): torch.int64, np.dtype(np.bool_): torch.bool}


def _batch(u, w, noise2, gs, gf, guse, out, target: str) -> Any:
    """The kernels' batch: NumPy views of CPU tensors, or CUDA arrays sharing the tensors' memory."""
    # A CPU batch: the readings (u, w, noise2 made together), the starts (gs, gf, guse) and the outputs NumPy arrays.
    if isinstance(u, np.ndarray) and isinstance(gs, np.ndarray) and isinstance(out.count, np.ndarray):
        return Batch(u, w, noise2, gs, gf, guse, out)
    if target == "cuda" and not _kernels.simulated():
        from numba import cuda

        def view(x: Any) -> Any:
            return cuda.as_cuda_array(x.contiguous())
    else:

        def view(x: Any) -> Any:
            return x if isinstance(x, np.ndarray) else x.contiguous().numpy()

    return Batch(view(u), view(w), view(noise2), view(gs), view(gf), view(guse), type(out)(*(view(x) for x in out)))


def _host(x: Any) -> Any:
    """A start's values for the kernels' arrays: NumPy ones as they are, a tensor as :func:`host_view` gives it."""
    return x if isinstance(x, np.ndarray) else host_view(x)


def _zeros(device: torch.device, *shapes: tuple[tuple[int, ...], torch.dtype]) -> list[Any]:
    """Zero arrays of these (shape, dtype): NumPy ones for the CPU (:func:`_outputs`), tensors on another device."""
    if device.type == "cpu":
        return [np.zeros(shape, _NUMPY[dtype]) for shape, dtype in shapes]
    return [torch.zeros(shape, dtype=dtype, device=device) for shape, dtype in shapes]


_NUMPY = {torch.float64: np.float64, torch.bool: np.bool_}


def _per_reading(
    name: str, value: float | torch.Tensor | None, B: int, like: torch.Tensor, *, positive: bool
) -> torch.Tensor | None:
    """A rod value given per call (:meth:`Estimator.estimate`) as a float64 tensor (B,) on ``like``'s device,
    keeping its gradient; None for None."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, torch.Tensor)):
        raise OptionsError(f"{name} must be a number or a tensor, got {type(value).__name__}")
    t = torch.as_tensor(value, dtype=torch.float64, device=like.device)
    if t.dim() > 1 or (t.dim() == 1 and t.shape[0] not in (1, B)):
        raise OptionsError(f"{name} must be a scalar or have shape (B,) = ({B},), got shape {tuple(t.shape)}")
    bad = ~torch.isfinite(t) | (t <= 0.0) if positive else ~torch.isfinite(t)
    if bool(bad.any()):
        worst = float(t.detach().reshape(-1)[bad.reshape(-1)][0])
        raise OptionsError(f"{name} must be {'positive and ' if positive else ''}finite, got {worst!r}")
    return t.expand(B) if t.dim() == 0 or t.shape[0] == 1 else t


def _spliced(result: EstimateResult, idx: torch.Tensor, rows: EstimateResult) -> EstimateResult:
    """``result`` with its readings ``idx`` replaced by ``rows``'s (in ``result``'s dtypes)."""

    def put(old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        return old.index_put((idx,), new.to(old.dtype))

    fields: dict[str, Any] = {}
    for field in dataclasses.fields(result):
        old, new = getattr(result, field.name), getattr(rows, field.name)
        if isinstance(old, PointForces):
            fields[field.name] = PointForces(put(old.s, new.s), put(old.f, new.f), put(old.active, new.active))
        else:
            fields[field.name] = put(old, new)
    return EstimateResult(**fields)


def _to_device(result: EstimateResult, device: torch.device) -> EstimateResult:
    """``result`` on ``device``."""
    if device.type == "cpu":
        return result
    fields: dict[str, Any] = {}
    for field in dataclasses.fields(result):
        x = getattr(result, field.name)
        fields[field.name] = x.to(device=device)
    return EstimateResult(**fields)


def _in_dtype(result: EstimateResult, dtype: torch.dtype) -> EstimateResult:
    """``result`` with its float64 fields in ``dtype`` (differentiably)."""
    if dtype == torch.float64:
        return result
    fields: dict[str, Any] = {}
    for field in dataclasses.fields(result):
        x = getattr(result, field.name)
        if isinstance(x, PointForces):
            fields[field.name] = PointForces(x.s.to(dtype), x.f.to(dtype), x.mask)
        else:
            fields[field.name] = x.to(dtype) if x.dtype == torch.float64 else x
    return EstimateResult(**fields)


def _tensors(out: Any) -> dict[str, torch.Tensor]:
    """The kernels' outputs by name, as tensors (sharing the memory of NumPy ones)."""
    if isinstance(out.count, np.ndarray):
        return dict(zip(out._fields, map(torch.from_numpy, out), strict=True))
    return dict(zip(out._fields, out, strict=True))


_MEMBERS = tuple(Status)
"""The statuses by code."""
