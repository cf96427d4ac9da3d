"""The same spring-mass cloth in constrained-particles and in pymunk, and timers for both.

The cloth is ``scenes.cloth(N, N, wall_x=None, drag=0)``: structural, shear and bend damped
springs, the top row on a horizontal wire, gravity. pymunk gets the same system through the
verification suite's translation: every particle a body of the same mass with infinite moment,
every spring a ``DampedSpring`` with the same rest length, stiffness and damping, and every
top-row particle a ``GrooveJoint`` on a static groove.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from constrained_particles import ParticleSystem, SimulationDiverged, scenes


def our_cloth(n: int) -> ParticleSystem:
    """The benchmark cloth, n x n particles."""
    return scenes.cloth(n, n, wall_x=None, drag=0.0)


def pymunk_cloth(system: ParticleSystem, iterations: int = 10):
    """The same cloth in pymunk (``verification.pymunk_check.to_pymunk``: infinite-moment bodies,
    ``DampedSpring``s, ``GrooveJoint`` wires), with ``iterations`` solver iterations. The result
    has ``step(dt)`` and ``bodies``."""
    from verification.pymunk_check import to_pymunk

    return to_pymunk(system, iterations)


def pymunk_positions(scene) -> np.ndarray:
    """Body positions of a :func:`pymunk_cloth` scene as an (n, 2) array in metres."""
    return np.array([tuple(b.position) for b in scene.bodies])


def rates(steps: dict, particles: int, repeats: int = 5, seconds: float = 0.25,
          warmup: int = 3) -> dict:
    """Median particle-steps per second of each ``steps[name]`` over ``repeats`` timed batches.

    Each batch runs whole steps for at least ``seconds`` of wall time after ``warmup`` steps.
    The engines' batches alternate (round-robin), so a machine that slows down or speeds up
    during the run affects all of them alike and their ratios stay meaningful. An engine whose
    simulation diverges gets ``None``.
    """
    samples: dict = {name: [] for name in steps}
    live = dict(steps)
    for name, step in steps.items():
        try:
            for _ in range(warmup):
                step()
        except SimulationDiverged:
            del live[name]
    for _ in range(repeats):
        for name, step in list(live.items()):
            k, t0 = 0, time.perf_counter()
            try:
                while True:
                    step()
                    k += 1
                    elapsed = time.perf_counter() - t0
                    if elapsed >= seconds:
                        break
            except SimulationDiverged:
                del live[name]
                continue
            samples[name].append(particles * k / elapsed)
    return {name: statistics.median(r) if name in live else None for name, r in samples.items()}
