"""RLlib: one PPO iteration on a local Ray instance, sampled by two EnvRunners on the native env.

Needs the ``ray`` extra (not part of ``test``: ray pins its own gymnasium). Starting Ray and two
EnvRunner actors dominates the run time (30-50 s on a loaded 2-core machine, 2.5 min if the
Numba kernels are not cached yet); the training itself is a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

ray = pytest.importorskip("ray", reason='needs the ray extra (pip install -e ".[ray,test]")')

from ray.rllib.algorithms.ppo import PPOConfig  # noqa: E402

import envs.rllib  # noqa: E402

PER_RUNNER = "num_env_steps_sampled_by_runner"


@pytest.fixture(scope="module")
def local_ray():
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()


def test_make_env_is_the_native_vector_env():
    venv = envs.rllib.make_env("ClothSlide-v0", {"num_envs": 3, "action_mode": "spring"})
    assert isinstance(venv.unwrapped, envs.cloth_slide.ClothSlideVectorEnv)
    assert venv.num_envs == 3 and venv.single_action_space.shape == (4,)
    single = envs.rllib.make_env("ClothSlide-v0", {})
    assert isinstance(single.unwrapped, envs.cloth_slide.ClothSlideEnv)
    with pytest.raises(ValueError, match="env_id"):
        envs.rllib.make_env("CartPole-v1", {})
    with pytest.raises(ValueError, match="num_envs_per_env_runner"):
        envs.rllib.configure(PPOConfig(), "ClothSlide-v0", num_envs_per_env_runner=0)


def test_one_ppo_iteration_samples_from_both_env_runners(local_ray):
    def count_steps(*, env_runner, metrics_logger, samples, **kwargs) -> None:
        """on_sample_end: env steps this EnvRunner sampled, under its own worker index (a nested
        function, so Ray pickles it by value: workers cannot import this test module)."""
        metrics_logger.log_value((PER_RUNNER, str(env_runner.worker_index)),
                                 sum(len(e) for e in samples), reduce="sum")

    config = (envs.rllib.configure(PPOConfig(), "ClothSlide-v0", num_env_runners=2,
                                   num_envs_per_env_runner=4)
              .training(train_batch_size_per_learner=256, minibatch_size=128, num_epochs=1)
              # RLlib drops samples that take over 60 s; a runner's first step compiles the
              # Numba kernels when they are not cached yet (2 min on a loaded 2-core machine)
              .env_runners(sample_timeout_s=600)
              .callbacks(on_sample_end=count_steps)
              .debugging(seed=0))
    algo = config.build_algo()
    try:
        kinds = algo.env_runner_group.foreach_env_runner(
            lambda r: (r.worker_index, type(r.env.unwrapped).__name__, r.num_envs),
            local_env_runner=False)
        assert sorted(kinds) == [(1, "ClothSlideVectorEnv", 4), (2, "ClothSlideVectorEnv", 4)]
        result = algo.train()
    finally:
        algo.stop()
    runners = result["env_runners"]
    per_runner = {int(k): v for k, v in runners[PER_RUNNER].items()}
    assert sorted(per_runner) == [1, 2]
    assert all(n > 0 for n in per_runner.values()), per_runner
    assert sum(per_runner.values()) == runners["num_env_steps_sampled"] >= 256
    learner = result["learners"]["default_policy"]
    assert np.isfinite(learner["total_loss"]) and learner["num_module_steps_trained"] >= 256
