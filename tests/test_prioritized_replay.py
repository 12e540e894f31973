"""Prioritised replay (``PrioritizedMOReplayBuffer``): the sum tree against numpy, draws in proportion to the
priorities, priorities from the TD errors for the learner's weights (scored again when the weights change), exact SFs
learned with it, and what it refuses."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import Fig1MOMDP, observation, optimal_policy, successor_features

from sb3_sfgpi.common.prioritized_buffer import REPLAY_BUFFERS, PrioritizedMOReplayBuffer, SumTree
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.trust import REPLAY_BUFFER_NAMES, check_learner_kwargs

SUPPORT = np.array([[0.8, 0.2], [0.3, 0.7]])
GAMMA = 0.9


@settings(max_examples=50, deadline=None)
@given(
    n=st.integers(1, 300),
    data=st.data(),
)
def test_the_tree_holds_the_sum_and_the_maximum_of_its_leaves_after_any_writes(n, data):
    tree, leaves = SumTree(n), np.zeros(n)
    for _ in range(data.draw(st.integers(1, 5))):
        rows = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=20, unique=True)))
        values = np.array(data.draw(st.lists(st.floats(0, 100), min_size=len(rows), max_size=len(rows))))
        tree.set(rows, values)
        leaves[rows] = values
    assert tree.total == pytest.approx(leaves.sum(), rel=1e-12, abs=1e-12)
    assert tree.max == leaves.max()
    np.testing.assert_array_equal(tree.leaves(slice(0, n)), leaves)
    if tree.total > 0:  # any mass finds a positive leaf, and the one whose cumulative interval holds it
        masses = np.array(data.draw(st.lists(st.floats(0, 1, exclude_max=True), min_size=1, max_size=10)))
        found = tree.find(masses * tree.total)
        assert (leaves[found] > 0).all()
        after = np.cumsum(leaves)  # the leaf's interval holds the mass, up to the sums' rounding
        tolerance = 1e-12 * tree.total
        assert ((after[found] - leaves[found] <= masses * tree.total + tolerance)
                & (masses * tree.total <= after[found] + tolerance)).all()  # fmt: skip


def _buffer(n: int = 100, **kwargs) -> PrioritizedMOReplayBuffer:
    return PrioritizedMOReplayBuffer(
        n, spaces.Box(-1, 1, (2,)), spaces.Discrete(3), device="cpu", reward_dim=2, **kwargs
    )


def _fill(buffer: PrioritizedMOReplayBuffer, k: int) -> None:
    for i in range(k):
        obs = np.full((1, 2), i / 100, dtype=np.float32)
        buffer.add(obs, obs, np.array([[i % 3]]), np.array([[1.0, 0.0]]), np.array([False]), [{}])


def test_new_transitions_get_the_highest_priority_and_the_errors_set_the_others():
    buffer = _buffer(alpha=0.5, min_priority=0.01)
    _fill(buffer, 3)
    np.testing.assert_array_equal(buffer.tree.leaves(slice(0, 4)), [1.0, 1.0, 1.0, 0.0])  # empty buffer: 1
    buffer.update_priorities(np.array([0, 1, 2]), th.tensor([4.0, -0.0001, -9.0]))
    np.testing.assert_allclose(buffer.tree.leaves(slice(0, 3)), [2.0, 0.1, 3.0])  # |error| ≥ 0.01, to the 0.5
    _fill(buffer, 1)
    assert buffer.tree.leaves(slice(3, 4))[0] == 3.0


def test_draws_follow_the_priorities_and_alpha_zero_draws_uniformly():
    np.random.seed(0)
    skewed, flat = _buffer(), _buffer(alpha=0.0)
    for buffer in (skewed, flat):
        _fill(buffer, 50)
        buffer.update_priorities(np.arange(50), np.where(np.arange(50) == 7, 10.0, 0.0))
    counts = np.bincount(np.concatenate([skewed.sample(50).rows for _ in range(400)]), minlength=50)
    share = 10.0**0.6 / (10.0**0.6 + 49 * 0.01**0.6)  # 0.63
    assert abs(counts[7] / counts.sum() - share) < 0.02
    counts = np.bincount(np.concatenate([flat.sample(50).rows for _ in range(400)]), minlength=50)
    assert counts.min() > 0.7 * counts.mean()
    batch = skewed.sample(8)
    np.testing.assert_allclose(batch.observations.numpy()[:, 0], batch.rows / 100, atol=1e-7)  # rows are the rows


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(alpha=1.5), "alpha must be in"),
        (dict(min_priority=0.0), "min_priority must be above zero"),
        (dict(optimize_memory_usage=True), "does not take optimize_memory_usage"),
    ],
)
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _buffer(**kwargs)


def test_a_table_refuses_prioritised_replay():
    with pytest.raises(ValueError, match="prioritised replay is for network policies"):
        SFDQN("TabularPolicy", Fig1MOMDP(), replay_buffer_class=PrioritizedMOReplayBuffer)


def _learner(policy: str, **kwargs) -> SFDQN:
    return SFDQN(
        policy, Fig1MOMDP(one_hot=True), weights=SUPPORT[0], learning_rate=1e-3, gamma=GAMMA, batch_size=64,
        learning_starts=200, target_update_interval=100, exploration_initial_eps=1.0, exploration_final_eps=1.0,
        buffer_size=5_000, replay_buffer_class=PrioritizedMOReplayBuffer, seed=0, **kwargs,
    )  # fmt: skip


def _errors_for(model: SFDQN, rows: np.ndarray) -> np.ndarray:
    buffer = model.replay_buffer
    with th.no_grad():
        return model.policy.weighted_errors(*model.policy.current_and_target(buffer.samples_at(rows), GAMMA)).numpy()


@pytest.mark.parametrize("policy", ["MlpPolicy", "ConditionedMlpPolicy"])
def test_priorities_are_the_errors_for_the_weights_and_are_scored_again_for_new_weights(policy):
    model = _learner(policy, policy_kwargs=dict(net_arch=[16]))
    model.learn(400)
    buffer = model.replay_buffer
    np.random.seed(1)
    rows = buffer.sample(64).rows
    expected = np.maximum(_errors_for(model, rows), 0.01) ** 0.6  # before the step
    np.random.seed(1)
    model.policy.td_update(buffer, 64, GAMMA, 10.0)  # draws the same rows, and gives their errors back
    np.testing.assert_allclose(buffer.tree.leaves(rows), expected, rtol=1e-6)
    model.set_weights(SUPPORT[1])
    model.learn(0, reset_num_timesteps=False)  # learning for new weights starts by scoring every row for them
    every = np.arange(400)
    np.testing.assert_allclose(buffer.tree.leaves(every), np.maximum(_errors_for(model, every), 0.01) ** 0.6, rtol=1e-6)


def test_a_conditioned_learner_with_prioritised_replay_learns_the_exact_successor_features():
    model = _learner("ConditionedMlpPolicy", train_freq=1, policy_kwargs=dict(net_arch=[64, 64], n_heads=1))
    model.set_weight_support(SUPPORT)
    model.learn(1_500)
    for w in SUPPORT:
        exact = successor_features(optimal_policy(w, GAMMA), GAMMA)
        for state in range(4):
            obs = th.as_tensor(observation(state, one_hot=True)).reshape(1, -1)
            with th.no_grad():
                psi = model.policy.sf_net(obs, th.as_tensor(w, dtype=th.float32))[0].numpy()
            np.testing.assert_allclose(psi, exact[state], atol=0.1)


def test_a_learner_takes_the_buffer_by_name_as_a_run_file_gives_it():
    model = SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True), replay_buffer_class="PrioritizedMOReplayBuffer",
                  replay_buffer_kwargs={"alpha": 0.5}, buffer_size=100)  # fmt: skip
    assert isinstance(model.replay_buffer, PrioritizedMOReplayBuffer) and model.replay_buffer.alpha == 0.5
    with pytest.raises(ValueError, match="unknown replay_buffer_class 'Prioritised'"):
        SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True), replay_buffer_class="Prioritised")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"replay_buffer_class": "os.system"}, "'replay_buffer_class' must be one of MOReplayBuffer, Prioritized"),
        ({"replay_buffer_kwargs": [0.6]}, "'replay_buffer_kwargs' must be an object"),
        ({"replay_buffer_kwargs": {"beta": 0.4}}, "replay buffer argument 'beta' is not taken from a run file"),
        ({"replay_buffer_kwargs": {"alpha": "0.6"}}, "replay buffer argument 'alpha' must be a number"),
    ],
)
def test_a_run_file_names_only_known_buffers_with_numbers_for_their_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        check_learner_kwargs(kwargs, "run.json")
    check_learner_kwargs({"replay_buffer_class": "PrioritizedMOReplayBuffer", "replay_buffer_kwargs": {"alpha": 1}}, "")
    assert REPLAY_BUFFER_NAMES == tuple(REPLAY_BUFFERS)  # what a run file names is what a learner resolves
