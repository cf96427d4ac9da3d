"""A system's compiled step on several threads (``ParticleSystem.threads``,
``constrained_particles.parallel``): the same bits as on one thread, for every method, split
steps and divergence; cut only where nothing couples the two sides; edits of the system seen.

The speed of it is measured by ``cparticles bench`` (section "threads"), not here.
"""

from __future__ import annotations

import copy
import pickle
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from constrained_particles import (
    DampedSpring,
    MouseSpring,
    ParticleSystem,
    SimulationDiverged,
    fused,
    kernels,
    parallel,
    scenes,
)

pytestmark = pytest.mark.skipif(not kernels.ENABLED, reason="threads step the compiled kernel")


@pytest.fixture(autouse=True)
def small_ranges(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ranges of any size: the systems here are small."""
    monkeypatch.setattr(parallel, "MIN_PARTICLES", 1)


def _cloths(copies: int = 6, threads: int = 1, nx: int = 4) -> ParticleSystem:
    s = scenes.cloth(nx, nx).tile(copies)
    rng = np.random.default_rng(3)
    s.v = rng.normal(0.0, 0.3, s.v.shape)  # (copies that differ)
    s.threads = threads
    return s


def _ranges(s: ParticleSystem) -> int:
    """The ranges the system's last step was cut into (1: stepped whole)."""
    part = s.thread_ranges()
    return 1 if part is None else len(part.packs)


@pytest.mark.parametrize("method", ["euler", "symplectic_euler", "midpoint", "rk4", "rattle"])
def test_every_method_gives_the_same_bits_on_threads(method: str) -> None:
    systems = [_cloths(threads=k) for k in (1, 2, 3)]
    for _ in range(20):
        for s in systems:
            s.step(2e-3, method, steps=3)
    assert [_ranges(s) for s in systems] == [1, 2, 3]
    for s in systems[1:]:
        np.testing.assert_array_equal(s.x, systems[0].x)
        np.testing.assert_array_equal(s.v, systems[0].v)
        np.testing.assert_array_equal(s.constraint_solver.lam, systems[0].constraint_solver.lam)
        assert s.t == systems[0].t


def test_split_steps_give_the_same_bits_on_threads() -> None:
    n = scenes.cloth(4, 4).n
    pieces = np.repeat(np.array([1, 3, 2, 5, 1, 4], np.int64), n)  # one count per copy
    one, two = _cloths(threads=1), _cloths(threads=2)
    for _ in range(10):
        assert one.step_pieces(2e-3, "rk4", 2, pieces)
        assert two.step_pieces(2e-3, "rk4", 2, pieces)
    assert _ranges(two) == 2
    np.testing.assert_array_equal(two.x, one.x)
    np.testing.assert_array_equal(two.v, one.v)
    np.testing.assert_array_equal(two.constraint_solver.lam, one.constraint_solver.lam)


def test_a_diverging_range_keeps_the_whole_state() -> None:
    """A copy in the second range blows up: the step raises as on one thread, and no range
    (not even the first, which stepped fine) keeps its new state or warm start."""
    systems = []
    for k in (1, 2):
        s = _cloths(threads=k)
        s.step(1e-3, "symplectic_euler")
        s.v[-1] = 1e9  # the last copy's last particle: beyond the divergence limit after a step
        systems.append(s)
    for s in systems:
        x, v, lam, t = s.x.copy(), s.v.copy(), s.constraint_solver.lam.copy(), s.t
        with pytest.raises(SimulationDiverged):
            s.step(1e-3, "symplectic_euler")
        np.testing.assert_array_equal(s.x, x)
        np.testing.assert_array_equal(s.v, v)
        np.testing.assert_array_equal(s.constraint_solver.lam, lam)
        assert s.t == t
    assert _ranges(systems[1]) == 2


def test_cuts_only_where_nothing_couples() -> None:
    s = ParticleSystem()
    s.add_particles(np.zeros((10, 2)))
    # particles 0-3 in a chain, 4-5 a pair, 6-9 a chain: cuts allowed at 4, 6
    s.add(DampedSpring([0, 1, 2, 4, 6, 7, 8], [1, 2, 3, 5, 7, 8, 9], rest=0.0))
    assert parallel.cuts(s.forces, s.n, 2) == [4]  # (5 is not allowed; 4 and 6 are as near)
    assert parallel.cuts(s.forces, s.n, 3) == [4, 6]
    s.add(DampedSpring([3], [6], rest=0.0))  # couples everything from 0 to 9
    assert parallel.cuts(s.forces, s.n, 2) == []


def test_one_piece_is_stepped_on_one_thread() -> None:
    """A single cloth cannot be cut: it steps whole, with the bits of one thread."""
    one, many = scenes.cloth(6, 6), scenes.cloth(6, 6)
    many.threads = 4
    for s in (one, many):
        for _ in range(5):
            s.step(1e-3, "rk4")
    assert _ranges(many) == 1
    np.testing.assert_array_equal(many.x, one.x)


def test_elements_out_of_order_are_stepped_whole() -> None:
    """A block whose elements do not run range by range (here: one spring per copy, listed
    from the last copy to the first) cannot be sliced: the step runs whole, still right."""
    systems = []
    for k in (1, 2):
        s = _cloths(threads=k)
        n = scenes.cloth(4, 4).n
        s.add(DampedSpring(np.arange(5, -1, -1) * n, np.arange(5, -1, -1) * n + 1, rest=0.05))
        systems.append(s)
    for s in systems:
        for _ in range(5):
            s.step(1e-3, "midpoint")
    assert _ranges(systems[1]) == 1
    np.testing.assert_array_equal(systems[1].x, systems[0].x)


def test_edits_of_the_system_reach_every_range() -> None:
    """An in-place edit of a parameter array is seen by the ranges (they hold views); a
    reassigned attribute cuts the system again."""
    systems = [_cloths(threads=k) for k in (1, 2)]
    for s in systems:
        s.step(1e-3, "symplectic_euler")
    first = systems[1]._partition
    for s in systems:
        spring = next(f for f in s.forces if isinstance(f, DampedSpring))
        spring.ks[::3] *= 4.0  # in place, in every range
        s.step(1e-3, "symplectic_euler")
    assert systems[1]._partition is first
    for s in systems:
        spring = next(f for f in s.forces if isinstance(f, DampedSpring))
        spring.kd = spring.kd * 0.5  # reassigned
        s.step(1e-3, "symplectic_euler")
    assert systems[1]._partition is not first and _ranges(systems[1]) == 2
    np.testing.assert_array_equal(systems[1].x, systems[0].x)
    np.testing.assert_array_equal(systems[1].v, systems[0].v)


def test_mouse_springs_follow_their_range() -> None:
    """One mouse spring per copy moves with the copy's range; a spring whose particle is in
    another copy's range makes the step run whole. Both give the bits of one thread."""
    n = scenes.cloth(4, 4).n
    systems = []
    for k in (1, 2):
        s = _cloths(threads=k)
        s.add(MouseSpring(np.zeros(6, np.int64), ks=30.0, kd=0.5))
        s.forces[-1].active[:] = False
        systems.append(s)
    for s in systems:
        s.forces[-1].set(np.arange(6), np.arange(6) * n + 5, np.full((6, 2), 0.3), True)
        for _ in range(3):
            s.step(1e-3, "symplectic_euler")
    calls = []
    real = fused._run_ranges
    try:
        fused._run_ranges = lambda *a: calls.append(1) or real(*a)
        for s in systems:
            s.forces[-1].set([0], [5 * n], active=True)  # copy 0's spring on copy 5's particle
            s.step(1e-3, "symplectic_euler")
    finally:
        fused._run_ranges = real
    assert not calls  # (the second system's step ran whole)
    np.testing.assert_array_equal(systems[1].x, systems[0].x)
    np.testing.assert_array_equal(systems[1].v, systems[0].v)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2", None, 10**6])
def test_bad_thread_count_is_a_clear_error(bad: object) -> None:
    s = scenes.cloth(2, 2)
    with pytest.raises((ValueError, TypeError), match="threads"):
        s.threads = bad
    assert s.threads == 1


def test_copies_of_a_threaded_system_have_threads_of_their_own() -> None:
    s = _cloths(threads=2)
    s.step(1e-3, "symplectic_euler")
    for twin in (copy.deepcopy(s), pickle.loads(pickle.dumps(s)), s.copy()):
        assert twin.threads == 2 and "_partition" not in twin.__dict__
        twin.step(1e-3, "symplectic_euler")
        assert twin._partition is not s._partition and _ranges(twin) == 2
    tiled = _cloths(copies=2, threads=2).tile(2)
    assert tiled.threads == 2 and "_partition" not in tiled.__dict__
    s.threads = 1  # fewer threads: the ranges and their threads go
    assert "_partition" not in s.__dict__


def test_an_error_on_a_crew_thread_reaches_the_caller() -> None:
    crew = parallel.Crew(2, "test")
    seen = []

    def failing() -> None:
        raise RuntimeError("thread 2 failed")

    with pytest.raises(RuntimeError, match="thread 2 failed"):
        crew.run(lambda: seen.append(threading.current_thread().name),
                 [lambda: 1, failing])
    assert seen == [threading.current_thread().name]
    assert crew.run(lambda: 0, [lambda: 1, lambda: 2]) == [0, 1, 2]  # the threads still serve
    threads = list(crew._threads)
    crew.close()
    crew.close()
    assert threads and not any(t.is_alive() for t in threads)


def test_a_system_that_can_no_longer_be_cut_steps_whole() -> None:
    """A spring added between the first and the last copy leaves nothing to cut; the system
    steps whole from then on (through later rebuilds of its pack), with the bits of one
    thread."""
    systems = [_cloths(threads=k) for k in (1, 2)]
    for s in systems:
        s.step(1e-3, "symplectic_euler")
    assert _ranges(systems[1]) == 2
    for s in systems:
        s.add(DampedSpring([0], [s.n - 1], rest=0.5, ks=1.0))
        s.step(1e-3, "symplectic_euler")
    assert _ranges(systems[1]) == 1
    for s in systems:
        s.forces[-1].ks = s.forces[-1].ks * 2.0  # (a rebuild: the uncut partition is replaced)
        s.step(1e-3, "symplectic_euler")
    assert _ranges(systems[1]) == 1
    np.testing.assert_array_equal(systems[1].x, systems[0].x)
    np.testing.assert_array_equal(systems[1].v, systems[0].v)


def test_a_forked_child_starts_threads_of_its_own() -> None:
    """Threads do not survive a fork: a child stepping a threaded system it inherited starts
    its own (instead of waiting for threads that are not there), with the parent's bits."""
    import multiprocessing

    s = _cloths(threads=2)
    s.step(1e-3, "symplectic_euler")
    expected = s.copy()
    expected.threads = 1
    expected.step(1e-3, "symplectic_euler")
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()

    def child() -> None:
        s.step(1e-3, "symplectic_euler")
        queue.put((s.x, _ranges(s)))

    p = ctx.Process(target=child)
    p.start()
    try:
        x, ranges = queue.get(timeout=60)
        p.join(timeout=60)
    finally:
        if p.is_alive():  # (a child waiting for threads it does not have)
            p.kill()
    assert p.exitcode == 0 and ranges == 2
    np.testing.assert_array_equal(x, expected.x)


def test_threads_cannot_be_changed_during_a_step() -> None:
    s = _cloths(threads=2)
    with s.stepping():  # (as another thread's step holds it)
        with pytest.raises(RuntimeError, match="another thread"):
            s.threads = 1
        with pytest.raises(RuntimeError, match="another thread"):
            s.close_threads()
    s.close_threads()
    s.threads = 3
    s.step(1e-3, "symplectic_euler")
    assert _ranges(s) == 3


def test_a_crew_serves_one_caller_at_a_time() -> None:
    """A second caller (another thread, or a call that reaches the crew again from inside a
    run) gets a clear error instead of taking the first caller's threads or results."""
    crew = parallel.Crew(1, "test")
    started, release = threading.Event(), threading.Event()
    errors: list[BaseException] = []

    def slow() -> int:
        started.set()
        release.wait(10)
        return 1

    def caller() -> None:
        try:
            crew.run(lambda: 0, [slow])
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=caller)
    t.start()
    try:
        assert started.wait(10)
        with pytest.raises(RuntimeError, match="one caller at a time"):
            crew.run(lambda: 0, [lambda: 1])
    finally:
        release.set()
        t.join(10)
    assert not errors
    with pytest.raises(RuntimeError, match="one caller at a time"):  # re-entered from a call
        crew.run(lambda: crew.run(lambda: 0, [lambda: 1]), [lambda: 1])
    assert crew.run(lambda: 0, [lambda: 2]) == [0, 2]  # (nothing left behind by either)
    with pytest.raises(ValueError, match="others"):
        crew.run(lambda: 0, [lambda: 1, lambda: 2])
    crew.close()


