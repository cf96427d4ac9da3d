"""The cparticles command line: simulate scenes, run agents, verify the numerics, benchmark.

Subcommands live beside the code they drive; each module provides ``add_arguments(parser)``
and ``main(args) -> int`` and is imported only when its subcommand is used. Every numeric option
is checked by argparse (finite, in range) and every output path before any work starts, so bad
input ends with one ``error:`` line and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
import tempfile
from collections.abc import Callable, Sequence

import numpy as np

from . import __version__
from .extras import MissingExtra
from .integrators import METHODS
from .scenes import SCENES
from .system import SimulationDiverged

#: name -> (module, one-line help). ``run`` is defined here.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": (__name__, "simulate a scene and print energy and constraint residual over time"),
    "demo": ("envs.demo", "run an agent on a Gymnasium environment and print its returns"),
    "verify": ("verification.__main__", "measure convergence orders and cross-check pymunk"),
    "view": ("constrained_particles.viewer", "interactive viewer (pygame-ce)"),
    "bench": ("constrained_particles.bench",
              "benchmark against pymunk, gymnasium's CartPole and the bare particle system"),
}

DESCRIPTION = ("constrained-particles: 2D constrained particle systems (Witkin & Baraff), "
               "Gymnasium environments and a solver-verification suite.")

#: Smallest time step (s) any command accepts.
MIN_DT = 1e-9
#: Most steps ``cparticles run`` takes (seconds / dt).
MAX_STEPS = 10**9


class HelpFormatter(argparse.HelpFormatter):
    """Plain help text with each option's default shown, unless it is None, False or empty."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if ("%(default)" in text or default is None or default is False
                or default == argparse.SUPPRESS or default == []):
            return text
        if isinstance(default, tuple):
            default = "x".join(str(d) for d in default)
        return f"{text} (default: {default})"


# ---------------------------------------------------------------- argparse types
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


def int_at_least(low: int) -> Callable[[str], int]:
    """argparse type factory: an integer >= ``low``."""

    def parse(text: str) -> int:
        value = int(_number(text, int))
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


def _probe_directory(path: str) -> None:
    """Raise OSError unless a file can be created in the existing directory ``path``."""
    with tempfile.TemporaryFile(dir=path or "."):
        pass


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
        try:
            _probe_directory(folder)
        except OSError as exc:
            raise argparse.ArgumentTypeError(
                f"cannot write to {folder or '.'!r}: {exc.strerror or exc}") from None
        return text

    parse.__name__ = "output file"
    return parse


def output_directory(text: str) -> str:
    """argparse type: a directory that exists or can be created, and is writable (created now;
    a file is created and deleted there to check)."""
    try:
        os.makedirs(text, exist_ok=True)
        _probe_directory(text)
    except OSError as exc:
        raise argparse.ArgumentTypeError(
            f"cannot write to {text!r}: {exc.strerror or exc}") from None
    return text


def progress_enabled(args: argparse.Namespace) -> bool:
    """Progress bars: on when stderr is a terminal, off with ``--quiet``; ``--progress`` forces
    them on."""
    if getattr(args, "quiet", False):
        return False
    return bool(getattr(args, "progress", False)) or sys.stderr.isatty()


# ---------------------------------------------------------------- cparticles run
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles run``."""
    parser.add_argument("scene", choices=sorted(SCENES), help="scene to simulate")
    parser.add_argument("--method", default="rk4", choices=sorted(METHODS), help="integrator")
    parser.add_argument("--dt", type=time_step, default=1e-3, help="time step in seconds")
    parser.add_argument("--seconds", type=positive_float, default=5.0,
                        help="simulated time in seconds, at least --dt")
    parser.add_argument("--every", type=positive_float, default=0.5,
                        help="print a row every this many simulated seconds")
    parser.add_argument("--project", action="store_true",
                        help="project back onto the constraints after every step")


def check_run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Checks across ``run``'s options: at least one and at most :data:`MAX_STEPS` steps."""
    steps = args.seconds / args.dt
    if steps < 1 - 1e-9:
        parser.error(f"--dt ({args.dt:g} s) must not exceed --seconds ({args.seconds:g} s)")
    if steps > MAX_STEPS:
        parser.error(f"--seconds / --dt is {steps:.3g} steps; at most {MAX_STEPS:.0e}")


def main_run(args: argparse.Namespace) -> int:
    """``cparticles run``: a table of t, energy, max |C| and max |Cdot|."""
    system = SCENES[args.scene]()
    system.project_each_step = args.project
    steps = max(1, int(round(args.seconds / args.dt)))
    every = max(1, int(round(min(args.every, args.seconds) / args.dt)))
    print(f"# {args.scene}: {system.n} particles, method={args.method}, dt={args.dt:g} s, "
          f"projection={'on' if args.project else 'off'}")
    print(f"{'t [s]':>8} {'energy [J]':>14} {'max|C|':>11} {'max|Cdot|':>11}")

    def row() -> None:
        C, Cdot = system.constraint_residual()
        worst = (np.max(np.abs(C)) if C.size else 0.0, np.max(np.abs(Cdot)) if C.size else 0.0)
        print(f"{system.t:8.3f} {system.energy():14.6e} {worst[0]:11.3e} {worst[1]:11.3e}")

    row()
    for k in range(1, steps + 1):
        try:
            system.step(args.dt, method=args.method)
        except SimulationDiverged as exc:
            print(f"diverged: {exc}", file=sys.stderr)
            return 1
        if k % every == 0 or k == steps:
            row()
    return 0


# ---------------------------------------------------------------- top level
def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The top-level parser. Only the module of the subcommand named in ``argv`` (default
    ``sys.argv[1:]``) is imported, so ``cparticles run`` never loads gymnasium or pygame."""
    parser = argparse.ArgumentParser(
        prog="cparticles", description=DESCRIPTION, formatter_class=HelpFormatter,
        epilog="Run 'cparticles COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    argv = sys.argv[1:] if argv is None else argv
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text,
                           formatter_class=HelpFormatter)
        if name == "run":
            add_arguments(p)
            p.set_defaults(handler=main_run, check=check_run)
        elif name == wanted:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.set_defaults(handler=mod.main, check=getattr(mod, "check_arguments", None))
        p.set_defaults(subparser=p)
    if wanted in (None, "train", "evaluate"):  # Stable-Baselines3 subcommands (the rl extra)
        importlib.import_module("envs.train").add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cparticles`` console script."""
    args = build_parser(argv).parse_args(argv)
    try:
        if getattr(args, "check", None) is not None:
            args.check(args.subparser, args)
        return int(args.handler(args) or 0)
    except MissingExtra as exc:  # the message names the command already
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"cparticles {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
