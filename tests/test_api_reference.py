"""The public API's type hints and the user docs' wording.

1. No public signature is annotated ``Any``. The signatures are read from the source (``ast``),
   so a module is checked whether or not its optional dependencies are installed: a public
   function, a public class's ``__init__``/``__call__`` and public methods (properties too),
   public class attributes (dataclass and named-tuple fields) and annotated module constants.
   "Public": a name without a leading underscore, in a module without one, and in the module's
   ``__all__`` where it has one.

   - :data:`STRICT` modules (every module of ``constrained_particles`` and ``verification``):
     ``Any`` appears nowhere in a public signature, nested ones (``dict[str, Any]``) included.
   - :data:`NO_BARE_ANY` modules (``envs`` and ``cparticles``): no annotation *is* ``Any`` or a
     union or callable around a bare ``Any``; ``Any`` may stand only as the value type of a
     heterogeneous record (``dict[str, Any]``: Gymnasium's ``info``, a JSON config).

2. The signatures resolve: :func:`typing.get_type_hints` evaluates every exported class's
   constructor, and ``help(DampedSpring)`` shows array-like arguments.

3. The docs and the packages' docstrings are written for users: no plans of work, no narrated
   history, no commit hashes, no citations of "the report" outside
   docs/notes_on_the_report.md (the one page for readers of the student report the project
   started from).
"""

from __future__ import annotations

import ast
import inspect
import pydoc
import re
import typing
from pathlib import Path

import pytest

import constrained_particles

ROOT = Path(__file__).resolve().parent.parent


def _modules(package: str) -> list[str]:
    """Every module of ``package`` whose name (and path) has no leading underscore but
    ``__init__``, as dotted names, from the source tree."""
    out = []
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts.pop()
        if any(p.startswith("_") for p in parts) or parts[-1:] == ["__main__"]:
            continue
        out.append(".".join(parts))
    return out


#: Modules in which ``Any`` appears in no public signature at all.
STRICT = _modules("constrained_particles") + _modules("verification")
#: Modules in which no public annotation is a bare ``Any``.
NO_BARE_ANY = _modules("envs") + _modules("cparticles")


def _source(module: str) -> ast.Module:
    path = ROOT / Path(*module.split("."))
    path = path.with_suffix(".py") if path.with_suffix(".py").exists() else path / "__init__.py"
    return ast.parse(path.read_text(), str(path))


def _all(tree: ast.Module) -> set[str] | None:
    for node in tree.body:
        if (isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__"
                                                 for t in node.targets)):
            return {e.value for e in node.value.elts}  # type: ignore[attr-defined]
    return None


def _module_level(body: list[ast.stmt]) -> list[ast.stmt]:
    """Statements at module level, looking inside ``if``/``try`` blocks (a compiled-only
    definition sits under ``if kernels.ENABLED:``)."""
    out: list[ast.stmt] = []
    for node in body:
        if isinstance(node, ast.If):
            out += _module_level(node.body) + _module_level(node.orelse)
        elif isinstance(node, ast.Try):
            out += _module_level(node.body)
        else:
            out.append(node)
    return out


def _function_annotations(where: str, fn: ast.FunctionDef | ast.AsyncFunctionDef
                          ) -> list[tuple[str, ast.expr]]:
    args = fn.args
    every = args.posonlyargs + args.args + args.kwonlyargs
    found = [(f"{where}({a.arg})", a.annotation) for a in every if a.annotation is not None]
    for star in (args.vararg, args.kwarg):
        if star is not None and star.annotation is not None:
            found.append((f"{where}(*{star.arg})", star.annotation))
    if fn.returns is not None:
        found.append((f"{where} -> return", fn.returns))
    return found


