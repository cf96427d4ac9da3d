"""ClothPin's compiled bookkeeping (Numba): its observation with the spring slots, its
measures and observation in one call, and the check of every copy's drawing in one pass.

The numpy references are ClothPin's own methods (``ClothPin.observe_reference``,
``ClothPin.place`` and ``ClothPin.resolve``); the tests tie each kernel to its reference. The
generic measures and observation these build on are in :mod:`envs._measure`. (A module of its
own beside ``cloth_pin.py``, which holds the task, its env classes and its declaration.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from . import _measure
from .checks import _owned

if TYPE_CHECKING:
    from .cloth_pin import ClothPin


class Pin(NamedTuple):
    """ClothPin's spring slots as its observation reads them (``ClothPin.observe``)."""

    slots: int  #: spring slots per copy (element ``i * slots + s`` is copy i's slot s)
    placed: np.ndarray  #: (N,) int64 springs placed per copy (slots below it are shown)
    i: np.ndarray  #: (N slots,) int64 each spring's first end (a particle of the system)
    j: np.ndarray  #: (N slots,) int64 its second end
    ks: np.ndarray  #: (N slots,) spring constants (N/m)
    rest: np.ndarray  #: (N slots,) rest lengths (m)
    ks_lo: float  #: the stiffness action's range of spring constants (N/m)
    ks_hi: float
    log_ratio: float  #: ``np.log(ks_hi / ks_lo)``
    count: int  #: the particles observed per copy (the cloth's, first in each copy)


class Drawing(NamedTuple):
    """What ClothPin's drawing check reads (``ClothPin.place``, ``ClothPin.resolve``)."""

    n: int  #: particles per copy: the cloth's, then the anchors
    cloth_n: int  #: the cloth's particles
    slots: int  #: the spring budget per copy
    cx: float  #: ``to_world(u) = c + h u`` (m)
    cy: float
    hx: float
    hy: float
    snap2: float  #: ``snap_radius ** 2`` (m^2)
    xmin: float  #: the anchor region (m)
    ymin: float
    xmax: float
    ymax: float



def pin_record(task: ClothPin, N: int, n: object, nc: object) -> tuple | None:
    """The spring slots of ``task``'s ``N`` copies of ``n`` particles, ``nc`` of them the
    cloth's (the observed ones), as the compiled observation reads them (:class:`Pin` in plain
    form); None where the numpy reference must run: sizes that are not ints with
    ``0 < nc <= n``, or arrays not of the shapes and types it reads."""
    B, sp, placed = task.max_springs, task.springs, task.placed  # (read once)
    si, sj, ks, rest = sp.i, sp.j, sp.ks, sp.rest
    if not (type(n) is int and type(nc) is int and type(B) is int and 0 < nc <= n
            and _owned(placed, np.int64, (N,)) and _owned(si, np.int64, (N * B,))
            and _owned(sj, np.int64, (N * B,)) and _owned(ks, np.float64, (N * B,))
            and _owned(rest, np.float64, (N * B,))):
        return None
    ks_range = task.ks_range
    lo, hi = ks_range
    ratio = task._log_ratio
    if ratio is None or ratio[0] is not ks_range:  # (made again when it is replaced)
        ratio = task._log_ratio = (ks_range, float(np.log(hi / lo)))
    return B, placed, si, sj, ks, rest, float(lo), float(hi), ratio[1], nc

def plan(task: ClothPin, newton: tuple[int, float]) -> np.ndarray | None:
    """``task.plan_distance()`` of every copy (m) by the compiled pass :data:`pin_plan`
    (``newton``: its most steps and force tolerance, N), or None where the numpy reference
    must run (compiled bookkeeping off, or arrays not of the shapes and types it reads)."""
    N, n, nc, B = task.num_envs, task.n, task.cloth_n, task.max_springs
    sp, flat, goal = task.springs, task.system.x, task.goal  # (read once)
    si, sj, ks, rest = sp.i, sp.j, sp.ks, sp.rest
    if not (pin_plan is not None and type(n) is int and type(nc) is int and type(B) is int
            and 0 < nc <= n and _owned(flat, np.float64, (N * n, 2))
            and _owned(goal, np.float64, (N,)) and _owned(si, np.int64, (N * B,))
            and _owned(sj, np.int64, (N * B,)) and _owned(ks, np.float64, (N * B,))
            and _owned(rest, np.float64, (N * B,))):
        return None
    return plan_checked(task, flat, (si, sj, ks, rest), (N, n, nc, B), goal, newton)


