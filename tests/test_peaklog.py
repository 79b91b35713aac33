"""Interrogator peak logs (torchrod.io.peaklog): time stamps, the mapping of the N peaks to (grating, core), lines
that cannot be placed, and the estimate from a log equal to the estimate from the curvature it encodes."""

from __future__ import annotations

import io
import json
import math

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.errors import OptionsError
from torchrod.io.peaklog import PeakLog, is_peak_line, parse_peaks_option, peak_time
from torchrod.io.readings import iter_readings

F64 = torch.float64
R = 3.5e-5
THREE = [[R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]
BASE = tr.presets.nitinol290()
G = BASE.num_gratings
REFERENCE = [[1530.0 + 2.5 * g + 0.05 * c for c in range(3)] for g in range(G)]
ROD = BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}})


def _peaks(u: torch.Tensor, order: str = "by-core") -> list[float]:
    """The N = 3G peak wavelengths [nm] that curvature (G, 2) gives, in ``order``."""
    lam = torch.tensor(REFERENCE, dtype=F64) + ROD.fibre.bending_shift(u) / 1e-9  # (G, C)
    return (lam.T if order == "by-core" else lam).flatten().tolist()


def _line(time: str, values: list) -> str:
    return f"{time}: " + ", ".join("" if v is None else f"{v:.10f}" for v in values)


def test_time_stamps():
    assert peak_time("12-30-01.250000") == (12 * 3600 + 30 * 60 + 1.25, None, True)
    assert peak_time("12:30:01.5")[0] == 45001.5
    seconds, date, _ = peak_time("2024-03-01 00:00:02.5")
    assert seconds == 2.5 and date.isoformat() == "2024-03-01"
    assert peak_time("17.25") == (17.25, None, False)
    for bad in ("25-00-00.0", "12-61-00", "noon"):
        with pytest.raises(ValueError, match="time stamp"):
            peak_time(bad)
    log = PeakLog(ROD.fibre, G)
    zero = [1530.0] * (3 * G)
    ts = [log.reading_object(_line(t, zero))["t"] for t in ("23-59-59.5", "00-00-00.5", "00-00-01.0")]
    assert ts == [86399.5, 86400.5, 86401.0]  # midnight passes: a day is added
    log = PeakLog(ROD.fibre, G)
    dated = [log.reading_object(_line(t, zero))["t"] for t in ("2024-03-01 23:59:59", "2024-03-02 00:00:01")]
    assert dated == [86399.0, 86401.0]


def test_is_peak_line():
    assert is_peak_line("10-11-12.123456: 1530.123, 1531.5")
    assert is_peak_line("3.5: 1530.1 1530.2")
    assert not is_peak_line("id,t,ux_1")
    assert not is_peak_line('{"id": 1}')
    assert not is_peak_line("a,b: 1, 2")


