"""Other sensors: multicore fibre strains and curvature magnitude + bend angle, turned into curvature at the edge
(torchrod.sensors, the reading parser, the CLI)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.io.readings import parse_csv_row, parse_reading
from torchrod.sensors import Fibre, polar_to_curvature

F64 = torch.float64
R = 3.5e-5
THREE = [[R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]
SKEWED = [[R, 0.0], [0.0, 2 * R], [-R, -0.5 * R], [0.2 * R, 0.1 * R]]


@pytest.fixture(scope="module")
def fibre_rod():
    return tr.presets.nitinol290().with_(fibre={"cores": THREE})


@pytest.fixture(scope="module")
def loads():
    return tr.PointForces(
        s=torch.tensor([[0.12, 0.24], [0.07, 0.2]], dtype=F64),
        f=torch.tensor([[[0.4, -0.9], [0.3, 0.2]], [[-1.2, 0.1], [0.0, 0.6]]], dtype=F64),
    )


@pytest.mark.parametrize("cores", [THREE, SKEWED])
def test_strain_round_trip_float_and_tensor(cores):
    fibre = Fibre(cores=cores)
    g = torch.Generator().manual_seed(0)
    u = 5.0 * torch.randn(50, 2, dtype=F64, generator=g)
    common = 1e-3 * torch.randn(50, dtype=F64, generator=g)
    strain = fibre.strain(u, common)
    assert strain.shape == (50, len(cores))
    # eps_c = ux y_c - uy x_c + eps_0, by hand for one core
    x, y = cores[1]
    assert torch.allclose(strain[:, 1], u[:, 0] * y - u[:, 1] * x + common, rtol=0, atol=1e-15)
    back = fibre.curvature(strain)
    assert torch.allclose(back, u, rtol=0, atol=1e-9)
    for k in range(5):  # the float path (the parser's) gives the same numbers
        pair = fibre.strain_to_curvature(strain[k].tolist())
        assert pair == pytest.approx(back[k].tolist(), rel=1e-12, abs=1e-12)
        assert fibre.curvature_to_strain(*u[k].tolist(), float(common[k])) == pytest.approx(
            strain[k].tolist(), abs=1e-15
        )


def test_curvature_sigma_matches_monte_carlo():
    g = torch.Generator().manual_seed(1)
    for cores in (THREE, SKEWED):
        fibre = Fibre(cores=cores)
        n = 40000
        noise = 1e-6 * torch.randn(n, fibre.num_cores, dtype=F64, generator=g)
        u = fibre.curvature(noise)  # curvature read from pure strain noise
        cov = u.T @ u / n
        largest = float(torch.linalg.eigvalsh(cov)[-1].sqrt())
        assert fibre.curvature_sigma(1e-6) == pytest.approx(largest, rel=0.03)
    # three cores at 120 degrees: isotropic, sigma_u = sigma_eps sqrt(2/3) / r
    assert Fibre(cores=THREE).curvature_sigma(1e-6) == pytest.approx(1e-6 * math.sqrt(2 / 3) / R, rel=1e-12)
    assert Fibre(cores=THREE).anisotropy == pytest.approx(1.0, abs=1e-9)
    assert Fibre(cores=SKEWED).anisotropy > 1.2


@pytest.mark.parametrize(
    ("cores", "message"),
    [
        ([[0.0, 0.0], [1e-5, 1e-5], [2e-5, 2e-5]], "on one line"),
        ([[0.0, 0.0], [1e-5, 0.0]], "at least 3 cores"),
        ([[0.0, 0.0], [1e-5, 0.0], [0.0, True]], r"fibre.cores\[2\]\[1\] must be a number"),
        ([[0.0, 0.0], [1e-5, 0.0], [0.0, "1e-5"]], r"fibre.cores\[2\]\[1\] must be a number"),
        ([[0.0, 0.0], [35.0, 0.0], [0.0, 35.0]], "in metres"),
        ([[0.0, 0.0], [1e-5, 0.0], [1e-5]], r"fibre.cores\[2\] must be a pair"),
        ("cores", "must be an array"),
    ],
)
def test_fibre_validation(cores, message):
    with pytest.raises(ValueError, match=message):
        Fibre(cores=cores)


def test_rod_file_with_fibre(tmp_path, fibre_rod):
    path = tmp_path / "rod.json"
    fibre_rod.to_json(path)
    again = tr.Rod.from_json(path)
    assert again == fibre_rod and again.fibre.num_cores == 3
    assert "fibre" not in tr.presets.nitinol290().to_dict()  # rods without one are written as before
    data = fibre_rod.to_dict()
    for bad, message in (
        ({"cores": THREE, "radius": 1}, "unknown fibre keys"),
        ({}, "fibre is empty"),
        ([THREE], "must be an object"),
    ):
        with pytest.raises(ValueError, match=message):
            tr.Rod.from_dict({**data, "fibre": bad})


def _representations(u: torch.Tensor, fibre: Fibre, common: torch.Tensor) -> dict[str, list]:
    """One reading's (G, 2) curvature as the three JSON forms (grating 2 missing in each)."""
    pairs = [None if k == 2 else row for k, row in enumerate(u.tolist())]
    strains = [
        None if k == 2 else fibre.curvature_to_strain(*row, float(common[k])) for k, row in enumerate(u.tolist())
    ]
    polar = [None if k == 2 else [math.hypot(*row), math.atan2(row[1], row[0])] for k, row in enumerate(u.tolist())]
    return {"curvature": pairs, "strain": strains, "curvature_polar": polar}