def public_annotations(module: str) -> list[tuple[str, ast.expr]]:
    """``(where, annotation)`` of every public signature of ``module`` (see the module
    docstring)."""
    tree = _source(module)
    exported = _all(tree)

    def public(name: str) -> bool:
        return not name.startswith("_") and (exported is None or name in exported)

    found: list[tuple[str, ast.expr]] = []
    for node in _module_level(tree.body):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and public(node.name):
            found += _function_annotations(f"{module}.{node.name}", node)
        elif (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
              and public(node.target.id)):
            found.append((f"{module}.{node.target.id}", node.annotation))
        elif isinstance(node, ast.ClassDef) and public(node.name):
            for item in node.body:
                where = f"{module}.{node.name}"
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and (
                        not item.name.startswith("_") or item.name in ("__init__", "__call__")):
                    found += _function_annotations(f"{where}.{item.name}", item)
                elif (isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
                      and not item.target.id.startswith("_")):
                    found.append((f"{where}.{item.target.id}", item.annotation))
    return found


def _is_any(node: ast.expr) -> bool:
    return (isinstance(node, ast.Name) and node.id == "Any") or (
        isinstance(node, ast.Attribute) and node.attr == "Any")


def _bare_any(node: ast.expr) -> bool:
    """``Any`` itself, ``Any`` in a union, or ``Any`` as a callable's argument or result: an
    annotation that tells the reader nothing about a value it names."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):  # a quoted annotation
        return _bare_any(ast.parse(node.value, mode="eval").body)
    if _is_any(node):
        return True
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
        return _bare_any(node.left) or _bare_any(node.right)
    if isinstance(node, ast.Subscript):
        name = ast.unparse(node.value).rsplit(".", 1)[-1]
        inner = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        if name in ("Optional", "Union", "ClassVar", "Final"):
            return any(_bare_any(e) for e in inner)
        if name == "Callable":
            flat = [x for e in inner for x in (e.elts if isinstance(e, ast.List) else [e])]
            return any(_bare_any(e) for e in flat)
    return False


def _mentions_any(node: ast.expr) -> bool:
    text = node.value if isinstance(node, ast.Constant) else ast.unparse(node)
    return bool(re.search(r"\bAny\b", str(text)))


def test_the_checker_tells_bare_from_nested_any():
    def ann(text: str) -> ast.expr:
        return ast.parse(text, mode="eval").body

    for bare in ("Any", "Any | None", "typing.Any", "Callable[[Any], int]",
                 "Callable[..., Any]", "Optional[Any]", "'Any'"):
        assert _bare_any(ann(bare)), bare
    for precise in ("ArrayLike", "dict[str, Any]", "list[dict[str, Any]]", "Anything",
                    "NDArray[np.float64] | None", "Callable[[np.ndarray], np.ndarray]"):
        assert not _bare_any(ann(precise)), precise
    assert _mentions_any(ann("dict[str, Any]")) and not _mentions_any(ann("AnyStr"))


def test_the_walk_covers_the_public_api():
    # the walk reaches the names users meet (a check that it reads what it claims to)
    seen = {where for m in STRICT + NO_BARE_ANY for where, _ in public_annotations(m)}
    for name in ("constrained_particles.forces.DampedSpring.__init__(i)",
                 "constrained_particles.system.ParticleSystem.add_particles(positions)",
                 "constrained_particles.raster.coverage(points)",
                 "verification.strategies.random_system(seed)",
                 "envs.goals.compute_reward(achieved_goal)",
                 "envs.single.ParticleEnv.step(action)",
                 "envs.sb3.GymnasiumVecEnv.reset -> return",
                 "envs.train.load_policy -> return"):
        assert name in seen, name
    assert "envs._measure" not in NO_BARE_ANY and "constrained_particles.records" in STRICT


@pytest.mark.parametrize("module", STRICT)
def test_no_any_in_public_signatures(module):
    offending = [f"{where}: {ast.unparse(a)}" for where, a in public_annotations(module)
                 if _mentions_any(a)]
    assert not offending, "\n".join(offending)


@pytest.mark.parametrize("module", NO_BARE_ANY)
def test_no_bare_any_in_public_signatures(module):
    offending = [f"{where}: {ast.unparse(a)}" for where, a in public_annotations(module)
                 if _bare_any(a)]
    assert not offending, "\n".join(offending)


@pytest.mark.parametrize("name", [n for n in constrained_particles.__all__
                                  if inspect.isclass(getattr(constrained_particles, n))])
def test_exported_constructors_resolve(name):
    cls = getattr(constrained_particles, name)
    if "__init__" not in vars(cls):
        return  # (the class inherits its constructor: checked on the class that defines it)
    hints = typing.get_type_hints(cls.__init__)
    assert all(h is not typing.Any for h in hints.values()), hints


def test_help_shows_precise_types():
    from constrained_particles import DampedSpring

    text = pydoc.render_doc(DampedSpring, renderer=pydoc.plaintext)
    signature = next(line for line in text.splitlines() if "__init__(self" in line)
    assert "Any" not in signature
    for argument in ("i: 'ArrayLike'", "rest: 'ArrayLike | None' = None", "ks: 'ArrayLike'"):
        assert argument in signature, signature


# ---------------------------------------------------------------- the docs' wording
#: Phrases of a lab notebook, with what they stand for.
NOTEBOOK = {
    r"goals are not met": "a verdict on the project's own goals",
    r"\bplan to\b|\bplans? of work\b|\bplan to reach\b": "a plan of work",
    r"\bdeliverables?\b": "a plan of work",
    r"\bsitting\b": "a work session",
    r"\bcommit [0-9a-f]{7,40}\b": "a commit hash",
    r"before the environments changed": "history",
    r"report eq\.": "an equation number of the student report",
    r"\bthe issue's\b|\bother developers\b|\bhand-over of the crew\b|\bthe crew's hand-over\b":
        "the project's bookkeeping",
}
#: Citations of the student report: only docs/notes_on_the_report.md (and the pages' one link
#: to it) speaks of it.
REPORT = (r"\bthe\s+report's\b|(?<!readers\sof\sthe\s)\b(?:student|original)\s+report\b"
          r"(?!\s+the\s+project\s+started\s+from)")


def _user_texts() -> list[Path]:
    texts = [ROOT / "README.md"]
    texts += sorted(p for p in (ROOT / "docs").rglob("*")
                    if p.suffix in (".md", ".rst", ".py") and "runs" not in p.parts)
    for package in ("constrained_particles", "envs", "verification", "cparticles"):
        texts += sorted((ROOT / package).rglob("*.py"))
    return texts


def test_the_scan_reads_the_docs_and_the_packages():
    names = {p.relative_to(ROOT).as_posix() for p in _user_texts()}
    for name in ("README.md", "docs/compile_time.md", "docs/performance.md", "docs/training.md",
                 "docs/api/index.rst", "envs/cloth_pin.py", "verification/report.py"):
        assert name in names, name
    assert re.search(REPORT, "as the report's eq. 3 says", re.I)
    assert re.search(REPORT, "the original report writes", re.I)
    assert not re.search(REPORT, "the verification report's tables", re.I)
    assert not re.search(REPORT, "for readers of the original report", re.I)
    assert not re.search(REPORT, "the student report\nthe project started from", re.I)


@pytest.mark.parametrize("pattern", sorted(NOTEBOOK), ids=lambda p: NOTEBOOK[p].replace(" ", "-"))
def test_docs_read_as_documentation(pattern):
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in _user_texts()
            for i, line in enumerate(p.read_text().splitlines(), 1)
            if re.search(pattern, line, re.I)]
    assert not hits, f"{NOTEBOOK[pattern]}:\n" + "\n".join(hits)


def test_only_the_notes_page_cites_the_report():
    notes = ROOT / "docs" / "notes_on_the_report.md"
    hits = []
    for p in _user_texts():
        text = p.read_text()
        if p != notes:  # (over the whole text: a phrase may wrap)
            hits += [f"{p.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}: "
                     f"{m.group(0)!r}" for m in re.finditer(REPORT, text, re.I)]
    assert not hits, "\n".join(hits)
