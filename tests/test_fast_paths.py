"""The fast paths give the same results as the straightforward code they replace (no timing here: see benchmarks/).

* GPI: the stacked tabular gather and the stacked MLP layers equal the generic ``vmap`` path, the stacked
  weight-conditioned members equal it bit for bit;
* replay sampling: one ``take`` per array equals indexing with (transition, env) index pairs, with the same random
  numbers drawn;
* ``set_training_mode``: the same ``training`` flags as ``Module.train``;
* ``SFDQN._store_transition`` stores what SB3's stores and leaves the new observation untouched.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import Fig1MOMDP
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

from sb3_sfgpi.common import checks
from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.common.checks import step_is_sound
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork
from sb3_sfgpi.stacking import StackedConditioned, StackedMLP, StackedTables, StackedVmap

# --------------------------------------------------------------------------------------------------------------
# GPI
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mlp", "tabular"])
def test_stacked_gpi_paths_equal_the_vmap_path(kind, make_random_mlp, make_random_tabular):
    make = make_random_mlp if kind == "mlp" else make_random_tabular
    policy_set = GPIPolicy()
    for seed in range(6):
        policy_set.add(make(seed), weights=[1.0, 1.0, 1.0])
    space = policy_set.observation_space
    space.seed(3)
    observations = np.stack([space.sample() for _ in range(17)])
    obs_tensor, _ = policy_set._obs_to_tensor(observations)
    assert isinstance(policy_set._stack(), StackedTables if kind == "tabular" else StackedMLP)
    reference = policy_set._psi_each(obs_tensor)
    np.testing.assert_allclose(policy_set.successor_features(observations), reference.numpy(), rtol=1e-6, atol=1e-6)
    for w in ([1.0, 0.0, 0.0], [0.2, 0.3, 0.5]):
        weights = th.as_tensor(np.asarray(w) / np.sum(w), dtype=th.float32)
        q = th.amax(reference @ weights, dim=0).numpy()
        np.testing.assert_allclose(policy_set.q_values(observations, w), q, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(policy_set.predict(observations, w)[0], q.argmax(axis=1))
    # Adding a policy restacks.
    policy_set.add(make(99), weights=[1.0, 0.0, 0.0])
    assert policy_set.successor_features(observations).shape[0] == 7


def _conditioned_member(seed: int, obs_dim: int, n_actions: int, net_arch: list[int], n_heads: int) -> nn.Module:
    """A conditioned network with every parameter moved off its initial values, bound to Dirichlet(1) weights."""
    th.manual_seed(seed)
    space = spaces.Box(-1.0, 1.0, shape=(obs_dim,), dtype=np.float32)
    extractor = FlattenExtractor(space)
    net = ConditionedSFNetwork(
        space, spaces.Discrete(n_actions), extractor, extractor.features_dim, 3, net_arch=net_arch, n_heads=n_heads
    )
    with th.no_grad():
        for parameter in net.parameters():  # layer normalisations' scales and shifts too
            parameter.add_(0.3 * th.randn_like(parameter))
    return net.bound_to(np.random.default_rng(seed).dirichlet(np.ones(3)))


@settings(max_examples=25, deadline=None)
@given(
    n_members=st.integers(1, 12),
    batch=st.sampled_from([1, 2, 3, 17, 52]),
    net_arch=st.sampled_from([[16], [64, 64, 64], [32, 8]]),
    n_heads=st.integers(1, 3),
    obs_dim=st.integers(1, 8),
    seed=st.integers(0, 10_000),
)
def test_stacked_conditioned_members_equal_the_vmap_path_bit_for_bit(
    n_members, batch, net_arch, n_heads, obs_dim, seed
):
    members = [_conditioned_member(seed + i, obs_dim, 4, net_arch, n_heads) for i in range(n_members)]
    assert StackedConditioned.supports(members[0])
    obs = th.as_tensor(np.random.default_rng(seed).uniform(-1, 1, (batch, obs_dim)).astype(np.float32))
    with th.no_grad():
        stacked, reference = StackedConditioned(members).psi(obs), StackedVmap(members).psi(obs)
    assert stacked.shape == (n_members, batch, 4, 3)
    assert th.equal(stacked, reference)  # the same bits: GPI's decisions and a run's numbers do not move


def test_a_set_of_conditioned_members_is_stacked_and_odd_ones_use_vmap():
    policy_set = GPIPolicy()
    for seed in range(3):
        policy_set.add(_conditioned_member(seed, 5, 4, [16, 16], 2), weights=[1.0, 0.0, 0.0])
    assert isinstance(policy_set._stack(), StackedConditioned)
    odd = _conditioned_member(7, 5, 4, [16, 16], 2)
    odd.sf_net[1].layers[1] = nn.LayerNorm(16, elementwise_affine=False)
    assert not StackedConditioned.supports(odd)
    odd_set = GPIPolicy()
    odd_set.add(odd, weights=[0.0, 1.0, 0.0])
    assert isinstance(odd_set._stack(), StackedVmap)


def test_weights_are_validated_on_every_call_even_when_cached(make_random_tabular):
    policy_set = GPIPolicy()
    policy_set.add(make_random_tabular(0), weights=[1.0, 1.0, 1.0])
    observation = policy_set.observation_space.sample()
    w = np.array([0.2, 0.3, 0.5])
    first = policy_set.predict(observation, w)[0]
    assert policy_set.predict(observation, w)[0] == first
    w[0] = -1.0  # the same array object, now invalid
    with pytest.raises(ValueError, match="non-negative"):
        policy_set.predict(observation, w)


def test_tabular_gpi_refuses_observations_outside_the_table(make_random_tabular):
    policy_set = GPIPolicy()
    policy_set.add(make_random_tabular(0), weights=[1.0, 1.0, 1.0])  # MultiDiscrete([3, 4, 2])
    with pytest.raises(ValueError, match=r"observation \[3, 3, 1\] is outside the observation space"):
        policy_set.predict(np.array([3, 3, 1]), [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"observation \[-1, 0, 0\] is outside the observation space"):
        policy_set.predict(np.array([-1, 0, 0]), [1.0, 0.0, 0.0])


def test_networks_the_stacked_mlp_does_not_know_use_vmap(make_random_mlp):
    odd = make_random_mlp(0)
    odd.sf_net = nn.Sequential(odd.sf_net[0], nn.Softplus(), *list(odd.sf_net)[2:])
    assert not StackedMLP.supports(odd)
    policy_set = GPIPolicy()
    policy_set.add(odd, weights=[1.0, 0.0, 0.0])
    observations = np.random.default_rng(0).uniform(-1, 1, size=(5, 4)).astype(np.float32)
    assert isinstance(policy_set._stack(), StackedVmap)
    with th.no_grad():
        expected = odd(th.as_tensor(observations)).numpy()
    np.testing.assert_allclose(policy_set.successor_features(observations)[0], expected, rtol=1e-6, atol=1e-6)


# --------------------------------------------------------------------------------------------------------------
# Replay sampling
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n_envs", [1, 3])
@pytest.mark.parametrize("optimize_memory_usage", [False, True])
def test_sampled_arrays_equal_two_index_reads_with_the_same_random_numbers(n_envs, optimize_memory_usage):
    buffer = MOReplayBuffer(
        50, spaces.Box(0, 1, (4,)), spaces.Discrete(3), "cpu", n_envs, optimize_memory_usage, reward_dim=2
    )
    rng = np.random.default_rng(0)
    for _ in range(80):  # wraps around
        buffer.add(
            rng.random((n_envs, 4)).astype(np.float32),
            rng.random((n_envs, 4)).astype(np.float32),
            rng.integers(0, 3, (n_envs,)),
            rng.random((n_envs, 2)).astype(np.float32),
            rng.random(n_envs) < 0.2,
            [{"TimeLimit.truncated": bool(rng.random() < 0.5)} for _ in range(n_envs)],
        )
    np.random.seed(1)
    inds = buffer._sample_indices(64)
    found = buffer._arrays(inds)
    after = np.random.random()
    np.random.seed(1)
    inds = buffer._sample_indices(64)
    envs = np.random.randint(0, high=n_envs, size=(64,))
    size = buffer.buffer_size  # SB3 divides the size by n_envs
    source = buffer.observations[(inds + 1) % size] if optimize_memory_usage else buffer.next_observations[inds]
    expected = (
        buffer.observations[inds, envs, :],
        buffer.actions[inds, envs, :],
        source[np.arange(64), envs, :],
        buffer.dones[inds, envs] * (1 - buffer.timeouts[inds, envs]),
        buffer.rewards[inds, envs, :],
    )
    assert np.random.random() == after  # the same random numbers were drawn
    assert found[5] is None  # no masks stored: none sampled
    for array, reference in zip(found[:5], expected, strict=True):
        assert array.dtype == reference.dtype
        np.testing.assert_array_equal(array, reference)


# --------------------------------------------------------------------------------------------------------------
# Policies and SFDQN
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("policy", ["MlpPolicy", "TabularPolicy"])
def test_set_training_mode_sets_the_flags_module_train_sets(policy):
    model = SFDQN(policy, Fig1MOMDP(), seed=0, learning_starts=0)
    reference = copy.deepcopy(model.policy)
    for mode in (True, False, False, True, False):
        model.policy.set_training_mode(mode)
        reference.sf_net.train(mode)
        reference.training = mode
        flags = [m.training for m in model.policy.modules()]
        assert flags == [m.training for m in reference.modules()]


def test_set_training_mode_calls_overridden_train_methods():
    calls = []

    class Recording(nn.Identity):
        def train(self, mode: bool = True):
            calls.append(mode)
            return super().train(mode)

    model = SFDQN("MlpPolicy", Fig1MOMDP(), seed=0)
    model.policy.sf_net.sf_net.append(Recording())
    model.policy.__dict__.pop("_mode_modules", None)  # a network changed after its first use: start afresh
    for mode in (False, True, True, False):
        model.policy.set_training_mode(mode)
    assert calls == [False, True, False]  # a call that changes nothing is skipped


def test_store_transition_stores_what_sb3_stores():
    ours = SFDQN("TabularPolicy", Fig1MOMDP(), seed=0, learning_starts=0, buffer_size=100)
    sb3 = copy.deepcopy(ours)
    for model in (ours, sb3):  # the same first step: the behaviour policy draws its tie-breaks from numpy.random
        np.random.seed(0)
        model.learn(1)
    rng = np.random.default_rng(0)
    for step in range(30):
        new_obs = rng.integers(0, 4, size=(1, *ours.observation_space.shape))
        done = np.array([step % 7 == 6])
        infos = [{"terminal_observation": np.array(3), "TimeLimit.truncated": False} if done[0] else {}]
        action, reward = np.array([[step % 3]]), rng.random((1, 2)).astype(np.float32)
        kept = new_obs.copy()
        ours._store_transition(ours.replay_buffer, action, new_obs, reward, done, infos)
        OffPolicyAlgorithm._store_transition(sb3, sb3.replay_buffer, action, new_obs.copy(), reward, done, infos)
        np.testing.assert_array_equal(new_obs, kept)  # not modified
        assert ours._last_obs is new_obs
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_array_equal(getattr(ours.replay_buffer, name), getattr(sb3.replay_buffer, name))


class _Spaces:
    """An env as the step check reads it: each agent's reward space."""

    def reward_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1, 1, shape=(2,))


