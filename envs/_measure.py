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

A task's own kernels (SliderCrank's crank measures and whole end of step, ClothPin's slot
observation and drawing check) live with the task (``envs/slider_crank.py``,
``envs/cloth_pin_kernels.py``) and build on the functions here.

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


def packed(system: Any, fresh: Any = None) -> Any:
    """The system's compiled description (``fused.Packed``), or None when the compiled
    bookkeeping is off or does not cover the system (then the numpy reference runs).

    ``fresh``: the pack that the step just taken made current and refreshed
    (:meth:`envs.base.ParticleTask.simulate_step`), or None. If it is still the system's, it
    is taken as it is: the measures of a step then read the parameters that step was taken
    with (an in-place edit made meanwhile by another thread is seen at the next step)."""
    if not ENABLED:
        return None
    if fresh is not None and fresh is system.__dict__.get("_packed") and fresh.valid:
        return fresh
    p = pack(system)
    if not p.valid:
        return None
    # several blocks of one type: bring the joined parameters the measures read up to date
    p.refresh(measured_only=True)
    return p


observe: Any = None  #: the compiled observation kernel (None when ``ENABLED`` is False)
grab: Any = None  #: the compiled spring-action grab (None when ``ENABLED`` is False)
clip_actions: Any = None  #: the compiled action check and clip (None when ``ENABLED`` is False)
shaped_reward: Any = None  #: the compiled shaped reward (None when ``ENABLED`` is False)
#: the measures then :func:`observe`'s observation, in one call (None when ``ENABLED`` is False)
measures_observe: Any = None

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

    # The wrapper below is inlined into its callers (the entries, here and in the tasks'
    # modules): a compiled level of its own would have LLVM optimise everything under it once
    # more (docs/compile_time.md).
    @njit(inline="always")
    def _measures_observe(state, task, blocks, walls, rest, stepped, blocked, out, success, view,
                          obs):  # pragma: no cover - compiled
        """:func:`_measures` then :func:`_observe` (one call from Python instead of two), with
        ``state = (x, v, mass)``."""
        x, v, mass = state
        _measures(x, v, mass, task, blocks, walls, rest, stepped, blocked, out, success)
        _observe(x, v, task.n, task.goal, view, obs)

    # The entry points from Python take the pack's blocks by reference (Packed.refs) and their
    # own records in plain form (constrained_particles.records.plain: typed in C, about half
    # the cost of a named tuple's typing per array), rebuilt here from borrowed arrays
    # (records.borrowed: the caller keeps its arguments alive for the whole call, so the
    # records cost no reference counting).
    @njit(nogil=True)
    def _observe_entry(x, v, n, goal, view, obs):  # pragma: no cover - compiled
        _observe(x, v, n, goal, View(*view), obs)

    @njit(nogil=True)
    def _measures_observe_entry(state, task, blocks, walls, rest, stepped, blocked, out,
                                success, view, obs):  # pragma: no cover - compiled
        task, rest = borrowed((task, rest))
        _measures_observe(state, Goal(*task), blocks, walls, Rest(*rest), stepped, blocked,
                          out, success, View(*view), obs)

    observe = _observe_entry
    measures_observe = _measures_observe_entry
    grab = _grab
    clip_actions = _clip_actions
    shaped_reward = _shaped_reward
