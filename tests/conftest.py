"""Shared fixtures: the paper's rod and seeded random generators (keep this file small)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchrod as tr


@pytest.fixture
def rod() -> tr.Rod:
    """The paper's Nitinol tube (L = 0.29 m, EI ~ 7.39e-3 N m^2, 14 gratings at 10, 30, ..., 270 mm)."""
    return tr.presets.nitinol290()


@pytest.fixture
def gen() -> torch.Generator:
    """A seeded torch generator (CPU), so every test draws the same cases."""
    return torch.Generator().manual_seed(1234)


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded numpy generator."""
    return np.random.default_rng(1234)