_VALUES = st.sampled_from([0.0, 1.5, -3.0, 1e308, np.nan, np.inf, -np.inf])
_AGENTS = st.sets(st.sampled_from(["a", "b", "c"]))
_REWARDS = st.builds(np.array, st.lists(_VALUES, min_size=1, max_size=3), st.sampled_from([np.float32, np.float64]))
_OBSERVATIONS = st.one_of(
    st.just(np.arange(3)), st.builds(lambda x: np.array([1.0, x]), _VALUES), st.just([0.5, 1.0]), st.just(7)
)


@st.composite
def _step_results(draw):
    """Results of a step, each possibly with agents missing or extra, non-finite or malformed values."""
    acted = draw(_AGENTS.filter(bool))

    def entries(values):
        keys = draw(_AGENTS) if draw(st.integers(0, 5)) == 0 else acted
        return {agent: draw(values) for agent in keys}

    results = (entries(_OBSERVATIONS), entries(_REWARDS), entries(st.just(False)), entries(st.just(False)))
    return acted, results, draw(_AGENTS) if draw(st.booleans()) else acted


@settings(max_examples=300, deadline=None)
@given(_step_results())
def test_the_quick_step_check_passes_only_what_the_full_check_passes(results):
    """Issue 59: the step check's quick path (``step_is_sound``) may send a sound step to the full check, never pass
    a step that the full check refuses (an unknown or missing agent, NaN or inf, a reward of another shape)."""
    acted, (observations, rewards, terminations, truncations), agents = results
    env = _Spaces()
    if step_is_sound(env, acted, observations, rewards, terminations, truncations, agents):
        full = checks._detailed_step_check
        full(env, 0, acted, (observations, rewards, terminations, truncations), agents, 1)  # raises nothing
