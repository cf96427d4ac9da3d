"""The reward both tasks share: a time cost, potential-based shaping and a success bonus.

Every env step pays

    r = k (Phi(s) - Phi(s')) - TIME_COST + SUCCESS_BONUS * success - (task penalties)

where ``Phi >= 0`` is a task's *cost to go* (metres of distance plus m/s of speed, plus whatever
else must be zero at success), ``s`` and ``s'`` the states before and after the step, and ``k``
(:attr:`ShapedTask.shaping_scale`) converts it into reward. The shaping term is potential-based
(Ng, Harada & Russell 1999, with the undiscounted potential difference): over an episode it sums
to ``k (Phi(s_0) - Phi(s_T))``, so it cannot be farmed by circling, and for an agent discounting
with gamma it equals Ng's policy-invariant shaping plus a dense cost ``k (1 - gamma) Phi(s')`` per
step. The optimal behaviour is therefore set by the time cost and the success bonus alone: finish
(reach the goal and come to rest there) as fast as possible. Any state that is not a success,
including resting near the goal or moving about on it, costs ``TIME_COST`` every step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from . import _measure

_NONE = np.zeros(0)  #: no penalties (for the compiled reward)

#: Reward on the step that completes the success test.
SUCCESS_BONUS = 10.0
#: Reward subtracted on every step (the episode's clock).
TIME_COST = 0.1


class ShapedTask:
    """Mixin for a :class:`~envs.base.ParticleTask`: keeps each copy's last potential.

    Subclasses define :meth:`potential` (per copy, from the measures of ``measure()``) and
    :meth:`penalties`. The potential of a copy's start is recorded whenever a start is written
    (``reset``, autoreset) or a state restored (``set_state``), so the first step's shaping term
    is right.
    """

    #: Reward per unit of potential (1/m, s/m).
    shaping_scale: float = 10.0
    #: The cost of one step of playing on (the time cost): see
    #: ``ParticleTask.divergence_penalty``.
    step_cost: float = TIME_COST
    num_envs: int
    measure: Callable[..., dict[str, np.ndarray]]  # ParticleTask.measure
    _paths: dict[str, bool]  # ParticleTask._paths

    def _compiled_paths(self) -> dict[str, bool]:
        """``ParticleTask._compiled_paths`` with ``penalties``: whether :meth:`penalties` is
        redefined (the reward subtracts penalties only then: x - 0 is x)."""
        paths = super()._compiled_paths()  # type: ignore[misc]
        paths["penalties"] = type(self).penalties is not ShapedTask.penalties
        return paths

    def potential(self, m: dict[str, Any]) -> float | np.ndarray:
        """The cost to go ``Phi`` (num_envs,) >= 0 from measures ``m``; 0 at the goal at rest.
        Written with arithmetic alone, so that it also takes one copy's measures as numbers
        (:meth:`reward_one`) and gives the same bits."""
        raise NotImplementedError

    def penalties(self, m: dict[str, Any]) -> float | np.ndarray:
        """Non-negative per-step penalties subtracted from the reward: (num_envs,) for measures
        ``m`` of arrays, a number for one copy's measures as numbers (see :meth:`reward_one`);
        none here."""
        distance = m["distance"]
        return 0.0 if isinstance(distance, float) else np.zeros(np.shape(distance))

    def _phi(self) -> np.ndarray:
        if getattr(self, "_last_potential", None) is None:
            self._last_potential = np.zeros(self.num_envs)
        return self._last_potential

    def _record_potential(self, envs: Any) -> None:
        envs = np.asarray(envs, dtype=np.int64)
        if envs.size:
            self._phi()[envs] = self.potential(self.measure())[envs]

    def write_starts(self, envs: Sequence[int], x: np.ndarray, v: np.ndarray,
                     goal: np.ndarray) -> None:
        super().write_starts(envs, x, v, goal)  # type: ignore[misc]
        self._record_potential(envs)

    def set_state(self, i: int, state: dict[str, Any]) -> None:
        super().set_state(i, state)  # type: ignore[misc]
        self._record_potential([i])

    def reward(self, m: dict[str, np.ndarray]) -> np.ndarray:
        """``k (Phi_before - Phi_after) - TIME_COST - penalties + SUCCESS_BONUS * success``
        per copy (called once per env step, after the physics)."""
        phi = self.potential(m)
        penalized = self._paths["penalties"]  # (else none: x - 0 is x)
        before = self._phi()
        success = m["is_success"]
        if (_measure.ENABLED and type(phi) is np.ndarray and phi.dtype == np.float64
                and phi.shape == before.shape == success.shape and success.dtype == np.bool_):
            # one compiled pass, the same operations in the same order
            pen = np.asarray(self.penalties(m), dtype=np.float64) if penalized else _NONE
            if pen.shape not in (before.shape, _NONE.shape):
                pen = np.broadcast_to(pen, before.shape).copy()
            r = np.empty_like(before)
            _measure.shaped_reward(before, np.ascontiguousarray(phi), success,
                                   np.ascontiguousarray(pen), float(self.shaping_scale),
                                   TIME_COST, SUCCESS_BONUS, r)
            return r
        r = before - phi
        r *= self.shaping_scale
        self._last_potential = phi.copy()
        r -= TIME_COST
        if penalized:
            r -= self.penalties(m)
        r += SUCCESS_BONUS * success
        return r

    def reward_one(self, m: dict[str, np.ndarray], values: dict[str, Any]) -> float:
        """:meth:`reward` of a task with one copy, from its measures as Python numbers
        (``values``; ``m`` holds the same as arrays). The same formula in the same order on
        IEEE doubles, so the same bits as :meth:`reward`, without a dozen array operations
        on arrays of one element."""
        phi = self.potential(values)
        last = self._phi()
        before = float(last[0])
        last[0] = phi
        return float(self.shaping_scale * (before - phi) - TIME_COST - self.penalties(values)
                     + SUCCESS_BONUS * values["is_success"])
