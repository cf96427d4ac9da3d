"""The fused compiled step: a whole explicit step of a standard system as one Numba call.

A system built only from the standard blocks (:class:`~.Gravity`, :class:`~.ConstantForce`,
:class:`~.DampedSpring`, :class:`~.AngularSpring`, :class:`~.Drag`, :class:`~.Wall`,
:class:`~.MouseSpring`; :class:`~.CircularWire`, :class:`~.Rod`, :class:`~.LineWire` /
:class:`~.HorizontalWire`, :class:`~.FixedPoint`) is *packed* into flat per-type arrays, and one
compiled function then runs ``steps`` steps of ``euler``, ``midpoint``, ``rk4`` or
``symplectic_euler``: force accumulation (the elements of :mod:`.kernels`), the constraint
solve and the integrator update, with no Python between blocks. It follows the reference path
(:meth:`ParticleSystem.acceleration` and :mod:`.integrators`) formula for formula; only the
order in which blocks' forces are summed differs (by type here, by block there), at the level
of rounding.

**The constraint solve.** The rows of ``J W J^T lam = -Jdot qdot - J W Q - ks C - kd Cdot`` are
split once per topology into connected components (rows that share a movable coordinate).
Components of up to :data:`DIRECT_MAX` rows are solved directly (dense Cholesky per component);
larger ones by Jacobi-preconditioned conjugate gradients per component, warm-started from the
previous multipliers. Copies of a tiled scene are therefore solved independently, and copy ``i``
of a batch reproduces the same scene stepped alone bit for bit.

Anything the fused kernel cannot do exactly as the reference does (a singular or ill-posed
solve, CG that does not converge, an index out of range, a user-defined block, a subclass) is
handed back: the step then runs on the reference path, which raises the documented errors.

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

**The spring loop.** Springs go in blocks: the ends' differences are gathered into scratch
arrays, the element runs over the block (its square roots and divisions vectorize), and the
forces are added in spring order. Runs of springs whose ends both step by one (a cloth's rows,
columns and diagonals: :func:`spring_runs`, found once per topology and checked against the
index arrays on every call) are read through contiguous slices instead, and each particle's two
sums from a run are written in one pass in the order the plain loop adds them, so every path
gives the plain loop's forces bit for bit.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from . import kernels
from .constraints import CircularWire, FixedPoint, HorizontalWire, LineWire, Rod
from .forces import AngularSpring, ConstantForce, DampedSpring, Drag, Gravity, MouseSpring, Wall
from .fused_accel import (
    DIVERGED,
    FALLBACK,
    FLAT_MIN,
    OK,
    RUN_MIN,
)
from .solver import DIRECT_MAX, row_components
from .terms import frozen, is_frozen

if TYPE_CHECKING:
    from .system import ParticleSystem

#: Integrators the fused kernel runs, with their codes.
METHOD_CODES = {"euler": 0, "midpoint": 1, "rk4": 2, "symplectic_euler": 3, "rattle": 4}
#: Butcher tableaus of the explicit Runge-Kutta methods the fused step runs in one stage loop:
#: stage i's state is ``y + h sum_j A[i, j] k_j`` and the step ``y + (h / D) sum_j W[j] k_j``
#: (W integers over a common denominator D, summed left to right: the arithmetic of
#: :func:`constrained_particles.integrators.rk4` and ``midpoint`` term for term).
MIDPOINT_A = np.array([[0.0, 0.0], [0.5, 0.0]])
MIDPOINT_W, MIDPOINT_D = np.array([0.0, 1.0]), 1.0
RK4_A = np.array([[0.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0], [0.0, 0.5, 0.0, 0.0],
                  [0.0, 0.0, 1.0, 0.0]])
RK4_W, RK4_D = np.array([1.0, 2.0, 2.0, 1.0]), 6.0

def integrator_args(method: str) -> tuple[int, bool | None, bool | None]:
    """The arguments ``(method, runge_kutta, rattle)`` by which the fused step is told the
    integrator ``method`` (a name in :data:`METHOD_CODES`): its code; True for a Runge-Kutta
    method (``midpoint``, ``rk4``), else None; True for RATTLE, else None. The kernel is
    compiled once per pattern of None, each version holding only its integrator family's
    code, so that a run compiles only the families it steps with. (The tableaus stay
    compile-time constants: passed as arrays instead, rk4 and midpoint measured slower in one
    run, though a repeat was within this machine's noise.)"""
    code = METHOD_CODES[method]
    return (code, True if code in (METHOD_CODES["midpoint"], METHOD_CODES["rk4"]) else None,
            True if code == METHOD_CODES["rattle"] else None)


#: The order of block types in the fused kernel's per-type element lists.
_ELEMENT_TYPES = ("gravity", "constant", "spring", "angular", "drag", "wall", "mouse", "circle",
                  "rod", "line", "fixed")
_FORCE_TYPES = (Gravity, ConstantForce, DampedSpring, AngularSpring, Drag, Wall, MouseSpring)
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
    if k < minimum:
        return _ro(np.zeros((0, 2), np.int64))
    step = (np.diff(i) != 1) | (np.diff(j) != 1)
    starts = np.flatnonzero(np.r_[True, step])
    ends = np.r_[starts[1:], k]
    keep = (ends - starts >= minimum) & (i[starts] != j[starts])
    return _ro(np.ascontiguousarray(np.stack([starts[keep], ends[keep]], axis=1),
                                    dtype=np.int64))


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
        self.forces = list(system.forces)
        self.constraints = list(system.constraints)
        self.zero_copy = True
        self.versions = [b.version for b in (*self.forces, *self.constraints)]
        self.constraint_versions = [c.version for c in self.constraints]
        self.valid = self.supported = supported(system)
        self._mouse_blocks: list[MouseSpring] = []
        self._refresh: list[tuple[np.ndarray, tuple[np.ndarray, ...], bool]] = []
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
                    self._refresh.append((joined, col, measured))
                out.append(joined)
            return tuple(out)

        grav = []
        for k, g in enumerate(by_type.get(Gravity, [])):
            idx = idx_of(g, "particles")
            grav.append((idx, _ro(np.full(len(idx), k, np.int64)), f64(g, "g", 1).reshape(1, 2)))
        self.grav = join(grav, (_I0, _I0, _F02))
        self.const = join([(idx_of(c, "particles"), f64(c, "force", 2))
                           for c in by_type.get(ConstantForce, [])], (_I0, _F02))
        spring = join([(idx_of(s, "i"), idx_of(s, "j"), f64(s, "rest", 1), f64(s, "ks", 1),
                        f64(s, "kd", 1)) for s in by_type.get(DampedSpring, [])],
                      (_I0, _I0, _F0, _F0, _F0))
        self.spring = (*spring, spring_runs(spring[0], spring[1]))
        self.ang = join([(idx_of(a, "a"), idx_of(a, "b"), idx_of(a, "c"), f64(a, "rest", 1),
                          f64(a, "k", 1), f64(a, "kd", 1))
                         for a in by_type.get(AngularSpring, [])],
                        (_I0, _I0, _I0, _F0, _F0, _F0))
        drag = []
        for d in by_type.get(Drag, []):
            idx = idx_of(d, "particles")
            drag.append((idx, made(np.full(len(idx), scalar(d, "kd")))))
        self.drag = join(drag, (_I0, _F0))
        wall = []
        for k, w in enumerate(by_type.get(Wall, [])):
            idx = idx_of(w, "particles")
            wall.append((idx, _ro(np.full(len(idx), k, np.int64)),
                         f64(w, "normal", 1).reshape(1, 2),
                         made(np.array([[scalar(w, "offset"), scalar(w, "kw"),
                                         scalar(w, "cw")]]))))
        self.wall = join(wall, (_I0, _I0, _F02, np.zeros((0, 3))), measured=True)
        mouse = []
        self._mouse_blocks = by_type.get(MouseSpring, [])
        for m in by_type.get(MouseSpring, []):
            active, same = _bool(m.active)
            self.zero_copy &= same
            if same:
                self.params.append((active, active.shape))
            mouse.append((idx_of(m, "particle"), f64(m, "anchor", 2), active, f64(m, "ks", 1),
                          f64(m, "kd", 1)))
        self.mouse = join(mouse, (_I0, _F02, _B0, _F0, _F0))

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
        self.circ = join(circ, (_I0, _F02, _F0, _I0), measured=True)
        self.rod = join(rod, (_I0, _I0, _F0, _I0), measured=True)
        self.line = join(line, (_I0, _F02, _F02, _I0), measured=True)
        self.fixed = join(fixed, (_I0, _F02, _I0), measured=True)
        if (previous is not None and previous.supported and previous.n == n
                and previous.zero_copy and self.zero_copy
                and len(previous.constraints) == len(self.constraints)
                and all(a is b for a, b in zip(previous.constraints, self.constraints,
                                               strict=True))
                and previous.constraint_versions == self.constraint_versions):
            # the same constraint blocks, unchanged: the same (immutable) rows and components
            self.cols, self.nnz = previous.cols, previous.nnz
            self.comp_rows, self.comp_ptr = previous.comp_rows, previous.comp_ptr
            self.max_component, self.rows_valid = previous.max_component, previous.rows_valid
        else:
            self._build_rows(system)
        self.valid = self.rows_valid and self._consistent()
        m = self.m
        # scratch space reused by every call: state-sized stage arrays, per-row values,
        # per-coordinate buffers, one dense component block
        self.ws_n = np.zeros((12, n, 2))
        self.ws_J = np.zeros((3, m, 4))
        self.ws_r = np.zeros((5, m))
        self.ws_q = np.zeros((2, 2 * n))
        self.ws_A = np.zeros((DIRECT_MAX + 1, DIRECT_MAX))
        self._ws_live: tuple | None = None  # (made on first use: see ws_live)
        self.args = (self.grav, self.const, self.spring, self.ang, self.drag, self.wall,
                     self.mouse, self.circ, self.rod, self.line, self.fixed, self.cols, self.nnz,
                     self.comp_rows, self.comp_ptr, self.ws_n, self.ws_J, self.ws_r, self.ws_q,
                     self.ws_A)

    def _build_rows(self, system: ParticleSystem) -> None:
        """Per-row particle columns and the connected components of the row graph."""
        m = self.m
        cols = np.full((m, 4), -1, np.int64)
        for p, _, _, rows in [self.circ, self.line]:
            cols[rows, 0], cols[rows, 1] = 2 * p, 2 * p + 1
        a, b, _, rows = self.rod
        cols[rows, 0], cols[rows, 1], cols[rows, 2], cols[rows, 3] = 2 * a, 2 * a + 1, 2 * b, \
            2 * b + 1
        p, _, rows = self.fixed
        cols[rows, 0], cols[rows + 1, 0] = 2 * p, 2 * p + 1
        #: False if a constraint's particle index is out of range (the reference path then
        #: reports it)
        self.rows_valid = not (m and cols.max() >= 2 * self.n)
        if not self.rows_valid:
            cols = np.minimum(cols, 2 * self.n - 1)
        self.cols = _ro(cols)
        self.nnz = _ro((cols >= 0).sum(axis=1).astype(np.int64))
        r, k = np.nonzero(cols >= 0)
        comp_rows, comp_ptr = row_components(r, cols[r, k], m, 2 * self.n)
        self.comp_rows, self.comp_ptr = _ro(comp_rows), _ro(comp_ptr)
        sizes = np.diff(self.comp_ptr)
        self.max_component = int(sizes.max()) if len(sizes) else 0

    def _consistent(self) -> bool:
        """True if every array the kernel indexes with holds what it must (checked here once:
        they are immutable): particle indices in [0, n), per-element arrays of one length,
        block numbers within their blocks, rows within [0, m), every row with 1 to 4 columns.
        (A mouse spring's particle is checked at every call, against its ``active`` flag.)"""
        n, m = self.n, self.m

        def inside(a: np.ndarray, top: int) -> bool:
            return len(a) == 0 or bool(a.min() >= 0 and a.max() < top)

        def aligned(arrays: tuple) -> bool:
            return all(len(a) == len(arrays[0]) for a in arrays)

        gi, gblock, gg = self.grav
        wi, wblock, wn, wpar = self.wall
        si, sj, *_, runs = self.spring
        return (aligned((gi, gblock)) and inside(gblock, len(gg)) and aligned((wi, wblock))
                and aligned((wn, wpar)) and inside(wblock, len(wn)) and aligned(self.const)
                and aligned(self.spring[:5]) and aligned(self.ang) and aligned(self.drag)
                and aligned(self.mouse) and aligned(self.circ) and aligned(self.rod)
                and aligned(self.line) and aligned(self.fixed)
                and all(inside(idx, n) for idx in (
                    gi, self.const[0], si, sj, *self.ang[:3], self.drag[0], wi, self.circ[0],
                    *self.rod[:2], self.line[0], self.fixed[0]))
                and all(inside(rows, m) for rows in (self.circ[3], self.rod[3], self.line[3]))
                and inside(self.fixed[2], m - 1)
                and bool(np.all((self.nnz >= 1) & (self.nnz <= 4)))
                and np.array_equal(runs, spring_runs(si, sj)))

    @property
    def ws_live(self) -> tuple:
        """The workspace of per-particle step counts (made on first use, as only split steps
        need it): the live mask, the live particle, row and component lists, their lengths,
        the live element list of each block type and :meth:`_live_index`."""
        if self._ws_live is None:
            n, m = self.n, self.m
            blocks = (self.grav, self.const, self.spring, self.ang, self.drag, self.wall,
                      self.mouse, self.circ, self.rod, self.line, self.fixed)
            self._ws_live = (np.ones(n, bool), np.zeros(n, np.int64), np.zeros(m, np.int64),
                             np.zeros(len(self.comp_ptr) - 1, np.int64),
                             np.zeros(4 + len(_ELEMENT_TYPES), np.int64),
                             tuple(np.zeros(len(b[0]), np.int64) for b in blocks),
                             self._live_index(blocks))
        return self._ws_live

    def _live_index(self, blocks: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                  np.ndarray]:
        """What ``_gate`` needs to list the live rows, components and elements from the live
        particles alone, instead of scanning every row and element: ``(ptr, ranged, comp_of,
        seen)``. For a block type whose elements are ordered by their first particle
        (``ranged[t]``), the elements of particle q are ``ptr[t, q]:ptr[t, q + 1]`` (so a list
        made particle by particle keeps the elements' order); other types are scanned.
        ``comp_of[c]`` is the component of coordinate c (-1: none), ``seen`` a zeroed mark
        per component."""
        n = self.n
        ranged = np.array([len(b[0]) == 0 or bool(np.all(np.diff(b[0]) >= 0)) for b in blocks])
        ptr = np.zeros((len(blocks), n + 1), np.int64)
        for t, b in enumerate(blocks):
            if ranged[t]:
                ptr[t] = np.searchsorted(b[0], np.arange(n + 1))
        ncomp = len(self.comp_ptr) - 1
        row_comp = np.empty(self.m, np.int64)
        row_comp[self.comp_rows] = np.repeat(np.arange(ncomp), np.diff(self.comp_ptr))
        comp_of = np.full(2 * n, -1, np.int64)
        used = self.cols >= 0
        comp_of[self.cols[used]] = np.broadcast_to(row_comp[:, None], self.cols.shape)[used]
        return (_ro(ptr), _ro(ranged), _ro(comp_of), np.zeros(len(self.comp_ptr) - 1, bool))

    def refresh(self, measured_only: bool = False) -> None:
        """Copy the parameter arrays of types with several blocks into their joined arrays
        (``measured_only``: only those the env measures read, walls' and constraints')."""
        for joined, parts, measured in self._refresh:
            if measured or not measured_only:
                np.concatenate(parts, out=joined)

    def current(self, system: ParticleSystem) -> bool:
        """True if this pack still describes ``system``: the same blocks, none of them with an
        attribute reassigned since it was built (each block's ``version``; in-place edits are
        seen through the arrays), and the parameter arrays of the shapes they had.

        A mouse spring's particle array is replaced (not edited) by ``MouseSpring.set`` at
        every grab; a lone mouse block's new array is taken over here without a rebuild when
        nothing else of the block changed."""
        if not (self.zero_copy and system.n == self.n and system.forces == self.forces
                and system.constraints == self.constraints):
            return False
        versions = self.versions
        for k, block in enumerate((*self.forces, *self.constraints)):
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
        particle, anchor, active, ks, kd = self.mouse
        if not (block.anchor is anchor and block.active is active and block.ks is ks
                and block.kd is kd):
            return False
        new, same = _i64(block.particle)
        if not (same and new.shape == particle.shape):
            return False
        self.mouse = (new, anchor, active, ks, kd)
        self.args = (*self.args[:6], self.mouse, *self.args[7:])
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


def prepare(system: ParticleSystem, lam: np.ndarray, residual_limit: float,
            state: tuple[Any, Any, Any, Any] | None = None
            ) -> tuple[Packed, tuple[np.ndarray, ...], tuple] | None:
    """The system's :class:`Packed` form, the state ``(x, v, mass, inv_mass)`` to step (read
    from the system once, or the caller's ``state`` read once by it) and the arguments
    :func:`fused_steps` takes after the state (``ks, kd, tol, divergence_limit,
    residual_limit`` and the packed blocks), or None where the kernel cannot run: unsupported
    blocks, an index out of range, a parameter array whose shape changed in place, or state
    arrays (and the warm start ``lam``) not C-ordered float64 of the packed sizes. The
    kernel's memory safety rests on these checks (O(1) per array: the arrays the kernel
    indexes with were checked when the pack was built, and cannot change)."""
    p = pack(system)
    if not p.valid:  # unsupported blocks, or an index out of range
        return None
    if not p.shapes_hold():
        return None
    if p._refresh:
        p.refresh()
    if state is None:
        state = system.x, system.v, system.mass, system.inv_mass
    x, v, mass, inv_mass = state
    nd, f64 = np.ndarray, np.float64
    if not (type(x) is nd and type(v) is nd and type(mass) is nd and type(inv_mass) is nd
            and type(lam) is nd and x.dtype == f64 and v.dtype == f64 and mass.dtype == f64
            and inv_mass.dtype == f64 and lam.dtype == f64 and x.flags.c_contiguous
            and v.flags.c_contiguous and mass.flags.c_contiguous
            and inv_mass.flags.c_contiguous and lam.flags.c_contiguous
            and x.shape == v.shape == (p.n, 2) and lam.shape == (p.m,)
            and mass.shape == inv_mass.shape == (p.n,)):
        return None
    args = p.args
    if len(p.mouse[2]):  # the kernel reads a copy of the mouse springs' ``active`` flags: the
        # only index an in-place edit can switch on, checked once per call, may not change
        # while the kernel runs (it releases the GIL, so another thread could edit the block)
        particle, anchor, active, mks, mkd = p.mouse
        args = (*args[:6], (particle, anchor, active.copy(), mks, mkd), *args[7:])
    return p, (x, v, mass, inv_mass), (float(system.ks), float(system.kd), float(system.tol),
                                       float(system.divergence_limit), float(residual_limit),
                                       *args)


def run(system: ParticleSystem, dt: float, method: str, steps: int, lam: np.ndarray,
        residual_limit: float, pieces: np.ndarray | None = None,
        state: tuple[Any, Any, Any, Any] | None = None
        ) -> tuple[int, np.ndarray, np.ndarray, int]:
    """Run ``steps`` fused steps of ``method`` from the system's state.

    ``pieces`` (optional, (n,) int64 >= 1, checked by the caller) splits each step of particle q
    into ``pieces[q]`` steps of ``dt / pieces[q]``; particles coupled by a force element or a
    constraint must share a count (else FALLBACK), and each group of coupled particles is then
    stepped bit for bit as it would be alone with its own count. Not for ``rattle`` (FALLBACK).

    Returns ``(status, x, v, failed_step)``: status :data:`OK` with the new state,
    :data:`DIVERGED` (``failed_step`` is the step whose result was non-finite, beyond
    ``divergence_limit`` or off the constraints by more than ``residual_limit`` m) or
    :data:`FALLBACK` (use the reference path). ``lam`` (the warm start) is updated in place.
    ``state`` is ``(x, v, mass, inv_mass)`` as the caller read them (default: read here), so
    that an attribute replaced meanwhile by another thread is never read.
    """
    ready = prepare(system, lam, residual_limit, state)
    if ready is None:
        return FALLBACK, None, None, 0
    p, (x, v, mass, inv_mass), common = ready
    code, runge_kutta, rattle = integrator_args(method)
    h = float(dt)
    x_out = np.empty_like(x)
    v_out = np.empty_like(v)
    if pieces is None:
        status, failed = fused_steps(code, runge_kutta, rattle, int(steps), h, _F0, _NO_COUNTS, x,
                                     v, mass, inv_mass, lam, x_out, v_out, *common, None)
        return int(status), x_out, v_out, int(failed)
    if pieces.shape != (p.n,) or pieces.dtype != np.int64:
        return FALLBACK, None, None, 0
    status, failed = fused_steps(code, runge_kutta, rattle, 0, h, h / pieces,
                                 pieces * int(steps), x, v, mass, inv_mass, lam, x_out, v_out,
                                 *common, p.ws_live)
    return int(status), x_out, v_out, int(failed)


if kernels.ENABLED:
    from .fused_accel import (
        _accel,
        _beyond_flat,
        _borrowed,
        _check_inputs,
        _copy_flat,
        _distance_error,
        _euler_flat,
        _rattle,
    )
    from .jit import njit

    @njit
    def _firsts(idx, mask, out):  # pragma: no cover - compiled
        """The elements whose particle ``idx[e]`` is live, into ``out``; their number.
        (Branch-free: every element is written and the count advances only for live ones, so
        a scattered mask costs no mispredicted branches; ``out`` has room for all.)"""
        k = 0
        for e in range(idx.shape[0]):
            out[k] = e
            k += mask[idx[e]]
        return k

    @njit
    def _element_lists_fit(lists, grav, const, spring, ang, drag, wall, mouse, circ, rod, line,
                           fixed):  # pragma: no cover - compiled
        """True if each live-element list has room for every element of its type."""
        return (lists[0].shape[0] >= grav[0].shape[0] and lists[1].shape[0] >= const[0].shape[0]
                and lists[2].shape[0] >= spring[0].shape[0]
                and lists[3].shape[0] >= ang[0].shape[0] and lists[4].shape[0] >= drag[0].shape[0]
                and lists[5].shape[0] >= wall[0].shape[0]
                and lists[6].shape[0] >= mouse[0].shape[0]
                and lists[7].shape[0] >= circ[0].shape[0] and lists[8].shape[0] >= rod[0].shape[0]
                and lists[9].shape[0] >= line[0].shape[0]
                and lists[10].shape[0] >= fixed[0].shape[0])

    @njit
    def _gate(step, counts, cols, comp_rows, comp_ptr, firsts, mouse_active, live):
        # pragma: no cover - compiled
        """Which particles take step ``step`` (those with ``counts`` above it): the mask
        ``live[0]`` and, when it changed, the lists of live particles, rows and components
        (``live[1:4]``) and of the live elements of each block type (``live[5]``, in the order
        of :data:`_ELEMENT_TYPES`; ``firsts`` holds each type's first-particle array), with
        their lengths in ``live[4]``, whose last entry keeps the next step at which the mask
        changes (until then nothing is scanned)."""
        mask, plist, rlist, clist, sizes, elements, index = live
        last = sizes.shape[0] - 1  # the next step at which the mask changes
        if step > 0 and step < sizes[last]:
            return
        flips = 0
        for q in range(mask.shape[0]):  # (branch-free: the loop vectorizes)
            now = step < counts[q]
            flips += now != mask[q]
            mask[q] = now
        upcoming = np.iinfo(np.int64).max
        for q in range(mask.shape[0]):
            c = counts[q]
            if c > step and c < upcoming:
                upcoming = c
        sizes[last] = upcoming
        if step > 0 and flips == 0:
            return
        k = 0  # (branch-free, as in _firsts)
        for q in range(mask.shape[0]):
            plist[k] = q
            k += mask[q]
        sizes[0] = k
        # the live components (those of the live particles' coordinates: a component's
        # particles share a count), then their rows, in order within each component (so each
        # coordinate gets its rows' terms in row order, as on the path without a mask)
        ptr, ranged, comp_of, seen = index
        ncomp = comp_ptr.shape[0] - 1
        k = 0
        for i in range(sizes[0]):
            q = plist[i]
            for col in range(2 * q, 2 * q + 2):
                c = comp_of[col]
                if c >= 0 and c < ncomp and not seen[c]:
                    seen[c] = True
                    clist[k] = c
                    k += 1
        sizes[2] = k
        j = 0
        for kk in range(k):
            c = clist[kk]
            seen[c] = False
            for a in range(comp_ptr[c], min(comp_ptr[c + 1], comp_ptr[c] + rlist.shape[0] - j)):
                rlist[j] = comp_rows[a]
                j += 1
        sizes[1] = j
        live_n = sizes[0]
        for t in range(6):  # (a loop, not six calls with constants: one compiled version)
            sizes[3 + t] = _live_elements(t, firsts[t], mask, plist, live_n, ptr, ranged,
                                          elements[t])
        k = 0  # mouse springs: only active ones have a particle to ask about (a grab replaces
        mi = firsts[6]  # the particle array, so they are always scanned)
        for e in range(mi.shape[0]):
            if mouse_active[e] and mask[mi[e]]:
                elements[6][k] = e
                k += 1
        sizes[9] = k
        for t in range(7, 11):
            sizes[3 + t] = _live_elements(t, firsts[t], mask, plist, live_n, ptr, ranged,
                                          elements[t])

    @njit
    def _live_elements(t, idx, mask, plist, live_n, ptr, ranged, out):
        # pragma: no cover - compiled
        """The live elements of block type ``t`` (first particles ``idx``) into ``out``, in
        element order; their number. For a type ordered by first particle (``ranged[t]``),
        the ranges ``ptr[t, q]:ptr[t, q + 1]`` of the ``live_n`` live particles in ``plist``
        (clipped to ``out``'s length); otherwise a scan of every element (:func:`_firsts`)."""
        if not ranged[t]:
            return _firsts(idx, mask, out)
        top = min(idx.shape[0], out.shape[0])
        k = 0
        for i in range(live_n):
            q = plist[i]
            lo = max(ptr[t, q], 0)
            for e in range(lo, min(ptr[t, q + 1], top, lo + top - k)):
                out[k] = e
                k += 1
        return k

    @njit
    def _steps(method, runge_kutta, rattle, steps, h, hp, counts, x0, v0, mass, inv_mass, lam,
               x_out, v_out, ks, kd, tol, limit, residual_limit, grav, const, spring, ang, drag,
               wall, mouse, circ, rod, line, fixed, cols, nnz, comp_rows, comp_ptr, ws_n, ws_J,
               ws_r, ws_q, ws_A, live):  # pragma: no cover - compiled
        """The step loop of :func:`fused_steps` (inputs checked, ``ws_q`` prepared by it):
        ``steps`` steps of ``h`` seconds, or of ``hp[q]`` seconds for particle q if ``hp`` is
        not empty; with ``live`` (the workspace of :func:`_gate`), particle q takes only
        ``counts[q]`` of them. Reads ``x0, v0`` and writes ``x_out, v_out`` only.

        The integrator is RATTLE if ``rattle`` is not None, else the Runge-Kutta method
        ``method`` (1 midpoint, 2 rk4) if ``runge_kutta`` is not None, else ``method`` (0
        euler, 3 symplectic_euler). Numba compiles a version per pattern of None and drops the other
        branches from it, so a run compiles only the integrator families it steps with."""
        n = x0.shape[0]
        m = lam.shape[0]
        per_particle = hp.shape[0] > 0
        w2, tmp = ws_q[0], ws_q[1]
        Jv, Jdv, J0 = ws_J[0], ws_J[1], ws_J[2]
        C, Cdot, b, dl = ws_r[0], ws_r[1], ws_r[2], ws_r[3]
        work, A = ws_A[DIRECT_MAX], ws_A[:DIRECT_MAX]
        a1, a2, a3, a4 = ws_n[2], ws_n[3], ws_n[4], ws_n[5]
        vs2, vs3 = ws_n[8], ws_n[9]
        # the first step reads the caller's state, the last writes the caller's output: no
        # copies in or out, and x0, v0 are never written (the state before the call is kept)
        x, v = x0, v0
        xs, vs = ws_n[6], ws_n[7]
        spare_x, spare_v = ws_n[0], ws_n[1]
        if live is not None:  # a particle that waits is never read by the steps it sits out
            _copy_flat(x0, x_out)  # (its forces and rows are those of waiting particles only):
            _copy_flat(v0, v_out)  # it waits in the output, written when it stops stepping
        for step in range(steps):
            if step == steps - 1:
                xs, vs = x_out, v_out
            if live is not None:
                if step > 0 and step >= live[4][live[4].shape[0] - 1]:  # some stop here
                    mask = live[0]
                    for q in range(n):
                        if mask[q] and step >= counts[q]:
                            x_out[q, 0], x_out[q, 1] = x[q, 0], x[q, 1]
                            v_out[q, 0], v_out[q, 1] = v[q, 0], v[q, 1]
                _gate(step, counts, cols, comp_rows, comp_ptr,
                      (grav[0], const[0], spring[0], ang[0], drag[0], wall[0], mouse[0], circ[0],
                       rod[0], line[0], fixed[0]), mouse[2], live)
            if rattle is not None:
                if not _rattle(x, v, xs, vs, a1, a2, h, mass, inv_mass, w2, grav, const, spring,
                               ang, drag, wall, mouse, circ, rod, line, fixed, cols, nnz,
                               comp_rows, comp_ptr, tol, C, Cdot, Jv, Jdv, J0, b, dl, work, A,
                               tmp):
                    return FALLBACK, step
            elif runge_kutta is None:  # euler / symplectic_euler
                if not _accel(x, v, mass, inv_mass, w2, grav, const, spring, ang, drag, wall,
                              mouse, circ, rod, line, fixed, cols, nnz, comp_rows, comp_ptr, ks,
                              kd, tol, lam, a1, C, Cdot, Jv, Jdv, b, work, A, tmp, live):
                    return FALLBACK, step
                flat = live is None and not per_particle and n >= FLAT_MIN
                if flat:
                    _euler_flat(method == 0, h, x, v, a1, xs, vs)
                for i in range(0 if flat else n if live is None else live[4][0]):
                    q = i if live is None else live[1][i]
                    hq = hp[q] if per_particle else h
                    for d in range(2):
                        if method == 0:
                            xs[q, d] = x[q, d] + hq * v[q, d]
                            vs[q, d] = v[q, d] + hq * a1[q, d]
                        else:
                            vs[q, d] = v[q, d] + hq * a1[q, d]
                            xs[q, d] = x[q, d] + hq * vs[q, d]
            else:  # explicit Runge-Kutta (midpoint, rk4): one stage loop over the tableau
                if method == 1:
                    tab_a, tab_w, tab_d = MIDPOINT_A, MIDPOINT_W, MIDPOINT_D
                else:
                    tab_a, tab_w, tab_d = RK4_A, RK4_W, RK4_D
                stages = tab_w.shape[0]
                kv = (vs2, vs3, vs)  # the velocities of stages 1, 2, 3 (stage 0's is v)
                ka = (a1, a2, a3, a4)  # the accelerations of stages 0, 1, 2, 3
                for stage in range(stages):
                    if stage > 0:  # its state: y + h sum_j A[stage, j] k_j (nonzero terms)
                        out_v = kv[stage - 1]
                        for i in range(n if live is None else live[4][0]):
                            q = i if live is None else live[1][i]
                            hq = hp[q] if per_particle else h
                            for d in range(2):
                                px, pv = x[q, d], v[q, d]
                                for j in range(stage):
                                    c = tab_a[stage, j]
                                    if c != 0.0:
                                        kx = v[q, d] if j == 0 else kv[j - 1][q, d]
                                        px += (c * hq) * kx
                                        pv += (c * hq) * ka[j][q, d]
                                xs[q, d], out_v[q, d] = px, pv
                        sx, sv = xs, out_v
                    else:
                        sx, sv = x, v
                    if not _accel(sx, sv, mass, inv_mass, w2, grav, const, spring, ang, drag,
                                  wall, mouse, circ, rod, line, fixed, cols, nnz, comp_rows,
                                  comp_ptr, ks, kd, tol, lam, ka[stage], C, Cdot, Jv, Jdv, b,
                                  work, A, tmp, live):
                        return FALLBACK, step
                # y + (h / d) sum_j w_j k_j, summed left to right over the nonzero weights
                for i in range(n if live is None else live[4][0]):
                    q = i if live is None else live[1][i]
                    scale = (hp[q] if per_particle else h) / tab_d
                    for d in range(2):
                        tx, tv, first = 0.0, 0.0, True
                        for j in range(stages):
                            wj = tab_w[j]
                            if wj != 0.0:
                                kx = v[q, d] if j == 0 else kv[j - 1][q, d]
                                if first:
                                    tx, tv, first = wj * kx, wj * ka[j][q, d], False
                                else:
                                    tx += wj * kx
                                    tv += wj * ka[j][q, d]
                        xs[q, d] = x[q, d] + scale * tx
                        vs[q, d] = v[q, d] + scale * tv
            # divergence: non-finite, beyond the limit, or off the constraints
            if live is None and n >= FLAT_MIN:
                if _beyond_flat(xs, vs, limit):
                    return DIVERGED, step
            else:
                for i in range(n if live is None else live[4][0]):  # (waiting particles are
                    q = i if live is None else live[1][i]  # unchanged since they passed)
                    for d in range(2):
                        if not (abs(xs[q, d]) < limit and abs(vs[q, d]) < limit):
                            return DIVERGED, step
            if residual_limit < math.inf and m:
                if not _distance_error(xs, circ, rod, line, fixed, live) <= residual_limit:
                    return DIVERGED, step
            if step == 0:  # the new state becomes current; never reuse the caller's arrays
                x, xs = xs, spare_x
                v, vs = vs, spare_v
            else:
                x, xs = xs, x
                v, vs = vs, v
        if steps == 0:  # (copied in loops: a slice assignment compiles Numba's error messages)
            _copy_flat(x0, x_out)
            _copy_flat(v0, v_out)
        return OK, steps


    @njit(nogil=True)
    def fused_steps(method, runge_kutta, rattle, steps, h, hp, counts, x0, v0, mass, inv_mass, lam,
                    x_out, v_out, ks, kd, tol, limit, residual_limit, grav, const, spring, ang,
                    drag, wall, mouse, circ, rod, line, fixed, cols, nnz, comp_rows, comp_ptr, ws_n,
                    ws_J, ws_r, ws_q, ws_A, live):  # pragma: no cover - compiled
        """``steps`` steps of ``h`` seconds, or of ``hp[q]`` seconds for particle q if ``hp`` is
        not empty, with the integrator that ``method, runge_kutta, rattle`` give as
        :func:`integrator_args` makes them. With ``live`` (the workspace of :func:`_gate`;
        None: every particle takes every step), particle q takes ``counts[q]`` steps instead
        (``steps`` is ignored): first the steps only some particles take (a particle with fewer
        waits, and the elements, constraint rows and components of waiting particles are
        skipped), then the steps every particle takes, without the mask. Each particle takes
        its own steps in its own order, so each independent group of particles is stepped
        exactly as it would be alone.
        Returns ``(status, steps done)``."""
        n = x0.shape[0]
        m = lam.shape[0]
        per_particle = hp.shape[0] > 0
        if per_particle and (rattle is not None or hp.shape[0] != n):
            return FALLBACK, 0
        if live is not None and (not per_particle or counts.shape[0] != n
                                 or live[0].shape[0] != n or live[1].shape[0] != n
                                 or live[2].shape[0] != m
                                 or live[3].shape[0] != comp_ptr.shape[0] - 1
                                 or live[4].shape[0] != 4 + len(_ELEMENT_TYPES)
                                 or live[6][0].shape != (len(_ELEMENT_TYPES), n + 1)
                                 or live[6][1].shape[0] != len(_ELEMENT_TYPES)
                                 or live[6][2].shape[0] != 2 * n
                                 or live[6][3].shape[0] != comp_ptr.shape[0] - 1
                                 or not _element_lists_fit(live[5], grav, const, spring, ang,
                                                           drag, wall, mouse, circ, rod, line,
                                                           fixed)):
            return FALLBACK, 0
        if live is None and counts.shape[0] != 0:
            return FALLBACK, 0
        if not _check_inputs(grav, const, spring, ang, drag, wall, mouse, circ, rod, line, fixed,
                             cols, nnz, n, m, lam, counts):
            return FALLBACK, 0
        if (ws_n.shape[0] < 12 or ws_n.shape[1] != n or ws_J.shape[1] != m or ws_r.shape[1] != m
                or ws_q.shape[1] != 2 * n):
            return FALLBACK, 0
        w2, tmp = ws_q[0], ws_q[1]
        for q in range(n):
            w2[2 * q] = inv_mass[q]
            w2[2 * q + 1] = inv_mass[q]
            tmp[2 * q] = 0.0
            tmp[2 * q + 1] = 0.0
        # every array below lives in the caller for the whole call: no reference counting
        # (``live`` itself is never reassigned: Numba then drops the branch that a None
        # ``live`` rules out, so a run without pieces compiles no masked step)
        hp, counts, x0, v0, mass, inv_mass, lam, x_out, v_out, ws_n, mask = _borrowed(
            (hp, counts, x0, v0, mass, inv_mass, lam, x_out, v_out, ws_n, live))
        args = _borrowed((ks, kd, tol, limit, residual_limit, grav, const, spring, ang, drag,
                          wall, mouse, circ, rod, line, fixed, cols, nnz, comp_rows, comp_ptr,
                          ws_n, ws_J, ws_r, ws_q, ws_A))
        if live is None:
            return _steps(method, runge_kutta, rattle, steps, h, hp, counts, x0, v0, mass, inv_mass,
                          lam, x_out, v_out, *args, None)
        if n == 0:
            return OK, 0
        first, total = counts.min(), counts.max()
        if first == total:  # every particle takes every step
            return _steps(method, runge_kutta, rattle, total, h, hp, counts, x0, v0, mass, inv_mass,
                          lam, x_out, v_out, *args, None)
        # the steps only some particles take come first, while their data are likely still in
        # cache from the last call (each particle takes its own steps in its own order, so
        # the order of the two passes changes no bit); then every particle's common steps
        x_mid, v_mid = ws_n[10], ws_n[11]
        status, done = _steps(method, runge_kutta, rattle, total - first, h, hp, counts - first, x0,
                              v0, mass, inv_mass, lam, x_mid, v_mid, *args, mask)
        if status != OK:
            return status, done
        status, more = _steps(method, runge_kutta, rattle, first, h, hp, counts, x_mid, v_mid, mass,
                              inv_mass, lam, x_out, v_out, *args, None)
        return status, done + more
