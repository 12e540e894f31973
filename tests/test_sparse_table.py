"""Tables that hold their stored rows (issue 48, memory): every row reads what a dense table would, to the last bit,
and a table, its copies and its files cost the rows it stored, not the size of the observation space."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy
from sb3_sfgpi.tabular import sparse
from sb3_sfgpi.tabular.sparse import INITIAL_CAPACITY, SparseTable

#: 13 x 13 cells and 6 flags: 10,816 rows, of which a test visits a few hundred
SPACE = spaces.MultiDiscrete([13, 13, 2, 2, 2, 2, 2, 2])
N_ACTIONS, REWARD_DIM = 4, 3


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 1.25]))
def test_a_sparse_table_reads_every_row_as_the_dense_table_it_stands_for(seed, default):
    rng = np.random.default_rng(seed)
    n_rows, width = 500, 6
    table, dense = SparseTable(n_rows, width, default), np.full((n_rows, width), default, dtype=np.float32)
    for _ in range(int(rng.integers(1, 12))):
        rows = rng.integers(0, n_rows, int(rng.integers(1, 3 * INITIAL_CAPACITY)))  # repeats; enough to grow
        if rng.random() < 0.1:
            value = float(rng.normal())
            table.fill(value)
            dense[:] = value
        slots = table.store(rows)
        np.testing.assert_array_equal(table.values[slots], dense[rows])  # stored rows start as the default row
        values = rng.normal(size=(len(rows), width)).astype(np.float32)
        np.add.at(table.values, slots, values)
        np.add.at(dense, rows, values)
        read = rng.integers(0, n_rows, 50)
        np.testing.assert_array_equal(table.values[table.slots(read)], dense[read])  # one fancy index, -1: default
    np.testing.assert_array_equal(table.dense(), dense)
    assert len(table) == len(np.unique(table.stored_rows())) <= n_rows
    np.testing.assert_array_equal(copy.deepcopy(table).dense(), dense)


def filled_buffer(rng: np.random.Generator, n: int) -> MOReplayBuffer:
    """``n`` random transitions between a few hundred of the space's observations."""
    buffer = MOReplayBuffer(n, SPACE, spaces.Discrete(N_ACTIONS), device="cpu", reward_dim=REWARD_DIM)
    visited = np.stack([SPACE.sample() for _ in range(300)])
    for _ in range(n):
        obs, next_obs = visited[rng.integers(len(visited), size=2)]
        reward = rng.integers(0, 2, (1, REWARD_DIM)).astype(np.float32)
        buffer.add(obs[None], next_obs[None], rng.integers(N_ACTIONS, size=(1, 1)), reward, rng.random(1) < 0.1, [{}])
    return buffer


def dense_td_update(table: np.ndarray, batch: tuple, alpha: float, gamma: float, weights: np.ndarray) -> None:
    """The TD update on a dense table (one row per ``(state, action)``), as it was before tables became sparse."""
    rows, actions, next_rows, dones, rewards = batch
    next_flat = next_rows * N_ACTIONS + weighted_sum(
        table.reshape(-1, N_ACTIONS, REWARD_DIM)[next_rows], weights
    ).argmax(1)
    target = rewards + ((1 - dones) * gamma)[:, None] * table[next_flat]
    flat = rows * N_ACTIONS + actions.astype(np.int64)
    np.add.at(table, flat, alpha * (target - table[flat]))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 1.25]))
def test_td_updates_and_planning_give_the_dense_tables_numbers_and_store_visited_rows_only(seed, optimism):
    rng = np.random.default_rng(seed)
    SPACE.seed(seed)
    buffer = filled_buffer(rng, 400)
    policy = TabularPolicy(SPACE, spaces.Discrete(N_ACTIONS), lambda _: 0.3, REWARD_DIM)
    policy.weights.copy_(policy.weights.new_tensor(rng.dirichlet(np.ones(REWARD_DIM))))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sparse, "INITIAL_CAPACITY", 8)  # the table grows during the updates
        policy.fill(optimism)
    net, weights = policy.sf_net, policy.weights.numpy()
    dense = np.full((net.table.n_rows * N_ACTIONS, REWARD_DIM), optimism, dtype=np.float32)
    for step in range(30):
        np.random.seed(seed % 2**31 + step)
        policy.td_update(buffer, 16, 0.9, 10.0)
        np.random.seed(seed % 2**31 + step)  # the same batch again, for the dense update
        obs, actions, next_obs, dones, rewards, _ = buffer.sample_arrays(16)
        dense_td_update(dense, (net.rows(obs), actions, net.rows(next_obs), dones, rewards), 0.3, 0.9, weights)
        np.testing.assert_array_equal(net.table.dense().reshape(dense.shape), dense)
    obs, _, next_obs, _, _ = buffer.stored_arrays()
    visited = set(net.rows(obs).tolist()) | set(net.rows(next_obs).tolist())
    policy.plan(buffer, 0.9, 5, untried_value=0.0)
    assert set(net.table.stored_rows().tolist()) <= visited  # memory follows the visited rows, not the space
    every_row = net.table.dense()
    np.testing.assert_array_equal(every_row[sorted(set(range(net.table.n_rows)) - visited)], 0.0)  # settled: 0


def test_a_policy_set_copies_and_saves_the_stored_rows_only(tmp_path):
    rng = np.random.default_rng(0)
    SPACE.seed(0)
    policy = TabularPolicy(SPACE, spaces.Discrete(N_ACTIONS), lambda _: 0.3, REWARD_DIM)
    policy.fill(1.25)
    buffer = filled_buffer(rng, 200)
    for _ in range(50):
        policy.td_update(buffer, 16, 0.9, 10.0)
    stored = len(policy.sf_net.table)
    assert 0 < stored <= 300 and len(policy.sf_net.table.values) > stored + 1  # room to grow
    policy_set = GPIPolicy()
    policy_set.add(policy.sf_net, weights=[1.0, 1.0, 1.0])
    copied = policy_set.networks[0].table
    assert copied.values.shape == (stored + 1, N_ACTIONS * REWARD_DIM) and copied._slot is None  # built when read
    policy_set.save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set")
    assert len(loaded.networks[0].table) == stored
    observations = np.stack([SPACE.sample() for _ in range(200)])
    for w in ([1.0, 0.0, 0.0], [0.2, 0.3, 0.5]):
        expected = policy.q_values(observations, np.asarray(w) / np.sum(w))[0]
        np.testing.assert_array_equal(loaded.q_values(observations, w), expected)
    assert loaded.networks[0].table._slot is None  # GPI's stack read the stored rows: no slot map per copy
