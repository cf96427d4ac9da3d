"""The published baselines (docs/baselines): run the grid, then make the plots and the table.

    python -m envs.baselines run --runs runs --jobs 2                   # the full grid
    python -m envs.baselines run --runs runs --envs ClothSlide-v0 --modes force --algos ppo
    python -m envs.baselines report --runs runs                         # plots + table
    python -m envs.baselines ship runs/RUN --results runs/results.json  # a pretrained agent

Everything is written where the options say, nothing elsewhere. ``run`` trains every (env,
action mode it takes, algorithm, seed) of the grid with ``cparticles train`` (the shipped
hyperparameters and budgets) into ``RUNS/<env>-<mode>-<algo>-<seed>`` (a run whose
``config.json`` exists is not trained again), evaluates each on ``EPISODES`` held-out episodes
(seeds from ``HELD_OUT_SEED_START``), deterministic and stochastic, and merges the records into
``--results`` (default ``RUNS/results.json``): ``{"env", "action_mode", "algo", "seed",
"timesteps", "success_rate", "mean_return", "eval_episodes", "deterministic", "wall_seconds",
...}``. ``--publish DIR`` (the published set is ``docs/baselines`` of the checkout) also copies
each run's config.json and evaluations.json (not its models) into ``DIR/runs/<run>/`` and merges
the records into ``DIR/results.json``. Trainings run in up to ``--jobs`` subprocesses, each with
one torch thread.

``report`` draws the learning curves (periodic evaluations from each run's evaluations.json in
``--runs``: median and interquartile range over seeds) into ``OUT/curves.png`` and writes
``OUT/table.md`` (``--out``, default ``--runs``): per (env, mode, algo), the median success rate
over seeds with a distribution-free confidence interval for the median (order statistics; with 5
seeds the interval is [min, max], coverage 94%), the median return, and the training time.

``ship`` keeps one run as the pretrained agent of its task, action mode and variant
(:func:`envs.pretrained.ship`: the run's data files and its held-out figures from
``--results``; a SAC run without its critics).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from constrained_particles.arguments import (
    HelpFormatter,
    int_at_least,
    new_directory,
    positive_float,
)

from .task import check_env_kwargs, env_action_modes, parse_variant
from .train import ALGOS, HELD_OUT_SEED_START

#: Held-out episodes per evaluation.
EPISODES = 100
#: Seeds per algorithm in the full grid (the issue: PPO 5, the second algorithm 3).
GRID_SEEDS = {"ppo": [0, 1, 2, 3, 4], "sac": [0, 1, 2]}
#: Fields that identify a record (a new record with the same fields replaces the old one);
#: ``variant`` (:func:`envs.task.variant_key` of the env keyword arguments) is ``""`` for the
#: default configuration, and absent from its records.
KEY_FIELDS = ("env", "variant", "action_mode", "algo", "seed", "deterministic")


def _key(record: dict[str, Any]) -> tuple[str, ...]:
    return tuple(str(record.get(k, "")) for k in KEY_FIELDS)


def run_name(env: str, mode: str, algo: str, seed: int, variant: str = "") -> str:
    """The run directory's name for one grid cell (a variant's keyword arguments between
    the env and the mode: ``ChainSwing-v0-target-swingup-force-ppo-0``)."""
    tag = variant.replace("=", "-").replace(",", "_")
    return f"{env}-{tag + '-' if tag else ''}{mode}-{algo}-{seed}"


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "cparticles", *args]


def train_and_evaluate(runs: Path, env: str, mode: str, algo: str, seed: int,
                       timesteps: int | None = None, episodes: int = EPISODES,
                       timeout: float | None = None, publish: Path | None = None,
                       variant: str = "") -> list[dict[str, Any]]:
    """Train one cell (unless already trained) and evaluate it both ways; its two records.
    ``variant``: the env keyword arguments (:func:`envs.task.variant_key` form; ``""`` the
    default configuration). With ``publish``, the run's config.json and evaluations.json are
    copied to ``publish/runs/<run>/``."""
    out = runs / run_name(env, mode, algo, seed, variant)
    if not (out / "config.json").is_file():
        cmd = _cli("train", env, "--algo", algo, "--seed", str(seed), "--out", str(out),
                   "--action-mode", mode, "--no-progress")
        if variant:
            cmd += ["--env-kwargs", *variant.split(",")]
        if timesteps is not None:
            cmd += ["--timesteps", str(timesteps)]
        runs.mkdir(parents=True, exist_ok=True)
        # (beside the run: train takes only a new or empty directory, and renames its own
        # into place when complete)
        with open(runs / f"{out.name}.train.log", "w") as log:
            subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT,
                           timeout=timeout)
    config = json.loads((out / "config.json").read_text())
    if publish is not None:
        # the learning curve and what was run, kept with the published results (not the models)
        kept = publish / "runs" / out.name
        kept.mkdir(parents=True, exist_ok=True)
        for name in ("config.json", "evaluations.json"):
            if (out / name).is_file():
                (kept / name).write_text((out / name).read_text())
    records = []
    for deterministic in (True, False):
        cmd = _cli("evaluate", str(out), "--episodes", str(episodes), "--seed-start",
                   str(HELD_OUT_SEED_START), "--json")
        if not deterministic:
            cmd.append("--stochastic")
        line = subprocess.run(cmd, check=True, capture_output=True, text=True,
                              timeout=timeout).stdout.strip().splitlines()[-1]
        res = json.loads(line)
        records.append({"env": env, **({"variant": variant} if variant else {}),
                        "action_mode": mode, "algo": algo, "seed": seed,
                        "timesteps": config["timesteps"], "success_rate": res["success_rate"],
                        "mean_return": round(res["mean_return"], 4),
                        "mean_length": res["mean_length"], "eval_episodes": res["episodes"],
                        "mean_normalized_performance": res.get("mean_normalized_performance"),
                        "eval_seed_start": res["seed_start"], "deterministic": deterministic,
                        "wall_seconds": config["wall_seconds"],
                        "mean_abs_squeeze": res["mean_abs_squeeze"],
                        "rms_speed_near_goal": res["rms_speed_near_goal"],
                        "failures_final_distance": res["failures_final_distance"],
                        "failures_final_speed": res["failures_final_speed"],
                        "run": out.name})
    return records


def merge(path: Path, new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Merge ``new`` records into the JSON list at ``path`` (same key: replaced); write it."""
    old = json.loads(path.read_text()) if path.is_file() else []
    keys = {_key(r) for r in new}
    merged = [r for r in old if _key(r) not in keys] + new
    merged.sort(key=_key)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(merged, indent=1) + "\n")
    return merged