#: ``center`` for :data:`pin_plan` to compute the cloth's centre of mass itself
NO_CENTER = np.zeros(0)


def plan_checked(task: ClothPin, flat: np.ndarray, springs: tuple, sizes: tuple[int, ...],
                 goal: np.ndarray, newton: tuple[int, float]) -> np.ndarray | None:
    """:func:`plan` from arrays the caller read once and checked as :func:`plan` does
    (``sizes = (N, n, nc, B)``): the centre of mass is computed in the compiled pass (the
    task keeps :meth:`ClothPin.tracked` as written, and the cloth has at most 128 particles:
    numpy's order of additions), else by ``task.tracked``."""
    N, n, nc, B = sizes
    out = np.empty(N)
    if task._paths["plan_center"] and nc <= 128:
        center = NO_CENTER
    else:
        center = task.tracked(flat.reshape(N, n, 2))
    if pin_plan(flat, springs, n, nc, B, center, goal,
                (task.wall_x, float(task.nx * task.push), *newton), out):
        return out
    return None


#: the compiled observation (None when ``_measure.ENABLED`` is False)
pin_observe: Callable[..., bool] | None = None
#: the measures then the observation, in one call (None when ``_measure.ENABLED`` is False)
pin_measures_observe: Callable[..., bool] | None = None
#: the drawing check (None when ``_measure.ENABLED`` is False)
pin_draws: Callable[..., bool] | None = None
#: ``ClothPin.plan_distance`` (None when ``_measure.ENABLED`` is False)
pin_plan: Callable[..., bool] | None = None

