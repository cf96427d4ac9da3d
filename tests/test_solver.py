"""The multiplier solve, its fast and fallback paths, degenerate constraints and projection.

The solved accelerations must satisfy the constraint equation of docs/physics.md,
``J qddot + Jdot qdot = -ks C - kd Cdot``, checked here from the assembled matrices and against
a dense numpy solve of ``J W J^T lam = rhs``.
"""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from constrained_particles import (
    CircularWire,
    DampedSpring,
    FixedPoint,
    Gravity,
    HorizontalWire,
    LineWire,
    ParticleSystem,
    Rod,
    scenes,
)
from constrained_particles.solver import DIRECT_MAX, SOLVER_METHODS, ConstraintSolver

SOLVERS = ["cg", "direct"]


def rebuilt(system: ParticleSystem, solver: str) -> ParticleSystem:
    """A copy of ``system`` that uses the multiplier solver ``solver``."""
    c = system.copy()
    out = ParticleSystem(solver=solver, ks=c.ks, kd=c.kd)
    out.add_particles(c.x, c.v, c.mass, c.fixed)
    out.add(*c.forces, *c.constraints)
    out.t = c.t
    return out


def perturbed(system: ParticleSystem, seed: int, size: float = 0.02) -> ParticleSystem:
    """``system`` moved off its constraints: C != 0 and Cdot != 0 (fixed particles stay)."""
    rng = np.random.default_rng(seed)
    s = system.copy()
    movable = ~s.fixed[:, None]
    s.x = s.x + size * rng.normal(size=s.x.shape) * movable
    s.v = s.v + rng.normal(size=s.v.shape) * movable
    return s


def mixed_system(solver: str = "cg") -> ParticleSystem:
    """Free and fixed particles under every constraint type, with springs and gravity."""
    rng = np.random.default_rng(11)
    s = ParticleSystem(solver=solver)
    grid = np.stack(np.meshgrid(np.arange(3), np.arange(3)), -1).reshape(-1, 2).astype(float)
    s.add_particles(grid + rng.uniform(-0.2, 0.2, grid.shape), rng.normal(size=grid.shape),
                    mass=rng.uniform(0.3, 2.0, 9), fixed=np.arange(9) == 4)
    s.add(Gravity(), DampedSpring([0, 2, 6], [8, 5, 7], ks=30.0, kd=0.3),
          Rod([4, 0, 1, 3], [0, 1, 2, 6]), CircularWire(8, center=(1.0, 1.0)),
          HorizontalWire(7), LineWire(5, direction=(1.0, 2.0)), FixedPoint(2))
    return s


SYSTEMS = {
    "wire_mixture": scenes.wire_mixture,
    "angular_chain": scenes.angular_chain,
    "cloth": lambda: scenes.cloth(nx=4, ny=4),
    "pendulum": scenes.pendulum,
    "mixed": mixed_system,
}


def constraint_equation_residual(s: ParticleSystem, a: np.ndarray) -> tuple[float, float]:
    """max |J qddot + Jdot qdot + ks C + kd Cdot| and the scale of its terms."""
    solver = s.constraint_solver
    solver.refill(s.x, s.v)
    qdot = s.v.ravel()
    terms = [solver.J @ a.ravel(), solver.Jdot @ qdot, s.ks * solver.C, s.kd * solver.Cdot]
    return float(np.abs(sum(terms)).max()), max(float(np.abs(t).max()) for t in terms)


