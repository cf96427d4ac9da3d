"""The compiled env bookkeeping (envs/_measure.py) against its numpy reference.

Every compiled piece of an env step outside the physics (action check, the spring action's
grab, SliderCrank's force action, the measures with their hold count, the observation) is run
next to the readable numpy code of ``envs.base`` and the env modules (selected by switching
``envs._measure.ENABLED`` off) from the same states, along random and wall-pushing rollouts of
vector envs: floats agree to 1e-12, booleans, counts and observations exactly. The constraint
residual is also checked against ``ParticleSystem.distance_errors``, and the rollouts are
checked to reach the cases that matter (wall contact, success counts, grabs that miss).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs.cloth_slide
from envs import _measure
from envs.base import ParticleTask

pytestmark = pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping disabled "
                                "(CPARTICLES_NUMBA=0): only the numpy reference runs")

CASES = [("ClothSlide-v0", "force"), ("ClothSlide-v0", "spring"),
         ("SliderCrank-v0", "force"), ("SliderCrank-v0", "spring"),
         ("ChainSwing-v0", "force"), ("ChainSwing-v0", "spring"), ("ClothPin-v1", None),
         ("ClothSlide-v0", "spring-radius")]  # a finite grab_radius, so that grabs can miss


def both(monkeypatch: pytest.MonkeyPatch, task: ParticleTask, fn):
    """``fn()`` with the compiled path, then with the numpy reference, each from the same hold
    counts and moving average velocities of the rest test."""
    hold, mean_v = task.hold.copy(), task.mean_v.copy()
    fast = fn()
    after, mean_after = task.hold.copy(), task.mean_v.copy()
    task.hold[:], task.mean_v[:] = hold, mean_v
    with monkeypatch.context() as m:
        m.setattr(_measure, "ENABLED", False)
        ref = fn()
    assert np.array_equal(task.hold, after), "hold counts differ"
    np.testing.assert_allclose(task.mean_v, mean_after, rtol=0, atol=1e-12,
                               err_msg="moving average velocities differ")
    return fast, ref


def assert_measures_equal(fast: dict, ref: dict) -> None:
    assert list(fast) == list(ref)
    for k in fast:
        a, b = np.asarray(fast[k]), np.asarray(ref[k])
        assert a.dtype == b.dtype and a.shape == b.shape, k
        if a.dtype == bool or a.dtype.kind in "iu":
            assert np.array_equal(a, b), k
        else:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=k)


@pytest.mark.parametrize(("env_id", "mode"), CASES, ids=[f"{e}-{m}" for e, m in CASES])
def test_compiled_bookkeeping_equals_numpy_reference(monkeypatch, env_id, mode):
    N = 4
    kwargs = {} if mode is None else {"action_mode": mode}
    if mode == "spring-radius":
        kwargs, mode = {"action_mode": "spring", "grab_radius": 0.2}, "spring"
    env = gym.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point", **kwargs)
    task = env.unwrapped.task
    env.reset(seed=3)
    # the compiled measures really run (else this would compare the reference with itself)
    assert task._tracking() is not None and _measure.packed(task.system) is not None
    rng = np.random.default_rng(0)
    seen = {"wall": False, "hold": False, "missed": False, "grabbed": False}
    for t in range(150):
        a = rng.uniform(-1.3, 1.3, (N, task.action_dim)).astype(np.float32)
        if env_id == "ClothSlide-v0" and t < 60:  # copies 0 and 1 drive into the right wall
            if mode == "force":
                a[:2] = 1.0
            else:  # grab the top row's middle particle and pull it right
                a[:2, :2] = task.to_normalized(task.positions()[:2, task.nx // 2])
                a[:2, 2:] = (1.0, 0.0)
        fast, ref = both(monkeypatch, task, lambda a=a: task.check_actions(a))
        assert fast.dtype == np.float64 and np.array_equal(fast, ref)
        stepped = rng.uniform(size=N) < 0.8
        fast, ref = both(monkeypatch, task, lambda s=stepped: task.measure(s))
        assert_measures_equal(fast, ref)
        # the measures and the observation in one call, as the envs take them after a step
        (fast, fast_obs), (ref, ref_obs) = both(monkeypatch, task,
                                                lambda s=stepped: task.measure_observe(s))
        assert_measures_equal(fast, ref)
        assert fast_obs.tobytes() == ref_obs.tobytes()
        fast, ref = both(monkeypatch, task, task.observe)
        assert fast.dtype == np.float32 and fast.tobytes() == ref.tobytes()
        worst = [task.single.distance_errors(task.system.x[task.copy_slice(i)]).max()
                 for i in range(N)]  # copy by copy, through the untiled scene
        np.testing.assert_allclose(task.measure()["constraint_residual"], worst, rtol=0,
                                   atol=1e-15)
        clipped = task.check_actions(a)
        if mode == "spring":
            act = task.actuator
            task._actuate(task._every, clipped)
            got = act.particle.copy(), act.anchor.copy(), act.active.copy()
            with monkeypatch.context() as m:
                m.setattr(_measure, "ENABLED", False)
                task._actuate(task._every, clipped)
            for u, w in zip(got, (act.particle, act.anchor, act.active), strict=True):
                assert np.array_equal(u, w)
            seen["missed"] |= not got[2].all()
            seen["grabbed"] |= got[2].any()
        else:
            x = task.positions()
            fast, ref = both(monkeypatch, task, lambda c=clipped, x=x: task.force_vectors(c, x))
            np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-15)
        m = task.measure()
        seen["wall"] |= bool(np.any(m.get("wall_force", np.ones(1)) > 0))
        seen["hold"] |= bool(np.any(task.hold > 0))
        env.step(a)
    assert seen["wall"], "no step touched a wall: the wall force was never tested"
    if mode == "spring":  # the default grab_radius (inf) never misses; 0.2 m does
        assert seen["grabbed"] and seen["missed"] == (task.grab_radius < np.inf)


def test_hold_count_follows_the_success_rule_in_both_paths(monkeypatch):
    """A ClothSlide copy placed at rest on its goal counts up, one pushed into the wall
    restarts: the same counts with the compiled path and the numpy reference."""
    for enabled in (True, False):
        with monkeypatch.context() as mp:
            mp.setattr(_measure, "ENABLED", enabled)
            task = envs.cloth_slide.ClothSlide(2)
            for i in range(2):
                x, v, _ = task.sample_start(np.random.default_rng(i))
                if i == 1:  # copy 1 at rest 1 mm into the right wall, its goal where it is
                    x[:, 0] += task.wall_x + 1e-3 - x[:, 0].max()
                task.write_start([i], [(x, v, float(task.tracked(x[None])[0]))])
            stepped = np.ones(2, bool)
            for k in range(1, 4):
                m = task.measure(stepped)
                assert task.hold.tolist() == [k, 0], enabled
                assert m["wall_force"][0] == 0 and m["wall_force"][1] > 0
                assert m["distance"][0] < 1e-12 and m["speed"][0] == 0
            m = task.measure(np.array([False, True]))
            assert task.hold.tolist() == [3, 0]


def test_check_actions_rejects_nonfinite_and_changes_nothing():
    task = envs.cloth_slide.ClothSlide(2)
    before = task.action.copy()
    for bad in (np.nan, np.inf, -np.inf):
        for dtype in (np.float32, np.float64):
            a = np.zeros((2, 2), dtype)
            a[1, 0] = bad
            with pytest.raises(ValueError, match="action"):
                task.check_actions(a)
    assert np.array_equal(task.action, before)
    # a non-contiguous batch takes the general path and gives the same clipped values
    wide = np.array([[2.0, 0.0, -3.0, 0.0], [0.5, 0.0, 0.25, 0.0]])[:, ::2]
    assert np.array_equal(task.check_actions(wide), [[1.0, -1.0], [0.5, 0.25]])
