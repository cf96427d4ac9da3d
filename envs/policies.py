"""A policy the project adds to Stable-Baselines3's (rl extra): :class:`PointerPolicy`, for
pick-and-place tasks whose observation pairs each observed point with the point it belongs on.

A Gaussian policy chooses a pick point as a continuous number, so choosing *which* observed
point to take (the one furthest from its target, say) has to be learned as a function that
jumps from one point to another, and its small noise never tries another point: PPO with an
MLP learns to take the same rope point every step (docs/training.md). :class:`PointerPolicy`
makes the choice explicit: each gripper takes observed point ``k`` with probability
``softmax(score)_k`` (one small network scores every point from its position, its target and
their difference, the same rule for each point) and then acts around that point's own pair,
pick ``~ N(x_k, s^2)`` and place ``~ N(t_k, s^2)``. The action's density is that mixture
(:class:`PointMixture`), so PPO's probability ratios and clipping apply unchanged; the
deterministic action takes each gripper's likeliest point. The action space is unchanged (a
``Box`` of pick and place points): the policy is an inductive bias, as a CNN is for images.

The observation it reads: ``points`` 2-D points, then their ``points`` targets, nothing else
(normalised view coordinates, as the task gives them: no running normalisation in between).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import gymnasium as gym
import torch as th
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import MlpExtractor
from torch import nn

__all__ = ["MAX_POINTS", "PointMixture", "PointerPolicy"]

#: The most observed points :class:`PointerPolicy` takes.
MAX_POINTS = 512
#: Hidden widths of the network that scores each point.
SCORE_ARCH = (64, 64)


class PointMixture(Distribution):
    """The action density of :class:`PointerPolicy`: per gripper ``g`` (4 action entries:
    pick x, y, place x, y), the mixture ``sum_k w_gk N(a_g; mu_k, diag(s_g^2))`` with ``w_g =
    softmax(logits_g)`` over the observed points and ``mu_k = (x_k, t_k)``; the grippers
    independent. ``entropy`` has no closed form: None (PPO then uses minus the log-density of
    the sampled actions, as SB3 does for such distributions)."""

    def __init__(self, action_dim: int) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.grippers = action_dim // 4

    def proba_distribution_net(self, latent_dim: int, log_std_init: float = 0.0
                               ) -> tuple[nn.Module, nn.Parameter]:
        """No layer of its own (the policy scores the points); the log standard deviations
        (one per action entry) start at ``log_std_init``."""
        return nn.Identity(), nn.Parameter(th.ones(self.action_dim) * log_std_init)

    def proba_distribution(self, logits: th.Tensor, means: th.Tensor, log_std: th.Tensor
                           ) -> PointMixture:
        """Set the parameters: ``logits`` (B, G, K), the points' pairs ``means`` (B, K, 4)
        and ``log_std`` (4 G,)."""
        self.log_w = logits - th.logsumexp(logits, dim=-1, keepdim=True)
        self.means = means
        self.log_std = log_std.reshape(self.grippers, 1, 4)
        return self

    def log_prob(self, actions: th.Tensor) -> th.Tensor:
        """Log-density (B,) of actions (B, 4 G)."""
        a = actions.reshape(len(actions), self.grippers, 1, 4)
        z = (a - self.means[:, None]) * th.exp(-self.log_std)
        comp = (-0.5 * z * z - self.log_std).sum(-1) - 2.0 * math.log(2.0 * math.pi)
        return th.logsumexp(self.log_w + comp, dim=-1).sum(-1)

    def entropy(self) -> None:
        return None

    def _pairs(self, k: th.Tensor) -> th.Tensor:
        """The pairs (B, G, 4) of points ``k`` (B, G)."""
        B = len(k)
        return th.gather(self.means[:, None].expand(B, self.grippers, -1, 4), 2,
                         k[:, :, None, None].expand(B, self.grippers, 1, 4))[:, :, 0]

    def sample(self) -> th.Tensor:
        k = th.distributions.Categorical(logits=self.log_w).sample()
        mu = self._pairs(k)
        return (mu + th.randn_like(mu) * th.exp(self.log_std[:, 0])).reshape(len(mu), -1)

    def mode(self) -> th.Tensor:
        mu = self._pairs(self.log_w.argmax(-1))
        return mu.reshape(len(mu), -1)

    def actions_from_params(self, *args: th.Tensor, **kwargs: object) -> th.Tensor:
        raise NotImplementedError("PointMixture is built by PointerPolicy")

    def log_prob_from_params(self, *args: th.Tensor, **kwargs: object
                             ) -> tuple[th.Tensor, th.Tensor]:
        raise NotImplementedError("PointMixture is built by PointerPolicy")


class PointerPolicy(ActorCriticPolicy):
    """PPO's actor-critic with the pointer actor of the module docstring; the value function
    an MLP of ``net_arch`` (its ``"vf"`` part if given apart) over the whole observation.

    ``points``: how many observed points the observation holds (then as many targets);
    ``log_std_init``: the Gaussians' log standard deviation at the start (action units).
    ValueError if the observation is not a vector of ``4 points`` numbers or the action not 4
    numbers per gripper."""

    def __init__(self, observation_space: gym.spaces.Space, action_space: gym.spaces.Space,
                 lr_schedule: Callable[[float], float], points: int = 10,
                 net_arch: list[int] | dict[str, list[int]] | None = None,
                 log_std_init: float = -2.5, **kwargs: object) -> None:
        if type(points) is not int or not 1 <= points <= MAX_POINTS:
            raise ValueError(f"points must be a whole number in [1, {MAX_POINTS}], got "
                             f"{points!r}")
        shape = getattr(observation_space, "shape", None)
        if not (isinstance(observation_space, gym.spaces.Box) and shape is not None
                and len(shape) == 1 and shape[0] == 4 * points):
            raise ValueError(f"points: PointerPolicy reads an observation of {points} points "
                             f"and their {points} targets ({4 * points} numbers), got "
                             f"{observation_space}")
        if not (isinstance(action_space, gym.spaces.Box) and len(action_space.shape) == 1
                and action_space.shape[0] % 4 == 0 and action_space.shape[0] > 0):
            raise ValueError(f"PointerPolicy acts with 4 numbers per gripper (pick and place "
                             f"points), got the action space {action_space}")
        if kwargs.get("use_sde", False):
            raise ValueError("use_sde does not go with PointerPolicy (its noise is the "
                             "mixture's)")
        self.points = points
        vf = (net_arch.get("vf", [64, 64]) if isinstance(net_arch, dict)
              else [64, 64] if net_arch is None else net_arch)
        self._vf_arch = list(vf)
        super().__init__(observation_space, action_space, lr_schedule,
                         net_arch={"pi": [], "vf": list(vf)}, log_std_init=log_std_init,
                         **kwargs)

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = MlpExtractor(self.features_dim, {"pi": [], "vf": self._vf_arch},
                                          self.activation_fn, self.device)

    def _build(self, lr_schedule: Callable[[float], float]) -> None:
        super()._build(lr_schedule)
        grippers = self.action_space.shape[0] // 4
        self.action_dist = PointMixture(4 * grippers)
        layers: list[nn.Module] = []
        width = 6
        for hidden in SCORE_ARCH:
            layers += [nn.Linear(width, hidden), nn.Tanh()]
            width = hidden
        layers.append(nn.Linear(width, grippers))
        self.score = nn.Sequential(*layers)  # (PyTorch's default initialisation)
        self.action_net = nn.Identity()  # (the mixture has no output layer)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1),
                                              **self.optimizer_kwargs)

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> PointMixture:
        K, B = self.points, len(latent_pi)
        x = latent_pi[:, :2 * K].reshape(B, K, 2)
        t = latent_pi[:, 2 * K:4 * K].reshape(B, K, 2)
        logits = self.score(th.cat([x, t, t - x], dim=-1)).transpose(1, 2)  # (B, G, K)
        return self.action_dist.proba_distribution(logits, th.cat([x, t], dim=-1),
                                                   self.log_std)
