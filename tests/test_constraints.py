"""Constraint blocks against finite differences: J = dC/dq, Jdot = dJ/dt, Cdot = J qdot.

Each block is checked through its own ``pattern()``/``evaluate()`` and again through the
assembled sparse ``system.constraint_solver.J`` of a system mixing every block type, which
checks the row offsets and the CSR permutation of the assembly.
"""

import numpy as np
import pytest

from constrained_particles import (
    CircularWire,
    DampedSpring,
    FixedPoint,
    HorizontalWire,
    LineWire,
    ParticleSystem,
    Rod,
)

N = 7


def separated_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` random points at least 0.4 m apart (a shuffled, jittered unit grid)."""
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)
    return grid[rng.permutation(len(grid))[:n]] + rng.uniform(-0.3, 0.3, (n, 2))


def make_blocks(rng: np.random.Generator) -> list:
    """One block of each type, several elements each, with explicit off-constraint geometry."""
    return [
        CircularWire([0, 3, 5], center=rng.normal(size=(3, 2)), radius=rng.uniform(0.5, 2, 3)),
        Rod([0, 1, 2, 4], [1, 2, 6, 0], length=rng.uniform(0.5, 2, 4)),
        HorizontalWire([2, 6], height=0.3),
        LineWire([1, 4], direction=rng.normal(size=(2, 2)), point=rng.normal(size=(2, 2))),
        FixedPoint([5, 6], point=rng.normal(size=(2, 2))),
    ]


def system_with(blocks, x, v, fixed=False) -> ParticleSystem:
    s = ParticleSystem()
    s.add_particles(x, v, mass=np.linspace(0.5, 2.0, len(x)), fixed=fixed)
    s.add(*blocks)
    return s


def dense(block, values: np.ndarray, n: int) -> np.ndarray:
    rows, cols = block.pattern()
    out = np.zeros((block.n_rows, 2 * n))
    np.add.at(out, (rows, cols), values)
    return out


def fd_jacobian(C_of, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """dC/dq by central differences; q = x.ravel()."""
    cols = []
    for k in range(x.size):
        xp, xm = x.copy().ravel(), x.copy().ravel()
        xp[k] += eps
        xm[k] -= eps
        cols.append((C_of(xp.reshape(x.shape)) - C_of(xm.reshape(x.shape))) / (2 * eps))
    return np.stack(cols, axis=1)


def block_parts(block, x, v):
    C, Cdot, Jv, Jdv = block.evaluate(x, v)
    n = len(x)
    return C, Cdot, dense(block, Jv, n), dense(block, Jdv, n)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("kind", range(5), ids=["circle", "rod", "hwire", "line", "fixed"])
def test_block_derivatives(seed, kind):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, N), rng.normal(size=(N, 2))
    block = make_blocks(rng)[kind]
    system_with([block], x, v)  # binds it
    C, Cdot, J, Jdot = block_parts(block, x, v)
    assert C.shape == Cdot.shape == (block.n_rows,)
    assert np.abs(C).max() > 1e-3  # the random state is off the constraint
    J_fd = fd_jacobian(lambda y: block.evaluate(y, v)[0], x)
    np.testing.assert_allclose(J, J_fd, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(Cdot, J_fd @ v.ravel(), rtol=1e-7, atol=1e-8)
    h = 1e-6
    Jdot_fd = (block_parts(block, x + h * v, v)[2] - block_parts(block, x - h * v, v)[2]) / (2 * h)
    np.testing.assert_allclose(Jdot, Jdot_fd, rtol=1e-7, atol=1e-8)
    Cdot_fd = (block.evaluate(x + h * v, v)[0] - block.evaluate(x - h * v, v)[0]) / (2 * h)
    np.testing.assert_allclose(Cdot, Cdot_fd, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_assembled_sparse_jacobian(seed):
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, N), rng.normal(size=(N, 2))
    blocks = make_blocks(rng)
    s = system_with(blocks, x, v)
    solver = s.constraint_solver
    assert solver.m == sum(b.n_rows for b in blocks) == 3 + 4 + 2 + 2 + 4
    assert solver.J.shape == (solver.m, 2 * N)

    def C_of(y):
        solver.refill(y, v)
        return solver.C.copy()

    J_fd = fd_jacobian(C_of, x)
    h = 1e-6
    solver.refill(x + h * v, v)
    Jp = solver.J.toarray()
    solver.refill(x - h * v, v)
    Jm = solver.J.toarray()
    solver.refill(x, v)
    np.testing.assert_allclose(solver.J.toarray(), J_fd, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(solver.Jdot.toarray(), (Jp - Jm) / (2 * h), rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(solver.Cdot, J_fd @ v.ravel(), rtol=1e-7, atol=1e-8)
    # rows come in block order, as the blocks report them
    np.testing.assert_array_equal(solver.C, np.concatenate([b.evaluate(x, v)[0] for b in blocks]))
    C, Cdot = s.constraint_residual()
    np.testing.assert_array_equal(C, solver.C)
    np.testing.assert_array_equal(Cdot, solver.Cdot)


def test_formulas_by_hand():
    """The docs/physics.md definitions of C, for one element of each block, with numbers."""
    x = np.array([[3.0, 4.0], [0.0, 1.0]])
    v = np.array([[1.0, -2.0], [0.5, 0.5]])
    assert CircularWire(0, (0.0, 0.0), 2.0).evaluate(x, v)[0] == pytest.approx([0.5 * (25 - 4)])
    assert Rod(0, 1, 1.0).evaluate(x, v)[0] == pytest.approx([0.5 * (18 - 1)])
    assert HorizontalWire(1, 0.25).evaluate(x, v)[0] == pytest.approx([0.75])
    line = LineWire(0, direction=(1.0, 1.0), point=(0.0, 0.0))
    assert abs(line.evaluate(x, v)[0][0]) == pytest.approx(1 / np.sqrt(2))
    np.testing.assert_allclose(FixedPoint(1, (1.0, 1.0)).evaluate(x, v)[0], [-1.0, 0.0])


def test_geometry_defaults_put_the_state_on_the_constraints():
    rng = np.random.default_rng(4)
    x, v = separated_points(rng, 5), np.zeros((5, 2))
    circle, rod = CircularWire([0, 1], center=(10.0, 0.0)), Rod([2, 3], [3, 4])
    hwire, line, pin = HorizontalWire(1), LineWire(3, (0.3, 1.0)), FixedPoint([0, 4])
    s = system_with([circle, rod, hwire, line, pin], x, v)
    C, _ = s.constraint_residual()
    np.testing.assert_allclose(C, 0.0, atol=1e-12)
    np.testing.assert_allclose(circle.radius, np.linalg.norm(x[[0, 1]] - (10.0, 0.0), axis=1))
    np.testing.assert_allclose(rod.length, np.linalg.norm(x[[2, 3]] - x[[3, 4]], axis=1))
    np.testing.assert_allclose(hwire.height, [x[1, 1]])
    np.testing.assert_allclose(pin.point, x[[0, 4]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rod_constraint_forces_conserve_momentum(seed):
    """On a free system, J^T lam from rods has zero total force and torque."""
    rng = np.random.default_rng(seed)
    x, v = separated_points(rng, 6), rng.normal(size=(6, 2))
    s = ParticleSystem()
    s.add_particles(x, v, mass=rng.uniform(0.2, 2.0, 6))
    s.add(Rod([0, 1, 2, 3, 4, 0], [1, 2, 0, 4, 5, 3]),
          DampedSpring([0, 2, 5], [4, 5, 1], rest=0.3, ks=40.0, kd=1.0))
    s.x = s.x + rng.normal(size=(6, 2)) * 0.05  # off the constraints: the feedback acts too
    fc = s.constraint_force(s.x, s.v)
    assert np.abs(fc).max() > 1e-2
    scale = np.abs(fc).max() * (1 + np.abs(s.x).max())
    assert np.abs(fc.sum(axis=0)).max() < 1e-11 * scale
    torque = np.sum(s.x[:, 0] * fc[:, 1] - s.x[:, 1] * fc[:, 0])
    assert abs(torque) < 1e-11 * scale


def test_constraint_forces_do_no_work_on_the_manifold():
    """An ideal constraint force is orthogonal to every allowed velocity: J^T lam . v = 0."""
    rng = np.random.default_rng(3)
    s = ParticleSystem()
    s.add_particles(separated_points(rng, 5), rng.normal(size=(5, 2)))
    s.add(Rod([0, 1, 2], [1, 2, 3]), CircularWire(4, center=(5.0, 5.0)), HorizontalWire(3))
    s.project()
    fc = s.constraint_force(s.x, s.v)
    assert np.abs(fc).max() > 1e-2
    assert abs(np.sum(fc * s.v)) < 1e-8 * np.abs(fc).max()


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(("make", "match"), [
    (lambda: CircularWire(0, radius=-1.0), "radius"),
    (lambda: CircularWire(0, radius=0.0), "radius"),
    (lambda: CircularWire(0, center=(np.nan, 0.0)), "center"),
    (lambda: Rod(0, 1, length=-0.5), "length"),
    (lambda: Rod(0, 1, length=0.0), "length"),
    (lambda: Rod([0, 1], [1]), "a and b"),
    (lambda: Rod(1, 1), "a and b"),
    (lambda: HorizontalWire(0, height=np.inf), "height"),
    (lambda: LineWire(0, direction=(0.0, 0.0)), "direction"),
    (lambda: LineWire(0, point=(1.0, np.nan)), "point"),
    (lambda: FixedPoint(0, point=(np.inf, 0.0)), "point"),
    (lambda: FixedPoint([[0, 1]]), "particles"),
    (lambda: Rod(0.5, 1), "a must hold integer"),
])
def test_bad_constructor_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(("make", "field"), [
    (lambda: CircularWire(9), "particles"),
    (lambda: CircularWire(-1), "particles"),
    (lambda: Rod(9, 0), "a"),
    (lambda: Rod(0, 9), "b"),
    (lambda: HorizontalWire([0, 9]), "particles"),
    (lambda: LineWire(3), "particles"),
    (lambda: FixedPoint(-3), "particles"),
])
def test_unknown_particle_indices(make, field):
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # negative indices are rejected by the constructor, too-large ones when added
    with pytest.raises(ValueError, match=rf"\b{field} (holds unknown|must hold integer) particle"):
        s.add(make())
    assert s.constraints == []


def test_default_radius_needs_a_particle_off_the_centre():
    s = ParticleSystem()
    s.add_particle((1.0, 2.0))
    with pytest.raises(ValueError, match="radius"):
        s.add(CircularWire(0, center=(1.0, 2.0)))
