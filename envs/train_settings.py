"""The training settings ``cparticles train`` checks and applies beside Stable-Baselines3's
own: the policies a run may name and their keyword arguments, linear schedules
(``"lin_<value>"``), the ceiling on a PPO policy's noise (``log_std_final``), frame stacking,
which policy suits which observation (images: ``CnnPolicy``), and a start from a clone of the
task's scripted agent (``imitate``).

Requires the ``rl`` extra only where a function says so (:func:`std_ceiling`,
:func:`imitate_scripted`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

if TYPE_CHECKING:  # (the rl extra)
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    from .pick_place import DragPlan, PickPlaceTask

#: Most scripted-agent env steps ``imitate`` may clone.
MAX_IMITATE = 10_000_000
#: How :func:`imitate_scripted` clones: env copies that collect the scripted agent's steps,
#: the Gaussian noise (action units) on the actions they execute (so that the clone also sees
#: states a little off the agent's path; it learns the agent's own actions; the setting
#: ``imitate_noise`` overrides it), the minibatch and the Adam updates of the policy's fit
#: (``imitate_updates`` overrides them) and then of its value function (learning rate 1e-3),
#: and the clone's own env steps whose discounted returns the value function is fit to.
IMITATE_COPIES, IMITATE_NOISE, IMITATE_BATCH = 16, 0.1, 512
IMITATE_POLICY_UPDATES, IMITATE_VALUE_UPDATES, IMITATE_VALUE_STEPS = 15_000, 5_000, 20_000
#: First seed of the episodes :func:`imitate_scripted` plays (``+ 100 * seed`` per training
#: seed): apart from the periodic evaluations (1,000,000) and the held-out ones (2,000,000).
IMITATE_SEED_START = 4_000_000
#: Most frames ``frame_stack`` may stack (rl-baselines3-zoo's key: SB3's ``VecFrameStack``).
MAX_FRAME_STACK = 16


#: Policies a run directory may name: Stable-Baselines3's aliases (``CnnPolicy``: Nature CNN
#: features, then ``net_arch``, for the image observations of ``obs_mode="pixels"``) and
#: the project's ``PointerPolicy`` (:class:`envs.policies.PointerPolicy`, PPO: each gripper
#: takes one of the observed points and places it near its target).
POLICIES = ("MlpPolicy", "CnnPolicy", "PointerPolicy")
#: Keys of ``policy_kwargs`` a run directory may give, and the widest layer it may ask for.
POLICY_KWARGS = ("net_arch", "log_std_init", "use_sde", "ortho_init", "points", "drag")
#: Keys of :data:`POLICY_KWARGS` only PPO's policy takes (SB3's SAC policy has no such argument).
PPO_POLICY_KWARGS = ("ortho_init",)
MAX_LAYER = 4096
#: Settings that may also be given as a schedule, ``"lin_<value>"``: ``value`` at the start,
#: decayed linearly to 0 at the end of the budget (rl-baselines3-zoo's notation).
SCHEDULE_KEYS = ("learning_rate", "clip_range")


class LinearSchedule:
    """``value * progress_remaining``: Stable-Baselines3 calls a schedule with the fraction of
    the budget left (1 at the start, 0 at the end), so the setting decays linearly to 0."""

    def __init__(self, value: float) -> None:
        self.value = value

    def __call__(self, progress_remaining: float) -> float:
        return self.value * progress_remaining

    def __repr__(self) -> str:
        return f"lin_{self.value:g}"


#: A setting's value as ``config.json`` holds it (JSON data).
Setting = str | int | float | bool | list | dict | None


def schedule(key: str, value: Setting) -> Setting | LinearSchedule:
    """The value of setting ``key`` for Stable-Baselines3: ``"lin_<value>"`` (a key of
    :data:`SCHEDULE_KEYS`, a finite ``value`` > 0) as a :class:`LinearSchedule`, anything else
    unchanged; ValueError naming the key for any other string there."""
    if key not in SCHEDULE_KEYS or not isinstance(value, str):
        return value
    try:
        start = float(value[4:]) if value.startswith("lin_") else float("nan")
    except ValueError:
        start = float("nan")
    if not (np.isfinite(start) and start > 0):
        raise ValueError(f"hyperparams: {key} must be a number or 'lin_<value>' (a linear "
                         f"decay from value > 0 to 0 over the budget), got {value!r}")
    return LinearSchedule(start)


#: Ended training episodes over which ``explore_until_success`` measures the success rate.
EXPLORE_WINDOW = 100


def std_ceiling(start: float, final: float, timesteps: int,
                hold_until: float = 0.0) -> BaseCallback:
    """A callback that caps a PPO policy's log standard deviations, before each rollout and at
    the end, at a ceiling lowered linearly from ``start`` (no cap at step 0) to ``final`` at
    ``timesteps`` (``log_std_final``): the policy explores as widely as ``log_std_init`` lets
    it early and acts with at most ``exp(final)`` of noise at the end, whatever the gradient
    did with it.

    With ``hold_until`` > 0 (``explore_until_success``, a success rate), the noise is first
    held up: until at least that fraction of the last :data:`EXPLORE_WINDOW` episodes of the
    rollouts ended in success (``info["is_success"]``; the window full), the log standard
    deviations are kept at least ``start`` and not capped; from the rollout after that, at
    step ``t0``, the ceiling falls linearly from ``start`` to ``final`` over the rest of the
    budget (``t0`` to ``timesteps``). A rate, not a first success: the policy's noise alone
    wins a lucky episode now and then. A run that never gets there explores to the end instead
    of settling, through a shrinking noise, on whatever it did before finding a way."""
    from collections import deque

    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    class StdCeiling(BaseCallback):
        #: the step from which the ceiling falls (None: held, the rate not reached yet)
        since: int | None = None if hold_until > 0 else 0

        def __init__(self) -> None:
            super().__init__()
            #: whether each of the last EXPLORE_WINDOW ended episodes succeeded
            self.recent: deque[bool] = deque(maxlen=EXPLORE_WINDOW)

        def _on_rollout_start(self) -> None:
            log_std = self.model.policy.log_std
            with torch.no_grad():
                if self.since is None:
                    log_std.clamp_(min=start)
                    return
                span = max(1, timesteps - self.since)
                done = min(1.0, max(0.0, (self.model.num_timesteps - self.since) / span))
                log_std.clamp_(max=start + (final - start) * done)

        def _on_training_end(self) -> None:
            with torch.no_grad():  # (the final policy: at most exp(final), whatever happened)
                self.model.policy.log_std.clamp_(max=final)

        def _on_step(self) -> bool:
            if self.since is None:
                dones, infos = self.locals.get("dones"), self.locals.get("infos", ())
                if dones is None:
                    return True
                self.recent.extend(bool(i.get("is_success", False))
                                   for d, i in zip(dones, infos, strict=False) if d)
                if (len(self.recent) == EXPLORE_WINDOW
                        and sum(self.recent) >= hold_until * EXPLORE_WINDOW):
                    self.since = self.model.num_timesteps
            return True

    return StdCeiling()


def check_explore(algo: str, hp: dict[str, Any]) -> float:
    """``hp["explore_until_success"]`` (0.0 without it): a success rate in (0, 1], and only
    beside ``log_std_final`` (checked as :func:`check_std_final` does); ValueError naming the
    key otherwise."""
    final = check_std_final(algo, hp)
    rate = hp.get("explore_until_success", 0.0)
    if type(rate) not in (int, float) or not (rate == 0 or 0 < rate <= 1):
        raise ValueError(f"hyperparams: explore_until_success must be a success rate in "
                         f"(0, 1] (the training episodes' rate that ends the hold), got "
                         f"{rate!r}")
    if rate and final is None:
        raise ValueError("hyperparams: explore_until_success holds the noise until a success "
                         "rate before log_std_final's ceiling falls; it needs log_std_final")
    return float(rate)


def check_imitate(algo: str, hp: dict[str, Any]) -> tuple[int, float, int]:
    """``hp["imitate"]`` (0 without it): the scripted agent's env steps to clone before PPO
    trains (:func:`imitate_scripted`), an int in [0, :data:`MAX_IMITATE`]; only for PPO with
    ``MlpPolicy`` or ``PointerPolicy``, observations not normalised and no frame stacking
    (the clone reads what the scripted agent reads). ``hp["imitate_noise"]`` (default
    :data:`IMITATE_NOISE`): the Gaussian noise (action units) on the actions the scripted
    agent executes while it is recorded, a number in [0, 1]; ``hp["imitate_updates"]``
    (default :data:`IMITATE_POLICY_UPDATES`): the Adam updates of the policy's fit (both
    unused with ``imitate`` 0, so that ``--hyperparams imitate=0`` trains a task's settings
    from scratch). Returns the three; ValueError naming the key otherwise."""
    steps = hp.get("imitate", 0)
    if type(steps) is not int or not 0 <= steps <= MAX_IMITATE:
        raise ValueError(f"hyperparams: imitate must be an int in [0, {MAX_IMITATE}] (the "
                         f"scripted agent's env steps to clone), got {steps!r}")
    if steps and (algo != "ppo"
                  or hp.get("policy", "MlpPolicy") not in ("MlpPolicy", "PointerPolicy")
                  or hp.get("normalize", False) or int(hp.get("frame_stack", 1)) != 1):
        raise ValueError("hyperparams: imitate clones the scripted agent into a PPO policy "
                         "that reads the observation as the agent does: it needs algo ppo, "
                         "policy MlpPolicy or PointerPolicy, normalize false and no "
                         "frame_stack")
    noise = hp.get("imitate_noise", IMITATE_NOISE)
    if type(noise) not in (int, float) or not 0 <= noise <= 1:
        raise ValueError(f"hyperparams: imitate_noise must be a number in [0, 1] (action "
                         f"units), got {noise!r}")
    updates = hp.get("imitate_updates", IMITATE_POLICY_UPDATES)
    if type(updates) is not int or not 1 <= updates <= MAX_IMITATE:
        raise ValueError(f"hyperparams: imitate_updates must be an int in [1, {MAX_IMITATE}] "
                         f"(the policy's Adam updates), got {updates!r}")
    return steps, float(noise), updates


def imitate_scripted(model: PPO, env_id: str, action_mode: str, env_kwargs: dict[str, Any],
                     seed: int, steps: int, noise: float = IMITATE_NOISE,
                     updates: int | None = None,
                     max_episode_steps: int | None = None) -> dict[str, float]:
    """Start PPO's ``model`` from a clone of the task's scripted agent (rl extra).

    ``steps`` env steps of the scripted agent (:data:`IMITATE_COPIES` copies of the native
    vector env, episodes seeded from :data:`IMITATE_SEED_START` ``+ 100 seed``, Gaussian
    noise of ``noise`` on the actions executed) give pairs (observation, the agent's action);
    the policy is fit to them (``updates`` Adam updates of :data:`IMITATE_BATCH` pairs, None
    for :data:`IMITATE_POLICY_UPDATES`): an ``MlpPolicy``'s mean by least squares, a
    ``PointerPolicy``'s point scores by maximum likelihood of the agent's actions under its
    mixture (each action is some observed point and its target: the likelihood is a
    cross-entropy over the points); in drag mode by cross-entropy of the point the agent
    works on (:func:`chosen_points`: its moves alone would not tell, as several points share
    a clipped move). The value
    function is then fit to the discounted returns (the model's ``gamma``) of the clone's
    own deterministic play over :data:`IMITATE_VALUE_STEPS` env steps (episodes of
    ``max_episode_steps``, None for the registered limit), so that PPO's first
    updates start from a critic that knows what the clone earns (from an untrained one, the
    first updates undo the clone). Its standard deviation is left at ``log_std_init``.
    Returns the policy's final loss (``policy_mse``, action units squared, ``policy_nll``,
    the mean negative log-likelihood of an action, or ``policy_choice_nll``, of a chosen
    point), the value function's mean
    squared error (``value_mse``) and the clone's mean discounted return (``clone_return``)."""
    import torch

    from .agents import make_agent
    from .policies import PointerPolicy

    vec = gym.make_vec(env_id, num_envs=IMITATE_COPIES, vectorization_mode="vector_entry_point",
                       action_mode=action_mode, **env_kwargs, **time_limit(max_episode_steps))
    try:
        agent = make_agent("scripted", vec)
        rng = np.random.default_rng(seed)
        gen = torch.Generator().manual_seed(seed)
        obs, _ = vec.reset(seed=IMITATE_SEED_START + 100 * seed)
        policy = model.policy
        # (drag mode: the pointer learns the agent's choice of point, read from its plan; its
        # moves alone do not tell it, as several points share a clipped move)
        plan = (getattr(agent, "plan", None)
                if isinstance(policy, PointerPolicy) and policy.drag is not None else None)
        seen, acts = [], []
        for _ in range(max(1, steps // IMITATE_COPIES)):
            a = agent(obs)
            seen.append(obs.copy())
            acts.append(a.copy() if plan is None else chosen_points(vec.unwrapped.task, obs,
                                                                    plan, policy.points))
            noisy = np.clip(a + rng.normal(0.0, noise, a.shape), -1.0, 1.0)
            obs, *_ = vec.step(noisy.astype(np.float32))
        x = torch.as_tensor(np.concatenate(seen), dtype=torch.float32, device=policy.device)
        y = torch.as_tensor(np.concatenate(acts), device=policy.device)
        y = y if plan is not None else y.float()
        value_names = ("mlp_extractor.value_net.", "value_net.")
        actor = [p for n, p in policy.named_parameters()
                 if n != "log_std" and not n.startswith(value_names)]
        critic = [p for n, p in policy.named_parameters() if n.startswith(value_names)]
        opt = torch.optim.Adam(actor, lr=1e-3)
        likelihood = isinstance(policy, PointerPolicy)
        for _ in range(IMITATE_POLICY_UPDATES if updates is None else updates):
            idx = torch.randint(0, len(x), (IMITATE_BATCH,), generator=gen)
            dist = policy.get_distribution(x[idx])
            if plan is not None:  # cross-entropy of the chosen points (B, G)
                policy_loss = -dist.log_w.gather(2, y[idx][:, :, None]).mean()
            elif likelihood:
                policy_loss = -dist.log_prob(y[idx]).mean()
            else:
                policy_loss = ((dist.distribution.mean - y[idx]) ** 2).mean()
            opt.zero_grad()
            policy_loss.backward()
            opt.step()
        obs, _ = vec.reset(seed=IMITATE_SEED_START + 100 * seed + 50)
        seen, rewards, ends = [], [], []
        for _ in range(max(1, IMITATE_VALUE_STEPS // IMITATE_COPIES)):
            seen.append(obs.copy())
            with torch.no_grad():
                mode = policy.get_distribution(torch.as_tensor(
                    obs, dtype=torch.float32, device=policy.device)).mode()
            obs, r, terminated, truncated, _ = vec.step(
                np.clip(mode.cpu().numpy(), -1.0, 1.0).astype(np.float32))
            rewards.append(r)
            ends.append(terminated | truncated)
        returns, future = [], np.zeros(IMITATE_COPIES)
        for r, end in zip(reversed(rewards), reversed(ends), strict=True):
            future = r + model.gamma * future * ~end
            returns.append(future)
        target = np.concatenate(returns[::-1])
        xv = torch.as_tensor(np.concatenate(seen), dtype=torch.float32, device=policy.device)
        yv = torch.as_tensor(target, dtype=torch.float32, device=policy.device)
        opt = torch.optim.Adam(critic, lr=1e-3)
        for _ in range(IMITATE_VALUE_UPDATES):
            idx = torch.randint(0, len(xv), (IMITATE_BATCH,), generator=gen)
            value_loss = ((policy.predict_values(xv[idx]).squeeze(-1) - yv[idx]) ** 2).mean()
            opt.zero_grad()
            value_loss.backward()
            opt.step()
    finally:
        vec.close()
    return {("policy_choice_nll" if plan is not None else "policy_nll" if likelihood
             else "policy_mse"): float(policy_loss.detach()),
            "value_mse": float(value_loss.detach()),
            "clone_return": float(target.mean())}


def chosen_points(task: PickPlaceTask, obs: np.ndarray, plan: DragPlan,
                  points: int) -> np.ndarray:
    """The observed point (B, G) int64 each gripper of a scripted drag agent works on, in
    observations ``obs`` (B, D): the one whose point and target lie nearest the pick and
    place points its plan headed for (``plan.heading``, :class:`envs.pick_place.DragPlan`);
    for a gripper that holds a particle, whose point lies nearest the gripper and target
    nearest the place it carries it to."""
    pick, place = plan.heading
    pos, holding = task.gripper_part(obs)
    pick = np.where(holding[:, :, None], pos, pick)
    o = np.asarray(obs, dtype=np.float64)
    B, K = len(o), points
    x = o[:, :2 * K].reshape(B, 1, K, 2)
    t = o[:, 2 * K:4 * K].reshape(B, 1, K, 2)
    p, q = task.to_normalized(pick)[:, :, None], task.to_normalized(place)[:, :, None]
    return np.argmin(((x - p) ** 2).sum(-1) + ((t - q) ** 2).sum(-1), axis=2)


def check_std_final(algo: str, hp: dict[str, Any]) -> float | None:
    """``hp["log_std_final"]`` (None without it): a finite number below the policy's
    ``log_std_init``, for PPO only; ValueError naming the key otherwise."""
    final = hp.get("log_std_final")
    if final is None:
        return None
    start = hp.get("policy_kwargs", {}).get("log_std_init", 0.0)
    if algo != "ppo" or hp.get("policy_kwargs", {}).get("use_sde", False):
        raise ValueError("hyperparams: log_std_final caps the log standard deviation of a PPO "
                         "policy without use_sde")
    if type(final) not in (int, float) or not np.isfinite(final) or final >= start:
        raise ValueError(f"hyperparams: log_std_final must be a number below log_std_init "
                         f"({start}), got {final!r}")
    return float(final)


def is_image(space: gym.Space) -> bool:
    """An image observation (``uint8`` ``(H, W, C)`` in [0, 255], as ``obs_mode="pixels"``
    gives): what SB3's ``CnnPolicy`` takes."""
    return (isinstance(space, gym.spaces.Box) and space.dtype == np.uint8
            and len(space.shape) == 3 and bool(np.all(space.low == 0))
            and bool(np.all(space.high == 255))
            and (space.shape[-1] in (1, 3, 4) or space.shape[0] in (1, 3, 4)))


#: The entries of PointerPolicy's ``drag`` setting (:class:`envs.policies.PointerPolicy`).
DRAG_KEYS = ("move_scale", "reach", "place")


def check_drag(drag: object) -> dict[str, float] | None:
    """``drag`` (PointerPolicy's setting) checked: None, or a dict of positive finite numbers
    ``move_scale`` (action per normalised view unit), ``reach`` and ``place`` (normalised view
    units): ValueError otherwise."""
    if drag is None:
        return None
    if not (isinstance(drag, dict) and set(drag) == set(DRAG_KEYS)
            and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                    and np.isfinite(v) and v > 0 for v in drag.values())):
        raise ValueError(f"drag must be None or a dict of positive numbers {DRAG_KEYS}, got "
                         f"{drag!r}")
    return {k: float(drag[k]) for k in DRAG_KEYS}


def check_episode_steps(hp: dict[str, Any]) -> int | None:
    """``hp["max_episode_steps"]``: the time limit (env steps) the run trains and is evaluated
    with, over the registered one (as ``gym.make(id, max_episode_steps=...)``; for an action
    mode whose episodes need more steps than the task's registered limit gives, such as drag
    mode's many steps per pick-and-place); None without it. ValueError unless a positive
    int of at most 100,000."""
    steps = hp.get("max_episode_steps")
    if steps is not None and (type(steps) is not int or not 1 <= steps <= 100_000):
        raise ValueError(f"hyperparams: max_episode_steps must be an int in [1, 100000], got "
                         f"{steps!r}")
    return steps


def time_limit(max_episode_steps: int | None) -> dict[str, int]:
    """The keyword arguments that give ``gym.make``/``gym.make_vec`` a time limit of
    ``max_episode_steps`` env steps: none for None (the registered limit)."""
    return {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}


def check_policy_fits(hp: dict[str, Any], space: gym.Space,
                      action_space: gym.Space | None = None, action_mode: str = "") -> None:
    """ValueError naming the setting unless the policy suits the observation: images go to
    ``CnnPolicy``, anything else to ``MlpPolicy``, or ``PointerPolicy`` where the observation
    is its points and their targets (in drag mode then the grippers of ``action_space``, 3
    action entries each)."""
    policy = hp.get("policy", "MlpPolicy")
    if is_image(space):
        if policy != "CnnPolicy":
            raise ValueError(f"policy: image observations {space.shape} need "
                             f"policy=CnnPolicy, got {policy!r} (--hyperparams "
                             "policy=CnnPolicy)")
    elif policy == "CnnPolicy":
        raise ValueError(f"policy: CnnPolicy takes image observations (obs_mode='pixels'), "
                         f"got a {type(space).__name__} of shape {space.shape}")
    elif policy == "PointerPolicy":
        pk = hp.get("policy_kwargs", {})
        if pk.get("drag") is not None and action_mode and action_mode != "drag":
            raise ValueError(f"policy: PointerPolicy's drag setting is for action_mode "
                             f"'drag', not {action_mode!r}")
        points = pk.get("points", 10)
        size = 4 * points
        tail = ""
        if pk.get("drag") is not None or action_mode == "drag":
            size += getattr(action_space, "shape", (3,))[0]
            tail = " and the grippers' positions and holding flags"
        shape = getattr(space, "shape", None)
        if not (isinstance(space, gym.spaces.Box) and shape is not None and len(shape) == 1
                and shape[0] == size):
            raise ValueError(f"policy: PointerPolicy with points={points} reads an observation "
                             f"of {points} points and their {points} targets{tail} ({size} "
                             f"numbers), got a {type(space).__name__} of shape {shape} (set "
                             "policy_kwargs.points to the observed points)")


#: The keys of ``net_arch`` given as separate networks, per algorithm (SB3's forms): the
#: policy and the value function (PPO), the actor and the critics (SAC).
ARCH_KEYS = {"ppo": ("pi", "vf"), "sac": ("pi", "qf")}


def check_policy_settings(config_path: Path, hp: dict[str, Any], algo: str) -> None:
    """ValueError unless the policy settings of ``hp`` are ones ``evaluate`` can rebuild for
    ``algo``: a policy of :data:`POLICIES` and ``policy_kwargs`` of :data:`POLICY_KWARGS`
    with layers of 1 to :data:`MAX_LAYER` units (``net_arch`` one list, or one per network
    of :data:`ARCH_KEYS`)."""
    if hp.get("policy", "MlpPolicy") not in POLICIES:
        raise ValueError(f"{config_path}: hyperparams.policy must be one of {POLICIES}, got "
                         f"{hp.get('policy')!r}")
    pk = hp.get("policy_kwargs", {})
    if not isinstance(pk, dict) or set(pk) - set(POLICY_KWARGS):
        raise ValueError(f"{config_path}: hyperparams.policy_kwargs may hold only "
                         f"{', '.join(POLICY_KWARGS)}")
    for key in PPO_POLICY_KWARGS:
        if key in pk and algo != "ppo":
            raise ValueError(f"{config_path}: hyperparams.policy_kwargs.{key} is a ppo setting "
                             f"({algo}'s policy does not take it)")
    arch = pk.get("net_arch", [64, 64])
    keys = ARCH_KEYS.get(algo, ("pi", "vf"))
    parts = list(arch.values()) if isinstance(arch, dict) and set(arch) == set(keys) \
        else [arch]
    if not all(isinstance(a, list) and len(a) <= 16
               and all(type(n) is int and 1 <= n <= MAX_LAYER for n in a) for a in parts):
        raise ValueError(f"{config_path}: hyperparams.policy_kwargs.net_arch must be a list of "
                         f"at most 16 layer widths in [1, {MAX_LAYER}], or such lists for the "
                         f"networks apart ({algo}: {{\"{keys[0]}\": [...], \"{keys[1]}\": "
                         "[...]})")
    policy = hp.get("policy", "MlpPolicy")
    if policy == "PointerPolicy":
        if algo != "ppo":
            raise ValueError(f"{config_path}: hyperparams.policy PointerPolicy is a ppo policy, "
                             f"not {algo}'s")
        if hp.get("normalize", False):
            raise ValueError(f"{config_path}: hyperparams.normalize must be false with "
                             "PointerPolicy (it acts at the observed points themselves)")
        if pk.get("use_sde", False):
            raise ValueError(f"{config_path}: hyperparams.policy_kwargs.use_sde does not go "
                             "with PointerPolicy (its noise is the mixture's)")
        try:
            check_drag(pk.get("drag"))
        except ValueError as exc:
            raise ValueError(f"{config_path}: hyperparams.policy_kwargs.{exc}") from None
        points = pk.get("points", 10)
        if type(points) is not int or not 1 <= points <= 512:
            raise ValueError(f"{config_path}: hyperparams.policy_kwargs.points must be a "
                             f"whole number in [1, 512], got {points!r}")
    else:
        for key in ("points", "drag"):
            if key in pk:
                raise ValueError(f"{config_path}: hyperparams.policy_kwargs.{key} is a setting"
                                 f" of PointerPolicy, not of {policy}")
    for flag in ("use_sde", "ortho_init"):
        if not isinstance(pk.get(flag, False), bool):
            raise ValueError(f"{config_path}: hyperparams.policy_kwargs.{flag} must be true or "
                             "false")
    stack = hp.get("frame_stack", 1)
    if type(stack) is not int or not 1 <= stack <= MAX_FRAME_STACK:
        raise ValueError(f"{config_path}: hyperparams.frame_stack must be a whole number in "
                         f"[1, {MAX_FRAME_STACK}], got {stack!r}")
    log_std = pk.get("log_std_init", 0.0)
    if type(log_std) not in (int, float) or not np.isfinite(log_std):
        raise ValueError(f"{config_path}: hyperparams.policy_kwargs.log_std_init must be a "
                         "finite number")
