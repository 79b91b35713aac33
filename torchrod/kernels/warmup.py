"""A tiny estimate that compiles (or loads) a target's kernels: one reading of a two-grating rod, every kind of
argument the real calls pass, so the compiled code is the one they use."""

from __future__ import annotations

from typing import Any

import numpy as np

from .layout import OPTIONS, Batch, Setup, Sizes


class _Euler:
    """A one-stage method (the warm-up's answer does not matter, only the arguments' types)."""

    c = np.zeros(1)
    bp = np.full(1, -0.25)
    bv = np.full(1, -0.5)

    @staticmethod
    def matrix() -> np.ndarray:
        return np.zeros((1, 1))


WARM_OPTIONS = {
    "max_forces": 1, "fixed": -1, "starts": 2, "per_interval": 2, "exchange_top": 2, "settle": True, "twins": True,
    "damping": 1e-3, "increase": 4.0, "decrease": 3.0, "max_damping": 1e9, "max_force_step": 10.0,
    "tolerance": 1e-3, "iterations": 5, "exact_steps": 1, "exact_tolerance": 1e-4,
    "acceleration": 0.5, "probe": 0.1, "acceleration_limit": 0.75,
}  # fmt: skip
"""The warm-up's :data:`.layout.OPTIONS` fields that are not 0 (False): counts 0 and 1, chosen; two scan starts of
two candidates per interval and two exchange re-placements (the arenas' sizes); settling and twins on; and a
Levenberg-Marquardt policy under which every step is defined (nothing it divides by is 0, the acceleration finite).
The tiny reading then runs a scan, the fits of both counts with their exact steps, the covariance and the verdict."""


def tiny_setup() -> tuple[Setup, Sizes]:
    """A setup for a straight two-grating rod with counts up to 1, and its sizes."""
    from .host import count_tables, rod_setup, setup_of

    rod, model = rod_setup(
        length=1.0, ei=1.0, gj=1.0, bias=0.0, gratings=[0.2, 0.6], segments=[], breakpoints=[], step_angle=0.3,
        max_steps=4, exact_angle=0.8, exact_max_steps=4, method=_Euler(),
    )  # fmt: skip
    opt = np.zeros(1, OPTIONS).view(np.recarray)
    for name, value in WARM_OPTIONS.items():
        opt[name] = value
    return setup_of(rod, model, opt, count_tables(2, 1, 0.05, 0.95, 0.5, 1e-3), [1])


def tiny_batch(empty: Any = np.empty) -> Batch:
    """One reading for :func:`tiny_setup`."""
    from .host import outputs

    u = np.array([[-0.3, 0.1, -0.1, 0.05]])
    return Batch(u=u, w=np.ones((1, 4)), noise2=np.full(1, 0.01), gs=np.full((1, 1, 1), 0.5),
                 gf=np.zeros((1, 1, 1, 2)), guse=np.ones((1, 1), np.bool_), out=outputs(1, 1, empty))  # fmt: skip


def warm_up(target: str, entry: Any) -> None:
    """Run ``entry`` of ``target`` once on the tiny problem (compiling or loading it)."""
    from .layout import allocate

    setup, sizes = tiny_setup()
    if target == "cuda":
        from numba import cuda

        from .host import _device_empty, _device_setup, simulated

        batch = tiny_batch()
        flag = np.zeros(1, np.int64)
        if not simulated():
            out = type(batch.out)(*(cuda.to_device(x) for x in batch.out))
            u, w, noise2, gs, gf, guse = (cuda.to_device(x) for x in batch[:-1])
            batch = Batch(u, w, noise2, gs, gf, guse, out)
            flag = cuda.to_device(flag)
        arenas = allocate(sizes, (1,), empty=_device_empty)
        entry[1, 1](_device_setup(setup), batch, arenas, flag, 0, 1)
        cuda.synchronize()
        return
    entry(0, 1, setup, tiny_batch(), allocate(sizes), np.zeros(1, np.int64))


def warm_up_schedule(entry: Any) -> None:
    """Run the schedule's ``entry`` once on one row of one force."""
    B, h, Q = 1, 1, 2
    entry(np.array([0.2, 0.6]), np.full((B, h), 0.5), np.ones((B, h, 2)), np.ones(B), 1.0, 0.8, 4,
          np.empty((B, h + Q), np.int64), np.empty((B, h + Q)), np.empty((B, h + Q), np.int64),
          np.empty(h, np.complex128), np.empty(h))  # fmt: skip


def warm_up_network(entry: Any) -> None:
    """Run the network's ``entry`` once on one reading of three gratings through one hidden layer of width 2."""
    G, H, W = 3, 1, 2
    n_in = 3 * G + 1 + 3 * (G - 2)
    params = np.zeros(n_in * W + 3 * W + W * 4 + 4, np.float32)
    layers = np.array([[n_in, W, 0, n_in * W, n_in * W + W, n_in * W + 2 * W],
                       [W, 4, n_in * W + 3 * W, n_in * W + 3 * W + W * 4, -1, -1]], np.int64)  # fmt: skip
    entry(np.ones((1, G, 2)), np.ones((1, G), np.bool_), 1.0, 1.0, params, layers, H, np.ones(4), np.ones((G - 2, 3)),
          np.empty((1, H)), np.empty((1, H, H)), np.empty((1, H, H, 2)), np.empty((G, 2)), np.empty((1, 4)),
          np.empty((1, n_in), np.float32), np.empty((1, n_in), np.float32))  # fmt: skip
