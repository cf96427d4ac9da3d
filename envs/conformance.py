"""The conformance loop: what every registered task promises, as checks any task can run.

Each check takes an env id and the keyword arguments of one configuration and raises
``AssertionError`` (or lets the env's own error through) when the promise does not hold:
Gymnasium's env checker, spaces and info, rendering, determinism, pickling, saved state, the
native vector env against Gymnasium's ``SyncVectorEnv`` of single envs (the independent
reference), the compiled bookkeeping against its numpy reference, and bad actions.
``tests/test_env_conformance.py`` runs :data:`CHECKS` on every case of every registered
declaration (:attr:`envs.task.TaskSpec.cases`); a task defined anywhere runs the same loop with
:func:`check_task` (docs/adding_a_task.md).

>>> import envs
>>> from envs.conformance import check_task
>>> check_task("SliderCrank-v0", checks=("spaces_types_and_info",))
"""

from __future__ import annotations

import contextlib
import pickle
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env

from . import _measure
from .agents import make_agent
from .task import task_spec

__all__ = ["CHECKS", "check_task"]


def rollout(env: Any, actions: Sequence[np.ndarray]) -> list[tuple]:
    """Step ``env`` through ``actions`` until an episode ends; the transitions, copied."""
    out = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append((obs.copy(), reward, terminated, truncated, dict(info)))
        if terminated or truncated:
            break
    return out


def random_actions(env: Any, steps: int, seed: int = 1, scale: float = 1.0) -> np.ndarray:
    """``steps`` uniform random actions in ``scale`` times the action Box, float32."""
    rng = np.random.default_rng(seed)
    return (scale * rng.uniform(-1, 1, (steps, *env.action_space.shape))).astype(np.float32)


def assert_same(run_a: list[tuple], run_b: list[tuple]) -> None:
    """Bit-for-bit equality of two rollouts."""
    assert len(run_a) == len(run_b), f"{len(run_a)} steps against {len(run_b)}"
    for k, ((o1, r1, te1, tr1, i1), (o2, r2, te2, tr2, i2)) in enumerate(
            zip(run_a, run_b, strict=True)):
        assert o1.tobytes() == o2.tobytes(), f"observations differ at step {k}"
        assert (r1, te1, tr1) == (r2, te2, tr2), f"reward or episode end differ at step {k}"
        assert _same_info(i1, i2), f"info differs at step {k}: {i1} against {i2}"


def _same_info(a: dict, b: dict) -> bool:
    if set(a) != set(b):
        return False
    return all(np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) else a[k] == b[k]
               for k in a)


@contextlib.contextmanager
def _raises(kind: type[BaseException], word: str) -> Iterator[None]:
    """Assert that the block raises ``kind`` with ``word`` in its message."""
    try:
        yield
    except kind as exc:
        assert word in str(exc), f"{kind.__name__} without {word!r}: {exc}"
    else:
        raise AssertionError(f"no {kind.__name__} naming {word!r}")


@contextlib.contextmanager
def _reference_path() -> Iterator[None]:
    """The env bookkeeping's numpy reference instead of its compiled path, for the block."""
    enabled = _measure.ENABLED
    _measure.ENABLED = False
    try:
        yield
    finally:
        _measure.ENABLED = enabled


