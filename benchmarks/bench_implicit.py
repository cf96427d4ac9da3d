"""Benchmark (not a test): implicit_euler against the explicit methods on the stiff cloth.

The stiff cloth: 15 x 15 particles of 0.01 kg, 0.1 m apart, structural springs of
ks = 2000 N/m and shear springs (``scenes.cloth`` gives them ks/2 = 1000 N/m; ``--shear-full``
makes them 2000 N/m too), kd = 0.05 N s/m, no bend springs, no drag, the top row on a horizontal
wire, gravity. Two scenarios, each simulated for 1 s:

- ``hanging``: released from its flat rest shape (it sags a few millimetres and rings);
- ``pushed``: the same with a horizontal force of 0.05 N on each top-row particle,
  so the cloth slides along the wire and swings.

Visual tolerance: the largest distance between any particle and its place in a fine reference
run (rk4, dt = 1/1920 s), over every frame of 1/60 s that the run reaches (every 1/30 s for a run
at dt = 1/30 s), must be at most ``--tol`` (default 1 cm, about a pixel at 100 px/m). The
reference's own error is estimated against rk4 at dt = 1/3840 s and printed.

For each method the largest step dt = 1/(60 k) that stays stable (no SimulationDiverged) and
meets the tolerance is found by trying k = 1, 2, 3, 4, 6, 8, ... in turn (implicit_euler also
tries 1/15 and 1/30 s). The wall (and CPU) time of 1 s at that dt is the best of ``--repeats`` runs.
Prints a table and then the results as JSON.

    python benchmarks/bench_implicit.py [--tol 0.01] [--repeats 5] [--shear-full]
    python benchmarks/bench_implicit.py --scaling   # cost per particle-step at 15, 30, 60
    python benchmarks/bench_implicit.py --solvers   # CG against the direct solve, 15 to 120
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from fractions import Fraction
from typing import Any

import numpy as np

from constrained_particles import METHODS, ParticleSystem, SimulationDiverged, scenes
from cparticles.bench_scaling import IMPLICIT_SIZES, bench_implicit_scaling, implicit_table

FRAME = Fraction(1, 60)
EXPLICIT_DIVISORS = (1, 2, 3, 4, 6, 8, 10, 12, 16, 20, 24, 32, 48, 64, 96, 128, 192, 256, 384,
                     512)
IMPLICIT_STEPS = (Fraction(1, 15), Fraction(1, 30)) + tuple(FRAME / k for k in (1, 2, 3, 4, 6, 8))
REFERENCE_DT = FRAME / 32
DURATION = Fraction(1)


def stiff_cloth(scenario: str, shear_full: bool = False) -> ParticleSystem:
    """The stiff cloth of the module docstring; ``scenario`` is ``"hanging"`` or ``"pushed"``."""
    push = {"hanging": 0.0, "pushed": 0.05}[scenario]
    s = scenes.cloth(15, 15, ks=2000.0, mass=0.01, kd=0.05, bend=False, wall_x=None, drag=0.0,
                     push=push)
    if shear_full:
        s.forces[1].ks[:] = 2000.0
    return s


def simulate(system: ParticleSystem, method: str, dt: Fraction, record: bool = True
             ) -> tuple[list[np.ndarray], float, float]:
    """Run ``DURATION`` seconds; positions after each frame of max(dt, 1/60) s, the wall time
    and the CPU time of this process (both in seconds).

    Raises SimulationDiverged if the method blows up.
    """
    per_frame = max(1, int(FRAME / dt))
    frames = int(DURATION / (dt * per_frame))
    h = float(dt)
    out = []
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(frames):
        for _ in range(per_frame):
            system.step(h, method=method)
        if record:
            out.append(system.x.copy())
    return out, time.perf_counter() - start, time.process_time() - cpu


def frame_error(run: list[np.ndarray], dt: Fraction, reference: list[np.ndarray]) -> float:
    """Largest particle distance (m) to the reference over the frames ``run`` reached."""
    stride = max(1, int(dt / FRAME))
    ref = reference[stride - 1::stride]
    return max(float(np.max(np.linalg.norm(a - b, axis=1))) for a, b in zip(run, ref, strict=True))


def search(scenario: str, method: str, reference: list[np.ndarray], tol: float,
           shear_full: bool) -> dict:
    """Largest dt for ``method`` that is stable and within ``tol``; every try is recorded."""
    steps = IMPLICIT_STEPS if method == "implicit_euler" else tuple(FRAME / k
                                                                    for k in EXPLICIT_DIVISORS)
    tries = []
    for dt in steps:
        try:
            run = simulate(stiff_cloth(scenario, shear_full), method, dt)[0]
        except SimulationDiverged:
            tries.append({"dt": float(dt), "stable": False})
            continue
        error = frame_error(run, dt, reference)
        tries.append({"dt": float(dt), "stable": True, "max_error_m": error})
        if error <= tol:
            return {"dt": float(dt), "dt_label": f"1/{int(1 / dt)}", "steps": int(DURATION / dt),
                    "max_error_m": error, "tries": tries, "_dt": dt}
    return {"dt": None, "tries": tries}


def timed(scenario: str, method: str, dt: Fraction, repeats: int, shear_full: bool
          ) -> dict[str, float]:
    """Best wall and CPU times (s) of ``repeats`` runs of 1 s (after a warm-up step)."""
    wall, cpu = np.inf, np.inf
    for _ in range(repeats):
        system = stiff_cloth(scenario, shear_full)
        system.copy().step(float(dt), method=method)
        _, w, c = simulate(system, method, dt, record=False)
        wall, cpu = min(wall, w), min(cpu, c)
    return {"wall_s": float(wall), "cpu_s": float(cpu)}


def bench(scenario: str, tol: float, repeats: int, shear_full: bool) -> dict:
    """All methods on one scenario."""
    reference, ref_time, _ = simulate(stiff_cloth(scenario, shear_full), "rk4", REFERENCE_DT)
    finer = simulate(stiff_cloth(scenario, shear_full), "rk4", REFERENCE_DT / 2)[0]
    start = stiff_cloth(scenario, shear_full).x
    out = {
        "scenario": scenario,
        "reference": {"method": "rk4", "dt": float(REFERENCE_DT), "wall_s": ref_time,
                      "error_vs_half_dt_m": frame_error(reference, FRAME, finer)},
        "motion_m": max(float(np.max(np.linalg.norm(x - start, axis=1))) for x in reference),
        "methods": {},
    }
    for method in METHODS:
        found = search(scenario, method, reference, tol, shear_full)
        dt = found.pop("_dt", None)
        if dt is not None:
            found.update(timed(scenario, method, dt, repeats, shear_full))
        out["methods"][method] = found
    at_60 = simulate(stiff_cloth(scenario, shear_full), "implicit_euler", FRAME)[0]
    out["implicit_euler_at_60hz"] = {"max_error_m": frame_error(at_60, FRAME, reference),
                                     **timed(scenario, "implicit_euler", FRAME, repeats,
                                             shear_full)}
    explicit = {m: r for m, r in out["methods"].items()
                if m != "implicit_euler" and r["dt"] is not None}
    fastest = min(explicit, key=lambda m: explicit[m]["wall_s"]) if explicit else None
    implicit = out["methods"]["implicit_euler"]
    out["fastest_explicit"] = fastest
    for clock in ("wall_s", "cpu_s"):
        out[f"speedup_{clock[:-2]}"] = (explicit[fastest][clock] / implicit[clock]
                                        if fastest and implicit["dt"] is not None else None)
    return out


def table(result: dict, tol: float) -> str:
    """A plain-text table of one scenario's results."""
    ref = result["reference"]
    lines = [f"scenario {result['scenario']}: largest motion {result['motion_m'] * 100:.2f} cm; "
             f"reference rk4 dt = 1/1920 s ({ref['wall_s']:.1f} s wall), its error vs dt/2 "
             f"{ref['error_vs_half_dt_m']:.1e} m; tolerance {tol * 100:g} cm",
             f"{'method':<18}{'dt (s)':>9}{'steps':>7}{'max err (cm)':>14}{'wall (s)':>10}"
             f"{'cpu (s)':>9}  unstable at"]
    for method, r in result["methods"].items():
        unstable = ", ".join(f"1/{round(1 / t['dt'])}" for t in r["tries"] if not t["stable"])
        if len(unstable) > 40:
            unstable = unstable[:37] + "..."
        if r["dt"] is None:
            lines.append(f"{method:<18}{'none within the searched steps':>49}  {unstable}")
            continue
        lines.append(f"{method:<18}{r['dt_label']:>9}{r['steps']:>7}{r['max_error_m'] * 100:>14.3f}"
                     f"{r['wall_s']:>10.3f}{r['cpu_s']:>9.3f}  {unstable}")
    r = result["implicit_euler_at_60hz"]
    lines.append(f"{'implicit @ 60 Hz':<18}{'1/60':>9}{60:>7}{r['max_error_m'] * 100:>14.3f}"
                 f"{r['wall_s']:>10.3f}{r['cpu_s']:>9.3f}")
    wall, cpu = result["speedup_wall"], result["speedup_cpu"]
    lines.append(f"fastest explicit: {result['fastest_explicit']}; implicit_euler is "
                 + (f"{wall:.2f}x as fast in wall time, {cpu:.2f}x in CPU time" if wall
                    else "not comparable"))
    return "\n".join(lines)


