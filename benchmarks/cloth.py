"""The same spring-mass cloth in constrained-particles and in pymunk, and timers for both.

The cloth is ``scenes.cloth(N, N, wall_x=None, drag=0)``: structural, shear and bend damped
springs, the top row on a horizontal wire, gravity. In pymunk every particle is a body of the
same mass with infinite moment, every spring a ``DampedSpring`` with the same rest length,
stiffness and damping, and every top-row particle a ``GrooveJoint`` on a static groove.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import numpy as np

from constrained_particles import ParticleSystem, scenes
from constrained_particles.forces import DampedSpring, Gravity


def our_cloth(n: int) -> ParticleSystem:
    """The benchmark cloth, n x n particles."""
    return scenes.cloth(n, n, wall_x=None, drag=0.0)


def pymunk_space(system: ParticleSystem, iterations: int = 10):
    """A pymunk Space holding the same cloth as ``system`` (built by :func:`our_cloth`).

    Returns ``(space, bodies)``.
    """
    import pymunk

    space = pymunk.Space()
    space.iterations = iterations
    space.damping = 1.0
    space.sleep_time_threshold = float("inf")
    gravity = next(f for f in system.forces if isinstance(f, Gravity))
    space.gravity = tuple(gravity.g)
    bodies = []
    for p, m in zip(system.x, system.mass, strict=True):
        body = pymunk.Body(float(m), float("inf"))
        body.position = tuple(p)
        bodies.append(body)
    space.add(*bodies)
    springs = next(f for f in system.forces if isinstance(f, DampedSpring))
    space.add(*(pymunk.DampedSpring(bodies[i], bodies[j], (0, 0), (0, 0), float(r), float(k),
                                    float(c))
                for i, j, r, k, c in zip(springs.i, springs.j, springs.rest, springs.ks,
                                         springs.kd, strict=True)))
    wire = system.constraints[0]
    far = 1e3
    space.add(*(pymunk.GrooveJoint(space.static_body, bodies[i], (-far, float(y)), (far, float(y)),
                                   (0, 0))
                for i, y in zip(wire.particles, wire.height, strict=True)))
    return space, bodies


def pymunk_positions(bodies) -> np.ndarray:
    """Body positions as an (n, 2) array in metres."""
    return np.array([tuple(b.position) for b in bodies])


def rate(step: Callable[[], None], particles: int, repeats: int = 5, seconds: float = 0.25,
         warmup: int = 3) -> float:
    """Median particle-steps per second of ``step`` over ``repeats`` timed batches.

    Each batch runs whole steps for at least ``seconds`` of wall time after ``warmup`` steps.
    """
    for _ in range(warmup):
        step()
    rates = []
    for _ in range(repeats):
        k, t0 = 0, time.perf_counter()
        while True:
            step()
            k += 1
            elapsed = time.perf_counter() - t0
            if elapsed >= seconds:
                break
        rates.append(particles * k / elapsed)
    return statistics.median(rates)
