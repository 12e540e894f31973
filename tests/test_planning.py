"""Dyna-style planning of tabular SFs: the empirical model's backup, exact on hand-made and Fig. 1 models."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIG1_TABULAR_KWARGS
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import N_STATES, REWARDS, TERMINAL, Fig1MOMDP, all_observations, optimal_value, successor_features

from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.tabular.planning import TOLERANCE, Experience
from sb3_sfgpi.tabular.sparse import SparseTable


def sparse(table: np.ndarray, n_actions: int, default: float = 0.0) -> SparseTable:
    """``table`` (one row per ``(state, action)``) as a table storing the states whose rows differ from ``default``."""
    n_states = len(table) // n_actions
    stored = SparseTable(n_states, n_actions * table.shape[1], default)
    stored.set_dense(table.reshape(n_states, -1))
    return stored


def test_a_stochastic_model_is_backed_up_with_its_empirical_probabilities():
    # s0 -a0-> s1 twice (reward (1, 0)), s0 -a0-> end once (reward (0, 3)); s1 -a0-> end (reward (2, 2)).
    rows, actions = np.array([0, 0, 0, 1]), np.zeros(4, dtype=np.int64)
    next_rows, dones = np.array([1, 1, 2, 2]), np.array([0.0, 0.0, 1.0, 1.0])
    rewards = np.array([[1, 0], [1, 0], [0, 3], [2, 2]], dtype=np.float32)
    model = Experience.from_transitions(rows, actions, next_rows, dones, rewards, n_rows=3, n_actions=1).model()
    table = SparseTable(3, 2)
    assert model.sweep(table, np.array([0.5, 0.5], np.float32), gamma=0.5, max_sweeps=50) < 50
    # ψ(s1) = (2, 2); ψ(s0) = 2/3 · ((1, 0) + 0.5 · (2, 2)) + 1/3 · (0, 3) = (4/3, 5/3); the end state stays 0.
    np.testing.assert_allclose(table.dense(), [[4 / 3, 5 / 3], [2, 2], [0, 0]], rtol=1e-6)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 0.5, 0.9]))
def test_sweeps_reach_value_iteration_on_the_empirical_model(seed, gamma):
    rng = np.random.default_rng(seed)
    n_states, n_actions, n = 4, 2, 40
    rows, actions = rng.integers(0, n_states, n), rng.integers(0, n_actions, n)
    next_rows, dones = rng.integers(0, n_states, n), (rng.random(n) < 0.3).astype(np.float64)
    rewards = rng.integers(0, 3, (n, 2)).astype(np.float32)
    w = np.array([0.3, 0.7], dtype=np.float32)
    model = Experience.from_transitions(rows, actions, next_rows, dones, rewards, n_states, n_actions).model()
    table = SparseTable(n_states, n_actions * 2)
    model.sweep(table, w, gamma, max_sweeps=2_000)

    # Value iteration, by hand, on the counts: one (s, a) at a time, every transition weighted equally.
    expected = np.zeros((n_states, n_actions, 2))
    for _ in range(2_000):
        previous, expected = expected, np.zeros_like(expected)
        for s, a in set(zip(rows.tolist(), actions.tolist(), strict=True)):
            seen = (rows == s) & (actions == a)
            following = previous[next_rows[seen], (previous[next_rows[seen]] @ w).argmax(axis=1)]
            expected[s, a] = np.mean(rewards[seen] + gamma * (1 - dones[seen])[:, None] * following, axis=0)
        if np.abs(expected - previous).max() < 1e-12:  # the fixed point, to far below the tolerance (γ <= 0.9)
            break
    np.testing.assert_allclose(table.dense().reshape(n_states, n_actions, 2), expected, atol=1e-4)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.integers(1, 8))
def test_a_sweep_is_the_jacobi_backup_of_the_whole_table_to_the_last_bit(seed, deterministic, max_sweeps):
    # The sweeps work on a copy of the rows they touch: the result must be that of backing up every recorded pair
    # from the whole table, one pair at a time, with the same arithmetic; rows never recorded must stay as they were.
    rng = np.random.default_rng(seed)
    n_states, n_actions, n = 50, 3, 60
    rows = rng.integers(0, n_states, n)
    actions = rng.integers(0, n_actions, n)
    next_rows = (rows * 7 + actions) % n_states if deterministic else rng.integers(0, n_states, n)
    dones, rewards = (rng.random(n) < 0.2).astype(np.float64), rng.random((n, 3)).astype(np.float32)
    model = Experience.from_transitions(rows, actions, next_rows, dones, rewards, n_states, n_actions).model()
    table = rng.normal(size=(n_states * n_actions, 3)).astype(np.float32)
    table[rng.random(len(table)) < 0.3] = 1.25  # optimistic untried pairs: exact ties between actions
    table.reshape(n_states, -1)[rng.random(n_states) < 0.3] = 1.25  # and untried states: not stored below
    weights = rng.dirichlet(np.ones(3)).astype(np.float32)
    expected, expected_sweeps = table.copy(), 0
    while expected_sweeps < max_sweeps:
        previous, expected_sweeps = expected.copy(), expected_sweeps + 1
        for pair, entry in enumerate(model.entries):
            backed_up = np.zeros(3)
            for o in np.flatnonzero(model.pair == pair):
                first = model.next_first[o]
                following = previous[first + (previous[first : first + n_actions] @ weights).argmax()]
                scale = 0.9 * model.continues[o] * model.probability[o]
                backed_up = backed_up + (model.reward[o] * model.probability[o] + scale * following)
            expected[entry] = backed_up
        if np.abs(expected - previous).max() <= TOLERANCE:
            break
    stored = sparse(table, n_actions, default=1.25)
    assert model.sweep(stored, weights, 0.9, max_sweeps) == expected_sweeps
    np.testing.assert_array_equal(stored.dense().reshape(-1, 3), expected)


@pytest.mark.parametrize("w", [[1.0, 0.0], [0.0, 1.0], [0.4, 0.6]])
def test_planning_on_a_fully_explored_fig1_gives_the_optimal_sfs(w):
    # Uniformly random actions, no TD updates: every (s, a) is recorded, and only planning learns.
    model = SFDQN(
        "TabularPolicy", Fig1MOMDP(), weights=w, gamma=1.0, learning_starts=10_000, exploration_initial_eps=1.0,
        exploration_final_eps=1.0, seed=0,
    )  # fmt: skip
    model.learn(400)
    assert model.policy.plan(model.replay_buffer, gamma=1.0, max_sweeps=10) <= 10
    psi = model.successor_features(all_observations())
    greedy = tuple(int(a) for a in (psi[:TERMINAL] @ np.asarray(w)).argmax(axis=1))
    assert float(np.asarray(w) @ psi[0, greedy[0]]) == pytest.approx(optimal_value(w), abs=1e-4)
    np.testing.assert_allclose(psi, successor_features(greedy), atol=1e-4)


def test_sfdqn_plans_every_planning_interval_and_learns_fig1_from_fewer_steps():
    steps, w = 60, [1.0, 0.0]
    kwargs = {**FIG1_TABULAR_KWARGS, "exploration_fraction": 1.0, "exploration_final_eps": 0.5, "seed": 0}
    planned = SFDQN("TabularPolicy", Fig1MOMDP(), weights=w, planning_sweeps=20, planning_interval=20, **kwargs)
    planned.learn(steps)
    assert planned._plannings == steps // 20
    psi = planned.successor_features(all_observations())
    assert float(np.asarray(w) @ psi[0].max(axis=0)) == pytest.approx(optimal_value(w), abs=1e-4)
    # Without planning the same steps leave the table short of the optimum.
    unplanned = SFDQN("TabularPolicy", Fig1MOMDP(), weights=w, **kwargs)
    unplanned.learn(steps)
    assert float((unplanned.successor_features(all_observations())[0] @ np.asarray(w)).max()) < optimal_value(w) - 1


@pytest.mark.parametrize(
    "policy, kwargs, message",
    [
        ("MlpPolicy", {"planning_sweeps": 5}, "needs TabularPolicy"),
        ("TabularPolicy", {"planning_sweeps": -1}, "planning_sweeps"),
        ("TabularPolicy", {"planning_sweeps": 5, "planning_interval": 0}, "planning_interval"),
    ],
)
def test_bad_planning_options_are_refused(policy, kwargs, message):
    with pytest.raises(ValueError, match=message):
        SFDQN(policy, Fig1MOMDP(one_hot=policy == "MlpPolicy"), **kwargs)


def test_stored_arrays_are_the_recorded_transitions():
    model = SFDQN("TabularPolicy", Fig1MOMDP(), learning_starts=10_000, exploration_initial_eps=1.0, seed=0)
    model.learn(40)
    obs, actions, next_obs, dones, rewards = model.replay_buffer.stored_arrays()
    assert len(actions) == 40
    np.testing.assert_array_equal(next_obs.reshape(-1), obs.reshape(-1) + 1)
    np.testing.assert_array_equal(dones, next_obs.reshape(-1) == N_STATES - 1)
    np.testing.assert_array_equal(rewards, REWARDS[obs.reshape(-1), actions])
