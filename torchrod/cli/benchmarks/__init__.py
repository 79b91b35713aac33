"""The benchmarks behind ``torchrod bench SUITE``.

Each suite is a module ``torchrod/cli/benchmarks/SUITE.py`` that defines, like a command, ``HELP`` (one line),
``configure(parser)`` and ``run(args) -> int``. Suites are imported only when they run; :data:`SUITES` lists the
names ``torchrod bench`` knows (a suite whose module is missing is reported as not available).

* ``forward``: speed and accuracy of the forward model (exact and node schemes, B = 1, 64, 4096).
* ``estimate``, ``stream``, ``paper``: estimation, streams, the paper's comparison.
* ``network``: the warm-start network alone, and the estimator with and without it.
* ``startup``: time to the first answer (``--version``, ``--help``, a one-reading estimate) against importing torch.
* ``gpu``: the CUDA kernels: their compiled size (no GPU needed), the CUDA tests and readings per second on a GPU.
* ``gratings``: a needle with 3 gratings and one grating's gain off, with and without a calibration error.
* ``patches``: patches of load against point forces and real pairs, with the patch rule and the count tests alone.
* ``memory``: a ``torchrod stream`` process fed a million readings, its memory sampled: flat or growing.
* ``backlog``: a backlog of 1-3 force readings through ``torchrod stream``, beside other versions' checkouts.
"""

from __future__ import annotations

__all__ = ["SUITES"]

SUITES: dict[str, str] = {
    "forward": "forward model speed and accuracy: exact and node schemes at B = 1, 64, 4096",
    "estimate": "force estimation speed and accuracy",
    "stream": "amortised estimation on a stream of readings",
    "paper": "the paper's speed and accuracy comparison",
    "network": "what the warm-start network buys: the network alone, the estimator with and without it",
    "startup": "time to the first answer (--version, --help, a one-reading estimate) against importing torch",
    "gpu": "the CUDA kernels: PTX size and registers, the CUDA tests, readings per second on a GPU",
    "memory": "a long stream's memory: RSS of torchrod stream over a million readings, flat or growing",
    "backlog": "a backlog of 1-3 force readings through torchrod stream, this version beside other checkouts",
    "gratings": "a 3-grating needle with one grating's gain off: the count and the forces, with and without a "
    "calibration error",
    "patches": "patches of load against point forces and real pairs: two-force answers with and without the patch rule",
}
