"""The fused compiled step: a whole explicit step of a standard system as one Numba call.

A system built only from the standard blocks (:class:`~.Gravity`, :class:`~.ConstantForce`,
:class:`~.DampedSpring`, :class:`~.AngularSpring`, :class:`~.Drag`, :class:`~.Wall`,
:class:`~.MouseSpring`, :class:`~.TableFriction`; :class:`~.CircularWire`, :class:`~.Rod`,
:class:`~.LineWire` / :class:`~.HorizontalWire`, :class:`~.FixedPoint`) is *packed* into flat
per-type arrays, and one compiled function then runs ``steps`` steps of ``euler``,
``midpoint``, ``rk4`` or ``symplectic_euler``: force accumulation (the elements of
:mod:`.kernels`), the constraint solve and the integrator update, with no Python between
blocks. It follows the reference path
(:meth:`ParticleSystem.acceleration` and :mod:`.integrators`) formula for formula; only the
order in which blocks' forces are summed differs (by type here, by block there), at the level
of rounding.

**The constraint solve.** The rows of ``J W J^T lam = -Jdot qdot - J W Q - ks C - kd Cdot`` are
split once per topology into connected components (rows that share a movable coordinate).
Components of up to :data:`DIRECT_MAX` rows are solved directly (dense Cholesky per component);
larger ones by a sparse Cholesky factorisation in the elimination order of :mod:`.ordering`
(:mod:`.factor_kernels`), or with ``solver="cg"`` by Jacobi-preconditioned conjugate gradients
per component, warm-started from the previous multipliers. Copies of a tiled scene are
therefore solved independently, and copy ``i`` of a batch reproduces the same scene stepped
alone bit for bit.

Anything the fused kernel cannot do exactly as the reference does (a singular or ill-posed
solve, CG that does not converge, an index out of range, a user-defined block, a subclass) is
handed back: the step then runs on the reference path, which raises the documented errors.

**Safety at the boundary.** The system reaches the kernel as a :class:`~.packing.Packed` form
(see :mod:`.packing`): the blocks' own arrays where possible, every index array immutable and
checked once when the pack is built; a call checks only what an in-place edit can change.

**The spring loop.** Springs go in blocks: the ends' differences are gathered into scratch
arrays, the element runs over the block (its square roots and divisions vectorize), and the
forces are added in spring order. Runs of springs whose ends both step by one (a cloth's rows,
columns and diagonals: :func:`spring_runs`, found once per topology and checked against the
index arrays when the pack is built) are read through contiguous slices instead, and each
particle's two sums from a run are written in one pass in the order the plain loop adds them,
so every path gives the plain loop's forces bit for bit.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from . import kernels, parallel
from .fused_accel import (
    DIVERGED,
    FALLBACK,
    FLAT_MIN,
    OK,
)
from .packing import (  # (the packing layer: its public names are this module's too)
    _F0,
    _NO_COUNTS,
    Packed,
    pack,
    spring_runs,  # noqa: F401
    supported,  # noqa: F401
)
from .records import (
    CIRCLE,
    FRICTION,
    LIVE_COMPONENTS,
    LIVE_ELEMENTS,
    LIVE_NEXT,
    LIVE_PARTICLES,
    LIVE_ROWS,
    MOUSE,
    TENSION,
    Settings,
    State,
    borrowed,
    live_lists,
)
from .solver import DIRECT_MAX

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

def integrator_args(method: str) -> tuple[int, bool | None]:
    """The arguments ``(method, rattle)`` by which the fused step is told the integrator
    ``method`` (a name in :data:`METHOD_CODES`): its code, and True for RATTLE, else None.
    The kernel is compiled once per pattern of None: RATTLE, which has its own step, is
    compiled only by a run that uses it. The explicit methods (euler, midpoint, rk4,
    symplectic_euler) share one version and choose by code at run time, so a run of another
    explicit method loads the step loop from the cache instead of compiling it again
    (docs/compile_time.md). The tableaus stay compile-time constants."""
    return _INTEGRATOR_ARGS[method]


#: :func:`integrator_args` of every method, made once
_INTEGRATOR_ARGS = {name: (code, True if name == "rattle" else None)
                    for name, code in METHOD_CODES.items()}


def schedule(steps: int, h: float) -> tuple[int, float, np.ndarray, np.ndarray]:
    """The ``schedule`` argument of :func:`fused_steps` for ``steps`` steps of ``h`` seconds
    (no step counted to a separate rate)."""
    return (steps, h, _F0, _NO_COUNTS)


#: ``(x, v, mass, inv_mass)`` as a caller read them from the system
StateArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def prepare(system: ParticleSystem, lam: np.ndarray, residual_limit: float,
            state: StateArrays | None = None, checked: bool = False
            ) -> tuple[Packed, State, Settings] | None:
    """What :func:`fused_steps` needs of ``system``: its :class:`Packed` form (whose
    :attr:`~.packing.Packed.refs` it takes), the :class:`~.records.State` to step (``x, v,
    mass, inv_mass`` read from the system once, or the caller's ``state`` read once by it, and
    the warm start ``lam``) and the :class:`~.records.Settings` (the system's, with
    ``residual_limit``); or None where the kernel cannot run: unsupported blocks, an index out
    of range, a parameter array whose shape changed in place, or state arrays (and ``lam``)
    not C-ordered float64 of the packed sizes. The kernel's memory safety rests on these
    checks (O(1) per array: the arrays the kernel indexes with were checked when the pack was
    built, and cannot change; the mouse springs' particles and flags are copied here).
    ``checked``: ``ParticleSystem._check_state`` returned True on this very ``state`` (exact
    float64 ndarrays, ``x`` and ``v`` of one (n, 2) shape, ``mass`` and ``inv_mass`` of
    (n,)), so only what that leaves open is checked here: the kernel's memory safety then
    rests on that check too."""
    p = pack(system)
    if not (p.valid and p.shapes_hold()):  # unsupported blocks, an index out of range, or
        return None  # a parameter array reshaped in place
    if p._refresh:
        p.refresh()
    if state is None:
        state = system.x, system.v, system.mass, system.inv_mass
    x, v, mass, inv_mass = state
    nd, f64 = np.ndarray, np.float64
    if checked:  # (float64 arrays of matching shapes: only contiguity and sizes are left)
        if not (type(lam) is nd and lam.dtype == f64 and lam.flags.c_contiguous
                and x.flags.c_contiguous and v.flags.c_contiguous and mass.flags.c_contiguous
                and inv_mass.flags.c_contiguous and len(x) == p.n and len(mass) == p.n
                and len(inv_mass) == p.n and lam.shape == (p.m,)):
            return None
    elif not (type(x) is nd and type(v) is nd and type(mass) is nd and type(inv_mass) is nd
              and type(lam) is nd and x.dtype == f64 and v.dtype == f64 and mass.dtype == f64
              and inv_mass.dtype == f64 and lam.dtype == f64 and x.flags.c_contiguous
              and v.flags.c_contiguous and mass.flags.c_contiguous
              and inv_mass.flags.c_contiguous and lam.flags.c_contiguous
              and x.shape == v.shape == (p.n, 2) and lam.shape == (p.m,)
              and mass.shape == inv_mass.shape == (p.n,)):
        return None
    if not p.take_mouse():
        return None
    return p, State(x, v, mass, inv_mass, lam), p.settings(system, residual_limit)


def run(system: ParticleSystem, dt: float, method: str, steps: int, lam: np.ndarray,
        residual_limit: float, pieces: np.ndarray | None = None,
        state: StateArrays | None = None, checked: bool = False
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
    that an attribute replaced meanwhile by another thread is never read; ``checked`` as for
    :func:`prepare`.
    """
    ready = prepare(system, lam, residual_limit, state, checked)
    if ready is None:
        return FALLBACK, None, None, 0
    p, start, settings = ready
    # (the pack, current and refreshed for this call: see envs._measure.packed)
    system.__dict__["_fresh_pack"] = p
    code, rattle = integrator_args(method)
    h = float(dt)
    if pieces is not None and (pieces.shape != (p.n,) or pieces.dtype != np.int64):
        return FALLBACK, None, None, 0
    threads = system.__dict__.get("_threads", 1)
    if (threads > 1 and (part := parallel.partition(system, p, threads)) is not None
            and part.take_mouse()):
        return _run_ranges(part, code, rattle, h, int(steps), pieces, start, settings)
    refs = p.refs
    x_out = np.empty_like(start.x)
    v_out = np.empty_like(start.v)
    if pieces is None:
        status, failed = fused_steps(code, rattle, *p.variant, (int(steps), h, _F0, _NO_COUNTS),
                                     tuple(start), (x_out, v_out), tuple(settings), refs.engine,
                                     None)
        return int(status), x_out, v_out, int(failed)
    status, failed = fused_split(code, rattle, *p.variant, (h, h / pieces, pieces * int(steps)),
                                 tuple(start), (x_out, v_out), tuple(settings), refs.engine,
                                 p.live_ref)
    return int(status), x_out, v_out, int(failed)


def _run_ranges(part: parallel.Partition, code: int, rattle: Any, h: float, steps: int,
                pieces: np.ndarray | None, start: State, settings: Settings
                ) -> tuple[int, np.ndarray, np.ndarray, int]:
    """:func:`run` with the system's particles cut into ``part``'s ranges, each stepped by the
    kernel on a thread of its own (:mod:`.parallel`): the same status and the same bits as one
    call over the whole system. The warm start of a range's rows is gathered into an array of
    its own and written back only when every range succeeded."""
    x, v, mass, inv_mass, lam = start
    x_out, v_out = np.empty_like(x), np.empty_like(v)
    plain_settings = tuple(settings)
    if pieces is not None:
        hp, counts = h / pieces, pieces * steps
    calls, lams = [], []
    for sp, (lo, hi), rows in zip(part.packs, part.spans, part.rows, strict=True):
        if sp._refresh:
            sp.refresh()
        lam_r = lam[rows]
        lams.append(lam_r)
        state = (x[lo:hi], v[lo:hi], mass[lo:hi], inv_mass[lo:hi], lam_r)
        if pieces is None:
            calls.append(functools.partial(
                fused_steps, code, rattle, *sp.variant, (steps, h, _F0, _NO_COUNTS), state,
                (x_out[lo:hi], v_out[lo:hi]), plain_settings, sp.refs.engine, None))
        else:
            calls.append(functools.partial(
                fused_split, code, rattle, *sp.variant, (h, hp[lo:hi], counts[lo:hi]), state,
                (x_out[lo:hi], v_out[lo:hi]), plain_settings, sp.refs.engine, sp.live_ref))
    results = part.run(calls, steps)
    failed = [(int(done), int(status) == DIVERGED) for status, done in results
              if int(status) != OK]
    if not failed:
        for rows, lam_r in zip(part.rows, lams, strict=True):
            lam[rows] = lam_r
        return OK, x_out, v_out, int(results[0][1])
    # The range that failed first decides, as in one call over the whole system, which
    # stops at its first failing step: a divergence there, else the reference path (a
    # range that falls back at a step another diverges at falls back: the reference path
    # then finds the divergence itself). With split steps (``pieces``) the ranges count
    # steps of their own lengths, and the step named may differ from one call's.
    step, diverged = min(failed)
    return (DIVERGED, None, None, step) if diverged else (FALLBACK, None, None, 0)


if kernels.ENABLED:
    from .fused_accel import (
        _accel,
        _beyond_flat,
        _check_inputs,
        _copy_flat,
        _count,
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

    @njit(inline="always")
    def _live_fits(live, blocks, n, m, ncomp):  # pragma: no cover - compiled
        """True if the live workspace has room for ``n`` particles, ``m`` rows, ``ncomp``
        components and every element of each block type."""
        types = len(live.elements)  # (one entry per block type)
        if not (live.mask.shape[0] == n and live.particles.shape[0] == n
                and live.rows.shape[0] == m and live.components.shape[0] == ncomp
                and live.sizes.shape[0] == LIVE_ELEMENTS + types + 1
                and live.ptr.shape == (types, n + 1) and live.ranged.shape[0] == types
                and live.comp_of.shape[0] == 2 * n and live.seen.shape[0] == ncomp):
            return False
        el = live.elements
        return (el.gravity.shape[0] >= blocks.gravity.particles.shape[0]
                and el.constant.shape[0] >= blocks.constant.particles.shape[0]
                and el.spring.shape[0] >= blocks.spring.i.shape[0]
                and el.angular.shape[0] >= blocks.angular.a.shape[0]
                and el.drag.shape[0] >= blocks.drag.particles.shape[0]
                and el.wall.shape[0] >= blocks.wall.particles.shape[0]
                and el.mouse.shape[0] >= blocks.mouse.particle.shape[0]
                and el.circle.shape[0] >= blocks.circle.particles.shape[0]
                and el.rod.shape[0] >= blocks.rod.a.shape[0]
                and el.line.shape[0] >= blocks.line.particles.shape[0]
                and el.fixed.shape[0] >= blocks.fixed.particles.shape[0]
                and el.friction.shape[0] >= blocks.friction.particles.shape[0]
                and el.tension.shape[0] >= blocks.tension.i.shape[0])

    @njit(inline="always")
    def _work_fits(ws, rows, n, m):  # pragma: no cover - compiled
        """True if the workspace has the shapes of ``n`` particles, ``m`` rows and the
        sparse factors planned in ``rows``."""
        for a in (ws.spare_x, ws.spare_v, ws.a1, ws.a2, ws.a3, ws.a4, ws.xs, ws.vs, ws.vs2,
                  ws.vs3, ws.x_mid, ws.v_mid):
            if a.shape != (n, 2):
                return False
        for a in (ws.Jv, ws.Jdv, ws.J0):
            if a.shape != (m, 4):
                return False
        for a in (ws.C, ws.Cdot, ws.b, ws.dl, ws.y):
            if a.shape[0] != m:
                return False
        if rows.lptr.shape[0] != m + 1 or ws.L.shape[0] != rows.lptr[m]:
            return False
        return (ws.w2.shape[0] == 2 * n and ws.tmp.shape[0] == 2 * n
                and ws.A.shape == (DIRECT_MAX, DIRECT_MAX) and ws.work.shape[0] == DIRECT_MAX)

    @njit
    def _gate(step, counts, rows, blocks, live):  # pragma: no cover - compiled
        """Which particles take step ``step`` (those with ``counts`` above it): the mask
        ``live.mask`` and, when it changed, the lists of live particles, rows, components
        and elements of each block type, with their numbers in ``live.sizes``, whose last
        entry (``LIVE_NEXT``) keeps the next step at which the mask changes (until then
        nothing is scanned)."""
        mask, plist, rlist, clist, sizes = (live.mask, live.particles, live.rows,
                                            live.components, live.sizes)
        if step > 0 and step < sizes[LIVE_NEXT]:
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
        sizes[LIVE_NEXT] = upcoming
        if step > 0 and flips == 0:
            return
        k = 0  # (branch-free, as in _firsts)
        for q in range(mask.shape[0]):
            plist[k] = q
            k += mask[q]
        sizes[LIVE_PARTICLES] = k
        # the live components (those of the live particles' coordinates: a component's
        # particles share a count), then their rows, in order within each component (so each
        # coordinate gets its rows' terms in row order, as on the path without a mask)
        comp_of, seen = live.comp_of, live.seen
        comp_rows, comp_ptr = rows.comp_rows, rows.comp_ptr
        ncomp = comp_ptr.shape[0] - 1
        k = 0
        for i in range(sizes[LIVE_PARTICLES]):
            q = plist[i]
            for col in range(2 * q, 2 * q + 2):
                c = comp_of[col]
                if c >= 0 and c < ncomp and not seen[c]:
                    seen[c] = True
                    clist[k] = c
                    k += 1
        sizes[LIVE_COMPONENTS] = k
        j = 0
        for kk in range(k):
            c = clist[kk]
            seen[c] = False
            for a in range(comp_ptr[c], min(comp_ptr[c + 1], comp_ptr[c] + rlist.shape[0] - j)):
                rlist[j] = comp_rows[a]
                j += 1
        sizes[LIVE_ROWS] = j
        live_n = sizes[LIVE_PARTICLES]
        el = live.elements
        firsts = (blocks.gravity.particles, blocks.constant.particles, blocks.spring.i,
                  blocks.angular.a, blocks.drag.particles, blocks.wall.particles)
        lists = (el.gravity, el.constant, el.spring, el.angular, el.drag, el.wall)
        for t in range(6):  # (a loop, not six calls with constants: one compiled version)
            sizes[LIVE_ELEMENTS + t] = _live_elements(t, firsts[t], mask, plist, live_n, live,
                                                      lists[t])
        k = 0  # mouse springs: only active ones have a particle to ask about (a grab replaces
        mi, active = blocks.mouse.particle, blocks.mouse.active  # the particle array, so they
        for e in range(mi.shape[0]):  # are always scanned)
            if active[e] and mask[mi[e]]:
                el.mouse[k] = e
                k += 1
        sizes[LIVE_ELEMENTS + MOUSE] = k
        firsts = (blocks.circle.particles, blocks.rod.a, blocks.line.particles,
                  blocks.fixed.particles)
        lists = (el.circle, el.rod, el.line, el.fixed)
        for t in range(4):
            sizes[LIVE_ELEMENTS + CIRCLE + t] = _live_elements(CIRCLE + t, firsts[t], mask,
                                                               plist, live_n, live, lists[t])
        sizes[LIVE_ELEMENTS + FRICTION] = _live_elements(
            FRICTION, blocks.friction.particles, mask, plist, live_n, live, el.friction)
        sizes[LIVE_ELEMENTS + TENSION] = _live_elements(TENSION, blocks.tension.i, mask, plist,
                                                        live_n, live, el.tension)

    @njit
    def _live_elements(t, idx, mask, plist, live_n, live, out):
        # pragma: no cover - compiled
        """The live elements of block type ``t`` (first particles ``idx``) into ``out``, in
        element order; their number. For a type ordered by first particle
        (``live.ranged[t]``), the ranges ``live.ptr[t, q]:live.ptr[t, q + 1]`` of the
        ``live_n`` live particles in ``plist`` (clipped to ``out``'s length); otherwise a scan
        of every element (:func:`_firsts`)."""
        ptr = live.ptr
        if not live.ranged[t]:
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

    @njit(nogil=True)
    def fused_steps(method, rattle, large, runs, extra, schedule, state, out, settings, engine,
                    live):  # pragma: no cover - compiled
        """With ``schedule = (steps, h, hp, counts)`` and ``out = (x_out, v_out)``:
        ``steps`` steps of ``h`` seconds from ``state`` into ``x_out, v_out``, or of
        ``hp[q]`` seconds for particle q if ``hp`` is not empty, with the integrator that
        ``method, rattle`` give as :func:`integrator_args` makes them: RATTLE if ``rattle`` is
        not None (Numba compiles a version per pattern of None and drops the other branches
        from it), else ``method``: 0 euler, 3 symplectic_euler, or the explicit Runge-Kutta
        method 1 midpoint, 2 rk4 (one stage loop over its tableau). ``large, runs, extra``
        are the pack's :attr:`~.packing.Packed.variant`: None where no constraint component
        has more than ``DIRECT_MAX`` rows (the version for None compiles neither the sparse
        factorisation nor conjugate gradients), where no springs form runs (no run loop), and
        where the system has no angular springs, mouse springs or fixed points (none of their
        loops). Returns
        ``(status, steps done)``. Reads ``state`` and writes ``x_out, v_out`` only (the
        first step reads the caller's state, the last writes the caller's output).

        The records come as the pack holds them: its ``blocks``, ``rows`` and workspace in one
        :class:`~.records.Engine` by reference (:attr:`~.packing.Packed.refs`), the others in
        :func:`~.records.plain` form, rebuilt here: ``State(*state)`` (its ``lam`` is the warm
        start, updated in place) and ``Settings(*settings)``. Every array here lives in the
        caller for the whole call, so the plain records are built from borrowed arrays
        (:func:`~.records.borrowed`): passing and unpacking them costs no reference counting.

        ``live`` is None (every particle takes every step; ``counts`` is empty, or has one
        entry per particle and is ignored) or the pack's live workspace
        (:attr:`~.packing.Packed.live_ref`, the workspace of :func:`_gate`): particle q then
        takes only ``counts[q]`` of the steps (a particle with fewer waits, and the elements,
        constraint rows and components of waiting particles are skipped).
        :func:`fused_split` runs a split step so. ``live`` itself is never reassigned and is
        what the None tests read: Numba then drops the branches that a None ``live`` rules
        out, so a run without pieces compiles no masked step.

        The entry and the step loop are one function: each compiled function that calls
        another has the callee's code optimised again inside its own (docs/compile_time.md),
        so a level between the entry and the loop would optimise the acceleration once more."""
        steps, h, hp, counts = schedule
        b_hp, b_counts, b_state, b_out = borrowed((hp, counts, state, out))
        start, xo, vo = State(*b_state), b_out[0], b_out[1]
        cfg = Settings(*settings)
        blocks, rows, ws = engine.blocks, engine.rows, engine.work
        n = start.x.shape[0]
        m = start.lam.shape[0]
        per_particle = b_hp.shape[0] > 0
        shape = start.x.shape
        if (shape[1] != 2 or start.v.shape != shape or xo.shape != shape or vo.shape != shape
                or start.mass.shape[0] != n or start.inv_mass.shape[0] != n):
            return FALLBACK, 0
        if per_particle and (rattle is not None or b_hp.shape[0] != n):
            return FALLBACK, 0
        if live is not None and (not per_particle or b_counts.shape[0] != n
                                 or not _live_fits(live, blocks, n, m,
                                                   rows.comp_ptr.shape[0] - 1)):
            return FALLBACK, 0
        if live is None and b_counts.shape[0] != 0 and b_counts.shape[0] != n:
            return FALLBACK, 0
        if not _check_inputs(blocks, rows, n, m, start.lam, b_counts, extra):
            return FALLBACK, 0
        if not _work_fits(ws, rows, n, m):
            return FALLBACK, 0
        w2, tmp, inv_mass = ws.w2, ws.tmp, start.inv_mass
        if rattle is None:  # w2 and tmp are read only at the constraint rows' coordinates:
            cols, nnz = rows.cols, rows.nnz  # O(rows) instead of O(particles) per call
            for r in range(m):
                for k in range(nnz[r]):
                    c = cols[r, k]
                    w2[c] = inv_mass[c // 2]
                    tmp[c] = 0.0
        else:  # RATTLE's corrections run over every coordinate
            for q in range(n):
                w2[2 * q] = inv_mass[q]
                w2[2 * q + 1] = inv_mass[q]
                tmp[2 * q] = 0.0
                tmp[2 * q + 1] = 0.0
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        x0, v0 = start.x, start.v
        a1, a2, a3, a4 = ws.a1, ws.a2, ws.a3, ws.a4
        limit = cfg.limit
        # the first step reads the caller's state, the last writes the caller's output: no
        # copies in or out, and x0, v0 are never written (the state before the call is kept)
        x, v = x0, v0
        xs, vs = ws.xs, ws.vs
        spare_x, spare_v = ws.spare_x, ws.spare_v
        if live is not None:  # a particle that waits is never read by the steps it sits out
            _copy_flat(x0, xo)  # (its forces and rows are those of waiting particles only):
            _copy_flat(v0, vo)  # it waits in the output, written when it stops stepping
        for step in range(steps):
            if step == steps - 1:
                xs, vs = xo, vo
            if live is not None:
                if step > 0 and step >= live.sizes[LIVE_NEXT]:  # some stop here
                    mask = live.mask
                    for q in range(n):
                        if mask[q] and step >= b_counts[q]:
                            xo[q, 0], xo[q, 1] = x[q, 0], x[q, 1]
                            vo[q, 0], vo[q, 1] = v[q, 0], v[q, 1]
                _gate(step, b_counts, rows, blocks, live)
            if rattle is not None:
                # (a step after the first starts where the one before ended: fresh factors)
                if not _rattle(x, v, xs, vs, h, start, cfg, engine, large, runs, extra,
                               step > 0):
                    return FALLBACK, step
            elif method == 0 or method == 3:  # euler / symplectic_euler
                if not _accel(x, v, a1, start, cfg, blocks, rows, ws, live, large, runs,
                              extra):
                    return FALLBACK, step
                flat = live is None and not per_particle and n >= FLAT_MIN
                if flat:
                    _euler_flat(method == 0, h, x, v, a1, xs, vs)
                for i in range(0 if flat else _count(live, LIVE_PARTICLES, n)):
                    q = i if live is None else lp[i]
                    hq = b_hp[q] if per_particle else h
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
                kv = (ws.vs2, ws.vs3, vs)  # the velocities of stages 1, 2, 3 (stage 0's is v)
                ka = (a1, a2, a3, a4)  # the accelerations of stages 0, 1, 2, 3
                for stage in range(stages):
                    if stage > 0:  # its state: y + h sum_j A[stage, j] k_j (nonzero terms)
                        out_v = kv[stage - 1]
                        for i in range(_count(live, LIVE_PARTICLES, n)):
                            q = i if live is None else lp[i]
                            hq = b_hp[q] if per_particle else h
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
                    if not _accel(sx, sv, ka[stage], start, cfg, blocks, rows, ws, live,
                                  large, runs, extra):
                        return FALLBACK, step
                # y + (h / d) sum_j w_j k_j, summed left to right over the nonzero weights
                for i in range(_count(live, LIVE_PARTICLES, n)):
                    q = i if live is None else lp[i]
                    scale = (b_hp[q] if per_particle else h) / tab_d
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
                for i in range(_count(live, LIVE_PARTICLES, n)):  # (waiting particles are
                    q = i if live is None else lp[i]  # unchanged since they passed)
                    for d in range(2):
                        if not (abs(xs[q, d]) < limit and abs(vs[q, d]) < limit):
                            return DIVERGED, step
            if cfg.residual_limit < math.inf and m:
                if not _distance_error(xs, blocks, live, extra) <= cfg.residual_limit:
                    return DIVERGED, step
            if step == 0:  # the new state becomes current; never reuse the caller's arrays
                x, xs = xs, spare_x
                v, vs = vs, spare_v
            else:
                x, xs = xs, x
                v, vs = vs, v
        if steps == 0:  # (copied in loops: a slice assignment compiles Numba's error messages)
            _copy_flat(x0, xo)
            _copy_flat(v0, vo)
        return OK, steps

    @njit(nogil=True)
    def fused_split(method, rattle, large, runs, extra, schedule, state, out, settings, engine,
                    live):  # pragma: no cover - compiled
        """A split step: with ``schedule = (h, hp, counts)``, particle q takes ``counts[q]``
        steps of ``hp[q]`` seconds (the other arguments as for :func:`fused_steps`, ``live``
        the pack's live workspace). First the steps only
        some particles take (masked), while their data are likely still in cache from the
        last call, then every particle's common steps (unmasked). Each particle takes its own
        steps in its own order, so the order of the two passes changes no bit, and each
        independent group of particles is stepped exactly as it would be alone."""
        h, hp, counts = schedule
        b_hp, b_counts, b_state, b_out = borrowed((hp, counts, state, out))
        n = b_state[0].shape[0]
        if b_counts.shape[0] != n:
            return FALLBACK, 0
        if n == 0:
            return OK, 0
        first, total = b_counts.min(), b_counts.max()
        if first == total:  # every particle takes every step
            return fused_steps(method, rattle, large, runs, extra, (total, h, b_hp, b_counts),
                               b_state, b_out, settings, engine, None)
        ws = engine.work
        x_mid, v_mid = ws.x_mid, ws.v_mid
        status, done = fused_steps(method, rattle, large, runs, extra,
                                   (total - first, h, b_hp, b_counts - first), b_state,
                                   (x_mid, v_mid), settings, engine, live)
        if status != OK:
            return status, done
        middle = (x_mid, v_mid, b_state[2], b_state[3], b_state[4])
        status, more = fused_steps(method, rattle, large, runs, extra,
                                   (first, h, b_hp, b_counts), middle, b_out, settings, engine,
                                   None)
        return status, done + more
