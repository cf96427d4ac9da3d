"""Stepping the independent parts of one system on several threads.

A system whose particles fall into groups that no force element or constraint couples (the
tiled copies of a batched environment, say) can take its compiled steps on
``ParticleSystem.threads`` threads: its particles are cut into that many consecutive ranges,
each cut between two groups, and each range is stepped by the fused kernel on a thread of its
own, reading and writing only its own slices of the state. The kernels release the GIL, so the
ranges run in parallel; the Python before and after the kernels runs once per step, as with
one thread.

**Same bits for every thread count.** A group of coupled particles is stepped exactly as it
would be alone (each constraint component is solved on its own, each particle's update reads
only its own group), so which range a group falls in, and which thread steps it, changes no
bit: a step with k threads returns the state and warm start of a step with one.

**What is cut.** :func:`cuts` finds where the particles can be cut (no element has particles on
both sides), and the range nearest each share of ``n / k`` particles ends there. A range's
blocks are views of the system's blocks (the elements of that range, with particle indices
shifted to the range's start), packed on their own (:class:`~.packing.Packed`): parameter
arrays are shared, so in-place edits (an environment's actions written into
``ConstantForce.force``) reach every range, and a reassigned attribute rebuilds the system's
pack and with it the ranges. Mouse springs, whose particles move between calls, are shared
out in proportion (one per copy of a tiled scene), and each call checks that every active one
pulls a particle of its own range. Where no cut fits (one big group, elements not ordered range
by range, a mouse spring on another range's particle) or the system is too small to gain
(fewer than :data:`MIN_PARTICLES` particles a range), the step runs whole on one thread.

**Threads or one, by timing.** A partition's :class:`Gauge` times the steps (the period of
the loop that calls them) with the threads and, now and then, with the ranges run one after the
other on the calling thread, and keeps the faster: on cores busy with other work, a step whose
threads wait for each other at its end runs slower than on one thread.

The threads are a :class:`Crew`: k - 1 daemon threads that wait for their next call spinning
on a flag without the GIL for about :data:`WAIT_SECONDS` (2 ms) and then sleep on an event, the
calling thread taking the first range. They start on the first threaded step, stop with
``ParticleSystem.close_threads()`` (or when the system is dropped) and start again in a
forked child.
"""

from __future__ import annotations

import copy
import functools
import math
import numbers
import os
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from . import kernels
from .forces import MouseSpring
from .packing import Packed
from .terms import Term, frozen

if TYPE_CHECKING:
    from .system import ParticleSystem

#: what a call run on a range returns
T = TypeVar("T")

__all__ = ["CLOSE_SECONDS", "MIN_PARTICLES", "POLL_SECONDS", "SETTLED", "WAIT_SECONDS", "Crew",
           "Gauge", "Partition", "cuts", "wait_spins"]

#: Fewest particles a range must have for a step to be cut into ranges at all: below it, handing
#: the ranges to threads costs more than it saves.
MIN_PARTICLES = 64
#: How long (s) a crew thread waits for its next call, spinning without the GIL, before it
#: sleeps on an event: waking a sleeping thread costs this class of VM 50-150 us, a spin about
#: nothing; a training loop whose policy takes a millisecond between steps steps again within
#: it, an idle system costs no CPU after it. The wait is counted in looks at a flag, as many as
#: last this long on the machine (:func:`wait_spins`).
WAIT_SECONDS = 0.002
POLL_SECONDS = 0.002  #: the same wait where the compiled code is off (polling with the GIL)
#: Looks timed (per run, fastest of :data:`_CALIBRATION_RUNS`) to find how long one lasts
_CALIBRATION_SPINS = 50_000
_CALIBRATION_RUNS = 5
#: Longest wait (s) of :meth:`Crew.close` for a run in progress, and for each thread to end.
CLOSE_SECONDS = 5.0
#: Calls a :class:`Gauge` times in the other way (threads or one thread) when it tries it, and
#: the calls of the current way it compares them with (medians).
GAUGE_PROBE = 5
#: Calls between a :class:`Gauge`'s tries of the other way: the first, after each change of
#: way; doubled after each try that keeps the way, up to the last.
GAUGE_INTERVALS = (20, 2000)
#: How much faster (time ratio) the other way must be for a :class:`Gauge` to take it.
GAUGE_MARGIN = 0.95
#: Longest time (s) from one run of a partition's ranges to the next that its gauge counts.
GAUGE_GAP = 1.0
#: Calls a partition must serve before a new pack of the system is cut again at once: a system
#: whose blocks change at nearly every call (a spring drawn at every step) steps a new pack
#: whole, and cuts it only at its second call (cutting costs more than one step gains).
SETTLED = 2


