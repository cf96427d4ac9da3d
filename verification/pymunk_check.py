"""An independent cross-check: the same scenes in pymunk (Chipmunk2D) converge to our trajectory.

:func:`to_pymunk` translates a :class:`~constrained_particles.ParticleSystem` into a pymunk
``Space``: every movable particle is a body of the same mass with infinite moment (it cannot
spin, so it behaves as a point); fixed particles are points of the static body; rods and
circular wires are ``PinJoint`` (a wire pins the particle to its centre on the static body),
line wires ``GrooveJoint`` on the static body, springs ``DampedSpring`` (pymunk damps the
relative velocity along the spring, like ours) and uniform gravity is the space's gravity.
pymunk's own velocity damping and sleeping are off, and its constraint solver runs enough
iterations that joint error is not what limits the comparison.

pymunk integrates with a first-order semi-implicit Euler step and fixes constraints with velocity
impulses, so as its dt shrinks its trajectory should approach ours at order about 1. Our side is
rk4 at a fine step (:data:`REFERENCE_H`), whose own error is orders of magnitude smaller.
The error is the largest particle position error (m) over ten checkpoints in the run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from constrained_particles import (
    CircularWire,
    ConstantForce,
    DampedSpring,
    Gravity,
    LineWire,
    ParticleSystem,
    Rod,
    scenes,
)

from .orders import checkpoints, run_positions, steps_between
from .properties import fit_slope

if TYPE_CHECKING:
    import pymunk

#: Step (s) of our rk4 trajectory that pymunk is compared with (quick: 1 ms, where rk4's own
#: error is still below 1e-8 m on these scenes, five orders under pymunk's).
REFERENCE_H = 2.5e-4
#: pymunk steps (s); the quick form uses the middle three.
PYMUNK_DTS = (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4)
#: Constraint-solver iterations per pymunk step (pymunk's default is 10).
ITERATIONS = 100
#: Half-length (m) of the grooves that stand for infinite line wires.
GROOVE_HALF_LENGTH = 1e3


def double_pendulum(length: float = 0.5, angle: float = 1.0, mass: float = 0.5
                    ) -> ParticleSystem:
    """Two particles of ``mass`` kg hanging from a fixed pivot by two rods of ``length`` m,
    released from rest with the upper rod at ``angle`` rad from the downward vertical and the
    lower one horizontal, under gravity."""
    s = ParticleSystem()
    pivot = s.add_particle((0.0, 0.0), fixed=True)
    p1 = np.array([np.sin(angle), -np.cos(angle)]) * length
    a = s.add_particle(p1, mass=mass)
    b = s.add_particle(p1 + (length, 0.0), mass=mass)
    s.add(Gravity((0.0, -scenes.G)), Rod([pivot, a], [a, b]))
    return s


def spring_chain(links: int = 4, link: float = 0.25, ks: float = 40.0, kd: float = 0.1,
                 mass: float = 0.2) -> ParticleSystem:
    """``links`` damped springs (``ks`` N/m, ``kd`` N s/m, rest ``link`` m) chaining ``links``
    particles of ``mass`` kg to a fixed particle at the origin; released horizontal, at rest
    length, under gravity."""
    s = ParticleSystem()
    pos = np.stack([np.arange(links + 1) * link, np.zeros(links + 1)], axis=1)
    idx = s.add_particles(pos, mass=mass, fixed=np.arange(links + 1) == 0)
    s.add(Gravity((0.0, -scenes.G)), DampedSpring(idx[:-1], idx[1:], ks=ks, kd=kd))
    return s


def small_cloth() -> ParticleSystem:
    """A 4 x 3 cloth (structural, shear and bend springs of 50 N/m, 0.02 N s/m damping, 0.02 kg
    particles 0.1 m apart) whose top row slides on a horizontal wire, pushed right by 0.02 N per
    top particle; no drag and no wall."""
    return scenes.cloth(nx=4, ny=3, ks=50.0, kd=0.02, drag=0.0, wall_x=None, push=0.02)


#: Scenes of the cross-check, by name.
SCENES: dict[str, Callable[[], ParticleSystem]] = {
    "pendulum": scenes.pendulum,
    "double_pendulum": double_pendulum,
    "slider_crank": scenes.wire_mixture,
    "spring_chain": spring_chain,
    "cloth_on_wire": small_cloth,
}


@dataclass
class PymunkScene:
    """A pymunk space standing for a particle system.

    ``bodies`` has one entry per particle: its body, or None for a fixed particle. ``forces``
    maps a body to the constant force (N) applied to it before every step (pymunk clears body
    forces after each step).
    """

    space: pymunk.Space
    bodies: list[pymunk.Body | None]
    forces: dict[pymunk.Body, tuple[float, float]]

    def step(self, dt: float) -> None:
        """One pymunk step of ``dt`` seconds."""
        for body, force in self.forces.items():
            body.force = force
        self.space.step(dt)


def to_pymunk(system: ParticleSystem, iterations: int = ITERATIONS) -> PymunkScene:
    """The pymunk equivalent of ``system``.

    Raises ValueError for a block pymunk cannot express this way (anything but uniform gravity,
    constant forces, damped springs, rods, circular and line wires).
    """
    import pymunk

    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    space = pymunk.Space()
    space.iterations = int(iterations)
    space.damping = 1.0  # no velocity damping
    space.sleep_time_threshold = float("inf")
    static = space.static_body
    bodies: list = []
    for x, v, m, w in zip(system.x, system.v, system.mass, system.inv_mass, strict=True):
        if w == 0:
            bodies.append(None)
            continue
        body = pymunk.Body(float(m), float("inf"))
        body.position = tuple(map(float, x))
        body.velocity = tuple(map(float, v))
        space.add(body)
        bodies.append(body)

    def end(i: int) -> tuple[object, tuple[float, float]]:
        """(body, local anchor) of particle i: the static body at its position if fixed."""
        body = bodies[i]
        return (static, tuple(map(float, system.x[i]))) if body is None else (body, (0.0, 0.0))

    forces: dict = {}
    for f in system.forces:
        if isinstance(f, Gravity) and f.particles is None:
            space.gravity = tuple(map(float, np.asarray(space.gravity) + f.g))
        elif isinstance(f, ConstantForce):
            for p, force in zip(f.particles, f.force, strict=True):
                if bodies[p] is not None:
                    total = forces.get(bodies[p], (0.0, 0.0))
                    forces[bodies[p]] = (total[0] + float(force[0]), total[1] + float(force[1]))
        elif isinstance(f, DampedSpring):
            for i, j, rest, ks, kd in zip(f.i, f.j, f.rest, f.ks, f.kd, strict=True):
                (a, pa), (b, pb) = end(i), end(j)
                space.add(pymunk.DampedSpring(a, b, pa, pb, float(rest), float(ks), float(kd)))
        else:
            raise ValueError(f"system: pymunk has no equivalent of {type(f).__name__} here")
    for c in system.constraints:
        if isinstance(c, Rod):
            for i, j in zip(c.a, c.b, strict=True):
                (a, pa), (b, pb) = end(i), end(j)
                space.add(pymunk.PinJoint(a, b, pa, pb))
        elif isinstance(c, CircularWire):
            for p, centre in zip(c.particles, c.center, strict=True):
                space.add(pymunk.PinJoint(static, bodies[p], tuple(map(float, centre)), (0, 0)))
        elif isinstance(c, LineWire):
            direction = np.stack([c.normal[:, 1], -c.normal[:, 0]], axis=1)
            for p, point, d in zip(c.particles, c.point, direction, strict=True):
                ga, gb = point - GROOVE_HALF_LENGTH * d, point + GROOVE_HALF_LENGTH * d
                space.add(pymunk.GrooveJoint(static, bodies[p], tuple(map(float, ga)),
                                             tuple(map(float, gb)), (0, 0)))
        else:
            raise ValueError(f"system: pymunk has no equivalent of {type(c).__name__} here")
    return PymunkScene(space, bodies, forces)


def pymunk_positions(system: ParticleSystem, dt: float, times: np.ndarray,
                     iterations: int = ITERATIONS) -> np.ndarray:
    """Positions (len(times), n, 2) in metres of ``system`` simulated by pymunk with step ``dt``
    (s), sampled at ``times`` (each a whole number of steps after the start)."""
    scene = to_pymunk(system, iterations)
    out = np.empty((len(times), system.n, 2))
    for k, steps in enumerate(steps_between(times, system.t, dt)):
        for _ in range(steps):
            scene.step(dt)
        out[k] = [system.x[i] if b is None else tuple(b.position)
                  for i, b in enumerate(scene.bodies)]
    return out


@dataclass
class PymunkResult:
    """pymunk's position error (m) against our trajectory, and its CPU time (s), per dt (s)."""

    scene: str
    dts: list[float]
    errors: list[float]
    cpu: list[float]
    order: float

    def to_dict(self) -> dict:
        return asdict(self)

    def error_at(self, dt: float) -> float:
        """The error at step ``dt`` (s)."""
        return self.errors[min(range(len(self.dts)), key=lambda k: abs(self.dts[k] - dt))]


