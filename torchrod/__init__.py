"""torchrod: where a continuum robot is touched, and how hard, from FBG curvature.

The public surface (SI units everywhere: m, N, Pa, 1/m):

- the rod and its loads: :class:`Rod`, :mod:`presets`, :class:`PointForces`;
- the differentiable, batched body-frame forward model: :func:`simulate`, :func:`grating_curvature`;
- the shape: :func:`rod_shape`, :class:`Shape`, :func:`bending_angle`;
- estimation: :class:`Estimator`, :class:`EstimatorOptions`, :class:`EstimateResult`, the batched :func:`lbfgs`;
- submodules for the rest: :mod:`torchrod.global_bvp` (global-frame reference and the paper's baselines),
  :mod:`torchrod.synthetic` (training sets and streams), :mod:`torchrod.calibration`, :mod:`torchrod.warm_start`,
  :mod:`torchrod.training`, :mod:`torchrod.stream`.
"""

from . import presets
from .estimate.estimator import EstimateResult, Estimator, EstimatorOptions
from .estimate.refine import LBFGSOptions, RefineResult, lbfgs
from .loads import PointForces, spread_to_nodes
from .model.body_frame import Simulation, grating_curvature, simulate
from .model.shape import Shape, bending_angle, rod_shape
from .rod import Rod, tube_bending_stiffness

__version__ = "0.1.0"

__all__ = [
    "EstimateResult",
    "Estimator",
    "EstimatorOptions",
    "LBFGSOptions",
    "PointForces",
    "RefineResult",
    "Rod",
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
