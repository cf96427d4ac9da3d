"""``obs_mode="goal"``: Gymnasium-Robotics' goal-conditioned interface on every task (see
:mod:`envs.goals`): the env checker, the reward as a function of the goals alone (what
hindsight relabelling needs), and the native vector env against single envs."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs

# (tasks whose declaration takes obs_mode='goal': a pick-and-place task's goal is no point)
IDS = [i for i in envs.ENV_IDS if "goal" in envs.task_spec(i).obs_modes]


@pytest.mark.parametrize("env_id", IDS)
def test_check_env_passes_in_goal_mode(env_id):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(env_id, obs_mode="goal")
        check_env(env.unwrapped)
    space = env.observation_space
    assert set(space.spaces) == {"observation", "achieved_goal", "desired_goal"}
    state = gym.make(env_id).observation_space.shape[0]
    assert space["observation"].shape == (state - 1,)
    k = 2 if env_id == "ChainSwing-v0" else 1
    assert space["achieved_goal"].shape == space["desired_goal"].shape == (k,)


@pytest.mark.parametrize("env_id", IDS)
def test_the_reward_is_compute_reward_of_the_goals(env_id):
    """Over random and scripted transitions (about 1,000 per task, episodes with successes
    included): the step's reward equals compute_reward of the observed goals, one by one and
    as a batch; relabelling with the achieved goal gives 0, a far goal -1. The goals follow
    the state observation: desired is the state's goal entry, achieved its tracked
    quantity."""
    env = gym.make(env_id, obs_mode="goal")
    state_env = gym.make(env_id)
    from envs.agents import make_agent

    agent = make_agent("scripted", state_env)
    rng = np.random.default_rng(0)
    achieved, desired, infos, rewards, successes = [], [], [], [], 0
    seed = 0
    while len(rewards) < 1000:
        obs, _ = env.reset(seed=seed)
        state, _ = state_env.reset(seed=seed)
        scripted = seed % 2 == 0
        seed += 1
        done = False
        while not done and len(rewards) < 1000:
            a = agent(state) if scripted else rng.uniform(-1, 1, env.action_space.shape)
            a = np.asarray(a, np.float32)
            obs, r, te, tr, info = env.step(a)
            state, *_ = state_env.step(a)
            g = envs.goals.goal_column(env.unwrapped.task)
            assert np.array_equal(obs["observation"], np.delete(state, g))
            assert obs["desired_goal"][0] == state[g]
            achieved.append(obs["achieved_goal"])
            desired.append(obs["desired_goal"])
            infos.append(dict(info))
            rewards.append(r)
            successes += info["is_success"]
            assert r == env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"],
                                                     info)
            done = te or tr
    a, d = np.array(achieved), np.array(desired)
    batch = env.unwrapped.compute_reward(a, d, infos)
    assert batch.shape == (1000,) and np.array_equal(batch, np.array(rewards))
    diverged = np.array([i["diverged"] for i in infos])
    penalty = -float(env.unwrapped.task.episode_steps) * diverged
    assert set(np.unique(batch - penalty)) <= {-1.0, 0.0}
    assert (batch == 0).any() and (batch == -1).any()
    assert np.array_equal(env.unwrapped.compute_reward(a, a, infos), penalty)
    assert np.array_equal(env.unwrapped.compute_reward(a, d + 5.0, infos), penalty - 1)
    if env_id != "ChainSwing-v0":  # (its scripted episodes run long; the others succeed)
        assert successes > 0


def test_a_diverged_step_pays_a_whole_episode():
    env = gym.make("ClothSlide-v0", obs_mode="goal").unwrapped
    g = np.zeros((3, 1), np.float32)
    r = env.compute_reward(g, g, [{"diverged": False}, {"diverged": True}, {}])
    assert r.tolist() == [0.0, -float(env.task.episode_steps), 0.0]
    with pytest.raises(ValueError, match="same shape"):
        env.compute_reward(g, g[:, :0], {})


@pytest.mark.parametrize("env_id", ["ClothSlide-v0", "ChainSwing-v0"])
def test_vector_copy_i_is_a_single_env_in_goal_mode(env_id):
    N = 3
    vec = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point",
                       obs_mode="goal", max_episode_steps=30)
    sync = gym.make_vec(env_id, num_envs=N, vectorization_mode="sync", obs_mode="goal",
                        max_episode_steps=30)
    o1, _ = vec.reset(seed=5)
    o2, _ = sync.reset(seed=5)
    rng = np.random.default_rng(1)
    for _ in range(70):
        a = rng.uniform(-1, 1, vec.action_space.shape).astype(np.float32)
        o1, r1, te1, tr1, _ = vec.step(a)
        o2, r2, te2, tr2, _ = sync.step(a)
        for key in o1:
            assert o1[key].tobytes() == o2[key].tobytes(), key
        assert r1.tobytes() == r2.tobytes()
        assert np.array_equal(te1, te2) and np.array_equal(tr1, tr2)


def test_obs_mode_is_checked():
    with pytest.raises(ValueError, match="obs_mode"):
        gym.make("ClothSlide-v0", obs_mode="pixel")
    with pytest.raises(ValueError, match="obs_mode"):
        gym.make_vec("ClothSlide-v0", num_envs=2, vectorization_mode="vector_entry_point",
                     obs_mode=None)


def test_compute_reward_only_in_goal_mode():
    """SB3's and Gymnasium-Robotics' checkers call an env with ``compute_reward`` a goal env:
    the method exists in goal mode only."""
    env = gym.make("ClothSlide-v0")
    assert not hasattr(env.unwrapped, "compute_reward")
    env.close()
    genv = gym.make("ClothSlide-v0", obs_mode="goal")
    assert hasattr(genv.unwrapped, "compute_reward")
    genv.close()
    for mode, has in (("state", False), ("goal", True)):
        vec = gym.make_vec("SliderCrank-v0", num_envs=2, vectorization_mode="vector_entry_point",
                           obs_mode=mode)
        assert hasattr(vec.unwrapped, "compute_reward") is has
        vec.close()
