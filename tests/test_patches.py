"""A patch of load the gratings cannot resolve is answered as one force (``EstimatorOptions.merge_patches``,
:func:`torchrod.kernels.counts.unresolved_pair`), and real pairs of forces keep their count."""

from __future__ import annotations

import json
import math

import pytest
import torch
from scipy.stats import chi2

import torchrod as tr
from torchrod.kernels.counts import PATCH_COSINE, PATCH_LEVER, PATCH_SPAN, PATCH_SPAN_MISFIT
from torchrod.synthetic import LoadSampler, sample_loads, sample_patches

F64 = torch.float64
SIGMA = 0.1


def _readings(rod: tr.Rod, loads: tr.PointForces, seed: int, sigma: float = SIGMA) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = tr.grating_curvature(rod, loads)
    return u + sigma * torch.randn(u.shape, generator=g, dtype=F64)


def _both(rod: tr.Rod, u: torch.Tensor, **options) -> tuple[tr.EstimateResult, tr.EstimateResult]:
    merged = tr.Estimator(rod, tr.EstimatorOptions(**options)).estimate(u)
    alone = tr.Estimator(rod, tr.EstimatorOptions(merge_patches=False, **options)).estimate(u)
    return merged, alone


def _patch_pair(rod: tr.Rod, s: torch.Tensor, f: torch.Tensor, span: float, margin: float = 1.0) -> bool:
    """Whether two of the forces (s (h,) [m], f (h, 2) [N]) form a pair the rule takes for a patch, less than
    ``span`` grating spacings apart, written out from the rule's statement on the rod's grating spacing (every
    grating present); ``margin`` < 1 asks for a pair well inside the rule's bounds."""
    delta = margin * (rod.gratings[-1] - rod.gratings[0]) / (rod.num_gratings - 1)
    for a in range(len(s)):
        for b in range(a + 1, len(s)):
            na, nb, d = float(f[a].norm()), float(f[b].norm()), abs(float(s[a] - s[b]))
            same_way = float(f[a] @ f[b]) >= (1 - margin * (1 - PATCH_COSINE)) * na * nb
            if d < span * delta and same_way and min(na, nb) * d < PATCH_LEVER * (na + nb) * delta:
                return True
    return False


def _explains(rod: tr.Rod, result: tr.EstimateResult, i: int, h: int, noise: float | None) -> bool:
    """Whether the reading's fit of h forces explains it at the given noise (no misfit); never with the noise
    learned, where the rule does not judge it."""
    if noise is None:
        return False
    loss = float(result.losses_by_count[i, h]) / (noise**2 + tr.EstimatorOptions().noise_floor ** 2)
    return chi2.sf(loss, 2 * rod.num_gratings - 3 * h) >= tr.EstimatorOptions().misfit_level


