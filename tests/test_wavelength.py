"""Peak wavelengths to curvature (torchrod.sensors, the reading parser, the CLI): the rod file's fibre.wavelength and
unit keys, the two routes (calibration matrices, physics), the readings "wavelength" and "wavelength_shift", the
noise they imply, the unit options, and round trips from simulated curvature through synthetic wavelengths to the
estimate."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.errors import RodError
from torchrod.io.readings import parse_reading, to_reading
from torchrod.sensors import Fibre

F64 = torch.float64
R = 3.5e-5
THREE = [[R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]
FOUR = [[0.0, 0.0], [R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]  # a central core
ROD = tr.presets.nitinol290()
G = ROD.num_gratings
PE = 0.22


def reference(C: int) -> list[list[float]]:
    """[nm] per grating, cores a little apart (as written gratings are)."""
    return [[1530.0 + 2.5 * g + 0.1 * c for c in range(C)] for g in range(G)]


def calibration(C: int, seed: int = 0) -> list[list[list[float]]]:
    """Per grating a 2 x C matrix [1/m per nm], different per grating."""
    g = torch.Generator().manual_seed(seed)
    return (25.0 * torch.randn(G, 2, C, generator=g, dtype=F64)).tolist()


@pytest.fixture(scope="module")
def physics_rod():
    return ROD.with_(fibre={"cores": THREE, "wavelength": {"reference": reference(3), "photoelastic": PE}})


@pytest.fixture(scope="module")
def calibrated_rod():
    return ROD.with_(fibre={"wavelength": {"reference": reference(4), "calibration": calibration(4)}})


# ---------------------------------------------------------------------------------------------------- rod file
def test_rod_file_round_trip_with_wavelength_and_units(tmp_path, physics_rod, calibrated_rod):
    for rod in (physics_rod, calibrated_rod, ROD.with_(fibre={"curvature_unit": "1/cm"})):
        path = tmp_path / "rod.json"
        rod.to_json(path)
        again = tr.Rod.from_json(path)
        assert again == rod
        assert again.to_dict()["fibre"] == rod.to_dict()["fibre"]
    assert physics_rod.fibre.route == "physics" and calibrated_rod.fibre.route == "calibration"
    assert json.loads((tmp_path / "rod.json").read_text())["fibre"] == {"curvature_unit": "1/cm"}
    # without a calibration the photoelastic coefficient is written (it is used); defaults are not
    written = physics_rod.to_dict()["fibre"]
    assert written["wavelength"]["reference"] == reference(3) and "curvature_unit" not in written


@pytest.mark.parametrize(
    ("fibre", "message"),
    [
        ({"wavelength": {"reference": [[1.55e-6] * 3] * G}, "cores": THREE}, r"reference\[0\]\[0\] = 1.55e-06 is not"),
        ({"wavelength": {"reference": reference(3)[:-1]}, "cores": THREE}, "has 13 rows but the rod has 14 gratings"),
        ({"wavelength": {"reference": reference(3)}}, "needs fibre.cores"),
        ({"wavelength": {"reference": reference(4)}, "cores": THREE}, "gives 4 values per grating but fibre.cores"),
        ({"wavelength": {"calibration": [[[1.0, 2.0, 3.0]]] * G}}, r"calibration\[0\] must hold two rows"),
        ({"wavelength": {"calibration": [[[1.0, 2.0], [1.0, "x"]]] * G}}, r"calibration\[0\]\[1\]\[1\] must be a"),
        ({"wavelength": {"reference": reference(3), "photoelastic": 1.5}, "cores": THREE}, "photoelastic must lie"),
        ({"wavelength": {"reference": reference(3), "gauge": 1}, "cores": THREE}, "unknown fibre.wavelength keys"),
        ({"wavelength": {}}, "needs a reference"),
        ({"wavelength": {"calibration": calibration(3), "reference": reference(3)[:3]}}, "one of each per grating"),
        ({"wavelength": {"calibration": calibration(3), "peaks": "by-row"}}, "peaks must be by-core or by-grating"),
        ({"wavelength": {"calibration": calibration(3), "peaks": [[1, 1], [1, 1]]}}, "both map to grating 1"),
        ({"wavelength": {"calibration": calibration(3), "peaks": [[1, 1], [1, 2]]}}, "maps 2 of grating 1's 3 cores"),
        ({"wavelength": {"calibration": calibration(3), "peaks": [[15, 1]]}}, "outside the fibre's 14 gratings"),
        ({"curvature_unit": "1/km"}, "fibre.curvature_unit must be one of 1/m, 1/cm, 1/mm"),
        ({"wavelength_unit": "m"}, "fibre.wavelength_unit must be one of nm, pm"),
        ({"strain_unit": True}, "fibre.strain_unit must be one of strain, microstrain"),
    ],
)
def test_rod_file_fibre_errors_name_the_field(fibre, message):
    with pytest.raises(RodError, match=message):
        tr.Rod.from_dict({**ROD.to_dict(), "fibre": fibre})


def _one_bad(grating: int, matrix: list[list[float]]) -> list[list[list[float]]]:
    mats = calibration(3)
    mats[grating] = matrix
    return mats


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        ([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], "reads no curvature from any shift"),
        ([[7.0, 7.0, 7.0], [-3.0, -3.0, -3.0]], "reads no curvature from any shift"),  # constant over the cores
        ([[1e-300, -2e-300, 1e-300], [3e-300, 0.0, -3e-300]], r"has gains \S+e-300 to \S+e-300 1/m per nm, outside"),
        ([[10.0, -5.0, -5.0], [20.0, -10.0, -10.0]], "is of rank one once the shift common"),  # proportional rows
        ([[10.0, -5.0, -5.0], [1e-9, 0.0, -1e-9]], "is of rank one once the shift common"),
        ([[1e7, -5e6, -5e6], [0.0, 8e6, -8e6]], r"has gains 1.13e\+07 to 1.22e\+07 1/m per nm, outside"),  # 1/m per pm
    ],
)
def test_calibration_that_cannot_read_a_bend_is_refused_naming_the_grating(matrix, message):
    """A calibration of zeros, constant across the cores or of 1e-300 read every reading as no force; one of rank
    one reads every force along one line: all are refused at load, naming the grating."""
    with pytest.raises(RodError, match=r"fibre.wavelength.calibration\[5\] \(grating 6\) " + message):
        tr.Rod.from_dict({**ROD.to_dict(), "fibre": {"wavelength": {"calibration": _one_bad(5, matrix)}}})


def test_calibration_of_two_cores_is_refused():
    mats = [[[10.0, -10.0], [3.0, -3.0]]] * G
    with pytest.raises(RodError, match=r"calibration\[0\] \(grating 1\) is of rank one"):
        tr.Rod.from_dict({**ROD.to_dict(), "fibre": {"wavelength": {"calibration": mats}}})


# ---------------------------------------------------------------------------------------------------- routes
def test_calibration_route_is_the_matrix_on_the_centred_shifts(calibrated_rod):
    fibre = calibrated_rod.fibre
    A = torch.tensor(calibration(4), dtype=F64)  # (G, 2, C) per nm
    d_nm = torch.randn(G, 4, dtype=F64, generator=torch.Generator().manual_seed(1))
    expected = torch.einsum("gjc,gc->gj", A, d_nm - d_nm.mean(-1, keepdim=True))
    got = fibre.wavelength_curvature(d_nm * 1e-9)  # the tensor path, SI
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12)
    for k in (0, 5):  # the float path the parser uses gives the same
        assert fibre.shift_to_curvature(k, (d_nm[k] * 1e-9).tolist()) == pytest.approx(expected[k].tolist(), rel=1e-12)
    # a shift common to the cores leaves no trace
    assert torch.allclose(
        fibre.wavelength_curvature(torch.full((G, 4), 3e-10, dtype=F64)), torch.zeros(G, 2, dtype=F64)
    )


def test_physics_route_is_strain_then_the_multicore_least_squares(physics_rod):
    fibre = physics_rod.fibre
    ref_m = torch.tensor(reference(3), dtype=F64) * 1e-9
    d = 1e-10 * torch.randn(G, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    strain = d / (ref_m * (1 - PE))
    expected = torch.tensor([Fibre(cores=THREE).strain_to_curvature(row) for row in strain.tolist()], dtype=F64)
    assert torch.allclose(fibre.wavelength_curvature(d), expected, rtol=1e-12, atol=1e-12)
    # a common strain (temperature: shifts proportional to each core's reference) leaves no trace
    assert torch.allclose(fibre.wavelength_curvature(ref_m * (1 - PE) * 4e-4), torch.zeros(G, 2, dtype=F64), atol=1e-9)
    # its size: 1 nm on the core at (r, 0) alone reads as u_y = -(2/3) eps / r, eps = 1 nm / (1530 nm (1 - p_e))
    one = torch.zeros(G, 3, dtype=F64)
    one[0, 0] = 1e-9
    got = fibre.wavelength_curvature(one)[0]
    assert float(got[0]) == pytest.approx(0.0, abs=1e-9)
    assert float(got[1]) == pytest.approx(-2 / 3 * 1e-9 / (1530e-9 * (1 - PE) * R), rel=1e-12)


@pytest.mark.parametrize("name", ["physics", "calibrated"])
def test_wavelength_sigmas_match_monte_carlo(name, physics_rod, calibrated_rod):
    fibre = (physics_rod if name == "physics" else calibrated_rod).fibre
    sigma = 2e-12  # 2 pm
    noise = sigma * torch.randn(40000, G, fibre.num_cores, dtype=F64, generator=torch.Generator().manual_seed(3))
    u = fibre.wavelength_curvature(noise)  # (n, G, 2)
    for g in (0, 7, 13):
        cov = u[:, g].T @ u[:, g] / u.shape[0]
        largest = float(torch.linalg.eigvalsh(cov)[-1].sqrt())
        assert fibre.wavelength_sigmas(sigma)[g] == pytest.approx(largest, rel=0.03)


def test_bending_and_temperature_shifts_invert_the_conversion(physics_rod, calibrated_rod):
    u = 5.0 * torch.randn(6, G, 2, dtype=F64, generator=torch.Generator().manual_seed(4))
    common = 1e-3 * torch.randn(6, G, dtype=F64, generator=torch.Generator().manual_seed(5))
    for rod in (physics_rod, calibrated_rod):
        d = rod.fibre.bending_shift(u) + rod.fibre.temperature_shift(common)
        assert torch.allclose(rod.fibre.wavelength_curvature(d), u, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------------- readings
def _pairs_of(u: torch.Tensor, missing: int = 2) -> list:
    return [None if k == missing else row for k, row in enumerate(u.tolist())]


def test_parser_reads_wavelength_and_shift_with_missing_gratings(calibrated_rod):
    fibre = calibrated_rod.fibre
    u = 3.0 * torch.randn(G, 2, dtype=F64, generator=torch.Generator().manual_seed(6))
    d_nm = fibre.bending_shift(u) / 1e-9 + 0.2  # a temperature of 0.2 nm on every core
    absolute = torch.tensor(reference(4), dtype=F64) + d_nm
    ref = parse_reading({"curvature": _pairs_of(u)}, G).curvature
    for key, values in (("wavelength", absolute), ("wavelength_shift", d_nm)):
        got = parse_reading({key: _pairs_of(values)}, G, fibre=fibre).curvature
        assert torch.isnan(got[2]).all()
        assert torch.allclose(torch.nan_to_num(got), torch.nan_to_num(ref), rtol=0, atol=1e-9)
        # the Python stream API's entry reads them too
        assert torch.allclose(
            torch.nan_to_num(to_reading({key: _pairs_of(values)}, G, fibre=fibre).curvature),
            torch.nan_to_num(ref),
            rtol=0,
            atol=1e-9,
        )


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        ({"wavelength": [[1530.0] * 4] * 14, "curvature": [[0.0, 0.0]] * 14}, "give exactly one"),
        ({"wavelength": [[1530.0] * 3] * 14}, r"wavelength\[0\] must be a list of 4 values \[nm\]"),
        ({"wavelength": [[1530000.0] * 4] * 14}, r"wavelength\[0\]\[0\] = 1530000.0 nm is not a peak wavelength"),
        ({"wavelength_shift": [[0.0, 0.0, 0.0, 150.0]] * 14}, r"wavelength_shift\[0\]\[3\] = 150.0 nm is a shift"),
        ({"wavelength_shift": [[0.0, True, 0.0, 0.0]] * 14}, r"wavelength_shift\[0\]\[1\] must be a number"),
        ({"wavelength_shift": [None] * 14}, "all gratings are missing"),
        ({"wavelength": [[1530.0 + 200] * 4] * 14}, r"lies 200 nm from its reference"),
    ],
)
def test_parser_wavelength_errors(obj, message, calibrated_rod):
    with pytest.raises(ValueError, match=message):
        parse_reading(obj, G, fibre=calibrated_rod.fibre)


def test_wavelength_needs_the_rod_files_section_and_a_reference():
    with pytest.raises(ValueError, match='needs the rod file\'s "fibre": {"wavelength"'):
        parse_reading({"wavelength_shift": [[0.0] * 3] * G}, G, fibre=Fibre(cores=THREE))
    no_reference = Fibre(wavelength={"calibration": calibration(3)})
    with pytest.raises(ValueError, match="no reference to subtract"):
        parse_reading({"wavelength": [[1530.0] * 3] * G}, G, fibre=no_reference)
    assert parse_reading({"wavelength_shift": [[0.0] * 3] * G}, G, fibre=no_reference).ok


def test_units_scale_every_quantity_and_the_bound_holds_in_si():
    u = [[1.5, -2.0]] * G
    cm = parse_reading({"curvature": [[x / 100 for x in p] for p in u]}, G, fibre=Fibre(curvature_unit="1/cm"))
    mm = parse_reading({"curvature_polar": [[2.5 / 1000, 0.5]] * G}, G, fibre=Fibre(curvature_unit="1/mm"))
    assert torch.allclose(cm.curvature, torch.tensor(u, dtype=F64), rtol=1e-12)
    assert torch.allclose(mm.curvature[0], torch.tensor([2.5 * math.cos(0.5), 2.5 * math.sin(0.5)], dtype=F64))
    micro = Fibre(cores=THREE, strain_unit="microstrain")
    strains = Fibre(cores=THREE).curvature_to_strain(1.0, -0.5, 2e-4)
    got = parse_reading({"strain": [[e * 1e6 for e in strains]] * G}, G, fibre=micro).curvature
    assert torch.allclose(got[0], torch.tensor([1.0, -0.5], dtype=F64), atol=1e-9)
    pm = Fibre(wavelength={"calibration": calibration(3)}, wavelength_unit="pm")
    nm = Fibre(wavelength={"calibration": calibration(3)})
    shifts = [[0.012, -0.03, 0.02]] * G
    assert torch.allclose(
        parse_reading({"wavelength_shift": [[x * 1000 for x in s] for s in shifts]}, G, fibre=pm).curvature,
        parse_reading({"wavelength_shift": shifts}, G, fibre=nm).curvature,
        rtol=1e-12,
    )
    with pytest.raises(ValueError, match=r"curvature\[0\]\[0\] = 20000.0 1/cm is beyond the bound of 10000 1/cm"):
        parse_reading({"curvature": [[2e4, 0.0]] * G}, G, fibre=Fibre(curvature_unit="1/cm"))
    with pytest.raises(ValueError, match="strains are read in microstrain"):
        parse_reading({"strain": [[2e5, 0.0, 0.0]] * G}, G, fibre=micro)


# ---------------------------------------------------------------------------------------------------- the CLI
LOADS = tr.PointForces(
    s=torch.tensor([[0.12, 0.24], [0.07, 0.2]], dtype=F64),
    f=torch.tensor([[[0.4, -0.9], [0.3, 0.2]], [[-1.2, 0.1], [0.0, 0.6]]], dtype=F64),
)


def _curvature() -> torch.Tensor:
    u = tr.simulate(ROD, LOADS).grating_curvature
    return u + 0.05 * torch.randn(u.shape, dtype=F64, generator=torch.Generator().manual_seed(7))


def _estimate(tmp_path: Path, capsys, rod: tr.Rod, lines: list[dict], *options: str) -> list[dict]:
    rod_file, path = tmp_path / "rod.json", tmp_path / "in.jsonl"
    rod.to_json(rod_file)
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert main(["estimate", str(rod_file), str(path), "--quiet", *options]) == 0, capsys.readouterr().err
    return [json.loads(line) for line in capsys.readouterr().out.splitlines()]


def _same_answers(got: list[dict], ref: list[dict], tol: float = 1e-6) -> None:
    assert [a["num_forces"] for a in ref] == [2, 2]
    for a, b in zip(got, ref, strict=True):
        assert a["id"] == b["id"] and a["num_forces"] == b["num_forces"] and a["status"] == b["status"]
        for fa, fb in zip(a["forces"], b["forces"], strict=True):
            for key in ("s", "fx", "fy"):
                assert fa[key] == pytest.approx(fb[key], rel=tol, abs=1e-9), key


@pytest.mark.parametrize("temperature", [False, True])
def test_round_trip_through_a_calibration(tmp_path, capsys, temperature):
    """Simulated curvature -> synthetic peak wavelengths through calibration matrices (their pseudo-inverse, plus
    a shift common to each grating's cores when ``temperature``) -> the estimate equals the curvature's."""
    u = _curvature()
    A = torch.tensor(calibration(4, seed=8), dtype=F64)
    centred = A - A.mean(-1, keepdim=True)  # A (I - 1 1^T / C), per nm
    d_nm = torch.einsum("gcj,bgj->bgc", torch.linalg.pinv(centred), u)
    if temperature:
        d_nm = d_nm + 0.3 * torch.rand(2, G, 1, dtype=F64, generator=torch.Generator().manual_seed(9))
    lam = torch.tensor(reference(4), dtype=F64) + d_nm
    rod = ROD.with_(fibre={"wavelength": {"reference": reference(4), "calibration": A.tolist()}})
    ref = _estimate(
        tmp_path, capsys, ROD, [{"id": b, "curvature": _pairs_of(u[b])} for b in range(2)], "--noise", "0.05"
    )
    got = _estimate(
        tmp_path, capsys, rod, [{"id": b, "wavelength": _pairs_of(lam[b])} for b in range(2)], "--noise", "0.05"
    )
    _same_answers(got, ref)
    shifts = [{"id": b, "wavelength_shift": _pairs_of(d_nm[b] * 1000)} for b in range(2)]  # in pm
    got = _estimate(tmp_path, capsys, rod, shifts, "--noise", "0.05", "--wavelength-unit", "pm")
    _same_answers(got, ref)


@pytest.mark.parametrize("temperature", [False, True])
def test_round_trip_through_the_physics(tmp_path, capsys, temperature):
    """Simulated curvature -> core strains eps_c = u_x y_c - u_y x_c (+ a temperature's common strain) -> peak
    wavelengths lambda_ref,c (1 + (1 - p_e) eps_c) -> the estimate equals the curvature's."""
    u = _curvature()
    x = torch.tensor([c[0] for c in THREE], dtype=F64)
    y = torch.tensor([c[1] for c in THREE], dtype=F64)
    eps = u[..., 0:1] * y - u[..., 1:2] * x  # (B, G, C)
    if temperature:
        eps = eps + 5e-4 * torch.rand(2, G, 1, dtype=F64, generator=torch.Generator().manual_seed(10))
    ref_nm = torch.tensor(reference(3), dtype=F64)
    lam = ref_nm * (1 + (1 - PE) * eps)
    rod = ROD.with_(fibre={"cores": THREE, "wavelength": {"reference": reference(3), "photoelastic": PE}})
    ref = _estimate(
        tmp_path, capsys, ROD, [{"id": b, "curvature": _pairs_of(u[b])} for b in range(2)], "--noise", "0.05"
    )
    got = _estimate(
        tmp_path, capsys, rod, [{"id": b, "wavelength": _pairs_of(lam[b])} for b in range(2)], "--noise", "0.05"
    )
    _same_answers(got, ref)


def test_wavelength_noise_weighs_the_fit_as_the_sigma_it_implies(tmp_path, capsys, physics_rod):
    u = _curvature()
    d_nm = physics_rod.fibre.bending_shift(u) / 1e-9
    lines = [{"id": b, "wavelength_shift": _pairs_of(d_nm[b])} for b in range(2)]
    sigma = max(physics_rod.fibre.wavelength_sigmas(2e-12))
    by_sigma = _estimate(tmp_path, capsys, physics_rod, lines, "--noise", repr(sigma))
    by_noise = _estimate(tmp_path, capsys, physics_rod, lines, "--wavelength-noise", "2")
    for a, b in zip(by_noise, by_sigma, strict=True):
        a.pop("time_ms"), b.pop("time_ms")
        assert a == b
    path = tmp_path / "in.jsonl"
    assert main(["estimate", "nitinol290", str(path), "--wavelength-noise", "1"]) == 2
    assert '"fibre": {"wavelength"' in capsys.readouterr().err
    rod_file = tmp_path / "rod.json"
    assert main(["estimate", str(rod_file), str(path), "--wavelength-noise", "1", "--noise", "0.1"]) == 2
    assert "not both" in capsys.readouterr().err


def test_a_file_in_1_per_cm_estimates_as_the_same_file_in_1_per_m(tmp_path, capsys):
    u = _curvature()
    si = [{"id": b, "curvature": _pairs_of(u[b])} for b in range(2)]
    cm = [{"id": b, "curvature": _pairs_of(u[b] / 100)} for b in range(2)]
    ref = _estimate(tmp_path, capsys, ROD, si, "--noise", "0.05")
    by_option = _estimate(tmp_path, capsys, ROD, cm, "--noise", "0.05", "--curvature-unit", "1/cm")
    by_rod_file = _estimate(tmp_path, capsys, ROD.with_(fibre={"curvature_unit": "1/cm"}), cm, "--noise", "0.05")
    _same_answers(by_option, ref, tol=1e-9)
    _same_answers(by_rod_file, ref, tol=1e-9)
    # the option overrides the rod file's key
    again = _estimate(
        tmp_path, capsys, ROD.with_(fibre={"curvature_unit": "1/cm"}), si, "--noise", "0.05", "--curvature-unit", "1/m"
    )
    _same_answers(again, ref, tol=1e-9)


def test_evaluate_through_wavelengths_keeps_the_curvature_and_implies_its_sigma(capsys):
    from torchrod.cli.commands.evaluate import evaluation_wavelength_fibre, through_wavelengths

    fibre = evaluation_wavelength_fibre(ROD)
    assert fibre.route == "physics"
    clean = torch.randn(4000, G, 2, dtype=F64, generator=torch.Generator().manual_seed(11))
    assert torch.allclose(through_wavelengths(clean, 0.0, fibre, seed=1), clean, rtol=0, atol=1e-8)
    noise = through_wavelengths(clean, 0.3, fibre, seed=2) - clean
    per_grating = noise.std(dim=(0, 2))
    assert float(per_grating.max()) == pytest.approx(0.3, rel=0.05)  # the largest grating's sigma is the row's
    assert (
        main(
            [
                "evaluate",
                "--input",
                "wavelength",
                "--count-per-cell",
                "3",
                "--rows",
                "zero",
                "--noise",
                "0.1",
                "--max-forces",
                "1",
                "--json",
            ]
        )
        == 0
    )
    row = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert row["readings"] == 3 and row["noise"] == 0.1
