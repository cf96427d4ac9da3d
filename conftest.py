"""Doctests of the modules that need an optional extra.

``envs/sb3.py`` imports Stable-Baselines3, ``envs/policies.py`` imports torch and
``envs/rllib.py``'s examples import Ray. The ``test`` extra installs none of them, so without
their extra these files are reported as skipped, with the reason, instead of failing to collect;
with it their doctests run as usual.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent
#: file (relative to the checkout) -> (module its doctests import, extra that installs it)
NEEDS = {"envs/sb3.py": ("stable_baselines3", "rl"), "envs/policies.py": ("torch", "rl"),
         "envs/rllib.py": ("ray", "ray")}


class MissingExtra(pytest.File):
    """A file whose doctests need an extra that is not installed: collected as one skip."""

    def collect(self) -> Iterator[Any]:
        module, extra = NEEDS[self.path.relative_to(ROOT).as_posix()]
        pytest.skip(f'doctests need the {extra} extra ({module} is not installed: '
                    f'pip install -e ".[{extra}]")')
        yield from ()


@pytest.hookimpl(wrapper=True)
def pytest_collect_file(file_path: Path, parent: pytest.Collector) -> Any:
    collectors = yield
    if not file_path.resolve().is_relative_to(ROOT):
        return collectors
    need = NEEDS.get(file_path.resolve().relative_to(ROOT).as_posix())
    if need is None or importlib.util.find_spec(need[0]) is not None:
        return collectors
    return [MissingExtra.from_parent(parent, path=file_path)]
