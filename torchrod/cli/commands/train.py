"""``torchrod train``: train the warm-start network (the same entry as ``python train/train_warm_start.py``).

``torchrod train --rod nitinol290 --generate 150000 --epochs 20 --checkpoint checkpoints/nitinol290.pt``; under
``torchrun --nproc_per_node=N -m torchrod train ...`` it trains with DistributedDataParallel. See
:mod:`torchrod.training` for the options and what is logged.
"""

from __future__ import annotations

import argparse

HELP = "train the warm-start network"


def configure(parser: argparse.ArgumentParser) -> None:
    from ...learn.training import add_arguments

    add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ...learn.training import run as run_training

    return run_training(args)
