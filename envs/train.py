"""``cparticles train`` and ``cparticles evaluate``: Stable-Baselines3 baselines on the envs.

    cparticles train ClothSlide-v0 --algo ppo --seed 0 --out runs/cloth-ppo-0
    cparticles evaluate runs/cloth-ppo-0 --episodes 100 --seed-start 2000000 --json

``train`` reads the shipped hyperparameters (``envs/hyperparams/{ppo,sac}.json``, one entry per
``"<env id>/<action mode>"``, in the style of rl-baselines3-zoo), builds the training env (the
native vector env through :func:`envs.sb3.to_sb3` when ``n_envs > 1``, as PPO wants; a single
env otherwise, as SAC wants), optionally wraps it in ``VecNormalize``, and trains with a progress
bar. Every ``--eval-freq`` steps it runs deterministic evaluation episodes on seeds from
``EVAL_SEED_START`` and appends them to ``DIR/evaluations.json``; it saves ``DIR/model.zip``,
``DIR/vecnormalize.pkl`` (if used), ``DIR/best_model.zip`` (best periodic evaluation) and
``DIR/config.json`` (what was run, how long it took).

``evaluate`` loads a run directory and plays ``--episodes`` episodes with seeds ``--seed-start``,
``--seed-start + 1``, ... (keep them away from the training and periodic-evaluation seeds:
``HELD_OUT_SEED_START`` is the convention of ``docs/baselines``), deterministic unless
``--stochastic``, and prints a summary; the last line of the output is one JSON object with
``success_rate``, ``mean_return``, ``mean_length``, ``episodes`` and diagnostics (for
ClothSlide: the mean |squeeze| of the actions, the RMS speed near the goal, final distances and
speeds of failed episodes).

Requires the ``rl`` extra (stable-baselines3, torch).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from . import ENV_IDS
from .base import ACTION_MODES

#: Algorithms ``cparticles train`` knows (Stable-Baselines3 classes).
ALGOS = ("ppo", "sac")
#: Folder of the shipped hyperparameter files, ``<algo>.json``.
HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"
#: Seeds of the periodic evaluation episodes during training.
EVAL_SEED_START = 1_000_000
#: First seed of held-out evaluation episodes (the convention of docs/baselines).
HELD_OUT_SEED_START = 2_000_000
#: Distance (m) from the goal within which ``evaluate`` measures the RMS speed.
NEAR_GOAL = 0.1
#: Keys of a hyperparameter entry that ``train`` consumes itself (the rest go to the algorithm).
OWN_KEYS = ("n_envs", "n_timesteps", "normalize", "normalize_reward", "policy", "env_kwargs")


def _algo_class(algo: str) -> type:
    from stable_baselines3 import PPO, SAC

    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return {"ppo": PPO, "sac": SAC}[algo]


def load_hyperparams(algo: str, env_id: str, action_mode: str = "force") -> dict[str, Any]:
    """The shipped hyperparameters of ``algo`` for ``env_id`` in ``action_mode`` (a copy)."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    if env_id not in ENV_IDS:
        raise ValueError(f"env_id must be one of {ENV_IDS}, got {env_id!r}")
    if action_mode not in ACTION_MODES:
        raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
    table = json.loads((HYPERPARAMS_DIR / f"{algo}.json").read_text())
    key = f"{env_id}/{action_mode}"
    if key not in table:
        raise ValueError(f"no {algo} hyperparameters for {key} in {HYPERPARAMS_DIR}")
    return json.loads(json.dumps(table[key]))


