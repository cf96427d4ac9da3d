"""RATTLE: velocity Verlet with the constraints solved at the position and velocity level.

One step of size h from (x0, v0) (Andersen 1983; Leimkuhler & Skeel 1994; Hairer, Lubich &
Wanner, *Geometric Numerical Integration*, VII.1), with ``W = M^-1`` and ``f`` the applied
forces::

    v_half = v0 + h/2 W (f(x0) + J(x0)^T lam)       lam such that C(x1) = 0
    x1     = x0 + h v_half
    v1     = v_half + h/2 W (f(x1) + J(x1)^T mu)     mu such that J(x1) v1 = 0

The position-level equations ``C(x0 + h v_half) = 0`` are nonlinear in lam (except for line
wires and fixed points). They are solved by Newton iterations: each one refills ``C`` and ``J``
at the current x1, solves ``J(x1) W J(x1)^T dlam = C(x1)`` with the constraint solver (the same
CG or sparse direct solve as the explicit methods) and moves x1 by ``-W J(x0)^T dlam``, the
direction the constraint force of the step has. The matrix is ``J(x1) W J(x1)^T`` instead of
the exact ``J(x1) W J(x0)^T``, so the iteration converges linearly, gaining a factor of about
``h |v| / L`` per iteration (L the constraint's length scale: radius, rod length); at
h = 2 ms that is 2-4 solves per step from the unconstrained prediction to roundoff (measured:
2.4 on the pendulum released at 2 rad, 3.5 on the slider-crank), plus one for the velocities.
Each connected component of the constraint graph (rows sharing a coordinate) stops once every
row of it is within :data:`POSITION_TOL` times the component's size (the largest coordinate of
its particles, m) of its constraint, as a distance ``|C_r| / |J_r|`` in metres, or
once its residual stops falling at most :data:`STALL_TOL` times its size (its roundoff floor);
a component that stops takes no further corrections, so tiled copies iterate as they would
alone. :class:`RattleSolveError` names the rows that do not get there in
:data:`MAX_ITERATIONS` iterations (too large a step).

Properties (measured in tests/test_rattle.py and the verification report):

- order 2; time-reversible and symplectic for forces that depend on positions only (springs
  without damping, gravity, angular springs, undamped walls), whatever the constraints, so the
  energy error stays bounded, O(h^2), with no secular drift over long runs;
- ``C = 0`` after every step to roundoff, and ``J v = 0`` to the solver's tolerance; the
  system's feedback gains ``ks``, ``kd`` play no part (there is no drift to pull back);
- velocity-dependent forces (spring and angular damping, drag, walls' dampers, the mouse
  spring's damping) are evaluated explicitly: the first half-kick at ``v0``, the second at the
  predicted ``2 v_half - v0 = v0 + h a`` (a first-order estimate of v1). This keeps the method
  second order for damped systems, but a damped step is neither symplectic nor reversible
  (damping is not), it removes energy at the rate the damping does plus an O(h^2) error, and it
  is stable only for ``c h < 2`` with ``c = kd/m`` the fastest damping rate (as symplectic
  Euler; ``implicit_euler`` has no such limit).

Stiff springs limit the step as for any explicit method (``w h < 2`` for the fastest mode).
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .integrators import METHODS, ORDERS, State
from .solver import ConstraintSolver
from .system import SimulationDiverged

if TYPE_CHECKING:
    from .system import ParticleSystem

#: Convergence of the position solve: every row within this fraction of its component's size
#: (the largest coordinate of its particles, m) of its constraint, as a distance ``|C_r| / |J_r|``.
POSITION_TOL = 1e-13
#: A component whose residual stops falling (less than halved by an iteration) is accepted at
#: its roundoff floor if every row is within this fraction of the component's size.
STALL_TOL = 1e-10
#: Newton iterations allowed per step before :class:`RattleSolveError`.
MAX_ITERATIONS = 50


class RattleSolveError(SimulationDiverged):
    """RATTLE's position-level constraint solve did not converge (usually: the step is too
    large for the motion). A subclass of :class:`~constrained_particles.SimulationDiverged`:
    the system keeps the state it had before the step."""


def _rows_of_blocks(solver: ConstraintSolver, rows: np.ndarray) -> str:
    """``"rows [3, 7] (Rod, CircularWire)"`` for the constraint rows ``rows``."""
    names = sorted({type(c).__name__ for c, s in zip(solver.constraints, solver.block_rows,
                                                     strict=True)
                    if np.any((rows >= s.start) & (rows < s.stop))})
    return f"rows {rows[:10].tolist()} ({', '.join(names)})"


def _kick(w: np.ndarray, f: np.ndarray, h: float) -> np.ndarray:
    """``h/2 W f`` (m/s) for forces f (n, 2) in newtons and inverse masses w (n,)."""
    out = (0.5 * h) * f
    out[:, 0] *= w  # per column: an (n, 1) broadcast is several times slower
    out[:, 1] *= w
    return out


def _applied(system: ParticleSystem, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    f = system.applied_forces(x, v)
    if not np.isfinite(f.sum()):  # a NaN or inf anywhere makes the sum non-finite
        raise SimulationDiverged("applied forces became non-finite")
    return f


def rattle(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float) -> State:
    """RATTLE (constrained velocity Verlet), order 2, symplectic for conservative forces.

    See the module docstring for the scheme, its convergence test and what velocity-dependent
    forces cost. Raises :class:`RattleSolveError` (a :class:`SimulationDiverged`) naming the
    rows when the position-level solve does not converge, and the solver's ``ValueError`` for a
    row with a vanishing gradient (a rod whose ends coincide), like the explicit methods.
    """
    w = system.inv_mass
    v_half = v + _kick(w, _applied(system, x, v), h)
    x1 = x + h * v_half
    if system.constraints:
        solver = system.constraint_solver
        x1, v_half = _position_solve(solver, np.repeat(w, 2), x, v, x1, v_half, h, t)
    # velocity-dependent forces see the predicted v1 = v0 + h a (module docstring)
    u = v_half + _kick(w, _applied(system, x1, 2.0 * v_half - v), h)
    if not system.constraints:
        return x1, u
    # J(x1) is current: the position solve ended with a refill at x1. mu: J(x1) v1 = 0.
    w2 = np.repeat(w, 2)
    nu = solver._solve(solver.J_times(u.ravel()), w2, None)
    return x1, u - (w2 * solver.JT_times(nu)).reshape(u.shape)


#: Constraint-graph components (rows sharing a coordinate) of each solver's pattern, by row.
_COMPONENTS: weakref.WeakKeyDictionary[ConstraintSolver, np.ndarray] = (
    weakref.WeakKeyDictionary())


def _components(solver: ConstraintSolver) -> np.ndarray:
    """The connected component of every constraint row (rows sharing a coordinate are
    connected), computed once per solver: its pattern is fixed."""
    labels = _COMPONENTS.get(solver)
    if labels is None:
        J = solver.J
        S = sp.csr_matrix((np.ones(J.nnz), J.indices, J.indptr), shape=J.shape)
        labels = _COMPONENTS[solver] = connected_components(S @ S.T, directed=False)[1]
    return labels


def _position_solve(solver: ConstraintSolver, w2: np.ndarray, x: np.ndarray, v: np.ndarray,
                    x1: np.ndarray, v_half: np.ndarray, h: float, t: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Newton iterations on ``C(x1) = 0`` along ``W J(x0)^T``; returns the new (x1, v_half).

    Convergence is decided per connected component of the constraint graph, and a component
    that has converged takes no further corrections, so the copies of a tiled system iterate as
    they would alone (bit for bit where the solver solves components independently).
    """
    solver.refill(x, v)
    solver._diag(w2)  # a row with a vanishing gradient: the explicit methods' ValueError
    J0 = solver.J.data.copy()
    cols = solver.J.indices
    rows = np.repeat(np.arange(solver.m), np.diff(solver.J.indptr))
    labels = _components(solver)
    count = int(labels.max()) + 1
    shape, n2 = x.shape, x.size
    done = np.zeros(count, dtype=bool)
    previous = np.full(count, np.inf)
    for iteration in range(MAX_ITERATIONS + 1):
        solver.refill(x1, v_half)
        grad = np.sqrt(np.bincount(rows, solver.J.data**2, minlength=solver.m))
        distance = np.abs(solver.C) / grad
        worst, size = np.zeros(count), np.zeros(count)
        np.maximum.at(worst, labels, distance)  # NaN propagates
        np.maximum.at(size, labels[rows], np.abs(x1.ravel()[cols]))
        if not (np.all(np.isfinite(worst)) and np.all(np.isfinite(size))):
            bad = _rows_of_blocks(solver, np.flatnonzero(~(distance < np.inf)))
            raise RattleSolveError(
                f"rattle: the position solve at t = {t:.6g} s met a non-finite state or a "
                f"vanishing gradient in constraint {bad}; the state was kept")
        # converged, or stalled at the roundoff floor of this component's constraint evaluation
        done |= (worst <= POSITION_TOL * size) | ((worst > 0.5 * previous)
                                                  & (worst <= STALL_TOL * size))
        if done.all():
            return x1, v_half
        if iteration == MAX_ITERATIONS:
            break
        previous = worst
        dlam = solver._solve(np.where(done[labels], 0.0, solver.C), w2, None)
        dq = (w2 * np.bincount(cols, J0 * dlam[rows], minlength=n2)).reshape(shape)
        x1 = x1 - dq
        v_half = v_half - dq / h
    far = np.flatnonzero(~done[labels] & (distance > POSITION_TOL * size[labels]))
    raise RattleSolveError(
        f"rattle: the position solve at t = {t:.6g} s did not converge in {MAX_ITERATIONS} "
        f"iterations: constraint {_rows_of_blocks(solver, far)} are still up to "
        f"{distance[far].max():.3g} m off (tolerance {POSITION_TOL:g} times the size of their "
        "component); a smaller step helps. The state was kept")


METHODS["rattle"] = rattle
ORDERS["rattle"] = 2
