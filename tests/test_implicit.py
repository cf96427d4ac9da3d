"""implicit_euler: force Jacobians, the KKT step, damping, order, stiff cloth.

Every check compares against something independent of the code under test: central finite
differences of ``accumulate``, the closed-form backward-Euler energy decay of a linear spring,
the exact pendulum (Jacobi elliptic functions), the geometry of linear constraints, or a
separately built system.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.special import ellipj, ellipk

from constrained_particles import (
    METHODS,
    ORDERS,
    AngularSpring,
    CircularWire,
    ConstantForce,
    DampedSpring,
    Drag,
    FixedPoint,
    Force,
    Gravity,
    ImplicitSolveError,
    LineWire,
    MouseSpring,
    ParticleSystem,
    Rod,
    SimulationDiverged,
    Wall,
    force_jacobians,
    scenes,
)

G = 9.81
N_RANDOM = 7


def _random_state(seed: int = 0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(N_RANDOM, 2)), rng.normal(size=(N_RANDOM, 2)),
            rng.uniform(0.5, 2.0, N_RANDOM))


def _matrices(force: Force, x, v, mass, definite=False):
    n2 = 2 * len(x)
    rows, cols = force.jacobian_pattern(len(x))
    K, D = force.jacobians(x, v, mass, definite)
    assert rows.shape == cols.shape == K.shape == D.shape
    return (sp.coo_matrix((K, (rows, cols)), shape=(n2, n2)).toarray(),
            sp.coo_matrix((D, (rows, cols)), shape=(n2, n2)).toarray())


def _finite_differences(force: Force, x, v, mass, eps=1e-6):
    """Central differences of ``accumulate`` w.r.t. every position and velocity coordinate."""
    n2 = 2 * len(x)
    K, D = np.zeros((n2, n2)), np.zeros((n2, n2))
    for c in range(n2):
        for out, moving_x in ((K, True), (D, False)):
            forces = []
            for sign in (1.0, -1.0):
                xs, vs = x.copy(), v.copy()
                (xs if moving_x else vs).reshape(-1)[c] += sign * eps
                F = np.zeros_like(x)
                force.accumulate(xs, vs, mass, F)
                forces.append(F.ravel())
            out[:, c] = (forces[0] - forces[1]) / (2 * eps)
    return K, D


def _wall_state():
    """Particles outside, inside and pushing in, and inside but separating fast (clamped)."""
    # for Wall((1, 0.5), 0, kw=100, cw=3): 0, 2, 5 inside and active, 3 inside but clamped
    x = np.array([[0.3, 0.0], [-0.5, 0.5], [0.2, 0.1], [0.05, 0.2], [-1.0, 0.0], [0.4, 0.4],
                  [-0.3, 0.2]])
    v = np.array([[-0.2, 0.1], [0.3, 0.0], [1.0, 0.5], [-10.0, 0.0], [0.0, 0.0], [-0.1, 0.3],
                  [0.0, -1.0]])
    return x, v, np.ones(7)


FORCE_CASES = {
    "spring stretched and compressed": lambda: DampedSpring([0, 1, 2, 4], [3, 4, 5, 6],
                                                            rest=[0.2, 3.0, 1.0, 0.5],
                                                            ks=[3.0, 4.0, 5.0, 2.0],
                                                            kd=[0.3, 0.7, 1.1, 0.0]),
    "angular spring": lambda: AngularSpring([0, 3], [1, 4], [2, 5], rest=[0.3, -2.0],
                                            k=[2.0, 3.0], kd=[0.5, 0.2]),
    "drag on all": lambda: Drag(0.3),
    "drag on some": lambda: Drag(0.2, particles=[1, 1, 3]),
    "wall": lambda: Wall((1.0, 0.5), 0.0, kw=100.0, cw=3.0),
    "wall on some": lambda: Wall((1.0, 0.5), 0.0, kw=100.0, cw=3.0, particles=[0, 2, 3]),
    "mouse spring": lambda: MouseSpring([2, 5], [(0.3, 0.1), (1.0, -1.0)], ks=7.0, kd=0.4),
    "gravity": lambda: Gravity(),
    "constant force": lambda: ConstantForce([1, 2], (1.0, 2.0)),
}


@pytest.mark.parametrize("case", sorted(FORCE_CASES))
@pytest.mark.parametrize("seed", [0, 1])
def test_jacobians_match_finite_differences(case, seed):
    force = FORCE_CASES[case]()
    x, v, mass = _wall_state() if case.startswith("wall") and seed == 0 else _random_state(seed)
    K, D = _matrices(force, x, v, mass)
    K_fd, D_fd = _finite_differences(force, x, v, mass)
    scale = max(1.0, np.abs(K_fd).max(), np.abs(D_fd).max())
    np.testing.assert_allclose(K, K_fd, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(D, D_fd, rtol=0, atol=1e-6 * scale)


def test_spring_jacobian_has_the_transverse_term():
    # a spring along x, length 2, rest 1: transverse stiffness ks (1 - r/|l|) = ks / 2
    force = DampedSpring(0, 1, rest=1.0, ks=10.0)
    K, _ = _matrices(force, np.array([[2.0, 0.0], [0.0, 0.0]]), np.zeros((2, 2)), np.ones(2))
    assert K[0, 0] == pytest.approx(-10.0)
    assert K[1, 1] == pytest.approx(-5.0)
    assert K[1, 3] == pytest.approx(5.0)


def test_wall_jacobian_is_zero_where_the_clamp_is_active():
    wall = Wall((1.0, 0.0), 0.0, kw=100.0, cw=10.0)
    x = np.array([[0.01, 0.0], [0.01, 0.0]])
    v = np.array([[0.5, 0.0], [-0.5, 0.0]])  # 100*0.01 - 10*0.5 < 0: clamped, no force
    F = np.zeros_like(x)
    wall.accumulate(x, v, np.ones(2), F)
    K, D = _matrices(wall, x, v, np.ones(2))
    assert F[1, 0] == 0.0 and K[2, 2] == 0.0 and D[2, 2] == 0.0
    assert K[0, 0] == -100.0 and D[0, 0] == -10.0


@pytest.mark.parametrize("case", ["spring stretched and compressed", "angular spring", "wall",
                                  "mouse spring", "drag on some"])
def test_definite_jacobians_are_symmetric_negative_semidefinite(case):
    force = FORCE_CASES[case]()
    for seed in range(5):
        x, v, mass = _random_state(seed)
        K, D = _matrices(force, x, v, mass, definite=True)
        for M in (K, D):
            np.testing.assert_allclose(M, M.T, atol=1e-12)
            assert np.linalg.eigvalsh(M).max() <= 1e-9 * max(1.0, np.abs(M).max())


def test_definite_spring_jacobian_is_exact_for_stretched_undamped_springs():
    force = DampedSpring([0, 1, 2], [3, 4, 5], rest=0.01, ks=[3.0, 4.0, 5.0])
    x, v, mass = _random_state(3)
    np.testing.assert_allclose(_matrices(force, x, v, mass, True)[0],
                               _matrices(force, x, v, mass)[0], atol=1e-12)


def test_jacobian_pattern_depends_only_on_topology():
    for case in FORCE_CASES:
        force = FORCE_CASES[case]()
        a, b = force.jacobian_pattern(N_RANDOM), force.jacobian_pattern(N_RANDOM)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        for seed in range(3):
            x, v, mass = _random_state(seed)
            assert force.jacobians(x, v, mass)[0].shape == a[0].shape


def test_force_jacobians_sums_blocks():
    s = scenes.angular_chain(links=4)
    K, D = force_jacobians(s, s.x, s.v)
    K_fd = sum(_finite_differences(f, s.x, s.v, s.mass)[0] for f in s.forces)
    np.testing.assert_allclose(K.toarray(), K_fd, atol=1e-6 * np.abs(K_fd).max())


def test_registered_with_order_one():
    assert "implicit_euler" in METHODS and ORDERS["implicit_euler"] == 1


def test_force_without_jacobians_is_reported():
    class Custom(Force):
        def accumulate(self, x, v, mass, F):
            F -= x

    s = ParticleSystem()
    s.add_particle((1.0, 0.0))
    s.add(Custom())
    with pytest.raises(NotImplementedError, match="Custom has no force Jacobians"):
        s.step(0.01, method="implicit_euler")


# ---------------------------------------------------------------------- damping and order
@pytest.mark.parametrize("h", [1 / 60, 1 / 240])
def test_linear_spring_loses_energy_exactly_as_backward_euler_predicts(h):
    # a spring along its own axis is linear: each step keeps 1 / (1 + (w h)^2) of the energy
    s = scenes.spring_pair(kd=0.0)
    w = np.sqrt(20.0 / 0.25)  # ks / reduced mass
    energies = [s.energy()]
    for _ in range(20):
        s.step(h, method="implicit_euler")
        energies.append(s.energy())
    np.testing.assert_allclose(np.array(energies[1:]) / energies[:-1], 1 / (1 + (w * h) ** 2),
                               rtol=1e-9)


def _exact_pendulum(t, length=1.0, angle=0.5):
    k = np.sin(angle / 2)
    sn = ellipj(ellipk(k * k) - np.sqrt(G / length) * t, k * k)[0]
    theta = 2 * np.arcsin(k * sn)
    return np.array([length * np.sin(theta), -length * np.cos(theta)])


def test_order_one_on_the_pendulum():
    hs = [0.01, 0.005, 0.0025]
    errors = []
    for h in hs:
        s = scenes.pendulum(1.0, 0.5, 1.0)
        for _ in range(round(1.0 / h)):
            s.step(h, method="implicit_euler")
        errors.append(np.linalg.norm(s.x[0] - _exact_pendulum(1.0)))
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(np.abs(orders - 1.0) < 0.15), (errors, orders)


def test_wire_pendulum_is_not_damped():
    # no force Jacobian (gravity is constant): the step behaves like symplectic Euler with the
    # constraint solved at velocity level, so the swing keeps its energy (documented)
    s = scenes.pendulum(1.0, 0.1, 1.0)
    e0 = s.energy() + G
    period = 4 * ellipk(np.sin(0.05) ** 2) / np.sqrt(G)
    for _ in range(round(period * 60)):
        s.step(1 / 60, method="implicit_euler")
    assert abs((s.energy() + G) / e0 - 1) < 0.01


# ---------------------------------------------------------------------- constraints, fixed
@pytest.mark.parametrize("beta", [1.0, 0.5, 0.0])
def test_linear_constraint_drift_is_removed_at_the_drift_correction_rate(beta):
    s = ParticleSystem(drift_correction=beta)
    p = s.add_particle((0.3, 0.2), velocity=(1.0, 0.5))
    wire = LineWire(p, direction=(1.0, 1.0), point=(0.0, 0.0))
    s.add(Gravity(), wire)
    c0 = s.constraint_residual()[0][0]
    s.step(0.05, method="implicit_euler")
    c1, cdot1 = s.constraint_residual()
    assert c1[0] == pytest.approx((1 - beta) * c0, abs=1e-12)
    assert cdot1[0] == pytest.approx(-beta * c0 / 0.05, abs=1e-10)


def test_fixed_particles_stay_fixed():
    s = scenes.angular_chain(links=5)
    tip = s.add_particle((0.0, 0.5), fixed=True)
    s.add(DampedSpring(tip, 3, ks=50.0, kd=1.0))
    x0 = s.x.copy()
    for _ in range(30):
        s.step(1 / 60, method="implicit_euler")
    np.testing.assert_array_equal(s.x[[0, tip]], x0[[0, tip]])
    np.testing.assert_array_equal(s.v[[0, tip]], 0.0)
    assert np.linalg.norm(s.x[-2] - x0[-2]) > 0.1
    C, _ = s.constraint_residual()
    assert np.abs(C).max() < 1e-3


def test_redundant_constraints_need_compliance():
    def build(compliance):
        s = ParticleSystem(compliance=compliance)
        o = s.add_particle((0.0, 0.0), fixed=True)
        a = s.add_particle((1.0, 0.0))
        s.add(Gravity(), Rod(o, a), Rod(o, a))
        return s

    s = build(0.0)
    x0 = s.x.copy()
    with pytest.raises(ImplicitSolveError, match="compliance"):
        s.step(1 / 60, method="implicit_euler")
    assert issubclass(ImplicitSolveError, SimulationDiverged)
    np.testing.assert_array_equal(s.x, x0)
    s = build(1e-8)
    for _ in range(60):
        s.step(1 / 60, method="implicit_euler")
    assert abs(np.linalg.norm(s.x[1]) - 1.0) < 2e-3
    assert s.x[1, 0] < -0.5  # it swung through to the other side


def test_constraint_on_fixed_particles_only_is_a_value_error():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0))
    s.add(FixedPoint(o), DampedSpring(o, a, ks=10.0))
    with pytest.raises(ValueError, match="fixed particles"):
        s.step(0.01, method="implicit_euler")


@pytest.mark.parametrize("kwargs", [{"drift_correction": 1.5}, {"drift_correction": -0.1},
                                    {"compliance": -1.0}, {"compliance": np.nan}])
def test_bad_gains_are_value_errors(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        ParticleSystem(**kwargs)


def test_regrabbing_the_mouse_rebuilds_the_pattern():
    def build():
        s = scenes.cloth(4, 4, ks=200.0, wall_x=None)
        m = MouseSpring(ks=20.0, kd=0.5)
        s.add(m)
        return s, m

    s, m = build()
    m.grab(15, (1.0, -1.0))
    for _ in range(5):
        s.step(1 / 60, method="implicit_euler")
    m.grab(12, (-1.0, -1.0))
    s.step(1 / 60, method="implicit_euler")
    fresh, fm = build()
    fresh.x, fresh.v, fresh.t = s.x.copy(), s.v.copy(), s.t
    fm.grab(12, (-1.0, -1.0))
    s.step(1 / 60, method="implicit_euler")
    fresh.step(1 / 60, method="implicit_euler")
    np.testing.assert_allclose(s.x, fresh.x, rtol=0, atol=1e-13)


def test_tiled_copies_step_like_the_single_system():
    s = scenes.cloth(4, 3, ks=500.0, wall_x=0.25)
    s.v[:] = np.random.default_rng(0).normal(size=s.v.shape)
    batch = s.tile(3)
    for _ in range(5):
        s.step(1 / 60, method="implicit_euler")
        batch.step(1 / 60, method="implicit_euler")
    for c in range(3):
        np.testing.assert_allclose(batch.x[c * s.n:(c + 1) * s.n], s.x, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------- the stiff cloth
def _stiff_cloth(shear_ks=None):
    s = scenes.cloth(15, 15, ks=2000.0, mass=0.01, kd=0.05, bend=False, wall_x=None, drag=0.0)
    if shear_ks is not None:
        springs = s.forces[1]
        springs.ks[springs.rest > 0.11] = shear_ks
    return s


@pytest.mark.parametrize("shear_ks", [None, 2000.0], ids=["shear ks/2", "shear ks"])
def test_stiff_cloth_runs_10_s_at_60_hz(shear_ks):
    s = _stiff_cloth(shear_ks)
    x0 = s.x.copy()
    energy = [s.energy()]
    worst_wire = 0.0
    for _ in range(600):
        s.step(1 / 60, method="implicit_euler")
        energy.append(s.energy())
        worst_wire = max(worst_wire, np.abs(s.constraint_residual()[0]).max())
        assert np.linalg.norm(s.x - x0, axis=1).max() < 2.0
    rises = np.diff(energy)
    assert rises.max() <= 1e-3
    assert energy[-1] < energy[0]
    assert worst_wire < 1e-6
    assert s.t == pytest.approx(10.0)


@pytest.mark.parametrize("method", ["euler", "midpoint", "rk4", "symplectic_euler"])
def test_explicit_methods_diverge_cleanly_on_the_stiff_cloth(method):
    s = _stiff_cloth()
    with pytest.raises(SimulationDiverged):
        for _ in range(600):
            before = (s.x.copy(), s.v.copy(), s.t)
            s.step(1 / 60, method=method)
    assert np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.v))
    np.testing.assert_array_equal(s.x, before[0])
    np.testing.assert_array_equal(s.v, before[1])
    assert s.t == before[2] < 10.0


def test_yanked_stiff_cloth_never_gains_energy():
    # a mouse spring with a fixed anchor is conservative, so the system's energy must not rise;
    # with the exact (indefinite) Jacobian of compressed springs this blows up
    s = _stiff_cloth()
    m = MouseSpring(ks=50.0, kd=0.5)
    s.add(m)
    m.grab(224, s.x[224] + (-2.0, 0.5))
    energy = [s.energy()]
    for _ in range(120):
        s.step(1 / 60, method="implicit_euler")
        energy.append(s.energy())
    assert np.diff(energy).max() <= 1e-9 * abs(energy[0])
    assert energy[-1] < 0.5 * energy[0]


# ---------------------------------------------------------------------- settling and damping
def _settled_spring(ks, mass):
    """A particle on a stiff spring to a fixed anchor, released 1 mm stretched, no gravity: the
    motion decays by 1/(1 + (w h)^2) per step into subnormal velocities (below 1e-308 m/s)."""
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.001, 0.0), mass=mass)
    s.add(DampedSpring(o, a, rest=1.0, ks=ks))
    return s


@pytest.mark.parametrize(("ks", "mass"), [(1e4, 0.01), (1e12, 1.0)])
def test_settled_stiff_spring_keeps_stepping(ks, mass):
    s = _settled_spring(ks, mass)
    for _ in range(400):
        s.step(1 / 60, method="implicit_euler")
    assert abs(s.x[1, 0] - 1.0) < 1e-12 and np.all(np.abs(s.v) < 1e-300)


def test_the_absolute_floor_is_what_accepts_subnormal_solutions(monkeypatch):
    import constrained_particles.implicit as implicit

    monkeypatch.setattr(implicit, "SOLVE_FLOOR", 0.0)  # the relative test alone
    s = _settled_spring(1e4, 0.01)
    with pytest.raises(ImplicitSolveError, match="independent"):
        for _ in range(400):
            s.step(1 / 60, method="implicit_euler")
    assert np.all(np.isfinite(s.v)) and 0 < np.abs(s.v).max() < 1e-300  # subnormal, kept


def test_vanishing_gradient_is_the_explicit_methods_value_error():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0))
    s.add(Gravity(), Rod(o, a))
    s.x[a] = s.x[o]
    x0 = s.x.copy()
    messages = []
    for method in ("rk4", "implicit_euler", "rattle"):
        with pytest.raises(ValueError, match="vanishing gradient") as err:
            s.step(1 / 60, method=method)
        messages.append(str(err.value))
    assert messages[0] == messages[1] == messages[2]
    np.testing.assert_array_equal(s.x, x0)


def test_independent_rows_get_no_advice_about_redundancy(monkeypatch):
    import constrained_particles.implicit as implicit

    # force a rejection (no tolerance at all) on a well-posed system with rounding residuals
    monkeypatch.setattr(implicit, "SOLVE_TOLERANCE", 0.0)
    monkeypatch.setattr(implicit, "SOLVE_FLOOR", 0.0)
    s = scenes.wire_mixture()
    with pytest.raises(ImplicitSolveError) as err:
        for _ in range(20):
            s.step(1 / 60, method="implicit_euler")
    assert "redundant" not in str(err.value) and "compliance" not in str(err.value)
    assert "independent" in str(err.value)


def test_dependent_rows_are_found():
    from constrained_particles.implicit import _dependent_rows

    J = np.array([[1.0, 0.0, 2.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 1.0, 2.0, 0.0],
                  [0.0, 0.0, 0.0, 3.0]])
    dependent = _dependent_rows(sp.csr_matrix(J))
    assert len(dependent) == 1 and dependent[0] in (0, 1, 2)
    assert np.linalg.matrix_rank(np.delete(J, dependent, axis=0)) == 3
    assert len(_dependent_rows(sp.csr_matrix(np.delete(J, 2, axis=0)))) == 0


def test_redundant_rows_are_named():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0))
    s.add(Gravity(), Rod(o, a), Rod(o, a))
    with pytest.raises(ImplicitSolveError, match=r"rows \[[01]\] depend linearly"):
        s.step(1 / 60, method="implicit_euler")


def test_the_fill_reducing_ordering_is_found_once_and_kept():
    """The first step of a topology finds SuperLU's fill-reducing ordering; later steps
    assemble the KKT matrix already permuted and factorise it in that order (no search): the
    fill as a fresh search (within 10%), and steps within 1e-12 of the KKT system solved
    directly (dense) from the same state."""
    from constrained_particles import implicit

    s = scenes.cloth(6, 5, wall_x=None, push=0.3)
    s.step(1 / 60, "implicit_euler")
    asm = implicit._assembly(s)
    assert asm.order is not None and sorted(asm.order) == list(range(asm.size))
    captured = {}
    solve = implicit._solve

    def spy(A, rhs, t, J, free, asm=None):
        captured.update(A=A.toarray(), rhs=rhs.copy())
        return solve(A, rhs, t, J, free, asm)

    implicit._solve = spy
    try:
        x0, v0 = s.x.copy(), s.v.copy()
        s.step(1 / 60, "implicit_euler")
    finally:
        implicit._solve = solve
    A = captured["A"]  # (assembled in the kept ordering)
    rhs = captured["rhs"][asm.order]
    dv = np.zeros(2 * s.n)
    direct = np.empty_like(rhs)
    direct[asm.order] = np.linalg.solve(A, rhs)
    dv[asm.free] = direct[:asm.nf]
    v1 = v0.ravel() + dv
    np.testing.assert_allclose(s.v.ravel(), v1, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s.x, x0 + (1 / 60) * v1.reshape(-1, 2), rtol=1e-12, atol=1e-14)
    lu = sp.linalg.splu(sp.csc_matrix(A), permc_spec="NATURAL", diag_pivot_thresh=0.1,
                        options={"SymmetricMode": True})
    fresh = sp.linalg.splu(sp.csc_matrix(A[np.ix_(np.argsort(asm.order), np.argsort(asm.order))]),
                           permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1,
                           options={"SymmetricMode": True})
    # (threshold pivoting may add a little fill either way: within 10% of a fresh search)
    assert lu.L.nnz + lu.U.nnz <= 1.1 * (fresh.L.nnz + fresh.U.nnz)


def test_scaling_report_runs_on_a_tiny_cloth():
    """``benchmarks/bench_implicit.py --scaling`` on a 4x4 cloth: its figures are there and
    the LU factors hold at least the matrix's own diagonal."""
    from benchmarks.bench_implicit import scaling

    (row,) = scaling(sizes=(4,), repeats=1)
    assert row["particles"] == 16 and row["kkt_size"] > 0
    assert row["ms_per_step"] > 0 and row["us_per_particle_step"] > 0
    assert row["fill_per_unknown"] >= 1 and row["searched_over_kept"] > 0


