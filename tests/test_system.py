"""ParticleSystem: bad input, divergence, determinism, copies, batching and the integrators."""

import pickle

import numpy as np
import pytest

from constrained_particles import (
    METHODS,
    ORDERS,
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
    scenes,
)

EXPLICIT = ["euler", "midpoint", "rk4", "symplectic_euler"]


def three_particles() -> ParticleSystem:
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    return s


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(("kwargs", "match"), [
    ({"position": (np.nan, 0.0)}, "position"),
    ({"position": (0.0, np.inf)}, "position"),
    ({"position": (0.0, 0.0), "velocity": (np.inf, 0.0)}, "velocity"),
    ({"position": (0.0, 0.0), "velocity": (0.0, np.nan)}, "velocity"),
    ({"position": (0.0, 0.0), "mass": 0.0}, "mass"),
    ({"position": (0.0, 0.0), "mass": -1.0}, "mass"),
    ({"position": (0.0, 0.0), "mass": np.nan}, "mass"),
    ({"position": (0.0, 0.0, 0.0)}, "position"),
])
def test_bad_particles(kwargs, match):
    s = three_particles()
    with pytest.raises(ValueError, match=match):
        s.add_particle(**kwargs)
    assert s.n == 3 and len(s.v) == len(s.mass) == len(s.inv_mass) == 3


def test_bad_particle_arrays():
    s = ParticleSystem()
    with pytest.raises(ValueError, match="positions"):
        s.add_particles(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="velocity"):
        s.add_particles(np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="mass"):
        s.add_particles(np.zeros((3, 2)), mass=[1.0, 0.0, 1.0])
    assert s.n == 0


INDEX_CASES = [
    (lambda: Gravity(particles=[0, 3]), "particles"),
    (lambda: ConstantForce([5], (1.0, 0.0)), "particles"),
    (lambda: DampedSpring(3, 0), "i"),
    (lambda: DampedSpring(0, -1), "j"),
    (lambda: AngularSpring(7, 1, 2), "a"),
    (lambda: AngularSpring(0, 3, 2), "b"),
    (lambda: AngularSpring(0, 1, 4), "c"),
    (lambda: Drag(0.1, particles=[-2]), "particles"),
    (lambda: Wall(particles=[3]), "particles"),
    (lambda: MouseSpring(particle=3, anchor=(0.0, 0.0)), "particle"),
    (lambda: CircularWire(3), "particles"),
    (lambda: Rod(0, 3), "b"),
    (lambda: HorizontalWire(8), "particles"),
    (lambda: LineWire(-4), "particles"),
    (lambda: FixedPoint([0, 9]), "particles"),
]


@pytest.mark.parametrize(("make", "field"), INDEX_CASES)
def test_unknown_particle_indices(make, field):
    s = three_particles()
    # negative indices are rejected by the constructor, too-large ones when added
    with pytest.raises(ValueError, match=rf"\b{field} (holds unknown|must hold integer) particle"):
        s.add(make())
    assert s.forces == [] and s.constraints == []


@pytest.mark.parametrize(("make", "match"), [
    (lambda: DampedSpring(0, 1, rest=-0.5), "rest"),
    (lambda: DampedSpring(0, 1, ks=-1.0), "ks"),
    (lambda: DampedSpring(0, 1, kd=-1.0), "kd"),
    (lambda: DampedSpring([0, 1], [1]), "i and j"),
    (lambda: DampedSpring(1, 1), "i and j"),
    (lambda: DampedSpring(1.5, 0), "i must hold integer"),
    (lambda: DampedSpring(0, 1, rest=[1.0, 2.0]), "rest"),
    (lambda: AngularSpring(0, 1, 2, rest=np.nan), "rest"),
    (lambda: AngularSpring(0, 1, 2, k=-2.0), "k"),
    (lambda: AngularSpring(0, 1, 1), "a, b and c"),
    (lambda: Gravity((np.nan, 0.0)), "g"),
    (lambda: ConstantForce([0, 1], [(1.0, 0.0)] * 3), "force"),
    (lambda: Drag(-0.1), "kd"),
    (lambda: Wall((0.0, 0.0), 1.0), "normal"),
    (lambda: Wall((1.0, 0.0), np.inf), "offset"),
    (lambda: Wall((1.0, 0.0), 0.0, kw=-1.0), "kw"),
    (lambda: MouseSpring(0, (0.0, 0.0), ks=-5.0), "ks"),
    (lambda: CircularWire(0, radius=-1.0), "radius"),
    (lambda: CircularWire(0, radius=0.0), "radius"),
    (lambda: Rod(0, 1, length=-1.0), "length"),
])
def test_bad_term_parameters(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"tol": 0.0}, "tol"), ({"ks": -1.0}, "ks"), ({"kd": np.nan}, "kd"),
    ({"divergence_limit": 0.0}, "divergence_limit"), ({"solver": "qr"}, "solver"),
])
def test_bad_system_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ParticleSystem(**kwargs)


