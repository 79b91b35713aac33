"""Precurved rods: the rod file's intrinsic curvature and torsion, the general body-frame march
(torchrod.model.precurved) against the straight rod's model and the global-frame BVP, gradients, and the preset."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

import torchrod as tr
from torchrod.model import body_frame
from torchrod.model import precurved as P
from torchrod.model.global_bvp import ShootingSolver, solve_reference
from torchrod.model.shape import shape


@pytest.fixture(scope="module")
def rod() -> tr.Rod:
    return tr.presets.ctr250()


def _loads(cases: list[list[tuple[float, float, float]]]) -> tr.PointForces:
    return tr.PointForces.from_lists(cases, max_forces=max(len(c) for c in cases))


# ---------------------------------------------------------------------------------------------------- the rod file
def test_rod_file_round_trip_and_lookups(rod, tmp_path):
    assert rod.precurved and rod.length == 0.25 and rod.intrinsic_curvature == ((0.15, 0.25, 12.0, 0.0),)
    assert rod.torsion_stiffness == pytest.approx(rod.bending_stiffness / 1.33)
    path = tmp_path / "ctr.json"
    rod.to_json(path)
    data = json.loads(path.read_text())
    assert data["intrinsic_curvature"] == [{"from": 0.15, "to": 0.25, "u": [12.0, 0.0]}]
    assert tr.Rod.from_json(path) == rod
    # The distal value at a breakpoint; zero outside the segments; the tip belongs to a segment ending there.
    assert rod.intrinsic_at([0.0, 0.1499, 0.15, 0.2, 0.25]) == [(0.0, 0.0), (0.0, 0.0), (12.0, 0.0), (12.0, 0.0)] + [
        (12.0, 0.0)
    ]
    assert rod.breakpoints() == [0.15]
    shape = rod.unloaded_curvature()
    assert shape.shape == (12, 2) and shape[7].tolist() == [12.0, 0.0] and shape[6].tolist() == [0.0, 0.0]
    assert float(tr.presets.nitinol290().unloaded_curvature().abs().max()) == 0.0
    gj = rod.with_(poisson_ratio=None, torsional_stiffness=1e-3)
    assert gj.torsion_stiffness == 1e-3 and tr.Rod.from_dict(gj.to_dict()) == gj
    straight = tr.presets.nitinol290()
    assert not straight.precurved and not straight.with_(intrinsic_curvature=[(0.0, 0.1, 0.0, 0.0)]).precurved
    assert any("intrinsic curvature" in d for d in rod.differences(rod.with_(intrinsic_curvature=[(0.1, 0.25, 12, 0)])))
    assert any("torsional" in d for d in rod.differences(rod.with_(poisson_ratio=0.2)))


@pytest.mark.parametrize(
    ("segments", "match"),
    [
        ([{"from": 0.1, "to": 0.05, "u": [1, 0]}], "from < to"),
        ([{"from": 0.1, "to": 0.3, "u": [1, 0]}], "length"),
        ([{"from": 0.0, "to": 0.2, "u": [1, 0]}, {"from": 0.1, "to": 0.25, "u": [0, 1]}], "overlap"),
        ([{"from": 0.0, "to": 0.2, "u": [1]}], r"u must be \[ux, uy\]"),
        ([{"from": 0.0, "to": 0.2, "u": [1, "x"]}], r"u\[1\]"),
        ([{"from": 0.0, "to": 0.2}], "missing"),
        ([{"from": 0.0, "to": 0.2, "u": [1, 0], "twist": 1}], "unknown"),
        ({"from": 0.0}, "list of segments"),
        ([{"from": 0.0, "to": float("nan"), "u": [1, 0]}], "finite"),
    ],
)
def test_bad_intrinsic_curvature_is_named(segments, match):
    data = tr.presets.ctr250().to_dict()
    data["intrinsic_curvature"] = segments
    with pytest.raises(ValueError, match=match):
        tr.Rod.from_dict(data)


def test_torsion_is_given_once():
    data = tr.presets.ctr250().to_dict()
    data["torsional_stiffness"] = 1e-3
    with pytest.raises(ValueError, match="not both"):
        tr.Rod.from_dict(data)
    data.pop("poisson_ratio", None)
    data["torsional_stiffness"] = -1.0
    with pytest.raises(ValueError, match="torsional_stiffness must be positive"):
        tr.Rod.from_dict(data)


# ---------------------------------------------------------------------------------------------------- the model
def test_straight_rod_agrees_with_the_complex_reduction_and_converges_at_fourth_order():
    """Without intrinsic curvature the general march is an independent solver of the straight rod's problem."""
    rod = tr.presets.nitinol290()
    loads = _loads([[(0.12, -0.9, 1.1), (0.25, 0.6, -0.4)], [(0.2, 1.5, 0.2), (0.29, 0.3, 0.3)]])
    ref = tr.simulate(rod, loads).grating_curvature
    errors = []
    for step in (2e-3, 1e-3):
        u = P.grating_curvature(rod, loads, max_step=step)
        errors.append(float((u - ref).abs().max() / ref.abs().max()))
    assert 10.0 < errors[0] / errors[1] < 25.0  # 2^4 = 16: fourth order
    assert float((P.grating_curvature(rod, loads) - ref).abs().max() / ref.abs().max()) < 1e-9


