"""Soak test (not a unit test): random actions on every registered env, both action modes, single
and native vector, counting everything that must never happen.

For each configuration it reports env steps, exceptions, non-finite observations or rewards,
*unflagged* steps whose geometric constraint residual exceeds 1 cm (measured here from the state
and the constraint blocks' parameters, independently of the env's own ``info["diverged"]`` and of
``Constraint.distance_error``), diverged episodes, and the process's resident memory growth per
100k steps after a warm-up.

    python -m benchmarks.soak --steps 200000 --seed 0 --json soak.json
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
import traceback
from typing import Any

import gymnasium as gym
import numpy as np

from constrained_particles import CircularWire, FixedPoint, LineWire, Rod
from envs.task import env_action_modes

#: Residual (m) above which an unflagged step counts as a failure.
RESIDUAL = 0.01
VECTOR_ENVS = 8


def rss_bytes() -> int:
    """Resident set size of this process (bytes), from /proc (0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return 0


def geometric_residuals(system: Any, copies: int) -> np.ndarray:
    """Largest distance (m) by which each copy violates a constraint, from first principles."""
    x = system.x
    n = len(x) // copies
    worst = np.zeros(copies)
    for c in system.constraints:
        if isinstance(c, CircularWire):
            p = c.particles
            err = np.abs(np.hypot(*(x[p] - c.center).T) - c.radius)
        elif isinstance(c, LineWire):  # also HorizontalWire
            p = c.particles
            err = np.abs(np.sum((x[p] - c.point) * c.normal, axis=1))
        elif isinstance(c, Rod):
            p = c.a
            err = np.abs(np.hypot(*(x[c.a] - x[c.b]).T) - c.length)
        elif isinstance(c, FixedPoint):
            p = c.particles
            err = np.max(np.abs(x[p] - c.point), axis=1)
        else:
            raise TypeError(f"soak: no independent residual for {type(c).__name__}")
        np.maximum.at(worst, p // n, np.where(np.isfinite(err), err, np.inf))
    return worst


def soak(env_id: str, mode: str, vector: bool, steps: int, seed: int) -> dict[str, Any]:
    """Run ``steps`` env steps of random actions; the counts of one configuration."""
    rng = np.random.default_rng(seed)
    if vector:
        env = gym.make_vec(env_id, num_envs=VECTOR_ENVS, vectorization_mode="vector_entry_point",
                           action_mode=mode)
        N = VECTOR_ENVS
    else:
        env = gym.make(env_id, action_mode=mode)
        N = 1
    task = env.unwrapped.task
    shape = env.action_space.shape
    out = {"env": env_id, "mode": mode, "kind": "vector" if vector else "single", "steps": 0,
           "episodes": 0, "exceptions": 0, "nonfinite": 0, "unflagged_residual": 0,
           "diverged": 0, "max_residual": 0.0, "errors": []}
    env.reset(seed=seed)
    start = time.perf_counter()
    while out["steps"] < steps:
        action = rng.uniform(-1.0, 1.0, shape).astype(np.float32)
        try:
            obs, reward, terminated, truncated, info = env.step(action)
        except Exception as exc:  # the soak counts every failure instead of stopping
            out["exceptions"] += 1
            if len(out["errors"]) < 5:
                out["errors"].append("".join(traceback.format_exception_only(exc)).strip())
            env.reset(seed=int(rng.integers(2**31)))
            continue
        out["steps"] += N
        diverged = np.atleast_1d(info["diverged"])
        ended = np.atleast_1d(terminated) | np.atleast_1d(truncated)
        out["nonfinite"] += int(np.sum(~np.all(np.isfinite(np.reshape(obs, (N, -1))), axis=1))
                                + np.sum(~np.isfinite(np.atleast_1d(reward))))
        residual = geometric_residuals(task.system, N)
        unflagged = (residual > RESIDUAL) & ~diverged
        out["unflagged_residual"] += int(unflagged.sum())
        out["max_residual"] = max(out["max_residual"], float(residual[~diverged].max(initial=0)))
        out["diverged"] += int(diverged.sum())
        out["episodes"] += int(ended.sum())
        if not vector and ended[0]:
            env.reset()
    out["seconds"] = time.perf_counter() - start
    out["steps_per_second"] = out["steps"] / out["seconds"]
    env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000,
                        help="total env steps, split evenly over the configurations")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.seed < 0:
        parser.error("--steps must be >= 1 and --seed >= 0")
    configs = [(env_id, mode, vector) for env_id, modes in env_action_modes().items()
               for mode in modes for vector in (False, True)]
    per = max(args.steps // len(configs), 1)
    for k, (env_id, mode, vector) in enumerate(configs):  # warm-up: imports, caches, JIT
        soak(env_id, mode, vector, 2 * VECTOR_ENVS, args.seed + k)
    gc.collect()
    rss0 = rss_bytes()
    rows = []
    for k, (env_id, mode, vector) in enumerate(configs):
        row = soak(env_id, mode, vector, per, args.seed + 1000 * k)
        rows.append(row)
        print(f"{env_id:15s} {mode:6s} {row['kind']:6s} steps {row['steps']:8d}  "
              f"episodes {row['episodes']:6d}  exceptions {row['exceptions']}  "
              f"nonfinite {row['nonfinite']}  unflagged>1cm {row['unflagged_residual']}  "
              f"diverged {row['diverged']}  max residual {row['max_residual']:.2e} m  "
              f"{row['steps_per_second']:.0f} steps/s", flush=True)
        for err in row["errors"]:
            print("    ", err)
    gc.collect()
    total = sum(r["steps"] for r in rows)
    episodes = sum(r["episodes"] for r in rows)
    summary = {
        "steps": total, "episodes": episodes,
        "exceptions": sum(r["exceptions"] for r in rows),
        "nonfinite": sum(r["nonfinite"] for r in rows),
        "unflagged_residual": sum(r["unflagged_residual"] for r in rows),
        "diverged_episodes": sum(r["diverged"] for r in rows),
        "diverged_per_10k_episodes": 1e4 * sum(r["diverged"] for r in rows) / max(episodes, 1),
        "rss_growth_mb_per_100k_steps": (rss_bytes() - rss0) / 2**20 / (total / 1e5),
    }
    print(json.dumps(summary, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"seed": args.seed, "summary": summary, "configs": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
