"""The named records that the compiled step's kernels pass around (see :mod:`.packing`).

Every array a kernel reads travels in a record of named fields: a block type's element arrays
(:class:`SpringArrays`, ...), all of a system's blocks (:class:`Blocks`), the constraint rows
and their components (:class:`Rows`), the state (:class:`State`), the solver settings
(:class:`Settings`), the scratch space (:class:`Workspace`) and the live sets of a split step
(:class:`Live`). They are named tuples, so a kernel reads ``blocks.spring.rest``, and a pack
builds them once per topology (:class:`~.packing.Packed`).

**At the boundary.** A pack's records cross into compiled code **by reference**
(:class:`RecordRef`, a Numba structure reference made once per pack by :func:`blocks_ref`,
:func:`rows_ref` and :func:`workspace_ref`): a call passes one pointer per record instead of
every array in it, and so does every compiled function that passes a record on. Numba types a
reference in well under a microsecond, where the same fields as a tuple of some fifty arrays
cost several microseconds a call, and the compiled code that moves one pointer is smaller (and
faster to compile) than code moving fifty array structures. The fused step takes the three
as one :class:`Engine` by reference (:func:`engine_ref`): each reference a call passes costs
Numba's dispatch most of a microsecond to type. A split step's live set
(:class:`Live`) crosses the same way (:func:`live_ref`). The per-call records (the state, the
settings) cross as plain tuples (:func:`plain`) and each entry point rebuilds them
(``State(*state)``): Numba types a plain tuple of arrays in C but a named tuple in Python.

Units are SI: positions in m, velocities in m/s, masses in kg, forces in N. Index arrays are
int64 particle indices (global, into the system's state) and are immutable once packed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import numpy as np

from . import kernels

# ---------------------------------------------------------------------------------------------
# force blocks, one record per type (several blocks of a type are joined into one)


class GravityArrays(NamedTuple):
    """Uniform gravity: particle ``particles[e]`` takes ``mass * g[block[e]]`` (N)."""

    particles: np.ndarray  #: (k,) int64
    block: np.ndarray  #: (k,) int64, the row of ``g`` (one per gravity block)
    g: np.ndarray  #: (blocks, 2) m/s^2


class ConstantArrays(NamedTuple):
    """Applied forces: ``force[e]`` (N) on particle ``particles[e]``."""

    particles: np.ndarray  #: (k,) int64
    force: np.ndarray  #: (k, 2) N


class SpringArrays(NamedTuple):
    """Damped springs between ``i[e]`` and ``j[e]``, with the runs of consecutive ends."""

    i: np.ndarray  #: (k,) int64
    j: np.ndarray  #: (k,) int64
    rest: np.ndarray  #: (k,) m
    ks: np.ndarray  #: (k,) N/m
    kd: np.ndarray  #: (k,) N s/m
    runs: np.ndarray  #: (runs, 2) int64 spans [lo, hi) (see ``packing.spring_runs``)


class AngularArrays(NamedTuple):
    """Angular springs on the angle at ``b[e]`` between ``a[e]`` and ``c[e]``."""

    a: np.ndarray  #: (k,) int64
    b: np.ndarray  #: (k,) int64
    c: np.ndarray  #: (k,) int64
    rest: np.ndarray  #: (k,) rad
    k: np.ndarray  #: (k,) N m/rad
    kd: np.ndarray  #: (k,) N m s/rad


class DragArrays(NamedTuple):
    """Linear drag ``-kd[e] v`` (N) on particle ``particles[e]``."""

    particles: np.ndarray  #: (k,) int64
    kd: np.ndarray  #: (k,) N s/m


class WallArrays(NamedTuple):
    """Penalty walls: particle ``particles[e]`` against wall ``block[e]``."""

    particles: np.ndarray  #: (k,) int64
    block: np.ndarray  #: (k,) int64, the row of ``normal`` and ``params``
    normal: np.ndarray  #: (walls, 2) unit normals
    params: np.ndarray  #: (walls, 3): offset (m), stiffness kw (N/m), damping cw (N s/m)


class MouseArrays(NamedTuple):
    """Mouse springs: particle ``particle[e]`` pulled to ``anchor[e]`` while ``active[e]``."""

    particle: np.ndarray  #: (k,) int64, checked at every call where active
    anchor: np.ndarray  #: (k, 2) m
    active: np.ndarray  #: (k,) bool
    ks: np.ndarray  #: (k,) N/m
    kd: np.ndarray  #: (k,) N s/m


class FrictionArrays(NamedTuple):
    """Table friction on particle ``particles[e]`` with its block's ``params[block[e]]``,
    switched off where ``lifted[e]``."""

    particles: np.ndarray  #: (k,) int64
    block: np.ndarray  #: (k,) int64, the row of ``params`` (one per friction block)
    mu: np.ndarray  #: (k,) friction coefficients
    lifted: np.ndarray  #: (k,) bool
    params: np.ndarray  #: (blocks, 2): g (m/s^2), v_s (m/s)


class TensionArrays(NamedTuple):
    """Tension-only springs (strings) between ``i[e]`` and ``j[e]``."""

    i: np.ndarray  #: (k,) int64
    j: np.ndarray  #: (k,) int64
    rest: np.ndarray  #: (k,) m
    ks: np.ndarray  #: (k,) N/m
    kd: np.ndarray  #: (k,) N s/m


# ---------------------------------------------------------------------------------------------
# constraint blocks: each element's first constraint row is ``row[e]`` (system block order)


class CircleArrays(NamedTuple):
    """Circular wires: ``|x_p - center| = radius``."""

    particles: np.ndarray  #: (k,) int64
    center: np.ndarray  #: (k, 2) m
    radius: np.ndarray  #: (k,) m
    row: np.ndarray  #: (k,) int64


class RodArrays(NamedTuple):
    """Rods: ``|x_a - x_b| = length``."""

    a: np.ndarray  #: (k,) int64
    b: np.ndarray  #: (k,) int64
    length: np.ndarray  #: (k,) m
    row: np.ndarray  #: (k,) int64


class LineArrays(NamedTuple):
    """Line wires: ``n . (x_p - point) = 0``."""

    particles: np.ndarray  #: (k,) int64
    normal: np.ndarray  #: (k, 2) unit normals
    point: np.ndarray  #: (k, 2) m
    row: np.ndarray  #: (k,) int64


class FixedArrays(NamedTuple):
    """Fixed points: ``x_p = point`` (two rows, ``row[e]`` and ``row[e] + 1``)."""

    particles: np.ndarray  #: (k,) int64
    point: np.ndarray  #: (k, 2) m
    row: np.ndarray  #: (k,) int64


class Blocks(NamedTuple):
    """Every block of a packed system, by type (in the order of ``packing.ELEMENT_TYPES``)."""

    gravity: GravityArrays
    constant: ConstantArrays
    spring: SpringArrays
    angular: AngularArrays
    drag: DragArrays
    wall: WallArrays
    mouse: MouseArrays
    circle: CircleArrays
    rod: RodArrays
    line: LineArrays
    fixed: FixedArrays
    friction: FrictionArrays
    tension: TensionArrays


class Rows(NamedTuple):
    """The constraint rows' sparsity, their connected components and how each component is
    solved, with the sparse factorisation's plan (fixed per topology; the plan's fields are
    those of :class:`~.ordering.FactorPlan`, over positions in ``comp_rows``)."""

    cols: np.ndarray  #: (m, 4) int64 coordinates (2 q + axis) of each row's nonzeros, -1 unused
    nnz: np.ndarray  #: (m,) int64 nonzeros per row, 1 to 4
    #: (m,) int64 rows grouped by component (a sparse-factorised one's in elimination order)
    comp_rows: np.ndarray
    comp_ptr: np.ndarray  #: (components + 1,) int64: component c is comp_rows[ptr[c]:ptr[c+1]]
    #: (components,) int64: how each is solved (``ordering.SINGLE``, ``DENSE``, ``SPARSE``,
    #: ``CG``)
    kind: np.ndarray
    lptr: np.ndarray  #: (m + 1,) int64, see :class:`~.ordering.FactorPlan`
    lpos: np.ndarray  #: (nnz(L),) int64
    aptr: np.ndarray  #: (m + 1,) int64
    prod: np.ndarray  #: (products, 5) int64
    uptr: np.ndarray  #: (m + 1,) int64
    upd: np.ndarray  #: (updates, 3) int64


class Engine(NamedTuple):
    """What the fused step reads of a packed system, each record held by reference
    (:class:`RecordRef`): one pointer crosses into compiled code instead of three."""

    blocks: object  #: the :class:`Blocks` (a :data:`RecordRef`)
    rows: object  #: the :class:`Rows` (a :data:`RecordRef`)
    work: object  #: the :class:`Workspace` (a :data:`RecordRef`)


class State(NamedTuple):
    """The state a step starts from, with the solver's warm start."""

    x: np.ndarray  #: (n, 2) m
    v: np.ndarray  #: (n, 2) m/s
    mass: np.ndarray  #: (n,) kg
    inv_mass: np.ndarray  #: (n,) 1/kg (0 for a pinned particle)
    lam: np.ndarray  #: (m,) Lagrange multipliers, updated in place


