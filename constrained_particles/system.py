"""The particle system: state arrays, terms, the derivative and the step."""

from __future__ import annotations

import copy
import math
import numbers
import os
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, NoReturn

import numpy as np
from numpy.typing import ArrayLike

from . import fused, parallel
from .constraints import Constraint
from .forces import Force
from .integrators import get_method
from .solver import SOLVER_METHODS, ConstraintSolver
from .terms import MAX_INDEX, ArgumentTypeError, Shape, Term, as_param_array


class SimulationDiverged(RuntimeError):
    """A step would have produced a non-finite or absurdly large state, or one that left its
    constraints by more than ``residual_limit``.

    The system keeps the state it had before the step.
    """

#: Linear solvers of an ``implicit_euler`` step (see :mod:`constrained_particles.implicit`).
IMPLICIT_SOLVERS = ("auto", "cg", "direct")
#: The multiplier solvers the fused compiled step runs.
_FUSED_SOLVERS = ("auto", "cg")

#: Shortest accepted time step (s): below it ``t + dt`` and ``1 / dt`` stop being meaningful.
MIN_DT = 1e-9
#: Most threads a system may be given (:attr:`ParticleSystem.threads`)
MAX_THREADS = 1024
_F64 = np.dtype(np.float64)  #: NumPy's float64 dtype (one object: compared by identity)


#: every system that has a step lock (see :func:`_fresh_locks_after_fork`)
_LOCKED: weakref.WeakSet[object] = weakref.WeakSet()


def _fresh_locks_after_fork() -> None:
    """In a child process just forked: a fresh step lock for every system. A child forked
    while a thread of its parent was inside a step inherits that lock held, by a thread the
    child does not have: without a fresh one the child could never step its copy. (The
    threads of threaded steps start again in the child by themselves:
    :mod:`constrained_particles.parallel`.)"""
    for system in list(_LOCKED):
        system.__dict__["_stepping"] = threading.Lock()


if hasattr(os, "register_at_fork"):  # (not on Windows, which does not fork)
    os.register_at_fork(after_in_child=_fresh_locks_after_fork)


