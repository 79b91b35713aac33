"""Jig calibration of the fibre's matrices (torchrod.jig, ``torchrod calibrate --fibre``): known matrices recovered
from noisy simulated jig readings within the statistics, a grating planted 2x off flagged, the leave-one-jig-out
check, the written rod file, and the refusals."""

from __future__ import annotations

import json
import math
import re

import pytest
import torch
from scipy.stats import chi2

import torchrod as tr
from torchrod.cli import main
from torchrod.errors import ReadingError
from torchrod.jig import GAIN_TOLERANCE, JigData, calibrate_fibre, read_jig_readings
from torchrod.sensors import Fibre

F64 = torch.float64
R = 3.5e-5
THREE = [[R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]
BASE = tr.presets.nitinol290()
G, C = BASE.num_gratings, 3
REFERENCE = [[1530.0 + 2.5 * g + 0.05 * c for c in range(C)] for g in range(G)]
SIGMA_NM = 0.002  # 2 pm of wavelength noise per core
KAPPAS = (5.0, 10.0, 20.0)  # [1/m], and a straight jig
ANGLES = [math.radians(a) for a in range(0, 360, 45)]


def true_matrices(planted: int | None = None) -> torch.Tensor:
    """(G, 2, C) [1/m per nm]: the physics route's maps, each grating perturbed by a few per cent; the rows made
    orthogonal to (1, 1, 1) (the part a calibration can know); grating ``planted`` twice as sensitive."""
    physics = Fibre(cores=THREE, wavelength={"reference": REFERENCE})
    maps = torch.tensor(physics.shift_maps(), dtype=F64) * 1e-9
    g = torch.Generator().manual_seed(0)
    maps = maps * (1.0 + 0.04 * torch.randn(G, 2, C, generator=g, dtype=F64))
    maps = maps - maps.mean(-1, keepdim=True)
    if planted is not None:
        maps[planted] *= 2.0
    return maps


def jig_readings(matrices: torch.Tensor, seed: int = 1, repeats: int = 2):
    """Shifts [nm] (R, G, C) of jig readings from ``matrices``: the bend's (the matrices' pseudo-inverse), a
    temperature per reading and grating, and noise; with their clean part, jig curvatures and jig names."""
    g = torch.Generator().manual_seed(seed)
    jigs = [(0.0, 0.0)] * 4 + [(k, a) for k in KAPPAS for a in ANGLES for _ in range(repeats)]
    u = torch.tensor([[k * math.cos(a), k * math.sin(a)] for k, a in jigs], dtype=F64)
    clean = torch.einsum("gcj,rj->rgc", torch.linalg.pinv(matrices), u)
    temperature = 0.5 * torch.rand(len(jigs), G, 1, generator=g, dtype=F64)
    noisy = clean + temperature + SIGMA_NM * torch.randn(clean.shape, generator=g, dtype=F64)
    return noisy, clean, jigs


def test_recovers_known_matrices_within_the_statistics():
    """To first order the fit's error is dA^T = -D^+ E A^T (E the noise on the centred shifts D), so per grating
    tr((sigma^2 A A^T)^-1 dA (D^T D) dA^T) is chi-square with 2 x 2 degrees of freedom; summed over the gratings,
    4G."""
    A = true_matrices()
    noisy, clean, jigs = jig_readings(A)
    data = JigData(noisy * 1e-9, torch.tensor([[k * math.cos(a), k * math.sin(a)] for k, a in jigs], dtype=F64),
                   tuple(k for k, _ in jigs))  # fmt: skip
    result = calibrate_fibre(BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}}), data)
    fitted = result.matrices * 1e-9  # per nm
    total = 0.0
    for g in range(G):
        d0 = clean[:, g] - clean[:, g].mean(-1, keepdim=True)
        da = fitted[g] - A[g]
        sigma2 = SIGMA_NM**2 * A[g] @ A[g].T
        total += float(torch.trace(torch.linalg.inv(sigma2) @ da @ (d0.T @ d0) @ da.T))
    dof = 4 * G
    assert chi2.ppf(0.001, dof) < total < chi2.ppf(0.999, dof), total
    # the residual is the noise carried through each matrix: sigma^2 tr(A A^T) / 2 per component
    predicted = SIGMA_NM * (torch.einsum("gjc,gjc->g", A, A) / 2).sqrt()
    ratio = result.residual / predicted
    assert bool((ratio > 0.7).all() and (ratio < 1.3).all()), ratio
    # leave-one-jig-out: a curvature the fit never saw is predicted about as well
    assert set(result.leave_one_out) == {0.0, *KAPPAS}
    assert all(v is not None and v < 5 * float(predicted.max()) for v in result.leave_one_out.values())
    assert bool((result.leave_one_out_grating < 3 * predicted).all())
    assert result.warnings == () and result.problems == ()


