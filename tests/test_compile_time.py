"""The pure helpers of benchmarks/compile_time.py: nesting arithmetic, signature comparison,
per-function rows and the table. Nothing here compiles or times anything; the event times are
made up so that each expected figure follows by hand."""

from __future__ import annotations

import pytest

from benchmarks.compile_time import (
    exclusive_times,
    format_table,
    per_function,
    signature_variants,
)


def ev(status: str, cpu: float, **data: object) -> dict[str, object]:
    return {"status": status, "cpu": cpu, "wall": 2 * cpu, **data}


def test_exclusive_time_subtracts_direct_children_only() -> None:
    # outer [0, 10] holds mid [1, 7], which holds inner [2, 5]; then a sibling [8, 9]
    events = [ev("start", 0, name="outer"), ev("start", 1, name="mid"),
              ev("start", 2, name="inner"), ev("end", 5), ev("end", 7),
              ev("start", 8, name="sib"), ev("end", 9, hit=True), ev("end", 10)]
    got = {r["name"]: r for r in exclusive_times(events)}
    assert [r["name"] for r in exclusive_times(events)] == ["inner", "mid", "sib", "outer"]
    assert got["inner"]["cpu"] == 3 and got["inner"]["cpu_self"] == 3
    assert got["mid"]["cpu"] == 6 and got["mid"]["cpu_self"] == 3
    assert got["outer"]["cpu"] == 10 and got["outer"]["cpu_self"] == 10 - 6 - 1
    assert got["outer"]["wall_self"] == 2 * (10 - 6 - 1)
    assert got["sib"]["hit"] is True  # keys of the end record are kept
    assert [got[n]["depth"] for n in ("outer", "mid", "inner", "sib")] == [0, 1, 2, 1]


@pytest.mark.parametrize("events", [[ev("end", 1)], [ev("start", 0, name="a")]])
def test_unbalanced_events_are_refused(events: list[dict[str, object]]) -> None:
    with pytest.raises(ValueError, match="events"):
        exclusive_times(events)


def test_signature_variants_names_the_differing_positions() -> None:
    c, ro = "array(int64, 1d, C)", "readonly array(int64, 1d, C)"
    sigs = [["int64", c, "float64"], ["int64", ro, "float64"], ["int64", c, "float64"]]
    assert signature_variants(sigs) == {1: sorted([c, ro])}
    assert signature_variants([["int64"]]) == {}
    assert signature_variants([]) == {}
    assert signature_variants([["a"], ["a", "b"]]) == {1: ["<absent>", "b"]}


def test_per_function_charges_compiles_and_hits_and_sorts_by_cost() -> None:
    intervals = [
        {"kind": "compile", "name": "g", "cpu": 2.0, "cpu_self": 2.0, "wall_self": 2.5,
         "depth": 1},
        {"kind": "compile", "name": "f", "cpu": 5.0, "cpu_self": 3.0, "wall_self": 3.0,
         "depth": 0},
        {"kind": "load", "name": "h", "cpu": 0.4, "cpu_self": 0.4, "depth": 0, "hit": True},
        {"kind": "load", "name": "f", "cpu": 0.1, "cpu_self": 0.1, "depth": 0, "hit": False},
    ]
    disp = [{"name": "f", "signatures": [["int64"], ["float64"]], "compiled": 2, "loaded": 0,
             "inline": False}]
    rows = per_function(intervals, disp)
    assert [r["name"] for r in rows] == ["f", "g", "h"]
    f, g, h = rows
    assert (f["compile_cpu"], f["compile_cpu_incl"], f["miss_cpu"]) == (3.0, 5.0, 0.1)
    assert (g["compile_cpu"], g["compile_cpu_incl"]) == (2.0, 0.0)  # nested: not a top compile
    assert (h["load_cpu"], h["loads"], h["compiles"]) == (0.4, 1, 0)
    assert f["variants"] == {0: ["float64", "int64"]}
    table = format_table(rows)
    assert "arg 0: float64 | int64" in table
    assert len(table.splitlines()) == 2 + 3


def test_table_leaves_out_inline_functions_and_shortens_names() -> None:
    rows = per_function([], [
        {"name": "m.inlined", "signatures": [], "compiled": 0, "loaded": 0, "inline": True},
        {"name": "m." + "x" * 80, "signatures": [["int64"]], "compiled": 1, "loaded": 0,
         "inline": False}])
    lines = format_table(rows).splitlines()
    assert len(lines) == 3
    assert "inlined" not in lines[2] and lines[2].startswith("...")


def test_llvm_time_stays_in_its_compile_and_is_shown_apart() -> None:
    # compile f [0, 10] holds llvm [1, 4] and compile g [5, 9], which holds llvm [6, 8];
    # a load of h [10, 12] holds llvm [10.5, 11.5]; llvm [13, 14] is outside everything
    events = [ev("start", 0, kind="compile", name="f"), ev("start", 1, kind="llvm", name="llvm"),
              ev("end", 4), ev("start", 5, kind="compile", name="g"),
              ev("start", 6, kind="llvm", name="llvm"), ev("end", 8), ev("end", 9), ev("end", 10),
              ev("start", 10, kind="load", name="h"), ev("start", 10.5, kind="llvm", name="llvm"),
              ev("end", 11.5), ev("end", 12, hit=True),
              ev("start", 13, kind="llvm", name="llvm"), ev("end", 14)]
    rows = {r["name"]: r for r in per_function(exclusive_times(events), [])}
    assert (rows["f"]["compile_cpu"], rows["f"]["llvm_cpu"]) == (10 - 4, 3)
    assert rows["f"]["compile_cpu_incl"] == 10
    assert (rows["g"]["compile_cpu"], rows["g"]["llvm_cpu"]) == (4, 2)
    assert (rows["g"]["compiled_from"], rows["f"]["compiled_from"]) == (["f"], [])
    assert (rows["h"]["load_cpu"], rows["h"]["llvm_cpu"]) == (2, 0)
    assert rows["(LLVM outside compiles)"]["compile_cpu"] == 1