def test_parser_reads_strain_and_polar(fibre_rod, loads):
    u = tr.simulate(fibre_rod, loads).grating_curvature[0]
    common = 5e-4 * torch.randn(fibre_rod.num_gratings, dtype=F64, generator=torch.Generator().manual_seed(2))
    forms = _representations(u, fibre_rod.fibre, common)
    G = fibre_rod.num_gratings
    ref = parse_reading({"curvature": forms["curvature"]}, G).curvature
    for key in ("strain", "curvature_polar"):
        got = parse_reading({key: forms[key]}, G, fibre=fibre_rod.fibre).curvature
        assert torch.isnan(got[2]).all()
        assert torch.allclose(torch.nan_to_num(got), torch.nan_to_num(ref), rtol=0, atol=1e-9)
    # CSV rows carry the same, per --csv-quantity
    for quantity, key, per in (("strain", "strain", 3), ("polar", "curvature_polar", 2)):
        cells = ["r", "0.5"]
        for entry in forms[key]:
            cells += [""] * per if entry is None else [repr(x) for x in entry]
        got = parse_csv_row(cells, G, quantity=quantity, fibre=fibre_rod.fibre).curvature
        assert torch.allclose(torch.nan_to_num(got), torch.nan_to_num(ref), rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("obj", "fibre", "message"),
    [
        ({"strain": [[0.0, 0.0, 0.0]] * 14}, False, "needs the rod's multicore fibre"),
        ({"strain": [[0.0, 0.0]] * 14}, True, r"strain\[0\] must be a list of 3 core strains"),
        ({"strain": [[500.0, 0.0, 0.0]] * 14}, True, "one microstrain"),
        ({"strain": [[0.0, True, 0.0]] * 14}, True, r"strain\[0\]\[1\] must be a number"),
        ({"strain": [None] * 14}, True, "all gratings are missing"),
        ({"strain": [[0.0] * 3] * 13}, True, "holds 13 gratings"),
        ({"curvature_polar": [[-1.0, 0.0]] * 14}, True, r"curvature_polar\[0\]\[0\] is a curvature magnitude"),
        ({"curvature_polar": [[1.0, float("nan")]] * 14}, True, "must be finite"),
        ({"curvature_polar": [[1.0]] * 14}, True, r"must be a pair \[kappa, phi\]"),
        ({"curvature_polar": [[0.0, 0.0]] * 14, "curvature": [[0.0, 0.0]] * 14}, True, "give exactly one"),
        ({"id": 3}, True, "missing 'curvature'"),
    ],
)
def test_parser_errors(obj, fibre, message, fibre_rod):
    with pytest.raises(ValueError, match=message):
        parse_reading(obj, 14, fibre=fibre_rod.fibre if fibre else None)


