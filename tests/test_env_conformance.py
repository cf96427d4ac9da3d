"""What every registered environment promises, checked on every id and action mode in
``envs.ENV_IDS`` (and ChainSwing's swing-up target): Gymnasium's env checker, spaces, rendering,
determinism, saved state, pickling, the native vector env against gymnasium's SyncVectorEnv of
single envs (the independent reference), and bad actions.

Each task's own rules (its reward, goals, walls, spring drawing, scripted agents) are tested in
its own file: tests/test_cloth_slide_slider_crank.py and tests/test_chain_swing_cloth_pin.py.
"""

from __future__ import annotations

import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs.agents import make_agent
from envs.train import ENV_ACTION_MODES

CASES = [(env_id, {"action_mode": mode}) for env_id in envs.ENV_IDS
         for mode in ENV_ACTION_MODES[env_id]] + [("ChainSwing-v0", {"target": "swingup"})]
IDS = [f"{env_id}-{'-'.join(map(str, kwargs.values()))}" for env_id, kwargs in CASES]


def rollout(env: gym.Env, actions: np.ndarray) -> list[tuple]:
    """Step ``env`` through ``actions`` until an episode ends; the transitions, copied."""
    out = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append((obs.copy(), reward, terminated, truncated, dict(info)))
        if terminated or truncated:
            break
    return out


def random_actions(env: gym.Env, steps: int, seed: int = 1, scale: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (scale * rng.uniform(-1, 1, (steps, *env.action_space.shape))).astype(np.float32)


def assert_same(run_a: list[tuple], run_b: list[tuple]) -> None:
    """Bit-for-bit equality of two rollouts."""
    assert len(run_a) == len(run_b)
    for (o1, r1, te1, tr1, i1), (o2, r2, te2, tr2, i2) in zip(run_a, run_b, strict=True):
        assert o1.tobytes() == o2.tobytes()
        assert (r1, te1, tr1) == (r2, te2, tr2)
        assert i1 == i2


def test_every_id_is_registered_with_a_vector_entry_point():
    assert set(envs.ENV_IDS) == {"ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0",
                                 "ClothPin-v1"}
    assert set(ENV_ACTION_MODES) == set(envs.ENV_IDS)
    for env_id in envs.ENV_IDS:
        spec = gym.spec(env_id)
        assert spec.vector_entry_point is not None and spec.max_episode_steps == 200


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_check_env_passes_without_warnings(env_id, kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(env_id, **kwargs)
        check_env(env.unwrapped)  # also renders every declared mode through the spec
        env.close()


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_spaces_types_and_info(env_id, kwargs):
    env = gym.make(env_id, **kwargs)
    assert env.action_space.dtype == np.float32 and env.observation_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=3)
    assert obs in env.observation_space
    for a in random_actions(env, 8, seed=2):
        obs, reward, terminated, truncated, info = env.step(a)
        assert obs in env.observation_space and np.all(np.isfinite(obs))
        assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    assert {"distance", "kinetic_energy", "constraint_residual", "is_success",
            "diverged"} <= set(info)
    assert info["kinetic_energy"] == pytest.approx(env.unwrapped.task.system.kinetic_energy())


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_render_modes(env_id, kwargs):
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (400, 600, 3)
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5  # a scene, not a blank frame
    env.close()
    human = gym.make(env_id, render_mode="human", **kwargs)  # SDL dummy driver in tests
    human.reset(seed=0)
    human.step(human.action_space.sample())
    assert human.render() is None
    human.close()
    human.close()
    with warnings.catch_warnings(), pytest.raises(ValueError, match="render_mode"):
        warnings.simplefilter("ignore")  # gymnasium warns first, then the env refuses
        gym.make(env_id, render_mode="ascii")


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_same_seed_same_episode_bit_for_bit(env_id, kwargs):
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


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_pickled_env_continues_identically(env_id, kwargs):
    env = gym.make(env_id, **kwargs)
    env.reset(seed=2)
    agent = make_agent("scripted", env)
    env.step(agent(env.unwrapped.task.observe()[0]))  # (ClothPin's agent draws its spring)
    clone = pickle.loads(pickle.dumps(env))
    actions = random_actions(env, 15, seed=4)
    assert_same(rollout(env, actions), rollout(clone, actions))


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_get_state_set_state_round_trip(env_id, kwargs):
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
    # and in another env instance, in the middle of a different episode
    other = gym.make(env_id, **kwargs).unwrapped
    other.reset(seed=99)
    other.step(other.action_space.sample())
    other.set_state(state)
    assert_same(ahead, rollout(other, actions))
    assert after["t"] > state["t"] and not np.array_equal(after["x"], state["x"])
    with pytest.raises(ValueError, match="x"):
        env.set_state(dict(state, x=np.full_like(state["x"], np.nan)))
    with pytest.raises(ValueError, match="missing"):
        env.set_state({"x": state["x"]})


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_native_vector_env_matches_single_envs(env_id, kwargs):
    """Copy i of the native vector env is a single env seeded ``seed + i``, bit for bit (each
    copy's constraints are solved per connected component, as they would be alone), through
    both kinds of episode end and the next-step autoreset."""
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
        np.testing.assert_array_equal(te1, te2)
        np.testing.assert_array_equal(tr1, tr2)
        for key in ("is_success", "distance", "kinetic_energy", "diverged"):
            np.testing.assert_array_equal(i1[key], i2[key], err_msg=key)
        ends += [te1.sum(), tr1.sum()]
    assert ends.sum() >= 2  # episodes ended, then autoreset, along the way


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_nonfinite_action_raises_and_leaves_state_untouched(env_id, kwargs):
    env = gym.make(env_id, **kwargs)
    env.reset(seed=1)
    env.step(env.action_space.sample())
    before = env.unwrapped.get_state()
    for value in (np.nan, np.inf, -np.inf):
        a = np.zeros(env.action_space.shape, np.float32)
        a[0] = value
        with pytest.raises(ValueError, match="action"):
            env.step(a)
        after = env.unwrapped.get_state()
        for key in before:
            if key != "np_random":
                assert np.array_equal(after[key], before[key]), key
    with pytest.raises(ValueError, match="action"):
        env.step(np.zeros(env.action_space.shape[0] + 1, np.float32))
    env.step(env.action_space.sample())  # still usable
    vec = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)
    vec.reset(seed=0)
    a = np.zeros(vec.action_space.shape, np.float32)
    a[1, 0] = np.nan
    x = vec.unwrapped.task.system.x.copy()
    with pytest.raises(ValueError, match="action"):
        vec.step(a)
    assert vec.unwrapped.task.system.x.tobytes() == x.tobytes()


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_actions_outside_the_box_are_clipped(env_id, kwargs):
    env = gym.make(env_id, **kwargs).unwrapped
    env.reset(seed=6)
    state = env.get_state()
    big = np.resize(np.array([3.0, -7.0, 0.4, 12.0], np.float32), env.action_space.shape)
    run_big = rollout(env, [big] * 3)
    env.set_state(state)
    assert_same(run_big, rollout(env, [np.clip(big, -1, 1)] * 3))
