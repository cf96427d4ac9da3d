"""The scenes: construction, exact solutions, and constraint drift over long runs.

The pendulum is compared with the exact large-amplitude solution,
``theta(t) = 2 arcsin(k sn(K - w0 t, k^2))`` with ``k = sin(theta0 / 2)``, ``w0 = sqrt(g / L)``
and ``K = K(k^2)`` the complete elliptic integral (scipy's parameter convention, m = k^2).
"""

import numpy as np
import pytest
from scipy.special import ellipj, ellipk

from constrained_particles import (
    METHODS,
    CircularWire,
    DampedSpring,
    Gravity,
    HorizontalWire,
    ParticleSystem,
    Wall,
    scenes,
)


def exact_pendulum_angle(t: float, theta0: float, length: float, g: float = 9.81) -> float:
    """Angle (rad) from the downward vertical of an ideal pendulum released from rest at theta0."""
    k = np.sin(theta0 / 2)
    sn = ellipj(ellipk(k**2) - np.sqrt(g / length) * t, k**2)[0]
    return float(2 * np.arcsin(k * sn))


def pendulum_angle(x: np.ndarray) -> float:
    return float(np.arctan2(x[0], -x[1]))


def test_exact_solution_is_right():
    """The reference itself: starts at theta0 from rest and obeys theta'' = -(g/L) sin(theta)."""
    theta0, L = 2.0, 1.3
    assert exact_pendulum_angle(0.0, theta0, L) == pytest.approx(theta0, abs=1e-12)
    h = 1e-4
    for t in (0.3, 1.1, 1.7):
        th = [exact_pendulum_angle(t + d * h, theta0, L) for d in (-1, 0, 1)]
        assert (th[0] - 2 * th[1] + th[2]) / h**2 == pytest.approx(-9.81 / L * np.sin(th[1]),
                                                                   rel=1e-5, abs=1e-5)
    assert (exact_pendulum_angle(h, theta0, L) - exact_pendulum_angle(-h, theta0, L)) == \
        pytest.approx(0.0, abs=1e-12)


def test_pendulum_matches_exact_large_amplitude_solution():
    """Done-when: radius 1.3 m, released at 2.0 rad, rk4 at dt = 1e-3, within 1e-6 rad at 2 s."""
    L, theta0 = 1.3, 2.0
    s = ParticleSystem()
    p = s.add_particle((L * np.sin(theta0), -L * np.cos(theta0)), velocity=(0.0, 0.0), mass=1.0)
    s.add(Gravity((0.0, -9.81)), CircularWire(p, center=(0.0, 0.0), radius=L))
    for _ in range(2000):
        s.step(1e-3, method="rk4")
    assert s.t == pytest.approx(2.0, abs=1e-12)
    exact = exact_pendulum_angle(2.0, theta0, L)
    assert abs(pendulum_angle(s.x[p]) - exact) < 1e-6
    assert abs(exact) > 0.1  # not a trivially easy point of the swing


def test_pendulum_scene_is_the_same_pendulum():
    s = scenes.pendulum(length=1.3, angle=2.0, mass=0.7)
    assert pendulum_angle(s.x[0]) == pytest.approx(2.0, abs=1e-14)
    assert np.linalg.norm(s.x[0]) == pytest.approx(1.3, abs=1e-14)
    assert not s.v.any() and s.mass[0] == 0.7
    for _ in range(500):
        s.step(1e-3)
    assert pendulum_angle(s.x[0]) == pytest.approx(exact_pendulum_angle(0.5, 2.0, 1.3), abs=1e-7)


def test_pendulum_converges_at_fourth_order():
    errors = []
    for h in (0.04, 0.02, 0.01):
        s = scenes.pendulum(length=1.3, angle=2.0)
        for _ in range(int(round(1.0 / h))):
            s.step(h)
        errors.append(abs(pendulum_angle(s.x[0]) - exact_pendulum_angle(1.0, 2.0, 1.3)))
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(np.abs(orders - 4) < 0.3), (errors, orders)


