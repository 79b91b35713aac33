"""``torchrod train``: train the warm-start network (the same entry as ``python train/train_warm_start.py``).

``torchrod train --rod nitinol290 --generate 150000 --epochs 20 --checkpoint my_network.pt``; under
``torchrun --nproc_per_node=N -m torchrod train ...`` it trains with DistributedDataParallel. See
:mod:`torchrod.learn.training` for what is trained and logged.

Where it writes: the network to ``--checkpoint`` (default ``checkpoints/warm_start.pt``) and the logs to ``--logdir``
(default ``runs/warm_start``), both in the current folder; from the repository's root, the network lands in its
top-level ``checkpoints/``, beside the shipped one (only the shipped one installs with the package).

The rod: generating, ``--rod`` (default nitinol290). With ``--data SET`` the network is trained for the set's rod;
a ``--rod`` given as well must agree with it (length, bending stiffness, gratings), else the command stops with
an error naming both instead of silently training for the set's rod.
"""

from __future__ import annotations

import argparse

from ...learn.training import (
    DEFAULT_ROD,
    LABELS,
    TrainConfig,
    distributed_env,
    format_metrics,
    format_quality,
    record_quality,
    train,
)
from ...presets import PRESETS

HELP = "train the warm-start network that gives the estimator its first guess"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The training options (shared by ``train/train_warm_start.py`` and ``torchrod train``)."""
    d = TrainConfig()
    a = parser.add_argument
    a(
        "--rod",
        default=None,
        help=f"preset name ({', '.join(PRESETS)}) or rod JSON file (default {DEFAULT_ROD} when generating; with "
        "--data the set's rod, which a --rod given must match)",
    )
    a(
        "--data",
        default=None,
        help="a saved synthetic set (torchrod generate); default: generate --generate cases",
    )
    a(
        "--generate",
        type=int,
        default=d.generate,
        help="cases generated at start without --data (%(default)s)",
    )
    a("--validation", type=int, default=d.validation, help="held-back cases (%(default)s)")
    a("--max-forces", type=int, default=d.max_forces, help="largest number of forces (%(default)s)")
    a("--epochs", type=int, default=d.epochs, help="%(default)s")
    a("--batch-size", type=int, default=d.batch_size, help="cases per step and process (%(default)s)")
    a("--lr", type=float, default=d.lr, help="peak learning rate (%(default)s)")
    a("--weight-decay", type=float, default=d.weight_decay, help="%(default)s")
    a("--seed", type=int, default=d.seed, help="%(default)s")
    a(
        "--count-weight",
        type=float,
        default=d.count_weight,
        help="weight of the count cross-entropy (%(default)s)",
    )
    a(
        "--physics-weight",
        type=float,
        default=d.physics_weight,
        help="weight of the physics loss (%(default)s)",
    )
    a(
        "--physics-batch",
        type=int,
        default=d.physics_batch,
        help="cases per batch in the physics loss (%(default)s)",
    )
    a("--noise", type=float, default=d.noise, help="sensor noise sigma [1/m] (%(default)s)")
    a(
        "--noise-jitter",
        type=float,
        default=d.noise_jitter,
        help="relative spread of the training noise (%(default)s)",
    )
    a(
        "--missing-prob",
        type=float,
        default=d.missing_prob,
        help="probability of a missing grating (%(default)s)",
    )
    a(
        "--labels",
        default=d.labels,
        choices=LABELS,
        help="what the network learns: the simulated loads ('truth', fresh noise each step), or the search's own fit "
        "of every count and its chosen count on one noisy reading per case ('search': amortises the search; the "
        "labelling runs the search on every case first) (%(default)s)",
    )
    a("--hidden", type=int, default=d.hidden, help="hidden width (%(default)s)")
    a("--depth", type=int, default=d.depth, help="hidden layers (%(default)s)")
    a("--logdir", default=d.logdir, help="tensorboard folder (%(default)s, in the current folder); 'none' for no logs")
    a(
        "--checkpoint",
        default=d.checkpoint,
        help="checkpoint written after every epoch (%(default)s, in the current folder: run from the repository's "
        "root, its checkpoints/ folder)",
    )
    a("--resume", default=None, help="continue from this checkpoint")
    a(
        "--no-optimizer-state",
        dest="optimizer_state",
        action="store_false",
        help="leave the optimiser state out of the checkpoint (smaller; --resume then starts a fresh optimiser)",
    )
    a("--log-every", type=int, default=d.log_every, help="steps between logged losses (%(default)s)")
    a("--device", default=d.device, choices=("auto", "cpu", "cuda"), help="%(default)s")
    a("--threads", type=int, default=None, help="CPU threads per process")
    a("--quiet", action="store_true", help="no progress lines")
    a(
        "--evaluate",
        metavar="CHECKPOINT",
        default=None,
        help="no training: measure CHECKPOINT's held-back quality (--validation readings at --noise) and record it",
    )


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    logdir = None if args.logdir in (None, "", "none") else args.logdir
    return TrainConfig(
        rod=args.rod,
        data=args.data,
        generate=args.generate,
        validation=args.validation,
        max_forces=args.max_forces,
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        weight_decay=args.weight_decay,
        seed=args.seed,
        count_weight=args.count_weight,
        physics_weight=args.physics_weight,
        physics_batch=args.physics_batch,
        noise=args.noise,
        noise_jitter=args.noise_jitter,
        missing_prob=args.missing_prob,
        hidden=args.hidden,
        depth=args.depth,
        logdir=logdir,
        checkpoint=args.checkpoint,
        resume=args.resume,
        optimizer_state=args.optimizer_state,
        log_every=args.log_every,
        device=args.device,
        threads=args.threads,
        progress=not args.quiet,
        labels=args.labels,
    )


def main(argv: list[str] | None = None) -> int:
    """``python train/train_warm_start.py [options]`` (also under torchrun); returns the exit status."""
    parser = argparse.ArgumentParser(prog="train_warm_start", description="train the warm-start network")
    configure(parser)
    return run(parser.parse_args(argv))


def configure(parser: argparse.ArgumentParser) -> None:
    """The command's options (:func:`add_arguments`)."""
    add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """``torchrod train``: as :func:`train_as_asked`, with an existing ``--checkpoint`` refused unless training goes
    on in it (``--resume``) or it is being evaluated."""
    from ...io.jsonl import check_output

    if args.evaluate is None:  # (--evaluate records its quality into the checkpoint it reads, by design)
        # --resume may name the checkpoint written: training goes on in the same file.
        check_output(args.checkpoint, {"--rod": args.rod, "--data": args.data}, "--checkpoint")
    return train_as_asked(args)


def train_as_asked(args: argparse.Namespace) -> int:
    """Train as the parsed options say (see :func:`add_arguments`); rank 0 prints the held-back metrics and the
    quality recorded in the checkpoint. ``--evaluate CHECKPOINT`` instead measures and records an existing
    checkpoint's quality (no training)."""
    if args.evaluate is not None:
        quality = record_quality(args.evaluate, rod=args.rod, count=args.validation, noise=args.noise, seed=args.seed)
        print(format_quality(quality))
        return 0
    result = train(config_from_args(args))
    if distributed_env()[1] == 0 and result.metrics:
        print(format_metrics(result.metrics))
        print(format_quality(result.quality))
    return 0
