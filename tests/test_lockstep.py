"""Episodes for many weights stepped together (one batched decision a step) give exactly the returns of the same
episodes run one after another: per-row weights in ``GPIPolicy.predict_rows``, ``run_lockstep``, and a run's test
evaluation and validation through ``MultiAgentRunner.lockstep``."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_tabular_network
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import Fig1MOMDP
from queue_lights import QueueLights

from sb3_sfgpi import MASFOLS, GPIPolicy, PadActions
from sb3_sfgpi.common.rollouts import run_episodes, run_lockstep
from sb3_sfgpi.common.weights import validate_weight_rows, validate_weights
from sb3_sfgpi.learners import default_learner_factory
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.validation import Scored, ValidationScorer

TABULAR = dict(policy="TabularPolicy", learning_rate=0.2, gamma=0.9, learning_starts=0, train_freq=1, batch_size=16)
WEIGHTS = np.random.default_rng(0).dirichlet(np.ones(2), 5)


@pytest.fixture(scope="module")
def padded_lights_set() -> GPIPolicy:
    """Tables of two padded lights (action masks, random arrivals) trained for two weights, in one set."""
    env = PadActions(QueueLights((2, 3)))
    runner = MultiAgentRunner(env, default_learner_factory(**TABULAR, buffer_size=1_500), seed=0, gamma=0.9)
    policy_set = GPIPolicy()
    for iteration, w in enumerate([np.array([0.9, 0.1]), np.array([0.2, 0.8])]):
        runner.start_iteration({agent: w for agent in runner.agents}, iteration, 1_500)
        for _ in range(1_500):
            runner.step()
        runner.end_iteration()
        for agent, learner in runner.learners.items():
            policy_set.add(learner, weights=w, agent=agent)
    return policy_set


def test_rows_with_their_own_weights_get_the_actions_of_predict(padded_lights_set):
    env = PadActions(QueueLights((2, 3)))
    observations, infos = env.reset(seed=3)
    obs = np.stack([observations[a] for a in env.agents] * len(WEIGHTS))
    masks = np.stack([infos[a]["action_mask"] for a in env.agents] * len(WEIGHTS))
    rows = np.repeat(WEIGHTS, len(env.agents), axis=0)
    actions = padded_lights_set.predict_rows(obs, rows, masks)
    for i, (o, w, m) in enumerate(zip(obs, rows, masks, strict=True)):
        assert actions[i] == padded_lights_set.predict(o, w, action_masks=m)[0]
    with pytest.raises(ValueError, match="one weight per observation"):
        padded_lights_set.predict_rows(obs, rows[:-1])
    with pytest.raises(ValueError, match="shape"):
        padded_lights_set.predict_rows(obs, rows[0])


def test_episodes_stepped_together_return_what_they_return_one_after_another(padded_lights_set):
    env = padded_lights()
    seeds = [100 * i for i in range(len(WEIGHTS))]
    policies = [padded_lights_set.joint_policy(w) for w in WEIGHTS]
    alone = [run_episodes(env, policy, 2, 0.9, seed=s) for policy, s in zip(policies, seeds, strict=True)]
    envs = [padded_lights() for _ in range(2 * len(WEIGHTS))]
    episode_seeds = [seed + episode for seed in seeds for episode in range(2)]

    def gpi(observations, weights, masks, agents):
        return padded_lights_set.predict_rows(observations, weights, masks)

    together = run_lockstep(envs, gpi, np.repeat(WEIGHTS, 2, 0), episode_seeds, 0.9, 2)
    for one, other in zip(alone, together, strict=True):
        for agent in env.possible_agents:
            np.testing.assert_array_equal(other.discounted[agent], one.discounted[agent])
            np.testing.assert_array_equal(other.undiscounted[agent], one.undiscounted[agent])
        assert len(other.final_infos) == 2
    assert len({float(r.discounted["light_0"][:, 0].sum()) for r in together}) > 1  # the weights act differently
    with pytest.raises(ValueError, match="per_result"):
        run_lockstep(envs, gpi, np.repeat(WEIGHTS, 2, 0), episode_seeds, 0.9, 3)


def padded_lights() -> PadActions:
    return PadActions(QueueLights((2, 3)))


def _lights_run(together: bool) -> MASFOLS:
    """Without ``env_fn`` the runner has no copies: the episodes run one after another."""
    model = MASFOLS(
        padded_lights(), policy="TabularPolicy", steps_per_iteration=600,
        learner_kwargs=dict(learning_rate=0.2, gamma=0.9, learning_starts=0, batch_size=16),
        test_weights=WEIGHTS, eval_episodes=2, seed=0, env_fn=padded_lights if together else None,
    )  # fmt: skip
    return model.learn(max_iterations=3)


def test_a_runs_test_evaluation_steps_its_weights_together_and_training_goes_on_the_same():
    together, alone = _lights_run(True), _lights_run(False)
    assert len(together.runner._side_by_side.copies) == 2 * len(WEIGHTS) - 1 and not alone.runner._side_by_side.copies
    together.runner.close()
    assert not together.runner._side_by_side.copies
    for mine, other in zip(together.history, alone.history, strict=True):
        assert mine["mean_return"] == other["mean_return"]
    assert [info.value.tolist() for info in together.policy_set.infos] == [
        info.value.tolist() for info in alone.policy_set.infos
    ]


def fig1() -> Fig1MOMDP:
    return Fig1MOMDP(one_hot=True)


def _scorers() -> tuple[ValidationScorer, ValidationScorer, MultiAgentRunner]:
    """Validation on the padded lights, one weight after another and stepped together (the runner's copies)."""
    runner = MultiAgentRunner(padded_lights(), default_learner_factory(**TABULAR), seed=0, gamma=0.9,
                              env_fn=padded_lights)  # fmt: skip
    weights = np.random.default_rng(1).dirichlet(np.ones(2), 6)
    alone = ValidationScorer(weights, runner.rollout, 2, 7)
    together = ValidationScorer(weights, runner.rollout, 2, 7, lockstep=runner.lockstep)
    return alone, together, runner


def _same(one: Scored, other: Scored) -> None:
    assert one.score == other.score and one.followed == other.followed
    for mine, theirs in zip(one.returns, other.returns, strict=True):
        for agent in mine.discounted:
            np.testing.assert_array_equal(mine.discounted[agent], theirs.discounted[agent])
    for mine, theirs in zip(one.decisions, other.decisions, strict=True):
        for a, b in zip(mine, theirs, strict=True):
            assert (a is None and b is None) or np.array_equal(a, b)


@pytest.fixture(scope="module")
def random_lights_set() -> GPIPolicy:
    """Random tables of the padded lights: every member decides somewhere, so leave-one-out runs weights again."""
    policy_set = GPIPolicy()
    for seed, w in enumerate(np.random.default_rng(2).dirichlet(np.ones(2), 4)):
        policy_set.add(random_tabular_network(seed, (3, 3, 3, 2, 2, 2), 3, 2), weights=w, agent=f"light_{seed % 2}")
    return policy_set


def test_validation_steps_its_weights_together_with_the_same_episodes_and_decisions(random_lights_set):
    alone, together, runner = _scorers()
    whole = alone(random_lights_set)
    _same(whole, together(random_lights_set))
    assert len(runner._side_by_side.copies) == 2 * 6 - 1  # the weights' episodes ran on copies, the last on the env
    assert together.rollouts == alone.rollouts == 6 and len(whole.decisive_members()) > 1
    for member in range(len(random_lights_set)):  # leave-one-out: only the weights where the member decided again
        _same(alone.without(random_lights_set, whole, member), together.without(random_lights_set, whole, member))
    smaller = random_lights_set.subset([0, 1])
    _same(alone.replayed(random_lights_set, alone(smaller)), together.replayed(random_lights_set, together(smaller)))
    assert together.rollouts == alone.rollouts > 6


def test_replayed_masked_decisions_roll_out_only_the_weights_where_gpi_acts_otherwise(random_lights_set):
    """Π with new policies is scored from Π's masked decisions (every weight's in one batch): each weight is rolled
    out again only where GPI over the larger set acts otherwise within the masks, and the scores are full rollouts'.
    The second new member is the first member's table with light_0's masked green (action 2, where its third approach
    flag is 0) worth the most: within the masks it changes no action, so no weight is rolled out for it."""
    scorer, _, _ = _scorers()
    tempting = random_tabular_network(0, (3, 3, 3, 2, 2, 2), 3, 2)
    table = random_lights_set.networks[0].table.dense().reshape(3, 3, 3, 2, 2, 2, 3, 2)
    table[..., 0, :, 2, :] = 1_000.0
    tempting.table.set_dense(table.reshape(tempting.table.n_rows, -1))
    smaller = random_lights_set.subset([0, 1])
    for added, replays in ((random_lights_set.networks[2], False), (tempting, True)):
        larger = smaller.subset([0, 1])
        larger.add(added, weights=[0.5, 0.5], agent="light_0")
        scored = scorer(smaller)
        assert all(masks is not None for _, masks, actions in scored.decisions if len(actions))
        acts_otherwise = sum(
            not np.array_equal(larger.predict_followed(observations, w, masks)[0], actions)
            for (observations, masks, actions), w in zip(scored.decisions, scorer.weights, strict=True)
        )
        before = scorer.rollouts
        replayed = scorer.replayed(larger, scored)
        assert scorer.rollouts - before == acts_otherwise == (0 if replays else len(scorer.weights))
        _same(replayed, scorer(larger))


ROW = st.floats(0.0, 1e308, allow_nan=False, allow_subnormal=True)


@settings(max_examples=200, deadline=None)
@given(d=st.integers(1, 12), data=st.data())
def test_weight_rows_validated_at_once_are_each_rows_validation_bit_for_bit(d, data):
    """GPI's per-row weights are validated in one pass (every step of a validation's lockstep episodes): the same
    normalised numbers as one row at a time, huge rows (whose sums overflow) included, and the same error."""
    rows = np.array(data.draw(st.lists(st.lists(ROW, min_size=d, max_size=d), min_size=1, max_size=6)))
    if (rows.max(axis=1) > 0).all():
        expected = np.array([validate_weights(row, d) for row in rows])
        assert validate_weight_rows(rows, d).tobytes() == expected.tobytes()
    bad = rows.copy()
    bad[-1, 0] = data.draw(st.sampled_from([-1.0, np.nan, np.inf]))
    with pytest.raises(ValueError) as at_once:
        validate_weight_rows(bad, d)
    with pytest.raises(ValueError) as one_by_one:
        [validate_weights(row, d) for row in bad]
    assert str(at_once.value) == str(one_by_one.value)
