"""Layers point one way: ``cparticles`` (command line, benchmarks) above ``envs`` and
``verification``, above the core ``constrained_particles``.

The source files are read as syntax trees (nothing is imported), so an import hidden inside a
function, or a module named in ``importlib.import_module("...")``, counts too.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = "constrained_particles"
#: What the core must never import: the layers above it and the RL libraries.
ABOVE_CORE = {"envs", "verification", "cparticles", "gymnasium", "gym", "stable_baselines3",
              "ray", "torch"}


def sources(package: str) -> list[Path]:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources found for {package}"
    return files


def imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, dotted module) of every import statement, every ``from X import y`` (as ``X``
    and ``X.y``, since ``y`` may be a module) and every ``import_module("X")`` /
    ``__import__("X")`` with a literal name."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
            found += [(node.lineno, f"{node.module}.{alias.name}") for alias in node.names]
        elif (isinstance(node, ast.Call) and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and (getattr(node.func, "attr", None) == "import_module"
                   or getattr(node.func, "id", None) in ("import_module", "__import__"))):
            found.append((node.lineno, node.args[0].value))
    return found


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_core_uses(source: str, where: str) -> list[str]:
    """Where ``source`` (a file's text; ``where`` names it) reaches a ``_``-prefixed core module
    or name: ``import constrained_particles._x``, ``from constrained_particles[.m] import _x``,
    a module path with a ``_`` part, and ``alias._x`` where ``alias`` was bound by importing
    from the core. (A private attribute reached through an instance, ``system._x``, is not
    seen.)"""
    tree = ast.parse(source, where)
    uses, aliases = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == CORE:
                    aliases.add(alias.asname or parts[0])
                    if any(is_private(p) for p in parts):
                        uses.append(f"{where}:{node.lineno} import {alias.name}")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.split(".")[0] == CORE:
            for alias in node.names:
                aliases.add(alias.asname or alias.name)
                if any(is_private(p) for p in node.module.split(".")) or is_private(alias.name):
                    uses.append(f"{where}:{node.lineno} from {node.module} import {alias.name}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and is_private(node.attr):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in aliases:
                uses.append(f"{where}:{node.lineno} {ast.unparse(node)}")
    return uses


def test_the_scanner_sees_what_it_looks_for():
    """The scanner itself, on a known snippet (so an empty result below means something)."""
    tree = ast.parse("import os\nfrom a.b import c\n"
                     "def f():\n    import gymnasium\n    importlib.import_module('envs.x')\n")
    assert [m for _, m in imported_modules(tree)] == ["os", "a.b", "a.b.c", "gymnasium",
                                                      "envs.x"]


@pytest.mark.parametrize("path", sources(CORE), ids=lambda p: p.name)
def test_the_core_imports_nothing_above_it(path):
    tree = ast.parse(path.read_text(), str(path))
    bad = [f"line {line}: {module}" for line, module in imported_modules(tree)
           if module.split(".")[0] in ABOVE_CORE]
    assert not bad, f"{path.relative_to(ROOT)} imports from a layer above the core: {bad}"


@pytest.mark.parametrize("package", ["envs", "verification"])
def test_envs_and_verification_do_not_import_the_command_line(package):
    bad = [f"{p.relative_to(ROOT)}:{line} {module}" for p in sources(package)
           for line, module in imported_modules(ast.parse(p.read_text()))
           if module.split(".")[0] == "cparticles"]
    assert not bad, bad


def test_envs_and_verification_use_only_public_core_names():
    uses = [u for package in ("envs", "verification") for p in sources(package)
            for u in private_core_uses(p.read_text(), str(p.relative_to(ROOT)))]
    assert not uses, "private core names used:\n" + "\n".join(uses)


def test_the_private_name_scanner_on_a_known_snippet():
    text = ("from constrained_particles import _kernels, fused, ParticleSystem\n"
            "import constrained_particles.system as S\n"
            "import numpy as np\n"
            "from constrained_particles.fused import _step\n"
            "x = fused._refresh(S._check, ParticleSystem._y, fused.OK, S.__name__, np._x)\n")
    uses = {u.split(" ", 1)[1] for u in private_core_uses(text, "probe.py")}
    assert uses == {"from constrained_particles import _kernels",
                    "from constrained_particles.fused import _step",
                    "fused._refresh", "S._check", "ParticleSystem._y"}
