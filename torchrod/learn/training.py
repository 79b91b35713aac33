"""Training the warm-start network (:mod:`torchrod.learn.warm_start`) on simulated readings.

One entry point, :func:`train`, driven by a frozen :class:`TrainConfig`; ``python train/train_warm_start.py`` and
``torchrod train`` build the config from the command line (:func:`torchrod.cli.commands.train.add_arguments`,
:func:`torchrod.cli.commands.train.config_from_args`) and call
it. Under ``torchrun --nproc_per_node=N`` it trains with DistributedDataParallel (gloo on CPU, nccl on CUDA), each
process taking its share of every epoch through a DistributedSampler; only rank 0 logs and saves.

Labels (``labels``). By default the network learns the simulated loads. With ``"search"`` it learns instead the
search's own fit of every count and the count it chooses, on one fixed noisy reading per case
(:mod:`torchrod.learn.labels`): every head is trained on its count's fit, and a reading the search answers with no
force takes no part in the count's cross-entropy.

Data. The load cases and their clean readings come from a :class:`torchrod.synthetic.loadsets.SyntheticSet` (``data``: a
saved set) or are generated at start (``generate`` cases, seeded). Every training step draws fresh sensor noise and
fresh missing gratings for its batch (a per-step seed, so a resumed run draws what the uninterrupted run would
have): the noise level of each case is ``noise * U(1 - noise_jitter, 1 + noise_jitter)`` [1/m]. A held-back set
(``validation`` cases, another seed, noise exactly ``noise``) measures the network after every epoch.

Loss, all dimensionless (s / L, f L^2 / EI, u L; :mod:`torchrod.learn.warm_start`):

* cross-entropy of the count logits, weighted by ``count_weight``;
* for the head of the true count h, a Huber loss on the h locations (in units of ``LOCATION_UNIT``) and on the h
  force components (in units of ``FORCE_UNIT`` x the network's force scale). Both the truth and the head are
  sorted by location, so they pair up in order;
* the physics loss, weighted by ``physics_weight``: the differentiable rod model
  (:func:`torchrod.model.body_frame.grating_curvature` on the unit rod) applied to the true count's predicted forces,
  against the noisy input reading, mean squared over the read gratings, in units of the curvature scale. It runs
  on the first ``physics_batch`` cases of each batch (measured on two CPU cores, batch 512: a step takes about
  11 ms without it and 14 to 15 ms with 64 to 256 cases in it).

Logs (tensorboard, ``logdir``): the loss terms, learning rate, and after each epoch on the held-back set the count
accuracy (overall and by number of forces), the median location [mm] and force [N] errors by number of forces, and
a figure of a few fits. Checkpoints (``checkpoint``) hold the network config and normalisation, the weights, the
torchrod version, step and epoch, the training config and the optimiser state; ``resume`` continues from one.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import sys
import textwrap
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from ..errors import OptionsError
from ..loads import PointForces
from ..model.body_frame import grating_curvature
from ..presets import load as load_rod
from ..rod import Rod
from .checkpoint import load_checkpoint, save_checkpoint
from .network import NetConfig, WarmStartNet, unit_rod
from .warm_start import WarmStart, WarmStartGuess

__all__ = [
    "DEFAULT_ROD",
    "FORCE_UNIT",
    "LABELS",
    "LOCATION_UNIT",
    "TrainConfig",
    "TrainResult",
    "TrainingData",
    "evaluate_guess",
    "format_metrics",
    "format_quality",
    "held_back_quality",
    "record_quality",
    "train",
]

DEFAULT_ROD = "nitinol290"
"""The rod simulated when generating training cases without ``rod`` (the paper's tube)."""

LABELS = ("truth", "search")
"""What a network may be trained on (:attr:`TrainConfig.labels`)."""

LOCATION_UNIT = 0.02
"""Location errors enter the loss in units of 0.02 L (about 6 mm on the 290 mm rod)."""
FORCE_UNIT = 0.05
"""Force errors enter the loss in units of 0.05 x the network's force scale."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (the command line turns into one of these at the edge).

    Attributes:
        rod: preset name or rod JSON file. Generating (no ``data``): the rod to simulate, None meaning
            ``DEFAULT_ROD``. With ``data`` the set's own rod is used; a ``rod`` given as well must agree with it
            (length, stiffness, gratings: :meth:`Rod.differences`), else ``ValueError`` naming both.
        data: a saved :class:`~torchrod.synthetic.loadsets.SyntheticSet`, or None to generate ``generate`` cases.
        generate: number of training cases generated at start when ``data`` is None.
        validation: number of held-back cases, generated with another seed.
        max_forces: largest number of forces (H) in the data and the network.
        epochs: passes over the training cases (a resumed run continues up to this many).
        batch_size: cases per step and per process.
        lr: peak learning rate (AdamW; linear warm-up over ``warmup`` of the steps, then cosine decay to 1 %).
        weight_decay: AdamW weight decay.
        warmup: fraction of the steps spent warming up.
        seed: seeds the data, the initial weights, the shuffling and the per-step sensor noise.
        count_weight: weight of the count cross-entropy (the regression terms have weight 1).
        physics_weight: weight of the physics loss (0 switches it off).
        physics_batch: cases per batch that enter the physics loss.
        noise: sensor noise level sigma [1/m] (training jitters it per case, validation uses it exactly).
        noise_jitter: relative spread of the training noise level, in [0, 1).
        missing_prob: probability that a grating is missing in a reading.
        hidden, depth: network width and number of hidden layers.
        logdir: tensorboard folder, or None for no logs (a relative path is in the current folder).
        checkpoint: where the checkpoint is written after every epoch (a relative path is in the current folder:
            the default, from the repository's root, is its ``checkpoints/`` folder).
        resume: a checkpoint to continue from (network, optimiser, step, epoch), or None.
        optimizer_state: store the optimiser state in the checkpoint (what ``resume`` needs to continue exactly;
            without it a resumed run starts a fresh optimiser, and the file is three times smaller).
        log_every: steps between logged training losses.
        figure_cases: held-back cases drawn in the fit figure after each epoch.
        device: ``auto`` (CUDA when present), ``cpu`` or ``cuda``.
        threads: CPU threads per process (None: torch's default, divided among local processes).
        progress: print a line per epoch (rank 0).
        labels: what the network learns: ``"truth"``, the simulated loads, each step on fresh noise; or
            ``"search"``, the search's own fit of every count and the count it chooses, on one noisy reading per
            case drawn at ``noise`` (:mod:`torchrod.learn.labels`): a network that amortises the search.
    """

    rod: str | None = None
    data: str | None = None
    generate: int = 200_000
    validation: int = 4096
    max_forces: int = 3
    epochs: int = 30
    batch_size: int = 512
    lr: float = 3e-3
    weight_decay: float = 1e-4
    warmup: float = 0.03
    seed: int = 0
    count_weight: float = 5.0
    physics_weight: float = 0.1
    physics_batch: int = 128
    noise: float = 0.1
    noise_jitter: float = 0.5
    missing_prob: float = 0.05
    hidden: int = 256
    depth: int = 4
    logdir: str | None = "runs/warm_start"
    checkpoint: str = "checkpoints/warm_start.pt"
    resume: str | None = None
    optimizer_state: bool = True
    log_every: int = 50
    figure_cases: int = 4
    device: str = "auto"
    threads: int | None = None
    progress: bool = True
    labels: str = "truth"

    def __post_init__(self) -> None:
        positive = (
            "generate",
            "validation",
            "max_forces",
            "epochs",
            "batch_size",
            "hidden",
            "depth",
            "log_every",
        )
        for name in positive:
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise OptionsError(f"{name} must be a positive integer, got {v!r}")
        for name in (
            "lr",
            "noise_jitter",
            "missing_prob",
            "warmup",
            "weight_decay",
            "physics_weight",
            "noise",
            "count_weight",
        ):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise OptionsError(f"{name} must be a finite number >= 0, got {v!r}")
        if self.lr <= 0:
            raise OptionsError(f"lr must be positive, got {self.lr}")
        if self.noise_jitter >= 1 or self.missing_prob >= 1 or self.warmup >= 1:
            raise OptionsError(
                f"noise_jitter, missing_prob and warmup must be < 1, got {self.noise_jitter}, "
                f"{self.missing_prob}, {self.warmup}"
            )
        if not isinstance(self.physics_batch, int) or self.physics_batch < 0:
            raise OptionsError(f"physics_batch must be an integer >= 0, got {self.physics_batch!r}")
        if self.labels not in LABELS:
            raise OptionsError(f"labels must be one of {', '.join(map(repr, LABELS))}, got {self.labels!r}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise OptionsError(f"device must be 'auto', 'cpu' or 'cuda', got {self.device!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise OptionsError(f"threads must be a positive integer or None, got {self.threads!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------------------------------- data


@dataclass(frozen=True)
class TrainingData:
    """Load cases and their clean readings, dimensionless (see :mod:`torchrod.learn.warm_start`).

    Attributes:
        rod: the rod the cases were simulated on (its length and stiffness made them dimensionless).
        s: (N, H) locations s / L, sorted, padding last (any value).
        f: (N, H, 2) forces f L^2 / EI (zero for padding).
        count: (N,) number of forces, 1..H.
        clean: (N, G, 2) noiseless readings u L.
        mask: (N, G) bool, gratings the data set says are read (fresh random gaps are added on top in training).
        reading: None, or (N, G, 2) fixed noisy readings u L that training uses as they are (no fresh noise or
            gaps): those the search labelled (:meth:`with_search_labels`).
        fits: None, or the search's fit of every count on ``reading``: s (N, H, H) (row h - 1 holds h
            locations s / L), f (N, H, H, 2) (f L^2 / EI) and whether each converged (N, H); ``count`` is then
            the search's chosen count, 0..H.
    """

    rod: Rod
    s: torch.Tensor
    f: torch.Tensor
    count: torch.Tensor
    clean: torch.Tensor
    mask: torch.Tensor
    reading: torch.Tensor | None = None
    fits: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def from_loads(
        cls, rod: Rod, loads: PointForces, clean: torch.Tensor, mask: torch.Tensor | None = None
    ) -> TrainingData:
        """From SI load cases (N, H) and their clean readings (N, G, 2) [1/m] on ``rod``."""
        loads = loads.sorted()
        L, EI = rod.length, rod.bending_stiffness
        active = loads.active
        if bool((active.sum(1) == 0).any()):
            raise OptionsError("every training case needs at least one force")
        N, G = clean.shape[0], rod.num_gratings
        if clean.shape != (N, G, 2) or loads.batch_size != N:
            raise OptionsError(
                f"clean must have shape (N, G, 2) = ({loads.batch_size}, {G}, 2), got {tuple(clean.shape)}"
            )
        if mask is None:
            mask = torch.ones(N, G, dtype=torch.bool)
        s = torch.where(active, loads.s / L, torch.zeros_like(loads.s))
        f = loads.masked_f() * (L * L / EI)
        return cls(
            rod=rod,
            s=s.to(torch.float32).cpu(),
            f=f.to(torch.float32).cpu(),
            count=active.sum(1).cpu(),
            clean=(clean * L).to(torch.float32).cpu(),
            mask=mask.to(torch.bool).cpu(),
        )

    @classmethod
    def from_set(cls, data: Any) -> TrainingData:
        """From a :class:`torchrod.synthetic.loadsets.SyntheticSet` (its clean readings and mask)."""
        return cls.from_loads(data.rod, data.loads, data.clean, data.mask)

    def with_search_labels(
        self, noise: float, missing_prob: float, seed: int, progress: Callable[[int, int], None] | None = None
    ) -> TrainingData:
        """These cases with one noisy reading each (sigma ``noise`` [1/m], each grating missing with probability
        ``missing_prob``, from ``seed``) and the search's fits of them as the targets
        (:func:`torchrod.learn.labels.search_labels`)."""
        from .labels import search_labels

        L, EI = self.rod.length, self.rod.bending_stiffness
        gen = torch.Generator().manual_seed(seed)
        reading = self.clean + (noise * L) * torch.randn(self.clean.shape, generator=gen)
        mask = self.mask & (torch.rand(self.mask.shape, generator=gen) >= missing_prob)
        u = reading.to(torch.float64) / L
        labels = search_labels(self.rod, u, mask, noise, max_forces=self.max_forces, progress=progress)
        fit_s = torch.nan_to_num(labels.s / L, nan=0.0).to(torch.float32)
        fit_f = (labels.f * (L * L / EI)).to(torch.float32)
        fits = (fit_s, fit_f, labels.fitted)
        return dataclasses.replace(self, count=labels.count, mask=mask, reading=reading, fits=fits)

    def __len__(self) -> int:
        return self.s.shape[0]

    @property
    def max_forces(self) -> int:
        return self.s.shape[1]

    def normalisation(self) -> dict[str, float]:
        """Typical scales: RMS |u L| over all readings and RMS |f L^2/EI| over all real forces."""
        u = torch.linalg.vector_norm(self.clean, dim=-1)
        active = torch.arange(self.max_forces).unsqueeze(0) < self.count.unsqueeze(1)
        fm = torch.linalg.vector_norm(self.f, dim=-1)[active]
        return {
            "curvature_scale": float(u.square().mean().sqrt()),
            "force_scale": float(fm.square().mean().sqrt()),
        }


def _simulated(rod: Rod, count: int, max_forces: int, seed: int, noise: float, missing_prob: float):
    from ..synthetic import LoadSampler, SensorModel, generate

    return generate(
        rod,
        count,
        sampler=LoadSampler(max_forces=max_forces),
        sensor=SensorModel(noise=noise, missing_prob=missing_prob),
        seed=seed,
    )


def _mix(*parts: int) -> int:
    """A 63-bit seed from integers (SplitMix64-style), so per-step generators never collide in practice."""
    x = 0x9E3779B97F4A7C15
    for p in parts:
        x = (x ^ (int(p) & 0xFFFFFFFFFFFFFFFF)) * 0xBF58476D1CE4E5B9 & 0xFFFFFFFFFFFFFFFF
        x = (x ^ (x >> 31)) * 0x94D049BB133111EB & 0xFFFFFFFFFFFFFFFF
    return x >> 1


def noisy_batch(
    data: TrainingData,
    index: torch.Tensor,
    *,
    noise: float,
    jitter: float,
    missing_prob: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Readings u L (B, G, 2) with fresh noise and their masks (B, G) for the cases ``index`` (on the CPU); the
    data's own fixed readings where it holds them (labelled by the search)."""
    if data.reading is not None:
        return data.reading[index], data.mask[index]
    clean = data.clean[index]
    B, G, _ = clean.shape
    level = noise * data.rod.length * (1.0 + jitter * (2.0 * torch.rand(B, 1, 1, generator=generator) - 1.0))
    reading = clean + level * torch.randn(clean.shape, generator=generator)
    present = data.mask[index] & (torch.rand(B, G, generator=generator) >= missing_prob)
    return reading, present


# ---------------------------------------------------------------------------------------------------- losses


def _padded_head(out_s: tuple[torch.Tensor, ...], out_f: tuple[torch.Tensor, ...], count: torch.Tensor):
    """The true count's head of every case, padded to H: s (B, H), f (B, H, 2), mask (B, H)."""
    H = len(out_s)
    B = count.shape[0]
    s = out_s[0].new_zeros(B, H)
    f = out_f[0].new_zeros(B, H, 2)
    for h in range(1, H + 1):
        sel = (count == h).to(s.dtype)
        s = s + sel.unsqueeze(1) * F.pad(out_s[h - 1], (0, H - h))
        f = f + sel.view(B, 1, 1) * F.pad(out_f[h - 1], (0, 0, 0, H - h))
    mask = torch.arange(H, device=count.device).unsqueeze(0) < count.unsqueeze(1)
    return s, f, mask


def compute_losses(
    net: torch.nn.Module,
    config: NetConfig,
    reading: torch.Tensor,
    present: torch.Tensor,
    s_true: torch.Tensor,
    f_true: torch.Tensor,
    count: torch.Tensor,
    *,
    physics_weight: float,
    physics_batch: int,
    count_weight: float = 1.0,
    fits: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> dict[str, torch.Tensor]:
    """The loss terms of one batch (dimensionless tensors, see the module docstring); ``total`` is their sum.
    With the search's ``fits`` (s (B, H, H), f (B, H, H, 2), converged (B, H): :class:`TrainingData`), every
    head learns its count's fit, and a count of 0 takes no part in the cross-entropy."""
    out = net(reading, present)
    counted = count > 0
    target = torch.where(counted, count - 1, -100)
    ce = F.cross_entropy(out.count_logits, target, ignore_index=-100, reduction="sum") / counted.sum().clamp(min=1)
    s, f, mask = _padded_head(out.s, out.f, count)
    funit = FORCE_UNIT * config.force_scale
    if fits is None:
        w = mask.to(s.dtype)
        n = w.sum()
        loc = (F.smooth_l1_loss(s / LOCATION_UNIT, s_true / LOCATION_UNIT, reduction="none") * w).sum() / n
        force = (F.smooth_l1_loss(f / funit, f_true / funit, reduction="none").sum(-1) * w).sum() / n
    else:
        fit_s, fit_f, fitted = fits
        loc = s.new_zeros(())
        force = s.new_zeros(())
        n = fitted.to(s.dtype).sum().clamp(min=1.0)
        for h in range(1, len(out.s) + 1):
            w = fitted[:, h - 1].to(s.dtype)[:, None]
            ds = F.smooth_l1_loss(out.s[h - 1] / LOCATION_UNIT, fit_s[:, h - 1, :h] / LOCATION_UNIT, reduction="none")
            df = F.smooth_l1_loss(out.f[h - 1] / funit, fit_f[:, h - 1, :h] / funit, reduction="none").sum(-1)
            loc = loc + (ds * w).sum() / h
            force = force + (df * w).sum() / h
        loc, force = loc / n, force / n
    total = count_weight * ce + loc + force
    terms = {"count": ce, "location": loc, "force": force}
    if physics_weight > 0 and physics_batch > 0:
        P = min(physics_batch, reading.shape[0])
        loads = PointForces(s[:P], f[:P], mask[:P])
        rod = unit_rod(config)
        u = grating_curvature(rod, loads)
        r = (u - reading[:P]) / config.curvature_scale
        wp = present[:P].to(r.dtype).unsqueeze(-1)
        physics = (r.square() * wp).sum() / (2.0 * wp.sum()).clamp(min=1.0)
        total = total + physics_weight * physics
        terms["physics"] = physics
    terms["total"] = total
    terms["_logits"] = out.count_logits
    return terms


# ---------------------------------------------------------------------------------------------------- evaluation


def evaluate_guess(guess: WarmStartGuess, truth: PointForces) -> dict[str, float]:
    """Accuracy of warm-start guesses against the true loads (SI).

    The count accuracy compares the most probable count with the true one; the location [m] and force [N] errors
    take, for a case with h forces, the guess for h forces (both sorted by location, paired in order), per force.
    Returns ``count_accuracy``, and for each h present in ``truth``: ``count_accuracy_h``, ``cases_h``,
    ``location_error_median_h`` [m], ``force_error_median_h`` [N] (the norm of the (f_x, f_y) error).
    """
    truth = truth.sorted()
    count = truth.count.to(guess.count.device)
    metrics: dict[str, float] = {"count_accuracy": float((guess.count == count).double().mean())}
    for h in range(1, guess.max_forces + 1):
        sel = count == h
        if not bool(sel.any()):
            continue
        g = guess.forces[h]
        ds = (g.s[sel] - truth.s[sel, :h].to(g.s)).abs()
        df = torch.linalg.vector_norm(g.f[sel] - truth.f[sel, :h].to(g.f), dim=-1)
        metrics[f"cases_{h}"] = float(sel.sum())
        metrics[f"count_accuracy_{h}"] = float((guess.count[sel] == h).double().mean())
        metrics[f"location_error_median_{h}"] = float(ds.flatten().quantile(0.5))
        metrics[f"force_error_median_{h}"] = float(df.flatten().quantile(0.5))
    return metrics


def _answer_quality(count: torch.Tensor, forces_of: Callable[[int], PointForces], truth: PointForces) -> list[float]:
    """[count accuracy, median relative force error, median location error (m)] of answers: ``count`` (B,) the
    counts given, ``forces_of(h)`` their h-force answers (B, h) (read where the count is h), against the sorted
    ``truth``; the errors over the readings whose count is right."""
    right = count == truth.count
    rel, loc = [], []
    for h in range(1, int(truth.count.max()) + 1 if truth.count.numel() else 1):
        sel = right & (truth.count == h)
        if not bool(sel.any()):
            continue
        g = forces_of(h)
        gs, gf = g.s[sel].to(truth.s), g.f[sel].to(truth.f)
        tf = truth.f[sel, :h]
        rel.append((torch.linalg.vector_norm(gf - tf, dim=-1) / torch.linalg.vector_norm(tf, dim=-1)).flatten())
        loc.append((gs - truth.s[sel, :h]).abs().flatten())

    def median(xs):
        return float(torch.cat(xs).quantile(0.5)) if xs else math.nan

    return [float(right.double().mean()), median(rel), median(loc)]


def held_back_quality(
    network: WarmStart, curvature: torch.Tensor, mask: torch.Tensor | None, truth: PointForces, noise: float
) -> dict[str, float]:
    """The quality a checkpoint records (:data:`torchrod.learn.warm_start.QUALITY_KEYS`) on held-back readings
    (``curvature`` (B, G, 2) [1/m], ``mask`` (B, G), the ``truth`` that made them, sensor ``noise`` [1/m]).

    Three answers are scored: the network's own guess (its most probable count, and its guess for that count), the
    estimator with the network's guesses beside its scan's starts, and the estimator with the guesses starting the
    fits alone (``trust_guesses``); with the estimator's evaluations per reading in both ways, and without a
    network, and the share of readings whose answer from the guesses alone fits worse than the full search's (its
    loss higher by more than sigma^2). They decide whether the network is trusted
    (:func:`torchrod.learn.warm_start.quality_verdict`). The estimator's accuracy without a network
    (``plain_count_accuracy``, ``plain_force_error_median``, ``plain_location_error_median``) is recorded beside
    them, for the report (:func:`format_quality`) to show what the network changes."""
    from ..estimate.estimator import Estimator, EstimatorOptions

    truth = truth.sorted().to(device="cpu", dtype=torch.float64)
    curvature = curvature.to(device="cpu", dtype=torch.float64)
    mask = mask.to(device="cpu") if mask is not None else None
    guess = network.guess(curvature, mask)
    scores = {"": _answer_quality(guess.count.cpu(), lambda h: guess.forces[h].sorted(), truth)}
    quality = {"readings": float(truth.count.numel()), "noise": float(noise)}
    losses = {}
    for prefix, trust, net in (("search_", False, network), ("trusted_", True, network), ("plain_", False, None)):
        est = Estimator(network.rod, EstimatorOptions(noise=noise, trust_guesses=trust), warm_start=net)
        r = est.estimate(curvature, mask)
        quality[f"{prefix}evaluations"] = float(r.evaluations.double().mean())
        losses[prefix] = r.loss
        found = r.forces

        def forces_of(h: int, found: PointForces = found) -> PointForces:
            return PointForces(found.s[:, :h], found.f[:, :h]).sorted()

        scores[prefix] = _answer_quality(r.num_forces, forces_of, truth)
    for prefix, (count_accuracy, force, location) in scores.items():
        quality[f"{prefix}count_accuracy"] = count_accuracy
        quality[f"{prefix}force_error_median"] = force
        quality[f"{prefix}location_error_median"] = location
    # A reading whose answer from the guesses alone fits worse than the full search's by more than sigma^2: the
    # guesses led to a wrong local minimum that nothing found suspicious.
    worse = losses["trusted_"] > losses["search_"] + float(noise) ** 2
    quality["trusted_worse_fits"] = float(worse.double().mean())
    return quality


QUALITY_ROWS = (
    ("plain_", "estimator without the network"),
    ("search_", "estimator, guesses beside the scan"),
    ("trusted_", "estimator, guesses alone (trusted)"),
    ("", "the network alone"),
)
"""The rows of :func:`format_quality`: the prefix of the recorded keys, and what answered."""


def format_quality(quality: Mapping[str, float]) -> str:
    """A checkpoint's recorded held-back quality as one block: the estimator's accuracy without the network, with
    its guesses beside the scan and with its guesses alone, and the network's own, side by side; then whether the
    estimator trusts the network and, when it does not, what to do."""
    from .warm_start import UNTRUSTED_ADVICE, quality_verdict

    def cell(key: str, scale: float, unit: str, digits: int) -> str:
        value = quality.get(key)
        return f"{scale * value:.{digits}f}{unit}" if isinstance(value, (int, float)) and math.isfinite(value) else "-"

    lines = [
        f"held-back quality: {int(quality['readings'])} readings the network never saw, noise {quality['noise']:g} 1/m "
        "(errors: medians over the readings whose count is right)",
        f"  {'':<36}{'count right':>12}{'force error':>13}{'location error':>16}{'evaluations':>13}",
    ]
    for prefix, who in QUALITY_ROWS:
        if f"{prefix}count_accuracy" not in quality and f"{prefix}evaluations" not in quality:
            continue
        lines.append(
            f"  {who:<36}{cell(f'{prefix}count_accuracy', 100, ' %', 1):>12}"
            f"{cell(f'{prefix}force_error_median', 100, ' %', 1):>13}"
            f"{cell(f'{prefix}location_error_median', 1e3, ' mm', 2):>16}"
            f"{cell(f'{prefix}evaluations', 1, '', 1) if prefix else '':>13}"
        )
    if "plain_evaluations" in quality and "plain_count_accuracy" not in quality:
        lines.append(
            "  (this checkpoint records no accuracy without the network: `torchrod train --evaluate CHECKPOINT --rod "
            "ROD` measures it)"
        )
    alone, search = quality.get("count_accuracy"), quality.get("search_count_accuracy")
    if alone is not None and search is not None and alone > search:
        lines.append(
            "  The network alone counts more readings right than the estimator: held-back readings include forces "
            "too weak for\n  the gratings to show, which the estimator leaves out (it adds a force only when the "
            "reading needs it) and the\n  network's prior need not. The estimator's count is the one the data "
            "support."
        )
    if "trusted_worse_fits" in quality:
        lines.append(
            f"  readings whose fit from the guesses alone is worse than the full search's by more than sigma^2: "
            f"{100 * quality['trusted_worse_fits']:.1f} %"
        )
    weak = quality_verdict({"quality": quality})
    if not weak:
        lines.append("  trusted: yes: the estimator starts its fits from the network's guesses alone")
        return "\n".join(line.rstrip() for line in lines)
    lines.append(f"  trusted: no ({weak})")
    advice = f"What to do: {UNTRUSTED_ADVICE}."
    lines.append(textwrap.fill(advice, width=118, initial_indent="  ", subsequent_indent="  "))
    return "\n".join(line.rstrip() for line in lines)


def fit_figure(rod: Rod, curvature: torch.Tensor, mask: torch.Tensor, guess: WarmStartGuess, truth: PointForces):
    """A matplotlib figure of a few readings (dots), the curvature of the guessed forces (lines, the most probable
    count) and the true (dashed) and guessed (solid) force locations."""
    from matplotlib.figure import Figure

    from ..model.body_frame import simulate

    B = curvature.shape[0]
    fig = Figure(figsize=(4.0 * B, 3.2), layout="constrained")
    axes = fig.subplots(1, B, squeeze=False)[0]
    grat = [1e3 * g for g in rod.gratings]
    counts = guess.count.tolist()
    truth_lists = truth.to_lists()
    for b, ax in enumerate(axes):
        h = counts[b]
        loads = guess.forces[h][b].to(torch.float64, "cpu")
        loads = PointForces(loads.s.clamp(0.0, rod.length), loads.f)
        sim = simulate(rod, loads, samples=120)
        sx = (1e3 * sim.s).tolist()
        m = mask[b].cpu().tolist()
        for k, (name, colour) in enumerate((("u_x", "tab:blue"), ("u_y", "tab:orange"))):
            ax.plot(sx, sim.curvature[0, :, k].tolist(), color=colour, label=f"{name} guess")
            ys = curvature[b, :, k].cpu().tolist()
            ax.plot(
                [g for g, keep in zip(grat, m, strict=False) if keep],
                [y for y, keep in zip(ys, m, strict=False) if keep],
                "o",
                color=colour,
                ms=3,
                label=f"{name} read",
            )
        for s, _, _ in truth_lists[b]:
            ax.axvline(1e3 * s, color="k", ls="--", lw=0.8)
        for s in loads.s[0].tolist():
            ax.axvline(1e3 * s, color="tab:red", lw=0.8)
        ax.set_title(
            f"true {len(truth_lists[b])} forces, guess {h} (p={float(guess.count_probs[b, h - 1]):.2f})",
            fontsize=9,
        )
        ax.set_xlabel("s [mm]")
    axes[0].set_ylabel("curvature [1/m]")
    axes[0].legend(fontsize=7)
    return fig


# ---------------------------------------------------------------------------------------------------- training


@dataclass
class TrainResult:
    """What :func:`train` returns (on every rank).

    Attributes:
        net: the trained network (unwrapped, on the training device).
        step: optimiser steps taken in total (resumed runs included).
        epoch: last completed epoch (1-based).
        metrics: held-back metrics after the last epoch (rank 0; empty on the other ranks).
        history: per epoch, the mean training loss terms (this process's batches).
        quality: the held-back quality recorded in the checkpoint (:func:`held_back_quality`; rank 0, else empty).
    """

    net: WarmStartNet
    step: int
    epoch: int
    metrics: dict[str, float]
    history: list[dict[str, float]]
    quality: dict[str, float] = dataclasses.field(default_factory=dict)


def _lr_at(step: int, total: int, config: TrainConfig) -> float:
    warm = max(1, int(config.warmup * total))
    if step < warm:
        return config.lr * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1, total - warm))
    return config.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))


class _Sized:
    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n


def distributed_env() -> tuple[int, int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    return world, rank, local


def train(
    config: TrainConfig, *, data: TrainingData | None = None, log: Callable[[str], None] | None = None
) -> TrainResult:
    """Train (or resume training) the warm-start network as ``config`` says; see the module docstring.

    Args:
        config: the run.
        data: training cases to use instead of ``config.data`` / ``config.generate`` (tests; the held-back set is
            still generated).
        log: where progress lines go (rank 0); default: stderr when ``config.progress``.
    Returns:
        :class:`TrainResult`.

    Distributed: with ``WORLD_SIZE`` > 1 in the environment (torchrun sets it, with RANK, LOCAL_RANK,
    MASTER_ADDR and MASTER_PORT) the process group is initialised here and destroyed at the end.
    """
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel
    from torch.utils.data.distributed import DistributedSampler

    world, rank, local_rank = distributed_env()
    if config.device == "cuda" or (config.device == "auto" and torch.cuda.is_available()):
        device = torch.device("cuda", local_rank if world > 1 else torch.cuda.current_device())
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
    # Process-level settings belong to the entry point: this function is one (the script and the CLI call it).
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    elif world > 1 and device.type == "cpu":
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local_world))
    distributed = world > 1
    owns_group = False
    if distributed and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        owns_group = True
    main_rank = rank == 0
    if log is None:
        log = (lambda msg: print(msg, file=sys.stderr, flush=True)) if config.progress else (lambda msg: None)
    say = log if main_rank else (lambda msg: None)

    try:
        return _train(
            config,
            data,
            device,
            world,
            rank,
            distributed,
            main_rank,
            say,
            DistributedDataParallel,
            DistributedSampler,
        )
    finally:
        if owns_group:
            # Without a collection here, a process of a two-process gloo run now and then aborted at exit (SIGABRT,
            # "terminate called without an active exception"); with it, none did. Why is not established.
            gc.collect()
            dist.destroy_process_group()


def _train(config, data, device, world, rank, distributed, main_rank, say, DDP, DistributedSampler) -> TrainResult:
    t0 = time.perf_counter()
    given = load_rod(config.rod) if config.rod is not None else None  # a bad --rod fails before any data loads
    if data is None:
        if config.data is not None:
            from ..synthetic import SyntheticSet

            data = TrainingData.from_set(SyntheticSet.load(config.data))
            say(f"loaded {len(data)} cases from {config.data}")
        else:
            rod = given if given is not None else load_rod(DEFAULT_ROD)
            data = TrainingData.from_set(_simulated(rod, config.generate, config.max_forces, config.seed, 0.0, 0.0))
            say(f"generated {len(data)} cases in {time.perf_counter() - t0:.1f} s")
    rod = data.rod
    if given is not None and (diff := rod.differences(given)):
        source = f"the data set {config.data}" if config.data is not None else "the training data"
        raise OptionsError(
            f"--rod {config.rod} contradicts {source}, made for another rod: {'; '.join(diff)} (the set's value "
            "first); leave out --rod to train for the set's rod"
        )
    if data.max_forces != config.max_forces:
        raise OptionsError(f"the data hold up to {data.max_forces} forces but max_forces is {config.max_forces}")
    if config.labels == "search" and data.fits is None:
        tl = time.perf_counter()
        data = data.with_search_labels(config.noise, config.missing_prob, _mix(config.seed, 3))
        say(f"labelled {len(data)} cases with the search's fits in {time.perf_counter() - tl:.0f} s")
    held = (
        _simulated(rod, config.validation, config.max_forces, _mix(config.seed, 1), config.noise, config.missing_prob)
        if main_rank
        else None
    )

    meta: dict[str, Any] = {}
    if config.resume is not None:
        net, meta = load_checkpoint(config.resume)
        net_config = net.config
        if len(net_config.relative_gratings) != rod.num_gratings or not WarmStart(net, rod).matches(rod):
            raise OptionsError(f"{config.resume}: its network does not match the rod's grating layout")
        say(f"resuming from {config.resume} (epoch {meta['epoch']}, step {meta['step']})")
    else:
        net_config = NetConfig.for_rod(
            rod,
            max_forces=config.max_forces,
            hidden=config.hidden,
            depth=config.depth,
            **data.normalisation(),
        )
        with torch.random.fork_rng(devices=[]):  # the initial weights, from the seed alone: the same on every rank
            torch.manual_seed(config.seed)
            net = WarmStartNet(net_config)
    net = net.to(device).train()
    model = DDP(net, device_ids=[device] if device.type == "cuda" else None) if distributed else net
    optimiser = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    if "optimizer" in meta:
        optimiser.load_state_dict(meta["optimizer"])
    elif config.resume is not None:
        say(f"{config.resume} holds no optimiser state: continuing with a fresh optimiser")
    step = int(meta.get("step", 0))
    first_epoch = int(meta.get("epoch", 0)) + 1

    sampler = DistributedSampler(
        _Sized(len(data)), num_replicas=world, rank=rank, shuffle=True, seed=config.seed, drop_last=True
    )
    steps_per_epoch = len(sampler) // config.batch_size
    if steps_per_epoch < 1:
        raise OptionsError(f"{len(data)} cases over {world} processes make no batch of {config.batch_size}")
    total_steps = steps_per_epoch * config.epochs
    writer = None
    if main_rank and config.logdir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(config.logdir, purge_step=step if step else None)
        if step == 0:
            writer.add_text("config", "\n".join(f"    {k}: {v}" for k, v in config.to_dict().items()))
    say(
        f"training {sum(p.numel() for p in net.parameters())} parameters on {device} x {world}, "
        f"{steps_per_epoch} steps per epoch, epochs {first_epoch}..{config.epochs}"
    )

    metrics: dict[str, float] = {}
    history: list[dict[str, float]] = []
    epoch = first_epoch - 1
    try:
        for epoch in range(first_epoch, config.epochs + 1):
            sampler.set_epoch(epoch)
            order = torch.tensor(list(iter(sampler)), dtype=torch.long)
            sums: dict[str, float] = {}
            window: dict[str, float] = {}
            window_n = 0
            correct = 0
            seen = 0
            te = time.perf_counter()
            for i in range(steps_per_epoch):
                index = order[i * config.batch_size : (i + 1) * config.batch_size]
                gen = torch.Generator().manual_seed(_mix(config.seed, step, rank))
                reading, present = noisy_batch(
                    data,
                    index,
                    noise=config.noise,
                    jitter=config.noise_jitter,
                    missing_prob=config.missing_prob,
                    generator=gen,
                )
                count = data.count[index].to(device)
                fits = None if data.fits is None else tuple(x[index].to(device) for x in data.fits)
                for group in optimiser.param_groups:
                    group["lr"] = _lr_at(step, total_steps, config)
                terms = compute_losses(
                    model,
                    net_config,
                    reading.to(device),
                    present.to(device),
                    data.s[index].to(device),
                    data.f[index].to(device),
                    count,
                    physics_weight=config.physics_weight,
                    physics_batch=config.physics_batch,
                    count_weight=config.count_weight,
                    fits=fits,
                )
                optimiser.zero_grad(set_to_none=True)
                terms["total"].backward()
                torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
                optimiser.step()
                step += 1
                logits = terms.pop("_logits").detach()
                correct += int((logits.argmax(1) + 1 == count).sum())
                seen += count.numel()
                values = {k: float(v.detach()) for k, v in terms.items()}
                for k, v in values.items():
                    sums[k] = sums.get(k, 0.0) + v
                    window[k] = window.get(k, 0.0) + v
                window_n += 1
                if writer is not None and step % config.log_every == 0:
                    for k, v in window.items():
                        writer.add_scalar(f"train/loss_{k}", v / window_n, step)
                    writer.add_scalar("train/lr", optimiser.param_groups[0]["lr"], step)
                    window, window_n = {}, 0
            means = {k: v / steps_per_epoch for k, v in sums.items()}
            means["count_accuracy"] = correct / max(1, seen)
            history.append(means)
            if main_rank:
                metrics = _validate(net, rod, held, writer, step, config)
                train_dict = config.to_dict()
                save_checkpoint(
                    config.checkpoint,
                    net,
                    step=step,
                    epoch=epoch,
                    train_config=train_dict,
                    optimizer=optimiser.state_dict() if config.optimizer_state else None,
                    metrics=metrics,
                )
                say(
                    f"epoch {epoch}/{config.epochs} step {step}: loss {means['total']:.4f} "
                    f"(count {means['count']:.3f}, location {means['location']:.3f}, force {means['force']:.3f}"
                    + (f", physics {means['physics']:.3f}" if "physics" in means else "")
                    + f"), held-back count accuracy {metrics['count_accuracy']:.3f}, "
                    f"{time.perf_counter() - te:.0f} s"
                )
    finally:
        if writer is not None:
            writer.close()
    net.eval()
    quality: dict[str, float] = {}
    if main_rank:
        # The quality measured at the end of training, on the held-back set, goes into the checkpoint: an
        # estimator told to use this network can tell whether to trust it (warm_start.quality_verdict).
        assert held is not None  # made on the main rank
        quality = held_back_quality(WarmStart(net, rod), held.curvature, held.mask, held.loads, config.noise)
        save_checkpoint(
            config.checkpoint,
            net,
            step=step,
            epoch=epoch,
            train_config=config.to_dict(),
            optimizer=optimiser.state_dict() if config.optimizer_state else None,
            metrics=metrics,
            quality=quality,
        )
    return TrainResult(net=net, step=step, epoch=epoch, metrics=metrics, history=history, quality=quality)


def _validate(net: WarmStartNet, rod: Rod, held: Any, writer: Any, step: int, config: TrainConfig) -> dict[str, float]:
    """Held-back metrics (SI) after an epoch, logged to tensorboard with a figure of a few fits."""
    net.eval()
    try:
        ws = WarmStart(net, rod)
        device = next(net.parameters()).device
        guess = ws.guess(held.curvature.to(device), held.mask.to(device))
        metrics = evaluate_guess(guess, held.loads.to(device=device))
        if writer is not None:
            for k, v in metrics.items():
                if k.startswith("cases_"):
                    continue
                scale = 1e3 if k.startswith("location") else 1.0
                name = k.replace("location_error_median", "location_error_median_mm")
                writer.add_scalar(f"val/{name}", v * scale, step)
            n = config.figure_cases
            if n > 0:
                sub = WarmStartGuess(guess.count_probs[:n], {h: p[:n] for h, p in guess.forces.items()})
                fig = fit_figure(rod, held.curvature[:n], held.mask[:n], sub, held.loads[:n])
                writer.add_figure("val/fits", fig, step)
            writer.flush()
        return metrics
    finally:
        net.train()


def record_quality(
    path: str | os.PathLike,
    *,
    rod: str | Rod | None = None,
    count: int = 4096,
    noise: float = 0.1,
    seed: int = 0,
) -> dict[str, float]:
    """Measure a checkpoint's held-back quality (:func:`held_back_quality`) on ``count`` readings simulated for
    ``rod`` (default: the rod its training config names, else the preset whose layout it fits) at ``noise``
    [1/m], with a seed training never uses, and write it into the checkpoint (weights unchanged). Returns it."""
    net, meta = load_checkpoint(path)
    if rod is None:
        rod = (meta.get("train_config") or {}).get("rod") or DEFAULT_ROD
    rod = load_rod(rod) if not isinstance(rod, Rod) else rod
    ws = WarmStart(net, rod)
    held = _simulated(rod, count, net.config.max_forces, _mix(seed, 2), noise, 0.0)
    quality = held_back_quality(ws, held.curvature, held.mask, held.loads, noise)
    save_checkpoint(
        path,
        net,
        step=int(meta.get("step", 0)),
        epoch=int(meta.get("epoch", 0)),
        train_config=meta.get("train_config"),
        optimizer=meta.get("optimizer"),
        metrics=meta.get("metrics"),
        quality=quality,
    )
    return quality


def format_metrics(metrics: Mapping[str, float]) -> str:
    """The metrics of :func:`evaluate_guess` as readable lines (%, mm, N)."""
    lines = [f"count accuracy {100 * metrics['count_accuracy']:.1f} %"]
    h = 1
    while f"cases_{h}" in metrics or h == 1:
        if f"cases_{h}" in metrics:
            lines.append(
                f"{h} force(s), {int(metrics[f'cases_{h}'])} cases: count accuracy "
                f"{100 * metrics[f'count_accuracy_{h}']:.1f} %, median location error "
                f"{1e3 * metrics[f'location_error_median_{h}']:.2f} mm, median force error "
                f"{metrics[f'force_error_median_{h}']:.3f} N"
            )
        h += 1
    return "\n".join(lines)
