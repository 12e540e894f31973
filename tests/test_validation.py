"""Policy validation: a new policy joins Π only if GPI does no worse with it on the validation weights."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv

from sb3_sfgpi import EvaluationConfig, MultiAgentRunner, OLSCallback, PolicyValidation
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import summarize_test_episodes
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.multiagent import LearnerFactory, default_learner_factory
from sb3_sfgpi.schedules import RandomSchedule

TEST_WEIGHTS = random_weights(2, 5, rng=0)
LIAR_CALL = 3  # the learners are made agent by agent: the 4th is agent_1's of iteration 1


def liar_factory() -> LearnerFactory:
    """The chain's learners, except that agent_1's learner of iteration 1 promises 1000 of each objective everywhere
    and never learns: its greedy policy takes action A in every state, (13, 22) on the chain instead of the optimal
    29 of objective 0."""
    make, calls = default_learner_factory(**CHAIN_LEARNER), itertools.count()

    def factory(agent, view, weights, seed):
        model = make(agent, view, weights, seed)
        if next(calls) == LIAR_CALL:
            model.policy.fill(1000.0)
            model.train = lambda gradient_steps, batch_size=100: None
        return model

    return factory


def run(n_weights: int, steps: int = 200, iterations: int = 3) -> OLSCallback:
    runner = MultiAgentRunner(ParallelChainEnv(2), liar_factory(), seed=0)
    validation = PolicyValidation(n_weights)
    evaluation = EvaluationConfig(TEST_WEIGHTS)
    callback = OLSCallback(RandomSchedule(), steps, evaluation, validation=validation, max_iterations=iterations)
    runner.learn(iterations * steps, callback)
    return callback


def test_a_policy_that_overestimates_is_left_out_and_training_is_the_same():
    without, validated = run(0), run(4)
    kept = [(info.agent, info.iteration) for info in without.policy_set.infos]
    assert ("agent_1", 2) in kept  # the liar's value was new: without validation it joins Π
    assert [(info.agent, info.iteration) for info in validated.policy_set.infos] == [
        key for key in kept if key != ("agent_1", 2)
    ]
    # the liar's value still went to the schedule: the same weights were trained, the same values estimated
    assert json.dumps(validated.schedule.state_dict()) == json.dumps(without.schedule.state_dict())
    assert [r["weights_trained"] for r in validated.history] == [r["weights_trained"] for r in without.history]
    # GPI follows the liar wherever it is in Π: from iteration 1 on it is worse without validation
    assert validated.history[0]["mean_return"] == without.history[0]["mean_return"]
    for with_it, without_it in zip(validated.history[1:], without.history[1:], strict=True):
        assert with_it["mean_return"] > without_it["mean_return"]


def validation_score(runner: MultiAgentRunner, policy_set) -> float:
    """The rule restated: mean over the validation weights and agents of GPI's discounted w·return."""
    weights = PolicyValidation(4).weights(2, runner.seed)
    returns = [
        runner.rollout(policy_set.joint_policy(w), 1, derive_seed(runner.seed, "validation", i))
        for i, w in enumerate(weights)
    ]
    return summarize_test_episodes(weights, returns)[0]["mean_return"]


def test_gpi_on_the_validation_weights_never_gets_worse():
    callback = run(4, steps=40, iterations=8)  # short training: policies of every quality
    policy_set = callback.policy_set  # Π grew policy by policy: every prefix of it was Π at some point
    scores = [validation_score(callback.model, policy_set.subset(range(n))) for n in range(1, len(policy_set) + 1)]
    assert len(scores) >= 4
    assert all(later >= earlier for earlier, later in itertools.pairwise(scores))


def test_validation_weights_are_the_extrema_then_draws_of_the_runs_seed():
    weights = PolicyValidation(6).weights(3, seed=5)
    assert weights.shape == (9, 3)
    np.testing.assert_array_equal(weights[:3], np.eye(3))
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert (weights >= 0).all()
    np.testing.assert_array_equal(weights, PolicyValidation(6).weights(3, seed=5))
    assert not np.allclose(weights[3:], PolicyValidation(6).weights(3, seed=6)[3:])
    assert not np.allclose(weights[3:], random_weights(3, 6, rng=0))  # not the test weights of the CLI and MASFOLS
    np.testing.assert_array_equal(PolicyValidation(0).weights(2, seed=0), np.eye(2))


@pytest.mark.parametrize("n_weights", [-1, True, 1.5])
def test_a_bad_number_of_validation_weights_is_refused(n_weights):
    with pytest.raises(ValueError, match="n_weights"):
        PolicyValidation(n_weights)


def test_validation_is_refused_where_agents_act_on_their_own_policies():
    with pytest.raises(ValueError, match="episodes"):
        PolicyValidation(2, episodes=0)
    with pytest.raises(ValueError, match="own"):
        own = EvaluationConfig(TEST_WEIGHTS, policies="own")
        OLSCallback(RandomSchedule(), 10, own, validation=PolicyValidation(2))
    with pytest.raises(ValueError, match="own"):
        MASFOLS(ParallelChainEnv(2), weights=[0.5, 0.5], validation_weights=2)
