"""Compiled per-step bookkeeping of the environments (Numba): measures and observations.

One env step of a small scene costs little physics once the step is compiled; what is left is
the bookkeeping around it. The kernels here do that bookkeeping for every copy of a tiled task
in one call each, with no Python between:

- the measures (``_measures``, which every entry below computes): per copy, the RMS particle
  speed (m/s), kinetic energy (J), the largest geometric constraint residual (m, see
  ``Constraint.distance_error``), the distance (m) from the tracked x coordinate (the mean x of
  some particles) or point to the goal, optionally the walls' total contact force (N), and the
  update of the count of consecutive steps at the goal (the rest test);
- :func:`observe`: the float32 observation (normalized positions, velocities, goal), clipped.

They read the system's blocks through :func:`constrained_particles.fused.pack`, so they see
exactly the blocks (and the in-place edits) the compiled step sees, and the wall formula is the
shared compiled element ``kernels.wall_element``. The numpy code in :mod:`envs.base` stays the
reference implementation: it runs when ``CPARTICLES_NUMBA=0`` (``ENABLED`` is then False) or a
system holds blocks the compiled step does not know, and the tests tie the two together.

Copies are independent: every value of copy ``i`` is computed from copy ``i``'s particles
alone, in the same order whatever the number of copies, so a vector env's copy ``i`` still
reproduces a single env bit for bit.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from constrained_particles import kernels
from constrained_particles.fused import pack

ENABLED = kernels.ENABLED  #: True when the compiled bookkeeping is in use


class Goal(NamedTuple):
    """What the success test of a task's copies reads."""

    n: int  #: particles per copy
    goal: np.ndarray  #: (N,) float64, each copy's goal x (m)
    track: np.ndarray  #: tracked particles (indices within a copy), whose mean x meets the goal
    track_scale: float  #: 1 / len(track)
    tolerance: float  #: goal tolerance (m)
    rest_speed: float  #: rest speed (m/s)
    hold_steps: int  #: consecutive settled steps for success
    #: NaN: the distance to the goal is along x (the tracked mean x to ``goal``); else the
    #: goal is the point ``(goal, height)`` (m) and the distance is from the tracked particles'
    #: mean point to it
    height: float
    #: the first ``count`` particles of a copy (all ``n`` but in a task with extra particles,
    #: such as ClothPin's anchors) make its speed (their RMS speed) and its rest test
    count: int
    #: with ``walls``, a copy touching a wall is not at rest (its hold count restarts)
    wall_rest: bool


class Rest(NamedTuple):
    """The rest test's state (``ParticleTask.advance_rest``), updated in place."""

    hold: np.ndarray  #: (N,) int64 consecutive settled steps
    mean_v: np.ndarray  #: (N n, 2) each particle's moving average velocity (m/s)
    alpha: float  #: the average's weight, 1 / rest_window


class View(NamedTuple):
    """How the observation normalizes: ``(x - c) / h`` and ``v / h``, clipped."""

    cx: float  #: view centre (m)
    cy: float
    ix: float  #: 1 / half-width (1/m)
    iy: float  #: 1 / half-height (1/m)
    limit: float  #: clip bound


class Crank(NamedTuple):
    """SliderCrank's crank geometry and per-copy crank measures (outputs filled in place)."""

    r: float  #: crank radius (m)
    r2: float  #: r^2 (m^2)
    rod2: float  #: rod length squared (m^2)
    height: np.ndarray  #: (N,) out: the crank's y (m)
    to_go: np.ndarray  #: (N,) out: arc length to the goal's crank angle (m)
    below: np.ndarray  #: (N,) bool out: the crank is not above the slider's wire
    seen: np.ndarray  #: (N,) the goals the angles in ``target`` were computed for (NaN: none)
    target: np.ndarray  #: (N,) the goal's crank angle (rad)


class Reward(NamedTuple):
    """The shaped reward ``(before - Phi) scale - time_cost + bonus [success]``."""

    before: np.ndarray  #: (N,) the potentials of the last step, updated in place
    scale: float
    time_cost: float
    bonus: float
    reward: np.ndarray  #: (N,) out


class Episode(NamedTuple):
    """The episode counters of a step every copy took (updated in place)."""

    steps: np.ndarray  #: (N,) int64 steps taken
    max_steps: int
    terminated: np.ndarray  #: (N,) bool out
    truncated: np.ndarray  #: (N,) bool out
    ended: np.ndarray  #: (N,) bool out


