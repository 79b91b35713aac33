"""Shape-sensing record streams (torchrod.io.fbgs, torchrod.io.tcp): the record's fields, and a replay server on
localhost that the stream reads: a closed connection answered in order, a truncated record as one error line, a
record with another grating count as that record's error, nothing already read lost; the same bytes from a file."""

from __future__ import annotations

import json
import math
import re
import socket
import threading
from pathlib import Path

import pytest
import torch

import torchrod as tr
from torchrod.cli import main
from torchrod.io.fbgs import RecordError, parse_record, read_records

F64 = torch.float64
ROD = tr.presets.nitinol290()
G = ROD.num_gratings


def _fields(sample: int, u: torch.Tensor, *, label: str = "Curvature [1/cm]", per_cm: float = 100.0) -> list[str]:
    """The tab-separated fields of one record as the public drivers describe it: date, time, sample number, four
    channels (number, grating count, four status values, peaks, powers), the curvature block, the angle block and
    the shape blocks (skipped by the reader)."""
    n = u.shape[0]
    kappa = torch.linalg.vector_norm(u, dim=-1) / per_cm
    phi = torch.atan2(u[:, 1], u[:, 0])
    fields = ["01.03.2024", f"10:00:{sample:02d}.500", str(sample), "4"]
    for m in range(4):
        fields += [str(m + 1), str(n), "0", "0", "0", "1"]
        fields += [f"{1530 + 2.5 * k + 0.01 * m:.4f}" for k in range(n)] + ["-31.25"] * n
    fields += [label, *map(repr, kappa.tolist()), "Angle [rad]", *map(repr, phi.tolist())]
    for axis in "xyz":
        fields += [f"Shape {axis} [cm]", "3", "0.0", "0.1", "0.2"]
    return fields


def _record(sample: int, u: torch.Tensor, **kw) -> bytes:
    payload = ("\t".join(_fields(sample, u, **kw)) + "\r\n").encode("ascii")
    return len(payload).to_bytes(4, "big") + payload


class Replay:
    """A one-connection TCP server on 127.0.0.1 that sends ``chunks`` and closes; bounded in time."""

    def __init__(self, chunks: list[bytes]) -> None:
        self.chunks = chunks
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(20.0)
        self.address = f"tcp://127.0.0.1:{self.server.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self.server.accept()
        except OSError:
            return
        with conn:
            for chunk in self.chunks:
                conn.sendall(chunk)

    def __enter__(self) -> Replay:
        return self

    def __exit__(self, *exc) -> None:
        self.server.close()
        self.thread.join(timeout=20.0)
        assert not self.thread.is_alive()


@pytest.fixture(scope="module")
def curvature():
    loads = tr.PointForces(
        s=torch.tensor([[0.12, 0.24], [0.07, 0.2], [0.15, 0.27]], dtype=F64),
        f=torch.tensor([[[0.4, -0.9], [0.3, 0.2]], [[-1.2, 0.1], [0.0, 0.6]], [[0.5, 0.5], [-0.4, 0.1]]], dtype=F64),
    )
    u = tr.simulate(ROD, loads).grating_curvature
    return u + 0.05 * torch.randn(u.shape, dtype=F64, generator=torch.Generator().manual_seed(1))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, curvature):
    """The answers to the same curvature given as JSON lines (ids the sample numbers)."""
    path = tmp_path_factory.mktemp("ref") / "u.jsonl"
    path.write_text("".join(json.dumps({"id": b, "curvature": curvature[b].tolist()}) + "\n" for b in range(3)))
    out = path.with_suffix(".out")
    assert main(_stream(str(path), "lines", out)) == 0
    return {a["id"]: a for a in _answers(out)}


def _stream(source: str, protocol: str, out: Path) -> list[str]:
    return ["stream", "--rod", "nitinol290", "--checkpoint", "none", "--input", source, "--protocol", protocol,
            "--noise", "0.05", "--time-budget-ms", "1e6", "--out", str(out)]  # fmt: skip


def _answers(out: Path) -> list[dict]:
    return [json.loads(x) for x in out.read_text().splitlines()]


