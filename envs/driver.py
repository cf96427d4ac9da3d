"""The prepared env step: an env step's physics and measures with what they were checked
against remembered, so that a step of an unchanged task pays for its compiled calls and a few
identity tests instead of every layer between the env and its kernels.

A :class:`StepPlan` is made for a task when the env is built and holds what does not change
from step to step: the integrator's compiled code, the schedule of substeps, the success
test's and the rest test's records. It takes the env step's physics and measures (after the
task's :meth:`~envs.base.ParticleTask.apply`) where the general path would take the same
compiled calls: the task's :meth:`~envs.base.ParticleTask.simulate` is the base class's
(decided once, when the plan is made), the physics is fused calls (split steps included; on
several threads the ranges through ``fused.run``; no projection) and every check of those
calls holds. A task whose :meth:`~envs.base.ParticleTask.measure_observe` is the base class's
is measured by the plan; one with its own compiled measures (SliderCrank, ClothPin) is
handed the step's checked post. Anywhere else the plan answers None with nothing changed and
the general path takes the step, so both give the same bits: the plan calls the same
compiled functions with the same arguments (``tests/test_driver.py`` ties them step by step,
single and vector envs, every task and mode).

What keeps it safe is what keeps the general path safe: the state arrays are checked at every
step as :meth:`ParticleSystem.step <constrained_particles.system.ParticleSystem.step>` checks
them (``fused.prepare``, under the system's step lock), and every array the measures read
without bounds checks is either made by this step (the new state, the outputs) or tested at
every step (the goal, hold and moving-average arrays). A remembered record is reused only
while every attribute it was made from is the very object it was made from (an attribute
reassigned makes it anew, through the task's own method)."""

from __future__ import annotations

import math
import operator
from typing import Any

import numpy as np

from constrained_particles import fused
from constrained_particles.packing import Packed
from constrained_particles.system import ParticleSystem

from . import _measure
from .base import ParticleTask, _measured
from .checks import _owned


