"""cparticles bench, the scaling sections: threads of the native vector env, and implicit
Euler from small to large cloths.

(e) threads. The native vector env of each task that asks for it (ClothSlide and SliderCrank)
    with 512 copies at 1, 2 and all cores' threads (``num_threads``), driven by uniform random
    actions (resets included): env-steps per second. Beside it, the machine's own answer to
    "what do two cores give": the same env (512 copies, one thread) stepped by one busy process
    alone, then by two busy processes at once; their summed rate over the lone one is the
    control. A thread count's speedup is its rate over one thread's in the same round, and
    ``of_control`` is the two-thread speedup over the control's (1.0: threads get all the
    machine gives two processes).
(f) implicit Euler. Cost per step on the stiff cloth (n x n particles of 0.01 kg, 0.1 m apart,
    ks = 2000 N/m, kd = 0.05 N s/m, top row on a wire, gravity, h = 1/60 s) at 15, 30, 60 and
    120, with the conjugate-gradient and the direct solve, and its growth per doubling of n
    (4x is linear in the particle count).

Every figure is a median over rounds; within a round the compared settings run one after the
other (thread counts, then the lone process, then the pair), so a machine whose load changes
affects them alike.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from constrained_particles import ParticleSystem, scenes

if TYPE_CHECKING:
    from .bench import Progress

THREAD_COPIES = 512
IMPLICIT_SIZES = (15, 30, 60, 120)
IMPLICIT_H = 1.0 / 60.0  #: implicit Euler's step on the stiff cloth (s)


def cores() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def thread_counts() -> list[int]:
    """1, 2 and every core, without repeats."""
    return sorted({1, 2, cores()})


# ---------------------------------------------------------------- (e) threads
def _vector(env_id: str, copies: int, threads: int, warmup: int | None = None
            ) -> tuple[Any, Any]:
    """A reset native vector env, warmed up through an episode's end (so every path the timed
    steps take has loaded its compiled code; ``warmup`` steps instead if given), and its cycle
    of random action batches."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)
    from cparticles.bench import _random_batches

    vec = gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point",
                       num_threads=threads)
    vec.reset(seed=0)
    batches = _random_batches(vec, 0)
    if warmup is None:
        warmup = (gym.spec(env_id).max_episode_steps or 0) + 2
    for _ in range(warmup):
        vec.step(next(batches))
    return vec, batches


def _rate(vec: Any, batches: Any, seconds: float, copies: int) -> float:
    """Env-steps per second of ``vec`` over whole steps lasting at least ``seconds``."""
    k, t0 = 0, time.perf_counter()
    while True:
        vec.step(next(batches))
        k += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return k * copies / elapsed


def _busy(env_id: str, copies: int, warmup: int | None) -> None:
    """A control process (``python -m cparticles.bench_scaling busy ENV COPIES [WARMUP]``):
    steps its own vector env (one thread); for each line ``START SECONDS`` on stdin, from the
    wall-clock time START for SECONDS, then prints its rate (env-steps/s). Ends at the end of
    stdin."""
    vec, batches = _vector(env_id, copies, 1, warmup)
    print("ready", flush=True)
    for line in sys.stdin:
        start_at, seconds = (float(v) for v in line.split())
        time.sleep(max(start_at - time.time(), 0.0))
        print(_rate(vec, batches, seconds, copies), flush=True)


class _Control:
    """The busy control processes of one env, started at once and ended on exit."""

    def __init__(self, env_id: str, copies: int, warmup: int | None, count: int = 2) -> None:
        command = [sys.executable, "-m", "cparticles.bench_scaling", "busy", env_id, str(copies),
                   *([] if warmup is None else [str(warmup)])]
        self.procs = [subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                       text=True) for _ in range(count)]

    def __enter__(self) -> _Control:
        for p in self.procs:  # each has compiled (or loaded) its kernels and warmed up
            if self._line(p) != "ready":
                raise RuntimeError("a control process did not start")
        return self

    @staticmethod
    def _line(p: subprocess.Popen) -> str:
        assert p.stdout is not None
        line = p.stdout.readline().strip()
        if not line:
            raise RuntimeError(f"a control process ended (exit code {p.wait()})")
        return line

    def rate(self, busy: int, seconds: float) -> float:
        """Summed env-steps per second of the first ``busy`` processes stepping together."""
        start_at = time.time() + 0.05
        for p in self.procs[:busy]:
            assert p.stdin is not None
            p.stdin.write(f"{start_at!r} {seconds!r}\n")
            p.stdin.flush()
        return sum(float(self._line(p)) for p in self.procs[:busy])

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            if p.stdin is not None:
                p.stdin.close()
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:  # pragma: no cover - a stuck control process
                p.kill()
                p.wait()


