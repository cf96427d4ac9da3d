"""Packing a system for the fused compiled step: its blocks as flat per-type arrays.

:func:`pack` turns a system built only from the standard blocks into a :class:`Packed` form,
cached on the system while it is current, which :mod:`.fused` hands to its kernels and the envs'
compiled measures read.

**Safety at the boundary.** Packed arrays are the blocks' own arrays where possible (zero copy,
so in-place edits such as an environment writing its actions into ``ConstantForce.force`` are
seen); where several blocks of one type are joined, their parameter arrays are copied into the
joined ones before every call. Every array the kernel indexes *with* (particle indices, rows,
columns, components, spring runs) is immutable (:func:`~.terms.frozen`: read-only memory that
no ``flags.writeable = True`` can reopen) and is checked once, when the pack is built. The
pack is rebuilt when a block's attribute is reassigned (each block's own ``version``), found
without scanning any array. A call checks only what an in-place edit can change in O(1) per
array: the shapes of the parameter arrays, and a mouse spring's ``active`` flags (the only
index an in-place edit can switch on).

**Rebuilds.** A pack is rebuilt when a block is added or removed or an attribute of one is
reassigned. The constraint rows and their connected components depend only on the constraint
blocks: a new pack takes them over from the previous one while those blocks are the same and
unchanged, so a force block given new index arrays (a drawn spring) costs no new row graph.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from . import kernels
from .constraints import CircularWire, FixedPoint, HorizontalWire, LineWire, Rod
from .forces import (
    AngularSpring,
    ConstantForce,
    DampedSpring,
    Drag,
    Gravity,
    MouseSpring,
    TableFriction,
    Wall,
)
from .fused_accel import RUN_MIN
from .ordering import CG, DENSE, SINGLE, SPARSE, factor_plan
from .records import (
    LIVE_ELEMENTS,
    AngularArrays,
    Blocks,
    CircleArrays,
    ConstantArrays,
    DragArrays,
    Elements,
    FixedArrays,
    FrictionArrays,
    GravityArrays,
    LineArrays,
    Live,
    MouseArrays,
    RodArrays,
    Rows,
    Settings,
    SpringArrays,
    TensionArrays,
    WallArrays,
    blocks_ref,
    engine_ref,
    live_ref,
    plain,
    rows_ref,
    workspace,
    workspace_ref,
    workspace_view,
)
from .solver import DIRECT_MAX, row_components
from .terms import frozen, is_frozen

if TYPE_CHECKING:
    from .system import ParticleSystem


#: The block types of :class:`~.records.Blocks`, in order.
ELEMENT_TYPES = Blocks._fields
_FORCE_TYPES = (Gravity, ConstantForce, DampedSpring, AngularSpring, Drag, Wall, MouseSpring,
                TableFriction)
_CONSTRAINT_TYPES = (CircularWire, Rod, LineWire, HorizontalWire, FixedPoint)

def _ro(a: np.ndarray) -> np.ndarray:
    """``a`` as an immutable array (:func:`~.terms.frozen`, no copy if it is one already): the
    pack's index arrays reach the kernel as one Numba type, and stay as they were checked."""
    return a if is_frozen(a) else frozen(a)


_I0 = _ro(np.zeros(0, np.int64))
#: No step counts (every particle takes every step): writable, as the counts of a call with
#: pieces are, so that the kernel compiles for one type of ``counts`` only.
_NO_COUNTS = np.zeros(0, np.int64)
_F0 = np.zeros(0)
_F02 = np.zeros((0, 2))
_B0 = np.zeros(0, bool)


def supported(system: ParticleSystem) -> bool:
    """True when every block of ``system`` is a standard type the fused kernel implements
    (exact types: a subclass may override the formulas, so it takes the reference path)."""
    return (kernels.ENABLED
            and all(type(f) in _FORCE_TYPES for f in system.forces)
            and all(type(c) in _CONSTRAINT_TYPES for c in system.constraints))


def _f64(a: Any, ndim: int) -> tuple[np.ndarray, bool]:
    """``a`` as a C-contiguous float64 array of ``ndim`` dimensions; True if no copy was made."""
    if (type(a) is np.ndarray and a.dtype == np.float64 and a.ndim == ndim
            and a.flags.c_contiguous and a.flags.writeable):
        return a, True
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape((-1, 2)[-ndim:])), False


