"""ClothSlide-v0 and SliderCrank-v0 in both action modes: their spaces and measures, success
and its hold, the native vector env's batching (masked resets, one tiled system, frames,
AsyncVectorEnv), bad arguments, divergence, agents, the compiled end of a step against the
general path, and the batched start draws. What every env promises (checker, determinism, state,
pickling, vector env against single envs, bad actions) is in tests/test_env_conformance.py.
"""

from __future__ import annotations

import doctest
import importlib
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import envs
import envs.agents
import envs.cloth_slide
import envs.slider_crank
from envs.agents import make_agent
from envs.base import ACTION_MODES
from envs.rewards import SUCCESS_BONUS, TIME_COST

#: The tasks with a goal along x and force or spring actions (the others:
#: test_chain_swing_cloth_pin.py)
GOAL_ON_X = ("ClothSlide-v0", "SliderCrank-v0")
CASES = [(env_id, mode) for env_id in GOAL_ON_X for mode in ACTION_MODES]
IDS = [f"{env_id}-{mode}" for env_id, mode in CASES]


def random_actions(env: gym.Env, steps: int, seed: int = 1, scale: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (scale * rng.uniform(-1, 1, (steps, *env.action_space.shape))).astype(np.float32)


# ---------------------------------------------------------------------- registration
def test_registration_is_idempotent_and_make_imports_the_package():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        importlib.reload(envs)
    code = ("import warnings; warnings.simplefilter('error'); import gymnasium as gym; "
            "e = gym.make('envs:ClothSlide-v0'); e.reset(seed=0); "
            "f = gym.make('envs:SliderCrank-v0'); f.reset(seed=0); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


# ---------------------------------------------------------------------- API conformance
@pytest.mark.parametrize(("env_id", "mode"), CASES, ids=IDS)
def test_spaces_and_info(env_id, mode):
    env = gym.make(env_id, action_mode=mode)
    assert env.action_space.dtype == np.float32 and env.observation_space.dtype == np.float32
    assert env.action_space.shape == ((4,) if mode == "spring" else
                                      (2,) if env_id.startswith("Cloth") else (1,))
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    n = env.unwrapped.task.n
    assert env.observation_space.shape == (4 * n + 1,)
    obs, info = env.reset(seed=3)
    assert obs in env.observation_space
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs in env.observation_space
        assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    assert {"distance", "kinetic_energy", "constraint_residual", "is_success",
            "diverged"} <= set(info)
    task = env.unwrapped.task
    # the observation's goal and the info's distance agree with the simulation state
    goal = task.center[0] + task.half[0] * float(obs[-1])
    assert goal == pytest.approx(task.goal[0], abs=1e-6)
    assert info["distance"] == pytest.approx(abs(task.tracked(task.positions())[0] - goal),
                                             abs=1e-5)
    assert info["kinetic_energy"] == pytest.approx(task.system.kinetic_energy())


# ---------------------------------------------------------------------- determinism and state
def test_success_holds_for_hold_steps_and_terminates():
    env = gym.make("SliderCrank-v0").unwrapped
    agent = make_agent("scripted", env)
    obs, info = env.reset(seed=0)
    held, terminated = [], False
    task = env.task
    average = task.velocities()[0].copy()  # moving average velocities, from the start's
    while not terminated:
        obs, reward, terminated, truncated, info = env.step(agent(obs))
        average += (task.velocities()[0] - average) / task.rest_window
        rest = np.sqrt(np.mean(np.sum(average**2, axis=1)))
        settled = (info["distance"] < task.goal_tolerance and rest < task.rest_speed
                   and info["crank_height"] > 0)
        held.append(settled)
        assert not truncated
    assert info["is_success"] and reward > 5  # the success bonus
    assert all(held[-env.task.hold_steps:])


# ---------------------------------------------------------------------- vector envs


def test_vector_reset_mask_writes_only_that_slice():
    env = gym.make_vec("ClothSlide-v0", num_envs=3, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    for _ in range(4):
        env.step(env.action_space.sample())
    task = env.unwrapped.task
    before_x, before_v, goal = task.system.x.copy(), task.system.v.copy(), task.goal.copy()
    obs, _ = env.reset(seed=[None, 40, None], options={"reset_mask": np.array([False, True,
                                                                              False])})
    keep = np.r_[0:task.n, 2 * task.n:3 * task.n]
    assert task.system.x[keep].tobytes() == before_x[keep].tobytes()
    assert task.system.v[keep].tobytes() == before_v[keep].tobytes()
    assert goal[[0, 2]].tobytes() == task.goal[[0, 2]].tobytes()
    single, _ = gym.make("ClothSlide-v0").reset(seed=40)
    assert obs[1].tobytes() == single.tobytes()
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.zeros(3, bool)})


def test_vector_env_is_one_tiled_system():
    env = gym.make_vec("ClothSlide-v0", num_envs=5, vectorization_mode="vector_entry_point",
                       action_mode="force")
    task = env.unwrapped.task
    assert task.system.n == 5 * task.single.n
    env.reset(seed=0)
    env.step(np.tile([[0.5, -0.25]], (5, 1)).astype(np.float32))
    push = task.system.forces[-1]
    # actions land in the tiled ConstantForce rows: two handles per copy
    np.testing.assert_allclose(push.force.reshape(5, 2, 2)[:, :, 0],
                               np.tile([0.5, -0.25], (5, 1)) * task.max_force)


def test_vector_env_renders_one_frame_per_copy():
    env = gym.make_vec("SliderCrank-v0", num_envs=2, vectorization_mode="vector_entry_point",
                       render_mode="rgb_array")
    env.reset(seed=[3, 4])
    frames = env.render()
    single = gym.make("SliderCrank-v0", render_mode="rgb_array")
    single.reset(seed=4)
    assert len(frames) == 2 and frames[0].shape == frames[1].shape == (400, 600, 3)
    assert frames[1].tobytes() == single.render().tobytes()
    assert frames[0].tobytes() != frames[1].tobytes()


@pytest.mark.parametrize("env_id", GOAL_ON_X)
def test_async_vector_env_with_two_workers(env_id):
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 2, 2 if "Cloth" in env_id else 1))
    results = []
    for mode in ("async", "sync"):
        env = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode)
        obs, _ = env.reset(seed=8)
        trace = [obs]
        for a in actions.astype(np.float32):
            trace.append(env.step(a)[0])
        env.close()
        results.append(np.stack(trace))
    assert results[0].tobytes() == results[1].tobytes()


