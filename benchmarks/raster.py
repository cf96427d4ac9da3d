"""Benchmark (not a test): the compiled rasteriser (constrained_particles.raster).

The scene is what a pixel observation of a ~36-particle cloth task draws: a 6 x 6 cloth
(0.1 m spacing, 25 quad cells, opacity 0.6, jittered a little differently in every copy),
four segments (two drawn springs 0.01 m wide, two 1-pixel lines) and three disks (a goal and
two grippers, 0.03 m), in a view ``--box`` metres wide (1.2 m: the cloth spans 27 of 64
pixels). Timed, as medians of alternated rounds (each entry timed once per round, round after
round, so a change in the machine's load moves them all alike):

- a batch of ``--copies`` images (512) at 64 x 64, RGB and grey, in one call on this thread,
  and RGB split over two threads (``threads=2``);
- the same batch's coverage (the union of the cells, issue 51) on a 64 x 64 raster;
- one image (a batch of one) at 64 x 64 RGB against pygame drawing the same cloth system
  (``Renderer.rgb_array``, 600 x 400) and shrinking it to 64 x 64 (``smoothscale``);
- for scale, one step of ``--copies`` copies of ``ClothSlide-v0`` (state observations), the
  physics the images would come with.

    python benchmarks/raster.py [--copies 512] [--repeats 9] [--seconds 0.2] [--box 1.2]
    python benchmarks/raster.py --picture docs/raster.png

Prints a table, then the figures as JSON. ``--picture`` writes a sample image instead (a
folded and a flat cloth, RGB and grey, each at 64 and 128 pixels, scaled up 3x, no
anti-aliasing in the scaling) with a small PNG writer (zlib).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from constrained_particles import raster, scenes
from cparticles.bench import alternate

N = 6  #: the cloth's particles per side
SPACING = 0.1  #: m


def cloth_points(copies: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (copies, 36 + 3, 2) (m): the cloth, centred, jittered by 1 cm per copy, then a
    goal and two grippers; and the cells (25, 4)."""
    rng = np.random.default_rng(seed)
    col, row = np.meshgrid(np.arange(N), np.arange(N))
    flat = np.stack([(col.ravel() - (N - 1) / 2) * SPACING,
                     ((N - 1) / 2 - row.ravel()) * SPACING], axis=1)
    cloth = flat[None] + rng.normal(0.0, 0.01, (copies, N * N, 2))
    extra = np.broadcast_to([[0.4, 0.3], [-0.25, 0.25], [0.25, 0.25]], (copies, 3, 2))
    idx = (row * N + col)
    cells = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    return np.concatenate([cloth, extra], axis=1), cells


def layers(cells: np.ndarray) -> list[raster.Layer]:
    """The benchmark scene's layers (indices into :func:`cloth_points`)."""
    goal, grip_a, grip_b = N * N, N * N + 1, N * N + 2
    return [raster.Layer("polygons", cells, (40, 90, 200), opacity=0.6),
            raster.Layer("segments", [[grip_a, 0], [grip_b, N - 1]], (20, 160, 70), size=0.01),
            raster.Layer("segments", [[0, N * N - 1], [N - 1, N * (N - 1)]], (70, 70, 80),
                         size=1.0, unit="px"),
            raster.Layer("disks", [goal, grip_a, grip_b], (200, 40, 40), size=0.03)]


def view(size: int, box: float) -> raster.View:
    """A ``size`` x ``size`` image of the square ``box`` m wide centred on the origin."""
    return raster.View((-box / 2, -box / 2, box / 2, box / 2), height=size, width=size)


def pygame_frame() -> Any:
    """A call drawing the 6 x 6 cloth system at 600 x 400 with pygame and shrinking it to
    64 x 64, or None when pygame is not installed (the ``render`` extra)."""
    try:
        import pygame

        from constrained_particles.render import Renderer
    except ImportError:
        return None
    system = scenes.cloth(N, N, spacing=SPACING, wall_x=None)
    renderer = Renderer.fit(system, size=(600, 400))
    surface = pygame.Surface((600, 400))

    def frame() -> np.ndarray:
        renderer.draw(surface, system)
        small = pygame.transform.smoothscale(surface, (64, 64))
        return pygame.surfarray.array3d(small).transpose(1, 0, 2)

    return frame


