"""``cparticles train``, ``evaluate`` and ``convert-run``: Stable-Baselines3 baselines on the envs.

    cparticles train ClothSlide-v0 --algo ppo --seed 0 --out runs/cloth-ppo-0
    cparticles evaluate runs/cloth-ppo-0 --episodes 100 --seed-start 2000000 --json

``train`` reads the shipped hyperparameters (each task's declaration, ``TaskSpec.hyperparams``:
one entry per algorithm and action mode, in the style of rl-baselines3-zoo), builds the training
env (the native vector env through :func:`envs.sb3.to_sb3` when ``n_envs > 1``, as PPO wants; a
single env otherwise, as SAC wants), optionally wraps it in ``VecNormalize``, and trains with a
progress bar. Every ``--eval-freq`` steps it runs deterministic evaluation episodes on seeds
from ``EVAL_SEED_START`` and appends them to ``DIR/evaluations.json``. The run is written into a
hidden directory beside ``DIR`` and renamed to ``DIR`` once complete, so a failed run (a full
disk, an interrupt) leaves no directory that looks like a run.

**A run directory holds data, not code** (format 2, ``config.json``'s ``"format"``):

- ``config.json``: what was run (env, action mode, algorithm, seed, steps, the hyperparameters
  with the policy settings), the observation and action spaces (shape, dtype, bounds), whether
  observations were normalized, how long it took;
- ``policy.pt`` and ``best_policy.pt`` (best periodic evaluation): the policy's weights, a
  PyTorch state dict of tensors, read back with ``torch.load(..., weights_only=True)``;
- ``normalization.npz`` and ``best_normalization.npz`` (when the hyperparameters normalize):
  the observation statistics of ``VecNormalize`` as plain arrays (``mean``, ``var``, ``count``,
  ``clip_obs``, ``epsilon``, ``norm_obs``), read with ``allow_pickle=False``;
- ``evaluations.json``: the periodic evaluations.

``evaluate`` checks ``config.json``, rebuilds the policy from its settings and the env's spaces,
loads the weights and statistics from those files, and never unpickles anything stored, so a
crafted run directory runs no code: a bad file is one ``error:`` line. Directories of an older
``train`` hold pickles (``model.zip``, ``vecnormalize.pkl``); ``evaluate`` refuses them and
names ``cparticles convert-run DIR``, which loads those pickles (running whatever they hold:
only for directories you trust) and writes the files above beside them.

``evaluate`` plays ``--episodes`` episodes with seeds ``--seed-start``,
``--seed-start + 1``, ... (keep them away from the training and periodic-evaluation seeds:
``HELD_OUT_SEED_START`` is the convention of ``docs/baselines``), deterministic unless
``--stochastic``, and prints a summary; the last line of the output is one JSON object with
``success_rate``, ``mean_return``, ``mean_length``, ``episodes`` and diagnostics (for
ClothSlide: the mean ``|squeeze|`` of the actions, the RMS speed near the goal, final distances and
speeds of failed episodes).

Requires the ``rl`` extra (stable-baselines3, torch).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from constrained_particles.extras import require

from .checks import check_positive
from .task import check_env_kwargs, check_env_mode, task_spec
from .train_settings import (
    check_episode_steps,
    check_explore,
    check_imitate,
    check_std_final,
    imitate_scripted,
    schedule,
    time_limit,
)
from .train_settings import check_policy_fits as _check_policy_fits
from .train_settings import check_policy_settings as _check_policy_settings
from .train_settings import is_image as _is_image
from .train_settings import std_ceiling as _std_ceiling

if TYPE_CHECKING:  # (the rl extra)
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.policies import BasePolicy
    from stable_baselines3.common.vec_env import VecEnv, VecNormalize

#: Algorithms ``cparticles train`` knows (Stable-Baselines3 classes).
ALGOS = ("ppo", "sac")
#: Seeds of the periodic evaluation episodes during training.
EVAL_SEED_START = 1_000_000
#: First seed of held-out evaluation episodes (the convention of docs/baselines).
HELD_OUT_SEED_START = 2_000_000
#: Distance (m) from the goal within which ``evaluate`` measures the RMS speed.
NEAR_GOAL = 0.1
#: Keys of a hyperparameter entry that ``train`` consumes itself (the rest go to the algorithm).
OWN_KEYS = ("n_envs", "n_timesteps", "normalize", "normalize_reward", "policy", "env_kwargs",
            "frame_stack", "log_std_final", "explore_until_success", "imitate",
            "imitate_noise", "imitate_updates", "max_episode_steps")
#: Largest ``--seed`` (the seeds of the env copies follow it; numpy's legacy seeding, which
#: Stable-Baselines3 uses, takes at most 2**32 - 1).
MAX_SEED = 2**31 - 1
#: What ``config.json`` of a run holds, with the types ``evaluate`` checks before loading.
CONFIG_FIELDS: dict[str, type] = {
    "env": str, "action_mode": str, "algo": str, "seed": int, "timesteps": int,
    "hyperparams": dict}
#: The version of the run directory format ``train`` writes (``config.json``'s ``"format"``):
#: 2 holds data only (weights, statistics, JSON); 1 (no ``"format"``) held pickles.
FORMAT = 2
#: The policy weights of the final and the best model (a PyTorch state dict of tensors).
POLICY_FILES = {"final": "policy.pt", "best": "best_policy.pt"}
#: The observation statistics of the final and the best model (plain arrays), when normalized.
NORMALIZATION_FILES = {"final": "normalization.npz", "best": "best_normalization.npz"}
#: The pickles a run directory of format 1 held (never loaded by ``evaluate``).
OLD_FILES = ("model.zip", "best_model.zip", "vecnormalize.pkl", "best_vecnormalize.pkl")
#: Largest ``config.json`` ``evaluate`` reads (bytes); one that ``train`` writes has a few kB.
MAX_CONFIG_BYTES = 1_000_000
def _algo_class(algo: str) -> type:
    from stable_baselines3 import PPO, SAC

    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return {"ppo": PPO, "sac": SAC}[algo]


def _policy_class(algo: str, hp: dict[str, Any]) -> type:
    """The policy class ``hp`` names for ``algo``: SB3's alias, or the project's
    :class:`envs.policies.PointerPolicy`."""
    name = hp.get("policy", "MlpPolicy")
    if name == "PointerPolicy":
        from .policies import PointerPolicy

        return PointerPolicy
    return _algo_class(algo).policy_aliases[name]


def load_hyperparams(algo: str, env_id: str, action_mode: str | None = None,
                     env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The shipped hyperparameters of ``algo`` for ``env_id`` in ``action_mode`` (None: the
    env's default mode) with the env keyword arguments ``env_kwargs`` (a variant with settings
    of its own takes those), a copy (the task's declaration, ``TaskSpec.settings``)."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return task_spec(env_id).settings(algo, action_mode, env_kwargs)


def check_overrides(algo: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """``overrides`` of the shipped settings of ``algo`` (``--hyperparams``), checked before
    any work: each key one of ``train``'s own (:data:`OWN_KEYS`) or a keyword argument of the
    Stable-Baselines3 class (ValueError naming it and listing the valid ones otherwise); a
    copy."""
    import inspect

    params = set(inspect.signature(_algo_class(algo).__init__).parameters) - {
        "self", "env", "policy", "seed", "verbose", "device", "_init_setup_model",
        "tensorboard_log"}
    valid = {*OWN_KEYS, *params} - {"env_kwargs"}  # (env keywords: --env-kwargs)
    unknown = [k for k in overrides if k not in valid]
    if unknown:
        raise ValueError(f"hyperparams: {', '.join(map(repr, unknown))} not a setting of "
                         f"{algo}; it takes {', '.join(sorted(valid))}")
    for key, value in overrides.items():
        schedule(key, value)
    return json.loads(json.dumps(overrides))


def make_train_env(env_id: str, action_mode: str, n_envs: int, seed: int,
                   env_kwargs: dict[str, Any] | None = None,
                   max_episode_steps: int | None = None) -> VecEnv:
    """An SB3 ``VecEnv`` for training, with episode statistics (``VecMonitor``).

    ``n_envs > 1``: the native vector env (all copies one particle system) through
    :func:`envs.sb3.to_sb3`; ``n_envs == 1``: a ``DummyVecEnv`` of one single env. Copy ``i``'s
    first episode is seeded with ``seed + i``. ``max_episode_steps``: the time limit (env
    steps), None for the registered one.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    from .sb3 import to_sb3

    kwargs = dict(env_kwargs or {}, action_mode=action_mode, **time_limit(max_episode_steps))
    if n_envs > 1:
        venv = to_sb3(gym.make_vec(env_id, num_envs=n_envs,
                                   vectorization_mode="vector_entry_point", **kwargs))
    else:
        venv = DummyVecEnv([lambda: gym.make(env_id, **kwargs)])
    venv = VecMonitor(venv)
    venv.seed(seed)
    return venv