SCALING_SIZES = (15, 30, 60)


def scaling(sizes: tuple[int, ...] = SCALING_SIZES, repeats: int = 5) -> list[dict]:
    """implicit_euler's cost per particle-step with the direct solve on the pushed stiff cloth
    at n x n particles (h = 1/60 s), next to the LU factors' fill per unknown of the KKT
    system, with the fill-reducing ordering kept from the first step (the default) and
    searched at every step (the time ratio is searched / kept). Medians of ``repeats``
    alternated batches."""
    from scipy.sparse import linalg as spla

    from constrained_particles import implicit

    out = []
    for n in sizes:
        systems = []
        for keep in (True, False):
            s = scenes.cloth(n, n, ks=2000.0, mass=0.01, kd=0.05, bend=False, wall_x=None,
                             drag=0.0, push=0.05)
            s.implicit_solver = "direct"
            s.step(float(FRAME), "implicit_euler")
            asm = implicit._assembly(s)
            if not keep:  # back to the unpermuted structure, never reordered again
                asm.keep_order = False
                asm.forget()
            systems.append(s)
        k = max(2, 20_000 // (n * n))
        times: list[list[float]] = [[], []]
        for _ in range(repeats):
            for which, s in enumerate(systems):
                t0 = time.perf_counter()
                for _ in range(k):
                    s.step(float(FRAME), "implicit_euler")
                times[which].append((time.perf_counter() - t0) / k)
        kept, searched = (float(np.median(t)) for t in times)
        seen: list = []
        solve = implicit._solve

        def spy(A: Any, *args: Any, seen: list = seen, solve: Any = solve, **kwargs: Any
                ) -> np.ndarray:
            seen.append(A)  # the KKT matrix of a step, in the kept ordering
            return solve(A, *args, **kwargs)

        implicit._solve = spy
        try:
            systems[0].step(float(FRAME), "implicit_euler")
        finally:
            implicit._solve = solve
        asm = implicit._assembly(systems[0])
        lu = spla.splu(seen[0], **implicit._LU_ORDERED)
        out.append({"n": n, "particles": n * n, "kkt_size": asm.size,
                    "ms_per_step": 1e3 * kept, "us_per_particle_step": 1e6 * kept / (n * n),
                    "fill_per_unknown": (lu.L.nnz + lu.U.nnz) / asm.size,
                    "searched_over_kept": float(np.median(np.array(times[1])
                                                          / np.array(times[0])))})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tol", type=float, default=0.01, help="visual tolerance in metres")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per method (best)")
    parser.add_argument("--shear-full", action="store_true",
                        help="shear springs of 2000 N/m instead of scenes.cloth's ks/2")
    parser.add_argument("--scenarios", nargs="+", default=["hanging", "pushed"],
                        choices=["hanging", "pushed"])
    parser.add_argument("--scaling", action="store_true",
                        help="instead: cost per particle-step and LU fill of implicit_euler "
                        f"at {', '.join(f'{n}x{n}' for n in SCALING_SIZES)}")
    parser.add_argument("--solvers", action="store_true",
                        help="instead: implicit_euler's cost per step with CG and the direct "
                        f"solve at {', '.join(f'{n}x{n}' for n in IMPLICIT_SIZES)}")
    args = parser.parse_args()
    if args.solvers:
        result = bench_implicit_scaling(repeats=args.repeats)
        print(implicit_table(result))
        print(json.dumps(result, indent=1))
        return
    if args.scaling:
        rows = scaling(repeats=args.repeats)
        print("| cloth | KKT unknowns | ms per step | us per particle-step | LU fill per unknown "
              "| ordering searched each step / kept |\n|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['n']}x{r['n']} | {r['kkt_size']} | {r['ms_per_step']:.2f} | "
                  f"{r['us_per_particle_step']:.1f} | {r['fill_per_unknown']:.0f} | "
                  f"{r['searched_over_kept']:.2f}x |")
        print(json.dumps(rows, indent=1))
        return
    results = {"machine": platform.processor() or platform.machine(),
               "python": platform.python_version(), "tolerance_m": args.tol,
               "shear_ks": 2000.0 if args.shear_full else 1000.0, "scenarios": []}
    for scenario in args.scenarios:
        result = bench(scenario, args.tol, args.repeats, args.shear_full)
        results["scenarios"].append(result)
        print(table(result, args.tol), flush=True)
        print()
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
