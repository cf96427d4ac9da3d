"""Implicit integration for stiff systems: linearized backward Euler with constraints inside.

One step of size h from (x0, v0) follows Baraff & Witkin 1998 ("Large Steps in Cloth
Simulation"): the forces are linearized about the start of the step with the analytic Jacobians
``K = df/dx`` and ``D = df/dv`` of every force block, and the velocity change dv solves
``(M - h D - h^2 K) dv = h (f0 + h K v0) + J^T p``, with masses (M, not I). The constraints are
rows of the same linear system, not a filter applied afterwards (a KKT system as in Tournier
et al. 2015, "Stable Constrained Dynamics"): the new velocity must satisfy the velocity-level
condition ``J v1 = -(beta/h) C - (c/h^2) p``, where ``p = h lam`` is the constraint impulse,
``beta`` the system's ``drift_correction`` and ``c`` its ``compliance``. Over the free
coordinates (fixed particles, inverse mass 0, are eliminated and keep their velocity) the
solve is, with ``y = -p``::

    [ M - h D - h^2 K     J^T      ] [ dv ]   [ h (f0 + h K v0)      ]
    [ J                  -c/h^2 I  ] [ y  ] = [ -(beta/h) C - J v0   ]

Then ``v1 = v0 + dv`` and ``x1 = x0 + h v1``. ``J``, ``C`` are taken at x0, so a linear
constraint (a line wire, a fixed point) holds exactly after the step when ``beta = 1``; a curved
one (circular wire, rod) is left off by O(h^2 |v|^2) and pulled back in the next step.

The forces are linearized with the semi-definite Jacobians (``definite=True`` of
:meth:`~constrained_particles.forces.Force.jacobians`: no compressive transverse spring
stiffness, Gauss-Newton angular springs; Choi & Ko 2002). With the exact ones a compressed
cloth predicts buckling and the next large step overshoots: a stiff cloth yanked by a mouse
spring gains energy without bound, while with these its energy never rises. The method stays
order 1. The sparse structure (union of the force blocks' ``jacobian_pattern`` and the
constraint pattern) is built once per topology; each step refills the values and factorises
with SuperLU (``scipy.sparse.linalg.splu``).

Damping (measured; tests/test_implicit.py checks the first and third figures). A mode whose
restoring force goes through a force Jacobian keeps ``1/(1 + (w h)^2)`` of its energy per step
(w its angular frequency), about ``exp(-2 pi w h)`` per period when w h is small:

- two 0.5 kg particles on a 20 N/m spring (w = 8.94 rad/s) keep 39.7 % of their energy per
  period at h = 1/60 s, 62.8 % at 1/120 s and 79.1 % at 1/240 s, exactly the formula;
- a 1 m pendulum hanging from a stiff spring (its swing restored by the spring's tension/length
  transverse stiffness, w = 3.13 rad/s) keeps 70 % per swing at 1/60 s, 85 % at 1/120 s;
- motion driven by constant forces along constraints is *not* damped: the wire pendulum
  (``scenes.pendulum``) has no force Jacobian, the step reduces to symplectic Euler with
  velocity-level constraints, and it keeps its energy to 0.1 % per period at h = 1/60 s;
- the stretching modes of the issue-3 cloth (ks = 2000 N/m, 0.01 kg, w up to 1100 rad/s)
  lose over 99.6 % of their energy in each step of 1/60 s, which is why it is stable there.

Use it where stability at large steps matters more than energy (stiff cloth at 60 Hz); use
``rattle`` for long energy-conserving runs with constraints and ``rk4`` for short accurate ones
(see :mod:`constrained_particles.integrators`). Walls are linearized only once a
particle is inside: a particle arriving at speed |v| can penetrate about |v| h before the wall
acts, and that stored energy appears within a step.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .integrators import METHODS, ORDERS, State
from .system import SimulationDiverged

if TYPE_CHECKING:
    from .solver import ConstraintSolver
    from .system import ParticleSystem

#: Relative backward error above which a KKT solution is rejected.
SOLVE_TOLERANCE = 1e-8
#: Absolute residual (in the right-hand side's units, N s and m/s) below which a KKT solution is
#: accepted whatever its relative error: far below anything physical, far above the subnormal
#: range (under 2.2e-308) where a settled system's velocities end up and floats keep only a few
#: significant digits, so that the relative test would reject a correct solution.
SOLVE_FLOOR = 1e-280


class ImplicitSolveError(SimulationDiverged):
    """The linear solve of an implicit step failed (singular or inaccurate KKT system).

    A subclass of :class:`~constrained_particles.SimulationDiverged`: the system keeps the
    state it had before the step.
    """


def force_jacobians(system: ParticleSystem, x: np.ndarray, v: np.ndarray,
                    definite: bool = False) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """``df/dx`` (N/m) and ``df/dv`` (N s/m) of all of ``system``'s forces at (x, v).

    Sparse (2n, 2n) matrices over the stacked coordinates ``q = (x_0, y_0, x_1, y_1, ...)``.
    ``definite=True`` gives the semi-definite approximations :func:`implicit_euler` uses (see
    :meth:`~constrained_particles.forces.Force.jacobians`).

    >>> from constrained_particles import ParticleSystem, DampedSpring
    >>> s = ParticleSystem()
    >>> a = s.add_particle((0.0, 0.0)); b = s.add_particle((1.0, 0.0))
    >>> s.add(DampedSpring(a, b, ks=10.0, kd=0.5))
    >>> K, D = force_jacobians(s, s.x, s.v)
    >>> float(K[0, 0]), float(D[0, 2])
    (-10.0, 0.5)
    """
    n2 = 2 * system.n
    rows, cols = _force_pattern(system)
    K, D = _force_values(system, x, v, definite)
    return (sp.csr_matrix((K, (rows, cols)), shape=(n2, n2)),
            sp.csr_matrix((D, (rows, cols)), shape=(n2, n2)))


def _force_pattern(system: ParticleSystem) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of every force block's Jacobian entries, in block order."""
    patterns = [f.jacobian_pattern(system.n) for f in system.forces]
    if not patterns:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate([p[0] for p in patterns]), np.concatenate([p[1] for p in patterns])