def test_unknown_method_lists_valid_ones():
    s = scenes.spring_pair()
    with pytest.raises(ValueError, match="method") as err:
        s.step(1e-3, method="rk5")
    assert all(name in str(err.value) for name in METHODS)
    assert s.t == 0.0


@pytest.mark.parametrize("dt", [0.0, -1e-3, np.nan, np.inf, "0.001", None])
def test_bad_dt(dt):
    s = scenes.pendulum()
    x = s.x.copy()
    with pytest.raises(ValueError, match="dt"):
        s.step(dt)
    assert s.t == 0.0 and np.array_equal(s.x, x)


def test_bad_terms_and_copies():
    s = scenes.spring_pair()
    with pytest.raises(ValueError, match="terms"):
        s.add("spring")
    with pytest.raises(ValueError, match="terms"):
        s.remove(Gravity())
    with pytest.raises(ValueError, match="copies"):
        s.tile(0)


# ---------------------------------------------------------------- divergence
def assert_step_diverges_and_keeps_state(s: ParticleSystem, dt: float, method: str):
    x, v, t = s.x.copy(), s.v.copy(), s.t
    lam = s.constraint_solver.lam.copy()
    with pytest.raises(SimulationDiverged):
        s.step(dt, method=method)
    assert np.array_equal(s.x, x) and np.array_equal(s.v, v) and s.t == t
    assert np.array_equal(s.constraint_solver.lam, lam)


def test_stiff_spring_with_euler_diverges_and_keeps_state():
    s = scenes.spring_pair(ks=1e5, kd=0.0)
    for _ in range(100):
        x, v, t = s.x.copy(), s.v.copy(), s.t
        try:
            s.step(0.05, method="euler")
        except SimulationDiverged:
            break
    else:
        pytest.fail("an explicit Euler step of 0.05 s on a 1e5 N/m spring must blow up")
    assert np.array_equal(s.x, x) and np.array_equal(s.v, v) and s.t == t
    assert 0 < t  # some steps succeeded before the failing one


def test_overflowing_forces_diverge_and_keep_state():
    s = scenes.spring_pair(ks=1e308, kd=0.0)
    assert_step_diverges_and_keeps_state(s, 1e-3, "rk4")


def test_constrained_divergence_keeps_state_and_warm_start():
    s = run(scenes.wire_mixture(), 3, dt=1e-3)
    assert s.constraint_solver.lam.any()
    anchor = s.add_particle((2.0, 2.0), fixed=True)
    s.add(DampedSpring(0, anchor, rest=0.1, ks=1e7))  # pulls the crank along its wire
    s.step(1e-6)  # fills the warm start of the rebuilt solver
    assert s.constraint_solver.lam.any()
    assert_step_diverges_and_keeps_state(s, 1.0, "euler")


# ---------------------------------------------------------------- determinism, copies
def busy_system() -> ParticleSystem:
    """A cloth pushed into its wall, plus an active mouse spring: most code paths at once."""
    s = scenes.cloth(nx=4, ny=4, push=0.5, wall_x=0.35)
    mouse = MouseSpring(15, (0.5, -0.5), ks=20.0, kd=0.5)
    s.add(mouse, AngularSpring(4, 5, 6, k=0.2, kd=0.01))
    return s


def run(s: ParticleSystem, steps: int, dt: float = 2e-3, method: str = "rk4"):
    for _ in range(steps):
        s.step(dt, method=method)
    return s


def test_determinism_from_copies():
    base = run(busy_system(), 10)
    a, b = run(base.copy(), 100), run(base.copy(), 100)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and a.t == b.t
    c = run(run(busy_system(), 10), 100)
    assert np.array_equal(a.x, c.x) and np.array_equal(a.v, c.v)


