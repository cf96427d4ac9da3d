"""A normal step of every side-view environment takes the compiled paths: the physics on the
fused kernel, the step splitting, the actuators (forces, grabbed springs, drawn springs), the
measures and the observation. Each numpy reference those paths stand for is trapped here, so a
change that sends a normal step back to one of them fails (the references themselves are tied
to the compiled paths by the tests of each piece; ``CPARTICLES_NUMBA=0`` runs them).

Not covered: the table-top pick-and-place tasks, whose pick-and-place loop, measures and
observation are numpy around the compiled physics; and each task's potential, its own
arithmetic on arrays (``ShapedTask.potential``), from which the compiled pass of
``ShapedTask.reward`` makes the reward (SliderCrank's vector env computes it compiled too).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from constrained_particles import constraints, forces
from constrained_particles.system import ParticleSystem
from envs import _measure
from envs.base import ParticleTask
from envs.cloth_pin import ClothPin
from envs.driver import StepPlan
from envs.pick_place import PickPlaceTask

pytestmark = pytest.mark.skipif(not _measure.ENABLED,
                                reason="the compiled paths are off (CPARTICLES_NUMBA=0)")

CASES = [(spec.id, kwargs) for spec in envs.task_specs() for kwargs in spec.cases
         if not issubclass(spec.env.task_class, PickPlaceTask)]
IDS = [f"{env_id}-{'-'.join(map(str, kwargs.values()))}" for env_id, kwargs in CASES]

#: The numpy references a normal step must not run: every force block's accumulation (the
#: reference physics and the reference step splitting), every constraint's residual (the
#: reference physics and measures), the reference measures' goal distance and rest test, and
#: ClothPin's reference drawing check, observation and plan distance.
TRAPPED = ([(cls, "accumulate") for cls in (forces.Gravity, forces.ConstantForce,
                                              forces.DampedSpring, forces.AngularSpring,
                                              forces.Drag, forces.TableFriction, forces.Wall,
                                              forces.MouseSpring)]
           + [(cls, "distance_error") for cls in (constraints.CircularWire, constraints.Rod,
                                                   constraints.LineWire,
                                                   constraints.FixedPoint)]
           + [(ParticleTask, name) for name in ("goal_distance", "advance_rest")]
           + [(ClothPin, name) for name in ("observe_reference", "plan_distance_reference",
                                             "place", "resolve")])


@pytest.fixture
def arm(monkeypatch):
    """``arm()``: from then on every reference of :data:`TRAPPED` raises and the fused physics
    must take every step (building an env may use them: ClothSlide's hanging start is found
    by minimising the energy). Returns the list of fused steps taken."""
    taken: list[bool] = []

    def trap(cls, name):
        def called(*args, **kwargs):
            raise AssertionError(f"a normal step ran the numpy reference {cls.__name__}.{name}")
        return called

    def arm_now() -> list[bool]:
        for cls, name in TRAPPED:
            monkeypatch.setattr(cls, name, trap(cls, name))
        fused = ParticleSystem._fused_step

        def fused_step(self, *args, **kwargs):
            ok = fused(self, *args, **kwargs)
            assert ok, "a normal step took the reference physics"
            taken.append(ok)
            return ok

        monkeypatch.setattr(ParticleSystem, "_fused_step", fused_step)
        physics = StepPlan.physics

        def planned(self):  # (a single env's prepared step: the same fused kernel)
            done = physics(self)
            assert done is not None, "a normal step left the prepared step"
            taken.append(True)
            return done

        monkeypatch.setattr(StepPlan, "physics", planned)
        return taken

    return arm_now


def _actions(space: gym.Space, rng: np.random.Generator, steps: int) -> list[np.ndarray]:
    """Uniform random actions (in ClothPin's draw mode a drawing on about half the steps)."""
    return [rng.uniform(space.low, space.high).astype(space.dtype) for _ in range(steps)]


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_a_single_env_step_takes_the_compiled_paths(env_id, kwargs, arm):
    env = gym.make(env_id, **kwargs)
    trapped = arm()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    ended = 0
    for a in _actions(env.action_space, rng, 150):
        _, reward, terminated, truncated, info = env.step(a)
        assert np.isfinite(reward)
        if terminated or truncated:
            ended += 1
            env.reset()
    assert trapped  # (the physics ran, on the fused kernel)
    if env_id == "ClothPin-v1":
        assert env.unwrapped.task.placed.max() >= 1 or ended  # (drawings were taken)


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=IDS)
def test_a_vector_env_step_takes_the_compiled_paths(env_id, kwargs, arm):
    env = gym.make_vec(env_id, num_envs=4, vectorization_mode="vector_entry_point", **kwargs)
    trapped = arm()
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    for a in _actions(env.action_space, rng, 150):
        _, reward, _, _, _ = env.step(a)
        assert np.isfinite(reward).all()
    assert trapped


