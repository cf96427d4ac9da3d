"""The single environment: a task with one copy behind ``gymnasium.Env``, and the drawing both
it and the native vector env (:mod:`envs.vector`) use."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike, NDArray

from . import goals, pixels
from .base import FRAME_SIZE, ParticleTask
from .checks import check_options, check_seed, check_task_kwargs
from .driver import StepPlan
from .goals import check_obs_mode


def _info(m: dict[str, np.ndarray], diverged: np.ndarray) -> dict[str, np.ndarray]:
    out = m.copy()
    out.pop("speed", None)
    out["diverged"] = diverged
    return out


class _Rendering:
    """Drawing: ``rgb_array`` frames and pixel observations with the compiled rasteriser
    (:mod:`envs.pixels`, no pygame), the ``human`` window through constrained_particles.render
    (pygame-ce imported lazily)."""

    task: ParticleTask
    metadata: dict[str, Any]
    obs_mode: str
    #: Pixel observations' size ``(H, W)`` and channels (see :mod:`envs.pixels`).
    pixel_size: tuple[int, int]
    pixel_channels: int

    def _frame(self, i: int, surface: Any) -> None:
        """Draw copy ``i`` onto a pygame ``surface`` (the ``human`` window)."""
        from constrained_particles.render import Renderer

        if getattr(self, "_renderer", None) is None:
            self._renderer = Renderer(bounds=self.task.view, size=FRAME_SIZE)
        system, extra, status = self.task.drawing(i)
        self._renderer.draw(surface, system, extra=extra, forces=True, hud=status)

    def _frames(self) -> np.ndarray:
        """Every copy's ``rgb_array`` frame (num_envs, 400, 600, 3) uint8: the task's picture
        at display size, drawn by the rasteriser."""
        if getattr(self, "_display", None) is None:
            self._display = pixels.Camera(self.task, (FRAME_SIZE[1], FRAME_SIZE[0]), 3)
        return self._display.draw()

    def _setup_pixels(self, obs_mode: str, pixel_size: Any, pixel_channels: Any) -> None:
        """Check and keep ``obs_mode``, ``pixel_size``, ``pixel_channels`` (ValueError naming
        the argument)."""
        self.obs_mode = check_obs_mode(obs_mode)
        self.pixel_size = pixels.check_pixel_size(pixel_size)
        self.pixel_channels = pixels.check_pixel_channels(pixel_channels)
        self._camera: pixels.Camera | None = None
        self._display: pixels.Camera | None = None

    def _one_space(self) -> spaces.Space:
        """One copy's observation space in this env's ``obs_mode``."""
        if self.obs_mode == "goal":
            return goals.goal_space(self.task)
        image = pixels.pixel_space(self.pixel_size, self.pixel_channels)
        return {"state": self.task.single_observation_space, "pixels": image,
                "state_pixels": spaces.Dict({"state": self.task.single_observation_space,
                                             "pixels": image})}[self.obs_mode]

    def _observation(self, obs: np.ndarray) -> Any:
        """Every copy's observation in this env's ``obs_mode`` from their state observations
        ``obs`` (num_envs, D)."""
        if self.obs_mode == "goal":
            return goals.goal_observation(self.task, obs)
        if self.obs_mode not in ("pixels", "state_pixels"):  # "state", or a task's own
            return obs  # state-like mode (a pick-and-place task's "particles")
        if self._camera is None:
            self._camera = pixels.Camera(self.task, self.pixel_size, self.pixel_channels,
                                         threads=getattr(self, "num_threads", 1))
        image = self._camera.draw()
        return image if self.obs_mode == "pixels" else {"state": obs, "pixels": image}


def _headless_driver() -> None:
    """On a machine with no display to open a window on (and no ``SDL_VIDEODRIVER`` chosen),
    let SDL draw ``"human"`` frames into its dummy driver, saying so once, instead of printing
    its own errors while it probes drivers that cannot work (``XDG_RUNTIME_DIR``, ...)."""
    import os
    import sys

    if (os.environ.get("SDL_VIDEODRIVER") or not sys.platform.startswith("linux")
            or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return
    os.environ["SDL_VIDEODRIVER"] = "dummy"
    gym.logger.warn("no display (DISPLAY and WAYLAND_DISPLAY are unset): render_mode='human' "
                    "draws into an invisible window; use render_mode='rgb_array' to get frames")


class ParticleEnv(_Rendering, gym.Env[np.ndarray, np.ndarray]):
    """A single environment: its task with one copy. Subclasses set ``task_class``."""

    task_class: ClassVar[type[ParticleTask]]
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"],
                                          "render_fps": 20}

    def __init__(self, render_mode: str | None = None, *, obs_mode: str = "state",
                 pixel_size: int | tuple[int, int] = pixels.DEFAULT_SIZE,
                 pixel_channels: int = 3, **kwargs: object) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or "
                             f"None, got {render_mode!r}")
        #: ``"state"`` (a flat Box), ``"goal"`` (Gymnasium-Robotics' Dict: see envs.goals),
        #: ``"pixels"`` or ``"state_pixels"`` (see envs.pixels)
        self._setup_pixels(obs_mode, pixel_size, pixel_channels)
        check_task_kwargs(self.task_class, kwargs, also=("render_mode", "obs_mode",
                                                         "pixel_size", "pixel_channels"))
        self.task = self.task_class(1, **kwargs)
        limit = self._registered_limit()  # (what a divergence pays for, as in a vector env
        if limit is not None:  # made with the registered limit; task.episode_steps changes it)
            self.task.episode_steps = limit
        self.action_space = self.task.single_action_space
        self.observation_space = self._one_space()
        self.render_mode = render_mode
        self.metadata = {**self.metadata,
                         "render_fps": round(1.0 / (self.task.dt * self.task.substeps))}
        self._renderer = None
        self._window = None
        self._clock = None
        #: The prepared step of the task (envs.driver), None where it has none
        self._plan = StepPlan.make(self.task)

    def _result(self, diverged: np.ndarray, stepped: np.ndarray | None = None
                ) -> tuple[np.ndarray, dict[str, Any]]:
        return self._package(*self.task.measure_observe(stepped), diverged)

    def _package(self, m: dict[str, np.ndarray], obs: np.ndarray, diverged: np.ndarray
                 ) -> tuple[np.ndarray, dict[str, Any]]:
        """The observation (in this env's ``obs_mode``) and info of the one copy's measures
        ``m`` and state observation ``obs``."""
        values = {k: v.item() for k, v in m.items()}  # one copy: arrays of one element
        info = values.copy()
        info.pop("speed", None)
        info["diverged"] = diverged.item()
        self._last, self._values = m, values
        if self.obs_mode == "state":
            return obs[0], info
        out = self._observation(obs)
        if isinstance(out, dict):
            return {k: v[0] for k, v in out.items()}, info
        return out[0], info

    @goals.GoalModeOnly
    def compute_reward(self, achieved_goal: ArrayLike, desired_goal: ArrayLike,
                       info: goals.Info) -> float | NDArray[np.float64]:
        """The goal-mode reward of goals ``(..., k)``, batched or not (for hindsight
        relabelling; :func:`envs.goals.compute_reward`): what :meth:`step` returns in
        ``obs_mode="goal"``."""
        return goals.compute_reward(self.task, achieved_goal, desired_goal, info)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode (randomness from ``self.np_random``); returns ``(obs, info)``.
        ``seed``: a Python or numpy integer >= 0, or None; ``options``: none are taken (a key
        is a ValueError)."""
        check_options(options, ())
        super().reset(seed=check_seed(seed))
        self.task.reset_envs([0], [self.np_random])
        self.task.system.t = 0.0  # the episode's time (a vector env's copies share one clock)
        obs, info = self._result(np.zeros(1, bool))
        if self.render_mode == "human":
            self.render()
        return obs, info

    def _registered_limit(self) -> int | None:
        """The time limit (env steps) the task is registered with, None if it is not."""
        from .task import spec_of_task

        try:
            return spec_of_task(self.task).max_episode_steps
        except ValueError:
            return None

    def step(self, action: ArrayLike) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply ``action`` for one env step (``substeps`` physics steps)."""
        task = self.task
        a = task.check_actions(action, single=True)
        task.apply(a)
        plan = self._plan
        # the prepared step where it can take it (the same bits: see envs.driver), else the
        # general path
        done = plan.physics() if plan is not None and plan.task is task else None
        if done is not None:
            obs, info = self._package(*plan.measure_observe(*done), np.zeros(1, bool))
        else:
            diverged = task.simulate_step()
            obs, info = self._result(diverged, ~diverged)
        if self.obs_mode == "goal":
            reward = self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
        else:
            reward = self.task.reward_one(self._last, self._values)
            if info["diverged"]:  # the episode ends (terminated) and pays for its remaining time
                reward -= self.task.divergence_penalty
        terminated = info["is_success"] or info["diverged"]
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, False, info

    def get_state(self) -> dict[str, Any]:
        """The full simulation state, for planning: restore it with :meth:`set_state`.

        Holds positions ``x`` (m), velocities ``v`` (m/s), time ``t`` (s), ``goal`` (m), the last
        clipped ``action``, the constraint solver's warm start ``lam`` and the state of
        ``np_random``. The ``TimeLimit`` wrapper's step counter is not part of it.
        """
        state = self.task.get_state(0)
        state["np_random"] = self.np_random.bit_generator.state
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`get_state`; ValueError naming the field if any field is
        malformed, and then nothing changes (``np_random`` included)."""
        if isinstance(state, dict) and "np_random" in state:
            trial = type(self.np_random.bit_generator)()
            try:
                trial.state = state["np_random"]
            except (TypeError, ValueError, KeyError, OverflowError):
                raise ValueError(f"state['np_random'] must be the state of a "
                                 f"{type(trial).__name__} from get_state(), got "
                                 f"{state['np_random']!r}") from None
        self.task.set_state(0, state)
        if "np_random" in state:
            self.np_random.bit_generator.state = state["np_random"]

    def render(self) -> np.ndarray | None:
        """``"rgb_array"``: a (400, 600, 3) uint8 frame (the task's picture at display size,
        drawn by the compiled rasteriser: no pygame); ``"human"``: draw into a pygame
        window."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode= to make()")
            return None
        if self.render_mode == "rgb_array":
            return self._frames()[0]
        import pygame

        if self._window is None:
            _headless_driver()
            pygame.display.init()
            pygame.display.set_caption(type(self).__name__)
            self._window = pygame.display.set_mode(FRAME_SIZE)
            self._clock = pygame.time.Clock()
        pygame.event.pump()
        self._frame(0, self._window)
        pygame.display.flip()
        self._clock.tick(self.metadata["render_fps"])
        return None

    def close(self) -> None:
        """Close the pygame window, if any (safe to call twice, and on an env whose
        constructor failed)."""
        if getattr(self, "_window", None) is not None:
            import pygame

            pygame.display.quit()
            self._window = None
            self._clock = None

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update(_renderer=None, _window=None, _clock=None, _camera=None, _display=None)
        return state
