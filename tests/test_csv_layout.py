"""CSV as interrogators write it (torchrod.io.readings.CsvLayout): a header row names the columns, id and t are
optional, ids read as in JSON, every command that reads readings takes CSV, detected without --format."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.errors import ReadingError
from torchrod.io.readings import CsvLayout, csv_id, detect_format, iter_readings, parse_reading

F64 = torch.float64
ROD = tr.presets.nitinol290()
G = ROD.num_gratings
R = 3.5e-5
THREE = [[R, 0.0], [-R / 2, R * math.sqrt(3) / 2], [-R / 2, -R * math.sqrt(3) / 2]]


@pytest.fixture(scope="module")
def curvature():
    loads = tr.PointForces(
        s=torch.tensor([[0.12, 0.24], [0.07, 0.2]], dtype=F64),
        f=torch.tensor([[[0.4, -0.9], [0.3, 0.2]], [[-1.2, 0.1], [0.0, 0.6]]], dtype=F64),
    )
    u = tr.simulate(ROD, loads).grating_curvature
    return u + 0.05 * torch.randn(u.shape, dtype=F64, generator=torch.Generator().manual_seed(1))


def _cells(values) -> list[str]:
    return [repr(float(x)) for x in values]


def _read(text: str, **kw) -> list:
    return list(iter_readings(io.StringIO(text), G, ROD.gratings, "csv", **kw))


# ---------------------------------------------------------------------------------------------------- the parser
def test_a_quoted_cell_holding_a_line_break_is_one_record(curvature):
    """CSV lets a quoted cell hold a line break: the row runs on over the next line and gets one answer (numbered
    by its first line), and the rows after it are read as they are."""
    u = curvature[0]
    header = ["id", "t"] + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)]
    values = [*_cells(u[:, 0]), *_cells(u[:, 1])]
    text = "\n".join(
        [
            ",".join(header),
            ",".join(['"run 1\ntake ""2"""', "0.25", *values]),
            ",".join(["8", '"0.\n5"', *values]),  # a number cell holding a line break: one error, not two
            ",".join(["9", "0.75", *values]),
        ]
    )
    got = _read(text + "\n")
    assert [(r.line, r.id) for r in got] == [(2, 'run 1\ntake "2"'), (4, 8), (6, 9)]
    assert got[0].ok and got[0].t == 0.25 and torch.equal(got[0].curvature, u)
    assert got[1].error.startswith('line 4: t must be a number, got "0.\\n5": a CSV number is decimal digits')
    assert got[2].ok


@pytest.mark.parametrize("max_line", [200, 10**6])
def test_an_unclosed_quote_costs_its_own_line_only(max_line):
    """A quote opened and never closed would take in every line after it (and hold a live stream's answers until
    it closed): the record stops at MAX_RECORD_LINES lines or the line limit, whichever comes first, the line that
    opened it is one error line, and every line after it is read again as a row of its own."""
    from torchrod.io.csv_rows import MAX_RECORD_LINES

    rows = ["a,,0.1,0.2", '"b,,0.1,0.2'] + [f"c{k},,0.1,0.2" for k in range(40)]
    got = list(iter_readings(io.StringIO("\n".join(rows) + "\n"), 1, fmt="csv", max_line=max_line))
    assert got[0].ok and got[0].id == "a"
    limit = max_line
    assert got[1].error == (
        f"line 2: a quoted cell opens here and is not closed within {MAX_RECORD_LINES} lines or {limit} bytes (a "
        "stray quote?); the line is not read, the lines after it are"
    )
    assert [r.id for r in got[2:]] == [f"c{k}" for k in range(40)] and all(r.ok for r in got[2:])


def test_header_ux_block_then_uy_block_is_read_by_name(curvature):
    """The layout that was misread by position: ux_1..ux_G, then uy_1..uy_G, with a header saying so."""
    u = curvature[0]
    header = ["id", "t"] + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)]
    row = ["7", "0.25", *_cells(u[:, 0]), *_cells(u[:, 1])]
    (got,) = _read(",".join(header) + "\n" + ",".join(row) + "\n")
    assert got.ok and got.id == 7 and got.t == 0.25 and got.line == 2
    assert torch.equal(got.curvature, u)


