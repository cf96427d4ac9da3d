"""The cparticles command line: simulate scenes, run agents, train, verify, benchmark.

It sits above the three packages it drives (:mod:`constrained_particles`, :mod:`envs`,
:mod:`verification`), which never import it. Subcommands live beside the code they drive: each
:class:`Command` names the module and its ``add_arguments(parser)``, optional
``check_arguments(parser, args)`` and ``main(args) -> int``, and that module is imported only
when its subcommand is used. Every numeric option is checked by argparse (finite, in range)
and every output path before any work starts (the types in
:mod:`constrained_particles.arguments`), so bad input ends with one ``error:`` line and exit
status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from constrained_particles import METHODS, SimulationDiverged, __version__
from constrained_particles.arguments import (
    HelpFormatter,
    positive_float,
    run_command,
    time_step,
)
from constrained_particles.scenes import SCENES


class Command(NamedTuple):
    """Where a subcommand lives: ``module`` and the names of its functions there."""

    module: str
    help: str
    add: str = "add_arguments"
    check: str | None = "check_arguments"
    main: str = "main"


#: name -> where it lives. ``run`` is defined here.
SUBCOMMANDS: dict[str, Command] = {
    "run": Command(__name__, "simulate a scene and print energy and constraint residual over "
                   "time", check="check_run", main="main_run"),
    "demo": Command("envs.demo", "run an agent on a Gymnasium environment and print its "
                    "returns"),
    "train": Command("envs.train_cli", "train a Stable-Baselines3 agent with the shipped "
                     "hyperparameters (rl extra)", add="add_train_arguments",
                     check="check_train_arguments", main="main_train"),
    "evaluate": Command("envs.train_cli", "evaluate a run directory that train wrote, on held-out "
                        "episodes (rl extra)",
                        add="add_evaluate_arguments", check="check_evaluate_arguments",
                        main="main_evaluate"),
    "convert-run": Command("envs.train_cli", "convert a run directory of an older train (pickles) "
                           "for evaluate; loads its pickles: trusted directories only (rl "
                           "extra)", add="add_convert_arguments",
                           check="check_convert_arguments", main="main_convert"),
    "verify": Command("verification.__main__", "measure convergence orders and cross-check "
                      "pymunk", check=None),
    "view": Command("constrained_particles.viewer", "interactive viewer (pygame-ce)"),
    "bench": Command("cparticles.bench", "benchmark against pymunk, gymnasium's CartPole and "
                     "the bare particle system"),
}

DESCRIPTION = ("constrained-particles: 2D constrained particle systems (Witkin & Baraff), "
               "Gymnasium environments and a solver-verification suite.")

#: Most steps ``cparticles run`` takes (seconds / dt).
MAX_STEPS = 10**9


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
    for name, command in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=command.help, description=command.help,
                           formatter_class=HelpFormatter)
        if name == wanted:
            mod = importlib.import_module(command.module)
            getattr(mod, command.add)(p)
            p.set_defaults(handler=getattr(mod, command.main),
                           check=getattr(mod, command.check) if command.check else None)
        p.set_defaults(subparser=p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cparticles`` console script."""
    args = build_parser(argv).parse_args(argv)

    def checked() -> int | None:
        if getattr(args, "check", None) is not None:
            args.check(args.subparser, args)
        return args.handler(args)

    return run_command(f"cparticles {args.command}", checked)


if __name__ == "__main__":
    sys.exit(main())
