"""Benchmark (not a test): the table-top pick-and-place tasks (every registered task whose
default action mode is ``pick_place``).

For each task, over ``--episodes`` episodes seeded ``--seed``, ``--seed + 1``, ... (default
100 from 1,000,000, seeds never used in the unit tests), in native vector envs of
``--batch`` copies:

- the scripted agent's (the task's oracle) and uniformly random actions' success rate, mean
  episode length and mean final ``normalized_performance``;
- the milliseconds of one pick-and-place step and of one reset of a single env (one
  thread; medians over ``--timed`` steps and resets of scripted episodes);
- the native vector env of ``--copies`` copies (64) over ``--vector-steps`` (15) scripted
  steps against the bare tiled system replaying the same physics steps (the grippers as the
  env moved them), and against the bare system running as many physics steps at rest (ms per
  env step, ratios; see :func:`vector_overhead`).

    python -m benchmarks.tabletop [--episodes 100] [--seed 1000000] [--only ID ...]
    python -m benchmarks.tabletop --pictures docs/envs
    python -m benchmarks.tabletop --drag [--max-episode-steps 100]

``--drag`` measures the agents in ``action_mode="drag"`` instead (SoftGym's low-level mode,
at the registered episode lengths, or at ``--max-episode-steps``: one pick-and-place takes
several drag steps): the success rates, lengths and normalized performance only.

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
    the bare tiled system running the same physics steps: milliseconds per env step of each,
    and their ratios (medians over the steps that ran physics, each step's env time divided
    by its replays' right after it).

    Two bare systems, each a copy of the env's in the state its step's physics starts from
    (after any autoreset):

    - ``replay``: the same physics (the grippers' anchors, their particles and the lifted
      flags as the env set them before each of its physics calls, set here by plain array
      writes); its final positions equal the env's last physics call's bit for bit (checked:
      it is the same computation), so the difference is what the env adds around the physics
      (choosing the pick, moving the anchors, the rest test, the measures);
    - ``rest``: the same number of physics steps in one call with the grippers off (the
      object left to settle from the same start): cheaper per step, since no gripper pulls
      the constraints out of shape.
    """
    import copy

    env = gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point")
    agent = make_agent("scripted", env)
    obs, _ = env.reset(seed=seed)
    task = env.unwrapped.task
    s = task.system
    warm = copy.deepcopy(s)
    warm.step(task.dt, task.integrator, steps=10)  # (warm)
    mouse, table = task._mouse_block, task._table_block
    spent: list[float] = []
    replayed: list[float] = []
    rested: list[float] = []
    calls: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]] = []
    last = [np.zeros(0)]
    first: list[tuple[np.ndarray, np.ndarray, float, np.ndarray]] = []
    real_step = type(s).step

    def recorded_step(system: Any, dt: float, integrator: str, steps: int = 1) -> None:
        if system is s:
            if not calls:  # (the state the physics starts from: after any autoreset)
                first.append((system.x.copy(), system.v.copy(), system.t,
                              system.constraint_solver.lam.copy()))
            g = system.forces[mouse]
            calls.append((g.particle.copy(), g.anchor.copy(), g.active.copy(),
                          system.forces[table].lifted.copy(), steps))
        real_step(system, dt, integrator, steps=steps)
        if system is s:
            last[0] = system.x.copy()

    for _ in range(steps):  # (alternated, so that the machine's load moves all alike)
        a = agent(obs)
        replay, rest = copy.deepcopy(s), copy.deepcopy(s)
        for bare in (replay, rest):  # (a copy rebuilds its solver and pack on first use)
            bare.step(task.dt, task.integrator, steps=1)
        calls.clear()
        first.clear()
        type(s).step = recorded_step  # (records only: timed outside)
        try:
            t0 = time.perf_counter()
            obs, *_ = env.step(a)
            took = time.perf_counter() - t0
        finally:
            type(s).step = real_step
        if not calls:  # (every copy started anew: no physics)
            continue
        x0, v0, t0_, lam0 = first[0]
        for bare in (replay, rest):
            bare.x, bare.v, bare.t = x0.copy(), v0.copy(), t0_
            bare.constraint_solver.lam[:] = lam0
        g, lifted = replay.forces[mouse], replay.forces[table].lifted
        t0 = time.perf_counter()
        for particle, anchor, active, lift, k in calls:
            if not np.array_equal(g.particle, particle):
                g.set_checked(np.arange(len(particle)), particle, anchor, active)
            g.anchor[:], g.active[:], lifted[:] = anchor, active, lift
            replay.step(task.dt, task.integrator, steps=k)
        replayed.append(time.perf_counter() - t0)
        spent.append(took)
        if not np.array_equal(replay.x, last[0]):
            raise RuntimeError(f"{env_id}: the replay is not the env's physics")
        rest.forces[mouse].active[:] = False
        rest.forces[table].lifted[:] = False
        total = sum(c[-1] for c in calls)
        t0 = time.perf_counter()
        rest.step(task.dt, task.integrator, steps=total)
        rested.append(time.perf_counter() - t0)
    env.close()
    e, r, b = (np.array(t) for t in (spent, replayed, rested))
    return {"copies": copies, "steps": len(e), "env_ms": 1000 * float(np.median(e)),
            "replay_ms": 1000 * float(np.median(r)), "ratio": float(np.median(e / r)),
            "rest_ms": 1000 * float(np.median(b)), "rest_ratio": float(np.median(e / b))}


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
    p.add_argument("--vector-steps", type=int, default=15,
                   help="scripted steps of the vector env timed against the bare system")
    p.add_argument("--only", nargs="*", default=None, help="task ids (default: all)")
    p.add_argument("--pictures", type=Path, default=None, help="write the README pictures here")
    p.add_argument("--drag", action="store_true", help="the agents in drag mode only")
    p.add_argument("--max-episode-steps", type=int, default=None,
                   help="drag mode: episodes of this many steps (default: the registered)")
    args = p.parse_args(argv)
    if args.max_episode_steps is not None and (not args.drag or args.max_episode_steps < 1):
        p.error("--max-episode-steps takes a positive number, with --drag")
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
                               "episodes": args.episodes, "seed": args.seed, "tasks": {},
                               "max_episode_steps": args.max_episode_steps}
    if args.drag:
        print("| task (drag mode) | scripted success | random success | scripted steps "
              "| scripted perf | random perf |\n|---|---|---|---|---|---|")
        for env_id in ids:
            limit = ({} if args.max_episode_steps is None
                     else {"max_episode_steps": args.max_episode_steps})
            scripted, random = (rates(env_id, agent, args.episodes, args.seed, args.batch,
                                      action_mode="drag", **limit)
                                for agent in ("scripted", "random"))
            results["tasks"][env_id] = {"scripted": scripted, "random": random}
            print(f"| {env_id} | {scripted['success']:.0%} | {random['success']:.0%} | "
                  f"{scripted['length']:.1f} | {scripted['normalized_performance']:.2f} | "
                  f"{random['normalized_performance']:.2f} |", flush=True)
        print(json.dumps(results, indent=1))
        return 0
    print("| task | scripted success | random success | scripted steps | scripted perf "
          "| random perf | ms/step | ms/reset | vector / replay ms | vector / rest |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for env_id in ids:
        scripted = rates(env_id, "scripted", args.episodes, args.seed, args.batch)
        random = rates(env_id, "random", args.episodes, args.seed, args.batch)
        speed = timings(env_id, args.timed, args.seed)
        vector = vector_overhead(env_id, args.copies, args.vector_steps, args.seed)
        results["tasks"][env_id] = {"scripted": scripted, "random": random, **speed,
                                    "vector": vector}
        print(f"| {env_id} | {scripted['success']:.0%} | {random['success']:.0%} | "
              f"{scripted['length']:.1f} | {scripted['normalized_performance']:.2f} | "
              f"{random['normalized_performance']:.2f} | {speed['step_ms']:.1f} | "
              f"{speed['reset_ms']:.1f} | {vector['env_ms']:.0f} / {vector['replay_ms']:.0f} = "
              f"{vector['ratio']:.2f} | {vector['rest_ratio']:.2f} |", flush=True)
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
