"""The decorator every compiled function of this project uses: ``numba.njit`` with a disk cache
in the user's cache directory.

Numba compiles a kernel on its first call; the cache keeps the machine code on disk so that the
next process loads it in well under a second instead of compiling again (tens of seconds for the
whole step). Numba's own ``cache=True`` writes next to the source file, that is into the
installed package (``site-packages/.../__pycache__``), where the files outlive an uninstall and
fail on a read-only install. Functions decorated with :func:`njit` cache instead in

1. ``$NUMBA_CACHE_DIR`` when that variable is set (Numba's own setting, honoured as Numba does);
2. otherwise the user's cache directory: ``$XDG_CACHE_HOME`` or ``~/.cache`` on Linux,
   ``~/Library/Caches`` on macOS, ``%LOCALAPPDATA%`` on Windows, in the sub-folder
   ``constrained-particles/numba-<numba version>-<python tag>``.

Inside it, each source folder gets its own sub-folder, named as Numba names them. A cached kernel
is used only while the sources it was compiled from are unchanged: Numba checks the function's
own file, but a kernel here also compiles in functions of other modules (the fused step calls
the elements of ``kernels.py`` and ``fused_accel.py``; the envs' kernels call the fused step), so
the stamp is the content of every module in the function's folder and in this package
(:func:`source_stamp`). When the chosen
directory cannot be created or written (a read-only home, say), the kernels compile in memory
instead: everything works, each new process compiles again, and one line on stderr says so.
A shared temporary directory is never used: the cache files are pickles, which anyone who can
write there could replace.

**A damaged cache heals itself.** A cache entry that cannot be loaded (an index or data file
truncated by a full disk or a killed process, garbled, empty, written by another Python, data
files left without their index) is set aside: its files are renamed with the suffix
``.unreadable`` in their folder, the kernel compiles again and is written afresh, and one line
on stderr (once per process) says what was found and where. A cache that cannot be written (a
full disk) keeps the compiled kernels in memory for the run, with one line too.

Only the functions decorated here are affected; Numba's settings for other code stay as they are.

When one of these functions starts compiling (its machine code is in no cache) and stderr is a
terminal, one line says so, once per process: a first run spends tens of seconds compiling, and
nothing else would tell the user why it waits. Output that is not a terminal (a pipe, a log file,
the tests) stays silent, as the command line's progress bars do.
"""

from __future__ import annotations

import functools
import glob
import hashlib
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba.core import caching, event
from numba.core.dispatcher import Dispatcher

__all__ = ["NUMBA_INTERNALS", "cache_dir", "default_cache_dir", "njit", "source_stamp"]

#: The parts of Numba this project uses that are not its documented public API, by dotted
#: name, with where and how: a Numba release may change them, so ``pyproject.toml`` bounds
#: Numba to the versions CI tests (the oldest and the newest allowed), and
#: ``tests/test_numba_internals.py`` checks each one, by name and by what the project needs of
#: it.
NUMBA_INTERNALS: dict[str, str] = {
    "numba.core.caching._CacheLocator": "jit: the base of the locator into the user's cache",
    "numba.core.caching._SourceFileBackedLocatorMixin":
        "jit: get_suitable_cache_subpath names a source folder's sub-folder",
    "numba.core.caching.CompileResultCacheImpl": "jit: _locator_classes takes this locator",
    "numba.core.caching.FunctionCache":
        "jit: load_overload/save_overload overridden to heal; _cache_path, "
        "_impl.filename_base name the files of an entry (<base>.nbi, <base>.<n>.nbc)",
    "numba.core.caching.IndexDataCacheFile":
        "jit: the index and data files an entry is made of (_save_index, _save_data)",
    "numba.core.dispatcher.Dispatcher._cache":
        "jit: set to the project's cache (what Dispatcher.enable_caching does)",
    "numba.core.event.register": "jit: a listener of numba:compile events",
    "numba.core.event.Listener": "jit: on_start gets ev.data['dispatcher']",
    "numba.config.CACHE_DIR": "jit: NUMBA_CACHE_DIR as Numba read it",
    "numba.extending.intrinsic":
        "parallel._load_acquire (an atomic load), records._borrowed (arrays without "
        "reference counts)",
    "numba.core.cgutils.get_item_pointer": "parallel._load_acquire: the address of flags[i]",
    "numba.core.cgutils.get_null_value": "records._strip: a null meminfo and parent",
    "numba.np.arrayobj.make_array":
        "records._strip: an array's struct, with the fields meminfo and parent",
    "numba.experimental.structref.register": "records: RecordRefType, records by reference",
    "numba.experimental.structref.StructRefProxy": "records: RecordRef, its ._type",
    "numba.experimental.structref.define_boxing": "records: RecordRef boxing",
    "numba.experimental.structref.new": "records._by_reference",
    "numba.extending.typeof_impl": "records: typeof of a RecordRef reads its ._type",
    "numba.extending.overload": "records: _by_reference, _live_lists (inline='always')",
}

