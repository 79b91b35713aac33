"""What a rod can do, before its estimates are trusted: ``torchrod rod`` prints it (:func:`describe_rod`).

Its EI, its grating layout, how many forces its readings can tell apart (:func:`torchrod.rod.max_testable_forces`),
whether the shipped warm-start network serves it, and the curvature a tip load gives at its base-most grating
against the sensor's noise.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from ..errors import OptionsError, RodWarning
from ..learn.warm_start import quality_verdict, shipped_network
from ..loads import PointForces
from ..model.body_frame import simulate
from ..rod import FORCE_RULE, Rod, max_testable_forces
from ..values import positive

__all__ = ["TIP_LOAD", "TYPICAL_NOISE", "RodReport", "describe_rod", "grating_layout"]

TYPICAL_NOISE = 0.1
"""[1/m] A typical FBG curvature noise (one sigma per component), against which :func:`describe_rod` sets the
curvature a tip load gives."""

TIP_LOAD = 1.0
"""[N] The tip load of :func:`describe_rod`'s sensitivity check."""


def grating_layout(rod: Rod, width: int = 60) -> str:
    """A text figure of ``rod`` with its gratings marked, two lines: the rod from its clamp (``||``) to its tip, a
    grating an ``o`` (a digit where 2 to 9 gratings share a column, ``#`` for more), then a scale in mm."""
    if width < 10:
        raise OptionsError(f"width must be at least 10 columns, got {width}")
    counts = [0] * width
    for x in rod.gratings:
        counts[min(width - 1, round(x / rod.length * (width - 1)))] += 1
    marks = "".join("-" if n == 0 else "o" if n == 1 else str(n) if n <= 9 else "#" for n in counts)
    clamp = "clamp ||"
    end = f"{rod.length * 1e3:g} mm"
    return f"{clamp}{marks}| tip\n{' ' * len(clamp)}{'0'.ljust(width - len(end))}{end}"


@dataclass(frozen=True)
class RodReport:
    """What a user should see of a rod before trusting it (:func:`describe_rod`; ``torchrod rod`` prints it).

    Attributes:
        length: L [m].
        bending_stiffness: EI [N m^2].
        stiffness_from: ``"geometry"`` (E pi (d_out^4 - d_in^4) / 64) or ``"given"`` (``bending_stiffness``).
        gratings: the grating positions [m].
        layout: :func:`grating_layout`, a text figure of the rod with its gratings.
        values_per_reading: 2G, the values (ux, uy per grating) of a full reading.
        max_forces: :func:`max_testable_forces`: the most forces a full reading can tell apart.
        force_rule: :data:`FORCE_RULE`, the rule of ``max_forces`` in words.
        network_fits: whether a shipped warm-start network serves the rod's grating layout.
        network_reason: which network, or why there is none (:func:`torchrod.learn.warm_start.shipped_network`).
        network_weak: why the network is not trusted to start the fits alone ('' when it is, or when there is none).
        tip_load: the check's tip load [N] (:data:`TIP_LOAD`), a follower force at ``s = L``.
        base_grating: the position of the grating nearest the clamp [m].
        tip_curvature: the curvature change [1/m] that ``tip_load`` gives at ``base_grating``, simulated (the
            smaller over the two body-frame directions).
        tip_curvature_linear: the same for small loads, ``tip_load (L - base_grating) / EI`` [1/m].
        tip_curvature_accurate: whether the simulation kept its accuracy bound (False: the load bends the rod too far).
        noise: :data:`TYPICAL_NOISE` [1/m], the noise the curvature is set against.
        smallest_tip_force: the tip force [N] whose small-load curvature at ``base_grating`` equals ``noise``:
            ``noise EI / (L - base_grating)``.
        limitations: :attr:`torchrod.Rod.limitations`, what the rod cannot determine.
    """

    length: float
    bending_stiffness: float
    stiffness_from: str
    gratings: tuple[float, ...]
    layout: str
    values_per_reading: int
    max_forces: int
    force_rule: str
    network_fits: bool
    network_reason: str
    network_weak: str
    tip_load: float
    base_grating: float
    tip_curvature: float
    tip_curvature_linear: float
    tip_curvature_accurate: bool
    noise: float
    smallest_tip_force: float
    limitations: tuple[str, ...]

    @property
    def num_gratings(self) -> int:
        return len(self.gratings)

    @property
    def tip_signal_to_noise(self) -> float:
        """``tip_curvature / noise``: how many noise sigmas the tip load's curvature at the base-most grating is."""
        return self.tip_curvature / self.noise


def describe_rod(rod: Rod, noise: float = TYPICAL_NOISE) -> RodReport:
    """What ``rod`` can do, as :class:`RodReport`: its EI, its grating layout, how many forces its readings can tell
    apart, whether the shipped warm-start network serves it, and the curvature a 1 N tip load gives at its
    base-most grating against the sensor ``noise`` [1/m]. Imports torch (to simulate the load and load the
    network)."""
    sigma = positive("noise", noise, " [1/m]")
    L, ei, g0 = rod.length, rod.bending_stiffness, rod.gratings[0]
    with warnings.catch_warnings():  # (the check makes a dimensionless copy of the rod, which warns again)
        warnings.simplefilter("ignore", RodWarning)
        network, reason = shipped_network(rod)
    weak = quality_verdict(network.meta) if network is not None else ""
    loads = PointForces.from_lists([[(L, TIP_LOAD, 0.0)], [(L, 0.0, TIP_LOAD)]])
    sim = simulate(rod, loads)
    change = sim.grating_curvature[:, 0, :] - rod.unloaded_curvature()[0]
    tip = float(change.norm(dim=-1).min())
    return RodReport(
        length=L,
        bending_stiffness=ei,
        stiffness_from="geometry" if rod.outer_diameter is not None else "given",
        gratings=rod.gratings,
        layout=grating_layout(rod),
        values_per_reading=2 * rod.num_gratings,
        max_forces=max_testable_forces(rod.num_gratings),
        force_rule=FORCE_RULE,
        network_fits=network is not None,
        network_reason=reason,
        network_weak=weak,
        tip_load=TIP_LOAD,
        base_grating=g0,
        tip_curvature=tip,
        tip_curvature_linear=TIP_LOAD * (L - g0) / ei,
        tip_curvature_accurate=bool(sim.accurate.all()),
        noise=sigma,
        smallest_tip_force=sigma * ei / (L - g0),
        limitations=rod.limitations,
    )
