"""Another name for :mod:`torchrod.synthetic`'s load sets and streams, for code that imports them from here: the
same objects."""

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
