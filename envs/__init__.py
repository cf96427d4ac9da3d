"""Gymnasium environments on the constrained-particles simulator.

Importing this package registers ``ClothSlide-v0`` and ``SliderCrank-v0`` (idempotently, so a
second import or a subprocess re-import is silent). ``gym.make("envs:ClothSlide-v0")`` imports it
for you. Both entry points live in :mod:`envs.cparticles`, so ``gym.pprint_registry()`` lists
the two ids together under ``cparticles``.
"""

from gymnasium.envs.registration import register, registry

#: The registered environment ids.
ENV_IDS = ("ClothSlide-v0", "SliderCrank-v0")

_SPECS = {
    "ClothSlide-v0": dict(entry_point="envs.cparticles:ClothSlideEnv",
                          vector_entry_point="envs.cparticles:ClothSlideVectorEnv",
                          max_episode_steps=200),
    "SliderCrank-v0": dict(entry_point="envs.cparticles:SliderCrankEnv",
                           vector_entry_point="envs.cparticles:SliderCrankVectorEnv",
                           max_episode_steps=200),
}

for _id, _kwargs in _SPECS.items():
    if _id not in registry:
        register(id=_id, **_kwargs)
