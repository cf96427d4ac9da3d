"""The verification report: measured orders, the pymunk cross-check, energy and constraint drift,
and the cloth experiments of docs/notes_on_the_report.md with numbers. Writes Markdown, JSON and
PNG plots.

Experiments (all SI units; every integrator in :data:`constrained_particles.METHODS`):

- **orders**: :func:`verification.orders.measure_orders` (convergence plot, table);
- **pymunk**: :func:`verification.pymunk_check.compare_all` (table, work-precision plot);
- **long-run energy**: :func:`verification.longrun.long_runs`, every integrator for
  :data:`~verification.longrun.LONG_STEPS` steps (quick:
  :data:`~verification.longrun.QUICK_STEPS`) on a pendulum on a circular wire, a chain of rods
  and a spring chain: maximal energy error, secular trend against bounded oscillation, constraint
  distance (table, plot);
- **energy drift**: the slider-crank (undamped, conservative) for :data:`DRIFT_SECONDS` s at
  ``h = 5 ms``: ``|E(t) - E(0)|`` over time, relative to the largest kinetic energy of the
  accurate (rk4) run;
- **constraint drift**: the same runs' largest constraint violation expressed as a distance,
  ``max_r |C_r| / |J_r|`` (m), with and without projection after every step;
- **cloth rise** (:func:`section_v`; the original program's section V experiment, see
  docs/notes_on_the_report.md): the default cloth (:func:`constrained_particles.scenes.cloth`)
  pushed into its wall by :data:`PUSH` N per top particle, ``h = 1 ms``: the highest any
  particle gets above the wire, and how far the top row leaves the wire;
- **spring constants** (:func:`section_via`; the original program's section VI.A
  experiment): the same cloth, released from rest under gravity with spring constants
  ``ks`` in {1, 10} N/m and damping ``kd`` in {1, 10} N s/m: the highest rise above the wire
  and the settling time, defined as the last time any particle is farther than
  :data:`SETTLE_TOL` m from the static equilibrium (found by minimising the potential energy
  with the top row on the wire); ">T" if it has not settled by the end of the run. rk4 with a
  step well inside its stability region for the stiffest spring mode (at most 1 ms).
"""

from __future__ import annotations

import inspect
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize

from constrained_particles import (
    METHODS,
    ORDERS,
    DampedSpring,
    HorizontalWire,
    ParticleSystem,
    SimulationDiverged,
    scenes,
)

from . import longrun, pymunk_check
from . import orders as orders_mod
from .properties import constraint_distance

DRIFT_SECONDS = 10.0  #: duration (s) of the energy and constraint drift runs (quick: 2 s)
DRIFT_H = 5e-3  #: step (s) of the drift runs
SECTION_V_H = 1e-3  #: the step (s) of the cloth-rise experiment
SECTION_V_SECONDS = 3.0  #: duration (s) of the cloth-rise experiment (quick: 1 s)
PUSH = 0.3  #: horizontal force (N) on each top-row particle in the cloth-rise experiment
SECTION_VIA_SECONDS = 5.0  #: duration (s) of the spring-constants experiment (quick: 1 s)
SETTLE_TOL = 0.01  #: settling tolerance (m): a tenth of the cloth's particle spacing
GAINS = ((1.0, 1.0), (1.0, 10.0), (10.0, 1.0), (10.0, 10.0))  #: (ks N/m, kd N s/m) of VI.A


def _bar(total: int, desc: str, progress: bool) -> Any:
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="run")


