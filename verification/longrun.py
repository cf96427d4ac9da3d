"""Long-run energy behaviour of every integrator: bounded oscillation or secular drift.

Each integrator in :data:`constrained_particles.METHODS` runs :data:`LONG_STEPS` fixed steps of
:data:`LONG_H` on three undamped, conservative systems (:data:`SYSTEMS`): the bead on a circular
wire released at 2 rad (:func:`constrained_particles.scenes.pendulum`, curved constraint), a
chain of rods hanging from a pivot (:func:`chain_of_rods`, chaotic, rods only) and a chain of
springs hanging from a fixed particle (:func:`spring_chain`, no constraint rows at all). The
energy error ``E(t) - E(0)`` (J) is measured after every step and summarised by:

- ``max_error``: ``max_t |E(t) - E(0)|`` over every step (J);
- ``trend``: the secular drift, the slope of the least-squares line through ``E(t) - E(0)``
  (sampled :data:`SAMPLES` times) times the run's duration (J);
- ``oscillation``: the peak-to-peak of ``E(t) - E(0)`` about that line (J), the bounded part;
- ``trend_ratio``: ``|trend| / oscillation``, small (well under 1) for a method whose energy error
  stays bounded, about 1 or more for one that drifts;
- ``max_constraint``: the largest constraint violation as a distance ``max_r |C_r| / |J_r|`` (m)
  over every step (on the 1 m pendulum this is ``|C|`` in m^2 to within 1e-13).

A run that raises :class:`~constrained_particles.SimulationDiverged` stops there and is marked.

>>> run = energy_run(chain_of_rods(), "rattle", 2e-3, 200, samples=50)
>>> run["max_error"] < 1e-4 and run["max_constraint"] < 1e-12
True
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from constrained_particles import (
    METHODS,
    DampedSpring,
    Gravity,
    ParticleSystem,
    Rod,
    SimulationDiverged,
    scenes,
)

from .properties import constraint_distance

LONG_STEPS = 100_000  #: steps per run of the full verification report
QUICK_STEPS = 3_000  #: steps per run of ``--quick``
LONG_H = 2e-3  #: step (s) of every run
SAMPLES = 2_000  #: recorded points per run (for the trend fit, the plot and the JSON)


def chain_of_rods(links: int = 3, link: float = 0.4, mass: float = 0.2) -> ParticleSystem:
    """``links`` rods of ``link`` m joining ``links + 1`` particles of ``mass`` kg, particle 0
    fixed at the origin, released from rest along +x under gravity (a chaotic multiple pendulum).

    >>> chain_of_rods().n
    4
    """
    if links < 1:
        raise ValueError(f"links must be >= 1, got {links}")
    s = ParticleSystem()
    s.add_particles(np.stack([np.arange(links + 1) * link, np.zeros(links + 1)], axis=1),
                    mass=mass, fixed=np.arange(links + 1) == 0)
    i = np.arange(links + 1)
    s.add(Gravity((0.0, -scenes.G)), Rod(i[:-1], i[1:]))
    return s


def spring_chain(count: int = 6, spacing: float = 0.2, ks: float = 40.0, mass: float = 0.1,
                 angle: float = 0.6) -> ParticleSystem:
    """``count`` particles of ``mass`` kg hanging from a fixed particle at the origin by undamped
    springs of ``ks`` N/m (rest length ``spacing`` m), released from rest as a straight line
    ``angle`` rad from the downward vertical, under gravity. No constraint rows: the fixed
    particle has inverse mass 0.

    From 0.6 rad the springs stay between 0.077 and 0.56 m long; released horizontally the chain
    whips, its springs fold down to 1.3 cm, near the kink of the spring potential at zero length,
    and every integrator's energy error jumps there (a test of that kink, not of the method).

    >>> spring_chain().constraints
    []
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    s = ParticleSystem()
    direction = np.array([np.sin(angle), -np.cos(angle)])
    s.add_particles(np.arange(count + 1)[:, None] * spacing * direction, mass=mass,
                    fixed=np.arange(count + 1) == 0)
    i = np.arange(count + 1)
    s.add(Gravity((0.0, -scenes.G)), DampedSpring(i[:-1], i[1:], rest=spacing, ks=ks))
    return s


#: The long-run systems by name, with what they test.
SYSTEMS: dict[str, tuple[Callable[[], ParticleSystem], str]] = {
    "pendulum": (lambda: scenes.pendulum(angle=2.0),
                 "bead on a 1 m circular wire, 1 kg, released from rest at 2 rad"),
    "chain_of_rods": (chain_of_rods, "3 rods of 0.4 m, 0.2 kg particles, pivot fixed, released "
                                     "horizontally"),
    "spring_chain": (spring_chain, "6 particles of 0.1 kg on springs of 40 N/m (0.2 m), hanging "
                                   "from a fixed particle, released at 0.6 rad; no constraints"),
}