def dense_multipliers(s: ParticleSystem) -> np.ndarray:
    """lam from numpy's dense solve of J W J^T lam = -Jdot qdot - J W Q - ks C - kd Cdot."""
    solver = s.constraint_solver
    solver.refill(s.x, s.v)
    J, Jdot = solver.J.toarray(), solver.Jdot.toarray()
    w2 = np.repeat(s.inv_mass, 2)
    Q = s.applied_forces(s.x, s.v).ravel()
    rhs = -Jdot @ s.v.ravel() - J @ (w2 * Q) - s.ks * solver.C - s.kd * solver.Cdot
    return np.linalg.solve((J * w2) @ J.T, rhs)


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("name", SYSTEMS)
def test_acceleration_satisfies_constraint_equation(name, solver):
    s = rebuilt(perturbed(SYSTEMS[name](), seed=1), solver)
    a = s.acceleration(s.t, s.x, s.v)
    residual, scale = constraint_equation_residual(s, a)
    assert scale > 1.0  # a real test: the perturbed state has sizeable C and Cdot terms
    assert residual < 1e-8 * scale
    # and against an independent dense solve
    lam = dense_multipliers(s)
    Q = s.applied_forces(s.x, s.v)
    expected = s.inv_mass[:, None] * (Q + (s.constraint_solver.J.T @ lam).reshape(Q.shape))
    np.testing.assert_allclose(a, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())


@pytest.mark.parametrize("name", ["wire_mixture", "angular_chain", "mixed"])
def test_cg_and_direct_agree(name):
    base = perturbed(SYSTEMS[name](), seed=2)
    a = {m: rebuilt(base, m).acceleration(0.0, base.x, base.v) for m in SOLVERS}
    np.testing.assert_allclose(a["cg"], a["direct"], rtol=1e-8, atol=1e-9 * np.abs(a["cg"]).max())


def test_warm_start_reuses_last_multipliers(monkeypatch):
    calls = []
    real_cg = spla.cg

    def spy(A, b, x0=None, **kw):
        iterations = []
        out = real_cg(A, b, x0=x0, callback=lambda xk: iterations.append(1), **kw)
        calls.append((None if x0 is None else np.array(x0), out[0].copy(), len(iterations)))
        return out

    monkeypatch.setattr(spla, "cg", spy)
    # 12 rods: one connected component larger than DIRECT_MAX, solved by CG with solver="cg"
    s = perturbed(scenes.angular_chain(links=12), seed=3)
    s.solver = "cg"
    assert not s.constraint_solver.diagonal
    assert len(s.constraint_solver._large) == 12 > DIRECT_MAX
    s.acceleration(0.0, s.x, s.v)
    s.acceleration(0.0, s.x, s.v)
    (x0_first, lam_first, it_first), (x0_second, _, it_second) = calls
    assert not np.any(x0_first) and it_first > 0
    np.testing.assert_array_equal(x0_second, lam_first)  # started from the previous answer
    assert it_second == 0  # which already solves the same system
    np.testing.assert_array_equal(s.constraint_solver.lam, lam_first)


def test_diagonal_fast_path_matches_general_solves():
    """The cloth's top row on a wire: no particle shared between rows, J W J^T is diagonal."""
    base = perturbed(scenes.cloth(nx=5, ny=5, push=0.3), seed=4)
    assert base.constraint_solver.diagonal
    assert not scenes.wire_mixture().constraint_solver.diagonal
    a_fast = base.acceleration(0.0, base.x, base.v)
    for method in SOLVERS:
        general = rebuilt(base, method)
        general.constraint_solver.diagonal = False  # force the cg / LU path
        a = general.acceleration(0.0, general.x, general.v)
        np.testing.assert_allclose(a_fast, a, rtol=1e-9, atol=1e-10 * np.abs(a).max())
    lam = dense_multipliers(base)
    np.testing.assert_allclose(base.constraint_solver.lam, lam, rtol=1e-10,
                               atol=1e-12 * np.abs(lam).max())


def pendulum_with_rods(rods: int, solver: str) -> ParticleSystem:
    s = ParticleSystem(solver=solver)
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.2), velocity=(0.3, -1.0))
    b = s.add_particle((1.5, 0.0), velocity=(0.0, 0.5))
    s.add(Gravity(), *[Rod([o, a], [a, b]) for _ in range(rods)])
    return s


