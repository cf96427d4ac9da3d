"""The long-run energy experiment (verification.longrun): its bookkeeping against closed forms."""

import json

import numpy as np
import pytest

from constrained_particles import METHODS, DampedSpring, ParticleSystem
from verification import longrun as L
from verification.__main__ import run as verification_main


def _oscillator(k: float = 4.0, m: float = 0.5) -> ParticleSystem:
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((0.3, 0.0), mass=m)
    s.add(DampedSpring(o, a, rest=0.0, ks=k))
    return s


def test_forward_euler_energy_growth_matches_its_closed_form():
    # forward Euler multiplies a linear oscillator's energy by exactly 1 + (w h)^2 per step
    k, m, h, steps = 4.0, 0.5, 0.01, 400
    s = _oscillator(k, m)
    run = L.energy_run(s, "euler", h, steps, samples=100)
    e0 = 0.5 * k * 0.3**2
    expected = e0 * ((1 + k / m * h * h) ** steps - 1)
    assert run["e0"] == pytest.approx(e0, rel=1e-15)
    assert run["max_error"] == pytest.approx(expected, rel=1e-9)
    assert len(run["t"]) == 100 and run["t"][-1] == pytest.approx(steps * h)
    assert run["trend"] > 0 and run["trend_ratio"] > 1  # a drift


def test_bounded_error_has_a_small_trend_ratio():
    run = L.energy_run(_oscillator(), "rattle", 0.01, 4000, samples=4000)
    assert run["trend_ratio"] < 0.05 and run["max_error"] < 1e-3 * run["e0"]
    assert run["max_constraint"] == 0.0 and not run["constrained"]


def test_bad_names_are_value_errors():
    with pytest.raises(ValueError, match="method"):
        L.energy_run(_oscillator(), "leapfrog", 0.01, 10)
    with pytest.raises(ValueError, match="systems"):
        L.long_runs(10, systems=["nowhere"])
    with pytest.raises(ValueError, match="links"):
        L.chain_of_rods(0)
    with pytest.raises(ValueError, match="count"):
        L.spring_chain(0)


def test_cli_energy_json(capsys):
    assert verification_main(["energy", "--steps", "20", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data) == set(L.SYSTEMS)
    for per_method in data.values():
        assert set(per_method) == set(METHODS)
        assert all(np.isfinite(r["max_error"]) for r in per_method.values())