def test_columns_in_any_order_without_id_and_with_other_columns(curvature):
    u = curvature[1]
    names = [f"uy{k}" for k in range(G, 0, -1)] + ["temperature", "t"] + [f"UX_{k}" for k in range(1, G + 1)]
    cells = _cells(u[:, 1].flip(0)) + ["21.5", "1.5"] + _cells(u[:, 0])
    cells[names.index("uy3")] = ""
    cells[names.index("UX_3")] = ""  # grating 3 missing: both its cells empty
    (got,) = _read(",".join(names) + "\n" + ",".join(cells) + "\n")
    assert got.ok and got.id is None and got.t == 1.5
    assert torch.isnan(got.curvature[2]).all()
    keep = torch.arange(G) != 2
    assert torch.equal(got.curvature[keep], u[keep])


def test_no_header_no_id_column(curvature):
    """An export of a time stamp and 2G values (no id), and of the values alone, by position."""
    u = curvature[0]
    values = [x for pair in u.tolist() for x in pair]
    rows = ",".join(["0.5", *map(repr, values)]) + "\n" + ",".join(map(repr, values)) + "\n"
    first, second = _read(rows)
    assert first.ok and first.t == 0.5 and first.id is None and torch.equal(first.curvature, u)
    assert second.ok and second.t is None and torch.equal(second.curvature, u)
    (bad,) = _read("a,b," + ",".join(map(repr, values[:-3])) + "\n")
    assert (
        "expected 30 cells (id, t, then ux, uy for 14 gratings), 29 (t, then the values) or 28 (the values "
        "alone), got 27" in bad.error
    )


def test_ids_read_as_in_json():
    zero = ",".join(["0.0"] * (2 * G))
    rows = [f"{ident},,{zero}" for ident in ("0", "42", "-3", "007", "1.5", "r1", "1e3")]
    got = _read("\n".join(rows) + "\n")
    assert [r.id for r in got] == [0, 42, -3, "007", 1.5, "r1", 1000.0]
    assert [type(r.id) for r in got][:3] == [int, int, int]
    assert csv_id("  ") is None and csv_id(" x ") == "x"


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("id,t,x1,y1", "names no reading column \\('id', 't', 'x1', 'y1'\\); expected id and t \\(both optional\\)"),
        ("a,b,c", "names no reading column"),
        ("id,ux_1,uy_1", "lacks the columns ux_2, uy_2, ux_3, uy_3, ux_4, uy_4 and 20 more"),
        ("ux_1,ux_1", "names 'ux_1' more than once"),
        (",".join([f"ux_{k},uy_{k}" for k in range(1, 16)]), "column 'ux_15', outside the rod's gratings 1..14"),
        ("ux_1,kappa_1", "names columns of curvature and curvature_polar"),
        ("eps_1_1,eps_1_2", 'give core strains: add "fibre"'),
        ("lambda_1,x", "column 'lambda_1' needs a core number"),
    ],
)
def test_header_errors_list_what_was_expected(header, message):
    with pytest.raises(ReadingError, match=message):
        _read(header + "\n1,2\n")


@pytest.mark.parametrize(
    ("column", "first", "second"),
    [("ux_1", "ux_1", "ux1"), ("ux_1", "ux_01", "ux_1"), ("uy_2", "UY_2", "uy02"), ("s_1", "s_1", "s1")],
)
def test_header_naming_one_value_under_two_spellings_is_refused(curvature, column, first, second):
    """Two columns for one grating's component were read with the last one winning; they are refused as one name
    given twice is, naming both."""
    names = [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)] + ["s_1", "fx_1", "fy_1"]
    names[names.index(column)] = first
    row = _cells(torch.cat([curvature[0, :, 0], curvature[0, :, 1]])) + ["0.1", "0.0", "0.0", "0.0"]
    with pytest.raises(ReadingError, match=f"names '{first}' and '{second}', two columns for the same value"):
        _read(",".join([*names, second]) + "\n" + ",".join(row) + "\n")


