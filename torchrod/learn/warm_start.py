"""The warm-start network bound to a rod for inference (:class:`WarmStart`), and whether an estimator may trust it.

The network itself (dimensionless, so one network serves every rod whose gratings sit at the same relative
positions, whatever its length and stiffness) is :mod:`.network`, its file format :mod:`.checkpoint`.
:class:`WarmStart` turns a rod's SI readings into the network's input and its guesses back into SI forces, and
refuses a rod whose layout differs from the network's by more than ``LAYOUT_TOLERANCE``; :func:`quality_verdict`
says whether an estimator may start its fits from the guesses alone (``trust_guesses``), and
:func:`load_estimator` makes an estimator that does so where it may.
"""

from __future__ import annotations

import dataclasses
import math
import operator
import os
import threading
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any, cast

import torch
from torch import nn

from ..errors import CheckpointError, MissingFileError, TorchrodTypeError
from ..estimate.checks import check_readings
from ..estimate.estimator import Estimator
from ..estimate.options import EstimatorOptions
from ..kernels.host import network_rows
from ..loads import PointForces
from ..rod import Rod
from .checkpoint import load_checkpoint
from .network import NetConfig, NetOutput, WarmStartNet

# cast: importlib's Traversable is not typed PathLike, though a package's files are paths
SHIPPED_CHECKPOINT = os.fspath(
    cast("os.PathLike[str]", resources.files("torchrod.checkpoints").joinpath("nitinol290.pt"))
)
"""The shipped warm-start network, trained for the ``nitinol290`` grating layout (the repository's
``checkpoints/nitinol290.pt``, installed with the package as ``torchrod.checkpoints``; :func:`shipped_network` finds
it for a rod)."""

__all__ = [
    "LAYOUT_TOLERANCE",
    "SHIPPED_CHECKPOINT",
    "WarmStart",
    "WarmStartGuess",
    "shipped_network",
]

LAYOUT_TOLERANCE = 1e-6
"""Largest difference in relative grating position s_k / L for a rod to match a network's layout."""


_VERSION = operator.attrgetter("_version")
"""A tensor's count of its in-place changes (torch's), read without a Python call per parameter."""


# ---------------------------------------------------------------------------------------------------- inference


@dataclass(frozen=True)
class WarmStartGuess:
    """The network's guesses for one batch of readings, in SI units and model coordinates (no location bias).

    Attributes:
        count_probs: (B, H) probability of 1..H forces.
        forces: for each count h in 1..H, ``PointForces`` with s (B, h) [m] (increasing) and f (B, h, 2) [N].
    """

    count_probs: torch.Tensor
    forces: dict[int, PointForces]

    @property
    def count(self) -> torch.Tensor:
        """(B,) the most probable number of forces (1..H)."""
        return self.count_probs.argmax(dim=1) + 1

    @property
    def max_forces(self) -> int:
        return self.count_probs.shape[1]