def _force_values(system: ParticleSystem, x: np.ndarray, v: np.ndarray, definite: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Values of df/dx and df/dv of every force block, in the order of :func:`_force_pattern`."""
    values = [f.jacobians(x, v, system.mass, definite) for f in system.forces]
    if not values:
        return np.zeros(0), np.zeros(0)
    return np.concatenate([val[0] for val in values]), np.concatenate([val[1] for val in values])


def _topology_key(system: ParticleSystem) -> tuple:
    """Everything the KKT structure depends on, apart from the constraint solver's identity."""
    forces = tuple(
        (type(f), id(f), tuple(b"" if getattr(f, name) is None else getattr(f, name).tobytes()
                               for name in f.index_fields))
        for f in system.forces)
    return system.n, (system.inv_mass > 0).tobytes(), forces


class _Assembly:
    """The KKT matrix structure for one topology; :meth:`matrix` only refills values.

    Every entry (mass diagonal, force Jacobian entries, J, J^T, compliance diagonal) has a
    precomputed slot in the CSC data array; repeated entries are summed with one bincount.
    """

    def __init__(self, system: ParticleSystem, solver: ConstraintSolver, key: tuple) -> None:
        self.key = key
        self.solver = solver
        self.free = np.repeat(system.inv_mass > 0, 2)
        reduced = np.cumsum(self.free) - 1
        self.nf = nf = int(self.free.sum())
        self.m = m = solver.m
        self.force_rows, self.force_cols = fr, fc = _force_pattern(system)
        self.keep_force = self.free[fr] & self.free[fc]
        jr = np.repeat(np.arange(m), np.diff(solver.J.indptr))
        jc = solver.J.indices
        self.keep_J = self.free[jc]
        empty = np.bincount(jr[self.keep_J], minlength=m) == 0
        if np.any(empty):
            raise ValueError(f"constraint rows {np.flatnonzero(empty)[:10].tolist()} act only on "
                             "fixed particles: implicit_euler cannot satisfy them")
        diag = np.arange(nf)
        jr, jc = nf + jr[self.keep_J], reduced[jc[self.keep_J]]
        lam = nf + np.arange(m)
        self._R = np.concatenate([diag, reduced[fr[self.keep_force]], jr, jc, lam])
        self._C = np.concatenate([diag, reduced[fc[self.keep_force]], jc, jr, lam])
        self.size = nf + m
        #: The fill-reducing ordering (new index -> old) SuperLU found at the first solve, or
        #: None: once known, the matrix is assembled already permuted and factorised without
        #: searching for an ordering again.
        self.order: np.ndarray | None = None
        #: Whether a successful search records its ordering (False: search at every step, as a
        #: benchmark's baseline does).
        self.keep_order = True
        self._structure(self._R, self._C)

    def _structure(self, R: np.ndarray, C: np.ndarray) -> None:
        """The CSC structure of the entries at rows ``R``, columns ``C`` (repeats summed)."""
        order = np.lexsort((R, C))
        Rs, Cs = R[order], C[order]
        first = np.ones(len(R), dtype=bool)
        first[1:] = (Rs[1:] != Rs[:-1]) | (Cs[1:] != Cs[:-1])
        self.slot = np.empty(len(R), dtype=np.int64)
        self.slot[order] = np.cumsum(first) - 1
        self.nnz = int(first.sum())
        self.indices = Rs[first]
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(Cs[first],
                                                                   minlength=self.size))])

    def forget(self) -> None:
        """Back to the unpermuted structure (the next solve searches for an ordering again)."""
        self._structure(self._R, self._C)
        self.order = None

    def reorder(self, order: np.ndarray) -> None:
        """Assemble from now on the symmetrically permuted matrix ``A[order][:, order]``."""
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        self._structure(rank[self._R], rank[self._C])
        self.order = order

    def matrix(self, mass2: np.ndarray, A_force: np.ndarray, J_data: np.ndarray,
               compliance: float) -> sp.csc_matrix:
        """The KKT matrix for per-coordinate masses, force entries ``-h D - h^2 K`` (in pattern
        order), the values of J and the compliance term ``-c/h^2``; permuted by
        :attr:`order` once it is known."""
        Jf = J_data[self.keep_J]
        vals = np.concatenate([mass2[self.free], A_force[self.keep_force], Jf, Jf,
                               np.full(self.m, compliance)])
        data = np.bincount(self.slot, weights=vals, minlength=self.nnz)
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))