def physics_step(copies: int) -> Any:
    """One step of ``copies`` copies of ClothSlide-v0 (state observations), or None when the
    environments cannot be made here."""
    try:
        import gymnasium as gym

        from envs.cloth_slide import TASK
    except ImportError:
        return None
    env = gym.make_vec(TASK.id, num_envs=copies,
                       vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, env.action_space.dtype)
    return lambda: env.step(action)


def measure(copies: int, repeats: int, seconds: float, box: float) -> dict[str, Any]:
    """Median seconds per call of each entry (see the module docstring), by name."""
    points, cells = cloth_points(copies)
    rgb = raster.Scene(layers(cells), view(64, box), channels=3)
    grey = raster.Scene(layers(cells), view(64, box), channels=1)
    out_rgb, out_grey = rgb.draw(points), grey.draw(points)
    one, out_one = points[:1], rgb.draw(points[:1])
    calls = {
        f"batch of {copies}, 64x64 RGB": lambda: rgb.draw(points, out_rgb),
        f"batch of {copies}, 64x64 RGB, 2 threads": lambda: rgb.draw(points, out_rgb,
                                                                     threads=2),
        f"batch of {copies}, 64x64 grey": lambda: grey.draw(points, out_grey),
        f"coverage of {copies}, 64x64": lambda: raster.coverage(points, cells, view(64, box)),
        "one image, 64x64 RGB": lambda: rgb.draw(one, out_one),
    }
    frame = pygame_frame()
    if frame is not None:
        calls["pygame 600x400 + smoothscale to 64x64"] = frame
    step = physics_step(copies)
    if step is not None:
        from envs.cloth_slide import TASK

        calls[f"{TASK.id} step, {copies} copies (state)"] = step
    samples = alternate(calls, repeats, seconds)
    return {name: statistics.median(s) if s else None for name, s in samples.items()}


def png(image: np.ndarray) -> bytes:
    """``image`` (H, W, 3) or (H, W, 1) uint8 as the bytes of a PNG file."""
    height, width, channels = image.shape
    rows = b"".join(b"\x00" + image[r].tobytes() for r in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    header = struct.pack(">IIBBBBB", width, height, 8, 2 if channels == 3 else 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
            + chunk(b"IEND", b""))


def picture(path: Path, box: float) -> None:
    """Write the sample picture (see the module docstring) to ``path``."""
    points, cells = cloth_points(2, seed=1)
    col = np.arange(N * N) % N
    folded = points[1, : N * N].copy()
    right = col >= N // 2  # the right half mirrored over the middle line, 2 mm higher
    folded[right, 0] = -folded[right, 0]
    folded[right, 1] += 0.02
    points[1, : N * N] = folded
    tiles = []
    for size in (64, 128):
        for channels in (3, 1):
            image = raster.Scene(layers(cells), view(size, box), channels=channels).draw(points)
            image = np.repeat(image, 3, axis=-1) if channels == 1 else image
            big = np.repeat(np.repeat(image, 3 * 128 // size, axis=1), 3 * 128 // size, axis=2)
            tiles.append(np.concatenate(list(big), axis=1))
    gap = np.full((8, tiles[0].shape[1], 3), 255, np.uint8)
    sheet = np.concatenate([tiles[0], gap, tiles[1], gap, tiles[2], gap, tiles[3]], axis=0)
    path.write_bytes(png(np.ascontiguousarray(sheet)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--copies", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--seconds", type=float, default=0.2)
    parser.add_argument("--box", type=float, default=1.2, help="view width (m)")
    parser.add_argument("--picture", type=Path, help="write the sample picture here and stop")
    args = parser.parse_args()
    if args.picture:
        picture(args.picture, args.box)
        return
    figures = measure(args.copies, args.repeats, args.seconds, args.box)
    print(f"{'entry':<52} {'us per call':>12} {'us per image':>13}")
    for name, seconds in figures.items():
        if seconds is None:
            print(f"{name:<52} {'(failed)':>12}")
            continue
        per = args.copies if name.startswith(("batch", "coverage")) else 1
        print(f"{name:<52} {seconds * 1e6:>12.1f} {seconds * 1e6 / per:>13.2f}")
    print(json.dumps({"machine": platform.processor() or platform.machine(),
                      "copies": args.copies, "box_m": args.box,
                      "seconds": figures}, indent=1))


if __name__ == "__main__":
    main()
