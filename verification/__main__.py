"""Measured convergence orders, a pymunk cross-check and the verification report.

The same subcommands run as ``python -m verification`` and as ``cparticles verify``::

    python -m verification orders [--quick] [--json] [--quiet]
    python -m verification pymunk [--quick] [--json] [--quiet]
    python -m verification energy [--quick] [--json] [--steps N] [--plot PNG] [--quiet]
    python -m verification report --out DIR [--quick] [--quiet]

Progress bars (tqdm, on stderr) show by default when stderr is a terminal. ``--json`` prints
one JSON object on one line (the shape is in each subcommand's ``--help``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from constrained_particles.arguments import (
    HelpFormatter,
    output_directory,
    output_file,
    progress_enabled,
    run_command,
)
from constrained_particles.extras import require

#: modules each subcommand needs (all from the ``verify`` extra)
NEEDS = {"orders": ("tqdm",), "pymunk": ("pymunk", "tqdm"), "energy": ("tqdm", "matplotlib"),
         "report": ("pymunk", "tqdm", "matplotlib")}

JSON_HELP = {
    "orders": 'print one JSON object on one line, {"case": {"method": observed order, ...}, '
              '...}, instead of a table',
    "pymunk": 'print one JSON object on one line, {"scene": {"order": observed order, '
              '"errors": {"dt": max position error in m, ...}}, ...}, instead of a table',
}


def _steps(text: str) -> int:
    """``--steps``: an integer in [3, 1e9] (argparse turns the ValueError into exit 2)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 3 <= value <= 10**9:
        raise argparse.ArgumentTypeError(f"must be in [3, 1e9], got {value}")
    return value


def _progress_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", "--no-progress", action="store_true",
                   help="no progress bars (they show by default when stderr is a terminal)")
    p.add_argument("--progress", action="store_true", help=argparse.SUPPRESS)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The subcommands ``orders``, ``pymunk`` and ``report``."""
    sub = parser.add_subparsers(dest="verify_command", required=True, metavar="SUBCOMMAND")
    for name, text in (("orders", "measured convergence order of every integrator"),
                       ("pymunk", "pymunk's convergence to our trajectories as its dt shrinks")):
        p = sub.add_parser(name, help=text, description=text, formatter_class=HelpFormatter)
        p.add_argument("--quick", action="store_true", help="fewer steps, shorter runs")
        p.add_argument("--json", action="store_true", help=JSON_HELP[name])
        _progress_options(p)
    text = "long-run energy error of every integrator (bounded or drifting)"
    p = sub.add_parser("energy", help=text, description=text, formatter_class=HelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer steps")
    p.add_argument("--steps", type=_steps, default=None,
                   help="steps per run (default: 100000, quick: 3000)")
    p.add_argument("--json", action="store_true",
                   help='print one JSON object on one line, {"system": {"method": {"max_error": '
                   '..., "trend": ..., ...}, ...}, ...}, instead of a table')
    p.add_argument("--plot", default=None, type=output_file(".png"),
                   help="also save the energy-error plot to this PNG (checked before any work; "
                   "default: no plot)")
    _progress_options(p)
    p = sub.add_parser("report", help="write the Markdown/JSON/PNG verification report",
                       description="run every experiment and write report.md, report.json and "
                                   "PNG plots into --out", formatter_class=HelpFormatter)
    p.add_argument("--out", required=True, type=output_directory,
                   help="output directory (created if missing; checked before any work)")
    p.add_argument("--quick", action="store_true",
                   help="the short version (about half a minute of CPU time)")
    _progress_options(p)


def main(args: argparse.Namespace) -> int:
    """Run the chosen subcommand; returns the exit status."""
    require(*NEEDS[args.verify_command], command=f"cparticles verify {args.verify_command}")
    progress = progress_enabled(args)
    if args.verify_command == "orders":
        from .orders import measure_orders, orders_summary, orders_table, orders_verdict

        results = measure_orders(quick=args.quick, progress=progress)
        verdict, agree = orders_verdict(results)
        print(json.dumps(orders_summary(results)) if args.json
              else f"{orders_table(results)}\n\n{verdict}")
        if not agree:
            return 1
    elif args.verify_command == "pymunk":
        from .pymunk_check import compare_all, pymunk_table

        results = compare_all(quick=args.quick, progress=progress)
        if args.json:
            print(json.dumps({n: {"order": round(r.order, 3),
                                  "errors": {f"{dt:g}": e for dt, e in zip(r.dts, r.errors,
                                                                           strict=True)}}
                              for n, r in results.items()}))
        else:
            print(pymunk_table(results))
    elif args.verify_command == "energy":
        from .longrun import LONG_STEPS, QUICK_STEPS, long_run_table, long_runs, plot_long_runs
        from .report import _jsonable

        steps = args.steps or (QUICK_STEPS if args.quick else LONG_STEPS)
        results = long_runs(steps, progress=progress)
        if args.plot:
            plot_long_runs(results, args.plot)
        if args.json:
            keep = ("max_error", "trend", "oscillation", "trend_ratio", "max_constraint",
                    "diverged_at", "cpu", "steps", "h")
            print(json.dumps(_jsonable({name: {m: {k: r[k] for k in keep} for m, r in per.items()}
                                        for name, per in results.items()})))
        else:
            print(long_run_table(results))
    else:
        from .report import write_report

        data = write_report(args.out, quick=args.quick, progress=progress)
        print(f"wrote {args.out}/report.md, report.json and plots in {data['seconds']:.1f} s")
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m verification``."""
    parser = argparse.ArgumentParser(prog="python -m verification",
                                     description=__doc__.splitlines()[0],
                                     formatter_class=HelpFormatter)
    add_arguments(parser)
    args = parser.parse_args(argv)
    return run_command(f"python -m verification {args.verify_command}", lambda: main(args))


if __name__ == "__main__":
    sys.exit(run())
