"""Compile time of the Numba kernels: CPU and wall seconds per command, and what each function cost.

Runs each command in a child process that shares one fresh, empty ``NUMBA_CACHE_DIR`` (a
temporary directory, removed afterwards unless ``--keep-cache`` names one), so the first command
compiles everything it uses, later commands compile only what the earlier ones did not, and a
repeated command shows the warm cost. Per run it reports the child's CPU seconds (user + sys, from
``os.wait4``) and wall seconds, and, from Numba's event API inside the child (``numba:compile``
and ``numba:llvm_lock`` events, and a timer around the cache's ``load_overload``), each
dispatcher's compiles: CPU seconds exclusive of nested compiles and cache loads (a compile of
``f`` that triggers a compile of ``g`` is charged to ``g``) and the part of them inside LLVM,
inclusive seconds, the signatures compiled in the run and those loaded from the disk cache, the
argument positions where its signatures differ and the functions whose compile triggered it.
Times are the thread CPU time of the thread that compiles. Functions marked ``inline="always"``
never compile on their own: their cost is inside every caller's.

    python -m benchmarks.compile_time                    # the three default demo runs
    python -m benchmarks.compile_time --json > out.json
    python -m benchmarks.compile_time --cmd "python -m cparticles demo --env ChainSwing-v0"

A command starting with ``python`` runs under this interpreter with the recorder installed; any
other command runs as given (totals only). The targets it prints are the project's goals for a
first ClothSlide demo (20 s CPU), SliderCrank's first demo after it (10 s) and a warm demo (5 s).
"""

from __future__ import annotations

import argparse
import json
import os
import runpy
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

DEMO = "python -m cparticles demo --env {env} --agent scripted --episodes 1"

#: (label, command, CPU-second target) of the default runs, in order, on one cache.
#: (The first two tasks of the registration list are ClothSlide and SliderCrank.)
_FIRST, _SECOND = (spec.id for spec in __import__("envs").task_specs()[:2])
DEFAULT_RUNS: tuple[tuple[str, str, float], ...] = (
    ("ClothSlide demo, empty cache", DEMO.format(env=_FIRST), 20.0),
    ("SliderCrank demo after it", DEMO.format(env=_SECOND), 10.0),
    ("ClothSlide demo, warm cache", DEMO.format(env=_FIRST), 5.0),
)

CHILD = "--child-report"  # internal: argv[1] of a child run under the recorder


# ----------------------------------------------------------------------------- pure helpers


