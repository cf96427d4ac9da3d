"""The compiled rasteriser (constrained_particles.raster): exact pixel coverage against
independent geometry (clipping each pixel's square), areas, the layers' colours, batches,
the coverage measure and its error bound, the numpy reference tied to the compiled entries,
bad input, and that importing compiles nothing and needs no pygame."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from constrained_particles import kernels, raster
from constrained_particles.raster import Layer, Scene, View, coverage, coverage_bound

ROOT = Path(__file__).resolve().parents[1]
compiled = pytest.mark.skipif(not kernels.ENABLED, reason="the compiled paths are off")


# ------------------------------------------------------------------ independent geometry
def clip(poly: list, xmin: float, ymin: float, xmax: float, ymax: float) -> list:
    """Sutherland-Hodgman: ``poly`` (vertices) clipped to the rectangle."""
    for axis, bound, keep_below in ((0, xmin, False), (0, xmax, True), (1, ymin, False),
                                    (1, ymax, True)):
        def inside(p, axis=axis, bound=bound, keep_below=keep_below):
            return p[axis] <= bound if keep_below else p[axis] >= bound

        out = []
        for j, p in enumerate(poly):
            q = poly[j - 1]
            if inside(p) != inside(q):
                t = (bound - q[axis]) / (p[axis] - q[axis])
                out.append((q[0] + t * (p[0] - q[0]), q[1] + t * (p[1] - q[1])))
            if inside(p):
                out.append(tuple(p))
        poly = out
        if not poly:
            return []
    return poly


def area(poly: list) -> float:
    """Shoelace area (unsigned)."""
    return 0.5 * abs(sum(poly[j - 1][0] * p[1] - p[0] * poly[j - 1][1]
                         for j, p in enumerate(poly)))


def random_polygon(rng: np.random.Generator, centre: tuple, size: float) -> np.ndarray:
    """A simple polygon of 3 to 8 vertices, star-shaped about ``centre`` (often not convex),
    in random order of orientation."""
    k = int(rng.integers(3, 9))
    angles = np.sort(rng.uniform(0, 2 * np.pi, k))
    radii = rng.uniform(0.2, 1.0, k) * size
    poly = np.stack([centre[0] + radii * np.cos(angles), centre[1] + radii * np.sin(angles)], 1)
    return poly[::-1] if rng.random() < 0.5 else poly


def grid(n: int, spacing: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n cloth centred on the origin: points (n * n, 2) and cells (cells, 4)."""
    col, row = np.meshgrid(np.arange(n), np.arange(n))
    points = np.stack([(col.ravel() - (n - 1) / 2) * spacing,
                       ((n - 1) / 2 - row.ravel()) * spacing], axis=1)
    idx = row * n + col
    cells = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1)
    return points, cells.reshape(-1, 4)


def folded(points: np.ndarray, n: int) -> np.ndarray:
    """The cloth's right half mirrored onto its left half, over its middle column (``n``
    odd): the union is the left half."""
    out = points.copy()
    right = np.arange(n * n) % n > (n - 1) / 2
    out[right, 0] = -out[right, 0]
    return out


# ------------------------------------------------------------------ exact coverage
def test_a_square_on_pixel_lines_covers_exactly_its_pixels():
    view = View((0.0, 0.0, 8.0, 8.0), height=8, width=8)  # one pixel a metre
    square = np.array([[[2.0, 3.0], [5.0, 3.0], [5.0, 6.0], [2.0, 6.0]]])
    areas, maps = coverage(square, [[0, 1, 2, 3]], view, maps=True)
    expected = np.zeros((8, 8))
    expected[2:5, 2:5] = 1.0  # rows 8 - 6 .. 8 - 3 (y up), columns 2 .. 5
    assert np.array_equal(maps[0], expected)
    assert areas[0] == 9.0
    image = Scene([Layer("polygons", [[0, 1, 2, 3]], (0, 0, 0))], view, channels=1).draw(square)
    assert np.array_equal(image[0, :, :, 0], np.where(expected > 0, 0, 255))