def test_layouts_place_each_peak():
    u = 4.0 * torch.randn(G, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    by_core = PeakLog(ROD.fibre, G).reading_object(_line("1.0", _peaks(u, "by-core")))
    by_grating = PeakLog(ROD.fibre, G, "by-grating").reading_object(_line("1.0", _peaks(u, "by-grating")))
    assert by_core["wavelength"] == by_grating["wavelength"]
    assert torch.allclose(
        torch.tensor(by_core["wavelength"], dtype=F64),
        torch.tensor(_peaks(u, "by-grating"), dtype=F64).reshape(G, 3),
        atol=1e-9,
    )
    # explicit, with a peak that is read by no grating (a temperature reference) and gratings 2..14 left out
    explicit = ((0, 2), None, (0, 0), (0, 1))
    obj = PeakLog(ROD.fibre, G, explicit).reading_object("1.0: 1530.3, 1600.0, 1530.1, 1530.2")
    assert obj["wavelength"][0] == [1530.1, 1530.2, 1530.3] and obj["wavelength"][1:] == [None] * (G - 1)


def test_a_line_that_cannot_be_placed_is_one_error_and_the_others_go_on():
    u = 4.0 * torch.randn(2, G, 2, dtype=F64, generator=torch.Generator().manual_seed(2))
    peaks = [_peaks(u[0]), _peaks(u[1])]
    lost = peaks[1][:-1]  # one peak not detected: nothing after it can be placed
    gap = list(peaks[1])
    gap[G + 4] = None  # an empty value: core 2 of grating 5 undetected, that grating missing
    text = "\n".join(
        [_line("10-00-00.0", peaks[0]), _line("10-00-00.1", lost), "not a log line", _line("10-00-00.2", gap)]
    )
    got = list(iter_readings(io.StringIO(text + "\n"), G, fmt="peaks", fibre=ROD.fibre))
    assert [r.ok for r in got] == [True, False, False, True]
    assert got[1].error.startswith("line 2: 41 peaks, the layout (14 gratings x 3 cores, by-core) has 42")
    assert got[2].error.startswith("line 3: not a peak log line")
    assert got[0].t == 36000.0 and got[3].t == pytest.approx(36000.2)
    assert torch.allclose(got[0].curvature, u[0], atol=1e-8)
    assert torch.isnan(got[3].curvature[4]).all()
    keep = torch.arange(G) != 4
    assert torch.allclose(got[3].curvature[keep], u[1][keep], atol=1e-8)


def test_the_last_peak_can_be_marked_undetected():
    """An empty last value was taken for a trailing comma, so the line had N - 1 peaks and was lost; it marks the
    last peak undetected (its grating missing), and one comma after all N values still ends a line."""
    u = 4.0 * torch.randn(G, 2, dtype=F64, generator=torch.Generator().manual_seed(3))
    peaks = _peaks(u)
    last = [*peaks[:-1], None]  # by-core: core 3 of grating 14
    text = "\n".join([_line("1.0", last), _line("2.0", peaks) + ",", _line("3.0", last) + ","])
    got = list(iter_readings(io.StringIO(text + "\n"), G, fmt="peaks", fibre=ROD.fibre))
    assert [r.ok for r in got] == [True, True, True], [r.error for r in got]
    assert torch.isnan(got[0].curvature[G - 1]).all() and torch.isnan(got[2].curvature[G - 1]).all()
    assert torch.allclose(got[0].curvature[: G - 1], u[: G - 1], atol=1e-8)
    assert torch.allclose(got[1].curvature, u, atol=1e-8)
    two_over = list(iter_readings(io.StringIO(_line("4.0", peaks) + ",,\n"), G, fmt="peaks", fibre=ROD.fibre))
    assert two_over[0].error.startswith("line 1: 44 peaks, the layout (14 gratings x 3 cores, by-core) has 42")


def test_peaks_option():
    assert parse_peaks_option("by-grating") == "by-grating"
    assert parse_peaks_option("1:1, 1:2 ,-,1:3") == ((0, 0), (0, 1), None, (0, 2))
    with pytest.raises(OptionsError, match="--peaks entry 2 is '1-2'"):
        parse_peaks_option("1:1,1-2")
    with pytest.raises(ValueError, match="--peaks maps 2 of grating 1's 3 cores"):
        PeakLog(ROD.fibre, G, ((0, 0), (0, 1)))


def test_estimate_from_a_peak_log_equals_the_curvatures(tmp_path, capsys):
    loads = tr.PointForces(
        s=torch.tensor([[0.12, 0.24], [0.07, 0.2]], dtype=F64),
        f=torch.tensor([[[0.4, -0.9], [0.3, 0.2]], [[-1.2, 0.1], [0.0, 0.6]]], dtype=F64),
    )
    u = tr.simulate(BASE, loads).grating_curvature
    u = u + 0.05 * torch.randn(u.shape, dtype=F64, generator=torch.Generator().manual_seed(3))
    rod_file, log, jsonl = tmp_path / "rod.json", tmp_path / "peaks.txt", tmp_path / "u.jsonl"
    ROD.to_json(rod_file)
    log.write_text("".join(_line(f"09-00-0{b}.000000", _peaks(u[b], "by-grating")) + "\n" for b in range(2)))
    jsonl.write_text("".join(json.dumps({"t": 32400.0 + b, "curvature": u[b].tolist()}) + "\n" for b in range(2)))
    base = ["--noise", "0.05", "--quiet"]
    assert main(["estimate", str(rod_file), str(log), *base, "--peaks", "by-grating"]) == 0  # detected: a peak log
    from_log = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert main(["estimate", str(rod_file), str(jsonl), *base]) == 0
    from_json = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [a["num_forces"] for a in from_json] == [2, 2]
    for a, b in zip(from_log, from_json, strict=True):
        assert a["num_forces"] == b["num_forces"]
        for fa, fb in zip(a["forces"], b["forces"], strict=True):
            for key in ("s", "fx", "fy"):
                assert fa[key] == pytest.approx(fb[key], rel=1e-6, abs=1e-9)
    # the wrong layout (by-core on a log written by grating) is no confident answer: every line is a misfit
    assert main(["estimate", str(rod_file), str(log), *base]) == 0
    assert [json.loads(x)["status"] for x in capsys.readouterr().out.splitlines()] == ["misfit", "misfit"]
    assert main(["estimate", "nitinol290", str(log), *base]) == 2
    assert "a peak log needs the rod file's" in capsys.readouterr().err
