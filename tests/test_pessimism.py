"""Pessimistic successor features (``n_critics`` heads, ψ their element-wise minimum): the network, the TD update,
learning, and saving and loading."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from conftest import random_mlp_network
from hypothesis import given, settings
from hypothesis import strategies as st
from momdp import Fig1MOMDP, all_observations, observation, policy_of, policy_value

from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.policy_files import CorruptPolicySetError
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.networks import scalarize


def test_psi_is_the_elementwise_minimum_of_the_heads():
    net = random_mlp_network(0, n_critics=3)
    obs = th.rand(16, 4) * 2 - 1
    heads = net.forward_heads(obs)
    assert heads.shape == (3, 16, 3, 3)
    assert not th.equal(heads[0], heads[1])  # separately initialised heads
    th.testing.assert_close(net(obs), heads.min(dim=0).values, rtol=0, atol=0)


def test_one_critic_keeps_the_state_dict_of_earlier_versions():
    one = random_mlp_network(0)
    assert list(one.state_dict()) == [f"sf_net.{i}.{p}" for i in (0, 2, 4) for p in ("weight", "bias")]
    obs = th.rand(5, 4)
    th.testing.assert_close(one(obs), one.forward_heads(obs)[0], rtol=0, atol=0)
    two = random_mlp_network(0, n_critics=2)
    assert len(two.state_dict()) == 2 * len(one.state_dict())


@pytest.mark.parametrize("n_critics", [0, 17, 1.0, "2", True])
def test_a_bad_number_of_critics_is_refused(n_critics):
    with pytest.raises(ValueError, match="n_critics must be an integer in"):
        random_mlp_network(0, n_critics=n_critics)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**16), n_critics=st.integers(2, 4), raw=st.lists(st.floats(0, 1), min_size=3, max_size=3))
def test_every_simplex_weight_values_the_minimum_no_higher_than_any_head(seed, n_critics, raw):
    """``w · ψ_min <= w · ψ_k`` for every head ``k`` and every ``w >= 0``: GPI's value of a policy is pessimistic."""
    w = th.tensor(raw, dtype=th.float32) + 1e-3
    w = w / w.sum()
    net = random_mlp_network(seed, n_critics=n_critics)
    obs = th.rand(8, 4, generator=th.Generator().manual_seed(seed)) * 2 - 1
    pessimistic = scalarize(net(obs), w)
    for head in net.forward_heads(obs):
        assert bool((pessimistic <= scalarize(head, w) + 1e-6).all())


def two_critic_model(**kwargs) -> SFDQN:
    options = dict(
        weights=[1.0, 0.0], learning_rate=5e-3, gamma=1.0, batch_size=32, train_freq=2, learning_starts=100,
        target_update_interval=100, exploration_fraction=0.5, exploration_final_eps=0.05, buffer_size=5_000,
        policy_kwargs=dict(net_arch=[32], n_critics=2), seed=0,
    )  # fmt: skip
    return SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True), **{**options, **kwargs})


def test_every_head_moves_toward_the_one_pessimistic_target():
    model = two_critic_model(learning_starts=0)
    model.learn(64)  # fills the buffer (and trains a little)
    policy = model.policy
    with th.no_grad():  # make the heads and the target network differ
        for parameter in policy.sf_net_target.other_critics.parameters():
            parameter.add_(0.3)
    np.random.seed(5)
    batch = model.replay_buffer.sample(model.batch_size)
    with th.no_grad():
        online_next = policy.sf_net(batch.next_observations)  # the heads' minimum
        a_star = scalarize(online_next, policy.weights).argmax(dim=1)
        target_heads = policy.sf_net_target.forward_heads(batch.next_observations)
        rows = th.arange(len(a_star))
        next_psi = target_heads[:, rows, a_star].min(dim=0).values
        target = batch.rewards + (1 - batch.dones) * model.gamma * next_psi
        heads = policy.sf_net.forward_heads(batch.observations)[:, rows, batch.actions.long().flatten()]
        expected = sum(th.nn.functional.smooth_l1_loss(head, target) for head in heads)
    np.random.seed(5)
    loss = policy.td_update(model.replay_buffer, model.batch_size, model.gamma, model.max_grad_norm)
    assert loss == pytest.approx(float(expected), rel=1e-6)


def test_two_critics_learn_the_optimum_and_its_successor_features_on_fig1():
    model = two_critic_model()
    model.learn(1_500)
    policy = policy_of(lambda s: model.predict(observation(s, one_hot=True), deterministic=True)[0])
    assert policy_value(policy)[0] >= 29.0 - 1e-6  # the optimum; the next best policy returns 28
    # on the data both heads learn the same targets: the minimum is the policy's SFs, not an underestimate
    start = th.as_tensor(observation(0, one_hot=True), dtype=th.float32, device=model.device)[None]
    for head in model.policy.sf_net.forward_heads(start).detach().cpu().numpy():
        np.testing.assert_allclose(head[0, policy[0]], [29.0, 24.0], atol=0.5)


def test_sfdqn_with_two_critics_saves_and_loads(tmp_path):
    model = two_critic_model(learning_starts=0)
    model.learn(50)
    model.save(tmp_path / "model.zip")
    loaded = SFDQN.load(tmp_path / "model.zip")
    assert loaded.policy.sf_net.n_critics == 2
    observations = all_observations(one_hot=True)
    np.testing.assert_array_equal(loaded.successor_features(observations), model.successor_features(observations))


@pytest.mark.parametrize(
    "n_critics, message",
    [
        ("2", "n_critics must be an integer in"),
        (0, "n_critics must be an integer in"),
        (True, "n_critics must be an integer in"),
        (1, "Unexpected key"),  # the files hold two heads
    ],
)
def test_a_manifest_with_a_wrong_number_of_critics_is_refused(tmp_path, n_critics, message):
    policy_set = GPIPolicy()
    policy_set.add(random_mlp_network(0, n_critics=2), weights=[1.0, 0.0, 0.0])
    policy_set.save(tmp_path / "set")
    manifest_file = tmp_path / "set" / "manifest.json"
    manifest = json.loads(manifest_file.read_text())
    assert manifest["network"]["n_critics"] == 2
    manifest["network"]["n_critics"] = n_critics
    manifest_file.write_text(json.dumps(manifest))
    with pytest.raises(CorruptPolicySetError, match=message):
        GPIPolicy.load(tmp_path / "set")