def exclusive_times(events: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Nested intervals with their exclusive time.

    ``events`` is a sequence of ``{"status": "start"|"end", "cpu": s, "wall": s, ...}`` records
    in the order they happened, starts and ends properly nested (one thread). Returns one record
    per interval (the other keys of its start and end records kept), in order of ending, with
    ``cpu``/``wall``
    (inclusive seconds), ``cpu_self``/``wall_self`` (minus the inclusive time of the intervals
    directly inside it), ``depth`` (0 for an outermost interval) and ``parent`` (the enclosing
    interval's ``kind`` and ``name``, or None).
    """
    stack: list[dict[str, Any]] = []
    done: list[dict[str, Any]] = []
    for ev in events:
        if ev["status"] == "start":
            rec = {k: v for k, v in ev.items() if k not in ("status", "cpu", "wall")}
            rec.update(_cpu0=ev["cpu"], _wall0=ev["wall"], _child_cpu=0.0, _child_wall=0.0,
                       depth=len(stack),
                       parent=(stack[-1].get("kind"), stack[-1].get("name")) if stack else None)
            stack.append(rec)
        else:
            if not stack:
                raise ValueError("events: an end without a start")
            rec = stack.pop()
            rec.update((k, v) for k, v in ev.items() if k not in ("status", "cpu", "wall"))
            cpu, wall = ev["cpu"] - rec.pop("_cpu0"), ev["wall"] - rec.pop("_wall0")
            rec.update(cpu=cpu, wall=wall, cpu_self=cpu - rec.pop("_child_cpu"),
                       wall_self=wall - rec.pop("_child_wall"))
            if stack:
                stack[-1]["_child_cpu"] += cpu
                stack[-1]["_child_wall"] += wall
            done.append(rec)
    if stack:
        raise ValueError("events: a start without an end")
    return done


def signature_variants(signatures: Sequence[Sequence[str]]) -> dict[int, list[str]]:
    """Argument positions at which a dispatcher's signatures differ, with the types seen there
    (sorted). Empty for one signature or identical ones."""
    if not signatures:
        return {}
    width = max(len(s) for s in signatures)
    out: dict[int, list[str]] = {}
    for k in range(width):
        seen = {s[k] if k < len(s) else "<absent>" for s in signatures}
        if len(seen) > 1:
            out[k] = sorted(seen)
    return out


def per_function(intervals: Iterable[dict[str, Any]],
                 dispatchers: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per function: exclusive/inclusive CPU and wall seconds of its compiles and of its
    cache loads in this run, signatures compiled and loaded, the functions whose compile
    triggered its compiles (``compiled_from``), sorted by exclusive CPU, largest first.
    ``intervals`` come from :func:`exclusive_times` (``kind`` "compile", "load" or "llvm",
    ``name``, ``parent``, and for a load ``hit``: False when the cache had no entry, its time
    is ``miss_cpu``). An "llvm" interval (time inside LLVM) directly inside a compile stays in
    that compile's ``compile_cpu`` and is also shown as its ``llvm_cpu``; a load's time is
    inclusive (LLVM work inside it included); an llvm interval outside both is charged to the
    row "(LLVM outside compiles)", one inside another llvm interval to nothing more.
    ``dispatchers`` are the child's end-of-run records (``name``, ``signatures``,
    ``compiled``, ``loaded``, ``inline``)."""
    rows: dict[str, dict[str, Any]] = {}

    def row(name: str) -> dict[str, Any]:
        return rows.setdefault(name, {
            "name": name, "compile_cpu": 0.0, "compile_cpu_incl": 0.0, "compile_wall": 0.0,
            "llvm_cpu": 0.0, "load_cpu": 0.0, "miss_cpu": 0.0, "compiles": 0, "loads": 0,
            "signatures": [], "compiled": 0, "loaded": 0, "inline": False, "variants": {},
            "compiled_from": []})

    for iv in intervals:
        if iv["kind"] == "llvm":
            parent = iv["parent"]
            if parent is None:
                row("(LLVM outside compiles)")["compile_cpu"] += iv["cpu"]
            elif parent[0] == "compile":
                row(parent[1])["llvm_cpu"] += iv["cpu"]
                row(parent[1])["compile_cpu"] += iv["cpu"]
                row(parent[1])["compile_wall"] += iv["wall"]
            continue
        r = row(iv["name"])
        if iv["kind"] == "compile":
            r["compile_cpu"] += iv["cpu_self"]
            r["compile_cpu_incl"] += iv["cpu"] if iv["depth"] == 0 else 0.0
            r["compile_wall"] += iv["wall_self"]
            r["compiles"] += 1
            parent = iv.get("parent")
            if parent is not None and parent[1] not in r["compiled_from"]:
                r["compiled_from"].append(parent[1])
        elif iv["hit"]:
            r["load_cpu"] += iv["cpu"]
            r["loads"] += 1
        else:
            r["miss_cpu"] += iv["cpu"]
    for d in dispatchers:
        r = row(d["name"])
        r.update(signatures=d["signatures"], compiled=d["compiled"], loaded=d["loaded"],
                 inline=d["inline"], variants=signature_variants(d["signatures"]))
    return sorted(rows.values(), key=lambda r: (-r["compile_cpu"], -r["load_cpu"], r["name"]))


def format_table(rows: Sequence[dict[str, Any]], top: int | None = None) -> str:
    """Text table of :func:`per_function` rows (seconds; ``sigs`` = signatures the dispatcher
    holds at the end of the run, ``new``/``hit`` = compiled in the run / loaded from cache)."""
    head = f"{'function':<46} {'cpu self':>8} {'llvm':>6} {'cpu top':>8} {'load':>6} " \
           f"{'sigs':>4} {'new':>4} {'hit':>4}  differing argument types"
    lines = [head, "-" * len(head)]
    for r in list(rows)[:top]:
        if r["inline"]:
            continue
        diff = "; ".join(f"arg {k}: {' | '.join(v)}" for k, v in r["variants"].items())
        lines.append(f"{_short(r['name']):<46} {r['compile_cpu']:8.2f} {r['llvm_cpu']:6.2f} "
                     f"{r['compile_cpu_incl']:8.2f} {r['load_cpu']:6.2f} "
                     f"{len(r['signatures']):4d} {r['compiled']:4d} {r['loaded']:4d}  {diff}")
    return "\n".join(lines)


def _short(name: str, width: int = 46) -> str:
    return name if len(name) <= width else "..." + name[-(width - 3):]


# ----------------------------------------------------------------------------- child side


def _child(report: str, argv: list[str]) -> None:
    """Run ``argv`` (``-m module args``, ``-c code args`` or ``script args``) in this process
    with Numba's compile events and cache loads recorded; write the record to ``report`` at
    exit."""
    from numba.core import caching, event
    from numba.core.dispatcher import Dispatcher

    events: list[dict[str, Any]] = []

    def mark(status: str, **data: Any) -> None:
        events.append({"status": status, "cpu": time.thread_time(), "wall": time.perf_counter(),
                       **data})

    class Listener(event.Listener):
        def on_start(self, ev: Any) -> None:
            d = ev.data
            mark("start", kind="compile", name=_qualname(d["dispatcher"].py_func),
                 args=[str(a) for a in d["args"]])

        def on_end(self, ev: Any) -> None:
            mark("end")

    load = caching.Cache.load_overload

    def timed_load(self: Any, sig: Any, target_context: Any) -> Any:
        mark("start", kind="load", name=_qualname(self._py_func))
        hit = False
        try:
            cres = load(self, sig, target_context)
            hit = cres is not None
            return cres
        finally:
            mark("end", hit=hit)

    class LLVM(event.Listener):
        def on_start(self, ev: Any) -> None:
            mark("start", kind="llvm", name="llvm")

        def on_end(self, ev: Any) -> None:
            mark("end")

    caching.Cache.load_overload = timed_load  # type: ignore[method-assign]
    event.register("numba:compile", Listener())
    event.register("numba:llvm_lock", LLVM())
    t0 = (time.process_time(), time.perf_counter())
    status = 0
    try:
        sys.argv = argv[1:] if argv[0] in ("-m", "-c") else argv
        if argv[0] == "-m":
            sys.path.insert(0, os.getcwd())
            sys.argv[0] = argv[1]
            runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
        elif argv[0] == "-c":
            sys.path.insert(0, "")
            sys.argv[0] = "-c"
            exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})
        else:
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as e:
        status = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        import gc
        disp = []
        for obj in gc.get_objects():
            if isinstance(obj, Dispatcher) and (obj.overloads or "inline" in obj.targetoptions):
                disp.append({
                    "name": _qualname(obj.py_func),
                    "signatures": [[str(a) for a in s] for s in obj.overloads],
                    "compiled": sum(obj._cache_misses.values()),
                    "loaded": sum(obj._cache_hits.values()),
                    "inline": obj.targetoptions.get("inline", "never") != "never"})
        Path(report).write_text(json.dumps({
            "events": events, "dispatchers": disp,
            "process_cpu": time.process_time() - t0[0],
            "wall": time.perf_counter() - t0[1]}))
    sys.exit(status)