def _i64(a: Any) -> tuple[np.ndarray, bool]:
    """``a`` as an immutable 1-D int64 array; True if it is the block's own (no copy made)."""
    if (type(a) is np.ndarray and a.dtype == np.int64 and a.ndim == 1 and a.flags.c_contiguous
            and is_frozen(a)):
        return a, True
    return frozen(np.asarray(a).ravel().astype(np.int64)), False


def _bool(a: Any) -> tuple[np.ndarray, bool]:
    if (type(a) is np.ndarray and a.dtype == np.bool_ and a.ndim == 1 and a.flags.c_contiguous
            and a.flags.writeable):
        return a, True
    return np.ascontiguousarray(np.asarray(a, dtype=bool).ravel()), False


def spring_runs(i: np.ndarray, j: np.ndarray, minimum: int = RUN_MIN) -> np.ndarray:
    """The runs in a spring list ``(i, j)``: spans ``[lo, hi)`` of at least ``minimum`` springs
    whose ends both step by one (``i[e] = i[lo] + e - lo``, ``j[e] = j[lo] + e - lo``) and
    differ (``i != j``), as a read-only (runs, 2) int64 array. A cloth's rows, columns and
    diagonals are such runs; the compiled spring loop reads and writes them contiguously."""
    k = len(i)
    if k == 0 or k < minimum:
        return _ro(np.zeros((0, 2), np.int64))
    start = np.empty(k, bool)  # (without np.r_, whose overhead was most of a small pack's)
    start[0] = True
    np.logical_or(np.diff(i) != 1, np.diff(j) != 1, out=start[1:])
    starts = np.flatnonzero(start)
    ends = np.empty_like(starts)
    ends[:-1] = starts[1:]
    ends[-1] = k
    keep = (ends - starts >= minimum) & (i[starts] != j[starts])
    runs = np.empty((int(np.count_nonzero(keep)), 2), np.int64)
    runs[:, 0] = starts[keep]
    runs[:, 1] = ends[keep]
    return _ro(runs)


class PackRefs(NamedTuple):
    """A :class:`Packed` system's records as compiled code takes them: each held by reference
    (:class:`~.records.RecordRef`), so that a call passes pointers instead of some sixty
    arrays."""

    blocks: object  #: the :class:`~.records.Blocks`, with the mouse springs' arrays below
    rows: object  #: the :class:`~.records.Rows`
    work: object  #: the :class:`~.records.Workspace` over ``Packed.backing``
    #: the three above as one :class:`~.records.Engine`, as the fused step takes them
    engine: object
    #: the mouse springs' particles and ``active`` flags as the compiled code reads them: the
    #: pack's own copies, refreshed before each call (:meth:`Packed.take_mouse`)
    mouse_particle: np.ndarray
    mouse_active: np.ndarray