def make_train_env(env_id: str, action_mode: str, n_envs: int, seed: int,
                   env_kwargs: dict[str, Any] | None = None) -> Any:
    """An SB3 ``VecEnv`` for training, with episode statistics (``VecMonitor``).

    ``n_envs > 1``: the native vector env (all copies one particle system) through
    :func:`envs.sb3.to_sb3`; ``n_envs == 1``: a ``DummyVecEnv`` of one single env. Copy ``i``'s
    first episode is seeded with ``seed + i``.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    from .sb3 import to_sb3

    kwargs = dict(env_kwargs or {}, action_mode=action_mode)
    if n_envs > 1:
        venv = to_sb3(gym.make_vec(env_id, num_envs=n_envs,
                                   vectorization_mode="vector_entry_point", **kwargs))
    else:
        venv = DummyVecEnv([lambda: gym.make(env_id, **kwargs)])
    venv = VecMonitor(venv)
    venv.seed(seed)
    return venv


Policy = Callable[[np.ndarray], np.ndarray]


def run_episodes(policy: Policy, env_id: str, episodes: int, seed_start: int,
                 action_mode: str = "force", env_kwargs: dict[str, Any] | None = None,
                 batch: int = 100) -> dict[str, Any]:
    """Play ``episodes`` episodes (seeds ``seed_start + k``) with ``policy`` (batched raw
    observations -> actions) in native vector envs of up to ``batch`` copies.

    Returns the per-episode arrays ``return``, ``length``, ``success``, ``final_distance`` (m),
    ``final_speed`` (m/s), and the summaries ``mean_abs_squeeze`` (N, ClothSlide force mode, else
    None) and ``rms_speed_near_goal`` (m/s, RMS particle speed over all steps within
    ``NEAR_GOAL`` m of the goal, None if there were none).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    keys = ("return", "length", "success", "final_distance", "final_speed")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    squeeze: list[np.ndarray] = []
    near: list[np.ndarray] = []
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                           action_mode=action_mode, **(env_kwargs or {}))
        task = env.unwrapped.task
        obs, _ = env.reset(seed=seed_start + start)
        ret, length = np.zeros(n), np.zeros(n, dtype=np.int64)
        success, done = np.zeros(n, bool), np.zeros(n, bool)
        dist, speed = np.zeros(n), np.zeros(n)
        while not done.all():
            obs, reward, terminated, truncated, info = env.step(policy(obs))
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
            done |= ended
        env.close()
        for k, v in zip(keys, (ret, length, success, dist, speed), strict=True):
            out[k].append(v)
    res: dict[str, Any] = {k: np.concatenate(v) for k, v in out.items()}
    res["mean_abs_squeeze"] = float(np.mean(np.concatenate(squeeze))) if squeeze else None
    near_all = np.concatenate(near) if near else np.zeros(0)
    res["rms_speed_near_goal"] = (float(np.sqrt(np.mean(near_all**2))) if near_all.size
                                  else None)
    return res


def summarize(res: dict[str, Any]) -> dict[str, Any]:
    """The JSON-able summary of :func:`run_episodes`."""
    fail = ~res["success"]
    return {"episodes": int(len(res["success"])),
            "success_rate": float(res["success"].mean()),
            "mean_return": float(res["return"].mean()),
            "mean_length": float(res["length"].mean()),
            "mean_abs_squeeze": res["mean_abs_squeeze"],
            "rms_speed_near_goal": res["rms_speed_near_goal"],
            "failures_final_distance": res["final_distance"][fail].round(4).tolist(),
            "failures_final_speed": res["final_speed"][fail].round(4).tolist()}


def sb3_policy(model: Any, obs_normalizer: Any = None, deterministic: bool = True) -> Policy:
    """A batched policy from an SB3 model and (optionally) a ``VecNormalize`` whose observation
    statistics it applies."""
    def policy(obs: np.ndarray) -> np.ndarray:
        o = obs if obs_normalizer is None else obs_normalizer.normalize_obs(obs)
        action, _ = model.predict(o, deterministic=deterministic)
        return action
    return policy


