"""Policy validation: a new policy joins Π only if GPI does no worse with it on the validation weights."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from momdp import N_ACTIONS, N_STATES, REWARD_DIM
from parallel_chain import CHAIN_LEARNER, ParallelChainEnv

from sb3_sfgpi import Admission, EvaluationConfig, MultiAgentRunner, OLSCallback
from sb3_sfgpi.callbacks import learn_iterations
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.common.weights import random_weights
from sb3_sfgpi.evaluation import summarize_test_episodes
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.learners import LearnerFactory, default_learner_factory
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.schedules import RandomSchedule

TEST_WEIGHTS = random_weights(2, 5, rng=0)
LIAR = ("agent_1", 1)  # agent_1's learner of the second iteration (iteration 2 in Π's infos)


def liar_factory(liar: tuple[str, int] = LIAR) -> LearnerFactory:
    """The chain's learners, except that one agent's learner of one iteration (0-based) promises 1000 of each
    objective everywhere and never learns: its greedy policy takes action A in every state, (13, 22) on the chain
    instead of the optimal 29 of objective 0. It is known by its seed, so a resumed run makes it again."""
    make = default_learner_factory(**CHAIN_LEARNER)
    agent, iteration = liar

    def factory(name, view, weights, seed):
        model = make(name, view, weights, seed)
        if seed == derive_seed(0, iteration, agent):
            model.policy.fill(1000.0)
            model.train = lambda gradient_steps, batch_size=100: None
        return model

    return factory


def run(
    n_weights: int,
    steps: int = 200,
    iterations: int = 3,
    liar: tuple[str, int] = LIAR,
    prune: bool = False,
    together: bool = False,
    factory: LearnerFactory | None = None,
    verbose: int = 0,
    **kwargs,
) -> OLSCallback:
    runner = MultiAgentRunner(ParallelChainEnv(2), factory or liar_factory(liar), seed=0)
    admission = Admission(n_weights, prune=prune, together=together, verbose=verbose)
    evaluation = EvaluationConfig(TEST_WEIGHTS)
    callback = OLSCallback(RandomSchedule(), steps, evaluation, admission=admission, verbose=verbose, **kwargs)
    learn_iterations(runner, callback, max_iterations=iterations)
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
    weights = Admission(4).weights(2, runner.seed)
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
    weights = Admission(6).weights(3, seed=5)
    assert weights.shape == (9, 3)
    np.testing.assert_array_equal(weights[:3], np.eye(3))
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert (weights >= 0).all()
    np.testing.assert_array_equal(weights, Admission(6).weights(3, seed=5))
    assert not np.allclose(weights[3:], Admission(6).weights(3, seed=6)[3:])
    assert not np.allclose(weights[3:], random_weights(3, 6, rng=0))  # not the test weights of the CLI and MASFOLS
    np.testing.assert_array_equal(Admission(0).weights(2, seed=0), np.eye(2))


@pytest.mark.parametrize("n_weights", [-1, True, 1.5])
def test_a_bad_number_of_validation_weights_is_refused(n_weights):
    with pytest.raises(ValueError, match="validation_weights must be a non-negative integer"):
        Admission(n_weights)


def test_validation_is_refused_where_agents_act_on_their_own_policies():
    with pytest.raises(ValueError, match="episodes"):
        Admission(2, episodes=0)
    with pytest.raises(ValueError, match="own"):
        own = EvaluationConfig(TEST_WEIGHTS, policies="own")
        OLSCallback(RandomSchedule(), 10, own, admission=Admission(2))
    with pytest.raises(ValueError, match="own"):
        MASFOLS(ParallelChainEnv(2), weights=[0.5, 0.5], validation_weights=2)


# --- pruning --------------------------------------------------------------------------------------------------------
FIRST_LIAR = ("agent_0", 0)  # the first policy of the run: it joins an empty Π, and GPI follows it everywhere


def test_pruning_retires_a_policy_that_misleads_gpi_once_better_ones_are_there():
    kept, pruned = run(4, liar=FIRST_LIAR), run(4, liar=FIRST_LIAR, prune=True)
    liar = ("agent_0", 1)
    assert liar in [(info.agent, info.iteration) for info in kept.policy_set.infos]  # admission alone keeps it
    assert liar not in [(info.agent, info.iteration) for info in pruned.policy_set.infos]
    retired = {(info.agent, info.iteration): info.retired for info in pruned.record.infos}
    assert retired[liar] == 1  # retired after the iteration that made it: agent_1's first policy replaces it
    assert [i for i in retired.values() if i is not None] == [1]
    assert len(pruned.record) == len(pruned.policy_set) + 1
    # training is the same; GPI is better from the first iteration on
    assert json.dumps(pruned.schedule.state_dict()) == json.dumps(kept.schedule.state_dict())
    for with_it, without_it in zip(pruned.history, kept.history, strict=True):
        assert with_it["mean_return"] > without_it["mean_return"]
        assert with_it["n_policies"] < without_it["n_policies"]


def test_after_pruning_no_single_policy_left_out_makes_gpi_better():
    callback = run(4, steps=40, iterations=6, prune=True)  # short training: policies of every quality
    runner, policy_set = callback.model, callback.policy_set
    score = validation_score(runner, policy_set)
    assert score == pytest.approx(callback.admission._current(policy_set))  # its cached score
    for i in range(len(policy_set)):
        assert validation_score(runner, policy_set.subset(j for j in range(len(policy_set)) if j != i)) <= score


def test_a_pruned_run_continues_exactly_and_saves_its_record(tmp_path):
    whole = run(4, liar=FIRST_LIAR, prune=True, run_dir=tmp_path / "whole")
    run(4, iterations=1, liar=FIRST_LIAR, prune=True, run_dir=tmp_path / "cut")
    continued = run(4, liar=FIRST_LIAR, prune=True, run_dir=tmp_path / "cut", resume=True)
    assert [r["mean_return"] for r in continued.history] == [r["mean_return"] for r in whole.history]
    for a, b in ((continued.record, whole.record), (continued.policy_set, whole.policy_set)):
        assert [(i.agent, i.iteration, i.retired) for i in a.infos] == [
            (i.agent, i.iteration, i.retired) for i in b.infos
        ]
    saved = GPIPolicy.load(tmp_path / "cut" / "policy_set")  # a user's load: Π, without the retired policy
    assert [(i.agent, i.iteration) for i in saved.infos] == [(i.agent, i.iteration) for i in whole.policy_set.infos]
    assert len(GPIPolicy.load(tmp_path / "cut" / "policy_set", retired=True)) == len(whole.record)


def test_pruning_needs_validation_weights():
    with pytest.raises(ValueError, match="pruning Π needs validation weights: validation_weights must be positive"):
        Admission(0, prune=True)
    assert Admission(1, prune=True).prune


# --- admitting together ---------------------------------------------------------------------------------------------
A, B, C = range(N_ACTIONS)  # the chain's rewards: s0 A (1, 9), B (8, 9), C (1, 5); s1 A (8, 7), B (7, 7), C (5, 2);
# s2 A (3, 6), B (9, 0), C (6, 1); s3 A (1, 0), B (4, 8), C (0, 5)


def promising(choices: dict[int, tuple[int, float]]) -> np.ndarray:
    """A ψ table that promises ``(v, v)`` for one action in some states (state -> (action, v)), 0 elsewhere: GPI
    follows, in each state, the table that promises most, whatever the weights."""
    table = np.zeros((N_STATES, N_ACTIONS, REWARD_DIM), dtype=np.float32)
    for state, (action, v) in choices.items():
        table[state, action] = v
    return table


FIRST = promising({0: (A, 10), 1: (B, 10), 2: (C, 10), 3: (C, 10)})  # (14, 22): second best in s0, s1 and s3
#: Two agents' policies of the second iteration: one leads GPI to a worse action in s0 (by (0, 4)) and a better one in
#: s1 (by (1, 0)), the other to a better one in s0 (by (7, 0)) and a worse one in s1 (by (2, 5)). Each alone is worse
#: than Π on the validation weights (their mean is (0.32, 0.68)); together each one's promise outbids the other's
#: where it leads to the better action.
HALVES = (promising({0: (C, 20), 1: (A, 40)}), promising({0: (B, 30), 1: (C, 30)}))


def frozen_factory(tables: dict[tuple[str, int], np.ndarray]) -> LearnerFactory:
    """The chain's learners with the ψ tables given by (agent, 0-based iteration), that never learn."""
    make = default_learner_factory(**CHAIN_LEARNER)
    by_seed = {derive_seed(0, iteration, agent): table for (agent, iteration), table in tables.items()}

    def factory(name, view, weights, seed):
        model = make(name, view, weights, seed)
        model.policy.sf_net.table.set_dense(by_seed[seed].reshape(N_STATES, -1))
        model.policy.sf_net_target.load_state_dict(model.policy.sf_net.state_dict())
        model.train = lambda gradient_steps, batch_size=100: None
        return model

    return factory


