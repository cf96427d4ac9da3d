"""The one drawing module: pygame-ce onto a Surface, world (metres) -> pixels.

Shared by the interactive viewer and the environments' ``render()``. Physics never knows
about pixels: terms describe themselves as :class:`~constrained_particles.terms.Shape`
primitives in world coordinates and this module maps and draws them. pygame is imported
lazily, so the core works without the ``render`` extra.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from .terms import Shape

if TYPE_CHECKING:
    import pygame

    from .system import ParticleSystem

BACKGROUND = (250, 250, 246)
PARTICLE = (30, 30, 40)
FIXED = (200, 40, 40)
ROD = (70, 70, 80)
WIRE = (120, 120, 130)
WALL = (185, 175, 160)
APPLIED = (235, 130, 20)
CONSTRAINT = (130, 60, 200)
MOUSE = (20, 160, 70)
GOAL = (20, 150, 60)
ANGULAR = (40, 110, 200)
TEXT = (20, 20, 20)
REGION = (226, 236, 250)


def _pygame() -> Any:
    try:
        import pygame
    except ImportError:  # pragma: no cover - depends on the installed extras
        from .extras import MissingExtra, install_hint

        raise MissingExtra("rendering needs the 'render' extra (missing: pygame-ce); "
                           f"install it with {install_hint('render')}") from None
    return pygame


def strain_colour(strain: float) -> tuple[int, int, int]:
    """Spring colour: blue when compressed, grey at rest, red when stretched (saturates at 20%)."""
    s = float(np.clip(strain / 0.2, -1.0, 1.0))
    grey = np.array([150, 150, 150])
    end = np.array([215, 40, 40]) if s > 0 else np.array([40, 90, 220])
    return tuple(int(c) for c in grey + abs(s) * (end - grey))


class Renderer:
    """Maps the world rectangle ``bounds = (xmin, ymin, xmax, ymax)`` (m) onto ``size = (w, h)``
    pixels, keeping the aspect ratio (the world rectangle is centred and grown to fit).

    >>> r = Renderer((0.0, 0.0, 2.0, 1.0), size=(400, 200))
    >>> r.world_to_pixel([[0.0, 1.0], [2.0, 0.0]]).tolist()
    [[0.0, 0.0], [400.0, 200.0]]
    """

    def __init__(self, bounds: Sequence[float], size: Sequence[int] = (640, 480)) -> None:
        xmin, ymin, xmax, ymax = (float(b) for b in bounds)
        if not (xmax > xmin and ymax > ymin):
            raise ValueError(f"bounds must satisfy xmin < xmax and ymin < ymax, got {bounds}")
        self.bounds = (xmin, ymin, xmax, ymax)
        self.resize(size)

    @classmethod
    def fit(cls, system: ParticleSystem, size: Sequence[int] = (640, 480), margin: float = 0.15,
            points: np.ndarray | None = None) -> Renderer:
        """A renderer whose view holds every particle, circular wire, wall boundary and ``points``
        (k, 2) of ``system``, plus ``margin`` (a fraction of the extent) on each side."""
        pts = [system.x]
        for shape in system.shapes():
            if shape.kind == "circle":
                r = np.asarray(shape.value)[:, None]
                pts += [shape.a - r, shape.a + r]
            elif shape.kind == "halfplane":
                pts.append(shape.a)
        if points is not None:
            pts.append(np.asarray(points, float).reshape(-1, 2))
        allp = np.concatenate(pts) if pts else np.zeros((1, 2))
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        extent = np.maximum(hi - lo, 0.5)
        centre = (lo + hi) / 2
        half = extent * (0.5 + margin)
        return cls((*(centre - half), *(centre + half)), size)

    def resize(self, size: Sequence[int]) -> None:
        """Change the pixel size, keeping the world aspect ratio (letterboxed)."""
        w, h = (int(s) for s in size)
        if w < 1 or h < 1:
            raise ValueError(f"size must be positive pixels, got {size}")
        self.size = (w, h)
        xmin, ymin, xmax, ymax = self.bounds
        self.scale = min(w / (xmax - xmin), h / (ymax - ymin))  # pixels per metre
        cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
        self._origin = np.array([w / 2 - cx * self.scale, h / 2 + cy * self.scale])

    @property
    def view(self) -> tuple[float, float, float, float]:
        """The world rectangle actually visible (m), which may exceed ``bounds``."""
        (x0, y1), (x1, y0) = self.pixel_to_world([[0, 0], self.size])
        return (x0, y0, x1, y1)

    def world_to_pixel(self, points: ArrayLike) -> np.ndarray:
        """World points (k, 2) in metres -> pixel coordinates (k, 2), y pointing down."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        return np.stack([self._origin[0] + p[:, 0] * self.scale,
                         self._origin[1] - p[:, 1] * self.scale], axis=1)

    def pixel_to_world(self, pixels: ArrayLike) -> np.ndarray:
        """Pixel coordinates (k, 2) -> world points (k, 2) in metres."""
        q = np.asarray(pixels, dtype=float).reshape(-1, 2)
        return np.stack([(q[:, 0] - self._origin[0]) / self.scale,
                         (self._origin[1] - q[:, 1]) / self.scale], axis=1)

    # ------------------------------------------------------------------ drawing
    def draw(self, surface: pygame.Surface, system: ParticleSystem, *,
             extra: Iterable[Shape] = (), forces: bool = True, constraint_forces: bool = False,
             hud: str | Sequence[str] | None = None) -> None:
        """Draw ``system`` (and ``extra`` shapes) onto ``surface``.

        ``forces`` toggles applied-force arrows, ``constraint_forces`` the constraint-force
        arrows. Arrows are scaled per frame and per kind (applied, constraint) so that the
        longest of each kind is 12% of the view width.
        ``hud`` is a line (or lines) of text drawn top-left.
        """
        pg = _pygame()
        surface.fill(BACKGROUND)
        shapes = [*system.shapes(constraint_forces=constraint_forces), *extra]
        order = {"region": 0, "halfplane": 0, "line": 1, "circle": 1, "marker": 2, "segment": 3,
                 "angle": 4, "arrow": 5}
        shapes.sort(key=lambda s: order.get(s.kind, 9))
        arrows = [s for s in shapes if s.kind == "arrow" and (forces or s.style == "constraint")]
        longest: dict[str, float] = {}
        for s in arrows:
            if len(s.b):
                top = float(np.max(np.linalg.norm(s.b, axis=1)))
                longest[s.style] = max(longest.get(s.style, 0.0), top)
        width = self.view[2] - self.view[0]
        for shape in shapes:
            if shape.kind != "arrow":
                getattr(self, f"_{shape.kind}")(pg, surface, shape)
        for shape in arrows:
            top = longest.get(shape.style, 0.0)
            self._arrows(pg, surface, shape, 0.12 * width / top if top > 0 else 0.0)
        self._particles(pg, surface, system)
        if hud:
            self._hud(pg, surface, [hud] if isinstance(hud, str) else list(hud))

    def rgb_array(self, system: ParticleSystem, *, extra: Iterable[Shape] = (),
                  forces: bool = True, constraint_forces: bool = False,
                  hud: str | Sequence[str] | None = None) -> np.ndarray:
        """Draw onto an off-screen surface (no display needed) and return (H, W, 3) uint8; the
        keywords are :meth:`draw`'s."""
        pg = _pygame()
        surface = pg.Surface(self.size)
        self.draw(surface, system, extra=extra, forces=forces,
                  constraint_forces=constraint_forces, hud=hud)
        return np.ascontiguousarray(pg.surfarray.array3d(surface).transpose(1, 0, 2))

    def _px(self, points: np.ndarray) -> list[tuple[float, float]]:
        return [tuple(p) for p in self.world_to_pixel(points)]

    def _far(self) -> float:
        x0, y0, x1, y1 = self.view
        return 4.0 * float(np.hypot(x1 - x0, y1 - y0))

    def _segment(self, pg: Any, surface: Any, shape: Shape) -> None:
        a, b = self.world_to_pixel(shape.a), self.world_to_pixel(shape.b)
        values = np.zeros(len(a)) if shape.value is None else shape.value
        for p, q, val in zip(a, b, values, strict=True):
            if shape.style == "rod":
                pg.draw.line(surface, ROD, p, q, 4)
            elif shape.style == "mouse":
                pg.draw.line(surface, MOUSE, p, q, 2)
                pg.draw.circle(surface, MOUSE, p, 5, 2)
            else:
                pg.draw.aaline(surface, strain_colour(val), p, q)

    def _circle(self, pg: Any, surface: Any, shape: Shape) -> None:
        for c, r in zip(self.world_to_pixel(shape.a), shape.value, strict=True):
            if shape.style == "pin":
                pg.draw.circle(surface, FIXED, c, 7, 2)
            else:
                pg.draw.circle(surface, WIRE, c, max(1.0, r * self.scale), 2)

    def _line(self, pg: Any, surface: Any, shape: Shape) -> None:
        far = self._far()
        for p, d in zip(shape.a, shape.b, strict=True):
            a, b = self.world_to_pixel([p - far * d, p + far * d])
            pg.draw.line(surface, WIRE, a, b, 2)

    def _halfplane(self, pg: Any, surface: Any, shape: Shape) -> None:
        far = self._far()
        for p, n in zip(shape.a, shape.b, strict=True):
            t = np.array([-n[1], n[0]])
            corners = [p - far * t, p + far * t, p + far * t + far * n, p - far * t + far * n]
            pg.draw.polygon(surface, WALL, self._px(np.array(corners)))
            a, b = self.world_to_pixel([p - far * t, p + far * t])
            pg.draw.line(surface, (120, 110, 95), a, b, 3)

    def _region(self, pg: Any, surface: Any, shape: Shape) -> None:
        """A shaded rectangle per (lower-left ``a``, upper-right ``b``) pair: an area where
        something is allowed (e.g. placing anchors)."""
        for lo, hi in zip(shape.a, shape.b, strict=True):
            (x0, y0), (x1, y1) = self.world_to_pixel([[lo[0], hi[1]], [hi[0], lo[1]]])
            x0, x1 = max(x0, -10.0), min(x1, self.size[0] + 10.0)
            y0, y1 = max(y0, -10.0), min(y1, self.size[1] + 10.0)
            rect = (x0, y0, max(x1 - x0, 0.0), max(y1 - y0, 0.0))
            pg.draw.rect(surface, REGION, rect)
            pg.draw.line(surface, ANGULAR, (x1, y0), (x1, y1), 1)

    def _angle(self, pg: Any, surface: Any, shape: Shape) -> None:
        for vertex, dev in zip(self.world_to_pixel(shape.a), shape.value, strict=True):
            s = float(np.clip(abs(dev) / 0.5, 0, 1))
            colour = tuple(int(c) for c in (1 - s) * np.array(ANGULAR) + s * np.array(FIXED))
            pg.draw.circle(surface, colour, vertex, 9, 2)

    def _marker(self, pg: Any, surface: Any, shape: Shape) -> None:
        x0, y0, x1, y1 = self.view
        for p in shape.a:
            top, bottom = self.world_to_pixel([[p[0], y1], [p[0], y0]])
            pg.draw.line(surface, (170, 220, 180), top, bottom, 1)
            c = self.world_to_pixel(p)[0]
            pg.draw.circle(surface, GOAL, c, 9, 3)
            pg.draw.line(surface, GOAL, c - (6, 0), c + (6, 0), 2)
            pg.draw.line(surface, GOAL, c - (0, 6), c + (0, 6), 2)

    def _arrows(self, pg: Any, surface: Any, shape: Shape, scale: float) -> None:
        colour = CONSTRAINT if shape.style == "constraint" else APPLIED
        starts = self.world_to_pixel(shape.a)
        ends = self.world_to_pixel(shape.a + scale * shape.b)
        for p, q in zip(starts, ends, strict=True):
            d = q - p
            length = float(np.hypot(*d))
            if length < 1.0:
                continue
            pg.draw.line(surface, colour, p, q, 2)
            u = d / length
            w = np.array([-u[1], u[0]])
            head = min(8.0, 0.4 * length)
            pg.draw.polygon(surface, colour, [tuple(q), tuple(q - head * u + 0.5 * head * w),
                                              tuple(q - head * u - 0.5 * head * w)])

    def _particles(self, pg: Any, surface: Any, system: ParticleSystem) -> None:
        radius = int(np.clip(0.012 * self.scale, 2, 6))
        for p, fixed in zip(self.world_to_pixel(system.x), system.fixed, strict=True):
            if fixed:
                pg.draw.rect(surface, FIXED, (p[0] - radius - 1, p[1] - radius - 1,
                                              2 * radius + 2, 2 * radius + 2))
            else:
                pg.draw.circle(surface, PARTICLE, p, radius)

    def _hud(self, pg: Any, surface: Any, lines: list[str]) -> None:
        if not pg.font.get_init():
            pg.font.init()
        font = pg.font.Font(None, 20)
        for k, line in enumerate(lines):
            surface.blit(font.render(line, True, TEXT), (8, 6 + 18 * k))