@pytest.mark.parametrize("solver", SOLVERS)
def test_redundant_rods_move_like_one(solver):
    single, double = pendulum_with_rods(1, solver), pendulum_with_rods(2, solver)
    for _ in range(150):
        single.step(1e-3)
        double.step(1e-3)
    assert np.all(np.isfinite(double.x)) and np.all(np.isfinite(double.v))
    np.testing.assert_allclose(double.x, single.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(double.v, single.v, rtol=0, atol=1e-8)
    # least-norm multipliers: the duplicated rows share the load equally
    lam1 = single.constraint_solver.lam
    lam2 = double.constraint_solver.lam
    np.testing.assert_allclose(lam2, np.tile(lam1 / 2, 2), rtol=1e-6, atol=1e-9)


def test_rod_between_two_fixed_particles_is_rejected():
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], fixed=[True, True, False])
    with pytest.raises(ValueError, match="fixed"):
        s.add(Rod([1, 0], [2, 1]))
    assert s.constraints == []


def test_rod_of_length_zero_is_rejected():
    s = ParticleSystem()
    s.add_particles([[1.0, 1.0], [1.0, 1.0]])
    with pytest.raises(ValueError, match="length"):
        s.add(Rod(0, 1))  # default length from coincident particles
    with pytest.raises(ValueError, match="length"):
        Rod(0, 1, length=0.0)
    # an explicit length with coincident ends has a vanishing gradient: an error, not NaN
    s.add(Gravity(), Rod(0, 1, length=1.0))
    x, v = s.x.copy(), s.v.copy()
    with pytest.raises(ValueError, match="zero row"):
        s.step(1e-3)
    np.testing.assert_array_equal(s.x, x)
    np.testing.assert_array_equal(s.v, v)


@pytest.mark.parametrize("make", [lambda: CircularWire(0), lambda: FixedPoint(0),
                                  lambda: HorizontalWire(0)])
def test_constraint_on_fixed_particle_only_is_an_error(make):
    s = ParticleSystem()
    s.add_particle((1.0, 1.0), fixed=True)
    s.add_particle((2.0, 1.0))
    s.add(make())
    with pytest.raises(ValueError, match="fixed"):
        s.acceleration(0.0, s.x, s.v)


def test_unknown_solver_lists_valid_ones():
    with pytest.raises(ValueError, match="solver") as err:
        ParticleSystem(solver="lu")
    assert all(m in str(err.value) for m in SOLVER_METHODS)
    with pytest.raises(ValueError, match="solver"):
        ConstraintSolver([], 0, method="jacobi")


@pytest.mark.parametrize("name", SYSTEMS)
def test_projection_reaches_the_constraints(name):
    s = perturbed(SYSTEMS[name](), seed=5, size=0.01)
    C0, _ = s.constraint_residual()
    assert np.abs(C0).max() > 1e-4
    x0 = s.x.copy()
    s.project()
    C, Cdot = s.constraint_residual()
    assert np.abs(C).max() < 1e-9
    assert np.abs(Cdot).max() < 1e-9
    assert np.abs(s.x - x0).max() < 0.1  # a small correction, not a jump elsewhere
    assert np.array_equal(s.x[s.fixed], x0[s.fixed])


def test_projection_onto_circle_is_radial():
    """For one particle on a circle the smallest move is radial; J v = 0 removes radial speed."""
    s = ParticleSystem()
    s.add_particle((0.3, 1.1), velocity=(2.0, -0.5))
    s.add(CircularWire(0, center=(0.1, 0.2), radius=0.7))
    s.project()
    d = np.array([0.2, 0.9])
    u = d / np.linalg.norm(d)
    np.testing.assert_allclose(s.x[0], (0.1, 0.2) + 0.7 * u, atol=1e-12)
    v = np.array([2.0, -0.5])
    np.testing.assert_allclose(s.v[0], v - np.dot(v, u) * u, atol=1e-12)


def test_projection_without_constraints_changes_nothing():
    s = scenes.spring_pair()
    x, v = s.x.copy(), s.v.copy()
    s.project()
    np.testing.assert_array_equal(s.x, x)
    np.testing.assert_array_equal(s.v, v)


@pytest.mark.parametrize("solver", SOLVERS)
def test_step_with_projection_ends_on_the_constraints(solver):
    s = rebuilt(perturbed(mixed_system(), seed=6, size=0.01), solver)
    s.step(1e-3, project=True)
    C, Cdot = s.constraint_residual()
    assert np.abs(C).max() < 1e-9 and np.abs(Cdot).max() < 1e-9
