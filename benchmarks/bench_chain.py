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

Run: ``python -m benchmarks.bench_chain [--rods 16 64 256 1024] [--steps 10] [--repeats 5]``.
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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rods", type=int, nargs="+", default=[16, 64, 256, 1024])
    ap.add_argument("--steps", type=int, default=10, help="steps per call")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=0.3, help="per engine and round")
    args = ap.parse_args(argv)
    print(f"chain of rods, {LINK} m, {MASS} kg, dt {DT} s, {args.steps} steps per call; "
          "us per step, median of alternated rounds")
    first = {}
    for rods in args.rods:
        engines = {"rattle": ours(rods, "rattle"),
                   "symplectic_euler": ours(rods, "symplectic_euler"),
                   "pymunk": pymunk_chain(rods)}
        mj = mujoco_chain(rods)
        if mj is not None:
            engines["mujoco"] = mj
        times: dict[str, list[float]] = {name: [] for name in engines}
        for run in engines.values():
            run(args.steps)  # compile / warm up
        for _ in range(args.repeats):
            for name, run in engines.items():
                count, start = 0, time.perf_counter()
                while time.perf_counter() - start < args.seconds:
                    run(args.steps)
                    count += args.steps
                times[name].append((time.perf_counter() - start) / count * 1e6)
        med = {name: float(np.median(t)) for name, t in times.items()}
        first.setdefault("rods", rods)
        for name in ("rattle", "symplectic_euler"):
            first.setdefault(name, med[name])
        line = ", ".join(f"{name} {t:.1f}" for name, t in med.items())
        ratios = ", ".join(f"{peer}/{name} {med[peer] / med[name]:.2f}x"
                           for name in ("rattle", "symplectic_euler")
                           for peer in med if peer not in ("rattle", "symplectic_euler"))
        growth = ", ".join(f"{name} x{med[name] / first[name]:.1f} from {first['rods']} rods"
                           for name in ("rattle", "symplectic_euler"))
        print(f"{rods:5d} rods: {line}; {ratios}; {growth}; "
              f"{med['rattle'] / rods * 1e3:.0f} ns per rod (rattle)")


if __name__ == "__main__":
    main()
