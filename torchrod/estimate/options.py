"""The estimator's options, as frozen dataclasses validated on construction, and their one mapping to the kernels'
record (:data:`torchrod.kernels.layout.OPTIONS`).

:class:`EstimatorOptions` holds everything; :class:`LMPolicy` (the Levenberg-Marquardt policy of every fit) and
:class:`SearchOptions` (the scan and the wider search) are its parts. What each setting does is said where the
kernels use it (:mod:`torchrod.kernels.fit`, :mod:`torchrod.kernels.search`, :mod:`torchrod.kernels.counts`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from ..errors import OptionsError
from ..kernels.counts import PAPER_THRESHOLD, RULE_NOISE, RULE_THRESHOLD
from ..kernels.layout import OPTIONS
from ..kernels.march import FIT_STEP_ANGLE
from ..rod import MIN_TEST_DOF, max_testable_forces
from ..values import MAX_CURVATURE
from .status import MISFIT_LEVEL

__all__ = [
    "MISFIT_LEVEL",
    "RULES",
    "TARGETS",
    "EstimatorOptions",
    "LMPolicy",
    "SearchOptions",
    "default_max_forces",
]

RULES = ("noise", "threshold")
"""The count rules: the significance tests at the noise (default), or the paper's loss threshold."""

TARGETS = ("auto", "cpu", "cuda", "python", "torch")
"""Where the kernels run: ``auto`` follows the readings' device (CUDA readings: ``torch`` where the estimator has
starts to refine, a warm start or ``extra_starts``, so no CUDA compile is waited for; else ``cuda``); ``python``
runs their source uncompiled (slow; the same answers, for debugging); ``torch`` refines the starts (a warm start's
guesses, or the caller's) in torch on the readings' device, with no compile step, and hands the refined fits to the
CPU kernels, which judge them and search the readings they do not answer ``ok`` (:mod:`torchrod.estimate.refine`)."""

CONDITION_LIMIT = 1e8
"""Default limit on the condition number of a fit's unit-diagonal Gauss-Newton matrix (poorly determined above)."""


def _integer(obj: Any, name: str, low: int) -> None:
    v = getattr(obj, name)
    if not isinstance(v, int) or isinstance(v, bool) or v < low:
        raise OptionsError(f"{name} must be an integer >= {low}, got {v!r}")


def _number(obj: Any, name: str, ok: Callable[[float], bool], what: str, finite: bool = True) -> None:
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (finite and not math.isfinite(v)) or not ok(v):
        raise OptionsError(f"{name} must be {what}, got {v!r}")


@dataclass(frozen=True)
class LMPolicy:
    """The Levenberg-Marquardt policy of every fit (:mod:`torchrod.kernels.fit`).

    Attributes:
        damping: lambda at the start of a fit.
        increase: lambda is multiplied by this after a rejected step, and kept in [``min_damping``,
            ``max_damping``]; at ``max_damping`` the fit stops (stalled).
        decrease: lambda is divided by this after an accepted step.
        max_force_step: the largest change of a force component per step [EI / L^2].
        tolerance: converged when the Gauss-Newton decrement is at most ``tolerance`` x sigma^2.
        iterations: at most this many steps per fit.
        refine_iterations: the chosen fit, where ``iterations`` left it open (not converged, not stalled), takes at
            most this many more steps from where it stands (0: none).
        exact_steps: Gauss-Newton steps on the exact model's residual after convergence, each taken only where it
            promises more than ``exact_tolerance`` x sigma^2.
        acceleration: add the geodesic acceleration to a step when the previous one lowered the loss by less than
            this fraction of what its Gauss-Newton model promised (None: never); ``probe``: its finite-difference
            step, a fraction of the step; ``acceleration_limit``: the largest ratio 2 |a| / |v| it is taken at.
    """

    damping: float = 1e-3
    increase: float = 4.0
    decrease: float = 3.0
    min_damping: float = 1e-9
    max_damping: float = 1e9
    max_force_step: float = 10.0
    tolerance: float = 1e-3
    iterations: int = 30
    refine_iterations: int = 100
    exact_steps: int = 3
    exact_tolerance: float = 1e-4
    acceleration: float | None = 0.5
    probe: float = 0.1
    acceleration_limit: float = 0.75

    def __post_init__(self) -> None:
        for name in ("damping", "increase", "decrease", "min_damping", "max_damping", "max_force_step", "tolerance"):
            _number(self, name, lambda v: v > 0.0, "a positive number")
        if not (self.increase > 1.0 and self.decrease > 1.0):
            raise OptionsError(f"increase and decrease must exceed 1, got {self.increase!r}, {self.decrease!r}")
        for name in ("iterations", "refine_iterations", "exact_steps"):
            _integer(self, name, 0)
        _number(self, "exact_tolerance", lambda v: v > 0.0, "a positive number")
        if self.acceleration is not None:
            _number(self, "acceleration", lambda v: v > 0.0, "None or a positive fraction")
        _number(self, "probe", lambda v: v > 0.0, "a positive fraction")
        _number(self, "acceleration_limit", lambda v: v > 0.0, "a positive ratio")


