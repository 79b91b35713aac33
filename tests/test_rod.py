"""The Rod description: validation at the edge, JSON round trips, and the paper's stiffness."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch

import torchrod as tr
import torchrod.cli
import torchrod.errors
from torchrod.data import path as shipped_file
from torchrod.errors import MissingFileError
from torchrod.rod import Rod

DATA = shipped_file("nitinol290.json").parent

GEOMETRY = {"length": 0.29, "outer_diameter": 1.397e-3, "inner_diameter": 1.118e-3, "youngs_modulus": 67e9}
GRATINGS = [0.01, 0.03, 0.05]


def test_nitinol290_bending_stiffness_matches_the_paper():
    # EI = E pi (d_out^4 - d_in^4) / 64 with the paper's tube: about 7.39e-3 N m^2 (docs/physics.md).
    rod = tr.presets.nitinol290()
    by_hand = 67e9 * math.pi * ((1.397e-3) ** 4 - (1.118e-3) ** 4) / 64.0
    assert rod.bending_stiffness == pytest.approx(by_hand, rel=1e-12)
    assert rod.bending_stiffness == pytest.approx(7.39e-3, rel=1e-3)
    assert rod.length == 0.29
    assert rod.num_gratings == 14
    assert rod.gratings == pytest.approx([0.01 + 0.02 * k for k in range(14)], abs=1e-15)
    assert tr.presets.nitinol290(calibrated=True).location_bias == pytest.approx(-3.12e-3)


def test_shipped_rod_file_is_the_preset():
    assert Rod.from_json(DATA / "nitinol290.json") == tr.presets.nitinol290()
    assert Rod.from_json(DATA / "ctr250.json") == tr.presets.ctr250()


def test_round_trip_geometry_form(tmp_path):
    rod = Rod.from_geometry(gratings=GRATINGS, location_bias=-1e-3, poisson_ratio=0.33, **GEOMETRY)
    data = rod.to_dict()
    assert "bending_stiffness" not in data  # geometry is the source of truth when known
    assert {"outer_diameter", "inner_diameter", "youngs_modulus"} <= set(data)
    assert Rod.from_dict(json.loads(json.dumps(data))) == rod
    path = tmp_path / "rod.json"
    rod.to_json(path)
    back = Rod.from_json(path)
    assert back == rod
    assert back.bending_stiffness == rod.bending_stiffness


def test_round_trip_bending_stiffness_form(tmp_path):
    rod = Rod(length=0.5, bending_stiffness=2.5e-2, gratings=(0.1, 0.2, 0.45), location_bias=2e-3)
    data = rod.to_dict()
    assert data["bending_stiffness"] == 2.5e-2
    assert not {"outer_diameter", "inner_diameter", "youngs_modulus"} & set(data)
    path = tmp_path / "rod.json"
    rod.to_json(path)
    assert Rod.from_json(path) == rod


def test_changing_stiffness_drops_the_geometry_that_no_longer_produces_it(tmp_path):
    rod = tr.presets.nitinol290().with_(bending_stiffness=1e-2)
    assert rod.outer_diameter is None and rod.bending_stiffness == 1e-2
    rod.to_json(tmp_path / "rod.json")
    assert Rod.from_json(tmp_path / "rod.json").bending_stiffness == 1e-2


def test_grating_positions_tensor_follows_the_requested_dtype():
    rod = tr.presets.nitinol290()
    g = rod.grating_positions(torch.float32)
    assert g.dtype == torch.float32 and g.shape == (14,)
    assert g.tolist() == pytest.approx(rod.gratings, abs=1e-7)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"length": -0.29}, "length"),
        ({"length": 0.0}, "length"),
        ({"length": float("nan")}, "length"),
        ({"bending_stiffness": -1e-3}, "bending_stiffness"),
        ({"bending_stiffness": 0.0}, "bending_stiffness"),
        ({"bending_stiffness": "stiff"}, "bending_stiffness"),
        ({"gratings": ()}, "at least one"),
        ({"gratings": (0.03, 0.01)}, "increasing"),
        ({"gratings": (0.01, 0.01)}, "increasing"),
        ({"gratings": (-0.01, 0.1)}, "inside"),
        ({"gratings": (0.1, 0.3)}, "inside"),
        ({"gratings": (0.1, float("inf"))}, "finite"),
        ({"location_bias": 0.5}, "location_bias"),
        ({"poisson_ratio": 0.7}, "poisson_ratio"),
    ],
)
def test_constructor_rejects_bad_values(kwargs, match):
    base = {"length": 0.29, "bending_stiffness": 7e-3, "gratings": (0.01, 0.27)}
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Rod(**base)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"outer_diameter": -1e-3}, "outer_diameter"),
        ({"inner_diameter": -1e-4}, "inner_diameter"),
        ({"inner_diameter": 1.397e-3}, "inner_diameter"),  # inner == outer: no wall
        ({"inner_diameter": 2e-3}, "inner_diameter"),  # inner > outer
        ({"youngs_modulus": -67e9}, "youngs_modulus"),
        ({"length": -0.29}, "length"),
    ],
)
def test_geometry_rejects_bad_sizes(changes, match):
    kwargs = dict(GEOMETRY, gratings=GRATINGS)
    kwargs.update(changes)
    with pytest.raises(ValueError, match=match):
        Rod.from_geometry(**kwargs)
    with pytest.raises(ValueError, match=match):
        Rod.from_dict(kwargs)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (dict(GEOMETRY, gratings=GRATINGS, colour="blue"), "unknown rod keys.*colour"),
        (dict(GEOMETRY, gratings=GRATINGS, Length=0.3), "unknown rod keys.*Length"),
        ({k: v for k, v in GEOMETRY.items() if k != "length"} | {"gratings": GRATINGS}, "missing 'length'"),
        (dict(GEOMETRY), "missing 'gratings'"),
        ({"length": 0.29, "gratings": GRATINGS}, "bending_stiffness"),
        (
            {"length": 0.29, "outer_diameter": 1e-3, "youngs_modulus": 1e9, "gratings": GRATINGS},
            "go together",
        ),
        ({"length": 0.29, "bending_stiffness": 7e-3, "gratings": 0.01}, "gratings"),
        ({"length": 0.29, "bending_stiffness": 7e-3, "gratings": "0.01"}, "gratings"),
        ({"length": 0.29, "bending_stiffness": 7e-3, "gratings": [0.2, 0.1]}, "increasing"),
        ([0.29, 7e-3], "JSON object"),
    ],
)
def test_from_dict_rejects_bad_descriptions(data, match):
    with pytest.raises(ValueError, match=match):
        Rod.from_dict(data)


def test_from_json_rejects_a_file_that_is_not_json(tmp_path):
    path = tmp_path / "rod.json"
    path.write_text("{length: 0.29", encoding="utf-8")
    with pytest.raises(ValueError, match="not valid JSON"):
        Rod.from_json(path)


def test_rod_is_frozen():
    rod = tr.presets.nitinol290()
    with pytest.raises(AttributeError):
        rod.length = 1.0  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------- damaged rod files
# Every bad rod file is ONE ValueError line naming the file, the key and (at most ~100 characters of) the value;
# through the CLI it is `torchrod CMD: error: ...` with exit status 2 and no traceback.
PRESET = tr.presets.nitinol290()
GOOD = PRESET.to_dict()


def _with(**changes) -> str:
    return json.dumps(dict(GOOD, **changes))


BAD_ROD_FILES = {
    "null inner_diameter": (_with(inner_diameter=None), r"inner_diameter must be a number \[m\], got null"),
    "list inner_diameter": (
        _with(inner_diameter=[1e-3]),
        r"inner_diameter must be a number \[m\], got \[0.001\]",
    ),
    "bool length": (_with(length=True), "length must be a number .*got true"),
    "string length": (_with(length="0.29"), 'length must be a number .*got "0.29"'),
    "400-digit number": (_with(youngs_modulus=int("6" * 400)), r"youngs_modulus is too large .*400 digits"),
    "1e400": (_with(length="@").replace('"@"', "1e400"), "length must be finite"),
    "null grating": (_with(gratings=[0.01, None, 0.05]), r"gratings\[1\] must be a number .*got null"),
    "grating beyond the tip": (_with(gratings=[0.01, 0.3]), r"gratings\[1\] = 0.3 m must lie inside the rod"),
    "contradictory stiffness and geometry": (
        _with(bending_stiffness=7.5e-3),
        r"bending_stiffness 0.0075 N m\^2 contradicts the geometry",
    ),
    "repeated key": ('{"length": 0.29, "length": 0.3}', "'length' appears twice"),
    "invalid JSON": ('{"length": 0.29,', "not valid JSON"),
    "empty file": ("", "not valid JSON"),
    "not UTF-8": (b"\xff\xfe\x00garbage", "not UTF-8"),
    "not an object": ("[0.29]", "must be a JSON object"),
}


def _write_rod(tmp_path: Path, content: str | bytes) -> Path:
    path = tmp_path / "rod.json"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    return path


def _one_clear_line(message: str) -> None:
    assert "\n" not in message and len(message) < 400, message


@pytest.mark.parametrize("case", sorted(BAD_ROD_FILES))
def test_a_bad_rod_file_is_one_clear_value_error_naming_the_file_and_key(case, tmp_path):
    content, match = BAD_ROD_FILES[case]
    path = _write_rod(tmp_path, content)
    for read in (Rod.from_json, tr.presets.load):
        with pytest.raises(ValueError, match=match) as info:
            read(str(path))
        assert str(info.value).startswith(f"{path}: ")
        _one_clear_line(str(info.value))


def test_a_directory_or_an_unreadable_path_is_a_value_error(tmp_path):
    with pytest.raises(ValueError, match="is a directory, not a rod file"):
        tr.presets.load(str(tmp_path))
    link = tmp_path / "dangling.json"
    link.symlink_to(tmp_path / "nowhere.json")
    with pytest.raises(ValueError, match="cannot read the rod file"):
        tr.presets.load(str(link))
    # A path that does not exist is a missing file (a FileNotFoundError), naming the presets too.
    with pytest.raises(MissingFileError, match="no such rod file.*nitinol290, ctr250"):
        tr.presets.load(str(tmp_path / "missing.json"))
    with pytest.raises(ValueError, match="neither a rod file nor a preset"):
        tr.presets.load("missing")


def test_huge_values_are_quoted_briefly():
    with pytest.raises(ValueError, match="too large") as info:
        Rod(length=10**400, bending_stiffness=7e-3, gratings=(0.01,))
    _one_clear_line(str(info.value))
    assert "(an integer of 401 digits)" in str(info.value)
    with pytest.raises(ValueError, match="more than 4300 digits|digits"):
        Rod(length=10**5000, bending_stiffness=7e-3, gratings=(0.01,))
    with pytest.raises(ValueError, match=r"\.\.\.") as info:
        Rod(length=0.29, bending_stiffness="x" * 1000, gratings=(0.01,))
    assert len(str(info.value)) < 200


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"length": True}, "length must be a number"),
        ({"length": "0.29"}, "length must be a number"),
        ({"length": None}, "length must be a number"),
        ({"bending_stiffness": [7e-3]}, "bending_stiffness must be a number"),
        ({"location_bias": False}, "location_bias must be a number"),
        ({"location_bias": None}, "location_bias must be a number"),
        ({"poisson_ratio": "0.3"}, "poisson_ratio must be a number"),
        ({"poisson_ratio": float("nan")}, "poisson_ratio must be finite"),
        ({"gratings": (0.01, True)}, r"gratings\[1\] must be a number"),
        ({"gratings": {"a": 0.01}}, "gratings must be a list"),
        ({"gratings": {0.01, 0.02}}, "gratings must be a list"),
        ({"outer_diameter": 1e-3}, "go together"),
    ],
)
def test_a_bool_a_string_or_null_is_not_a_number(kwargs, match):
    base = {"length": 0.29, "bending_stiffness": 7e-3, "gratings": (0.01, 0.27)}
    with pytest.raises(ValueError, match=match):
        Rod(**dict(base, **kwargs))


def test_numbers_of_numeric_types_are_accepted():
    import numpy as np

    rod = Rod(length=np.float32(0.25), bending_stiffness=torch.tensor(7e-3), gratings=np.array([0.01, 0.2]))
    assert rod.length == pytest.approx(0.25) and rod.gratings == (0.01, 0.2) and type(rod.length) is float
    assert Rod(length=1, bending_stiffness=1, gratings=[0, 1]).gratings == (0.0, 1.0)  # ints are numbers


def test_stiffness_and_geometry_that_agree_are_accepted_and_the_geometry_kept(tmp_path):
    both = dict(GOOD, bending_stiffness=PRESET.bending_stiffness * (1 + 1e-11))
    path = _write_rod(tmp_path, json.dumps(both))
    rod = Rod.from_json(path)
    assert rod == PRESET and rod.bending_stiffness == PRESET.bending_stiffness
    with pytest.raises(ValueError, match="contradicts the geometry"):
        Rod.from_dict(dict(GOOD, bending_stiffness=PRESET.bending_stiffness * (1 + 1e-8)))


def test_changing_the_geometry_recomputes_the_stiffness():
    stiffer = PRESET.with_(youngs_modulus=2 * PRESET.youngs_modulus)
    assert stiffer.bending_stiffness == pytest.approx(2 * PRESET.bending_stiffness, rel=1e-12)
    solid = PRESET.with_(inner_diameter=0.0)
    assert solid.bending_stiffness == pytest.approx(67e9 * math.pi * 1.397e-3**4 / 64, rel=1e-12)
    with pytest.raises(ValueError, match="contradicts"):
        PRESET.with_(youngs_modulus=1e9, bending_stiffness=1.0)


def test_differences_name_what_a_reading_depends_on():
    assert PRESET.differences(tr.presets.nitinol290(calibrated=True)) == []  # the bias does not count
    other = PRESET.with_(length=0.3, bending_stiffness=1e-2)
    diff = PRESET.differences(other)
    assert len(diff) == 2 and diff[0] == "length 0.29 m vs 0.3 m" and "bending_stiffness" in diff[1]
    assert "gratings" in PRESET.differences(PRESET.with_(gratings=PRESET.gratings[:-1]))[0]


@pytest.mark.parametrize("case", ["null inner_diameter", "400-digit number", "contradictory stiffness and geometry"])
def test_the_cli_reports_a_bad_rod_file_with_status_2_and_no_traceback(case, tmp_path, capsys):
    from torchrod.cli import main

    path = _write_rod(tmp_path, BAD_ROD_FILES[case][0])
    readings = tmp_path / "r.jsonl"
    readings.write_text(json.dumps({"curvature": [[0.0, 0.0]] * 14}) + "\n")
    assert main(["estimate", "--rod", str(path), str(readings)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"torchrod estimate: error: {path}: ") and err.count("\n") == 1, err
    assert main(["estimate", "--rod", str(tmp_path), str(readings)]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_a_directory_as_rod_through_the_command_line_prints_no_traceback(tmp_path):
    import subprocess
    import sys

    readings = tmp_path / "r.jsonl"
    readings.write_text(json.dumps({"curvature": [[0.0, 0.0]] * 14}) + "\n")
    done = subprocess.run(
        [sys.executable, "-m", "torchrod", "plot", str(readings), str(readings), "--rod", str(tmp_path)],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr == f"torchrod plot: error: {tmp_path}: is a directory, not a rod file\n"


# ---------------------------------------------------------------------------------------------------- units sanity
def test_a_rod_in_millimetres_and_gigapascals_is_refused_with_the_conversion(tmp_path, capsys):
    """The paper's tube written in mm and GPa: every implausible value is named with its value in SI units."""
    path = tmp_path / "rod.json"
    path.write_text(
        json.dumps(
            {
                "length": 290,
                "outer_diameter": 1.397,
                "inner_diameter": 1.118,
                "youngs_modulus": 67,
                "gratings": [10 + 20 * k for k in range(14)],
            }
        )
    )
    with pytest.raises(tr.errors.RodError) as info:
        Rod.from_json(path)
    text = str(info.value)
    assert "SI units" in text
    for part in ("length = 290 m", "give 0.29 m", "outer_diameter = 1.397 m", "give 0.001397 m"):
        assert part in text
    assert "youngs_modulus = 67 Pa" in text and "in GPa, give 6.7e+10 Pa" in text
    forces = tmp_path / "f.jsonl"
    forces.write_text('{"forces": []}\n')
    assert tr.cli.main(["simulate", "--rod", str(path), str(forces)]) == 2  # (it used to answer all-zero curvature)
    assert "give 0.29 m" in capsys.readouterr().err


