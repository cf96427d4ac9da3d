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


@pytest.mark.parametrize("dt", ["0", "-0.01", "nan"])
def test_bad_dt_returns_2_with_a_message(dt, capsys):
    assert cli.main(["run", "wire_mixture", "--seconds", "0.2", f"--dt={dt}"]) == 2
    err = capsys.readouterr().err
    assert "--dt" in err and "error" in err


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
