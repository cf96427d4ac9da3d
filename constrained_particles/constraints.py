"""Constraint blocks: circular wire, rod, line wires and fixed points.

Each block holds ``len(self) * rows_per_element`` scalar constraints ``C(q) = 0``. It declares
the sparsity pattern of its rows of ``J = dC/dq`` once (:meth:`Constraint.pattern`, columns
index the stacked coordinates ``q = (x_0, y_0, x_1, y_1, ...)``) and, at every evaluation,
returns ``C``, ``Cdot = J qdot`` and the values of ``J`` and ``Jdot = dJ/dt`` in that pattern's
order (:meth:`Constraint.evaluate`). Formulas follow docs/physics.md ("Constraints").
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .terms import Shape, Term, as_index_array, as_param_array, as_unit_vectors


class Constraint(Term):
    """Base class of constraint blocks."""

    rows_per_element: ClassVar[int] = 1

    def bind(self, system):
        super().bind(system)
        limit = system.divergence_limit
        for name in self.element_fields:
            arr = getattr(self, name)
            if arr is not None and not np.all(np.abs(arr) < limit):
                raise ValueError(f"{type(self).__name__}: {name} must be within the system's "
                                 f"divergence_limit = {limit:g} (m), got {arr!r}")

    @property
    def n_rows(self) -> int:
        """Number of scalar constraint rows in this block."""
        return len(self) * self.rows_per_element

    def pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """Local row and global column (into q, length 2n) of every structural nonzero of J."""
        raise NotImplementedError

    def evaluate(self, x: np.ndarray, v: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(C, Cdot, J values, Jdot values)`` at positions ``x`` (m), velocities ``v`` (m/s)."""
        raise NotImplementedError

    def distance_error(self, x: np.ndarray) -> np.ndarray:
        """Geometric residual (m) of each row at positions ``x``, shape (n_rows,): how far the
        state is from satisfying it. This default is ``|C|``, right for constraints whose ``C``
        is a length; blocks whose ``C`` is not (e.g. half a squared length) override it."""
        return np.abs(self.evaluate(x, np.zeros_like(x))[0])


def _xy_columns(idx: np.ndarray) -> np.ndarray:
    """(k, 2) columns of the x and y coordinates of particles ``idx`` in q."""
    return np.stack([2 * idx, 2 * idx + 1], axis=1)


class _OneParticle(Constraint):
    """A constraint whose rows each involve one particle through a gradient g (k, 2)."""

    index_fields = ("particles",)

    def pattern(self):
        k = len(self.particles)
        return np.repeat(np.arange(k), 2), _xy_columns(self.particles).ravel()


class CircularWire(_OneParticle):
    """Particles on circles: ``C = 1/2 (|x - center|^2 - radius^2)`` (docs/physics.md).

    ``J = (x - center)^T``, ``Jdot = v^T``. ``center`` in metres; ``radius`` (m, > 0) defaults to
    the current distance from the centre.

    >>> from constrained_particles import ParticleSystem, CircularWire
    >>> s = ParticleSystem(); p = s.add_particle((0.0, -1.3))
    >>> s.add(CircularWire(p, center=(0.0, 0.0))); float(s.constraints[0].radius[0])
    1.3
    """

    element_fields = ("center", "radius")

    def __init__(self, particles: ArrayLike, center: ArrayLike = (0.0, 0.0),
                 radius: ArrayLike | None = None) -> None:
        self.particles = as_index_array("particles", particles)
        k = len(self.particles)
        self.center = as_param_array("center", center, k, width=2)
        self.radius = None if radius is None else as_param_array("radius", radius, k,
                                                                  positive=True)

    def bind(self, system):
        super().bind(system)
        if self.radius is None:
            r = np.linalg.norm(system.x[self.particles] - self.center, axis=1)
            if np.any(r <= 0):
                raise ValueError("radius: a particle sits on the centre of its circular wire; "
                                 "give a radius > 0")
            self.radius = r

    def evaluate(self, x, v):
        d = x[self.particles] - self.center
        vp = v[self.particles]
        C = 0.5 * (np.einsum("kd,kd->k", d, d) - self.radius**2)
        return C, np.einsum("kd,kd->k", d, vp), d.ravel(), vp.ravel()

    def distance_error(self, x):
        """``| |x - center| - radius |`` (m): the distance from the wire."""
        return np.abs(np.linalg.norm(x[self.particles] - self.center, axis=1) - self.radius)

    def shapes(self, x, v):
        return [Shape("circle", "wire", self.center.copy(), None, self.radius.copy())]


