"""Stable-Baselines3 on the native vector envs: :func:`to_sb3` wraps a Gymnasium ``VectorEnv``.

Stable-Baselines3 (SB3) trains on its own ``VecEnv`` interface, not on Gymnasium's ``VectorEnv``,
and the two disagree on what happens when an episode ends:

- Gymnasium 1.x vector envs (ours, ``CartPoleVectorEnv``, ``SyncVectorEnv``) use *next-step*
  autoreset: the step that ends an episode returns its last observation, and the *following*
  ``step`` resets that copy (ignoring its action, reward 0).
- SB3 wants *same-step* reset: the step that ends an episode returns ``done=True``, the first
  observation of the next episode, and the last one in ``info["terminal_observation"]``.

:func:`to_sb3` converts the first into the second by resetting the copies that just ended with
``reset(options={"reset_mask": mask})`` (only their slices are written), so nothing is stepped
twice and every copy keeps its own random stream. With the same seeds and actions the result
matches SB3's ``DummyVecEnv`` of single envs (``tests/test_sb3.py`` checks it to 1e-6 on
ClothSlide over episode ends); the native env steps all copies as one particle system, which is
what makes it faster.

>>> import gymnasium as gym
>>> import envs
>>> from envs.sb3 import to_sb3
>>> venv = to_sb3(gym.make_vec("ClothSlide-v0", num_envs=4,
...                            vectorization_mode="vector_entry_point"))
>>> _ = venv.seed(0)
>>> obs = venv.reset()
>>> obs.shape
(4, 145)
>>> obs, rewards, dones, infos = venv.step(np.zeros((4, 2), np.float32))
>>> rewards.shape, dones.dtype, sorted(infos[0])[:3]
((4,), dtype('bool'), ['TimeLimit.truncated', 'constraint_residual', 'distance'])

Requires the ``rl`` extra (``pip install -e ".[rl]"`` in the checkout).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from copy import deepcopy
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

from constrained_particles.extras import require

require("stable_baselines3", command="envs.sb3")  # (one line naming the extra, if missing)

from stable_baselines3.common.vec_env import VecEnv  # noqa: E402
from stable_baselines3.common.vec_env.base_vec_env import (  # noqa: E402
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
)

__all__ = ["GymnasiumVecEnv", "to_sb3"]


def _item(value: Any) -> Any:
    """numpy scalars as Python scalars (what a single env's info holds); dicts recursively."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: _item(v) for k, v in value.items()}
    return value


def _split_info(info: dict[str, Any], num_envs: int) -> list[dict[str, Any]]:
    """A Gymnasium vector info (dict of arrays, ``_key`` masks) as one dict per copy."""
    out: list[dict[str, Any]] = [{} for _ in range(num_envs)]
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info.get(f"_{key}")
        if isinstance(value, dict):
            parts = _split_info(value, num_envs)
            for i in range(num_envs):
                if mask is None or mask[i]:
                    out[i][key] = parts[i]
            continue
        for i in range(num_envs):
            if mask is None or mask[i]:
                out[i][key] = _item(value[i])
    return out


def _take(obs: Any, i: int) -> Any:
    """Copy ``i``'s observation from a batched array (or dict of arrays)."""
    if isinstance(obs, dict):
        return {k: _take(v, i) for k, v in obs.items()}
    return np.array(obs[i], copy=True)


def _put(obs: Any, new: Any, mask: np.ndarray) -> Any:
    """``obs`` with the masked copies' entries replaced from ``new``."""
    if isinstance(obs, dict):
        return {k: _put(obs[k], new[k], mask) for k in obs}
    out = np.array(obs, copy=True)
    out[mask] = new[mask]
    return out


class GymnasiumVecEnv(VecEnv):
    """An SB3 ``VecEnv`` over a Gymnasium ``VectorEnv`` with next-step autoreset (see
    :func:`to_sb3`).

    Attributes are shared by all copies of a vector env, so ``get_attr(name)`` returns the vector
    env's attribute once per requested index and ``set_attr`` sets it on the vector env (only for
    all indices at once); ``env_method(name)`` calls the vector env's method once and returns its
    result once per index. ``env_is_wrapped`` is False for every wrapper class: the copies are not
    individual ``gymnasium.Env`` objects (wrap the result in ``VecMonitor`` for episode stats).
    """

    def __init__(self, vector_env: VectorEnv) -> None:
        if not isinstance(vector_env, VectorEnv):
            raise TypeError(f"vector_env must be a gymnasium.vector.VectorEnv, got "
                            f"{type(vector_env).__name__}")
        mode = vector_env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        if isinstance(mode, str):
            mode = AutoresetMode(mode)
        if mode != AutoresetMode.NEXT_STEP:
            raise ValueError(f"vector_env must use next-step autoreset "
                             f"(metadata['autoreset_mode'] = AutoresetMode.NEXT_STEP), got {mode}")
        self.vector_env = vector_env
        super().__init__(vector_env.num_envs, vector_env.single_observation_space,
                         vector_env.single_action_space)
        self._actions: np.ndarray | None = None
        self._obs: Any = None

    # ------------------------------------------------------------------ stepping
    def reset(self) -> VecEnvObs:
        """Reset every copy (with the seeds of :meth:`seed`, if any, used once)."""
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        options = self._options[0] if self._options else {}
        if any(o != options for o in self._options):
            raise ValueError("to_sb3: a vector env takes one options dict for all copies; "
                             "set_options() got different options per copy")
        obs, info = self.vector_env.reset(seed=seeds, options=deepcopy(options) or None)
        self.reset_infos = _split_info(info, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        self._obs = obs
        return deepcopy(obs)

    def step_async(self, actions: np.ndarray) -> None:
        """Remember ``actions`` (num_envs, ...) for :meth:`step_wait`."""
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        """Step all copies; copies whose episode ended are reset in the same call, their last
        observation in ``info["terminal_observation"]``."""
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async()")
        if self._obs is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        actions, self._actions = self._actions, None
        obs, rewards, terminated, truncated, info = self.vector_env.step(actions)
        terminated = np.asarray(terminated, dtype=bool)
        truncated = np.asarray(truncated, dtype=bool)
        dones = terminated | truncated
        infos = _split_info(info, self.num_envs)
        for i in range(self.num_envs):
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if dones.any():
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = _take(obs, i)
            new_obs, reset_info = self.vector_env.reset(options={"reset_mask": dones.copy()})
            for i, part in enumerate(_split_info(reset_info, self.num_envs)):
                if dones[i]:
                    self.reset_infos[i] = part
            obs = _put(obs, new_obs, dones)
        self._obs = obs
        return (deepcopy(obs), np.asarray(rewards, dtype=np.float32).copy(), dones, infos)

    def close(self) -> None:
        """Close the vector env."""
        self.vector_env.close()

    # ------------------------------------------------------------------ attributes and methods
    def _count(self, indices: VecEnvIndices) -> int:
        return len(list(self._get_indices(indices)))

    def _all(self, indices: VecEnvIndices) -> bool:
        return sorted(self._get_indices(indices)) == list(range(self.num_envs))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The vector env's attribute ``attr_name``, once per index (AttributeError if absent)."""
        value = getattr(self.vector_env, attr_name)
        return [value] * self._count(indices)

    def set_attr(self, attr_name: str, value: object, indices: VecEnvIndices = None) -> None:
        """Set ``attr_name`` on the vector env; the copies share it, so ``indices`` must cover
        all of them (ValueError otherwise)."""
        if not self._all(indices):
            raise ValueError("to_sb3: attributes are shared by all copies of a vector env; "
                             "set_attr needs indices=None (all copies)")
        setattr(self.vector_env, attr_name, value)

    def env_method(self, method_name: str, *method_args: object, indices: VecEnvIndices = None,
                   **method_kwargs: object) -> list[Any]:
        """Call the vector env's method ``method_name`` once; its result, once per index."""
        result = getattr(self.vector_env, method_name)(*method_args, **method_kwargs)
        return [result] * self._count(indices)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper],
                       indices: VecEnvIndices = None) -> list[bool]:
        """False for every index: the copies are not individual wrapped envs."""
        return [False] * self._count(indices)

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One (H, W, 3) uint8 frame per copy (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array":
            raise ValueError(f"get_images needs render_mode='rgb_array', got {self.render_mode!r}")
        frames = self.vector_env.render()
        return list(frames) if frames is not None else [None] * self.num_envs

    def _get_indices(self, indices: VecEnvIndices) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, (int, np.integer)):
            return [int(indices)]
        return [int(i) for i in indices]

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.vector_env!r})"


def to_sb3(vector_env: VectorEnv) -> GymnasiumVecEnv:
    """An SB3 ``VecEnv`` over ``vector_env``, a Gymnasium ``VectorEnv`` with next-step autoreset.

    Same-step reset semantics (a copy whose episode ended this step is reset in the same call,
    its last observation in ``info["terminal_observation"]``), ``info["TimeLimit.truncated"]``
    (truncated and not terminated), ``seed(s)`` (copy ``i`` gets ``s + i`` at the next
    ``reset()``, as in SB3's ``DummyVecEnv``), ``set_options``, ``render()`` / ``get_images()``
    with ``render_mode="rgb_array"``, and ``get_attr``/``set_attr``/``env_method`` on the vector
    env. Rewards come back as float32 and dones as bool, per SB3's convention.

    Raises TypeError if ``vector_env`` is not a ``VectorEnv``, ValueError if its autoreset mode
    is not next-step.
    """
    return GymnasiumVecEnv(vector_env)
