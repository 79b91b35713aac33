"""The shared JSON-lines helpers: reading with per-line errors, batching, writing."""

from __future__ import annotations

import io
import json
import sys

import pytest

from torchrod.errors import MissingFileError
from torchrod.io.jsonl import (
    LineWriter,
    as_number,
    batched,
    check_keys,
    get_list,
    get_number,
    parse_records,
    read_lines,
    read_records,
)


def numbers(obj):
    """A parse function: the object's "x" as a finite float."""
    return get_number(obj, "x")


def test_read_lines_skips_blank_lines_but_counts_them(tmp_path):
    path = tmp_path / "in.jsonl"
    path.write_text('{"x": 1}\n\n   \n{"x": 2}\n{"x": 3}', encoding="utf-8")  # no final newline
    assert [n for n, _ in read_lines(path)] == [1, 4, 5]
    assert [n for n, _ in read_lines(str(path))] == [1, 4, 5]
    assert [n for n, _ in read_lines(io.StringIO('{"x": 1}\n\n{"x": 2}\n'))] == [1, 3]


def test_dash_reads_stdin_as_it_is_when_reading_starts(monkeypatch):
    lines = read_lines("-")  # nothing read yet
    monkeypatch.setattr(sys, "stdin", io.StringIO('{"x": 5}\n'))
    assert [r.value for r in parse_records(lines, numbers)] == [5.0]


def test_undecodable_bytes_fail_their_own_line_only(tmp_path):
    path = tmp_path / "in.jsonl"
    path.write_bytes(b'{"x": 1}\n\xff\xfe garbage\n{"x": 2}\n')
    records = list(read_records(path, numbers))
    assert [r.ok for r in records] == [True, False, True]
    assert records[1].error.startswith("line 2: not valid JSON")


def test_missing_file_raises_when_reading_starts(tmp_path):
    with pytest.raises(FileNotFoundError):
        list(read_lines(tmp_path / "nope.jsonl"))


def test_records_carry_ids_values_and_errors_in_order():
    text = "\n".join(  # noqa: FLY002
        [
            '{"id": "a", "x": 1.5}',
            "{broken",
            '{"id": 3, "x": "2"}',
            '{"id": ["any", "json"], "x": NaN}',
            '"just a string"',
            '{"x": 4}',
            '{"id": "k"}',
        ]
    )
    records = list(read_records(io.StringIO(text), numbers))
    assert [r.line for r in records] == [1, 2, 3, 4, 5, 6, 7]
    assert [r.id for r in records] == ["a", None, 3, ["any", "json"], None, None, "k"]
    assert [r.value for r in records] == [1.5, None, None, None, None, 4.0, None]
    assert [r.ok for r in records] == [True, False, False, False, False, True, False]
    assert records[1].error.startswith("line 2: not valid JSON")
    assert records[2].error == 'line 3: x must be a number, got a string "2"'
    assert records[3].error == "line 4: x must be finite, got NaN"
    assert records[4].error == 'line 5: expected a JSON object, got a string "just a string"'
    assert records[6].error == "line 7: missing 'x'"


def test_parse_errors_of_the_usual_kinds_become_records_others_propagate():
    def key_error(obj):
        return obj["absent"]

    def type_error(obj):
        return len(obj["x"])

    def bug(obj):
        raise RuntimeError("a bug, not bad input")

    line = [(1, '{"x": 1}')]
    assert next(parse_records(line, key_error)).error == "line 1: missing key 'absent'"
    assert "line 1: " in next(parse_records(line, type_error)).error
    with pytest.raises(RuntimeError):
        next(parse_records(line, bug))


def test_deeply_nested_json_is_an_error_line_not_a_crash():
    deep = "[" * 100_000 + "]" * 100_000
    (record,) = parse_records([(1, deep)], numbers)
    assert not record.ok


def test_batched_keeps_order_and_is_lazy():
    assert list(batched(range(7), 3)) == [[0, 1, 2], [3, 4, 5], [6]]
    assert list(batched([], 3)) == []

    def endless():
        k = 0
        while True:
            yield k
            k += 1

    assert next(batched(endless(), 2)) == [0, 1]
    for bad in (0, -1, 2.0):
        with pytest.raises(ValueError, match="batch size"):
            list(batched(range(3), bad))


def test_writer_writes_one_flushed_line_per_object_and_counts_errors():
    class Recorder(io.StringIO):
        flushes = 0

        def flush(self):
            self.flushes += 1
            super().flush()

    out = Recorder()
    writer = LineWriter(out)
    writer.write({"id": "a", "v": [1.0, 2.5]})
    writer.error(None, "line 2: bad")
    assert out.flushes == 2
    assert [json.loads(line) for line in out.getvalue().splitlines()] == [
        {"id": "a", "v": [1.0, 2.5]},
        {"id": None, "error": "line 2: bad"},
    ]
    assert (writer.lines, writer.errors) == (2, 1)


