"""The scripts in examples/ run, at a small size, and print what they promise."""

from __future__ import annotations

import collections
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run(script: str, *args: str, cwd: Path) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True, timeout=300, cwd=cwd, env=env
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_every_example_is_tested():
    assert {p.name for p in EXAMPLES.glob("*.py")} == {
        "simulate_and_estimate.py",
        "estimate_file.py",
        "stream_sensor.py",
        "own_rod.py",
        "fit_rod_by_gradient.py",
        "distributed_contact.py",
    }


def test_simulate_and_estimate(tmp_path):
    out = run("simulate_and_estimate.py", "--count", "2", "--seed", "3", cwd=tmp_path)
    assert out.count("reading ") == 2 and out.count("estimate: ") == 2
    assert "s = " in out and " mm" in out and " N" in out


def test_estimate_file_writes_one_answer_per_reading(tmp_path):
    """On the shipped example stream (simulated from the model, at the noise the example assumes) the answers are
    ok: the model fits (no misfit), the search converged in time, and most are determined; the summary it prints is
    the answers' own."""
    answers = tmp_path / "answers.jsonl"
    out = run("estimate_file.py", "--count", "6", "--out", str(answers), cwd=tmp_path)
    assert "6 readings" in out and "the shipped warm-start network" in out
    records = [json.loads(line) for line in answers.read_text().splitlines()]
    assert [r["id"] for r in records] == [f"f{k:06d}" for k in range(6)]
    statuses = collections.Counter(r["status"] for r in records)
    assert set(statuses) <= {"ok", "poorly_determined"}, statuses
    assert statuses["ok"] >= 5, statuses
    assert all(r["num_forces"] == len(r["forces"]) >= 1 for r in records)  # each reading was taken under load
    counts = dict(sorted(collections.Counter(r["num_forces"] for r in records).items()))
    assert f"statuses: {dict(statuses)}" in out and f"forces per reading: {counts}" in out
    assert f"wrote 6 answers to {answers}" in out


def test_estimate_file_reports_a_bad_line_and_goes_on(tmp_path):
    readings = tmp_path / "r.jsonl"
    good = (ROOT / "data" / "example_stream.jsonl").read_text().splitlines()[0]
    readings.write_text(good + "\n" + '{"id": "bad", "curvature": [[1, 2]]}\n')
    out = run("estimate_file.py", str(readings), cwd=tmp_path)
    assert "skipped: line 2" in out and "1 readings" in out


def test_stream_sensor(tmp_path):
    out = run("stream_sensor.py", "--count", "8", "--rate", "400", cwd=tmp_path)
    lines = [line for line in out.splitlines() if line.startswith("f0000")]
    assert [line.split()[0] for line in lines] == [f"f{k:06d}" for k in range(8)]
    assert "latency median" in out


def test_own_rod_writes_a_rod_file_the_cli_reads(tmp_path):
    rod_file = tmp_path / "my_rod.json"
    out = run("own_rod.py", "--out", str(rod_file), "--count", "2", cwd=tmp_path)
    assert f"rod file: {rod_file}" in out and out.count("true ") == 2
    import torchrod as tr

    rod = tr.presets.load(str(rod_file))
    assert rod.length == 0.4 and rod.num_gratings == 8 and rod.youngs_modulus == 193e9


def test_fit_rod_by_gradient_lands_where_calibrate_does(tmp_path):
    """Gradient descent through the estimator and the least-squares calibration find the same stiffness and bias,
    both near the truth."""
    out = run("fit_rod_by_gradient.py", "--steps", "120", cwd=tmp_path)
    values = {}
    for line in out.splitlines():
        name, _, rest = line.partition(":")
        if name.strip() in ("truth", "gradient descent", "calibrate"):
            words = rest.split()
            values[name.strip()] = (float(words[1]), float(words[5]))
    (ei, bias), (ei_cal, bias_cal), (ei_true, bias_true) = (
        values["gradient descent"],
        values["calibrate"],
        values["truth"],
    )
    assert abs(ei / ei_cal - 1) < 0.01 and abs(bias - bias_cal) < 0.2  # [mm]
    assert abs(ei / ei_true - 1) < 0.02 and abs(bias - bias_true) < 0.3


def test_distributed_contact_counts_the_two_force_answers_of_patches(tmp_path):
    out = run("distributed_contact.py", "--count", "40", "--seed", "2", cwd=tmp_path)
    assert out.startswith("40 patches 12 mm long on 14 gratings 20 mm apart")
    lines = out.splitlines()
    for said in ("given", "each reading's own"):
        (line,) = [x for x in lines if x.startswith(f"noise {said}: ")]
        two = int(line.split(": ")[1].split(" of ")[0])
        assert 0 <= two <= 40
    answers = [x for x in lines if x.startswith("  patch at ")]
    assert all("one force alone: p-value" in x for x in answers)
