"""``torchrod estimate``, ``torchrod evaluate`` and ``torchrod bench estimate`` through ``main()``."""

from __future__ import annotations

import io
import json
import math

import torch

import torchrod as tr
from torchrod.cli import main


def _reading_lines(rod: tr.Rod) -> list[dict]:
    cases = [[(0.2, 0.3, 0.0)], [(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)]]
    loads = tr.PointForces.from_lists(cases, max_forces=2)
    u = tr.simulate(rod, loads).grating_curvature.tolist()
    return [{"id": f"r{b}", "curvature": u[b], "gratings": list(rod.gratings)} for b in range(2)]


def test_estimate_lines_and_errors(rod, tmp_path, capsys):
    good = _reading_lines(rod)
    holed = dict(
        good[1],
        id="holed",
        curvature=[None if k in (3, 8) else row for k, row in enumerate(good[1]["curvature"])],
    )
    lines = [
        json.dumps(good[0]),
        "this is not json",
        json.dumps({"id": "short", "curvature": good[0]["curvature"][:5]}),
        json.dumps(holed),
        '{"id": "nan", "curvature": ' + json.dumps(good[0]["curvature"][:13])[:-1] + ", [NaN, 0.0]]}",
        json.dumps({"id": "empty", "curvature": [None] * rod.num_gratings}),
        json.dumps(
            {"id": "other-rod", "curvature": good[0]["curvature"], "gratings": [0.0] * rod.num_gratings}
        ),
        "",
        json.dumps(good[1]),
    ]
    path = tmp_path / "readings.jsonl"
    path.write_text("\n".join(lines) + "\n")
    status = main(["estimate", "--rod", "nitinol290", "--noise", "0.01", "--batch-size", "3", str(path)])
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert status == 1
    assert [o.get("id") for o in out] == ["r0", None, "short", "holed", "nan", "empty", "other-rod", "r1"]
    errors = {o["id"]: o["error"] for o in out if "error" in o}
    assert set(errors) == {None, "short", "nan", "empty", "other-rod"}
    assert errors[None].startswith("line 2: not valid JSON")
    assert "5 gratings" in errors["short"] and "finite" in errors["nan"]
    assert "all gratings are missing" in errors["empty"] and "do not match" in errors["other-rod"]
    r0, holed_out, r1 = out[0], out[3], out[7]
    assert r0["num_forces"] == 1 and r1["num_forces"] == 2 and holed_out["num_forces"] == 2
    f = r0["forces"][0]
    assert math.isclose(f["s"], 0.2, abs_tol=1e-5) and math.isclose(f["fx"], 0.3, rel_tol=1e-4)
    assert math.isclose(f["magnitude"], math.hypot(f["fx"], f["fy"]))
    assert [g["s"] for g in r1["forces"]] == sorted(g["s"] for g in r1["forces"])
    for o in (r0, holed_out, r1):
        assert set(o) == {
            "id",
            "num_forces",
            "forces",
            "loss",
            "converged",
            "iterations",
            "poorly_determined",
            "time_ms",
        }
        assert all(set(g) == {"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"} for g in o["forces"])
        assert o["time_ms"] > 0 and o["converged"] is True


def test_estimate_stdin_fixed_count_and_clean_exit(rod, monkeypatch, capsys):
    text = "\n".join(json.dumps(x) for x in _reading_lines(rod)) + "\n"
    monkeypatch.setattr("sys.stdin", io.StringIO(text))
    status = main(["estimate", "--rod", "nitinol290", "--num-forces", "2", "--quiet", "-"])
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert status == 0
    assert [o["num_forces"] for o in out] == [2, 2]
    # the paper's rule by option
    monkeypatch.setattr("sys.stdin", io.StringIO(text))
    assert main(["estimate", "--rod", "nitinol290", "--selection", "threshold", "--threshold", "3", "-"]) == 0
    assert [json.loads(x)["num_forces"] for x in capsys.readouterr().out.splitlines()] == [1, 2]


def test_estimate_bad_option(capsys, tmp_path):
    path = tmp_path / "r.jsonl"
    path.write_text("")
    assert main(["estimate", "--rod", "no-such-rod", str(path)]) == 2
    assert "neither a rod file nor a preset" in capsys.readouterr().err


def test_evaluate_prints_a_table(capsys):
    threads = torch.get_num_threads()
    try:
        status = main(
            ["evaluate", "--count-per-cell", "6", "--noise", "0,0.1", "--max-forces", "2", "--seed", "3"]
        )
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out.splitlines()
    assert status == 0
    rows = [line.split() for line in out if line.strip() and line.split()[0].isdigit()]
    assert [(r[0], r[1]) for r in rows] == [("1", "0"), ("1", "0.1"), ("2", "0"), ("2", "0.1")]
    clean = rows[0]
    # one clean force: count right (all readings, and those with forces >= 0.2 N), force error ~0 %
    assert float(clean[3]) == 100.0 and float(clean[5]) < 0.1


def test_evaluate_json_and_bench_quick(capsys):
    threads = torch.get_num_threads()
    try:
        assert (
            main(["evaluate", "--count-per-cell", "4", "--noise", "0.1", "--max-forces", "1", "--json"]) == 0
        )
        (cell,) = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        assert cell["forces"] == 1 and cell["readings"] == 4 and 0.0 <= cell["count_accuracy"] <= 1.0
        assert main(["bench", "estimate", "--quick"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "B=1" in out and out.count("|") >= 12
