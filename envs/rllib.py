"""Ray RLlib on the native vector envs: every EnvRunner steps its copies as one particle system.

RLlib's current API stack (``SingleAgentEnvRunner``) builds each EnvRunner's environment with
``gymnasium.make_vec``. For a name registered with :func:`ray.tune.registry.register_env` and
``gym_env_vectorize_mode="vector_entry_point"``, it calls the registered creator once per
EnvRunner with ``env_config | {"num_envs": N}`` and uses the ``gymnasium.vector.VectorEnv`` it
returns as is. :func:`register` registers :func:`make_env` that way under the Gymnasium ids
(``ClothSlide-v0``, ...), so each EnvRunner gets our native vector env (N copies, one derivative
evaluation per physics step) rather than N single envs in a ``SyncVectorEnv``. Ray stores the
creator by reference to this module, so every worker process that builds an env imports
``envs.rllib`` and thereby ``envs`` (which registers the Gymnasium ids there); on a cluster every
node therefore needs this package installed, like any other dependency. Our vector envs use
Gymnasium's next-step autoreset, which is what RLlib's EnvRunner expects.

:func:`configure` applies the environment and its vectorization to any ``AlgorithmConfig``:

>>> from ray.rllib.algorithms.ppo import PPOConfig
>>> import envs.rllib
>>> config = envs.rllib.configure(PPOConfig(), "ClothSlide-v0", num_env_runners=2,
...                               num_envs_per_env_runner=8, env_config={"action_mode": "spring"})
>>> config.env, config.num_env_runners, config.num_envs_per_env_runner
('ClothSlide-v0', 2, 8)
>>> algo = config.build_algo()  # starts Ray if needed; then algo.train()  # doctest: +SKIP

Without Ray, :func:`make_env` is an ordinary factory (what each EnvRunner calls):

>>> venv = envs.rllib.make_env("ClothSlide-v0", {"num_envs": 4})
>>> type(venv.unwrapped).__name__, venv.num_envs
('ClothSlideVectorEnv', 4)

Requires the ``ray`` extra (``pip install -e ".[ray]"`` in the checkout: ``ray[rllib]`` and
torch) for :func:`register` and :func:`configure`; importing this module does not import Ray.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from constrained_particles.extras import require

from .task import task_spec, task_specs

if TYPE_CHECKING:  # (the ray extra)
    from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
    from ray.rllib.connectors.connector_v2 import ConnectorV2

__all__ = ["configure", "make_env", "register", "scaled_pixels_connector"]

#: RLlib's name for our vectorization: each EnvRunner calls the env's vector entry point.
VECTORIZE_MODE = "vector_entry_point"


def _check_id(env_id: object) -> str:
    if not isinstance(env_id, str):
        raise TypeError(f"env_id must be a string, got {type(env_id).__name__}")
    return task_spec(env_id).id  # (ValueError listing the registered ids)


def make_env(env_id: str, config: Mapping[str, Any] | None = None
             ) -> gym.Env | gym.vector.VectorEnv:
    """RLlib env creator: the native vector env if ``config`` has ``num_envs``, else one env.

    ``config`` is RLlib's ``env_config`` (an ``EnvContext``, a dict): every key other than
    ``num_envs`` is a keyword argument of the environment (``action_mode``, ``cloth_size``, ...).
    With ``num_envs`` (what RLlib adds in ``vector_entry_point`` mode) the result is
    ``gym.make_vec(env_id, num_envs, vectorization_mode="vector_entry_point", **kwargs)``: one
    particle system holding ``num_envs`` copies, 200-step episodes, next-step autoreset.
    """
    _check_id(env_id)
    kwargs = dict(config or {})
    num_envs = kwargs.pop("num_envs", None)
    if num_envs is None:
        return gym.make(env_id, **kwargs)
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=VECTORIZE_MODE, **kwargs)


def register(env_ids: Iterable[str] | None = None) -> tuple[str, ...]:
    """Register ``env_ids`` (default: every registered task) with Ray's env registry (under the
    same names); returns the names.

    Call it in the driver before building the algorithm; Ray makes the registration visible to
    every worker process of the cluster (the one it is connected to, or the next one started).
    Registering again replaces the entry with an identical one.
    """
    require("ray.tune", command="envs.rllib.register")
    from ray.tune.registry import register_env

    if env_ids is None:
        env_ids = [spec.id for spec in task_specs()]
    ids = tuple(_check_id(i) for i in env_ids)
    for env_id in ids:
        register_env(env_id, functools.partial(make_env, env_id))
    return ids


def configure(config: AlgorithmConfig, env_id: str, *, num_env_runners: int = 2,
              num_envs_per_env_runner: int = 8, env_config: Mapping[str, Any] | None = None
              ) -> AlgorithmConfig:
    """``config`` (an RLlib ``AlgorithmConfig``) set to sample ``env_id`` on the native vector env.

    Registers ``env_id`` (:func:`register`), then sets ``config.environment(env_id, env_config)``
    and ``config.env_runners(num_env_runners, num_envs_per_env_runner,
    gym_env_vectorize_mode="vector_entry_point")``: ``num_env_runners`` EnvRunner actors (0
    samples in the driver), each stepping ``num_envs_per_env_runner`` copies as one particle
    system. Returns ``config`` (modified in place, as RLlib's own setters do).
    """
    for name, value in (("num_env_runners", num_env_runners),
                        ("num_envs_per_env_runner", num_envs_per_env_runner)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if num_env_runners < 0:
        raise ValueError(f"num_env_runners must be >= 0, got {num_env_runners}")
    if num_envs_per_env_runner < 1:
        raise ValueError(f"num_envs_per_env_runner must be >= 1, got {num_envs_per_env_runner}")
    register([env_id])
    config = (config
              .environment(env_id, env_config=dict(env_config or {}))
              .env_runners(num_env_runners=num_env_runners,
                           num_envs_per_env_runner=num_envs_per_env_runner,
                           gym_env_vectorize_mode=VECTORIZE_MODE))
    if (env_config or {}).get("obs_mode") in ("pixels", "state_pixels"):
        config = config.env_runners(env_to_module_connector=_scaled_pixels)
    return config


def _scaled_pixels(env: object = None, spaces: object = None, device: object = None
                   ) -> ConnectorV2:
    """RLlib env-to-module connector factory: :func:`scaled_pixels_connector`'s piece."""
    return scaled_pixels_connector()


def scaled_pixels_connector() -> ConnectorV2:
    """An RLlib env-to-module connector piece that hands the module each ``uint8`` image of a
    pixel observation (``obs_mode="pixels"``, or the ``"pixels"`` entry of
    ``"state_pixels"``) as ``float32`` in [0, 1], the input RLlib's CNN encoders take (they do
    not convert images themselves). :func:`configure` adds it for those observation modes."""
    require("ray.rllib", command="envs.rllib.scaled_pixels_connector")
    import numpy as np
    from ray.rllib.connectors.env_to_module.observation_preprocessor import (
        SingleAgentObservationPreprocessor,
    )

    def scaled(space: gym.Space) -> gym.Space:
        if isinstance(space, gym.spaces.Box) and space.dtype == np.uint8:
            return gym.spaces.Box(0.0, 1.0, space.shape, np.float32)
        if isinstance(space, gym.spaces.Dict) and "pixels" in space.spaces:
            return gym.spaces.Dict({**space.spaces, "pixels": scaled(space["pixels"])})
        return space

    class ScaledPixels(SingleAgentObservationPreprocessor):
        def recompute_output_observation_space(self, input_observation_space: gym.Space,
                                               input_action_space: gym.Space) -> gym.Space:
            return scaled(input_observation_space)

        def preprocess(self, observation: Any, episode: Any) -> Any:
            if isinstance(observation, dict):
                return {**observation,
                        "pixels": observation["pixels"].astype(np.float32) * (1.0 / 255.0)}
            return observation.astype(np.float32) * (1.0 / 255.0)

    return ScaledPixels()