_ASSEMBLIES: weakref.WeakKeyDictionary[ParticleSystem, _Assembly] = weakref.WeakKeyDictionary()


def _assembly(system: ParticleSystem) -> _Assembly:
    solver = system.constraint_solver
    key = _topology_key(system)
    cached = _ASSEMBLIES.get(system)
    if cached is None or cached.solver is not solver or cached.key != key:
        cached = _ASSEMBLIES[system] = _Assembly(system, solver, key)
    return cached


#: SuperLU settings, tried in order: a fill-reducing ordering of the KKT's symmetric structure
#: with threshold pivoting (fast), then COLAMD with full partial pivoting (robust). A matrix
#: already assembled in the ordering found at its topology's first solve tries
#: :data:`_LU_ORDERED` first (no ordering search: the structure is the same every step).
_LU_OPTIONS = (dict(permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1,
                    options={"SymmetricMode": True}),
               dict(permc_spec="COLAMD", diag_pivot_thresh=1.0))
_LU_ORDERED = dict(permc_spec="NATURAL", diag_pivot_thresh=0.1, options={"SymmetricMode": True})


def _solve(A: sp.csc_matrix, rhs: np.ndarray, t: float, J: sp.csr_matrix, free: np.ndarray,
           asm: _Assembly | None = None) -> np.ndarray:
    """Solve the KKT system by sparse LU, accepting only a small backward error: relative
    (:data:`SOLVE_TOLERANCE`) or below the absolute :data:`SOLVE_FLOOR`. The constraint
    Jacobian ``J`` and the mask ``free`` of free coordinates only serve to explain a failure.

    With ``asm``: ``A`` and ``rhs`` are in its ordering if it has one (the solution is
    returned in the original order), and a first solve that succeeds with the fill-reducing
    ordering records that ordering for the following steps."""
    ordered = asm is not None and asm.order is not None
    if ordered:
        rhs = rhs[asm.order]
    scale_rhs = np.max(np.abs(rhs), initial=0.0)
    scale_A = np.max(np.abs(A.data), initial=0.0)
    problem = "it was not attempted"
    for options in ((_LU_ORDERED, *_LU_OPTIONS) if ordered else _LU_OPTIONS):
        try:
            lu = spla.splu(A, **options)
            sol = lu.solve(rhs)
        except RuntimeError as err:
            problem = f"the matrix is singular ({err})"
            continue
        residual = np.max(np.abs(A @ sol - rhs), initial=0.0)
        scale = scale_A * np.max(np.abs(sol), initial=0.0) + scale_rhs
        if np.all(np.isfinite(sol)) and residual <= SOLVE_TOLERANCE * scale + SOLVE_FLOOR:
            if ordered:
                out = np.empty_like(sol)
                out[asm.order] = sol
                if options is not _LU_ORDERED:  # the kept order failed: search again next step
                    asm.forget()
                return out
            if asm is not None and asm.keep_order and options is _LU_OPTIONS[0]:
                asm.reorder(np.argsort(lu.perm_c))  # A Pc = A[:, argsort(perm_c)]
            return sol
        problem = f"the relative residual is {residual / scale if scale > 0 else np.inf:.3g}"
    dependent = _dependent_rows(J[:, free])
    if dependent is None:
        cause = ("if some constraints are redundant, ParticleSystem(compliance > 0) solves them "
                 "(too many rows to check here)")
    elif len(dependent):
        cause = (f"constraint rows {dependent[:10].tolist()} depend linearly on the others "
                 "(redundant constraints): they need ParticleSystem(compliance > 0)")
    else:
        cause = ("the constraint rows are linearly independent, so the matrix is ill-conditioned "
                 "(extreme stiffness, mass or step ratios)")
    raise ImplicitSolveError(
        f"implicit_euler: the KKT solve at t = {t:.6g} s failed: {problem}; {cause}. "
        "The state was kept")


