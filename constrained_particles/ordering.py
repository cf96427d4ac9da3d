"""The elimination ordering and symbolic Cholesky factor of a constraint component's
``J W J^T``, computed once per topology (docs/physics.md, "Which solve runs where").

The matrix ``A = J W J^T`` of a connected component of constraint rows has a nonzero at
``(r, s)`` wherever rows r and s share a coordinate. Its Cholesky factor ``L`` (``A = L L^T``
after a symmetric permutation) fills in where the elimination of a row joins neighbours that
were not neighbours before. The ordering here is greedy: it eliminates a *simplicial* row
(one whose remaining neighbours are all neighbours of each other, so that its elimination
joins nothing) whenever there is one, else a row of minimum degree.

For a chain of rods ``A`` is tridiagonal and its end rows are simplicial: the chain is
eliminated from its ends inwards and ``L`` has exactly the nonzeros of ``A``'s lower triangle.
For any tree of rods (Baraff 1996, "Linear-Time Dynamics using Lagrange Multipliers": an
acyclic constraint graph) the rows' graph is chordal (the rods at one particle form a clique,
and the cliques meet in a tree), a chordal graph always has a simplicial vertex, and
eliminating one leaves a chordal graph: the greedy ordering is a perfect elimination ordering
and produces no fill. The factorisation and each solve then cost time linear in the rows
(times the squared number of rods at a particle). For a component with cycles (a cloth of
rods) the minimum-degree choice limits the fill; the tests count it.

:func:`factor_plan` turns the orderings of the components into flat arrays that the compiled
kernels and the numpy reference both read (:class:`FactorPlan`).
"""

from __future__ import annotations

import heapq
from typing import NamedTuple

import numpy as np

#: How a component's ``J W J^T lam = b`` is solved: a component of one row by a division;
#: up to ``DIRECT_MAX`` rows by a dense Cholesky factorisation; larger ones by the sparse
#: Cholesky factorisation planned here, or by conjugate gradients.
SINGLE, DENSE, SPARSE, CG = 0, 1, 2, 3


def elimination_order(neighbours: list[set[int]]) -> tuple[list[int], list[list[int]]]:
    """A fill-reducing elimination order of the graph ``neighbours`` (vertex -> set of
    adjacent vertices, no self loops), with the structure of the factor it gives.

    Returns ``(order, later)``: ``order[k]`` is the vertex eliminated k-th, and ``later[v]``
    the vertices adjacent to v when v is eliminated (its column's off-diagonal rows in the
    Cholesky factor), sorted by their elimination index. A simplicial vertex (its neighbours
    form a clique: no fill) is taken whenever one exists, else one of minimum degree; ties go
    to the lowest degree, then the lowest vertex number, so that a translated copy of a graph
    gets the translated order.
    """
    n = len(neighbours)
    adj = [set(s) for s in neighbours]
    alive = [True] * n

    def is_simplicial(u: int) -> bool:
        nb = adj[u]
        return all(len(nb) - 1 <= len(adj[w]) and nb <= adj[w] | {w} for w in nb)

    by_degree = [(len(adj[u]), u) for u in range(n)]
    heapq.heapify(by_degree)
    simplicial = [(len(adj[u]), u) for u in range(n) if is_simplicial(u)]
    heapq.heapify(simplicial)
    order: list[int] = []
    later: list[list[int]] = [[] for _ in range(n)]
    position = [0] * n
    while len(order) < n:
        v = -1
        while simplicial:
            d, u = heapq.heappop(simplicial)
            if alive[u] and d == len(adj[u]) and is_simplicial(u):
                v = u
                break
        if v < 0:
            while True:
                d, u = heapq.heappop(by_degree)
                if alive[u] and d == len(adj[u]):
                    v = u
                    break
        alive[v] = False
        position[v] = len(order)
        order.append(v)
        nb = adj[v]
        later[v] = list(nb)
        filled = False
        for w in nb:
            adj[w].discard(v)
        for w in nb:
            missing = nb - adj[w] - {w}
            if missing:
                filled = True
                adj[w] |= missing
        touched = set(nb)
        if filled:  # fill can make a neighbour's neighbour simplicial too
            for w in nb:
                touched |= adj[w]
        for u in touched:
            if alive[u]:
                heapq.heappush(by_degree, (len(adj[u]), u))
                if is_simplicial(u):
                    heapq.heappush(simplicial, (len(adj[u]), u))
        adj[v] = set()
    for v in range(n):
        later[v].sort(key=position.__getitem__)
    return order, later


class FactorPlan(NamedTuple):
    """The sparse Cholesky factorisation of every planned component, as flat arrays.

    Positions are indices into the rows grouped by component (``comp_rows``), whose planned
    components list their rows in elimination order; ``L`` is stored by columns, one column
    per position, its diagonal first. ``A = J W J^T`` of a component is assembled into ``L``'s
    storage from products of the values of J; the left-looking factorisation then applies the
    updates of each column and scales it. A column's diagonal entry ends as the inverse of
    the factor's diagonal (the solves multiply by it)."""

    #: (m + 1,) int64: column p of L is entries ``lptr[p]:lptr[p + 1]``, the diagonal first
    lptr: np.ndarray
    #: (nnz(L),) int64: the position (row of L) of each entry
    lpos: np.ndarray
    #: (m + 1,) int64: the products of column p are ``prod[aptr[p]:aptr[p + 1]]``
    aptr: np.ndarray
    #: (products, 4) int64: ``L[e] += Jv.flat[j1] * w2[c] * Jv.flat[j2]`` for rows
    #: ``(e, j1, j2, c)``, with ``j = 4 r + k`` the k-th nonzero of row r (Jv (m, 4)) and c
    #: the coordinate both nonzeros sit in; sorted by ``e``
    prod: np.ndarray
    #: (m + 1,) int64: the updates of column p are ``upd[uptr[p]:uptr[p + 1]]``
    uptr: np.ndarray
    #: (updates, 3) int64: ``L[t] -= L[a] * L[b]`` for rows ``(t, a, b)``, a and b in earlier
    #: columns
    upd: np.ndarray


