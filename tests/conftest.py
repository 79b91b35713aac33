"""Shared fixtures: the paper's rod and seeded random generators (keep this file small)."""

from __future__ import annotations

import time

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


WITHOUT_KERNELS = frozenset(
    {
        "test_body_frame",
        "test_calibration",
        "test_cli_simulate",
        "test_doc_names",
        "test_errors",
        "test_global_bvp",
        "test_jig",
        "test_jsonl",
        "test_nystrom",
        "test_readings",
        "test_rod_command",
        "test_shape",
    }
)
"""Test modules none of whose tests runs the estimation kernels, in this process or in a command it starts. They run
first, while the kernels compile in a background process on an empty cache (as a first ``torchrod`` command does),
so that the compile, minutes on a small machine, overlaps them instead of holding every test back."""


def _needs_kernels(item: pytest.Item) -> bool:
    module = getattr(item, "module", None)
    return module is None or module.__name__.rpartition(".")[2] not in WITHOUT_KERNELS


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_needs_kernels)  # stable: the kernel-free modules first, each order otherwise kept


@pytest.fixture(autouse=True, scope="session")
def _kernels_compiling(request):
    """The schedule kernels (seconds) compiled now, and the estimation kernels started compiling in a background
    process when a selected test needs them and the cache has none (else loaded now)."""
    from torchrod.kernels import targets

    targets.cpu_schedule().ready()
    if any(_needs_kernels(item) for item in request.session.items):
        targets.cpu().start()


@pytest.fixture(autouse=True)
def _kernels_compiled(request, _kernels_compiling):
    """Before a test that may run the estimation kernels: the background compile finished and the kernels loaded.
    Tests that run the command line in a subprocess, and time it or interrupt it, then meet loaded kernels and not a
    first compile."""
    if _needs_kernels(request.node):
        from torchrod.kernels import targets

        compiled = targets.cpu()
        while compiled.compiling():
            time.sleep(0.2)
        compiled.ready()


@pytest.fixture(autouse=True)
def _no_stream_time_budget(monkeypatch):
    """``torchrod stream`` without its default time budget: with it, which readings time out depends on the
    machine's speed and load, and tests that compare answers need them to be the same on every run
    (tests/test_budget.py tests the budget itself)."""
    from torchrod.cli.commands import stream

    monkeypatch.setattr(stream, "DEFAULT_TIME_BUDGET_MS", None)