@dataclass(frozen=True)
class SearchOptions:
    """How the fits of each count are started and searched further (:mod:`torchrod.kernels.search`).

    Attributes:
        per_interval: scan candidates per grating interval.
        exchange_top: re-placements tried per exchange round: those the scan promises the lowest loss from, over
            every removed force.
        rounds: at most this many exchange rounds per count.
        explore: steps a start of the wider search takes before it is dropped, unless its loss has fallen below
            the fit it tries to beat (then it is fitted to the end).
        suspect: a fit with known noise is searched further when its loss exceeds this quantile of the chi-square
            law of a correct fit's loss.
        kink_suspect: the same as ``suspect``, for a fit with a force on a grating.
        hopeless: a count below the chosen one is searched further only when its loss is within this many times
            the loss it needs to pass the count tests, or when ``explained`` lets it.
        explained: a count below the chosen one is also searched further when its loss is below this many times
            the loss of the count under it (it explains nearly all of that one's misfit).
        twins: stop a row that another row of the same reading has joined in the same intervals with a lower loss,
            and a start of the wider search that reaches the intervals of the fit it is to beat without a lower
            loss (False: only the one-force case, which always holds).
        escape_turning: with the count fixed to h >= 1, a fit that misfits a reading turning the rod by more than
            this [rad] (the integral of the bend's |u| along the rod) is searched once more through h + 1 forces,
            whose fit less its weakest force starts h again (:func:`torchrod.kernels.search.escape`): at a large
            bend the search of h forces alone can end in a wrong minimum. ``math.inf``: never.
    """

    per_interval: int = 2
    exchange_top: int = 2
    rounds: int = 2
    explore: int = 8
    suspect: float = 0.95
    kink_suspect: float = 0.5
    hopeless: float = 3.0
    explained: float = 0.01
    twins: bool = True
    escape_turning: float = math.pi / 2

    def __post_init__(self) -> None:
        for name in ("per_interval", "exchange_top", "explore"):
            _integer(self, name, 1)
        _integer(self, "rounds", 0)
        for name in ("suspect", "kink_suspect"):
            _number(self, name, lambda v: 0.0 < v < 1.0, "in (0, 1)")
        _number(self, "hopeless", lambda v: v >= 1.0, ">= 1")
        _number(self, "explained", lambda v: v >= 0.0, ">= 0")
        _number(self, "escape_turning", lambda v: v > 0.0, "a positive angle [rad] or math.inf", finite=False)
        if not isinstance(self.twins, bool):
            raise OptionsError(f"twins must be True or False, got {self.twins!r}")