def median_ci(values: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Distribution-free interval ``[x_(k), x_(n+1-k)]`` for the median of ``values``: the
    narrowest order-statistic interval whose coverage is at least ``level`` (or [min, max] if
    none is); returns ``(low, high, coverage)``."""
    x = np.sort(np.asarray(values, float))
    n = len(x)
    best = (x[0], x[-1], 1.0 - 2 * 0.5**n)
    for k in range(1, n // 2 + 1):
        # P(x_(k) <= median <= x_(n+1-k)) = 1 - 2 P(Binomial(n, 1/2) <= k - 1)
        tail = sum(math.comb(n, j) for j in range(k)) / 2**n
        coverage = 1 - 2 * tail
        if coverage >= level or k == 1:
            best = (x[k - 1], x[n - k], coverage)
    return best


def _median_cell(s: np.ndarray, low: float, high: float, coverage: float) -> str:
    """The success column: the median with its interval and the interval's coverage; one
    seed has no interval to give."""
    if len(s) == 1:
        return f"{s[0]:.0%} (one seed: no interval)"
    return f"{np.median(s):.0%} [{low:.0%}, {high:.0%}] ({coverage:.0%})"


def report(results_path: Path, runs: Path, docs: Path) -> str:
    """Write ``docs/table.md`` and ``docs/curves.png`` (``docs``: any folder) from the results
    and the runs' learning curves; returns the table (markdown)."""
    records = json.loads(results_path.read_text())
    cells: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in records:
        env = f"{r['env']} ({r['variant']})" if r.get("variant") else r["env"]
        cells.setdefault((env, r["action_mode"], r["algo"]), []).append(r)
    lines = ["| env | action mode | algo | seeds | steps | "
             "success (det.), median [CI] (coverage) | "
             "success (stoch.), median | return (det.), median | train time / seed |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (env, mode, algo), recs in sorted(cells.items()):
        det = [r for r in recs if r["deterministic"]]
        sto = [r for r in recs if not r["deterministic"]]
        if not det:
            continue
        s = np.array([r["success_rate"] for r in det])
        low, high, cov = median_ci(s)
        sto_s = np.median([r["success_rate"] for r in sto]) if sto else float("nan")
        minutes = np.median([r["wall_seconds"] for r in det]) / 60
        lines.append(f"| {env} | {mode} | {algo.upper()} | {len(det)} | "
                     f"{int(np.median([r['timesteps'] for r in det])):,} | "
                     f"{_median_cell(s, low, high, cov)} | "
                     f"{sto_s:.0%} | {np.median([r['mean_return'] for r in det]):.2f} | "
                     f"{minutes:.1f} min |")
    table = "\n".join(lines) + "\n"
    (docs / "table.md").write_text(table)
    _plot_curves(cells, runs, docs / "curves.png")
    return table


def _plot_curves(cells: dict, runs: Path, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    panels = sorted({(env, mode) for env, mode, _ in cells})
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4), squeeze=False)
    for ax, (env, mode) in zip(axes[0], panels, strict=True):
        for algo in ALGOS:
            recs = [r for r in cells.get((env, mode, algo), []) if r["deterministic"]]
            curves = []
            for r in recs:
                f = runs / r["run"] / "evaluations.json"
                if f.is_file():
                    ev = json.loads(f.read_text())
                    curves.append((np.array([e["timesteps"] for e in ev]),
                                   np.array([e["success_rate"] for e in ev])))
            if not curves:
                continue
            grid = np.unique(np.concatenate([c[0] for c in curves]))
            ys = np.array([np.interp(grid, t, y) for t, y in curves])
            q25, q50, q75 = np.percentile(ys, [25, 50, 75], axis=0)
            line, = ax.plot(grid, q50, label=f"{algo.upper()} ({len(curves)} seeds)")
            ax.fill_between(grid, q25, q75, alpha=0.25, color=line.get_color())
        ax.set_title(f"{env}, {mode}")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:.0f}k"))
        ax.set_xlabel("env steps")
        ax.set_ylabel("success rate (periodic eval)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def new_directory_file(text: str) -> str:
    """argparse type: a file path whose folder exists or can be created, and is writable."""
    new_directory(os.path.dirname(os.path.abspath(text)))
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory")
    return text


def main(argv: list[str] | None = None) -> int:
    """``python -m envs.baselines {run,report,ship}``."""
    p = argparse.ArgumentParser(prog="python -m envs.baselines",
                                description=__doc__.split("\n")[0], formatter_class=HelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="train and evaluate the grid", formatter_class=HelpFormatter)
    r.add_argument("--runs", default="runs", type=new_directory,
                   help="folder of the run directories (created)")
    takes_modes = env_action_modes()
    ids = list(takes_modes)
    r.add_argument("--envs", nargs="+", default=ids, choices=ids,
                   metavar="ENV_ID", help=f"env ids, of {', '.join(ids)}")
    modes = sorted({m for v in takes_modes.values() for m in v})
    r.add_argument("--modes", nargs="+", default=modes, choices=modes,
                   help="action modes (each env trains in those it takes)")
    r.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    r.add_argument("--variants", nargs="+", default=["default"], metavar="KEY=VALUE[,...]",
                   help="configurations to train: 'default', or env keyword arguments such "
                   "as target=swingup or obs_mode=pixels (each trains with its own shipped "
                   "settings where the task ships them)")
    r.add_argument("--seeds", nargs="+", type=int_at_least(0),
                   help="seeds (default: " + ", ".join(f"{len(v)} for {k.upper()}"
                                                       for k, v in GRID_SEEDS.items()) + ")")
    r.add_argument("--timesteps", type=int_at_least(1),
                   help="override the shipped budgets (default: the shipped budgets)")
    r.add_argument("--episodes", type=int_at_least(1), default=EPISODES,
                   help="held-out episodes per evaluation")
    r.add_argument("--jobs", type=int_at_least(1), default=1, help="trainings in parallel")
    r.add_argument("--timeout", type=positive_float,
                   help="seconds allowed per training (default: no limit)")
    r.add_argument("--results", type=new_directory_file,
                   help="JSON file the records are merged into (default: RUNS/results.json)")
    r.add_argument("--publish", type=new_directory,
                   help="also copy each run's config.json and evaluations.json (no models) to "
                   "PUBLISH/runs/ and merge the records into PUBLISH/results.json (default: "
                   "no copy)")
    g = sub.add_parser("report", help="plots and table from results.json",
                       formatter_class=HelpFormatter)
    g.add_argument("--runs", default="runs",
                   help="folder with <run>/evaluations.json (a run folder or a published one)")
    g.add_argument("--results", help="records to tabulate (default: RUNS/results.json)")
    g.add_argument("--out", type=new_directory,
                   help="folder for table.md and curves.png (created; default: RUNS)")
    h = sub.add_parser("ship", help="keep a run as the package's pretrained agent of its task",
                       formatter_class=HelpFormatter)
    h.add_argument("run", help="run directory (train's; a SAC run's critics are left out)")
    h.add_argument("--results", required=True,
                   help="the baselines' records holding the run's held-out figures")
    h.add_argument("--root", help="folder of the shipped agents (default: the package's "
                   "envs/pretrained)")
    args = p.parse_args(argv)
    if args.command == "ship":
        from . import pretrained

        try:
            folder = pretrained.ship(args.run, args.results, args.root or pretrained.ROOT)
        except ValueError as exc:
            what, _, words = str(exc).partition(": ")
            p.error(f"argument {what if what == 'run' else '--' + what}: {words}")
        print(folder)
        return 0
    runs = Path(args.runs)
    results = Path(args.results) if args.results else runs / "results.json"
    if args.command == "report":
        if not results.is_file():
            p.error(f"argument --results: {str(results)!r} does not exist")
        out = Path(args.out) if args.out else runs
        out.mkdir(parents=True, exist_ok=True)
        print(report(results, runs, out), end="")
        return 0
    variants = ["" if v == "default" else v for v in args.variants]
    for env in args.envs:
        for v in variants:
            try:
                check_env_kwargs(env, parse_variant(v))
            except ValueError as exc:
                p.error(f"argument --variants: {env}: {exc}")
    grid = [(env, mode, algo, seed, v) for env in args.envs for v in variants
            for mode in args.modes if mode in takes_modes[env]
            for algo in args.algos for seed in (args.seeds or GRID_SEEDS[algo])]
    if not grid:
        takes = "; ".join(f"{e} takes {', '.join(takes_modes[e])}" for e in args.envs)
        p.error(f"no env in --envs takes an action mode in --modes ({takes})")
    publish = Path(args.publish) if args.publish else None
    lock = threading.Lock()

    def cell(c: tuple[str, str, str, int, str]) -> list[dict[str, Any]]:
        recs = train_and_evaluate(runs, *c[:4], timesteps=args.timesteps,
                                  episodes=args.episodes, timeout=args.timeout,
                                  publish=publish, variant=c[4])
        with lock:
            merge(results, recs)
            if publish is not None:
                merge(publish / "results.json", recs)
        print(f"{run_name(*c[:4], variant=c[4])}: success {recs[0]['success_rate']:.0%} "
              f"(deterministic), {recs[1]['success_rate']:.0%} (stochastic), "
              f"{recs[0]['wall_seconds']:.0f} s",
              flush=True)
        return recs

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        list(pool.map(cell, grid))
    return 0


if __name__ == "__main__":
    sys.exit(main())
