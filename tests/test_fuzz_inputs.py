"""Bad input to the core library: a clear error naming the argument and an unchanged system.

Each kind of bad input has a test here, and hypothesis throws generated
bad values, shapes, types and indices at the public constructors and calls. The unchanged
system is checked by comparing a snapshot of its whole state (arrays, blocks and their arrays)
before and after the rejected call.
"""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

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
    scenes,
)
from constrained_particles.solver import InconsistentConstraints

BAD_ERRORS = (ValueError, TypeError)


def snapshot(s: ParticleSystem) -> bytes:
    """Everything a rejected call must leave alone, as bytes (pickle of the state and blocks)."""
    blocks = [(type(t).__name__, {k: v for k, v in vars(t).items()})
              for t in [*s.forces, *s.constraints]]
    return pickle.dumps((s.x, s.v, s.mass, s.inv_mass, s.t, blocks))


def rejected(s: ParticleSystem, call, name: str | None = None) -> str:
    """Assert ``call()`` raises ValueError/TypeError (naming ``name``) and leaves ``s`` alone."""
    before = snapshot(s)
    with pytest.raises(BAD_ERRORS) as info:
        call()
    assert snapshot(s) == before
    message = str(info.value)
    if name is not None:
        assert name in message, message
    return message


def spring_system() -> tuple[ParticleSystem, DampedSpring]:
    s = ParticleSystem()
    a = s.add_particle((0.0, 0.0))
    b = s.add_particle((1.0, 0.0))
    s.add_particle((0.0, 1.0))
    sp = DampedSpring(a, b, rest=0.5, ks=10.0)
    s.add(Gravity(), sp)
    return s, sp


# ---------------------------------------------------------------- item 2: memory safety
def test_index_arrays_are_read_only_and_replacements_validated():
    s, sp = spring_system()
    with pytest.raises(ValueError, match="read-only"):
        sp.j[0] = 10**6
    with pytest.raises(ValueError):
        sp.j.flags.writeable = True  # its base is read-only too
    rejected(s, lambda: setattr(sp, "j", [10**6]), "j holds unknown particle indices")
    rejected(s, lambda: setattr(sp, "i", np.array([True])), "i")
    sp.j = [2]  # a valid replacement is taken, and read-only again
    assert sp.j.tolist() == [2] and not sp.j.flags.writeable
    s.step(1e-3)
    assert np.all(np.isfinite(s.x))


def test_copies_and_pickles_keep_index_arrays_read_only():
    s, sp = spring_system()
    for other in (s.copy(), pickle.loads(pickle.dumps(s)), s.tile(3)):
        spring = other.forces[1]
        assert not spring.i.flags.writeable and not spring.j.flags.writeable
        with pytest.raises(ValueError):
            spring.j[0] = 10**6


def test_replaced_state_arrays_are_rejected_before_any_kernel_runs():
    s, sp = spring_system()
    before = snapshot(s)
    s.x = s.x[:1].copy()  # shorter than v, mass, inv_mass and the springs' indices
    with pytest.raises(ValueError, match=r"must be a float64 array of shape \(1, 2\)"):
        s.step(1e-3)
    s.x = np.zeros((3, 2), dtype=np.float32)
    with pytest.raises(ValueError, match="x must be a float64"):
        s.step(1e-3)
    s.x = pickle.loads(before)[0]
    s.step(1e-3)


def test_compiled_spring_kernel_never_reads_outside_its_arrays():
    s, sp = spring_system()
    x, v = s.x.copy(), s.v.copy()
    F = np.zeros_like(x)
    # mismatched parameter arrays or a too-short state: the guard refuses the compiled kernel
    # and the numpy path raises a Python error instead of reading foreign memory
    sp.__dict__["ks"] = np.zeros(0)
    with pytest.raises((ValueError, IndexError)):
        sp.accumulate(x, v, s.mass, F)
    sp.__dict__["ks"] = np.full(1, 10.0)
    with pytest.raises((ValueError, IndexError)):
        sp.accumulate(x[:1], v[:1], s.mass, F[:1])
    assert not sp._kernel_arguments_valid(x[:1], v[:1], F[:1])
    assert sp._kernel_arguments_valid(x, v, F)


