"""``cparticles view``: the interactive viewer (pygame-ce).

A :class:`Viewer` owns a :class:`~constrained_particles.system.ParticleSystem` built from
:data:`~constrained_particles.scenes.SCENES`, a :class:`~constrained_particles.render.Renderer`
(the project's one drawing module) and the interaction state. Events go in through
:meth:`Viewer.handle`, time through :meth:`Viewer.update` and pictures come out of
:meth:`Viewer.draw`, so the same object runs in a window, headless, or under synthetic events
in the tests. pygame is imported only inside functions.

Mouse: press-drag-release draws a damped spring between the press and
release points, creating a particle at each end unless one is within :attr:`Viewer.snap_radius`
pixels; a click places a single particle under the same proximity check; right-drag (or
shift-drag) pulls the nearest particle with Witkin's mouse spring. :data:`CONTROLS` lists
every key.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .arguments import int_at_least, output_file, positive_float, time_step
from .extras import require
from .forces import DampedSpring, Drag, Gravity, MouseSpring, Wall
from .integrators import METHODS
from .render import Renderer, _pygame
from .scenes import SCENES
from .system import ParticleSystem, SimulationDiverged
from .terms import Shape

if TYPE_CHECKING:
    import pygame
    from PIL import Image

#: Integrators selected by keys 1-6 (a name missing from METHODS is reported, not selected).
INTEGRATOR_KEYS = ("euler", "midpoint", "rk4", "symplectic_euler", "implicit_euler", "rattle")

#: Keyword arguments the viewer passes to a scene builder: the cloth gets a horizontal push
#: (N per top-row particle) so that it slides into its wall.
SCENE_KWARGS: dict[str, dict[str, float]] = {"cloth": {"push": 0.06}}

#: Default time step (s) per scene; scenes not listed use :data:`DEFAULT_DT`.
SCENE_DT: dict[str, float] = {"gravity": 2e-3, "angular_chain": 2e-3}
DEFAULT_DT = 1e-3
DT_RANGE = (1e-6, 0.5)  #: the + and - keys keep dt inside this range (s)

SNAP_RADIUS = 12.0  #: pixels: a press or release this close to a particle uses it
CLICK_RADIUS = 5.0  #: pixels: a press and release closer than this is a click, not a drag

#: (control, action) rows: the help overlay and the controls table of docs/viewer.md.
CONTROLS: tuple[tuple[str, str], ...] = (
    ("left drag", f"draw a spring (ends snap to a particle within {SNAP_RADIUS:g} px, "
                  "else new particles)"),
    ("left click", f"place a particle (unless one is within {SNAP_RADIUS:g} px)"),
    ("ctrl + click / drag", "the same, but new particles are fixed"),
    ("right drag, shift + drag", "pull the nearest particle with a mouse spring"),
    (" ".join(str(k) for k in range(1, len(INTEGRATOR_KEYS) + 1)),
     "integrator: " + ", ".join(INTEGRATOR_KEYS)),
    ("+ / -", "time step x2 / /2"),
    ("space", "pause / run"),
    (".", "single step (pauses)"),
    ("r", "reset the scene"),
    ("n / p", "next / previous scene"),
    ("f", "applied-force arrows on / off"),
    ("c", "constraint-force arrows on / off"),
    ("h", "this help"),
    ("q / Esc", "quit"),
)


def _median(values: list[np.ndarray], default: float) -> float:
    flat = np.concatenate(values) if values else np.zeros(0)
    return float(np.median(flat)) if flat.size else default


class Viewer:
    """Interactive state around one scene: system, renderer, integrator, dt and mouse tools.

    ``scene`` is a key of :data:`~constrained_particles.scenes.SCENES`; ``method`` an
    integrator name; ``dt`` the step in seconds (default: :data:`SCENE_DT` or
    :data:`DEFAULT_DT`); ``size`` the picture in pixels. ``forces`` and ``constraint_forces``
    switch the two kinds of arrows (both on by default). ``preview`` seconds of motion are
    simulated (on a copy, with symplectic Euler) when a scene loads so that the view fits where
    it goes, not only where it starts. ``max_steps`` caps the steps per frame: when stepping
    falls behind real time the simulation runs in slow motion instead of freezing the window.

    >>> v = Viewer("spring_pair", preview=0.0)
    >>> i = v.add_particle_at((0.0, 0.5))
    >>> v.add_spring(0, i)
    >>> v.system.n, v.user_springs.rest.round(3).tolist()
    (3, [0.707])
    """

    snap_radius = SNAP_RADIUS  #: pixels (see :data:`SNAP_RADIUS`)
    click_radius = CLICK_RADIUS  #: pixels (see :data:`CLICK_RADIUS`)
    headroom = 0.15  #: extra view height above the scene, as a fraction of the view width

    def __init__(self, scene: str = "cloth", *, method: str = "rk4", dt: float | None = None,
                 size: Sequence[int] = (960, 640), forces: bool = True,
                 constraint_forces: bool = True, preview: float = 1.5,
                 max_steps: int = 100) -> None:
        if method not in METHODS:
            raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
        if dt is not None and not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        if not preview >= 0:
            raise ValueError(f"preview must be >= 0 seconds, got {preview!r}")
        if int(max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps!r}")
        self.method = method
        self.size = tuple(int(s) for s in size)
        self.show_forces = bool(forces)
        self.show_constraint_forces = bool(constraint_forces)
        self.show_help = False
        self.preview = float(preview)
        self.max_steps = int(max_steps)
        self.running = True
        self.fps = 0.0  #: measured frames per second, set by the main loop
        self._modifiers = {"shift": False, "ctrl": False}
        self.load(scene, dt)

    # ------------------------------------------------------------------ scenes
    @property
    def scene_names(self) -> list[str]:
        """Scene names in the order n / p cycles through them."""
        return list(SCENES)

    def load(self, scene: str, dt: float | None = None) -> None:
        """Build ``scene`` afresh, fit the view to it and reset time, dt and the mouse tools."""
        if scene not in SCENES:
            raise ValueError(f"scene must be one of {sorted(SCENES)}, got {scene!r}")
        self.scene = scene
        self.dt = float(dt) if dt is not None else SCENE_DT.get(scene, DEFAULT_DT)
        self.reset()
        fit = Renderer.fit(self.system, self.size, points=self._preview_points())
        x0, y0, x1, y1 = fit.bounds
        # headroom above the scene for the HUD lines and upward force arrows
        self.renderer = Renderer((x0, y0, x1, y1 + self.headroom * (x1 - x0)), self.size)

    def reset(self) -> None:
        """Rebuild the current scene (user particles and springs are dropped; integrator, dt
        and the view are kept) and run."""
        self.system: ParticleSystem = SCENES[self.scene](**SCENE_KWARGS.get(self.scene, {}))
        self.user_springs: DampedSpring | None = None
        self.mouse: MouseSpring | None = None
        self._grab_button = 0
        self.paused = False
        self.message = ""
        self._press: tuple[np.ndarray, int | None, bool] | None = None  # pixel, particle, fixed
        self._cursor = np.zeros(2)
        self._accumulated = 0.0
        self._behind = False
        springs = [f for f in self.system.forces if isinstance(f, DampedSpring)]
        movable = self.system.mass[~self.system.fixed]
        #: mass (kg) of particles the user places: the scene's typical movable mass
        self.new_mass = float(np.median(movable)) if movable.size else 0.1
        # new springs look like the scene's springs; without any, a 1.5 Hz spring with 5% of
        # critical damping between two new particles
        default_ks = self.new_mass * (2 * np.pi * 1.5) ** 2
        self.new_ks = _median([f.ks for f in springs], default_ks)
        self.new_kd = _median([f.kd for f in springs],
                              0.05 * 2 * np.sqrt(self.new_ks * self.new_mass))

    def _preview_points(self) -> np.ndarray | None:
        if self.preview <= 0:
            return None
        sim = self.system.copy()
        h = max(self.dt, self.preview / 1500)  # at most 1,500 cheap steps
        steps = int(round(self.preview / h))
        every = max(1, steps // 30)
        points = [sim.x.copy()]
        try:
            for k in range(1, steps + 1):
                sim.step(h, method="symplectic_euler")
                if k % every == 0:
                    points.append(sim.x.copy())
        except SimulationDiverged:
            pass
        return np.concatenate(points)

    # ------------------------------------------------------------------ editing
    def nearest(self, pixel: ArrayLike, radius: float | None = None, movable: bool = False,
                exclude: int | None = None) -> int | None:
        """Index of the particle nearest to ``pixel`` (within ``radius`` pixels if given),
        optionally only movable ones and never ``exclude``; None if there is none."""
        if self.system.n == 0:
            return None
        d = np.linalg.norm(self.renderer.world_to_pixel(self.system.x) - np.asarray(pixel),
                           axis=1)
        if movable:
            d[self.system.fixed] = np.inf
        if exclude is not None:
            d[exclude] = np.inf
        k = int(np.argmin(d))
        limit = np.inf if radius is None else radius
        return k if d[k] <= limit and np.isfinite(d[k]) else None

    def add_particle_at(self, position: ArrayLike, fixed: bool = False) -> int:
        """Add a particle at ``position`` (m) with :attr:`new_mass`, and give it the scene's
        gravity, drag and walls (blocks listing their particles are extended; blocks without a
        list already act on every particle). Returns its index."""
        i = self.system.add_particle(position, mass=self.new_mass, fixed=fixed)
        for f in self.system.forces:
            if isinstance(f, (Gravity, Drag, Wall)) and f.particles is not None:
                f.particles = np.append(f.particles, i)
        return i

    def add_spring(self, i: int, j: int) -> None:
        """Join particles ``i`` and ``j`` with a damped spring whose rest length is their current
        distance, stiffness :attr:`new_ks` (N/m) and damping :attr:`new_kd` (N s/m). All user
        springs live in one :class:`DampedSpring` block, :attr:`user_springs`."""
        old = self.user_springs
        ii = [i] if old is None else [*old.i, i]
        jj = [j] if old is None else [*old.j, j]
        rest = np.linalg.norm(self.system.x[i] - self.system.x[j])
        rests = [rest] if old is None else [*old.rest, rest]
        block = DampedSpring(ii, jj, rest=rests, ks=self.new_ks, kd=self.new_kd)
        if old is not None:
            self.system.remove(old)
        self.system.add(block)
        self.user_springs = block

    def _endpoint(self, pixel: np.ndarray, particle: int | None, fixed: bool) -> int:
        if particle is not None:
            return particle
        return self.add_particle_at(self.renderer.pixel_to_world(pixel)[0], fixed=fixed)

    def grab(self, pixel: ArrayLike) -> None:
        """Attach a mouse spring from the cursor at ``pixel`` to the nearest movable particle.

        Its stiffness gives the whole scene's movable mass a 2 Hz pull (capped so the grabbed
        particle alone stays resolved by the step), with critical damping of that particle.
        """
        k = self.nearest(pixel, movable=True)
        if k is None:
            return
        total = float(np.sum(self.system.mass[~self.system.fixed]))
        m = float(self.system.mass[k])
        ks = min(total * (2 * np.pi * 2.0) ** 2, m * (0.5 / self.dt) ** 2)
        anchor = self.renderer.pixel_to_world(pixel)[0]
        self.mouse = MouseSpring(k, anchor, ks=ks, kd=2 * np.sqrt(ks * m))
        self.system.add(self.mouse)

    def release(self) -> None:
        """Detach the mouse spring, if any."""
        if self.mouse is not None:
            self.system.remove(self.mouse)
            self.mouse = None

    # ------------------------------------------------------------------ events
    def handle(self, event: pygame.event.Event) -> None:
        """React to one pygame event (keys, mouse buttons and motion, resize, quit)."""
        pg = _pygame()
        if event.type == pg.QUIT:
            self.running = False
        elif event.type in (pg.KEYDOWN, pg.KEYUP):
            self._track_modifiers(pg, event)
            if event.type == pg.KEYDOWN:
                self._key(pg, event.key)
        elif event.type == pg.MOUSEBUTTONDOWN:
            self._mouse_down(pg, event)
        elif event.type == pg.MOUSEMOTION:
            self._cursor = np.asarray(event.pos, float)
            if self.mouse is not None:
                self.mouse.move(self.renderer.pixel_to_world(self._cursor)[0])
        elif event.type == pg.MOUSEBUTTONUP:
            self._mouse_up(pg, event)
        elif event.type == pg.VIDEORESIZE:
            self.size = (max(1, event.w), max(1, event.h))
            self.renderer.resize(self.size)

    def _track_modifiers(self, pg: ModuleType, event: pygame.event.Event) -> None:
        down = event.type == pg.KEYDOWN
        if event.key in (pg.K_LSHIFT, pg.K_RSHIFT):
            self._modifiers["shift"] = down
        elif event.key in (pg.K_LCTRL, pg.K_RCTRL):
            self._modifiers["ctrl"] = down

    def _held(self, pg: ModuleType, name: str) -> bool:
        mask = pg.KMOD_SHIFT if name == "shift" else pg.KMOD_CTRL
        live = bool(pg.key.get_mods() & mask) if pg.display.get_init() else False
        return live or self._modifiers[name]

    def _key(self, pg: ModuleType, key: int) -> None:
        keys = range(1, len(INTEGRATOR_KEYS) + 1)
        numbers = {getattr(pg, f"K_{k}"): k - 1 for k in keys}
        numbers.update({getattr(pg, f"K_KP{k}"): k - 1 for k in keys})
        actions: dict[int, Callable[[], None]] = {
            pg.K_SPACE: self.toggle_pause,
            pg.K_PERIOD: self.single_step,
            pg.K_KP_PERIOD: self.single_step,
            pg.K_r: self.reset,
            pg.K_n: lambda: self.cycle_scene(1),
            pg.K_p: lambda: self.cycle_scene(-1),
            pg.K_f: lambda: setattr(self, "show_forces", not self.show_forces),
            pg.K_c: lambda: setattr(self, "show_constraint_forces",
                                    not self.show_constraint_forces),
            pg.K_h: lambda: setattr(self, "show_help", not self.show_help),
            pg.K_q: self.quit,
            pg.K_ESCAPE: self.quit,
        }
        for k in (pg.K_PLUS, pg.K_EQUALS, pg.K_KP_PLUS):
            actions[k] = lambda: self.scale_dt(2.0)
        for k in (pg.K_MINUS, pg.K_KP_MINUS):
            actions[k] = lambda: self.scale_dt(0.5)
        if key in numbers:
            self.select_method(INTEGRATOR_KEYS[numbers[key]])
        elif key in actions:
            actions[key]()

    def _mouse_down(self, pg: ModuleType, event: pygame.event.Event) -> None:
        pixel = np.asarray(event.pos, float)
        self._cursor = pixel
        if event.button == 3 or (event.button == 1 and self._held(pg, "shift")):
            self.release()
            self.grab(pixel)
            self._grab_button = event.button
        elif event.button == 1:
            self._press = (pixel, self.nearest(pixel, self.snap_radius), self._held(pg, "ctrl"))

    def _mouse_up(self, pg: ModuleType, event: pygame.event.Event) -> None:
        pixel = np.asarray(event.pos, float)
        self._cursor = pixel
        if self.mouse is not None and event.button == self._grab_button:
            self.release()
            return
        if event.button != 1 or self._press is None:
            return
        start, a, fixed = self._press
        self._press = None
        if np.linalg.norm(pixel - start) < self.click_radius:
            if a is None:
                self.add_particle_at(self.renderer.pixel_to_world(pixel)[0], fixed=fixed)
            return
        b = self.nearest(pixel, self.snap_radius, exclude=a)
        i = self._endpoint(start, a, fixed)
        j = self._endpoint(pixel, b, fixed)
        self.add_spring(i, j)

    # ------------------------------------------------------------------ commands
    def select_method(self, name: str) -> None:
        """Switch the integrator to ``name`` (a message if it is not available)."""
        if name in METHODS:
            self.method = name
            self.message = ""
        else:
            self.message = f"{name} is not available (have: {', '.join(METHODS)})"

    def scale_dt(self, factor: float) -> None:
        """Multiply dt by ``factor``, kept inside :data:`DT_RANGE`."""
        self.dt = float(np.clip(self.dt * factor, *DT_RANGE))

    def toggle_pause(self) -> None:
        """Pause or run (running again clears a divergence message)."""
        self.paused = not self.paused
        if not self.paused:
            self.message = ""

    def single_step(self) -> None:
        """Pause and advance exactly one step."""
        self.paused = True
        self._step(1)

    def cycle_scene(self, offset: int) -> None:
        """Load the scene ``offset`` places further in :attr:`scene_names` (wrapping)."""
        names = self.scene_names
        self.load(names[(names.index(self.scene) + offset) % len(names)])

    def quit(self) -> None:
        """Stop the main loop."""
        self.running = False

    # ------------------------------------------------------------------ time and drawing
    def update(self, real_dt: float) -> int:
        """Advance the simulation by ``real_dt`` seconds of real time: as many dt steps as fit
        (the remainder carries to the next frame), at most :attr:`max_steps`. Returns the
        number of steps taken; a diverging step pauses with a message instead of raising."""
        if self.paused:
            self._accumulated = 0.0
            return 0
        self._accumulated += max(0.0, float(real_dt))
        steps = int(self._accumulated / self.dt)
        self._behind = steps > self.max_steps
        if self._behind:
            steps, self._accumulated = self.max_steps, 0.0
        else:
            self._accumulated -= steps * self.dt
        return self._step(steps)

    def _step(self, steps: int) -> int:
        for k in range(steps):
            try:
                self.system.step(self.dt, method=self.method)
            except SimulationDiverged:
                self.paused = True
                self.message = (f"DIVERGED at t = {self.system.t:.4g} s with {self.method}, "
                                f"dt = {self.dt:.3g} s: paused (- smaller dt, r reset, "
                                f"1-{len(INTEGRATOR_KEYS)} integrator, space run on)")
                return k
        return steps

    def hud(self) -> list[str]:
        """The heads-up lines: scene, integrator, dt, simulated time, energy, max ``|C|``, fps,
        then the state (running, paused, a message)."""
        C, _ = self.system.constraint_residual()
        worst = float(np.max(np.abs(C))) if C.size else 0.0
        line = (f"{self.scene}  |  {self.method}  |  dt {self.dt * 1e3:.3g} ms  |  "
                f"t {self.system.t:.3f} s  |  E {self.system.energy():.5g} J  |  "
                f"max|C| {worst:.2e}  |  {self.fps:.0f} fps")
        state = "paused" if self.paused else "running"
        if self._behind and not self.paused:
            state += " (slow motion: the steps do not fit in real time)"
        status = self.message or f"{state}  |  {self.system.n} particles  |  h: help"
        return [line, status]

    def extra_shapes(self) -> list[Shape]:
        """The spring being drawn (from its start to the cursor), as a renderer shape."""
        if self._press is None:
            return []
        start, a, _ = self._press
        begin = self.system.x[a] if a is not None else self.renderer.pixel_to_world(start)[0]
        end = self.renderer.pixel_to_world(self._cursor)[0]
        return [Shape("segment", "mouse", begin[None, :], end[None, :], np.zeros(1))]

    def draw(self, surface: pygame.Surface) -> None:
        """Draw the scene, the HUD and (if on) the help overlay onto the pygame ``surface``."""
        self.renderer.draw(surface, self.system, extra=self.extra_shapes(),
                           forces=self.show_forces,
                           constraint_forces=self.show_constraint_forces, hud=self.hud())
        if self.show_help:
            self._draw_help(surface)

    def _draw_help(self, surface: pygame.Surface) -> None:
        pg = _pygame()
        if not pg.font.get_init():
            pg.font.init()
        font = pg.font.Font(None, 22)
        rows = [(font.render(k, True, (255, 255, 255)), font.render(a, True, (230, 230, 230)))
                for k, a in CONTROLS]
        left = max(r[0].get_width() for r in rows) + 24
        width = left + max(r[1].get_width() for r in rows) + 16
        height = 22 * len(rows) + 20
        panel = pg.Surface((width, height), pg.SRCALPHA)
        panel.fill((20, 20, 30, 215))
        for k, (key, action) in enumerate(rows):
            panel.blit(key, (12, 10 + 22 * k))
            panel.blit(action, (left, 10 + 22 * k))
        w, h = surface.get_size()
        surface.blit(panel, ((w - width) // 2, max(50, (h - height) // 2)))


# ---------------------------------------------------------------------- command line
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must look like 960x640, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"--size must be at least 16x16, got {text!r}")
    return w, h


def display_problem() -> str | None:
    """Why no window can be opened here, or None if one (probably) can.

    ``SDL_VIDEODRIVER=dummy`` or ``offscreen`` opens no window; on Linux without
    ``SDL_VIDEODRIVER`` a window needs ``DISPLAY`` (X11) or ``WAYLAND_DISPLAY``. Setting
    ``SDL_VIDEODRIVER`` to a real driver (``x11``, ``wayland``, ``kmsdrm``) skips the check.
    """
    driver = os.environ.get("SDL_VIDEODRIVER", "").strip().lower()
    if driver in ("dummy", "offscreen"):
        return f"SDL_VIDEODRIVER={driver} opens no window"
    if (not driver and sys.platform.startswith("linux")
            and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")):
        return "no display to open a window on (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles view``."""
    parser.add_argument("scene", nargs="?", default="cloth", choices=list(SCENES),
                        help="scene to open (n / p cycle through the others)")
    parser.add_argument("--method", default="rk4", choices=sorted(METHODS), help="integrator")
    parser.add_argument("--dt", type=time_step, default=None,
                        help=f"time step in seconds (default {DEFAULT_DT:g}, or the scene's)")
    parser.add_argument("--size", type=_size, default=(960, 640), help="window size, WxH pixels")
    parser.add_argument("--fps", type=positive_float, default=60.0, help="frames per second")
    parser.add_argument("--headless", action="store_true",
                        help="no window (SDL dummy driver); each frame advances 1/fps s")
    parser.add_argument("--frames", type=int_at_least(1), default=None,
                        help="stop after this many frames (default: 120 when headless)")
    parser.add_argument("--screenshot", type=output_file(".png"), default=None,
                        metavar="PATH.png",
                        help="save the last frame as a PNG (default: no screenshot)")
    parser.add_argument("--record", type=output_file(".gif"), default=None, metavar="PATH.gif",
                        help="record the session to an animated GIF (pillow, at most 25 "
                        "frames/s; frames stay in memory until the end, so keep it short; default: "
                        "no recording)")
    parser.add_argument("--no-forces", action="store_true", help="start with force arrows off")
    parser.add_argument("--no-constraint-forces", action="store_true",
                        help="start with constraint-force arrows off")


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Before any work: the ``render`` extra is installed, and a window can be opened unless
    ``--headless``."""
    require("pygame", "PIL", command="cparticles view")
    if args.dt is not None and not DT_RANGE[0] <= args.dt <= DT_RANGE[1]:
        parser.error(f"argument --dt: must be in [{DT_RANGE[0]:g}, {DT_RANGE[1]:g}] s, "
                     f"got {args.dt:g}")
    problem = None if args.headless else display_problem()
    if problem:
        parser.error(f"{problem}; run with --headless (add --screenshot PATH.png or "
                     "--record PATH.gif to keep what it shows)")


def main(args: argparse.Namespace) -> int:
    """``cparticles view``: open the viewer (or run it headless) until quit or ``--frames``."""
    frames = args.frames if args.frames is not None else (120 if args.headless else None)
    viewer = Viewer(args.scene, method=args.method, dt=args.dt, size=args.size,
                    forces=not args.no_forces, constraint_forces=not args.no_constraint_forces)
    if args.headless:
        os.environ["SDL_VIDEODRIVER"] = "dummy"
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    pg = _pygame()
    pg.display.init()  # no pg.init(): the viewer needs no audio device
    pg.font.init()
    try:
        flags = 0 if args.headless else pg.RESIZABLE
        pg.display.set_mode(viewer.size, flags)
        pg.display.set_caption("cparticles view")
        recorder = _Recorder(args.record) if args.record else None
        run(viewer, frames=frames, fps=args.fps, realtime=not args.headless,
            on_frame=recorder.add if recorder else None)
        surface = pg.display.get_surface()
        if args.screenshot:
            pg.image.save(surface, args.screenshot)
            print(f"saved {args.screenshot}")
        if recorder:
            recorder.save()
            print(f"saved {args.record} ({len(recorder.frames)} frames)")
    finally:
        pg.quit()
    return 0


def run(viewer: Viewer, frames: int | None = None, fps: float = 60.0, realtime: bool = True,
        on_frame: Callable[[pygame.Surface, float], None] | None = None) -> int:
    """The main loop on the current pygame display: events, ``update``, ``draw``, flip.

    With ``realtime`` each frame advances the real time that passed (the clock holds ``fps``);
    without it each frame advances exactly ``1 / fps`` s, so headless runs are deterministic.
    ``on_frame(surface, seconds)`` is called after every frame is drawn with the time that
    frame advanced. Returns the number of frames drawn.
    """
    pg = _pygame()
    clock = pg.time.Clock()
    count = 0
    last = time.perf_counter()
    while viewer.running and (frames is None or count < frames):
        for event in pg.event.get():
            viewer.handle(event)
        elapsed = min(clock.tick(fps) / 1000.0, 0.25) if realtime else 1.0 / fps
        viewer.update(elapsed)
        surface = pg.display.get_surface()
        viewer.draw(surface)
        pg.display.flip()
        if on_frame is not None:
            on_frame(surface, elapsed)
        now = time.perf_counter()
        rate = 1.0 / max(now - last, 1e-6)
        viewer.fps = rate if viewer.fps == 0 else 0.9 * viewer.fps + 0.1 * rate
        last = now
        count += 1
    return count


class _Recorder:
    """Collects frames at most 25 per second (of session time) and writes an animated GIF
    whose frame durations are the session's own, so it plays back in real time."""

    interval = 0.04  # s between captured frames at least

    def __init__(self, path: str) -> None:
        self.path = path
        self.frames: list[Image.Image] = []
        self.durations: list[float] = []  # ms
        self._since = 0.0

    def add(self, surface: pygame.Surface, elapsed: float) -> None:
        self._since += elapsed
        if self.frames and self._since < self.interval - 1e-9:
            return
        from PIL import Image

        if self.frames:
            self.durations.append(1000.0 * self._since)
        self._since = 0.0
        pg = _pygame()
        rgb = np.ascontiguousarray(pg.surfarray.array3d(surface).transpose(1, 0, 2))
        # palette frames at once: a third of the memory of RGB ones
        self.frames.append(Image.fromarray(rgb).quantize(colors=128,
                                                         method=Image.Quantize.FASTOCTREE))

    def save(self) -> None:
        if self.frames:
            last = 1000.0 * max(self._since, self.interval)
            self.frames[0].save(self.path, save_all=True, append_images=self.frames[1:],
                                duration=[*self.durations, last], loop=0)