def _interrupt_the_first_runs_wait(monkeypatch: pytest.MonkeyPatch, crew: parallel.Crew
                                   ) -> None:
    """Make the calling thread's first run of ``crew`` raise KeyboardInterrupt in its wait for
    its calls' end (as Ctrl-C would), leaving its call to the crew thread."""
    main, real, looks = threading.current_thread(), parallel._wait_for, []

    def wait(flags: np.ndarray, i: int, value: int, spins: int) -> bool:
        if flags is crew._done and threading.current_thread() is main:
            looks.append(value)
            if len(looks) == 2:  # (the first look is the run's wait for an idle thread)
                raise KeyboardInterrupt
        return real(flags, i, value, spins)

    monkeypatch.setattr(parallel, "_wait_for", wait)


def test_a_run_after_an_interrupted_one_gets_its_own_result(monkeypatch) -> None:
    """A run left by an exception while a crew thread still holds its call (here: between
    taking it and clearing its slot, a window widened to 0.2 s) does not make the next run
    lose its call or take the old one's place."""
    crew = parallel.Crew(1, "test")
    ran: list[str] = []

    class SlowClear(list):
        def __setitem__(self, i: int, value: object) -> None:
            if value is None and threading.current_thread() is not main:
                threading.Event().wait(0.2)
            super().__setitem__(i, value)

    main = threading.current_thread()
    crew._calls = SlowClear(crew._calls)
    _interrupt_the_first_runs_wait(monkeypatch, crew)
    with pytest.raises(KeyboardInterrupt):
        crew.run(lambda: 0, [lambda: ran.append("old") or "old"])
    assert crew.run(lambda: 0, [lambda: ran.append("new") or "new"]) == [0, "new"]
    assert ran == ["old", "new"]
    crew.close()
    assert not any(t.is_alive() for t in crew._threads)


