"""Benchmark (not a test): how much action noise the table-top tasks' scripted agents absorb.

A trained Gaussian policy acts with noise when evaluated stochastically, and its mean is never
exactly the oracle's action. This measures the precision the pick-and-place tasks ask for: the
scripted agent's actions plus Gaussian noise of standard deviation ``sigma`` (normalised action
units, clipped to the Box), success rate over ``--episodes`` episodes of a single env seeded
``--seed``, ``--seed + 1``, ... (the noise from ``numpy.random.default_rng(0)``, one stream per
sigma).

    python -m benchmarks.tabletop_noise [--episodes 100] [--seed 1000] [--only ID ...]

Prints one Markdown row per task: the success rate at each sigma.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import envs
from envs.agents import make_agent

#: Standard deviations of the noise (normalised action units: 1 is half the view box).
SIGMAS = (0.0, 0.01, 0.02, 0.05, 0.1)


def noisy_success(env_id: str, sigma: float, episodes: int, seed: int) -> float:
    """Success rate of the scripted agent plus N(0, sigma^2) noise on every action entry."""
    env = gym.make(env_id)
    agent = make_agent("scripted", env)
    rng = np.random.default_rng(0)
    wins = 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        while True:
            a = np.clip(agent(obs) + rng.normal(0.0, sigma, env.action_space.shape), -1, 1)
            obs, _, terminated, truncated, info = env.step(a.astype(np.float32))
            if terminated or truncated:
                break
        wins += bool(info["is_success"])
    env.close()
    return wins / episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--only", nargs="+", default=None, metavar="ID")
    args = parser.parse_args()
    ids = args.only or [s.id for s in envs.task_specs() if s.default_mode == "pick_place"]
    print("| environment | " + " | ".join(f"noise {s:g}" for s in SIGMAS) + " |")
    print("|---|" + "---|" * len(SIGMAS))
    for env_id in ids:
        rates = [noisy_success(env_id, s, args.episodes, args.seed) for s in SIGMAS]
        print(f"| {env_id} | " + " | ".join(f"{100 * r:.0f}%" for r in rates) + " |",
              flush=True)


if __name__ == "__main__":
    main()
