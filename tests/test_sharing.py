"""Parameter sharing: one SFDQN that every agent acts with and feeds (``sharing="shared"``)."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
from conftest import FEW_VALIDATION
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import REWARDS, TERMINAL
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv, optimal_value

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.cli import main
from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import SHARED, MultiAgentRunner

LEARNER_KWARGS = {k: v for k, v in CHAIN_LEARNER.items() if k != "policy"}


def shared_chain_runner(n_agents: int = 3, **learner_kwargs) -> MultiAgentRunner:
    env = ParallelChainEnv(n_agents, staggered=True)  # agent i starts at state i: they finish one after the other
    return MultiAgentRunner(env, default_learner_factory(**{**CHAIN_LEARNER, **learner_kwargs}), sharing="shared")


def make_buffer(size: int, n_envs: int) -> MOReplayBuffer:
    return MOReplayBuffer(
        size, gym.spaces.Discrete(1000), gym.spaces.Discrete(3), device="cpu", n_envs=n_envs, reward_dim=2
    )


def test_add_rows_of_one_transition_is_add():
    by_add, by_rows = make_buffer(4, 1), make_buffer(4, 1)
    for i in range(6):  # wraps around
        obs, next_obs, action = np.array([[i]]), np.array([[i + 1]]), np.array([[i % 3]])
        reward, done = np.array([[i, -i]], dtype=np.float32), np.array([i % 2 == 0])
        by_add.add(obs, next_obs, action, reward, done, [{"TimeLimit.truncated": i == 2}])
        by_rows.add_rows(obs, next_obs, action, reward, done, np.array([i == 2]))
    assert (by_rows.pos, by_rows.full) == (by_add.pos, by_add.full) == (2, True)
    for a, b in zip(by_add.stored_arrays(), by_rows.stored_arrays(), strict=True):
        np.testing.assert_array_equal(a, b)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 3), max_size=30))
def test_add_rows_keeps_the_last_complete_steps_in_the_order_written(counts):
    buffer = make_buffer(12, 3)  # 12 rows: 4 steps of 3 (SB3's buffer_size counts transitions)
    written = 0
    for k in counts:
        rows = np.arange(written, written + k)
        rewards = np.stack([rows, -rows], axis=1).astype(np.float32)
        buffer.add_rows(rows[:, None], rows[:, None] + 1, rows[:, None] % 3, rewards, np.zeros(k), np.zeros(k))
        written += k
    obs, actions, next_obs, _, rewards = buffer.stored_arrays()
    if written >= 12:  # full: every row holds one of the last 12 transitions written
        expected = np.arange(written - 12, written)
    else:  # the rows of complete steps: the step being written is not sampled yet
        expected = np.arange(written // 3 * 3)
    assert sorted(obs.reshape(-1).tolist()) == expected.tolist()
    np.testing.assert_array_equal(next_obs.reshape(-1), obs.reshape(-1) + 1)
    np.testing.assert_array_equal(actions, obs.reshape(-1) % 3)
    np.testing.assert_array_equal(rewards, np.stack([obs.reshape(-1), -obs.reshape(-1)], axis=1))
    assert buffer.full == (written >= 12)


def test_a_shared_learner_stores_the_transitions_of_the_live_agents_only():
    runner = shared_chain_runner(3)
    assert runner.learner_names == [SHARED]
    runner.start_iteration({SHARED: np.array([0.5, 0.5])}, iteration=0, total_timesteps=100)
    for _ in range(8):  # two episodes of 4 joint steps; agents 0, 1, 2 make 4, 3 and 2 transitions in each
        runner.step()
    learner = runner.learners[SHARED]
    assert learner.n_envs == 3 and learner._n_calls == 8
    assert learner.num_timesteps == 18 and learner._episode_num == 6
    obs, actions, next_obs, dones, rewards = learner.replay_buffer.stored_arrays()  # 18 rows: 6 complete steps
    obs, next_obs = obs.reshape(-1), next_obs.reshape(-1)
    assert sorted(obs.tolist()) == sorted([0, 1, 1, 2, 2, 2, 3, 3, 3] * 2)
    np.testing.assert_array_equal(next_obs, obs + 1)
    np.testing.assert_array_equal(dones, next_obs == TERMINAL)
    np.testing.assert_array_equal(rewards, REWARDS[obs, actions])


def test_one_shared_learner_acts_for_every_agent_in_one_batch():
    runner = shared_chain_runner(3)
    runner.start_iteration({SHARED: np.array([1.0, 0.0])}, iteration=0, total_timesteps=10)
    learner = runner.learners[SHARED]
    calls = []
    predict = learner.predict
    learner.predict = lambda obs, **kwargs: calls.append(np.shape(obs)) or predict(obs, **kwargs)
    actions = runner.learner_policy()({"agent_0": 0, "agent_1": 1, "agent_2": 2})
    assert set(actions) == {"agent_0", "agent_1", "agent_2"} and calls == [(3,)]


def test_shared_ma_sfols_finds_the_exact_ccs_on_the_chain():
    model = MASFOLS(
        ParallelChainEnv(2),
        steps_per_iteration=600,
        learner_kwargs=LEARNER_KWARGS,
        test_weights=3,
        sharing="shared",
    ).learn(max_iterations=10)
    assert model.callback.ended_by_schedule and len(model.history) < 10
    trained = [row["weights_trained"] for row in model.history]
    assert trained[:2] == [{SHARED: [1.0, 0.0]}, {SHARED: [0.0, 1.0]}]  # one weight per iteration: the extrema first
    assert {info.agent for info in model.policy_set.infos} == {SHARED}
    assert [row["timesteps"] for row in model.history] == [600 * (i + 1) for i in range(len(model.history))]
    for w0 in np.linspace(0, 1, 21):
        w = np.array([w0, 1 - w0])
        assert model.policy_set.q_values(np.array([0]), w).max() == pytest.approx(optimal_value(w), abs=1e-3)


def test_fixed_weights_with_a_shared_learner_evaluate_gpi_over_the_shared_policies():
    model = MASFOLS(
        ParallelChainEnv(2), weights=[0.3, 0.7], steps_per_iteration=300, learner_kwargs=LEARNER_KWARGS,
        sharing="shared",
    ).learn(max_iterations=2)  # fmt: skip
    assert model.callback.evaluation.policies == "shared" and len(model.policy_set) == 2
    (entry,) = model.history[-1]["test"]
    for returns in entry["agents"].values():
        assert np.dot([0.3, 0.7], returns["undiscounted"]) == pytest.approx(optimal_value(np.array([0.3, 0.7])))
    independent = MASFOLS(  # one learner per agent: each agent is evaluated by GPI over its own policies
        ParallelChainEnv(2), weights=[0.3, 0.7], steps_per_iteration=300, learner_kwargs=LEARNER_KWARGS
    )
    assert independent.callback.evaluation.policies == "own"


def test_bad_sharing_options_are_refused():
    for sharing in ("pooled", "experience"):  # experience sharing was measured and removed
        with pytest.raises(ValueError, match="sharing must be one of .*'independent', 'shared'"):
            MultiAgentRunner(ParallelChainEnv(2), sharing=sharing)
    with pytest.raises(ValueError, match="optimize_memory_usage=False"):
        MASFOLS(ParallelChainEnv(2), sharing=SHARED, learner_kwargs={**LEARNER_KWARGS, "optimize_memory_usage": True})


def test_cli_trains_with_sharing_and_refuses_to_change_it_on_resume(tmp_path):
    out = tmp_path / "fr"
    train = ["train", "four-room", "--iterations", "1", "--steps-per-iteration", "100", "--no-progress"]
    small = ["--set", "n_test_weights=2", *FEW_VALIDATION]  # sharing is tested, not validation
    assert main([*train, "--set", "sharing=shared", *small, "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["sharing"] == "shared"
    assert json.loads((out / "evaluation.json").read_text())[0]["weights_trained"].keys() == {SHARED}
    train[train.index("--iterations") + 1] = "2"
    assert main([*train, "--set", "sharing=independent", "--out", str(out), "--resume"]) == 2
    assert main([*train, "--out", str(out), "--resume"]) == 0  # the stored sharing goes on
    assert json.loads((out / "checkpoint.json").read_text())["iteration"] == 2


def test_beach_with_twenty_agents_trains_one_shared_learner():
    mobeach_v0 = pytest.importorskip("momaland.envs.beach.mobeach_v0")
    from sb3_sfgpi import SwapTerminationsTruncations

    env = SwapTerminationsTruncations(mobeach_v0.parallel_env(num_agents=20, num_timesteps=10))
    learner = dict(learning_starts=50, batch_size=16)
    model = MASFOLS(
        env,
        policy="MlpPolicy",
        steps_per_iteration=100,
        test_weights=2,
        learner_kwargs=learner,
        sharing="shared",
    ).learn(max_iterations=2)
    shared = model.runner.learners[SHARED]
    assert shared.n_envs == 20 and shared.num_timesteps == 100 * 20  # every agent's transition, every joint step
    assert len(model.history) >= 1 and all(np.isfinite(row["mean_return"]) for row in model.history)


def chain_runner(sharing: str, n_agents: int = 3) -> MultiAgentRunner:
    env = ParallelChainEnv(n_agents, staggered=True)  # agent i starts at state i: agent_1 never visits state 0
    return MultiAgentRunner(env, default_learner_factory(**CHAIN_LEARNER), sharing=sharing)


def test_an_independent_learner_learns_only_the_states_its_own_agent_visits():
    w = np.array([0.3, 0.7])
    runner = chain_runner("independent", n_agents=2)
    runner.start_iteration({name: w for name in runner.learner_names}, 0, total_timesteps=600)
    for _ in range(600):
        runner.step()
    runner.end_iteration()
    values = {
        name: (learner.successor_features(np.array([0]))[0] @ w).max() for name, learner in runner.learners.items()
    }
    assert values["agent_0"] == pytest.approx(optimal_value(w), abs=1e-3)
    assert values["agent_1"] == 0.0  # agent_1 starts at state 1: its table knows nothing of state 0