def check_gymnasium(env_id: str, kwargs: dict[str, Any]) -> None:
    """Gymnasium's ``check_env`` passes, with no warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(env_id, **kwargs)
        check_env(env.unwrapped)  # also renders every declared mode through the spec
        env.close()


def check_spaces_types_and_info(env_id: str, kwargs: dict[str, Any]) -> None:
    """float32 Box spaces, actions in [-1, 1], observations inside their space and finite,
    Python scalars for reward and episode ends, and the common measures in ``info``."""
    env = gym.make(env_id, **kwargs)
    assert env.action_space.dtype == np.float32 and env.observation_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=3)
    assert obs in env.observation_space
    for a in random_actions(env, 8, seed=2):
        obs, reward, terminated, truncated, info = env.step(a)
        assert obs in env.observation_space and np.all(np.isfinite(obs))
        assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    missing = {"distance", "kinetic_energy", "constraint_residual", "is_success",
               "diverged"} - set(info)
    assert not missing, f"info lacks {sorted(missing)}"
    energy = env.unwrapped.task.system.kinetic_energy()
    assert abs(info["kinetic_energy"] - energy) <= 1e-9 * max(1.0, abs(energy))


def check_render_modes(env_id: str, kwargs: dict[str, Any]) -> None:
    """``rgb_array`` gives a 600 x 400 picture of a scene, ``human`` a window (SDL's dummy
    driver headless), and an unknown render mode a ValueError."""
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (400, 600, 3)
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5, "a blank frame"
    env.close()
    human = gym.make(env_id, render_mode="human", **kwargs)
    human.reset(seed=0)
    human.step(human.action_space.sample())
    assert human.render() is None
    human.close()
    human.close()
    with warnings.catch_warnings(), _raises(ValueError, "render_mode"):
        warnings.simplefilter("ignore")  # gymnasium warns first, then the env refuses
        gym.make(env_id, render_mode="ascii")


def check_same_seed_same_episode(env_id: str, kwargs: dict[str, Any]) -> None:
    """A seed fixes the episode bit for bit, whatever episodes came before; another seed
    starts elsewhere."""
    runs, firsts = [], []
    for _ in range(2):
        env = gym.make(env_id, **kwargs)
        env.reset(seed=11)
        env.reset(seed=5)  # an earlier episode must leave no trace
        obs, _ = env.reset(seed=11)
        firsts.append(obs)
        runs.append(rollout(env, random_actions(env, 25)))
    assert firsts[0].tobytes() == firsts[1].tobytes()
    assert_same(*runs)
    assert gym.make(env_id, **kwargs).reset(seed=12)[0].tobytes() != firsts[0].tobytes()


def check_pickled_env_continues(env_id: str, kwargs: dict[str, Any]) -> None:
    """An env pickled mid-episode continues as the original does."""
    env = gym.make(env_id, **kwargs)
    env.reset(seed=2)
    agent = make_agent("scripted", env)
    env.step(agent(env.unwrapped.task.observe()[0]))  # (an agent's first move, e.g. a spring)
    clone = pickle.loads(pickle.dumps(env))
    actions = random_actions(env, 15, seed=4)
    assert_same(rollout(env, actions), rollout(clone, actions))


def check_state_round_trip(env_id: str, kwargs: dict[str, Any]) -> None:
    """``get_state`` then ``set_state`` replays the same future, in the same env and in another
    one mid-episode; a bad state is refused naming the field."""
    env = gym.make(env_id, **kwargs).unwrapped
    agent = make_agent("scripted", env)
    obs, _ = env.reset(seed=4)
    for _ in range(6):
        obs, *_ = env.step(agent(obs))
    state = env.get_state()
    actions = random_actions(env, 12, seed=9, scale=0.5)
    ahead = rollout(env, actions)
    after = env.get_state()
    env.set_state(state)
    assert_same(ahead, rollout(env, actions))
    other = gym.make(env_id, **kwargs).unwrapped
    other.reset(seed=99)
    other.step(other.action_space.sample())
    other.set_state(state)
    assert_same(ahead, rollout(other, actions))
    assert after["t"] > state["t"] and not np.array_equal(after["x"], state["x"])
    with _raises(ValueError, "x"):
        env.set_state(dict(state, x=np.full_like(state["x"], np.nan)))
    with _raises(ValueError, "missing"):
        env.set_state({"x": state["x"]})


def check_vector_matches_single(env_id: str, kwargs: dict[str, Any]) -> None:
    """Copy i of the native vector env is a single env seeded ``seed + i``, bit for bit,
    through both kinds of episode end and the next-step autoreset (Gymnasium's
    ``SyncVectorEnv`` of single envs is the reference)."""
    N, limit = 4, 60
    native = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point",
                          max_episode_steps=limit, **kwargs)
    sync = gym.make_vec(env_id, num_envs=N, vectorization_mode="sync", max_episode_steps=limit,
                        **kwargs)
    assert native.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    o1, _ = native.reset(seed=21)
    o2, _ = sync.reset(seed=21)
    assert o1.tobytes() == o2.tobytes()
    agent = make_agent("scripted", native)
    rng = np.random.default_rng(0)
    ends = np.zeros(2, int)
    for _ in range(2 * limit + 5):
        a = agent(o1)
        a[2:] = rng.uniform(-1, 1, a[2:].shape)  # copies 2, 3 act at random
        o1, r1, te1, tr1, i1 = native.step(a)
        o2, r2, te2, tr2, i2 = sync.step(a)
        assert o1.tobytes() == o2.tobytes() and r1.tobytes() == r2.tobytes()
        assert np.array_equal(te1, te2) and np.array_equal(tr1, tr2)
        for key in ("is_success", "distance", "kinetic_energy", "diverged"):
            assert np.array_equal(i1[key], i2[key]), key
        ends += [te1.sum(), tr1.sum()]
    assert ends.sum() >= 2, "no episode ended: the autoreset was not tested"


def check_compiled_matches_reference(env_id: str, kwargs: dict[str, Any]) -> None:
    """The compiled bookkeeping of a vector env (actions checked and clipped, the measures
    with the rest test's counters, the observation) equals its numpy reference from the same
    states along a random rollout: booleans, counts and observations exactly, floats to
    1e-12. Nothing to compare when the compiled path is off (``CPARTICLES_NUMBA=0``)."""
    if not _measure.ENABLED:
        return
    N = 3
    env = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point", **kwargs)
    task = env.unwrapped.task
    env.reset(seed=3)
    # (else this would compare the reference with itself)
    assert task._compiled_post() is not None, "the compiled bookkeeping does not run"
    rng = np.random.default_rng(0)
    for _ in range(40):
        a = rng.uniform(-1.3, 1.3, (N, task.action_dim)).astype(np.float32)
        assert np.array_equal(task.check_actions(a), _on_reference(task, task.check_actions, a))
        stepped = rng.uniform(size=N) < 0.8
        hold, mean_v = task.hold.copy(), task.mean_v.copy()
        fast, fast_obs = task.measure_observe(stepped)
        fast_hold, fast_mean_v = task.hold.copy(), task.mean_v.copy()
        task.hold[:], task.mean_v[:] = hold, mean_v
        ref, ref_obs = _on_reference(task, task.measure_observe, stepped)
        assert np.array_equal(task.hold, fast_hold), "hold counts differ"
        assert np.allclose(task.mean_v, fast_mean_v, rtol=0, atol=1e-12), "moving averages"
        assert list(fast) == list(ref), f"measures {list(fast)} against {list(ref)}"
        for k in fast:
            u, w = np.asarray(fast[k]), np.asarray(ref[k])
            assert u.dtype == w.dtype and u.shape == w.shape, k
            same = (np.array_equal(u, w) if u.dtype == bool or u.dtype.kind in "iu"
                    else np.allclose(u, w, rtol=0, atol=1e-12, equal_nan=True))
            assert same, f"measure {k}: {u} against {w}"
        assert fast_obs.tobytes() == ref_obs.tobytes(), "observations differ"
        assert task.observe().tobytes() == _on_reference(task, task.observe).tobytes()
        env.step(a)
    env.close()


def _on_reference(task: Any, fn: Callable[..., Any], *args: Any) -> Any:
    with _reference_path():
        return fn(*args)


def check_bad_actions(env_id: str, kwargs: dict[str, Any]) -> None:
    """A NaN or infinite action, or one of the wrong shape, raises ValueError naming the action
    and changes nothing, in the single and the vector env; the env stays usable."""
    env = gym.make(env_id, **kwargs)
    env.reset(seed=1)
    env.step(env.action_space.sample())
    before = env.unwrapped.get_state()
    for value in (np.nan, np.inf, -np.inf):
        a = np.zeros(env.action_space.shape, np.float32)
        a[0] = value
        with _raises(ValueError, "action"):
            env.step(a)
        after = env.unwrapped.get_state()
        for key in before:
            if key != "np_random":
                assert np.array_equal(after[key], before[key]), key
    with _raises(ValueError, "action"):
        env.step(np.zeros(env.action_space.shape[0] + 1, np.float32))
    env.step(env.action_space.sample())  # still usable
    vec = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)
    vec.reset(seed=0)
    a = np.zeros(vec.action_space.shape, np.float32)
    a[1, 0] = np.nan
    x = vec.unwrapped.task.system.x.copy()
    with _raises(ValueError, "action"):
        vec.step(a)
    assert vec.unwrapped.task.system.x.tobytes() == x.tobytes()


def check_actions_clipped(env_id: str, kwargs: dict[str, Any]) -> None:
    """Actions outside the Box act as their clipped values."""
    env = gym.make(env_id, **kwargs).unwrapped
    env.reset(seed=6)
    state = env.get_state()
    big = np.resize(np.array([3.0, -7.0, 0.4, 12.0], np.float32), env.action_space.shape)
    run_big = rollout(env, [big] * 3)
    env.set_state(state)
    assert_same(run_big, rollout(env, [np.clip(big, -1, 1)] * 3))


def check_obs_modes(env_id: str, kwargs: dict[str, Any]) -> None:
    """Gymnasium's ``check_env`` passes in every ``obs_mode`` the task declares
    (``TaskSpec.obs_modes``: the pixel modes for every shipped task);
    a pixel observation is a ``uint8`` image inside its space, not blank, grey when asked; copy
    ``i`` of the native vector env observes the pixels (and state) of a single env seeded
    ``seed + i`` bit for bit, through episode ends and the next-step autoreset (Gymnasium's
    ``SyncVectorEnv`` of single envs is the reference); a bad ``obs_mode``, ``pixel_size`` or
    ``pixel_channels`` is a ValueError naming it."""
    modes = task_spec(env_id).obs_modes
    for mode in modes:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            env = gym.make(env_id, obs_mode=mode, **kwargs)
            check_env(env.unwrapped)
            env.close()
    if "pixels" not in modes:
        return
    grey = gym.make(env_id, obs_mode="pixels", pixel_size=(40, 56), pixel_channels=1, **kwargs)
    image, _ = grey.reset(seed=0)
    assert image.dtype == np.uint8 and image.shape == (40, 56, 1) and image in \
        grey.observation_space
    assert len(np.unique(image)) > 3, "a blank image"
    N, limit = 3, 12
    made = dict(obs_mode="state_pixels", max_episode_steps=limit, **kwargs)
    native = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point", **made)
    sync = gym.make_vec(env_id, num_envs=N, vectorization_mode="sync", **made)
    o1, _ = native.reset(seed=7)
    o2, _ = sync.reset(seed=7)
    rng = np.random.default_rng(1)
    ends = 0
    for step in range(2 * limit + 3):
        for key in ("state", "pixels"):
            assert o1[key].dtype == o2[key].dtype and o1[key].shape == o2[key].shape, key
            assert o1[key].tobytes() == o2[key].tobytes(), f"{key} differ at step {step}"
        a = rng.uniform(-1, 1, native.action_space.shape).astype(np.float32)
        o1, _, te, tr, _ = native.step(a)
        o2, *_ = sync.step(a)
        ends += int(np.count_nonzero(te | tr))
    assert ends >= N, "no episode ended: the autoreset was not tested"
    native.close()
    sync.close()
    for name, value in (("obs_mode", "image"), ("pixel_size", 4), ("pixel_size", (64, 2000)),
                        ("pixel_channels", 2)):
        with _raises(ValueError, name):
            gym.make(env_id, **{"obs_mode": "pixels", **kwargs, name: value})


#: Every check of the loop, by name.
CHECKS: dict[str, Callable[[str, dict[str, Any]], None]] = {
    "gymnasium": check_gymnasium,
    "spaces_types_and_info": check_spaces_types_and_info,
    "render_modes": check_render_modes,
    "same_seed_same_episode": check_same_seed_same_episode,
    "pickled_env_continues": check_pickled_env_continues,
    "state_round_trip": check_state_round_trip,
    "vector_matches_single": check_vector_matches_single,
    "compiled_matches_reference": check_compiled_matches_reference,
    "bad_actions": check_bad_actions,
    "actions_clipped": check_actions_clipped,
    "obs_modes": check_obs_modes,
}


def check_task(env_id: str, kwargs: dict[str, Any] | None = None,
               checks: Sequence[str] | None = None) -> None:
    """Run ``checks`` (default: all of :data:`CHECKS`) on ``env_id`` made with ``kwargs``
    (default: every case of its declaration, :attr:`envs.task.TaskSpec.cases`). Raises the
    first failure, an ``AssertionError`` naming the check and the case."""
    from .task import task_spec

    cases = task_spec(env_id).cases if kwargs is None else [dict(kwargs)]
    names = list(CHECKS) if checks is None else list(checks)
    unknown = set(names) - set(CHECKS)
    if unknown:
        raise ValueError(f"checks: {sorted(unknown)} are not checks of {list(CHECKS)}")
    for case in cases:
        for name in names:
            try:
                CHECKS[name](env_id, case)
            except AssertionError as exc:
                raise AssertionError(f"{env_id} {case}: {name}: {exc}") from exc
