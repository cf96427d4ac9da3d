"""Force blocks: gravity, applied forces, springs, drag, walls and the mouse spring.

Every class is one vectorized block. ``accumulate`` adds the block's forces (newtons) into an
(n, 2) array, ``potential`` returns its potential energy (joules; 0 for dissipative or
external forces) and ``element_forces`` gives per-element force vectors for drawing.
Formulas follow docs/physics.md ("Forces").
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from . import kernels
from .terms import (
    ArgumentTypeError,
    Shape,
    Term,
    as_index,
    as_index_array,
    as_param_array,
    as_unit_vectors,
    frozen,
    scatter_add,
)


def _perp(p: np.ndarray) -> np.ndarray:
    """Rotate (k, 2) vectors by +90 degrees: perp(p) = (-p_y, p_x)."""
    return np.stack([-p[:, 1], p[:, 0]], axis=1)


def _selected(idx: np.ndarray | None, n: int) -> np.ndarray:
    return np.arange(n) if idx is None else idx


_NO_ENTRIES = np.zeros(0, dtype=np.int64)


def _block_pattern(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns in q = (x_0, y_0, x_1, ...) of the 2x2 blocks (particle p, particle q).

    ``p``, ``q`` are (k, blocks) particle arrays; entries are ordered by element, then block,
    then row-major inside the block, matching ``values.ravel()`` of a (k, blocks, 2, 2) array.
    """
    rows = 2 * p[..., None] + np.array([0, 0, 1, 1])
    cols = 2 * q[..., None] + np.array([0, 1, 0, 1])
    return rows.ravel(), cols.ravel()


