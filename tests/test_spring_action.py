"""The spring action: the nearest particle is grabbed and pulled toward a target relative to it,
with at most ``max_force`` newtons on a particle at rest (the force mode's bound).

The expected forces are computed here from the action's definition (the grab point's nearest
particle by brute force, the pull scaled onto the unit disc, Witkin's mouse-spring formula
``f = ks (target - x_p) - kd v_p``), not read from the env's code.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the ids)
from envs import _measure

SPRING_ENVS = ["ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0"]


def spring_force(task, i: int) -> np.ndarray:
    """The mouse spring's force (N) on copy ``i``'s grabbed particle, now."""
    act = task.actuator
    p = act.particle[i]
    return act.ks[i] * (act.anchor[i] - task.system.x[p]) - act.kd[i] * task.system.v[p]


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("env_id", SPRING_ENVS)
def test_pull_is_relative_bounded_and_grabs_the_nearest_particle(monkeypatch, env_id, compiled):
    if compiled and not _measure.ENABLED:
        pytest.skip("compiled bookkeeping disabled (CPARTICLES_NUMBA=0)")
    monkeypatch.setattr(_measure, "ENABLED", compiled)
    env = gym.make(env_id, action_mode="spring").unwrapped
    task = env.task
    env.reset(seed=0)
    task.system.v[:] = 0.0  # a particle at rest: the pull is the spring's alone
    rng = np.random.default_rng(1)
    for _ in range(40):
        a = rng.uniform(-1, 1, 4)
        task.apply(task.check_actions(a, single=True))
        grab = task.center + task.half * a[:2]
        d = np.linalg.norm(task.system.x - grab, axis=1)
        assert task.actuator.active[0]  # the default grab_radius never misses
        assert d[task.actuator.particle[0]] == d.min()
        pull = a[2:] / max(1.0, np.hypot(*a[2:]))
        np.testing.assert_allclose(spring_force(task, 0), task.max_force * pull, rtol=0,
                                   atol=1e-12)
    # the largest pull, in every direction, is max_force
    for angle in np.linspace(0, 2 * np.pi, 9):
        a = np.array([0.0, 0.0, 2 * np.cos(angle), 2 * np.sin(angle)])  # clipped, then scaled
        task.apply(task.check_actions(a, single=True))
        assert np.linalg.norm(spring_force(task, 0)) == pytest.approx(task.max_force,
                                                                      rel=1e-12)


@pytest.mark.parametrize("env_id", SPRING_ENVS)
def test_random_spring_actions_pull_like_the_force_mode(env_id):
    """Under uniform random actions the pull at the start of a step stays within ``max_force``
    plus the spring's damping of the particle's own motion."""
    env = gym.make(env_id, action_mode="spring").unwrapped
    task = env.task
    env.reset(seed=2)
    rng = np.random.default_rng(3)
    for _ in range(60):
        a = rng.uniform(-1, 1, 4).astype(np.float32)
        task.apply(task.check_actions(a, single=True))
        p = task.actuator.particle[0]
        damping = task.mouse_kd * np.linalg.norm(task.system.v[p])
        assert np.linalg.norm(spring_force(task, 0)) <= task.max_force + damping + 1e-12
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()


def test_a_finite_grab_radius_can_miss():
    env = gym.make("ClothSlide-v0", action_mode="spring", grab_radius=0.2).unwrapped
    env.reset(seed=0)
    env.task.apply(env.task.check_actions(np.array([-1.0, -1.0, 1.0, 0.0]), single=True))
    assert not env.task.actuator.active[0]  # the view's corner is far from the cloth


def test_grab_radius_must_be_positive_or_inf():
    for bad in (0.0, -1.0, np.nan, "far"):
        with pytest.raises(ValueError, match="grab_radius"):
            gym.make("ClothSlide-v0", action_mode="spring", grab_radius=bad)
    assert gym.make("ClothSlide-v0", grab_radius=np.inf).unwrapped.task.grab_radius == np.inf
