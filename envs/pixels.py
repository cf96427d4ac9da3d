"""Pixel observations: what a fixed camera over a task's view box sees, for every copy at once.

``obs_mode="pixels"`` observes a ``uint8`` image ``(H, W, C)`` (``Box(0, 255)``) and
``obs_mode="state_pixels"`` a ``Dict`` of the state observation (``"state"``) and the image
(``"pixels"``), on the single and the native vector env alike. ``pixel_size`` is the image's
size in pixels (an int for a square, or ``(H, W)``; 8 to 1024, default 64) and
``pixel_channels`` 3 (RGB) or 1 (grey, the luma of the colours).

A task says what is drawn with a :class:`Picture` (:meth:`envs.base.ParticleTask.picture`):
:class:`Mark` layers of filled polygons, lines with a width and disks, whose corners are
points of each copy: the copy's particles first, then the picture's fixed points (walls,
wires, regions: the same for every copy), then its moving points (per copy: the goal marker,
placed springs, the spring action). The default picture (:func:`default_picture`) is made from
the scene's blocks, so any task has one:

- a **cloth** (four particles joined by springs along the sides and both diagonals, a
  convex cell in the scene as built) is drawn as filled cells at opacity 0.6, so a fold, two
  sheets, shows darker; springs within the cloth are not drawn;
- other **springs** (placed ones: those with ``ks = kd = 0`` in a copy are not drawn) and
  the **spring action** as thin lines, **rods** as thicker dark lines;
- **walls** as filled half-planes, **wires** (straight and circular) and **pins**, and the
  shaded regions of the human view (``drawing(0)``'s ``"region"`` shapes: ClothPin's anchor
  region);
- particles outside a cloth as small **disks** (fixed ones red);
- the **goal**: a translucent green disk at ``(goal, goal_height)`` (one mark: each layer
  costs every copy a pass over its image).

All copies are drawn in one call of the compiled rasteriser (:mod:`constrained_particles.
raster`, docs/raster.md) over the task's fixed view box (letterboxed into the image), and copy
``i``'s bytes depend on its own points only: copy ``i`` of a vector env gives the bytes of a
single env seeded alike. Sizes of lines and disks are given in pixels of a 64-pixel image and
scale with the image (``min(H, W) / 64``). A single frame carries positions, not velocities:
stack frames (docs/pixels.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike

from constrained_particles import (
    CircularWire,
    DampedSpring,
    FixedPoint,
    LineWire,
    MouseSpring,
    Rod,
    Wall,
    raster,
)

if TYPE_CHECKING:
    from .base import ParticleTask

__all__ = ["DEFAULT_SIZE", "Camera", "Mark", "Picture", "check_pixel_channels",
           "check_pixel_size", "cloth_cells", "default_picture", "pixel_space"]

#: Default image size (pixels, square).
DEFAULT_SIZE = 64
#: Smallest and largest image side (pixels).
MIN_SIZE, MAX_SIZE = 8, 1024

BACKGROUND = (250, 250, 246)
CLOTH = (40, 90, 200)
SPRING = (120, 120, 120)
ROD = (60, 60, 70)
WIRE = (150, 150, 160)
WALL = (185, 175, 160)
PARTICLE = (30, 30, 40)
FIXED = (200, 40, 40)
GOAL = (20, 150, 60)
MOUSE = (20, 160, 70)
REGION = (200, 218, 245)


def check_pixel_size(pixel_size: object) -> tuple[int, int]:
    """``pixel_size`` as ``(height, width)`` pixels: an int (a square) or a pair, each side a
    whole number in [8, 1024] (ValueError naming the argument otherwise)."""
    sides = pixel_size if isinstance(pixel_size, (tuple, list)) else (pixel_size, pixel_size)
    ok = len(sides) == 2 and all(
        not isinstance(s, (bool, np.bool_)) and isinstance(s, (int, np.integer))
        and MIN_SIZE <= s <= MAX_SIZE for s in sides)
    if not ok:
        raise ValueError(f"pixel_size must be an int or an (H, W) pair of ints in "
                         f"[{MIN_SIZE}, {MAX_SIZE}], got {pixel_size!r}")
    return int(sides[0]), int(sides[1])


def check_pixel_channels(pixel_channels: object) -> int:
    """``pixel_channels``: 3 (RGB) or 1 (grey) (ValueError naming the argument otherwise)."""
    if isinstance(pixel_channels, (bool, np.bool_)) \
            or not isinstance(pixel_channels, (int, np.integer)) or pixel_channels not in (1, 3):
        raise ValueError(f"pixel_channels must be 3 (RGB) or 1 (grey), got {pixel_channels!r}")
    return int(pixel_channels)


def pixel_space(size: tuple[int, int], channels: int) -> spaces.Box:
    """One copy's image space: ``Box(0, 255, (H, W, C), uint8)``."""
    return spaces.Box(0, 255, (*size, channels), np.uint8)


