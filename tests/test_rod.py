"""The Rod description: validation at the edge, JSON round trips, and the paper's stiffness."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.rod import Rod

DATA = Path(__file__).resolve().parents[1] / "data"

GEOMETRY = {"length": 0.29, "outer_diameter": 1.397e-3, "inner_diameter": 1.118e-3, "youngs_modulus": 67e9}
GRATINGS = [0.01, 0.03, 0.05]


def test_nitinol290_bending_stiffness_matches_the_paper():
    # EI = E pi (d_out^4 - d_in^4) / 64 with the paper's tube: about 7.39e-3 N m^2 (NOTES.md).
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
