"""Common machinery of force and constraint blocks.

A *term* is one vectorized block over index arrays: a cloth's 2,000 springs are one
:class:`~constrained_particles.forces.DampedSpring` with arrays ``i, j, rest, ks, kd``.
Each term class declares which of its attributes are particle-index arrays and which are
per-element parameter arrays; that is enough to validate it, to copy it for a batch of
disconnected systems (:meth:`Term.tiled`) and to draw it.
"""

from __future__ import annotations

import copy
import math
import numbers
from typing import TYPE_CHECKING, ClassVar, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from .system import ParticleSystem


class Shape(NamedTuple):
    """A drawable primitive in world coordinates (metres), produced by a term.

    ``kind`` is one of:

    - ``"segment"``: ``a`` start points (k, 2), ``b`` end points (k, 2), ``value`` e.g. strain;
    - ``"arrow"``: ``a`` origins (k, 2), ``b`` force vectors in newtons (k, 2), ``value`` ``|f|``;
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


class ArgumentTypeError(TypeError, ValueError):
    """An argument of the wrong type (a string for a number, a bool mask for indices, ...).

    A TypeError, and also a ValueError so that code catching the library's documented
    ValueError for bad arguments catches it too.
    """


#: Largest particle index (and count) accepted anywhere: beyond it arrays cannot be allocated.
MAX_INDEX = 2**40


def frozen(arr: np.ndarray) -> np.ndarray:
    """An immutable copy of ``arr``: a read-only array over a private ``bytes`` buffer. Writing
    to it raises ValueError, and neither its WRITEABLE flag nor that of any view of it can be
    switched back on (numpy refuses: the memory belongs to an immutable object)."""
    arr = np.ascontiguousarray(arr)
    return np.frombuffer(arr.tobytes(), dtype=arr.dtype).reshape(arr.shape)


def is_frozen(arr: object) -> bool:
    """True if ``arr`` is an array made by :func:`frozen` (or a view of one): read-only memory
    that nothing can make writeable again, so a check of its values holds for good."""
    if not isinstance(arr, np.ndarray) or arr.flags.writeable:
        return False
    base = arr
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            return False
        base = base.base
    return isinstance(base, bytes)


def as_index(name: str, value: ArrayLike) -> int:
    """``value`` as one particle index (an int >= 0), else TypeError or ValueError naming it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral,
                                                                        numbers.Real)):
        raise ArgumentTypeError(f"{name} must be an integer particle index, got {value!r}")
    if not (math.isfinite(value) and value == int(value) and 0 <= value < MAX_INDEX):
        raise ValueError(f"{name} must be an integer particle index >= 0, got {value!r}")
    return int(value)


def as_index_array(name: str, value: ArrayLike) -> np.ndarray:
    """Return ``value`` as a read-only 1-D int64 array of particle indices.

    Integral floats are accepted; booleans (a mask is not a list of indices), strings and other
    types raise TypeError, and non-integral, negative or impossibly large values ValueError,
    each naming ``name``.
    """
    try:
        arr = np.atleast_1d(np.asarray(value))
    except (TypeError, ValueError, OverflowError):
        raise ArgumentTypeError(f"{name} must be particle indices, got {value!r}") from None
    if arr.dtype.kind == "b":
        raise ArgumentTypeError(f"{name} must hold integer particle indices, not booleans "
                                f"(for a mask use np.flatnonzero(mask)), got {value!r}")
    if arr.size and arr.dtype.kind not in "iuf":
        raise ArgumentTypeError(f"{name} must hold integer particle indices, got {value!r}")
    if arr.ndim != 1:
        raise ValueError(f"{name} must be an index or a 1-D index array, got shape {arr.shape}")
    if arr.size:
        with np.errstate(invalid="ignore"):
            ok = np.all((arr >= 0) & (arr < MAX_INDEX))
            if ok and arr.dtype.kind == "f":
                ok = np.all(np.equal(np.mod(arr, 1), 0))
        if not ok:
            raise ValueError(f"{name} must hold integer particle indices >= 0, got {value!r}")
    return frozen(arr.astype(np.int64))


def as_param_array(name: str, value: ArrayLike, k: int, *, width: int | None = None,
                   nonnegative: bool = False, positive: bool = False) -> np.ndarray:
    """Broadcast a scalar (or vector of length ``width``) parameter to ``k`` elements.

    Raises ValueError naming ``name`` for a wrong shape, a non-finite value or a sign
    violation.
    """
    try:
        raw = np.asarray(value)
        if raw.dtype.kind not in "iuf":  # booleans, strings, None, objects
            raise TypeError
        arr = raw.astype(float)
    except (TypeError, ValueError, OverflowError):
        raise ArgumentTypeError(f"{name} must be a number or an array of numbers, "
                                f"got {value!r}") from None
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