def _qualname(func: Any) -> str:
    return f"{getattr(func, '__module__', '?')}.{getattr(func, '__qualname__', repr(func))}"


# ----------------------------------------------------------------------------- parent side


def run_one(command: str, cache: str, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``command`` with ``NUMBA_CACHE_DIR=cache``; CPU (user+sys) and wall seconds of the
    child, its exit status, and (for a ``python`` command) the per-function record."""
    argv = shlex.split(command)
    report = None
    if argv and argv[0] in ("python", "python3"):
        fd, report = tempfile.mkstemp(suffix=".json")
        os.close(fd)
        argv = [sys.executable, str(Path(__file__).resolve()), CHILD, report, *argv[1:]]
    child_env = dict(os.environ if env is None else env, NUMBA_CACHE_DIR=cache)
    with tempfile.TemporaryFile() as err:  # a file, not a pipe: a long stderr cannot block
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, env=child_env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
        err.seek(0)
        stderr = err.read().decode(errors="replace")
    out: dict[str, Any] = {"command": command, "cpu": usage.ru_utime + usage.ru_stime,
                           "user": usage.ru_utime, "sys": usage.ru_stime, "wall": wall,
                           "status": proc.returncode,
                           "stderr_tail": stderr[-2000:], "load": os.getloadavg()}
    if report is not None:
        try:
            rec = json.loads(Path(report).read_text() or "{}")
        finally:
            os.unlink(report)
        if rec:
            iv = exclusive_times(rec["events"])
            rows = per_function(iv, rec["dispatchers"])
            top_compile = [i for i in iv if i["kind"] == "compile" and i["depth"] == 0]
            out.update(functions=rows,
                       compile_cpu=sum(i["cpu"] for i in top_compile),
                       load_cpu=sum(i["cpu"] for i in iv if i["kind"] == "load" and i["hit"]),
                       miss_cpu=sum(i["cpu"] for i in iv if i["kind"] == "load" and not i["hit"]),
                       llvm_cpu=sum(i["cpu"] for i in iv
                                    if i["kind"] == "llvm" and i["parent"] is None
                                    or i["kind"] == "llvm" and i["parent"][0] == "compile"),
                       signatures_compiled=sum(1 for i in iv if i["kind"] == "compile"),
                       signatures_loaded=sum(1 for i in iv if i["kind"] == "load" and i["hit"]),
                       child_process_cpu=rec["process_cpu"])
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: run the default demo runs (or ``--cmd`` ones) on one empty cache."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == [CHILD]:
        _child(args[1], args[2:])
    p = argparse.ArgumentParser(prog="python -m benchmarks.compile_time",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--cmd", action="append", metavar="COMMAND",
                   help="command to run (repeatable, in order, on one cache; default: the "
                   "ClothSlide, SliderCrank, warm ClothSlide demos)")
    p.add_argument("--keep-cache", metavar="DIR",
                   help="use DIR as NUMBA_CACHE_DIR (must be empty or absent) and keep it")
    p.add_argument("--top", type=int, default=15, help="functions listed per run (default 15)")
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    a = p.parse_args(args)
    runs = ([(c, c, None) for c in a.cmd] if a.cmd else list(DEFAULT_RUNS))
    cache = a.keep_cache or tempfile.mkdtemp(prefix="numba-cache-")
    if a.keep_cache:
        Path(cache).mkdir(parents=True, exist_ok=True)
        if any(Path(cache).iterdir()):
            p.error(f"--keep-cache: {cache} is not empty")
    results = []
    try:
        for label, cmd, target in runs:
            r = run_one(cmd, cache)
            r.update(label=label, target_cpu=target)
            results.append(r)
            if not a.json:
                _print_run(r, a.top)
    finally:
        if not a.keep_cache:
            shutil.rmtree(cache, ignore_errors=True)
    if a.json:
        print(json.dumps({"python": sys.version.split()[0], "cpus": os.cpu_count(),
                          "runs": results}, indent=1))
    return 0 if all(r["status"] == 0 for r in results) else 1


def _print_run(r: dict[str, Any], top: int) -> None:
    target = "" if r["target_cpu"] is None else f"  (target <= {r['target_cpu']:g} s)"
    print(f"\n== {r['label']}\n   {r['command']}")
    print(f"   CPU {r['cpu']:.1f} s (user {r['user']:.1f}, sys {r['sys']:.1f}){target}, wall "
          f"{r['wall']:.1f} s, exit {r['status']}, load average "
          + " ".join(f"{x:.2f}" for x in r["load"]))
    if r["status"] != 0:
        tail = [line[:200] for line in r["stderr_tail"].strip().splitlines()[-5:]]
        print("   stderr (end): " + "\n   ".join(tail))
    if "functions" in r:
        print(f"   Numba: {r['compile_cpu']:.1f} s CPU compiling {r['signatures_compiled']} "
              f"signatures ({r['llvm_cpu']:.1f} s of it in LLVM), "
              f"{r['load_cpu']:.2f} s loading {r['signatures_loaded']} from cache, "
              f"{r['miss_cpu']:.2f} s looking up entries the cache did not have")
        print("   " + format_table(r["functions"], top).replace("\n", "\n   "))


if __name__ == "__main__":
    sys.exit(main())
