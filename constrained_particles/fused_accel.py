"""The compiled acceleration of a packed system, for the fused step (:mod:`.fused`): forces by
block type (the elements of :mod:`.kernels`), the constraint rows and their per-component solve
(dense Cholesky up to :data:`~.solver.DIRECT_MAX` rows, beyond them the sparse factorisation
of :mod:`.factor_kernels` or Jacobi-preconditioned conjugate gradients), :func:`_accel` (both,
for one state) and RATTLE's step :func:`_rattle`; with the flat per-particle helpers of the
step loop and the check of a pack's inputs.

The step loop, the tableau-driven Runge-Kutta stages and the entry point
:func:`~.fused.fused_steps` are in :mod:`.fused`, which also packs the blocks; see its
docstring for the design (packing, safety at the boundary, the spring loop).
"""

from __future__ import annotations

import math

import numpy as np

from . import kernels
from .ordering import SPARSE
from .records import (
    ANGULAR,
    CIRCLE,
    CONSTANT,
    DRAG,
    FIXED,
    FRICTION,
    GRAVITY,
    LINE,
    LIVE_COMPONENTS,
    LIVE_ELEMENTS,
    LIVE_PARTICLES,
    LIVE_ROWS,
    MOUSE,
    ROD,
    SPRING,
    TENSION,
    WALL,
    live_lists,
)
from .solver import DIRECT_MAX

#: RATTLE's position solve (the values of :mod:`constrained_particles.rattle`, which documents
#: them): convergence and stall tolerances as fractions of the system's size, and iterations.
RATTLE_POSITION_TOL, RATTLE_STALL_TOL, RATTLE_MAX_ITERATIONS = 1e-13, 1e-10, 50
#: Springs per block of the compiled spring loop (see ``_springs``).
SPRING_BLOCK = 128
#: Shortest run of springs ``(a + t, b + t)`` that the spring loop takes as a run (contiguous
#: reads and writes instead of gathers and scatters), and the run loop's block size.
RUN_MIN, RUN_BLOCK = 32, 256
#: Particles from which the compiled per-particle loops run over flat views (a view costs
#: about as much as the loop saves on a few dozen particles).
FLAT_MIN = 256
#: Kernel status codes.
OK, DIVERGED, FALLBACK = 0, 1, 2


