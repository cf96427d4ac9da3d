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
integral with a closed form (``mean_clamp``). Left of an edge's piece in a row the integral
is the piece's height, right of it 0, so each piece writes only its differences at the
columns it crosses and a running sum along the row gives every pixel (as font rasterisers
accumulate signed area). Exact for any simple polygon up to rounding (about
1e-15 of a pixel), whichever way round its vertices go. A layer of polygons is drawn by its
edges, each once, weighted by the orientations of the cells on either side: the inner edges
of a flat cloth weigh 0 and are skipped, a fold line weighs 2. A quad turned inside out (a
bow-tie) is drawn as its two lobes (``lobes``); a self-intersecting polygon of more
corners counts by its winding number. Segments are drawn as rectangles (butt ends) of the
given width, disks as a regular polygon of the disk's area with enough sides that its edge
stays within about :data:`SAGITTA` pixels of the circle (up to 40 pixels of radius).

**Layers and colour.** A :class:`Layer` is a set of shapes of one colour and opacity
``alpha``. Its shapes' coverages add up per pixel into a depth ``d`` (1 inside one sheet of
cloth, 2 in a fold, fractional at edges; adjacent cells sum to 1 along their shared edge, so
a flat cloth shows no seams), and the layer is laid over the image with transmittance
``T = (1 - alpha)^floor(d) (1 - alpha frac(d))``: exact alpha compositing of ``floor(d)``
sheets, linear between (``d`` within :data:`SNAP` of a whole number counts as that number,
``d`` above :data:`DEPTH_CAP` as the cap). Each layer rounds to bytes, ``new = floor(old +
(colour - old)(1 - T) + 1/2)`` (for whole sheets read from a table of the same bytes). A
grey image (one channel) uses the luma ``0.299 R + 0.587 G + 0.114 B`` of each colour.

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
stop)``, so a caller can give ranges to threads (``threads=`` does so).

**Bad input** raises ValueError naming the argument before any compiled loop runs (shapes,
sizes, channels, a non-finite box, indices out of range). Positions that are not finite, or
that land more than :data:`FAR` pixels from the origin, draw nothing: the shape using them is
skipped, the rest of the image is drawn.

The numpy reference (:func:`draw_reference`, :func:`union_reference`, in
:mod:`~.raster_kernels` with the compiled entries) runs when the compiled
paths are off (``CPARTICLES_NUMBA=0``); the tests tie it to the compiled entries byte for
byte (and the coverage to the last bit): it follows the compiled code operation for
operation, and the scalar geometry (``crossing``, ``lobes``, ``turn``) is one Python
function run by both. It is slow: Python loops over copies, layers and edges.

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
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from . import kernels
from .raster_kernels import (
    DEPTH_CAP,
    DISKS,
    FAR,
    KINDS,
    LUMA,
    MAX_SIDES,
    POLYGONS,
    SAGITTA,
    SEGMENTS,
    TABLED,
    Packed,
    _draw_range,
    _union_range,
    blend,
    draw_reference,
    union_reference,
)

__all__ = ["DEPTH_CAP", "FAR", "KINDS", "Layer", "Packed", "SAGITTA", "Scene", "View",
           "coverage", "coverage_bound", "draw_reference", "pack", "union_reference"]

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

    def to_pixels(self, points: ArrayLike) -> np.ndarray:
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
    index: ArrayLike
    colour: tuple[float, float, float]
    opacity: float = 1.0
    size: float = 0.0
    unit: str = "m"


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


def _table(alpha: float, colour: np.ndarray) -> np.ndarray:
    """Each byte (256, C) under k = 0 .. :data:`TABLED` whole sheets of ``colour`` at opacity
    ``alpha``: :func:`_blend` at ``a = 1 - (1 - alpha)^k``, worked out as for any depth."""
    powers = _powers(alpha)
    old = np.repeat(np.arange(256.0)[:, None], len(colour), axis=1)
    return np.array([blend(old, colour, np.full(256, 1.0 - powers[k] * (1.0 - alpha * 0.0)))
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


def _points(points: ArrayLike, packed: Packed) -> np.ndarray:
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

    def draw(self, points: ArrayLike, out: np.ndarray | None = None, *, start: int = 0,
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


#: :func:`coverage`'s packed cells, by the cells' bytes and the scale (what an env measures
#: every step: built once, never modified by the kernels).
_UNION_PACKS: dict[tuple, Packed] = {}


def coverage(points: ArrayLike, cells: ArrayLike, view: View, *, maps: bool = False,
             threads: int = 1) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
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
    key = (cells.dtype.str, cells.shape, cells.tobytes(), view.scale)
    packed = _UNION_PACKS.get(key)
    if packed is None:
        packed = pack([Layer("polygons", cells, (0, 0, 0))], view.scale, 1)
        if len(_UNION_PACKS) >= 16:  # (a few cloths per process: keep the newest)
            _UNION_PACKS.pop(next(iter(_UNION_PACKS)), None)
        _UNION_PACKS[key] = packed
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