def test_copy_is_independent():
    s = run(busy_system(), 5)
    c = s.copy()
    np.testing.assert_array_equal(c.constraint_solver.lam, s.constraint_solver.lam)
    x = s.x.copy()
    run(c, 5)
    c.forces[-1].k[:] = 99.0
    next(f for f in c.forces if isinstance(f, ConstantForce)).force[:] = 0.0
    assert np.array_equal(s.x, x) and s.t == pytest.approx(5 * 2e-3)
    assert s.forces[-1].k[0] == 0.2
    assert next(f for f in s.forces if isinstance(f, ConstantForce)).force[0, 0] == 0.5


@pytest.mark.parametrize("make", [busy_system, scenes.wire_mixture, scenes.angular_chain])
def test_pickle_round_trip(make):
    s = run(make(), 5)
    r = pickle.loads(pickle.dumps(s))
    assert np.array_equal(r.x, s.x) and np.array_equal(r.v, s.v) and r.t == s.t
    assert r.energy() == s.energy()
    run(r, 50)
    run(s, 50)
    assert np.array_equal(r.x, s.x) and np.array_equal(r.v, s.v)


# ---------------------------------------------------------------- tiling
def with_solver(system: ParticleSystem, solver: str) -> ParticleSystem:
    """The same system rebuilt with the multiplier solver ``solver`` (scenes default to cg)."""
    out = ParticleSystem(solver=solver, ks=system.ks, kd=system.kd)
    out.add_particles(system.x, system.v, system.mass, system.fixed)
    out.add(*system.forces, *system.constraints)
    return out


TILE_SCENES = {
    "wire_mixture": scenes.wire_mixture,
    "angular_chain": lambda: scenes.angular_chain(links=4),
    "busy": busy_system,
    "gravity": scenes.gravity,
}


@pytest.mark.parametrize("solver", ["direct", "cg"])
@pytest.mark.parametrize("name", TILE_SCENES)
def test_tile_behaves_like_independent_copies(name, solver):
    base = with_solver(TILE_SCENES[name](), solver)
    n, copies = base.n, 3
    rng = np.random.default_rng(0)
    tiled = base.tile(copies)
    singles = []
    for c in range(copies):
        single = base.copy()
        single.v = single.v * (1.0 + 0.4 * c) + 0.1 * c * rng.normal(size=single.v.shape)
        single.v[single.fixed] = 0.0
        for f in single.forces:  # each copy gets its own actions
            if isinstance(f, ConstantForce):
                f.force[:] = (0.2 * c, -0.1)
        single.project()
        singles.append(single)
        tiled.x[c * n:(c + 1) * n] = single.x
        tiled.v[c * n:(c + 1) * n] = single.v
        for f in tiled.forces:
            if isinstance(f, ConstantForce):
                f.force[c * len(f.force) // copies:(c + 1) * len(f.force) // copies] = (0.2 * c,
                                                                                        -0.1)
    J = tiled.constraint_solver.J.toarray()
    rows = base.constraint_solver.m
    for c in range(copies):  # block-diagonal
        block = J[c * rows:(c + 1) * rows]
        assert not np.delete(block, np.s_[2 * c * n:2 * (c + 1) * n], axis=1).any()
    run(tiled, 60, dt=2e-3)
    for single in singles:
        run(single, 60, dt=2e-3)
    # cg stops at a relative residual of 1e-10 of the whole batch's right-hand side
    tol_x, tol_v = (1e-12, 1e-11) if solver == "direct" else (1e-10, 1e-9)
    for c, single in enumerate(singles):
        np.testing.assert_allclose(tiled.x[c * n:(c + 1) * n], single.x, rtol=0, atol=tol_x)
        np.testing.assert_allclose(tiled.v[c * n:(c + 1) * n], single.v, rtol=0, atol=tol_v)
    assert tiled.energy() == pytest.approx(sum(s.energy() for s in singles), rel=1e-9)


def test_tiled_mouse_springs_are_per_copy():
    base = scenes.spring_pair()
    base.add(MouseSpring())
    tiled = base.tile(3)
    mouse = tiled.forces[-1]
    assert len(mouse) == 3 and not mouse.active.any()
    mouse.set([1], particles=[3], anchors=(0.0, 1.0), active=[True])
    F = tiled.applied_forces(tiled.x, tiled.v) - base.tile(3).applied_forces(tiled.x, tiled.v)
    np.testing.assert_allclose(F[3], -50.0 * (tiled.x[3] - (0.0, 1.0)))
    assert not np.delete(F, 3, axis=0).any()