def empty_plan(m: int) -> FactorPlan:
    """A :class:`FactorPlan` that plans no component (every pointer zero)."""
    z = np.zeros(m + 1, np.int64)
    return FactorPlan(z, np.zeros(0, np.int64), z, np.zeros((0, 5), np.int64), z,
                      np.zeros((0, 3), np.int64))


def factor_plan(cols: np.ndarray, nnz: np.ndarray, comp_rows: np.ndarray, comp_ptr: np.ndarray,
                planned: np.ndarray) -> tuple[np.ndarray, FactorPlan]:
    """Order the rows of each component with ``planned[k]`` True (:func:`elimination_order`)
    and plan its sparse Cholesky factorisation.

    ``cols`` (m, 4) holds each row's coordinates (-1 unused), ``nnz`` (m,) their number, and
    ``comp_rows``, ``comp_ptr`` the components (:func:`~.solver.row_components`). Returns the
    rows grouped by component with the planned ones in elimination order (the others as
    given), and the :class:`FactorPlan` over those positions.
    """
    m = len(comp_rows)
    comp_rows = np.array(comp_rows, np.int64)
    lptr = np.zeros(m + 1, np.int64)
    aptr = np.zeros(m + 1, np.int64)
    uptr = np.zeros(m + 1, np.int64)
    lpos: list[int] = []
    prod: list[tuple[int, int, int, int]] = []
    upd: list[tuple[int, int, int]] = []
    per_col_l: list[list[int]] = [[] for _ in range(m)]  # (entries' positions, per column)
    col_prod: list[list[tuple[int, int, int, int]]] = [[] for _ in range(m)]
    col_upd: list[list[tuple[int, int, int]]] = [[] for _ in range(m)]
    for k in np.flatnonzero(planned):
        start, stop = int(comp_ptr[k]), int(comp_ptr[k + 1])
        rows = comp_rows[start:stop].copy()
        local = {int(r): i for i, r in enumerate(rows)}
        touching: dict[int, list[tuple[int, int]]] = {}  # coordinate -> (row, slot)
        for r in rows:
            for s in range(int(nnz[r])):
                touching.setdefault(int(cols[r, s]), []).append((int(r), s))
        neighbours: list[set[int]] = [set() for _ in rows]
        for members in touching.values():
            for a, _ in members:
                for b, _ in members:
                    if a != b:
                        neighbours[local[a]].add(local[b])
        order, later = elimination_order(neighbours)
        comp_rows[start:stop] = rows[order]
        pos = {int(rows[v]): start + i for i, v in enumerate(order)}
        for i, v in enumerate(order):
            per_col_l[start + i] = [start + i] + [pos[int(rows[w])] for w in later[v]]
        for members in touching.values():
            for a, sa in members:
                for b, sb in members:
                    pa, pb = pos[a], pos[b]
                    if pa > pb or a == b:  # (every pair of slots of one row: its diagonal)
                        col_prod[pb].append((pa, 4 * a + sa, 4 * b + sb, int(cols[a, sa])))
    # entry numbers
    entry: list[dict[int, int]] = [{} for _ in range(m)]
    e = 0
    for p in range(m):
        lptr[p] = e
        for q in per_col_l[p]:
            entry[p][q] = e
            lpos.append(q)
            e += 1
    lptr[m] = e
    # left-looking updates: column k's entries (i, k), i >= p, update column p = a row of k
    for k in range(m):
        below = per_col_l[k][1:]
        for ii, p in enumerate(below):
            pk = entry[k][p]
            for i in below[ii:]:
                col_upd[p].append((entry[p][i], entry[k][i], pk))
    for p in range(m):
        aptr[p] = len(prod)
        prod.extend(sorted((entry[p][row], j1, j2, c) for row, j1, j2, c in col_prod[p]))
        uptr[p] = len(upd)
        upd.extend(col_upd[p])
    aptr[m], uptr[m] = len(prod), len(upd)
    plan = FactorPlan(lptr, np.array(lpos, np.int64).reshape(-1),
                      aptr, np.array(prod, np.int64).reshape(-1, 4),
                      uptr, np.array(upd, np.int64).reshape(-1, 3))
    return comp_rows, plan


def fill(plan: FactorPlan, comp_ptr: np.ndarray, k: int) -> int:
    """The entries of component k's factor below the diagonal that ``J W J^T`` does not have
    (its fill), for a planned component."""
    start, stop = int(comp_ptr[k]), int(comp_ptr[k + 1])
    lower = plan.lptr[stop] - plan.lptr[start] - (stop - start)
    present = {int(e) for e in plan.prod[plan.aptr[start]:plan.aptr[stop], 0]}
    return int(lower - (len(present) - (stop - start)))