def compare(name: str, dts: Sequence[float] = PYMUNK_DTS, duration: float = 1.0,
            iterations: int = ITERATIONS, reference_h: float = REFERENCE_H, repeats: int = 3,
            progress: Callable[[], None] | None = None) -> PymunkResult:
    """Run scene ``name`` in pymunk at each dt and measure its distance to our rk4 trajectory
    (step ``reference_h``) over ``duration`` seconds; the observed order is the slope of
    log(error) on log(dt). CPU time: the best of ``repeats`` runs."""
    if name not in SCENES:
        raise ValueError(f"name must be one of {sorted(SCENES)}, got {name!r}")
    system = SCENES[name]()
    times = checkpoints(duration)
    ours = run_positions(system, "rk4", reference_h, times)
    errors, cpu = [], []
    pymunk_positions(system, dts[0], times[:1], iterations)  # warm-up, untimed
    for dt in dts:
        runs = []
        for _ in range(repeats):
            start = time.process_time()
            theirs = pymunk_positions(system, dt, times, iterations)
            runs.append(time.process_time() - start)
        cpu.append(min(runs))
        errors.append(float(np.max(np.abs(theirs - ours))))
        if progress is not None:
            progress()
    return PymunkResult(name, list(dts), errors, cpu, fit_slope(dts, errors))