if _measure.ENABLED:
    from constrained_particles.jit import njit
    from constrained_particles.records import borrowed

    from ._measure import Goal, Rest, View, _measures, _observe_particles, _unit

    @njit
    def _pin_fits(x, n, goal, pin, obs):  # pragma: no cover - compiled
        """True if :func:`_pin_observe` may read and write these arrays without bounds checks:
        ``N = len(goal)`` copies of ``n`` particles in ``x``, ``0 < pin.count <= n``, the slot
        arrays of ``N * slots`` springs (``placed`` of ``N``), every spring end a particle of
        ``x``, and ``obs`` of shape (N, 4 count + 1 + 7 slots)."""
        N, slots, count = goal.shape[0], pin.slots, pin.count
        si, sj = pin.i, pin.j
        if not (0 < count <= n and slots >= 0 and x.shape[0] >= N * n
                and pin.placed.shape[0] == N and si.shape[0] == N * slots
                and sj.shape[0] == N * slots and pin.ks.shape[0] == N * slots
                and pin.rest.shape[0] == N * slots
                and obs.shape[0] == N and obs.shape[1] == 4 * count + 1 + 7 * slots):
            return False
        total = x.shape[0]
        for e in range(si.shape[0]):
            if si[e] < 0 or si[e] >= total or sj[e] < 0 or sj[e] >= total:
                return False
        return True

    @njit
    def _pin_stiffness(ks, pin):  # pragma: no cover - compiled
        """The observed stiffness of spring constant ``ks`` (N/m): ``ClothPin._stiffness_seen``
        (``ks`` clipped into the range, then ``2 log(ks / lo) / log(hi / lo) - 1`` clipped to
        [-1, 1]; NaN stays NaN, as with ``np.minimum`` and ``np.maximum``)."""
        if ks < pin.ks_lo:
            ks = pin.ks_lo
        if ks > pin.ks_hi:
            ks = pin.ks_hi
        a = 2.0 * math.log(ks / pin.ks_lo) / pin.log_ratio - 1.0
        if a < -1.0:
            a = -1.0
        if a > 1.0:
            a = 1.0
        return a

    @njit
    def _pin_observe(x, v, n, goal, view, pin, obs):  # pragma: no cover - compiled
        """ClothPin's observation (``ClothPin.observe``) into ``obs`` (N, 4 count + 1 + 7
        slots) float32 (``view``: :class:`View`, ``pin``: :class:`Pin`): the first
        ``pin.count`` particles' ``(x - c) / h`` and ``v / h`` of each copy of ``n``, the
        goal's ``(goal - c_x) / h_x``, then per spring slot ``s`` of copy ``i`` (element
        ``i * slots + s``) ``(1, ends (x - c) / h, observed stiffness, rest / h_x)`` if
        ``s < placed[i]``, else zeros; each value computed in float64 (``ix, iy`` = 1 / h),
        rounded to float32 and clipped to ``[-limit, limit]``. The caller checked the arrays
        (:func:`_pin_fits`)."""
        hi = np.float32(view.limit)
        lo = np.float32(-view.limit)
        cx, cy, ix, iy = view.cx, view.cy, view.ix, view.iy
        count = pin.count
        _observe_particles(x, v, n, count, goal, cx, cy, ix, iy, lo, hi, obs)
        base = 4 * count + 1
        slots, placed, si, sj = pin.slots, pin.placed, pin.i, pin.j
        for i in range(goal.shape[0]):
            for s in range(slots):
                o = base + 7 * s
                if s < placed[i]:
                    e = i * slots + s
                    a, b = si[e], sj[e]
                    obs[i, o] = 1.0
                    obs[i, o + 1] = _unit((x[a, 0] - cx) * ix, lo, hi)
                    obs[i, o + 2] = _unit((x[a, 1] - cy) * iy, lo, hi)
                    obs[i, o + 3] = _unit((x[b, 0] - cx) * ix, lo, hi)
                    obs[i, o + 4] = _unit((x[b, 1] - cy) * iy, lo, hi)
                    obs[i, o + 5] = _unit(_pin_stiffness(pin.ks[e], pin), lo, hi)
                    obs[i, o + 6] = _unit(pin.rest[e] * ix, lo, hi)
                else:
                    for q in range(7):
                        obs[i, o + q] = 0.0

    @njit
    def _nearest(x, base, d, anchors, px, py):  # pragma: no cover - compiled
        """``ClothPin.resolve`` of the point ``(px, py)`` (m) in the copy whose particles start
        at ``base``: ``(nearest usable, its squared distance, nearest cloth particle)``, each
        the first of equals as ``np.argmin`` takes it (a NaN distance is the minimum)."""
        best, bd, best_nan = -1, np.inf, False
        cloth, cd, cloth_nan = -1, np.inf, False
        for q in range(d.n):
            dx = x[base + q, 0] - px
            dy = x[base + q, 1] - py
            d2 = dx * dx + dy * dy
            if q < d.cloth_n and not cloth_nan:
                if d2 != d2:
                    cloth, cloth_nan = q, True
                elif cloth < 0 or d2 < cd:
                    cloth, cd = q, d2
            if not (q < d.cloth_n or q - d.cloth_n < anchors):
                d2 = np.inf  # (an anchor not placed yet)
            if not best_nan:
                if d2 != d2:
                    best, bd, best_nan = q, d2, True
                elif best < 0 or d2 < bd:
                    best, bd = q, d2
        return best, bd, cloth

    @njit(nogil=True)
    def _pin_draws(x, actions, idle, placed, anchors_used, draw, ends, ok):
        # pragma: no cover - compiled
        """ClothPin's drawings checked, every copy in one pass (``draw``: a :class:`Drawing`
        in plain form): copy ``i`` draws (``actions[i, 5] > 0``, not ``idle[i]``) with room in
        its budget; its two ends (``to_world`` of ``actions[i, 0:2]`` and ``[2:4]``) resolve
        as ``ClothPin.resolve`` does (the particle within a copy, -2 for a new anchor) into
        ``ends[i]``; ``ok[i]`` if exactly one end is on the cloth and at most one is new.
        Returns False, writing nothing, unless the arrays hold ``N = len(actions)`` copies of
        ``d.n`` particles (``0 < d.cloth_n <= d.n``) and one entry per copy each."""
        d = Drawing(*draw)
        N = actions.shape[0]
        if not (0 < d.cloth_n <= d.n and x.shape[0] >= N * d.n and actions.shape[1] >= 6
                and idle.shape[0] == N and placed.shape[0] == N
                and anchors_used.shape[0] == N and ok.shape[0] == N
                and ends.shape[0] == N and ends.shape[1] == 2):
            return False
        for i in range(N):
            ok[i] = False
            ends[i, 0] = ends[i, 1] = -1
            if not actions[i, 5] > 0 or idle[i] or placed[i] >= d.slots:
                continue
            on_cloth, new = 0, 0
            for k in range(2):
                px = d.cx + d.hx * actions[i, 2 * k]
                py = d.cy + d.hy * actions[i, 2 * k + 1]
                best, bd, cloth = _nearest(x, i * d.n, d, anchors_used[i], px, py)
                if bd <= d.snap2:
                    end = best
                elif d.xmin <= px <= d.xmax and d.ymin <= py <= d.ymax:
                    end = -2
                else:
                    end = cloth
                ends[i, k] = end
                on_cloth += 0 <= end < d.cloth_n
                new += end == -2
            ok[i] = on_cloth == 1 and new <= 1
        return True

    @njit(nogil=True)
    def _pin_observe_entry(x, v, n, goal, view, pin, obs):  # pragma: no cover - compiled
        """:func:`_pin_observe` (False, writing nothing, unless :func:`_pin_fits`)."""
        slots = Pin(*pin)
        if not _pin_fits(x, n, goal, slots, obs):
            return False
        _pin_observe(x, v, n, goal, View(*view), slots, obs)
        return True

    @njit(nogil=True)
    def _pin_measures_observe_entry(state, task, blocks, walls, rest, stepped, blocked, out,
                                    success, view, pin, obs):
        # pragma: no cover - compiled
        """:func:`_measures`, then :func:`_pin_observe`: ClothPin's bookkeeping after a step
        in one call (False, writing nothing, unless :func:`_pin_fits`); ``state = (x, v,
        mass)``."""
        x, v, mass = state
        b_task, b_rest, b_pin = borrowed((task, rest, pin))
        slots, goal = Pin(*b_pin), Goal(*b_task)
        if not _pin_fits(x, goal.n, goal.goal, slots, obs):
            return False
        _measures(x, v, mass, goal, blocks, walls, Rest(*b_rest), stepped, blocked, out,
                  success)
        _pin_observe(x, v, goal.n, goal.goal, View(*view), slots, obs)
        return True

    @njit
    def _pairwise_sum(a, n):  # pragma: no cover - compiled
        """``np.sum`` of ``a[:n]`` with numpy's own order of additions (its pairwise sum, for
        ``n <= 128``: eight running sums, added to the reduction's identity ``0.0``, which
        makes a sum of ``-0.0`` ``+0.0``), so that the compiled pass gives numpy's bits."""
        if n < 8:
            res = 0.0
            for q in range(n):
                res += a[q]
            return res
        r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
        q = 8
        while q < n - n % 8:
            r0 += a[q]
            r1 += a[q + 1]
            r2 += a[q + 2]
            r3 += a[q + 3]
            r4 += a[q + 4]
            r5 += a[q + 5]
            r6 += a[q + 6]
            r7 += a[q + 7]
            q += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while q < n:
            res += a[q]
            q += 1
        return 0.0 + res

    @njit
    def _np_min(a, b):  # pragma: no cover - compiled
        """``np.minimum(a, b)`` of two numbers (NaN if either is)."""
        if a != a or b != b:
            return a + b
        return a if a <= b else b

    @njit(nogil=True)
    def _pin_plan(x, springs, n, nc, slots, center, goal, plan, out):
        # pragma: no cover - compiled
        """``ClothPin.plan_distance_reference`` of every copy into ``out`` (N,), with its
        arithmetic in its order (numpy's pairwise sums over the ``slots`` springs of a copy):
        the same bits. ``springs = (i, j, ks, rest)`` of ``N * slots`` springs, ``center`` the
        cloth's centre of mass x per copy (m; empty: computed here, as ``ClothPin.tracked``
        computes it, ``np.mean`` of the first ``nc`` particles' x, with numpy's order of
        additions, for ``nc <= 128``), ``plan = (wall_x, push, steps, tolerance)``.
        False, writing nothing, unless the arrays fit (N copies of ``n`` particles, ``0 < nc
        <= n``, spring ends particles of ``x``) and ``slots <= 128``."""
        si, sj, ks, rest = springs
        wall_x, push, steps, tol = plan
        N = goal.shape[0]
        if not (0 < nc <= n and 0 <= slots <= 128 and x.shape[0] == N * n
                and si.shape[0] == N * slots and sj.shape[0] == N * slots
                and ks.shape[0] == N * slots and rest.shape[0] == N * slots
                and (center.shape[0] == N or (center.shape[0] == 0 and nc <= 128))
                and out.shape[0] == N):
            return False
        for e in range(si.shape[0]):
            if si[e] < 0 or si[e] >= x.shape[0] or sj[e] < 0 or sj[e] >= x.shape[0]:
                return False
        ux = np.empty(slots)
        uy2 = np.empty(slots)
        k = np.empty(slots)
        pull = np.empty(slots)
        bend = np.empty(slots)
        own = center.shape[0] == 0
        cloth = np.empty(nc if own else 0)
        for c in range(N):
            base, e0 = c * n, c * slots
            if own:
                for q in range(nc):
                    cloth[q] = x[base + q, 0]
                mean = _pairwise_sum(cloth, nc) / nc
            else:
                mean = center[c]
            for b in range(slots):
                e = e0 + b
                sign = (1.0 if sj[e] - base < nc else 0.0) - (1.0 if si[e] - base < nc else 0.0)
                ux[b] = sign * (x[sj[e], 0] - x[si[e], 0])
                uy = sign * (x[sj[e], 1] - x[si[e], 1])
                uy2[b] = uy * uy
                k[b] = ks[e] if sign != 0 else 0.0
            top = x[base, 0]
            for q in range(base + 1, base + nc):
                v = x[q, 0]
                if v > top or v != v:  # (np.max: NaN wins)
                    if top == top:
                        top = v
            wall = wall_x - top
            shift = wall
            for step in range(steps):
                for b in range(slots):
                    sx = ux[b] + shift
                    length = math.sqrt(sx * sx + uy2[b])
                    if length < 1e-12:
                        length = 1e-12
                    r = rest[e0 + b]
                    pull[b] = k[b] * (length - r) * sx / length
                    bend[b] = k[b] * (1.0 - r * uy2[b] / (length * length * length))
                excess = push - _pairwise_sum(pull, slots)
                slope = -_pairwise_sum(bend, slots)
                if step == 0:
                    if not excess < 0:  # (the springs cannot stop it before the wall)
                        break
                elif abs(excess) < tol:
                    break
                if slope < 0:
                    shift = shift - excess / _np_min(slope, -1e-12)
            out[c] = abs(mean + _np_min(shift, wall) - goal[c])
        return True

    pin_plan = _pin_plan
    pin_observe = _pin_observe_entry
    pin_measures_observe = _pin_measures_observe_entry
    pin_draws = _pin_draws
