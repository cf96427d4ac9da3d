"""Rebuild the README's viewer pictures: ``python docs/viewer/screenshots.py`` (headless).

``cloth.png`` is exactly ``cparticles view cloth --headless --frames 120``;
``interaction.png`` drives the same viewer with synthetic mouse events: a spring drawn (with
ctrl) from the cloth's bottom-left corner to a new fixed particle, and the bottom-right corner
pulled by the mouse spring.
"""

import os
import sys
from pathlib import Path

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import pygame as pg  # noqa: E402

from constrained_particles.viewer import Viewer  # noqa: E402
from cparticles.cli import main  # noqa: E402

HERE = Path(__file__).parent


def interaction(path: Path) -> None:
    pg.display.init()
    pg.font.init()
    v = Viewer("cloth")
    surface = pg.display.set_mode(v.size)

    def event(kind, **kw):
        v.handle(pg.event.Event(kind, **kw))

    for _ in range(60):
        v.update(1 / 60)
    corner = v.renderer.world_to_pixel(v.system.x[56])[0]  # bottom-left particle
    event(pg.KEYDOWN, key=pg.K_LCTRL, mod=pg.KMOD_LCTRL, unicode="")  # a fixed new end
    event(pg.MOUSEBUTTONDOWN, pos=tuple(corner), button=1)
    event(pg.MOUSEMOTION, pos=tuple(corner + (-150, -30)), rel=(0, 0), buttons=(1, 0, 0))
    event(pg.MOUSEBUTTONUP, pos=tuple(corner + (-150, -30)), button=1)
    event(pg.KEYUP, key=pg.K_LCTRL, mod=0, unicode="")
    grab = v.renderer.world_to_pixel(v.system.x[63])[0]  # bottom-right particle
    event(pg.MOUSEBUTTONDOWN, pos=tuple(grab), button=3)
    event(pg.MOUSEMOTION, pos=tuple(grab + (60, -120)), rel=(0, 0), buttons=(0, 0, 1))
    for _ in range(40):
        v.update(1 / 60)
    v.fps = 60.0
    v.draw(surface)
    pg.image.save(surface, str(path))
    pg.quit()


if __name__ == "__main__":
    sys.argv = [sys.argv[0]]
    main(["view", "cloth", "--headless", "--frames", "120", "--screenshot",
          str(HERE / "cloth.png")])
    interaction(HERE / "interaction.png")
