"""Benchmark (not a test): what one ``step`` call costs beyond the step it takes.

Two comparisons on the benchmark cloth (``scenes.cloth(n, n, wall_x=None, drag=0)``: structural,
shear and bend damped springs, the top row on a horizontal wire, gravity) at dt = 1 ms, each
timed as medians over alternated repeats (every entry is timed once per round, round after
round, so a change in the machine's load moves all of them alike):

- **per-call cost** (64 x 64): ``system.step(dt, "symplectic_euler")`` (one step per call)
  against one step inside ``system.step(dt, "symplectic_euler", steps=10)`` (the call's time
  divided by ten). The difference is what a call costs beyond its step (argument checks, the
  pack check, entering the compiled code).
- **one step per call against pymunk** (20 x 20 and 64 x 64): ``symplectic_euler`` at one
  step per call against pymunk at 1 iteration (``space.step(dt)``, the way pymunk is called),
  and both at ten steps per call (``steps=10`` for ours, ten ``space.step`` calls for pymunk).

    python benchmarks/bench_call.py [--repeats 15] [--seconds 0.2]

Prints a table, then the figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from collections.abc import Callable
from typing import Any

from constrained_particles import scenes
from cparticles.bench import alternate

DT = 1e-3  #: physics step (s)
METHOD = "symplectic_euler"
CALL_STEPS = 10  #: steps per call of the "ten steps per call" entries


def cloth(n: int) -> Any:
    """The benchmark cloth, n x n particles."""
    return scenes.cloth(n, n, wall_x=None, drag=0.0)


def pymunk_scene(n: int) -> Any:
    """The same cloth in pymunk at 1 iteration (``verification.pymunk_check.to_pymunk``)."""
    from verification.pymunk_check import to_pymunk

    return to_pymunk(cloth(n), 1)


def alternated(calls: dict[str, Callable[[], None]], repeats: int, seconds: float
               ) -> dict[str, list[float]]:
    """Seconds per call of each entry, one sample per round (``cparticles bench``'s
    alternation: batches of at least ``seconds``, entries taking turns, three warm-up calls)."""
    samples = alternate(calls, repeats, seconds)
    diverged = [name for name, s in samples.items() if s is None]
    if diverged:
        raise RuntimeError(f"the benchmark cloth diverged in {diverged}")
    return {name: s for name, s in samples.items() if s is not None}


def per_call_cost(repeats: int, seconds: float, n: int = 64) -> dict[str, float]:
    """Microseconds: a one-step call, a step inside a ten-step call, and their difference
    (median over rounds of the per-round difference)."""
    one, ten = cloth(n), cloth(n)
    t = alternated({"one": lambda: one.step(DT, METHOD),
                    "ten": lambda: ten.step(DT, METHOD, steps=CALL_STEPS)}, repeats, seconds)
    step_in_ten = [s / CALL_STEPS for s in t["ten"]]
    return {"one_step_call_us": 1e6 * statistics.median(t["one"]),
            "step_in_ten_step_call_us": 1e6 * statistics.median(step_in_ten),
            "call_overhead_us": 1e6 * statistics.median(a - b for a, b in
                                                        zip(t["one"], step_in_ten, strict=True))}


def against_pymunk(repeats: int, seconds: float, n: int) -> dict[str, float]:
    """Our speed over pymunk's (1 iteration) on the n x n cloth, at one and at ten steps per
    call: medians over rounds of the per-round time ratios."""
    ours1, ours10 = cloth(n), cloth(n)
    pm1, pm10 = pymunk_scene(n), pymunk_scene(n)

    def pymunk_ten() -> None:
        for _ in range(CALL_STEPS):
            pm10.step(DT)

    t = alternated({"ours_1": lambda: ours1.step(DT, METHOD), "pymunk_1": lambda: pm1.step(DT),
                    "ours_10": lambda: ours10.step(DT, METHOD, steps=CALL_STEPS),
                    "pymunk_10": pymunk_ten}, repeats, seconds)
    ratio = {k: statistics.median(p / o for p, o in zip(t[f"pymunk_{k}"], t[f"ours_{k}"],
                                                        strict=True)) for k in (1, 10)}
    return {"one_step_per_call_ratio": ratio[1], "ten_steps_per_call_ratio": ratio[10],
            "ours_one_step_call_us": 1e6 * statistics.median(t["ours_1"]),
            "pymunk_one_step_us": 1e6 * statistics.median(t["pymunk_1"])}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run both comparisons, print a table and the JSON; return the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--seconds", type=float, default=0.2)
    args = parser.parse_args(argv)
    out: dict[str, Any] = {"machine": platform.platform(), "method": METHOD, "dt": DT,
                           "per_call_64": per_call_cost(args.repeats, args.seconds),
                           "pymunk": {n: against_pymunk(args.repeats, args.seconds, n)
                                      for n in (20, 64)}}
    c = out["per_call_64"]
    print(f"64x64 {METHOD}: one-step call {c['one_step_call_us']:.1f} us, step in a ten-step "
          f"call {c['step_in_ten_step_call_us']:.1f} us, call overhead "
          f"{c['call_overhead_us']:.1f} us")
    for n, r in out["pymunk"].items():
        print(f"{n}x{n} against pymunk (1 iteration): {r['one_step_per_call_ratio']:.2f}x at one "
              f"step per call, {r['ten_steps_per_call_ratio']:.2f}x at ten")
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