def _diagonal_pattern(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the diagonal entries (x and y) of particles ``p``."""
    rows = (2 * p[:, None] + np.array([0, 1])).ravel()
    return rows, rows.copy()


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-element outer products a_k b_k^T of (k, 2) arrays: (k, 2, 2)."""
    return a[:, :, None] * b[:, None, :]


def _dperp_over_square(p: np.ndarray) -> np.ndarray:
    """d/dp [perp(p) / |p|^2] for (k, 2) vectors p: (k, 2, 2) in 1/m^2 (0 where p = 0)."""
    pp = np.einsum("kd,kd->k", p, p)
    inv = 1.0 / np.where(pp > 0, pp, np.inf)
    R = np.array([[0.0, -1.0], [1.0, 0.0]])
    return inv[:, None, None] * R - 2.0 * (inv**2)[:, None, None] * _outer(_perp(p), p)


class Force(Term):
    """Base class of force blocks."""

    conservative: ClassVar[bool] = False
    #: True for forces that do not depend on positions or velocities (zero Jacobians).
    state_independent: ClassVar[bool] = False

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

    def jacobian_pattern(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the structural nonzeros of this block's force Jacobians.

        Indices run over the 2n stacked coordinates ``q = (x_0, y_0, x_1, y_1, ...)`` of a
        system of ``n`` particles; repeated (row, column) pairs are summed. The pattern depends
        only on the block's particle indices, so an implicit integrator assembles its sparse
        matrix once per topology and :meth:`jacobians` only refills values.
        """
        if self.state_independent:
            return _NO_ENTRIES, _NO_ENTRIES
        raise NotImplementedError(f"{type(self).__name__} has no force Jacobians "
                                  "(jacobian_pattern and jacobians), which implicit_euler needs")

    def jacobians(self, x: np.ndarray, v: np.ndarray, mass: np.ndarray, definite: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Values of ``df/dx`` (N/m) and ``df/dv`` (N s/m) at (x, v), in the order of
        :meth:`jacobian_pattern`. Entry (r, c) is the derivative of force coordinate r with
        respect to position (velocity) coordinate c.

        ``definite=False`` gives the exact derivatives. ``definite=True`` gives symmetric
        negative semi-definite approximations (the same where the exact ones already are), for
        implicit integrators: a compressed spring's negative transverse stiffness or an angular
        spring's curvature term predicts a buckling the next step then overshoots.
        """
        if self.state_independent:
            return np.zeros(0), np.zeros(0)
        raise NotImplementedError(f"{type(self).__name__} has no force Jacobians "
                                  "(jacobian_pattern and jacobians), which implicit_euler needs")


class Gravity(Force):
    """Uniform gravitational field ``g`` (m/s^2) on ``particles`` (default: every particle).

    >>> from constrained_particles import ParticleSystem, Gravity
    >>> s = ParticleSystem(); p = s.add_particle((0.0, 0.0), mass=2.0)
    >>> s.add(Gravity((0.0, -9.81))); s.step(1e-3, method="euler"); float(s.v[p, 1])
    -0.00981
    """

    index_fields = ("particles",)
    conservative = True
    state_independent = True

    def __init__(self, g: ArrayLike = (0.0, -9.81), particles: ArrayLike | None = None) -> None:
        self.g = as_param_array("g", g, 1, width=2)[0]
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def accumulate(self, x, v, mass, F):
        if self.particles is None:
            F[:, 0] += mass * self.g[0]
            F[:, 1] += mass * self.g[1]
        else:
            scatter_add(F, self.particles, mass[self.particles, None] * self.g)

    def potential(self, x, mass):
        idx = _selected(self.particles, len(x))
        return float(-np.sum(mass[idx] * (x[idx] @ self.g)))


class ConstantForce(Force):
    """A constant applied force (N) on chosen particles, e.g. a push on a cloth's top row.

    ``force`` broadcasts to one (2,) vector per particle and may be rewritten between steps
    (the environments write their actions into it). Its work is external input, so it has
    no potential energy.
    """

    index_fields = ("particles",)
    element_fields = ("force",)
    state_independent = True

    def __init__(self, particles: ArrayLike, force: ArrayLike) -> None:
        self.particles = as_index_array("particles", particles)
        self.force = as_param_array("force", force, len(self.particles), width=2)

    def accumulate(self, x, v, mass, F):
        scatter_add(F, self.particles, self.force)

    def element_forces(self, x, v, mass):
        return x[self.particles], self.force.copy()

    def shapes(self, x, v):
        return [Shape("arrow", "applied", x[self.particles], self.force.copy(),
                      np.linalg.norm(self.force, axis=1))]


def _spring_arguments(x: object, v: object, F: object, i: object, j: object, ks: object,
                      kd: object, rest: object) -> bool:
    """Whether the compiled spring kernel may run on these arrays: it indexes without bounds
    checks, so every array must have the shape and dtype it assumes and every index must be
    inside ``x``."""
    if not (isinstance(i, np.ndarray) and isinstance(j, np.ndarray)
            and isinstance(x, np.ndarray)):
        return False
    k, n = len(i), len(x)
    arrays_ok = all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (k,)
                    for a in (ks, kd, rest))
    states_ok = all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.ndim == 2
                    and a.shape == (n, 2) for a in (x, v, F))
    if not (arrays_ok and states_ok and i.shape == j.shape == (k,)
            and i.dtype == j.dtype == np.int64):
        return False
    return k == 0 or (min(i.min(), j.min()) >= 0 and max(i.max(), j.max()) < n)


