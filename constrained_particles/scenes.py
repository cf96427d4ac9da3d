"""Ready-to-run scenes, in SI units (metres, kilograms, seconds).

``SCENES`` maps a name to a builder that takes only keyword arguments with defaults.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .constraints import CircularWire, HorizontalWire, Rod
from .forces import AngularSpring, ConstantForce, DampedSpring, Drag, Gravity, Wall
from .system import ParticleSystem

G = 9.81  #: standard gravity, m/s^2


def spring_pair(separation: float = 1.0, rest: float = 0.6, ks: float = 20.0, kd: float = 0.2,
                mass: float = 0.5) -> ParticleSystem:
    """Two free particles joined by one damped spring, stretched and released.

    ``separation`` and ``rest`` in m, ``ks`` in N/m, ``kd`` in N s/m, ``mass`` in kg. No gravity,
    so the pair oscillates about its fixed centre of mass.
    """
    s = ParticleSystem()
    a = s.add_particle((-separation / 2, 0.0), mass=mass)
    b = s.add_particle((separation / 2, 0.0), mass=mass)
    s.add(DampedSpring(a, b, rest=rest, ks=ks, kd=kd))
    return s


def gravity(count: int = 5, floor: float = -1.0, drag: float = 0.0) -> ParticleSystem:
    """Projectiles under gravity launched at different angles, bouncing on a floor wall at
    ``floor`` (m); optional viscous ``drag`` (N s/m)."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    s = ParticleSystem()
    angles = np.linspace(np.pi / 6, np.pi / 2.2, count)
    s.add_particles(np.zeros((count, 2)), 3.0 * np.stack([np.cos(angles), np.sin(angles)], 1),
                    mass=0.1)
    s.add(Gravity((0.0, -G)), Wall((0.0, -1.0), -floor, kw=2000.0, cw=0.5))
    if drag > 0:
        s.add(Drag(drag))
    return s


def cloth(nx: int = 8, ny: int = 8, spacing: float = 0.1, mass: float = 0.02,
          ks: float = 500.0, kd: float = 0.2, shear: bool = True, bend: bool = True,
          wire_height: float = 0.0, wall_x: float | None = 1.2, push: float = 0.0,
          drag: float = 0.01) -> ParticleSystem:
    """A spring-mass cloth hanging from a horizontal wire, with a wall to its right.

    ``nx`` x ``ny`` particles of ``mass`` kg, ``spacing`` m apart, the top row (the first ``nx``
    particles) sliding on a wire at ``wire_height`` m. Structural springs join neighbours,
    ``shear`` springs the diagonals (stiffness ``ks/2``) and ``bend`` springs every second
    particle (``ks/4``); ``ks`` in N/m, ``kd`` in N s/m. Particle ``(row, col)`` has index
    ``row * nx + col``; row 0 is the top. The wall fills ``x > wall_x`` (None: no wall). ``push``
    (N) is a horizontal force on each top-row particle, toward the wall. ``drag`` in N s/m.
    """
    if nx < 2 or ny < 2:
        raise ValueError(f"nx and ny must be >= 2, got nx={nx}, ny={ny}")
    if spacing <= 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    s = ParticleSystem()
    col, row = np.meshgrid(np.arange(nx), np.arange(ny))
    pos = np.stack([col.ravel() * spacing, wire_height - row.ravel() * spacing], axis=1)
    s.add_particles(pos, mass=mass)
    idx = (row * nx + col)
    pairs = [(idx[:, :-1], idx[:, 1:], ks), (idx[:-1, :], idx[1:, :], ks)]
    if shear:
        pairs += [(idx[:-1, :-1], idx[1:, 1:], ks / 2), (idx[:-1, 1:], idx[1:, :-1], ks / 2)]
    if bend:
        pairs += [(idx[:, :-2], idx[:, 2:], ks / 4), (idx[:-2, :], idx[2:, :], ks / 4)]
    i = np.concatenate([p[0].ravel() for p in pairs])
    j = np.concatenate([p[1].ravel() for p in pairs])
    k = np.concatenate([np.full(p[0].size, p[2]) for p in pairs])
    s.add(Gravity((0.0, -G)), DampedSpring(i, j, ks=k, kd=kd),
          HorizontalWire(idx[0], height=wire_height))
    if drag > 0:
        s.add(Drag(drag))
    if wall_x is not None:
        s.add(Wall((1.0, 0.0), wall_x, kw=200.0, cw=0.5))
    if push:
        s.add(ConstantForce(idx[0], (push, 0.0)))
    return s


