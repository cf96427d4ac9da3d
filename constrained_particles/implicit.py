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
one (circular wire, rod) is left off by O(h^2 ``|v|^2``) and pulled back in the next step.

The forces are linearized with the semi-definite Jacobians (``definite=True`` of
:meth:`~constrained_particles.forces.Force.jacobians`: no compressive transverse spring
stiffness, Gauss-Newton angular springs; Choi & Ko 2002). With the exact ones a compressed
cloth predicts buckling and the next large step overshoots: a stiff cloth yanked by a mouse
spring gains energy without bound, while with these its energy never rises. The method stays
order 1. The sparse structure (union of the force blocks' ``jacobian_pattern`` and the
constraint pattern) is built once per topology; each step refills the values.

The linear solve is ``ParticleSystem(implicit_solver=...)``: ``"direct"`` factorises the KKT
matrix with SuperLU (``scipy.sparse.linalg.splu``), whose fill grows faster than the system;
``"cg"`` runs Baraff & Witkin's modified preconditioned conjugate gradients (section 5 of their
paper), cost linear in the particle count: each constraint row on a single moving particle
(wires, fixed points, a rod to a fixed particle) becomes a per-particle *filter* ``S`` and a
prescribed velocity change ``z``, ``dv = z + S y``, and CG solves ``S (A dv - b) = 0`` with
``A = M - h D - h^2 K``, a block-Jacobi preconditioner restricted to the free directions, a warm
start from the previous dv and a relative tolerance :data:`CG_TOLERANCE`. Constraints it cannot
filter (a rod between moving particles, compliance > 0) and a CG solve that fails take the
direct solve. ``"auto"`` (default) takes CG from :data:`CG_MIN_COORDINATES` free coordinates.
docs/physics.md ("Implicit Euler") has the details and figures.

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
particle is inside: a particle arriving at speed ``|v|`` can penetrate about ``|v| h`` before
the wall acts, and that stored energy appears within a step.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import kernels
from .integrators import METHODS, ORDERS, State
from .system import IMPLICIT_SOLVERS, SimulationDiverged

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
#: Conjugate gradients stop when the preconditioned residual norm ``sqrt(r^T P r)`` has fallen
#: to this fraction of its value at the start (``dv = z``, no warm start).
CG_TOLERANCE = 1e-6
#: Absolute floor (J, the units of ``r^T P r``) below which a CG residual is accepted.
CG_FLOOR = 1e-300
#: CG iterations after which a solve is abandoned for the direct one.
CG_MAX_ITERATIONS = 1000
#: ``implicit_solver="auto"`` takes CG from this many free coordinates up (measured crossover).
CG_MIN_COORDINATES = 1024
#: Two rows on one particle whose gradients are this close to parallel (``|sin|`` of their angle)
#: are left to the direct solve, which names them if they are redundant.
PARALLEL_ROWS = 1e-9


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


def _structure(R: np.ndarray, C: np.ndarray, size: int
               ) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """The CSC structure of a (size, size) matrix with entries at rows ``R``, columns ``C``
    (repeats summed): the data slot of every entry, the number of stored values, the row
    indices and the column pointers."""
    order = np.lexsort((R, C))
    Rs, Cs = R[order], C[order]
    first = np.ones(len(R), dtype=bool)
    first[1:] = (Rs[1:] != Rs[:-1]) | (Cs[1:] != Cs[:-1])
    slot = np.empty(len(R), dtype=np.int64)
    slot[order] = np.cumsum(first) - 1
    indptr = np.concatenate([[0], np.cumsum(np.bincount(Cs[first], minlength=size))])
    return slot, int(first.sum()), Rs[first], indptr


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
        #: The conjugate-gradient structure, built at the first CG solve of this topology.
        self.filtered: _Filter | None = None
        #: Which solver gave the last step's dv ("cg" or "direct"), the last CG solve's
        #: iteration count and how many CG solves failed and were redone directly.
        self.last_solver = ""
        self.cg_iterations = 0
        self.cg_failures = 0

    def _structure(self, R: np.ndarray, C: np.ndarray) -> None:
        """The CSC structure of the entries at rows ``R``, columns ``C`` (repeats summed)."""
        self.slot, self.nnz, self.indices, self.indptr = _structure(R, C, self.size)

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