def _wait_for(flags: np.ndarray, i: int, value: int, spins: int) -> bool:
    """True once ``flags[i] >= value``; False if it is not so after ``spins`` looks (numpy
    path: polling for :data:`POLL_SECONDS`, yielding the GIL between looks)."""
    start = time.perf_counter()
    while flags[i] < value:
        if time.perf_counter() - start > POLL_SECONDS:
            return False
        time.sleep(0)
    return True


if kernels.ENABLED:
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    from .jit import njit

    @intrinsic
    def _load_acquire(typingctx, flags, i):  # pragma: no cover - compiled
        """``flags[i]`` read with an atomic load (acquire): a loop of them is never folded
        into one read, and sees what the writer stored before its flag."""
        if not (isinstance(flags, types.Array) and flags.dtype == types.int64
                and flags.ndim == 1):
            return None
        sig = types.int64(flags, types.intp)

        def codegen(context, builder, sig, args):
            ary = context.make_array(sig.args[0])(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, sig.args[0], ary, [args[1]],
                                           wraparound=False)
            return builder.load_atomic(ptr, ordering="acquire", align=8)

        return sig, codegen

    @njit(nogil=True)
    def _wait_for(flags, i, value, spins):  # noqa: F811  # pragma: no cover - compiled
        """True once ``flags[i] >= value``, looked at up to ``spins`` times without the GIL
        (False at once for an ``i`` outside ``flags``: the atomic load reads unchecked)."""
        if not 0 <= i < flags.shape[0]:
            return False
        for _ in range(spins):
            if _load_acquire(flags, i) >= value:
                return True
        return False


def wait_spins(seconds: float = WAIT_SECONDS) -> int:
    """How many looks at a flag of the crew's compiled wait last about ``seconds`` (s) on this
    machine: measured once per process (the fastest of a few timed runs of
    :data:`_CALIBRATION_SPINS` looks at a flag that never flips, about 15 us each; a look
    costs some 0.27 ns on this class of machine, where a fixed count of 1.5e6 once stood for
    2 ms and lasted 0.4 ms). At least 1. ValueError unless ``seconds`` is a finite number
    >= 0."""
    if not (isinstance(seconds, numbers.Real) and not isinstance(seconds, bool)
            and math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"seconds must be a finite number >= 0, got {seconds!r}")
    if not kernels.ENABLED:  # (the polling wait counts seconds, not looks)
        return 1
    return max(1, int(seconds / _seconds_per_look()))


@functools.cache
def _seconds_per_look() -> float:
    """How long (s) one look of the compiled :func:`_wait_for` lasts here (measured once per
    process, see :func:`wait_spins`)."""
    never = np.zeros(1, np.int64)
    _wait_for(never, 0, 1, 1)  # (compiled or loaded before it is timed)
    best = math.inf
    for _ in range(_CALIBRATION_RUNS):
        start = time.perf_counter()
        _wait_for(never, 0, 1, _CALIBRATION_SPINS)
        best = min(best, time.perf_counter() - start)
    return max(best, 1e-9) / _CALIBRATION_SPINS


