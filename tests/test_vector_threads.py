"""The native vector env on several threads (``num_threads``): the same results bit for bit as
on one, for every env and action mode, with the physics really cut into ranges; bad input
changes nothing.

How much faster threads are is a speed figure: ``cparticles bench`` measures it (section
"threads"), against two busy processes on the same machine.
"""

from __future__ import annotations

import copy
import gc
import pickle
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import envs
from constrained_particles import fused, kernels, parallel
from envs.base import ParticleTask

#: Threads step the compiled kernel: with ``CPARTICLES_NUMBA=0`` a threaded env steps on one
#: thread, and only the tests of what it returns apply.
compiled = pytest.mark.skipif(not kernels.ENABLED, reason="threads step the compiled kernel")
CONFIGS = [(env_id, mode) for env_id in envs.ENV_IDS
           for mode in envs.task_spec(env_id).action_modes]


#: Envs whose physics blocks change at most steps (ClothPin draws its pins as springs): their
#: new packs are stepped whole, and cut into ranges only once a pack serves a second step.
CHURNING = {"ClothPin-v1"}


def _vec(env_id: str, threads: int, num_envs: int = 64, **kwargs: object) -> gym.vector.VectorEnv:
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        num_threads=threads, **kwargs)


def _ranges(vec: gym.vector.VectorEnv) -> int:
    """Into how many ranges the env's physics was cut at its last step (1: not cut)."""
    part = vec.unwrapped.task.system.thread_ranges()
    return 1 if part is None else len(part.packs)


def _run(env_id: str, mode: str, threads: int, steps: int = 150, limit: int = 40
         ) -> tuple[list[np.ndarray], int, tuple[int, int, int]]:
    """Everything 64 copies return over ``steps`` random-action steps (episodes of at most
    ``limit`` steps, so that copies end and autoreset along the way), then a masked reset; how many
    episodes ended; and how many of the steps' compiled physics calls ran on ranges, of how
    many, and how many measures ran on the ranges."""
    vec = _vec(env_id, threads, action_mode=mode, max_episode_steps=limit)
    obs, info = vec.reset(seed=11)
    out = [obs, *(info[k] for k in sorted(info))]
    rng = np.random.default_rng(5)
    ended = 0
    calls = {"run": 0, "ranges": 0, "measures": 0}
    real_run, real_ranges = fused.run, fused._run_ranges
    real_measures = ParticleTask._measures_ranges

    def counted(name: str, real: Any) -> Any:
        def call(*args: object, **kwargs: object) -> object:
            result = real(*args, **kwargs)
            calls[name] += result is not False  # (measures on the ranges return False
            return result  # where they did not run there)
        return call

    fused.run, fused._run_ranges = counted("run", real_run), counted("ranges", real_ranges)
    ParticleTask._measures_ranges = counted("measures", real_measures)
    try:
        for _ in range(steps):
            a = rng.uniform(-1.2, 1.2, vec.action_space.shape).astype(np.float32)
            obs, reward, terminated, truncated, info = vec.step(a)
            out += [obs, reward, terminated, truncated, *(info[k] for k in sorted(info))]
            ended += int(np.count_nonzero(terminated | truncated))
        if env_id not in CHURNING:
            assert _ranges(vec) == (min(threads, 3) if kernels.ENABLED else 1)
    finally:
        fused.run, fused._run_ranges = real_run, real_ranges
        ParticleTask._measures_ranges = real_measures
    mask = np.zeros(64, bool)
    mask[[3, 40]] = True  # one copy in each half
    out.append(vec.reset(seed=2, options={"reset_mask": mask})[0])
    out.append(vec.step(np.zeros(vec.action_space.shape, np.float32))[0])
    vec.close()
    return out, ended, (calls["ranges"], calls["run"], calls["measures"])


