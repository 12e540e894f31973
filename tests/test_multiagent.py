"""MultiAgentRunner: independent learners stepping one ParallelEnv in lockstep."""

from __future__ import annotations

import numpy as np
import pytest
from parallel_chain import ParallelChainEnv, make_chain_runner

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.callbacks import OLSCallback, learn_iterations
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import EvaluationConfig
from sb3_sfgpi.multiagent import AgentVecEnv
from sb3_sfgpi.schedules import OLSSchedule

TEST_WEIGHTS = random_weights(2, 5, rng=0)


def test_early_finishing_agents_store_no_transitions_and_truncation_bootstraps():
    runner = make_chain_runner(max_steps=2)  # truncated after two steps, before the terminal state
    learn_iterations(runner, OLSCallback(OLSSchedule(), 40, EvaluationConfig(TEST_WEIGHTS)), max_iterations=1)
    for learner in runner.learners.values():
        buffer = learner.replay_buffer
        n = buffer.pos
        assert n == 40  # one transition per joint step: both agents are live every step
        dones, timeouts = buffer.dones[:n, 0], buffer.timeouts[:n, 0]
        assert np.all(dones[1::2] == 1) and np.all(timeouts[1::2] == 1)  # every 2nd step is a truncation


def test_agent_view_cannot_be_stepped_alone():
    runner = make_chain_runner()
    with pytest.raises(RuntimeError, match="MultiAgentRunner steps the shared env"):
        runner.views["agent_0"].step(np.array([0]))
    assert isinstance(runner.views["agent_0"], AgentVecEnv)


def test_learn_without_a_callback_is_refused():
    with pytest.raises(ValueError, match="runner-level callback"):
        make_chain_runner().learn(10)


class ThreeRewardsForTwo(ParallelChainEnv):
    """A chain whose rewards have three components while its reward space declares two."""

    def step(self, actions):
        obs, rewards, *rest = super().step(actions)
        return (obs, {agent: np.append(r, 0.0) for agent, r in rewards.items()}, *rest)


def test_a_reward_of_another_shape_than_the_reward_space_is_refused_naming_both():
    model = MASFOLS(ThreeRewardsForTwo(2), policy="TabularPolicy", steps_per_iteration=10, seed=0)
    with pytest.raises(
        ValueError, match=r"agent 'agent_0', step 1: the reward has shape \(3,\), its reward_space \(2,\)"
    ):
        model.learn(max_iterations=1)