def test_precurved_ivp_matches_the_global_bvp(rod):
    """Large deflection (the curved section alone turns 69 degrees), out-of-plane forces that twist the tube: the
    body-frame march from the tip and the global-frame shooting (DOP853, tip residual 1e-12) agree to 1e-8."""
    cases = [[(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)], [(0.2, 1.5, 0.2), (0.25, 0.3, 0.3)]]
    q = torch.tensor([0.0, *rod.gratings], dtype=torch.float64)
    u, n = P.simulate_torch(rod, _loads(cases), q)
    k = np.array([rod.bending_stiffness, rod.bending_stiffness, rod.torsion_stiffness])
    for b, case in enumerate(cases):
        # The first case from the BVP's own start (load continuation); the second from the march's base values
        # (the shooting then only polishes: its root does not depend on where it starts).
        initial = None if b == 0 else np.concatenate([n[b, 0].numpy(), k * u[b, 0].numpy()])
        sol = solve_reference(rod, case, at=rod.gratings, initial=initial)
        assert sol.converged
        assert np.abs(sol.u[:, 2]).max() > 1.0  # it twists: torsion is part of the answer
        rel = np.abs(u[b, 1:].numpy() - sol.u).max() / np.abs(sol.u).max()
        assert rel < 1e-8, rel
    # Torsional stiffness matters for a precurved rod (and the BVP uses the same one).
    stiff = P.grating_curvature(
        rod.with_(poisson_ratio=None, torsional_stiffness=10 * rod.torsion_stiffness), _loads(cases)
    )
    assert float((stiff - u[:, 1:, :2]).abs().max()) > 1e-2


