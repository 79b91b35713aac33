"""``torchrod train``: train the warm-start network (the same entry as ``python train/train_warm_start.py``).

``torchrod train --rod nitinol290 --generate 150000 --epochs 20 --checkpoint my_network.pt``; under
``torchrun --nproc_per_node=N -m torchrod train ...`` it trains with DistributedDataParallel. See
:mod:`torchrod.learn.training` for the options and what is logged.

The rod: generating, ``--rod`` (default nitinol290). With ``--data SET`` the network is trained for the set's rod;
a ``--rod`` given as well must agree with it (length, bending stiffness, gratings), else the command stops with
an error naming both instead of silently training for the set's rod.
"""

from __future__ import annotations

import argparse

HELP = "train the warm-start network that gives the estimator its first guess"


def configure(parser: argparse.ArgumentParser) -> None:
    from ...learn.training import add_arguments

    add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ...io.jsonl import check_output
    from ...learn.training import run as run_training

    if args.evaluate is None:  # (--evaluate records its quality into the checkpoint it reads, by design)
        # --resume may name the checkpoint written: training goes on in the same file.
        check_output(args.checkpoint, {"--rod": args.rod, "--data": args.data}, "--checkpoint")
    return run_training(args)
