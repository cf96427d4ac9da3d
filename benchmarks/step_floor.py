"""Benchmark (not a test): how much of a single env's step is its compiled work.

``ChainSwing-v0`` in force mode, stepped two ways from the same state under the same actions:

- **the env**: ``env.step(action)`` of ``gym.make("ChainSwing-v0")`` (the default wrappers);
- **the floor**: the same compiled calls with their arguments built once, before the loop,
  and nothing checked or routed at each step: the action clipped and written into the
  carrier's force, the fused step (``fused.fused_steps``: the task's ``substeps`` steps of
  ``rk4``), the compiled measures and observation (``envs._measure.measures_observe``), the
  task's own ``reward_one`` and the info dict. It takes the env's own steps: the same states,
  observations and rewards, bit for bit (``tests/test_bench.py`` checks it).

and gymnasium's ``CartPole-v1`` as the peer, in alternated rounds (medians). The difference
between the env and the floor is what the checks of every input (the arrays a kernel reads
without bounds checks, the pack's blocks, the settings) and the layers between the env and
its kernels cost per step.

    python -m benchmarks.step_floor [--rounds 7] [--steps 3000]
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the ids)
from constrained_particles import fused
from envs import _measure
from envs.base import _measured
from envs.chain_swing import TASK

ENV_ID = TASK.id  #: the env timed (ChainSwing's)


def floor_stepper(env: Any) -> Callable[[np.ndarray], tuple]:
    """A function that steps ``env`` (a ``gym.make(ENV_ID)`` env, reset, force mode) as its
    ``step`` does, through the same compiled calls with arguments built here once: returns
    ``(obs, reward, terminated, truncated, info)``. No input is checked at a step (the
    arguments must stay as they are now), no divergence is handled and the time limit is not
    counted: a measurement, not an env."""
    task = env.unwrapped.task
    s = task.system
    p, start, settings = fused.prepare(s, s.constraint_solver.lam, s.residual_limit)
    code, rattle = fused.integrator_args(task.integrator)
    post = task._compiled_post()
    if post is None or task.action_mode != "force" or task.num_envs != 1:
        raise ValueError("floor_stepper: the env must be a single force-mode env on the "
                         "compiled path")
    goal = tuple(post[1])
    out, success = np.empty((5, 1)), np.empty(1, bool)
    obs = np.empty((1, 4 * task.n + 1), np.float32)
    rest, view = tuple(task._rest()), tuple(task._view())
    every, none = task._every_copy, task._mask(None)
    force, action = task.actuator.force, task.action
    mass, inv_mass, lam = start.mass, start.inv_mass, start.lam
    engine, blocks = p.refs.engine, p.refs.blocks
    schedule = (task.substeps, task.dt, fused._F0, fused._NO_COUNTS)
    plain_settings = tuple(settings)
    dt, substeps, max_force = task.dt, task.substeps, task.max_force
    walls = task.measure_walls

    def step(a: np.ndarray) -> tuple:
        u = min(max(float(a[0]), -1.0), 1.0)
        action[0, 0] = u
        force[0, 0] = u * max_force
        x, v = s.x, s.v
        xo, vo = np.empty_like(x), np.empty_like(v)
        fused.fused_steps(code, rattle, *p.variant, schedule, (x, v, mass, inv_mass, lam),
                          (xo, vo), plain_settings, engine, None)
        t = s.t
        for _ in range(substeps):
            t = t + dt
        s.x, s.v, s.t = xo, vo, t
        _measure.measures_observe((xo, vo, mass), goal, blocks, walls, rest, every, none,
                                  out, success, view, obs)
        m = task.add_measures(_measured(out, success), out[4])
        values = {k: val.item() for k, val in m.items()}
        reward = task.reward_one(m, values)
        info = values.copy()
        info.pop("speed")
        info["diverged"] = False
        return obs[0], reward, values["is_success"], False, info

    return step


def _loop(step: Callable[[Any], tuple], actions: Any, steps: int,
          reset: Callable[[], Any] | None) -> float:
    """Seconds per step over ``steps`` steps (resetting where an episode ends, if ``reset``)."""
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = step(next(actions))
        if reset is not None and (terminated or truncated):
            reset()
    return (time.perf_counter() - t0) / steps


def measure(rounds: int = 7, steps: int = 3000, seed: int = 0) -> dict[str, Any]:
    """Microseconds per step of the env, the floor and CartPole, medians of ``rounds``
    alternated rounds of ``steps`` steps each, and the env and the floor as multiples of
    CartPole (median of the per-round ratios)."""
    # (neither ChainSwing env is truncated, so neither pays for resets: the floor never ends
    # an episode, and random actions rarely bring the tip to the goal)
    env, low = (gym.make(ENV_ID, max_episode_steps=10**9) for _ in range(2))
    cart = gym.make("CartPole-v1")
    for e in (env, low, cart):
        e.reset(seed=seed)
        e.action_space.seed(seed)
    pool = [env.action_space.sample() for _ in range(997)]
    act, low_act = itertools.cycle(pool), itertools.cycle(pool)
    cart_act = itertools.cycle([cart.action_space.sample() for _ in range(997)])
    floor = floor_stepper(low)
    times: dict[str, list[float]] = {"env": [], "floor": [], "CartPole-v1": []}
    for _ in range(rounds + 1):  # (the first round warms up and is dropped)
        times["env"].append(_loop(env.step, act, steps, env.reset))
        times["floor"].append(_loop(floor, low_act, steps, None))
        times["CartPole-v1"].append(_loop(cart.step, cart_act, steps, cart.reset))
    for e in (env, low, cart):
        e.close()
    times = {k: v[1:] for k, v in times.items()}
    us = {k: 1e6 * statistics.median(v) for k, v in times.items()}
    ratio = {k: statistics.median(a / b for a, b in zip(times[k], times["CartPole-v1"],
                                                         strict=True))
             for k in ("env", "floor")}
    return {"env_id": ENV_ID, "rounds": rounds, "steps": steps, "us_per_step": us,
            "vs_cartpole": ratio}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args(argv)
    r = measure(args.rounds, args.steps)
    for k, us in r["us_per_step"].items():
        times = r["vs_cartpole"].get(k)
        print(f"{k:12s} {us:7.1f} us" + (f"  {times:5.2f}x CartPole-v1" if times else ""))
    print(json.dumps(r))


if __name__ == "__main__":
    main()
