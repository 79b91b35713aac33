"""The one set of reading rules (torchrod.io.readings): numbers, bounds, ids, CSV numbers, quoting, and the tensor
checks the estimator and the warm-start network share."""

import json
import math

import numpy as np
import pytest
import torch

from torchrod.estimate.checks import check_readings
from torchrod.io.readings import (
    MAX_CURVATURE,
    HugeInteger,
    Reading,
    as_number,
    check_id,
    csv_number,
    curvature_tensor,
    parse_csv_row,
    parse_reading,
    quote,
    to_reading,
)

G = 3
GRATINGS = (0.1, 0.2, 0.3)


def pairs(*first):
    """G curvature pairs [1/m], the first one given."""
    return [list(first), [0.5, -0.5], [0.25, 0.0]]


# ---------------------------------------------------------------------------------------------------- tensors
def test_nan_gratings_are_masked_not_zeroed():
    u = torch.ones(2, 3, 2, dtype=torch.float64)
    u[1, 2] = math.nan
    out, mask = check_readings(u, None, 3)
    assert out is u  # values are not rewritten
    assert mask.tolist() == [[True, True, True], [True, True, False]]


@pytest.mark.parametrize("shape", [(2, 4, 2), (2, 3), (2, 3, 3)])
def test_wrong_shapes_name_the_shape(shape):
    with pytest.raises(ValueError, match=r"\(B, 3, 2\)"):
        check_readings(torch.zeros(shape), None, 3)


def test_mask_checks():
    u = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match="mask must have shape"):
        check_readings(u, torch.ones(2, 4, dtype=torch.bool), 3)
    with pytest.raises(TypeError, match="bool"):
        check_readings(u, torch.ones(2, 3), 3)
    u[0, 1, 0] = math.nan
    with pytest.raises(ValueError, match=r"curvature\[0, 1\] is not finite"):
        check_readings(u, torch.ones(2, 3, dtype=torch.bool), 3)
    with pytest.raises(TypeError, match="floating-point"):
        check_readings(torch.zeros(2, 3, 2, dtype=torch.long), None, 3)


def test_tensor_checks_apply_the_bound_and_refuse_half_and_infinite_rows():
    """The estimator's check has the parser's rules: a present value beyond MAX_CURVATURE or infinite is named,
    a row with one NaN is refused without a mask; values the mask leaves out are ignored, whatever they are;
    finite but absurd values within the bound pass."""
    u = torch.zeros(2, 3, 2, dtype=torch.float64)
    u[1, 2, 0] = 1e308
    with pytest.raises(ValueError, match=r"curvature\[1, 2\].*exceeds the bound of 1e\+06 1/m"):
        check_readings(u, None, 3)
    mask = torch.ones(2, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"curvature\[1, 2\].*exceeds the bound"):
        check_readings(u, mask, 3)
    mask[1, 2] = False
    assert check_readings(u, mask, 3)[1] is mask
    u[1, 2] = torch.tensor([math.inf, 0.0])
    with pytest.raises(ValueError, match=r"curvature\[1, 2\] is not finite"):
        check_readings(u, None, 3)
    u[1, 2] = torch.tensor([math.nan, 0.0])
    with pytest.raises(ValueError, match=r"curvature\[1, 2\].*one NaN component"):
        check_readings(u, None, 3)
    u[1, 2] = 1e4
    assert check_readings(u, None, 3)[1].all()


# ---------------------------------------------------------------------------------------------------- numbers
def test_as_number_names_the_field_and_refuses_what_is_not_a_finite_number():
    assert as_number(3, "x") == 3.0 and isinstance(as_number(3, "x"), float)
    assert as_number(np.float32(0.5), "x") == 0.5
    for value, message in [
        (True, "x must be a number, got a boolean true"),
        ("1", 'x must be a number, got a string "1"'),
        (None, "x must be a number, got null"),
        ([1], "x must be a number, got an array [1]"),
        (math.nan, "x must be finite, got NaN"),
        (-math.inf, "x must be finite, got -Infinity"),
        (10**400, "x must be a finite number, got 100000000000000000000... (401 digits), which overflows"),
        (HugeInteger("9" * 5000), "x must be a finite number, got an integer of 5000 digits"),
    ]:
        with pytest.raises(ValueError) as info:
            as_number(value, "x")
        assert str(info.value).startswith(message), str(info.value)
    with pytest.raises(ValueError, match=r"u = 1e\+308 1/m is beyond the bound of 1e\+06 1/m"):
        as_number(1e308, "u", bound=MAX_CURVATURE, unit="1/m")
    assert as_number(-1e6, "u", bound=MAX_CURVATURE) == -1e6


