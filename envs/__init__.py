"""Gymnasium environments on the constrained-particles simulator.

Importing this package registers ``ClothSlide-v0``, ``SliderCrank-v0``, ``ChainSwing-v0`` and
``ClothPin-v1`` (idempotently, so a second import or a subprocess re-import is silent).
``gym.make("envs:ClothSlide-v0")`` imports it for you. Every entry point lives in
:mod:`envs.cparticles`, so ``gym.pprint_registry()`` lists the ids together under ``cparticles``.
"""

from gymnasium.envs.registration import register, registry

#: Every registered id. ClothSlide, SliderCrank and ChainSwing take action modes "force" and
#: "spring"; ClothPin draws springs ("draw").
ENV_IDS = ("ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0", "ClothPin-v1")

_SPECS = {
    "ClothSlide-v0": dict(entry_point="envs.cparticles:ClothSlideEnv",
                          vector_entry_point="envs.cparticles:ClothSlideVectorEnv",
                          max_episode_steps=200),
    "SliderCrank-v0": dict(entry_point="envs.cparticles:SliderCrankEnv",
                           vector_entry_point="envs.cparticles:SliderCrankVectorEnv",
                           max_episode_steps=200),
    "ChainSwing-v0": dict(entry_point="envs.cparticles:ChainSwingEnv",
                          vector_entry_point="envs.cparticles:ChainSwingVectorEnv",
                          max_episode_steps=200),
    "ClothPin-v1": dict(entry_point="envs.cparticles:ClothPinEnv",
                        vector_entry_point="envs.cparticles:ClothPinVectorEnv",
                        max_episode_steps=200),
}

for _id, _kwargs in _SPECS.items():
    if _id not in registry:
        register(id=_id, **_kwargs)
