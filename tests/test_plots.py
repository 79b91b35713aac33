"""Figures (torchrod.plots) and ``torchrod plot``: files written, PNG, and the numbers the figures show."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.data import path as shipped_file
from torchrod.eval import plots

PNG = b"\x89PNG\r\n\x1a\n"
DATA = shipped_file("nitinol290.json").parent


def _is_png(path: Path) -> bool:
    data = path.read_bytes()
    return data[:8] == PNG and len(data) > 5_000


def _residual_bars(fig) -> np.ndarray:
    ax = next(a for a in fig.axes if a.get_title().startswith("residuals"))
    return np.array([p.get_height() for p in ax.patches])


def test_reading_figure_with_the_true_forces_fits_exactly_on_a_biased_rod(tmp_path):
    rod = tr.presets.nitinol290(calibrated=True)
    reported = np.array([[0.12, 0.5, -0.2], [0.24, -0.1, 0.3]])
    model = tr.PointForces(
        torch.from_numpy(reported[None, :, 0] - rod.location_bias),
        torch.from_numpy(reported[None, :, 1:].copy()),
    )
    u = tr.grating_curvature(rod, model)[0].numpy()
    fig = plots.reading_figure(rod, u.tolist(), reported, truth=reported, title="exact")
    # The figure maps reported locations back to the model's (reported = model + bias): no residual left.
    bars = _residual_bars(fig)
    assert bars.shape == (2 * rod.num_gratings,) and np.abs(bars).max() < 1e-9
    # A wrong estimate leaves residuals, and a missing grating (None) is drawn as no bar (NaN), not as zero.
    u_missing = u.tolist()
    u_missing[3] = None
    fig2 = plots.reading_figure(rod, u_missing, reported[:1])
    bars2 = _residual_bars(fig2)
    assert np.isnan(bars2[[3, rod.num_gratings + 3]]).all()
    assert np.nanmax(np.abs(bars2)) > 0.1
    path = plots.save(fig, tmp_path / "sub" / "r.png")
    assert _is_png(Path(path))
    # No forces at all: a straight rod, still a figure.
    assert _is_png(Path(plots.save(plots.reading_figure(rod, u.tolist(), []), tmp_path / "empty.png")))
    with pytest.raises(ValueError, match="G, 2"):
        plots.reading_figure(rod, u[:3].tolist(), reported)


def _write(path: Path, rows) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_plot_command_one_file_unless_asked_for_more(tmp_path, capsys):
    rod = tr.presets.nitinol290()
    forces = [[(0.15, 0.4, 0.1)], [(0.1, -0.3, 0.2), (0.24, 0.2, 0.2)], [(0.2, 0.0, -0.6)]]
    u = tr.grating_curvature(rod, tr.PointForces.from_lists(forces))
    readings = _write(tmp_path / "r.jsonl", [{"id": f"case/{k}", "curvature": u[k].tolist()} for k in range(3)])
    truth = _write(
        tmp_path / "t.jsonl",
        [
            {"id": f"case/{k}", "forces": [{"s": s, "fx": fx, "fy": fy} for s, fx, fy in f]}
            for k, f in enumerate(forces)
        ],
    )
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.01", "--quiet", str(readings)]) == 0
    estimates = tmp_path / "e.jsonl"
    estimates.write_text(capsys.readouterr().out)
    out = tmp_path / "figs"
    plot = ["plot", str(readings), str(estimates), "--rod", "nitinol290"]
    # By default one file: the first reading's figure, and a word on how to get the others.
    assert main([*plot, "--truth", str(truth), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert [Path(p).name for p in captured.out.split()] == ["reading-case_0.png"]
    assert sorted(p.name for p in out.iterdir()) == ["reading-case_0.png"]
    assert "first of 3 readings" in captured.err and "--all" in captured.err
    # --all: one figure per reading.
    assert main([*plot, "--truth", str(truth), "--out", str(out), "--all"]) == 0
    written = capsys.readouterr().out.split()
    names = sorted(Path(p).name for p in written)
    assert names == ["reading-case_0.png", "reading-case_1.png", "reading-case_2.png"]
    assert all(_is_png(Path(p)) for p in written)
    # The default's one figure may go to a file name.
    first = tmp_path / "first.png"
    assert main([*plot, "--out", str(first)]) == 0
    assert capsys.readouterr().out.strip() == str(first) and _is_png(first)
    # --id: one figure, to a file name.
    one = tmp_path / "one.png"
    assert main([*plot, "--id", "case/1", "--out", str(one)]) == 0
    assert capsys.readouterr().out.strip() == str(one) and _is_png(one)
    # Several figures cannot go to one file; an unknown id is an error.
    assert main([*plot, "--all", "--out", str(tmp_path / "x.png")]) == 2
    assert "one file" in capsys.readouterr().err
    assert main([*plot, "--id", "nope", "--out", str(out)]) == 2
    assert "no reading with id" in capsys.readouterr().err


def test_plot_command_stream_against_time_with_truth(tmp_path, capsys, monkeypatch):
    lines = (DATA / "example_stream.jsonl").read_text().splitlines()[:12]
    readings = tmp_path / "s.jsonl"
    readings.write_text("\n".join(lines) + "\n")
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.1", "--quiet", str(readings)]) == 0
    estimates = tmp_path / "e.jsonl"
    estimates.write_text(capsys.readouterr().out)
    out = tmp_path / "stream"
    args = [
        "plot",
        str(readings),
        str(estimates),
        "--rod",
        "nitinol290",
        "--truth",
        str(DATA / "example_stream_truth.jsonl"),
        "--out",
    ]
    seen = {}
    original = plots.stream_figure

    def spy(t, est, **kwargs):
        seen.update(kwargs, t=t)
        return original(t, est, **kwargs)

    monkeypatch.setattr(plots, "stream_figure", spy)
    assert main(args + [str(out)]) == 0
    written = [Path(p) for p in capsys.readouterr().out.split()]
    assert [p.name for p in written] == ["stream.png"] and _is_png(written[0])
    # Only the truth of the 12 readings plotted (the truth file covers 500), at their times; their statuses.
    assert seen["truth_t"] == seen["t"] and len(seen["truth"]) == 12
    assert seen["statuses"] == [json.loads(x)["status"] for x in estimates.read_text().splitlines()]
    # The stream figure holds one point per estimated force, at the readings' times, in its location panel.
    est = [json.loads(x) for x in estimates.read_text().splitlines()]
    t = [json.loads(x)["t"] for x in lines]
    fig = plots.stream_figure(t, [[(f["s"], f["fx"], f["fy"]) for f in e["forces"]] for e in est])
    times, locations = _estimate_points(fig)
    assert len(times) == sum(len(e["forces"]) for e in est)
    assert set(times) <= set(t)
    assert sorted(locations) == pytest.approx(sorted(1e3 * f["s"] for e in est for f in e["forces"]))
    # A reading whose estimate is an error line is drawn as one without an estimate (status None).
    broken = est[:3] + [{"id": est[3]["id"], "error": "no fit"}] + est[4:]
    _write(estimates, broken)
    assert main(args + [str(out)]) == 0 and _is_png(out / "stream.png")
    assert seen["statuses"][3] is None and seen["statuses"][:3] == [e["status"] for e in est[:3]]
    assert len(seen["t"]) == 12
    _write(estimates, est)
    capsys.readouterr()
    # A reading of the stream by id (its truth drawn too).
    assert main(args + [str(tmp_path / "f3.png"), "--id", "f000003"]) == 0
    assert _is_png(tmp_path / "f3.png")


def _estimate_points(fig):
    """(times [s], locations [mm]) of the estimated forces the location panel of a stream figure draws."""
    ax = next(a for a in fig.axes if a.get_ylabel().startswith("location"))
    xy = [c.get_offsets() for c in ax.collections if len(c.get_offsets())]
    xy += [np.c_[ln.get_xdata(), ln.get_ydata()] for ln in ax.get_lines() if (ln.get_label() or "").startswith("stray")]
    points = np.concatenate(xy) if xy else np.zeros((0, 2))
    return points[:, 0].tolist(), points[:, 1].tolist()


def test_track_forces_links_forces_by_nearest_location():
    locations = [
        [0.05, 0.15],  # two contacts
        [0.152, 0.055],  # listed the other way round: each stays on its track
        [0.06],  # the one at 150 mm missed for a reading...
        [0.062, 0.149],  # ...and continued
        [0.064, 0.20, 0.151],  # one more appears
        [0.065, 0.148],  # the new one vanishes
        [],
        [],
        [],  # a gap longer than TRACK_MAX_GAP (2): tracks end
        [0.066],
        [0.066 + 1.5 * plots.TRACK_GATE],  # a jump beyond the gate: another contact
    ]
    tracks = plots.track_forces(locations)
    assert [x.tolist() for x in tracks] == [[0, 1], [1, 0], [0], [0, 1], [0, 2, 1], [0, 1], [], [], [], [3], [4]]
    # Two forces near one track: the nearer continues it, the other starts a track.
    assert [x.tolist() for x in plots.track_forces([[0.1], [0.115, 0.105]])] == [[0], [1, 0]]


def test_missed_contacts_counts_a_known_miss_and_no_false_one():
    tol = plots.MISS_TOLERANCE
    estimated = [
        [0.100, 0.200],  # both found, within the tolerance
        [0.100 + 0.9 * tol],  # found (just inside), the other missed
        [],  # nothing estimated: both missed
        [0.150],  # one force between two contacts 20 mm apart finds only one of them (the nearer)
    ]
    true = [[0.101, 0.195], [0.100, 0.200], [0.1, 0.2], [0.141, 0.160]]
    flags = plots.missed_contacts(estimated, true)
    assert [f.tolist() for f in flags] == [[False, False], [False, True], [True, True], [False, True]]
    assert sum(int(f.sum()) for f in flags) == 4
    with pytest.raises(ValueError, match="same readings"):
        plots.missed_contacts(estimated, true[:2])


def test_status_marks_for_readings_not_ok():
    t = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    statuses = ["ok", "poorly_determined", "poorly_determined", "ok", "misfit", None]
    spans = plots.status_spans(t, statuses)
    # One span per run of a status, each reading from halfway to its neighbours; no estimate has its own mark.
    assert list(spans) == ["misfit", "poorly_determined", plots.NO_ESTIMATE]
    assert spans["poorly_determined"] == [pytest.approx((0.05, 0.2))]
    assert spans["misfit"] == [pytest.approx((0.35, 0.1))]
    assert spans[plots.NO_ESTIMATE] == [pytest.approx((0.45, 0.1))]
    assert plots.status_spans(t, ["ok"] * 6) == {}
    # The figure draws them, one colour per status, and names them in a legend; the readings' forces, missed true
    # contacts (one here: the 200 mm contact at t = 0.1 s) and the count in the title.
    est = [[(0.1, 0.3, 0.0)], [(0.1, 0.3, 0.1)], [(0.1, 0.2, 0.0), (0.2, 0.1, 0.0)], [(0.1, 0.3, 0.0)], [], None]
    truth = [[(0.1, 0.3, 0.0)], [(0.1, 0.3, 0.1), (0.2, 0.05, 0.0)], [(0.1, 0.2, 0.0), (0.2, 0.1, 0.0)]]
    fig = plots.stream_figure(t, est, statuses=statuses, truth_t=t[:3], truth=truth, title="x")
    strip = next(a for a in fig.axes if a.get_ylabel() == "status")
    legend = strip.get_legend()
    assert [x.get_text() for x in legend.get_texts()] == ["misfit (1)", "poorly_determined (2)", "no estimate (1)"]
    colours = {tuple(c.get_facecolor()[0]) for c in strip.collections}
    assert len(strip.collections) == 3 and len(colours) == 3
    assert [x.get_text() for x in fig.texts] == ["x; 1 of 5 true contacts missed"]
    ax = next(a for a in fig.axes if a.get_ylabel().startswith("location"))
    missed = next(ln for ln in ax.get_lines() if ln.get_label().startswith("missed"))
    assert missed.get_xdata().tolist() == [0.1] and missed.get_ydata().tolist() == pytest.approx([200.0])
    assert len(_estimate_points(fig)[0]) == 5
    # Every reading ok: no marks, and a word that says so.
    fig = plots.stream_figure(t[:2], est[:2])
    strip = next(a for a in fig.axes if a.get_ylabel() == "status")
    assert not strip.collections and strip.get_legend() is None
    assert "every reading ok" in [x.get_text() for x in strip.texts]


def test_plot_needs_the_rod_unless_the_inputs_name_it(tmp_path, capsys):
    # A 16-grating rod: plot used to assume nitinol290 and fail with "the rod has 14".
    rod = tr.Rod(length=0.34, bending_stiffness=7e-3, gratings=tuple(0.01 + 0.02 * k for k in range(16)))
    rod.to_json(tmp_path / "rod16.json")
    u = tr.grating_curvature(rod, tr.PointForces.from_lists([[(0.2, 0.3, -0.2)]]))
    rows = [{"id": "a", "curvature": u[0].tolist()}]
    readings = _write(tmp_path / "r.jsonl", rows)
    estimates = _write(tmp_path / "e.jsonl", [{"id": "a", "forces": [{"s": 0.2, "fx": 0.3, "fy": -0.2}]}])
    out = tmp_path / "a.png"
    assert main(["plot", str(readings), str(estimates), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    # (the message names the input files, whose temporary paths may hold any digits: look at the rest)
    assert err.startswith("torchrod plot: error: which rod? pass --rod ROD"), err
    assert "14" not in err.replace(str(tmp_path), ""), err
    assert main(["plot", str(readings), str(estimates), "--rod", str(tmp_path / "rod16.json"), "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out) and _is_png(out)
    # The inputs may name it: a rod file beside them, a preset, or a rod object; all lines must agree.
    for named in ("rod16.json", rod.to_dict()):
        _write(readings, [dict(rows[0], rod=named)])
        out.unlink()
        assert main(["plot", str(readings), str(estimates), "--out", str(out)]) == 0 and _is_png(out)
        capsys.readouterr()
    _write(estimates, [{"id": "a", "rod": "nitinol290", "forces": []}])
    assert main(["plot", str(readings), str(estimates), "--out", str(out)]) == 2
    assert "name 2 different rods; pass --rod" in capsys.readouterr().err


def test_out_of_memory_names_options_plot_has(tmp_path, capsys, monkeypatch):
    """--dpi 20000 runs out of memory; the message suggested --count and --batch-size, which plot does not have."""
    rod = tr.presets.nitinol290()
    u = tr.grating_curvature(rod, tr.PointForces.from_lists([[(0.15, 0.4, 0.1)]]))
    readings = _write(tmp_path / "r.jsonl", [{"id": 1, "curvature": u[0].tolist()}])
    answer = {"id": 1, "num_forces": 1, "forces": [{"s": 0.15, "fx": 0.4, "fy": 0.1}]}
    estimates = _write(tmp_path / "e.jsonl", [answer])

    def out_of_memory(fig, path, dpi):
        assert dpi == 20000
        raise MemoryError  # what a 20000 dpi figure gives (allocating it here would take tens of GB)

    monkeypatch.setattr(plots, "save", out_of_memory)
    argv = ["plot", str(readings), str(estimates), "--rod", "nitinol290", "--dpi", "20000", "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == "torchrod plot: error: out of memory; ask for less at a time (a smaller --dpi)\n", err