@pytest.mark.parametrize("seed", range(6))
def test_each_pixel_gets_the_area_of_the_polygon_inside_its_square(seed):
    rng = np.random.default_rng(seed)
    view = View((-1.0, -1.0, 1.0, 1.0), height=24, width=24)
    poly = random_polygon(rng, rng.uniform(-1.0, 1.0, 2), rng.uniform(0.1, 1.2))
    areas, maps = coverage(poly[None], [list(range(len(poly)))], view, maps=True)
    pix = [tuple(p) for p in view.to_pixels(poly)]
    expected = np.array([[area(clip(pix, c, r, c + 1, r + 1)) for c in range(24)]
                         for r in range(24)])
    assert np.abs(maps[0] - expected).max() < 1e-9  # (a pixel under 1e-9 counts 0: EMPTY)
    visible = area(clip(pix, 0, 0, 24, 24)) * view.pixel_area
    assert areas[0] == pytest.approx(visible, rel=1e-9, abs=1e-12)


def test_vertex_order_does_not_change_the_image():
    rng = np.random.default_rng(7)
    view = View((-1.0, -1.0, 1.0, 1.0), height=32, width=32)
    poly = random_polygon(rng, (0.1, -0.2), 0.8)
    order = list(range(len(poly)))
    scene = Scene([Layer("polygons", [order], (10, 120, 200), 0.7)], view)
    flipped = Scene([Layer("polygons", [order[::-1]], (10, 120, 200), 0.7)], view)
    assert np.array_equal(scene.draw(poly[None]), flipped.draw(poly[None]))


def darkness(image: np.ndarray) -> np.ndarray:
    """Coverage read back from a black, fully opaque layer on white (grey image)."""
    return (255.0 - image[..., 0].astype(float)) / 255.0


def test_a_segment_covers_its_length_times_its_width():
    view = View((0.0, 0.0, 40.0, 40.0), height=40, width=40)  # one pixel a metre
    ends = np.array([[[5.3, 7.1], [31.7, 29.4]]])
    width = 2.5
    image = Scene([Layer("segments", [[0, 1]], (0, 0, 0), size=width)], view,
                  channels=1).draw(ends)
    length = float(np.hypot(*(ends[0, 1] - ends[0, 0])))
    touched = np.count_nonzero(image < 255)
    # each byte is the coverage rounded to 1/255
    assert darkness(image[0]).sum() == pytest.approx(length * width, abs=touched * 0.5 / 255)
    pixels_wide = Scene([Layer("segments", [[0, 1]], (0, 0, 0), size=width, unit="px")], view,
                        channels=1).draw(ends)
    assert np.array_equal(image, pixels_wide)  # (1 px = 1 m here)


@pytest.mark.parametrize("radius", [0.7, 2.0, 5.5, 17.0])
def test_a_disk_covers_its_area_and_stays_within_the_sagitta(radius):
    view = View((0.0, 0.0, 48.0, 48.0), height=48, width=48)
    centre = np.array([[[23.4, 24.9]]])
    image = Scene([Layer("disks", [0], (0, 0, 0), size=radius)], view, channels=1).draw(centre)
    cover = darkness(image[0])
    touched = np.count_nonzero(cover)
    assert cover.sum() == pytest.approx(math.pi * radius ** 2, abs=touched * 0.5 / 255 + 1e-9)
    col, row = np.meshgrid(np.arange(48) + 0.5, np.arange(48) + 0.5)
    u, v = view.to_pixels(centre[0, 0])
    far = np.hypot(col - u, row - v)  # distance of each pixel's centre from the disk's
    half = math.sqrt(0.5)  # a pixel's half diagonal
    assert np.all(cover[far < radius - raster.SAGITTA - half] == 1.0)
    assert np.all(cover[far > radius + raster.SAGITTA + half] == 0.0)


def test_the_disk_polygon_stays_within_the_sagitta_up_to_forty_pixels():
    for radius in np.linspace(0.06, 40.0, 200):
        sides, grown, _ = raster._disk_polygon(float(radius))
        apothem = grown * math.cos(math.pi / sides)
        assert max(grown - radius, radius - apothem) <= raster.SAGITTA + 1e-12


# ------------------------------------------------------------------ colour and layers
def test_a_flat_cloth_shows_no_seams_and_a_fold_is_darker():
    n = 7
    points, cells = grid(n, 0.1)
    view = View((-0.4, -0.4, 0.4, 0.4), height=64, width=64)
    scene = Scene([Layer("polygons", cells, (0, 0, 0), opacity=0.6)], view, channels=1)
    flat = scene.draw(points[None])[0, :, :, 0]
    u, v = view.to_pixels(points).T
    inside = np.zeros((64, 64), bool)
    inside[math.ceil(v.min()):math.floor(v.max()), math.ceil(u.min()):math.floor(u.max())] = True
    assert np.all(flat[inside] == 102)  # 255 (1 - 0.6) everywhere inside: no seams
    assert np.all(flat[~inside] > 102)
    fold = scene.draw(folded(points, n)[None])[0, :, :, 0]
    u, v = view.to_pixels(folded(points, n)).T
    double = np.zeros((64, 64), bool)
    double[math.ceil(v.min()):math.floor(v.max()), math.ceil(u.min()):math.floor(u.max())] = True
    assert np.all(fold[double] == 41)  # two sheets: 255 (1 - 0.6)^2 = 40.8


