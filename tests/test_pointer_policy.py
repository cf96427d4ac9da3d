"""The pointer policy (envs.policies): its mixture density against torch's own mixture, its
samples and deterministic action, training and rebuilding a run, and the settings it refuses."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason='needs the rl extra (pip install -e ".[rl]")')

import gymnasium as gym  # noqa: E402
import torch  # noqa: E402

from cparticles import cli  # noqa: E402
from envs.policies import PointerPolicy, PointMixture  # noqa: E402
from envs.train import evaluate, load_hyperparams, load_policy, read_run  # noqa: E402


def _policy(points: int, grippers: int, log_std_init: float = -1.0) -> PointerPolicy:
    obs = gym.spaces.Box(-10, 10, (4 * points,), np.float32)
    act = gym.spaces.Box(-1, 1, (4 * grippers,), np.float32)
    return PointerPolicy(obs, act, lambda _: 3e-4, points=points, net_arch=[32],
                         log_std_init=log_std_init)


@pytest.mark.parametrize("grippers", [1, 2])
def test_the_mixture_density_is_torchs_mixture_of_gaussians(grippers):
    """log_prob against ``torch.distributions.MixtureSameFamily`` of diagonal Gaussians at the
    points' pairs with the softmax weights (an independent implementation), per gripper, the
    grippers independent."""
    torch.manual_seed(0)
    B, K, G = 7, 5, grippers
    logits = torch.randn(B, G, K)
    means = torch.randn(B, K, 4)
    log_std = torch.randn(4 * G) * 0.3 - 1.0
    dist = PointMixture(4 * G).proba_distribution(logits, means, log_std)
    actions = torch.randn(B, 4 * G)
    want = torch.zeros(B)
    for g in range(G):
        std = log_std.reshape(G, 4)[g].exp().expand(B, K, 4)
        mix = torch.distributions.MixtureSameFamily(
            torch.distributions.Categorical(logits=logits[:, g]),
            torch.distributions.Independent(torch.distributions.Normal(means, std), 1))
        want += mix.log_prob(actions[:, 4 * g:4 * g + 4])
    assert torch.allclose(dist.log_prob(actions), want, rtol=1e-5, atol=1e-5)


def test_samples_take_each_point_as_often_as_its_weight_and_the_mode_the_likeliest():
    torch.manual_seed(1)
    K, n = 4, 20000
    means = torch.tensor([[-0.8, 0.0, 0.1, 0.1], [0.0, 0.8, 0.2, 0.2], [0.8, 0.0, 0.3, 0.3],
                          [0.0, -0.8, 0.4, 0.4]]).expand(n, K, 4)
    weights = torch.tensor([0.1, 0.2, 0.3, 0.4])
    logits = weights.log().expand(n, 1, K)
    dist = PointMixture(4).proba_distribution(logits, means, torch.full((4,), -4.0))
    a = dist.sample()
    # each sample lies at one point's pair (std e^-4 = 0.018): which one, by its pick point
    k = torch.cdist(a[:, None, :2], means[:1, :, :2].expand(n, K, 2))[:, 0].argmin(-1)
    assert torch.allclose(a[:, 2:], means[0, k, 2:], atol=0.1)
    freq = torch.bincount(k, minlength=K).double() / n
    assert torch.allclose(freq, weights.double(), atol=0.015)  # (4 sigma of a binomial)
    assert torch.equal(dist.mode(), means[:, 3])  # the likeliest point's pair, exactly


def test_each_gripper_weighs_the_points_by_one_rule_for_every_point():
    """The weights are a distribution over the points per gripper, and the same rule for
    every point: listing the points (with their targets) in another order permutes them."""
    policy = _policy(points=6, grippers=2)
    obs = torch.randn(3, 24)
    w = policy.get_distribution(obs).log_w.exp()
    assert torch.allclose(w.sum(-1), torch.ones(3, 2))
    order = torch.tensor([3, 0, 5, 1, 4, 2])
    x, t = obs[:, :12].reshape(3, 6, 2), obs[:, 12:].reshape(3, 6, 2)
    shuffled = torch.cat([x[:, order].reshape(3, 12), t[:, order].reshape(3, 12)], dim=1)
    assert torch.allclose(policy.get_distribution(shuffled).log_w.exp(), w[:, :, order],
                          atol=1e-6)
    assert policy.predict_values(obs).shape == (3, 1)


@pytest.mark.parametrize(("obs_shape", "act_shape", "points"), [
    ((40,), (4,), 12), ((41,), (4,), 10), ((40,), (6,), 10), ((40,), (4,), 0)])
def test_the_policy_refuses_spaces_it_cannot_read(obs_shape, act_shape, points):
    obs = gym.spaces.Box(-10, 10, obs_shape, np.float32)
    act = gym.spaces.Box(-1, 1, act_shape, np.float32)
    with pytest.raises(ValueError, match="points|gripper"):
        PointerPolicy(obs, act, lambda _: 3e-4, points=points)


def test_a_pointer_run_trains_and_is_rebuilt_from_its_weights(tmp_path, monkeypatch):
    """A short RopeShape run with the shipped pointer settings: config.json names the policy,
    evaluate rebuilds it from the weights alone (the same figures twice, and the same actions
    as the trained model's own policy)."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    hp = load_hyperparams("ppo", "RopeShape-v0")
    assert hp["policy"] == "PointerPolicy" and hp["normalize"] is False
    out = tmp_path / "run"
    assert cli.main(["train", "RopeShape-v0", "--seed", "3", "--out", str(out), "--timesteps",
                     "1024", "--eval-freq", "1024", "--eval-episodes", "1",
                     "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["hyperparams"]["policy"] == "PointerPolicy"
    assert not (out / "normalization.npz").exists()
    first = evaluate(out, episodes=2, seed_start=11)
    again = evaluate(out, episodes=2, seed_start=11, deterministic=False)
    assert first == evaluate(out, episodes=2, seed_start=11)
    assert again == evaluate(out, episodes=2, seed_start=11, deterministic=False)
    policy = load_policy(read_run(out), out / "policy.pt")
    assert isinstance(policy, PointerPolicy)
    obs = torch.randn(5, 40) * 0.3
    a = policy.get_distribution(obs).mode()
    # the deterministic action is an observed point and its own target, exactly
    pairs = torch.cat([obs[:, :20].reshape(5, 10, 2), obs[:, 20:].reshape(5, 10, 2)], dim=-1)
    assert all(any(torch.equal(a[b], p) for p in pairs[b]) for b in range(5))


@pytest.mark.parametrize(("argv", "says"), [
    (["--hyperparams", "normalize=true"], "normalize must be false"),
    (["--hyperparams", "policy=PointerPolicy", "normalize=false",
      'policy_kwargs={"points": 20}'], "points=20"),
    (["--algo", "sac", "--hyperparams", "policy=PointerPolicy", "normalize=false"], "ppo policy"),
    (["--hyperparams", "policy=MlpPolicy", "normalize=true", 'policy_kwargs={"points": 10}'],
     "setting of PointerPolicy"),
    (["--env-kwargs", "obs_mode=particles"], "points=10"),
    (["--hyperparams", 'policy_kwargs={"points": 10, "drag": {"move_scale": 1, "reach": 1, '
      '"place": 1}}'], "for action_mode 'drag'"),
    (["--hyperparams", 'policy_kwargs={"points": 10, "drag": {"move_scale": 1}}'],
     "dict of positive numbers"),
    (["--hyperparams", "max_episode_steps=0"], "max_episode_steps must be"),
])
def test_pointer_settings_that_cannot_work_are_refused_before_training(tmp_path, capsys,
                                                                        monkeypatch, argv, says):
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", "RopeShape-v0", "--out", str(tmp_path / "run"), "--timesteps", "64",
                  "--no-progress", *argv])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
