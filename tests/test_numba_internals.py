"""The Numba internals the project relies on (``constrained_particles.jit.NUMBA_INTERNALS``),
each still there and doing what the project needs of it, on the installed Numba: a release
that changes one fails here by name, not somewhere deep in a compile. CI runs these against
the oldest and the newest Numba that ``pyproject.toml`` allows."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import numpy as np
import pytest

from constrained_particles import kernels
from constrained_particles.jit import NUMBA_INTERNALS

ROOT = Path(__file__).resolve().parents[1]
compiled = pytest.mark.skipif(not kernels.ENABLED, reason="the compiled path is off "
                              "(CPARTICLES_NUMBA=0): its internals are not used")


def resolve(dotted: str) -> object:
    """The object a dotted name names (a module, then attributes)."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for name in parts[i:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(dotted)


@pytest.mark.parametrize("name", sorted(NUMBA_INTERNALS))
def test_every_listed_internal_exists(name: str) -> None:
    if name.endswith("._cache"):  # (an instance attribute: a dispatcher made by njit has it)
        from constrained_particles import jit

        assert hasattr(jit.njit(lambda x: x), "_cache")
        name = name.rsplit(".", 1)[0]
    assert resolve(name) is not None


def test_the_list_names_every_numba_import_of_the_packages() -> None:
    """Every ``from numba.X import Y`` (X not public API) in the shipped packages is listed."""
    public = {"numba", "numba.typed"}
    listed = set(NUMBA_INTERNALS)
    missing = []
    for package in ("constrained_particles", "envs", "verification", "cparticles"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for module, names in re.findall(r"from (numba[\w.]*) import ([\w, ]+)",
                                            path.read_text()):
                if module in public:
                    continue
                for name in (n.strip() for n in names.split(",")):
                    if name in ("types",):  # (numba.core.types: the public type objects)
                        continue
                    if not any(k == f"{module}.{name}" or k.startswith(f"{module}.{name}.")
                               for k in listed):
                        missing.append(f"{path.relative_to(ROOT)}: {module}.{name}")
    assert missing == []


def test_cache_locator_and_entry_files(tmp_path, monkeypatch) -> None:
    """The locator names the sub-folder as Numba does, and an entry's files are
    ``<filename_base>.nbi`` and ``<filename_base>.<n>.nbc`` in ``_cache_path``."""
    from numba.core import caching

    from constrained_particles import jit

    def twice(x):
        return 2.0 * x

    monkeypatch.setattr(jit, "cache_dir", lambda: tmp_path)
    cache = jit._Cache(twice)
    assert isinstance(cache, caching.FunctionCache)
    assert Path(cache._cache_path).parent == tmp_path
    assert Path(cache._cache_path).name.endswith(f"-{jit.FLAVOUR}")
    files = jit._entry_files(cache)
    assert files[0].name == f"{cache._impl.filename_base}.nbi"
    assert isinstance(cache._cache_file, caching.IndexDataCacheFile)
    assert cache._cache_file._index_path == str(files[0])


@compiled
def test_compile_events_name_their_dispatcher() -> None:
    from numba.core import event

    from constrained_particles import jit

    seen = []

    class Spy(event.Listener):
        def on_start(self, ev):
            seen.append(ev.data.get("dispatcher") if isinstance(ev.data, dict) else None)

        def on_end(self, ev):
            pass

    spy = Spy()
    event.register("numba:compile", spy)
    try:
        f = jit.njit(lambda x: x + 1.0)
        f._cache.disable()  # (nothing written to the user's cache)
        assert f(1.0) == 2.0
    finally:
        event.unregister("numba:compile", spy)
    assert f in seen


@compiled
def test_atomic_load_intrinsic() -> None:
    from constrained_particles import parallel

    flags = np.array([0, 5, 2], np.int64)
    assert parallel._wait_for(flags, 1, 5, 10)
    assert not parallel._wait_for(flags, 2, 3, 10)
    assert not parallel._wait_for(flags, 7, 0, 10)  # (outside the array: False at once)


@compiled
def test_borrowed_arrays_keep_their_data() -> None:
    from constrained_particles import records
    from constrained_particles.jit import njit

    @njit
    def total(a, t):
        b, (c, d) = records.borrowed((a, t))
        return b.sum() + c.sum() + d

    a, c = np.arange(6.0).reshape(2, 3), np.ones(4)
    assert total(a, (c, 2.5)) == a.sum() + c.sum() + 2.5


@compiled
def test_records_by_reference() -> None:
    """A record held by reference (structref) crosses into compiled code and back, typed by
    its ``_type`` (typeof_impl), its fields read there."""
    import numba

    from constrained_particles import records
    from constrained_particles.jit import njit

    backing = records.workspace(3, 2, 2)
    ref = records.workspace_ref(*backing)
    assert isinstance(ref, records.RecordRef)
    assert numba.typeof(ref) is ref._type

    @njit
    def read(w):
        w.spare_x[0, 0] = 7.0  # (a field is a view of its backing array)
        return w.A.shape[0], w.Jv.shape[0]

    assert read(ref) == (2, 2)
    assert backing[0][0, 0, 0] == 7.0


@compiled
def test_a_record_by_reference_keeps_its_borrowed_arrays_alive() -> None:
    """A record held by reference holds its arrays borrowed (no reference counts in compiled
    code): the reference itself keeps them alive. With every other Python reference to a
    large workspace dropped (NumPy would hand its pages back to the system), a kernel still
    reads and writes it through the reference; run in a child process, so that a reference
    that failed to keep its arrays fails this test instead of crashing the run."""
    import subprocess
    import sys

    code = (
        "import gc\n"
        "from constrained_particles import records\n"
        "from constrained_particles.jit import njit\n"
        "@njit\n"
        "def touch(w):\n"
        "    w.spare_x[-1, 1] = 5.0\n"
        "    s = 0.0\n"
        "    for q in range(w.spare_x.shape[0]):\n"
        "        s += w.spare_x[q, 0] + w.spare_x[q, 1]\n"
        "    return s\n"
        "ref = records.workspace_ref(*records.workspace(200_000, 3, 2))\n"
        "gc.collect()\n"
        "import numpy as np\n"  # (arrays of the workspace's sizes take over freed memory)
        "filler = [np.full(a.shape, 7.0) for a in records.workspace(200_000, 3, 2)]\n"
        "assert touch(ref) == 5.0, touch(ref)\n"
        "print('ok')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