def test_layers_are_laid_in_order_and_grey_is_the_luma():
    view = View((0.0, 0.0, 4.0, 4.0), height=4, width=4)
    square = np.array([[[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]]])
    red = Layer("polygons", [[0, 1, 2, 3]], (200, 40, 40))
    half_blue = Layer("polygons", [[0, 1, 2, 3]], (40, 90, 200), opacity=0.5)
    rgb = Scene([red, half_blue], view, background=(10, 20, 30)).draw(square)
    assert rgb[0, 0, 0].tolist() == [120, 65, 120]  # red, then blue at half over it
    grey = Scene([red], view, channels=1, background=(10, 20, 30)).draw(square)
    assert grey[0, 0, 0, 0] == round(0.299 * 200 + 0.587 * 40 + 0.114 * 40)
    empty = Scene([], view, channels=1, background=(10, 20, 30)).draw(square)
    assert np.all(empty == round(0.299 * 10 + 0.587 * 20 + 0.114 * 30))


# ------------------------------------------------------------------ batches
def scene_and_points(rng: np.random.Generator, copies: int, height: int = 64, width: int = 64,
                     channels: int = 3) -> tuple[Scene, np.ndarray, np.ndarray]:
    """A crumpled cloth (folds and cells turned inside out), segments and disks, with random
    colours and opacities; points (copies, 39, 2), and the cells."""
    n = 6
    points, cells = grid(n, 0.1)
    cloth = points[None] + rng.normal(0.0, 0.05, (copies, n * n, 2))
    extra = rng.uniform(-0.6, 0.6, (copies, 3, 2))
    layers = [Layer("polygons", cells, tuple(rng.integers(0, 256, 3)), rng.uniform(0.2, 1.0)),
              Layer("polygons", [[36, 37, 38]], tuple(rng.integers(0, 256, 3)), 0.5),
              Layer("segments", [[36, 0], [37, 5], [0, 35]], tuple(rng.integers(0, 256, 3)),
                    size=rng.uniform(0.005, 0.03)),
              Layer("segments", [[5, 30]], (0, 0, 0), size=1.0, unit="px"),
              Layer("disks", [36, 37, 38, 14], tuple(rng.integers(0, 256, 3)),
                    rng.uniform(0.3, 1.0), size=rng.uniform(0.01, 0.06))]
    view = View((-0.5, -0.5, 0.5, 0.5), height=height, width=width)
    return (Scene(layers, view, channels=channels, background=tuple(rng.integers(0, 256, 3))),
            np.concatenate([cloth, extra], axis=1), cells)


def test_a_copy_gets_the_same_bytes_whatever_the_batch():
    rng = np.random.default_rng(3)
    scene, points, _ = scene_and_points(rng, 6)
    batch = scene.draw(points)
    for i in range(6):
        assert np.array_equal(scene.draw(points[i:i + 1])[0], batch[i])
    out = np.full_like(batch, 7)
    scene.draw(points, out, start=2, stop=5)
    assert np.array_equal(out[2:5], batch[2:5])
    assert np.all(out[:2] == 7) and np.all(out[5:] == 7)
    assert np.array_equal(scene.draw(points, threads=4), batch)
    assert np.array_equal(scene.draw(points, threads=20), batch)
    points[4, :, :] = np.nan  # another copy's points change nothing in copy 3
    scene.draw(points, out)
    assert np.array_equal(out[3], batch[3])


def test_coverage_is_the_same_on_threads():
    rng = np.random.default_rng(4)
    _, points, cells = scene_and_points(rng, 7)
    view = View((-0.5, -0.5, 0.5, 0.5), height=32, width=32)
    one = coverage(points, cells, view, maps=True)
    three = coverage(points, cells, view, maps=True, threads=3)
    assert np.array_equal(one[0], three[0]) and np.array_equal(one[1], three[1])


@pytest.mark.parametrize(("height", "width", "channels"),
                         [(64, 64, 3), (64, 64, 1), (84, 84, 3), (128, 128, 1), (48, 80, 3)])