class Rod(Constraint):
    """Rigid rods between ``a`` and ``b``, an equality (docs/physics.md, "Constraints").

    ``C = 1/2 (|x_a - x_b|^2 - length^2)``, ``J = [d^T, -d^T]`` with ``d = x_a - x_b``,
    ``Jdot = [dv^T, -dv^T]``. ``length`` (m, > 0) defaults to the current distance.

    >>> from constrained_particles import ParticleSystem, Rod
    >>> s = ParticleSystem()
    >>> a = s.add_particle((0.0, 0.0), fixed=True); b = s.add_particle((0.0, -2.0))
    >>> s.add(Rod(a, b)); float(s.constraints[0].length[0])
    2.0
    """

    index_fields = ("a", "b")
    element_fields = ("length",)

    def __init__(self, a: ArrayLike, b: ArrayLike, length: ArrayLike | None = None) -> None:
        self.a = as_index_array("a", a)
        self.b = as_index_array("b", b)
        if len(self.a) != len(self.b):
            raise ValueError(f"a and b must have the same length, got {len(self.a)}, {len(self.b)}")
        if np.any(self.a == self.b):
            raise ValueError("a and b must differ: a rod joins two distinct particles")
        self.length = None if length is None else as_param_array("length", length, len(self.a),
                                                                  positive=True)

    def bind(self, system):
        super().bind(system)
        both_fixed = (system.inv_mass[self.a] == 0) & (system.inv_mass[self.b] == 0)
        if np.any(both_fixed):
            raise ValueError("a, b: a rod between two fixed particles constrains nothing "
                             f"(rods {np.flatnonzero(both_fixed).tolist()})")
        if self.length is None:
            length = np.linalg.norm(system.x[self.a] - system.x[self.b], axis=1)
            if np.any(length <= 0):
                raise ValueError("length: a rod between coincident particles would have length 0")
            self.length = length

    def pattern(self):
        k = len(self.a)
        cols = np.concatenate([_xy_columns(self.a), _xy_columns(self.b)], axis=1)
        return np.repeat(np.arange(k), 4), cols.ravel()

    def evaluate(self, x, v):
        d = x[self.a] - x[self.b]
        dv = v[self.a] - v[self.b]
        C = 0.5 * (np.einsum("kd,kd->k", d, d) - self.length**2)
        return (C, np.einsum("kd,kd->k", d, dv), np.concatenate([d, -d], axis=1).ravel(),
                np.concatenate([dv, -dv], axis=1).ravel())

    def distance_error(self, x):
        """``| |x_a - x_b| - length |`` (m): the error of each rod's length."""
        return np.abs(np.linalg.norm(x[self.a] - x[self.b], axis=1) - self.length)

    def shapes(self, x, v):
        return [Shape("segment", "rod", x[self.a], x[self.b], np.zeros(len(self.a)))]


class LineWire(_OneParticle):
    """Particles sliding on straight wires: ``C = n . (x - point)`` with ``n`` the wire's normal.

    ``direction`` is the wire's direction (normalised here; ``n = perp(direction)``), ``point``
    a point on it in metres, defaulting to each particle's current position. ``J = n^T``,
    ``Jdot = 0``.
    """

    element_fields = ("point", "normal")

    def __init__(self, particles: ArrayLike, direction: ArrayLike = (1.0, 0.0),
                 point: ArrayLike | None = None) -> None:
        self.particles = as_index_array("particles", particles)
        k = len(self.particles)
        d = as_unit_vectors("direction", direction, k)
        self.normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
        self.point = None if point is None else as_param_array("point", point, k, width=2)

    def bind(self, system):
        super().bind(system)
        if self.point is None:
            self.point = system.x[self.particles].copy()

    def evaluate(self, x, v):
        p, nx, ny = self.particles, self.normal[:, 0], self.normal[:, 1]
        xp, vp = x.take(p, axis=0), v.take(p, axis=0)
        C = nx * (xp[:, 0] - self.point[:, 0]) + ny * (xp[:, 1] - self.point[:, 1])
        Cdot = nx * vp[:, 0] + ny * vp[:, 1]
        return C, Cdot, self.normal.ravel(), np.zeros(2 * len(p))

    def distance_error(self, x):
        """``|C| = |n . (x - point)|`` (m): the distance from the wire."""
        d = x.take(self.particles, axis=0) - self.point
        return np.abs(d[:, 0] * self.normal[:, 0] + d[:, 1] * self.normal[:, 1])

    def shapes(self, x, v):
        direction = np.stack([self.normal[:, 1], -self.normal[:, 0]], axis=1)
        return [Shape("line", "wire", self.point.copy(), direction)]


class HorizontalWire(LineWire):
    """Particles sliding on a horizontal wire at ``height`` (m): ``C = y - height``.

    ``height`` defaults to each particle's current height.
    """

    def __init__(self, particles: ArrayLike, height: float | None = None) -> None:
        point = None if height is None else (0.0, float(as_param_array("height", height, 1)[0]))
        super().__init__(particles, direction=(1.0, 0.0), point=point)

    @property
    def height(self) -> np.ndarray:
        """Wire height (m) of each element."""
        return self.point[:, 1]


class FixedPoint(Constraint):
    """Pins particles to points (two rows each): ``C = x - point``, ``J = I``, ``Jdot = 0``.

    Not ``1/2 |x - point|^2``, whose gradient vanishes on the constraint and would make
    ``J W J^T`` singular. ``point`` (m) defaults to the current position.
    """

    index_fields = ("particles",)
    element_fields = ("point",)
    rows_per_element = 2

    def __init__(self, particles: ArrayLike, point: ArrayLike | None = None) -> None:
        self.particles = as_index_array("particles", particles)
        self.point = None if point is None else as_param_array("point", point, len(self.particles),
                                                                width=2)

    def bind(self, system):
        super().bind(system)
        if self.point is None:
            self.point = system.x[self.particles].copy()

    def pattern(self):
        return np.arange(2 * len(self.particles)), _xy_columns(self.particles).ravel()

    def evaluate(self, x, v):
        k = len(self.particles)
        return ((x[self.particles] - self.point).ravel(), v[self.particles].ravel(),
                np.ones(2 * k), np.zeros(2 * k))

    def distance_error(self, x):
        """``|C|`` (m) per row: the x and y offsets of each particle from its point."""
        return np.abs((x[self.particles] - self.point).ravel())

    def shapes(self, x, v):
        return [Shape("circle", "pin", self.point.copy(), None, np.zeros(len(self.particles)))]