def test_tiled_mouse_spring_grab_accepts_particles_of_later_copies():
    base = scenes.spring_pair()
    base.add(MouseSpring())
    tiled = base.tile(3)
    mouse = tiled.forces[-1]
    mouse.grab(4, (0.0, 1.0), element=2)  # particle 0 of copy 2
    assert mouse.active[2] and not mouse.active[:2].any()
    F = tiled.applied_forces(tiled.x, tiled.v) - base.tile(3).applied_forces(tiled.x, tiled.v)
    np.testing.assert_allclose(F[4], -50.0 * (tiled.x[4] - (0.0, 1.0)))


# ---------------------------------------------------------------- integrators
def spring_pair_exact(t: float, separation=1.0, rest=0.6, ks=20.0, kd=0.2, mass=0.5):
    """Exact state of scenes.spring_pair: a damped oscillator in the separation l = x1 - x0."""
    mu = mass / 2  # reduced mass
    gamma, w0sq = kd / (2 * mu), ks / mu
    wd = np.sqrt(w0sq - gamma**2)
    e0 = separation - rest
    e = e0 * np.exp(-gamma * t) * (np.cos(wd * t) + gamma / wd * np.sin(wd * t))
    edot = -e0 * np.exp(-gamma * t) * (w0sq / wd) * np.sin(wd * t)
    l, ldot = rest + e, edot
    x = np.array([[-l / 2, 0.0], [l / 2, 0.0]])
    v = np.array([[-ldot / 2, 0.0], [ldot / 2, 0.0]])
    return x, v


# step sizes in each method's asymptotic range (omega h <= 0.04) and above round-off
STEPS = {1: (2e-3, 1e-3, 5e-4), 2: (4e-3, 2e-3, 1e-3), 4: (0.02, 0.01, 0.005)}


@pytest.mark.parametrize("method", sorted(ORDERS))
def test_measured_order_on_spring_pair(method):
    T = 0.5
    x_ref, v_ref = spring_pair_exact(T)
    errors = []
    for h in STEPS[ORDERS[method]]:
        s = scenes.spring_pair()
        run(s, int(round(T / h)), dt=h, method=method)
        errors.append(max(np.abs(s.x - x_ref).max(), np.abs(s.v - v_ref).max() / 10))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert errors[-1] < 1e-2
    assert np.all(np.abs(orders - ORDERS[method]) < 0.1), (errors, orders)


class Recorder:
    """Wraps ``system.acceleration``; records every (t, x, v) it is called with and the result."""

    def __init__(self, system):
        self.calls, self.results = [], []
        self.inner = system.acceleration

    def __call__(self, t, x, v):
        self.calls.append((t, x.copy(), v.copy()))
        self.results.append(self.inner(t, x, v))
        return self.results[-1]


