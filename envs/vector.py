"""The native vector env: ``num_envs`` copies of a task behind ``gymnasium.vector.VectorEnv``.

The copies are stepped as one particle system (:class:`~envs.base.ParticleTask` with
``num_envs`` copies), or, with ``num_threads=k`` (k > 1), as k systems ("shards") of about
``num_envs / k`` consecutive copies each, stepped at the same time on k threads. The compiled
kernels release the GIL, so the shards' physics runs in parallel; what remains serial is the
Python between kernel calls (a few per step). A copy's arithmetic does not depend on which
copies share its system (copy ``i`` of a vector env already reproduces a single env seeded
``seed + i``), so the results are bit for bit the same for every ``num_threads``.

The calling thread steps the first shard and one thread per other shard, started with the
env, steps each of the others; between steps those threads poll for the next one for
:data:`POLL_SECONDS`, then sleep on an event (waking one costs more than a short step's
hand-off can afford).

Threads, not processes: the shards share the caller's memory (no pickling, observations are
written where the agent reads them), and a step is one synchronisation, not two messages.
Numba's own threading layer (``prange``, ``NUMBA_NUM_THREADS``) is not used: the kernels step
one system serially and the parallelism is over whole systems, so ``NUMBA_NUM_THREADS`` has no
effect on it.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .base import ParticleTask
from .checks import check_positive, checked_actions
from .single import _info, _Rendering

#: Number of threads a native vector env steps its copies on unless told otherwise.
DEFAULT_THREADS = 1
#: Seconds a shard's thread keeps polling for the next step before it sleeps on an event: a
#: wake-up from the event costs this VM about 150 us per step, polling a few; a busy training
#: loop steps again well within it, an idle env costs no CPU after it.
POLL_SECONDS = 0.002


class _Crew:
    """``k`` daemon threads that each run one call per :meth:`run`, the calling thread running
    another; between runs a thread polls for its next call for :data:`POLL_SECONDS`, then waits
    on an event."""

    _STOP = object()

    def __init__(self, k: int, name: str) -> None:
        self._calls: list[Any] = [None] * k
        self._results: list[tuple[bool, Any] | None] = [None] * k
        self._wake = [threading.Event() for _ in range(k)]
        self._threads = [threading.Thread(target=self._serve, args=(i,), daemon=True,
                                          name=f"{name}-{i + 1}") for i in range(k)]
        for t in self._threads:
            t.start()

    def _serve(self, i: int) -> None:
        while True:
            start = time.perf_counter()
            while self._calls[i] is None:
                if time.perf_counter() - start < POLL_SECONDS:
                    time.sleep(0)  # (yields the GIL and the core)
                else:
                    self._wake[i].wait()
                    self._wake[i].clear()
            call = self._calls[i]
            if call is self._STOP:
                return
            self._calls[i] = None  # taken (before the result is out: run() may then call again)
            try:
                result = (True, call())
            except BaseException as exc:  # handed to the caller of run()
                result = (False, exc)
            self._results[i] = result

    def run(self, first: Callable[[], Any], others: list[Callable[[], Any]]) -> list[Any]:
        """``first()`` on this thread and ``others[i]()`` on thread i; every result once all
        have returned, raising the first error (this thread's first)."""
        for i, call in enumerate(others):
            self._results[i] = None
            self._calls[i] = call
            self._wake[i].set()
        try:
            mine = first()
        finally:
            for i in range(len(others)):  # no call is still running when this returns
                while self._results[i] is None:
                    time.sleep(0)
        out = [mine]
        for i in range(len(others)):
            ok, value = self._results[i]  # type: ignore[misc]
            self._results[i] = None
            if not ok:
                raise value
            out.append(value)
        return out

    def close(self) -> None:
        """Stop the threads (safe to call twice)."""
        for i, t in enumerate(self._threads):
            if t.is_alive():
                self._calls[i] = self._STOP
                self._wake[i].set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join()


class ParticleVectorEnv(_Rendering, VectorEnv):
    """The native vector env: ``num_envs`` copies stepped as one system, or as ``num_threads``
    systems on as many threads.

    Autoreset is ``NEXT_STEP`` (a copy that ended is reset by the following ``step``, which
    ignores its action and returns its first observation with reward 0); truncation after
    ``max_episode_steps`` is handled here. Copy ``i`` draws its randomness from its own generator,
    seeded with ``seed + i`` by ``reset(seed=seed)``, so it reproduces a single env (and
    ``SyncVectorEnv``) seeded the same way. ``reset(options={"reset_mask": mask})`` resets only
    the masked copies and writes only their slices.

    ``num_threads`` (default 1) splits the copies into that many shards of consecutive copies
    (at most ``num_envs``), each its own vector env in :attr:`shards`, stepped on a thread of
    its own; every result is bit for bit the one of ``num_threads=1``. The default is one thread
    because the libraries that drive envs usually parallelise already: SB3's ``SubprocVecEnv``
    and RLlib's EnvRunners run one env per process, and the policy network's torch threads
    want the remaining cores. Give it more where one process steps many copies on a machine
    with idle cores (for example ``num_threads=len(os.sched_getaffinity(0))``); with several
    EnvRunners, keep ``num_env_runners * num_threads`` at most the number of cores.
    """

    task_class: ClassVar[type[ParticleTask]]
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 20,
                                          "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, max_episode_steps: int = 200,
                 render_mode: str | None = None, *, num_threads: int = DEFAULT_THREADS,
                 **kwargs: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or "
                             f"None, got {render_mode!r}")
        threads = check_positive("num_threads", num_threads, integer=True)
        self.max_episode_steps = check_positive("max_episode_steps", max_episode_steps,
                                                integer=True)
        #: The shards (vector envs of consecutive copies, one per thread) when ``num_threads``
        #: > 1; empty when this env steps its copies itself.
        self.shards: tuple[ParticleVectorEnv, ...] = ()
        if threads > 1 and isinstance(num_envs, (int, np.integer)) and num_envs > 1:
            k = min(threads, int(num_envs))
            sizes = [num_envs // k + (i < num_envs % k) for i in range(k)]
            self.shards = tuple(type(self)(n, max_episode_steps, render_mode, **kwargs)
                                for n in sizes)
            #: The first shard's task: the task's parameters (every shard has the same); the
            #: copies' state is in the shards' tasks.
            self.task = self.shards[0].task
            self.num_envs = int(num_envs)
            self._bounds = np.cumsum([0, *sizes])
            self._slices = [slice(int(a), int(a + n)) for a, n in zip(self._bounds, sizes,
                                                                      strict=False)]
        else:
            self.task = self.task_class(num_envs, **kwargs)
            self.task.episode_steps = self.max_episode_steps  # (what divergence pays for)
            self.num_envs = self.task.num_envs
            self.steps = np.zeros(self.num_envs, dtype=np.int64)
            self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self.num_threads = max(len(self.shards), 1)
        self.render_mode = render_mode
        self.metadata = {**self.metadata,
                         "render_fps": round(1.0 / (self.task.dt * self.task.substeps))}
        self.single_action_space = self.task.single_action_space
        self.single_observation_space = self.task.single_observation_space
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._renderer = None
        self._rngs: list[np.random.Generator] | None = None
        self._info_keys: tuple[tuple[str, ...], tuple[str, ...]] = ((), ())
        self._crew: _Crew | None = None

    # ------------------------------------------------------------------ seeding and reset
    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        """One seed (or None: keep the copy's generator) per copy, from ``reset``'s ``seed``."""
        N = self.num_envs
        seeds = ([seed + i for i in range(N)] if isinstance(seed, (int, np.integer))
                 else [None] * N if seed is None else list(seed))
        if len(seeds) != N:
            raise ValueError(f"seed must be an int, None or a list of {N} seeds, got {seed!r}")
        if self._rngs is None:  # first reset: unseeded copies draw a seed from np_random
            seeds = [int(self.np_random.integers(2**63)) if s is None else s for s in seeds]
        return seeds

    def _seed_copies(self, seeds: list[int | None]) -> None:
        if self._rngs is None:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        else:
            self._rngs = [r if s is None else seeding.np_random(s)[0]
                          for r, s in zip(self._rngs, seeds, strict=True)]

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every copy, or those in ``options["reset_mask"]`` (a (num_envs,) bool array)."""
        super().reset(seed=seed if isinstance(seed, (int, np.integer)) else None)
        seeds = self._seeds(seed)
        mask = np.ones(self.num_envs, bool)
        if options is not None and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != bool or not mask.any():
                raise ValueError("options['reset_mask'] must be a bool array of shape "
                                 f"({self.num_envs},) with at least one True")
        if not self.shards:
            return self._reset_copies(seeds, mask)
        self._rngs = []  # (marks the env as reset; the generators live in the shards)
        parts = [(seeds[sl], mask[sl]) for sl in self._slices]
        return self._joined(self._map(lambda env, part: env._reset_copies(*part), parts))

    def _reset_copies(self, seeds: list[int | None], mask: np.ndarray
                      ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reseed the copies (``seeds`` as from :meth:`_seeds`), then reset the masked ones (none
        at all is allowed: a shard without a masked copy only returns its observation)."""
        self._seed_copies(seeds)
        envs = np.flatnonzero(mask)
        if len(envs):
            self.task.reset_envs(envs, [self._rngs[i] for i in envs])
        self.steps[mask] = 0
        self._autoreset[mask] = False
        obs, info, _ = self._result(np.zeros(self.num_envs, bool))
        return obs, info

    # ------------------------------------------------------------------ stepping
    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        """Step every copy; copies that ended on the previous step are reset instead."""
        if self._rngs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        if not self.shards:
            return self._step_copies(actions)
        # every action is checked before any shard steps: a bad one changes nothing
        a = checked_actions(actions, self.num_envs, self.task.action_dim)
        parts = [a[sl] for sl in self._slices]
        # the shards return their measures; the info dict is made once, from the joined ones
        obs, reward, terminated, truncated, m, diverged = self._joined(
            self._map(lambda env, part: env._step_measured(part), parts))
        return obs, reward, terminated, truncated, self._info(m, diverged)

    def _step_copies(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                  np.ndarray, dict[str, Any]]:
        """:meth:`step` of the copies this env steps itself (all, or a shard's)."""
        obs, reward, terminated, truncated, m, diverged = self._step_measured(actions)
        return obs, reward, terminated, truncated, self._info(m, diverged)

    def _step_measured(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                    np.ndarray, dict[str, np.ndarray],
                                                    np.ndarray]:
        """:meth:`_step_copies` with the step's measures and divergence mask in place of the
        info dict made of them."""
        # (count_nonzero: any() in a fraction of the time)
        calm_start = not np.count_nonzero(self._autoreset)  # the usual step: no copy resets
        a = self.task.check_actions(actions)
        if calm_start:
            self.task.apply(a)
            diverged = self.task.simulate()
            calm = not np.count_nonzero(diverged)  # every copy was stepped: no masks to apply
            done = self.task._finish_step(self.steps, self.max_episode_steps) if calm else None
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
                diverged = self.task.simulate()
                # the resetting copies were stepped along (no actuation); put their start back
                self.task.write_starts(envs, *starts)
                diverged[resetting] = False
        m, obs = self.task.measure_observe(self.task._every_copy if calm
                                           else ~resetting & ~diverged)
        reward = self.task.reward(m)
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
        return obs, self._info(m, diverged), m

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

    # ------------------------------------------------------------------ shards
    def _map(self, call: Callable[[ParticleVectorEnv, Any], Any], parts: list[Any]
             ) -> list[Any]:
        """``call(shard, part)`` for every shard and its part, the first on this thread and the
        others on the crew's; returns once every call has returned, raising the first error."""
        if self._crew is None:
            self._crew = _Crew(len(self.shards) - 1, f"{type(self).__name__}-shard")
            weakref.finalize(self, self._crew.close)  # (an env never closed frees its threads)
        return self._crew.run(
            lambda: call(self.shards[0], parts[0]),
            [lambda env=env, part=part: call(env, part)
             for env, part in zip(self.shards[1:], parts[1:], strict=True)])

    @staticmethod
    def _joined(results: list[tuple]) -> Any:
        """The shards' ``reset`` or ``step`` results joined along the copies."""
        joined = []
        for part in zip(*results, strict=True):
            if isinstance(part[0], dict):
                joined.append({k: np.concatenate([d[k] for d in part]) for k in part[0]})
            else:
                joined.append(np.concatenate(part))
        return tuple(joined)

    def _shard_of(self, i: int) -> tuple[ParticleVectorEnv, int]:
        """The env stepping copy ``i`` and the copy's index in it."""
        if not self.shards:
            return self, i
        k = int(np.searchsorted(self._bounds, i, side="right")) - 1
        return self.shards[k], i - int(self._bounds[k])

    # ------------------------------------------------------------------ the rest
    def render(self) -> list[np.ndarray] | None:
        """One (H, W, 3) uint8 frame per copy (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass it to make_vec()")
            return None
        frames = []
        for i in range(self.num_envs):
            env, j = self._shard_of(i)
            frames.append(env._frame(j))
        return frames

    def close(self, **kwargs: Any) -> None:
        """Stop the shards' threads (safe to call twice)."""
        if self._crew is not None:
            self._crew.close()
            self._crew = None
        super().close(**kwargs)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update(_renderer=None, _crew=None)
        return state

    def __repr__(self) -> str:
        name = self.spec.id if self.spec is not None else type(self).__name__
        threads = f", num_threads={self.num_threads}" if self.shards else ""
        return f"{type(self).__name__}({name}, num_envs={self.num_envs}{threads})"
