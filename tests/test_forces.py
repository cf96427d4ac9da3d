"""Force blocks against independent finite differences and hand-computed formulas.

Conservative forces must equal minus the central-difference gradient of their ``potential``;
damping terms are checked separately against the formulas of docs/physics.md, computed here
element by element (the library computes them vectorized). Internal forces must conserve linear
and angular momentum.
"""

import numpy as np
import pytest

from constrained_particles import (
    AngularSpring,
    ConstantForce,
    DampedSpring,
    Drag,
    Gravity,
    MouseSpring,
    ParticleSystem,
    Wall,
)

SEEDS = [0, 1, 2, 3]


def separated_points(rng: np.random.Generator, n: int, spacing: float = 1.0) -> np.ndarray:
    """``n`` random points at least ``0.4 * spacing`` apart: a jittered grid, shuffled."""
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)
    pts = grid[rng.permutation(len(grid))[:n]] * spacing
    return pts + rng.uniform(-0.3, 0.3, (n, 2)) * spacing + rng.uniform(-5, 5, 2)


def forces_of(term, x, v, mass) -> np.ndarray:
    F = np.zeros_like(x)
    term.accumulate(x, v, mass, F)
    return F


def minus_grad(term, x, mass, eps: float = 1e-6) -> np.ndarray:
    """-dE/dx by central differences of ``term.potential``."""
    g = np.zeros_like(x)
    for p in range(x.shape[0]):
        for d in range(2):
            xp, xm = x.copy(), x.copy()
            xp[p, d] += eps
            xm[p, d] -= eps
            g[p, d] = (term.potential(xp, mass) - term.potential(xm, mass)) / (2 * eps)
    return -g


def bound(term, x, v=None, mass=None):
    """A system holding ``x`` (and ``v``, ``mass``) with ``term`` added (fills defaults)."""
    s = ParticleSystem()
    s.add_particles(x, v, 1.0 if mass is None else mass)
    s.add(term)
    return s


def assert_gradient(term, x, mass):
    F = forces_of(term, x, np.zeros_like(x), mass)
    G = minus_grad(term, x, mass)
    scale = max(1.0, np.abs(G).max())
    np.testing.assert_allclose(F, G, rtol=1e-6, atol=1e-6 * scale)
    assert np.abs(F).max() > 0, "the configuration should exert some force"


def signed_angle(p: np.ndarray, q: np.ndarray) -> float:
    """Signed angle from vector p to vector q, computed from complex numbers."""
    return float(np.angle(complex(q[0], q[1]) / complex(p[0], p[1])))


