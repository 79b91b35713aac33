"""Fuzzing the one reading parser with hypothesis: whatever a line holds (numbers JSON or a double cannot carry,
ids JSON cannot echo, deep nesting, odd text, CSV cells outside the grammar), every non-blank line gets exactly one
answer, in order, as valid JSON, and no exception escapes; through the parser directly and through ``main()``."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from typing import Any
from unittest import mock

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchrod as tr
from torchrod.cli import main
from torchrod.estimate.checks import check_readings
from torchrod.io.readings import MAX_CURVATURE, Reading, id_problem, iter_readings, to_reading
from torchrod.sensors import Fibre

ROD = tr.presets.nitinol290()
G = ROD.num_gratings
FIBRE = Fibre(cores=[[3.5e-5, 0.0], [-1.75e-5, 3.03e-5], [-1.75e-5, -3.03e-5]])
UNKNOWN = object()  # an answer's id the test does not predict


class Raw(str):
    """JSON text written as it is (NaN, 1e999, a 5000-digit integer: what json.dumps will not write)."""


def render(value: Any) -> str:
    """JSON text of a value built from Raw tokens, None, booleans, strings, lists and dicts."""
    if isinstance(value, Raw):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(render(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(json.dumps(k) + ": " + render(v) for k, v in value.items()) + "}"
    return json.dumps(value)


# ---------------------------------------------------------------------------------------------------- strategies
number_texts = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.floats(-1e6, 1e6).map(repr),
    st.integers(-(10**7), 10**7).map(str),
    st.integers(300, 4400).map(lambda n: "8" * n),  # overflows a double; over 4300 digits Python refuses it
    st.sampled_from(["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1e308", "1e6", "1000001", "-0", "1E-400"]),
)
numbers = number_texts.map(Raw)
scalars = st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=12))
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=12,
)
plausible = st.floats(-50.0, 50.0).map(lambda x: Raw(repr(x)))
pairs = st.one_of(st.none(), st.lists(numbers, min_size=2, max_size=2), st.lists(plausible, min_size=2, max_size=2))
curvatures = st.one_of(
    st.lists(st.one_of(st.none(), st.lists(plausible, min_size=2, max_size=2)), min_size=G, max_size=G),
    st.lists(pairs, min_size=G, max_size=G),
    st.lists(pairs, max_size=G + 2),
    values,
)
ids = st.one_of(st.text(max_size=10), st.integers(-5, 5), numbers, values, st.just(Raw("[" * 60 + "]" * 60)))
small = st.floats(-1e-3, 1e-3).map(lambda x: Raw(repr(x)))
core_strains = st.one_of(
    st.none(), st.lists(small, min_size=3, max_size=3), st.lists(st.one_of(numbers, small), max_size=4), values
)
strains = st.one_of(
    st.lists(st.one_of(st.none(), st.lists(small, min_size=3, max_size=3)), min_size=G, max_size=G),
    st.lists(core_strains, min_size=G, max_size=G),
    values,
)
OPTIONAL = {
    "id": ids,
    "t": st.one_of(numbers, st.none(), values),
    "gratings": st.one_of(st.just([Raw(repr(g)) for g in ROD.gratings]), values),
    "extra": values,
}
readings = st.one_of(
    st.fixed_dictionaries({"curvature": curvatures}, optional=OPTIONAL),
    st.fixed_dictionaries({"strain": strains}, optional=OPTIONAL),
    st.fixed_dictionaries({"curvature_polar": curvatures}, optional=OPTIONAL),
    st.fixed_dictionaries({"curvature": curvatures, "strain": strains}, optional=OPTIONAL),
)
line_text = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n"), max_size=120)
deep = st.integers(1, 3000).map(lambda d: '{"id": "deep", "curvature": ' + "[" * d + "]" * d + "}")


@st.composite
def json_lines(draw: Any, max_lines: int = 6) -> list[tuple[str, Any]]:
    """Lines with the id each answer must carry (UNKNOWN when the test does not predict it)."""
    out = []
    for k in range(draw(st.integers(0, max_lines))):
        kind = draw(st.sampled_from(["reading", "reading", "reading", "text", "deep", "blank"]))
        if kind == "reading":
            obj = draw(readings)
            if draw(st.booleans()):
                obj = {**obj, "id": f"L{k}"}
            out.append(
                (
                    render(obj),
                    obj["id"] if isinstance(obj.get("id"), str) and not isinstance(obj["id"], Raw) else UNKNOWN,
                )
            )
        elif kind == "text":
            out.append((draw(line_text), UNKNOWN))
        elif kind == "deep":
            out.append((draw(deep), UNKNOWN))
        else:
            out.append((draw(st.sampled_from(["", "   ", "\t\r"])), UNKNOWN))
    return out


csv_cells = st.one_of(
    number_texts,
    st.floats(-50.0, 50.0).map(repr),
    st.sampled_from(["", " ", "nan", "inf", "1_000", "0x1f", "1 000", "½", "١٢", '"1.5"', "1e", "+.5", "5."]),
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n\r"), max_size=8),
)


@st.composite
def csv_lines(draw: Any, max_lines: int = 6, per: int = 2) -> list[tuple[str, Any]]:
    """CSV rows (id, t, ``per`` G value cells, mostly), with the ids the answers must carry."""
    out = []
    for k in range(draw(st.integers(0, max_lines))):
        width = draw(st.sampled_from([per * G + 2] * 4 + [0, 1, per * G + 1, per * G + 3]))
        cells = draw(st.lists(csv_cells, min_size=width, max_size=width))
        if width and draw(st.booleans()):
            cells[0] = f"C{k}"
        out.append((",".join(cells), f"C{k}" if width and cells[0] == f"C{k}" else UNKNOWN))
    return out


# ---------------------------------------------------------------------------------------------------- checks
def expected_lines(lines: list[tuple[str, Any]]) -> list[tuple[int, Any]]:
    """(line number, id) of the lines that must get an answer: the non-blank ones (a BOM opens line 1)."""
    out = []
    for number, (text, ident) in enumerate(lines, start=1):
        if number == 1 and text.startswith("\ufeff"):
            text = text[1:]
        if text.strip():
            out.append((number, ident))
    return out


def expected_rows(lines: list[tuple[str, Any]]) -> list[tuple[int, Any]]:
    """(line number, id) of the CSV rows that must get an answer: Python's :mod:`csv` says where each row ends (a
    generated cell may open a quote, and a quoted cell holding a line break makes one row of several lines, answered
    once under its first line's number); a blank line outside quotes gets none."""
    reader = csv.reader(io.StringIO("".join(line + "\n" for line, _ in lines)))
    out = []
    start = 1
    for _ in reader:
        first, start = start, reader.line_num + 1
        if reader.line_num > first or lines[first - 1][0].strip():
            out.append((first, lines[first - 1][1]))
    return out