@pytest.mark.parametrize("text", ["12", "-1.5", "+.5", "5.", "2.5E-3", " 7e+2 ", "0", "00012"])
def test_csv_numbers_of_the_grammar_are_read(text):
    assert csv_number(text, "c") == float(text)


@pytest.mark.parametrize(
    "text",
    ["1_000", "0x1f", "1 000", "1,5", "½", "١٢", "1e", "e5", "--1", "+", ".", "1.2.3", "0b1", "infinit"],
)
def test_csv_cells_outside_the_grammar_are_not_numbers(text):
    """Python's float() takes 1_000 and non-ASCII digits; a CSV number must not."""
    with pytest.raises(ValueError, match="c must be a number, got .*a CSV number is decimal digits"):
        csv_number(text, "c")


def test_csv_nan_and_inf_are_not_finite_and_empty_is_missing():
    for text in ("nan", "NaN", "-inf", "Infinity"):
        with pytest.raises(ValueError, match="c must be finite.*leave a missing value's cell empty"):
            csv_number(text, "c")
    assert csv_number("  ", "c") is None
    with pytest.raises(ValueError, match="beyond the bound"):
        csv_number("2e6", "c", bound=MAX_CURVATURE)


# ---------------------------------------------------------------------------------------------------- quoting, ids
def test_quote_is_short_and_never_recurses():
    text = quote("a" * 10_000_000)
    assert len(text) < 130 and text.endswith("(10000000 characters)")
    deep: list = []
    inner = deep
    for _ in range(100_000):
        inner.append([])
        inner = inner[0]
    assert len(quote(deep)) <= 110
    assert quote({"a": math.nan, "b": [1, True, None]}) == '{"a": NaN, "b": [1, true, null]}'
    assert "(5000 digits)" in quote(HugeInteger("7" * 5000))
    assert len(quote(10**4000)) < 60


def test_ids_json_cannot_echo_are_refused_and_others_pass():
    for good in ["r1", 3, -2.5, True, None, ["a", {"b": 1}], "x" * 900]:
        assert check_id(good) == good
    for bad, message in [
        (math.nan, "id NaN cannot be written as JSON"),
        (math.inf, "id Infinity cannot be written as JSON"),
        ([1, -math.inf], "id [1, -Infinity] cannot be written as JSON (it holds -Infinity)"),
        (HugeInteger("1" * 4301), "id holds an integer of 4301 digits"),
        ("x" * 5000, "id is longer than 1000 characters"),
        (json.loads("[" * 40 + "]" * 40), "id is nested more than 32 levels deep"),
        (object(), "id must be a JSON value"),
    ]:
        with pytest.raises(ValueError) as info:
            check_id(bad)
        assert str(info.value).startswith(message), str(info.value)
        assert len(str(info.value)) < 400


