"""cparticles bench: constrained-particles against pymunk, CartPole and itself, in one run.

Every figure is a median over ``--repeats`` (at least 5) timed batches after warm-up, and the
batches of the engines compared in a figure alternate (round-robin), so a machine that slows
down or speeds up during the run affects them alike and their ratios stay meaningful.

Sections, in the order printed:

(a) pymunk at equal accuracy. The same N x N cloth (structural, shear and bend damped springs,
    top row on a horizontal wire, gravity) in both engines at dt = 1 ms. pymunk runs with 1 and
    with 10 solver iterations; each setting's error, and each integrator's, is measured after
    0.3 s of the 20 x 20 cloth against a fine rk4 reference (dt = 0.1 ms). The headline ratio
    is symplectic_euler against the cheapest pymunk setting whose error is at most twice ours.
    Each timed call advances 10 steps (``step(1e-3, steps=10)`` for ours, ten ``space.step``
    for pymunk), so our one-off cost per call (argument checks and entering compiled code,
    about 8 us) is shared by ten steps as in the environments' substeps.
(b) small envs. One env step of every registered task in each of its action modes (ClothSlide,
    SliderCrank, ChainSwing, ClothPin, ...) as a multiple of one step of gymnasium's CartPole-v1,
    all made by ``gym.make`` with the default wrappers and driven by uniform random actions
    (resets included when an episode ends).
(c) vector scaling. The native vector env of each task whose declaration asks for it
    (``TaskSpec.bench_vector``: ClothSlide and SliderCrank) at 1, 8, 64, 512 and 4096 copies:
    env-steps per second, and its cost per particle-step against stepping the bare tiled system
    (``task.system``) the same number of substeps in one call.
(d) the rest: particle-steps per second of every integrator against pymunk (10 iterations),
    cost per particle-step for 32 / 64 / 128 square cloths, peak memory of the 128 x 128 cloth,
    the first of those tasks as single env, SyncVectorEnv(64), AsyncVectorEnv(2) and native
    vector env(64), and the error of rk4 and pymunk at equal CPU time.
(e) threads: the native vector env with 512 copies at 1, 2 and all cores' threads, beside two
    busy processes against one (the machine's own control); then the first of those tasks at 2
    threads against 1 with a spinning process on every core (``bench_busy``); see
    :mod:`cparticles.bench_scaling`.
(f) implicit Euler's cost per step on the stiff cloth at 15 x 15 to 120 x 120, with the
    conjugate-gradient and the direct solve; see :mod:`cparticles.bench_scaling`.

Progress goes to stderr (tqdm) when it is a terminal; ``--quiet`` turns it off.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from constrained_particles import METHODS, ParticleSystem, SimulationDiverged, scenes
from constrained_particles.arguments import int_at_least, progress_enabled
from constrained_particles.extras import require

if TYPE_CHECKING:  # (the verify extra)
    from verification.pymunk_check import PymunkScene

DT = 1e-3  #: physics step of the cloth comparison (s)
#: Steps of DT each timed call advances in the cloth comparison: ``step(DT, steps=CALL_STEPS)``
#: for ours, CALL_STEPS ``space.step(DT)`` calls for pymunk (same work, each engine's own API).
CALL_STEPS = 10
ACCURACY_N = 20  #: cloth size whose errors decide "equal accuracy"
ACCURACY_SECONDS = 0.3  #: simulated time of the accuracy runs (s)
REFERENCE_DT = 1e-4  #: rk4 step of the reference trajectory (s)
PYMUNK_ITERATIONS = (1, 10)
EQUAL_ACCURACY_FACTOR = 2.0  #: pymunk counts as "as accurate" within this factor of our error
OURS = "symplectic_euler"  #: our integrator in the headline ratio
VECTOR_COPIES = (1, 8, 64, 512, 4096)
MIN_REPEATS = 5
WORK_STEPS = 400  #: untimed env steps over which integrator steps per physics step are counted


def small_envs() -> tuple[tuple[str, str], ...]:
    """``(env id, action mode)`` of every registered task and mode, timed as a single env in
    section (b)."""
    import envs

    return tuple((spec.id, mode) for spec in envs.task_specs() for mode in spec.action_modes)


def vector_envs() -> tuple[str, ...]:
    """The ids whose declarations ask for the vector and thread sections
    (``TaskSpec.bench_vector``), in registration order."""
    import envs

    return tuple(spec.id for spec in envs.task_specs() if spec.bench_vector)


# ---------------------------------------------------------------- the cloth in both engines
def our_cloth(n: int) -> ParticleSystem:
    """The benchmark cloth, n x n particles: ``scenes.cloth(n, n, wall_x=None, drag=0)``."""
    return scenes.cloth(n, n, wall_x=None, drag=0.0)


def pymunk_cloth(system: ParticleSystem, iterations: int = 10) -> PymunkScene:
    """The same cloth in pymunk (``verification.pymunk_check.to_pymunk``: infinite-moment
    bodies, ``DampedSpring``s, ``GrooveJoint`` wires) with ``iterations`` solver iterations. The
    result has ``step(dt)`` and ``bodies``."""
    from verification.pymunk_check import to_pymunk

    return to_pymunk(system, iterations)


def pymunk_positions(scene: PymunkScene) -> np.ndarray:
    """Body positions of a :func:`pymunk_cloth` scene as an (n, 2) array in metres."""
    return np.array([tuple(b.position) for b in scene.bodies])


# ---------------------------------------------------------------- timing
class Progress:
    """A tqdm bar on stderr over units of work, or nothing when disabled."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="bench", unit="batch", file=sys.stderr)

    def section(self, name: str) -> None:
        if self.bar is not None:
            self.bar.set_description(name)

    def update(self, k: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(k)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def alternate(calls: dict[str, Callable[[], object]], repeats: int, seconds: float,
              progress: Progress | None = None, warmup: int = 3) -> dict[str, list[float] | None]:
    """Seconds per call of each ``calls[name]``: one sample per repeat, from a batch of whole
    calls lasting at least ``seconds`` (at least one call). Batches alternate round-robin.
    A call that raises :class:`SimulationDiverged` drops that entry (its value is None)."""
    samples: dict[str, list[float] | None] = {name: [] for name in calls}
    live = dict(calls)
    for name, call in calls.items():
        try:
            for _ in range(warmup):
                call()
        except SimulationDiverged:
            del live[name]
            samples[name] = None
    for _ in range(repeats):
        for name, call in list(live.items()):
            k, t0 = 0, time.perf_counter()
            try:
                while True:
                    call()
                    k += 1
                    elapsed = time.perf_counter() - t0
                    if elapsed >= seconds:
                        break
            except SimulationDiverged:
                del live[name]
                samples[name] = None
                continue
            sample = samples[name]
            assert sample is not None
            sample.append(elapsed / k)
        if progress is not None:
            progress.update()
    return samples


def median(values: list[float] | None) -> float | None:
    """The median, or None for a dropped entry."""
    return None if not values else statistics.median(values)


def median_ratio(a: list[float] | None, b: list[float] | None) -> float | None:
    """Median over repeats of ``a[k] / b[k]`` (two entries timed in the same round)."""
    if not a or not b:
        return None
    return statistics.median(x / y for x, y in zip(a, b, strict=False))


# ---------------------------------------------------------------- (a) pymunk, equal accuracy
def cloth_errors(n: int = ACCURACY_N, seconds: float = ACCURACY_SECONDS,
                 methods: tuple[str, ...] = (OURS, "midpoint", "rk4"),
                 progress: Progress | None = None) -> dict[str, float | None]:
    """Largest particle position error (m) after ``seconds`` of the n x n cloth at dt = 1 ms,
    against rk4 at dt = 0.1 ms: for each of our ``methods`` and for pymunk at each of
    :data:`PYMUNK_ITERATIONS` (keys ``pymunk_1``, ``pymunk_10``). None: diverged."""
    reference = our_cloth(n)
    for _ in range(int(round(seconds / REFERENCE_DT))):
        reference.step(REFERENCE_DT, "rk4")
    steps = int(round(seconds / DT))
    out: dict[str, float | None] = {}
    for method in methods:
        s = our_cloth(n)
        try:
            for _ in range(steps):
                s.step(DT, method)
            out[method] = float(np.abs(s.x - reference.x).max())
        except SimulationDiverged:
            out[method] = None
        if progress is not None:
            progress.update()
    for iterations in PYMUNK_ITERATIONS:
        scene = pymunk_cloth(our_cloth(n), iterations)
        for _ in range(steps):
            scene.step(DT)
        out[f"pymunk_{iterations}"] = float(np.abs(pymunk_positions(scene) - reference.x).max())
        if progress is not None:
            progress.update()
    return out


def bench_pymunk(sizes: list[int], methods: list[str], repeats: int, seconds: float,
                 progress: Progress | None = None) -> dict[str, Any]:
    """Particle-steps per second of each of our ``methods`` and of pymunk at each iteration
    count, per cloth size, and our rate over pymunk's (None for a diverging integrator). Each
    timed call advances :data:`CALL_STEPS` steps of :data:`DT`."""
    out: dict[str, Any] = {"ours": {}, "pymunk": {}, "ratio": {}}
    for n in sizes:
        calls: dict[str, Callable[[], Any]] = {}
        for iterations in PYMUNK_ITERATIONS:
            scene = pymunk_cloth(our_cloth(n), iterations)

            def pymunk_call(scene: Any = scene) -> None:
                for _ in range(CALL_STEPS):
                    scene.step(DT)

            calls[f"pymunk_{iterations}"] = pymunk_call
        for method in methods:
            system = our_cloth(n)
            calls[method] = lambda s=system, m=method: s.step(DT, m, steps=CALL_STEPS)
        if progress is not None:
            progress.section(f"pymunk {n}x{n}")
        times = alternate(calls, repeats, seconds, progress)
        rate = {name: None if median(t) is None else n * n * CALL_STEPS / median(t)
                for name, t in times.items()}
        out["pymunk"][n] = {k: rate[f"pymunk_{k}"] for k in PYMUNK_ITERATIONS}
        out["ours"][n] = {m: rate[m] for m in methods}
        out["ratio"][n] = {m: {k: median_ratio(times[f"pymunk_{k}"], times[m])
                               for k in PYMUNK_ITERATIONS} for m in methods}
    return out


def equal_accuracy(errors: dict[str, float | None], pymunk: dict[str, Any]) -> dict[str, Any]:
    """The headline comparison: :data:`OURS` against the cheapest pymunk setting whose error is
    at most :data:`EQUAL_ACCURACY_FACTOR` times ours (if none is, the most accurate one)."""
    ours = errors[OURS]
    settings = {k: errors[f"pymunk_{k}"] for k in PYMUNK_ITERATIONS}
    if ours is None:
        raise RuntimeError(f"{OURS} diverged on the benchmark cloth")
    close = [k for k, e in settings.items() if e is not None
             and e <= EQUAL_ACCURACY_FACTOR * ours]
    def cost(k: int) -> float:  # seconds per particle-step, summed over the cloth sizes
        return sum(1.0 / rates[k] if rates[k] else np.inf for rates in pymunk["pymunk"].values())

    if close:
        chosen = min(close, key=cost)
        rule = f"cheapest pymunk setting with error <= {EQUAL_ACCURACY_FACTOR:g}x ours"
    else:
        chosen = min(settings, key=lambda k: settings[k] or np.inf)
        rule = "no pymunk setting is as accurate; its most accurate one"
    return {"method": OURS, "pymunk_iterations": chosen, "rule": rule,
            "our_error": ours, "pymunk_error": settings[chosen],
            "ratio": {n: r[OURS][chosen] for n, r in pymunk["ratio"].items()}}


# ---------------------------------------------------------------- (b) small envs
def _stepper(env: Any, seed: int) -> Callable[[], None]:
    """One env step under pre-drawn random actions, resetting when the episode ends."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = itertools.cycle([env.action_space.sample() for _ in range(997)])

    def step() -> None:
        _, _, terminated, truncated, _ = env.step(next(actions))
        if terminated or truncated:
            env.reset()

    return step


def bench_small_envs(repeats: int, seconds: float, progress: Progress | None = None,
                     variant: tuple[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """Seconds per single-env step of each of :func:`small_envs` and of CartPole-v1, and each
    as a multiple of CartPole's (median over repeats of the per-round ratio). ``variant``:
    ``(env id, keyword arguments)`` of one more env timed in each of its action modes (rows
    ``"ID[k=v,...]/mode"``)."""
    import gymnasium as gym

    import envs

    made = {"CartPole-v1": gym.make("CartPole-v1")}
    for env_id, mode in small_envs():
        made[f"{env_id}/{mode}"] = gym.make(env_id, action_mode=mode)
    if variant is not None:
        env_id, kwargs = variant
        label = env_id + "[" + ",".join(f"{k}={v}" for k, v in kwargs.items()) + "]"
        for mode in envs.task_spec(env_id).action_modes:
            made[f"{label}/{mode}"] = gym.make(env_id, action_mode=mode, **kwargs)
    calls = {name: _stepper(env, seed=0) for name, env in made.items()}
    if progress is not None:
        progress.section("small envs")
    times = alternate(calls, repeats, seconds, progress)
    for env in made.values():
        env.close()
    return {"us_per_step": {name: 1e6 * median(t) for name, t in times.items()},
            "vs_cartpole": {name: median_ratio(t, times["CartPole-v1"])
                            for name, t in times.items() if name != "CartPole-v1"}}


# ---------------------------------------------------------------- (c) vector scaling
def _random_batches(vec: Any, seed: int) -> Iterator[np.ndarray]:
    """16 batches of uniform random actions for the vector env ``vec``, cycled."""
    rng = np.random.default_rng(seed)
    return itertools.cycle(rng.uniform(-1, 1, (16, *vec.action_space.shape)).astype(np.float32))


def bench_vector(env_id: str, copies: tuple[int, ...], repeats: int, seconds: float,
                 progress: Progress | None = None) -> dict[str, Any]:
    """The native vector env of ``env_id`` at each number of copies: env-steps per second and
    microseconds per particle-step, against the bare tiled system advanced ``substeps`` steps
    in one call."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)

    out: dict[str, Any] = {}
    for count in copies:
        vec = gym.make_vec(env_id, num_envs=count, vectorization_mode="vector_entry_point")
        vec.reset(seed=0)
        task = vec.unwrapped.task
        bare = task.system.copy()
        batches = _random_batches(vec, 0)

        def bare_step(bare: ParticleSystem = bare, task: Any = task) -> None:
            bare.step(task.dt, task.integrator, steps=task.substeps)

        if progress is not None:
            progress.section(f"{env_id} x{count}")
        # warm up through the end of an episode, so that every path the timed steps take
        # (the copies' resets included) has loaded its compiled code before timing starts
        episode = gym.spec(env_id).max_episode_steps or 0
        times = alternate({"env": lambda vec=vec, b=batches: vec.step(next(b)),
                           "bare": bare_step},
                          repeats, seconds, progress, warmup=episode + 2)
        vec.close()
        particle_steps = count * task.n * task.substeps
        env_t, bare_t = median(times["env"]), median(times["bare"])
        over = median_ratio(times["env"], times["bare"])
        work = work_factor(env_id, count, rng_seed=0, steps=WORK_STEPS)
        out[count] = {
            "env_steps_per_s": count / env_t,
            "us_per_particle_step": 1e6 * env_t / particle_steps,
            "bare_us_per_particle_step": 1e6 * bare_t / particle_steps,
            "env_over_bare": over,
            "integrator_steps_per_physics_step": work,
            "env_over_bare_per_step_taken": None if over is None else over / work,
        }
    return out


def work_factor(env_id: str, count: int, rng_seed: int = 0, steps: int = 400) -> float:
    """Integrator steps the native vector env of ``env_id`` takes per nominal physics step,
    averaged over copies and the first ``steps`` env steps of the rollout :func:`bench_vector`
    times (the same seed and random actions; untimed, and the timed run may go on longer): 1
    unless copies split their steps into pieces (``ParticleTask.pieces``), as fast ones do
    under random actions; the bare system at rest never does."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)

    probe = gym.make_vec(env_id, num_envs=1, vectorization_mode="vector_entry_point")
    splits = probe.unwrapped.task.step_travel != math.inf
    probe.close()
    if not splits:
        return 1.0
    vec = gym.make_vec(env_id, num_envs=count, vectorization_mode="vector_entry_point")
    vec.reset(seed=0)
    task = vec.unwrapped.task
    batches = _random_batches(vec, rng_seed)
    decided: list[float] = []
    decide = task._decide

    def recorded(system: Any) -> tuple:  # the counts each env step uses (not those of a
        out = decide(system)              # diverged copy's probe)
        if system is task.system:
            decided.append(float(out[0].mean()))
        return out

    task._decide = recorded  # (every env step asks it, through the task's simulate)
    for _ in range(steps):
        vec.step(next(batches))
    vec.close()
    return float(np.mean(decided)) if decided else 1.0


# ---------------------------------------------------------------- (d) the rest
def bench_scaling(sizes: list[int], method: str, repeats: int, seconds: float,
                  progress: Progress | None = None) -> dict[str, Any]:
    """Microseconds per particle-step for each cloth size, and the largest over the smallest."""
    if progress is not None:
        progress.section("scaling")
    systems = {n: our_cloth(n) for n in sizes}
    times = alternate({n: (lambda s=s: s.step(DT, method)) for n, s in systems.items()},
                      repeats, seconds, progress)
    cost = {n: 1e6 * median(times[n]) / (n * n) for n in sizes}
    return {"method": method, "us_per_particle_step": cost,
            "scaling_ratio": cost[sizes[-1]] / cost[sizes[0]]}


def peak_memory_mb(n: int = 128, steps: int = 20) -> float:
    """Peak resident memory (MB) of a fresh process that builds the n x n cloth and steps rk4."""
    code = (
        "import resource\n"
        "from cparticles.bench import our_cloth\n"
        f"s = our_cloth({n})\n"
        f"for _ in range({steps}): s.step({DT}, 'rk4')\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


def bench_env_modes(env_id: str, repeats: int, seconds: float,
                    progress: Progress | None = None) -> dict[str, Any]:
    """Env-steps per second of ``env_id`` as a single env, SyncVectorEnv(64), AsyncVectorEnv
    (2 workers) and the native vector env (64), and native over sync."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)

    configs = {
        "single": (gym.make(env_id), 1),
        "sync_64": (gym.make_vec(env_id, num_envs=64, vectorization_mode="sync"), 64),
        "async_2": (gym.make_vec(env_id, num_envs=2, vectorization_mode="async"), 2),
        "native_64": (gym.make_vec(env_id, num_envs=64, vectorization_mode="vector_entry_point"),
                      64),
    }
    calls: dict[str, Callable[[], Any]] = {"single": _stepper(configs["single"][0], seed=0)}
    rng = np.random.default_rng(0)
    for name, (env, _) in configs.items():
        if name != "single":
            env.reset(seed=0)
            batches = itertools.cycle(rng.uniform(-1, 1, (16, *env.action_space.shape))
                                      .astype(np.float32))
            calls[name] = lambda env=env, b=batches: env.step(next(b))
    if progress is not None:
        progress.section(f"{env_id} vector modes")
    times = alternate(calls, repeats, seconds, progress)
    for env, _ in configs.values():
        env.close()
    rates = {name: configs[name][1] / median(t) for name, t in times.items()}
    return {**rates, "vector_speedup": rates["native_64"] / rates["sync_64"]}


def bench_accuracy_at_equal_time(n: int = 10, horizon: float = 0.5,
                                 progress: Progress | None = None) -> dict[str, Any]:
    """(CPU seconds, max position error in m, dt) for rk4 and pymunk (30 iterations) at several
    dt, and each one's error interpolated (log-log) at a CPU time both reach."""
    reference = our_cloth(n)
    for _ in range(int(round(horizon / REFERENCE_DT))):
        reference.step(REFERENCE_DT, "rk4")
    out: dict[str, Any] = {"rk4": [], "pymunk": []}
    for dt in (4e-3, 2e-3, 1e-3, 5e-4):
        s = our_cloth(n)
        t0 = time.process_time()
        for _ in range(int(round(horizon / dt))):
            s.step(dt, "rk4")
        out["rk4"].append((time.process_time() - t0, float(np.abs(s.x - reference.x).max()), dt))
    if progress is not None:
        progress.update()
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5):
        scene = pymunk_cloth(our_cloth(n), iterations=30)
        t0 = time.process_time()
        for _ in range(int(round(horizon / dt))):
            scene.step(dt)
        err = float(np.abs(pymunk_positions(scene) - reference.x).max())
        out["pymunk"].append((time.process_time() - t0, err, dt))
    if progress is not None:
        progress.update()
    t_common = min(max(r[0] for r in out["rk4"]), max(r[0] for r in out["pymunk"]))
    for engine in ("rk4", "pymunk"):
        pts = sorted(out[engine])
        t, e = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        out[f"{engine}_error_at_equal_time"] = float(np.exp(np.interp(np.log(t_common), t, e)))
    out.update(equal_cpu_seconds=t_common, cloth=n, seconds=horizon)
    return out