@pytest.mark.parametrize(
    ("noise", "sigma"), [(SIGMA, SIGMA), (0.03, 0.03), (None, 0.03)], ids=["given", "low-given", "low-learned"]
)
def test_patches_answered_as_a_poorly_determined_pair_are_answered_as_one_force(noise, sigma):
    """12 mm patches on a rod whose gratings lie 20 mm apart, noise 0.1 and 0.03 1/m: the count tests alone answer
    some as a force and a light one beside it pushing the same way (a grating under a patch reads more than one force
    gives). Each such answer whose pair the data do not pin down (poorly determined), and only such an answer,
    becomes one force: within 2.5 grating spacings where one force explains the reading at the given noise, within
    1.5 where it misfits (the answer then says ``misfit``) or the noise is learned. No answer comes out ``ok``; no
    count rises."""
    rod = tr.presets.nitinol290()
    loads, _ = sample_patches(rod, 600, 0.012, torch.Generator().manual_seed(21))
    u = _readings(rod, loads, 22, sigma)
    merged, alone = _both(rod, u, noise=noise)
    changed = (merged.num_forces != alone.num_forces).nonzero().flatten().tolist()
    assert len(changed) >= 3, "no patch answered as a pair: the case tests nothing"
    assert (merged.num_forces <= alone.num_forces).all()
    for i in changed:
        h = int(alone.num_forces[i])
        assert int(merged.num_forces[i]) < h  # (merged again where the count below holds a patch's pair too)
        explains = _explains(rod, alone, i, h - 1, noise)
        span = PATCH_SPAN if explains else PATCH_SPAN_MISFIT
        assert _patch_pair(rod, alone.forces.s[i, :h], alone.forces.f[i, :h], span)
        assert alone.statuses[i] != tr.Status.OK  # a pair the data pinned down stays two forces
        if int(merged.num_forces[i]) == h - 1:
            said = tr.Status.MISFIT if noise is not None and not explains else tr.Status.POORLY_DETERMINED
            assert merged.statuses[i] == said
        # the count above is still reported, as the count tests had it
        assert merged.losses_by_count[i, h] == alone.losses_by_count[i, h]
    if noise == 0.03:
        assert sum(merged.statuses[i] == tr.Status.MISFIT for i in changed) >= 3  # the misfit branch was taken
        assert sum(merged.statuses[i] == tr.Status.POORLY_DETERMINED for i in changed) >= 3  # and the other
    for i in range(len(u)):  # a pair left as it is does not look like a patch, or the data pin it down
        h = int(merged.num_forces[i])
        span = PATCH_SPAN if _explains(rod, merged, i, h - 1, noise) else PATCH_SPAN_MISFIT
        if h >= 2 and _patch_pair(rod, merged.forces.s[i, :h], merged.forces.f[i, :h], span, margin=0.9):
            assert merged.statuses[i] != tr.Status.POORLY_DETERMINED


@pytest.mark.parametrize("k", [2, 3])
def test_real_pairs_keep_their_count(k):
    """Readings of k forces at least 25 mm apart (the accuracy tables' draws), the noise given and learned: merging
    patches changes at most one answer in 500."""
    rod = tr.presets.nitinol290()
    g = torch.Generator().manual_seed(30 + k)
    u = _readings(rod, sample_loads(rod, 500, LoadSampler(min_forces=k, max_forces=k), g), 40 + k)
    for noise in (SIGMA, None):
        merged, alone = _both(rod, u, noise=noise)
        assert int((merged.num_forces != alone.num_forces).sum()) <= 1


def test_two_forces_pushing_the_same_way_a_grating_spacing_apart_stay_two():
    """1 N and 0.8 N, 30 mm apart, one way: the lighter one's moment about the other (24 mN m) is far beyond what a
    patch no longer than the 20 mm spacing makes (1.8 N x 20 mm / 8 = 4.5 mN m): two forces, as without the rule."""
    rod = tr.presets.nitinol290()
    angle = 0.7
    d = torch.tensor([math.cos(angle), math.sin(angle)], dtype=F64)
    loads = tr.PointForces(torch.tensor([[0.150, 0.180]], dtype=F64), torch.stack([1.0 * d, 0.8 * d])[None])
    u = _readings(rod, loads, 5)
    merged, alone = _both(rod, u, noise=SIGMA)
    assert int(merged.num_forces[0]) == int(alone.num_forces[0]) == 2
    assert torch.allclose(merged.forces.s[0, :2], torch.tensor([0.150, 0.180], dtype=F64), atol=0.015)


def test_the_paper_rule_and_a_fixed_count_take_no_patch_rule():
    """The paper's threshold rule is reproduced as published, and a fixed count is the caller's: the option changes
    neither."""
    rod = tr.presets.nitinol290()
    loads, _ = sample_patches(rod, 200, 0.012, torch.Generator().manual_seed(21))
    u = _readings(rod, loads, 22)
    for options in ({"noise": SIGMA, "selection": "threshold"}, {"noise": SIGMA, "num_forces": 2}):
        merged, alone = _both(rod, u, **options)
        assert torch.equal(merged.num_forces, alone.num_forces)
        assert torch.equal(merged.forces.s, alone.forces.s)


