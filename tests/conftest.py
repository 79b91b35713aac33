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


@pytest.fixture(autouse=True, scope="session")
def _kernels_compiled():
    """The CPU kernels compiled (or loaded from the cache) once, before the first test: tests that run the
    command line in a subprocess, and time it or interrupt it, then meet loaded kernels and not a first compile."""
    from torchrod.kernels import targets

    targets.cpu().ready()
    targets.cpu_schedule().ready()


@pytest.fixture(autouse=True)
def _no_stream_time_budget(monkeypatch):
    """``torchrod stream`` without its default time budget: with it, which readings time out depends on the
    machine's speed and load, and tests that compare answers need them to be the same on every run
    (tests/test_budget.py tests the budget itself)."""
    from torchrod.cli.commands import stream

    monkeypatch.setattr(stream, "DEFAULT_TIME_BUDGET_MS", None)