@pytest.mark.parametrize(
    "change, message",
    [
        ({"length": 25.0}, "length = 25 m lies outside the plausible 1 mm to 20 m"),
        ({"length": 5e-4, "gratings": [1e-4]}, "length = 0.0005 m lies outside"),
        ({"youngs_modulus": 5e5}, "youngs_modulus = 500000 Pa lies outside"),
        ({"youngs_modulus": 2000}, "in MPa, give 2e+09 Pa"),
        ({"youngs_modulus": 2e12}, "youngs_modulus = 2e+12 Pa"),
        ({"outer_diameter": 0.2, "inner_diameter": 0.0}, "outer_diameter = 0.2 m is larger than 0.1 m"),
        ({"gratings": [0.01, 270.0]}, "gratings[1] = 270 m must lie inside the rod, [0, 0.29] m"),
        ({"gratings": [-0.01, 0.1]}, "gratings[0] = -0.01 m must lie inside"),
    ],
)
def test_each_implausible_value_is_an_error_naming_it(change, message):
    with pytest.raises(tr.errors.RodError) as info:
        Rod.from_dict({**GEOMETRY, "gratings": GRATINGS, **change})
    assert message in str(info.value)


def test_the_bounds_themselves_are_plausible():
    """Each plausibility bound is inclusive and lies where the constants say: a rod exactly at a bound is built and
    holds the values given; one a hair beyond it is refused, naming the value."""
    from torchrod.rod import LENGTH_RANGE, MAX_DIAMETER, YOUNGS_MODULUS_RANGE

    assert LENGTH_RANGE == (1e-3, 20.0) and YOUNGS_MODULUS_RANGE == (1e6, 1.2e12) and MAX_DIAMETER == 0.1
    hair = 1e-9
    for length in LENGTH_RANGE:
        rod = Rod(length=length, bending_stiffness=1.0, gratings=(0.0, 0.5 * length))
        assert (rod.length, rod.gratings) == (length, (0.0, 0.5 * length))
    for length in (1e-3 * (1 - hair), 20.0 * (1 + hair)):
        with pytest.raises(tr.errors.RodError, match=r"length = .* m lies outside the plausible 1 mm to 20 m"):
            Rod(length=length, bending_stiffness=1.0, gratings=(0.0, 0.5 * length))
    for outer, youngs in ((0.1, 1e6), (1e-3, 1.2e12)):
        rod = Rod.from_geometry(
            length=0.29, outer_diameter=outer, inner_diameter=0.0, youngs_modulus=youngs, gratings=GRATINGS
        )
        assert (rod.outer_diameter, rod.youngs_modulus) == (outer, youngs)
        assert rod.bending_stiffness == pytest.approx(youngs * math.pi * outer**4 / 64, rel=1e-12)  # a solid rod
    for outer, youngs, message in (
        (0.1 * (1 + hair), 1e6, "outer_diameter = 0.1 m is larger than 0.1 m"),
        (1e-3, 1e6 * (1 - hair), "youngs_modulus = 1e+06 Pa lies outside the plausible"),
        (1e-3, 1.2e12 * (1 + hair), "youngs_modulus = 1.2e+12 Pa lies outside the plausible"),
    ):
        with pytest.raises(tr.errors.RodError, match=re.escape(message)):
            Rod.from_geometry(
                length=0.29, outer_diameter=outer, inner_diameter=0.0, youngs_modulus=youngs, gratings=GRATINGS
            )


