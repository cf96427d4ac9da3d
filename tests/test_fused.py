"""The fused compiled step against the readable reference path.

The reference is the Python path: ``integrators.METHODS[name](system, t, x, v, h)``, which calls
``system.acceleration`` and the numpy blocks. The fused kernel must agree with it to rounding
(1e-12 relative) on every block and constraint type and every explicit integrator, keep copies
of a tiled scene exactly independent, hand back to the reference whatever it cannot do, and
never read outside its arrays.
"""

import os
import subprocess
import sys

import numpy as np
import pytest

from constrained_particles import (
    AngularSpring,
    CircularWire,
    ConstantForce,
    DampedSpring,
    Drag,
    FixedPoint,
    Gravity,
    HorizontalWire,
    LineWire,
    MouseSpring,
    ParticleSystem,
    Rod,
    SimulationDiverged,
    Wall,
    fused,
    fused_accel,
    kernels,
    packing,
    scenes,
)
from constrained_particles.integrators import METHODS
from constrained_particles.records import SpringArrays
from constrained_particles.solver import DIRECT_MAX

pytestmark = pytest.mark.skipif(not kernels.ENABLED, reason="compiled path disabled "
                                "(CPARTICLES_NUMBA=0): nothing to compare")
EXPLICIT = ["euler", "midpoint", "rk4", "symplectic_euler"]


def every_block(seed: int, copies_of_gravity: int = 1) -> ParticleSystem:
    """Nine movable particles and one fixed, with every standard force and constraint type."""
    rng = np.random.default_rng(seed)
    s = ParticleSystem()
    s.add_particles(rng.uniform(-1, 1, (9, 2)), rng.normal(0, 0.5, (9, 2)),
                    mass=rng.uniform(0.2, 2.0, 9))
    anchor = s.add_particle((0.0, 1.5), fixed=True)
    for _ in range(copies_of_gravity):
        s.add(Gravity((rng.normal(), -9.81)))
    s.add(ConstantForce([1, 2], rng.normal(size=(2, 2))),
          DampedSpring([0, 2, 3, 6, 7], [1, 5, 6, 8, anchor], ks=rng.uniform(5, 50, 5),
                       kd=rng.uniform(0, 1, 5)),
          AngularSpring([3, 5], [6, 7], [8, 2], k=rng.uniform(0.1, 2, 2), kd=0.05,
                        rest=rng.uniform(-3, 3, 2)),
          Drag(0.2, particles=[0, 3, 4]),
          Wall((1.0, 0.2), 0.3, kw=800.0, cw=2.0),
          Wall((0.0, -1.0), 0.5, kw=500.0, cw=0.0, particles=[0, 1, 2, 3, 4]),
          MouseSpring(4, anchor=(0.2, 0.3), ks=30.0, kd=0.5),
          CircularWire(0, center=s.x[0] + (0.3, 0.1)),
          Rod(1, 2),
          LineWire(3, direction=(1.0, 0.4)),
          HorizontalWire(5),
          FixedPoint(8),
          Rod(7, anchor))
    return s


def reference(s: ParticleSystem, method: str, h: float, steps: int
              ) -> tuple[np.ndarray, np.ndarray]:
    ref = s.copy()
    x, v, t = ref.x, ref.v, ref.t
    for _ in range(steps):
        x, v = METHODS[method](ref, t, x, v, h)
        t += h
    return x, v


def close(a: np.ndarray, b: np.ndarray, rtol: float = 1e-12) -> None:
    scale = max(np.abs(b).max(), 1.0)
    assert np.abs(a - b).max() <= rtol * scale, np.abs(a - b).max() / scale


@pytest.mark.parametrize("method", EXPLICIT)
@pytest.mark.parametrize("seed", range(3))
def test_fused_step_matches_the_reference_on_every_block(method, seed):
    s = every_block(seed)
    assert fused.pack(s).supported
    x_ref, v_ref = reference(s, method, 1e-3, 40)
    s.step(1e-3, method, steps=40)
    close(s.x, x_ref)
    close(s.v, v_ref)
    assert s.t == pytest.approx(0.04)


