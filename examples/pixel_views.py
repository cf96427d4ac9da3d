"""Write the pictures of docs/pixels.md: what the agent sees in ``obs_mode="pixels"``.

For every registered task, after 25 steps of its scripted agent from seed 0:
``docs/images/agent_<id>.png``, the 64 x 64 observation scaled up 2x without smoothing, and
``docs/images/human_<id>.png``, the ``rgb_array`` frame (600 x 400) shrunk to 240 x 160. Then
``docs/images/stack.png``: four consecutive 64 x 64 frames of ClothSlide-v0 pushed right (what
a frame stack holds), and ``docs/images/grey.png``: the same scene in one channel.

    python examples/pixel_views.py [--out docs/images]

Needs pillow (the render extra) to write PNGs; no pygame.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
from PIL import Image

import envs
from envs.agents import make_agent
from envs.cloth_slide import TASK as SLIDE
from envs.pick_place import PickPlaceTask

STEPS = 25  #: scripted steps before the picture


def scripted_run(env_id: str, steps: int, **kwargs: object) -> gym.Env:
    """A single env of ``env_id`` after ``steps`` steps of its scripted agent from seed 0."""
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    env.reset(seed=0)
    agent = make_agent("scripted", env)
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(agent(env.unwrapped.task.observe()[0]))
        if terminated or truncated:
            break
    return env


def big(image: np.ndarray, factor: int = 2) -> Image.Image:
    """``image`` (H, W, C) scaled up ``factor`` times, each pixel a block (no smoothing)."""
    grown = np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)
    return Image.fromarray(grown[:, :, 0] if grown.shape[2] == 1 else grown)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/images"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for env_id in envs.ENV_IDS:
        # (a table-top task at its start: a tangle, a crumpled cloth, the target to reach)
        table_top = issubclass(envs.task_spec(env_id).env.task_class, PickPlaceTask)
        env = scripted_run(env_id, 0 if table_top else STEPS, obs_mode="pixels")
        agent_view = env.unwrapped._observation(env.unwrapped.task.observe())[0]
        big(agent_view).save(args.out / f"agent_{env_id}.png", optimize=True)
        Image.fromarray(env.render()).resize((240, 160), Image.LANCZOS).save(
            args.out / f"human_{env_id}.png", optimize=True)
    env = gym.make(SLIDE.id, obs_mode="pixels")
    frames = [env.reset(seed=3)[0]]
    for _ in range(3):
        for _ in range(3):
            obs, *_ = env.step(np.array([1.0, 1.0], np.float32))
        frames.append(obs)
    gap = np.full((64, 4, 3), 255, np.uint8)
    strip = np.concatenate([part for f in frames for part in (f, gap)][:-1], axis=1)
    big(strip).save(args.out / "stack.png", optimize=True)
    grey = gym.make(SLIDE.id, obs_mode="pixels", pixel_channels=1).reset(seed=3)[0]
    big(grey).save(args.out / "grey.png", optimize=True)
    print(f"wrote {len(envs.ENV_IDS) * 2 + 2} pictures into {args.out}")


if __name__ == "__main__":
    main()
