"""Clean-reading recovery: does the estimator find the forces behind noise-free readings, or say it cannot?

A stratified set of random noise-free cases (:func:`recovery_cases`), where local minima and ambiguity hide:

* a third (``"near base"``) with a force within 20 mm of the first two gratings (between the first grating and
  20 mm distal to the second);
* a third (``"missing"``) with 1 to 3 gratings missing;
* a third (``"anywhere"``) with the forces anywhere from the first present grating to the tip;

and, across all of them, pairs that straddle a grating (one force each side, within half a grating spacing of
it) in a quarter of the cases with two or more forces. 1 to 3 forces of 0.05 to 2 N in any direction, at least
2 mm apart, the rod's total turning at most 90 degrees (the synthetic envelope).

With ``elastic=True`` the envelope is the rod's elastic range instead: no limit on the turning, but the largest
bending strain |u| d_out / 2 at most ``max_strain`` (:data:`ELASTIC_STRAIN`; a rod given by its stiffness alone, with
no diameter, is held to a turning of one full turn instead), and a fourth stratum (``"large bend"``) of cases that
turn the rod by more than 135 degrees, whose magnitudes are drawn up to :data:`LARGE_BEND_LOAD` times EI / L^2.

Each case is classified (:func:`identifiable`): the data decide it when every force lies in its own interval
between present gratings, none in the first interval (one grating sees it: its magnitude trades against its
lever), the gratings that see the forces leave at least three residuals beyond the unknowns (one more force could
otherwise hide there), and every force changes the reading by at least ``visible`` [1/m] at two or more gratings
(a force a few micrometres past a grating bends that grating by nothing measurable, so only the gratings before it
see it and, if that is one, its magnitude trades against its lever as in the first interval). A result is *exact* when
the count is right, every force within 0.1 % and every location within 0.1 mm. :func:`judge` sorts each result into

* ``exact``: recovered;
* ``within_error``: the right count, answered ``ok``, every location and force component within three of the
  standard deviations the estimator reports (at the noise it is told, or its floor): not exact, but the answer's
  own error bars hold the truth (a force 0.1 mm from a grating, fitted onto it, for example);
* ``missed``: an identifiable case not recovered either way: the search failed (the status says whether it knew);
* ``flagged``: not recovered, not identifiable, and the status says the answer is doubtful (not ``ok``);
* ``parsimonious``: fewer forces than the truth, answered ``ok``, and the answer, simulated again, reproduces the
  reading to within the estimator's noise floor (root mean square): the reading cannot tell it from the truth (two
  forces in one interval, a force on the first grating, which bends nothing);
* ``wrong``: not recovered and ``ok`` otherwise: a confident wrong answer, the worst output there is.

The tests and ``torchrod evaluate --recovery`` run it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..errors import OptionsError
from ..loads import PointForces
from ..rod import Rod

__all__ = [
    "RecoveryCase",
    "VERDICTS",
    "explains",
    "gauss_newton_condition",
    "identifiable",
    "judge",
    "recovery_cases",
    "run",
    "summarise",
]

STRATA = ("near base", "missing", "anywhere")
ELASTIC_STRATA = (*STRATA, "large bend")

ELASTIC_STRAIN = 0.04
"""The largest bending strain of the elastic envelope: inside the 6 to 8 % superelastic nitinol recovers; a rod of
another material may need a smaller value."""

LARGE_BEND = math.radians(135.0)
"""[rad] The total turning beyond which a case belongs to the ``"large bend"`` stratum."""

LARGE_BEND_LOAD = 100.0
"""The ``"large bend"`` stratum's largest magnitude, in units of EI / L^2 (the force whose lever over the whole
length bends the base by 1/L): about 9 N on the paper's tube, which curls it past a full turn near the tip."""
VERDICTS = ("exact", "within_error", "missed", "flagged", "parsimonious", "wrong")


@dataclass(frozen=True)
class RecoveryCase:
    """One noise-free case: true forces (model coordinates), the grating mask, its stratum."""

    s: list[float]
    f: list[tuple[float, float]]
    present: list[bool]
    stratum: str
    straddle: bool


