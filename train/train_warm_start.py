"""Train the warm-start network: a thin wrapper around :func:`torchrod.training.main` (same as ``torchrod train``).

Single process:   python train/train_warm_start.py --generate 150000 --epochs 20 --checkpoint checkpoints/nitinol290.pt
Data parallel:    torchrun --nproc_per_node=2 train/train_warm_start.py ...
Logs:             tensorboard --logdir runs/warm_start
Run ``python train/train_warm_start.py --help`` for every option.
"""

import sys

from torchrod.training import main

if __name__ == "__main__":
    sys.exit(main())