def bench_threads(env_ids: tuple[str, ...] | None = None, copies: int = THREAD_COPIES,
                  repeats: int = 5, seconds: float = 0.5, progress: Progress | None = None,
                  warmup: int | None = None) -> dict[str, Any]:
    """Section (e): for each env, env-steps per second at each thread count, the speedups over
    one thread, and the two-process control (see the module docstring). ``warmup``: untimed
    steps of every env before timing (default: through the end of an episode). ``env_ids``:
    default, the tasks whose declarations ask for it (``TaskSpec.bench_vector``)."""
    if env_ids is None:
        from cparticles.bench import vector_envs

        env_ids = vector_envs()
    counts = thread_counts()
    out: dict[str, Any] = {"cores": cores(), "copies": copies, "threads": counts,
                           "repeats": repeats, "batch_seconds": seconds}
    for env_id in env_ids:
        if progress is not None:
            progress.section(f"threads {env_id}")
        made = {k: _vector(env_id, copies, k, warmup) for k in counts}
        rates: dict[Any, list[float]] = {**{k: [] for k in counts}, "one": [], "two": []}
        try:
            with _Control(env_id, copies, warmup) as control_processes:
                for _ in range(repeats):
                    for k in counts:
                        rates[k].append(_rate(*made[k], seconds, copies))
                    rates["one"].append(control_processes.rate(1, seconds))
                    rates["two"].append(control_processes.rate(2, seconds))
                    if progress is not None:
                        progress.update()
        finally:
            for vec, _ in made.values():
                vec.close()
        control = [b / a for a, b in zip(rates["one"], rates["two"], strict=True)]
        speedup = {k: statistics.median(r / o for r, o in zip(rates[k], rates[1], strict=True))
                   for k in counts}
        out[env_id] = {
            "env_steps_per_s": {k: statistics.median(rates[k]) for k in counts},
            "speedup": speedup,
            "control_one_process": statistics.median(rates["one"]),
            "control_two_processes": statistics.median(rates["two"]),
            "control_speedup": statistics.median(control),
            "of_control": statistics.median(
                r / o / c for r, o, c in zip(rates[min(2, max(counts))], rates[1], control,
                                             strict=True)),
        }
    return out


class _Spinners:
    """Processes that keep every core busy (a Python loop each), started on entry and ended,
    by their own handles, on exit."""

    def __init__(self, count: int) -> None:
        self.count = count
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> _Spinners:
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                      for _ in range(self.count)]
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            p.kill()
            p.wait()


def bench_busy(env_id: str | None = None, copies: int = THREAD_COPIES, repeats: int = 9,
               seconds: float = 0.6, settle: float = 3.0) -> dict[str, Any]:
    """Threads on busy cores: the native vector env of ``env_id`` (default: the first task
    whose declaration asks for the thread benchmarks, ClothSlide) (``copies`` copies, uniform
    random actions) at 1 thread and at 2 threads, with one spinning process per core running
    beside it (:func:`cores` of them). Each env first runs ``settle`` s among the spinners
    (time for the thread gauge, ``constrained_particles.parallel.Gauge``, to find its way),
    then ``repeats`` rounds time both for ``seconds`` each in turn; ``ratio``: the median
    over rounds of 2 threads' rate over 1 thread's in the round (1.0: the second thread costs
    nothing when it has no core to run on). The same with no spinners (``idle_ratio``) after
    it."""
    if env_id is None:
        from cparticles.bench import vector_envs

        env_id = vector_envs()[0]
    made = {k: _vector(env_id, copies, k) for k in (1, 2)}
    out: dict[str, Any] = {"env_id": env_id, "copies": copies, "spinners": cores(),
                           "repeats": repeats}
    try:
        for label, count in (("busy", cores()), ("idle", 0)):
            with _Spinners(count):
                for k in (1, 2):
                    _rate(*made[k], settle, copies)
                rates: dict[int, list[float]] = {1: [], 2: []}
                for _ in range(repeats):
                    for k in (1, 2):
                        rates[k].append(_rate(*made[k], seconds, copies))
            out[f"{label}_env_steps_per_s"] = {k: statistics.median(r) for k, r in rates.items()}
            out[f"{label}_ratio"] = statistics.median(
                b / a for a, b in zip(rates[1], rates[2], strict=True))
            out[f"{label}_ratios"] = [b / a for a, b in zip(rates[1], rates[2], strict=True)]
    finally:
        for vec, _ in made.values():
            vec.close()
    out["ratio"] = out.pop("busy_ratio")
    return out


def threads_markdown(r: dict[str, Any]) -> list[str]:
    """Section (e) as Markdown lines."""
    counts = r["threads"]
    lines = ["", f"Threads ({r['copies']} copies, {r['cores']} cores; median of {r['repeats']} "
             "rounds): env-steps/s and speedup over 1 thread; control: 2 busy processes over 1",
             "", "| env | " + " | ".join(f"{k} thread{'s' * (k > 1)}" for k in counts)
             + " | control (2 processes) | 2 threads / control |",
             "|---|" + "---|" * (len(counts) + 2)]
    for env_id in r:
        if not isinstance(r[env_id], dict):
            continue
        e = r[env_id]
        cells = [f"{e['env_steps_per_s'][k]:.4g} ({e['speedup'][k]:.2f}x)" for k in counts]
        lines.append(f"| {env_id} | " + " | ".join(cells)
                     + f" | {e['control_speedup']:.2f}x | {e['of_control']:.2f} |")
    return lines


