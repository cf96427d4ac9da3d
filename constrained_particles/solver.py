"""Sparse constraint assembly and the multiplier solve.

The pattern of ``J`` (m x 2n) is built once per topology; each evaluation only refills the
values of ``J`` and ``Jdot`` (same pattern). The multipliers solve (docs/physics.md, "The
constraint force")::

    J W J^T lam = -Jdot qdot - J W Q - ks C - kd Cdot

with ``W = M^-1`` (0 for fixed particles), either by conjugate gradients on the operator
``r -> J (W (J^T r))`` with a Jacobi preconditioner and a warm start from the previous ``lam``
(``method="cg"``), or by a sparse LU factorisation (``method="direct"``). When ``J W J^T`` is
diagonal (no particle shared between rows, e.g. a cloth's top row on a wire) the solve is a
division. A singular but consistent system (two identical rods) gets the least-norm answer.

``method="auto"`` (the default) solves each connected component of the constraint graph on its
own: one row by a division, up to :data:`DIRECT_MAX` rows by a dense factorisation, larger ones
by a sparse Cholesky factorisation in the fill-reducing order of :mod:`.ordering` (linear time
on chains and trees of rods); ``method="cg"`` takes conjugate gradients for those instead
(docs/physics.md, "Which solve runs where").
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .constraints import Constraint
from .ordering import factor_plan

SOLVER_METHODS = ("auto", "cg", "direct")
#: Connected components of the constraint graph with at most this many rows are solved
#: directly (dense, batched over components); larger ones iteratively.
DIRECT_MAX = 8


def row_components(rows: np.ndarray, cols: np.ndarray, m: int, width: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of constraint rows that share a coordinate.

    ``rows``, ``cols`` are the structural nonzeros of J (m x width). Returns ``(comp_rows,
    comp_ptr)``: the rows grouped by component, components ordered by their first row and rows
    ascending inside each, component k being ``comp_rows[comp_ptr[k]:comp_ptr[k + 1]]``. A
    fixed particle's coordinates count as shared too: the partition is then independent of
    the masses (coarser at worst, never wrong). Copies of a tiled scene never share one.
    """
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64)
    from scipy.sparse.csgraph import connected_components

    inc = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(m, max(width, 1)))
    _, label = connected_components(inc @ inc.T, directed=False)
    first = np.full(label.max() + 1, m, np.int64)
    np.minimum.at(first, label, np.arange(m))
    rank = np.empty_like(first)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    comp = rank[label]
    comp_rows = np.lexsort((np.arange(m), comp)).astype(np.int64)
    sizes = np.bincount(comp, minlength=len(first))
    return comp_rows, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


class InconsistentConstraints(ValueError):
    """Constraint rows that cannot all hold at once (e.g. two wires at different heights through
    one particle): ``J W J^T lam = b`` has no solution. The message names the blocks involved."""


def check_consistent(solver: ConstraintSolver, A: spla.LinearOperator, y: np.ndarray,
                     b: np.ndarray) -> None:
    """Raise :class:`InconsistentConstraints` naming the blocks whose rows the least-squares
    answer ``y`` of ``A y = b`` leaves unsatisfied (a consistent singular system, such as two
    identical rods, is solved to the tolerance and passes)."""
    r = A.matvec(y) - b
    scale = np.linalg.norm(b)
    if np.linalg.norm(r) <= 1e-6 * scale or not np.all(np.isfinite(r)):
        return
    rows = np.flatnonzero(np.abs(r) > 1e-3 * np.max(np.abs(r)))
    blocks = []
    for k, (c, span) in enumerate(zip(solver.constraints, solver.block_rows, strict=True)):
        mine = rows[(rows >= span.start) & (rows < span.stop)]
        if len(mine):
            blocks.append(f"constraints[{k}] {type(c).__name__} (rows {mine.tolist()[:5]})")
    raise InconsistentConstraints(
        f"constraints cannot all hold at once: {', '.join(blocks)} contradict each other "
        f"(J W J^T lam = b has no solution; residual {np.linalg.norm(r):.3g} of "
        f"{scale:.3g}). Remove or correct one of them.")


