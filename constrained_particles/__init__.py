"""constrained-particles: 2D constrained particle systems in the style of Witkin & Baraff.

>>> from constrained_particles import ParticleSystem, Gravity, Rod
>>> s = ParticleSystem()
>>> o = s.add_particle((0.0, 0.0), fixed=True)
>>> a = s.add_particle((0.0, -1.0), mass=1.0)
>>> s.add(Gravity((0.0, -9.81)), Rod(o, a))
>>> s.step(1e-3, method="rk4")
"""

from . import raster, scenes
from .constraints import CircularWire, Constraint, FixedPoint, HorizontalWire, LineWire, Rod
from .forces import (
                     AngularSpring,
                     ConstantForce,
                     DampedSpring,
                     Drag,
                     Force,
                     Gravity,
                     MouseSpring,
                     TableFriction,
                     Wall,
)
from .implicit import ImplicitSolveError, force_jacobians
from .integrators import METHODS, ORDERS
from .rattle import RattleSolveError
from .system import ParticleSystem, SimulationDiverged
from .terms import Shape

__version__ = "0.1.0"

__all__ = [
    "AngularSpring", "CircularWire", "ConstantForce", "Constraint", "DampedSpring", "Drag",
    "FixedPoint", "Force", "Gravity", "HorizontalWire", "ImplicitSolveError", "LineWire",
    "METHODS", "MouseSpring", "ORDERS", "ParticleSystem", "RattleSolveError", "Rod", "Shape",
    "SimulationDiverged", "TableFriction", "Wall", "force_jacobians", "raster", "scenes",
]