# ---------------------------------------------------------------- (f) implicit Euler
def scaling_cloth(n: int, implicit_solver: str) -> ParticleSystem:
    """The stiff cloth at ``n`` x ``n`` particles (section (f))."""
    s = scenes.cloth(n, n, ks=2000.0, mass=0.01, kd=0.05, bend=False, wall_x=None, drag=0.0)
    s.implicit_solver = implicit_solver
    return s


def bench_implicit_scaling(sizes: tuple[int, ...] = IMPLICIT_SIZES, repeats: int = 5,
                           steps: int = 10, progress: Progress | None = None) -> dict[str, Any]:
    """implicit_euler's cost per step (ms) on the stiff cloth at n x n particles, h = 1/60 s,
    with both linear solvers (``implicit_solver="cg"`` and ``"direct"``), and its growth from
    one size to the next (linear in the particle count is (n2/n1)^2, 4x per doubling).

    A batch is ``steps`` steps of a fresh cloth after one untimed step (which builds the
    topology's structures; the CG warm start then carries over within the batch), so every
    batch does the same work. ``repeats`` rounds, each timing every size with both solvers in
    turn (cg, then direct); the figures are the medians over rounds. Also reports CG's median
    iteration count per step, the solver ``implicit_solver="auto"`` picks, and the largest
    position difference (m) between the two solvers after the batch."""
    from constrained_particles import implicit

    times: dict[str, dict[int, list[float]]] = {k: {n: [] for n in sizes}
                                                for k in ("cg", "direct")}
    iterations: dict[int, list[int]] = {n: [] for n in sizes}
    difference: dict[int, float] = {}
    for _ in range(repeats):
        for n in sizes:
            final = {}
            for solver in ("cg", "direct"):
                s = scaling_cloth(n, solver)
                s.step(IMPLICIT_H, "implicit_euler")
                start = time.perf_counter()
                for _ in range(steps):
                    s.step(IMPLICIT_H, "implicit_euler")
                    if solver == "cg":
                        iterations[n].append(implicit.last_solve(s)["cg_iterations"])
                times[solver][n].append((time.perf_counter() - start) / steps)
                used = implicit.last_solve(s)["solver"]
                if used != solver:
                    raise RuntimeError(f"{n}x{n}: asked for {solver}, the step used {used}")
                final[solver] = s.x
            difference[n] = float(np.max(np.abs(final["cg"] - final["direct"])))
        if progress is not None:
            progress.update()
    ms = {k: [1e3 * statistics.median(t[n]) for n in sizes] for k, t in times.items()}
    pairs = list(zip(sizes[:-1], sizes[1:], strict=True))
    auto = []
    for n in sizes:
        s = scaling_cloth(n, "auto")
        s.step(IMPLICIT_H, "implicit_euler")
        auto.append(implicit.last_solve(s)["solver"])
    return {"sizes": list(sizes), "particles": [n * n for n in sizes], "repeats": repeats,
            "steps_per_batch": steps, "dt": IMPLICIT_H, "ms_per_step": ms,
            "growth": {k: [v[i + 1] / v[i] for i in range(len(pairs))] for k, v in ms.items()},
            "linear_growth": [(b / a) ** 2 for a, b in pairs],
            "cg_iterations": [float(np.median(iterations[n])) for n in sizes],
            "cg_minus_direct_max_m": [difference[n] for n in sizes], "auto_picks": auto}


def implicit_table(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`bench_implicit_scaling`'s result."""
    lines = [f"implicit_euler on the stiff cloth, h = 1/60 s: ms per step (median of "
             f"{result['repeats']} alternated batches of {result['steps_per_batch']} steps)",
             f"{'cloth':>8}{'cg':>10}{'growth':>8}{'direct':>10}{'growth':>8}{'linear':>8}"
             f"{'CG its':>8}{'auto':>8}{'|cg-direct| m':>15}"]
    for k, n in enumerate(result["sizes"]):
        grow = [f"{result['growth'][s][k - 1]:.2f}x" if k else "" for s in ("cg", "direct")]
        linear = f"{result['linear_growth'][k - 1]:.2f}x" if k else ""
        lines.append(f"{f'{n}x{n}':>8}{result['ms_per_step']['cg'][k]:>10.2f}{grow[0]:>8}"
                     f"{result['ms_per_step']['direct'][k]:>10.2f}{grow[1]:>8}{linear:>8}"
                     f"{result['cg_iterations'][k]:>8.0f}{result['auto_picks'][k]:>8}"
                     f"{result['cg_minus_direct_max_m'][k]:>15.1e}")
    return "\n".join(lines)


if __name__ == "__main__":
    if sys.argv[1:2] == ["busy"] and len(sys.argv) in (4, 5):
        _busy(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]) if len(sys.argv) == 5 else None)
    elif sys.argv[1:] == ["busy-cores"]:
        import json

        print(json.dumps(bench_busy(), indent=1))
    else:
        sys.exit("usage: python -m cparticles.bench_scaling busy ENV_ID COPIES [WARMUP]\n"
                 "       python -m cparticles.bench_scaling busy-cores")
