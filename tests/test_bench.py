"""The benchmark harness: its pieces on tiny inputs (the timings themselves are not tested)."""

import json

import numpy as np
import pytest

from constrained_particles import SimulationDiverged
from cparticles import bench as B
from cparticles import bench_scaling as S


def test_alternate_times_every_entry_and_drops_a_diverging_one():
    calls = {"a": lambda: None, "bad": lambda: (_ for _ in ()).throw(SimulationDiverged("x"))}
    order = []
    calls["b"] = lambda: order.append("b")
    out = B.alternate(calls, repeats=5, seconds=0.0, warmup=1)
    assert len(out["a"]) == 5 and len(out["b"]) == 5 and out["bad"] is None
    assert all(t >= 0 for t in out["a"])


def test_median_ratio_pairs_rounds():
    assert B.median_ratio([2.0, 4.0, 100.0], [1.0, 2.0, 50.0]) == 2.0
    assert B.median_ratio(None, [1.0]) is None


def test_equal_accuracy_picks_the_cheapest_pymunk_setting_as_accurate_as_ours():
    rates = {"pymunk": {20: {1: 4.0, 10: 1.0}},
             "ratio": {20: {B.OURS: {1: 0.5, 10: 2.0}}}}
    # 1 iteration is within 2x of our error: compare with it, not with the slower 10
    eq = B.equal_accuracy({B.OURS: 1e-4, "pymunk_1": 1.5e-4, "pymunk_10": 1e-4}, rates)
    assert eq["pymunk_iterations"] == 1 and eq["ratio"] == {20: 0.5}
    # 1 iteration is 3x worse: the 10-iteration setting is the fair one
    eq = B.equal_accuracy({B.OURS: 1e-4, "pymunk_1": 3e-4, "pymunk_10": 1.1e-4}, rates)
    assert eq["pymunk_iterations"] == 10 and eq["ratio"] == {20: 2.0}
    # neither is as accurate: the most accurate one, and the rule says so
    eq = B.equal_accuracy({B.OURS: 1e-6, "pymunk_1": 3e-4, "pymunk_10": 1e-4}, rates)
    assert eq["pymunk_iterations"] == 10 and "no pymunk setting" in eq["rule"]


def test_cloth_errors_are_small_and_ordered():
    """On a 4x4 cloth over 0.05 s: rk4 at 1 ms is far closer to the reference than the first
    order methods, and pymunk's error is of the first-order kind."""
    errors = B.cloth_errors(n=4, seconds=0.05)
    assert set(errors) == {B.OURS, "midpoint", "rk4", "pymunk_1", "pymunk_10"}
    assert all(e is not None and np.isfinite(e) for e in errors.values())
    assert errors["rk4"] < 1e-2 * errors[B.OURS]
    assert errors["pymunk_1"] > 10 * errors["rk4"]


def test_json_carries_the_headline_keys(monkeypatch):
    """A tiny full run (0.02 s accuracy runs; the subprocess memory probe, the 2-process async
    env, scaling and the equal-time sweep stubbed out): the keys ``cparticles bench --json``
    promises are there and positive."""
    monkeypatch.setattr(B, "peak_memory_mb", lambda: 1.0)
    monkeypatch.setattr(B, "bench_env_modes", lambda *a, **k: {"vector_speedup": 1.0})
    monkeypatch.setattr(B, "bench_accuracy_at_equal_time", lambda progress=None: {})
    monkeypatch.setattr(B, "bench_scaling", lambda *a, **k: {"scaling_ratio": 1.0})
    monkeypatch.setattr(S, "IMPLICIT_SIZES", (4, 8))
    threads_asked = []
    monkeypatch.setattr(S, "bench_threads", lambda *a, **k: threads_asked.append(a) or {})
    busy_asked = []
    monkeypatch.setattr(S, "bench_busy", lambda *a, **k: busy_asked.append(a) or {})
    out = json.loads(json.dumps(B.run(repeats=1, sizes=[4], copies=(1, 2), seconds=0.0,
                                      accuracy_n=4, accuracy_seconds=0.02, thread_copies=4)))
    assert out["implicit_scaling"]["sizes"] == [4, 8]
    assert threads_asked[0][:2] == (B.vector_envs(), 4) and "threads" in out
    assert busy_asked[0][:2] == (B.vector_envs()[0], 4) and "busy_cores" in out
    assert out["pymunk_ratio_equal_accuracy"]["4"] > 0
    assert set(out["pymunk_ratio"]) == {"1", "10"}
    assert set(out["env_step_vs_cartpole"]) == {f"{e}/{m}" for e, m in B.small_envs()}
    assert set(out["vector_scaling"]) == set(B.vector_envs())
    assert all(set(rows) == {"1", "2"} for rows in out["vector_scaling"].values())
    assert set(out["cloth_errors"]) == {B.OURS, "midpoint", "rk4", "pymunk_1", "pymunk_10"}
    assert all(r > 0 for r in out["env_step_vs_cartpole"].values())
    for rows in out["vector_scaling"].values():
        for row in rows.values():
            assert row["env_steps_per_s"] > 0 and row["env_over_bare"] > 0
            assert row["us_per_particle_step"] > 0 and row["bare_us_per_particle_step"] > 0
            assert row["integrator_steps_per_physics_step"] >= 1.0
            assert row["env_over_bare_per_step_taken"] == pytest.approx(
                row["env_over_bare"] / row["integrator_steps_per_physics_step"])