def test_closing_a_crew_while_a_run_waits_for_a_leftover_call_ends_both(monkeypatch) -> None:
    """A run that waits for a call left by an interrupted run, while the crew is closed from
    another thread: the run ends (with its result, or RuntimeError if the crew closed first)
    and so do the crew's threads; no run is handed to a thread that has ended."""
    monkeypatch.setattr(parallel, "CLOSE_SECONDS", 30.0)
    crew = parallel.Crew(1, "test")
    threads = list(crew._threads)
    release = threading.Event()
    _interrupt_the_first_runs_wait(monkeypatch, crew)
    with pytest.raises(KeyboardInterrupt):
        crew.run(lambda: 0, [lambda: release.wait(10)])  # (left running)
    outcome: list[object] = []

    def second() -> None:
        try:
            outcome.append(crew.run(lambda: 0, [lambda: "new"]))
        except RuntimeError as exc:
            outcome.append(exc)

    runner = threading.Thread(target=second)
    closer = threading.Thread(target=crew.close)
    runner.start()
    threading.Event().wait(0.1)  # (the second run waits for the leftover call)
    closer.start()
    threading.Event().wait(0.1)  # (close() has marked the crew closed and waits)
    release.set()
    runner.join(10)
    closer.join(10)
    assert not runner.is_alive() and not closer.is_alive()
    assert outcome == [[0, "new"]] or "stopped" in str(outcome[0])
    assert not any(th.is_alive() for th in threads)


