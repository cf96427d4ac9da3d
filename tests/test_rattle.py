"""rattle: the constrained velocity Verlet step, its orders, energy and errors.

The references are independent of the code under test: the exact pendulum (Jacobi elliptic
functions) and DOP853 runs of the same ODE through :mod:`verification.orders`, the blocks'
definitions of C, energy bookkeeping, a separately built (single) system for the tiled one, and
symplectic Euler as the counter-example that the energy checks must catch.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings

import envs  # noqa: F401  (registers the environments)
from constrained_particles import (
    METHODS,
    ORDERS,
    CircularWire,
    DampedSpring,
    Gravity,
    ParticleSystem,
    RattleSolveError,
    Rod,
    SimulationDiverged,
    scenes,
)
from constrained_particles import rattle as rattle_module
from verification import orders as O
from verification.longrun import energy_run
from verification.strategies import random_system, systems


def test_registered_with_order_two():
    assert METHODS["rattle"] is rattle_module.rattle
    assert ORDERS["rattle"] == 2
    assert issubclass(RattleSolveError, SimulationDiverged)


# ---------------------------------------------------------------------- orders
def _damped_case() -> O.Case:
    # seed 85 with damping: damped springs, a damped angular spring and drag on every
    # constraint kind (a different system from the orders table's undamped seed 85)
    return O.Case("damped", lambda: random_system(O.RANDOM_SEED, gravity=True, damped=True), 1.0)


def test_second_order_with_velocity_dependent_forces():
    # the velocity-dependent forces of the second half-kick see the predicted v1 = v0 + h a;
    # evaluated at v_half instead the same run measures order 1.11
    s = _damped_case().build()
    assert any(np.any(getattr(f, "kd", 0.0)) for f in s.forces)
    result = O.measure_order(_damped_case(), "rattle", quick=True)
    assert abs(result.order - 2) <= 0.2, result


# ---------------------------------------------------------------------- constraints
def _distances(s: ParticleSystem) -> np.ndarray:
    """|C_r| / |grad C_r| from the blocks' definitions: the distance (m) off each constraint."""
    zero = np.zeros_like(s.x)
    C = np.concatenate([c.evaluate(s.x, zero)[0] for c in s.constraints])
    grad = np.zeros_like(C)
    for k in range(s.x.size):  # C is at most quadratic: central differences are exact
        dx = np.zeros(s.x.size)
        dx[k] = 1e-3
        plus = np.concatenate([c.evaluate(s.x + dx.reshape(s.x.shape), zero)[0]
                               for c in s.constraints])
        minus = np.concatenate([c.evaluate(s.x - dx.reshape(s.x.shape), zero)[0]
                                for c in s.constraints])
        grad += ((plus - minus) / 2e-3) ** 2
    return np.abs(C) / np.sqrt(grad)


@settings(max_examples=15)
@given(systems(damped=True))
def test_constraints_hold_to_roundoff_after_every_step(s):
    if not s.constraints:
        return
    for _ in range(30):
        s.step(5e-3, method="rattle")
        assert _distances(s).max() < 1e-12 * max(1.0, np.abs(s.x).max())
        _, Cdot = s.constraint_residual()
        assert np.abs(Cdot).max() < 1e-8 * max(1.0, np.abs(s.v).max())


def test_straight_and_curved_constraints_hold_on_the_slider_crank():
    s = scenes.wire_mixture()
    for _ in range(500):
        s.step(1e-2, method="rattle")
        assert _distances(s).max() < 1e-12


def test_constraint_free_system_is_velocity_verlet():
    # a harmonic oscillator: velocity Verlet's one-step map is known in closed form
    k, m, h = 4.0, 0.5, 0.05
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((0.3, 0.0), velocity=(0.0, 0.0), mass=m)
    s.add(DampedSpring(o, a, rest=0.0, ks=k))
    q, p = 0.3, 0.0
    for _ in range(20):
        s.step(h, method="rattle")
        p_half = p - 0.5 * h * k * q / m
        q = q + h * p_half
        p = p_half - 0.5 * h * k * q / m
    assert s.x[a, 0] == pytest.approx(q, abs=1e-15)
    assert s.v[a, 0] == pytest.approx(p, abs=1e-15)


