"""Calibration: simulated readings with a known location bias and stiffness error are calibrated back."""

from __future__ import annotations

import json

import pytest
import torch

from torchrod import PointForces, Rod, grating_curvature, presets
from torchrod import errors as tr_errors
from torchrod.cli import main
from torchrod.estimate.calibration import CalibrationData, calibrate
from torchrod.io.known_loads import read_readings

F64 = torch.float64
ROD = presets.nitinol290()
BIAS = -3.12e-3  # [m] the paper's value
RATIO = 1.08  # true EI / nominal EI
CASES = [
    [(0.12, 0.8, 0.0)],
    [(0.20, 0.0, -0.6)],
    [(0.26, 0.5, 0.5)],
    [(0.08, -1.0, 0.3), (0.22, 0.4, -0.4)],
    [(0.15, 0.3, 1.2)],
    [(0.05, 0.6, 0.6), (0.14, -0.5, 0.2), (0.24, 0.2, -0.3)],
]


def known_forces() -> PointForces:
    """The known forces, located in the true (fibre's) coordinate."""
    return PointForces.from_lists(CASES)


def simulate_readings(noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """(R, G, 2) readings of a rod whose true EI is RATIO x nominal and whose model sees s_true - BIAS."""
    loads = known_forces()
    s_model = torch.where(loads.active, loads.s - BIAS, loads.s)
    clean = grating_curvature(
        ROD, PointForces(s_model, loads.f, loads.mask), bending_stiffness=RATIO * ROD.bending_stiffness
    )
    g = torch.Generator().manual_seed(seed)
    return clean + noise * torch.randn(clean.shape, generator=g, dtype=F64)


def data_of(curvature: torch.Tensor, present: torch.Tensor | None = None) -> CalibrationData:
    if present is None:
        present = torch.ones(curvature.shape[:2], dtype=torch.bool)
    return CalibrationData(curvature * present.unsqueeze(-1), present, known_forces())


@pytest.mark.parametrize("directions", ["known", "free"])
def test_noise_free_readings_give_back_the_bias_and_the_stiffness(directions):
    present = torch.ones(len(CASES), ROD.num_gratings, dtype=torch.bool)
    present[0, 3] = present[3, 10] = present[5, 0] = False  # some gratings without a reading
    result = calibrate(ROD, data_of(simulate_readings(), present), directions=directions)
    assert result.converged
    assert abs(result.location_bias - BIAS) < 1e-9
    assert abs(result.stiffness_ratio - RATIO) < 1e-9
    assert result.rms_location_step < 1e-9 and result.rms_stiffness_step < 1e-9
    # step 1 fits the forces freely at the nominal EI: they come out as the true ones / RATIO (curvature ~ f / EI)
    fitted = result.fitted_forces.masked_f()
    assert (fitted * RATIO - known_forces().masked_f()).abs().max() < 1e-8


def test_noisy_readings_recover_both_within_their_standard_errors():
    """sigma = 0.1 1/m (FBG noise is 0.1 to 0.3 1/m). The standard errors are honest: over 40 noise draws of this
    set-up the bias errors had sd 0.258 mm against a mean reported error of 0.252 mm, and the stiffness errors sd
    0.257 % against 0.261 % (a study run once, not here). So 4 standard errors is a safe bound for one draw."""
    result = calibrate(ROD, data_of(simulate_readings(noise=0.1, seed=7)))
    assert 0.1e-3 < result.location_bias_std < 0.5e-3  # [m]
    assert 0.001 < result.bending_stiffness_std / result.bending_stiffness < 0.005
    assert abs(result.location_bias - BIAS) < 4 * result.location_bias_std
    ei_true = RATIO * ROD.bending_stiffness
    assert abs(result.bending_stiffness - ei_true) < 4 * result.bending_stiffness_std
    assert 0.08 < result.rms_location_step < 0.12  # the residual is the noise


def test_the_bias_is_where_the_gratings_really_are():
    """Readings of a fibre whose gratings sit BIAS further along than the rod file says, forces at their true
    places: the fitted bias is BIAS, so that an estimate reported as s_model + location_bias is the true location."""
    shifted_fibre = Rod(ROD.length, ROD.bending_stiffness, tuple(g + BIAS for g in ROD.gratings))
    readings = grating_curvature(shifted_fibre, known_forces())  # forces at s_true, gratings at g + BIAS
    result = calibrate(ROD, data_of(readings))
    # the same physics integrated over other segments: equal to the integrator's accuracy (exact here)
    assert abs(result.location_bias - BIAS) < 1e-7
    assert abs(result.stiffness_ratio - 1.0) < 1e-7
    # the rod with the fitted bias: model locations + bias = true locations
    est = result.fitted_forces.s + result.location_bias
    assert (est - known_forces().s)[known_forces().active].abs().max() < 1e-7


def test_apply_keeps_geometry_and_scales_youngs_modulus(tmp_path):
    result = calibrate(ROD, data_of(simulate_readings()))
    new = result.apply(ROD)
    assert new.outer_diameter == ROD.outer_diameter and new.inner_diameter == ROD.inner_diameter
    assert new.youngs_modulus == pytest.approx(RATIO * ROD.youngs_modulus, rel=1e-9)
    assert new.location_bias == pytest.approx(BIAS, abs=1e-9)
    new.to_json(tmp_path / "rod.json")
    again = Rod.from_json(tmp_path / "rod.json")  # EI recomputed from the geometry
    assert again.bending_stiffness == pytest.approx(result.bending_stiffness, rel=1e-12)
    by_stiffness = Rod(ROD.length, ROD.bending_stiffness, ROD.gratings)
    assert result.apply(by_stiffness).bending_stiffness == result.bending_stiffness
    assert result.apply(by_stiffness).youngs_modulus is None


# ---------------------------------------------------------------------------------------------- files and CLI
def write_readings(path, curvature: torch.Tensor, missing=()) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        for i, (case, curv) in enumerate(zip(CASES, curvature.tolist(), strict=False)):
            pairs = [None if (i, k) in missing else pair for k, pair in enumerate(curv)]
            forces = [{"s": s, "fx": fx, "fy": fy} for s, fx, fy in case]
            fh.write(json.dumps({"id": f"r{i}", "curvature": pairs, "forces": forces}) + "\n")


def test_read_readings_marks_missing_gratings(tmp_path):
    path = tmp_path / "cal.jsonl"
    write_readings(path, simulate_readings(), missing={(1, 4)})
    data = read_readings(path, ROD)
    assert data.ids == tuple(f"r{i}" for i in range(len(CASES)))
    assert data.curvature.shape == (len(CASES), ROD.num_gratings, 2)
    assert not bool(data.present[1, 4]) and int(data.present.sum()) == len(CASES) * ROD.num_gratings - 1
    assert data.forces.count.tolist() == [len(c) for c in CASES]


@pytest.mark.parametrize(
    "line, message",
    [
        ({"id": 1, "curvature": [[0, 0]] * 3, "forces": [{"s": 0.1, "fx": 1, "fy": 0}]}, "14"),
        ({"id": 1, "curvature": [[0, 0]] * 14, "forces": [{"s": 0.1, "fx": 1}]}, "forces\\[0\\]"),
        ({"id": 1, "curvature": [[0, "a"]] + [[0, 0]] * 13, "forces": []}, "curvature\\[0\\]\\[1\\]"),
        ({"id": 1, "curvature": [[0, 0]] * 14}, "forces"),
    ],
)
def test_read_readings_names_the_bad_line(tmp_path, line, message):
    path = tmp_path / "bad.jsonl"
    path.write_text(
        '{"id": 0, "curvature": ' + json.dumps([[0, 0]] * 14) + ', "forces": []}\n' + json.dumps(line) + "\n"
    )
    with pytest.raises(ValueError, match=f"line 2: .*{message}"):
        read_readings(path, ROD)


def test_calibrate_rejects_forces_off_the_rod():
    loads = PointForces.from_lists([[(0.35, 1.0, 0.0)]])
    data = CalibrationData(
        torch.zeros(1, ROD.num_gratings, 2, dtype=F64),
        torch.ones(1, ROD.num_gratings, dtype=torch.bool),
        loads,
    )
    with pytest.raises(ValueError, match="0.35"):
        calibrate(ROD, data)


def test_cli_writes_the_calibrated_rod(tmp_path, capsys):
    readings = tmp_path / "cal.jsonl"
    write_readings(readings, simulate_readings(noise=0.05, seed=3), missing={(2, 0)})
    rod_in, rod_out = tmp_path / "rod.json", tmp_path / "calibrated.json"
    ROD.to_json(rod_in)
    status = main(["calibrate", "--rod", str(rod_in), str(readings), "--out", str(rod_out)])
    err = capsys.readouterr().err
    assert status == 0
    new = Rod.from_json(rod_out)
    assert new.location_bias == pytest.approx(BIAS, abs=0.6e-3)
    assert new.bending_stiffness == pytest.approx(RATIO * ROD.bending_stiffness, rel=0.01)
    assert new.youngs_modulus == pytest.approx(RATIO * ROD.youngs_modulus, rel=0.01)
    assert new.gratings == ROD.gratings and new.outer_diameter == ROD.outer_diameter
    assert "location_bias" in err and "+/-" in err and "youngs_modulus" in err
    # the preset name works too, and without --out the rod goes to standard output
    assert main(["calibrate", "--rod", "nitinol290", str(readings)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["location_bias"] == pytest.approx(new.location_bias, abs=1e-12)


def test_cli_reports_a_bad_file(tmp_path, capsys):
    readings = tmp_path / "cal.jsonl"
    readings.write_text('{"curvature": [[0, 0]], "forces": []}\n')
    assert main(["calibrate", "--rod", "nitinol290", str(readings)]) == 2
    assert "line 1" in capsys.readouterr().err


def test_cli_reads_standard_input_and_its_help_gives_the_format(tmp_path, monkeypatch, capsys):
    """``calibrate -`` reads the readings from standard input (it used to look for a file named '-'), and
    ``calibrate --help`` says what a line holds."""
    import io

    readings = tmp_path / "cal.jsonl"
    write_readings(readings, simulate_readings(noise=0.05, seed=3))
    assert main(["calibrate", "--rod", "nitinol290", str(readings)]) == 0
    from_file = json.loads(capsys.readouterr().out)
    monkeypatch.setattr("sys.stdin", io.StringIO(readings.read_text()))
    assert main(["calibrate", "--rod", "nitinol290", "-"]) == 0
    assert json.loads(capsys.readouterr().out) == from_file
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = capsys.readouterr().out
    assert '"curvature": [[ux, uy], null, ...]' in text and '"forces": [{"s"' in text and "'-' for stdin" in text


def test_read_readings_lists_the_bad_lines_by_the_shared_rules(tmp_path):
    """Every line is checked by the rules of every reading; the error names the bad lines (five at most)."""
    ok = {"id": 0, "curvature": [[0, 0]] * 14, "forces": []}
    lines = [json.dumps(ok)] + [json.dumps(dict(ok, id=k, curvature=[[1e7, 0]] + [[0, 0]] * 13)) for k in range(1, 8)]
    path = tmp_path / "bad.jsonl"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"7 unusable line\(s\): line 2: curvature\[0\]\[0\] = 10000000.0 1/m") as info:
        read_readings(path, ROD)
    assert "line 6:" in str(info.value) and "line 7:" not in str(info.value) and "(and 2 more)" in str(info.value)


# ---------------------------------------------------------------------------------------------- refusals
def test_a_sound_calibration_has_no_problems():
    noisy = data_of(simulate_readings(noise=0.1, seed=7))
    assert calibrate(ROD, noisy).problems == ()
    assert calibrate(ROD, noisy, noise=0.1).problems == ()
    assert calibrate(ROD, data_of(simulate_readings()), directions="free").problems == ()


@pytest.mark.parametrize(
    "name, change, expected",
    [
        ("dead sensor", lambda u: torch.zeros_like(u), ["all but zero", "outside physical bounds"]),
        ("sign flipped", lambda u: -u, ["point against the known ones", "known forces leave an RMS residual"]),
        ("scaled by 1e5", lambda u: 1e5 * u, ["even forces fitted freely leave", "not determined"]),
    ],
)
def test_readings_inconsistent_with_the_known_forces_are_refused_saying_which(name, change, expected):
    result = calibrate(ROD, data_of(change(simulate_readings(noise=0.1, seed=7))))
    text = " | ".join(result.problems)
    for part in expected:
        assert part in text, (name, text)
    with pytest.raises(ValueError, match="not applied") as info:
        result.apply(ROD)
    assert isinstance(info.value, tr_errors.ReadingError)
    if 1e6 <= ROD.youngs_modulus * result.stiffness_ratio <= 1.2e12:
        assert result.apply(ROD, force=True).location_bias == result.location_bias
    else:  # forced, the rod itself refuses a modulus no material has
        with pytest.raises(tr_errors.RodError, match="youngs_modulus"):
            result.apply(ROD, force=True)


def test_a_residual_far_beyond_the_given_noise_is_refused():
    """Readings with noise 0.3 1/m calibrated as if the sensor's sigma were 0.03: the residual is ten times it."""
    result = calibrate(ROD, data_of(simulate_readings(noise=0.3, seed=1)), noise=0.03)
    assert any("times the noise sigma" in p for p in result.problems), result.problems


def test_a_stiffness_out_of_physical_bounds_or_not_determined_is_refused():
    # A rod 20 times stiffer than its file says: the fit is exact, and refused for the stiffness alone.
    loads = known_forces()
    stiff = grating_curvature(ROD, loads, bending_stiffness=20 * ROD.bending_stiffness)
    result = calibrate(ROD, data_of(stiff))
    assert len(result.problems) == 1 and "outside physical bounds" in result.problems[0], result.problems
    assert "20" in result.problems[0] and "Young's modulus" in result.problems[0]
    # One weak force in the noise: the stiffness is not determined.
    weak = PointForces.from_lists([[(0.2, 0.01, 0.0)]])
    u = grating_curvature(ROD, weak) + 0.1 * torch.randn(
        1, ROD.num_gratings, 2, dtype=F64, generator=torch.Generator().manual_seed(0)
    )
    one = CalibrationData(u, torch.ones(1, ROD.num_gratings, dtype=torch.bool), weak)
    assert any("not determined by the data" in p for p in calibrate(ROD, one).problems)


def test_cli_refuses_a_dead_sensor_and_writes_no_rod_unless_forced(tmp_path, capsys):
    readings = tmp_path / "cal.jsonl"
    write_readings(readings, torch.zeros(len(CASES), ROD.num_gratings, 2, dtype=F64))
    out = tmp_path / "new.json"
    assert main(["calibrate", "--rod", "nitinol290", str(readings), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert not out.exists() and captured.out == ""
    assert "refused: readings inconsistent with the known forces: the readings are all but zero" in captured.err
    assert "no rod written (--force writes it anyway)" in captured.err
    assert main(["calibrate", "--rod", "nitinol290", str(readings)]) == 1  # nor to standard output
    assert capsys.readouterr().out == ""
    # forced, the rod file itself refuses the modulus a dead sensor gives
    assert main(["calibrate", "--rod", "nitinol290", str(readings), "--out", str(out), "--force"]) == 2
    assert "youngs_modulus" in capsys.readouterr().err and not out.exists()
    # --noise judges the residuals: a sound set passes with its sigma, fails with a tenth of it (unless forced)
    sound = tmp_path / "sound.jsonl"
    write_readings(sound, simulate_readings(noise=0.1, seed=7))
    assert main(["calibrate", "--rod", "nitinol290", str(sound), "--noise", "0.1"]) == 0
    assert main(["calibrate", "--rod", "nitinol290", str(sound), "--noise", "0.01"]) == 1
    assert "times the noise sigma" in capsys.readouterr().err
    assert main(["calibrate", "--rod", "nitinol290", str(sound), "--noise", "0.01", "--out", str(out), "--force"]) == 0
    assert "warning (forced)" in capsys.readouterr().err and Rod.from_json(out).location_bias != 0.0


# ---------------------------------------------------------------------------------------------- the Jacobian
def _free_force_problem():
    """The calibration's least squares with every known force's components free at the nominal stiffness (its first
    step without the bias): a model of k copies of the readings' rows, as the Jacobian asks."""
    from torchrod.estimate import calibration as C

    data = data_of(simulate_readings(noise=0.1, seed=7))
    loads = data.forces
    R, h = loads.s.shape

    def model(X: torch.Tensor) -> torch.Tensor:
        k = X.shape[0] // R
        mask = None if loads.mask is None else loads.mask.repeat(k, 1)
        return grating_curvature(ROD, PointForces(loads.s.repeat(k, 1), X.reshape(-1, h, 2), mask))

    used = loads.active.unsqueeze(-1).expand(-1, -1, 2).reshape(R, 2 * h)
    fixed = loads.masked_f().reshape(R, 2 * h)
    return C._Problem(model, data, 0, used, fixed), fixed[used].numpy()


def test_the_jacobian_over_copies_is_the_finite_difference_of_the_residuals(monkeypatch):
    """The Jacobian from reverse passes over copies of the readings (every component in one pass) against central
    differences of the residuals, and bit for bit the same with one component per pass."""
    import numpy as np

    from torchrod.estimate import calibration as C

    problem, theta = _free_force_problem()
    r, J = problem.evaluate(theta)
    assert J.shape == (r.shape[0], theta.shape[0]) and np.array_equal(r, problem.residual(theta))
    step = 1e-6
    for j in range(theta.shape[0]):
        up, down = theta.copy(), theta.copy()
        up[j] += step
        down[j] -= step
        fd = (problem.residual(up) - problem.residual(down)) / (2 * step)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-6, atol=1e-6 * np.abs(J).max())
    monkeypatch.setattr(C, "JACOBIAN_ROWS", 1)  # one component per pass
    single, _ = _free_force_problem()
    r1, J1 = single.evaluate(theta)
    assert np.array_equal(J1, J) and np.array_equal(r1, r)