class Settings(NamedTuple):
    """The system's solver and safety settings."""

    ks: float  #: constraint drift feedback on C (1/s^2)
    kd: float  #: constraint drift feedback on Cdot (1/s)
    tol: float  #: conjugate gradients' relative tolerance
    limit: float  #: divergence limit on |x| (m) and |v| (m/s)
    residual_limit: float  #: largest constraint residual (m) a step may leave (inf: none)


class Workspace(NamedTuple):
    """Scratch space reused by every call of one pack (sizes: n particles, m rows)."""

    spare_x: np.ndarray  #: (n, 2) a state buffer the step loop swaps in
    spare_v: np.ndarray  #: (n, 2)
    a1: np.ndarray  #: (n, 2) m/s^2, the accelerations of stages 1 to 4
    a2: np.ndarray  #: (n, 2)
    a3: np.ndarray  #: (n, 2)
    a4: np.ndarray  #: (n, 2)
    xs: np.ndarray  #: (n, 2) the stage (and new) state
    vs: np.ndarray  #: (n, 2)
    vs2: np.ndarray  #: (n, 2) the velocities of Runge-Kutta stages 1 and 2
    vs3: np.ndarray  #: (n, 2)
    x_mid: np.ndarray  #: (n, 2) the state between the two passes of a split step
    v_mid: np.ndarray  #: (n, 2)
    Jv: np.ndarray  #: (m, 4) the values of J
    Jdv: np.ndarray  #: (m, 4) the values of Jdot
    J0: np.ndarray  #: (m, 4) J at the step's start (RATTLE)
    C: np.ndarray  #: (m,) constraint values
    Cdot: np.ndarray  #: (m,)
    b: np.ndarray  #: (m,) right-hand side
    dl: np.ndarray  #: (m,) multiplier corrections (RATTLE)
    #: (2 n,) inverse mass per coordinate (set by each fused call at the constraint rows'
    #: coordinates, the only ones read, or at every coordinate for RATTLE)
    w2: np.ndarray
    tmp: np.ndarray  #: (2 n,) per-coordinate buffer, zero where read at the start of a call
    A: np.ndarray  #: (DIRECT_MAX, DIRECT_MAX) one dense component block
    work: np.ndarray  #: (DIRECT_MAX,) its solve's vector
    #: (m,) a vector over the positions of ``Rows.comp_rows`` (a sparse solve's)
    y: np.ndarray
    #: (nnz(L),) the values of the sparse-factorised components' Cholesky factors
    L: np.ndarray


