"""The pymunk cross-check in quick form: pymunk converges to our trajectories at first order."""

import json

import numpy as np
import pytest

pytest.importorskip("pymunk")

from constrained_particles import AngularSpring, scenes  # noqa: E402
from verification import pymunk_check as K  # noqa: E402
from verification.__main__ import run  # noqa: E402
from verification.orders import checkpoints, run_positions  # noqa: E402


def test_pymunk_converges_to_our_trajectories_at_first_order(capsys):
    assert run(["pymunk", "--quick", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data) == set(K.SCENES)
    for name, result in data.items():
        assert abs(result["order"] - 1.0) <= 0.3, (name, result)
        assert result["errors"]["0.001"] < 1e-2, (name, result)


def test_a_different_model_does_not_converge():
    # the check discriminates: pymunk given a 5% longer pendulum stays ~cm away at every dt
    ours = scenes.pendulum(length=1.0)
    other = scenes.pendulum(length=1.05)
    times = checkpoints(1.0)
    reference = run_positions(ours, "rk4", 1e-3, times)
    errors = [np.max(np.abs(K.pymunk_positions(other, dt, times) - reference))
              for dt in (2e-3, 1e-3, 5e-4)]
    assert min(errors) > 1e-2
    assert errors[-1] > 0.8 * errors[0]


def test_translation_keeps_masses_velocities_and_joints():
    s = scenes.wire_mixture()
    scene = K.to_pymunk(s)
    assert [b.mass for b in scene.bodies] == list(s.mass)
    assert np.allclose([tuple(b.velocity) for b in scene.bodies], s.v)
    assert len(scene.space.constraints) == 3  # pin (circle), groove (wire), pin (rod)
    assert all(b.moment == float("inf") for b in scene.bodies)


def test_unsupported_blocks_are_refused():
    s = scenes.angular_chain(links=2)
    assert any(isinstance(f, AngularSpring) for f in s.forces)
    with pytest.raises(ValueError, match="AngularSpring"):
        K.to_pymunk(s)
    with pytest.raises(ValueError, match="name"):
        K.compare("trebuchet")
