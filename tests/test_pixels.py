"""Pixel observations (``obs_mode="pixels"`` and ``"state_pixels"``, :mod:`envs.pixels`): the
spaces, the bytes (deterministic, the vector env's copies against single envs, grey against
RGB, sizes against each other), where things land in the image against the view's transform,
a fold's shade against alpha compositing, bad arguments, rendering without pygame, and the
libraries that stack frames and learn from images (Gymnasium's FrameStackObservation, SB3's
CnnPolicy through ``envs.sb3.to_sb3`` with VecFrameStack, MultiInputPolicy on
``state_pixels``). The conformance loop runs the env checker in every obs_mode on every task
(``envs.conformance.check_obs_modes``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs import pixels
from envs.cloth_slide import ClothSlide

SLIDE = "ClothSlide-v0"
IDS = list(envs.ENV_IDS)


def image_of(obs):
    return obs["pixels"] if isinstance(obs, dict) else obs


@pytest.mark.parametrize("env_id", IDS)
def test_spaces_and_dtype(env_id):
    env = gym.make(env_id, obs_mode="pixels")
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3) and obs in env.observation_space
    both = gym.make(env_id, obs_mode="state_pixels", pixel_size=84, pixel_channels=1)
    space = both.observation_space
    assert set(space.spaces) == {"state", "pixels"}
    assert space["state"] == gym.make(env_id).observation_space
    assert space["pixels"].shape == (84, 84, 1) and space["pixels"].dtype == np.uint8
    obs, _ = both.reset(seed=0)
    state, _ = gym.make(env_id).reset(seed=0)
    assert obs in space and obs["state"].tobytes() == state.tobytes()


def test_same_seed_same_bytes_and_other_seeds_differ():
    runs = []
    for _ in range(2):
        env = gym.make(SLIDE, obs_mode="pixels")
        frames = [env.reset(seed=4)[0]]
        for a in np.random.default_rng(0).uniform(-1, 1, (10, 2)).astype(np.float32):
            frames.append(env.step(a)[0])
        runs.append(b"".join(f.tobytes() for f in frames))
    assert runs[0] == runs[1]
    assert gym.make(SLIDE, obs_mode="pixels").reset(seed=5)[0].tobytes() != runs[0][:64 * 64 * 3]
    assert not np.array_equal(frames[0], frames[-1]), "the cloth did not move in the image"


@pytest.mark.parametrize("threads", [1, 2])
def test_vector_copy_i_is_the_single_env_seeded_alike(threads):
    """The conformance loop compares with SyncVectorEnv; here, with the physics and the
    drawing on two threads too, 5 copies against 5 single envs over 30 steps."""
    N = 5
    vec = gym.make_vec("ChainSwing-v0", num_envs=N, vectorization_mode="vector_entry_point",
                       obs_mode="pixels", num_threads=threads, max_episode_steps=200)
    singles = [gym.make("ChainSwing-v0", obs_mode="pixels") for _ in range(N)]
    got, _ = vec.reset(seed=30)
    want = [e.reset(seed=30 + i)[0] for i, e in enumerate(singles)]
    rng = np.random.default_rng(3)
    for _ in range(30):
        for i in range(N):
            assert got[i].tobytes() == want[i].tobytes()
        a = rng.uniform(-1, 1, (N, 1)).astype(np.float32)
        got, *_ = vec.step(a)
        want = [e.step(a[i])[0] for i, e in enumerate(singles)]


def test_grey_is_the_luma_of_the_colour_image():
    """Each layer is blended in grey with the luma of its colour, so the grey image is the
    luma of the RGB image up to each layer's rounding (at most 1 per layer)."""
    rgb = gym.make(SLIDE, obs_mode="pixels")
    grey = gym.make(SLIDE, obs_mode="pixels", pixel_channels=1)
    a, b = rgb.reset(seed=1)[0], grey.reset(seed=1)[0]
    luma = a.astype(float) @ np.array([0.299, 0.587, 0.114])
    assert b.shape == (64, 64, 1)
    assert np.max(np.abs(b[:, :, 0] - luma)) <= 3.0


def test_sizes_a_finer_image_averages_to_the_coarser():
    """Coverage is exact area, so the mean of each 2 x 2 block of the 128-pixel image is the
    64-pixel image up to rounding (the layers' compositing makes pixels shared by two layers
    differ a little)."""
    small = gym.make(SLIDE, obs_mode="pixels").reset(seed=2)[0].astype(float)
    big = gym.make(SLIDE, obs_mode="pixels", pixel_size=128).reset(seed=2)[0].astype(float)
    blocks = big.reshape(64, 2, 64, 2, 3).mean(axis=(1, 3))
    assert np.mean(np.abs(blocks - small)) < 1.0
    assert np.max(np.abs(blocks - small)) < 40
    wide = gym.make(SLIDE, obs_mode="pixels", pixel_size=(48, 96)).reset(seed=2)[0]
    assert wide.shape == (48, 96, 3)