Policy = Callable[[np.ndarray], np.ndarray]


def stack_frames(stack: np.ndarray | None, obs: np.ndarray, frames: int) -> np.ndarray:
    """The last ``frames`` observations of each copy concatenated along their last axis,
    oldest first, as SB3's ``VecFrameStack`` holds them: ``stack`` (None at an episode's
    start: the older frames zero) shifted by one frame and ``obs`` (num_envs, ..., C) put
    last. Returns the new stack (num_envs, ..., frames * C)."""
    c = obs.shape[-1]
    if stack is None:
        stack = np.zeros((*obs.shape[:-1], frames * c), dtype=obs.dtype)
    else:
        stack = np.roll(stack, -c, axis=-1)
    stack[..., -c:] = obs
    return stack


def run_episodes(policy: Policy, env_id: str, episodes: int, seed_start: int,
                 action_mode: str = "force", env_kwargs: dict[str, Any] | None = None,
                 batch: int = 100, frame_stack: int = 1,
                 max_episode_steps: int | None = None) -> dict[str, Any]:
    """Play ``episodes`` episodes (seeds ``seed_start + k``) with ``policy`` (batched raw
    observations -> actions) in native vector envs of up to ``batch`` copies;
    ``frame_stack > 1`` hands the policy each copy's last ``frame_stack`` observations
    (:func:`stack_frames`), as training with that setting did; ``max_episode_steps``: the
    time limit (env steps), None for the registered one.

    Returns the per-episode arrays ``return``, ``length``, ``success``, ``final_distance`` (m),
    ``final_speed`` (m/s), ``final_performance`` (the last ``info["normalized_performance"]``,
    SoftGym's measure, of the tasks that report it; NaN for the others), and the summaries
    ``mean_abs_squeeze`` (N, ClothSlide force mode, else None) and ``rms_speed_near_goal``
    (m/s, RMS particle speed over all steps within ``NEAR_GOAL`` m of the goal, None if there
    were none).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    keys = ("return", "length", "success", "final_distance", "final_speed",
            "final_performance")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    squeeze: list[np.ndarray] = []
    near: list[np.ndarray] = []
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                           action_mode=action_mode, **(env_kwargs or {}),
                           **time_limit(max_episode_steps))
        task = env.unwrapped.task
        obs, _ = env.reset(seed=seed_start + start)
        seen = stack_frames(None, obs, frame_stack) if frame_stack > 1 else obs
        ret, length = np.zeros(n), np.zeros(n, dtype=np.int64)
        success, done = np.zeros(n, bool), np.zeros(n, bool)
        dist, speed, perf = np.zeros(n), np.zeros(n), np.full(n, np.nan)
        while not done.all():
            obs, reward, terminated, truncated, info = env.step(policy(seen))
            # (a copy that ended keeps stepping, ignored, until the batch is done)
            seen = stack_frames(seen, obs, frame_stack) if frame_stack > 1 else obs
            live = ~done
            m = task.measure()
            ret[live] += reward[live]
            length[live] += 1
            dist[live], speed[live] = m["distance"][live], m["speed"][live]
            if "squeeze" in m and action_mode == "force":
                squeeze.append(np.abs(m["squeeze"][live]))
            near.append(m["speed"][live & (m["distance"] < NEAR_GOAL)])
            ended = live & (terminated | truncated)
            success[ended] = info["is_success"][ended]
            if "normalized_performance" in info:
                perf[ended] = info["normalized_performance"][ended]
            done |= ended
        env.close()
        for k, v in zip(keys, (ret, length, success, dist, speed, perf), strict=True):
            out[k].append(v)
    res: dict[str, Any] = {k: np.concatenate(v) for k, v in out.items()}
    res["mean_abs_squeeze"] = float(np.mean(np.concatenate(squeeze))) if squeeze else None
    near_all = np.concatenate(near) if near else np.zeros(0)
    res["rms_speed_near_goal"] = (float(np.sqrt(np.mean(near_all**2))) if near_all.size
                                  else None)
    return res


def summarize(res: dict[str, Any]) -> dict[str, Any]:
    """The JSON-able summary of :func:`run_episodes` (``mean_normalized_performance``: None
    for a task that does not report it)."""
    fail = ~res["success"]
    perf = res.get("final_performance")
    has_perf = perf is not None and not np.isnan(perf).all()
    return {"episodes": int(len(res["success"])),
            "success_rate": float(res["success"].mean()),
            "mean_return": float(res["return"].mean()),
            "mean_length": float(res["length"].mean()),
            "mean_normalized_performance": float(np.mean(perf)) if has_perf else None,
            "mean_abs_squeeze": res["mean_abs_squeeze"],
            "rms_speed_near_goal": res["rms_speed_near_goal"],
            "failures_final_distance": res["final_distance"][fail].round(4).tolist(),
            "failures_final_speed": res["final_speed"][fail].round(4).tolist()}


def sb3_policy(model: BaseAlgorithm | BasePolicy,
               obs_normalizer: VecNormalize | ObsNormalizer | None = None,
               deterministic: bool = True) -> Policy:
    """A batched policy from an SB3 model or policy (anything with ``predict``) and
    (optionally) a ``VecNormalize`` or :class:`ObsNormalizer` whose observation statistics it
    applies."""
    def policy(obs: np.ndarray) -> np.ndarray:
        o = obs if obs_normalizer is None else obs_normalizer.normalize_obs(obs)
        action, _ = model.predict(o, deterministic=deterministic)
        return action
    return policy


def drag_geometry(env_id: str, env_kwargs: dict[str, Any]) -> dict[str, float]:
    """The drag-mode geometry of ``env_id``'s task with ``env_kwargs``
    (:meth:`envs.pick_place.PickPlaceTask.drag_pointer`), for
    :class:`envs.policies.PointerPolicy` in drag mode."""
    env = gym.make_vec(env_id, num_envs=1, vectorization_mode="vector_entry_point",
                       action_mode="drag", **env_kwargs)
    try:
        return dict(env.unwrapped.task.drag_pointer())
    finally:
        env.close()


def _callback(out: Path, env_id: str, action_mode: str, env_kwargs: dict[str, Any],
              eval_freq: int, eval_episodes: int, started: float, frame_stack: int = 1,
              max_episode_steps: int | None = None) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class PeriodicEvaluation(BaseCallback):
        """Deterministic episodes every ``eval_freq`` env steps, appended to evaluations.json;
        the best model (success rate, then mean return) saved as best_model.zip."""

        def __init__(self) -> None:
            super().__init__()
            self.next_eval = eval_freq
            self.records: list[dict[str, Any]] = []
            self.best: tuple[float, float] | None = None

        def evaluate_now(self) -> None:
            vn = _obs_normalizer(self.model)
            res = run_episodes(sb3_policy(self.model, vn), env_id, eval_episodes,
                               EVAL_SEED_START, action_mode, env_kwargs,
                               frame_stack=frame_stack, max_episode_steps=max_episode_steps)
            s = summarize(res)
            rec = {"timesteps": int(self.num_timesteps),
                   "seconds": round(time.perf_counter() - started, 1),
                   **{k: s[k] for k in ("success_rate", "mean_return", "mean_length",
                                        "mean_abs_squeeze", "rms_speed_near_goal")}}
            self.records.append(rec)
            (out / "evaluations.json").write_text(json.dumps(self.records, indent=1))
            key = (s["success_rate"], s["mean_return"])
            if self.best is None or key > self.best:
                self.best = key
                save_policy(self.model, out / POLICY_FILES["best"])
                if vn is not None:
                    save_normalization(vn, out / NORMALIZATION_FILES["best"])
            print(f"eval @ {rec['timesteps']} steps: success {s['success_rate']:.0%}, "
                  f"return {s['mean_return']:.2f}, length {s['mean_length']:.0f} "
                  f"({rec['seconds']:.0f} s)", file=sys.stderr, flush=True)

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += eval_freq
                self.evaluate_now()
            return True

    return PeriodicEvaluation()


def _obs_normalizer(model: BaseAlgorithm) -> VecNormalize | None:
    """The model's ``VecNormalize`` if it normalizes observations (not images, whose rewards
    alone it normalizes), else None."""
    vn = model.get_vec_normalize_env()
    return vn if vn is not None and vn.norm_obs else None


def save_policy(model: BaseAlgorithm, path: Path) -> None:
    """Write the weights of ``model``'s policy to ``path``: a PyTorch state dict of CPU
    tensors, which :func:`load_policy` reads with ``weights_only`` (no code runs)."""
    import torch

    state = {k: v.detach().cpu().clone() for k, v in model.policy.state_dict().items()}
    with open(path, "wb") as f:
        torch.save(state, f)


def save_normalization(normalizer: VecNormalize, path: Path) -> None:
    """Write the observation statistics of a ``VecNormalize`` to ``path`` as plain arrays
    (``.npz``; :class:`ObsNormalizer` reads them back without pickles)."""
    rms = normalizer.obs_rms
    with open(path, "wb") as f:
        np.savez(f, mean=np.asarray(rms.mean, np.float64), var=np.asarray(rms.var, np.float64),
                 count=np.float64(rms.count), clip_obs=np.float64(normalizer.clip_obs),
                 epsilon=np.float64(normalizer.epsilon), norm_obs=np.bool_(normalizer.norm_obs))


class ObsNormalizer:
    """The observation normalization of a ``VecNormalize`` (its ``normalize_obs``, the same
    bits), from statistics stored as plain arrays by :func:`save_normalization`."""

    def __init__(self, mean: np.ndarray, var: np.ndarray, clip_obs: float, epsilon: float,
                 norm_obs: bool = True) -> None:
        self.mean, self.var = np.asarray(mean, np.float64), np.asarray(var, np.float64)
        self.clip_obs, self.epsilon, self.norm_obs = float(clip_obs), float(epsilon), norm_obs

    @classmethod
    def load(cls, path: Path, shape: tuple[int, ...]) -> ObsNormalizer:
        """Read ``path`` (no pickles allowed); ValueError naming the file unless it holds the
        arrays :func:`save_normalization` writes, finite, for observations of ``shape``."""
        try:
            with np.load(path, allow_pickle=False) as f:
                data = {k: f[k] for k in ("mean", "var", "clip_obs", "epsilon", "norm_obs")}
        except (OSError, ValueError, KeyError, EOFError) as exc:
            raise ValueError(f"{path} is not a normalization file of cparticles train "
                             f"({exc})") from None
        for name in ("mean", "var"):
            a = data[name]
            if a.dtype.kind != "f" or a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"{path}: {name} must be finite floats of shape {shape}, "
                                 f"got {a.dtype} {a.shape}")
        scalars = [data[k] for k in ("clip_obs", "epsilon")]
        if any(a.shape != () or a.dtype.kind != "f" or not np.isfinite(a) or a <= 0
               for a in scalars) or (data["var"] < 0).any() \
                or data["norm_obs"].shape != () or data["norm_obs"].dtype != bool:
            raise ValueError(f"{path}: clip_obs and epsilon must be finite numbers > 0, var "
                             ">= 0 and norm_obs a bool")
        return cls(data["mean"], data["var"], float(data["clip_obs"]), float(data["epsilon"]),
                   bool(data["norm_obs"]))

    def normalize_obs(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` normalized and clipped, float32 (as ``VecNormalize.normalize_obs``)."""
        if not self.norm_obs:
            return obs
        return np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip_obs,
                       self.clip_obs).astype(np.float32)


