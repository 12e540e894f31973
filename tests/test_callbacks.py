"""OLSCallback: Algorithm 1 over independent learners (MA-SFOLS, Random + GPI), checkpoints and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import StopAfter
from parallel_chain import make_chain_runner, optimal_value

from sb3_sfgpi.callbacks import OLSCallback, learn_iterations
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import EvaluationConfig
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.schedules import OLSSchedule, RandomSchedule, WeightSchedule, make_schedule

TEST_WEIGHTS = random_weights(2, 5, rng=0)


def ols_callback(steps: int, schedule: WeightSchedule | None = None, **kwargs) -> OLSCallback:
    """MA-SFOLS (or ``schedule``) over the chain, evaluated on :data:`TEST_WEIGHTS`."""
    return OLSCallback(schedule or OLSSchedule(), steps, EvaluationConfig(TEST_WEIGHTS), **kwargs)


def test_ma_sfols_builds_an_exact_ccs_and_stops(tmp_path):
    runner = make_chain_runner()
    callback = ols_callback(600, run_dir=tmp_path)
    learn_iterations(runner, callback, max_iterations=10)
    assert callback.next_weights is None and len(callback.history) < 10  # OLS ended before the iteration cap
    assert callback.schedule.ols.next_weight() is None and callback.ended_by_schedule
    for w0 in np.linspace(0, 1, 21):
        w = np.array([w0, 1 - w0])
        assert callback.policy_set.q_values(np.array([0]), w).max() == pytest.approx(optimal_value(w), abs=1e-3)
    # The GPI evaluation in the env reaches the optimum for every test weight and both agents.
    last = callback.history[-1]
    for entry in last["test"]:
        for returns in entry["agents"].values():
            assert np.dot(entry["weights"], returns["undiscounted"]) == pytest.approx(optimal_value(entry["weights"]))
    # Every policy in the set carries its weight, value, agent and iteration.
    assert {info.agent for info in callback.policy_set.infos} <= {"agent_0", "agent_1"}
    assert all(info.value is not None and info.iteration is not None for info in callback.policy_set.infos)


def test_first_iteration_trains_the_simplex_extrema_one_per_agent():
    runner = make_chain_runner()
    callback = ols_callback(200)
    learn_iterations(runner, callback, max_iterations=1)
    trained = callback.history[0]["weights_trained"]
    assert trained == {"agent_0": [1.0, 0.0], "agent_1": [0.0, 1.0]}


def test_agents_beyond_the_queue_get_random_weights():
    runner = make_chain_runner(n_agents=3)
    callback = ols_callback(200)
    learn_iterations(runner, callback, max_iterations=1)
    third = np.array(callback.history[0]["weights_trained"]["agent_2"])
    assert third.sum() == pytest.approx(1.0) and np.all(third > 0) and np.all(third < 1)


def test_random_baseline_uses_only_random_weights_and_runs_all_iterations():
    runner = make_chain_runner()
    callback = ols_callback(200, RandomSchedule())
    learn_iterations(runner, callback, max_iterations=3)
    assert len(callback.history) == 3
    for row in callback.history:
        for w in row["weights_trained"].values():
            assert 0 < w[0] < 1  # never an extremum: Dirichlet(1) draws
    # Random weights differ between agents and iterations.
    drawn = {tuple(w) for row in callback.history for w in row["weights_trained"].values()}
    assert len(drawn) == 6


def test_resume_after_interruption_gives_the_same_policy_set(tmp_path):
    full = make_chain_runner(seed=3)
    full_cb = ols_callback(300, run_dir=tmp_path / "full")
    learn_iterations(full, full_cb, max_iterations=3)

    first = make_chain_runner(seed=3)
    first_cb = ols_callback(300, run_dir=tmp_path / "cut")
    learn_iterations(first, first_cb, max_iterations=3, callbacks=[StopAfter(450)])  # killed half-way through it. 2
    assert json.loads((tmp_path / "cut" / "checkpoint.json").read_text())["iteration"] == 1

    resumed = make_chain_runner(seed=3)
    resumed_cb = ols_callback(300, run_dir=tmp_path / "cut", resume=True)
    learn_iterations(resumed, resumed_cb, max_iterations=3)

    a, b = GPIPolicy.load(tmp_path / "full" / "policy_set"), GPIPolicy.load(tmp_path / "cut" / "policy_set")
    assert len(a) == len(b)
    for info_a, info_b in zip(a.infos, b.infos, strict=True):
        np.testing.assert_allclose(info_a.weights, info_b.weights)
        np.testing.assert_allclose(info_a.value, info_b.value)
        assert (info_a.agent, info_a.iteration) == (info_b.agent, info_b.iteration)
    obs = np.arange(5)
    np.testing.assert_allclose(a.successor_features(obs), b.successor_features(obs))
    assert [r["mean_return"] for r in full_cb.history] == [r["mean_return"] for r in resumed_cb.history]


def test_resuming_a_finished_run_does_nothing(tmp_path):
    learn_iterations(make_chain_runner(), ols_callback(300, run_dir=tmp_path), max_iterations=2)
    runner = make_chain_runner()
    callback = ols_callback(300, run_dir=tmp_path, resume=True)
    learn_iterations(runner, callback, max_iterations=2)
    assert callback.reached_max_iterations and runner.num_timesteps == 600 and len(callback.history) == 2


def test_bad_schedule_and_test_weights_are_refused():
    with pytest.raises(ValueError, match="weights must be .ols., .random."):
        make_schedule("greedy")
    with pytest.raises(ValueError, match="length 2"):
        learn_iterations(make_chain_runner(), OLSCallback(OLSSchedule(), 10, EvaluationConfig(np.ones((2, 3)) / 3)))
