"""Patches of load against point forces: what the count tests and the patch rule answer.

A patch (:func:`torchrod.synthetic.sample_patches`) is a contact spread over ``width`` (12 mm by default) on
``nitinol290``, whose gratings lie 20 mm apart: a grating under it reads more moment than one force at its centre
would, and the count tests may then add a light force beside it pushing the same way
(:func:`torchrod.kernels.counts.unresolved_pair`). :func:`study` answers four sets of readings, each with noise
``sigma`` (given to the estimator, or not), with ``merge_patches`` on (the default) and off (the count tests alone):

* ``patch``: the patches;
* ``point``: the same loads, each as one force at its patch's centre;
* ``2 forces``, ``3 forces``: real pairs and triples, at least 25 mm apart (:class:`~torchrod.synthetic.LoadSampler`,
  the accuracy tables' draws).

Per row: the fraction answered with two forces or more, and with the right count (one for a patch), with the rule and
without it, and how many answers the rule changed. ``torchrod bench patches`` prints the table.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..estimate.estimator import Estimator, EstimatorOptions
from ..loads import PointForces
from ..model.body_frame import grating_curvature
from ..presets import nitinol290
from ..synthetic import LoadSampler, sample_loads, sample_patches

__all__ = ["StudyRow", "study", "table"]


@dataclass(frozen=True)
class StudyRow:
    """One row of :func:`study`'s table (module docstring): fractions of ``count`` readings."""

    loads: str
    noise_known: bool
    count: int
    more: float
    more_alone: float
    right: float
    right_alone: float
    changed: int


def _sets(count: int, width: float, seed: int) -> list[tuple[str, PointForces, int]]:
    """The study's loads: (name, loads, true count)."""
    rod = nitinol290()
    patches, centre = sample_patches(rod, count, width, torch.Generator().manual_seed(seed))
    point = PointForces(centre[:, None].clone(), patches.f.sum(1, keepdim=True).contiguous())
    sets = [("patch", patches, 1), ("point", point, 1)]
    for k in (2, 3):
        sampler = LoadSampler(min_forces=k, max_forces=k)
        sets.append((f"{k} forces", sample_loads(rod, count, sampler, torch.Generator().manual_seed(seed + k)), k))
    return sets


def study(
    count: int = 3000, width: float = 0.012, sigma: float = 0.1, seed: int = 1000, threads: int | None = None
) -> list[StudyRow]:
    """The table (module docstring): for each set of loads, a row with the noise given and one without."""
    rod = nitinol290()
    rows = []
    for j, (name, loads, k) in enumerate(_sets(count, width, seed)):
        u = grating_curvature(rod, loads)
        u = u + sigma * torch.randn(u.shape, generator=torch.Generator().manual_seed(seed + 10 + j), dtype=u.dtype)
        for noise in (sigma, None):
            merged, alone = (
                Estimator(rod, EstimatorOptions(noise=noise, merge_patches=merge, threads=threads)).estimate(u)
                for merge in (True, False)
            )
            frac = lambda x: float(x.double().mean())  # noqa: E731
            rows.append(
                StudyRow(
                    loads=name,
                    noise_known=noise is not None,
                    count=count,
                    more=frac(merged.num_forces >= 2),
                    more_alone=frac(alone.num_forces >= 2),
                    right=frac(merged.num_forces == k),
                    right_alone=frac(alone.num_forces == k),
                    changed=int((merged.num_forces != alone.num_forces).sum()),
                )
            )
    return rows


def table(rows: list[StudyRow]) -> list[str]:
    """The rows as the lines of a Markdown table."""
    out = [
        "| loads | noise | 2+ forces | 2+ forces, count tests alone | right count | right count, count tests alone "
        "| answers changed |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r.loads} | {'given' if r.noise_known else 'learned'} | {100 * r.more:.2f} % | "
            f"{100 * r.more_alone:.2f} % | {100 * r.right:.2f} % | {100 * r.right_alone:.2f} % | "
            f"{r.changed} of {r.count} |"
        )
    return out
