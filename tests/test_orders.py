"""Measured convergence orders (quick form), the references they rest on, and the report."""

import json

import numpy as np
import pytest

from constrained_particles import METHODS, ORDERS, scenes
from cparticles.cli import main as cli_main
from verification import orders as O
from verification import report as R


def test_exact_pendulum_matches_an_independent_reference():
    # two independent answers to the same question: elliptic functions and DOP853 on our ODE
    times = O.checkpoints(1.0)
    exact = O.pendulum_exact(1.0, 0.5, scenes.G)(times)
    assert np.max(np.abs(O.reference_positions(scenes.pendulum(), times) - exact)) < 1e-9


def test_exact_pendulum_conserves_energy():
    times = np.linspace(0.0, 2.0, 201)
    xy = O.pendulum_exact(1.2, -0.9, 9.81)(times)[:, 0]
    v = np.gradient(xy, times, axis=0, edge_order=2)
    energy = 0.5 * np.sum(v**2, axis=1) + 9.81 * xy[:, 1]
    assert np.ptp(energy) < 1e-3 * 9.81 * 1.2  # finite-difference velocities: 1e-3 is generous
    assert np.allclose(np.linalg.norm(xy, axis=1), 1.2)


@pytest.mark.parametrize("case", sorted(O.CASES))
@pytest.mark.parametrize("method", sorted(METHODS))
def test_measured_order_matches_theory(case, method):
    if method not in ORDERS:
        pytest.skip(f"{method} declares no theoretical order")
    result = O.measure_order(O.CASES[case], method, quick=True)
    assert all(np.isfinite(result.errors))
    assert abs(result.order - ORDERS[method]) <= 0.2, result


def test_steps_divide_the_checkpoints():
    for method in METHODS:
        for quick in (False, True):
            for h in O.default_steps(method, quick):
                steps = 0.1 / h
                assert abs(steps - round(steps)) < 1e-9


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="method"):
        O.measure_order(O.CASES["pendulum"], "leapfrog")
    with pytest.raises(ValueError, match="cases"):
        O.measure_orders(["nowhere"])
    with pytest.raises(ValueError, match="length"):
        O.pendulum_exact(-1.0, 0.5, 9.81)
    with pytest.raises(ValueError, match="h = "):
        O.run_positions(scenes.pendulum(), "rk4", 0.03, O.checkpoints(1.0))


def test_cli_verify_orders_json(capsys):
    assert cli_main(["verify", "orders", "--quick", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data) == set(O.CASES)
    for per_method in data.values():
        assert set(per_method) == set(METHODS)
        for method, order in per_method.items():
            assert method not in ORDERS or abs(order - ORDERS[method]) <= 0.2


def test_report_writes_markdown_json_and_plots(tmp_path):
    data = R.collect(quick=True, progress=False, cases=["pendulum"],
                     pymunk_scenes=["pendulum"], durations=(0.05, 0.02, 0.02),
                     long_steps=30)
    R.write(data, tmp_path)
    text = (tmp_path / "report.md").read_text()
    for heading in ("Convergence orders", "pymunk cross-check",
                    "Does the cloth rise above the wire?", "Spring and damping constants",
                    "Long-run energy"):
        assert heading in text
    saved = json.loads((tmp_path / "report.json").read_text())
    assert set(saved["orders"]["pendulum"]) == set(METHODS)
    assert len(saved["section_via"]) == 4
    for system in ("pendulum", "chain_of_rods", "spring_chain"):
        assert set(saved["long_run"][system]) == set(METHODS)
    for name in ("convergence", "work_precision", "energy_drift", "constraint_drift", "cloth",
                 "long_run_energy"):
        png = (tmp_path / f"{name}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_static_equilibrium_balances_the_forces():
    s = scenes.cloth(nx=3, ny=3, ks=10.0, kd=1.0, wall_x=None)
    x = R.static_equilibrium(s)
    F = s.applied_forces(x, np.zeros_like(x))
    top = s.constraints[0].particles
    F[top, 1] = 0.0  # the wire carries the vertical load of the top row
    assert np.max(np.abs(F)) < 1e-6 * np.max(s.mass) * scenes.G * s.n
