"""The ``cparticles`` command line and the benchmark harness, above the three library packages.

:mod:`constrained_particles` (the simulator), :mod:`envs` (the Gymnasium environments) and
:mod:`verification` (the numerical checks) never import this package; it imports them, and only
the one a subcommand needs. Run ``cparticles --help`` or ``python -m cparticles --help``.
"""

from constrained_particles import __version__

__all__ = ["__version__"]