# ---------------------------------------------------------------------------------------------------- a reading
def test_curvature_lists_and_tensors_follow_the_same_rules():
    u = curvature_tensor([[1, 2], None, [0.5, 1e4]], G)
    assert u.dtype == torch.float64 and u.shape == (G, 2)
    assert torch.isnan(u[1]).all() and u[2, 1] == 1e4  # absurd but finite: passed on
    t = torch.tensor([[1.0, 2.0], [math.nan, math.nan], [0.5, 1e4]], dtype=torch.float32)
    torch.testing.assert_close(curvature_tensor(t, G), u, equal_nan=True)
    torch.testing.assert_close(curvature_tensor(t.numpy(), G), u, equal_nan=True)
    cases = [
        ([[1, 2]], "curvature holds 1 gratings, the rod has 3"),
        ([[1, 2], [1], None], r"curvature\[1\] must be a pair \[ux, uy\]"),
        (
            [[1, 2], [math.nan, 1], None],
            r"curvature\[1\]\[0\] must be finite, got NaN \(for a grating without",
        ),
        ([[1, 2], [2e6, 1], None], r"curvature\[1\]\[0\] = 2000000.0 1/m is beyond the bound"),
        ([[1, 2], [10**400, 1], None], r"curvature\[1\]\[0\] must be a finite number.*overflows"),
        ([None, None, None], "all gratings are missing"),
        ("abc", "curvature must be an array of 3"),
        (torch.zeros(G, 3), r"must have shape \(3, 2\)"),
        (torch.tensor([[1.0, math.nan], [0, 0], [0, 0]]), r"curvature\[0\] has one NaN component"),
        (torch.tensor([[1.0, math.inf], [0, 0], [0, 0]]), r"curvature\[0\]\[1\] must be finite"),
        (torch.full((G, 2), 1e7), r"curvature\[0\]\[0\] = 10000000.0 1/m is beyond the bound"),
        (torch.full((G, 2), math.nan), "all gratings are missing"),
        (torch.zeros(G, 2, dtype=torch.bool), "must be a real tensor"),
    ]
    for value, message in cases:
        with pytest.raises(ValueError, match=message):
            curvature_tensor(value, G)


def test_parse_reading_checks_id_t_and_gratings_and_ignores_other_keys():
    r = parse_reading({"id": "a", "t": 2, "curvature": pairs(1, 2), "gratings": list(GRATINGS), "x": 1}, G, GRATINGS)
    assert (r.id, r.t, r.ok) == ("a", 2.0, True)
    with pytest.raises(ValueError, match="gratings .* do not match the rod's"):
        parse_reading({"curvature": pairs(1, 2), "gratings": [0.0, 0.2, 0.3]}, G, GRATINGS)
    with pytest.raises(ValueError, match="t must be finite, got NaN .t is a timestamp in seconds"):
        parse_reading({"t": math.nan, "curvature": pairs(1, 2)}, G)
    with pytest.raises(ValueError, match="missing 'curvature'"):
        parse_reading({"id": 1}, G)
    with pytest.raises(ValueError, match="id NaN"):
        parse_reading({"id": math.nan, "curvature": pairs(1, 2)}, G)


def test_to_reading_never_raises_and_keeps_ids_it_can_echo():
    """The Python stream API's entry: anything becomes a checked reading or an error reading."""
    ok = to_reading({"id": 7, "curvature": pairs(1, 2)}, G)
    assert ok.ok and ok.curvature.shape == (G, 2)
    assert to_reading(Reading("r", torch.ones(G, 2)), G).ok
    for item in [
        None,
        3,
        "text",
        [1, 2],
        {"curvature": None},
        {"id": math.nan, "curvature": pairs(1, 2)},
        Reading("r", curvature=object()),
        Reading(math.nan, error="upstream"),
        {"curvature": pairs(1e300, 0)},
    ]:
        r = to_reading(item, G)
        assert not r.ok and isinstance(r.error, str) and len(r.error) < 400
        assert r.id is None or r.id == "r"


def test_a_reading_checked_here_is_not_checked_again():
    """:func:`to_reading` takes a reading the checks made (:func:`parse_reading`, a file's readings) as it is: a
    stream reads each line through them, then takes what they yield through :func:`to_reading`. A reading made
    otherwise or changed (:func:`dataclasses.replace` makes a new one), or one for a rod with another number of
    gratings, is checked."""
    import dataclasses
    import io

    from torchrod.io.readings import iter_readings

    r = parse_reading({"id": "a", "curvature": pairs(1, 2)}, G)
    assert to_reading(r, G) is r and "_checked" not in repr(r)
    (read,) = iter_readings(io.StringIO(json.dumps({"id": "b", "curvature": pairs(1, 2)}) + "\n"), G)
    assert to_reading(read, G) is read and read.line == 1
    changed = dataclasses.replace(r, curvature=torch.full((G, 2), math.inf))
    assert "must be finite" in to_reading(changed, G).error
    assert "shape (4, 2)" in to_reading(r, G + 1).error
    made = Reading("c", torch.tensor(pairs(1, 2), dtype=torch.float64))
    assert to_reading(made, G) is not made and to_reading(made, G).ok


