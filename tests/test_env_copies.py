"""Training on several copies of the env, each in its own process (``n_envs``)."""

from __future__ import annotations

import functools
import json
import warnings

import numpy as np
import pytest
from momdp import REWARDS, TERMINAL
from parallel_chain import CHAIN_LEARNER, FailingChain, ParallelChainEnv, optimal_value

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.gym_domains import make_gym_env
from sb3_sfgpi.common.env_copies import EnvCopies, SideBySide, build_copy
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner

LEARNER_KWARGS = {k: v for k, v in CHAIN_LEARNER.items() if k != "policy"}


def test_every_copy_feeds_every_learner_a_slot_per_agent():
    kwargs = dict(n_agents=2, staggered=True)
    runner = MultiAgentRunner(
        ParallelChainEnv(**kwargs), default_learner_factory(**CHAIN_LEARNER), n_envs=3, env_fn=ParallelChainEnv,
        env_kwargs=kwargs,
    )  # fmt: skip
    try:
        runner.start_iteration({a: np.array([0.5, 0.5]) for a in runner.agents}, iteration=0, total_timesteps=100)
        for _ in range(8):  # two episodes of 4 joint steps in each of the 3 copies
            runner.step()
        for agent, learner in runner.learners.items():
            per_copy = 4 if agent == "agent_0" else 3  # agent_1 starts one state further: 3 steps an episode
            assert learner.n_envs == 3 and learner._n_calls == 2 * per_copy
            assert learner.num_timesteps == 3 * 2 * per_copy
            obs, actions, next_obs, dones, rewards = learner.replay_buffer.stored_arrays()
            obs, next_obs = obs.reshape(-1), next_obs.reshape(-1)
            assert len(obs) == 3 * 2 * per_copy
            np.testing.assert_array_equal(next_obs, obs + 1)
            np.testing.assert_array_equal(dones, next_obs == TERMINAL)
            np.testing.assert_array_equal(rewards, REWARDS[obs, actions])
    finally:
        runner.close()


def test_ma_sfols_on_two_copies_finds_the_exact_ccs_and_continues_exactly(tmp_path):
    def make(run_dir):
        return MASFOLS(
            ParallelChainEnv(2), steps_per_iteration=300, learner_kwargs=LEARNER_KWARGS,
            test_weights=3, seed=2, n_envs=2, env_fn=functools.partial(ParallelChainEnv, n_agents=2),
            run_dir=run_dir,
        )  # fmt: skip

    whole = make(tmp_path / "whole").learn(max_iterations=10)
    whole.close()
    assert whole.callback.ended_by_schedule
    for w0 in np.linspace(0, 1, 11):
        w = np.array([w0, 1 - w0])
        assert whole.policy_set.q_values(np.array([0]), w).max() == pytest.approx(optimal_value(w), abs=1e-3)
    cut = make(tmp_path / "cut")
    cut.learn(max_iterations=1)
    cut.close()
    continued = MASFOLS.load(
        tmp_path / "cut", ParallelChainEnv(2), env_fn=functools.partial(ParallelChainEnv, n_agents=2)
    )
    continued.learn(max_iterations=10)
    continued.close()
    assert [r["mean_return"] for r in continued.history] == [r["mean_return"] for r in whole.history]
    assert [r["weights_trained"] for r in continued.history] == [r["weights_trained"] for r in whole.history]


def test_a_broken_copy_stops_training_with_its_error_and_bad_options_are_refused():
    copies = EnvCopies(FailingChain, {"n_agents": 2}, 2)
    try:
        copies.reset([0, 1])
        copies.step([{"agent_0": 0, "agent_1": 0}] * 2)
        copies.step([{"agent_0": 0, "agent_1": 0}] * 2)
        with pytest.raises(RuntimeError, match="env copy 0 failed: ValueError: the simulator broke"):
            copies.step([{"agent_0": 0, "agent_1": 0}] * 2)
    finally:
        copies.close()
    with pytest.raises(ValueError, match="n_envs > 1 needs env_fn"):
        MultiAgentRunner(ParallelChainEnv(2), n_envs=2)
    with pytest.raises(ValueError, match="n_envs must be a positive integer"):
        MultiAgentRunner(ParallelChainEnv(2), n_envs=0)


def test_cli_trains_on_copies_and_refuses_to_change_their_number_on_resume(tmp_path):
    out = tmp_path / "fr"
    train = ["train", "four-room", "--iterations", "1", "--steps-per-iteration", "100", "--no-progress",
             "--set", "n_test_weights=2", "--set", "validation_weights=0", "--set", "prune=false"]  # fmt: skip
    assert main([*train, "--set", "n_envs=2", "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["n_envs"] == 2
    assert json.loads((out / "checkpoint.json").read_text())["timesteps"] == 100  # joint steps, as with one env
    train[train.index("--iterations") + 1] = "2"
    assert main([*train, "--set", "n_envs=1", "--out", str(out), "--resume"]) == 2
    assert main([*train, "--out", str(out), "--resume"]) == 0
    assert main([*train, "--set", "n_envs=0", "--out", str(tmp_path / "bad")]) == 2


class WarningChain(ParallelChainEnv):
    """The chain, whose constructor warns (as MO-Gymnasium's minecart does of its spaces' bounds)."""

    def __init__(self, **kwargs):
        warnings.warn("a constructor's warning", UserWarning, stacklevel=2)
        super().__init__(**kwargs)


def test_copies_are_built_without_their_constructors_warnings_which_the_original_gave():
    with pytest.warns(UserWarning, match="a constructor's warning"):
        env = WarningChain(n_agents=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        envs = SideBySide(env, WarningChain, {"n_agents": 2}).envs(4)
        copy = build_copy(WarningChain, {"n_agents": 2})
    assert not caught
    assert len(envs) == 4 and envs[-1] is env and copy.possible_agents == env.possible_agents


def test_gym_ids_step_vector_rewards_without_gymnasiums_scalar_reward_warning():
    env = make_gym_env("deep-sea-treasure-v0")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(seed=0)
        _, rewards, *_ = env.step({agent: 0 for agent in env.agents})
    assert not caught
    assert all(np.shape(reward) == (2,) for reward in rewards.values())