def _same(answer: dict, ref: dict) -> None:
    assert answer["num_forces"] == ref["num_forces"] == 2 and answer["status"] == ref["status"]
    for fa, fb in zip(answer["forces"], ref["forces"], strict=True):
        for key in ("s", "fx", "fy"):
            assert fa[key] == pytest.approx(fb[key], rel=1e-6, abs=1e-9)


# ---------------------------------------------------------------------------------------------------- the record
def test_record_fields(curvature):
    u = curvature[0]
    payload = _record(7, u)[4:]
    sample, t, pairs = parse_record(payload, G)
    assert sample == 7 and t == pytest.approx(36007.5)
    got = torch.tensor([[k * math.cos(p), k * math.sin(p)] for k, p in pairs], dtype=F64)
    assert torch.allclose(got, u, rtol=1e-12, atol=1e-12)  # 1/cm read as such, back in 1/m
    in_m = parse_record(_record(7, u, label="Curvature [1/m]", per_cm=1.0)[4:], G)[2]
    assert torch.allclose(torch.tensor(in_m, dtype=F64), torch.tensor(pairs, dtype=F64), rtol=1e-12, atol=0)
    with pytest.raises(RecordError, match=r"says 1/cm, but the curvature unit was given as 1/m"):
        parse_record(payload, G, unit="1/m")
    with pytest.raises(RecordError, match="14 gratings, the rod has 13"):
        parse_record(payload, G - 1)
    fields = _fields(7, u)
    no_block = "\t".join(f for f in fields if not f.startswith("Curvature")).encode()
    with pytest.raises(RecordError, match="no curvature block"):
        parse_record(no_block, G)
    with pytest.raises(RecordError, match="ends before its channel 2's number"):
        parse_record("\t".join(fields[:30]).encode(), G)
    with pytest.raises(RecordError, match=r"field 3 \(sample number\) must be an integer"):
        parse_record("\t".join([*fields[:2], "x", *fields[3:]]).encode(), G)
    with pytest.raises(RecordError, match="not ASCII"):
        parse_record(b"\xff\t1", G)


def _payload(fields: list[str]) -> bytes:
    payload = "\t".join(fields).encode("ascii")
    return len(payload).to_bytes(4, "big") + payload


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"Curvature [1/cm]": (2, "NaN")}, r"grating 2's curvature \(field \d+\) is \"NaN\", not a finite number"),
        ({"Curvature [1/cm]": (1, "-inf")}, r"grating 1's curvature \(field \d+\) is \"-inf\", not a finite number"),
        ({"Angle [rad]": (14, "nan")}, r"grating 14's bend angle \(field \d+\) is \"nan\", not a finite number"),
        ({1: "99:99:99"}, r"field 2 \(time\) \"99:99:99\" is not a time of day"),
        ({1: "24:00:00.000"}, r"field 2 \(time\) \"24:00:00.000\" is not a time of day"),
    ],
)
def test_a_record_that_cannot_be_used_is_named_by_its_sample_number(curvature, change, message):
    """NaN curvature was reported as "0 gratings", a time of 99:99:99 was read as 27 h, and every error answer had
    "id": null although the sample number had been read."""
    fields = _fields(7, curvature[0])
    for where, value in change.items():
        if isinstance(where, str):
            k, value = value
            fields[fields.index(where) + k] = value
        else:
            fields[where] = value
    (got,) = read_records(_reader(_payload(fields)), G)
    assert got.id == 7 and got.t is None and re.match("record 1: " + message, got.error), got.error
    with pytest.raises(tr.errors.ReadingError, match=message):
        parse_record(_payload(fields)[4:], G)
    (fewer,) = read_records(_reader(_record(8, curvature[0][:-1])), G)
    assert fewer.id == 8 and fewer.error == "record 1: 13 gratings, the rod has 14: is this the rod's sensor?"
    (unread,) = read_records(_reader(_payload([*fields[:2], "x", *fields[3:]])), G)
    assert unread.id is None and "field 3 (sample number) must be an integer" in unread.error