def _callback(out: Path, env_id: str, action_mode: str, env_kwargs: dict[str, Any],
              eval_freq: int, eval_episodes: int, started: float) -> Any:
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
            vn = self.model.get_vec_normalize_env()
            res = run_episodes(sb3_policy(self.model, vn), env_id, eval_episodes,
                               EVAL_SEED_START, action_mode, env_kwargs)
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
                self.model.save(out / "best_model.zip")
                if vn is not None:
                    vn.save(str(out / "best_vecnormalize.pkl"))
            print(f"eval @ {rec['timesteps']} steps: success {s['success_rate']:.0%}, "
                  f"return {s['mean_return']:.2f}, length {s['mean_length']:.0f} "
                  f"({rec['seconds']:.0f} s)", file=sys.stderr, flush=True)

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += eval_freq
                self.evaluate_now()
            return True

    return PeriodicEvaluation()


def train(env_id: str, algo: str, seed: int, out: str | Path, action_mode: str = "force",
          timesteps: int | None = None, eval_freq: int | None = None, eval_episodes: int = 50,
          progress_bar: bool = True, threads: int = 1, verbose: int = 0) -> dict[str, Any]:
    """Train ``algo`` on ``env_id`` with the shipped hyperparameters; write the run to ``out``.

    ``timesteps`` overrides the file's ``n_timesteps``; ``eval_freq`` (env steps, default a
    tenth of the budget) and ``eval_episodes`` set the periodic evaluation. ``threads`` caps
    torch's CPU threads. Returns the contents of ``out/config.json``.
    """
    import stable_baselines3
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    hp = load_hyperparams(algo, env_id, action_mode)
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
    torch.set_num_threads(threads)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    env_kwargs = dict(hp.get("env_kwargs", {}))
    n_envs = int(hp.get("n_envs", 1))
    venv = make_train_env(env_id, action_mode, n_envs, seed, env_kwargs)
    kwargs = {k: v for k, v in hp.items() if k not in OWN_KEYS}
    if hp.get("normalize", False):
        venv = VecNormalize(venv, norm_obs=True, norm_reward=hp.get("normalize_reward", True),
                            gamma=kwargs.get("gamma", 0.99))
    started = time.perf_counter()
    cls = _algo_class(algo)
    model = cls(hp.get("policy", "MlpPolicy"), venv, seed=seed, verbose=verbose, **kwargs)
    callback = _callback(out, env_id, action_mode, env_kwargs, eval_freq, eval_episodes, started)
    model.learn(total_timesteps=timesteps, callback=callback, progress_bar=progress_bar)
    if not callback.records or callback.records[-1]["timesteps"] < timesteps:
        callback.evaluate_now()
    seconds = time.perf_counter() - started
    model.save(out / "model.zip")
    vn = model.get_vec_normalize_env()
    if vn is not None:
        vn.save(str(out / "vecnormalize.pkl"))
    config = {"env": env_id, "action_mode": action_mode, "algo": algo, "seed": seed,
              "timesteps": int(model.num_timesteps), "hyperparams": hp,
              "wall_seconds": round(seconds, 1), "threads": threads,
              "versions": {"stable_baselines3": stable_baselines3.__version__,
                           "torch": torch.__version__, "gymnasium": gym.__version__}}
    (out / "config.json").write_text(json.dumps(config, indent=1))
    venv.close()
    return config


def evaluate(out: str | Path, episodes: int = 100, seed_start: int = HELD_OUT_SEED_START,
             deterministic: bool = True, which: str = "final") -> dict[str, Any]:
    """Play ``episodes`` episodes (seeds from ``seed_start``) with the run in ``out``
    (``which``: ``"final"`` model.zip or ``"best"`` best_model.zip). Returns :func:`summarize`
    plus the run's identity (env, action_mode, algo, seed, timesteps)."""
    out = Path(out)
    if which not in ("final", "best"):
        raise ValueError(f"which must be 'final' or 'best', got {which!r}")
    config_path = out / "config.json"
    if not config_path.is_file():
        raise ValueError(f"{out} is not a training run directory (no config.json)")
    config = json.loads(config_path.read_text())
    prefix = "" if which == "final" else "best_"
    model = _algo_class(config["algo"]).load(out / f"{prefix}model.zip", device="cpu")
    normalizer = None
    vn_path = out / f"{prefix}vecnormalize.pkl"
    if vn_path.is_file():
        with open(vn_path, "rb") as f:
            normalizer = pickle.load(f)
    res = run_episodes(sb3_policy(model, normalizer, deterministic), config["env"], episodes,
                       seed_start, config["action_mode"],
                       config["hyperparams"].get("env_kwargs", {}))
    return {"env": config["env"], "action_mode": config["action_mode"],
            "algo": config["algo"], "seed": config["seed"], "timesteps": config["timesteps"],
            "model": which, "deterministic": deterministic, "seed_start": seed_start,
            **summarize(res)}


