"""Nothing a user does to an environment's public arrays, or to a system from a thread, may crash
the interpreter.

For every registered env (single env through ``gym.make`` and native vector env through
``gym.make_vec(..., vectorization_mode="vector_entry_point")``, every action mode), every public
numpy array reachable from ``env.unwrapped`` (attributes walked recursively through the
project's own objects, lists, tuples and dicts; names starting with ``_`` skipped) is, in turn
on a fresh env:

- edited in place, with ``flags.writeable`` switched on where numpy allows it: every entry set
  to 10**12, to -1, to NaN and to inf (values the dtype cannot hold are skipped);
- reassigned with its first row only;
- reassigned with a wrong dtype (float32 for floats, float64 for integers and booleans);

and the env is then stepped three times. The edit may be refused (ValueError, TypeError, or
AttributeError for a read-only property); each step must return normally or raise a clear
error (ValueError, TypeError, RuntimeError, which includes SimulationDiverged). The cases run in
subprocesses, each running many cases; a subprocess killed by a signal (or exiting abnormally)
names the case it was running, and the remaining cases go on in a new subprocess. Every case
runs: there is no sampled subset. "A fresh env" is a deep copy of one env made and reset
once per subprocess.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import threading
from typing import Any

import numpy as np
import pytest

HERE = os.path.abspath(__file__)
ROOT = os.path.dirname(os.path.dirname(HERE))
#: (env id, make_vec or make, keyword arguments)
CONFIGS = [(env_id, kind, {"action_mode": mode})
           for env_id, modes in (("ClothSlide-v0", ("force", "spring")),
                                 ("SliderCrank-v0", ("force", "spring")),
                                 ("ChainSwing-v0", ("force", "spring")),
                                 ("ClothPin-v1", ("draw",)))
           for mode in modes for kind in ("single", "vector")]
# the threaded vector env: its physics cut into two ranges of one copy each, stepped on two
# threads (ranges as small as one copy are allowed for it: see _make)
CONFIGS += [("SliderCrank-v0", "vector", {"action_mode": "spring", "num_threads": 2}),
            ("ClothSlide-v0", "vector", {"action_mode": "force", "num_threads": 2}),
            # (its pins change the system's blocks: cut again, stepped whole, cut reusing the
            # cut before)
            ("ClothPin-v1", "vector", {"action_mode": "draw", "num_threads": 2})]
EDITS = ("huge", "negative", "nan", "inf", "one_row", "dtype")
ALLOWED = (ValueError, TypeError, RuntimeError)
STEPS = 3


# ---------------------------------------------------------------- the worker (a subprocess)
def _ours(obj: Any) -> bool:
    module = getattr(type(obj), "__module__", "") or ""
    return module.split(".")[0] in ("constrained_particles", "envs")


def array_paths(root: Any) -> list[list]:
    """Paths ``[[kind, key], ...]`` from ``root`` to every public numpy array reachable through
    the project's objects (``attr``), lists and tuples (``item``) and dicts (``key``)."""
    out: list[list] = []
    seen: set[int] = set()

    def walk(obj: Any, path: list) -> None:
        if isinstance(obj, np.ndarray):
            out.append(path)
            return
        if id(obj) in seen:
            return
        if isinstance(obj, (list, tuple)):
            seen.add(id(obj))
            for k, item in enumerate(obj):
                walk(item, [*path, ["item", k]])
        elif isinstance(obj, dict):
            seen.add(id(obj))
            for k in sorted(obj, key=repr):
                if isinstance(k, str) and not k.startswith("_"):
                    walk(obj[k], [*path, ["key", k]])
        elif _ours(obj) and hasattr(obj, "__dict__"):
            seen.add(id(obj))
            names = set(vars(obj))
            for cls in type(obj).__mro__:  # public properties too
                names |= {k for k, v in vars(cls).items() if isinstance(v, property)}
            for name in sorted(names):
                if name.startswith("_"):
                    continue
                try:
                    value = getattr(obj, name)
                except Exception:  # noqa: BLE001 - a property that cannot be read is no array
                    continue
                walk(value, [*path, ["attr", name]])

    walk(root, [])
    return out