class Crew:
    """``k`` daemon threads that each run one call per :meth:`run`, the calling thread running
    another.

    Handing a call over and waiting for its end use a counter per thread (calls posted, calls
    done), looked at in a compiled loop that holds no GIL (:func:`_wait_for`): the calling
    thread's Python runs undisturbed while a crew thread waits, and a call starts within about
    a microsecond of being handed over (a thread woken from an event would take 50-150 us on
    this class of VM). A crew thread that has waited about :data:`WAIT_SECONDS` (as
    :func:`wait_spins` looks) sleeps on an event until the next call.

    A crew serves one caller at a time: :meth:`run` while another thread is in it raises
    RuntimeError (so does a call that reaches :meth:`run` again from inside one). A run left
    by an exception (an interrupt while it waits, say) leaves nothing behind that the next
    run could mistake for its own: the waits compare counters, and the next run hands a
    thread its call only once the thread has done every call posted before. :meth:`close`
    waits up to :data:`CLOSE_SECONDS` for a run in progress; a crew closed while one runs
    stops when it ends."""

    _STOP = object()

    def __init__(self, k: int, name: str) -> None:
        self._spins = wait_spins()  # (looks lasting WAIT_SECONDS)
        self._calls: list[Any] = [None] * k
        self._results: list[tuple[bool, Any] | None] = [None] * k
        self._posted = np.zeros(k, np.int64)  # the number of calls handed to thread i
        self._done = np.zeros(k, np.int64)  # the number of calls thread i has finished
        self._sleeping = [False] * k
        self._wake = [threading.Event() for _ in range(k)]
        self._lock = threading.Lock()  # held by the caller of run()
        self._owner: int | None = None  # that caller's thread id, while it is in run()
        self._closed = False
        #: held to post calls, and by a thread deciding to end because the crew is closed: a
        #: run never posts to a thread that has ended, nor a thread ends with a call posted
        self._post_lock = threading.Lock()
        #: the process whose threads these are (a forked child has none of them)
        self.pid = os.getpid()
        self._threads: list[threading.Thread] = []
        try:
            for i in range(k):
                t = threading.Thread(target=self._serve, args=(i,), daemon=True,
                                     name=f"{name}-{i + 1}")
                t.start()
                self._threads.append(t)
        except BaseException:  # (threads that started are stopped, not leaked)
            self._stop()
            raise

    @property
    def size(self) -> int:
        """The number of crew threads (calls a run can hand over besides its own)."""
        return len(self._calls)

    @property
    def live(self) -> bool:
        """True while the crew can run calls: not closed, and in the process that made it."""
        return not self._closed and self.pid == os.getpid()

    def _serve(self, i: int) -> None:
        posted, done, wake, spins = self._posted, self._done, self._wake[i], self._spins
        seq = 0
        while True:
            if not _wait_for(posted, i, seq + 1, spins):
                self._sleeping[i] = True  # (then looked at again: run() may have posted
                while posted[i] <= seq:  # before it saw this flag)
                    wake.wait()
                    wake.clear()
                self._sleeping[i] = False
            seq += 1  # (nothing is posted to this thread before it has done the call before)
            call = self._calls[i]
            self._calls[i] = None
            if call is self._STOP:
                done[i] = seq
                return
            try:
                result = (True, call())
            except BaseException as exc:  # handed to the caller of run()
                result = (False, exc)
            self._results[i] = result
            call = result = None  # (nothing of a finished call is kept alive here)
            done[i] = seq
            if self._closed:  # (closed while this call ran: _stop may not have posted the
                with self._post_lock:  # stop call, to leave the call before it undisturbed)
                    if posted[i] == seq:
                        return

    def run(self, first: Callable[[], T], others: list[Callable[[], T]]) -> list[T]:
        """``first()`` on this thread and ``others[i]()`` on thread i; every result once all
        have returned, raising the first error (this thread's first). RuntimeError if another
        caller is in a run or the crew is stopped; ValueError for more calls than threads."""
        if len(others) > self.size:
            raise ValueError(f"others must hold at most {self.size} calls (one per crew "
                             f"thread), got {len(others)}")
        if not self._lock.acquire(blocking=False):
            raise RuntimeError("this crew's threads serve one caller at a time (another run "
                               "is in progress)")
        try:
            self._owner = threading.get_ident()
            if not self.live:
                raise RuntimeError("this crew is stopped (close() was called, or it belongs "
                                   "to another process)")
            return self._run(first, others)
        finally:
            try:
                if self._closed:  # (closed while running: stopped now that the run is over)
                    self._stop()
            finally:
                self._owner = None
                self._lock.release()

    def _run(self, first: Callable[[], T], others: list[Callable[[], T]]) -> list[T]:
        posted, done = self._posted, self._done
        targets = []
        for i in range(len(others)):
            # a call of a run left by an exception may still be running (or not yet taken):
            # a slot is written only once its thread has done every call posted before
            while not _wait_for(done, i, int(posted[i]), self._spins):
                pass
        with self._post_lock:
            if self._closed:  # (closed meanwhile: a thread may have ended)
                raise RuntimeError("this crew is stopped (close() was called)")
            for i, call in enumerate(others):
                self._calls[i] = call
                posted[i] += 1
                targets.append(int(posted[i]))
                if self._sleeping[i]:
                    self._wake[i].set()
        try:
            mine = first()
        finally:
            for i, target in enumerate(targets):  # no call is still running when this returns
                while not _wait_for(done, i, target, self._spins):
                    pass
        out = [mine]
        errors = []
        for i in range(len(others)):
            ok, value = self._results[i]  # type: ignore[misc]
            self._results[i] = None
            (out if ok else errors).append(value)
        if errors:
            raise errors[0]
        return out

    def close(self) -> None:
        """Stop the threads (safe to call twice; nothing to stop in a forked child). Waits up
        to :data:`CLOSE_SECONDS` for a run in progress on another thread; if it is still
        running then (or this is called from inside a run), the threads stop when it ends."""
        if self.pid != os.getpid():
            return
        self._closed = True
        here = threading.current_thread()
        inside = (self._owner == threading.get_ident()  # (from inside a run: no wait)
                  or any(t is here for t in self._threads))
        if not (self._lock.acquire(blocking=False) if inside
                else self._lock.acquire(timeout=CLOSE_SECONDS)):
            return  # (run() stops the threads as it returns)
        try:
            self._stop()
        finally:
            self._lock.release()

    def _stop(self) -> None:
        """Hand every idle live thread the stop call and join them (the run lock held, or no
        run possible). A thread still busy with a call of a run left by an exception (or the
        thread calling this) is not handed it: it ends by itself when its call returns, as
        :attr:`_closed` is set first."""
        self._closed = True
        here = threading.current_thread()
        deadline = time.monotonic() + CLOSE_SECONDS
        for i, t in enumerate(self._threads):
            if t is here or not t.is_alive() or self._calls[i] is self._STOP:
                continue
            while not _wait_for(self._done, i, int(self._posted[i]), self._spins):
                if time.monotonic() > deadline:
                    break
            else:  # (idle: nothing posted is left undone, so the slot is free)
                self._calls[i] = self._STOP
                self._posted[i] += 1
                self._wake[i].set()
        for t in self._threads:
            if t is not here:
                t.join(max(0.0, deadline - time.monotonic()))


