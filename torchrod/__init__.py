"""torchrod: where a continuum robot is touched, and how hard, from FBG curvature.

The public surface (SI units everywhere: m, N, Pa, 1/m):

- the rod and its loads: :class:`Rod`, :mod:`presets`, :class:`PointForces`;
- the differentiable, batched body-frame forward model: :func:`simulate`, :func:`grating_curvature`;
- the shape: :func:`rod_shape`, :class:`Shape`, :func:`bending_angle`;
- estimation: :class:`Estimator`, :class:`EstimatorOptions` (with :class:`LMPolicy` and :class:`SearchOptions`),
  :class:`EstimateResult`, the batched :func:`lbfgs`;
- subpackages for the rest: :mod:`torchrod.model` (forward model, the global-frame reference and the paper's
  baselines), :mod:`torchrod.estimate` (fit, count selection, uncertainty, calibration), :mod:`torchrod.learn`
  (synthetic data, the warm-start network, training), :mod:`torchrod.io` (readings, streams).

The names are loaded on first use (PEP 562): ``import torchrod`` and ``torchrod.__version__`` do not import torch,
so ``torchrod --version`` and ``torchrod --help`` answer at once; ``torchrod.Rod`` or ``torchrod.simulate`` import
what they need when first touched.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# public name -> (module relative to this package, attribute; None: the module itself)
_LAZY: dict[str, tuple[str, str | None]] = {
    "EstimateResult": (".estimate.estimator", "EstimateResult"),
    "Estimator": (".estimate.estimator", "Estimator"),
    "EstimatorOptions": (".estimate.estimator", "EstimatorOptions"),
    "LBFGSOptions": (".estimate.refine", "LBFGSOptions"),
    "LMPolicy": (".estimate.lm", "LMPolicy"),
    "PointForces": (".loads", "PointForces"),
    "RefineResult": (".estimate.refine", "RefineResult"),
    "Rod": (".rod", "Rod"),
    "SearchOptions": (".estimate.search", "SearchOptions"),
    "Shape": (".model.shape", "Shape"),
    "Simulation": (".model.body_frame", "Simulation"),
    "bending_angle": (".model.shape", "bending_angle"),
    "grating_curvature": (".model.body_frame", "grating_curvature"),
    "lbfgs": (".estimate.refine", "lbfgs"),
    "presets": (".presets", None),
    "rod_shape": (".model.shape", "rod_shape"),
    "simulate": (".model.body_frame", "simulate"),
    "spread_to_nodes": (".loads", "spread_to_nodes"),
    "tube_bending_stiffness": (".rod", "tube_bending_stiffness"),
}

__all__ = [  # the names of _LAZY and __version__ (a test holds them equal)
    "EstimateResult",
    "Estimator",
    "EstimatorOptions",
    "LBFGSOptions",
    "LMPolicy",
    "PointForces",
    "RefineResult",
    "Rod",
    "SearchOptions",
    "Shape",
    "Simulation",
    "__version__",
    "bending_angle",
    "grating_curvature",
    "lbfgs",
    "presets",
    "rod_shape",
    "simulate",
    "spread_to_nodes",
    "tube_bending_stiffness",
]

# Subpackages and modules that ``torchrod.X`` reaches without an import of its own (as when they were eager).
_SUBMODULES = frozenset({"cli", "estimate", "eval", "io", "learn", "loads", "model", "rod"})

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports on first use
    from . import presets
    from .estimate.estimator import EstimateResult, Estimator, EstimatorOptions
    from .estimate.lm import LMPolicy
    from .estimate.refine import LBFGSOptions, RefineResult, lbfgs
    from .estimate.search import SearchOptions
    from .loads import PointForces, spread_to_nodes
    from .model.body_frame import Simulation, grating_curvature, simulate
    from .model.shape import Shape, bending_angle, rod_shape
    from .rod import Rod, tube_bending_stiffness


def __getattr__(name: str) -> Any:
    """Import a public name on first use and keep it (later lookups do not come here)."""
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    try:
        module_name, attribute = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    module = importlib.import_module(module_name, __name__)
    value = module if attribute is None else getattr(module, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