def test_several_blocks_of_one_type_are_summed_and_edits_seen():
    s = every_block(7, copies_of_gravity=3)
    ref = s.copy()
    for k in range(20):
        for system in (s, ref):  # in-place edits of a joined block's parameters
            system.forces[1].g[0] = 0.1 * k
            walls = [f for f in system.forces if isinstance(f, Wall)]
            walls[1].offset = 0.5 + 0.01 * k  # and a reassigned scalar
        s.step(2e-3, "rk4")
        ref.x, ref.v = METHODS["rk4"](ref, ref.t, ref.x, ref.v, 2e-3)
    close(s.x, ref.x)
    close(s.v, ref.v)


def test_steps_in_one_call_equal_single_steps_bit_for_bit():
    a = scenes.cloth(nx=5, ny=4, push=0.2)
    b = a.copy()
    a.step(1e-3, "symplectic_euler", steps=7)
    for _ in range(7):
        b.step(1e-3, "symplectic_euler")
    assert a.x.tobytes() == b.x.tobytes() and a.v.tobytes() == b.v.tobytes()
    assert a.t == b.t


def test_copies_of_a_tiled_scene_are_exactly_independent():
    """Per-component direct solves: copy i of a batch is the scene stepped alone, bit for bit."""
    single = scenes.wire_mixture(omega=3.0)
    n = single.n
    tiled = single.tile(5)
    rng = np.random.default_rng(0)
    alone = []
    for i in range(5):
        one = single.copy()
        one.v = one.v * rng.uniform(0.2, 2.0)  # consistent with the constraints: J v scales
        tiled.v[n * i:n * (i + 1)] = one.v
        alone.append(one)
    for _ in range(200):
        tiled.step(2e-3, "rk4")
        for one in alone:
            one.step(2e-3, "rk4")
    for i, one in enumerate(alone):
        assert tiled.x[n * i:n * (i + 1)].tobytes() == one.x.tobytes()
        assert tiled.v[n * i:n * (i + 1)].tobytes() == one.v.tobytes()


def test_large_components_use_warm_started_cg_like_the_reference():
    s = scenes.angular_chain(links=14)  # 14 rods in one component: CG
    assert fused.pack(s).max_component == 14
    # (the version with conjugate gradients, and angular springs)
    assert fused.pack(s).variant == (True, None, True)
    status, *_ = fused.run(s.copy(), 1e-3, "rk4", 1, s.constraint_solver.lam.copy(), 1e-3)
    assert status == fused.OK  # solved on the fused path, not handed to the reference
    x_ref, v_ref = reference(s, "rk4", 1e-3, 50)
    s.step(1e-3, "rk4", steps=50)
    close(s.x, x_ref, rtol=1e-8)  # two CG solves, each to tol 1e-10
    close(s.v, v_ref, rtol=1e-7)
    assert np.abs(s.constraint_residual()[0]).max() < 1e-9


def test_in_place_edits_are_seen_and_replaced_arrays_repacked():
    s = every_block(1)
    ref = s.copy()
    push = s.forces[1]
    for k in range(5):
        push.force[:] = k * 0.3  # written in place, as the environments do
        ref.forces[1].force[:] = k * 0.3
        s.step(1e-3, "midpoint")
        x, v = METHODS["midpoint"](ref, ref.t, ref.x, ref.v, 1e-3)
        ref.x, ref.v = x, v
    close(s.x, ref.x)
    s.forces[2].ks = s.forces[2].ks * 3.0  # a new array: the pack is rebuilt
    ref.forces[2].ks = ref.forces[2].ks * 3.0
    s.forces[4].kd = 0.9  # a scalar
    ref.forces[4].kd = 0.9
    s.step(1e-3, "midpoint")
    x, _ = METHODS["midpoint"](ref, ref.t, ref.x, ref.v, 1e-3)
    close(s.x, x)


def test_a_rewired_force_block_keeps_the_constraint_rows_and_steps_as_a_fresh_pack():
    """A force block's new index arrays rebuild the pack but not its constraint row graph
    (taken over while the constraint blocks are the same and unchanged); the step is bit for
    bit that of a system packed from scratch. A changed constraint block builds new rows."""
    s = every_block(2)
    s.step(1e-3, "rk4")
    old = fused.pack(s)
    spring = s.forces[2]
    spring.j = np.array([1, 5, 6, 8, 4])  # one spring rewired (a new, validated array)
    fresh = s.copy()
    fresh._packed = None
    new = fused.pack(s)
    assert new is not old and new.rows is old.rows
    s.step(1e-3, "rk4")
    fresh.step(1e-3, "rk4")
    assert fused.pack(fresh).rows is not old.rows
    np.testing.assert_array_equal(s.x, fresh.x)
    np.testing.assert_array_equal(s.v, fresh.v)
    s.constraints[0].radius = s.constraints[0].radius * 1.0  # a new array: new rows
    assert fused.pack(s).rows is not new.rows


