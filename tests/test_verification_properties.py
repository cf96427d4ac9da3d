"""The verification properties on hypothesis-generated constrained systems.

Each property returns a measured figure; the bounds are the solver tolerance or rounding. The
last tests break the simulator on purpose and check that the properties notice.
"""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from constrained_particles import AngularSpring, DampedSpring, ParticleSystem, Rod, scenes
from verification import properties as P
from verification.strategies import random_system, systems


# ------------------------------------------------------------------ the strategy itself
@given(systems())
def test_generated_systems_start_consistent_and_well_posed(s):
    assert 2 <= s.n <= 12
    gaps = np.linalg.norm(s.x[:, None] - s.x[None, :], axis=2) + np.eye(s.n) * 1e9
    assert gaps.min() >= 0.6 - 1e-12  # well separated
    C, Cdot = s.constraint_residual()
    assert np.max(np.abs(C), initial=0.0) < 1e-12
    assert np.max(np.abs(Cdot), initial=0.0) < 1e-9
    if s.constraints:
        solver = s.constraint_solver
        J = solver.J.toarray()
        rows = (J != 0).reshape(solver.m, s.n, 2).any(axis=2).sum(axis=0)
        assert np.all(rows[s.inv_mass > 0] <= 2)  # never more rows than coordinates
        w2 = np.repeat(s.inv_mass, 2)
        assert np.linalg.cond((J * w2) @ J.T) < 1e6  # J W J^T comfortably invertible


def test_random_system_is_reproducible():
    a, b = random_system(123), random_system(123)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)
    assert repr(a) == repr(b)


# ------------------------------------------------------------------ the properties
@given(systems())
def test_constraint_residual_after_solve(s):
    assert P.constraint_acceleration_residual(s) < 1e-8


@given(systems())
def test_constraint_forces_do_no_work(s):
    assert P.constraint_power(s) < 1e-8


@given(systems(damped=True))
def test_conservative_forces_are_gradients(s):
    assert P.gradient_error(s) < 1e-6


@given(systems(damped=True))
def test_internal_forces_conserve_momentum(s):
    assert P.internal_momentum_error(s) < 1e-12


@given(systems(gravity=False))
def test_undamped_system_keeps_its_energy(s):
    assume(s.kinetic_energy() > 1e-3)
    assert P.energy_drift(s, "rk4", h=1e-3, duration=0.1) < 1e-7


@settings(max_examples=6)
@given(systems(gravity=False, max_particles=6, solver="direct"))
def test_rk4_energy_error_has_no_low_order_term(s):
    # the direct solver: CG's 1e-10 tolerance would put a floor under the energy error.
    # Between any two steps max_t |E(t) - E(0)| can dip on random systems (local slopes such
    # as 5.8, 5.9, 2.3, 3.5 for h = 10 ... 0.625 ms), so the slope is a least-squares fit over
    # an 8x range of h, using only errors above round-off (about 1e-15 J): over 77 seeded
    # systems, min 3.60 (64 systems usable) with a 1e-14 J cut. A 1e-12 J cut kept only the
    # three coarsest steps of systems whose errors dip there, e.g. 5.5e-11, 1.2e-11, 1.1e-12 J
    # (slope 2.81, while the fourth step's 1e-13 J restores the trend).
    hs = (0.005, 0.0025, 0.00125, 0.000625)
    errors = P.energy_errors(s, "rk4", hs, duration=0.3)
    usable = [(h, e) for h, e in zip(hs, errors, strict=True) if e > 1e-14]
    # the system has forces that do work, measurably: errors that stay within a few times
    # round-off at every step (1.0e-14 to 1.4e-14 J on a spring between a line wire and a
    # fixed point) have no slope to fit
    assume(len(usable) >= 3 and max(errors) > 1e-12)
    assert P.fit_slope(*zip(*usable, strict=True)) > 3.0


@pytest.mark.parametrize("build", [scenes.pendulum, scenes.wire_mixture,
                                   lambda: random_system(85, gravity=False, solver="direct")],
                         ids=["pendulum", "slider_crank", "random_system_85"])
def test_rk4_energy_error_falls_at_fourth_order(build):
    assert 3.6 < P.energy_error_order(build(), "rk4", hs=(0.04, 0.02, 0.01)) < 5.5


@settings(max_examples=10)
@given(systems(gravity=False))
def test_rattle_energy_error_is_bounded_and_second_order(s):
    # a symplectic method's energy error is h^2 times a bounded function of the state (the
    # modified energy): halving h divides it by 4 (3.9999-4.0003 over 39 seeded systems,
    # 4.08 for one whose errors are at 1e-11), and it stays small (at most 5.5e-5 of the
    # largest kinetic energy at h = 2 ms over 0.4 s on those systems)
    assume(s.kinetic_energy() > 1e-3)
    coarse = P.energy_drift(s, "rattle", h=2e-3, duration=0.4)
    fine = P.energy_drift(s, "rattle", h=1e-3, duration=0.4)
    assert coarse < 2e-4
    assume(fine > 1e-9)  # above round-off and the solver's tolerance
    assert 3.7 < coarse / fine < 4.3