def recovery_cases(
    rod: Rod,
    count: int,
    seed: int = 0,
    max_bending: float = math.pi / 2,
    *,
    elastic: bool = False,
    max_strain: float = ELASTIC_STRAIN,
) -> list[RecoveryCase]:
    """``count`` stratified random cases (module docstring), reproducible from ``seed``: within ``max_bending``
    [rad] of total turning, or with ``elastic`` within the elastic range (bending strain at most ``max_strain``)."""
    from ..synthetic import turning_and_peak

    if not 0.0 < max_strain < 1.0:
        raise OptionsError(f"max_strain must lie in (0, 1), got {max_strain!r}")
    g = torch.Generator().manual_seed(seed)
    q = list(rod.gratings)
    G, L = len(q), rod.length
    spacing = (q[-1] - q[0]) / max(G - 1, 1)
    strata = ELASTIC_STRATA if elastic else STRATA
    radius = 0.5 * rod.outer_diameter if rod.outer_diameter is not None else None
    big = LARGE_BEND_LOAD * rod.bending_stiffness / L**2

    def rand():
        return float(torch.rand(1, generator=g, dtype=torch.float64))

    def inside(loads: PointForces, stratum: str) -> bool:
        """Whether the case lies in the envelope (and its stratum): its turning and largest curvature."""
        turnings, peaks = turning_and_peak(rod, loads)
        turning, peak = float(turnings[0]), float(peaks[0])
        if not elastic:
            return turning <= max_bending
        if radius is not None and peak * radius > max_strain:
            return False
        if radius is None and turning > 2.0 * math.pi:
            return False
        return turning > LARGE_BEND if stratum == "large bend" else True

    out: list[RecoveryCase] = []
    while len(out) < count:
        stratum = strata[len(out) % len(strata)]
        k = 1 + int(torch.randint(0, 3, (1,), generator=g))
        present = [True] * G
        if stratum == "missing":
            for j in torch.randperm(G, generator=g)[: 1 + int(torch.randint(0, 3, (1,), generator=g))].tolist():
                present[j] = False
        first = q[present.index(True)]
        s: list[float] = []
        straddle = k >= 2 and rand() < 0.25
        if stratum == "near base":
            hi = min(q[1] + 0.02, L) if G > 1 else L
            s.append(first + (hi - first) * rand())
        if straddle:
            j = int(torch.randint(1, G, (1,), generator=g))
            s += [q[j] - 0.5 * spacing * rand(), q[j] + 0.5 * spacing * rand()]
        while len(s) < k:
            s.append(first + (L - first) * rand())
        s = sorted(min(max(x, first), L) for x in s[:k])
        if any(b - a < 0.002 for a, b in zip(s, s[1:], strict=False)):
            continue
        top = big if stratum == "large bend" else 2.0
        mag = [0.05 + (top - 0.05) * rand() for _ in range(k)]
        ang = [2.0 * math.pi * rand() for _ in range(k)]
        f = [(m * math.cos(a), m * math.sin(a)) for m, a in zip(mag, ang, strict=False)]
        loads = PointForces(torch.tensor([s], dtype=torch.float64), torch.tensor([f], dtype=torch.float64))
        if not inside(loads, stratum):
            continue
        out.append(RecoveryCase(s, f, present, stratum, straddle))
    return out


def readings(rod: Rod, cases: list[RecoveryCase]) -> tuple[torch.Tensor, torch.Tensor]:
    """The noise-free readings (B, G, 2) [1/m] (NaN at missing gratings) and the masks (B, G), from the
    simulator's model."""
    from ..model.body_frame import simulate

    h = max(len(c.s) for c in cases)
    loads = PointForces.from_lists(
        [[(si, fx, fy) for si, (fx, fy) in zip(c.s, c.f, strict=False)] for c in cases], max_forces=h
    )
    u = simulate(rod, loads).grating_curvature
    mask = torch.tensor([c.present for c in cases])
    return torch.where(mask.unsqueeze(-1), u, torch.full_like(u, math.nan)), mask


