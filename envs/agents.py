"""Baseline agents: a random agent, and each task's scripted agent (its declaration's).

An agent is a callable ``agent(obs) -> action`` that works on one observation ``(obs_dim,)`` or a
batch ``(B, obs_dim)`` (for vector envs). Each task module defines its scripted agent beside the
task and names it in its :class:`~envs.task.TaskSpec` (``scripted_agent``); most decode the
observation with the env's own normalization (positions, velocities, goal) through
:class:`ScriptedAgent` and run PD or LQR control on the force the task wants.

>>> import gymnasium as gym
>>> import envs
>>> from envs.agents import make_agent
>>> env = gym.make("SliderCrank-v0")
>>> agent = make_agent("scripted", env)
>>> obs, info = env.reset(seed=0)
>>> env.action_space.contains(agent(obs))
True
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import gymnasium as gym
    from gymnasium.vector import VectorEnv

    from .base import ParticleTask

Agent = Callable[[np.ndarray], np.ndarray]

#: Agent kinds accepted by :func:`make_agent`.
AGENTS = ("random", "scripted")


class RandomAgent:
    """Uniform random actions in [-1, 1] from its own generator (seeded with ``seed``)."""

    def __init__(self, action_dim: int, seed: int | None = None) -> None:
        self.action_dim = action_dim
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        shape = np.shape(obs)[:-1] + (self.action_dim,)
        return self.rng.uniform(-1.0, 1.0, shape).astype(np.float32)


class ScriptedAgent:
    """Base of the PD controllers: decodes observations of ``task``'s layout."""

    def __init__(self, task: ParticleTask) -> None:
        self.task = task

    def decode(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (B, n, 2) m, velocities (B, n, 2) m/s and goals (B,) m from observations."""
        t = self.task
        o = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        B, n = len(o), t.n
        x = t.to_world(o[:, :2 * n].reshape(B, n, 2))
        v = o[:, 2 * n:4 * n].reshape(B, n, 2) * t.half
        goal = t.center[0] + t.half[0] * o[:, 4 * n]
        return x, v, goal

    def force(self, x: np.ndarray, v: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """The force (B, 2) in newtons the controller wants on its handle particle(s)."""
        raise NotImplementedError

    #: Particle (index within one copy) pulled by the mouse spring in spring mode.
    spring_particle: int = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x, v, goal = self.decode(obs)
        F = self.force(x, v, goal)
        t = self.task
        if t.action_mode == "force":
            a = self.force_action(F, x)
        else:
            # grab the particle where it is and pull it with F (the target F / ks ahead of it)
            p = x[:, self.spring_particle]
            a = np.concatenate([t.to_normalized(p), F / t.max_force], axis=1)
        a = np.clip(a, -1.0, 1.0).astype(np.float32)
        return a if np.ndim(obs) > 1 else a[0]

    def force_action(self, F: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The force-mode action (B, force_dim) that applies ``F``."""
        raise NotImplementedError


def make_agent(kind: str, env: gym.Env | VectorEnv, seed: int | None = None) -> Agent:
    """A ``"random"`` or ``"scripted"`` agent for ``env`` (a made env or native vector env).

    ``seed`` seeds the random agent's generator; the scripted agent is the one the task's
    declaration names (:attr:`envs.task.TaskSpec.scripted_agent`).
    """
    if kind not in AGENTS:
        raise ValueError(f"agent must be one of {AGENTS}, got {kind!r}")
    task = env.unwrapped.task
    if kind == "random":
        return RandomAgent(task.action_dim, seed)
    from .task import spec_of_task

    return spec_of_task(task).scripted_agent(task)
