"""One module per ``torchrod`` subcommand (see :mod:`torchrod.cli`), and the option checks they share."""

from __future__ import annotations

import argparse

__all__ = ["check_estimation_options"]


def check_estimation_options(args: argparse.Namespace) -> None:
    """Check ``--batch-size``, ``--noise`` and ``--threads`` of an estimating command and apply ``--threads``.

    Raises ``ValueError`` naming the option and its bad value (the CLI turns it into exit status 2).
    """
    import torch

    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.noise is not None and not args.noise >= 0.0:
        raise ValueError(f"--noise must be >= 0, got {args.noise}")
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