class StepPlan:
    """The prepared step of ``task`` (see the module's docstring); :meth:`make` returns None
    for a task whose step it cannot take."""

    def __init__(self, task: ParticleTask) -> None:
        self.task = task
        #: ``((integrator, dt, substeps, system), (code, rattle), schedule)``: the physics
        #: arguments and what they were made from (one attribute, read and written whole)
        self._physics: tuple | None = None
        #: ``(key, record, (goal, rest))``: the success test's record, what it was made from,
        #: and it and the rest test's record as the kernels take them (plain tuples)
        self._records: tuple | None = None
        #: masks of the measures, the plan's own (never handed out): every copy stepped, none
        #: blocked
        self._stepped = np.ones(task.num_envs, bool)
        self._blocked = np.zeros(task.num_envs, bool)
        #: whether :meth:`measure_observe` measures the task (see :meth:`make`)
        self.measured = False

    @staticmethod
    def make(task: ParticleTask) -> StepPlan | None:
        """A plan for ``task``, or None if its physics is not the base class's
        :meth:`~envs.base.ParticleTask.simulate` (a task that redefines it takes the general
        path) or the compiled bookkeeping is off. Decided once: the methods are looked up on
        the class. A task whose :meth:`~envs.base.ParticleTask.measure_observe` is the base
        class's is measured by the plan (:meth:`measure_observe`); one with its own is
        handed the step's pack, as :meth:`~envs.base.ParticleTask.simulate_step` hands it."""
        cls = type(task)
        if not (_measure.ENABLED and fused.kernels.ENABLED
                and cls.simulate is ParticleTask.simulate and task._paths.get("fresh_pack")):
            return None
        plan = StepPlan(task)
        plan.measured = bool(cls.measure_observe is ParticleTask.measure_observe
                             and task._paths.get("measure_observe") and task._paths.get("goal"))
        return plan

    # ------------------------------------------------------------------ physics
    def _physics_args(self, s: ParticleSystem) -> tuple | None:
        """The integrator's ``(method, (code, rattle), schedule)`` for the task's substeps,
        remade only when the integrator, ``dt``, ``substeps`` or the system was reassigned;
        None where the general path must step (a value it would refuse or convert, or a
        method the fused kernel does not take)."""
        task = self.task
        method, dt, substeps = task.integrator, task.dt, task.substeps
        made = self._physics
        if (made is not None and method is made[0][0] and dt is made[0][1]
                and substeps is made[0][2] and s is made[0][3]):
            return method, made[1], made[2]
        if not (type(dt) is float and math.isfinite(dt) and dt > 0.0 and type(substeps) is int
                and 1 <= substeps <= 10**9 and isinstance(method, str)
                and method in fused.METHOD_CODES and method != "rattle"):
            return None
        made = ((method, dt, substeps, s), fused.integrator_args(method),
                fused.schedule(substeps, dt))
        self._physics = made
        return method, made[1], made[2]

    def physics(self) -> tuple[Packed, np.ndarray, np.ndarray, np.ndarray] | None:
        """Take the env step's physics (``substeps`` steps of the task's integrator) on the
        fused kernel, as :meth:`ParticleTask.simulate_step` would: returns ``(pack, x, v,
        mass)``, the pack the call was made with, the new state and the masses it was
        checked with (the arguments of :meth:`measure_observe`), or None with nothing
        changed (a divergence included: the general path then takes the step, and finds the
        same divergence). ValueError for an invalid state, RuntimeError if another thread is
        stepping the system, as a step raises them."""
        task = self.task
        s = task.system
        args = self._physics_args(s)
        if args is None or s.project_each_step or not s._fusable(args[0]):
            return None
        method, (code, rattle), schedule = args
        lock = s._step_lock()  # (taken as step takes it)
        pieces = None
        if task.step_travel != math.inf:  # (as simulate decides them, before the lock)
            _, rows, largest = task._decide(s)
            if largest != 1:
                pieces = rows
        if not lock.acquire(blocking=False):  # (another thread is stepping the system: the
            with s.stepping():  # RuntimeError a step raises; if that thread has just
                return None  # finished, the general path takes the step)
        try:
            state = s.x, s.v, s.mass, s.inv_mass, s.t
            t = state[4]
            if not (type(t) is float and math.isfinite(t)):
                return None  # (the general path's error, or its conversion)
            solver = s.constraint_solver
            lam = solver.lam
            if s.__dict__.get("_threads", 1) != 1:  # (the ranges on their threads, as a
                return self._ranges(s, solver, method, schedule, state, pieces)  # step does)
            # (every state array checked in full: the general path raises for a bad one)
            ready = fused.prepare(s, lam, s.residual_limit, state[:4])
            if ready is None:
                return None
            p, start, settings = ready
            x_out, v_out = np.empty(state[0].shape), np.empty(state[1].shape)  # (C float64,
            # as the state arrays prepare checked)
            kept = lam.copy()
            steps, h = schedule[:2]
            if pieces is None:
                status, _ = fused.fused_steps(code, rattle, *p.variant, schedule,
                                              tuple(start), (x_out, v_out), tuple(settings),
                                              p.refs.engine, None)
            elif pieces.shape == (p.n,) and pieces.dtype == np.int64:
                # (each particle's steps split into its own pieces, as step_pieces takes them)
                status, _ = fused.fused_split(code, rattle, *p.variant,
                                              (h, h / pieces, pieces * steps), tuple(start),
                                              (x_out, v_out), tuple(settings), p.refs.engine,
                                              p.live_ref)
            else:
                return None
            if status != fused.OK:
                solver.lam = kept
                return None
            return _advanced(s, p, x_out, v_out, state, steps, h)
        finally:
            lock.release()

    def _ranges(self, s: ParticleSystem, solver: Any, method: str, schedule: tuple,
                state: tuple, pieces: np.ndarray | None
                ) -> tuple[Packed, np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`physics` of a system stepped on several threads (its lock held): the
        ranges through ``fused.run``, which checks and cuts them as a step does."""
        lam = solver.lam
        kept = lam.copy()
        steps, h = schedule[:2]
        status, x_out, v_out, _ = fused.run(s, h, method, steps, lam, s.residual_limit,
                                            pieces, state[:4])
        p = s.__dict__.pop("_fresh_pack", None)
        if status != fused.OK or p is None:
            solver.lam = kept
            return None
        return _advanced(s, p, x_out, v_out, state, steps, h)

    # ------------------------------------------------------------------ measures
    def _goal_record(self) -> tuple | None:
        """``(record, (goal, rest))``: the success test's record and the success and rest
        tests' records as the kernels take them, remade (by the task's own ``_goal_record``)
        only when an attribute they are made from was reassigned; None where the general path
        must measure. The arrays the kernel writes or reads by copy index are tested at every
        call."""
        task = self.task
        N = task.num_envs
        goal, hold, mean_v = task.goal, task.hold, task.mean_v
        if not (_owned(goal, np.float64, (N,)) and _owned(hold, np.int64, (N,))
                and _owned(mean_v, np.float64, (N * task.n, 2))):
            return None
        track = task._tracking()
        key = (goal, hold, mean_v, track, task.goal_tolerance, task.rest_speed,
               task.hold_steps, task.goal_height, task.planar_goal, task.wall_rest,
               task.rest_count, task._alpha)
        made = self._records
        if made is not None and all(map(operator.is_, key, made[0])):  # (keys of one length)
            return made[1:]
        record = None if track is None else task._goal_record(track)
        if record is None:
            return None
        made = (key, record, (tuple(record), tuple(task._rest())))
        self._records = made
        return made[1:]

    def hand(self, p: Packed, x: np.ndarray, v: np.ndarray, mass: np.ndarray) -> tuple | None:
        """Hand the step :meth:`physics` took (its return values as arguments) to the task's
        own compiled measures, as :meth:`ParticleTask.simulate_step` hands them the step's
        pack: the whole post ``_compiled_post`` would make (the pack, the success record
        checked now, the state), or the pack alone where the success record does not hold.
        Returns :meth:`_goal_record`'s records in the first case, else None. The task takes
        what is handed once; the caller drops what is left."""
        task = self.task
        records = self._goal_record()
        if records is not None and p.n == task.num_envs * task.n:
            task.__dict__["_fresh_pack"] = (p, records[0], (x, v, mass))
            return records
        task.__dict__["_fresh_pack"] = p
        return None

    def measure_observe(self, p: Packed, x: np.ndarray, v: np.ndarray, mass: np.ndarray
                        ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """:meth:`ParticleTask.measure_observe` after :meth:`physics` took the step (every
        copy stepped; its return values as arguments: ``x``, ``v`` the arrays it made,
        ``mass`` the one it checked): the same compiled call with the same arguments where
        the plan measures the task (:meth:`make`) and what it reads holds, else the task's
        own, handed the step as :meth:`hand` hands it."""
        task = self.task  # (with threads, the task's measures run on the ranges)
        try:
            records = self.hand(p, x, v, mass)
            if records is not None and self.measured and task.system.threads == 1:
                return self._measure(records[1], x, v, mass, p)
            return task.measure_observe(np.ones(task.num_envs, bool))
        finally:
            task.__dict__.pop("_fresh_pack", None)  # (taken once, or not at all)

    def _measure(self, plain: tuple, x: np.ndarray, v: np.ndarray, mass: np.ndarray,
                 p: Packed) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The base class's compiled measures and observation (see :meth:`measure_observe`),
        with ``plain``, the records :meth:`_goal_record` checked for this step."""
        task = self.task
        N, n = task.num_envs, task.n
        out, success = np.empty((5, N)), np.empty(N, bool)
        obs = np.empty((N, 4 * n + 1), np.float32)
        goal, rest = plain
        _measure.measures_observe((x, v, mass), goal, p.refs.blocks, task.measure_walls, rest,
                                  self._stepped, self._blocked, out, success,
                                  tuple(task._view()), obs)
        return task.add_measures(_measured(out, success), out[4]), obs


def _advanced(s: ParticleSystem, p: Packed, x: np.ndarray, v: np.ndarray, state: tuple,
              steps: int, h: float) -> tuple[Packed, np.ndarray, np.ndarray, np.ndarray]:
    """Put the stepped state into ``s`` (``t`` advanced ``steps`` times by ``h``, as a step
    adds them) and return what :meth:`StepPlan.physics` returns."""
    t = state[4]
    for _ in range(steps):
        t = t + h
    s.x, s.v, s.t = x, v, t
    return p, x, v, state[2]
