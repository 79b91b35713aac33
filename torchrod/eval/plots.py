"""Figures: the paper's comparison (``torchrod bench paper``) and readings with their estimates (``torchrod plot``).

Every function returns a :class:`matplotlib.figure.Figure` drawn on the Agg canvas (no pyplot, no global backend
switch, nothing shown); :func:`save` writes it as a PNG. Units on the axes: mm for locations, N for forces, 1/m for
curvature, s for times.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..errors import OptionsError
from ..loads import PointForces
from ..rod import Rod

__all__ = [
    "figure",
    "loss_maps_figure",
    "reading_figure",
    "save",
    "speed_figure",
    "stream_figure",
    "versus_q_figure",
]

_METHOD_STYLE = {
    "bvp_lm": ("BVP + LM", "tab:red", "o"),
    "bvp_dp": ("BVP + DP", "tab:orange", "s"),
    "nodes": ("body frame, node scheme", "tab:blue", "^"),
    "torchrod": ("torchrod default (B = 1)", "tab:green", "D"),
    "torchrod_batched": ("torchrod default (batched, per reading)", "tab:olive", "v"),
}
_COUNT_COLOURS = {1: "tab:blue", 2: "tab:orange", 3: "tab:green"}


def figure(width: float, height: float) -> Figure:
    """A figure of ``width`` x ``height`` inches on the Agg canvas."""
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def save(fig: Figure, path: str | os.PathLike, dpi: int = 90) -> str:
    """Write ``fig`` as a PNG (parent folders created); returns the path."""
    path = os.fspath(path)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path


# ================================================================================================ the paper's figures
def speed_figure(table, paper: Mapping[int, Mapping[str, float]] | None = None) -> Figure:
    """Table II as a figure: median single-force estimation time [s] against q, log scale, one line per method
    (:class:`torchrod.eval.paper.SpeedTable`), the paper's times as hollow markers on dashed lines."""
    fig = figure(8.6, 4.2)
    ax = fig.add_subplot(1, 1, 1)
    q = list(table.nodes)
    for name in table.baselines:
        label, colour, marker = _METHOD_STYLE.get(name, (name, None, "o"))
        ax.plot(q, [table.median(name, n) for n in q], marker=marker, color=colour, label=f"{label} (here)")
        if paper:
            pq = [n for n in sorted(paper) if name in paper[n]]
            if pq:
                ax.plot(
                    pq,
                    [paper[n][name] for n in pq],
                    ls="--",
                    marker=marker,
                    mfc="none",
                    color=colour,
                    alpha=0.7,
                    label=f"{label} (paper, MATLAB)",
                )
    for key, value in (("torchrod", table.median("torchrod")), ("torchrod_batched", table.torchrod_batched)):
        label, colour, marker = _METHOD_STYLE[key]
        ax.plot(q, [value] * len(q), marker=marker, color=colour, label=f"{label}, exact loads: no q")
    ax.set_yscale("log")
    ax.set_xlabel("nodes q")
    ax.set_ylabel("time per single-force estimate [s]")
    ax.set_title("The paper's Table II, measured here")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6.5, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    return fig


