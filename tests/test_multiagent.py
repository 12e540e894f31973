"""The multi-agent loop: independent learners, MA-SFOLS, Random + GPI, checkpoints and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from parallel_chain import ParallelChainEnv, optimal_value
from stable_baselines3.common.callbacks import BaseCallback

from sb3_sfgpi.callbacks import OLSCallback
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.multiagent import AgentVecEnv, MultiAgentRunner, default_learner_factory

LEARNER = dict(
    policy="TabularPolicy",
    learning_rate=0.3,
    gamma=1.0,
    exploration_initial_eps=1.0,
    exploration_fraction=0.6,
    exploration_final_eps=0.1,
    learning_starts=0,
    train_freq=1,
    batch_size=16,
    buffer_size=10_000,
)
TEST_WEIGHTS = random_weights(2, 5, rng=0)


def make_runner(n_agents: int = 2, seed: int = 0, max_steps: int | None = None) -> MultiAgentRunner:
    env = ParallelChainEnv(n_agents, max_steps=max_steps)
    return MultiAgentRunner(env, default_learner_factory(**LEARNER), seed=seed)


def test_ma_sfols_builds_an_exact_ccs_and_stops(tmp_path):
    runner = make_runner()
    callback = OLSCallback(600, TEST_WEIGHTS, max_iterations=10, run_dir=tmp_path)
    runner.learn(6000, callback)
    assert callback.finished and len(callback.history) < 10  # OLS ended before the iteration cap
    assert callback.ols.next_weight() is None
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
    runner = make_runner()
    callback = OLSCallback(200, TEST_WEIGHTS, max_iterations=1)
    runner.learn(200, callback)
    trained = callback.history[0]["weights_trained"]
    assert trained == {"agent_0": [1.0, 0.0], "agent_1": [0.0, 1.0]}


def test_agents_beyond_the_queue_get_random_weights():
    runner = make_runner(n_agents=3)
    callback = OLSCallback(200, TEST_WEIGHTS, max_iterations=1)
    runner.learn(200, callback)
    third = np.array(callback.history[0]["weights_trained"]["agent_2"])
    assert third.sum() == pytest.approx(1.0) and np.all(third > 0) and np.all(third < 1)


def test_random_baseline_uses_only_random_weights_and_runs_all_iterations():
    runner = make_runner()
    callback = OLSCallback(200, TEST_WEIGHTS, algorithm="random", max_iterations=3)
    runner.learn(600, callback)
    assert len(callback.history) == 3
    for row in callback.history:
        for w in row["weights_trained"].values():
            assert 0 < w[0] < 1  # never an extremum: Dirichlet(1) draws
    # Random weights differ between agents and iterations.
    drawn = {tuple(w) for row in callback.history for w in row["weights_trained"].values()}
    assert len(drawn) == 6


def test_resume_after_interruption_gives_the_same_policy_set(tmp_path):
    full = make_runner(seed=3)
    full_cb = OLSCallback(300, TEST_WEIGHTS, max_iterations=3, run_dir=tmp_path / "full")
    full.learn(900, full_cb)

    class StopAfter(BaseCallback):
        def __init__(self, steps: int):
            super().__init__()
            self.steps = steps

        def _on_step(self) -> bool:
            return self.model.num_timesteps < self.steps

    first = make_runner(seed=3)
    first_cb = OLSCallback(300, TEST_WEIGHTS, max_iterations=3, run_dir=tmp_path / "cut")
    first.learn(900, [first_cb, StopAfter(450)])  # killed half-way through the second iteration
    assert json.loads((tmp_path / "cut" / "checkpoint.json").read_text())["iteration"] == 1

    resumed = make_runner(seed=3)
    resumed_cb = OLSCallback(300, TEST_WEIGHTS, max_iterations=3, run_dir=tmp_path / "cut", resume=True)
    resumed.learn(900, resumed_cb)

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
    make_runner().learn(600, OLSCallback(300, TEST_WEIGHTS, max_iterations=2, run_dir=tmp_path))
    runner = make_runner()
    callback = OLSCallback(300, TEST_WEIGHTS, max_iterations=2, run_dir=tmp_path, resume=True)
    runner.learn(600, callback)
    assert callback.finished and runner.num_timesteps == 600 and len(callback.history) == 2


def test_early_finishing_agents_store_no_transitions_and_truncation_bootstraps():
    runner = make_runner(max_steps=2)  # truncated after two steps, before the terminal state
    callback = OLSCallback(40, TEST_WEIGHTS, max_iterations=1)
    runner.learn(40, callback)
    for learner in runner.learners.values():
        buffer = learner.replay_buffer
        n = buffer.pos
        assert n == 40  # one transition per joint step: both agents are live every step
        dones, timeouts = buffer.dones[:n, 0], buffer.timeouts[:n, 0]
        assert np.all(dones[1::2] == 1) and np.all(timeouts[1::2] == 1)  # every 2nd step is a truncation


def test_agent_view_cannot_be_stepped_alone():
    runner = make_runner()
    with pytest.raises(RuntimeError, match="MultiAgentRunner steps the shared env"):
        runner.views["agent_0"].step(np.array([0]))
    assert isinstance(runner.views["agent_0"], AgentVecEnv)


def test_learn_without_a_callback_is_refused():
    with pytest.raises(ValueError, match="runner-level callback"):
        make_runner().learn(10)


def test_bad_algorithm_and_test_weights_are_refused():
    with pytest.raises(ValueError, match="algorithm"):
        OLSCallback(10, TEST_WEIGHTS, algorithm="greedy")
    with pytest.raises(ValueError, match="length 2"):
        make_runner().learn(10, OLSCallback(10, np.ones((2, 3)) / 3))