def workspace(n: int, m: int, direct_max: int, factor: int = 0) -> tuple[np.ndarray, ...]:
    """The backing arrays of a zeroed :class:`Workspace` for ``n`` particles, ``m`` rows,
    dense component blocks of up to ``direct_max`` rows and ``factor`` entries of sparse
    Cholesky factors: one array per kind of field, (12, n, 2), (3, m, 4), (5, m), (2, 2 n),
    (direct_max + 1, direct_max) and (factor,), whose slices are the fields
    (:func:`workspace_ref` holds them by reference, :func:`workspace_view` names them in
    Python)."""
    return (np.zeros((12, n, 2)), np.zeros((3, m, 4)), np.zeros((5, m)), np.zeros((2, 2 * n)),
            np.zeros((direct_max + 1, direct_max)), np.zeros(factor))


def _name_workspace(per_particle: np.ndarray, per_entry: np.ndarray, per_row: np.ndarray,
                    per_coordinate: np.ndarray, dense: np.ndarray, factor: np.ndarray
                    ) -> Workspace:
    """The :class:`Workspace` whose fields are slices of the backing arrays (see
    :func:`workspace`), in field order."""
    d = dense.shape[1]
    return Workspace(per_particle[0], per_particle[1], per_particle[2], per_particle[3],
                     per_particle[4], per_particle[5], per_particle[6], per_particle[7],
                     per_particle[8], per_particle[9], per_particle[10], per_particle[11],
                     per_entry[0], per_entry[1], per_entry[2], per_row[0], per_row[1],
                     per_row[2], per_row[3], per_coordinate[0], per_coordinate[1], dense[:d],
                     dense[d], per_row[4], factor)