def test_closing_a_crew_waits_for_its_run_and_a_closed_crew_refuses(monkeypatch) -> None:
    crew = parallel.Crew(2, "test")
    started = threading.Event()
    results: list[object] = []
    finished: list[int] = []

    def slow() -> str:
        started.set()
        threading.Event().wait(0.3)
        finished.append(1)
        return "finished"

    t = threading.Thread(target=lambda: results.append(crew.run(lambda: 0, [slow, slow])))
    t.start()
    assert started.wait(10)
    threads = list(crew._threads)
    crew.close()  # (while the run is in progress: it returns once the run has ended)
    assert finished == [1, 1]
    t.join(10)
    assert results == [[0, "finished", "finished"]]
    assert not any(th.is_alive() for th in threads)
    with pytest.raises(RuntimeError, match="stopped"):
        crew.run(lambda: 0, [lambda: 1])
    # closed from inside its own run: no wait for the run (it would wait for itself), and
    # the threads stop as the run ends
    monkeypatch.setattr(parallel, "CLOSE_SECONDS", 60.0)
    crew = parallel.Crew(1, "test")
    threads = list(crew._threads)
    closer = threading.Thread(target=lambda: results.append(
        crew.run(lambda: crew.close(), [lambda: 1])))
    closer.start()
    closer.join(10)
    assert not closer.is_alive() and results[-1] == [None, 1]
    assert not any(th.is_alive() for th in threads)


