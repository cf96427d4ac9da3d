"""Pick-and-place on a table seen from above: what the table-top tasks share.

An object (a rope, a cloth) lies on a table (``TableFriction``: Coulomb friction ``mu m g``,
regularised below ``v_s``, docs/physics.md "Table friction"). An action names, for each of
``num_grippers`` grippers, a *pick point* and a *place point* in normalised view-box
coordinates ``[-1, 1]^2`` (4 numbers per gripper: ``pick_x, pick_y, place_x, place_y``). One
env step is one pick-and-place:

1. **Grab.** Each gripper takes the particle nearest its pick point within ``grab_radius``
   (m) with a stiff damped mouse spring (``mouse_ks`` N/m, ``mouse_kd`` N s/m; Witkin's mouse
   spring, docs/physics.md "Forces"), and lifts it (``TableFriction.lift``: no friction while
   carried). No particle within the radius: that gripper misses (the step still costs its
   time). Two grippers on one particle: the second misses.
2. **Carry.** The spring's anchor moves from the particle's position to the place point in a
   straight line at ``speed`` m/s (updated every ``chunk`` physics steps), then holds there
   for ``hold_time`` s.
3. **Release.** The springs let go and the particles are lowered onto the table.
4. **Settle.** The object slides on until it is at rest (every particle slower than
   ``rest_speed`` m/s) or ``settle_time`` s have passed since the release (``settled`` in
   ``info`` says which).

Each copy of a vector env keeps its own schedule: a copy that is done is put back, at the
end of the step, in its state at the moment it was done, so copy ``i`` of a vector env is a
single env seeded ``seed + i``, bit for bit, however long the other copies take.

``action_mode="drag"`` is SoftGym's low-level mode: per gripper a move ``(dx, dy)`` of up to
``max_move`` metres and a grip flag; a gripping gripper holds its particle (or takes the one
within ``grab_radius`` of it, closing on it), the others let go; each step lasts ``max_move /
speed`` seconds, the grippers moving from rest to rest (a smoothstep), and nothing settles.

Tasks subclass :class:`PickPlaceTask` with the object (:meth:`~PickPlaceTask.build_object`),
a start (:meth:`~PickPlaceTask.sample_episode`), a progress measure ``p``
(:meth:`~PickPlaceTask.progress`) and its success test (:meth:`~PickPlaceTask.success`).
``info`` carries ``progress`` (``p``), SoftGym's ``normalized_performance`` ``(p - p_start) /
(p_goal - p_start)`` and ``settled``; the reward is potential-based shaping on the task's
cost to go (``envs.rewards``) with a time cost per pick-and-place.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from constrained_particles import MouseSpring, ParticleSystem, Shape, TableFriction
from constrained_particles.system import SimulationDiverged

from .base import OBS_LIMIT, ParticleTask
from .checks import check_positive
from .pixels import GOAL, Mark, Picture, default_picture, fixed_marks
from .rewards import ShapedTask
from .single import ParticleEnv
from .vector import ParticleVectorEnv

__all__ = ["PICK_PLACE_MODES", "PP_OBS_MODES", "DragPlan", "PickPlaceEnv", "PickPlaceTask",
           "PickPlaceVectorEnv", "finish_action"]

#: Valid values of a pick-and-place task's ``action_mode`` argument: one pick-and-place per
#: step (the default), or SoftGym's low-level ``"drag"`` (see :class:`PickPlaceTask`).
PICK_PLACE_MODES = ("pick_place", "drag")
#: Distance (m) from its place within which a scripted drag agent's gripper lets go.
PLACE_TOLERANCE = 1e-3
#: Valid values of a pick-and-place env's ``obs_mode`` argument: ``"state"`` (keypoints and
#: the goal), ``"particles"`` (every particle and the goal), or the pixel modes every env has,
#: ``"pixels"`` and ``"state_pixels"`` (the keypoints beside the image; :mod:`envs.pixels`).
PP_OBS_MODES = ("state", "particles", "pixels", "state_pixels")


class PickPlaceTask(ShapedTask, ParticleTask):
    """``num_envs`` copies of an object on a table, moved by pick-and-place (module docstring).

    Subclasses define :meth:`build_object`, :meth:`sample_episode`, :meth:`progress`,
    :meth:`success`, :attr:`p_goal`, :attr:`keypoints` and :attr:`goal_dim` (the goal's
    entries in the observation, from :meth:`goal_features`) or :attr:`goal_per_point`.
    """

    force_dim = 1
    #: The progress that counts as done (``normalized_performance`` is 1 there).
    p_goal: float = 1.0
    #: Entries per copy of the task's goal data (``self.target``, (num_envs, target_size)).
    target_size: ClassVar[int] = 1
    #: The goal's entries in the observation.
    goal_dim: ClassVar[int] = 0
    #: True for a goal observed as one point per observed particle (where that particle
    #: belongs): :attr:`goal_dim` is then twice the observed particles, set by
    #: :meth:`set_obs_mode`.
    goal_per_point: ClassVar[bool] = False

    def __init__(self, num_envs: int, *, action_mode: str, num_grippers: int, dt: float,
                 integrator: str, speed: float, grab_radius: float, mouse_ks: float,
                 mouse_kd: float, hold_time: float, settle_time: float, rest_speed: float,
                 chunk: int, residual_limit: float, max_move: float = 0.05) -> None:
        if not isinstance(action_mode, str) or action_mode not in PICK_PLACE_MODES:
            raise ValueError(f"action_mode must be one of {PICK_PLACE_MODES}, "
                             f"got {action_mode!r}")
        self.num_grippers = check_positive("num_grippers", num_grippers, integer=True,
                                           maximum=2)
        self.speed = check_positive("speed", speed, maximum=100.0)
        self.hold_time = check_positive("hold_time", hold_time, allow_zero=True, maximum=100.0)
        self.settle_time = check_positive("settle_time", settle_time, maximum=1000.0)
        self.chunk = check_positive("chunk", chunk, integer=True, maximum=1000)
        self.max_move = check_positive("max_move", max_move, maximum=10.0)
        self.obs_mode = "state"
        super().__init__(num_envs, action_mode="force", dt=dt, substeps=1,
                         integrator=integrator, max_force=1.0, grab_radius=grab_radius,
                         mouse_ks=mouse_ks, mouse_kd=mouse_kd, goal_tolerance=1.0,
                         rest_speed=rest_speed, hold_steps=1, residual_limit=residual_limit)
        self.action_mode = action_mode
        N, G = self.num_envs, self.num_grippers
        # (the base made the action buffer and space for 4 numbers per gripper)
        self.__dict__["action"] = np.zeros((N, self.action_dim))
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.action_dim,), np.float32)
        self.tracked_particles = np.arange(self.n)
        self.grippers: MouseSpring = self.system.forces[self._mouse_block]
        self.table: TableFriction = self.system.forces[self._table_block]
        #: Each copy's goal data (the task's own: a target curve, a fold line, ...).
        self.target = np.zeros((N, self.target_size))
        #: Each copy's progress at the start of its episode.
        self.p_start = np.zeros(N)
        #: Whether each copy came to rest within ``settle_time`` on its last step.
        self.settled = np.ones(N, bool)
        #: Whether each gripper of each copy held a particle on the last step (N, G).
        self.grabbed = np.zeros((N, G), bool)
        self._idle: np.ndarray | None = None
        self.chunk_time = self.dt * self.chunk
        self.hold_chunks = int(math.ceil(self.hold_time / self.chunk_time - 1e-9))
        self.settle_chunks = max(1, int(math.ceil(self.settle_time / self.chunk_time - 1e-9)))
        #: Chunks of one drag step: ``max_move`` at ``speed``.
        self.drag_chunks = max(1, int(math.ceil(self.max_move / (self.speed * self.chunk_time)
                                                - 1e-9)))
        #: Drag mode: each gripper's position (N, G, 2) m and the particle it holds (index
        #: within the copy, -1 for none), (N, G).
        self.gripper_pos = np.zeros((N, G, 2))
        self.holding = np.full((N, G), -1, np.int64)
        self.set_obs_mode("state")

    def set_obs_mode(self, obs_mode: str) -> spaces.Box:
        """Observe the keypoints (``"state"``) or every particle (``"particles"``), each with
        its goal point if :attr:`goal_per_point`; returns the observation space of one copy
        (ValueError naming ``obs_mode`` for another value)."""
        if not isinstance(obs_mode, str) or obs_mode not in PP_OBS_MODES:
            raise ValueError(f"obs_mode must be one of {PP_OBS_MODES}, got {obs_mode!r}")
        self.obs_mode = obs_mode
        seen = 2 * (self.n if obs_mode == "particles" else len(self.keypoints))
        if self.goal_per_point:
            self.goal_dim = seen
        size = seen + self.goal_dim + 3 * self.num_grippers * (self.action_mode == "drag")
        self.single_observation_space = spaces.Box(-OBS_LIMIT, OBS_LIMIT, (size,), np.float32)
        return self.single_observation_space

    @property
    def physics_line(self) -> str:
        """The docs' overview table's "physics per env step" entry."""
        return (f"`{self.integrator}`, {1000 * self.dt:g} ms steps until at rest "
                f"(at most {self.settle_time:g} s after the release)")

    # ------------------------------------------------------------------ subclass hooks
    #: Particles (indices within a copy) observed in ``obs_mode="state"``.
    keypoints: np.ndarray

    def build_object(self) -> ParticleSystem:
        """One copy of the object, with its forces and constraints, without table friction
        (added by :meth:`build_scene`)."""
        raise NotImplementedError

    #: Friction coefficient of the table (dimensionless) and its regularisation speed (m/s).
    mu: float = 0.5
    friction_v_s: float = 0.01

    def sample_episode(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A start of one copy from ``rng`` alone: positions (n, 2) m at rest, and the goal
        data (target_size,)."""
        raise NotImplementedError

    def progress(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The progress measure ``p`` per copy from positions (k, n, 2) and goal data
        (k, target_size)."""
        raise NotImplementedError

    def success(self, x: np.ndarray, target: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The success test per copy (bools) from positions, goal data and progress ``p``."""
        raise NotImplementedError

    def distance(self, p: np.ndarray) -> np.ndarray:
        """The task's cost to go (the ``distance`` measure, >= 0) from progress ``p``:
        ``p_goal - p`` clipped at 0."""
        return np.maximum(self.p_goal - p, 0.0)

    def goal_features(self, envs: np.ndarray) -> np.ndarray:
        """The goal's observed entries (len(envs), goal_dim), normalised (none here)."""
        return np.zeros((len(envs), 0))

    # ------------------------------------------------------------------ scene
    def build_scene(self) -> ParticleSystem:
        """The object, the table's friction on every particle, and the grippers' mouse springs
        (one element per gripper, inactive)."""
        s = self.build_object()
        s.add(TableFriction(mu=self.mu, v_s=self.friction_v_s))
        self._table_block = len(s.forces) - 1
        s.add(MouseSpring(np.zeros(self.num_grippers, np.int64), ks=self.mouse_ks,
                          kd=self.mouse_kd))
        s.forces[-1].active[:] = False
        self._mouse_block = len(s.forces) - 1
        return s

    def force_handles(self, scene: ParticleSystem) -> np.ndarray:
        """(The base class's force actuator, kept at zero: the grippers act instead.)"""
        return np.array([0])

    def force_vectors(self, action: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Zero: the grippers' springs act instead of the force actuator."""
        return np.zeros((len(action), 1, 2))

    @property
    def action_dim(self) -> int:
        """Four numbers per gripper (pick x, y and place x, y); in drag mode three (a move
        x, y and a grip flag)."""
        return (3 if self.__dict__.get("action_mode") == "drag" else 4) * self.num_grippers

    def sample_start(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        """(The base hook: :meth:`sample_starts` draws the goal data too.)"""
        x, _ = self.sample_episode(rng)
        return x, np.zeros_like(x), 0.0

    def sample_starts(self, rngs: Sequence[np.random.Generator]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample_episode` from each generator: positions, velocities (zero), goals
        (zero: the goal data is ``target``) and goal data, stacked."""
        n = self.n
        x = np.empty((len(rngs), n, 2))
        target = np.empty((len(rngs), self.target_size))
        for k, rng in enumerate(rngs):
            xk, tk = self.sample_episode(rng)
            x[k], target[k] = xk, tk
        return x, np.zeros_like(x), np.zeros(len(rngs)), target

    def write_starts(self, envs: Sequence[int] | np.ndarray, x: np.ndarray, v: np.ndarray,
                     goal: np.ndarray, target: np.ndarray | None = None) -> None:
        """Write starts and their goal data; record their starting progress."""
        envs = np.asarray(envs, dtype=np.int64).reshape(-1)
        if target is not None and len(envs):
            self.target[envs] = target
        if len(envs):
            self.p_start[envs] = self.progress(np.reshape(x, (len(envs), self.n, 2)),
                                               self.target[envs])
            self.settled[envs] = True
            self.grabbed[envs] = False
            self.holding[envs] = -1
            self.gripper_pos[envs] = np.reshape(x, (len(envs), self.n, 2)).mean(axis=1)[:, None]
        super().write_starts(envs, x, v, goal)

    # ------------------------------------------------------------------ the step
    def apply(self, actions: np.ndarray, idle: np.ndarray | None = None) -> None:
        """Keep the clipped actions (the grippers act in :meth:`simulate`); ``idle`` copies
        (autoresetting) do nothing this step."""
        self.action[:] = actions
        self._idle = None if idle is None else idle.copy()
        if idle is not None:
            self.action[idle] = 0.0

    def _grab(self, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray]:
        """Each gripper's particle (global index), start and place points (m) and whether it
        holds one, for the copies in ``active``: (N, G) int, (N, G, 2), (N, G, 2), (N, G)."""
        N, G, n = self.num_envs, self.num_grippers, self.n
        x = self.positions()
        a = self.action.reshape(N, G, 4)
        pick = self.to_world(a[:, :, :2])
        place = self.to_world(a[:, :, 2:])
        d2 = ((x[:, None, :, :] - pick[:, :, None, :]) ** 2).sum(axis=3)  # (N, G, n)
        nearest = np.argmin(d2, axis=2)
        held = (np.take_along_axis(d2, nearest[:, :, None], axis=2)[:, :, 0]
                <= self.grab_radius**2) & active[:, None]
        if G == 2:
            held[:, 1] &= ~(held[:, 0] & (nearest[:, 1] == nearest[:, 0]))
        particle = nearest + (np.arange(N) * n)[:, None]
        start = x.reshape(-1, 2)[particle]
        return particle, start, place, held

    def simulate(self) -> np.ndarray:
        """One pick-and-place per copy (module docstring); returns the (num_envs,) mask of
        copies whose simulation diverged: each is put back in its state from before the step
        (grippers open, not settled) while the others go on as they would alone (copy ``i``
        still reproduces a single env); no NaN leaves this method. When every copy diverges,
        the whole step is taken back (the clock too)."""
        s, N, G, n = self.system, self.num_envs, self.num_grippers, self.n
        idle = np.zeros(N, bool) if self._idle is None else self._idle
        self._idle = None
        if self.action_mode == "drag":
            return self._drag(idle)
        particle, start, place, held = self._grab(~idle)
        self.grabbed[:] = held
        dist = np.sqrt(((place - start) ** 2).sum(axis=2))
        step_len = self.speed * self.chunk_time
        carry = np.where(held, np.ceil(dist / step_len), 0).astype(np.int64)  # (N, G)
        release = np.where(held.any(axis=1), carry.max(axis=1) + self.hold_chunks, 0)
        done = idle.copy()
        cap = release + self.settle_chunks
        rows_of = self._row_env
        lam = self._lam()
        x_done, v_done, lam_done = s.x.copy(), s.v.copy(), lam.copy()
        x0, v0, lam0, t0 = s.x.copy(), s.v.copy(), lam.copy(), s.t
        settled = np.ones(N, bool)
        grip = self.grippers
        flat_held = held.reshape(-1)
        flat_particle = np.where(flat_held, particle.reshape(-1), 0)
        if not np.array_equal(grip.particle, flat_particle):  # (a new index array: a repack)
            grip.set_checked(np.arange(N * G), flat_particle, grip.anchor, grip.active)
        j = 0
        moving = int(carry.max(initial=0))  # (chunks in which some anchor still moves)
        was_on = None
        lifted = self.table.lifted  # (the friction block covers every particle, in order)
        diverged = np.zeros(N, bool)
        try:
            while not done.all():
                on = (held & (j < release)[:, None] & ~done[:, None]).reshape(-1)
                if j <= moving:
                    frac = np.minimum(1.0, (j + 1) / np.maximum(carry, 1))[:, :, None]
                    grip.anchor[:] = (start + (place - start) * frac).reshape(-1, 2)
                if was_on is None or not np.array_equal(on, was_on):
                    grip.active[:] = on
                    lifted[:] = False
                    lifted[flat_particle[on]] = True
                    was_on = on
                bad = self._chunk()
                if bad.any():  # (those copies end the step as they began it)
                    bad &= ~done
                    if (diverged | bad).sum() == (~idle).sum() and not (done & ~idle).any():
                        return self._undo(x0, v0, t0, lam0)  # (every copy: as alone)
                    diverged |= bad
                    rows = np.repeat(bad, n)
                    x_done[rows], v_done[rows] = x0[rows], v0[rows]
                    lam_done[bad[rows_of]] = lam0[bad[rows_of]]
                    settled[bad] = False
                    done |= bad
                    was_on = None
                    continue
                j += 1
                if j < release[~done].min():  # (no copy can be done yet)
                    continue
                v = s.v
                speed2 = (v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]).reshape(N, n).max(axis=1)
                rest = speed2 < self.rest_speed**2
                finished = ~done & (j >= release) & (rest | (j >= cap))
                if finished.any():
                    settled[finished] = rest[finished]
                    rows = np.repeat(finished, n)
                    x_done[rows], v_done[rows] = s.x[rows], s.v[rows]
                    lrows = finished[rows_of]
                    lam_done[lrows] = self._lam()[lrows]
                    done |= finished
        except SimulationDiverged:
            return self._undo(x0, v0, t0, lam0)
        self._let_go()
        keep = ~idle
        rows = np.repeat(keep, n)
        s.x[rows], s.v[rows] = x_done[rows], v_done[rows]
        lam = self._lam()
        lrows = keep[rows_of]
        lam[lrows] = lam_done[lrows]
        self.settled[keep] = settled[keep]
        return diverged

    def _chunk(self) -> np.ndarray:
        """``chunk`` physics steps of the whole system; returns the (num_envs,) mask of the
        copies that diverge in them (none: the system advanced). When some do, the system is
        left as before the chunk, with those copies frozen (at rest, grippers open, on the
        table) so that the next try runs the others alone: each copy's arithmetic is its
        own, so which copies diverge is found by stepping each one with every other frozen."""
        s = self.system
        try:
            s.step(self.dt, self.integrator, steps=self.chunk)
            return np.zeros(self.num_envs, bool)
        except SimulationDiverged:
            pass
        x, v, t, lam = s.x.copy(), s.v.copy(), s.t, self._lam().copy()
        active, lifted = self.grippers.active.copy(), self.table.lifted.copy()
        bad = np.zeros(self.num_envs, bool)
        for c in range(self.num_envs):
            others = np.ones(self.num_envs, bool)
            others[c] = False
            self._freeze(others)
            try:
                s.step(self.dt, self.integrator, steps=self.chunk)
            except SimulationDiverged:
                bad[c] = True
            s.x, s.v, s.t = x.copy(), v.copy(), t
            self._lam()[:] = lam
            self.grippers.active[:], self.table.lifted[:] = active, lifted
        if not bad.any():  # (only together: none can be told apart)
            bad[:] = True
        self._freeze(bad)
        return bad

    def _freeze(self, copies: np.ndarray) -> None:
        """The masked copies at rest where they are, their grippers open, on the table."""
        s, n, G = self.system, self.n, self.num_grippers
        s.v[np.repeat(copies, n)] = 0.0
        self.grippers.active.reshape(self.num_envs, G)[copies] = False
        self.table.lifted.reshape(self.num_envs, n)[copies] = False

    def _drag(self, idle: np.ndarray) -> np.ndarray:
        """One step of drag mode: each gripper with ``grip > 0`` holds (or grabs, within
        ``grab_radius`` of where it is) a particle, ``grip <= 0`` lets go; each moves by
        ``max_move`` times its move (clipped to the view box) in a straight line at ``speed``,
        its particle following on the mouse spring, lifted. The step lasts ``drag_chunks``
        chunks whatever the copies do, so the copies keep one schedule."""
        s, N, G, n = self.system, self.num_envs, self.num_grippers, self.n
        a = self.action.reshape(N, G, 3)
        grip = (a[:, :, 2] > 0) & ~idle[:, None]
        self.holding[~grip] = -1
        x = self.positions()
        pos = self.gripper_pos
        d2 = ((x[:, None, :, :] - pos[:, :, None, :]) ** 2).sum(axis=3)
        nearest = np.argmin(d2, axis=2)
        near = np.take_along_axis(d2, nearest[:, :, None], axis=2)[:, :, 0] <= self.grab_radius**2
        new = grip & (self.holding < 0) & near
        self.holding[new] = nearest[new]
        # (a gripper closes on the particle it takes: its spring starts unstretched)
        taken = x[np.arange(N)[:, None], nearest]  # (N, G, 2)
        pos[new] = taken[new]
        if G == 2:  # (two grippers on one particle: the second lets go)
            same = (self.holding[:, 1] >= 0) & (self.holding[:, 1] == self.holding[:, 0])
            self.holding[same, 1] = -1
        held = self.holding >= 0
        self.grabbed[:] = held
        lo, hi = np.array(self.view[:2]), np.array(self.view[2:])
        start = pos.copy()
        target = np.minimum(np.maximum(start + self.max_move * a[:, :, :2], lo), hi)
        flat = np.where(held, self.holding + (np.arange(N) * n)[:, None], 0).reshape(-1)
        springs = self.grippers
        if not np.array_equal(springs.particle, flat):
            springs.set_checked(np.arange(N * G), flat, springs.anchor, springs.active)
        on = held.reshape(-1)
        springs.active[:] = on
        self.table.lifted[:] = False
        self.table.lifted[flat[on]] = True
        x0, v0, lam0, t0 = s.x.copy(), s.v.copy(), self._lam().copy(), s.t
        diverged = np.zeros(N, bool)
        j = 0
        while j < self.drag_chunks:
            u = (j + 1) / self.drag_chunks
            frac = u * u * (3.0 - 2.0 * u)  # (smooth: the gripper starts and stops at rest)
            springs.anchor[:] = (start + (target - start) * frac).reshape(-1, 2)
            bad = self._chunk()
            if bad.any():
                if (diverged | bad).all():
                    return self._undo(x0, v0, t0, lam0)  # (every copy: as alone)
                diverged |= bad
                continue  # (the chunk again, those copies frozen by _chunk)
            j += 1
        self._let_go()
        moved = ~idle & ~diverged
        self.gripper_pos[moved] = target[moved]
        v = s.v
        speed2 = (v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]).reshape(N, n).max(axis=1)
        self.settled[:] = speed2 < self.rest_speed**2
        if diverged.any():  # (as they began the step)
            rows = np.repeat(diverged, n)
            s.x[rows], s.v[rows] = x0[rows], v0[rows]
            lrows = diverged[self._row_env]
            self._lam()[lrows] = lam0[lrows]
            self.settled[diverged] = False
        return diverged

    def _undo(self, x0: np.ndarray, v0: np.ndarray, t0: float, lam0: np.ndarray
              ) -> np.ndarray:
        """A diverged step taken back: the state, time and multipliers it started from, the
        grippers open, no copy settled; every copy flagged diverged (num_envs,) bool."""
        s = self.system
        s.x, s.v, s.t = x0, v0, t0
        self._lam()[:] = lam0
        self._let_go()
        self.settled[:] = False
        return np.ones(self.num_envs, bool)

    def _let_go(self) -> None:
        """Every gripper inactive, every particle on the table."""
        self.grippers.active[:] = False
        self.table.lifted[:] = False

    # ------------------------------------------------------------------ measures
    def add_measures(self, m: dict[str, np.ndarray], wall_force: np.ndarray
                     ) -> dict[str, np.ndarray]:
        """The task's ``progress`` ``p``, its cost to go as ``distance``, its success test as
        ``is_success``, ``normalized_performance`` ``(p - p_start) / (p_goal - p_start)`` and
        ``settled``."""
        x = self.positions()
        p = self.progress(x, self.target)
        m["distance"] = self.distance(p)
        m["is_success"] = self.success(x, self.target, p)
        m["progress"] = p
        span = self.p_goal - self.p_start
        m["normalized_performance"] = (p - self.p_start) / np.where(np.abs(span) > 1e-12,
                                                                    span, 1e-12)
        m["settled"] = self.settled.copy()
        return m

    def potential(self, m: dict[str, Any]) -> np.ndarray | float:
        """The cost to go: the ``distance`` measure."""
        return m["distance"]

    def _compiled_paths(self) -> dict[str, bool]:
        paths = super()._compiled_paths()
        paths["fresh_pack"] = type(self).simulate is PickPlaceTask.simulate
        paths["measure_observe"] = False  # (the observation is the task's own)
        return paths

    def observe(self) -> np.ndarray:
        """Observations (num_envs, D) float32: the normalised positions of the keypoints
        (``obs_mode="state"``) or of every particle (``"particles"``), then the goal's
        entries; clipped to [-OBS_LIMIT, OBS_LIMIT]."""
        x = self.observed_order(self.positions())
        if self.obs_mode == "state":
            x = x[:, self.keypoints]
        pos = ((x - self.center) * (1.0 / self.half)).reshape(self.num_envs, -1)
        parts = [pos, self.goal_features(self._every)]
        if self.action_mode == "drag":  # the grippers: positions, then holding flags
            parts += [((self.gripper_pos - self.center) * (1.0 / self.half)).reshape(
                self.num_envs, -1), (self.holding >= 0).astype(float)]
        obs = np.concatenate(parts, axis=1)
        return np.clip(obs, -OBS_LIMIT, OBS_LIMIT).astype(np.float32)

    def observed_order(self, x: np.ndarray) -> np.ndarray:
        """Positions (num_envs, n, 2) in the order the observation lists them: the particles'
        own order here (a task may list a symmetric object from a canonical end)."""
        return x

    def observed_points(self, obs: np.ndarray) -> np.ndarray:
        """World positions (B, k, 2) m of the observed particles in observations (B, D)."""
        o = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        k = self.n if self.obs_mode == "particles" else len(self.keypoints)
        return self.to_world(o[:, :2 * k].reshape(len(o), k, 2))

    def goal_part(self, obs: np.ndarray) -> np.ndarray:
        """The goal's entries (B, goal_dim) of observations (B, D)."""
        o = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        k = 2 * (self.n if self.obs_mode == "particles" else len(self.keypoints))
        return o[:, k:k + self.goal_dim]

    def gripper_part(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drag mode: the grippers' positions (B, G, 2) m and holding flags (B, G) of
        observations (B, D)."""
        o = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        G = self.num_grippers
        tail = o[:, o.shape[1] - 3 * G:]
        return self.to_world(tail[:, :2 * G].reshape(len(o), G, 2)), tail[:, 2 * G:] > 0.5

    def drag_pointer(self) -> dict[str, float]:
        """The drag-mode geometry of the scripted agents' rule (:func:`finish_action`) in
        normalised view units, as :class:`envs.policies.PointerPolicy` takes it (``drag``):
        ``move_scale``, the action per unit of offset (the view's half-width over
        ``max_move``); ``reach``, where a gripper grips (half of ``grab_radius``); ``place``,
        where it lets go (1 mm)."""
        half = float(self.half[0])
        if not np.isclose(self.half[1], half):
            raise ValueError("drag_pointer: the view is not square")
        return {"move_scale": half / self.max_move, "reach": 0.5 * self.grab_radius / half,
                "place": PLACE_TOLERANCE / half}

    # ------------------------------------------------------------------ state
    def get_state(self, i: int) -> dict[str, Any]:
        """The base state plus the goal data ``target``, ``p_start`` and ``settled``."""
        state = super().get_state(i)
        state.update(target=self.target[i].copy(), p_start=float(self.p_start[i]),
                     settled=bool(self.settled[i]), gripper_pos=self.gripper_pos[i].copy(),
                     holding=self.holding[i].copy())
        return state

    def set_state(self, i: int, state: dict[str, Any]) -> None:
        """Restore copy ``i`` from :meth:`get_state`; ValueError naming a bad field."""
        if not isinstance(state, dict):
            raise ValueError(f"state must be a dict from get_state(), got {type(state).__name__}")
        missing = {"target", "p_start", "settled", "gripper_pos", "holding"} - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")
        try:
            target = np.asarray(state["target"], dtype=float)
            p_start = float(state["p_start"])
        except (TypeError, ValueError):
            raise ValueError("state['target'] and state['p_start'] must be numbers") from None
        if target.shape != (self.target_size,) or not np.all(np.isfinite(target)):
            raise ValueError(f"state['target'] must be a finite array of shape "
                             f"({self.target_size},), got {state['target']!r}")
        if not math.isfinite(p_start):
            raise ValueError(f"state['p_start'] must be finite, got {state['p_start']!r}")
        if not isinstance(state["settled"], (bool, np.bool_)):
            raise ValueError(f"state['settled'] must be a bool, got {state['settled']!r}")
        G = self.num_grippers
        try:
            pos = np.asarray(state["gripper_pos"], dtype=float)
            holding = np.asarray(state["holding"])
        except (TypeError, ValueError):
            raise ValueError("state['gripper_pos'] must be numbers") from None
        if pos.shape != (G, 2) or not np.all(np.isfinite(pos)):
            raise ValueError(f"state['gripper_pos'] must be a finite array of shape ({G}, 2), "
                             f"got {state['gripper_pos']!r}")
        if (holding.shape != (G,) or holding.dtype.kind not in "iu"
                or np.any(holding < -1) or np.any(holding >= self.n)):
            raise ValueError(f"state['holding'] must be {G} particle indices or -1, "
                             f"got {state['holding']!r}")
        self.check_state(state)
        self.gripper_pos[i] = pos
        self.holding[i] = holding
        self.target[i] = target
        self.p_start[i] = p_start
        self.settled[i] = bool(state["settled"])
        super().set_state(i, state)

    # ------------------------------------------------------------------ drawing
    def target_segments(self) -> np.ndarray | None:
        """Every copy's target as line segments (num_envs, k, 2, 2) m (segment, end, xy), or
        None for a task whose target is no line (here)."""
        return None

    def target_shapes(self, i: int) -> list[Shape]:
        """Shapes drawing copy ``i``'s goal in the human view: its :meth:`target_segments`."""
        segments = self.target_segments()
        if segments is None:
            return []
        return [Shape("segment", "mouse", segments[i, :, 0], segments[i, :, 1])]

    def picture(self) -> Picture:
        """What a pixel observation shows: the default picture (the object, the grippers'
        springs while they carry) without a goal disk, and under the object the task's target
        (:meth:`target_segments`: RopeShape's curve, ClothFold's fold line) as lines."""
        pic = default_picture(self, goal=False)
        segments = self.target_segments()
        if segments is not None:
            count = segments.shape[1]
            ends = pic.add_moving(
                2 * count, lambda task: task.target_segments().reshape(task.num_envs, -1, 2))
            pic.marks.insert(fixed_marks(pic), Mark("segments", ends.reshape(-1, 2), GOAL,
                                                    opacity=0.7, size=1.5))
        return pic

    def drawing(self, i: int) -> tuple[ParticleSystem, list[Shape], str]:
        """Copy ``i`` without its (idle) grippers, its goal, and a status line."""
        one = self.load_single(i)
        p = float(self.progress(one.x[None], self.target[i:i + 1])[0])
        status = (f"{type(self).__name__}   progress {p:.3f} (goal {self.p_goal:g})   "
                  f"{'at rest' if self.settled[i] else 'moving'}")
        return one, self.target_shapes(i), status


class DragPlan:
    """A scripted agent's memory in drag mode, where one pick-and-place takes several steps:
    the place each gripper carries its particle to, fixed when it takes the particle and kept
    until it lets go. An oracle that chooses afresh every step (the particle furthest from its
    place, say) would otherwise turn towards another particle's place as soon as the one it
    carries is no longer the furthest. One plan per agent (and batch size: a plan whose batch
    size changes starts afresh); a row whose gripper holds nothing plans afresh, so an
    episode's reset needs no notice.

    ``keep_places=False``: a holding gripper heads for its particle's place as the agent gives
    it at each step (an agent that picks the particle a gripper holds while it holds it, and
    whose places move with the object, as ClothFlatten's flat cloth fitted to the cloth as it
    lies); the plan then only records where the grippers head (:attr:`heading`)."""

    def __init__(self, keep_places: bool = True) -> None:
        self.keep_places = keep_places
        self.place: np.ndarray | None = None  # (B, G, 2) m: each gripper's kept place
        self.kept = np.zeros((0, 0), dtype=bool)  # (B, G): the place is kept
        #: The pick and place points (B, G, 2) m each gripper headed for in the last action
        #: (:func:`finish_action`): the pair it works on, which a clone learns to choose.
        self.heading: tuple[np.ndarray, np.ndarray] | None = None

    def follow(self, pos: np.ndarray, holding: np.ndarray, pick: np.ndarray,
               place: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pick and place points (B, G, 2) m to head for, from the grippers' positions
        ``pos`` (B, G, 2) m and holding flags ``holding`` (B, G) and the agent's fresh pairs
        ``pick``, ``place``: a holding gripper takes the pair whose pick point is nearest to
        it (the pairs are swapped between grippers, not changed) and keeps its place while it
        holds."""
        pick, place = pick.copy(), place.copy()
        B, G = holding.shape
        if self.place is None or self.place.shape != place.shape:
            self.place, self.kept = place.copy(), np.zeros((B, G), dtype=bool)
        for b in np.flatnonzero(holding.any(axis=1)):  # each holding gripper takes the pair
            claimed = np.zeros(G, dtype=bool)  # of the particle it holds: the nearest pick
            for g in np.flatnonzero(holding[b]):  # among the pairs not yet taken so
                free = np.flatnonzero(~claimed)
                j = int(free[np.argmin(np.linalg.norm(pick[b, free] - pos[b, g], axis=1))])
                pick[b, [g, j]], place[b, [g, j]] = pick[b, [j, g]], place[b, [j, g]]
                claimed[g] = True
        keep = holding & self.kept if self.keep_places else np.zeros_like(holding)
        place = np.where(keep[:, :, None], self.place, place)
        self.place = place.copy()
        return pick, place

    def carrying(self, carrying: np.ndarray) -> None:
        """Record which grippers carry (or take, this step) a particle (B, G): their places
        are kept from now on."""
        self.kept = carrying.copy()


def finish_action(task: PickPlaceTask, obs: np.ndarray, pick_place: np.ndarray,
                  plan: DragPlan | None = None) -> np.ndarray:
    """A scripted agent's action from its pick-and-place actions ``pick_place`` (B, 4 G) in
    normalised coordinates: clipped to the Box as float32, one row for one observation; in drag
    mode turned into moves: each gripper that holds nothing heads for its pick point and grips
    once there, one that holds a particle heads for the place point and lets go there.
    ``plan``: the agent's :class:`DragPlan` (drag mode), so that a gripper carries its particle
    to the place chosen when it took it."""
    a = np.asarray(pick_place, dtype=np.float64)
    if task.action_mode == "drag":
        B, G = len(a), task.num_grippers
        pos, holding = task.gripper_part(obs)
        pp = a.reshape(B, G, 4)
        pick, place = task.to_world(pp[:, :, :2]), task.to_world(pp[:, :, 2:])
        if plan is not None:
            pick, place = plan.follow(pos, holding, pick, place)
            plan.heading = (pick, place)
        at_pick = np.linalg.norm(pick - pos, axis=2) <= 0.5 * task.grab_radius
        at_place = np.linalg.norm(place - pos, axis=2) <= PLACE_TOLERANCE
        carrying = holding | at_pick
        if plan is not None:
            plan.carrying(carrying & ~(holding & at_place))
        go = np.where(carrying[:, :, None], place, pick)
        move = (go - pos) * (1.0 / task.max_move)
        grip = np.where(carrying & ~(holding & at_place), 1.0, -1.0)
        a = np.concatenate([np.clip(move, -1.0, 1.0), grip[:, :, None]], axis=2).reshape(B, -1)
    a = np.clip(a, -1.0, 1.0).astype(np.float32)
    return a if np.ndim(obs) > 1 else a[0]


class PickPlaceEnv(ParticleEnv):
    """A single pick-and-place env (subclasses set ``task_class``). ``obs_mode``: ``"state"``
    (keypoints and the goal, the default), ``"particles"`` (every particle and the goal),
    ``"pixels"`` or ``"state_pixels"`` (:mod:`envs.pixels`, with ``pixel_size`` and
    ``pixel_channels``); ``"goal"`` is refused (these tasks' goals are not points: see
    ``obs_modes`` of :class:`envs.task.TaskSpec`)."""

    task_class: ClassVar[type[PickPlaceTask]]
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"],
                                          "render_fps": 4}

    def __init__(self, render_mode: str | None = None, *, obs_mode: str = "state",
                 **kwargs: object) -> None:
        if not isinstance(obs_mode, str) or obs_mode not in PP_OBS_MODES:
            raise ValueError(f"obs_mode must be one of {PP_OBS_MODES}, got {obs_mode!r}")
        particles = obs_mode == "particles"
        super().__init__(render_mode, obs_mode="state" if particles else obs_mode, **kwargs)
        if particles:
            self.obs_mode = obs_mode
            self.observation_space = self.task.set_obs_mode(obs_mode)
        self.metadata = {**self.metadata, "render_fps": 4}


class PickPlaceVectorEnv(ParticleVectorEnv):
    """The native vector env of a pick-and-place task (subclasses set ``task_class``):
    ``num_envs`` copies stepped as one particle system, each on its own schedule."""

    task_class: ClassVar[type[PickPlaceTask]]
    metadata: ClassVar[dict[str, Any]] = {**ParticleVectorEnv.metadata, "render_fps": 4}

    def __init__(self, num_envs: int = 1, max_episode_steps: int | None = None,
                 render_mode: str | None = None, *, obs_mode: str = "state",
                 **kwargs: object) -> None:
        if not isinstance(obs_mode, str) or obs_mode not in PP_OBS_MODES:
            raise ValueError(f"obs_mode must be one of {PP_OBS_MODES}, got {obs_mode!r}")
        particles = obs_mode == "particles"
        super().__init__(num_envs, max_episode_steps, render_mode,
                         obs_mode="state" if particles else obs_mode, **kwargs)
        if particles:
            self.obs_mode = obs_mode
            self.single_observation_space = self.task.set_obs_mode(obs_mode)
            self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.metadata = {**self.metadata, "render_fps": 4}