APP = "constrained-particles"  #: the folder name inside the user's cache directory
#: A tag in the name of each cache folder, changed when the options given to :func:`njit` change
#: (numba's cache index does not record options such as ``nogil``: without it, code compiled
#: with the old options would be loaded in place of the new)
FLAVOUR = "o3"


def default_cache_dir() -> Path | None:
    """The folder :func:`njit` caches in when ``NUMBA_CACHE_DIR`` is not set, or None when the
    platform's user cache directory is unknown (no home directory)."""
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA", "")
    elif sys.platform == "darwin":
        base = os.path.expanduser("~/Library/Caches")
    else:
        base = os.environ.get("XDG_CACHE_HOME", "")
        if not os.path.isabs(base):  # unset, empty or relative: ignored, as the XDG spec says
            base = os.path.expanduser("~/.cache")
    if not os.path.isabs(base):  # "~" left unexpanded: no home directory
        return None
    tag = sys.implementation.cache_tag or f"py{sys.version_info[0]}{sys.version_info[1]}"
    return Path(base) / APP / f"numba-{numba.__version__}-{tag}"


def _writable(path: Path) -> str | None:
    """Create ``path`` and write a file in it; None on success, else the reason it failed."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


@functools.cache
def cache_dir() -> Path | None:
    """The directory the compiled kernels are cached in, or None when they compile in memory.

    Decided once per process, on first use (see the module docstring for the order). When no
    directory is usable, prints one line to stderr saying so and returns None."""
    configured = numba.config.CACHE_DIR  # Numba reads NUMBA_CACHE_DIR into this at import
    path = Path(configured).expanduser() if configured else default_cache_dir()
    reason = "no home directory" if path is None else _writable(path)
    if reason is None:
        return path
    where = "" if path is None else f" {path}"
    hint = "" if configured else " (set NUMBA_CACHE_DIR to a writable folder to keep them)"
    print(f"constrained-particles: cache directory{where} not usable ({reason}); compiled "
          f"kernels are kept in memory only, so each new process compiles them again{hint}",
          file=sys.stderr)
    return None


@functools.cache
def _folder_digest(folder: str) -> str:
    """SHA-256 of the names and contents of the ``*.py`` files in ``folder`` (once per process)."""
    digest = hashlib.sha256()
    for path in sorted(Path(folder).glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def source_stamp(py_file: str) -> tuple[str, str]:
    """The source stamp of the cached kernels defined in ``py_file``: digests of the modules in
    its folder and in this package. A cached kernel compiled from other sources (an edited
    module whose functions it calls, in a checkout) is compiled again instead of loaded."""
    return (_folder_digest(str(Path(py_file).resolve().parent)),
            _folder_digest(str(Path(__file__).resolve().parent)))


class _Locator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """Numba's cache locator pointing into :func:`cache_dir`, with Numba's own naming of the
    sub-folder for a source folder, and :func:`source_stamp` as the source stamp."""

    def __init__(self, py_func: Callable[..., Any], py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        root = cache_dir()
        if root is None:  # pragma: no cover - _cached only builds a cache when there is a dir
            raise OSError("no cache directory")
        self._cache_path = str(root / f"{self.get_suitable_cache_subpath(py_file)}-{FLAVOUR}")

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> tuple[str, str]:
        return source_stamp(self._py_file)


class _Impl(caching.CompileResultCacheImpl):
    _locator_classes = [_Locator]


#: the suffix a cache file that could not be loaded is renamed with (:func:`_set_aside`)
SET_ASIDE = ".unreadable"
#: what this process has said on stderr about the cache (each said once per process)
_SAID: set[str] = set()


def _say_once(topic: str, line: str) -> None:
    """Print ``line`` (one line) to stderr, the first time ``topic`` comes up in this process."""
    if topic in _SAID:
        return
    _SAID.add(topic)
    if sys.stderr is not None:
        print(" ".join(line.split()), file=sys.stderr, flush=True)


def _entry_files(cache: caching.FunctionCache) -> list[Path]:
    """The files of ``cache``'s entry: its index and every data file of the function."""
    base = cache._impl.filename_base
    folder = Path(cache._cache_path)
    return [folder / f"{base}.nbi", *sorted(folder.glob(f"{glob.escape(base)}.*.nbc"))]