@dataclass(frozen=True)
class Mark:
    """One layer of a :class:`Picture`: shapes of one colour (see :class:`raster.Layer`).

    ``kind`` is ``"polygons"`` (``index`` (m, k) corners), ``"segments"`` (``index`` (m, 2)
    ends; ``size`` the width) or ``"disks"`` (``index`` (m,) centres; ``size`` the radius);
    indices are into a copy's points (particles, then fixed, then moving points). ``size`` is
    in pixels of a 64-pixel image (scaled by ``min(H, W) / 64``); ``colour`` RGB 0..255;
    ``opacity`` in (0, 1].
    """

    kind: str
    index: ArrayLike
    colour: tuple[float, float, float]
    opacity: float = 1.0
    size: float = 0.0


def _no_points(task: Any) -> np.ndarray:
    return np.zeros((task.num_envs, 0, 2))


@dataclass
class Picture:
    """What the camera draws for a task: :class:`Mark` layers in order over ``background``,
    the world box ``box`` (m) the image shows, the copy's particle count ``n``, ``fixed``
    points (k, 2) m shared by every copy, and ``moving(task) -> (num_envs, g, 2)`` m, each
    copy's own further points (``moving_count`` = g; a point that is not finite draws nothing:
    the shapes using it are skipped)."""

    box: tuple[float, float, float, float]
    n: int
    marks: list[Mark] = field(default_factory=list)
    fixed: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    moving: Callable[[ParticleTask], np.ndarray] = _no_points
    moving_count: int = 0
    background: tuple[float, float, float] = BACKGROUND

    def add_fixed(self, points: ArrayLike) -> np.ndarray:
        """Append fixed points (k, 2) m; returns their indices. Fixed points come before
        moving ones (ValueError after :meth:`add_moving`: the moving points' indices would
        shift)."""
        if self.moving_count:
            raise ValueError("points: add fixed points before moving ones")
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        first = self.n + len(self.fixed)
        self.fixed = np.concatenate([self.fixed, p])
        return first + np.arange(len(p))

    def add_moving(self, count: int, points: Callable[[ParticleTask], np.ndarray]
                   ) -> np.ndarray:
        """Append ``count`` moving points made by ``points(task) -> (num_envs, count, 2)``;
        returns their indices."""
        first = self.n + len(self.fixed) + self.moving_count
        before, k = self.moving, self.moving_count
        if k == 0:
            self.moving = points
        else:
            self.moving = lambda task: np.concatenate([before(task), points(task)], axis=1)
        self.moving_count += count
        return first + np.arange(count)

    def layers(self, height: int, width: int) -> list[raster.Layer]:
        """The marks as rasteriser layers for an image of ``height x width`` pixels."""
        grow = min(height, width) / DEFAULT_SIZE
        out = []
        for m in self.marks:
            if len(np.asarray(m.index)) == 0:
                continue
            size = max(m.size * grow, 0.5) if m.kind != "polygons" else 0.0
            out.append(raster.Layer(m.kind, m.index, m.colour, opacity=m.opacity, size=size,
                                    unit="px"))
        return out

    def scene(self, height: int, width: int, channels: int) -> raster.Scene:
        """A compiled-rasteriser scene of the picture at ``height x width`` pixels.

        The leading marks that use fixed points only (walls, wires, regions: the same in
        every copy and every frame) are drawn once, here, into the scene's background image;
        each frame then draws the rest over it. Layers are laid one after another, each
        reading only the bytes below it, so the bytes are those of drawing every mark in
        every frame."""
        view = raster.View(self.box, height=height, width=width)
        layers = self.layers(height, width)
        lo, hi = self.n, self.n + len(self.fixed)
        static = 0
        while static < len(layers) and np.all(
                (np.asarray(layers[static].index) >= lo) & (np.asarray(layers[static].index) < hi)):
            static += 1
        scene = raster.Scene(layers[static:], view, channels=channels,
                             background=self.background)
        if static:
            points = np.zeros((1, hi, 2))
            points[0, lo:] = self.fixed
            behind = raster.Scene(layers[:static], view, channels=channels,
                                  background=self.background)
            scene.image[...] = behind.draw(points)[0]
        return scene


