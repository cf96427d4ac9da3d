"""argparse types and checks shared by the command lines built on this package.

``cparticles`` (the :mod:`cparticles` package), ``python -m verification`` and the subcommands
that :mod:`envs` and :mod:`constrained_particles.viewer` contribute all parse their options with
these, so every numeric option is checked (finite, in range) and every output path is checked
writable before any work starts: a bad value ends in one ``error:`` line and exit status 2,
never a traceback.

    >>> int_at_least(1)("3")
    3
    >>> time_step("1e-3")
    0.001
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from .extras import MissingExtra

#: Smallest time step (s) any command accepts.
MIN_DT = 1e-9


class HelpFormatter(argparse.HelpFormatter):
    """Plain help text with each option's default shown, unless it is None, False or empty
    (an option whose default is None states in its help what happens without it)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if ("%(default)" in text or default is None or default is False
                or default == argparse.SUPPRESS or default == []):
            return text
        if isinstance(default, tuple):
            default = "x".join(str(d) for d in default)
        return f"{text} (default: {default})"


def _number(text: str, kind: Callable[[str], float | int]) -> float | int:
    try:
        value = kind(text)
    except ValueError:
        name = "a number" if kind is float else "an integer"
        raise argparse.ArgumentTypeError(f"must be {name}, got {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0 (and at least 1e-300, so that 1 / x is finite)."""
    value = float(_number(text, float))
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    if value < 1e-300:
        raise argparse.ArgumentTypeError(f"must be at least 1e-300, got {text!r}")
    return value


def time_step(text: str) -> float:
    """argparse type: a time step in seconds, finite and at least :data:`MIN_DT`."""
    value = float(_number(text, float))
    if not value >= MIN_DT:
        raise argparse.ArgumentTypeError(f"must be at least {MIN_DT:g} s, got {text!r}")
    return value


def int_at_least(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type factory: an integer >= ``low`` (and <= ``high`` if given)."""

    def parse(text: str) -> int:
        value = int(_number(text, int))
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {text!r}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be <= {high}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


def key_values(items: list[str] | None, option: str, tuples_for_lists: bool = True
               ) -> dict[str, object]:
    """The ``KEY=VALUE`` pairs of an option given as ``nargs="*"`` (or one JSON object), as a
    dict: a value is read as JSON where it is JSON (numbers, ``true``, ``null``, lists, quoted
    strings), else kept as the string it is (``target=swingup``); JSON lists become tuples
    (unless ``tuples_for_lists`` is False).
    ValueError naming ``option`` for a pair without ``=``, an empty key, a key given twice or
    JSON that is not an object.

    >>> key_values(["target=swingup", "links=3", "goal_range=[-0.3, 0.3]"], "--env-kwargs")
    {'target': 'swingup', 'links': 3, 'goal_range': (-0.3, 0.3)}
    """
    import json

    def tuples(value: object) -> object:
        if isinstance(value, list) and tuples_for_lists:
            return tuple(tuples(v) for v in value)
        if isinstance(value, dict):
            return {k: tuples(v) for k, v in value.items()}
        if isinstance(value, list):
            return [tuples(v) for v in value]
        return value

    if not items:
        return {}
    if len(items) == 1 and items[0].lstrip().startswith("{"):
        try:
            got = json.loads(items[0])
        except json.JSONDecodeError as exc:
            raise ValueError(f"{option}: not a JSON object ({exc})") from None
        if not isinstance(got, dict):
            raise ValueError(f"{option}: not a JSON object")
        return {k: tuples(v) for k, v in got.items()}
    out: dict[str, object] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"{option}: {item!r} is not KEY=VALUE")
        if key in out:
            raise ValueError(f"{option}: {key!r} is given twice")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        if isinstance(value, float) and not math.isfinite(value):
            value = text
        out[key] = tuples(value)
    return out


def _reason(exc: OSError) -> str:
    """`` (why)`` a file cannot be created in an existing directory, or nothing where the
    system's words would mislead (a directory like /proc exists, yet a new file in it is "No
    such file or directory")."""
    if exc.errno in (errno.EACCES, errno.EPERM):
        return " (permission denied)"
    if exc.errno == errno.EROFS:
        return " (read-only file system)"
    if exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.EINVAL, errno.EOPNOTSUPP):
        return ""
    return f" ({(exc.strerror or str(exc)).lower()})"


def writable_directory_problem(path: str) -> str | None:
    """None if a file can be created in the existing directory ``path`` (checked by creating
    and deleting a temporary file there), else the reason in a few words."""
    try:
        with tempfile.TemporaryFile(dir=path or "."):
            pass
    except OSError as exc:
        return f"directory {path or '.'!r} does not accept new files{_reason(exc)}"
    return None


def output_file(*suffixes: str) -> Callable[[str], str]:
    """argparse type factory: a file path ending in one of ``suffixes`` whose directory exists
    and is writable (checked by creating and deleting a temporary file there)."""

    def parse(text: str) -> str:
        if suffixes and not text.lower().endswith(suffixes):
            raise argparse.ArgumentTypeError(f"must end in {' or '.join(suffixes)}, got {text!r}")
        folder = os.path.dirname(text)
        if folder and not os.path.isdir(folder):
            raise argparse.ArgumentTypeError(f"directory {folder!r} does not exist")
        if os.path.isdir(text):
            raise argparse.ArgumentTypeError(f"{text!r} is a directory")
        problem = writable_directory_problem(folder)
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return text

    parse.__name__ = "output file"
    return parse


def new_directory(text: str) -> str:
    """argparse type: a directory that can be created (or exists), and is writable. Nothing is
    created: the deepest existing ancestor is probed, so a later usage error leaves nothing
    behind."""
    if not text:
        raise argparse.ArgumentTypeError("must not be empty")
    path = os.path.abspath(text)
    if os.path.lexists(path) and not os.path.exists(path):
        raise argparse.ArgumentTypeError(f"{text!r} is a symbolic link to nothing (dangling)")
    if os.path.exists(path) and not os.path.isdir(path):
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a directory")
    existing = path
    while not os.path.isdir(existing):
        parent = os.path.dirname(existing)
        if os.path.lexists(existing) or parent == existing:
            # a file where a parent directory should be
            raise argparse.ArgumentTypeError(
                f"cannot create {text!r}: {existing!r} is not a directory")
        existing = parent
    problem = writable_directory_problem(existing)
    if problem:
        raise argparse.ArgumentTypeError(f"cannot create {text!r}: {problem}"
                                         if existing != path else problem)
    return text


def output_directory(text: str) -> str:
    """argparse type: a directory that exists or can be created, and is writable (created now;
    a file is created and deleted there to check)."""
    new_directory(text)
    try:
        os.makedirs(text, exist_ok=True)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot create {text!r}{_reason(exc)}") from None
    problem = writable_directory_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def progress_enabled(args: argparse.Namespace) -> bool:
    """Progress bars: on when stderr is a terminal, off with ``--quiet``; ``--progress`` forces
    them on."""
    if getattr(args, "quiet", False):
        return False
    return bool(getattr(args, "progress", False)) or sys.stderr.isatty()


def os_error_words(exc: OSError) -> str:
    """An OSError in a few words: the system's reason and the file(s) it names."""
    words = exc.strerror or " ".join(str(exc).split()) or type(exc).__name__
    files = [f for f in (exc.filename, exc.filename2) if f is not None]
    return words + "".join(f": {os.fsdecode(f)}" for f in files)


def run_command(prog: str, call: Callable[[], int | None]) -> int:
    """``call()``'s exit status; a :class:`~constrained_particles.extras.MissingExtra` (whose
    message names the command) or a ValueError becomes one ``error:`` line on stderr and exit
    status 2 (a mistake in the arguments or the files given), an OSError (a full disk, a
    permission denied while working) one ``error:`` line and exit status 1."""
    try:
        return int(call() or 0)
    except MissingExtra as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"{prog}: error: {' '.join(str(exc).splitlines())}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"{prog}: error: {os_error_words(exc)}", file=sys.stderr)
        return 1


@contextmanager
def written_whole(path: str | os.PathLike[str]) -> Iterator[str]:
    """The name of a temporary file beside ``path`` to write, renamed to ``path`` when the
    block ends without an error and removed otherwise: a full disk or an interrupt never
    leaves a truncated ``path`` (nor replaces the file that was there)."""
    path = os.fspath(path)
    folder, name = os.path.split(os.path.abspath(path))
    while True:  # (created with the permissions a new file gets: the umask's)
        partial = os.path.join(folder, f".{name}.partial-{os.getpid()}-{os.urandom(4).hex()}")
        try:
            open(partial, "xb").close()
            break
        except FileExistsError:
            continue
    try:
        yield partial
        os.replace(partial, path)
    finally:
        if os.path.lexists(partial):
            os.unlink(partial)