def test_merge_patches_must_be_a_bool():
    with pytest.raises(tr.OptionsError, match="merge_patches must be True or False, got 1"):
        tr.EstimatorOptions(merge_patches=1)


def test_bench_patches_quick_prints_the_table(capsys):
    from torchrod.cli import main

    assert main(["bench", "patches", "--quick"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("nitinol290 (gratings 20 mm apart): 40 readings per set; patches 12 mm long")
    assert "| loads | noise | 2+ forces | 2+ forces, count tests alone |" in out
    rows = [line for line in out.splitlines() if line.startswith("| ") and " of 40 |" in line]
    assert [r.split(" | ")[0:2] for r in rows] == [
        [f"| {name}", noise] for name in ("patch", "point", "2 forces", "3 forces") for noise in ("given", "learned")
    ]


@pytest.mark.parametrize("command", ["estimate", "stream"])
def test_the_command_line_merges_patches_unless_told_not_to(command, tmp_path, capsys):
    """``torchrod estimate`` and ``torchrod stream`` answer a patch read as a pair with one force, and with
    ``--no-merge-patches`` as the count tests alone do."""
    from torchrod.cli import main

    rod = tr.presets.nitinol290()
    loads, _ = sample_patches(rod, 600, 0.012, torch.Generator().manual_seed(21))
    u = _readings(rod, loads, 22)
    merged, alone = _both(rod, u, noise=SIGMA)
    picked = (merged.num_forces < alone.num_forces).nonzero().flatten()[:2].tolist()
    assert len(picked) == 2  # the readings this test is for
    path = tmp_path / "patches.jsonl"
    path.write_text("".join(json.dumps({"id": f"p{i}", "curvature": u[i].tolist()}) + "\n" for i in picked))
    counts = {}
    for flag in ([], ["--no-merge-patches"]):
        if command == "estimate":
            argv = ["estimate", "--rod", "nitinol290", "--noise", str(SIGMA), "--quiet", *flag, str(path)]
        else:
            argv = ["stream", "--rod", "nitinol290", "--input", str(path), "--noise", str(SIGMA),
                    "--per-reading-noise", "--checkpoint", "none", *flag]  # fmt: skip
        assert main(argv) == 0
        counts[bool(flag)] = [json.loads(x)["num_forces"] for x in capsys.readouterr().out.splitlines()]
    assert counts[False] == merged.num_forces[picked].tolist()
    assert counts[True] == alone.num_forces[picked].tolist()


def test_sample_patches_draws_one_way_patches_of_the_width_asked_within_the_rod():
    """Each patch: PATCH_PARTS equal forces, one direction, spread evenly over the width about its centre, its total in
    the range asked, the whole patch between the second grating and the tip; a width that leaves no room is refused,
    naming it."""
    from torchrod.synthetic import PATCH_PARTS

    rod = tr.presets.nitinol290()
    width = 0.012
    loads, centre = sample_patches(rod, 200, width, torch.Generator().manual_seed(3), force_range=(0.5, 1.5))
    assert loads.s.shape == (200, PATCH_PARTS) and loads.f.shape == (200, PATCH_PARTS, 2) and centre.shape == (200,)
    assert torch.allclose(loads.s.mean(dim=1), centre)
    spread = loads.s[:, -1] - loads.s[:, 0]
    assert torch.allclose(spread, torch.full_like(spread, width * (PATCH_PARTS - 1) / PATCH_PARTS))
    assert bool((loads.s[:, 0] > rod.gratings[1]).all() and (loads.s[:, -1] < rod.length).all())
    assert torch.equal(loads.f, loads.f[:, :1].expand_as(loads.f))  # equal parts, one way
    total = loads.f.sum(dim=1).norm(dim=-1)
    assert bool(((total >= 0.5) & (total <= 1.5)).all()) and float(total.max() - total.min()) > 0.5
    with pytest.raises(tr.OptionsError, match="width .* got 0.3 m"):
        sample_patches(rod, 3, 0.3)