class Camera:
    """Draws ``task``'s :meth:`~envs.base.ParticleTask.picture` for every copy at ``size``
    ``(H, W)`` pixels with ``channels`` channels, in one rasteriser call (``threads``: ranges
    of copies drawn at once, the same bytes)."""

    def __init__(self, task: ParticleTask, size: tuple[int, int], channels: int,
                 threads: int = 1) -> None:
        self.task = task
        self.size, self.channels = check_pixel_size(size), check_pixel_channels(channels)
        self.threads = int(threads)
        self.picture = task.picture()
        self.scene = self.picture.scene(*self.size, self.channels)
        p, n = self.picture, task.n
        self._points = np.empty((task.num_envs, n + len(p.fixed) + p.moving_count, 2))
        self._points[:, n:n + len(p.fixed)] = p.fixed
        self.space = pixel_space(self.size, self.channels)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["picture"] = state["scene"] = None  # (made again: the moving points' closures)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.picture = self.task.picture()
        self.scene = self.picture.scene(*self.size, self.channels)

    def draw(self, out: np.ndarray | None = None) -> np.ndarray:
        """Every copy's image (num_envs, H, W, C) uint8 (into ``out`` if given)."""
        task, p = self.task, self.picture
        n, k = task.n, len(p.fixed)
        pts = self._points
        pts[:, :n] = task.positions()
        if p.moving_count:
            pts[:, n + k:] = p.moving(task)
        if out is None:  # (every byte is written: the background, then the layers)
            out = np.empty((task.num_envs, *self.scene.shape), np.uint8)
        return self.scene.draw(pts, out, threads=self.threads)


