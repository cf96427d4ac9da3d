"""A normal step of every side-view environment takes the compiled paths: the physics on the
fused kernel, the step splitting, the actuators (forces, grabbed springs, drawn springs), the
measures and the observation. Each numpy reference those paths stand for is trapped here, so a
change that sends a normal step back to one of them fails (the references themselves are tied
to the compiled paths by the tests of each piece; ``CPARTICLES_NUMBA=0`` runs them).

Not covered: the table-top pick-and-place tasks, whose pick-and-place loop, measures and
observation are numpy around the compiled physics; and each task's potential, its own
arithmetic on arrays (``ShapedTask.potential``), from which the compiled pass of
``ShapedTask.reward`` makes the reward (SliderCrank's vector env computes it compiled too).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from constrained_particles import constraints, forces
from constrained_particles.system import ParticleSystem
from envs import _measure
from envs.base import ParticleTask
from envs.cloth_pin import ClothPin
from envs.pick_place import PickPlaceTask

pytestmark = pytest.mark.skipif(not _measure.ENABLED,
                                reason="the compiled paths are off (CPARTICLES_NUMBA=0)")

CASES = [(spec.id, kwargs) for spec in envs.task_specs() for kwargs in spec.cases
         if not issubclass(spec.env.task_class, PickPlaceTask)]
IDS = [f"{env_id}-{'-'.join(map(str, kwargs.values()))}" for env_id, kwargs in CASES]

#: The numpy references a normal step must not run: every force block's accumulation (the
#: reference physics and the reference step splitting), every constraint's residual (the
#: reference physics and measures), the reference measures' goal distance and rest test, and
#: ClothPin's reference drawing check, observation and plan distance.
TRAPPED = ([(cls, "accumulate") for cls in (forces.Gravity, forces.ConstantForce,
                                              forces.DampedSpring, forces.AngularSpring,
                                              forces.Drag, forces.TableFriction, forces.Wall,
                                              forces.MouseSpring)]
           + [(cls, "distance_error") for cls in (constraints.CircularWire, constraints.Rod,
                                                   constraints.LineWire,
                                                   constraints.FixedPoint)]
           + [(ParticleTask, name) for name in ("goal_distance", "advance_rest")]
           + [(ClothPin, name) for name in ("observe_reference", "plan_distance_reference",
                                             "place", "resolve")])


@pytest.fixture
def arm(monkeypatch):
    """``arm()``: from then on every reference of :data:`TRAPPED` raises and the fused physics
    must take every step (building an env may use them: ClothSlide's hanging start is found
    by minimising the energy). Returns the list of fused steps taken."""
    taken: list[bool] = []

    def trap(cls, name):
        def called(*args, **kwargs):
            raise AssertionError(f"a normal step ran the numpy reference {cls.__name__}.{name}")
        return called

    def arm_now() -> list[bool]:
        for cls, name in TRAPPED:
            monkeypatch.setattr(cls, name, trap(cls, name))
        fused = ParticleSystem._fused_step

        def fused_step(self, *args, **kwargs):
            ok = fused(self, *args, **kwargs)
            assert ok, "a normal step took the reference physics"
            taken.append(ok)
            return ok

        monkeypatch.setattr(ParticleSystem, "_fused_step", fused_step)
        return taken

    return arm_now


def _actions(space: gym.Space, rng: np.random.Generator, steps: int) -> list[np.ndarray]:
    """Uniform random actions (in ClothPin's draw mode a drawing on about half the steps)."""
    return [rng.uniform(space.low, space.high).astype(space.dtype) for _ in range(steps)]


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_a_single_env_step_takes_the_compiled_paths(env_id, kwargs, arm):
    env = gym.make(env_id, **kwargs)
    trapped = arm()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    ended = 0
    for a in _actions(env.action_space, rng, 150):
        _, reward, terminated, truncated, info = env.step(a)
        assert np.isfinite(reward)
        if terminated or truncated:
            ended += 1
            env.reset()
    assert trapped  # (the physics ran, on the fused kernel)
    if env_id == "ClothPin-v1":
        assert env.unwrapped.task.placed.max() >= 1 or ended  # (drawings were taken)


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_a_vector_env_step_takes_the_compiled_paths(env_id, kwargs, arm):
    env = gym.make_vec(env_id, num_envs=4, vectorization_mode="vector_entry_point", **kwargs)
    trapped = arm()
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    for a in _actions(env.action_space, rng, 150):
        _, reward, _, _, _ = env.step(a)
        assert np.isfinite(reward).all()
    assert trapped
