"""The table of input formats (:mod:`torchrod.io.formats`) is what ``--format``, ``--protocol`` and ROS bags read:
an interrogator's format is one entry of it."""

from __future__ import annotations

import argparse
import types

import pytest

from torchrod.cli.commands import add_input_options, reading_source
from torchrod.io import formats, sources
from torchrod.io.formats import INPUT_FORMATS, InputFormat
from torchrod.io.reading import Reading


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {action.dest: action for action in parser._actions}


def test_the_options_and_the_bags_offer_the_table() -> None:
    parser = argparse.ArgumentParser()
    add_input_options(parser)
    options = _options(parser)
    assert tuple(options["format"].choices) == ("auto", "jsonl", "csv", "peaks")
    assert tuple(options["protocol"].choices) == ("lines", "fbgs")
    from torchrod.io.rosbag import MESSAGE_TYPE

    assert list(formats.bag_formats()) == [MESSAGE_TYPE]
    assert sources.FORMATS == sources.format_names()


def _tsv(lines, parse, options):
    from torchrod.io.csv_rows import csv_records

    rows = ((number, text.replace("\t", ",")) for number, text in lines)
    return csv_records(rows, options.num_gratings, options.quantity, options.fibre, parse)


def test_a_new_line_format_is_one_entry(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(INPUT_FORMATS, "tsv", InputFormat("tab-separated rows", lines=_tsv, extensions=(".tsv",)))
    path = tmp_path / "readings.tsv"
    path.write_text("id\tux_1\tuy_1\nr1\t1.5\t-2\n")
    for fmt in ("tsv", "auto"):  # by name, and by the extension
        (reading,) = sources.iter_readings(path, 1, fmt=fmt)
        assert reading.ok and reading.id == "r1" and reading.curvature.tolist() == [[1.5, -2.0]]
    parser = argparse.ArgumentParser()
    add_input_options(parser)
    assert parser.parse_args(["--format", "tsv"]).format == "tsv"
    assert "tsv (tab-separated rows)" in _options(parser)["format"].help
    with pytest.raises(ValueError, match=r"format must be one of auto, jsonl, csv, peaks, tsv, got 'ssv'"):
        list(sources.iter_readings(path, 1, fmt="ssv"))


def test_a_new_protocol_is_one_entry(monkeypatch) -> None:
    seen = []

    def source(path, options):
        seen.append((path, options.num_gratings, options.unit))
        return [Reading("a", error="line 1: only a test")]

    monkeypatch.setitem(INPUT_FORMATS, "probe", InputFormat("probe records", "records of a test", protocol=source))
    parser = argparse.ArgumentParser()
    add_input_options(parser)
    args = parser.parse_args(["--protocol", "probe"])
    assert "probe: records of a test" in _options(parser)["protocol"].help
    args.curvature_unit = "1/mm"
    rod = types.SimpleNamespace(num_gratings=3, gratings=(0.1, 0.2, 0.3), fibre=None)
    assert [r.id for r in reading_source(args, rod, "RUN")] == ["a"]
    assert seen == [("RUN", 3, "1/mm")]


def test_an_entry_is_exactly_one_kind() -> None:
    with pytest.raises(TypeError, match="exactly one"):
        InputFormat("nothing")
    with pytest.raises(TypeError, match="exactly one"):
        InputFormat("both", lines=_tsv, protocol=lambda source, options: [])
    with pytest.raises(TypeError, match="exactly one"):
        InputFormat("a bag type without its reader", bag_type="std_msgs/msg/Float32MultiArray")


def test_the_readings_module_still_offers_every_name_from_its_new_home() -> None:
    """``torchrod.io.readings`` gathers the names of the modules it was split into: old imports keep working and
    give the same objects."""
    from torchrod.io import csv_rows, numbers, quantities, reading, readings, values

    homes = (csv_rows, numbers, quantities, reading, sources, values)
    for name in readings.__all__:
        assert any(getattr(home, name, None) is getattr(readings, name) for home in homes), name
    assert readings.ReadingSource is sources.ReadingSource and readings.Reading is reading.Reading