class DampedSpring(Force):
    """Damped springs between particle pairs ``i`` and ``j``: one block for many springs.

    With ``l = x_i - x_j`` and ``ldot = v_i - v_j`` (docs/physics.md, "Forces"):
    ``f_i = -[ks (|l| - rest) + kd (ldot . l)/|l|] l/|l|``, ``f_j = -f_i``, energy
    ``ks/2 (|l| - rest)^2``. ``rest`` (m) defaults to the current length, ``ks`` is in N/m and
    ``kd`` in N s/m. A spring of zero current length exerts no force (its direction is undefined).

    ``tension_only=True`` makes every spring of the block a string that pulls but never pushes
    (cloth buckles instead of resisting compression, docs/physics.md "Tension-only spring"):
    ``f_i = -max(0, ks (|l| - rest) + kd (ldot . l)/|l|) l/|l|`` while ``|l| > rest``, else 0;
    energy ``ks/2 max(|l| - rest, 0)^2``.

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
    #: True: the springs pull but never push (see the class docstring)
    tension_only: bool = False

    def __init__(self, i: ArrayLike, j: ArrayLike, rest: ArrayLike | None = None,
                 ks: ArrayLike = 1.0, kd: ArrayLike = 0.0,
                 tension_only: bool = False) -> None:
        self.tension_only = tension_only
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

    def __setattr__(self, name: str, value: object) -> None:
        if name == "tension_only" and not isinstance(value, (bool, np.bool_)):
            raise ArgumentTypeError(f"tension_only must be True or False, got {value!r}")
        super().__setattr__(name, bool(value) if name == "tension_only" else value)

    def bind(self, system):
        super().bind(system)
        if self.rest is None:
            self.rest = np.linalg.norm(system.x[self.i] - system.x[self.j], axis=1)

    def _geometry(self, x, v):
        # np.take beats x[self.i], and whole columns beat (k, 2) broadcasts, whose inner loops
        # are 2 long: several times faster for batched systems, same floating-point results
        l = np.take(x, self.i, axis=0) - np.take(x, self.j, axis=0)
        lx, ly = l[:, 0], l[:, 1]
        length = np.sqrt(lx * lx + ly * ly)
        positive = length > 0
        safe = np.where(positive, length, 1.0)
        u = np.empty_like(l)
        u[:, 0] = lx / safe * positive
        u[:, 1] = ly / safe * positive
        return l, length, u, np.take(v, self.i, axis=0) - np.take(v, self.j, axis=0)

    def element_forces(self, x, v, mass):
        """Force on particle ``i`` of each spring (the force on ``j`` is its negative)."""
        _, length, u, ldot = self._geometry(x, v)
        mag = self.ks * (length - self.rest) + self.kd * (ldot[:, 0] * u[:, 0]
                                                          + ldot[:, 1] * u[:, 1])
        if self.tension_only:  # a string: no force while slack, and it never pushes
            mag = np.where((length > self.rest) & (mag > 0.0), mag, 0.0)
        f = np.empty_like(u)
        f[:, 0] = -mag * u[:, 0]
        f[:, 1] = -mag * u[:, 1]
        return np.take(x, self.i, axis=0), f

    def _kernel_arguments_valid(self, x, v, F) -> bool:
        """Whether the compiled kernel may run on the block's current arrays."""
        return _spring_arguments(x, v, F, self.i, self.j, self.ks, self.kd, self.rest)

    def accumulate(self, x, v, mass, F):
        args = (self.i, self.j, self.ks, self.kd, self.rest)  # each attribute read once
        if (kernels.spring_forces is not None and not self.tension_only
                and _spring_arguments(x, v, F, *args)):
            # the compiled element (see kernels)
            i, j, ks, kd, rest = args
            kernels.spring_forces(x, v, i, j, ks, kd, rest, F)
            return
        # the numpy reference: the formula of element_forces, scattered onto both ends
        _, f = self.element_forces(x, v, mass)
        n = len(x)
        for axis in (0, 1):
            F[:, axis] += (np.bincount(self.i, f[:, axis], minlength=n)
                           - np.bincount(self.j, f[:, axis], minlength=n))

    def potential(self, x, mass):
        stretch = np.linalg.norm(x[self.i] - x[self.j], axis=1) - self.rest
        if self.tension_only:
            stretch = np.maximum(stretch, 0.0)
        return float(0.5 * np.sum(self.ks * stretch**2))

    def jacobian_pattern(self, n):
        """Blocks (i, i), (i, j), (j, i), (j, j) of every spring."""
        i, j = self.i[:, None], self.j[:, None]
        return _block_pattern(np.hstack([i, i, j, j]), np.hstack([i, j, i, j]))

    def jacobians(self, x, v, mass, definite=False):
        """Jacobians of the damped spring force.

        Exact: with ``P = I - u u^T`` and ``s = ks (|l| - rest) + kd (ldot . u)``,
        ``df_i/dl = -[ks u u^T + (s/|l|) P + (kd/|l|) u (P ldot)^T]``, whose ``s/|l|`` part holds
        the transverse term ``ks (1 - rest/|l|) P`` (negative when compressed), and
        ``df_i/dldot = -kd u u^T``; ``f_j = -f_i``. ``definite=True`` keeps
        ``-[ks u u^T + max(ks (1 - rest/|l|), 0) P]``: no compressive transverse stiffness and
        no damping terms in df/dx (Choi & Ko 2002).

        ``tension_only``: both are zero for a spring that exerts no force (slack, ``|l| <=
        rest``, or clamped, ``ks (|l| - rest) + kd (ldot . u) <= 0``), as its force is zero
        on a neighbourhood of the state; elsewhere they are those above.
        """
        _, length, u, ldot = self._geometry(x, v)
        inv = 1.0 / np.where(length > 0, length, np.inf)
        uu = _outer(u, u)
        P = np.eye(2) - uu
        if definite:
            s = np.maximum(self.ks * (length - self.rest), 0.0)
            Kl = -(self.ks[:, None, None] * uu + (s * inv)[:, None, None] * P)
        else:
            s = self.ks * (length - self.rest) + self.kd * np.einsum("kd,kd->k", ldot, u)
            Kl = -(self.ks[:, None, None] * uu + (s * inv)[:, None, None] * P
                   + (self.kd * inv)[:, None, None] * _outer(u, np.einsum("kij,kj->ki", P, ldot)))
        Dl = -self.kd[:, None, None] * uu
        if self.tension_only:
            pull = self.ks * (length - self.rest) + self.kd * np.einsum("kd,kd->k", ldot, u)
            on = ((length > self.rest) & (pull > 0.0)).astype(float)[:, None, None]
            Kl, Dl = Kl * on, Dl * on
        return (np.stack([Kl, -Kl, -Kl, Kl], axis=1).ravel(),
                np.stack([Dl, -Dl, -Dl, Dl], axis=1).ravel())

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

    def __init__(self, a: ArrayLike, b: ArrayLike, c: ArrayLike, rest: ArrayLike | None = None,
                 k: ArrayLike = 1.0, kd: ArrayLike = 0.0) -> None:
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

    def jacobian_pattern(self, n):
        """All nine blocks (p, q), p and q in (a, b, c), p-major."""
        t = np.stack([self.a, self.b, self.c], axis=1)
        return _block_pattern(np.repeat(t, 3, axis=1), np.tile(t, (1, 3)))

    def jacobians(self, x, v, mass, definite=False):
        """Jacobians of ``f_p = -(k d + kd thetadot) g_p`` with ``g_p = dtheta/dx_p``.

        Exact: ``df_p/dx_q = -g_p (k g_q + kd dthetadot/dx_q)^T - (k d + kd thetadot) H_pq``
        with ``H`` the Hessian of theta (``dg_a/du = -d/du[perp(u)/|u|^2]``,
        ``dg_c/dw = d/dw[perp(w)/|w|^2]``, ``g_b = -(g_a + g_c)``), and
        ``df_p/dv_q = -kd g_p g_q^T``. ``definite=True`` keeps the Gauss-Newton part
        ``-k g_p g_q^T`` of df/dx.
        """
        g = np.stack(self.gradients(x), axis=1)
        gg = np.einsum("kpi,kqj->kpqij", g, g)
        D = -self.kd[:, None, None, None, None] * gg
        if definite:
            return (-self.k[:, None, None, None, None] * gg).ravel(), D.ravel()
        u = x[self.a] - x[self.b]
        w = x[self.c] - x[self.b]
        Gu = -_dperp_over_square(u)
        Gw = _dperp_over_square(w)
        zero = np.zeros_like(Gu)
        H = np.stack([np.stack([Gu, -Gu, zero], axis=1),
                      np.stack([-Gu, Gu + Gw, -Gw], axis=1),
                      np.stack([zero, -Gw, Gw], axis=1)], axis=1)
        vs = np.stack([v[self.a], v[self.b], v[self.c]], axis=1)
        thetadot = np.einsum("kpd,kpd->k", g, vs)
        # H is symmetric, so dthetadot/dx_q = sum_p H_pq v_p
        dthetadot = np.einsum("kpqij,kpi->kqj", H, vs)
        torque = self.k * self.deviation(x) + self.kd * thetadot
        K = -(np.einsum("kpi,kqj->kpqij", g, self.k[:, None, None] * g
                        + self.kd[:, None, None] * dthetadot)
              + torque[:, None, None, None, None] * H)
        return K.ravel(), D.ravel()

    def shapes(self, x, v):
        arms = np.stack([x[self.a], x[self.c]], axis=1)
        return [Shape("angle", "angular", x[self.b], arms, self.deviation(x))]