def identifiable(rod: Rod, case: RecoveryCase, visible: float = 0.01, condition: float = 1e6) -> bool:
    """Whether the data decide the case (module docstring): every force in its own interval between present
    gratings and none in the first, at least three residuals to spare among the gratings that see the forces,
    every force changing the reading by at least ``visible`` [1/m] at two or more gratings, and the Gauss-Newton matrix
    at the truth (unit diagonal) conditioned better than ``condition`` (else a nearby answer fits as well: two forces
    the gratings
    between them barely separate can have another exact solution a fraction of a millimetre away)."""
    from ..model.body_frame import simulate

    q = [x for x, p in zip(rod.gratings, case.present, strict=False) if p]
    intervals = [max(j for j in range(len(q)) if q[j] <= s) for s in case.s]
    if len(set(intervals)) < len(intervals) or 0 in intervals:
        return False
    seen = sum(1 for x in q if x < max(case.s))
    if 2 * seen - 3 * len(case.s) < 3:
        return False
    full = [(s, fx, fy) for s, (fx, fy) in zip(case.s, case.f, strict=False)]
    without = [[force for j, force in enumerate(full) if j != i] for i in range(len(full))]  # each force removed
    u = simulate(rod, PointForces.from_lists([full, *without], max_forces=len(full))).grating_curvature
    gone = (u[:1] - u[1:])[:, torch.tensor(case.present)].abs().amax(dim=-1)  # (h, present gratings)
    if bool(((gone >= visible).sum(dim=-1) < 2).any()):
        return False
    return gauss_newton_condition(rod, case) <= condition


def gauss_newton_condition(rod: Rod, case: RecoveryCase) -> float:
    """The condition number of the Gauss-Newton matrix J^T J of the case's present readings at the truth, scaled to
    a unit diagonal (J: d curvature / d (s_j, f_x,j, f_y,j), from the differentiable forward model).

    J comes from one backward pass: the case is simulated as a batch of one row per present reading value, and row
    b's gradient is that of its own value b (rows are independent), instead of one backward pass per value."""
    import numpy as np

    from ..model.body_frame import simulate

    present = torch.tensor(case.present)
    h, n = len(case.s), 2 * int(present.sum())  # unknowns per force, and the present values: J is (n, 3 h)
    s = torch.tensor([case.s], dtype=torch.float64).expand(n, h).clone().requires_grad_(True)
    f = torch.tensor([case.f], dtype=torch.float64).expand(n, h, 2).clone().requires_grad_(True)
    values = simulate(rod, PointForces(s, f)).grating_curvature[:, present].reshape(n, n)  # row b: all n values
    values.diagonal().sum().backward()  # row b's gradient: d value_b / d (s, f)
    assert s.grad is not None and f.grad is not None
    Jp = torch.cat((s.grad[:, :, None], f.grad), dim=-1).reshape(n, 3 * h).numpy()  # (s, f_x, f_y) per force
    N = Jp.T @ Jp
    d = np.sqrt(np.diag(N))
    if not np.all(d > 0):
        return math.inf
    return float(np.linalg.cond(N / np.outer(d, d)))


def judge(
    case: RecoveryCase,
    num_forces: int,
    s: list[float],
    f: list[tuple[float, float]],
    std: list[tuple[float, float, float]],
    status: str,
    decidable: bool,
    explains: bool,
) -> str:
    """One verdict of the module docstring. ``s``, ``f``, ``std``: the estimate in model coordinates, sorted by
    location, and its standard deviations (s [m], f_x [N], f_y [N]); ``explains``: whether the estimate, simulated
    again, reproduces the reading (:func:`explains`)."""
    pairs = list(zip(s, case.s, f, case.f, std, strict=False))
    same = num_forces == len(case.s)
    if same and all(
        abs(a - b) <= 1e-4 and math.hypot(fa[0] - fb[0], fa[1] - fb[1]) <= 1e-3 * math.hypot(*fb)
        for a, b, fa, fb, _ in pairs
    ):
        return "exact"
    if (
        same
        and status == "ok"
        and all(
            abs(a - b) <= 3.0 * sd[0] and abs(fa[0] - fb[0]) <= 3.0 * sd[1] and abs(fa[1] - fb[1]) <= 3.0 * sd[2]
            for a, b, fa, fb, sd in pairs
        )
    ):
        return "within_error"
    if decidable:
        return "missed"
    if status != "ok":
        return "flagged"
    return "parsimonious" if num_forces < len(case.s) and explains else "wrong"


