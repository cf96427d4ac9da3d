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

In drag mode (``drag`` given: SoftGym's low-level action, a move ``(dx, dy)`` and a grip per
gripper, :class:`envs.pick_place.PickPlaceTask`), one pick-and-place takes several steps and
the observation ends with the grippers' positions and holding flags. Each gripper again takes
observed point ``k`` with probability ``softmax(score)_k``, now scored from the point, its
target, their difference, the point's offset from the gripper (in action units, clipped at
:data:`NEAR_CLIP`) and the gripper's holding flag
(so it can learn to keep the point it holds); the move is then Gaussian around the one that
carries that point out: towards the point while the gripper holds nothing, gripping once
within ``reach`` of it, and towards the point's target while it holds, letting go there (the
scripted agents' rule, :func:`envs.pick_place.finish_action`). What is learned is which point
to work on, step by step.
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

from .train_settings import check_drag

__all__ = ["MAX_POINTS", "PointMixture", "PointerPolicy", "drag_moves"]

#: The most observed points :class:`PointerPolicy` takes.
MAX_POINTS = 512
#: Hidden widths of the network that scores each point.
SCORE_ARCH = (64, 64)
#: Drag mode: the clip (action units) of a point's offset from the gripper as the score
#: network reads it.
NEAR_CLIP = 3.0


