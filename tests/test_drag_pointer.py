"""The pointer policy in drag mode (envs.policies): its per-point moves against the scripted
drag agents' actions, its density against torch's own mixture, the policy's checks, and a
drag run trained and evaluated with its settings' time limit."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason='needs the rl extra (pip install -e ".[rl]")')

import gymnasium as gym  # noqa: E402
import torch  # noqa: E402

from cparticles import cli  # noqa: E402
from envs.agents import make_agent  # noqa: E402
from envs.policies import PointerPolicy, PointMixture, drag_moves  # noqa: E402
from envs.train import evaluate, load_hyperparams, load_policy, read_run  # noqa: E402
from envs.train_settings import check_drag, chosen_points  # noqa: E402

DRAG = {"move_scale": 12.0, "reach": 0.04, "place": 0.002}


def _split(obs: np.ndarray, K: int, G: int) -> tuple[torch.Tensor, ...]:
    """Offsets (B, G, K, 2) of the points and of their targets from each gripper, and the
    holding flags (B, G, 1, 1), of drag observations (B, 4 K + 3 G)."""
    o = torch.as_tensor(obs, dtype=torch.float64)
    B = len(o)
    x = o[:, :2 * K].reshape(B, 1, K, 2)
    t = o[:, 2 * K:4 * K].reshape(B, 1, K, 2)
    g = o[:, 4 * K:4 * K + 2 * G].reshape(B, G, 1, 2)
    h = (o[:, 4 * K + 2 * G:] > 0.5).double().reshape(B, G, 1, 1)
    return x - g, t - g, h


def test_each_scripted_drag_action_is_the_move_of_one_observed_point():
    """The scripted RopeShape agent's drag actions (numpy, envs.pick_place.finish_action with
    its plan) are, at every step, holding or not, exactly one of the moves the policy's
    mixture is centred on (torch, one per observed point): cloning it is a choice of point."""
    env = gym.make_vec("RopeShape-v0", num_envs=8, vectorization_mode="vector_entry_point",
                       action_mode="drag", max_episode_steps=100)
    task = env.unwrapped.task
    drag = task.drag_pointer()
    agent = make_agent("scripted", env)
    K = len(task.keypoints)
    obs, _ = env.reset(seed=5)
    gaps, held, chosen_gaps = [], [], []
    for _ in range(60):
        a = agent(obs)
        to_point, to_target, h = _split(obs, K, 1)
        moves = drag_moves(to_point, to_target, h, drag)[:, 0]  # (B, K, 3)
        gap = (moves - torch.as_tensor(a, dtype=torch.float64)[:, None]).abs().amax(-1)
        gaps.append(gap.amin(-1).numpy())
        # the imitation's label (the agent's plan, not its move) names such a point
        k = chosen_points(task, obs, agent.plan, K)[:, 0]
        chosen_gaps.append(gap[np.arange(len(k)), k].numpy())
        held.append(h.reshape(-1).numpy() > 0.5)
        obs, *_ = env.step(a)
    env.close()
    gaps, held, chosen_gaps = map(np.concatenate, (gaps, held, chosen_gaps))
    assert held.mean() > 0.2 and (~held).mean() > 0.2  # (both kinds of step were seen)
    assert gaps.max() < 1e-6
    assert np.mean(chosen_gaps < 1e-6) > 0.98


def test_a_drag_move_heads_for_the_point_then_its_target_and_grips_as_the_rule_says():
    tp = torch.tensor([[[1.0, 0.0]], [[0.01, 0.0]], [[0.5, 0.5]], [[0.5, 0.5]]])
    tt = torch.tensor([[[0.0, -0.05]], [[0.0, 0.05]], [[0.05, 0.0]], [[0.001, 0.0]]])
    h = torch.tensor([[[0.0]], [[0.0]], [[1.0]], [[1.0]]])
    m = drag_moves(tp, tt, h, DRAG)[:, 0]
    assert torch.allclose(m[0], torch.tensor([1.0, 0.0, -1.0]))  # far: towards it, clipped
    assert torch.allclose(m[1], torch.tensor([0.0, 0.6, 1.0]))  # within reach: grip, go
    assert torch.allclose(m[2], torch.tensor([0.6, 0.0, 1.0]))  # holding: to the target
    assert torch.allclose(m[3], torch.tensor([0.012, 0.0, -1.0]))  # there: let go


def test_the_drag_mixture_density_is_torchs_mixture_of_gaussians():
    """Per-gripper component means (B, G, K, 3): log_prob against MixtureSameFamily."""
    torch.manual_seed(0)
    B, K, G = 6, 5, 2
    logits, means = torch.randn(B, G, K), torch.randn(B, G, K, 3)
    log_std = torch.randn(3 * G) * 0.3 - 1.0
    dist = PointMixture(3 * G, 3).proba_distribution(logits, means, log_std)
    actions = torch.randn(B, 3 * G)
    want = torch.zeros(B)
    for g in range(G):
        std = log_std.reshape(G, 3)[g].exp().expand(B, K, 3)
        mix = torch.distributions.MixtureSameFamily(
            torch.distributions.Categorical(logits=logits[:, g]),
            torch.distributions.Independent(torch.distributions.Normal(means[:, g], std), 1))
        want += mix.log_prob(actions[:, 3 * g:3 * g + 3])
    assert torch.allclose(dist.log_prob(actions), want, rtol=1e-5, atol=1e-5)
    assert dist.sample().shape == (B, 3 * G)


@pytest.mark.parametrize("grippers", [1, 2])
def test_the_drag_policy_acts_on_one_point_per_gripper_by_one_rule(grippers):
    K, G = 6, grippers
    obs_space = gym.spaces.Box(-10, 10, (4 * K + 3 * G,), np.float32)
    act_space = gym.spaces.Box(-1, 1, (3 * G,), np.float32)
    policy = PointerPolicy(obs_space, act_space, lambda _: 3e-4, points=K, net_arch=[32],
                           drag=DRAG)
    torch.manual_seed(2)
    obs = torch.randn(4, 4 * K + 3 * G) * 0.3
    obs[:, 4 * K + 2 * G:] = (torch.rand(4, G) > 0.5).float()
    dist = policy.get_distribution(obs)
    w = dist.log_w.exp()
    assert w.shape == (4, G, K) and torch.allclose(w.sum(-1), torch.ones(4, G))
    a = dist.mode().reshape(4, G, 3).double()
    to_point, to_target, h = _split(obs.numpy(), K, G)
    moves = drag_moves(to_point, to_target, h, DRAG)
    k = dist.log_w.argmax(-1)
    for b in range(4):
        for g in range(G):
            assert torch.allclose(a[b, g], moves[b, g, k[b, g]], atol=1e-6)
    order = torch.tensor([3, 0, 5, 1, 4, 2])
    x, t = obs[:, :2 * K].reshape(4, K, 2), obs[:, 2 * K:4 * K].reshape(4, K, 2)
    shuffled = torch.cat([x[:, order].reshape(4, -1), t[:, order].reshape(4, -1),
                          obs[:, 4 * K:]], dim=1)
    assert torch.allclose(policy.get_distribution(shuffled).log_w.exp(), w[:, :, order],
                          atol=1e-6)
    with pytest.raises(ValueError, match="grippers"):
        PointerPolicy(gym.spaces.Box(-10, 10, (4 * K,), np.float32), act_space,
                      lambda _: 3e-4, points=K, drag=DRAG)


@pytest.mark.parametrize("bad", [{"move_scale": 1.0}, {**DRAG, "reach": -1.0},
                                 {**DRAG, "place": float("nan")}, [1, 2, 3],
                                 {**DRAG, "move_scale": True}])
def test_bad_drag_settings_are_refused(bad):
    with pytest.raises(ValueError, match="drag"):
        check_drag(bad)


def test_a_drag_pointer_run_trains_with_its_time_limit_and_is_rebuilt(tmp_path, monkeypatch):
    """RopeShape's drag settings: the pointer with the task's drag geometry, episodes of the
    settings' 100 steps (the registered limit is 40) in training's evaluations and in
    evaluate; the policy rebuilt from its weights."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    hp = load_hyperparams("ppo", "RopeShape-v0", "drag")
    assert hp["policy"] == "PointerPolicy" and hp["max_episode_steps"] == 100
    assert gym.spec("RopeShape-v0").max_episode_steps < 100
    out = tmp_path / "run"
    assert cli.main(["train", "RopeShape-v0", "--action-mode", "drag", "--seed", "3", "--out",
                     str(out), "--timesteps", "1024", "--eval-freq", "1024",
                     "--eval-episodes", "2", "--hyperparams", "imitate=512",
                     "imitate_updates=20", "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    env = gym.make("RopeShape-v0", action_mode="drag")
    assert config["hyperparams"]["policy_kwargs"]["drag"] == env.unwrapped.task.drag_pointer()
    env.close()
    evals = json.loads((out / "evaluations.json").read_text())
    res = evaluate(out, episodes=4, seed_start=11)
    assert res["max_episode_steps"] == 100
    # (an agent this short-trained rarely finishes: its episodes run past the registered 40)
    assert max(evals[-1]["mean_length"], res["mean_length"]) > 40
    assert isinstance(load_policy(read_run(out), out / "policy.pt"), PointerPolicy)
    # a variant whose moves the trained pointer would misjudge is refused, naming the cause
    max_move = env.unwrapped.task.max_move
    with pytest.raises(ValueError, match="drag geometry"):
        evaluate(out, episodes=1, env_kwargs={"max_move": 2 * max_move})