def explains(
    rod: Rod,
    case: RecoveryCase,
    reading: torch.Tensor,
    s: list[float],
    f: list[tuple[float, float]],
    floor: float,
) -> bool:
    """Whether the answer (s, f), simulated again, reproduces the clean ``reading`` (G, 2) [1/m] at the present
    gratings to within ``floor`` [1/m], root mean square."""
    from ..model.body_frame import simulate

    loads = PointForces.from_lists(
        [[(si, fx, fy) for si, (fx, fy) in zip(s, f, strict=False)]], max_forces=max(len(s), 1)
    )
    u = simulate(rod, loads).grating_curvature[0]
    present = torch.tensor(case.present)
    diff = (u - reading)[present]
    return bool(diff.pow(2).mean().sqrt() <= floor)


def summarise(rows: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Counts of each verdict per stratum (and ``all``)."""
    out: dict[str, dict[str, int]] = {}
    for row in rows:
        for key in (row["stratum"], "all"):
            cell = out.setdefault(key, {"cases": 0, **{v: 0 for v in VERDICTS}})
            cell["cases"] += 1
            cell[row["verdict"]] += 1
    return out


def run(
    rod: Rod,
    count: int,
    *,
    seed: int = 0,
    estimator: Any = None,
    batch_size: int = 250,
    elastic: bool = False,
    max_strain: float = ELASTIC_STRAIN,
) -> list[dict[str, Any]]:
    """Estimate ``count`` stratified clean cases (default estimator: ``EstimatorOptions(noise=0.0)``; ``elastic``,
    ``max_strain``: the envelope, :func:`recovery_cases`) and judge each: one dict per case with its ``stratum``,
    ``straddle``, ``decidable``, ``verdict``, the truth and the answer."""
    from ..estimate.estimator import Estimator, EstimatorOptions

    est = estimator if estimator is not None else Estimator(rod, EstimatorOptions(noise=0.0))
    cases = recovery_cases(rod, count, seed, elastic=elastic, max_strain=max_strain)
    rows: list[dict[str, Any]] = []
    for b0 in range(0, len(cases), batch_size):
        chunk = cases[b0 : b0 + batch_size]
        u, mask = readings(rod, chunk)
        result = est.estimate(u, mask)
        statuses = result.statuses
        floor = math.hypot(est.options.noise or 0.0, est.options.noise_floor)
        for i, case in enumerate(chunk):
            n = int(result.num_forces[i])
            s = [float(x) - rod.location_bias for x in result.forces.s[i, :n].tolist()]
            f = [tuple(p) for p in result.forces.f[i, :n].tolist()]
            std = [tuple(p) for p in result.std[i, :n].tolist()]
            decidable = identifiable(rod, case)
            fits = explains(rod, case, torch.nan_to_num(u[i]), s, f, floor) if n < len(case.s) else False
            rows.append(
                {
                    "stratum": case.stratum,
                    "straddle": case.straddle,
                    "decidable": decidable,
                    "verdict": judge(case, n, s, f, std, statuses[i], decidable, fits),
                    "status": statuses[i],
                    "truth": [(si, fi) for si, fi in zip(case.s, case.f, strict=False)],
                    "missing": [k for k, p in enumerate(case.present) if not p],
                    "estimate": list(zip(s, f, strict=False)),
                }
            )
    return rows
