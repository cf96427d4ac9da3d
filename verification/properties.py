"""Reusable checks of a particle system's numerics; each returns the figure it measures.

The checks compare the simulator against something it does not compute itself: derivatives of
``C`` and of the potential energy by finite differences, momentum sums, energy bookkeeping, a
rigidly moved copy of the system, a second run. Tests assert on the returned figures; users can
run them on their own systems.

>>> from constrained_particles import scenes
>>> s = scenes.wire_mixture()
>>> constraint_acceleration_residual(s) < 1e-8
True
>>> constraint_power(s) < 1e-8
True
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence

import numpy as np

from constrained_particles import (
    AngularSpring,
    CircularWire,
    ConstantForce,
    DampedSpring,
    Drag,
    FixedPoint,
    Gravity,
    LineWire,
    MouseSpring,
    ParticleSystem,
    Rod,
    TableFriction,
    Wall,
)

#: Force blocks whose forces depend only on relative positions and velocities.
INTERNAL_FORCES = (DampedSpring, AngularSpring)

_TINY = 1e-300


def _constraint_values(system: ParticleSystem, x: np.ndarray) -> np.ndarray:
    """``C(x)`` over every constraint row, straight from the blocks' definitions."""
    zero = np.zeros_like(x)
    parts = [c.evaluate(x, zero)[0] for c in system.constraints]
    return np.concatenate(parts) if parts else np.zeros(0)