def test_out_of_range_index_never_reaches_compiled_code():
    """Bad indices are refused at the door, block arrays cannot be edited behind the system's
    back, and a pack checks every index once, when it is built, before any call reads
    through one (the arrays it holds are immutable, so the check holds for good)."""
    s = every_block(2)
    with pytest.raises(ValueError, match="particle"):
        s.forces[7].particle = np.array([10**6])  # replaced attribute: validated
    idx = np.array(s.forces[2].i)
    s.forces[2].i = idx  # the block keeps its own immutable copy
    idx[0] = 10**6
    with pytest.raises(ValueError):
        s.forces[2].i[0] = 10**6
    with pytest.raises(ValueError):
        s.forces[2].i.flags.writeable = True
    status, *_ = fused.run(s, 1e-3, "rk4", 1, s.constraint_solver.lam.copy(), np.inf)
    assert status == fused.OK
    # an index array forced past the setter (into the block's __dict__, so no new version):
    # the current pack keeps the arrays it checked; a new pack checks them and refuses
    for block, name in [(2, "i"), (2, "j"), (3, "c")]:
        t = s.copy()
        bad = np.array(getattr(t.forces[block], name))
        bad[0] = 10**6
        t.step(1e-3, "rk4")
        t.forces[block].__dict__[name] = bad
        status, *_ = fused.run(t, 1e-3, "rk4", 1, t.constraint_solver.lam.copy(), np.inf)
        assert status == fused.OK  # (the pack's own checked copy)
        assert fused.pack(t).blocks.spring.i.max() < t.n
        t._packed = None
        status, *_ = fused.run(t, 1e-3, "rk4", 1, t.constraint_solver.lam.copy(), np.inf)
        assert status == fused.FALLBACK, (block, name)
        with pytest.raises((ValueError, IndexError)):
            t.step(1e-3, "rk4")


def test_the_step_checks_the_state_once_and_refuses_what_the_full_check_refuses():
    """A step checks its state once (``ParticleSystem._check_state``); when that finds the
    usual exact float64 arrays, ``fused.prepare`` checks only what it leaves open. Both
    together accept exactly what ``prepare``'s own full check accepts, for every odd state
    below, and an unpickled state (whose float64 dtype is an equal but other object) is still
    the usual case."""
    s = scenes.cloth(3, 3)
    s.step(1e-3, "symplectic_euler")
    n, lam = s.n, s.constraint_solver.lam
    good = (s.x, s.v, s.mass, s.inv_mass)
    big = np.zeros((n, 2), ">f8")

    class Sub(np.ndarray):
        pass

    odd = {"fortran": (np.asfortranarray(s.x), 0), "strided": (np.zeros((n, 4))[:, ::2], 0),
           "reversed": (s.x[::-1], 0), "short": (s.x[:-1], 0),
           "float32": (s.x.astype(np.float32), 0),
           "big-endian": (big, 0), "3-d": (s.x[None], 0), "subclass": (s.x.view(Sub), 0),
           "short v": (s.v[:-1], 1), "strided v": (np.zeros((n, 4))[:, ::2], 1),
           "short mass": (s.mass[:-1], 2), "strided mass": (np.zeros(2 * n)[::2], 2),
           "short inv_mass": (s.inv_mass[:-1], 3),
           "float32 inv_mass": (s.inv_mass.astype(np.float32), 3)}
    cases = {"good": (good, lam, 0.0), "short lam": (good, lam[:-1], 0.0),
             "float32 lam": (good, lam.astype(np.float32), 0.0)}
    for name, (arr, k) in odd.items():
        state = list(good)
        state[k] = arr
        cases[name] = (tuple(state), lam, 0.0)
    accepted = []
    for name, (state, lam_, t) in cases.items():
        full = fused.prepare(s, lam_, np.inf, state) is not None
        try:
            usual = ParticleSystem._check_state(*state, t)
        except ValueError:
            assert not full, name  # refused at the door: the full check refuses it too
            continue
        assert (fused.prepare(s, lam_, np.inf, state, usual) is not None) == full, name
        if full:
            accepted.append(name)
    assert accepted == ["good"]
    import pickle
    u = pickle.loads(pickle.dumps(s))
    assert u.x.dtype is not np.dtype(np.float64) and u.x.dtype == np.float64  # (the premise)
    assert ParticleSystem._check_state(u.x, u.v, u.mass, u.inv_mass, u.t)