class PointMixture(Distribution):
    """The action density of :class:`PointerPolicy`: per gripper ``g`` (``per`` action
    entries: pick x, y, place x, y; or in drag mode a move x, y and a grip), the mixture
    ``sum_k w_gk N(a_g; mu_gk, diag(s_g^2))`` with ``w_g = softmax(logits_g)`` over the
    observed points and ``mu_gk`` the action that works on point ``k`` (its pair ``(x_k, t_k)``
    in pick-and-place); the grippers independent. ``entropy`` has no closed form: None (PPO
    then uses minus the log-density of the sampled actions, as SB3 does for such
    distributions)."""

    def __init__(self, action_dim: int, per: int = 4) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.per = per
        self.grippers = action_dim // per

    def proba_distribution_net(self, latent_dim: int, log_std_init: float = 0.0
                               ) -> tuple[nn.Module, nn.Parameter]:
        """No layer of its own (the policy scores the points); the log standard deviations
        (one per action entry) start at ``log_std_init``."""
        return nn.Identity(), nn.Parameter(th.ones(self.action_dim) * log_std_init)

    def proba_distribution(self, logits: th.Tensor, means: th.Tensor, log_std: th.Tensor
                           ) -> PointMixture:
        """Set the parameters: ``logits`` (B, G, K), the components' means (B, G, K, per),
        or (B, K, per) shared by the grippers, and ``log_std`` (per G,)."""
        self.log_w = logits - th.logsumexp(logits, dim=-1, keepdim=True)
        B, G = len(logits), self.grippers
        self.means = means if means.dim() == 4 else means[:, None].expand(B, G, -1, self.per)
        self.log_std = log_std.reshape(G, 1, self.per)
        return self

    def log_prob(self, actions: th.Tensor) -> th.Tensor:
        """Log-density (B,) of actions (B, per G)."""
        a = actions.reshape(len(actions), self.grippers, 1, self.per)
        z = (a - self.means) * th.exp(-self.log_std)
        comp = (-0.5 * z * z - self.log_std).sum(-1) - 0.5 * self.per * math.log(2.0 * math.pi)
        return th.logsumexp(self.log_w + comp, dim=-1).sum(-1)

    def entropy(self) -> None:
        return None

    def _pairs(self, k: th.Tensor) -> th.Tensor:
        """The means (B, G, per) of components ``k`` (B, G)."""
        B = len(k)
        return th.gather(self.means, 2,
                         k[:, :, None, None].expand(B, self.grippers, 1, self.per))[:, :, 0]

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
                 log_std_init: float = -2.5, drag: dict[str, float] | None = None,
                 **kwargs: object) -> None:
        if type(points) is not int or not 1 <= points <= MAX_POINTS:
            raise ValueError(f"points must be a whole number in [1, {MAX_POINTS}], got "
                             f"{points!r}")
        self.drag = check_drag(drag)
        per = 4 if self.drag is None else 3
        if not (isinstance(action_space, gym.spaces.Box) and len(action_space.shape) == 1
                and action_space.shape[0] % per == 0 and action_space.shape[0] > 0):
            raise ValueError(f"PointerPolicy acts with {per} numbers per gripper "
                             f"({'pick and place points' if per == 4 else 'a move and a grip'}"
                             f"), got the action space {action_space}")
        grippers = action_space.shape[0] // per
        size = 4 * points + (0 if self.drag is None else 3 * grippers)
        shape = getattr(observation_space, "shape", None)
        if not (isinstance(observation_space, gym.spaces.Box) and shape is not None
                and len(shape) == 1 and shape[0] == size):
            raise ValueError(f"points: PointerPolicy reads an observation of {points} points "
                             f"and their {points} targets"
                             f"{'' if self.drag is None else ', then the grippers'} "
                             f"({size} numbers), got {observation_space}")
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
        per = 4 if self.drag is None else 3
        grippers = self.action_space.shape[0] // per
        self.action_dist = PointMixture(per * grippers, per)
        layers: list[nn.Module] = []
        # (pick-and-place: one network gives every gripper's score of a point from its pair;
        # drag: one score of a point for a gripper, from the pair, the gripper's offset and
        # its holding flag, the same network for each gripper)
        width = 6 if self.drag is None else 9
        for hidden in SCORE_ARCH:
            layers += [nn.Linear(width, hidden), nn.Tanh()]
            width = hidden
        layers.append(nn.Linear(width, grippers if self.drag is None else 1))
        self.score = nn.Sequential(*layers)  # (PyTorch's default initialisation)
        self.action_net = nn.Identity()  # (the mixture has no output layer)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1),
                                              **self.optimizer_kwargs)

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> PointMixture:
        K, B = self.points, len(latent_pi)
        x = latent_pi[:, :2 * K].reshape(B, K, 2)
        t = latent_pi[:, 2 * K:4 * K].reshape(B, K, 2)
        if self.drag is None:
            logits = self.score(th.cat([x, t, t - x], dim=-1)).transpose(1, 2)  # (B, G, K)
            return self.action_dist.proba_distribution(logits, th.cat([x, t], dim=-1),
                                                       self.log_std)
        G = self.action_dist.grippers
        tail = latent_pi[:, 4 * K:]
        g = tail[:, :2 * G].reshape(B, G, 1, 2)
        holding = (tail[:, 2 * G:3 * G] > 0.5).to(latent_pi.dtype).reshape(B, G, 1, 1)
        xs, ts = x[:, None].expand(B, G, K, 2), t[:, None].expand(B, G, K, 2)
        to_point, to_target = xs - g, ts - g
        # (the offset from the gripper in action units, clipped: the held point and its
        # neighbours a link apart differ by O(1) there, not by a few hundredths)
        scale = self.drag["move_scale"]
        near = (to_point * scale).clamp(-NEAR_CLIP, NEAR_CLIP)
        feats = th.cat([xs, ts, (ts - xs) * scale, near, holding.expand(B, G, K, 1)], dim=-1)
        logits = self.score(feats)[..., 0]  # (B, G, K)
        return self.action_dist.proba_distribution(
            logits, drag_moves(to_point, to_target, holding, self.drag), self.log_std)


def drag_moves(to_point: th.Tensor, to_target: th.Tensor, holding: th.Tensor,
               drag: dict[str, float]) -> th.Tensor:
    """The drag actions (..., 3) that work on each point, from its offset ``to_point`` and
    its target's ``to_target`` (..., 2) from the gripper and the gripper's holding flag
    ``holding`` (..., 1: 0 or 1), normalised view units: a gripper that holds nothing, or
    comes within ``drag["reach"]`` of the point, grips (+1; else -1) and moves towards the
    target if it grips, else towards the point; one that holds lets go (-1) once within
    ``drag["place"]`` of the target. A move is the offset times ``drag["move_scale"]`` (the
    action per normalised unit), clipped to [-1, 1]."""
    reach = (to_point * to_point).sum(-1, keepdim=True) <= drag["reach"] ** 2
    placed = (to_target * to_target).sum(-1, keepdim=True) <= drag["place"] ** 2
    held = holding > 0.5
    carrying = held | reach
    move = th.where(carrying, to_target, to_point) * drag["move_scale"]
    grip = th.where(carrying & ~(held & placed), 1.0, -1.0).to(to_point.dtype)
    return th.cat([move.clamp(-1.0, 1.0), grip], dim=-1)
