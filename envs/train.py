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

**A run directory holds pickles.** ``model.zip`` and ``best_model.zip`` (Stable-Baselines3
archives, which hold cloudpickled objects) and ``vecnormalize.pkl`` run code when they are
loaded, so a crafted run directory can run any program. ``evaluate`` loads only what looks like
a directory ``train`` wrote: it reads ``config.json`` first (no pickle involved) and refuses a
directory without one, with an unknown env, action mode or algorithm, without the model file, or
whose recorded observation shape does not match its env, all before unpickling anything. That
check stops mistakes, not an attacker who writes a matching ``config.json``: evaluate only run
directories you made yourself or otherwise trust.

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

from constrained_particles.arguments import int_at_least, new_directory
from constrained_particles.extras import require

from . import ENV_IDS
from .base import ACTION_MODES
from .cloth_pin import DRAW_MODES

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
#: The action modes each env takes, its default first (``train`` ships hyperparameters for each).
ENV_ACTION_MODES: dict[str, tuple[str, ...]] = {
    env_id: DRAW_MODES if env_id == "ClothPin-v1" else ACTION_MODES for env_id in ENV_IDS}
#: Largest ``--seed`` (the seeds of the env copies follow it; numpy's legacy seeding, which
#: Stable-Baselines3 uses, takes at most 2**32 - 1).
MAX_SEED = 2**31 - 1
#: What ``config.json`` of a run holds, with the types ``evaluate`` checks before loading.
CONFIG_FIELDS: dict[str, type] = {
    "env": str, "action_mode": str, "algo": str, "seed": int, "timesteps": int,
    "hyperparams": dict}


def _algo_class(algo: str) -> type:
    from stable_baselines3 import PPO, SAC

    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return {"ppo": PPO, "sac": SAC}[algo]


def check_env_mode(env_id: str, action_mode: str | None) -> str:
    """The action mode to use (``None``: the env's default); ValueError naming the argument if
    ``env_id`` is not a registered id or does not take ``action_mode``."""
    if env_id not in ENV_ACTION_MODES:
        raise ValueError(f"env_id must be one of {ENV_IDS}, got {env_id!r}")
    modes = ENV_ACTION_MODES[env_id]
    if action_mode is None:
        return modes[0]
    if action_mode not in modes:
        raise ValueError(f"action_mode: {env_id} takes {' or '.join(modes)}, "
                         f"got {action_mode!r}")
    return action_mode