# ---------------------------------------------------------------------------------------------------- limitations
def test_a_rod_whose_only_grating_is_at_the_tip_is_refused():
    """No force can bend the rod distal to the tip, so no reading would ever see one (every loaded reading used to be
    answered 'ok, 0 forces')."""
    with pytest.raises(tr.errors.RodError, match="no grating lies proximal to the tip"):
        Rod(length=0.29, bending_stiffness=7e-3, gratings=(0.29,))
    with pytest.raises(tr.errors.RodError, match="no grating lies proximal"):
        Rod(length=0.29, bending_stiffness=7e-3, gratings=(0.29 - 1e-9,))


@pytest.mark.parametrize(
    "gratings, message",
    [
        ((0.1, 0.1 + 1e-12, 0.2), r"gratings\[0\] and gratings\[1\] lie 1e-12 m apart"),
        ((0.05,), "a single grating"),
        ((0.2, 0.25, 0.27), "the first grating lies at 0.2 m, 69 % of the length"),
    ],
)
def test_a_rod_that_cannot_determine_everything_is_warned_at_load(gratings, message):
    data = {"length": 0.29, "bending_stiffness": 7e-3, "gratings": list(gratings)}
    with pytest.warns(tr.errors.RodWarning, match=message):
        rod = Rod.from_dict(data)
    assert any(re.search(message, text) for text in rod.limitations)


def test_a_sound_rod_has_no_limitations_and_gives_no_warning():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tr.presets.nitinol290().limitations == () and tr.presets.ctr250().limitations == ()


def test_the_cli_prints_a_rod_warning_as_one_line(tmp_path, capsys):
    path = tmp_path / "rod.json"
    path.write_text(json.dumps({"length": 0.29, "bending_stiffness": 7e-3, "gratings": [0.1, 0.1 + 1e-12, 0.2]}))
    forces = tmp_path / "f.jsonl"
    forces.write_text('{"forces": [{"s": 0.25, "fx": 0.1, "fy": 0.0}]}\n')
    assert tr.cli.main(["simulate", "--rod", str(path), str(forces)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "torchrod simulate: warning: gratings[0] and gratings[1] lie 1e-12 m apart: they read the same curvature, "
        "which counts twice in the fit (a count test too sure of itself if they carry one sensor's value twice); "
        "give one of them"
    ]
