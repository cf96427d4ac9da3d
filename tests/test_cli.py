"""``cparticles run``: the table it prints and its exit codes."""

import sys

import numpy as np
import pytest

from constrained_particles import METHODS, cli


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
    (["demo", "--env", "ClothPin-v0", "--action-mode", "spring"], "--action-mode"),
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
    assert "--out" in err and "cannot write" in err


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
    command prints one line naming the extra and both ways to install it, and does nothing."""
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
    assert f'pip install -e ".[{extra}]"' in lines[0]
    assert f'pip install "constrained-particles[{extra}]"' in lines[0]
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
    assert cli.progress_enabled(argparse.Namespace(**flags)) is shown


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


@pytest.mark.parametrize("env_id, mode", [("ChainSwing-v0", "force"), ("ClothPin-v0", "draw")])
def test_demo_runs_every_registered_environment(env_id, mode, capsys):
    """The two newer environments run in ``cparticles demo`` too, each in its default action
    mode (ClothPin draws springs), with the scripted agent reaching the goal."""
    import json

    assert cli.main(["demo", "--env", env_id, "--episodes", "2", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["env"] == env_id and data["action_mode"] == mode
    assert len(data["returns"]) == 2 and data["diverged_episodes"] == 0
    assert data["success_rate"] == 1.0