def _directional(system: ParticleSystem, x: np.ndarray, u: np.ndarray, eps: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivatives of ``C`` along ``u`` (central differences).

    Exact up to rounding for constraints at most quadratic in x (every built-in kind).
    """
    cp = _constraint_values(system, x + eps * u)
    cm = _constraint_values(system, x - eps * u)
    c0 = _constraint_values(system, x)
    return (cp - cm) / (2 * eps), (cp - 2 * c0 + cm) / eps**2


def constraint_acceleration_residual(system: ParticleSystem, eps: float = 1e-2) -> float:
    """Relative residual of the multiplier equation (docs/physics.md, "The constraint force")
    after the multiplier solve, at the current state.

    Measures ``Cddot + ks C + kd Cdot`` with ``Cddot = J qddot + Jdot qdot``, where ``qddot`` is
    :meth:`ParticleSystem.acceleration` and ``J qddot``, ``Jdot qdot = qdot^T H qdot`` and
    ``Cdot`` are finite differences of ``C`` (step ``eps`` in metres), independent of the
    solver's ``J`` and ``Jdot``. Each row is divided by its gradient norm ``|J_r|`` (making it an
    acceleration, m/s^2) and the largest is divided by the accelerations in play,
    ``max|W Q| + max|qddot| + max|v|^2 / L + ks max|C/J_r| + kd max|Cdot/J_r|`` (``L`` the
    system's extent). Expect the solver's relative tolerance; 0 without constraints or motion.
    """
    if not system.constraints:
        return 0.0
    x, v = system.x, system.v
    a = system.acceleration(system.t, x, v)
    applied = system.inv_mass[:, None] * system.applied_forces(x, v)
    C = _constraint_values(system, x)
    na, nv = np.linalg.norm(a), np.linalg.norm(v)
    Ja = _directional(system, x, a / na, eps)[0] * na if na > 0 else np.zeros_like(C)
    if nv > 0:
        Cdot, vHv = _directional(system, x, v / nv, eps)
        Cdot, vHv = Cdot * nv, vHv * nv**2
    else:
        Cdot = vHv = np.zeros_like(C)
    solver = system.constraint_solver
    solver.refill(x, v)
    grad = np.sqrt(np.asarray(solver.J.multiply(solver.J).sum(axis=1)).ravel())
    residual = np.abs(Ja + vHv + system.ks * C + system.kd * Cdot) / grad
    extent = max(float(np.ptp(x, axis=0).max()), 1e-3) if len(x) > 1 else 1.0
    speed = np.max(np.abs(v), initial=0.0)
    scale = (np.max(np.abs(applied)) + np.max(np.abs(a)) + speed**2 / extent
             + system.ks * np.max(np.abs(C) / grad) + system.kd * np.max(np.abs(Cdot) / grad))
    return float(np.max(residual) / scale) if scale > 0 else 0.0


def constraint_distance(system: ParticleSystem) -> float:
    """The largest constraint violation as a distance: ``max_r |C_r| / |J_r|`` in metres at the
    current state (0 without constraints); for wires and rods, to first order, how far the
    particles are off their constraint."""
    if not system.constraints:
        return 0.0
    solver = system.constraint_solver
    solver.refill(system.x, system.v)
    rows = np.repeat(np.arange(solver.m), np.diff(solver.J.indptr))
    grad = np.sqrt(np.bincount(rows, solver.J.data**2, minlength=solver.m))
    return float(np.max(np.abs(solver.C) / grad))


def constraint_power(system: ParticleSystem, min_speed: float = 1e-9) -> float:
    """Relative power of the constraint force at the current state: ``|lam^T J v|`` divided by
    ``|J^T lam| |v|``. Zero (to the solver's tolerance) when ``Cdot = J v = 0``: ideal
    constraints do no work. Returns 0 without constraints or without motion: speeds below
    ``min_speed`` (m/s, norm over all particles) are rounding residue, e.g. 1e-16 m/s left by
    a projection, to which the feedback force answers along the same direction."""
    if np.linalg.norm(system.v) < min_speed:
        return 0.0
    fc = system.constraint_force(system.x, system.v)
    scale = np.linalg.norm(fc) * np.linalg.norm(system.v)
    return float(abs(np.sum(fc * system.v)) / scale) if scale > 0 else 0.0


def gradient_error(system: ParticleSystem, eps: float = 1e-4, atol: float = 1e-7) -> float:
    """How far the conservative force blocks are from ``-grad E`` (finite differences).

    For every block with a potential (``conservative``), its force at ``v = 0`` (damping terms
    vanish) is compared with minus the gradient of its :meth:`potential`, by central differences
    of steps ``eps`` and ``eps/2`` (m) combined by Richardson extrapolation (error O(eps^4)),
    over every coordinate of every particle. Returns the worst block's
    ``max |F + grad E| / max(|F|, |grad E|, atol)`` (0 without conservative blocks); ``atol``
    (N) keeps a block at rest (zero force, rounding-level gradient) from counting as wrong.
    """
    x0, zero = system.x, np.zeros_like(system.x)
    worst = 0.0
    for block in system.forces:
        if not block.conservative:
            continue
        F = np.zeros_like(x0)
        block.accumulate(x0, zero, system.mass, F)

        def central(idx: tuple[int, int], e: float, block=block) -> float:
            xp, xm = x0.copy(), x0.copy()
            xp[idx] += e
            xm[idx] -= e
            return (block.potential(xp, system.mass) - block.potential(xm, system.mass)) / (2 * e)

        grad = np.zeros_like(x0)
        for idx in np.ndindex(*x0.shape):
            grad[idx] = (4 * central(idx, eps / 2) - central(idx, eps)) / 3
        scale = max(np.max(np.abs(F)), np.max(np.abs(grad)), atol)
        worst = max(worst, float(np.max(np.abs(F + grad)) / scale))
    return worst


def _momentum_of(F: np.ndarray, x: np.ndarray, atol: float) -> tuple[float, float]:
    """Relative net force and net torque of a force field F (N) on points x (m)."""
    net = np.linalg.norm(F.sum(axis=0)) / max(np.sum(np.linalg.norm(F, axis=1)), atol)
    torque = x[:, 0] * F[:, 1] - x[:, 1] * F[:, 0]
    arm = np.linalg.norm(x, axis=1) * np.linalg.norm(F, axis=1)
    return float(net), float(abs(torque.sum()) / max(arm.sum(), atol))


def internal_momentum_error(system: ParticleSystem, atol: float = 1e-9) -> float:
    """Net force and torque of the internal forces, relative to their magnitudes.

    Internal forces are the :data:`INTERNAL_FORCES` blocks (with damping, at the current
    velocities) and the constraint forces ``J_rod^T lam_rod`` of rods: each must sum to zero
    force and zero torque about the origin, i.e. conserve linear and angular momentum. Forces on
    fixed particles count (they are reactions). Returns the largest relative figure; sums of
    magnitudes below ``atol`` (N, or N m for torques) count as ``atol``.
    """
    x, v = system.x, system.v
    fields = []
    for block in system.forces:
        if isinstance(block, INTERNAL_FORCES):
            F = np.zeros_like(x)
            block.accumulate(x, v, system.mass, F)
            fields.append(F)
    if any(isinstance(c, Rod) for c in system.constraints):
        system.constraint_force(x, v)
        solver = system.constraint_solver
        for c, rows in zip(solver.constraints, solver.block_rows, strict=True):
            if isinstance(c, Rod):
                fields.append((solver.J[rows].T @ solver.lam[rows]).reshape(x.shape))
    return max((max(_momentum_of(F, x, atol)) for F in fields), default=0.0)


def stopping_distance(v0: Sequence[float], mu: float, g: float = 9.81, v_s: float = 0.05,
                      mass: float = 1.0, method: str = "rk4", h: float = 1e-3,
                      duration: float | None = None) -> float:
    """How far (m) a particle of ``mass`` (kg) launched at velocity ``v0`` (m/s) slides on a
    :class:`~constrained_particles.TableFriction` table (``mu``, ``g`` in m/s^2, ``v_s`` in
    m/s) with nothing else acting, stepped by ``method`` at ``h`` (s) for ``duration`` (s;
    default the Coulomb stopping time ``|v0| / (mu g)`` plus 30 time constants ``v_s / (mu g)``
    of the damper below ``v_s``, which leaves under 1e-13 of its distance).

    Coulomb friction's exact answer is ``|v0|^2 / (2 mu g)``; the regularised force's is
    ``(|v0|^2 + v_s^2) / (2 mu g)`` for ``|v0| >= v_s`` (docs/physics.md "Table friction").

    >>> d = stopping_distance((2.0, 0.0), mu=0.5, g=10.0, v_s=0.01)
    >>> abs(d - 2.0**2 / (2 * 0.5 * 10.0)) <= 0.01**2 / (2 * 0.5 * 10.0) + 1e-6
    True
    """
    speed = float(np.hypot(*v0))
    if duration is None:
        duration = speed / (mu * g) + 30 * v_s / (mu * g)
    s = ParticleSystem()
    s.add_particle((0.0, 0.0), v0, mass=mass)
    s.add(TableFriction(mu=mu, g=g, v_s=v_s))
    s.step(h, method, steps=max(1, int(np.ceil(duration / h))))
    return float(np.hypot(*s.x[0]))


def slack_spring_error(system: ParticleSystem) -> float:
    """The largest force (N) or energy (J) of a slack tension-only spring of ``system`` (one
    with ``|l| <= rest``, in a ``DampedSpring(tension_only=True)`` block), each spring
    evaluated on its own at the current state, with its damping. Zero when the blocks are
    right: a string carries nothing below its rest length."""
    worst = 0.0
    for block in system.forces:
        if not (isinstance(block, DampedSpring) and block.tension_only):
            continue
        length = np.linalg.norm(system.x[block.i] - system.x[block.j], axis=1)
        for e in np.flatnonzero(length <= block.rest):
            one = DampedSpring(block.i[e], block.j[e], rest=block.rest[e], ks=block.ks[e],
                               kd=block.kd[e], tension_only=True)
            force = one.element_forces(system.x, system.v, system.mass)[1]
            worst = max(worst, float(np.max(np.abs(force))),
                        abs(one.potential(system.x, system.mass)))
    return worst


def cloth_coverage(size: int = 9, side: float = 0.3, pixels: int = 256,
                   angle: float = 0.3, center: Sequence[float] = (0.0123, -0.0311)
                   ) -> dict[str, float]:
    """The raster coverage (:func:`constrained_particles.raster.coverage`) of a square cloth
    of ``size`` x ``size`` particles and side ``side`` (m), flat at ``angle`` (rad) about
    ``center`` (m), and of the same cloth folded in half along its middle column, on a
    ``pixels`` x ``pixels`` raster of a box twice the cloth's side; each as a fraction of the
    flat area ``side^2``, with the raster's stated bound on the folded one's error.

    The flat cloth's cells do not overlap, so its coverage is exact to rounding (1); the folded
    cloth covers half the area, measured at most ``bound`` above 1/2
    (:func:`~constrained_particles.raster.coverage_bound` of the folded outline: three sides of
    the half square, 8 ``size`` edge pieces at most).

    >>> r = cloth_coverage()
    >>> abs(r["flat"] - 1.0) < 1e-9, 0.5 <= r["folded"] <= 0.5 + r["bound"]
    (True, True)
    """
    from constrained_particles import raster

    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 3 \
            or size % 2 == 0:
        raise ValueError(f"size must be an odd whole number of particles >= 3, got {size!r}")
    u = np.linspace(-side / 2, side / 2, size)
    gx, gy = np.meshgrid(u, u)  # (row by row: y outer)
    c, s = np.cos(angle), np.sin(angle)
    flat = np.stack([gx.ravel(), gy.ravel()], axis=1) @ np.array([[c, s], [-s, c]])
    flat += np.asarray(center, dtype=float)
    idx = np.arange(size * size).reshape(size, size)
    cells = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]],
                     axis=2).reshape(-1, 4)
    # the fold: the columns right of the middle one reflected across its line
    mid = idx[:, size // 2]
    a, b = flat[mid[0]], flat[mid[-1]]
    d = (b - a) / np.linalg.norm(b - a)
    normal = np.array([-d[1], d[0]])
    off = (flat - a) @ normal
    folded = flat.copy()
    right = (gx.ravel() > 0)
    folded[right] -= 2.0 * off[right, None] * normal
    half = np.asarray(center, dtype=float)
    view = raster.View((half[0] - side, half[1] - side, half[0] + side, half[1] + side),
                       height=pixels, width=pixels)
    area = side * side
    got = raster.coverage(np.stack([flat, folded]), cells, view) / area
    bound = raster.coverage_bound(3 * side, 8 * size, view) / area
    return {"flat": float(got[0]), "folded": float(got[1]), "bound": float(bound)}


def run(system: ParticleSystem, method: str, h: float, steps: int, project: bool | None = None
        ) -> ParticleSystem:
    """Advance a copy of ``system`` by ``steps`` steps of ``h`` seconds; returns the copy."""
    out = system.copy()
    for _ in range(int(steps)):
        out.step(h, method=method, project=project)
    return out


def _energy_errors(system: ParticleSystem, method: str, h: float, duration: float
                   ) -> tuple[float, float]:
    """``max_t |E(t) - E(0)|`` (J) and the largest kinetic energy (J) over a run."""
    s = system.copy()
    e0 = s.energy()
    worst, kinetic = 0.0, s.kinetic_energy()
    for _ in range(int(round(duration / h))):
        s.step(h, method=method)
        worst = max(worst, abs(s.energy() - e0))
        kinetic = max(kinetic, s.kinetic_energy())
    return worst, kinetic


def energy_drift(system: ParticleSystem, method: str = "rk4", h: float = 1e-3,
                 duration: float = 1.0) -> float:
    """Largest energy change over ``duration`` seconds of steps ``h`` (s), relative.

    ``max_t |E(t) - E(0)|`` divided by the largest kinetic energy met on the way (the energy in
    play). For an undamped conservative system this is the integrator's energy error.
    """
    worst, kinetic = _energy_errors(system, method, h, duration)
    return worst / max(kinetic, _TINY)


def fit_slope(hs: Sequence[float], errors: Sequence[float]) -> float:
    """Least-squares slope of ``log(error)`` against ``log(h)``: the observed order.

    >>> round(fit_slope([0.1, 0.05, 0.025], [3e-4, 3.75e-5, 4.6875e-6]), 6)
    3.0
    """
    h, e = np.asarray(hs, float), np.asarray(errors, float)
    if len(h) < 2 or h.shape != e.shape or not (np.all(e > 0) and np.all(np.isfinite(e))):
        raise ValueError(f"errors must be positive and finite, one per h, got {errors}")
    if not np.all(h > 0):
        raise ValueError(f"hs must be positive, got {hs}")
    return float(np.polyfit(np.log(h), np.log(e), 1)[0])


def energy_errors(system: ParticleSystem, method: str = "rk4",
                  hs: Sequence[float] = (0.04, 0.02, 0.01), duration: float = 1.0) -> list[float]:
    """``max_t |E(t) - E(0)|`` (J) over ``duration`` seconds for each step ``h`` in ``hs`` (s)."""
    return [_energy_errors(system, method, h, duration)[0] for h in hs]


def energy_error_order(system: ParticleSystem, method: str = "rk4",
                       hs: Sequence[float] = (0.04, 0.02, 0.01), duration: float = 1.0) -> float:
    """Observed order of the energy error ``max_t |E(t) - E(0)|`` in the step ``h`` (s).

    About 4 for rk4 on a smooth undamped conservative system (its global error order; energy
    often converges faster still). Raises ValueError if an error is exactly zero.
    """
    return fit_slope(hs, energy_errors(system, method, hs, duration))


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def rigidly_moved(system: ParticleSystem, angle: float, shift: Sequence[float]
                  ) -> ParticleSystem:
    """A copy of ``system`` rotated by ``angle`` (rad) about the origin, then shifted by
    ``shift`` (m): state, wires, pins, walls, applied forces and gravity all move with it.

    Raises ValueError for a block type it does not know how to move.
    """
    R, d = _rotation(angle), np.asarray(shift, float)
    out = system.copy()
    out.x = system.x @ R.T + d
    out.v = system.v @ R.T
    constraints = []
    for c in out.constraints:
        if isinstance(c, LineWire):  # HorizontalWire too: rotated, it is a general line wire
            direction = np.stack([c.normal[:, 1], -c.normal[:, 0]], axis=1) @ R.T
            c = LineWire(c.particles, direction, c.point @ R.T + d)
        elif isinstance(c, CircularWire):
            c.center = c.center @ R.T + d
        elif isinstance(c, FixedPoint):
            c.point = c.point @ R.T + d
        elif not isinstance(c, Rod):
            raise ValueError(f"system: cannot move a {type(c).__name__} rigidly")
        constraints.append(c)
    out.constraints = constraints
    lam = system.constraint_solver.lam.copy()  # the same CG warm start as the original
    for f in out.forces:
        if isinstance(f, Gravity):
            f.g = R @ f.g
        elif isinstance(f, ConstantForce):
            f.force = f.force @ R.T
        elif isinstance(f, Wall):
            f.normal = R @ f.normal
            f.offset = f.offset + float(f.normal @ d)
        elif isinstance(f, MouseSpring):
            f.anchor = f.anchor @ R.T + d
        elif not isinstance(f, (DampedSpring, AngularSpring, Drag)):
            raise ValueError(f"system: cannot move a {type(f).__name__} rigidly")
    out.constraint_solver.lam = lam
    return out


def invariance_error(system: ParticleSystem, method: str = "rk4", h: float = 1e-3,
                     steps: int = 20, angle: float = 0.7, shift: Sequence[float] = (3.0, -2.0)
                     ) -> float:
    """Stepping commutes with a rigid motion: ``max |R x_A + d - x_B|``, in metres, where A is
    stepped then moved and B moved then stepped (``steps`` steps of ``h`` s). Rounding only."""
    R, d = _rotation(angle), np.asarray(shift, float)
    a = run(system, method, h, steps)
    b = run(rigidly_moved(system, angle, shift), method, h, steps)
    return float(np.max(np.abs(a.x @ R.T + d - b.x), initial=0.0))


def determinism_error(system: ParticleSystem, method: str = "rk4", h: float = 1e-3,
                      steps: int = 20) -> float:
    """Largest difference (m, m/s) between two runs of the same input: a copy, and a copy that
    went through pickle. Bit-for-bit determinism means exactly 0.0."""
    a = run(system, method, h, steps)
    b = run(pickle.loads(pickle.dumps(system)), method, h, steps)
    return float(max(np.max(np.abs(a.x - b.x), initial=0.0),
                     np.max(np.abs(a.v - b.v), initial=0.0)))