def test_header_naming_one_core_value_under_two_spellings_is_refused():
    fibre = tr.sensors.Fibre(cores=THREE, wavelength={"calibration": [[[10.0, -5.0, -5.0], [0.0, 8.0, -8.0]]] * G})
    names = [f"lambda_{k}_{c}" for k in range(1, G + 1) for c in range(1, 4)] + ["lambda1_1"]
    with pytest.raises(ReadingError, match="names 'lambda_1_1' and 'lambda1_1', two columns for the same value"):
        _read(",".join(names) + "\n", fibre=fibre)


def test_other_quantities_by_header():
    fibre = tr.sensors.Fibre(cores=THREE, wavelength={"calibration": [[[10.0, -5.0, -5.0], [0.0, 8.0, -8.0]]] * G})
    u = [1.0, -2.0]
    strains = fibre.curvature_to_strain(*u, 3e-4)
    polar = [math.hypot(*u), math.atan2(u[1], u[0])]
    shift = (fibre.bending_shift(torch.tensor([u] * G, dtype=F64)) / 1e-9).tolist()
    cases = {
        "kappa_{k},phi_{k}": polar,
        "eps_{k}_1,eps_{k}_2,eps_{k}_3": strains,
        "dlambda_{k}_1,dlambda_{k}_2,dlambda_{k}_3": shift[0],
    }
    for pattern, per in cases.items():
        header = ",".join(pattern.format(k=k) for k in range(1, G + 1))
        row = ",".join(repr(x) for _ in range(G) for x in per)
        (got,) = list(iter_readings(io.StringIO(header + "\n" + row + "\n"), G, fmt="csv", fibre=fibre))
        assert got.ok, got.error
        assert torch.allclose(got.curvature, torch.tensor([u] * G, dtype=F64), atol=1e-9), pattern


def test_row_errors_name_the_field_and_keep_the_other_rows(curvature):
    header = ",".join(["id"] + [f"{c}_{k}" for k in range(1, G + 1) for c in ("ux", "uy")])
    good = ",".join(["g", *_cells(curvature[0].flatten())])
    half = ",".join(["h", "1.0", "", *_cells(curvature[0].flatten()[2:])])
    short = "s,1,2"
    got = _read("\n".join([header, good, half, short, good]) + "\n")
    assert [r.ok for r in got] == [True, False, False, True]
    assert got[1].id == "h" and "line 3: curvature[0][1] must be a number, got null (an empty cell)" in got[1].error
    assert got[2].error == "line 4: the row has 3 cells, the header (line 1) names 29 columns"


def test_format_is_detected_from_the_extension_or_the_content():
    assert detect_format("run.csv", '{"id": 1}') == "csv"
    assert detect_format("run.jsonl", "a,b") == "jsonl"
    assert detect_format("-", '  {"id": 1}') == "jsonl"
    assert detect_format("run.txt", "12-30-01.250000: 1530.1, 1530.2") == "peaks"
    assert detect_format("run.txt", "id,t,ux_1") == "csv"
    assert detect_format("run.dat", "1,2,3") == "csv"


def test_layouts_positional_and_from_header_agree():
    positional = CsvLayout.positional(2 * G + 2, G)
    header = ["id", "t"] + [f"{c}_{k}" for k in range(1, G + 1) for c in ("ux", "uy")]
    named = CsvLayout.from_header(header, G)
    assert positional.data == named.data and (positional.id_column, positional.t_column) == (0, 1)


# ---------------------------------------------------------------------------------------------------- commands
def _csv_file(path: Path, u: torch.Tensor, *, ids: bool = True) -> None:
    header = (
        (["id"] if ids else []) + ["t"] + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)]
    )
    rows = [",".join(header)]
    for b in range(u.shape[0]):
        rows.append(",".join(([str(b)] if ids else []) + [str(0.1 * b)] + _cells(u[b, :, 0]) + _cells(u[b, :, 1])))
    path.write_text("\n".join(rows) + "\n")


