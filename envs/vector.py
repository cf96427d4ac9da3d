"""The native vector env: ``num_envs`` copies of a task behind ``gymnasium.vector.VectorEnv``.

The copies are stepped as one particle system (:class:`~envs.base.ParticleTask` with
``num_envs`` copies). With ``num_threads=k`` (k > 1) that system's compiled physics steps on k
threads (``ParticleSystem.threads``, :mod:`constrained_particles.parallel`): its particles are
cut into k ranges of whole copies, each stepped by the fused kernel on a thread of its own,
while the Python around the kernels (actions, resets, measures, the info dict) runs once per
step, as with one thread. A copy's arithmetic does not depend on which copies share its range
(copy ``i`` of a vector env already reproduces a single env seeded ``seed + i``), so the
results are bit for bit the same for every ``num_threads``.

Numba's own threading layer (``prange``, ``NUMBA_NUM_THREADS``) is not used: the kernels step
one range serially and the parallelism is over ranges, so ``NUMBA_NUM_THREADS`` has no effect
on it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import ArrayLike, NDArray

from . import goals, pixels
from .base import ParticleTask
from .checks import check_options, check_positive, check_seed, check_task_kwargs
from .driver import StepPlan
from .single import _info, _Rendering

#: Number of threads a native vector env steps its copies on unless told otherwise.
DEFAULT_THREADS = 1


class ParticleVectorEnv(_Rendering, VectorEnv):
    """The native vector env: ``num_envs`` copies stepped as one system, whose physics runs on
    ``num_threads`` threads.

    Autoreset is ``NEXT_STEP`` (a copy that ended is reset by the following ``step``, which
    ignores its action and returns its first observation with reward 0); truncation after
    ``max_episode_steps`` is handled here. Copy ``i`` draws its randomness from its own generator,
    seeded with ``seed + i`` by ``reset(seed=seed)``, so it reproduces a single env (and
    ``SyncVectorEnv``) seeded the same way. ``reset(options={"reset_mask": mask})`` resets only
    the masked copies and writes only their slices.

    ``num_threads`` (default 1) steps the physics of that many ranges of consecutive copies
    on as many threads (``ParticleSystem.threads``; fewer where the copies are too few for the
    threads to gain, see :mod:`constrained_particles.parallel`, and on one while busy cores make
    the threads slower); every result is bit for bit the one of ``num_threads=1``. The default
    is one thread because the libraries that drive envs usually parallelise already: SB3's
    ``SubprocVecEnv`` and RLlib's EnvRunners run one env per process, and the policy network's
    torch threads want the remaining cores. Give it more where one process steps many copies
    on a machine with idle cores (for example ``num_threads=len(os.sched_getaffinity(0))``);
    with several EnvRunners, keep ``num_env_runners * num_threads`` at most the number of cores.
    """

    task_class: ClassVar[type[ParticleTask]]
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 20,
                                          "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, max_episode_steps: int | None = None,
                 render_mode: str | None = None, *, num_threads: int = DEFAULT_THREADS,
                 obs_mode: str = "state",
                 pixel_size: int | tuple[int, int] = pixels.DEFAULT_SIZE,
                 pixel_channels: int = 3, **kwargs: object) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or "
                             f"None, got {render_mode!r}")
        threads = check_positive("num_threads", num_threads, integer=True)
        if max_episode_steps is None:  # (the task's declaration says, else 200)
            from .task import registered_episode_steps
            max_episode_steps = registered_episode_steps(type(self))
        self.max_episode_steps = check_positive("max_episode_steps", max_episode_steps,
                                                integer=True)
        #: ``"state"`` (a flat Box), ``"goal"`` (Gymnasium-Robotics' Dict: see envs.goals),
        #: ``"pixels"`` or ``"state_pixels"`` (see envs.pixels)
        self._setup_pixels(obs_mode, pixel_size, pixel_channels)
        check_task_kwargs(self.task_class, kwargs, also=("num_envs", "max_episode_steps",
                                                         "render_mode", "num_threads",
                                                         "obs_mode", "pixel_size",
                                                         "pixel_channels"))
        self.task = self.task_class(num_envs, **kwargs)
        self.task.episode_steps = self.max_episode_steps  # (what divergence pays for)
        #: The threads the copies' physics is stepped on (``ParticleSystem.threads``).
        self.num_threads = self.task.system.threads = int(threads)
        self.num_envs = self.task.num_envs
        self.steps = np.zeros(self.num_envs, dtype=np.int64)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self.render_mode = render_mode
        self.metadata = {**self.metadata,
                         "render_fps": round(1.0 / (self.task.dt * self.task.substeps))}
        self.single_action_space = self.task.single_action_space
        self.single_observation_space = self._one_space()
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._renderer = None
        self._rngs: list[np.random.Generator] | None = None
        self._info_keys: tuple[tuple[str, ...], tuple[str, ...]] = ((), ())
        #: The prepared step of the task (envs.driver; it steps on one thread only), or None
        self._plan = StepPlan.make(self.task)

    # ------------------------------------------------------------------ seeding and reset
    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        """One seed (or None: keep the copy's generator) per copy, from ``reset``'s ``seed``."""
        N = self.num_envs
        if seed is None or isinstance(seed, (int, np.integer, bool, np.bool_)):
            first = check_seed(seed)
            return ([None] * N if first is None else [first + i for i in range(N)]) \
                if self._rngs is not None or first is not None else self._draw([None] * N)
        if isinstance(seed, (str, bytes)) or not hasattr(seed, "__len__") or len(seed) != N:
            raise ValueError(f"seed must be an int, None or a list of {N} seeds, got {seed!r}")
        seeds = [check_seed(s, f"seed[{i}]") for i, s in enumerate(seed)]
        return seeds if self._rngs is not None else self._draw(seeds)

    def _draw(self, seeds: list[int | None]) -> list[int | None]:
        """On the first reset: a seed drawn from ``np_random`` for each unseeded copy."""
        return [int(self.np_random.integers(2**63)) if s is None else s for s in seeds]

    def _seed_copies(self, seeds: list[int | None]) -> None:
        if self._rngs is None:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        else:
            self._rngs = [r if s is None else seeding.np_random(s)[0]
                          for r, s in zip(self._rngs, seeds, strict=True)]

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every copy, or those in ``options["reset_mask"]`` (a (num_envs,) bool array,
        the only option). ``seed``: a Python or numpy integer >= 0 (copy i gets seed + i), a
        list of one seed (or None) per copy, or None."""
        options = check_options(options, ("reset_mask",))
        one = seed is None or isinstance(seed, (int, np.integer, bool, np.bool_))
        seeds = self._seeds(seed)  # (checked before anything changes)
        super().reset(seed=seeds[0] if one and seed is not None else None)
        mask = np.ones(self.num_envs, bool)
        if "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != bool or not mask.any():
                raise ValueError("options['reset_mask'] must be a bool array of shape "
                                 f"({self.num_envs},) with at least one True")
        self._seed_copies(seeds)
        envs = np.flatnonzero(mask)
        if len(envs):
            self.task.reset_envs(envs, [self._rngs[i] for i in envs])
        self.steps[mask] = 0
        self._autoreset[mask] = False
        obs, info, _ = self._result(np.zeros(self.num_envs, bool))
        return obs, info

    # ------------------------------------------------------------------ stepping
    def step(self, actions: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        """Step every copy; copies that ended on the previous step are reset instead."""
        if self._rngs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        resetting = self._autoreset.copy()
        obs, reward, terminated, truncated, m, diverged = self._step_measured(actions)
        info = self._info(m, diverged)
        if self.obs_mode != "state":
            obs = self._observation(obs)
        if self.obs_mode == "goal":
            reward = self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
            reward[resetting] = 0.0  # (a copy's first observation after its autoreset)
        return obs, reward, terminated, truncated, info

    @goals.GoalModeOnly
    def compute_reward(self, achieved_goal: ArrayLike, desired_goal: ArrayLike,
                       info: goals.Info) -> float | NDArray[np.float64]:
        """The goal-mode reward of goals ``(..., k)`` (:func:`envs.goals.compute_reward`)."""
        return goals.compute_reward(self.task, achieved_goal, desired_goal, info)

    def _step_measured(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                    np.ndarray, dict[str, np.ndarray],
                                                    np.ndarray]:
        """:meth:`step` with the step's measures and divergence mask in place of the info dict
        made of them."""
        # (count_nonzero: any() in a fraction of the time)
        calm_start = not np.count_nonzero(self._autoreset)  # the usual step: no copy resets
        task = self.task
        a = task.check_actions(actions)
        planned = None
        if calm_start:
            task.apply(a)
            plan = self._plan  # (the prepared step where it can take it: the same bits)
            planned = plan.physics() if plan is not None and plan.task is task else None
            if planned is None:
                diverged = task.simulate_step()
                calm = not np.count_nonzero(diverged)  # every copy was stepped: no masks
            else:
                diverged, calm = np.zeros(self.num_envs, bool), True
                plan.hand(*planned)  # (the step's checked pack for the end of step below)
            done = task._finish_step(self.steps, self.max_episode_steps) if calm else None
            if planned is not None:
                task.__dict__.pop("_fresh_pack", None)  # (handed again to the measures)
            if done is not None:  # the task's compiled end of the step (the same values)
                obs, m, reward, terminated, truncated, self._autoreset, _ = done
                return obs, reward, terminated, truncated, m, diverged
            resetting = self._autoreset  # (all False; not written below)
        else:
            calm = False
            resetting = self._autoreset.copy()
            envs = np.flatnonzero(resetting)
            starts = self.task.sample_starts([self._rngs[i] for i in envs])
            self.task.write_starts(envs, *starts)
            self.task.apply(a, idle=resetting)
            if (len(envs) == self.num_envs  # every copy starts anew: no physics to keep
                    and self.task._paths["restart_all"]):
                self.task.pass_time()
                diverged = np.zeros(self.num_envs, bool)
            else:
                diverged = self.task.simulate_step()
                # the resetting copies were stepped along (no actuation); put their start back
                self.task.write_starts(envs, *starts)
                diverged[resetting] = False
        if planned is not None:
            m, obs = self._plan.measure_observe(*planned)
        else:
            m, obs = task.measure_observe(task._every_copy if calm else ~resetting & ~diverged)
        reward = task.reward(m)
        self.steps += 1
        if calm:
            terminated = m["is_success"].copy()
            truncated = self.steps >= self.max_episode_steps
        else:
            self.steps[resetting] = 0
            terminated = (m["is_success"] | diverged) & ~resetting
            truncated = (self.steps >= self.max_episode_steps) & ~resetting
            reward[diverged] -= self.task.divergence_penalty
            reward[resetting] = 0.0
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, m, diverged

    def _result(self, diverged: np.ndarray, stepped: np.ndarray | None = None
                ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
        m, obs = self.task.measure_observe(stepped)
        return self._observation(obs), self._info(m, diverged), m

    def _info(self, m: dict[str, np.ndarray], diverged: np.ndarray) -> dict[str, np.ndarray]:
        """The info dict of measures ``m``: every measure but ``speed``, ``diverged``, and a
        mask (all True) per key, as gymnasium's vector envs give them."""
        info = _info(m, diverged)
        keys = tuple(info)
        if keys != self._info_keys[0]:  # the mask names, made once per set of keys
            self._info_keys = (keys, tuple(f"_{k}" for k in keys))
        masks = np.ones((len(keys), self.num_envs), bool)  # one allocation, a row per key
        info.update(zip(self._info_keys[1], masks, strict=True))
        return info

    # ------------------------------------------------------------------ the rest
    def render(self) -> list[np.ndarray] | None:
        """One (400, 600, 3) uint8 frame per copy (``render_mode="rgb_array"``), all drawn in
        one rasteriser call (no pygame)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass it to make_vec()")
            return None
        return list(self._frames())

    def close(self, **kwargs: object) -> None:
        """Stop the physics threads (safe to call twice; a step after it starts them again;
        nothing to stop on an env whose constructor failed)."""
        task = self.__dict__.get("task")
        if task is not None:
            task.system.close_threads()
        super().close(**kwargs)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update(_renderer=None, _camera=None, _display=None)
        return state

    def __repr__(self) -> str:
        name = self.spec.id if self.spec is not None else type(self).__name__
        threads = f", num_threads={self.num_threads}" if self.num_threads > 1 else ""
        return f"{type(self).__name__}({name}, num_envs={self.num_envs}{threads})"
