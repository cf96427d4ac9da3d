"""The command lines of :mod:`envs.train`: ``cparticles train``, ``evaluate`` and
``convert-run`` (arguments checked before any work, then the jobs of :mod:`envs.train`)."""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from constrained_particles.arguments import int_at_least, key_values, new_directory
from constrained_particles.extras import require

from . import pretrained
from .task import check_env_kwargs, task_spec, task_specs, variant_key
from .train import (
    ALGOS,
    HELD_OUT_SEED_START,
    MAX_SEED,
    OLD_FILES,
    POLICY_FILES,
    _check_policy_fits,
    _check_policy_settings,
    check_convertible,
    check_episode_steps,
    check_explore,
    check_imitate,
    check_overrides,
    convert_run,
    evaluate,
    load_hyperparams,
    read_run,
    train,
)

TRUST = ("A run directory holds data only (config.json, the policy weights, the observation "
         "statistics as plain arrays): evaluate runs no code stored in it. A directory of an "
         "older train (model.zip, vecnormalize.pkl: pickles) is refused; convert one you "
         "trust with cparticles convert-run.")


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles train``."""
    specs = task_specs()
    ids = [spec.id for spec in specs]
    modes = "; ".join(f"{spec.id}: {', '.join(spec.action_modes)}" for spec in specs)
    parser.add_argument("env", choices=ids, metavar="ENV_ID",
                        help=f"environment id: {', '.join(ids)}")
    other = [f"{spec.default_algo()} for {spec.id}" for spec in specs
             if spec.default_algo() != "ppo"]
    parser.add_argument("--algo", choices=ALGOS,
                        help="SB3 algorithm (default: the one the task ships first: "
                        f"{', '.join(other + ['ppo for the others' if other else 'ppo'])})")
    parser.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0,
                        help="seed of the model; env copy i starts from seed + i")
    parser.add_argument("--out", required=True, type=new_directory,
                        help="run directory (created when the run is complete; must not "
                        "exist, or be an empty directory)")
    parser.add_argument("--action-mode", choices=sorted({m for spec in specs
                                                         for m in spec.action_modes}),
                        help=f"action mode ({modes}) (default: the env's first)")
    parser.add_argument("--timesteps", type=int_at_least(1),
                        help="env steps (default: the shipped budget of the env, mode and algo)")
    parser.add_argument("--eval-freq", type=int_at_least(1),
                        help="env steps between evaluations (default: a tenth of --timesteps)")
    parser.add_argument("--eval-episodes", type=int_at_least(1), default=50,
                        help="episodes per periodic evaluation")
    parser.add_argument("--threads", type=int_at_least(1), default=1, help="torch CPU threads")
    parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE",
                        help="keyword arguments of the environment, over the shipped entry's "
                        "(KEY=VALUE pairs read as JSON where they are JSON, or one JSON object), "
                        "e.g. target=swingup (default: none)")
    parser.add_argument("--hyperparams", nargs="+", metavar="KEY=VALUE",
                        help="settings over the shipped ones, e.g. learning_rate=1e-4 "
                        "n_steps=256 (default: none; recorded in config.json)")
    parser.add_argument("--n-envs", type=int_at_least(1, 4096),
                        help="env copies (default: the shipped n_envs)")
    parser.add_argument("--device", default="auto",
                        help="torch device: auto, cpu, cuda or cuda:N")
    parser.add_argument("--tensorboard-log", type=new_directory, metavar="DIR",
                        help="also write TensorBoard event files into DIR/<name of --out> "
                        "(needs tensorboard, in the rl extra; default: progress.csv in the "
                        "run directory only)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def check_train_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Before any work: an action mode the env takes, shipped hyperparameters, an ``--out``
    that holds no run yet, then the rl extra (argument mistakes are reported either way)."""
    modes = task_spec(args.env).action_modes
    if args.action_mode is None:
        args.action_mode = modes[0]
    if args.action_mode not in modes:
        parser.error(f"argument --action-mode: {args.env} takes {' or '.join(modes)}, "
                     f"got {args.action_mode!r}")
    if args.algo is None:
        args.algo = task_spec(args.env).default_algo(args.action_mode)
    try:
        load_hyperparams(args.algo, args.env, args.action_mode)
    except ValueError as exc:
        parser.error(str(exc))
    for option, name in (("--env-kwargs", "env_kwargs"), ("--hyperparams", "hyperparams")):
        try:
            setattr(args, name, key_values(getattr(args, name), option,
                                           tuples_for_lists=name == "env_kwargs"))
            if name == "env_kwargs":
                args.env_kwargs = check_env_kwargs(args.env, args.env_kwargs)
            else:
                hp = {**load_hyperparams(args.algo, args.env, args.action_mode,
                                         args.env_kwargs),
                      **check_overrides(args.algo, args.hyperparams)}
                _check_policy_settings(Path("hyperparams"), hp, args.algo)
                check_explore(args.algo, hp)
                check_imitate(args.algo, hp)
                check_episode_steps(hp)
                env = task_spec(args.env).env(action_mode=args.action_mode,
                                              **{**hp.get("env_kwargs", {}), **args.env_kwargs})
                try:
                    _check_policy_fits(hp, env.observation_space, env.action_space,
                                       args.action_mode)
                finally:
                    env.close()
        except ImportError:
            pass  # (the rl extra's check below says what is missing)
        except ValueError as exc:
            parser.error(f"argument {option}: {exc}")
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?|mps", args.device):
        parser.error(f"argument --device: auto, cpu, cuda or cuda:N, got {args.device!r}")
    out = Path(args.out)
    if out.is_dir() and any(out.iterdir()):
        held = " a run" if any((out / n).exists() for n in ("config.json", *OLD_FILES)) else ""
        parser.error(f"argument --out: {args.out!r} already holds{held or ' files'}; choose "
                     "another directory (or an empty one)")
    require("stable_baselines3", "torch", command="cparticles train")
    if args.tensorboard_log is not None:
        require("tensorboard", command="cparticles train --tensorboard-log")
    if args.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            parser.error(f"argument --device: {args.device}: torch sees no CUDA device here")


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles evaluate``."""
    parser.description = ("evaluate a run directory that cparticles train wrote, on held-out "
                          f"episodes (rl extra). {TRUST}")
    parser.add_argument("dir", nargs="?",
                        help="run directory written by cparticles train (or --pretrained)")
    shipped = sorted(pretrained.shipped())
    parser.add_argument("--pretrained", metavar="ENV_ID",
                        help="evaluate the agent shipped with the package for ENV_ID instead "
                        "of a run directory; with --env-kwargs naming a variant, the agent "
                        "trained on it (default: none; shipped: "
                        f"{', '.join(map(pretrained.describe, shipped)) or 'none'})")
    parser.add_argument("--action-mode",
                        help="with --pretrained: the action mode of the shipped agent "
                        "(default: the env's default mode)")
    parser.add_argument("--episodes", type=int_at_least(1), default=100,
                        help="number of episodes")
    parser.add_argument("--seed-start", type=int_at_least(0), default=HELD_OUT_SEED_START,
                        help="seed of the first episode (then +1 each)")
    parser.add_argument("--stochastic", action="store_true",
                        help="sample actions instead of the deterministic policy")
    parser.add_argument("--best", action="store_true",
                        help="use the best model of the periodic evaluations "
                        f"({POLICY_FILES['best']}), not the final one")
    parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE",
                        help="keyword arguments of the environment over the run's own (a "
                        "variant with the same spaces), KEY=VALUE pairs or one JSON object "
                        "(default: the run's)")
    parser.add_argument("--json", action="store_true", help="print only the JSON line")


def check_evaluate_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace
                             ) -> None:
    """Before any work: a run directory :func:`read_run` accepts (given, or the shipped agent
    that ``--pretrained`` names), then the rl extra."""
    if (args.dir is None) == (args.pretrained is None):
        parser.error("give a run directory or --pretrained ENV_ID (one of the two)")
    if args.action_mode is not None and args.pretrained is None:
        parser.error("argument --action-mode: only with --pretrained (a run directory has its "
                     "own)")
    if args.pretrained is not None:
        try:
            given = key_values(args.env_kwargs, "--env-kwargs")
        except ValueError as exc:
            parser.error(f"argument --env-kwargs: {exc}")
        try:
            variant = variant_key(given)
        except ValueError:
            variant = ""
        if variant and not any(k[0] == args.pretrained and k[2] == variant
                               for k in pretrained.shipped()):
            variant = ""  # (the default configuration's agent, played on the variant)
        try:
            args.dir = str(pretrained.pretrained_dir(args.pretrained, args.action_mode,
                                                     variant))
        except ValueError as exc:
            name = "--action-mode" if str(exc).startswith("action_mode") else "--pretrained"
            parser.error(f"argument {name}: {str(exc).split(': ', 1)[1]}")
    try:
        config = read_run(args.dir, "best" if args.best else "final")
    except ValueError as exc:
        parser.error(f"argument dir: {exc}")
    try:
        args.env_kwargs = check_env_kwargs(config["env"],
                                           key_values(args.env_kwargs, "--env-kwargs"))
    except ValueError as exc:
        parser.error(f"argument --env-kwargs: {exc}")
    require("stable_baselines3", "torch", command="cparticles evaluate")


def main_train(args: argparse.Namespace) -> int:
    """``cparticles train``; the run directory appears only when the run is complete."""
    config = train(args.env, args.algo, args.seed, args.out, args.action_mode, args.timesteps,
                   args.eval_freq, args.eval_episodes, progress_bar=not args.no_progress,
                   threads=args.threads, env_kwargs=args.env_kwargs,
                   hyperparams=args.hyperparams, n_envs=args.n_envs, device=args.device,
                   tensorboard_log=args.tensorboard_log)
    print(f"trained {config['algo']} on {config['env']} ({config['action_mode']}), seed "
          f"{config['seed']}, {config['timesteps']} steps in {config['wall_seconds']:.0f} s; "
          f"saved to {args.out}")
    return 0


def main_evaluate(args: argparse.Namespace) -> int:
    """``cparticles evaluate``: a summary, then one JSON line (the last line of the output)."""
    res = evaluate(args.dir, args.episodes, args.seed_start, not args.stochastic,
                   "best" if args.best else "final", env_kwargs=args.env_kwargs)
    if not args.json:
        print(f"# {res['algo']} on {res['env']} ({res['action_mode']}), seed {res['seed']}, "
              f"{'best' if args.best else 'final'} model, "
              f"{'deterministic' if res['deterministic'] else 'stochastic'}, seeds "
              f"{args.seed_start}..{args.seed_start + args.episodes - 1}"
              + ("" if res.get("max_episode_steps") is None else
                 f", episodes of at most {res['max_episode_steps']} steps (its settings)"))
        print(f"success rate {res['success_rate']:.0%}, mean return {res['mean_return']:.2f}, "
              f"mean length {res['mean_length']:.1f} steps"
              + ("" if res.get("mean_normalized_performance") is None else
                 f", mean normalized performance {res['mean_normalized_performance']:.2f}"))
    print(json.dumps(res))
    return 0


def add_convert_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles convert-run``."""
    parser.description = ("convert a run directory of an older cparticles train (model.zip, "
                          "vecnormalize.pkl: pickles) to the current format, which evaluate "
                          "reads. This LOADS THE PICKLES, which runs any code they hold: only "
                          "for directories you made yourself or otherwise trust (rl extra).")
    parser.add_argument("dir", help="run directory of an older cparticles train (trusted)")


def check_convert_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace
                            ) -> None:
    """Before any work: a directory to convert (its config.json only is read), the rl
    extra."""
    try:
        check_convertible(Path(args.dir))
    except ValueError as exc:
        parser.error(f"argument dir: {exc}")
    require("stable_baselines3", "torch", command="cparticles convert-run")


def main_convert(args: argparse.Namespace) -> int:
    """``cparticles convert-run``: one line saying what was trusted and written."""
    print(f"loading the pickles of {args.dir} (trusted, as convert-run says) ...",
          file=sys.stderr, flush=True)
    written = convert_run(args.dir)
    print(f"converted {args.dir}: wrote {', '.join(written)} (the pickles are left in place "
          "and never read by evaluate)")
    return 0