def test_csv_rows_read_like_json_lines():
    row = ["a", "0.5", "1", "2", "", "", "0.5", "-1e4"]
    r = parse_csv_row(row, G, line=3)
    assert (r.id, r.t, r.line) == ("a", 0.5, 3) and torch.isnan(r.curvature[1]).all()
    with pytest.raises(ValueError, match=r"curvature\[0\]\[0\] must be a number, got \"1_000\""):
        parse_csv_row(["a", "", "1_000", "2", "", "", "0", "0"], G)
    with pytest.raises(ValueError, match=r"curvature\[1\]\[1\] must be a number, got null \(an empty cell\)"):
        parse_csv_row(["a", "", "1", "2", "3", "", "0", "0"], G)
    with pytest.raises(ValueError, match="t must be a number"):
        parse_csv_row(["a", "0x10", "1", "2", "", "", "0", "0"], G)
    with pytest.raises(ValueError, match="expected 8 cells"):
        parse_csv_row(["a"], G)


@pytest.mark.parametrize("fmt", ["auto", "csv", "jsonl"])
def test_an_overlong_line_is_said_to_be_overlong_in_every_format(tmp_path, fmt):
    """A line over the bound is not kept, so it cannot decide the format either: the first line read does (a CSV
    row here, a JSON line there), and the overlong one is an error saying so, not 'got 0 cells'."""
    from torchrod.io.readings import iter_readings

    rows = [[0.1, -0.2]] * 14
    kind = "jsonl" if fmt == "jsonl" else "csv"
    good = json.dumps({"id": 7, "curvature": rows}) if kind == "jsonl" else "7,," + ",".join("0.1,-0.2" for _ in rows)
    path = tmp_path / "in.txt"
    path.write_text("x" * 5000 + "\n" + good + "\n")
    readings = list(iter_readings(path, 14, fmt=fmt, max_line=1000))
    assert [r.error for r in readings] == ["line 1: longer than 1000 bytes; not read", None]
    assert readings[1].id in (7, "7") and readings[1].curvature.shape == (14, 2)


@pytest.mark.parametrize("source", ["path", "text stream"])
def test_a_line_refused_for_its_length_keeps_the_id_it_starts_with(tmp_path, source):
    """The answer to an overlong line names it by the id at its start (a JSON line's ``{"id": ...``, a CSV row's
    first cell when it is the id): only the line's first bytes are kept, enough for an id."""
    import io

    from torchrod.io.readings import iter_readings

    rows = [[0.1, -0.2]] * 14
    pad = ",".join("0.1,-0.2" for _ in range(400))
    cases = {
        "jsonl": (
            [
                '{"id": "r-1", "curvature": [' + "[0.1, -0.2], " * 400 + "null]}",
                '{"id": [1, {"a": 2}], "pad": "' + "x" * 5000 + '"}',
                '{"t": 1, "id": 3, "pad": "' + "x" * 5000 + '"}',  # (the id is not at the start: not looked for)
                '{"id": NaN, "pad": "' + "x" * 5000 + '"}',  # (an id JSON cannot echo stays null)
                json.dumps({"id": 7, "curvature": rows}),
            ],
            ["r-1", [1, {"a": 2}], None, None, 7],
        ),
        "csv": (
            [
                "id,t," + ",".join(f"ux_{k},uy_{k}" for k in range(1, 15)),
                "r-1,0.5," + pad,
                '"r,2",0.5,' + pad,
                "7,0.5," + pad,
            ],
            ["r-1", "r,2", 7],
        ),
        "csv without a header": (
            ["r-1,0.5," + pad, "7,0.5," + pad, "7,," + ",".join("0.1,-0.2" for _ in rows)],
            ["r-1", None, 7],  # (a number in the first cell may be t or a value: only text names the line)
        ),
    }
    for fmt, (lines, ids) in cases.items():
        text = "\n".join(lines) + "\n"
        if source == "path":
            path = tmp_path / f"in-{len(ids)}.txt"
            path.write_text(text)
            given = path
        else:
            given = io.StringIO(text)
        readings = list(iter_readings(given, 14, fmt=fmt.split()[0], max_line=1000))
        assert [r.id for r in readings] == ids, fmt
        assert all(r.error == f"line {r.line}: longer than 1000 bytes; not read" for r in readings[:-1]), fmt
