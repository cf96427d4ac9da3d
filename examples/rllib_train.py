"""Train PPO with Ray RLlib on our native vector envs, on one machine or on a Ray cluster.

    python examples/rllib_train.py --env ClothSlide-v0 --num-env-runners 2 --iterations 20
    python examples/rllib_train.py --address auto ...              # on a node of a running cluster
    python examples/rllib_train.py --address ray://HEAD:10001 ...  # from outside (Ray Client)

Without ``--address`` the script starts a local Ray instance with this machine's CPUs. Each of the
K EnvRunner actors steps ``--num-envs-per-env-runner`` copies of the environment as one particle
system (``envs.rllib.configure``); the PPO learner runs in the driver. On a cluster the script
ships its own copy of ``envs`` and ``constrained_particles`` to the workers (Ray's ``py_modules``),
so the other nodes need only the dependencies (``pip install -e ".[ray]"`` of the same checkout
is simplest). Prints one line per iteration and, with ``--checkpoint DIR``, saves the trained
algorithm there.
"""

from __future__ import annotations

import argparse
import os
import time

import ray
from ray.rllib.algorithms.ppo import PPOConfig

import constrained_particles
import envs
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
    p.add_argument("--action-mode", choices=("force", "spring"), default="force")
    p.add_argument("--num-env-runners", type=positive_int, default=2,
                   help="EnvRunner actors sampling in parallel (default 2)")
    p.add_argument("--num-envs-per-env-runner", type=positive_int, default=16,
                   help="env copies per EnvRunner, stepped as one particle system (default 16)")
    p.add_argument("--iterations", type=positive_int, default=20,
                   help="PPO training iterations (default 20)")
    p.add_argument("--train-batch-size", type=positive_int, default=4000,
                   help="env steps sampled per iteration (default 4000)")
    p.add_argument("--num-epochs", type=positive_int, default=10,
                   help="passes over each batch (default 10)")
    p.add_argument("--minibatch-size", type=positive_int, default=256)
    p.add_argument("--address", default=None,
                   help="an existing cluster: 'auto' (run on a cluster node) or "
                        "'ray://HOST:10001' (Ray Client); default: start Ray locally")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="save the trained algorithm to DIR at the end")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    # On an existing cluster, ship this copy of the code to every worker (runtime_env
    # py_modules), so that nodes need only the dependencies and all run the driver's version.
    modules = [os.path.dirname(m.__file__) for m in (envs, constrained_particles)]
    runtime_env = None if args.address is None else {"py_modules": modules}
    # "local" starts a new instance even if this machine is part of a cluster.
    ray.init(address=args.address or "local", runtime_env=runtime_env)
    try:
        config = (envs.rllib.configure(
                      PPOConfig(), args.env, num_env_runners=args.num_env_runners,
                      num_envs_per_env_runner=args.num_envs_per_env_runner,
                      env_config={"action_mode": args.action_mode})
                  .training(train_batch_size_per_learner=args.train_batch_size,
                            num_epochs=args.num_epochs, minibatch_size=args.minibatch_size)
                  # a worker's first step may compile the Numba kernels (minutes on a slow
                  # machine); RLlib's default of 60 s would discard that first sample
                  .env_runners(sample_timeout_s=600)
                  .debugging(seed=args.seed))
        algo = config.build_algo()
        print(f"{args.env} ({args.action_mode}): PPO, {args.num_env_runners} EnvRunners x "
              f"{args.num_envs_per_env_runner} envs, cluster CPUs: "
              f"{ray.cluster_resources().get('CPU', 0):g}")
        for i in range(1, args.iterations + 1):
            t0 = time.perf_counter()
            result = algo.train()
            seconds = time.perf_counter() - t0
            runners = result["env_runners"]
            ret = runners.get("episode_return_mean", float("nan"))
            print(f"iter {i:3d}  env steps {int(runners['num_env_steps_sampled_lifetime']):8d}  "
                  f"return {ret:8.2f}  {runners['num_env_steps_sampled'] / seconds:7.0f} "
                  f"steps/s (sample + train)", flush=True)
        if args.checkpoint:
            print("checkpoint:", algo.save_to_path(args.checkpoint))
        algo.stop()
    finally:
        ray.shutdown()


if __name__ == "__main__":
    main()
