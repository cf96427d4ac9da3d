"""Stable-Baselines3 on the native vector envs (envs.sb3.to_sb3) and the ``cparticles train`` /
``evaluate`` commands."""

import json
import sys

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3",
                    reason='needs the rl extra (pip install -e ".[rl]")')

import torch  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402

import envs  # noqa: E402
from cparticles import cli  # noqa: E402
from envs import pretrained  # noqa: E402
from envs.agents import make_agent  # noqa: E402
from envs.sb3 import to_sb3  # noqa: E402
from envs.task import parse_variant  # noqa: E402
from envs.train import load_hyperparams  # noqa: E402


def native(env_id="ClothSlide-v0", n=4, **kwargs):
    return to_sb3(gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                               **kwargs))


def dummy(env_id="ClothSlide-v0", n=4, **kwargs):
    return DummyVecEnv([lambda: gym.make(env_id, **kwargs) for _ in range(n)])


def test_to_sb3_matches_dummy_vec_env_over_episode_ends():
    """Same seeds, same actions: observations, rewards, dones, terminal observations and
    TimeLimit.truncated agree with SB3's own DummyVecEnv of single envs, over 300 steps with
    both successes (terminations) and time limits (truncations)."""
    n, steps = 4, 300
    a, b = native(n=n, max_episode_steps=80), dummy(n=n, max_episode_steps=80)
    assert a.seed(7) == b.seed(7)
    oa, ob = a.reset(), b.reset()
    np.testing.assert_allclose(oa, ob, atol=1e-6)
    scripted = make_agent("scripted", a.vector_env)
    rng = np.random.default_rng(0)
    kinds = {"terminated": 0, "truncated": 0}
    noise = np.array([0.0, 0.0, 1.0, 1.0])[:, None]  # copies 0, 1 succeed; 2, 3 time out
    for _ in range(steps):
        act = np.clip(scripted(oa) + noise * rng.normal(0, 1, (n, 2)), -1, 1).astype(np.float32)
        oa, ra, da, ia = a.step(act)
        ob, rb, db, ib = b.step(act)
        np.testing.assert_allclose(oa, ob, atol=1e-6)
        np.testing.assert_allclose(ra, rb, atol=1e-6)
        assert ra.dtype == rb.dtype and da.dtype == db.dtype
        np.testing.assert_array_equal(da, db)
        for i in range(n):
            assert ia[i]["TimeLimit.truncated"] == ib[i]["TimeLimit.truncated"]
            assert set(ia[i]) == set(ib[i])
            assert ia[i]["is_success"] == ib[i]["is_success"]
            if da[i]:
                np.testing.assert_allclose(ia[i]["terminal_observation"],
                                           ib[i]["terminal_observation"], atol=1e-6)
                kinds["truncated" if ia[i]["TimeLimit.truncated"] else "terminated"] += 1
    assert kinds["terminated"] >= 3 and kinds["truncated"] >= 3, kinds
    a.close()
    b.close()


def test_to_sb3_slider_crank_matches_and_env_checker_passes():
    from stable_baselines3.common.env_checker import check_env

    check_env(gym.make("SliderCrank-v0"), warn=True)
    a, b = native("SliderCrank-v0", n=3), dummy("SliderCrank-v0", n=3)
    a.seed(1), b.seed(1)
    np.testing.assert_allclose(a.reset(), b.reset(), atol=1e-6)
    rng = np.random.default_rng(1)
    for _ in range(30):
        act = rng.uniform(-1, 1, (3, 1)).astype(np.float32)
        oa, ra, _, _ = a.step(act)
        ob, rb, _, _ = b.step(act)
        np.testing.assert_allclose(oa, ob, atol=1e-6)
        np.testing.assert_allclose(ra, rb, atol=1e-6)


def test_to_sb3_vec_env_api():
    v = native(n=3, render_mode="rgb_array")
    assert v.num_envs == 3 and v.observation_space.shape == (145,)
    assert v.render_mode == "rgb_array"
    v.seed(0)
    v.reset()
    assert v.get_attr("num_envs") == [3, 3, 3]
    assert v.get_attr("max_episode_steps", indices=[0, 2]) == [200, 200]
    assert v.has_attr("task") and not v.has_attr("no_such_attribute")
    assert v.env_is_wrapped(gym.Wrapper) == [False] * 3
    v.set_attr("max_episode_steps", 100)
    assert v.vector_env.max_episode_steps == 100
    with pytest.raises(ValueError, match="all copies"):
        v.set_attr("max_episode_steps", 50, indices=[1])
    frame = v.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3
    assert len(v.get_images()) == 3
    # step_async / step_wait, and the reset infos of the copies
    v.step_async(np.zeros((3, 2), np.float32))
    obs, rew, done, info = v.step_wait()
    assert obs.shape == (3, 145) and rew.shape == (3,) and done.shape == (3,)
    assert len(v.reset_infos) == 3 and "distance" in v.reset_infos[0]
    # VecNormalize over it works (the wrapper train uses)
    norm = VecNormalize(v)
    norm.reset()
    assert norm.step(np.zeros((3, 2), np.float32))[0].shape == (3, 145)
    v.close()
    with pytest.raises(TypeError, match="VectorEnv"):
        to_sb3(gym.make("ClothSlide-v0"))


def test_ppo_trains_through_to_sb3():
    """A tiny PPO run on the native vector env: it learns (the policy changes) and predicts."""
    v = native(n=4)
    model = PPO("MlpPolicy", v, n_steps=64, batch_size=64, n_epochs=2, seed=0,
                policy_kwargs={"net_arch": [16]})
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(256)
    assert model.num_timesteps == 256
    after = list(model.policy.parameters())
    assert any(not np.allclose(x.numpy(), y.detach().numpy())
               for x, y in zip(before, after, strict=True))
    action, _ = model.predict(v.reset(), deterministic=True)
    assert action.shape == (4, 2)