class WarmStart:
    """A trained :class:`WarmStartNet` bound to a rod: SI readings in, SI force guesses out.

    Build it with :meth:`load`. The rod supplies the length and stiffness that turn the dimensionless network into
    SI; its gratings must sit at the network's relative positions (:meth:`matches`).
    """

    def __init__(self, net: WarmStartNet, rod: Rod, meta: Mapping[str, Any] | None = None) -> None:
        if not isinstance(net, WarmStartNet):
            raise TorchrodTypeError(f"net must be a WarmStartNet, got {type(net).__name__}")
        if not isinstance(rod, Rod):
            raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
        self.net = net.eval()
        self.rod = rod
        self.meta = dict(meta or {})
        if not self.matches(rod):
            raise CheckpointError(self._mismatch(rod))
        self._on: dict[torch.device, WarmStartNet] = {next(net.parameters()).device: self.net}
        self._forward: dict[tuple[torch.device, torch.dtype], Callable[[torch.Tensor, torch.Tensor], Any]] = {}
        self._forward_lock = threading.Lock()
        self._cpu: tuple[Any, ...] | None = None  # (the parameters, their versions, _pack's arrays)

    @classmethod
    def load(cls, path: str | os.PathLike, rod: Rod) -> WarmStart:
        """The network in checkpoint ``path`` for ``rod``.

        Raises what :func:`load_checkpoint` raises for a bad file, and ``ValueError`` naming the file if the
        network's grating layout differs from ``rod``'s.
        """
        net, meta = load_checkpoint(path)
        try:
            return cls(net, rod, meta)
        except ValueError as exc:
            raise CheckpointError(f"{os.fspath(path)}: {exc}") from None

    @property
    def config(self) -> NetConfig:
        return self.net.config

    @property
    def max_forces(self) -> int:
        return self.net.config.max_forces

    def matches(self, rod: Rod) -> bool:
        """True if ``rod``'s gratings sit at the network's relative positions (within ``LAYOUT_TOLERANCE``)."""
        mine = self.net.config.relative_gratings
        theirs = rod.relative_gratings
        same = len(mine) == len(theirs) and all(
            abs(a - b) <= LAYOUT_TOLERANCE for a, b in zip(mine, theirs, strict=False)
        )
        # A precurved rod (or a network trained for one) also needs the same dimensionless precurvature and GJ / EI.
        other = NetConfig.for_rod(rod)
        shape = [x for seg in self.net.config.intrinsic_curvature for x in seg]
        other_shape = [x for seg in other.intrinsic_curvature for x in seg]
        same_shape = len(shape) == len(other_shape) and all(
            abs(a - b) <= LAYOUT_TOLERANCE * max(1.0, abs(a)) for a, b in zip(shape, other_shape, strict=False)
        )
        ratio, other_ratio = self.net.config.torsion_ratio, other.torsion_ratio
        same_torsion = (ratio is None) == (other_ratio is None) and (
            ratio is None or abs(ratio - cast(float, other_ratio)) <= LAYOUT_TOLERANCE * ratio  # both or neither None
        )
        return same and same_shape and same_torsion

    def _mismatch(self, rod: Rod) -> str:
        mine = [round(x, 6) for x in self.net.config.relative_gratings]
        theirs = [round(x, 6) for x in rod.relative_gratings]
        if mine != theirs:
            return (
                f"the warm-start network was trained for gratings at relative positions {mine} (s/L), "
                f"but the rod has {theirs}"
            )
        other = NetConfig.for_rod(rod)
        return (
            "the warm-start network was trained for a rod with dimensionless precurvature "
            f"{[list(x) for x in self.net.config.intrinsic_curvature]} (s/L, u* L) and GJ/EI "
            f"{self.net.config.torsion_ratio}, but the rod has {[list(x) for x in other.intrinsic_curvature]} and "
            f"{other.torsion_ratio}"
        )

    def _net_on(self, device: torch.device) -> WarmStartNet:
        net = self._on.get(device)
        if net is None:
            net = WarmStartNet(self.net.config).to(device)
            net.load_state_dict(self.net.state_dict())
            net.eval()
            self._on[device] = net
        return net

    def _forward_on(self, device: torch.device, dtype: torch.dtype) -> Callable[[torch.Tensor, torch.Tensor], Any]:
        """The guesses' forward pass for inference on ``device`` (:class:`_SI`: readings of ``dtype`` [1/m] in, the
        count probabilities and the forces in SI and ``dtype`` out): traced (:func:`_traced`) where tracing gives
        the eager pass's outputs, else the eager pass."""
        key = (device, dtype)
        forward = self._forward.get(key)
        if forward is None:
            with self._forward_lock:
                forward = self._forward.get(key)
                if forward is None:
                    si = _SI(self._net_on(device), self.rod.length, self.rod.bending_stiffness, dtype)
                    traced = _traced(si, device, dtype)
                    forward = self._forward[key] = traced if traced is not None else si
        return forward

    def _packed(self) -> tuple[Any, ...]:
        """The network's parameters as its forward pass for inference on the CPU takes them (:func:`_pack`), packed
        again whenever one of them has changed in place since (torch counts each tensor's changes, and
        ``load_state_dict`` copies into them)."""
        packed = self._cpu
        if packed is None or tuple(map(_VERSION, packed[0])) != packed[1]:
            with self._forward_lock:
                tensors = tuple(self.net.parameters())
                packed = self._cpu = (tensors, tuple(map(_VERSION, tensors)), _pack(self.net))
        return packed[2]

    def ready(self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64) -> None:
        """Make the forward pass for readings of ``dtype`` on ``device`` now (first calls then pay nothing): on the
        CPU the compiled pass (compiled or loaded), elsewhere torch's trace."""
        device = torch.device(device)
        if device.type == "cpu":
            G = self.net.config.num_gratings
            self.compiled_arrays(torch.zeros(1, G, 2, dtype=dtype), torch.ones(1, G, dtype=torch.bool))
        else:
            self._forward_on(device, dtype)

    def guess(self, curvature: torch.Tensor, mask: torch.Tensor | None = None) -> WarmStartGuess:
        """Guesses for every count 1..H, and the count probabilities.

        Args:
            curvature: (B, G, 2) readings (u_x, u_y) at the rod's gratings [1/m]; values at missing gratings are
                ignored (they may be NaN).
            mask: (B, G) bool, True where the grating was read; ``None`` = the gratings with finite values.
        Returns:
            :class:`WarmStartGuess` with tensors of ``curvature``'s dtype and device (no gradient).
        """
        curvature, mask = check_readings(curvature, mask, self.net.config.num_gratings)
        return self._guess(curvature, mask)

    def _guess(self, curvature: torch.Tensor, mask: torch.Tensor) -> WarmStartGuess:
        """:meth:`guess` of readings already checked (the estimator's, which checks its input once): on the CPU by
        the network's compiled forward pass (:mod:`torchrod.kernels.network`), each reading's guesses the same in any
        batch; on another device (a GPU) by torch's."""
        if curvature.device.type == "cpu":
            return self._compiled_guess(curvature, mask)
        forward = self._forward_on(curvature.device, curvature.dtype)
        with torch.inference_mode():  # cheaper than no_grad at small batch
            probs, s, f = forward(curvature.detach(), mask)
        # Outside inference mode: the results are ordinary tensors (callers may modify them in place).
        forces = {h: PointForces(s_h, f_h) for h, (s_h, f_h) in enumerate(zip(s, f, strict=True), start=1)}
        return WarmStartGuess(probs, forces)

    def compiled_arrays(self, curvature: torch.Tensor, mask: torch.Tensor, compiled: bool = True) -> tuple[Any, ...]:
        """The guesses of checked CPU readings from the network's forward pass in :mod:`torchrod.kernels.network`
        (``compiled`` False: its source run as Python), as NumPy arrays (float64, SI): the count probabilities
        (B, H), and the locations (B, H, H) [m] and forces (B, H, H, 2) [N] of each count h in ``[:, h - 1, :h]``."""
        rod = self.rod
        u = curvature.detach().to(torch.float64).numpy()
        force_si = rod.bending_stiffness / rod.length**2
        return network_rows(u, mask.numpy(), rod.length, force_si, self._packed(), self.max_forces, compiled)

    def _compiled_guess(self, curvature: torch.Tensor, mask: torch.Tensor, compiled: bool = True) -> WarmStartGuess:
        """:meth:`compiled_arrays` as a :class:`WarmStartGuess` in ``curvature``'s dtype."""
        probs, s, f = self.compiled_arrays(curvature, mask, compiled)
        dtype = curvature.dtype

        def tensor(x: Any) -> torch.Tensor:
            t = torch.from_numpy(x)
            return t if dtype == torch.float64 else t.to(dtype)

        s_all, f_all = tensor(s), tensor(f)
        out = {h: PointForces(s_all[:, h - 1, :h], f_all[:, h - 1, :h]) for h in range(1, self.max_forces + 1)}
        return WarmStartGuess(tensor(probs), out)


