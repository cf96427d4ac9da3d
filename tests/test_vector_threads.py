"""The native vector env on several threads (``num_threads``): the same results bit for bit as
on one, for every env and action mode; bad input checked before any shard steps.

How much faster threads are is a speed figure: ``cparticles bench`` measures it (section
"threads"), against two busy processes on the same machine.
"""

from __future__ import annotations

import copy
import gc
import pickle

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs.train import ENV_ACTION_MODES

CONFIGS = [(env_id, mode) for env_id in envs.ENV_IDS for mode in ENV_ACTION_MODES[env_id]]


def _vec(env_id: str, threads: int, num_envs: int = 64, **kwargs: object) -> gym.vector.VectorEnv:
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        num_threads=threads, **kwargs)


def _run(env_id: str, mode: str, threads: int, steps: int = 150
         ) -> tuple[list[np.ndarray], int]:
    """Everything 64 copies return over ``steps`` random-action steps (episodes of at most 40
    steps, so that copies end and autoreset along the way), then a masked reset; and how many
    episodes ended."""
    vec = _vec(env_id, threads, action_mode=mode, max_episode_steps=40)
    obs, info = vec.reset(seed=11)
    out = [obs, *(info[k] for k in sorted(info))]
    rng = np.random.default_rng(5)
    ended = 0
    for _ in range(steps):
        a = rng.uniform(-1.2, 1.2, vec.action_space.shape).astype(np.float32)
        obs, reward, terminated, truncated, info = vec.step(a)
        out += [obs, reward, terminated, truncated, *(info[k] for k in sorted(info))]
        ended += int(np.count_nonzero(terminated | truncated))
    mask = np.zeros(64, bool)
    mask[[3, 40]] = True  # one copy in each half
    out.append(vec.reset(seed=2, options={"reset_mask": mask})[0])
    out.append(vec.step(np.zeros(vec.action_space.shape, np.float32))[0])
    vec.close()
    return out, ended


@pytest.mark.parametrize(("env_id", "mode"), CONFIGS)
def test_threads_give_the_same_bits(env_id: str, mode: str) -> None:
    one, ended = _run(env_id, mode, 1)
    assert ended >= 64, "copies did not end: the autoreset path went untested"
    for threads in (2, 3) if mode == ENV_ACTION_MODES[env_id][0] else (2,):
        # 3 threads (shards of 22, 21 and 21 copies) in each env's first mode
        other, _ = _run(env_id, mode, threads)
        assert len(other) == len(one)
        for k, (a, b) in enumerate(zip(one, other, strict=True)):
            assert a.dtype == b.dtype and a.shape == b.shape, k
            np.testing.assert_array_equal(a, b, err_msg=f"{env_id} {mode} item {k}")


def test_shards_and_their_copies() -> None:
    vec = _vec("ClothSlide-v0", 3, num_envs=7)
    u = vec.unwrapped
    assert u.num_threads == 3 and [s.num_envs for s in u.shards] == [3, 2, 2]
    assert vec.observation_space.shape[0] == 7 and vec.action_space.shape[0] == 7
    obs, _ = vec.reset(seed=0)
    single = gym.make("ClothSlide-v0")
    for i in (0, 3, 6):  # copy i (in whichever shard) is the single env seeded 0 + i
        np.testing.assert_array_equal(obs[i], single.reset(seed=i)[0])
    # more threads than copies: one shard per copy; one copy: no shards at all
    assert _vec("ClothSlide-v0", 8, num_envs=3).unwrapped.num_threads == 3
    assert _vec("ClothSlide-v0", 4, num_envs=1).unwrapped.shards == ()
    assert "num_threads=3" in repr(u)


@pytest.mark.parametrize("threads", [0, -1, 1.5, "2", True, None])
def test_bad_thread_count_is_a_clear_error(threads: object) -> None:
    with pytest.raises(ValueError, match="num_threads"):
        _vec("SliderCrank-v0", threads, num_envs=4)


def test_a_bad_action_changes_no_shard() -> None:
    vec = _vec("SliderCrank-v0", 2, num_envs=4)
    vec.reset(seed=0)
    vec.step(np.zeros((4, 1), np.float32))
    before = [(s.task.system.x.copy(), s.task.system.v.copy(), s.steps.copy())
              for s in vec.unwrapped.shards]
    bad = np.zeros((4, 1), np.float32)
    bad[3] = np.nan  # in the second shard: the first must not have stepped either
    with pytest.raises(ValueError, match="finite"):
        vec.step(bad)
    with pytest.raises(ValueError, match="shape"):
        vec.step(np.zeros((3, 1), np.float32))
    for s, (x, v, steps) in zip(vec.unwrapped.shards, before, strict=True):
        np.testing.assert_array_equal(s.task.system.x, x)
        np.testing.assert_array_equal(s.task.system.v, v)
        np.testing.assert_array_equal(s.steps, steps)


def test_step_before_reset_and_copies_of_a_threaded_env() -> None:
    vec = _vec("ClothSlide-v0", 2, num_envs=4)
    with pytest.raises(gym.error.ResetNeeded):
        vec.step(np.zeros((4, 2), np.float32))
    vec.reset(seed=1)
    a = np.full((4, 2), 0.5, np.float32)
    vec.step(a)
    for duplicate in (copy.deepcopy, lambda env: pickle.loads(pickle.dumps(env))):
        twin = duplicate(vec)
        np.testing.assert_array_equal(twin.step(a)[0], vec.step(a)[0])
        twin.close()
    vec.close()
    vec.close()  # twice is fine
    vec.step(a)  # a closed pool is made again on the next step


def test_render_every_copy_of_a_threaded_env() -> None:
    pytest.importorskip("pygame")
    vec = _vec("ClothSlide-v0", 2, num_envs=3, render_mode="rgb_array")
    vec.reset(seed=0)
    frames = vec.render()
    assert len(frames) == 3 and all(f.shape == (400, 600, 3) for f in frames)
    # shards of 2 and 1 copies: copy 2 is the second shard's only copy, drawn as it draws it
    np.testing.assert_array_equal(frames[2], vec.unwrapped.shards[1]._frame(0))
    assert not np.array_equal(frames[1], frames[2])  # (another copy, another start)


def test_an_error_on_a_shard_thread_reaches_the_caller() -> None:
    vec = _vec("ClothSlide-v0", 2, num_envs=4)
    vec.reset(seed=1)
    u = vec.unwrapped
    a = np.full((4, 2), 0.5, np.float32)
    vec.step(a)

    def failing(env: object, part: np.ndarray) -> object:
        if env is u.shards[1]:  # (the shard stepped on the other thread)
            raise RuntimeError("shard 1 failed")
        return env._step_copies(part)

    with pytest.raises(RuntimeError, match="shard 1 failed"):
        u._map(failing, [a[sl] for sl in u._slices])
    assert np.all(np.isfinite(vec.step(a)[0]))  # the threads still serve
    threads = list(u._crew._threads)
    vec.close()
    assert threads and not any(t.is_alive() for t in threads)


def test_the_threads_of_an_env_never_closed_end_with_it() -> None:
    vec = _vec("ClothSlide-v0", 2, num_envs=4)
    vec.reset(seed=1)
    vec.step(np.zeros((4, 2), np.float32))
    threads = list(vec.unwrapped._crew._threads)
    assert threads and all(t.is_alive() for t in threads)
    del vec
    gc.collect()
    for t in threads:
        t.join(timeout=10)
    assert not any(t.is_alive() for t in threads)
