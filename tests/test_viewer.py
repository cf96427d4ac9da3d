"""The interactive viewer, driven by synthetic pygame events under the SDL dummy driver."""

import sys

import numpy as np
import pygame as pg  # the test extra installs pygame-ce: a missing one must fail, not skip
import pytest

from constrained_particles import (  # noqa: E402
    METHODS,
    DampedSpring,
    Gravity,
    ParticleSystem,
    render,
)
from constrained_particles.viewer import INTEGRATOR_KEYS, Viewer  # noqa: E402
from cparticles.cli import main as cli_main  # noqa: E402


def press(v, pixel, button=1):
    v.handle(pg.event.Event(pg.MOUSEBUTTONDOWN, pos=tuple(pixel), button=button))


def move(v, pixel):
    v.handle(pg.event.Event(pg.MOUSEMOTION, pos=tuple(pixel), rel=(0, 0), buttons=(1, 0, 0)))


def release(v, pixel, button=1):
    v.handle(pg.event.Event(pg.MOUSEBUTTONUP, pos=tuple(pixel), button=button))


def key(v, k):
    v.handle(pg.event.Event(pg.KEYDOWN, key=k, mod=0, unicode=""))
    v.handle(pg.event.Event(pg.KEYUP, key=k, mod=0, unicode=""))


def drag(v, a, b, button=1):
    press(v, a, button)
    move(v, (np.asarray(a) + np.asarray(b)) / 2)
    move(v, b)
    release(v, b, button)


def springs(system):
    """(i, j, rest) of every damped spring in the system."""
    blocks = [f for f in system.forces if isinstance(f, DampedSpring)]
    return (np.concatenate([f.i for f in blocks]), np.concatenate([f.j for f in blocks]),
            np.concatenate([f.rest for f in blocks]))


@pytest.fixture
def viewer():
    """spring_pair: particles at (-0.5, 0) and (0.5, 0), no gravity, no constraints."""
    v = Viewer("spring_pair", preview=0.0, size=(640, 480))
    v.paused = True
    return v


def pixel(v, world):
    return v.renderer.world_to_pixel(world)[0]


def test_drag_on_empty_space_creates_one_spring_and_two_particles(viewer):
    n, k = viewer.system.n, len(springs(viewer.system)[0])
    a, b = pixel(viewer, (-0.3, 0.4)), pixel(viewer, (0.2, 0.6))
    drag(viewer, a, b)
    i, j, rest = springs(viewer.system)
    assert viewer.system.n == n + 2
    assert len(i) == k + 1
    assert {int(i[-1]), int(j[-1])} == {n, n + 1}
    # new particles where the mouse was, rest length = the drawn length (pixels / scale)
    np.testing.assert_allclose(viewer.system.x[n:], [[-0.3, 0.4], [0.2, 0.6]], atol=1e-9)
    drawn = np.linalg.norm(b - a) / viewer.renderer.scale
    assert rest[-1] == pytest.approx(drawn)
    assert not viewer.system.fixed[n:].any()


def test_drag_starting_on_a_particle_reuses_it(viewer):
    n = viewer.system.n
    start = pixel(viewer, viewer.system.x[0]) + (4.0, -3.0)  # within the 12 px snap radius
    drag(viewer, start, pixel(viewer, (-0.5, 0.5)))
    i, j, rest = springs(viewer.system)
    assert viewer.system.n == n + 1
    assert {int(i[-1]), int(j[-1])} == {0, n}
    assert rest[-1] == pytest.approx(0.5)


def test_drag_between_two_particles_adds_none(viewer):
    n = viewer.system.n
    drag(viewer, pixel(viewer, viewer.system.x[0]), pixel(viewer, viewer.system.x[1]) + (5, 5))
    i, j, rest = springs(viewer.system)
    assert viewer.system.n == n
    assert {int(i[-1]), int(j[-1])} == {0, 1}
    assert rest[-1] == pytest.approx(1.0)


def test_click_adds_one_particle_unless_one_is_near(viewer):
    n, k = viewer.system.n, len(springs(viewer.system)[0])
    spot = pixel(viewer, (0.1, -0.3))
    press(viewer, spot)
    release(viewer, spot + (1, 1))  # a jitter of a pixel is still a click
    assert viewer.system.n == n + 1
    np.testing.assert_allclose(viewer.system.x[n], [0.1, -0.3], atol=2 / viewer.renderer.scale)
    press(viewer, spot + (3, 0))  # on the particle just placed: nothing new
    release(viewer, spot + (3, 0))
    assert viewer.system.n == n + 1
    assert len(springs(viewer.system)[0]) == k


def test_ctrl_click_places_a_fixed_particle(viewer):
    viewer.handle(pg.event.Event(pg.KEYDOWN, key=pg.K_LCTRL, mod=pg.KMOD_LCTRL, unicode=""))
    spot = pixel(viewer, (0.0, 0.5))
    press(viewer, spot)
    release(viewer, spot)
    assert viewer.system.fixed[-1]