def test_a_grating_planted_2x_off_is_flagged():
    A = true_matrices(planted=4)
    noisy, _, jigs = jig_readings(A, seed=2)
    u = torch.tensor([[k * math.cos(a), k * math.sin(a)] for k, a in jigs], dtype=F64)
    rod = BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}})
    result = calibrate_fibre(rod, JigData(noisy * 1e-9, u, tuple(k for k, _ in jigs)))
    assert len(result.warnings) == 2, result.warnings
    assert all(w.startswith("grating 5's gain") for w in result.warnings)
    assert "from the gratings' median" in result.warnings[0] and "from the physics route's" in result.warnings[1]
    assert f"tolerance {100 * GAIN_TOLERANCE:g} %" in result.warnings[0]
    assert float(result.gains[4] / result.physics_gains[4]) == pytest.approx(2.0, rel=0.1)


def test_one_bend_direction_cannot_determine_a_matrix():
    A = true_matrices()
    shifts = torch.einsum("gcj,rj->rgc", torch.linalg.pinv(A), torch.tensor([[5.0, 0.0], [10.0, 0.0]], dtype=F64))
    data = JigData(shifts * 1e-9, torch.tensor([[5.0, 0.0], [10.0, 0.0]], dtype=F64), (5.0, 10.0))
    with pytest.raises(ReadingError, match="grating 1: the readings span one bend direction only"):
        calibrate_fibre(BASE.with_(fibre={"cores": THREE}), data)