@dataclass(frozen=True)
class EstimatorOptions:
    """Settings of :class:`torchrod.Estimator`.

    Attributes:
        max_forces: the largest count considered; the count is chosen among 0..max_forces, and only among the counts
            a reading can test: a fit leaving fewer than :data:`torchrod.rod.MIN_TEST_DOF` degrees of freedom in
            the reading's values (2 per present grating) is never chosen (:mod:`torchrod.kernels.counts`). An
            estimator made without options takes :func:`default_max_forces` of its rod.
        num_forces: a fixed count instead (0 allowed); the result then holds num_forces slots.
        noise: sensor sigma per curvature component [1/m]; None: estimated per reading (the F test).
        max_noise: [1/m] with ``noise`` None, the largest sensor sigma the verdict believes: a reading that needs
            more is a misfit.
        selection: ``"noise"`` (significance tests, default) or ``"threshold"`` (the paper's rule).
        threshold: the paper's loss threshold [1/m^2] for ``selection="threshold"``.
        significance: alpha of the count tests, before the Bonferroni factor G.
        misfit_level: the misfit verdict's significance.
        merge_patches: a chosen fit holding two forces that the gratings cannot tell from one patch of load (close,
            pushing the same way, the lighter one's moment about the other within what a patch no longer than the
            grating spacing makes) and that the data do not pin down (the fit poorly determined) is answered with
            one force fewer, ``poorly_determined``, or ``misfit`` where one force fewer does not explain the
            reading at the given noise (:func:`torchrod.kernels.counts.unresolved_pair`); the noise rule only.
            False: the count tests alone.
        noise_floor: [1/m] added in quadrature to sigma: the least noise any reading is assumed to carry (a
            noise-free reading is not held to a loss of exactly zero; the reported fits use the exact model,
            accurate to ~1e-9 1/m, far below this).
        starts: scan starts per count (the best intervals for one more force); 0 uses only other starts (a
            warm-start network's, ``extra_starts``).
        settle: with a known noise, stop fitting larger counts of a reading once its count is decided.
        lm: the Levenberg-Marquardt policy (:class:`LMPolicy`).
        search: the scan and the wider search (:class:`SearchOptions`).
        max_step_angle: accuracy of the fitting model: the bound on (local rate) x (step) of its steps.
        condition_limit: ``poorly_determined`` above this condition number.
        trust_guesses: a count with guesses (a warm-start network's, ``extra_starts``) is first fitted from them
            alone; the scan's starts serve only a fit found suspicious. A network's guesses are then used for its
            most probable count and the one below only (``guess_probability`` aside), and the counts below those
            are not fitted: the network amortises the search. Set by :func:`torchrod.load_estimator` when the
            network's recorded quality is trusted.
        guess_probability: a network's guess of h forces starts a fit only where the network gives h at least this
            probability (0: every guess is used). Ignored with ``starts=0``.
        relative: readings of a precurved rod are the change of curvature from the unloaded shape, u - u*.
        time_budget: [s] per reading, None: no limit. A call on B readings stops searching ``B * time_budget``
            after it began (compilation, done before, never counts); the readings whose search it cut get the best
            fit found so far and the status ``timeout``. For real time. On a GPU the search cannot be stopped from
            the host: use ``max_evaluations`` there.
        max_evaluations: a deterministic budget instead: each reading's search stops after this many evaluations
            of the forward model (its answer then ``timeout``); 0: none. The same on every machine and every run.
        threads: CPU threads a batch is spread over (None: every core); a reading is never split.
        target: where the kernels run (:data:`TARGETS`).
    """

    max_forces: int = 3
    num_forces: int | None = None
    noise: float | None = None
    max_noise: float = 1.0
    selection: str = "noise"
    threshold: float = PAPER_THRESHOLD
    significance: float = 0.05
    misfit_level: float = MISFIT_LEVEL
    merge_patches: bool = True
    noise_floor: float = 1e-3
    starts: int = 3
    settle: bool = True
    lm: LMPolicy = field(default_factory=LMPolicy)
    search: SearchOptions = field(default_factory=SearchOptions)
    max_step_angle: float = FIT_STEP_ANGLE
    condition_limit: float = CONDITION_LIMIT
    trust_guesses: bool = False
    guess_probability: float = 0.01
    relative: bool = False
    time_budget: float | None = None
    max_evaluations: int = 0
    threads: int | None = None
    target: str = "auto"

    def __post_init__(self) -> None:
        _integer(self, "max_forces", 0)
        _integer(self, "starts", 0)
        _integer(self, "max_evaluations", 0)
        if self.num_forces is not None:
            _integer(self, "num_forces", 0)
        if self.threads is not None:
            _integer(self, "threads", 1)
        # A sigma beyond the largest curvature any reading may carry makes every reading noise (and its square
        # overflows a double soon after): a unit or typing error.

        most = f"at most {MAX_CURVATURE:g} [1/m], the largest curvature a reading may carry"
        if self.noise is not None:
            _number(self, "noise", lambda v: 0.0 <= v <= MAX_CURVATURE, f"None or a sigma >= 0 and {most}")
        if self.time_budget is not None:
            _number(self, "time_budget", lambda v: v >= 0.0, "None or a finite time >= 0 [s]")
        _number(self, "max_noise", lambda v: 0.0 < v <= MAX_CURVATURE, f"a positive sigma {most}")
        if self.selection not in RULES:
            raise OptionsError(f"selection must be one of {RULES}, got {self.selection!r}")
        _number(self, "threshold", lambda v: v > 0.0, "positive [1/m^2]")
        _number(self, "significance", lambda v: 0.0 < v < 1.0, "in (0, 1)")
        _number(self, "misfit_level", lambda v: 0.0 < v < 1.0, "in (0, 1)")
        if not isinstance(self.merge_patches, bool):
            raise OptionsError(f"merge_patches must be True or False, got {self.merge_patches!r}")
        _number(self, "noise_floor", lambda v: 0.0 <= v <= MAX_CURVATURE, f">= 0 and {most}")
        for name in ("noise", "max_noise"):
            sigma = getattr(self, name)
            if sigma is not None and not float(sigma) ** 2 + float(self.noise_floor) ** 2 > 0.0:
                raise OptionsError(
                    f"{name} = {sigma!r} with noise_floor = {self.noise_floor!r} leaves no noise at all (sigma^2 + "
                    "floor^2 = 0): every residual would be infinitely significant; give a positive noise_floor"
                )
        _number(self, "max_step_angle", lambda v: v > 0.0, "positive")
        _number(self, "condition_limit", lambda v: v > 1.0, "above 1")
        _number(self, "guess_probability", lambda v: 0.0 <= v < 1.0, "in [0, 1)")
        for name, kind in (("lm", LMPolicy), ("search", SearchOptions)):
            if not isinstance(getattr(self, name), kind):
                raise OptionsError(f"{name} must be {kind.__name__}, got {type(getattr(self, name)).__name__}")
        if self.target not in TARGETS:
            raise OptionsError(f"target must be one of {TARGETS}, got {self.target!r}")

    @property
    def counts(self) -> list[int]:
        """The counts the choice is among: [num_forces], or 0..max_forces."""
        return [self.num_forces] if self.num_forces is not None else list(range(self.max_forces + 1))

    @property
    def width(self) -> int:
        """Force slots in a result: num_forces if fixed, else max_forces."""
        return self.num_forces if self.num_forces is not None else self.max_forces

    @property
    def noise2(self) -> float:
        """The kernels' noise of a reading: sigma^2 + floor^2 [1/m^2] with the noise given, -1.0 without."""
        return -1.0 if self.noise is None else float(self.noise) ** 2 + float(self.noise_floor) ** 2

    def record(self) -> Any:
        """These options as the kernels' :data:`~torchrod.kernels.layout.OPTIONS` record: :func:`kernel_values`."""
        from ..kernels.host import options_record

        return options_record(**kernel_values(self))