def _flag(name: str, value: object) -> bool:
    """``value`` as a bool, TypeError naming ``name`` for anything else (``"no"`` is not False)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ArgumentTypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_dt(dt: float) -> float:
    """``dt`` (s) as a float in [MIN_DT, inf), TypeError or ValueError naming it otherwise."""
    if type(dt) is float and math.isfinite(dt) and dt >= MIN_DT:  # the usual case, quickly
        return dt
    if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, numbers.Real):
        raise ArgumentTypeError(f"dt must be a number of seconds, got {dt!r}")
    if not (np.isfinite(dt) and dt >= MIN_DT):
        raise ValueError(f"dt must be a finite number >= {MIN_DT:g} s, got {dt!r}")
    return float(dt)


def _finite_vectors(name: str, value: ArrayLike, shape: tuple[int, ...], limit: float
                    ) -> np.ndarray:
    arr = as_param_array(name, value, shape[0], width=2)
    if np.any(np.abs(arr) >= limit):
        raise ValueError(f"{name} must be within divergence_limit = {limit:g} in every "
                         f"coordinate, got {value!r}")
    return arr


def _busy() -> NoReturn:
    """RuntimeError for a step call on a system another thread is stepping."""
    raise RuntimeError("this ParticleSystem is being stepped by another thread: a system takes "
                       "one step call at a time (use one system per thread, or take turns with "
                       "a lock)")


class ParticleSystem:
    """A 2D constrained particle system (Witkin & Baraff).

    State is arrays: positions ``x`` (n, 2) in metres, velocities ``v`` (n, 2) in m/s, masses
    ``mass`` (n,) in kg and inverse masses ``inv_mass`` (0 for fixed particles), time ``t`` in
    seconds. Forces and constraints are vectorized blocks added with :meth:`add`.

    Parameters
    ----------
    solver
        how the multipliers are solved for:
        ``"auto"`` (default: each connected component of the constraint graph on its own,
        directly; a sparse Cholesky factorisation in a fill-reducing order for components of
        more than 8 rows, linear time on chains and trees of rods), ``"cg"`` (conjugate
        gradients, Jacobi preconditioner, warm start, for components of more than 8 rows) or
        ``"direct"`` (one sparse LU of the whole system).
    tol
        relative residual tolerance of the multiplier solve (default 1e-10).
    ks, kd
        constraint feedback gains in 1/s^2 and 1/s
        (docs/physics.md, "The constraint force"). The defaults pull drift back critically
        damped with a 0.1 s time constant.
    project
        if True, every step ends with a projection back onto ``C = 0``, ``J v = 0``.
    divergence_limit
        a step that produces a coordinate (m) or speed (m/s) above this, or a
        non-finite one, raises :class:`SimulationDiverged`.
    drift_correction
        ``method="implicit_euler"`` only: the fraction beta in [0, 1] of the
        constraint error C removed per step (its constraint rows ask ``J v = -(beta/h) C``).
    compliance
        ``method="implicit_euler"`` only: constraint softness c >= 0 in units of C per
        unit of lam (m/N for line wires and fixed points); 0 is a hard constraint, and a small
        value regularises redundant constraints. See :mod:`constrained_particles.implicit`.
    implicit_solver
        ``method="implicit_euler"`` only: ``"cg"`` (filtered preconditioned
        conjugate gradients, cost linear in the particle count), ``"direct"`` (sparse LU of the
        KKT system) or ``"auto"`` (default: CG from 1024 free coordinates up, where it is
        faster). Constraints CG cannot filter (rods between moving particles, compliance > 0)
        always take the direct solve. See :mod:`constrained_particles.implicit`.
    residual_limit
        a step whose new state leaves any constraint row by more than this many
        metres (its :meth:`~constrained_particles.Constraint.distance_error`: distance from the
        wire, from the pinned point, error of a rod's length) raises :class:`SimulationDiverged`
        and keeps the old state. Default ``inf`` (no check); the environments use 0.01 m.

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

    def __init__(self, *, solver: str = "auto", tol: float = 1e-10, ks: float = 100.0,
                 kd: float = 20.0, project: bool = False, divergence_limit: float = 1e6,
                 drift_correction: float = 1.0, compliance: float = 0.0,
                 residual_limit: float = np.inf, implicit_solver: str = "auto") -> None:
        if not isinstance(solver, str) or solver not in SOLVER_METHODS:
            raise ValueError(f"solver must be one of {SOLVER_METHODS}, got {solver!r}")
        self.solver = solver
        self.tol = float(as_param_array("tol", tol, 1, positive=True)[0])
        self.ks = float(as_param_array("ks", ks, 1, nonnegative=True)[0])
        self.kd = float(as_param_array("kd", kd, 1, nonnegative=True)[0])
        self.project_each_step = _flag("project", project)
        self.divergence_limit = float(as_param_array("divergence_limit", divergence_limit, 1,
                                                     positive=True)[0])
        self.drift_correction = float(as_param_array("drift_correction", drift_correction, 1,
                                                     nonnegative=True)[0])
        if self.drift_correction > 1:
            raise ValueError(f"drift_correction must be in [0, 1], got {drift_correction!r}")
        self.compliance = float(as_param_array("compliance", compliance, 1, nonnegative=True)[0])
        if not isinstance(implicit_solver, str) or implicit_solver not in IMPLICIT_SOLVERS:
            raise ValueError(f"implicit_solver must be one of {IMPLICIT_SOLVERS}, "
                             f"got {implicit_solver!r}")
        self.implicit_solver = implicit_solver
        if isinstance(residual_limit, (bool, np.bool_)) or not isinstance(residual_limit,
                                                                          numbers.Real):
            raise ArgumentTypeError(f"residual_limit must be a number of metres, "
                                    f"got {residual_limit!r}")
        if not residual_limit > 0:  # also False for NaN
            raise ValueError(f"residual_limit must be > 0 m (inf: no check), "
                             f"got {residual_limit!r}")
        self.residual_limit = float(residual_limit)
        self.x = np.zeros((0, 2))
        self.v = np.zeros((0, 2))
        self.mass = np.zeros(0)
        self.inv_mass = np.zeros(0)
        self.t = 0.0
        self.forces: list[Force] = []
        self.constraints: list[Constraint] = []
        self._solver: ConstraintSolver | None = None

    # ------------------------------------------------------------------ threads
    @property
    def threads(self) -> int:
        """Threads a compiled step may use (default 1). With k > 1 the particles are cut into
        up to k ranges that no force element or constraint couples, each stepped on a thread
        of its own, with the same bits as on one thread (:mod:`constrained_particles.parallel`);
        a system that cannot be cut so (or is too small to gain) steps on one, and so does one
        whose steps the threads make slower (cores busy with other work: the ranges then run
        one after the other, as :class:`~constrained_particles.parallel.Gauge` finds by
        timing)."""
        return self.__dict__.get("_threads", 1)

    @threads.setter
    def threads(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ArgumentTypeError(f"threads must be a positive int, got {value!r}")
        if not 1 <= value <= MAX_THREADS:
            raise ValueError(f"threads must be in [1, {MAX_THREADS}], got {value!r}")
        with self.stepping():  # (a step on another thread is using the ranges' threads)
            self.__dict__["_threads"] = int(value)
            self._drop_partition()

    def thread_ranges(self) -> parallel.Partition | None:
        """The ranges this system's threaded steps cut it into
        (:class:`~constrained_particles.parallel.Partition`: ``spans`` of particles, ``packs``,
        and :meth:`~constrained_particles.parallel.Partition.map` to run per-range work on
        their threads), while they describe the system as it is; None when the system is
        stepped whole (one thread, nothing to cut, or not yet stepped since a change)."""
        held = self.__dict__.get("_partition")
        if held is None or not held.valid or self.threads < 2:
            return None
        return held if held.parent is self.__dict__.get("_packed") and held.parent.current(
            self) else None

    def close_threads(self) -> None:
        """Stop the threads of a threaded step (:attr:`threads`); the next step starts them
        again. RuntimeError if another thread is stepping the system."""
        with self.stepping():
            self._drop_partition()

    def _drop_partition(self) -> None:
        self.__dict__.pop("_whole_for", None)
        held = self.__dict__.pop("_partition", None)
        if held is not None:
            held.close()

    # ------------------------------------------------------------------ building
    @property
    def n(self) -> int:
        """Number of particles."""
        return len(self.x)

    @property
    def fixed(self) -> np.ndarray:
        """Boolean mask of immovable particles (n,)."""
        return self.inv_mass == 0

    def add_particle(self, position: ArrayLike, velocity: ArrayLike = (0.0, 0.0), mass: float = 1.0,
                     fixed: bool = False) -> int:
        """Add one particle at ``position`` (m) with ``velocity`` (m/s) and ``mass`` (kg).

        A ``fixed`` particle never moves (inverse mass 0, velocity 0). Returns its index.
        """
        return int(self.add_particles([position], [velocity], mass, fixed)[0])

    def add_particles(self, positions: ArrayLike, velocities: ArrayLike | None = None,
                      mass: ArrayLike = 1.0,
                      fixed: ArrayLike = False) -> np.ndarray:
        """Add k particles at once; ``positions`` (k, 2) m, ``velocities`` (k, 2) m/s (default 0),
        ``mass`` scalar or (k,) kg, ``fixed`` scalar or (k,) bool. Returns their indices."""
        try:
            shape = np.shape(positions)
        except ValueError:  # ragged nesting
            shape = ("ragged",)
        if len(shape) != 2 or shape[1] != 2:
            raise ValueError(f"positions must have shape (k, 2), got {shape}")
        k = shape[0]
        if self.n + k > MAX_INDEX:
            raise ValueError(f"positions: {self.n + k} particles would exceed {MAX_INDEX}")
        limit = self.divergence_limit
        pos = _finite_vectors("position", positions, (k, 2), limit)
        vel = (np.zeros((k, 2)) if velocities is None
               else _finite_vectors("velocity", velocities, (k, 2), limit))
        m = as_param_array("mass", mass, k, positive=True)
        with np.errstate(over="ignore", divide="ignore"):
            inv = 1.0 / m
        if not (np.all(np.isfinite(inv)) and np.all(inv > 0)):
            raise ValueError(f"mass must be a normal positive number of kg (1/mass finite and "
                             f"> 0), got {mass!r}")
        try:
            flags = np.asarray(fixed)
        except ValueError:
            flags = np.asarray(None)
        if flags.dtype != bool:
            raise ArgumentTypeError(f"fixed must be True/False or an array of bools, got {fixed!r}")
        try:
            fix = np.broadcast_to(flags, (k,))
        except ValueError:
            raise ValueError(f"fixed must broadcast to shape ({k},), got shape "
                             f"{flags.shape}") from None
        vel[fix] = 0.0
        start = self.n
        self.x = np.concatenate([self.x, pos])
        self.v = np.concatenate([self.v, vel])
        self.mass = np.concatenate([self.mass, m])
        self.inv_mass = np.concatenate([self.inv_mass, np.where(fix, 0.0, inv)])
        self._solver = None
        for term in [*self.forces, *self.constraints]:
            term._bound_n = self.n
        return np.arange(start, start + k)

    def add(self, *terms: Term) -> None:
        """Add force and constraint blocks; each is validated against this system first.

        On an error (TypeError or ValueError) neither the system nor the blocks change.
        """
        present = {id(t) for t in [*self.forces, *self.constraints]}
        for k, term in enumerate(terms):
            if not isinstance(term, (Force, Constraint)):
                raise ArgumentTypeError(f"terms must be Force or Constraint blocks, got {term!r}")
            if id(term) in present or any(term is other for other in terms[:k]):
                raise ValueError(f"terms: {term!r} is already in this system (add it once)")
        saved = [dict(term.__dict__) for term in terms]
        try:
            for term in terms:
                term.bind(self)
        except Exception:
            for term, before in zip(terms, saved, strict=True):
                term.__dict__.clear()
                term.__dict__.update(before)
            raise
        for term in terms:
            (self.forces if isinstance(term, Force) else self.constraints).append(term)
            if isinstance(term, Constraint):
                self._solver = None

    def remove(self, *terms: Term) -> None:
        """Remove previously added blocks; if any is not in this system (or is named twice),
        ValueError and nothing is removed."""
        for k, term in enumerate(terms):
            target = self.forces if isinstance(term, Force) else self.constraints
            if not any(existing is term for existing in target):
                raise ValueError(f"terms: {term!r} is not in this system")
            if any(term is other for other in terms[:k]):
                raise ValueError(f"terms: {term!r} is named twice")
        for term in terms:
            if isinstance(term, Force):
                self.forces = [f for f in self.forces if f is not term]
            else:
                self.constraints = [c for c in self.constraints if c is not term]
                self._solver = None

    @property
    def constraint_solver(self) -> ConstraintSolver:
        """The sparse assembly for the current topology: rebuilt when particles or constraint
        blocks are added, removed or replaced, or when ``solver`` or ``tol`` is changed."""
        built = self._solver
        # (terms compare by identity: the list comparison asks whether they are the same)
        if (built is None or built.n != self.n or built.method != self.solver
                or built.tol != self.tol or built.constraints != self.constraints):
            if self.solver not in SOLVER_METHODS:
                raise ValueError(f"solver must be one of {SOLVER_METHODS}, got {self.solver!r}")
            self._solver = ConstraintSolver(self.constraints, self.n, self.solver, self.tol)
        return self._solver

    def tile(self, copies: int) -> ParticleSystem:
        """``copies`` disconnected copies of this system as one system (block-diagonal J).

        Copy ``c`` owns particles ``c * n .. (c + 1) * n - 1``. Used for batched environments.
        """
        if isinstance(copies, (bool, np.bool_)) or not isinstance(copies, numbers.Integral):
            raise ArgumentTypeError(f"copies must be an integer, got {copies!r}")
        if not 1 <= copies <= MAX_INDEX // max(self.n, 1):
            raise ValueError(f"copies must be in [1, {MAX_INDEX // max(self.n, 1)}] "
                             f"(at most {MAX_INDEX} particles in all), got {copies!r}")
        copies = int(copies)
        out = copy.copy(self)
        out.x = np.tile(self.x, (copies, 1))
        out.v = np.tile(self.v, (copies, 1))
        out.mass = np.tile(self.mass, copies)
        out.inv_mass = np.tile(self.inv_mass, copies)
        out.forces = [f.tiled(copies, self.n) for f in self.forces]
        out.constraints = [c.tiled(copies, self.n) for c in self.constraints]
        for term in [*out.forces, *out.constraints]:
            term._bound_n = out.n
        out._solver = None
        out.__dict__.pop("_packed", None)
        out.__dict__.pop("_fresh_pack", None)
        out.__dict__.pop("_partition", None)  # (threads of its own, on first use)
        out.__dict__.pop("_whole_for", None)
        out.__dict__.pop("_stepping", None)
        return out

    def __getstate__(self) -> dict[str, object]:
        # the compiled pack holds views of the blocks' arrays: rebuilt, never copied; a copy
        # gets its own step lock (made on first use)
        state = self.__dict__.copy()
        state.pop("_packed", None)
        state.pop("_fresh_pack", None)
        state.pop("_stepping", None)
        state.pop("_partition", None)
        state.pop("_whole_for", None)
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
        # a NaN or inf anywhere makes a sum non-finite; a stage state can be non-finite while
        # the forces are not (gravity), and the constraint solve must not see it
        if not np.isfinite(Q.sum() + x.sum() + v.sum()):
            raise SimulationDiverged("a stage's state or applied forces became non-finite")
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
        (:mod:`constrained_particles.fused`) for ``euler``, ``midpoint``, ``rk4``,
        ``symplectic_euler`` and ``rattle`` with the ``"auto"`` (default) or ``"cg"`` solver;
        everything else, and ``CPARTICLES_NUMBA=0``, takes the reference path. Both compute the
        same formulas.

        A call reads each state attribute (``x``, ``v``, ``mass``, ``inv_mass``, ``t``) once and
        steps from what it read, so another thread replacing one meanwhile cannot make it read
        foreign memory. One system takes one step call at a time: a call made while another
        thread is stepping the same system raises RuntimeError (a clear error, not a wait: two
        threads stepping one system at once would each step from the same old state). Use one
        system per thread, or a lock of your own to take turns.
        """
        dt = check_dt(dt)
        if type(steps) is not int and (isinstance(steps, (bool, np.bool_))
                                       or not isinstance(steps, numbers.Integral)):
            raise ArgumentTypeError(f"steps must be an integer >= 1, got {steps!r}")
        if not 1 <= steps <= 10**9:
            raise ValueError(f"steps must be an integer in [1, 1e9], got {steps!r}")
        integrate = get_method(method)
        project = self.project_each_step if project is None else _flag("project", project)
        lock = self._step_lock()
        if not lock.acquire(blocking=False):  # (acquired last before the try: nothing runs
            _busy()  # between them that could leave it held)
        try:
            self._step(dt, integrate, method, int(steps), project)
        finally:
            lock.release()

    @contextmanager
    def stepping(self) -> Iterator[None]:
        """Hold this system's step lock for a block that steps it by other means (an
        environment's own compiled step, say): RuntimeError at once, as for :meth:`step`, if
        another thread is stepping the system. The fused kernels of one system share its
        pack's buffers, so a call into them from outside :meth:`step` belongs in this block."""
        lock = self._step_lock()
        if not lock.acquire(blocking=False):  # (acquired last before the try: nothing runs
            _busy()  # between them that could leave it held)
        try:
            yield
        finally:
            lock.release()

    def _step_lock(self) -> threading.Lock:
        """This system's step lock (not acquired: the caller acquires it without blocking,
        right before its ``try``, and calls :func:`_busy` if that fails)."""
        lock = self.__dict__.get("_stepping")
        if lock is None:
            lock = self.__dict__.setdefault("_stepping", threading.Lock())
            _LOCKED.add(self)  # (a forked child gives it a fresh one)
        return lock

    def _step(self, h: float, integrate: Any, method: str, steps: int, project: bool) -> None:
        """The body of :meth:`step` (arguments checked, the step lock held)."""
        x, v, mass, inv_mass, t = state = self.x, self.v, self.mass, self.inv_mass, self.t
        usual = self._check_state(*state)
        solver = self.constraint_solver
        project = bool(project and self.constraints)
        if self._fused_step(h, method, steps, project, solver=solver, state=state,
                            checked=usual):
            return
        lam = solver.lam.copy()
        try:
            with np.errstate(all="ignore"):
                for _ in range(int(steps)):
                    x, v = integrate(self, t, x, v, h)
                    self._check(x, v, residual=not project)
                    if project:
                        x, v = solver.project(x, v, np.repeat(self.inv_mass, 2))
                        self._check(x, v)
                    t = t + h
        except Exception:
            solver.lam = lam
            raise
        self.x, self.v, self.t = x, v, t

    def _fusable(self, method: str) -> bool:
        return (self.solver in _FUSED_SOLVERS and method in fused.METHOD_CODES
                and "acceleration" not in self.__dict__
                and type(self).acceleration is ParticleSystem.acceleration)

    def _fused_step(self, h: float, method: str, steps: int, project: bool,
                    pieces: np.ndarray | None = None,
                    solver: ConstraintSolver | None = None,
                    state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]
                    | None = None,
                    checked: bool = False) -> bool:
        """Take the steps on the fused kernel if it can (True); False, with nothing changed,
        if the reference path must. Raises SimulationDiverged, keeping the state. ``state``
        is ``(x, v, mass, inv_mass, t)`` as the caller read them (default: read here);
        ``checked``: :meth:`_check_state` returned True on that very ``state`` (ignored
        without one: a state read here is checked in full by ``fused.prepare``)."""
        if not self._fusable(method) or (project and steps > 1):
            return False
        if state is None:
            state = self.x, self.v, self.mass, self.inv_mass, self.t
            checked = False
        solver = self.constraint_solver if solver is None else solver
        lam = solver.lam.copy()
        # with projection, the residual is judged after it (as on the reference path)
        status, x, v, failed = fused.run(self, h, method, steps, solver.lam,
                                         math.inf if project else self.residual_limit, pieces,
                                         state[:4], checked)
        if status == fused.OK:
            try:
                if project:
                    with np.errstate(all="ignore"):
                        x, v = solver.project(x, v, np.repeat(self.inv_mass, 2))
                    self._check(x, v)
            except Exception:
                solver.lam = lam
                raise
            t = state[4] + h
            for _ in range(steps - 1):  # (t advances step by step, as on the reference path)
                t = t + h
            self.x, self.v, self.t = x, v, t
            return True
        solver.lam = lam
        if status == fused.DIVERGED:
            t = state[4]
            for _ in range(failed):
                t = t + h
            raise SimulationDiverged(
                f"step at t = {t:.6g} s produced a non-finite state, one beyond "
                f"divergence_limit = {self.divergence_limit:g} or one off the constraints "
                "by more than residual_limit; state kept as it was before the step")
        return False

    def step_pieces(self, dt: float, method: str, steps: int, pieces: np.ndarray) -> bool:
        """``steps`` steps of ``dt`` seconds in which particle q takes each step as
        ``pieces[q]`` equal steps (an (n,) int64 array >= 1; coupled particles must share a
        count), on the fused kernel; ``t`` advances by ``steps dt``. Returns False, with nothing
        changed, where the fused kernel cannot do it (the caller steps the groups itself, as
        envs.base.ParticleTask does); raises SimulationDiverged keeping the state.

        A group of coupled particles ends bit for bit where ``steps * k`` steps of ``dt / k`` of
        that group alone would leave it, so copies of a tiled system can each split their steps
        as they need without touching the others."""
        if not (isinstance(pieces, np.ndarray) and pieces.dtype == np.int64
                and pieces.shape == (self.n,) and pieces.min(initial=1) >= 1):
            raise ValueError(f"pieces must be an int64 array of shape ({self.n},) with entries "
                             f">= 1, got {pieces!r}")
        dt = check_dt(dt)
        if type(steps) is not int or not 1 <= steps <= 10**9:
            raise ValueError(f"steps must be an int in [1, 1e9], got {steps!r}")
        get_method(method)
        if method == "rattle" or self.project_each_step:
            self.check_arrays()
            return False
        lock = self._step_lock()
        if not lock.acquire(blocking=False):  # (acquired last before the try: nothing runs
            _busy()  # between them that could leave it held)
        try:
            state = self.x, self.v, self.mass, self.inv_mass, self.t
            usual = self._check_state(*state)
            return self._fused_step(float(dt), method, int(steps), False, pieces, state=state,
                                    checked=usual)
        finally:
            lock.release()

    def check_arrays(self) -> None:
        """ValueError unless the state arrays are consistent: ``x``, ``v`` float64 (n, 2),
        ``mass``, ``inv_mass`` float64 (n,), ``t`` a finite number. Run before every step, so a
        replaced array cannot send the compiled kernels outside their memory."""
        self._check_state(self.x, self.v, self.mass, self.inv_mass, self.t)

    @staticmethod
    def _check_state(x: object, v: object, mass: object, inv_mass: object, t: object) -> bool:
        """:meth:`check_arrays` of state arrays read once by the caller. True in the usual
        case: exact ndarrays (no subclass) of float64, ``x`` and ``v`` of one (n, 2) shape,
        ``mass`` and ``inv_mass`` of (n,), ``t`` a finite float; then ``fused.prepare`` checks
        only what this leaves open. False for any other valid state (``fused.prepare`` then
        checks everything); ValueError for an invalid one."""
        f64 = _F64  # (NumPy's float64 dtype is one object, tested first by identity; an
        # equal one, such as an unpickled array's, by comparison)
        if (type(x) is np.ndarray and type(v) is np.ndarray and type(mass) is np.ndarray
                and type(inv_mass) is np.ndarray
                and (x.dtype is f64 or x.dtype == f64) and (v.dtype is f64 or v.dtype == f64)
                and (mass.dtype is f64 or mass.dtype == f64)
                and (inv_mass.dtype is f64 or inv_mass.dtype == f64) and x.ndim == 2
                and x.shape[1] == 2 and v.shape == x.shape and mass.shape == inv_mass.shape
                == x.shape[:1] and type(t) is float and math.isfinite(t)):
            return True  # the usual case, in a few operations
        n = len(x) if isinstance(x, np.ndarray) and x.ndim else -1
        for name, arr, shape in (("x", x, (n, 2)), ("v", v, (n, 2)), ("mass", mass, (n,)),
                                 ("inv_mass", inv_mass, (n,))):
            if not (isinstance(arr, np.ndarray) and arr.dtype == np.float64
                    and arr.shape == shape):
                raise ValueError(f"{name} must be a float64 array of shape {shape} (x has "
                                 f"{n} rows), got {type(arr).__name__} "
                                 f"{getattr(arr, 'dtype', '')} {np.shape(arr)}")
        if not (isinstance(t, numbers.Real) and np.isfinite(t)):
            raise ValueError(f"t must be a finite number of seconds, got {t!r}")
        return False

    def distance_errors(self, x: np.ndarray | None = None) -> np.ndarray:
        """Every constraint row's geometric residual (m) at positions ``x`` (default: the
        current ones), in row order: see :meth:`Constraint.distance_error`."""
        x = self.x if x is None else x
        if not self.constraints:
            return np.zeros(0)
        return np.concatenate([c.distance_error(x) for c in self.constraints])

    def _check(self, x: np.ndarray, v: np.ndarray, residual: bool = True) -> None:
        limit = self.divergence_limit
        # max/min propagate NaN, and NaN < limit is False: one pass per bound, no temporaries
        if not (x.max(initial=0.0) < limit and -x.min(initial=0.0) < limit
                and v.max(initial=0.0) < limit and -v.min(initial=0.0) < limit):
            raise SimulationDiverged(
                f"step at t = {self.t:.6g} s produced a non-finite state or one beyond "
                f"divergence_limit = {limit:g}; state kept as it was before the step")
        if residual and self.constraints and self.residual_limit < np.inf:
            for c in self.constraints:
                err = c.distance_error(x)
                if not (err.max(initial=0.0) <= self.residual_limit):
                    raise SimulationDiverged(
                        f"step at t = {self.t:.6g} s left the constraints of "
                        f"{type(c).__name__} by {err.max():.3g} m > residual_limit = "
                        f"{self.residual_limit:g} m; state kept as it was before the step")

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