def workspace_view(backing: tuple[np.ndarray, ...]) -> Workspace:
    """The named :class:`Workspace` over the backing arrays of :func:`workspace`."""
    return _name_workspace(*backing)


class Elements(NamedTuple):
    """Per block type, the live elements of a split step (room for every element)."""

    gravity: np.ndarray
    constant: np.ndarray
    spring: np.ndarray
    angular: np.ndarray
    drag: np.ndarray
    wall: np.ndarray
    mouse: np.ndarray
    circle: np.ndarray
    rod: np.ndarray
    line: np.ndarray
    fixed: np.ndarray
    friction: np.ndarray
    tension: np.ndarray


#: Each block type's position in :class:`Blocks` and :class:`Elements`.
(GRAVITY, CONSTANT, SPRING, ANGULAR, DRAG, WALL, MOUSE, CIRCLE, ROD, LINE, FIXED, FRICTION,
 TENSION) = range(13)

#: Entries of :attr:`Live.sizes`: the numbers of live particles, rows and components, then
#: of live elements of each block type (from :data:`LIVE_ELEMENTS`, in the order of
#: :class:`Elements`), and last (:data:`LIVE_NEXT`) the next step at which the mask changes.
LIVE_PARTICLES, LIVE_ROWS, LIVE_COMPONENTS, LIVE_ELEMENTS = 0, 1, 2, 3
LIVE_NEXT = -1


class Live(NamedTuple):
    """The workspace of a step in which particles take different numbers of steps: which
    particles, rows, components and elements take the current one (``_gate`` fills it)."""

    mask: np.ndarray  #: (n,) bool, live particles
    particles: np.ndarray  #: (n,) int64, the live particles first
    rows: np.ndarray  #: (m,) int64, the live rows first
    components: np.ndarray  #: (components,) int64, the live components first
    sizes: np.ndarray  #: (4 + block types,) int64, see LIVE_PARTICLES ... LIVE_NEXT
    elements: Elements
    ptr: np.ndarray  #: (types, n + 1) int64: type t's elements of particle q (if ranged[t])
    ranged: np.ndarray  #: (types,) bool: elements ordered by first particle
    comp_of: np.ndarray  #: (2 n,) int64 component of each coordinate (-1: none)
    seen: np.ndarray  #: (components,) bool, zeroed marks


def plain(record: object) -> object:
    """``record`` with every named tuple in it (recursively) made a plain tuple: the form in
    which records cross into compiled code (see the module docstring)."""
    if isinstance(record, tuple):
        return tuple(plain(item) for item in record)
    return record


#: compiled: a :class:`RecordRef` to the :class:`Blocks` whose :func:`plain` form is given
blocks_ref: Callable[[tuple], object] | None = None
#: compiled: a :class:`RecordRef` to the :class:`Rows` whose :func:`plain` form is given
rows_ref: Callable[[tuple], object] | None = None
#: compiled: a :class:`RecordRef` to the :class:`Workspace` over the backing arrays of
#: :func:`workspace`
workspace_ref: Callable[..., object] | None = None
#: compiled: a :class:`RecordRef` to the :class:`Live` whose :func:`plain` form is given
live_ref: Callable[[tuple], object] | None = None
#: compiled: a :class:`RecordRef` to the :class:`Engine` of three records held by reference
#: (``blocks, rows, work``)
engine_ref: Callable[..., object] | None = None
#: compiled: a live set's ``(particles, rows, components, elements)`` (four Nones for None),
#: read once by a kernel before its loops
live_lists: Callable[[object], tuple] | None = None
#: compiled: a value with its arrays' reference counts detached (see ``_borrowed``)
borrowed: Callable[[object], object] | None = None
#: the Python handle of a record held by reference (compiled path only; see the module
#: docstring)
RecordRef: type | None = None

