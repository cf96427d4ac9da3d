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
import scipy.linalg

from constrained_particles import ConstantForce, ParticleSystem
from constrained_particles.scenes import G

from .base import ParticleTask
from .chain_swing import ChainSwing
from .cloth_pin import ClothPin
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
            # grab the particle where it is and pull it with F (the target F / ks ahead of it)
            p = x[:, self.spring_particle]
            a = np.concatenate([t.to_normalized(p), F / t.max_force], axis=1)
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


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi)."""
    return np.mod(angle + np.pi, 2 * np.pi) - np.pi


class ChainSwingController(ScriptedAgent):
    """Linear-quadratic control of the chain in its own coordinates, linearized from the physics.

    The state is ``s = (x_c, phi_1 .. phi_L, xdot_c, phidot_1 .. phidot_L)``: the carrier's x
    (m) and each link's angle from the downward vertical (rad), with rates. :func:`linearize`
    differentiates the task's own particle system (rods, angular springs, drag, with a force on
    the carrier) by central differences about the straight chain hanging down (``"lateral"``) or
    standing up (``"swingup"``); a discrete LQR for the env step (zero-order hold) gives the
    feedback ``F = -K (s - s_goal)`` in newtons.

    For ``"swingup"`` the chain is first pumped up: in the carrier's frame a carrier
    acceleration ``a`` does work ``-a p`` on the chain per second (``p`` the chain's horizontal
    momentum relative to the carrier, in kg m/s), so the controller asks for
    ``a = -pump g (E* - E) / E* sign(p) - kx (x_c - goal) - kv xdot_c`` (m/s^2; ``E`` the
    chain's energy in the carrier's frame, ``E*`` the upright chain's, ``(kx, kv) = center``)
    and finds the force that gives it from the physics (:meth:`carrier_response`: the light
    carrier's acceleration depends as much on the swinging chain as on the force). The LQR takes
    over once every link is within ``catch`` rad of upright.
    """

    def __init__(self, task: ChainSwing, catch: float = 0.8, pump: float = 12.0,
                 center: tuple[float, float] = (3.0, 2.0)) -> None:
        super().__init__(task)
        self.catch, self.pump, self.center = catch, pump, center
        self._tiled: tuple[int, ParticleSystem] | None = None
        self.spring_particle = 0
        L = task.links
        up = np.pi if task.target == "swingup" else 0.0
        self.rest = np.full(L, up)
        A, B = linearize(task, self.rest)
        h = task.dt * task.substeps
        # zero-order hold: expm([[A, B], [0, 0]] h) = [[Ad, Bd], [0, I]]
        M = np.zeros((2 * L + 3, 2 * L + 3))
        M[:2 * L + 2, :2 * L + 2], M[:2 * L + 2, -1:] = A, B
        E = scipy.linalg.expm(M * h)
        Ad, Bd = E[:2 * L + 2, :2 * L + 2], E[:2 * L + 2, -1:]
        Q = np.diag([20.0] + [10.0] * L + [1.0] + [0.2] * L)
        R = np.array([[0.05]])
        P = scipy.linalg.solve_discrete_are(Ad, Bd, Q, R)
        self.K = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)[0]
        self.upright_energy = G * task.particle_mass * task.link * L * (L + 1) / 2

    def carrier_response(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(a0, b)`` (B,) with the carrier's acceleration ``a0 + b F`` (m/s^2) under a force
        ``F`` (N) on it, from the physics at positions ``x`` and velocities ``v`` (B, n, 2)."""
        B = len(x)
        if self._tiled is None or self._tiled[0] != B:
            scene = self.task.build_scene()
            scene.add(ConstantForce([0], [[0.0, 0.0]]))
            self._tiled = (B, scene.tile(B))
        s = self._tiled[1]
        X, V = x.reshape(-1, 2), v.reshape(-1, 2)
        s.forces[-1].force[:] = 0.0
        a0 = s.acceleration(0.0, X, V).reshape(B, -1, 2)[:, 0, 0]
        s.forces[-1].force[:, 0] = 1.0
        a1 = s.acceleration(0.0, X, V).reshape(B, -1, 2)[:, 0, 0]
        return a0, a1 - a0

    def state(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Link angles (B, L) in rad and their rates (B, L) in rad/s from particle states."""
        d = np.diff(x, axis=1)
        dv = np.diff(v, axis=1)
        phi = np.arctan2(d[..., 0], -d[..., 1])
        rate = (d[..., 0] * dv[..., 1] - d[..., 1] * dv[..., 0]) / np.sum(d * d, axis=2)
        return phi, rate

    def force(self, x, v, goal):
        t = self.task
        phi, rate = self.state(x, v)
        err = np.concatenate([(x[:, 0, 0] - goal)[:, None], _wrap(phi - self.rest),
                              v[:, 0, :1], rate], axis=1)
        F = -err @ self.K
        if t.target == "swingup":
            rel = v[:, 1:] - v[:, :1]
            m = t.particle_mass
            energy = (0.5 * m * np.sum(rel**2, axis=(1, 2)) + m * G * np.sum(x[:, 1:, 1], axis=1)
                      + 0.5 * t.stiffness * np.sum(_wrap(np.diff(phi, axis=1)) ** 2, axis=1))
            p = m * np.sum(rel[:, :, 0], axis=1)
            deficit = np.clip((self.upright_energy - energy) / self.upright_energy, -1.0, 1.0)
            kx, kv = self.center
            a_want = (-self.pump * G * deficit * np.sign(p)
                      - kx * (x[:, 0, 0] - goal) - kv * v[:, 0, 0])
            a0, b = self.carrier_response(x, v)
            swing = (a_want - a0) / b
            caught = np.all(np.abs(_wrap(phi - self.rest)) < self.catch, axis=1)
            F = np.where(caught, F, swing)
        if t.action_mode == "spring":  # the mouse spring's own damping, compensated
            F = F + t.mouse_kd * v[:, 0, 0]
        return np.stack([F, np.zeros_like(F)], axis=1)

    def force_action(self, F, x):
        return F[:, :1] / self.task.max_force


def linearize(task: ChainSwing, angles: np.ndarray, eps: float = 1e-6
              ) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` of ``sdot = A s + B F`` about the chain at rest with link ``angles`` (rad),
    ``s`` as in :class:`ChainSwingController` and ``F`` a horizontal force (N) on the carrier,
    by central differences of the task's particle system."""
    s = task.build_scene()
    push = ConstantForce([0], [[0.0, 0.0]])
    s.add(push)
    L, l = task.links, task.link

    def accel(z: np.ndarray, F: float) -> np.ndarray:
        x, v = task.chain(z[0], z[1:L + 1], z[L + 2:])
        v[:, 0] += z[L + 1]
        push.force[0, 0] = F
        a = s.acceleration(0.0, x, v)
        phi = z[1:L + 1]
        dd = np.diff(a, axis=0)
        # d = l (sin phi, -cos phi) per link, so phi'' = d'' . (cos phi, sin phi) / l exactly
        return np.concatenate([[a[0, 0]], (dd[:, 0] * np.cos(phi) + dd[:, 1] * np.sin(phi)) / l])

    z0 = np.concatenate([[0.0], angles, np.zeros(L + 1)])
    A = np.zeros((2 * L + 2, 2 * L + 2))
    A[:L + 1, L + 1:] = np.eye(L + 1)
    for k in range(2 * L + 2):
        dz = np.zeros_like(z0)
        dz[k] = eps
        A[L + 1:, k] = (accel(z0 + dz, 0.0) - accel(z0 - dz, 0.0)) / (2 * eps)
    B = np.zeros((2 * L + 2, 1))
    B[L + 1:, 0] = (accel(z0, eps) - accel(z0, -eps)) / (2 * eps)
    return A, B


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


_CONTROLLERS: dict[type, Callable[[Any], Agent]] = {
    ClothSlide: ClothSlideController,
    SliderCrank: SliderCrankController,
    ChainSwing: ChainSwingController,
    ClothPin: ClothPinController,
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