#: Largest m x (free coordinates) for which a failed solve checks the rank of J densely.
RANK_CHECK_SIZE = 4_000_000


def _dependent_rows(J_free: sp.csr_matrix) -> np.ndarray | None:
    """Rows of ``J_free`` that are linear combinations of the other rows (empty if J has full
    row rank), by QR with column pivoting of J^T; None if J is too large to check densely."""
    m, nf = J_free.shape
    if m == 0:
        return np.zeros(0, np.int64)
    if m * nf > RANK_CHECK_SIZE:
        return None
    r, piv = scipy.linalg.qr(J_free.toarray().T, mode="r", pivoting=True)
    diag = np.abs(np.diag(r))
    rank = int(np.sum(diag > diag.max(initial=0.0) * max(m, nf) * np.finfo(float).eps))
    return np.sort(piv[rank:])


def implicit_euler(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float
                   ) -> State:
    """Linearized backward Euler (Baraff & Witkin 1998), order 1, constraints in a KKT solve.

    See the module docstring for the system solved. The stabilisation gains are the system's
    ``drift_correction`` (beta, dimensionless in [0, 1]: the fraction of the constraint error C
    removed per step) and ``compliance`` (c >= 0, in units of C per unit of lam, m/N for line
    wires and fixed points; 0 is a hard constraint). Raises :class:`ImplicitSolveError` if the
    KKT system is singular or the solve is inaccurate (its message names linearly dependent
    constraint rows, which need compliance > 0, when there are any), the explicit methods'
    ``ValueError`` for a constraint row with a vanishing gradient (a rod whose ends coincide),
    ``NotImplementedError`` for a force block without Jacobians.
    """
    asm = _assembly(system)
    solver = asm.solver
    beta, compliance = system.drift_correction, system.compliance
    f0 = system.applied_forces(x, v).ravel()
    if not np.all(np.isfinite(f0)):
        raise SimulationDiverged("applied forces became non-finite")
    K, D = _force_values(system, x, v, definite=True)
    qdot = v.ravel()
    Kv = np.bincount(asm.force_rows, weights=K * qdot[asm.force_cols], minlength=qdot.size)
    solver.refill(x, v)
    if solver.m:  # a row with a vanishing gradient gets the explicit methods' ValueError
        solver._diag(np.repeat(system.inv_mass, 2))
    A = asm.matrix(np.repeat(system.mass, 2), -h * D - h * h * K, solver.J.data,
                   -compliance / (h * h))
    rhs = np.concatenate([(h * (f0 + h * Kv))[asm.free],
                          -(beta / h) * solver.C - solver.J @ qdot])
    sol = _solve(A, rhs, t, solver.J, asm.free, asm)
    dv = np.zeros_like(qdot)
    dv[asm.free] = sol[:asm.nf]
    v1 = (qdot + dv).reshape(v.shape)
    return x + h * v1, v1


METHODS["implicit_euler"] = implicit_euler
ORDERS["implicit_euler"] = 1
