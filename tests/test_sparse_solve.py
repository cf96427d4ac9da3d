"""The sparse Cholesky multiplier solve (constrained_particles.ordering, docs/physics.md).

Checked against independent answers: the elimination order gives no fill on chains and trees
of rods (counted, and a perfect elimination order checked on the graph itself), the planned
factor reproduces ``J W J^T`` (dense product), and the multipliers agree with a dense solve
of the same system and with conjugate gradients to 1e-10 relative, on random chains, trees
and cloths of rods, on the reference path and the compiled one.
"""

import itertools

import numpy as np
import pytest

from constrained_particles import Gravity, ParticleSystem, Rod, fused, kernels
from constrained_particles.ordering import SPARSE, elimination_order, factor_plan, fill
from constrained_particles.solver import DIRECT_MAX, row_components


def rod_system(edges: np.ndarray, points: np.ndarray, seed: int, fixed: int | None = 0,
               solver: str = "auto") -> ParticleSystem:
    """Rods along ``edges`` between ``points``, random masses and velocities, gravity."""
    rng = np.random.default_rng(seed)
    s = ParticleSystem(solver=solver)
    n = len(points)
    s.add_particles(points, rng.normal(0, 0.5, (n, 2)), mass=rng.uniform(0.005, 0.05, n))
    if fixed is not None:
        s.inv_mass[fixed] = 0.0
    s.add(Rod(edges[:, 0], edges[:, 1]), Gravity((0.0, -9.81)))
    return s


def chain(nr: int, seed: int = 0, **kw) -> ParticleSystem:
    k = np.arange(nr + 1)
    pts = np.stack([0.05 * k * np.sin(0.5), -0.05 * k * np.cos(0.5)], 1)
    pts += np.random.default_rng(seed).normal(0, 1e-3, pts.shape)
    return rod_system(np.stack([k[:-1], k[1:]], 1), pts, seed, **kw)


def random_tree(n: int, seed: int, **kw) -> ParticleSystem:
    """A random tree of rods: particle i > 0 hangs from a random earlier one."""
    rng = np.random.default_rng(seed)
    parent = np.array([rng.integers(0, i) for i in range(1, n)])
    pts = np.zeros((n, 2))
    for i in range(1, n):
        pts[i] = pts[parent[i - 1]] + rng.normal(0, 0.05, 2) + (0.0, -0.05)
    return rod_system(np.stack([parent, np.arange(1, n)], 1), pts, seed, **kw)


def rod_cloth(nx: int, ny: int, seed: int, **kw) -> ParticleSystem:
    """A cloth-like net of rods with cycles: a random tree on a jittered grid of nx * ny
    particles plus rods closing about one loop in four grid cells (generic positions, fewer
    rods than free coordinates, so ``J W J^T`` is regular)."""
    rng = np.random.default_rng(seed)
    idx = np.arange(nx * ny).reshape(ny, nx)
    gx, gy = np.meshgrid(np.arange(nx) * 0.05, -np.arange(ny) * 0.05)
    pts = np.stack([gx.ravel(), gy.ravel()], 1) + rng.normal(0, 1e-2, (nx * ny, 2))
    edges = [(idx[0, i], idx[0, i + 1]) for i in range(nx - 1)]  # the top row
    edges += [(idx[j, i], idx[j + 1, i]) for j in range(ny - 1) for i in range(nx)]  # columns
    edges += [(idx[j, i], idx[j, i + 1]) for j in range(1, ny) for i in range(nx - 1)
              if rng.random() < 0.25]  # loops
    return rod_system(np.array(edges), pts, seed, **kw)


def plan_of(s: ParticleSystem):
    solver = s.constraint_solver
    solver.refill(s.x, s.v)
    J = solver.J
    m = solver.m
    rows = np.repeat(np.arange(m), np.diff(J.indptr))
    cols = np.full((m, 4), -1, np.int64)
    nnz = np.diff(J.indptr)
    slot = np.arange(J.nnz) - np.repeat(J.indptr[:-1], nnz)
    cols[rows, slot] = J.indices
    comp_rows, comp_ptr = row_components(rows, J.indices, m, 2 * s.n)
    planned = np.diff(comp_ptr) > DIRECT_MAX
    ordered, plan = factor_plan(cols, nnz, comp_rows, comp_ptr, planned)
    return ordered, comp_ptr, planned, plan, J


