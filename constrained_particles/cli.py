"""The ``cparticles`` command line.

Subcommands live beside the code they drive; each module provides ``add_arguments(parser)``
and ``main(args) -> int`` and is imported only when its subcommand is used.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

import numpy as np

from .integrators import METHODS
from .scenes import SCENES
from .system import SimulationDiverged

#: name -> (module, one-line help). ``run`` is defined here.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": (__name__, "simulate a scene and print energy and constraint residual over time"),
    "demo": ("envs.demo", "run an agent on a Gymnasium environment and print its returns"),
    "verify": ("verification.__main__", "measure convergence orders and cross-check pymunk"),
    "view": ("constrained_particles.viewer", "interactive viewer (pygame-ce)"),
    "bench": ("benchmarks.run", "benchmark against pymunk and the environments' throughput"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``cparticles run``."""
    parser.add_argument("scene", choices=sorted(SCENES), help="scene to simulate")
    parser.add_argument("--method", default="rk4", choices=sorted(METHODS), help="integrator")
    parser.add_argument("--dt", type=float, default=1e-3, help="time step in seconds")
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated time in seconds")
    parser.add_argument("--every", type=float, default=0.5,
                        help="print a row every this many simulated seconds")
    parser.add_argument("--project", action="store_true",
                        help="project back onto the constraints after every step")


def main_run(args: argparse.Namespace) -> int:
    """``cparticles run``: a table of t, energy, max |C| and max |Cdot|."""
    if not args.dt > 0 or not args.seconds > 0 or not args.every > 0:
        raise ValueError("--dt, --seconds and --every must be > 0")
    system = SCENES[args.scene]()
    system.project_each_step = args.project
    steps = int(round(args.seconds / args.dt))
    every = max(1, int(round(args.every / args.dt)))
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


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The top-level parser. Only the module of the subcommand named in ``argv`` (default
    ``sys.argv[1:]``) is imported, so ``cparticles run`` never loads gymnasium or pygame."""
    parser = argparse.ArgumentParser(prog="cparticles", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    argv = sys.argv[1:] if argv is None else argv
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == "run":
            add_arguments(p)
            p.set_defaults(handler=main_run)
        elif name == wanted:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.set_defaults(handler=mod.main)
    if wanted in (None, "train", "evaluate"):  # Stable-Baselines3 subcommands (the rl extra)
        importlib.import_module("envs.train").add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cparticles`` console script."""
    args = build_parser(argv).parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except ValueError as exc:
        print(f"cparticles {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
