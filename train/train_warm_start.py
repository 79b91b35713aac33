"""Train the warm-start network: a thin wrapper around :func:`torchrod.cli.commands.train.main` (as
``torchrod train``).

The shipped weights (checkpoints/nitinol290.pt: 200k generated cases, 30 epochs, 5.5 min on two CPU cores):
                  python train/train_warm_start.py --checkpoint checkpoints/nitinol290.pt --no-optimizer-state \
                      --logdir runs/nitinol290
Single process:   python train/train_warm_start.py --generate 200000 --epochs 30 --checkpoint runs/ws.pt
Data parallel:    torchrun --nproc_per_node=2 train/train_warm_start.py ...
Logs:             tensorboard --logdir runs/warm_start
Run ``python train/train_warm_start.py --help`` for every option.
"""

import sys

from torchrod.cli.commands.train import main

if __name__ == "__main__":
    sys.exit(main())