def load_hyperparams(algo: str, env_id: str, action_mode: str | None = None) -> dict[str, Any]:
    """The shipped hyperparameters of ``algo`` for ``env_id`` in ``action_mode`` (None: the
    env's default mode), a copy."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    action_mode = check_env_mode(env_id, action_mode)
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


def train(env_id: str, algo: str, seed: int, out: str | Path, action_mode: str | None = None,
          timesteps: int | None = None, eval_freq: int | None = None, eval_episodes: int = 50,
          progress_bar: bool = True, threads: int = 1, verbose: int = 0) -> dict[str, Any]:
    """Train ``algo`` on ``env_id`` with the shipped hyperparameters; write the run to ``out``.

    ``action_mode`` None takes the env's default. ``timesteps`` overrides the file's
    ``n_timesteps``; ``eval_freq`` (env steps, default a tenth of the budget) and
    ``eval_episodes`` set the periodic evaluation. ``threads`` caps torch's CPU threads.
    Returns the contents of ``out/config.json``.
    """
    import stable_baselines3
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    action_mode = check_env_mode(env_id, action_mode)
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
    if not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be in [0, {MAX_SEED}], got {seed}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
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
              "observation_shape": list(venv.observation_space.shape),
              "action_shape": list(venv.action_space.shape),
              "wall_seconds": round(seconds, 1), "threads": threads,
              "versions": {"stable_baselines3": stable_baselines3.__version__,
                           "torch": torch.__version__, "gymnasium": gym.__version__}}
    (out / "config.json").write_text(json.dumps(config, indent=1))
    venv.close()
    return config


def read_run(out: str | Path, which: str = "final") -> dict[str, Any]:
    """The ``config.json`` of a run directory that ``train`` wrote, checked before anything in
    the directory is unpickled: ValueError unless ``out`` holds a config.json with the fields
    ``train`` writes, a registered env with an action mode it takes, a known algorithm, the
    model file of ``which`` (``"final"``: model.zip, ``"best"``: best_model.zip), and (when
    recorded) the observation and action shapes that env gives."""
    out = Path(out)
    if which not in ("final", "best"):
        raise ValueError(f"which must be 'final' or 'best', got {which!r}")
    if not out.is_dir():
        raise ValueError(f"{str(out)!r} is not a directory")
    config_path = out / "config.json"
    if not config_path.is_file():
        raise ValueError(f"{str(out)!r} is not a run directory of cparticles train "
                         "(no config.json)")
    try:
        config = json.loads(config_path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read {config_path} ({exc.strerror or exc})") from None
    except ValueError as exc:  # also UnicodeDecodeError
        raise ValueError(f"{config_path} is not valid JSON ({exc})") from None
    if not isinstance(config, dict):
        raise ValueError(f"{config_path} is not a JSON object")
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
    model = out / ("model.zip" if which == "final" else "best_model.zip")
    if not model.is_file():
        raise ValueError(f"{str(out)!r} has no {model.name} (train writes it when a run "
                         "finishes; was it interrupted?)")
    try:
        env = gym.make(config["env"], action_mode=config["action_mode"], **env_kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{config_path}: {config['env']} does not accept its env_kwargs "
                         f"({exc})") from None
    shapes = {"observation_shape": env.observation_space.shape,
              "action_shape": env.action_space.shape}
    env.close()
    for name, shape in shapes.items():
        if name in config and tuple(config[name]) != shape:
            raise ValueError(f"{config_path}: the run's {name.replace('_', ' ')} is "
                             f"{tuple(config[name])}, but {config['env']} "
                             f"({config['action_mode']}) gives {shape}")
    return {**config, **shapes}


def _check_spaces(config: dict[str, Any], model: Any, normalizer: Any) -> None:
    """ValueError if the loaded model or normalizer was made for other observations or actions
    than the env of ``config`` (a run directory assembled from different runs)."""
    for what, space, shape in (("model", model.observation_space, config["observation_shape"]),
                               ("model", model.action_space, config["action_shape"]),
                               ("vecnormalize.pkl",
                                getattr(normalizer, "observation_space", None),
                                config["observation_shape"])):
        if space is not None and tuple(space.shape) != tuple(shape):
            raise ValueError(f"the run's {what} expects shape {tuple(space.shape)}, but "
                             f"{config['env']} ({config['action_mode']}) gives {tuple(shape)}")


def evaluate(out: str | Path, episodes: int = 100, seed_start: int = HELD_OUT_SEED_START,
             deterministic: bool = True, which: str = "final") -> dict[str, Any]:
    """Play ``episodes`` episodes (seeds from ``seed_start``) with the run in ``out``
    (``which``: ``"final"`` model.zip or ``"best"`` best_model.zip). Returns :func:`summarize`
    plus the run's identity (env, action_mode, algo, seed, timesteps).

    The run's files are pickles that run code when loaded: :func:`read_run` checks
    ``config.json`` first, but only load directories you trust (see the module docstring).
    """
    config = read_run(out, which)
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    if seed_start < 0:
        raise ValueError(f"seed_start must be >= 0, got {seed_start}")
    out = Path(out)
    prefix = "" if which == "final" else "best_"
    model = _algo_class(config["algo"]).load(out / f"{prefix}model.zip", device="cpu")
    normalizer = None
    vn_path = out / f"{prefix}vecnormalize.pkl"
    if vn_path.is_file():
        with open(vn_path, "rb") as f:
            normalizer = pickle.load(f)
    _check_spaces(config, model, normalizer)
    res = run_episodes(sb3_policy(model, normalizer, deterministic), config["env"], episodes,
                       seed_start, config["action_mode"],
                       config["hyperparams"].get("env_kwargs", {}))
    return {"env": config["env"], "action_mode": config["action_mode"],
            "algo": config["algo"], "seed": config["seed"], "timesteps": config["timesteps"],
            "model": which, "deterministic": deterministic, "seed_start": seed_start,
            **summarize(res)}


# ---------------------------------------------------------------------- command line
TRUST = ("A run directory holds pickles (model.zip, best_model.zip, vecnormalize.pkl) that run "
         "code when loaded: evaluate only directories that cparticles train wrote and that you "
         "trust. config.json is checked before anything is unpickled.")


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles train``."""
    modes = "; ".join(f"{e}: {', '.join(m)}" for e, m in ENV_ACTION_MODES.items())
    parser.add_argument("env", choices=ENV_IDS, metavar="ENV_ID",
                        help=f"environment id: {', '.join(ENV_IDS)}")
    parser.add_argument("--algo", choices=ALGOS, default="ppo", help="SB3 algorithm")
    parser.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0,
                        help="seed of the model; env copy i starts from seed + i")
    parser.add_argument("--out", required=True, type=new_directory,
                        help="run directory (created; must not hold a run already)")
    parser.add_argument("--action-mode", choices=sorted({m for v in ENV_ACTION_MODES.values()
                                                         for m in v}),
                        help=f"action mode ({modes}) (default: the env's first)")
    parser.add_argument("--timesteps", type=int_at_least(1),
                        help="env steps (default: the shipped budget of the env, mode and algo)")
    parser.add_argument("--eval-freq", type=int_at_least(1),
                        help="env steps between evaluations (default: a tenth of --timesteps)")
    parser.add_argument("--eval-episodes", type=int_at_least(1), default=50,
                        help="episodes per periodic evaluation")
    parser.add_argument("--threads", type=int_at_least(1), default=1, help="torch CPU threads")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def check_train_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Before any work: an action mode the env takes, shipped hyperparameters, an ``--out``
    that holds no run yet, then the rl extra (argument mistakes are reported either way)."""
    modes = ENV_ACTION_MODES[args.env]
    if args.action_mode is None:
        args.action_mode = modes[0]
    if args.action_mode not in modes:
        parser.error(f"argument --action-mode: {args.env} takes {' or '.join(modes)}, "
                     f"got {args.action_mode!r}")
    try:
        load_hyperparams(args.algo, args.env, args.action_mode)
    except ValueError as exc:
        parser.error(str(exc))
    for name in ("config.json", "model.zip"):
        if (Path(args.out) / name).exists():
            parser.error(f"argument --out: {args.out!r} already holds a run ({name}); choose "
                         "another directory")
    require("stable_baselines3", "torch", command="cparticles train")


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles evaluate``."""
    parser.description = ("evaluate a run directory that cparticles train wrote, on held-out "
                          f"episodes (rl extra). {TRUST}")
    parser.add_argument("dir", help="run directory written by cparticles train (trusted: it "
                        "holds pickles)")
    parser.add_argument("--episodes", type=int_at_least(1), default=100,
                        help="number of episodes")
    parser.add_argument("--seed-start", type=int_at_least(0), default=HELD_OUT_SEED_START,
                        help="seed of the first episode (then +1 each)")
    parser.add_argument("--stochastic", action="store_true",
                        help="sample actions instead of the deterministic policy")
    parser.add_argument("--best", action="store_true",
                        help="use best_model.zip (best periodic evaluation), not model.zip")
    parser.add_argument("--json", action="store_true", help="print only the JSON line")


def check_evaluate_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace
                             ) -> None:
    """Before any work: a run directory :func:`read_run` accepts, then the rl extra."""
    try:
        read_run(args.dir, "best" if args.best else "final")
    except ValueError as exc:
        parser.error(f"argument dir: {exc}")
    require("stable_baselines3", "torch", command="cparticles evaluate")


def main_train(args: argparse.Namespace) -> int:
    """``cparticles train``; a directory it created stays only if something was written."""
    out = Path(args.out)
    created = not out.exists()
    try:
        config = train(args.env, args.algo, args.seed, out, args.action_mode, args.timesteps,
                       args.eval_freq, args.eval_episodes, progress_bar=not args.no_progress,
                       threads=args.threads)
    finally:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
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