# ---------------------------------------------------------------------- the default picture
def cloth_cells(x: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The cells (m, 4) of any cloth among particles at ``x`` (n, 2) m joined by spring
    ``pairs`` (k, 2): four particles joined along the four sides of a quad and both its
    diagonals, the quad convex at ``x`` with every corner between 30 and 150 degrees and no
    other particle inside it. Corners counter-clockwise."""
    if not len(pairs):
        return np.zeros((0, 4), np.int64)
    near: dict[int, set[int]] = {}
    for a, b in pairs.tolist():
        near.setdefault(a, set()).add(b)
        near.setdefault(b, set()).add(a)
    found: set[tuple[int, ...]] = set()
    for a, b in pairs.tolist():
        common = sorted(near[a] & near[b])
        for u in range(len(common)):
            for w in range(u + 1, len(common)):
                c, d = common[u], common[w]
                if d in near[c]:
                    found.add(tuple(sorted((a, b, c, d))))
    cells = []
    for four in sorted(found):
        q = x[list(four)]
        centre = q.mean(axis=0)
        order = np.argsort(np.arctan2(q[:, 1] - centre[1], q[:, 0] - centre[0]))
        q = q[order]
        ok = True
        for k in range(4):
            e1, e2 = q[k] - q[k - 1], q[(k + 1) % 4] - q[k]
            turn = e1[0] * e2[1] - e1[1] * e2[0]
            size = math.hypot(*e1) * math.hypot(*e2)
            if not size or turn < 0.5 * size:  # (a corner between 30 and 150 degrees)
                ok = False
                break
        if not ok:
            continue
        others = np.setdiff1d(np.arange(len(x)), four)
        inside = np.ones(len(others), bool)
        for k in range(4):
            e = q[(k + 1) % 4] - q[k]
            r = x[others] - q[k]
            inside &= e[0] * r[:, 1] - e[1] * r[:, 0] > 0
        if not inside.any():
            cells.append(np.asarray(four)[order])
    return np.array(cells, dtype=np.int64).reshape(-1, 4)


def _tiled_rows(task: Any, index: int, kind: str) -> tuple[Any, int] | None:
    """The tiled system's block for ``single``'s block number ``index`` (forces) and its
    elements per copy, if the copies' elements are laid copy after copy."""
    block = task.system.forces[index] if kind == "forces" else task.system.constraints[index]
    one = task.single.forces[index] if kind == "forces" else task.single.constraints[index]
    per = len(one)
    if len(block) != per * task.num_envs:
        return None
    return block, per


def default_picture(task: ParticleTask, goal: bool = True) -> Picture:
    """The picture made from ``task``'s scene blocks (see the module docstring): any task has
    it; a task adds or replaces marks in its own :meth:`~envs.base.ParticleTask.picture`.
    ``goal=False`` leaves out the goal disk (a task whose goal is no point draws its own)."""
    s = task.single
    n = task.n
    pic = Picture(tuple(float(b) for b in task.view), n)
    xmin, ymin, xmax, ymax = pic.box
    far = 4.0 * math.hypot(xmax - xmin, ymax - ymin) + abs(xmin) + abs(xmax) + abs(ymin) \
        + abs(ymax)
    springs = [(k, f) for k, f in enumerate(s.forces) if isinstance(f, DampedSpring)]
    pairs = np.concatenate([np.stack([f.i, f.j], axis=1) for _, f in springs]
                           or [np.zeros((0, 2), np.int64)])
    # (cells from the scene as built, not from ``single``'s current state, which drawing a
    # frame overwrites: a crumpled cloth has cells that are no longer convex)
    cells = cloth_cells(task.park, pairs)
    in_cloth = np.zeros(n, bool)
    in_cloth[cells.ravel()] = True
    # walls (filled half-planes) and wires, behind everything
    walls, lines, rings = [], [], []
    seen: set[tuple[float, ...]] = set()
    for term in [*s.constraints, *s.forces]:
        if isinstance(term, Wall):
            for shape in term.shapes(s.x, s.v):
                for p, nrm in zip(shape.a, shape.b, strict=True):
                    t = np.array([-nrm[1], nrm[0]])
                    walls.append(pic.add_fixed([p - far * t, p + far * t,
                                                p + far * t + far * nrm,
                                                p - far * t + far * nrm]))
        elif isinstance(term, LineWire):
            for shape in term.shapes(s.x, s.v):
                for p, d in zip(shape.a, shape.b, strict=True):
                    # (one line per distinct wire: a wire block holds one element a particle)
                    key = (round(float(d[1] * p[0] - d[0] * p[1]), 12), *np.round(d, 12))
                    if key not in seen:
                        seen.add(key)
                        lines.append(pic.add_fixed([p - far * d, p + far * d]))
        elif isinstance(term, CircularWire):
            for c, r in zip(term.center, term.radius, strict=True):
                angle = 2 * math.pi * np.arange(48) / 48
                ring = pic.add_fixed(np.stack([c[0] + r * np.cos(angle),
                                               c[1] + r * np.sin(angle)], axis=1))
                rings += [[ring[k], ring[(k + 1) % 48]] for k in range(48)]
    pins = [pic.add_fixed(term.point) for term in s.constraints if isinstance(term, FixedPoint)
            and term.point is not None]
    # shaded regions of the human view (ClothPin's anchor region), the same for every copy
    regions = [pic.add_fixed([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]])
               for shape in task.drawing(0)[1] if shape.kind == "region"
               for lo, hi in zip(shape.a, shape.b, strict=True)]
    pic.marks.append(Mark("polygons", np.array(regions, np.int64).reshape(-1, 4), REGION))
    pic.marks.append(Mark("polygons", np.array(walls).reshape(-1, 4), WALL))
    wires = lines + rings
    pic.marks.append(Mark("segments", np.array(wires, np.int64).reshape(-1, 2), WIRE, size=0.75))
    goal_at = pic.add_moving(1, _goal_point) if goal else None
    # the cloth, then springs and rods
    pic.marks.append(Mark("polygons", cells, CLOTH, opacity=0.6))
    for k, f in springs:
        keep = np.flatnonzero(~(in_cloth[f.i] & in_cloth[f.j]))
        if not len(keep):
            continue
        ends = pic.add_moving(2 * len(keep), _spring_ends(k, keep))
        pic.marks.append(Mark("segments", ends.reshape(-1, 2), SPRING, size=0.75))
    rods = [np.stack([c.a, c.b], axis=1) for c in s.constraints if isinstance(c, Rod)]
    if rods:
        pic.marks.append(Mark("segments", np.concatenate(rods), ROD, size=1.5))
    # the spring action
    for k, f in enumerate(s.forces):
        if isinstance(f, MouseSpring) and len(f):
            ends = pic.add_moving(2 * len(f), _mouse_ends(k, len(f))).reshape(-1, 2)
            pic.marks.append(Mark("segments", ends, MOUSE, size=1.0))
            pic.marks.append(Mark("disks", ends[:, 0], MOUSE, size=1.0))
    # particles outside the cloth, fixed ones red; pins; the goal marker last
    loose = ~in_cloth & ~s.fixed
    pic.marks.append(Mark("disks", np.flatnonzero(loose), PARTICLE, size=1.0))
    pic.marks.append(Mark("disks", np.concatenate([np.flatnonzero(s.fixed & ~in_cloth),
                                                   *pins]).astype(np.int64), FIXED, size=1.0))
    if goal_at is not None:
        pic.marks.append(Mark("disks", goal_at[:1], GOAL, opacity=0.7, size=1.6))
    return pic