# ---------------------------------------------------------------------- bad input and faults
def test_one_diverging_copy_leaves_the_others_alone():
    """Copy 1 is pushed into divergence; copies 0 and 2 match single envs bit for bit."""
    kw = dict(dt=0.01, substeps=5, integrator="symplectic_euler")
    vec = gym.make_vec("ClothSlide-v0", num_envs=3, vectorization_mode="vector_entry_point",
                       **kw)
    vec.reset(seed=30)
    task = vec.unwrapped.task
    # about to leave the system's divergence_limit (1e6 m) within the first physics step
    task.system.x[task.copy_slice(1), 0] += 0.999e6
    task.system.v[task.copy_slice(1), 0] = 1e6
    singles = [gym.make("ClothSlide-v0", **kw) for _ in range(3)]
    for k, env in enumerate(singles):
        env.reset(seed=30 + k)
    diverged = False
    for a in random_actions(singles[0], 12, seed=5):
        obs, _, terminated, _, info = vec.step(np.tile(a, (3, 1)))
        for k in (0, 2):
            assert obs[k].tobytes() == singles[k].step(a)[0].tobytes()
        diverged |= bool(info["diverged"][1])
        if diverged:
            assert terminated[1] and not terminated[0] and not terminated[2]
            break
    assert diverged


# ---------------------------------------------------------------------- agents, demo, docs
@pytest.mark.parametrize(("env_id", "mode"), CASES, ids=IDS)
def test_scripted_agent_succeeds(env_id, mode):
    from envs.demo import run_episodes

    res = run_episodes(env_id, "scripted", 20, seed=100, action_mode=mode)
    assert res["success"].mean() >= (0.9 if mode == "force" else 0.7)


@pytest.mark.parametrize("env_id", GOAL_ON_X)
def test_random_agent_fails(env_id):
    from envs.demo import run_episodes

    res = run_episodes(env_id, "random", 20, seed=100, action_mode="force")
    assert res["success"].mean() <= 0.1
    # an episode it does not win runs out of time (nothing else ends it)
    assert np.all(res["length"][~res["success"]] == 200)