def versus_q_figure(
    study,
    paper_force: Mapping[int, float] | None = None,
    paper_location: Mapping[int, float] | None = None,
    paper_times: Mapping[int, Mapping[int, float]] | None = None,
) -> Figure:
    """Accuracy and time against q (:class:`torchrod.eval.paper.AccuracyStudy`): force RMSE [N], location RMSE [mm]
    and median time per estimate [s] of the paper's method (count given) for each force count, torchrod's default
    (count automatic) as a horizontal line, the paper's numbers as hollow markers."""
    fig = figure(11.0, 3.6)
    axes = [fig.add_subplot(1, 3, i + 1) for i in range(3)]
    q = list(study.nodes)
    for k in study.readings:
        colour = _COUNT_COLOURS.get(k)
        acc = [study.accuracy(f"nodes q={n}", k) for n in q]
        mine = study.accuracy("torchrod", k)
        runs = [study.runs[f"nodes q={n}"][k] for n in q]
        axes[0].plot(q, [a.force_rmse for a in acc], marker="o", color=colour, label=f"{k} force(s), node scheme")
        axes[0].axhline(mine.force_rmse, color=colour, ls=":", label=f"{k}, torchrod")
        axes[1].plot(q, [1e3 * a.location_rmse for a in acc], marker="o", color=colour)
        axes[1].axhline(1e3 * mine.location_rmse, color=colour, ls=":")
        axes[2].plot(q, [r.median_wall for r in runs], marker="o", color=colour)
        axes[2].axhline(study.runs["torchrod"][k].median_wall, color=colour, ls=":")
        if paper_force and k in paper_force:
            axes[0].plot(
                [250],
                [paper_force[k]],
                marker="*",
                mfc="none",
                ms=10,
                color=colour,
                ls="none",
                label=f"{k}, paper (real bench)",
            )
        if paper_location and k in paper_location:
            axes[1].plot([250], [1e3 * paper_location[k]], marker="*", mfc="none", ms=10, color=colour, ls="none")
        if paper_times:
            pq = sorted(n for n in paper_times if k in paper_times[n])
            axes[2].plot(
                pq,
                [paper_times[n][k] for n in pq],
                marker="*",
                mfc="none",
                ms=10,
                color=colour,
                ls="--",
                alpha=0.7,
            )
    axes[0].set_ylabel("force magnitude RMSE [N]")
    axes[1].set_ylabel("location RMSE [mm]")
    axes[2].set_ylabel("time per estimate [s]")
    axes[2].set_yscale("log")
    for ax in axes:
        ax.set_xlabel("nodes q")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.suptitle("Against q: node scheme (lines), torchrod (dotted), paper (stars)", fontsize=9)
    fig.tight_layout()
    return fig


def loss_maps_figure(maps) -> Figure:
    """The paper's loss maps (:class:`torchrod.eval.paper.LossMaps`): shape loss and curvature loss (log colour scale)
    over location [mm] and magnitude [N], the truth (white cross) and each map's minimum (red circle)."""
    fig = figure(9.0, 3.8)
    extent = (1e3 * maps.s[0], 1e3 * maps.s[-1], maps.magnitude[0], maps.magnitude[-1])
    for i, (which, grid, unit) in enumerate(
        (("shape", maps.shape_loss, "m$^2$"), ("curvature", maps.curvature_loss, "1/m$^2$"))
    ):
        ax = fig.add_subplot(1, 2, i + 1)
        positive = grid[grid > 0]
        floor = positive.min() if positive.size else 1e-30
        img = ax.imshow(np.log10(np.maximum(grid, floor)), origin="lower", extent=extent, aspect="auto", cmap="viridis")
        fig.colorbar(img, ax=ax, label=f"log10 {which} loss [{unit}]")
        ax.contour(
            1e3 * maps.s,
            maps.magnitude,
            np.log10(np.maximum(grid, floor)),
            levels=12,
            colors="w",
            linewidths=0.4,
            alpha=0.5,
        )
        ax.plot(1e3 * maps.true[0], math.hypot(maps.true[1], maps.true[2]), "wx", ms=9, mew=2, label="truth")
        s_min, f_min = maps.minimum(which)
        ax.plot(
            1e3 * s_min,
            f_min,
            "o",
            mfc="none",
            mec="r",
            ms=11,
            mew=1.5,
            label=f"minimum ({1e3 * s_min:.0f} mm, {f_min:.3f} N)",
        )
        ax.set_xlabel("force location [mm]")
        ax.set_ylabel("force magnitude [N]")
        ax.set_title(f"({'ab'[i]}) {which} loss")
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


# ================================================================================================ readings
def _rows(forces) -> np.ndarray:
    a = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
    return a[np.argsort(a[:, 0], kind="stable")]