def test_writer_refuses_nan_and_writes_nothing_then():
    out = io.StringIO()
    writer = LineWriter(out)
    with pytest.raises(ValueError):
        writer.write({"v": float("nan")})
    assert out.getvalue() == "" and writer.lines == 0


def test_writer_defaults_to_stdout_at_write_time(capsys):
    writer = LineWriter()
    writer.write({"a": 1})
    assert capsys.readouterr().out == '{"a": 1}\n'


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (True, "must be a number"),
        ("1", "must be a number"),
        (None, "must be a number"),
        ([1], "must be a number"),
    ]
    + [(float("inf"), "must be finite"), (float("-inf"), "must be finite"), (float("nan"), "must be finite")],
)
def test_as_number_refuses_non_numbers(value, message):
    with pytest.raises(ValueError, match=message):
        as_number(value, "x")


def test_field_helpers():
    assert as_number(3, "x") == 3.0 and isinstance(as_number(3, "x"), float)
    assert get_number({"s": 0.5}, "s", "forces[0]") == 0.5
    with pytest.raises(ValueError, match=r"missing 'forces\[0\].s'"):
        get_number({}, "s", "forces[0]")
    assert get_list({"a": [1]}, "a") == [1]
    with pytest.raises(ValueError, match="a must be an array, got an object"):
        get_list({"a": {"b": 1}}, "a")
    obj = {"s": 1, "fx": 2}
    assert check_keys(obj, ("s",), ("fx", "fy")) is obj
    with pytest.raises(ValueError, match="f is missing 'fy'"):
        check_keys(obj, ("s", "fy"), where="f")
    with pytest.raises(ValueError, match="unknown key.*'fx'"):
        check_keys(obj, ("s",), where="f")
    with pytest.raises(ValueError, match="f must be an object, got a number"):
        check_keys(3, ("s",), where="f")


# ---------------------------------------------------------------------------------------------- hostile lines
def test_numbers_json_cannot_carry_become_error_records_with_their_line():
    """Integers over 4300 digits (Python's conversion limit) and non-finite ids fail their own line, naming the
    field; the other lines are read."""
    huge = "7" * 5000
    text = "\n".join(
        [
            '{"id": "a", "x": ' + huge + "}",
            '{"id": ' + huge + ', "x": 1}',
            '{"id": NaN, "x": 1}',
            '{"id": -Infinity, "x": 1}',
            '{"id": 1e999, "x": 1}',
            '{"id": "b", "other": ' + huge + ', "x": 2}',
            '{"id": "c", "x": ' + "1" * 400 + "}",
        ]
    )
    records = list(read_records(io.StringIO(text), numbers))
    assert [r.id for r in records] == ["a", None, None, None, None, "b", "c"]
    assert [r.value for r in records] == [None, None, None, None, None, 2.0, None]
    assert records[0].error.startswith("line 1: x must be a finite number, got an integer of 5000 digits")
    assert records[1].error.startswith("line 2: id holds an integer of 5000 digits")
    assert records[2].error.startswith("line 3: id NaN cannot be written as JSON")
    assert records[3].error.startswith("line 4: id -Infinity cannot be written as JSON")
    assert records[4].error.startswith("line 5: id Infinity cannot be written as JSON")
    assert "overflows a float" in records[6].error
    assert all(len(r.error) < 400 for r in records if not r.ok)


def test_deep_nesting_and_huge_values_give_short_messages():
    """A field nested 500 or 985 levels deep, or deeper than the decoder goes, fails its line without a
    RecursionError; a 10 MB value is quoted in at most about 100 characters."""
    lines = [
        '{"id": "d500", "x": ' + "[" * 500 + "]" * 500 + "}",
        '{"id": "d985", "x": ' + "[" * 985 + "]" * 985 + "}",
        '{"id": "d1e5", "x": ' + "[" * 100_000 + "]" * 100_000 + "}",
        '{"id": "big", "x": "' + "v" * 10_000_000 + '"}',
        '{"id": "keys", "x": 1, ' + ", ".join(f'"k{k}": 1' for k in range(1000)) + "}",
    ]
    records = list(parse_records(enumerate(lines, start=1), numbers))
    assert [r.ok for r in records] == [False, False, False, False, True]
    assert records[0].error.startswith("line 1: x must be a number, got an array [[[[")
    assert records[1].error.startswith("line 2: ")
    assert records[2].error == "line 3: not usable JSON: nested too deeply"
    assert records[3].error.startswith('line 4: x must be a number, got a string "vvvv')
    assert records[3].error.endswith("(10000000 characters)")
    assert all(len(r.error) < 300 for r in records if not r.ok)
    with pytest.raises(ValueError, match="unknown key"):
        check_keys(json.loads(lines[4]), ("x",), ("id",))
    assert len(str(pytest.raises(ValueError, check_keys, json.loads(lines[4]), ("x",), ("id",)).value)) < 400