def reference_step(quick: bool = False) -> float:
    """The rk4 step (s) of our side: :data:`REFERENCE_H`, or 1 ms in the quick form."""
    return 1e-3 if quick else REFERENCE_H


def compare_all(names: Sequence[str] | None = None, quick: bool = False, progress: bool = False
                ) -> dict[str, PymunkResult]:
    """:func:`compare` on every scene (quick: three dts around 1e-3 and half a second)."""
    names = list(SCENES) if names is None else list(names)
    dts = PYMUNK_DTS[1:4] if quick else PYMUNK_DTS
    reference_h = reference_step(quick)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(names) * len(dts), desc="pymunk", unit="run")
    try:
        return {n: compare(n, dts, duration=1.0, reference_h=reference_h,
                           progress=bar.update if bar else None) for n in names}
    finally:
        if bar is not None:
            bar.close()


def pymunk_table(results: dict[str, PymunkResult]) -> str:
    """A Markdown table of pymunk's error per dt and its observed order, per scene."""
    dts = sorted({dt for r in results.values() for dt in r.dts}, reverse=True)
    head = " | ".join(f"dt = {dt:g} s" for dt in dts)
    lines = [f"| scene | {head} | observed order |", "|---|" + "---|" * (len(dts) + 1)]
    for name, r in results.items():
        cells = " | ".join(f"{r.error_at(dt):.2e}" if dt in r.dts else "" for dt in dts)
        lines.append(f"| {name} | {cells} | {r.order:.2f} |")
    return "\n".join(lines)