def strict_json(text: str) -> dict:
    def refuse(token: str) -> None:
        raise AssertionError(f"{token} in an answer: not JSON")

    obj = json.loads(text, parse_constant=refuse)
    assert isinstance(obj, dict)
    return obj


def check_answers(answers: list[dict], expected: list[tuple[int, Any]]) -> None:
    assert len(answers) == len(expected)
    for answer, (number, ident) in zip(answers, expected, strict=False):
        assert id_problem(answer.get("id")) is None
        if "error" in answer:
            assert answer["error"].startswith(f"line {number}: "), (number, answer["error"])
            assert len(answer["error"]) < 1000
        if ident is not UNKNOWN:
            assert answer["id"] == ident


def check_reading(reading: Any, number: int, ident: Any) -> None:
    """A parsed reading: an error naming its line, or a (G, 2) float64 curvature of NaN rows and values within the
    bound, with an id JSON can echo; the estimator's own check accepts it."""
    assert reading.line == number and id_problem(reading.id) is None
    if ident is not UNKNOWN:
        assert reading.id == ident
    if not reading.ok:
        assert reading.error.startswith(f"line {number}: ") and len(reading.error) < 1000
        return
    u = reading.curvature
    assert u.dtype == torch.float64 and u.shape == (G, 2)
    nan = torch.isnan(u)
    assert bool((nan.all(-1) | ~nan.any(-1)).all()) and not bool(nan.all())
    assert bool((u[~nan].abs() <= MAX_CURVATURE).all())
    assert reading.t is None or math.isfinite(reading.t)
    check_readings(u.unsqueeze(0), None, G)


SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(json_lines(max_lines=8))
def test_parser_reads_every_json_line_into_one_reading(lines):
    text = "".join(line + "\n" for line, _ in lines)
    got = list(iter_readings(io.StringIO(text), G, ROD.gratings, "jsonl", fibre=FIBRE))
    expected = expected_lines(lines)
    assert len(got) == len(expected)
    for reading, (number, ident) in zip(got, expected, strict=False):
        check_reading(reading, number, ident)


@SETTINGS
@given(csv_lines(max_lines=8, per=3))
def test_parser_reads_every_csv_strain_row_into_one_reading(lines):
    header = ",".join(["id", "t"] + [f"eps_{k}_{c}" for k in range(1, G + 1) for c in range(1, 4)])
    text = header + "\n" + "".join(line + "\n" for line, _ in lines)
    got = list(iter_readings(io.StringIO(text), G, ROD.gratings, "csv", quantity="strain", fibre=FIBRE))
    expected = [(number + 1, ident) for number, ident in expected_rows(lines)]
    assert len(got) == len(expected)
    for reading, (number, ident) in zip(got, expected, strict=False):
        check_reading(reading, number, ident)


@SETTINGS
@given(csv_lines(max_lines=8))
def test_parser_reads_every_csv_row_into_one_reading(lines):
    header = ",".join(["id", "t"] + [f"{c}{k}" for k in range(1, G + 1) for c in ("ux", "uy")])
    text = header + "\n" + "".join(line + "\n" for line, _ in lines)
    got = list(iter_readings(io.StringIO(text), G, ROD.gratings, "csv"))
    expected = [(number + 1, ident) for number, ident in expected_rows(lines)]
    assert len(got) == len(expected)
    for reading, (number, ident) in zip(got, expected, strict=False):
        check_reading(reading, number, ident)


WAVE_FIBRE = Fibre(
    cores=FIBRE.cores, wavelength={"reference": [[1530.0 + 2.5 * k] * 3 for k in range(G)]}, wavelength_unit="nm"
)
peak_cells = st.one_of(
    st.floats(1520.0, 1570.0).map(lambda x: f"{x:.4f}"),
    st.sampled_from(["", " ", "nan", "1_530", "1530.0.1", "-", "1e999"]),
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n\r,:"), max_size=6),
)


@st.composite
def peak_lines(draw: Any, max_lines: int = 6) -> list[str]:
    """Peak log lines: a time stamp (mostly valid), a colon and about G x C values (mostly a valid count)."""
    out = []
    for _ in range(draw(st.integers(0, max_lines))):
        time = draw(
            st.one_of(
                st.sampled_from(["10-00-00.5", "23:59:59.9", "2024-01-02 00:00:01", "3.5"]),
                st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n\r"), max_size=8),
            )
        )
        count = draw(st.sampled_from([3 * G] * 4 + [3 * G - 1, 3 * G + 1, 0]))
        cells = draw(st.lists(peak_cells, min_size=count, max_size=count))
        out.append(f"{time}: " + ", ".join(cells))
    return out


@SETTINGS
@given(peak_lines(max_lines=8))
def test_parser_reads_every_peak_log_line_into_one_reading(lines):
    text = "".join(line + "\n" for line in lines)
    got = list(iter_readings(io.StringIO(text), G, ROD.gratings, "peaks", fibre=WAVE_FIBRE))
    expected = expected_lines([(line, UNKNOWN) for line in lines])
    assert len(got) == len(expected)
    for reading, (number, _) in zip(got, expected, strict=False):
        check_reading(reading, number, UNKNOWN)


@SETTINGS
@given(st.lists(st.one_of(st.binary(max_size=40), st.integers(0, 300).map(lambda n: n.to_bytes(4, "big"))), max_size=8))
def test_fbgs_reader_never_raises_on_any_bytes(chunks):
    """Whatever bytes arrive, each record read becomes one reading or one error naming it, and reading ends."""
    from torchrod.io.fbgs import read_records

    rest = list(chunks)
    got = list(read_records(lambda n: rest.pop(0) if rest else b"", G))
    for number, reading in enumerate(got, start=1):
        assert reading.ok or reading.error.startswith(f"record {number}: ")
        if reading.ok:
            check_readings(reading.curvature.unsqueeze(0), None, G)


