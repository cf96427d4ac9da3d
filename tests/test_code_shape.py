"""The shape the compiled engine keeps: no function takes a wall of positional arguments, and
no source file grows past what one reader holds in mind.

Read as syntax trees (nothing is imported), so the compiled kernels defined under
``if kernels.ENABLED:`` are counted like every other function.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("constrained_particles", "envs", "verification", "cparticles")
MAX_POSITIONAL = 12  #: positional parameters (``self`` included; keyword-only ones do not count)
MAX_LINES = 800  #: non-blank lines per source file


def sources() -> list[Path]:
    files = [f for package in PACKAGES for f in sorted((ROOT / package).rglob("*.py"))]
    assert len(files) > 20, "the package sources were not found"
    return files


def walls(tree: ast.AST) -> list[tuple[str, int, int]]:
    """(name, line, positional parameters) of every function or lambda taking more than
    :data:`MAX_POSITIONAL` positionally."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            count = len(node.args.posonlyargs) + len(node.args.args)
            if count > MAX_POSITIONAL:
                found.append((getattr(node, "name", "<lambda>"), node.lineno, count))
    return found


def test_the_scanner_counts_positional_parameters_only():
    many = ", ".join(f"a{i}" for i in range(MAX_POSITIONAL + 1))
    snippet = (f"def wall({many}): pass\n"
               f"def fine(a, /, {', '.join(f'b{i}' for i in range(MAX_POSITIONAL - 1))}, *, "
               f"{', '.join(f'k{i}' for i in range(30))}): pass\n"
               f"class C:\n    def method(self, {many}): pass\n"
               f"f = lambda {many}: 0\n")
    assert [(name, count) for name, _, count in walls(ast.parse(snippet))] == [
        ("wall", MAX_POSITIONAL + 1), ("method", MAX_POSITIONAL + 2),
        ("<lambda>", MAX_POSITIONAL + 1)]


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_function_takes_a_wall_of_positional_arguments(path):
    found = walls(ast.parse(path.read_text(), str(path)))
    assert not found, (f"{path.relative_to(ROOT)}: functions with more than {MAX_POSITIONAL} "
                       f"positional parameters (name, line, count): {found}")


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_source_file_is_longer_than_a_reader_holds(path):
    lines = sum(1 for line in path.read_text().splitlines() if line.strip())
    assert lines <= MAX_LINES, (f"{path.relative_to(ROOT)} has {lines} non-blank lines (at most "
                                f"{MAX_LINES}): split it by job")
