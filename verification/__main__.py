"""Measured convergence orders, a pymunk cross-check and the verification report.

The same subcommands run as ``python -m verification`` and as ``cparticles verify``::

    python -m verification orders [--quick] [--json]
    python -m verification pymunk [--quick] [--json]
    python -m verification energy [--quick] [--json] [--steps N] [--plot PNG]
    python -m verification report --out DIR [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The subcommands ``orders``, ``pymunk`` and ``report``."""
    sub = parser.add_subparsers(dest="verify_command", required=True, metavar="SUBCOMMAND")
    for name, text in (("orders", "measured convergence order of every integrator"),
                       ("pymunk", "pymunk's convergence to our trajectories as its dt shrinks")):
        p = sub.add_parser(name, help=text, description=text)
        p.add_argument("--quick", action="store_true", help="fewer steps, shorter runs")
        p.add_argument("--json", action="store_true",
                       help='print {"case": {"method": order, ...}, ...} instead of a table')
        p.add_argument("--progress", action="store_true", help="show a progress bar")
    text = "long-run energy error of every integrator (bounded or drifting)"
    p = sub.add_parser("energy", help=text, description=text)
    p.add_argument("--quick", action="store_true", help="fewer steps")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default: 100000, "
                                                             "quick: 3000)")
    p.add_argument("--json", action="store_true",
                   help="print the figures per system and method as JSON instead of a table")
    p.add_argument("--plot", default=None, help="also save the energy-error plot to this PNG")
    p.add_argument("--progress", action="store_true", help="show a progress bar")
    p = sub.add_parser("report", help="write the Markdown/JSON/PNG verification report",
                       description="run every experiment and write report.md, report.json and "
                                   "PNG plots into --out")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--quick", action="store_true", help="the short version (under a minute)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def main(args: argparse.Namespace) -> int:
    """Run the chosen subcommand; returns the exit status."""
    if args.verify_command == "orders":
        from .orders import measure_orders, orders_summary, orders_table

        results = measure_orders(quick=args.quick, progress=args.progress)
        print(json.dumps(orders_summary(results), indent=1) if args.json
              else orders_table(results))
    elif args.verify_command == "pymunk":
        from .pymunk_check import compare_all, pymunk_table

        results = compare_all(quick=args.quick, progress=args.progress)
        if args.json:
            print(json.dumps({n: {"order": round(r.order, 3),
                                  "errors": {f"{dt:g}": e for dt, e in zip(r.dts, r.errors,
                                                                           strict=True)}}
                              for n, r in results.items()}, indent=1))
        else:
            print(pymunk_table(results))
    elif args.verify_command == "energy":
        from .longrun import LONG_STEPS, QUICK_STEPS, long_run_table, long_runs, plot_long_runs
        from .report import _jsonable

        steps = args.steps or (QUICK_STEPS if args.quick else LONG_STEPS)
        if steps < 3:
            raise SystemExit(f"--steps must be >= 3, got {steps}")
        results = long_runs(steps, progress=args.progress)
        if args.plot:
            plot_long_runs(results, args.plot)
        if args.json:
            keep = ("max_error", "trend", "oscillation", "trend_ratio", "max_constraint",
                    "diverged_at", "cpu", "steps", "h")
            print(json.dumps(_jsonable({name: {m: {k: r[k] for k in keep} for m, r in per.items()}
                                        for name, per in results.items()}), indent=1))
        else:
            print(long_run_table(results))
    else:
        from .report import write_report

        data = write_report(args.out, quick=args.quick, progress=not args.no_progress)
        print(f"wrote {args.out}/report.md, report.json and plots in {data['seconds']:.1f} s")
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m verification``."""
    parser = argparse.ArgumentParser(prog="python -m verification",
                                     description=__doc__.splitlines()[0])
    add_arguments(parser)
    return main(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(run())
