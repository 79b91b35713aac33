"""The warm-start network's checkpoint format: what ``torchrod train`` writes and every loader reads.

A checkpoint is a file ``torch.load(path, weights_only=True)`` reads (no pickled code ever runs), holding a dict:
the format tag :data:`CHECKPOINT_FORMAT`, the network's :class:`~torchrod.learn.network.NetConfig` as plain values,
its weights, and what training records beside them (step, epoch, the training config, the held-back quality).
:func:`load_checkpoint` refuses, naming the file and what is wrong, anything else: a truncated or damaged file, a
config out of range, weights of the wrong shapes or not finite.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, cast

import torch

from ..errors import CheckpointError, MissingFileError
from ..values import brief, clip
from .network import NetConfig, WarmStartNet

__all__ = ["CHECKPOINT_FORMAT", "load_checkpoint", "save_checkpoint"]

CHECKPOINT_FORMAT = "torchrod.warm_start/1"
"""The format tag a checkpoint carries."""


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
    held-back quality measured at the end of training (:data:`torchrod.learn.warm_start.QUALITY_KEYS`, read by
    :func:`torchrod.learn.warm_start.quality_verdict`).
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
        raise CheckpointError(  # noqa: TRY004 (a bad file)
            f"{name}: not a warm-start checkpoint (it holds a {type(payload).__name__}, expected a dict with "
            f"format {CHECKPOINT_FORMAT!r})"
        )
    found = payload.get("format")
    if found != CHECKPOINT_FORMAT:
        shown = "no format tag" if "format" not in payload else f"format {brief(found)}"
        raise CheckpointError(f"{name}: not a warm-start checkpoint ({shown}, expected {CHECKPOINT_FORMAT!r})")
    config = _checkpoint_config(name, payload)
    for key in ("step", "epoch"):
        value = payload.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            got = "nothing" if key not in payload else brief(value)
            raise CheckpointError(f"{name}: damaged checkpoint: {key!r} must be an integer >= 0, got {got}")
    for key in ("train_config", "optimizer", "metrics"):
        if key in payload and not isinstance(payload[key], Mapping):
            raise CheckpointError(
                f"{name}: damaged checkpoint: {key!r} must be a mapping, got {type(payload[key]).__name__}"
            )
    net = WarmStartNet(config)
    net.load_state_dict(_checkpoint_weights(name, payload, net))
    net.eval()
    meta = {k: v for k, v in payload.items() if k != "state_dict"}
    return net, meta


def _read_checkpoint(name: str, map_location: str | torch.device | None) -> Any:
    """``torch.load(name, weights_only=True)``, every failure turned into one line naming the file."""
    import pickle

    if os.path.isdir(name):
        raise CheckpointError(f"{name}: is a directory, not a checkpoint")
    if not os.path.lexists(name):
        raise MissingFileError(
            f"no such checkpoint: {name} (give the path of a file `torchrod train` wrote; the shipped network is "
            "torchrod.learn.warm_start.SHIPPED_CHECKPOINT)"
        )
    try:
        with open(name, "rb") as fh:
            empty = fh.read(1) == b""
    except OSError as exc:
        raise CheckpointError(f"{name}: cannot read the checkpoint ({exc.strerror or type(exc).__name__})") from None
    if empty:
        raise CheckpointError(f"{name}: the checkpoint file is empty")
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
            what = clip(words[3], 60) if len(words) > 3 and words[2] == "GLOBAL" else "an unknown global"
            raise CheckpointError(
                f"{name}: refused: besides tensors and plain containers it holds a Python object ({what}), and "
                "building it could run code (torch's weights_only check)"
            ) from None
        why = detail or f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # noqa: BLE001 -- RuntimeError (zip reader), EOFError, KeyError, ...: a damaged file
        why = f"{type(exc).__name__}: {exc}"
    raise CheckpointError(
        f"{name}: not a readable checkpoint (truncated, damaged or not a torch file: {clip(why, 80)})"
    )


def _checkpoint_config(name: str, payload: Mapping[str, Any]) -> NetConfig:
    """The checkpoint's :class:`NetConfig`, checked, and not larger than the weights the file holds (so a damaged
    config cannot make us build a huge network)."""
    if "config" not in payload:
        raise CheckpointError(f"{name}: damaged checkpoint: no 'config' (the network's layout and size)")
    raw = payload["config"]
    if not isinstance(raw, Mapping):
        raise CheckpointError(f"{name}: damaged checkpoint: 'config' must be a mapping, got {type(raw).__name__}")  # noqa: TRY004
    try:
        config = NetConfig.from_dict(raw)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise CheckpointError(f"{name}: invalid network config: {clip(str(exc), 160)}") from None
    state = payload.get("state_dict")
    held = sum(v.numel() for v in state.values() if isinstance(v, torch.Tensor)) if isinstance(state, Mapping) else 0
    # Every hidden layer is at least hidden x hidden (the first at least hidden x 3G), the output at least
    # hidden x max_forces: a lower bound on the weights the config describes.
    least = config.hidden * (3 * config.num_gratings + config.max_forces + (config.depth - 1) * config.hidden)
    if least > held:
        raise CheckpointError(
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
        raise CheckpointError(f"{name}: damaged checkpoint: 'state_dict' must be a mapping of weights, got {got}")  # noqa: TRY004
    expected = net.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [str(k) for k in state if k not in expected]
    if missing or unexpected:
        parts = ([f"lacks {brief(missing)}"] if missing else []) + (
            [f"has unexpected {brief(unexpected)}"] if unexpected else []
        )
        raise CheckpointError(f"{name}: its weights do not fit the network its config describes: {'; '.join(parts)}")
    out: dict[str, torch.Tensor] = {}
    for key, want in expected.items():
        value = state[key]
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            kind = f"a {value.dtype} tensor" if isinstance(value, torch.Tensor) else f"a {type(value).__name__}"
            raise CheckpointError(f"{name}: weight {key!r} must be a floating-point tensor, got {kind}")
        if value.shape != want.shape:
            raise CheckpointError(
                f"{name}: its weights do not fit the network its config describes: {key!r} has shape "
                f"{tuple(value.shape)}, the config asks for {tuple(want.shape)}"
            )
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise CheckpointError(
                f"{name}: weight {key!r} holds {bad} non-finite value(s) (NaN or inf): a diverged or damaged "
                "training run"
            )
        out[key] = value
    return out