# ---------------------------------------------------------------- report
def _x(value: float | None, digits: int = 2) -> str:
    return "diverges" if value is None else f"{value:.{digits}f}x"


def markdown(r: dict[str, Any]) -> str:
    """The results as text with Markdown tables, the equal-accuracy ratio first."""
    eq = r["equal_accuracy"]
    lines = [f"pymunk at equal accuracy: {OURS} is "
             + ", ".join(f"{_x(v)} at {n}x{n}" for n, v in eq["ratio"].items())
             + f" pymunk with {eq['pymunk_iterations']} iteration(s) ({eq['rule']}; errors after "
             f"{eq['seconds']:g} s of the {eq['cloth']}x{eq['cloth']} cloth at dt = 1 ms against "
             f"rk4 at 0.1 ms: ours {eq['our_error']:.2e} m, pymunk {eq['pymunk_error']:.2e} m).",
             "", f"| engine | error after {eq['seconds']:g} s (m) |", "|---|---|"]
    lines += [f"| {name} | {'diverges' if e is None else f'{e:.2e}'} |"
              for name, e in r["cloth_errors"].items()]
    a = r["pymunk"]
    methods = list(next(iter(a["ours"].values())))
    head = " | ".join(f"{m} (vs it=1, it=10)" for m in methods)
    lines += ["", f"| N | pymunk it=1 | pymunk it=10 | {head} |",
              "|---|---|---|" + "---|" * len(methods)]
    for n in a["ours"]:
        cells = ["diverges" if a["ours"][n][m] is None else
                 f"{a['ours'][n][m]:.3g} ({_x(a['ratio'][n][m][1])}, {_x(a['ratio'][n][m][10])})"
                 for m in methods]
        lines.append(f"| {n} | {a['pymunk'][n][1]:.3g} | {a['pymunk'][n][10]:.3g} | "
                     + " | ".join(cells) + " |")
    lines.append("(particle-steps per second)")
    s = r["small_envs"]
    lines += ["", "| single env (gym.make) | us per step | x CartPole-v1 |", "|---|---|---|"]
    lines += [f"| {name} | {us:.1f} | {s['vs_cartpole'].get(name, 1.0):.1f} |"
              for name, us in s["us_per_step"].items()]
    for env_id, rows in r["vector_scaling"].items():
        lines += ["", f"| {env_id} native vector env: copies | env-steps/s | us per particle-step"
                  " | bare system | env / bare | integrator steps per step | env / bare per "
                  "step taken |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {c} | {v['env_steps_per_s']:.4g} | {v['us_per_particle_step']:.3g} | "
                  f"{v['bare_us_per_particle_step']:.3g} | {v['env_over_bare']:.2f} | "
                  f"{v.get('integrator_steps_per_physics_step', 1.0):.3f} | "
                  f"{v.get('env_over_bare_per_step_taken', v['env_over_bare']):.2f} |"
                  for c, v in rows.items()]
    c = r["scaling"]
    lines += ["", f"Cost per particle-step ({c['method']}): " + ", ".join(
        f"N={n}: {v:.3g} us" for n, v in c["us_per_particle_step"].items())
        + f"; ratio {r['scaling_ratio']:.2f}. Peak memory 128x128: {r['peak_mb_128']:.0f} MB."]
    if "envs" in r:
        lines += ["", f"| {r.get('envs_id', 'ClothSlide')} | env-steps/s |", "|---|---|"]
        lines += [f"| {k} | {v:.4g} |" for k, v in r["envs"].items() if k != "vector_speedup"]
        lines += ["", f"Native vector env over SyncVectorEnv (64 envs): "
                  f"{r['vector_speedup']:.1f}x"]
    d = r["accuracy"]
    lines += ["", f"Accuracy at equal CPU time ({d['equal_cpu_seconds']:.2f} s, "
              f"{d['cloth']}x{d['cloth']} cloth, {d['seconds']:g} s): rk4 error "
              f"{d['rk4_error_at_equal_time']:.2e} m, pymunk (30 iterations) error "
              f"{d['pymunk_error_at_equal_time']:.2e} m."]
    from cparticles import bench_scaling as S

    if "threads" in r:
        lines += S.threads_markdown(r["threads"])
    if "busy_cores" in r:
        b = r["busy_cores"]
        lines += ["", f"Threads on busy cores ({b['env_id']}, {b['copies']} copies, a spinning "
                  f"process on each of {b['spinners']} cores; median of {b['repeats']} rounds): "
                  f"2 threads run at {b['ratio']:.2f}x of 1 thread "
                  f"({b['idle_ratio']:.2f}x with the cores idle)."]
    lines += ["", S.implicit_table(r["implicit_scaling"])]
    if "chains" in r:
        from cparticles.bench_chain import markdown as chain_markdown

        lines += chain_markdown(r["chains"], 10)
    return "\n".join(lines)