def test_polar_to_curvature_floats_and_tensors():
    assert polar_to_curvature(2.0, math.pi / 2) == pytest.approx((0.0, 2.0), abs=1e-15)
    k, phi = torch.tensor([1.0, 3.0], dtype=F64), torch.tensor([0.0, math.pi], dtype=F64)
    assert torch.allclose(polar_to_curvature(k, phi), torch.tensor([[1.0, 0.0], [-3.0, 0.0]], dtype=F64), atol=1e-15)


def test_estimate_is_the_same_from_every_sensor(tmp_path: Path, capsys, fibre_rod, loads):
    """Strain and polar readings, in JSON lines and CSV, give the estimate of the curvature they encode."""
    rod_file = tmp_path / "rod.json"
    fibre_rod.to_json(rod_file)
    u = tr.simulate(fibre_rod, loads).grating_curvature
    u = u + 0.05 * torch.randn(u.shape, dtype=F64, generator=torch.Generator().manual_seed(3))
    common = 5e-4 * torch.randn(2, fibre_rod.num_gratings, dtype=F64, generator=torch.Generator().manual_seed(4))
    files = {}
    for key in ("curvature", "strain", "curvature_polar"):
        lines = [json.dumps({"id": b, key: _representations(u[b], fibre_rod.fibre, common[b])[key]}) for b in range(2)]
        files[key] = tmp_path / f"{key}.jsonl"
        files[key].write_text("\n".join(lines) + "\n")
    csv = []
    for b in range(2):
        cells = [str(b), ""]
        for entry in _representations(u[b], fibre_rod.fibre, common[b])["strain"]:
            cells += [""] * 3 if entry is None else [repr(x) for x in entry]
        csv.append(",".join(cells))
    files["csv"] = tmp_path / "strain.csv"
    files["csv"].write_text("\n".join(csv) + "\n")
    sigma_eps = 0.05 / fibre_rod.fibre.curvature_sigma(1.0)  # the strain noise that implies 0.05 1/m
    answers = {}
    for name, path in files.items():
        extra = ["--format", "csv", "--csv-quantity", "strain"] if name == "csv" else []
        noise = ["--strain-noise", repr(sigma_eps)] if name in ("strain", "csv") else ["--noise", "0.05"]
        assert main(["estimate", "--rod", str(rod_file), str(path), "--quiet", *noise, *extra]) == 0
        answers[name] = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    ref = answers["curvature"]
    assert [a["num_forces"] for a in ref] == [2, 2]
    for name, got in answers.items():
        for a, b in zip(got, ref, strict=True):
            assert a["num_forces"] == b["num_forces"] and a["status"] == b["status"], name
            for fa, fb in zip(a["forces"], b["forces"], strict=True):
                for key in ("s", "fx", "fy"):
                    assert fa[key] == pytest.approx(fb[key], rel=1e-6, abs=1e-9), (name, key)


def test_strain_noise_option_errors(tmp_path: Path, capsys, fibre_rod):
    path = tmp_path / "r.jsonl"
    path.write_text(json.dumps({"curvature": [[0.0, 0.0]] * 14}) + "\n")
    assert main(["estimate", "--rod", "nitinol290", str(path), "--strain-noise", "1e-6"]) == 2
    assert "multicore fibre" in capsys.readouterr().err
    rod_file = tmp_path / "rod.json"
    fibre_rod.to_json(rod_file)
    assert main(["estimate", "--rod", str(rod_file), str(path), "--strain-noise", "1e-6", "--noise", "0.1"]) == 2
    assert "not both" in capsys.readouterr().err


def test_evaluate_through_fibre_keeps_the_curvature_and_implies_its_sigma():
    """``torchrod evaluate --input strain``: the common strain leaves no trace, and the strain noise implies the
    row's curvature sigma."""
    from torchrod.cli.commands.evaluate import EVALUATION_FIBRE, through_fibre

    fibre = Fibre(cores=EVALUATION_FIBRE)
    clean = torch.randn(4000, 14, 2, dtype=F64, generator=torch.Generator().manual_seed(5))
    assert torch.allclose(through_fibre(clean, 0.0, fibre, seed=1), clean, rtol=0, atol=1e-9)
    noise = through_fibre(clean, 0.3, fibre, seed=2) - clean
    assert float(noise.std()) == pytest.approx(0.3, rel=0.02)
    assert abs(float(noise.mean())) < 0.01
