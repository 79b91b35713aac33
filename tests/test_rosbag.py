"""ROS bags in and out of ``torchrod stream`` (torchrod.io.rosbag), on bags the tests write themselves."""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main

pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from torchrod.io.rosbag import BagSource, write_readings  # noqa: E402

F64 = torch.float64
TOPIC = "/fbg/curvature"


@pytest.fixture(scope="module")
def readings():
    """Four readings (t [s], curvature pairs or None): two clean ones, one with a grating missing, one bad."""
    rod = tr.presets.nitinol290()
    loads = tr.PointForces(
        s=torch.tensor([[0.15, 0.25], [0.2, 0.29]], dtype=F64),
        f=torch.tensor([[[0.5, -0.3], [0.2, 0.4]], [[0.0, 0.8], [0.0, 0.0]]], dtype=F64),
    )
    u = tr.simulate(rod, loads).grating_curvature.tolist()
    return [
        (1.0, u[0]),
        (1.01, [None, *u[1][1:]]),
        (1.02, [[1.0, math.nan], *u[1][1:]]),  # half a grating missing: an error in its place
        (1.03, u[0]),
    ]


def _messages(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for connection, stamp, raw in reader.messages(connections=reader.connections):
            out.setdefault(connection.topic, []).append((stamp, reader.deserialize(raw, connection.msgtype)))
    return out


@pytest.mark.parametrize("name", ["run", "run.bag"])  # a ROS 2 directory, a ROS 1 file
def test_bag_round_trip(tmp_path: Path, capsys, readings, name):
    bag, out_bag = tmp_path / name, tmp_path / f"out_{name}"
    write_readings(bag, TOPIC, readings)
    source = list(BagSource(bag, TOPIC, 14))
    assert [r.id for r in source] == [0, 1, 2, 3]
    assert [r.t for r in source] == pytest.approx([1.0, 1.01, 1.02, 1.03])
    assert torch.isnan(source[1].curvature[0]).all() and source[2].error is not None
    # One batch whatever the source's pace (the same starts, so the same answers from the bag and from JSON lines).
    argv = [
        "--rod",
        "nitinol290",
        "--noise",
        "0.01",
        "--checkpoint",
        "none",
        "--max-forces",
        "2",
        "--max-latency-ms",
        "10000",
    ]
    status = main(["stream", *argv, "--input", str(bag), "--topic", TOPIC, "--output-bag", str(out_bag)])
    answers = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert status == 1  # one message failed
    assert len(answers) == 4 and "one NaN value" in answers[2]["error"] and answers[2]["id"] == 2
    assert [a["num_forces"] for a in (answers[0], answers[1], answers[3])] == [2, 1, 2]
    # The same readings as JSON lines give the same estimates.
    lines = tmp_path / "same.jsonl"
    lines.write_text("".join(json.dumps({"id": i, "curvature": readings[i][1]}) + "\n" for i in (0, 1, 3)))
    assert main(["stream", *argv, "--input", str(lines)]) == 0
    again = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    for a, b in zip(again, (answers[0], answers[1], answers[3]), strict=True):
        assert a["forces"] == b["forces"]
    # The output bag: every topic has one message per reading, stamped with the reading's t.
    msgs = _messages(out_bag)
    assert set(msgs) == {
        "/torchrod/estimate",
        *(f"/torchrod/contact_{k}/{kind}" for k in range(2) for kind in ("wrench", "arc_length")),
    }
    for topic, items in msgs.items():
        assert [stamp for stamp, _ in items] == [round(t * 1e9) for t, _ in readings], topic
    assert [json.loads(m.data) for _, m in msgs["/torchrod/estimate"]] == answers
    for i, answer in enumerate(answers):
        forces = answer.get("forces", [])
        for k in range(2):
            _, wrench = msgs[f"/torchrod/contact_{k}/wrench"][i]
            _, arc = msgs[f"/torchrod/contact_{k}/arc_length"][i]
            assert wrench.header.stamp.sec == 1 and wrench.header.frame_id == "torchrod_body"
            if k < len(forces):
                assert (wrench.wrench.force.x, wrench.wrench.force.y, arc.data) == (
                    forces[k]["fx"],
                    forces[k]["fy"],
                    forces[k]["s"],
                )
            else:
                assert math.isnan(wrench.wrench.force.x) and math.isnan(arc.data)
    # A bag is never overwritten.
    assert main(["stream", *argv, "--input", str(bag), "--topic", TOPIC, "--output-bag", str(out_bag)]) == 2
    assert "exists already" in capsys.readouterr().err


def test_bag_errors(tmp_path: Path, capsys, readings):
    bag = tmp_path / "run"
    write_readings(bag, TOPIC, readings[:1])
    base = ["stream", "--rod", "nitinol290", "--noise", "0.1", "--checkpoint", "none"]
    assert main([*base, "--input", str(bag), "--topic", "/other"]) == 2
    assert "no topic '/other'" in capsys.readouterr().err and TOPIC
    assert main([*base, "--input", str(tmp_path / "nothing"), "--topic", TOPIC]) == 2
    assert "no such bag" in capsys.readouterr().err
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all")
    assert main([*base, "--input", str(junk), "--topic", TOPIC]) == 2
    assert "not a readable ROS bag" in capsys.readouterr().err
    assert main([*base, "--topic", TOPIC]) == 2  # stdin is not a bag
    assert "give its path with --input" in capsys.readouterr().err
    # Wrong message length: an error answer in its place.
    short = tmp_path / "short"
    write_readings(short, TOPIC, [(0.5, readings[0][1][:5])])
    assert main([*base, "--input", str(short), "--topic", TOPIC]) == 1
    assert "holds 10 values" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------------- faults
def _stream_lines(path: Path, readings, times) -> None:
    """JSON lines of the readings' curvature at the given times [s]."""
    curvature = [u for _, u in readings if all(p is None or not math.isnan(p[1]) for p in u)]
    lines = [json.dumps({"id": k, "t": t, "curvature": curvature[k % len(curvature)]}) for k, t in enumerate(times)]
    path.write_text("\n".join(lines) + "\n")


BASE = ["stream", "--rod", "nitinol290", "--noise", "0.05", "--checkpoint", "none", "--max-forces", "2"]


@pytest.mark.parametrize("name", ["run", "run.bag"])
def test_a_time_stamp_the_bag_cannot_hold_is_an_error_line_for_that_reading(tmp_path, capsys, readings, name):
    """t = 2^40 s and t in milliseconds since the epoch (1.7e12) fit neither format: those readings are answered
    with an error line (saying what t may be), every other reading is answered and written, and the bag is
    readable with its topics aligned."""
    lines, out_bag = tmp_path / "in.jsonl", tmp_path / name
    times = [1.0, 1.01, 2.0**40, 1.03, 1.7e12, 1.05]
    _stream_lines(lines, readings, times)
    status = main([*BASE, "--input", str(lines), "--output-bag", str(out_bag)])
    answers = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert status == 1
    assert [a["id"] for a in answers] == list(range(6))
    for k in (2, 4):
        assert "cannot be a time stamp" in answers[k]["error"] and answers[k]["t"] == times[k]
    assert "milliseconds" in answers[4]["error"] and "1.7e+09" in answers[4]["error"]
    good = [0, 1, 3, 5]
    assert all("forces" in answers[k] for k in good)
    msgs = _messages(out_bag)
    for topic, items in msgs.items():
        assert [stamp for stamp, _ in items] == [round(times[k] * 1e9) for k in good], topic
    assert [json.loads(m.data) for _, m in msgs["/torchrod/estimate"]] == [answers[k] for k in good]


@pytest.mark.parametrize("ros1", [True, False])
def test_bag_time_stamps_hold_what_the_format_holds(tmp_path, ros1):
    from torchrod.errors import ReadingError
    from torchrod.io.rosbag import BagWriter

    with BagWriter(tmp_path / ("b.bag" if ros1 else "b"), 1) as bag:
        assert bag.stamp(1.5) == 1_500_000_000 and bag.stamp(None) == 0
        assert bag.stamp(2.0**31 - 1) == (2**31 - 1) * 10**9
        if ros1:
            assert bag.stamp(2.0**31) == 2**31 * 10**9
        for t in ((2.0**32,) if ros1 else (2.0**31,)) + (-1.0, 2.0**40, math.inf):
            with pytest.raises(ReadingError, match="cannot be a time stamp"):
                bag.write({"id": 0, "forces": []}, t)
        bag.write({"id": 0, "forces": []}, 3.0)
    msgs = _messages(tmp_path / ("b.bag" if ros1 else "b"))
    assert all([stamp for stamp, _ in items] == [3 * 10**9] for items in msgs.values())


def test_a_ros1_bag_damaged_in_the_middle_answers_what_it_could_read_then_one_error(tmp_path, capsys, readings):
    bag = tmp_path / "run.bag"
    write_readings(bag, TOPIC, [(1.0 + 0.01 * k, readings[0][1]) for k in range(200)])
    size = bag.stat().st_size
    with open(bag, "r+b") as fh:
        fh.seek(size // 2)
        fh.write(bytes(range(256)) * 8)
    status = main([*BASE, "--input", str(bag), "--topic", TOPIC])
    out, err = capsys.readouterr()
    answers = [json.loads(x) for x in out.splitlines()]
    assert status == 2
    assert 10 < len(answers) < 200 and [a["id"] for a in answers] == list(range(len(answers)))
    # (the message that the damage starts in may be read as garbage: an error answer of its own)
    assert all(a["num_forces"] == 2 for a in answers[:-1]) and ("error" in answers[-1] or "forces" in answers[-1])
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "damaged" in lines[0] and f"message {len(answers)}" in lines[0]


def _failing(real, exc, after: int):
    """``real`` (a writer's method), raising ``exc`` from its call number ``after`` on."""
    calls = [0]

    def write(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] > after:
            raise exc
        return real(self, *args, **kwargs)

    return write


@pytest.mark.parametrize("name", ["run", "run.bag"])
def test_a_full_disk_under_the_output_bag_is_one_clear_error(tmp_path, capsys, monkeypatch, readings, name):
    """The storage refusing a write (injected: ENOSPC from the ROS 1 file, SQLite's "database or disk is full",
    at the write and again when the bag is closed): one error line, every reading still answered, status 1."""
    import errno
    import sqlite3

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2

    writer = Writer1 if name.endswith(".bag") else Writer2
    full = (
        OSError(errno.ENOSPC, "No space left on device")
        if writer is Writer1
        else sqlite3.OperationalError("database or disk is full")
    )
    monkeypatch.setattr(writer, "write", _failing(writer.write, full, after=7 * 3))  # 3 answers of 7 messages
    monkeypatch.setattr(writer, "close", _failing(writer.close, full, after=0))
    lines = tmp_path / "in.jsonl"
    _stream_lines(lines, readings, [1.0 + 0.01 * k for k in range(8)])
    status = main([*BASE, "--input", str(lines), "--output-bag", str(tmp_path / name)])
    out, err = capsys.readouterr()
    assert status == 1
    assert [json.loads(x)["id"] for x in out.splitlines()] == list(range(8))
    errors = [line for line in err.splitlines() if line.strip()]
    assert len(errors) == 1 and "--output-bag" in errors[0] and ("No space" in errors[0] or "disk is full" in errors[0])
    assert "Traceback" not in err


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="mounting a tmpfs needs root")
@pytest.mark.parametrize("name", ["run", "run.bag"])
def test_a_really_full_disk_under_the_output_bag(tmp_path, capsys, readings, name):
    """The same on a real 256 KiB tmpfs, where this machine lets the test mount one."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)], capture_output=True, check=False
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        lines = tmp_path / "in.jsonl"
        _stream_lines(lines, readings, [1.0 + 0.001 * k for k in range(1500)])
        status = main([*BASE, "--input", str(lines), "--output-bag", str(disk / name), "--max-forces", "1"])
        out, err = capsys.readouterr()
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)  # (lazy: a file left open cannot keep it)
    assert status == 1
    assert len(out.splitlines()) == 1500
    errors = [line for line in err.splitlines() if line.strip()]
    assert len(errors) == 1 and "--output-bag" in errors[0] and ("No space" in errors[0] or "disk is full" in errors[0])