def test_calibrate_fibre_command_writes_the_rod_and_refuses_its_input(tmp_path, capsys):
    """Absolute wavelengths on a rod without a reference: the straight jig's mean becomes it; the written rod reads
    wavelengths as the jig's curvature."""
    A = true_matrices()
    noisy, _, jigs = jig_readings(A, seed=3, repeats=1)
    lam = torch.tensor(REFERENCE, dtype=F64) + noisy
    rod_file, readings, out = tmp_path / "rod.json", tmp_path / "jig.jsonl", tmp_path / "calibrated.json"
    BASE.with_(fibre={"cores": THREE}).to_json(rod_file)
    with readings.open("w") as fh:
        for r, (k, a) in enumerate(jigs):
            jig = {"curvature": k / 100, "angle": a, "name": f"R{k:g}"}  # jig curvatures given in 1/cm
            fh.write(json.dumps({"id": r, "wavelength": lam[r].tolist(), "jig": jig}) + "\n")
    argv = ["calibrate", "--fibre", "--rod", str(rod_file), str(readings), "--curvature-unit", "1/cm"]
    assert main([*argv, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "jig readings on 4 jigs, 14 gratings x 3 cores" in err
    assert "leave-one-jig-out: jig 'R20' (8 readings) predicted from the others: RMS" in err
    assert "warning" not in err
    calibrated = tr.Rod.from_json(out)
    assert calibrated.fibre.route == "calibration" and calibrated.fibre.curvature_unit == "1/m"
    # each grating's leave-one-jig-out error as a fraction of the jig curvatures: its calibration error
    assert len(calibrated.calibration_error) == G and all(0.0 < x < 0.05 for x in calibrated.calibration_error)
    # the straight jig's mean: the reference up to its readings' temperature, a shift common to each grating's cores
    offset = torch.tensor(calibrated.fibre.wavelength.reference, dtype=F64) - torch.tensor(REFERENCE, dtype=F64)
    assert torch.allclose(offset - offset.mean(-1, keepdim=True), torch.zeros(G, C, dtype=F64), atol=0.01)
    fitted = torch.tensor(calibrated.fibre.wavelength.calibration, dtype=F64)
    assert torch.allclose(fitted, A, rtol=0, atol=0.05 * float(A.abs().max()))
    # the written rod turns a wavelength reading into the jig's curvature
    reading = {"wavelength": (torch.tensor(REFERENCE, dtype=F64) + noisy[-1]).tolist()}
    u = tr.io.readings.parse_reading(reading, G, fibre=calibrated.fibre).curvature
    k, a = jigs[-1]
    assert torch.allclose(u, torch.tensor([[k * math.cos(a), k * math.sin(a)]] * G, dtype=F64), atol=0.1)
    # never over an input
    before = rod_file.read_text()
    for target in (rod_file, readings):
        assert main([*argv, "--out", str(target)]) == 2
        assert "writing it would erase the input" in capsys.readouterr().err
    assert rod_file.read_text() == before


def test_jig_readings_from_csv_and_their_errors(tmp_path):
    A = true_matrices()
    noisy, _, jigs = jig_readings(A, seed=4, repeats=1)
    header = ["id"] + [f"dlambda_{g + 1}_{c + 1}" for g in range(G) for c in range(C)] + ["jig_curvature", "jig_angle"]
    rows = [",".join(header)]
    for r, (k, a) in enumerate(jigs):
        rows.append(",".join([str(r), *map(repr, noisy[r].flatten().tolist()), repr(k), repr(a)]))
    path = tmp_path / "jig.csv"
    path.write_text("\n".join(rows) + "\n")
    rod = BASE.with_(fibre={"cores": THREE})
    data = read_jig_readings(path, rod)
    assert torch.allclose(data.shifts, noisy * 1e-9, rtol=1e-12) and data.jigs[:5] == (0.0, 0.0, 0.0, 0.0, 5.0)
    bad = tmp_path / "bad.jsonl"
    bad.write_text(
        json.dumps({"wavelength_shift": noisy[0].tolist()}) + "\n"
        + json.dumps({"wavelength_shift": noisy[0].tolist(), "jig": {"curvature": 5.0}}) + "\n"
        + json.dumps({"curvature": [[0.0, 0.0]] * G, "jig": {"curvature": 0.0}}) + "\n"
    )  # fmt: skip
    with pytest.raises(ReadingError, match="3 unusable line") as info:
        read_jig_readings(bad, rod)
    message = str(info.value)
    assert "line 1: missing 'jig'" in message and "line 2: jig is missing 'angle'" in message
    assert "line 3: a jig reading gives exactly one of wavelength, wavelength_shift" in message


def _write_jig_file(path, shifts: torch.Tensor, jigs) -> None:
    with path.open("w") as fh:
        for r, (k, a) in enumerate(jigs):
            fh.write(json.dumps({"id": r, "wavelength_shift": shifts[r].tolist(), "jig": {"curvature": k, "angle": a}}))
            fh.write("\n")


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        ("random", "residual up to .* 1/m, .* % of the jig curvatures' RMS .* 1/m \\(bound 10 %\\)"),
        ("angles off by pi", "the fit turns a bend by up to 180 degrees from the physics route's direction"),
        ("one jig's angles off by pi", "leave-one-jig-out error up to"),
        ("curvatures 100x", "gain up to 10[0-9.]* times the physics route's \\(bound a factor 3\\)"),
        ("mirrored", "the fit mirrors a bend against the physics route's"),
    ],
)
def test_calibrate_fibre_refuses_a_fit_the_jigs_do_not_support(tmp_path, capsys, spoil, message):
    """Random shifts, jig angles off by pi, jig curvatures 100x off were written with exit 0 (at most warnings);
    they are refused as the known-force calibration is: exit 1, no rod written, --force writes it anyway."""
    A = true_matrices()
    noisy, _, jigs = jig_readings(A, seed=5, repeats=1)
    if spoil == "random":
        noisy = torch.randn(noisy.shape, generator=torch.Generator().manual_seed(6), dtype=F64)
    elif spoil == "angles off by pi":
        jigs = [(k, a + math.pi) for k, a in jigs]
    elif spoil == "one jig's angles off by pi":
        jigs = [(k, a + math.pi if k == 10.0 else a) for k, a in jigs]
    elif spoil == "curvatures 100x":
        jigs = [(100 * k, a) for k, a in jigs]
    else:
        jigs = [(k, -a) for k, a in jigs]
    rod_file, readings, out = tmp_path / "rod.json", tmp_path / "jig.jsonl", tmp_path / "calibrated.json"
    BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}}).to_json(rod_file)
    _write_jig_file(readings, noisy, jigs)
    argv = ["calibrate", "--fibre", "--rod", str(rod_file), str(readings), "--out", str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert re.search("torchrod calibrate --fibre: refused: grating.*" + message, err), err
    assert "torchrod calibrate --fibre: no rod written (--force writes it anyway)" in err
    assert not out.exists()
    assert main([*argv, "--force"]) == 0
    assert "torchrod calibrate --fibre: warning (forced): grating" in capsys.readouterr().err
    assert tr.Rod.from_json(out).fibre.route == "calibration"


def test_good_jig_readings_are_not_refused(tmp_path, capsys):
    noisy, _, jigs = jig_readings(true_matrices(), seed=5, repeats=1)
    rod_file, readings, out = tmp_path / "rod.json", tmp_path / "jig.jsonl", tmp_path / "calibrated.json"
    BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}}).to_json(rod_file)
    _write_jig_file(readings, noisy, jigs)
    assert main(["calibrate", "--fibre", "--rod", str(rod_file), str(readings), "--out", str(out)]) == 0
    assert "refused" not in capsys.readouterr().err and out.exists()


