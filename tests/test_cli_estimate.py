"""``torchrod estimate``, ``torchrod evaluate`` and ``torchrod bench estimate`` through ``main()``."""

from __future__ import annotations

import array
import fcntl
import io
import json
import math
import os
import signal
import subprocess
import sys
import termios
import time

import pytest
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
        json.dumps({"id": "other-rod", "curvature": good[0]["curvature"], "gratings": [0.0] * rod.num_gratings}),
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
        # the estimator's record (it may gain fields) plus time_ms
        assert {"id", "num_forces", "forces", "loss", "converged", "time_ms"} <= set(o) and "error" not in o
        assert all({"s", "fx", "fy", "magnitude", "std_s", "std_fx", "std_fy"} <= set(g) for g in o["forces"])
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


_R = 3.5e-5
_THREE = [[_R, 0.0], [-_R / 2, _R * math.sqrt(3) / 2], [-_R / 2, -_R * math.sqrt(3) / 2]]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["--noise", "1e200"],
            "--noise must be at most 1e+06 1/m, the largest curvature a reading may carry, got 1e+200",
        ),
        (["--wavelength-noise", "1e300"], "--wavelength-noise must be at most 100000 pm, the largest shift a reading"),
        (["--strain-noise", "1e300"], "--strain-noise must be at most 0.1, the largest strain a reading may carry"),
    ],
)
def test_a_noise_sigma_no_reading_can_carry_is_a_usage_error(rod, tmp_path, capsys, argv, message):
    """--noise 1e200 and --wavelength-noise 1e300 ended in an OverflowError traceback; they are usage errors, as a
    NaN or negative sigma is."""
    fibre = {"cores": _THREE, "wavelength": {"reference": [[1530.0 + 2.5 * g + 0.1 * c for c in range(3)] for g in
                                                            range(rod.num_gratings)]}}  # fmt: skip
    rod_file, path = tmp_path / "rod.json", tmp_path / "r.jsonl"
    rod.with_(fibre=fibre).to_json(rod_file)
    path.write_text(json.dumps(_reading_lines(rod)[0]) + "\n")
    assert main(["estimate", "--rod", str(rod_file), *argv, str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and f"torchrod estimate: error: {message}" in captured.err
    assert "Traceback" not in captured.err


def test_estimator_options_refuse_a_sigma_whose_square_overflows():
    for name in ("noise", "max_noise", "noise_floor"):
        with pytest.raises(tr.errors.OptionsError, match=f"{name} must be .*at most 1e\\+06 \\[1/m\\].*got 1e\\+200"):
            tr.EstimatorOptions(**{name: 1e200})


@pytest.mark.parametrize(
    "command",
    [["estimate", "-"], ["stream"], ["bench", "stream", "--quick"], ["bench", "estimate"], ["simulate"], ["generate"]],
)
def test_a_device_that_cannot_be_used_is_refused_at_once(command, capsys, tmp_path):
    """A device torch does not know, or does not see here, is a bad option (exit 2, naming it) before any reading;
    so are worker processes beside a GPU (tests/test_cuda.py runs that where there is one)."""
    rod = [] if command[0] == "bench" else ["--rod", "nitinol290"]
    if command == ["simulate"]:
        forces = tmp_path / "forces.jsonl"
        forces.write_text('{"forces": [{"s": 0.2, "fx": 0.1, "fy": 0.0}]}\n')
        command = ["simulate", str(forces)]
    elif command == ["generate"]:
        command = ["generate", "--count", "1", "--out", str(tmp_path / "set.npz")]
    assert main([*command, *rod, "--device", "gpu0"]) == 2
    assert "'gpu0' is not a torch device" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main([*command, *rod, "--device", "cuda"]) == 2
        assert "no CUDA device" in capsys.readouterr().err


def test_evaluate_prints_a_table(capsys):
    threads = torch.get_num_threads()
    try:
        status = main(["evaluate", "--count-per-cell", "6", "--noise", "0,0.1", "--max-forces", "2", "--seed", "3"])
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out.splitlines()
    assert status == 0
    rows = [line.split() for line in out if line.strip() and not line.lstrip().startswith(("#", "forces", "["))]
    labels = [(" ".join(r[:-13]), r[-13]) for r in rows]
    assert labels == [(k, s) for k in ("0", "1", "2", "1 nb", "2 nb", "unexpl.") for s in ("0", "0.1")], labels
    by = {(" ".join(r[:-13]), r[-13]): r[-13:] for r in rows}
    # one clean force: count right (all readings, and those with forces >= 0.2 N), force error ~0 %, rms too
    clean = by[("1", "0")]
    assert float(clean[2]) == 100.0 and float(clean[4]) < 0.1 and float(clean[6]) < 0.1
    # no force: the count is 0; readings no forces make: flagged misfit
    assert float(by[("0", "0.1")][2]) >= 80.0
    assert float(by[("unexpl.", "0.1")][-2]) >= 80.0
    assert by[("unexpl.", "0.1")][2] == "-"


def test_evaluate_json_and_bench_quick(capsys):
    threads = torch.get_num_threads()
    try:
        assert (
            main(
                [
                    "evaluate",
                    "--count-per-cell",
                    "4",
                    "--noise",
                    "0.1",
                    "--max-forces",
                    "1",
                    "--json",
                    "--rows",
                    "forces,zero",
                ]
            )
            == 0
        )
        zero, cell = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        assert zero["forces"] == 0 and zero["row"] == "0" and 0.0 <= zero["count_accuracy"] <= 1.0
        assert cell["forces"] == 1 and cell["readings"] == 4 and 0.0 <= cell["count_accuracy"] <= 1.0
        assert "force_error_rms" in cell and "location_error_rms" in cell and "misfit" in cell
        assert main(["bench", "estimate", "--quick"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "B=1" in out and out.count("|") >= 12 and "network none" in out
    with pytest.raises(SystemExit):
        main(["evaluate", "--rows", "nonsense"])


def test_bench_estimate_with_the_network_and_idle_gaps(capsys):
    """The one-at-a-time row as a paced live source meets it: the shipped network's guesses, and the estimator idle
    before each call; a negative gap is refused."""
    threads = torch.get_num_threads()
    try:
        args = ["bench", "estimate", "--quick", "--forces", "1", "--checkpoint", "shipped", "--gap-ms", "2"]
        assert main(args) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert "network checkpoints/nitinol290.pt" in out
    assert "2 ms idle before each one-at-a-time call" in out
    assert main(["bench", "estimate", "--quick", "--gap-ms", "-1"]) == 2
    assert "--gap-ms must be" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- hostile input
def _with_first(curvature: list, first: str) -> str:
    """The JSON text of ``curvature`` with its first pair replaced by the raw text ``first``."""
    rest = json.dumps(curvature[1:])[1:]
    return "[" + first + ", " + rest


def test_every_hostile_line_gets_one_short_error_line_in_order(rod, tmp_path, capsys):
    """The crashes users found, each now the error line of its own line, naming the line and the field and
    quoting at most about 100 characters; the lines around them are answered; exit status 1."""
    good = _reading_lines(rod)[0]
    u = good["curvature"]
    cu = json.dumps(u)
    hostile = [
        (
            "int400",
            '{"id": "int400", "curvature": ' + _with_first(u, "[" + "1" * 400 + ", 0]") + "}",
            "curvature[0][0] must be a finite number",
        ),
        (
            "t400",
            '{"id": "t400", "t": ' + "9" * 400 + ', "curvature": ' + cu + "}",
            "t must be a finite number",
        ),
        (None, '{"id": NaN, "curvature": ' + cu + "}", "id NaN cannot be written as JSON"),
        (None, '{"id": Infinity, "curvature": ' + cu + "}", "id Infinity cannot be written as JSON"),
        (None, '{"id": ' + "4" * 4400 + ', "curvature": ' + cu + "}", "id holds an integer of 4400 digits"),
        (
            "int4400",
            '{"id": "int4400", "curvature": ' + _with_first(u, "[0, " + "4" * 4400 + "]") + "}",
            "curvature[0][1] must be a finite number, got an integer of 4400 digits",
        ),
        (
            "deep",
            '{"id": "deep", "curvature": ' + _with_first(u, "[" * 400 + "]" * 400) + "}",
            "curvature[0] must be a pair",
        ),
        (
            None,
            '{"id": "deeper", "curvature": ' + _with_first(u, "[" * 985 + "]" * 985) + "}",
            "nested too deeply",
        ),
        (
            "e308",
            '{"id": "e308", "curvature": ' + _with_first(u, "[1e308, 0]") + "}",
            "curvature[0][0] = 1e+308 1/m is beyond the bound of 1e+06 1/m",
        ),
        (
            "e999",
            '{"id": "e999", "curvature": ' + _with_first(u, "[1e999, 0]") + "}",
            "curvature[0][0] must be finite, got Infinity",
        ),
        (
            "10MB",
            '{"id": "10MB", "curvature": ' + _with_first(u, '["' + "x" * 10_000_000 + '", 0]') + "}",
            "curvature[0][0] must be a number, got a string",
        ),
    ]
    lines = [json.dumps(good)] + [text for _, text, _ in hostile] + [json.dumps(dict(good, id="last"))]
    # "deeper" may decode (its id then kept) or not, depending on the stack depth: both are one error line.
    path = tmp_path / "hostile.jsonl"
    path.write_text("\n".join(lines) + "\n")
    # (the 10 MB line is over the default line limit: --max-line-bytes lets it be read, and its value quoted)
    args = ["estimate", "--rod", "nitinol290", "--noise", "0.01", "--max-forces", "1", "--max-line-bytes", "16000000"]
    status = main([*args, str(path)])
    cap = capsys.readouterr()
    out = [json.loads(x) for x in cap.out.splitlines()]
    assert status == 1 and "Traceback" not in cap.err
    assert len(out) == len(lines)
    assert out[0]["id"] == "r0" and out[0]["num_forces"] == 1
    assert out[-1]["id"] == "last" and out[-1]["num_forces"] == 1
    for k, (ident, _, message) in enumerate(hostile, start=2):
        o = out[k - 1]
        assert set(o) == {"id", "error"}
        if ident is not None:
            assert o["id"] == ident
        assert o["error"].startswith(f"line {k}: "), o["error"]
        assert message in o["error"], o["error"]
        assert len(o["error"]) < 400
    assert len(cap.out) < 20_000  # no value echoed in full


def test_finite_but_absurd_values_reach_the_estimator(rod, tmp_path, capsys):
    """Within the bound (1e6 1/m) a value is the estimator's to judge: 1e4 gets an answer, not an error."""
    u = _reading_lines(rod)[0]["curvature"]
    path = tmp_path / "absurd.jsonl"
    path.write_text(json.dumps({"id": "absurd", "curvature": [[1e4, 0.0]] + u[1:]}) + "\n")
    status = main(["estimate", "--rod", "nitinol290", "--noise", "0.01", "--num-forces", "1", str(path)])
    (o,) = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert status == 0 and "error" not in o and o["num_forces"] == 1


def test_out_writes_the_answers_to_a_file(rod, tmp_path, capsys):
    path = tmp_path / "in.jsonl"
    path.write_text("\n".join(json.dumps(x) for x in _reading_lines(rod)) + "\nnot json\n")
    target = tmp_path / "answers.jsonl"
    base = ["estimate", "--rod", "nitinol290", "--noise", "0.01", str(path)]
    assert main([*base, "--out", str(target)]) == 1
    assert capsys.readouterr().out == ""
    out = [json.loads(x) for x in target.read_text().splitlines()]
    assert [o["id"] for o in out] == ["r0", "r1", None] and out[1]["num_forces"] == 2
    for bad, message in [
        (tmp_path / "no" / "a.jsonl", "cannot write there"),
        (path, "would erase the input"),
    ]:
        assert main([*base, "--out", str(bad)]) == 2
        assert message in capsys.readouterr().err
    assert path.read_text().endswith("not json\n")


def test_checkpoint_option(rod, tmp_path, capsys):
    """--checkpoint PATH uses a warm-start network (as load_estimator); a missing or unreadable
    checkpoint is a bad option (status 2), 'none' is no network."""
    from torchrod.learn.warm_start import SHIPPED_CHECKPOINT

    path = tmp_path / "in.jsonl"
    path.write_text("\n".join(json.dumps(x) for x in _reading_lines(rod)) + "\n")
    base = ["estimate", "--rod", "nitinol290", "--noise", "0.01", str(path)]
    if os.path.exists(SHIPPED_CHECKPOINT):
        assert main([*base, "--checkpoint", SHIPPED_CHECKPOINT]) == 0
        assert [json.loads(x)["num_forces"] for x in capsys.readouterr().out.splitlines()] == [1, 2]
    assert main([*base, "--checkpoint", "none"]) == 0
    capsys.readouterr()
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    for bad, message in [(tmp_path / "missing.pt", "no such file"), (junk, "not a readable checkpoint")]:
        assert main([*base, "--checkpoint", str(bad)]) == 2
        cap = capsys.readouterr()
        assert message in cap.err and cap.out == ""


def test_counts_must_not_be_negative_and_csv_is_read(rod, tmp_path, capsys):
    path = tmp_path / "in.csv"
    u = _reading_lines(rod)[0]["curvature"]
    path.write_text("a,0.5," + ",".join(repr(x) for pair in u for x in pair) + "\nb,,1_000\n")
    for option in ("--num-forces", "--max-forces"):
        assert main(["estimate", "--rod", "nitinol290", option, "-1", str(path)]) == 2
        assert f"{option} must be >= 0" in capsys.readouterr().err
    assert main(["estimate", "--rod", "nitinol290", "--noise", "0.01", "--format", "csv", str(path)]) == 1
    out = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert out[0]["id"] == "a" and out[0]["num_forces"] == 1
    assert out[1] == {
        "id": "b",
        "error": f"line 2: expected {2 + 2 * rod.num_gratings} cells (id, t, then ux, uy "
        f"for {rod.num_gratings} gratings), {1 + 2 * rod.num_gratings} (t, then the values) or "
        f"{2 * rod.num_gratings} (the values alone), got 3; or give a header row naming the columns",
    }


def _unread(pipe) -> int:
    """Bytes written to ``pipe`` that its reader has not read yet."""
    buf = array.array("i", [0])
    fcntl.ioctl(pipe.fileno(), termios.FIONREAD, buf)
    return buf[0]


def test_sigterm_answers_every_line_read_then_exits_143(rod):
    """SIGTERM as Ctrl-C: the lines of a batch that is far from full are answered before the exit (status 143)."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "torchrod",
            "estimate",
            "--rod",
            "nitinol290",
            "--noise",
            "0.01",
            "--batch-size",
            "100",
            "--threads",
            "1",
            "-",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        proc.stdin.write("".join(json.dumps(x) + "\n" for x in _reading_lines(rod)) + "not json\n")
        proc.stdin.flush()
        deadline = time.monotonic() + 60
        while _unread(proc.stdin) and time.monotonic() < deadline:  # until the command has read them
            time.sleep(0.05)
        time.sleep(0.5)  # the batch waits for more lines
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        status = proc.wait(timeout=60)
        out = [json.loads(x) for x in proc.stdout.read().splitlines()]
        err = proc.stderr.read()
        assert status == 143, err
        assert [o["id"] for o in out] == ["r0", "r1", None] and out[1]["num_forces"] == 2
        assert "Traceback" not in err and "Fatal" not in err
    finally:
        if proc.poll() is None:
            proc.kill()


def test_evaluate_recovery_prints_verdicts_per_stratum(capsys):
    assert main(["evaluate", "--recovery", "12", "--seed", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    table = {line.split()[0]: line.split()[1:] for line in out[2:] if line.split() and line.split()[0] != "near"}
    assert out[0].startswith("# 12 clean cases (seed 2)")
    assert int(table["all"][0]) == 12 and sum(int(x) for x in table["all"][1:]) == 12
    assert main(["evaluate", "--recovery", "6", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["summary"]["all"]["cases"] == 6 and isinstance(record["failures"], list)


def test_evaluate_recovery_up_to_the_elastic_limit_has_a_large_bend_stratum(capsys):
    assert main(["evaluate", "--recovery", "4", "--large-bends", "--max-strain", "0.03"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("# 4 clean cases (seed 0) up to a bending strain of 0.03:")
    table = {line.split()[0]: line.split() for line in out[2:] if line.split()}
    assert table["large"][:3] == ["large", "bend", "1"]
    assert main(["evaluate", "--large-bends"]) == 2
    assert "--large-bends and --max-strain go with --recovery N" in capsys.readouterr().err
    assert main(["evaluate", "--recovery", "4", "--large-bends", "--max-strain", "5"]) == 2
