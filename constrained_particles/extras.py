"""Optional dependencies ("extras") and the one-line message a command gives when one is missing.

Commands check what they need before doing any work::

    >>> require("numpy", command="cparticles run")   # installed: nothing happens
    >>> install_hint("verify")
    'pip install -e ".[verify]" in the constrained-particles checkout'

The package is installed from its source checkout (it is not on a package index), so the hint
names the extra for ``pip install -e`` there.
"""

from __future__ import annotations

import importlib.util

#: importable module -> the extra that installs it
EXTRA_OF: dict[str, str] = {
    "pymunk": "verify",
    "hypothesis": "verify",
    "tqdm": "verify",
    "matplotlib": "verify",
    "pygame": "render",
    "PIL": "render",
    "stable_baselines3": "rl",
    "torch": "rl",
    "tensorboard": "rl",
    "ray": "ray",
    "ray.tune": "ray",
}


#: importable module -> the distribution a user installs, where the names differ
DISTRIBUTION: dict[str, str] = {"pygame": "pygame-ce", "PIL": "pillow",
                                "stable_baselines3": "stable-baselines3", "ray.tune": "ray[rllib]"}


class MissingExtra(ImportError):
    """A command needs an optional dependency that is not installed; the message is one line
    naming the extra and how to install it."""


def install_hint(extra: str) -> str:
    """How to install ``extra``: from the source checkout the package was installed from."""
    return f'pip install -e ".[{extra}]" in the constrained-particles checkout'


def missing(*modules: str) -> list[str]:
    """The names in ``modules`` that cannot be imported (without importing them)."""
    out = []
    for name in modules:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(name)
    return out


def require(*modules: str, command: str) -> None:
    """Raise :class:`MissingExtra` naming the extra to install if any of ``modules`` is
    missing; ``command`` (e.g. ``"cparticles bench"``) starts the message."""
    absent = missing(*modules)
    if absent:
        extra = EXTRA_OF.get(absent[0], "verify")
        names = ", ".join(DISTRIBUTION.get(name, name) for name in absent)
        raise MissingExtra(f"{command} needs the '{extra}' extra (missing: {names}); "
                           f"install it with {install_hint(extra)}")
