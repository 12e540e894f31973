"""The compiled tabular TD update and read (issue 59) against numpy's: the same table and values, bit for bit,
from the same random draws, for every kind of buffer and table; and machine code without fused multiply-adds (a fused
``a · b + c`` rounds once, numpy's twice: other bits on other CPUs)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from llvmlite import binding as llvm
from numba import njit

from sb3_sfgpi.common.action_masks import masked
from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.sfdqn.networks import argmax_random_ties
from sb3_sfgpi.sfdqn.policies import SFDQNPolicy
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy
from sb3_sfgpi.tabular import kernels
from sb3_sfgpi.tabular.network import TabularSFNetwork
from sb3_sfgpi.tabular.numpy_random import global_stream

OBSERVATION_SPACES = [spaces.Discrete(7, start=-2), spaces.MultiDiscrete([3, 4], start=[1, -1]), spaces.MultiBinary(3)]


def numpy_update(policy: TabularPolicy, buffer: MOReplayBuffer, batch_size: int, gamma: float) -> np.ndarray:
    """The update as numpy did it before it was compiled (``TabularPolicy._backup`` of commit 5fa6c10)."""
    obs, actions, next_obs, dones, rewards, next_masks = buffer.sample_arrays(batch_size)
    lr = policy.optimizer.param_groups[0]["lr"]
    net, target_net, n_actions = policy.sf_net, policy.sf_net_target, policy.sf_net.n_actions
    slots = net.table.store(net.rows(obs, check=False))
    next_rows = net.rows(next_obs, check=False)
    entries, next_first = net.table.values.reshape(-1, net.reward_dim), net.table.slots(next_rows) * n_actions
    psi = entries.reshape(-1, n_actions, entries.shape[1])[next_first // n_actions]
    next_flat = next_first + masked(weighted_sum(psi, policy.weights.numpy()), next_masks).argmax(axis=1)
    if target_net is net:
        next_psi = entries[next_flat]
    else:
        target_entries = target_net.table.values.reshape(-1, net.reward_dim)
        next_psi = target_entries[target_net.table.slots(next_rows) * n_actions + next_flat - next_first]
    target_psi = rewards + ((1 - dones) * gamma)[:, None] * next_psi
    flat = slots * n_actions + actions.astype(np.int64, copy=False)
    td_error = target_psi - entries[flat]
    np.add.at(entries, flat, lr * td_error)
    return td_error


def learner(space: spaces.Space, seed: int, target_network: bool, lr: float) -> TabularPolicy:
    """A tabular policy of 4 actions and 3 objectives whose tables hold a few rows of values that round."""
    policy = TabularPolicy(space, spaces.Discrete(4), lambda _: lr, 3, target_network=target_network)
    rng = np.random.default_rng(seed)
    policy.weights.copy_(torch_weights(rng))
    for net in {id(policy.sf_net): policy.sf_net, id(policy.sf_net_target): policy.sf_net_target}.values():
        rows = np.unique(rng.integers(0, net.table.n_rows, 3))
        values = rng.choice(np.float32([0, 0.1, 1 / 3, -2.5, 7e-3, 123.456]), size=(len(rows), net.table.width))
        net.table.set_rows(rows, values, net.table.default.copy())
    return policy


def torch_weights(rng: np.random.Generator) -> th.Tensor:
    w = rng.dirichlet(np.ones(3)).astype(np.float32)
    w[rng.integers(3)] = 0.0 if rng.random() < 0.3 else w[0]
    return th.from_numpy(w)


def filled_buffer(space: spaces.Space, seed: int, n_envs: int, compact: bool, masks: bool) -> MOReplayBuffer:
    buffer = MOReplayBuffer(64, space, spaces.Discrete(4), n_envs=n_envs, optimize_memory_usage=compact, reward_dim=3)
    space.seed(seed)
    rng = np.random.default_rng(seed)
    for _ in range(90):  # wraps around
        obs = np.stack([space.sample() for _ in range(n_envs)])
        infos = [
            {
                "action_mask": (rng.random(4) < 0.6) | (np.arange(4) == rng.integers(4)),
                "TimeLimit.truncated": bool(rng.random() < 0.3),
            }
            if masks
            else {}
            for _ in range(n_envs)
        ]
        buffer.add(
            obs, np.stack([space.sample() for _ in range(n_envs)]), rng.integers(0, 4, (n_envs, 1)),
            rng.standard_normal((n_envs, 3)).astype(np.float32), rng.random(n_envs) < 0.2, infos,
        )  # fmt: skip
    return buffer


@settings(max_examples=60, deadline=None)
@given(
    space=st.sampled_from(OBSERVATION_SPACES),
    seed=st.integers(0, 2**32 - 1),
    target_network=st.booleans(),
    n_envs=st.sampled_from([1, 2]),
    compact=st.booleans(),
    masks=st.booleans(),
    gamma=st.sampled_from([0.9, 0.99, 1.0]),
    lr=st.sampled_from([0.1, 0.5, 1e-3]),
)
def test_the_compiled_td_update_leaves_the_bits_numpy_leaves(
    space, seed, target_network, n_envs, compact, masks, gamma, lr
):
    buffer = filled_buffer(space, seed, n_envs, compact, masks)
    ours, theirs = learner(space, seed, target_network, lr), learner(space, seed, target_network, lr)
    for update in range(3):  # the tables grow: rows not stored yet are stored first
        np.random.seed(seed % 1000 + update)
        expected = numpy_update(theirs, buffer, 32, gamma)
        np.random.seed(seed % 1000 + update)
        loss = ours.td_update(buffer, 32, gamma, 10.0)
        assert loss == float(0.5 * np.square(expected).sum())
        for mine, reference in ((ours.sf_net, theirs.sf_net), (ours.sf_net_target, theirs.sf_net_target)):
            np.testing.assert_array_equal(mine.table.stored_rows(), reference.table.stored_rows())
            np.testing.assert_array_equal(mine.table.dense().view(np.uint32), reference.table.dense().view(np.uint32))


def test_an_update_that_overflows_stores_no_inf_and_says_so():
    space = spaces.Discrete(3)
    policy, buffer = learner(space, 0, False, 1.0), filled_buffer(space, 0, 1, False, False)
    buffer.rewards[:] = 3e38
    with pytest.raises(ValueError, match="the tabular TD update diverged"):
        for _ in range(10):
            policy.td_update(buffer, 32, 0.99, 10.0)
    assert np.isfinite(policy.sf_net.table.dense()).all()


@settings(max_examples=60, deadline=None)
@given(
    space=st.sampled_from(OBSERVATION_SPACES),
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from(["int64", "int8", "float32"]),
)
def test_the_compiled_read_of_the_table_gives_the_bits_numpy_gives(space, seed, dtype):
    policy = learner(space, seed, False, 0.1)
    space.seed(seed)
    obs = np.stack([space.sample() for _ in range(5)]).astype(dtype)
    net = policy.sf_net
    psi = net.table.values.reshape(-1, net.n_actions, net.reward_dim)[net.table.slots(net.rows(obs))]
    expected = weighted_sum(psi, policy.weights.numpy())
    values, vectorized = policy.q_values(obs, policy.weights.numpy())
    assert vectorized
    np.testing.assert_array_equal(values.view(np.uint32), expected.view(np.uint32))


@pytest.mark.parametrize("observation", [[4, 0], [0, 0], [1, 3], [1.5, 0], [np.nan, 0], [1e30, 0], [-0.5, 0], [1, -2]])
def test_an_observation_outside_the_space_is_refused_by_the_compiled_read(observation):
    policy = learner(spaces.MultiDiscrete([3, 4], start=[1, -1]), 0, False, 0.1)  # components 1..3 and -1..2
    with pytest.raises(ValueError, match=r"outside the observation space"):
        policy.q_values(np.array([[2, 0], observation]), policy.weights.numpy())


def test_the_compiled_read_takes_one_weight_vector():
    policy = learner(OBSERVATION_SPACES[0], 0, False, 0.1)
    with pytest.raises(ValueError, match=r"weights of shape \(3,\)"):
        policy.q_values(np.array([0, 1]), np.ones((2, 3)) / 3)


@pytest.mark.parametrize(
    "kernel",
    [
        "sampled_td_update",
        "greedy_action",
        "table_row",
        "action_values",
        "epsilon_greedy",
        "planning_sweeps",
        "gpi_attaining",
    ],
)
def test_the_compiled_kernels_have_no_fused_multiply_add(kernel):
    compiled = getattr(kernels, kernel)
    if not compiled.signatures:  # compiled on first use: use it once
        policy, space = learner(OBSERVATION_SPACES[0], 0, False, 0.1), OBSERVATION_SPACES[0]
        buffer = filled_buffer(space, 0, 1, False, False)
        policy.td_update(buffer, 32, 0.9, 10.0)
        policy.q_values(np.array([0, 1]), policy.weights.numpy())
        policy.masked_actions(np.array([0, 1]), policy.weights.numpy(), None, 0.0)
        policy.plan(buffer, 0.9, 2)
        policy_set = GPIPolicy()
        policy_set.add(policy.sf_net, weights=policy.weights.numpy())
        policy_set.predict_attaining(np.array([0, 1]), [0.5, 0.2, 0.3])
    assert_no_fused_multiply_add(compiled)


def assert_no_fused_multiply_add(compiled) -> None:
    """No FMA in the machine code of any signature of a compiled function: the code this process compiled, or where
    it loaded the function from numba's cache (which keeps no machine code to show), the function compiled afresh."""
    assert compiled.signatures
    for signature in compiled.signatures:
        assembly = compiled.inspect_asm(signature)
        if len(assembly) < 1_000:  # a line saying the code came from the cache
            assembly = njit(signature, cache=False)(compiled.py_func).inspect_asm(signature)
        assert len(assembly) > 1_000 and "fma" not in assembly.lower()


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(
        st.lists(st.sampled_from([0.0, -0.0, 1.0, 2.0, np.inf, -np.inf, np.nan]), min_size=1, max_size=5),
        min_size=1,
        max_size=4,
    ),
    seed=st.integers(0, 2**32 - 1),
)
def test_compiled_ties_are_broken_as_numpy_breaks_them(values, seed):
    """The compiled greedy choice, ties broken on numpy's global generator, is ``argmax_random_ties``'s: the same
    actions and draws, with NaN, infinities and signed zeros among the values."""
    width = max(len(row) for row in values)
    q = np.array([(row * width)[:width] for row in values], dtype=np.float32)
    saved = np.random.get_state()
    np.random.seed(seed)
    expected, after = argmax_random_ties(q), np.random.get_state()
    np.random.seed(seed)
    actions = np.empty(len(q), dtype=np.int64)
    kernels._greedy_random_ties(q, *global_stream(), actions)
    state = np.random.get_state()
    np.random.set_state(saved)
    np.testing.assert_array_equal(actions, expected)
    assert state[2] == after[2] and np.array_equal(state[1], after[1])