def drift_runs(seconds: float, h: float = DRIFT_H, progress: bool = False) -> dict:
    """Energy error and constraint distance over time on the slider-crank, per integrator,
    without and with projection. A diverged run stops at its last good step.

    Energy errors are relative to one scale for every run, the largest kinetic energy of the
    plain rk4 run (accurate to 1e-7 here), so a run that blows up does not shrink its own error.
    """
    out: dict = {}
    bar = _bar(2 * len(METHODS), "drift", progress)
    steps = int(round(seconds / h))
    every = max(1, steps // 400)
    for method in sorted(METHODS):
        out[method] = {}
        for project in (False, True):
            s = scenes.wire_mixture()
            e0 = s.energy()
            t, energy, drift, kinetic = [], [], [], s.kinetic_energy()
            diverged = None
            for k in range(1, steps + 1):
                try:
                    s.step(h, method=method, project=project)
                except SimulationDiverged:
                    diverged = s.t
                    break
                kinetic = max(kinetic, s.kinetic_energy())
                if k % every == 0:
                    t.append(s.t)
                    energy.append(abs(s.energy() - e0))
                    drift.append(constraint_distance(s))
            out[method]["projected" if project else "plain"] = {
                "t": t, "energy_error_joules": energy, "kinetic_max": kinetic,
                "constraint_distance": drift, "diverged_at": diverged}
            if bar is not None:
                bar.update()
    if bar is not None:
        bar.close()
    calm = [r for runs in out.values() for r in runs.values() if r["diverged_at"] is None]
    scale = (out["rk4"]["plain"]["kinetic_max"] if "rk4" in out
             else max((r["kinetic_max"] for r in calm), default=1.0))
    for runs in out.values():
        for r in runs.values():
            r["energy_error"] = (np.array(r["energy_error_joules"]) / scale).tolist()
    return out


def _cloth_run(system: ParticleSystem, method: str, h: float, seconds: float,
               record: Callable[[ParticleSystem], None]) -> float | None:
    """Step ``system`` in place, calling ``record`` after every step; returns the divergence
    time or None."""
    for _ in range(int(round(seconds / h))):
        try:
            system.step(h, method=method)
        except SimulationDiverged:
            return system.t
        record(system)
    return None


def _wire(system: ParticleSystem) -> tuple[np.ndarray, float]:
    wire = next(c for c in system.constraints if isinstance(c, HorizontalWire))
    return wire.particles, float(wire.height[0])


def section_v(seconds: float = SECTION_V_SECONDS, h: float = SECTION_V_H, push: float = PUSH,
              progress: bool = False) -> dict:
    """The cloth-rise experiment (the original program's section V, docs/notes_on_the_report.md)
    with numbers: for each integrator, the default
    cloth pushed into its wall; the highest point of the cloth relative to the wire (m) and the
    top row's largest distance from the wire (m), with their time series."""
    out: dict = {}
    bar = _bar(len(METHODS), "cloth rise", progress)
    for method in sorted(METHODS):
        s = scenes.cloth(push=push)
        top, height = _wire(s)
        rest = np.setdiff1d(np.arange(s.n), top)
        series: dict[str, list] = {"t": [], "rise": [], "wire_gap": []}

        def record(sys: ParticleSystem, series=series, top=top, rest=rest, height=height) -> None:
            series["t"].append(sys.t)
            series["rise"].append(float(sys.x[rest, 1].max() - height))
            series["wire_gap"].append(float(np.abs(sys.x[top, 1] - height).max()))

        start = time.process_time()
        diverged = _cloth_run(s, method, h, seconds, record)
        out[method] = {"max_rise": max(series["rise"], default=float("nan")),
                       "max_wire_gap": max(series["wire_gap"], default=float("nan")),
                       "diverged_at": diverged, "cpu": time.process_time() - start,
                       "series": {k: v[::10] for k, v in series.items()}}
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    return out


def stable_step(system: ParticleSystem, h_max: float = 1e-3, safety: float = 0.7) -> float:
    """A step (s) inside rk4's stability region for the system's springs at their current
    directions: ``safety * 2.78 / (rho_D + sqrt(rho_K))`` with ``rho`` the spectral radii of
    ``M^-1 D`` and ``M^-1 K`` (D, K the springs' damping and stiffness matrices, dense, so for
    systems of a few hundred particles), capped at ``h_max``. 2.78 is where rk4's stability
    region meets the negative real axis."""
    n2 = 2 * system.n
    K, D = np.zeros((n2, n2)), np.zeros((n2, n2))
    for f in system.forces:
        if isinstance(f, DampedSpring):
            l = system.x[f.i] - system.x[f.j]
            u = l / np.maximum(np.linalg.norm(l, axis=1), 1e-300)[:, None]
            for i, j, ui, ks, kd in zip(f.i, f.j, u, f.ks, f.kd, strict=True):
                block = np.outer(ui, ui)
                for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
                    K[2 * a:2 * a + 2, 2 * b:2 * b + 2] += sign * ks * block
                    D[2 * a:2 * a + 2, 2 * b:2 * b + 2] += sign * kd * block
    w = np.sqrt(np.repeat(system.inv_mass, 2))
    rho_k = float(np.linalg.eigvalsh(w[:, None] * K * w[None, :])[-1]) if n2 else 0.0
    rho_d = float(np.linalg.eigvalsh(w[:, None] * D * w[None, :])[-1]) if n2 else 0.0
    radius = rho_d + np.sqrt(max(rho_k, 0.0))
    return float(min(h_max, safety * 2.78 / radius)) if radius > 0 else float(h_max)


def static_equilibrium(system: ParticleSystem) -> np.ndarray:
    """Positions (n, 2) minimising the potential energy with every horizontal-wire particle on
    its wire (the other constraints are not supported); fixed particles stay put."""
    top, height = _wire(system)
    free = system.inv_mass > 0
    on_wire = np.zeros(system.n, bool)
    on_wire[top] = True
    mask = np.stack([free, free & ~on_wire], axis=1)  # x free; y free unless on the wire
    x0 = system.x.copy()
    x0[top, 1] = height
    zero = np.zeros_like(x0)

    def energy(q: np.ndarray) -> tuple[float, np.ndarray]:
        x = x0.copy()
        x[mask] = q
        F = system.applied_forces(x, zero)
        return sum(f.potential(x, system.mass) for f in system.forces), -F[mask]

    res = minimize(energy, x0[mask], jac=True, method="L-BFGS-B",
                   options={"maxiter": 20000, "gtol": 1e-12, "ftol": 1e-15})
    x = x0.copy()
    x[mask] = res.x
    return x


def section_via(seconds: float = SECTION_VIA_SECONDS, progress: bool = False) -> dict:
    """The spring-constants experiment (the original program's section VI.A,
    docs/notes_on_the_report.md) with numbers, for each (ks, kd) in :data:`GAINS`."""
    out: dict = {}
    bar = _bar(len(GAINS), "spring constants", progress)
    for ks, kd in GAINS:
        s = scenes.cloth(ks=ks, kd=kd, push=0.0)
        top, height = _wire(s)
        rest = np.setdiff1d(np.arange(s.n), top)
        x_eq = static_equilibrium(s)
        h = stable_step(s)
        series: dict[str, list] = {"t": [], "rise": [], "distance": []}

        def record(sys: ParticleSystem, series=series, rest=rest, height=height, x_eq=x_eq
                   ) -> None:
            series["t"].append(sys.t)
            series["rise"].append(float(sys.x[rest, 1].max() - height))
            series["distance"].append(float(np.linalg.norm(sys.x - x_eq, axis=1).max()))

        start = time.process_time()
        diverged = _cloth_run(s, "rk4", h, seconds, record)
        far = np.flatnonzero(np.array(series["distance"]) > SETTLE_TOL)
        if diverged is not None or (len(far) and far[-1] == len(series["t"]) - 1):
            settling = None
        else:
            settling = float(series["t"][far[-1]]) if len(far) else 0.0
        stride = max(1, len(series["t"]) // 500)
        out[f"ks={ks:g},kd={kd:g}"] = {
            "ks": ks, "kd": kd, "h": h, "max_rise": max(series["rise"]),
            "damping_ratio": kd / (2 * np.sqrt(ks * float(s.mass.max()) / 2)),
            "settling_time": settling, "duration": seconds, "diverged_at": diverged,
            "equilibrium_sag": float(height - x_eq[:, 1].min()),
            "final_distance": series["distance"][-1], "cpu": time.process_time() - start,
            "series": {k: v[::stride] for k, v in series.items()}}
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    return out


# ---------------------------------------------------------------------------------- plots
def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt



def _colours(methods: list[str]) -> dict[str, Any]:
    cmap = _pyplot().get_cmap("tab10")
    return {m: cmap(k) for k, m in enumerate(methods)}


def plot_convergence(results: dict, path: Path) -> None:
    """Log-log error against h per integrator, one panel per case, with dotted reference slopes
    of each method's theoretical order."""
    plt = _pyplot()
    from matplotlib.ticker import NullFormatter

    cases = list(results)
    methods = sorted({m for per in results.values() for m in per})
    colours = _colours(methods)
    fig, axes = plt.subplots(1, len(cases), figsize=(5.2 * len(cases), 4.6), squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        for method, r in results[case].items():
            hs, errs = np.array(r.hs), np.array(r.errors)
            ok = np.isfinite(errs)
            ax.loglog(hs[ok], errs[ok], "o-", color=colours[method],
                      label=f"{method}: {r.order:.2f} (theory {r.theory})")
            if r.theory and ok.any():
                anchor_h, anchor_e = hs[ok][-1], errs[ok][-1]
                ax.loglog(hs, anchor_e * (hs / anchor_h) ** r.theory, ":", color=colours[method],
                          lw=1)
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("step h (s)")
        ax.set_ylabel("max position error (m)")
        ax.set_title(f"{case}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, title="observed order", title_fontsize=8)
    fig.suptitle("Convergence: error against step (dotted: slope of the theoretical order)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_work_precision(orders: dict, pymunk: dict, path: Path) -> None:
    """Error against CPU time per integrator, and pymunk, on the scenes both measured."""
    plt = _pyplot()
    cases = [c for c in orders if c in pymunk]
    methods = sorted({m for per in orders.values() for m in per})
    colours = _colours(methods + ["pymunk"])
    fig, axes = plt.subplots(1, len(cases), figsize=(5.6 * len(cases), 4.6), squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        for method, r in orders[case].items():
            ok = np.isfinite(r.errors)
            ax.loglog(np.array(r.cpu)[ok], np.array(r.errors)[ok], "o-", color=colours[method],
                      label=method)
        p = pymunk[case]
        ax.loglog(p.cpu, p.errors, "s--", color=colours["pymunk"], label="pymunk (vs our rk4)")
        ax.set_xlabel("CPU time for the run (s)")
        ax.set_ylabel("max position error (m)")
        ax.set_title(case)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Work-precision: lower-left is better")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_drift(drift: dict, key: str, ylabel: str, title: str, path: Path,
               top: float | None = None) -> None:
    """One curve per integrator (solid: plain, dashed: projected) of ``drift[...][key]``;
    values above ``top`` leave the plot (a run on its way to diverging)."""
    plt = _pyplot()
    methods = sorted(drift)
    colours = _colours(methods)
    fig, ax = plt.subplots(figsize=(10.5, 4.8))
    floor = 1e-17  # exact zeros (a step that lands on C = 0) drawn at the bottom
    for method in methods:
        for variant, style, lw in (("plain", "-", 1.4), ("projected", "--", 0.8)):
            run = drift[method][variant]
            y = np.maximum(np.array(run[key], float), floor)
            label = f"{method}" + (" + projection" if variant == "projected" else "")
            if run["diverged_at"] is not None:
                label += f" (diverged at {run['diverged_at']:.2f} s)"
            ax.semilogy(run["t"], y, style, color=colours[method], label=label, lw=lw)
    if top is not None:
        ax.set_ylim(top=min(ax.get_ylim()[1], top))
    ax.set_xlabel("time t (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_cloth(sec_v: dict, sec_via: dict, path: Path) -> None:
    """The cloth-rise experiment (rise per integrator) and the spring-constants experiment (rise
    and distance to equilibrium)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    colours = _colours(sorted(sec_v))
    for method, r in sec_v.items():
        label = method + (f" (diverged at {r['diverged_at']:.2f} s)" if r["diverged_at"] else "")
        axes[0].plot(r["series"]["t"], 100 * np.array(r["series"]["rise"]),
                     color=colours[method], label=label)
    stable = [100 * np.array(r["series"]["rise"]) for r in sec_v.values()
              if r["diverged_at"] is None and r["series"]["rise"]]
    low = min([-12.0] + [float(y.min()) - 1 for y in stable])
    high = max([2.0] + [float(y.max()) + 1 for y in stable])
    axes[0].set_ylim(low, high)  # a diverged run leaves the plot upwards
    axes[0].set_title(f"Cloth pushed into the wall, h = {SECTION_V_H * 1e3:g} ms")
    axes[0].set_ylabel("highest particle above the wire (cm)")
    gain_colours = _colours(list(sec_via))
    for name, r in sec_via.items():
        axes[1].plot(r["series"]["t"], 100 * np.array(r["series"]["rise"]),
                     color=gain_colours[name], label=name)
        axes[2].semilogy(r["series"]["t"], r["series"]["distance"], color=gain_colours[name],
                         label=name)
    axes[1].set_title("Spring constants: released under gravity (rk4)")
    axes[1].set_ylabel("highest particle above the wire (cm)")
    axes[2].axhline(SETTLE_TOL, color="k", ls=":", label=f"settling tolerance {SETTLE_TOL} m")
    axes[2].set_title("Spring constants: settling")
    axes[2].set_ylabel("max distance from equilibrium (m)")
    for ax in axes[:2]:
        ax.axhline(0.0, color="0.4", lw=2, label="the wire")
    for ax in axes:
        ax.set_xlabel("time t (s)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------- report
def _fmt_time(value: float | None, duration: float) -> str:
    return f"> {duration:g}" if value is None else f"{value:.2f}"


def _cloth_defaults() -> str:
    p = {k: v.default for k, v in inspect.signature(scenes.cloth).parameters.items()}
    return (f"{p['nx']} x {p['ny']} particles of {p['mass']:g} kg {p['spacing']:g} m apart, "
            f"springs ks = {p['ks']:g} N/m, kd = {p['kd']:g} N s/m, drag {p['drag']:g} N s/m, "
            f"wall at x = {p['wall_x']:g} m")


def markdown(data: dict) -> str:
    """The verification report as Markdown (tables and links to the PNGs beside it)."""
    quick = data["quick"]
    lines = ["# Verification report", "",
             f"Generated by `python -m verification report{' --quick' if quick else ''}`; "
             f"the experiments took {data['seconds']:.0f} s. Integrators: "
             f"{', '.join(data['methods'])}. All quantities in SI units.", "",
             "## Convergence orders", "",
             "Error: the largest particle position error over ten checkpoints of the run; "
             "reference: exact elliptic solution (pendulum) or `solve_ivp(DOP853, rtol=1e-12)` "
             "of the same ODE; order: least-squares slope of log(error) on log(h).", "",
             orders_mod.orders_table(data["_orders"]), "",
             "![convergence](convergence.png)", "",
             "## pymunk cross-check", "",
             "The same scenes in pymunk (bodies with infinite moment, `PinJoint`, `GrooveJoint`, "
             f"`DampedSpring`, {pymunk_check.ITERATIONS} solver iterations) against our rk4 "
             f"trajectory (h = {data['pymunk_reference_h']:g} s); error: the largest particle "
             "position error (m) over ten checkpoints in "
             "1 s. pymunk is first order, so the error should halve with dt.", "",
             pymunk_check.pymunk_table(data["_pymunk"]), "",
             "![work-precision](work_precision.png)", "",
             "## Energy and constraint drift", "",
             f"Slider-crank (`scenes.wire_mixture`, undamped), h = {DRIFT_H * 1e3:g} ms, "
             f"{data['drift_seconds']:g} s. Energy error `max |E(t) - E(0)|` relative to the "
             "largest kinetic energy of the exact motion; "
             "constraint distance `max |C_r| / |J_r|` (m).", "",
             "| integrator | max energy error | max energy error (projected) | "
             "max constraint distance (m) | with projection (m) |", "|---|---|---|---|---|"]
    for method, runs in data["drift"].items():
        cells = []
        for key in ("energy_error", "constraint_distance"):
            for variant in ("plain", "projected"):
                r = runs[variant]
                cells.append(f"{max(r[key], default=float('nan')):.2e}"
                             if r["diverged_at"] is None else
                             f"diverged at {r['diverged_at']:.2f} s")
        lines.append(f"| {method} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} |")
    lines += ["", "![energy drift](energy_drift.png)", "",
              "![constraint drift](constraint_drift.png)", ""]
    lines += long_run_markdown(data["long_run"])
    lines += [
              "## Does the cloth rise above the wire?", "",
              "The original program's section V experiment (docs/notes_on_the_report.md). "
              f"Default cloth (`scenes.cloth(push={PUSH})`: {_cloth_defaults()}), top row on "
              f"the wire and pushed right into the wall, h = {SECTION_V_H * 1e3:g} ms, "
              f"{data['section_v_seconds']:g} s. Rise: the highest non-wire particle relative "
              "to the wire (negative: it stays below); wire gap: the top row's largest "
              "distance from the wire.", "",
              "| integrator | max rise (m) | max wire gap (m) | diverged at (s) |",
              "|---|---|---|---|"]
    for method, r in data["section_v"].items():
        if r["diverged_at"] is None:
            lines.append(f"| {method} | {r['max_rise']:.4f} | {r['max_wire_gap']:.2e} | |")
        else:  # the numbers before a blow-up measure the blow-up, not the cloth
            lines.append(f"| {method} | unstable | unstable | {r['diverged_at']:.3f} |")
    stable = [r for r in data["section_v"].values() if r["diverged_at"] is None]
    if stable and all(r["max_rise"] < 0 for r in stable):
        lines += ["", "No stable integrator lifts the cloth above the wire, and the top row "
                  "stays on the wire to rounding: the wire constraint is linear, and every "
                  "Runge-Kutta method preserves linear invariants (here C and Cdot) exactly."]
    lines += ["", "## Spring and damping constants", "",
              "The original program's section VI.A experiment (docs/notes_on_the_report.md): "
              "the default cloth released from rest under gravity with its constants "
              "in SI units, integrated with rk4 at a step well inside its stability region for "
             "the stiffest spring mode (h column). "
              f"Settling time: the last time any particle is farther than {SETTLE_TOL} m from "
              "the static equilibrium (potential-energy minimum with the top row on the wire); "
              "'>' means not settled by the end of the run.", "",
              "Damping ratio: one spring between two particles, `kd / (2 sqrt(ks m / 2))`; above "
              "1 it cannot oscillate.", "",
              "| ks (N/m) | kd (N s/m) | damping ratio | h (s) | max rise (m) | "
              "equilibrium sag (m) | settling time (s) |", "|---|---|---|---|---|---|---|"]
    for r in data["section_via"].values():
        lines.append(f"| {r['ks']:g} | {r['kd']:g} | {r['damping_ratio']:.2f} | {r['h']:.2e} | "
                     f"{r['max_rise']:.4f} | {r['equilibrium_sag']:.3f} | "
                     f"{_fmt_time(r['settling_time'], r['duration'])} |")
    lines += ["", "![cloth experiments](cloth.png)", ""]
    return "\n".join(lines)


def long_run_markdown(results: dict) -> list[str]:
    """The long-run energy section: what was run, the table and the plot."""
    first = next(iter(next(iter(results.values())).values()))
    systems = "; ".join(f"**{name}**: {longrun.SYSTEMS[name][1]}" for name in results)
    return ["## Long-run energy: bounded or drifting?", "",
            f"Every integrator, {first['steps']} steps of h = {first['h'] * 1e3:g} ms on "
            f"undamped, conservative systems ({systems}). After every step: the energy error "
            "E(t) - E(0) and the constraint distance max |C_r| / |J_r|. Secular trend: the "
            "slope of the least-squares line through E(t) - E(0) times the duration; "
            "oscillation: the peak-to-peak of E(t) - E(0) about that line. A trend well under "
            "the oscillation means a bounded energy error; a trend of the order of the "
            "oscillation or above, a drift.", "",
            longrun.long_run_table(results), "",
            "![long-run energy](long_run_energy.png)", ""]


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items() if not k.startswith("_")}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else str(value)
    if isinstance(value, np.integer):
        return int(value)
    if hasattr(value, "to_dict"):
        return _jsonable(value.to_dict())
    return value


def collect(quick: bool = False, progress: bool = True, cases: list[str] | None = None,
            pymunk_scenes: list[str] | None = None,
            durations: tuple[float, float, float] | None = None,
            long_steps: int | None = None) -> dict:
    """Run every experiment; returns the verification report's data (raw result objects under
    keys that start with ``_``). ``cases`` and ``pymunk_scenes`` restrict the order and pymunk
    runs; ``durations`` overrides the seconds of (drift, cloth rise, spring constants),
    ``long_steps`` the steps of the long-run energy runs."""
    start = time.perf_counter()
    if durations is None:
        durations = (2.0, 1.0, 1.0) if quick else (DRIFT_SECONDS, SECTION_V_SECONDS,
                                                   SECTION_VIA_SECONDS)
    data: dict[str, Any] = {"quick": quick, "methods": sorted(METHODS), "theory": dict(ORDERS)}
    data["_orders"] = orders_mod.measure_orders(cases, quick=quick, progress=progress)
    data["orders"] = {c: {m: r.to_dict() for m, r in per.items()}
                      for c, per in data["_orders"].items()}
    data["_pymunk"] = pymunk_check.compare_all(pymunk_scenes, quick=quick, progress=progress)
    data["pymunk"] = {n: r.to_dict() for n, r in data["_pymunk"].items()}
    data["pymunk_reference_h"] = pymunk_check.reference_step(quick)
    data["drift_seconds"], data["section_v_seconds"], data["section_via_seconds"] = durations
    if long_steps is None:
        long_steps = longrun.QUICK_STEPS if quick else longrun.LONG_STEPS
    data["long_run"] = longrun.long_runs(long_steps, progress=progress)
    data["drift"] = drift_runs(durations[0], progress=progress)
    data["section_v"] = section_v(durations[1], progress=progress)
    data["section_via"] = section_via(durations[2], progress=progress)
    data["seconds"] = time.perf_counter() - start
    return data


def write(data: dict, out: str | os.PathLike) -> None:
    """Write ``report.md``, ``report.json`` and the PNG plots of ``data`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plot_convergence(data["_orders"], out / "convergence.png")
    plot_work_precision(data["_orders"], data["_pymunk"], out / "work_precision.png")
    plot_drift(data["drift"], "energy_error", "|E(t) - E(0)| / largest kinetic energy",
               f"Energy drift, slider-crank, h = {DRIFT_H * 1e3:g} ms", out / "energy_drift.png",
               top=1e3)
    plot_drift(data["drift"], "constraint_distance", "max |C| / |J| (m)",
               f"Constraint drift, slider-crank, h = {DRIFT_H * 1e3:g} ms",
               out / "constraint_drift.png")
    plot_cloth(data["section_v"], data["section_via"], out / "cloth.png")
    longrun.plot_long_runs(data["long_run"], out / "long_run_energy.png")
    (out / "report.md").write_text(markdown(data))
    (out / "report.json").write_text(json.dumps(_jsonable(data), indent=1))


def write_report(out: str | os.PathLike, quick: bool = False, progress: bool = True) -> dict:
    """Run every experiment (:func:`collect`) and write the report into ``out``
    (:func:`write`); returns the data."""
    data = collect(quick=quick, progress=progress)
    write(data, out)
    return data