def test_a_crew_keeps_nothing_of_a_finished_call() -> None:
    """A call's arguments and result are not kept alive by the crew after the run."""
    import gc
    import weakref

    class Big:
        pass

    crew = parallel.Crew(1, "test")
    arg, result = Big(), []
    refs = [weakref.ref(arg)]

    def call(a: Big = arg) -> Big:
        out = Big()
        refs.append(weakref.ref(out))
        return out

    result = crew.run(lambda: 0, [call])
    del arg, call, result
    gc.collect()
    assert [r() for r in refs] == [None, None]
    crew.close()


def test_a_partition_made_again_keeps_its_threads_and_row_graphs() -> None:
    """A force attribute reassigned: the system is cut again, on the same threads, and each
    range keeps its constraint rows (the constraints did not change)."""
    s = scenes.cloth(4, 4).tile(4)
    s.threads = 2
    for _ in range(2):
        s.step(1e-3, "symplectic_euler")
    first = s.thread_ranges()
    assert first is not None and first.packs[0].m > 0
    crew = first.crew()
    spring = next(f for f in s.forces if isinstance(f, DampedSpring))
    spring.kd = spring.kd * 0.5
    s.step(1e-3, "symplectic_euler")
    again = s.thread_ranges()
    assert again is not None and again is not first
    assert again.crew() is crew and crew.live
    assert all(a.rows is b.rows for a, b in zip(again.packs, first.packs, strict=True))