def _cloth_pixels(image):
    """Mask of the cloth's blue pixels (blue well above red)."""
    img = image.astype(int)
    return img[:, :, 2] - img[:, :, 0] > 60


def test_the_cloth_and_goal_land_where_the_view_puts_them():
    """The centroid of the cloth's pixels is its centre of mass mapped by the view's
    transform (u = ox + s x, v = oy - s y), to a pixel; the green goal marker's centroid is
    the goal point's."""
    env = gym.make(SLIDE, obs_mode="pixels", pixel_size=256)
    image, _ = env.reset(seed=6)
    task = env.unwrapped.task
    xmin, ymin, xmax, ymax = task.view
    s = min(256 / (xmax - xmin), 256 / (ymax - ymin))
    ox, oy = 128 - (xmin + xmax) / 2 * s, 128 + (ymin + ymax) / 2 * s
    rows, cols = np.nonzero(_cloth_pixels(image))
    x = task.positions()[0]
    hull = (x[:, 0].min(), x[:, 0].max(), x[:, 1].min(), x[:, 1].max())
    assert abs(cols.mean() + 0.5 - (ox + s * (hull[0] + hull[1]) / 2)) < 1.0
    assert abs(rows.mean() + 0.5 - (oy - s * (hull[2] + hull[3]) / 2)) < 1.0
    img = image.astype(int)
    green = (img[:, :, 1] - img[:, :, 0] > 60) & (img[:, :, 1] - img[:, :, 2] > 40)
    gr, gc = np.nonzero(green)
    assert abs(gc.mean() + 0.5 - (ox + s * task.goal[0])) < 1.0
    assert abs(gr.mean() + 0.5 - (oy - s * task.goal_height)) < 1.5


def test_a_fold_shows_darker_as_two_sheets():
    """Fold the cloth's last row of cells up over the one above (a state on the wire, so
    set_state takes it): the overlap shows the shade of two sheets at opacity 0.6 over the
    background, ``bg + (1 - 0.4^2)(blue - bg)``, and the rest one sheet,
    ``bg + 0.6 (blue - bg)``."""
    env = gym.make(SLIDE, obs_mode="pixels", pixel_size=256).unwrapped
    env.reset(seed=0)
    task: ClothSlide = env.task
    state = env.get_state()
    x = state["x"].reshape(task.ny, task.nx, 2).copy()
    fold = x[4, :, 1].copy()  # row 4 of 6: row 5 folds up over rows 3..4
    x[5, :, 1] = 2 * fold - x[5, :, 1] + 0.002
    env.set_state(dict(state, x=x.reshape(-1, 2), v=np.zeros_like(state["v"])))
    image = env._observation(task.observe())[0].astype(float)
    bg, blue = np.array(pixels.BACKGROUND, float), np.array(pixels.CLOTH, float)
    one, two = bg + 0.6 * (blue - bg), bg + 0.84 * (blue - bg)
    near_one = np.all(np.abs(image - one) <= 1.0, axis=2).sum()
    near_two = np.all(np.abs(image - two) <= 1.0, axis=2).sum()
    assert near_two > 200, "no pixel shows two sheets"
    assert near_one > 50, "no pixel shows one sheet"


@pytest.mark.parametrize(("name", "value"), [
    ("obs_mode", "rgb"), ("obs_mode", None), ("pixel_size", 7), ("pixel_size", 1025),
    ("pixel_size", 64.0), ("pixel_size", True), ("pixel_size", (64,)),
    ("pixel_size", (64, 64, 3)), ("pixel_channels", 2), ("pixel_channels", True),
    ("pixel_channels", "3"), ("pixel_channels", 3.0)])
def test_bad_arguments_name_themselves(name, value):
    with pytest.raises(ValueError, match=name):
        gym.make(SLIDE, **{"obs_mode": "pixels", name: value})
    with pytest.raises(ValueError, match=name):
        gym.make_vec(SLIDE, num_envs=2, vectorization_mode="vector_entry_point",
                     **{"obs_mode": "pixels", name: value})


