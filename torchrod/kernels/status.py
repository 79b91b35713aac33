"""The verdict codes the kernels write, one per reading (:func:`torchrod.kernels.counts.verdict` applies them in
the order of precedence that :mod:`torchrod.estimate.status` explains to users).

They live with the kernels, which import nothing from the rest of the package; :class:`torchrod.Status` names
them.
"""

OK, MISFIT, UNCONVERGED, POORLY_DETERMINED, TIMEOUT = range(5)
"""The codes, as the kernels write them."""

NAMES = ("ok", "misfit", "unconverged", "poorly_determined", "timeout")
"""The status names, by code: ``NAMES[code]``."""
