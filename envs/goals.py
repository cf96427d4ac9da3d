"""Goal observations: ``obs_mode="goal"``, Gymnasium-Robotics' goal-conditioned interface.

With ``obs_mode="goal"`` an environment observes a ``Dict`` of

- ``observation``: the state observation without the goal (normalized positions, velocities,
  and a task's own entries such as ClothPin's springs), float32;
- ``achieved_goal``: where the task's tracked quantity is, in the view box's normalized
  coordinates: the tracked x (``(x - c_x) / h_x``: ClothSlide's cloth centre, SliderCrank's
  slider, ClothPin's cloth centre), or the tracked point (ChainSwing's tip, 2 values);
- ``desired_goal``: the goal in the same coordinates;

and its reward is :func:`compute_reward` of those two, the sparse reward of Gymnasium-Robotics'
tasks: ``-1`` while the achieved goal is farther than ``goal_tolerance`` metres from the desired
one, ``0`` within it (minus ``episode_steps``, a whole episode of -1 steps, on a diverged step,
read from ``info["diverged"]``). A function of the goals alone, so that hindsight relabelling (SB3's
``HerReplayBuffer``) recomputes it for any goal: the env's ``compute_reward(achieved_goal,
desired_goal, info)`` takes batches. The episode ends as in ``"state"`` mode (success: at the
goal and at rest for ``hold_steps`` steps; ``info["is_success"]``).

``obs_mode`` takes ``"state"`` (the default: a flat ``Box``), ``"goal"``, or the pixel
observations ``"pixels"`` and ``"state_pixels"`` (:mod:`envs.pixels`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from .base import ParticleTask

#: Valid values of ``obs_mode``.
OBS_MODES = ("state", "goal", "pixels", "state_pixels")

#: What ``compute_reward`` reads ``info["diverged"]`` from: one info dict (a single env's, or
#: a vector env's dict of arrays), a sequence of them (SB3's replay buffers), or None.
Info = Mapping[str, object] | Sequence[Mapping[str, object]] | None


def check_obs_mode(obs_mode: object) -> str:
    """``obs_mode`` if valid (ValueError naming the argument otherwise)."""
    if not isinstance(obs_mode, str) or obs_mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
    return obs_mode


def goal_size(task: ParticleTask) -> int:
    """Entries of a goal: 2 for a task with a point as its goal, else 1."""
    return 2 if task.planar_goal else 1


def goal_column(task: ParticleTask) -> int:
    """Index of the goal in the task's state observation (after the observed particles'
    positions and velocities)."""
    return 4 * task.rest_count


def goal_space(task: ParticleTask) -> spaces.Dict:
    """The ``Dict`` observation space of one copy of ``task`` in goal mode."""
    box = task.single_observation_space
    k = goal_size(task)
    low, high = float(box.low.flat[0]), float(box.high.flat[0])
    return spaces.Dict({
        "observation": spaces.Box(low, high, (box.shape[0] - 1,), np.float32),
        "achieved_goal": spaces.Box(low, high, (k,), np.float32),
        "desired_goal": spaces.Box(low, high, (k,), np.float32)})


def _unit(value: np.ndarray, limit: float) -> np.ndarray:
    return np.clip(value.astype(np.float32), np.float32(-limit), np.float32(limit))


def goal_observation(task: ParticleTask, obs: np.ndarray) -> dict[str, np.ndarray]:
    """The goal-mode observation of every copy from their state observations ``obs``
    (num_envs, D): the goal column moved out of ``observation``, the achieved goal computed
    from the positions (float64, then rounded to float32 and clipped as the state is)."""
    g = goal_column(task)
    limit = float(task.single_observation_space.high.flat[0])
    x = task.positions()
    cx, cy = task.center
    hx, hy = task.half
    achieved = [(task.tracked(x) - cx) * (1.0 / hx)]
    desired = [(task.goal - cx) * (1.0 / hx)]
    if task.planar_goal:
        idx = task.tracked_particles
        achieved.append((x[:, idx, 1].sum(axis=1) * (1.0 / len(idx)) - cy) * (1.0 / hy))
        desired.append(np.full(task.num_envs, (task.goal_height - cy) * (1.0 / hy)))
    return {"observation": np.delete(obs, g, axis=1),
            "achieved_goal": _unit(np.stack(achieved, axis=1), limit),
            "desired_goal": _unit(np.stack(desired, axis=1), limit)}


def _diverged(info: Info, shape: tuple[int, ...]) -> np.ndarray:
    """``info["diverged"]`` as a bool array of ``shape``: from one info dict (a single env or
    a vector env's dict of arrays), from a sequence of them (SB3's replay buffers), or False
    where there is none."""
    if isinstance(info, Mapping):
        return np.broadcast_to(np.asarray(info.get("diverged", False), bool), shape)
    if isinstance(info, Sequence | np.ndarray) and len(info) and isinstance(info[0], Mapping):
        return np.array([bool(i.get("diverged", False)) for i in info]).reshape(shape)
    return np.zeros(shape, bool)


class GoalModeOnly:
    """A method that exists only on an env made with ``obs_mode="goal"``: elsewhere reading it
    raises AttributeError, so ``hasattr(env, "compute_reward")`` (how Stable-Baselines3's and
    Gymnasium-Robotics' checkers tell a goal-conditioned env) is False in the other modes."""

    def __init__(self, method: Callable[..., object]) -> None:
        self.method = method
        self.__doc__ = method.__doc__
        self.__name__ = method.__name__

    def __get__(self, obj: object, owner: type | None = None) -> object:
        if obj is None:
            return self
        if getattr(obj, "obs_mode", None) != "goal":
            raise AttributeError(f"{self.__name__} exists only with obs_mode='goal'")
        return self.method.__get__(obj, owner)


def compute_reward(task: ParticleTask, achieved_goal: ArrayLike, desired_goal: ArrayLike,
                   info: Info) -> float | NDArray[np.float64]:
    """The goal-mode reward (see the module docstring) of goals ``(..., k)`` in normalized
    coordinates: ``-1.0`` where they are farther apart than ``goal_tolerance`` metres, else
    ``0.0``, less ``task.episode_steps`` where ``info`` says the step diverged. A float for one
    pair, else an array of the batch's shape."""
    a = np.asarray(achieved_goal, np.float64)
    d = np.asarray(desired_goal, np.float64)
    k = goal_size(task)
    if a.shape != d.shape or a.shape[-1:] != (k,):
        raise ValueError(f"achieved_goal and desired_goal must have the same shape (..., {k}), "
                         f"got {a.shape} and {d.shape}")
    gap = (a - d) * task.half[:k]
    distance = np.sqrt(np.sum(gap * gap, axis=-1))
    reward = -(distance > task.goal_tolerance).astype(np.float64)
    # (a diverged step pays for a whole episode of -1 steps: never a cheaper way out)
    reward = reward - float(task.episode_steps) * _diverged(info, reward.shape)
    return float(reward) if reward.ndim == 0 else reward