KERNEL_CONVERSIONS: dict[str, Callable[[EstimatorOptions], Any]] = {
    "max_forces": lambda o: o.width + (1 if o.num_forces and math.isfinite(o.search.escape_turning) else 0),
    "fixed": lambda o: -1 if o.num_forces is None else o.num_forces,
    "min_dof": lambda o: MIN_TEST_DOF,
    "trusted": lambda o: o.trust_guesses,
    "rule": lambda o: {"noise": RULE_NOISE, "threshold": RULE_THRESHOLD}[o.selection],
    "floor2": lambda o: float(o.noise_floor) ** 2,
    "max_noise2": lambda o: float(o.max_noise) ** 2 + float(o.noise_floor) ** 2,
    "acceleration": lambda o: -math.inf if o.lm.acceleration is None else o.lm.acceleration,
}
"""The fields of :data:`~torchrod.kernels.layout.OPTIONS` that are not an option's value as it stands, each made
from the options: the rows' largest count (the result's width; one more for a fixed count's escape), the fixed count
(-1: chosen), the least degrees of freedom a chosen count leaves, the count rule's code, the squared noise floor and
misfit sigma, the acceleration's -inf for never. Where an option has an OPTIONS field's name (``max_forces``,
``acceleration``) this, not the option, fills it."""


def kernel_values(options: EstimatorOptions) -> dict[str, Any]:
    """Every field of :data:`~torchrod.kernels.layout.OPTIONS` from ``options``: a field of the options, of their
    :class:`LMPolicy` or of their :class:`SearchOptions` that has an OPTIONS field's name goes in as it is, unless
    :data:`KERNEL_CONVERSIONS` makes that field. A new setting is thus a dataclass field and an OPTIONS field of one
    name; an OPTIONS field that two of the dataclasses name is an error."""
    names = set(OPTIONS.names or ())
    values = {name: make(options) for name, make in KERNEL_CONVERSIONS.items()}
    owner: dict[str, str] = {}
    for source in (options, options.lm, options.search):
        for f in fields(source):
            if f.name not in names or f.name in KERNEL_CONVERSIONS:
                continue
            if f.name in owner:
                raise OptionsError(
                    f"the kernels' option {f.name!r} is named by both {owner[f.name]} and {type(source).__name__}"
                )
            owner[f.name] = type(source).__name__
            values[f.name] = getattr(source, f.name)
    return values


def default_max_forces(num_gratings: int) -> int:
    """The largest count an estimator considers unless told otherwise: ``EstimatorOptions.max_forces`` (3), or
    fewer where the rod's ``num_gratings`` cannot test as many (:func:`torchrod.rod.max_testable_forces`)."""
    return min(EstimatorOptions.max_forces, max_testable_forces(num_gratings))
