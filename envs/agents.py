"""Baseline agents: a random agent and a scripted controller for each env and action mode.

An agent is a callable ``agent(obs) -> action`` that works on one observation ``(obs_dim,)`` or a
batch ``(B, obs_dim)`` (for vector envs). Scripted controllers decode the observation with the
env's own normalization (positions, velocities, goal) and run PD control:

- ClothSlide: PD on the cloth's centre of mass toward the goal; the total force goes to the two
  top corners (force mode) or through a mouse spring on the top row's middle particle (spring).
- SliderCrank: the crank angle above the wire that puts the slider at the goal, reached by PD
  control on the angle plus gravity compensation, as a tangential force (force mode) or through a
  mouse spring on the crank (spring mode).

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
from typing import Any

import numpy as np

from constrained_particles.scenes import G

from .base import ParticleTask
from .cloth_slide import ClothSlide
from .slider_crank import SliderCrank

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
            # a spring from the particle's position to an anchor F / ks ahead of it
            p = x[:, self.spring_particle]
            a = np.concatenate([t.to_normalized(p), t.to_normalized(p + F / t.mouse_ks)], axis=1)
        a = np.clip(a, -1.0, 1.0).astype(np.float32)
        return a if np.ndim(obs) > 1 else a[0]

    def force_action(self, F: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The force-mode action (B, force_dim) that applies ``F``."""
        raise NotImplementedError


class ClothSlideController(ScriptedAgent):
    """PD control of the cloth's centre of mass: ``F = kp (goal - c) - kd c_dot``, total force
    capped at ``f_max`` newtons so the cloth never hits the wall hard."""

    def __init__(self, task: ClothSlide, kp: float = 3.0, kd: float = 2.5,
                 f_max: float = 1.0) -> None:
        super().__init__(task)
        self.kp, self.kd, self.f_max = kp, kd, f_max
        self.spring_particle = task.nx // 2

    def force(self, x, v, goal):
        c = x[:, :, 0].mean(axis=1)
        c_dot = v[:, :, 0].mean(axis=1)
        F = np.clip(self.kp * (goal - c) - self.kd * c_dot, -self.f_max, self.f_max)
        return np.stack([F, np.zeros_like(F)], axis=1)

    def force_action(self, F, x):
        per_corner = F[:, 0] / (2 * self.task.max_force)
        return np.stack([per_corner, per_corner], axis=1)


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
        F_t = t.particle_mass * G * np.cos(theta) + self.kp * error - self.kd * v_t
        return F_t[:, None] * tangent

    def force_action(self, F, x):
        crank = x[:, 0]
        tangent = np.stack([-crank[:, 1], crank[:, 0]], axis=1)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        return np.sum(F * tangent, axis=1, keepdims=True) / self.task.max_force


_CONTROLLERS: dict[type, type[ScriptedAgent]] = {
    ClothSlide: ClothSlideController,
    SliderCrank: SliderCrankController,
}


def make_agent(kind: str, env: Any, seed: int | None = None) -> Agent:
    """A ``"random"`` or ``"scripted"`` agent for ``env`` (a made env or native vector env).

    ``seed`` seeds the random agent's generator.
    """
    if kind not in AGENTS:
        raise ValueError(f"agent must be one of {AGENTS}, got {kind!r}")
    task = env.unwrapped.task
    if kind == "random":
        return RandomAgent(task.action_dim, seed)
    return _CONTROLLERS[type(task)](task)