def test_mouse_spring_changes_only_through_validated_calls():
    m = MouseSpring()
    s = ParticleSystem()
    s.add_particles(np.zeros((2, 2)) + [[0.0, 0.0], [1.0, 0.0]])
    s.add(m)
    with pytest.raises(ValueError):
        m.particle[0] = 5
    rejected(s, lambda: m.grab(0, []), "anchor")
    rejected(s, lambda: m.grab(np.inf, (0.0, 0.0)), "particle")
    rejected(s, lambda: m.grab(7, (0.0, 0.0)), "unknown particle")
    rejected(s, lambda: m.grab(True, (0.0, 0.0)), "particle")
    rejected(s, lambda: m.set([0], active=["yes"]), "active")
    rejected(s, lambda: m.set([3], active=[True]), "elements")
    rejected(s, lambda: setattr(m, "active", np.array([1.0])), "active")
    m.grab(1, (2.0, 0.0))
    assert int(m.particle[0]) == 1 and m.active[0]


# ---------------------------------------------------------------- item 3: atomic calls
def test_remove_checks_every_term_first():
    s, sp = spring_system()
    gravity = s.forces[0]
    rejected(s, lambda: s.remove(gravity, Drag()), "not in this system")
    rejected(s, lambda: s.remove(sp, sp), "twice")
    assert s.forces == [gravity, sp]


def test_add_checks_every_term_first_and_leaves_terms_unbound():
    s, sp = spring_system()
    fresh = DampedSpring(0, 2)  # rest is filled at bind
    rejected(s, lambda: s.add(fresh, Rod(0, 9)), "unknown particle")
    assert fresh.rest is None
    rejected(s, lambda: s.add(sp), "already")
    rejected(s, lambda: s.add(fresh, fresh), "already")
    rejected(s, lambda: s.add("spring"), "terms")


def test_add_particles_validates_everything_first():
    s, _ = spring_system()
    rejected(s, lambda: s.add_particle((0.0, 0.0), mass=1e-310), "mass")
    rejected(s, lambda: s.add_particle((0.0, 0.0), fixed="no"), "fixed")
    rejected(s, lambda: s.add_particle((0.0, 0.0), fixed=np.nan), "fixed")
    rejected(s, lambda: s.add_particle((1e300, 0.0)), "position")
    rejected(s, lambda: s.add_particles(np.zeros((2, 2)), fixed=[True, False, True]), "fixed")
    rejected(s, lambda: s.add_particles([[0.0, "a"]]), "position")


# ---------------------------------------------------------------- items 4 and 5: one error type
def test_steps_with_bad_arguments():
    s = scenes.wire_mixture()
    rejected(s, lambda: s.step(1e-200, "implicit_euler"), "dt")
    rejected(s, lambda: s.step(1e-310), "dt")
    rejected(s, lambda: s.step(True), "dt")
    rejected(s, lambda: s.step(0.01, project="no"), "project")
    rejected(s, lambda: s.step(0.01, method="leapfrog"), "method")
    with pytest.raises(TypeError, match="project"):
        ParticleSystem(project="no")
    with pytest.raises(ValueError, match="residual_limit"):
        ParticleSystem(residual_limit=-1.0)


@pytest.mark.parametrize("copies", [np.inf, 5e16, 2.5, True, "3", 0, -1, 10**30])
def test_tile_with_impossible_counts(copies):
    s = scenes.wire_mixture()
    rejected(s, lambda: s.tile(copies), "copies")


def test_wall_normal_of_huge_components_stays_a_unit_vector():
    w = Wall((1e200, 0.0))
    np.testing.assert_allclose(w.normal, (1.0, 0.0))
    w = Wall((1e308, 1e308))
    np.testing.assert_allclose(w.normal, (np.sqrt(0.5), np.sqrt(0.5)))


