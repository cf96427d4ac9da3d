"""The ``cparticles`` command line: ``run``'s table, and for every subcommand its help, its
exit codes and its checks of user mistakes (exit 2, one ``error:`` line, never a traceback)."""

import json
import sys

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
from constrained_particles import METHODS
from constrained_particles.arguments import progress_enabled
from cparticles import cli


@pytest.fixture(autouse=True)
def keep_argv(monkeypatch):
    """``cli.main`` rewrites sys.argv (to pick the subcommand to import); restore it after."""
    monkeypatch.setattr(sys, "argv", ["cparticles"])


def table(out: str) -> np.ndarray:
    """The numeric rows of a ``run`` table: t, energy, max|C|, max|Cdot|."""
    rows = []
    for line in out.splitlines():
        try:
            rows.append([float(word) for word in line.split()])
        except ValueError:  # the title and header lines
            continue
    return np.array(rows)


def test_run_prints_a_table(capsys):
    assert cli.main(["run", "wire_mixture", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    header = [line for line in out.splitlines() if "t [s]" in line]
    assert len(header) == 1 and "energy" in header[0] and "max|C|" in header[0]
    assert out.startswith("# wire_mixture")
    rows = table(out)
    assert rows.shape[1] == 4
    np.testing.assert_allclose(rows[:, 0], [0.0, 0.2])  # default --every 0.5 s: start and end
    assert np.all(rows[:, 2] < 1e-6) and np.all(rows[:, 3] < 1e-6)
    assert np.ptp(rows[:, 1]) < 1e-4 * abs(rows[0, 1])  # undamped: energy kept


def test_run_rows_every_and_projection(capsys):
    code = cli.main(["run", "pendulum", "--seconds", "0.1", "--every", "0.025", "--dt", "0.005",
                     "--method", "midpoint", "--project"])
    assert code == 0
    out = capsys.readouterr().out
    assert "method=midpoint" in out and "projection=on" in out
    rows = table(out)
    np.testing.assert_allclose(rows[:, 0], np.arange(0.0, 0.1001, 0.025))
    assert np.all(rows[:, 2] < 1e-9)


def usage_error(argv: list[str], capsys) -> str:
    """Run ``cparticles argv``; it must stop in argparse with exit status 2 and one clean
    ``error:`` line (no traceback). Returns stderr."""
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert sum("error:" in line for line in err.splitlines()) == 1
    return err


@pytest.mark.parametrize("option, value", [
    ("--dt", "0"), ("--dt", "-0.01"), ("--dt", "nan"), ("--dt", "inf"), ("--dt", "1e-310"),
    ("--dt", "10"), ("--dt", "abc"), ("--seconds", "inf"), ("--seconds", "0"),
    ("--every", "inf"), ("--every", "-1")])
def test_bad_run_numbers_are_usage_errors(option, value, capsys):
    err = usage_error(["run", "wire_mixture", "--seconds", "0.2", f"{option}={value}"]
                      if option != "--seconds" else ["run", "wire_mixture", f"{option}={value}"],
                      capsys)
    assert option in err


def test_too_many_steps_is_a_usage_error(capsys):
    err = usage_error(["run", "pendulum", "--dt", "1e-9", "--seconds", "100"], capsys)
    assert "steps" in err


def test_dt_equal_to_seconds_runs_one_step(capsys):
    assert cli.main(["run", "pendulum", "--dt", "0.01", "--seconds", "0.01"]) == 0
    np.testing.assert_allclose(table(capsys.readouterr().out)[:, 0], [0.0, 0.01])


@pytest.mark.parametrize("argv, option", [
    (["demo", "--seed", "-1"], "--seed"),
    (["demo", "--episodes", "0"], "--episodes"),
    (["demo", "--dt", "inf"], "--dt"),
    (["demo", "--substeps", "0"], "--substeps"),
    (["demo", "--save-gif", "/nonexistent/x.gif"], "--save-gif"),
    (["demo", "--save-gif", "episode.png"], "--save-gif"),
    (["demo", "--env", "ClothPin-v1", "--action-mode", "spring"], "--action-mode"),
    (["demo", "--env", "SliderCrank-v0", "--action-mode", "draw"], "--action-mode"),
    (["verify", "report", "--out", "/proc/x"], "--out"),
    (["view", "pendulum", "--headless", "--fps", "0"], "--fps"),
    (["view", "pendulum", "--headless", "--dt", "1e-310"], "--dt"),
    (["view", "pendulum", "--headless", "--record", "/nonexistent/x.gif"], "--record"),
    (["bench", "--repeats", "1"], "--repeats"),
])
def test_bad_options_of_every_command_stop_before_any_work(argv, option, capsys):
    assert option in usage_error(argv, capsys)


def test_output_directory_must_be_writable(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    err = usage_error(["verify", "report", "--out", str(blocker / "sub")], capsys)
    assert "--out" in err and "cannot create" in err and "not a directory" in err


def test_unknown_scene_and_method_are_usage_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", "trebuchet"])
    assert exc.value.code == 2
    assert "wire_mixture" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", "pendulum", "--method", "rk5"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert all(name in err for name in METHODS)


def test_diverging_run_returns_1(capsys):
    code = cli.main(["run", "spring_pair", "--method", "euler", "--dt", "1", "--seconds", "50"])
    assert code == 1
    assert "diverged" in capsys.readouterr().err


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert all(name in out for name in cli.SUBCOMMANDS)


def test_version(capsys):
    from constrained_particles import __version__

    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"cparticles {__version__}"


@pytest.mark.parametrize("command", sorted(cli.SUBCOMMANDS))
def test_help_is_plain_text_with_defaults(command, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["cparticles", command, "--help"])
    with pytest.raises(SystemExit) as exc:
        cli.main([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "``" not in out and ":func:" not in out
    if command in ("run", "demo", "view", "bench"):
        assert "(default: " in out
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "``" not in capsys.readouterr().out


def test_verify_pymunk_help_describes_its_json(capsys, monkeypatch):
    with pytest.raises(SystemExit):
        cli.main(["verify", "pymunk", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert '"order"' in out and '"errors"' in out


def test_bench_help_states_the_repeats_it_enforces(capsys):
    with pytest.raises(SystemExit):
        cli.main(["bench", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "at least 5" in out and "(default: 5)" in out


@pytest.mark.parametrize("argv, hidden, extra", [
    (["bench", "--quick"], "pymunk", "verify"),
    (["verify", "pymunk", "--quick"], "pymunk", "verify"),
    (["verify", "orders", "--quick"], "tqdm", "verify"),
    (["verify", "report", "--quick", "--out", "OUT"], "matplotlib", "verify"),
    (["view", "pendulum", "--headless", "--frames", "1"], "pygame", "render"),
    (["demo", "--episodes", "1", "--save-gif", "TMP/x.gif"], "PIL", "render"),
])
def test_missing_extra_is_one_line_before_any_work(argv, hidden, extra, monkeypatch, capsys,
                                                   tmp_path):
    """With an optional module hidden (``sys.modules[name] = None`` makes it unimportable), the
    command prints one line naming the extra and how to install it from the checkout (the
    package is not on an index), and does nothing."""
    argv = [a.replace("OUT", str(tmp_path / "out")).replace("TMP", str(tmp_path)) for a in argv]
    monkeypatch.setitem(sys.modules, hidden, None)
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, lines
    shown = {"PIL": "pillow", "pygame": "pygame-ce"}.get(hidden, hidden)
    assert f"'{extra}' extra" in lines[0] and f"missing: {shown}" in lines[0]
    assert lines[0].startswith("error: cparticles ")
    assert f'pip install -e ".[{extra}]"' in lines[0] and "checkout" in lines[0]
    assert "constrained-particles[" not in lines[0]
    assert not (tmp_path / "out" / "report.md").exists() and not (tmp_path / "x.gif").exists()


def test_the_python_api_names_a_missing_extra_in_one_short_exception(monkeypatch, tmp_path):
    """Without the rl (or ray) extra, the Python entry points raise one MissingExtra naming
    the extra and how to install it, before any work and with no chained traceback."""
    import importlib

    from constrained_particles.extras import MissingExtra

    monkeypatch.setitem(sys.modules, "stable_baselines3", None)
    monkeypatch.delitem(sys.modules, "envs.sb3", raising=False)
    calls = [lambda: importlib.import_module("envs.sb3")]
    from envs import train

    calls += [lambda: train.train("ClothSlide-v0", "ppo", 0, tmp_path / "run"),
              lambda: train.evaluate(tmp_path)]
    for call in calls:
        with pytest.raises(MissingExtra) as exc:
            call()
        text = str(exc.value)
        assert "'rl' extra" in text and 'pip install -e ".[rl]"' in text and "\n" not in text
        assert exc.value.__cause__ is None
    assert not (tmp_path / "run").exists()
    monkeypatch.setitem(sys.modules, "ray", None)
    import envs.rllib

    with pytest.raises(MissingExtra, match="'ray' extra"):
        envs.rllib.register()


def test_python_m_verification_reports_a_missing_extra(monkeypatch, capsys):
    from verification.__main__ import run

    monkeypatch.setitem(sys.modules, "pymunk", None)
    assert run(["pymunk", "--quick"]) == 2
    assert "'verify' extra" in capsys.readouterr().err


@pytest.mark.parametrize("tty, flags, shown", [
    (True, {}, True), (False, {}, False), (True, {"quiet": True}, False),
    (False, {"progress": True}, True), (True, {"quiet": True, "progress": True}, False)])
def test_progress_shows_on_a_terminal_unless_quiet(tty, flags, shown, monkeypatch):
    import argparse

    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    assert progress_enabled(argparse.Namespace(**flags)) is shown


def test_verify_passes_progress_to_the_measurement(monkeypatch, capsys):
    """On a terminal ``verify orders`` asks for progress bars; ``--quiet`` turns them off."""
    import verification.orders as orders

    seen = []
    monkeypatch.setattr(orders, "measure_orders",
                        lambda quick, progress: seen.append(progress) or {})
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert cli.main(["verify", "orders", "--json"]) == 0
    assert cli.main(["verify", "orders", "--json", "--quiet"]) == 0
    assert seen == [True, False]


def test_verify_orders_ends_with_a_verdict_against_theory(monkeypatch, capsys):
    """The table ends with one verdict line; an order off theory is named and exits 1."""
    import verification.orders as orders

    def result(order, theory=2):
        return orders.OrderResult("pendulum", "midpoint", theory, [0.01, 0.005], [1e-4, 2.5e-5],
                                  [0.1, 0.2], order)

    for measured, code, words in ((2.05, 0, "all 1 observed orders agree"),
                                  (1.4, 1, "1 of 1 observed orders differ")):
        monkeypatch.setattr(orders, "measure_orders", lambda quick, progress, m=measured:
                            {"pendulum": {"midpoint": result(m)}})
        assert cli.main(["verify", "orders", "--quiet"]) == code
        last = capsys.readouterr().out.strip().splitlines()[-1]
        assert last.startswith("verdict: ") and words in last, last
        assert ("pendulum/midpoint 1.40 (theory 2)" in last) == (code == 1)


def test_demo_takes_env_keywords_checked_before_any_work(capsys):
    """``--env-kwargs`` reaches a variant (ChainSwing's swing-up); an unknown key or a bad
    value is a usage error listing what the env takes."""
    assert cli.main(["demo", "--env", "ChainSwing-v0", "--env-kwargs", "target=swingup",
                     "links=3", "--agent", "random", "--episodes", "1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["target"] == "swingup" and summary["links"] == 3
    for words, argv in ((["'targt'", "stiffness"], ["targt=swingup"]),
                        (["links must be"], ["links=0"]),
                        (["not a JSON object"], ["{nope"])):
        with pytest.raises(SystemExit) as exc:
            cli.main(["demo", "--env", "ChainSwing-v0", "--env-kwargs", *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and all(w in err for w in ["--env-kwargs", *words]), err


def test_demo_reports_diverged_episodes(capsys):
    """Forward Euler at 20 ms is unstable on the cloth: every episode ends diverged, and the
    table and the JSON say so; the default settings diverge in none."""
    import json

    argv = ["demo", "--env", "ClothSlide-v0", "--episodes", "2", "--integrator", "euler",
            "--dt", "0.02", "--substeps", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert "diverged" in out.splitlines()[1] and "2 diverged" in out
    assert cli.main([*argv, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["diverged_episodes"] == 2 and data["diverged"] == [True, True]
    assert data["success_rate"] == 0.0
    assert cli.main(["demo", "--env", "SliderCrank-v0", "--episodes", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["diverged_episodes"] == 0


@pytest.mark.parametrize("env_id, mode", [("ChainSwing-v0", "force"), ("ClothPin-v1", "draw")])
def test_demo_runs_every_registered_environment(env_id, mode, capsys):
    """The two newer environments run in ``cparticles demo`` too, each in its default action
    mode (ClothPin draws springs), with the scripted agent reaching the goal."""
    import json

    assert cli.main(["demo", "--env", env_id, "--episodes", "2", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["env"] == env_id and data["action_mode"] == mode
    assert len(data["returns"]) == 2 and data["diverged_episodes"] == 0
    assert data["success_rate"] == 1.0


# ------------------------------------------------------------------ every default in --help
def all_parsers(parser, name="cparticles"):
    """(name, parser) of ``parser`` and its subcommands, recursively."""
    import argparse

    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from all_parsers(sub, f"{name} {sub_name}")


@pytest.mark.parametrize("command", sorted(cli.SUBCOMMANDS))
def test_help_states_every_default(command):
    """Every option that takes a value and is not required says its default in ``--help``
    (shown by the formatter, or stated in words where the default is None)."""
    import argparse

    from constrained_particles.arguments import HelpFormatter

    parsers = [(n, p) for n, p in all_parsers(cli.build_parser([command]))
               if n.split()[1:2] == [command]]
    assert parsers
    silent = []
    for name, parser in parsers:
        formatter = HelpFormatter(name)
        for action in parser._actions:
            if (action.help == argparse.SUPPRESS or action.required or action.nargs == 0
                    or isinstance(action, argparse._SubParsersAction)
                    or (not action.option_strings and action.default is None)):
                continue  # flags, --help, subcommands and required positionals
            if "default" not in formatter._get_help_string(action):
                silent.append(f"{name} {action.option_strings or action.dest}")
    assert not silent, f"options whose help does not state the default: {silent}"


@pytest.mark.parametrize("env_id", ["ClothSlide-v0", "SliderCrank-v0", "ChainSwing-v0",
                                    "ClothPin-v1"])
def test_train_help_after_every_env_id(env_id, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", env_id, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    out = " ".join(out.split())
    assert "--timesteps" in out and "ClothPin-v1: draw" in out
    assert "(default: the one the task ships first: sac for RopeStraighten-v0, ppo for the " \
           "others)" in out


# ------------------------------------------------------------------ train / evaluate mistakes
def fails_cleanly(argv: list[str], capsys) -> str:
    """``cparticles argv`` ends with exit status 2 (from argparse or returned), one ``error:``
    line and no traceback; returns stderr."""
    try:
        code = cli.main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert sum("error:" in line for line in err.splitlines()) == 1, err
    return err


@pytest.mark.parametrize("argv, words", [
    (["train", "ClothSlide-v0", "--out", "/proc/nope"], ["--out", "'/proc'"]),
    (["train", "ClothSlide-v0", "--out", "FILE"], ["--out", "not a directory"]),
    (["train", "ClothSlide-v0", "--out", "FILE/sub"], ["--out", "not a directory"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--threads", "0"], ["--threads"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--seed", "-1"], ["--seed"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--timesteps", "0"], ["--timesteps"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--eval-freq", "x"], ["--eval-freq"]),
    (["train", "ClothPin-v1", "--out", "TMP/run", "--action-mode", "force"],
     ["--action-mode", "draw"]),
    (["train", "ChainSwing-v0", "--out", "TMP/run", "--action-mode", "draw"],
     ["--action-mode", "force or spring"]),
    (["train", "Pendulum-v1", "--out", "TMP/run"], ["ENV_ID"]),
    (["train", "ClothSlide-v0", "--out", "DONE"], ["--out", "already holds a run"]),
    (["evaluate", "TMP/nothing"], ["not a directory"]),
    (["evaluate", "TMP"], ["no config.json"]),
    (["evaluate", "DONE", "--episodes", "0"], ["--episodes"]),
    (["evaluate", "DONE", "--seed-start", "-5"], ["--seed-start"]),
    (["train", "ChainSwing-v0", "--out", "TMP/run", "--env-kwargs", "targt=swingup"],
     ["--env-kwargs", "'targt'", "target", "links"]),
    (["train", "ChainSwing-v0", "--out", "TMP/run", "--env-kwargs", "target=up"],
     ["--env-kwargs", "target must be one of"]),
    (["train", "ChainSwing-v0", "--out", "TMP/run", "--env-kwargs", "target"],
     ["--env-kwargs", "KEY=VALUE"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--env-kwargs", "action_mode=spring"],
     ["--env-kwargs", "--action-mode"]),
    (["train", "ClothSlide-v0", "--out", "TMP/run", "--device", "gpu7"], ["--device"]),
    (["evaluate", "DONE", "--env-kwargs", "spacing=0.2", "nonsense=1"],
     ["--env-kwargs", "'nonsense'"]),
])
def test_train_and_evaluate_check_every_argument_first(argv, words, tmp_path, capsys):
    """Each mistake stops before any work: nothing is created under TMP."""
    (tmp_path / "FILE").write_text("")
    done = tmp_path / "DONE"
    done.mkdir()
    (done / "config.json").write_text(json.dumps(RUN_CONFIG))
    (done / "policy.pt").write_bytes(b"")
    before = sorted(tmp_path.rglob("*"))
    argv = [str(tmp_path / a[4:]) if a.startswith("TMP/") else a for a in argv]
    argv = [str(tmp_path / a) if a in ("FILE", "FILE/sub", "DONE") else
            str(tmp_path) if a == "TMP" else a for a in argv]
    err = fails_cleanly(argv, capsys)
    assert all(w in err for w in words), err
    assert sorted(tmp_path.rglob("*")) == before


def _spaces(env_id: str = "SliderCrank-v0") -> dict:
    from envs.train import space_record

    env = gym.make(env_id)
    spaces = {"observation": space_record(env.observation_space),
              "action": space_record(env.action_space)}
    env.close()
    return spaces


#: The fields ``cparticles train`` writes into config.json (a SliderCrank run).
RUN_CONFIG = {"format": 2, "env": "SliderCrank-v0", "action_mode": "force", "algo": "ppo",
              "seed": 0, "timesteps": 2048,
              "hyperparams": {"n_envs": 16, "policy": "MlpPolicy",
                              "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -0.5}},
              "observation_shape": [9], "action_shape": [1], "spaces": _spaces(),
              "normalized": True, "wall_seconds": 1.0}
#: What a run directory of an older train held in config.json (its model: pickles).
OLD_RUN_CONFIG = {k: v for k, v in RUN_CONFIG.items()
                  if k not in ("format", "spaces", "normalized")}


class Marker:
    """Unpickling this creates the file ``path``: the stand-in for a crafted pickle."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


@pytest.mark.parametrize("change, words", [
    ({"env": "Nope-v0"}, ["env_id must be one of", "Nope-v0"]),
    ({"action_mode": "draw"}, ["action_mode", "force or spring"]),
    ({"algo": "dqn"}, ["algo"]),
    ({"seed": None}, ["'seed'"]),
    ({"format": 3}, ["'format'", "2"]),
    ({"spaces": {**_spaces(), "observation": _spaces("ClothSlide-v0")["observation"]}},
     ["observation space", "(145,)", "(9,)"]),
    ({"hyperparams": {"env_kwargs": {"nonsense": 1}}}, ["env_kwargs"]),
    ({"hyperparams": {"policy": "CnnPolicy"}}, ["hyperparams.policy", "image"]),
    ({"hyperparams": {"policy": "TransformerPolicy"}}, ["hyperparams.policy", "MlpPolicy"]),
    ({"hyperparams": {"policy_kwargs": {"activation_fn": "os.system"}}}, ["policy_kwargs"]),
    ({"hyperparams": {"policy_kwargs": {"net_arch": [10**9]}}}, ["net_arch"]),
    ({"hyperparams": {"policy_kwargs": {"net_arch": {"pi": [], "qf": [8]}}}},
     ["net_arch", "ppo", "vf"]),
    ({"algo": "sac", "hyperparams": {"policy_kwargs": {"net_arch": {"pi": [], "vf": [8]}}}},
     ["net_arch", "sac", "qf"]),
    ({"hyperparams": {"policy_kwargs": {"net_arch": {"pi": [0], "vf": [8]}}}}, ["net_arch"]),
    ({"hyperparams": {"policy_kwargs": {"ortho_init": "no"}}}, ["ortho_init", "true or false"]),
    ({"algo": "sac", "hyperparams": {"policy_kwargs": {"ortho_init": False}}},
     ["ortho_init", "ppo setting"]),
    (None, ["not valid JSON"]),
    ("deep", ["nested too deeply"]),
    ("huge", ["larger than"]),
])
def test_evaluate_checks_config_json_first(change, words, tmp_path, capsys):
    """A run directory whose config.json is not one train writes (malformed, deeply nested or
    huge JSON included) is refused with one error line, and nothing stored in it is loaded
    (the crafted pickles would create a file)."""
    import pickle

    run = tmp_path / "run"
    run.mkdir()
    marker = tmp_path / "unpickled"
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(Marker(marker)))
    (run / "policy.pt").write_bytes(pickle.dumps(Marker(marker)))
    text = ("{not json" if change is None else "[" * 100_000 + "]" * 100_000
            if change == "deep" else json.dumps({**RUN_CONFIG, "pad": "x" * 2_000_000})
            if change == "huge" else json.dumps({**RUN_CONFIG, **change}))
    (run / "config.json").write_text(text)
    err = fails_cleanly(["evaluate", str(run)], capsys)
    assert all(w in err for w in words), err
    assert not marker.exists()


def crafted_model_zip(path, marker) -> None:
    """A Stable-Baselines3 archive whose stored policy class is a pickle that creates
    ``marker`` when loaded (SB3 unpickles such entries while reading the archive)."""
    import base64
    import pickle
    import zipfile

    payload = base64.b64encode(pickle.dumps(Marker(marker))).decode()
    data = {"policy_class": {":type:": "<class 'type'>", ":serialized:": payload}}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("data", json.dumps(data))
        z.writestr("_stable_baselines3_version", "2.3.0")


@pytest.mark.parametrize("best", [False, True])
def test_a_crafted_run_directory_of_the_old_format_runs_nothing(best, tmp_path, capsys):
    """model.zip / vecnormalize.pkl payloads (which the old evaluate unpickled) are never
    opened: one error line that says how to convert a directory one trusts."""
    import pickle

    run = tmp_path / "run"
    run.mkdir()
    marker = tmp_path / "ran"
    prefix = "best_" if best else ""
    crafted_model_zip(run / f"{prefix}model.zip", marker)
    (run / f"{prefix}vecnormalize.pkl").write_bytes(pickle.dumps(Marker(marker)))
    (run / "config.json").write_text(json.dumps(OLD_RUN_CONFIG))
    err = fails_cleanly(["evaluate", str(run), *(["--best"] if best else [])], capsys)
    assert "older cparticles train" in err and f"cparticles convert-run {run}" in err, err
    assert not marker.exists()


def test_a_crafted_weights_or_statistics_file_runs_nothing(tmp_path, capsys):
    """In a run directory of the current format: a weights file that is a pickle payload, a
    statistics file holding a pickled object array, and pickles where the old format kept
    its model, give one error line each; none of them runs (the marker is never written)."""
    pytest.importorskip("stable_baselines3")
    import pickle

    import torch
    from stable_baselines3 import PPO

    from envs.train import load_policy, read_run

    run = tmp_path / "run"
    run.mkdir()
    marker = tmp_path / "ran"
    (run / "config.json").write_text(json.dumps(RUN_CONFIG))
    crafted_model_zip(run / "model.zip", marker)  # (left over: never opened)
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(Marker(marker)))
    (run / "policy.pt").write_bytes(pickle.dumps(Marker(marker)))
    err = fails_cleanly(["evaluate", str(run), "--episodes", "1"], capsys)
    assert "policy.pt is not a weights file" in err, err
    # a torch.save'd payload (a zip archive holding the pickle) is refused the same way
    with open(run / "policy.pt", "wb") as f:
        torch.save({"w": Marker(marker)}, f)
    err = fails_cleanly(["evaluate", str(run), "--episodes", "1"], capsys)
    assert "policy.pt is not a weights file" in err, err
    # real weights, then statistics holding a pickled object array
    model = PPO("MlpPolicy", gym.make("SliderCrank-v0"), n_steps=64, device="cpu",
                policy_kwargs=RUN_CONFIG["hyperparams"]["policy_kwargs"])
    torch.save(model.policy.state_dict(), run / "policy.pt")
    assert load_policy(read_run(run), run / "policy.pt") is not None
    np.savez(run / "normalization.npz", mean=np.array([Marker(marker)], dtype=object))
    err = fails_cleanly(["evaluate", str(run), "--episodes", "1"], capsys)
    assert "normalization.npz is not a normalization file" in err, err
    assert not marker.exists()


def test_evaluate_without_the_policy_names_the_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(RUN_CONFIG))
    err = fails_cleanly(["evaluate", str(run)], capsys)
    assert "no policy.pt" in err
    err = fails_cleanly(["evaluate", str(run), "--best"], capsys)
    assert "no best_policy.pt" in err


def test_evaluate_of_weights_for_another_env_is_an_error(tmp_path, capsys):
    """SliderCrank weights (9 observations) in a directory whose config.json says ClothSlide
    (145): refused when the weights are loaded, before any episode."""
    pytest.importorskip("stable_baselines3")
    import torch
    from stable_baselines3 import PPO

    run = tmp_path / "run"
    run.mkdir()
    model = PPO("MlpPolicy", gym.make("SliderCrank-v0"), n_steps=64, device="cpu",
                policy_kwargs=RUN_CONFIG["hyperparams"]["policy_kwargs"])
    torch.save(model.policy.state_dict(), run / "policy.pt")
    config = {**RUN_CONFIG, "env": "ClothSlide-v0", "spaces": _spaces("ClothSlide-v0")}
    (run / "config.json").write_text(json.dumps(config))
    err = fails_cleanly(["evaluate", str(run), "--episodes", "1"], capsys)
    assert "does not hold the weights of the run's policy" in err and "145" in err, err


def test_evaluate_help_says_a_run_holds_data_only(capsys):
    with pytest.raises(SystemExit):
        cli.main(["evaluate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "data only" in out and "runs no code" in out and "convert-run" in out
    with pytest.raises(SystemExit):
        cli.main(["convert-run", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "LOADS THE PICKLES" in out and "trust" in out


# ------------------------------------------------------------------ without the rl extra
HIDE_SB3 = ("import sys; sys.modules['stable_baselines3'] = None; "
            "from cparticles.cli import main; sys.exit(main(sys.argv[1:]))")


@pytest.mark.parametrize("argv", [["train", "ClothSlide-v0", "--out", "TMP/run"],
                                  ["train", "ClothPin-v1", "--out", "TMP/run"],
                                  ["evaluate", "TMP"]])
def test_train_without_the_rl_extra_is_a_one_line_hint(argv, tmp_path):
    """A fresh interpreter in which stable_baselines3 cannot be imported (as if the rl extra
    were not installed): one line naming the extra and the install command of a checkout
    (``evaluate`` gets a run directory whose files pass the checks made before the extra's)."""
    import os
    import subprocess

    (tmp_path / "config.json").write_text(json.dumps(RUN_CONFIG))
    (tmp_path / "policy.pt").write_bytes(b"")
    argv = [a.replace("TMP", str(tmp_path)) for a in argv]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [root, *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, "-c", HIDE_SB3, *argv], capture_output=True,
                          text=True, env=env, timeout=300)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert lines[0].startswith(f"error: cparticles {argv[0]} needs the 'rl' extra")
    assert "stable-baselines3" in lines[0] and 'pip install -e ".[rl]"' in lines[0]
    assert "constrained-particles[" not in lines[0]
    assert done.stdout == "" and not (tmp_path / "run").exists()


# ------------------------------------------------------------------ output paths, JSON shapes
@pytest.mark.parametrize("argv", [["demo", "--save-gif", "/proc/x.gif"],
                                  ["view", "pendulum", "--headless", "--record", "/proc/x.gif"],
                                  ["verify", "energy", "--plot", "/proc/x.png"]])
def test_an_unwritable_existing_directory_is_named_sensibly(argv, capsys):
    """/proc exists but takes no new files; the message says so (not "No such file")."""
    err = usage_error(argv, capsys)
    assert "'/proc' does not accept new files" in err
    assert "No such file" not in err


def test_verify_orders_json_is_one_object_on_one_line(capsys):
    """The shape the README shows: {"case": {"method": observed order, ...}, ...} on one line;
    rk4's measured order is near its theoretical 4."""
    assert cli.main(["verify", "orders", "--quick", "--json", "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    data = json.loads(lines[0])
    assert "pendulum" in data
    for per in data.values():
        assert set(per) == set(METHODS)
        assert all(isinstance(v, float) for v in per.values())
        assert abs(per["rk4"] - 4) < 0.5


# ------------------------------------------------------------------ the system says no
def test_out_naming_a_dangling_symlink_or_a_device_is_an_argument_error(tmp_path, capsys):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "nowhere")
    err = fails_cleanly(["train", "SliderCrank-v0", "--out", str(link)], capsys)
    assert "--out" in err and "dangling" in err
    err = fails_cleanly(["train", "SliderCrank-v0", "--out", "/dev/null"], capsys)
    assert "--out" in err and "not a directory" in err
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    err = fails_cleanly(["train", "SliderCrank-v0", "--out", str(busy)], capsys)
    assert "already holds files" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy", "link"]


def test_a_gif_on_a_full_disk_is_one_line_and_leaves_no_file(tmp_path, capsys, monkeypatch):
    """Writing the GIF fails with ENOSPC half-way: exit status 1, one error line, no
    traceback, and neither the GIF nor its partial file is left."""
    pytest.importorskip("PIL")
    import errno

    from PIL import Image

    def full(self, fp, *args, **kwargs):
        with open(fp, "wb") as f:
            f.write(b"GIF89a")  # (a start, then the disk is full)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full)
    gif = tmp_path / "x.gif"
    code = cli.main(["demo", "--env", "SliderCrank-v0", "--episodes", "1", "--save-gif",
                     str(gif)])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines() == ["cparticles demo: error: No space left on device"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("exc, words", [
    (OSError(28, "No space left on device", "/data/run/x"),
     "No space left on device: /data/run/x"),
    (PermissionError(13, "Permission denied", "/etc/x"), "Permission denied: /etc/x"),
    (IsADirectoryError(21, "Is a directory", "/tmp"), "Is a directory: /tmp"),
])
def test_an_os_error_of_a_command_is_one_line_and_status_1(exc, words, capsys):
    from constrained_particles.arguments import run_command

    def fail():
        raise exc

    assert run_command("cparticles x", fail) == 1
    assert capsys.readouterr().err == f"cparticles x: error: {words}\n"
