"""The verdict on every estimate: whether a user can act on it, and what to do when not.

Each reading's result carries one status; when several apply, the first in this order wins:

``"timeout"``
    The reading's time budget (``EstimatorOptions.time_budget``) ran out before its search was done: the answer
    is the best fit found so far, and the larger counts, other starts or refinement it would still have tried
    were skipped. Its p-value, ``converged`` and ``poorly_determined`` are those of that fit, so a timeout
    with a small p-value may be a misfit that more time would have fixed, or not. Use it with care (or hold
    the last good answer); if many readings time out, give a larger budget, fewer ``max_forces``, or more
    CPU threads.
``"misfit"``
    The chosen fit is worse than the noise explains: its loss exceeds the ``1 - misfit_level`` quantile of the
    chi-square law of a correct fit's loss, ``loss / sigma^2 ~ chi2(n - 3h)``, at the given noise (with the floor)
    or, noise unknown, at the largest noise the estimator believes (``max_noise``: a reading that needs more noise
    than any FBG interrogator makes is not explained). With the default level 0.001, one correct reading in a
    thousand is flagged by chance. The p-value is reported. No set of forces of the counts considered produces
    this reading: a sensor fault (a broken or mis-registered grating, a wrong calibration), a load the model does
    not hold (a distributed load, a moment, a contact force with friction), more contacts than ``max_forces``, or a
    wrong ``noise``. A patch of load the gratings see (``EstimatorOptions.merge_patches``) may be answered so too:
    one force where the patch is, the poorly determined pair of forces that would fit it not taken for two
    contacts. Do not act on the forces; check the sensor and the rod file.
``"unconverged"``
    The fit was still improving when its budget ran out (or its linear algebra failed): the forces may be off.
    Retry with more iterations (``EstimatorOptions(lm=LMPolicy(iterations=..., refine_iterations=...))``) or
    report the reading.
``"poorly_determined"``
    The data cannot tell this answer from others (:mod:`torchrod.kernels.covariance`: forces the gratings cannot
    separate, a force seen by one grating only, a location uncertain beyond its grating interval; one force where a
    patch of load may be two close forces, ``EstimatorOptions.merge_patches``). The fit explains
    the reading, but some of its numbers are not pinned down: use the standard deviations, or a denser grating
    layout.
``"ok"``
    The fit explains the reading and its parameters are determined; the standard deviations hold.
"""

from __future__ import annotations

from enum import Enum

from ..kernels.status import NAMES

__all__ = ["MISFIT_LEVEL", "STATUSES", "Status"]


class Status(str, Enum):
    """A reading's verdict, a string (``Status.OK == "ok"``); its position in this enumeration is the code that
    :attr:`torchrod.EstimateResult.status` holds per reading."""

    OK = "ok"
    MISFIT = "misfit"
    UNCONVERGED = "unconverged"
    POORLY_DETERMINED = "poorly_determined"
    TIMEOUT = "timeout"

    def __str__(self) -> str:
        return self.value

    @property
    def code(self) -> int:
        """The integer code of this status in :attr:`torchrod.EstimateResult.status`."""
        return STATUSES.index(self.value)


STATUSES = NAMES
"""The status names, by code: ``STATUSES[code]`` (the kernels' :data:`torchrod.kernels.status.NAMES`)."""

if tuple(s.value for s in Status) != STATUSES:  # (an internal invariant: the members in the kernels' code order)
    raise AssertionError(f"Status members {[s.value for s in Status]} differ from the kernels' codes {STATUSES}")

MISFIT_LEVEL = 1e-3
"""Default significance of the misfit test: the chance that a correct fit is called a misfit."""