def energy_run(system: ParticleSystem, method: str, h: float, steps: int,
               samples: int = SAMPLES) -> dict:
    """Step a copy of ``system`` ``steps`` times by ``h`` (s) with ``method``; the energy error
    and constraint figures of the module docstring, with ``t`` (s) and ``energy_error`` (J) at
    about ``samples`` evenly spaced steps."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    s = system.copy()
    e0 = s.energy()
    every = max(1, int(steps) // max(1, int(samples)))
    t, err = [], []
    worst, worst_c, diverged = 0.0, constraint_distance(s), None
    start = time.process_time()
    for k in range(1, int(steps) + 1):
        try:
            s.step(h, method=method)
        except SimulationDiverged:
            diverged = s.t
            break
        e = s.energy() - e0
        worst = max(worst, abs(e))
        worst_c = max(worst_c, constraint_distance(s))
        if k % every == 0:
            t.append(s.t)
            err.append(e)
    cpu = time.process_time() - start
    trend = oscillation = float("nan")
    if len(t) >= 3:
        slope, intercept = np.polyfit(t, err, 1)
        trend = float(slope * (t[-1] - t[0]))
        oscillation = float(np.ptp(np.array(err) - (slope * np.array(t) + intercept)))
    ratio = abs(trend) / oscillation if oscillation > 0 else float("nan")
    return {"method": method, "h": h, "steps": int(steps), "e0": e0, "t": t,
            "energy_error": err, "max_error": worst, "trend": trend,
            "oscillation": oscillation, "trend_ratio": ratio, "max_constraint": worst_c,
            "diverged_at": diverged, "cpu": cpu, "constrained": bool(system.constraints)}


def long_runs(steps: int = LONG_STEPS, h: float = LONG_H, systems: Sequence[str] | None = None,
              methods: Sequence[str] | None = None, progress: bool = False) -> dict:
    """``{system: {method: energy_run(...)}}`` for every named system and integrator."""
    names = list(SYSTEMS) if systems is None else list(systems)
    for name in names:
        if name not in SYSTEMS:
            raise ValueError(f"systems must be among {sorted(SYSTEMS)}, got {name!r}")
    methods = sorted(METHODS) if methods is None else list(methods)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(names) * len(methods), desc="long runs", unit="run")
    out: dict = {}
    try:
        for name in names:
            system = SYSTEMS[name][0]()
            out[name] = {}
            for method in methods:
                out[name][method] = energy_run(system, method, h, steps)
                if bar is not None:
                    bar.update()
    finally:
        if bar is not None:
            bar.close()
    return out


def long_run_table(results: dict) -> str:
    """A Markdown table: one row per system and method with the figures of the module
    docstring."""
    lines = ["| system | method | max abs(E - E0) (J) | secular trend (J) | oscillation (J) | "
             "trend / oscillation | max constraint distance (m) |",
             "|---|---|---|---|---|---|---|"]
    for name, per_method in results.items():
        for method, r in per_method.items():
            if r["diverged_at"] is not None:
                lines.append(f"| {name} | {method} | diverged at t = {r['diverged_at']:.2f} s "
                             "| | | | |")
                continue
            distance = f"{r['max_constraint']:.1e}" if r["constrained"] else "-"
            lines.append(f"| {name} | {method} | {r['max_error']:.2e} | {r['trend']:+.2e} | "
                         f"{r['oscillation']:.2e} | {r['trend_ratio']:.3g} | {distance} |")
    return "\n".join(lines)


def plot_long_runs(results: dict, path) -> None:
    """``|E(t) - E(0)|`` against t, one panel per system, one curve per integrator."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    methods = sorted({m for per in results.values() for m in per})
    cmap = plt.get_cmap("tab10")
    colours = {m: cmap(k) for k, m in enumerate(methods)}
    fig, axes = plt.subplots(1, len(names), figsize=(5.4 * len(names), 4.6), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        e0 = abs(next(iter(results[name].values()))["e0"])
        for method, r in results[name].items():
            y = np.maximum(np.abs(np.array(r["energy_error"], float)), 1e-16)
            label = f"{method}: trend/osc. {r['trend_ratio']:.2g}"
            if r["diverged_at"] is not None:
                label = f"{method} (diverged at {r['diverged_at']:.1f} s)"
            ax.semilogy(r["t"], y, color=colours[method], lw=1.0, label=label)
        ax.set_ylim(top=max(10 * e0, 1.0))
        ax.set_xlabel("time t (s)")
        ax.set_ylabel("|E(t) - E(0)| (J)")
        ax.set_title(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    first = next(iter(next(iter(results.values())).values()))
    fig.suptitle(f"Long-run energy error, h = {first['h'] * 1e3:g} ms, {first['steps']} steps")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
