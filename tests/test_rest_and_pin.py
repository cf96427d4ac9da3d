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

import envs.cloth_slide
from envs import _measure


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
    env = gym.make("ClothPin-v0").unwrapped
    env.reset(seed=1)
    task = env.task
    x = task.positions()[0].copy()
    for _ in range(6):  # more tries than the budget: none is placed, none is charged
        _, reward, _, _, info = env.step(pin_action(task, x[3], x[20]))
        assert not info["placed"] and info["springs"] == 0
    assert task.placed[0] == 0 and np.all(task.springs.ks == 0)
    _, _, _, _, info = env.step(pin_action(task, x[3], [-1.1, 0.0]))  # cloth to anchor
    assert info["placed"] and info["springs"] == 1


def _pin_args(task):
    sp = task.springs
    return (task.system.x, task.system.v, task.n, task.cloth_n, task.goal, task._view(),
            task.max_springs, task.placed, sp.i, sp.j, task._stiffness_seen(sp.ks), sp.rest)


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off: nothing to compare")
def test_cloth_pin_compiled_observation_matches_the_numpy_reference():
    env = gym.make_vec("ClothPin-v0", num_envs=6, vectorization_mode="vector_entry_point")
    env.reset(seed=3)
    task = env.unwrapped.task
    rng = np.random.default_rng(0)
    for _ in range(40):
        a = rng.uniform(-1, 1, (6, 6)).astype(np.float32)
        a[:, 5] = np.where(rng.random(6) < 0.3, 1.0, -1.0)  # some drawings, most refused
        env.step(a)
        compiled, reference = task.observe(), task.observe_reference()
        assert compiled.dtype == reference.dtype == np.float32
        assert compiled.tobytes() == reference.tobytes()
    assert task.placed.max() >= 2  # filled spring slots were compared too


@pytest.mark.skipif(not _measure.ENABLED, reason="compiled bookkeeping off")
def test_cloth_pin_compiled_observation_refuses_a_spring_end_out_of_range():
    env = gym.make_vec("ClothPin-v0", num_envs=2, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    task = env.unwrapped.task
    args = list(_pin_args(task))
    obs = np.full((2, task.single_observation_space.shape[0]), 7.0, np.float32)
    for k, bad in ((8, -1), (9, len(task.system.x))):  # spring_i, spring_j
        broken = list(args)
        broken[k] = args[k].copy()
        broken[k][-1] = bad
        assert not _measure.pin_observe(*broken, obs)
        assert np.all(obs == 7.0)  # nothing written
    assert _measure.pin_observe(*args, obs)
    assert obs.tobytes() == task.observe_reference().tobytes()
