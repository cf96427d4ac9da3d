"""Benchmark (not a test): the table-top pick-and-place tasks (every registered task whose
default action mode is ``pick_place``).

For each task, over ``--episodes`` episodes seeded ``--seed``, ``--seed + 1``, ... (default
100 from 1,000,000, seeds never used in the unit tests), in native vector envs of
``--batch`` copies:

- the scripted agent's (the task's oracle) and uniformly random actions' success rate, mean
  episode length and mean final ``normalized_performance``;
- the milliseconds of one pick-and-place step and of one reset of a single env (one
  thread; medians over ``--timed`` steps and resets of scripted episodes);
- the native vector env of ``--copies`` copies (64) over 5 scripted steps against the bare
  tiled system running the same number of physics steps in one call (ms per env step of
  each, and the ratio), and against the time the env spends in its own physics calls.

    python -m benchmarks.tabletop [--episodes 100] [--seed 1000000] [--only ID ...]
    python -m benchmarks.tabletop --pictures docs/envs

Prints a table, then the figures as JSON. ``--pictures DIR`` writes each task's picture for
the README instead (``DIR/<module>.png``: the start of a seeded episode beside where the
scripted agent leaves it, each frame at half size).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import envs
from envs.agents import make_agent


def pick_place_ids() -> list[str]:
    """The registered tasks whose default action mode is pick-and-place."""
    return [s.id for s in envs.task_specs() if s.default_mode == "pick_place"]


def rates(env_id: str, agent: str, episodes: int, seed: int, batch: int,
          **kwargs: Any) -> dict[str, float]:
    """Success rate, mean length and mean final normalized performance of ``agent`` over
    ``episodes`` episodes seeded ``seed ..`` (the random agent seeded per batch)."""
    success, length, perf = [], [], []
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                           **kwargs)
        policy = make_agent(agent, env, seed=seed + start)
        obs, _ = env.reset(seed=seed + start)
        done = np.zeros(n, bool)
        steps = np.zeros(n, np.int64)
        ok, final = np.zeros(n, bool), np.zeros(n)
        while not done.all():
            obs, _, terminated, truncated, info = env.step(policy(obs))
            live = ~done
            steps[live] += 1
            ended = live & (terminated | truncated)
            ok[ended] = info["is_success"][ended]
            final[ended] = info["normalized_performance"][ended]
            done |= ended
        env.close()
        success.append(ok)
        length.append(steps)
        perf.append(final)
    return {"success": float(np.concatenate(success).mean()),
            "length": float(np.concatenate(length).mean()),
            "normalized_performance": float(np.concatenate(perf).mean())}


def timings(env_id: str, timed: int, seed: int) -> dict[str, float]:
    """Median milliseconds of a scripted pick-and-place step and of a reset, single env."""
    env = gym.make(env_id)
    agent = make_agent("scripted", env)
    steps, resets = [], []
    obs, _ = env.reset(seed=seed)
    k = 0
    while len(steps) < timed:
        a = agent(obs)
        t0 = time.perf_counter()
        obs, _, terminated, truncated, _ = env.step(a)
        steps.append(time.perf_counter() - t0)
        if terminated or truncated:
            k += 1
            t0 = time.perf_counter()
            obs, _ = env.reset(seed=seed + k)
            resets.append(time.perf_counter() - t0)
    while len(resets) < 10:
        k += 1
        t0 = time.perf_counter()
        env.reset(seed=seed + k)
        resets.append(time.perf_counter() - t0)
    env.close()
    return {"step_ms": 1000 * statistics.median(steps),
            "reset_ms": 1000 * statistics.median(resets)}


def vector_overhead(env_id: str, copies: int, steps: int, seed: int) -> dict[str, float]:
    """Time of ``steps`` scripted steps of the native vector env of ``copies`` copies against
    the bare tiled system (a copy of the env's, grippers off) running the same number of
    physics steps in one call after each: milliseconds per env step of each, and their
    ratio; and the env's step against the time spent in its own physics calls (what the env
    adds around the physics it runs: the grippers, the rest test, the measures)."""
    import copy

    env = gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point")
    agent = make_agent("scripted", env)
    obs, _ = env.reset(seed=seed)
    task = env.unwrapped.task
    s = task.system
    bare = copy.deepcopy(s)
    bare.step(task.dt, task.integrator, steps=10)  # (warm)
    spent, alone, physics = 0.0, 0.0, 0
    inside = [0.0]
    real_step = type(s).step

    def timed_step(system: Any, *args: Any, **kwargs: Any) -> None:
        t0 = time.perf_counter()
        try:
            real_step(system, *args, **kwargs)
        finally:
            if system is s:
                inside[0] += time.perf_counter() - t0

    type(s).step = timed_step  # (the env's own physics calls, timed within its steps)
    try:
        for _ in range(steps):  # (alternated, so that the machine's load moves both alike)
            a = agent(obs)
            t0, clock = time.perf_counter(), s.t
            obs, *_ = env.step(a)
            spent += time.perf_counter() - t0
            k = int(round((s.t - clock) / task.dt))
            physics += k
            if not k:  # (every copy started anew: no physics)
                continue
            t0 = time.perf_counter()
            bare.step(task.dt, task.integrator, steps=k)
            alone += time.perf_counter() - t0
    finally:
        type(s).step = real_step
    env.close()
    return {"copies": copies, "physics_steps": physics, "env_ms": 1000 * spent / steps,
            "bare_ms": 1000 * alone / steps, "ratio": spent / alone,
            "own_physics_ms": 1000 * inside[0] / steps, "own_ratio": spent / inside[0]}


def picture(env_id: str, seed: int = 0) -> np.ndarray:
    """The start of episode ``seed`` beside its end under the scripted agent, (200, 600, 3)
    uint8 (each 600 x 400 frame averaged over 2 x 2 pixels)."""
    env = gym.make(env_id, render_mode="rgb_array")
    agent = make_agent("scripted", env)
    obs, _ = env.reset(seed=seed)
    first = env.render()
    done = False
    while not done:
        obs, _, terminated, truncated, _ = env.step(agent(obs))
        done = terminated or truncated
    both = np.concatenate([first, env.render()], axis=1).astype(np.float64)
    env.close()
    h, w = both.shape[0] // 2, both.shape[1] // 2
    small = both[:2 * h, :2 * w].reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
    return np.round(small).astype(np.uint8)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=1_000_000)
    p.add_argument("--batch", type=int, default=25)
    p.add_argument("--timed", type=int, default=100)
    p.add_argument("--copies", type=int, default=64, help="vector env copies timed")
    p.add_argument("--only", nargs="*", default=None, help="task ids (default: all)")
    p.add_argument("--pictures", type=Path, default=None, help="write the README pictures here")
    args = p.parse_args(argv)
    ids = pick_place_ids() if not args.only else args.only
    if args.pictures is not None:
        from benchmarks.raster import png

        for env_id in ids:
            name = envs.task_spec(env_id).env.__module__.rsplit(".", 1)[1]
            path = args.pictures / f"{name}.png"
            path.write_bytes(png(picture(env_id)))
            print(path)
        return 0
    results: dict[str, Any] = {"machine": platform.processor() or platform.machine(),
                               "episodes": args.episodes, "seed": args.seed, "tasks": {}}
    print("| task | scripted success | random success | scripted steps | scripted perf "
          "| random perf | ms/step | ms/reset | vector / bare ms | vector / own physics |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for env_id in ids:
        scripted = rates(env_id, "scripted", args.episodes, args.seed, args.batch)
        random = rates(env_id, "random", args.episodes, args.seed, args.batch)
        speed = timings(env_id, args.timed, args.seed)
        vector = vector_overhead(env_id, args.copies, 5, args.seed)
        results["tasks"][env_id] = {"scripted": scripted, "random": random, **speed,
                                    "vector": vector}
        print(f"| {env_id} | {scripted['success']:.0%} | {random['success']:.0%} | "
              f"{scripted['length']:.1f} | {scripted['normalized_performance']:.2f} | "
              f"{random['normalized_performance']:.2f} | {speed['step_ms']:.1f} | "
              f"{speed['reset_ms']:.1f} | {vector['env_ms']:.0f} / {vector['bare_ms']:.0f} = "
              f"{vector['ratio']:.2f} | {vector['own_ratio']:.2f} |", flush=True)
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
