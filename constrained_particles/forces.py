"""Force blocks: gravity, applied forces, springs, drag, walls and the mouse spring.

Every class is one vectorized block. ``accumulate`` adds the block's forces (newtons) into an
(n, 2) array, ``potential`` returns its potential energy (joules; 0 for dissipative or
external forces) and ``element_forces`` gives per-element force vectors for drawing.
Formulas follow shared/DESIGN.md ("Physics (corrected)").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from .terms import Shape, Term, as_index_array, as_param_array, as_unit_vectors, scatter_add

if TYPE_CHECKING:
    from .system import ParticleSystem


def _perp(p: np.ndarray) -> np.ndarray:
    """Rotate (k, 2) vectors by +90 degrees: perp(p) = (-p_y, p_x)."""
    return np.stack([-p[:, 1], p[:, 0]], axis=1)


def _selected(idx: np.ndarray | None, n: int) -> np.ndarray:
    return np.arange(n) if idx is None else idx


class Force(Term):
    """Base class of force blocks."""

    conservative: ClassVar[bool] = False

    def accumulate(self, x: np.ndarray, v: np.ndarray, mass: np.ndarray, F: np.ndarray) -> None:
        """Add this block's forces (N) at positions ``x`` (m), velocities ``v`` (m/s) into ``F``."""
        raise NotImplementedError

    def potential(self, x: np.ndarray, mass: np.ndarray) -> float:
        """Potential energy in joules (0 for forces without one)."""
        return 0.0

    def element_forces(self, x: np.ndarray, v: np.ndarray, mass: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Per-element application points (k, 2) and force vectors (k, 2), for drawing."""
        F = np.zeros_like(x)
        self.accumulate(x, v, mass, F)
        moved = np.flatnonzero(np.any(F != 0, axis=1))
        return x[moved], F[moved]


class Gravity(Force):
    """Uniform gravitational field ``g`` (m/s^2) on ``particles`` (default: every particle).

    >>> from constrained_particles import ParticleSystem, Gravity
    >>> s = ParticleSystem(); p = s.add_particle((0.0, 0.0), mass=2.0)
    >>> s.add(Gravity((0.0, -9.81))); s.step(1e-3, method="euler"); float(s.v[p, 1])
    -0.00981
    """

    index_fields = ("particles",)
    conservative = True

    def __init__(self, g: Any = (0.0, -9.81), particles: Any = None) -> None:
        self.g = as_param_array("g", g, 1, width=2)[0]
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def accumulate(self, x, v, mass, F):
        if self.particles is None:
            F += mass[:, None] * self.g
        else:
            scatter_add(F, self.particles, mass[self.particles, None] * self.g)

    def potential(self, x, mass):
        idx = _selected(self.particles, len(x))
        return float(-np.sum(mass[idx] * (x[idx] @ self.g)))


class ConstantForce(Force):
    """A constant applied force (N) on chosen particles, e.g. the report's horizontal force.

    ``force`` broadcasts to one (2,) vector per particle and may be rewritten between steps
    (the environments write their actions into it). Its work is external input, so it has
    no potential energy.
    """

    index_fields = ("particles",)
    element_fields = ("force",)

    def __init__(self, particles: Any, force: Any) -> None:
        self.particles = as_index_array("particles", particles)
        self.force = as_param_array("force", force, len(self.particles), width=2)

    def accumulate(self, x, v, mass, F):
        scatter_add(F, self.particles, self.force)

    def element_forces(self, x, v, mass):
        return x[self.particles], self.force.copy()

    def shapes(self, x, v):
        return [Shape("arrow", "applied", x[self.particles], self.force.copy(),
                      np.linalg.norm(self.force, axis=1))]


class DampedSpring(Force):
    """Damped springs between particle pairs ``i`` and ``j``: one block for many springs.

    With ``l = x_i - x_j`` and ``ldot = v_i - v_j`` (DESIGN.md, report eq. 1 with its sign fixed):
    ``f_i = -[ks (|l| - rest) + kd (ldot . l)/|l|] l/|l|``, ``f_j = -f_i``, energy
    ``ks/2 (|l| - rest)^2``. ``rest`` (m) defaults to the current length, ``ks`` is in N/m and
    ``kd`` in N s/m. A spring of zero current length exerts no force (its direction is undefined).

    >>> from constrained_particles import ParticleSystem, DampedSpring
    >>> s = ParticleSystem()
    >>> a = s.add_particle((0.0, 0.0)); b = s.add_particle((2.0, 0.0))
    >>> s.add(DampedSpring(a, b, rest=1.0, ks=10.0))
    >>> float(s.potential_energy())
    5.0
    """

    index_fields = ("i", "j")
    element_fields = ("rest", "ks", "kd")
    conservative = True

    def __init__(self, i: Any, j: Any, rest: Any = None, ks: Any = 1.0, kd: Any = 0.0) -> None:
        self.i = as_index_array("i", i)
        self.j = as_index_array("j", j)
        k = len(self.i)
        if len(self.j) != k:
            raise ValueError(f"i and j must have the same length, got {k} and {len(self.j)}")
        if np.any(self.i == self.j):
            raise ValueError("i and j must differ: a spring needs two distinct particles")
        self.rest = None if rest is None else as_param_array("rest", rest, k, nonnegative=True)
        self.ks = as_param_array("ks", ks, k, nonnegative=True)
        self.kd = as_param_array("kd", kd, k, nonnegative=True)

    def bind(self, system):
        super().bind(system)
        if self.rest is None:
            self.rest = np.linalg.norm(system.x[self.i] - system.x[self.j], axis=1)

    def _geometry(self, x, v):
        l = x[self.i] - x[self.j]
        length = np.linalg.norm(l, axis=1)
        safe = np.where(length > 0, length, 1.0)
        u = l / safe[:, None] * (length > 0)[:, None]
        return l, length, u, v[self.i] - v[self.j]

    def element_forces(self, x, v, mass):
        """Force on particle ``i`` of each spring (the force on ``j`` is its negative)."""
        _, length, u, ldot = self._geometry(x, v)
        mag = self.ks * (length - self.rest) + self.kd * np.einsum("kd,kd->k", ldot, u)
        return x[self.i], -mag[:, None] * u

    def accumulate(self, x, v, mass, F):
        _, f = self.element_forces(x, v, mass)
        scatter_add(F, self.i, f)
        scatter_add(F, self.j, -f)

    def potential(self, x, mass):
        length = np.linalg.norm(x[self.i] - x[self.j], axis=1)
        return float(0.5 * np.sum(self.ks * (length - self.rest) ** 2))

    def shapes(self, x, v):
        length = np.linalg.norm(x[self.i] - x[self.j], axis=1)
        strain = (length - self.rest) / np.where(self.rest > 0, self.rest, 1.0)
        return [Shape("segment", "spring", x[self.i], x[self.j], strain)]


class AngularSpring(Force):
    """Angular springs on triples (``a``, vertex ``b``, ``c``) with rest angle ``rest`` (rad).

    With ``u = x_a - x_b``, ``w = x_c - x_b``, the signed angle ``theta = atan2(u x w, u . w)``
    and ``d = wrap(theta - rest)`` in (-pi, pi], the energy is ``k/2 d^2`` (``k`` in N m/rad)
    and the force on particle p is ``-(k d + kd thetadot) dtheta/dx_p``: exactly -grad E plus an
    optional damping term (``kd`` in N m s/rad), conserving linear and angular momentum.
    ``rest`` defaults to the current angle.
    """

    index_fields = ("a", "b", "c")
    element_fields = ("rest", "k", "kd")
    conservative = True

    def __init__(self, a: Any, b: Any, c: Any, rest: Any = None, k: Any = 1.0, kd: Any = 0.0
                 ) -> None:
        self.a = as_index_array("a", a)
        self.b = as_index_array("b", b)
        self.c = as_index_array("c", c)
        n = len(self.a)
        if len(self.b) != n or len(self.c) != n:
            raise ValueError("a, b and c must have the same length")
        if np.any((self.a == self.b) | (self.b == self.c) | (self.a == self.c)):
            raise ValueError("a, b and c must be three distinct particles")
        self.rest = None if rest is None else as_param_array("rest", rest, n)
        self.k = as_param_array("k", k, n, nonnegative=True)
        self.kd = as_param_array("kd", kd, n, nonnegative=True)

    def angles(self, x: np.ndarray) -> np.ndarray:
        """Signed angle (rad) from arm b->a to arm b->c of each triple."""
        u = x[self.a] - x[self.b]
        w = x[self.c] - x[self.b]
        return np.arctan2(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0], np.einsum("kd,kd->k", u, w))

    def bind(self, system):
        super().bind(system)
        if self.rest is None:
            self.rest = self.angles(system.x)

    def deviation(self, x: np.ndarray) -> np.ndarray:
        """``wrap(theta - rest)`` into (-pi, pi], in radians."""
        d = self.angles(x) - self.rest
        return np.pi - np.mod(np.pi - d, 2 * np.pi)

    def gradients(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dtheta/dx_a, dtheta/dx_b, dtheta/dx_c, each (k, 2), in rad/m (0 for a zero arm)."""
        u = x[self.a] - x[self.b]
        w = x[self.c] - x[self.b]
        uu = np.einsum("kd,kd->k", u, u)
        ww = np.einsum("kd,kd->k", w, w)
        ga = -_perp(u) / np.where(uu > 0, uu, np.inf)[:, None]
        gc = _perp(w) / np.where(ww > 0, ww, np.inf)[:, None]
        return ga, -(ga + gc), gc

    def accumulate(self, x, v, mass, F):
        ga, gb, gc = self.gradients(x)
        thetadot = (np.einsum("kd,kd->k", ga, v[self.a]) + np.einsum("kd,kd->k", gb, v[self.b])
                    + np.einsum("kd,kd->k", gc, v[self.c]))
        torque = -(self.k * self.deviation(x) + self.kd * thetadot)
        for idx, g in ((self.a, ga), (self.b, gb), (self.c, gc)):
            scatter_add(F, idx, torque[:, None] * g)

    def potential(self, x, mass):
        return float(0.5 * np.sum(self.k * self.deviation(x) ** 2))

    def shapes(self, x, v):
        arms = np.stack([x[self.a], x[self.c]], axis=1)
        return [Shape("angle", "angular", x[self.b], arms, self.deviation(x))]


class Drag(Force):
    """Viscous drag ``f = -kd v`` (``kd`` in N s/m) on ``particles`` (default: every particle)."""

    index_fields = ("particles",)

    def __init__(self, kd: float = 0.1, particles: Any = None) -> None:
        self.kd = float(as_param_array("kd", kd, 1, nonnegative=True)[0])
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def accumulate(self, x, v, mass, F):
        if self.particles is None:
            F -= self.kd * v
        else:
            scatter_add(F, self.particles, -self.kd * v[self.particles])


class Wall(Force):
    """A wall filling ``normal . x > offset``; particles live where ``normal . x <= offset``.

    ``normal`` is a direction pointing into the wall (normalised here), ``offset`` in metres.
    A particle at penetration ``p = normal . x - offset > 0`` feels the one-sided spring-damper
    ``f = -max(kw p + cw (normal . v), 0) normal`` (``kw`` in N/m, ``cw`` in N s/m). The
    ``max(., 0)`` keeps the damper from pulling a separating particle back in (DESIGN.md's
    formula without it makes walls sticky). Energy ``kw/2 p^2`` while inside.

    >>> from constrained_particles import Wall
    >>> right_wall = Wall((1.0, 0.0), 2.0)  # particles stay at x <= 2 m
    """

    index_fields = ("particles",)
    conservative = True

    def __init__(self, normal: Any = (1.0, 0.0), offset: float = 0.0, kw: float = 1e4,
                 cw: float = 1.0, particles: Any = None) -> None:
        self.normal = as_unit_vectors("normal", normal, 1)[0]
        self.offset = float(as_param_array("offset", offset, 1)[0])
        self.kw = float(as_param_array("kw", kw, 1, nonnegative=True)[0])
        self.cw = float(as_param_array("cw", cw, 1, nonnegative=True)[0])
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def penetration(self, x: np.ndarray) -> np.ndarray:
        """``normal . x - offset`` (m) for the affected particles; positive is inside the wall."""
        return x[_selected(self.particles, len(x))] @ self.normal - self.offset

    def accumulate(self, x, v, mass, F):
        idx = _selected(self.particles, len(x))
        p = x[idx] @ self.normal - self.offset
        inside = p > 0
        if not np.any(inside):
            return
        hit = idx[inside]
        mag = np.maximum(self.kw * p[inside] + self.cw * (v[hit] @ self.normal), 0.0)
        scatter_add(F, hit, -mag[:, None] * self.normal)

    def potential(self, x, mass):
        p = self.penetration(x)
        return float(0.5 * self.kw * np.sum(np.where(p > 0, p, 0.0) ** 2))

    def shapes(self, x, v):
        point = self.normal * self.offset
        return [Shape("halfplane", "wall", point[None, :], self.normal[None, :])]


class MouseSpring(Force):
    """Witkin's mouse spring: a zero-rest-length spring from a movable anchor to a particle.

    ``f = -ks (x_p - anchor) - kd v_p`` (``ks`` in N/m, ``kd`` in N s/m), energy
    ``ks/2 |x_p - anchor|^2``. A block holds several mouse springs (one per environment of a
    batch); each element can be switched off. ``grab``/``move``/``release`` edit it between
    steps.

    >>> from constrained_particles import MouseSpring
    >>> m = MouseSpring()            # one spring, not yet attached
    >>> m.grab(0, (1.0, 2.0)); bool(m.active[0])
    True
    """

    index_fields = ("particle",)
    element_fields = ("anchor", "active", "ks", "kd")
    conservative = True

    def __init__(self, particle: Any = None, anchor: Any = None, ks: Any = 50.0,
                 kd: Any = 1.0) -> None:
        attached = particle is not None
        self.particle = as_index_array("particle", 0 if particle is None else particle)
        k = len(self.particle)
        self.anchor = as_param_array("anchor", (0.0, 0.0) if anchor is None else anchor, k,
                                     width=2)
        self.ks = as_param_array("ks", ks, k, nonnegative=True)
        self.kd = as_param_array("kd", kd, k, nonnegative=True)
        self.active = np.full(k, attached)
        self._n: int | None = None

    def bind(self, system: ParticleSystem) -> None:
        super().bind(system)
        self._n = system.n

    def grab(self, particle: int, anchor: Any, element: int = 0) -> None:
        """Attach spring ``element`` to ``particle`` with its anchor at ``anchor`` (m)."""
        if self._n is not None and not 0 <= int(particle) < self._n:
            raise ValueError(f"particle {particle} is not a particle index (n = {self._n})")
        self.particle[element] = int(particle)
        self.move(anchor, element)
        self.active[element] = True

    def move(self, anchor: Any, element: int = 0) -> None:
        """Move the anchor of spring ``element`` to ``anchor`` (m)."""
        self.anchor[element] = as_param_array("anchor", anchor, 1, width=2)[0]

    def release(self, element: int = 0) -> None:
        """Detach spring ``element``."""
        self.active[element] = False

    def element_forces(self, x, v, mass):
        p = self.particle
        f = -self.ks[:, None] * (x[p] - self.anchor) - self.kd[:, None] * v[p]
        f *= self.active[:, None]
        return x[p], f

    def accumulate(self, x, v, mass, F):
        _, f = self.element_forces(x, v, mass)
        scatter_add(F, self.particle, f)

    def potential(self, x, mass):
        d = x[self.particle] - self.anchor
        return float(0.5 * np.sum(self.active * self.ks * np.einsum("kd,kd->k", d, d)))

    def shapes(self, x, v):
        on = self.active
        return [Shape("segment", "mouse", self.anchor[on], x[self.particle[on]],
                      np.zeros(int(on.sum())))]