# ---------------------------------------------------------------------- energy
def test_pendulum_energy_done_when_at_a_tenth_of_the_horizon():
    # The published bars are for 1e5 steps (measured: max |E - E0| = 2.33e-4 J, trend
    # 1.2e-7 J = 0.05 % of the 2.36e-4 J peak-to-peak, max |C| = 9.4e-14;
    # docs/verification/long_run.md).
    # Over 1e4 steps a linear drift would be 10x smaller: the trend bar is 0.1 % here.
    run = energy_run(scenes.pendulum(angle=2.0), "rattle", 2e-3, 10_000, samples=10_000)
    assert run["diverged_at"] is None
    assert run["max_error"] < 0.05 / 10
    assert abs(run["trend"]) < 1e-3 * run["oscillation"]
    assert run["max_constraint"] < 1e-9


@pytest.mark.parametrize(("build", "steps"), [(lambda: scenes.pendulum(angle=2.0), 3000),
                                              (scenes.wire_mixture, 2000)],
                         ids=["pendulum", "slider_crank"])
def test_energy_error_does_not_grow(build, steps):
    # bounded: the second half of a run is no worse than the first (measured: equal to 1e-5);
    # symplectic Euler's multiplier from the old velocity makes it grow about linearly on
    # curved constraints (measured: 1.9x and 2.7x). The chaotic chain of rods has bounded but
    # spiky errors (fast whips); the report measures it over 1e5 steps.
    def halves(method):
        run = energy_run(build(), method, 2e-3, steps, samples=steps)
        err = np.abs(np.array(run["energy_error"]))
        return err[:steps // 2].max(), err[steps // 2:].max()

    first, second = halves("rattle")
    assert second < 1.05 * first
    first, second = halves("symplectic_euler")
    assert second > 1.5 * first


def test_energy_error_falls_at_second_order():
    s = scenes.wire_mixture()
    errors = [energy_run(s, "rattle", h, int(round(1.0 / h)), samples=200)["max_error"]
              for h in (4e-3, 2e-3, 1e-3)]
    slope = np.polyfit(np.log([4e-3, 2e-3, 1e-3]), np.log(errors), 1)[0]
    assert 1.8 < slope < 2.3


# ---------------------------------------------------------------------- batching, errors
def test_tiled_copies_step_like_the_single_system():
    s = scenes.wire_mixture()
    batch = s.tile(3)
    batch.v[s.n:] *= -0.5  # different motions per copy; project to stay consistent
    batch.project()
    singles = [s.copy() for _ in range(3)]
    for c, single in enumerate(singles):
        single.x, single.v = batch.x[c * s.n:(c + 1) * s.n].copy(), batch.v[c * s.n:(c + 1) * s.n]
    for _ in range(50):
        batch.step(5e-3, method="rattle")
        for single in singles:
            single.step(5e-3, method="rattle")
    for c, single in enumerate(singles):
        np.testing.assert_allclose(batch.x[c * s.n:(c + 1) * s.n], single.x, rtol=0, atol=1e-12)


def test_tiled_copies_with_independent_rows_are_bit_for_bit_the_single_systems():
    # one row per copy (J W J^T diagonal): each copy's Newton iterations stop on their own
    angles = (0.3, 1.0, 2.5)
    singles = [scenes.pendulum(angle=a) for a in angles]
    batch = singles[0].tile(3)
    batch.constraints[0].center[:] = 0.0
    for c, single in enumerate(singles):
        batch.x[c] = single.x[0]
    for _ in range(200):
        batch.step(5e-3, method="rattle")
        for single in singles:
            single.step(5e-3, method="rattle")
    for c, single in enumerate(singles):
        assert batch.x[c].tobytes() == single.x[0].tobytes()
        assert batch.v[c].tobytes() == single.v[0].tobytes()


def test_too_large_a_step_names_the_rows_and_keeps_the_state():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0), velocity=(0.0, 30.0))
    b = s.add_particle((0.0, -1.0), velocity=(0.0, 0.0))
    s.add(Gravity(), Rod(o, a), CircularWire(b, (0.0, 0.0), 1.0))
    x0, v0 = s.x.copy(), s.v.copy()
    with pytest.raises(RattleSolveError, match=r"rows \[0\] \(Rod\)"):
        s.step(0.5, method="rattle")
    np.testing.assert_array_equal(s.x, x0)
    np.testing.assert_array_equal(s.v, v0)
    s.step(1e-3, method="rattle")  # a sensible step goes on from the kept state


# ---------------------------------------------------------------------- environments
@pytest.mark.parametrize("env_id", ["ClothSlide-v0", "SliderCrank-v0"])
def test_envs_accept_rattle(env_id):
    env = gym.make(env_id, integrator="rattle")
    obs, _ = env.reset(seed=0)
    for _ in range(40):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.isfinite(reward)
        assert not info.get("diverged", False)
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
