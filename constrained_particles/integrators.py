"""Time integrators, chosen by name like ``scipy.integrate.solve_ivp(method=...)``.

Each integrator is a stateless function ``step(system, t, x, v, h) -> (x_new, v_new)`` that
calls ``system.acceleration(t, x, v)`` (forces and constraint forces re-evaluated at that
stage's state) as many times as it has stages. It must not modify its inputs.
Formulas are those of docs/physics.md; y = (x, v) and f(t, y) = (v, a(t, x, v)).

Which to use (figures from ``python -m verification energy``, 1e5 steps of 2 ms;
docs/integrators.md):

- ``rattle`` (:mod:`constrained_particles.rattle`) for long conservative runs with
  constraints: symplectic on rods and curved wires too, energy error bounded with no secular
  trend, ``C = 0`` to roundoff after every step; order 2.
- ``rk4`` for short accurate runs: order 4, the smallest error per step, but its energy error
  drifts slowly (not symplectic) and the constraints drift to the solver's feedback level.
- ``symplectic_euler`` only for unconstrained systems or straight wires (line wires, fixed
  points), where its energy error stays bounded. On curved constraints its multiplier comes from
  the old velocity plus feedback, and the energy drifts secularly, about linearly in h.
- ``implicit_euler`` (:mod:`constrained_particles.implicit`) for stiff systems at large steps:
  stable where the explicit methods diverge, but it dissipates energy.
- ``euler`` and ``midpoint`` are the textbook references (first and second order, drifting).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .system import ParticleSystem

State = tuple[np.ndarray, np.ndarray]
Integrator = Callable[["ParticleSystem", float, np.ndarray, np.ndarray, float], State]


def euler(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float) -> State:
    """Forward Euler, order 1: ``y += h f(t, y)``."""
    a = system.acceleration(t, x, v)
    return x + h * v, v + h * a


def midpoint(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float) -> State:
    """Explicit midpoint, order 2: ``y_m = y + h/2 f(t, y)``; ``y += h f(t + h/2, y_m)``."""
    a1 = system.acceleration(t, x, v)
    x_m = x + 0.5 * h * v
    v_m = v + 0.5 * h * a1
    a_m = system.acceleration(t + 0.5 * h, x_m, v_m)
    return x + h * v_m, v + h * a_m


def rk4(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float) -> State:
    """Classical Runge-Kutta, order 4; every stage starts from the step's initial state."""
    k1x, k1v = v, system.acceleration(t, x, v)
    k2x = v + 0.5 * h * k1v
    k2v = system.acceleration(t + 0.5 * h, x + 0.5 * h * k1x, k2x)
    k3x = v + 0.5 * h * k2v
    k3v = system.acceleration(t + 0.5 * h, x + 0.5 * h * k2x, k3x)
    k4x = v + h * k3v
    k4v = system.acceleration(t + h, x + h * k3x, k4x)
    return (x + (h / 6.0) * (k1x + 2.0 * k2x + 2.0 * k3x + k4x),
            v + (h / 6.0) * (k1v + 2.0 * k2v + 2.0 * k3v + k4v))


def symplectic_euler(system: ParticleSystem, t: float, x: np.ndarray, v: np.ndarray, h: float
                     ) -> State:
    """Semi-implicit (symplectic) Euler, order 1: ``v += h a(x, v)``; ``x += h v_new``.

    Bounded energy error for unconstrained systems and straight wires only: on curved
    constraints (rods, circular wires) the energy drifts secularly; use ``rattle`` there.
    """
    v_new = v + h * system.acceleration(t, x, v)
    return x + h * v_new, v_new


#: Integrators by name. ``implicit_euler`` and ``rattle`` register themselves here from their
#: own modules.
METHODS: dict[str, Integrator] = {
    "euler": euler,
    "midpoint": midpoint,
    "rk4": rk4,
    "symplectic_euler": symplectic_euler,
}

#: Theoretical order of accuracy of each method (checked by the verification suite).
ORDERS: dict[str, int] = {"euler": 1, "midpoint": 2, "rk4": 4, "symplectic_euler": 1}


def get_method(name: str) -> Integrator:
    """The integrator called ``name``; a ValueError lists the valid names otherwise."""
    try:
        return METHODS[name]
    except (KeyError, TypeError):
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {name!r}") from None