def test_pixels_and_rgb_array_frames_need_no_pygame():
    """In a fresh interpreter where importing pygame or pillow fails (the core install): an
    rgb_array env renders frames (600 x 400, not blank) and observes pixels, and pygame was
    never imported."""
    code = textwrap.dedent("""
        import sys
        sys.modules["pygame"] = None  # (import pygame raises ImportError)
        sys.modules["PIL"] = None  # (nor is pillow needed: the core install draws)
        import gymnasium as gym
        import numpy as np
        import envs
        env = gym.make("ClothSlide-v0", render_mode="rgb_array", obs_mode="pixels")
        obs, _ = env.reset(seed=0)
        obs, *_ = env.step(env.action_space.sample())
        frame = env.render()
        assert frame.shape == (400, 600, 3) and frame.dtype == np.uint8
        assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5
        assert obs.shape == (64, 64, 3)
        vec = gym.make_vec("ChainSwing-v0", num_envs=2, render_mode="rgb_array",
                           vectorization_mode="vector_entry_point")
        vec.reset(seed=0)
        assert [f.shape for f in vec.render()] == [(400, 600, 3)] * 2
        print(sys.modules.get("pygame", "absent"))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "None"  # (our blocker, never replaced by a real import)


def test_gymnasium_frame_stack_carries_the_motion():
    """A single frame has no velocity; FrameStackObservation's stack does: after a push the
    newest two frames differ, and the stack's frames are the env's last observations."""
    env = gym.wrappers.FrameStackObservation(gym.make(SLIDE, obs_mode="pixels"), stack_size=3)
    stack, _ = env.reset(seed=0)
    assert stack.shape == (3, 64, 64, 3) and stack.dtype == np.uint8
    assert all(np.array_equal(stack[0], f) for f in stack)  # (padded with the first frame)
    previous = stack[-1]
    for _ in range(4):
        stack, *_ = env.step(np.array([1.0, 1.0], np.float32))
    assert np.array_equal(stack[-1], env.unwrapped._observation(env.unwrapped.task.observe())[0])
    assert not np.array_equal(stack[-1], stack[-2]) and not np.array_equal(stack[-1], previous)


def test_sb3_cnn_policy_with_frame_stacking_and_multi_input():
    sb3 = pytest.importorskip("stable_baselines3", reason="the rl extra is not installed")
    from stable_baselines3.common.env_checker import check_env as sb3_check_env
    from stable_baselines3.common.torch_layers import CombinedExtractor, NatureCNN
    from stable_baselines3.common.vec_env import VecFrameStack

    from envs.sb3 import to_sb3

    for mode in ("pixels", "state_pixels"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # (SB3's checker warns about unusual image spaces)
            sb3_check_env(gym.make(SLIDE, obs_mode=mode).unwrapped)
    venv = VecFrameStack(to_sb3(gym.make_vec(
        SLIDE, num_envs=2, vectorization_mode="vector_entry_point", obs_mode="pixels",
        max_episode_steps=10)), n_stack=3)
    model = sb3.PPO("CnnPolicy", venv, n_steps=16, batch_size=16, n_epochs=1, seed=0,
                    device="cpu")
    assert model.observation_space.shape == (9, 64, 64)  # channels first, 3 frames of RGB
    assert isinstance(model.policy.features_extractor, NatureCNN)
    model.learn(32)
    assert model.num_timesteps == 32
    obs = venv.reset()
    assert obs.shape == (2, 64, 64, 9)
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (2, 2)
    both = to_sb3(gym.make_vec(SLIDE, num_envs=2, vectorization_mode="vector_entry_point",
                               obs_mode="state_pixels", max_episode_steps=10))
    multi = sb3.PPO("MultiInputPolicy", both, n_steps=16, batch_size=16, n_epochs=1, seed=0,
                    device="cpu")
    assert isinstance(multi.policy.features_extractor, CombinedExtractor)
    multi.learn(32)
    assert multi.num_timesteps == 32


def test_demo_saves_a_gif_without_pygame(monkeypatch, tmp_path, capsys):
    """``cparticles demo --save-gif`` needs pillow only: with pygame unimportable it writes
    an animated GIF of 600 x 400 frames."""
    from PIL import Image

    from cparticles import cli

    monkeypatch.setitem(sys.modules, "pygame", None)
    gif = tmp_path / "x.gif"
    assert cli.main(["demo", "--env", "SliderCrank-v0", "--episodes", "1", "--save-gif",
                     str(gif)]) == 0
    with Image.open(gif) as im:
        assert im.size == (600, 400) and im.n_frames > 2


@pytest.mark.parametrize("env_id", IDS)
def test_the_camera_draws_the_bytes_of_every_mark_drawn_every_frame(env_id):
    """The camera draws the static marks (walls, wires, regions) once into its background;
    the bytes equal those of a plain rasteriser scene drawing every mark of the picture, in
    order, over the background, for 3 copies after some random steps."""
    from constrained_particles import raster

    vec = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                       obs_mode="pixels", pixel_size=(40, 72), pixel_channels=3)
    vec.reset(seed=8)
    for a in np.random.default_rng(2).uniform(-1, 1, (6, *vec.action_space.shape)):
        got, *_ = vec.step(a.astype(np.float32))
    task = vec.unwrapped.task
    pic = task.picture()
    points = np.concatenate([task.positions(), np.broadcast_to(pic.fixed, (3, *pic.fixed.shape)),
                             pic.moving(task)], axis=1)
    plain = raster.Scene(pic.layers(40, 72), raster.View(pic.box, height=40, width=72),
                         channels=3, background=pic.background)
    assert plain.draw(points).tobytes() == got.tobytes()
    assert pic.marks  # (a side view has walls or wires, drawn in advance; a table none)


def test_a_pickled_pixel_env_continues_with_the_same_images():
    import pickle

    env = gym.make("ClothPin-v1", obs_mode="state_pixels")
    env.reset(seed=1)
    env.step(env.action_space.sample())
    clone = pickle.loads(pickle.dumps(env))
    for a in np.random.default_rng(5).uniform(-1, 1, (8, 6)).astype(np.float32):
        mine, theirs = env.step(a)[0], clone.step(a)[0]
        assert mine["pixels"].tobytes() == theirs["pixels"].tobytes()
        assert mine["state"].tobytes() == theirs["state"].tobytes()


def test_cloth_cells_are_found_from_the_springs_alone():
    """A 6 x 5 cloth of scenes.cloth (structural, shear and bend springs), turned and
    sheared a little: the cells found from its springs are exactly the 20 grid cells of the
    index formula ``row * nx + col``; bend springs make four-cliques with three particles in
    a row, which are not cells. Without shear springs there are no cells."""
    from constrained_particles import DampedSpring, scenes

    nx, ny = 6, 5
    s = scenes.cloth(nx, ny, spacing=0.1, wall_x=None)
    turn = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    x = s.x @ turn.T + [[0.05, 0.0]] * (s.x[:, 1:] ** 2)
    springs = next(f for f in s.forces if isinstance(f, DampedSpring))
    cells = pixels.cloth_cells(x, np.stack([springs.i, springs.j], axis=1))
    idx = np.arange(nx * ny).reshape(ny, nx)
    want = {frozenset((idx[r, c], idx[r, c + 1], idx[r + 1, c], idx[r + 1, c + 1]))
            for r in range(ny - 1) for c in range(nx - 1)}
    assert {frozenset(c) for c in cells.tolist()} == want and len(cells) == len(want)
    d1, d2 = x[cells[:, 2]] - x[cells[:, 0]], x[cells[:, 3]] - x[cells[:, 1]]
    area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])  # (half the diagonals' cross)
    assert np.allclose(area, 0.01, rtol=0.1)  # corners in order, counter-clockwise
    plain = scenes.cloth(nx, ny, shear=False, wall_x=None)
    springs = next(f for f in plain.forces if isinstance(f, DampedSpring))
    assert len(pixels.cloth_cells(plain.x, np.stack([springs.i, springs.j], axis=1))) == 0


def test_the_spring_action_shows_while_it_pulls():
    """action_mode="spring": no spring-green pixel after a reset (the spring is off); while
    it pulls, its target shows as a green disk where the task put the anchor."""
    env = gym.make(SLIDE, obs_mode="pixels", action_mode="spring", pixel_size=128)
    image, _ = env.reset(seed=0)

    def green(img):
        return np.abs(img.astype(int) - pixels.MOUSE).sum(axis=2) < 5

    assert not green(image).any()
    image, *_ = env.step(np.array([0.0, -0.3, 1.0, 0.5], np.float32))
    rows, cols = np.nonzero(green(image))
    task = env.unwrapped.task
    xmin, ymin, xmax, ymax = task.view
    s = min(128 / (xmax - xmin), 128 / (ymax - ymin))
    anchor = task.actuator.anchor[0]
    assert len(rows) >= 3
    assert abs(cols.mean() + 0.5 - (64 - (xmin + xmax) / 2 * s + s * anchor[0])) < 1.5
    assert abs(rows.mean() + 0.5 - (64 + (ymin + ymax) / 2 * s - s * anchor[1])) < 1.5
