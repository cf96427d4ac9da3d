"""The particle system: state arrays, terms, the derivative and the step."""

from __future__ import annotations

import copy
import math
import numbers
from typing import Any

import numpy as np

from . import fused
from .constraints import Constraint
from .forces import Force
from .integrators import get_method
from .solver import SOLVER_METHODS, ConstraintSolver
from .terms import Shape, Term, as_param_array


class SimulationDiverged(RuntimeError):
    """A step would have produced a non-finite (or absurdly large) state.

    The system keeps the state it had before the step.
    """


def _finite_vectors(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    try:
        arr = np.broadcast_to(arr, shape).astype(float)
    except ValueError:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}") from None
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return arr


class ParticleSystem:
    """A 2D constrained particle system (Witkin & Baraff).

    State is arrays: positions ``x`` (n, 2) in metres, velocities ``v`` (n, 2) in m/s, masses
    ``mass`` (n,) in kg and inverse masses ``inv_mass`` (0 for fixed particles), time ``t`` in
    seconds. Forces and constraints are vectorized blocks added with :meth:`add`.

    Parameters
    ----------
    solver : ``"cg"`` (conjugate gradients, Jacobi preconditioner, warm start) or ``"direct"``.
    tol : relative residual tolerance of the multiplier solve (default 1e-10).
    ks, kd : constraint feedback gains in 1/s^2 and 1/s (report eq. 2). The defaults pull drift
        back critically damped with a 0.1 s time constant.
    project : if True, every step ends with a projection back onto ``C = 0``, ``J v = 0``.
    divergence_limit : a step that produces a coordinate (m) or speed (m/s) above this, or a
        non-finite one, raises :class:`SimulationDiverged`.
    drift_correction : ``method="implicit_euler"`` only: the fraction beta in [0, 1] of the
        constraint error C removed per step (its constraint rows ask ``J v = -(beta/h) C``).
    compliance : ``method="implicit_euler"`` only: constraint softness c >= 0 in units of C per
        unit of lam (m/N for line wires and fixed points); 0 is a hard constraint, and a small
        value regularises redundant constraints. See :mod:`constrained_particles.implicit`.

    >>> from constrained_particles import ParticleSystem, Gravity, Rod
    >>> s = ParticleSystem()
    >>> o = s.add_particle((0.0, 0.0), fixed=True)
    >>> a = s.add_particle((1.0, 0.0), mass=0.5)
    >>> s.add(Gravity(), Rod(o, a))
    >>> for _ in range(100):
    ...     s.step(1e-3, method="rk4")
    >>> round(float(np.linalg.norm(s.x[a] - s.x[o])), 9)
    1.0
    """

    def __init__(self, *, solver: str = "cg", tol: float = 1e-10, ks: float = 100.0,
                 kd: float = 20.0, project: bool = False, divergence_limit: float = 1e6,
                 drift_correction: float = 1.0, compliance: float = 0.0) -> None:
        if solver not in SOLVER_METHODS:
            raise ValueError(f"solver must be one of {SOLVER_METHODS}, got {solver!r}")
        self.solver = solver
        self.tol = float(as_param_array("tol", tol, 1, positive=True)[0])
        self.ks = float(as_param_array("ks", ks, 1, nonnegative=True)[0])
        self.kd = float(as_param_array("kd", kd, 1, nonnegative=True)[0])
        self.project_each_step = bool(project)
        self.divergence_limit = float(as_param_array("divergence_limit", divergence_limit, 1,
                                                     positive=True)[0])
        self.drift_correction = float(as_param_array("drift_correction", drift_correction, 1,
                                                     nonnegative=True)[0])
        if self.drift_correction > 1:
            raise ValueError(f"drift_correction must be in [0, 1], got {drift_correction!r}")
        self.compliance = float(as_param_array("compliance", compliance, 1, nonnegative=True)[0])
        self.x = np.zeros((0, 2))
        self.v = np.zeros((0, 2))
        self.mass = np.zeros(0)
        self.inv_mass = np.zeros(0)
        self.t = 0.0
        self.forces: list[Force] = []
        self.constraints: list[Constraint] = []
        self._solver: ConstraintSolver | None = None

    # ------------------------------------------------------------------ building
    @property
    def n(self) -> int:
        """Number of particles."""
        return len(self.x)

    @property
    def fixed(self) -> np.ndarray:
        """Boolean mask of immovable particles (n,)."""
        return self.inv_mass == 0

    def add_particle(self, position: Any, velocity: Any = (0.0, 0.0), mass: float = 1.0,
                     fixed: bool = False) -> int:
        """Add one particle at ``position`` (m) with ``velocity`` (m/s) and ``mass`` (kg).

        A ``fixed`` particle never moves (inverse mass 0, velocity 0). Returns its index.
        """
        return int(self.add_particles([position], [velocity], mass, fixed)[0])

    def add_particles(self, positions: Any, velocities: Any = None, mass: Any = 1.0,
                      fixed: Any = False) -> np.ndarray:
        """Add k particles at once; ``positions`` (k, 2) m, ``velocities`` (k, 2) m/s (default 0),
        ``mass`` scalar or (k,) kg, ``fixed`` scalar or (k,) bool. Returns their indices."""
        pos = np.asarray(positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2:
            raise ValueError(f"positions must have shape (k, 2), got {pos.shape}")
        k = len(pos)
        pos = _finite_vectors("position", pos, (k, 2))
        vel = np.zeros((k, 2)) if velocities is None else _finite_vectors("velocity", velocities,
                                                                          (k, 2))
        m = as_param_array("mass", mass, k, positive=True)
        fix = np.broadcast_to(np.asarray(fixed, dtype=bool), (k,))
        vel[fix] = 0.0
        start = self.n
        self.x = np.concatenate([self.x, pos])
        self.v = np.concatenate([self.v, vel])
        self.mass = np.concatenate([self.mass, m])
        self.inv_mass = np.concatenate([self.inv_mass, np.where(fix, 0.0, 1.0 / m)])
        self._solver = None
        return np.arange(start, start + k)

    def add(self, *terms: Term) -> None:
        """Add force and constraint blocks; each is validated against this system first."""
        for term in terms:
            if not isinstance(term, (Force, Constraint)):
                raise ValueError(f"terms must be Force or Constraint blocks, got {term!r}")
            term.bind(self)
        for term in terms:
            (self.forces if isinstance(term, Force) else self.constraints).append(term)
            if isinstance(term, Constraint):
                self._solver = None

    def remove(self, *terms: Term) -> None:
        """Remove previously added blocks."""
        for term in terms:
            target = self.forces if isinstance(term, Force) else self.constraints
            for k, existing in enumerate(target):
                if existing is term:
                    del target[k]
                    break
            else:
                raise ValueError(f"terms: {term!r} is not in this system")
            if isinstance(term, Constraint):
                self._solver = None

    @property
    def constraint_solver(self) -> ConstraintSolver:
        """The sparse assembly for the current topology: rebuilt when particles or constraint
        blocks are added, removed or replaced, or when ``solver`` or ``tol`` is changed."""
        built = self._solver
        if (built is None or built.n != self.n or built.method != self.solver
                or built.tol != self.tol or len(built.constraints) != len(self.constraints)
                or any(a is not b for a, b in zip(built.constraints, self.constraints,
                                                  strict=True))):
            if self.solver not in SOLVER_METHODS:
                raise ValueError(f"solver must be one of {SOLVER_METHODS}, got {self.solver!r}")
            self._solver = ConstraintSolver(self.constraints, self.n, self.solver, self.tol)
        return self._solver

    def tile(self, copies: int) -> ParticleSystem:
        """``copies`` disconnected copies of this system as one system (block-diagonal J).

        Copy ``c`` owns particles ``c * n .. (c + 1) * n - 1``. Used for batched environments.
        """
        if int(copies) < 1:
            raise ValueError(f"copies must be >= 1, got {copies!r}")
        out = copy.copy(self)
        out.x = np.tile(self.x, (copies, 1))
        out.v = np.tile(self.v, (copies, 1))
        out.mass = np.tile(self.mass, copies)
        out.inv_mass = np.tile(self.inv_mass, copies)
        out.forces = [f.tiled(copies, self.n) for f in self.forces]
        out.constraints = [c.tiled(copies, self.n) for c in self.constraints]
        out._solver = None
        out.__dict__.pop("_packed", None)
        return out

    def __getstate__(self) -> dict[str, Any]:
        # the compiled pack holds views of the blocks' arrays: rebuilt, never copied
        state = self.__dict__.copy()
        state.pop("_packed", None)
        return state

    def copy(self) -> ParticleSystem:
        """A deep copy (state, terms and solver warm start)."""
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ dynamics
    def applied_forces(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Sum of every force block at (x, v): Q as an (n, 2) array in newtons."""
        Q = np.zeros_like(x)
        for f in self.forces:
            f.accumulate(x, v, self.mass, Q)
        return Q

    def acceleration(self, t: float, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The derivative's second half: ``qddot = W (Q + J^T lam)`` (m/s^2), shape (n, 2).

        A pure function of (t, x, v) apart from the solver's warm start.
        """
        Q = self.applied_forces(x, v)
        if not np.isfinite(Q.sum()):  # a NaN or inf anywhere makes the sum non-finite
            raise SimulationDiverged("applied forces became non-finite")
        if self.constraints:
            Q = Q + self.constraint_force(x, v, Q)
        Q[:, 0] *= self.inv_mass  # per column: an (n, 1) broadcast is several times slower
        Q[:, 1] *= self.inv_mass
        return Q

    def constraint_force(self, x: np.ndarray, v: np.ndarray, Q: np.ndarray | None = None
                         ) -> np.ndarray:
        """``J^T lam`` (N), shape (n, 2): the constraint force at (x, v) under applied forces Q."""
        if not self.constraints:
            return np.zeros_like(x)
        if Q is None:
            Q = self.applied_forces(x, v)
        solver = self.constraint_solver
        w2 = np.repeat(self.inv_mass, 2)
        lam = solver.multipliers(x, v, Q, w2, self.ks, self.kd)
        return solver.JT_times(lam).reshape(x.shape)

    def step(self, dt: float, method: str = "rk4", project: bool | None = None, *,
             steps: int = 1) -> None:
        """Advance ``x``, ``v`` and ``t`` by ``steps`` steps of ``dt`` seconds with ``method``.

        ``project`` (default: the system's setting) projects the result of every step back
        onto the constraints. Raises :class:`SimulationDiverged`, keeping the state from before
        the call, if a step would produce a non-finite state or one beyond
        ``divergence_limit``.

        Systems made of the standard blocks step through the fused compiled kernel
        (:mod:`constrained_particles.fused`) for ``euler``, ``midpoint``, ``rk4`` and
        ``symplectic_euler`` with the default ``"cg"`` solver; everything else, and
        ``CPARTICLES_NUMBA=0``, takes the reference path. Both compute the same formulas.
        """
        if not (isinstance(dt, numbers.Real) and not isinstance(dt, bool) and np.isfinite(dt)
                and dt > 0):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 1:
            raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
        integrate = get_method(method)
        project = self.project_each_step if project is None else project
        solver = self.constraint_solver
        lam = solver.lam.copy()
        h = float(dt)
        project = bool(project and self.constraints)
        if (self.solver == "cg" and method in fused.METHOD_CODES and (steps == 1 or not project)
                and "acceleration" not in self.__dict__
                and type(self).acceleration is ParticleSystem.acceleration):
            status, x, v, failed = fused.run(self, h, method, int(steps), solver.lam,
                                             getattr(self, "residual_limit", math.inf))
            if status == fused.OK:
                try:
                    if project:
                        with np.errstate(all="ignore"):
                            x, v = solver.project(x, v, np.repeat(self.inv_mass, 2))
                        self._check(x, v)
                except SimulationDiverged:
                    solver.lam[:] = lam
                    raise
                t = self.t
                for _ in range(int(steps)):
                    t = t + h
                self.x, self.v, self.t = x, v, t
                return
            solver.lam[:] = lam
            if status == fused.DIVERGED:
                t = self.t
                for _ in range(failed):
                    t = t + h
                raise SimulationDiverged(
                    f"step at t = {t:.6g} s produced a non-finite state, one beyond "
                    f"divergence_limit = {self.divergence_limit:g} or one off the constraints "
                    "by more than residual_limit; state kept as it was before the step")
        x, v, t = self.x, self.v, self.t
        try:
            with np.errstate(all="ignore"):
                for _ in range(int(steps)):
                    x, v = integrate(self, t, x, v, h)
                    self._check(x, v)
                    if project:
                        x, v = solver.project(x, v, np.repeat(self.inv_mass, 2))
                        self._check(x, v)
                    t = t + h
        except SimulationDiverged:
            solver.lam[:] = lam
            raise
        self.x, self.v, self.t = x, v, t

    def _check(self, x: np.ndarray, v: np.ndarray) -> None:
        limit = self.divergence_limit
        # max/min propagate NaN, and NaN < limit is False: one pass per bound, no temporaries
        if not (x.max(initial=0.0) < limit and -x.min(initial=0.0) < limit
                and v.max(initial=0.0) < limit and -v.min(initial=0.0) < limit):
            raise SimulationDiverged(
                f"step at t = {self.t:.6g} s produced a non-finite state or one beyond "
                f"divergence_limit = {limit:g}; state kept as it was before the step")

    def project(self) -> None:
        """Project the current state onto ``C = 0`` and ``J v = 0`` in place."""
        if self.constraints:
            self.x, self.v = self.constraint_solver.project(self.x, self.v,
                                                            np.repeat(self.inv_mass, 2))

    # ------------------------------------------------------------------ measurements
    def constraint_residual(self) -> tuple[np.ndarray, np.ndarray]:
        """``(C, Cdot)`` over every constraint row at the current state."""
        if not self.constraints:
            return np.zeros(0), np.zeros(0)
        solver = self.constraint_solver
        solver.refill(self.x, self.v)
        return solver.C.copy(), solver.Cdot.copy()

    def kinetic_energy(self) -> float:
        """``1/2 sum m |v|^2`` over movable particles, in joules."""
        movable = self.inv_mass > 0
        return float(0.5 * np.sum(self.mass[movable] * np.sum(self.v[movable] ** 2, axis=1)))

    def potential_energy(self) -> float:
        """Sum of every force block's potential (springs, gravity, angular, wall, mouse), J."""
        return float(sum(f.potential(self.x, self.mass) for f in self.forces))

    def energy(self) -> float:
        """Mechanical energy: kinetic plus potential, in joules."""
        return self.kinetic_energy() + self.potential_energy()

    def shapes(self, constraint_forces: bool = False) -> list[Shape]:
        """Drawable primitives of every term at the current state (world coordinates, m)."""
        out: list[Shape] = []
        for term in [*self.constraints, *self.forces]:
            out.extend(term.shapes(self.x, self.v))
        if constraint_forces and self.constraints:
            fc = self.constraint_force(self.x, self.v)
            moved = np.flatnonzero(np.any(fc != 0, axis=1))
            out.append(Shape("arrow", "constraint", self.x[moved], fc[moved],
                             np.linalg.norm(fc[moved], axis=1)))
        return out

    def __repr__(self) -> str:
        return (f"ParticleSystem(n={self.n}, forces={[type(f).__name__ for f in self.forces]}, "
                f"constraints={[type(c).__name__ for c in self.constraints]}, t={self.t:g})")
