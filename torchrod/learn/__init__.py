"""The warm-start network: the network, its checkpoints, its training and its inference (the synthetic sets it
learns from are :mod:`torchrod.synthetic`)."""
