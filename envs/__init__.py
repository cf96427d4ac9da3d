"""Gymnasium environments on the constrained-particles simulator.

Importing this package registers every task of the registration list below
(``ClothSlide-v0``, ``SliderCrank-v0``, ``ChainSwing-v0``, ``ClothPin-v1`` and the table-top
pick-and-place tasks ``RopeStraighten-v0``, ``ClothFlatten-v0``, ``ClothFold-v0`` and
``RopeShape-v0``; idempotently, so a
second import or a subprocess re-import is silent). ``gym.make("envs:ClothSlide-v0")`` imports
it for you. Each task is one module ending with its declaration, a :class:`TaskSpec` (see
:mod:`envs.task` and docs/adding_a_task.md); :func:`register_task` registers one from anywhere,
and every tool of the project (``cparticles train``, ``evaluate``, ``demo``, ``bench``,
:func:`envs.agents.make_agent`, the conformance tests) reads the declarations through
:func:`task_spec` and :func:`task_specs`. Every entry point lives in :mod:`envs.cparticles`, so
``gym.pprint_registry()`` lists the ids together under ``cparticles``.
"""

from . import (
    chain_swing,
    cloth_flatten,
    cloth_fold,
    cloth_pin,
    cloth_slide,
    rope_shape,
    rope_straighten,
    slider_crank,
)
from .task import TaskSpec, register_task, task_spec, task_specs

__all__ = ["ENV_IDS", "TaskSpec", "register_task", "task_spec", "task_specs"]

#: The registration list: the tasks this package ships, in the order the tools list them.
_SHIPPED = (cloth_slide, slider_crank, chain_swing, cloth_pin, rope_straighten, cloth_flatten,
            cloth_fold, rope_shape)
for _module in _SHIPPED:
    register_task(_module.TASK)

#: The ids of the shipped tasks (:func:`task_specs` also holds any registered since).
ENV_IDS = tuple(_module.TASK.id for _module in _SHIPPED)