def test_a_kept_ordering_that_fails_is_searched_again(monkeypatch):
    """If the factorisation in the kept ordering fails, the step still succeeds by a fresh
    search (the same result to rounding), the kept ordering is dropped, and the next step finds
    and keeps one again."""
    from constrained_particles import implicit

    s, ref = scenes.cloth(5, 4, wall_x=None, push=0.3), scenes.cloth(5, 4, wall_x=None, push=0.3)
    for system in (s, ref):
        system.step(1 / 60, "implicit_euler")
    asm = implicit._assembly(s)
    assert asm.order is not None
    splu = implicit.spla.splu

    def failing(A, **options):
        if options.get("permc_spec") == "NATURAL":
            raise RuntimeError("Factor is exactly singular")
        return splu(A, **options)

    monkeypatch.setattr(implicit.spla, "splu", failing)
    s.step(1 / 60, "implicit_euler")
    monkeypatch.setattr(implicit.spla, "splu", splu)
    ref.step(1 / 60, "implicit_euler")
    np.testing.assert_allclose(s.x, ref.x, rtol=0, atol=1e-13)
    assert asm.order is None
    s.step(1 / 60, "implicit_euler")
    assert implicit._assembly(s).order is not None


# ---------------------------------------------------------------------- the CG linear solve
def _constrained_cloth(implicit_solver, circular=False):
    """A pushed cloth on its wire with the kinds of rows CG filters: a fixed particle, a pinned
    point, a slanted line wire, a rod to the fixed particle, and with ``circular`` a circular
    wire."""
    s = scenes.cloth(8, 7, ks=100.0, mass=0.05, kd=0.1, bend=True, wall_x=None, push=0.2)
    s.implicit_solver = implicit_solver
    anchor = s.add_particle((0.35, 0.3), fixed=True)
    s.add(DampedSpring(anchor, 3, ks=40.0, kd=0.2), FixedPoint(55),
          ConstantForce(np.arange(40, 47), (-1.0, 0.5)),
          LineWire(48, direction=(1.0, -1.0)), Rod(anchor, 4))
    if circular:
        s.add(CircularWire(15, center=(0.7, -0.1)))
    s.v[:] = np.random.default_rng(3).normal(scale=1.0, size=s.v.shape)
    s.v[anchor] = 0.0
    s.project()
    return s


