"""A compiled rasteriser for small images: filled polygons (cloth cells, triangles) with exact
area anti-aliasing, segments with a width, disks; every copy of a batch in one call, no pygame.

**The transform** (:class:`View`). The world box ``(xmin, ymin, xmax, ymax)`` (m, y up) is
centred in an image of ``height x width`` pixels and scaled to fit (one scale for x and y,
the box letterboxed along the other axis), as :class:`~constrained_particles.render.Renderer`
does. A point ``(x, y)`` lands at pixel coordinates ``u = ox + s x``, ``v = oy - s y`` (``s``
pixels per metre, ``v`` down); pixel ``[row, col]`` is the unit square ``[col, col + 1] x
[row, row + 1]`` of those coordinates.

**Anti-aliasing** is exact coverage: the value a polygon gives a pixel is the area of the
polygon inside the pixel's square, by Green's theorem ``area(P n S) = sum over edges of the
integral of clamp(u(v) - col, 0, 1) dv`` over the part of the edge in the pixel's row, an
integral with a closed form (:func:`mean_clamp`). Each pixel's value is independent of the
others, exact for any simple polygon up to rounding (about 1e-15 of a pixel), whichever way
round its vertices go; a self-intersecting one (a cell turned inside out) gets the absolute
value of its winding number's integral. Segments are drawn as rectangles (butt ends) of the
given width, disks as a regular polygon of the disk's area with enough sides that its edge
stays within about :data:`SAGITTA` pixels of the circle (up to 40 pixels of radius).

**Layers and colour.** A :class:`Layer` is a set of shapes of one colour and opacity
``alpha``. Its shapes' coverages add up per pixel into a depth ``d`` (1 inside one sheet of
cloth, 2 in a fold, fractional at edges; adjacent cells sum to 1 along their shared edge, so
a flat cloth shows no seams), and the layer is laid over the image with transmittance
``T = (1 - alpha)^floor(d) (1 - alpha frac(d))``: exact alpha compositing of ``floor(d)``
sheets, linear between (``d`` above :data:`DEPTH_CAP` counts as the cap). Each layer rounds
to bytes, ``new = floor(old + (colour - old)(1 - T) + 1/2)``. A grey image (one channel) uses
the luma ``0.299 R + 0.587 G + 0.114 B`` of each colour.

**Coverage** (:func:`coverage`): the area of the union of cells, per copy, from the same
per-pixel coverages: each pixel counts ``min(1, d)`` of its area. Pixels the union's
boundary does not cross are exact (1 inside, 0 outside); a pixel the boundary crosses is
exact too unless two cells overlap in it (a fold line), where it may count up to its whole
area. So ``0 <= measured - true <= h^2 B`` for pixels ``h`` metres wide, ``B`` the number of
pixels crossed by the union's boundary where cells overlap: at most
``sqrt(2) P / h + E`` for a boundary of length ``P`` (m) made of ``E`` straight pieces, that
is an error of at most ``sqrt(2) P h + E h^2`` m^2 (:func:`coverage_bound`). A cloth lying
flat (no overlaps) is measured exactly, up to rounding.

**Batches and threads.** Copies share the layers (index arrays into each copy's points) and
each copy's pixels depend on its own points only: copy ``i`` of a batch has the bytes a batch
of one gets. The compiled entries release the GIL and take a range of copies ``[start,
stop)``, so a caller can give ranges to threads.

**Bad input** raises ValueError naming the argument before any compiled loop runs (shapes,
sizes, channels, a non-finite box, indices out of range). Positions that are not finite, or
that land more than :data:`FAR` pixels from the origin, draw nothing: the shape using them is
skipped, the rest of the image is drawn.

The numpy reference (:func:`draw_reference`, :func:`union_reference`) runs when the compiled
paths are off (``CPARTICLES_NUMBA=0``); the tests tie it to the compiled entries byte for
byte (and the coverage to the last bit). It is slow: Python loops over copies, shapes and
edges, numpy over pixels.

>>> view = View((0.0, 0.0, 1.0, 1.0), height=4, width=4)
>>> points = np.array([[[0.0, 0.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]]])
>>> scene = Scene([Layer("polygons", [[0, 1, 2, 3]], (0, 0, 0))], view, channels=1)
>>> scene.draw(points)[0, :, :, 0].tolist()
[[255, 255, 255, 255], [255, 255, 255, 255], [0, 0, 255, 255], [0, 0, 255, 255]]
>>> float(coverage(points, [[0, 1, 2, 3]], view)[0])
0.25
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from . import kernels

__all__ = ["DEPTH_CAP", "FAR", "KINDS", "Layer", "SAGITTA", "Scene", "View", "coverage",
           "coverage_bound", "draw_reference", "mean_clamp", "union_reference"]

#: layer kinds, by name, and the code the compiled entries see
KINDS = {"polygons": 0, "segments": 1, "disks": 2}
POLYGONS, SEGMENTS, DISKS = 0, 1, 2
MAX_SIDES = 64  #: most vertices of one polygon (cells, triangles, the polygon of a disk)
SAGITTA = 0.05  #: px, how far a disk's polygon may stray from its circle
DEPTH_CAP = 64  #: layers of one colour beyond which more do not darken a pixel
SNAP = 1e-9  #: a depth this close to a whole number of sheets (one or more) counts as that number
TABLED = 4  #: sheets up to which a layer's colours over each byte are tabled (the same bytes)
EMPTY = 1e-9  #: depth below which a pixel counts as uncovered (below a byte's rounding)
FAR = 1e9  #: px; a shape with a vertex further than this from the origin (or not finite) is skipped
#: px; an edge spanning less than this vertically is left out (its area, below this times the
#: image width, is far below a byte; the slope of a flatter edge could overflow)
FLAT = 1e-9
STRAIGHT = 1e-6  #: px; below this change across a pixel the coverage uses the edge's midpoint
LUMA = (0.299, 0.587, 0.114)  #: the weights of a grey image's channel (ITU-R BT.601)


@dataclass(frozen=True)
class View:
    """The world box ``box = (xmin, ymin, xmax, ymax)`` (m) in an image of ``height x width``
    pixels: centred, one scale for both axes (letterboxed), y up in the world.

    >>> v = View((0.0, 0.0, 2.0, 1.0), height=32, width=64)
    >>> v.scale, v.to_pixels([[0.0, 1.0], [2.0, 0.0]]).tolist()
    (32.0, [[0.0, 0.0], [64.0, 32.0]])
    """

    box: tuple[float, float, float, float]
    height: int = 64  #: pixels
    width: int = 64  #: pixels

    def __post_init__(self) -> None:
        try:
            box = tuple(float(b) for b in self.box)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"box must be four numbers (xmin, ymin, xmax, ymax), got "
                             f"{self.box!r}") from exc
        if len(box) != 4 or not all(math.isfinite(b) for b in box) \
                or not (box[2] > box[0] and box[3] > box[1]):
            raise ValueError(f"box must be four finite numbers (xmin, ymin, xmax, ymax) with "
                             f"xmin < xmax and ymin < ymax, got {self.box!r}")
        for name in ("height", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
                    or not 1 <= value <= 8192:
                raise ValueError(f"{name} must be a whole number of pixels in [1, 8192], got "
                                 f"{value!r}")
            object.__setattr__(self, name, int(value))
        object.__setattr__(self, "box", box)

    @property
    def scale(self) -> float:
        """Pixels per metre."""
        xmin, ymin, xmax, ymax = self.box
        return min(self.width / (xmax - xmin), self.height / (ymax - ymin))

    @property
    def origin(self) -> tuple[float, float]:
        """Pixel coordinates ``(ox, oy)`` of the world origin."""
        xmin, ymin, xmax, ymax = self.box
        s = self.scale
        return self.width / 2 - (xmin + xmax) / 2 * s, self.height / 2 + (ymin + ymax) / 2 * s

    @property
    def pixel_area(self) -> float:
        """The area of one pixel (m^2)."""
        return 1.0 / (self.scale * self.scale)

    def to_pixels(self, points: Any) -> np.ndarray:
        """World points (..., 2) in m -> pixel coordinates (..., 2): ``(ox + s x, oy - s y)``,
        column then row, the row growing downwards."""
        p = np.asarray(points, dtype=np.float64)
        ox, oy = self.origin
        s = self.scale
        return np.stack([ox + s * p[..., 0], oy - s * p[..., 1]], axis=-1)


@dataclass(frozen=True)
class Layer:
    """Shapes of one colour, drawn together (their coverages add: see the module docstring).

    ``kind`` and ``index`` (particle indices into each copy's points):

    - ``"polygons"``: ``index`` (m, k), the k corners of each polygon in order (3 <= k <= 64;
      cloth cells are quads, k = 4);
    - ``"segments"``: ``index`` (m, 2), each segment's ends; ``size`` is its full width;
    - ``"disks"``: ``index`` (m,), the centres; ``size`` is the radius.

    ``colour`` is RGB in 0..255; ``opacity`` in (0, 1] is one sheet's alpha; ``unit`` says
    whether ``size`` is in metres (``"m"``) or pixels (``"px"``).
    """

    kind: str
    index: Any
    colour: tuple[float, float, float]
    opacity: float = 1.0
    size: float = 0.0
    unit: str = "m"


class Packed(NamedTuple):
    """A scene's layers as the compiled entries read them (one row per layer)."""

    kind: np.ndarray  #: (L,) int64, a value of :data:`KINDS`
    count: np.ndarray  #: (L,) int64, shapes in the layer
    arity: np.ndarray  #: (L,) int64, indices per shape (k, 2 or 1)
    start: np.ndarray  #: (L,) int64, where the layer's indices start in ``index``
    index: np.ndarray  #: (total,) int64, every layer's indices, row after row
    size: np.ndarray  #: (L,) float64 px: half the width of a segment, a disk's polygon radius
    alpha: np.ndarray  #: (L,) float64, opacity
    colour: np.ndarray  #: (L, C) float64, in 0..255
    sides: np.ndarray  #: (L,) int64, the vertices of a disk's polygon
    units: np.ndarray  #: (L, MAX_SIDES, 2) float64, a disk polygon's unit vertices
    powers: np.ndarray  #: (L, DEPTH_CAP + 1) float64, ``(1 - alpha)^k``, multiplied in order
    table: np.ndarray  #: (L, TABLED + 1, 256, C) uint8, a byte under k whole sheets
    edges: np.ndarray  #: (E, 2) int64, the polygon layers' edges, each once: (lo, hi) indices
    edge_start: np.ndarray  #: (L + 1,) int64, layer l's edges are ``edges[edge_start[l]:...]``
    incidence: np.ndarray  #: (I,) int64, the cells (numbered in their layer) along each edge
    sense: np.ndarray  #: (I,) float64, +1 where the cell goes from lo to hi, -1 the other way
    incidence_start: np.ndarray  #: (E + 1,) int64, edge e's cells are ``incidence[...]``


def _disk_polygon(radius: float) -> tuple[int, float, np.ndarray]:
    """Sides, circumradius (px) and unit vertices of the regular polygon drawn for a disk of
    ``radius`` px: the fewest sides (8 to :data:`MAX_SIDES`) whose sagitta is within
    :data:`SAGITTA`, with the disk's area."""
    need = math.pi / math.acos(1.0 - SAGITTA / radius) if radius > SAGITTA else 8.0
    sides = int(min(MAX_SIDES, max(8, math.ceil(need))))
    angle = 2.0 * math.pi * np.arange(sides) / sides
    grow = math.sqrt(2.0 * math.pi / (sides * math.sin(2.0 * math.pi / sides)))
    units = np.zeros((MAX_SIDES, 2))
    units[:sides] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return sides, radius * grow, units


def _powers(alpha: float) -> list[float]:
    """``(1 - alpha)^k`` for k = 0 .. :data:`DEPTH_CAP`, one multiplication after another."""
    out = [1.0]
    for _ in range(DEPTH_CAP):
        out.append(out[-1] * (1.0 - alpha))
    return out


def _blend(old: np.ndarray, colour: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Bytes ``old`` (..., C) with ``colour`` (C,) laid over at opacity ``a`` (...,), rounded:
    ``floor(old + (colour - old) a + 1/2)``, at most 255."""
    old = old.astype(np.float64)
    new = old + (colour - old) * a[..., None]
    return np.minimum(np.floor(new + 0.5), 255.0).astype(np.uint8)


def _table(alpha: float, colour: np.ndarray) -> np.ndarray:
    """Each byte (256, C) under k = 0 .. :data:`TABLED` whole sheets of ``colour`` at opacity
    ``alpha``: :func:`_blend` at ``a = 1 - (1 - alpha)^k``, worked out as for any depth."""
    powers = _powers(alpha)
    old = np.repeat(np.arange(256.0)[:, None], len(colour), axis=1)
    return np.array([_blend(old, colour, np.full(256, 1.0 - powers[k] * (1.0 - alpha * 0.0)))
                     for k in range(TABLED + 1)])


def _layer_row(layer: Layer, number: int, scale: float, channels: int
               ) -> tuple[int, np.ndarray, float, float, np.ndarray, int, np.ndarray]:
    """Check ``layer`` (the ``number``-th) and return its kind code, indices (m, arity), size
    (px), opacity, colour (channels,), polygon sides and unit vertices."""
    where = f"layers[{number}]"
    if not isinstance(layer, Layer):
        raise ValueError(f"{where} must be a raster.Layer, got {type(layer).__name__}")
    if layer.kind not in KINDS:
        raise ValueError(f"{where}.kind must be one of {sorted(KINDS)}, got {layer.kind!r}")
    kind = KINDS[layer.kind]
    try:
        index = np.asarray(layer.index)
    except ValueError as exc:  # (ragged)
        raise ValueError(f"{where}.index must be a rectangular array of integers") from exc
    if index.dtype.kind not in "iu" and index.size:
        raise ValueError(f"{where}.index must hold integers, got dtype {index.dtype}")
    index = index.astype(np.int64)
    if kind == DISKS:
        index = index.reshape(-1, 1) if index.ndim == 1 or index.size == 0 else index
        ok = index.ndim == 2 and index.shape[1] == 1
    elif kind == SEGMENTS:
        index = index.reshape(0, 2) if index.size == 0 else index
        ok = index.ndim == 2 and index.shape[1] == 2
    else:
        ok = index.ndim == 2 and 3 <= index.shape[1] <= MAX_SIDES
    if not ok:
        wanted = {POLYGONS: f"(m, k) with 3 <= k <= {MAX_SIDES}", SEGMENTS: "(m, 2)",
                  DISKS: "(m,)"}[kind]
        raise ValueError(f"{where}.index must have shape {wanted} for {layer.kind}, got "
                         f"{np.shape(layer.index)}")
    if index.size and index.min() < 0:
        raise ValueError(f"{where}.index must be >= 0, got {index.min()}")
    rgb = np.asarray(layer.colour, dtype=np.float64)
    if rgb.shape != (3,) or not np.all((rgb >= 0) & (rgb <= 255)):
        raise ValueError(f"{where}.colour must be three numbers in 0..255 (RGB), got "
                         f"{layer.colour!r}")
    colour = rgb if channels == 3 else np.array([LUMA[0] * rgb[0] + LUMA[1] * rgb[1]
                                                 + LUMA[2] * rgb[2]])
    opacity = float(layer.opacity)
    if not 0.0 < opacity <= 1.0:
        raise ValueError(f"{where}.opacity must be in (0, 1], got {layer.opacity!r}")
    if layer.unit not in ("m", "px"):
        raise ValueError(f"{where}.unit must be 'm' or 'px', got {layer.unit!r}")
    size = float(layer.size) * (scale if layer.unit == "m" else 1.0)
    sides, units = index.shape[1], np.zeros((MAX_SIDES, 2))
    if kind != POLYGONS:
        if not (math.isfinite(size) and size > 0.0):
            raise ValueError(f"{where}.size must be a finite width or radius > 0, got "
                             f"{layer.size!r} {layer.unit}")
        if kind == SEGMENTS:
            size, sides = size / 2.0, 4
        else:
            sides, size, units = _disk_polygon(size)
    return kind, index, size, opacity, colour, sides, units


def pack(layers: Sequence[Layer], scale: float, channels: int) -> Packed:
    """The compiled entries' record of ``layers`` at ``scale`` pixels per metre, colours in
    ``channels`` (1 or 3) channels (checked; see :class:`Layer`)."""
    if isinstance(layers, Layer) or not isinstance(layers, Sequence):
        raise ValueError(f"layers must be a sequence of raster.Layer, got "
                         f"{type(layers).__name__}")
    rows = [_layer_row(layer, k, scale, channels) for k, layer in enumerate(layers)]
    counts = [len(r[1]) for r in rows]
    arity = [r[1].shape[1] for r in rows]
    start = np.concatenate([[0], np.cumsum([c * a for c, a in zip(counts, arity,
                                                                   strict=True)])])[:-1]
    flat = [r[1].ravel() for r in rows]
    shared = [_shared_edges(r[1] if r[0] == POLYGONS else r[1][:0, :0]) for r in rows]
    edge_start = np.cumsum([0] + [len(e[0]) for e in shared])
    incidence_start = np.cumsum([0] + [len(c) for e in shared for c in e[1]])
    return Packed(kind=np.array([r[0] for r in rows], dtype=np.int64),
                  count=np.array(counts, dtype=np.int64),
                  arity=np.array(arity, dtype=np.int64),
                  start=start.astype(np.int64),
                  index=np.concatenate(flat) if flat else np.zeros(0, np.int64),
                  size=np.array([r[2] for r in rows], dtype=np.float64),
                  alpha=np.array([r[3] for r in rows], dtype=np.float64),
                  colour=np.array([r[4] for r in rows], dtype=np.float64).reshape(
                      len(rows), channels),
                  sides=np.array([r[5] for r in rows], dtype=np.int64),
                  units=np.array([r[6] for r in rows], dtype=np.float64).reshape(
                      len(rows), MAX_SIDES, 2),
                  powers=np.array([_powers(r[3]) for r in rows], dtype=np.float64).reshape(
                      len(rows), DEPTH_CAP + 1),
                  table=np.array([_table(r[3], r[4]) for r in rows], dtype=np.uint8).reshape(
                      len(rows), TABLED + 1, 256, channels),
                  edges=np.concatenate([e[0] for e in shared] + [np.zeros((0, 2), np.int64)]),
                  edge_start=edge_start.astype(np.int64),
                  incidence=np.array([c for e in shared for cells in e[1] for c in cells],
                                     dtype=np.int64),
                  sense=np.array([d for e in shared for signs in e[2] for d in signs],
                                 dtype=np.float64),
                  incidence_start=incidence_start.astype(np.int64))


def _shared_edges(cells: np.ndarray) -> tuple[np.ndarray, list[list[int]], list[list[float]]]:
    """The edges of polygons ``cells`` (m, k), each once as (lo, hi) point indices (E, 2), in
    order of first appearance, with the cells along each and +1 where a cell goes from lo
    to hi, -1 the other way."""
    found: dict[tuple[int, int], int] = {}
    along: list[list[int]] = []
    signs: list[list[float]] = []
    for cell, corners in enumerate(cells.tolist()):
        for j, a in enumerate(corners):
            b = corners[(j + 1) % len(corners)]
            key = (min(a, b), max(a, b))
            if key not in found:
                found[key] = len(along)
                along.append([])
                signs.append([])
            along[found[key]].append(cell)
            signs[found[key]].append(1.0 if a <= b else -1.0)
    return np.array(list(found), dtype=np.int64).reshape(-1, 2), along, signs


def _points(points: Any, packed: Packed) -> np.ndarray:
    """``points`` as a C-contiguous float64 (N, n, 2) array, checked against the indices."""
    p = np.asarray(points)
    if p.dtype.kind not in "fiu" or p.ndim != 3 or p.shape[2] != 2:
        raise ValueError(f"points must be real numbers of shape (copies, n, 2) (m), got shape "
                         f"{p.shape} and dtype {p.dtype}")
    if packed.index.size and packed.index.max() >= p.shape[1]:
        raise ValueError(f"points has {p.shape[1]} points per copy but the layers use index "
                         f"{packed.index.max()}")
    return np.ascontiguousarray(p, dtype=np.float64)


def _threads(threads: int) -> int:
    """``threads``, checked."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ValueError(f"threads must be a whole number >= 1, got {threads!r}")
    return int(threads)


def _span(start: int, stop: int | None, copies: int) -> tuple[int, int]:
    """The checked copy range ``[start, stop)`` of ``copies`` copies."""
    stop = copies if stop is None else stop
    for name, value in (("start", start), ("stop", stop)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name} must be a whole number, got {value!r}")
    if not 0 <= start <= stop <= copies:
        raise ValueError(f"start and stop must satisfy 0 <= start <= stop <= {copies} "
                         f"(copies), got start={start}, stop={stop}")
    return int(start), int(stop)


class Scene:
    """Layers drawn in order, over a background, for one :class:`View` and channel count.

    ``channels`` is 3 (RGB) or 1 (grey); ``background`` is RGB in 0..255. The layers are
    checked and packed once, here; :meth:`draw` then draws any batch of copies.
    """

    def __init__(self, layers: Sequence[Layer], view: View, *, channels: int = 3,
                 background: Sequence[float] = (255, 255, 255)) -> None:
        if not isinstance(view, View):
            raise ValueError(f"view must be a raster.View, got {type(view).__name__}")
        if channels not in (1, 3) or isinstance(channels, bool):
            raise ValueError(f"channels must be 1 (grey) or 3 (RGB), got {channels!r}")
        self.view = view
        self.channels = int(channels)
        self.packed = pack(layers, view.scale, self.channels)
        rgb = np.asarray(background, dtype=np.float64)
        if rgb.shape != (3,) or not np.all((rgb >= 0) & (rgb <= 255)):
            raise ValueError(f"background must be three numbers in 0..255 (RGB), got "
                             f"{background!r}")
        grey = np.array([LUMA[0] * rgb[0] + LUMA[1] * rgb[1] + LUMA[2] * rgb[2]])
        self.background = np.floor((rgb if channels == 3 else grey) + 0.5).astype(np.uint8)
        self.image = np.empty(self.shape, dtype=np.uint8)  #: the background image
        self.image[...] = self.background

    @property
    def shape(self) -> tuple[int, int, int]:
        """One image's shape ``(height, width, channels)``."""
        return self.view.height, self.view.width, self.channels

    def draw(self, points: Any, out: np.ndarray | None = None, *, start: int = 0,
             stop: int | None = None, threads: int = 1) -> np.ndarray:
        """Draw copies ``[start, stop)`` (default all) of ``points`` (N, n, 2) (m) into ``out``
        (N, height, width, channels) uint8, C-contiguous (None: a new zeroed array) and return
        it; other copies of ``out`` are left as they are. ``threads`` > 1 splits the copies
        into that many ranges drawn at once (the same bytes)."""
        p = _points(points, self.packed)
        if out is None:
            out = np.zeros((p.shape[0], *self.shape), dtype=np.uint8)
        elif not (isinstance(out, np.ndarray) and out.dtype == np.uint8
                  and out.shape == (p.shape[0], *self.shape) and out.flags.c_contiguous
                  and out.flags.writeable):
            raise ValueError(f"out must be a writable C-contiguous uint8 array of shape "
                             f"{(p.shape[0], *self.shape)}, got "
                             f"{getattr(out, 'shape', None)} {getattr(out, 'dtype', type(out))}")
        lo, hi = _span(start, stop, p.shape[0])
        threads = _threads(threads)
        ox, oy = self.view.origin
        if kernels.ENABLED:  # (a plain tuple: Numba types it faster than a named one)
            _split(_draw_range, (p, tuple(self.packed), (ox, oy, self.view.scale), self.image,
                                 out), lo, hi, threads)
        else:
            draw_reference(p, self.packed, (ox, oy, self.view.scale), self.image, out, lo, hi)
        return out


@functools.cache
def _pool(threads: int) -> ThreadPoolExecutor:
    """The threads that draw ranges of copies at once (made once per count)."""
    return ThreadPoolExecutor(threads, thread_name_prefix="raster")


def _split(entry: Any, args: tuple, start: int, stop: int, threads: int) -> None:
    """``entry(*args, lo, hi)`` over ``[start, stop)``, in ``threads`` ranges at once (the
    compiled entries release the GIL; each writes only its own copies)."""
    cuts = np.linspace(start, stop, min(int(threads), max(stop - start, 1)) + 1).astype(int)
    if len(cuts) <= 2:
        entry(*args, start, stop)
        return
    for job in [_pool(len(cuts) - 1).submit(entry, *args, int(lo), int(hi))
                for lo, hi in zip(cuts[:-1], cuts[1:], strict=True)]:
        job.result()


def coverage(points: Any, cells: Any, view: View, *, maps: bool = False, threads: int = 1
             ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Area (m^2) of the union of ``cells`` (m, k) (polygons by particle index) of each copy
    of ``points`` (N, n, 2) (m) within the image of ``view``, measured on its pixels: each
    pixel counts ``min(1, d)`` of its area, ``d`` the sum of the cells' exact coverages of it.

    Never below the true area, and above it by at most :func:`coverage_bound` (see the module
    docstring); exact (to rounding) for cells that do not overlap. With ``maps``, returns
    ``(areas (N,), maps (N, height, width))``, the per-pixel fractions ``min(1, d)``.
    ``threads`` as in :meth:`Scene.draw`.
    """
    if not isinstance(view, View):
        raise ValueError(f"view must be a raster.View, got {type(view).__name__}")
    try:
        cells = np.asarray(cells)
    except ValueError as exc:  # (ragged)
        raise ValueError("cells must be a rectangular (m, k) array of integers") from exc
    if cells.ndim != 2:
        raise ValueError(f"cells must have shape (m, k), got {cells.shape}")
    packed = pack([Layer("polygons", cells, (0, 0, 0))], view.scale, 1)
    p = _points(points, packed)
    threads = _threads(threads)
    areas = np.zeros(p.shape[0])
    pixels = np.zeros((p.shape[0] if maps else 0, view.height, view.width))
    ox, oy = view.origin
    if kernels.ENABLED:
        _split(_union_range, (p, tuple(packed), (ox, oy, view.scale), pixels, areas), 0,
               p.shape[0], threads)
    else:
        union_reference(p, packed, (ox, oy, view.scale), pixels, areas, 0, p.shape[0])
    return (areas, pixels) if maps else areas


def coverage_bound(perimeter: float, pieces: int, view: View) -> float:
    """The most (m^2) :func:`coverage` can over-measure a union whose boundary is ``pieces``
    straight pieces of total length ``perimeter`` (m): ``sqrt(2) P h + E h^2``, ``h`` the
    pixel size (m), since such a boundary crosses at most ``sqrt(2) P / h + E`` pixels."""
    h = 1.0 / view.scale
    return math.sqrt(2.0) * perimeter * h + pieces * h * h


# ------------------------------------------------------------------------ scalar geometry
# Plain Python on floats, called as they are by the reference and compiled by Numba for the
# compiled entries: one formula, the same operations in the same order, the same bits.
def crossing(ax: float, ay: float, bx: float, by: float, cx: float, cy: float, dx: float,
             dy: float) -> float:
    """Where segment AB properly crosses segment CD, as the fraction ``t`` of the way from A
    to B (``X = A + t (B - A)``), or -1 when they do not cross (touching does not count)."""
    d1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)  # C, D on either side of line AB
    d2 = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)
    d3 = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx)  # A, B on either side of line CD
    d4 = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx)
    if d1 * d2 < 0.0 and d3 * d4 < 0.0:
        return d3 / (d3 - d4)
    return -1.0


def twisted(q: np.ndarray) -> bool:
    """Whether the quad ``q`` (4, 2) is turned inside out: a bow-tie, AB crossing CD or BC
    crossing DA (as :func:`lobes` finds, without making the lobes)."""
    return (crossing(q[0, 0], q[0, 1], q[1, 0], q[1, 1], q[2, 0], q[2, 1], q[3, 0], q[3, 1])
            >= 0.0 or crossing(q[1, 0], q[1, 1], q[2, 0], q[2, 1], q[3, 0], q[3, 1], q[0, 0],
                               q[0, 1]) >= 0.0)


def lobes(q: np.ndarray) -> tuple[bool, np.ndarray]:
    """Whether the quad ``q`` (4, 2) is turned inside out (a bow-tie: AB crosses CD, or BC
    crosses DA) and, if so, its two lobes as triangles (2, 3, 2). A cell whose side crosses
    the opposite one covers both lobes once; by its winding number one lobe would count
    negative."""
    ax, ay, bx, by = q[0, 0], q[0, 1], q[1, 0], q[1, 1]
    cx, cy, dx, dy = q[2, 0], q[2, 1], q[3, 0], q[3, 1]
    out = np.zeros((2, 3, 2))
    corners = np.zeros((5, 2))  # A, B, C, D and the crossing X
    corners[:4] = q[:4]
    t = crossing(ax, ay, bx, by, cx, cy, dx, dy)
    if t >= 0.0:
        corners[4, 0], corners[4, 1] = ax + t * (bx - ax), ay + t * (by - ay)
        order = ((4, 1, 2), (4, 3, 0))  # XBC and XDA
    else:
        t = crossing(bx, by, cx, cy, dx, dy, ax, ay)
        if t < 0.0:
            return False, out
        corners[4, 0], corners[4, 1] = bx + t * (cx - bx), by + t * (cy - by)
        order = ((0, 1, 4), (4, 2, 3))  # ABX and XCD
    for k in range(2):
        for j in range(3):
            out[k, j, 0], out[k, j, 1] = corners[order[k][j], 0], corners[order[k][j], 1]
    return True, out


def turn(p: np.ndarray, count: int) -> float:
    """+1 or -1, the sign of the signed area of polygon ``p[:count]`` (pixels), 0 for none:
    the weight that makes its coverage positive whichever way round it goes."""
    twice = 0.0
    for e in range(count):
        f = e + 1 if e + 1 < count else 0
        twice = twice + (p[e, 0] * p[f, 1] - p[f, 0] * p[e, 1])
    return 0.0 if twice == 0.0 else (1.0 if twice > 0.0 else -1.0)


# ------------------------------------------------------------------------ numpy reference
def _ramp(u: np.ndarray) -> np.ndarray:
    """The integral of ``clamp(t, 0, 1)`` from 0 to ``u``."""
    return np.where(u <= 0.0, 0.0, np.where(u < 1.0, 0.5 * u * u, u - 0.5))


def mean_clamp(ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Mean of ``clamp(u, 0, 1)`` as ``u`` runs linearly from ``ua`` to ``ub`` (px): the
    fraction of a pixel's width an edge piece leaves on its left, averaged over the piece."""
    du = ub - ua
    with np.errstate(divide="ignore", invalid="ignore"):
        full = (_ramp(ub) - _ramp(ua)) / du
    mid = 0.5 * (ua + ub)  # (exact within one pixel: no division)
    within = (ua >= 0.0) & (ua <= 1.0) & (ub >= 0.0) & (ub <= 1.0)
    return np.where(np.abs(du) < STRAIGHT, np.minimum(np.maximum(mid, 0.0), 1.0),
                    np.where(within, mid, full))


def _pixels_reference(points: np.ndarray, transform: tuple[float, float, float]
                      ) -> np.ndarray:
    """Pixel coordinates ``(ox + s x, oy - s y)`` of ``points`` (..., 2) (m)."""
    ox, oy, s = transform
    return np.stack([ox + s * points[..., 0], oy - s * points[..., 1]], axis=-1)


def _shapes_reference(pixels: np.ndarray, packed: Packed, layer: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel vertices (N, m, sides, 2) of every shape of ``layer`` in every copy of ``pixels``
    (N, n, 2), and which ones are drawn (N, m) (finite, within :data:`FAR`, segments of
    nonzero length)."""
    kind, arity = packed.kind[layer], packed.arity[layer]
    first = packed.start[layer]
    idx = packed.index[first:first + packed.count[layer] * arity].reshape(-1, arity)
    u, v = pixels[:, idx, 0], pixels[:, idx, 1]
    drawn = np.ones(u.shape[:2], dtype=bool)
    if kind == POLYGONS:
        verts = np.stack([u, v], axis=-1)
    elif kind == SEGMENTS:
        ax, ay, bx, by = u[..., 0], v[..., 0], u[..., 1], v[..., 1]
        dx, dy = bx - ax, by - ay
        length = np.sqrt(dx * dx + dy * dy)
        hw = packed.size[layer]
        nx, ny = -dy / length * hw, dx / length * hw
        verts = np.stack([np.stack([ax + nx, ay + ny], -1), np.stack([bx + nx, by + ny], -1),
                          np.stack([bx - nx, by - ny], -1), np.stack([ax - nx, ay - ny], -1)],
                         axis=2)
        drawn = length > 0.0
    else:
        sides = packed.sides[layer]
        unit = packed.units[layer, :sides]
        radius = packed.size[layer]
        verts = np.stack([u[..., :1] + radius * unit[:, 0], v[..., :1] + radius * unit[:, 1]],
                         axis=-1)
    drawn = drawn & np.all(np.abs(verts) <= FAR, axis=(2, 3))
    return verts, drawn


def _orientation(verts: np.ndarray, drawn: np.ndarray) -> np.ndarray:
    """+1 or -1, the sign of the signed area of each polygon ``verts`` (..., k, 2) (0 for no
    area or not ``drawn``): it makes each polygon's coverage positive whichever way round its
    vertices go."""
    k = verts.shape[-2]
    twice = np.zeros(verts.shape[:-2])
    for e in range(k):
        a, b = verts[..., e, :], verts[..., (e + 1) % k, :]
        twice = twice + (a[..., 0] * b[..., 1] - b[..., 0] * a[..., 1])
    return np.where(drawn, np.sign(twice), 0.0)


def _add_edge_reference(a: np.ndarray, b: np.ndarray, w: float, D: np.ndarray,
                        box: list[int]) -> None:
    """Add the edge from ``a`` to ``b`` (pixels), weighted by ``w`` (the sum of the signed
    orientations of the polygons it bounds), to the row differences ``D`` (H, W + 1), whose
    running sums along each row are the depth; grow ``box`` (r0, r1, c0, c1): the rows
    ``[r0, r1)`` and columns ``[c0, c1]`` written.

    In each row the edge's piece, from ``xl`` to ``xh`` over a height ``h`` (signed, times
    ``w``), leaves the depth ``g(c) = h (mean_clamp(xl - c, xh - c) - 1)`` in column ``c``
    (Green's theorem: the coverage of a pixel is the sum over the boundary of ``clamp(x - c, 0,
    1) dy``, here less ``h``, so that it is 0 left of the piece and ``-h`` right of it): it adds
    ``g(c) - g(c - 1)`` at the columns it crosses, columns left of the image gathered into
    column 0."""
    height, width = D.shape[0], D.shape[1] - 1
    (ax, ay), (bx, by) = a, b
    if abs(by - ay) < FLAT:
        return
    top, bottom, sign = (ay, by, 1.0) if ay < by else (by, ay, -1.0)
    rows = np.arange(max(0, math.floor(top)), min(height, math.ceil(bottom)))
    lo, hi = np.maximum(top, rows), np.minimum(bottom, rows + 1.0)
    slope = (bx - ax) / (by - ay)
    xl, xh = ax + (lo - ay) * slope, ax + (hi - ay) * slope
    h = w * sign * (hi - lo)
    first = np.maximum(np.floor(np.clip(np.minimum(xl, xh), -1.0, width + 1.0)), 0.0)
    edge = np.ceil(np.clip(np.maximum(xl, xh), -1.0, width + 1.0))
    last = np.maximum(np.minimum(edge, float(width)), first)  # (left of the image: column 0)
    live = (hi > lo) & (first <= width - 1)
    right = (hi > lo) & (first > width - 1)  # right of the image: the depth runs on to its edge
    if (live | right).any():
        written = rows[live | right]
        box[0], box[1] = min(box[0], int(written.min())), max(box[1], int(written.max()) + 1)
    if right.any():
        box[3] = width
    if not live.any():
        return
    box[2], box[3] = min(box[2], int(first[live].min())), max(box[3], int(last[live].max()))
    runs = np.where(live, last - first + 1.0, 0.0).astype(np.int64)
    pick = np.repeat(np.arange(len(rows)), runs)
    at = np.repeat(np.cumsum(runs) - runs, runs)
    col = first[pick] + (np.arange(runs.sum()) - at)
    g = np.where(col < edge[pick],
                 h[pick] * (mean_clamp(xl[pick] - col, xh[pick] - col) - 1.0), -h[pick])
    prev = np.where(np.arange(len(g)) == at, 0.0, np.concatenate([[0.0], g[:-1]]))
    D[rows[pick], col.astype(np.int64)] += g - prev


def _layer_reference(pixels: np.ndarray, packed: Packed, layer: int, verts: np.ndarray,
                     drawn: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Layer ``layer`` of one copy (``pixels`` (n, 2); its shapes ``verts`` (m, sides, 2) and
    ``drawn`` (m,)) through ``D``: returns the depth over the pixels covered and their box
    ``[r0, r1, c0, c1]`` (rows ``[r0, r1)``, columns ``[c0, c1)``), and leaves ``D`` zero.

    A polygon layer adds each edge of its cells once, weighted by the orientations of the
    cells on either side (a flat cloth's inner edges weigh 0 and are skipped; a fold line 2),
    and a quad turned inside out as its two lobes (:func:`lobes`); segments and disks add
    their own polygons' edges."""
    height, width = D.shape[0], D.shape[1] - 1
    box = [height, 0, width, 0]
    orient = _orientation(verts, drawn)
    tangled = []
    if packed.kind[layer] == POLYGONS:
        if verts.shape[1] == 4:  # bow-ties: out of the shared edges, drawn as their two lobes
            for cell in np.flatnonzero(orient):
                if twisted(verts[cell]):
                    orient[cell] = 0.0
                    tangled.append(lobes(verts[cell])[1])
        for e in range(packed.edge_start[layer], packed.edge_start[layer + 1]):
            w = 0.0
            for k in range(packed.incidence_start[e], packed.incidence_start[e + 1]):
                w = w + orient[packed.incidence[k]] * packed.sense[k]
            if w != 0.0:
                lo, hi = packed.edges[e]
                _add_edge_reference(pixels[lo], pixels[hi], w, D, box)
        for parts in tangled:
            for part in parts:
                w = turn(part, 3)
                for j in range(3 if w else 0):
                    _add_edge_reference(part[j], part[(j + 1) % 3], w, D, box)
    else:
        for shape in np.flatnonzero(orient):
            sides = verts.shape[1]
            for j in range(sides):
                _add_edge_reference(verts[shape, j], verts[shape, (j + 1) % sides],
                                    orient[shape], D, box)
    r0, r1, c0, c1 = box
    if r0 >= r1:
        return np.zeros((0, 0)), box
    depth = np.cumsum(D[r0:r1, c0:c1 + 1], axis=1)[:, :-1]  # (summed in order, as compiled)
    D[r0:r1, c0:c1 + 1] = 0.0
    return depth, box


def draw_reference(points: np.ndarray, packed: Packed, transform: tuple[float, float, float],
                   background: np.ndarray, out: np.ndarray, start: int, stop: int) -> None:
    """The numpy reference of the compiled draw: copies ``[start, stop)`` of ``points`` (N, n,
    2) onto the image ``background`` (H, W, C) into ``out`` (N, H, W, C) uint8, with
    ``transform = (ox, oy, s)`` (pixels, pixels, pixels per metre)."""
    height, width = out.shape[1:3]
    D = np.zeros((height, width + 1))
    with np.errstate(all="ignore"):  # (positions not finite or far: those shapes are skipped)
        pixels = _pixels_reference(points[start:stop], transform)
        shapes = [_shapes_reference(pixels, packed, layer) for layer in range(len(packed.kind))]
        for i in range(start, stop):
            out[i] = background
            for layer, (verts, drawn) in enumerate(shapes):
                d, (r0, r1, c0, c1) = _layer_reference(pixels[i - start], packed, layer,
                                                       verts[i - start], drawn[i - start], D)
                if r0 >= r1:
                    continue
                whole = np.floor(d + 0.5)
                d = np.where((whole >= 1.0) & (np.abs(d - whole) <= SNAP), whole, d)
                capped = np.minimum(d, float(DEPTH_CAP))
                sheets = np.floor(capped)
                T = packed.powers[layer][sheets.astype(np.int64).clip(0)] * (
                    1.0 - packed.alpha[layer] * (capped - sheets))
                old = out[i, r0:r1, c0:c1]
                new = _blend(old, packed.colour[layer], 1.0 - T)
                out[i, r0:r1, c0:c1] = np.where((d > EMPTY)[..., None], new, old)


def union_reference(points: np.ndarray, packed: Packed, transform: tuple[float, float, float],
                    maps: np.ndarray, areas: np.ndarray, start: int, stop: int) -> None:
    """The numpy reference of the compiled coverage: for copies ``[start, stop)`` the area
    (m^2) of the union of layer 0's polygons into ``areas``, and the per-pixel fractions into
    ``maps`` (N, H, W) unless it has no copies (its shape gives H and W)."""
    D = np.zeros((maps.shape[1], maps.shape[2] + 1))
    s = transform[2]
    with np.errstate(all="ignore"):  # (positions not finite or far: those cells are skipped)
        pixels = _pixels_reference(points[start:stop], transform)
        verts, drawn = _shapes_reference(pixels, packed, 0)
        for i in range(start, stop):
            if maps.shape[0]:
                maps[i] = 0.0
            d, (r0, r1, c0, c1) = _layer_reference(pixels[i - start], packed, 0,
                                                   verts[i - start], drawn[i - start], D)
            if r0 >= r1:
                areas[i] = 0.0
                continue
            fraction = np.where(d > EMPTY, np.minimum(d, 1.0), 0.0)
            areas[i] = np.cumsum(fraction.ravel())[-1] / (s * s)  # (in order, as compiled)
            if maps.shape[0]:
                maps[i, r0:r1, c0:c1] = fraction


# ------------------------------------------------------------------------ compiled entries
_draw_range = None  #: compiled :func:`draw_reference`, or None when the compiled paths are off
_union_range = None  #: compiled :func:`union_reference`, or None

if kernels.ENABLED:
    from numba.extending import register_jitable

    from .jit import njit

    register_jitable(crossing)  # (for lobes and twisted, compiled as they are)
    _twisted = njit(twisted)
    _lobes = njit(lobes)
    _turn = njit(turn)

    @njit
    def _mean_clamp(ua: float, ub: float) -> float:  # pragma: no cover - compiled
        """:func:`mean_clamp` of one pair."""
        du = ub - ua
        if abs(du) < STRAIGHT:
            return min(max(0.5 * (ua + ub), 0.0), 1.0)
        if 0.0 <= ua <= 1.0 and 0.0 <= ub <= 1.0:
            return 0.5 * (ua + ub)
        fa = 0.0 if ua <= 0.0 else (0.5 * ua * ua if ua < 1.0 else ua - 0.5)
        fb = 0.0 if ub <= 0.0 else (0.5 * ub * ub if ub < 1.0 else ub - 0.5)
        return (fb - fa) / du

    @njit
    def _vertices(pixels: np.ndarray, index: np.ndarray, base: int, kind: int, size: float,
                  sides: int, units: np.ndarray, layer: int,
                  verts: np.ndarray) -> int:  # pragma: no cover - compiled
        """The segment or disk whose indices start at ``index[base]`` (``kind``; its layer's
        ``size``, ``sides`` and ``units``) in ``verts`` (pixels), from one copy's ``pixels``
        (n, 2), as :func:`_shapes_reference` makes them; returns the vertex count, 0 when the
        shape is skipped. (The packed record's fields arrive one by one: reading arrays out of
        a record inside the loops costs Numba a reference count each time, some 20 times the
        work.)"""
        if kind == SEGMENTS:
            count = 4
            a, b = index[base], index[base + 1]
            ax, ay, bx, by = pixels[a, 0], pixels[a, 1], pixels[b, 0], pixels[b, 1]
            dx, dy = bx - ax, by - ay
            length = math.sqrt(dx * dx + dy * dy)
            if not length > 0.0:
                return 0
            nx, ny = -dy / length * size, dx / length * size
            verts[0, 0], verts[0, 1] = ax + nx, ay + ny
            verts[1, 0], verts[1, 1] = bx + nx, by + ny
            verts[2, 0], verts[2, 1] = bx - nx, by - ny
            verts[3, 0], verts[3, 1] = ax - nx, ay - ny
        else:
            count = sides
            c = index[base]
            cx, cy = pixels[c, 0], pixels[c, 1]
            for j in range(count):
                verts[j, 0] = cx + size * units[layer, j, 0]
                verts[j, 1] = cy + size * units[layer, j, 1]
        for j in range(count):
            if not (abs(verts[j, 0]) <= FAR and abs(verts[j, 1]) <= FAR):
                return 0
        return count

    @njit
    def _add_edge(ax: float, ay: float, bx: float, by: float, w: float, D: np.ndarray,
                  rows: np.ndarray, span: np.ndarray) -> None:  # pragma: no cover - compiled
        """:func:`_add_edge_reference` of the edge from ``(ax, ay)`` to ``(bx, by)``, growing
        ``rows`` (r0, r1), the rows written, and ``span[r]`` (c0, c1), the columns written
        in row r (the running sums then skip the rest of the layer's box, where ``D`` is 0 and
        the depth stays below :data:`EMPTY`: the same bytes)."""
        height, width = D.shape[0], D.shape[1] - 1
        if abs(by - ay) < FLAT:
            return
        top, bottom, sign = (ay, by, 1.0) if ay < by else (by, ay, -1.0)
        slope = (bx - ax) / (by - ay)
        for r in range(max(0, math.floor(top)), min(height, math.ceil(bottom))):
            lo, hi = max(top, float(r)), min(bottom, float(r + 1))
            if not hi > lo:
                continue
            xl, xh = ax + (lo - ay) * slope, ax + (hi - ay) * slope
            h = w * sign * (hi - lo)
            first = max(math.floor(min(max(min(xl, xh), -1.0), width + 1.0)), 0)
            if first > width - 1:  # right of the image: the depth runs on to its edge
                rows[0], rows[1] = min(rows[0], r), max(rows[1], r + 1)
                span[r, 1] = width
                continue
            edge = math.ceil(min(max(max(xl, xh), -1.0), width + 1.0))
            last = max(min(edge, width), first)
            rows[0], rows[1] = min(rows[0], r), max(rows[1], r + 1)
            span[r, 0], span[r, 1] = min(span[r, 0], first), max(span[r, 1], last)
            prev = 0.0
            for c in range(first, last + 1):
                g = h * (_mean_clamp(xl - c, xh - c) - 1.0) if c < edge else -h
                D[r, c] += g - prev
                prev = g

    @njit
    def _layer(pixels: np.ndarray, packed: tuple, layer: int, orient: np.ndarray,
               tangled: np.ndarray, D: np.ndarray, verts: np.ndarray, rows: np.ndarray,
               span: np.ndarray) -> None:  # pragma: no cover - compiled
        """:func:`_layer_reference` up to the running sums: every shape of ``layer`` in one
        copy (``pixels`` (n, 2)) into ``D``, ``rows`` (r0, r1) the rows written (empty: ``r0
        >= r1``) and ``span[r]`` (c0, c1) the columns ``[c0, c1]`` of row r. The caller sums
        ``D`` along the rows and zeroes it and ``span`` (to ``(W, 0)``). ``packed`` is a
        :class:`Packed` as a plain tuple."""
        (kind, count, arity, start, index, size, _, _, sides, units, _, _, edges, edge_start,
         incidence, sense, incidence_start) = packed
        rows[0], rows[1] = D.shape[0], 0
        k, m, step, first = kind[layer], count[layer], arity[layer], start[layer]
        if k == POLYGONS:
            for cell in range(m):
                twice, inside = 0.0, True
                for j in range(step):
                    p = index[first + cell * step + j]
                    q = index[first + cell * step + (j + 1 if j + 1 < step else 0)]
                    twice = twice + (pixels[p, 0] * pixels[q, 1] - pixels[q, 0] * pixels[p, 1])
                    inside = inside and abs(pixels[p, 0]) <= FAR and abs(pixels[p, 1]) <= FAR
                orient[cell] = 0.0 if not inside or twice == 0.0 else (
                    1.0 if twice > 0.0 else -1.0)
                tangled[cell] = False
                if step == 4 and orient[cell] != 0.0:
                    for j in range(4):
                        p = index[first + cell * step + j]
                        verts[j, 0], verts[j, 1] = pixels[p, 0], pixels[p, 1]
                    if _twisted(verts):
                        orient[cell], tangled[cell] = 0.0, True
            for e in range(edge_start[layer], edge_start[layer + 1]):
                w = 0.0
                for j in range(incidence_start[e], incidence_start[e + 1]):
                    w = w + orient[incidence[j]] * sense[j]
                if w != 0.0:
                    a, b = edges[e, 0], edges[e, 1]
                    _add_edge(pixels[a, 0], pixels[a, 1], pixels[b, 0], pixels[b, 1], w, D,
                              rows, span)
            for cell in range(m):
                if not tangled[cell]:
                    continue
                for j in range(4):
                    p = index[first + cell * step + j]
                    verts[j, 0], verts[j, 1] = pixels[p, 0], pixels[p, 1]
                _, parts = _lobes(verts)
                for part in parts:
                    w = _turn(part, 3)
                    for j in range(3 if w != 0.0 else 0):
                        f = j + 1 if j + 1 < 3 else 0
                        _add_edge(part[j, 0], part[j, 1], part[f, 0], part[f, 1], w, D, rows,
                                  span)
            return
        for shape in range(m):
            n = _vertices(pixels, index, first + shape * step, k, size[layer], sides[layer],
                          units, layer, verts)
            twice = 0.0
            for j in range(n):
                f = j + 1 if j + 1 < n else 0
                twice = twice + (verts[j, 0] * verts[f, 1] - verts[f, 0] * verts[j, 1])
            if n == 0 or twice == 0.0:
                continue
            w = 1.0 if twice > 0.0 else -1.0
            for j in range(n):
                f = j + 1 if j + 1 < n else 0
                _add_edge(verts[j, 0], verts[j, 1], verts[f, 0], verts[f, 1], w, D, rows,
                          span)

    @njit
    def _scratch(height: int, width: int, points: np.ndarray, count: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                            np.ndarray, np.ndarray]:  # pragma: no cover - compiled
        """The working arrays of one call: the row differences ``D`` (H, W + 1), a shape's
        vertices, the rows written, each row's columns written (``(W, 0)``: none), one copy's
        points in pixels, the orientations of a layer's cells and which are bow-ties."""
        span = np.empty((height, 2), dtype=np.int64)
        span[:, 0], span[:, 1] = width, 0
        most = max(count.max(), 1) if count.shape[0] else 1
        return (np.zeros((height, width + 1)), np.zeros((MAX_SIDES, 2)),
                np.zeros(2, dtype=np.int64), span, np.zeros((points.shape[1], 2)),
                np.zeros(most), np.zeros(most, dtype=np.bool_))

    @njit
    def _pixels(points: np.ndarray, i: int, transform: tuple[float, float, float],
                pixels: np.ndarray) -> None:  # pragma: no cover - compiled
        """Copy ``i``'s points in pixel coordinates, as :func:`_pixels_reference`."""
        ox, oy, s = transform
        for q in range(points.shape[1]):
            pixels[q, 0] = ox + s * points[i, q, 0]
            pixels[q, 1] = oy - s * points[i, q, 1]

    @njit(nogil=True)
    def _draw_range(points: np.ndarray, packed: tuple, transform: tuple[float, float, float],
                    background: np.ndarray, out: np.ndarray, start: int,
                    stop: int) -> None:  # pragma: no cover - compiled
        """Compiled :func:`draw_reference` (``packed``: a :class:`Packed` as a plain tuple)."""
        height, width, channels = out.shape[1], out.shape[2], out.shape[3]
        count, alphas, colours, powers, table = packed[1], packed[6], packed[7], packed[10], \
            packed[11]
        D, verts, rows, span, pixels, orient, tangled = _scratch(height, width, points, count)
        size = height * width * channels
        flat = background.reshape(size)
        words = size // 8 * 8  # (copied eight bytes at a time: a byte loop is three times slower)
        for i in range(start, stop):
            image = out[i].reshape(size)
            image[:words].view(np.uint64)[:] = flat[:words].view(np.uint64)
            image[words:] = flat[words:]
            _pixels(points, i, transform, pixels)
            for layer in range(alphas.shape[0]):
                _layer(pixels, packed, layer, orient, tangled, D, verts, rows, span)
                alpha = alphas[layer]
                for r in range(rows[0], rows[1]):
                    d = 0.0
                    for c in range(span[r, 0], span[r, 1] + 1):
                        d += D[r, c]
                        D[r, c] = 0.0
                        if d > EMPTY and c < span[r, 1]:
                            at = (r * width + c) * channels
                            whole = int(d + 0.5)
                            snap = whole >= 1 and abs(d - whole) <= SNAP
                            if snap and whole <= TABLED:
                                for ch in range(channels):
                                    image[at + ch] = table[layer, whole, image[at + ch], ch]
                                continue
                            capped = min(float(whole) if snap else d, float(DEPTH_CAP))
                            sheets = int(capped)
                            a = 1.0 - powers[layer, sheets] * (1.0 - alpha * (capped - sheets))
                            for ch in range(channels):
                                old = float(image[at + ch])
                                new = old + (colours[layer, ch] - old) * a
                                image[at + ch] = min(int(new + 0.5), 255)
                    span[r, 0], span[r, 1] = width, 0

    @njit(nogil=True)
    def _union_range(points: np.ndarray, packed: tuple, transform: tuple[float, float, float],
                     maps: np.ndarray, areas: np.ndarray, start: int,
                     stop: int) -> None:  # pragma: no cover - compiled
        """Compiled :func:`union_reference` (``packed``: a :class:`Packed` as a plain
        tuple)."""
        width = maps.shape[2]
        D, verts, rows, span, pixels, orient, tangled = _scratch(maps.shape[1], width, points,
                                                                 packed[1])
        s = transform[2]
        for i in range(start, stop):
            if maps.shape[0]:
                maps[i] = 0.0
            _pixels(points, i, transform, pixels)
            _layer(pixels, packed, 0, orient, tangled, D, verts, rows, span)
            total = 0.0
            for r in range(rows[0], rows[1]):
                d = 0.0
                for c in range(span[r, 0], span[r, 1] + 1):
                    d += D[r, c]
                    D[r, c] = 0.0
                    if c < span[r, 1]:
                        fraction = min(d, 1.0) if d > EMPTY else 0.0
                        total += fraction
                        if maps.shape[0]:
                            maps[i, r, c] = fraction
                span[r, 0], span[r, 1] = width, 0
            areas[i] = total / (s * s)