def _profile(rod: Rod, rows: np.ndarray, samples: int) -> tuple[np.ndarray, ...]:
    """The model rod under reported rows: s (S,) [m], curvature (S, 2) [1/m], positions (S, 3) [m], frames
    (S, 3, 3) and the curvature at the gratings (G, 2) [1/m]."""
    from ..model.body_frame import simulate
    from ..model.shape import rod_shape

    model = rows.copy()
    model[:, 0] = np.clip(model[:, 0] - rod.location_bias, 0.0, rod.length)
    if len(model):
        loads = PointForces(torch.from_numpy(model[None, :, 0].copy()), torch.from_numpy(model[None, :, 1:].copy()))
    else:
        loads = PointForces(torch.zeros(1, 1, dtype=torch.float64), torch.zeros(1, 1, 2, dtype=torch.float64))
    with torch.no_grad():
        sim = simulate(rod, loads, samples=samples)
        shp = rod_shape(sim.s, sim.full_curvature)  # with the twist of a precurved rod
    return (
        sim.s.numpy(),
        sim.curvature[0].numpy(),
        shp.position[0].numpy(),
        shp.frames[0].numpy(),
        sim.grating_curvature[0].numpy(),
    )


def _draw_forces(
    ax,
    rod: Rod,
    rows: np.ndarray,
    s: np.ndarray,
    P: np.ndarray,
    R: np.ndarray,
    colour: str,
    label: str,
    scale: float,
) -> None:
    for j, (si, fx, fy) in enumerate(rows):
        sm = min(max(si - rod.location_bias, 0.0), rod.length)
        k = int(np.argmin(np.abs(s - sm)))
        F = R[k] @ np.array([fx, fy, 0.0])  # body frame -> base frame
        tail = P[k] - scale * F
        ax.quiver(
            tail[0],
            tail[1],
            tail[2],
            *(scale * F),
            color=colour,
            arrow_length_ratio=0.25,
            linewidth=1.6,
            label=label if j == 0 else None,
        )
        ax.text(*tail, f"{math.hypot(fx, fy):.2f} N", color=colour, fontsize=6)