def test_cg_matches_the_direct_solve_with_fixed_points_and_wires():
    """60 steps of 1/60 s with CG stay within 1e-6 m and 1e-5 m/s of the direct KKT solve (CG
    stops at a relative residual of CG_TOLERANCE = 1e-6; measured: 5e-8 m, 5e-7 m/s), every
    step by CG, and the linear constraints hold to rounding as with the direct solve."""
    from constrained_particles import implicit

    cg, direct = _constrained_cloth("cg"), _constrained_cloth("direct")
    for _ in range(60):
        cg.step(1 / 60, method="implicit_euler")
        direct.step(1 / 60, method="implicit_euler")
        assert implicit._assembly(cg).last_solver == "cg"
        assert implicit._assembly(direct).last_solver == "direct"
    np.testing.assert_allclose(cg.x, direct.x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(cg.v, direct.v, rtol=0, atol=1e-5)
    assert np.linalg.norm(cg.x - _constrained_cloth("cg").x, axis=1).max() > 0.01  # it moved
    np.testing.assert_allclose(cg.x[55], direct.x[55], rtol=0, atol=1e-14)  # the pinned point
    normal = np.array([1.0, 1.0]) / np.sqrt(2)  # the slanted wire's normal: 0 along it
    start = _constrained_cloth("cg").x[48]
    assert abs((cg.x[48] - start) @ normal) < 1e-12
    assert np.abs(cg.x[:8, 1]).max() < 1e-12  # the top row on its wire at height 0
    assert implicit._assembly(cg).cg_failures == 0


def test_a_cg_step_matches_the_direct_one_with_a_circular_wire():
    """From the same states (along a direct run), a CG step's velocities are within 1e-5 of the
    largest speed from the direct step's (measured 1.3e-6). (A whole run is not compared: on
    this scene the particle on the circular wire amplifies a 1e-7 m/s difference to mm/s
    within a second, with either solver.)"""
    from constrained_particles import implicit

    direct = _constrained_cloth("direct", circular=True)
    for _ in range(30):
        cg = direct.copy()
        cg.implicit_solver = "cg"
        direct.step(1 / 60, method="implicit_euler")
        cg.step(1 / 60, method="implicit_euler")
        assert implicit._assembly(cg).last_solver == "cg"
        assert np.abs(cg.v - direct.v).max() <= 1e-5 * np.abs(direct.v).max()


def test_cg_is_stable_on_the_stiff_cloth_at_60_hz():
    from constrained_particles import implicit

    s = _stiff_cloth()
    s.implicit_solver = "cg"
    x0 = s.x.copy()
    energy = [s.energy()]
    for _ in range(600):
        s.step(1 / 60, method="implicit_euler")
        assert implicit._assembly(s).last_solver == "cg"
        energy.append(s.energy())
        assert np.linalg.norm(s.x - x0, axis=1).max() < 2.0
    assert np.diff(energy).max() <= 1e-3
    assert energy[-1] < energy[0]
    assert np.abs(s.constraint_residual()[0]).max() < 1e-6
    assert implicit._assembly(s).cg_failures == 0


@pytest.mark.parametrize("value", ["lu", "CG", None, 1])
def test_a_bad_implicit_solver_is_a_value_error(value):
    with pytest.raises(ValueError, match="implicit_solver"):
        ParticleSystem(implicit_solver=value)
    s = scenes.spring_pair()
    s.implicit_solver = value
    x0 = s.x.copy()
    with pytest.raises(ValueError, match="implicit_solver"):
        s.step(1 / 60, method="implicit_euler")
    np.testing.assert_array_equal(s.x, x0)


def _cloth_reference(cloth, t_end):
    """The cloth's positions at t_end by rk4 at 1/6400 s (its own error is far below the
    implicit steps' errors measured here)."""
    ref = cloth()
    for _ in range(round(t_end * 6400)):
        ref.step(1 / 6400, method="rk4")
    return ref.x


def test_order_one_with_the_cg_solve():
    from constrained_particles import implicit

    def cloth():
        s = scenes.cloth(6, 6, ks=60.0, mass=0.05, kd=0.05, bend=False, wall_x=None, push=0.1)
        s.implicit_solver = "cg"
        return s

    reference = _cloth_reference(cloth, 0.5)
    hs = [0.01, 0.005, 0.0025]
    errors = []
    for h in hs:
        s = cloth()
        for _ in range(round(0.5 / h)):
            s.step(h, method="implicit_euler")
            assert implicit._assembly(s).last_solver == "cg"
        errors.append(np.abs(s.x - reference).max())
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all(np.abs(orders - 1.0) < 0.15), (errors, orders)


def test_rods_between_moving_particles_and_compliance_take_the_direct_solve():
    from constrained_particles import implicit

    def build(**kwargs):
        s = scenes.wire_mixture()  # a rod joins the crank and the slider: not filterable
        s.implicit_solver = "cg"
        for name, value in kwargs.items():
            setattr(s, name, value)
        return s

    s, ref = build(), build(implicit_solver="direct")
    for _ in range(10):
        s.step(1 / 60, method="implicit_euler")
        ref.step(1 / 60, method="implicit_euler")
    assert implicit._assembly(s).last_solver == "direct"
    np.testing.assert_array_equal(s.x, ref.x)
    soft = _constrained_cloth("cg")
    soft.compliance = 1e-6  # soft rows cannot be filtered
    soft.step(1 / 60, method="implicit_euler")
    assert implicit._assembly(soft).last_solver == "direct"


def test_a_cg_solve_that_fails_is_redone_directly(monkeypatch):
    """A CG solve that does not converge (here: allowed 2 iterations) is replaced by the direct
    solve: the same step as the direct solver's, and the failure is counted."""
    from constrained_particles import implicit

    cg, direct = _constrained_cloth("cg"), _constrained_cloth("direct")
    monkeypatch.setattr(implicit, "CG_MAX_ITERATIONS", 2)
    cg.step(1 / 60, method="implicit_euler")
    direct.step(1 / 60, method="implicit_euler")
    asm = implicit._assembly(cg)
    assert asm.last_solver == "direct" and asm.cg_failures == 1
    np.testing.assert_allclose(cg.x, direct.x, rtol=0, atol=1e-14)


def test_auto_takes_cg_from_the_documented_size():
    from constrained_particles import implicit

    edge = np.sqrt(implicit.CG_MIN_COORDINATES / 2)  # a cloth of n x n has 2 n^2 coordinates
    for n, expected in ((int(np.floor(edge)) - 1, "direct"), (int(np.ceil(edge)) + 1, "cg")):
        s = scenes.cloth(n, n, ks=2000.0, mass=0.01, kd=0.05, bend=False, wall_x=None, drag=0.0)
        assert s.implicit_solver == "auto"
        s.step(1 / 60, method="implicit_euler")
        asm = implicit._assembly(s)
        assert (asm.nf >= implicit.CG_MIN_COORDINATES) == (expected == "cg")
        assert asm.last_solver == expected


def test_the_compiled_cg_kernel_matches_its_numpy_reference():
    """The same CG inputs (a step of the constrained cloth, cold start) through the compiled
    kernel and the numpy reference: the same iteration count and dv to 1e-12 m/s."""
    from constrained_particles import implicit, kernels

    if not kernels.ENABLED:
        pytest.skip("the compiled kernel is off (CPARTICLES_NUMBA=0)")
    captured = {}

    def spy(*args):
        captured["args"] = args
        return implicit._cg_reference(*args)

    s = _constrained_cloth("cg", circular=True)
    compiled = implicit._cg_compiled
    implicit._cg_compiled = spy
    try:
        s.step(1 / 60, method="implicit_euler")
    finally:
        implicit._cg_compiled = compiled
    args = captured["args"]
    ref_dv, ref_its, ref_ok = implicit._cg_reference(*args)
    dv, its, ok = compiled(*args)
    assert ref_ok and ok and its == ref_its > 5
    np.testing.assert_allclose(dv, ref_dv, rtol=0, atol=1e-12)