def test_the_papers_shooting_baselines_take_the_precurvature(rod):
    """The paper's RK4 shooting (both inner Jacobians) on the precurved tube converges at fourth order to the
    reference shooting."""
    case = [(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]
    ref = solve_reference(rod, case, at=rod.gratings).u
    for jacobian in ("dp", "fd"):
        errors = []
        for nodes in (100, 200):
            sol = ShootingSolver(rod, nodes=nodes, jacobian=jacobian).solve(case, at=rod.gratings)
            assert sol.converged
            errors.append(np.abs(sol.u - ref).max() / np.abs(ref).max())
        assert errors[1] < 2e-9 and 12.0 < errors[0] / errors[1] < 20.0, errors


def test_unloaded_rod_reads_its_shape_and_the_jump_sits_at_the_breakpoint(rod):
    zero = _loads([[(0.1, 0.0, 0.0)]])
    u = P.grating_curvature(rod, zero)
    assert torch.equal(u[0], torch.tensor(rod.intrinsic_at(rod.gratings), dtype=torch.float64))
    assert float(P.grating_curvature(rod, zero, relative=True).abs().max()) == 0.0
    # Under load the moment is continuous at the breakpoint, so u jumps by exactly the jump of u*.
    loads = _loads([[(0.22, 0.8, -0.5)]])
    q = torch.tensor([0.15 - 1e-9, 0.15], dtype=torch.float64)
    u, _ = P.simulate_torch(rod, loads, q)
    jump = u[0, 1] - u[0, 0]
    assert torch.allclose(jump, torch.tensor([12.0, 0.0, 0.0], dtype=torch.float64), atol=1e-6)


def test_gradcheck_in_locations_forces_and_stiffness(rod):
    s = torch.tensor([[0.13, 0.21]], dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[[0.4, -0.3], [0.2, 0.5]]], dtype=torch.float64, requires_grad=True)
    ei = torch.tensor(rod.bending_stiffness, dtype=torch.float64, requires_grad=True)
    q = torch.tensor([0.05, 0.15, 0.2, 0.24], dtype=torch.float64)

    def fn(s, f, ei):
        # Coarse steps keep it quick; a step length that does not divide any segment keeps the step counts fixed
        # under gradcheck's perturbations (the discrete march is smooth between changes of its step counts).
        u, n = P.simulate_torch(rod, tr.PointForces(s, f), q, max_step=7.3e-3, bending_stiffness=ei)
        return u, n

    assert torch.autograd.gradcheck(fn, (s, f, ei), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_large_forces_keep_the_error_bound_or_are_flagged(rod):
    # 300 N at the tip: the 0.5 mm RK4 steps alone were off by 1.1e-4; simulate takes shorter ones and checks them.
    # 1e5 N would need steps shorter than max_steps allows over the rod: flagged. The small case is not touched.
    loads = tr.PointForces.from_lists([[(0.25, 90.0, 300.0)], [(0.25, 0.0, 1e5)], [(0.2, 0.5, 0.2)]])
    sim = tr.simulate(rod, loads)
    accurate = getattr(sim, "accurate", torch.ones(3, dtype=torch.bool))
    assert accurate.tolist() == [True, False, True]
    want = P.simulate_torch(rod, loads[0:1], rod.grating_positions(torch.float64), max_step=2.5e-5)[0][0, :, :2]
    err = (sim.grating_curvature[0] - want).abs().max() / want.abs().max()
    assert err < body_frame.ACCURACY, float(err)  # measured 5e-10
    alone = tr.simulate(rod, loads[2:3]).grating_curvature[0]
    torch.testing.assert_close(sim.grating_curvature[2], alone, rtol=1e-13, atol=1e-13)


def test_simulate_dispatches_and_refuses_what_does_not_apply(rod):
    loads = _loads([[(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]])
    sim = tr.simulate(rod, loads, samples=11)
    assert torch.allclose(sim.grating_curvature, P.grating_curvature(rod, loads), rtol=1e-9, atol=1e-9)
    assert sim.curvature.shape == (1, 11, 2) and sim.internal_force.shape == (1, 11, 3)
    padded = tr.PointForces(
        torch.tensor([[0.12, float("nan")]], dtype=torch.float64),
        torch.tensor([[[-0.9, 1.1], [5.0, 5.0]]], dtype=torch.float64),
        torch.tensor([[True, False]]),
    )
    alone = tr.simulate(rod, _loads([[(0.12, -0.9, 1.1)]])).grating_curvature
    assert torch.equal(tr.simulate(rod, padded).grating_curvature, alone)  # padding carries no force
    for kwargs in ({"steps": 4}, {"method": "rkn4"}):
        with pytest.raises(ValueError, match="precurved"):
            tr.simulate(rod, loads, **kwargs)
    # the paper's node scheme: the same march with the forces spread onto the nodes, as the measurement model
    nodes = tr.simulate(rod, loads, scheme="nodes", nodes=400, samples=5)
    model = body_frame.grating_curvature(rod, loads, scheme="nodes", nodes=400)
    assert torch.allclose(nodes.grating_curvature, model, rtol=1e-9, atol=1e-9)  # (the samples add steps)
    assert nodes.internal_force.shape == (1, 5, 3)
    assert (nodes.grating_curvature - sim.grating_curvature).abs().max() < 0.01 * sim.grating_curvature.abs().max()


def _random_cases(rod: tr.Rod, count: int, seed: int) -> list[list[tuple[float, float, float]]]:
    """Stratified random clean cases on the preset: 1 to 3 forces 0.2 to 1.5 N in any direction, at least 25 mm
    apart, between the second grating and the tip; one in three has a force within 10 mm of the breakpoint of u*
    (150 mm), one in three a force within 3 mm of a grating."""
    g = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        k = int(g.integers(1, 4))
        s = np.sort(g.uniform(rod.gratings[1], rod.length, size=k))
        kind = len(out) % 3
        if kind == 1:
            s[g.integers(k)] = 0.15 + g.uniform(-0.01, 0.01)
        elif kind == 2:
            s[g.integers(k)] = rod.gratings[int(g.integers(1, rod.num_gratings))] + g.uniform(-0.003, 0.003)
        s = np.sort(s)
        if k > 1 and np.diff(s).min() < 0.025:
            continue
        mag, ang = g.uniform(0.2, 1.5, size=k), g.uniform(0, 2 * np.pi, size=k)
        out.append(
            [(float(a), float(m * np.cos(t)), float(m * np.sin(t))) for a, m, t in zip(s, mag, ang, strict=True)]
        )
    return out


def test_forces_on_a_precurved_rod_are_recovered_from_clean_readings(rod):
    """Clean readings (the simulator's, noise 0): every case whose answer is ``ok`` has the right count, forces
    within 0.1 % and locations within 0.1 mm; most are ``ok``; none is a confident wrong answer."""
    cases = _random_cases(rod, 24, seed=0)
    loads = _loads(cases)
    u = tr.simulate(rod, loads).grating_curvature
    result = tr.Estimator(rod, tr.EstimatorOptions(noise=0.0)).estimate(u)
    ok = 0
    for b, case in enumerate(cases):
        if result.statuses[b] != "ok":
            continue
        ok += 1
        h = int(result.num_forces[b])
        assert h == len(case), (b, case, result.forces.s[b])
        s_hat, f_hat = result.forces.s[b, :h].numpy(), result.forces.f[b, :h].numpy()
        truth = np.array(case)
        assert np.abs(s_hat - truth[:, 0]).max() < 1e-4, (b, case, s_hat)
        rel = np.linalg.norm(f_hat - truth[:, 1:], axis=1) / np.linalg.norm(truth[:, 1:], axis=1)
        assert rel.max() < 1e-3, (b, case, f_hat)
    assert ok >= 20


def test_relative_readings_and_the_kernels_run_as_python_agree(rod):
    cases = [[(0.12, -0.9, 1.1), (0.2, 0.5, 0.4)], [(0.17, 0.7, 0.1)]]
    u = tr.simulate(rod, _loads(cases)).grating_curvature
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=0.0))
    total = est.estimate(u)
    shape = torch.tensor(rod.intrinsic_at(rod.gratings), dtype=torch.float64)
    relative = est.estimate(u - shape, options=dataclasses.replace(est.options, relative=True))
    as_python = est.estimate(u, options=dataclasses.replace(est.options, target="python"))
    assert total.num_forces.tolist() == relative.num_forces.tolist() == as_python.num_forces.tolist() == [2, 1]
    for other in (relative, as_python):
        assert torch.allclose(other.forces.s, total.forces.s, atol=1e-9)
        assert torch.allclose(other.forces.f, total.forces.f, atol=1e-8)
    # The same readings taken as total curvature of a straight rod's relative change would be another problem:
    assert not torch.allclose(est.estimate(u - shape).forces.f, total.forces.f, atol=1e-3)


