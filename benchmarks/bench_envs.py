"""Throughput of the environments: the native vector env against SyncVectorEnv.

Every registered environment runs with ``num_envs`` copies (default 64) as the native vector env
(``vectorization_mode="vector_entry_point"``: all copies are one particle system, one derivative
evaluation per physics step for all of them) and as gymnasium's ``SyncVectorEnv`` (N single envs
stepped one after another), under the same uniform random actions. Timed blocks of the two
alternate, and each keeps its best block, so that other processes on a shared machine affect
both alike. Prints env-steps per second, the speedup and a JSON line. A script, not a test::

    python benchmarks/bench_envs.py [--num-envs 64] [--steps 40] [--repeats 5] [--spring] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import gymnasium as gym
import numpy as np

import envs

#: The environments compared (their force and spring action modes): the tasks whose
#: declarations ask for the vector benchmarks (``TaskSpec.bench_vector``)
COMPARED = tuple(spec.id for spec in envs.task_specs() if spec.bench_vector)


def _block(env: Any, actions: np.ndarray) -> float:
    start = time.perf_counter()
    for a in actions:
        env.step(a)
    return time.perf_counter() - start


def compare(env_id: str, num_envs: int = 64, steps: int = 40, repeats: int = 5, seed: int = 0,
            **kwargs: Any) -> dict[str, float]:
    """Best-of-``repeats`` env-steps per second of the native and the sync vector env.

    Each timed block is ``steps`` native steps or ``max(2, steps // 8)`` sync steps, after five
    warm-up steps; blocks of the two modes alternate.
    """
    modes = {"native": ("vector_entry_point", steps), "sync": ("sync", max(2, steps // 8))}
    vec = {name: gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=mode, **kwargs)
           for name, (mode, _) in modes.items()}
    rng = np.random.default_rng(seed)
    shape = vec["native"].action_space.shape
    best = dict.fromkeys(modes, np.inf)
    for env in vec.values():
        env.reset(seed=seed)
        _block(env, rng.uniform(-1, 1, (5, *shape)).astype(np.float32))
    for _ in range(repeats):
        for name, (_, n) in modes.items():
            actions = rng.uniform(-1, 1, (n, *shape)).astype(np.float32)
            best[name] = min(best[name], _block(vec[name], actions) / n)
    for env in vec.values():
        env.close()
    rates = {name: num_envs / t for name, t in best.items()}
    return {"num_envs": num_envs, **rates, "speedup": rates["native"] / rates["sync"]}


def run(num_envs: int = 64, steps: int = 40, repeats: int = 5,
        action_modes: tuple[str, ...] = ("force",)) -> dict[str, dict[str, float]]:
    """``{"<id>/<action_mode>": {"native": steps/s, "sync": steps/s, "speedup": ratio, ...}}``."""
    return {f"{env_id}/{mode}": compare(env_id, num_envs, steps, repeats, action_mode=mode)
            for env_id in COMPARED for mode in action_modes}


def main(argv: list[str] | None = None) -> int:
    """Command-line entry: print a table and a JSON line (only the JSON with ``--json``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=64, help="copies per vector env")
    parser.add_argument("--steps", type=int, default=40,
                        help="native steps per timed block (sync blocks are 1/8 of it)")
    parser.add_argument("--repeats", type=int, default=5, help="timed blocks per mode")
    parser.add_argument("--spring", action="store_true", help="also the spring action mode")
    parser.add_argument("--json", action="store_true", help="print only the JSON")
    args = parser.parse_args(argv)
    modes = ("force", "spring") if args.spring else ("force",)
    results = run(args.num_envs, args.steps, args.repeats, modes)
    if not args.json:
        print(f"{'environment':24} {'native [env-steps/s]':>21} {'sync [env-steps/s]':>19} "
              f"{'speedup':>8}")
        for name, r in results.items():
            print(f"{name:24} {r['native']:21,.0f} {r['sync']:19,.0f} {r['speedup']:7.1f}x")
    print(json.dumps(results, indent=2 if args.json else None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
