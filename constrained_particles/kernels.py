"""Compiled force and constraint *elements* (Numba), and the block kernels built on them.

Each formula of docs/physics.md is written here once, as a small compiled
function of one element (one spring, one wall contact, one constraint row). Two callers share
them: the block kernels below, which the blocks' ``accumulate`` use, and the fused whole-step
kernel in :mod:`constrained_particles.fused`. The readable numpy code in
:mod:`~constrained_particles.forces` and :mod:`~constrained_particles.constraints` is the
reference implementation; the tests tie the two together to 1e-12.

Numba is a core dependency. Setting the environment variable ``CPARTICLES_NUMBA=0`` before the
first import turns every compiled path off (``ENABLED`` is False and the block kernels are
None); the numpy reference then runs everywhere.
"""

from __future__ import annotations

import math
import os

import numpy as np

ENABLED = False  #: True when the compiled paths are in use
spring_forces = None  #: compiled DampedSpring block accumulation, or None
group_pieces = None  #: compiled step splitting for groups of particles (envs), or None
mouse_forces = None  #: compiled MouseSpring block accumulation (envs' step splitting), or None

if os.environ.get("CPARTICLES_NUMBA", "1") != "0":
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a core dependency
        numba = None
    if numba is not None:
        ENABLED = True
        from .jit import njit

        # ---------------------------------------------------------------- force elements
        @njit
        def spring_element(lx: float, ly: float, ux: float, uy: float, ks: float, kd: float,
                           rest: float) -> tuple[float, float]:  # pragma: no cover - compiled
            """Force (N) on end i of a damped spring with ``l = x_i - x_j`` (m) and
            ``ldot = v_i - v_j`` (``ux, uy``, m/s): ``-[ks (|l| - r) + kd (ldot . l)/|l|] l/|l|``.
            Zero for a zero-length spring."""
            length = math.sqrt(lx * lx + ly * ly)
            if length > 0.0:
                inv = 1.0 / length
                mag = (ks * (length - rest) + kd * (ux * lx + uy * ly) * inv) * inv
                return -mag * lx, -mag * ly
            return 0.0, 0.0

        @njit
        def tension_element(lx: float, ly: float, ux: float, uy: float, ks: float, kd: float,
                            rest: float) -> tuple[float, float]:  # pragma: no cover - compiled
            """Force (N) on end i of a tension-only spring (a string) with ``l = x_i - x_j``
            (m) and ``ldot = v_i - v_j`` (``ux, uy``, m/s):
            ``-max(0, ks (|l| - r) + kd (ldot . l)/|l|) l/|l|`` while ``|l| > r``, else zero."""
            length = math.sqrt(lx * lx + ly * ly)
            if length > rest and length > 0.0:
                inv = 1.0 / length
                mag = ks * (length - rest) + kd * (ux * lx + uy * ly) * inv
                if mag > 0.0:
                    mag *= inv
                    return -mag * lx, -mag * ly
            return 0.0, 0.0

        @njit
        def friction_element(vx: float, vy: float, mu: float, mass: float, g: float,
                             v_s: float) -> tuple[float, float]:  # pragma: no cover - compiled
            """Table friction (N) on a particle of ``mass`` (kg) sliding at ``v`` (m/s):
            ``-mu m g v / max(|v|, v_s)`` (``g`` in m/s^2, ``v_s`` > 0 in m/s)."""
            speed = math.sqrt(vx * vx + vy * vy)
            scale = mu * mass * g / (speed if speed > v_s else v_s)
            return -scale * vx, -scale * vy

        @njit
        def angular_element(ux: float, uy: float, wx: float, wy: float, vax: float, vay: float,
                            vbx: float, vby: float, vcx: float, vcy: float,
                            spring: tuple[float, float, float]
                            ) -> tuple[float, float, float, float, float, float]:
            # pragma: no cover - compiled
            """Forces (N) on a, b, c of an angular spring with arms ``u = x_a - x_b``,
            ``w = x_c - x_b``: ``-(k d + kd thetadot) dtheta/dx_p``, ``d = wrap(theta - rest)``,
            with ``spring = (k, kd, rest)``: stiffness (N m/rad), damping (N m s/rad) and rest
            angle (rad)."""
            k, kd, rest = spring
            theta = math.atan2(ux * wy - uy * wx, ux * wx + uy * wy)
            # d = pi - ((pi - (theta - rest)) % 2 pi), the modulo as Python's (the sign of the
            # divisor) without its library call where the argument is within one turn of
            # [0, 2 pi): the same bits (fmod is exact there, and so is y - 2 pi, by Sterbenz)
            y = math.pi - (theta - rest)
            tau = 2.0 * math.pi
            if 0.0 <= y < tau:
                wrapped = y
            elif -tau <= y < 0.0:
                wrapped = y + tau
            elif tau <= y < 2.0 * tau:
                wrapped = y - tau
            else:
                wrapped = y % tau
            d = math.pi - wrapped
            uu = ux * ux + uy * uy
            ww = wx * wx + wy * wy
            gax = gay = gcx = gcy = 0.0
            if uu > 0.0:  # dtheta/dx_a = -perp(u)/|u|^2, perp(p) = (-p_y, p_x)
                gax = uy / uu
                gay = -ux / uu
            if ww > 0.0:  # dtheta/dx_c = perp(w)/|w|^2
                gcx = -wy / ww
                gcy = wx / ww
            gbx = -(gax + gcx)
            gby = -(gay + gcy)
            thetadot = (gax * vax + gay * vay) + (gbx * vbx + gby * vby) + (gcx * vcx + gcy * vcy)
            torque = -(k * d + kd * thetadot)
            return (torque * gax, torque * gay, torque * gbx, torque * gby, torque * gcx,
                    torque * gcy)

        @njit
        def wall_element(px: float, py: float, vx: float, vy: float, nx: float, ny: float,
                         offset: float, kw: float, cw: float) -> tuple[float, float]:
            # pragma: no cover - compiled
            """Wall force (N): ``-max(kw p + cw (n . v), 0) n`` while ``p = n . x - offset > 0``."""
            p = px * nx + py * ny - offset
            if p > 0.0:
                mag = max(kw * p + cw * (vx * nx + vy * ny), 0.0)
                return -mag * nx, -mag * ny
            return 0.0, 0.0

        @njit
        def mouse_element(px: float, py: float, vx: float, vy: float, ax: float, ay: float,
                          ks: float, kd: float) -> tuple[float, float]:  # pragma: no cover
            """Mouse spring force (N): ``-ks (x_p - anchor) - kd v_p``."""
            return -ks * (px - ax) - kd * vx, -ks * (py - ay) - kd * vy

        # ------------------------------------------------------------ constraint elements
        @njit
        def circle_row(dx: float, dy: float, vx: float, vy: float, radius: float
                       ) -> tuple[float, float]:  # pragma: no cover - compiled
            """Circular wire with ``d = x - center``: ``(C, Cdot) = (1/2 (|d|^2 - r^2), d . v)``;
            ``J = d^T``, ``Jdot = v^T``."""
            return 0.5 * ((dx * dx + dy * dy) - radius * radius), dx * vx + dy * vy

        @njit
        def rod_row(dx: float, dy: float, dvx: float, dvy: float, length: float
                    ) -> tuple[float, float]:  # pragma: no cover - compiled
            """Rod with ``d = x_a - x_b``: ``(C, Cdot) = (1/2 (|d|^2 - L^2), d . dv)``;
            ``J = [d^T, -d^T]``, ``Jdot = [dv^T, -dv^T]``."""
            return 0.5 * ((dx * dx + dy * dy) - length * length), dx * dvx + dy * dvy

        @njit
        def line_row(px: float, py: float, vx: float, vy: float, nx: float, ny: float,
                     ox: float, oy: float) -> tuple[float, float]:  # pragma: no cover
            """Line wire through ``o`` with normal ``n``: ``(C, Cdot) = (n . (x - o), n . v)``;
            ``J = n^T``, ``Jdot = 0``."""
            return nx * (px - ox) + ny * (py - oy), nx * vx + ny * vy

        @njit
        def length_error(dx: float, dy: float, length: float) -> float:  # pragma: no cover
            """Distance error (m) of a length constraint with ``d`` (m) the vector it constrains
            (``x - center`` of a circular wire of radius ``length``, ``x_a - x_b`` of a rod):
            ``| |d| - length |``, the geometric residual of ``circle_row`` and ``rod_row``."""
            return abs(math.hypot(dx, dy) - length)

        @njit
        def line_error(px: float, py: float, nx: float, ny: float, ox: float, oy: float
                       ) -> float:  # pragma: no cover - compiled
            """Distance error (m) off a line wire through ``o`` with unit normal ``n``:
            ``|n . (x - o)|`` (``|C|`` of ``line_row``)."""
            return abs(nx * (px - ox) + ny * (py - oy))

        @njit
        def add_spring(x: np.ndarray, v: np.ndarray, F: np.ndarray, a: int, b: int, ks: float,
                       kd: float, rest: float) -> None:  # pragma: no cover - compiled
            """Add one damped spring's force (N) between particles ``a`` and ``b`` (indices
            already checked) into ``F``: :func:`spring_element` on ``a``, its opposite on ``b``."""
            fx, fy = spring_element(x[a, 0] - x[b, 0], x[a, 1] - x[b, 1], v[a, 0] - v[b, 0],
                                    v[a, 1] - v[b, 1], ks, kd, rest)
            F[a, 0] += fx
            F[a, 1] += fy
            F[b, 0] -= fx
            F[b, 1] -= fy

        # ------------------------------------------------------------------ block kernels
        @njit
        def _spring_forces(x: np.ndarray, v: np.ndarray, i: np.ndarray, j: np.ndarray,
                           ks: np.ndarray, kd: np.ndarray, rest: np.ndarray,
                           F: np.ndarray) -> None:  # pragma: no cover - compiled
            n = x.shape[0]
            for s in range(i.shape[0]):
                a, b = i[s], j[s]
                if a < 0 or a >= n or b < 0 or b >= n:
                    raise IndexError("DampedSpring: particle index out of range")
                # (unsigned, as the fused kernels pass them: checked >= 0 above, and one
                # compiled version of add_spring serves both)
                add_spring(x, v, F, np.uint64(a), np.uint64(b), ks[s], kd[s], rest[s])

        def spring_forces(x: np.ndarray, v: np.ndarray, i: np.ndarray, j: np.ndarray,
                          ks: np.ndarray, kd: np.ndarray, rest: np.ndarray,
                          F: np.ndarray) -> None:
            """Add the forces (N) of springs ``(i, j, ks, kd, rest)`` at ``(x, v)`` into ``F``.

            Shapes and dtypes are checked here and indices inside the kernel, so no public
            attribute a user edits can make it read or write outside its arrays (IndexError
            or ValueError instead).
            """
            k = len(i)
            n = len(x)
            if not (x.shape == v.shape == F.shape == (n, 2) and len(j) == len(ks) == len(kd)
                    == len(rest) == k):
                raise ValueError("DampedSpring: inconsistent array shapes "
                                 f"(x {x.shape}, v {v.shape}, F {F.shape}, i {np.shape(i)}, "
                                 f"j {np.shape(j)}, ks {np.shape(ks)}, kd {np.shape(kd)}, "
                                 f"rest {np.shape(rest)})")
            _spring_forces(np.ascontiguousarray(x, dtype=np.float64),
                           np.ascontiguousarray(v, dtype=np.float64),
                           np.ascontiguousarray(i, dtype=np.int64),
                           np.ascontiguousarray(j, dtype=np.int64),
                           np.ascontiguousarray(ks, dtype=np.float64),
                           np.ascontiguousarray(kd, dtype=np.float64),
                           np.ascontiguousarray(rest, dtype=np.float64), F)

        @njit(nogil=True)
        def group_pieces(v: np.ndarray, F: np.ndarray, frow: np.ndarray, inv_mass: np.ndarray,
                         size: int, horizon: float, dt: float, travel: float, max_pieces: int,
                         out: np.ndarray, rows: np.ndarray) -> int:  # pragma: no cover
            """For each group of ``size`` consecutive particles, into how many pieces a step of
            ``dt`` (s) must be split so that no particle moves more than ``travel`` (m) per
            piece, bounding its speed over the next ``horizon`` seconds by ``|v| + |F| horizon /
            m`` (m/s): ``ceil(dt max_speed / travel)``, or 1 where that is below 1, above
            ``max_pieces`` or not finite. ``F`` holds each particle's force (N) or, if
            ``frow`` has one entry per particle, a force block's rows: particle q's force is
            then ``F[frow[q]]`` (zero where ``frow[q] < 0``). Writes one count per group into
            ``out`` and, if ``rows`` has one entry per particle, each particle's group count
            into it; returns the largest count."""
            largest = 1
            mapped = frow.shape[0] == v.shape[0]
            for g in range(out.shape[0]):
                worst = 0.0
                finite = True
                for q in range(g * size, (g + 1) * size):
                    fx, fy = 0.0, 0.0
                    if not mapped:
                        fx, fy = F[q, 0], F[q, 1]
                    elif frow[q] >= 0:
                        fx, fy = F[frow[q], 0], F[frow[q], 1]
                    speed = (math.sqrt(v[q, 0] * v[q, 0] + v[q, 1] * v[q, 1])
                             + math.sqrt(fx * fx + fy * fy) * (inv_mass[q] * horizon))
                    if not speed < math.inf:
                        finite = False
                    elif speed > worst:
                        worst = speed
                need = np.ceil(worst * dt / travel)
                count = int(need) if finite and 1.0 <= need <= max_pieces else 1
                out[g] = count
                largest = max(largest, count)
                if rows.shape[0] == v.shape[0]:
                    for q in range(g * size, (g + 1) * size):
                        rows[q] = count
            return largest

        @njit(nogil=True)
        def mouse_forces(x: np.ndarray, v: np.ndarray, particle: np.ndarray,
                         anchor: np.ndarray, ks: np.ndarray, kd: np.ndarray,
                         active: np.ndarray, F: np.ndarray) -> bool:  # pragma: no cover
            """Add the forces (N) of mouse springs ``(particle, anchor, ks, kd, active)`` at
            ``(x, v)`` into ``F``, as ``MouseSpring.accumulate`` does (nothing unless some
            spring is active; then every spring's force times its flag, summed per particle in
            element order): the same bits. False, with nothing written, unless the shapes
            agree and every spring's particle is one of ``x``'s (``accumulate`` then raises)."""
            n, k = x.shape[0], particle.shape[0]
            if not (v.shape[0] == n and F.shape[0] == n and anchor.shape[0] == k
                    and ks.shape[0] == k and kd.shape[0] == k and active.shape[0] == k):
                return False
            on = False
            for e in range(k):
                if particle[e] < 0 or particle[e] >= n:
                    return False
                on = on or active[e]
            if not on:
                return True
            for e in range(k):
                p = particle[e]
                fx, fy = mouse_element(x[p, 0], x[p, 1], v[p, 0], v[p, 1], anchor[e, 0],
                                       anchor[e, 1], ks[e], kd[e])
                flag = 1.0 if active[e] else 0.0
                F[p, 0] += fx * flag
                F[p, 1] += fy * flag
            return True