if kernels.ENABLED:
    # fused_steps releases the GIL (another thread may step another system meanwhile): the
    # arrays it reads stay alive as its arguments, and their index arrays cannot change.
    from .factor_kernels import _factor_sparse, _sparse_factor, _sparse_solve
    from .jit import njit
    from .kernels import (
        add_spring,
        angular_element,
        circle_row,
        friction_element,
        length_error,
        line_error,
        line_row,
        mouse_element,
        rod_row,
        spring_element,
        tension_element,
        wall_element,
    )
    # the per-block helpers of _accel, inlined into it: each call passed dozens of arrays
    # (a call of _accel with nothing to do cost 1.4 us, now 0.7; a single SliderCrank env's
    # physics step 10.7 -> 8.9 us), for some 20 s more of first-run compilation
    njit_inline = njit(inline="always")

    @njit
    def _same_count(counts, a, b):  # pragma: no cover - compiled
        """True if particles a[e] and b[e] take the same number of steps, for every e."""
        for e in range(a.shape[0]):
            if counts[a[e]] != counts[b[e]]:
                return False
        return True

    @njit_inline
    def _check_inputs(blocks, rows, n, m, lam, counts, extra):  # pragma: no cover - compiled
        """False if the per-element arrays of a block disagree in length, if an active mouse
        spring's particle is outside [0, n), (``counts`` not empty) if two particles coupled
        by a force element or a constraint row take different numbers of steps, or if
        ``extra`` is None (the version of the step without angular springs, mouse springs,
        fixed points, table friction and tension-only springs: see :func:`_forces`) and the
        blocks hold any of them.

        O(1) per array (and per mouse spring) on a plain call: the index, row, column and run
        arrays were checked when the pack was built (``Packed._consistent``) and are immutable,
        so only what an in-place edit can change is checked here, once per call, before any
        array is read through an index. The mouse springs' particles and ``active`` flags the
        kernel reads are the pack's own copies (``Packed.take_mouse``, under the system's step
        lock): another thread cannot switch one on, or move it, after this check."""
        grav, wall, drag = blocks.gravity, blocks.wall, blocks.drag
        if (grav.block.shape[0] != grav.particles.shape[0]
                or blocks.constant.force.shape[0] != blocks.constant.particles.shape[0]
                or wall.block.shape[0] != wall.particles.shape[0]
                or wall.normal.shape[0] != wall.params.shape[0]
                or drag.kd.shape[0] != drag.particles.shape[0]):
            return False
        spring = blocks.spring
        k = spring.i.shape[0]
        if (spring.j.shape[0] != k or spring.rest.shape[0] != k or spring.ks.shape[0] != k
                or spring.kd.shape[0] != k):
            return False
        ang, mouse, fixed = blocks.angular, blocks.mouse, blocks.fixed
        fric, tension = blocks.friction, blocks.tension
        if extra is None:
            if (ang.a.shape[0] or mouse.particle.shape[0] or fixed.particles.shape[0]
                    or fric.particles.shape[0] or tension.i.shape[0]):
                return False
        else:
            k = fric.particles.shape[0]
            if (fric.block.shape[0] != k or fric.mu.shape[0] != k or fric.lifted.shape[0] != k
                    or fric.params.shape[1] != 2):
                return False
            k = tension.i.shape[0]
            if (tension.j.shape[0] != k or tension.rest.shape[0] != k
                    or tension.ks.shape[0] != k or tension.kd.shape[0] != k):
                return False
            k = ang.a.shape[0]
            if (ang.b.shape[0] != k or ang.c.shape[0] != k or ang.rest.shape[0] != k
                    or ang.k.shape[0] != k or ang.kd.shape[0] != k):
                return False
            k = mouse.particle.shape[0]
            if (mouse.anchor.shape[0] != k or mouse.active.shape[0] != k
                    or mouse.ks.shape[0] != k or mouse.kd.shape[0] != k):
                return False
            k = fixed.particles.shape[0]
            if fixed.point.shape[0] != k or fixed.row.shape[0] != k:
                return False
            mi, mact = mouse.particle, mouse.active
            for e in range(mi.shape[0]):
                if mact[e] and (mi[e] < 0 or mi[e] >= n):
                    return False
        circ, rod, line = blocks.circle, blocks.rod, blocks.line
        k = circ.particles.shape[0]
        if circ.center.shape[0] != k or circ.radius.shape[0] != k or circ.row.shape[0] != k:
            return False
        k = rod.a.shape[0]
        if rod.b.shape[0] != k or rod.length.shape[0] != k or rod.row.shape[0] != k:
            return False
        k = line.particles.shape[0]
        if line.normal.shape[0] != k or line.point.shape[0] != k or line.row.shape[0] != k:
            return False
        cols, nnz = rows.cols, rows.nnz
        if lam.shape[0] != m or cols.shape[0] != m or nnz.shape[0] != m:
            return False
        if counts.shape[0] == 0:
            return True
        if counts.shape[0] != n:
            return False
        if not (_same_count(counts, spring.i, spring.j) and _same_count(counts, ang.a, ang.b)
                and _same_count(counts, ang.b, ang.c)
                and _same_count(counts, tension.i, tension.j)):
            return False
        for r in range(m):
            for k in range(1, nnz[r]):
                if counts[cols[r, k] // 2] != counts[cols[r, 0] // 2]:
                    return False
        return True

    @njit_inline  # (a dispatcher between loops: inlined, no compiled level of its own)
    def _springs(x, v, F, spring, runs):  # pragma: no cover - compiled
        """Add the forces (N) of the springs ``spring`` (:class:`~.records.SpringArrays`) at
        ``(x, v)`` into ``F``, in spring order: the runs (see :func:`spring_runs`, checked when
        packed) by :func:`_spring_run`, the springs between them by
        :func:`_scattered_springs`. Bitwise the plain loop's result either way. ``runs``
        (``Packed.spring_runs``) None: the pack has no runs, and Numba drops the runs' code
        from this version (every spring then goes by :func:`_scattered_springs`)."""
        si, sj, srest, sks, skd = spring.i, spring.j, spring.rest, spring.ks, spring.kd
        k = si.shape[0]
        if runs is None or spring.runs.shape[0] == 0:
            _scattered_springs(x, v, F, si, sj, srest, sks, skd)
            return
        xf, vf, Ff = x.reshape(-1), v.reshape(-1), F.reshape(-1)
        ws = np.empty((6, RUN_BLOCK))
        e = 0
        spans = spring.runs  # (the runs themselves: ``runs`` is the flag)
        for r in range(spans.shape[0] + 1):
            stop = spans[r, 0] if r < spans.shape[0] else k
            if stop > e:
                _scattered_springs(x, v, F, si[e:stop], sj[e:stop], srest[e:stop],
                                   sks[e:stop], skd[e:stop])
            if r == spans.shape[0]:
                break
            lo, hi = spans[r, 0], spans[r, 1]
            a0, d = si[lo], sj[lo] - si[lo]
            for c in range(lo, hi, RUN_BLOCK):
                m = min(RUN_BLOCK, hi - c)
                _spring_run(xf, vf, Ff, a0 + (c - lo), d, srest[c:c + m], sks[c:c + m],
                            skd[c:c + m], ws)
            e = hi

    @njit
    def _spring_run(xf, vf, Ff, a, d, rest, ks, kd, ws):  # pragma: no cover - compiled
        """The springs ``(a + t, a + d + t)``, t < m = len(rest) (d != 0, all in range), on
        flat views of x, v and F: the ends' differences are read from contiguous slices, the
        :func:`spring_element` loop runs over the block, and each particle's sums are written
        in one pass in the plain loop's order (a particle that ends two springs of the run
        takes the earlier spring's force first), so the result is bitwise the plain loop's."""
        m = rest.shape[0]
        b = a + d
        lx, ly, ux, uy, fx, fy = ws[0], ws[1], ws[2], ws[3], ws[4], ws[5]
        xa, xb = xf[2 * a:2 * (a + m)], xf[2 * b:2 * (b + m)]
        va, vb = vf[2 * a:2 * (a + m)], vf[2 * b:2 * (b + m)]
        for t in range(m):
            lx[t] = xa[2 * t] - xb[2 * t]
            ly[t] = xa[2 * t + 1] - xb[2 * t + 1]
            ux[t] = va[2 * t] - vb[2 * t]
            uy[t] = va[2 * t + 1] - vb[2 * t + 1]
        for t in range(m):
            fx[t], fy[t] = spring_element(lx[t], ly[t], ux[t], uy[t], ks[t], kd[t], rest[t])
        if d >= m or -d >= m:  # the two ends' ranges are disjoint
            Fa = Ff[2 * a:2 * (a + m)]
            for t in range(m):
                Fa[2 * t] += fx[t]
                Fa[2 * t + 1] += fy[t]
            Fb = Ff[2 * b:2 * (b + m)]
            for t in range(m):
                Fb[2 * t] -= fx[t]
                Fb[2 * t + 1] -= fy[t]
        elif d > 0:  # [a, b): end i only; [b, a + m): j of spring t, then i of t + d; then j
            Fa = Ff[2 * a:2 * b]
            for t in range(d):
                Fa[2 * t] += fx[t]
                Fa[2 * t + 1] += fy[t]
            Fm = Ff[2 * b:2 * (a + m)]
            for t in range(m - d):
                Fm[2 * t] = (Fm[2 * t] - fx[t]) + fx[t + d]
                Fm[2 * t + 1] = (Fm[2 * t + 1] - fy[t]) + fy[t + d]
            Fb = Ff[2 * (a + m):2 * (b + m)]
            for t in range(d):
                Fb[2 * t] -= fx[m - d + t]
                Fb[2 * t + 1] -= fy[m - d + t]
        else:  # [b, a): end j only; [a, b + m): i of spring t, then j of t - d; then i
            g = -d
            Fb = Ff[2 * b:2 * a]
            for t in range(g):
                Fb[2 * t] -= fx[t]
                Fb[2 * t + 1] -= fy[t]
            Fm = Ff[2 * a:2 * (b + m)]
            for t in range(m - g):
                Fm[2 * t] = (Fm[2 * t] + fx[t]) - fx[t + g]
                Fm[2 * t + 1] = (Fm[2 * t + 1] + fy[t]) - fy[t + g]
            Fa = Ff[2 * (b + m):2 * (a + m)]
            for t in range(g):
                Fa[2 * t] += fx[m - g + t]
                Fa[2 * t + 1] += fy[m - g + t]

    @njit
    def _scattered_springs(x, v, F, si, sj, srest, sks, skd):  # pragma: no cover - compiled
        """Add the forces (N) of the springs ``(si, sj, srest, sks, skd)`` at ``(x, v)`` into
        ``F``. Indices were checked by :func:`_check_inputs`; read as unsigned, they are used
        without the negative-index wraparound.

        Many springs go ``SPRING_BLOCK`` at a time: the ends' differences are gathered into a
        scratch array made here (so the compiler knows it aliases nothing else),
        :func:`spring_element` runs over the block without indirect access (so its square root
        and division are vectorized), and the forces are added to ``F`` in spring order. Each
        spring's arithmetic and the order of the sums into ``F`` are those of the plain loop,
        so both ways give bitwise the same result."""
        k = si.shape[0]
        if k < 2 * SPRING_BLOCK:  # few springs: the plain loop (no allocation)
            for e in range(k):
                add_spring(x, v, F, np.uint64(si[e]), np.uint64(sj[e]), sks[e], skd[e],
                           srest[e])
            return
        ws = np.empty((6, SPRING_BLOCK))
        lx, ly, ux, uy, fx, fy = ws[0], ws[1], ws[2], ws[3], ws[4], ws[5]
        for lo in range(0, k, SPRING_BLOCK):
            m = min(SPRING_BLOCK, k - lo)
            ii, jj = si[lo:lo + m], sj[lo:lo + m]
            for t in range(m):
                a, b = np.uint64(ii[t]), np.uint64(jj[t])
                lx[t] = x[a, 0] - x[b, 0]
                ly[t] = x[a, 1] - x[b, 1]
                ux[t] = v[a, 0] - v[b, 0]
                uy[t] = v[a, 1] - v[b, 1]
            rest, ks, kd = srest[lo:lo + m], sks[lo:lo + m], skd[lo:lo + m]
            for t in range(m):
                fx[t], fy[t] = spring_element(lx[t], ly[t], ux[t], uy[t], ks[t], kd[t], rest[t])
            for t in range(m):
                a, b = np.uint64(ii[t]), np.uint64(jj[t])
                fa, fb = fx[t], fy[t]
                F[a, 0] += fa
                F[a, 1] += fb
                F[b, 0] -= fa
                F[b, 1] -= fb

    # Loops over every particle as flat views, which the compiler vectorizes (each view costs
    # about what the vectorized loop saves on a few dozen particles: see FLAT_MIN). Kept out of
    # the step kernel, whose small-system speed suffers from their presence.
    @njit
    def _scale_flat(out, inv_mass):  # pragma: no cover - compiled
        """``out[q] *= inv_mass[q]`` for every particle q."""
        flat = out.reshape(-1)
        for q in range(inv_mass.shape[0]):
            w = inv_mass[q]
            flat[2 * q] *= w
            flat[2 * q + 1] *= w

    @njit
    def _euler_flat(explicit, h, x, v, a, xs, vs):  # pragma: no cover - compiled
        """One Euler step of ``h`` seconds from ``(x, v)`` with accelerations ``a`` into
        ``(xs, vs)``: explicit (positions with the old velocities) or symplectic (with the
        new ones)."""
        xf, vf, af, xsf, vsf = x.reshape(-1), v.reshape(-1), a.reshape(-1), xs.reshape(-1), \
            vs.reshape(-1)
        if explicit:
            for c in range(xf.shape[0]):
                xsf[c] = xf[c] + h * vf[c]
                vsf[c] = vf[c] + h * af[c]
        else:
            for c in range(xf.shape[0]):
                vnew = vf[c] + h * af[c]
                vsf[c] = vnew
                xsf[c] = xf[c] + h * vnew

    @njit
    def _copy_flat(a, out):  # pragma: no cover - compiled
        """``out[...] = a`` for two C-ordered arrays of one shape, as one flat loop."""
        af, of = a.reshape(-1), out.reshape(-1)
        for c in range(af.shape[0]):
            of[c] = af[c]

    @njit
    def _beyond_flat(xs, vs, limit):  # pragma: no cover - compiled
        """True if any coordinate of ``xs`` or ``vs`` is not below ``limit`` in magnitude
        (NaN included); counted without an early exit, so the loop vectorizes."""
        xsf, vsf = xs.reshape(-1), vs.reshape(-1)
        bad = 0
        for c in range(xsf.shape[0]):
            bad += not (abs(xsf[c]) < limit and abs(vsf[c]) < limit)
        return bad > 0

    @njit_inline
    def _count(live, kind, everything):  # pragma: no cover - compiled
        """How many elements of block type ``kind`` (or, for ``LIVE_PARTICLES`` /
        ``LIVE_ROWS`` / ``LIVE_COMPONENTS``, how many particles, rows, components) a loop
        visits: ``everything`` without ``live``, else the live ones."""
        return everything if live is None else live.sizes[kind]

    @njit_inline
    def _forces(x, v, mass, F, blocks, live, runs, extra):  # pragma: no cover - compiled
        """Applied forces Q (N) into F (overwritten), summed by block type (indices were
        checked by :func:`_check_inputs`). With ``live`` (the workspace of :func:`_gate`; None:
        all live), elements on particles that are not live are skipped, and so are those
        particles' rows of F (nothing reads them). ``runs``: see :func:`_springs`. ``extra``
        (``Packed.extra``) None: the pack has no angular springs, mouse springs, fixed
        points, table friction or tension-only springs, and Numba drops their loops from this
        version (here and in :func:`_rows`,
        :func:`_distance_error`; :func:`_check_inputs` refuses blocks that hold them)."""
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        if live is None:
            F[:, :] = 0.0
        else:
            for i in range(live.sizes[LIVE_PARTICLES]):
                q = lp[i]
                F[q, 0] = 0.0
                F[q, 1] = 0.0
        grav = blocks.gravity
        for ee in range(_count(live, LIVE_ELEMENTS + GRAVITY, grav.particles.shape[0])):
            e = ee if live is None else el.gravity[ee]
            # (checked indices read as unsigned: no wraparound needed)
            q, k = np.uint64(grav.particles[e]), np.uint64(grav.block[e])
            F[q, 0] += mass[q] * grav.g[k, 0]
            F[q, 1] += mass[q] * grav.g[k, 1]
        const = blocks.constant
        for ee in range(_count(live, LIVE_ELEMENTS + CONSTANT, const.particles.shape[0])):
            e = ee if live is None else el.constant[ee]
            q = const.particles[e]
            F[q, 0] += const.force[e, 0]
            F[q, 1] += const.force[e, 1]
        spring = blocks.spring
        if live is None:
            _springs(x, v, F, spring, runs)
        else:
            for ee in range(live.sizes[LIVE_ELEMENTS + SPRING]):
                e = el.spring[ee]
                add_spring(x, v, F, np.uint64(spring.i[e]), np.uint64(spring.j[e]),
                           spring.ks[e], spring.kd[e], spring.rest[e])
        if extra is not None:
            ang = blocks.angular
            for ee in range(_count(live, LIVE_ELEMENTS + ANGULAR, ang.a.shape[0])):
                e = ee if live is None else el.angular[ee]
                a, b, c = ang.a[e], ang.b[e], ang.c[e]
                fax, fay, fbx, fby, fcx, fcy = angular_element(
                    x[a, 0] - x[b, 0], x[a, 1] - x[b, 1], x[c, 0] - x[b, 0], x[c, 1] - x[b, 1],
                    v[a, 0], v[a, 1], v[b, 0], v[b, 1], v[c, 0], v[c, 1],
                    (ang.k[e], ang.kd[e], ang.rest[e]))
                F[a, 0] += fax
                F[a, 1] += fay
                F[b, 0] += fbx
                F[b, 1] += fby
                F[c, 0] += fcx
                F[c, 1] += fcy
        drag = blocks.drag
        for ee in range(_count(live, LIVE_ELEMENTS + DRAG, drag.particles.shape[0])):
            e = ee if live is None else el.drag[ee]
            q = drag.particles[e]
            F[q, 0] -= drag.kd[e] * v[q, 0]
            F[q, 1] -= drag.kd[e] * v[q, 1]
        wall = blocks.wall
        wn, wpar = wall.normal, wall.params
        for ee in range(_count(live, LIVE_ELEMENTS + WALL, wall.particles.shape[0])):
            e = ee if live is None else el.wall[ee]
            q, k = wall.particles[e], wall.block[e]
            fx, fy = wall_element(x[q, 0], x[q, 1], v[q, 0], v[q, 1], wn[k, 0], wn[k, 1],
                                  wpar[k, 0], wpar[k, 1], wpar[k, 2])
            F[q, 0] += fx
            F[q, 1] += fy
        if extra is not None:
            mouse = blocks.mouse
            for ee in range(_count(live, LIVE_ELEMENTS + MOUSE, mouse.particle.shape[0])):
                e = ee if live is None else el.mouse[ee]
                if mouse.active[e]:
                    q = mouse.particle[e]
                    fx, fy = mouse_element(x[q, 0], x[q, 1], v[q, 0], v[q, 1], mouse.anchor[e, 0],
                                           mouse.anchor[e, 1], mouse.ks[e], mouse.kd[e])
                    F[q, 0] += fx
                    F[q, 1] += fy
            tension = blocks.tension
            for ee in range(_count(live, LIVE_ELEMENTS + TENSION, tension.i.shape[0])):
                e = ee if live is None else el.tension[ee]
                a, b = tension.i[e], tension.j[e]
                fx, fy = tension_element(x[a, 0] - x[b, 0], x[a, 1] - x[b, 1],
                                         v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], tension.ks[e],
                                         tension.kd[e], tension.rest[e])
                F[a, 0] += fx
                F[a, 1] += fy
                F[b, 0] -= fx
                F[b, 1] -= fy
            fric = blocks.friction
            fpar, lifted = fric.params, fric.lifted
            for ee in range(_count(live, LIVE_ELEMENTS + FRICTION, fric.particles.shape[0])):
                e = ee if live is None else el.friction[ee]
                if not lifted[e]:
                    q, k = fric.particles[e], fric.block[e]
                    fx, fy = friction_element(v[q, 0], v[q, 1], fric.mu[e], mass[q],
                                              fpar[k, 0], fpar[k, 1])
                    F[q, 0] += fx
                    F[q, 1] += fy

    @njit_inline
    def _rows(x, v, blocks, C, Cdot, Jv, Jdv, live, extra):  # pragma: no cover - compiled
        """C, Cdot and the values of J and Jdot (m, 4) at (x, v), per row (rows of particles
        that are not ``live`` are skipped; None: all live; ``extra``: see :func:`_forces`)."""
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        circ = blocks.circle
        cc = circ.center
        for ee in range(_count(live, LIVE_ELEMENTS + CIRCLE, circ.particles.shape[0])):
            e = ee if live is None else el.circle[ee]
            q, r = circ.particles[e], circ.row[e]
            dx, dy = x[q, 0] - cc[e, 0], x[q, 1] - cc[e, 1]
            C[r], Cdot[r] = circle_row(dx, dy, v[q, 0], v[q, 1], circ.radius[e])
            Jv[r, 0], Jv[r, 1] = dx, dy
            Jdv[r, 0], Jdv[r, 1] = v[q, 0], v[q, 1]
        rod = blocks.rod
        for ee in range(_count(live, LIVE_ELEMENTS + ROD, rod.a.shape[0])):
            e = ee if live is None else el.rod[ee]
            a, b, r = rod.a[e], rod.b[e], rod.row[e]
            dx, dy = x[a, 0] - x[b, 0], x[a, 1] - x[b, 1]
            dvx, dvy = v[a, 0] - v[b, 0], v[a, 1] - v[b, 1]
            C[r], Cdot[r] = rod_row(dx, dy, dvx, dvy, rod.length[e])
            Jv[r, 0], Jv[r, 1], Jv[r, 2], Jv[r, 3] = dx, dy, -dx, -dy
            Jdv[r, 0], Jdv[r, 1], Jdv[r, 2], Jdv[r, 3] = dvx, dvy, -dvx, -dvy
        line = blocks.line
        ln, lpt = line.normal, line.point
        for ee in range(_count(live, LIVE_ELEMENTS + LINE, line.particles.shape[0])):
            e = ee if live is None else el.line[ee]
            q, r = line.particles[e], line.row[e]
            C[r], Cdot[r] = line_row(x[q, 0], x[q, 1], v[q, 0], v[q, 1], ln[e, 0], ln[e, 1],
                                     lpt[e, 0], lpt[e, 1])
            Jv[r, 0], Jv[r, 1] = ln[e, 0], ln[e, 1]
            Jdv[r, 0], Jdv[r, 1] = 0.0, 0.0
        if extra is not None:
            fixed = blocks.fixed
            for ee in range(_count(live, LIVE_ELEMENTS + FIXED, fixed.particles.shape[0])):
                e = ee if live is None else el.fixed[ee]
                q, r = fixed.particles[e], fixed.row[e]
                for axis in range(2):
                    C[r + axis] = x[q, axis] - fixed.point[e, axis]
                    Cdot[r + axis] = v[q, axis]
                    Jv[r + axis, 0] = 1.0
                    Jdv[r + axis, 0] = 0.0

    @njit
    def _distance_error(x, blocks, live, extra):  # pragma: no cover - compiled
        """Largest geometric constraint residual (m): how far any particle is off its wire,
        any rod from its length, any pin from its point (of ``live`` particles; None: all;
        ``extra``: see :func:`_forces`)."""
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        worst = 0.0
        circ = blocks.circle
        cc = circ.center
        for ee in range(_count(live, LIVE_ELEMENTS + CIRCLE, circ.particles.shape[0])):
            e = ee if live is None else el.circle[ee]
            q = circ.particles[e]
            d = length_error(x[q, 0] - cc[e, 0], x[q, 1] - cc[e, 1], circ.radius[e])
            if not d <= worst:
                worst = d
        rod = blocks.rod
        for ee in range(_count(live, LIVE_ELEMENTS + ROD, rod.a.shape[0])):
            e = ee if live is None else el.rod[ee]
            a, b = rod.a[e], rod.b[e]
            d = length_error(x[a, 0] - x[b, 0], x[a, 1] - x[b, 1], rod.length[e])
            if not d <= worst:
                worst = d
        line = blocks.line
        ln, lpt = line.normal, line.point
        for ee in range(_count(live, LIVE_ELEMENTS + LINE, line.particles.shape[0])):
            e = ee if live is None else el.line[ee]
            q = line.particles[e]
            d = line_error(x[q, 0], x[q, 1], ln[e, 0], ln[e, 1], lpt[e, 0], lpt[e, 1])
            if not d <= worst:
                worst = d
        if extra is not None:
            fixed = blocks.fixed
            for ee in range(_count(live, LIVE_ELEMENTS + FIXED, fixed.particles.shape[0])):
                e = ee if live is None else el.fixed[ee]
                q = fixed.particles[e]
                for axis in range(2):
                    d = abs(x[q, axis] - fixed.point[e, axis])
                    if not d <= worst:
                        worst = d
        return worst

    @njit_inline
    def _solve_components(rows, ws, b, lam, tol, live, large, factored):
        # pragma: no cover - compiled
        """Solve ``J W J^T lam = b`` (``J`` the values ``ws.Jv`` on ``rows``) component by
        component (with ``live``, only those of live particles: see :func:`_gate`); False if
        any solve is singular, ill-posed or does not converge (the caller then uses the
        reference solver). Components of more than ``DIRECT_MAX`` rows are solved by their
        sparse Cholesky factorisation (``Rows.kind`` ``SPARSE``; with ``factored`` True by the
        factors already in ``ws.L``, else factorised here) or by conjugate gradients
        (``CG``), if ``large`` is not None (``Packed.large``: the pack has such a
        component); with None, Numba drops that branch, so a system without them compiles
        neither, and such a component (never there) would return False."""
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        cols, nnz, comp_rows, comp_ptr = rows.cols, rows.nnz, rows.comp_rows, rows.comp_ptr
        w2, Jv, work, A, tmp = ws.w2, ws.Jv, ws.work, ws.A, ws.tmp
        ncomp = comp_ptr.shape[0] - 1
        for kk in range(_count(live, LIVE_COMPONENTS, ncomp)):
            k = kk if live is None else lc[kk]
            start, stop = comp_ptr[k], comp_ptr[k + 1]
            s = stop - start
            if s <= DIRECT_MAX:
                # dense J W J^T of this component
                for i in range(s):
                    ri = comp_rows[start + i]
                    for j in range(i + 1):
                        rj = comp_rows[start + j]
                        acc = 0.0
                        for ki in range(nnz[ri]):
                            ci = cols[ri, ki]
                            for kj in range(nnz[rj]):
                                if cols[rj, kj] == ci:
                                    acc += Jv[ri, ki] * w2[ci] * Jv[rj, kj]
                        A[i, j] = acc
                # Cholesky in place (lower triangle)
                for j in range(s):
                    d = A[j, j]
                    for q in range(j):
                        d -= A[j, q] * A[j, q]
                    if not d > 1e-12 * A[j, j] or not d > 0.0:
                        return False
                    d = math.sqrt(d)
                    A[j, j] = d
                    for i in range(j + 1, s):
                        acc = A[i, j]
                        for q in range(j):
                            acc -= A[i, q] * A[j, q]
                        A[i, j] = acc / d
                for i in range(s):  # forward: L y = b
                    acc = b[comp_rows[start + i]]
                    for q in range(i):
                        acc -= A[i, q] * work[q]
                    work[i] = acc / A[i, i]
                for i in range(s - 1, -1, -1):  # back: L^T lam = y
                    acc = work[i]
                    for q in range(i + 1, s):
                        acc -= A[q, i] * work[q]
                    work[i] = acc / A[i, i]
                for i in range(s):
                    lam[comp_rows[start + i]] = work[i]
            elif large is None:
                return False
            elif rows.kind[k] == SPARSE:
                if not (factored or _sparse_factor(rows, Jv, w2, ws.L, k)):
                    return False
                _sparse_solve(rows, ws.L, ws.y, b, lam, k)
            elif not _cg_component(cols, nnz, comp_rows[start:stop], w2, Jv, b, lam, tol, tmp):
                return False
        return True

    @njit
    def _matvec(cols, nnz, rows, w2, Jv, p, out, tmp):  # pragma: no cover - compiled
        """out = J W J^T p on the rows of one component (tmp is a zeroed (2n,) buffer)."""
        for i in range(rows.shape[0]):
            r = rows[i]
            for k in range(nnz[r]):
                tmp[cols[r, k]] += Jv[r, k] * p[i]
        for i in range(rows.shape[0]):
            r = rows[i]
            acc = 0.0
            for k in range(nnz[r]):
                acc += Jv[r, k] * w2[cols[r, k]] * tmp[cols[r, k]]
            out[i] = acc
        for i in range(rows.shape[0]):
            r = rows[i]
            for k in range(nnz[r]):
                tmp[cols[r, k]] = 0.0

    @njit
    def _cg_component(cols, nnz, rows, w2, Jv, b, lam, tol, tmp):  # pragma: no cover
        """Jacobi-preconditioned CG on one component, warm-started from ``lam``."""
        s = rows.shape[0]
        d = np.empty(s)
        y = np.empty(s)
        rhs = np.empty(s)
        for i in range(s):
            r = rows[i]
            acc = 0.0
            for k in range(nnz[r]):
                acc += Jv[r, k] * Jv[r, k] * w2[cols[r, k]]
            if not acc > 0.0:
                return False
            d[i] = acc
            y[i] = lam[r]
            rhs[i] = b[r]
        bnorm = math.sqrt(np.sum(rhs * rhs))
        Ap = np.empty(s)
        _matvec(cols, nnz, rows, w2, Jv, y, Ap, tmp)
        res = rhs - Ap
        if bnorm == 0.0:
            for i in range(s):
                lam[rows[i]] = 0.0
            return True
        z = res / d
        p = z.copy()
        rz = np.sum(res * z)
        for _ in range(10 * s + 10):
            if math.sqrt(np.sum(res * res)) <= tol * bnorm:
                for i in range(s):
                    lam[rows[i]] = y[i]
                return True
            _matvec(cols, nnz, rows, w2, Jv, p, Ap, tmp)
            pAp = np.sum(p * Ap)
            if not pAp > 0.0:
                return False
            alpha = rz / pAp
            y += alpha * p
            res -= alpha * Ap
            z = res / d
            rz_new = np.sum(res * z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        if math.sqrt(np.sum(res * res)) <= tol * bnorm:
            for i in range(s):
                lam[rows[i]] = y[i]
            return True
        return False

    @njit
    def _accel(x, v, out, state, settings, blocks, rows, ws, live, large, runs, extra):
        # pragma: no cover - compiled
        """``qddot = W (Q + J^T lam)`` (m/s^2) at ``(x, v)`` into ``out`` (with ``live``, of
        the live particles only: see :func:`_gate`), the multipliers into ``state.lam`` (warm
        start in); False if the solve failed. ``large``: see :func:`_solve_components`; ``runs``:
        see :func:`_springs`; ``extra``: see :func:`_forces`."""
        lp, lr, lc, el = live_lists(live)  # (hoisted: None without live)
        mass, inv_mass, lam = state.mass, state.inv_mass, state.lam
        _forces(x, v, mass, out, blocks, live, runs, extra)
        C, Cdot, Jv, Jdv, b, w2 = ws.C, ws.Cdot, ws.Jv, ws.Jdv, ws.b, ws.w2
        cols, nnz = rows.cols, rows.nnz
        m = C.shape[0]
        if m:
            _rows(x, v, blocks, C, Cdot, Jv, Jdv, live, extra)
            ks, kd = settings.ks, settings.kd
            for rr in range(_count(live, LIVE_ROWS, m)):  # b = -Jdot qdot - J W Q
                r = rr if live is None else lr[rr]  # - ks C - kd Cdot
                acc = 0.0
                for k in range(nnz[r]):
                    c = cols[r, k]
                    q, axis = c // 2, c % 2
                    acc += Jdv[r, k] * v[q, axis] + Jv[r, k] * (w2[c] * out[q, axis])
                b[r] = -acc - ks * C[r] - kd * Cdot[r]
            if not _solve_components(rows, ws, b, lam, settings.tol, live, large, False):
                return False
            for rr in range(_count(live, LIVE_ROWS, m)):  # Q += J^T lam
                r = rr if live is None else lr[rr]
                for k in range(nnz[r]):
                    c = cols[r, k]
                    out[c // 2, c % 2] += Jv[r, k] * lam[r]
        if live is None and x.shape[0] >= FLAT_MIN:
            _scale_flat(out, inv_mass)
            return True
        for i in range(_count(live, LIVE_PARTICLES, x.shape[0])):
            q = i if live is None else lp[i]
            out[q, 0] *= inv_mass[q]
            out[q, 1] *= inv_mass[q]
        return True

    @njit
    def _rattle(x, v, xs, vs, h, state, settings, engine, large, runs, extra, fresh):
        # pragma: no cover - compiled
        """One RATTLE step of ``h`` seconds from (x, v) into (xs, vs), as
        :func:`constrained_particles.rattle.rattle` does it; False where the reference must
        take over (it raises the errors). ``large``, ``runs``, ``extra``: see
        :func:`_solve_components`, :func:`_springs`, :func:`_forces`.

        Sparse-factorised components take simplified Newton iterations in the position solve:
        ``J(x0) W J(x0)^T``, factorised once, instead of the reference's ``J(x1) W J(x1)^T``
        at every iteration (both err from the exact ``J(x1) W J(x0)^T`` by O(h |v| / L), so
        they converge alike, to the same root). The velocity solve factorises ``J(x1) W
        J(x1)^T``, which is the next step's ``J(x0) W J(x0)^T``: with ``fresh`` True (the
        step before, in the same call, ended at ``x``) ``ws.L`` holds it already, and a step
        costs one factorisation. ``engine``: the :class:`~.records.Engine` (its ``blocks``,
        ``rows`` and workspace)."""
        blocks, rows, ws = engine.blocks, engine.rows, engine.work
        mass, inv_mass, tol = state.mass, state.inv_mass, settings.tol
        f0, f1 = ws.a1, ws.a2  # (stage buffers: RATTLE's force and predicted velocity)
        C, Cdot, Jv, Jdv, J0, b, dl = ws.C, ws.Cdot, ws.Jv, ws.Jdv, ws.J0, ws.b, ws.dl
        w2, tmp = ws.w2, ws.tmp
        cols, nnz, comp_rows, comp_ptr = rows.cols, rows.nnz, rows.comp_rows, rows.comp_ptr
        n = x.shape[0]
        m = C.shape[0]
        half = 0.5 * h
        _forces(x, v, mass, f0, blocks, None, runs, extra)
        for q in range(n):
            for d in range(2):
                vs[q, d] = v[q, d] + (half * f0[q, d]) * inv_mass[q]  # v_half
                xs[q, d] = x[q, d] + h * vs[q, d]
        if m:
            _rows(x, v, blocks, C, Cdot, J0, Jdv, None, extra)
            if large is not None and not fresh and not _factor_sparse(rows, J0, w2, ws.L):
                return False
            # Newton on C(x1) = 0, convergence decided per component (as the reference does)
            ncomp = comp_ptr.shape[0] - 1
            done = np.zeros(ncomp, np.bool_)
            previous = np.full(ncomp, math.inf)
            for iteration in range(RATTLE_MAX_ITERATIONS + 1):
                _rows(xs, vs, blocks, C, Cdot, Jv, Jdv, None, extra)
                remaining = 0
                for k in range(ncomp):
                    worst = 0.0
                    size = 0.0
                    for i in range(comp_ptr[k], comp_ptr[k + 1]):
                        r = comp_rows[i]
                        g = 0.0
                        for kk in range(nnz[r]):
                            c = cols[r, kk]
                            g += Jv[r, kk] * Jv[r, kk]
                            a = abs(xs[c // 2, c % 2])
                            if not a <= size:
                                size = a
                        dist = abs(C[r]) / math.sqrt(g)
                        if not dist <= worst:
                            worst = dist
                    if not (worst < math.inf and size < math.inf):
                        return False  # non-finite or a vanishing gradient: the reference says
                    if worst <= RATTLE_POSITION_TOL * size or (
                            worst > 0.5 * previous[k] and worst <= RATTLE_STALL_TOL * size):
                        done[k] = True
                    if not done[k]:
                        remaining += 1
                    previous[k] = worst
                if remaining == 0:
                    break
                if iteration == RATTLE_MAX_ITERATIONS:
                    return False
                for k in range(ncomp):
                    for i in range(comp_ptr[k], comp_ptr[k + 1]):
                        r = comp_rows[i]
                        b[r] = 0.0 if done[k] else C[r]
                        dl[r] = 0.0
                if not _solve_components(rows, ws, b, dl, tol, None, large, True):
                    return False
                for r in range(m):  # dq = W J(x0)^T dlam, accumulated in tmp
                    for k in range(nnz[r]):
                        tmp[cols[r, k]] += J0[r, k] * dl[r]
                for q in range(n):
                    for d in range(2):
                        dq = w2[2 * q + d] * tmp[2 * q + d]
                        tmp[2 * q + d] = 0.0
                        xs[q, d] -= dq
                        vs[q, d] -= dq / h
        # velocity-dependent forces see the predicted v1 = 2 v_half - v0
        for q in range(n):
            for d in range(2):
                f1[q, d] = 2.0 * vs[q, d] - v[q, d]
        _forces(xs, f1, mass, f0, blocks, None, runs, extra)
        for q in range(n):
            for d in range(2):
                vs[q, d] = vs[q, d] + (half * f0[q, d]) * inv_mass[q]  # u
        if m:  # J(x1) is current; mu such that J(x1) v1 = 0
            for r in range(m):
                acc = 0.0
                for k in range(nnz[r]):
                    c = cols[r, k]
                    acc += Jv[r, k] * vs[c // 2, c % 2]
                b[r] = acc
                dl[r] = 0.0
            if not _solve_components(rows, ws, b, dl, tol, None, large, False):
                return False
            for r in range(m):
                for k in range(nnz[r]):
                    tmp[cols[r, k]] += Jv[r, k] * dl[r]
            for q in range(n):
                for d in range(2):
                    vs[q, d] = vs[q, d] - w2[2 * q + d] * tmp[2 * q + d]
                    tmp[2 * q + d] = 0.0
        return True