if kernels.ENABLED:
    from numba.core import cgutils, types
    from numba.experimental import structref
    from numba.extending import intrinsic, overload, typeof_impl
    from numba.np.arrayobj import make_array

    from .jit import njit

    def _strip(context: Any, builder: Any, ty: Any, value: Any) -> Any:
        """``value`` of type ``ty`` with every array in it (tuples recursively) carrying no
        reference count (null meminfo and parent): see :func:`_borrowed`."""
        if isinstance(ty, types.Array):
            ary = make_array(ty)(context, builder, value=value)
            ary.meminfo = cgutils.get_null_value(ary.meminfo.type)
            ary.parent = cgutils.get_null_value(ary.parent.type)
            return ary._getvalue()
        if isinstance(ty, types.BaseTuple):
            items = [_strip(context, builder, t, builder.extract_value(value, i))
                     for i, t in enumerate(ty.types)]
            return context.make_tuple(builder, ty, items)
        return value

    @intrinsic
    def _borrowed(typingctx: Any, value: Any) -> Any:  # pragma: no cover - compiled
        """``value`` (an array, a scalar, None or a nested tuple of them) with its arrays'
        reference counts detached: the same data, shapes and strides, but passing or
        unpacking them no longer costs an atomic increment and decrement each (a fused step
        passes some ninety arrays to each acceleration). Only for an entry point's own
        arguments, which the caller keeps alive for the whole call, and for a result that
        does not escape the call. Never for a record built inside the call: that is a
        temporary whose own references would then be dropped (the heap was corrupted so)."""
        def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
            return _strip(context, builder, value, args[0])
        return value(value), codegen

    borrowed = _borrowed

    # the record builders are inlined where they are called: compiled on their own, each took
    # a compile of its own (1-3 s, most of it moving its records' fields)
    @njit(inline="always")
    def _blocks_record(t):  # pragma: no cover - compiled
        """The :class:`Blocks` whose :func:`plain` form is ``t`` (fields in record order)."""
        return Blocks(GravityArrays(*t[GRAVITY]), ConstantArrays(*t[CONSTANT]),
                      SpringArrays(*t[SPRING]), AngularArrays(*t[ANGULAR]),
                      DragArrays(*t[DRAG]), WallArrays(*t[WALL]), MouseArrays(*t[MOUSE]),
                      CircleArrays(*t[CIRCLE]), RodArrays(*t[ROD]), LineArrays(*t[LINE]),
                      FixedArrays(*t[FIXED]), FrictionArrays(*t[FRICTION]),
                      TensionArrays(*t[TENSION]))

    @structref.register
    class RecordRefType(types.StructRef):
        """Numba's type of a record held by reference: the fields of a named tuple, in a
        reference-counted structure that crosses a call as one pointer."""

        def preprocess_fields(self, fields: Iterable[tuple[str, types.Type]]
                              ) -> tuple[tuple[str, types.Type], ...]:
            return tuple((name, types.unliteral(typ)) for name, typ in fields)

    class _RecordRef(structref.StructRefProxy):
        """A record held by reference, as Python holds it: opaque (compiled code reads its
        fields), immutable, and keeping its arrays alive (an array it holds cannot be
        resized in place meanwhile: NumPy refuses, as the array is referenced)."""

    structref.define_boxing(RecordRefType, _RecordRef)
    RecordRef = _RecordRef

    @typeof_impl.register(_RecordRef)
    def _typeof_record_ref(val: Any, c: Any) -> Any:
        """A record reference's Numba type, read directly: Numba's generic ``typeof`` first
        tries the buffer protocol (an exception raised and caught) before it reads
        ``_numba_type_``, which cost every call that passes a reference about 1.5 us."""
        return val._type

    def _by_reference(record: Any) -> Any:
        """``record`` (a named tuple) held by reference: a structure with the same fields
        (compiled only)."""
        raise NotImplementedError("compiled code only")

    @overload(_by_reference, inline="always")  # (straight-line code: no compile of its own)
    def _typed_by_reference(record):  # (no annotations: Numba compares them with impl's)
        """:func:`_by_reference` for the named tuple type of ``record``: a
        :class:`RecordRefType` with its fields, each set from the field of that name."""
        names = record.fields
        ref_type = RecordRefType(list(zip(names, record.types, strict=True)))
        lines = ["def impl(record):", "    ref = new(ref_type)"]
        lines += [f"    ref.{name} = record.{name}" for name in names]
        lines.append("    return ref")
        scope = {"new": structref.new, "ref_type": ref_type}
        exec("\n".join(lines), scope)  # (a field name is an attribute name: one line each)
        return scope["impl"]

    # A record held by reference holds its arrays borrowed (records.borrowed: no reference
    # counts): a field read in a kernel's loop then costs no atomic increment and decrement
    # per array. The arrays are kept alive by Python instead: each reference made below
    # holds the arrays it was made from (``_keep``, see _kept), and the caller of a kernel
    # holds the reference.
    @njit
    def _blocks_ref_compiled(t):  # pragma: no cover - compiled
        return _by_reference(borrowed(_blocks_record(t)))

    @njit
    def _rows_ref_compiled(t):  # pragma: no cover - compiled
        return _by_reference(borrowed(Rows(*t)))

    _workspace_named = njit(inline="always")(_name_workspace)

    @njit
    def _workspace_ref_compiled(per_particle, per_entry, per_row, per_coordinate, dense,
                                factor):  # pragma: no cover - compiled
        return _by_reference(borrowed(_workspace_named(per_particle, per_entry, per_row,
                                                       per_coordinate, dense, factor)))

    @njit(inline="always")
    def _live_record(t):  # pragma: no cover - compiled
        """The :class:`Live` whose :func:`plain` form is ``t`` (fields in record order)."""
        mask, particles, rows, components, sizes, elements, ptr, ranged, comp_of, seen = t
        return Live(mask, particles, rows, components, sizes, Elements(*elements), ptr, ranged,
                    comp_of, seen)

    def _live_lists(live: object) -> tuple:
        """``(live.particles, live.rows, live.components, live.elements)``, or four Nones
        for a None ``live`` (compiled only). A kernel reads them once, before its loops: a
        field of a record held by reference is loaded (and its reference counted) at every
        read."""
        raise NotImplementedError("compiled code only")

    @overload(_live_lists, inline="always")
    def _typed_live_lists(live):  # (no annotations: Numba compares them with impl's)
        if isinstance(live, types.NoneType):
            return lambda live: (None, None, None, None)
        return lambda live: (live.particles, live.rows, live.components, live.elements)

    def _kept(ref: Any, arrays: object) -> Any:
        """``ref`` holding ``arrays`` (what its borrowed fields point into) for as long as it
        lives."""
        ref._keep = arrays
        return ref

    def _blocks_ref(t: tuple) -> Any:
        return _kept(_blocks_ref_compiled(t), t)

    def _rows_ref(t: tuple) -> Any:
        return _kept(_rows_ref_compiled(t), t)

    def _workspace_ref(*backing: np.ndarray) -> Any:
        return _kept(_workspace_ref_compiled(*backing), backing)

    live_lists = _live_lists
    blocks_ref = _blocks_ref
    rows_ref = _rows_ref
    workspace_ref = _workspace_ref

    @njit
    def _live_ref_compiled(t):  # pragma: no cover - compiled
        return _by_reference(borrowed(_live_record(t)))

    def _live_ref(t: tuple) -> Any:
        return _kept(_live_ref_compiled(t), t)

    live_ref = _live_ref

    @njit
    def _engine_ref_compiled(blocks, rows, work):  # pragma: no cover - compiled
        return _by_reference(Engine(blocks, rows, work))

    def _engine_ref(blocks: Any, rows: Any, work: Any) -> Any:
        # (it holds the three references counted; their proxies hold the arrays)
        return _kept(_engine_ref_compiled(blocks, rows, work), (blocks, rows, work))

    engine_ref = _engine_ref
