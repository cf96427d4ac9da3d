"""ClothPin-v1: draw persistent springs that hold a pushed cloth at a goal short of the wall."""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces

from constrained_particles import DampedSpring, ParticleSystem, Shape, Wall, scenes

from . import cloth_pin_kernels
from .base import OBS_LIMIT, ParticleTask, _measured
from .checks import _owned, check_positive, check_range
from .cloth_slide import _hanging_equilibrium
from .rewards import ShapedTask
from .single import ParticleEnv
from .task import TaskSpec, ppo, sac
from .vector import ParticleVectorEnv

#: Valid values of ClothPin's ``action_mode`` argument.
DRAW_MODES = ("draw",)
#: Observed values per spring slot: placed flag, both ends (x, y), stiffness, rest length.
SLOT_SIZE = 7
#: Newton steps of :meth:`ClothPin.plan_distance` at most, and the force (N) left over at
#: which it stops early.
PLAN_NEWTON_STEPS = 6
PLAN_TOLERANCE = 1e-9


class ClothPin(ShapedTask, ParticleTask):
    """The ClothPin physics and task for ``num_envs`` copies (see :class:`ClothPinEnv`).

    One copy's particles: the cloth (``nx * ny``, row-major from the top row on the wire), then
    ``max_springs`` fixed anchor particles parked far outside the view. The spring budget is one
    :class:`DampedSpring` block of ``max_springs`` elements per copy with ``ks = kd = 0`` until
    placed; placing a spring (:meth:`place`) rewrites one element's ends, rest length and
    constants, and may move one anchor into the anchor region. Nothing is ever added to the
    system, so every copy keeps one sparse pattern. The horizontal push on the top row is the
    copy's ``ConstantForce`` block, switched on while the copy is stepped.
    """

    force_dim = 0
    wall_rest = False  # (the wall's contact is measured and penalised, but not part of rest)

    @property
    def rest_count(self) -> int:
        """The cloth's particles (the anchors after them do not count in ``speed`` and the
        rest test)."""
        return self.cloth_n

    def __init__(self, num_envs: int = 1, *, action_mode: str = "draw",
                 cloth_size: tuple[int, int] = (6, 6), spacing: float = 0.1,
                 particle_mass: float = 0.02, cloth_ks: float = 40.0, cloth_kd: float = 0.05,
                 drag: float = 0.05, push: float = 0.1, wall_x: float = 1.0,
                 wall_penalty: float = 1.0, max_springs: int = 4, spring_cost: float = 0.1,
                 ks_range: tuple[float, float] = (0.2, 20.0), spring_kd: float = 0.02,
                 snap_radius: float = 0.1,
                 anchor_region: tuple[float, float, float, float] = (-1.3, -0.1, -0.9, 0.1),
                 start_range: tuple[float, float] = (-0.5, -0.2),
                 goal_range: tuple[float, float] = (0.0, 0.5), min_distance: float = 0.2,
                 dt: float = 0.01, substeps: int = 5, integrator: str = "symplectic_euler",
                 goal_tolerance: float = 0.05, rest_speed: float = 0.05,
                 hold_steps: int = 5, rest_window: int = 10, residual_limit: float = 0.01) -> None:
        if action_mode not in DRAW_MODES:
            raise ValueError(f"action_mode must be one of {DRAW_MODES}, got {action_mode!r}")
        try:
            nx, ny = (int(c) for c in cloth_size)
        except (TypeError, ValueError):
            raise ValueError(f"cloth_size must be a (columns, rows) pair of ints, "
                             f"got {cloth_size!r}") from None
        if nx < 2 or ny < 2 or (nx, ny) != tuple(cloth_size):
            raise ValueError(f"cloth_size must be two integers >= 2, got {cloth_size!r}")
        self.nx, self.ny, self.cloth_n = nx, ny, nx * ny
        #: The tracked coordinate is the cloth's centre of mass x (m): see :meth:`tracked`.
        self.tracked_particles = np.arange(self.cloth_n)
        self.spacing = check_positive("spacing", spacing)
        self.particle_mass = check_positive("particle_mass", particle_mass)
        self.cloth_ks = check_positive("cloth_ks", cloth_ks)
        self.cloth_kd = check_positive("cloth_kd", cloth_kd, allow_zero=True)
        self.drag = check_positive("drag", drag, allow_zero=True)
        self.push = check_positive("push", push)
        self.wall_penalty = check_positive("wall_penalty", wall_penalty, allow_zero=True)
        self.max_springs = check_positive("max_springs", max_springs, integer=True)
        self.spring_cost = check_positive("spring_cost", spring_cost, allow_zero=True)
        self.ks_range = check_range("ks_range", ks_range)
        if self.ks_range[0] <= 0 or self.ks_range[1] <= self.ks_range[0]:
            raise ValueError(f"ks_range must be (low, high) with 0 < low < high N/m, "
                             f"got {ks_range!r}")
        self.spring_kd = check_positive("spring_kd", spring_kd, allow_zero=True)
        self.snap_radius = check_positive("snap_radius", snap_radius)
        self.start_range = check_range("start_range", start_range)
        self.goal_range = check_range("goal_range", goal_range)
        self.min_distance = check_positive("min_distance", min_distance, allow_zero=True)
        if isinstance(wall_x, bool) or not isinstance(wall_x, (int, float, np.number)) \
                or not math.isfinite(wall_x):
            raise ValueError(f"wall_x must be a finite number (m), got {wall_x!r}")
        self.wall_x = float(wall_x)
        try:
            box = tuple(float(b) for b in anchor_region)
        except (TypeError, ValueError):
            box = ()
        if len(box) != 4 or not all(map(math.isfinite, box)) or box[2] <= box[0] \
                or box[3] <= box[1]:
            raise ValueError(f"anchor_region must be finite (xmin, ymin, xmax, ymax) m with "
                             f"xmin < xmax and ymin < ymax, got {anchor_region!r}")
        self.anchor_region = box
        half_width = (nx - 1) * self.spacing / 2
        if self.start_range[1] + self.min_distance > self.goal_range[0]:
            raise ValueError(f"start_range {start_range!r} must end min_distance = "
                             f"{self.min_distance:g} m left of goal_range {goal_range!r}")
        if self.goal_range[1] + half_width >= self.wall_x:
            raise ValueError(f"goal_range: a goal at {self.goal_range[1]} m would put the "
                             f"cloth's edge into the wall at wall_x = {self.wall_x} m")
        if box[2] + self.snap_radius >= self.start_range[0] - half_width:
            raise ValueError(f"anchor_region {anchor_region!r} must end snap_radius left of the "
                             f"cloth's left edge at the leftmost start")
        height = (ny - 1) * self.spacing
        self.view = (min(box[0], box[2] - 0.4), -1.6 * height - 0.2, self.wall_x + 0.3, 0.3)
        super().__init__(num_envs, action_mode="force", dt=dt, substeps=substeps,
                         integrator=integrator, max_force=self.push, grab_radius=snap_radius,
                         mouse_ks=1.0, mouse_kd=0.0, goal_tolerance=goal_tolerance,
                         rest_speed=rest_speed, hold_steps=hold_steps, rest_window=rest_window,
                         residual_limit=residual_limit)
        self.action_mode = action_mode
        N, B = self.num_envs, self.max_springs
        self.wall = next(f for f in self.system.forces if isinstance(f, Wall))
        self.springs: DampedSpring = self.system.forces[self._block]
        #: Springs placed (N,), anchors moved into the region (N,), and the copies that placed
        #: one on the last step (N,).
        self.placed = np.zeros(N, dtype=np.int64)
        self.anchors_used = np.zeros(N, dtype=np.int64)
        self.placed_now = np.zeros(N, dtype=bool)
        self._log_ratio: tuple[Any, float] | None = None  # (ks_range, log(hi / lo)): pin_record
        self.movable = np.tile(~self.single.fixed, N)
        self.weight = self.cloth_n * self.particle_mass * scenes.G
        obs_dim = 4 * self.cloth_n + 1 + SLOT_SIZE * B
        self.single_observation_space = spaces.Box(-OBS_LIMIT, OBS_LIMIT, (obs_dim,), np.float32)

    # ------------------------------------------------------------------ scene
    @property
    def action_dim(self) -> int:
        """``(a_x, a_y, b_x, b_y, stiffness, draw)``."""
        return 6

    def build_scene(self) -> ParticleSystem:
        """The cloth of ``scenes.cloth`` hanging in static equilibrium centred on x = 0, the
        parked anchors, and the spring budget (every element anchor k -> particle 0, ks = 0)."""
        s = scenes.cloth(self.nx, self.ny, spacing=self.spacing, mass=self.particle_mass,
                         ks=self.cloth_ks, kd=self.cloth_kd, wire_height=0.0, wall_x=self.wall_x,
                         drag=self.drag)
        s.x[:, 0] -= s.x[:, 0].mean()
        self.rest_shape = _hanging_equilibrium(s, top=np.arange(self.nx))
        s.x = self.rest_shape.copy()
        self.goal_height = float(self.rest_shape[:, 1].mean())
        B = self.max_springs
        xmin, _, _, ymax = self.view
        self.parking = np.stack([xmin - 2.0 - 0.1 * np.arange(B), np.full(B, ymax + 2.0)], axis=1)
        self.anchors = s.add_particles(self.parking, mass=self.particle_mass, fixed=True)
        s.add(DampedSpring(self.anchors, np.zeros(B, np.int64), rest=0.0, ks=0.0, kd=0.0))
        self._block = len(s.forces) - 1
        return s

    def force_handles(self, scene: ParticleSystem) -> np.ndarray:
        """The top row: the horizontal push acts there."""
        return np.arange(self.nx)

    def force_vectors(self, action: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The push: ``push`` newtons in +x on every top-row particle, whatever the action."""
        f = np.zeros((len(action), self.nx, 2))
        f[:, :, 0] = self.push
        return f

    def sample_start(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        """The cloth at rest in equilibrium centred at x0 ~ U(start_range), anchors parked; the
        goal ~ U(goal_range)."""
        x0 = float(rng.uniform(*self.start_range))
        goal = float(rng.uniform(*self.goal_range))
        x = np.concatenate([self.rest_shape + [x0, 0.0], self.parking])
        return x, np.zeros_like(x), goal

    def tracked(self, x: np.ndarray) -> np.ndarray:
        """The cloth's centre of mass x (m) (all cloth particles have the same mass)."""
        return np.mean(np.ascontiguousarray(x[:, :self.cloth_n, 0]), axis=1)

    # ------------------------------------------------------------------ springs
    def stiffness(self, s: np.ndarray) -> np.ndarray:
        """Spring constant (N/m) of stiffness action ``s`` in [-1, 1]: log-uniform over
        ``ks_range``."""
        lo, hi = self.ks_range
        return lo * (hi / lo) ** ((np.asarray(s) + 1.0) / 2.0)

    def stiffness_action(self, ks: np.ndarray) -> np.ndarray:
        """The stiffness action in [-1, 1] for spring constants ``ks`` (N/m), clipped."""
        lo, hi = self.ks_range
        action = 2.0 * np.log(np.asarray(ks) / lo) / np.log(hi / lo) - 1.0
        return np.minimum(np.maximum(action, -1.0), 1.0)  # (np.clip's call overhead, without it)

    def _slots(self, envs: np.ndarray) -> np.ndarray:
        """Global spring-element indices (len(envs), max_springs) of copies ``envs``."""
        return envs[:, None] * self.max_springs + np.arange(self.max_springs)

    def resolve(self, envs: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Particle (index within a copy) that each drawn end ``points`` (len(envs), 2) m of
        copies ``envs`` takes: the nearest cloth particle or placed anchor within
        ``snap_radius``; else ``-2`` for a new anchor when the point lies in the anchor region;
        else the nearest cloth particle, however far (the cloth end of a drawing takes the
        cloth reliably, wherever the cloth has moved: no chasing it within ``snap_radius``)."""
        x = self.positions()[envs]
        d2 = np.sum((x - points[:, None, :]) ** 2, axis=2)
        local = np.arange(self.n)
        anchor_rank = local - self.cloth_n
        usable = (local < self.cloth_n) | (anchor_rank < self.anchors_used[envs, None])
        d2 = np.where(usable, d2, np.inf)
        rows = np.arange(len(envs))
        nearest = np.argmin(d2, axis=1)
        near = d2[rows, nearest] <= self.snap_radius**2
        cloth = np.argmin(d2[:, :self.cloth_n], axis=1)
        xmin, ymin, xmax, ymax = self.anchor_region
        region = ((points[:, 0] >= xmin) & (points[:, 0] <= xmax)
                  & (points[:, 1] >= ymin) & (points[:, 1] <= ymax))
        return np.where(near, nearest, np.where(region, -2, cloth))

    def place(self, envs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """Draw one spring per copy in ``envs`` from clipped actions (len(envs), 6), the
        drawing being valid; returns the mask of copies that placed one.

        A drawing is refused (nothing changes) when the budget is spent, when the cloth is not
        at rest (:meth:`still`), or when the spring would not join the cloth to an anchor (both
        ends on the cloth, or neither): only such a spring can hold the cloth against the push,
        so no other uses up the budget. A new anchor is the
        copy's next parked anchor, moved to the drawn point. The rest length is the distance
        between the two ends as placed.
        """
        out = np.zeros(len(envs), bool)
        # (a spent budget refuses, and so does a cloth that is not at rest)
        room = np.flatnonzero((self.placed[envs] < self.max_springs) & self.still()[envs])
        if not len(room):
            return out
        envs, action = envs[room], action[room]
        # both ends in one resolve (row by row the same arithmetic as two calls)
        first = len(envs)
        both = self.resolve(np.concatenate([envs, envs]),
                            self.to_world(np.concatenate([action[:, 0:2], action[:, 2:4]])))
        ends = np.stack([both[:first], both[first:]], axis=1)
        on_cloth = (ends >= 0) & (ends < self.cloth_n)
        new = ends == -2
        ok = (on_cloth.sum(axis=1) == 1) & (new.sum(axis=1) <= 1)
        if not ok.any():
            return out
        out[room[ok]] = True
        self._attach(envs[ok], ends[ok], action[ok])
        return out

    def still(self) -> np.ndarray:
        """Copies (num_envs,) bool whose cloth is at rest, so that a spring may be drawn: the
        rest test's speed (the RMS, m/s, of the cloth particles' moving average velocities;
        see :meth:`advance_rest`) below ``rest_speed``. True at a reset; the push takes a
        free cloth out of rest within about 6 steps (0.3 s)."""
        N, n, nc = self.num_envs, self.n, self.cloth_n
        avg = self.mean_v.reshape(N, n, 2)[:, :nc]
        speed = np.sqrt((avg[:, :, 0] * avg[:, :, 0] + avg[:, :, 1] * avg[:, :, 1]).sum(axis=1)
                        * (1.0 / nc))
        return speed < self.rest_speed

    def _attach(self, envs: np.ndarray, ends: np.ndarray, action: np.ndarray) -> None:
        """Place one spring per copy in ``envs`` whose drawing is valid: ``ends`` (len(envs),
        2) as :meth:`resolve` gives them (-2: a new anchor), ``action`` their clipped actions."""
        new = ends == -2
        # a new anchor becomes the copy's next unused anchor particle, at the drawn point
        anchor = self.cloth_n + self.anchors_used[envs]
        drawn = np.where(new[:, :1], action[:, 0:2], action[:, 2:4])
        has_new = new.any(axis=1)
        base = envs * self.n
        self.system.x[(base + anchor)[has_new]] = self.to_world(drawn[has_new])
        self.anchors_used[envs] += has_new
        ends = np.where(new, anchor[:, None], ends) + base[:, None]
        k = envs * self.max_springs + self.placed[envs]
        sp = self.springs
        self._rewire(k, ends[:, 0], ends[:, 1])
        sp.rest[k] = np.linalg.norm(self.system.x[ends[:, 0]] - self.system.x[ends[:, 1]],
                                    axis=1)
        sp.ks[k] = self.stiffness(action[:, 4])
        sp.kd[k] = self.spring_kd
        self.placed[envs] += 1

    def _rewire(self, slots: np.ndarray, i: np.ndarray, j: np.ndarray) -> None:
        """Point spring ``slots`` at particles ``i``, ``j``. A block's index arrays are read-only:
        new arrays replace them, validated against the system by the block."""
        sp = self.springs
        new_i, new_j = sp.i.copy(), sp.j.copy()
        new_i[slots], new_j[slots] = i, j
        sp.i, sp.j = new_i, new_j

    def _clear_springs(self, envs: np.ndarray) -> None:
        """Every spring of copies ``envs`` back to unplaced (anchor k -> particle 0, ks = 0)."""
        k = self._slots(envs)
        base = envs[:, None] * self.n
        sp = self.springs
        i = np.broadcast_to(base + self.anchors[None, :], k.shape).ravel()
        j = np.broadcast_to(base, k.shape).ravel()
        if not (np.array_equal(sp.i[k.ravel()], i) and np.array_equal(sp.j[k.ravel()], j)):
            self._rewire(k.ravel(), i, j)  # (else already unplaced: no new arrays, no repack)
        sp.rest[k] = sp.ks[k] = sp.kd[k] = 0.0
        self.placed[envs] = 0
        self.anchors_used[envs] = 0
        self.placed_now[envs] = False

    # ------------------------------------------------------------------ base hooks
    def apply(self, actions: np.ndarray, idle: np.ndarray | None = None) -> None:
        """Place the springs that copies draw (``draw > 0``) on a cloth at rest, then switch
        the push on (off for ``idle`` copies, whose action is ignored). The drawings are
        checked in one compiled pass (:func:`envs.cloth_pin_kernels.pin_draws`) where the
        arrays allow it, else by :meth:`place`; the same springs either way (:meth:`still`
        refuses in both)."""
        if not np.count_nonzero(actions[:, 5] > 0):  # (the usual step: nobody draws)
            self.placed_now[:] = False
            super().apply(actions, idle)
            return
        drawn = self._drawn(actions, idle)
        if drawn is not None:
            ends, ok = drawn
            if np.count_nonzero(ok):  # (a moving cloth refuses, as in place)
                ok &= self.still()
            self.placed_now[:] = ok
            if np.count_nonzero(ok):
                envs = np.flatnonzero(ok)
                self._attach(envs, ends[envs], actions[envs])
        else:
            envs = np.arange(self.num_envs)
            drawing = actions[:, 5] > 0
            if idle is not None:
                drawing &= ~idle
            self.placed_now[:] = False
            if drawing.any():
                self.placed_now[drawing] = self.place(envs[drawing], actions[drawing])
        super().apply(actions, idle)

    def _drawn(self, actions: np.ndarray, idle: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(ends, ok)`` of every copy's drawing from the compiled check (see :meth:`apply`),
        or None where the numpy reference must run (compiled bookkeeping off, or arrays not
        of the shapes and types it reads)."""
        N, n, nc, B = self.num_envs, self.n, self.cloth_n, self.max_springs  # (read once)
        state = self._compiled_state()
        if not (state is not None and type(n) is int and type(nc) is int and type(B) is int
                and 0 < nc <= n and len(state[0]) == N * n
                and _owned(actions, np.float64, (N, 6)) and _owned(self.placed, np.int64, (N,))
                and _owned(self.anchors_used, np.int64, (N,))):
            return None
        if idle is None:
            idle = self._mask(None)
        elif not _owned(idle, np.bool_, (N,)):
            return None
        ends, ok = np.empty((N, 2), np.int64), np.empty(N, bool)
        c, h = self.center, self.half
        xmin, ymin, xmax, ymax = self.anchor_region
        if not cloth_pin_kernels.pin_draws(state[0], actions, idle, self.placed, self.anchors_used,
                                  (n, nc, B, float(c[0]), float(c[1]), float(h[0]),
                                   float(h[1]), float(self.snap_radius**2), float(xmin),
                                   float(ymin), float(xmax), float(ymax)), ends, ok):
            return None
        return ends, ok

    def write_starts(self, envs: Sequence[int], x: np.ndarray, v: np.ndarray,
                     goal: np.ndarray) -> None:
        """Write starting states and clear the copies' springs."""
        super().write_starts(envs, x, v, goal)
        self._clear_springs(np.asarray(envs, dtype=np.int64).reshape(-1))
        self._record_potential(envs)  # (the potential counts the springs: now cleared)

    def _put(self, copies: np.ndarray, x: np.ndarray, v: np.ndarray) -> None:
        """As the base, but anchors stay where they are (they never move during a step)."""
        rows = np.repeat(copies, self.n) & self.movable
        self.system.x[rows] = x[rows]
        self.system.v[rows] = v[rows]
        self._actuate(np.flatnonzero(copies), None)

    def load_single(self, i: int) -> ParticleSystem:
        """Copy ``i``'s state, push and springs into :attr:`single`."""
        one = super().load_single(i)
        mine, k = one.forces[self._block], self._slots(np.array([i]))[0]
        new_i = self.springs.i[k] - i * self.n
        new_j = self.springs.j[k] - i * self.n
        if not (np.array_equal(new_i, mine.i) and np.array_equal(new_j, mine.j)):
            mine.i, mine.j = new_i, new_j  # read-only index arrays are replaced, not edited
        for name in ("rest", "ks", "kd"):
            getattr(mine, name)[:] = getattr(self.springs, name)[k]
        return one

    #: Keys of a copy's spring state in :meth:`get_state`.
    SPRING_KEYS: ClassVar[tuple[str, ...]] = ("spring_i", "spring_j", "spring_rest", "spring_ks",
                                              "spring_kd", "placed", "anchors_used")

    def get_state(self, i: int) -> dict[str, Any]:
        """The base state plus copy ``i``'s springs: ends (particle indices within the copy),
        rest lengths (m), ks (N/m), kd (N s/m), and the counts of springs and anchors placed."""
        state = super().get_state(i)
        k = self._slots(np.array([i]))[0]
        sp = self.springs
        state.update(spring_i=sp.i[k] - i * self.n, spring_j=sp.j[k] - i * self.n,
                     spring_rest=sp.rest[k].copy(), spring_ks=sp.ks[k].copy(),
                     spring_kd=sp.kd[k].copy(), placed=int(self.placed[i]),
                     anchors_used=int(self.anchors_used[i]))
        return state

    def set_state(self, i: int, state: dict[str, Any]) -> None:
        """Restore copy ``i`` from :meth:`get_state`; ValueError for a malformed state."""
        if not isinstance(state, dict):
            raise ValueError(f"state must be a dict from get_state(), got {type(state).__name__}")
        missing = set(self.SPRING_KEYS) - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")
        B = self.max_springs
        values = {}
        for key in self.SPRING_KEYS[:5]:
            arr = np.asarray(state[key], dtype=float)
            if arr.shape != (B,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ValueError(f"state[{key!r}] must be a finite array >= 0 of shape ({B},), "
                                 f"got {arr!r}")
            values[key] = arr
        ends = np.stack([values["spring_i"], values["spring_j"]])
        if np.any(ends != np.round(ends)) or np.any(ends >= self.n) \
                or np.any(ends[0] == ends[1]):
            raise ValueError("state['spring_i'], state['spring_j'] must be distinct particle "
                             f"indices below {self.n}")
        counts = {}
        for key in ("placed", "anchors_used"):
            c = state[key]
            if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c <= B:
                raise ValueError(f"state[{key!r}] must be an integer in [0, {B}], got {c!r}")
            counts[key] = int(c)
        super().set_state(i, state)
        k = self._slots(np.array([i]))[0]
        sp = self.springs
        offset = i * self.n
        self._rewire(k, ends[0].astype(np.int64) + offset, ends[1].astype(np.int64) + offset)
        sp.rest[k], sp.ks[k], sp.kd[k] = (values["spring_rest"], values["spring_ks"],
                                          values["spring_kd"])
        self.placed[i], self.anchors_used[i] = counts["placed"], counts["anchors_used"]
        self.placed_now[i] = False
        self._record_potential([i])  # (the potential counts the springs: now restored)

    # ------------------------------------------------------------------ measures
    def _compiled_paths(self) -> dict[str, bool]:
        """``ParticleTask._compiled_paths``, with ``measure_observe`` for this class's
        :meth:`observe` (the pin observation)."""
        paths = super()._compiled_paths()
        cls = type(self)
        paths["measure_observe"] = (cls.measure is ParticleTask.measure
                                    and cls.observe is ClothPin.observe)
        paths["plan_center"] = cls.tracked is ClothPin.tracked  # (the kernel's own mean)
        paths["plan"] = cls.plan_distance is ClothPin.plan_distance  # (in measure_observe)
        return paths

    def observe(self) -> np.ndarray:
        """Observations (num_envs, 4 nc + 1 + 7 max_springs) float32: the cloth's normalized
        positions and velocities, the goal, and one row per spring slot (see the env docs).
        In one compiled pass (:func:`envs.cloth_pin_kernels.pin_observe`) where the arrays allow it,
        else by the numpy reference :meth:`observe_reference`."""
        N, n, nc, goal = self.num_envs, self.n, self.cloth_n, self.goal  # (read once)
        state = self._compiled_state()
        pin = (cloth_pin_kernels.pin_record(self, N, n, nc)
               if state is not None and _owned(goal, np.float64, (N,)) else None)
        if pin is not None and len(state[0]) == N * n:
            obs = self._obs(N, nc, pin[0])
            if cloth_pin_kernels.pin_observe(state[0], state[1], n, goal, tuple(self._view()),
                                             pin, obs):
                return obs
        return self.observe_reference()

    def measure_observe(self, stepped: np.ndarray | None = None
                        ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """:meth:`measure`, then :meth:`observe`: in one compiled call
        (:func:`envs.cloth_pin_kernels.pin_measures_observe`) unless a subclass redefines either or
        the arrays do not allow it; the same values either way."""
        post = self._compiled_post() if self._paths["measure_observe"] else None
        if post is None:
            return self.measure(stepped), self.observe()
        p, goal, (x, v, mass) = post
        N, nc = len(goal.goal), self.cloth_n
        pin = cloth_pin_kernels.pin_record(self, N, goal.n, nc)
        if pin is None:
            return self.measure(stepped), self.observe()
        out, success, obs = np.empty((5, N)), np.empty(N, bool), self._obs(N, nc, pin[0])
        if not cloth_pin_kernels.pin_measures_observe(
                (x, v, mass), tuple(goal), p.refs.blocks, True, tuple(self._rest()),
                self._mask(stepped), self._mask(None), out, success, tuple(self._view()), pin,
                obs):
            return self.measure(stepped), self.observe()
        plan = (cloth_pin_kernels.plan_checked(  # (arrays pin_record, _compiled_post checked)
            self, x, pin[2:6], (N, goal.n, nc, pin[0]), goal.goal,
            (PLAN_NEWTON_STEPS, PLAN_TOLERANCE)) if self._paths["plan"] else None)
        return self.add_measures(_measured(out, success), out[4], plan), obs

    @staticmethod
    def _obs(N: int, nc: int, slots: int) -> np.ndarray:
        """A fresh observation array (N, 4 nc + 1 + 7 slots) float32."""
        return np.empty((N, 4 * nc + 1 + SLOT_SIZE * slots), np.float32)

    def observe_reference(self) -> np.ndarray:
        """:meth:`observe` in numpy (the reference of the compiled pass): each entry computed
        in float64 (``(x - c) / h`` as ``(x - c) * (1 / h)``), rounded to float32 and clipped
        to [-OBS_LIMIT, OBS_LIMIT]."""
        N, nc, B = self.num_envs, self.cloth_n, self.max_springs
        inv_half = 1.0 / self.half
        x = self.positions()
        pos = ((x[:, :nc] - self.center) * inv_half).reshape(N, -1)
        vel = (self.velocities()[:, :nc] * inv_half).reshape(N, -1)
        goal = (self.goal[:, None] - self.center[0]) * inv_half[0]
        sp = self.springs
        on = (np.arange(B)[None, :] < self.placed[:, None]).reshape(-1)
        flat = self.system.x
        rows = np.concatenate([np.ones((len(on), 1)), (flat[sp.i] - self.center) * inv_half,
                               (flat[sp.j] - self.center) * inv_half,
                               self._stiffness_seen(sp.ks)[:, None],
                               (sp.rest * inv_half[0])[:, None]], axis=1)
        rows = np.where(on[:, None], rows, 0.0)
        obs = np.concatenate([pos, vel, goal, rows.reshape(N, -1)], axis=1)
        return np.clip(obs, -OBS_LIMIT, OBS_LIMIT).astype(np.float32)

    def _stiffness_seen(self, ks: np.ndarray) -> np.ndarray:
        """The observed stiffness of springs ``ks`` (N/m): :meth:`stiffness_action` of ``ks``
        clipped into ``ks_range``."""
        lo, hi = self.ks_range
        return self.stiffness_action(np.minimum(np.maximum(ks, lo), hi))

    measure_walls = True

    def add_measures(self, m: dict[str, np.ndarray], wall_force: np.ndarray,
                     plan: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The common measures (``speed`` over the cloth only) plus ``wall_force`` (N), the
        ``springs`` placed so far, ``placed`` (a spring was placed on the last step) and
        ``plan_distance`` (m, :meth:`plan_distance`; ``plan`` if the caller has it)."""
        m["wall_force"] = wall_force
        m["springs"] = self.placed.copy()
        m["placed"] = self.placed_now.copy()
        m["plan_distance"] = self.plan_distance() if plan is None else plan
        return m

    def plan_distance(self) -> np.ndarray:
        """Distance (num_envs,) m from the goal to where the placed springs would hold the
        cloth at rest: the cloth's centre of mass after the rigid shift along x at which the
        springs' horizontal pull balances the push (``nx * push`` N), or after the shift that
        brings its right edge to the wall if they cannot hold it before (as with no springs).
        The shift: up to :data:`PLAN_NEWTON_STEPS` Newton steps from the wall's, each copy
        stopping once its force left over is below :data:`PLAN_TOLERANCE`; the pull (convex in
        the shift while the cloth ends are right of their anchors) makes them approach the
        balance from the wall's side. Exact after one step for the scripted agent's horizontal
        spring on the top row; for other springs it leaves out the cloth's own deformation. A
        function of each copy's own state alone (springs, positions, goal). In one compiled
        pass (:func:`envs.cloth_pin_kernels.pin_plan`) where the arrays allow it, else by the
        numpy reference :meth:`plan_distance_reference`; the same bits either way."""
        out = cloth_pin_kernels.plan(self, (PLAN_NEWTON_STEPS, PLAN_TOLERANCE))
        return self.plan_distance_reference() if out is None else out

    def plan_distance_reference(self) -> np.ndarray:
        """:meth:`plan_distance` in numpy (the reference of the compiled pass)."""
        N, n, nc, B = self.num_envs, self.n, self.cloth_n, self.max_springs
        sp, flat = self.springs, self.system.x
        base = (np.arange(N) * n)[:, None]
        i, j = sp.i.reshape(N, B) - base, sp.j.reshape(N, B) - base
        # +1 where only j is on the cloth, -1 where only i is: u runs from anchor to cloth
        sign = (j < nc).astype(np.float64) - (i < nc)
        u = sign[:, :, None] * (flat[sp.j] - flat[sp.i]).reshape(N, B, 2)
        uy2 = u[:, :, 1] * u[:, :, 1]
        ks = np.where(sign != 0, sp.ks.reshape(N, B), 0.0)
        rest = sp.rest.reshape(N, B)
        x = self.positions()[:, :nc, 0]
        push = self.nx * self.push
        wall = self.wall_x - x.max(axis=1)  # the shift that puts the right edge on the wall
        shift = wall.copy()
        going = np.zeros(N, bool)  # (the copies still taking Newton steps)
        for step in range(PLAN_NEWTON_STEPS):
            sx = u[:, :, 0] + shift[:, None]
            length = np.maximum(np.sqrt(sx * sx + uy2), 1e-12)
            # the push less the springs' pull (N), and its slope (N/m)
            excess = push - np.sum(ks * (length - rest) * sx / length, axis=1)
            slope = -np.sum(ks * (1.0 - rest * uy2 / (length * length * length)), axis=1)
            if step == 0:
                going = excess < 0  # (else the springs cannot stop it before the wall)
            else:
                going &= ~(np.abs(excess) < PLAN_TOLERANCE)
            if not going.any():
                break
            shift = np.where(going & (slope < 0), shift - excess / np.minimum(slope, -1e-12),
                             shift)
        shift = np.minimum(shift, wall)
        return np.abs(self.tracked(self.positions()) + shift - self.goal)

    def potential(self, m: dict[str, Any]) -> float | np.ndarray:
        """Cost to go ``Phi = d + s + p``: distance to the goal (m) plus the cloth's RMS
        particle speed (m/s) plus ``plan_distance`` (m): the distance from the goal at which
        the springs placed so far would hold the cloth at rest, so that a drawing is credited
        on the step it is made."""
        return m["distance"] + m["speed"] + m["plan_distance"]

    def penalties(self, m: dict[str, Any]) -> float | np.ndarray:
        """``wall_penalty F_wall / (M g) + spring_cost placed``, per copy (arrays) or for one
        copy (numbers: see ``reward_one``)."""
        return self.wall_penalty * m["wall_force"] / self.weight + self.spring_cost * m["placed"]

    def drawing(self, i: int) -> tuple[ParticleSystem, list[Shape], str]:
        """Copy ``i`` with only its placed springs, the anchor region, the goal and a status."""
        one, extra, status = super().drawing(i)
        shown = copy.copy(one)
        budget = one.forces[self._block]
        on = np.arange(self.max_springs) < self.placed[i]
        shown.forces = [f for f in one.forces if f is not budget]
        if on.any():
            shown.forces.append(DampedSpring(budget.i[on], budget.j[on], budget.rest[on],
                                             budget.ks[on], budget.kd[on]))
        box = np.array(self.anchor_region)
        region = Shape("region", "anchor", box[None, :2], box[None, 2:])
        status = f"{status}   springs {self.placed[i]}/{self.max_springs}"
        return shown, [region, *extra], status


class ClothPinEnv(ParticleEnv):
    """
    ## Description

    The viewer's interaction as the action: drawing springs that stay. A spring-mass cloth hangs
    from a horizontal wire (its top row slides on it, a Lagrange-multiplier constraint) and a
    horizontal force pushes every top-row particle toward a wall on the right. Each
    step the agent may draw one persistent damped spring, as in the viewer: each end snaps to
    the nearest particle within ``snap_radius``; otherwise an end in the marked
    ``anchor_region`` (shaded, left of the cloth on the wire's line) becomes a new fixed
    anchor there, and any other end takes the cloth particle nearest to it, however far; the
    rest length is the distance between the two ends as placed. Stop the cloth with its
    centre of mass at rest at a goal short of the wall, with at most ``max_springs`` springs,
    each costing a little. A spring drawn at rest length holds the cloth where its tension
    balances the push, so the stiffness of the springs sets where the cloth stops.

    **Springs are drawn only on a cloth at rest** (the rest test's averaged speed below
    ``rest_speed``, the same test as success; ``task.still()``). The cloth starts at rest and
    the push takes it out of rest within about 6 steps (0.3 s), so the springs that stop it
    are planned from the start, before the cloth moves: a spring cannot catch the moving
    cloth on the fly. (Drawings on a cloth that has come to rest again, on its springs or
    against the wall, are taken, but a spring drawn at rest length there carries no force.)

    ## Action Space

    ``Box(-1, 1, (6,), float32)`` = ``(a_x, a_y, b_x, b_y, stiffness, draw)`` (only
    ``action_mode="draw"``): the two ends of the spring in normalized scene coordinates (see
    below), its stiffness ``ks = ks_lo (ks_hi / ks_lo)^((stiffness + 1) / 2)`` N/m (log-uniform
    over ``ks_range``), damping ``spring_kd``, and a trigger: the spring is drawn when
    ``draw > 0``. A drawing is refused (nothing happens, nothing is charged, the budget is
    unchanged) when the budget is spent, when the cloth is not at rest (see above), or when
    the spring would not join the cloth to an anchor (both ends on the cloth, or neither end
    on it): only a spring to an anchor can hold the cloth against the push, so a drawing that
    cannot help never uses up the budget. Refusals cost nothing, so that exploring drawings
    is never punished. Springs cannot be removed.

    Actions outside the Box are clipped; a NaN or inf action raises ValueError and changes nothing.

    ## Observation Space

    Normalized scene coordinates map the view box ``env.unwrapped.task.view`` = ``(xmin, ymin,
    xmax, ymax)``, by default ``(-1.3, -1.0, 1.3, 0.3)`` m, onto [-1, 1]^2.

    ``Box(-10, 10, (4 nc + 1 + 7 max_springs,), float32)`` with ``nc = columns * rows`` cloth
    particles (173 floats by default), clipped to [-10, 10]. Cloth particle ``k`` is at row
    ``k // columns`` (0 is the top row, on the wire), column ``k % columns``. Spring slot ``s``
    (in the order placed) is all zeros until placed.

    | Index                       | Observation                                  | Min | Max |
    |-----------------------------|----------------------------------------------|-----|-----|
    | 2k, 2k + 1                  | cloth particle k position x, y               | -10 | 10  |
    | 2nc + 2k, 2nc + 2k + 1      | cloth particle k velocity x, y (1/s)         | -10 | 10  |
    | 4nc                         | goal x (same scale as x)                     | -10 | 10  |
    | 4nc + 1 + 7s                | spring s placed (1) or not (0)               | 0   | 1   |
    | 4nc + 2 + 7s .. 4nc + 5 + 7s| spring s end positions a_x, a_y, b_x, b_y    | -10 | 10  |
    | 4nc + 6 + 7s                | spring s stiffness, as the action's value    | -1  | 1   |
    | 4nc + 7 + 7s                | spring s rest length / half view width       | 0   | 10  |

    ## Rewards

    Every step (see ``envs.rewards``, as ClothSlide):

        r = 10 (Phi - Phi') - 0.1 - wall_penalty * F_wall / (M g) - spring_cost * placed
            + 10 * success

    with the potential ``Phi = d + s + p`` before the step and ``Phi'`` after it
    (potential-based shaping: it sums over an episode to ``10 (Phi_0 - Phi_T)``), ``d`` the
    distance (m) from the cloth's centre of mass to the goal, ``s`` the RMS speed of the cloth
    particles (m/s), ``p`` the *plan distance* (m): how far from the goal the springs placed so
    far would hold the cloth at rest (where their horizontal pull balances the push, the
    cloth shifted rigidly along x; the wall's stop while they cannot hold it, as with no
    springs; ``task.plan_distance()``), a time cost of 0.1 per step, ``F_wall`` the wall's
    total contact force (N), ``M g`` the cloth's weight (N), ``placed`` 1 on a step that
    places a spring, and ``success`` 1 on the step that completes the success test (see
    Episode End). ``p`` credits a drawing on the step it is made, by the stop it plans, rather
    than only some 50-100 steps later when the cloth comes to rest; at rest it equals ``d`` up
    to the cloth's own deformation.

    ## Starting State

    The cloth hangs at rest in static equilibrium, its centre at x0 ~ U(``start_range``), with
    no springs and the push on; the goal is ~ U(``goal_range``), which lies at least
    ``min_distance`` to the right of every start. All draws come from ``self.np_random``.

    ## Episode End

    1. Termination: ``d < goal_tolerance`` and ``s_avg < rest_speed`` for ``hold_steps`` consecutive
       steps (success, ``info["is_success"]``).
       Here ``s_avg`` is the RMS (m/s) of the particles' velocities averaged over about
       ``rest_window`` steps (a moving average taking ``1 / rest_window`` of each new
       velocity), so a policy's own zero-mean action noise averages out, while a drift or a
       swing does not.
    2. Truncation: 200 steps (10 s) with the registered ``max_episode_steps``.
    3. Termination: the simulation diverged (only with unstable ``dt``/``integrator`` choices);
       the state before that step is returned, ``info["diverged"]`` is True and the step's
       reward loses ``task.divergence_penalty`` (the time cost of a whole episode: 20 for
       the registered 200 steps; ``task.episode_steps`` sets another length), so diverging is
       never a cheaper way out than playing on.

    ``info`` holds ``distance`` (m), ``kinetic_energy`` (J), ``constraint_residual`` (largest
    distance off the wire, m),
    ``wall_force`` (N), ``springs`` (placed so far), ``placed`` (on this step),
    ``plan_distance`` (m, ``p`` above), ``is_success`` and ``diverged``.

    ## Arguments

    ```python
    >>> import gymnasium as gym
    >>> import envs
    >>> env = gym.make("ClothPin-v1", cloth_size=(5, 4), max_springs=2)
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, env.action_space.shape
    ((95,), (6,))

    ```

    | Parameter        | Default                     | Description                               |
    |------------------|-----------------------------|-------------------------------------------|
    | `action_mode`    | `"draw"`                    | the only mode                             |
    | `cloth_size`     | `(6, 6)`                    | particle columns and rows, each >= 2      |
    | `spacing`        | `0.1`                       | rest distance between neighbours (m)      |
    | `particle_mass`  | `0.02`                      | mass of each cloth particle (kg)          |
    | `cloth_ks`       | `40.0`                      | structural springs (N/m; shear /2, bend /4) |
    | `cloth_kd`       | `0.05`                      | cloth spring damping (N s/m)              |
    | `drag`           | `0.05`                      | air drag per particle (N s/m)             |
    | `push`           | `0.1`                       | the push on each top-row particle (N)     |
    | `wall_x`         | `1.0`                       | the wall fills x > wall_x (m)             |
    | `wall_penalty`   | `1.0`                       | weight of the wall term of the reward     |
    | `max_springs`    | `4`                         | springs per episode                       |
    | `spring_cost`    | `0.1`                       | reward cost of each placed spring         |
    | `ks_range`       | `(0.2, 20.0)`               | stiffness range of drawn springs (N/m)    |
    | `spring_kd`      | `0.02`                      | damping of drawn springs (N s/m)          |
    | `snap_radius`    | `0.1`                       | an end within this of a particle snaps (m) |
    | `anchor_region`  | `(-1.3, -0.1, -0.9, 0.1)`   | anchors only in this box (m) (*)          |
    | `start_range`    | `(-0.5, -0.2)`              | range of start positions (m)              |
    | `goal_range`     | `(0.0, 0.5)`                | range of goal positions (m)               |
    | `min_distance`   | `0.2`                       | least gap from starts to goals (m)        |
    | `dt`             | `0.01`                      | physics step (s)                          |
    | `substeps`       | `5`                         | physics steps per env step (0.05 s)       |
    | `integrator`     | `"symplectic_euler"`        | a name in `constrained_particles.METHODS` |
    | `goal_tolerance` | `0.05`                      | success distance (m)                      |
    | `rest_speed`     | `0.05`                      | rest (success, drawing): RMS speed (m/s)  |
    | `hold_steps`     | `5`                         | env steps the success test must hold      |
    | `rest_window`    | `10`                        | rest test: averaging window (steps)       |
    | `residual_limit` | `0.01`                      | constraint error (m) counted as diverged  |

    (*) ``(xmin, ymin, xmax, ymax)``, ending at least ``snap_radius`` left of the cloth at its
    leftmost start.

    Bad values raise ValueError at ``make``. ``env.unwrapped.get_state()`` and
    ``set_state(state)`` save and restore the full simulation state, springs included.

    ## Vectorized environment

    ``gym.make_vec("ClothPin-v1", num_envs=N, vectorization_mode="vector_entry_point")`` runs
    :class:`ClothPinVectorEnv`: the N cloths, their anchors and spring budgets are one particle
    system. Autoreset is NEXT_STEP, and copy ``i`` reproduces a single env reset with
    ``seed + i``.

    ## Version History

    * v0: Initial version.
      Changed before any release: the reward became potential-based shaping with a time cost
      (it was ``-d - 0.1 s - penalties`` per step); a drawing that does not join the cloth to
      an anchor is refused instead of using up the budget; the rest test averages velocities
      over about ``rest_window`` steps (it was the instantaneous RMS speed); a diverged step
      ends the episode as terminated with ``divergence_penalty`` (it was a truncation); an
      end outside ``snap_radius`` of every particle and outside the anchor region takes the
      nearest cloth particle (it refused the drawing).
    * v1: Springs are drawn only on a cloth at rest (a drawing on a moving cloth is refused
      and costs nothing), and the anchor region is the band ``y`` in [-0.1, 0.1] m on the
      wire's line (it was [-0.25, 0.25] m). Why: v0 was won by chance. Uniformly random
      actions succeeded in 8.1% of 1,000 episodes (seeds 3,000,000-3,000,999, the agent
      seeded per episode), because a random stiff spring drawn while the pushed cloth passes
      its goal stops it there; v1 asks for the plan up front, before the cloth moves, and the
      same random episodes succeed in 0.9% (the scripted agent, which draws one spring on the
      first step, in 100% of both). Spaces and the other defaults are unchanged.
      Changed before any release: the reward's potential adds the plan distance ``p`` (it was
      ``d + s``), so that the springs are credited when they are drawn (PPO had to learn the
      stiffness from an outcome some 50-100 steps later and did not learn it reliably:
      docs/baselines); random and scripted success are unchanged.
    """

    task_class = ClothPin


class ClothPinVectorEnv(ParticleVectorEnv):
    """``num_envs`` ClothPin copies stepped as one particle system (see :class:`ClothPinEnv`).
    Takes the single env's keyword arguments plus ``num_envs``, ``max_episode_steps``
    (default 200) and ``num_threads`` (default 1; see :class:`~envs.vector.ParticleVectorEnv`)."""

    task_class = ClothPin


class ClothPinController:
    """Draw the one spring that holds the cloth at the goal against the push, on the first step.

    At rest the wire carries the weight and only horizontal forces remain: the push ``P = nx *
    push`` newtons on the top row against the spring's tension. A horizontal spring from an
    anchor in the anchor region to the top row's middle particle, drawn at its rest length
    while the cloth's centre is at ``c``, has tension ``ks (c_end - c)`` once the (rigidly
    shifted) cloth rests at ``c_end``, so ``ks = P / (goal - c)`` stops it at the goal. The
    cloth starts at rest, left of every goal, so the spring is drawn at once; afterwards the
    agent draws nothing.
    """

    def __init__(self, task: ClothPin) -> None:
        self.task = task

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        t = self.task
        o = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        B, nc = len(o), t.cloth_n
        x = t.to_world(o[:, :2 * nc].reshape(B, nc, 2))
        goal = t.center[0] + t.half[0] * o[:, 4 * nc]
        placed = o[:, 4 * nc + 1] > 0.5
        c = x[:, :, 0].mean(axis=1)
        ks = t.nx * t.push / np.maximum(goal - c, 1e-9)
        grip = x[:, t.nx // 2]
        xmin, ymin, xmax, ymax = t.anchor_region
        anchor = np.stack([np.full(B, (xmin + xmax) / 2), np.clip(grip[:, 1], ymin, ymax)], axis=1)
        a = np.concatenate([t.to_normalized(grip), t.to_normalized(anchor),
                            t.stiffness_action(ks)[:, None],
                            np.where(placed, -1.0, 1.0)[:, None]], axis=1)
        a = np.clip(a, -1.0, 1.0).astype(np.float32)
        return a if np.ndim(obs) > 1 else a[0]


#: The task's declaration (see :mod:`envs.task`).
TASK = TaskSpec(
    id="ClothPin-v1", env=ClothPinEnv, vector_env=ClothPinVectorEnv,
    action_modes=DRAW_MODES, scripted_agent=ClothPinController,
    summary="draw up to four springs on a pushed cloth, once it is at rest, so that it comes "
            "to rest at a goal",
    hyperparams={"ppo": {"draw": ppo(2000000, (128, 128), log_std_init=-1.0, n_steps=256,
                                     batch_size=1024, clip_range=0.1, ent_coef=0.0, gamma=0.995,
                                     gae_lambda=0.98, learning_rate="lin_3e-4",
                                     log_std_final=-3.0, explore_until_success=0.1)},
                 "sac": {"draw": sac()}},
    notes=("History (settings chosen on tuning seeds 100-103; runs on the results seeds 0-4 "
           "are named as such). ClothPin-v0: the ClothSlide "
           "spring-mode settings tuned on seed 100 to n_steps 256, batch 1024, clip 0.1 (98% / "
           "82% at 1M). ClothPin-v1: those settings at 2M gave 40/70/14/87/49% deterministic, "
           "9-25% stochastic on seeds 0-4; with the plan distance in the reward and ent_coef 0, "
           "gamma 0.995, gae_lambda 0.98, log_std_init -1 (seed 100, 1M: 33% / 13%) seeds 0-4 "
           "gave 79/8/84/95/26% deterministic, 21-30% stochastic, the periodic evaluations "
           "swinging 30-90 points and the stiffness action's noise staying near 0.2. Then, 2M "
           "steps each, 100 episodes from seed 5,000,000, deterministic / stochastic: "
           "log_std_init -2 (seed 100) drew no spring up to 1.4M (0%, stopped); learning_rate "
           "lin_3e-4 (seed 100) 68% / 14%, its final stds 0.26-0.37; lin_3e-4 with log_std_final "
           "-3 (the std capped from exp(-1) down to exp(-3) = 0.05 over the budget) 100% / 70% "
           "(seed 100) and 100% / 73% (seed 101); the same with log_std_final -3.5 (seed 100) "
           "drew no spring up to 1.6M (0%, stopped). Those settings (lin_3e-4, log_std_final -3) "
           "were published first: seeds 0-4 gave 100/0/57/100/0% deterministic, 68/0/52/69/0% "
           "stochastic, seeds 1 and 4 never drawing a spring (every periodic evaluation a "
           "return of -30.3): once the ceiling fell below about exp(-1.6) (600-800k steps) "
           "before an anchor was drawn in the anchor region, exploration could not find one. "
           "Hence explore_until_success (the noise held at exp(-1) until a success rate, then "
           "the ceiling falling over the rest of the budget). Ended at the first success "
           "(tuning seed 102: 100% / 65%) it ended at 4k steps, on a lucky episode of the "
           "initial policy, and changed nothing: a results run started with it gave seed 0 "
           "100% / 69% and seed 1 again no spring to 1.2M, and was stopped there. As a rate, "
           "10% of the last 100 training episodes: tuning seed 103 100% / 92%, where the "
           "settings published first gave it 0% / 0% (no spring ever drawn); the hold lasted "
           "to about 560k steps. Shipped: lin_3e-4, log_std_final -3, "
           "explore_until_success 0.1. Published (docs/baselines), seeds 0-4 on the 100 "
           "held-out episodes: 100/99/100/99/100% deterministic, 84/69/78/75/78% stochastic, "
           "the hold ending at about 480-660k steps. The SAC settings are untuned, carried "
           "over from ClothSlide in spring mode."))
