"""Measured convergence order of every integrator, against an exact or a reference solution.

For each case (a system and a duration) and each integrator in
:data:`constrained_particles.METHODS`, the system is stepped with a sequence of steps
``h_k = h_0 / 2^k``; the error is the largest particle position error (m) over ten checkpoints
evenly spread over the run, and the observed order is the least-squares slope of
``log(error)`` against ``log(h)`` (:func:`~verification.properties.fit_slope`). The reference is
the exact elliptic-function solution for the pendulum and, otherwise,
``scipy.integrate.solve_ivp(method="DOP853", rtol=1e-12)`` of the same ODE
``y = (x, v)``, ``y' = (v, system.acceleration(t, x, v))`` on a copy of the system.

The sequences of h start where the error is already in the asymptotic range and stop well above
round-off and the multiplier solve's tolerance (tightened to 1e-13 for these runs): they depend
on the theoretical order (:data:`constrained_particles.ORDERS`), rk4 needing the largest steps.

>>> result = measure_order(CASES["pendulum"], "midpoint", quick=True)
>>> abs(result.order - 2) < 0.2
True
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipj, ellipk

from constrained_particles import (
    METHODS,
    ORDERS,
    Gravity,
    ParticleSystem,
    SimulationDiverged,
    scenes,
)

from .properties import fit_slope
from .strategies import random_system

#: Multiplier-solve tolerance for the order runs, so it never floors the measured errors.
SOLVE_TOL = 1e-13
#: Seed of the generated case: the first seed (counting from 0) whose system, with gravity, has
#: at least six particles, every constraint kind, springs and angular springs, and whose angular
#: springs stay well away from their +-pi wrap over the run (a kink in the potential). It has 9
#: particles, 2 rods, a circular wire, 2 line wires, a horizontal wire, a fixed point, 5 springs
#: and an angular spring.
RANDOM_SEED = 85


@dataclass
class Case:
    """A system to measure orders on, the duration (s) and optionally its exact solution.

    ``exact(times)`` returns positions (len(times), n, 2) in metres.
    """

    name: str
    build: Callable[[], ParticleSystem]
    duration: float = 1.0
    exact: Callable[[np.ndarray], np.ndarray] | None = None
    description: str = ""


def pendulum_exact(length: float, angle: float, g: float) -> Callable[[np.ndarray], np.ndarray]:
    """Exact motion of a point pendulum (``length`` m) released from rest at ``angle`` rad from
    the downward vertical under gravity ``g`` (m/s^2), pivot at the origin.

    ``sin(theta/2) = k sn(K(m) - omega t | m)`` with ``k = sin(angle/2)``, ``m = k^2``,
    ``omega = sqrt(g/length)``. Returns ``times -> positions`` of shape (len(times), 1, 2).

    >>> xy = pendulum_exact(1.0, 0.5, 9.81)(np.array([0.0]))
    >>> np.allclose(xy[0, 0], [np.sin(0.5), -np.cos(0.5)])
    True
    """
    if not (length > 0 and 0 < abs(angle) < np.pi and g > 0):
        raise ValueError(f"length, g must be > 0 and 0 < |angle| < pi, got {length}, {angle}, {g}")
    k = np.sin(abs(angle) / 2)
    m = k * k
    K, omega = ellipk(m), np.sqrt(g / length)

    def positions(times: np.ndarray) -> np.ndarray:
        sn = ellipj(K - omega * np.asarray(times, float), m)[0]
        theta = np.sign(angle) * 2 * np.arcsin(k * sn)
        return np.stack([length * np.sin(theta), -length * np.cos(theta)], axis=-1)[:, None, :]

    return positions


def _pendulum_case() -> Case:
    length, angle = 1.0, 0.5
    return Case("pendulum", lambda: scenes.pendulum(length=length, angle=angle), 1.0,
                pendulum_exact(length, angle, scenes.G),
                f"particle on a circular wire (radius {length} m) released at {angle} rad; "
                "exact elliptic-function solution")


CASES: dict[str, Case] = {
    "pendulum": _pendulum_case(),
    "slider_crank": Case("slider_crank", scenes.wire_mixture, 1.0, None,
                         "scenes.wire_mixture: circular wire + horizontal wire + rod, gravity; "
                         "DOP853 reference"),
    "random_system": Case("random_system", lambda: random_system(RANDOM_SEED, gravity=True), 1.0,
                          None, f"verification.strategies.random_system({RANDOM_SEED}, "
                          "gravity=True); DOP853 reference"),
}


def default_steps(method: str, quick: bool = False) -> tuple[float, ...]:
    """Steps h (s) for ``method``: 0.1 s / 2^k, larger for higher theoretical order.

    >>> default_steps("rk4")
    (0.05, 0.025, 0.0125, 0.00625)
    """
    first = {1: 4, 2: 3, 4: 1}.get(ORDERS.get(method, 1), 4)
    count = 3 if quick else 4
    return tuple(0.1 / 2 ** (first + k) for k in range(count))


def _copy_for_orders(system: ParticleSystem) -> ParticleSystem:
    s = system.copy()
    s.tol = SOLVE_TOL  # the system rebuilds its solver with the new tolerance
    return s


def checkpoints(duration: float, count: int = 10) -> np.ndarray:
    """``count`` evenly spaced times in (0, duration], in seconds."""
    return duration * np.arange(1, count + 1) / count


def reference_positions(system: ParticleSystem, times: Sequence[float], rtol: float = 1e-12,
                        atol: float = 1e-12) -> np.ndarray:
    """Positions (len(times), n, 2) in metres from ``solve_ivp(method="DOP853")`` of the system's
    ODE ``y = (x, v)``, ``y' = (v, acceleration(t, x, v))``, started at the system's state."""
    s = _copy_for_orders(system)
    n = s.n

    def f(t: float, y: np.ndarray) -> np.ndarray:
        x, v = y[: 2 * n].reshape(n, 2), y[2 * n:].reshape(n, 2)
        return np.concatenate([y[2 * n:], s.acceleration(t, x, v).ravel()])

    times = np.asarray(times, float)
    y0 = np.concatenate([s.x.ravel(), s.v.ravel()])
    sol = solve_ivp(f, (s.t, times[-1]), y0, method="DOP853", rtol=rtol, atol=atol, t_eval=times)
    if not sol.success:
        raise RuntimeError(f"reference solve failed: {sol.message}")
    return sol.y[: 2 * n].T.reshape(len(times), n, 2)


def run_positions(system: ParticleSystem, method: str, h: float, times: np.ndarray,
                  project: bool = False) -> np.ndarray:
    """Positions (len(times), n, 2) at ``times`` from fixed steps ``h`` (s) of ``method``.

    Each checkpoint interval must be a whole number of steps. Raises SimulationDiverged.
    """
    s = _copy_for_orders(system)
    out = np.empty((len(times), s.n, 2))
    for k, steps in enumerate(steps_between(times, s.t, h)):
        for _ in range(steps):
            s.step(h, method=method, project=project)
        out[k] = s.x
    return out


def steps_between(times: Sequence[float], start: float, h: float) -> list[int]:
    """Whole numbers of steps ``h`` (s) from ``start`` to each checkpoint in ``times`` (s) in turn.

    Raises ValueError if ``h`` does not divide a checkpoint interval.
    """
    out, t_prev = [], start
    for t in times:
        steps = (t - t_prev) / h
        if abs(steps - round(steps)) > 1e-9 * max(steps, 1.0):
            raise ValueError(f"h = {h} does not divide the checkpoint interval {t - t_prev}")
        out.append(int(round(steps)))
        t_prev = t
    return out


@dataclass
class OrderResult:
    """Errors (m) and CPU times (s) per step h (s), and the fitted order, of one method on one
    case. A diverged run has error ``inf`` and is left out of the fit."""

    case: str
    method: str
    theory: int | None
    hs: list[float]
    errors: list[float]
    cpu: list[float]
    order: float = float("nan")
    local: list[float] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def reference_for(case: Case, times: np.ndarray) -> np.ndarray:
    """The case's reference positions at ``times``: exact if known, else DOP853."""
    if case.exact is not None:
        return case.exact(times)
    return reference_positions(case.build(), times)


