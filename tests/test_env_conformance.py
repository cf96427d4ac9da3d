"""What every registered environment promises: the conformance loop of
:mod:`envs.conformance` (Gymnasium's env checker, spaces, rendering, determinism, saved state,
pickling, the native vector env against gymnasium's SyncVectorEnv of single envs, the compiled
bookkeeping against its numpy reference, bad actions) on every case of every registered task's
declaration (each action mode, and variants such as ChainSwing's swing-up).

Each task's own rules (its reward, goals, walls, spring drawing, scripted agents) are tested in
its own file: tests/test_cloth_slide_slider_crank.py and tests/test_chain_swing_cloth_pin.py;
tests/test_task_protocol.py defines a task in one file and runs this same loop on it.
"""

from __future__ import annotations

import gymnasium as gym
import pytest

import envs
from constrained_particles import kernels
from envs.conformance import CHECKS
from envs.pick_place import PickPlaceTask

CASES = [(spec.id, kwargs) for spec in envs.task_specs() for kwargs in spec.cases]
IDS = [f"{env_id}-{'-'.join(map(str, kwargs.values()))}" for env_id, kwargs in CASES]


def test_every_id_is_registered_with_a_vector_entry_point():
    assert set(envs.ENV_IDS) == {"ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0",
                                 "ClothPin-v1", "RopeStraighten-v0", "ClothFlatten-v0",
                                 "ClothFold-v0", "RopeShape-v0"}
    assert [s.id for s in envs.task_specs()][:len(envs.ENV_IDS)] == list(envs.ENV_IDS)
    # (pick-and-place episodes are short: one step is a whole pick-and-place)
    lengths = {"RopeStraighten-v0": 30, "ClothFlatten-v0": 50, "ClothFold-v0": 20,
               "RopeShape-v0": 40}
    for spec in envs.task_specs():
        registered = gym.spec(spec.id)
        assert registered.vector_entry_point is not None
        assert registered.max_episode_steps == spec.max_episode_steps == lengths.get(spec.id,
                                                                                      200)


def test_the_loop_covers_each_action_mode_and_the_swing_up():
    assert ("ChainSwing-v0", {"target": "swingup"}) in CASES
    assert ("ClothPin-v1", {"action_mode": "draw"}) in CASES
    assert sum(env_id == "ClothSlide-v0" for env_id, _ in CASES) == 2


def _numpy_pick_and_place(env_id: str) -> bool:
    """A pick-and-place task on the numpy reference path (``CPARTICLES_NUMBA=0``): one env step
    is hundreds of physics steps, seconds each in numpy, and the loop takes minutes per case."""
    return (not kernels.ENABLED
            and issubclass(envs.task_spec(env_id).env.task_class, PickPlaceTask))


@pytest.mark.parametrize("check", list(CHECKS))
@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_conformance(env_id, kwargs, check):
    if _numpy_pick_and_place(env_id):
        pytest.skip("pick-and-place tasks run the loop on the compiled path only (minutes per "
                    "case in numpy); tests/test_tabletop.py covers them")
    CHECKS[check](env_id, kwargs)