def _spans(blocks: Sequence[Term]) -> tuple[np.ndarray, np.ndarray] | None:
    """The lowest and highest particle of every element that couples particles (an element
    with two or more index fields), or None if a block refers to all particles implicitly
    with more than one field (nothing such exists today) or its index arrays are not one
    dimensional arrays of one length."""
    lows, highs = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for b in blocks:
        if len(b.index_fields) < 2 or not len(b):
            continue
        idx = [b.__dict__.get(name) for name in b.index_fields]
        if any(i is None or np.ndim(i) != 1 or len(i) != len(idx[0]) for i in idx):
            return None  # (an index array reshaped in place, say: the step runs whole)
        stacked = np.stack([np.asarray(i, np.int64) for i in idx])
        lows.append(stacked.min(axis=0))
        highs.append(stacked.max(axis=0))
    return np.concatenate(lows), np.concatenate(highs)


def cuts(blocks: Sequence[Term], n: int, k: int) -> list[int]:
    """Where ``n`` particles with elements ``blocks`` are cut into at most ``k`` ranges: the
    inner boundaries, increasing, each the allowed cut nearest its share ``i n / k`` (a cut
    at ``c`` is allowed when no element has particles both below ``c`` and at or above it).
    Empty when no cut is allowed."""
    spans = _spans(blocks)
    if spans is None or k < 2 or n < 2:
        return []
    low, high = spans
    cover = np.zeros(n + 1, np.int64)  # cover[c] > 0: some element spans the cut at c
    np.add.at(cover, low + 1, 1)
    np.add.at(cover, high + 1, -1)
    allowed = np.flatnonzero(np.cumsum(cover)[1:n] == 0) + 1  # cuts in [1, n - 1]
    if not len(allowed):
        return []
    out: list[int] = []
    for i in range(1, k):
        target = i * n / k
        j = int(np.searchsorted(allowed, target))
        near = [allowed[t] for t in (j - 1, j) if 0 <= t < len(allowed)]
        c = int(min(near, key=lambda a: (abs(a - target), a)))
        if not out or c > out[-1]:  # (allowed cuts lie in [1, n - 1])
            out.append(c)
    return out