@pytest.mark.parametrize("make", [lambda: chain(64), lambda: chain(1024),
                                  lambda: random_tree(200, 1), lambda: random_tree(300, 2)])
def test_chains_and_trees_of_rods_factor_without_fill(make):
    s = make()
    _, comp_ptr, planned, plan, _ = plan_of(s)
    assert planned.any()
    for k in np.flatnonzero(planned):
        assert fill(plan, comp_ptr, k) == 0
    # linear work: updates and factor entries a small multiple of the rows
    m = s.constraint_solver.m
    assert len(plan.lpos) <= 8 * m and len(plan.upd) <= 40 * m


def test_the_order_is_a_perfect_elimination_order_on_chordal_graphs():
    # on a chordal graph (a tree's line graph, cliques joined in a tree) every vertex's later
    # neighbours must already form a clique: checked on the graph, not on the factor
    rng = np.random.default_rng(5)
    for _ in range(20):
        n = int(rng.integers(5, 40))
        parent = [int(rng.integers(0, i)) for i in range(1, n)]
        rods = [(parent[i - 1], i) for i in range(1, n)]
        nb = [set() for _ in rods]
        for a, b in itertools.combinations(range(len(rods)), 2):
            if set(rods[a]) & set(rods[b]):
                nb[a].add(b)
                nb[b].add(a)
        order, later = elimination_order(nb)
        position = {v: i for i, v in enumerate(order)}
        for v in range(len(rods)):
            ahead = {w for w in nb[v] if position[w] > position[v]}
            assert set(later[v]) == ahead  # no fill: only original neighbours
            for a, b in itertools.combinations(ahead, 2):
                assert b in nb[a]


def test_a_cloth_of_rods_has_fill_but_the_factor_is_exact():
    s = rod_cloth(8, 8, 3)
    ordered, comp_ptr, planned, plan, J = plan_of(s)
    assert planned.sum() == 1
    w2 = np.repeat(s.inv_mass, 2)
    Jv = np.zeros((J.shape[0], 4))
    Jv[np.repeat(np.arange(J.shape[0]), np.diff(J.indptr)),
       np.arange(J.nnz) - np.repeat(J.indptr[:-1], np.diff(J.indptr))] = J.data
    # the factor, in numpy from the plan, against the dense J W J^T in elimination order
    L = np.zeros(len(plan.lpos))
    flat = Jv.ravel()
    for e, j1, j2, c in plan.prod:
        L[e] += flat[j1] * w2[c] * flat[j2]
    m = len(ordered)
    for p in range(m):
        for t, a, b in plan.upd[plan.uptr[p]:plan.uptr[p + 1]]:
            L[t] -= L[a] * L[b]
        e0 = plan.lptr[p]
        L[e0] = np.sqrt(L[e0])
        L[e0 + 1:plan.lptr[p + 1]] /= L[e0]
    dense = np.zeros((m, m))
    for p in range(m):
        for e in range(plan.lptr[p], plan.lptr[p + 1]):
            dense[plan.lpos[e], p] = L[e]
    A = (J.toarray() * w2) @ J.toarray().T
    P = A[np.ix_(ordered, ordered)]
    assert np.abs(dense @ dense.T - P).max() <= 1e-13 * np.abs(P).max()
    assert fill(plan, comp_ptr, 0) > 0  # cycles: some fill, bounded by the ordering
    assert len(plan.lpos) < 0.2 * m * m


def multipliers(s: ParticleSystem) -> np.ndarray:
    Q = s.applied_forces(s.x, s.v)
    return s.constraint_solver.multipliers(s.x, s.v, Q, np.repeat(s.inv_mass, 2), s.ks,
                                           s.kd).copy()


CASES = [lambda seed: chain(64, seed), lambda seed: chain(300, seed),
         lambda seed: random_tree(120, seed), lambda seed: rod_cloth(6, 7, seed)]