def wire_mixture(radius: float = 0.3, rod: float = 0.8, wire_height: float = 0.0,
                 angle: float = 1.0, omega: float = 4.0, mass: float = 0.1) -> ParticleSystem:
    """A mixture of constraints (circular wire, horizontal wire, rod): a slider-crank.

    Particle 0 (the crank) rides a circular wire of ``radius`` m centred at the origin, starting
    at ``angle`` rad (counter-clockwise from +x) with angular speed ``omega`` rad/s; particle 1
    (the slider) rides a horizontal wire at ``wire_height`` m; a rod of ``rod`` m joins them.
    Both have ``mass`` kg, under gravity. Velocities are made consistent with the constraints.
    """
    if rod <= radius + abs(wire_height):
        raise ValueError(f"rod must exceed radius + |wire_height| so the slider can always "
                         f"reach the wire, got rod={rod}, radius={radius}")
    s = ParticleSystem()
    crank = np.array([np.cos(angle), np.sin(angle)]) * radius
    dy = crank[1] - wire_height
    slider = np.array([crank[0] + np.sqrt(rod**2 - dy**2), wire_height])
    c = s.add_particle(crank, velocity=omega * radius * np.array([-np.sin(angle), np.cos(angle)]),
                       mass=mass)
    p = s.add_particle(slider, mass=mass)
    s.add(Gravity((0.0, -G)), CircularWire(c, (0.0, 0.0), radius), HorizontalWire(p, wire_height),
          Rod(c, p, rod))
    s.project()
    return s


def angular_chain(links: int = 8, link: float = 0.15, stiffness: float = 0.5,
                  damping: float = 0.01, mass: float = 0.05) -> ParticleSystem:
    """A chain hanging from a fixed particle, released horizontally.

    ``links`` rods of ``link`` m join ``links + 1`` particles of ``mass`` kg (particle 0 fixed at
    the origin); angular springs of ``stiffness`` N m/rad and ``damping`` N m s/rad at every
    interior particle keep it straight (rest angle pi), so it swings down like a bending beam.
    """
    if links < 2:
        raise ValueError(f"links must be >= 2, got {links}")
    s = ParticleSystem()
    pos = np.stack([np.arange(links + 1) * link, np.zeros(links + 1)], axis=1)
    s.add_particles(pos, mass=mass, fixed=np.arange(links + 1) == 0)
    i = np.arange(links + 1)
    s.add(Gravity((0.0, -G)), Rod(i[:-1], i[1:]),
          AngularSpring(i[:-2], i[1:-1], i[2:], rest=np.pi, k=stiffness, kd=damping))
    return s


def pendulum(length: float = 1.0, angle: float = 0.5, mass: float = 1.0) -> ParticleSystem:
    """One particle of ``mass`` kg on a circular wire of radius ``length`` m centred at the origin,
    released from rest ``angle`` rad from the downward vertical (positive: to the right)."""
    if length <= 0:
        raise ValueError(f"length must be > 0, got {length}")
    s = ParticleSystem()
    p = s.add_particle((length * np.sin(angle), -length * np.cos(angle)), mass=mass)
    s.add(Gravity((0.0, -G)), CircularWire(p, (0.0, 0.0), length))
    return s


SCENES: dict[str, Callable[..., ParticleSystem]] = {
    "spring_pair": spring_pair,
    "gravity": gravity,
    "cloth": cloth,
    "wire_mixture": wire_mixture,
    "angular_chain": angular_chain,
    "pendulum": pendulum,
}