def measure_order(case: Case, method: str, hs: Sequence[float] | None = None,
                  quick: bool = False, reference: np.ndarray | None = None,
                  progress: Callable[[], None] | None = None) -> OrderResult:
    """Errors against the reference for each h in ``hs`` (default :func:`default_steps`) and the
    fitted order. ``reference`` (positions at :func:`checkpoints`) is computed if not given."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    hs = tuple(default_steps(method, quick) if hs is None else hs)
    duration = case.duration / 2 if quick else case.duration
    times = checkpoints(duration)
    ref = reference_for(case, times) if reference is None else reference
    system = case.build()
    errors, cpu = [], []
    for h in hs:
        start = time.process_time()
        try:
            err = float(np.max(np.abs(run_positions(system, method, h, times) - ref)))
        except SimulationDiverged:
            err = float("inf")
        cpu.append(time.process_time() - start)
        errors.append(err)
        if progress is not None:
            progress()
    finite = [(h, e) for h, e in zip(hs, errors, strict=True) if np.isfinite(e) and e > 0]
    order = fit_slope(*zip(*finite, strict=True)) if len(finite) >= 2 else float("nan")
    local = [float(np.log(errors[k] / errors[k + 1]) / np.log(hs[k] / hs[k + 1]))
             for k in range(len(hs) - 1)]
    return OrderResult(case.name, method, ORDERS.get(method), list(hs), errors, cpu, order, local)


def measure_orders(cases: Sequence[str] | None = None, methods: Sequence[str] | None = None,
                   quick: bool = False, progress: bool = False
                   ) -> dict[str, dict[str, OrderResult]]:
    """Every method on every case: ``{case: {method: OrderResult}}``.

    ``progress`` shows a tqdm bar over the runs.
    """
    cases = list(CASES) if cases is None else list(cases)
    methods = sorted(METHODS) if methods is None else list(methods)
    for name in cases:
        if name not in CASES:
            raise ValueError(f"cases must be among {sorted(CASES)}, got {name!r}")
    bar = None
    if progress:
        from tqdm import tqdm

        total = sum(len(default_steps(m, quick)) for m in methods) * len(cases)
        bar = tqdm(total=total, desc="orders", unit="run")
    out: dict[str, dict[str, OrderResult]] = {}
    try:
        for name in cases:
            case = CASES[name]
            times = checkpoints(case.duration / 2 if quick else case.duration)
            ref = reference_for(case, times)
            out[name] = {m: measure_order(case, m, quick=quick, reference=ref,
                                          progress=bar.update if bar else None) for m in methods}
    finally:
        if bar is not None:
            bar.close()
    return out


def orders_table(results: dict[str, dict[str, OrderResult]]) -> str:
    """A Markdown table: one row per case and method with errors per h and the fitted order."""
    lines = ["| case | method | theory | h (s) | max position error (m) | observed order |",
             "|---|---|---|---|---|---|"]
    for name, per_method in results.items():
        for method, r in per_method.items():
            hs = ", ".join(f"{h:.3g}" for h in r.hs)
            errs = ", ".join(f"{e:.2e}" for e in r.errors)
            ok = ("" if r.theory is None or abs(r.order - r.theory) <= ORDER_TOLERANCE
                  else " (off)")
            lines.append(f"| {name} | {method} | {r.theory if r.theory is not None else '?'} | "
                         f"{hs} | {errs} | {r.order:.2f}{ok} |")
    return "\n".join(lines)


#: How far (in order) an observed order may lie from theory and still agree with it.
ORDER_TOLERANCE = 0.2


def orders_verdict(results: dict[str, dict[str, OrderResult]]) -> tuple[str, bool]:
    """One line saying how many observed orders agree with theory (within
    :data:`ORDER_TOLERANCE`), naming those that do not; and whether all do."""
    checked = [(name, m, r) for name, per in results.items() for m, r in per.items()
               if r.theory is not None]
    off = [f"{name}/{m} {r.order:.2f} (theory {r.theory})" for name, m, r in checked
           if not abs(r.order - r.theory) <= ORDER_TOLERANCE]
    unknown = sum(r.theory is None for per in results.values() for r in per.values())
    extra = f"; {unknown} without a theoretical order" if unknown else ""
    if off:
        return (f"verdict: {len(off)} of {len(checked)} observed orders differ from theory by "
                f"more than {ORDER_TOLERANCE}: {', '.join(off)}{extra}"), False
    return (f"verdict: all {len(checked)} observed orders agree with theory within "
            f"{ORDER_TOLERANCE}{extra}"), True


def orders_summary(results: dict[str, dict[str, OrderResult]]) -> dict[str, dict[str, float]]:
    """``{case: {method: observed order}}``, rounded to 3 decimals."""
    return {name: {m: round(r.order, 3) for m, r in per.items()} for name, per in results.items()}


def gravity_of(system: ParticleSystem) -> np.ndarray:
    """The summed uniform gravity (m/s^2) of a system's Gravity blocks acting on everything."""
    return sum((f.g for f in system.forces if isinstance(f, Gravity) and f.particles is None),
               np.zeros(2))