def _answers(capsys) -> list[dict]:
    return [json.loads(line) for line in capsys.readouterr().out.splitlines()]


def test_estimate_rod_file_and_csv_without_format_equals_json(tmp_path, capsys, curvature):
    rod_file, csv, jsonl = tmp_path / "rod.json", tmp_path / "readings.csv", tmp_path / "readings.jsonl"
    ROD.to_json(rod_file)
    _csv_file(csv, curvature)
    jsonl.write_text("".join(json.dumps({"id": b, "curvature": curvature[b].tolist()}) + "\n" for b in range(2)))
    assert main(["estimate", str(rod_file), str(csv), "--noise", "0.05", "--quiet"]) == 0
    from_csv = _answers(capsys)
    assert main(["estimate", "--rod", str(rod_file), str(jsonl), "--noise", "0.05", "--quiet"]) == 0
    from_json = _answers(capsys)
    assert [a["id"] for a in from_csv] == [0, 1]  # integers, as in the JSON readings
    for a, b in zip(from_csv, from_json, strict=True):
        a.pop("time_ms"), b.pop("time_ms")
        assert a == b
    # a header naming no known column: status 2, the expected columns listed
    bad = tmp_path / "bad.csv"
    bad.write_text("time,x1,y1\n0,1,2\n")
    assert main(["estimate", str(rod_file), str(bad), "--noise", "0.05"]) == 2
    assert "names no reading column" in capsys.readouterr().err
    assert main(["estimate", str(rod_file), "nitinol290", str(csv)]) == 2
    assert "give the rod and the readings" in capsys.readouterr().err


def test_stream_plot_and_calibrate_read_csv(tmp_path, capsys, curvature):
    csv = tmp_path / "readings.csv"
    _csv_file(csv, curvature, ids=False)
    out = tmp_path / "answers.jsonl"
    argv = ["stream", "--rod", "nitinol290", "--checkpoint", "none", "--input", str(csv), "--noise", "0.05"]
    argv += ["--time-budget-ms", "1e6"]
    assert main([*argv, "--out", str(out)]) == 0
    answers = [json.loads(x) for x in out.read_text().splitlines()]
    assert [a["num_forces"] for a in answers] == [2, 2] and [a["t"] for a in answers] == [0.0, 0.1]
    png = tmp_path / "stream.png"
    assert main(["plot", str(csv), str(out), "--rod", "nitinol290", "--out", str(png)]) == 0
    assert png.exists() and png.stat().st_size > 1000
    capsys.readouterr()
    # calibrate's reader: the known forces in columns s_J, fx_J, fy_J
    from torchrod.io.known_loads import read_readings

    header = ["id"] + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)]
    header += ["s_1", "fx_1", "fy_1", "s_2", "fx_2", "fy_2"]
    forces = [[0.12, 0.4, -0.9, 0.24, 0.3, 0.2], [0.07, -1.2, 0.1, "", "", ""]]
    rows = [",".join(header)]
    for b in range(2):
        rows.append(",".join([str(b), *_cells(curvature[b, :, 0]), *_cells(curvature[b, :, 1]), *map(str, forces[b])]))
    calib = tmp_path / "calib.csv"
    calib.write_text("\n".join(rows) + "\n")
    data = read_readings(calib, ROD)
    assert data.ids == (0, 1) and torch.equal(data.curvature, curvature)
    assert data.forces.count.tolist() == [2, 1]
    assert torch.allclose(data.forces.s[0], torch.tensor([0.12, 0.24], dtype=F64))
    assert torch.allclose(data.forces.f[1, 0], torch.tensor([-1.2, 0.1], dtype=F64))


def test_csv_id_matches_the_json_reading_of_the_same_id():
    zero = [[0.0, 0.0]] * G
    from_json = parse_reading({"id": 3, "curvature": zero}, G)
    (from_csv,) = _read("3,," + ",".join(["0.0"] * (2 * G)) + "\n")
    assert from_csv.id == from_json.id and type(from_csv.id) is type(from_json.id)