python_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5), st.just(10**400)),
    lambda inner: st.one_of(
        st.lists(inner, max_size=G + 1),
        st.tuples(inner, inner),
        st.dictionaries(st.sampled_from(["id", "curvature", "t", "error", "x"]), inner, max_size=4),
    ),
    max_leaves=40,
)


@SETTINGS
@given(st.one_of(python_values, st.builds(Reading, python_values, python_values, python_values)))
def test_python_api_readings_never_raise(item):
    """The stream API's entry: any Python object becomes a checked reading or an error reading."""
    reading = to_reading(item, G, ROD.gratings)
    assert id_problem(reading.id) is None
    if reading.ok:
        check_readings(reading.curvature.unsqueeze(0), None, G)
    else:
        assert isinstance(reading.error, str) and len(reading.error) < 1000


# ---------------------------------------------------------------------------------------------------- through main()
class _Result:
    """What the commands read from an estimate: records, and no converged reading to track."""

    def __init__(self, B: int) -> None:
        self.converged = torch.zeros(B, dtype=torch.bool)
        self.num_forces = torch.zeros(B, dtype=torch.long)

    def to_records(self, ids: list) -> list[dict]:
        return [{"id": i, "num_forces": 0, "forces": [], "loss": None, "converged": False} for i in ids]


class _CheckingEstimator:
    """A stand-in for the estimator (the fuzz is of the input and output edges, and must stay fast): it checks
    what reaches it by the estimator's own rules, as the real one does, and answers every reading."""

    def __init__(self, rod: tr.Rod, options: Any = None, warm_start: Any = None) -> None:
        self.rod, self.options = rod, options

    def plan(self, *args: Any, **kwargs: Any) -> None:
        """Nothing to compile."""

    def estimate(self, curvature: torch.Tensor, mask: torch.Tensor | None = None, **kwargs: Any) -> _Result:
        check_readings(curvature, mask, self.rod.num_gratings)
        return _Result(curvature.shape[0])


def run_cli(command: str, fmt: str, text: str, *options: str) -> tuple[int, list[dict]]:
    """Exit status and strictly decoded answers of ``torchrod COMMAND`` on ``text`` (written with --out)."""
    with tempfile.TemporaryDirectory() as folder:
        source, target = os.path.join(folder, "in.txt"), os.path.join(folder, "out.jsonl")
        with open(source, "w", encoding="utf-8") as fh:
            fh.write(text)
        if command == "estimate":
            argv = ["estimate", "--rod", "nitinol290", "--format", fmt, "--batch-size", "3", source]
        else:
            argv = [
                "stream",
                "--rod",
                "nitinol290",
                "--checkpoint",
                "none",
                "--format",
                fmt,
                "--input",
                source,
            ]
            argv += ["--batch-size", "3", "--max-latency-ms", "0"]
        status = main([*argv, "--noise", "0.1", "--out", target, *options])
        with open(target, encoding="utf-8") as fh:
            answers = [strict_json(line) for line in fh.read().splitlines()]
    return status, answers


@pytest.mark.parametrize(("command", "fmt"), [("estimate", "jsonl"), ("stream", "jsonl"), ("stream", "csv")])
@settings(max_examples=70, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_cli_answers_every_line_once_in_order(command, fmt, data):
    lines = data.draw(json_lines() if fmt == "jsonl" else csv_lines())
    text = "".join(line + "\n" for line, _ in lines)
    expected = expected_lines(lines)
    if fmt == "csv":
        text = ",".join(["id", "t"] + [f"{c}_{k}" for k in range(1, G + 1) for c in ("ux", "uy")]) + "\n" + text
        expected = [(number + 1, ident) for number, ident in expected_rows(lines)]
    module = f"torchrod.cli.commands.{command}.Estimator"
    with mock.patch(module, _CheckingEstimator):
        status, answers = run_cli(command, fmt, text)
    check_answers(answers, expected)
    assert status == (1 if any("error" in a for a in answers) else 0)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(json_lines(max_lines=3))
def test_cli_with_the_real_estimator_answers_every_line(lines):
    """The real estimator on whatever passes the edge (absurd but finite values included): one valid JSON line
    per input line still."""
    status, answers = run_cli("estimate", "jsonl", "".join(line + "\n" for line, _ in lines), "--num-forces", "1")
    check_answers(answers, expected_lines(lines))
    assert status in (0, 1)