def test_demo_cli_json_table_and_gif(tmp_path, capsys):
    import json

    from PIL import Image

    from cparticles.cli import main

    gif = tmp_path / "episode.gif"
    assert main(["demo", "--env", "SliderCrank-v0", "--episodes", "3", "--json",
                 "--save-gif", str(gif)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["episodes"] == 3 and len(out["returns"]) == 3
    assert 0.0 <= out["success_rate"] <= 1.0 and np.isfinite(out["mean_return"])
    with Image.open(gif) as im:
        assert im.n_frames > 5 and im.size == (600, 400)
    assert main(["demo", "--env", "ClothSlide-v0", "--agent", "random", "--episodes", "2",
                 "--action-mode", "spring", "--integrator", "midpoint", "--dt", "0.0125",
                 "--substeps", "4"]) == 0
    table = capsys.readouterr().out
    assert "success rate" in table and "episode" in table
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--episodes", "0"])
    assert exc.value.code == 2


@pytest.mark.parametrize("module", [envs.agents, envs.cloth_slide, envs.slider_crank])
def test_docstring_examples(module):
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0 and result.attempted > 0


@pytest.mark.parametrize("mode", ["force", "spring"])
def test_slider_crank_vector_copies_equal_single_envs_bit_for_bit(mode):
    """Copy i of the native vector env is a single env seeded seed + i, exactly, over 200
    random-action steps (episode ends and autoresets included)."""
    N = 4
    native = gym.make_vec("SliderCrank-v0", num_envs=N, vectorization_mode="vector_entry_point",
                          action_mode=mode, max_episode_steps=60)
    sync = gym.make_vec("SliderCrank-v0", num_envs=N, vectorization_mode="sync",
                        action_mode=mode, max_episode_steps=60)
    o1, _ = native.reset(seed=7)
    o2, _ = sync.reset(seed=7)
    rng = np.random.default_rng(7)
    for _ in range(200):
        a = rng.uniform(-1, 1, native.action_space.shape).astype(np.float32)
        o1, r1, te1, tr1, _ = native.step(a)
        o2, r2, te2, tr2, _ = sync.step(a)
        assert o1.tobytes() == o2.tobytes() and r1.tobytes() == r2.tobytes()
        np.testing.assert_array_equal(te1 | tr1, te2 | tr2)


@pytest.mark.parametrize("mode", ["force", "spring"])
def test_compiled_steps_equal_the_general_path(mode):
    """SliderCrank's compiled end of a calm step (measures to episode counters, in one call,
    either mode) gives exactly what the general path gives: observations, rewards, ends,
    infos with their masks, hold counts, clocks and the potentials kept for the next reward,
    over steps with successes, truncations and autoresets."""
    def make():
        env = gym.make_vec("SliderCrank-v0", num_envs=6, vectorization_mode="vector_entry_point",
                           action_mode=mode, max_episode_steps=25, goal_tolerance=0.2,
                           rest_speed=1.0, hold_steps=2)
        env.reset(seed=3)
        return env
    fast, general = make(), make()
    general.unwrapped.task._finish_step = lambda steps, max_steps: None
    calls = []

    def counted(name):
        hook = getattr(fast.unwrapped.task, name)

        def call(*a):
            done = hook(*a)
            calls.append(done is not None)
            return done
        return call

    fast.unwrapped.task._finish_step = counted("_finish_step")
    rng = np.random.default_rng(3)
    ends = np.zeros(2, int)
    for _ in range(120):
        a = rng.uniform(-1, 1, fast.action_space.shape).astype(np.float32)
        out1, out2 = fast.step(a), general.step(a)
        for x, y in zip(out1[:4], out2[:4], strict=True):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
        i1, i2 = out1[4], out2[4]
        assert list(i1) == list(i2)
        for k in i1:
            assert i1[k].dtype == i2[k].dtype and i1[k].tobytes() == i2[k].tobytes(), k
        t1, t2 = fast.unwrapped.task, general.unwrapped.task
        assert np.array_equal(t1.hold, t2.hold) and np.array_equal(fast.unwrapped.steps,
                                                                   general.unwrapped.steps)
        assert t1._phi().tobytes() == t2._phi().tobytes() and t1.system.t == t2.system.t
        assert t1.action.tobytes() == t2.action.tobytes()
        ends += [out1[2].sum(), out1[3].sum()]
    assert ends[0] >= 2 and ends[1] >= 2  # both kinds of end, then autoresets
    if envs._measure.ENABLED:  # (else both envs take the general path)
        assert sum(calls) >= 60  # mostly calm steps, taken by a compiled path


def test_a_nonfinite_action_raises_and_changes_nothing():
    """An action that is not finite raises ValueError from a SliderCrank vector step, with the
    state, the actions, the actuator and the step counters as they were."""
    env = gym.make_vec("SliderCrank-v0", num_envs=3, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    env.step(np.full((3, 1), 0.5, np.float32))
    task = env.unwrapped.task
    before = (task.system.x.copy(), task.system.v.copy(), task.action.copy(),
              task.actuator.force.copy(), env.unwrapped.steps.copy(), task.system.t)
    bad = np.array([[0.2], [np.nan], [0.1]], np.float32)
    with pytest.raises(ValueError, match="finite"):
        env.step(bad)
    after = (task.system.x, task.system.v, task.action, task.actuator.force,
             env.unwrapped.steps)
    for x, y in zip(before[:5], after, strict=True):
        assert x.tobytes() == y.tobytes()
    assert task.system.t == before[5]


@pytest.mark.parametrize("env_id", ["ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0",
                                    "ClothPin-v1"])
def test_batched_starts_are_the_single_starts(env_id):
    """``sample_starts`` (one pass over many generators, as the vector env's resets use it)
    draws bit for bit what ``sample_start`` draws from each generator alone."""
    task = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point").unwrapped.task
    x, v, goal = task.sample_starts([np.random.default_rng(s) for s in range(5)])
    assert x.shape == v.shape == (5, task.n, 2) and goal.shape == (5,)
    for s in range(5):
        x1, v1, g1 = task.sample_start(np.random.default_rng(s))
        assert x[s].tobytes() == np.asarray(x1, float).reshape(task.n, 2).tobytes()
        assert v[s].tobytes() == np.asarray(v1, float).reshape(task.n, 2).tobytes()
        assert goal[s] == g1


def test_a_subclass_start_is_used_by_batched_resets():
    """A SliderCrank subclass that redefines ``sample_start`` gets it in vector resets too."""
    from envs.slider_crank import SliderCrank

    class Still(SliderCrank):
        def sample_start(self, rng):
            x, v, goal = super().sample_start(rng)
            return x, np.zeros_like(v), goal

    task = Still(3)
    _, v, _ = task.sample_starts([np.random.default_rng(s) for s in range(3)])
    assert not v.any()


def test_a_subclass_redefinition_takes_the_numpy_path_chosen_when_the_task_is_built():
    """The compiled or reference choice is made once per task, from its class: a SliderCrank
    subclass that redefines ``potential`` (or ``penalties``, ``force_vectors``) gets the
    general end of step, and its own potential shapes its reward; the physics and the
    observations stay those of SliderCrank, step for step."""
    from envs.slider_crank import SliderCrank, SliderCrankVectorEnv

    class Steeper(SliderCrank):
        def potential(self, m):
            return 2.0 * super().potential(m)

    class Fined(SliderCrank):
        def penalties(self, m):
            return 0.25 + 0.0 * m["distance"]

    class Pushed(SliderCrank):
        def force_vectors(self, action, x):
            return super().force_vectors(action, x)

    base = SliderCrank(2)
    assert base._paths["finish"] and base._paths["push"] and not base._paths["penalties"]
    assert not Steeper(2)._paths["finish"] and Steeper(2)._paths["measure_observe"]
    assert not Fined(2)._paths["finish"] and Fined(2)._paths["penalties"]
    assert not Pushed(2)._paths["push"] and Pushed(2)._paths["finish"]

    def make(cls):
        vector_class = type(f"{cls.__name__}Vector", (SliderCrankVectorEnv,), {"task_class": cls})
        env = vector_class(3, max_episode_steps=1000)
        env.reset(seed=4)
        return env

    envs_ = {cls.__name__: make(cls) for cls in (SliderCrank, Steeper, Fined, Pushed)}
    rng = np.random.default_rng(4)
    for _ in range(30):
        a = rng.uniform(-1, 1, (3, 1)).astype(np.float32)
        out = {name: env.step(a) for name, env in envs_.items()}
        ref = out["SliderCrank"]
        for name, step in out.items():
            assert step[0].tobytes() == ref[0].tobytes(), name
        assert np.array_equal(out["Pushed"][1], ref[1])
        assert np.allclose(out["Fined"][1], ref[1] - 0.25, rtol=0, atol=1e-12)
        assert not np.array_equal(out["Steeper"][1], ref[1])  # its own potential shapes it


def test_scaled_draws_are_numpys_uniform_bit_for_bit():
    """envs.base.scaled of a ``rng.random()`` draw (the starts' scalar draws) is exactly what
    Generator.uniform returns from the same stream, for ranges of every sign and size."""
    from envs.checks import scaled

    bounds = [(-np.pi, np.pi), (-1.0, 1.0), (0.0, 0.37), (0.8, 1.05), (-1e-3, 5e3), (2.0, 2.0)]
    for seed in range(5):
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        for _ in range(400):
            for low, high in bounds:
                assert float(a.uniform(low, high)) == scaled(b.random(), low, high)
        assert a.random() == b.random()  # the streams stayed in step


def test_slider_crank_start_draws_are_numpys_uniform_draws_bit_for_bit():
    """SliderCrank draws a start's three doubles in one ``rng.random(3)`` call; the starts are
    those of numpy's ``uniform`` from three successive draws of the same stream (angle, speed,
    the goal away from the slider), for every seed tried and two geometries."""
    for kwargs in ({}, {"max_start_speed": 2.5, "radius": 0.25, "rod": 0.9}):
        task = gym.make("SliderCrank-v0", **kwargs).unwrapped.task
        low, high = task.goal_range
        for seed in range(300):
            ref = np.random.default_rng(seed)
            angle = float(ref.uniform(-np.pi, np.pi))
            omega = float(ref.uniform(-1.0, 1.0)) * task.max_start_speed / task.radius
            values = task._linkage_values(angle, omega)
            x0, gap = values[2], task.min_distance
            left = max(0.0, min(x0 - gap, high) - low)
            right = max(0.0, high - max(x0 + gap, low))
            u = float(ref.uniform(0.0, left + right))
            goal = low + u if u < left else max(x0 + gap, low) + (u - left)
            rng = np.random.default_rng(seed)
            assert task._draw(rng) == (values, goal)
            assert rng.random() == ref.random()  # the streams stayed in step


@pytest.mark.parametrize("env_id", ["SliderCrank-v0", "ClothPin-v1"])
def test_a_step_in_which_every_copy_starts_anew_skips_the_physics_alone(env_id):
    """When every copy resets at once (all truncated together) the vector env writes the starts
    without stepping the physics the starts would overwrite: observations, infos, clock and the
    steps after are exactly those of stepping it."""
    def make():
        env = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                           max_episode_steps=4)
        env.reset(seed=5)
        return env
    lean, full = make(), make()
    full_task = full.unwrapped.task
    cls = type(full_task)

    class Stepped(cls):  # a subclass with its own simulate: every reset step is stepped
        def simulate(self):
            return super().simulate()

    full_task.__class__ = Stepped
    calls = []
    pass_time = lean.unwrapped.task.pass_time
    lean.unwrapped.task.pass_time = lambda: calls.append(1) or pass_time()
    rng = np.random.default_rng(5)
    for _ in range(14):
        a = rng.uniform(-1, 1, lean.action_space.shape).astype(np.float32)
        out1, out2 = lean.step(a), full.step(a)
        for x, y in zip(out1[:4], out2[:4], strict=True):
            assert x.tobytes() == y.tobytes()
        for k in out1[4]:
            assert out1[4][k].tobytes() == out2[4][k].tobytes(), k
        assert lean.unwrapped.task.system.t == full_task.system.t
        assert lean.unwrapped.task.system.x.tobytes() == full_task.system.x.tobytes()
    assert len(calls) >= 2  # truncations at steps 4 and 8: reset steps 5 and 10


# ---------------------------------------------------------------------- rewards and walls
@pytest.mark.parametrize("env_id", ["ClothSlide-v0", "SliderCrank-v0"])
def test_shaped_return_telescopes(env_id):
    """The episode return is k (Phi_0 - Phi_T) - TIME_COST T - penalties + bonus, whatever the
    actions: the shaping term cannot be farmed."""
    env = gym.make(env_id, max_episode_steps=60)
    task = env.unwrapped.task
    rng = np.random.default_rng(3)
    for seed in range(3):
        env.reset(seed=seed)
        phi0 = float(task.potential(task.measure())[0])
        total, penalties, steps, success = 0.0, 0.0, 0, False
        done = False
        while not done:
            _, r, term, trunc, info = env.step(rng.uniform(-1, 1, env.action_space.shape))
            penalties += float(task.penalties(task.measure())[0])
            total += r
            steps += 1
            success |= info["is_success"]
            done = term or trunc
        phiT = float(task.potential(task.measure())[0])
        expected = (task.shaping_scale * (phi0 - phiT) - TIME_COST * steps - penalties
                    + SUCCESS_BONUS * success)
        assert total == pytest.approx(expected, abs=1e-9)


def test_cloth_squeeze_is_penalised_and_reported():
    """Pushing the corners together (net force 0) costs reward and shows in info["squeeze"]."""
    rewards = {}
    for name, action in (("idle", [0.0, 0.0]), ("squeeze", [1.0, -1.0])):
        env = gym.make("ClothSlide-v0")
        env.reset(seed=0)
        _, r, _, _, info = env.step(np.array(action, np.float32))
        rewards[name] = r
        assert info["squeeze"] == pytest.approx(0.5 * (action[0] - action[1]))
    assert rewards["squeeze"] < rewards["idle"] - 0.15


def test_cloth_cannot_leave_to_the_left():
    """The wire has a left end: pushing left at full force for 10 s keeps the cloth in view."""
    env = gym.make("ClothSlide-v0")
    env.reset(seed=0)
    task = env.unwrapped.task
    for _ in range(200):
        _, _, _, _, info = env.step(np.array([-1.0, -1.0], np.float32))
    assert task.positions()[0, :, 0].min() > task.left_wall_x - 0.1
    assert info["wall_force"] > 0


def test_slider_crank_success_needs_the_crank_above():
    """A linkage held at rest at the goal with the crank below the wire never succeeds; the
    mirror image above does."""
    outcomes = {}
    for side in (-1.0, 1.0):
        env = gym.make("SliderCrank-v0", drag=0.0)
        env.reset(seed=0)
        task = env.unwrapped.task
        # crank angle whose slider position is 0.9 m, on the chosen side, at rest
        g, r, L = 0.9, task.radius, task.rod
        angle = side * np.arccos((g**2 + r**2 - L**2) / (2 * g * r))
        x, v = task.linkage(angle, 0.0)
        state = env.unwrapped.get_state()
        # held there at rest: the rest test's averaged velocities are zero too
        state.update(x=x, v=v, goal=g, mean_v=np.zeros_like(state["mean_v"]))
        env.unwrapped.set_state(state)
        hold = task.particle_mass * 9.81 * np.cos(angle) / task.max_force  # cancels gravity
        success = False
        for _ in range(10):
            _, _, term, _, info = env.step(np.array([hold], np.float32))
            success |= term
        outcomes[side] = success
    assert outcomes == {-1.0: False, 1.0: True}


# ----------------------------------------------------------------------------- train/evaluate


def test_the_divergence_penalty_covers_a_longer_time_limit():
    """A vector env with max_episode_steps=500 pays for 500 steps on a diverged step, not the
    registered 200; a single env (whose time limit is gym.make's wrapper, out of its sight)
    does when told through ``task.episode_steps``."""
    kw = dict(dt=0.05, substeps=1, integrator="euler")
    env = gym.make("ClothSlide-v0", max_episode_steps=500, **kw)
    assert env.unwrapped.task.divergence_penalty == pytest.approx(TIME_COST * 200)
    for bad in (0, 2.5, "500"):
        with pytest.raises(ValueError, match="episode_steps"):
            env.unwrapped.task.episode_steps = bad
    env.unwrapped.task.episode_steps = 500
    env.reset(seed=0)
    assert env.unwrapped.task.divergence_penalty >= TIME_COST * 500
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            break
    assert info["diverged"] and reward <= -TIME_COST * 500
    vec = gym.make_vec("ClothSlide-v0", num_envs=3, vectorization_mode="vector_entry_point",
                       max_episode_steps=500, **kw)
    assert vec.unwrapped.task.divergence_penalty >= TIME_COST * 500
    threaded = gym.make_vec("ClothSlide-v0", num_envs=3, vectorization_mode="vector_entry_point",
                            max_episode_steps=500, num_threads=2, **kw)
    assert threaded.unwrapped.task.divergence_penalty >= TIME_COST * 500
    vec.reset(seed=0)
    for _ in range(100):
        _, reward, _, _, info = vec.step(vec.action_space.sample())
        if info["diverged"].any():
            break
    assert info["diverged"].any()
    assert np.all(reward[info["diverged"]] <= -TIME_COST * 500)
