"""Pretrained agents shipped with the package: ``cparticles evaluate --pretrained ENV_ID``.

Each agent is a run directory of ``cparticles train`` kept under ``envs/pretrained/`` (the
folder is named ``<env id>-<action mode>``, with a variant's keyword arguments between the
two as the baselines' run directories have them: ``ChainSwing-v0-target-swingup-force``):
``config.json`` (the run's settings, JSON), ``policy.pt`` (the policy's weights, a PyTorch
state dict of tensors read with ``weights_only``) and, when the run normalized its
observations, ``normalization.npz`` (plain arrays). Loading one runs no code stored in it, as
for any run directory (:func:`envs.train.evaluate`); ``evaluations.json`` keeps the run's
periodic evaluations and ``published.json`` its figures on 100 held-out episodes (seeds from
2,000,000), deterministic and stochastic, as the baselines table gives them.

>>> from envs.pretrained import shipped
>>> all(path.is_dir() for path in shipped().values())
True
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

#: The folder holding the shipped run directories.
ROOT = Path(__file__).with_name("pretrained")


def _variant(config: dict) -> str:
    """The variant (:func:`envs.task.variant_key` form, ``""`` for the default
    configuration) a run's ``config.json`` trained on: its env keyword arguments but those
    its action mode's shipped settings give themselves (ClothFlatten's PPO settings observe
    every particle: a run with them plays the default configuration)."""
    from .task import task_spec, variant_key

    kwargs = config.get("hyperparams", {}).get("env_kwargs", {})
    if not isinstance(kwargs, dict):
        return ""
    try:
        own = task_spec(str(config.get("env"))).hyperparams.get(
            str(config.get("algo")), {}).get(str(config.get("action_mode")), {}).get(
            "env_kwargs", {})
    except ValueError:  # (a task not registered here)
        own = {}
    try:
        return variant_key({k: v for k, v in kwargs.items() if own.get(k, object()) != v})
    except ValueError:
        return ""


def shipped() -> dict[tuple[str, str, str], Path]:
    """The shipped agents: ``{(env id, action mode, variant): run directory}`` (``variant``:
    the env keyword arguments it trained with as :func:`envs.task.variant_key` writes them,
    ``""`` for the default configuration), read from each folder's ``config.json`` (folders
    without one, and hidden ones, are ignored)."""
    found: dict[tuple[str, str, str], Path] = {}
    if not ROOT.is_dir():
        return found
    for folder in sorted(ROOT.iterdir()):
        config = folder / "config.json"
        if folder.name.startswith(".") or not config.is_file():
            continue  # (hidden: one :func:`ship` is still writing)
        with open(config, encoding="utf-8") as f:
            data = json.load(f)
        found[(str(data.get("env")), str(data.get("action_mode")), _variant(data))] = folder
    return found


def pretrained_dir(env_id: str, action_mode: str | None = None, variant: str = "") -> Path:
    """The run directory of the shipped agent for ``env_id`` in ``action_mode`` (default: the
    env's default mode if an agent is shipped for it, else its only shipped mode) trained on
    ``variant`` (``"target=swingup"``; default ``""``, the default configuration). ValueError
    naming the argument, with what is shipped, when there is none."""
    agents = shipped()
    modes = [mode for (env, mode, v) in agents if env == env_id and v == variant]
    if not modes:
        have = ", ".join(describe(k) for k in agents) or "none"
        what = f"{env_id!r}" + (f" with {variant}" if variant else "")
        raise ValueError(f"env_id: no pretrained agent is shipped for {what} "
                         f"(shipped: {have})")
    if action_mode is None:
        from .task import task_spec

        try:
            default = task_spec(env_id).action_modes[0]
        except ValueError:
            default = modes[0]
        action_mode = default if default in modes else modes[0]
    if (env_id, action_mode, variant) not in agents:
        raise ValueError(f"action_mode: no pretrained agent for {env_id!r} in mode "
                         f"{action_mode!r} (shipped modes: {', '.join(modes)})")
    return agents[(env_id, action_mode, variant)]


def describe(key: tuple[str, str, str]) -> str:
    """``"ChainSwing-v0 (force, target=swingup)"`` for a key of :func:`shipped`."""
    env, mode, variant = key
    return f"{env} ({mode}{', ' + variant if variant else ''})"


#: What a shipped agent keeps of its run directory (``normalization.npz`` when the run has it;
#: ``policy.pt`` of a SAC run without its critics, which acting does not use).
KEPT = ("config.json", "evaluations.json", "normalization.npz", "policy.pt")


def ship(run: str | Path, results: str | Path, root: str | Path = ROOT) -> Path:
    """Keep the run directory ``run`` as the shipped agent of its env, action mode and
    variant: its :data:`KEPT` files and ``published.json`` (its deterministic and stochastic
    records in the baselines' ``results`` file: success, return, length, episodes, first
    seed) go to ``root/<env>-[<variant>-]<mode>``, replacing the agent shipped there. Returns
    that folder; ValueError naming the argument if ``run`` is no complete run or ``results``
    holds no records of it."""
    import torch

    from .baselines import run_name
    from .train import CRITIC_KEYS, read_run

    run = Path(run)
    try:
        config = read_run(run)
    except (OSError, ValueError) as exc:
        raise ValueError(f"run: {exc}") from None
    try:
        with open(results, encoding="utf-8") as f:
            records = [r for r in json.load(f) if isinstance(r, dict) and r.get("run") == run.name]
    except (OSError, ValueError) as exc:
        raise ValueError(f"results: cannot read {str(results)!r} ({exc})") from None
    fields = ("success_rate", "mean_return", "mean_length", "eval_episodes", "eval_seed_start")
    published = {}
    for kind, deterministic in (("stochastic", False), ("deterministic", True)):
        found = [r for r in records if r.get("deterministic") is deterministic
                 and all(k in r for k in fields)]
        if not found:
            raise ValueError(f"results: no {kind} record of run {run.name!r} in {str(results)!r}")
        published[kind] = {k: found[-1][k] for k in fields}
    variant = _variant(config)
    name = run_name(config["env"], config["action_mode"], config["algo"], config["seed"],
                    variant).rsplit("-", 2)[0]
    folder = Path(root) / name
    new = Path(root) / f".{name}.partial"  # (written whole, then put in place)
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir(parents=True)
    for file in KEPT:
        if file == "policy.pt" and config["algo"] == "sac":
            state = torch.load(run / file, map_location="cpu", weights_only=True)
            torch.save({k: v for k, v in state.items() if not k.startswith(CRITIC_KEYS)},
                       new / file)
        elif (run / file).is_file():
            shutil.copyfile(run / file, new / file)
    (new / "published.json").write_text(json.dumps(published, indent=1) + "\n",
                                        encoding="utf-8")
    old = Path(root) / f".{name}.replaced"  # (the agent shipped before, until the new one
    shutil.rmtree(old, ignore_errors=True)  # is in place: an agent is always there)
    if folder.exists():
        folder.rename(old)
    new.rename(folder)
    shutil.rmtree(old, ignore_errors=True)
    return folder
