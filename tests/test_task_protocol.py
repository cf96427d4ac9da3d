"""The task protocol: a new task defined in this one file registers, every tool of the project
reads its declaration, and it passes the same conformance loop as the shipped tasks.

``RopeCarry`` is the task a maintainer would write first: a rope of rods hangs from two
grippers that slide on a wire (each end particle on the wire, rods between neighbours, a
spreader rod between the ends, gravity, a little drag, walls ending the wire); the two grippers'
horizontal forces (force mode, two
actuators) or the project's mouse spring (spring mode) bring the rope's centre to rest at a goal
on the wire. Nothing outside this file changes to add it.
"""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import envs
from constrained_particles import Drag, Gravity, HorizontalWire, ParticleSystem, Rod, Wall, scenes
from envs.agents import ScriptedAgent, make_agent
from envs.base import ACTION_MODES, ParticleTask
from envs.checks import check_goal_range, uniform_away
from envs.conformance import CHECKS, check_task
from envs.single import ParticleEnv
from envs.task import TaskSpec, ppo, spec_of_task, task_spec, unregister_task
from envs.vector import ParticleVectorEnv

ROPE_ID = "RopeCarry-v0"


class RopeCarry(ParticleTask):
    """``num_envs`` ropes of ``links`` rods (``link`` m each, ``mass`` kg per particle) whose
    two ends slide on a wire at y = 0 between walls at x = -+``travel`` m."""

    force_dim = 2

    def __init__(self, num_envs: int = 1, *, action_mode: str = "force", links: int = 4,
                 link: float = 0.1, mass: float = 0.05, travel: float = 1.0,
                 goal_range: tuple[float, float] = (-0.5, 0.5), dt: float = 0.01,
                 substeps: int = 5, integrator: str = "rattle",
                 max_force: float = 1.0) -> None:
        self.links, self.link, self.mass, self.travel = int(links), float(link), mass, travel
        self.goal_range, self.min_distance = check_goal_range(goal_range, 0.2)
        self.view = (-travel - 0.2, -0.5, travel + 0.2, 0.2)
        self.goal_height = -0.1
        self.step_cost = 2.0 * travel
        super().__init__(num_envs, action_mode=action_mode, dt=dt, substeps=substeps,
                         integrator=integrator, max_force=max_force, grab_radius=np.inf,
                         mouse_ks=10.0, mouse_kd=0.5, goal_tolerance=0.05, rest_speed=0.05,
                         hold_steps=5)
        self.tracked_particles = np.arange(self.n)  # the rope's centre x

    def rope(self, x0: float) -> np.ndarray:
        """The rope hanging in a V below the wire, its ends ``0.8`` of its length apart, centred
        on ``x0`` (m)."""
        L = self.links
        half = 0.4 * L * self.link  # each end 0.4 of the rope's length from the centre
        x = np.zeros((L + 1, 2))
        x[:, 0] = x0 + np.linspace(-half, half, L + 1)
        dx = 2 * half / L
        dy = np.sqrt(self.link**2 - dx**2)
        depth = np.minimum(np.arange(L + 1), L - np.arange(L + 1))
        x[:, 1] = -dy * depth
        return x

    def build_scene(self) -> ParticleSystem:
        s = ParticleSystem()
        L = self.links
        s.add_particles(self.rope(0.0), mass=np.full(L + 1, self.mass))
        i = np.arange(L + 1)
        s.add(Gravity((0.0, -scenes.G)), HorizontalWire(0, 0.0), HorizontalWire(L, 0.0),
              Rod(i[:-1], i[1:], self.link),
              Rod(0, L, 0.8 * L * self.link),  # the spreader: the ends never fold together
              Wall((1.0, 0.0), self.travel, kw=500.0, cw=2.0, particles=[0, L]),
              Wall((-1.0, 0.0), self.travel, kw=500.0, cw=2.0, particles=[0, L]),
              Drag(0.02))
        return s

    def force_handles(self, scene: ParticleSystem) -> np.ndarray:
        """The two grippers: the rope's end particles."""
        return np.array([0, self.links])

    def force_vectors(self, action: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Horizontal forces ``action * max_force`` (N) on the two ends."""
        f = np.zeros((len(action), 2, 2))
        f[:, :, 0] = action * self.max_force
        return f

    def sample_start(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
        low, high = self.goal_range
        x0 = float(rng.uniform(low, high))
        goal = uniform_away(rng, low, high, x0, self.min_distance)
        x = self.rope(x0)
        return x, np.zeros_like(x), goal

    def reward(self, m: dict[str, np.ndarray]) -> np.ndarray:
        """``-distance - 0.1 speed + 10 is_success``."""
        return -m["distance"] - 0.1 * m["speed"] + 10.0 * m["is_success"]


class RopeCarryController(ScriptedAgent):
    """PD control of the rope's centre; the force is shared by the two grippers."""

    def __init__(self, task: RopeCarry) -> None:
        super().__init__(task)
        self.spring_particle = task.links // 2

    def force(self, x, v, goal):
        F = np.clip(3.0 * (goal - x[:, :, 0].mean(axis=1)) - 2.0 * v[:, :, 0].mean(axis=1),
                    -1.0, 1.0)
        return np.stack([F, np.zeros_like(F)], axis=1)

    def force_action(self, F, x):
        return np.repeat(F[:, :1] / (2 * self.task.max_force), 2, axis=1)


class RopeCarryEnv(ParticleEnv):
    """Carry a hanging rope by its two ends to a goal on the wire."""

    task_class = RopeCarry


class RopeCarryVectorEnv(ParticleVectorEnv):
    """``num_envs`` RopeCarry copies stepped as one particle system."""

    task_class = RopeCarry


TASK = TaskSpec(id=ROPE_ID, env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                action_modes=ACTION_MODES, scripted_agent=RopeCarryController,
                summary="carry a hanging rope by its two ends to a goal",
                hyperparams={"ppo": {"force": ppo(20000, (32, 32))}})
envs.register_task(TASK)


# ---------------------------------------------------------------------- the tests
@pytest.mark.parametrize("check", list(CHECKS))
@pytest.mark.parametrize("kwargs", TASK.cases, ids=lambda k: k["action_mode"])
def test_a_task_defined_in_one_file_passes_the_conformance_loop(kwargs, check):
    CHECKS[check](ROPE_ID, kwargs)


def test_the_tools_read_its_declaration():
    assert task_spec(ROPE_ID) is TASK and TASK in envs.task_specs()
    env = gym.make(ROPE_ID)
    assert spec_of_task(env.unwrapped.task) is TASK
    assert type(make_agent("scripted", env)) is RopeCarryController
    assert gym.spec(ROPE_ID).max_episode_steps == TASK.max_episode_steps
    from cparticles.bench import small_envs
    from envs.demo import run_episodes
    from envs.train import load_hyperparams

    assert (ROPE_ID, "spring") in small_envs()
    assert load_hyperparams("ppo", ROPE_ID)["n_timesteps"] == 20000
    with pytest.raises(ValueError, match="no sac settings"):
        load_hyperparams("sac", ROPE_ID)
    res = run_episodes(ROPE_ID, "scripted", 4, seed=0)
    assert res["success"].all()  # the scripted agent carries every rope to its goal
    assert (run_episodes(ROPE_ID, "random", 4, seed=0)["success"].sum() < 4)


def test_a_vector_env_made_directly_truncates_where_its_declaration_says():
    """The native vector env's default ``max_episode_steps`` is the declaration's (here 200,
    the TaskSpec default; a shipped task's own, 30 for RopeStraighten), for a subclass too;
    a class no declaration names gets 200; an explicit value wins."""
    from envs.rope_straighten import RopeStraightenVectorEnv

    assert RopeCarryVectorEnv(2).max_episode_steps == TASK.max_episode_steps
    assert RopeStraightenVectorEnv(1).max_episode_steps == \
        task_spec("RopeStraighten-v0").max_episode_steps == 30
    assert type("Sub", (RopeStraightenVectorEnv,), {})(1).max_episode_steps == 30
    assert type("Loose", (ParticleVectorEnv,), {"task_class": RopeCarry})(1) \
        .max_episode_steps == 200
    assert RopeStraightenVectorEnv(1, max_episode_steps=7).max_episode_steps == 7


def test_the_command_line_lists_a_registered_task():
    import argparse

    from envs.demo import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--env", ROPE_ID, "--action-mode", "spring"])
    assert args.env == ROPE_ID


def test_the_loop_catches_what_a_task_forgot():
    """A task whose start does not come from the env's generator is not deterministic: the
    loop says so."""

    class Careless(RopeCarry):
        def sample_start(self, rng):
            return super().sample_start(np.random.default_rng())  # (not the env's generator)

    class CarelessEnv(ParticleEnv):
        task_class = Careless

    class CarelessVectorEnv(ParticleVectorEnv):
        task_class = Careless

    envs.register_task(TaskSpec(id="CarelessRope-v0", env=CarelessEnv,
                                vector_env=CarelessVectorEnv, action_modes=("force",),
                                scripted_agent=RopeCarryController, summary="careless"))
    try:
        with pytest.raises(AssertionError, match="same_seed_same_episode"):
            check_task("CarelessRope-v0", checks=["same_seed_same_episode"])
    finally:
        unregister_task("CarelessRope-v0")
    assert "CarelessRope-v0" not in gym.registry
    with pytest.raises(ValueError, match="env_id"):
        task_spec("CarelessRope-v0")


def test_declarations_are_checked():
    with pytest.raises(ValueError, match="action_modes"):
        TaskSpec(id="X-v0", env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                 action_modes=(), scripted_agent=RopeCarryController, summary="")
    with pytest.raises(ValueError, match="not action modes"):
        TaskSpec(id="X-v0", env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                 action_modes=("force",), scripted_agent=RopeCarryController, summary="",
                 hyperparams={"ppo": {"draw": {}}})
    with pytest.raises(ValueError, match="env"):
        TaskSpec(id="X-v0", env=int, vector_env=RopeCarryVectorEnv,
                 action_modes=("force",), scripted_agent=RopeCarryController, summary="")
    other = TaskSpec(id=ROPE_ID, env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                     action_modes=("spring",), scripted_agent=RopeCarryController, summary="")
    with pytest.raises(ValueError, match="already registered"):
        envs.register_task(other)
    assert envs.register_task(TASK) is TASK  # the same declaration again: nothing happens
    with pytest.raises(ValueError, match="env_id must be one of"):
        task_spec("Nope-v0")


def test_no_registered_id_is_written_outside_its_module():
    """Each shipped id appears as a string literal only in its own module, the registration
    list, the tests and the docs (docstrings' examples are docs)."""
    files = subprocess.run(["git", "ls-files", "*.py"], capture_output=True, text=True,
                           cwd=envs.__path__[0] + "/..", check=False).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    owners = {spec.id: sys.modules[spec.env.__module__].__file__ for spec in envs.task_specs()
              if spec.id in envs.ENV_IDS}
    import ast
    import pathlib

    root = pathlib.Path(envs.__path__[0]).parent
    found = []
    for name in files:
        if name.startswith(("tests/", "docs/")):
            continue
        path = root / name
        tree = ast.parse(path.read_text())
        docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef,
                                        ast.AsyncFunctionDef))
                      and n.body and isinstance(n.body[0], ast.Expr)
                      and isinstance(n.body[0].value, ast.Constant)}
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and isinstance(node.value, str)
                    and id(node) not in docstrings):
                for env_id, owner in owners.items():
                    if env_id in node.value and pathlib.Path(owner) != path:
                        found.append(f"{name}:{node.lineno}: {env_id}")
    assert not found, found


