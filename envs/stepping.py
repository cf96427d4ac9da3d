"""How a task steps its copies: each physics step split into pieces where particles move fast,
copies that need different splits kept apart, and copies that diverge parked so that they cannot
drag the others down. A mixin of :class:`envs.base.ParticleTask`, which it shares its attributes
with (``system``, ``single``, ``n``, ``num_envs``, ``dt``, ``substeps``, ``integrator``,
``step_travel``, ``actuator``, ``park``)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import numpy as np

from constrained_particles import ConstantForce, ParticleSystem, kernels
from constrained_particles.forces import MouseSpring
from constrained_particles.system import SimulationDiverged

from .checks import _owned

#: Most pieces one physics step is split into when particles move fast (see
#: :meth:`SteppedCopies.pieces`); a copy that would need more is left to the divergence check.
MAX_PIECES = 64
_NO_ROWS = np.zeros(0, np.int64)  # group_pieces: the forces are given per particle


def _mouse_forces(act: object, x: np.ndarray, v: np.ndarray, F: np.ndarray) -> bool:
    """A mouse-spring actuator's forces (N) added into the zeros of ``F`` by the compiled
    kernel (``kernels.mouse_forces``, the bits of ``MouseSpring.accumulate``): True; False,
    with nothing written, where ``accumulate`` must (another actuator, arrays not of the
    kernel's types, or a particle index it does not accept)."""
    if kernels.mouse_forces is None or not isinstance(act, MouseSpring):
        return False
    p, anchor, ks, kd, on = act.particle, act.anchor, act.ks, act.kd, act.active
    k, n = len(p), len(x)
    return bool(_owned(p, np.int64, (k,)) and _owned(anchor, np.float64, (k, 2))
                and _owned(ks, np.float64, (k,)) and _owned(kd, np.float64, (k,))
                and _owned(on, np.bool_, (k,)) and _owned(x, np.float64, (n, 2))
                and _owned(v, np.float64, (n, 2)) and _owned(F, np.float64, (n, 2))
                and kernels.mouse_forces(x, v, p, anchor, ks, kd, on, F))


class SteppedCopies:
    """The physics of a task's ``num_envs`` tiled copies (mixed into
    :class:`envs.base.ParticleTask`)."""

    # (attributes of the task this mixin reads; set by ParticleTask)
    system: ParticleSystem
    single: ParticleSystem
    n: int
    num_envs: int
    dt: float
    substeps: int
    integrator: str
    step_travel: float
    actuator: ConstantForce | MouseSpring
    park: np.ndarray

    def pieces(self, system: ParticleSystem | None = None) -> np.ndarray:
        """Into how many equal pieces each physics step of the next env step of each copy of
        ``system`` (default: all copies) is split, so that no particle travels more than
        :attr:`step_travel` metres per piece: an int array with one entry per copy, decided
        once per env step from the copy's own state (so a copy of a vector env decides as a
        single env would).

        A particle's speed over the env step is bounded by its speed at the end of it if the
        actuator alone accelerated it, ``|v| + |F_act| substeps dt / m``, and its reach per
        physics step by that times dt. A copy that would need more than :data:`MAX_PIECES` is
        beyond help and gets 1: the divergence check catches it.
        """
        return self._decide(self.system if system is None else system)[0].copy()

    def _decide(self, s: ParticleSystem) -> tuple[np.ndarray, np.ndarray, int]:
        """:meth:`pieces` for the tiled ``s``, with each particle's count (the array the kernel
        takes) and the largest count."""
        copies = s.n // self.n
        if self.step_travel == math.inf:
            return np.ones(copies, np.int64), np.ones(s.n, np.int64), 1
        s.check_arrays()  # (ValueError naming a replaced state array, as a step raises)
        act = s.forces[-1]
        horizon = self.substeps * self.dt
        # the compiled formula reads every particle of every copy without bounds checks: the
        # state it reads (each array read once) must be C-ordered float64 of copies * n rows
        v, inv_mass, total = s.v, s.inv_mass, copies * self.n
        compiled = (kernels.group_pieces is not None and s.n == total
                    and _owned(v, np.float64, (total, 2))
                    and _owned(inv_mass, np.float64, (total,)))
        if (compiled and s is self.system and copies == self.num_envs
                and isinstance(act, ConstantForce) and self._pushed is not None
                and act.particles is self._pushed[0]
                and _owned(act.force, np.float64, (len(act.particles), 2))):
            # the same formula, compiled, reading the actuator's rows through the row map
            # (into buffers reused from step to step: only this step's caller reads them)
            out, rows, frow = self._pushed[1:]
            largest = kernels.group_pieces(v, act.force, frow, inv_mass, self.n, horizon,
                                            self.dt, self.step_travel, MAX_PIECES, out, rows)
            return out, rows, largest
        x = s.x
        F = np.zeros_like(x)
        if not (compiled and _mouse_forces(act, x, v, F)):
            act.accumulate(s.x, s.v, s.mass, F)
        if compiled and _owned(F, np.float64, (total, 2)):  # the same formula, compiled
            out, rows = np.empty(copies, np.int64), np.empty(total, np.int64)
            largest = kernels.group_pieces(v, F, _NO_ROWS, inv_mass, self.n, horizon,
                                            self.dt, self.step_travel, MAX_PIECES, out, rows)
            return out, rows, largest
        with np.errstate(invalid="ignore", over="ignore"):
            speed = np.sqrt(np.sum(s.v * s.v, axis=1)) + np.sqrt(np.sum(F * F, axis=1)) * (
                s.inv_mass * horizon)
            need = np.ceil(speed.reshape(copies, self.n).max(axis=1) * self.dt
                           / self.step_travel)
            need = np.where((need >= 1) & (need <= MAX_PIECES), need, 1).astype(np.int64)
            return need, np.repeat(need, self.n), int(need.max(initial=1))

    def _physics_step(self, system: ParticleSystem, need: np.ndarray | None = None) -> None:
        """One physics step of ``dt`` for every copy of ``system``, each in its own number of
        pieces (``need``, default :meth:`pieces`); on SimulationDiverged the system is back in
        its state from before.

        Copies that need different counts are advanced in separate runs of the whole system,
        each copy keeping the run with its own count, so a copy's trajectory never depends on
        the others' (copy ``i`` of a vector env still reproduces a single env). In a run with
        fewer pieces than a copy needs, that copy waits parked at rest without actuation, so it
        cannot make the run diverge.
        """
        need = self.pieces(system) if need is None else need
        counts = np.unique(need)
        solver = system.constraint_solver
        x0, v0, t0, lam0 = system.x, system.v, system.t, solver.lam.copy()
        if len(counts) == 1 and counts[0] == 1:
            system.step(self.dt, self.integrator)
            return
        x, v, lam = x0.copy(), v0.copy(), lam0.copy()
        try:
            for k in counts:
                system.x, system.v, system.t, solver.lam = x0.copy(), v0.copy(), t0, lam0.copy()
                slower = need > k
                with self._parked(system, slower):
                    for _ in range(k):
                        system.step(self.dt / k, self.integrator)
                rows = np.repeat(need == k, self.n)
                x[rows], v[rows] = system.x[rows], system.v[rows]
                mine = (need == k)[self._row_env] if system is self.system else slice(None)
                lam[mine] = solver.lam[mine]
        except SimulationDiverged:
            system.x, system.v, system.t, solver.lam = x0, v0, t0, lam0
            raise
        system.x, system.v, system.t, solver.lam = x, v, t0 + self.dt, lam

    @contextlib.contextmanager
    def _parked(self, system: ParticleSystem, copies: np.ndarray) -> Iterator[None]:
        """Within the block, the masked ``copies`` of the tiled ``system`` rest in the scene's
        initial state without actuation; their actuation is restored afterwards."""
        if not copies.any():
            yield
            return
        act = self.actuator
        saved = act.force.copy() if isinstance(act, ConstantForce) else act.active.copy()
        rows = np.repeat(copies, self.n)
        system.x[rows] = np.tile(self.park, (self.num_envs, 1))[rows]
        system.v[rows] = 0.0
        self._actuate(np.flatnonzero(copies), None)
        try:
            yield
        finally:
            if isinstance(act, ConstantForce):
                act.force[:] = saved
            else:
                act.set(np.arange(len(saved)), active=saved)

    def simulate(self) -> np.ndarray:
        """Advance every copy by ``substeps`` physics steps; returns the (num_envs,) mask of copies
        whose simulation diverged (non-finite, beyond the divergence limit, or off a constraint
        by more than ``residual_limit``).

        A diverged copy ends the step in its state from before this call. For the remaining
        physics steps it is parked in the scene's initial state, at rest and without actuation,
        so that it cannot drag the other copies down; no NaN ever leaves this method.
        """
        s = self.system
        if self.step_travel == math.inf:
            need, rows, largest = self._one_piece, None, 1
        else:
            need, rows, largest = self._decide(s)
        # the usual case: every substep of every copy in one compiled call (bit for bit the same
        # as stepping them one by one; copies that need their steps split take their own pieces
        # in the same call); a divergence leaves the state as it was and the careful path below
        # finds the copy and parks it
        try:
            if largest == 1:
                s.step(self.dt, self.integrator, steps=self.substeps)
                return np.zeros(self.num_envs, bool)
            if s.step_pieces(self.dt, self.integrator, self.substeps, rows):
                return np.zeros(self.num_envs, bool)
        except SimulationDiverged:
            pass
        x0, v0 = s.x.copy(), s.v.copy()
        park = np.tile(self.park, (self.num_envs, 1))
        rest = np.zeros_like(v0)
        frozen = np.zeros(self.num_envs, bool)
        for _ in range(self.substeps):
            try:
                self._physics_step(s, need)
            except SimulationDiverged:
                bad = self._diverging()
                frozen |= bad if bad.any() else True
                self._put(frozen, park, rest)
                if not frozen.all():
                    try:
                        self._physics_step(s, need)
                    except SimulationDiverged:
                        frozen[:] = True
            if frozen.all():
                break
            if frozen.any():
                self._put(frozen, park, rest)
        if frozen.any():
            self._put(frozen, x0, v0)
        return frozen

    def simulate_step(self) -> np.ndarray:
        """:meth:`simulate`, as an env's step calls it: where :meth:`simulate` is the task
        class's own (it changes no block after its physics: ``_paths["fresh_pack"]``), the
        measures that follow (:meth:`~envs.base.ParticleTask.measure_observe`) take the
        system's compiled pack as the step's last compiled call checked and refreshed it,
        instead of checking and refreshing it again (:func:`envs._measure.packed`)."""
        s = self.system
        s.__dict__.pop("_fresh_pack", None)
        self.__dict__.pop("_fresh_pack", None)
        diverged = self.simulate()
        fresh = s.__dict__.pop("_fresh_pack", None)
        if fresh is not None and self._paths.get("fresh_pack"):
            self.__dict__["_fresh_pack"] = fresh
        return diverged

    def pass_time(self) -> None:
        """Advance the clock by one env step (``substeps`` steps of ``dt``, added as a step
        adds them) without stepping: for an env step in which every copy starts anew, whose
        physics would be overwritten by the starts."""
        t = self.system.t
        for _ in range(self.substeps):
            t = t + self.dt
        self.system.t = t

    def _put(self, copies: np.ndarray, x: np.ndarray, v: np.ndarray) -> None:
        """Set the masked ``copies`` to their rows of ``x``, ``v``; switch off their actuation."""
        rows = np.repeat(copies, self.n)
        self.system.x[rows] = x[rows]
        self.system.v[rows] = v[rows]
        self._actuate(np.flatnonzero(copies), None)

    def _diverging(self) -> np.ndarray:
        """Which copies diverge when stepped alone from the current state (one physics step)."""
        if self.num_envs == 1:
            return np.ones(1, bool)
        bad = np.zeros(self.num_envs, bool)
        for i in range(self.num_envs):
            self.load_single(i)
            try:
                self._physics_step(self.single)
            except SimulationDiverged:
                bad[i] = True
        return bad

    def load_single(self, i: int) -> ParticleSystem:
        """Copy ``i``'s state and actuation into :attr:`single` (for drawing or testing it)."""
        sl = self.copy_slice(i)
        one = self.single
        one.x, one.v, one.t = self.system.x[sl].copy(), self.system.v[sl].copy(), self.system.t
        act, mine = self.actuator, one.forces[-1]
        if isinstance(act, ConstantForce):
            mine.force[:] = act.force[i * self.rows_per_copy:(i + 1) * self.rows_per_copy]
        else:
            mine.set([0], [act.particle[i] - i * self.n], act.anchor[i], [act.active[i]])
        return one