# ---------------------------------------------------------------------- command line
def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles train``."""
    parser.add_argument("env", choices=ENV_IDS, metavar="ENV_ID", help="environment id")
    parser.add_argument("--algo", choices=ALGOS, default="ppo", help="SB3 algorithm")
    parser.add_argument("--seed", type=int, default=0, help="seed of the model and env copies")
    parser.add_argument("--out", required=True, help="run directory (created)")
    parser.add_argument("--action-mode", default="force", choices=ACTION_MODES)
    parser.add_argument("--timesteps", type=int, help="env steps (default: the shipped budget)")
    parser.add_argument("--eval-freq", type=int, help="env steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=50,
                        help="episodes per periodic evaluation")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles evaluate``."""
    parser.add_argument("dir", help="run directory written by cparticles train")
    parser.add_argument("--episodes", type=int, default=100, help="number of episodes")
    parser.add_argument("--seed-start", type=int, default=HELD_OUT_SEED_START,
                        help="seed of the first episode (then +1 each)")
    parser.add_argument("--stochastic", action="store_true",
                        help="sample actions instead of the deterministic policy")
    parser.add_argument("--best", action="store_true",
                        help="use best_model.zip (best periodic evaluation), not model.zip")
    parser.add_argument("--json", action="store_true", help="print only the JSON line")


def main_train(args: argparse.Namespace) -> int:
    """``cparticles train``."""
    config = train(args.env, args.algo, args.seed, args.out, args.action_mode, args.timesteps,
                   args.eval_freq, args.eval_episodes, progress_bar=not args.no_progress,
                   threads=args.threads)
    print(f"trained {config['algo']} on {config['env']} ({config['action_mode']}), seed "
          f"{config['seed']}, {config['timesteps']} steps in {config['wall_seconds']:.0f} s; "
          f"saved to {args.out}")
    return 0


def main_evaluate(args: argparse.Namespace) -> int:
    """``cparticles evaluate``: a summary, then one JSON line (the last line of the output)."""
    res = evaluate(args.dir, args.episodes, args.seed_start, not args.stochastic,
                   "best" if args.best else "final")
    if not args.json:
        print(f"# {res['algo']} on {res['env']} ({res['action_mode']}), seed {res['seed']}, "
              f"{'best' if args.best else 'final'} model, "
              f"{'deterministic' if res['deterministic'] else 'stochastic'}, seeds "
              f"{args.seed_start}..{args.seed_start + args.episodes - 1}")
        print(f"success rate {res['success_rate']:.0%}, mean return {res['mean_return']:.2f}, "
              f"mean length {res['mean_length']:.1f} steps")
    print(json.dumps(res))
    return 0


def add_parsers(subparsers: Any) -> None:
    """Register ``train`` and ``evaluate`` on an argparse subparsers object."""
    p = subparsers.add_parser("train", help="train a Stable-Baselines3 agent (rl extra)",
                              description="train a Stable-Baselines3 agent with the shipped "
                                          "hyperparameters")
    add_train_arguments(p)
    p.set_defaults(handler=main_train)
    p = subparsers.add_parser("evaluate", help="evaluate a trained run on held-out episodes",
                              description="evaluate a run directory of cparticles train")
    add_evaluate_arguments(p)
    p.set_defaults(handler=main_evaluate)
