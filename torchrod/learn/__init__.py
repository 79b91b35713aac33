"""Simulated data and the warm-start network: synthetic sets and streams, the network, its training."""