def fixed_marks(picture: Picture) -> int:
    """How many of ``picture``'s leading marks use fixed points only (walls, wires, regions:
    drawn once, behind everything; :meth:`Picture.scene`): a task's own marks that belong
    under the object go right after them."""
    lo, hi = picture.n, picture.n + len(picture.fixed)
    k = 0
    while k < len(picture.marks):
        index = np.asarray(picture.marks[k].index)
        if not np.all((index >= lo) & (index < hi)):
            break
        k += 1
    return k


def _goal_point(task: Any) -> np.ndarray:
    """Per copy, the goal point ``(goal, goal_height)``, (num_envs, 1, 2) m."""
    out = np.empty((task.num_envs, 1, 2))
    out[:, 0, 0] = task.goal
    out[:, 0, 1] = task.goal_height
    return out


def _spring_ends(index: int, keep: np.ndarray) -> Callable[[Any], np.ndarray]:
    """Per copy, the ends (num_envs, 2 len(keep), 2) m of the springs ``keep`` of force block
    ``index``, read from the tiled system (a copy's springs may differ: ClothPin places them);
    a spring with ``ks = kd = 0`` (unplaced) is not finite: not drawn."""
    def ends(task: Any) -> np.ndarray:
        tiled = _tiled_rows(task, index, "forces")
        N = task.num_envs
        if tiled is None:  # (not laid copy after copy: draw the single copy's springs)
            one = task.single.forces[index]
            i = (np.arange(N)[:, None] * task.n + one.i[keep]).ravel()
            j = (np.arange(N)[:, None] * task.n + one.j[keep]).ravel()
            off = np.zeros(i.shape, bool)
        else:
            block, per = tiled
            rows = (np.arange(N)[:, None] * per + keep).ravel()
            i, j = block.i[rows], block.j[rows]
            off = (block.ks[rows] == 0) & (block.kd[rows] == 0)
        x = task.system.x
        out = np.stack([x[i], x[j]], axis=1)  # (N * len(keep), 2, 2)
        out[off] = np.nan
        return out.reshape(N, 2 * len(keep), 2)
    return ends


def _mouse_ends(index: int, per: int) -> Callable[[Any], np.ndarray]:
    """Per copy, each of its ``per`` mouse springs' anchor and grabbed particle
    (num_envs, 2 per, 2) m (not finite while a spring is off), from force block ``index``
    of the tiled system (a copy's springs one after another)."""
    def ends(task: Any) -> np.ndarray:
        block = task.system.forces[index]
        if len(block) != task.num_envs * per:  # (not one block per copy: nothing drawn)
            return np.full((task.num_envs, 2 * per, 2), np.nan)
        out = np.stack([block.anchor, task.system.x[block.particle]], axis=1)
        out[~block.active] = np.nan
        return out.reshape(task.num_envs, 2 * per, 2)
    return ends
