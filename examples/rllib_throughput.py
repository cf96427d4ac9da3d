"""Sampling throughput of RLlib EnvRunners (1 vs 2) and of Stable-Baselines3, in one run.

    python examples/rllib_throughput.py            # a table; --json for the raw figures

Starts a local Ray instance (``--num-cpus``, default 2), builds PPO with two EnvRunner actors,
each stepping ``--num-envs`` copies of the env as one particle system (``envs.rllib.configure``),
and times ``EnvRunner.sample(num_timesteps=--steps)`` (policy inference with exploration plus
env steps, as in training) on one runner alone and on both at once; "env-steps/s" is env steps
returned divided by wall time seen from the driver. The SB3 figure is PPO's rollout collection
(``learn``'s rollout phase, timed with ``on_rollout_start``/``on_rollout_end``) on the same number
of copies in this process, with the same network (256-256 tanh, separate value net) and one torch
thread, like one EnvRunner. SB3 steps ``envs.sb3.to_sb3`` of the native vector env if that module
is present, else a ``DummyVecEnv`` of ``gym.make`` envs (the JSON says which). The three
measurements alternate ``--repeats`` times (the single runner alternates between the two actors),
so machine drift affects all of them alike; medians are reported, with the load average.

A control measures what the machine gives two processes at that moment: the same alternation
runs a pure-Python busy loop in 1 and in 2 processes (``multiprocessing``) for ``--control-seconds``
and reports the ratio of work done. On a quiet 2-core machine it is about 2; on a machine shared
with other sessions it can be near 1 (Linux's autogroup scheduler gives each login session one
share, however many processes it runs), and then no 2-runner ratio can exceed it.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import time
from typing import Any

import gymnasium as gym
import ray
from ray.rllib.algorithms.ppo import PPOConfig

import envs.rllib
from envs import ENV_IDS


def positive_int(text: str) -> int:
    """argparse type: an int >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", choices=ENV_IDS, default=ENV_IDS[0])
    p.add_argument("--num-envs", type=positive_int, default=16,
                   help="env copies per EnvRunner and for SB3 (default 16)")
    p.add_argument("--steps", type=positive_int, default=6000,
                   help="env steps per runner per timed sample (default 6000)")
    p.add_argument("--repeats", type=positive_int, default=5)
    p.add_argument("--num-cpus", type=positive_int, default=2,
                   help="CPUs of the local Ray instance (default 2)")
    p.add_argument("--vectorize", choices=("vector_entry_point", "sync"),
                   default="vector_entry_point",
                   help="EnvRunner vectorization: our native vector env (default) or "
                        "gymnasium's SyncVectorEnv of single envs")
    p.add_argument("--no-sb3", action="store_true", help="skip the SB3 measurement")
    p.add_argument("--control-seconds", type=float, default=2.0,
                   help="duration of each CPU control measurement; 0 skips it (default 2)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    return p.parse_args(argv)


def _count(runner: Any, steps: int) -> int:
    """Env steps in one ``sample`` of ``steps`` on ``runner`` (runs in the EnvRunner actor)."""
    return sum(len(episode) for episode in runner.sample(num_timesteps=steps))


def _busy(seconds: float, out: Any) -> None:
    """Count pure-Python work units for ``seconds`` of wall time; put the count on ``out``."""
    end, n = time.perf_counter() + seconds, 0
    while time.perf_counter() < end:
        sum(range(1000))
        n += 1
    out.put(n)


def cpu_control(processes: int, seconds: float) -> float:
    """Work units per second done by ``processes`` busy-looping processes at once."""
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=_busy, args=(seconds, out)) for _ in range(processes)]
    for proc in procs:
        proc.start()
    total = sum(out.get() for _ in procs)
    for proc in procs:
        proc.join()
    return total / seconds


def rllib_sampler(args: argparse.Namespace) -> Any:
    """PPO with two EnvRunners; returns ``sample(ids)`` -> env-steps/s with runners ``ids``."""
    config = envs.rllib.configure(PPOConfig(), args.env, num_env_runners=2,
                                  num_envs_per_env_runner=args.num_envs)
    config.env_runners(gym_env_vectorize_mode=args.vectorize)
    algo = config.build_algo()
    group = algo.env_runner_group
    steps = args.steps

    def sample(ids: list[int]) -> float:
        t0 = time.perf_counter()
        counts = group.foreach_env_runner(lambda r: _count(r, steps), remote_worker_ids=ids,
                                          local_env_runner=False)
        seconds = time.perf_counter() - t0
        if len(counts) != len(ids):
            raise RuntimeError(f"EnvRunners {ids} returned {len(counts)} results")
        return sum(counts) / seconds

    sample([1, 2])  # warm-up: first reset, first forward passes
    return algo, sample


