"""The prepared env step (:mod:`envs.driver`) against the general path: a single env steps
through its plan where it can, and gives the same observations, rewards, ends, infos and
states, bit for bit, as the same env with no plan; where a check fails it leaves the step to
the general path with nothing changed."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs import _measure
from envs.driver import StepPlan
from envs.pick_place import PickPlaceTask

pytestmark = pytest.mark.skipif(not _measure.ENABLED,
                                reason="the compiled paths are off (CPARTICLES_NUMBA=0)")

CASES = [(spec.id, kwargs) for spec in envs.task_specs() for kwargs in spec.cases
         if not issubclass(spec.env.task_class, PickPlaceTask)]
IDS = [f"{env_id}-{'-'.join(map(str, kwargs.values()))}" for env_id, kwargs in CASES]


def _pair(env_id: str, kwargs: dict) -> tuple[gym.Env, gym.Env]:
    """Two envs made alike and reset with one seed: the first with its plan, the second
    without (the general path)."""
    planned, plain = (gym.make(env_id, max_episode_steps=40, **kwargs) for _ in range(2))
    assert planned.unwrapped._plan is not None
    plain.unwrapped._plan = None
    for env in (planned, plain):
        env.reset(seed=7)
    return planned, plain


def _same(a: tuple, b: tuple) -> None:
    obs, reward, terminated, truncated, info = a
    obs2, reward2, terminated2, truncated2, info2 = b
    assert np.asarray(obs).tobytes() == np.asarray(obs2).tobytes()
    assert (reward, terminated, truncated) == (reward2, terminated2, truncated2)
    assert sorted(info) == sorted(info2)
    for k in info:
        assert np.asarray(info[k]).tobytes() == np.asarray(info2[k]).tobytes(), k


def _states_equal(e1: gym.Env, e2: gym.Env) -> None:
    s1, s2 = e1.unwrapped.task.system, e2.unwrapped.task.system
    assert s1.x.tobytes() == s2.x.tobytes() and s1.v.tobytes() == s2.v.tobytes()
    assert s1.t == s2.t
    assert s1.constraint_solver.lam.tobytes() == s2.constraint_solver.lam.tobytes()


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_the_prepared_step_gives_the_general_paths_bits(env_id, kwargs, monkeypatch):
    taken = []
    physics = StepPlan.physics

    def counted(self):
        done = physics(self)
        taken.append(done is not None)
        return done

    monkeypatch.setattr(StepPlan, "physics", counted)
    planned, plain = _pair(env_id, kwargs)
    rng = np.random.default_rng(1)
    space = planned.action_space
    for _ in range(120):
        a = rng.uniform(space.low, space.high).astype(space.dtype)
        out = planned.step(a)
        _same(out, plain.step(a))
        _states_equal(planned, plain)
        if out[2] or out[3]:
            (o1, i1), (o2, i2) = planned.reset(), plain.reset()
            _same((o1, 0.0, False, False, i1), (o2, 0.0, False, False, i2))
    assert taken and all(taken)  # (every step took the plan)


def test_a_replaced_state_array_is_left_to_the_general_path():
    """A state array replaced by one of another layout (Fortran order), or an invalid one,
    is not stepped by the plan: the general path takes it (and its errors are the step's)."""
    planned, plain = _pair("ChainSwing-v0", {})
    for env in (planned, plain):
        s = env.unwrapped.task.system
        s.v = np.asfortranarray(s.v + 0.0)
    plan = planned.unwrapped._plan
    assert plan.physics() is None  # (nothing changed: the system is as it was)
    assert np.isfortran(planned.unwrapped.task.system.v)
    a = np.array([0.5], np.float32)
    _same(planned.step(a), plain.step(a))
    _states_equal(planned, plain)
    errors = []
    for env in (planned, plain):
        env.unwrapped.task.system.x = np.zeros((3, 2))
        with pytest.raises(ValueError) as error:
            env.step(a)
        errors.append(str(error.value))
    assert errors[0] == errors[1]


def test_a_diverging_step_is_left_to_the_general_path():
    """A step that diverges is taken again by the general path from the same state, which
    parks the copy and ends the episode as it does without a plan."""
    planned, plain = _pair("ClothSlide-v0", {})
    for env in (planned, plain):
        env.unwrapped.task.system.v[:] = 1e9
    a = planned.action_space.sample()
    out = planned.step(a)
    assert out[4]["diverged"]
    _same(out, plain.step(a))
    _states_equal(planned, plain)


def test_a_reassigned_goal_or_setting_is_read_anew():
    """The plan remembers the success test's record only while every attribute it was made
    from is the same object: a goal array reassigned, a tolerance changed, are read at the
    next step, as the general path reads them."""
    planned, plain = _pair("ChainSwing-v0", {})
    a = np.array([0.2], np.float32)
    _same(planned.step(a), plain.step(a))
    for env in (planned, plain):
        task = env.unwrapped.task
        task.goal = task.goal + 0.25
        task.goal_tolerance = 5.0  # (every copy is within it now)
    for _ in range(3):
        _same(planned.step(a), plain.step(a))
    outcomes = []
    for env in (planned, plain):  # (the goal reshaped in place: the general path's)
        env.unwrapped.task.goal.shape = (1, 1)
        try:
            outcomes.append(env.step(a))
        except (ValueError, TypeError) as error:  # (the general path's own error)
            outcomes.append(f"{type(error).__name__}: {error}")
    if isinstance(outcomes[0], str):
        assert outcomes[0] == outcomes[1]
    else:
        _same(*outcomes)


def test_tasks_with_their_own_physics_have_no_plan():
    pick_place = [spec for spec in envs.task_specs()
                  if issubclass(spec.env.task_class, PickPlaceTask)]
    env = gym.make(pick_place[0].id)
    assert isinstance(env.unwrapped.task, PickPlaceTask)
    assert env.unwrapped._plan is None


def test_a_system_being_stepped_elsewhere_is_refused_as_by_a_step():
    """The prepared step takes the system's step lock as ``ParticleSystem.step`` does: while
    another thread holds it, the env's step raises the same RuntimeError and the state is
    left as it was; once released, the next step goes through the plan again."""
    planned, plain = _pair("ClothSlide-v0", {})
    a = planned.action_space.sample()
    for env in (planned, plain):
        s = env.unwrapped.task.system
        x = s.x.copy()
        with s.stepping():  # (held, as by another thread stepping the system)
            with pytest.raises(RuntimeError, match="another thread"):
                env.step(a)
        assert s.x.tobytes() == x.tobytes()
    _same(planned.step(a), plain.step(a))
    _states_equal(planned, plain)


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_a_vector_envs_prepared_step_gives_the_general_paths_bits(env_id, kwargs):
    """The native vector env takes the prepared step on the steps no copy resets in (one
    thread): observations, rewards, ends and infos bit for bit those of the general path,
    through episode ends and autoresets."""
    made = [gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                         max_episode_steps=6, **kwargs) for _ in range(2)]
    assert made[0].unwrapped._plan is not None
    made[1].unwrapped._plan = None
    records = []
    for env in made:
        rng = np.random.default_rng(2)
        obs, _ = env.reset(seed=5)
        out = [obs.tobytes()]
        for _ in range(14):
            obs, r, te, tr, info = env.step(
                rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            out.append((obs.tobytes(), r.tobytes(), te.tobytes(), tr.tobytes(),
                        sorted((k, np.asarray(v).tobytes()) for k, v in info.items())))
        s = env.unwrapped.task.system
        out.append((s.x.tobytes(), s.v.tobytes(), s.t))
        records.append(out)
        env.close()
    assert records[0] == records[1]


def test_split_steps_take_the_prepared_step_too(monkeypatch):
    """SliderCrank's copies split their steps when they move fast (``step_travel``): the plan
    takes those steps through the split kernel as the general path does, with the same bits
    (16 copies pushed hard, so that some steps split)."""
    from constrained_particles import fused

    split, calls = fused.fused_split, []

    def counted(*args):
        calls.append(1)
        return split(*args)

    monkeypatch.setattr(fused, "fused_split", counted)
    made = [gym.make_vec("SliderCrank-v0", num_envs=16, vectorization_mode="vector_entry_point")
            for _ in range(2)]
    made[1].unwrapped._plan = None
    records = []
    for env in made:
        env.reset(seed=1)
        out = []
        for k in range(40):
            a = np.full(env.action_space.shape, 1.0 if k % 10 < 6 else -1.0, np.float32)
            obs, r, te, tr, _ = env.step(a)
            out.append((obs.tobytes(), r.tobytes(), te.tobytes(), tr.tobytes()))
        records.append(out)
        env.close()
    assert len(calls) >= 4  # (split steps were taken, by both)
    assert records[0] == records[1]