# ---------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles bench``."""
    parser.add_argument("--quick", action="store_true",
                        help="shorter batches, fewer sizes (about a minute of CPU time)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--repeats", type=int_at_least(MIN_REPEATS), default=MIN_REPEATS,
                        help=f"timed batches per figure, alternated (at least {MIN_REPEATS})")
    parser.add_argument("--skip-envs", action="store_true",
                        help="skip the environment sections (small envs, vector scaling, "
                        "vector modes and threads)")
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bar (it shows by default when stderr is a terminal)")
    parser.add_argument("--env", metavar="ENV_ID",
                        help="also time this environment, made with --env-kwargs, in the "
                        "small-envs section (default: the registered envs only)")
    parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE",
                        help="keyword arguments of --env (KEY=VALUE pairs read as JSON where "
                        "they are JSON, or one JSON object), e.g. target=swingup (default: "
                        "none)")
    parser.add_argument("--progress", action="store_true", help=argparse.SUPPRESS)


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Before any work: ``--env`` and ``--env-kwargs`` (checked against the environment's
    arguments), then the ``verify`` extra (pymunk, tqdm)."""
    args.variant = None
    if args.env_kwargs and args.env is None:
        parser.error("argument --env-kwargs: give --env too")
    if args.env is not None:
        import envs
        from constrained_particles.arguments import key_values

        try:
            envs.task_spec(args.env)
        except ValueError as exc:
            parser.error(f"argument --env: {exc}")
        if args.skip_envs:
            parser.error("argument --env: the environment sections are skipped (--skip-envs)")
        try:
            kwargs = envs.task.check_env_kwargs(args.env, key_values(args.env_kwargs,
                                                                     "--env-kwargs"))
        except ValueError as exc:
            parser.error(f"argument --env-kwargs: {exc}")
        args.variant = (args.env, kwargs)
    require("pymunk", "tqdm", command="cparticles bench")


def run(quick: bool = False, repeats: int = MIN_REPEATS, envs: bool = True,
        progress: bool = False, *, sizes: list[int] | None = None,
        copies: tuple[int, ...] = VECTOR_COPIES, seconds: float | None = None,
        accuracy_n: int = ACCURACY_N, accuracy_seconds: float = ACCURACY_SECONDS,
        threads: bool = True, thread_copies: int = 512,
        variant: tuple[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """Every section; the JSON document ``cparticles bench --json`` prints. ``variant``: an
    env id and keyword arguments also timed in the small-envs section. ``sizes`` (cloth
    sizes of section (a)), ``copies`` (section (c)), ``seconds`` (per timed batch),
    ``accuracy_n`` and ``accuracy_seconds`` (the equal-accuracy runs), ``threads`` (section
    (e) on or off) and ``thread_copies`` (its copies) override the defaults. ``quick`` times
    implicit Euler at 15 x 15 and 30 x 30 only."""
    seconds = (0.05 if quick else 0.3) if seconds is None else seconds
    sizes = ([20, 64] if quick else [10, 20, 40, 64]) if sizes is None else sizes
    methods = [OURS, "rk4"] if quick else [m for m in METHODS if m != "implicit_euler"]
    from cparticles import bench_scaling as S

    units = (len(sizes) * repeats + 5 + repeats + 2 + repeats
             + (repeats * (1 + len(vector_envs()) * len(copies)) + repeats if envs else 0)
             + (repeats * len(vector_envs()) if envs and threads else 0) + 1)
    bar = Progress(units, progress)
    try:
        bar.section("accuracy")
        errors = cloth_errors(accuracy_n, accuracy_seconds, progress=bar)
        results: dict[str, Any] = {"cloth_errors": errors}
        results["pymunk"] = bench_pymunk(sizes, methods, repeats, seconds, bar)
        results["equal_accuracy"] = {**equal_accuracy(errors, results["pymunk"]),
                                     "cloth": accuracy_n, "seconds": accuracy_seconds}
        results["pymunk_ratio_equal_accuracy"] = results["equal_accuracy"]["ratio"]
        results["pymunk_ratio"] = {k: {n: {m: r[m][k] for m in methods}
                                       for n, r in results["pymunk"]["ratio"].items()}
                                   for k in PYMUNK_ITERATIONS}
        if envs:
            small = bench_small_envs(repeats, seconds / 2, bar, variant)
            results["small_envs"] = small
            results["env_step_vs_cartpole"] = small["vs_cartpole"]
            results["vector_scaling"] = {env_id: bench_vector(env_id, copies, repeats, seconds,
                                                              bar) for env_id in vector_envs()}
        results["scaling"] = bench_scaling([32, 64, 128], OURS, repeats, seconds, bar)
        results["scaling_ratio"] = results["scaling"]["scaling_ratio"]
        bar.section("peak memory")
        results["peak_mb_128"] = peak_memory_mb()
        if envs:
            results["envs_id"] = vector_envs()[0]
            results["envs"] = bench_env_modes(results["envs_id"], repeats, seconds, bar)
            results["vector_speedup"] = results["envs"]["vector_speedup"]
        bar.section("accuracy at equal time")
        results["accuracy"] = bench_accuracy_at_equal_time(progress=bar)
        if envs and threads:
            results["threads"] = S.bench_threads(vector_envs(), thread_copies, repeats,
                                                 2 * seconds, bar)
            bar.section("threads on busy cores")
            results["busy_cores"] = S.bench_busy(vector_envs()[0], thread_copies, repeats,
                                                 2 * seconds, settle=3.0)
        bar.section("chains of rods")
        from cparticles.bench_chain import bench_chains

        results["chains"] = bench_chains([16, 64, 256] if quick else [16, 64, 256, 1024], 10,
                                         repeats, seconds)
        bar.update()
        bar.section("implicit Euler")
        results["implicit_scaling"] = S.bench_implicit_scaling(
            S.IMPLICIT_SIZES[:2] if quick else S.IMPLICIT_SIZES, repeats, progress=bar)
    finally:
        bar.close()
    results["settings"] = {"quick": quick, "repeats": repeats, "batch_seconds": seconds,
                           "python": sys.version.split()[0]}
    return results


def main(args: argparse.Namespace) -> int:
    """Run every section and print JSON or Markdown."""
    results = run(args.quick, args.repeats, not args.skip_envs, progress_enabled(args),
                  variant=getattr(args, "variant", None))
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        if "small_envs" not in results:
            results["small_envs"] = {"us_per_step": {}, "vs_cartpole": {}}
            results["vector_scaling"] = {}
        print(markdown(results))
    return 0


if __name__ == "__main__":
    from cparticles.cli import main as cli_main

    sys.exit(cli_main(["bench", *sys.argv[1:]]))
