"""The environments under misuse and under hostile action sequences.

Every env case of the issue has a test: the slider-crank spring-mode explosion no longer happens
and a step that leaves its constraints is flagged, bad ``gym.make`` arguments get a ValueError
naming them, wrongly shaped action batches are rejected, and a rejected ``set_state`` changes
nothing. Residuals are measured here from the positions and the wires' geometry, not taken from
the env.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the ids)


def crank_residual(env: gym.Env) -> float:
    """Largest distance (m) by which the slider-crank leaves its circle, wire or rod."""
    task = env.unwrapped.task
    x = task.system.x.reshape(-1, 2, 2)
    circle = np.abs(np.linalg.norm(x[:, 0], axis=1) - task.radius)
    wire = np.abs(x[:, 1, 1])
    rod = np.abs(np.linalg.norm(x[:, 0] - x[:, 1], axis=1) - task.rod)
    return float(np.max([circle, wire, rod]))


def test_issue_repro_spring_mode_no_longer_explodes():
    """reset(seed=110), actions uniform(-1, 1, 4) from default_rng(110): exploded at step 99."""
    env = gym.make("SliderCrank-v0", action_mode="spring")
    env.reset(seed=110)
    rng = np.random.default_rng(110)
    for _ in range(150):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 4))
        assert not info["diverged"]
        # the exploded step paid -36,430; the shaped reward moves by 10 x the change of the
        # cost to go (metres of crank arc plus m/s of speed) in one step, a few units at most
        assert crank_residual(env) < 0.01 and np.isfinite(reward) and reward > -100
        if terminated or truncated:
            env.reset()


def test_constant_full_force_spins_the_crank_without_diverging():
    """Full tangential force on every step drives the crank to about 10 m/s (30 rad/s), where
    25 ms rk4 steps used to lose the wire after ~130 env steps."""
    env = gym.make("SliderCrank-v0", max_episode_steps=400)
    env.reset(seed=1)
    top = 0.0
    for _ in range(300):
        obs, reward, terminated, truncated, info = env.step(np.ones(1, np.float32))
        assert not info["diverged"] and not truncated
        assert crank_residual(env) < 0.01
        top = max(top, float(np.abs(env.unwrapped.task.system.v).max()))
    assert top > 8.0  # the fast regime was really reached


def test_fast_copies_are_split_into_pieces_without_touching_the_slow_ones():
    vec = gym.make_vec("SliderCrank-v0", num_envs=2, vectorization_mode="vector_entry_point")
    single = gym.make("SliderCrank-v0")
    vec.reset(seed=4)
    single.reset(seed=4)
    task = vec.unwrapped.task
    state = task.get_state(1)
    state["v"] = state["v"] * 0.0
    # copy 1 spun up to 30 m/s along its constraints (from the linkage's exact kinematics):
    # more than 2 rad of crank turn per unsplit 25 ms step
    x, v = task.linkage(0.4, 100.0)
    state.update(x=x, v=v)
    task.set_state(1, state)
    assert task.pieces()[0] == 1 and task.pieces()[1] >= 6
    for _ in range(5):
        a = np.array([[0.3], [-0.2]], np.float32)
        o_vec, _, _, truncated, info = vec.step(a)
        o_single = single.step(a[0])[0]
        np.testing.assert_allclose(o_vec[0], o_single, rtol=0, atol=1e-6)
        assert not info["diverged"].any() and not truncated.any()
    assert crank_residual(vec) < 0.01


def test_leaving_the_constraints_is_flagged_and_the_state_kept():
    env = gym.make("SliderCrank-v0", residual_limit=1e-12)
    env.reset(seed=3)
    before = env.unwrapped.get_state()
    obs, reward, terminated, truncated, info = env.step(np.ones(1, np.float32))
    assert info["diverged"] and terminated and not truncated
    after = env.unwrapped.get_state()
    assert after["x"].tobytes() == before["x"].tobytes()
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)


@pytest.mark.parametrize(("env_id", "kwargs", "name"), [
    ("SliderCrank-v0", {"dt": 1e-310}, "dt"),
    ("ClothSlide-v0", {"dt": 1e-310}, "dt"),
    ("SliderCrank-v0", {"dt": True}, "dt"),
    ("SliderCrank-v0", {"radius": 1e300}, "radius"),
    ("SliderCrank-v0", {"rod": 1e300}, "rod"),
    ("SliderCrank-v0", {"max_start_speed": 1e300}, "max_start_speed"),
    ("SliderCrank-v0", {"particle_mass": 1e-310}, "mass"),
    ("SliderCrank-v0", {"substeps": 10**12}, "substeps"),
    ("SliderCrank-v0", {"residual_limit": "1cm"}, "residual_limit"),
    ("SliderCrank-v0", {"residual_limit": -0.01}, "residual_limit"),
    ("ClothSlide-v0", {"cloth_size": (float("inf"), 3)}, "cloth_size"),
    ("ClothSlide-v0", {"cloth_size": (10**6, 10**6)}, "cloth_size"),
    ("ClothSlide-v0", {"spacing": 1e300}, "spacing"),
    ("ClothSlide-v0", {"mouse_ks": float("nan")}, "mouse_ks"),
    ("ClothSlide-v0", {"integrator": ["rk4"]}, "integrator"),
    ("ClothSlide-v0", {"cloth_size": (1, 5)}, "cloth_size"),
    ("ClothSlide-v0", {"cloth_size": (4,)}, "cloth_size"),
    ("ClothSlide-v0", {"cloth_size": (2.5, 3)}, "cloth_size"),
    ("ClothSlide-v0", {"dt": 0.0}, "dt"),
    ("ClothSlide-v0", {"dt": -0.01}, "dt"),
    ("SliderCrank-v0", {"dt": float("nan")}, "dt"),
    ("ClothSlide-v0", {"integrator": "leapfrog"}, "integrator"),
    ("SliderCrank-v0", {"integrator": "RK4"}, "integrator"),
    ("ClothSlide-v0", {"action_mode": "torque"}, "action_mode"),
    ("SliderCrank-v0", {"action_mode": None}, "action_mode"),
    ("ClothSlide-v0", {"substeps": 0}, "substeps"),
    ("ClothSlide-v0", {"substeps": 2.0}, "substeps"),
    ("ClothSlide-v0", {"goal_range": (-0.6, 0.9), "wall_x": 1.0}, "goal_range"),
    ("ClothSlide-v0", {"wall_x": float("inf")}, "wall_x"),
    ("ClothSlide-v0", {"goal_range": (0.3, -0.3)}, "goal_range"),
    ("ClothSlide-v0", {"cloth_ks": -1.0}, "cloth_ks"),
    ("SliderCrank-v0", {"rod": 0.2}, "rod"),
    ("SliderCrank-v0", {"goal_range": (0.3, 1.0)}, "goal_range"),
    ("SliderCrank-v0", {"max_force": 0}, "max_force"),
    ("SliderCrank-v0", {"grab_radius": -1}, "grab_radius"),
    ("ChainSwing-v0", {"target": "up"}, "target"),
    ("ChainSwing-v0", {"links": 1}, "links"),
    ("ChainSwing-v0", {"links": 3.5}, "links"),
    ("ChainSwing-v0", {"stiffness": -1.0}, "stiffness"),
    ("ChainSwing-v0", {"goal_range": (-1.2, 0.5)}, "goal_range"),
    ("ChainSwing-v0", {"start_angle": 2.0}, "start_angle"),
    ("ChainSwing-v0", {"action_mode": "draw"}, "action_mode"),
    ("ChainSwing-v0", {"dt": float("nan")}, "dt"),
    ("ClothPin-v1", {"action_mode": "force"}, "action_mode"),
    ("ClothPin-v1", {"max_springs": 0}, "max_springs"),
    ("ClothPin-v1", {"ks_range": (0.0, 5.0)}, "ks_range"),
    ("ClothPin-v1", {"anchor_region": (-1.3, 0.0, -1.4, 0.1)}, "anchor_region"),
    ("ClothPin-v1", {"anchor_region": (-1.3, -0.2, -0.6, 0.2)}, "anchor_region"),
    ("ClothPin-v1", {"start_range": (-0.5, 0.1)}, "start_range"),
    ("ClothPin-v1", {"goal_range": (0.0, 0.9)}, "goal_range"),
    ("ClothPin-v1", {"push": 0.0}, "push"),
    ("ClothPin-v1", {"cloth_size": (1, 5)}, "cloth_size"),
])
def test_bad_make_arguments_get_a_value_error_naming_them(env_id, kwargs, name):
    with pytest.raises(ValueError, match=name):
        gym.make(env_id, **kwargs)
    with pytest.raises(ValueError, match=name):
        gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)


@pytest.mark.parametrize(("env_id", "kwargs"), [
    ("ClothSlide-v0", dict(dt=0.05, substeps=1, integrator="euler")),
    ("SliderCrank-v0", dict(dt=0.2, substeps=1, integrator="euler")),
    ("ChainSwing-v0", dict(dt=0.05, substeps=1, integrator="euler")),
    ("ClothPin-v1", dict(dt=0.05, substeps=1, integrator="euler")),
])
def test_diverging_simulation_terminates_with_a_penalty_without_nan(env_id, kwargs):
    env = gym.make(env_id, **kwargs)
    env.reset(seed=0)
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.isfinite(reward) and obs in env.observation_space
        if terminated or truncated:
            break
    assert terminated and info["diverged"] and not truncated and not info["is_success"]
    assert all(np.all(np.isfinite(v)) for v in info.values())
    # at least the cost of playing on for a whole episode at the task's largest per-step cost
    assert reward <= -200 * env.unwrapped.task.step_cost < 0
    vec = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point", **kwargs)
    vec.reset(seed=0)
    seen = np.zeros(3, bool)
    for _ in range(100):
        obs, reward, terminated, truncated, info = vec.step(vec.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))
        np.testing.assert_array_equal(terminated & info["diverged"], info["diverged"])
        assert np.all(reward[info["diverged"]] <= -200 * vec.unwrapped.task.step_cost)
        seen |= info["diverged"]
        if seen.all():
            break
    assert seen.any()


@pytest.mark.parametrize("shape", [(2, 4), (8,), (1, 8), (4, 4, 1), (4,)])
def test_vector_actions_must_have_exactly_the_batch_shape(shape):
    vec = gym.make_vec("SliderCrank-v0", num_envs=4, vectorization_mode="vector_entry_point",
                       action_mode="spring")
    vec.reset(seed=0)
    x = vec.unwrapped.task.system.x.copy()
    with pytest.raises(ValueError, match=r"action must have shape \(4, 4\)"):
        vec.step(np.zeros(shape, np.float32))
    assert vec.unwrapped.task.system.x.tobytes() == x.tobytes()
    vec.step(np.zeros((4, 4), np.float32))  # the right shape still works


@pytest.mark.parametrize("action", [np.zeros((1, 1)), 0.5, np.zeros(2), ["a"], np.array([True])])
def test_single_env_actions_must_have_the_action_shape(action):
    env = gym.make("SliderCrank-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(action)


BAD_STATES = [
    ("hold", 1e300), ("hold", -5), ("hold", 2.7), ("hold", True), ("t", -1.0),
    ("t", float("nan")), ("goal", "far"), ("x", np.zeros((3, 2))), ("v", [[np.inf, 0.0]] * 2),
    ("action", [5.0]), ("lam", np.zeros(7)), ("np_random", {"garbage": 1}),
    ("np_random", np.random.MT19937(0).state), ("np_random", None),
]


@pytest.mark.parametrize(("key", "value"), BAD_STATES, ids=[k for k, _ in BAD_STATES])
def test_rejected_set_state_changes_nothing(key, value):
    env = gym.make("SliderCrank-v0").unwrapped
    env.reset(seed=5)
    env.step(np.ones(1, np.float32))
    saved = env.get_state()
    env.step(np.ones(1, np.float32))
    before = env.get_state()
    with pytest.raises(ValueError, match=key):
        env.set_state({**saved, key: value})
    after = env.get_state()
    for k in ("x", "v", "action", "lam"):
        assert after[k].tobytes() == before[k].tobytes()
    assert (after["t"], after["goal"], after["hold"]) == (before["t"], before["goal"],
                                                         before["hold"])
    assert after["np_random"] == before["np_random"]


def test_set_state_rejects_positions_off_the_constraints():
    env = gym.make("SliderCrank-v0").unwrapped
    env.reset(seed=5)
    state = env.get_state()
    with pytest.raises(ValueError, match="leaves the constraints"):
        env.set_state({**state, "x": state["x"] + 0.05})
    env.set_state(state)  # the original is fine


def test_spring_actuator_cannot_be_written_around():
    env = gym.make("SliderCrank-v0", action_mode="spring")
    env.reset(seed=0)
    mouse = env.unwrapped.task.actuator
    with pytest.raises(ValueError):
        mouse.particle[0] = 10**6
    with pytest.raises(ValueError, match="unknown particle"):
        mouse.set([0], particles=[10**6], active=[True])
    env.step(np.zeros(4, np.float32))  # still fine


def test_a_replaced_actuator_force_array_of_the_wrong_length_is_not_read_out_of_bounds():
    """The compiled split rule and step read the force actuator's rows through a row map; a
    force array of fewer rows is refused when it is assigned (the block keeps its number of
    elements), so nothing can read past its end, and the env steps on."""
    env = gym.make_vec("SliderCrank-v0", num_envs=4, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    task = env.unwrapped.task
    x0 = task.system.x.copy()
    with pytest.raises(ValueError, match="keeps its 4 elements"):
        task.actuator.force = np.zeros((2, 2))
    assert task.actuator.force.shape == (4, 2)
    assert task.system.x.tobytes() == x0.tobytes()
    env.step(np.zeros((4, 1), np.float32))
    assert np.all(np.isfinite(task.system.x))


def _vector(env_id: str = "ClothSlide-v0", **kwargs: object) -> gym.vector.VectorEnv:
    return gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **kwargs)


@pytest.mark.parametrize("env_id", envs.ENV_IDS)
def test_python_and_numpy_integer_seeds_are_alike(env_id: str) -> None:
    """A numpy integer seeds a single or a vector env as the Python int of the same value
    (gymnasium alone refuses it), in a list of per-copy seeds too."""
    single = gym.make(env_id)
    first = single.reset(seed=5)[0]
    for seed in (np.int64(5), np.uint32(5), np.int8(5)):
        np.testing.assert_array_equal(single.reset(seed=seed)[0], first)
    vec = _vector(env_id)
    batch = vec.reset(seed=5)[0]
    np.testing.assert_array_equal(batch[0], first)
    np.testing.assert_array_equal(vec.reset(seed=np.int64(5))[0], batch)
    np.testing.assert_array_equal(vec.reset(seed=[np.uint16(5), 6])[0], batch)
    vec.close()


@pytest.mark.parametrize("seed", [-1, True, 1.5, "3"])
def test_a_bad_seed_is_a_value_error_naming_it(seed: object) -> None:
    single, vec = gym.make("ClothSlide-v0"), _vector()
    for env in (single, vec):
        with pytest.raises(ValueError, match="seed"):
            env.reset(seed=seed)
    with pytest.raises(ValueError, match=r"seed\[1\]"):
        vec.reset(seed=[1, -2])


def test_unknown_reset_options_are_an_error_naming_the_valid_ones() -> None:
    single, vec = gym.make("ClothSlide-v0"), _vector()
    with pytest.raises(ValueError, match="'goal'.*takes no options"):
        single.reset(options={"goal": 0.3})
    with pytest.raises(ValueError, match="'goal'.*valid keys are 'reset_mask'"):
        vec.reset(options={"goal": 0.3, "reset_mask": np.ones(2, bool)})
    with pytest.raises(ValueError, match="options"):
        vec.reset(options=["reset_mask"])
    single.reset(options={})  # (gymnasium's checker passes an empty dict)
    vec.reset(options={"reset_mask": np.array([True, False])})


def test_a_failed_constructor_leaves_no_warning_behind(monkeypatch: pytest.MonkeyPatch) -> None:
    """An env whose constructor raised is closed by the garbage collector (gymnasium's
    vector envs close themselves in ``__del__`` in some versions): no "Exception ignored"."""
    import gc
    import sys

    from envs.cloth_slide import ClothSlideEnv, ClothSlideVectorEnv

    ignored: list[object] = []
    monkeypatch.setattr(sys, "unraisablehook", ignored.append)
    for kwargs in ({"num_threads": 0}, {"num_envs": 0}, {"nonsense": 1}):
        with pytest.raises((TypeError, ValueError)):
            ClothSlideVectorEnv(**kwargs)
    with pytest.raises((TypeError, ValueError)):
        ClothSlideEnv(nonsense=1)
    gc.collect()
    assert ignored == []
    for cls in (ClothSlideVectorEnv, ClothSlideEnv):  # what __del__ calls: close()
        half = object.__new__(cls)
        half.close()
        half.close()


def test_human_rendering_without_a_display_uses_the_dummy_driver_and_says_so(monkeypatch):
    """No display and no SDL_VIDEODRIVER: SDL gets its dummy driver (no probing of drivers
    that print errors such as XDG_RUNTIME_DIR's), with one warning; with a display, nothing
    is changed."""
    import sys

    from envs.single import _headless_driver

    if not sys.platform.startswith("linux"):
        pytest.skip("the display variables are Linux's")
    for name in ("SDL_VIDEODRIVER", "DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("DISPLAY", ":0")
    _headless_driver()
    assert "SDL_VIDEODRIVER" not in __import__("os").environ
    monkeypatch.delenv("DISPLAY")
    with pytest.warns(UserWarning, match="no display"):
        _headless_driver()
    assert __import__("os").environ["SDL_VIDEODRIVER"] == "dummy"
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")  # (restored by monkeypatch afterwards)