class Packed:
    """A system's blocks as the fused kernel's flat per-type arrays (see the module docstring).

    Built by :func:`pack`; :meth:`current` tells whether it still describes the system.
    """

    def __init__(self, system: ParticleSystem, previous: Packed | None = None) -> None:
        """``previous``: the system's last pack, whose constraint rows and components are
        taken over when the constraint blocks are the same and unchanged (a force block's
        new index arrays, such as a drawn spring's, then cost no new row graph)."""
        n = system.n
        self.n = n
        #: the system's multiplier solver (``"auto"`` or ``"cg"``: how components of more
        #: than ``DIRECT_MAX`` rows are solved)
        self.solver = getattr(system, "solver", "auto")
        self.forces = list(system.forces)
        self.constraints = list(system.constraints)
        self.zero_copy = True
        self._terms = (*self.forces, *self.constraints)  # (the blocks in versions' order)
        self.versions = [b.version for b in self._terms]
        self.constraint_versions = [c.version for c in self.constraints]
        self.valid = self.supported = supported(system)
        self._mouse_blocks: list[MouseSpring] = []
        #: ``(joined, ((part, its rows of joined), ...), read by the measures)`` per joined
        #: parameter array (:meth:`refresh`)
        self._refresh: list[tuple[np.ndarray, tuple[tuple[np.ndarray, np.ndarray], ...],
                                  bool]] = []
        #: the parameter arrays held zero copy, with the shapes they had (checked every call:
        #: an in-place ``arr.shape = ...`` must not send the kernel past their ends)
        self.params: list[tuple[np.ndarray, tuple[int, ...]]] = []
        if not self.supported:
            return
        by_type: dict[type, list] = {}
        for f in self.forces:
            by_type.setdefault(type(f), []).append(f)
        every = _ro(np.arange(n, dtype=np.int64))

        def idx_of(block: Any, name: str) -> np.ndarray:
            raw = getattr(block, name)
            if raw is None:
                return every
            arr, same = _i64(raw)
            self.zero_copy &= same
            return arr

        def f64(block: Any, name: str, ndim: int) -> np.ndarray:
            arr, same = _f64(getattr(block, name), ndim)
            self.zero_copy &= same
            if same:
                self.params.append((arr, arr.shape))
            return arr

        def scalar(block: Any, name: str) -> float:
            return float(getattr(block, name))

        fresh: list[np.ndarray] = []  # parameter arrays made here from scalars

        def made(a: np.ndarray) -> np.ndarray:
            fresh.append(a)
            return a

        def join(parts: list[tuple], empty: tuple, measured: bool = False) -> tuple:
            """One block's arrays as they are; several blocks' concatenated. Index arrays are
            read-only, so their concatenation stays right; parameter arrays are concatenated
            again before every call (:meth:`refresh`), so in-place edits are seen."""
            if not parts:
                return empty
            if len(parts) == 1:
                return parts[0]
            out = []
            for col in zip(*parts, strict=True):
                joined = np.ascontiguousarray(np.concatenate(col))
                if joined.dtype == np.int64:
                    joined = _ro(joined)
                elif not all(any(a is f for f in fresh) for a in col):
                    # (arrays made here never change)
                    ends = np.cumsum([0, *(len(a) for a in col)])
                    views = tuple(joined[lo:hi] for lo, hi in zip(ends[:-1], ends[1:],
                                                                    strict=True))
                    self._refresh.append((joined, tuple(zip(col, views, strict=True)),
                                          measured))
                out.append(joined)
            return tuple(out)

        grav = []
        for k, g in enumerate(by_type.get(Gravity, [])):
            idx = idx_of(g, "particles")
            grav.append((idx, _ro(np.full(len(idx), k, np.int64)), f64(g, "g", 1).reshape(1, 2)))
        gravity = GravityArrays(*join(grav, (_I0, _I0, _F02)))
        constant = ConstantArrays(*join([(idx_of(c, "particles"), f64(c, "force", 2))
                                         for c in by_type.get(ConstantForce, [])], (_I0, _F02)))
        spring_blocks = by_type.get(DampedSpring, [])
        spring = join([(idx_of(s, "i"), idx_of(s, "j"), f64(s, "rest", 1), f64(s, "ks", 1),
                        f64(s, "kd", 1)) for s in spring_blocks if not s.tension_only],
                      (_I0, _I0, _F0, _F0, _F0))
        springs = SpringArrays(*spring, spring_runs(spring[0], spring[1]))
        tension = TensionArrays(*join([(idx_of(s, "i"), idx_of(s, "j"), f64(s, "rest", 1),
                                        f64(s, "ks", 1), f64(s, "kd", 1))
                                       for s in spring_blocks if s.tension_only],
                                      (_I0, _I0, _F0, _F0, _F0)))
        angular = AngularArrays(*join([(idx_of(a, "a"), idx_of(a, "b"), idx_of(a, "c"),
                                        f64(a, "rest", 1), f64(a, "k", 1), f64(a, "kd", 1))
                                       for a in by_type.get(AngularSpring, [])],
                                      (_I0, _I0, _I0, _F0, _F0, _F0)))
        drag = []
        for d in by_type.get(Drag, []):
            idx = idx_of(d, "particles")
            drag.append((idx, made(np.full(len(idx), scalar(d, "kd")))))
        drags = DragArrays(*join(drag, (_I0, _F0)))
        wall = []
        for k, w in enumerate(by_type.get(Wall, [])):
            idx = idx_of(w, "particles")
            wall.append((idx, _ro(np.full(len(idx), k, np.int64)),
                         f64(w, "normal", 1).reshape(1, 2),
                         made(np.array([[scalar(w, "offset"), scalar(w, "kw"),
                                         scalar(w, "cw")]]))))
        walls = WallArrays(*join(wall, (_I0, _I0, _F02, np.zeros((0, 3))), measured=True))
        mouse = []
        self._mouse_blocks = by_type.get(MouseSpring, [])
        for m in by_type.get(MouseSpring, []):
            active, same = _bool(m.active)
            self.zero_copy &= same
            if same:
                self.params.append((active, active.shape))
            mouse.append((idx_of(m, "particle"), f64(m, "anchor", 2), active, f64(m, "ks", 1),
                          f64(m, "kd", 1)))
        mice = MouseArrays(*join(mouse, (_I0, _F02, _B0, _F0, _F0)))
        friction = []
        for k, f in enumerate(by_type.get(TableFriction, [])):
            lifted, same = _bool(f.lifted)
            self.zero_copy &= same
            if same:
                self.params.append((lifted, lifted.shape))
            idx = idx_of(f, "particles")
            friction.append((idx, _ro(np.full(len(idx), k, np.int64)), f64(f, "mu", 1), lifted,
                             made(np.array([[scalar(f, "g"), scalar(f, "v_s")]]))))
        frictions = FrictionArrays(*join(friction, (_I0, _I0, _F0, _B0, _F02)))

        # constraints: per type, with the global row of each element (system block order)
        circ, rod, line, fixed = [], [], [], []
        offset = 0
        for c in self.constraints:
            k = len(c)
            rows = _ro(offset + np.arange(k, dtype=np.int64) * c.rows_per_element)
            if type(c) is CircularWire:
                circ.append((idx_of(c, "particles"), f64(c, "center", 2), f64(c, "radius", 1),
                             rows))
            elif type(c) is Rod:
                rod.append((idx_of(c, "a"), idx_of(c, "b"), f64(c, "length", 1), rows))
            elif type(c) in (LineWire, HorizontalWire):
                line.append((idx_of(c, "particles"), f64(c, "normal", 2), f64(c, "point", 2),
                             rows))
            else:
                fixed.append((idx_of(c, "particles"), f64(c, "point", 2), rows))
            offset += c.n_rows
        self.m = offset
        #: every block, as the kernels' named records (:class:`~.records.Blocks`)
        self.blocks = Blocks(
            gravity, constant, springs, angular, drags, walls, mice,
            CircleArrays(*join(circ, (_I0, _F02, _F0, _I0), measured=True)),
            RodArrays(*join(rod, (_I0, _I0, _F0, _I0), measured=True)),
            LineArrays(*join(line, (_I0, _F02, _F02, _I0), measured=True)),
            FixedArrays(*join(fixed, (_I0, _F02, _I0), measured=True)),
            frictions, tension)
        if (previous is not None and previous.supported and previous.n == n
                and previous.solver == self.solver and previous.zero_copy and self.zero_copy
                and len(previous.constraints) == len(self.constraints)
                and all(a is b for a, b in zip(previous.constraints, self.constraints,
                                               strict=True))
                and previous.constraint_versions == self.constraint_versions):
            # the same constraint blocks, unchanged: the same (immutable) rows and components
            self.rows = previous.rows
            self.max_component, self.rows_valid = previous.max_component, previous.rows_valid
        else:
            self._build_rows(system)
        self.valid = self.rows_valid and self._consistent()
        #: ``(large, spring_runs, extra)``: which optional parts of the fused step this pack
        #: needs (True) or not (None), fixed for the pack's life (a mouse spring's new particle
        #: array has the old one's shape). The fused step takes them as arguments, and Numba
        #: compiles a version per pattern of None without the parts a None rules out: a run
        #: compiles only what its systems use (docs/compile_time.md).
        self.variant: tuple[bool | None, bool | None, bool | None] = (
            self.large, self.spring_runs, self.extra)
        #: scratch space reused by every call: the backing arrays and the named
        #: :class:`~.records.Workspace` over them
        self.backing = workspace(n, self.m, DIRECT_MAX, int(self.rows.lptr[-1]))
        self.work = workspace_view(self.backing)
        self._live: Live | None = None  # (made on first use: see live)
        self._live_ref: Any = None
        self._refs: PackRefs | None = None  # (made on first use: see refs)
        self._settings: tuple[tuple[Any, ...], Settings] | None = None  # (see settings)

    def _build_rows(self, system: ParticleSystem) -> None:
        """Per-row particle columns and the connected components of the row graph."""
        m = self.m
        blocks = self.blocks
        cols = np.full((m, 4), -1, np.int64)
        for one in (blocks.circle, blocks.line):
            p, rows = one.particles, one.row
            cols[rows, 0], cols[rows, 1] = 2 * p, 2 * p + 1
        a, b, rows = blocks.rod.a, blocks.rod.b, blocks.rod.row
        cols[rows, 0], cols[rows, 1], cols[rows, 2], cols[rows, 3] = 2 * a, 2 * a + 1, 2 * b, \
            2 * b + 1
        p, rows = blocks.fixed.particles, blocks.fixed.row
        cols[rows, 0], cols[rows + 1, 0] = 2 * p, 2 * p + 1
        #: False if a constraint's particle index is out of range (the reference path then
        #: reports it)
        self.rows_valid = not (m and cols.max() >= 2 * self.n)
        if not self.rows_valid:
            cols = np.minimum(cols, 2 * self.n - 1)
        r, k = np.nonzero(cols >= 0)
        comp_rows, comp_ptr = row_components(r, cols[r, k], m, 2 * self.n)
        nnz = (cols >= 0).sum(axis=1).astype(np.int64)
        sizes = np.diff(comp_ptr)
        kind = np.where(sizes == 1, SINGLE, DENSE).astype(np.int64)
        large = sizes > DIRECT_MAX
        kind[large] = SPARSE if self.solver == "auto" else CG
        comp_rows, plan = factor_plan(cols, nnz, comp_rows, comp_ptr, kind == SPARSE)
        #: the constraint rows, their components and the sparse factorisation's plan
        #: (:class:`~.records.Rows`)
        self.rows = Rows(_ro(cols), _ro(nnz), _ro(comp_rows), _ro(comp_ptr), _ro(kind),
                         *(_ro(a) for a in plan))
        self.max_component = int(sizes.max()) if len(sizes) else 0

    @property
    def large(self) -> bool | None:
        """True if a constraint component has more than ``DIRECT_MAX`` rows (the kernels
        solve it by its sparse factorisation, or by conjugate gradients with
        ``solver="cg"``), else None: the fused step takes it as an argument, and its version
        for None compiles neither (docs/compile_time.md)."""
        return True if self.max_component > DIRECT_MAX else None

    @property
    def extra(self) -> bool | None:
        """True if the system has angular springs, mouse springs, fixed points, table
        friction or tension-only springs, else None: the fused step's version for None
        compiles none of their loops, and refuses blocks that hold any (the reference then
        steps them). None for the cloths, the force-mode ClothSlide and SliderCrank and
        ClothPin; True for ChainSwing and the spring modes."""
        b = self.blocks
        if (len(b.angular.a) or len(b.mouse.particle) or len(b.fixed.particles)
                or len(b.friction.particles) or len(b.tension.i)):
            return True
        return None

    @property
    def spring_runs(self) -> bool | None:
        """True if some of the springs form runs (``SpringArrays.runs``, stepped by the
        kernels' vectorised run loop), else None: the fused step takes it as an argument, and
        its version for None compiles no run loop (docs/compile_time.md)."""
        return True if len(self.blocks.spring.runs) else None

    def _consistent(self) -> bool:
        """True if every array the kernel indexes with holds what it must (checked here once:
        they are immutable): particle indices in [0, n), per-element arrays of one length,
        block numbers within their blocks, rows within [0, m), every row with 1 to 4 columns.
        (A mouse spring's particle is checked at every call, against its ``active`` flag.)"""
        n, m = self.n, self.m
        blocks = self.blocks

        def inside(a: np.ndarray, top: int) -> bool:
            return len(a) == 0 or bool(a.min() >= 0 and a.max() < top)

        def aligned(arrays: tuple) -> bool:
            return all(len(a) == len(arrays[0]) for a in arrays)

        grav, wall, spring = blocks.gravity, blocks.wall, blocks.spring
        fric, tension = blocks.friction, blocks.tension
        return (aligned((grav.particles, grav.block)) and inside(grav.block, len(grav.g))
                and aligned(fric[:-1]) and inside(fric.block, len(fric.params))
                and fric.params.shape[1:] == (2,) and aligned(tension)
                and aligned((wall.particles, wall.block)) and aligned((wall.normal, wall.params))
                and inside(wall.block, len(wall.normal)) and aligned(blocks.constant)
                and aligned(spring[:-1]) and aligned(blocks.angular) and aligned(blocks.drag)
                and aligned(blocks.mouse) and aligned(blocks.circle) and aligned(blocks.rod)
                and aligned(blocks.line) and aligned(blocks.fixed)
                and all(inside(idx, n) for idx in (
                    grav.particles, blocks.constant.particles, spring.i, spring.j,
                    blocks.angular.a, blocks.angular.b, blocks.angular.c,
                    blocks.drag.particles, wall.particles, blocks.circle.particles,
                    blocks.rod.a, blocks.rod.b, blocks.line.particles, blocks.fixed.particles,
                    fric.particles, tension.i, tension.j))
                and all(inside(rows, m) for rows in (blocks.circle.row, blocks.rod.row,
                                                     blocks.line.row))
                and inside(blocks.fixed.row, m - 1)
                and bool(np.all((self.rows.nnz >= 1) & (self.rows.nnz <= 4)))
                and self._plan_consistent()
                and np.array_equal(spring.runs, spring_runs(spring.i, spring.j)))

    def _plan_consistent(self) -> bool:
        """True if the sparse factorisation's plan (:class:`~.ordering.FactorPlan`, in
        ``rows``) indexes only within its arrays: pointers that start at 0 and never fall,
        within their lists; entry numbers within L; each column's entries its own diagonal
        first, then later positions of its component; products of existing nonzeros of rows
        of one component that meet in a coordinate; updates of a column from earlier columns.
        (Built here, so this holds; checked once, as the kernels index with it unchecked.)"""
        rows, m = self.rows, self.m
        ptr = rows.comp_ptr
        if len(rows.comp_rows) != m or len(rows.kind) != len(ptr) - 1:
            return False
        nl = len(rows.lpos)
        for p, top in ((rows.lptr, nl), (rows.aptr, len(rows.prod)), (rows.uptr, len(rows.upd))):
            if len(p) != m + 1 or p[0] != 0 or p[-1] != top or np.any(np.diff(p) < 0):
                return False
        comp = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr))  # component of each position
        col = np.repeat(np.arange(m), np.diff(rows.lptr))  # column of each entry
        lpos = rows.lpos
        if nl and not (lpos.min() >= 0 and lpos.max() < m and np.all(lpos >= col)
                       and np.all(comp[lpos] == comp[col])
                       and np.all(lpos[rows.lptr[:-1][np.diff(rows.lptr) > 0]]
                                  == np.flatnonzero(np.diff(rows.lptr) > 0))):
            return False
        planned = comp[np.flatnonzero(np.diff(rows.lptr) > 0)]
        if not np.all(rows.kind[planned] == SPARSE):
            return False
        if np.count_nonzero(np.diff(rows.lptr) > 0) != int(
                np.diff(ptr)[rows.kind == SPARSE].sum()):
            return False
        prod, upd = rows.prod, rows.upd
        if len(prod):
            e, j1, j2, c = prod.T
            r1, r2 = j1 // 4, j2 // 4
            if not (e.min() >= 0 and e.max() < nl and j1.min() >= 0 and j1.max() < 4 * m
                    and j2.min() >= 0 and j2.max() < 4 * m
                    and np.all(j1 % 4 < rows.nnz[r1]) and np.all(j2 % 4 < rows.nnz[r2])
                    and np.all(np.diff(e) >= 0)):
                return False
            flat = rows.cols.reshape(-1)
            if not (np.array_equal(flat[j1], c) and np.array_equal(flat[j2], c)):
                return False
            owner = np.repeat(np.arange(m), np.diff(rows.aptr))
            if not np.all(col[e] == owner):
                return False
        if len(upd):
            if not (upd.min() >= 0 and upd.max() < nl):
                return False
            owner = np.repeat(np.arange(m), np.diff(rows.uptr))
            if not (np.all(col[upd[:, 0]] == owner) and np.all(col[upd[:, 1]] < owner)
                    and np.all(col[upd[:, 2]] < owner)):
                return False
        return True

    @property
    def refs(self) -> PackRefs:
        """The pack's records as compiled code takes them, each held by reference
        (:class:`PackRefs`; made on first use, once per pack)."""
        if self._refs is None:
            mouse = self.blocks.mouse
            particle, active = mouse.particle.copy(), mouse.active.copy()
            blocks = self.blocks._replace(mouse=mouse._replace(particle=particle, active=active))
            b, r, w = (blocks_ref(plain(blocks)), rows_ref(plain(self.rows)),
                       workspace_ref(*self.backing))
            self._refs = PackRefs(b, r, w, engine_ref(b, r, w), particle, active)
        return self._refs

    def settings(self, system: ParticleSystem, residual_limit: float) -> Settings:
        """The :class:`~.records.Settings` of ``system`` for a call that judges residuals
        against ``residual_limit`` (m). Five floats are remembered by identity, and made again
        only when one of them is another object than at the last call (an attribute
        reassigned): a call then reads each attribute once and converts nothing."""
        ks, kd, tol, limit = system.ks, system.kd, system.tol, system.divergence_limit
        last = self._settings
        if last is not None:
            key = last[0]
            if (ks is key[0] and kd is key[1] and tol is key[2] and limit is key[3]
                    and residual_limit is key[4]):
                return last[1]
        made = Settings(float(ks), float(kd), float(tol), float(limit), float(residual_limit))
        f = float  # (only immutable values are remembered: a 0-d array could change in place)
        if (type(ks) is f and type(kd) is f and type(tol) is f and type(limit) is f
                and type(residual_limit) is f):
            self._settings = (ks, kd, tol, limit, residual_limit), made
        return made

    def take_mouse(self) -> bool:
        """Copy the mouse springs' particles and ``active`` flags into the ones the compiled
        code reads (:attr:`PackRefs.mouse_particle`, ``mouse_active``), before each call and
        with the system's step lock held (``ParticleSystem.stepping``): another thread can
        then not switch a spring on, or move it to another particle, after the call has
        checked them. False (nothing copied) if an array's shape changed in place."""
        refs, mouse = self.refs, self.blocks.mouse
        if not len(refs.mouse_active):
            return True
        if (mouse.particle.shape != refs.mouse_particle.shape
                or mouse.active.shape != refs.mouse_active.shape):
            return False
        np.copyto(refs.mouse_particle, mouse.particle)
        np.copyto(refs.mouse_active, mouse.active)
        return True

    @property
    def live(self) -> Live:
        """The workspace of per-particle step counts (:class:`~.records.Live`; made on first
        use, as only split steps need it)."""
        if self._live is None:
            n, m = self.n, self.m
            ncomp = len(self.rows.comp_ptr) - 1
            ptr, ranged, comp_of = self._live_index()
            self._live = Live(np.ones(n, bool), np.zeros(n, np.int64), np.zeros(m, np.int64),
                              np.zeros(ncomp, np.int64),
                              np.zeros(LIVE_ELEMENTS + len(ELEMENT_TYPES) + 1, np.int64),
                              Elements(*(np.zeros(len(b[0]), np.int64) for b in self.blocks)),
                              ptr, ranged, comp_of, np.zeros(ncomp, bool))
        return self._live

    @property
    def live_ref(self) -> object:
        """:attr:`live` as compiled code takes it: held by reference
        (:class:`~.records.RecordRef`; made on first use)."""
        if self._live_ref is None:
            self.live  # noqa: B018 (its arrays)
            self._live_ref = live_ref(plain(self._live))
        return self._live_ref

    def _live_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What ``_gate`` needs to list the live rows, components and elements from the live
        particles alone, instead of scanning every row and element: ``(ptr, ranged,
        comp_of)``. For a block type whose elements are ordered by their first particle
        (``ranged[t]``), the elements of particle q are ``ptr[t, q]:ptr[t, q + 1]`` (so a list
        made particle by particle keeps the elements' order); other types are scanned.
        ``comp_of[c]`` is the component of coordinate c (-1: none)."""
        n, blocks, rows = self.n, self.blocks, self.rows
        ranged = np.array([len(b[0]) == 0 or bool(np.all(np.diff(b[0]) >= 0)) for b in blocks])
        ptr = np.zeros((len(blocks), n + 1), np.int64)
        for t, b in enumerate(blocks):
            if ranged[t]:
                ptr[t] = np.searchsorted(b[0], np.arange(n + 1))
        ncomp = len(rows.comp_ptr) - 1
        row_comp = np.empty(self.m, np.int64)
        row_comp[rows.comp_rows] = np.repeat(np.arange(ncomp), np.diff(rows.comp_ptr))
        comp_of = np.full(2 * n, -1, np.int64)
        used = rows.cols >= 0
        comp_of[rows.cols[used]] = np.broadcast_to(row_comp[:, None], rows.cols.shape)[used]
        return _ro(ptr), _ro(ranged), _ro(comp_of)

    def refresh(self, measured_only: bool = False) -> None:
        """Copy the parameter arrays of types with several blocks into their joined arrays
        (``measured_only``: only those the env measures read, walls' and constraints')."""
        for joined, pairs, read_by_measures in self._refresh:
            if read_by_measures or not measured_only:
                for part, view in pairs:  # (each block's rows of the joined array)
                    if part.shape != view.shape:  # (reshaped in place: as concatenate does,
                        np.concatenate([a for a, _ in pairs], out=joined)  # or its error)
                        break
                    view[...] = part

    def current(self, system: ParticleSystem) -> bool:
        """True if this pack still describes ``system``: the same blocks, none of them with an
        attribute reassigned since it was built (each block's ``version``; in-place edits are
        seen through the arrays), and the parameter arrays of the shapes they had.

        A mouse spring's particle array is replaced (not edited) by ``MouseSpring.set`` at
        every grab; a lone mouse block's new array is taken over here without a rebuild when
        nothing else of the block changed."""
        if not (self.zero_copy and system.n == self.n and system.forces == self.forces
                and system.constraints == self.constraints
                and getattr(system, "solver", "auto") == self.solver):
            return False
        versions = self.versions
        for k, block in enumerate(self._terms):
            if block.version != versions[k]:
                if not self._take_mouse(block):
                    return False
                versions[k] = block.version
        return True

    def _take_mouse(self, block: Any) -> bool:
        """Take over the new particle array of the lone mouse block ``block`` (True), if that
        is all that changed in it; False if the pack must be rebuilt."""
        if len(self._mouse_blocks) != 1 or block is not self._mouse_blocks[0]:
            return False
        mouse = self.blocks.mouse
        if not (block.anchor is mouse.anchor and block.active is mouse.active
                and block.ks is mouse.ks and block.kd is mouse.kd):
            return False
        new, same = _i64(block.particle)
        if not (same and new.shape == mouse.particle.shape):
            return False
        # (the compiled code reads a copy, refreshed before each call: see take_mouse)
        self.blocks = self.blocks._replace(mouse=mouse._replace(particle=new))
        return True

    def shapes_hold(self) -> bool:
        """True if every parameter array held zero copy still has the shape it had when the
        pack was built (an in-place ``arr.shape = ...`` or ``resize`` changes it)."""
        for arr, shape in self.params:
            if arr.shape != shape:
                return False
        return True


def pack(system: ParticleSystem) -> Packed:
    """The system's current :class:`Packed` form (cached on the system while it is current)."""
    cached = getattr(system, "_packed", None)
    if cached is not None and cached.current(system):
        return cached
    packed = Packed(system, cached)
    system._packed = packed
    return packed
