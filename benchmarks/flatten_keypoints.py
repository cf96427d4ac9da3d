"""Benchmark (not a test): how much of the cloth a ClothFlatten-v0 policy must see.

``obs_mode="state"`` observes the cloth's four corners and where they belong on the flat cloth
fitted to the whole cloth; this measures what a policy could do from the particles alone, as
before the fitted places were observed. It plays the scripted agent's rule
(fit the flat cloth rigidly to the current one, take the particle furthest from its place on
the fitted cloth and put it there: ``envs.cloth_flatten.ClothFlattenController``) reading only
a ``k x k`` grid of evenly spaced particles (``k = 2``: the corners), over ``--episodes``
episodes of a single env seeded ``--seed``, ``--seed + 1``, ...

    python -m benchmarks.flatten_keypoints [--episodes 40] [--seed 1000] [--grids 2 3 5]

Prints one Markdown row per grid: success rate, mean normalized performance at the episode's
end, mean episode length (steps, of at most 50).
"""

from __future__ import annotations

import argparse

import numpy as np

from envs.cloth_flatten import ClothFlattenEnv, rigid_fit


def grid_particles(size: int, k: int) -> np.ndarray:
    """Indices of a ``k x k`` grid of evenly spaced particles of a ``size x size`` cloth."""
    sel = np.unique(np.round(np.linspace(0, size - 1, k)).astype(int))
    return (sel[:, None] * size + sel[None, :]).ravel()


def play(k: int, episodes: int, seed: int) -> tuple[float, float, float]:
    """``(success rate, mean normalized performance, mean length)`` of the rule on a ``k x k``
    grid (module docstring)."""
    env = ClothFlattenEnv()
    t = env.task
    kp = grid_particles(t.size, k)
    wins, perf, length = 0, 0.0, 0
    for ep in range(episodes):
        env.reset(seed=seed + ep)
        steps = 0
        for _ in range(50):  # (the registered episode length)
            steps += 1
            x = t.positions()[0][kp]
            goal = rigid_fit(t.flat[kp][None], x[None])[0]
            c = np.clip(goal.mean(axis=0), -0.5 * t.view_half, 0.5 * t.view_half)
            goal = goal - goal.mean(axis=0) + c
            j = int(np.argmax(np.linalg.norm(x - goal, axis=1)))
            a = np.concatenate([t.to_normalized(x[j]), t.to_normalized(goal[j])])
            _, _, terminated, truncated, info = env.step(a.astype(np.float32))
            if terminated or truncated:
                break
        wins += bool(info["is_success"])
        perf += float(info["normalized_performance"])
        length += steps
    return wins / episodes, perf / episodes, length / episodes


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--grids", type=int, nargs="+", default=[2, 3, 5, 9])
    args = p.parse_args(argv)
    print("| particles read | success | normalized performance | steps |")
    print("|---|---|---|---|")
    for k in args.grids:
        rate, perf, steps = play(k, args.episodes, args.seed)
        print(f"| {k} x {k} | {rate:.0%} | {perf:.2f} | {steps:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
