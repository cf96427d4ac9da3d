"""Argument checks and small helpers the environments share: numbers, ranges, actions.

Every check raises ValueError naming the argument (``ArgumentTypeError``, also a ValueError, for
a value of the wrong type) and returns the value in the type the environments keep.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from constrained_particles.terms import ArgumentTypeError

from . import _measure


def check_positive(name: str, value: object, *, integer: bool = False, allow_zero: bool = False,
                   minimum: float = 0.0, maximum: float = 1e6) -> int | float:
    """``value`` as a finite number > 0 (>= 0 if ``allow_zero``; an int if ``integer``), at least
    ``minimum`` and at most ``maximum`` (default 1e6, the systems' divergence limit), else
    ValueError naming ``name`` (ArgumentTypeError, also a ValueError, for a non-number).

    The bounds keep derived quantities (1 / dt, r^2, frame rates, arrays) representable: an
    overflowing or underflowing argument gets this ValueError, never an OverflowError.
    """
    bound = ">= 0" if allow_zero else "> 0"
    if isinstance(value, (bool, np.bool_)) or not isinstance(
            value, (int, np.integer) if integer else (int, float, np.integer, np.floating)):
        raise ArgumentTypeError(f"{name} must be {'an integer' if integer else 'a number'} "
                                f"{bound}, got {value!r}")
    if not (math.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
        raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")
    if value < minimum or value > maximum:
        raise ValueError(f"{name} must be in [{minimum:g}, {maximum:g}], got {value!r}")
    return int(value) if integer else float(value)


def check_seed(seed: object, name: str = "seed") -> int | None:
    """``seed`` as a Python int (a Python or numpy integer >= 0) or None, else ValueError
    naming ``name`` (ArgumentTypeError, also a ValueError, for a non-integer): Python and numpy
    integers seed alike."""
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise ArgumentTypeError(f"{name} must be an integer >= 0 or None, got {seed!r}")
    if seed < 0:
        raise ValueError(f"{name} must be an integer >= 0 or None, got {seed!r}")
    return int(seed)


def check_options(options: object, valid: tuple[str, ...]) -> dict[str, object]:
    """``reset``'s ``options`` (None: none) as a dict, else ValueError naming ``options``: a
    mapping whose keys are all in ``valid`` (a misspelt key is an error, not ignored)."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ArgumentTypeError(f"options must be a dict or None, got {options!r}")
    unknown = [k for k in options if k not in valid]
    if unknown:
        takes = f"the valid keys are {', '.join(map(repr, valid))}" if valid else \
            "this env takes no options (pass None or {})"
        raise ValueError(f"options: unknown key{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(map(repr, unknown))}; {takes}")
    return options


def check_range(name: str, value: object) -> tuple[float, float]:
    """``value`` as a finite ``(low, high)`` pair with ``low <= high``, else ValueError."""
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (low, high) pair of numbers, got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise ValueError(f"{name} must be finite with low <= high, got {value!r}")
    return low, high


def check_goal_range(goal_range: object, min_distance: object) -> tuple[tuple[float, float], float]:
    """Validate a goal range and the minimum start-to-goal distance (m) drawn inside it."""
    low, high = check_range("goal_range", goal_range)
    gap = check_positive("min_distance", min_distance, allow_zero=True)
    if gap > 0 and high - low <= 2 * gap:
        raise ValueError(f"goal_range {goal_range!r} must be wider than twice min_distance = "
                         f"{gap:g} m, or no goal could be that far from some starts")
    return (low, high), gap


#: NumPy's dtype objects of the scalar types :func:`_owned` is asked about (one object each),
#: tested by identity before the comparison that also accepts an equal dtype
_DTYPES = {t: np.dtype(t) for t in (np.float64, np.float32, np.int64, np.bool_)}


def _owned(a: Any, dtype: Any, shape: tuple[int, ...], _dtype_of: Any = _DTYPES.get) -> bool:
    """True if ``a`` is a C-ordered ndarray of ``dtype`` and ``shape``, as the task made it:
    the compiled bookkeeping reads (and writes) such arrays without bounds checks, so one a
    user replaced with another shape takes the numpy path and its checks instead."""
    if type(a) is not np.ndarray or a.shape != shape:
        return False
    dt = a.dtype
    return (dt is _dtype_of(dtype) or dt == dtype) and a.flags.c_contiguous


def scaled(u: float, low: float, high: float) -> float:
    """``low + (high - low) u``: how numpy's ``uniform(low, high)`` maps its double ``u`` in
    [0, 1) (so a ``u`` drawn by ``rng.random()`` gives ``rng.uniform(low, high)`` bit for bit)."""
    return low + (high - low) * u


def away(u: float, low: float, high: float, x0: float, gap: float) -> float:
    """:func:`uniform_away` from its draw ``u`` in [0, 1)."""
    left = max(0.0, min(x0 - gap, high) - low)
    right = max(0.0, high - max(x0 + gap, low))
    w = scaled(u, 0.0, left + right)
    return low + w if w < left else max(x0 + gap, low) + (w - left)


def uniform_away(rng: np.random.Generator, low: float, high: float, x0: float,
                 gap: float) -> float:
    """One draw, uniform on ``[low, high]`` minus ``(x0 - gap, x0 + gap)``.

    Non-empty whenever ``high - low > 2 gap`` (see :func:`check_goal_range`).
    """
    return away(rng.random(), low, high, x0, gap)


def checked_actions(actions: ArrayLike, num_envs: int, action_dim: int, single: bool = False
                    ) -> np.ndarray:
    """``actions`` for ``num_envs`` copies validated and clipped, as a (num_envs, action_dim)
    float64 array (see :meth:`ParticleTask.check_actions`, which this is)."""
    shape = (action_dim,) if single else (num_envs, action_dim)
    if (type(actions) is np.ndarray and actions.dtype.kind == "f"
            and actions.shape == shape):  # the usual case, checked in a few operations
        if _measure.ENABLED and actions.flags.c_contiguous and actions.dtype.char in "fd":
            a = np.empty((num_envs, action_dim))
            if not _measure.clip_actions(actions, a):
                raise ValueError(f"action must be finite, got {actions!r}")
            return a
        a = actions.astype(np.float64).reshape(num_envs, action_dim)
        if not np.isfinite(a).all():
            raise ValueError(f"action must be finite, got {actions!r}")
        return np.clip(a, -1.0, 1.0, out=a)
    try:
        raw = np.asarray(actions)
        if raw.dtype.kind not in "iuf":
            raise TypeError
        a = raw.astype(np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"action must be numeric, got {actions!r}") from None
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {actions!r}")
    return np.clip(a, -1.0, 1.0).reshape(num_envs, action_dim)


def task_arguments(task_class: type) -> dict[str, Any]:
    """The keyword arguments a task class declares (its ``__init__``'s, but ``num_envs``), with
    their defaults (``inspect.Parameter.empty`` for none)."""
    import inspect

    params = inspect.signature(task_class.__init__).parameters
    return {name: p.default for name, p in params.items()
            if name not in ("self", "num_envs")
            and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}


def check_task_kwargs(task_class: type, kwargs: dict[str, Any], also: tuple[str, ...] = ()
                      ) -> None:
    """ValueError naming each key of ``kwargs`` that ``task_class`` does not declare (nor
    ``also``), and listing the valid ones."""
    valid = [*task_arguments(task_class), *also]
    unknown = [k for k in kwargs if k not in valid]
    if unknown:
        name = getattr(task_class, "__name__", str(task_class))
        raise ValueError(f"{', '.join(map(repr, unknown))}: not an argument of {name}; it "
                         f"takes {', '.join(sorted(valid))}")
