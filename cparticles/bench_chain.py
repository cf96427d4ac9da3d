"""Chains of rods: this project's RATTLE and symplectic Euler against pymunk and MuJoCo.

The chain: ``rods`` rods of 0.05 m hung from a fixed point, a particle of 0.01 kg at the end of
each, released straight at 0.5 rad under gravity, dt = 1 ms. Each engine steps it in calls of
``steps`` steps; figures are microseconds per step (median of alternated repeats, every engine
timed in each round) and the ratio of each peer's time to ours (above 1: ours is faster).

- this project, ``solver="auto"``: ``rattle`` (exact constraints, the sparse Cholesky solve
  of docs/physics.md) and ``symplectic_euler`` (multipliers with drift feedback);
- pymunk: the same chain of point-like bodies joined by ``PinJoint`` s (iterative impulses, 10
  iterations, its default);
- MuJoCo, if installed (``pip install mujoco``; not a dependency): a chain of ``rods`` hinge
  joints, each body's mass at the end of its link (reduced coordinates: exact), its default
  Euler integrator. Its XML parser refuses chains nested as deep as 1024 bodies: those rows
  have no MuJoCo figure.

Run: ``python -m cparticles.bench_chain [--rods 16 64 256 1024] [--steps 10] [--repeats 5]``,
or as a section of ``cparticles bench``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from constrained_particles import Gravity, ParticleSystem, Rod

LINK, MASS, ANGLE, DT = 0.05, 0.01, 0.5, 1e-3


def ours(rods: int, method: str) -> Callable[[int], None]:
    s = ParticleSystem()
    k = np.arange(rods + 1)
    pts = np.stack([LINK * k * np.sin(ANGLE), -LINK * k * np.cos(ANGLE)], 1)
    s.add_particle(pts[0], fixed=True)
    s.add_particles(pts[1:], mass=MASS)
    s.add(Rod(k[:-1], k[1:]), Gravity((0.0, -9.81)))
    return lambda steps: s.step(DT, method, steps=steps)


def pymunk_chain(rods: int) -> Callable[[int], None]:
    import pymunk

    space = pymunk.Space()
    space.gravity = (0.0, -9.81)
    prev = space.static_body
    prev_pos = (0.0, 0.0)
    for i in range(1, rods + 1):
        body = pymunk.Body(MASS, 1e-9)
        body.position = (LINK * i * np.sin(ANGLE), -LINK * i * np.cos(ANGLE))
        space.add(body, pymunk.PinJoint(prev, body, (0, 0) if i > 1 else prev_pos, (0, 0)))
        prev = body

    def run(steps: int) -> None:
        for _ in range(steps):
            space.step(DT)
    return run


def mujoco_chain(rods: int) -> Callable[[int], None] | None:
    try:
        import mujoco
    except ImportError:
        return None
    body = ""
    for i in range(rods):
        pos = "0 0 0" if i == 0 else f"0 0 {-LINK}"
        body += (f'<body pos="{pos}"><joint type="hinge" axis="0 1 0"/>'
                 f'<inertial pos="0 0 {-LINK}" mass="{MASS}" diaginertia="1e-9 1e-9 1e-9"/>')
    body += "</body>" * rods
    xml = (f'<mujoco><option timestep="{DT}" gravity="0 0 -9.81"><flag contact="disable"/>'
           f"</option><worldbody>{body}</worldbody></mujoco>")
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError:  # (its XML parser refuses a nesting as deep as a long chain)
        return None
    data = mujoco.MjData(model)
    data.qpos[0] = ANGLE
    return lambda steps: mujoco.mj_step(model, data, steps)


def bench_chains(rods: list[int], steps: int = 10, repeats: int = 5,
                 seconds: float = 0.3) -> dict[str, dict[str, float]]:
    """Microseconds per step of each engine on chains of each length in ``rods`` (medians of
    ``repeats`` alternated rounds of ``seconds`` per engine, ``steps`` steps per call):
    ``{str(rods): {engine: us}}``, MuJoCo where it is installed and takes the chain."""
    out: dict[str, dict[str, float]] = {}
    for n in rods:
        engines = {"rattle": ours(n, "rattle"), "symplectic_euler": ours(n, "symplectic_euler"),
                   "pymunk": pymunk_chain(n)}
        mj = mujoco_chain(n)
        if mj is not None:
            engines["mujoco"] = mj
        times: dict[str, list[float]] = {name: [] for name in engines}
        for run in engines.values():
            run(steps)  # compile / warm up
        for _ in range(repeats):
            for name, run in engines.items():
                count, start = 0, time.perf_counter()
                while count == 0 or time.perf_counter() - start < seconds:  # (at least once)
                    run(steps)
                    count += steps
                times[name].append((time.perf_counter() - start) / count * 1e6)
        out[str(n)] = {name: float(np.median(t)) for name, t in times.items()}
    return out


def markdown(results: dict[str, dict[str, float]], steps: int) -> list[str]:
    """The chain section as a Markdown table: microseconds per step, and each peer's time
    over ours (above 1: ours is faster)."""
    peers = sorted({p for r in results.values() for p in r} - {"rattle", "symplectic_euler"})
    lines = ["", f"Chains of rods ({LINK} m, {MASS} kg, dt {DT} s, {steps} steps per call), "
             "us per step:", "",
             "| rods | rattle | symplectic_euler | " + " | ".join(peers) + " | "
             + " | ".join(f"{p} / rattle | {p} / symplectic_euler" for p in peers)
             + " | rattle ns per rod |",
             "|---" * (4 + 3 * len(peers)) + "|"]
    for n, r in results.items():
        cells = [n, f"{r['rattle']:.1f}", f"{r['symplectic_euler']:.1f}"]
        cells += [f"{r[p]:.1f}" if p in r else "-" for p in peers]
        for p in peers:
            cells += ([f"{r[p] / r['rattle']:.2f}x", f"{r[p] / r['symplectic_euler']:.2f}x"]
                      if p in r else ["-", "-"])
        cells.append(f"{r['rattle'] / int(n) * 1e3:.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rods", type=int, nargs="+", default=[16, 64, 256, 1024])
    ap.add_argument("--steps", type=int, default=10, help="steps per call")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=0.3, help="per engine and round")
    args = ap.parse_args(argv)
    results = bench_chains(args.rods, args.steps, args.repeats, args.seconds)
    print("\n".join(markdown(results, args.steps)))


if __name__ == "__main__":
    main()
