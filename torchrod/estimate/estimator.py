"""Estimating the contact forces behind FBG curvature readings: the orchestration of one estimate.

For B readings, :meth:`Estimator.estimate`

1. checks the readings (:func:`torchrod.io.readings.check_readings`) and poses the least-squares problem
   (:mod:`.problem`: residuals over the present gratings, each force in its grating interval);
2. fits the counts 0, 1, ..., ``max_forces`` in turn, each from the one below (:mod:`.search`: a scan for where one
   more force helps most, Levenberg-Marquardt fits (:mod:`.lm`) from the best few places and from any network or
   caller guesses, an exchange of forces that sit in a wrong interval); with the noise known, a reading whose
   count is already decided (:func:`.selection.settled`) is not fitted further;
3. chooses the count (:func:`.selection.select_count`; 0 is a count like any other);
4. gives every reading a verdict (:mod:`.status`: ``ok``, ``misfit``, ``unconverged``, ``poorly_determined``,
   ``timeout``) with the chi-square p-value of its fit, and the Gauss-Newton standard deviations
   (:mod:`.uncertainty`); a time budget, when given, cuts the search of the readings it runs out on;
5. reports locations as ``s_model + rod.location_bias``, forces sorted by location, in the input's dtype and
   device.

The work runs on one of two backends (:mod:`torchrod.backend`) with the same code: NumPy on the CPU (a
one-reading estimate is a few hundred small array operations, which cost several times less in NumPy than in
torch; at large batches NumPy's complex arithmetic also measured faster on the CPU than torch's, docs/results.md),
torch on other devices (CUDA). Tests hold the two to the same answers.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..backend import NUMPY, Backend, TorchBackend
from ..io.readings import check_readings
from ..loads import PointForces
from ..model.precurved import Precurved
from ..model.sensitivity import ESTIMATION_STEP_ANGLE
from ..rod import Rod
from . import lm, search
from .problem import Fits, interval_of, make_problem, sided
from .refine import LBFGSOptions
from .selection import MISFIT_FACTOR, RULES, ceilings, chi2_quantile, chi2_survival, select_count, settled
from .status import MISFIT_LEVEL, STATUSES, verdict
from .uncertainty import CONDITION_LIMIT, fit_uncertainty

__all__ = ["DEFAULT_LBFGS", "EstimateResult", "Estimator", "EstimatorOptions"]

DEFAULT_LBFGS = LBFGSOptions(max_iter=10, history_size=10, lr=1.0, tolerance_grad=1e-9, tolerance_change=1e-12)
"""Settings of the L-BFGS refinement of fits the Levenberg-Marquardt budget leaves unconverged."""

_MAX_STEPS = 12  # cap on integrator steps per segment while fitting (far-off trial points need no accuracy)


@dataclass(frozen=True)
class EstimatorOptions:
    """Settings of :class:`Estimator` (all can be overridden per call of :meth:`Estimator.estimate`).

    Attributes:
        max_forces: the largest count considered; the count is chosen among 0..max_forces.
        num_forces: a fixed count instead (0 allowed); the result then holds num_forces slots.
        noise: sensor sigma per curvature component [1/m]; None: estimated per reading (selection F test).
        max_noise: [1/m] with ``noise`` None, the largest sensor sigma the verdict believes: a reading that needs
            more is a misfit (:mod:`.status`).
        selection: ``"noise"`` (significance test, default) or ``"threshold"`` (the paper's rule).
        threshold: the paper's loss threshold [1/m^2] for ``selection="threshold"``.
        significance: alpha of the count tests, before the Bonferroni factor G (:mod:`.selection`).
        misfit_level: the misfit verdict's significance (:mod:`.status`).
        noise_floor: [1/m] added in quadrature to sigma: the least noise any reading is assumed to carry (a
            noise-free reading is not held to a loss of exactly zero; the reported fits use the exact model,
            accurate to ~1e-9 1/m, so this is far above the model's own error).
        starts: scan starts per count (the best intervals for one more force); 0 uses only other starts (a
            warm-start network's, ``extra_starts``).
        settle: with a known noise, stop fitting larger counts of a reading once its count is decided.
        lm: the Levenberg-Marquardt policy (:class:`.lm.LMPolicy`).
        search: scan and exchange settings (:class:`.search.SearchOptions`).
        lbfgs: refinement of fits still unconverged after ``lm.iterations`` steps (:func:`torchrod.lbfgs`).
        max_step_angle: accuracy of the forward model used for fitting (:mod:`torchrod.model.sensitivity`).
        condition_limit: ``poorly_determined`` above this condition number (:mod:`.uncertainty`).
        backend: ``"auto"`` (NumPy on the CPU, torch elsewhere), ``"numpy"`` (CPU only) or ``"torch"``. On a GPU
            the torch backend gives the CPU's answers but, at present, far more slowly than NumPy on the CPU (each
            small operation of the march is a kernel of its own; docs/results.md, "On a GPU").
        trust_guesses: a count with guesses (a warm-start network's, ``extra_starts``) is first fitted from them
            alone; the scan's starts serve only a fit found suspicious (:mod:`.search`). Set by
            :meth:`Estimator.from_checkpoint` when the network's recorded quality is trusted; otherwise guesses
            are starts beside the scan's.
        guess_probability: a warm-start network's guess of h forces starts a fit only for the readings where the
            network gives h at least this probability (its count head); elsewhere it would be one more start for
            a count the reading is unlikely to have (docs/results.md, "Network guesses where the network expects
            them"). 0: every guess is used. Ignored with ``starts=0`` (the guesses are then the only starts) and
            for a warm start that gives no probabilities.
        relative: readings of a precurved rod are the change of curvature from the unloaded shape, u - u*, not the
            total curvature u a fibre that is straight when unstrained reads (no effect on a straight rod).
        time_budget: [s] per reading, None: no limit. A call on B readings stops searching ``B * time_budget``
            after it began; the readings whose search it cut get the best fit found so far and the status
            ``timeout`` (:mod:`.status`). For real time, where an answer late is worth less than an answer
            less sure. It is checked between solver steps (a compiled solve of a few rows: every few steps,
            ``_lm_compiled.STEPS_PER_CHECK`` row steps at most), so a call overruns it by about one step of its
            batch, the exact residual of the fits it keeps and the report (a few ms at one reading per call).
    """

    max_forces: int = 3
    num_forces: int | None = None
    noise: float | None = None
    max_noise: float = 1.0
    selection: str = "noise"
    threshold: float = 3.0
    significance: float = 0.05
    misfit_level: float = MISFIT_LEVEL
    noise_floor: float = 1e-3
    starts: int = 3
    settle: bool = True
    lm: lm.LMPolicy = lm.LMPolicy()
    search: search.SearchOptions = search.SearchOptions()
    lbfgs: LBFGSOptions = DEFAULT_LBFGS
    max_step_angle: float = ESTIMATION_STEP_ANGLE
    condition_limit: float = CONDITION_LIMIT
    backend: str = "auto"
    trust_guesses: bool = False
    guess_probability: float = 0.01
    relative: bool = False
    time_budget: float | None = None

    def __post_init__(self) -> None:
        def integer(name: str, low: int) -> None:
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")

        def number(name: str, ok: Callable[[float], bool], what: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
                raise ValueError(f"{name} must be {what}, got {v!r}")

        integer("max_forces", 0)
        integer("starts", 0)
        if self.num_forces is not None:
            integer("num_forces", 0)
        if self.noise is not None:
            number("noise", lambda v: v >= 0.0, "None or a finite sigma >= 0 [1/m]")
        if self.time_budget is not None:
            number("time_budget", lambda v: v >= 0.0, "None or a finite time >= 0 [s]")
        number("max_noise", lambda v: v > 0.0, "a positive sigma [1/m]")
        if self.selection not in RULES:
            raise ValueError(f"selection must be one of {RULES}, got {self.selection!r}")
        number("threshold", lambda v: v > 0.0, "positive [1/m^2]")
        number("significance", lambda v: 0.0 < v < 1.0, "in (0, 1)")
        number("misfit_level", lambda v: 0.0 < v < 1.0, "in (0, 1)")
        number("noise_floor", lambda v: v >= 0.0, ">= 0 [1/m]")
        number("max_step_angle", lambda v: v > 0.0, "positive")
        number("condition_limit", lambda v: v > 1.0, "above 1")
        number("guess_probability", lambda v: 0.0 <= v < 1.0, "in [0, 1)")
        for name, kind in (("lm", lm.LMPolicy), ("search", search.SearchOptions), ("lbfgs", LBFGSOptions)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be {kind.__name__}, got {type(getattr(self, name)).__name__}")
        if self.backend not in ("auto", "numpy", "torch"):
            raise ValueError(f"backend must be 'auto', 'numpy' or 'torch', got {self.backend!r}")

    @property
    def counts(self) -> list[int]:
        """The counts the choice is among: [num_forces], or 0..max_forces."""
        return [self.num_forces] if self.num_forces is not None else list(range(self.max_forces + 1))

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
        num_forces: (B,) long, the chosen count (0: no contact).
        status: (B,) long, the verdict, an index into :data:`torchrod.estimate.status.STATUSES` (``ok``,
            ``misfit``, ``unconverged``, ``poorly_determined``, ``timeout``; :mod:`.status` says what each means
            and what to do).
        p_value: (B,) the chi-square p-value of the chosen fit's loss (the chance that a correct fit is this bad or
            worse; NaN with no degree of freedom left).
        loss: (B,) loss of the chosen fit: sum over present gratings of squared residuals [1/m^2].
        converged: (B,) bool, the chosen fit stopped on its tolerance.
        iterations: (B,) long, the chosen fit's solver steps.
        std: (B, W, 3) standard deviations of (s [m], f_x [N], f_y [N]); NaN for padding.
        poorly_determined: (B,) bool (:mod:`.uncertainty`).
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
    def statuses(self) -> list[str]:
        """The status names, one per reading."""
        return [STATUSES[int(c)] for c in self.status.tolist()]

    @property
    def ok(self) -> torch.Tensor:
        """(B,) bool: status ``ok``."""
        return self.status == 0

    def __getitem__(self, index: int | slice | torch.Tensor) -> EstimateResult:
        """Select readings along the batch dimension (an int keeps a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        fields = {f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)}
        return EstimateResult(**fields)

    def to_records(self, ids: Sequence[Any] | None = None) -> list[dict[str, Any]]:
        """One JSON-ready dict per reading (the ``torchrod estimate`` output, without ``time_ms``).

        ``{"id", "status", "num_forces", "forces": [{"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"},
        ...] sorted by s, "p_value", "loss", "converged", "iterations", "poorly_determined"}``; SI units; a
        non-finite number is null. ``ids`` default to the batch index.
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
        status = self.statuses
        p = self.p_value.detach().cpu().tolist()
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
                    "status": status[b],
                    "num_forces": int(n[b]),
                    "forces": forces,
                    "p_value": num(p[b]),
                    "loss": num(loss[b]),
                    "converged": bool(conv[b]),
                    "iterations": int(it[b]),
                    "poorly_determined": bool(poor[b]),
                }
            )
        return out


WarmStartLike = Callable[[torch.Tensor, torch.Tensor], Mapping[int, PointForces]]


def _p_values(problem: Any, opts: EstimatorOptions, readings: Any, chosen: Any, loss: Any) -> Any:
    """(n,) the verdict's chi-square p-values of fits of ``chosen`` (n,) forces with ``loss`` (n,) to
    ``readings`` (n,): at the given noise, or (noise unknown) at the largest believed; 0 where the loss is not
    finite (it explains nothing)."""
    xp = problem.xp
    test_sigma2 = (float(opts.noise) if opts.noise is not None else float(opts.max_noise)) ** 2 + problem.floor2
    dof = xp.tolist(problem.residuals[readings] - 3 * chosen)
    p_value = xp.asarray(chi2_survival(xp.tolist(loss / test_sigma2), dof))
    return xp.where(xp.isfinite(loss), p_value, 0.0)


class Estimator:
    """Force estimation for one rod (module docstring: the method).

    Args:
        rod: the rod (length, EI, gratings, location bias).
        options: :class:`EstimatorOptions`.
        warm_start: optional source of extra starts, in MODEL coordinates (no location bias): an object with a
            ``guess(curvature, mask)`` method returning something with a ``forces`` dict {h: PointForces (B, h)}
            (e.g. :class:`torchrod.learn.warm_start.WarmStart`), or a callable ``(curvature, mask) -> {h:
            PointForces}``. Its guesses are starts beside the scan's (``starts`` > 0): a network can add starts,
            never take the search's away.
    """

    def __init__(self, rod: Rod, options: EstimatorOptions = EstimatorOptions(), warm_start: Any = None) -> None:
        if not isinstance(rod, Rod):
            raise TypeError(f"rod must be a Rod, got {type(rod).__name__}")
        if not isinstance(options, EstimatorOptions):
            raise TypeError(f"options must be EstimatorOptions, got {type(options).__name__}")
        if warm_start is not None and not (hasattr(warm_start, "guess") or callable(warm_start)):
            raise TypeError(f"warm_start must have a guess() method or be callable, got {type(warm_start).__name__}")
        self.rod = rod
        self.options = options
        self.warm_start = warm_start

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        rod: Rod,
        options: EstimatorOptions | None = None,
        *,
        warn: Callable[[str], None] | None = None,
    ) -> Estimator:
        """An estimator whose starts include a trained warm-start network's guesses.

        The network is used when its grating layout (positions relative to the length) matches ``rod``'s. A
        checkpoint whose recorded held-back quality says that its guesses alone answer as well as the full search
        (:data:`torchrod.learn.warm_start.TRUST_TOLERANCE`) is trusted: its guesses start the fits alone, and the
        scan serves the fits found suspicious (``trust_guesses``).
        Otherwise the network is said to be weak, once, through ``warn`` (default: a :class:`UserWarning`), and its
        guesses are starts beside the scan's, so it cannot make results worse. When the layout does not match (or the
        file is missing or damaged), the estimator runs without a network and says so, and how to train one.

        Args:
            path: a checkpoint written by :mod:`torchrod.learn.training` (loaded with ``weights_only=True``).
            rod: the rod to estimate on.
            options: estimator settings (default :class:`EstimatorOptions`).
        """
        from ..learn.warm_start import WarmStart, quality_verdict

        say = warn if warn is not None else (lambda m: warnings.warn(m, UserWarning, stacklevel=3))
        options = options if options is not None else EstimatorOptions()
        try:
            ws = WarmStart.load(path, rod)
        except (ValueError, FileNotFoundError, OSError) as exc:
            say(
                f"torchrod: no warm-start network for this rod ({exc}); estimating without one (the scan finds "
                "the starts, slower but as accurate); train one with `torchrod generate` and `torchrod train` "
                "(README, 'The warm-start network')"
            )
            return cls(rod, options)
        weak = quality_verdict(getattr(ws, "meta", {}) or {})
        if weak:
            say(
                f"torchrod: the warm-start network {os.fspath(path)!r} is weak ({weak}); its guesses are used only "
                "beside the scan's starts"
            )
        return cls(rod, dataclasses.replace(options, trust_guesses=not weak), warm_start=ws)

    def stream(self, readings: Any, options: Any = None, **overrides: Any) -> Any:
        """Estimate a stream of readings in order, in latency-bounded batches (:func:`torchrod.io.stream.stream`).

        Args:
            readings: any iterable of :class:`torchrod.io.stream.Reading` (or dicts with ``id``, ``curvature``,
                optional ``t``).
            options: :class:`torchrod.io.stream.StreamOptions` (batch size, latency bound).
            **overrides: :class:`EstimatorOptions` fields for every batch.
        Yields:
            one :class:`torchrod.io.stream.StreamResult` per reading, in input order.
        """
        from ..io.stream import StreamOptions, stream

        return stream(self, readings, options if options is not None else StreamOptions(), **overrides)

    # ------------------------------------------------------------------ input checks
    def _check(self, curvature: Any, mask: Any) -> tuple[torch.Tensor, torch.Tensor]:
        curvature, mask = check_readings(curvature, mask, self.rod.num_gratings)
        if curvature.shape[0] == 0:
            raise ValueError(f"curvature must hold at least one reading, got shape {tuple(curvature.shape)}")
        if not bool(mask.any(dim=1).all()):
            rows = (~mask.any(dim=1)).nonzero().squeeze(1).tolist()
            raise ValueError(f"readings {rows[:10]} have no present grating (mask all False)")
        return curvature, mask

    def _backend(self, opts: EstimatorOptions, B: int, device: torch.device) -> Backend:
        name = opts.backend
        if name == "auto":
            name = "numpy" if device.type == "cpu" else "torch"
        if name == "numpy":
            if device.type != "cpu":
                raise ValueError(f"backend 'numpy' runs on the CPU only, got readings on {device}")
            return NUMPY
        return TorchBackend(device)

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
                :attr:`EstimateResult.forces`, so a previous solution can be passed as is); rows whose forces are
                not all finite are ignored; counts that are not fitted are ignored.
            **overrides: any :class:`EstimatorOptions` field for this call.
        Returns:
            :class:`EstimateResult` in ``curvature``'s dtype and device (computed in float64). A reading that the
            numerics fail on is reported with a status, never raised.
        """
        began = time.perf_counter()
        opts = dataclasses.replace(self.options, **overrides) if overrides else self.options
        curvature, mask = self._check(curvature, mask)
        device, out_dtype = curvature.device, curvature.dtype
        B = curvature.shape[0]
        xp = self._backend(opts, B, device)
        rod = self.rod
        u = curvature.to(torch.float64)
        if opts.relative and rod.precurved:  # readings of the change from the unloaded shape: add the shape back
            u = u + rod.unloaded_curvature(torch.float64, u.device)
        floor2 = float(opts.noise_floor) ** 2
        noise2 = None if opts.noise is None else xp.full((B,), float(opts.noise) ** 2 + floor2)
        present = xp.asarray(mask, "bool")
        problem = make_problem(
            xp,
            rod.length,
            rod.bending_stiffness,
            rod.gratings,
            xp.where(present[:, :, None], xp.asarray(u), 0.0),  # a missing grating's value (NaN, say) never read
            present,
            noise2=noise2,
            floor2=floor2,
            step_angle=opts.max_step_angle,
            max_steps=_MAX_STEPS,
            precurved=Precurved.of(rod) if rod.precurved else None,
        )
        counts = opts.counts
        top = max(counts)
        guesses = self._guesses(problem, curvature, mask, opts, extra_starts, top)
        # A reading the numerics fail on (an overflow, a singular matrix) gets a status, not a warning or an error.
        deadline = None if opts.time_budget is None else began + B * opts.time_budget
        with np.errstate(all="ignore"):
            return self._solve(problem, opts, guesses, counts, top, mask, out_dtype, device, deadline)

    def _solve(self, problem, opts, guesses, counts, top, mask, out_dtype, device, deadline) -> EstimateResult:
        found = search.fit_counts(
            problem,
            search.Solver(opts.lm, opts.lbfgs, deadline),
            opts.search,
            self._rules(problem, opts),
            top_count=top,
            starts=opts.starts,
            guesses=guesses,
            needed=set(counts) - {0},
            trusted=opts.trust_guesses,
        )
        return self._report(problem, opts, found, mask, out_dtype, device)

    # ------------------------------------------------------------------ stages
    def _guesses(
        self,
        problem: Any,
        curvature: torch.Tensor,
        mask: torch.Tensor,
        opts: EstimatorOptions,
        extra_starts: Mapping[int, PointForces] | None,
        top: int,
    ) -> dict[int, list[Fits]]:
        """The starts other than the scan's, per count 1..top, as Fits of B rows in model coordinates: the caller's
        ``extra_starts`` (location bias removed), then the warm start's guesses. A guess that is not finite for a
        reading becomes, for that reading, a force at the middle of its first interval with no load."""
        B = curvature.shape[0]
        xp = problem.xp
        # per count: (the guess, its location shift [m], the readings it starts: None for all)
        found: dict[int, list[tuple[PointForces, float, Any]]] = {h: [] for h in range(1, top + 1)}
        if extra_starts:
            for h, pf in extra_starts.items():
                if h in found:
                    found[h].append((self._check_guess(pf, B, h), -self.rod.location_bias, None))
        if self.warm_start is not None:
            net = (
                self.warm_start.guess(curvature, mask)
                if hasattr(self.warm_start, "guess")
                else self.warm_start(curvature, mask)
            )
            probs = getattr(net, "count_probs", None)
            probs = None if probs is None else xp.asarray(probs.detach())
            for h, pf in (net.forces if hasattr(net, "forces") else net).items():
                if h in found:
                    likely = None
                    if probs is not None and opts.starts > 0 and opts.guess_probability > 0 and h <= probs.shape[1]:
                        likely = probs[:, h - 1] >= opts.guess_probability
                        likely = None if bool(xp.all(likely)) else xp.nonzero(likely)
                    found[h].append((self._check_guess(pf, B, h), 0.0, likely))
        reading = xp.arange(B)
        first = 0.5 * (problem.lo[:, :1] + problem.hi[:, :1])  # (B, 1) the first interval's middle
        out: dict[int, list[Fits]] = {}
        for h, guesses in found.items():
            for pf, shift, rows in guesses:
                if rows is not None and rows.shape[0] == 0:
                    continue
                s = xp.clip(xp.asarray(pf.s.detach()) + shift, lo=0.0, hi=self.rod.length)
                f = xp.asarray(pf.f.detach())
                ok = xp.all(xp.asarray(pf.active, "bool") & xp.isfinite(s) & xp.all(xp.isfinite(f), 2), 1)
                s = xp.where(ok[:, None], s, xp.expand(first, (B, h)))
                f = xp.where(ok[:, None, None], f, 0.0)
                j, s = interval_of(problem, reading, s)
                fits = Fits(reading, s, f, j)
                if rows is not None:
                    fits = fits.take(rows)
                out.setdefault(h, []).append(fits)
        return out

    def _rules(self, problem: Any, opts: EstimatorOptions) -> search.Rules:
        """The search's decisions from the options (:class:`.search.Rules`, :mod:`.selection`)."""
        xp = problem.xp
        G = self.rod.num_gratings
        known = opts.noise is not None
        fixed = opts.num_forces is not None
        tests = dict(
            rule=opts.selection,
            noise=opts.noise,
            threshold=opts.threshold,
            significance=opts.significance,
            floor=opts.noise_floor,
            num_gratings=G,
        )

        def choose(losses: Any) -> Any:
            if fixed:
                return xp.full((losses.shape[0],), opts.num_forces, "int")
            return select_count(xp, losses, list(range(losses.shape[1])), problem.residuals, **tests)[0]

        def settle(losses: Any, readings: Any, gain: Any) -> Any:
            counts = list(range(losses.shape[1]))
            return settled(xp, losses, counts, problem.residuals[readings], gain, **tests)

        def quantile(p: float, h: int, readings: Any) -> Any:
            """The p-quantile of a correct h-force fit's loss at the noise (given, or unknown: the floor)."""
            n = xp.tolist(problem.residuals[readings])
            q = xp.asarray([chi2_quantile(p, int(k) - 3 * h) for k in n])
            return q * (problem.noise2[readings] if known else problem.floor2)

        def suspect(h: int, readings: Any) -> tuple[Any, Any]:
            return quantile(opts.search.suspect, h, readings), quantile(opts.search.kink_suspect, h, readings)

        def plausible(readings: Any, losses: Any) -> Any:
            # Within `hopeless` times the loss each count needs to be chosen (its ceiling, given the larger counts'
            # fits), and of the misfit guard's quantile at the noise (given, or unknown: the floor).
            counts = list(range(losses.shape[1]))
            ceiling = ceilings(xp, losses, counts, problem.residuals[readings], **tests)
            level = 1.0 - opts.significance / MISFIT_FACTOR
            guard = xp.stack([quantile(level, h, readings) for h in counts], 1)
            return opts.search.hopeless * xp.lib.minimum(guard, ceiling)

        def doubtful(state: Any) -> Any:
            n, h = state.fits.s.shape
            if known:
                sigma = xp.lib.sqrt(problem.noise2[state.fits.reading])
            else:
                dof = xp.clip(xp.astype(problem.residuals[state.fits.reading] - 3 * h, "float"), lo=1.0)
                sigma = xp.lib.sqrt(state.loss / dof + problem.floor2)
            unc = fit_uncertainty(
                problem,
                state.fits,
                xp.ones((n, h), "bool"),
                sided(problem, state.fits, state.J),
                sigma,
                condition_limit=opts.condition_limit,
            )
            return unc.poorly_determined

        def unexplained(readings: Any, chosen: Any, loss: Any) -> Any:
            return _p_values(problem, opts, readings, chosen, loss) < opts.misfit_level  # the verdict's misfit

        return search.Rules(
            choose=choose,
            doubtful=doubtful,
            unexplained=unexplained,
            settled=settle if (opts.settle and not fixed and opts.starts > 0) else None,
            suspect=suspect,
            plausible=plausible,
        )

    def _report(
        self,
        problem: Any,
        opts: EstimatorOptions,
        found: search.CountFits,
        mask: torch.Tensor,
        out_dtype: torch.dtype,
        device: torch.device,
    ) -> EstimateResult:
        """The chosen count, its fit in reported form, the verdict and the uncertainty."""
        xp = problem.xp
        rod = self.rod
        B = problem.batch_size
        G = rod.num_gratings
        counts, W = opts.counts, opts.width
        nan = math.nan
        losses = xp.stack([found.states[h].loss for h in counts], 1)  # (B, C)
        if len(counts) > 1:
            chosen, sigma = select_count(
                xp,
                losses,
                counts,
                problem.residuals,
                rule=opts.selection,
                noise=opts.noise,
                threshold=opts.threshold,
                significance=opts.significance,
                floor=opts.noise_floor,
                num_gratings=G,
            )
        else:
            # The fixed count, or where the time budget cut the search before it, the largest count fitted (the
            # best answer so far: never a fit that was not made).
            chosen = xp.zeros((B,), "int")
            for h in range(counts[0] + 1):
                chosen = xp.where(found.fitted[h], h, chosen)
            if opts.noise is not None:
                sigma = xp.full((B,), math.sqrt(float(opts.noise) ** 2 + problem.floor2))
        # The chosen fits, padded to W forces.
        s = xp.zeros((B, W))
        f = xp.zeros((B, W, 2))
        interval = xp.zeros((B, W), "int")
        J = xp.zeros((B, 2 * G, 3 * W))
        loss = xp.zeros((B,)) + nan
        converged = xp.zeros((B,), "bool")
        steps = xp.zeros((B,), "int")
        for h in set(xp.tolist(chosen)):
            at = xp.nonzero(chosen == h)
            st = found.states[h].take(xp, at)
            if h:
                s[at, :h] = st.fits.s
                f[at, :h] = st.fits.f
                interval[at, :h] = st.fits.interval
                J[at, :, : 3 * h] = sided(problem, st.fits, st.J)
            loss[at] = st.loss
            converged[at] = st.converged
            steps[at] = st.steps
        if len(counts) == 1 and opts.noise is None:  # the noise from the fit's own loss
            dof = xp.clip(xp.astype(problem.residuals - 3 * chosen, "float"), lo=1.0)
            sigma = xp.lib.sqrt(xp.clip(loss / dof, lo=0.0) + problem.floor2)
        active = xp.arange(W)[None, :] < chosen[:, None]
        unc = fit_uncertainty(
            problem,
            Fits(xp.arange(B), s, f, interval),
            active,
            J,
            sigma,
            condition_limit=opts.condition_limit,
        )
        p_value = _p_values(problem, opts, xp.arange(B), chosen, loss)
        converged = converged & xp.isfinite(loss)
        status = verdict(xp, p_value, converged, unc.poorly_determined, opts.misfit_level, found.cut)

        # Reported form: sorted by location (padding, and a location that is not a number, last), the location bias
        # added, then in the input's dtype and device.
        order = xp.argsort_desc(xp.where(active & (s == s), -s, -math.inf))
        act = xp.take(active, order, 1)
        s_rep = xp.where(act, xp.take(s, order, 1) + rod.location_bias, 0.0)
        f_rep = xp.where(act[:, :, None], xp.take(f, xp.expand(order[:, :, None], (B, W, 2)), 1), 0.0)
        std = xp.where(act[:, :, None], xp.take(unc.std, xp.expand(order[:, :, None], (B, W, 3)), 1), nan)
        by_count = xp.full((B, W + 1), nan)
        by_count[:, list(counts)] = losses

        def to(x):
            return xp.to_torch(x, device)

        def cast(x):
            return to(x).to(out_dtype)

        return EstimateResult(
            forces=PointForces(cast(s_rep), cast(f_rep), to(act)),
            num_forces=to(chosen).long(),
            status=to(status).long(),
            p_value=cast(p_value),
            loss=cast(loss),
            converged=to(converged),
            iterations=to(steps).long(),
            std=cast(std),
            poorly_determined=to(unc.poorly_determined),
            losses_by_count=cast(by_count),
            noise=cast(sigma),
            evaluations=to(found.evaluations).long(),
        )

    def _check_guess(self, pf: Any, B: int, h: int) -> PointForces:
        if not isinstance(pf, PointForces):
            raise TypeError(f"a start for h = {h} must be PointForces, got {type(pf).__name__}")
        if pf.s.shape != (B, h):
            raise ValueError(f"the starts for h = {h} must have shape (B, h) = {(B, h)}, got {tuple(pf.s.shape)}")
        return pf