@pytest.mark.parametrize("method", EXPLICIT)
def test_every_stage_reevaluates_at_its_own_state(method):
    """Stage times and states, and the final combination, of docs/physics.md's formulas."""
    s = scenes.wire_mixture()
    s.add(Drag(0.3))  # velocity dependence, so the stage velocities matter
    s.step(1e-3)
    rec = Recorder(s)
    s.acceleration = rec
    h, t, x, v = 0.01, s.t, s.x.copy(), s.v.copy()
    s.step(h, method=method)
    del s.acceleration
    a = rec.results
    if method == "euler":
        expected = [(t, x, v)]
        final = (x + h * v, v + h * a[0])
    elif method == "symplectic_euler":
        expected = [(t, x, v)]
        final = (x + h * (v + h * a[0]), v + h * a[0])
    elif method == "midpoint":
        vm = v + h / 2 * a[0]
        expected = [(t, x, v), (t + h / 2, x + h / 2 * v, vm)]
        final = (x + h * vm, v + h * a[1])
    else:
        v2, v3 = v + h / 2 * a[0], v + h / 2 * a[1]
        v4 = v + h * a[2]
        expected = [(t, x, v), (t + h / 2, x + h / 2 * v, v2), (t + h / 2, x + h / 2 * v2, v3),
                    (t + h, x + h * v3, v4)]
        final = (x + h / 6 * (v + 2 * v2 + 2 * v3 + v4),
                 v + h / 6 * (a[0] + 2 * a[1] + 2 * a[2] + a[3]))
    assert len(rec.calls) == len(expected)
    for (tc, xc, vc), (te, xe, ve) in zip(rec.calls, expected, strict=True):
        assert tc == pytest.approx(te, abs=1e-15)
        np.testing.assert_allclose(xc, xe, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(vc, ve, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(s.x, final[0], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(s.v, final[1], rtol=1e-14, atol=1e-15)
    # distinct stages really are distinct states, so a cached force would be caught
    assert len({xc.tobytes() + vc.tobytes() for _, xc, vc in rec.calls}) == len(rec.calls)


def test_acceleration_is_pure():
    s = run(busy_system(), 3)
    x, v = s.x.copy(), s.v.copy()
    a1 = s.acceleration(s.t, s.x, s.v)
    a2 = s.acceleration(s.t, s.x, s.v)
    np.testing.assert_allclose(a1, a2, rtol=1e-12, atol=1e-12)
    assert np.array_equal(s.x, x) and np.array_equal(s.v, v)
    assert not a1[s.fixed].any()


def test_fixed_particles_never_move():
    s = scenes.angular_chain(links=3)
    s.add_particle((0.5, 0.5), velocity=(3.0, 1.0), fixed=True)
    s.add(DampedSpring(0, 4, ks=10.0), DampedSpring(4, 2, ks=10.0))
    x_fixed = s.x[s.fixed].copy()
    assert not s.v[s.fixed].any()
    run(s, 100, dt=1e-3)
    assert np.array_equal(s.x[s.fixed], x_fixed) and not s.v[s.fixed].any()


@pytest.mark.parametrize(("make", "seconds", "rtol"), [
    (lambda: scenes.spring_pair(kd=0.0), 3.0, 1e-9),
    (lambda: scenes.pendulum(angle=1.2), 1.0, 1e-8),
    (lambda: scenes.angular_chain(links=4, damping=0.0), 0.5, 1e-6),
    (scenes.wire_mixture, 0.5, 1e-6),
])
def test_energy_is_conserved_without_damping(make, seconds, rtol):
    s = make()
    E0 = s.energy()
    scale = max(abs(E0), s.kinetic_energy(), 1.0)
    run(s, int(round(seconds / 1e-3)), dt=1e-3)
    assert abs(s.energy() - E0) < rtol * scale
    assert s.kinetic_energy() > 1e-3 * scale  # it did move


def test_damping_dissipates_energy():
    s = scenes.spring_pair(kd=0.5)
    energies = [s.energy()]
    for _ in range(20):
        run(s, 50, dt=1e-3)
        energies.append(s.energy())
    assert np.all(np.diff(energies) < 0)


def test_adding_particles_and_removing_terms_rebuilds_the_solver():
    s = scenes.wire_mixture()
    rows = s.constraint_solver.m
    p = s.add_particle((2.0, 2.0))
    assert s.constraint_solver.n == s.n == 3
    wire = CircularWire(p, center=(2.0, 1.0))
    s.add(wire)
    assert s.constraint_solver.m == rows + 1
    s.step(1e-3)
    assert abs(np.linalg.norm(s.x[p] - (2.0, 1.0)) - 1.0) < 1e-9
    s.remove(wire)
    assert s.constraint_solver.m == rows
    gravity = s.forces[0]
    s.remove(gravity)
    assert not s.applied_forces(s.x, s.v).any()


def test_shapes_describe_every_term():
    s = busy_system()
    s.add(Rod(0, 5))
    kinds = {(sh.kind, sh.style) for sh in s.shapes(constraint_forces=True)}
    assert {("segment", "spring"), ("line", "wire"), ("halfplane", "wall"), ("arrow", "applied"),
            ("segment", "mouse"), ("angle", "angular"), ("segment", "rod"),
            ("arrow", "constraint")} <= kinds
    for sh in s.shapes(constraint_forces=True):
        assert all(arr is None or np.all(np.isfinite(arr)) for arr in (sh.a, sh.b, sh.value))


def test_changing_solver_options_after_construction_takes_effect():
    s = scenes.wire_mixture()
    s.step(1e-3)
    s.tol = 1e-13
    assert s.constraint_solver.tol == 1e-13
    s.solver = "direct"
    assert s.constraint_solver.method == "direct"
    s.step(1e-3)
    s.solver = "bogus"
    with pytest.raises(ValueError, match="solver"):
        s.step(1e-3)


def test_replacing_a_constraint_block_rebuilds_the_assembly():
    s = scenes.pendulum()
    s.step(1e-3)
    wire = s.constraints[0]
    s.constraints[0] = CircularWire(wire.particles, wire.center, wire.radius * 0.5)
    s.step(1e-3)  # the new (violated) wire is the one being enforced
    C, _ = s.constraint_residual()
    assert abs(C[0] - 0.5 * (np.sum((s.x[0] - wire.center[0]) ** 2) - (0.5 * wire.radius[0]) ** 2)
               ) < 1e-12
