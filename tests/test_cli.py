"""The ``cparticles`` command line: ``run``'s table, and for every subcommand its help, its
exit codes and its checks of user mistakes (exit 2, one ``error:`` line, never a traceback)."""

import json
import sys

import numpy as np
import pytest

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
    assert "--timesteps" in out and "(default: ppo)" in out and "ClothPin-v1: draw" in out


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
])
def test_train_and_evaluate_check_every_argument_first(argv, words, tmp_path, capsys):
    """Each mistake stops before any work: nothing is created under TMP."""
    (tmp_path / "FILE").write_text("")
    done = tmp_path / "DONE"
    done.mkdir()
    (done / "config.json").write_text(json.dumps(RUN_CONFIG))
    (done / "model.zip").write_bytes(b"")
    before = sorted(tmp_path.rglob("*"))
    argv = [str(tmp_path / a[4:]) if a.startswith("TMP/") else a for a in argv]
    argv = [str(tmp_path / a) if a in ("FILE", "FILE/sub", "DONE") else
            str(tmp_path) if a == "TMP" else a for a in argv]
    err = fails_cleanly(argv, capsys)
    assert all(w in err for w in words), err
    assert sorted(tmp_path.rglob("*")) == before


#: The fields ``cparticles train`` writes into config.json (a SliderCrank run).
RUN_CONFIG = {"env": "SliderCrank-v0", "action_mode": "force", "algo": "ppo", "seed": 0,
              "timesteps": 2048, "hyperparams": {"n_envs": 16}, "observation_shape": [9],
              "action_shape": [1], "wall_seconds": 1.0}


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
    ({"observation_shape": [145]}, ["observation shape", "(145,)", "(9,)"]),
    ({"hyperparams": {"env_kwargs": {"nonsense": 1}}}, ["env_kwargs"]),
    (None, ["not valid JSON"]),
])
def test_evaluate_checks_config_json_before_unpickling(change, words, tmp_path, capsys):
    """A run directory whose config.json is not one train writes is refused with one error
    line, and none of its pickles is loaded (the crafted one would create a file)."""
    import pickle

    run = tmp_path / "run"
    run.mkdir()
    marker = tmp_path / "unpickled"
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(Marker(marker)))
    (run / "model.zip").write_bytes(b"")
    text = "{not json" if change is None else json.dumps({**RUN_CONFIG, **change})
    (run / "config.json").write_text(text)
    err = fails_cleanly(["evaluate", str(run)], capsys)
    assert all(w in err for w in words), err
    assert not marker.exists()


def test_evaluate_without_model_names_the_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(RUN_CONFIG))
    err = fails_cleanly(["evaluate", str(run)], capsys)
    assert "no model.zip" in err and "model.zip.zip" not in err
    err = fails_cleanly(["evaluate", str(run), "--best"], capsys)
    assert "no best_model.zip" in err


def test_evaluate_of_a_model_for_another_env_is_an_error(tmp_path, capsys):
    """A SliderCrank model (9 observations) in a directory whose config.json says ClothSlide
    (145) and records no shapes: refused after loading, before any episode."""
    pytest.importorskip("stable_baselines3")
    import gymnasium as gym
    from stable_baselines3 import PPO

    import envs  # noqa: F401

    run = tmp_path / "run"
    run.mkdir()
    PPO("MlpPolicy", gym.make("SliderCrank-v0"), n_steps=64, device="cpu").save(
        run / "model.zip")
    config = {k: v for k, v in RUN_CONFIG.items() if not k.endswith("_shape")}
    (run / "config.json").write_text(json.dumps({**config, "env": "ClothSlide-v0"}))
    err = fails_cleanly(["evaluate", str(run), "--episodes", "1"], capsys)
    assert "(9,)" in err and "(145,)" in err and "ClothSlide-v0" in err


def test_evaluate_help_says_a_run_holds_pickles(capsys):
    with pytest.raises(SystemExit):
        cli.main(["evaluate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "pickles" in out and "run code when loaded" in out and "trust" in out
    from envs import train

    assert "run code when" in " ".join(train.__doc__.split())
    assert "pickles" in " ".join(train.evaluate.__doc__.split())


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
    (tmp_path / "model.zip").write_bytes(b"")
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
