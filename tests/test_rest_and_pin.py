"""The windowed rest test and ClothPin's refusal of springs that cannot help.

The rest test averages each particle's velocity over about ``rest_window`` steps (a moving
average moving ``1 / rest_window`` of the way each step), so zero-mean jitter, the noise of a
stochastic policy, averages out while a steady drift does not. The expected averages here are
the closed form of that recursion, not the env's code.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs.cloth_pin
import envs.cloth_slide
from envs import _measure, cloth_pin_kernels


def pin_action(task, a, b, ks: float = 1.0) -> np.ndarray:
    """ClothPin action drawing a spring from world point ``a`` to ``b`` (m)."""
    return np.concatenate([task.to_normalized(np.asarray(a, float)),
                           task.to_normalized(np.asarray(b, float)),
                           [float(task.stiffness_action(ks)), 1.0]]).astype(np.float32)


def at_goal(task: envs.cloth_slide.ClothSlide) -> None:
    x, v, _ = task.sample_start(np.random.default_rng(0))
    task.write_start([0], [(x, v, float(task.tracked(x[None])[0]))])


@pytest.mark.parametrize("compiled", [True, False])
def test_jitter_at_the_goal_is_rest_and_a_drift_is_not(monkeypatch, compiled):
    if compiled and not _measure.ENABLED:
        pytest.skip("compiled bookkeeping disabled (CPARTICLES_NUMBA=0)")
    monkeypatch.setattr(_measure, "ENABLED", compiled)
    task = envs.cloth_slide.ClothSlide(1)
    at_goal(task)
    stepped = np.ones(1, bool)
    u = 4 * task.rest_speed  # far above rest_speed at every step
    for k in range(1, 21):
        task.system.v[:, 0] = u * (-1) ** k  # zero-mean jitter, positions unchanged
        m = task.measure(stepped)
        assert m["speed"][0] == pytest.approx(u) and task.hold[0] == k
    assert m["is_success"][0]
    # a steady drift of 1.2 rest_speed: the average reaches it, and the count restarts
    at_goal(task)
    drift, a = 1.2 * task.rest_speed, 1.0 / task.rest_window
    counts = []
    for k in range(1, 41):
        task.system.v[:, 0] = drift
        task.measure(stepped)
        np.testing.assert_allclose(task.mean_v[:, 0], drift * (1 - (1 - a) ** k), rtol=1e-12)
        counts.append(int(task.hold[0]))
    settled = [drift * (1 - (1 - a) ** k) < task.rest_speed for k in range(1, 41)]
    assert counts[-1] == 0 and [c > 0 for c in counts] == settled


def test_rest_state_is_saved_and_restored():
    env = gym.make("ClothSlide-v0").unwrapped
    env.reset(seed=4)
    for _ in range(3):
        env.step(np.ones(2, np.float32))
    state = env.get_state()
    assert np.abs(state["mean_v"]).max() > 0
    after = [env.step(np.zeros(2, np.float32))[0] for _ in range(3)]
    env.set_state(state)
    again = [env.step(np.zeros(2, np.float32))[0] for _ in range(3)]
    assert all(a.tobytes() == b.tobytes() for a, b in zip(after, again, strict=True))
    for bad in (np.full((36, 2), np.nan), np.zeros((3, 2))):
        with pytest.raises(ValueError, match="mean_v"):
            env.set_state({**state, "mean_v": bad})
    with pytest.raises(ValueError, match="rest_window"):
        gym.make("ClothSlide-v0", rest_window=0)


def test_cloth_to_cloth_spring_is_refused_and_keeps_the_budget():
    env = gym.make("ClothPin-v1", max_springs=2).unwrapped
    env.reset(seed=1)
    task = env.task
    x = task.positions()[0].copy()
    # more tries than the budget, all while the cloth is still at rest (its first few steps):
    # none is placed, none is charged
    for _ in range(3):
        assert task.still()[0]
        _, reward, _, _, info = env.step(pin_action(task, x[3], x[20]))
        assert not info["placed"] and info["springs"] == 0
    assert task.placed[0] == 0 and np.all(task.springs.ks == 0)
    assert task.still()[0]
    _, _, _, _, info = env.step(pin_action(task, x[3], [-1.1, 0.0]))  # cloth to anchor
    assert info["placed"] and info["springs"] == 1


def _pin_args(task):
    return (task.system.x, task.system.v, task.n, task.goal, tuple(task._view()),
            cloth_pin_kernels.pin_record(task, task.num_envs, task.n, task.cloth_n))


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off: nothing to compare")
def test_cloth_pin_compiled_observation_matches_the_numpy_reference():
    # a push too weak to move the cloths out of rest: drawings are taken on every step
    env = gym.make_vec("ClothPin-v1", num_envs=6, vectorization_mode="vector_entry_point",
                       push=1e-4)
    env.reset(seed=3)
    task = env.unwrapped.task
    rng = np.random.default_rng(0)
    for _ in range(100):
        a = rng.uniform(-1, 1, (6, 6)).astype(np.float32)
        a[:, 5] = np.where(rng.random(6) < 0.3, 1.0, -1.0)  # some drawings, most refused
        env.step(a)
        compiled, reference = task.observe(), task.observe_reference()
        assert compiled.dtype == reference.dtype == np.float32
        assert compiled.tobytes() == reference.tobytes()
    assert task.placed.max() >= 2  # filled spring slots were compared too


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off")
def test_cloth_pin_compiled_observation_refuses_a_spring_end_out_of_range():
    env = gym.make_vec("ClothPin-v1", num_envs=2, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    task = env.unwrapped.task
    args = list(_pin_args(task))
    obs = np.full((2, task.single_observation_space.shape[0]), 7.0, np.float32)
    # the springs' i, j in the Pin record, and its observed count (the last field)
    for k, bad in ((2, -1), (3, len(task.system.x)), (-1, 0), (-1, task.n + 1)):
        pin = list(args[-1])
        if k < 0:
            pin[k] = bad
        else:
            pin[k] = pin[k].copy()
            pin[k][-1] = bad
        assert not cloth_pin_kernels.pin_observe(*args[:-1], tuple(pin), obs)
        assert np.all(obs == 7.0)  # nothing written
    # arrays of the wrong sizes: one copy's placed count only, a slot array short by one,
    # an observation one column short, and fewer particles than the copies hold
    pin = list(args[-1])
    for k, short in ((1, pin[1][:1]), (4, pin[4][:-1]), (5, pin[5][:-1])):
        broken = list(pin)
        broken[k] = np.ascontiguousarray(short)
        assert not cloth_pin_kernels.pin_observe(*args[:-1], tuple(broken), obs)
    narrow = np.full((2, obs.shape[1] - 1), 7.0, np.float32)
    assert not cloth_pin_kernels.pin_observe(*args, narrow) and np.all(narrow == 7.0)
    few = np.ascontiguousarray(args[0][:-1])
    assert not cloth_pin_kernels.pin_observe(few, *args[1:], obs)
    assert np.all(obs == 7.0)
    assert cloth_pin_kernels.pin_observe(*args, obs)
    assert obs.tobytes() == task.observe_reference().tobytes()


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off")
def test_cloth_pin_compiled_drawing_check_refuses_arrays_of_the_wrong_sizes():
    env = gym.make_vec("ClothPin-v1", num_envs=2, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    task = env.unwrapped.task
    x, N = task.system.x, 2
    actions = np.ones((N, 6))
    draw = (task.n, task.cloth_n, task.max_springs, 0.0, 0.0, 1.0, 1.0, 0.01,
            *task.anchor_region)

    def run(x=x, actions=actions, placed=task.placed, draw=draw):
        ends, ok = np.full((N, 2), 7, np.int64), np.ones(N, bool)
        return cloth_pin_kernels.pin_draws(x, actions, np.zeros(N, bool), placed, task.anchors_used,
                                  draw, ends, ok), ends, ok

    done, ends, ok = run()
    assert done and not np.all(ends == 7)
    for bad in ({"x": np.ascontiguousarray(x[:-1])}, {"actions": np.ones((N, 5))},
                {"placed": task.placed[:1].copy()},
                {"draw": (task.n, task.n + 1, *draw[2:])},  # more cloth than particles
                {"draw": (task.n + 1, *draw[1:])}):  # more particles per copy than x holds
        done, ends, ok = run(**bad)
        assert not done and np.all(ends == 7) and ok.all()  # nothing written


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off: nothing to compare")
def test_cloth_pin_compiled_drawings_and_bookkeeping_match_the_numpy_reference(monkeypatch):
    """Two identical vector envs take the same drawings, one through the compiled drawing check
    and bookkeeping, one through the numpy reference (``resolve``, ``place``, ``measure``,
    ``observe_reference``): the springs, anchors, measures and observations agree exactly."""
    N = 6
    fast, ref = (gym.make_vec("ClothPin-v1", num_envs=N, vectorization_mode="vector_entry_point")
                 .unwrapped.task for _ in range(2))
    for task in (fast, ref):
        task.reset_envs(list(range(N)), [np.random.default_rng(i) for i in range(N)])
    def into_the_wall(task):  # copy 0's cloth pressed 5 mm into the wall
        cloth = np.arange(task.cloth_n)
        task.system.x[cloth, 0] += task.wall_x + 0.005 - task.system.x[cloth, 0].max()

    for task in (fast, ref):
        into_the_wall(task)
    rng = np.random.default_rng(2)
    lo_x, lo_y, hi_x, hi_y = fast.anchor_region
    seen = {"placed": 0, "refused": 0, "new": 0, "wall": 0}
    for _ in range(80):
        x = fast.positions()
        cloth = x[np.arange(N), rng.integers(0, fast.cloth_n, N)]
        region = np.stack([rng.uniform(lo_x, hi_x, N), rng.uniform(lo_y, hi_y, N)], axis=1)
        ends = [cloth + rng.normal(0, 0.05, (N, 2)), region]
        if rng.random() < 0.5:
            ends.reverse()
        a = np.concatenate([fast.to_normalized(ends[0]), fast.to_normalized(ends[1]),
                            rng.uniform(-1, 1, (N, 2))], axis=1)
        wild = rng.random(N) < 0.3  # some drawings anywhere (mostly refused)
        a[wild, :4] = rng.uniform(-1, 1, (int(wild.sum()), 4))
        a = np.clip(a, -1, 1)
        idle = rng.random(N) < 0.2
        used = fast.anchors_used.copy()
        fast.apply(a.copy(), idle)
        with monkeypatch.context() as m:
            m.setattr(_measure, "ENABLED", False)
            ref.apply(a.copy(), idle)
        for name in ("placed_now", "placed", "anchors_used"):
            assert np.array_equal(getattr(fast, name), getattr(ref, name)), name
        for name in ("i", "j", "rest", "ks", "kd"):
            assert np.array_equal(getattr(fast.springs, name), getattr(ref.springs, name)), name
        assert fast.system.x.tobytes() == ref.system.x.tobytes()
        seen["placed"] += int(fast.placed_now.sum())
        seen["refused"] += int(((a[:, 5] > 0) & ~idle & ~fast.placed_now).sum())
        seen["new"] += int((fast.anchors_used > used).sum())
        for task in (fast, ref):
            task.simulate()
        stepped = rng.random(N) < 0.8
        m_fast, obs_fast = fast.measure_observe(stepped)
        with monkeypatch.context() as m:
            m.setattr(_measure, "ENABLED", False)
            m_ref, obs_ref = ref.measure_observe(stepped)
        assert obs_fast.dtype == obs_ref.dtype == np.float32
        assert obs_fast.tobytes() == obs_ref.tobytes()
        assert list(m_fast) == list(m_ref)
        for k in m_fast:
            np.testing.assert_allclose(m_fast[k], m_ref[k], rtol=0, atol=1e-12, err_msg=k)
        assert np.array_equal(fast.hold, ref.hold)
        seen["wall"] += int(np.count_nonzero(m_fast["wall_force"]))
        if fast.placed.min() == fast.max_springs:
            for task in (fast, ref):
                task.reset_envs(list(range(N)), [np.random.default_rng(i) for i in range(N)])
                into_the_wall(task)
    assert min(seen.values()) >= 5, seen


@pytest.mark.parametrize("compiled", [True, False])
def test_a_moving_cloth_refuses_a_drawing_and_a_cloth_at_rest_takes_it(monkeypatch, compiled):
    """ClothPin draws springs only on a cloth at rest: its averaged particle speed below
    ``rest_speed`` (0.05 m/s). Three copies start with every cloth particle's velocity (and so
    its moving average) at 0, 0.049 and 0.051 m/s; the same valid drawing is taken by the
    first two only, on the compiled drawing check and on the numpy reference alike."""
    if compiled and not _measure.ENABLED:
        pytest.skip("compiled bookkeeping off")
    monkeypatch.setattr(_measure, "ENABLED", compiled)
    task = envs.cloth_pin.ClothPin(3)
    nc = task.cloth_n
    starts = []
    for speed in (0.0, 0.049, 0.051):
        x, v, goal = task.sample_start(np.random.default_rng(0))
        v[:nc] = [0.0, speed]  # (vertical: the same speed on every particle)
        starts.append((x, v, goal))
    task.write_start([0, 1, 2], starts)
    assert task.still().tolist() == [True, True, False]
    x = task.positions()[0]
    action = np.tile(pin_action(task, x[3], [-1.1, 0.0]).astype(np.float64), (3, 1))
    task.apply(action)
    assert task.placed.tolist() == [1, 1, 0] and task.placed_now.tolist() == [True, True, False]
    ks = task.springs.ks.reshape(3, -1)
    assert ks[0, 0] > 0 and ks[1, 0] > 0 and not ks[2].any()
    assert task.anchors_used.tolist() == [1, 1, 0]


def test_a_drawing_on_the_moving_cloth_changes_nothing_and_costs_nothing():
    """Once the push has the cloth moving (10 steps after a reset), a valid drawing is refused:
    the episode goes on exactly as if nothing had been drawn (same observations and rewards),
    while the same drawing on the first step is taken."""
    runs = []
    for draw_at in (None, 10, 0):
        env = gym.make("ClothPin-v1")
        env.reset(seed=4)
        task = env.unwrapped.task
        x = task.positions()[0]
        draw = pin_action(task, x[3], [-1.1, 0.0])
        idle = draw.copy()
        idle[5] = -1.0
        trace = []
        for k in range(15):
            obs, reward, *_ = env.step(draw if k == draw_at else idle)
            trace.append((obs.tobytes(), reward, int(task.placed[0])))
        runs.append(trace)
    assert runs[1] == runs[0] and runs[0][-1][2] == 0
    assert runs[2][0][2] == 1 and runs[2][-1][0] != runs[0][-1][0]


@pytest.mark.filterwarnings("ignore:.*ClothPin-v0 is out of date")
def test_the_v0_id_names_its_successor():
    from gymnasium.error import DeprecatedEnv

    with pytest.raises(DeprecatedEnv, match="ClothPin-v1"):
        gym.make("ClothPin-v0")


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off: nothing to compare")
@pytest.mark.parametrize(("max_springs", "push"), [(4, 0.1), (4, 1e-4), (12, 1e-4)])
def test_cloth_pin_compiled_plan_distance_is_the_numpy_reference_and_each_copys_own(
        max_springs, push):
    """``plan_distance`` (compiled) against ``plan_distance_reference`` bit for bit, over random
    drawings (weak pushes: most are taken, Newton steps run); and copy i of the vector env
    against the same state in a one-copy task: each copy's Newton steps stop on its own test,
    so a copy's figure never depends on the others'."""
    N = 6
    env = gym.make_vec("ClothPin-v1", num_envs=N, vectorization_mode="vector_entry_point",
                       max_springs=max_springs, push=push)
    env.reset(seed=5)
    task = env.unwrapped.task
    alone = envs.cloth_pin.ClothPin(1, max_springs=max_springs, push=push)
    rng = np.random.default_rng(1)
    lo_x, lo_y, hi_x, hi_y = task.anchor_region
    held = 0
    for step in range(60):
        x = task.positions()
        cloth = x[np.arange(N), rng.integers(0, task.cloth_n, N)]
        region = np.stack([rng.uniform(lo_x, hi_x, N), rng.uniform(lo_y, hi_y, N)], axis=1)
        a = np.concatenate([task.to_normalized(cloth), task.to_normalized(region),
                            rng.uniform(-1, 1, (N, 1)), np.where(rng.random((N, 1)) < 0.5, 1, -1)],
                           axis=1).astype(np.float32)
        env.step(a)
        compiled, reference = task.plan_distance(), task.plan_distance_reference()
        assert compiled.tobytes() == reference.tobytes()
        right = task.positions()[:, :task.cloth_n, 0].max(axis=1)
        wall = np.abs(task.tracked(task.positions()) + (task.wall_x - right) - task.goal)
        held += int(np.count_nonzero(compiled != wall))  # (the springs hold it off the wall)
        if step % 10 == 9:
            for i in range(N):
                alone.set_state(0, task.get_state(i))
                assert alone.plan_distance().tobytes() == compiled[i:i + 1].tobytes()
    assert held > 20  # Newton steps were taken, not only the wall's shift
    assert task.placed.min() >= 1


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off")
def test_cloth_pin_compiled_plan_distance_refuses_arrays_that_do_not_fit():
    env = gym.make_vec("ClothPin-v1", num_envs=2, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    task = env.unwrapped.task
    sp, x, n, nc, B = task.springs, task.system.x, task.n, task.cloth_n, task.max_springs
    center = task.tracked(task.positions())
    plan = (task.wall_x, float(task.nx * task.push), 6, 1e-9)
    springs = (sp.i, sp.j, sp.ks, sp.rest)

    def run(x=x, springs=springs, n=n, nc=nc, B=B, center=center, goal=task.goal):
        out = np.full(2, 7.0)
        return cloth_pin_kernels.pin_plan(x, springs, n, nc, B, center, goal, plan, out), out

    done, out = run()
    assert done and out.tobytes() == task.plan_distance_reference().tobytes()
    bad_end = sp.j.copy()
    bad_end[-1] = len(x)
    for bad in ({"x": np.ascontiguousarray(x[:-1])}, {"springs": (sp.i, bad_end, sp.ks, sp.rest)},
                {"springs": (sp.i[:-1].copy(), sp.j, sp.ks, sp.rest)}, {"nc": n + 1},
                {"nc": 0}, {"center": center[:1].copy()}, {"B": 129}):
        done, out = run(**bad)
        assert not done and np.all(out == 7.0)  # nothing written


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off")
@pytest.mark.parametrize("nc", [1, 7, 8, 9, 35, 64, 127, 128])
def test_cloth_pin_compiled_plan_takes_numpys_mean_of_the_cloth(nc):
    """With no centre given, the compiled plan computes the cloth's centre of mass itself in
    numpy's order of additions: the same bits as with ``np.mean`` of the first ``nc``
    particles' x given (random positions of every size numpy sums with its eight running sums,
    and below and above them); more than 128 particles are refused (the caller gives
    ``np.mean``)."""
    rng = np.random.default_rng(nc)
    N, n, B = 4, nc + 2, 3
    springs = (np.zeros(N * B, np.int64), np.ones(N * B, np.int64), np.zeros(N * B),
               np.zeros(N * B))
    plan = (1.0, 0.5, 6, 1e-9)
    for _ in range(50):
        x = rng.normal(0.0, rng.choice([1e-3, 1.0, 1e3]), (N * n, 2))
        goal = rng.normal(0.0, 1.0, N)
        given, own = np.empty(N), np.empty(N)
        center = np.mean(np.ascontiguousarray(x.reshape(N, n, 2)[:, :nc, 0]), axis=1)
        assert cloth_pin_kernels.pin_plan(x, springs, n, nc, B, center, goal, plan, given)
        assert cloth_pin_kernels.pin_plan(x, springs, n, nc, B, cloth_pin_kernels.NO_CENTER,
                                          goal, plan, own)
        assert own.tobytes() == given.tobytes()
    zeros = np.full(nc, -0.0)  # (numpy's sum of -0.0 is +0.0: its identity comes first)
    assert np.copysign(1.0, cloth_pin_kernels._pairwise_sum(zeros, nc)) == \
        np.copysign(1.0, np.sum(zeros)) == 1.0
    if nc == 128:
        x = np.zeros((N * 131, 2))
        assert not cloth_pin_kernels.pin_plan(x, springs, 131, 129, B,
                                              cloth_pin_kernels.NO_CENTER, goal, plan, own)