def _make(env_id: str, kind: str, kwargs: dict) -> Any:
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids

    if "num_threads" in kwargs:
        from constrained_particles import parallel

        parallel.MIN_PARTICLES = 1  # (two copies of two particles: one range each)
    if kind == "vector":
        env = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point",
                           **kwargs)
    else:
        env = gym.make(env_id, disable_env_checker=True, **kwargs)
    env.reset(seed=0)
    env.action_space.seed(0)
    if "num_threads" in kwargs:  # the ranges are what this config is for: they must exist
        twin = copy.deepcopy(env)
        twin.step(twin.action_space.sample())
        held = twin.unwrapped.task.system.__dict__.get("_partition")
        if held is None or not held.valid or len(held.packs) != kwargs["num_threads"]:
            raise RuntimeError("the threaded config's system was not cut into ranges")
        twin.close()
    return env


def _resolve(root: Any, path: list) -> tuple[Any, list]:
    parent = root
    for kind, key in path[:-1]:
        parent = getattr(parent, key) if kind == "attr" else parent[key]
    return parent, path[-1]


def _get(parent: Any, last: list) -> Any:
    kind, key = last
    return getattr(parent, key) if kind == "attr" else parent[key]


def _put(parent: Any, last: list, value: Any) -> None:
    kind, key = last
    if kind == "attr":
        setattr(parent, key, value)
    else:
        parent[key] = value  # a tuple refuses (TypeError): accepted like any clear error


def _edit(env: Any, path: list, edit: str) -> None:
    parent, last = _resolve(env.unwrapped, path)
    arr = _get(parent, last)
    if edit in ("huge", "negative", "nan", "inf"):
        value = {"huge": 10**12, "negative": -1, "nan": np.nan, "inf": np.inf}[edit]
        try:
            arr.flags.writeable = True
        except ValueError:
            return  # numpy refuses: the array cannot be edited in place
        try:
            arr[...] = value
        except (ValueError, OverflowError, TypeError):
            return  # the dtype cannot hold the value
    elif edit == "one_row":
        _put(parent, last, arr[:1].copy() if arr.ndim else arr.copy())
    else:
        wrong = np.float32 if arr.dtype.kind == "f" else np.float64
        _put(parent, last, arr.astype(wrong))


def worker(config: int, cases: list[tuple[int, str]]) -> None:
    """Run ``cases`` (path number, edit) of config ``config``, printing ``DONE k`` after each."""
    import warnings

    warnings.simplefilter("ignore")
    env_id, kind, kwargs = CONFIGS[config]
    # each case edits a deep copy of one freshly made and reset env (making a ClothSlide env
    # solves for its hanging cloth: ~0.3 s, a copy ~5 ms)
    pristine = _make(env_id, kind, kwargs)
    paths = array_paths(pristine.unwrapped)
    for k, (p, edit) in enumerate(cases):
        env = copy.deepcopy(pristine)
        try:
            _edit(env, paths[p], edit)
        except (*ALLOWED, AttributeError):  # (a property without a setter refuses too)
            pass
        for _ in range(STEPS):
            try:
                env.step(env.action_space.sample())
            except ALLOWED:
                pass
        env.close()
        print(f"DONE {k}", flush=True)


# ---------------------------------------------------------------- the test (the parent)
def _run(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, HERE, *args], capture_output=True, text=True,
                          env=env, timeout=timeout, cwd=ROOT)


def _paths(config: int) -> list[str]:
    out = _run(["list", str(config)])
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def _failures(config: int) -> tuple[int, list[str]]:
    """(cases run, descriptions of the cases that crashed or raised an unexpected error)."""
    names = _paths(config)
    cases = [(p, edit) for p in range(len(names)) for edit in EDITS]
    failures: list[str] = []
    start = 0
    while start < len(cases):
        batch = cases[start:]
        out = _run(["run", str(config), json.dumps(batch)])
        done = sum(line.startswith("DONE ") for line in out.stdout.splitlines())
        if out.returncode == 0 and done == len(batch):
            break
        p, edit = batch[done]
        tail = out.stderr.strip().splitlines()[-1:] if out.stderr.strip() else []
        failures.append(f"{CONFIGS[config][:2]} {CONFIGS[config][2]} {names[p]} {edit}: "
                        f"exit {out.returncode} {tail}")
        start += done + 1
    return len(cases), failures


@pytest.mark.parametrize("config", range(len(CONFIGS)),
                         ids=[f"{c[0]}-{c[1]}-{c[2]['action_mode']}"
                              f"{'-threads' if 'num_threads' in c[2] else ''}" for c in CONFIGS])