def test_cli_simulate_on_the_preset(tmp_path, capsys):
    from torchrod.cli import main

    path = tmp_path / "forces.jsonl"
    path.write_text(json.dumps({"id": "a", "forces": [{"s": 0.2, "fx": 0.5, "fy": 0.3}]}) + "\n")
    assert main(["simulate", "--rod", "ctr250", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    expected = P.grating_curvature(tr.presets.ctr250(), _loads([[(0.2, 0.5, 0.3)]]))[0]
    assert np.allclose(out["curvature"], expected.numpy(), rtol=1e-9, atol=1e-9)
    assert out["curvature"][-1] == [12.0, 0.0]  # distal to the force the tube keeps its shape
    # The tip angle, with the twist: unloaded, the curved 100 mm turn it by 12 1/m x 0.1 m; under out-of-plane
    # forces, as the global-frame shooting's frames give it.
    case = [(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]
    forces = [{"s": s, "fx": fx, "fy": fy} for s, fx, fy in case]
    lines = [{"id": "free", "forces": []}, {"id": "loaded", "forces": forces}]
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert main(["simulate", "--rod", "ctr250", "--tip-angle", str(path)]) == 0
    free, loaded = (json.loads(x)["tip_angle"] for x in capsys.readouterr().out.splitlines())
    assert abs(free - 1.2) < 1e-6
    tip = solve_reference(tr.presets.ctr250(), case, at=[0.25]).R[-1][:, 2]
    assert abs(loaded - math.atan2(math.hypot(tip[0], tip[1]), tip[2])) < 1e-5, loaded
    # the paper's node scheme runs on it, as the library's does
    path.write_text(json.dumps({"id": "a", "forces": [{"s": 0.2, "fx": 0.5, "fy": 0.3}]}) + "\n")
    assert main(["simulate", "--rod", "ctr250", "--scheme", "nodes", "--nodes", "400", str(path)]) == 0
    nodes = json.loads(capsys.readouterr().out)["curvature"]
    model = body_frame.grating_curvature(tr.presets.ctr250(), _loads([[(0.2, 0.5, 0.3)]]), scheme="nodes", nodes=400)
    assert np.allclose(nodes, model[0].numpy(), rtol=1e-9, atol=1e-9)


def test_cli_estimate_on_the_preset_total_and_relative(tmp_path, capsys):
    from torchrod.cli import main

    rod = tr.presets.ctr250()
    u = tr.simulate(rod, _loads([[(0.18, 0.6, -0.3)]])).grating_curvature[0]
    shape = torch.tensor(rod.intrinsic_at(rod.gratings), dtype=torch.float64)
    total, relative = tmp_path / "total.jsonl", tmp_path / "relative.jsonl"
    total.write_text(json.dumps({"id": 0, "curvature": u.tolist()}) + "\n")
    relative.write_text(json.dumps({"id": 0, "curvature": (u - shape).tolist()}) + "\n")
    answers = []
    for path, extra in ((total, []), (relative, ["--relative"])):
        assert main(["estimate", "--rod", "ctr250", "--noise", "0.05", *extra, str(path)]) == 0
        answers.append(json.loads(capsys.readouterr().out))
    for a in answers:
        assert a["status"] == "ok" and a["num_forces"] == 1
        assert a["forces"][0]["s"] == pytest.approx(0.18, abs=1e-6)
        assert a["forces"][0]["fx"] == pytest.approx(0.6, abs=1e-5) and a["forces"][0]["fy"] == pytest.approx(
            -0.3, abs=1e-5
        )


def test_evaluate_rows_on_the_preset_start_from_its_shape():
    from torchrod.cli.commands.evaluate import misfit_cell, zero_cell

    rod = tr.presets.ctr250()
    assert zero_cell(rod, 0.1, 12, batch_size=12)["count_accuracy"] >= 0.9
    assert misfit_cell(rod, 0.1, 3, batch_size=3)["misfit"] == 1.0


def test_a_network_layout_carries_the_precurvature(rod):
    """The dimensionless rod a network is trained on reproduces the preset's readings (u L for s / L and f L^2 / EI:
    the scaling holds with precurvature and torsion too); a network for one precurvature refuses another rod."""
    from torchrod.learn.network import NetConfig, WarmStartNet, unit_rod
    from torchrod.learn.warm_start import WarmStart

    config = NetConfig.for_rod(rod)
    assert config.intrinsic_curvature == ((0.6, 1.0, 3.0, 0.0),)
    assert config.torsion_ratio == pytest.approx(1 / 1.33)
    assert NetConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    unit = unit_rod(config)
    L, EI = rod.length, rod.bending_stiffness
    case = [(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]
    scaled = [(s / L, fx * L * L / EI, fy * L * L / EI) for s, fx, fy in case]
    u = tr.simulate(rod, _loads([case])).grating_curvature
    u_unit = tr.simulate(unit, _loads([scaled])).grating_curvature
    assert torch.allclose(u_unit, u * L, rtol=1e-9, atol=1e-9)
    # body_frame.grating_curvature (the training's physics loss, calibration) takes the precurved path too
    from torchrod.model.body_frame import grating_curvature

    assert torch.allclose(grating_curvature(rod, _loads([case])), u, rtol=1e-12, atol=1e-12)
    net = WarmStartNet(config)
    assert WarmStart(net, rod, {}).matches(rod)
    with pytest.raises(ValueError, match="precurvature"):
        WarmStart(net, rod.with_(intrinsic_curvature=[(0.15, 0.25, 10.0, 0.0)]), {})
    with pytest.raises(ValueError, match="relative positions"):
        WarmStart(net, tr.presets.nitinol290(), {})


def test_the_papers_node_scheme_on_a_precurved_rod(rod):
    """Forces spread onto q nodes (the paper's scheme) on the precurved tube: the body-frame march and the
    global-frame shooting with the same spreading agree, and both approach the exact point loads as q^-2."""
    from torchrod.model.body_frame import grating_curvature

    case = [(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]
    exact = grating_curvature(rod, _loads([case]))[0].numpy()
    errors = []
    for q in (50, 100):
        nodes = grating_curvature(rod, _loads([case]), scheme="nodes", nodes=q)[0].numpy()
        bvp = ShootingSolver(rod, nodes=q, scheme="nodes", jacobian="dp").solve(case, at=rod.gratings).u[:, :2]
        assert np.abs(nodes - bvp).max() < 3e-5 * np.abs(bvp).max()
        errors.append(np.abs(nodes - exact).max() / np.abs(exact).max())
    assert 3.0 < errors[0] / errors[1] < 5.0, errors


def test_shapes_of_the_precurved_tube_take_its_twist(rod):
    """Unloaded: a straight 150 mm and an arc of radius 1/12 m turning 1.2 rad towards -d2. Loaded out of plane
    (it twists): the shape from simulate's (u_x, u_y, u_z) matches the global shooting's centreline."""
    theta = 0.1 * 12.0
    unloaded = shape(rod, _loads([[(0.1, 0.0, 0.0)]]), samples=801)
    tip = unloaded.position[0, -1].numpy()
    expected = np.array([0.0, -(1.0 - np.cos(theta)) / 12.0, 0.15 + np.sin(theta) / 12.0])
    assert np.abs(tip - expected).max() < 1e-6, (tip, expected)
    case = [(0.12, -0.9, 1.1), (0.22, 0.6, -0.4)]
    sim = tr.simulate(rod, _loads([case]), samples=5)
    assert sim.twist is not None and float(sim.twist.abs().max()) > 1.0
    loaded = shape(rod, _loads([case]), samples=801)
    ref = solve_reference(rod, case, at=[rod.length])
    assert np.abs(loaded.position[0, -1].numpy() - ref.P[-1]).max() < 1e-5
    assert np.abs(loaded.frames[0, -1].numpy() - ref.R[-1]).max() < 1e-4