@pytest.mark.parametrize("make", [
    lambda: Wall(particles=np.array([True, False])),
    lambda: Gravity(particles=[True]),
    lambda: DampedSpring(np.array([True]), 1),
    lambda: Rod(0, False),
    lambda: DampedSpring(0, 1, ks=True),
])
def test_booleans_are_not_indices_or_numbers(make):
    with pytest.raises(TypeError):
        make()


def test_contradicting_wires_name_both_blocks_with_either_solver():
    for solver in ("cg", "direct"):
        s = ParticleSystem(solver=solver)
        p = s.add_particle((0.0, 0.0))
        s.add(Gravity(), HorizontalWire(p, 0.0), HorizontalWire(p, 0.1))
        before = snapshot(s)
        with pytest.raises(InconsistentConstraints,
                           match=r"constraints\[0\] HorizontalWire.*constraints\[1\] "
                                 "HorizontalWire"):
            s.step(0.01)
        assert snapshot(s) == before
        assert np.all(np.abs(s.constraint_solver.lam) < 1e3)


def test_redundant_but_consistent_constraints_still_solve():
    s = ParticleSystem(solver="cg")
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0))
    s.add(Gravity(), Rod(o, a), Rod(o, a))
    for _ in range(10):
        s.step(1e-3)
    assert abs(np.linalg.norm(s.x[a]) - 1.0) < 1e-6


# ---------------------------------------------------------------- item 1: residual check
def test_distance_error_of_every_block_by_hand():
    x = np.array([[0.0, 1.5], [3.0, 4.0], [2.0, -0.25]])
    cases = [
        (CircularWire(0, center=(0.0, 0.0), radius=1.0), [0.5]),
        (Rod(0, 1, length=2.0), [np.hypot(3.0, 2.5) - 2.0]),
        (HorizontalWire(2, height=0.5), [0.75]),
        (LineWire(1, direction=(1.0, 1.0), point=(0.0, 0.0)), [1.0 / np.sqrt(2.0)]),
        (FixedPoint(2, point=(1.0, 0.0)), [1.0, 0.25]),
    ]
    for block, expected in cases:
        np.testing.assert_allclose(block.distance_error(x), expected, rtol=1e-12)


def test_step_leaving_the_constraints_raises_and_keeps_the_state():
    s = scenes.wire_mixture(omega=40.0)
    s.residual_limit = 1e-3
    before = snapshot(s)
    lam = s.constraint_solver.lam.copy()
    with pytest.raises(SimulationDiverged, match="residual_limit"):
        s.step(0.1, "euler")  # 4 rad of crank turn in one Euler step
    assert snapshot(s) == before
    np.testing.assert_array_equal(s.constraint_solver.lam, lam)
    s.step(1e-4, "rk4")  # a small step is fine
    assert s.distance_errors().max() < 1e-3


# ---------------------------------------------------------------- generated bad input
BAD_VALUES = st.sampled_from([
    np.nan, np.inf, -np.inf, 1e300, -1e300, 1e-310, -1.0, 0.0, 2.5, True, False, "no", None,
    [], [[1.0, 2.0], [3.0]], np.array([True, False]), 10**30, 1j, object(), (1.0, 2.0, 3.0),
    np.zeros((2, 2, 2)), -(2**63),
])

