"""Synthetic data made with the forward model: load sets for training and measuring a network
(:mod:`torchrod.synthetic.loadsets`: load cases, their readings, the ``.npz`` file format) and reading streams with
their true forces (:mod:`torchrod.synthetic.trajectories`). ``torchrod generate`` writes both."""

from .loadsets import (
    CHUNK,
    FORMAT,
    FORMAT_VERSION,
    PATCH_PARTS,
    LoadSampler,
    SensorModel,
    SyntheticDataset,
    SyntheticSet,
    generate,
    sample_loads,
    sample_patches,
    total_turning,
    turning_and_peak,
)
from .trajectories import ContactModel, Trajectory, generate_trajectory, truth_path, write_trajectory

__all__ = [
    "CHUNK",
    "FORMAT",
    "FORMAT_VERSION",
    "PATCH_PARTS",
    "ContactModel",
    "LoadSampler",
    "SensorModel",
    "SyntheticDataset",
    "SyntheticSet",
    "Trajectory",
    "generate",
    "generate_trajectory",
    "sample_loads",
    "sample_patches",
    "total_turning",
    "truth_path",
    "turning_and_peak",
    "write_trajectory",
]
