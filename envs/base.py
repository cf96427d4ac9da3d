"""What the environments share: N scenes stepped as one particle system.

A :class:`ParticleTask` holds ``num_envs`` copies of one scene as a single
:class:`~constrained_particles.ParticleSystem` built with ``system.tile(num_envs)`` (block-diagonal
constraint Jacobian, one derivative evaluation for all copies), writes the agents' actions into the
tiled actuator blocks (``ConstantForce.force`` rows or ``MouseSpring`` elements), and measures the
task on every copy at once. :class:`envs.single.ParticleEnv` is the task with one copy behind the
``gymnasium.Env`` interface; :class:`envs.vector.ParticleVectorEnv` is the same task with N copies
behind the ``gymnasium.vector.VectorEnv`` interface (the native vector env, in the style of
gymnasium's ``CartPoleVectorEnv``). Both therefore run the same code, and the vector env's copy
``i`` reproduces a single env seeded with ``seed + i``, like ``SyncVectorEnv``.

Coordinates: an env's *view box* ``(xmin, ymin, xmax, ymax)`` (metres) maps onto normalized scene
coordinates ``[-1, 1]^2``. Observed positions, the observed goal and the spring action's grab and
target points all use that map; observed velocities use the same scale per second.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike

from constrained_particles import (
    ConstantForce,
    MouseSpring,
    ParticleSystem,
    Shape,
    Wall,
)
from constrained_particles.integrators import METHODS
from constrained_particles.terms import as_index_array, is_frozen

from . import _measure
from .checks import (
    _owned,
    check_positive,
    checked_actions,
)
from .stepping import SteppedCopies

if TYPE_CHECKING:
    from .pixels import Picture

#: Valid values of the ``action_mode`` argument.
ACTION_MODES = ("force", "spring")
#: Observations are clipped to [-OBS_LIMIT, OBS_LIMIT] (normalized units; the view box is [-1, 1]).
OBS_LIMIT = 10.0
#: Pixel size of rendered frames.
FRAME_SIZE = (600, 400)
#: Shortest physics step (s) an env accepts.
MIN_DT = 1e-6
#: The registered episode length (env steps): a diverged step's penalty covers the cost of
#: playing on for this many steps unless the env has another time limit (see
#: :attr:`ParticleTask.divergence_penalty`).
EPISODE_STEPS = 200


class ParticleTask(SteppedCopies):
    """``num_envs`` copies of a scene as one tiled system, with a goal per copy.

    Subclasses build the scene (:meth:`build_scene`), choose the particles the force action
    pushes (:meth:`force_vectors`), sample starting states (:meth:`sample_start`), say which
    scalar is driven to the goal (:meth:`tracked`) and define the reward (:meth:`reward`).
    Every per-copy quantity is an array with a leading axis of length ``num_envs``.

    Common arguments (validated here; a bad value raises ValueError):
    ``action_mode`` (``"force"`` or ``"spring"``), ``dt`` (physics step, s), ``substeps``
    (physics steps per env step), ``integrator`` (a name in ``constrained_particles.METHODS``),
    ``max_force`` (N, the force of action 1; a spring action's pull at rest is at most this),
    ``grab_radius`` (m, ``inf``: every grab takes the nearest particle), ``mouse_ks`` (N/m) and
    ``mouse_kd`` (N s/m) of the spring action, and the success test: within ``goal_tolerance``
    (m) of the goal and at rest, the RMS of the particles' velocities averaged over about
    ``rest_window`` steps below ``rest_speed`` (m/s), for ``hold_steps`` consecutive env steps
    (see :meth:`advance_rest`). ``residual_limit`` (m, default 0.01; ``inf`` switches the
    check off): a physics step that leaves any constraint by more than this distance counts as
    diverged.

    A physics step is split into equal pieces when a particle could travel more than
    :attr:`step_travel` metres in it (see :meth:`pieces`), so fast motion, whatever the actions,
    stays within what the integrator carries.
    """

    #: Number of force-action components (subclasses set it).
    force_dim: ClassVar[int] = 1

    def __setattr__(self, name: str, value: Any) -> None:
        # A public array of the task (goals, hold counts, actions, ...) keeps its shape and
        # dtype: every copy's bookkeeping, compiled or not, reads it as made. Reassigning one
        # with another is refused here, at the boundary (its values may be edited in place).
        old = self.__dict__.get(name)
        if isinstance(old, np.ndarray) and not name.startswith("_") and not (
                type(value) is np.ndarray and value.shape == old.shape
                and value.dtype == old.dtype):
            raise ValueError(f"{name} must stay a {old.dtype} array of shape {old.shape} (edit "
                             f"it in place instead), got {type(value).__name__} "
                             f"{getattr(value, 'dtype', '')} {np.shape(value)}")
        super().__setattr__(name, value)
    #: The most reward one step of playing on can cost before success (a task's time cost, or its
    #: per-step distance cost at the farthest): see :attr:`divergence_penalty`.
    step_cost: float = 0.0
    @property
    def episode_steps(self) -> int:
        """The episode length (env steps) that :attr:`divergence_penalty` covers: a native
        vector env sets its ``max_episode_steps`` here; otherwise :data:`EPISODE_STEPS` (a
        single env cannot see the time limit ``gym.make`` wraps around it: set this to match
        another one). A positive integer (ValueError naming it otherwise)."""
        return self.__dict__.get("_episode_steps", EPISODE_STEPS)

    @episode_steps.setter
    def episode_steps(self, value: int) -> None:
        self.__dict__["_episode_steps"] = int(check_positive("episode_steps", value,
                                                             integer=True))

    @property
    def divergence_penalty(self) -> float:
        """Reward subtracted on a diverged step, which ends the episode as terminated: the cost
        of playing on for a whole episode (``episode_steps * step_cost``), so that diverging is
        never a cheaper way out than playing on, whatever the time limit."""
        return self.episode_steps * self.step_cost

    #: Farthest distance (m) a particle may travel in one integrator step before the physics step
    #: is split into pieces (subclasses set it from the scene's smallest length).
    step_travel: float = math.inf

    def __init__(self, num_envs: int, *, action_mode: str, dt: float, substeps: int,
                 integrator: str, max_force: float, grab_radius: float, mouse_ks: float,
                 mouse_kd: float, goal_tolerance: float, rest_speed: float,
                 hold_steps: int, residual_limit: float = 0.01, rest_window: int = 10) -> None:
        #: Which compiled paths this task takes (:meth:`_compiled_paths`), decided once, here
        self._paths = self._compiled_paths()
        self.num_envs = check_positive("num_envs", num_envs, integer=True, maximum=10**6)
        self._every = np.arange(self.num_envs)
        self._one_piece = np.ones(self.num_envs, np.int64)
        if not isinstance(action_mode, str) or action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
        if not isinstance(integrator, str) or integrator not in METHODS:
            raise ValueError(f"integrator must be one of {sorted(METHODS)}, got {integrator!r}")
        self.action_mode = action_mode
        self.integrator = integrator
        self.dt = check_positive("dt", dt, minimum=MIN_DT, maximum=10.0)
        self.substeps = check_positive("substeps", substeps, integer=True, maximum=10**4)
        self.residual_limit = (math.inf if residual_limit == math.inf else
                               check_positive("residual_limit", residual_limit))
        self.max_force = check_positive("max_force", max_force)
        self.grab_radius = (math.inf if grab_radius == math.inf else
                            check_positive("grab_radius", grab_radius))
        self.mouse_ks = check_positive("mouse_ks", mouse_ks)
        self.mouse_kd = check_positive("mouse_kd", mouse_kd, allow_zero=True)
        #: Distance (m) from the grabbed particle to the spring action's target at a pull of
        #: 1 (``max_force / mouse_ks``): the spring pulls a particle at rest with at most
        #: ``max_force`` newtons.
        self.spring_reach = self.max_force / self.mouse_ks
        self.goal_tolerance = check_positive("goal_tolerance", goal_tolerance)
        self.rest_speed = check_positive("rest_speed", rest_speed)
        self.hold_steps = check_positive("hold_steps", hold_steps, integer=True)
        self.rest_window = check_positive("rest_window", rest_window, integer=True,
                                          maximum=10**4)
        #: Weight of the newest velocity in the moving averages of the rest test.
        self._alpha = 1.0 / self.rest_window

        scene = self.build_scene()
        scene.residual_limit = self.residual_limit
        n = self.n = scene.n
        if action_mode == "force":
            handles = self.force_handles(scene)
            scene.add(ConstantForce(handles, np.zeros((len(handles), 2))))
        else:
            scene.add(MouseSpring(None, ks=self.mouse_ks, kd=self.mouse_kd))
        #: One copy with its actuator (the last force block): draws copy ``i``, and finds which
        #: copy diverged.
        self.single = scene
        #: Positions (n, 2) where a diverged copy waits out the rest of a step.
        self.park = scene.x.copy()
        #: All copies as one system; copy ``i`` owns particles ``i n .. (i + 1) n - 1``.
        self.system = scene.tile(self.num_envs)
        #: The tiled actuator: copy ``i``'s action is written into its rows only.
        self.actuator: ConstantForce | MouseSpring = self.system.forces[-1]
        # (the force actuator's particles, if none repeats, with the split rule's buffers and
        # each particle's row of the actuator, -1 for none: pieces() reads the actuator's
        # forces through it instead of accumulating them)
        self._pushed: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        act = self.actuator
        if isinstance(act, ConstantForce) and len(np.unique(act.particles)) == len(act):
            frow = np.full(self.system.n, -1, np.int64)
            frow[act.particles] = np.arange(len(act))
            self._pushed = (act.particles, np.empty(self.num_envs, np.int64),
                            np.empty(self.system.n, np.int64), frow)
        self.rows_per_copy = len(scene.forces[-1])
        self.goal = np.zeros(self.num_envs)
        self.hold = np.zeros(self.num_envs, dtype=np.int64)
        #: Each particle's moving average velocity (num_envs * n, 2) in m/s, the rest test's
        #: (see :meth:`_measures`).
        self.mean_v = np.zeros((self.num_envs * n, 2))
        self.action = np.zeros((self.num_envs, self.action_dim))
        self._row_env = np.concatenate(
            [np.repeat(np.arange(self.num_envs), c.n_rows // self.num_envs)
             for c in self.system.constraints] or [np.zeros(0, np.int64)])
        xmin, ymin, xmax, ymax = self.view
        self.center = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
        self.half = np.array([(xmax - xmin) / 2, (ymax - ymin) / 2])
        #: The default ``stepped`` and ``blocked`` masks of :meth:`_measures`: no copy.
        self._no_copies = np.zeros(self.num_envs, bool)
        #: The ``stepped`` mask of a step every copy took (never written).
        self._every_copy = np.ones(self.num_envs, bool)
        self._scale: _measure.View | None = None
        self._track: tuple[np.ndarray, float] | None = None
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.action_dim,), np.float32)
        self.single_observation_space = spaces.Box(-OBS_LIMIT, OBS_LIMIT, (4 * n + 1,), np.float32)

    # ------------------------------------------------------------------ subclass hooks
    #: ``(xmin, ymin, xmax, ymax)`` in metres: rendering bounds and the normalization box.
    view: tuple[float, float, float, float]

    def build_scene(self) -> ParticleSystem:
        """One copy of the scene without actuators."""
        raise NotImplementedError

    def force_handles(self, scene: ParticleSystem) -> np.ndarray:
        """Particles (indices within one copy) that the force action pushes."""
        raise NotImplementedError

    def force_vectors(self, action: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Forces (N) on the handles, (num_envs, handles, 2), for clipped actions
        ``action`` (num_envs, force_dim) at positions ``x`` (num_envs, n, 2)."""
        raise NotImplementedError

    def sample_start(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        """A starting state of one copy: positions (n, 2) m, velocities (n, 2) m/s, goal (m)."""
        raise NotImplementedError

    def tracked(self, x: np.ndarray) -> np.ndarray:
        """The x coordinate (m) driven to the goal, per copy, from positions (num_envs, n, 2):
        the mean x of :attr:`tracked_particles`."""
        idx = self.tracked_particles
        if idx is None:
            raise NotImplementedError
        return x[:, idx, 0].sum(axis=1) * (1.0 / len(idx))

    def goal_distance(self, x: np.ndarray, goal: np.ndarray | None = None) -> np.ndarray:
        """Distance (m) to the goal per copy, from positions (copies, n, 2) and those copies'
        goals (default: every copy's ``goal``): along x, from :meth:`tracked` to the goal; or,
        for a task with :attr:`planar_goal`, from the mean point of :attr:`tracked_particles` to
        the point ``(goal, goal_height)``."""
        along = self.tracked(x) - (self.goal if goal is None else goal)
        if not self.planar_goal:
            return np.abs(along)
        idx = self.tracked_particles
        if idx is None:  # (a planar goal needs the tracked particles' y as well)
            raise NotImplementedError
        return np.hypot(along, x[:, idx, 1].sum(axis=1) * (1.0 / len(idx)) - self.goal_height)

    def reward(self, m: dict[str, np.ndarray]) -> np.ndarray:
        """Reward per copy from the measures of :meth:`measure`."""
        raise NotImplementedError

    def reward_one(self, m: dict[str, np.ndarray], values: dict[str, Any]) -> float:
        """The reward of a task with one copy from its measures ``m`` (arrays) or the same as
        Python numbers (``values``): :meth:`reward` here; tasks may compute it from ``values``
        faster, with the same bits."""
        return float(self.reward(m)[0])

    # ------------------------------------------------------------------ state
    @property
    def action_dim(self) -> int:
        """Length of one copy's action vector."""
        return self.force_dim if self.action_mode == "force" else 4

    def copy_slice(self, i: int) -> slice:
        """Rows of copy ``i`` in the tiled particle arrays."""
        return slice(i * self.n, (i + 1) * self.n)

    def positions(self) -> np.ndarray:
        """Positions (num_envs, n, 2) in metres (a view)."""
        return self.system.x.reshape(self.num_envs, self.n, 2)

    def velocities(self) -> np.ndarray:
        """Velocities (num_envs, n, 2) in m/s (a view)."""
        return self.system.v.reshape(self.num_envs, self.n, 2)

    def to_world(self, u: np.ndarray) -> np.ndarray:
        """Normalized scene coordinates (..., 2) to metres."""
        return self.center + self.half * u

    def to_normalized(self, p: np.ndarray) -> np.ndarray:
        """Metres (..., 2) to normalized scene coordinates."""
        return (p - self.center) / self.half

    def sample_starts(self, rngs: Sequence[np.random.Generator]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample_start` from each generator, stacked: positions and velocities
        (len(rngs), n, 2) and goals (len(rngs),). A subclass may draw them in one pass; each
        copy's draws must stay those of :meth:`sample_start` from its generator, bit for bit."""
        n = self.n
        x, v, goal = np.empty((len(rngs), n, 2)), np.empty((len(rngs), n, 2)), \
            np.empty(len(rngs))
        for k, rng in enumerate(rngs):
            xk, vk, goal[k] = self.sample_start(rng)
            x[k], v[k] = np.reshape(xk, (n, 2)), np.reshape(vk, (n, 2))
        return x, v, goal

    def write_start(self, envs: Sequence[int], starts: Sequence[tuple]) -> None:
        """Write starting states ``(x, v, goal)`` into the slices of copies ``envs`` only."""
        copies = len(np.asarray(envs).reshape(-1))
        if copies != len(starts):
            raise ValueError(f"write_start: {copies} copies but {len(starts)} starts")
        n = self.n
        self.write_starts(envs, np.array([np.reshape(x, (n, 2)) for x, _, _ in starts],
                                         dtype=float).reshape(-1, n, 2),
                          np.array([np.reshape(v, (n, 2)) for _, v, _ in starts],
                                   dtype=float).reshape(-1, n, 2),
                          np.array([goal for _, _, goal in starts], dtype=float))

    def write_starts(self, envs: Sequence[int], x: np.ndarray, v: np.ndarray,
                     goal: np.ndarray) -> None:
        """Write starting positions and velocities (len(envs), n, 2) and goals (len(envs),)
        into the slices of copies ``envs`` only (in a few whole-array operations)."""
        envs = np.asarray(envs, dtype=np.int64).reshape(-1)
        if not len(envs):
            return
        n = self.n
        rows = (envs[:, None] * n + np.arange(n)).reshape(-1)
        self.system.x[rows] = x.reshape(-1, 2)
        self.system.v[rows] = v.reshape(-1, 2)
        self.mean_v[rows] = v.reshape(-1, 2)
        self.goal[envs] = goal
        self.hold[envs] = 0
        self.action[envs] = 0.0
        self._actuate(envs, None)
        # the multiplier solve's warm start, so that a seed fixes the episode bit for bit
        chosen = np.zeros(self.num_envs, bool)
        chosen[envs] = True
        self._lam()[chosen[self._row_env]] = 0.0

    def reset_envs(self, envs: Sequence[int], rngs: Sequence[np.random.Generator]) -> None:
        """Draw a starting state for each copy in ``envs`` from its generator and write it."""
        self.write_starts(envs, *self.sample_starts(rngs))

    def get_state(self, i: int) -> dict[str, Any]:
        """Copy ``i``'s full simulation state (positions, velocities, goal, steps held at the goal,
        last action, time, the multiplier warm start)."""
        sl = self.copy_slice(i)
        rows = self._row_env == i
        return {"t": float(self.system.t), "x": self.system.x[sl].copy(),
                "v": self.system.v[sl].copy(), "goal": float(self.goal[i]),
                "hold": int(self.hold[i]), "mean_v": self.mean_v[sl].copy(),
                "action": self.action[i].copy(), "lam": self._lam()[rows].copy()}

    def set_state(self, i: int, state: dict[str, Any]) -> None:
        """Restore copy ``i`` from :meth:`get_state`.

        Every field is validated before anything is written (ValueError naming the field, and
        nothing changes): shapes, finiteness, ``t >= 0``, ``hold`` an integer >= 0, ``action``
        inside the action Box and positions on the constraints within ``residual_limit``.
        """
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) \
                or not 0 <= i < self.num_envs:
            raise ValueError(f"i must be a copy index in [0, {self.num_envs}), got {i!r}")
        values = self.check_state(state)
        rows = self._row_env == i
        sl = self.copy_slice(i)
        self.system.x[sl] = values["x"]
        self.system.v[sl] = values["v"]
        self.system.t = float(values["t"])
        self.goal[i] = float(values["goal"])
        self.hold[i] = values["hold"]
        self.mean_v[sl] = values["mean_v"]
        self.action[i] = values["action"]
        self._actuate_rows(i, values["action"])
        lam = self._lam()
        lam[rows] = values["lam"]

    def check_state(self, state: object) -> dict[str, Any]:
        """The validated fields of one copy's ``state`` (see :meth:`set_state`)."""
        if not isinstance(state, dict):
            raise ValueError(f"state must be a dict from get_state(), got {type(state).__name__}")
        missing = {"t", "x", "v", "goal", "hold", "mean_v", "action", "lam"} - set(state)
        if missing:
            raise ValueError(f"state is missing {sorted(missing)}")
        arrays = {"x": (self.n, 2), "v": (self.n, 2), "mean_v": (self.n, 2),
                  "action": (self.action_dim,),
                  "lam": (int(np.sum(self._row_env == 0)),), "t": (), "goal": ()}
        values: dict[str, Any] = {}
        for key, shape in arrays.items():
            try:
                raw = np.asarray(state[key])
                if raw.dtype.kind not in "iuf":
                    raise TypeError
                arr = raw.astype(float)
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"state[{key!r}] must be numbers, got {state[key]!r}") from None
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise ValueError(f"state[{key!r}] must be a finite array of shape {shape}, "
                                 f"got {state[key]!r}")
            values[key] = arr
        hold = state["hold"]
        if isinstance(hold, (bool, np.bool_)) or not isinstance(hold, (int, np.integer)) \
                or not 0 <= hold <= 2**62:
            raise ValueError(f"state['hold'] must be an integer >= 0, got {hold!r}")
        values["hold"] = int(hold)
        if values["t"] < 0:
            raise ValueError(f"state['t'] must be >= 0 s, got {state['t']!r}")
        if np.any(np.abs(values["action"]) > 1):
            raise ValueError(f"state['action'] must lie in the action Box [-1, 1], "
                             f"got {state['action']!r}")
        limit = self.system.divergence_limit
        if np.any(np.abs(values["x"]) >= limit) or np.any(np.abs(values["v"]) >= limit):
            raise ValueError(f"state['x'] and state['v'] must be within divergence_limit = "
                             f"{limit:g}")
        error = self.single.distance_errors(values["x"]).max(initial=0.0)
        if error > self.residual_limit:
            raise ValueError(f"state['x'] leaves the constraints by {error:.3g} m > "
                             f"residual_limit = {self.residual_limit:g} m")
        return values

    def _lam(self) -> np.ndarray:
        return self.system.constraint_solver.lam

    # ------------------------------------------------------------------ actions and physics
    def check_actions(self, actions: ArrayLike, single: bool = False) -> np.ndarray:
        """Validated, clipped actions (num_envs, action_dim) as float64.

        ``actions`` must have shape exactly ``(num_envs, action_dim)``, or ``(action_dim,)`` for
        a ``single`` env: a batch of another shape is never reshaped, so no action reaches the
        wrong copy. ValueError for a wrong shape or a NaN/inf entry (nothing is changed then);
        finite values outside [-1, 1] are clipped into the action Box.
        """
        return checked_actions(actions, self.num_envs, self.action_dim, single)

    def _write_forces(self, action: np.ndarray, out: np.ndarray) -> None:
        """Write :meth:`force_vectors` of every copy's ``action`` into the tiled actuator's
        force rows ``out`` (num_envs * rows per copy, 2), in newtons."""
        out[:] = self.force_vectors(action, self.positions()).reshape(-1, 2)

    def _actuate_rows(self, i: int, action: np.ndarray | None) -> None:
        """Write copy ``i``'s action into the tiled actuator (None: no actuation)."""
        self._actuate(np.array([i]), None if action is None else action[None, :])

    def _actuate(self, envs: np.ndarray, action: np.ndarray | None) -> None:
        """Write actions (len(envs), action_dim) of copies ``envs`` into their rows of the tiled
        actuator; ``None`` switches their actuation off."""
        act = self.actuator
        if isinstance(act, ConstantForce):
            if len(envs) == self.num_envs:  # every copy (envs is then arange): no gathers
                if action is None:
                    act.force[:] = 0.0
                else:
                    self._write_forces(action, act.force)
                return
            k = self.rows_per_copy
            rows = (envs[:, None] * k + np.arange(k)).ravel()
            act.force[rows] = (0.0 if action is None else
                               self.force_vectors(action, self.positions()[envs]).reshape(-1, 2))
        elif action is None:
            act.set(envs, active=np.zeros(len(envs), bool))
        elif self._grab_ready(act, envs, action, x := self.system.x):  # the spring action,
            particles = np.empty(len(envs), np.int64)  # compiled (the reference is below)
            c, h = self.center, self.half
            if _measure.grab(x, self.n, envs, action, (c[0], c[1], h[0], h[1]),
                             self.grab_radius**2, self.spring_reach, act.particle, particles,
                             act.anchor, act.active):  # anchors and flags written in place
                act.set_checked(envs, particles, act.anchor[envs], act.active[envs])
        else:
            # the spring action: the particle nearest the grab point (within grab_radius), and
            # a target spring_reach * pull from it, the pull clipped to the unit disc
            x = self.positions() if len(envs) == self.num_envs else self.positions()[envs]
            grab = self.to_world(action[:, :2])
            d2 = np.sum((x - grab[:, None, :]) ** 2, axis=2)
            nearest = np.argmin(d2, axis=1)
            pull = action[:, 2:]
            norm2 = pull[:, 0] * pull[:, 0] + pull[:, 1] * pull[:, 1]
            pull = pull * (1.0 / np.sqrt(np.maximum(norm2, 1.0)))[:, None]  # (x 1.0: exact)
            target = x[np.arange(len(envs)), nearest] + self.spring_reach * pull
            act.set_checked(envs, envs * self.n + nearest, target,
                            d2[np.arange(len(envs)), nearest] <= self.grab_radius**2)

    def _grab_ready(self, act: Any, envs: np.ndarray, action: np.ndarray, x: Any) -> bool:
        """True if the compiled spring action may run on these arrays (O(1) checks of what it
        reads and writes without bounds checks: the mouse block's arrays one per copy, the
        positions ``x`` of every copy, copies ``envs`` in range, one action of 4 per copy)."""
        N = self.num_envs
        return (_measure.ENABLED and _owned(x, np.float64, (N * self.n, 2))
                and _owned(act.particle, np.int64, (N,)) and _owned(act.anchor, np.float64, (N, 2))
                and _owned(act.active, np.bool_, (N,)) and _owned(envs, np.int64, envs.shape)
                and envs.ndim == 1 and _owned(action, np.float64, (len(envs), 4))
                and (not len(envs) or (envs.min() >= 0 and envs.max() < N)))

    def apply(self, actions: np.ndarray, idle: np.ndarray | None = None) -> None:
        """Write validated ``actions`` (num_envs, action_dim); copies in the ``idle`` mask get no
        actuation (their action is ignored)."""
        self.action[:] = actions
        if idle is None or not np.count_nonzero(idle):
            self._actuate(self._every, self.action)
            return
        envs = np.arange(self.num_envs)
        if idle is not None and idle.any():
            self.action[idle] = 0.0
            self._actuate(envs[idle], None)
            envs = envs[~idle]
        if len(envs):
            self._actuate(envs, self.action[envs])

    # ------------------------------------------------------------------ measures
    def observe(self) -> np.ndarray:
        """Observations (num_envs, 4 n + 1) float32: normalized positions, velocities, goal.

        Each entry is computed in float64 (``(x - c) / h`` as ``(x - c) * (1 / h)``), rounded to
        float32 and clipped to [-OBS_LIMIT, OBS_LIMIT]: in one compiled pass
        (:func:`envs._measure.observe`), or by the numpy reference below, a handful of
        whole-array operations with no per-copy Python."""
        N, n = self.num_envs, self.n
        s = self.system
        obs = np.empty((N, 4 * n + 1), np.float32)
        state = self._compiled_state()
        if state is not None and _owned(self.goal, np.float64, (N,)):
            _measure.observe(state[0], state[1], n, self.goal, tuple(self._view()), obs)
            return obs
        inv_half = 1.0 / self.half
        pos = obs[:, :2 * n].reshape(N, n, 2)  # views: only the last axis is split
        np.multiply((s.x - self.center).reshape(N, n, 2), inv_half, out=pos, casting="same_kind")
        vel = obs[:, 2 * n:4 * n].reshape(N, n, 2)
        np.multiply(s.v.reshape(N, n, 2), inv_half, out=vel, casting="same_kind")
        obs[:, -1] = (self.goal - self.center[0]) * inv_half[0]
        np.clip(obs, -OBS_LIMIT, OBS_LIMIT, out=obs)
        return obs

    def _view(self) -> _measure.View:
        """The view box's centre and inverse half-sizes (1/m), and the clip bound, as the
        compiled observation takes them."""
        if self._scale is None:
            self._scale = _measure.View(float(self.center[0]), float(self.center[1]),
                                        float(1.0 / self.half[0]), float(1.0 / self.half[1]),
                                        float(OBS_LIMIT))
        return self._scale

    def _compiled_paths(self) -> dict[str, bool]:
        """Which compiled paths this task takes, decided once, when it is built. A compiled
        path computes what some methods compute, so it runs only where the task's class keeps
        them as written; a subclass that redefines one gets the numpy reference for that part
        (the same values with the methods as written). Subclasses add their own entries:

        - ``measure_observe``: :meth:`measure_observe` in one compiled call;
        - ``goal``: the compiled measures compute :meth:`goal_distance`;
        - ``restart_all``: an env step in which every copy starts anew may skip the physics
          (:meth:`simulate` is the base one, which only steps the copies' physics);
        - ``fresh_pack``: the measures after :meth:`simulate_step` take the pack its physics
          left checked (:meth:`simulate`, the base one, changes no block after it)."""
        cls = type(self)
        stock = cls.simulate is ParticleTask.simulate
        return {"measure_observe": (cls.measure is ParticleTask.measure
                                    and cls.observe is ParticleTask.observe),
                "goal": cls.goal_distance is ParticleTask.goal_distance,
                "restart_all": stock, "fresh_pack": stock}

    def measure_observe(self, stepped: np.ndarray | None = None
                        ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """:meth:`measure` (``stepped`` as there), then :meth:`observe`: what the envs need
        after every step. In one compiled call (:func:`envs._measure.measures_observe`) when
        a subclass redefines neither and the blocks allow it; the same values either way."""
        post = self._compiled_post() if self._paths["measure_observe"] else None
        if post is not None:
            obs = np.empty((len(post[1].goal), 4 * post[1].n + 1), np.float32)
            return self.add_measures(*self._measures(stepped, walls=self.measure_walls,
                                                     obs=obs, post=post)), obs
        return self.measure(stepped), self.observe()

    def _mask(self, mask: np.ndarray | None) -> np.ndarray:
        """A per-copy mask as the compiled bookkeeping reads it (None: no copy); ValueError
        for anything but a bool array of shape (num_envs,)."""
        if mask is None:
            none = self._no_copies
            if not _owned(none, np.bool_, (self.num_envs,)):  # (replaced: made anew)
                none = self._no_copies = np.zeros(self.num_envs, bool)
            return none
        if not _owned(mask, np.bool_, (self.num_envs,)):
            raise ValueError(f"a copy mask must be a bool array of shape ({self.num_envs},), "
                             f"got {mask!r}")
        return mask

    def _finish_step(self, steps: np.ndarray, max_steps: int) -> tuple | None:
        """After an env step that every copy took: the measures and observation (as
        :meth:`measure_observe` with every copy stepped), the reward and the episode counters
        (``steps`` advanced in place; terminated on success, truncated at ``max_steps``), in
        one go: ``(obs, measures, reward, terminated, truncated, ended, number ended)``. None
        here: the vector env takes its general path; a task with a compiled version returns
        exactly what that path would."""
        return None

    def _compiled_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The system's ``(x, v, mass)``, each read once, if the compiled bookkeeping may read
        them without bounds checks (C-ordered float64 arrays of ``num_envs * n`` particles);
        None otherwise, and when it is off: the numpy reference then runs (and raises on a
        wrong shape). O(1): the arrays' types and shapes only."""
        if not _measure.ENABLED:
            return None
        s, total = self.system, self.num_envs * self.n
        x, v, mass = s.x, s.v, s.mass
        if (_owned(x, np.float64, (total, 2)) and _owned(v, np.float64, (total, 2))
                and _owned(mass, np.float64, (total,))):
            return x, v, mass
        return None

    def _compiled_post(self) -> tuple[Any, _measure.Goal, tuple] | None:
        """``(pack, goal, (x, v, mass))`` for the compiled measures (``goal``: the success
        test's :class:`envs._measure.Goal`), or None where the numpy reference must run (the
        compiled bookkeeping off, or what it reads not of the blocks, shapes, types it takes)."""
        fresh = self.__dict__.pop("_fresh_pack", None)  # (see simulate_step: taken once; a
        if type(fresh) is tuple:  # prepared step hands its whole post: envs.driver)
            return fresh
        if not _measure.ENABLED:
            return None
        track = self._tracking()
        state = self._compiled_state()
        goal = None if track is None or state is None else self._goal_record(track)
        p = None if goal is None else _measure.packed(self.system, fresh)
        return None if p is None or p.n != len(state[0]) else (p, goal, state)

    def _goal_record(self, track: tuple[np.ndarray, float]) -> _measure.Goal | None:
        """The success test as the compiled measures read it (``track``: :meth:`_tracking`), or
        None unless they compute it: the task's own :meth:`goal_distance`, the goal's and rest
        test's arrays as they read them, a :attr:`rest_count` in [1, n], a finite ``goal_height``
        for a :attr:`planar_goal` (each attribute read once)."""
        N, n = self.num_envs, self.n
        goal, count = self.goal, self.rest_count
        height = self.goal_height if self.planar_goal else math.nan
        if not (self._paths["goal"] and type(count) is int and 0 < count <= n
                and _owned(goal, np.float64, (N,)) and _owned(self.hold, np.int64, (N,))
                and _owned(self.mean_v, np.float64, (N * n, 2))
                and isinstance(height, (int, float)) and not isinstance(height, bool)
                and (math.isfinite(height) or not self.planar_goal)):
            return None
        return _measure.Goal(n, goal, track[0], track[1], float(self.goal_tolerance),
                             float(self.rest_speed), int(self.hold_steps), float(height),
                             count, bool(self.wall_rest))

    def measure(self, stepped: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Per-copy measures: ``distance`` to the goal (m, :meth:`goal_distance`), ``speed``
        (RMS speed of the first :attr:`rest_count` particles, m/s),
        ``kinetic_energy`` (J), ``constraint_residual`` (the largest distance, m, by which a
        constraint is violated: see ``Constraint.distance_error``) and ``is_success``.

        ``stepped`` masks the copies that just took an env step: their count of consecutive
        steps at the goal and at rest advances (or restarts at 0).

        A task adds measures of its own in :meth:`add_measures` (rather than redefining this
        method, which would take the measures and the observation out of their common
        compiled call); with :attr:`measure_walls` the walls' contact force is measured too.
        """
        return self.add_measures(*self._measures(stepped, walls=self.measure_walls))

    #: Whether :meth:`measure` computes the walls' total contact force per copy (N) for
    #: :meth:`add_measures` (zeros otherwise).
    measure_walls: ClassVar[bool] = False

    def add_measures(self, m: dict[str, np.ndarray], wall_force: np.ndarray
                     ) -> dict[str, np.ndarray]:
        """The task's own measures added to the common ones ``m`` (in place; returns ``m``),
        ``wall_force`` being the walls' contact force per copy (N; see
        :attr:`measure_walls`). None here."""
        return m

    @property
    def tracked_particles(self) -> np.ndarray | None:
        """The particles (indices within one copy) whose mean x is the coordinate driven to
        the goal (see :meth:`tracked`; their mean point, for a :attr:`planar_goal`), as an
        immutable int64 array. Subclasses set it, or
        override :meth:`tracked` and leave it None (the measures then take the numpy reference
        path); a subclass that does both must compute that same mean (the compiled measures
        use this attribute, the reference :meth:`tracked`). Assigning validates the indices
        (ValueError or TypeError naming the attribute); the array cannot be edited in place."""
        return self.__dict__.get("_tracked_particles")

    @tracked_particles.setter
    def tracked_particles(self, value: ArrayLike | None) -> None:
        idx = None if value is None else as_index_array("tracked_particles", value)
        if idx is not None:
            n = self.__dict__.get("n")
            if not len(idx) or (n is not None and idx.max() >= n):
                raise ValueError(f"tracked_particles must be particle indices in [0, {n}) "
                                 f"within a copy, at least one, got {value!r}")
        self.__dict__["_tracked_particles"] = idx
        self._track = None

    def __getstate__(self) -> dict[str, Any]:
        """The attributes for a copy or a pickle, less what is remembered of this task's
        arrays (the tracked indices as checked, the step's pack): the copy checks its own."""
        return {**self.__dict__, "_track": None, "_fresh_pack": None}

    def __setstate__(self, state: dict[str, Any]) -> None:
        """As :meth:`__getstate__` leaves them (a subclass's own, or an older pickle, too)."""
        self.__dict__.update(state, _track=None)
        self.__dict__.pop("_fresh_pack", None)

    def _tracking(self) -> tuple[np.ndarray, float] | None:
        """``(particles, 1 / count)`` of :attr:`tracked_particles` for the compiled measures, or
        None if it is not set (a subclass computes :meth:`tracked` its own way). The indices
        are immutable: checked against the copy's particle count once. A copied or unpickled
        task holds a plain copy of them, which is validated and made immutable again here
        (it holds no ``_track``: :meth:`__getstate__`)."""
        track = self._track
        if (track is not None and track[0] is self.__dict__.get("_tracked_particles")
                and not track[0].flags.writeable):
            return track  # (made from the frozen indices below; a copy of them is writeable)
        idx = self.tracked_particles
        if idx is not None and not is_frozen(idx):
            self.tracked_particles = idx
            idx = self.tracked_particles
        if self._track is None and idx is not None and len(idx) and idx.max() < self.n:
            self._track = (idx, 1.0 / len(idx))
        return self._track

    def _measures(self, stepped: np.ndarray | None = None, blocked: np.ndarray | None = None,
                  walls: bool = False, obs: np.ndarray | None = None, post: tuple | None = None
                  ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The measures of :meth:`measure` and the walls' total contact force per copy (N,
        the sum over particles of ``|F_x|``; zeros unless ``walls``).

        The hold count of a ``stepped`` copy advances if it is within ``goal_tolerance`` of
        the goal, slower than ``rest_speed`` (the RMS of the moving average velocities of its
        first :attr:`rest_count` particles), not ``blocked`` and (with ``walls``, in a task
        with :attr:`wall_rest`) touching no wall; otherwise it restarts at 0. Computed in one
        compiled pass (:func:`envs._measure.measures_observe`) when the system's blocks allow
        it, else by the numpy reference below. With ``obs``, the compiled pass also writes
        :meth:`observe`'s observation into it; the reference does not.
        ``post``: :meth:`_compiled_post` if the caller has it (else made here).
        """
        N, n = self.num_envs, self.n
        s = self.system
        if post is None:
            post = self._compiled_post()
        if post is not None:
            p, goal, (x, v, mass) = post
            out = np.empty((5, N))
            success = np.empty(N, bool)
            if obs is None:  # (one compiled entry for both: the observation is scratch here,
                # sized from the record the kernel reads, as measure_observe sizes it)
                obs = np.empty((len(goal.goal), 4 * goal.n + 1), np.float32)
            rest, view = self._rest(), tuple(self._view())
            stepped, blocked = self._mask(stepped), self._mask(blocked)
            if not (s.threads > 1  # (ranges only with threads)
                    and self._measures_ranges(post, rest, walls, stepped, blocked, out,
                                              success, view, obs)):
                _measure.measures_observe((x, v, mass), tuple(goal), p.refs.blocks, walls,
                                          tuple(rest), stepped, blocked, out, success, view,
                                          obs)
            return _measured(out, success), out[4]
        v = s.v
        v2 = (v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]).reshape(N, n)
        residual = np.zeros(N)
        for c in s.constraints:  # tiled blocks list their rows copy by copy
            err = c.distance_error(s.x)
            if err.size:
                np.maximum(residual, err.reshape(N, -1).max(axis=1), out=residual)
        distance = self.goal_distance(self.positions())
        k = self.rest_count
        speed = np.sqrt(v2[:, :k].sum(axis=1) * (1.0 / k))
        wall_force = np.zeros(N)
        if walls:
            found = [w for w in s.forces if isinstance(w, Wall)]
            if any(w.penetration(s.x).max(initial=0.0) > 0 for w in found):  # else no contact
                F = np.zeros_like(s.x)
                for wall in found:
                    wall.accumulate(s.x, s.v, s.mass, F)
                wall_force = np.abs(F[:, 0]).reshape(N, n).sum(axis=1)
        if stepped is not None:
            settled = (distance < self.goal_tolerance) & (self.advance_rest(stepped, k)
                                                          < self.rest_speed)
            if self.wall_rest:
                settled &= ~(wall_force > 0)  # resting against a wall is not rest
            if blocked is not None:
                settled &= ~blocked
            self.hold[stepped] = np.where(settled[stepped], self.hold[stepped] + 1, 0)
        return {"distance": distance, "speed": speed,
                "kinetic_energy": 0.5 * (s.mass.reshape(N, n) * v2).sum(axis=1),
                "constraint_residual": residual,
                "is_success": self.hold >= self.hold_steps}, wall_force

    def _measures_ranges(self, post: tuple, rest: _measure.Rest, walls: bool,
                         stepped: np.ndarray, blocked: np.ndarray, out: np.ndarray,
                         success: np.ndarray, view: tuple, obs: np.ndarray) -> bool:
        """The compiled measures and observation of :meth:`_measures`, each range of the
        system's threaded steps (``ParticleSystem.thread_ranges``) on its own thread, over the
        copies in it (its blocks are the range's own, particle indices from the range's
        start); False, with nothing done, unless the ranges are those of the pack in ``post``
        and each holds whole copies (the caller then makes one call). A copy's measures read
        only its own particles, so they are the same bits as one call over all copies.

        The ranges are read, refreshed and run under the system's step lock: another thread
        cannot step the system, and with it change the ranges, in between."""
        n = self.n
        p, goal, (x, v, mass) = post
        with self.system.stepping():  # (the ranges' threads serve one caller at a time)
            part = self.system.thread_ranges()
            if (part is None or part.parent is not p or part.spans[-1][1] != len(x)
                    or any(lo % n or hi % n for lo, hi in part.spans)):
                return False
            calls, blocks = [], []
            for sp, (lo, hi) in zip(part.packs, part.spans, strict=True):
                c0, c1 = lo // n, hi // n
                sp.refresh(measured_only=True)
                out_r = np.empty((5, c1 - c0))
                blocks.append((c0, c1, out_r))
                calls.append(functools.partial(
                    _measure.measures_observe, (x[lo:hi], v[lo:hi], mass[lo:hi]),
                    tuple(goal._replace(goal=goal.goal[c0:c1])), sp.refs.blocks, walls,
                    tuple(rest._replace(hold=rest.hold[c0:c1], mean_v=rest.mean_v[lo:hi])),
                    stepped[c0:c1], blocked[c0:c1], out_r, success[c0:c1], view, obs[c0:c1]))
            part.map(calls)
        for c0, c1, out_r in blocks:
            out[:, c0:c1] = out_r
        return True

    def _rest(self) -> _measure.Rest:
        """The rest test's state as the compiled measures take it."""
        return _measure.Rest(self.hold, self.mean_v, self._alpha)

    def _rest_owned(self) -> bool:
        """True if the compiled measures may read and write the rest test's arrays."""
        N = self.num_envs
        return (_owned(self.hold, np.int64, (N,))
                and _owned(self.mean_v, np.float64, (N * self.n, 2)))

    def advance_rest(self, stepped: np.ndarray, count: int | None = None) -> np.ndarray:
        """Move the ``stepped`` copies' moving average velocities ``1 / rest_window`` of the
        way to the particles' velocities; returns every copy's *rest speed*, the RMS (m/s)
        of the averages of its first ``count`` particles (default all). The rest test
        compares it with ``rest_speed``: an average over about ``rest_window`` steps, so a
        policy's own zero-mean action noise averages out while a drift or a swing does not.
        (The numpy reference of the compiled measures.)"""
        N, n = self.num_envs, self.n
        rows = np.repeat(stepped, n)
        mv = self.mean_v[rows]
        mv += (self.system.v[rows] - mv) * self._alpha
        self.mean_v[rows] = mv
        k = n if count is None else count
        avg = self.mean_v.reshape(N, n, 2)[:, :k]
        return np.sqrt((avg[:, :, 0] * avg[:, :, 0] + avg[:, :, 1] * avg[:, :, 1]).sum(axis=1)
                       * (1.0 / k))

    def picture(self) -> Picture:
        """What a pixel observation shows (:mod:`envs.pixels`): the default picture made from
        the scene's blocks (cloth cells, springs, rods, walls, wires, particles, the goal,
        the human view's shaded regions); a task overrides it to draw more or otherwise. Called once
        per camera; its moving points are read from the task at every frame."""
        from .pixels import default_picture

        return default_picture(self)

    def drawing(self, i: int) -> tuple[ParticleSystem, list[Shape], str]:
        """Copy ``i`` as a drawable single system, its goal marker and a status line."""
        one = self.load_single(i)
        marker = Shape("marker", "goal", np.array([[self.goal[i], self.goal_height]]))
        distance = float(self.goal_distance(one.x[None], self.goal[i:i + 1])[0])
        status = (f"{type(self).__name__} ({self.action_mode})   distance to goal "
                  f"{distance:.3f} m   held {self.hold[i]}/{self.hold_steps}")
        return one, [marker], status

    #: Height (m) at which the goal marker is drawn (subclasses set it); the goal point's y
    #: for a task with :attr:`planar_goal`.
    goal_height: float = 0.0
    #: False: the goal is the x coordinate ``goal`` and the distance is along x (see
    #: :meth:`goal_distance`); True: the goal is the point ``(goal, goal_height)``.
    planar_goal: ClassVar[bool] = False
    #: With the walls' contact measured, a copy touching a wall is not at rest (its hold count
    #: restarts); False: the contact is measured but the rest test ignores it.
    wall_rest: ClassVar[bool] = True

    @property
    def rest_count(self) -> int:
        """The first particles of a copy whose RMS speed is its ``speed`` measure and whose
        moving average velocities make its rest test: all ``n``, unless the task has particles
        of its own that do not count (ClothPin's spring anchors)."""
        return self.n


def _measured(out: np.ndarray, success: np.ndarray) -> dict[str, np.ndarray]:
    """The measures dict from the compiled measures' output rows (see
    ``_measure.measures_observe``)."""
    return {"distance": out[0], "speed": out[1], "kinetic_energy": out[2],
            "constraint_residual": out[3], "is_success": success}