class _Part:
    """The particle count and blocks of one range: what :class:`~.packing.Packed` reads of a
    system."""

    def __init__(self, n: int, forces: list[Any], constraints: list[Any], solver: str) -> None:
        self.n = n
        self.forces = forces
        self.constraints = constraints
        self.solver = solver


def _element_ranges(block: Any, bounds: np.ndarray) -> np.ndarray | None:
    """For each range ``[bounds[r], bounds[r + 1])``, the first and end element of ``block``
    in it (``(ranges + 1,)`` element offsets), or None where the block's elements are not
    ordered by range. A block without particle lists (all particles) has None here too; its
    caller keeps it whole."""
    idx = block.__dict__.get(block.index_fields[0]) if block.index_fields else None
    if idx is None or np.ndim(idx) != 1:
        return None
    rid = np.searchsorted(bounds, np.asarray(idx, np.int64), side="right") - 1
    if len(rid) and np.any(np.diff(rid) < 0):
        return None
    return np.searchsorted(rid, np.arange(len(bounds)), side="left")


def _mouse_ranges(count: int, bounds: np.ndarray) -> np.ndarray | None:
    """The element offsets per range of a mouse block of ``count`` springs: its particles move
    between calls, so its elements are shared out in proportion to the ranges' particles
    (spring ``e`` of ``count`` to the range of particle ``e n / count``: one spring per copy of
    a tiled system, say), or None where the proportion is not whole. Each call checks that
    every active spring's particle is in its range (:meth:`Partition.take_mouse`)."""
    n = int(bounds[-1])
    scaled = count * bounds
    if np.any(scaled % n):
        return None
    return scaled // n


def _sub_block(block: Any, a: int, b: int, lo: int) -> Any:
    """Elements ``a:b`` of ``block`` as a block of its own, particle indices less ``lo``:
    per-element arrays as views and every other attribute shared (in-place edits of the
    system's block are seen)."""
    sub = copy.copy(block)
    d = sub.__dict__
    for name in block.index_fields:
        idx = block.__dict__.get(name)
        if idx is not None:
            d[name] = frozen(np.asarray(idx[a:b], np.int64) - lo)
    for name in block.element_fields:
        arr = block.__dict__.get(name)
        if arr is not None:
            d[name] = arr[a:b]
    return sub