class Finish(NamedTuple):
    """Everything :func:`crank_finish` writes after SliderCrank's physics step."""

    crank: Crank
    task: Goal
    rest: Rest
    every: np.ndarray  #: (N,) bool, all True: the copies that stepped
    out: np.ndarray  #: (5, N) out: the measures' rows (``_measures``)
    success: np.ndarray  #: (N,) bool out
    frame: View  #: the observation's normalization
    obs: np.ndarray  #: (N, 4 n + 1) float32 out
    reward: Reward
    episode: Episode


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


def packed(system: Any) -> Any:
    """The system's compiled description (``fused.Packed``), or None when the compiled
    bookkeeping is off or does not cover the system (then the numpy reference runs)."""
    if not ENABLED:
        return None
    p = pack(system)
    if not p.valid:
        return None
    # several blocks of one type: bring the joined parameters the measures read up to date
    p.refresh(measured_only=True)
    return p


observe: Any = None  #: the compiled observation kernel (None when ``ENABLED`` is False)
#: ClothPin's compiled observation (None when ``ENABLED`` is False)
pin_observe: Any = None
#: the measures then ClothPin's observation, in one call (None when ``ENABLED`` is False)
pin_measures_observe: Any = None
#: ClothPin's drawing check (None when ``ENABLED`` is False)
pin_draws: Any = None
grab: Any = None  #: the compiled spring-action grab (None when ``ENABLED`` is False)
clip_actions: Any = None  #: the compiled action check and clip (None when ``ENABLED`` is False)
crank: Any = None  #: the compiled SliderCrank measures (None when ``ENABLED`` is False)
crank_push: Any = None  #: the compiled SliderCrank force action (None when ``ENABLED`` is False)
shaped_reward: Any = None  #: the compiled shaped reward (None when ``ENABLED`` is False)
#: the measures then :func:`observe`'s observation, in one call (None when ``ENABLED`` is False)
measures_observe: Any = None
#: :func:`crank`, then the measures with the crank's ``below`` as ``blocked``, then
#: :func:`observe`, in one call (None when ``ENABLED`` is False)
crank_measures_observe: Any = None
#: :func:`crank_measures_observe`, SliderCrank's shaped reward and the episode counters of a
#: step every copy took, in one call (None when ``ENABLED`` is False)
crank_finish: Any = None