HALVES_RUN = frozen_factory(
    {("agent_0", 0): FIRST, ("agent_1", 0): FIRST, ("agent_0", 1): HALVES[0], ("agent_1", 1): HALVES[1]}
)


def test_policies_that_only_help_gpi_together_join_together():
    one_by_one = run(4, iterations=2, factory=HALVES_RUN)
    together = run(4, iterations=2, together=True, factory=HALVES_RUN)
    runner, policy_set = together.model, together.policy_set
    first, *alone = (validation_score(runner, policy_set.subset(members)) for members in ([0], [0, 1], [0, 2]))
    assert max(alone) < first < validation_score(runner, policy_set)  # each alone makes GPI worse, both better
    assert [(i.agent, i.iteration) for i in one_by_one.policy_set.infos] == [("agent_0", 1)]
    assert [(i.agent, i.iteration) for i in together.policy_set.infos] == [
        ("agent_0", 1), ("agent_0", 2), ("agent_1", 2)
    ]  # fmt: skip
    assert len(one_by_one.record) == 1 and len(together.record) == 3  # left out: not in the run's record
    assert together.admission._current(policy_set) == pytest.approx(validation_score(runner, policy_set))
    assert together.history[1]["mean_return"] > one_by_one.history[1]["mean_return"]
    # the same weights were trained and the same values went to the schedule
    assert json.dumps(together.schedule.state_dict()) == json.dumps(one_by_one.schedule.state_dict())