# ------------------------------------------------------------------------------------------ errors that name the fix
@pytest.mark.parametrize(
    ("separator", "named"), [(";", "semicolons (;)"), ("\t", "tabs"), ("|", "vertical bars (|)"), (" ", "spaces")]
)
def test_a_header_in_one_cell_names_its_separator_and_asks_for_commas(separator, named):
    header = separator.join(["id", "t"] + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)])
    row = separator.join(["1", "0.0"] + ["0.5"] * (2 * G))
    with pytest.raises(ReadingError) as error:
        _read(f"{header}\n{row}\n")
    message = str(error.value)
    assert message.startswith("line 1: the CSV header is one cell")
    assert f"separated by {named}, not commas" in message and "write the file with commas" in message


def test_a_first_row_without_header_in_one_cell_names_its_separator_too():
    with pytest.raises(ReadingError, match=r"the CSV first row is one cell .*separated by semicolons \(;\)"):
        _read(";".join(["0.5"] * (2 * G)) + "\n")


def test_a_row_of_one_cell_without_a_separator_is_still_an_error_line():
    (got,) = _read("hello\n")
    assert not got.ok and "got 1" in got.error


def _header_without_id_or_t(extra: list[str]) -> str:
    return ",".join(extra + [f"ux_{k}" for k in range(1, G + 1)] + [f"uy_{k}" for k in range(1, G + 1)])


def test_a_header_without_id_or_t_says_which_columns_it_ignores(curvature):
    u = curvature[0]
    text = (
        _header_without_id_or_t(["sample", "Time"]) + "\n" + ",".join(["3", "0.5", *_cells(u[:, 0]), *_cells(u[:, 1])])
    )
    with pytest.warns(tr.ReadingWarning) as caught:
        (got,) = _read(text + "\n")
    assert got.ok and got.id is None and got.t is None  # read, but without them
    (warning,) = caught
    message = str(warning.message)
    assert message.startswith("line 1: the CSV header has no id or t column and ignores the columns 'sample', 'Time'")
    assert "rename 'sample' to id" in message and "rename 'Time' to t" in message


def test_no_warning_when_the_header_has_t_or_ignores_nothing(curvature, recwarn):
    u = curvature[0]
    values = [*_cells(u[:, 0]), *_cells(u[:, 1])]
    _read(_header_without_id_or_t(["t", "temperature"]) + "\n" + ",".join(["0.5", "21.0", *values]) + "\n")
    _read(_header_without_id_or_t([]) + "\n" + ",".join(values) + "\n")
    assert not [w for w in recwarn if issubclass(w.category, tr.TorchrodWarning)]


def test_a_header_that_fails_names_the_columns_it_ignored():
    with pytest.raises(ReadingError, match=r"lacks the columns .* \(it ignores the columns 'sample', 'time'\)"):
        _read("sample,time,ux_1,uy_1\n1,2,3,4\n")


def test_the_command_prints_the_ignored_columns_as_a_warning(tmp_path, capsys, curvature):
    u = curvature[0]
    path = tmp_path / "r.csv"
    path.write_text(
        _header_without_id_or_t(["sample", "time"]) + "\n" + ",".join(["3", "0.5", *_cells(u[:, 0]), *_cells(u[:, 1])])
    )
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.1", str(path)]) == 0
    err = capsys.readouterr().err
    assert "torchrod estimate: warning: line 1: the CSV header has no id or t column" in err
    path.write_text("t;ux_1;uy_1\n0;1;2\n")
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.1", str(path)]) == 2
    assert "error: line 1: the CSV header is one cell" in capsys.readouterr().err


def test_a_title_line_in_one_cell_stays_an_error_line_of_its_own(curvature):
    u = curvature[0]
    row = ",".join(["r1", "0.5", *(x for k in range(G) for x in _cells(u[k]))])
    title, got = _read(f"Exported by FooSoft 1.2; all channels\n{row}\n")
    assert not title.ok and title.line == 1
    assert got.ok and got.id == "r1"