def test_divergence_keeps_the_state_from_before_the_call():
    s = scenes.spring_pair(ks=1e7)
    x0, v0 = s.x.copy(), s.v.copy()
    with pytest.raises(SimulationDiverged):
        s.step(0.05, "euler", steps=50)
    assert s.x.tobytes() == x0.tobytes() and s.v.tobytes() == v0.tobytes() and s.t == 0.0


def test_residual_limit_flags_a_step_that_leaves_the_constraints():
    s = scenes.pendulum(angle=2.0)
    s.residual_limit = 1e-9  # a large step of euler drifts off the circle by more than this
    x0 = s.x.copy()
    with pytest.raises(SimulationDiverged):
        s.step(0.05, "euler", steps=10)
    assert s.x.tobytes() == x0.tobytes()
    s.residual_limit = 0.5  # the same steps stay well within half a metre
    s.step(0.05, "euler", steps=10)


def test_singular_solves_fall_back_to_the_reference_least_norm_answer():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0))
    s.add(Gravity(), Rod(o, a), Rod(o, a))  # the same rod twice: J W J^T singular
    ref = s.copy()
    s.step(1e-3, "rk4")
    x, v = METHODS["rk4"](ref, 0.0, ref.x, ref.v, 1e-3)
    close(s.x, x, rtol=1e-9)
    assert abs(np.linalg.norm(s.x[a]) - 1.0) < 1e-9


def test_subclassed_blocks_take_the_reference_path():
    class Softer(DampedSpring):
        def accumulate(self, x, v, mass, F):
            super().accumulate(x, v, mass, 0.5 * F)

    s = scenes.spring_pair()
    s.forces[0].__class__ = Softer
    assert not fused.supported(s)
    s.step(1e-3, "rk4")  # runs, on the Python path


def test_environment_variable_turns_the_compiled_path_off():
    code = ("from constrained_particles import kernels, fused, scenes; s = scenes.cloth(); "
            "s.step(1e-3); print(kernels.ENABLED, fused.supported(s))")
    env = {**os.environ, "CPARTICLES_NUMBA": "0"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         check=True)
    assert out.stdout.split() == ["False", "False"]


def test_rattle_constants_are_the_reference_ones():
    from constrained_particles import rattle

    assert (fused_accel.RATTLE_POSITION_TOL, fused_accel.RATTLE_STALL_TOL,
            fused_accel.RATTLE_MAX_ITERATIONS) == (
        rattle.POSITION_TOL, rattle.STALL_TOL, rattle.MAX_ITERATIONS)


@pytest.mark.parametrize("seed", range(3))
def test_fused_rattle_matches_the_reference(seed):
    s = every_block(seed)
    assert fused.run(s.copy(), 1e-3, "rattle", 1, s.constraint_solver.lam.copy(),
                     np.inf)[0] == fused.OK  # compiled, not handed back
    x_ref, v_ref = reference(s, "rattle", 1e-3, 30)
    s.step(1e-3, "rattle", steps=30)
    close(s.x, x_ref, rtol=1e-11)
    close(s.v, v_ref, rtol=1e-10)
    assert np.abs(s.constraint_residual()[0]).max() < 1e-12


def test_fused_rattle_on_tiled_pendulums_and_slider_cranks_is_copy_exact():
    single = scenes.wire_mixture(omega=4.0)
    n = single.n
    tiled = single.tile(3)
    alone = [single.copy() for _ in range(3)]
    for i, one in enumerate(alone):
        one.v = one.v * (0.5 + i)
        tiled.v[n * i:n * (i + 1)] = one.v
    for _ in range(100):
        tiled.step(2e-3, "rattle")
        for one in alone:
            one.step(2e-3, "rattle")
    for i, one in enumerate(alone):
        assert tiled.x[n * i:n * (i + 1)].tobytes() == one.x.tobytes()
        assert tiled.v[n * i:n * (i + 1)].tobytes() == one.v.tobytes()


