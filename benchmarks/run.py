"""``cparticles bench``: constrained-particles against pymunk, in one run on one machine.

Sections (each figure a median of ``--repeats`` timed batches after warm-up):

(a) the same N x N cloth in both engines at dt = 1e-3: particle-steps per second and our
    figure divided by pymunk's, per integrator;
(b) ClothSlide-v0 env-steps per second: single env, SyncVectorEnv(64), AsyncVectorEnv(2),
    the native vector env (64);
(c) cost per particle-step for N in {32, 64, 128} and peak memory of the 128 x 128 cloth;
(d) accuracy at equal cost: error after 0.5 s of a 10 x 10 cloth against a fine rk4 reference,
    against CPU time, for rk4 and pymunk.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import numpy as np

from constrained_particles import METHODS

from .cloth import our_cloth, pymunk_cloth, pymunk_positions, rates

DT = 1e-3


def bench_pymunk(sizes: list[int], methods: list[str], repeats: int, seconds: float) -> dict:
    """Section (a): particle-steps/s for each engine and the ratio ours / pymunk's (None for an
    integrator that diverges on this cloth at this dt)."""
    out: dict = {"ours": {}, "pymunk": {}, "ratio": {}}
    for n in sizes:
        scene = pymunk_cloth(our_cloth(n))
        steps = {"pymunk": lambda scene=scene: scene.step(DT)}
        for method in methods:
            system = our_cloth(n)
            steps[method] = lambda s=system, m=method: s.step(DT, m)
        measured = rates(steps, n * n, repeats, seconds)
        out["pymunk"][n] = pymunk = measured.pop("pymunk")
        out["ours"][n] = measured
        out["ratio"][n] = {m: None if r is None else r / pymunk for m, r in measured.items()}
    return out


def bench_scaling(sizes: list[int], method: str, repeats: int, seconds: float) -> dict:
    """Section (c): microseconds per particle-step for each N, and the largest over smallest."""
    cost = {}
    for n in sizes:
        s = our_cloth(n)
        cost[n] = 1e6 / rates({n: lambda s=s: s.step(DT, method)}, n * n, repeats, seconds)[n]
    return {"method": method, "us_per_particle_step": cost,
            "scaling_ratio": cost[sizes[-1]] / cost[sizes[0]]}


def peak_memory_mb(n: int = 128, steps: int = 20) -> float:
    """Peak resident memory (MB) of a fresh process that builds the n x n cloth and steps rk4."""
    code = (
        "import resource\n"
        "from benchmarks.cloth import our_cloth\n"
        f"s = our_cloth({n})\n"
        f"for _ in range({steps}): s.step({DT}, 'rk4')\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


def bench_accuracy(n: int = 10, horizon: float = 0.5) -> dict:
    """Section (d): (CPU seconds, max position error in m) for rk4 and pymunk at several dt."""
    reference = our_cloth(n)
    for _ in range(int(round(horizon / 1e-4))):
        reference.step(1e-4, "rk4")
    out: dict = {"rk4": [], "pymunk": []}
    for dt in (4e-3, 2e-3, 1e-3, 5e-4):
        s = our_cloth(n)
        t0 = time.process_time()
        for _ in range(int(round(horizon / dt))):
            s.step(dt, "rk4")
        out["rk4"].append((time.process_time() - t0, float(np.abs(s.x - reference.x).max()), dt))
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5):
        scene = pymunk_cloth(our_cloth(n), iterations=30)
        t0 = time.process_time()
        for _ in range(int(round(horizon / dt))):
            scene.step(dt)
        err = float(np.abs(pymunk_positions(scene) - reference.x).max())
        out["pymunk"].append((time.process_time() - t0, err, dt))
    # each engine's error interpolated (log-log) at the CPU time where both have data
    t_common = min(max(r[0] for r in out["rk4"]), max(r[0] for r in out["pymunk"]))
    for engine in ("rk4", "pymunk"):
        pts = sorted(out[engine])
        t, e = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        out[f"{engine}_error_at_equal_time"] = float(np.exp(np.interp(np.log(t_common), t, e)))
    out["equal_cpu_seconds"] = t_common
    return out


def _env_block(env, actions: np.ndarray, single: bool) -> float:
    start = time.perf_counter()
    for a in actions:
        out = env.step(a)
        if single and (out[2] or out[3]):
            env.reset()
    return time.perf_counter() - start


def bench_envs(env_id: str, repeats: int, steps: int) -> dict:
    """Section (b): median env-steps per second of ``env_id`` as a single env, SyncVectorEnv(64),
    AsyncVectorEnv (2 workers, one env each) and the native vector env (64).

    Timed blocks of the four alternate, so a busy machine slows them alike.
    """
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)

    configs = {
        "single": (gym.make(env_id), 1, steps),
        "sync_64": (gym.make_vec(env_id, num_envs=64, vectorization_mode="sync"), 64,
                    max(2, steps // 16)),
        "async_2": (gym.make_vec(env_id, num_envs=2, vectorization_mode="async"), 2, steps),
        "native_64": (gym.make_vec(env_id, num_envs=64, vectorization_mode="vector_entry_point"),
                      64, steps),
    }
    rng = np.random.default_rng(0)
    times: dict[str, list[float]] = {name: [] for name in configs}
    for name, (env, _, _) in configs.items():
        env.reset(seed=0)
        _env_block(env, np.array([env.action_space.sample() for _ in range(3)]), name == "single")
    for _ in range(repeats):
        for name, (env, _, n) in configs.items():
            shape = env.action_space.shape
            actions = rng.uniform(-1, 1, (n, *shape)).astype(np.float32)
            times[name].append(_env_block(env, actions, name == "single") / n)
    for env, _, _ in configs.values():
        env.close()
    rates = {name: configs[name][1] / statistics.median(t) for name, t in times.items()}
    return {**rates, "vector_speedup": rates["native_64"] / rates["sync_64"]}


def markdown(results: dict) -> str:
    """The results as Markdown tables."""
    a = results["pymunk"]
    methods = sorted(next(iter(a["ratio"].values())))
    header = " | ".join(f"{m} (ratio)" for m in methods)
    lines = [f"| N | pymunk particle-steps/s | {header} |", "|---|---|" + "---|" * len(methods)]
    for n in a["ratio"]:
        cells = ["diverges" if a["ratio"][n][m] is None
                 else f"{a['ours'][n][m]:.3g} ({a['ratio'][n][m]:.2f}x)" for m in methods]
        lines.append(f"| {n} | {a['pymunk'][n]:.3g} | " + " | ".join(cells) + " |")
    c = results["scaling"]
    lines += ["", f"Cost per particle-step ({c['method']}): " + ", ".join(
        f"N={n}: {v:.3g} us" for n, v in c["us_per_particle_step"].items())
        + f"; ratio {results['scaling_ratio']:.2f}. Peak memory 128x128: "
        f"{results['peak_mb_128']:.0f} MB."]
    if "envs" in results:
        lines += ["", "| ClothSlide-v0 | env-steps/s |", "|---|---|"]
        lines += [f"| {k} | {v:.4g} |" for k, v in results["envs"].items()
                  if isinstance(v, (int, float))]
        lines += ["", f"Native vector env speedup over SyncVectorEnv (64 envs): "
                  f"{results['vector_speedup']:.1f}x"]
    d = results["accuracy"]
    lines += ["", f"Accuracy at equal CPU time ({d['equal_cpu_seconds']:.2f} s, 10x10 cloth, "
              f"0.5 s): rk4 error {d['rk4_error_at_equal_time']:.2e} m, pymunk error "
              f"{d['pymunk_error_at_equal_time']:.2e} m."]
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles bench``."""
    parser.add_argument("--quick", action="store_true", help="shorter batches, fewer sizes")
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--repeats", type=int, default=5, help="timed batches per figure (>= 5)")
    parser.add_argument("--skip-envs", action="store_true", help="skip section (b)")


def main(args: argparse.Namespace) -> int:
    """Run every section and print JSON or Markdown."""
    if args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    seconds = 0.1 if args.quick else 0.4
    sizes = [20, 64] if args.quick else [10, 20, 40, 64]
    methods = ["symplectic_euler", "rk4"] if args.quick else [
        m for m in METHODS if m != "implicit_euler"]
    results: dict = {"pymunk": bench_pymunk(sizes, methods, args.repeats, seconds)}
    results["pymunk_ratio"] = results["pymunk"]["ratio"]
    results["scaling"] = bench_scaling([32, 64, 128], "symplectic_euler", args.repeats, seconds)
    results["scaling_ratio"] = results["scaling"]["scaling_ratio"]
    results["peak_mb_128"] = peak_memory_mb()
    if not args.skip_envs:
        results["envs"] = bench_envs("ClothSlide-v0", args.repeats, 20 if args.quick else 60)
        results["vector_speedup"] = results["envs"]["vector_speedup"]
    results["accuracy"] = bench_accuracy()
    print(json.dumps(results, indent=2) if args.json else markdown(results))
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__)
    add_arguments(parser)
    sys.exit(main(parser.parse_args()))