def test_line_endings_bom_and_overlong_lines(tmp_path, monkeypatch):
    """A line ends at \\n only (a stray \\r stays in its line), a UTF-8 byte-order mark is dropped, and a line over
    MAX_LINE_BYTES is an error of its own line, read past without keeping it."""
    from torchrod.io import jsonl

    path = tmp_path / "in.jsonl"
    path.write_bytes(b'\xef\xbb\xbf{"x": 1}\r\n{"x": 2}\r{"x": 3}\n{"x": "' + b"y" * 5000 + b'"}\n{"x": 4}')
    monkeypatch.setattr(jsonl, "MAX_LINE_BYTES", 1000)
    records = list(read_records(path, numbers))
    assert [r.line for r in records] == [1, 2, 3, 4]
    assert records[0].value == 1.0 and records[3].value == 4.0
    assert records[1].error.startswith("line 2: not valid JSON")
    assert records[2].error == "line 3: longer than 1000 bytes; not read"


def test_writer_answers_with_an_error_line_when_json_cannot_hold_the_answer():
    out = io.StringIO()
    writer = LineWriter(out)
    assert writer.answer({"id": "a", "v": 1.0}, 1) is True
    assert writer.answer({"id": "b", "v": float("nan")}, 2) is False
    writer.error(float("nan"), "line 3: " + "m" * 10_000)
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    assert lines[0] == {"id": "a", "v": 1.0}
    assert lines[1]["id"] == "b" and lines[1]["error"].startswith("line 2: the answer cannot be written as JSON")
    assert lines[2]["id"] is None and len(lines[2]["error"]) < 700
    assert (writer.lines, writer.errors) == (3, 2)


def test_output_and_input_paths_are_checked_with_clear_errors(tmp_path):
    from torchrod.io.jsonl import check_input, open_output

    with (
        pytest.raises(ValueError, match="--out .*cannot write there"),
        open_output(str(tmp_path / "no" / "d.jsonl")),
    ):
        pass
    with pytest.raises(ValueError, match="--out .*cannot write there"), open_output(str(tmp_path)):
        pass
    source = tmp_path / "in.jsonl"
    source.write_text('{"x": 1}\n')
    with pytest.raises(ValueError, match="would erase the input"), open_output(str(source), [str(source)]):
        pass
    assert source.read_text() == '{"x": 1}\n'
    with open_output(str(tmp_path / "out.jsonl")) as fh:
        LineWriter(fh).write({"a": 1})
    assert (tmp_path / "out.jsonl").read_text() == '{"a": 1}\n'
    with open_output("-") as fh:
        assert fh is None
    # A missing input is the library's MissingFileError (a FileNotFoundError), naming the option and the path.
    with pytest.raises(MissingFileError, match="READINGS .*missing: no such file"):
        check_input(str(tmp_path / "missing"), "READINGS")
    with pytest.raises(ValueError, match="READINGS .*Is a directory"):
        check_input(str(tmp_path), "READINGS")


def test_sigterm_raises_terminated_inside_the_block_only():
    import os
    import signal

    from torchrod.io.jsonl import Terminated, interrupt_status, sigterm_as_interrupt

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated) as info, sigterm_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between bytecodes
            pass
    assert isinstance(info.value, KeyboardInterrupt) and interrupt_status(info.value) == 143
    assert interrupt_status(KeyboardInterrupt()) == 130
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_halted_reader_yields_the_lines_it_holds_then_ends(tmp_path):
    """After ReadControl.halt() the reader gives the complete lines already read from the file (one 64 KiB read)
    and stops reading: the flush after an interrupt answers what was read, no more."""
    from torchrod.io.jsonl import ReadControl

    line = '{"x": 1, "pad": "' + "p" * 80 + '"}\n'
    path = tmp_path / "big.jsonl"
    path.write_text(line * 2000)
    control = ReadControl()
    lines = read_lines(path, control)
    first = next(lines)
    control.halt()
    rest = list(lines)
    assert first[0] == 1 and 1 + len(rest) == 2**16 // len(line) < 2000
    assert [n for n, _ in rest] == list(range(2, 2 + len(rest)))


def test_a_line_of_tens_of_megabytes_is_refused_in_bounded_memory(tmp_path):
    """A 40 MB line (an array of small numbers: decoded, about 20 bytes of Python objects per byte of text) is an
    error line read past in chunks: the reader never holds more than MAX_LINE_BYTES of it, and the next line is
    read. Before, lines up to 256 MiB were decoded whole, and a 72 MB one took gigabytes."""
    import tracemalloc

    from torchrod.io.jsonl import MAX_LINE_BYTES

    size = 40_000_000
    path = tmp_path / "long.jsonl"
    with open(path, "w") as fh:
        fh.write('{"id": 1, "curvature": [' + "[0,0]," * (size // 6) + "[0,0]]}\n")
        fh.write('{"id": 2, "x": 1}\n')
    tracemalloc.start()
    try:
        records = list(read_records(path, lambda obj: obj.get("x")))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert records[0].error == f"line 1: longer than {MAX_LINE_BYTES} bytes; not read"
    assert records[1].ok and records[1].value == 1
    assert peak < MAX_LINE_BYTES + 4 * 2**20 < size
