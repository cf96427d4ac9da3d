"""Benchmark (not a test): pixel observations (``obs_mode="pixels"``, envs/pixels.py).

Two comparisons, each timed as medians of alternated rounds in one run (each entry once per
round, round after round, so a change in the machine's load moves them alike), ratios of
those medians:

- **(a)** one step of ``--copies`` (512) copies of ``ClothSlide-v0`` in the native vector env,
  ``obs_mode="pixels"`` (64 x 64 RGB) against ``obs_mode="state"``, the same actions (the bar:
  the pixel step at most 2x the state step), and the drawing of those 512 images alone;
- **(b)** a single env's 64 x 64 observation: the env's own (``obs_mode="pixels"``: the
  rasteriser drawing one copy) against what a user had before it, Gymnasium's
  ``AddRenderObservation`` over the ``rgb_array`` render of that time (pygame drawing the
  600 x 400 frame, ``constrained_particles.render.Renderer``) resized to 64 x 64 with pillow
  (the bar: at least 20x faster). Also timed: the same wrapper over today's ``rgb_array``
  render (the rasteriser at 600 x 400), and whole steps of both wrapped envs.

    python benchmarks/pixels.py [--copies 512] [--repeats 9] [--seconds 0.3]

Prints a table, then the figures as JSON. Needs pygame-ce and pillow (the render extra) for
the pygame reference.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from typing import Any

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the envs)
from cparticles.bench import alternate
from envs.base import FRAME_SIZE
from envs.cloth_slide import TASK
from envs.pixels import Camera

SIZE = 64  #: pixels


class PygameFrames(gym.Wrapper):
    """``render()`` as it was before the rasteriser: the pygame frame of copy 0 (600 x 400,
    ``Renderer.rgb_array`` of the task's drawing, with its status line)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        from constrained_particles.render import Renderer

        self._renderer = Renderer(bounds=env.unwrapped.task.view, size=FRAME_SIZE)

    def render(self) -> np.ndarray:
        system, extra, status = self.env.unwrapped.task.drawing(0)
        return self._renderer.rgb_array(system, extra=extra, forces=True, hud=status)


def resized(env: gym.Env) -> gym.Env:
    """``AddRenderObservation`` (the frame only) with the frame resized to 64 x 64 by pillow
    (bilinear), the way a user gets a small image from a render."""
    from PIL import Image

    wrapped = gym.wrappers.AddRenderObservation(env, render_only=True)
    space = gym.spaces.Box(0, 255, (SIZE, SIZE, 3), np.uint8)
    return gym.wrappers.TransformObservation(
        wrapped, lambda frame: np.asarray(Image.fromarray(frame).resize((SIZE, SIZE),
                                                                        Image.BILINEAR)), space)


def vector_calls(copies: int) -> dict[str, Any]:
    """(a): a step of ``copies`` copies in each obs_mode, the same actions."""
    calls = {}
    action = np.random.default_rng(0).uniform(-1, 1, (copies, 2)).astype(np.float32)
    for mode in ("state", "pixels"):
        env = gym.make_vec(TASK.id, num_envs=copies, vectorization_mode="vector_entry_point",
                           obs_mode=mode, max_episode_steps=10**6)
        env.reset(seed=0)
        calls[f"(a) {TASK.id} step, {copies} copies, {mode}"] = (
            lambda env=env: env.step(action))
    camera = Camera(env.unwrapped.task, (SIZE, SIZE), 3)  # (the pixel env's copies)
    calls[f"(a) the {copies} images alone (the camera)"] = camera.draw
    return calls


def single_calls() -> dict[str, Any]:
    """(b): a single env's 64 x 64 observation (and whole steps) three ways."""
    ours = gym.make(TASK.id, obs_mode="pixels")
    ours.reset(seed=0)
    inner = ours.unwrapped
    old = resized(PygameFrames(gym.make(TASK.id, render_mode="rgb_array")))
    old.reset(seed=0)
    new = resized(gym.make(TASK.id, render_mode="rgb_array"))
    new.reset(seed=0)
    action = np.array([0.3, 0.3], np.float32)
    return {
        "(b) observation: obs_mode='pixels' (rasteriser, 64x64)":
            lambda: inner._observation(inner.task.observe()),
        "(b) observation: AddRenderObservation, pygame 600x400 + pillow resize":
            lambda: old.observation(old.env.render()),
        "(b) observation: AddRenderObservation, rasteriser 600x400 + pillow resize":
            lambda: new.observation(new.env.render()),
        "(b) step: obs_mode='pixels'": lambda: _step(ours, action),
        "(b) step: AddRenderObservation, pygame + resize": lambda: _step(old, action),
    }


def _step(env: gym.Env, action: np.ndarray) -> None:
    _, _, terminated, truncated, _ = env.step(action)
    if terminated or truncated:
        env.reset()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--copies", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--seconds", type=float, default=0.3)
    args = parser.parse_args()
    calls = {**vector_calls(args.copies), **single_calls()}
    samples = alternate(calls, args.repeats, args.seconds)
    med = {name: statistics.median(s) for name, s in samples.items() if s}
    names = list(med)
    ratios = {
        "(a) pixel step / state step": med[names[1]] / med[names[0]],
        "(a) (pixel step - state step) / images alone":
            (med[names[1]] - med[names[0]]) / med[names[2]],
        "(b) pygame+resize observation / pixel observation": med[names[4]] / med[names[3]],
        "(b) rasteriser 600x400+resize observation / pixel observation":
            med[names[5]] / med[names[3]],
        "(b) pygame+resize step / pixel step": med[names[7]] / med[names[6]],
    }
    print(f"{'entry':<76} {'us per call':>12}")
    for name, seconds in med.items():
        print(f"{name:<76} {seconds * 1e6:>12.1f}")
    for name, ratio in ratios.items():
        print(f"{name:<76} {ratio:>12.2f}")
    print(json.dumps({"machine": platform.processor() or platform.machine(),
                      "copies": args.copies, "repeats": args.repeats,
                      "seconds": med, "ratios": ratios}, indent=1))


if __name__ == "__main__":
    main()
