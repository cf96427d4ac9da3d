"""The compiled sparse Cholesky factorisation and solves of constraint components beyond
``DIRECT_MAX`` rows, by the plan of :mod:`.ordering` held in :class:`~.records.Rows` (the
kernels of :mod:`.fused_accel` call them; docs/physics.md, "Which solve runs where")."""

from __future__ import annotations

import math

from . import kernels
from .ordering import SPARSE

if kernels.ENABLED:
    from .jit import njit

    @njit
    def _sparse_factor(rows, Jv, w2, L, k):  # pragma: no cover - compiled
        """The Cholesky factor of ``J W J^T`` of the sparse-factorised component ``k`` (``J``
        the values ``Jv``) into ``L``, by the plan in ``rows`` (:class:`~.ordering.FactorPlan`:
        assembly from the products of J's values, then each column's left-looking updates from
        earlier columns, its square root and scaling), each diagonal entry stored as its
        inverse; False if a pivot is not above 1e-12 of its diagonal entry (a singular or
        ill-posed component: the reference then solves it)."""
        lptr, aptr, prod, uptr, upd = rows.lptr, rows.aptr, rows.prod, rows.uptr, rows.upd
        jf = Jv.reshape(-1)
        start, stop = rows.comp_ptr[k], rows.comp_ptr[k + 1]
        for e in range(lptr[start], lptr[stop]):
            L[e] = 0.0
        q, end = aptr[start], aptr[stop]
        while q < end:  # (products sorted by entry: each entry's sum in a register)
            e = prod[q, 0]
            acc = 0.0
            while q < end and prod[q, 0] == e:
                acc += jf[prod[q, 1]] * w2[prod[q, 3]] * jf[prod[q, 2]]
                q += 1
            L[e] = acc
        for p in range(start, stop):
            e0 = lptr[p]
            d0 = L[e0]
            for u in range(uptr[p], uptr[p + 1]):
                L[upd[u, 0]] -= L[upd[u, 1]] * L[upd[u, 2]]
            d = L[e0]
            if not d > 1e-12 * d0 or not d > 0.0:
                return False
            inv = 1.0 / math.sqrt(d)
            L[e0] = inv
            for e in range(e0 + 1, lptr[p + 1]):
                L[e] *= inv
        return True

    @njit
    def _sparse_solve(rows, L, y, b, lam, k):  # pragma: no cover - compiled
        """``lam`` of component ``k`` from its factor ``L`` (:func:`_sparse_factor`, the
        diagonal inverted): the right-hand side ``b`` in elimination order into ``y``, ``L z =
        b`` by columns, ``L^T y = z`` by rows, and back into row order."""
        lptr, lpos, comp_rows = rows.lptr, rows.lpos, rows.comp_rows
        start, stop = rows.comp_ptr[k], rows.comp_ptr[k + 1]
        for p in range(start, stop):
            y[p] = b[comp_rows[p]]
        for p in range(start, stop):
            e0 = lptr[p]
            yp = y[p] * L[e0]
            y[p] = yp
            for e in range(e0 + 1, lptr[p + 1]):
                y[lpos[e]] -= L[e] * yp
        for p in range(stop - 1, start - 1, -1):
            e0 = lptr[p]
            acc = y[p]
            for e in range(e0 + 1, lptr[p + 1]):
                acc -= L[e] * y[lpos[e]]
            y[p] = acc * L[e0]
        for p in range(start, stop):
            lam[comp_rows[p]] = y[p]

    @njit
    def _factor_sparse(rows, Jv, w2, L):  # pragma: no cover - compiled
        """:func:`_sparse_factor` of every sparse-factorised component (RATTLE's position
        solve reuses the factors of ``J(x0)``); False if one fails."""
        kind = rows.kind
        for k in range(kind.shape[0]):
            if kind[k] == SPARSE and not _sparse_factor(rows, Jv, w2, L, k):
                return False
        return True