def _set_aside(cache: caching.FunctionCache, exc: BaseException) -> None:
    """Rename the files of ``cache``'s entry (an index or data file that could not be loaded)
    with the suffix :data:`SET_ASIDE`, so that Numba compiles and writes the entry again, and
    say so on stderr, once per process. A file another process renamed or rewrote meanwhile
    is left to it."""
    moved = []
    for path in _entry_files(cache):
        try:
            os.replace(path, path.with_name(path.name + SET_ASIDE))
            moved.append(path.name)
        except OSError:
            pass
    what = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    _say_once("unreadable", f"constrained-particles: a compiled kernel in the cache could not be "
              f"loaded ({what[:200]}); its files in {cache._cache_path} were set aside as "
              f"*{SET_ASIDE} and it is compiled again (later ones in this run silently)")


class _Cache(caching.FunctionCache):
    """Numba's function cache with this module's locator, healing itself: an entry that cannot
    be loaded (a truncated, garbled or empty index or data file, files of another Numba or
    Python) is set aside (:func:`_set_aside`) and compiled again instead of failing the call;
    a cache that cannot be written (a full disk) leaves the compiled code in memory."""

    _impl_class = _Impl

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        try:
            loaded = super().load_overload(sig, target_context)
        except Exception as exc:  # (any damage: pickle, EOF, value, type, import errors...)
            _set_aside(self, exc)
            return None
        if loaded is None:
            files = _entry_files(self)
            if not files[0].exists() and len(files) > 1:  # data files left without an index
                _set_aside(self, FileNotFoundError(f"data files without their index "
                                                   f"{files[0].name}"))
        return loaded

    def save_overload(self, sig: Any, data: Any) -> None:
        for attempt in (1, 2):
            try:
                super().save_overload(sig, data)
                return
            except OSError as exc:  # (a full disk, a folder gone read-only: kept in memory)
                _say_once("unwritable", f"constrained-particles: a compiled kernel could not "
                          f"be written to the cache in {self._cache_path} "
                          f"({exc.strerror or exc}); it is kept in memory for this run")
                return
            except Exception as exc:  # the index read before writing was damaged meanwhile
                _set_aside(self, exc)
                if attempt == 2:
                    return


#: ``id`` of every dispatcher made by :func:`njit` (they live as long as their modules)
_OURS: set[int] = set()


class _CompileNotice(event.Listener):
    """Numba's ``numba:compile`` events (a cache miss, then a compile): the first one of a
    function decorated here prints one line to stderr, a terminal or not (a notebook, a CI
    log), so that nobody waits in silence."""

    def __init__(self) -> None:
        self.said = False

    def on_start(self, ev: event.Event) -> None:
        data = ev.data if isinstance(ev.data, dict) else {}
        if self.said or id(data.get("dispatcher")) not in _OURS:
            return
        if "unreadable" in _SAID:  # (that line said it compiles again)
            self.said = True
            return
        self.said = True
        stream = sys.stderr
        if stream is None:
            return
        where = cache_dir()
        if where is None:  # (the line saying no cache is usable said they compile each run)
            return
        print(f"constrained-particles: compiling kernels, first run only (tens of seconds; "
              f"cached in {where}) ...", file=stream, flush=True)

    def on_end(self, ev: event.Event) -> None:
        pass


event.register("numba:compile", _CompileNotice())


def _cached(dispatcher: Any) -> Any:
    """``dispatcher`` with its disk cache in :func:`cache_dir` (or none: compiled in memory)."""
    if not isinstance(dispatcher, Dispatcher):
        return dispatcher  # NUMBA_DISABLE_JIT gave the plain function
    _OURS.add(id(dispatcher))
    if cache_dir() is None:
        return dispatcher  # no usable directory: compiled in memory
    try:
        # what ``Dispatcher.enable_caching`` does, with this module's locator
        dispatcher._cache = _Cache(dispatcher.py_func)
    except (OSError, RuntimeError):  # directory gone since cache_dir() checked it
        pass
    return dispatcher


def njit(func: Callable[..., object] | None = None, **options: bool | str
         ) -> Callable[..., object]:
    """``numba.njit(**options)`` with the disk cache described in the module docstring.

    Use as ``@njit`` or ``@njit(inline="always")``; ``cache`` is not an option (always on where
    a cache directory is usable). Give ``nogil=True`` to an entry point that runs long enough
    (a whole step: hundreds of microseconds) for other threads to use the released GIL, such
    as the ranges of a threaded system; a short call keeps it, since every release lets
    another thread take the GIL and makes this one wait for it on return.

    Division follows NumPy (``error_model="numpy"``): a float divided by zero is inf or nan,
    as in the numpy reference, which the kernels' finiteness checks then catch (a diverging
    step, or the reference path taking over), never a ZeroDivisionError out of compiled
    code."""
    if "cache" in options:
        raise ValueError("options: 'cache' is decided by constrained_particles.jit, not per call")
    options.setdefault("error_model", "numpy")

    def decorate(f: Callable[..., object]) -> Callable[..., object]:
        return _cached(numba.njit(**options)(f))

    return decorate if func is None else decorate(func)
