"""Verification of constrained-particles' numerics: measure, do not eyeball.

- :mod:`verification.strategies`: random constrained systems (hypothesis strategy and seeded);
- :mod:`verification.properties`: checks that return measured figures (constraint residual,
  constraint power, gradients, momentum, energy, invariance, determinism);
- :mod:`verification.orders`: convergence order of every integrator against exact or DOP853
  references;
- :mod:`verification.pymunk_check`: the same scenes in pymunk, converging to ours;
- :mod:`verification.report`: Markdown, JSON and PNG report (``python -m verification report``).

Submodules are imported on use, so ``import verification`` needs neither hypothesis, pymunk nor
matplotlib.
"""