def test_the_docs_overview_table_is_the_declarations():
    import pathlib

    from envs.task import overview_table

    page = pathlib.Path(envs.__path__[0]).parent / "docs" / "environments.md"
    if not page.is_file():
        pytest.skip("docs are not installed beside the package")
    shipped = tuple(envs.task_spec(env_id) for env_id in envs.ENV_IDS)
    assert overview_table(shipped) in page.read_text(), "run python -m envs.overview"


def test_a_variant_ships_settings_of_its_own():
    """``variant_hyperparams`` are taken for exactly their keyword arguments, which they
    record; other keyword arguments keep the mode's settings; malformed keys are refused."""
    from envs.task import parse_variant, variant_key

    spec = TaskSpec(id="X-v0", env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                    action_modes=("spring", "force"), scripted_agent=RopeCarryController,
                    summary="", hyperparams={"ppo": {"spring": ppo(1000, (8,))}},
                    variant_hyperparams={"obs_mode=pixels": {"ppo": {"spring": ppo(
                        2000, (16,), policy="CnnPolicy")}}})
    base = spec.settings("ppo", "spring")
    assert base["n_timesteps"] == 1000 and "env_kwargs" not in base
    own = spec.settings("ppo", "spring", {"obs_mode": "pixels"})
    assert own["n_timesteps"] == 2000 and own["policy"] == "CnnPolicy"
    assert own["env_kwargs"] == {"obs_mode": "pixels"}
    # more or other keyword arguments: the mode's settings
    assert spec.settings("ppo", "spring", {"obs_mode": "pixels", "pixel_size": 84}) == base
    assert spec.settings("ppo", "spring", {"pixel_size": (84, 84)}) == base
    with pytest.raises(ValueError, match="no ppo settings shipped"):
        spec.settings("ppo", "force", {"obs_mode": "pixels"})
    for bad, words in (({"pixels,obs_mode": {}}, "variant"), ({"b=1,a=2": {}}, "sorted"),
                       ({"obs_mode=pixels": {"ppo": {"draw": {}}}}, "not action modes"),
                       ({"action_mode=force": {}}, "inner key")):
        with pytest.raises(ValueError, match=words):
            TaskSpec(id="X-v0", env=RopeCarryEnv, vector_env=RopeCarryVectorEnv,
                     action_modes=("spring", "force"), scripted_agent=RopeCarryController,
                     summary="", variant_hyperparams=bad)
    for kwargs in ({}, {"target": "swingup"}, {"a": 2, "b": 1.5, "c": True}):
        assert parse_variant(variant_key(kwargs)) == kwargs
    with pytest.raises(ValueError, match="variant"):
        parse_variant("target")