@pytest.mark.parametrize("method", EXPLICIT)
def test_per_copy_pieces_step_each_copy_as_it_would_be_stepped_alone(method):
    """``step_pieces``: copy i of a tiled scene, split into k_i pieces per step, ends bit for bit
    where ``steps * k_i`` separate steps of ``dt / k_i`` of that copy alone leave it, while the
    other copies (with other counts) wait; cloths (CG components), slider-cranks (direct) and
    a scene with every force and constraint type (each type's live list, several blocks of a
    type, a pinned particle)."""
    for single, dt in [(scenes.wire_mixture(omega=3.0), 4e-3),
                       (scenes.cloth(nx=4, ny=3, push=0.2), 1e-3), (every_block(4), 1e-3)]:
        single.add(Drag(0.1))
        n = single.n
        counts = [1, 3, 2, 4]
        tiled = single.tile(len(counts))
        rng = np.random.default_rng(1)
        alone = []
        for i in range(len(counts)):
            one = single.copy()
            one.v = one.v * rng.uniform(0.5, 2.0)
            tiled.v[n * i:n * (i + 1)] = one.v
            alone.append(one)
        pieces = np.repeat(np.array(counts, np.int64), n)
        for _ in range(3):  # several calls: the warm starts carry over as they would alone
            assert tiled.step_pieces(dt, method, 5, pieces)
            for one, k in zip(alone, counts, strict=True):
                for _ in range(5 * k):
                    one.step(dt / k, method)
        for i, one in enumerate(alone):
            assert tiled.x[n * i:n * (i + 1)].tobytes() == one.x.tobytes(), (i, method)
            assert tiled.v[n * i:n * (i + 1)].tobytes() == one.v.tobytes(), (i, method)
        assert tiled.t == pytest.approx(15 * dt)


