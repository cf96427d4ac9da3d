"""The optional Numba spring kernel against the pure-numpy path (both must stay correct)."""

import os
import subprocess
import sys

import numpy as np
import pytest

from constrained_particles import DampedSpring, ParticleSystem, kernels, scenes


def random_springs(seed: int, n: int = 30, k: int = 120) -> tuple[ParticleSystem, DampedSpring]:
    rng = np.random.default_rng(seed)
    s = ParticleSystem()
    s.add_particles(rng.uniform(-1, 1, (n, 2)), rng.normal(size=(n, 2)))
    i = rng.integers(0, n, k)
    j = (i + rng.integers(1, n, k)) % n
    spring = DampedSpring(i, j, rest=rng.uniform(0, 1, k), ks=rng.uniform(0, 50, k),
                          kd=rng.uniform(0, 2, k))
    s.add(spring)
    return s, spring


def forces(spring: DampedSpring, x: np.ndarray, v: np.ndarray, kernel) -> np.ndarray:
    saved = kernels.spring_forces
    kernels.spring_forces = kernel
    try:
        F = np.zeros_like(x)
        spring.accumulate(x, v, np.ones(len(x)), F)
        return F
    finally:
        kernels.spring_forces = saved


@pytest.mark.parametrize("seed", range(5))
def test_numpy_path_matches_the_per_element_formula(seed):
    s, spring = random_springs(seed)
    s.x[spring.j[0]] = s.x[spring.i[0]]  # one zero-length spring: no force, no NaN
    F = forces(spring, s.x, s.v, None)
    origin, f = spring.element_forces(s.x, s.v, s.mass)
    expected = np.zeros_like(F)
    np.add.at(expected, spring.i, f)
    np.add.at(expected, spring.j, -f)
    np.testing.assert_allclose(F, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.skipif(kernels.spring_forces is None,
                    reason="compiled kernels off (CPARTICLES_NUMBA=0): nothing to compare")
@pytest.mark.parametrize("seed", range(5))
def test_numba_kernel_matches_numpy_path(seed):
    s, spring = random_springs(seed)
    s.x[spring.j[0]] = s.x[spring.i[0]]
    np.testing.assert_allclose(forces(spring, s.x, s.v, kernels.spring_forces),
                               forces(spring, s.x, s.v, None), rtol=1e-12, atol=1e-12)


def test_numpy_path_steps_a_cloth_like_the_active_path():
    a, b = scenes.cloth(5, 5), scenes.cloth(5, 5)
    saved = kernels.spring_forces
    try:
        for _ in range(200):
            a.step(1e-3, "rk4")
            kernels.spring_forces = None
            b.step(1e-3, "rk4")
            kernels.spring_forces = saved
    finally:
        kernels.spring_forces = saved
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-11)