def test_no_public_array_edit_crashes(config: int) -> None:
    count, failures = _failures(config)
    assert count >= 6 * 10, f"only {count} cases found: the walk misses the env's arrays"
    assert not failures, "\n".join(failures)


def test_walk_finds_the_arrays_that_crashed_before() -> None:
    """The walk reaches the arrays of the crashes reported against the envs (a tracked
    particle list, a spring action's anchors) and the system's blocks and state."""
    names = set(_paths(CONFIGS.index(("ClothSlide-v0", "vector", {"action_mode": "spring"}))))
    for want in ("task.tracked_particles", "task.system.x", "task.system.v",
                 "task.system.forces[0]", "task.goal"):
        assert any(n.startswith(want) for n in names), (want, sorted(names))
    assert any(n.endswith(".anchor") for n in names), sorted(names)


# ---------------------------------------------------------------- the core's boundary
def test_index_arrays_cannot_be_reopened_for_writing() -> None:
    """Every block's index arrays, and every array the fused pack indexes with, are immutable:
    numpy refuses ``flags.writeable = True`` on them and on every base below them."""
    from constrained_particles import fused, scenes
    from constrained_particles.terms import is_frozen

    system = scenes.cloth(8, 8)
    system.step(1e-3, "symplectic_euler")
    arrays = [getattr(b, name) for b in (*system.forces, *system.constraints)
              for name in b.index_fields if getattr(b, name) is not None]
    p = fused.pack(system)
    b = p.blocks
    arrays += [b.spring.i, b.spring.j, b.spring.runs, *p.rows, b.line.particles, b.line.row,
               b.gravity.particles, b.gravity.block]
    assert len(arrays) > 10
    for arr in arrays:
        assert is_frozen(arr)
        base = arr
        while isinstance(base, np.ndarray):
            with pytest.raises(ValueError):
                base.flags.writeable = True
            base = base.base


def test_a_reassigned_index_array_rebuilds_only_through_its_block_version() -> None:
    """Reassigning a block's attribute bumps that block's version alone and the next call
    packs again; an in-place edit of a parameter array is seen by the same pack (zero copy);
    an index out of range is refused by the setter."""
    from constrained_particles import ConstantForce, fused, scenes

    system = scenes.cloth(6, 6)
    push = ConstantForce([0, 1], [[0.0, 0.0], [0.0, 0.0]])
    system.add(push)
    plain = system.copy()
    system.step(1e-3, "symplectic_euler")
    plain.step(1e-3, "symplectic_euler")
    first = fused.pack(system)
    versions = [b.version for b in system.forces]
    push.force[0] = (3.0, -1.0)  # in place: no new version, the same pack, the new force
    assert [b.version for b in system.forces] == versions
    pushed = plain.copy()
    pushed.forces[-1].force[0] = (3.0, -1.0)
    system.step(1e-3, "symplectic_euler")
    plain.step(1e-3, "symplectic_euler")
    pushed.step(1e-3, "symplectic_euler")
    assert fused.pack(system) is first
    np.testing.assert_array_equal(system.x, pushed.x)
    assert not np.array_equal(system.x, plain.x)
    with pytest.raises(ValueError, match="unknown particle"):
        push.particles = [0, 10**6]
    push.particles = [2, 3]
    assert push.version == versions[-1] + 1
    assert [b.version for b in system.forces[:-1]] == versions[:-1]
    system.step(1e-3, "symplectic_euler")
    assert fused.pack(system) is not first
    with pytest.raises(AttributeError):
        push.version = 0


def test_a_parameter_array_reshaped_in_place_is_never_read_past_its_end() -> None:
    """``arr.shape = ...`` changes a parameter array the pack holds zero copy without a new
    version: the call's O(1) shape check refuses the compiled kernel, and the reference path
    raises a clear error (or steps)."""
    from constrained_particles import ConstantForce, scenes

    system = scenes.cloth(6, 6)
    push = ConstantForce([0, 1], [[1.0, 0.0], [0.0, 1.0]])
    system.add(push)
    system.step(1e-3, "symplectic_euler")
    push.force.shape = (1, 4)
    with pytest.raises(ALLOWED):
        system.step(1e-3, "symplectic_euler")
    push.force.shape = (2, 2)
    spring = system.forces[1]
    spring.ks.shape = (1, len(spring.ks))
    try:
        system.step(1e-3, "symplectic_euler")
    except ALLOWED:
        pass


