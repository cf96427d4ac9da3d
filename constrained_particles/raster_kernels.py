"""The rasteriser's working parts (see :mod:`constrained_particles.raster`, which draws with
them): the packed record of a scene's layers, the scalar geometry, the numpy reference
(:func:`draw_reference`, :func:`union_reference`) and the compiled entries (Numba), which
follow the reference operation for operation and which the tests tie to it byte for byte.

The compiled entries release the GIL and take a range of copies ``[start, stop)``; they are
None when the compiled paths are off (``CPARTICLES_NUMBA=0``). Units: pixel coordinates
(``u`` right, ``v`` down) unless said otherwise.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import kernels

__all__ = ["DEPTH_CAP", "EMPTY", "FAR", "FLAT", "KINDS", "LUMA", "MAX_SIDES", "Packed",
           "SAGITTA", "SNAP", "STRAIGHT", "TABLED", "blend", "crossing", "draw_reference",
           "lobes", "mean_clamp", "turn", "twisted", "union_reference"]

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


def blend(old: np.ndarray, colour: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Bytes ``old`` (..., C) with ``colour`` (C,) laid over at opacity ``a`` (...,), rounded:
    ``floor(old + (colour - old) a + 1/2)``, at most 255."""
    old = old.astype(np.float64)
    new = old + (colour - old) * a[..., None]
    return np.minimum(np.floor(new + 0.5), 255.0).astype(np.uint8)


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
                new = blend(old, packed.colour[layer], 1.0 - T)
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
    from .jit import njit

    # (rebound to its compiled self, which the compiled lobes and twisted call; the
    # reference's calls then run it compiled too: the same operations, the same bits)
    crossing = njit(crossing)
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
        a record inside the loops costs Numba a reference count each time, some 15 times the
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
