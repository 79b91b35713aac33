"""The backends' guarded linear algebra: a broken system fails alone, the others are solved as if it were not there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrod.backend import NUMPY, torch_backend


def _systems(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Seven 3 x 3 positive definite systems, four of them broken, and the indices of the good ones."""
    M = rng.standard_normal((7, 5, 3))
    A = np.swapaxes(M, 1, 2) @ M + 0.1 * np.eye(3)
    b = rng.standard_normal((7, 3))
    A[1, 0, 2] = A[1, 2, 0] = np.nan
    A[2, 1, 1] = np.inf
    b[3, 2] = -np.inf
    A[4] = 0.0  # singular
    A[5] = 1e308 * np.eye(3)  # finite, but its entries' sum overflows: still a good system
    b[5] = 1e308
    return A, b, [0, 5, 6]


@pytest.mark.parametrize("name", ["numpy", "torch"])
@pytest.mark.parametrize("columns", [None, 2])
def test_spd_solve_fails_only_the_broken_systems(rng, name, columns):
    A, b, good = _systems(rng)
    if columns:
        b = np.stack([b, -0.5 * b], 2)
    xp = NUMPY if name == "numpy" else torch_backend()
    x, ok = xp.spd_solve(xp.asarray(A), xp.asarray(b))
    x, ok = np.asarray(x), np.asarray(ok)
    assert ok.tolist() == [i in good for i in range(7)]
    assert np.all(x[~ok] == 0.0)
    for i in good:
        want = np.linalg.solve(A[i], b[i])
        assert np.allclose(x[i], want, rtol=1e-12, atol=0.0), (i, x[i], want)


@pytest.mark.parametrize("name", ["numpy", "torch"])
def test_solve_of_good_systems_takes_no_detour(rng, name):
    """Every system good (the common case): the result is the plain solver's."""
    A, b, good = _systems(rng)
    A, b = A[[0, 6]], b[[0, 6]]
    xp = NUMPY if name == "numpy" else torch_backend()
    x, ok = xp.spd_solve(xp.asarray(A), xp.asarray(b))
    assert bool(np.asarray(ok).all())
    assert np.allclose(np.asarray(x), np.linalg.solve(A, b[..., None])[..., 0], rtol=1e-12, atol=0.0)
    assert torch.is_tensor(x) == (name == "torch")