def _multiply_add(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    for i in range(len(a)):
        c[i] = a[i] * b[i] + c[i]


@pytest.mark.skipif("fma" not in llvm.get_host_cpu_features().flatten(), reason="this CPU has no FMA instruction")
def test_the_fused_multiply_add_check_finds_one_where_fast_math_allows_it():
    signature = "void(float64[::1], float64[::1], float64[::1])"
    assert_no_fused_multiply_add(njit(signature, cache=False)(_multiply_add))
    with pytest.raises(AssertionError):
        assert_no_fused_multiply_add(njit(signature, cache=False, fastmath=True)(_multiply_add))


@settings(max_examples=40, deadline=None)
@given(
    n_envs=st.integers(1, 3),
    optimize_memory_usage=st.booleans(),
    n_steps=st.integers(1, 45),
    batch_size=st.integers(1, 70),
    seed=st.integers(0, 2**32 - 1),
)
def test_compiled_minibatch_rows_are_the_buffers_draws(n_envs, optimize_memory_usage, n_steps, batch_size, seed):
    """The compiled sampler draws the rows numpy's ``sample_rows`` draws and leaves numpy's generator as it does, for
    buffers of one or several envs, with one shared observation array or two, before and after they wrap around."""
    buffer = MOReplayBuffer(
        20, spaces.Discrete(5), spaces.Discrete(2), "cpu", n_envs, optimize_memory_usage, reward_dim=2
    )
    rng = np.random.default_rng(seed)
    for _ in range(n_steps):
        buffer.add(*rng.integers(0, 5, (2, n_envs, 1)), rng.integers(0, 2, n_envs), rng.random((n_envs, 2)),
                   rng.random(n_envs) < 0.2, [{}] * n_envs)  # fmt: skip
    if buffer.valid_positions()[1] <= buffer.valid_positions()[0]:
        return  # nothing to sample yet (one shared array keeps its newest transition out)
    saved = np.random.get_state()
    np.random.seed(seed)
    flat = buffer.sample_rows(batch_size)
    expected, after = (flat, buffer.next_rows(flat)), np.random.get_state()
    np.random.seed(seed)
    rows = TabularPolicy.minibatch_rows(buffer, batch_size)
    state = np.random.get_state()
    np.random.set_state(saved)
    np.testing.assert_array_equal(rows[0], expected[0])
    np.testing.assert_array_equal(rows[1], expected[1])
    assert state[2] == after[2] and np.array_equal(state[1], after[1])


@settings(max_examples=80, deadline=None)
@given(
    space=st.sampled_from(OBSERVATION_SPACES),
    seed=st.integers(0, 2**32 - 1),
    batch=st.integers(0, 6),
    exploration_rate=st.sampled_from([0.0, 0.05, 0.5, 1.0]),
    with_masks=st.booleans(),
)
def test_the_compiled_epsilon_greedy_takes_numpys_actions_with_numpys_draws(
    space, seed, batch, exploration_rate, with_masks
):
    """The same actions as numpy's ``SFDQNPolicy.masked_actions`` and the same state of numpy's generator left, with
    ties (most observations read the default row: every action ties), masks and one observation or a batch."""
    policy = learner(space, seed, False, 0.1)
    rng = np.random.default_rng(seed)
    space.seed(seed)
    observations = np.stack([space.sample() for _ in range(max(batch, 1))])
    observation = observations if batch else observations[0]  # batch 0: one observation, not a batch
    masks = None
    if with_masks:
        masks = rng.random((len(observations), 4)) < 0.5
        masks[np.arange(len(observations)), rng.integers(0, 4, len(observations))] = True  # each has an action
    saved, outcomes = np.random.get_state(), []
    for act in (policy.masked_actions, functools.partial(SFDQNPolicy.masked_actions, policy)):  # compiled, numpy's
        np.random.seed(seed)
        policy.action_space.seed(seed)
        actions, vectorized = act(observation, policy.weights.numpy(), masks, exploration_rate)
        state = np.random.get_state()
        outcomes.append((actions.tolist(), vectorized, state[2], state[1].tobytes()))
    np.random.set_state(saved)
    assert outcomes[0] == outcomes[1]


def test_an_observation_outside_the_space_is_refused_by_the_compiled_epsilon_greedy():
    policy = learner(spaces.MultiDiscrete([3, 4], start=[1, -1]), 0, False, 0.1)
    with pytest.raises(ValueError, match=r"observation \[4, 0\] is outside the observation space"):
        policy.masked_actions(np.array([[2, 0], [4, 0]]), policy.weights.numpy(), None, 0.0)


VALUES = st.sampled_from([0.0, -0.0, 1.0, 2.0, -1.0, np.inf, -np.inf, np.nan])


@settings(max_examples=80, deadline=None)
@given(n_policies=st.integers(1, 4), reward_dim=st.integers(1, 3), per_row=st.booleans(), data=st.data())
def test_compiled_gpi_decisions_and_members_followed_are_numpys(n_policies, reward_dim, per_row, data):
    """GPI over CPU tables acts and traces the members it follows in one compiled call: the same actions and members
    as the numpy path of other sets (here: the same tables as a view without one more member), with ties, signed
    zeros, infinities and NaN among the values, per-row weights, a member left out per row, and action masks."""
    nvec, n_actions = (3, 2), 3
    tables = []
    for _ in range(n_policies + 1):
        net = TabularSFNetwork(spaces.MultiDiscrete(nvec), spaces.Discrete(n_actions), reward_dim)
        width = n_actions * reward_dim
        values = data.draw(st.lists(VALUES, min_size=6 * width, max_size=6 * width))
        net.table.set_dense(np.array(values, dtype=np.float32).reshape(6, width))
        tables.append(net)
    compiled = GPIPolicy()
    for net in tables[:-1]:
        compiled.add(net, weights=np.ones(reward_dim))
    extended = compiled.subset(range(n_policies))
    extended.add(tables[-1], weights=np.ones(reward_dim))
    numpy_path = extended.without(n_policies)  # a view: the numpy arithmetic over the same tables
    batch = data.draw(st.integers(1, 6))
    obs = np.array(data.draw(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 1)), min_size=batch, max_size=batch)))
    weight = st.lists(st.integers(0, 3), min_size=reward_dim, max_size=reward_dim).filter(any)
    w = np.array(data.draw(st.lists(weight, min_size=batch, max_size=batch) if per_row else weight), dtype=np.float64)
    left_out = np.array(data.draw(st.lists(st.integers(-1, n_policies - 1), min_size=batch, max_size=batch)))
    mask = st.lists(st.booleans(), min_size=n_actions, max_size=n_actions).filter(any)
    masks = np.array(data.draw(st.lists(mask, min_size=batch, max_size=batch)))
    for options in ({}, {"left_out": left_out}, {"action_masks": masks}, {"left_out": left_out, "action_masks": masks}):
        actions, attaining = compiled.predict_attaining(obs, w, per_row=per_row, **options)
        expected_actions, expected_attaining = numpy_path.predict_attaining(obs, w, per_row=per_row, **options)
        np.testing.assert_array_equal(actions, expected_actions)
        np.testing.assert_array_equal(attaining, expected_attaining)
