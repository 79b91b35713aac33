"""Figures: the paper's comparison (``torchrod bench paper``) and readings with their estimates (``torchrod plot``).

Every function returns a :class:`matplotlib.figure.Figure` drawn on the Agg canvas (no pyplot, no global backend
switch, nothing shown); :func:`save` writes it as a PNG. Units on the axes: mm for locations, N for forces, 1/m for
curvature, s for times.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

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
        raise ValueError(f"curvature must have shape (G, 2) = ({rod.num_gratings}, 2), got {u.shape}")
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


def stream_figure(
    t: Sequence[float],
    estimates: Sequence,
    *,
    truth_t: Sequence[float] | None = None,
    truth: Sequence | None = None,
    title: str | None = None,
) -> Figure:
    """Forces of a stream against time: magnitude [N] and reported location [mm] of every estimated force
    (markers), the true forces as grey dots when given.

    Args:
        t: (T,) times [s]; estimates: per time, (h, 3) rows (s [m], f_x [N], f_y [N]).
        truth_t, truth: the ground truth's times and rows, same form.
    """
    fig = figure(9.0, 5.0)
    axm = fig.add_subplot(2, 1, 1)
    axs = fig.add_subplot(2, 1, 2, sharex=axm)

    def points(times, rows_list):
        tt, mm, ss = [], [], []
        for ti, rows in zip(times, rows_list, strict=False):
            for si, fx, fy in _rows(rows):
                tt.append(ti)
                mm.append(math.hypot(fx, fy))
                ss.append(1e3 * si)
        return tt, mm, ss

    if truth is not None and truth_t is not None:
        tt, mm, ss = points(truth_t, truth)
        axm.plot(tt, mm, ".", color="0.55", ms=3, label="truth")
        axs.plot(tt, ss, ".", color="0.55", ms=3, label="truth")
    tt, mm, ss = points(t, estimates)
    axm.plot(tt, mm, ".", color="tab:red", ms=2.5, label="estimate")
    axs.plot(tt, ss, ".", color="tab:red", ms=2.5, label="estimate")
    axm.set_ylabel("force magnitude [N]")
    axs.set_ylabel("location [mm]")
    axs.set_xlabel("t [s]")
    for ax in (axm, axs):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper right", markerscale=3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
