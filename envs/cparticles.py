"""The registered environment classes under one module name.

Gymnasium's ``pprint_registry`` groups ids by the module of their entry point, so every id points
here (``envs.cparticles:ClothSlideEnv``, ...) and are listed together under ``cparticles``.
"""

from .chain_swing import ChainSwingEnv, ChainSwingVectorEnv
from .cloth_pin import ClothPinEnv, ClothPinVectorEnv
from .cloth_slide import ClothSlideEnv, ClothSlideVectorEnv
from .slider_crank import SliderCrankEnv, SliderCrankVectorEnv

__all__ = ["ChainSwingEnv", "ChainSwingVectorEnv", "ClothPinEnv", "ClothPinVectorEnv",
           "ClothSlideEnv", "ClothSlideVectorEnv", "SliderCrankEnv", "SliderCrankVectorEnv"]