class ConstraintSolver:
    """Assembles ``J``, ``Jdot`` for fixed constraint blocks on ``n`` particles and solves for lam.

    Parameters
    ----------
    constraints : the constraint blocks, in row order.
    n : number of particles.
    method : ``"auto"`` (default), ``"cg"`` or ``"direct"`` (see the module docstring).
    tol : relative residual tolerance of the iterative solves.
    """

    def __init__(self, constraints: Sequence[Constraint], n: int, method: str = "auto",
                 tol: float = 1e-10) -> None:
        if method not in SOLVER_METHODS:
            raise ValueError(f"solver must be one of {SOLVER_METHODS}, got {method!r}")
        self.constraints = list(constraints)
        self.n = n
        self.method = method
        self.tol = tol
        rows, cols, self.block_rows = [], [], []
        offset = 0
        for c in self.constraints:
            r, col = c.pattern()
            rows.append(r + offset)
            cols.append(col)
            self.block_rows.append(slice(offset, offset + c.n_rows))
            offset += c.n_rows
        self.m = offset
        rows = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        cols = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        # CSR order once; every refill permutes the blocks' values into it.
        self._perm = np.lexsort((cols, rows))
        self._rows = rows[self._perm]
        self._cols = cols[self._perm]
        indptr = np.concatenate([[0], np.cumsum(np.bincount(self._rows, minlength=self.m))])
        shape = (self.m, 2 * n)
        self.J = sp.csr_matrix((np.zeros(len(rows)), self._cols, indptr), shape=shape)
        self.Jdot = sp.csr_matrix((np.zeros(len(rows)), self._cols, indptr), shape=shape)
        self.J.has_sorted_indices = True
        self.Jdot.has_sorted_indices = True
        # blocks whose values already come in CSR order need no permutation at refill
        self._sorted = bool(np.array_equal(self._perm, np.arange(len(rows))))
        # rows coupled through a shared coordinate make J W J^T non-diagonal
        structure = sp.csr_matrix((np.ones(len(rows)), self._cols, indptr), shape=shape)
        self.diagonal = (structure @ structure.T).nnz == self.m
        self._plan_components()
        self.lam = np.zeros(self.m)
        self.C = np.zeros(self.m)
        self.Cdot = np.zeros(self.m)

    def _plan_components(self) -> None:
        """Group the rows into connected components, once per topology: each group of small
        components of one size is solved as a batch of dense systems (the nonzero pairs that
        meet in a column, and where their products land, are listed here), each larger
        component by a sparse Cholesky factorisation with its rows in elimination order
        (``method="auto"``), or the rows of all larger components by conjugate gradients
        together (``method="cg"``)."""
        comp_rows, comp_ptr = row_components(self._rows, self._cols, self.m, 2 * self.n)
        sizes = np.diff(comp_ptr)
        # nonzeros sorted by column: every pair within a column meets in J W J^T
        by_col = np.argsort(self._cols, kind="stable")
        col_sorted = self._cols[by_col]
        starts = np.flatnonzero(np.r_[True, col_sorted[1:] != col_sorted[:-1]])
        counts = np.diff(np.r_[starts, len(col_sorted)])
        e1, e2 = [], []
        for t in np.unique(counts):
            group = starts[counts == t]
            a = (group[:, None] + np.arange(t)).repeat(t, axis=1).ravel()
            b = np.tile(group[:, None] + np.arange(t), (1, t)).ravel()
            e1.append(by_col[a])
            e2.append(by_col[b])
        e1 = np.concatenate(e1) if e1 else np.zeros(0, np.int64)
        e2 = np.concatenate(e2) if e2 else np.zeros(0, np.int64)
        comp_of = np.empty(self.m, np.int64)
        pos_of = np.empty(self.m, np.int64)
        comp_of[comp_rows] = np.repeat(np.arange(len(sizes)), sizes)
        pos_of[comp_rows] = np.arange(self.m) - np.repeat(comp_ptr[:-1], sizes)
        r1, r2 = self._rows[e1], self._rows[e2]
        self._groups = []  # (size, rows (k, size), e1, e2, target index into (k, size, size))
        for size in np.unique(sizes[(sizes > 1) & (sizes <= DIRECT_MAX)]):
            comps = np.flatnonzero(sizes == size)
            slot = np.full(len(sizes), -1, np.int64)
            slot[comps] = np.arange(len(comps))
            rows = comp_rows[comp_ptr[comps][:, None] + np.arange(size)]
            pick = slot[comp_of[r1]] >= 0
            target = (slot[comp_of[r1[pick]]] * size + pos_of[r1[pick]]) * size + pos_of[r2[pick]]
            self._groups.append((int(size), rows, e1[pick], e2[pick], target))
        single = comp_rows[comp_ptr[:-1][sizes == 1]]
        self._single = single
        large = sizes > DIRECT_MAX
        #: the rows of each sparse-factorised component, in elimination order
        self._sparse: list[np.ndarray] = []
        if self.method == "auto" and large.any():
            cols = np.full((self.m, 4), -1, np.int64)
            nnz = np.bincount(self._rows, minlength=self.m)
            slot = np.arange(len(self._rows)) - np.repeat(np.cumsum(nnz) - nnz, nnz)
            cols[self._rows, slot] = self._cols
            comp_rows, _ = factor_plan(cols, nnz, comp_rows, comp_ptr, large)
            self._sparse = [comp_rows[comp_ptr[k]:comp_ptr[k + 1]]
                            for k in np.flatnonzero(large)]
            large = np.zeros_like(large)
        self._large = (np.concatenate([comp_rows[comp_ptr[k]:comp_ptr[k + 1]]
                                       for k in np.flatnonzero(large)])
                       if large.any() else np.zeros(0, np.int64))

    def _solve_components(self, b: np.ndarray, w2: np.ndarray, d: np.ndarray,
                          x0: np.ndarray | None) -> np.ndarray | None:
        """Component-wise solve of ``J W J^T y = b`` (None if a dense block is singular or CG on
        the large components fails; the caller then takes the least-squares path)."""
        y = np.zeros(self.m)
        y[self._single] = b[self._single] / d[self._single]
        wv = w2[self._cols] if len(self._groups) else None
        for size, rows, e1, e2, target in self._groups:
            k = len(rows)
            vals = self.J.data[e1] * wv[e1] * self.J.data[e2]
            A = np.bincount(target, vals, minlength=k * size * size).reshape(k, size, size)
            try:
                y[rows] = np.linalg.solve(A, b[rows][..., None])[..., 0]
            except np.linalg.LinAlgError:
                return None
            if not np.all(np.isfinite(y[rows])):
                return None
        for rows in self._sparse:
            Jc = self.J[rows]
            A = (Jc.multiply(w2) @ Jc.T).tocsc()
            try:
                # rows in elimination order, factorised in that order without pivoting: the
                # Cholesky factor's pattern, as L D L^T (a pivot is L's squared diagonal)
                lu = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True})
            except RuntimeError:  # exactly singular
                return None
            if not np.all(lu.U.diagonal() > 1e-12 * A.diagonal()):
                return None  # (numerically) singular: the least-squares path
            y[rows] = lu.solve(b[rows])
            if not np.all(np.isfinite(y[rows])):
                return None
        large = self._large
        if len(large):
            mask = np.zeros(self.m)
            mask[large] = 1.0

            def matvec(r: np.ndarray) -> np.ndarray:
                return mask * self.J_times(w2 * self.JT_times(mask * r))

            A = spla.LinearOperator((self.m, self.m), matvec=matvec, rmatvec=matvec, dtype=float)
            M = spla.LinearOperator((self.m, self.m), matvec=lambda r: mask * r / d, dtype=float)
            start = None if x0 is None else mask * x0
            sol, info = spla.cg(A, mask * b, x0=start, rtol=self.tol, atol=0.0,
                                maxiter=10 * len(large) + 10, M=M)
            if info != 0:
                return None
            y[large] = sol[large]
        return y

    def refill(self, x: np.ndarray, v: np.ndarray) -> None:
        """Evaluate every block at (x, v): refill ``J``, ``Jdot`` values and ``C``, ``Cdot``."""
        parts = [c.evaluate(x, v) for c in self.constraints]
        if not parts:
            return
        if len(parts) == 1:
            self.C, self.Cdot, jv, jdv = parts[0]
        else:
            self.C = np.concatenate([p[0] for p in parts])
            self.Cdot = np.concatenate([p[1] for p in parts])
            jv = np.concatenate([p[2] for p in parts])
            jdv = np.concatenate([p[3] for p in parts])
        self.J.data[:] = jv if self._sorted else jv[self._perm]
        self.Jdot.data[:] = jdv if self._sorted else jdv[self._perm]

    def J_times(self, q: np.ndarray) -> np.ndarray:
        """``J q`` for a flat (2n,) vector ``q``, shape (m,)."""
        return np.bincount(self._rows, self.J.data * q[self._cols], minlength=self.m)

    def JT_times(self, lam: np.ndarray) -> np.ndarray:
        """``J^T lam`` for (m,) multipliers, flat shape (2n,)."""
        return np.bincount(self._cols, self.J.data * lam[self._rows], minlength=2 * self.n)

    def _diag(self, w2: np.ndarray) -> np.ndarray:
        d = np.bincount(self._rows, weights=self.J.data**2 * w2[self._cols], minlength=self.m)
        if d.min() > 0:  # also False for NaN
            return d
        bad = ~(d > 0)
        if np.any(bad):
            rows = np.flatnonzero(bad)
            blocks = zip(self.constraints, self.block_rows, strict=True)
            names = sorted({type(c).__name__ for c, s in blocks
                            if np.any((rows >= s.start) & (rows < s.stop))})
            raise ValueError(
                f"constraint rows {rows[:10].tolist()} ({', '.join(names)}) have a zero row in "
                "J W J^T: they act only on fixed particles or have a vanishing gradient "
                "(e.g. a rod whose ends coincide)")
        return d

    def _solve(self, b: np.ndarray, w2: np.ndarray, x0: np.ndarray | None) -> np.ndarray:
        """Solve ``J W J^T y = b`` (least-norm if singular but consistent)."""
        if not self.m:  # only empty constraint blocks
            return np.zeros(0)
        d = self._diag(w2)
        if self.diagonal:
            return b / d
        J = self.J

        def matvec(r: np.ndarray) -> np.ndarray:
            return self.J_times(w2 * self.JT_times(r))

        A = spla.LinearOperator((self.m, self.m), matvec=matvec, rmatvec=matvec, dtype=float)
        if self.method == "direct":
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")
                    return spla.splu((J.multiply(w2) @ J.T).tocsc()).solve(b)
            except (RuntimeError, spla.MatrixRankWarning):
                pass
        else:
            y = self._solve_components(b, w2, d, x0)
            if y is not None:
                return y
        # singular (redundant constraints) or CG stalled: least-squares, least-norm answer, which
        # must still solve the system (redundant but consistent rows) or the rows contradict
        y = spla.lsmr(A, b, atol=self.tol * 1e-2, btol=self.tol * 1e-2,
                      maxiter=20 * self.m + 20)[0]
        check_consistent(self, A, y, b)
        return y

    def multipliers(self, x: np.ndarray, v: np.ndarray, Q: np.ndarray, w2: np.ndarray,
                    ks: float, kd: float) -> np.ndarray:
        """Lagrange multipliers lam at state (x, v) under applied forces Q (N) (docs/physics.md).

        ``w2`` is the inverse mass per coordinate (2n,); ``ks`` (1/s^2) and ``kd`` (1/s) are the
        feedback gains that pull drift back. Returns lam (m,); ``J^T lam`` is the constraint force.
        """
        self.refill(x, v)
        rows, cols = self._rows, self._cols
        # -Jdot qdot - J W Q in one pass over the nonzeros
        g = self.Jdot.data * v.ravel()[cols] + self.J.data * (w2 * Q.ravel())[cols]
        b = -np.bincount(rows, g, minlength=self.m) - ks * self.C - kd * self.Cdot
        self.lam = self._solve(b, w2, self.lam)
        return self.lam

    def project(self, x: np.ndarray, v: np.ndarray, w2: np.ndarray, tol: float = 1e-12,
                maxiter: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Project (x, v) onto ``C = 0`` (Gauss-Newton, mass-weighted) and then ``J v = 0``.

        Each position iteration is ``dq = -W J^T (J W J^T)^-1 C``, the smallest mass-weighted
        move that zeroes C to first order. Returns new arrays; the inputs are left unchanged.
        """
        x = x.copy()
        shape = x.shape
        for _ in range(maxiter):
            self.refill(x, v)
            if not self.m or np.max(np.abs(self.C)) <= tol:
                break
            x -= (w2 * self.JT_times(self._solve(self.C, w2, None))).reshape(shape)
        self.refill(x, v)
        if not self.m:
            return x, v.copy()
        mu = self._solve(self.J_times(v.ravel()), w2, None)
        v = v - (w2 * self.JT_times(mu)).reshape(shape)
        self.refill(x, v)
        return x, v
