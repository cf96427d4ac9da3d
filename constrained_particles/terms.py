"""Common machinery of force and constraint blocks.

A *term* is one vectorized block over index arrays: a cloth's 2,000 springs are one
:class:`~constrained_particles.forces.DampedSpring` with arrays ``i, j, rest, ks, kd``.
Each term class declares which of its attributes are particle-index arrays and which are
per-element parameter arrays; that is enough to validate it, to copy it for a batch of
disconnected systems (:meth:`Term.tiled`) and to draw it.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from .system import ParticleSystem


class Shape(NamedTuple):
    """A drawable primitive in world coordinates (metres), produced by a term.

    ``kind`` is one of:

    - ``"segment"``: ``a`` start points (k, 2), ``b`` end points (k, 2), ``value`` e.g. strain;
    - ``"arrow"``: ``a`` origins (k, 2), ``b`` force vectors in newtons (k, 2), ``value`` |f|;
    - ``"circle"``: ``a`` centres (k, 2), ``value`` radii (k,);
    - ``"line"``: ``a`` points on the line (k, 2), ``b`` unit directions (k, 2);
    - ``"halfplane"``: ``a`` points on the boundary (k, 2), ``b`` outward unit normals (k, 2);
    - ``"angle"``: ``a`` vertices (k, 2), ``b`` (k, 2, 2) arm end points, ``value`` angle error.

    ``style`` names what the renderer should make of it (``"spring"``, ``"rod"``, ...).
    """

    kind: str
    style: str
    a: np.ndarray
    b: np.ndarray | None = None
    value: np.ndarray | None = None


def as_index_array(name: str, value: Any) -> np.ndarray:
    """Return ``value`` as a 1-D int64 array of particle indices or raise ValueError naming it."""
    arr = np.atleast_1d(np.asarray(value))
    if arr.ndim != 1:
        raise ValueError(f"{name} must be an index or a 1-D index array, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.equal(np.mod(arr, 1), 0)):
            raise ValueError(f"{name} must hold integer particle indices, got {arr!r}")
    return arr.astype(np.int64)


def as_param_array(name: str, value: Any, k: int, *, width: int | None = None,
                   nonnegative: bool = False, positive: bool = False) -> np.ndarray:
    """Broadcast a scalar (or vector of length ``width``) parameter to ``k`` elements.

    Raises ValueError naming ``name`` for a wrong shape, a non-finite value or a sign
    violation.
    """
    arr = np.asarray(value, dtype=float)
    shape = (k,) if width is None else (k, width)
    try:
        arr = np.broadcast_to(arr, shape).copy()
    except ValueError:
        raise ValueError(f"{name} must broadcast to shape {shape}, got shape {arr.shape}") from None
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0, got {value!r}")
    if nonnegative and np.any(arr < 0):
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return arr


def as_unit_vectors(name: str, value: Any, k: int) -> np.ndarray:
    """Broadcast direction(s) to (k, 2) unit vectors, raising ValueError for a zero vector."""
    arr = as_param_array(name, value, k, width=2)
    norm = np.linalg.norm(arr, axis=1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError(f"{name} must be a non-zero vector, got {value!r}")
    return arr / norm


def scatter_add(F: np.ndarray, idx: np.ndarray, f: np.ndarray) -> None:
    """Add per-element vectors ``f`` (k, 2) into ``F`` (n, 2) at rows ``idx`` (repeats summed)."""
    n = F.shape[0]
    F[:, 0] += np.bincount(idx, weights=f[:, 0], minlength=n)
    F[:, 1] += np.bincount(idx, weights=f[:, 1], minlength=n)


class Term:
    """Base class of force and constraint blocks.

    Subclasses list their particle-index arrays in ``index_fields`` and their per-element
    arrays (one entry per spring, wire, ...) in ``element_fields``. Parameters that a
    constructor leaves as ``None`` are filled from the system's geometry by :meth:`bind`
    when the term is added to a system.
    """

    index_fields: ClassVar[tuple[str, ...]] = ()
    element_fields: ClassVar[tuple[str, ...]] = ()
    #: Bumped whenever an attribute of any term is (re)assigned, so that compiled packs of a
    #: system (:mod:`constrained_particles.fused`) know when to rebuild. In-place edits of
    #: arrays need no bump: the packs hold the blocks' own arrays.
    generation: ClassVar[int] = 0

    def __setattr__(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)
        Term.generation += 1

    def __len__(self) -> int:
        """Number of elements (springs, wires, ...) in the block."""
        if not self.index_fields:
            return 0
        return len(getattr(self, self.index_fields[0]))

    def bind(self, system: ParticleSystem) -> None:
        """Validate indices against ``system`` and fill geometry defaults. Called by ``add``."""
        n = system.n
        for name in self.index_fields:
            idx = getattr(self, name)
            if idx is None:
                continue
            bad = (idx < 0) | (idx >= n)
            if np.any(bad):
                raise ValueError(
                    f"{type(self).__name__}: {name} holds unknown particle indices "
                    f"{idx[bad].tolist()} (system has {n} particles)")

    def tiled(self, copies: int, stride: int) -> Term:
        """This block repeated for ``copies`` disconnected systems of ``stride`` particles each.

        Copy ``c`` refers to particles ``idx + c * stride``. Used to batch N environments into
        one system with a block-diagonal constraint Jacobian.
        """
        out = copy.deepcopy(self)
        offsets = np.arange(copies, dtype=np.int64) * stride
        for name in self.index_fields:
            idx = getattr(self, name)
            if idx is not None:
                setattr(out, name, (idx[None, :] + offsets[:, None]).ravel())
        for name in self.element_fields:
            arr = getattr(self, name)
            if arr is not None:
                setattr(out, name, np.tile(arr, (copies,) + (1,) * (arr.ndim - 1)))
        return out

    def shapes(self, x: np.ndarray, v: np.ndarray) -> list[Shape]:
        """Drawable primitives for this term at positions ``x`` and velocities ``v``."""
        return []

    def __repr__(self) -> str:
        return f"{type(self).__name__}(<{len(self)} elements>)"
