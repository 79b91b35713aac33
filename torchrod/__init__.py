"""torchrod: where a continuum robot is touched, and how hard, from FBG curvature.

The public surface: a :class:`Rod`, :class:`PointForces`, the differentiable body-frame forward model
:func:`simulate`, and (see the submodules) the global-frame reference, estimation, training and streams.
"""

from . import presets
from .body_frame import Simulation, grating_curvature, simulate
from .loads import PointForces, spread_to_nodes
from .rod import Rod, tube_bending_stiffness

__version__ = "0.1.0"

__all__ = [
    "Rod",
    "tube_bending_stiffness",
    "presets",
    "PointForces",
    "spread_to_nodes",
    "Simulation",
    "simulate",
    "grating_curvature",
    "__version__",
]
