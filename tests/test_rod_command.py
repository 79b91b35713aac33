"""``torchrod rod`` and :func:`torchrod.eval.rod_report.describe_rod`: a rod file written from its numbers,
checked, and the report's numbers (EI, how many forces, the warm-start network, a tip load's curvature)."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

import torchrod as tr
from torchrod.cli import main
from torchrod.cli.commands.rod import NOT_OPTIONS, NUMBER_OPTIONS
from torchrod.errors import RodError
from torchrod.eval.rod_report import describe_rod, grating_layout
from torchrod.rod import MIN_TEST_DOF, Rod, max_testable_forces

TUBE = {"length": 0.6, "outer_diameter": 0.0012, "inner_diameter": 0.0009, "youngs_modulus": 193e9}
GRATINGS = [0.05, 0.15, 0.25, 0.35, 0.45, 0.55]


def _argv(numbers: dict, gratings=GRATINGS) -> list[str]:
    argv = ["rod"]
    for key, value in numbers.items():
        argv += ["--" + key.replace("_", "-"), repr(value)]
    return [*argv, "--gratings", ",".join(map(repr, gratings))]


def test_the_written_file_loads_as_the_rod_built_from_the_same_numbers(tmp_path, capsys):
    out = tmp_path / "my_rod.json"
    assert main([*_argv(TUBE), "--out", str(out)]) == 0
    assert Rod.from_json(out) == Rod.from_geometry(**TUBE, gratings=GRATINGS)
    captured = capsys.readouterr()
    assert f"wrote {out}" in captured.err
    assert "EI" in captured.out

    stiff = {"length": 0.3, "bending_stiffness": 0.02, "location_bias": -0.002}
    out2 = tmp_path / "ei.json"
    assert main([*_argv(stiff, [0.01, 0.1, 0.2]), "--out", str(out2)]) == 0
    assert Rod.from_json(out2) == Rod(**stiff, gratings=(0.01, 0.1, 0.2))


def test_out_dash_writes_the_rod_on_stdout_and_the_report_on_stderr(capsys):
    assert main([*_argv(TUBE), "--out", "-"]) == 0
    captured = capsys.readouterr()
    assert Rod.from_dict(json.loads(captured.out)) == Rod.from_geometry(**TUBE, gratings=GRATINGS)
    assert "EI" in captured.err


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"length": 400.0}, "length = 400 m"),  # millimetres
        ({"youngs_modulus": 193.0}, "youngs_modulus = 193 Pa"),  # GPa
        ({"outer_diameter": 1.2, "inner_diameter": 0.9}, "outer_diameter = 1.2 m"),  # millimetres
        ({"inner_diameter": 0.0015}, "inner_diameter (0.0015 m)"),  # wider than the outer diameter
        ({"length": -0.6}, "length must be positive"),
        ({"length": float("nan")}, "length must be finite"),
    ],
)
def test_nonsense_numbers_are_refused_with_the_librarys_error_naming_the_value(tmp_path, capsys, change, named):
    numbers = {**TUBE, **change}
    with pytest.raises(ValueError) as library:
        Rod.from_dict({**numbers, "gratings": GRATINGS})
    assert named in str(library.value)
    out = tmp_path / "bad.json"
    assert main([*_argv(numbers), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"torchrod rod: error: {library.value}" in err
    assert not out.exists()


def test_gratings_outside_the_rod_and_bad_entries_are_refused(capsys):
    assert main(_argv(TUBE, [0.05, 0.7])) == 2
    err = capsys.readouterr().err
    with pytest.raises(RodError) as library:
        Rod.from_geometry(**TUBE, gratings=[0.05, 0.7])
    assert f"error: {library.value}" in err and "gratings[1] = 0.7 m" in err
    with pytest.raises(SystemExit):
        main(["rod", "--length", "0.6", "--bending-stiffness", "0.01", "--gratings", "0.1,ten"])
    assert "entry 2, 'ten', is not a number" in capsys.readouterr().err


def test_it_asks_for_what_is_missing_and_refuses_a_file_with_numbers(capsys):
    assert main(["rod", "--length", "0.6", "--bending-stiffness", "0.01"]) == 2
    assert "give --gratings" in capsys.readouterr().err
    assert main(["rod", "--length", "0.6", "--gratings", "0.1"]) == 2
    assert "--bending-stiffness" in capsys.readouterr().err
    assert main(["rod", "nitinol290", "--length", "0.6"]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["rod"]) == 2
    assert "ROD" in capsys.readouterr().err


def test_a_preset_is_written_as_its_rod_file_but_never_over_its_input(tmp_path, capsys):
    out = tmp_path / "copy.json"
    assert main(["rod", "nitinol290", "--out", str(out)]) == 0
    assert Rod.from_json(out) == tr.presets.nitinol290()
    before = out.read_text()
    assert main(["rod", str(out), "--out", str(out)]) == 2
    assert "would erase the input" in capsys.readouterr().err and out.read_text() == before


def test_an_option_for_every_number_of_a_rod_file():
    keys = {f.name for f in dataclasses.fields(Rod)}
    assert keys == {*NUMBER_OPTIONS, "gratings", *NOT_OPTIONS}


def test_checking_a_file_prints_ei_the_layout_and_the_network(tmp_path, capsys):
    path = tmp_path / "rod.json"
    tr.presets.nitinol290().to_json(path)
    assert main(["rod", str(path)]) == 0
    out = capsys.readouterr().out
    assert "0.00738831 N m^2" in out
    layout = next(line for line in out.splitlines() if line.startswith("clamp ||"))
    assert layout.count("o") == 14
    assert "up to 8" in out and "nitinol290.pt" in out
    flat = " ".join(out.split())
    assert "1 N at the tip" in flat and "times a noise of 0.1 1/m" in flat


def test_the_report_ei_is_the_tube_formula():
    report = describe_rod(Rod.from_geometry(**TUBE, gratings=GRATINGS))
    d_out, d_in, e = TUBE["outer_diameter"], TUBE["inner_diameter"], TUBE["youngs_modulus"]
    assert report.bending_stiffness == pytest.approx(e * math.pi * (d_out**4 - d_in**4) / 64, rel=1e-12)
    assert report.stiffness_from == "geometry"
    assert report.values_per_reading == 12 and report.max_forces == 3
    assert not report.network_fits and "no shipped" in report.network_reason


def test_the_tip_load_curvature_is_d_over_ei_for_a_stiff_rod():
    # A steel tube 10 mm across: 1 N bends it little, so the curvature at a grating d from the tip is d / EI.
    rod = Rod.from_geometry(0.5, 0.01, 0.008, 193e9, gratings=[0.05, 0.25, 0.45])
    report = describe_rod(rod)
    d = rod.length - 0.05
    assert report.base_grating == 0.05
    assert report.tip_curvature_linear == pytest.approx(d / rod.bending_stiffness, rel=1e-12)
    assert report.tip_curvature == pytest.approx(d / rod.bending_stiffness, rel=1e-3)
    assert report.tip_curvature_accurate
    assert report.smallest_tip_force == pytest.approx(0.1 * rod.bending_stiffness / d)
    assert report.tip_signal_to_noise == pytest.approx(report.tip_curvature / 0.1)


def test_the_shipped_network_fits_the_paper_layout_at_any_length():
    report = describe_rod(Rod(length=0.58, bending_stiffness=0.05, gratings=[0.02 + 0.04 * k for k in range(14)]))
    assert report.network_fits and "nitinol290.pt" in report.network_reason
    assert report.max_forces == 8


@pytest.mark.parametrize(("gratings", "forces"), [(1, 0), (2, 0), (3, 1), (4, 1), (5, 2), (6, 3), (14, 8), (40, 25)])
def test_testable_forces_leave_a_few_degrees_of_freedom(gratings, forces):
    assert max_testable_forces(gratings) == forces
    if forces:
        assert 2 * gratings - 3 * forces >= MIN_TEST_DOF
    assert 2 * gratings - 3 * (forces + 1) < MIN_TEST_DOF


def test_the_layout_marks_each_grating_and_shares_a_crowded_column():
    rod = Rod(length=0.4, bending_stiffness=0.01, gratings=[0.1, 0.2, 0.2001, 0.3])
    top, scale = grating_layout(rod, width=40).splitlines()
    assert top.startswith("clamp ||") and top.endswith("| tip")
    assert top.count("o") == 2 and "2" in top
    assert scale.rstrip().endswith("400 mm") and len(scale) == len(top) - len("| tip")
