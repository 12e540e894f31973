"""SFDQN: learning on the paper's Fig. 1 MOMDP, the TD target, refusals and tie-breaking."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import BAD_WEIGHTS, FIG1_TABULAR_KWARGS, FIG1_TABULAR_STEPS
from gymnasium.wrappers import TimeLimit
from momdp import (
    N_STATES,
    REWARDS,
    Fig1MOMDP,
    all_observations,
    observation,
    optimal_policy,
    optimal_value,
    policy_of,
    policy_value,
    rollout_return,
    successor_features,
)
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

from sb3_sfgpi.common.vec_env import MODummyVecEnv, MOMonitor
from sb3_sfgpi.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.networks import argmax_random_ties


def greedy_policy(model: SFDQN, one_hot: bool = False, w=None) -> tuple[int, ...]:
    """The deterministic policy (one action per state) model.predict follows greedily."""
    return policy_of(lambda s: model.predict(observation(s, one_hot), deterministic=True, w=w)[0])


# --------------------------------------------------------------------------------------------------------------
# Learning
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("weights", [[1.0, 0.0], [0.0, 1.0]], ids=["w=(1,0)", "w=(0,1)"])
def test_tabular_sfdqn_learns_the_exact_optimum_on_fig1(make_tabular_sfdqn, weights):
    assert optimal_value([1, 0]) == 29.0 and optimal_value([0, 1]) == 30.0  # the numbers of Fig. 1
    model = make_tabular_sfdqn(weights)
    model.learn(FIG1_TABULAR_STEPS)

    policy = greedy_policy(model)
    value = policy_value(policy)
    assert np.dot(weights, value) == optimal_value(weights)
    # The same return when the greedy policy is rolled out in the env.
    np.testing.assert_allclose(rollout_return(lambda obs: model.predict(obs, deterministic=True)[0]), value)

    # ψ(s0, a*) is the value vector of the learned policy; ψ(s0, ·) and ψ(s, π(s)) are its exact SFs.
    psi, exact = model.successor_features(all_observations()), successor_features(policy)
    np.testing.assert_allclose(psi[0, policy[0]], value, atol=0.05)
    np.testing.assert_allclose(psi[0], exact[0], atol=0.05)
    on_policy = np.arange(4), np.array(policy)
    np.testing.assert_allclose(psi[on_policy], exact[on_policy], atol=0.05)
    if weights == [1.0, 0.0]:  # the optimum is unique for w = (1, 0): ψ(s0, a*) = (29, 24)
        assert policy == optimal_policy(weights) == (1, 0, 1, 1)
        np.testing.assert_allclose(psi[0, policy[0]], [29.0, 24.0], atol=0.05)


def test_mlp_sfdqn_learns_fig1_with_one_hot_observations():
    model = SFDQN(
        "MlpPolicy",
        Fig1MOMDP(one_hot=True),
        weights=[1.0, 0.0],
        learning_rate=5e-3,
        gamma=1.0,
        batch_size=32,
        train_freq=2,
        learning_starts=100,
        target_update_interval=100,
        exploration_fraction=0.5,
        exploration_final_eps=0.05,
        buffer_size=5_000,
        policy_kwargs=dict(net_arch=[32]),
        seed=0,
    )
    model.learn(1_500)
    policy = greedy_policy(model, one_hot=True)
    assert policy_value(policy)[0] >= 29.0 - 1e-6  # the optimum; the next best policy returns 28
    psi = model.successor_features(observation(0, one_hot=True))[0]
    np.testing.assert_allclose(psi[policy[0]], [29.0, 24.0], atol=0.5)


def test_tabular_sfdqn_learns_with_two_envs():
    venv = MODummyVecEnv([lambda: MOMonitor(Fig1MOMDP()), lambda: MOMonitor(Fig1MOMDP())])
    model = SFDQN("TabularPolicy", venv, weights=[1.0, 0.0], seed=0, **FIG1_TABULAR_KWARGS)
    assert model.n_envs == 2 and model.replay_buffer.rewards.shape[1:] == (2, 2)
    model.learn(FIG1_TABULAR_STEPS)
    assert policy_value(greedy_policy(model))[0] == 29.0
    assert len(model.ep_info_buffer) > 0 and all(info["l"] == 4 for info in model.ep_info_buffer)


def test_optimize_memory_usage_samples_and_learns(make_tabular_sfdqn):
    # A buffer smaller than the run, so that it wraps around.
    model = make_tabular_sfdqn([1.0, 0.0], optimize_memory_usage=True, buffer_size=64)
    assert model.replay_buffer.optimize_memory_usage and not hasattr(model.replay_buffer, "next_observations")
    model.learn(FIG1_TABULAR_STEPS)
    assert model.replay_buffer.full
    assert np.dot([1, 0], policy_value(greedy_policy(model))) == 29.0

    samples = model.replay_buffer.sample(256)
    assert samples.rewards.shape == (256, 2)
    assert samples.dones.shape == (256, 1)
    obs = samples.observations.flatten().long().numpy()
    next_obs = samples.next_observations.flatten().long().numpy()
    actions = samples.actions.flatten().long().numpy()
    dones = samples.dones.flatten().numpy()
    np.testing.assert_array_equal(samples.rewards.numpy(), REWARDS[obs, actions])
    np.testing.assert_array_equal(dones, obs == 3)  # only the last transition terminates
    # With one array for obs and next_obs, a non-terminal next observation must still be the true one.
    np.testing.assert_array_equal(next_obs[dones == 0], obs[dones == 0] + 1)


# --------------------------------------------------------------------------------------------------------------
# The TD target, by hand
# --------------------------------------------------------------------------------------------------------------


def fill_table(net, seed: int) -> np.ndarray:
    size = (net.table.n_rows, net.table.width)
    table = np.random.default_rng(seed).uniform(-2.0, 5.0, size=size).astype(np.float32)
    net.table.set_dense(table)
    return table.reshape(N_STATES, 3, 2).astype(np.float64)


@pytest.mark.parametrize(
    "done, truncated, bootstraps",
    [(False, False, True), (True, False, False), (True, True, True)],
    ids=["mid-episode", "terminated", "time-limit-truncated"],
)
@pytest.mark.parametrize("target_network", [False, True], ids=["no-target-net", "target-net"])
def test_one_train_step_is_the_tabular_sf_update(
    make_tabular_sfdqn, silent_logger, done, truncated, bootstraps, target_network
):
    w, alpha, gamma = np.array([0.3, 0.7]), 0.25, 0.9
    model = make_tabular_sfdqn(w, learning_rate=alpha, gamma=gamma, policy_kwargs=dict(target_network=target_network))
    model.set_logger(silent_logger)
    online = fill_table(model.policy.sf_net, seed=1)
    target = fill_table(model.policy.sf_net_target, seed=2) if target_network else online
    assert (model.policy.sf_net_target is model.policy.sf_net) != target_network

    s, a, s_next, r = 1, 2, 2, REWARDS[1, 2]
    info = {"TimeLimit.truncated": True} if truncated else {}
    model.replay_buffer.add(
        np.array([s]), np.array([s_next]), np.array([[a]]), r[None], np.array([done], dtype=np.float32), [info]
    )
    model.train(gradient_steps=1, batch_size=1)

    a_star = int(np.argmax(online[s_next] @ w))  # the online table picks the next action ...
    expected_target = r + (gamma * target[s_next, a_star] if bootstraps else 0.0)  # ... the target table values it
    expected = online.copy()
    expected[s, a] += alpha * (expected_target - online[s, a])
    learned = model.policy.sf_net.table.dense().reshape(N_STATES, 3, 2)
    np.testing.assert_allclose(learned, expected, rtol=1e-5, atol=1e-5)
    if target_network:  # train() never writes the target table
        np.testing.assert_array_equal(model.policy.sf_net_target.table.dense().reshape(N_STATES, 3, 2), target)


def test_a_lin_learning_rate_falls_linearly_to_zero_over_learn(make_tabular_sfdqn):
    """``learning_rate="lin_X"`` (RL Zoo's notation): the rate the updates use is X times the progress remaining."""
    rates = []

    class Record(BaseCallback):
        def _on_step(self) -> bool:
            rates.append((self.model._current_progress_remaining, self.model.policy.optimizer.param_groups[0]["lr"]))
            return True

    model = make_tabular_sfdqn(learning_rate="lin_0.4", learning_starts=0)
    model.learn(200, callback=Record())
    progress, lr = np.array(rates).T
    np.testing.assert_allclose(lr, 0.4 * progress, atol=1e-12)
    assert lr[0] == pytest.approx(0.4) and lr[-1] == pytest.approx(0.4 / 200)  # from X to 0 over the 200 steps


def test_time_limit_truncation_is_stored_as_a_bootstrapping_transition():
    model = SFDQN(
        "TabularPolicy", TimeLimit(Fig1MOMDP(), max_episode_steps=2), weights=[0.5, 0.5], learning_starts=1_000, seed=0
    )
    model.learn(10)  # episodes s0 → s1 → s2, cut by the time limit
    buffer = model.replay_buffer
    n = buffer.pos
    assert n >= 10 and n % 2 == 0
    np.testing.assert_array_equal(buffer.observations[:n, 0, 0], [0, 1] * (n // 2))
    np.testing.assert_array_equal(buffer.dones[:n, 0], [0, 1] * (n // 2))
    np.testing.assert_array_equal(buffer.timeouts[:n, 0], [0, 1] * (n // 2))
    samples = buffer.sample(64)
    assert samples.dones.sum() == 0  # truncation is not termination
    np.testing.assert_array_equal(samples.next_observations.flatten(), samples.observations.flatten() + 1)


# --------------------------------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------------------------------


def test_refuses_a_scalar_reward_env():
    with pytest.raises(ValueError, match="scalar rewards"):
        SFDQN("MlpPolicy", gym.make("CartPole-v1"))


def test_refuses_n_step_returns(make_fig1_env):
    with pytest.raises(ValueError, match="n_steps"):
        SFDQN("TabularPolicy", make_fig1_env(), n_steps=2)


def test_refuses_sb3_replay_buffer(make_fig1_env):
    with pytest.raises(ValueError, match="MOReplayBuffer"):
        SFDQN("TabularPolicy", make_fig1_env(), replay_buffer_class=ReplayBuffer)


def test_refuses_reward_normalisation(make_fig1_env):
    venv = VecNormalize(MODummyVecEnv([lambda: MOMonitor(make_fig1_env(one_hot=True))]), norm_reward=True)
    with pytest.raises(ValueError, match="norm_reward"):
        SFDQN("MlpPolicy", venv)
    # Observation normalisation alone is fine.
    venv = VecNormalize(MODummyVecEnv([lambda: MOMonitor(make_fig1_env(one_hot=True))]), norm_reward=False)
    assert SFDQN("MlpPolicy", venv).reward_dim == 2


def test_refuses_sb3_dummy_vec_env_and_vec_monitor(make_fig1_env):
    with pytest.raises(ValueError, match="DummyVecEnv"):
        SFDQN("TabularPolicy", DummyVecEnv([make_fig1_env]))
    with pytest.raises(ValueError, match="VecMonitor"):
        SFDQN("TabularPolicy", VecMonitor(MODummyVecEnv([make_fig1_env])))


@pytest.mark.parametrize("weights, message", BAD_WEIGHTS)
def test_bad_weights_are_refused_everywhere(make_fig1_env, weights, message):
    with pytest.raises(ValueError, match=message):
        SFDQN("TabularPolicy", make_fig1_env(), weights=weights)
    model = SFDQN("TabularPolicy", make_fig1_env(), weights=[0.25, 0.75])
    with pytest.raises(ValueError, match=message):
        model.set_weights(weights)
    np.testing.assert_array_equal(model.weights, [0.25, 0.75])  # unchanged by the refused call
    with pytest.raises(ValueError, match=message):
        model.predict(0, deterministic=True, w=weights)
    model.exploration_rate = 1.0  # an exploratory action must not skip the check
    with pytest.raises(ValueError, match=message):
        model.predict(0, deterministic=False, w=weights)


def test_weights_are_normalised_and_predict_w_overrides(make_tabular_sfdqn):
    model = make_tabular_sfdqn([2.0, 6.0])
    np.testing.assert_allclose(model.weights, [0.25, 0.75])
    np.testing.assert_allclose(model.policy.weights.numpy(), [0.25, 0.75])
    model.policy.sf_net.table.set_dense(successor_features((1, 0, 1, 1)).reshape(N_STATES, -1))
    # ψ(s0, ·) = (22, 24), (29, 24), (22, 20): B for w = (1, 0); A and B tie for w = (0, 1), ties go to A.
    assert model.predict(0, deterministic=True, w=[1, 0])[0] == 1
    assert model.predict(0, deterministic=True, w=[0, 1])[0] == 0
    np.testing.assert_array_equal(model.predict(np.arange(4), deterministic=True, w=[1, 0])[0], [1, 0, 1, 1])


@pytest.mark.parametrize("policy", ["TabularPolicy", "MlpPolicy"])
def test_the_behaviour_policy_breaks_ties_at_random_the_learned_policy_does_not(make_fig1_env, policy):
    model = SFDQN(policy, make_fig1_env(), weights=[0.0, 1.0], seed=0)
    with th.no_grad():  # ψ(s0, ·) = (22, 24), (29, 24), (22, 20): A and B tie for w = (0, 1), C is worse
        for parameter in model.policy.sf_net.parameters():
            parameter.zero_()
        if policy == "TabularPolicy":
            model.policy.sf_net.table.set_dense(successor_features((1, 0, 1, 1)).reshape(N_STATES, -1))
        else:  # a constant network: the last layer's bias alone
            model.policy.sf_net.sf_net[-1].bias.copy_(th.as_tensor(successor_features((1, 0, 1, 1))[0].reshape(-1)))
    model.exploration_rate = 0.0  # no ε-step: every action below is a greedy one
    behaviour = [int(model.predict(0, deterministic=False)[0]) for _ in range(200)]
    assert set(behaviour) == {0, 1} and 60 < behaviour.count(0) < 140  # uniform over the tied A and B, never C
    assert {int(model.predict(0, deterministic=True)[0]) for _ in range(20)} == {0}  # the learned policy: the first
    np.random.seed(7)
    first = [int(model.predict(0)[0]) for _ in range(20)]
    np.random.seed(7)
    assert [int(model.predict(0)[0]) for _ in range(20)] == first  # the draws come from the seeded numpy.random


def test_argmax_random_ties_is_uniform_over_the_tied_actions_and_draws_nothing_without_ties():
    q = np.array([[1.0, 3.0, 2.0], [0.0, -1.0, 5.0]])
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    np.testing.assert_array_equal(argmax_random_ties(q, rng), [1, 2])
    assert rng.bit_generator.state == state  # no ties: no random numbers used
    tied = np.array([[2.0, 2.0, 1.0, 2.0]] * 3000)
    counts = np.bincount(argmax_random_ties(tied, rng), minlength=4)
    assert counts[2] == 0 and all(900 < c < 1100 for c in counts[[0, 1, 3]])