def reading_figure(
    rod: Rod,
    curvature,
    forces,
    *,
    truth=None,
    title: str | None = None,
    samples: int = 117,
) -> Figure:
    """One reading and its estimate: the rod's 3-D shape (from the estimated forces) with the forces drawn as
    arrows at their locations (the true ones too, if given), the measured and fitted curvature at each grating (and
    the fitted profile along the rod), and the residuals.

    Args:
        rod: the rod the estimate was made with (its location bias maps reported locations to the model's).
        curvature: (G, 2) measured (u_x, u_y) [1/m]; NaN (or None) at a missing grating.
        forces: (h, 3) estimated rows (s [m] reported, f_x [N], f_y [N]); may be empty.
        truth: optional (k, 3) true rows, same form.
        title: figure title.
        samples: positions along the rod for the profile and the shape.
    """
    u = np.array([[np.nan, np.nan] if c is None else c for c in curvature], dtype=np.float64).reshape(-1, 2)
    if u.shape != (rod.num_gratings, 2):
        raise OptionsError(f"curvature must have shape (G, 2) = ({rod.num_gratings}, 2), got {u.shape}")
    rows = _rows(forces)
    s, prof, P, R, fitted = _profile(rod, rows, samples)
    g = 1e3 * np.asarray(rod.gratings)
    fig = figure(13.0, 4.6)
    grid = fig.add_gridspec(1, 3, width_ratios=(1.25, 1.0, 1.0))
    ax3 = fig.add_subplot(grid[0, 0], projection="3d")
    ax3.plot(1e3 * P[:, 0], 1e3 * P[:, 1], 1e3 * P[:, 2], color="k", lw=2, label="rod (fitted)")
    Pg = np.array([P[int(np.argmin(np.abs(s - x)))] for x in rod.gratings])
    ax3.scatter(1e3 * Pg[:, 0], 1e3 * Pg[:, 1], 1e3 * Pg[:, 2], s=8, color="0.4", label="gratings")
    mags = [math.hypot(r[1], r[2]) for r in rows] + (
        [math.hypot(r[1], r[2]) for r in _rows(truth)] if truth is not None else []
    )
    scale = 0.25 * rod.length / max(max(mags, default=0.0), 1e-9)
    _draw_forces(ax3, rod, rows, s, 1e3 * P, R, "tab:red", "estimated force", 1e3 * scale)
    if truth is not None:
        t = _rows(truth)
        ts, _, tP, tR, _ = _profile(rod, t, samples)
        ax3.plot(
            1e3 * tP[:, 0],
            1e3 * tP[:, 1],
            1e3 * tP[:, 2],
            color="tab:blue",
            lw=1,
            ls="--",
            label="rod (truth)",
        )
        _draw_forces(ax3, rod, t, ts, 1e3 * tP, tR, "tab:blue", "true force", 1e3 * scale)
    ax3.set_xlabel("x [mm]", fontsize=7)
    ax3.set_ylabel("y [mm]", fontsize=7)
    ax3.set_zlabel("z [mm]", fontsize=7)
    ax3.tick_params(labelsize=6)
    # To scale: every axis spans its data (at least 0.3 L), the box in proportion.
    spans = []
    for c, setter in enumerate((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim)):
        lo, hi = 1e3 * P[:, c].min(), 1e3 * P[:, c].max()
        half = max(0.5 * (hi - lo), 150.0 * rod.length) + 10.0
        mid = 0.5 * (lo + hi)
        setter(mid - half, mid + half)
        spans.append(2 * half)
    ax3.set_box_aspect(spans)
    ax3.legend(fontsize=6, loc="upper left")
    ax3.set_title("shape and forces (arrows end where they act)", fontsize=9)

    ax = fig.add_subplot(grid[0, 1])
    for c, (name, colour) in enumerate((("u_x", "tab:red"), ("u_y", "tab:blue"))):
        ax.plot(1e3 * s, prof[:, c], color=colour, lw=1, label=f"{name} fitted")
        ax.plot(g, u[:, c], "o", color=colour, mfc="none", label=f"{name} measured")
    for si in rows[:, 0]:
        ax.axvline(1e3 * si, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("s [mm]")
    ax.set_ylabel("curvature [1/m]")
    ax.set_title("curvature at the gratings", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=6)

    ax = fig.add_subplot(grid[0, 2])
    res = u - fitted
    width = 0.4 * (g[1] - g[0]) if len(g) > 1 else 5.0
    ax.bar(g - width / 2, res[:, 0], width, color="tab:red", label="u_x")
    ax.bar(g + width / 2, res[:, 1], width, color="tab:blue", label="u_y")
    ax.axhline(0.0, color="k", lw=0.6)
    loss = float(np.nansum(res**2))
    ax.set_xlabel("s [mm]")
    ax.set_ylabel("measured - fitted [1/m]")
    ax.set_title(f"residuals (loss {loss:.3g} 1/m$^2$)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


# ========================================================================================================= a stream
TRACK_GATE = 0.02
"""Farthest a contact is taken to move between consecutive readings of a track [m]: one grating interval of the
shipped rods (20 mm). A contact sliding that far in one reading (20 ms at 50 Hz: 1 m/s) is faster than a
continuum robot's contacts move, while the location of a weak force scatters by up to about one interval."""

TRACK_MAX_GAP = 2
"""Readings a track may skip (a force missed, a reading without an estimate) and still go on."""

TRACK_MIN_LENGTH = 5
"""Forces in fewer readings than this (0.1 s at 50 Hz) make a stray track: drawn as small dark dots, not given a
colour of their own, so that the colours stay with the contacts that last."""

MISS_TOLERANCE = 0.02
"""Farthest an estimated force may lie from a true contact and still be that contact found [m]: one grating
interval of the shipped rods (20 mm). Within it the gratings locate a force only to a fraction of the interval
(the example stream's ``std_s`` is about 7 mm, so 20 mm is about three standard deviations); an estimate farther
off sits by other gratings and is another contact."""

_Rows = Sequence[float] | np.ndarray  # (n,) numbers of one reading

NO_ESTIMATE = "no estimate"
"""The status :func:`status_spans` gives a reading that has no estimate (an error line, or none at all)."""

_TRACK_COLOURS = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:purple",
    "tab:brown",
    "tab:olive",
    "tab:cyan",
)  # (red and grey are the truth's)
_STATUS_COLOURS = {
    "misfit": "black",
    "unconverged": "tab:brown",
    "poorly_determined": "gold",
    "timeout": "darkorange",
    NO_ESTIMATE: "0.55",
}
_MISSED = "crimson"


def track_forces(
    locations: Sequence[_Rows], gate: float = TRACK_GATE, max_gap: int = TRACK_MAX_GAP
) -> list[np.ndarray]:
    """Link the forces of consecutive readings into contact tracks by nearest location (greedy).

    Readings are taken in the order given (time order). At each reading the pairs (track still alive, force) are
    taken closest first, each track and each force at most once, and only pairs within ``gate`` of the track's last
    location; a force left over starts a new track. A track that has not been continued for more than ``max_gap``
    readings ends (a later force there starts a new one).

    Args:
        locations: per reading, (h,) locations s [m] of its forces (h may be 0).
        gate: farthest a track's location may move from one of its forces to the next [m].
        max_gap: readings a track may skip and still be continued.

    Returns:
        per reading, (h,) int track numbers of its forces, in the order given; tracks are numbered 0, 1, ... in the
        order they start.
    """
    last: list[tuple[float, int]] = []  # per track: (last location [m], reading index)
    out = []
    for k, row in enumerate(locations):
        s = np.asarray(row, dtype=np.float64).reshape(-1)
        ids = np.full(s.shape, -1, dtype=np.int64)
        alive = [j for j, (_, seen) in enumerate(last) if k - seen <= max_gap + 1]
        pairs = sorted(
            (abs(s[i] - last[j][0]), j, i) for j in alive for i in range(len(s)) if abs(s[i] - last[j][0]) <= gate
        )
        taken: set[int] = set()
        for _, j, i in pairs:
            if ids[i] < 0 and j not in taken:
                ids[i] = j
                taken.add(j)
        for i in range(len(s)):
            if ids[i] < 0:
                ids[i] = len(last)
                last.append((float(s[i]), k))
            else:
                last[ids[i]] = (float(s[i]), k)
        out.append(ids)
    return out


def missed_contacts(
    estimated: Sequence[_Rows], true: Sequence[_Rows], tolerance: float = MISS_TOLERANCE
) -> list[np.ndarray]:
    """Which true contacts each reading's estimate missed: those left without an estimated force within
    ``tolerance`` of their location once every estimated force has been given to at most one true contact (the
    closest pairs first), so one force found between two contacts finds only one of them.

    Args:
        estimated: per reading, (h,) estimated locations s [m].
        true: per reading (the same readings), (k,) true locations s [m].
        tolerance: farthest an estimated force may lie from a true contact it finds [m].

    Returns:
        per reading, (k,) bool: True where that true contact was missed.
    """
    if len(estimated) != len(true):
        raise OptionsError(f"estimated and true must hold the same readings, got {len(estimated)} and {len(true)}")
    out = []
    for est_row, true_row in zip(estimated, true, strict=True):
        e = np.asarray(est_row, dtype=np.float64).reshape(-1)
        s = np.asarray(true_row, dtype=np.float64).reshape(-1)
        missed = np.ones(s.shape, dtype=bool)
        used: set[int] = set()
        pairs = sorted((abs(s[i] - e[j]), i, j) for i in range(len(s)) for j in range(len(e)))
        for d, i, j in pairs:
            if d <= tolerance and missed[i] and j not in used:
                missed[i] = False
                used.add(j)
        out.append(missed)
    return out


def status_spans(t: _Rows, statuses: Sequence[str | None]) -> dict[str, list[tuple[float, float]]]:
    """The stretches of time to mark for readings whose status is not ``ok``.

    Each reading covers the time from halfway to the previous reading to halfway to the next (the ends as far out
    as the nearest neighbour's half interval); neighbouring readings of the same status are merged into one span.

    Args:
        t: (T,) times [s], increasing.
        statuses: (T,) each reading's status (``"ok"``, ``"misfit"``, ...; None for a reading without an estimate,
            marked as :data:`NO_ESTIMATE`).

    Returns:
        per status present other than ``ok`` (in the order of :class:`torchrod.estimate.status.Status`, then
        others by name), the spans (start [s], width [s]) it covers.
    """
    tt = np.asarray(t, dtype=np.float64).reshape(-1)
    if len(tt) != len(statuses):
        raise OptionsError(f"t and statuses must have the same length, got {len(tt)} and {len(statuses)}")
    if len(tt) == 0:
        return {}
    mid = 0.5 * (tt[1:] + tt[:-1])
    half = 0.5 * (tt[1] - tt[0]) if len(tt) > 1 else 0.5
    lo = np.concatenate(([tt[0] - half], mid))
    hi = np.concatenate((mid, [tt[-1] + (0.5 * (tt[-1] - tt[-2]) if len(tt) > 1 else 0.5)]))
    spans: dict[str, list[list[float]]] = {}
    previous = None
    for k, status in enumerate(statuses):
        name = NO_ESTIMATE if status is None else str(status)
        if name == "ok":
            previous = None
            continue
        runs = spans.setdefault(name, [])
        if previous == name:
            runs[-1][1] = hi[k]
        else:
            runs.append([lo[k], hi[k]])
        previous = name
    known = [*_STATUS_COLOURS]
    order = sorted(spans, key=lambda n: (known.index(n) if n in known else len(known), n))
    return {n: [(float(a), float(b - a)) for a, b in spans[n]] for n in order}


def _track_points(times: np.ndarray, rows: Sequence[np.ndarray], tracks: Sequence[np.ndarray], j: int) -> np.ndarray:
    """(n, 4) rows (t [s], s [m], f_x [N], f_y [N]) of the forces of track ``j``, in time order."""
    pts = [(times[k], *r[i]) for k, (r, x) in enumerate(zip(rows, tracks, strict=True)) for i in np.flatnonzero(x == j)]
    return np.array(pts, dtype=np.float64).reshape(-1, 4)


def _same_times(t: np.ndarray, other: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (k, i) of an entry of ``t`` and one of ``other`` at the same time (within 1 µs) [s]."""
    at = {round(float(x) * 1e6): k for k, x in enumerate(t) if math.isfinite(x)}
    return [(at[key], i) for i, x in enumerate(other) if math.isfinite(x) and (key := round(float(x) * 1e6)) in at]


def _nice(x: float) -> float:
    """The 1, 2 or 5 times a power of ten at or below ``x`` (> 0)."""
    p = 10.0 ** math.floor(math.log10(x))
    return max(m * p for m in (1.0, 2.0, 5.0) if m * p <= x * (1 + 1e-9))


def stream_figure(
    t: Sequence[float],
    estimates: Sequence,
    *,
    statuses: Sequence[str | None] | None = None,
    truth_t: Sequence[float] | None = None,
    truth: Sequence | None = None,
    title: str | None = None,
    tolerance: float = MISS_TOLERANCE,
) -> Figure:
    """Forces of a stream against time, each tied to its location.

    The main panel shows each estimated force at its reported location s [mm] against time, a dot whose area
    grows with its magnitude, the forces linked into contact tracks (:func:`track_forces`), one colour per track.
    The panel below shows the magnitudes [N] in the same colours. A strip on top marks the readings whose status
    is not ``ok`` (:func:`status_spans`), one colour per status. With the truth, the true contacts are drawn as
    grey lines in both panels, and those missed (:func:`missed_contacts`: no estimated force within ``tolerance``)
    as crosses, their count in the title.

    Args:
        t: (T,) times [s] of the readings.
        estimates: per reading, (h, 3) rows (s [m], f_x [N], f_y [N]); None for a reading without an estimate.
        statuses: (T,) each reading's status (None: no estimate); default ``ok`` for every estimate.
        truth_t, truth: the true forces' times [s] and rows, same form (no None); ``truth_t`` defaults to ``t``.
            A true contact is judged found or missed where a reading with an estimate has its time (within 1 µs).
        title: figure title (the count of missed contacts is added).
        tolerance: farthest an estimated force may lie from a true contact it finds [m].
    """
    if len(estimates) != len(t):
        raise OptionsError(f"t and estimates must have the same length, got {len(t)} and {len(estimates)}")
    if statuses is None:
        statuses = ["ok" if e is not None else None for e in estimates]
    if len(statuses) != len(t):
        raise OptionsError(f"t and statuses must have the same length, got {len(t)} and {len(statuses)}")
    order = np.argsort(np.asarray(t, dtype=np.float64), kind="stable")
    times = np.asarray(t, dtype=np.float64)[order]
    rows = [_rows(estimates[k]) if estimates[k] is not None else np.zeros((0, 3)) for k in order]
    status = [None if estimates[k] is None else statuses[k] for k in order]
    tracks = track_forces([r[:, 0] for r in rows])

    fig = figure(11.0, 7.0)
    grid = fig.add_gridspec(3, 1, height_ratios=(0.28, 3.0, 1.5), hspace=0.08)
    axq = fig.add_subplot(grid[0, 0])
    axs = fig.add_subplot(grid[1, 0], sharex=axq)
    axm = fig.add_subplot(grid[2, 0], sharex=axq)

    # The truth: grey lines along its contacts, crosses where missed.
    missed_count = judged = 0
    if truth is not None:
        tt = np.asarray(t if truth_t is None else truth_t, dtype=np.float64)
        if len(tt) != len(truth):
            raise OptionsError(f"truth_t and truth must have the same length, got {len(tt)} and {len(truth)}")
        torder = np.argsort(tt, kind="stable")
        tt = tt[torder]
        trows = [_rows(truth[k]) for k in torder]
        ttracks = track_forces([r[:, 0] for r in trows])
        for j in range(max((int(x.max()) + 1 for x in ttracks if len(x)), default=0)):
            p = _track_points(tt, trows, ttracks, j)
            kw: dict[str, Any] = {"color": "0.55", "lw": 4.0, "alpha": 0.45, "solid_capstyle": "round", "zorder": 1}
            axs.plot(p[:, 0], 1e3 * p[:, 1], label="true contact" if j == 0 else None, **kw)
            axm.plot(p[:, 0], np.hypot(p[:, 2], p[:, 3]), **kw)
        # Judged where a reading with an estimate has the truth's time.
        answered = np.where([x is not None for x in status], times, np.nan)
        pairs = _same_times(answered, tt)
        flags = missed_contacts([rows[k][:, 0] for k, _ in pairs], [trows[i][:, 0] for _, i in pairs], tolerance)
        miss = np.array(
            [(tt[i], *trows[i][m]) for (_, i), f in zip(pairs, flags, strict=True) for m in np.flatnonzero(f)]
        )
        judged = sum(len(f) for f in flags)
        missed_count = len(miss)
        if missed_count:
            kw = {"color": _MISSED, "marker": "x", "ls": "none", "ms": 4, "mew": 1.0, "zorder": 4}
            label = (
                f"missed true contact: {missed_count} of {judged}\n(no estimated force within {1e3 * tolerance:g} mm)"
            )
            axs.plot(miss[:, 0], 1e3 * miss[:, 1], label=label, **kw)
            axm.plot(miss[:, 0], np.hypot(miss[:, 2], miss[:, 3]), **kw)

    # The estimates: one colour per track, dot area by magnitude.
    mags = np.concatenate([np.hypot(r[:, 1], r[:, 2]) for r in rows]) if rows else np.zeros(0)
    ref = float(np.percentile(mags, 95)) if len(mags) else 1.0
    ref = ref if ref > 0 else 1.0

    def area(m):
        return 3.0 + 60.0 * np.clip(np.asarray(m) / ref, 0.0, 1.5)

    n_tracks = max((int(x.max()) + 1 for x in tracks if len(x)), default=0)
    lengths = np.bincount(np.concatenate(tracks), minlength=n_tracks) if n_tracks else np.zeros(0, dtype=int)
    colours: dict[int, str] = {}
    for long in np.flatnonzero(lengths >= TRACK_MIN_LENGTH):
        colours[int(long)] = _TRACK_COLOURS[len(colours) % len(_TRACK_COLOURS)]
    stray = []
    for j in range(n_tracks):
        p = _track_points(times, rows, tracks, j)
        m = np.hypot(p[:, 2], p[:, 3])
        if j not in colours:
            stray.append(p)
            continue
        colour = colours[j]
        axs.plot(p[:, 0], 1e3 * p[:, 1], color=colour, lw=0.7, alpha=0.8, zorder=2)
        axs.scatter(p[:, 0], 1e3 * p[:, 1], s=area(m), color=colour, edgecolors="none", alpha=0.85, zorder=3)
        axm.plot(p[:, 0], m, color=colour, lw=1.0, marker=".", ms=2.5, zorder=3)
    if stray:
        p = np.concatenate(stray)
        kw = {"color": "0.2", "marker": ".", "ls": "none", "ms": 2.5, "zorder": 3}
        axs.plot(p[:, 0], 1e3 * p[:, 1], label=f"stray force (track of < {TRACK_MIN_LENGTH} readings)", **kw)
        axm.plot(p[:, 0], np.hypot(p[:, 2], p[:, 3]), **kw)
    if colours:
        # The legend: what a dot is, and the areas of some magnitudes.
        first = next(iter(colours.values()))
        label = f"estimated force: {len(colours)} tracks,\none colour each, area by magnitude:"
        axs.plot([], [], color=first, marker="o", ls="-", lw=0.7, ms=4, label=label)
        for value in sorted({_nice(ref / 4), _nice(ref)}):
            axs.scatter([], [], s=area(value), color="0.3", edgecolors="none", label=f"{value:g} N")
    # Status strip.
    spans = status_spans(times, status)
    for name, runs in spans.items():
        count = sum(1 for x in status if (NO_ESTIMATE if x is None else x) == name)
        axq.broken_barh(runs, (0.0, 1.0), color=_STATUS_COLOURS.get(name, "0.5"), label=f"{name} ({count})")
    axq.set_ylim(0.0, 1.0)
    axq.set_yticks([])
    axq.set_ylabel("status", rotation=0, ha="right", va="center", fontsize=8)
    axq.tick_params(labelbottom=False)
    if spans:
        axq.legend(
            fontsize=7,
            loc="upper left",
            bbox_to_anchor=(1.005, 1.15),
            title="not ok (readings)",
            title_fontsize=7,
            frameon=False,
        )
    else:
        axq.text(0.5, 0.5, "every reading ok", transform=axq.transAxes, ha="center", va="center", fontsize=7)

    axs.set_ylabel("location s [mm]")
    axs.tick_params(labelbottom=False)
    axm.set_ylabel("magnitude [N]")
    axm.set_xlabel("t [s]")
    axm.set_ylim(bottom=0.0)
    # The legend: the estimates first, then the truth.
    handles, labels = axs.get_legend_handles_labels()
    first_words = ("estimated", "", "stray", "true", "missed")  # ("": the magnitudes, "... N")
    rank = [
        1 if label.endswith(" N") else next((n for n, w in enumerate(first_words) if w and label.startswith(w)), 5)
        for label in labels
    ]
    ranked = sorted(range(len(labels)), key=lambda n: rank[n])
    axs.legend(
        [handles[n] for n in ranked],
        [labels[n] for n in ranked],
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.005, 1.0),
        frameon=False,
    )
    for ax in (axs, axm):
        ax.grid(True, alpha=0.3)
    if len(times):
        pad = 0.01 * (times[-1] - times[0]) if len(times) > 1 else 0.5
        axq.set_xlim(times[0] - pad, times[-1] + pad)
    full = title or ""
    if truth is not None:
        full += ("; " if full else "") + f"{missed_count} of {judged} true contacts missed"
    if full:
        fig.suptitle(full, fontsize=10)
    fig.subplots_adjust(left=0.08, right=0.72, top=0.93, bottom=0.08)
    return fig