def test_policies_that_are_worse_together_stay_out(capsys):
    worse = promising({1: (C, 50)})  # outbids HALVES[0] in s1 and leads GPI to the worst action there
    tables = {("agent_0", 0): FIRST, ("agent_1", 0): FIRST, ("agent_0", 1): HALVES[0], ("agent_1", 1): worse}
    callback = run(4, iterations=2, together=True, factory=frozen_factory(tables), verbose=1)
    assert "agent_0 and agent_1's policies together left out of Π" in capsys.readouterr().out  # tried, kept out
    assert [(i.agent, i.iteration) for i in callback.policy_set.infos] == [("agent_0", 1)]
    assert len(callback.record) == 1
    score = validation_score(callback.model, callback.policy_set)
    assert callback.admission._current(callback.policy_set) == pytest.approx(score)


def test_policies_that_tie_together_join_together():
    # each alone leads GPI to a worse action (s0: C; s1: C); together each outbids the other where it leads to
    # FIRST's action (s0: A, s1: B): GPI takes FIRST's actions everywhere and does exactly as well as without them
    ties = (promising({0: (C, 20), 1: (B, 40)}), promising({0: (A, 30), 1: (C, 30)}))
    tables = {("agent_0", 0): FIRST, ("agent_1", 0): FIRST, ("agent_0", 1): ties[0], ("agent_1", 1): ties[1]}
    callback = run(4, iterations=2, together=True, factory=frozen_factory(tables))
    runner, policy_set = callback.model, callback.policy_set
    first, *alone = (validation_score(runner, policy_set.subset(members)) for members in ([0], [0, 1], [0, 2]))
    assert max(alone) < first == validation_score(runner, policy_set)  # a tie: "no worse" admits them
    assert [(i.agent, i.iteration) for i in policy_set.infos] == [("agent_0", 1), ("agent_0", 2), ("agent_1", 2)]
    assert len(callback.record) == 3


def test_admitting_together_needs_validation_weights():
    with pytest.raises(ValueError, match="together needs validation weights: validation_weights must be positive"):
        Admission(0, together=True)
    assert Admission(1, together=True).together