def test_environment_variable_disables_numba():
    code = "from constrained_particles import kernels; print(kernels.spring_forces is None)"
    env = {**os.environ, "CPARTICLES_NUMBA": "0"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "True"


def test_group_pieces_matches_the_numpy_rule():
    """The compiled step-splitting rule of envs.base.ParticleTask.pieces against its numpy
    form, on random states including non-finite speeds and counts beyond the cap."""
    if kernels.group_pieces is None:
        pytest.skip("compiled path disabled (CPARTICLES_NUMBA=0)")
    rng = np.random.default_rng(0)
    size, groups, dt, travel, horizon, cap = 3, 400, 0.025, 0.12, 0.05, 8
    v = rng.normal(0, 3, (size * groups, 2)) * rng.uniform(0, 4, (size * groups, 1))
    F = rng.normal(0, 2, (size * groups, 2))
    inv_mass = rng.uniform(0.5, 20, size * groups)
    v[5, 0], v[40, 1], F[77, 0] = np.nan, np.inf, -np.inf
    out, rows = np.empty(groups, np.int64), np.empty(size * groups, np.int64)
    largest = kernels.group_pieces(v, F, np.zeros(0, np.int64), inv_mass, size, horizon, dt,
                                    travel, cap, out, rows)
    with np.errstate(invalid="ignore"):
        speed = (np.sqrt(np.sum(v * v, axis=1))
                 + np.sqrt(np.sum(F * F, axis=1)) * (inv_mass * horizon))
        need = np.ceil(speed.reshape(groups, size).max(axis=1) * dt / travel)
    expected = np.where((need >= 1) & (need <= cap), need, 1).astype(np.int64)
    assert np.array_equal(out, expected)
    assert np.array_equal(rows, np.repeat(expected, size)) and largest == expected.max()
    assert set(out[[1, 13, 25]]) == {1}  # the groups holding the non-finite entries
    assert 1 < len(np.unique(out)) and out.max() <= cap


def test_mouse_forces_are_the_mouse_spring_blocks_bits():
    """The compiled mouse-spring accumulation (the envs' step splitting) against
    ``MouseSpring.accumulate``: bit for bit, with springs sharing a particle, released
    springs, non-finite states, and none active (nothing added); an index it cannot read
    writes nothing and leaves the error to ``accumulate``."""
    if kernels.mouse_forces is None:
        pytest.skip("compiled path disabled (CPARTICLES_NUMBA=0)")
    from constrained_particles.forces import MouseSpring

    rng = np.random.default_rng(3)
    n, k = 40, 25
    for trial in range(6):
        x, v = rng.normal(0, 2, (n, 2)), rng.normal(0, 5, (n, 2))
        if trial == 1:
            x[3, 0], v[7, 1] = np.inf, np.nan
        particle = rng.integers(0, n, k)
        particle[1] = particle[0]  # (two springs on one particle)
        active = rng.random(k) < (0.0 if trial == 2 else 0.6)
        block = MouseSpring(particle, anchor=rng.normal(0, 1, (k, 2)),
                            ks=rng.uniform(0, 300, k), kd=rng.uniform(0, 3, k))
        block.active = active
        want, got = np.zeros((n, 2)), np.zeros((n, 2))
        with np.errstate(invalid="ignore"):
            block.accumulate(x, v, np.ones(n), want)
        assert kernels.mouse_forces(x, v, block.particle, block.anchor, block.ks, block.kd,
                                    block.active, got)
        assert got.tobytes() == want.tobytes(), trial
        assert (trial == 2) == (not got.any())
    beyond = np.array(block.particle)
    beyond[4] = n
    got = np.full((n, 2), 7.0)
    assert not kernels.mouse_forces(x, v, beyond, block.anchor, block.ks, block.kd,
                                    block.active, got)
    assert not kernels.mouse_forces(x, v[:-1], block.particle, block.anchor, block.ks,
                                    block.kd, block.active, got)
    assert np.all(got == 7.0)


def test_group_pieces_reads_a_force_block_through_its_row_map():
    """Forces given as a block's rows and a per-particle row map (-1: not pushed) split the
    steps exactly as the same forces written out per particle."""
    if kernels.group_pieces is None:
        pytest.skip("compiled path disabled (CPARTICLES_NUMBA=0)")
    rng = np.random.default_rng(1)
    size, groups, dt, travel, horizon, cap = 2, 300, 0.025, 0.12, 0.05, 8
    n = size * groups
    v = rng.normal(0, 3, (n, 2))
    inv_mass = rng.uniform(0.5, 20, n)
    pushed = np.flatnonzero(rng.uniform(size=n) < 0.5)
    block = rng.normal(0, 40, (len(pushed), 2))
    frow = np.full(n, -1, np.int64)
    frow[pushed] = np.arange(len(pushed))
    dense = np.zeros((n, 2))
    dense[pushed] = block
    got, got_rows = np.empty(groups, np.int64), np.empty(n, np.int64)
    want = np.empty(groups, np.int64)
    largest = kernels.group_pieces(v, block, frow, inv_mass, size, horizon, dt, travel, cap,
                                    got, got_rows)
    kernels.group_pieces(v, dense, np.zeros(0, np.int64), inv_mass, size, horizon, dt, travel,
                          cap, want, np.zeros(0, np.int64))
    assert np.array_equal(got, want) and 1 < len(np.unique(want))
    assert np.array_equal(got_rows, np.repeat(want, size)) and largest == want.max()


@pytest.mark.skipif(not kernels.ENABLED,
                    reason="compiled kernels off (CPARTICLES_NUMBA=0): nothing to compare")
@pytest.mark.parametrize("seed", range(3))
def test_distance_error_elements_match_the_constraint_blocks(seed):
    """The compiled distance-error elements (the fused step's divergence test and the envs'
    residual measure both call them) against the blocks' numpy ``distance_error``."""
    from constrained_particles import CircularWire, LineWire, Rod

    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, (12, 2))
    wire = CircularWire(np.arange(4), center=rng.uniform(-1, 1, 2), radius=0.7)
    rod = Rod(np.arange(4, 8), np.arange(8, 12), length=rng.uniform(0.1, 1, 4))
    line = LineWire(np.arange(4), direction=rng.normal(size=2), point=rng.uniform(-1, 1, 2))
    circle = [kernels.length_error(*(x[q] - wire.center[k]), wire.radius[k])
              for k, q in enumerate(wire.particles)]
    rods = [kernels.length_error(*(x[a] - x[b]), rod.length[k])
            for k, (a, b) in enumerate(zip(rod.a, rod.b, strict=True))]
    lines = [kernels.line_error(*x[q], *line.normal[k], *line.point[k])
             for k, q in enumerate(line.particles)]
    np.testing.assert_allclose(circle, wire.distance_error(x), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(rods, rod.distance_error(x), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(lines, line.distance_error(x), rtol=1e-13, atol=1e-15)


@pytest.mark.skipif(not kernels.ENABLED, reason="the compiled kernels are off")
def test_angular_element_wraps_the_angle_as_pythons_modulo():
    """The compiled angular spring wraps ``theta - rest`` into (-pi, pi] without a library
    call where it can: the same bits as Python's ``%`` (the formula written out here), for
    angles and rest angles that take every branch, the turn's ends included."""
    import math

    rng = np.random.default_rng(0)
    angles = np.concatenate([rng.uniform(-math.pi, math.pi, 400), [math.pi, -math.pi, 0.0]])
    rests = np.concatenate([rng.uniform(-3 * math.pi, 3 * math.pi, 60),
                            [0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 7.0, -7.0]])
    k, kd = 3.0, 0.0
    for rest in rests:
        for theta in angles:
            u = (1.0, 0.0)
            w = (math.cos(theta), math.sin(theta))
            got = kernels.angular_element(*u, *w, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                          (k, kd, float(rest)))
            th = math.atan2(u[0] * w[1] - u[1] * w[0], u[0] * w[0] + u[1] * w[1])
            d = math.pi - ((math.pi - (th - float(rest))) % (2.0 * math.pi))
            # (arm a on the x axis: the force on a is -k d dtheta/dx_a = -k d (0, -1))
            assert got[1] == -(k * d) * -1.0, (theta, rest)