def max_residual_over_run(s: ParticleSystem, seconds: float, dt: float = 1e-3
                          ) -> tuple[float, float]:
    """Largest |C| and |Cdot| seen after any step of an rk4 run."""
    worst_C = worst_Cdot = 0.0
    for _ in range(int(round(seconds / dt))):
        s.step(dt, method="rk4")
        C, Cdot = s.constraint_residual()
        worst_C = max(worst_C, float(np.abs(C).max()))
        worst_Cdot = max(worst_Cdot, float(np.abs(Cdot).max()))
    return worst_C, worst_Cdot


# The residual of a feedback-stabilised run (ks, kd > 0) does not accumulate: each step's solve
# holds it at the solver's tolerance. Measured over 10 s at dt = 1 ms (rk4), the largest |C| and
# |Cdot| of each run below are reached within its first 3 s and then recur or decay (the crank
# and slider repeat their motion every 3 s, the pendulum every 3.4 s, the chain's swing decays,
# the cloth's residual stays near 1e-16), and every 10 s maximum is at least 1e4 times under its
# bar. So each run lasts as long as its motion needs to show its worst case, with the bars of
# the 10 s runs: 3 s for the free slider-crank and the cloth, 4 s (more than a period) for the
# pendulum, 2 s for the damped chain, and 1 s with projection (which zeroes C after every step,
# so a longer run adds nothing).
@pytest.mark.parametrize("project, seconds", [(False, 3.0), (True, 1.0)],
                         ids=["free", "projected"])
def test_wire_mixture_residual_stays_small(project, seconds):
    """Done-when: |C| < 1e-4 without projection and < 1e-9 with it, rk4, dt = 1e-3."""
    s = scenes.wire_mixture()
    s.project_each_step = project
    E0 = s.energy()
    worst_C, worst_Cdot = max_residual_over_run(s, seconds)
    assert worst_C < (1e-9 if project else 1e-4)
    assert worst_Cdot < (1e-9 if project else 1e-4)
    assert abs(s.energy() - E0) < 1e-4 * s.mass.sum() * 9.81  # undamped: energy is kept too


@pytest.mark.parametrize("name, seconds", [("pendulum", 4.0), ("cloth", 3.0),
                                           ("angular_chain", 2.0)])
def test_constrained_scene_residual_stays_small(name, seconds):
    build = {"pendulum": lambda: scenes.pendulum(angle=2.5),
             "cloth": lambda: scenes.cloth(nx=5, ny=5, push=0.05),
             "angular_chain": lambda: scenes.angular_chain(links=4)}[name]
    worst_C, worst_Cdot = max_residual_over_run(build(), seconds)
    assert worst_C < 1e-6
    assert worst_Cdot < 1e-6


# ---------------------------------------------------------------- every scene
@pytest.mark.parametrize("name", sorted(scenes.SCENES))
def test_scene_builds_with_defaults_and_steps_with_every_method(name):
    base = scenes.SCENES[name]()
    assert base.n > 0 and base.forces
    assert np.all(np.isfinite(base.x)) and np.all(np.isfinite(base.v))
    C, Cdot = base.constraint_residual()
    assert np.abs(C).max(initial=0.0) < 1e-9 and np.abs(Cdot).max(initial=0.0) < 1e-9
    for method in METHODS:
        s = base.copy()
        for _ in range(3):
            s.step(1e-3, method=method)
        assert np.all(np.isfinite(s.x)) and np.isfinite(s.energy())
        assert s.t == pytest.approx(3e-3)


def test_spring_pair_keeps_its_centre_of_mass():
    s = scenes.spring_pair(separation=1.0, rest=0.6)
    assert np.linalg.norm(s.x[1] - s.x[0]) == pytest.approx(1.0)
    assert s.forces[0].rest[0] == 0.6
    for _ in range(500):
        s.step(1e-3)
    np.testing.assert_allclose(s.x.mean(axis=0), 0.0, atol=1e-14)
    np.testing.assert_allclose((s.mass[:, None] * s.v).sum(axis=0), 0.0, atol=1e-14)