ALL_CASES = [(spec.id, kwargs) for spec in envs.task_specs() for kwargs in spec.cases]


def _episode_record(env_id: str, kwargs: dict, fresh: bool) -> list:
    """Observations, rewards, ends and infos of a vector env of 3 copies over 9 random steps
    (episodes of 4 steps: autoresets included), with the measures taking the step's pack
    (``fresh``) or checking and refreshing it anew."""
    env = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                       max_episode_steps=4, **kwargs)
    task = env.unwrapped.task
    task._paths["fresh_pack"] = fresh
    env.unwrapped._plan = None  # (the general path's hand-over; the plan's: test_driver.py)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=3)
    out = [obs.tobytes()]
    for _ in range(9):
        obs, r, te, tr, info = env.step(
            rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        out.append((obs.tobytes(), r.tobytes(), te.tobytes(), tr.tobytes(),
                    sorted((k, np.asarray(v).tobytes()) for k, v in info.items())))
    env.close()
    return out


@pytest.mark.parametrize(("env_id", "kwargs"), ALL_CASES,
                         ids=[f"{i}-{'-'.join(map(str, k.values()))}" for i, k in ALL_CASES])
def test_the_measures_after_a_step_take_its_pack_with_the_same_bits(env_id, kwargs,
                                                                   monkeypatch):
    """The measures after an env step take the compiled pack the step's own call checked and
    refreshed (``ParticleTask.simulate_step``): the same observations, rewards, ends and
    infos, bit for bit, as with the pack checked and refreshed again, in every task and
    mode."""
    packed, taken = _measure.packed, []

    def counted(system, fresh=None):
        p = packed(system, fresh)
        taken.append(fresh is not None and p is fresh)
        return p

    monkeypatch.setattr(_measure, "packed", counted)
    fresh = _episode_record(env_id, kwargs, True)
    assert sum(taken) >= 5  # (the steps' packs were taken: most steps end in no reset)
    taken.clear()
    assert fresh == _episode_record(env_id, kwargs, False)
    assert not any(taken)


def test_a_task_that_changes_a_block_after_its_physics_is_measured_anew():
    """A task whose own ``simulate`` reassigns a block's attribute after its physics does not
    hand the step's pack to its measures: they see the block as it is now."""

    class Moving(ClothPin):
        def simulate(self) -> np.ndarray:
            diverged = super().simulate()
            self.wall.offset = -1.0  # (the wall moves in: the cloth is far through it)
            return diverged

    task = Moving(2)
    task.reset_envs([0, 1], [np.random.default_rng(0), np.random.default_rng(1)])
    task.apply(np.zeros((2, 6)))
    task.simulate_step()
    m, _ = task.measure_observe(None)
    assert np.all(m["wall_force"] > 0)
    assert m["wall_force"].tobytes() == task.measure(None)["wall_force"].tobytes()


def test_a_copied_tasks_tracked_particles_are_checked_again():
    """A task copied through a subclass's own ``__getstate__`` (or pickled by an older
    version) remembers nothing of the original's checked indices: an index the copy's array
    is edited to out of range is refused with a ValueError, not read (in a subprocess: a read
    out of bounds would end it)."""
    import subprocess
    import sys

    code = (
        "import copy, numpy as np\n"
        "from envs.chain_swing import ChainSwing\n"
        "class Logged(ChainSwing):\n"
        "    def __getstate__(self):\n"
        "        return self.__dict__.copy()\n"
        "t = Logged(2)\n"
        "t.reset_envs([0, 1], [np.random.default_rng(0), np.random.default_rng(1)])\n"
        "t.measure()\n"
        "c = copy.deepcopy(t)\n"
        "idx = c.__dict__['_tracked_particles']\n"
        "assert idx.flags.writeable\n"
        "idx[0] = 10**11\n"
        "try:\n"
        "    c.measure()\n"
        "except ValueError as e:\n"
        "    print('refused:', e)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "refused:" in done.stdout and "tracked_particles" in done.stdout