@given(systems(), st.floats(-np.pi, np.pi), st.floats(-5, 5), st.floats(-5, 5))
def test_stepping_commutes_with_rigid_motions(s, angle, dx, dy):
    assert P.invariance_error(s, "rk4", h=1e-3, steps=10, angle=angle, shift=(dx, dy)) < 1e-9


@given(systems(damped=True),
       st.sampled_from(["euler", "midpoint", "rk4", "symplectic_euler", "rattle"]))
def test_bit_for_bit_determinism(s, method):
    assert P.determinism_error(s, method, h=1e-3, steps=10) == 0.0


def test_fit_slope_rejects_bad_errors():
    with pytest.raises(ValueError, match="errors"):
        P.fit_slope([0.1, 0.05], [1e-3, 0.0])


# ------------------------------------------------------------------ the checks have teeth
class _RodWithoutJdot(Rod):
    """A rod whose Jdot is wrongly zero (the velocity term of report eq. 2 is lost)."""

    def evaluate(self, x, v):
        C, Cdot, J, Jdot = super().evaluate(x, v)
        return C, Cdot, J, np.zeros_like(Jdot)


def test_residual_check_catches_a_wrong_jdot():
    s = ParticleSystem()
    o = s.add_particle((0.0, 0.0), fixed=True)
    a = s.add_particle((1.0, 0.0), velocity=(0.0, 2.0))
    s.add(_RodWithoutJdot(o, a))
    assert P.constraint_acceleration_residual(s) > 0.1


class _ReportAngularSpring(AngularSpring):
    """The report's angular spring: torque from the cosine of the angle (not a gradient)."""

    def accumulate(self, x, v, mass, F):
        ga, gb, gc = self.gradients(x)
        torque = -self.k * np.cos(self.angles(x))
        for idx, g in ((self.a, ga), (self.b, gb), (self.c, gc)):
            np.add.at(F, idx, torque[:, None] * g)


def test_gradient_check_catches_a_non_gradient_force():
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [1.0, 0.0], [1.5, 1.0]])
    s.add(_ReportAngularSpring(0, 1, 2, rest=2.0, k=1.0))
    assert P.gradient_error(s) > 0.1


class _OneSidedSpring(DampedSpring):
    """A spring that pushes only particle i (no reaction on j)."""

    def accumulate(self, x, v, mass, F):
        _, f = self.element_forces(x, v, mass)
        np.add.at(F, self.i, f)


def test_momentum_check_catches_a_missing_reaction():
    s = ParticleSystem()
    s.add_particles([[0.0, 0.0], [2.0, 0.0]])
    s.add(_OneSidedSpring(0, 1, rest=1.0, ks=5.0))
    assert P.internal_momentum_error(s) > 0.1


def test_invariance_check_catches_a_fixed_direction():
    s = scenes.spring_pair()
    s.add(scenes.Gravity((0.0, -9.81)))  # gravity not rotated with the system
    moved = P.rigidly_moved(s, 1.0, (0.0, 0.0))
    moved.forces[-1].g = np.array([0.0, -9.81])
    a, b = P.run(s, "rk4", 1e-2, 10), P.run(moved, "rk4", 1e-2, 10)
    R = np.array([[np.cos(1.0), -np.sin(1.0)], [np.sin(1.0), np.cos(1.0)]])
    assert np.max(np.abs(a.x @ R.T - b.x)) > 1e-3


# ------------------------------------------------------------------ coverage of a cloth
@settings(max_examples=25, deadline=None)
@given(size=st.sampled_from([5, 7, 9, 11]), pixels=st.sampled_from([128, 256]),
       angle=st.floats(-np.pi, np.pi), cx=st.floats(-1.0, 1.0), cy=st.floats(-1.0, 1.0))
def test_a_flat_cloth_covers_its_area_and_a_folded_one_half(size, pixels, angle, cx, cy):
    r = P.cloth_coverage(size=size, pixels=pixels, angle=angle, center=(cx, cy))
    assert r["flat"] == pytest.approx(1.0, abs=1e-9)
    assert 0.5 - 1e-9 <= r["folded"] <= 0.5 + r["bound"]


def test_the_folded_cloths_excess_falls_with_the_pixel_size():
    excess = [P.cloth_coverage(pixels=p)["folded"] - 0.5 for p in (64, 128, 256, 512)]
    bounds = [P.cloth_coverage(pixels=p)["bound"] for p in (64, 128, 256, 512)]
    assert all(0 <= e <= b for e, b in zip(excess, bounds, strict=True))
    # the boundary's pixels: the excess falls about as the pixel size (first order)
    slopes = np.diff(np.log(excess)) / np.log(0.5)
    assert np.all(slopes > 0.8) and np.all(slopes < 1.2), slopes


def test_cloth_coverage_refuses_an_even_size():
    with pytest.raises(ValueError, match="size"):
        P.cloth_coverage(size=8)
