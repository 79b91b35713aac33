"""The warm-start network: a first guess of the contact forces from one FBG reading, for the refinement to start from.

The network works in dimensionless form. With s~ = s / L, u~ = u L and f~ = f L^2 / EI the body-frame equations
(:mod:`torchrod.model.body_frame`) read U~'' = -|U~|^2 U~ / 2 with jumps f~ / 1 at the forces: the length and the
stiffness leave the problem. So one network serves every rod whose gratings sit at the same relative positions s_k / L,
whatever its length and stiffness; the checkpoint records that layout and :meth:`WarmStart.load` refuses a rod
whose layout differs (by more than ``LAYOUT_TOLERANCE``).

Input: the reading u~ (B, G, 2) and the grating mask (B, G) (False = missing grating; its values are ignored).
Output, for each possible count h = 1..H: the h forces, sorted by location by construction (the locations are the
cumulative sums of a softmax over h + 1 gaps, each at least ``MIN_GAP``, so 0 < s~_1 < ... < s~_h < 1), and logits for
the count.

The problem is symmetric under a rotation of the cross-section plane (an isotropic rod: rotating every force by an
angle rotates every curvature by it) and under a reflection (u_y -> -u_y is f_x -> -f_x). The network uses both:
it turns each reading to a canonical frame (its largest curvature along +x, the sum of u_y non-negative), predicts
there, and turns the forces back. That leaves the MLP one fundamental domain to learn.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import numbers
import operator
import os
import threading
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any, NamedTuple, cast

import torch
from torch import nn

from ..errors import MissingFileError
from ..estimate.checks import check_readings
from ..estimate.estimator import Estimator
from ..estimate.options import EstimatorOptions
from ..kernels import network as network_kernel
from ..kernels.host import network_rows
from ..loads import PointForces
from ..rod import Rod

# cast: importlib's Traversable is not typed PathLike, though a package's files are paths
SHIPPED_CHECKPOINT = os.fspath(cast("os.PathLike[str]", resources.files("torchrod.data").joinpath("nitinol290.pt")))
"""The shipped warm-start network, trained for the ``nitinol290`` grating layout (``torchrod/data/nitinol290.pt``,
installed with the package; :func:`shipped_network` finds it for a rod)."""

__all__ = [
    "CHECKPOINT_FORMAT",
    "LAYOUT_TOLERANCE",
    "SHIPPED_CHECKPOINT",
    "NetConfig",
    "NetOutput",
    "WarmStart",
    "WarmStartGuess",
    "WarmStartNet",
    "load_checkpoint",
    "save_checkpoint",
    "shipped_network",
    "to_dimensionless",
    "unit_rod",
]

LAYOUT_TOLERANCE = 1e-6
"""Largest difference in relative grating position s_k / L for a rod to match a network's layout."""

CHECKPOINT_FORMAT = "torchrod.warm_start/1"

_VERSION = operator.attrgetter("_version")
"""A tensor's count of its in-place changes (torch's), read without a Python call per parameter."""

# The network's rules, shared with its forward pass for inference (torchrod.kernels.network).
MIN_GAP = network_kernel.MIN_GAP
"""Least gap between guessed locations, and between them and the rod's ends, as a fraction of the length."""