def _reader(*chunks: bytes):
    """A ``read(n)`` that gives ``chunks`` one by one, then the end."""
    rest = list(chunks)
    return lambda n: rest.pop(0) if rest else b""


def test_framing_errors_stop_once(curvature):
    (only,) = read_records(_reader(b"\x00\x00\x00\x00", _record(0, curvature[0])), G)
    assert only.error.startswith("record 1: announces 0 bytes")
    (cut,) = read_records(_reader(b"\x00\x00"), G)
    assert cut.error == "record 1: truncated: the stream ended inside its 4-byte length"
    good, halted = list(read_records(_reader(_record(0, curvature[0]), b"\x00\x00", None), G)), None
    assert len(good) == 1 and good[0].ok and halted is None  # a read that says stop drops the partial record


# ---------------------------------------------------------------------------------------------------- the stream
def test_closed_connection_is_answered_in_order(tmp_path, curvature, reference):
    records = [_record(b, curvature[b]) for b in range(3)]
    joined = b"".join(records)
    chunks = [joined[k : k + 97] for k in range(0, len(joined), 97)]  # records split across TCP segments
    out = tmp_path / "out.jsonl"
    with Replay(chunks) as server:
        assert main(_stream(server.address, "fbgs", out)) == 0
    answers = _answers(out)
    assert [a["id"] for a in answers] == [0, 1, 2] and [a["t"] for a in answers] == [36000.5, 36001.5, 36002.5]
    for a in answers:
        _same(a, reference[a["id"]])


def test_truncated_and_wrong_records_lose_nothing_read(tmp_path, curvature, reference):
    wrong = _record(1, curvature[1][:-1])  # 13 gratings
    cut = _record(3, curvature[2])[:-40]  # the connection closes inside this record
    out = tmp_path / "out.jsonl"
    with Replay([_record(0, curvature[0]), wrong, _record(2, curvature[2]), cut]) as server:
        assert main(_stream(server.address, "fbgs", out)) == 1
    answers = _answers(out)
    assert len(answers) == 4
    _same(answers[0], reference[0])
    assert answers[1] == {"id": 1, "error": "record 2: 13 gratings, the rod has 14: is this the rod's sensor?"}
    assert answers[2]["id"] == 2 and answers[2]["num_forces"] == 2
    assert answers[3]["error"].startswith("record 4: truncated: ")
    # the same bytes recorded to a file read the same (estimate reads them too)
    recording = tmp_path / "run.fbgs"
    recording.write_bytes(_record(0, curvature[0]) + wrong + _record(2, curvature[2]) + cut)
    again = tmp_path / "again.jsonl"
    assert main(_stream(str(recording), "fbgs", again)) == 1
    replayed = _answers(again)
    for a, b in zip(replayed, answers, strict=True):
        a.pop("latency_ms", None), b.pop("latency_ms", None)
        assert a == b
    assert main(["estimate", "nitinol290", str(recording), "--protocol", "fbgs", "--noise", "0.05", "--quiet",
                 "--out", str(tmp_path / "e.jsonl")]) == 1  # fmt: skip
    estimated = _answers(tmp_path / "e.jsonl")
    assert [a.get("id") for a in estimated] == [0, 1, 2, None]  # the cut record's sample number was not read


def test_json_lines_over_tcp_and_an_unreachable_server(tmp_path, capsys, curvature, reference):
    lines = "".join(json.dumps({"id": b, "curvature": curvature[b].tolist()}) + "\n" for b in range(2))
    out = tmp_path / "out.jsonl"
    with Replay([lines.encode()[:50], lines.encode()[50:]]) as server:
        assert main(_stream(server.address, "lines", out)) == 0
    answers = _answers(out)
    assert [a["id"] for a in answers] == [0, 1]
    _same(answers[1], reference[1])
    with socket.create_server(("127.0.0.1", 0)) as closed:
        port = closed.getsockname()[1]
    assert main(_stream(f"tcp://127.0.0.1:{port}", "fbgs", out)) == 2
    assert "cannot connect" in capsys.readouterr().err
    assert main(_stream("tcp://127.0.0.1", "fbgs", out)) == 2
    assert "is not a TCP address" in capsys.readouterr().err
