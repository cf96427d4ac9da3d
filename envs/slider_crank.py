"""SliderCrank-v0: turn a crank on a circular wire until its rod-linked slider holds at a goal."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from constrained_particles import Drag, ParticleSystem, scenes

from . import _measure
from .agents import ScriptedAgent
from .base import ACTION_MODES, ParticleTask, _measured
from .checks import _owned, away, check_goal_range, check_positive, scaled
from .rewards import SUCCESS_BONUS, TIME_COST, ShapedTask
from .single import ParticleEnv
from .task import TaskSpec, ppo, sac
from .vector import ParticleVectorEnv


class SliderCrank(ShapedTask, ParticleTask):
    """The SliderCrank physics and task for ``num_envs`` copies (see :class:`SliderCrankEnv`)."""

    force_dim = 1

    def __init__(self, num_envs: int = 1, *, action_mode: str = "force", radius: float = 0.3,
                 rod: float = 0.8, particle_mass: float = 0.1, drag: float = 0.05,
                 dt: float = 0.025, substeps: int = 2, integrator: str = "rk4",
                 max_force: float = 2.0, goal_range: tuple[float, float] = (0.8, 1.05),
                 min_distance: float = 0.1, max_start_speed: float = 2.0,
                 goal_tolerance: float = 0.02, rest_speed: float = 0.05,
                 hold_steps: int = 5,
                 rest_window: int = 10, grab_radius: float = math.inf, mouse_ks: float = 20.0,
                 mouse_kd: float = 1.0, residual_limit: float = 0.01) -> None:
        self.radius = check_positive("radius", radius, minimum=1e-3, maximum=1e3)
        self.rod = check_positive("rod", rod, minimum=1e-3, maximum=1e3)
        if self.rod <= self.radius:
            raise ValueError(f"rod must exceed radius so the slider can always reach the wire, "
                             f"got rod={rod}, radius={radius}")
        self.particle_mass = check_positive("particle_mass", particle_mass)
        self.drag = check_positive("drag", drag, allow_zero=True)
        self.max_start_speed = check_positive("max_start_speed", max_start_speed,
                                              allow_zero=True)
        self.goal_range, self.min_distance = check_goal_range(goal_range, min_distance)
        low, high = self.goal_range
        if low <= self.rod - self.radius or high >= self.rod + self.radius:
            raise ValueError(f"goal_range must lie inside the slider's stroke "
                             f"({self.rod - self.radius:g}, {self.rod + self.radius:g}) m, "
                             f"got {goal_range!r}")
        r, L = self.radius, self.rod
        # rk4 carries the crank's rotation to about 1 rad per step (13 m/s at the defaults) and
        # then loses the wire: steps longer than 0.4 rad of crank turn are split
        self.step_travel = 0.4 * r
        self.view = (-r - 0.15, -r - 0.15, L + r + 0.15, r + 0.15)
        self.goal_height = 0.0
        #: The tracked coordinate is the slider's x (m).
        self.tracked_particles = np.array([1])
        #: ((copies, radius, rod), goals, their crank angles) last used by the compiled measure
        #: (see :func:`crank_measures`); rebuilt when the copies or the geometry change
        self._goal_angle: tuple[tuple, np.ndarray, np.ndarray] | None = None
        super().__init__(num_envs, action_mode=action_mode, dt=dt, substeps=substeps,
                         integrator=integrator, max_force=max_force, grab_radius=grab_radius,
                         mouse_ks=mouse_ks, mouse_kd=mouse_kd, goal_tolerance=goal_tolerance,
                         rest_speed=rest_speed, hold_steps=hold_steps, rest_window=rest_window,
                         residual_limit=residual_limit)

    def build_scene(self) -> ParticleSystem:
        """``scenes.wire_mixture`` (crank 0 on a circle about the origin, slider 1 on y = 0, a rod
        between them) plus air drag on both particles."""
        s = scenes.wire_mixture(radius=self.radius, rod=self.rod, wire_height=0.0, angle=0.0,
                                omega=0.0, mass=self.particle_mass)
        if self.drag > 0:
            s.add(Drag(self.drag))
        return s

    def force_handles(self, scene: ParticleSystem) -> np.ndarray:
        """The crank particle."""
        return np.array([0])

    def _compiled_paths(self) -> dict[str, bool]:
        """``ParticleTask._compiled_paths`` for the crank: ``measure_observe`` with this
        class's :meth:`measure`; ``push`` (:meth:`force_vectors` compiled); ``starts``
        (:meth:`sample_starts` in one pass: ``sample_start`` and ``linkage`` as written);
        ``finish`` (:meth:`_finish_step`: the measures, observation, potential and reward as
        written)."""
        paths = super()._compiled_paths()
        cls = type(self)
        paths["measure_observe"] = (cls.measure is SliderCrank.measure
                                    and cls.observe is ParticleTask.observe)
        paths["push"] = cls.force_vectors is SliderCrank.force_vectors
        paths["starts"] = (cls.sample_start is SliderCrank.sample_start
                           and cls.linkage is SliderCrank.linkage)
        paths["finish"] = (paths["measure_observe"]
                           and cls.measure_observe is SliderCrank.measure_observe
                           and cls.potential is SliderCrank.potential
                           and cls.penalties is ShapedTask.penalties
                           and cls.reward is ShapedTask.reward)
        return paths

    def force_vectors(self, action: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``action * max_force`` (N) along the crank's counter-clockwise tangent."""
        if (_measure.ENABLED and _owned(action, np.float64, (len(action), 1))
                and _owned(x, np.float64, (len(action), self.n, 2))):  # compiled; the
            f = np.empty((len(action), 1, 2))  # reference is below
            crank_push(x, action, self.max_force, f)
            return f
        crank = x[:, 0, :]
        tangent = np.stack([-crank[:, 1], crank[:, 0]], axis=1)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        return (action * self.max_force)[:, :, None] * tangent[:, None, :]

    def _write_forces(self, action: np.ndarray, out: np.ndarray) -> None:
        """:meth:`force_vectors` written straight into the actuator's rows ``out`` (compiled),
        unless a subclass redefines it."""
        if (_measure.ENABLED and self._paths["push"]
                and out.flags.c_contiguous and out.dtype == np.float64
                and out.shape == (self.num_envs, 2)
                and _owned(action, np.float64, (self.num_envs, 1))
                and (state := self._compiled_state()) is not None):
            crank_push(state[0].reshape(self.num_envs, self.n, 2), action,
                                self.max_force, out.reshape(self.num_envs, 1, 2))
            return
        super()._write_forces(action, out)

    def _linkage_values(self, angle: float, omega: float) -> tuple[float, ...]:
        """:meth:`linkage` as eight numbers: crank x, y, slider x, y (m), then their
        velocities (m/s)."""
        r, L = self.radius, self.rod
        c, s = math.cos(angle), math.sin(angle)
        reach = math.sqrt(L**2 - (r * s) ** 2)
        dslider = -r * s - (r * s) * (r * c) / reach  # d(slider x)/d(angle)
        return (r * c, r * s, r * c + reach, 0.0,
                omega * (-r * s), omega * (r * c), omega * dslider, 0.0)

    def linkage(self, angle: float, omega: float) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities (2, 2) of crank and slider for crank ``angle`` (rad,
        counter-clockwise from +x) and angular speed ``omega`` (rad/s)."""
        values = self._linkage_values(angle, omega)
        return np.array(values[:4]).reshape(2, 2), np.array(values[4:]).reshape(2, 2)

    def _draw(self, rng: np.random.Generator) -> tuple[tuple[float, ...], float]:
        """One start's draws from ``rng``: the linkage's eight numbers (see
        :meth:`_linkage_values`) and the goal (m). Three uniform doubles, drawn in one call
        (the same three that three calls of ``rng.random()`` return): the crank angle
        ~ U(-pi, pi), the angular speed ~ U(+-max_start_speed / radius), and the goal's draw
        (:func:`~envs.checks.uniform_away`)."""
        u_angle, u_speed, u_goal = rng.random(3).tolist()
        angle = scaled(u_angle, -np.pi, np.pi)
        omega = scaled(u_speed, -1.0, 1.0) * self.max_start_speed / self.radius
        values = self._linkage_values(angle, omega)
        low, high = self.goal_range
        return values, away(u_goal, low, high, values[2], self.min_distance)

    def sample_start(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        """Crank angle ~ U(-pi, pi), angular speed ~ U(+-max_start_speed / radius); the goal
        uniform over goal_range at least ``min_distance`` from the slider's start."""
        values, goal = self._draw(rng)
        return np.array(values[:4]).reshape(2, 2), np.array(values[4:]).reshape(2, 2), goal

    def sample_starts(self, rngs: Sequence[np.random.Generator]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample_start` for each generator, stacked (the same draws and arithmetic,
        so bit for bit the same starts). A subclass that redefines ``sample_start`` or
        ``linkage`` gets the base version, which calls them."""
        if not self._paths["starts"]:
            return super().sample_starts(rngs)
        draws = [self._draw(rng) for rng in rngs]
        states = np.array([values for values, _ in draws]).reshape(len(rngs), 2, 2, 2)
        return (np.ascontiguousarray(states[:, 0]), np.ascontiguousarray(states[:, 1]),
                np.array([goal for _, goal in draws], dtype=np.float64))

    def measure(self, stepped: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The common measures plus ``crank_height``: the crank's y (m; the success test also
        needs the crank above the slider's wire, ``crank_height > 0``: a step held at the goal
        and at rest, but below, does not count), and ``crank_to_go``: the arc length (m) along
        the crank's wire, the short way round, from the crank to the point above the wire that
        puts the slider at the goal."""
        N = self.num_envs
        r, L, g = self.radius, self.rod, self.goal
        state = self._compiled_state()
        if state is not None and _owned(g, np.float64, (N,)):
            height, to_go, below = np.empty(N), np.empty(N), np.empty(N, bool)
            crank_measures(state[0], self.n, g, tuple(self._crank_record(height, to_go, below)))
        else:
            crank = self.positions()[:, 0]
            height = crank[:, 1].copy()
            below = ~(height > 0)
            target = np.arccos(np.clip((g**2 + r**2 - L**2) / (2 * g * r), -1.0, 1.0))
            theta = np.arctan2(crank[:, 1], crank[:, 0])
            to_go = r * np.abs(np.angle(np.exp(1j * (target - theta))))
        m, _ = self._measures(stepped, blocked=below)
        m["crank_height"] = height
        m["crank_to_go"] = to_go
        return m

    def measure_observe(self, stepped: np.ndarray | None = None
                        ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """:meth:`measure`, then :meth:`observe`: in one compiled call
        (:func:`crank_measures_observe`) unless a subclass redefines either."""
        post = self._compiled_post() if self._paths["measure_observe"] else None
        if post is None:
            return super().measure_observe(stepped)
        p, goal, (x, v, mass) = post
        values, flags, obs, m = self._crank_outputs()
        crank_measures_observe(
            tuple(self._crank_record(values[5], values[6], flags[1])), (x, v, mass), tuple(goal),
            p.refs.blocks, False, tuple(self._rest()), self._mask(stepped), values[:5],
            flags[0], tuple(self._view()), obs)
        return m, obs

    def _crank_record(self, height: np.ndarray, to_go: np.ndarray, below: np.ndarray
                      ) -> Crank:
        """The compiled crank measure's geometry, outputs and goal-angle cache."""
        r = float(self.radius)
        seen, target = self._goal_angles()
        return Crank(r, r**2, float(self.rod)**2, height, to_go, below, seen, target)

    def _finish_record(self, goal: _measure.Goal, values: np.ndarray, flags: np.ndarray,
                       obs: np.ndarray, before: np.ndarray, steps: np.ndarray, max_steps: int
                       ) -> tuple:
        """What the compiled end of a step writes (see :func:`crank_finish`) into
        :meth:`_crank_outputs`' blocks ``values``, ``flags`` and ``obs``, in the plain form
        (``constrained_particles.records.plain``) in which the kernels take it."""
        success, below, terminated, truncated, ended = flags
        return tuple(Finish(
            tuple(self._crank_record(values[5], values[6], below)), tuple(goal),
            tuple(self._rest()), self._every_copy, values[:5], success, tuple(self._view()), obs,
            tuple(_measure.Reward(before, float(self.shaping_scale), TIME_COST, SUCCESS_BONUS,
                                  values[7])),
            tuple(_measure.Episode(steps, int(max_steps), terminated, truncated, ended))))

    def _crank_outputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Fresh outputs of the compiled crank bookkeeping, filled in place by the kernels: a
        float block (8, num_envs) (the five measures' rows of ``_measure.measures_observe``,
        crank height, arc to go, reward), a bool block (5, num_envs) (success, crank below the
        wire, terminated, truncated, ended), the observation, and the measures dict over their
        rows."""
        N = self.num_envs
        values, flags = np.empty((8, N)), np.empty((5, N), bool)
        m = _measured(values[:5], flags[0])
        m["crank_height"] = values[5]
        m["crank_to_go"] = values[6]
        return values, flags, np.empty((N, 4 * self.n + 1), np.float32), m

    def _finish_step(self, steps: np.ndarray, max_steps: int) -> tuple | None:
        """After an env step that every copy took: :meth:`measure_observe` for all copies,
        :meth:`reward` and the episode counters (``steps`` advanced in place), in one compiled
        call (:func:`crank_finish`). Returns ``(obs, measures, reward,
        terminated, truncated, ended, number ended)``, or None where the general path must run
        (compiled bookkeeping off, or a subclass redefines a part of it)."""
        if not (self._paths["finish"] and steps.dtype == np.int64
                and steps.shape == (self.num_envs,)):
            return None
        post = self._compiled_post()
        before = self._phi()
        if post is None or before.dtype != np.float64 or before.shape != (self.num_envs,):
            return None
        p, goal, (x, v, mass) = post
        values, flags, obs, m = self._crank_outputs()
        count = crank_finish(
            x, v, mass, p.refs.blocks, self._finish_record(goal, values, flags, obs, before,
                                                            steps, max_steps))
        return obs, m, values[7], flags[2], flags[3], flags[4], count

    def _goal_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """The compiled crank measure's cache: the goals its angles were computed for (NaN:
        none yet) and those angles (rad); made anew when the copies or the geometry change."""
        key = (self.num_envs, self.radius, self.rod)
        if self._goal_angle is None or self._goal_angle[0] != key:
            self._goal_angle = (key, np.full(self.num_envs, np.nan), np.zeros(self.num_envs))
        return self._goal_angle[1], self._goal_angle[2]

    def potential(self, m: dict[str, np.ndarray]) -> np.ndarray:
        """Cost to go ``Phi = crank_to_go + s`` (m, m/s): zero only with the crank at rest at
        its goal point above the wire, and decreasing all the way along a swing-up through a
        dead centre (the slider's distance to the goal would first grow)."""
        return m["crank_to_go"] + m["speed"]


class SliderCrankEnv(ParticleEnv):
    """
    ## Description

    The constraint mixture of Witkin & Baraff's notes as a slider-crank: the crank particle rides
    a circular wire of radius ``radius`` about the origin, the slider particle rides a horizontal
    wire at y = 0, and a rigid rod of length ``rod`` joins them; all three are
    Lagrange-multiplier constraints solved together. Gravity pulls the crank down and air drag
    slows both. Bring the slider to a goal position on its wire and hold it there at rest, with
    the crank above the slider's wire.

    ## Action Space

    ``action_mode="force"`` (default): ``Box(-1, 1, (1,), float32)``, a force of ``action *
    max_force`` newtons on the crank along its counter-clockwise tangent (taken at the start of
    the step and held for its substeps; its component off the wire is absorbed by the wire).

    ``action_mode="spring"``: ``Box(-1, 1, (4,), float32)`` = ``(grab_x, grab_y, pull_x,
    pull_y)``. The particle nearest the grab point (in normalized scene coordinates, see below)
    is grabbed, whatever the distance, and pulled for this step by a damped mouse spring
    (``mouse_ks``, ``mouse_kd``) toward a target ``spring_reach * pull`` metres from where it
    is, ``spring_reach = max_force / mouse_ks``, with ``pull`` scaled down onto the unit disc
    if longer than 1: a particle at rest feels at most ``max_force`` newtons, as in force mode.
    A pull of 0 holds the particle with the spring's damping alone. A finite ``grab_radius``
    (m) lets grabs miss: a particle farther than that from the grab point is not pulled.

    Actions outside the Box are clipped; a NaN or inf action raises ValueError and changes nothing.

    ## Observation Space

    Normalized scene coordinates map the view box ``env.unwrapped.task.view`` = ``(xmin, ymin,
    xmax, ymax)``, by default ``(-0.45, -0.45, 1.25, 0.45)`` m, onto [-1, 1]^2.

    ``Box(-10, 10, (9,), float32)`` in normalized scene coordinates (position ``(p - c) / h`` for
    the view box's centre ``c`` and half-size ``h``; velocity ``v / h``):

    | Index | Observation                    | Min | Max |
    |-------|--------------------------------|-----|-----|
    | 0, 1  | crank position x, y            | -10 | 10  |
    | 2, 3  | slider position x, y           | -10 | 10  |
    | 4, 5  | crank velocity x, y (1/s)      | -10 | 10  |
    | 6, 7  | slider velocity x, y (1/s)     | -10 | 10  |
    | 8     | goal x (same scale as x)       | -10 | 10  |

    ## Rewards

    Every step (see ``envs.rewards``):

        r = 10 (Phi - Phi') - 0.1 + 10 * success

    with the potential (cost to go) ``Phi = a + s`` before the step and ``Phi'`` after it:
    ``a`` the arc length (m) along the crank's wire, the short way round, from the crank to the
    point above the wire that puts the slider at the goal (``info["crank_to_go"]``), and ``s``
    the RMS speed of the two particles (m/s). ``Phi`` is zero only at the goal at rest and
    decreases all the way along a swing-up through a dead centre, where the slider's own
    distance ``d`` (m) to the goal would first grow. The shaping is potential-based (Ng, Harada
    & Russell 1999) and sums to ``10 (Phi_0 - Phi_T)`` over an episode; ``-0.1`` is a time cost
    per step until success; ``success`` is 1 on the step that completes the success test (see
    Episode End).

    ## Starting State

    Crank angle ~ U(-pi, pi) and crank speed ~ U(-``max_start_speed``, ``max_start_speed``) m/s,
    with the slider's position and velocity consistent with the constraints; the goal is uniform
    over ``goal_range`` at least ``min_distance`` from the slider. All draws come from
    ``self.np_random``.

    ## Episode End

    1. Termination: ``d < goal_tolerance``, ``s_avg < rest_speed`` and the crank above the wire
       (``y_crank > 0``), for ``hold_steps`` consecutive steps (success, ``info["is_success"]``).
       Every slider position has a crank angle above and one below the wire; the task asks for
       the one above. From a start below (half the starts) the crank must swing up through a
       dead centre (slider at 0.5 m or 1.1 m, where the slider's motion reverses), and holding
       it above needs a steady force ``m g cos(theta)`` against gravity.
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

    ``info`` holds ``distance`` (m), ``crank_height`` (m), ``crank_to_go`` (m),
    ``kinetic_energy`` (J), ``constraint_residual`` (the largest distance in m by
    which the crank leaves its circle, the slider its wire or the rod its length),
    ``is_success`` and ``diverged``.

    ## Arguments

    ```python
    >>> import gymnasium as gym
    >>> import envs
    >>> env = gym.make("SliderCrank-v0", integrator="midpoint", substeps=4, dt=0.0125)
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, env.action_space.shape
    ((9,), (1,))

    ```

    | Parameter         | Default       | Description                                      |
    |-------------------|---------------|--------------------------------------------------|
    | `action_mode`     | `"force"`     | `"force"` or `"spring"`                          |
    | `radius`          | `0.3`         | crank (circular wire) radius (m)                 |
    | `rod`             | `0.8`         | rod length (m), > radius                         |
    | `particle_mass`   | `0.1`         | mass of crank and slider (kg)                    |
    | `drag`            | `0.05`        | air drag per particle (N s/m)                    |
    | `dt`              | `0.025`       | physics step (s)                                 |
    | `substeps`        | `2`           | physics steps per env step (0.05 s)              |
    | `integrator`      | `"rk4"`       | a name in `constrained_particles.METHODS`        |
    | `max_force`       | `2.0`         | tangential force of action 1 (N)                 |
    | `goal_range`      | `(0.8, 1.05)` | goals (m), inside the stroke (rod -+ radius)     |
    | `min_distance`    | `0.1`         | minimum start-to-goal distance (m)               |
    | `max_start_speed` | `2.0`         | maximum starting crank speed (m/s)               |
    | `goal_tolerance`  | `0.02`        | success distance (m)                             |
    | `rest_speed`      | `0.05`        | success RMS speed (m/s)                          |
    | `hold_steps`      | `5`           | env steps the success test must hold             |
    | `rest_window`     | `10`          | rest test: averaging window (steps)              |
    | `grab_radius`     | `inf`         | farthest grab (m); inf: never misses             |
    | `mouse_ks`        | `20.0`        | spring action stiffness (N/m)                    |
    | `mouse_kd`        | `1.0`         | spring action damping (N s/m)                    |
    | `residual_limit`  | `0.01`        | constraint error (m) counted as diverged         |

    Bad values raise ValueError at ``make``. ``env.unwrapped.get_state()`` and
    ``set_state(state)`` save and restore the full simulation state for planning.

    ## Vectorized environment

    ``gym.make_vec("SliderCrank-v0", num_envs=N, vectorization_mode="vector_entry_point")`` runs
    :class:`SliderCrankVectorEnv`: the N linkages are one particle system with a block-diagonal
    constraint Jacobian, so each derivative evaluation is one multiplier solve for all of them.
    Autoreset is NEXT_STEP, and copy ``i`` reproduces a single env reset with ``seed + i``
    (up to the multiplier solve's 1e-10 tolerance).

    ## Version History

    * v0: Initial version (the reward and the crank-above rule of the success test were settled
      before any results were published on it).
      Changed before any release: the spring action grabs the nearest particle always and
      pulls it toward a target relative to it, at most ``max_force`` on a particle at rest (it
      was an absolute target point within a 0.2 m grab radius); the rest test averages
      velocities over about ``rest_window`` steps (it was the instantaneous RMS speed); a
      diverged step ends the episode as terminated with ``divergence_penalty`` (it was a
      truncation).
    """

    task_class = SliderCrank


class SliderCrankVectorEnv(ParticleVectorEnv):
    """``num_envs`` SliderCrank copies stepped as one particle system (see
    :class:`SliderCrankEnv`). Takes the single env's keyword arguments plus ``num_envs``,
    ``max_episode_steps`` (default 200) and ``num_threads`` (default 1; see
    :class:`~envs.vector.ParticleVectorEnv`)."""

    task_class = SliderCrank


class SliderCrankController(ScriptedAgent):
    """Drive the crank to the angle above the wire that puts the slider at the goal (through a
    dead centre if it starts below), with gravity compensation: ``F_t = m g cos(theta)
    + kp (theta* - theta) - kd v_t`` along the tangent."""

    def __init__(self, task: SliderCrank, kp: float = 3.0, kd: float = 1.5) -> None:
        super().__init__(task)
        self.kp, self.kd = kp, kd
        self.spring_particle = 0

    def force(self, x, v, goal):
        t = self.task
        r, L = t.radius, t.rod
        crank = x[:, 0]
        theta = np.arctan2(crank[:, 1], crank[:, 0])
        # slider at g: r cos(th) + sqrt(L^2 - r^2 sin^2(th)) = g, so cos(th) = (g^2 + r^2 - L^2)/2gr
        cos_target = np.clip((goal**2 + r**2 - L**2) / (2 * goal * r), -1.0, 1.0)
        target = np.arccos(cos_target)  # the success test wants the crank above the wire

        error = np.angle(np.exp(1j * (target - theta)))
        tangent = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
        v_t = np.sum(v[:, 0] * tangent, axis=1)
        F_t = t.particle_mass * scenes.G * np.cos(theta) + self.kp * error - self.kd * v_t
        return F_t[:, None] * tangent

    def force_action(self, F, x):
        crank = x[:, 0]
        tangent = np.stack([-crank[:, 1], crank[:, 0]], axis=1)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        return np.sum(F * tangent, axis=1, keepdims=True) / self.task.max_force

# ------------------------------------------------------------------ compiled bookkeeping
# SliderCrank's own kernels: its crank measures and force action, and its whole end of step in
# one call, built on the generic measures and observation of envs._measure (the numpy reference
# of each is the SliderCrank method that calls it).


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


class Finish(NamedTuple):
    """Everything :func:`crank_finish` writes after SliderCrank's physics step."""

    crank: Crank
    task: _measure.Goal
    rest: _measure.Rest
    every: np.ndarray  #: (N,) bool, all True: the copies that stepped
    out: np.ndarray  #: (5, N) out: the measures' rows (``_measures``)
    success: np.ndarray  #: (N,) bool out
    frame: _measure.View  #: the observation's normalization
    obs: np.ndarray  #: (N, 4 n + 1) float32 out
    reward: _measure.Reward
    episode: Episode


#: the compiled crank measures (None when ``_measure.ENABLED`` is False)
crank_measures: Callable[..., None] | None = None
#: the compiled force action (None when ``_measure.ENABLED`` is False)
crank_push: Callable[..., None] | None = None
#: :func:`crank_measures`, then the measures with the crank's ``below`` as ``blocked``, then
#: the observation, in one call (None when ``_measure.ENABLED`` is False)
crank_measures_observe: Callable[..., None] | None = None
#: :func:`crank_measures_observe`, the shaped reward and the episode counters of a step every
#: copy took, in one call (None when ``_measure.ENABLED`` is False)
crank_finish: Callable[..., int] | None = None

if _measure.ENABLED:
    from constrained_particles.jit import njit
    from constrained_particles.records import borrowed

    from ._measure import Episode, Goal, Rest, Reward, View, _measures_observe, _shaped_reward

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

    @njit(inline="always")
    def _crank_measures_observe(crank, state, task, blocks, walls, rest, stepped, out, success,
                                view, obs):  # pragma: no cover - compiled
        """:func:`_crank`, :func:`_measures` with the copies whose crank is not above the
        slider's wire as ``blocked``, and :func:`_observe`: SliderCrank's whole bookkeeping
        after a step in one call."""
        _crank(state[0], task.n, task.goal, crank)
        _measures_observe(state, task, blocks, walls, rest, stepped, crank.below, out, success,
                          view, obs)

    @njit(inline="always")
    def _finish_record(t):  # pragma: no cover - compiled
        """The :class:`Finish` whose plain form is ``t`` (inlined: as a function of its own it
        took a separate compile, about 1 s)."""
        crank, task, rest, every, out, success, frame, obs, reward, episode = t
        return Finish(Crank(*crank), Goal(*task), Rest(*rest), every, out, success,
                      View(*frame), obs, Reward(*reward), Episode(*episode))

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
    def _crank_measures_observe_entry(crank, state, task, blocks, walls, rest, stepped, out,
                                      success, view, obs):  # pragma: no cover - compiled
        crank, task, rest = borrowed((crank, task, rest))
        _crank_measures_observe(Crank(*crank), state, Goal(*task), blocks, walls, Rest(*rest),
                                stepped, out, success, View(*view), obs)

    @njit(nogil=True)
    def _crank_entry(x, n, goal, crank):  # pragma: no cover - compiled
        _crank(x, n, goal, Crank(*crank))

    crank_measures = _crank_entry
    crank_push = _crank_push
    crank_measures_observe = _crank_measures_observe_entry
    crank_finish = _crank_finish_entry


#: The task's declaration (see :mod:`envs.task`).
TASK = TaskSpec(
    id="SliderCrank-v0", env=SliderCrankEnv, vector_env=SliderCrankVectorEnv,
    action_modes=ACTION_MODES, scripted_agent=SliderCrankController, bench_vector=True,
    summary="turn a crank so that the slider it drives rests at a goal",
    hyperparams={"ppo": {"force": ppo(300000, (64, 64)), "spring": ppo(400000, (64, 64))},
                 "sac": {"force": sac(), "spring": sac()}})
