"""docs/reference/formats.md names every key the parsers accept and every field an answer holds: the lists are taken
from the code (the rod parser's accepted keys, the CSV header's column names, the keys of real answers), so a key
added to the code without its line in the reference fails here."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.errors import RodError
from torchrod.estimate.noise import NoiseLearning
from torchrod.io import csv_rows, readings
from torchrod.rod import Rod
from torchrod.sensors import Fibre, Wavelength

FORMATS = Path(__file__).resolve().parents[1] / "docs" / "reference" / "formats.md"


def _sections() -> dict[str, str]:
    """formats.md by its ``## `` sections (subsections stay in their section)."""
    parts = re.split(r"^## (.+)$", FORMATS.read_text(encoding="utf-8"), flags=re.MULTILINE)
    return {title.strip(): body for title, body in zip(parts[1::2], parts[2::2], strict=True)}


def _named(text: str) -> set[str]:
    """Every name in backticks in ``text``, and the last part of a dotted or ``forces[].x`` one."""
    names = set()
    for quoted in re.findall(r"`([^`\n]+)`", text):
        names.add(quoted)
        names.add(re.split(r"[.\]]", quoted)[-1])
    return names


def _known_keys(parse, data) -> list[str]:
    """The keys a parser accepts, read from its own refusal of an unknown key ("... the known keys are [...]")."""
    with pytest.raises(RodError) as refusal:
        parse({**data, "no_such_key": 1})
    return ast.literal_eval(str(refusal.value).rsplit("known keys are ", 1)[1])


def test_every_rod_file_key_is_in_the_reference():
    section = _sections()["A rod file"]
    named = _named(section)
    rod_keys = {f.name for f in dataclasses.fields(Rod)}  # the set Rod.from_dict accepts
    assert {"length", "gratings", "fibre"} <= rod_keys
    assert sorted(rod_keys - named) == []
    fibre_keys = _known_keys(Fibre.from_dict, {})
    wavelength_keys = _known_keys(Wavelength.from_dict, {})
    assert {"cores", "wavelength"} <= set(fibre_keys) and {"reference", "calibration"} <= set(wavelength_keys)
    dotted = {f"fibre.{k}" for k in fibre_keys} | {f"fibre.wavelength.{k}" for k in wavelength_keys}
    assert sorted(dotted - named) == []
    segment = tr.presets.ctr250().to_dict()["intrinsic_curvature"][0]
    assert sorted(set(segment) - named) == []


def _header_columns() -> set[str]:
    """Every column name form the CSV header parser accepts, from its own tables (K: grating, C: core, J: force)."""
    stems = re.match(r"\(([a-z|]+)\)", csv_rows._COLUMN.pattern).group(1).split("|")
    forms = {"id", "t", *csv_rows._JIG_COLUMNS}
    for stem in stems:
        if stem in csv_rows._PER_CORE:
            forms.add(f"{stem}_K_C")
        elif stem in csv_rows._FORCE_FIELDS:
            forms.add(f"{stem}_J")
        else:
            forms.add(f"{stem}_K")
    return forms


def test_every_csv_header_column_and_quantity_is_in_the_reference():
    section = _sections()["CSV"]
    named = _named(section)
    forms = _header_columns()
    assert {"ux_K", "kappa_K", "lambda_K_C", "dlambda_K_C", "s_J", "jig_angle"} <= forms
    assert sorted(forms - named) == []
    assert sorted(set(readings.QUANTITIES) - named) == []  # --csv-quantity's values
    flat = " ".join(section.split())
    assert "any order" in flat and "case ignored" in flat and "ignored" in flat.replace("case ignored", "")


def test_every_reading_key_is_in_the_reference():
    named = _named(_sections()["Readings in JSON lines"])
    keys = {*readings.QUANTITIES.values(), "id", "t", "gratings", "forces", "jig"}
    assert sorted(keys - named) == []


def _estimate_answers(tmp_path: Path, capsys) -> list[dict]:
    rod = tr.presets.nitinol290()
    loads = tr.PointForces.from_lists([[(0.15, 0.4, -0.3)]] * 6)
    kappa = tr.grating_curvature(rod, loads) + 0.1 * torch.randn(6, 14, 2, generator=torch.Generator().manual_seed(0))
    lines = [{"id": f"r{k}", "t": 0.02 * k, "curvature": kappa[k].tolist()} for k in range(6)]
    path = tmp_path / "readings.jsonl"
    path.write_text("\n".join(map(json.dumps, [*lines, {"id": "bad", "curvature": [[0.0, 0.0]]}])) + "\n")
    answers = []
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.1", str(path)]) == 1  # (1: a line was an error)
    answers += [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    estimator = tr.Estimator(rod, tr.EstimatorOptions(noise=None))
    options = tr.StreamOptions(learn_noise=NoiseLearning(after=1, window=1), workers=1)
    answers += [result.record for result in tr.stream(estimator, lines, options)]
    return answers


def test_every_answer_field_is_in_the_reference(tmp_path, capsys):
    answers = _estimate_answers(tmp_path, capsys)
    fields = {key for answer in answers for key in answer}
    force_fields = {key for answer in answers for force in answer.get("forces", []) for key in force}
    assert {"status", "forces", "p_value", "time_ms", "latency_ms", "t", "noise", "error"} <= fields
    assert {"s", "fx", "magnitude", "std_fy"} <= force_fields
    section = _sections()["An estimate"]
    named = _named(section)
    assert sorted(fields - named) == []
    assert sorted(force_fields - named) == []  # (named as forces[].s, or in a list after it: `std_fx`)