def _pack(net: WarmStartNet) -> tuple[Any, ...]:
    """``net``'s parameters for :mod:`torchrod.kernels.network` (its docstring): float32 weights transposed to (in,
    out), biases, the layer norms' gains and shifts in one array, the layers' offsets into it, the scales, the
    second-derivative stencil, and the widest layer (the scratch's size)."""
    import numpy as np

    cfg = net.config
    modules = [*net.body, net.out]
    linears = [m for m in modules if isinstance(m, nn.Linear)]
    norms = [m for m in modules if isinstance(m, nn.LayerNorm)]
    chunks: list[np.ndarray] = []
    table = []
    at = 0

    def put(t: torch.Tensor) -> int:
        nonlocal at
        chunks.append(t.detach().to("cpu", torch.float32).contiguous().numpy().ravel())
        start, at = at, at + chunks[-1].size
        return start

    for k, linear in enumerate(linears):
        row = [linear.in_features, linear.out_features, put(linear.weight.t()), put(linear.bias), -1, -1]
        if k < len(norms):
            row[4:] = [put(norms[k].weight), put(norms[k].bias)]
        table.append(row)
    eps = norms[0].eps if norms else 1e-5
    scales = np.array([cfg.curvature_scale, cfg.force_scale, net._spacing2, eps])
    layers = np.array(table, np.int64)
    return (
        np.concatenate(chunks),
        layers,
        scales,
        net.stencil.detach().to("cpu", torch.float64).numpy().copy(),
        int(max(layers[0, 0], layers[:, 1].max())),
    )


