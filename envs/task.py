"""The task protocol: what a task module declares, and the registry that reads it.

A task is one module. Besides its physics and its environment classes it ends with a
:class:`TaskSpec`, the one place that says what the rest of the project needs to know about it:
its id, its single and vector environment classes, its action modes (the default first), the
keyword arguments of its variants worth testing, its scripted agent, its shipped
hyperparameters, its episode length and one line for the docs' tables. Registration
(``gym.make``), ``cparticles train``, ``evaluate``, ``demo`` and ``bench``, :func:`envs.agents.
make_agent` and the conformance tests (:mod:`envs.conformance`) all read the declaration; no env
id appears anywhere else but in its own module and the registration list of
:mod:`envs` (docs/adding_a_task.md walks through a new task).

>>> import envs
>>> spec = envs.task_spec("SliderCrank-v0")
>>> spec.action_modes
('force', 'spring')
>>> spec.default_mode
'force'
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from gymnasium.envs.registration import register, registry

if TYPE_CHECKING:
    import gymnasium as gym
    import numpy as np
    from gymnasium.vector import VectorEnv

    from .base import ParticleTask

__all__ = ["TaskSpec", "check_env_kwargs", "check_env_mode", "env_action_modes",
           "parse_variant", "ppo", "register_task", "sac", "spec_of_task", "task_spec",
           "task_specs", "unregister_task", "variant_key"]

#: Algorithms whose settings a task may ship (Stable-Baselines3's PPO and SAC).
HYPERPARAM_ALGOS = ("ppo", "sac")


@dataclass(frozen=True)
class TaskSpec:
    """A task's declaration (see the module docstring).

    ``env`` and ``vector_env``: the ``gymnasium.Env`` and native ``VectorEnv`` classes (each
    with a ``task_class``); ``action_modes``: the values of the ``action_mode`` argument, the
    default first; ``scripted_agent``: ``agent(task) -> callable(obs) -> action`` for the
    task's physics object (``env.unwrapped.task``), batched or not; ``hyperparams``:
    ``{algo: {action_mode: settings}}`` in the form ``cparticles train`` reads (see
    :mod:`envs.train`), with ``notes`` saying how they were chosen; ``variants``: keyword
    arguments of further configurations that the conformance tests run besides each action
    mode (ChainSwing's swing-up); ``max_episode_steps``: the registered time limit (env steps);
    ``bench_vector``: ``cparticles bench`` times the native vector env and threads on it;
    ``obs_modes``: the values of the envs' ``obs_mode`` argument, the default first (a
    pick-and-place task's goal is no point, so it takes ``"particles"`` instead of
    ``"goal"``); ``summary``: one line for the docs' tables; ``variant_hyperparams``: settings
    of configurations other than the default one, ``{variant: {algo: {action_mode:
    settings}}}`` with ``variant`` the env keyword arguments as :func:`variant_key` writes
    them (``"target=swingup"``, ``"obs_mode=pixels"``): training with exactly those keyword
    arguments takes these settings (each records its keyword arguments as ``env_kwargs``).
    """

    id: str
    env: type
    vector_env: type
    action_modes: tuple[str, ...]
    scripted_agent: Callable[[ParticleTask], Callable[[np.ndarray], np.ndarray]]
    summary: str
    hyperparams: Mapping[str, Mapping[str, Mapping[str, Any]]] = field(default_factory=dict)
    notes: str = ""
    variants: tuple[Mapping[str, Any], ...] = ()
    max_episode_steps: int = 200
    bench_vector: bool = False
    obs_modes: tuple[str, ...] = ("state", "goal", "pixels", "state_pixels")
    variant_hyperparams: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Any]]]] = field(
        default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or "-v" not in self.id:
            raise ValueError(f"id must be a string 'Name-vN', got {self.id!r}")
        for name in ("env", "vector_env"):
            cls = getattr(self, name)
            if not isinstance(cls, type) or not hasattr(cls, "task_class"):
                raise ValueError(f"{name} must be an environment class with a task_class, "
                                 f"got {cls!r}")
        modes = self.action_modes
        if (not isinstance(modes, tuple) or not modes
                or not all(isinstance(m, str) for m in modes) or len(set(modes)) != len(modes)):
            raise ValueError(f"action_modes must be a non-empty tuple of distinct strings, the "
                             f"default first, got {modes!r}")
        if not callable(self.scripted_agent):
            raise ValueError(f"scripted_agent must be callable(task) -> agent, "
                             f"got {self.scripted_agent!r}")
        tables = {"hyperparams": self.hyperparams}
        for variant, table in self.variant_hyperparams.items():
            if not isinstance(variant, str) or variant != variant_key(parse_variant(variant)):
                raise ValueError(f"variant_hyperparams: keys must be env keyword arguments as "
                                 f"variant_key writes them ('key=value,...', sorted), got "
                                 f"{variant!r}")
            if "action_mode" in parse_variant(variant):
                raise ValueError(f"variant_hyperparams[{variant!r}]: the action mode is the "
                                 f"inner key, not a variant")
            tables[f"variant_hyperparams[{variant!r}]"] = table
        for name, hyperparams in tables.items():
            for algo, table in hyperparams.items():
                if algo not in HYPERPARAM_ALGOS:
                    raise ValueError(f"{name}: algo must be one of {HYPERPARAM_ALGOS}, "
                                     f"got {algo!r}")
                unknown = set(table) - set(modes)
                if unknown:
                    raise ValueError(f"{name}[{algo!r}]: {sorted(unknown)} are not action "
                                     f"modes of {self.id} ({', '.join(modes)})")
        if (not isinstance(self.obs_modes, tuple) or not self.obs_modes
                or not all(isinstance(m, str) for m in self.obs_modes)):
            raise ValueError(f"obs_modes must be a non-empty tuple of strings, the default "
                             f"first, got {self.obs_modes!r}")
        if (isinstance(self.max_episode_steps, bool) or not isinstance(self.max_episode_steps,
                                                                        int)
                or self.max_episode_steps < 1):
            raise ValueError(f"max_episode_steps must be a positive int, "
                             f"got {self.max_episode_steps!r}")

    @property
    def default_mode(self) -> str:
        """The action mode a task takes when none is given."""
        return self.action_modes[0]

    @property
    def task_class(self) -> type:
        """The task's physics class (``env.unwrapped.task`` is one)."""
        return self.env.task_class

    @property
    def cases(self) -> list[dict[str, Any]]:
        """Keyword arguments of every configuration the conformance tests run: each action
        mode, then each variant (in the default mode unless it names one)."""
        return ([{"action_mode": m} for m in self.action_modes]
                + [dict(v) for v in self.variants])

    def settings(self, algo: str, action_mode: str | None = None,
                 env_kwargs: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """A copy of the shipped ``algo`` settings for ``action_mode`` (None: the default
        mode) and the env keyword arguments ``env_kwargs``: a variant's own settings when
        :attr:`variant_hyperparams` ships them for exactly these keyword arguments (with them
        as ``"env_kwargs"``), else the mode's; ValueError naming the argument if there are
        none."""
        if algo not in HYPERPARAM_ALGOS:
            raise ValueError(f"algo must be one of {HYPERPARAM_ALGOS}, got {algo!r}")
        mode = self.default_mode if action_mode is None else action_mode
        if mode not in self.action_modes:
            raise ValueError(f"action_mode: {self.id} takes {' or '.join(self.action_modes)}, "
                             f"got {action_mode!r}")
        try:
            variant = variant_key(env_kwargs or {})
        except ValueError:  # (keyword arguments no variant is named by: the mode's settings)
            variant = None
        table = self.variant_hyperparams.get(variant, {}).get(algo, {}) if variant else {}
        if mode in table:
            entry = json.loads(json.dumps(table[mode]))
            entry["env_kwargs"] = {**entry.get("env_kwargs", {}), **dict(env_kwargs or {})}
            return entry
        table = self.hyperparams.get(algo, {})
        if mode not in table:
            have = ", ".join(f"{a}/{m}" for a, t in self.hyperparams.items() for m in t)
            raise ValueError(f"algo: no {algo} settings shipped for {self.id} in {mode} mode "
                             f"(it ships {have or 'none'})")
        return copy.deepcopy(json.loads(json.dumps(table[mode])))

    def default_algo(self, action_mode: str | None = None) -> str:
        """The algorithm ``cparticles train`` uses when none is named: the first of
        :attr:`hyperparams` that ships settings for ``action_mode`` (None: the default mode);
        ``"ppo"`` if none does."""
        mode = self.default_mode if action_mode is None else action_mode
        return next((algo for algo, modes in self.hyperparams.items() if mode in modes), "ppo")

    @property
    def trained_variants(self) -> tuple[str, ...]:
        """The variants (:func:`variant_key` form) with settings of their own, in order."""
        return tuple(self.variant_hyperparams)


#: The settings every shipped PPO entry starts from (keyword arguments of
#: ``stable_baselines3.PPO`` plus ``cparticles train``'s own keys: see :mod:`envs.train`).
PPO_BASE: dict[str, Any] = {
    "n_envs": 16, "normalize": True, "policy": "MlpPolicy", "n_steps": 128, "batch_size": 512,
    "n_epochs": 10, "learning_rate": 0.0003, "gamma": 0.99, "gae_lambda": 0.95,
    "clip_range": 0.2, "ent_coef": 0.0}
#: The settings every shipped SAC entry starts from: one single env (SAC makes one gradient
#: step per env step and gains little from many copies), observations normalized (not
#: rewards: SAC's entropy tuning is scale-aware).
SAC_BASE: dict[str, Any] = {
    "n_envs": 1, "normalize": True, "normalize_reward": False, "policy": "MlpPolicy",
    "learning_rate": 0.0003, "buffer_size": 300000, "batch_size": 256, "gamma": 0.99,
    "tau": 0.005, "learning_starts": 2000, "train_freq": 1, "gradient_steps": 1,
    "ent_coef": "auto"}


def ppo(n_timesteps: int, net_arch: tuple[int, ...] | dict[str, tuple[int, ...]],
        log_std_init: float = -0.5, points: int | None = None,
        **changes: object) -> dict[str, Any]:
    """A PPO entry: :data:`PPO_BASE` with ``changes``, ``n_timesteps`` (the default budget, env
    steps) and an MLP of ``net_arch`` hidden sizes (one tuple for both networks, or
    ``{"pi": ..., "vf": ...}`` apart: ``"pi": ()`` is a policy whose mean is linear in the
    normalised observation) whose Gaussian policy starts from a standard deviation of
    ``exp(log_std_init)`` in action units. ``points``: the pointer policy instead
    (:class:`envs.policies.PointerPolicy` over that many observed points and their targets,
    observations not normalised; ``net_arch`` sizes its value function)."""
    arch: list[int] | dict[str, list[int]] = (
        {key: list(sizes) for key, sizes in net_arch.items()} if isinstance(net_arch, dict)
        else list(net_arch))
    kwargs: dict[str, Any] = {"net_arch": arch, "log_std_init": log_std_init}
    if points is not None:
        kwargs["points"] = points
        changes = {"policy": "PointerPolicy", "normalize": False, **changes}
    return {**PPO_BASE, "n_timesteps": n_timesteps, **changes, "policy_kwargs": kwargs}


def sac(n_timesteps: int = 100000, net_arch: tuple[int, ...] = (256, 256),
        **changes: object) -> dict[str, Any]:
    """A SAC entry: :data:`SAC_BASE` with ``changes``, ``n_timesteps`` and ``net_arch``."""
    return {**SAC_BASE, "n_timesteps": n_timesteps, **changes,
            "policy_kwargs": {"net_arch": list(net_arch)}}


#: Every registered task's declaration, by id, in registration order.
_SPECS: dict[str, TaskSpec] = {}


def register_task(spec: TaskSpec) -> TaskSpec:
    """Register ``spec`` with Gymnasium (``gym.make(spec.id)``, ``gym.make_vec`` with the
    native vector env) and with the project's tools; idempotent for the same declaration.

    The entry points name :mod:`envs.cparticles`, which resolves each class through this
    registry, so ``gym.pprint_registry()`` lists every task under ``cparticles``.
    ValueError if another declaration already holds the id."""
    if not isinstance(spec, TaskSpec):
        raise ValueError(f"spec must be a TaskSpec, got {type(spec).__name__}")
    old = _SPECS.get(spec.id)
    if old is not None and old is not spec and old != spec:
        raise ValueError(f"spec: {spec.id} is already registered by another declaration")
    for cls in (spec.env, spec.vector_env):
        other = _by_class_name().get(cls.__name__)
        if other is not None and other is not cls:
            raise ValueError(f"spec: a class named {cls.__name__} is already registered")
    _SPECS[spec.id] = spec
    if spec.id not in registry:
        register(id=spec.id, entry_point=f"envs.cparticles:{spec.env.__name__}",
                 vector_entry_point=f"envs.cparticles:{spec.vector_env.__name__}",
                 max_episode_steps=spec.max_episode_steps)
    return spec


def unregister_task(env_id: str) -> None:
    """Remove ``env_id`` from the project's registry and Gymnasium's (a task registered in a
    notebook or a test, to be declared again); ValueError if it is not registered."""
    task_spec(env_id)
    del _SPECS[env_id]
    registry.pop(env_id, None)


def _by_class_name() -> dict[str, type]:
    return {cls.__name__: cls for s in _SPECS.values() for cls in (s.env, s.vector_env)}


def environment_class(name: str) -> type:
    """The registered environment class called ``name`` (:mod:`envs.cparticles`'s entry
    points); AttributeError if none is."""
    found = _by_class_name().get(name)
    if found is None:
        raise AttributeError(f"no registered environment class {name!r}")
    return found


def registered_episode_steps(vector_env: type) -> int:
    """The ``max_episode_steps`` declared by the task whose native vector env is
    ``vector_env`` (a subclass of one counts as it), a declaration's default (200) for a
    class no declaration names: the vector envs' default, as ``gym.make`` applies the
    registered limit to a single env."""
    for cls in vector_env.__mro__:
        for spec in _SPECS.values():
            if spec.vector_env is cls:
                return spec.max_episode_steps
    return TaskSpec.max_episode_steps


def task_specs() -> tuple[TaskSpec, ...]:
    """Every registered task's declaration, in registration order."""
    return tuple(_SPECS.values())


def env_action_modes() -> dict[str, tuple[str, ...]]:
    """Each registered id's action modes, the default first."""
    return {spec.id: spec.action_modes for spec in _SPECS.values()}


def task_spec(env_id: str) -> TaskSpec:
    """The declaration of ``env_id``; ValueError listing the registered ids otherwise."""
    spec = _SPECS.get(env_id) if isinstance(env_id, str) else None
    if spec is None:
        raise ValueError(f"env_id must be one of {tuple(_SPECS)}, got {env_id!r}")
    return spec


def spec_of_task(task: ParticleTask | gym.Env | VectorEnv) -> TaskSpec:
    """The declaration whose environments hold ``task`` (a task object, or a made env)."""
    task = getattr(getattr(task, "unwrapped", task), "task", task)
    for spec in _SPECS.values():
        if type(task) is spec.task_class:
            return spec
    raise ValueError(f"task: {type(task).__name__} belongs to no registered task")


def variant_key(env_kwargs: Mapping[str, Any]) -> str:
    """The canonical name of a configuration: its env keyword arguments as ``key=value``
    pairs, sorted by key and joined by commas (``""`` for none).

    >>> variant_key({"target": "swingup"}), variant_key({"b": 2, "a": 1.5}), variant_key({})
    ('target=swingup', 'a=1.5,b=2', '')
    """
    for k, v in env_kwargs.items():
        if not isinstance(v, (str, int, float, bool)) or "," in str(v) or "=" in str(k):
            raise ValueError(f"env_kwargs: a variant's values must be plain numbers or words, "
                             f"got {k}={v!r}")
    return ",".join(f"{k}={v}" for k, v in sorted(env_kwargs.items()))


def parse_variant(variant: str) -> dict[str, Any]:
    """The env keyword arguments of a :func:`variant_key` name (numbers read as numbers,
    ``true``/``false`` as booleans); ValueError naming the argument if it is malformed.

    >>> parse_variant("target=swingup"), parse_variant("a=1.5,b=2"), parse_variant("")
    ({'target': 'swingup'}, {'a': 1.5, 'b': 2}, {})
    """
    if not isinstance(variant, str):
        raise ValueError(f"variant must be a string 'key=value,...', got {variant!r}")
    out: dict[str, Any] = {}
    for part in filter(None, variant.split(",")):
        key, sep, text = part.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"variant must be 'key=value,...', got {variant!r}")
        value: Any = text
        if text in ("True", "False", "true", "false"):
            value = text.lower() == "true"
        else:
            for kind in (int, float):
                try:
                    value = kind(text)
                    break
                except ValueError:
                    pass
        out[key] = value
    return out