def test_sizes_and_channels(height, width, channels):
    scene, points, _ = scene_and_points(np.random.default_rng(height + channels), 2, height,
                                        width, channels)
    assert scene.draw(points).shape == (2, height, width, channels)


@compiled
@pytest.mark.parametrize("seed", range(8))
def test_the_reference_gives_the_compiled_bytes(seed):
    rng = np.random.default_rng(seed)
    height, width = [(64, 64), (84, 84), (128, 128), (48, 80)][seed % 4]
    scene, points, cells = scene_and_points(rng, 4, height, width, 1 + 2 * (seed % 2))
    points[1, 3] = [np.nan, 0.0]  # a cell, a segment and a disk skipped
    points[2, 7] = [1e300, -1e300]
    points[3, 36] = [np.inf, 0.2]
    transform = (*scene.view.origin, scene.view.scale)
    fast = np.zeros((4, *scene.shape), np.uint8)
    slow = np.zeros_like(fast)
    raster._draw_range(points, tuple(scene.packed), transform, scene.image, fast, 0, 4)
    raster.draw_reference(points, scene.packed, transform, scene.image, slow, 0, 4)
    assert np.array_equal(fast, slow)
    packed = raster.pack([Layer("polygons", cells, (0, 0, 0))], scene.view.scale, 1)
    areas = [np.zeros(4), np.zeros(4)]
    maps = [np.zeros((4, height, width)), np.zeros((4, height, width))]
    raster._union_range(points, tuple(packed), transform, maps[0], areas[0], 0, 4)
    raster.union_reference(points, packed, transform, maps[1], areas[1], 0, 4)
    assert np.array_equal(areas[0], areas[1]) and np.array_equal(maps[0], maps[1])


def test_the_reference_runs_when_the_compiled_paths_are_off():
    code = ("import numpy as np, sys\n"
            "from constrained_particles import raster\n"
            "sys.path.insert(0, 'tests')\n"
            "from test_raster import scene_and_points\n"
            "scene, points, cells = scene_and_points(np.random.default_rng(5), 3)\n"
            "assert raster._draw_range is None\n"
            "a = raster.coverage(points, cells, scene.view)\n"
            "np.save(sys.argv[1], scene.draw(points)); np.save(sys.argv[2], a)\n")
    env = {**os.environ, "CPARTICLES_NUMBA": "0"}
    files = [str(ROOT / ".pytest-raster-image.npy"), str(ROOT / ".pytest-raster-areas.npy")]
    try:
        subprocess.run([sys.executable, "-c", code, *files], cwd=ROOT, env=env, check=True,
                       timeout=300)
        scene, points, cells = scene_and_points(np.random.default_rng(5), 3)
        assert np.array_equal(np.load(files[0]), scene.draw(points))
        assert np.array_equal(np.load(files[1]), coverage(points, cells, scene.view))
    finally:
        for f in files:
            Path(f).unlink(missing_ok=True)


# ------------------------------------------------------------------ coverage (issue 51)
def test_a_flat_cloth_is_measured_exactly_and_a_folded_one_at_half_within_the_bound():
    n = 7
    points, cells = grid(n, 0.1)
    flat_area = (0.1 * (n - 1)) ** 2
    view = View((-0.5, -0.5, 0.5, 0.5), height=64, width=64)
    flat = coverage(points[None], cells, view)[0]
    assert flat == pytest.approx(flat_area, rel=1e-9)  # no overlaps: exact
    half = coverage(folded(points, n)[None], cells, view)[0]
    side = 0.1 * (n - 1)
    bound = coverage_bound(3 * side, 4, view)  # the union: a side x side/2 rectangle
    assert flat_area / 2 - 1e-12 <= half <= flat_area / 2 + bound
    assert bound / flat_area < 0.15  # (the bound at 64 pixels for a cloth of 32)


def union_by_sampling(points: np.ndarray, cells: np.ndarray, box: tuple, samples: int
                      ) -> float:
    """The area of the union of the cells, by testing the centres of a samples x samples
    grid over ``box`` for being inside any cell (matplotlib's point-in-polygon)."""
    xmin, ymin, xmax, ymax = box
    step = (xmax - xmin) / samples
    x, y = np.meshgrid(xmin + step * (np.arange(samples) + 0.5),
                       ymin + step * (np.arange(samples) + 0.5))
    probe = np.stack([x.ravel(), y.ravel()], 1)
    hit = np.zeros(len(probe), bool)
    for cell in cells:
        hit |= MplPath(points[cell]).contains_points(probe)
    return hit.sum() * step * step