CONSTRUCTORS = {
    "Gravity": (Gravity, {"g": (0.0, -9.81), "particles": [0, 1]}),
    "ConstantForce": (ConstantForce, {"particles": [0], "force": (1.0, 0.0)}),
    "DampedSpring": (DampedSpring, {"i": 0, "j": 1, "rest": 0.5, "ks": 10.0, "kd": 0.1}),
    "AngularSpring": (AngularSpring, {"a": 0, "b": 1, "c": 2, "rest": 0.3, "k": 1.0,
                                      "kd": 0.0}),
    "Drag": (Drag, {"kd": 0.1, "particles": [1]}),
    "Wall": (Wall, {"normal": (1.0, 0.0), "offset": 2.0, "kw": 100.0, "cw": 1.0,
                    "particles": [0, 2]}),
    "MouseSpring": (MouseSpring, {"particle": 1, "anchor": (0.0, 0.0), "ks": 5.0, "kd": 0.1}),
    "CircularWire": (CircularWire, {"particles": 1, "center": (0.0, 0.0), "radius": 1.0}),
    "Rod": (Rod, {"a": 0, "b": 2, "length": 1.0}),
    "LineWire": (LineWire, {"particles": 1, "direction": (1.0, 0.0), "point": (1.0, 0.0)}),
    "HorizontalWire": (HorizontalWire, {"particles": 2, "height": 1.0}),
    "FixedPoint": (FixedPoint, {"particles": 0, "point": (0.0, 0.0)}),
}
ARGUMENTS = [(name, arg) for name, (_, kw) in CONSTRUCTORS.items() for arg in kw]


def three_particles() -> ParticleSystem:
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    return s


@given(case=st.sampled_from(ARGUMENTS), value=BAD_VALUES)
def test_generated_bad_constructor_arguments(case, value):
    """Either a ValueError/TypeError naming the argument, or a block that adds and steps like
    any other (finite state or SimulationDiverged, never another exception or a crash)."""
    name, arg = case
    cls, kw = CONSTRUCTORS[name]
    try:
        block = cls(**{**kw, arg: copy.deepcopy(value)})
    except BAD_ERRORS as exc:
        assert arg in str(exc) or "must differ" in str(exc), (arg, str(exc))
        return
    s = three_particles()
    try:
        s.add(block)
    except BAD_ERRORS:
        assert s.forces == [] and s.constraints == []
        return
    before = snapshot(s)
    try:
        s.step(1e-3)
    except (SimulationDiverged, ValueError) as exc:
        # diverged, contradicting rows (InconsistentConstraints) or a degenerate geometry such
        # as a particle on its wire's centre: a named error, and the step did not happen
        assert isinstance(exc, SimulationDiverged) or "constraint" in str(exc), str(exc)
        assert snapshot(s) == before
        return
    assert np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.v))


@given(arg=st.sampled_from(["positions", "velocities", "mass", "fixed"]), value=BAD_VALUES)
def test_generated_bad_particles(arg, value):
    s, _ = spring_system()
    kw = {"positions": [[0.5, 0.5], [1.0, 1.0]], "velocities": None, "mass": 1.0,
          "fixed": False}
    before = snapshot(s)
    try:
        s.add_particles(**{**kw, arg: copy.deepcopy(value)})
    except BAD_ERRORS as exc:
        assert snapshot(s) == before
        message = str(exc)
        names = {"positions": "position", "velocities": "velocit", "mass": "mass",
                 "fixed": "fixed"}
        assert names[arg] in message, message
        return
    assert s.n == 5 and np.all(np.isfinite(s.x)) and np.all(s.mass > 0)
    assert np.all(np.isfinite(s.inv_mass))


@given(dt=BAD_VALUES, method=st.sampled_from(["rk4", "euler", "implicit_euler", "bogus", None]),
       project=st.sampled_from([None, True, False, "no", 1, np.nan]))
def test_generated_bad_steps(dt, method, project):
    s = scenes.wire_mixture()
    before = snapshot(s)
    try:
        s.step(dt, method, project)
    except BAD_ERRORS:
        assert snapshot(s) == before
        return
    except SimulationDiverged:
        assert snapshot(s) == before
        return
    assert np.all(np.isfinite(s.x))


@given(value=BAD_VALUES, field=st.sampled_from(["i", "j"]))
def test_generated_index_replacements_on_a_bound_spring(value, field):
    s, sp = spring_system()
    try:
        setattr(sp, field, copy.deepcopy(value))
    except BAD_ERRORS:
        s.step(1e-3)  # still the old, valid block
        return
    # accepted: then it is a valid index array for this system
    s.step(1e-3)
    assert np.all((getattr(sp, field) >= 0) & (getattr(sp, field) < s.n))