def sb3_sampler(args: argparse.Namespace) -> tuple[str, Any]:
    """SB3 PPO on ``args.num_envs`` copies; returns (vec env kind, ``sample()`` -> steps/s)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    try:
        from envs.sb3 import to_sb3
        venv = to_sb3(gym.make_vec(args.env, num_envs=args.num_envs,
                                   vectorization_mode="vector_entry_point"))
        kind = "envs.sb3.to_sb3 (native vector env)"
    except ImportError:
        from stable_baselines3.common.vec_env import DummyVecEnv
        venv = DummyVecEnv([lambda: gym.make(args.env)] * args.num_envs)
        kind = "DummyVecEnv of gym.make envs"
    n_steps = max(1, args.steps // args.num_envs)
    net = dict(pi=[256, 256], vf=[256, 256])
    model = PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=n_steps * args.num_envs,
                n_epochs=1, device="cpu", seed=0, policy_kwargs=dict(net_arch=net))

    class RolloutTimer(BaseCallback):
        def _on_rollout_start(self) -> None:
            self.t0 = time.perf_counter()

        def _on_rollout_end(self) -> None:
            self.seconds = time.perf_counter() - self.t0

        def _on_step(self) -> bool:
            return True

    timer = RolloutTimer()

    def sample() -> float:
        model.learn(n_steps * args.num_envs, callback=timer, reset_num_timesteps=False)
        return n_steps * args.num_envs / timer.seconds

    sample()  # warm-up
    return kind, sample


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Alternate the three measurements ``args.repeats`` times; the figures as a dict."""
    envs.rllib.register()
    ray.init(address="local", num_cpus=args.num_cpus, include_dashboard=False,
             log_to_driver=False)
    try:
        algo, rllib = rllib_sampler(args)
        kind, sb3 = (None, None) if args.no_sb3 else sb3_sampler(args)
        load_before = os.getloadavg()
        runs: dict[str, list[float]] = {"rllib_1": [], "rllib_2": [], "sb3": [],
                                        "control_1": [], "control_2": []}
        for rep in range(args.repeats):
            if args.control_seconds > 0:
                runs["control_1"].append(cpu_control(1, args.control_seconds))
                runs["control_2"].append(cpu_control(2, args.control_seconds))
            runs["rllib_1"].append(rllib([1 + rep % 2]))
            runs["rllib_2"].append(rllib([1, 2]))
            if sb3 is not None:
                runs["sb3"].append(sb3())
        load_after = os.getloadavg()
        algo.stop()
    finally:
        ray.shutdown()
    med = {k: statistics.median(v) for k, v in runs.items() if v}
    paired = [b / a for a, b in zip(runs["rllib_1"], runs["rllib_2"], strict=True)]
    control = (med["control_2"] / med["control_1"]) if "control_1" in med else None
    return {"env": args.env, "num_envs": args.num_envs, "steps": args.steps,
            "repeats": args.repeats, "vectorize": args.vectorize, "num_cpus": args.num_cpus,
            "sb3_vec_env": kind, "loadavg_before": load_before, "loadavg_after": load_after,
            "runs": runs, "median": med, "ratio_2_over_1": med["rllib_2"] / med["rllib_1"],
            "ratio_2_over_1_paired_median": statistics.median(paired),
            "control_ratio_2_over_1": control}


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    result = measure(args)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    med = result["median"]
    print(f"{args.env}, {args.num_envs} envs per sampler, {args.steps} steps per runner per "
          f"sample, median of {args.repeats}; load average {result['loadavg_before'][0]:.2f} "
          f"-> {result['loadavg_after'][0]:.2f}")
    print(f"RLlib, 1 EnvRunner : {med['rllib_1']:8.0f} env-steps/s")
    print(f"RLlib, 2 EnvRunners: {med['rllib_2']:8.0f} env-steps/s  "
          f"({result['ratio_2_over_1']:.2f}x; paired median "
          f"{result['ratio_2_over_1_paired_median']:.2f}x)")
    if result["control_ratio_2_over_1"] is not None:
        print(f"CPU control        : 2 busy processes do {result['control_ratio_2_over_1']:.2f}x "
              f"the work of 1 (the most any 2-process ratio can reach here now)")
    if "sb3" in med:
        print(f"SB3 PPO rollouts   : {med['sb3']:8.0f} env-steps/s  ({result['sb3_vec_env']})")


if __name__ == "__main__":
    main()
