"""The registered environment classes under one module name.

Gymnasium's ``pprint_registry`` groups ids by the module of their entry point, so every task's
entry points name this module (``envs.cparticles:ClothSlideEnv``, ...) and the ids are listed
together under ``cparticles``. A name resolves to the class of that name among the registered
tasks' declarations (:func:`envs.task.register_task`).
"""

from typing import Any

import envs  # noqa: F401  (registers the shipped tasks)

from .task import environment_class


def __getattr__(name: str) -> Any:
    return environment_class(name)