class _Filter:
    """The filtered conjugate-gradient solve of one topology (Baraff & Witkin 1998, section 5).

    Every constraint row that acts on one moving particle (line and circular wires, fixed
    points, a rod to a fixed particle) prescribes that particle's velocity change along the
    row's gradient; a particle with one such row keeps one free direction, with two none. The
    solve then runs over the free directions only: ``dv = z + S y``, with ``S`` the per-particle
    projection onto the free directions (the filter) and ``z`` the prescribed part. :attr:`ok`
    is False when a row couples two moving particles (a rod between them) or a particle carries
    more than two rows: those topologies take the direct KKT solve.
    """

    def __init__(self, system: ParticleSystem, asm: _Assembly) -> None:
        n = self.n = system.n
        diag = np.arange(2 * n)
        R = np.concatenate([diag, asm.force_rows])
        C = np.concatenate([diag, asm.force_cols])
        # (C, R) swapped: the CSC structure of the transpose is the CSR structure of the matrix
        self.slot, self.nnz, self.indices, self.indptr = _structure(C, R, 2 * n)
        own = (R // 2 == C // 2) & (R <= C)  # the upper triangle of each particle's 2x2 block
        self.own = own
        self.own_slot = 3 * (R[own] // 2) + (R[own] & 1) + (C[own] & 1)  # xx 0, xy 1, yy 2
        self.fixed = np.flatnonzero(system.inv_mass == 0)
        #: The previous step's dv (m/s): the next solve's first guess.
        self.warm: np.ndarray | None = None
        J, m = asm.solver.J, asm.m
        self.m = m
        jr = np.repeat(np.arange(m), np.diff(J.indptr))[asm.keep_J]
        part = J.indices[asm.keep_J] // 2
        first = np.full(m, n)
        last = np.full(m, -1)
        np.minimum.at(first, jr, part)
        np.maximum.at(last, jr, part)
        count = np.bincount(first, minlength=n + 1)[:n]
        self.ok = bool(np.all(first == last) and count.max(initial=0) <= 2)
        if not self.ok:
            return
        self.target = 2 * jr + (J.indices[asm.keep_J] & 1)
        rows = np.argsort(first, kind="stable")
        start = np.concatenate([[0], np.cumsum(count)])[:-1]
        self.p1 = np.flatnonzero(count == 1)
        self.k1 = rows[start[self.p1]]
        self.p2 = np.flatnonzero(count == 2)
        self.ka, self.kb = rows[start[self.p2]], rows[start[self.p2] + 1]
        #: Particles whose filter is not the identity (sorted).
        self.filtered = np.union1d(np.union1d(self.p1, self.p2), self.fixed)

    def matrix(self, mass2: np.ndarray, A_force: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """``A = M - h D - h^2 K`` over all 2n coordinates (CSR) and the upper triangles
        (xx, xy, yy) of its diagonal 2x2 blocks, shape (n, 3)."""
        vals = np.concatenate([mass2, A_force])
        data = np.bincount(self.slot, weights=vals, minlength=self.nnz)
        blocks = np.bincount(self.own_slot, weights=vals[self.own], minlength=3 * self.n)
        n2 = 2 * self.n
        return (sp.csr_matrix((data, self.indices, self.indptr), shape=(n2, n2)),
                blocks.reshape(self.n, 3))

    def constraints(self, J_data: np.ndarray, keep_J: np.ndarray, r: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The filter and the prescribed velocity change for rows with values ``J_data`` and
        right-hand sides ``r`` (``J dv = r``): ``S`` of the filtered particles as an (k, 3)
        array (xx, xy, yy), ``z`` (2n,). None if a particle's two rows are (nearly) parallel,
        which only the direct solve can diagnose."""
        n, m = self.n, self.m
        g = np.bincount(self.target, weights=J_data[keep_J], minlength=2 * m).reshape(m, 2)
        z = np.zeros((n, 2))
        S = np.zeros((n, 3))
        g1, r1 = g[self.k1], r[self.k1]
        gg = g1[:, 0] ** 2 + g1[:, 1] ** 2
        z[self.p1] = g1 * (r1 / gg)[:, None]
        S[self.p1] = np.stack([g1[:, 1] ** 2, -g1[:, 0] * g1[:, 1], g1[:, 0] ** 2], 1) / gg[:, None]
        ga, gb, ra, rb = g[self.ka], g[self.kb], r[self.ka], r[self.kb]
        det = ga[:, 0] * gb[:, 1] - ga[:, 1] * gb[:, 0]
        if np.any(np.abs(det) <= PARALLEL_ROWS * np.hypot(*ga.T) * np.hypot(*gb.T)):
            return None
        z[self.p2, 0] = (gb[:, 1] * ra - ga[:, 1] * rb) / det
        z[self.p2, 1] = (ga[:, 0] * rb - gb[:, 0] * ra) / det
        return S[self.filtered], z.ravel()

    def preconditioner(self, blocks: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The block-Jacobi preconditioner, (n, 3) (xx, xy, yy): the inverse of each particle's
        2x2 diagonal block of A restricted to its free directions (0 where it has none)."""
        a, b, c = blocks.T
        P = np.stack([c, -b, a], 1) / (a * c - b * b)[:, None]
        f = self.filtered
        sa, sb, sc = S.T  # S = t t^T (one free direction t) or 0
        d = sa * a[f] + 2 * sb * b[f] + sc * c[f]  # t^T B t when S = t t^T
        with np.errstate(divide="ignore", invalid="ignore"):
            P[f] = np.where((sa + sc > 0.5)[:, None], S / d[:, None], 0.0)
        return P

    def solve(self, A: sp.csr_matrix, P: np.ndarray, S: np.ndarray, z: np.ndarray,
              b: np.ndarray, tol: float, max_iterations: int
              ) -> tuple[np.ndarray | None, int]:
        """Modified preconditioned conjugate gradients (Baraff & Witkin 1998, section 5.3):
        ``dv = z + S y`` with ``S (A dv - b) = 0``, from the previous step's dv, until the
        preconditioned residual ``r^T P r`` is at most ``tol^2`` times its value at ``dv = z``
        (plus :data:`CG_FLOOR`). Returns (dv, iterations); dv is None if A is not positive
        definite on the free directions, the iteration did not converge, or the residual,
        recomputed from dv at the end, fails the same test (four times looser, for rounding).

        The compiled kernel runs it when Numba is enabled, :func:`_cg_reference` otherwise."""
        warm = np.zeros(0) if self.warm is None else self.warm
        run = _cg_compiled if kernels.ENABLED else _cg_reference
        dv, iterations, ok = run(A.indptr, A.indices, A.data, P, self.filtered, S, z, b, warm,
                                 tol, CG_FLOOR, max_iterations)
        if not ok:
            return None, iterations
        self.warm = dv
        return dv, iterations


def _cg_reference(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, P: np.ndarray,
                  fidx: np.ndarray, S: np.ndarray, z: np.ndarray, b: np.ndarray,
                  warm: np.ndarray, tol: float, floor: float, max_iterations: int
                  ) -> tuple[np.ndarray, int, bool]:
    """The filtered PCG of :meth:`_Filter.solve` in numpy (the reference of the compiled
    kernel): the CSR matrix A, the preconditioner P (n, 3), the filter S (k, 3) of particles
    ``fidx``, the prescribed part z, the right-hand side b, a first guess ``warm`` (empty: none).
    Returns (dv, iterations, converged)."""
    A = sp.csr_matrix((data, indices, indptr), shape=(len(b), len(b)))
    px, pxy, py = P[:, 0], P[:, 1], P[:, 2]

    def filtered(u: np.ndarray) -> np.ndarray:
        u2 = u.reshape(-1, 2)
        ux, uy = u2[fidx, 0], u2[fidx, 1]
        u2[fidx, 0] = S[:, 0] * ux + S[:, 1] * uy
        u2[fidx, 1] = S[:, 1] * ux + S[:, 2] * uy
        return u

    def precondition(r: np.ndarray) -> np.ndarray:
        rx, ry = r[0::2], r[1::2]
        out = np.empty_like(r)
        out[0::2] = px * rx + pxy * ry
        out[1::2] = pxy * rx + py * ry
        return out

    residual = filtered(b - A @ z)
    delta0 = float(np.dot(residual, precondition(residual)))
    goal = tol * tol * delta0 + floor
    dv = z.copy()
    if len(warm) and delta0 > goal:
        guess = filtered(warm.copy())
        dv += guess
        residual -= filtered(A @ guess)
    c = precondition(residual)
    delta = float(np.dot(residual, c))
    iterations = 0
    while delta > goal:
        if iterations == max_iterations:
            return dv, iterations, False
        q = A @ c
        cq = float(np.dot(c, q))  # (c is in the free directions: c . S q = c . q)
        if not cq > 0:  # (also NaN) not positive definite on the free directions
            return dv, iterations, False
        alpha = delta / cq
        dv += alpha * c
        residual -= alpha * filtered(q)
        s = precondition(residual)
        delta, old = float(np.dot(residual, s)), delta
        c = s + (delta / old) * c
        iterations += 1
    final = filtered(b - A @ dv)
    return dv, iterations, bool(float(np.dot(final, precondition(final))) <= 4 * goal)


_cg_compiled = None
if kernels.ENABLED:
    njit = kernels.njit

    @njit
    def _matvec(indptr, indices, data, c, out):  # pragma: no cover - compiled
        """``out = A c`` for the CSR matrix A; returns ``c . A c``."""
        total = 0.0
        for i in range(len(out)):
            acc = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                acc += data[k] * c[indices[k]]
            out[i] = acc
            total += c[i] * acc
        return total

    @njit
    def _filter(fidx, S, u):  # pragma: no cover - compiled
        """``u = S u`` on the filtered particles ``fidx``."""
        for k in range(len(fidx)):
            p = fidx[k]
            ux, uy = u[2 * p], u[2 * p + 1]
            u[2 * p] = S[k, 0] * ux + S[k, 1] * uy
            u[2 * p + 1] = S[k, 1] * ux + S[k, 2] * uy

    @njit
    def _precondition(P, r, out):  # pragma: no cover - compiled
        """``out = P r`` (block diagonal); returns ``r . P r``."""
        total = 0.0
        for p in range(len(P)):
            rx, ry = r[2 * p], r[2 * p + 1]
            sx = P[p, 0] * rx + P[p, 1] * ry
            sy = P[p, 1] * rx + P[p, 2] * ry
            out[2 * p], out[2 * p + 1] = sx, sy
            total += rx * sx + ry * sy
        return total

    @njit(nogil=True)
    def _cg_compiled(indptr, indices, data, P, fidx, S, z, b, warm, tol, floor,
                     max_iterations):  # pragma: no cover - compiled
        """The compiled twin of :func:`_cg_reference` (same arguments and results)."""
        size = len(b)
        q = np.empty(size)
        s = np.empty(size)
        _matvec(indptr, indices, data, z, q)
        residual = b - q
        _filter(fidx, S, residual)
        delta0 = _precondition(P, residual, s)
        goal = tol * tol * delta0 + floor
        dv = z.copy()
        if len(warm) > 0 and delta0 > goal:
            guess = warm.copy()
            _filter(fidx, S, guess)
            _matvec(indptr, indices, data, guess, q)
            _filter(fidx, S, q)
            for i in range(size):
                dv[i] += guess[i]
                residual[i] -= q[i]
        delta = _precondition(P, residual, s)
        c = s.copy()
        iterations = 0
        while delta > goal:
            if iterations == max_iterations:
                return dv, iterations, False
            cq = _matvec(indptr, indices, data, c, q)
            if not cq > 0.0:
                return dv, iterations, False
            alpha = delta / cq
            _filter(fidx, S, q)
            for i in range(size):
                dv[i] += alpha * c[i]
                residual[i] -= alpha * q[i]
            old = delta
            delta = _precondition(P, residual, s)
            beta = delta / old
            for i in range(size):
                c[i] = s[i] + beta * c[i]
            iterations += 1
        _matvec(indptr, indices, data, dv, q)
        for i in range(size):
            q[i] = b[i] - q[i]
        _filter(fidx, S, q)
        return dv, iterations, _precondition(P, q, s) <= 4.0 * goal


_ASSEMBLIES: weakref.WeakKeyDictionary[ParticleSystem, _Assembly] = weakref.WeakKeyDictionary()


def _assembly(system: ParticleSystem) -> _Assembly:
    solver = system.constraint_solver
    key = _topology_key(system)
    cached = _ASSEMBLIES.get(system)
    if cached is None or cached.solver is not solver or cached.key != key:
        cached = _ASSEMBLIES[system] = _Assembly(system, solver, key)
    return cached


def last_solve(system: ParticleSystem) -> dict[str, str | int]:
    """How ``system``'s latest implicit_euler step solved its linear system: ``solver``
    (``"cg"`` or ``"direct"``; ``""`` before the first step), ``cg_iterations`` (of that step's
    conjugate gradients, 0 for a direct solve) and ``cg_failures`` (steps since the topology
    was built whose CG did not converge and fell back to the direct solve)."""
    asm = _assembly(system)
    return {"solver": asm.last_solver, "cg_iterations": asm.cg_iterations,
            "cg_failures": asm.cg_failures}


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
    ``ValueError`` for a constraint row with a vanishing gradient (a rod whose ends coincide)
    or an unknown ``implicit_solver``, ``NotImplementedError`` for a force block without
    Jacobians. The system's ``implicit_solver`` (``"auto"``, ``"cg"`` or ``"direct"``) picks
    the linear solve (module docstring).
    """
    choice = getattr(system, "implicit_solver", "auto")
    if choice not in IMPLICIT_SOLVERS:
        raise ValueError(f"implicit_solver must be one of {IMPLICIT_SOLVERS}, got {choice!r}")
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
    mass2 = np.repeat(system.mass, 2)
    A_force = -h * D - h * h * K
    b = h * (f0 + h * Kv)
    r = -(beta / h) * solver.C - solver.J @ qdot
    dv = None
    if compliance == 0 and (choice == "cg" or (choice == "auto"
                                               and asm.nf >= CG_MIN_COORDINATES)):
        dv = _solve_cg(asm, system, mass2, A_force, b, r)
    if dv is None:
        A = asm.matrix(mass2, A_force, solver.J.data, -compliance / (h * h))
        sol = _solve(A, np.concatenate([b[asm.free], r]), t, solver.J, asm.free, asm)
        dv = np.zeros_like(qdot)
        dv[asm.free] = sol[:asm.nf]
        asm.last_solver = "direct"
    v1 = (qdot + dv).reshape(v.shape)
    return x + h * v1, v1


def _solve_cg(asm: _Assembly, system: ParticleSystem, mass2: np.ndarray, A_force: np.ndarray,
              b: np.ndarray, r: np.ndarray) -> np.ndarray | None:
    """dv (2n,) by filtered CG for ``A = M + A_force``, forces ``b`` and rows ``J dv = r``, or
    None where the direct solve must take over: the topology or the rows cannot be filtered,
    or CG failed (counted in ``asm.cg_failures``)."""
    if asm.filtered is None:
        asm.filtered = _Filter(system, asm)
    filt = asm.filtered
    if not filt.ok:
        return None
    found = filt.constraints(asm.solver.J.data, asm.keep_J, r)
    if found is None:
        return None
    S, z = found
    A, blocks = filt.matrix(mass2, A_force)
    P = filt.preconditioner(blocks, S)
    dv, asm.cg_iterations = filt.solve(A, P, S, z, b, CG_TOLERANCE, CG_MAX_ITERATIONS)
    if dv is None:
        asm.cg_failures += 1
    else:
        asm.last_solver = "cg"
    return dv


METHODS["implicit_euler"] = implicit_euler
ORDERS["implicit_euler"] = 1