@pytest.mark.parametrize("make", CASES)
@pytest.mark.parametrize("seed", range(3))
def test_multipliers_agree_with_dense_and_cg_solves(make, seed):
    s = make(seed)
    lam = multipliers(s)
    assert any(len(r) > DIRECT_MAX for r in s.constraint_solver._sparse)
    # independent answers: a dense solve of the same assembled system, and CG to 1e-13
    solver = s.constraint_solver
    J = solver.J.toarray()
    w2 = np.repeat(s.inv_mass, 2)
    Q = s.applied_forces(s.x, s.v).ravel()
    b = (-solver.Jdot.toarray() @ s.v.ravel() - J @ (w2 * Q) - s.ks * solver.C
         - s.kd * solver.Cdot)
    dense = np.linalg.solve((J * w2) @ J.T, b)
    assert np.abs(lam - dense).max() <= 1e-10 * np.abs(dense).max()
    cg = s.copy()
    cg.solver, cg.tol = "cg", 1e-13
    assert np.abs(lam - multipliers(cg)).max() <= 1e-10 * np.abs(dense).max()


@pytest.mark.skipif(not kernels.ENABLED, reason="compiled path disabled")
@pytest.mark.parametrize("make", CASES)
def test_compiled_sparse_steps_match_the_reference(make):
    from constrained_particles.integrators import METHODS

    for method in ("symplectic_euler", "rattle"):
        s = make(7)
        s.v = 0.1 * s.v  # (random velocities across 300 rods are violent at the first step)
        p = fused.pack(s)
        assert SPARSE in p.rows.kind and p.variant[0] is True
        status, *_ = fused.run(s.copy(), 1e-3, method, 1, s.constraint_solver.lam.copy(),
                               np.inf)
        assert status == fused.OK  # solved by the compiled sparse factor, not handed back
        ref = s.copy()
        for _ in range(20):
            ref.x, ref.v = METHODS[method](ref, ref.t, ref.x, ref.v, 1e-3)
        s.step(1e-3, method, steps=20)
        scale = max(np.abs(ref.x).max(), 1.0)
        assert np.abs(s.x - ref.x).max() <= 1e-11 * scale
        # (two direct solves of J W J^T, whose condition number grows with the square of the
        # chain's length and the mass ratio: measured 5e-9 on 300 rods after 20 steps)
        assert np.abs(s.v - ref.v).max() <= 2e-8 * max(np.abs(ref.v).max(), 1.0)
        if method == "rattle":
            assert np.abs(s.constraint_residual()[0]).max() < 1e-12


@pytest.mark.skipif(not kernels.ENABLED, reason="compiled path disabled")
def test_tiled_chains_step_copy_exact_on_the_sparse_factor():
    single = chain(20, 1)
    n = single.n
    tiled = single.tile(3)
    alone = [single.copy() for _ in range(3)]
    for i, one in enumerate(alone):
        one.v = one.v * (0.5 + i)
        tiled.v[n * i:n * (i + 1)] = one.v
    for method in ("rattle", "symplectic_euler"):
        tiled.step(1e-3, method, steps=5)
        for one in alone:
            one.step(1e-3, method, steps=5)
    for i, one in enumerate(alone):
        assert tiled.x[n * i:n * (i + 1)].tobytes() == one.x.tobytes()
        assert tiled.v[n * i:n * (i + 1)].tobytes() == one.v.tobytes()


@pytest.mark.skipif(not kernels.ENABLED, reason="compiled path disabled")
def test_rattle_reuses_the_factor_bit_for_bit_across_steps_of_one_call():
    # ten steps in one call (the factor of J(x1) reused as the next step's J(x0)) and ten
    # calls of one step (factorised afresh each time) give the same bits
    a, b = chain(64, 2), chain(64, 2)
    a.step(1e-3, "rattle", steps=10)
    for _ in range(10):
        b.step(1e-3, "rattle")
    assert a.x.tobytes() == b.x.tobytes() and a.v.tobytes() == b.v.tobytes()