if ENABLED:
    from constrained_particles.jit import njit
    from constrained_particles.kernels import length_error, line_error, wall_element
    from constrained_particles.records import borrowed

    @njit
    def _worse(residual: np.ndarray, i: int, d: float) -> None:  # pragma: no cover - compiled
        """``residual[i] = max(residual[i], d)``, NaN winning (as ``np.maximum``)."""
        if not d <= residual[i]:
            residual[i] = d

    @njit(nogil=True)
    def _measures(x, v, mass, task, blocks, walls, rest, stepped, blocked, out, success):
        # pragma: no cover - compiled
        """Fill ``out`` (5, N) with distance (m), speed (m/s), kinetic energy (J), constraint
        residual (m) and wall force (N) per copy of ``task.n`` particles (the constraint and
        wall blocks read from the packed ``blocks``), advance the rest test of the
        ``stepped`` copies and write ``success = hold >= hold_steps``.

        ``rest`` (:class:`Rest`): a stepped copy's averages move ``alpha`` of the way to the
        velocities (``mean_v + (v - mean_v) alpha``); it is settled, and its count advances
        (else restarts at 0), if within ``task.tolerance`` of the goal with the RMS of the
        averages of its first ``task.count`` particles below ``task.rest_speed`` (the speed
        measure is over the same particles), not ``blocked`` and, with ``walls`` and
        ``task.wall_rest``, touching no wall.

        ``task.track`` holds the particles (within a copy) whose mean x, ``track_scale``
        times their sum, is driven to ``task.goal`` (or, with a ``task.height`` that is not
        NaN, whose mean point is driven to ``(goal, height)``). ``walls``: compute the walls'
        contact force (and, with ``task.wall_rest``, let a step touching a wall restart the
        count); ``blocked`` copies restart it too.
        """
        n, goal, track, track_scale = task.n, task.goal, task.track, task.track_scale
        height, count = task.height, task.count
        planar = not math.isnan(height)
        N = goal.shape[0]
        distance, speed, energy, residual, wall_force = out[0], out[1], out[2], out[3], out[4]
        for i in range(N):
            s2 = 0.0
            e2 = 0.0
            for k in range(i * n, (i + 1) * n):
                w = v[k, 0] * v[k, 0] + v[k, 1] * v[k, 1]
                if k - i * n < count:
                    s2 += w
                e2 += mass[k] * w
            speed[i] = math.sqrt(s2 * (1.0 / count))
            energy[i] = 0.5 * e2
            t = 0.0
            ty = 0.0
            for j in range(track.shape[0]):
                t += x[i * n + track[j], 0]
                ty += x[i * n + track[j], 1]
            if planar:
                distance[i] = math.hypot(t * track_scale - goal[i], ty * track_scale - height)
            else:
                distance[i] = abs(t * track_scale - goal[i])
            residual[i] = 0.0
            wall_force[i] = 0.0
        circ, rod, line, fixed = blocks.circle, blocks.rod, blocks.line, blocks.fixed
        cc, cr = circ.center, circ.radius
        for e in range(circ.particles.shape[0]):
            q = circ.particles[e]
            _worse(residual, q // n, length_error(x[q, 0] - cc[e, 0], x[q, 1] - cc[e, 1], cr[e]))
        for e in range(rod.a.shape[0]):
            a, b = rod.a[e], rod.b[e]
            _worse(residual, a // n, length_error(x[a, 0] - x[b, 0], x[a, 1] - x[b, 1],
                                                  rod.length[e]))
        ln, lpt = line.normal, line.point
        for e in range(line.particles.shape[0]):
            q = line.particles[e]
            _worse(residual, q // n, line_error(x[q, 0], x[q, 1], ln[e, 0], ln[e, 1],
                                                lpt[e, 0], lpt[e, 1]))
        fpt = fixed.point
        for e in range(fixed.particles.shape[0]):
            q = fixed.particles[e]
            _worse(residual, q // n, abs(x[q, 0] - fpt[e, 0]))
            _worse(residual, q // n, abs(x[q, 1] - fpt[e, 1]))
        if walls:
            wall = blocks.wall
            wi, wk, wn, wp = wall.particles, wall.block, wall.normal, wall.params
            fx = np.zeros(x.shape[0])
            touching = False
            for e in range(wi.shape[0]):
                q, k = wi[e], wk[e]
                f, _ = wall_element(x[q, 0], x[q, 1], v[q, 0], v[q, 1], wn[k, 0], wn[k, 1],
                                    wp[k, 0], wp[k, 1], wp[k, 2])
                if f != 0.0:
                    fx[q] += f
                    touching = True
            if touching:
                for i in range(N):
                    f = 0.0
                    for k in range(i * n, (i + 1) * n):
                        f += abs(fx[k])
                    wall_force[i] = f
        _advance_hold(v, task, distance, blocked, wall_force, walls and task.wall_rest, rest,
                      stepped, success)

    @njit
    def _advance_hold(v, task, distance, blocked, wall_force, wall_rest, rest, stepped,
                      success):  # pragma: no cover
        """The rest test (``ParticleTask.advance_rest`` and the hold count): each ``stepped``
        copy's moving average velocities move ``alpha`` of the way to ``v`` (``rest = (hold,
        mean_v, alpha)``); the copy (``task.n`` particles) is settled, and its count advances
        (else restarts at 0), if ``distance`` (m) is below ``task.tolerance``, the RMS of the
        averages of its first ``task.count`` particles below ``task.rest_speed`` (m/s), it is
        not ``blocked`` and (with ``wall_rest``) its ``wall_force`` (N) is not positive.
        Writes ``success = hold >= task.hold_steps`` for every copy."""
        n, count, tolerance = task.n, task.count, task.tolerance
        rest_speed, hold_steps = task.rest_speed, task.hold_steps
        hold, mean_v, alpha = rest.hold, rest.mean_v, rest.alpha
        for i in range(distance.shape[0]):
            if stepped[i]:
                d2 = 0.0
                for k in range(i * n, (i + 1) * n):
                    mx = mean_v[k, 0] + (v[k, 0] - mean_v[k, 0]) * alpha
                    my = mean_v[k, 1] + (v[k, 1] - mean_v[k, 1]) * alpha
                    mean_v[k, 0] = mx
                    mean_v[k, 1] = my
                    if k - i * n < count:
                        d2 += mx * mx + my * my
                if (distance[i] < tolerance and math.sqrt(d2 * (1.0 / count)) < rest_speed
                        and not blocked[i] and not (wall_rest and wall_force[i] > 0.0)):
                    hold[i] += 1
                else:
                    hold[i] = 0
            success[i] = hold[i] >= hold_steps

    @njit
    def _unit(value, lo, hi):  # pragma: no cover - compiled
        """``value`` rounded to float32 and clipped to ``[lo, hi]`` (float32 bounds)."""
        return min(max(np.float32(value), lo), hi)

    @njit
    def _observe_particles(x, v, n, count, goal, cx, cy, ix, iy, lo, hi, obs):
        # pragma: no cover - compiled
        """Write the first ``4 count + 1`` columns of ``obs`` (N rows) float32: the first
        ``count`` particles' ``(x - c) / h`` and ``v / h`` of each copy of ``n``, then the
        goal's ``(goal - c_x) / h_x``, each computed in float64 (``ix, iy`` = 1 / h), rounded
        to float32 and clipped to ``[lo, hi]``."""
        for i in range(goal.shape[0]):
            for k in range(count):
                p = i * n + k
                obs[i, 2 * k] = _unit((x[p, 0] - cx) * ix, lo, hi)
                obs[i, 2 * k + 1] = _unit((x[p, 1] - cy) * iy, lo, hi)
                obs[i, 2 * count + 2 * k] = _unit(v[p, 0] * ix, lo, hi)
                obs[i, 2 * count + 2 * k + 1] = _unit(v[p, 1] * iy, lo, hi)
            obs[i, 4 * count] = _unit((goal[i] - cx) * ix, lo, hi)

    @njit(inline="always")  # (a wrapper: inlined, no compiled level of its own)
    def _observe(x, v, n, goal, view, obs):  # pragma: no cover - compiled
        """Write ``obs`` (N, 4 n + 1) float32: ``(x - c) / h``, ``v / h``, the goal's
        ``(goal - c_x) / h_x``, each computed in float64 (``view``: ``ix, iy`` = 1 / h),
        rounded to float32 and clipped to ``[-limit, limit]``."""
        _observe_particles(x, v, n, n, goal, view.cx, view.cy, view.ix, view.iy,
                           np.float32(-view.limit), np.float32(view.limit), obs)

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

    @njit
    def _grab(x, n, envs, action, box, r2, reach, current, particles, anchors, active):
        # pragma: no cover - compiled
        """The spring action of copies ``envs``: for each, the particle of the copy nearest the
        grab point ``c + h * action[:2]`` (``box = (cx, cy, hx, hy)``, m: the view's centre and
        half sizes; the first of equals; ``particles``, global indices),
        the target ``x_p + reach * u`` (``anchors[envs]``, m), ``u`` the pull ``action[2:]``
        scaled down onto the unit disc if longer than 1, and whether the particle is within
        ``sqrt(r2)`` metres of the grab point (``active[envs]``). ``anchors`` and ``active``
        are the mouse-spring block's own arrays, written in place; True if some copy's particle
        differs from its entry of ``current`` (the block's particle array), which the caller
        must then replace."""
        cx, cy, hx, hy = box
        changed = False
        for e in range(envs.shape[0]):
            i = envs[e]
            gx = cx + hx * action[e, 0]
            gy = cy + hy * action[e, 1]
            best = i * n
            d2 = math.inf
            for k in range(i * n, (i + 1) * n):
                dx = x[k, 0] - gx
                dy = x[k, 1] - gy
                dk = dx * dx + dy * dy
                if dk < d2:
                    d2 = dk
                    best = k
            particles[e] = best
            changed |= current[i] != best
            ux, uy = action[e, 2], action[e, 3]
            norm2 = ux * ux + uy * uy
            if norm2 > 1.0:
                scale = 1.0 / math.sqrt(norm2)
                ux, uy = ux * scale, uy * scale
            anchors[i, 0] = x[best, 0] + reach * ux
            anchors[i, 1] = x[best, 1] + reach * uy
            active[i] = d2 <= r2
        return changed

    @njit
    def _clip_actions(a, out):  # pragma: no cover - compiled
        """``out = clip(a, -1, 1)`` as float64 (same shape, C order); False, with ``out``
        unspecified, if any entry of ``a`` is NaN or infinite."""
        flat = a.reshape(-1)
        dst = out.reshape(-1)
        for k in range(flat.shape[0]):
            u = np.float64(flat[k])
            if not math.isfinite(u):
                return False
            dst[k] = min(max(u, -1.0), 1.0)
        return True

    @njit
    def _crank(x, n, goal, crank):  # pragma: no cover - compiled
        """SliderCrank's crank measures per copy (:class:`Crank`: particle 0 of each copy is
        the crank, on a circle of radius ``r`` = sqrt(``r2``) m; the rod's length squared is
        ``rod2``):
        ``height`` its y (m), ``below`` whether it is not above the slider's wire, and
        ``to_go`` the arc length (m) the short way round to the point above the wire that puts
        the slider at ``goal``: ``r |wrap(acos((g^2 + r^2 - L^2) / (2 g r)) - theta)|``, the
        difference wrapped into [-pi, pi] by a whole turn (the reference takes the angle of
        ``exp(i d)``: the same to rounding). The goal's angle is kept in ``target`` and
        recomputed only where ``goal`` differs from ``seen`` (the goals it was computed for;
        NaN: never)."""
        r, r2, rod2 = crank.r, crank.r2, crank.rod2
        height, to_go, below, seen, target = (crank.height, crank.to_go, crank.below,
                                              crank.seen, crank.target)
        for i in range(goal.shape[0]):
            px, py = x[i * n, 0], x[i * n, 1]
            g = goal[i]
            if not seen[i] == g:
                target[i] = math.acos(min(max((g * g + r2 - rod2) / (2 * g * r), -1.0), 1.0))
                seen[i] = g
            d = target[i] - math.atan2(py, px)  # in [-pi, 2 pi]: one turn at most to wrap
            if d > math.pi:
                d -= 2.0 * math.pi
            elif d < -math.pi:
                d += 2.0 * math.pi
            height[i] = py
            below[i] = not py > 0.0
            to_go[i] = r * abs(d)

    @njit
    def _crank_push(x, action, max_force, out):  # pragma: no cover - compiled
        """SliderCrank's force action: ``out[i, 0] = action[i, 0] max_force t`` (N), ``t`` the
        unit counter-clockwise tangent ``(-y, x) / |(x, y)|`` at copy ``i``'s crank ``x[i, 0]``
        (positions (copies, n, 2), m)."""
        for i in range(action.shape[0]):
            px, py = x[i, 0, 0], x[i, 0, 1]
            norm = math.sqrt(py * py + px * px)
            f = action[i, 0] * max_force
            out[i, 0, 0] = f * (-py / norm)
            out[i, 0, 1] = f * (px / norm)

    @njit
    def _shaped_reward(before, phi, success, penalty, scale, time_cost, bonus, out):
        # pragma: no cover - compiled
        """``out = ((before - phi) * scale - time_cost [- penalty]) + bonus * success`` per
        copy, in that order (the numpy reference's operations, so the same bits; ``penalty``
        empty: none), then ``before = phi`` (the potentials for the next step)."""
        with_penalty = penalty.shape[0] == out.shape[0]
        for i in range(out.shape[0]):
            r = (before[i] - phi[i]) * scale - time_cost
            if with_penalty:
                r = r - penalty[i]
            out[i] = r + bonus * (1.0 if success[i] else 0.0)
            before[i] = phi[i]

    # The two wrappers below are inlined into their callers (the entries): a compiled level of
    # their own would have LLVM optimise everything under it once more (docs/compile_time.md).
    @njit(inline="always")
    def _measures_observe(state, task, blocks, walls, rest, stepped, blocked, out, success, view,
                          obs):  # pragma: no cover - compiled
        """:func:`_measures` then :func:`_observe` (one call from Python instead of two), with
        ``state = (x, v, mass)``."""
        x, v, mass = state
        _measures(x, v, mass, task, blocks, walls, rest, stepped, blocked, out, success)
        _observe(x, v, task.n, task.goal, view, obs)

    @njit(inline="always")
    def _crank_measures_observe(crank, state, task, blocks, walls, rest, stepped, out, success,
                                view, obs):  # pragma: no cover - compiled
        """:func:`_crank`, :func:`_measures` with the copies whose crank is not above the
        slider's wire as ``blocked``, and :func:`_observe`: SliderCrank's whole bookkeeping
        after a step in one call."""
        _crank(state[0], task.n, task.goal, crank)
        _measures_observe(state, task, blocks, walls, rest, stepped, crank.below, out, success,
                          view, obs)

    # The entry points from Python take the pack's blocks by reference (Packed.refs) and their
    # own records in plain form (constrained_particles.records.plain: typed in C, about half
    # the cost of a named tuple's typing per array), rebuilt here from borrowed arrays
    # (records.borrowed: the caller keeps its arguments alive for the whole call, so the
    # records cost no reference counting).
    @njit(inline="always")
    def _finish_record(t):  # pragma: no cover - compiled
        """The :class:`Finish` whose plain form is ``t`` (inlined: as a function of its own it
        took a separate compile, about 1 s)."""
        crank, task, rest, every, out, success, frame, obs, reward, episode = t
        return Finish(Crank(*crank), Goal(*task), Rest(*rest), every, out, success,
                      View(*frame), obs, Reward(*reward), Episode(*episode))

    @njit(nogil=True)
    def _observe_entry(x, v, n, goal, view, obs):  # pragma: no cover - compiled
        _observe(x, v, n, goal, View(*view), obs)

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

    @njit(nogil=True)
    def _crank_finish_entry(x, v, mass, blocks, plain_finish):  # pragma: no cover - compiled
        """The end of a SliderCrank env step that every copy took (``plain_finish``: a
        :class:`Finish` in plain form; one entry, with no compiled level of its own below it
        for the records or the reward, as each level is optimised again in its callers): the
        measures and observation (:func:`_crank_measures_observe`), the
        shaped reward (:func:`_shaped_reward`, no penalties) of the potential ``Phi =
        crank_to_go + speed`` (``SliderCrank.potential``; ``before`` becomes ``Phi``), and the
        episode counters: ``steps`` advance, ``terminated = success``, ``truncated = steps >=
        max_steps``, ``ended`` either. Returns how many copies ended."""
        finish = _finish_record(borrowed(plain_finish))
        episode, reward = finish.episode, finish.reward
        no_walls = episode.ended.shape[0] < 0  # (False as a run-time bool: a constant False
        # would compile the measures once more, for its own literal type)
        _crank_measures_observe(finish.crank, (x, v, mass), finish.task, blocks, no_walls,
                                finish.rest, finish.every, finish.out, finish.success,
                                finish.frame, finish.obs)
        phi = finish.crank.to_go + finish.out[1]  # SliderCrank.potential
        success = finish.success
        _shaped_reward(reward.before, phi, success, phi[:0], reward.scale, reward.time_cost,
                       reward.bonus, reward.reward)
        count = 0
        steps, terminated, truncated, ended = (episode.steps, episode.terminated,
                                               episode.truncated, episode.ended)
        for i in range(steps.shape[0]):
            steps[i] += 1
            terminated[i] = success[i]
            truncated[i] = steps[i] >= episode.max_steps
            ended[i] = terminated[i] or truncated[i]
            count += ended[i]
        return count


    @njit(nogil=True)
    def _measures_observe_entry(state, task, blocks, walls, rest, stepped, blocked, out,
                                success, view, obs):  # pragma: no cover - compiled
        task, rest = borrowed((task, rest))
        _measures_observe(state, Goal(*task), blocks, walls, Rest(*rest), stepped, blocked,
                          out, success, View(*view), obs)

    @njit(nogil=True)
    def _crank_measures_observe_entry(crank, state, task, blocks, walls, rest, stepped, out,
                                      success, view, obs):  # pragma: no cover - compiled
        crank, task, rest = borrowed((crank, task, rest))
        _crank_measures_observe(Crank(*crank), state, Goal(*task), blocks, walls, Rest(*rest),
                                stepped, out, success, View(*view), obs)

    @njit(nogil=True)
    def _crank_entry(x, n, goal, crank):  # pragma: no cover - compiled
        _crank(x, n, goal, Crank(*crank))

    observe = _observe_entry
    pin_observe = _pin_observe_entry
    pin_measures_observe = _pin_measures_observe_entry
    pin_draws = _pin_draws
    crank_finish = _crank_finish_entry
    measures_observe = _measures_observe_entry
    crank_measures_observe = _crank_measures_observe_entry
    grab = _grab
    clip_actions = _clip_actions
    crank = _crank_entry
    crank_push = _crank_push
    shaped_reward = _shaped_reward
