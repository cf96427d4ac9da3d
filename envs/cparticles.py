"""The registered environment classes under one module name.

Gymnasium's ``pprint_registry`` groups ids by the module of their entry point, so both ids point
here (``envs.cparticles:ClothSlideEnv``, ...) and are listed together under ``cparticles``.
"""

from .cloth_slide import ClothSlideEnv, ClothSlideVectorEnv
from .slider_crank import SliderCrankEnv, SliderCrankVectorEnv

__all__ = ["ClothSlideEnv", "ClothSlideVectorEnv", "SliderCrankEnv", "SliderCrankVectorEnv"]