def space_record(space: gym.spaces.Box) -> dict[str, Any]:
    """A Box space as JSON data: shape, dtype, low and high (``config.json``'s ``spaces``)."""
    return {"shape": list(space.shape), "dtype": str(space.dtype),
            "low": space.low.tolist(), "high": space.high.tolist()}


def _partial_directory(out: Path) -> Path:
    """A new hidden directory beside ``out`` that a run is written into before it is renamed
    to ``out`` (so a failed run leaves nothing that looks like one)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))


def _finish(partial: Path, out: Path) -> None:
    """Rename the complete run ``partial`` to ``out`` (which may exist as an empty directory)."""
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    os.rename(partial, out)


def train(env_id: str, algo: str, seed: int, out: str | Path, action_mode: str | None = None,
          timesteps: int | None = None, eval_freq: int | None = None, eval_episodes: int = 50,
          progress_bar: bool = True, threads: int = 1, verbose: int = 0, *,
          env_kwargs: dict[str, Any] | None = None, hyperparams: dict[str, Any] | None = None,
          n_envs: int | None = None, device: str = "auto",
          tensorboard_log: str | Path | None = None) -> dict[str, Any]:
    """Train ``algo`` on ``env_id`` with the shipped hyperparameters; write the run to ``out``.

    ``action_mode`` None takes the env's default. ``timesteps`` overrides the shipped
    ``n_timesteps``; ``eval_freq`` (env steps, default a tenth of the budget) and
    ``eval_episodes`` set the periodic evaluation. ``threads`` caps torch's CPU threads.
    ``env_kwargs``: keyword arguments of the env (a variant, such as ChainSwing's
    ``target="swingup"``), over the shipped entry's; ``hyperparams``: settings over the
    shipped ones (:func:`check_overrides`); ``n_envs``: env copies (over the shipped
    ``n_envs``); ``device``: torch's (``"auto"``, ``"cpu"``, ``"cuda"``, ...). The run
    directory gets ``progress.csv`` (SB3's logger: the training statistics every rollout);
    ``tensorboard_log``: a folder that also gets TensorBoard event files, in a subfolder named
    after ``out``. ``config.json`` records the settings used and the overrides given.
    ``out`` must not exist or be an empty directory: the run is written into a hidden
    directory beside it and renamed to ``out`` only once complete (a failure, a full disk or
    an interrupt leaves no ``out``). Returns the contents of ``out/config.json``.
    """
    require("stable_baselines3", "torch", command="envs.train.train")
    import stable_baselines3
    import torch
    from stable_baselines3.common.logger import Logger, make_output_format
    from stable_baselines3.common.vec_env import VecNormalize

    action_mode = check_env_mode(env_id, action_mode)
    overrides = check_overrides(algo, dict(hyperparams or {}))
    if n_envs is not None:
        overrides["n_envs"] = int(check_positive("n_envs", n_envs, integer=True,
                                                 maximum=4096))
    if env_kwargs:
        env_kwargs = check_env_kwargs(env_id, env_kwargs)
    hp = {**load_hyperparams(algo, env_id, action_mode, env_kwargs), **overrides}
    if env_kwargs:
        hp["env_kwargs"] = {**hp.get("env_kwargs", {}), **env_kwargs}
        overrides["env_kwargs"] = env_kwargs
    if (hp.get("policy") == "PointerPolicy" and action_mode == "drag"
            and "drag" not in hp.get("policy_kwargs", {})):  # (the task's drag geometry)
        hp["policy_kwargs"] = {**hp.get("policy_kwargs", {}),
                               "drag": drag_geometry(env_id, hp.get("env_kwargs", {}))}
    _check_policy_settings(Path("hyperparams"), hp, algo)  # (what evaluate will accept)
    for key, value in hp.items():  # (a schedule's notation, before any work)
        schedule(key, value)
    std_final = check_std_final(algo, hp)
    explore = check_explore(algo, hp)
    imitate, imitate_noise, imitate_updates = check_imitate(algo, hp)
    episode_steps = check_episode_steps(hp)
    if timesteps is None:
        timesteps = int(hp["n_timesteps"])
    if isinstance(timesteps, bool) or not isinstance(timesteps, (int, np.integer)) \
            or timesteps < 1:
        raise ValueError(f"timesteps must be an integer >= 1, got {timesteps!r}")
    if eval_freq is None:
        eval_freq = max(1, timesteps // 10)
    if eval_freq < 1 or eval_episodes < 1:
        raise ValueError(f"eval_freq and eval_episodes must be >= 1, got {eval_freq}, "
                         f"{eval_episodes}")
    if not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be in [0, {MAX_SEED}], got {seed}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    out = Path(out)
    if os.path.lexists(out) and not (out.is_dir() and not any(out.iterdir())):
        raise ValueError(f"out: {str(out)!r} exists and is not an empty directory")
    torch.set_num_threads(threads)
    env_kwargs = dict(hp.get("env_kwargs", {}))
    n_envs = int(hp.get("n_envs", 1))
    partial = _partial_directory(out)
    venv = None
    try:
        venv = make_train_env(env_id, action_mode, n_envs, seed, env_kwargs, episode_steps)
        _check_policy_fits(hp, venv.observation_space, venv.action_space, action_mode)
        env_space = venv.observation_space
        frame_stack = int(hp.get("frame_stack", 1))
        if frame_stack > 1:
            from stable_baselines3.common.vec_env import VecFrameStack

            venv = VecFrameStack(venv, frame_stack, channels_order="last")
        # (a copy: SB3 writes into policy_kwargs, and config.json records the settings given)
        kwargs = json.loads(json.dumps({k: v for k, v in hp.items() if k not in OWN_KEYS}))
        kwargs = {k: schedule(k, v) for k, v in kwargs.items()}
        if hp.get("normalize", False):
            # (images are not normalized: the CNN policy scales pixels by 1/255 itself; the
            # rewards still are)
            venv = VecNormalize(venv, norm_obs=not _is_image(env_space),
                                norm_reward=hp.get("normalize_reward", True),
                                gamma=kwargs.get("gamma", 0.99))
        started = time.perf_counter()
        cls = _algo_class(algo)
        model = cls(_policy_class(algo, hp), venv, seed=seed, verbose=verbose,
                    device=device, **kwargs)
        writers = [make_output_format("csv", str(partial))]
        if tensorboard_log is not None:
            writers.append(make_output_format("tensorboard",
                                              str(Path(tensorboard_log) / out.name)))
        model.set_logger(Logger(str(partial), writers))
        callback = _callback(partial, env_id, action_mode, env_kwargs, eval_freq,
                             eval_episodes, started, frame_stack, episode_steps)
        callbacks: list[Any] = [callback]
        if std_final is not None:
            callbacks.append(_std_ceiling(hp["policy_kwargs"].get("log_std_init", 0.0),
                                          std_final, timesteps, explore))
        imitation = (imitate_scripted(model, env_id, action_mode, env_kwargs, seed, imitate,
                                      imitate_noise, imitate_updates, episode_steps)
                     if imitate else None)
        model.learn(total_timesteps=timesteps, callback=callbacks, progress_bar=progress_bar)
        if not callback.records or callback.records[-1]["timesteps"] < timesteps:
            callback.evaluate_now()
        seconds = time.perf_counter() - started
        save_policy(model, partial / POLICY_FILES["final"])
        vn = _obs_normalizer(model)
        if vn is not None:
            save_normalization(vn, partial / NORMALIZATION_FILES["final"])
        config = {"format": FORMAT, "env": env_id, "action_mode": action_mode, "algo": algo,
                  "seed": seed, "timesteps": int(model.num_timesteps), "hyperparams": hp,
                  "overrides": overrides, "device": str(model.device),
                  "observation_shape": list(env_space.shape),
                  "action_shape": list(venv.action_space.shape),
                  "spaces": {"observation": space_record(env_space),
                             "action": space_record(venv.action_space)},
                  "normalized": vn is not None,
                  **({"imitation": imitation} if imitation is not None else {}),
                  "wall_seconds": round(seconds, 1), "threads": threads,
                  "versions": {"stable_baselines3": stable_baselines3.__version__,
                               "torch": torch.__version__, "gymnasium": gym.__version__}}
        (partial / "config.json").write_text(json.dumps(config, indent=1))
        _finish(partial, out)
    finally:
        if venv is not None:
            venv.close()
        shutil.rmtree(partial, ignore_errors=True)  # (gone already when renamed)
    return config


def _read_config(config_path: Path) -> Any:
    """The JSON in ``config_path``; ValueError for a file that cannot be read, is too big
    (:data:`MAX_CONFIG_BYTES`), is not JSON, or nests too deeply to parse."""
    try:
        with open(config_path, "rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"cannot read {config_path} ({exc.strerror or exc})") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ValueError(f"{config_path} is larger than {MAX_CONFIG_BYTES} bytes (a config.json "
                         "of cparticles train has a few kB)")
    try:
        return json.loads(data)
    except ValueError as exc:  # also UnicodeDecodeError
        raise ValueError(f"{config_path} is not valid JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{config_path} is not a config.json of cparticles train (nested too "
                         "deeply to read)") from None


def read_run(out: str | Path, which: str = "final") -> dict[str, Any]:
    """The ``config.json`` of a run directory that ``train`` wrote, checked: ValueError unless
    ``out`` holds a config.json (JSON data only, nothing else is read) with the fields
    ``train`` writes, of the current :data:`FORMAT`, a registered env with an action mode it
    takes, a known algorithm, policy settings ``evaluate`` can rebuild, the policy file of
    ``which`` (``"final"`` or ``"best"``), and the observation and action spaces that env
    gives. A directory of an older ``train`` (pickles) is refused with how to convert it."""
    out = Path(out)
    if which not in ("final", "best"):
        raise ValueError(f"which must be 'final' or 'best', got {which!r}")
    if not out.is_dir():
        raise ValueError(f"{str(out)!r} is not a directory")
    config_path = out / "config.json"
    if not config_path.is_file():
        raise ValueError(f"{str(out)!r} is not a run directory of cparticles train "
                         "(no config.json)")
    config = _read_config(config_path)
    if not isinstance(config, dict):
        raise ValueError(f"{config_path} is not a JSON object")
    if "format" not in config and any((out / name).exists() for name in OLD_FILES):
        raise ValueError(f"{str(out)!r} was written by an older cparticles train: its model is "
                         "a pickle, which runs code when loaded, and evaluate loads no "
                         "pickles. If you made it yourself or otherwise trust it, convert it "
                         f"with: cparticles convert-run {out}")
    if config.get("format") != FORMAT or isinstance(config.get("format"), bool):
        raise ValueError(f"{config_path}: field 'format' must be {FORMAT} (a run directory of "
                         f"this cparticles train), got {config.get('format')!r}")
    for name, kind in CONFIG_FIELDS.items():
        if not isinstance(config.get(name), kind) or isinstance(config.get(name), bool):
            raise ValueError(f"{config_path}: field {name!r} missing or not a "
                             f"{kind.__name__}")
    try:
        check_env_mode(config["env"], config["action_mode"])
    except ValueError as exc:
        raise ValueError(f"{config_path}: {exc}") from None
    if config["algo"] not in ALGOS:
        raise ValueError(f"{config_path}: algo must be one of {ALGOS}, got {config['algo']!r}")
    env_kwargs = config["hyperparams"].get("env_kwargs", {})
    if not isinstance(env_kwargs, dict):
        raise ValueError(f"{config_path}: hyperparams.env_kwargs must be an object")
    _check_policy_settings(config_path, config["hyperparams"], config["algo"])
    try:
        check_episode_steps(config["hyperparams"])
    except ValueError as exc:
        raise ValueError(f"{config_path}: {exc}") from None
    policy = out / POLICY_FILES[which]
    if not policy.is_file():
        raise ValueError(f"{str(out)!r} has no {policy.name} (train writes it when a run "
                         "finishes)")
    try:
        env = gym.make(config["env"], action_mode=config["action_mode"], **env_kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{config_path}: {config['env']} does not accept its env_kwargs "
                         f"({exc})") from None
    spaces = {"observation": env.observation_space, "action": env.action_space}
    env.close()
    try:
        _check_policy_fits(config["hyperparams"], spaces["observation"], spaces["action"],
                           config["action_mode"])
    except ValueError as exc:
        raise ValueError(f"{config_path}: hyperparams.{exc}") from None
    if not isinstance(config.get("normalized", False), bool):
        raise ValueError(f"{config_path}: field 'normalized' must be true or false")
    recorded = config.get("spaces")
    for name, space in spaces.items():
        mine = recorded.get(name) if isinstance(recorded, dict) else None
        if mine != space_record(space):
            shape = mine.get("shape") if isinstance(mine, dict) else None
            was = (f"shape {tuple(shape)}" if isinstance(shape, list) and len(shape) < 9
                   else "missing or malformed")
            raise ValueError(f"{config_path}: the run's {name} space ({was}) is not the one "
                             f"{config['env']} ({config['action_mode']}) gives: shape "
                             f"{space.shape}, {space.dtype}, its bounds")
    return {**config, "observation_shape": spaces["observation"].shape,
            "action_shape": spaces["action"].shape, "_spaces": spaces}


#: Prefixes of a SAC policy's weights that acting does not use (its critics): a SAC weights
#: file may hold all of them or none (the actor alone, as a shipped agent does).
CRITIC_KEYS = ("critic.", "critic_target.")


def load_policy(config: dict[str, Any], path: Path) -> BasePolicy:
    """The SB3 policy of a run (``config`` from :func:`read_run`), rebuilt from its settings
    and spaces, with the weights in ``path`` read by PyTorch's ``weights_only`` loading (no
    code runs); ValueError naming the file if they are not weights of that policy. A SAC
    file may leave out the critics (:data:`CRITIC_KEYS`): the policy then acts as the run's
    did, and its critics are untrained."""
    import torch

    hp = config["hyperparams"]
    policy_class = _policy_class(config["algo"], hp)
    spaces = config["_spaces"]
    observation = spaces["observation"]
    stack = hp.get("frame_stack", 1)
    if stack > 1:  # (the policy saw the last frames along the last axis: VecFrameStack's)
        observation = gym.spaces.Box(np.repeat(observation.low, stack, axis=-1),
                                     np.repeat(observation.high, stack, axis=-1),
                                     dtype=observation.dtype)
    if _is_image(spaces["observation"]):  # (trained channel-first: SB3 transposes images)
        from stable_baselines3.common.vec_env import VecTransposeImage

        observation = VecTransposeImage.transpose_space(observation)
    policy = policy_class(observation, spaces["action"], lambda _: 0.0,
                          **hp.get("policy_kwargs", {}))
    try:
        with warnings.catch_warnings():  # (torch's notes on a file it then refuses)
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # (weights_only refuses anything but tensors and containers)
        words = " ".join(str(exc).split())[:300]
        raise ValueError(f"{path} is not a weights file of cparticles train ({words})") from None
    if not (isinstance(state, dict)
            and all(isinstance(k, str) and isinstance(v, torch.Tensor)
                    for k, v in state.items())):
        raise ValueError(f"{path} is not a weights file of cparticles train (not a dict of "
                         "tensors)")
    expected = {k: tuple(v.shape) for k, v in policy.state_dict().items()}
    given = {k: tuple(v.shape) for k, v in state.items()}
    if config["algo"] == "sac" and not any(k.startswith(CRITIC_KEYS) for k in given):
        # (an acting policy: SAC's critics, kept out of a shipped agent, are not needed to
        # act; they keep their initial values)
        state = {**{k: v for k, v in policy.state_dict().items()
                    if k.startswith(CRITIC_KEYS)}, **state}
        expected = {k: v for k, v in expected.items() if not k.startswith(CRITIC_KEYS)}
    wrong = ([f"{k} missing" for k in expected if k not in given]
             + [f"{k} unknown" for k in given if k not in expected]
             + [f"{k} has shape {given[k]}, the policy's {shape}"
                for k, shape in expected.items() if k in given and given[k] != shape])
    if wrong:
        raise ValueError(f"{path} does not hold the weights of the run's policy "
                         f"({'; '.join(wrong[:3])}{'; ...' if len(wrong) > 3 else ''})")
    try:
        policy.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        words = " ".join(str(exc).split())[:300]
        raise ValueError(f"{path} does not hold the weights of the run's policy "
                         f"({words})") from None
    policy.set_training_mode(False)
    return policy


def evaluate(out: str | Path, episodes: int = 100, seed_start: int = HELD_OUT_SEED_START,
             deterministic: bool = True, which: str = "final", *,
             env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Play ``episodes`` episodes (seeds from ``seed_start``) with the run in ``out``
    (``which``: ``"final"`` or ``"best"`` model). A stochastic evaluation
    (``deterministic=False``) samples its actions from torch's generator seeded with
    ``seed_start``, so that it too gives the same figures every time. Returns
    :func:`summarize` plus the run's identity (env, action_mode, algo, seed, timesteps).
    ``env_kwargs`` change the env the run trained on (a variant), over its own: the
    observation and action spaces must stay the run's (ValueError otherwise).

    Nothing stored in the directory can run code: :func:`read_run` checks ``config.json``
    (JSON), the policy is rebuilt from its settings and the weights read with ``weights_only``
    (:func:`load_policy`), the observation statistics read as plain arrays
    (:class:`ObsNormalizer`); the pickles an older ``train`` wrote are never opened.
    """
    require("stable_baselines3", "torch", command="envs.train.evaluate")
    import torch
    with torch.random.fork_rng(devices=[]):  # (the caller's torch generator left as it was)
        return _evaluate(out, episodes, seed_start, deterministic, which, env_kwargs)