@pytest.mark.parametrize("case", ["one direction", "angles 0 and pi", "two readings"])
def test_readings_bending_one_way_are_refused_not_divided_by_zero(tmp_path, capsys, case):
    """Noisy readings of bends along one line spanned a plane of shifts but not of curvatures: a zero gain, then
    ZeroDivisionError. They are refused with the one-direction message."""
    A = true_matrices()
    if case == "two readings":
        jigs = [(0.0, 0.0), (10.0, 0.5)]
    else:
        angles = (0.0,) if case == "one direction" else (0.0, math.pi)
        jigs = [(0.0, 0.0)] * 2 + [(k, a) for k in KAPPAS for a in angles]
    u = torch.tensor([[k * math.cos(a), k * math.sin(a)] for k, a in jigs], dtype=F64)
    g = torch.Generator().manual_seed(7)
    shifts = torch.einsum("gcj,rj->rgc", torch.linalg.pinv(A), u)
    shifts = shifts + SIGMA_NM * torch.randn(shifts.shape, generator=g, dtype=F64)
    with pytest.raises(ReadingError, match="grating 1: the readings span one bend direction only"):
        calibrate_fibre(BASE.with_(fibre={"cores": THREE}), JigData(shifts * 1e-9, u, tuple(k for k, _ in jigs)))
    rod_file, readings = tmp_path / "rod.json", tmp_path / "jig.jsonl"
    BASE.with_(fibre={"cores": THREE, "wavelength": {"reference": REFERENCE}}).to_json(rod_file)
    _write_jig_file(readings, shifts, jigs)
    out = tmp_path / "calibrated.json"
    assert main(["calibrate", "--fibre", "--rod", str(rod_file), str(readings), "--out", str(out)]) == 2
    assert "the readings span one bend direction only" in capsys.readouterr().err and not out.exists()


def test_a_fit_no_jig_can_check_is_refused():
    """Two readings at two bend directions determine the matrices exactly, and nothing is left to check them by."""
    A = true_matrices()
    u = torch.tensor([[10.0, 0.0], [0.0, 10.0]], dtype=F64)
    shifts = torch.einsum("gcj,rj->rgc", torch.linalg.pinv(A), u)
    result = calibrate_fibre(BASE.with_(fibre={"cores": THREE}), JigData(shifts * 1e-9, u, ("J1", "J2")))
    assert result.problems == (
        "no jig of 2 can be left out and predicted from the others (every one is needed to determine the matrices), "
        "so nothing checks the fit: add readings on more jigs, at two bend directions or more",
    )