@dataclass(frozen=True)
class NetConfig:
    """Shape and normalisation of a :class:`WarmStartNet`.

    Attributes:
        relative_gratings: the layout, s_k / L for the G gratings, increasing in (0, 1].
        max_forces: H, the largest number of forces the network proposes.
        hidden: width of the hidden layers.
        depth: number of hidden layers.
        curvature_scale: typical |u L| of the training readings (dimensionless); inputs are divided by it.
        force_scale: typical |f| L^2 / EI of the training forces (dimensionless); force outputs are multiples of it.
        intrinsic_curvature: a precurved rod's u*, dimensionless: segments ``(from / L, to / L, ux* L, uy* L)``
            (empty for a straight rod); torsion_ratio: its GJ / EI. Both are part of the layout a network serves.
    """

    relative_gratings: tuple[float, ...]
    max_forces: int = 3
    hidden: int = 192
    depth: int = 3
    curvature_scale: float = 5.0
    force_scale: float = 5.0
    intrinsic_curvature: tuple[tuple[float, float, float, float], ...] = ()
    torsion_ratio: float | None = None

    def __post_init__(self) -> None:
        raw = self.relative_gratings
        if isinstance(raw, (str, bytes, Mapping)) or not isinstance(raw, Iterable):
            raise ValueError(f"relative_gratings must be a list of numbers, got {_brief(raw)}")  # noqa: TRY004
        raw = tuple(raw)
        if any(isinstance(x, bool) or not isinstance(x, numbers.Real) for x in raw):
            raise ValueError(f"relative_gratings must be a list of numbers, got {_brief(list(raw))}")
        g = tuple(float(x) for x in raw)
        if not g or any(not (0.0 <= x <= 1.0) for x in g) or any(b <= a for a, b in itertools.pairwise(g)):
            raise ValueError(f"relative_gratings must increase inside [0, 1], got {_brief(list(g))}")
        object.__setattr__(self, "relative_gratings", g)
        for name in ("max_forces", "hidden", "depth"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {_brief(v)}")
        for name in ("curvature_scale", "force_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v <= 0.0:
                raise ValueError(f"{name} must be positive and finite, got {_brief(v)}")
            object.__setattr__(self, name, float(v))
        # Checked by the rod they describe (the unit rod: lengths in units of L).
        unit = unit_rod(self)
        object.__setattr__(self, "intrinsic_curvature", unit.intrinsic_curvature)
        if self.torsion_ratio is not None:
            object.__setattr__(self, "torsion_ratio", unit.torsion_stiffness)

    @property
    def num_gratings(self) -> int:
        return len(self.relative_gratings)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["relative_gratings"] = list(self.relative_gratings)
        d["intrinsic_curvature"] = [list(x) for x in self.intrinsic_curvature]
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> NetConfig:
        """From :meth:`to_dict`'s form; ``ValueError`` naming an unknown or missing key or a bad value."""
        if not isinstance(data, Mapping):
            raise ValueError(f"a network config must be a mapping, got {type(data).__name__}")  # noqa: TRY004
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            raise ValueError(f"unknown network config keys {unknown}; known keys are {sorted(known)}")
        if "relative_gratings" not in data:
            raise ValueError("the network config lacks 'relative_gratings' (the grating layout)")
        return cls(**data)

    @classmethod
    def for_rod(cls, rod: Rod, **kwargs: Any) -> NetConfig:
        """A config with ``rod``'s layout (and, for a precurved rod, its dimensionless precurvature and GJ / EI)."""
        if rod.precurved:
            L = rod.length
            kwargs.setdefault(
                "intrinsic_curvature", tuple((a / L, b / L, ux * L, uy * L) for a, b, ux, uy in rod.intrinsic_curvature)
            )
            kwargs.setdefault("torsion_ratio", rod.torsion_stiffness / rod.bending_stiffness)
        return cls(relative_gratings=rod.relative_gratings, **kwargs)


class NetOutput(NamedTuple):
    """Raw, dimensionless network output (a tuple, so that DistributedDataParallel can see through it).

    Attributes:
        count_logits: (B, H) logits for 1..H forces.
        s: H tensors, ``s[h-1]`` (B, h): locations s / L, increasing along the last dimension.
        f: H tensors, ``f[h-1]`` (B, h, 2): body-frame components f L^2 / EI.
    """

    count_logits: torch.Tensor
    s: tuple[torch.Tensor, ...]
    f: tuple[torch.Tensor, ...]


def _head_sizes(max_forces: int) -> list[int]:
    # per count h: h + 1 gap logits and 2 h force components
    return [(h + 1) + 2 * h for h in range(1, max_forces + 1)]


class WarmStartNet(nn.Module):
    """Dimensionless reading -> count logits and, for each count, sorted dimensionless forces.

    ``forward(reading, mask)``: reading (B, G, 2) u L (dimensionless; values at missing gratings are ignored),
    mask (B, G) bool (True = grating read). Returns :class:`NetOutput`. Computes in float32 whatever the input
    dtype (the caller casts back; see :class:`WarmStart`).
    """

    stencil: torch.Tensor  # a buffer (register_buffer in __init__)

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        G, H, W = config.num_gratings, config.max_forces, config.hidden
        layers: list[nn.Module] = []
        width = 3 * G + 1 + (3 * (G - 2) if G >= 3 else 0)
        # Three-point second-derivative weights at the interior gratings (non-uniform spacing), dimensionless.
        g = torch.tensor(config.relative_gratings, dtype=torch.float64)
        if G >= 3:
            h1, h2 = g[1:-1] - g[:-2], g[2:] - g[1:-1]
            weights = torch.stack((2 / (h1 * (h1 + h2)), -2 / (h1 * h2), 2 / (h2 * (h1 + h2))), dim=1)
            spacing = float((g[-1] - g[0]) / (G - 1))
        else:
            weights, spacing = torch.zeros(0, 3, dtype=torch.float64), 1.0
        self.register_buffer("stencil", weights.float(), persistent=False)
        self._spacing2 = spacing * spacing
        for _ in range(config.depth):
            layers += [nn.Linear(width, W), nn.LayerNorm(W), nn.SiLU()]
            width = W
        self.body = nn.Sequential(*layers)
        # One output layer for every head: every parameter takes part in every loss (DDP needs no unused ones).
        self.out = nn.Linear(W, H + sum(_head_sizes(H)))

    def forward(self, reading: torch.Tensor, mask: torch.Tensor) -> NetOutput:
        cfg = self.config
        dtype = self.out.weight.dtype
        present = mask.to(torch.bool)
        x = torch.where(present.unsqueeze(-1), reading.to(dtype), torch.zeros((), dtype=dtype, device=reading.device))
        x = x.contiguous()  # viewed as complex below (any layout of the reading: a transposed one keeps its strides)
        turn, sign, zc = _canonical_frame(x, present)
        xc = torch.stack((zc.real, zc.imag * sign.unsqueeze(1)), dim=-1)
        # Shape and size apart: the reading divided by its RMS over the read gratings, and the log of that RMS.
        # In the small-deflection regime forces are linear in the reading, so forces are predicted relative to it.
        pf = present.to(dtype)
        rms = (
            ((xc.square().sum(-1) * pf).sum(1) / pf.sum(1).clamp(min=1.0))
            .sqrt()
            .clamp(min=network_kernel.RMS_FLOOR * cfg.curvature_scale)
        )
        parts = [(xc / rms.view(-1, 1, 1)).flatten(1), pf, torch.log(rms / cfg.curvature_scale).unsqueeze(1)]
        if cfg.num_gratings >= 3:
            parts += list(self._load_density(xc, pf, rms))
        features = torch.cat(parts, dim=1)  # (B, 3G + 1 + 3(G - 2))
        force_unit = (rms * (cfg.force_scale / cfg.curvature_scale)).view(-1, 1, 1)
        raw = self.out(self.body(features))
        H = cfg.max_forces
        count_logits, rest = raw[:, :H], raw[:, H:]
        s_out: list[torch.Tensor] = []
        f_out: list[torch.Tensor] = []
        start = 0
        back = turn.conj().resolve_conj().unsqueeze(1)  # the rotation back to the reading's frame
        for h, size in zip(range(1, H + 1), _head_sizes(H), strict=False):
            chunk = rest[:, start : start + size]
            start += size
            # Every gap at least MIN_GAP: locations strictly inside (0, 1) and strictly increasing, even in float32.
            gaps = MIN_GAP + (1.0 - (h + 1) * MIN_GAP) * torch.softmax(chunk[:, : h + 1], dim=1)
            s_out.append(torch.cumsum(gaps, dim=1)[:, :h])
            fc = chunk[:, h + 1 :].reshape(-1, h, 2) * force_unit
            # Undo the reflection (u_y -> -u_y is f_x -> -f_x), then the rotation (forces turn with the curvature).
            fc = torch.stack((fc[..., 0] * sign.unsqueeze(1), fc[..., 1]), dim=-1)
            f_out.append(torch.view_as_real(torch.view_as_complex(fc) * back))
        return NetOutput(count_logits, tuple(s_out), tuple(f_out))

    def _load_density(self, xc: torch.Tensor, pf: torch.Tensor, rms: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The distributed load the reading implies at the interior gratings, and where it is defined.

        Between forces U'' = -|U|^2 U / 2 (dimensionless form), so r = U'' + |U|^2 U / 2 vanishes away from the
        forces and peaks near each of them: counting forces becomes counting peaks. U'' is the three-point
        difference; r is defined where a grating and both neighbours are read. Returns r h^2 / rms (B, 2(G-2)),
        with h the mean grating spacing, and the validity (B, G-2).
        """
        w = self.stencil.to(xc.dtype)
        second = w[:, 0, None] * xc[:, :-2] + w[:, 1, None] * xc[:, 1:-1] + w[:, 2, None] * xc[:, 2:]
        mid = xc[:, 1:-1]
        r = second + 0.5 * mid.square().sum(-1, keepdim=True) * mid
        valid = pf[:, :-2] * pf[:, 1:-1] * pf[:, 2:]
        r = r * valid.unsqueeze(-1) * (self._spacing2 / rms.view(-1, 1, 1))
        return r.flatten(1), valid


def _canonical_frame(x: torch.Tensor, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The unit complex number turn (B,) whose product with the reading (as u_x + i u_y) takes its largest read
    curvature to +x, the reflection sign (B,) that then makes the sum of u_y over the read gratings non-negative,
    and that product (B, G) complex. No gradient flows through the frame."""
    z = torch.view_as_complex(x)  # (B, G)
    with torch.no_grad():
        mag = z.abs().masked_fill(~present, -1.0)
        ref = z.gather(1, mag.argmax(dim=1, keepdim=True)).squeeze(1)  # (B,)
        norm = ref.abs()
        turn = torch.where(norm > 0, ref.conj() / norm.clamp(min=torch.finfo(norm.dtype).tiny), torch.ones_like(ref))
    turned = z * turn.unsqueeze(1)
    with torch.no_grad():
        sign = torch.where(turned.imag.sum(dim=1) >= 0, 1.0, -1.0).to(x.dtype)
    return turn, sign, turned


# ---------------------------------------------------------------------------------------------------- dimensionless


def unit_rod(layout: NetConfig | Sequence[float]) -> Rod:
    """The dimensionless rod of a network's layout (a :class:`NetConfig`, or the relative grating positions of a
    straight rod): length 1, EI = 1, its gratings, precurvature and GJ / EI (for the physics loss)."""
    if not isinstance(layout, NetConfig):
        return Rod(length=1.0, bending_stiffness=1.0, gratings=tuple(layout))
    segments = cast(
        "tuple[tuple[float, float, float, float], ...]", tuple(tuple(x) for x in layout.intrinsic_curvature)
    )
    return Rod(
        length=1.0,
        bending_stiffness=1.0,
        gratings=layout.relative_gratings,
        intrinsic_curvature=segments,
        torsional_stiffness=layout.torsion_ratio,
    )


def to_dimensionless(rod: Rod, curvature: torch.Tensor | None = None, loads: PointForces | None = None):
    """(u L, PointForces(s / L, f L^2 / EI)) for whichever of ``curvature`` [1/m] and ``loads`` are given."""
    L, EI = rod.length, rod.bending_stiffness
    u = None if curvature is None else curvature * L
    p = None if loads is None else PointForces(loads.s / L, loads.f * (L * L / EI), loads.mask)
    return u, p


# ---------------------------------------------------------------------------------------------------- checkpoints


def save_checkpoint(
    path: str | os.PathLike,
    net: WarmStartNet,
    *,
    step: int = 0,
    epoch: int = 0,
    train_config: Mapping[str, Any] | None = None,
    optimizer: Mapping[str, Any] | None = None,
    metrics: Mapping[str, float] | None = None,
    quality: Mapping[str, float] | None = None,
) -> None:
    """Write a checkpoint that :func:`load_checkpoint` reads with ``weights_only=True``.

    It holds the network's config (layout and normalisation), its float32 weights, the torchrod version, the
    training step and epoch, and optionally the training config, the optimiser state (to resume), metrics and the
    held-back quality measured at the end of training (:data:`QUALITY_KEYS`, read by :func:`quality_verdict`).
    Written to a temporary file first and renamed, so an interrupted save never leaves a broken checkpoint.
    """
    from .. import __version__

    module = cast(WarmStartNet, net.module if hasattr(net, "module") else net)  # (a DistributedDataParallel's)
    payload: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "torchrod_version": __version__,
        "config": module.config.to_dict(),
        "state_dict": {k: v.detach().to("cpu", torch.float32).clone() for k, v in module.state_dict().items()},
        "step": int(step),
        "epoch": int(epoch),
    }
    if train_config is not None:
        payload["train_config"] = dict(train_config)
    if optimizer is not None:
        payload["optimizer"] = optimizer
    if metrics is not None:
        payload["metrics"] = {k: float(v) for k, v in metrics.items()}
    if quality is not None:
        payload["quality"] = {k: float(v) for k, v in quality.items()}
    path = os.fspath(path)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(
    path: str | os.PathLike, *, map_location: str | torch.device | None = "cpu"
) -> tuple[WarmStartNet, dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint` (``torch.load(..., weights_only=True)``: no code runs).

    Returns the network (eval mode, float32) and the rest of the checkpoint (format, version, config, step, epoch,
    train_config, optimizer, metrics, and any further entries, as stored).

    Raises ``FileNotFoundError`` for a missing file and otherwise one ``ValueError`` naming the file and what is
    wrong: a directory or unreadable file; an empty, truncated or damaged one (not a torch file); one that holds
    Python objects other than tensors and plain containers (refused unread by torch's ``weights_only`` check,
    since unpickling them could run code); another format tag; a missing or invalid ``config``, ``step`` or
    ``epoch``; weights missing, unexpected or of another shape than the config describes; non-finite weights.
    """
    name = os.fspath(path)
    payload = _read_checkpoint(name, map_location)
    if not isinstance(payload, dict):
        raise ValueError(  # noqa: TRY004 (a bad file)
            f"{name}: not a warm-start checkpoint (it holds a {type(payload).__name__}, expected a dict with "
            f"format {CHECKPOINT_FORMAT!r})"
        )
    found = payload.get("format")
    if found != CHECKPOINT_FORMAT:
        shown = "no format tag" if "format" not in payload else f"format {_brief(found)}"
        raise ValueError(f"{name}: not a warm-start checkpoint ({shown}, expected {CHECKPOINT_FORMAT!r})")
    config = _checkpoint_config(name, payload)
    for key in ("step", "epoch"):
        value = payload.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            got = "nothing" if key not in payload else _brief(value)
            raise ValueError(f"{name}: damaged checkpoint: {key!r} must be an integer >= 0, got {got}")
    for key in ("train_config", "optimizer", "metrics"):
        if key in payload and not isinstance(payload[key], Mapping):
            raise ValueError(
                f"{name}: damaged checkpoint: {key!r} must be a mapping, got {type(payload[key]).__name__}"
            )
    net = WarmStartNet(config)
    net.load_state_dict(_checkpoint_weights(name, payload, net))
    net.eval()
    meta = {k: v for k, v in payload.items() if k != "state_dict"}
    return net, meta


def _clip(text: str, limit: int = 100) -> str:
    """``text`` on one line, at most ``limit`` characters (for error messages)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _brief(value: Any) -> str:
    """``repr(value)`` on one line, at most about 100 characters (for error messages)."""
    try:
        return _clip(repr(value))
    except Exception:  # noqa: BLE001 -- a value whose repr fails is still named by its type
        return f"a {type(value).__name__}"


def _read_checkpoint(name: str, map_location: str | torch.device | None) -> Any:
    """``torch.load(name, weights_only=True)``, every failure turned into one line naming the file."""
    import pickle

    if os.path.isdir(name):
        raise ValueError(f"{name}: is a directory, not a checkpoint")
    if not os.path.lexists(name):
        raise MissingFileError(
            f"no such checkpoint: {name} (give the path of a file `torchrod train` wrote; the shipped network is "
            "torchrod.learn.warm_start.SHIPPED_CHECKPOINT)"
        )
    try:
        with open(name, "rb") as fh:
            empty = fh.read(1) == b""
    except OSError as exc:
        raise ValueError(f"{name}: cannot read the checkpoint ({exc.strerror or type(exc).__name__})") from None
    if empty:
        raise ValueError(f"{name}: the checkpoint file is empty")
    try:
        return torch.load(name, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's weights_only unpickler refuses anything but tensors and plain containers: either the file names
        # Python objects (unsafe to build, so refused unread) or its bytes are not a pickle at all.
        text = str(exc)
        detail = text.split("WeightsUnpickler error:", 1)[1] if "WeightsUnpickler error:" in text else ""
        detail = " ".join(detail.split("Check the documentation", 1)[0].split())
        if detail.startswith("Unsupported global"):
            words = detail.split()
            what = _clip(words[3], 60) if len(words) > 3 and words[2] == "GLOBAL" else "an unknown global"
            raise ValueError(
                f"{name}: refused: besides tensors and plain containers it holds a Python object ({what}), and "
                "building it could run code (torch's weights_only check)"
            ) from None
        why = detail or f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # noqa: BLE001 -- RuntimeError (zip reader), EOFError, KeyError, ...: a damaged file
        why = f"{type(exc).__name__}: {exc}"
    raise ValueError(f"{name}: not a readable checkpoint (truncated, damaged or not a torch file: {_clip(why, 80)})")


def _checkpoint_config(name: str, payload: Mapping[str, Any]) -> NetConfig:
    """The checkpoint's :class:`NetConfig`, checked, and not larger than the weights the file holds (so a damaged
    config cannot make us build a huge network)."""
    if "config" not in payload:
        raise ValueError(f"{name}: damaged checkpoint: no 'config' (the network's layout and size)")
    raw = payload["config"]
    if not isinstance(raw, Mapping):
        raise ValueError(f"{name}: damaged checkpoint: 'config' must be a mapping, got {type(raw).__name__}")  # noqa: TRY004
    try:
        config = NetConfig.from_dict(raw)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name}: invalid network config: {_clip(str(exc), 160)}") from None
    state = payload.get("state_dict")
    held = sum(v.numel() for v in state.values() if isinstance(v, torch.Tensor)) if isinstance(state, Mapping) else 0
    # Every hidden layer is at least hidden x hidden (the first at least hidden x 3G), the output at least
    # hidden x max_forces: a lower bound on the weights the config describes.
    least = config.hidden * (3 * config.num_gratings + config.max_forces + (config.depth - 1) * config.hidden)
    if least > held:
        raise ValueError(
            f"{name}: its weights do not fit its config: the config describes at least {least} weights "
            f"(hidden {config.hidden}, depth {config.depth}, {config.num_gratings} gratings), the file holds {held}"
        )
    return config


def _checkpoint_weights(name: str, payload: Mapping[str, Any], net: WarmStartNet) -> dict[str, torch.Tensor]:
    """The checkpoint's weights, checked against ``net`` (the network its config describes): the same names and
    shapes, floating point, finite."""
    state = payload.get("state_dict")
    if not isinstance(state, Mapping):
        got = "nothing" if "state_dict" not in payload else type(state).__name__
        raise ValueError(f"{name}: damaged checkpoint: 'state_dict' must be a mapping of weights, got {got}")  # noqa: TRY004
    expected = net.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [str(k) for k in state if k not in expected]
    if missing or unexpected:
        parts = ([f"lacks {_brief(missing)}"] if missing else []) + (
            [f"has unexpected {_brief(unexpected)}"] if unexpected else []
        )
        raise ValueError(f"{name}: its weights do not fit the network its config describes: {'; '.join(parts)}")
    out: dict[str, torch.Tensor] = {}
    for key, want in expected.items():
        value = state[key]
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            kind = f"a {value.dtype} tensor" if isinstance(value, torch.Tensor) else f"a {type(value).__name__}"
            raise ValueError(f"{name}: weight {key!r} must be a floating-point tensor, got {kind}")
        if value.shape != want.shape:
            raise ValueError(
                f"{name}: its weights do not fit the network its config describes: {key!r} has shape "
                f"{tuple(value.shape)}, the config asks for {tuple(want.shape)}"
            )
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise ValueError(
                f"{name}: weight {key!r} holds {bad} non-finite value(s) (NaN or inf): a diverged or damaged "
                "training run"
            )
        out[key] = value
    return out


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
            raise TypeError(f"net must be a WarmStartNet, got {type(net).__name__}")
        if not isinstance(rod, Rod):
            raise TypeError(f"rod must be a Rod, got {type(rod).__name__}")
        self.net = net.eval()
        self.rod = rod
        self.meta = dict(meta or {})
        if not self.matches(rod):
            raise ValueError(self._mismatch(rod))
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
            raise ValueError(f"{os.fspath(path)}: {exc}") from None

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
"""The warm-start networks shipped in :mod:`torchrod.data`, each for one grating layout."""


def shipped_network(rod: Rod) -> tuple[WarmStart | None, str]:
    """The shipped warm-start network that serves ``rod``'s grating layout, or None; with a line that says which
    (or why there is none). ``torchrod estimate`` and ``torchrod stream`` use it when no ``--checkpoint`` is given.

    A network serves every rod whose gratings sit at its layout's positions relative to the length, whatever the
    rod's length and stiffness (the network works in dimensionless form).
    """
    from ..data import path

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
        say(
            f"torchrod: the warm-start network {os.fspath(path)!r} is weak ({weak}); its guesses are used only "
            "beside the scan's starts"
        )
    return Estimator(rod, dataclasses.replace(options, trust_guesses=not weak), warm_start=ws)