class _SI(nn.Module):
    """A network's guesses in SI units: readings [1/m] -> (count probabilities (B, H), locations s[h-1] (B, h) [m],
    forces f[h-1] (B, h, 2) [N]), each in ``dtype``. The scaling is part of the traced pass (:func:`_traced`), so
    that a batch of one reading does not pay Python's dispatch for each of its small operations."""

    def __init__(self, net: WarmStartNet, length: float, bending_stiffness: float, dtype: torch.dtype) -> None:
        super().__init__()
        self.net, self.length, self.force_scale, self.dtype = net, length, bending_stiffness / length**2, dtype

    def forward(
        self, curvature: torch.Tensor, mask: torch.Tensor
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        out = NetOutput(*self.net(curvature * self.length, mask))
        probs = torch.softmax(out.count_logits, dim=1).to(self.dtype)
        s = tuple((s_h * self.length).to(self.dtype) for s_h in out.s)
        f = tuple((f_h * self.force_scale).to(self.dtype) for f_h in out.f)
        return probs, s, f


def _traced(net: _SI, device: torch.device, dtype: torch.dtype) -> Any:
    """``net``'s forward pass for inference traced by :func:`torch.jit.trace` (None where that fails or disagrees).

    Run from the trace, the same operations skip Python's dispatch of each one: at a batch of one reading, where the
    network's many small operations cost more than its arithmetic, this halves its cost. The trace shares the
    network's parameters, so it follows any later change to them. It is kept only if it reproduces the eager pass's
    outputs exactly on two test batches (readings of ``dtype``); torch marks the tracer deprecated, so its warnings
    are silenced here, and a torch without it leaves the eager pass in use.
    """
    G = net.net.config.num_gratings
    examples = []
    for B in (1, 3):
        reading = torch.linspace(-3.0, 2.0, B * G * 2, dtype=dtype, device=device).reshape(B, G, 2)
        mask = torch.ones((B, G), dtype=torch.bool, device=device)
        if G > 1:
            mask[-1, G // 2] = False  # a missing grating
        examples.append((reading, mask))
    try:
        with warnings.catch_warnings(), torch.inference_mode():
            warnings.simplefilter("ignore")
            traced = torch.jit.trace(net, examples[1], check_trace=False)
            for example in examples:
                eager, again = net(*example), traced(*example)
                if not all(torch.equal(a, b) for a, b in zip(_flat(eager), _flat(again), strict=True)):
                    return None
    except Exception:  # noqa: BLE001 - any failure of the tracer leaves the eager pass, which is always right
        return None
    return traced


def _flat(out: tuple[torch.Tensor, tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]) -> list[torch.Tensor]:
    return [out[0], *out[1], *out[2]]


# ---------------------------------------------------------------------------------------------------- quality
QUALITY_KEYS = (
    "count_accuracy",
    "force_error_median",
    "location_error_median",
    "readings",
    "noise",
    "search_count_accuracy",
    "search_force_error_median",
    "search_location_error_median",
    "trusted_count_accuracy",
    "trusted_force_error_median",
    "trusted_location_error_median",
    "search_evaluations",
    "trusted_evaluations",
    "plain_evaluations",
    "trusted_worse_fits",
)
"""What a checkpoint records of its held-back quality (:func:`torchrod.learn.training.held_back_quality`), on
``readings`` readings it never saw, at noise ``noise`` [1/m]. Three answers to each reading, each scored by the
share of readings whose count it gets right and, over those, the median relative force error and the median
location error [m]: the network alone (no prefix), the estimator with the guesses beside its scan's starts
(``search_``), and the estimator with the guesses starting the fits alone (``trusted_``); the estimator's mean
evaluations per reading in those two ways and without a network (``plain_evaluations``); and the share of readings
whose answer from the guesses alone has a loss higher than the full search's by more than sigma^2
(``trusted_worse_fits``)."""

TRUST_TOLERANCE = {
    "count_accuracy": 0.005,
    "force_error_median": 0.05,
    "location_error_median": 0.05,
    "worse_fits": 0.005,
}
"""How much worse than the full search the estimator may answer held-back readings when it starts the fits from
the network's guesses alone, for the network to be trusted: a count accuracy lower by at most 0.005 (half a point),
median force and location errors higher by at most 5 % (relative), and at most 0.5 % of the readings answered with
a fit worse than the full search's (a loss higher by more than sigma^2: a wrong local minimum the medians do not
show). It must also cost fewer evaluations than the
estimator without a network: trusting exists to save work, and the search's guards keep even a bad network's
answers accurate, at the price of more evaluations. A weaker network is said to be weak, once, by
:func:`load_estimator`, which then uses its guesses beside the scan's starts, so it cannot make
results worse. The network alone is not the test: on readings whose forces the noise hides, no estimator can count
them, and the prior a network learns can count better than any fit without being a good start
(docs/guides/network.md)."""


UNTRUSTED_ADVICE = (
    "its guesses only add starts beside the scan's, so the answers are as accurate as without it, at a few more "
    "evaluations per reading; to save those, leave it out (--checkpoint none, or an Estimator without a warm start); "
    "to make it pay, train on more cases for longer at your sensor's noise (torchrod train --generate, --epochs, "
    "--noise) and measure it again (torchrod train --evaluate CHECKPOINT --rod ROD)"
)
"""What to do about a network that is not trusted: said the same way by the warning, ``torchrod train``'s report and
the docs."""


def quality_verdict(meta: Mapping[str, Any]) -> str:
    """Why a checkpoint's network is weak ('' when trusting it loses no more than :data:`TRUST_TOLERANCE` and saves
    evaluations)."""
    quality = meta.get("quality")
    how = "record one with `torchrod train --evaluate CHECKPOINT --rod ROD`"
    if not isinstance(quality, Mapping):
        return f"it records no held-back quality; {how}"
    missing = [k for k in QUALITY_KEYS[5:] if not _finite(quality.get(k))]
    if missing:
        return f"it records no comparison of trusted and full-search answers ({', '.join(missing)}); {how}"
    why = []
    worse = float(quality["trusted_worse_fits"])
    if worse > TRUST_TOLERANCE["worse_fits"]:
        why.append(f"trusting it, {worse:.1%} of held-back readings end in a worse fit than the full search's")
    for key, tolerance in TRUST_TOLERANCE.items():
        if key == "worse_fits":
            continue
        search, trusted = float(quality[f"search_{key}"]), float(quality[f"trusted_{key}"])
        if key == "count_accuracy" and trusted < search - tolerance:
            why.append(f"trusting it, the held-back count accuracy falls from {search:.1%} to {trusted:.1%}")
        elif key != "count_accuracy" and trusted > search * (1.0 + tolerance):
            name = key.replace("_", " ")
            why.append(f"trusting it, the held-back {name} rises from {search:.3g} to {trusted:.3g}")
    trusted, plain = float(quality["trusted_evaluations"]), float(quality["plain_evaluations"])
    if not trusted < plain:
        why.append(f"trusted, it costs {trusted:.1f} evaluations per reading against {plain:.1f} without it")
    return "; ".join(why)


def is_trusted(network: Any) -> bool:
    """Whether an estimator may start its fits from ``network``'s guesses alone (``trust_guesses``): its
    checkpoint's recorded quality says nothing against it (:func:`quality_verdict`). False for None, and for a
    network without a checkpoint's record."""
    return network is not None and not quality_verdict(getattr(network, "meta", None) or {})


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


SHIPPED_NETWORKS = ("nitinol290.pt",)
"""The warm-start networks shipped with the package (:mod:`torchrod.data` finds them), each for one grating layout."""


def shipped_network(rod: Rod) -> tuple[WarmStart | None, str]:
    """The shipped warm-start network that serves ``rod``'s grating layout, or None; with a line that says which
    (or why there is none). ``torchrod estimate`` and ``torchrod stream`` use it when no ``--checkpoint`` is given.

    A network serves every rod whose gratings sit at its layout's positions relative to the length, whatever the
    rod's length and stiffness (the network works in dimensionless form).
    """
    from ..shipped import path

    for name in SHIPPED_NETWORKS:
        net, meta = load_checkpoint(path(name))
        try:
            return WarmStart(net, rod, meta), f"the shipped warm-start network {name}"
        except ValueError:  # another grating layout (WarmStart.matches)
            continue
    return None, (
        "no shipped warm-start network fits this rod's grating layout; estimating without one (as accurate, "
        "slower: `torchrod train` makes one)"
    )


def load_estimator(
    path: str | os.PathLike,
    rod: Rod,
    options: EstimatorOptions | None = None,
    *,
    warn: Callable[[str], None] | None = None,
) -> Estimator:
    """An estimator whose starts include a trained warm-start network's guesses.

    The network is used when its grating layout (positions relative to the length) matches ``rod``'s. A
    checkpoint whose recorded held-back quality says that its guesses alone answer as well as the full search
    (:data:`TRUST_TOLERANCE`) is trusted: its guesses start the fits alone, and the scan serves the fits found
    suspicious (``trust_guesses``). Otherwise the network is said to be weak, once, through ``warn`` (default: a
    :class:`UserWarning`), and its guesses are starts beside the scan's, so it cannot make results worse. When the
    layout does not match (or the file is damaged), the estimator runs without a network and says so, and how to
    train one; a path that does not exist is an error (:class:`~torchrod.MissingFileError`).

    Args:
        path: a checkpoint written by ``torchrod train`` (loaded with ``weights_only=True``).
        rod: the rod to estimate on.
        options: estimator settings (default :class:`~torchrod.EstimatorOptions`).
        warn: where the notes on the network go (default: :func:`warnings.warn`).
    """
    if not os.path.exists(path):
        raise MissingFileError(f"checkpoint {os.fspath(path)!r} does not exist (the shipped network of the "
                               "nitinol290 preset: torchrod.learn.warm_start.SHIPPED_CHECKPOINT)")  # fmt: skip
    say = warn if warn is not None else (lambda m: warnings.warn(m, UserWarning, stacklevel=3))
    options = options if options is not None else EstimatorOptions()
    try:
        ws = WarmStart.load(path, rod)
    except (ValueError, FileNotFoundError, OSError) as exc:
        say(
            f"torchrod: no warm-start network for this rod ({exc}); estimating without one (the scan finds "
            "the starts, slower but as accurate); train one with `torchrod generate` and `torchrod train` "
            "(README, 'The warm-start network')"
        )
        return Estimator(rod, options)
    weak = quality_verdict(ws.meta)
    if weak:
        say(f"torchrod: the warm-start network {os.fspath(path)!r} is not trusted ({weak}): {UNTRUSTED_ADVICE}")
    return Estimator(rod, dataclasses.replace(options, trust_guesses=not weak), warm_start=ws)
