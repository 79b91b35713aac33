"""The synthetic load sets and streams under the name they had before :mod:`torchrod.synthetic`, kept for code
that imports them from here: the same objects as :mod:`torchrod.synthetic`'s."""

from ..synthetic import (
    CHUNK,
    FORMAT,
    FORMAT_VERSION,
    ContactModel,
    LoadSampler,
    SensorModel,
    SyntheticDataset,
    SyntheticSet,
    Trajectory,
    generate,
    generate_trajectory,
    sample_loads,
    total_turning,
    truth_path,
    turning_and_peak,
    write_trajectory,
)

__all__ = [
    "CHUNK",
    "FORMAT",
    "FORMAT_VERSION",
    "ContactModel",
    "LoadSampler",
    "SensorModel",
    "SyntheticDataset",
    "SyntheticSet",
    "Trajectory",
    "generate",
    "generate_trajectory",
    "sample_loads",
    "total_turning",
    "truth_path",
    "turning_and_peak",
    "write_trajectory",
]