def check_env_kwargs(env_id: str, kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """``kwargs`` checked for ``env_id`` before any work: each key an argument its task
    declares (ValueError listing them otherwise; ``action_mode`` has an option of its own in
    the commands, so it is refused here), and the values accepted by making one env (its own
    ValueError naming the argument)."""
    from .checks import check_task_kwargs

    spec = task_spec(env_id)
    kwargs = dict(kwargs)
    if not kwargs:
        return kwargs
    if "action_mode" in kwargs:
        raise ValueError("action_mode: give it with --action-mode, not as an env keyword")
    check_task_kwargs(spec.task_class, kwargs, also=("obs_mode", "pixel_size",
                                                     "pixel_channels"))
    spec.env(**kwargs).close()
    return kwargs


def check_env_mode(env_id: str, action_mode: str | None) -> str:
    """The action mode to use (``None``: the env's default); ValueError naming the argument if
    ``env_id`` is not a registered id or does not take ``action_mode``."""
    modes = task_spec(env_id).action_modes
    if action_mode is None:
        return modes[0]
    if action_mode not in modes:
        raise ValueError(f"action_mode: {env_id} takes {' or '.join(modes)}, "
                         f"got {action_mode!r}")
    return action_mode


def overview_table(specs: tuple[TaskSpec, ...] | None = None) -> str:
    """The overview table of docs/environments.md (Markdown), made from the declarations
    (default: every registered task) and one env of each action mode: id, action modes, action
    spaces, observation size, integrator and physics steps per env step, version."""
    import gymnasium as gym

    rows = ["| id | action modes | action | observation | physics per env step | version |",
            "|---|---|---|---|---|---|"]
    for spec in task_specs() if specs is None else specs:
        made = [gym.make(spec.id, action_mode=m) for m in spec.action_modes]
        tasks = [env.unwrapped.task for env in made]
        modes = (f"`{spec.default_mode}` (the only one)" if len(spec.action_modes) == 1 else
                 ", ".join(f"`{m}`" + (" (default)" if k == 0 else "")
                           for k, m in enumerate(spec.action_modes)))
        shapes = [env.action_space.shape for env in made]
        action = f"`Box(-1, 1, {shapes[0]})`" + "".join(f" / `{s}`" for s in shapes[1:])
        obs = made[0].observation_space.shape
        t = tasks[0]
        physics = getattr(t, "physics_line", None) or (
            f"`{t.integrator}`, {t.substeps} x {1000 * t.dt:g} ms")
        rows.append(f"| `{spec.id}` | {modes} | {action} | "
                    f"{obs[0] if len(obs) == 1 else obs} floats | {physics} | "
                    f"v{spec.id.rsplit('-v', 1)[1]} |")
        for env in made:
            env.close()
    return "\n".join(rows) + "\n"