def test_live_lists_are_the_elements_rows_and_components_of_the_live_particles():
    """``_gate``'s lists for a step that only some copies take, against a plain numpy
    selection: every element whose first particle is live (in element order, whether its type
    is listed by per-particle ranges or by a scan), every row and component of a live
    particle, each row once, and a component's rows in row order."""
    s = every_block(3).tile(5)
    s.add(Drag(0.1))
    p = fused.pack(s)
    live = p.live
    blocks, rows = p.blocks, p.rows
    assert not live.ranged.all() and live.ranged.any()  # both kinds of types are in the scene
    rng = np.random.default_rng(0)
    for trial in range(6):
        counts = np.repeat(rng.integers(0, 3, 5), s.n // 5).astype(np.int64)
        step = int(trial % 2)
        live.sizes[-1] = 0
        fused._gate(step, counts, rows, blocks, live)
        sizes = live.sizes
        alive = counts > step
        assert live.mask.tolist() == alive.tolist()
        assert live.particles[:sizes[0]].tolist() == np.flatnonzero(alive).tolist()
        for t, b in enumerate(blocks):
            want = np.flatnonzero(alive[b[0]])  # (each record's first field: first particles)
            if t == 6:  # mouse springs: the active ones
                want = want[blocks.mouse.active[want]]
            assert live.elements[t][:sizes[3 + t]].tolist() == want.tolist(), t
        live_rows = live.rows[:sizes[1]]
        assert sorted(live_rows.tolist()) == np.flatnonzero(alive[rows.cols[:, 0] // 2]).tolist()
        comps = live.components[:sizes[2]]
        firsts = rows.cols[rows.comp_rows[rows.comp_ptr[:-1]], 0] // 2
        assert sorted(comps.tolist()) == np.flatnonzero(alive[firsts]).tolist()
        k = 0
        for c in comps:  # rows grouped by component, in row order within each
            mine = rows.comp_rows[rows.comp_ptr[c]:rows.comp_ptr[c + 1]]
            assert live_rows[k:k + len(mine)].tolist() == sorted(mine.tolist())
            k += len(mine)
        assert not live.seen.any()  # the marks are cleared for the next call


def test_per_copy_pieces_refuse_what_they_cannot_do():
    s = scenes.wire_mixture(omega=3.0).tile(2)
    x0 = s.x.copy()
    mixed = np.array([1, 2, 2, 2], np.int64)  # the crank and slider of copy 0 are coupled
    assert not s.step_pieces(1e-3, "rk4", 1, mixed)
    assert not s.step_pieces(1e-3, "rattle", 1, np.ones(4, np.int64))
    assert s.x.tobytes() == x0.tobytes() and s.t == 0.0
    for bad in [np.ones(3, np.int64), np.zeros(4, np.int64), np.ones(4), [1, 1, 1, 1]]:
        with pytest.raises(ValueError, match="pieces"):
            s.step_pieces(1e-3, "rk4", 1, bad)
    for steps in [0, -2, 1.5]:
        with pytest.raises(ValueError, match="steps"):
            s.step_pieces(1e-3, "rk4", steps, np.ones(4, np.int64))
    assert s.x.tobytes() == x0.tobytes() and s.t == 0.0


def test_per_copy_pieces_divergence_keeps_the_state():
    s = scenes.spring_pair(ks=1e7).tile(2)
    x0, v0 = s.x.copy(), s.v.copy()
    with pytest.raises(SimulationDiverged):
        s.step_pieces(0.05, "euler", 20, np.array([1, 1, 2, 2], np.int64))
    assert s.x.tobytes() == x0.tobytes() and s.v.tobytes() == v0.tobytes() and s.t == 0.0


def test_many_springs_go_in_blocks_bitwise_like_the_plain_loop_and_close_to_numpy():
    """More springs than the compiled loop's plain-loop limit (a last block part full, one
    spring of zero length): bit for bit the block kernel's plain loop, and within 1e-12 of
    the force formula written here in numpy."""
    rng = np.random.default_rng(3)
    n, k = 300, 4 * fused_accel.SPRING_BLOCK + 37
    x, v = rng.uniform(-1, 1, (n, 2)), rng.normal(size=(n, 2))
    i, j = rng.integers(0, n, k), rng.integers(0, n, k)
    i[5] = j[5]  # zero length: no force
    ks, kd, rest = rng.uniform(1, 100, k), rng.uniform(0, 2, k), rng.uniform(0, 1, k)
    blocks = np.zeros((n, 2))
    fused_accel._springs(x, v, blocks,
                         SpringArrays(i, j, rest, ks, kd, fused.spring_runs(i, j)), True)
    plain = np.zeros((n, 2))
    kernels.spring_forces(x, v, i, j, ks, kd, rest, plain)
    assert blocks.tobytes() == plain.tobytes()
    d, u = x[i] - x[j], v[i] - v[j]
    length = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mag = np.where(length > 0, ks * (length - rest) + kd * (u * d).sum(axis=1) / length, 0.0)
        f = np.where(length[:, None] > 0, -mag[:, None] * d / length[:, None], 0.0)
    expected = np.zeros((n, 2))
    np.add.at(expected, i, f)
    np.add.at(expected, j, -f)
    close(blocks, expected)


def test_runs_of_springs_are_bitwise_the_plain_loop():
    """Runs of springs (both ends stepping by one: a cloth's rows, columns and diagonals) go
    through contiguous slices; with runs whose ends overlap either way round (offsets +-1,
    +-3), ends far apart, runs longer than a block, springs between runs and a run at the end,
    the forces are bit for bit the block kernel's plain loop."""
    rng = np.random.default_rng(7)
    n = 2000
    parts = [(np.arange(100, 100 + 700), 1),      # overlapping ends, offset +1, > 2 blocks
             (rng.integers(0, n, 50), None),      # scattered
             (np.arange(900, 900 + 300), -3),     # overlapping, negative offset
             (np.arange(10, 10 + 40), 1000),      # disjoint ends
             (rng.integers(0, n, 5), None),
             (np.arange(1500, 1500 + 257), -1),
             (np.arange(1300, 1300 + fused_accel.RUN_MIN - 1), 2),   # one short of a run
             (np.arange(40, 40 + 600), 64)]
    i = np.concatenate([a for a, _ in parts])
    j = np.concatenate([a + d if d is not None else rng.integers(0, n, len(a)) for a, d in parts])
    runs = fused.spring_runs(i, j)
    assert len(runs) == 5 and runs[-1, 1] == len(i)
    assert not runs.flags.writeable
    k = len(i)
    x, v = rng.uniform(-1, 1, (n, 2)), rng.normal(size=(n, 2))
    ks, kd, rest = rng.uniform(1, 100, k), rng.uniform(0, 2, k), rng.uniform(0, 1, k)
    got, plain = rng.normal(size=(n, 2)), np.zeros((n, 2))
    plain[:] = got  # forces add to what F holds
    scattered = got.copy()
    fused_accel._springs(x, v, got, SpringArrays(i, j, rest, ks, kd, runs), True)
    kernels.spring_forces(x, v, i, j, ks, kd, rest, plain)
    assert got.tobytes() == plain.tobytes()
    # the fused step's version for packs without runs takes every spring one by one
    fused_accel._springs(x, v, scattered, SpringArrays(i, j, rest, ks, kd, runs), None)
    assert scattered.tobytes() == plain.tobytes()


def test_a_spring_list_that_no_longer_fits_its_runs_is_refused():
    """The runs are checked against the index arrays when the pack is built (both are
    immutable, so the check holds for every later call): runs that the spring list does not
    hold make the pack invalid, and the pack's runs cannot be reopened for writing."""
    s = scenes.cloth(40, 3, wall_x=None)
    p = fused.pack(s)
    runs = p.blocks.spring.runs
    assert len(runs) > 0 and p._consistent()
    with pytest.raises(ValueError):
        runs.flags.writeable = True
    bad = np.array(runs)
    bad[0, 1] += 1  # one spring too many
    for wrong in (bad, np.ascontiguousarray(runs[:, :1])):  # (the second: no ends column)
        p.blocks = p.blocks._replace(spring=p.blocks.spring._replace(runs=packing._ro(wrong)))
        assert not p._consistent()


@pytest.mark.parametrize("method", ["symplectic_euler", "rk4"])
def test_tiled_cloths_are_copy_exact_with_the_spring_blocks(method):
    """A small cloth alone takes the plain spring loop; eight copies of it (616 springs) take
    the blocked one: each copy still ends bit for bit as the cloth stepped alone, and the
    batch stays within 1e-12 of the reference."""
    single = scenes.cloth(nx=5, ny=4, push=0.3)
    n = single.n
    tiled = single.tile(8)
    assert len(fused.pack(tiled).blocks.spring.i) > 2 * fused_accel.SPRING_BLOCK
    rng = np.random.default_rng(1)
    alone = []
    for c in range(8):
        one = single.copy()
        one.v = rng.normal(0, 0.05, one.v.shape) * (one.inv_mass > 0)[:, None]
        one.v[:5, 1] = 0.0  # the top row slides on its wire
        tiled.v[n * c:n * (c + 1)] = one.v
        alone.append(one)
    x_ref, v_ref = reference(tiled, method, 1e-3, 30)
    tiled.step(1e-3, method, steps=30)
    close(tiled.x, x_ref)
    close(tiled.v, v_ref)
    for c, one in enumerate(alone):
        one.step(1e-3, method, steps=30)
        assert tiled.x[n * c:n * (c + 1)].tobytes() == one.x.tobytes(), c
        assert tiled.v[n * c:n * (c + 1)].tobytes() == one.v.tobytes(), c


def test_small_components_take_the_fused_step_without_conjugate_gradients():
    # every component of at most DIRECT_MAX rows: the pack says None, and the fused step's
    # version for None (which compiles no conjugate gradients) steps it like the reference
    s = scenes.wire_mixture()
    p = fused.pack(s)
    assert 0 < p.max_component <= DIRECT_MAX and p.variant == (None, None, None)
    x_ref, v_ref = reference(s, "rk4", 1e-3, 50)
    status, *_ = fused.run(s.copy(), 1e-3, "rk4", 1, s.constraint_solver.lam.copy(), 1e-3)
    assert status == fused.OK
    s.step(1e-3, "rk4", steps=50)
    close(s.x, x_ref)
    close(s.v, v_ref)


@pytest.mark.parametrize("size, runs", [(6, None), (10, True)])
def test_the_pack_names_the_spring_runs_its_step_needs(size, runs):
    # a small cloth's springs form no runs (every spring goes one by one, and the fused
    # step's version for None compiles no run loop); a larger one's rows do
    s = scenes.cloth(size, size)
    assert fused.pack(s).variant == (None, runs, None)
    assert (len(fused.pack(s).blocks.spring.runs) > 0) == (runs is True)
    status, *_ = fused.run(s.copy(), 1e-3, "midpoint", 1, s.constraint_solver.lam.copy(), 1e-3)
    assert status == fused.OK  # stepped by the fused kernel, not handed to the reference
    x_ref, v_ref = reference(s, "midpoint", 1e-3, 20)
    s.step(1e-3, "midpoint", steps=20)
    close(s.x, x_ref)
    close(s.v, v_ref)


def _one_rare_element(kind: str) -> ParticleSystem:
    """Four particles on springs and a rod, with one angular spring, one mouse spring or one
    fixed point (the elements of the fused step's ``extra`` part) and nothing else rare."""
    s = ParticleSystem()
    s.add_particles([(0.0, 0.0), (0.5, 0.1), (1.0, -0.1), (1.4, 0.2)],
                    [(0.1, 0.0), (0.0, 0.2), (-0.1, 0.1), (0.0, -0.3)], mass=[1.0, 0.5, 2.0, 1.0])
    s.add(Gravity((0.0, -9.81)), DampedSpring([0, 1], [1, 2], ks=20.0, kd=0.2), Rod(2, 3))
    s.add({"angular": AngularSpring([0], [1], [2], k=1.5, kd=0.05, rest=2.5),
           "mouse": MouseSpring(3, anchor=(1.0, 1.0), ks=30.0, kd=0.5),
           "fixed": FixedPoint(0)}[kind])
    return s


def _fused_call(s: ParticleSystem, variant: tuple) -> tuple[int, np.ndarray, np.ndarray]:
    """One midpoint step of ``s`` by ``fused.fused_steps`` with the given variant flags; the
    status and the outputs (filled with 7.0 before the call)."""
    p, start, settings = fused.prepare(s, s.constraint_solver.lam.copy(), 1e-3)
    code, rattle = fused.integrator_args("midpoint")
    x_out, v_out = np.full_like(s.x, 7.0), np.full_like(s.v, 7.0)
    status, _ = fused.fused_steps(code, rattle, *variant, (1, 1e-3, np.zeros(0),
                                  np.zeros(0, np.int64)), tuple(start), (x_out, v_out),
                                  tuple(settings), p.refs.engine, None)
    return int(status), x_out, v_out


@pytest.mark.parametrize("kind", ["angular", "mouse", "fixed"])
def test_the_step_without_the_rarer_elements_refuses_blocks_that_hold_them(kind):
    # one angular spring, mouse spring or fixed point is enough for the pack to ask for the
    # fused step's version with their loops; the version without them (extra None) hands the
    # system to the reference (FALLBACK, outputs untouched) instead of dropping the element
    s = _one_rare_element(kind)
    p = fused.pack(s)
    assert p.variant == (None, None, True)
    status, x_out, v_out = _fused_call(s, p.variant)
    assert status == fused.OK
    x_ref, v_ref = reference(s, "midpoint", 1e-3, 1)
    close(x_out, x_ref)
    close(v_out, v_ref)
    # (after that step the pack's workspace holds valid rows: a version that skipped the
    # fixed point's rows would solve with them instead of failing on a zero row)
    status, x_out, v_out = _fused_call(s, (None, None, None))
    assert status == fused.FALLBACK and (x_out == 7.0).all() and (v_out == 7.0).all()


def test_the_step_without_conjugate_gradients_hands_large_components_to_the_reference():
    # a component of 14 rows with large None (the version without conjugate gradients):
    # FALLBACK with the outputs untouched, never a step that skips the component's solve
    s = scenes.angular_chain(links=14)
    p = fused.pack(s)
    assert p.variant[0] is True
    status, x_out, v_out = _fused_call(s, (None, *p.variant[1:]))
    assert status == fused.FALLBACK and (x_out == 7.0).all() and (v_out == 7.0).all()
    assert _fused_call(s, p.variant)[0] == fused.OK


def _env_cases() -> list[tuple[str, str]]:
    import envs
    return [(env_id, mode) for env_id in envs.ENV_IDS
            for mode in envs.task_spec(env_id).action_modes]


@pytest.mark.parametrize("env_id, mode", _env_cases())
def test_every_env_steps_on_the_fused_kernel(env_id, mode):
    # a pack whose variant left out a part its system needs would fall back to the reference
    # at every step (slow, not wrong): each env's system, in each action mode, steps on the
    # fused kernel itself, with the variant its blocks call for
    import gymnasium as gym

    env = gym.make(env_id, action_mode=mode)
    env.reset(seed=0)
    task = env.unwrapped.task
    s = task.system
    p = fused.pack(s)
    b = p.blocks
    rare = len(b.angular.a) + len(b.mouse.particle) + len(b.fixed.particles)
    assert p.variant == (True if p.max_component > DIRECT_MAX else None,
                         True if len(b.spring.runs) else None, True if rare else None)
    status, *_ = fused.run(s.copy(), task.dt, task.integrator, 1,
                           s.constraint_solver.lam.copy(), s.residual_limit)
    assert status == fused.OK
    env.close()
