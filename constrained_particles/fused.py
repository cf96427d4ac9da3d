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

**Safety at the boundary.** The system reaches the kernel as a :class:`~.packing.Packed` form
(see :mod:`.packing`): the blocks' own arrays where possible, every index array immutable and
checked once when the pack is built; a call checks only what an in-place edit can change.

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
from .fused_accel import (
    DIVERGED,
    FALLBACK,
    FLAT_MIN,
    OK,
)
from .packing import (  # (the packing layer: its public names are this module's too)
    _ELEMENT_TYPES,
    _F0,
    _NO_COUNTS,
    Packed,
    pack,
    spring_runs,  # noqa: F401
    supported,  # noqa: F401
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