def test_blocks_reassigned_at_every_step_are_stepped_whole(monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    """A system whose pack changes at every step (a spring drawn at every step, say) is not
    cut again at every step (cutting costs more than the step gains): it steps whole, with the
    bits of one thread, and is cut again once its blocks hold still."""
    made = []

    class Counted(parallel.Partition):
        def __init__(self, *args: object) -> None:
            made.append(1)
            super().__init__(*args)

    monkeypatch.setattr(parallel, "Partition", Counted)
    systems = [_cloths(threads=k) for k in (1, 2)]
    for step in range(8):
        for s in systems:
            spring = next(f for f in s.forces if isinstance(f, DampedSpring))
            spring.kd = spring.kd * (1.0 + 0.01 * step)  # reassigned: a new pack
            s.step(1e-3, "symplectic_euler")
    assert len(made) == 1 and _ranges(systems[1]) == 1
    for _ in range(3):
        for s in systems:
            s.step(1e-3, "symplectic_euler")
    assert len(made) == 2 and _ranges(systems[1]) == 2
    np.testing.assert_array_equal(systems[1].x, systems[0].x)
    np.testing.assert_array_equal(systems[1].v, systems[0].v)


@pytest.mark.parametrize(("results", "expected"), [
    ([(fused.OK, 3), (fused.DIVERGED, 2), (fused.FALLBACK, 1)], (fused.FALLBACK, 0)),
    ([(fused.DIVERGED, 1), (fused.FALLBACK, 2), (fused.OK, 3)], (fused.DIVERGED, 1)),
    ([(fused.FALLBACK, 2), (fused.DIVERGED, 2), (fused.DIVERGED, 3)], (fused.FALLBACK, 0)),
])
def test_the_range_that_fails_first_decides(monkeypatch: pytest.MonkeyPatch,
                                            results: list, expected: tuple) -> None:
    """As one call over the whole system stops at its first failing step, the ranges' result
    is that of the range that failed first (a fallback where one falls back at the step
    another diverges at: the reference path then finds the divergence)."""
    s = _cloths(threads=3)
    s.step(1e-3, "symplectic_euler")
    assert _ranges(s) == 3
    monkeypatch.setattr(parallel.Crew, "run", lambda self, first, others: list(results))
    status, x, v, step = fused.run(s, 1e-3, "symplectic_euler", 3, s.constraint_solver.lam,
                                   1e-3)
    assert (status, step) == expected and x is None and v is None


def test_a_crew_thread_waits_about_wait_seconds_before_it_sleeps() -> None:
    """The spinning wait lasts at least about the time asked for (a fixed count of looks once
    stood for 2 ms and lasted 0.4 ms on this class of machine). A lower bound: a busy machine
    makes the wait longer, not shorter."""
    never = np.zeros(1, np.int64)
    spins = parallel.wait_spins(0.004)
    assert parallel.wait_spins(0.002) in (spins // 2, spins // 2 + 1)
    start = time.perf_counter()
    assert not parallel._wait_for(never, 0, 1, spins)
    assert time.perf_counter() - start >= 0.002
    crew = parallel.Crew(1, "test")
    assert crew._spins == parallel.wait_spins()
    crew.close()


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "2 ms", True])
def test_a_bad_wait_is_a_clear_error(bad: object) -> None:
    with pytest.raises(ValueError, match="seconds"):
        parallel.wait_spins(bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------ threads or one, by timing
def _feed(gauge: parallel.Gauge, threads: float, one: float, calls: int) -> list[bool]:
    """Give ``gauge`` ``calls`` calls timed ``threads`` s (run on the threads) or ``one`` s
    (run on one thread); the ways it chose, call by call."""
    ways = []
    for _ in range(calls):
        way = gauge.use_threads()
        ways.append(way)
        gauge.record(threads if way else one)
    return ways


def test_a_gauge_keeps_the_threads_while_they_are_faster_and_tries_less_often() -> None:
    g = parallel.Gauge()
    first, longest = parallel.GAUGE_INTERVALS
    ways = _feed(g, 1.0, 1.7, 40_000)
    assert g.threaded and g.changes == 0 and g.interval == longest
    tries = ways.count(False)
    # each try is GAUGE_PROBE calls; the gaps between them double from the first to the longest
    assert tries % parallel.GAUGE_PROBE == 0
    assert ways[:first] == [True] * first and not any(ways[first:first + parallel.GAUGE_PROBE])
    assert tries < 40_000 * 0.01


def test_a_gauge_turns_to_one_thread_when_the_threads_get_slower_and_back() -> None:
    g = parallel.Gauge()
    _feed(g, 1.0, 1.7, 200)  # idle cores: threads
    assert g.threaded
    busy = _feed(g, 2.0, 1.0, 5_000)  # every core busy: two threads take twice one's time
    assert not g.threaded and g.changes == 1
    assert busy[-1000:].count(True) <= 2 * parallel.GAUGE_PROBE  # (only its tries)
    _feed(g, 1.0, 1.7, 5_000)  # free again
    assert g.threaded and g.changes == 2


def test_a_gauge_ignores_differences_within_its_margin() -> None:
    g = parallel.Gauge()
    _feed(g, 1.0, 0.97, 10_000)  # one thread 3% faster: not enough to change
    assert g.threaded and g.changes == 0


def test_ranges_run_on_one_thread_give_the_same_bits() -> None:
    """A gauge that has the ranges run one after the other on the calling thread changes no
    bit (the same calls), nor do its tries of the threads in between (whether a try then
    turns the gauge back to the threads depends on this machine's timing, so the test
    counts the calls each way instead of asserting the gauge's final way)."""
    one, two = _cloths(threads=1), _cloths(threads=2)
    ways: list[bool] = []
    for i in range(60):
        one.step(2e-3, "rk4", steps=2)
        two.step(2e-3, "rk4", steps=2)
        if i == 5:
            part = two.thread_ranges()
            assert part is not None and part.gauge.threaded
            gauge = part.gauge
            gauge.threaded = False

            def logged(asked: Callable[[], bool] = gauge.use_threads) -> bool:
                ways.append(asked())
                return ways[-1]

            gauge.use_threads = logged  # type: ignore[method-assign]
    assert _ranges(two) == 2 and two.thread_ranges().gauge is gauge
    # the calls up to the gauge's first try (GAUGE_INTERVALS[0] of the current way) ran
    # on the calling thread alone
    assert ways[:parallel.GAUGE_INTERVALS[0] - 8] == [False] * (parallel.GAUGE_INTERVALS[0] - 8)
    np.testing.assert_array_equal(two.x, one.x)
    np.testing.assert_array_equal(two.v, one.v)


def test_a_paused_loop_is_not_timed() -> None:
    s = _cloths(threads=2)
    s.step(2e-3, "symplectic_euler")
    s.step(2e-3, "symplectic_euler")
    part = s.thread_ranges()
    counted = part.gauge.count
    s.step(2e-3, "symplectic_euler")
    assert part.gauge.count == counted + 1
    part._last = (time.perf_counter() - 2 * parallel.GAUGE_GAP, 1)
    s.step(2e-3, "symplectic_euler")
    assert part.gauge.count == counted + 1