def _evaluate(out: str | Path, episodes: int, seed_start: int, deterministic: bool,
              which: str, env_kwargs: dict[str, Any] | None) -> dict[str, Any]:
    """:func:`evaluate`, inside its own torch generator state."""
    import torch
    config = read_run(out, which)
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    if seed_start < 0:
        raise ValueError(f"seed_start must be >= 0, got {seed_start}")
    out = Path(out)
    policy = load_policy(config, out / POLICY_FILES[which])
    normalizer = None
    norm_path = out / NORMALIZATION_FILES[which]
    if config.get("normalized", norm_path.exists()):
        if not norm_path.is_file():
            raise ValueError(f"{str(out)!r} has no {norm_path.name} (its config.json says the "
                             "observations were normalized)")
        shape = tuple(config["observation_shape"])
        stack = config["hyperparams"].get("frame_stack", 1)
        normalizer = ObsNormalizer.load(norm_path, (*shape[:-1], shape[-1] * stack))
    kwargs = {**config["hyperparams"].get("env_kwargs", {}), **(env_kwargs or {})}
    if env_kwargs:
        check_env_kwargs(config["env"], env_kwargs)
        env = gym.make(config["env"], action_mode=config["action_mode"], **kwargs)
        spaces = (space_record(env.observation_space), space_record(env.action_space))
        env.close()
        if spaces != (config["spaces"]["observation"], config["spaces"]["action"]):
            raise ValueError(f"env_kwargs: {env_kwargs} change the observation or action "
                             f"space the run was trained on")
        drag = config["hyperparams"].get("policy_kwargs", {}).get("drag")
        if drag is not None and (now := drag_geometry(config["env"], kwargs)) != drag:
            def shown(d: dict[str, float]) -> str:
                return ", ".join(f"{k} {v:.4g}" for k, v in d.items())
            raise ValueError(f"env_kwargs: {env_kwargs} change the drag geometry (the "
                             f"gripper's largest move, where it grips and lets go) that the "
                             f"run's PointerPolicy was trained with ({shown(drag)}; with "
                             f"them: {shown(now)})")
    torch.manual_seed(seed_start)  # stochastic actions: the same noise on every call
    limit = config["hyperparams"].get("max_episode_steps")
    res = run_episodes(sb3_policy(policy, normalizer, deterministic), config["env"], episodes,
                       seed_start, config["action_mode"], kwargs,
                       frame_stack=config["hyperparams"].get("frame_stack", 1),
                       max_episode_steps=limit)
    return {"env": config["env"], "action_mode": config["action_mode"],
            **({"env_kwargs": kwargs} if kwargs else {}),
            **({"max_episode_steps": limit} if limit is not None else {}),
            "algo": config["algo"], "seed": config["seed"], "timesteps": config["timesteps"],
            "model": which, "deterministic": deterministic, "seed_start": seed_start,
            **summarize(res)}