def test_number_keys_select_integrators(viewer):
    viewer.method = "euler"
    key(viewer, pg.K_3)
    assert viewer.method == "rk4"
    key(viewer, pg.K_1)
    assert viewer.method == "euler"
    key(viewer, pg.K_4)
    assert viewer.method == "symplectic_euler"
    key(viewer, pg.K_5)
    if "implicit_euler" in METHODS:
        assert viewer.method == "implicit_euler"
    else:
        assert viewer.method == "symplectic_euler" and "implicit_euler" in viewer.message
    key(viewer, pg.K_6)
    assert viewer.method == "rattle"
    assert INTEGRATOR_KEYS == ("euler", "midpoint", "rk4", "symplectic_euler", "implicit_euler",
                               "rattle")


def test_keys_dt_pause_step_toggles(viewer):
    dt = viewer.dt
    key(viewer, pg.K_EQUALS)
    assert viewer.dt == pytest.approx(2 * dt)
    key(viewer, pg.K_MINUS)
    key(viewer, pg.K_MINUS)
    assert viewer.dt == pytest.approx(dt / 2)
    key(viewer, pg.K_SPACE)
    assert not viewer.paused
    key(viewer, pg.K_SPACE)
    assert viewer.paused
    t = viewer.system.t
    key(viewer, pg.K_PERIOD)
    assert viewer.system.t == pytest.approx(t + dt / 2)
    assert viewer.update(1.0) == 0  # paused: no steps
    forces, cforces, help_ = (viewer.show_forces, viewer.show_constraint_forces,
                              viewer.show_help)
    for k in (pg.K_f, pg.K_c, pg.K_h):
        key(viewer, k)
    assert (viewer.show_forces, viewer.show_constraint_forces, viewer.show_help) == (
        not forces, not cforces, not help_)
    key(viewer, pg.K_q)
    assert not viewer.running


def test_reset_and_scene_cycle(viewer):
    spot = pixel(viewer, (0.0, 0.5))
    press(viewer, spot)
    release(viewer, spot)
    key(viewer, pg.K_r)
    assert viewer.system.n == 2 and viewer.user_springs is None
    names = viewer.scene_names
    key(viewer, pg.K_n)
    assert viewer.scene == names[(names.index("spring_pair") + 1) % len(names)]
    key(viewer, pg.K_p)
    key(viewer, pg.K_p)
    assert viewer.scene == names[(names.index("spring_pair") - 1) % len(names)]


def test_right_drag_pulls_the_grabbed_particle_toward_the_cursor(viewer):
    viewer.paused = False
    p0 = viewer.system.x[0].copy()
    press(viewer, pixel(viewer, p0) + (30, 0), button=3)  # nearest particle: 0
    target = p0 + (0.0, 0.5)
    move(viewer, pixel(viewer, target))
    cursor = viewer.renderer.pixel_to_world(pixel(viewer, target))[0]
    before = np.linalg.norm(viewer.system.x[0] - cursor)
    for _ in range(30):
        viewer.update(1 / 60)
    after = np.linalg.norm(viewer.system.x[0] - cursor)
    assert after < 0.5 * before
    release(viewer, pixel(viewer, target), button=3)
    assert viewer.mouse is None
    assert not any(type(f).__name__ == "MouseSpring" for f in viewer.system.forces)


def test_shift_drag_grabs_too(viewer):
    viewer.handle(pg.event.Event(pg.KEYDOWN, key=pg.K_LSHIFT, mod=pg.KMOD_LSHIFT, unicode=""))
    n = viewer.system.n
    press(viewer, pixel(viewer, (0.4, 0.2)))
    assert viewer.mouse is not None and int(viewer.mouse.particle[0]) == 1
    release(viewer, pixel(viewer, (0.4, 0.4)))
    assert viewer.mouse is None and viewer.system.n == n


def test_new_particles_get_listed_gravity():
    v = Viewer("pendulum", preview=0.0)
    s = ParticleSystem()
    s.add_particle((0.0, 0.0))
    g = Gravity((0.0, -9.81), particles=[0])
    s.add(g)
    v.system = s
    i = v.add_particle_at((1.0, 0.0))
    assert i in g.particles
    s.step(0.01, method="euler")
    assert s.v[i, 1] == pytest.approx(-0.0981)


def test_divergence_pauses_instead_of_raising(viewer):
    viewer.select_method("euler")
    for _ in range(15):
        key(viewer, pg.K_PLUS)  # dt x2 up to its 0.5 s ceiling
    viewer.paused = False
    for _ in range(100):
        viewer.update(0.5)
        if viewer.paused:
            break
    assert viewer.paused and "DIVERGED" in viewer.message
    assert np.all(np.isfinite(viewer.system.x))
    surface = pg.Surface(viewer.size)
    viewer.draw(surface)  # still drawable, the message is on screen
    assert any("DIVERGED" in line for line in viewer.hud())