@pytest.fixture
def small_ranges(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ranges of any size (64 SliderCrank copies hold 128 particles: three ranges of them
    would be below the size at which threads gain)."""
    monkeypatch.setattr(parallel, "MIN_PARTICLES", 1)


@pytest.mark.parametrize(("env_id", "mode"), CONFIGS)
def test_threads_give_the_same_bits(env_id: str, mode: str, small_ranges: None) -> None:
    # (a task whose episodes are short by declaration, one pick-and-place per step, each step
    # hundreds of physics steps: 12 steps see every copy end twice at a 5-step limit)
    steps, limit = (150, 40) if envs.task_spec(env_id).max_episode_steps >= 150 else (12, 5)
    one, ended, _ = _run(env_id, mode, 1, steps, limit)
    assert ended >= 64, "copies did not end: the autoreset path went untested"
    for threads in (2, 3) if mode == envs.task_spec(env_id).default_mode else (2,):
        # 3 threads (ranges of 22, 21 and 21 copies) in each env's first mode
        other, _, (on_ranges, calls, measures) = _run(env_id, mode, threads, steps, limit)
        # (every compiled physics call ran on the ranges: none fell back to one thread; the
        # tasks whose measures are the generic ones measured on the ranges too)
        if kernels.ENABLED and env_id in CHURNING:
            assert calls >= 100 and 0 < on_ranges < calls, (on_ranges, calls)
        elif kernels.ENABLED:  # (a compiled physics call at least every step but those in
            # which every copy autoresets, at most one per episode limit)
            assert calls >= steps - steps // limit and on_ranges == calls, (on_ranges, calls)
            if env_id in ("ClothSlide-v0", "ChainSwing-v0"):
                assert measures >= 100, measures
        assert len(other) == len(one)
        for k, (a, b) in enumerate(zip(one, other, strict=True)):
            assert a.dtype == b.dtype and a.shape == b.shape, k
            np.testing.assert_array_equal(a, b, err_msg=f"{env_id} {mode} item {k}")


@compiled
def test_ranges_hold_whole_copies(small_ranges: None) -> None:
    vec = _vec("ClothSlide-v0", 3, num_envs=7)
    u = vec.unwrapped
    assert u.num_threads == 3 and u.task.system.threads == 3
    assert vec.observation_space.shape[0] == 7 and vec.action_space.shape[0] == 7
    obs, _ = vec.reset(seed=0)
    vec.step(np.zeros((7, 2), np.float32))
    held = u.task.system._partition
    n = u.task.n
    assert held.valid and [(hi - lo) // n for lo, hi in held.spans] == [2, 3, 2]
    assert all(lo % n == 0 and hi % n == 0 for lo, hi in held.spans)
    single = gym.make("ClothSlide-v0")
    for i in (0, 3, 6):  # copy i (in whichever range) is the single env seeded 0 + i
        np.testing.assert_array_equal(obs[i], single.reset(seed=i)[0])
    assert "num_threads=3" in repr(u)
    # one copy: nothing to cut between (the cloth is one piece), stepped on one thread
    one = _vec("ClothSlide-v0", 4, num_envs=1)
    one.reset(seed=0)
    one.step(np.zeros((1, 2), np.float32))
    assert _ranges(one) == 1


def test_too_few_particles_stay_on_one_thread() -> None:
    """Below MIN_PARTICLES particles a range, a step is not cut (the threads would cost more
    than they save)."""
    vec = _vec("SliderCrank-v0", 2, num_envs=8)  # 16 particles
    vec.reset(seed=0)
    vec.step(np.zeros((8, 1), np.float32))
    assert _ranges(vec) == 1
    assert 16 < 2 * parallel.MIN_PARTICLES


@pytest.mark.parametrize("threads", [0, -1, 1.5, "2", True, None])
def test_bad_thread_count_is_a_clear_error(threads: object) -> None:
    with pytest.raises(ValueError, match="num_threads"):
        _vec("SliderCrank-v0", threads, num_envs=4)


def test_a_bad_action_changes_nothing(small_ranges: None) -> None:
    vec = _vec("SliderCrank-v0", 2, num_envs=4)
    vec.reset(seed=0)
    vec.step(np.zeros((4, 1), np.float32))
    task = vec.unwrapped.task
    before = (task.system.x.copy(), task.system.v.copy(), vec.unwrapped.steps.copy())
    bad = np.zeros((4, 1), np.float32)
    bad[3] = np.nan  # in the second range
    with pytest.raises(ValueError, match="finite"):
        vec.step(bad)
    with pytest.raises(ValueError, match="shape"):
        vec.step(np.zeros((3, 1), np.float32))
    after = (task.system.x, task.system.v, vec.unwrapped.steps)
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)


@compiled
def test_step_before_reset_and_copies_of_a_threaded_env(small_ranges: None) -> None:
    vec = _vec("ClothSlide-v0", 2, num_envs=4)
    with pytest.raises(gym.error.ResetNeeded):
        vec.step(np.zeros((4, 2), np.float32))
    vec.reset(seed=1)
    a = np.full((4, 2), 0.5, np.float32)
    vec.step(a)
    for duplicate in (copy.deepcopy, lambda env: pickle.loads(pickle.dumps(env))):
        twin = duplicate(vec)
        np.testing.assert_array_equal(twin.step(a)[0], vec.step(a)[0])
        assert _ranges(twin) == 2  # (a copy cuts its own system, with threads of its own)
        assert twin.unwrapped.task.system._partition is not vec.unwrapped.task.system._partition
        twin.close()
    vec.close()
    vec.close()  # twice is fine
    vec.step(a)  # closed threads are started again on the next step
    assert _ranges(vec) == 2


def test_render_every_copy_of_a_threaded_env(small_ranges: None) -> None:
    pytest.importorskip("pygame")
    frames = []
    for threads in (1, 2):
        vec = _vec("ClothSlide-v0", threads, num_envs=3, render_mode="rgb_array")
        vec.reset(seed=0)
        vec.step(np.full((3, 2), 0.5, np.float32))
        frames.append(vec.render())
        vec.close()
    assert len(frames[1]) == 3 and all(f.shape == (400, 600, 3) for f in frames[1])
    for a, b in zip(*frames, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(frames[1][1], frames[1][2])  # (another copy, another start)


@compiled
def test_the_threads_of_an_env_never_closed_end_with_it(small_ranges: None) -> None:
    vec = _vec("ClothSlide-v0", 2, num_envs=4)
    vec.reset(seed=1)
    vec.step(np.zeros((4, 2), np.float32))
    threads = list(vec.unwrapped.task.system._partition._box[0]._threads)
    assert threads and all(t.is_alive() for t in threads)
    del vec
    gc.collect()
    for t in threads:
        t.join(timeout=10)
    assert not any(t.is_alive() for t in threads)


def _play(vec: gym.vector.VectorEnv, actions: np.ndarray) -> np.ndarray:
    """Observations of an episode start (seed 3) and ``actions``, stacked."""
    rows = [vec.reset(seed=3)[0]]
    rows += [vec.step(a)[0] for a in actions]
    return np.stack(rows)


def test_a_child_forked_while_a_parent_thread_steps_steps_its_env(small_ranges: None) -> None:
    """A child forked while a thread of the parent is inside a step of a threaded vector env
    inherits the system's step lock held (by a thread the child does not have): the child
    still steps its copy, with the results of a fresh env."""
    import os
    import threading
    import time
    import warnings

    actions = np.random.default_rng(0).uniform(-1, 1, (12, 8, 2)).astype(np.float32)
    expected = _play(_vec("ClothSlide-v0", 2, num_envs=8), actions)
    vec = _vec("ClothSlide-v0", 2, num_envs=8)
    vec.reset(seed=0)
    lock = vec.unwrapped.task.system._step_lock()
    stop = threading.Event()

    def stepper() -> None:
        while not stop.is_set():
            vec.step(actions[0])

    thread = threading.Thread(target=stepper, daemon=True)
    thread.start()
    seen_held = 0
    try:
        for _ in range(10):
            deadline = time.monotonic() + 10
            while not lock.locked() and time.monotonic() < deadline:
                pass
            read, write = os.pipe()
            with warnings.catch_warnings():  # (Python 3.12+: forking a process with threads)
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
            if pid == 0:  # the child: one thread, the parent's env in mid-step
                code = 1
                try:
                    held = lock.locked()  # (the parent's lock, as it was at the fork)
                    os.write(write, pickle.dumps((held, _play(vec, actions))))
                    code = 0
                except BaseException as exc:
                    os.write(write, pickle.dumps((None, repr(exc))))
                finally:
                    os._exit(code)
            os.close(write)
            with os.fdopen(read, "rb") as f:
                data = f.read()
            _, status = os.waitpid(pid, 0)
            held, got = pickle.loads(data)
            assert os.waitstatus_to_exitcode(status) == 0, got
            np.testing.assert_array_equal(got, expected)
            seen_held += bool(held)
            if seen_held >= 3:
                break
    finally:
        stop.set()
        thread.join(timeout=60)
        vec.close()
    assert seen_held >= 1, "no fork landed inside a step: the case went untested"
