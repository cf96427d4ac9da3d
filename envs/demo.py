"""``cparticles demo``: run a baseline agent on an environment and report its episodes.

The episodes run side by side in the native vector env (episode ``k`` is copy ``k`` of a batch,
which reproduces a single env reset with seed ``seed + k``), so 50 episodes cost about as much as
a few single ones. ``--save-gif`` records episode 0 in a single env; ``--watch`` shows it in a
pygame-ce window.

    cparticles demo --env ClothSlide-v0 --agent scripted --episodes 50 --seed 0
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import gymnasium as gym
import numpy as np

from constrained_particles.arguments import (
    int_at_least,
    key_values,
    output_file,
    time_step,
    written_whole,
)
from constrained_particles.integrators import METHODS

from .agents import AGENTS, make_agent
from .task import check_env_kwargs, task_spec, task_specs

#: Largest batch of episodes run as one vector env.
BATCH = 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles demo``."""
    specs = task_specs()
    ids = [spec.id for spec in specs]
    parser.add_argument("--env", default=ids[0], choices=ids, metavar="ENV_ID",
                        help="environment id: " + "; ".join(  # (argparse reads % as a format)
                            f"{spec.id}, {spec.summary.replace('%', '%%')}" for spec in specs))
    parser.add_argument("--agent", default="scripted", choices=AGENTS, help="which agent")
    parser.add_argument("--episodes", type=int_at_least(1), default=50,
                        help="number of episodes")
    parser.add_argument("--seed", type=int_at_least(0), default=0,
                        help="seed of episode 0 (then +1 each)")
    modes = "; ".join(f"{spec.id}: {', '.join(spec.action_modes)}" for spec in specs)
    parser.add_argument("--action-mode",
                        choices=sorted({m for spec in specs for m in spec.action_modes}),
                        help=f"action mode ({modes}) (default: the env's first)")
    parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE",
                        help="keyword arguments of the environment (KEY=VALUE pairs, values "
                        "read as JSON where they are JSON, or one JSON object), e.g. "
                        "target=swingup for ChainSwing's swing-up (default: none)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--save-gif", type=output_file(".gif"), metavar="PATH.gif",
                        help="save episode 0 as an animated GIF (needs pillow, no pygame; default: "
                        "no GIF)")
    parser.add_argument("--watch", action="store_true",
                        help="show episode 0 in a pygame-ce window first (needs a display)")
    parser.add_argument("--integrator", choices=sorted(METHODS),
                        help="physics integrator (default: the environment's)")
    parser.add_argument("--dt", type=time_step,
                        help="physics step in seconds (default: the environment's)")
    parser.add_argument("--substeps", type=int_at_least(1),
                        help="physics steps per env step (default: the environment's)")


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Before any work: the render extra for ``--watch`` (pygame-ce) and pillow for
    ``--save-gif``, and a display for ``--watch``."""
    from constrained_particles.extras import require
    from constrained_particles.viewer import display_problem

    try:
        args.env_kwargs = check_env_kwargs(args.env, key_values(args.env_kwargs,
                                                                "--env-kwargs"))
    except ValueError as exc:
        parser.error(f"argument --env-kwargs: {exc}")
    modes = task_spec(args.env).action_modes
    if args.action_mode is not None and args.action_mode not in modes:
        parser.error(f"--action-mode: {args.env} takes one of {', '.join(modes)}, "
                     f"got {args.action_mode!r}")
    if args.watch:
        require("pygame", "PIL", command="cparticles demo --watch")
    if args.save_gif:  # (frames drawn by the rasteriser: pillow writes the GIF, no pygame)
        require("PIL", command="cparticles demo --save-gif")
    problem = display_problem() if args.watch else None
    if problem:
        parser.error(f"--watch: {problem}; use --save-gif PATH.gif to record episode 0 instead")


def run_episodes(env_id: str, agent: str, episodes: int, seed: int = 0,
                 action_mode: str | None = None, **env_kwargs: object) -> dict[str, np.ndarray]:
    """Run ``episodes`` episodes (seeds ``seed .. seed + episodes - 1``) in native vector envs
    made with ``env_kwargs`` (and ``action_mode``; None: the environment's default). Returns
    per-episode arrays ``return``, ``length``, ``success`` and ``diverged`` (the episode ended
    because its simulation diverged).
    """
    if action_mode is not None:
        env_kwargs = {**env_kwargs, "action_mode": action_mode}
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    out: dict[str, list[np.ndarray]] = {"return": [], "length": [], "success": [],
                                        "diverged": []}
    for start in range(0, episodes, BATCH):
        n = min(BATCH, episodes - start)
        env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                           **env_kwargs)
        policy = make_agent(agent, env, seed=seed + start)
        obs, _ = env.reset(seed=seed + start)
        ret, length = np.zeros(n), np.zeros(n, dtype=np.int64)
        success, done = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        diverged = np.zeros(n, dtype=bool)
        while not done.all():
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            live = ~done
            ret[live] += reward[live]
            length[live] += 1
            ended = live & (terminated | truncated)
            success[ended] = info["is_success"][ended]
            diverged[ended] = info["diverged"][ended]
            done |= ended
        env.close()
        for key, value in (("return", ret), ("length", length), ("success", success),
                           ("diverged", diverged)):
            out[key].append(value)
    return {key: np.concatenate(v) for key, v in out.items()}


def record_episode(env_id: str, agent: str, seed: int, action_mode: str | None,
                   render_mode: str = "rgb_array", **env_kwargs: object
                   ) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Run one episode in a single env; returns its frames (``rgb_array``) and last info."""
    if action_mode is not None:
        env_kwargs = {**env_kwargs, "action_mode": action_mode}
    env = gym.make(env_id, render_mode=render_mode, **env_kwargs)
    policy = make_agent(agent, env, seed=seed)
    obs, info = env.reset(seed=seed)
    frames = [env.render()] if render_mode == "rgb_array" else []
    while True:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        if render_mode == "rgb_array":
            frames.append(env.render())
        if terminated or truncated:
            break
    fps = env.metadata["render_fps"]
    env.close()
    return frames, {**info, "fps": fps}


def save_gif(path: str, frames: list[np.ndarray], fps: float) -> None:
    """Write ``frames`` ((H, W, 3) uint8) as a looping GIF at ``fps`` (pillow)."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    with written_whole(path) as partial:  # (a full disk leaves no truncated GIF)
        images[0].save(partial, format="GIF", save_all=True, append_images=images[1:], loop=0,
                       duration=int(round(1000 / fps)), optimize=True)


def main(args: argparse.Namespace) -> int:
    """``cparticles demo``: a table (or JSON) of return, length and success per episode."""
    physics = {**args.env_kwargs,
               **{k: getattr(args, k) for k in ("integrator", "dt", "substeps")
                  if getattr(args, k) is not None}}
    if args.action_mode is None:  # each environment's default
        args.action_mode = task_spec(args.env).default_mode
    if args.watch:
        record_episode(args.env, args.agent, args.seed, args.action_mode, render_mode="human",
                       **physics)
    start = time.perf_counter()
    res = run_episodes(args.env, args.agent, args.episodes, args.seed, args.action_mode,
                       **physics)
    seconds = time.perf_counter() - start
    summary = {"env": args.env, "agent": args.agent, "action_mode": args.action_mode,
               **physics, "episodes": args.episodes, "seed": args.seed,
               "success_rate": float(res["success"].mean()),
               "mean_return": float(res["return"].mean()),
               "mean_length": float(res["length"].mean()),
               "diverged_episodes": int(res["diverged"].sum()), "seconds": round(seconds, 2)}
    if args.save_gif:
        frames, info = record_episode(args.env, args.agent, args.seed, args.action_mode,
                                      **physics)
        save_gif(args.save_gif, frames, info["fps"])
        summary["gif"] = args.save_gif
    if args.json:
        summary.update(returns=res["return"].round(4).tolist(), lengths=res["length"].tolist(),
                       successes=res["success"].tolist(), diverged=res["diverged"].tolist())
        print(json.dumps(summary, indent=2))
        return 0
    variant = "".join(f", {k}={v}" for k, v in args.env_kwargs.items())
    print(f"# {args.env}{variant}, {args.agent} agent, action_mode={args.action_mode}, "
          f"seeds {args.seed}..{args.seed + args.episodes - 1}")
    print(f"{'episode':>7} {'seed':>6} {'return':>9} {'length':>6} {'success':>7} "
          f"{'diverged':>8}")
    for k in range(args.episodes):
        print(f"{k:7d} {args.seed + k:6d} {res['return'][k]:9.2f} {res['length'][k]:6d} "
              f"{'yes' if res['success'][k] else 'no':>7} "
              f"{'yes' if res['diverged'][k] else 'no':>8}")
    print(f"success rate {summary['success_rate']:.0%}, mean return {summary['mean_return']:.2f}, "
          f"mean length {summary['mean_length']:.1f} steps, "
          f"{summary['diverged_episodes']} diverged ({seconds:.1f} s)")
    if args.save_gif:
        print(f"saved {args.save_gif}")
    return 0