def test_gravity_scene_projectiles_follow_parabolas_then_bounce():
    s = scenes.gravity(count=4, floor=-1.0)
    x0, v0 = s.x.copy(), s.v.copy()
    g = np.array([0.0, -9.81])
    for _ in range(200):
        s.step(1e-3)
    t = s.t
    np.testing.assert_allclose(s.x, x0 + v0 * t + 0.5 * g * t**2, atol=1e-12)
    np.testing.assert_allclose(s.v, v0 + g * t, atol=1e-12)
    lowest, rising = 0.0, False
    for _ in range(1500):
        s.step(1e-3)
        lowest = min(lowest, s.x[:, 1].min())
        rising |= bool(np.any((s.x[:, 1] < -0.9) & (s.v[:, 1] > 0)))
    assert lowest < -1.0 and lowest > -1.05  # touched the floor, but a contact, not a fall
    assert rising  # bounced


def test_cloth_layout_and_springs():
    nx, ny, h = 5, 4, 0.1
    s = scenes.cloth(nx=nx, ny=ny, spacing=h, wire_height=0.2, push=0.3)
    rows, cols = np.divmod(np.arange(s.n), nx)
    np.testing.assert_allclose(s.x, np.stack([cols * h, 0.2 - rows * h], axis=1), atol=1e-15)
    springs = next(f for f in s.forces if isinstance(f, DampedSpring))
    structural = nx * (ny - 1) + ny * (nx - 1)
    shear = 2 * (nx - 1) * (ny - 1)
    bend = nx * (ny - 2) + ny * (nx - 2)
    assert len(springs) == structural + shear + bend
    # E = -m g . x = m 9.81 y: only gravity, the springs start at their rest lengths
    assert s.potential_energy() == pytest.approx(9.81 * np.sum(s.mass * s.x[:, 1]))
    wire = next(c for c in s.constraints if isinstance(c, HorizontalWire))
    np.testing.assert_array_equal(np.sort(wire.particles), np.arange(nx))
    assert any(isinstance(f, Wall) for f in s.forces)


def test_pushed_cloth_hits_the_wall_and_is_held_back():
    s = scenes.cloth(nx=4, ny=3, push=0.2, wall_x=0.5)
    max_x, hit = 0.0, False
    for _ in range(1500):
        s.step(2e-3)
        max_x = max(max_x, s.x[:, 0].max())
        hit |= bool(np.any(s.x[:, 0] > 0.5))
    assert hit and max_x < 0.55
    np.testing.assert_allclose(s.x[:4, 1], 0.0, atol=1e-9)  # the top row stays on its wire


def test_angular_chain_starts_straight_and_swings_down():
    s = scenes.angular_chain(links=4, link=0.2)
    assert s.fixed[0] and not s.fixed[1:].any()
    assert s.potential_energy() == pytest.approx(0.0, abs=1e-12)  # gravity at y = 0, no bending
    for _ in range(300):
        s.step(1e-3)
    assert np.all(s.x[1:, 1] < 0)
    np.testing.assert_allclose(np.linalg.norm(np.diff(s.x, axis=0), axis=1), 0.2, atol=1e-9)


def test_wire_mixture_is_a_slider_crank():
    s = scenes.wire_mixture(radius=0.3, rod=0.8, wire_height=0.1)
    C, Cdot = s.constraint_residual()
    assert np.abs(C).max() < 1e-12 and np.abs(Cdot).max() < 1e-12
    assert np.linalg.norm(s.x[0]) == pytest.approx(0.3)
    assert s.x[1, 1] == pytest.approx(0.1)
    assert np.linalg.norm(s.x[0] - s.x[1]) == pytest.approx(0.8)
    assert np.linalg.norm(s.v[0]) > 0


@pytest.mark.parametrize(("build", "kwargs", "match"), [
    ("cloth", {"nx": 1}, "nx"),
    ("cloth", {"ny": 0}, "ny"),
    ("cloth", {"spacing": 0.0}, "spacing"),
    ("wire_mixture", {"radius": 0.5, "rod": 0.4}, "rod"),
    ("angular_chain", {"links": 1}, "links"),
    ("pendulum", {"length": 0.0}, "length"),
    ("pendulum", {"length": -1.0}, "length"),
    ("gravity", {"count": 0}, "count"),
    ("spring_pair", {"mass": 0.0}, "mass"),
    ("spring_pair", {"rest": -0.1}, "rest"),
])
def test_bad_scene_parameters(build, kwargs, match):
    with pytest.raises(ValueError, match=match):
        scenes.SCENES[build](**kwargs)