def moments(F: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Total force and total torque about the origin."""
    return F.sum(axis=0), float(np.sum(x[:, 0] * F[:, 1] - x[:, 1] * F[:, 0]))


# ---------------------------------------------------------------- gravity, constant, drag
@pytest.mark.parametrize("seed", SEEDS)
def test_gravity_is_minus_gradient(seed):
    rng = np.random.default_rng(seed)
    x = separated_points(rng, 6)
    mass = rng.uniform(0.1, 3.0, 6)
    g = rng.normal(size=2) * 5
    assert_gradient(Gravity(g), x, mass)
    sub = Gravity(g, particles=[1, 4])
    assert_gradient(sub, x, mass)
    F = forces_of(sub, x, np.zeros_like(x), mass)
    np.testing.assert_array_equal(F[[0, 2, 3, 5]], 0.0)
    np.testing.assert_allclose(F[4], mass[4] * g, rtol=1e-15)


def test_constant_force_sums_repeated_particles_and_has_no_potential():
    x = separated_points(np.random.default_rng(0), 3)
    f = ConstantForce([0, 2, 0], [(1.0, 2.0), (3.0, 4.0), (0.5, -1.0)])
    F = forces_of(f, x, np.zeros_like(x), np.ones(3))
    np.testing.assert_allclose(F, [[1.5, 1.0], [0.0, 0.0], [3.0, 4.0]])
    assert f.potential(x, np.ones(3)) == 0.0
    f.force[:] = 0.0  # the environments write their actions into this array
    assert not forces_of(f, x, np.zeros_like(x), np.ones(3)).any()


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_drag_opposes_velocity(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 5), rng.normal(size=(5, 2))
    np.testing.assert_allclose(forces_of(Drag(0.7), x, v, np.ones(5)), -0.7 * v)
    F = forces_of(Drag(0.7, particles=[3]), x, v, np.ones(5))
    np.testing.assert_allclose(F[3], -0.7 * v[3])
    assert not np.delete(F, 3, axis=0).any()


# ---------------------------------------------------------------- damped spring
def random_springs(rng, n, k):
    pairs = np.array([rng.choice(n, 2, replace=False) for _ in range(k)])
    return pairs[:, 0], pairs[:, 1]


@pytest.mark.parametrize("seed", SEEDS)
def test_spring_force_is_minus_gradient(seed):
    rng = np.random.default_rng(seed)
    x = separated_points(rng, 7)
    i, j = random_springs(rng, 7, 12)
    spring = DampedSpring(i, j, rest=rng.uniform(0.2, 2.0, 12), ks=rng.uniform(1, 50, 12))
    assert_gradient(spring, x, np.ones(7))


@pytest.mark.parametrize("seed", SEEDS)
def test_spring_damping_matches_hand_formula(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 6), rng.normal(size=(6, 2))
    i, j = random_springs(rng, 6, 8)
    kd = rng.uniform(0.1, 3.0, 8)
    rest = rng.uniform(0.2, 2.0, 8)
    damped = DampedSpring(i, j, rest=rest, ks=7.0, kd=kd)
    elastic = DampedSpring(i, j, rest=rest, ks=7.0, kd=0.0)
    expected = np.zeros_like(x)
    for e in range(8):
        l = x[i[e]] - x[j[e]]
        u = l / np.linalg.norm(l)
        f = -kd[e] * np.dot(v[i[e]] - v[j[e]], u) * u
        expected[i[e]] += f
        expected[j[e]] -= f
    np.testing.assert_allclose(forces_of(damped, x, v, np.ones(6)) - forces_of(elastic, x, v,
                                                                                 np.ones(6)),
                               expected, rtol=1e-9, atol=1e-12)


def test_spring_rest_defaults_to_current_length_and_energy():
    x = np.array([[0.0, 0.0], [3.0, 4.0]])
    spring = DampedSpring(0, 1, ks=2.0)
    s = bound(spring, x)
    np.testing.assert_allclose(spring.rest, [5.0])
    assert s.potential_energy() == 0.0
    s.x[1] = (6.0, 8.0)
    assert s.potential_energy() == pytest.approx(0.5 * 2.0 * 5.0**2)


def test_spring_of_zero_length_exerts_no_force():
    x = np.array([[1.0, 1.0], [1.0, 1.0]])
    F = forces_of(DampedSpring(0, 1, rest=1.0, ks=5.0, kd=1.0), x, np.ones((2, 2)), np.ones(2))
    assert np.all(np.isfinite(F)) and not F.any()


# ---------------------------------------------------------------- angular spring
def random_triples(rng, n, k):
    t = np.array([rng.choice(n, 3, replace=False) for _ in range(k)])
    return t[:, 0], t[:, 1], t[:, 2]


@pytest.mark.parametrize("seed", SEEDS)
def test_angle_definition(seed):
    rng = np.random.default_rng(seed)
    x = separated_points(rng, 6)
    a, b, c = random_triples(rng, 6, 10)
    spring = AngularSpring(a, b, c, rest=0.0)
    expected = [signed_angle(x[a[e]] - x[b[e]], x[c[e]] - x[b[e]]) for e in range(10)]
    np.testing.assert_allclose(spring.angles(x), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_angular_spring_force_is_minus_gradient(seed):
    rng = np.random.default_rng(seed)
    x = separated_points(rng, 7)
    a, b, c = random_triples(rng, 7, 10)
    spring = AngularSpring(a, b, c, rest=rng.uniform(-np.pi, np.pi, 10),
                           k=rng.uniform(0.5, 5.0, 10))
    # stay away from the energy's kink at deviation = +-pi, where E is not differentiable
    assert np.all(np.abs(spring.deviation(x)) < np.pi - 1e-3)
    assert_gradient(spring, x, np.ones(7))


def hinge(theta: float, rest: float, arm_a: float = 0.8, arm_c: float = 1.3):
    """Three particles: vertex at (0.2, -0.1), arm a along +x rotated by 0.4, arm c at theta."""
    b = np.array([0.2, -0.1])
    pa = b + arm_a * np.array([np.cos(0.4), np.sin(0.4)])
    pc = b + arm_c * np.array([np.cos(0.4 + theta), np.sin(0.4 + theta)])
    return np.array([pa, b, pc]), AngularSpring(0, 1, 2, rest=rest, k=2.5)


@pytest.mark.parametrize(("theta", "rest"), [
    (np.pi - 1e-8, np.pi),          # straight chain; the angle flips sign under the FD step
    (-np.pi + 1e-8, np.pi),
    (np.pi - 1e-8, np.pi - 0.3),
    (-np.pi + 1e-8, np.pi - 0.3),   # theta - rest = -2 pi + 0.3: must wrap to 0.3
    (3.0, -3.0),                    # theta - rest = 6 rad wraps to 6 - 2 pi
    (-3.0, 3.0),
    (2.9, -2.9 + 1e-4),
])
def test_angular_spring_gradient_near_pi_and_wrap(theta, rest):
    x, spring = hinge(theta, rest)
    expected_dev = np.mod(theta - rest + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(spring.deviation(x), [expected_dev], atol=1e-9)
    F = forces_of(spring, x, np.zeros_like(x), np.ones(3))
    G = minus_grad(spring, x, np.ones(3), eps=1e-6)
    np.testing.assert_allclose(F, G, rtol=1e-5, atol=1e-7)
    _, torque = moments(F, x)
    assert abs(torque) < 1e-12 and np.abs(F.sum(axis=0)).max() < 1e-12


def numeric_angle_gradient(spring, x, eps=1e-6):
    """d theta / dx by central differences of the (unwrapped) angle."""
    g = np.zeros((len(spring), *x.shape))
    for p in range(x.shape[0]):
        for d in range(2):
            xp, xm = x.copy(), x.copy()
            xp[p, d] += eps
            xm[p, d] -= eps
            diff = spring.angles(xp) - spring.angles(xm)
            g[:, p, d] = (np.mod(diff + np.pi, 2 * np.pi) - np.pi) / (2 * eps)
    return g


@pytest.mark.parametrize("seed", SEEDS)
def test_angular_spring_damping_matches_thetadot(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 6), rng.normal(size=(6, 2))
    a, b, c = random_triples(rng, 6, 5)
    kd = rng.uniform(0.1, 2.0, 5)
    damper = AngularSpring(a, b, c, rest=0.0, k=0.0, kd=kd)
    h = 1e-6
    dtheta = damper.angles(x + h * v) - damper.angles(x - h * v)
    thetadot = (np.mod(dtheta + np.pi, 2 * np.pi) - np.pi) / (2 * h)
    grad = numeric_angle_gradient(damper, x)
    expected = np.einsum("k,kpd->pd", -kd * thetadot, grad)
    np.testing.assert_allclose(forces_of(damper, x, v, np.ones(6)), expected, rtol=1e-5,
                               atol=1e-7 * np.abs(expected).max())


def test_angular_spring_rest_defaults_to_current_angle():
    x, _ = hinge(1.1, 0.0)
    spring = AngularSpring(0, 1, 2, k=3.0)
    s = bound(spring, x)
    np.testing.assert_allclose(spring.rest, [1.1], atol=1e-12)
    assert s.potential_energy() < 1e-20
    assert not forces_of(spring, x, np.zeros_like(x), np.ones(3)).any()


# ---------------------------------------------------------------- wall
@pytest.mark.parametrize("seed", SEEDS)
def test_wall_force_is_minus_gradient_inside(seed):
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=2)
    n_hat = normal / np.linalg.norm(normal)
    x = separated_points(rng, 8)
    offset = float(np.median(x @ n_hat))
    # keep every particle well away from the contact kink at p = 0
    depth = x @ n_hat - offset
    x += np.where(np.abs(depth) < 0.05, np.where(depth >= 0, 0.1, -0.1), 0.0)[:, None] * n_hat
    wall = Wall(normal, offset, kw=300.0, cw=0.0)
    assert_gradient(wall, x, np.ones(8))
    p = x @ n_hat - offset
    F = forces_of(wall, x, np.zeros_like(x), np.ones(8))
    assert not F[p < 0].any()
    np.testing.assert_allclose(F[p > 0], -300.0 * p[p > 0, None] * n_hat, rtol=1e-12)


def test_wall_damper_is_one_sided():
    wall = Wall((0.0, -1.0), 1.0, kw=100.0, cw=4.0)  # floor at y = -1
    x = np.array([[0.0, -1.1], [1.0, -1.1], [2.0, -0.5]])  # two inside by 0.1 m, one outside
    v = np.array([[0.0, -1.0], [0.0, 10.0], [0.0, -1.0]])
    F = forces_of(wall, x, v, np.ones(3))
    # moving in: spring plus damper push up; leaving fast: the damper may not pull it back down
    np.testing.assert_allclose(F[0], [0.0, 100.0 * 0.1 + 4.0 * 1.0])
    np.testing.assert_array_equal(F[1:], 0.0)


def test_ball_bounces_off_wall():
    s = ParticleSystem()
    s.add_particle((0.0, 0.0), velocity=(2.0, 0.0), mass=0.1)
    s.add(Wall((1.0, 0.0), 0.5, kw=2000.0, cw=0.0))
    for _ in range(1000):
        s.step(1e-3)
    # elastic contact: the speed comes back (up to the error of stepping across the kink at p = 0)
    assert s.v[0, 0] == pytest.approx(-2.0, rel=2e-3)
    assert s.x[0, 0] < 0.5


# ---------------------------------------------------------------- mouse spring
@pytest.mark.parametrize("seed", SEEDS)
def test_mouse_spring_is_minus_gradient_and_damped(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 5), rng.normal(size=(5, 2))
    anchors = rng.normal(size=(3, 2))
    mouse = MouseSpring([0, 3, 3], anchors, ks=rng.uniform(1, 60, 3), kd=0.0)
    assert_gradient(mouse, x, np.ones(5))
    damped = MouseSpring([0, 3, 3], anchors, ks=mouse.ks, kd=[0.5, 1.0, 2.0])
    diff = forces_of(damped, x, v, np.ones(5)) - forces_of(mouse, x, v, np.ones(5))
    np.testing.assert_allclose(diff[0], -0.5 * v[0], rtol=1e-12)
    np.testing.assert_allclose(diff[3], -3.0 * v[3], rtol=1e-12)


def test_mouse_spring_grab_move_release():
    x = separated_points(np.random.default_rng(5), 4)
    mouse = MouseSpring(ks=10.0, kd=0.0)
    s = bound(mouse, x)
    assert not mouse.active.any() and s.potential_energy() == 0.0
    assert not s.applied_forces(s.x, s.v).any()
    mouse.grab(2, (1.0, 1.0))
    np.testing.assert_allclose(s.applied_forces(s.x, s.v)[2], -10.0 * (x[2] - (1.0, 1.0)))
    mouse.move((-1.0, 0.5))
    np.testing.assert_allclose(s.applied_forces(s.x, s.v)[2], -10.0 * (x[2] - (-1.0, 0.5)))
    assert s.potential_energy() == pytest.approx(5.0 * np.sum((x[2] - (-1.0, 0.5)) ** 2))
    mouse.release()
    assert not s.applied_forces(s.x, s.v).any() and s.potential_energy() == 0.0
    with pytest.raises(ValueError, match="particle"):
        mouse.grab(-1, (0.0, 0.0))
    # a bound spring checks the index against its system at once, and changes nothing
    with pytest.raises(ValueError, match="particles holds unknown particle indices"):
        mouse.grab(4, (0.0, 0.0))
    assert not mouse.active.any() and int(mouse.particle[0]) == 2
    np.testing.assert_array_equal(mouse.anchor[0], (-1.0, 0.5))


# ---------------------------------------------------------------- momentum conservation
@pytest.mark.parametrize("seed", SEEDS)
def test_internal_forces_conserve_momentum(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 8), rng.normal(size=(8, 2))
    i, j = random_springs(rng, 8, 15)
    a, b, c = random_triples(rng, 8, 10)
    for term in (DampedSpring(i, j, rest=rng.uniform(0.2, 2, 15), ks=30.0, kd=2.0),
                 AngularSpring(a, b, c, rest=rng.uniform(-3, 3, 10), k=4.0, kd=0.7)):
        F = forces_of(term, x, v, np.ones(8))
        total, torque = moments(F, x)
        scale = np.abs(F).max() * (1 + np.abs(x).max())
        assert np.abs(total).max() < 1e-12 * scale
        assert abs(torque) < 1e-12 * scale
        # and about another origin, since a nonzero total force would make it depend on it
        assert abs(moments(F, x - rng.normal(size=2) * 10)[1]) < 1e-11 * scale


def test_element_forces_match_accumulate():
    rng = np.random.default_rng(9)
    x, v = separated_points(rng, 5), rng.normal(size=(5, 2))
    spring = DampedSpring([0, 1], [2, 4], rest=0.3, ks=5.0, kd=0.5)
    points, f = spring.element_forces(x, v, np.ones(5))
    np.testing.assert_array_equal(points, x[[0, 1]])
    F = forces_of(spring, x, v, np.ones(5))
    np.testing.assert_allclose(F[[0, 1]], f)
    np.testing.assert_allclose(F[[2, 4]], -f)
    gravity = Gravity((0.0, -2.0), particles=[1, 3])
    points, f = gravity.element_forces(x, v, np.full(5, 0.5))
    np.testing.assert_array_equal(points, x[[1, 3]])
    np.testing.assert_allclose(f, [[0.0, -1.0], [0.0, -1.0]])