# ----------------------------------------------------------------------------- rewards
def test_shipped_hyperparameters_cover_every_env_and_mode():
    """Every registered id in every action mode its env accepts (found by making it) has PPO
    and SAC hyperparameters; a mode the env refuses has none."""
    for env_id in envs.ENV_IDS:
        for mode in ("force", "spring", "draw"):
            try:
                gym.make(env_id, action_mode=mode).close()
                accepted = True
            except ValueError:
                accepted = False
            for algo in ("ppo", "sac"):
                if accepted:
                    hp = load_hyperparams(algo, env_id, mode)
                    assert hp["n_timesteps"] > 0 and hp["n_envs"] >= 1
                else:
                    with pytest.raises(ValueError, match="action_mode"):
                        load_hyperparams(algo, env_id, mode)
    with pytest.raises(ValueError, match="algo"):
        load_hyperparams("dqn", "ClothSlide-v0")


def test_train_without_algo_takes_the_tasks_shipped_algorithm(tmp_path, capsys, monkeypatch):
    """``--algo`` left out: the algorithm the task ships first for the mode (SAC for
    RopeStraighten, whose PPO settings learn on some seeds only), recorded in config.json;
    every task's default has settings for each mode that ships any."""
    for spec in envs.task_specs():
        for mode in spec.action_modes:
            algo = spec.default_algo(mode)
            if any(mode in table for table in spec.hyperparams.values()):
                assert load_hyperparams(algo, spec.id, mode)["n_timesteps"] > 0
    assert envs.task_spec("RopeStraighten-v0").default_algo() == "sac"
    assert envs.task_spec("ClothSlide-v0").default_algo() == "ppo"
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "run"
    assert cli.main(["train", "RopeStraighten-v0", "--seed", "1", "--out", str(out),
                     "--timesteps", "40", "--eval-freq", "40", "--eval-episodes", "1",
                     "--no-progress", "--hyperparams", "learning_starts=20"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "sac"
    assert config["hyperparams"]["gamma"] == 0.9
    capsys.readouterr()
    with pytest.raises(SystemExit):
        cli.main(["train", "RopeStraighten-v0", "--help"])
    assert "sac for RopeStraighten-v0" in " ".join(capsys.readouterr().out.split())


def test_a_shipped_sac_agent_keeps_the_actor_and_acts_as_its_run(tmp_path, capsys,
                                                                 monkeypatch):
    """``python -m envs.baselines ship RUN``: the run's data files and its held-out records
    (published.json) in a folder of the agents' root; a SAC policy without its critics, which
    then plays the same episodes with the same figures as the whole run."""
    from envs import baselines
    from envs.train import evaluate

    monkeypatch.setattr(sys, "argv", ["cparticles"])
    run = tmp_path / "SliderCrank-v0-force-sac-1"
    assert cli.main(["train", "SliderCrank-v0", "--algo", "sac", "--seed", "1", "--out",
                     str(run), "--timesteps", "64", "--eval-freq", "64", "--eval-episodes", "1",
                     "--no-progress", "--hyperparams", "learning_starts=32"]) == 0
    records = [{**res, "eval_episodes": res["episodes"], "eval_seed_start": res["seed_start"],
                "run": run.name}  # (the fields of a baselines record that ship reads)
               for res in (evaluate(run, episodes=3, seed_start=77, deterministic=d)
                           for d in (True, False))]
    results = tmp_path / "results.json"
    results.write_text(json.dumps(records))
    root = tmp_path / "agents"
    capsys.readouterr()
    assert baselines.main(["ship", str(run), "--results", str(results), "--root",
                           str(root)]) == 0
    folder = root / "SliderCrank-v0-force"
    assert capsys.readouterr().out.strip() == str(folder)
    assert [p.name for p in root.iterdir()] == [folder.name]  # (nothing half-written left)
    state = torch.load(folder / "policy.pt", weights_only=True)
    whole = torch.load(run / "policy.pt", weights_only=True)
    assert any(k.startswith("critic") for k in whole)
    assert sorted(state) == sorted(k for k in whole if k.startswith("actor."))
    published = json.loads((folder / "published.json").read_text())
    again = evaluate(folder, episodes=3, seed_start=77)
    for kind, rec in zip(("deterministic", "stochastic"), records, strict=True):
        assert published[kind]["mean_return"] == rec["mean_return"]
    assert (again["success_rate"], again["mean_return"]) == (
        records[0]["success_rate"], records[0]["mean_return"])
    (folder / "stale.txt").write_text("from the agent shipped before")
    assert baselines.main(["ship", str(run), "--results", str(results), "--root",
                           str(root)]) == 0  # (replaces it: the old folder moved aside first)
    assert [p.name for p in root.iterdir()] == [folder.name]
    assert not (folder / "stale.txt").exists() and (folder / "published.json").is_file()
    for argv in (["ship", str(tmp_path / "nothing"), "--results", str(results)],
                 ["ship", str(run), "--results", str(tmp_path / "none.json")]):
        with pytest.raises(SystemExit) as exc:
            baselines.main(argv)
        assert exc.value.code == 2
    results.write_text("[]")
    with pytest.raises(SystemExit):
        baselines.main(["ship", str(run), "--results", str(results), "--root", str(root)])
    assert "no stochastic record" in capsys.readouterr().err


def test_a_policy_and_value_function_apart_train_and_evaluate(tmp_path, capsys, monkeypatch):
    """``net_arch`` as ``{"pi": [...], "vf": [...]}`` (here a linear policy beside a small
    value network): trained, recorded in config.json, rebuilt by evaluate with its weights."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "run"
    arch = {"pi": [], "vf": [8]}
    assert cli.main(["train", "SliderCrank-v0", "--seed", "1", "--out", str(out),
                     "--timesteps", "512", "--eval-freq", "512", "--eval-episodes", "2",
                     "--no-progress", "--hyperparams",
                     "policy_kwargs=" + json.dumps({"net_arch": arch})]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["hyperparams"]["policy_kwargs"]["net_arch"] == arch
    state = torch.load(out / "policy.pt", weights_only=True)
    assert not any(k.startswith("mlp_extractor.policy_net") for k in state)  # (linear)
    assert state["action_net.weight"].shape == (1, 9)
    capsys.readouterr()
    assert cli.main(["evaluate", str(out), "--episodes", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["episodes"] == 2


def test_train_then_evaluate_cli(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "run"
    code = cli.main(["train", "SliderCrank-v0", "--algo", "ppo", "--seed", "3", "--out",
                     str(out), "--timesteps", "2048", "--eval-freq", "2048",
                     "--eval-episodes", "4", "--no-progress"])
    assert code == 0
    names = {"policy.pt", "normalization.npz", "config.json", "evaluations.json",
             "best_policy.pt", "best_normalization.npz", "progress.csv"}
    assert {p.name for p in out.iterdir()} == names  # data only: no pickles
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # (no partial directory left)
    config = json.loads((out / "config.json").read_text())
    assert config["format"] == 2 and config["normalized"] is True
    assert config["hyperparams"] == load_hyperparams("ppo", "SliderCrank-v0", "force")
    assert config["spaces"]["observation"]["shape"] == [9]
    assert config["timesteps"] == 2048 and config["seed"] == 3 and config["wall_seconds"] > 0
    capsys.readouterr()
    assert cli.main(["evaluate", str(out), "--episodes", "5", "--seed-start", "100",
                     "--stochastic", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    res = json.loads(lines[-1])
    assert {"success_rate", "mean_return", "mean_length", "episodes"} <= set(res)
    assert res["episodes"] == 5 and res["deterministic"] is False
    assert 0.0 <= res["success_rate"] <= 1.0 and 1 <= res["mean_length"] <= 200
    assert config["observation_shape"] == [9] and config["action_shape"] == [1]
    # a stochastic evaluation is seeded: the same figures again, whatever torch's global
    # generator holds (and left as it was)
    torch.manual_seed(12345)
    before = torch.rand(3)
    torch.manual_seed(12345)
    assert cli.main(["evaluate", str(out), "--episodes", "5", "--seed-start", "100",
                     "--stochastic", "--json"]) == 0
    assert torch.equal(torch.rand(3), before)
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again == res
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        cli.main(["evaluate", str(tmp_path / "nothing")])
    assert exc.value.code == 2


@pytest.mark.parametrize("key", sorted(pretrained.shipped()))
def test_every_shipped_agent_still_solves_its_task(key, capsys, monkeypatch):
    """A shipped agent keeps its published figure on the env as it is now: its deterministic
    success is at least 0.7 of the figure in its published.json (100 held-out episodes), on
    the first 10 of those episodes for an agent published at 90% or more, on all 100 for one
    below (10 episodes of a 45% agent hold 3 or 4 successes by chance alone) (a change to the
    task that breaks the agent fails here)."""
    env_id, mode, variant = key
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    more = ["--env-kwargs", *variant.split(",")] if variant else []
    published = json.loads((pretrained.shipped()[key] / "published.json").read_text())
    episodes = 10 if published["deterministic"]["success_rate"] >= 0.9 else 100
    assert cli.main(["evaluate", "--pretrained", env_id, "--action-mode", mode,
                     "--episodes", str(episodes), "--json", *more]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (res["env"], res["action_mode"], res["deterministic"]) == (env_id, mode, True)
    if variant:  # (the variant's own agent, on the variant)
        assert res["env_kwargs"] == parse_variant(variant)
    assert published["deterministic"]["eval_episodes"] == 100
    assert res["success_rate"] >= 0.7 * published["deterministic"]["success_rate"]


def test_pretrained_names_what_is_shipped(capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    for argv in (["evaluate", "--pretrained", "NoSuchEnv-v0"], ["evaluate"],
                 ["evaluate", "--pretrained", "ClothPin-v1", "--action-mode", "nope"],
                 ["evaluate", "somewhere", "--pretrained", "ClothPin-v1"]):
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert exc.value.code == 2
        assert "Traceback" not in capsys.readouterr().err


def test_a_shipped_agent_is_named_by_the_env_arguments_its_settings_do_not_give():
    """An agent's variant is the env keyword arguments it trained with beyond those of its
    mode's shipped settings: ClothFlatten's PPO settings observe every particle, so a run with
    them is the default configuration's agent, and one with two grippers too is that
    variant's; ChainSwing's swing-up is a variant."""
    def config(env, kwargs, algo="ppo", mode="pick_place"):
        return {"env": env, "algo": algo, "action_mode": mode,
                "hyperparams": {"env_kwargs": kwargs}}

    flat = envs.task_spec("ClothFlatten-v0").settings("ppo")["env_kwargs"]
    assert flat == {"obs_mode": "particles"}
    assert pretrained._variant(config("ClothFlatten-v0", flat)) == ""
    assert pretrained._variant(config("ClothFlatten-v0", {**flat, "num_grippers": 2})) \
        == "num_grippers=2"
    assert pretrained._variant(config("ClothFlatten-v0", {"obs_mode": "state"})) \
        == "obs_mode=state"
    assert pretrained._variant(config("ChainSwing-v0", {"target": "swingup"}, mode="force")) \
        == "target=swingup"
    assert pretrained._variant(config("ClothFlatten-v0", {})) == ""


@pytest.mark.parametrize("env_id, mode", [("ChainSwing-v0", "spring"), ("ClothPin-v1", None)])
def test_train_and_evaluate_the_newer_envs(env_id, mode, tmp_path, capsys, monkeypatch):
    """ChainSwing and ClothPin train and evaluate through the command line too (ClothPin in
    its only mode, draw, chosen when --action-mode is left out)."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "run"
    argv = ["train", env_id, "--seed", "1", "--out", str(out), "--timesteps", "2048",
            "--eval-episodes", "2", "--no-progress"]
    assert cli.main(argv + (["--action-mode", mode] if mode else [])) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["env"] == env_id and config["action_mode"] == (mode or "draw")
    capsys.readouterr()
    assert cli.main(["evaluate", str(out), "--episodes", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["env"] == env_id and res["episodes"] == 2


def test_train_takes_zoo_options_and_records_them(tmp_path, capsys, monkeypatch):
    """``--env-kwargs`` trains a variant (the swing-up) that ``evaluate`` plays again,
    ``--hyperparams`` overrides a setting, ``--n-envs`` the copies, ``--tensorboard-log``
    writes event files beside the CSV log in the run; config.json records all of it."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out, tb = tmp_path / "swing", tmp_path / "tb"
    assert cli.main(["train", "ChainSwing-v0", "--seed", "2", "--out", str(out), "--timesteps",
                     "512", "--eval-episodes", "2", "--no-progress", "--env-kwargs",
                     "target=swingup", "--hyperparams", "learning_rate=1e-4", "n_steps=64",
                     "batch_size=128",
                     "--n-envs", "4", "--tensorboard-log", str(tb), "--device", "cpu"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["overrides"] == {"learning_rate": 1e-4, "n_steps": 64, "batch_size": 128,
                                   "n_envs": 4,
                                   "env_kwargs": {"target": "swingup"}}
    hp = config["hyperparams"]
    assert hp["learning_rate"] == 1e-4 and hp["n_steps"] == 64 and hp["n_envs"] == 4
    assert config["timesteps"] == 512 and config["device"] == "cpu"  # (4 copies x 64 x 2)
    rows = (out / "progress.csv").read_text().splitlines()
    assert "train/learning_rate" in rows[0] and len(rows) >= 2
    events = list(tb.rglob("events.out.tfevents.*"))
    assert events and events[0].parent.name == "swing" and events[0].stat().st_size > 0
    capsys.readouterr()
    assert cli.main(["evaluate", str(out), "--episodes", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["env_kwargs"] == {"target": "swingup"}
    for argv, words in ((["--hyperparams", "learnin_rate=1e-4"], ["'learnin_rate'",
                                                                  "learning_rate"]),
                        (["--hyperparams", "policy=CnnPolicy"], ["policy", "CnnPolicy", "image"]),
                        (["--algo", "sac", "--hyperparams",  # (PPO's form given to SAC)
                          'policy_kwargs={"net_arch": {"pi": [], "vf": [8]}}'],
                         ["net_arch", "sac", "qf"]),
                        (["--algo", "sac", "--hyperparams",  # (a PPO-only policy argument)
                          'policy_kwargs={"ortho_init": false}'], ["ortho_init", "ppo"])):
        with pytest.raises(SystemExit) as exc:
            cli.main(["train", "SliderCrank-v0", "--out", str(tmp_path / "x"), *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and all(w in err for w in words), err
    assert not (tmp_path / "x").exists()


def test_train_decays_a_lin_setting_and_the_std_ceiling(tmp_path, capsys, monkeypatch):
    """``learning_rate=lin_<value>`` (rl-baselines3-zoo's notation) starts at ``value`` and
    decays linearly to 0 over the budget; config.json keeps the string. ``log_std_final``
    caps the final policy's log standard deviations. Any other string there, or a
    ``log_std_final`` not below ``log_std_init`` or for SAC, is refused before any work."""
    from envs.train_settings import LinearSchedule, schedule

    assert schedule("learning_rate", "lin_3e-4")(1.0) == pytest.approx(3e-4)
    assert schedule("clip_range", "lin_0.2")(0.25) == pytest.approx(0.05)
    assert schedule("learning_rate", 1e-4) == 1e-4 and schedule("gamma", "lin_1") == "lin_1"
    assert repr(LinearSchedule(1e-4)) == "lin_0.0001"
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "lin"
    assert cli.main(["train", "SliderCrank-v0", "--seed", "1", "--out", str(out), "--timesteps",
                     "512", "--eval-episodes", "1", "--no-progress", "--hyperparams",
                     "learning_rate=lin_1e-3", "n_steps=32", "batch_size=64",
                     "log_std_final=-2.5", "--n-envs", "4", "--device", "cpu"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["hyperparams"]["learning_rate"] == "lin_1e-3"
    assert config["hyperparams"]["log_std_final"] == -2.5
    log_std = torch.load(out / "policy.pt", weights_only=True)["log_std"]
    assert float(log_std.max()) <= -2.5 + 1e-6
    rows = (out / "progress.csv").read_text().splitlines()
    column = rows[0].split(",").index("train/learning_rate")
    rates = [float(r.split(",")[column]) for r in rows[1:] if r.split(",")[column]]
    assert len(rates) >= 2 and rates == sorted(rates, reverse=True) and rates[0] < 1e-3
    assert rates[-1] == pytest.approx(1e-3 / 4, rel=1e-6)  # (the last of 4 updates: 1/4 left)
    capsys.readouterr()
    for argv, words in [(["--hyperparams", f"learning_rate={bad}"], ["learning_rate", "lin_"])
                        for bad in ("lin_x", "lin_-1e-4", "cos_1e-4")] + [
            (["--hyperparams", "log_std_final=0"], ["log_std_final", "log_std_init"]),
            (["--algo", "sac", "--hyperparams", "log_std_final=-3"], ["log_std_final", "PPO"])]:
        with pytest.raises(SystemExit) as exc:
            cli.main(["train", "SliderCrank-v0", "--out", str(tmp_path / "x"), *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and all(w in err for w in words), err
    assert not (tmp_path / "x").exists()


def test_the_results_table_reads_right_for_one_seed_and_for_five():
    from envs.baselines import _median_cell, median_ci

    one = np.array([1.0])
    assert _median_cell(one, *median_ci(one)) == "100% (one seed: no interval)"
    five = np.array([0.4, 0.7, 0.14, 0.87, 0.49])
    assert _median_cell(five, *median_ci(five)) == "49% [14%, 87%] (94%)"


def test_median_interval_coverage_matches_the_binomial():
    from scipy.stats import binom

    from envs.baselines import median_ci

    low, high, cov = median_ci([0.9, 0.5, 1.0, 0.8, 0.7])  # 5 seeds: [min, max]
    assert (low, high) == (0.5, 1.0) and cov == pytest.approx(1 - 2 * binom.cdf(0, 5, 0.5))
    x = np.arange(10.0)  # 10 seeds: [x_(2), x_(9)], the narrowest with coverage >= 95%
    low, high, cov = median_ci(x)
    assert (low, high) == (1.0, 8.0) and cov == pytest.approx(1 - 2 * binom.cdf(1, 10, 0.5))
    assert 1 - 2 * binom.cdf(2, 10, 0.5) < 0.95 <= cov


def test_the_stored_statistics_normalize_as_vec_normalize_does(tmp_path):
    from envs.train import ObsNormalizer, save_normalization

    vn = VecNormalize(native("SliderCrank-v0", n=4), norm_reward=False)
    vn.reset()
    rng = np.random.default_rng(0)
    for _ in range(30):
        vn.step(rng.uniform(-1, 1, (4, 1)).astype(np.float32))
    save_normalization(vn, tmp_path / "n.npz")
    mine = ObsNormalizer.load(tmp_path / "n.npz", (9,))
    obs = rng.normal(0, 3, (50, 9)).astype(np.float32)
    np.testing.assert_array_equal(mine.normalize_obs(obs), vn.normalize_obs(obs))
    assert mine.normalize_obs(obs).dtype == np.float32
    with pytest.raises(ValueError, match="mean"):
        ObsNormalizer.load(tmp_path / "n.npz", (145,))


def test_convert_run_makes_an_old_directory_evaluate_the_same(tmp_path, capsys, monkeypatch):
    """A run directory as the older train wrote it (model.zip, vecnormalize.pkl and their
    best_ twins, a config.json without "format"): refused by evaluate, converted by
    convert-run (which says it loads the pickles), then evaluated with the results of the
    pickled model itself."""
    from envs.train import read_run, run_episodes, sb3_policy, summarize

    monkeypatch.setattr(sys, "argv", ["cparticles"])
    run = tmp_path / "run"
    run.mkdir()
    hp = load_hyperparams("ppo", "SliderCrank-v0", "force")
    venv = VecNormalize(native("SliderCrank-v0", n=4), norm_reward=False)
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=64, seed=0, device="cpu",
                policy_kwargs=hp["policy_kwargs"])
    model.learn(128)
    for prefix in ("", "best_"):
        model.save(run / f"{prefix}model.zip")
        venv.save(str(run / f"{prefix}vecnormalize.pkl"))
    old = {"env": "SliderCrank-v0", "action_mode": "force", "algo": "ppo", "seed": 0,
           "timesteps": 128, "hyperparams": hp, "observation_shape": [9], "action_shape": [1]}
    (run / "config.json").write_text(json.dumps(old))
    with pytest.raises(SystemExit) as exc:
        cli.main(["evaluate", str(run)])
    assert exc.value.code == 2 and "convert-run" in capsys.readouterr().err
    assert cli.main(["convert-run", str(run)]) == 0
    io = capsys.readouterr()
    assert "trusted" in io.err and "policy.pt" in io.out
    assert read_run(run)["format"] == 2 and (run / "config.v1.json").is_file()
    assert cli.main(["evaluate", str(run), "--episodes", "6", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    want = summarize(run_episodes(sb3_policy(model, venv), "SliderCrank-v0", 6, 2_000_000))
    assert {k: res[k] for k in want} == want
    with pytest.raises(SystemExit):  # (converted once: nothing more to convert)
        cli.main(["convert-run", str(run)])
    assert "already of format 2" in capsys.readouterr().err


def test_a_train_that_fails_leaves_no_run_directory(tmp_path, capsys, monkeypatch):
    """A full disk while the weights are written: one error line, exit status 1, and neither
    the run directory nor its partial twin is left."""
    import errno

    from envs import train

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "x"))

    monkeypatch.setattr(sys, "argv", ["cparticles"])
    monkeypatch.setattr(train, "save_policy", full)
    out = tmp_path / "run"
    code = cli.main(["train", "SliderCrank-v0", "--out", str(out), "--timesteps", "256",
                     "--eval-freq", "256", "--eval-episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert [line for line in err.splitlines() if "error" in line] == [
        f"cparticles train: error: No space left on device: {tmp_path / 'x'}"], err
    assert list(tmp_path.iterdir()) == []


def test_a_sac_policy_is_rebuilt_from_its_settings(tmp_path):
    """SAC (whose constructor writes use_sde into policy_kwargs): weights saved as train saves
    them evaluate as the model itself does, and train records the settings it was given."""
    from stable_baselines3 import SAC

    from envs.train import (
        FORMAT,
        evaluate,
        run_episodes,
        save_policy,
        sb3_policy,
        space_record,
        summarize,
    )

    hp = load_hyperparams("sac", "SliderCrank-v0", "force")
    env = gym.make("SliderCrank-v0")
    model = SAC("MlpPolicy", env, seed=1, device="cpu", **{
        k: v for k, v in json.loads(json.dumps(hp)).items()
        if k in ("policy_kwargs", "learning_rate", "buffer_size", "gamma")})
    run = tmp_path / "run"
    run.mkdir()
    save_policy(model, run / "policy.pt")
    config = {"format": FORMAT, "env": "SliderCrank-v0", "action_mode": "force", "algo": "sac",
              "seed": 1, "timesteps": 0, "hyperparams": {**hp, "policy_kwargs": {
                  **hp["policy_kwargs"], "use_sde": False}},
              "spaces": {"observation": space_record(env.observation_space),
                         "action": space_record(env.action_space)}, "normalized": False}
    (run / "config.json").write_text(json.dumps(config))
    res = evaluate(run, episodes=3)
    want = summarize(run_episodes(sb3_policy(model), "SliderCrank-v0", 3, 2_000_000))
    assert {k: res[k] for k in want} == want


def test_sac_with_hindsight_relabelling_runs_on_goal_observations():
    """SB3's HerReplayBuffer takes the goal mode as it takes Gymnasium-Robotics' tasks: SAC
    trains through it, and the rewards of relabelled samples are the env's compute_reward of
    their goals (an integration check, not a learning curve)."""
    from stable_baselines3 import SAC, HerReplayBuffer

    env = gym.make("SliderCrank-v0", obs_mode="goal", max_episode_steps=40)
    model = SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer,
                replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
                learning_starts=64, batch_size=32, seed=0,
                policy_kwargs={"net_arch": [16, 16]})
    model.learn(96)
    batch = model.replay_buffer.sample(64)
    obs = batch.next_observations
    expected = env.unwrapped.compute_reward(obs["achieved_goal"].numpy(),
                                            obs["desired_goal"].numpy(), {})
    assert np.array_equal(batch.rewards.numpy().ravel(), expected.astype(np.float32))


def _evaluate_replays_the_last_periodic_evaluation(out, capsys):
    """``evaluate`` on the first periodic-evaluation seed gives the return the run's last
    periodic evaluation (one episode, the final model) recorded: the policy is rebuilt and fed
    as in training."""
    last = json.loads((out / "evaluations.json").read_text())[-1]
    capsys.readouterr()
    assert cli.main(["evaluate", str(out), "--episodes", "1", "--seed-start", "1000000",
                     "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["mean_return"] == pytest.approx(last["mean_return"], abs=1e-9)


def test_a_cnn_policy_trains_on_pixels_and_evaluates_the_same(tmp_path, capsys, monkeypatch):
    """``obs_mode=pixels`` trains SB3's CnnPolicy (images channel-first for torch, rewards
    normalized, pixels not); ``evaluate`` rebuilds it from the weights and plays the final
    periodic evaluation's episode again with the same return; an MLP on images is refused
    before any work."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "cnn"
    assert cli.main(["train", "ClothSlide-v0", "--seed", "3", "--out", str(out),
                     "--timesteps", "256", "--eval-episodes", "1", "--eval-freq", "100000",
                     "--no-progress", "--env-kwargs", "obs_mode=pixels", "pixel_size=40",
                     "--hyperparams", "policy=CnnPolicy", "n_steps=32", "batch_size=64",
                     "--n-envs", "4"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["hyperparams"]["policy"] == "CnnPolicy"
    assert config["spaces"]["observation"]["shape"] == [40, 40, 3]
    assert config["spaces"]["observation"]["dtype"] == "uint8"
    _evaluate_replays_the_last_periodic_evaluation(out, capsys)
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", "ClothSlide-v0", "--out", str(tmp_path / "x"), "--env-kwargs",
                  "obs_mode=pixels"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "CnnPolicy" in err and "image" in err, err
    assert not (tmp_path / "x").exists()


def test_baselines_keep_a_variant_apart_from_the_default(tmp_path, capsys):
    """A variant's records (ChainSwing's swing-up) merge beside the default configuration's,
    its runs are named apart, its rows are labelled in the table; a keyword argument the env
    does not take is refused before any work."""
    pytest.importorskip("matplotlib")
    from envs.baselines import main, merge, report, run_name

    assert run_name("ChainSwing-v0", "force", "ppo", 0) == "ChainSwing-v0-force-ppo-0"
    assert (run_name("ChainSwing-v0", "force", "ppo", 0, "target=swingup")
            == "ChainSwing-v0-target-swingup-force-ppo-0")

    def rec(variant, seed, success):
        return {"env": "ChainSwing-v0", **({"variant": variant} if variant else {}),
                "action_mode": "force", "algo": "ppo", "seed": seed, "deterministic": True,
                "timesteps": 1000, "success_rate": success, "mean_return": 1.0,
                "wall_seconds": 60.0, "run": run_name("ChainSwing-v0", "force", "ppo", seed,
                                                      variant)}

    path = tmp_path / "results.json"
    merge(path, [rec("", 0, 1.0), rec("target=swingup", 0, 0.5)])
    merged = merge(path, [rec("target=swingup", 0, 0.25)])  # (replaces the variant's only)
    assert sorted(r["success_rate"] for r in merged) == [0.25, 1.0]
    table = report(path, tmp_path, tmp_path)
    rows = [line for line in table.splitlines() if line.startswith("| ChainSwing")]
    assert len(rows) == 2 and any("ChainSwing-v0 (target=swingup)" in r and "25%" in r
                                  for r in rows)
    with pytest.raises(SystemExit) as exc:
        main(["run", "--runs", str(tmp_path / "runs"), "--envs", "ChainSwing-v0",
              "--variants", "targt=swingup"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "'targt'" in err and "target" in err, err
    assert not (tmp_path / "runs" / "results.json").exists()


def test_stacked_frames_are_vec_frame_stacks():
    """``stack_frames`` holds what SB3's ``VecFrameStack`` hands the policy over an episode
    (zeros before the first frame, oldest first along the channels)."""
    from stable_baselines3.common.vec_env import VecFrameStack

    from envs.train import stack_frames

    venv = VecFrameStack(native(n=2, obs_mode="pixels", pixel_size=16), 3,
                         channels_order="last")
    venv.seed(5)
    theirs = venv.reset()
    mine = stack_frames(None, theirs[..., -3:], 3)  # (the first frame, last)
    assert np.array_equal(mine, theirs) and not theirs[..., :6].any() and theirs.any()
    rng = np.random.default_rng(0)
    for _ in range(4):
        theirs, _, dones, _ = venv.step(rng.uniform(-1, 1, (2, 2)).astype(np.float32))
        assert not dones.any()
        mine = stack_frames(mine, theirs[..., -3:], 3)
        assert np.array_equal(mine, theirs)


def test_a_cnn_on_stacked_frames_evaluates_as_it_trained(tmp_path, capsys, monkeypatch):
    """``frame_stack`` (rl-baselines3-zoo's key) trains on ``VecFrameStack`` and evaluates
    with the same stacks: the final periodic evaluation's episode plays again with its
    return."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "stack"
    assert cli.main(["train", "ChainSwing-v0", "--seed", "3", "--out", str(out),
                     "--timesteps", "128", "--eval-episodes", "1", "--eval-freq", "100000",
                     "--no-progress", "--env-kwargs", "obs_mode=pixels", "pixel_size=36",
                     "--hyperparams", "policy=CnnPolicy", "frame_stack=3",
                     "n_steps=16", "batch_size=32", "--n-envs", "4"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["spaces"]["observation"]["shape"] == [36, 36, 3]  # (9 channels stacked)
    assert config["hyperparams"]["frame_stack"] == 3
    assert config["normalized"] is False  # (rewards only: images are not normalized)
    _evaluate_replays_the_last_periodic_evaluation(out, capsys)
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", "ChainSwing-v0", "--out", str(tmp_path / "x"),
                  "--hyperparams", "frame_stack=0"])
    assert exc.value.code == 2 and "frame_stack" in capsys.readouterr().err


def test_the_noise_is_held_until_a_success_rate_then_its_ceiling_falls_over_the_rest():
    """``explore_until_success`` (a rate r): until r of the last 100 ended training episodes
    succeeded, the policy's log standard deviations are kept at least ``log_std_init`` (a
    gradient that shrank them is undone) and not capped, whatever a few lucky episodes did;
    from the step t0 where the rate is reached the ceiling falls linearly from
    ``log_std_init`` at t0 to ``log_std_final`` at the end of the budget; the final policy is
    capped whatever happened. It is refused without ``log_std_final`` or outside (0, 1]."""
    from types import SimpleNamespace

    from envs.train_settings import EXPLORE_WINDOW, check_explore, std_ceiling

    log_std = torch.full((2,), -1.0)
    model = SimpleNamespace(policy=SimpleNamespace(log_std=log_std), num_timesteps=0,
                            get_env=lambda: None, logger=None)
    cb = std_ceiling(-1.0, -3.0, 1000, hold_until=0.2)
    cb.init_callback(model)

    def rollout(steps: int, wins: int, episodes: int) -> None:
        """A rollout at ``steps`` in which ``episodes`` episodes end, the first ``wins`` of
        them in success (two copies: the other copy's episode never ends)."""
        model.num_timesteps = steps
        cb.on_rollout_start()
        for k in range(episodes):
            cb.update_locals({"dones": np.array([False, True]),
                              "infos": [{"is_success": True}, {"is_success": k < wins}]})
            cb.on_step()

    log_std.fill_(-2.0)  # (the gradient shrank it: held up again)
    rollout(100, wins=5, episodes=5)  # (lucky: 5 of 5, but the window is not full)
    assert torch.all(log_std == -1.0)
    log_std.fill_(0.5)  # (no ceiling while held)
    rollout(200, wins=10, episodes=EXPLORE_WINDOW)  # (15 of the last 100: below 20%)
    assert torch.all(log_std == 0.5)
    rollout(600, wins=20, episodes=EXPLORE_WINDOW)  # (20 of 100: the ceiling falls from 600)
    log_std.fill_(0.5)
    rollout(800, wins=0, episodes=1)  # (half-way from 600 to 1000)
    assert torch.allclose(log_std, torch.tensor(-2.0))
    log_std.fill_(-2.5)  # (below the ceiling: left alone, no floor any more)
    rollout(900, wins=0, episodes=1)
    assert torch.all(log_std == -2.5)
    model.num_timesteps = 950
    log_std.fill_(0.0)
    cb.on_training_end()
    assert torch.all(log_std == -3.0)
    # without the hold, as before: the ceiling falls from step 0
    plain = std_ceiling(-1.0, -3.0, 1000)
    plain.init_callback(model)
    log_std.fill_(0.0)
    model.num_timesteps = 500
    plain.on_rollout_start()
    assert torch.allclose(log_std, torch.tensor(-2.0))
    assert check_explore("ppo", {"log_std_final": -3.0, "explore_until_success": 0.2,
                                 "policy_kwargs": {"log_std_init": -1.0}}) == 0.2
    assert check_explore("ppo", {}) == 0.0
    for hp, word in (({"explore_until_success": 0.2}, "log_std_final"),
                     ({"explore_until_success": True, "log_std_final": -3.0}, r"\(0, 1\]"),
                     ({"explore_until_success": 1.5, "log_std_final": -3.0}, r"\(0, 1\]")):
        with pytest.raises(ValueError, match=word):
            check_explore("ppo", hp)


# ----------------------------------------------------------------------------- imitation
@pytest.mark.parametrize("hp, algo", [
    ({"imitate": -1}, "ppo"), ({"imitate": 1.5}, "ppo"), ({"imitate": True}, "ppo"),
    ({"imitate": 100}, "sac"), ({"imitate": 100, "normalize": True}, "ppo"),
    ({"imitate": 100, "frame_stack": 2}, "ppo"),
    ({"imitate": 100, "policy": "CnnPolicy"}, "ppo"),
    ({"imitate": 100, "imitate_noise": -0.1}, "ppo"),
    ({"imitate": 100, "imitate_noise": 1.5}, "ppo"),
    ({"imitate": 100, "imitate_noise": "0.1"}, "ppo"),
    ({"imitate": 100, "imitate_updates": 0}, "ppo"),
    ({"imitate": 100, "imitate_updates": 2.0}, "ppo")])
def test_bad_imitation_settings_are_value_errors_naming_the_key(hp, algo):
    from envs.train_settings import check_imitate

    with pytest.raises(ValueError, match="imitate"):
        check_imitate(algo, hp)
    assert check_imitate("ppo", {}) == (0, 0.1, 15000)
    assert check_imitate("ppo", {"imitate": 64}) == (64, 0.1, 15000)
    assert check_imitate("ppo", {"imitate": 64, "imitate_noise": 0, "imitate_updates": 9,
                                 "policy": "PointerPolicy"}) == (64, 0.0, 9)
    # (unused without imitate: a task's settings with them train from scratch with imitate=0)
    flat = {**envs.task_spec("ClothFlatten-v0").settings("ppo"), "imitate": 0}
    assert check_imitate("ppo", flat) == (0, 0.003, 2000)


def scripted_steps(env_id: str, steps: int, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """The observations and the scripted agent's actions over ``steps`` steps of 8 copies of
    ``env_id`` seeded 12345 (episodes no imitation in these tests records)."""
    probe = gym.make_vec(env_id, num_envs=8, vectorization_mode="vector_entry_point", **kwargs)
    agent = make_agent("scripted", probe)
    obs, _ = probe.reset(seed=12345)
    seen, acts = [], []
    for _ in range(steps):
        a = agent(obs)
        seen.append(obs)
        acts.append(a)
        obs, *_ = probe.step(a)
    return np.concatenate(seen), np.concatenate(acts)


def test_imitation_clones_the_scripted_agent_and_fits_the_critic(monkeypatch):
    """imitate_scripted on ClothFold in drag mode (fewer updates than shipped): the policy's
    mean moves from far off the scripted agent's actions to near them, on states of other
    episodes than those it learnt from, and the value function ends closer to the clone's
    discounted returns than the constant that fits them best does."""
    from envs import train_settings as T

    monkeypatch.setattr(T, "IMITATE_POLICY_UPDATES", 1500)
    monkeypatch.setattr(T, "IMITATE_VALUE_UPDATES", 1500)
    monkeypatch.setattr(T, "IMITATE_VALUE_STEPS", 640)
    venv = native("ClothFold-v0", n=2, action_mode="drag")
    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, seed=3, gamma=0.95,
                policy_kwargs={"net_arch": [64, 64]})
    x, y = scripted_steps("ClothFold-v0", 12, action_mode="drag")

    def error() -> float:
        with torch.no_grad():
            mean = model.policy.get_distribution(torch.as_tensor(x)).distribution.mean
        return float(((np.clip(mean.numpy(), -1, 1) - y) ** 2).mean())

    before = error()
    out = T.imitate_scripted(model, "ClothFold-v0", "drag", {}, 3, 4000)
    after = error()
    assert after < 0.5 * before, (before, after)
    assert out["policy_mse"] < 0.2 and np.isfinite(out["clone_return"])
    # (the constant that fits the returns best leaves their variance)
    assert out["value_mse"] < 1.0 + 0.5 * abs(out["clone_return"]) ** 2


def test_imitation_teaches_the_pointer_policy_which_particle_to_move(monkeypatch):
    """imitate_scripted with a PointerPolicy on ClothFlatten (every particle and where it
    belongs observed; fewer updates than shipped): by maximum likelihood, the clone's likeliest
    particle becomes the scripted agent's (the one furthest from its place) on states of other
    episodes, far more often than the untrained scores do."""
    from envs import train_settings as T
    from envs.policies import PointerPolicy

    monkeypatch.setattr(T, "IMITATE_VALUE_UPDATES", 200)
    monkeypatch.setattr(T, "IMITATE_VALUE_STEPS", 320)
    kwargs = {"obs_mode": "particles"}
    venv = native("ClothFlatten-v0", n=2, **kwargs)
    model = PPO(PointerPolicy, venv, n_steps=16, batch_size=32, seed=3,
                policy_kwargs={"points": 81, "log_std_init": -5.0})
    x, y = scripted_steps("ClothFlatten-v0", 10, **kwargs)

    def agreement() -> float:
        with torch.no_grad():
            mode = model.policy.get_distribution(torch.as_tensor(x)).mode().numpy()
        return float(np.mean(np.abs(mode - y).max(axis=1) < 1e-4))

    before = agreement()
    out = T.imitate_scripted(model, "ClothFlatten-v0", "pick_place", kwargs, 3, 3000, 0.003,
                             600)
    after = agreement()
    assert after > 0.7 and after > before + 0.5, (before, after)
    assert set(out) == {"policy_nll", "value_mse", "clone_return"}
    assert np.isfinite(out["policy_nll"]) and np.isfinite(out["clone_return"])


def test_train_records_the_imitation(tmp_path, monkeypatch):
    """``--hyperparams imitate=N``: the run starts from the clone and config.json records the
    setting and the clone's fit."""
    from envs import train_settings as T

    monkeypatch.setattr(T, "IMITATE_POLICY_UPDATES", 20)
    monkeypatch.setattr(T, "IMITATE_VALUE_UPDATES", 20)
    monkeypatch.setattr(T, "IMITATE_VALUE_STEPS", 32)
    monkeypatch.setattr(sys, "argv", ["cparticles"])
    out = tmp_path / "run"
    assert cli.main(["train", "ClothFold-v0", "--action-mode", "drag", "--seed", "1", "--out",
                     str(out), "--timesteps", "64", "--eval-freq", "64", "--eval-episodes",
                     "1", "--no-progress", "--hyperparams", "imitate=64", "n_envs=2",
                     "n_steps=32", "batch_size=32"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["hyperparams"]["imitate"] == 64 and config["overrides"]["imitate"] == 64
    assert set(config["imitation"]) == {"policy_mse", "value_mse", "clone_return"}
