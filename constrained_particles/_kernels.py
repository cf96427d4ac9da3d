"""Optional compiled kernels for the hot path (Numba), behind the blocks' usual API.

Numba is used when it is installed (the ``fast`` extra) unless the environment variable
``CPARTICLES_NUMBA=0`` is set; otherwise every block runs its pure-numpy path. Both paths
compute the same formulas and are compared in the tests (they differ only in the order in
which forces are summed, at the level of rounding).
"""

from __future__ import annotations

import os

import numpy as np

spring_forces = None  #: compiled DampedSpring force accumulation, or None

if os.environ.get("CPARTICLES_NUMBA", "1") != "0":
    try:
        import numba
    except ImportError:  # the pure-numpy path serves
        numba = None
    if numba is not None:

        @numba.njit(cache=True)
        def _spring_forces(x: np.ndarray, v: np.ndarray, i: np.ndarray, j: np.ndarray,
                           ks: np.ndarray, kd: np.ndarray, rest: np.ndarray,
                           F: np.ndarray) -> None:  # pragma: no cover - compiled
            # DESIGN.md damped spring: f_i = -[ks (|l| - r) + kd (ldot . l)/|l|] l/|l|
            for s in range(i.shape[0]):
                a, b = i[s], j[s]
                lx = x[a, 0] - x[b, 0]
                ly = x[a, 1] - x[b, 1]
                length = np.sqrt(lx * lx + ly * ly)
                if length > 0.0:
                    inv = 1.0 / length
                    ldot_l = (v[a, 0] - v[b, 0]) * lx + (v[a, 1] - v[b, 1]) * ly
                    mag = (ks[s] * (length - rest[s]) + kd[s] * ldot_l * inv) * inv
                    F[a, 0] -= mag * lx
                    F[a, 1] -= mag * ly
                    F[b, 0] += mag * lx
                    F[b, 1] += mag * ly

        spring_forces = _spring_forces
