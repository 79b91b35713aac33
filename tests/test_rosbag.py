"""ROS bags in and out of ``torchrod stream`` (torchrod.io.rosbag), on bags the tests write themselves."""

from __future__ import annotations

import json
import math
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