@pytest.mark.parametrize("seed", range(3))
def test_a_crumpled_cloth_lies_between_and_matches_sampling_within_the_bound(seed):
    n = 6
    points, cells = grid(n, 0.1)
    rng = np.random.default_rng(seed)
    squeeze = points * rng.uniform(0.45, 0.95, (n * n, 1)) + rng.normal(0, 0.01, (n * n, 2))
    view = View((-0.5, -0.5, 0.5, 0.5), height=64, width=64)
    measured = coverage(squeeze[None], cells, view)[0]
    flat_area = (0.1 * (n - 1)) ** 2
    assert 0.1 * flat_area < measured < flat_area
    truth = union_by_sampling(squeeze, cells, view.box, 1000)
    # the union's boundary is made of cell edges: their total length bounds its perimeter,
    # for the raster's bound and the sampling's (the samples are 1 mm apart)
    lengths = np.linalg.norm(squeeze[cells] - squeeze[np.roll(cells, -1, 1)], axis=2).sum()
    sampling = math.sqrt(2) * lengths * 1e-3 + cells.size * 1e-6
    assert truth - sampling <= measured <= truth + coverage_bound(lengths, cells.size, view) \
        + sampling
    finer = coverage(squeeze[None], cells, View(view.box, height=512, width=512))[0]
    assert truth - sampling <= finer <= measured + 1e-12


def test_coverage_does_not_depend_on_where_the_cloth_lies_or_which_way_it_turns():
    n = 7
    points, cells = grid(n, 0.1)
    fold = folded(points, n)
    view = View((-1.0, -1.0, 1.0, 1.0), height=64, width=64)
    rng = np.random.default_rng(11)
    moved = []
    for _ in range(12):
        turn = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
        moved.append(fold @ rot.T + rng.uniform(-0.4, 0.4, 2))
    areas = coverage(np.array(moved), cells, view)
    truth = (0.1 * (n - 1)) ** 2 / 2
    bound = coverage_bound(3 * 0.1 * (n - 1), 4, view)
    assert np.all(areas >= truth - 1e-12) and np.all(areas <= truth + bound)
    turned = np.array([[0.6, -0.8], [0.8, 0.6]])
    flat = coverage(np.array([points, points @ turned.T]), cells, view)
    assert flat == pytest.approx([(0.1 * (n - 1)) ** 2] * 2, rel=1e-9)


def test_coverage_bound_is_root_two_perimeter_pixel_plus_pieces_pixel_squared():
    view = View((0.0, 0.0, 1.0, 1.0), height=100, width=100)
    assert coverage_bound(2.0, 5, view) == pytest.approx(math.sqrt(2) * 2.0 * 0.01
                                                         + 5 * 1e-4)


# ------------------------------------------------------------------ bad input
def bad(**change):
    """Build a scene and draw, with one argument changed."""
    args = {"box": (0.0, 0.0, 1.0, 1.0), "height": 8, "width": 8, "channels": 3,
            "background": (255, 255, 255), "kind": "polygons", "index": [[0, 1, 2]],
            "colour": (1, 2, 3), "opacity": 1.0, "size": 0.1, "unit": "m",
            "points": np.zeros((1, 3, 2)), "out": None, "start": 0, "stop": None, "threads": 1}
    args.update(change)
    view = View(args["box"], height=args["height"], width=args["width"])
    layer = Layer(args["kind"], args["index"], args["colour"], args["opacity"], args["size"],
                  args["unit"])
    scene = Scene([layer], view, channels=args["channels"], background=args["background"])
    scene.draw(args["points"], args["out"], start=args["start"], stop=args["stop"],
               threads=args["threads"])