class Drag(Force):
    """Viscous drag ``f = -kd v`` (``kd`` in N s/m) on ``particles`` (default: every particle)."""

    index_fields = ("particles",)

    def __init__(self, kd: float = 0.1, particles: ArrayLike | None = None) -> None:
        self.kd = float(as_param_array("kd", kd, 1, nonnegative=True)[0])
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def accumulate(self, x, v, mass, F):
        if self.particles is None:
            F -= self.kd * v
        else:
            scatter_add(F, self.particles, -self.kd * v[self.particles])

    def jacobian_pattern(self, n):
        """The x and y diagonal entries of every affected particle."""
        return _diagonal_pattern(_selected(self.particles, n))

    def jacobians(self, x, v, mass, definite=False):
        """``df/dx = 0``, ``df/dv = -kd I``."""
        k = 2 * len(_selected(self.particles, len(x)))
        return np.zeros(k), np.full(k, -self.kd)


def _flags(name: str, value: ArrayLike, k: int) -> np.ndarray:
    """``value`` (a bool or bools) as a writable (k,) bool array, else TypeError or ValueError
    naming ``name``."""
    try:
        flags = np.asarray(value)
    except ValueError:  # ragged nesting
        flags = np.asarray(None)
    if flags.dtype != bool:
        raise ArgumentTypeError(f"{name} must be True/False or an array of bools, got {value!r}")
    try:
        return np.broadcast_to(flags, (k,)).copy()
    except ValueError:
        raise ValueError(f"{name} must broadcast to shape ({k},), got shape "
                         f"{flags.shape}") from None