def convert_run(out: str | Path) -> list[str]:
    """Convert a run directory of an older ``train`` (``model.zip``, ``vecnormalize.pkl``,
    their ``best_`` twins: pickles) in place to the current :data:`FORMAT`: **this loads the
    pickles, which runs any code they hold; only for directories you trust.** Writes the
    policy and normalization files and a new ``config.json`` (the old one kept as
    ``config.v1.json``); the pickles stay. Returns the names of the files written."""
    require("stable_baselines3", "torch", command="envs.train.convert_run")
    import pickle

    out = Path(out)
    config = check_convertible(out)
    config_path = out / "config.json"
    cls = _algo_class(config["algo"])
    written = []
    for which, prefix in (("final", ""), ("best", "best_")):
        zipped = out / f"{prefix}model.zip"
        if not zipped.is_file():
            continue
        model = cls.load(zipped, device="cpu")  # (the trusted pickles: code runs here)
        save_policy(model, out / POLICY_FILES[which])
        written.append(POLICY_FILES[which])
        pkl = out / f"{prefix}vecnormalize.pkl"
        if pkl.is_file():
            with open(pkl, "rb") as f:
                save_normalization(pickle.load(f), out / NORMALIZATION_FILES[which])
            written.append(NORMALIZATION_FILES[which])
    spaces = {"observation": space_record(model.observation_space),
              "action": space_record(model.action_space)}
    new = {"format": FORMAT, **config, "spaces": spaces,
           "normalized": (out / NORMALIZATION_FILES["final"]).exists()}
    shutil.copyfile(config_path, out / "config.v1.json")
    config_path.write_text(json.dumps(new, indent=1))
    return [*written, "config.json"]


def check_convertible(out: Path) -> dict[str, Any]:
    """The ``config.json`` of a run directory of an older ``train`` (read as JSON, nothing
    else opened); ValueError unless there is one to convert."""
    config_path = out / "config.json"
    if not out.is_dir() or not config_path.is_file():
        raise ValueError(f"{str(out)!r} is not a run directory of cparticles train (no "
                         "config.json)")
    config = _read_config(config_path)
    if not isinstance(config, dict):
        raise ValueError(f"{config_path} is not a JSON object")
    if "format" in config:
        raise ValueError(f"{str(out)!r} is already of format {config['format']!r}: nothing to "
                         "convert")
    if config.get("algo") not in ALGOS:
        raise ValueError(f"{config_path}: algo must be one of {ALGOS}, got "
                         f"{config.get('algo')!r}")
    if not (out / "model.zip").is_file():
        raise ValueError(f"{str(out)!r} has no model.zip to convert")
    return config