# ---------------------------------------------------------------- threads
def test_swapping_state_from_a_thread_never_crashes() -> None:
    """One thread keeps replacing ``system.v`` (right shape, wrong shapes and dtypes, other
    types) while another steps: every step returns or raises a clear error, in a subprocess
    that must exit normally."""
    out = _run(["swap"], timeout=900)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert "SWAP OK" in out.stdout, out.stdout[-2000:]


def _swap() -> None:
    from constrained_particles import scenes

    system = scenes.cloth(16, 16)
    good = system.v.copy()
    swaps = [good.copy(), good[:3].copy(), good.astype(np.float32), good.T.copy(),
             np.asfortranarray(good), good.ravel().copy(), [[0.0, 0.0]], None, good.copy()]
    stop = threading.Event()

    def swapper() -> None:
        k = 0
        while not stop.is_set():
            system.v = swaps[k % len(swaps)]
            k += 1

    thread = threading.Thread(target=swapper)
    thread.start()
    steps = errors = 0
    try:
        for _ in range(4000):
            for method in ("symplectic_euler", "rk4"):
                try:
                    system.step(1e-3, method)
                    steps += 1
                except ALLOWED:
                    errors += 1
    finally:
        stop.set()
        thread.join()
    print(f"SWAP OK steps={steps} errors={errors}", flush=True)


def test_two_threads_stepping_one_system_get_a_clear_error() -> None:
    """Two threads stepping one system at once: the second caller gets a RuntimeError saying
    the system is being stepped; the state is then exactly what the steps that ran produce
    alone (each step that returned advanced the system once, in some order)."""
    from constrained_particles import ParticleSystem, scenes

    system = scenes.cloth(24, 24)
    reference = system.copy()
    done = [0, 0]
    refused: list[str] = []
    lock = threading.Lock()
    barrier = threading.Barrier(2)

    def stepper(k: int) -> None:
        barrier.wait()
        for _ in range(300):
            try:
                system.step(1e-3, "symplectic_euler")
                with lock:
                    done[k] += 1
            except RuntimeError as err:
                assert "another thread" in str(err)
                with lock:
                    refused.append(str(err))

    threads = [threading.Thread(target=stepper, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(done) + len(refused) == 600
    for _ in range(sum(done)):
        reference.step(1e-3, "symplectic_euler")
    assert isinstance(system, ParticleSystem)
    np.testing.assert_array_equal(system.x, reference.x)
    np.testing.assert_array_equal(system.v, reference.v)



def test_an_env_step_while_its_system_is_being_stepped_gets_a_clear_error() -> None:
    """While another caller holds a vector env's system step lock (``system.stepping()``), an
    env step raises the same RuntimeError as ``ParticleSystem.step`` and the state (x, v, t)
    stays as it was (the actions and the actuator's forces, written before the physics, are
    not rolled back); once released, the env steps."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)

    env = gym.make_vec("SliderCrank-v0", num_envs=4, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    system = env.unwrapped.task.system
    action = np.full(env.action_space.shape, 0.5, np.float32)
    env.step(action)
    x, v, t = system.x.copy(), system.v.copy(), system.t
    holder_ready, release = threading.Event(), threading.Event()

    def holder() -> None:
        with system.stepping():
            holder_ready.set()
            release.wait(10)

    thread = threading.Thread(target=holder)
    thread.start()
    try:
        holder_ready.wait(10)
        with pytest.raises(RuntimeError, match="another thread"):
            env.step(action)
        np.testing.assert_array_equal(system.x, x)
        np.testing.assert_array_equal(system.v, v)
        assert system.t == t
    finally:
        release.set()
        thread.join()
    env.step(action)
    assert system.t > t
    env.close()

if __name__ == "__main__":
    if sys.argv[1] == "list":
        c = int(sys.argv[2])
        found = array_paths(_make(*CONFIGS[c]).unwrapped)
        print(json.dumps(["".join(f".{k}" if kind == "attr" else f"[{k!r}]" for kind, k in p)[1:]
                          for p in found]))
    elif sys.argv[1] == "run":
        worker(int(sys.argv[2]), [tuple(c) for c in json.loads(sys.argv[3])])
    elif sys.argv[1] == "swap":
        _swap()
