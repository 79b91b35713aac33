"""torchrod: where a continuum robot is touched, and how hard, from FBG curvature.

The public surface (SI units everywhere: m, N, Pa, 1/m):

- the rod and its loads: :class:`Rod`, :mod:`presets`, :class:`PointForces`;
- the differentiable, batched body-frame forward model: :func:`simulate`, :func:`grating_curvature`;
- the shape: :func:`rod_shape`, :class:`Shape`, :func:`bending_angle`;
- estimation: :class:`Estimator`, :class:`EstimatorOptions` (with :class:`LMPolicy` and :class:`SearchOptions`),
  :class:`EstimateResult` and its :class:`Status`; :func:`calibrate` (a rod's stiffness and location bias from
  readings of known loads); the warm-start network, :class:`WarmStart`, and
  :func:`load_estimator` (an estimator with a trained network's guesses);
- streams: :func:`stream` with :class:`StreamOptions` (readings in order, in latency-bounded batches);
- errors and warnings: :class:`TorchrodError` (with :class:`ReadingError`, :class:`RodError`,
  :class:`OptionsError`, :class:`MissingFileError`,
  :class:`CheckpointError`, :class:`TorchrodTypeError`) and :class:`TorchrodWarning` (with :class:`RodWarning`);
- subpackages for the rest: :mod:`torchrod.model` (forward model, the global-frame reference and the paper's
  baselines), :mod:`torchrod.estimate` (options, status, noise, calibration), :mod:`torchrod.kernels` (the
  estimator's numerical core), :mod:`torchrod.learn` (the warm-start network, training),
  :mod:`torchrod.synthetic` (synthetic load sets and reading streams),
  :mod:`torchrod.io` (readings, streams, files), :mod:`torchrod.sensors` (strain and wavelengths to curvature).

The names are loaded on first use (PEP 562): ``import torchrod`` and ``torchrod.__version__`` do not import torch,
so ``torchrod --version`` and ``torchrod --help`` answer at once; ``torchrod.Rod`` or ``torchrod.simulate`` import
what they need when first touched.
"""

import importlib as _importlib
import typing as _typing

__version__ = "0.1.0"

# public name -> (module relative to this package, attribute; None: the module itself)
_LAZY: dict[str, tuple[str, str | None]] = {
    "CheckpointError": (".errors", "CheckpointError"),
    "EstimateResult": (".estimate.estimator", "EstimateResult"),
    "Estimator": (".estimate.estimator", "Estimator"),
    "EstimatorOptions": (".estimate.options", "EstimatorOptions"),
    "LMPolicy": (".estimate.options", "LMPolicy"),
    "MissingFileError": (".errors", "MissingFileError"),
    "OptionsError": (".errors", "OptionsError"),
    "PointForces": (".loads", "PointForces"),
    "ReadingError": (".errors", "ReadingError"),
    "ReadingWarning": (".errors", "ReadingWarning"),
    "Rod": (".rod", "Rod"),
    "RodError": (".errors", "RodError"),
    "RodWarning": (".errors", "RodWarning"),
    "SearchOptions": (".estimate.options", "SearchOptions"),
    "Shape": (".model.shape", "Shape"),
    "Simulation": (".model.body_frame", "Simulation"),
    "Status": (".estimate.status", "Status"),
    "StreamOptions": (".io.stream", "StreamOptions"),
    "TorchrodError": (".errors", "TorchrodError"),
    "TorchrodTypeError": (".errors", "TorchrodTypeError"),
    "TorchrodWarning": (".errors", "TorchrodWarning"),
    "WarmStart": (".learn.warm_start", "WarmStart"),
    "bending_angle": (".model.shape", "bending_angle"),
    "calibrate": (".estimate.calibration", "calibrate"),
    "grating_curvature": (".model.body_frame", "grating_curvature"),
    "load_estimator": (".learn.warm_start", "load_estimator"),
    "presets": (".presets", None),
    "rod_shape": (".model.shape", "rod_shape"),
    "simulate": (".model.body_frame", "simulate"),
    "stream": (".io.stream", "stream"),
}

__all__ = [  # the names of _LAZY and __version__ (a test holds them equal)
    "CheckpointError",
    "EstimateResult",
    "Estimator",
    "EstimatorOptions",
    "LMPolicy",
    "MissingFileError",
    "OptionsError",
    "PointForces",
    "ReadingError",
    "ReadingWarning",
    "Rod",
    "RodError",
    "RodWarning",
    "SearchOptions",
    "Shape",
    "Simulation",
    "Status",
    "StreamOptions",
    "TorchrodError",
    "TorchrodTypeError",
    "TorchrodWarning",
    "WarmStart",
    "__version__",
    "bending_angle",
    "calibrate",
    "grating_curvature",
    "load_estimator",
    "presets",
    "rod_shape",
    "simulate",
    "stream",
]

# Subpackages and modules that ``torchrod.<name>`` reaches without an import of its own (as when they were eager).
_SUBMODULES = frozenset(
    {"cli", "errors", "estimate", "eval", "io", "kernels", "learn", "loads", "model", "rod", "sensors", "synthetic"}
)

if _typing.TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports on first use
    from . import presets
    from .errors import (
        CheckpointError,
        MissingFileError,
        OptionsError,
        ReadingError,
        ReadingWarning,
        RodError,
        RodWarning,
        TorchrodError,
        TorchrodTypeError,
        TorchrodWarning,
    )
    from .estimate.calibration import calibrate
    from .estimate.estimator import EstimateResult, Estimator
    from .estimate.options import EstimatorOptions, LMPolicy, SearchOptions
    from .estimate.status import Status
    from .io.stream import StreamOptions, stream
    from .learn.warm_start import WarmStart, load_estimator
    from .loads import PointForces
    from .model.body_frame import Simulation, grating_curvature, simulate
    from .model.shape import Shape, bending_angle, rod_shape
    from .rod import Rod


def __getattr__(name: str) -> _typing.Any:
    """Import a public name on first use and keep it (later lookups do not come here)."""
    if name in _SUBMODULES:
        return _importlib.import_module(f".{name}", __name__)
    try:
        module_name, attribute = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    module = _importlib.import_module(module_name, __name__)
    value = module if attribute is None else getattr(module, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names and subpackages (not this module's own helpers)."""
    return sorted(set(__all__) | _SUBMODULES)