class Gauge:
    """Whether a partition's ranges run on the crew's threads or one after the other on the
    calling thread (the same calls, so the same bits), chosen by timing both.

    Threads gain only while the cores are free: with every core busy with other work (two
    spinning processes on two cores, say), a step whose ranges wait for each other at its end
    waits for whichever thread the scheduler left out, and two threads ran at about half the
    speed of one on the 2-core VM of docs/performance.md. So a gauge times every call (seconds
    per step), starts with the threads, and every so often runs :data:`GAUGE_PROBE` calls the
    other way; it takes that way when their median time is below :data:`GAUGE_MARGIN` of the
    median of the last :data:`GAUGE_PROBE` calls of the current way. The calls between tries
    start at ``GAUGE_INTERVALS[0]`` and double after each try that keeps the way, up to
    ``GAUGE_INTERVALS[1]`` (a try of the slower way costs at most 5 calls in 2,000 once the
    machine is steady). A call's time is the period of the loop that steps the system
    (:meth:`Partition.run`)."""

    def __init__(self) -> None:
        #: the current way: True, the crew's threads; False, the calling thread alone
        self.threaded = True
        #: calls of the current way since the last try, and the calls until the next
        self.count, self.interval = 0, GAUGE_INTERVALS[0]
        self._recent: list[float] = []  # the last GAUGE_PROBE calls' times, current way
        self._probe: list[float] | None = None  # the times of a try in progress
        #: the changes of way so far
        self.changes = 0

    def use_threads(self) -> bool:
        """How the next call runs: the current way, or the other during a try."""
        return self.threaded if self._probe is None else not self.threaded

    def record(self, seconds: float) -> None:
        """The time (s per step) of the last call, run the way :meth:`use_threads` said."""
        if self._probe is not None:
            self._probe.append(seconds)
            if len(self._probe) < GAUGE_PROBE:
                return
            other, mine = sorted(self._probe)[GAUGE_PROBE // 2], sorted(self._recent)[
                GAUGE_PROBE // 2]
            self._probe, self.count = None, 0
            if other < GAUGE_MARGIN * mine:
                self.threaded = not self.threaded
                self.interval, self._recent = GAUGE_INTERVALS[0], []
                self.changes += 1
            else:
                self.interval = min(2 * self.interval, GAUGE_INTERVALS[1])
            return
        self._recent = [*self._recent[1 - GAUGE_PROBE:], seconds]
        self.count += 1
        if self.count >= self.interval and len(self._recent) == GAUGE_PROBE:
            self._probe = []


class Partition:
    """A system's particles cut into ranges stepped on threads (see the module docstring),
    made for one :class:`~.packing.Packed` form of the system; :attr:`valid` False where no
    cut fits."""

    def __init__(self, parent: Packed, k: int, previous: Partition | None = None) -> None:
        """``previous``: the system's last partition, whose constraint blocks per range (and
        so each range's constraint rows and components, :class:`~.packing.Packed`) are taken
        over when the ranges and the system's constraint blocks are the same and unchanged."""
        self.parent = parent
        self.k = k
        self.valid = False
        #: the steps (calls) this partition has served
        self.calls = 0
        #: threads or one thread, by timing (:class:`Gauge`); taken over by the next partition
        self.gauge = Gauge()
        self._last: tuple[float, int] | None = None  # the last run's start (s) and steps
        # the crew, in a box the finalizer shares: a crew handed on to the next partition
        # (take_crew) is not stopped when this one is dropped
        self._box: list[Crew | None] = [None]
        weakref.finalize(self, _close_box, self._box)
        #: each range's blocks of each constraint block of ``parent``, in order
        self._constraint_parts: list[list[Any]] = []
        #: the mouse springs' element offsets per range, if the system has a mouse block (see
        #: :meth:`take_mouse`)
        self.mouse_elements: np.ndarray | None = None
        n = parent.n
        blocks = [*parent.forces, *parent.constraints]
        mice = [b for b in parent.forces if type(b) is MouseSpring]
        if k < 2 or not parent.valid or not parent.zero_copy or len(mice) > 1:
            return
        inner = cuts(blocks, n, min(k, n // MIN_PARTICLES))
        if not inner:
            return
        bounds = np.array([0, *inner, n], np.int64)
        ranges = len(bounds) - 1
        spans = tuple((int(bounds[r]), int(bounds[r + 1])) for r in range(ranges))
        same = (previous is not None and previous.valid and previous.spans == spans
                and len(previous.parent.constraints) == len(parent.constraints)
                and all(a is b for a, b in zip(previous.parent.constraints, parent.constraints,
                                               strict=True))
                and previous.parent.constraint_versions == parent.constraint_versions)
        forces: list[list[Any]] = [[] for _ in range(ranges)]
        constraints: list[list[Any]] = [[] for _ in range(ranges)]
        row_range = np.empty(parent.m, np.int64)  # the range of each constraint row
        offset = 0
        nf = len(parent.forces)
        for b_no, block in enumerate(blocks):
            is_constraint = b_no >= nf
            if block.index_fields and block.__dict__.get(block.index_fields[0]) is None:
                if len(block.index_fields) > 1 or is_constraint:
                    return  # (no such block exists; kept whole it would span the ranges)
                parts = [copy.copy(block) for _ in range(ranges)]  # (all of each range's)
            else:
                el = (_mouse_ranges(len(block), bounds) if type(block) is MouseSpring
                      else _element_ranges(block, bounds))
                if el is None:
                    return
                if type(block) is MouseSpring:
                    self.mouse_elements = el
                if is_constraint and same:  # (the same objects: the ranges' packs then
                    parts = previous._constraint_parts[b_no - nf]  # keep their row graphs)
                else:
                    parts = [_sub_block(block, int(el[r]), int(el[r + 1]), int(bounds[r]))
                             for r in range(ranges)]
                if is_constraint:
                    per = block.rows_per_element
                    for r in range(ranges):
                        row_range[offset + per * el[r]:offset + per * el[r + 1]] = r
            for r in range(ranges):
                (constraints if is_constraint else forces)[r].append(parts[r])
            if is_constraint:
                offset += block.n_rows
                self._constraint_parts.append(parts)
        #: each range's first and end particle, as ints
        self.spans = spans
        #: each range's packed blocks
        self.packs = tuple(Packed(_Part(hi - lo, forces[r], constraints[r], parent.solver),
                                  previous.packs[r] if same else None)
                           for r, (lo, hi) in enumerate(self.spans))
        #: the system's constraint rows of each range, in the system's order (which is the
        #: range's own: blocks in order, elements in order within a block)
        self.rows = tuple(np.flatnonzero(row_range == r) for r in range(ranges))
        self.valid = (offset == parent.m and all(p.valid and p.zero_copy for p in self.packs)
                      and all(len(rows) == p.m for rows, p in zip(self.rows, self.packs,
                                                                     strict=True)))

    def take_mouse(self) -> bool:
        """Copy the system's mouse springs (the particles and ``active`` flags its pack just
        took, :meth:`~.packing.Packed.take_mouse`) into each range's, particle indices less the
        range's start (an inactive spring's index as 0). False, with nothing changed, if an
        active spring's particle is outside its range: the step then runs whole."""
        el = self.mouse_elements
        if el is None:
            return True
        refs = self.parent.refs
        particle, active = refs.mouse_particle, refs.mouse_active
        for r, (lo, hi) in enumerate(self.spans):
            a, b = int(el[r]), int(el[r + 1])
            p, on = particle[a:b], active[a:b]
            if np.any(on & ((p < lo) | (p >= hi))):
                return False
        for r, (sp, (lo, _)) in enumerate(zip(self.packs, self.spans, strict=True)):
            a, b = int(el[r]), int(el[r + 1])
            mine = sp.refs
            np.copyto(mine.mouse_active, active[a:b])
            np.copyto(mine.mouse_particle, np.where(active[a:b], particle[a:b] - lo, 0))
        return True

    def crew(self) -> Crew:
        """The threads that step every range but the first (started on first use, and again
        in a process forked from this one, which has none of them; stopped when the partition
        is dropped)."""
        crew = self._box[0]
        if crew is None or not crew.live:
            self._box[0] = crew = Crew(len(self.packs) - 1, "cparticles-range")
        return crew

    def take_crew(self, other: Partition) -> None:
        """Take over ``other``'s threads if they are live and as many as this partition needs
        (a system whose blocks changed keeps its threads); ``other`` is left without."""
        crew = other._box[0]
        if (self.valid and self._box[0] is None and crew is not None and crew.live
                and crew.size == len(self.packs) - 1):
            self._box[0], other._box[0] = crew, None
        self.gauge = other.gauge  # (what the timing found holds for the same machine)

    def run(self, calls: list[Callable[[], T]], steps: int = 1) -> list[T]:
        """Run ``calls[r]()`` for every range r, on the ranges' threads or one after the other
        on this thread, as :attr:`gauge` says (``steps``: the steps the calls take); every
        result, raising the first error. What the gauge is given is the time from one run's
        start to the next's, per step: the whole period of a stepping loop, so that what the
        threads cost outside the calls (a crew thread spinning on a busy core while the
        caller's Python runs) counts too; a period over :data:`GAUGE_GAP` s (a loop that
        paused) is not counted."""
        now = time.perf_counter()
        last = self._last
        if last is not None and now - last[0] <= GAUGE_GAP:
            self.gauge.record((now - last[0]) / last[1])
        self._last = (now, max(int(steps), 1))
        return self._dispatch(calls)

    def _dispatch(self, calls: list[Callable[[], T]]) -> list[T]:
        """``calls`` on the crew's threads, or one after the other on this thread while
        :attr:`gauge` has the steps run there."""
        if self.gauge.use_threads():
            return self.crew().run(calls[0], list(calls[1:]))
        return [call() for call in calls]

    def map(self, calls: list[Callable[[], T]]) -> list[T]:
        """Run ``calls[r]()`` for every range r, each on the thread that steps the range (the
        first on the calling thread; all on it while :attr:`gauge` has the steps run there);
        every result once all have returned, raising the first error. For per-range work after
        a step (an environment's measures of the copies in each range): the calls must touch
        only their own range's data."""
        if len(calls) != len(self.packs):
            raise ValueError(f"calls must hold one call per range ({len(self.packs)}), "
                             f"got {len(calls)}")
        return self._dispatch(calls)

    def close(self) -> None:
        """Stop the threads (safe to call twice)."""
        _close_box(self._box)


def _close_box(box: list[Crew | None]) -> None:
    """Stop the crew in ``box``, if any, and empty it."""
    crew, box[0] = box[0], None
    if crew is not None:
        crew.close()


def partition(system: ParticleSystem, parent: Packed, k: int) -> Partition | None:
    """The system's :class:`Partition` into ``k`` ranges for its pack ``parent`` (made once
    per pack and thread count, kept on the system), or None where the step runs whole: no cut
    fits, or the system's blocks change at nearly every call (the partition before served
    fewer than :data:`SETTLED` calls: the new pack is stepped whole once, and cut if it serves
    a second call). A new partition keeps the threads, and where the constraints and ranges
    are unchanged the row graphs, of the one before."""
    d = system.__dict__
    held = d.get("_partition")
    if held is None or held.parent is not parent or held.k != k:
        if held is not None and held.k != k:
            held.close()
            held = None
        if held is not None and held.calls < SETTLED and d.get("_whole_for") is not parent:
            d["_whole_for"] = parent
            return None
        new = Partition(parent, k, held)
        if held is not None:
            new.take_crew(held)
            held.close()
        d["_partition"] = held = new
        d.pop("_whole_for", None)
    held.calls += 1
    return held if held.valid else None