def as_unit_vectors(name: str, value: ArrayLike, k: int) -> np.ndarray:
    """Broadcast direction(s) to (k, 2) unit vectors, raising ValueError for a zero vector."""
    arr = as_param_array(name, value, k, width=2)
    # scale by the largest component first, so that |(1e200, 0)| does not overflow to inf
    big = np.max(np.abs(arr), axis=1, keepdims=True)
    if np.any(big == 0):
        raise ValueError(f"{name} must be a non-zero vector, got {value!r}")
    arr = arr / big
    return arr / np.linalg.norm(arr, axis=1, keepdims=True)


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
    #: This block's version: bumped whenever one of its public attributes is (re)assigned, so
    #: that the compiled packs of a system (:mod:`constrained_particles.fused`) know when to
    #: rebuild without scanning any array. In-place edits of parameter arrays need no bump (the
    #: packs hold the blocks' own arrays); index arrays are immutable (:func:`frozen`).
    version: int = 0

    def __len__(self) -> int:
        """Number of elements (springs, wires, ...) in the block."""
        if not self.index_fields:
            return 0
        return len(getattr(self, self.index_fields[0]))

    def __setattr__(self, name: str, value: object) -> None:
        if name == "version":
            raise AttributeError("version is kept by the block: it counts reassignments")
        # Index arrays are immutable; replacing one is validated like the constructor's argument
        # and, once the block is bound, against the system's particle count, so that no later
        # evaluation (numpy or compiled) can read outside the state arrays.
        if name in self.index_fields:
            bound = self.__dict__.get("_bound_n")
            old = self.__dict__.get(name)
            if value is not None:
                value = as_index_array(name, value)
            # arrays that must stay aligned (i with j, particles with their parameters) keep
            # their length; a lone particle list (Gravity, Drag, Wall) may grow or shrink
            aligned = len(self.index_fields) > 1 or bool(self.element_fields)
            if bound is not None and old is not None and (
                    value is None or (aligned and len(value) != len(old))):
                raise ValueError(f"{name}: a block in a system keeps its {len(old)} elements; "
                                 f"got {value!r} (remove the block and add a new one)")
            if bound is not None and value is not None:
                self._check_indices(name, value, bound)
        elif name in self.element_fields and value is not None:
            # a bound block's per-element arrays keep their number of elements
            old = self.__dict__.get(name)
            if (self.__dict__.get("_bound_n") is not None and old is not None
                    and np.shape(value)[:1] != np.shape(old)[:1]):
                raise ValueError(f"{name}: a block in a system keeps its {len(old)} elements; "
                                 f"got shape {np.shape(value)} (remove the block and add a new "
                                 "one)")
        super().__setattr__(name, value)
        if not name.startswith("_"):
            self.__dict__["version"] = self.version + 1

    def _assign_checked(self, name: str, value: object) -> None:
        """Set attribute ``name`` to ``value``, already validated by the caller (index arrays
        :func:`frozen`), and bump :attr:`version` as any assignment does."""
        super().__setattr__(name, value)
        self.__dict__["version"] = self.version + 1

    def __setstate__(self, state: dict[str, object]) -> None:
        # copies and unpickled blocks get read-only index arrays again
        self.__dict__.update(state)
        for name in self.index_fields:
            if state.get(name) is not None:
                self.__dict__[name] = frozen(state[name])

    def _check_indices(self, name: str, idx: np.ndarray, n: int) -> None:
        bad = (idx < 0) | (idx >= n)
        if np.any(bad):
            raise ValueError(
                f"{type(self).__name__}: {name} holds unknown particle indices "
                f"{idx[bad].tolist()[:10]} (system has {n} particles)")

    def bind(self, system: ParticleSystem) -> None:
        """Validate indices against ``system`` and fill geometry defaults. Called by ``add``.

        Afterwards a replaced index array is checked against ``system``'s particle count.
        """
        for name in self.index_fields:
            idx = getattr(self, name)
            if idx is not None:
                self._check_indices(name, idx, system.n)
        self._bound_n = system.n

    def tiled(self, copies: int, stride: int) -> Term:
        """This block repeated for ``copies`` disconnected systems of ``stride`` particles each.

        Copy ``c`` refers to particles ``idx + c * stride``. Used to batch N environments into
        one system with a block-diagonal constraint Jacobian.
        """
        out = copy.deepcopy(self)
        out.__dict__.pop("_bound_n", None)  # the copies' indices range over the larger system
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
