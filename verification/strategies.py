"""Random constrained particle systems, for hypothesis and for seeded experiments.

One builder draws every choice through a small *drawer*: :func:`systems` backs it with
hypothesis (so failing examples shrink), :func:`random_system` with a seeded numpy generator (so
an experiment can name one system by its seed). What it builds:

- 2-12 particles (0.5-2 kg) on distinct cells of a 4 m x 4 m grid, jittered by at most 0.2 m,
  so any two are at least 0.6 m apart; about one in five is fixed (never all of them);
- constraints of every kind (:class:`Rod`, :class:`CircularWire`, :class:`HorizontalWire`,
  :class:`LineWire`, :class:`FixedPoint`), each placed through the particle's current position so
  that ``C = 0`` at the start;
- damped springs (1-30 N/m, rest length 0.7-1.3 times the current length) and angular springs
  (0.1-2 N m/rad, rest angle within 0.4 rad of the current angle), optional gravity;
- velocities up to 1 m/s per coordinate, projected so that ``Cdot = J v = 0``.

Degenerate systems are never built. Rods and the particles they join form a forest in which each
tree is *grounded* at most once (by a fixed particle, a wire or a fixed point), so no rod loop
can lock and ``J W J^T`` is non-singular in every configuration: peel the tree from its leaves,
each leaf's coordinates appear only in its own rod's row. No movable particle carries more
constraint rows than its two coordinates, no constraint acts on fixed particles only, and no
spring joins two fixed particles.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from constrained_particles import (
    AngularSpring,
    CircularWire,
    DampedSpring,
    Drag,
    FixedPoint,
    Gravity,
    HorizontalWire,
    LineWire,
    ParticleSystem,
    Rod,
)

if TYPE_CHECKING:
    from hypothesis.strategies import SearchStrategy

GRID = 4  #: particles sit on distinct cells of a GRID x GRID grid with 1 m cells
JITTER = 0.2  #: maximal displacement (m) of a particle from its cell centre
CONSTRAINT_KINDS = ("rod", "circular_wire", "horizontal_wire", "line_wire", "fixed_point")


class Drawer(Protocol):
    """Source of random choices; smaller draws should mean simpler systems (for shrinking)."""

    def integer(self, lo: int, hi: int) -> int:
        """An integer in [lo, hi]."""

    def real(self, lo: float, hi: float) -> float:
        """A float in [lo, hi]."""

    def cells(self, k: int) -> list[int]:
        """``k`` distinct grid cells out of ``GRID**2``."""


class _HypothesisDrawer:
    def __init__(self, draw: Any) -> None:
        from hypothesis import strategies as st

        self._draw, self._st = draw, st

    def integer(self, lo: int, hi: int) -> int:
        return self._draw(self._st.integers(lo, hi))

    def real(self, lo: float, hi: float) -> float:
        return self._draw(self._st.floats(lo, hi, allow_nan=False, allow_infinity=False))

    def cells(self, k: int) -> list[int]:
        return self._draw(self._st.permutations(range(GRID**2)))[:k]


class _NumpyDrawer:
    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)

    def integer(self, lo: int, hi: int) -> int:
        return int(self._rng.integers(lo, hi + 1))

    def real(self, lo: float, hi: float) -> float:
        return float(self._rng.uniform(lo, hi))

    def cells(self, k: int) -> list[int]:
        return [int(c) for c in self._rng.permutation(GRID**2)[:k]]


class _Topology:
    """Bookkeeping that keeps the constraint graph a singly grounded forest."""

    def __init__(self, fixed: np.ndarray) -> None:
        self.fixed = fixed
        self.parent = list(range(len(fixed)))
        self.grounded = [bool(f) for f in fixed]
        self.rows = [0] * len(fixed)

    def root(self, i: int) -> int:
        while self.parent[i] != i:
            i = self.parent[i]
        return i

    def can_ground(self, p: int, rows: int) -> bool:
        """Whether movable particle ``p`` may take ``rows`` rows tying it to the world."""
        return (not self.fixed[p] and not self.grounded[self.root(p)]
                and self.rows[p] + rows <= 2)

    def ground(self, p: int, rows: int) -> None:
        self.grounded[self.root(p)] = True
        self.rows[p] += rows

    def can_join(self, a: int, b: int) -> bool:
        ra, rb = self.root(a), self.root(b)
        return (a != b and ra != rb and not (self.grounded[ra] and self.grounded[rb])
                and all(self.fixed[p] or self.rows[p] < 2 for p in (a, b)))

    def join(self, a: int, b: int) -> None:
        ra, rb = self.root(a), self.root(b)
        self.parent[rb] = ra
        self.grounded[ra] = self.grounded[ra] or self.grounded[rb]
        for p in (a, b):
            self.rows[p] += 1


def build_system(draw: Drawer, *, min_particles: int = 2, max_particles: int = 12,
                 gravity: bool | None = None, damped: bool = False, solver: str | None = None
                 ) -> ParticleSystem:
    """Build one random system from the choices of ``draw`` (see the module docstring).

    ``gravity`` None lets the drawer decide; ``damped`` adds spring damping and drag (otherwise
    the system conserves energy); ``solver`` None lets the drawer pick ``"cg"`` or ``"direct"``.
    """
    if not 2 <= min_particles <= max_particles <= GRID**2:
        raise ValueError(f"min_particles, max_particles must satisfy 2 <= min <= max <= {GRID**2}, "
                         f"got {min_particles}, {max_particles}")
    n = draw.integer(min_particles, max_particles)
    cells = np.array(draw.cells(n))
    centres = np.stack([cells % GRID, cells // GRID], axis=1) - (GRID - 1) / 2
    jitter = np.array([[draw.real(-JITTER, JITTER) for _ in range(2)] for _ in range(n)])
    x = centres + jitter
    mass = np.array([draw.real(0.5, 2.0) for _ in range(n)])
    fixed = np.array([draw.integer(0, 4) == 4 for _ in range(n)])
    if fixed.all():
        fixed[0] = False
    movable = np.flatnonzero(~fixed)
    solver = ("cg", "direct")[draw.integer(0, 1)] if solver is None else solver
    s = ParticleSystem(solver=solver)
    s.add_particles(x, mass=mass, fixed=fixed)

    topo = _Topology(fixed)
    rods: list[tuple[int, int]] = []
    circles: list[tuple[int, tuple[float, float]]] = []
    lines: list[tuple[int, tuple[float, float]]] = []
    horizontal: list[int] = []
    pinned: list[int] = []
    for _ in range(draw.integer(0, n + 2)):
        kind = CONSTRAINT_KINDS[draw.integer(0, len(CONSTRAINT_KINDS) - 1)]
        if kind == "rod":
            a, b = draw.integer(0, n - 1), draw.integer(0, n - 1)
            if topo.can_join(a, b) and not (fixed[a] and fixed[b]):
                topo.join(a, b)
                rods.append((a, b))
            continue
        p = int(movable[draw.integer(0, len(movable) - 1)])
        rows = 2 if kind == "fixed_point" else 1
        if not topo.can_ground(p, rows):
            continue
        topo.ground(p, rows)
        if kind == "circular_wire":
            radius, phi = draw.real(0.3, 1.0), draw.real(-np.pi, np.pi)
            circles.append((p, (x[p, 0] - radius * np.cos(phi), x[p, 1] - radius * np.sin(phi))))
        elif kind == "line_wire":
            phi = draw.real(-np.pi, np.pi)
            lines.append((p, (np.cos(phi), np.sin(phi))))
        elif kind == "horizontal_wire":
            horizontal.append(p)
        else:
            pinned.append(p)
    if rods:
        a, b = np.array(rods).T
        s.add(Rod(a, b))
    if circles:
        s.add(CircularWire([p for p, _ in circles], [c for _, c in circles]))
    if lines:
        s.add(LineWire([p for p, _ in lines], [d for _, d in lines]))
    if horizontal:
        s.add(HorizontalWire(horizontal))
    if pinned:
        s.add(FixedPoint(pinned))

    springs = []
    for _ in range(draw.integer(0, n + 2)):
        i, j = draw.integer(0, n - 1), draw.integer(0, n - 1)
        if i != j and not (fixed[i] and fixed[j]):
            springs.append((i, j, draw.real(0.7, 1.3), draw.real(1.0, 30.0),
                            draw.real(0.0, 0.5) if damped else 0.0))
    if springs:
        i, j, stretch, ks, kd = (np.array(c) for c in zip(*springs, strict=True))
        i, j = i.astype(int), j.astype(int)
        s.add(DampedSpring(i, j, rest=stretch * np.linalg.norm(x[i] - x[j], axis=1), ks=ks, kd=kd))
    triples = []
    for _ in range(draw.integer(0, 3)):
        a, b, c = (draw.integer(0, n - 1) for _ in range(3))
        if len({a, b, c}) == 3 and not (fixed[a] and fixed[b] and fixed[c]):
            triples.append((a, b, c, draw.real(-0.4, 0.4), draw.real(0.1, 2.0),
                            draw.real(0.0, 0.05) if damped else 0.0))
    if triples:
        a, b, c, offset, k, kd = (np.array(col) for col in zip(*triples, strict=True))
        a, b, c = a.astype(int), b.astype(int), c.astype(int)
        block = AngularSpring(a, b, c, k=k, kd=kd)
        s.add(block)
        block.rest = block.rest + offset
    if gravity is None:
        gravity = draw.integer(0, 1) == 1
    if gravity:
        s.add(Gravity((0.0, -9.81)))
    if damped and draw.integer(0, 1) == 1:
        s.add(Drag(draw.real(0.0, 0.2)))

    v = np.array([[draw.real(-1.0, 1.0) for _ in range(2)] for _ in range(n)])
    s.v = np.where(fixed[:, None], 0.0, v)
    s.project()
    return s


def random_system(seed: int, *, min_particles: int = 2, max_particles: int = 12,
                  gravity: bool | None = None, damped: bool = False, solver: str | None = None
                  ) -> ParticleSystem:
    """The random system drawn from ``numpy.random.default_rng(seed)``; keywords as
    :func:`build_system`.

    >>> s = random_system(7, min_particles=5)
    >>> s.n >= 5
    True
    """
    return build_system(_NumpyDrawer(int(seed)), min_particles=min_particles,
                        max_particles=max_particles, gravity=gravity, damped=damped,
                        solver=solver)


def systems(*, min_particles: int = 2, max_particles: int = 12, gravity: bool | None = None,
            damped: bool = False, solver: str | None = None) -> SearchStrategy[ParticleSystem]:
    """Hypothesis strategy of random constrained systems; keywords as :func:`build_system`.

    Needs hypothesis (the ``test`` extra).
    """
    from hypothesis import strategies as st

    @st.composite
    def _systems(draw: Any) -> ParticleSystem:
        return build_system(_HypothesisDrawer(draw), min_particles=min_particles,
                            max_particles=max_particles, gravity=gravity, damped=damped,
                            solver=solver)

    return _systems()