def test_work_factor_counts_the_pieces_the_env_decides():
    """Under random actions some SliderCrank copies split their steps: more than one
    integrator step per physics step on average, at most MAX_PIECES; ClothSlide never
    splits (no step_travel), so exactly one."""
    from envs.stepping import MAX_PIECES

    w = B.work_factor("SliderCrank-v0", 16, steps=60)
    assert 1.0 < w <= MAX_PIECES
    assert B.work_factor("ClothSlide-v0", 2, steps=3) == 1.0


def test_implicit_scaling_times_both_solvers_and_they_agree():
    """At 4x4 and 8x8 (tiny: auto picks the direct solve) both solvers run, the growth is
    the ratio of the costs, and CG lands within its tolerance of the direct solve."""
    r = S.bench_implicit_scaling((4, 8), repeats=1, steps=2)
    assert r["linear_growth"] == [4.0] and r["auto_picks"] == ["direct", "direct"]
    for solver in ("cg", "direct"):
        ms = r["ms_per_step"][solver]
        assert all(t > 0 for t in ms)
        assert r["growth"][solver] == [pytest.approx(ms[1] / ms[0])]
    assert max(r["cg_minus_direct_max_m"]) < 1e-6
    assert "8x8" in S.implicit_table(r)


def test_thread_section_reports_speedups_and_the_control():
    """One env at 4 copies, two warm-up steps, one round of zero-length batches (at least one
    step each): every thread count, the speedups over one thread and the two-process control
    are there."""
    r = S.bench_threads(("SliderCrank-v0",), copies=4, repeats=1, seconds=0.0, warmup=2)
    row = r["SliderCrank-v0"]
    assert r["threads"] == S.thread_counts() and r["cores"] >= 1
    assert set(row["speedup"]) == set(S.thread_counts()) and row["speedup"][1] == 1.0
    assert min(row["env_steps_per_s"].values()) > 0 and row["control_one_process"] > 0
    assert row["control_speedup"] > 0 and row["of_control"] > 0
    assert "SliderCrank-v0" in "\n".join(S.threads_markdown(r))


def test_busy_core_section_times_both_thread_counts_and_ends_its_spinners(monkeypatch):
    """bench_busy at 4 copies, one round of zero-length batches, no settling: both thread
    counts timed with the spinners running and without; every spinner it started has ended
    when it returns."""
    started = []
    real = S._Spinners.__enter__

    def enter(self):
        out = real(self)
        started.extend(self.procs)
        return out

    monkeypatch.setattr(S._Spinners, "__enter__", enter)
    r = S.bench_busy("SliderCrank-v0", copies=4, repeats=1, seconds=0.0, settle=0.0)
    assert r["spinners"] == S.cores() and len(started) == S.cores()
    assert all(p.poll() is not None for p in started)
    assert min(r["busy_env_steps_per_s"].values()) > 0 and r["ratio"] > 0
    assert r["idle_ratio"] > 0 and len(r["busy_ratios"]) == 1


def test_small_envs_time_a_variant_in_each_of_its_modes():
    out = B.bench_small_envs(1, 0.0, variant=("ChainSwing-v0", {"target": "swingup"}))
    rows = set(out["vs_cartpole"])
    assert {"ChainSwing-v0[target=swingup]/force", "ChainSwing-v0[target=swingup]/spring"} <= rows
    assert {f"{e}/{m}" for e, m in B.small_envs()} <= rows
    assert all(v > 0 for v in out["us_per_step"].values())


def test_bench_env_kwargs_are_checked_before_any_work(capsys):
    from cparticles import cli

    for argv, words in ((["--env-kwargs", "target=swingup"], ["--env"]),
                        (["--env", "Nope-v0"], ["--env", "env_id must be one of"]),
                        (["--env", "ChainSwing-v0", "--env-kwargs", "targt=1"], ["'targt'"])):
        with pytest.raises(SystemExit) as exc:
            cli.main(["bench", *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and all(w in err for w in words), err


def test_the_step_floor_takes_the_envs_own_steps():
    """benchmarks.step_floor times the env's compiled calls without its checks: stepped so
    from the same state under the same actions, it gives the env's states, observations,
    rewards and infos bit for bit (so the floor it times is the same work)."""
    import gymnasium as gym

    from benchmarks.step_floor import ENV_ID, floor_stepper

    env, low = gym.make(ENV_ID), gym.make(ENV_ID)
    env.reset(seed=3)
    low.reset(seed=3)
    floor = floor_stepper(low)
    rng = np.random.default_rng(4)
    for _ in range(60):
        a = rng.uniform(-1.2, 1.2, 1).astype(np.float32)  # (some beyond the Box: clipped)
        got, want = floor(a), env.step(a)
        assert np.array_equal(got[0], want[0]) and got[1] == want[1]
        assert got[2:4] == want[2:4] and got[4] == want[4]
    one, two = env.unwrapped.task.system, low.unwrapped.task.system
    assert np.array_equal(one.x, two.x) and np.array_equal(one.v, two.v) and one.t == two.t