@pytest.mark.parametrize(("change", "named"), [
    ({"box": (0.0, 0.0, np.nan, 1.0)}, "box"), ({"box": (1.0, 0.0, 0.0, 1.0)}, "box"),
    ({"box": (0.0, 0.0, 1.0)}, "box"), ({"height": 0}, "height"), ({"width": 2.5}, "width"),
    ({"channels": 2}, "channels"), ({"background": (0, 0, 300)}, "background"),
    ({"kind": "lines"}, "kind"), ({"index": [0, 1, 2]}, "index"),
    ({"index": [[0, 1, 5]]}, "points"), ({"index": [[0, -1, 2]]}, "index"),
    ({"index": [[0.0, 1.0, 2.0]]}, "index"), ({"kind": "segments"}, "index"),
    ({"index": [[0, 1, 2], [0, 1]]}, "index"),
    ({"colour": (1, 2)}, "colour"), ({"colour": (1, 2, np.nan)}, "colour"),
    ({"opacity": 0.0}, "opacity"), ({"opacity": 1.5}, "opacity"),
    ({"kind": "disks", "index": [0], "size": 0.0}, "size"),
    ({"kind": "segments", "index": [[0, 1]], "size": np.inf}, "size"),
    ({"unit": "cm"}, "unit"), ({"points": np.zeros((3, 2))}, "points"),
    ({"points": np.zeros((1, 3, 3))}, "points"), ({"points": np.full((1, 3, 2), "a")}, "points"),
    ({"out": np.zeros((1, 8, 8, 3))}, "out"), ({"out": np.zeros((2, 8, 8, 3), np.uint8)}, "out"),
    ({"out": np.zeros((1, 8, 8, 3), np.uint8)[:, ::-1]}, "out"),
    ({"start": -1}, "start"), ({"stop": 2}, "stop"), ({"start": 1.0}, "start"),
    ({"threads": 0}, "threads"), ({"threads": 1.5}, "threads"),
])
def test_bad_input_is_a_value_error_naming_the_argument(change, named):
    with pytest.raises(ValueError, match=named):
        bad(**change)


def test_bad_coverage_input_is_a_value_error_naming_the_argument():
    view = View((0.0, 0.0, 1.0, 1.0), height=8, width=8)
    with pytest.raises(ValueError, match="cells"):
        coverage(np.zeros((1, 4, 2)), [0, 1, 2, 3], view)
    with pytest.raises(ValueError, match="view"):
        coverage(np.zeros((1, 4, 2)), [[0, 1, 2, 3]], (0, 0, 1, 1))
    with pytest.raises(ValueError, match="points"):
        coverage(np.zeros((1, 3, 2)), [[0, 1, 2, 3]], view)
    with pytest.raises(ValueError, match="layers"):
        Scene(Layer("polygons", [[0, 1, 2]], (0, 0, 0)), view)


def test_positions_not_finite_or_far_skip_their_shapes_only():
    view = View((-0.5, -0.5, 0.5, 0.5), height=32, width=32)
    points = np.array([[[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3], [0.0, 0.0]]] * 4)
    points[1, 4] = np.nan
    points[2, 4] = [1e300, 1e300]
    points[3, 4] = [-np.inf, 0.0]
    layers = [Layer("polygons", [[0, 1, 2, 3]], (0, 0, 0), 0.5),
              Layer("polygons", [[0, 1, 4]], (0, 0, 255), 0.5),
              Layer("segments", [[0, 4], [1, 2]], (255, 0, 0), size=0.02),
              Layer("disks", [4, 2], (0, 255, 0), size=0.05)]
    images = Scene(layers, view).draw(points)
    without = [Layer("polygons", [[0, 1, 2, 3]], (0, 0, 0), 0.5),
               Layer("segments", [[1, 2]], (255, 0, 0), size=0.02),
               Layer("disks", [2], (0, 255, 0), size=0.05)]
    expected = Scene(without, view).draw(points[:1])[0]
    for i in (1, 2, 3):
        assert np.array_equal(images[i], expected)
    assert not np.array_equal(images[0], expected)
    areas = coverage(points, [[0, 1, 4]], view)
    assert areas[1] == areas[2] == areas[3] == 0.0 and areas[0] > 0.0


# ------------------------------------------------------------------ imports
def test_importing_compiles_nothing_and_drawing_needs_no_pygame():
    code = ("import sys, numpy as np\n"
            "import constrained_particles\n"
            "from constrained_particles import raster, kernels\n"
            "if kernels.ENABLED:\n"
            "    assert raster._draw_range.signatures == [], 'compiled at import'\n"
            "    assert raster._union_range.signatures == [], 'compiled at import'\n"
            "v = raster.View((0, 0, 1, 1), height=8, width=8)\n"
            "raster.Scene([raster.Layer('disks', [0], (0, 0, 0), size=0.2)], v)"
            ".draw(np.full((1, 1, 2), 0.5))\n"
            "raster.coverage(np.zeros((1, 3, 2)), [[0, 1, 2]], v)\n"
            "assert 'pygame' not in sys.modules, 'pygame imported'\n")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=300)