def test_resize_keeps_aspect_ratio(viewer):
    bounds = viewer.renderer.bounds
    viewer.handle(pg.event.Event(pg.VIDEORESIZE, w=1200, h=300, size=(1200, 300)))
    assert viewer.renderer.size == (1200, 300)
    a, b = viewer.renderer.world_to_pixel([[0.0, 0.0], [1.0, 1.0]])
    assert abs(b[0] - a[0]) == pytest.approx(abs(b[1] - a[1]))
    x0, y0, x1, y1 = viewer.renderer.view
    assert x0 <= bounds[0] and y0 <= bounds[1] + 1e-9 and x1 >= bounds[2] and y1 >= bounds[3] - 1e-9


def test_draw_shows_drag_preview_and_help(viewer):
    surface = pg.Surface(viewer.size)
    viewer.draw(surface)
    plain = pg.surfarray.array3d(surface).copy()
    press(viewer, pixel(viewer, (-0.2, 0.4)))
    move(viewer, pixel(viewer, (0.3, 0.4)))
    viewer.draw(surface)
    with_line = pg.surfarray.array3d(surface).copy()
    assert np.any(with_line != plain)
    viewer.show_help = True
    viewer.draw(surface)
    assert np.any(pg.surfarray.array3d(surface) != with_line)


def test_bad_arguments():
    with pytest.raises(ValueError, match="scene"):
        Viewer("nope", preview=0.0)
    with pytest.raises(ValueError, match="method"):
        Viewer("pendulum", method="leapfrog", preview=0.0)
    with pytest.raises(ValueError, match="dt"):
        Viewer("pendulum", dt=-1.0, preview=0.0)


def run_cli(monkeypatch, *argv):
    monkeypatch.setattr(sys, "argv", [sys.argv[0]])
    return cli_main(list(argv))


def test_headless_screenshot_is_a_non_blank_png(tmp_path, monkeypatch):
    from PIL import Image

    path = tmp_path / "shot.png"
    assert run_cli(monkeypatch, "view", "cloth", "--headless", "--frames", "3", "--size",
                   "320x240", "--screenshot", str(path)) == 0
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (320, 240)
        rgb = np.asarray(im.convert("RGB"))
    colours = np.unique(rgb.reshape(-1, 3), axis=0)
    assert len(colours) >= 6
    # cloth particles, the wall and the push arrows are all there
    for colour in [render.PARTICLE, render.WALL, render.APPLIED]:
        assert np.any(np.all(rgb == colour, axis=-1)), colour


def test_record_gif(tmp_path, monkeypatch):
    from PIL import Image

    path = tmp_path / "run.gif"
    assert run_cli(monkeypatch, "view", "pendulum", "--headless", "--frames", "8", "--fps",
                   "25", "--size", "160x120", "--record", str(path)) == 0
    with Image.open(path) as im:
        durations = []
        for k in range(im.n_frames):  # pillow merges identical frames, adding their durations
            im.seek(k)
            durations.append(im.info["duration"])
    assert len(durations) >= 2
    assert sum(durations) == pytest.approx(8 * 1000 / 25)


def test_cli_rejects_bad_record_path(tmp_path, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exc:
        run_cli(monkeypatch, "view", "pendulum", "--headless", "--frames", "1",
                "--record", str(tmp_path / "x.mp4"))
    assert exc.value.code == 2
    assert "--record" in capsys.readouterr().err


@pytest.mark.parametrize("env", [{"SDL_VIDEODRIVER": "dummy"},
                                 {"SDL_VIDEODRIVER": "", "DISPLAY": "", "WAYLAND_DISPLAY": ""}])
@pytest.mark.parametrize("argv", [["view", "pendulum"], ["demo", "--watch", "--episodes", "1"]])
def test_no_display_is_a_clear_usage_error(env, argv, monkeypatch, capsys):
    """Without a display, view and demo --watch stop before any work and say what to use."""
    if not sys.platform.startswith("linux") and env["SDL_VIDEODRIVER"] == "":
        pytest.skip("the DISPLAY check applies on Linux only")
    for name, value in env.items():
        if value:
            monkeypatch.setenv(name, value)
        else:
            monkeypatch.delenv(name, raising=False)
    with pytest.raises(SystemExit) as exc:
        run_cli(monkeypatch, *argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert ("--headless" in err and "--record" in err) if argv[0] == "view" else (
        "--save-gif" in err)


def test_display_problem_trusts_an_explicit_driver(monkeypatch):
    from constrained_particles.viewer import display_problem

    monkeypatch.setenv("SDL_VIDEODRIVER", "x11")
    monkeypatch.delenv("DISPLAY", raising=False)
    assert display_problem() is None
    monkeypatch.setenv("SDL_VIDEODRIVER", "offscreen")
    assert "offscreen" in display_problem()