class TableFriction(Force):
    """Coulomb friction of particles sliding on a table seen from above, regularised.

    Gravity ``g`` (m/s^2) presses each particle into the table, so particle p of mass m_p
    sliding at velocity v_p feels ``f = -mu m_p g v_p / max(|v_p|, v_s)``: the Coulomb force
    ``mu m_p g`` against the motion above the speed ``v_s`` (m/s), and below it a linear damper
    of rate ``mu g / v_s`` (1/s), so that the force is continuous and a resting particle feels
    none (docs/physics.md "Table friction"). A particle launched at ``v0 > v_s`` slides
    ``(v0^2 + v_s^2) / (2 mu g)`` before it stops: ``v0^2 / (2 mu g)`` (Coulomb's distance) plus
    ``v_s^2 / (2 mu g)``. Explicit steps need ``h < 2 v_s / (mu g)``.

    ``mu`` (dimensionless, >= 0) is one per element; ``particles`` default to every particle the
    system has when the block is added. ``lifted`` (bools, one per element, edited in place)
    switches an element's friction off: a particle carried above the table (grabbed) slides on
    nothing. The actuator that grabs a particle lifts it (:meth:`lift`, :meth:`lower`).

    >>> from constrained_particles import ParticleSystem, TableFriction
    >>> s = ParticleSystem(); p = s.add_particle((0.0, 0.0), (1.0, 0.0), mass=2.0)
    >>> s.add(TableFriction(mu=0.5, g=10.0, v_s=0.01))
    >>> s.applied_forces(s.x, s.v)[p].tolist()  # -mu m g along -v: 0.5 * 2 * 10 N
    [-10.0, 0.0]
    """

    index_fields = ("particles",)
    element_fields = ("mu", "lifted")

    def __init__(self, mu: ArrayLike = 0.5, particles: ArrayLike | None = None, g: float = 9.81,
                 v_s: float = 0.05, lifted: ArrayLike = False) -> None:
        self.g = float(as_param_array("g", g, 1, positive=True)[0])
        self.v_s = float(as_param_array("v_s", v_s, 1, positive=True)[0])
        if particles is None:  # every particle, from the system's count when added (bind)
            self.particles = None
            try:
                k = int(np.size(mu))
            except ValueError:  # ragged nesting
                k = 1
            self.mu = as_param_array("mu", mu, max(k, 1), nonnegative=True)
            self.lifted = _flags("lifted", lifted, int(np.size(np.asarray(lifted, dtype=object))))
        else:
            self.particles = as_index_array("particles", particles)
            k = len(self.particles)
            self.mu = as_param_array("mu", mu, k, nonnegative=True)
            self.lifted = _flags("lifted", lifted, k)

    def __setattr__(self, name: str, value: object) -> None:
        if name == "lifted" and not (isinstance(value, np.ndarray) and value.dtype == bool
                                     and value.ndim == 1):
            raise ArgumentTypeError(f"lifted must be a 1-D boolean array, got {value!r}")
        if name in ("g", "v_s"):
            value = float(as_param_array(name, value, 1, positive=True)[0])
        super().__setattr__(name, value)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def bind(self, system):
        if self.particles is None:
            n = system.n
            # everything validated before anything is assigned (add() changes nothing on an
            # error)
            particles = as_index_array("particles", np.arange(n))
            mu = as_param_array("mu", self.mu, n, nonnegative=True)
            lifted = _flags("lifted", self.lifted, n)
            self.__dict__.update(particles=particles, mu=mu, lifted=lifted)
            self.__dict__["version"] = self.version + 1
        k = len(self.particles)
        if len(self.mu) != k or len(self.lifted) != k:
            raise ValueError(f"mu and lifted must hold one entry per particle ({k}), got "
                             f"{len(self.mu)} and {len(self.lifted)}")
        super().bind(system)

    def _elements_of(self, particles: ArrayLike) -> np.ndarray:
        """The elements whose particle is one of ``particles`` (indices, validated)."""
        idx = as_index_array("particles", particles)
        if self.particles is None:
            raise ValueError("TableFriction: the block is not in a system yet (no particles)")
        return np.flatnonzero(np.isin(self.particles, idx))

    def lift(self, particles: ArrayLike) -> None:
        """Mark ``particles`` (indices) lifted: they feel no friction until :meth:`lower`."""
        self.lifted[self._elements_of(particles)] = True

    def lower(self, particles: ArrayLike | None = None) -> None:
        """Put ``particles`` (indices; default every particle) back on the table."""
        if particles is None:
            self.lifted[:] = False
        else:
            self.lifted[self._elements_of(particles)] = False

    def _speeds(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocities (k, 2) of the block's particles and their speeds (k,), m/s."""
        vv = np.take(v, self.particles, axis=0)
        return vv, np.sqrt(vv[:, 0] * vv[:, 0] + vv[:, 1] * vv[:, 1])

    def accumulate(self, x, v, mass, F):
        if self.particles is None:
            return
        vv, speed = self._speeds(v)
        # (the compiled element's arithmetic, in its order: (mu m) g / max(|v|, v_s))
        scale = self.mu * np.take(mass, self.particles) * self.g / np.maximum(speed, self.v_s)
        scale = np.where(self.lifted, 0.0, scale)
        f = np.empty_like(vv)
        f[:, 0] = -scale * vv[:, 0]
        f[:, 1] = -scale * vv[:, 1]
        scatter_add(F, self.particles, f)

    def jacobian_pattern(self, n):
        """One 2x2 block per element (its particle's velocity)."""
        idx = _selected(self.particles, 0)[:, None]
        return _block_pattern(idx, idx)

    def jacobians(self, x, v, mass, definite=False):
        """``df/dx = 0``; ``df/dv = -(mu m g / v_s) I`` below ``v_s`` and
        ``-(mu m g / |v|) (I - vhat vhat^T)`` above it (no resistance to a change of speed,
        only of direction); zero for lifted particles. Both are symmetric negative
        semi-definite, so ``definite`` changes nothing."""
        k = len(self)
        if k == 0:
            return np.zeros(0), np.zeros(0)
        vv, speed = self._speeds(v)
        coulomb = speed > self.v_s
        scale = self.mu * np.take(mass, self.particles) * self.g / np.maximum(speed, self.v_s)
        scale = np.where(self.lifted, 0.0, scale)
        inv = 1.0 / np.where(coulomb, speed, 1.0)
        vhat = vv * inv[:, None]
        D = np.eye(2) - np.where(coulomb, 1.0, 0.0)[:, None, None] * _outer(vhat, vhat)
        return np.zeros(4 * k), (-scale[:, None, None] * D).ravel()


class Wall(Force):
    """A wall filling ``normal . x > offset``; particles live where ``normal . x <= offset``.

    ``normal`` is a direction pointing into the wall (normalised here), ``offset`` in metres.
    A particle at penetration ``p = normal . x - offset > 0`` feels the one-sided spring-damper
    ``f = -max(kw p + cw (normal . v), 0) normal`` (``kw`` in N/m, ``cw`` in N s/m). The
    ``max(., 0)`` keeps the damper from pulling a separating particle back in (the design notes'
    formula without it makes walls sticky). Energy ``kw/2 p^2`` while inside.

    >>> from constrained_particles import Wall
    >>> right_wall = Wall((1.0, 0.0), 2.0)  # particles stay at x <= 2 m
    """

    index_fields = ("particles",)
    conservative = True

    def __init__(self, normal: ArrayLike = (1.0, 0.0), offset: float = 0.0, kw: float = 1e4,
                 cw: float = 1.0, particles: ArrayLike | None = None) -> None:
        self.normal = as_unit_vectors("normal", normal, 1)[0]
        self.offset = float(as_param_array("offset", offset, 1)[0])
        self.kw = float(as_param_array("kw", kw, 1, nonnegative=True)[0])
        self.cw = float(as_param_array("cw", cw, 1, nonnegative=True)[0])
        self.particles = None if particles is None else as_index_array("particles", particles)

    def __len__(self) -> int:
        return 0 if self.particles is None else len(self.particles)

    def penetration(self, x: np.ndarray) -> np.ndarray:
        """``normal . x - offset`` (m) for the affected particles; positive is inside the wall."""
        return (x if self.particles is None else x[self.particles]) @ self.normal - self.offset

    def accumulate(self, x, v, mass, F):
        idx = _selected(self.particles, len(x))
        p = (x if self.particles is None else x[idx]) @ self.normal - self.offset
        inside = p > 0
        if not np.any(inside):
            return
        hit = idx[inside]
        mag = np.maximum(self.kw * p[inside] + self.cw * (v[hit] @ self.normal), 0.0)
        scatter_add(F, hit, -mag[:, None] * self.normal)

    def potential(self, x, mass):
        p = self.penetration(x)
        return float(0.5 * self.kw * np.sum(np.where(p > 0, p, 0.0) ** 2))

    def jacobian_pattern(self, n):
        """One 2x2 block per affected particle (zero while the particle is outside)."""
        idx = _selected(self.particles, n)[:, None]
        return _block_pattern(idx, idx)

    def jacobians(self, x, v, mass, definite=False):
        """``df/dx = -kw n n^T`` and ``df/dv = -cw n n^T`` for particles inside the wall whose
        ``max(kw p + cw (n . v), 0)`` clamp is inactive; zero elsewhere (where the force is 0)."""
        idx = _selected(self.particles, len(x))
        p = x[idx] @ self.normal - self.offset
        on = ((p > 0) & (self.kw * p + self.cw * (v[idx] @ self.normal) > 0)).astype(float)
        nn = np.outer(self.normal, self.normal)
        return ((-self.kw * on)[:, None, None] * nn).ravel(), ((-self.cw * on)[:, None, None]
                                                                * nn).ravel()

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

    def __init__(self, particle: ArrayLike | None = None, anchor: ArrayLike | None = None,
                 ks: ArrayLike = 50.0,
                 kd: ArrayLike = 1.0) -> None:
        attached = particle is not None
        self.particle = as_index_array("particle", 0 if particle is None else particle)
        k = len(self.particle)
        self.anchor = as_param_array("anchor", (0.0, 0.0) if anchor is None else anchor, k,
                                     width=2)
        self.ks = as_param_array("ks", ks, k, nonnegative=True)
        self.kd = as_param_array("kd", kd, k, nonnegative=True)
        self.active = np.full(k, attached)

    def __setattr__(self, name: str, value: object) -> None:
        if name == "active" and value is not None:
            if not (isinstance(value, np.ndarray) and value.dtype == bool):
                raise ArgumentTypeError(f"active must be a boolean array, got {value!r}")
        super().__setattr__(name, value)

    def bind(self, system):
        # an unattached spring's particle index is a placeholder: check only attached ones
        unknown = self.active & (self.particle >= system.n)
        if np.any(unknown):
            raise ValueError(f"MouseSpring: particle holds unknown particle indices "
                             f"{self.particle[unknown].tolist()} (system has {system.n} particles)")
        self._bound_n = system.n

    def _check_indices(self, name, idx, n):
        unknown = idx >= n
        if len(idx) == len(self.active):
            unknown &= self.active
        if np.any(unknown):
            raise ValueError(f"MouseSpring: {name} holds unknown particle indices "
                             f"{idx[unknown].tolist()[:10]} (system has {n} particles)")

    def _elements(self, elements: ArrayLike) -> np.ndarray:
        idx = as_index_array("elements", elements)
        if np.any(idx >= len(self.particle)):
            raise ValueError(f"elements must be in [0, {len(self.particle)}), got {elements!r}")
        return idx

    def set_checked(self, elements: np.ndarray, particles: np.ndarray, anchors: np.ndarray,
                    active: np.ndarray) -> None:
        """:meth:`set` for arguments the caller has already validated (what the environments
        call every step): ``elements`` and ``particles`` int64 arrays of one length with the
        elements in range, ``anchors`` finite (k, 2) in m, ``active`` bools. Only the particle
        indices are checked again (against the system), so the block stays safe to evaluate."""
        bound = self.__dict__.get("_bound_n")
        if len(particles) and (particles.min() < 0
                               or (bound is not None and particles.max() >= bound)):
            raise ValueError(f"particles holds unknown particle indices {particles.tolist()[:10]}"
                             f" (system has {bound} particles)")
        new_particle = self.particle.copy()
        new_particle[elements] = particles
        self._assign_checked("particle", frozen(new_particle))
        self.anchor[elements] = anchors
        self.active[elements] = active

    def set(self, elements: ArrayLike, particles: ArrayLike | None = None,
            anchors: ArrayLike | None = None, active: ArrayLike | None = None) -> None:
        """Set springs ``elements`` at once: their ``particles`` (indices), ``anchors`` (m,
        (k, 2) or one point) and ``active`` flags (bools); ``None`` leaves a field as it is.

        Everything is validated first (ValueError or TypeError naming the argument); on an error
        nothing changes. A particle index is checked against the system's particle count.
        """
        idx = self._elements(elements)
        k = len(idx)
        new_particle = self.particle
        if particles is not None:
            p = as_index_array("particles", particles)
            if len(p) not in (1, k):
                raise ValueError(f"particles must hold 1 or {k} indices, got {len(p)}")
            new_particle = self.particle.copy()
            new_particle[idx] = p
        new_anchor = None if anchors is None else as_param_array("anchors", anchors, k, width=2)
        new_active = None if active is None else _flags("active", active, k)
        bound = self.__dict__.get("_bound_n")
        if bound is not None and particles is not None:
            on = self.active.copy()
            if new_active is not None:
                on[idx] = new_active
            unknown = on & (new_particle >= bound)
            if np.any(unknown):
                raise ValueError(f"particles holds unknown particle indices "
                                 f"{new_particle[unknown].tolist()[:10]} (system has {bound} "
                                 "particles)")
        if particles is not None:
            self._assign_checked("particle", frozen(new_particle))
        if new_anchor is not None:
            self.anchor[idx] = new_anchor
        if new_active is not None:
            self.active[idx] = new_active

    def grab(self, particle: int, anchor: ArrayLike, element: int = 0) -> None:
        """Attach spring ``element`` to ``particle`` with its anchor at ``anchor`` (m).

        Validated first (nothing changes on an error); the index is checked against the
        system's particle count.
        """
        self.set([as_index("element", element)], [as_index("particle", particle)],
                 as_param_array("anchor", anchor, 1, width=2), np.array([True]))

    def move(self, anchor: ArrayLike, element: int = 0) -> None:
        """Move the anchor of spring ``element`` to ``anchor`` (m)."""
        self.set([as_index("element", element)], anchors=as_param_array("anchor", anchor, 1,
                                                                         width=2))

    def release(self, element: int = 0) -> None:
        """Detach spring ``element``."""
        self.set([as_index("element", element)], active=np.array([False]))

    def element_forces(self, x, v, mass):
        p = self.particle
        f = -self.ks[:, None] * (x[p] - self.anchor) - self.kd[:, None] * v[p]
        f *= self.active[:, None]
        return x[p], f

    def accumulate(self, x, v, mass, F):
        unknown = self.active & (self.particle >= len(x))
        if np.any(unknown):
            raise ValueError(f"MouseSpring: particle holds unknown particle indices "
                             f"{self.particle[unknown].tolist()} (system has {len(x)} particles)")
        if np.any(self.active):
            scatter_add(F, self.particle, self.element_forces(x, v, mass)[1])

    def jacobian_pattern(self, n):
        """The x and y diagonal entries of each spring's particle (zero while released)."""
        return _diagonal_pattern(self.particle)

    def jacobians(self, x, v, mass, definite=False):
        """``df/dx = -ks I``, ``df/dv = -kd I`` for active springs, 0 for released ones."""
        return (np.repeat(-self.ks * self.active, 2), np.repeat(-self.kd * self.active, 2))

    def potential(self, x, mass):
        if not np.any(self.active):
            return 0.0
        d = x[self.particle] - self.anchor
        return float(0.5 * np.sum(self.active * self.ks * np.einsum("kd,kd->k", d, d)))

    def shapes(self, x, v):
        on = self.active
        return [Shape("segment", "mouse", self.anchor[on], x[self.particle[on]],
                      np.zeros(int(on.sum())))]
