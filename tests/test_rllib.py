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


def test_ppo_learns_on_pixels_through_a_cnn(local_ray):
    """``obs_mode="pixels"``: RLlib builds its CNN encoder for the image and the connector
    that :func:`envs.rllib.configure` adds hands it float32 in [0, 1] (RLlib's encoders do not
    convert uint8 images: without it the first forward pass fails); one PPO iteration in the
    driver trains on finite losses."""
    import gymnasium as gym
    import torch

    piece = envs.rllib.scaled_pixels_connector()
    image = gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    out = piece.recompute_output_observation_space(image, None)
    assert out.dtype == np.float32 and out.high.max() == 1.0 and out.shape == (64, 64, 3)
    both = gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (5,)), "pixels": image})
    assert piece.recompute_output_observation_space(both, None)["pixels"] == out
    frame = np.full((64, 64, 3), 255, np.uint8)
    assert piece.preprocess(frame, None).max() == 1.0
    assert piece.preprocess({"state": np.zeros(5), "pixels": frame}, None)["pixels"].dtype \
        == np.float32
    config = (envs.rllib.configure(PPOConfig(), "ClothSlide-v0", num_env_runners=0,
                                   num_envs_per_env_runner=4,
                                   env_config={"obs_mode": "pixels"})
              .training(train_batch_size_per_learner=128, minibatch_size=64, num_epochs=1)
              .debugging(seed=0))
    algo = config.build_algo()
    try:
        convs = [m for m in algo.get_module().modules() if isinstance(m, torch.nn.Conv2d)]
        assert convs and convs[0].in_channels == 3
        result = algo.train()
    finally:
        algo.stop()
    learner = result["learners"]["default_policy"]
    assert np.isfinite(learner["total_loss"]) and learner["num_module_steps_trained"] >= 128
